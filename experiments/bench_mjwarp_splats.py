"""MuJoCo Warp's own Gaussian-splat ray tracer against our batched rasterizer, same worlds and cameras; prints JSON.

``--worlds`` MuJoCo Warp worlds of a converted scene (``BatchedEnvironment(backend="warp")``), every
world but world 0 with its objects thrown (``bench_warp_worlds.throws``), stepped ``--steps`` steps,
then rendered from ``--cameras`` of the scene's cameras at ``--width`` (height by the cameras' aspect):

- ``mjwarp``: the wheel's renderer (``mujoco_warp.create_render_context`` + ``render``), the scene's
  Gaussians as its splats: colour the SH degree-0 colour max(SH_C0·c₀ + ½, 0), opacity
  sigmoid(logit), scale exp(log_scale), rotation wxyz. The wheel's splats are fixed world-space
  points: nothing attaches one to a body, and every world's rays query one group of the splat BVH
  (``splat_group_id``). So each world gets its own group, the static background copied into every
  group and the object Gaussians placed at that world's body poses (``transform_bodies`` in JAX, on
  the device); after a step they are written into the context's splat arrays and the BVH is refit
  (``bvh.refit_splat_bvh``, the wheel's own). The cameras are the scene's pinhole cameras as
  MuJoCo cameras (sensor size and intrinsics in pixels) of a render-only model holding nothing
  else, so no geom is traced; the background colour is black in both renderers.
- ``ours``: ``BatchedEnvironment.render(cameras, pixels="uint8")`` on the same worlds' placements.

Each side reports its set-up (context and BVH build / static views) and compile time (first call
minus the median of ``--repeats`` later calls) apart from the median run time and frames/s; the
wheel's side splits a frame batch into placing the splats, refitting the BVH and tracing. Images:
world 0, camera 0, PSNR (dB, uint8 images) of the wheel's frame against ours, against the single
``Environment.render`` of world 0's state (full SH), and against that render with the SH cut to
degree 0 (what the splats carry: what is left is the two methods' difference, ray-traced
3D-Gaussian maxima sorted per ray against projected 2D Gaussians sorted per Gaussian). Also the
wheel's limits as met here (``mjwarp.limits``).

``--constructor``: the splat BVH's builder. The wheel's ``create_render_context`` builds with
``"sah"``, which Warp runs on the host (bounds copied back, tree copied up); ``"lbvh"`` builds on
the GPU (a render context made with one splat, then its splat BVH rebuilt by the wheel's
``bvh.build_splat_bvh`` with that builder).

    python -m experiments.bench_mjwarp_splats OUT_DIR [--worlds 1024] [--cameras 4] [--width 640]
        [--steps 240] [--repeats 5] [--constructor sah|lbvh] [--out result.json]
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

CONSTRUCTORS = ("sah", "lbvh", "median")
PSNR_EQUAL = 100.0   # dB reported for equal images (JSON has no infinity)


def _say(message: str) -> None:
    print(f"bench_mjwarp_splats: {message}", file=sys.stderr, flush=True)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) of two uint8 images of the same shape (peak 255), at most ``PSNR_EQUAL`` (equal images)."""
    err = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return PSNR_EQUAL if err == 0 else round(min(PSNR_EQUAL, float(10.0 * np.log10(255.0 ** 2 / err))), 3)


def camera_model(cameras):
    """A MuJoCo model holding the given pinhole cameras and one speck of a geom (``phirie_jax.types.Camera``, OpenCV
    axes, all of one size): fixed world cameras (MuJoCo's axes: x right, y up, looking along −z) whose
    sensor is the image in pixels and whose intrinsics are K's focal lengths and principal point
    (as MuJoCo's offset from the sensor's centre, y up), so pixel (i, j)'s ray through its centre
    (i + ½, j + ½) is K's."""
    import mujoco

    spec = mujoco.MjSpec()
    # one speck far below everything: the wheel's ray caster needs a geom BVH (with none, its
    # megakernel reads an empty tree and crashes on the CPU); no ray comes near it
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[1e-3, 0, 0], pos=[0.0, 0.0, -1e4],
                            contype=0, conaffinity=0)
    flip = np.diag([1.0, -1.0, -1.0])
    for k, cam in enumerate(cameras):
        c2w = cam.camera_to_world
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, np.ascontiguousarray(c2w[:3, :3] @ flip).ravel())
        spec.worldbody.add_camera(name=f"view{k}", pos=c2w[:3, 3], quat=quat)
    model = spec.compile()
    for k, cam in enumerate(cameras):
        if abs(cam.K[0, 1]) > 1e-9:
            raise ValueError(f"camera {cam.name}: K has skew {cam.K[0, 1]} (MuJoCo cameras have none)")
        model.cam_resolution[k] = (cam.width, cam.height)
        model.cam_sensorsize[k] = (cam.width, cam.height)
        model.cam_intrinsic[k] = (cam.K[0, 0], cam.K[1, 1], 0.5 * cam.width - cam.K[0, 2],
                                  0.5 * cam.height - cam.K[1, 2])
    return model


