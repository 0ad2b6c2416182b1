"""MuJoCo Warp's splat renderer against ours (experiments.bench_mjwarp_splats) runs end to end on the
CPU at a tiny size and draws the same scene: cameras placed as ours, splats moved with the bodies."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("mujoco_warp", reason="MuJoCo Warp not installed (pip install 'phirie_jax[warp]')")

SAME_SCENE_PSNR = 15.0   # dB, world 0 against our render at 64×48 (a camera off by a pixel or a mirrored
                         # axis drops it to about 10; the two methods' footprints differ at edges)


@pytest.mark.slow  # 18 s on 2 cores (MuJoCo Warp's kernels and our render compiled); the camera test below stays
def test_bench_reports_both_renderers_and_the_same_image(converted, tmp_path):
    from experiments import bench_mjwarp_splats

    out = tmp_path / "bench.json"
    bench_mjwarp_splats.main([str(converted[0]), "--worlds", "2", "--cameras", "1", "--width", "64",
                              "--steps", "4", "--repeats", "1", "--out", str(out)])
    result = json.loads(out.read_text())
    assert result["image"] == [64, 48] and result["frames"] == 2 and result["overflow_worlds"] == 0
    wheel, ours = result["mjwarp"], result["ours"]
    assert wheel["splats"] == 2 * (result["background_gaussians"] + result["object_gaussians"])
    assert wheel["frames_per_s"] > 0 and wheel["bvh_refit_ms"] > 0 and ours["frames_per_s"] > 0
    images = result["images_world0_camera0"]
    assert images["psnr_mjwarp_vs_ours"] > SAME_SCENE_PSNR
    assert images["psnr_mjwarp_vs_single_dc"] > SAME_SCENE_PSNR
    assert images["psnr_ours_vs_single"] > 40.0


def test_camera_model_casts_the_rays_of_our_cameras():
    """A splat on the optical axis of an off-centre, non-square pinhole lands on K's principal pixel,
    one to its right at +x in the camera's frame; splats follow placements of their body."""
    import mujoco
    import mujoco_warp as mjw

    from experiments.bench_mjwarp_splats import camera_model, psnr
    from phirie_jax.types import Camera

    K = np.array([[40.0, 0.0, 20.5], [0.0, 40.0, 12.5], [0.0, 0.0, 1.0]])
    w2c = np.eye(4)
    w2c[:3, :3] = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])   # looks along world +y, image y = world −z
    w2c[:3, 3] = [0.0, 0.0, 2.0]
    cam = Camera("a.png", K, w2c, 32, 24)
    model = camera_model([cam])
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    # two splats 2 m ahead: one on the axis (pixel (20, 12)), one 0.5 m to the camera's right (x += 10 px)
    c2w = cam.camera_to_world
    points = np.array([[0.0, 0.0, 2.0], [0.5, 0.0, 2.0]]) @ c2w[:3, :3].T + c2w[:3, 3]
    rc = mjw.create_render_context(model, nworld=1, cam_res=(32, 24), render_depth=False, render_seg=False,
                                   use_textures=False, use_shadows=False, background_color=(0, 0, 0, 1),
                                   splat_position=points.astype(np.float32),
                                   splat_rotation=np.tile([1.0, 0, 0, 0], (2, 1)).astype(np.float32),
                                   splat_scale=np.full((2, 3), 0.01, np.float32),
                                   splat_rgba=np.array([[1.0, 0, 0, 1], [0, 1.0, 0, 1]], np.float32))
    mjw.render(mjw.put_model(model), mjw.put_data(model, data), rc)
    packed = rc.rgb_data.numpy()[0].reshape(24, 32)
    red, green = (packed >> 16) & 0xFF, (packed >> 8) & 0xFF
    assert np.unravel_index(np.argmax(red), red.shape) == (12, 20)
    assert np.unravel_index(np.argmax(green), green.shape) == (12, 30)
    image = np.zeros((4, 4, 3), np.uint8)
    assert psnr(image, image) == 100.0 and 0 < psnr(image, image + 1) < 100.0
