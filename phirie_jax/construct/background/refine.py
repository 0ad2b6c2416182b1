"""Host driver of the disk refinement (``kernels.fill``): static buckets, capacity, the Adam loop.

Every disk of every object is refined together against every frame: a disk may show in
another object's frame, and one loss keeps them consistent. Shapes are bucketed so a second
scene of the same buckets reuses the compiled step: disks and slab Gaussians padded to powers
of two (transparent padding), frames padded to a power of two with empty frames (zero mask,
a camera that sees nothing). The intersection capacity starts at twice what the initial disks
need (bounded on the host from the disks' largest extent) and grows (one recompile) if a step
reports overflow; that step is then repeated.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from kernels import fill as fill_kernel
from kernels.gaussians import Gaussians
from kernels.raster import RasterConfig
from phirie_jax.construct.background.config import BackgroundConfig
from phirie_jax.construct.background.targets import Frame
from phirie_jax.construct.background.views import padded, to_device
from phirie_jax.geometry import sigmoid
from phirie_jax.progress import task
from phirie_jax.render import gaussian_bucket, grown_capacity, next_power_of_two
from phirie_jax.types import GaussianSplatData

MIN_CAPACITY = 1 << 14
EMPTY_DEPTH = -1e6      # padding frames: a camera translation that puts everything behind it
MIN_OPACITY = 1.0 / 255.0  # disks fitted below this are dropped (they never show)

_step = jax.jit(fill_kernel.fill_step, static_argnames=("width", "config", "dssim_weight"))


@dataclasses.dataclass(frozen=True)
class DiskSet:
    """All objects' disks: their Gaussians (SH DC) and in-plane axes, in one array each."""

    disks: GaussianSplatData  # (N,) SH DC only
    tangents: np.ndarray      # (N, 2, 3)
    owner: np.ndarray         # (N,) object id

    def normals(self) -> np.ndarray:
        """(N, 3) unit plane normals (u × v)."""
        return np.cross(self.tangents[:, 0], self.tangents[:, 1]).astype(np.float64)


def geometry(disk_set: DiskSet, size: int, grid: float, max_sigma: float) -> fill_kernel.FillGeometry:
    n = disk_set.disks.num
    pad = size - n
    d = disk_set.disks
    return fill_kernel.FillGeometry(
        centres=to_device(np.concatenate([d.means, np.zeros((pad, 3), np.float32)])),
        tangents=to_device(np.concatenate([disk_set.tangents, np.zeros((pad, 2, 3))]).astype(np.float32)),
        quats=to_device(np.concatenate([d.quats, np.tile([[1.0, 0, 0, 0]], (pad, 1))]).astype(np.float32)),
        log_thickness=to_device(np.concatenate([d.log_scales[:, 2], np.full(pad, -10.0)]).astype(np.float32)),
        valid=to_device(np.arange(size) < n),
        max_offset=jnp.float32(grid), min_log_scale=jnp.float32(np.log(0.25 * grid)),
        max_log_scale=jnp.float32(np.log(max_sigma * grid)))


def initial_params(disk_set: DiskSet, size: int) -> fill_kernel.FillParams:
    d = disk_set.disks
    pad = size - d.num
    return fill_kernel.FillParams(
        dc=to_device(np.concatenate([d.sh[:, 0], np.zeros((pad, 3), np.float32)])),
        opacity_logits=to_device(np.concatenate([d.opacity_logits, np.full(pad, -10.0, np.float32)])),
        raw_offsets=jnp.zeros((size, 2), jnp.float32),
        log_scales=to_device(np.concatenate([d.log_scales[:, :2], np.zeros((pad, 2), np.float32)])))


def frame_disks(disk_set: DiskSet, frame: Frame, max_sigma: float, max_offset: float) -> np.ndarray:
    """Indices of the disks (any object's) that can touch the frame's reachable pixels while fitted."""
    from phirie_jax.construct.background.targets import touching

    grown = dataclasses.replace(disk_set.disks, log_scales=np.full_like(disk_set.disks.log_scales, np.log(
        max_sigma + max_offset)))  # a disk moved by its offset stays inside a disc of σ + offset (3σ bound)
    return np.flatnonzero(touching(grown, frame.crop, frame.reach))


