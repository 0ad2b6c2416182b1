"""3DGS training: the loop around ``kernels.splat_fit.train_step``, with checkpoints to resume from.

``train_gaussians`` runs ``TrainConfig``'s schedule (``phirie_jax.capture.config``) from an
initial set: one training view per step in a seeded order (each epoch a fresh permutation of the
views), the per-field learning rates with the position's exponential decay, SH bands switched on
every ``sh_band_interval`` steps, and after the step numbered ``s`` (counting from 1):

- densification (``phirie_jax.capture.densify``) when ``densify_from ≤ s < densify_until`` and
  ``s`` is a multiple of ``densify_interval``, on the screen gradients accumulated since the last;
- an opacity reset when ``s`` is a multiple of ``opacity_reset_interval`` (and ``s < densify_until``);
- a checkpoint when ``s`` is a multiple of ``checkpoint_interval``, and at the end.

A step whose tile intersections overflow the buffer changes nothing; its view is trained again
with a larger buffer. A step is dispatched before the one in flight is checked (unless that one
ends with host work), so the host's work overlaps the device's. The
training state is a pytree (the padded Gaussians, Adam's state, the densification statistics);
a checkpoint holds its valid rows, the random generator's state, the view order and what has
been recorded, written to a temporary name and renamed (``phirie_jax.io.atomic``). Resuming
from it continues exactly: on one machine, a run killed after a checkpoint and resumed ends
with the same Gaussians, bit for bit, as a run that was never stopped.

The synthetic scenes' fitter (``phirie_jax.synthetic.fitted``) runs this loop with its own
schedule and a random initialization; ``phirie capture`` with gsplat's and the SfM points.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import math
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from kernels import splat_fit
from kernels.composite_pallas import PallasSettings
from kernels.gaussians import Gaussians
from kernels.raster import RasterConfig
from kernels.sh import num_sh_coeffs, rgb_to_sh_dc
from phirie_jax.capture.config import TrainConfig
from phirie_jax.capture.densify import densify_on_device, padded, prepare_densify, reset_opacity, unpadded
from phirie_jax.capture.programs import Programs, like, with_rows
from phirie_jax.errors import SceneInputError
from phirie_jax.io.atomic import write_bytes
from phirie_jax.render import gaussian_bucket, grown_capacity, next_power_of_two
from phirie_jax.types import Camera, GaussianSplatData

MIN_CAPACITY = 1 << 16         # tile intersections of the first program
CAPACITY_PER_GAUSSIAN = 4      # ... or this many per (padded) Gaussian, if more
FIRST_CAPACITY_MARGIN = 1.5    # ... or the busiest view's count at the start × this (footprints grow in the first steps)
EXTENT_MARGIN = 1.1            # gsplat's scene scale: 1.1 × the largest camera distance from their mean
RESET_CEILING = 2.0            # an opacity reset clamps opacities to this × min_opacity (gsplat)
CHECKPOINT_VERSION = 1
# Training's renders (the capacity set per run): the compositor's backward walks chunks of 16 list
# entries, not the renderer's 8 (``PallasSettings.backward_chunk``: faster at a training view's
# scale on the real captures measured; 8 is the renderer's choice at 1080p).
TRAINING_RASTER = RasterConfig(pallas=PallasSettings(backward_chunk=16))
IN_FLIGHT = 2                  # steps dispatched before the oldest is checked (its host work overlaps the next)
# While a thread traces programs ahead (pure Python, holding the GIL), the loop waits for the GIL
# each time it gets it back from a blocking call: up to Python's switch interval (5 ms) each time.
SWITCH_INTERVAL_S = 2e-4
GROW_AHEAD = 0.75              # the next bucket's (capacity's) program is compiled once this much of one is used

_STATIC = ("config", "dssim_weight", "exact_screen_gradient")
_train_step = jax.jit(splat_fit.train_step, static_argnames=_STATIC)
_train_step_donated = jax.jit(splat_fit.train_step, static_argnames=_STATIC, donate_argnums=(0, 1, 9, 10))
_views_intersections = jax.jit(splat_fit.views_intersections, static_argnames=("width", "height", "config"))
_render_view = jax.jit(lambda params, valid, K, w2c, bg, *, width, height, config: splat_fit.render_views(
    params, valid, K[None], w2c[None], bg, width=width, height=height, config=config), static_argnames=(
    "width", "height", "config"))


@dataclasses.dataclass(frozen=True)
class Views:
    """Training views, one image size, on the host: a step takes its view's photo to the
    device (a few MB, while the step before runs), so the photos never occupy device memory
    together (80 photos at 1000×750 would hold 180 MB of it)."""

    Ks: np.ndarray                # (V, 3, 3) float32
    world_to_cameras: np.ndarray  # (V, 4, 4) float32
    images: np.ndarray            # (V, H, W, 3) float32 in [0, 1] or uint8

    @property
    def count(self) -> int:
        return int(self.Ks.shape[0])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @staticmethod
    def of(images: list[np.ndarray], cameras: list[Camera]) -> Views:
        """images: V arrays (H, W, 3), float in [0, 1] or uint8, one size; cameras: V pinhole cameras of it."""
        sizes = {(c.width, c.height) for c in cameras} | {(im.shape[1], im.shape[0]) for im in images}
        if len(sizes) != 1:
            raise ValueError(f"every training view must have one size (found {sorted(sizes)})")
        stacked = np.stack(images)
        return Views(Ks=np.stack([c.K for c in cameras]).astype(np.float32),
                     world_to_cameras=np.stack([c.world_to_camera for c in cameras]).astype(np.float32),
                     images=stacked if stacked.dtype == np.uint8 else stacked.astype(np.float32))


@dataclasses.dataclass(frozen=True)
class Trained:
    gaussians: GaussianSplatData  # every Gaussian of the last step (nothing pruned after it)
    raster: RasterConfig          # a capacity that held every training view
    losses: list[float]           # one per step (of every run that led here)
    record: dict                  # counts, densification events, times (module docstring)


def camera_extent(cameras: list[Camera]) -> float:
    """gsplat's scene scale: 1.1 × the largest distance of a camera centre from their mean."""
    centres = np.array([c.center for c in cameras])
    return EXTENT_MARGIN * float(np.max(np.linalg.norm(centres - centres.mean(0), axis=1)))


