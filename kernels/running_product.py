"""Running products along one axis of a block inside a Pallas kernel: each element's product
of the elements before it and up to it (the compositor's transmittances before and after
each entry of a chunk).

Pallas lowers ``jnp.cumsum`` to Triton but no cumulative product, so the compositor took its
running transmittances as 2 to the power of a running sum of log₂(1 − α): two special-function
instructions (a logarithm and a power) for every entry and pixel. This primitive is one Triton
scan over the pairs (p, q) = (product up to here, product before the last element), whose
combination (p₁, q₁)·(p₂, q₂) = (p₁p₂, p₁q₂) is associative; its leaves are (x, 1). It takes
two multiplications per element and no special function. The exclusive products come out of
the scan itself, with no division by the element.

Lowered through Triton on a GPU (registered with Pallas' Triton lowering, whose rule table is
private to JAX); elsewhere, and in Pallas' interpreter, it is ``jnp.cumprod`` shifted by one.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax.numpy as jnp
from jax.extend.core import Primitive
from jax.interpreters import batching, mlir

if TYPE_CHECKING:
    from jax._src.lib.mlir import ir

running_products_p = Primitive("running_products")
running_products_p.multiple_results = True


def running_products(x, axis: int):
    """x (..., B, ...) float → (before, upto), each the shape of x: before[j] = Π_{k<j} x[k]
    (1 for the first) and upto[j] = Π_{k≤j} x[k] along ``axis`` (B the axis' length)."""
    return running_products_p.bind(x, jnp.ones_like(x), axis=axis % x.ndim)


def _reference(x, ones, *, axis: int):
    """The same products in XLA: ``jnp.cumprod`` and that shifted by one along ``axis``;
    x (..., B, ...) and ones (..., B, ...) the primitive's operands."""
    upto = jnp.cumprod(x, axis=axis)
    first = jnp.take(ones, jnp.arange(1), axis=axis)
    before = jnp.concatenate([first, jnp.take(upto, jnp.arange(x.shape[axis] - 1), axis=axis)], axis=axis)
    return before, upto


def _abstract(x, ones, *, axis: int):
    """The outputs' shapes: x (..., B, ...) and ones (..., B, ...) as avals → two of x's."""
    del ones, axis
    return x, x


def _batched(args: tuple, dims: tuple, *, axis: int) -> tuple:
    """vmap: args (x, ones), each (..., B, ...) with its batch axis at ``dims`` (None: not
    mapped) → the products of x, its batch axis first, and the outputs' batch axes."""
    x, ones = args
    if dims[0] is None:   # x not mapped (only the ones were): its products are every slice's
        return running_products_p.bind(x, jnp.ones_like(x), axis=axis), (None, None)
    x = jnp.moveaxis(x, dims[0], 0)
    return running_products_p.bind(x, jnp.ones_like(x), axis=axis + 1), (0, 0)


def _triton_lowering(ctx: object, x: ir.Value, ones: ir.Value, *, axis: int) -> list:
    """One ``tt.scan`` over the operands (x, 1): (p₁, q₁)·(p₂, q₂) = (p₁p₂, p₁q₂) gives p, the
    inclusive product, and q, the product before each element (Triton tensors of one shape;
    ``ctx``, Pallas' lowering context, is not needed)."""
    from jax._src.lib.mlir import ir
    from jax._src.lib.mlir.dialects import arith
    from jax._src.lib.triton import dialect as tt

    del ctx
    element = ir.RankedTensorType(x.type).element_type
    scan = tt.ScanOp([x, ones], axis)
    region = scan.regions[0].blocks.append(element, element, element, element)
    with ir.InsertionPoint.at_block_begin(region):
        p_left, q_left, p_right, q_right = region.arguments
        tt.scan_return([arith.mulf(p_left, p_right), arith.mulf(p_left, q_right)])
    scan.verify()
    upto, before = scan.result
    return [before, upto]


def _register_triton_lowering() -> bool:
    """Add the Triton rule to Pallas' table; False where this JAX has no such table (a kernel
    using the primitive then fails to lower on a GPU, naming it; the interpreter still runs)."""
    try:
        from jax._src.pallas.triton import lowering
    except ImportError:
        return False
    table = getattr(lowering, "triton_lowering_rules", None)
    if not isinstance(table, dict):
        return False
    table[running_products_p] = _triton_lowering
    return True


running_products_p.def_impl(_reference)
running_products_p.def_abstract_eval(_abstract)
batching.primitive_batchers[running_products_p] = _batched
mlir.register_lowering(running_products_p, mlir.lower_fun(_reference, multiple_results=True))
LOWERS_TO_TRITON = _register_triton_lowering()
