"""Where a step of ``phirie capture``'s training goes: one 3DGS train step cut into its parts.

    python -m experiments.profile_train_step SCENE [--gaussians PLY_OR_NPZ] [--out JSON] [--trace DIR]

SCENE: a capture folder (transforms.json or COLMAP cameras + images) whose Gaussians stand for a
set late in training (e.g. the snowmiku capture: 237,916 Gaussians fitted by gsplat at
1000×750). ``--gaussians`` may name a ``.npz`` of the PLY's fields (means, quats, log_scales,
opacity_logits, sh; any float dtype) to carry a smaller file.

Prints JSON: for each part, the first call (compilation included) and the median of later calls
(each blocked on), all on the same Gaussians, padded to the training loop's bucket, and one
training view:

- ``project``: the projection of every Gaussian;
- ``bin``: projection + depth sort + tile intersection buffer + tile sort, at the loop's
  capacity (``CAPACITY_PER_GAUSSIAN`` × the bucket, grown past the needed count as the loop
  grows it) and at the needed count's power of two;
- ``forward``: the whole render;
- ``loss_grad``: the loss and its gradient (render forward + backward, SSIM, screen gradient);
- ``photometric_grad``: the loss and its gradient of the image alone (L1 + SSIM);
- ``adam``: the optimizer update of every parameter;
- ``train_step``: the loop's jitted step (donated and not), and ``loop_50``: 50 steps as the
  training loop calls them (a host sync per step) against 50 dispatched without syncing;
- the same step on the exact count (no padding) and at the tight capacity.

The step and the loop use training's raster settings (``phirie_jax.capture.train.TRAINING_RASTER``).

``--loop N`` runs ``train_gaussians`` itself on the one view for N steps (no densification, every
SH band on): its median step with 2, 3 and 4 steps in flight, and with the photo already on the
device, against the parts above (where the loop's time goes beyond the step's own).

``--levers`` times the colour render and the loss gradient per Pallas setting (the backward's
chunk and block orientation, warps). ``memory``: what XLA's compiled train step holds (its
temporaries, arguments, outputs and the outputs aliased to donated arguments, MiB) and the
device's peak so far. ``--trace DIR`` records a profiler trace of 20 steps there; the JSON gets the device time per
kernel of one step (``experiments.profiling``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from experiments.profiling import traced
from experiments.timing import timed
from kernels import splat_fit
from kernels.composite import TileGrid
from kernels.composite_pallas import PallasSettings
from kernels.project import project_gaussians
from kernels.raster import RasterConfig, bin_gaussians, rasterize
from phirie_jax.capture.config import TrainConfig
from phirie_jax.capture.densify import padded
from phirie_jax.capture.train import CAPACITY_PER_GAUSSIAN, MIN_CAPACITY, TRAINING_RASTER, learning_rates, sh_mask
from phirie_jax.render import gaussian_bucket, next_power_of_two
from phirie_jax.types import GaussianSplatData

REPEATS = 20


def _gaussians(path: Path | None, scene) -> GaussianSplatData:
    if path is None or path.suffix == ".ply":
        from phirie_jax.io.ply import read_gaussian_ply

        return read_gaussian_ply(path) if path is not None else scene.gaussians
    with np.load(path) as z:
        return GaussianSplatData(**{k: np.asarray(z[k], np.float32) for k in
                                    ("means", "quats", "log_scales", "opacity_logits", "sh")})


def _view(scene, index: int):
    import cv2

    camera = scene.cameras[index]
    bgr = cv2.imread(str(camera.image_path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise SystemExit(f"{camera.image_path}: not a readable image")
    return camera, jnp.asarray(np.ascontiguousarray(bgr[..., ::-1]), jnp.uint8)


def _ms(pair) -> dict:
    first, later = pair
    return {"first_s": round(first, 4), "ms": round(later * 1e3, 3)}


LEVER_SETTINGS = (  # the backward's (chunk, warps, entries-major blocks); the forward keeps its defaults
    (8, 4, False), (16, 4, False), (32, 4, False), (8, 4, True), (16, 4, True), (16, 2, False), (16, 8, False))


def _training_raster(capacity: int) -> RasterConfig:
    """Training's raster settings (``TRAINING_RASTER``) at a tile-intersection buffer of ``capacity``."""
    return dataclasses.replace(TRAINING_RASTER, capacity=capacity)


