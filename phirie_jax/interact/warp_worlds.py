"""Many worlds of one scene in MuJoCo Warp: the exact model, its poses handed to JAX on the device.

``WarpWorlds(model, data, num_worlds)`` puts a compiled MuJoCo model on the Warp devices with N
copies of one state (``mujoco_warp.put_data(nworld=N)``): the scene as exported, every CoACD part
of every object and, when the scene has one, the robot with its link meshes and finger capsules,
so a world is the single environment's MuJoCo C model, stepped in float32. Several devices
(``warp_batch.warp_devices``) hold contiguous, near-equal parts of the worlds, one model each;
every part's work is launched before anything is read, so the devices run at once.

- ``step(steps, ctrl)``: ``ctrl`` (N, nu) held for ``steps`` steps; a JAX array on the device
  is read where it lies (``wp.from_jax``), anything else is copied from the host;
- ``play(ctrl, substeps)``: a whole control sequence (T, N, nu), put on the device once and read
  tick by tick by a kernel (``warp_kernels.tick_controls``) inside the stepping, so a rollout never returns
  to the host;
- ``poses()``: body positions (N, nbody, 3) and quaternions (N, nbody, 4, wxyz) as JAX arrays
  on the device, through DLPack (``wp.to_jax``) — on a GPU no byte crosses to the host. They are
  copies made on the device (``wp.clone``), so a later step cannot change an array JAX holds
  (JAX arrays are immutable; DLPack shares memory).

On a GPU the stepping is replayed from CUDA graphs (``wp.ScopedCapture``): the first call of a
kind runs one unit of work (a step, a tick) plainly, which compiles and loads every kernel, then
records ``GRAPH_STEPS`` steps (``GRAPH_TICKS`` ticks) as one graph that later calls launch. With
several GPUs each launches its graphs from its own host thread: a graph launch costs the host
time in proportion to its nodes, and from one thread the GPUs' graphs ran as if one after the
other (1,024 worlds, 240 steps on two H200s: 0.59 s against 0.40 s on one); from a thread per
GPU, 0.35 s (``experiments/results/scaling_2gpu_warp.json``; the drop tests measured the same,
``docs/scaling.md``). On a CPU the kernels are launched one by one.

Contact and constraint capacities are per world (``capacity``): MuJoCo Warp allocates them
ahead and drops what does not fit, so ``overflow()`` says which worlds ran out (the run then
needs larger ``contacts`` / ``constraints``).

Needs ``warp-lang`` and ``mujoco-warp`` (``pip install phirie_jax[warp]``), imported lazily.
"""

from __future__ import annotations

import atexit
import dataclasses
import weakref
from typing import Any

import mujoco
import numpy as np

from kernels.sharding import split
from phirie_jax.construct.physics.warp_batch import available, warp_devices

GRAPH_STEPS = 16          # simulator steps per captured graph of ``step``
GRAPH_TICKS = 8           # control ticks per captured graph of ``play``
SETTLE_STEPS = 120        # MuJoCo C steps from the initial state that size the contact capacity
CONTACT_MARGIN = 2        # × the contacts the settled scene holds ...
GRASP_CONTACTS = 32       # ... plus this many when a robot can grasp (a grasp adds up to 31 in C)
MIN_CONTACTS = 16         # contacts per world at least
# Overflows that lose contacts or constraint rows (the solver's iteration limits are not losses)
CAPACITY_FLAGS = ("NEFC", "NJMAX_NNZ", "BROADPHASE", "NARROWPHASE", "CCD", "EPA_HORIZON")
STATE = ("qpos", "qvel", "act", "ctrl", "mocap_pos", "mocap_quat")   # what a reset restores
_SHARED: list[weakref.ref] = []   # JAX arrays on Warp memory (DLPack), released before Warp shuts down


@atexit.register
def _release_shared() -> None:
    """Free the JAX arrays still holding Warp memory while Warp can take it back (at exit Warp's
    module is torn down first, and its DLPack deleter would fail)."""
    for ref in _SHARED:
        array = ref()
        if array is not None and not array.is_deleted():
            array.delete()


def _bucket(n: float) -> int:
    """The smallest of 16, 24, 32, 48, 64, ... (MuJoCo Warp's own capacity steps) holding ``n``."""
    size = 16
    while size < n:
        size = size * 3 // 2 if size & (size - 1) == 0 else size * 4 // 3
    return size


