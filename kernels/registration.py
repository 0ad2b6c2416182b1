"""Batched Sim(3) registration of a complete candidate shape to a partial observation.

The observation Q (observed surface samples of one instance) is given in a gravity frame
(+z up, support plane horizontal); the candidate's points P in its own canonical frame,
whose up axis and scale are unknown. A similarity S (x ↦ s R x + t) places P onto Q.

Search (the paper's "Object candidates and registered assets"):

1. Scale init per source-up axis from robust (2nd–98th percentile) extents of Q and P.
2. Hypotheses: every signed source-up axis a (→ +z) × ``num_yaws`` yaws about +z × scale
   multipliers; translation puts the candidate's horizontal box centre on Q's and its
   lowest point on the support (or on Q's 2nd-percentile height). Each is scored by
   E(S) = d_τ(SP, Q) + d_τ(Q, SP) on subsets of P and Q; all of them in one call.
3. The ``top_k`` best hypotheses of the candidate's own up (+z, when searched) and of the
   ``refine_other_axes`` other axes whose best sweep score is lowest are refined:
   partial-to-complete point-to-point ICP (each q ∈ Q matched to its nearest point of SP
   within ``max_corr``; Kabsch), then scale and translation refinement with R fixed.
4. Every refined hypothesis is scored again on all of P (and up to ``score_obs_points`` of
   Q): E, its two terms, and the observation support (fraction of Q within τ of SP).

The host picks among the refined hypotheses (the candidate's own up = axis +z first, the
other five axes on retry). Each step is written for one hypothesis and batched with
``vmap`` (through ``lax.map(batch_size=...)``) in ``register``, the one jitted entry; given a
``kernels.sharding.BatchMesh``, the hypotheses are spread over its devices (each maps its own).
Shapes are static: P has ``SearchSpec.model_points`` rows in random order (its leading
rows are the sweep and ICP subsets), Q is padded to a power of two with a mask and its
valid rows come first, in random order (its leading rows are the sweep subset).
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

from kernels.chamfer import FAR, clipped_chamfer_support, nearest_point
from kernels.pytree import pytree_dataclass
from kernels.sharding import BatchMesh, map_rows

Rotation = Literal["full", "yaw"]   # ICP's rotation: 3D Kabsch, or about +z only

# Signed source-up axes; index 0 (+z) is the candidate's own up, tried first by default.
UP_AXES = np.array([[0, 0, 1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, -1]], np.float64)
AXIS_NAMES = ("+z", "+x", "-x", "+y", "-y", "-z")
# AXIS_ROTATIONS[k]: the smallest proper rotation taking UP_AXES[k] to +z (a quarter turn for
# ±x, ±y; for −z the half turn about x), as its signed permutation matrix. The host's
# ``phirie_jax.geometry.rotation_to_z`` gives the same matrices (tests/kernels/test_registration.py).
AXIS_ROTATIONS = np.array([
    [[1, 0, 0], [0, 1, 0], [0, 0, 1]],     # +z: identity
    [[0, 0, -1], [0, 1, 0], [1, 0, 0]],    # +x: quarter turn about −y
    [[0, 0, 1], [0, 1, 0], [-1, 0, 0]],    # -x: quarter turn about +y
    [[1, 0, 0], [0, 0, -1], [0, 1, 0]],    # +y: quarter turn about +x
    [[1, 0, 0], [0, 0, 1], [0, -1, 0]],    # -y: quarter turn about −x
    [[1, 0, 0], [0, -1, 0], [0, 0, -1]],   # -z: half turn about x
], np.float64)
ROBUST_LO, ROBUST_HI = 0.02, 0.98  # paper: scale from the 2nd–98th percentile extents
MIN_EXTENT = 1e-9                  # guards the extent ratio of a flat candidate
MIN_CORRESPONDENCES = 3.0          # fewer than this (weighted) → keep the current pose
# Below this share of a model above the scoring floor (``scored_model``), the whole model is
# scored: a model that is mostly floor band (a 1 cm bump) must not be judged on a sliver.
MIN_SCORED_FRACTION = 0.5


@dataclasses.dataclass(frozen=True)
class SearchSpec:
    """Static shape of one registration program (each distinct value compiles once).

    Attributes:
        axes: indices into ``UP_AXES`` searched in this call (all six: retry costs no call).
        num_yaws: yaws per axis, evenly spaced (36 = the paper's 10°).
        scale_multipliers: multipliers of the per-axis scale init.
        top_k: hypotheses refined per refined axis.
        refine_other_axes: besides the own up (+z, always refined when it is in ``axes``), this many
            other axes are refined — those with the lowest sweep score. All six: set it to 5.
        model_points: rows of P (the paper's 20K).
        sweep_model_points / sweep_obs_points: leading rows of P / Q scoring the sweep.
        icp_model_points / icp_obs_points: leading rows of P / Q matched by the refinements.
        score_obs_points: leading rows of Q in the final scores (all of P is used); beyond a few
            thousand points a mean of clipped distances changes by well under 0.1 mm.
        icp_iterations / scale_iterations: fixed iteration counts of the two refinements.
        rotation: "full" (3D Kabsch) or "yaw" (rotation about +z only) in ICP.
        chunk: queries per brute-force nearest-neighbour block.
        hypothesis_batch: hypotheses vmapped together on each device (memory ∝ batch · chunk ·
            targets).
        snap_to_support: after refinement, move each hypothesis vertically so its lowest point
            is on the support when it is within τ of it (and a support is given).
    """

    axes: tuple[int, ...] = (0, 1, 2, 3, 4, 5)
    num_yaws: int = 36
    scale_multipliers: tuple[float, ...] = (0.85, 1.0, 1.15)
    top_k: int = 1
    refine_other_axes: int = 2
    model_points: int = 20_000
    sweep_model_points: int = 512
    sweep_obs_points: int = 512
    icp_model_points: int = 2048
    icp_obs_points: int = 2048
    score_obs_points: int = 4096
    icp_iterations: int = 20
    scale_iterations: int = 10
    rotation: Rotation = "full"
    chunk: int = 256
    hypothesis_batch: int = 36
    snap_to_support: bool = False

    @property
    def hypotheses_per_axis(self) -> int:
        return self.num_yaws * len(self.scale_multipliers)

    @property
    def num_hypotheses(self) -> int:
        return len(self.axes) * self.hypotheses_per_axis

    @property
    def own_searched(self) -> bool:
        return 0 in self.axes

    @property
    def refined_axes(self) -> int:
        return min(len(self.axes), int(self.own_searched) + self.refine_other_axes)


@pytree_dataclass
class Registration:
    """Refined hypotheses of one candidate: R = refined_axes · top_k rows, axis-major, the own
    up (+z) first when it was searched."""

    rotation: jax.Array      # (R, 3, 3)
    translation: jax.Array   # (R, 3)
    scale: jax.Array         # (R,)
    energy: jax.Array        # (R,) E on the full sets
    model_to_obs: jax.Array  # (R,) d_τ(SP, Q)
    obs_to_model: jax.Array  # (R,) d_τ(Q, SP)
    support: jax.Array       # (R,) fraction of Q within τ of SP
    axis: jax.Array          # (R,) int32 index into UP_AXES
    yaw: jax.Array           # (R,) initial yaw (radians) of the hypothesis it came from
    scale_init: jax.Array    # (R,) robust-extent scale init of its axis
    sweep_energy: jax.Array  # (A, num_yaws · M) E of every hypothesis of the sweep


# --- host constants ------------------------------------------------------------------


def axis_rotation(axis: np.ndarray) -> np.ndarray:
    """(3, 3) the entry of ``AXIS_ROTATIONS`` for ``axis`` (3,), one of the rows of ``UP_AXES``."""
    matches = np.flatnonzero(np.all(np.isclose(UP_AXES, np.asarray(axis, np.float64)), axis=1))
    if len(matches) != 1:
        raise ValueError(f"axis_rotation: {axis!r} is not one of UP_AXES")
    return AXIS_ROTATIONS[matches[0]].copy()


def yaw_matrix(yaw):
    """yaw (...,) radians → (..., 3, 3) rotation about +z."""
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    zero, one = jnp.zeros_like(c), jnp.ones_like(c)
    return jnp.stack([jnp.stack([c, -s, zero], -1), jnp.stack([s, c, zero], -1),
                      jnp.stack([zero, zero, one], -1)], -2)


# --- pieces for one hypothesis -------------------------------------------------------


def robust_extents(points, mask):
    """Height (z) and the two horizontal extents along the xy principal axes, each the
    2nd–98th percentile range of the valid points: points (N, 3), mask (N,) bool.
    → (3,) [h, w_major, w_minor]."""
    w = mask.astype(points.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    xy = points[:, :2]
    centred = xy - jnp.sum(xy * w[:, None], 0) / n
    cov = (centred * w[:, None]).T @ centred / n
    _, vecs = jnp.linalg.eigh(cov)                 # ascending eigenvalues
    proj = centred @ vecs[:, ::-1]                  # major axis first
    coords = jnp.concatenate([points[:, 2:3], proj], axis=1)
    coords = jnp.where(mask[:, None], coords, jnp.nan)
    lo, hi = jnp.nanquantile(coords, jnp.array([ROBUST_LO, ROBUST_HI]), axis=0)
    return hi - lo


def scale_init(model, obs_extents):
    """Median of the three extent ratios observed / model: model (Np, 3) already rotated to its up;
    obs_extents (3,) ``robust_extents`` of Q. → ()."""
    model_extents = robust_extents(model, jnp.ones(model.shape[0], bool))
    ratios = obs_extents / jnp.maximum(model_extents, MIN_EXTENT)
    return jnp.sum(ratios) - jnp.max(ratios) - jnp.min(ratios)


def place(model, rotation, scale, centre_xy, base_z):
    """Translation putting s R P's horizontal box centre at centre_xy (2,) and its lowest
    point at base_z (). model (Np, 3); rotation (3, 3); scale (). → (3,)."""
    x = scale * model @ rotation.T
    lo, hi = jnp.min(x, axis=0), jnp.max(x, axis=0)
    return jnp.concatenate([centre_xy - 0.5 * (lo[:2] + hi[:2]), (base_z - lo[2])[None]])


def scored_model(placed, floor):
    """Which placed model points E scores: placed (Np, 3), those at or above floor () — the
    observation holds no point lower than that (the support and a band above it are cut from
    Q), so a model point there has nothing it could match. When fewer than
    ``MIN_SCORED_FRACTION`` of the points remain (a flat model) every point is scored.
    → (Np,) bool."""
    above = placed[:, 2] >= floor
    return above | (jnp.mean(above.astype(placed.dtype)) < MIN_SCORED_FRACTION)


def hypothesis_energy(model, obs, obs_mask, rotation, scale, translation, tau, chunk: int, floor=None):
    """E(S) = d_τ(SP, Q) + d_τ(Q, SP) of one hypothesis; → (E, d_τ(SP, Q), d_τ(Q, SP), support).

    model (Np, 3) canonical, every row valid; obs (Nq, 3); obs_mask (Nq,) bool; rotation (3, 3);
    scale (); translation (3,); tau (); floor () or None: placed model points below this height
    take no part in either term (``scored_model``; None or −inf: every point). The score is
    ``kernels.chamfer.clipped_chamfer_support`` of the placed model against Q (its only home);
    support = fraction of valid q within τ of SP.
    """
    x = scale * model @ rotation.T + translation
    x_mask = None if floor is None else scored_model(x, floor)
    return clipped_chamfer_support(x, x_mask, obs, obs_mask, tau, chunk)


def _correspondences(model, obs, obs_mask, rotation, scale, translation, max_corr, chunk: int):
    """Each q's nearest point of S P (placed), and its weight: 1 when q is valid and the match
    is within max_corr (), else 0. model (Np, 3); obs (Nq, 3); obs_mask (Nq,) bool;
    rotation (3, 3); scale (); translation (3,). → (Nq, 3), (Nq,)."""
    x = scale * model @ rotation.T + translation
    d2, matched = nearest_point(obs, x, None, chunk)
    weight = (obs_mask & (d2 <= max_corr * max_corr) & (d2 < FAR)).astype(obs.dtype)
    return matched, weight


def _kabsch(src, dst, weight, yaw_only: bool):
    """Weighted rigid (R, t) minimising Σ w ‖R src + t − dst‖² (R about +z only if yaw_only).

    src (N, 3); dst (N, 3); weight (N,). → (3, 3), (3,)."""
    n = jnp.maximum(jnp.sum(weight), 1e-12)
    cs = jnp.sum(src * weight[:, None], 0) / n
    cd = jnp.sum(dst * weight[:, None], 0) / n
    a, b = src - cs, dst - cd
    if yaw_only:
        cross = jnp.sum(weight * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
        dot = jnp.sum(weight * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
        rot = yaw_matrix(jnp.arctan2(cross, dot))
    else:
        h = (a * weight[:, None]).T @ b
        u, _, vt = jnp.linalg.svd(h)
        d = jnp.sign(jnp.linalg.det(vt.T @ u.T))
        rot = vt.T @ jnp.diag(jnp.array([1.0, 1.0, 0.0], h.dtype) + d * jnp.array([0.0, 0.0, 1.0], h.dtype)) @ u.T
    ok = jnp.sum(weight) >= MIN_CORRESPONDENCES
    rot = jnp.where(ok, rot, jnp.eye(3, dtype=src.dtype))
    return rot, jnp.where(ok, cd - rot @ cs, 0.0)


def icp(model, obs, obs_mask, rotation, scale, translation, max_corr, iterations: int,
        yaw_only: bool, chunk: int):
    """Partial-to-complete point-to-point ICP with the scale fixed. → (R (3, 3), t (3,)).

    model (Np, 3); obs (Nq, 3); obs_mask (Nq,) bool; rotation (3, 3), scale (), translation (3,)
    the start; max_corr () metres."""

    def step(_, state):
        rot, trans = state
        placed, weight = _correspondences(model, obs, obs_mask, rot, scale, trans, max_corr, chunk)
        d_rot, d_trans = _kabsch(placed, obs, weight, yaw_only)
        return d_rot @ rot, d_rot @ trans + d_trans

    return jax.lax.fori_loop(0, iterations, step, (rotation, translation))


def refine_scale(model, obs, obs_mask, rotation, scale, translation, max_corr, iterations: int,
                 chunk: int):
    """Scale and translation refinement with R fixed: closed-form least squares per step.
    → (s (), t (3,)).

    model (Np, 3); obs (Nq, 3); obs_mask (Nq,) bool; rotation (3, 3); scale (), translation (3,)
    the start; max_corr () metres."""

    def step(_, state):
        s, trans = state
        placed, weight = _correspondences(model, obs, obs_mask, rotation, s, trans, max_corr, chunk)
        y = (placed - trans) / s  # R p of each match
        n = jnp.maximum(jnp.sum(weight), 1e-12)
        cy = jnp.sum(y * weight[:, None], 0) / n
        cq = jnp.sum(obs * weight[:, None], 0) / n
        a, b = y - cy, obs - cq
        num = jnp.sum(weight * jnp.sum(a * b, 1))
        den = jnp.sum(weight * jnp.sum(a * a, 1))
        ok = (jnp.sum(weight) >= MIN_CORRESPONDENCES) & (num > 0) & (den > 0)
        s_new = jnp.where(ok, num / jnp.where(den > 0, den, 1.0), s)
        return s_new, jnp.where(ok, cq - s_new * cy, trans)

    return jax.lax.fori_loop(0, iterations, step, (scale, translation))


# --- the batched program -------------------------------------------------------------


def register(model, obs, obs_mask, support_z, has_support, tau, max_corr, spec: SearchSpec,
             mesh: BatchMesh | None = None, floor=None) -> Registration:
    """Search, refine and score; see the module docstring. ``spec`` and ``mesh`` are static.

    model (model_points, 3) canonical, random order; obs (Nq, 3) gravity frame, valid rows
    first; obs_mask (Nq,) bool; support_z () height of the support plane, used when
    has_support () bool; tau () clip radius; max_corr () ICP correspondence radius (metres).
    mesh: the devices the hypotheses (of the sweep, then of the refinement) are spread over,
    ``hypothesis_batch`` at a time on each (``kernels.sharding.map_rows``); None: this device.
    floor () or None: every score leaves out the placed model points below this height
    (``hypothesis_energy``); ICP matches every point as before.
    """
    dtype = obs.dtype
    p_sweep = model[: spec.sweep_model_points]
    p_icp = model[: spec.icp_model_points]
    nq_sweep = min(spec.sweep_obs_points, obs.shape[0])
    q_sweep, m_sweep = obs[:nq_sweep], obs_mask[:nq_sweep]
    nq_icp = min(spec.icp_obs_points, obs.shape[0])
    q_icp, m_icp = obs[:nq_icp], obs_mask[:nq_icp]
    nq_score = min(spec.score_obs_points, obs.shape[0])
    q_score, m_score = obs[:nq_score], obs_mask[:nq_score]

    q = jnp.where(obs_mask[:, None], obs, jnp.nan)
    q_lo, q_hi = jnp.nanquantile(q, jnp.array([ROBUST_LO, ROBUST_HI]), axis=0)
    centre_xy = 0.5 * (q_lo[:2] + q_hi[:2])
    base_z = jnp.where(has_support, support_z, q_lo[2])
    obs_ext = robust_extents(obs, obs_mask)

    axis_rots = jnp.asarray(AXIS_ROTATIONS[list(spec.axes)], dtype)
    s0 = jax.vmap(lambda r: scale_init(p_icp @ r.T, obs_ext))(axis_rots)  # (A,)

    yaws = jnp.arange(spec.num_yaws, dtype=dtype) * (2 * np.pi / spec.num_yaws)
    mults = jnp.asarray(spec.scale_multipliers, dtype)
    a_idx, y_idx, m_idx = (g.reshape(-1) for g in jnp.meshgrid(
        jnp.arange(len(spec.axes)), jnp.arange(spec.num_yaws), jnp.arange(len(mults)), indexing="ij"))
    rots = yaw_matrix(yaws[y_idx]) @ axis_rots[a_idx]      # (H, 3, 3)
    scales = s0[a_idx] * mults[m_idx]                        # (H,)

    cut = jnp.asarray(-jnp.inf if floor is None else floor, dtype)

    def sweep_one(shared, h):
        p, q, m, centre, base, clip, low = shared
        rot, s = h
        t = place(p, rot, s, centre, base)
        return hypothesis_energy(p, q, m, rot, s, t, clip, spec.chunk, low)[0]

    energy = map_rows(sweep_one, (p_sweep, q_sweep, m_sweep, centre_xy, base_z, tau, cut), (rots, scales),
                      spec.hypothesis_batch, mesh)
    per_axis = energy.reshape(len(spec.axes), spec.hypotheses_per_axis)
    axis_best = jnp.min(per_axis, axis=1)
    if spec.own_searched:
        own = spec.axes.index(0)
        others = jnp.where(jnp.arange(len(spec.axes)) == own, jnp.inf, axis_best)
        _, more = jax.lax.top_k(-others, spec.refined_axes - 1)
        chosen = jnp.concatenate([jnp.array([own]), more])
    else:
        _, chosen = jax.lax.top_k(-axis_best, spec.refined_axes)
    _, best = jax.lax.top_k(-per_axis[chosen], spec.top_k)                          # (refined axes, k)
    pick = (best + chosen[:, None] * spec.hypotheses_per_axis).reshape(-1)

    def refine_one(shared, h):
        full, p, q, m, q_full, m_full, centre, base, supported, clip, corr, low = shared
        rot, s = h
        t = place(p, rot, s, centre, base)
        rot, t = icp(p, q, m, rot, s, t, corr, spec.icp_iterations, spec.rotation == "yaw", spec.chunk)
        s, t = refine_scale(p, q, m, rot, s, t, corr, spec.scale_iterations, spec.chunk)
        if spec.snap_to_support:
            gap = base - (jnp.min(s * full @ rot[2]) + t[2])
            t = t.at[2].add(jnp.where(supported & (jnp.abs(gap) < clip), gap, 0.0))
        e, mq, qm, sup = hypothesis_energy(full, q_full, m_full, rot, s, t, clip, spec.chunk, low)
        return rot, t, s, e, mq, qm, sup

    shared = (model, p_icp, q_icp, m_icp, q_score, m_score, centre_xy, base_z, has_support, tau, max_corr, cut)
    rot, t, s, e, mq, qm, sup = map_rows(refine_one, shared, (rots[pick], scales[pick]),
                                         spec.hypothesis_batch, mesh)
    axis_ids = jnp.asarray(spec.axes, jnp.int32)[a_idx[pick]]
    return Registration(rot, t, s, e, mq, qm, sup, axis_ids, yaws[y_idx[pick]], s0[a_idx[pick]], per_axis)
