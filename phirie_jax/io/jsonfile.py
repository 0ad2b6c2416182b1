"""JSON files whose top level must be an object, read with errors for people."""

from __future__ import annotations

import json
from pathlib import Path

from phirie_jax.errors import SceneInputError


def read_json_object(path: str | Path, expected: str = "a JSON object") -> dict:
    """The file's top-level object. A missing file, invalid JSON or another top-level value is a
    ``SceneInputError`` naming the file (``expected`` says what the object should hold)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SceneInputError(path, None, "file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SceneInputError(path, None, f"not valid JSON ({e})") from None
    if not isinstance(data, dict):
        raise SceneInputError(path, None, f"expected {expected}")
    return data
