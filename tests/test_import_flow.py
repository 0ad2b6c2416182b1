"""Imports follow the pipeline (docs/architecture.md "Layout"): kernels ← shared records ← io ← observe ←
construct (objects ← physics ← background) ← interact ← pipeline ← commands. A module may import
its own layer or an earlier one, never a later one; lazy imports inside functions count too."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# (module prefix, layer): the longest matching prefix decides a module's layer.
LAYERS = (
    ("kernels", 0),
    ("phirie_jax.errors", 1), ("phirie_jax.native", 1), ("phirie_jax.types", 1), ("phirie_jax.geometry", 1), ("phirie_jax.rotations", 1),
    ("phirie_jax.layout", 1),
    ("phirie_jax.ranges", 1), ("phirie_jax.progress", 1), ("phirie_jax.threads", 1), ("phirie_jax.compile_count", 1), ("phirie_jax.compile_cache", 1),
    ("phirie_jax.io", 2),
    ("phirie_jax.manifest", 3), ("phirie_jax.records", 3), ("phirie_jax.render", 3), ("phirie_jax.provenance", 3),
    ("phirie_jax.frame", 4), ("phirie_jax.synthetic", 4), ("phirie_jax.synthetic.fitted", 4), ("phirie_jax.capture", 4),
    ("phirie_jax.observe", 5),
    ("phirie_jax.construct.objects", 6),
    ("phirie_jax.construct.physics", 7),
    ("phirie_jax.construct.background", 8),
    ("phirie_jax.interact", 9),
    ("phirie_jax.pipeline", 10), ("phirie_jax.report.config", 10),
    ("phirie_jax.info", 11), ("phirie_jax.demo", 11), ("phirie_jax.cli", 11), ("phirie_jax.view", 11),
    ("phirie_jax.report", 11), ("phirie_jax.cluster", 11),
)
PACKAGE_ROOTS = ("phirie_jax", "kernels")
CONTAINERS = ("phirie_jax", "phirie_jax.construct", "phirie_jax.frame")  # packages that only group others: they import nothing


def layer(module: str) -> int | None:
    best = None
    for prefix, level in LAYERS:
        if (module == prefix or module.startswith(prefix + ".")) and (best is None or len(prefix) > len(best[0])):
            best = (prefix, level)
    return None if best is None else best[1]


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import of a project module in the file, including ``from X import
    submodule`` (resolved to X.submodule when that is a module of ours)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                as_path = ROOT.joinpath(*sub.split("."))
                if as_path.with_suffix(".py").is_file() or (as_path / "__init__.py").is_file():
                    found.append((node.lineno, sub))
    return [(line, m) for line, m in found if m.split(".")[0] in PACKAGE_ROOTS]


def package_files() -> list[Path]:
    return sorted(p for root in PACKAGE_ROOTS for p in (ROOT / root).rglob("*.py"))


def test_every_module_has_a_layer():
    missing = [module_name(p) for p in package_files()
               if layer(module_name(p)) is None and module_name(p) not in CONTAINERS]
    assert not missing, f"modules outside the layer table (add them to LAYERS): {missing}"
    for name in CONTAINERS:
        path = ROOT.joinpath(*name.split("."), "__init__.py")
        assert imported_modules(path) == [], f"{name} only groups its subpackages"


def test_no_import_goes_against_the_flow():
    backward = []
    for path in package_files():
        own = layer(module_name(path))
        for line, target in imported_modules(path):
            theirs = layer(target)
            if theirs is not None and own is not None and theirs > own:
                backward.append(f"{path.relative_to(ROOT)}:{line} imports {target}")
    assert not backward, "imports against the pipeline's flow:\n" + "\n".join(backward)


@pytest.mark.parametrize("source, expected", [("from phirie_jax.interact.environment import Environment", True),
                                              ("from phirie_jax.construct import physics", True),
                                              ("from phirie_jax.io.ply import read_gaussian_ply", False)])
def test_the_check_sees_a_backward_edge(tmp_path, source, expected):
    """The walker finds late imports, plain or as a submodule of a package, in a low-layer module."""
    fake = tmp_path / "probe.py"
    fake.write_text(f"def f():\n    {source}\n")
    targets = [m for _, m in imported_modules(fake)]
    assert any((layer(m) or 0) > layer("phirie_jax.observe") for m in targets) == expected


def imports_of(path: Path) -> set[str]:
    """The project modules a file imports (lazy imports included): ``from X import Y`` is an edge to
    X.Y where that is a module, else to X (importing a submodule runs its package only to find it)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                as_path = ROOT.joinpath(*sub.split("."))
                is_module = as_path.with_suffix(".py").is_file() or (as_path / "__init__.py").is_file()
                found.add(sub if is_module else node.module)
    return {m for m in found if m.split(".")[0] in PACKAGE_ROOTS}


def import_graph(paths: list[Path]) -> dict[str, set[str]]:
    """module → the project modules it imports."""
    return {module_name(p): imports_of(p) - {module_name(p)} for p in paths}


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.get(root, ()))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, edges = work[-1]
            for nxt in edges:
                if nxt not in graph:
                    continue
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph[nxt]))))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        circles.append(sorted(component))
    return circles


def test_no_import_circles():
    """No two modules import each other, directly or round a longer loop, lazily or not: layers rule
    out circles between layers, this rules them out inside one."""
    circles = import_circles(import_graph(package_files()))
    assert not circles, "import circles:\n" + "\n".join(" ↔ ".join(c) for c in circles)


def test_the_check_sees_a_circle(tmp_path):
    """Two modules that import each other and a three-module loop are found, each once; a chain is
    not a circle; a lazy import of a submodule is an edge to that submodule."""
    graph = {"a": {"b"}, "b": {"a", "c"}, "c": {"d"}, "d": {"e"}, "e": {"c"}, "f": {"a"}, "g": set()}
    assert sorted(import_circles(graph)) == [["a", "b"], ["c", "d", "e"]]
    assert import_circles({"a": {"b"}, "b": {"c"}, "c": set()}) == []
    probe = tmp_path / "probe.py"
    probe.write_text("import kernels.sh\ndef f():\n    from phirie_jax.construct.physics import warp_batch\n"
                     "    from phirie_jax.construct.physics.config import DropTestConfig\n")
    assert imports_of(probe) == {"kernels.sh", "phirie_jax.construct.physics.warp_batch",
                                 "phirie_jax.construct.physics.config"}


def test_importing_any_module_starts_no_jax_backend():
    """Importing a module runs no JAX computation: collision worker processes import the command's
    module, and on a GPU host a backend started there takes a CUDA context and memory in every
    worker (the large preset's collision step took 60-90 s instead of 14 s that way)."""
    import subprocess
    import sys

    modules = sorted(module_name(p) for p in package_files() if not module_name(p).endswith("__main__"))
    code = ("import importlib, sys\n"
            f"for name in {modules!r}:\n"
            "    try:\n"
            "        importlib.import_module(name)\n"
            "    except ImportError:\n"
            "        pass  # an optional extra that is not installed\n"
            "from jax._src import xla_bridge\n"
            "sys.exit(1 if xla_bridge._backends else 0)\n")
    done = subprocess.run([sys.executable, "-c", code], check=False, cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, f"a module import started a JAX backend\n{done.stderr[-2000:]}"