def capacity(model, data: mujoco.MjData, grasp: bool = False) -> tuple[int, int]:
    """(contacts, constraint rows) to allocate per world: ``CONTACT_MARGIN`` × what MuJoCo C holds
    after ``SETTLE_STEPS`` from ``data`` (its contacts; its rows, limits and equalities included),
    plus, when a robot grasps, ``GRASP_CONTACTS`` contacts of the widest kind the model makes
    (pyramidal cones: 2 (condim − 1) rows each)."""
    settled = mujoco.MjData(model)
    for name in STATE:
        getattr(settled, name)[:] = getattr(data, name)
    mujoco.mj_step(model, settled, nstep=SETTLE_STEPS)
    colliding = (model.geom_contype | model.geom_conaffinity) > 0
    condim = int(model.geom_condim[colliding].max()) if colliding.any() else 1
    widest = condim if model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC else max(1, 2 * (condim - 1))
    contacts = CONTACT_MARGIN * max(settled.ncon, data.ncon) + GRASP_CONTACTS * grasp
    rows = CONTACT_MARGIN * max(settled.nefc, data.nefc) + GRASP_CONTACTS * widest * grasp
    return _bucket(max(MIN_CONTACTS, contacts)), _bucket(max(MIN_CONTACTS, rows))


@dataclasses.dataclass
class _Part:
    """The worlds ``rows`` on one Warp device: its model, data and captured graphs."""

    device: str
    rows: slice
    model: Any                      # mujoco_warp.Model
    data: Any                       # mujoco_warp.Data (nworld = the rows')
    graphs: dict = dataclasses.field(default_factory=dict)
    sequence: Any = None            # (T, n, nu) controls of ``play`` on the device
    tick: Any = None                # (1,) int32: the tick ``play`` reads next
    held: list = dataclasses.field(default_factory=list)   # arrays a pending copy reads from

    @property
    def cuda(self) -> bool:
        return self.device.startswith("cuda")


