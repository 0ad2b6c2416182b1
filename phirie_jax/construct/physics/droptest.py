"""Drop tests (the paper's protocol) of bodies made of convex parts, in MJX or MuJoCo C.

Protocol (``DropTestConfig``): each body alone on a plane, 240 Hz; spawned in its registered
orientation with its lowest collision point on the plane; 2 s with velocities zeroed after
every step, then 2 s free. Stable if its centre of mass ends < 3 cm from where it was spawned
and no lower than −5 cm relative to the plane.

Both backends simulate the same compiled MuJoCo models (``build_model``): a plane and the
body added by ``body.add_body`` (the builder of ``scene.xml``'s bodies: explicit inertial, the
priors' contact parameters), its convex parts inline and padded to the part bucket with ghost
parts. "mujoco" steps each model with the C library, one after another (the reference);
"mjx" runs a whole bucket as one vmapped program (``mjx_batch``); "warp" runs it as one MuJoCo
Warp batch, a world per candidate (``warp_batch``).

A mounted body (welded to its wall) is not dropped: ``hold_test`` simulates the exported
``scene.xml`` and asks the weld to hold it.

The construction stage's settling check calls ``drop_test_meshes`` (one convex hull per
candidate, every candidate in one batch) and ``settling_check`` (a check-table row).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import mujoco
import numpy as np

from kernels.sharding import resolve_devices
from phirie_jax.construct.physics.body import ObjectBody, add_body, object_body
from phirie_jax.construct.physics.collision import ConvexPart, MeshError, hull_part
from phirie_jax.construct.physics.config import DropTestConfig, PhysicsConfig
from phirie_jax.construct.physics.ground import add_drop_plane, set_drop_options
from phirie_jax.construct.physics.mjcf import scene_motion
from phirie_jax.construct.physics.priors import MassProperties, Priors, mass_properties, priors
from phirie_jax.geometry import rotation_to_z, split_sim3
from phirie_jax.rotations import matrix_to_quat, quat_angle, quat_to_matrix


@dataclasses.dataclass(frozen=True)
class DropBody:
    """One body to drop: the object's body and its spawn orientation."""

    body: ObjectBody
    rotation: np.ndarray            # (3, 3) body → gravity frame (up = +z) at spawn

    @property
    def parts(self) -> tuple[ConvexPart, ...]:
        """Convex parts in the body frame (canonical mesh frame, scale applied), metres."""
        return self.body.parts

    @property
    def mass(self) -> MassProperties:
        return self.body.mass

    @property
    def priors(self) -> Priors:
        return self.body.priors


@dataclasses.dataclass(frozen=True)
class DropResult:
    stable: bool | None
    drift_m: float | None           # |centre of mass at the end − at spawn|
    final_height_m: float | None    # centre of mass above the plane at the end
    settle_drift_m: float | None    # |centre of mass after settling − at spawn|
    tilt_deg: float | None          # rotation between spawn and end
    backend: str
    error: str | None = None

    @classmethod
    def not_run(cls, backend: str, error: str) -> DropResult:
        """The result of a body that could not be tested: no verdict, no measurements, ``error`` says why."""
        return cls(None, None, None, None, None, backend, error)

    def record(self) -> dict:
        return dataclasses.asdict(self)


def body_from_parts(parts: Sequence[ConvexPart], pose: np.ndarray, up=(0.0, 0.0, 1.0),
                    body_priors: Priors | None = None) -> DropBody:
    """A drop body from canonical-frame parts placed by a Sim(3) ``pose`` in a scene whose up is ``up``."""
    return drop_body(object_body(None, parts, pose, body_priors or priors(None)), up)


def drop_body(body: ObjectBody, up=(0.0, 0.0, 1.0)) -> DropBody:
    """``body`` spawned in its pose's orientation in a scene whose up is ``up`` (3,)."""
    return DropBody(body, rotation_to_z(up) @ split_sim3(body.pose)[1])


def part_bucket(parts: int, config: DropTestConfig) -> int:
    for bucket in config.part_buckets:
        if parts <= bucket:
            return bucket
    raise ValueError(f"{parts} convex parts (more than the largest part bucket {config.part_buckets[-1]})")


def build_model(body: DropBody, bucket: int, config: DropTestConfig) -> mujoco.MjModel:
    """The compiled drop-test model of ``body``: plane + one free body with ``bucket`` mesh parts."""
    spec = mujoco.MjSpec()
    spec.modelname = "phirie_droptest"
    set_drop_options(spec.option, config)
    add_drop_plane(spec)
    add_body(spec, body.body, name="body", placed=False, inline=True, pad_to=bucket)
    return spec.compile()