def _splats(g):
    """The wheel's splat attributes of Gaussians ``g``: position, unit wxyz rotation, standard
    deviations, RGBA (SH degree-0 colour, sigmoid opacity), float32."""
    import jax
    import jax.numpy as jnp

    from kernels.gaussians import quat_normalize
    from kernels.sh import SH_C0

    rgb = jnp.maximum(SH_C0 * g.sh[:, 0, :] + 0.5, 0.0)
    rgba = jnp.concatenate([rgb, jax.nn.sigmoid(g.opacity_logits)[:, None]], axis=1)
    return tuple(x.astype(jnp.float32) for x in (g.means, quat_normalize(g.quats), jnp.exp(g.log_scales), rgba))


@functools.cache
def _world_splats_fn():
    import jax
    import jax.numpy as jnp

    from kernels.gaussians import Sim3, transform_bodies

    @jax.jit
    def world_splats(background, attached, body, placements):
        """(N·(B+M), ...) splat attributes: world w's B background splats then its M object splats at
        placements[w] (N, K, 4, 4), world after world (the wheel's group w)."""
        static = _splats(background)
        moved = jax.vmap(lambda p: _splats(transform_bodies(attached, Sim3.from_matrix(p), body)))(placements)
        n = placements.shape[0]
        return tuple(jnp.concatenate([jnp.broadcast_to(s, (n,) + s.shape), m], axis=1).reshape(-1, s.shape[-1])
                     for s, m in zip(static, moved))

    return world_splats


def _to_warp(x, dtype, device: str):
    """A float32 JAX array as a Warp array of ``dtype`` on ``device``: shared through DLPack on a GPU,
    copied through the host otherwise."""
    import warp as wp

    if device.startswith("cuda"):
        return wp.from_jax(x, dtype=dtype)
    return wp.array(np.asarray(x), dtype=dtype, device=device)


class SplatWorlds:
    """The wheel's renderer drawing the scene's Gaussians in every world (module docstring)."""

    def __init__(self, env, cameras, placements, constructor: str, device: str):
        import mujoco
        import mujoco_warp as mjw
        import warp as wp
        from mujoco_warp._src import bvh

        self.device = device
        self.cameras = cameras
        self.num_worlds = int(placements.shape[0])
        self.attached, self.body = env.object_gaussians, env.body_index
        self.background = env.background
        self.per_world = int(self.background.num + self.attached.num)
        cam = cameras[0]
        self.size = (cam.width, cam.height)
        self.mjm = camera_model(cameras)
        mjd = mujoco.MjData(self.mjm)
        mujoco.mj_forward(self.mjm, mjd)
        splats = self._arrays(placements)
        host = [np.asarray(s) for s in splats]
        adr = np.arange(self.num_worlds + 1, dtype=np.int32) * self.per_world
        group = np.arange(self.num_worlds, dtype=np.int32)
        with wp.ScopedDevice(device):
            self.m = mjw.put_model(self.mjm)
            self.d = mjw.put_data(self.mjm, mjd, nworld=self.num_worlds)
            options = {"cam_res": self.size, "render_rgb": True, "render_depth": False, "render_seg": False,
                       "use_textures": False, "use_shadows": False, "background_color": (0.0, 0.0, 0.0, 1.0)}
            t0 = time.perf_counter()
            if constructor == "sah":   # the wheel's own path: create_render_context builds with SAH
                self.rc = mjw.create_render_context(self.mjm, nworld=self.num_worlds, **options,
                                                    splat_position=host[0], splat_rotation=host[1],
                                                    splat_scale=host[2], splat_rgba=host[3], splat_adr=adr,
                                                    splat_group_id=group)
            else:
                one = [h[:1] for h in host]
                self.rc = mjw.create_render_context(self.mjm, nworld=self.num_worlds, **options,
                                                    splat_position=one[0], splat_rotation=one[1],
                                                    splat_scale=one[2], splat_rgba=one[3])
                (self.rc.splat_position, self.rc.splat_rotation, self.rc.splat_scale, self.rc.splat_rgba,
                 self.rc.splat_bvh, self.rc.splat_bvh_id, self.rc.splat_lower, self.rc.splat_upper,
                 self.rc.splat_group_root, self.rc.splat_count) = bvh.build_splat_bvh(
                    *host, adr, group, constructor=constructor)
            wp.synchronize_device(device)
            self.build_s = time.perf_counter() - t0

    def _arrays(self, placements):
        import jax.numpy as jnp

        return _world_splats_fn()(self.background, self.attached, jnp.asarray(self.body, jnp.int32),
                                  jnp.asarray(placements, jnp.float32))

    def place(self, placements) -> None:
        """Every world's splats at ``placements`` (N, K, 4, 4), written into the context's arrays."""
        import jax
        import warp as wp

        position, rotation, _, _ = self._arrays(placements)
        jax.block_until_ready((position, rotation))   # made on JAX's stream; Warp copies them on its own
        with wp.ScopedDevice(self.device):
            wp.copy(self.rc.splat_position, _to_warp(position, wp.vec3, self.device))
            wp.copy(self.rc.splat_rotation, _to_warp(rotation, wp.quat, self.device))
            wp.synchronize_device(self.device)

    def refit(self) -> None:
        """The splat BVH refit to the written splats (the wheel's ``refit_splat_bvh``)."""
        import warp as wp
        from mujoco_warp._src import bvh

        with wp.ScopedDevice(self.device):
            bvh.refit_splat_bvh(self.rc)
            wp.synchronize_device(self.device)

    def render(self) -> None:
        import mujoco_warp as mjw
        import warp as wp

        with wp.ScopedDevice(self.device):
            mjw.render(self.m, self.d, self.rc)
            wp.synchronize_device(self.device)

    def image(self, world: int, camera: int) -> np.ndarray:
        """(H, W, 3) uint8 of one world and camera, from the packed 0xAARRGGBB pixels."""
        width, height = self.size
        adr = int(self.rc.rgb_adr.numpy()[camera])
        packed = self.rc.rgb_data.numpy()[world, adr:adr + width * height].reshape(height, width)
        return np.stack([(packed >> s) & 0xFF for s in (16, 8, 0)], axis=-1).astype(np.uint8)