def stack_frames(frames: list[Frame], count: int, disk_lists: list[np.ndarray]) -> fill_kernel.FillFrame:
    """The frames as one batched ``FillFrame`` of ``count`` (≥ len(frames)) entries, stacked and
    padded on the host (one transfer per field; on the device every slab of a new size compiled
    its own padding programs)."""
    slab_size = gaussian_bucket(max(f.slab.num for f in frames))
    disk_size = gaussian_bucket(max(len(d) for d in disk_lists))
    size = frames[0].crop.size
    items = []
    for k in range(count):
        if k < len(frames):
            f = frames[k]
            disks = np.zeros(disk_size, np.int32)
            disks[: len(disk_lists[k])] = disk_lists[k]
            items.append({
                "K": np.asarray(f.crop.camera.K, np.float32),
                "world_to_camera": np.asarray(f.crop.camera.world_to_camera, np.float32),
                "slab": padded(f.slab, slab_size), "front_rgb": f.front_rgb, "front_trans": f.front_trans,
                "back_rgb": f.back_rgb, "kept_rgb": f.kept_rgb, "reach": f.reach, "target": f.target,
                "mask": f.mask, "disks": disks, "disk_valid": np.arange(disk_size) < len(disk_lists[k])})
        else:  # a padding frame: the first one's arrays seen by a camera that sees nothing, no loss
            w2c = np.eye(4, dtype=np.float32)
            w2c[2, 3] = EMPTY_DEPTH
            items.append({**items[0], "world_to_camera": w2c, "mask": np.zeros((size, size), np.float32)})

    def stacked(key):
        return to_device(np.stack([np.asarray(item[key]) for item in items]))

    slab = Gaussians(**{k: to_device(np.stack([item["slab"][k] for item in items])) for k in items[0]["slab"]})
    return fill_kernel.FillFrame(
        K=stacked("K"), world_to_camera=stacked("world_to_camera"), slab=slab, disks=stacked("disks"),
        disk_valid=stacked("disk_valid"), front_rgb=stacked("front_rgb"), front_trans=stacked("front_trans"),
        back_rgb=stacked("back_rgb"), kept_rgb=stacked("kept_rgb"), reach=stacked("reach"),
        target=stacked("target"), mask=stacked("mask"))


_fill_gaussians = jax.jit(fill_kernel.fill_gaussians)


def _to_data(params: fill_kernel.FillParams, geom: fill_kernel.FillGeometry, n: int, sh_coeffs: int
             ) -> GaussianSplatData:
    g = jax.tree.map(np.asarray, _fill_gaussians(params, geom))  # one program, sliced on the host
    sh = np.zeros((n, sh_coeffs, 3), np.float32)
    sh[:, 0] = g.sh[:n, 0]
    return GaussianSplatData(means=np.asarray(g.means[:n], np.float32), quats=np.asarray(g.quats[:n], np.float32),
                             log_scales=np.asarray(g.log_scales[:n], np.float32),
                             opacity_logits=np.asarray(g.opacity_logits[:n], np.float32), sh=sh)


