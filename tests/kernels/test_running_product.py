"""``kernels.running_product``: the products before and up to each element, against a slow
loop, inside a Pallas kernel (interpreted), and lowered to Triton for a CUDA target."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import export
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

from kernels.running_product import LOWERS_TO_TRITON, running_products


def _loop_products(x: np.ndarray, axis: int):
    """The slow reference: a loop along ``axis`` carrying the product (float64)."""
    x = np.moveaxis(np.asarray(x, np.float64), axis, 0)
    before, upto = np.empty_like(x), np.empty_like(x)
    carried = np.ones(x.shape[1:])
    for j in range(x.shape[0]):
        before[j] = carried
        carried = carried * x[j]
        upto[j] = carried
    return np.moveaxis(before, 0, axis), np.moveaxis(upto, 0, axis)


@pytest.mark.parametrize("axis", [0, 1, -1])
def test_products_match_a_loop(axis):
    """before[j] = Π_{k<j} x[k] and upto[j] = Π_{k≤j} x[k], for transmittance-like factors."""
    x = np.random.default_rng(0).uniform(0.01, 1.0, (8, 16)).astype(np.float32)
    before, upto = jax.jit(running_products, static_argnums=1)(x, axis)
    want_before, want_upto = _loop_products(x, axis)
    np.testing.assert_allclose(before, want_before, rtol=1e-5)
    np.testing.assert_allclose(upto, want_upto, rtol=1e-5)


def test_products_under_vmap_are_each_rows_products():
    """Mapped over a leading axis, each slice's products are its own (the primitive's batching)."""
    x = np.random.default_rng(3).uniform(0.01, 1.0, (3, 8, 16)).astype(np.float32)
    before, upto = jax.vmap(lambda a: running_products(a, 0))(x)
    for k in range(3):
        want_before, want_upto = _loop_products(x[k], 0)
        np.testing.assert_allclose(before[k], want_before, rtol=1e-5)
        np.testing.assert_allclose(upto[k], want_upto, rtol=1e-5)


def test_products_properties():
    """The first element is preceded by nothing (1); upto = before · x; the products never grow
    for factors in [0, 1]; a zero factor zeroes everything after it, not before."""
    x = np.random.default_rng(1).uniform(0.0, 1.0, (16, 4)).astype(np.float32)
    x[5, 2] = 0.0
    before, upto = (np.asarray(v) for v in running_products(jnp.asarray(x), 0))
    np.testing.assert_array_equal(before[0], 1.0)
    np.testing.assert_allclose(upto, before * x, rtol=1e-6)
    assert np.all(np.diff(upto, axis=0) <= 0.0)
    assert np.all(before[:6, 2] > 0.0) and np.all(before[6:, 2] == 0.0) and np.all(upto[5:, 2] == 0.0)


def _products_kernel(x_ref, before_ref, upto_ref):
    before, upto = running_products(x_ref[...], 0)
    before_ref[...] = before
    upto_ref[...] = upto


def _products_call(x, interpret: bool):
    shape = jax.ShapeDtypeStruct(x.shape, x.dtype)
    params = None if interpret else plgpu.CompilerParams(num_warps=4)  # the Triton backend
    return pl.pallas_call(_products_kernel, out_shape=(shape, shape), interpret=interpret,
                          compiler_params=params)(x)


def test_products_in_an_interpreted_pallas_kernel():
    """A Pallas kernel (interpreted) gives the loop's products."""
    x = np.random.default_rng(2).uniform(0.01, 1.0, (8, 32)).astype(np.float32)
    before, upto = _products_call(jnp.asarray(x), interpret=True)
    want_before, want_upto = _loop_products(x, 0)
    np.testing.assert_allclose(before, want_before, rtol=1e-5)
    np.testing.assert_allclose(upto, want_upto, rtol=1e-5)


def test_products_lower_to_triton():
    """The primitive has a Triton rule and a kernel using it lowers for a CUDA target (no GPU
    needed: what the scan computes there is checked by the GPU benchmarks' image comparisons)."""
    assert LOWERS_TO_TRITON
    exported = export.export(jax.jit(lambda x: _products_call(x, interpret=False)), platforms=["cuda"],
                             disabled_checks=[export.DisabledSafetyCheck.custom_call("__gpu$xla.gpu.triton")])(
        jax.ShapeDtypeStruct((8, 32), jnp.float32))
    assert "__gpu$xla.gpu.triton" in exported.mlir_module()