def init_from_points(points: np.ndarray, colours: np.ndarray, config: TrainConfig, rng) -> GaussianSplatData:
    """One Gaussian per SfM point (gsplat's ``init_type="sfm"``): points (P, 3), colours (P, 3) in [0, 1].

    Isotropic, σ = the root mean square distance to the 3 nearest points; random rotation;
    opacity ``config.init_opacity``; SH DC from the colour, the higher bands zero."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64)
    dist, _ = cKDTree(points).query(points, k=min(4, len(points)))
    sigma = np.sqrt(np.mean(np.asarray(dist)[:, 1:] ** 2, axis=1))
    sigma = np.maximum(sigma, np.finfo(np.float32).tiny ** 0.25)  # coincident points: a tiny, finite σ
    n, k = len(points), num_sh_coeffs(config.sh_degree)
    sh = np.zeros((n, k, 3), np.float32)
    sh[:, 0] = rgb_to_sh_dc(np.asarray(colours, np.float64))
    logit = np.log(config.init_opacity / (1 - config.init_opacity))
    return GaussianSplatData(
        means=points.astype(np.float32), quats=rng.uniform(size=(n, 4)).astype(np.float32),
        log_scales=np.repeat(np.log(sigma)[:, None], 3, axis=1).astype(np.float32),
        opacity_logits=np.full(n, logit, np.float32), sh=sh)


# The step's small inputs are host (NumPy) values: the step's call takes them to the device with
# its other arguments, where a JAX array made for each would be a separate operation per step.

def learning_rates(config: TrainConfig, extent: float, step: int) -> Gaussians:
    """Per-field rates at ``step`` (0-based), NumPy float32: the position's decays exponentially
    over the run."""
    t = step / max(1, config.steps - 1)
    position = config.lr_position * extent * (config.lr_position_final / config.lr_position) ** t
    sh = np.full((num_sh_coeffs(config.sh_degree), 1), config.lr_colour / 20.0, np.float32)
    sh[0] = config.lr_colour
    return Gaussians(means=np.float32(position), quats=np.float32(config.lr_rotation),
                     log_scales=np.float32(config.lr_scale), opacity_logits=np.float32(config.lr_opacity), sh=sh)


def sh_mask(config: TrainConfig, step: int) -> np.ndarray:
    """(K, 1) float32, 1 for the coefficients of the bands on at ``step``."""
    degree = min(config.sh_degree, step // config.sh_band_interval)
    return (np.arange(num_sh_coeffs(config.sh_degree)) < num_sh_coeffs(degree))[:, None].astype(np.float32)


def first_capacity(params: Gaussians, valid, views: Views) -> int:
    """The tile-intersection buffer of the first steps: a power of two that holds every training
    view of the starting set with ``FIRST_CAPACITY_MARGIN`` to spare (counted from the
    projection, so the first steps do not overflow and compile a program for each buffer they
    outgrow), and at least ``MIN_CAPACITY`` and ``CAPACITY_PER_GAUSSIAN`` slots per (padded)
    Gaussian."""
    counts = _views_intersections(params, valid, jnp.asarray(views.Ks), jnp.asarray(views.world_to_cameras),
                                  width=views.width, height=views.height, config=RasterConfig())
    return max(MIN_CAPACITY, next_power_of_two(CAPACITY_PER_GAUSSIAN * int(valid.shape[0])),
               next_power_of_two(int(FIRST_CAPACITY_MARGIN * int(jnp.max(counts)))))


def peak_device_memory_mb() -> float | None:
    """The device's peak allocated memory so far in MiB (None where the backend does not say: a CPU)."""
    stats = jax.local_devices()[0].memory_stats()
    if not stats or "peak_bytes_in_use" not in stats:
        return None
    return round(stats["peak_bytes_in_use"] / 2**20, 1)