def tile_intersections(data: GaussianSplatData, crop, tile: int) -> int:
    """An upper bound of the tile intersections of ``data`` in a crop (the radius bound's squares)."""
    from phirie_jax.construct.background.views import screen_radius_bound

    if data.num == 0:
        return 0
    uv, z, r = screen_radius_bound(data, crop.camera)
    tiles = -(-crop.size // tile)
    lo = np.clip(np.floor((uv - r[:, None]) / tile), 0, tiles)
    hi = np.clip(np.floor((uv + r[:, None]) / tile), -1, tiles - 1)
    span = np.maximum(hi - lo + 1, 0)
    return int(np.sum(np.where(z > 0, span[:, 0] * span[:, 1], 0)))


@dataclasses.dataclass
class _Fit:
    """What the Adam loop hands back: the final parameters and the run's losses and counts."""

    params: fill_kernel.FillParams
    raster: RasterConfig
    losses: list[float]               # (steps + 1,) the loss before each step and after the last
    frame_losses: list[np.ndarray]    # (steps + 1,) of (F,) per-frame losses
    steps: int
    retries: int
    first_s: float
    loop_s: float


def _fit(params, geom, stacked, lrs, raster: RasterConfig, statics: dict, iterations: int, num_frames: int) -> _Fit:
    """The Adam loop. One compiled program: the step returns the loss of the parameters it was
    given, so the initial loss is the first step's and the final loss one more call's (whose update
    is dropped). A step that overflows the intersection capacity grows it and is repeated."""
    opt_state = fill_kernel.init_state(params)
    losses, frame_losses = [], []
    steps = retries = 0
    first_s = None
    t0 = time.perf_counter()
    with task("fill refinement (Adam steps)", iterations) as advance:
        while True:
            new_params, new_state, loss, (per_frame, overflow, needed) = _step(params, opt_state, geom, stacked, lrs,
                                                                               config=raster, **statics)
            if bool(overflow):  # this step's gradient is incomplete: grow, repeat it
                raster = _grow(raster, int(needed))
                retries += 1
                continue
            if first_s is None:
                first_s = time.perf_counter() - t0
            losses.append(float(loss))
            frame_losses.append(np.asarray(per_frame)[:num_frames])
            if steps == iterations:
                break
            params, opt_state = new_params, new_state
            steps += 1
            advance()
    return _Fit(params, raster, losses, frame_losses, steps, retries, first_s, time.perf_counter() - t0 - first_s)


def _capacity(disk_set: DiskSet, frames: list[Frame], disk_lists: list[np.ndarray], config: BackgroundConfig
              ) -> RasterConfig:
    """The raster config of the fit: its intersection capacity twice what the disks at their largest
    σ and the slab need in the busiest frame (a power of two, at least ``MIN_CAPACITY``)."""
    grown = dataclasses.replace(disk_set.disks, log_scales=np.full_like(
        disk_set.disks.log_scales, np.log(config.fill.max_disk_sigma * config.fill.grid)))
    tile = RasterConfig().tile_size
    estimate = max(tile_intersections(grown.subset(d), f.crop, tile) + tile_intersections(f.slab, f.crop, tile)
                   for f, d in zip(frames, disk_lists))
    return RasterConfig(capacity=max(MIN_CAPACITY, next_power_of_two(estimate)))


def refine(disk_set: DiskSet, frames: list[Frame], config: BackgroundConfig, sh_coeffs: int
           ) -> tuple[GaussianSplatData, dict]:
    """Fit the disks to the frames' targets. Returns the refined disks (SH padded to ``sh_coeffs``,
    those fitted transparent dropped) and a record (losses, steps, buckets, times).

    A fit that does not lower the loss (or diverges) is reverted to the initial disks.
    """
    fill, opt = config.fill, config.refine
    n = disk_set.disks.num
    size = gaussian_bucket(n)
    geom = geometry(disk_set, size, fill.grid, fill.max_disk_sigma)
    init_params = initial_params(disk_set, size)
    batch = next_power_of_two(len(frames))
    disk_lists = [frame_disks(disk_set, f, fill.max_disk_sigma * fill.grid, fill.grid) for f in frames]
    stacked = stack_frames(frames, batch, disk_lists)
    width = frames[0].crop.size
    lrs = fill_kernel.FillParams(dc=jnp.float32(opt.lr_colour), opacity_logits=jnp.float32(opt.lr_opacity),
                                 raw_offsets=jnp.float32(opt.lr_offset), log_scales=jnp.float32(opt.lr_scale))
    statics = {"width": width, "dssim_weight": float(opt.dssim_weight)}
    fit = _fit(init_params, geom, stacked, lrs, _capacity(disk_set, frames, disk_lists, config), statics,
               opt.iterations, len(frames))
    losses, params, reverted = fit.losses, fit.params, None
    if not np.isfinite(losses[-1]) or losses[-1] > losses[0]:
        reverted = "the fit did not lower the loss" if np.isfinite(losses[-1]) else "the fit diverged"
        params = init_params
    data = _to_data(params, geom, n, sh_coeffs)
    alive = sigmoid(data.opacity_logits) >= MIN_OPACITY
    record = {
        "disks": n, "disks_kept": int(alive.sum()), "frames": len(frames), "buckets": {
            "disks": size, "frames": batch, "crop": width, "slab": int(stacked.slab.means.shape[1]),
            "frame_disks": int(stacked.disks.shape[1]),
            "capacity": fit.raster.capacity},
        "steps": fit.steps, "capacity_retries": fit.retries, "loss_initial": losses[0], "loss_final": losses[-1],
        "frame_loss_initial": fit.frame_losses[0].round(6).tolist(),
        "frame_loss_final": fit.frame_losses[-1].round(6).tolist(),
        "loss_curve": np.asarray(losses).round(6).tolist(), "reverted": reverted,
        "first_call_s": round(fit.first_s, 3), "loop_s": round(fit.loop_s, 3)}
    return data.subset(alive), record


def _grow(raster: RasterConfig, needed: int) -> RasterConfig:
    return grown_capacity(raster, needed, "use a smaller crop size or a coarser grid")