class WarpWorlds:
    """N worlds of one MuJoCo model in MuJoCo Warp (module docstring).

    model: the compiled ``mujoco.MjModel``; data: the state every world starts from (and
    ``reset`` restores; ``batched.initial_data``); devices: ``warp_batch.warp_devices`` (None, every GPU,
    else the CPU); contacts, constraints: per-world capacities (default ``capacity``)."""

    def __init__(self, model, data: mujoco.MjData, num_worlds: int, devices=None,
                 contacts: int | None = None, constraints: int | None = None, grasp: bool = False):
        ok, why = available()
        if not ok:
            raise RuntimeError(why)
        import mujoco_warp as mjw
        import warp as wp

        if num_worlds < 1:
            raise ValueError(f"num_worlds {num_worlds} (expected at least 1)")
        self.mj_model = model
        self.num_worlds = int(num_worlds)
        guess = capacity(model, data, grasp)
        self.contacts = int(contacts or guess[0])
        self.constraints = int(constraints or guess[1])
        self._initial = {name: np.array(getattr(data, name), np.float32) for name in STATE}
        quiet = mjw.OverflowType.ITERATIONS | mjw.OverflowType.LS_ITERATIONS
        self.parts: list[_Part] = []
        names = warp_devices(devices)
        for rows, name in zip(split(self.num_worlds, len(names)), names):
            with wp.ScopedDevice(name):
                wmodel = mjw.put_model(model)
                wmodel.opt.warn_overflow &= ~quiet   # the solver's iteration limits are MuJoCo's own
                wdata = mjw.put_data(model, data, nworld=rows.stop - rows.start, nconmax=self.contacts,
                                     njmax=self.constraints)
            self.parts.append(_Part(name, rows, wmodel, wdata, tick=wp.zeros(1, dtype=wp.int32, device=name)))

    @property
    def devices(self) -> tuple[str, ...]:
        return tuple(p.device for p in self.parts)

    # --- state ------------------------------------------------------------------------

    def reset(self) -> None:
        """Every world back to the initial state (MuJoCo Warp's reset, then the state's fields)."""
        import mujoco_warp as mjw
        import warp as wp

        for p in self.parts:
            with wp.ScopedDevice(p.device):
                mjw.reset_data(p.model, p.data)
                n = p.rows.stop - p.rows.start
                for name, value in self._initial.items():
                    if value.size:
                        getattr(p.data, name).assign(np.ascontiguousarray(np.broadcast_to(value, (n,) + value.shape)))
                mjw.forward(p.model, p.data)

    def set_state(self, qpos=None, qvel=None, ctrl=None) -> None:
        """Per-world qpos (N, nq), qvel (N, nv) and/or ctrl (N, nu); the derived quantities
        (body poses, contacts) are recomputed (``mujoco_warp.forward``)."""
        import mujoco_warp as mjw
        import warp as wp

        for name, value in (("qpos", qpos), ("qvel", qvel), ("ctrl", ctrl)):
            if value is not None:
                self._write(name, value)
        for p in self.parts:
            with wp.ScopedDevice(p.device):
                mjw.forward(p.model, p.data)

    def _write(self, name: str, value) -> None:
        """A (N, …) per-world field into every part's data: a JAX array on that GPU through DLPack
        (no host copy), anything else from the host."""
        import warp as wp

        width = getattr(self.parts[0].data, name).shape[1]
        if tuple(value.shape) != (self.num_worlds, width):
            raise ValueError(f"{name} of shape {tuple(value.shape)} (expected ({self.num_worlds}, {width}): worlds × "
                             f"{name}'s size)")
        for p in self.parts:
            target = getattr(p.data, name)
            with wp.ScopedDevice(p.device):
                source = _on_device(value, p)
                if source is None:
                    target.assign(np.ascontiguousarray(np.asarray(value, np.float32)[p.rows]))
                else:
                    wp.copy(target, source)
                    p.held = [source]   # alive until the copy, queued on the device, has run

    def field(self, name: str) -> np.ndarray:
        """A data field of every world on the host, (N, …) float64 (``qpos``, ``xpos``, ...)."""
        import warp as wp

        out = []
        for p in self.parts:
            with wp.ScopedDevice(p.device):
                out.append(getattr(p.data, name).numpy())
        return np.concatenate(out).astype(np.float64)

    def overflow(self) -> np.ndarray:
        """(N,) bool: worlds that lost contacts or constraint rows since the last reset."""
        import mujoco_warp as mjw

        mask = 0
        for name in CAPACITY_FLAGS:
            mask |= int(getattr(mjw.OverflowType, name))
        return (self.field("overflow").astype(np.int64) & mask) != 0

    # --- stepping ---------------------------------------------------------------------

    def step(self, steps: int = 1, ctrl=None) -> None:
        """Every world ``steps`` simulator steps on, ``ctrl`` (N, nu) held when given."""
        import mujoco_warp as mjw

        if ctrl is not None:
            self._write("ctrl", ctrl)
        self._repeat(("step",), int(steps), [lambda p=p: mjw.step(p.model, p.data) for p in self.parts], GRAPH_STEPS)

    def play(self, ctrl, substeps: int, ticks: int | None = None) -> None:
        """Every world through a control sequence ``ctrl`` (T, N, nu): tick t's controls held for
        ``substeps`` steps; only its first ``ticks`` when given (a warm-up that compiles and
        captures). The sequence is copied to the devices once; each tick a kernel reads its row
        there (module docstring)."""
        import mujoco_warp as mjw
        import warp as wp

        ctrl = np.asarray(ctrl, np.float32)
        nu = self.mj_model.nu
        if ctrl.ndim != 3 or ctrl.shape[1:] != (self.num_worlds, nu):
            raise ValueError(f"play: ctrl of shape {ctrl.shape} (expected (ticks, {self.num_worlds}, {nu}))")
        from phirie_jax.interact.warp_kernels import next_tick, tick_controls

        ticks_of_parts = []
        for p in self.parts:
            n = p.rows.stop - p.rows.start
            with wp.ScopedDevice(p.device):
                rows = np.ascontiguousarray(ctrl[:, p.rows])
                if p.sequence is None or p.sequence.shape != rows.shape:
                    p.sequence = wp.array(rows, dtype=wp.float32)
                    p.graphs = {k: g for k, g in p.graphs.items() if k[0] != "tick"}  # they read the old one
                else:
                    p.sequence.assign(rows)
                p.tick.zero_()

            def one_tick(p=p, n=n):
                wp.launch(tick_controls, dim=(n, nu), inputs=[p.sequence, p.tick], outputs=[p.data.ctrl])
                for _ in range(substeps):
                    mjw.step(p.model, p.data)
                wp.launch(next_tick, dim=1, inputs=[p.tick])

            ticks_of_parts.append(one_tick)
        self._repeat(("tick", int(substeps)), ctrl.shape[0] if ticks is None else min(ticks, ctrl.shape[0]),
                     ticks_of_parts, GRAPH_TICKS)

    def _repeat(self, key: tuple, count: int, units: list, length: int) -> None:
        """``count`` units of work on every part (``units[i]`` launches part i's unit): on a GPU,
        graphs of ``length`` units (captured at the first call, after one plain unit has loaded
        every kernel), the rest plainly. Several GPUs launch their graphs from a thread each (a
        graph launch names its own device and stream); a plain unit launches on the default
        device, the process's, so those stay on this thread."""
        import warp as wp

        plans = []   # per part: its graph (or None), the graphs to launch, the plain units done
        for part, one in zip(self.parts, units):
            graph, done = None, 0
            if part.cuda and count > length:
                with wp.ScopedDevice(part.device):
                    graph = part.graphs.get(key)
                    if graph is None:
                        one()
                        done = 1
                        with wp.ScopedCapture() as capture:
                            for _ in range(length):
                                one()
                        graph = part.graphs[key] = capture.graph
            plans.append((graph, (count - done) // length if graph is not None else 0, done))

        def launch(plan: tuple) -> None:
            graph, launches, _ = plan
            for _ in range(launches):
                wp.capture_launch(graph)

        if sum(1 for plan in plans if plan[1]) > 1:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(len(plans), thread_name_prefix="Warp worlds") as pool:
                list(pool.map(launch, plans))
        else:
            for plan in plans:
                launch(plan)
        for part, one, (_, launches, done) in zip(self.parts, units, plans):
            with wp.ScopedDevice(part.device):
                for _ in range(done + launches * length, count):
                    one()

    def synchronize(self) -> None:
        """Wait until every device has finished what was launched (timing)."""
        import warp as wp

        for p in self.parts:
            wp.synchronize_device(p.device)

    # --- poses, on the device ---------------------------------------------------------

    def poses(self, sharding=None) -> tuple[Any, Any]:
        """(xpos (N, nbody, 3), xquat (N, nbody, 4) wxyz) float32 JAX arrays made on the device
        (module docstring). With a ``sharding`` of the worlds axis whose devices are the parts'
        (one GPU each, in order) the parts' pieces become that array's shards as they lie; else
        they are concatenated and placed by it (a copy: the CPU, other device sets)."""
        return self._jax("xpos", sharding), self._jax("xquat", sharding)

    def _jax(self, name: str, sharding=None):
        import jax
        import jax.numpy as jnp
        import warp as wp

        pieces = []
        for p in self.parts:
            with wp.ScopedDevice(p.device):
                pieces.append(wp.to_jax(wp.clone(getattr(p.data, name))))
                _SHARED[:] = [r for r in _SHARED if r() is not None] + [weakref.ref(pieces[-1])]
        devices = [next(iter(x.devices())) for x in pieces]
        if sharding is not None and len(pieces) > 1 and list(sharding.mesh.devices.flat) == devices:
            return jax.make_array_from_single_device_arrays((self.num_worlds,) + pieces[0].shape[1:], sharding,
                                                            pieces)
        whole = pieces[0] if len(pieces) == 1 else jnp.concatenate([jax.device_put(x, devices[0]) for x in pieces])
        return whole if sharding is None else jax.device_put(whole, sharding)


def _on_device(value, part: _Part):
    """``value``'s rows of ``part`` as a Warp array on its GPU without a host copy, when ``value``
    is a JAX array and the part is on a GPU; else None."""
    if not part.cuda or not hasattr(value, "addressable_shards"):
        return None
    import jax
    import jax.numpy as jnp
    import warp as wp

    ordinal = int(part.device.split(":")[1])
    device = next((d for d in jax.devices() if d.platform == "gpu" and d.local_hardware_id == ordinal), None)
    if device is None:
        return None
    rows = jax.device_put(jnp.asarray(value[part.rows], jnp.float32), device)
    return wp.from_jax(rows)
