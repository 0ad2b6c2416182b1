"""One synthetic tabletop shared by the frame tests: the tiny preset with a 25 cm marker printed
on its table, and a copy of it in a tilted, scaled (×3.7), shifted frame (``WORLD_TO_CAPTURE``)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from phirie_jax.geometry import sim3_matrix

UNITS_PER_METRE = 3.7
TILT = Rotation.from_euler("xyz", [70, -20, 35], degrees=True).as_matrix()
WORLD_TO_CAPTURE = sim3_matrix(UNITS_PER_METRE, TILT, np.array([0.4, -1.2, 2.0]))
MARKER_SIDE = 0.25


@pytest.fixture(scope="session")
def tilted_tabletop(tmp_path_factory):
    """(the scene folder, its tilted copy)."""
    from phirie_jax.synthetic import synthesize
    from phirie_jax.synthetic.reframe import reframe_scene

    root = tmp_path_factory.mktemp("frame")
    synthesize(root / "scene", preset="tiny", seed=3, marker=MARKER_SIDE)
    reframe_scene(root / "scene", root / "tilted", WORLD_TO_CAPTURE)
    return root / "scene", root / "tilted"
