"""A batch axis over several devices: which devices, the 1-D mesh, padding to a multiple.

The batched programs (the worlds of ``BatchedEnvironment``, the drop-test candidates, the
registration hypotheses) spread their batch over the devices of a 1-D ``Mesh`` (axis
``AXIS``) with one jitted program for any number of devices:

- the batch is padded to a multiple of the device count (``BatchMesh.padded``) with copies of
  its first row (``pad_rows``): a pad row is a real case, so it cannot produce NaN or a
  different control flow, and it is cut off (or masked) before anything reduces over the batch;
- its arrays are placed with a ``NamedSharding`` that splits the leading axis over the mesh
  (``BatchMesh.rows``); what every row shares (a model, a template) is replicated
  (``BatchMesh.replicated``);
- the per-row function runs through ``jax.shard_map`` (``BatchMesh.map``): each device runs
  the single-device program on its own rows, and nothing crosses devices.

One device is a mesh of one: the same program, so a result on N devices can be compared with
the result on one. ``split`` divides a batch into contiguous, near-equal parts for backends
that hold one model per device (MuJoCo Warp).
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

AXIS = "batch"   # the mesh's one axis name


def resolve_devices(devices: int | Sequence[jax.Device] | None = None) -> tuple[jax.Device, ...]:
    """The devices to spread a batch over: None, every device of JAX's default backend; an int
    k, the first k of them; otherwise the given ``jax.Device`` objects, in order."""
    available = jax.devices()
    if devices is None:
        return tuple(available)
    if isinstance(devices, (int, np.integer)):
        if not 1 <= int(devices) <= len(available):
            raise ValueError(f"devices={int(devices)}: expected 1 to {len(available)} "
                             f"(the {jax.default_backend()} devices JAX sees)")
        return tuple(available[: int(devices)])
    chosen = tuple(devices)
    if not chosen:
        raise ValueError("devices: an empty list (expected None, a count, or jax.Device objects)")
    if len({d.id for d in chosen}) != len(chosen):
        raise ValueError(f"devices: {[str(d) for d in chosen]} names a device twice")
    return chosen


GSPMD_REASON = ("JAX 0.11's Shardy partitioner crashed (SIGSEGV) compiling the MJX drop tests and "
                "the batched worlds for two H200s; GSPMD compiled and ran the drop tests")


def use_gspmd_on_gpus(devices: Sequence[jax.Device]) -> bool:
    """Switch JAX to the GSPMD partitioner before a program spans several GPUs (``GSPMD_REASON``);
    True when it switched. One device, or CPU devices, keep the default. ``JAX_USE_SHARDY_PARTITIONER``
    set in the environment is the user's choice and is kept."""
    import os
    import warnings

    gpus = [d for d in devices if d.platform == "gpu"]
    if len(gpus) < 2 or not jax.config.jax_use_shardy_partitioner or "JAX_USE_SHARDY_PARTITIONER" in os.environ:
        return False
    jax.config.update("jax_use_shardy_partitioner", False)
    warnings.warn(f"phirie_jax: batches over {len(gpus)} GPUs compile with GSPMD ({GSPMD_REASON}); "
                  "set JAX_USE_SHARDY_PARTITIONER=1 to keep Shardy", RuntimeWarning, stacklevel=3)
    return True


