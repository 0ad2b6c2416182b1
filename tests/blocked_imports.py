"""Run Python in a fresh interpreter in which some top-level packages cannot be imported."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_without(blocked: tuple[str, ...], modules: tuple[str, ...] | list[str], then: str = ""
                ) -> subprocess.CompletedProcess:
    """Import ``modules`` (then run the code ``then``) with ``blocked`` packages unimportable; the
    script prints "ok" last when everything worked. Runs in the project root."""
    script = f"""
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {tuple(blocked)!r}:
            raise ImportError("blocked in this test: " + name)
sys.meta_path.insert(0, Block())
for name in {list(modules)!r}:
    __import__(name)
{then}
print("ok")
"""
    return subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True)
