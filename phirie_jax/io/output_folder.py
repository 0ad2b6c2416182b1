"""The output folder's safety rules: what a run may write into, and one run at a time.

A run writes only into a folder that is new, empty, holds unrelated files only, or holds an
earlier run's output (its ``manifest.json``, schema ``phirie/...``). It refuses, before any work
and with one line:

- a folder that holds a capture's inputs (a Gaussian PLY, cameras, images) and no earlier run's
  manifest: converting into another capture would replace its ``transforms.json``;
- a folder inside the scene folder, or one that holds it: the outputs would land among the
  capture's files;
- a folder that holds a file at a name the run writes (``scene.xml``, ``objects/`` ...) but no
  earlier run's manifest: an output never replaces a file no run of ours wrote;
- an input (``--gaussians``, ``--surface``, the masks, the images) inside the output folder.

``OutputLock`` takes the folder for one run: ``OUT/.phirie.lock`` holds the holder's process id,
host, start time and command, under an exclusive ``flock``. The kernel releases the flock when the
holder exits or is killed, so a lock file left by a killed run is stale: the next run sees the
flock free, says whose it was, and takes it over. A second run while the first holds it is refused
with the holder's details. The lock file is removed on a clean release.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
import sys
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

from phirie_jax import layout
from phirie_jax.errors import OptionError, SceneInputError
from phirie_jax.types import GAUSSIAN_NAMES

# What marks a folder as a capture (``io.scene`` reads these): Gaussians, cameras, images.
CAPTURE_FILES = (*GAUSSIAN_NAMES, "transforms.json")
CAPTURE_FOLDERS = ("point_cloud", "sparse", "dslr", "images")
SCHEMA_PREFIX = "phirie/"
LOCK_ATTEMPTS = 8   # a lock file replaced between open and flock is opened again


def _inside(path: Path, folder: Path) -> bool:
    """Whether ``path`` is ``folder`` or lies under it (both resolved, links followed)."""
    path, folder = Path(os.path.realpath(path)), Path(os.path.realpath(folder))
    return path == folder or folder in path.parents


def earlier_output(out_dir: Path) -> bool | None:
    """True when ``out_dir`` holds a manifest one of our runs wrote, False when it holds another
    ``manifest.json``, None when it holds none."""
    path = Path(out_dir) / layout.MANIFEST
    if not path.is_file():
        return None
    try:
        schema = json.loads(path.read_text(encoding="utf-8")).get("schema")
    except (OSError, ValueError, AttributeError):
        return False
    return isinstance(schema, str) and schema.startswith(SCHEMA_PREFIX)


def capture_inputs(folder: Path) -> list[str]:
    """The names in ``folder`` that mark a capture (a Gaussian PLY, cameras, images)."""
    found = [name for name in CAPTURE_FILES if (folder / name).is_file()]
    found += [name + "/" for name in CAPTURE_FOLDERS if (folder / name).is_dir()]
    return found


def _written_names(folder: Path) -> list[str]:
    """The names in ``folder`` that a run writes (``layout.TOP_LEVEL``)."""
    return [name for name in layout.TOP_LEVEL if os.path.lexists(folder / name)]


def _refuse(out_dir: Path, problem: str) -> None:
    raise OptionError("--out", f"{problem}; nothing was written", str(out_dir))


def check_output_folder(out_dir: Path, scene_root: Path) -> None:
    """Refuse an ``--out`` a run must not write into (module docstring); ``scene_root`` is the
    scene folder being converted. Nothing is created or written here."""
    out_dir = Path(out_dir)
    for path in (out_dir, *out_dir.absolute().parents):
        if path.exists():
            if not path.is_dir():
                what = "is a file" if path == out_dir else f"{path} is a file"
                raise OptionError("--out", f"{what} (expected a folder: a new one or an earlier run's output)",
                                  str(out_dir))
            break
    scene_root = Path(scene_root)
    if out_dir.exists() and out_dir.resolve() == scene_root.resolve():
        raise OptionError("--out", "the scene folder itself (expected another folder: the outputs would "
                          "overwrite the scene's own transforms.json)", str(out_dir))
    if _inside(out_dir, scene_root):
        _refuse(out_dir, f"inside the scene folder {scene_root.resolve()} (expected a folder outside it: the "
                "outputs would be written among the capture's files)")
    if _inside(scene_root, out_dir):
        _refuse(out_dir, f"holds the scene folder {scene_root.resolve()} (expected a folder beside it)")
    if not out_dir.is_dir():
        return
    ours = earlier_output(out_dir)
    if ours is False:
        _refuse(out_dir, f"holds a {layout.MANIFEST} that phirie did not write (expected a new folder or an "
                "earlier run's output)")
    captured = capture_inputs(out_dir)
    if ours:
        captured = [name for name in captured if name != layout.CAMERAS]  # the run wrote that one
    if captured:
        where = "beside an earlier run's manifest.json" if ours else "and no earlier run's manifest.json"
        _refuse(out_dir, f"holds a capture's inputs ({', '.join(captured)}) {where} (expected a new folder or an "
                "earlier run's output: converting into a capture would replace its files)")
    written = _written_names(out_dir)
    links = [name for name in written if (out_dir / name).is_symlink()]
    if links:
        _refuse(out_dir, f"{', '.join(links)} is a symbolic link (expected the run's own files and folders)")
    if written and not ours:
        _refuse(out_dir, f"holds files a run would replace ({', '.join(written)}) and no earlier run's "
                "manifest.json (expected a new folder or an earlier run's output)")
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise OptionError("--out", "not writable (expected a folder this user can write into)", str(out_dir))


def check_inputs_outside(out_dir: Path, inputs: Iterable[tuple[str, Path | None]]) -> None:
    """Refuse an input (``(what, path)``, e.g. ``("--gaussians", path)``) inside ``out_dir``."""
    for what, path in inputs:
        if path is not None and _inside(path, out_dir):
            _refuse(out_dir, f"holds {what} {path} (expected the inputs outside the output folder: "
                    "the run would write where it reads)")


def check_scene_target(folder: Path, earlier: str) -> None:
    """A command that writes a whole scene folder (``phirie synth``, ``phirie capture``) writes into
    a new or empty folder, or one it wrote before (``earlier`` names a file only it writes there);
    anything else is refused before any work, so a capture is never overwritten."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise SceneInputError(folder, None, "is a file (expected a new or empty folder)")
    if folder.is_dir() and any(folder.iterdir()) and not (folder / earlier).is_file():
        found = ", ".join(sorted(p.name + ("/" if p.is_dir() else "") for p in folder.iterdir())[:4])
        raise SceneInputError(folder, None, f"holds files ({found}) and is not an earlier output of this command "
                              "(expected a new or empty folder); nothing was written")