@dataclasses.dataclass
class _Loop:
    """The host side of the training state (the device side: params, Adam state, statistics)."""

    step: int = 0
    order: list[int] = dataclasses.field(default_factory=list)
    losses: list[float] = dataclasses.field(default_factory=list)
    events: list[dict] = dataclasses.field(default_factory=list)
    resets: list[int] = dataclasses.field(default_factory=list)
    buckets: set[int] = dataclasses.field(default_factory=set)
    retries: int = 0


def fingerprint(config: TrainConfig, views: Views, init: GaussianSplatData, extent: float) -> str:
    """What a checkpoint must have been made from to be resumed: the config, the views' count
    and size, the initial set and the extent (a digest)."""
    digest = hashlib.sha256(json.dumps(dataclasses.asdict(config), sort_keys=True).encode())
    digest.update(np.float64([views.count, views.width, views.height, extent]).tobytes())
    for field in ("means", "log_scales", "opacity_logits"):
        digest.update(np.ascontiguousarray(getattr(init, field)).tobytes())
    return digest.hexdigest()[:16]


class _Written:
    """A checkpoint being written by a thread: ``wait()`` joins it and raises what it raised."""

    def __init__(self, write: Callable[[], None]):
        self.error: BaseException | None = None

        def run():
            try:
                write()
            except BaseException as err:  # noqa: BLE001 (handed to wait(), which raises it)
                self.error = err

        self.thread = threading.Thread(target=run, name="checkpoint", daemon=False)
        self.thread.start()

    def wait(self) -> None:
        self.thread.join()
        if self.error is not None:
            raise self.error


def save_checkpoint(path: Path, params: Gaussians, valid, state, grad_sum, seen, raster: RasterConfig,
                    loop: _Loop, rng, stamp: str) -> _Written:
    """The training state after ``loop.step`` steps (module docstring), written atomically. The
    valid rows are copied to the host here; the file is written by a thread (training goes on
    meanwhile): ``wait()`` on the result before relying on the file."""
    n, size = int(valid.sum()), int(valid.shape[0])

    def host(x):  # a host copy of the valid rows: the device buffers may be donated to the next step
        x = np.array(x)  # whole, then sliced on the host (a device slice compiles a program per count)
        return x[:n] if x.ndim and x.shape[0] == size else x

    arrays = {f"params.{k}": host(getattr(params, k)) for k in Gaussians.__dataclass_fields__}
    arrays.update({f"state.{i}": host(leaf) for i, leaf in enumerate(jax.tree.leaves(state))})
    arrays["grad_sum"], arrays["seen"] = host(grad_sum), host(seen)
    meta = {"version": CHECKPOINT_VERSION, "stamp": stamp, "step": loop.step, "size": size, "n": n,
            "capacity": raster.capacity, "rng": rng.bit_generator.state, "order": [int(v) for v in loop.order],
            "losses": loop.losses, "events": loop.events, "resets": loop.resets, "buckets": sorted(loop.buckets),
            "retries": loop.retries}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)

    def write() -> None:
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        write_bytes(path, buf.getvalue())

    return _Written(write)


