"""A tilted, scaled (×3.7), shifted copy of a synthetic tabletop converts to the same scene as the
original when given the scale: the same objects accepted and stable, the same shapes in the
same places (up to the yaw and shift the frame leaves free), a background that looks the same."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from kernels.image_metrics import psnr
from phirie_jax.frame.config import FrameConfig
from phirie_jax.frame.resolve import world_camera
from phirie_jax.geometry import split_sim3
from phirie_jax.io.mesh import load_trimesh
from phirie_jax.io.ply import read_gaussian_ply
from phirie_jax.io.scene import load_scene
from phirie_jax.pipeline import run_convert
from phirie_jax.render import render
from tests.frame.conftest import UNITS_PER_METRE, WORLD_TO_CAPTURE

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    from phirie_jax.synthetic import synthesize
    from phirie_jax.synthetic.reframe import reframe_scene

    root = tmp_path_factory.mktemp("convert_in_frame")
    synthesize(root / "scene", preset="tiny", seed=3)
    reframe_scene(root / "scene", root / "tilted", WORLD_TO_CAPTURE)
    original = run_convert(root / "scene", root / "out", masks="files")
    tilted = run_convert(root / "tilted", root / "out_tilted", masks="files",
                         frame=FrameConfig(scale=1 / UNITS_PER_METRE))
    return root, original, tilted


def test_same_objects_same_verdicts_same_shapes_in_place(converted):
    root, original, tilted = converted
    assert tilted["frame"]["scale_source"] == "given (--scale)"
    # the original's world → the tilted copy's world: a yaw and a shift (scale 1)
    between = np.asarray(tilted["frame"]["capture_to_world"]) @ WORLD_TO_CAPTURE
    scale, rotation, _ = split_sim3(between)
    assert scale == pytest.approx(1.0, rel=1e-6) and rotation[2, 2] == pytest.approx(1.0, abs=1e-4)
    first = {o["id"]: o for o in original["objects"]}
    second = {o["id"]: o for o in tilted["objects"]}
    assert {i: o["status"] for i, o in first.items()} == {i: o["status"] for i, o in second.items()}
    for ident, obj in first.items():
        if obj["status"] != "accepted":
            continue
        assert obj["drop_test"]["stable"] == second[ident]["drop_test"]["stable"]
        # the placed shapes coincide (a pose alone may differ by a symmetry of the shape)
        a = placed_surface(root / "out", obj, between)
        b = placed_surface(root / "out_tilted", second[ident], np.eye(4))
        gap = 0.5 * (cKDTree(a).query(b)[0].mean() + cKDTree(b).query(a)[0].mean())
        assert gap < 0.005, (ident, gap)


def placed_surface(out, obj: dict, world: np.ndarray) -> np.ndarray:
    """(2000, 3) samples of an object's mesh placed by its pose, then by ``world`` (4, 4)."""
    mesh = load_trimesh(out / obj["mesh"])
    mesh.apply_transform(world @ np.asarray(obj["pose"]))
    return mesh.sample(2000, seed=0)


def test_background_looks_the_same(converted):
    root, original, tilted = converted
    photos = load_scene(root / "scene")
    cameras = json.loads((root / "out_tilted" / "transforms.json").read_text())["frames"]
    assert len(cameras) == len(photos.cameras)
    world = load_scene(root / "tilted")

    first = read_gaussian_ply(root / "out" / original["background"]["path"]).to_kernel()
    second = read_gaussian_ply(root / "out_tilted" / tilted["background"]["path"]).to_kernel()
    frame = np.asarray(tilted["frame"]["capture_to_world"])
    for view in range(0, len(photos.cameras), 3):
        photo = cv2.cvtColor(cv2.imread(str(photos.cameras[view].image_path)), cv2.COLOR_BGR2RGB) / 255.0
        a = psnr(np.asarray(render(first, photos.cameras[view]).rgb), photo)
        b = psnr(np.asarray(render(second, world_camera(world.cameras[view], frame)).rgb), photo)
        assert abs(float(a) - float(b)) < 0.5, (view, float(a), float(b))
