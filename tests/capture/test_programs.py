"""The training step's programs compiled ahead on a thread (phirie_jax.capture.programs)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from phirie_jax.capture.programs import StepPrograms, like, with_rows

_step = jax.jit(lambda rows, count, *, offset: (rows + offset, count + 1), static_argnames="offset")


def test_a_prepared_program_runs_the_step_of_its_sizes():
    programs = StepPrograms(_step, lambda capacity: {"offset": float(capacity)})
    rows, count = jnp.arange(6.0).reshape(3, 2), jnp.int32(4)
    programs.prepare((5, 7), (with_rows(rows, 5), like(count)))
    programs.wait()
    assert (5, 7) in programs.ready and not programs.failed
    bigger = jnp.ones((5, 2))
    out = programs((5, 7), bigger, count)
    np.testing.assert_array_equal(np.asarray(out[0]), np.full((5, 2), 8.0))
    assert int(out[1]) == 5
    # sizes nobody prepared: the jit compiles them on the spot, same result
    out = programs((3, 7), rows, count)
    np.testing.assert_array_equal(np.asarray(out[0]), np.asarray(rows) + 7.0)
    assert (3, 7) not in programs.ready


def test_a_failed_compilation_is_recorded_and_the_jit_takes_over():
    programs = StepPrograms(_step, lambda capacity: {"offset": float(capacity)})
    programs.prepare((2, 1), (with_rows(jnp.zeros((3, 2)), 2),))  # one argument short: lowering fails
    programs.wait()
    assert (2, 1) not in programs.ready and len(programs.failed) == 1
    out = programs((2, 1), jnp.zeros((2, 2)), jnp.int32(0))
    np.testing.assert_array_equal(np.asarray(out[0]), np.ones((2, 2)))


def test_with_rows_keeps_scalars_and_trailing_axes():
    tree = {"a": jnp.zeros((4, 3, 2)), "n": jnp.int32(1)}
    shapes = with_rows(tree, 16)
    assert shapes["a"].shape == (16, 3, 2) and shapes["n"].shape == () and shapes["n"].dtype == jnp.int32