def _median_ms(fn, repeats: int) -> tuple[float, float]:
    """(first call s, median of ``repeats`` later calls ms)."""
    t0 = time.perf_counter()
    fn()
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return first, 1e3 * statistics.median(times)


def bench(env, worlds: int, cameras: list[int], steps: int, repeats: int, constructor: str,
          throw: float) -> dict:
    import jax
    import warp as wp

    from experiments.bench_warp_worlds import throws
    from phirie_jax.interact.batched import BatchedEnvironment

    frames = worlds * len(cameras)
    _say(f"{worlds} Warp worlds, {steps} steps")
    batch = BatchedEnvironment(env, worlds, backend="warp")
    batch.set_velocities(throws(env, worlds, throw))
    batch.step(steps)
    batch.worlds.synchronize()
    placements = jax.block_until_ready(batch.placements())
    result = {"overflow_worlds": int(batch.worlds.overflow()[:worlds].sum())}

    # (b) ours
    _say("ours: batched uint8 render")
    t0 = time.perf_counter()
    ours_first = jax.block_until_ready(batch.render(cameras, pixels="uint8"))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(batch.render(cameras, pixels="uint8"))
        times.append(time.perf_counter() - t0)
    ours_s = statistics.median(times)
    result["ours"] = {"first_call_s": round(first, 2), "compile_s": round(first - ours_s, 2),
                      "render_ms": round(1e3 * ours_s, 3), "frames_per_s": round(frames / ours_s, 1),
                      "output": "uint8 (N, C, H, W, 3), JAX, on the device"}
    ours0 = np.asarray(ours_first[0, 0])
    del ours_first

    # (a) the wheel's renderer
    device = batch.worlds.devices[0]
    _say(f"mjwarp: {worlds * (env.background.num + env.object_gaussians.num):,} splats, {constructor} BVH")
    t0 = time.perf_counter()
    splats = SplatWorlds(env, [env.camera(c) for c in cameras], placements, constructor, device)
    setup_s = time.perf_counter() - t0
    render_first, render_ms = _median_ms(splats.render, repeats)
    image0 = splats.image(0, 0)
    place_first, place_ms = _median_ms(lambda: splats.place(batch.placements()), repeats)
    refit_first, refit_ms = _median_ms(splats.refit, repeats)
    frame_ms = place_ms + refit_ms + render_ms
    total = worlds * splats.per_world
    result["mjwarp"] = {
        "constructor": constructor, "splats": total, "splats_per_world": splats.per_world,
        "context_and_bvh_build_s": round(splats.build_s, 2), "setup_s": round(setup_s, 2),
        "render_first_s": round(render_first, 2), "compile_s": round(render_first - 1e-3 * render_ms, 2),
        "render_ms": round(render_ms, 3), "place_first_s": round(place_first, 2), "place_ms": round(place_ms, 3),
        "refit_first_s": round(refit_first, 2), "bvh_refit_ms": round(refit_ms, 3),
        "frame_batch_ms": round(frame_ms, 3), "frames_per_s": round(frames / (1e-3 * frame_ms), 1),
        "frames_per_s_render_only": round(frames / (1e-3 * render_ms), 1),
        "output": "packed uint32 0xAARRGGBB (N, C·H·W), Warp, on the device",
        "limits": {
            "body_attachment": "none: splats are world-space points; a body's splats are moved and the "
                               "BVH refit outside the renderer (place_ms, bvh_refit_ms)",
            "per_world_splats": "one BVH group per world; a ray queries one group, so the static "
                                f"background is copied into every group ({worlds} x {env.background.num})",
            "colour": "RGB per splat, no spherical harmonics (degree-0 colour here)",
            "hits_per_pass": 32, "min_transmittance": 0.005, "min_alpha": round(1 / 255, 5),
            "min_response": 0.01},
    }
    result["speed_ours_over_mjwarp"] = round(result["ours"]["frames_per_s"] / result["mjwarp"]["frames_per_s"], 3)
    result["speed_ours_over_mjwarp_render_only"] = round(
        result["ours"]["frames_per_s"] / result["mjwarp"]["frames_per_s_render_only"], 3)

    # images of world 0, camera 0: the single environment at world 0's poses
    env.data.xpos[:] = batch.worlds.field("xpos")[0]
    quats = batch.worlds.field("xquat")[0]
    env.data.xquat[:] = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    from phirie_jax.interact.batched import as_pixels
    from phirie_jax.render import render

    single = np.asarray(as_pixels(env.render(cameras[0]).rgb, "uint8"))
    dc = env.gaussians()
    dc = dc.replace(sh=dc.sh[:, :1])
    single_dc = np.asarray(as_pixels(render(dc, env.camera(cameras[0]),
                                            background=np.zeros(3, np.float32)).rgb, "uint8"))
    result["images_world0_camera0"] = {
        "psnr_mjwarp_vs_ours": psnr(image0, ours0), "psnr_mjwarp_vs_single": psnr(image0, single),
        "psnr_mjwarp_vs_single_dc": psnr(image0, single_dc), "psnr_ours_vs_single": psnr(ours0, single),
        "psnr_single_dc_vs_single": psnr(single_dc, single),
        "mean_rgb_mjwarp": np.round(image0.reshape(-1, 3).mean(0), 2).tolist(),
        "mean_rgb_ours": np.round(ours0.reshape(-1, 3).mean(0), 2).tolist()}
    with wp.ScopedDevice(device):
        wp.synchronize_device(device)
    return result


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path, help="a `phirie convert` output folder (e.g. .devdata/demo)")
    parser.add_argument("--worlds", type=int, default=1024)
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--width", type=int, default=640, help="image width (height by the cameras' aspect)")
    parser.add_argument("--steps", type=int, default=240, help="simulator steps before rendering")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls after the first")
    parser.add_argument("--throw", type=float, default=0.5, help="m/s: the largest random throw of an object")
    parser.add_argument("--constructor", choices=CONSTRUCTORS, default="sah",
                        help="the splat BVH's builder (the wheel's create_render_context: sah, on the host)")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")   # MuJoCo Warp shares the device with JAX

    from importlib.metadata import version

    import jax
    import warp as wp

    from experiments.report import emit
    from phirie_jax.interact.environment import Environment

    wp.init()
    env = Environment.load(args.out_dir)
    env.cameras = [c.scaled(args.width / c.width) for c in env.cameras]
    if args.cameras > len(env.cameras):
        raise ValueError(f"--cameras {args.cameras}: {args.out_dir} has {len(env.cameras)} cameras")
    cameras = list(range(args.cameras))
    cam = env.cameras[0]
    result = {"benchmark": "bench_mjwarp_splats", "scene": str(args.out_dir), "worlds": args.worlds,
              "cameras": args.cameras, "image": [cam.width, cam.height], "steps": args.steps,
              "repeats": args.repeats, "frames": args.worlds * args.cameras,
              "background_gaussians": int(env.background.num), "object_gaussians": int(env.object_gaussians.num),
              "sh_degree": int(env.background.sh_degree), "device": str(jax.devices()[0]),
              "device_kind": jax.devices()[0].device_kind, "jax": jax.__version__,
              "warp_version": version("warp-lang"), "mujoco_warp_version": version("mujoco-warp"),
              "machine": platform.platform()}
    result.update(bench(env, args.worlds, cameras, args.steps, args.repeats, args.constructor, args.throw))
    emit(result, args.out)


if __name__ == "__main__":
    main()
