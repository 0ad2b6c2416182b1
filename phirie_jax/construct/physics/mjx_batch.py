"""Every drop test of a batch in one vmapped, jitted MJX program.

The program depends only on static shapes: the number of convex parts (a bucket, padded
with ghost parts) and the vertex budget of a part (hulls padded by repeating their first
vertex; MJX's plane-convex manifold picks the lowest index among equal points and drops
repeats, so padding adds no contact). Candidates differ only in *model data*: per-body
inertia, per-geom frame/size/friction, per-part hull vertices and the solver's inertia
scale. So one canonical template model per bucket is put on the device once; the values
of each candidate, read from its own compiled MuJoCo C model (the reference runs exactly
those models), are stacked along a leading axis and vmapped over. The candidate count is
padded to a power of two, so compile time does not grow with it and a second batch of the
same bucket reuses the program (``TRACES`` counts traces; the tests check it).

The candidates are spread over the devices of a ``kernels.sharding.BatchMesh`` (every device JAX
sees, unless told otherwise): the batch is padded to a multiple of their count as well, its
rows split over them, the template replicated; one program for any number of devices, each
device simulating its own candidates.

``simulate_one`` is the single-candidate kernel (pure: arrays in, arrays out); ``run``
vmaps it in one place.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from kernels.sharding import BatchMesh, pad_rows
from phirie_jax.construct.physics.config import DropTestConfig

# Model fields that vary per candidate (floats): stacked and vmapped.
BATCHED = ("body_ipos", "body_iquat", "body_mass", "body_subtreemass", "body_inertia", "body_invweight0",
           "dof_invweight0", "dof_M0", "geom_pos", "geom_quat", "geom_size", "geom_rbound", "geom_aabb",
           "geom_friction", "geom_solref", "geom_solimp")
# Fields allowed to differ and not used by a plane-only MJX step: mesh storage (MJX collides the
# stacked hull vertices instead), the C library's "same frame" / "simple body" shortcuts that MJX
# does not read (checked in its source), private sizes.
UNUSED = ("body_sameframe", "geom_sameframe")
# The sparse mass-matrix pattern: diagonal for a "simple" body (inertial frame = body frame), dense
# 6×6 otherwise. The template is never simple, and the dense pattern holds the diagonal one, so a
# simple candidate is simulated exactly (its off-diagonal entries come out zero).
SPARSITY = ("body_simple", "dof_simplenum", "M_rownnz", "M_rowadr", "M_colind")
TRACES = {"count": 0}   # incremented when the kernel is traced (a compile); for the tests


def _impl(model):
    """MJX keeps JAX-only fields in ``model._impl`` since 3.3; older versions on the model."""
    return getattr(model, "_impl", None) or model


def hull_vertices(model: mujoco.MjModel, mesh_id: int) -> np.ndarray:
    """(V, 3) vertices of a compiled mesh's convex hull in its mesh frame (what MJX collides)."""
    start, count = model.mesh_vertadr[mesh_id], model.mesh_vertnum[mesh_id]
    graph = model.mesh_graph[model.mesh_graphadr[mesh_id]:]
    numvert = int(graph[0])
    ids = graph[2 + numvert: 2 + 2 * numvert]
    return np.asarray(model.mesh_vert[start:start + count][ids], np.float64)


def _check_compatible(template: mujoco.MjModel, model: mujoco.MjModel) -> None:
    """Every field not stacked must equal the template's, or the batch would simulate wrong models."""
    for name in (f.name for f in mjx.Model.fields() if f.name not in ("_impl", "opt", "stat")):
        if (name in BATCHED or name in UNUSED or name in SPARSITY or name.startswith(("mesh_", "_"))
                or not hasattr(model, name)):
            continue
        a, b = getattr(template, name), getattr(model, name)
        if isinstance(a, np.ndarray) and (a.shape != b.shape or not np.array_equal(a, b)):
            raise ValueError(f"drop-test model field {name!r} differs from the bucket template "
                             "(the batch would simulate the wrong model)")
    for name in ("timestep", "iterations", "ls_iterations", "tolerance", "integrator", "cone", "solver", "jacobian"):
        if getattr(template.opt, name) != getattr(model.opt, name):
            raise ValueError(f"drop-test option {name!r} differs from the bucket template")


def stack_params(template: mujoco.MjModel, models: list[mujoco.MjModel], budget: int) -> dict[str, np.ndarray]:
    """Per-candidate model data, stacked: BATCHED fields, hull vertices (N, P, budget, 3), meaninertia (N,)."""
    if template.body_simple[1]:
        raise ValueError("the bucket template's body must not be simple (its mass-matrix pattern must be dense)")
    params = {name: np.stack([getattr(m, name) for m in models]) for name in BATCHED}
    verts = np.empty((len(models), template.nmesh, budget, 3))
    for i, m in enumerate(models):
        _check_compatible(template, m)
        for j in range(m.nmesh):
            hull = hull_vertices(m, j)
            if len(hull) > budget:
                raise ValueError(f"a convex part has {len(hull)} hull vertices (> the vertex budget {budget})")
            verts[i, j, : len(hull)] = hull
            verts[i, j, len(hull):] = hull[0]
    params["vert"] = verts
    params["meaninertia"] = np.array([m.stat.meaninertia for m in models])
    return params


