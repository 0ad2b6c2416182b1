"""Fixtures of the interactive environment's tests: a converted tiny scene, built once per session."""

from __future__ import annotations

import pytest

from tests.fixtures.converted import converted_folder


@pytest.fixture(scope="session")
def converted(tmp_path_factory):
    """(folder, synthetic scene): the tiny scene of seed 3 (a box, a fruit, a can) as converted."""
    return converted_folder(tmp_path_factory.mktemp("converted"))