def _levers(params, valid, mask, K, w2c, bg, target, offset, capacity: int, config: TrainConfig, width: int,
            height: int, g_masked) -> dict:
    """The colour render and the loss gradient per Pallas setting (``LEVER_SETTINGS``)."""
    out = {}
    for chunk, warps, backward_entries_major in LEVER_SETTINGS:
        settings = PallasSettings(backward_chunk=chunk, backward_num_warps=warps,
                                  backward_entries_major=backward_entries_major)
        raster = RasterConfig(capacity=capacity, pallas=settings, depth=False)
        fn = jax.jit(lambda g, r=raster: rasterize(g, K, w2c, width=width, height=height, background=bg,
                                                   config=r).rgb)
        row = {"forward_colour_only_ms": _ms(timed(lambda f=fn: f(g_masked), 10))["ms"]}
        grad = jax.jit(jax.value_and_grad(
            lambda p, o, r=raster: splat_fit.view_loss(p, valid, mask, K, w2c, bg, target, o, config=r,
                                                       dssim_weight=config.dssim_weight)[0], argnums=(0, 1)))
        row["loss_grad_ms"] = _ms(timed(lambda f=grad: f(params, offset), 10))["ms"]
        name = f"backward_chunk{chunk}_warps{warps}_{'entries' if backward_entries_major else 'pixels'}_major"
        out[name] = row
        print(f"profile_train_step: {name} {row}", file=sys.stderr, flush=True)
    return out


def _memory(fn, params, valid, mask, K, w2c, image, bg, lrs, raster: RasterConfig, config: TrainConfig) -> dict:
    """The compiled step's memory (module docstring), in MiB."""
    state, zeros = splat_fit.init_state(params), jnp.zeros(params.num)
    compiled = fn.lower(params, state, lrs, valid, mask, K, w2c, image, bg, zeros, zeros,
                        config=raster, dssim_weight=config.dssim_weight,
                        exact_screen_gradient=config.exact_screen_gradient).compile()
    analysis = compiled.memory_analysis()
    mib = 2.0 ** 20
    out = {key: round(getattr(analysis, f"{key}_size_in_bytes") / mib, 1)
           for key in ("temp", "argument", "output", "alias", "generated_code")
           if hasattr(analysis, f"{key}_size_in_bytes")}
    stats = jax.local_devices()[0].memory_stats() or {}
    if "peak_bytes_in_use" in stats:
        out["device_peak_so_far"] = round(stats["peak_bytes_in_use"] / mib, 1)
    return out


def _training_loop(data: GaussianSplatData, camera, image: np.ndarray, steps: int) -> dict:
    """``train_gaussians`` on one view (module docstring, ``--loop``)."""
    from phirie_jax.capture import train

    config = TrainConfig(steps=steps, densify_from=steps + 1, opacity_reset_interval=0, checkpoint_interval=0,
                         sh_band_interval=1)
    on_host = train.Views.of([image], [camera])
    on_device = dataclasses.replace(on_host, images=jnp.asarray(on_host.images))
    default, out = train.IN_FLIGHT, {}
    try:
        for name, views, in_flight in (("in_flight_2", on_host, 2), ("in_flight_3", on_host, 3),
                                       ("in_flight_4", on_host, 4), ("in_flight_2_photo_on_device", on_device, 2)):
            train.IN_FLIGHT = in_flight
            record = train.train_gaussians(data, views, 5.0, config, np.random.default_rng(0), donate=True).record
            out[name] = {"step_ms_median": round(record["step_s_median"] * 1e3, 3),
                         "run_ms_per_step": round(record["run_s"] / steps * 1e3, 3), "compile_s": record["compile_s"]}
            print(f"profile_train_step: loop {name} {out[name]}", file=sys.stderr, flush=True)
    finally:
        train.IN_FLIGHT = default
    return out


