"""Shared fixtures of the capture tests: one set of rendered photos for the session."""

from __future__ import annotations

import pytest

from tests.capture.photos import render_photos


@pytest.fixture(scope="session")
def arc_photos(tmp_path_factory):
    """12 photos (320×240) of the tiny synthetic scene on a 110° arc, and their true cameras."""
    folder = tmp_path_factory.mktemp("arc") / "photos"
    folder.mkdir()
    return folder, render_photos(folder)
