"""The training's programs compiled ahead on a thread (phirie_jax.capture.programs)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from phirie_jax.capture.programs import Programs, like, with_rows

_step = jax.jit(lambda rows, count, *, offset: (rows + offset, count + 1), static_argnames="offset")


def test_a_prepared_program_runs_the_function_at_its_sizes():
    programs = Programs()
    rows, count = jnp.arange(6.0).reshape(3, 2), jnp.int32(4)
    programs.prepare(("step", 5), _step, (with_rows(rows, 5), like(count)), offset=7.0)
    programs.wait()
    assert ("step", 5) in programs.ready and not programs.failed
    out = programs(("step", 5), _step, jnp.ones((5, 2)), count, offset=7.0)
    np.testing.assert_array_equal(np.asarray(out[0]), np.full((5, 2), 8.0))
    assert int(out[1]) == 5
    # sizes nobody prepared: the jit compiles them on the spot, same result
    out = programs(("step", 3), _step, rows, count, offset=7.0)
    np.testing.assert_array_equal(np.asarray(out[0]), np.asarray(rows) + 7.0)
    assert ("step", 3) not in programs.ready


def test_a_failed_compilation_is_recorded_and_the_jit_takes_over():
    programs = Programs()
    programs.prepare(("step", 2), _step, (with_rows(jnp.zeros((3, 2)), 2),), offset=1.0)  # one argument short
    programs.wait()
    assert ("step", 2) not in programs.ready and len(programs.failed) == 1
    out = programs(("step", 2), _step, jnp.zeros((2, 2)), jnp.int32(0), offset=1.0)
    np.testing.assert_array_equal(np.asarray(out[0]), np.ones((2, 2)))


def test_with_rows_keeps_scalars_and_trailing_axes():
    tree = {"a": jnp.zeros((4, 3, 2)), "n": jnp.int32(1)}
    shapes = with_rows(tree, 16)
    assert shapes["a"].shape == (16, 3, 2) and shapes["n"].shape == () and shapes["n"].dtype == jnp.int32


def test_programs_not_enabled_leave_everything_to_the_jit():
    programs = Programs(enabled=False)
    programs.prepare(("step", 5), _step, (with_rows(jnp.zeros((3, 2)), 5), like(jnp.int32(0))), offset=1.0)
    assert not programs.ready and not programs.pending
    out = programs(("step", 5), _step, jnp.zeros((5, 2)), jnp.int32(0), offset=1.0)
    np.testing.assert_array_equal(np.asarray(out[0]), np.ones((5, 2)))
