"""Every array in ``kernels/`` declares its shape, in one style:

- a function's array parameter is named in its docstring followed by its shape,
  ``points (N, 3)`` (or ``points: (N, 3)``); a scalar is ``tau ()``;
- a pytree field's shape is the first thing in its trailing comment, ``means: jax.Array  # (N, 3)``.

A parameter is an array when it is annotated as one (``jax.Array``, ``jnp.ndarray``,
``np.ndarray``, ``Array``, optionally ``| None``) or not annotated at all: in kernels every
parameter that is not an array (sizes, flags, configs, pytrees of arrays, callables) carries
its type. Checked for every module-level function and method, public or private; functions
nested inside them (closures for ``vmap``/``lax.map``) take their shapes from the enclosing one.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

KERNELS = Path(__file__).resolve().parents[2] / "kernels"
ARRAY_ANNOTATIONS = {"jax.Array", "jnp.ndarray", "np.ndarray", "Array", "jax.Array | None",
                     "np.ndarray | None", "jnp.ndarray | None", "Array | None"}
# A shape: "()" or comma-separated dimensions, each "..." or a size expression (N, 3, Nt + 1, K · M).
_DIM = r"\s*(?:\.\.\.|[\w][\w .+\-*/·²]*)\s*"
SHAPE = rf"\((?:\s*|{_DIM}(?:,{_DIM})*,\s*|{_DIM}(?:,{_DIM})+)\)"


def _is_array(annotation: ast.expr | None) -> bool:
    return annotation is None or ast.unparse(annotation) in ARRAY_ANNOTATIONS


def _declared(name: str, doc: str) -> bool:
    return re.search(rf"(?<![\w.]){re.escape(name)}`{{0,2}}:?\s*{SHAPE}", doc) is not None


def undeclared(source: str, filename: str = "<kernel>") -> list[str]:
    """'file:line name' for every array parameter or pytree field without a declared shape."""
    tree = ast.parse(source)
    lines = source.splitlines()
    missing = []

    def check_function(fn: ast.FunctionDef, owner: str = "") -> None:
        doc = ast.get_docstring(fn) or ""
        args = fn.args
        params = args.posonlyargs + args.args + args.kwonlyargs
        params += [a for a in (args.vararg, args.kwarg) if a is not None]
        for arg in params:
            if arg.arg in ("self", "cls") or not _is_array(arg.annotation):
                continue
            if not _declared(arg.arg, doc):
                missing.append(f"{filename}:{fn.lineno} {owner}{fn.name}({arg.arg})")

    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            check_function(node)
        elif isinstance(node, ast.ClassDef):
            for item in node.body:
                if isinstance(item, ast.FunctionDef):
                    check_function(item, f"{node.name}.")
                elif (isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name)
                      and item.annotation is not None and _is_array(item.annotation)):
                    line = lines[item.end_lineno - 1]
                    comment = line.split("#", 1)[1] if "#" in line else ""
                    if not re.match(rf"\s*{SHAPE}", comment):
                        missing.append(f"{filename}:{item.lineno} {node.name}.{item.target.id}")
    return missing


@pytest.mark.parametrize("path", sorted(KERNELS.glob("*.py")), ids=lambda p: p.name)
def test_every_kernel_array_declares_its_shape(path):
    assert undeclared(path.read_text(), path.name) == []


def test_the_check_catches_undeclared_shapes():
    bad = '''
def f(points, mask, n: int, tau):
    """points (N, 3) the points; mask the valid ones."""

@pytree_dataclass
class P:
    a: jax.Array  # (N, 3)
    b: jax.Array  # bool per row
    c: int = static_field()
'''
    assert undeclared(bad) == ["<kernel>:2 f(mask)", "<kernel>:2 f(tau)", "<kernel>:8 P.b"]
    good = '''
def f(points, mask, n: int, tau):
    """points (N, 3); mask: (N,) bool; tau ()."""
'''
    assert undeclared(good) == []
