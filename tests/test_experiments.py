"""Experiments import the package as it is installed (no ``sys.path`` edits) and run as modules
from the project root (``python -m experiments.NAME``)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted(p.stem for p in (ROOT / "experiments").glob("*.py") if p.stem != "__init__")


def test_no_experiment_edits_sys_path():
    edits = [name for name in SCRIPTS if "sys.path" in (ROOT / "experiments" / f"{name}.py").read_text()]
    assert not edits


def test_every_experiment_imports_as_a_module():
    script = "import importlib\n" + "".join(f"importlib.import_module('experiments.{n}')\n" for n in SCRIPTS)
    done = subprocess.run([sys.executable, "-c", script + "print('ok')"], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-2000:]