def profile(scene_dir: Path, gaussians_path: Path | None, trace: Path | None, levers: bool = False,
            loop: int = 0) -> dict:
    from phirie_jax.io.scene import load_scene

    scene = load_scene(scene_dir, gaussians=gaussians_path if gaussians_path and gaussians_path.suffix == ".ply"
                       else None, check_images=False)  # only the first view's image is read
    data = _gaussians(gaussians_path, scene)
    camera, image = _view(scene, 0)
    height, width = image.shape[:2]
    config = TrainConfig(steps=7000)
    size = gaussian_bucket(data.num)
    params, valid = padded(data, size)
    K = jnp.asarray(camera.K, jnp.float32)
    w2c = jnp.asarray(camera.world_to_camera, jnp.float32)
    bg = jnp.zeros(3, jnp.float32)
    lrs = learning_rates(config, 5.0, 3000)
    mask = sh_mask(config, 6000)
    loop_capacity = max(MIN_CAPACITY, next_power_of_two(CAPACITY_PER_GAUSSIAN * size))
    grid = TileGrid(width, height, 16)

    needed = int(splat_fit.views_intersections(params, valid, K[None], w2c[None], width=width, height=height,
                                               config=RasterConfig())[0])
    while loop_capacity < needed:  # the loop grows its buffer the same way on overflow
        loop_capacity *= 2
    tight = next_power_of_two(needed)
    result = {"gaussians": data.num, "bucket": size, "width": width, "height": height,
              "tile_intersections": needed, "loop_capacity": loop_capacity, "tight_capacity": tight,
              "device": str(jax.devices()[0]), "backend": jax.default_backend(), "parts": {}}
    parts = result["parts"]

    g_masked = jax.jit(splat_fit.masked_sh)(params, valid, mask)
    project = jax.jit(lambda g: project_gaussians(g, K, w2c, width=width, height=height))
    parts["project"] = _ms(timed(lambda: project(g_masked), REPEATS))
    for name, capacity in (("bin_loop_capacity", loop_capacity), ("bin_tight", tight)):
        fn = jax.jit(lambda g, c=capacity: bin_gaussians(
            jax.lax.stop_gradient(project_gaussians(g, K, w2c, width=width, height=height)), grid, c))
        parts[name] = _ms(timed(lambda f=fn: f(g_masked), REPEATS))
    for name, capacity in (("forward", loop_capacity), ("forward_tight", tight)):
        raster = _training_raster(capacity)
        fn = jax.jit(lambda g, r=raster: rasterize(g, K, w2c, width=width, height=height, background=bg,
                                                   config=r).rgb)
        parts[name] = _ms(timed(lambda f=fn: f(g_masked), REPEATS))

    raster = _training_raster(loop_capacity)
    target = splat_fit.as_float_image(image)
    offset = jnp.zeros((size, 2), jnp.float32)
    loss_grad = jax.jit(jax.value_and_grad(
        lambda p, o: splat_fit.view_loss(p, valid, mask, K, w2c, bg, target, o, config=raster,
                                         dssim_weight=config.dssim_weight)[0], argnums=(0, 1)))
    parts["loss_grad"] = _ms(timed(lambda: loss_grad(params, offset), REPEATS))
    rendered = jax.jit(lambda g: rasterize(g, K, w2c, width=width, height=height, background=bg,
                                           config=raster).rgb)(g_masked)
    photometric = jax.jit(jax.value_and_grad(lambda r: splat_fit.photometric_loss(r, target, config.dssim_weight)))
    parts["photometric_grad"] = _ms(timed(lambda: photometric(rendered), REPEATS))
    grads = loss_grad(params, offset)[1][0]
    state = splat_fit.init_state(params)

    @jax.jit
    def adam(p, s, g):
        updates, s = splat_fit.optimizer().update(g, s, p)
        return jax.tree.map(lambda x, u, lr: x + lr * u, p, updates, lrs), s

    parts["adam"] = _ms(timed(lambda: adam(params, state, grads), REPEATS))

    def step_fn(raster_config, donate):
        static = ("config", "dssim_weight", "exact_screen_gradient")
        return jax.jit(splat_fit.train_step, static_argnames=static,
                       donate_argnums=(0, 1, 9, 10) if donate else ())

    def run_steps(fn, p, v, r, count, sync):
        s, gsum, seen = splat_fit.init_state(p), jnp.zeros(p.num), jnp.zeros(p.num)
        out = fn(p, s, lrs, v, mask, K, w2c, image, bg, gsum, seen, config=r,
                 dssim_weight=config.dssim_weight, exact_screen_gradient=config.exact_screen_gradient)
        jax.block_until_ready(out)
        p, s, _, gsum, seen = out[:5]
        t0 = time.perf_counter()
        for _ in range(count):
            out = fn(p, s, lrs, v, mask, K, w2c, image, bg, gsum, seen, config=r,
                     dssim_weight=config.dssim_weight, exact_screen_gradient=config.exact_screen_gradient)
            p, s, loss, gsum, seen = out[:5]
            if sync:
                bool(out[6]), float(loss)
        jax.block_until_ready(out)
        return (time.perf_counter() - t0) / count

    exact_params, exact_valid = padded(data, data.num)
    for name, (p, v, cap, donate) in {
            "train_step": (params, valid, loop_capacity, False),
            "train_step_donated": (params, valid, loop_capacity, True),
            "train_step_tight": (params, valid, tight, True),
            "train_step_unpadded_tight": (exact_params, exact_valid, tight, True)}.items():
        at = _training_raster(cap)
        fn = step_fn(at, donate)
        t0 = time.perf_counter()
        per_step = run_steps(fn, jax.tree.map(jnp.copy, p), v, at, REPEATS, sync=True)
        parts[name] = {"first_and_run_s": round(time.perf_counter() - t0, 3), "ms": round(per_step * 1e3, 3)}
    fn = step_fn(raster, True)
    result["memory"] = _memory(fn, params, valid, mask, K, w2c, image, bg, lrs, raster, config)
    for sync in (True, False):
        per_step = run_steps(fn, jax.tree.map(jnp.copy, params), valid, raster, 50, sync)
        parts[f"loop_50_{'synced' if sync else 'dispatched'}"] = {"ms": round(per_step * 1e3, 3)}

    if loop:
        result["training_loop"] = _training_loop(data, camera, np.asarray(image), loop)
    if levers:
        result["levers"] = _levers(params, valid, mask, K, w2c, bg, target, offset, loop_capacity, config,
                                   width, height, g_masked)
    if trace is not None:
        result["trace_summary"] = traced(  # per step of 20
            lambda: run_steps(fn, jax.tree.map(jnp.copy, params), valid, raster, 20, True), 1, trace,
            calls_per_work=20)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path)
    parser.add_argument("--gaussians", type=Path)
    parser.add_argument("--out", type=Path)
    parser.add_argument("--trace", type=Path)
    parser.add_argument("--loop", type=int, default=0, metavar="N",
                        help="also run the training loop itself for N steps on the view (several variants)")
    parser.add_argument("--levers", action="store_true", help="also time the render and the loss gradient per "
                        "Pallas setting (chunk, warps, prefetch) and with and without the depth channel")
    args = parser.parse_args()
    result = profile(args.scene, args.gaussians, args.trace, args.levers, args.loop)
    text = json.dumps(result, indent=1)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