def spawn_qpos(body: DropBody) -> np.ndarray:
    """(7,) free-joint qpos: spawn orientation, lowest point of the parts exactly on the plane."""
    lowest = min(float((p.vertices @ body.rotation.T)[:, 2].min()) for p in body.parts)
    quat = matrix_to_quat(body.rotation)
    return np.concatenate([[0.0, 0.0, -lowest], quat])


@functools.lru_cache(maxsize=8)
def bucket_template(bucket: int, config: DropTestConfig):
    """(MjModel, (mjx.Model, mjx.Data)) of a canonical body of ``bucket`` parts: the shape every
    candidate of the bucket is batched into (its values are replaced per candidate)."""
    from mujoco import mjx

    cube = hull_part(np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * 0.1)
    canonical = DropBody(ObjectBody(None, (cube,), np.eye(4), mass_properties((cube,), 1.0), priors(None)), np.eye(3))
    model = build_model(canonical, bucket, config)
    mx = mjx.put_model(model)
    return model, (mx, mjx.make_data(mx))


def run_reference(model: mujoco.MjModel, qpos0: np.ndarray, config: DropTestConfig) -> tuple[np.ndarray, np.ndarray]:
    """The protocol with the MuJoCo C library: qpos after settling and at the end."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos0
    for _ in range(config.settle_steps):
        mujoco.mj_step(model, data)
        data.qvel[:] = 0.0
    settled = data.qpos.copy()
    if config.free_steps:
        mujoco.mj_step(model, data, nstep=config.free_steps)
    return settled, data.qpos.copy()


def _com(model: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    """World centre of mass of the free body at ``qpos``; NaN where the state diverged."""
    quat = np.asarray(qpos[3:7], np.float64)
    if not (np.isfinite(qpos).all() and np.linalg.norm(quat) > 1e-9):
        return np.full(3, np.nan)
    rot = quat_to_matrix(quat / np.linalg.norm(quat))
    return qpos[:3] + rot @ model.body_ipos[1]


def _tilt_deg(q0: np.ndarray, q1: np.ndarray) -> float:
    return float(np.degrees(quat_angle(q0 / np.linalg.norm(q0), q1 / np.linalg.norm(q1))))


def verdict(model: mujoco.MjModel, qpos0, settled, final, config: DropTestConfig, backend: str) -> DropResult:
    com0, com_s, com_f = (_com(model, q) for q in (qpos0, settled, final))
    if not (np.isfinite(com_f).all() and np.isfinite(com_s).all()):
        return DropResult(False, None, None, None, None, backend, "simulation diverged (non-finite state)")
    drift = float(np.linalg.norm(com_f - com0))
    height = float(com_f[2])
    stable = drift < config.max_drift and height >= config.min_final_height
    return DropResult(bool(stable), drift, height, float(np.linalg.norm(com_s - com0)),
                      _tilt_deg(qpos0[3:7], final[3:7]), backend)


AUTO_BATCH_MIN = 1024  # "auto" batches on an accelerator from this many candidates (docs/performance.md)


def resolve_backend(backend: str, candidates: int | None = None) -> str:
    """"auto": the C library below ``AUTO_BATCH_MIN`` candidates or without an accelerator (it
    compiles nothing, and below that count it finishes before MJX has compiled or Warp has built its
    kernels: docs/performance.md, "Drop tests"); from there MuJoCo Warp when installed on a CUDA
    device, else MJX. ``candidates`` None (a record of the backend's kind): as for a large batch."""
    if backend != "auto":
        return backend
    import jax

    if jax.default_backend() == "cpu" or (candidates is not None and candidates < AUTO_BATCH_MIN):
        return "mujoco"
    from phirie_jax.construct.physics import warp_batch

    return "warp" if warp_batch.available()[0] and jax.default_backend() == "gpu" else "mjx"


def drop_test(bodies: Sequence[DropBody], config: DropTestConfig = DropTestConfig(),
              backend: str | None = None, devices=None) -> list[DropResult]:
    """Drop-test every body; MJX or Warp run each part bucket as one batched program, its
    candidates spread over ``devices`` (``kernels.sharding.resolve_devices``: None, every device
    JAX sees; for Warp, every GPU it sees)."""
    backend = resolve_backend(backend or config.backend, len(bodies))
    results: list[DropResult | None] = [None] * len(bodies)
    groups: dict[int, list[int]] = {}
    models: dict[int, mujoco.MjModel] = {}
    qpos0: dict[int, np.ndarray] = {}
    for k, body in enumerate(bodies):
        try:
            bucket = part_bucket(len(body.parts), config)
            models[k], qpos0[k] = build_model(body, bucket, config), spawn_qpos(body)
            groups.setdefault(bucket, []).append(k)
        except (ValueError, MeshError) as err:
            results[k] = DropResult.not_run(backend, f"{type(err).__name__}: {err}")
    for bucket, members in groups.items():
        if backend == "warp":
            from phirie_jax.construct.physics import warp_batch

            run = warp_batch.run([models[k] for k in members], np.stack([qpos0[k] for k in members]), config,
                                 devices=None if devices is None else resolve_devices(devices))
            settled, final = run.settled, run.final
        elif backend == "mjx":
            from phirie_jax.construct.physics import mjx_batch

            template_model, template = bucket_template(bucket, config)
            settled, final = mjx_batch.run(template_model, template, [models[k] for k in members],
                                           np.stack([qpos0[k] for k in members]), config, devices)
        else:
            runs = [run_reference(models[k], qpos0[k], config) for k in members]
            settled, final = np.stack([r[0] for r in runs]), np.stack([r[1] for r in runs])
        for row, k in enumerate(members):
            results[k] = verdict(models[k], qpos0[k], settled[row], final[row], config, backend)
    return results  # type: ignore[return-value]


def drop_test_meshes(meshes: Sequence[tuple[np.ndarray, np.ndarray]], poses: Sequence[np.ndarray],
                     up=(0.0, 0.0, 1.0), categories: Sequence[str | None] | None = None,
                     config: PhysicsConfig = PhysicsConfig(), backend: str | None = None,
                     devices=None) -> list[DropResult]:
    """Drop-test candidate placements with the fast single-hull stand-in, all in one batch.

    Args:
        meshes: (vertices (N, 3), faces (M, 3)) of each candidate in its own frame.
        poses: (4, 4) Sim(3) of each candidate, its frame → scene (scale included).
        up: the scene's up direction (gravity is −up).
        categories: per-candidate category for the mass prior (default: the config's mass).
        config: physics priors and the drop test's settings.
        backend: "mjx", "warp", "mujoco" or "auto" (default ``config.drop_test.backend``).
        devices: the devices a batch is spread over (``drop_test``; None: all).

    A candidate whose hull is empty or flat, or whose pose is not a similarity, gets a result
    with ``error`` set; the others are unaffected.
    """
    bodies, index, results = [], [], [None] * len(meshes)
    backend = resolve_backend(backend or config.drop_test.backend, len(meshes))
    for k, ((vertices, _faces), pose) in enumerate(zip(meshes, poses, strict=True)):
        try:
            part = hull_part(vertices, config.max_hull_vertices)
            cat = None if categories is None else categories[k]
            bodies.append(body_from_parts((part,), pose, up, priors(cat, config)))
            index.append(k)
        except (ValueError, MeshError) as err:
            results[k] = DropResult.not_run(backend, f"{type(err).__name__}: {err}")
    for k, result in zip(index, drop_test(bodies, config.drop_test, backend, devices)):
        results[k] = result
    return results  # type: ignore[return-value]


HOLD_BACKEND = "mujoco, scene.xml"


def hold_test(scene_xml, names: Sequence[str], config: DropTestConfig = DropTestConfig()) -> dict[str, DropResult]:
    """The drop test of mounted bodies (``ObjectBody.mounted``), by body name: the exported
    ``scene.xml`` simulated freely for the drop test's whole time (settle + free) in MuJoCo C;
    a body is stable when its weld holds its centre of mass within ``max_drift`` of where it was
    placed. Nothing is dropped: the free drop would only show the fall the weld exists to stop."""
    motion = scene_motion(scene_xml, config.settle_time + config.free_time)
    out = {}
    for name in names:
        if name not in motion:
            out[name] = DropResult.not_run(HOLD_BACKEND, f"no body {name} in {scene_xml}")
            continue
        moved, turned = motion[name]
        if not np.isfinite(moved):
            out[name] = DropResult(False, None, None, None, None, HOLD_BACKEND, "simulation diverged (non-finite state)")
            continue
        out[name] = DropResult(bool(moved < config.max_drift), moved, None, None, turned, HOLD_BACKEND)
    return out


def settling_check(result: DropResult, config: DropTestConfig = DropTestConfig(), method: str = "") -> dict:
    """A check-table row ({value, threshold, passed, ...}) for the construction stage's settling check."""
    row = {"value": result.drift_m, "threshold": config.max_drift, "passed": result.stable,
           "final_height_m": result.final_height_m, "min_final_height": config.min_final_height,
           "backend": result.backend, "status": "run"}
    if method:
        row["method"] = method
    if result.error:
        row.update(passed=False, status="failed", reason=result.error)
    return row
