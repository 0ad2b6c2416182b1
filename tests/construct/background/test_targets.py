"""Target pass: the removed-weight render of a frame needs only the Gaussians that share a tile
with a removed one and can sort before it (``removed_weight_subset``), and ``Footprints`` culls
as ``views.cull`` does."""

from __future__ import annotations

import numpy as np
import pytest

from phirie_jax.construct.background.targets import removed_weight_subset
from phirie_jax.construct.background.views import (
    CropJob,
    CropRenderer,
    Footprints,
    ViewProjection,
    cull,
    make_crop,
    pass_bucket,
)
from tests.construct.background import scene as toy

WEIGHT_TOL = 1e-5  # the subset's removed weight vs the full render's: the kernel's chunked sums, rounding apart
TILE = 16


@pytest.fixture(scope="module")
def scene():
    """An orange plane, the four toy spheres on and above it (removed: 1, 2 and 4) and a kept grey
    wall of blobs in front of sphere 1 from some cameras (it must stay: it hides part of sphere 1)."""
    rng = np.random.default_rng(3)
    xs = np.arange(-0.2, 0.2 + 1e-9, 0.008)
    xy = np.stack(np.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    plane = toy._gaussians(np.c_[xy, np.zeros(len(xy))], np.tile([0.0, 0, 1], (len(xy), 1)), toy.ORANGE, 0.007)
    parts, labels = [plane], [np.zeros(plane.num, np.int64)]
    for k, (c, r) in toy.SPHERES.items():
        pts, normals = toy._sphere_points(c, r, 0.006, rng)
        parts.append(toy._gaussians(pts, normals, toy.COLOURS[k], 0.005))
        labels.append(np.full(len(pts), k))
    wall = np.c_[np.full(40, -0.11), np.linspace(-0.08, 0.04, 40), rng.uniform(0.01, 0.06, 40)]
    parts.append(toy._gaussians(wall, np.tile([1.0, 0, 0], (40, 1)), (0.5, 0.5, 0.5), 0.008, opacity=0.6))
    labels.append(np.full(40, 10))
    data, labels = toy._cat(parts), np.concatenate(labels)
    return data, np.isin(labels, (1, 2, 4)), toy.cameras()


def test_footprints_cull_as_views_cull(scene):
    data, _, cams = scene
    footprints = Footprints.of(data)
    for cam in cams[:3]:
        idx, uv, z, r = footprints.cull(cam)
        np.testing.assert_array_equal(idx, cull(data, cam))
        assert uv.shape == (len(idx), 2) and z.shape == r.shape == (len(idx),)


def test_a_views_projection_culls_its_crops_as_culling_each_crop_does(scene):
    data, _, cams = scene
    footprints = Footprints.of(data)
    for view, cam in enumerate(cams[:3]):
        projection = ViewProjection.of(footprints, cam)
        for box, size in (([40, 20, 120, 100], 128), ([0, 0, 300, 260], 64), ([150, 90, 170, 110], 32)):
            crop = make_crop(cam, view, np.array(box), (size,), 2)
            idx, uv, z, r = projection.cull(crop.camera)
            np.testing.assert_array_equal(idx, cull(data, crop.camera))
            _, uv_each, z_each, r_each = footprints.cull(crop.camera)
            np.testing.assert_allclose(uv, uv_each, rtol=1e-12, atol=1e-9)
            np.testing.assert_allclose(r, r_each, rtol=1e-12)
            np.testing.assert_array_equal(z, z_each)


def test_the_removed_weight_of_the_subset_is_the_full_renders(scene):
    data, removed, cams = scene
    crops = CropRenderer()
    footprints = Footprints.of(data)
    full_jobs, sub_jobs, dropped = [], [], []
    for view, cam in enumerate(cams):
        crop = make_crop(cam, view, np.array([40, 20, 120, 100]), (128,), 8)
        idx, uv, z, r = footprints.cull(crop.camera)
        gone = removed[idx]
        keep = removed_weight_subset(gone, uv, z, r, crop.size, TILE)
        assert keep[gone].all()
        dropped.append(int((~keep).sum()))
        full_jobs.append(CropJob(data, crop, idx, gone[:, None].astype(np.float32)))
        sub_jobs.append(CropJob(data, crop, idx[keep], gone[keep, None].astype(np.float32)))
    pad = pass_bucket([j.num for j in full_jobs])
    full = crops.render_many(full_jobs, pad)
    sub = crops.render_many(sub_jobs, pad)
    assert sum(dropped) > 0.3 * sum(j.num for j in full_jobs)   # the plane behind the spheres goes
    for f, s in zip(full, sub):
        assert f.features[..., 0].max() > 0.5
        np.testing.assert_allclose(s.features[..., 0], f.features[..., 0], atol=WEIGHT_TOL)


def test_a_kept_gaussian_in_front_of_a_removed_one_stays():
    """Two discs on one pixel: kept in front of removed stays, kept behind it goes, and a kept one
    in another tile goes."""
    uv = np.array([[20.0, 20.0], [20.0, 20.0], [20.0, 20.0], [100.0, 100.0]])
    z = np.array([1.0, 0.9, 1.5, 0.5])
    r = np.full(4, 3.0)
    removed = np.array([True, False, False, False])
    np.testing.assert_array_equal(removed_weight_subset(removed, uv, z, r, 128, TILE), [True, True, False, False])
    # within the float32 slack behind it: kept (the device may sort it first)
    z[2] = 1.0 + 1e-6
    assert removed_weight_subset(removed, uv, z, r, 128, TILE)[2]
    assert not removed_weight_subset(np.zeros(4, bool), uv, z, r, 128, TILE).any()
