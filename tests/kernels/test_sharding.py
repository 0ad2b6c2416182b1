"""The batch-axis helpers on this process's devices (one, usually); four devices: tests/multi_device.py."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kernels.sharding import BatchMesh, map_in_batches, map_rows, pad_rows, resolve_devices, split


def test_devices_are_resolved_from_none_a_count_or_a_list():
    assert resolve_devices() == tuple(jax.devices())
    assert resolve_devices(1) == (jax.devices()[0],)
    assert resolve_devices([jax.devices()[0]]) == (jax.devices()[0],)
    with pytest.raises(ValueError, match="expected 1 to"):
        resolve_devices(len(jax.devices()) + 1)
    with pytest.raises(ValueError, match="empty"):
        resolve_devices([])
    with pytest.raises(ValueError, match="twice"):
        resolve_devices([jax.devices()[0]] * 2)


def test_padding_repeats_the_first_row_to_a_multiple_of_the_devices():
    mesh = BatchMesh.over(1)
    assert mesh.size == 1 and mesh.padded(0) == 1 and mesh.padded(7) == 7
    tree = {"a": np.arange(6.0).reshape(3, 2), "b": jnp.array([5, 6, 7])}
    grown = pad_rows(tree, 5)
    assert isinstance(grown["a"], np.ndarray) and isinstance(grown["b"], jax.Array)
    np.testing.assert_array_equal(grown["a"], [[0, 1], [2, 3], [4, 5], [0, 1], [0, 1]])
    np.testing.assert_array_equal(grown["b"], [5, 6, 7, 5, 5])
    assert pad_rows(tree, 3) is not tree and pad_rows(tree, 3)["a"] is tree["a"]
    with pytest.raises(ValueError, match="cannot be padded"):
        pad_rows(np.zeros((4, 2)), 3)


def test_split_gives_contiguous_near_equal_parts():
    assert split(7, 3) == [slice(0, 3), slice(3, 5), slice(5, 7)]
    assert split(2, 4) == [slice(0, 1), slice(1, 2)]        # no empty part
    assert split(0, 2) == [slice(0, 0)]
    for n, parts in ((4096, 2), (1023, 8), (5, 5)):
        pieces = split(n, parts)
        assert pieces[0].start == 0 and pieces[-1].stop == n
        assert all(a.stop == b.start for a, b in itertools.pairwise(pieces))
        assert max(p.stop - p.start for p in pieces) - min(p.stop - p.start for p in pieces) <= 1
    with pytest.raises(ValueError):
        split(3, 0)


def test_map_rows_on_a_mesh_of_one_is_lax_map_and_a_new_mesh_reuses_the_program():
    traces = []

    def row(shared, x):
        traces.append(1)
        return jnp.sum(jnp.sin(x * shared)), x[::-1]

    @jax.jit
    def plain(shared, xs):
        return map_rows(row, shared, xs, 4, None)

    xs = jnp.linspace(0.0, 3.0, 27).reshape(9, 3)
    ref = plain(jnp.float32(1.7), xs)
    program = jax.jit(lambda s, xs, mesh: map_rows(row, s, xs, 4, mesh), static_argnums=2)
    got = program(jnp.float32(1.7), xs, BatchMesh.over(1))
    for a, b in zip(got, ref, strict=True):
        np.testing.assert_array_equal(a, b)
    count = len(traces)
    program(jnp.float32(0.3), xs, BatchMesh.over(1))          # an equal mesh: the same program
    assert len(traces) == count
    assert BatchMesh.over(1) == BatchMesh.over([jax.devices()[0]])


def test_map_in_batches_is_vmap_with_a_remainder_and_empty_outputs():
    def row(x):
        return jnp.cumsum(x) * 2.0, jnp.zeros((2, 0)), x[:1]

    xs = jnp.linspace(0.0, 3.0, 27).reshape(9, 3)
    ref = jax.vmap(row)(xs)
    for size in (1, 2, 4, 9, 20):  # remainders 0, 1, 1, 0 and one batch larger than the rows
        got = jax.jit(lambda xs, size=size: map_in_batches(row, xs, size))(xs)
        for a, b in zip(got, ref, strict=True):
            assert a.shape == b.shape
            np.testing.assert_array_equal(a, b)


class _FakeGpu:
    platform = "gpu"


def test_several_gpus_compile_with_gspmd_and_cpus_keep_the_default(monkeypatch):
    from kernels.sharding import use_gspmd_on_gpus

    before = jax.config.jax_use_shardy_partitioner
    monkeypatch.delenv("JAX_USE_SHARDY_PARTITIONER", raising=False)
    try:
        jax.config.update("jax_use_shardy_partitioner", True)
        assert use_gspmd_on_gpus(jax.devices()) is False           # CPU devices: the default stays
        assert use_gspmd_on_gpus([_FakeGpu()]) is False            # one GPU: nothing is partitioned
        assert jax.config.jax_use_shardy_partitioner
        monkeypatch.setenv("JAX_USE_SHARDY_PARTITIONER", "1")      # the user's choice is kept
        assert use_gspmd_on_gpus([_FakeGpu(), _FakeGpu()]) is False
        monkeypatch.delenv("JAX_USE_SHARDY_PARTITIONER")
        with pytest.warns(RuntimeWarning, match="GSPMD"):
            assert use_gspmd_on_gpus([_FakeGpu(), _FakeGpu()]) is True
        assert not jax.config.jax_use_shardy_partitioner
    finally:
        jax.config.update("jax_use_shardy_partitioner", before)