# --- one run at a time ---------------------------------------------------------------------------


def _holder_record() -> dict:
    return {"pid": os.getpid(), "host": socket.gethostname(),
            "started": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime()),
            "command": " ".join(os.path.basename(a) if i == 0 else a for i, a in enumerate(sys.argv))[:200]}


def _read_holder(fd: int) -> dict:
    try:
        data = json.loads(os.pread(fd, 4096, 0).decode("utf-8") or "{}")
    except (OSError, ValueError, UnicodeDecodeError):
        return {}
    return data if isinstance(data, dict) else {}


def describe_holder(holder: dict) -> str:
    """``process 123 on host, started ... (phirie convert ...)`` from a lock file's record."""
    if not holder.get("pid"):
        return "another process"
    text = f"process {holder['pid']}"
    if holder.get("host"):
        text += f" on {holder['host']}"
    if holder.get("started"):
        text += f", started {holder['started']}"
    if holder.get("command"):
        text += f" ({holder['command']})"
    return text


def running_holder(out_dir: Path) -> str | None:
    """Who holds ``out_dir``'s lock now, described, when its process runs on this host; else None.
    Read without taking the lock (so a run starting now is never turned away by the reader)."""
    path = Path(out_dir) / layout.LOCK
    try:
        holder = json.loads(path.read_text(encoding="utf-8"))
        pid = int(holder["pid"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if holder.get("host") not in (None, socket.gethostname()) or pid == os.getpid():
        return None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return None
    except PermissionError:
        pass
    return describe_holder(holder)


class OutputLock:
    """The exclusive lock of one output folder (module docstring). ``stale`` is the record of a
    killed run whose lock this one took over (None when there was none)."""

    def __init__(self, fd: int, path: Path, stale: dict | None):
        self._fd: int | None = fd
        self.path = path
        self.stale = stale

    @classmethod
    def acquire(cls, out_dir: Path) -> OutputLock:
        """Take ``out_dir``'s lock (the folder must exist); ``OptionError`` naming the holder when
        another process has it."""
        path = Path(out_dir) / layout.LOCK
        for _ in range(LOCK_ATTEMPTS):
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _read_holder(fd)
                os.close(fd)
                raise OptionError("--out", f"in use by {describe_holder(holder)} (expected one run at a time "
                                  f"in a folder; wait for it to finish or stop it)", str(out_dir)) from None
            except BaseException:
                os.close(fd)
                raise
            try:  # a holder releasing in between unlinked the file we opened: open the new one
                current = os.stat(path)
            except FileNotFoundError:
                current = None
            mine = os.fstat(fd)
            if current is None or (current.st_ino, current.st_dev) != (mine.st_ino, mine.st_dev):
                os.close(fd)
                continue
            previous = _read_holder(fd)
            record = json.dumps(_holder_record()).encode("utf-8")
            os.ftruncate(fd, 0)
            os.pwrite(fd, record, 0)
            return cls(fd, path, previous or None)
        raise OptionError("--out", "its lock file keeps changing (expected one run at a time in a folder)",
                          str(out_dir))

    def release(self) -> None:
        """Remove the lock file and let go (idempotent)."""
        if self._fd is None:
            return
        with contextlib.suppress(FileNotFoundError):
            current = os.stat(self.path)
            mine = os.fstat(self._fd)
            if (current.st_ino, current.st_dev) == (mine.st_ino, mine.st_dev):
                os.unlink(self.path)
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> OutputLock:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


@contextlib.contextmanager
def locked(out_dir: Path) -> Iterator[OutputLock]:
    """``out_dir`` (created when missing) held by this process for the block; says so when it took
    over a killed run's lock."""
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    with OutputLock.acquire(out_dir) as lock:
        if lock.stale:
            print(f"phirie: note: {Path(out_dir) / layout.LOCK}: took over the lock of "
                  f"{describe_holder(lock.stale)}, which is no longer running", file=sys.stderr, flush=True)
        yield lock
