"""Write-then-rename, so no output file is ever half-written.

A file is written to ``.NAME.XXXXXXXX.tmp`` beside NAME (``tempfile``'s eight random characters)
and renamed over NAME once complete. A process killed in between leaves that temporary behind;
``remove_temporaries`` clears such leftovers from a folder (the next run of the same output).
"""

from __future__ import annotations

import contextlib
import os
import re
import stat
import tempfile
from pathlib import Path
from typing import IO, Iterator


def ordinary_file_mode() -> int:
    """The mode an ordinary new file gets (0o666 less the umask); ``mkstemp`` makes 0o600."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


# The names ``_stage`` makes: ``.`` + NAME + ``.`` + tempfile's 8 random characters + ``.tmp``.
TEMPORARY_NAME = re.compile(r"\.(?P<name>.+)\.[a-z0-9_]{8}\.tmp")


def _stage(folder: Path, name: str) -> tuple[int, str]:
    fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=folder)
    os.fchmod(fd, ordinary_file_mode())
    return fd, tmp


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file beside ``path``; on success rename it over ``path``.

    On any exception the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _stage(path.parent, path.name)
    try:
        with os.fdopen(fd, mode, **({} if "b" in mode else {"encoding": "utf-8"})) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_text(path: str | Path, text: str) -> None:
    with atomic_write(path, "w") as f:
        f.write(text)


def write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_write(path, "wb") as f:
        f.write(data)


def write_files(folder: Path, files: dict[str, bytes]) -> None:
    """Write each ``name → bytes`` into ``folder``: all to temporary names first, then renamed."""
    folder.mkdir(parents=True, exist_ok=True)
    staged: list[tuple[str, Path]] = []
    try:
        for name, data in files.items():
            fd, tmp = _stage(folder, name)
            staged.append((name, Path(tmp)))
            with os.fdopen(fd, "wb") as out:
                out.write(data)
                out.flush()
                os.fsync(out.fileno())
        for name, tmp in staged:
            os.replace(tmp, folder / name)
    finally:
        for _, tmp in staged:
            tmp.unlink(missing_ok=True)


def remove_temporaries(folder: str | Path) -> list[Path]:
    """Remove the temporaries an interrupted write left in ``folder`` (not its subfolders); returns them.

    Only regular files named like ``_stage``'s temporaries are removed, nothing else. Meant for a
    folder one run writes at a time: a write in progress elsewhere would lose its temporary.
    """
    folder = Path(folder)
    removed = []
    for entry in sorted(os.scandir(folder), key=lambda e: e.name) if folder.is_dir() else ():
        if TEMPORARY_NAME.fullmatch(entry.name) and stat.S_ISREG(entry.stat(follow_symlinks=False).st_mode):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(entry.path)
                removed.append(Path(entry.path))
    return removed
