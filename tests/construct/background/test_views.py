"""Crop rendering: host padding equals the renderer's, batched crops equal crops rendered one by
one, and subsets of new sizes compile no new programs."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from phirie_jax.compile_count import CompileCount
from phirie_jax.construct.background.views import (
    CropJob,
    CropRenderer,
    _fill_rows,
    _pad_rows,
    baked,
    colourless,
    make_crop,
    padded,
    pass_bucket,
)
from phirie_jax.render import pad_gaussians
from phirie_jax.types import GaussianSplatData
from tests.construct.background import scene as toy

BATCH_TOL = 1e-5  # batched (vmapped) vs one-by-one renders: the same kernel, at most float rounding apart
BAKED_TOL = 1e-5  # a colour baked on the host (float64) vs the kernel's SH evaluation (float32)


@pytest.fixture(scope="module")
def toy_data():
    data = toy._cat([toy._gaussians(*toy._sphere_points(c, r, 0.006, np.random.default_rng(k)), toy.COLOURS[k],
                                    0.005) for k, (c, r) in toy.SPHERES.items()])
    return data, toy.cameras()


def _dc_only(data: GaussianSplatData) -> GaussianSplatData:
    return dataclasses.replace(data, sh=data.sh[:, :1].copy())


def test_host_padding_equals_the_renderers():
    data = toy._gaussians(np.arange(15.0).reshape(5, 3), np.tile([0.0, 0, 1], (5, 1)), (0.2, 0.4, 0.6), 0.01)
    host = padded(data, 256)
    device = pad_gaussians(data.to_kernel(), 256)
    for field in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(host[field], np.asarray(getattr(device, field)), err_msg=field)
    with pytest.raises(ValueError, match="do not fit"):
        padded(data, 4)
    assert padded(_dc_only(data), 256, sh_coeffs=16)["sh"][:, 1:].max() == 0.0


def test_batched_crops_equal_crops_rendered_one_by_one(toy_data):
    data, cams = toy_data
    rng = np.random.default_rng(1)
    jobs = []
    for k, cam in enumerate(cams[:5]):
        crop = make_crop(cam, k, np.array([10 + 3 * k, 8, 70, 60]), (64,), 4)
        index = np.sort(rng.choice(data.num, size=300 + 97 * k, replace=False))
        features = rng.uniform(0, 1, (len(index), 1 + k % 2)).astype(np.float32)
        source = _dc_only(data) if k == 2 else data  # SH of one coefficient beside full SH: one program
        jobs.append(CropJob(source, crop, index, features, None if k == 3 else rng.uniform(0, 1, 3)))
    pad = pass_bucket([j.num for j in jobs])
    batched = CropRenderer().render_many(jobs, pad)
    alone = CropRenderer()
    for job, image in zip(jobs, batched):
        ref = alone.render(job.gaussians(), job.crop, pad, job.features, background=job.background)
        for field in ("rgb", "alpha", "depth", "features"):
            np.testing.assert_allclose(getattr(image, field), getattr(ref, field), atol=BATCH_TOL, err_msg=field)
        np.testing.assert_allclose(image.depth_normalized, ref.depth_normalized, atol=BATCH_TOL)
        assert image.alpha.max() > 0.1, "the crop sees its Gaussians"


def test_subsets_of_one_set_gathered_on_the_device_equal_subsets_packed_on_the_host(toy_data):
    data, cams = toy_data
    rng = np.random.default_rng(4)
    crops = [make_crop(cam, k, np.array([10 + 2 * k, 8, 70, 60]), (64,), 4) for k, cam in enumerate(cams[:5])]
    indices = [np.sort(rng.choice(data.num, size=250 + 61 * k, replace=False)) for k in range(5)]
    pad = pass_bucket([len(i) for i in indices])
    gathering = CropRenderer()
    shared = gathering.render_many([CropJob(data, c, i) for c, i in zip(crops, indices)], pad)
    assert gathering._uploaded is not None and gathering._uploaded[0] is data     # the device path ran
    packing = CropRenderer()   # a separate copy per job: packed on the host
    packed = packing.render_many([CropJob(data.subset(i), c) for c, i in zip(crops, indices)], pad)
    assert packing._uploaded is None
    for a, b in zip(shared, packed):
        for field in ("rgb", "alpha", "depth", "features"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    assert max(image.alpha.max() for image in shared) > 0.1, "the crops see their Gaussians"


def test_subsets_of_new_sizes_compile_no_new_programs(toy_data):
    data, cams = toy_data
    crop = make_crop(cams[0], 0, np.array([10, 8, 70, 60]), (64,), 4)
    renderer = CropRenderer()
    renderer.render_many([CropJob(data, crop, np.arange(200))], 2048)   # compiles this pass's programs
    renderer.render(data.subset(np.arange(210)), crop, 2048)
    with CompileCount() as compiles:
        for n in (333, 517, 1024, 1301):
            renderer.render(data.subset(np.arange(n)), crop, 2048, features=np.ones((n, 1), np.float32))
            renderer.render_many([CropJob(data, crop, np.arange(n - 7))], 2048)
    assert compiles.count == 0, f"{compiles.count} programs compiled for subsets of new sizes"


def test_a_batch_of_crops_of_different_sizes_is_refused(toy_data):
    data, cams = toy_data
    small = make_crop(cams[0], 0, np.array([10, 8, 20, 20]), (32,), 4)
    large = make_crop(cams[0], 0, np.array([10, 8, 20, 20]), (64,), 4)
    with pytest.raises(ValueError, match="one size"):
        CropRenderer().render_many([CropJob(data, small), CropJob(data, large)], pass_bucket([data.num]))


def test_compile_count_sees_a_new_program():
    with CompileCount() as compiles:
        jnp.arange(7919.0).sum().block_until_ready()   # a shape no other test uses
    assert compiles.count >= 1 and compiles.seconds > 0


def _view_dependent(data: GaussianSplatData, seed: int = 5) -> GaussianSplatData:
    sh = data.sh.copy()
    sh[:, 1:] = np.random.default_rng(seed).normal(0, 0.15, sh[:, 1:].shape)
    return dataclasses.replace(data, sh=sh)


def test_colourless_and_baked_passes_equal_the_full_sh_renders(toy_data):
    """A pass without colour renders alpha, depth and features bit for bit as with the full SH; a
    layer with its colour baked for the camera renders its colour within float rounding."""
    data, cams = toy_data
    data = _view_dependent(data)
    index = np.arange(0, data.num, 2)
    feats = np.random.default_rng(2).uniform(0, 1, (len(index), 1)).astype(np.float32)
    crops = [make_crop(cam, k, np.array([10, 8, 70, 60]), (64,), 4) for k, cam in enumerate(cams[:3])]
    pad = pass_bucket([len(index)])
    renderer = CropRenderer()
    full = renderer.render_many([CropJob(data, c, index, feats) for c in crops], pad)
    dark = renderer.render_many([CropJob(colourless(data), c, index, feats) for c in crops], pad)
    lit = renderer.render_many([CropJob(baked(data, index, c.camera), c) for c in crops], pad)
    dc_only = renderer.render_many([CropJob(_dc_only(data), c, index) for c in crops], pad)
    assert max(np.abs(f.rgb - d.rgb).max() for f, d in zip(full, dc_only)) > 0.05, "the SH shows (else no test)"
    for f, d, b in zip(full, dark, lit):
        for field in ("alpha", "depth", "features"):
            np.testing.assert_array_equal(getattr(d, field), getattr(f, field), err_msg=field)
        np.testing.assert_allclose(b.rgb, f.rgb, atol=BAKED_TOL)


def test_batch_rows_equal_the_host_padding(toy_data):
    data, _ = toy_data
    index = np.array([5, 1, 9, 200])
    rows = _pad_rows(2, 256, 16)
    _fill_rows(rows, 1, _dc_only(data), index)
    ref = padded(_dc_only(data).subset(index), 256, sh_coeffs=16)
    for field, value in ref.items():
        np.testing.assert_array_equal(rows[field][1], value, err_msg=field)
        np.testing.assert_array_equal(rows[field][0], padded(data.subset(np.zeros(0, np.int64)), 256, 16)[field])