def bind(template: mjx.Model, params: dict) -> mjx.Model:
    """The template with one candidate's data (``params`` unbatched: one candidate's rows)."""
    impl = _impl(template)
    convex = tuple(c.replace(vert=params["vert"][i]) for i, c in enumerate(impl.mesh_convex))
    fields = {name: params[name] for name in BATCHED}
    stat = template.stat.replace(meaninertia=params["meaninertia"])
    if impl is template:
        return template.replace(**fields, stat=stat, mesh_convex=convex)
    return template.replace(**fields, stat=stat, _impl=impl.replace(mesh_convex=convex))


def simulate_one(template: mjx.Model, data0: mjx.Data, params: dict, qpos0: jax.Array,
                 settle_steps: int, free_steps: int, unroll: int = 1) -> tuple[jax.Array, jax.Array]:
    """The drop-test protocol for one candidate: ``settle_steps`` with velocities zeroed after
    each step, then ``free_steps`` free (``unroll`` steps per loop iteration). Returns qpos (7,)
    after settling and at the end."""
    TRACES["count"] += 1
    model = bind(template, params)
    data = data0.replace(qpos=qpos0.astype(data0.qpos.dtype))

    def settle(d, _):
        d = mjx.step(model, d)
        return d.replace(qvel=jnp.zeros_like(d.qvel)), None

    def free(d, _):
        return mjx.step(model, d), None

    data, _ = jax.lax.scan(settle, data, length=settle_steps, unroll=unroll)
    settled = data.qpos
    data, _ = jax.lax.scan(free, data, length=free_steps, unroll=unroll)
    return settled, data.qpos


@functools.partial(jax.jit, static_argnums=(4, 5, 6, 7))
def _batched(template, data0, params, qpos0, settle_steps, free_steps, unroll, mesh: BatchMesh):
    def local(template, data0, params, qpos0):
        return jax.vmap(simulate_one, in_axes=(None, None, 0, 0, None, None, None))(
            template, data0, params, qpos0, settle_steps, free_steps, unroll)

    return mesh.map(local, (False, False, True, True))(template, data0, params, qpos0)


def padded_count(n: int, config: DropTestConfig, mesh: BatchMesh | None = None) -> int:
    """Candidates are padded to a power of two ≥ ``min_batch`` (≤ ``max_batch``), then to a
    multiple of the mesh's device count."""
    count = min(config.max_batch, max(config.min_batch, 1 << max(0, (n - 1).bit_length())))
    return count if mesh is None else mesh.padded(count)


def device_args(template: tuple[mjx.Model, mjx.Data], params: dict, qpos0: np.ndarray,
                mesh: BatchMesh | None = None) -> tuple:
    """The program's arrays on ``mesh`` (default: every device): the template replicated, the
    candidates' rows (padded to a multiple of the device count) split over the devices."""
    mesh = mesh or BatchMesh.over()
    size = mesh.padded(len(qpos0))
    rows = mesh.put_rows(pad_rows(({k: np.asarray(v) for k, v in params.items()}, np.asarray(qpos0)), size))
    return (*mesh.put_replicated(template), *rows)


def lower(template: tuple[mjx.Model, mjx.Data], params: dict, qpos0: np.ndarray, config: DropTestConfig,
          mesh: BatchMesh | None = None):
    """The batch program lowered for these shapes (``.compile()`` it to time compilation alone)."""
    mesh = mesh or BatchMesh.over()
    return _batched.lower(*device_args(template, params, qpos0, mesh), config.settle_steps, config.free_steps,
                          config.unroll, mesh)


def run(template_model: mujoco.MjModel, template: tuple[mjx.Model, mjx.Data], models: list[mujoco.MjModel],
        qpos0: np.ndarray, config: DropTestConfig, devices=None) -> tuple[np.ndarray, np.ndarray]:
    """Drop-test ``models`` (all of one bucket, built like ``template_model``; ``template`` is
    its device copy and initial data) in MJX, spread over ``devices``
    (``kernels.sharding.resolve_devices``: None, every device). Returns qpos after settling and
    at the end, (N, 7)."""
    mesh = BatchMesh.over(devices)
    params = stack_params(template_model, models, config.vertex_budget)
    n = len(models)
    chunk = padded_count(n, config, mesh)
    settled, final = [], []
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        idx = np.arange(start, start + chunk)
        idx = np.where(idx < stop, idx, start)    # pad with copies of the chunk's first candidate
        sub = {k: v[idx] for k, v in params.items()}
        s, f = _batched(*device_args(template, sub, qpos0[idx], mesh), config.settle_steps, config.free_steps,
                        config.unroll, mesh)
        settled.append(np.asarray(s, np.float64)[: stop - start])
        final.append(np.asarray(f, np.float64)[: stop - start])
    return np.concatenate(settled), np.concatenate(final)
