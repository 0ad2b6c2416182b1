"""Host side of registration: sample P, bucket Q, call the jitted kernel, read results.

One compiled program per (Q bucket, search shape): Q is padded to a power of two
(``obs_bucket``) and P always has ``RegistrationConfig.points`` rows, so every candidate
of every instance in the same bucket reuses the program (``TRACE_COUNTS`` counts traces).
``search`` spreads the hypotheses over every device JAX sees (or those given) with one program.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from kernels.registration import (
    AXIS_NAMES,
    Registration,
    SearchSpec,
    hypothesis_energy,
    register,
    robust_extents,
    scale_init,
)
from kernels.sharding import BatchMesh
from phirie_jax.construct.objects.config import RegistrationConfig

TRACE_COUNTS = {"register": 0, "score": 0}
ALL_AXES = (0, 1, 2, 3, 4, 5)
OWN_AXIS = (0,)          # +z: the candidate's own up
OTHER_AXES = (1, 2, 3, 4, 5)


def _traced_register(model, obs, mask, support_z, has_support, tau, max_corr, floor, *, spec, mesh):
    TRACE_COUNTS["register"] += 1  # runs only while tracing: once per compiled program
    return register(model, obs, mask, support_z, has_support, tau, max_corr, spec, mesh, floor)


def _traced_score(model, obs, mask, rotation, scale, translation, tau, floor, *, chunk):
    TRACE_COUNTS["score"] += 1
    energy, mq, qm, support = hypothesis_energy(model, obs, mask, rotation, scale, translation, tau, chunk, floor)
    return energy, mq, qm, support, scale * scale_init(model @ rotation.T, robust_extents(obs, mask))


_register_jit = jax.jit(_traced_register, static_argnames=("spec", "mesh"))
_score_jit = jax.jit(_traced_score, static_argnames=("chunk",))


def obs_bucket(n: int, minimum: int) -> int:
    """Padded size of Q for n points: the next power of two, at least ``minimum``."""
    return max(minimum, 1 << max(0, int(n) - 1).bit_length())


@dataclasses.dataclass(frozen=True)
class Observation:
    points: np.ndarray   # (B, 3) float32 gravity frame; valid rows first, in random order
    mask: np.ndarray     # (B,) bool
    count: int
    support_z: float
    has_support: bool
    floor: float = -np.inf  # E leaves out model points placed below this (``scored_model``)
    size: float = 0.0       # the diagonal of Q's 2–98 % box, metres (``observed_size``)


def observed_size(points: np.ndarray) -> float:
    """The diagonal of the (N, 3) points' 2–98 % box: the observed object's size, robust to strays."""
    if len(points) == 0:
        return 0.0
    lo, hi = np.percentile(np.asarray(points, np.float64), [2, 98], axis=0)
    return float(np.linalg.norm(hi - lo))


def prepare_observation(q_gravity: np.ndarray, support_z: float, has_support: bool,
                        config: RegistrationConfig, cut: float | None = None) -> Observation:
    """Q padded to its bucket. ``cut``: Q's points less than this above the support were cut
    (the instance's ``Support.clearance``), so E leaves out the model points below that height
    (with ``config.skip_cut_base``)."""
    n = len(q_gravity)
    bucket = obs_bucket(n, config.min_obs_bucket)
    order = np.random.default_rng(config.seed).permutation(n)
    points = np.zeros((bucket, 3), np.float32)
    points[:n] = q_gravity[order]
    mask = np.zeros(bucket, bool)
    mask[:n] = True
    floor = -np.inf
    if cut is not None and config.skip_cut_base:
        floor = float(support_z) + cut
    return Observation(points, mask, n, float(support_z), bool(has_support), floor, observed_size(q_gravity))


def sample_model(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int) -> np.ndarray:
    """(count, 3) float32 area-weighted surface samples, in random order."""
    rng = np.random.default_rng(seed)
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(tri), size=count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[face]
    points = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    return points.astype(np.float32)


@dataclasses.dataclass(frozen=True)
class Hypothesis:
    """One registered placement of a candidate (canonical → gravity frame)."""

    axis: str              # the candidate's axis taken as up
    yaw_deg: float         # initial yaw of the sweep hypothesis it was refined from
    matrix: np.ndarray     # (4, 4) s R | t
    scale: float
    scale_init: float
    energy: float          # E = d_τ(SP, Q) + d_τ(Q, SP), metres
    model_to_obs: float
    obs_to_model: float
    support: float         # fraction of Q within τ of SP

    @property
    def finite(self) -> bool:
        return bool(np.all(np.isfinite(self.matrix)) and np.isfinite(self.energy) and self.scale > 0)

    def scores(self) -> dict:
        return {"energy": self.energy, "model_to_obs": self.model_to_obs, "obs_to_model": self.obs_to_model,
                "support": self.support, "scale": self.scale, "scale_init": self.scale_init,
                "axis": self.axis, "yaw_deg": self.yaw_deg}


CPU_HYPOTHESIS_BATCH = 36   # bounds memory on a CPU; a GPU takes every hypothesis at once


def search_spec(config: RegistrationConfig, axes: tuple[int, ...], snap: bool) -> SearchSpec:
    """The configured search over ``axes``, with the hypothesis batch resolved for this backend."""
    batch = config.hypothesis_batch
    if batch is None:
        batch = CPU_HYPOTHESIS_BATCH if jax.default_backend() == "cpu" else len(axes) * config.search.hypotheses_per_axis
    return dataclasses.replace(config.search, axes=tuple(axes), hypothesis_batch=batch, snap_to_support=snap)


def _matrix(rotation, scale, translation) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = float(scale) * np.asarray(rotation, np.float64)
    m[:3, 3] = np.asarray(translation, np.float64)
    return m


def search(model: np.ndarray, obs: Observation, config: RegistrationConfig, axes: tuple[int, ...],
           snap: bool = True, devices=None) -> tuple[list[Hypothesis], Registration]:
    """Register one candidate over ``axes``: the best refined hypothesis of each axis (in the
    order of ``axes``) and the kernel's raw output. The hypotheses are spread over ``devices``
    (``kernels.sharding.resolve_devices``: None, every device; one program for any count)."""
    spec = search_spec(config, axes, snap)
    out = _register_jit(jnp.asarray(model), jnp.asarray(obs.points), jnp.asarray(obs.mask),
                        jnp.float32(obs.support_z), jnp.bool_(obs.has_support), jnp.float32(config.tau),
                        jnp.float32(config.icp_max_correspondence), jnp.float32(obs.floor), spec=spec,
                        mesh=BatchMesh.over(devices))
    out = jax.device_get(out)
    best: dict[int, Hypothesis] = {}
    for r in range(len(out.energy)):
        axis = int(out.axis[r])
        h = Hypothesis(AXIS_NAMES[axis], float(np.degrees(out.yaw[r])),
                       _matrix(out.rotation[r], out.scale[r], out.translation[r]), float(out.scale[r]),
                       float(out.scale_init[r]), float(out.energy[r]), float(out.model_to_obs[r]),
                       float(out.obs_to_model[r]), float(out.support[r]))
        if axis not in best or not (best[axis].energy <= h.energy):
            best[axis] = h
    return [best[a] for a in axes if a in best], out


def score_placement(model: np.ndarray, obs: Observation, placement: np.ndarray,
                    config: RegistrationConfig) -> Hypothesis:
    """Score a known placement (canonical → gravity, rigid) on the full point sets."""
    rot, trans = placement[:3, :3], placement[:3, 3]
    n = min(config.search.score_obs_points, len(obs.points))
    energy, mq, qm, support, s0 = jax.device_get(_score_jit(
        jnp.asarray(model), jnp.asarray(obs.points[:n]), jnp.asarray(obs.mask[:n]), jnp.asarray(rot, jnp.float32),
        jnp.float32(1.0), jnp.asarray(trans, jnp.float32), jnp.float32(config.tau), jnp.float32(obs.floor),
        chunk=config.search.chunk))
    return Hypothesis("+z", 0.0, placement.copy(), 1.0, float(s0), float(energy), float(mq), float(qm),
                      float(support))
