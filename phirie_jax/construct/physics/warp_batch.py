"""Every drop test of a batch as one MuJoCo Warp program: one simulated world per candidate.

MuJoCo Warp (``mujoco_warp``, NVIDIA Warp kernels) steps ``nworld`` copies of one model, and a
model field whose spec starts with ``*`` may differ per world (``put_model(batch_sizes=...)``).
Among those is ``geom_dataid``, the mesh a geom collides with. So the batch is one *bank* model:
the plane and one free body of ``bucket`` mesh geoms, with every candidate's convex parts (ghost
parts included, as ``droptest.build_model`` pads them) as mesh assets. World w's geoms point at
candidate w's meshes, and its inertia, geom frames, sizes and contact parameters are read from
candidate w's own compiled MuJoCo C model (the reference runs exactly those models). MuJoCo
compiles a mesh into its own frame the same way in both models, so the geom frames carry over.

The protocol's two phases are replayed as CUDA graphs on a GPU (one capture of
``GRAPH_STEPS`` steps each, launched until the phase is done); on a CPU the kernels are launched
one by one.

``early_exit`` is a masked early exit through MuJoCo's own sleeping: in the free phase (never while
settling, where velocities are zeroed on purpose) a body whose velocities stay below
``SLEEP_TOLERANCE`` for MuJoCo's minimum awake time falls asleep, its world's kernels skip it and
its pose is frozen; the phase ends once every world sleeps (checked every ``GRAPH_STEPS``).

Several GPUs: ``prepare_split`` divides the worlds into contiguous, near-equal parts
(``kernels.sharding.split``), one bank model per device, and ``simulate_all`` runs them at once:
Warp launches and graph replays are asynchronous, so every device's phase is launched before any
result is read (Warp's current device is process-wide, so this is done from one thread).

Needs ``warp-lang`` and ``mujoco-warp`` (``pip install phirie_jax[warp]``); the module imports
them lazily so the package stays importable without them.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence

import mujoco
import numpy as np

from kernels.sharding import split
from phirie_jax.construct.physics.config import DropTestConfig
from phirie_jax.construct.physics.ground import add_drop_plane, set_drop_options
from phirie_jax.rotations import quat_to_matrix

# Per-world model fields: what differs between candidates of one bucket (``mjx_batch.BATCHED``
# without the fields MuJoCo Warp does not have).
PER_WORLD = ("body_ipos", "body_iquat", "body_mass", "body_subtreemass", "body_inertia", "body_invweight0",
             "dof_invweight0", "geom_pos", "geom_quat", "geom_size", "geom_rbound", "geom_aabb",
             "geom_friction", "geom_solref", "geom_solimp")
# Features a drop-test model has none of (its one joint is free; no actuators, sensors, tendons,
# equalities, springs or dampers; one body per world, so one island): turned off, a step launches
# fewer kernels and the verdicts do not change (measured in docs/performance.md, "Drop tests").
UNUSED_FEATURES = ("EQUALITY", "FRICTIONLOSS", "LIMIT", "SPRING", "DAMPER", "ACTUATION", "CLAMPCTRL", "SENSOR",
                   "EULERDAMP", "ISLAND")
GRAPH_STEPS = 16        # protocol steps per captured graph (and between early-exit checks)
SLEEP_TOLERANCE = 1e-4  # early exit: a body sleeps once its velocities stay below this (MuJoCo's default)
CONTACTS_PER_PART = 8  # contact slots per mesh geom and world (a plane–convex pair makes at most 4)
MISSING = "MuJoCo Warp is not installed: pip install 'phirie_jax[warp]' (warp-lang, mujoco-warp)"


def available() -> tuple[bool, str]:
    """(True, version) when warp and mujoco_warp import, else (False, the line saying what to install)."""
    try:
        import mujoco_warp  # noqa: F401
        import warp
    except ImportError:
        return False, MISSING
    return True, warp.__version__


def warp_devices(devices=None) -> list[str]:
    """Warp device names to split a batch over: None, every CUDA device Warp sees (else "cpu");
    names ("cuda:1", "cpu") as given; ``jax.Device`` objects mapped to theirs (a GPU to
    "cuda:<its ordinal>", CPU devices to one "cpu")."""
    import warp as wp

    if devices is None:
        count = wp.get_cuda_device_count()
        return [f"cuda:{k}" for k in range(count)] if count else ["cpu"]
    names = []
    for d in devices:
        name = d if isinstance(d, str) else ("cpu" if d.platform == "cpu" else f"cuda:{d.local_hardware_id}")
        if isinstance(d, str) or name not in names:
            names.append(name)
    if not names:
        raise ValueError("warp devices: an empty list (expected None, names such as 'cuda:0', or jax devices)")
    return names


@dataclasses.dataclass(frozen=True)
class WarpBatchResult:
    settled: np.ndarray   # (N, 7) free-joint qpos after the settling phase
    final: np.ndarray     # (N, 7) ... at the end
    free_steps_run: int   # free-phase steps actually simulated (fewer with early exit; the most of any device)
    device: str           # the device, or the devices joined by "," (in the order of the worlds)


def bank_model(models: list[mujoco.MjModel], config: DropTestConfig, sleep: bool = False
               ) -> tuple[mujoco.MjModel, np.ndarray]:
    """The bank model holding every candidate's parts, and (N, P) the mesh id of candidate n's
    part p in it. models: each candidate's drop-test model (``droptest.build_model``, one bucket);
    sleep: compiled with sleeping allowed (the early exit)."""
    parts = models[0].ngeom - 1
    spec = mujoco.MjSpec()
    spec.modelname = "phirie_droptest_bank"
    set_drop_options(spec.option, config)
    if sleep:
        spec.option.enableflags |= mujoco.mjtEnableBit.mjENBL_SLEEP
        spec.option.sleep_tolerance = SLEEP_TOLERANCE
    add_drop_plane(spec)
    ids = np.zeros((len(models), parts), np.int64)
    for n, m in enumerate(models):
        if m.ngeom - 1 != parts:
            raise ValueError(f"candidate {n} has {m.ngeom - 1} parts, the batch {parts} (one bucket per batch)")
        for p in range(parts):
            mesh = int(m.geom_dataid[1 + p])
            start, count = m.mesh_vertadr[mesh], m.mesh_vertnum[mesh]
            # the compiled mesh, in its own frame, put back where the candidate's geom holds it
            verts = m.mesh_vert[start:start + count] @ quat_to_matrix(m.geom_quat[1 + p]).T + m.geom_pos[1 + p]
            spec.add_mesh(name=f"c{n}_p{p}").uservert = verts.ravel()
            ids[n, p] = n * parts + p
    ref = models[0]
    body = spec.worldbody.add_body(name="body")
    body.add_freejoint(name="body")
    body.explicitinertial = True
    body.mass, body.ipos = float(ref.body_mass[1]), ref.body_ipos[1]
    body.iquat, body.inertia = ref.body_iquat[1], ref.body_inertia[1]
    for p in range(parts):
        body.add_geom(name=f"part_{p:02d}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"c0_p{p}",
                      friction=ref.geom_friction[1 + p], solref=ref.geom_solref[1 + p],
                      solimp=ref.geom_solimp[1 + p])
    return spec.compile(), ids


def _per_world(bank: mujoco.MjModel, models: list[mujoco.MjModel], mesh_ids: np.ndarray) -> dict[str, np.ndarray]:
    """Per-world values of ``PER_WORLD`` (from each candidate's model) and ``geom_dataid``."""
    values = {name: np.stack([getattr(m, name) for m in models]) for name in PER_WORLD}
    dataid = np.repeat(bank.geom_dataid[None], len(models), axis=0)
    dataid[:, 1:] = mesh_ids
    values["geom_dataid"] = dataid
    return values


def _put(bank: mujoco.MjModel, values: dict[str, np.ndarray], nworld: int):
    """The bank on the current Warp device with its per-world fields set."""
    import mujoco_warp as mjw

    with warnings.catch_warnings():
        # the plane has no friction of its own: MuJoCo takes the larger friction of a pair
        warnings.filterwarnings("ignore", message=r"geom 0: friction\[0\]")
        model = mjw.put_model(bank, batch_sizes={name: nworld for name in values})
    for name, array in values.items():
        field = getattr(model, name)
        like = field.numpy()
        field.assign(np.ascontiguousarray(array.reshape(like.shape), dtype=like.dtype))
    return model


@dataclasses.dataclass
class WarpDropBatch:
    """A prepared batch: the bank on the device, its data, and (on a GPU) the phases' graphs.
    ``simulate`` runs the protocol from the spawn poses; it can be called again (benchmarks)."""

    model: object            # mujoco_warp.Model
    data: object             # mujoco_warp.Data
    qpos0: np.ndarray        # (N, 7)
    config: DropTestConfig
    early_exit: bool
    device: str
    graph_steps: int = GRAPH_STEPS
    settle_graph: object = None
    free_graph: object = None

    def _steps(self):
        import mujoco_warp as mjw

        model, data = self.model, self.data

        def settle():
            mjw.step(model, data)
            data.qvel.zero_()

        return settle, lambda: mjw.step(model, data)

    def _phase(self, free: bool) -> None:
        """MuJoCo's sleeping only in the free phase of an early-exit batch (settling zeroes velocities)."""
        import mujoco_warp as mjw

        flag = int(mjw.EnableBit.SLEEP)
        on = free and self.early_exit
        self.model.opt.enableflags = (self.model.opt.enableflags | flag) if on else (self.model.opt.enableflags & ~flag)

    def _reset(self) -> None:
        import mujoco_warp as mjw

        mjw.reset_data(self.model, self.data)
        self.data.qpos.assign(np.asarray(self.qpos0, np.float32))

    def capture(self) -> None:
        """Record both phases as CUDA graphs (a GPU only). Each phase's step runs once before its
        capture, so Warp compiles and loads the kernels outside it; the data is reset after."""
        import warp as wp

        if not self.device.startswith("cuda"):
            return
        graphs = []
        with wp.ScopedDevice(self.device):
            for free, step in zip((False, True), self._steps()):
                self._phase(free)
                step()
                with wp.ScopedCapture() as capture:
                    for _ in range(self.graph_steps):
                        step()
                graphs.append(capture.graph)
            self.settle_graph, self.free_graph = graphs
            self._reset()

    def simulate(self) -> WarpBatchResult:
        """The protocol from the spawn poses: qpos after settling and at the end."""
        return simulate_all([self])


def simulate_all(batches: Sequence[WarpDropBatch], parallel_launch: bool = True) -> WarpBatchResult:
    """The protocol of every batch (each on its device), their worlds concatenated in order.

    Each phase is launched on every device before anything is read back: launches are
    asynchronous, so the devices simulate at once. A CUDA graph launch costs the host time in
    proportion to the graph's nodes, so with several devices each launches its graphs from its own
    thread (``parallel_launch``; False: one thread launches for all, in turn). The settled state is
    copied on the device (asynchronously too) before the free phase starts. With early exit the
    free phase goes ``graph_steps`` at a time on every device still awake, then checks them all."""
    import warp as wp

    steps = {id(b): b._steps() for b in batches}
    kept = {}
    for b in batches:
        with wp.ScopedDevice(b.device):
            b._reset()
            b._phase(False)
    _launch_each(wp, batches, lambda b: (b.settle_graph, b.config.settle_steps, steps[id(b)][0]), parallel_launch)
    for b in batches:
        with wp.ScopedDevice(b.device):
            kept[id(b)] = wp.clone(b.data.qpos)
            b._phase(True)
    _launch_each(wp, [b for b in batches if not b.early_exit],
                 lambda b: (b.free_graph, b.config.free_steps, steps[id(b)][1]), parallel_launch)
    done = {id(b): (0 if b.early_exit else b.config.free_steps) for b in batches}
    awake = [b for b in batches if b.early_exit]
    while awake:
        for b in awake:
            with wp.ScopedDevice(b.device):
                chunk = min(b.graph_steps, b.config.free_steps - done[id(b)])
                _repeat(wp, b.free_graph if chunk == b.graph_steps else None, chunk, steps[id(b)][1],
                        b.graph_steps)
                done[id(b)] += chunk
        awake = [b for b in awake if done[id(b)] < b.config.free_steps and b.data.tree_awake.numpy().any()]
    settled, final = [], []
    for b in batches:
        with wp.ScopedDevice(b.device):
            settled.append(kept[id(b)].numpy().astype(np.float64))
            final.append(b.data.qpos.numpy().astype(np.float64))
    return WarpBatchResult(np.concatenate(settled), np.concatenate(final), max(done.values()),
                           ",".join(b.device for b in batches))


def prepare(models: list[mujoco.MjModel], qpos0: np.ndarray, config: DropTestConfig, early_exit: bool = False,
            device: str | None = None, graph_steps: int = GRAPH_STEPS, options: dict | None = None) -> WarpDropBatch:
    """The batch of ``models`` (one bucket, ``droptest.build_model``) from ``qpos0`` (N, 7), on
    ``device`` (default: the first GPU, else the CPU), its graphs captured. graph_steps: protocol
    steps per captured graph; options: MuJoCo Warp ``Option`` fields to override (benchmarks)."""
    ok, why = available()
    if not ok:
        raise RuntimeError(why)
    import mujoco_warp as mjw
    import warp as wp

    device = device or ("cuda:0" if wp.get_cuda_device_count() > 0 else "cpu")
    n = len(models)
    bank, mesh_ids = bank_model(models, config, sleep=early_exit)
    with wp.ScopedDevice(device):
        model = _put(bank, _per_world(bank, models, mesh_ids), n)
        # the protocol runs its own iteration counts on purpose: no overflow notices
        model.opt.warn_overflow &= ~(mjw.OverflowType.ITERATIONS | mjw.OverflowType.LS_ITERATIONS)
        for name in UNUSED_FEATURES:
            model.opt.disableflags |= int(getattr(mjw.DisableBit, name))
        for name, value in (options or {}).items():
            setattr(model.opt, name, value)
        parts = bank.ngeom - 1
        data = mjw.make_data(bank, nworld=n, nconmax=CONTACTS_PER_PART * parts,
                             njmax=CONTACTS_PER_PART * parts * 4, naconmax=n * CONTACTS_PER_PART * parts)
    batch = WarpDropBatch(model, data, np.asarray(qpos0, np.float64).reshape(n, -1), config, early_exit, str(device),
                          graph_steps)
    batch.capture()
    return batch


def prepare_split(models: list[mujoco.MjModel], qpos0: np.ndarray, config: DropTestConfig, early_exit: bool = False,
                  devices=None, graph_steps: int = GRAPH_STEPS, options: dict | None = None) -> list[WarpDropBatch]:
    """The batch divided over ``devices`` (``warp_devices``: None, every GPU): contiguous,
    near-equal parts of the worlds, each prepared on its device (``prepare``)."""
    names = warp_devices(devices)
    qpos0 = np.asarray(qpos0, np.float64).reshape(len(models), -1)
    return [prepare(models[part], qpos0[part], config, early_exit, name, graph_steps, options)
            for part, name in zip(split(len(models), len(names)), names)]


def run(models: list[mujoco.MjModel], qpos0: np.ndarray, config: DropTestConfig, early_exit: bool = False,
        device: str | None = None, devices=None) -> WarpBatchResult:
    """Drop-test ``models`` (one bucket, ``droptest.build_model``) from ``qpos0`` (N, 7) in MuJoCo Warp,
    on ``device``, or divided over ``devices`` (``warp_devices``: None, every GPU)."""
    return simulate_all(prepare_split(models, qpos0, config, early_exit, [device] if device else devices))


def _launch_each(wp, batches: Sequence[WarpDropBatch], phase, parallel: bool) -> None:
    """One phase of every batch: ``phase(batch)`` = (its graph or None, its steps, its step). The
    whole graphs go from one thread per device when ``parallel`` (a graph launch names its own
    device and stream, so the threads share nothing), then the remaining steps one by one here
    (a step launches on the default device, which is the process's, not the thread's)."""
    def launch(b: WarpDropBatch) -> None:
        graph, count, _ = phase(b)
        if graph is not None:
            for _ in range(count // b.graph_steps):
                wp.capture_launch(graph)

    if parallel and len(batches) > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(len(batches)) as pool:
            list(pool.map(launch, batches))
    else:
        for b in batches:
            launch(b)
    for b in batches:
        graph, count, step = phase(b)
        with wp.ScopedDevice(b.device):
            for _ in range(count // b.graph_steps * b.graph_steps if graph is not None else 0, count):
                step()


def _repeat(wp, graph, steps: int, step, graph_steps: int = GRAPH_STEPS) -> None:
    """``steps`` protocol steps: whole graphs of ``graph_steps``, then the remainder one by one."""
    done = 0
    if graph is not None:
        for _ in range(steps // graph_steps):
            wp.capture_launch(graph)
        done = steps // graph_steps * graph_steps
    for _ in range(done, steps):
        step()