def load_checkpoint(path: Path, stamp: str, rng, raster: RasterConfig):
    """(params, valid, state, grad_sum, seen, raster, loop) from ``save_checkpoint``'s file;
    ``rng`` takes the saved state. A checkpoint of another training is a ``SceneInputError``."""
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    meta = json.loads(arrays.pop("meta").tobytes())
    if meta.get("version") != CHECKPOINT_VERSION or meta.get("stamp") != stamp:
        raise SceneInputError(path, "stamp", "a checkpoint of another training (other photos, SfM or settings): "
                              "run without --resume to start again")
    n, size = meta["n"], meta["size"]
    data = GaussianSplatData(**{k: arrays[f"params.{k}"] for k in Gaussians.__dataclass_fields__})
    params, valid = padded(data, size)
    leaves, treedef = jax.tree.flatten(splat_fit.init_state(params))

    def grown(x):
        return jnp.asarray(np.concatenate([x, np.zeros((size - n,) + x.shape[1:], x.dtype)]) if x.ndim and
                           x.shape[0] == n and n != size else x)

    state = jax.tree.unflatten(treedef, [grown(arrays[f"state.{i}"]).astype(leaf.dtype)
                                         for i, leaf in enumerate(leaves)])
    rng.bit_generator.state = meta["rng"]
    loop = _Loop(step=meta["step"], order=meta["order"], losses=meta["losses"], events=meta["events"],
                 resets=meta["resets"], buckets=set(meta["buckets"]), retries=meta["retries"])
    return (params, valid, state, grown(arrays["grad_sum"]), grown(arrays["seen"]),
            dataclasses.replace(raster, capacity=meta["capacity"]), loop)


