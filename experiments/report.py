"""How every benchmark hands its result over: JSON on stdout, and the same text in ``--out``."""

from __future__ import annotations

import json
from pathlib import Path

from phirie_jax.io.atomic import write_text


def emit(result: dict, out: Path | None) -> None:
    """Print ``result`` as JSON; also write it to ``out`` (atomically) when given."""
    text = json.dumps(result, indent=2)
    print(text)
    if out:
        write_text(Path(out), text + "\n")