@dataclasses.dataclass(frozen=True)
class BatchMesh:
    """A 1-D mesh of devices carrying a batch axis (module docstring). Hashable: a static
    argument of jitted programs (the same devices give the same compiled program)."""

    mesh: Mesh

    @classmethod
    def over(cls, devices: int | Sequence[jax.Device] | None = None) -> BatchMesh:
        """The mesh over ``resolve_devices(devices)`` (``use_gspmd_on_gpus`` for several GPUs)."""
        chosen = resolve_devices(devices)
        use_gspmd_on_gpus(chosen)
        return cls(Mesh(np.array(chosen, dtype=object), (AXIS,)))

    @property
    def devices(self) -> tuple[jax.Device, ...]:
        return tuple(self.mesh.devices.flat)

    @property
    def size(self) -> int:
        """Number of devices."""
        return int(self.mesh.devices.size)

    def padded(self, n: int) -> int:
        """The smallest multiple of the device count holding ``n`` rows (at least one per device)."""
        return max(1, -(-int(n) // self.size)) * self.size

    @property
    def rows(self) -> NamedSharding:
        """Leading axis split over the devices."""
        return NamedSharding(self.mesh, P(AXIS))

    @property
    def replicated(self) -> NamedSharding:
        """A whole copy on every device."""
        return NamedSharding(self.mesh, P())

    def put_rows(self, tree: Any) -> Any:
        """Every leaf on the mesh, its leading axis (a multiple of ``size``) split over it."""
        return jax.device_put(tree, self.rows)

    def put_replicated(self, tree: Any) -> Any:
        """Every leaf copied onto each device of the mesh."""
        return jax.device_put(tree, self.replicated)

    def map(self, fn: Callable, batched: Sequence[bool]) -> Callable:
        """``fn`` run on each device's rows: argument k is split along its leading axis when
        ``batched[k]``, else replicated; every output is split along its leading axis. Call it
        inside ``jax.jit``; the leading axes must be a multiple of ``size``."""
        specs = tuple(P(AXIS) if b else P() for b in batched)
        return jax.shard_map(fn, mesh=self.mesh, in_specs=specs, out_specs=P(AXIS), check_vma=False)


def pad_rows(tree: Any, size: int) -> Any:
    """Every leaf's leading axis grown to ``size`` with copies of its first row (NumPy leaves
    stay NumPy; works inside ``jit``). Leaves already ``size`` long are returned as they are."""

    def grow(x):
        n = x.shape[0]
        if n == size:
            return x
        if n == 0 or n > size:
            raise ValueError(f"pad_rows: {n} rows cannot be padded to {size}")
        xp = np if isinstance(x, np.ndarray) else jnp
        return xp.concatenate([x, xp.broadcast_to(x[:1], (size - n,) + x.shape[1:])])

    return jax.tree.map(grow, tree)


def map_in_batches(fn: Callable, rows: Any, batch_size: int) -> Any:
    """``fn`` on every row of ``rows`` (a pytree of arrays with a common leading axis N),
    ``batch_size`` rows vmapped at a time in a loop, the last N mod ``batch_size`` vmapped
    after it: ``jax.lax.map(fn, rows, batch_size=...)``, but also for outputs with an empty
    axis (lax.map reshapes with -1, which cannot infer a size next to a zero)."""
    n = jax.tree.leaves(rows)[0].shape[0]
    size = max(1, min(int(batch_size), n))
    steps, rest = divmod(n, size)
    head = jax.tree.map(lambda x: x[: steps * size].reshape((steps, size) + x.shape[1:]), rows)
    ys = jax.tree.map(lambda y: y.reshape((steps * size,) + y.shape[2:]), jax.lax.map(jax.vmap(fn), head))
    if rest:
        tail = jax.vmap(fn)(jax.tree.map(lambda x: x[steps * size:], rows))
        ys = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), ys, tail)
    return ys


def map_rows(fn: Callable, shared: Any, rows: Any, batch_size: int, mesh: BatchMesh | None) -> Any:
    """``fn(shared, row)`` for every row of ``rows`` (a pytree of arrays with a common leading
    axis), ``batch_size`` rows vmapped at a time (``jax.lax.map``). With a mesh the rows are
    padded to a multiple of its size and each device maps its own (``batch_size`` per device);
    the pad is cut off the outputs. Call it inside ``jax.jit``."""
    n = jax.tree.leaves(rows)[0].shape[0]
    if mesh is None:
        return map_in_batches(lambda r: fn(shared, r), rows, batch_size)
    size = mesh.padded(n)
    local = mesh.map(lambda s, r: map_in_batches(lambda x: fn(s, x), r, batch_size), (False, True))
    return jax.tree.map(lambda x: x[:n], local(shared, pad_rows(rows, size)))


def split(n: int, parts: int) -> list[slice]:
    """``n`` rows in ``min(parts, n)`` contiguous, near-equal slices (the first ones one longer)."""
    if parts < 1:
        raise ValueError(f"split: {parts} parts (expected at least 1)")
    parts = max(1, min(parts, n))
    bounds = np.cumsum([0] + [n // parts + (k < n % parts) for k in range(parts)])
    return [slice(int(a), int(b)) for a, b in itertools.pairwise(bounds)]