def train_gaussians(init: GaussianSplatData, views: Views, extent: float, config: TrainConfig, rng,
                    background=(0.0, 0.0, 0.0), *, checkpoint: Path | None = None, resume: bool = False,
                    on_step: Callable[[int, float, int], None] | None = None, donate: bool = False,
                    compile_ahead: bool | None = None) -> Trained:
    """Train ``init`` on ``views`` (module docstring). extent: the scene scale the position's rate
    and the size thresholds are relative to; rng: a NumPy generator (view order, split offsets).

    checkpoint: where checkpoints go; with ``resume``, training continues from the one there.
    on_step(step, loss, gaussians) is called after every step (progress). donate: let each step
    reuse its inputs' device memory (smaller peak; the inputs are consumed). compile_ahead:
    compile the programs of the next sizes on a thread (``phirie_jax.capture.programs``); by
    default where the device is not the host's CPU, whose cores would otherwise run the steps.
    """
    stamp = fingerprint(config, views, init, extent)
    size = gaussian_bucket(init.num)
    params, valid = padded(init, size)
    state = splat_fit.init_state(params)
    raster = TRAINING_RASTER
    grad_sum, seen = jnp.zeros(size), jnp.zeros(size)
    loop = _Loop(buckets={size})
    resumed_at = None
    if resume and checkpoint is not None and Path(checkpoint).is_file():
        params, valid, state, grad_sum, seen, raster, loop = load_checkpoint(Path(checkpoint), stamp, rng, raster)
        resumed_at = loop.step
        count = int(valid.sum())
    else:
        count = init.num  # the valid Gaussians, kept on the host (reading the device's would wait for it)
        raster = dataclasses.replace(TRAINING_RASTER, capacity=first_capacity(params, valid, views))
    start_capacity = raster.capacity
    bg = jnp.asarray(background, jnp.float32)
    step_fn = _train_step_donated if donate else _train_step
    programs = Programs(enabled=jax.default_backend() != "cpu" if compile_ahead is None else compile_ahead)

    def statics(capacity: int) -> dict:
        return {"config": dataclasses.replace(raster, capacity=capacity), "dssim_weight": config.dssim_weight,
                "exact_screen_gradient": config.exact_screen_gradient}
    called: set = set()                 # program keys called so far
    compile_calls, step_times = [], []  # seconds of the calls that compiled a program; between checked steps
    densify_s = 0.0                     # time densifying (two programs and a count read back each)
    dispatch_s = wait_s = 0.0           # host time dispatching steps; waiting for a step's results
    inflight: list[tuple] = []          # (outputs, view) dispatched, not checked yet
    t0 = last_checked = time.perf_counter()
    written: _Written | None = None   # the checkpoint being written
    last_args: tuple = ()               # the arguments of the last step dispatched (their shapes)
    densifying = config.densify_from < config.densify_until

    asked: set = set()  # the sizes prepare() was asked for (each traced once: tracing takes the loop's host time)

    def prepare(rows: int, capacity: int) -> None:
        """Compile the step for these sizes, and densification at these rows, in the background
        (``phirie_jax.capture.programs``)."""
        if (rows, capacity) in asked:
            return
        asked.add((rows, capacity))
        params_, state_, lrs_, valid_, mask_, *view_, grad_sum_, seen_ = last_args
        programs.prepare(("step", rows, capacity), step_fn, (
            with_rows(params_, rows), with_rows(state_, rows), like(lrs_), with_rows(valid_, rows), like(mask_),
            *map(like, view_), with_rows(grad_sum_, rows), with_rows(seen_, rows)), **statics(capacity))
        if densifying:
            prepare_densify(programs, params_, state_, rows, config)

    def densifies(s: int) -> bool:  # after the step numbered s (from 1)
        return config.densify_from <= s < config.densify_until and s % config.densify_interval == 0

    def resets(s: int) -> bool:
        return bool(config.opacity_reset_interval) and s % config.opacity_reset_interval == 0 and s < config.densify_until

    def saves(s: int) -> bool:
        return checkpoint is not None and (bool(config.checkpoint_interval and s % config.checkpoint_interval == 0)
                                           or s == config.steps)

    def host_work_after(s: int) -> bool:
        """Does the step numbered s end with host work on the parameters?"""
        return densifies(s) or resets(s) or saves(s)

    if densifying:  # densification at the starting size, compiled while the first step compiles
        prepare_densify(programs, params, state, int(valid.shape[0]), config)
    switch_interval = sys.getswitchinterval()
    if programs.enabled:
        sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        while loop.step < config.steps or inflight:
            ahead = loop.step + len(inflight)  # steps done once those in flight succeed
            if (ahead < config.steps and len(inflight) < IN_FLIGHT
                    and not (inflight and host_work_after(ahead))):
                # Dispatch before checking the step in flight: the host's work overlaps the device's.
                if not loop.order:
                    loop.order = list(rng.permutation(views.count))
                view = loop.order.pop(0)
                key, t_call = ("step", int(valid.shape[0]), raster.capacity), time.perf_counter()
                last_args = (params, state, learning_rates(config, extent, ahead), valid, sh_mask(config, ahead),
                             views.Ks[view], views.world_to_cameras[view], views.images[view], bg, grad_sum, seen)
                out = programs(key, step_fn, *last_args, **statics(raster.capacity))
                if key not in called:
                    compile_calls.append(time.perf_counter() - t_call)
                    called.add(key)
                else:
                    dispatch_s += time.perf_counter() - t_call
                params, state, _, grad_sum, seen = out[:5]
                inflight.append((out, view))
                continue
            out, view = inflight.pop(0)
            t_wait = time.perf_counter()
            overflow, needed, loss = jax.device_get((out[6], out[7], out[2]))  # one transfer
            wait_s += time.perf_counter() - t_wait
            if overflow:  # the step changed nothing; grow and train its view again
                if int(needed) > raster.capacity:
                    raster = grown_capacity(raster, int(needed), "train at a lower resolution or with fewer Gaussians")
                loop.retries += 1
                loop.order.insert(0, view)
                continue
            if int(needed) > GROW_AHEAD * raster.capacity:  # the next capacity's program, before it overflows
                prepare(int(valid.shape[0]), 2 * raster.capacity)
            now = time.perf_counter()
            step_times.append(now - last_checked)
            last_checked = now
            loop.losses.append(float(loss))
            loop.step += 1
            s = loop.step
            if densifies(s):
                t_densify = time.perf_counter()
                reset = config.opacity_reset_interval
                params, valid, state, counts = densify_on_device(
                    params, valid, state, grad_sum, seen, extent, config, jax.random.key(rng.integers(2**31)),
                    prune_large=not reset or s > reset, programs=programs)
                size = int(valid.shape[0])
                loop.buckets.add(size)
                grad_sum, seen = jnp.zeros(size), jnp.zeros(size)
                count = int(counts.pop("count"))
                loop.events.append({"step": s, "gaussians": count, **counts})
                if loop.events[-1]["gaussians"] > GROW_AHEAD * size:  # the next bucket's program
                    prepare(2 * size, raster.capacity)
                densify_s += time.perf_counter() - t_densify
            if resets(s):
                params, state = reset_opacity(params, state, RESET_CEILING * config.min_opacity)
                loop.resets.append(s)
            if saves(s):
                if written is not None:
                    written.wait()
                written = save_checkpoint(Path(checkpoint), params, valid, state, grad_sum, seen, raster, loop, rng,
                                          stamp)
            if on_step is not None:
                on_step(s, loop.losses[-1], count)
    finally:  # a checkpoint is whole on disk before anything else happens, a kill included
        if written is not None:
            written.wait()
        programs.wait()
        sys.setswitchinterval(switch_interval)
    wall_s = time.perf_counter() - t0
    # the median leaves out the few intervals that held a compilation (one per program)
    step_s = float(np.median(step_times)) if step_times else 0.0
    compile_s = max(0.0, sum(compile_calls) - len(compile_calls) * step_s)
    gaussians = unpadded(params, valid)
    record = {
        "steps": config.steps, "gaussians": gaussians.num, "initial_gaussians": init.num,
        "loss_first": loop.losses[0] if loop.losses else None, "loss_last": loop.losses[-1] if loop.losses else None,
        "densify": loop.events, "opacity_resets": loop.resets, "buckets": sorted(loop.buckets),
        "capacity": raster.capacity, "first_capacity": start_capacity, "capacity_retries": loop.retries, "programs": len(called),
        "programs_compiled_ahead": sorted(programs.ready, key=str), "compile_ahead_s": round(programs.background_s, 3),
        "backend": jax.default_backend(), "device": str(jax.devices()[0]), "resumed_at": resumed_at,
        "wall_s": round(wall_s, 3), "step_s_median": round(step_s, 4),
        # calls that compiled, less a step each; ~0 when this process compiled the programs for an earlier run
        "compile_s": round(compile_s, 3), "run_s": round(wall_s - compile_s, 3), "densify_s": round(densify_s, 3),
        "dispatch_s": round(dispatch_s, 3), "wait_s": round(wait_s, 3), **step_spread(step_times),
        **({"compile_ahead_failed": programs.failed} if programs.failed else {})}
    return Trained(gaussians, raster, list(loop.losses), record)


def step_spread(step_times: list[float]) -> dict:
    """How the intervals between checked steps spread: quantiles, the mean of each tenth of the
    run, and the seconds spent above twice the median (compilations, host work, stalls)."""
    if not step_times:
        return {}
    t = np.asarray(step_times)
    median = float(np.median(t))
    tenths = [float(part.mean()) for part in np.array_split(t, min(10, len(t)))]
    return {"step_s_mean": round(float(t.mean()), 5), "step_s_quantiles": {
                q: round(float(np.quantile(t, float(q))), 5) for q in ("0.1", "0.5", "0.9", "0.99")},
            "step_s_by_tenth": [round(x, 5) for x in tenths],
            "slow_steps": int(np.sum(t > 2 * median)), "slow_steps_s": round(float(np.sum(t[t > 2 * median])), 3)}


def views_psnr(data: GaussianSplatData, views: Views, background, raster: RasterConfig, clip: bool = False
               ) -> np.ndarray:
    """(V,) PSNR of the set rendered, every SH band on, in each view against its image; clip: the
    renders clamped to [0, 1] first (as gsplat's evaluation does)."""
    params, valid = padded(data, gaussian_bucket(data.num))
    bg = jnp.asarray(background, jnp.float32)
    psnr = []
    for K, w2c, image in zip(views.Ks, views.world_to_cameras, views.images):  # one program for any view count
        while True:
            rgb, overflow = _render_view(params, valid, K, w2c, bg, width=views.width, height=views.height,
                                         config=raster)
            if not bool(overflow):
                break
            raster = grown_capacity(raster, 2 * raster.capacity, "score at a lower resolution")
        target = np.asarray(image, np.float64) / (255.0 if image.dtype == np.uint8 else 1.0)
        rgb = np.asarray(rgb[0], np.float64)
        mse = np.mean(((np.clip(rgb, 0.0, 1.0) if clip else rgb) - target) ** 2)
        psnr.append(10.0 * np.log10(1.0 / max(mse, 1e-12)))
    return np.asarray(psnr)


def fraction_step(fraction: float, steps: int) -> int:
    """The first whole step s with s ≥ fraction × steps (a schedule given in fractions of the run)."""
    return math.ceil(fraction * steps)
