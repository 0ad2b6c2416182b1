"""Where a conversion's threads hold the Python interpreter: a stage run again under py-spy's
``--gil`` sampling, the samples summed by the project function that was running.

The objects stage builds every object in its own thread (``ObjectsConfig.workers``). Whatever a
thread does while it holds the interpreter (Python code, NumPy operations that keep it, native
calls that never let it go) runs one thread at a time, however many cores the host has: the
held seconds summed over the threads are a floor under the stage's wall time on any machine.

    pip install py-spy
    python -m experiments.interpreter_profile --capture WORK/capture --converted WORK/out \\
        --stages objects --out experiments/results/objects_interpreter_cpu.json

``--converted`` is a folder whose earlier stages are complete (a ``convert_scale`` run's
``out``); it is copied, and the copy's ``--stages`` run again (the frame stage always runs).
``--raw FILE`` summarizes an earlier py-spy ``--format raw`` recording instead of recording.
"""

from __future__ import annotations

import argparse
import collections
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

PROJECT = ("phirie_jax/", "kernels/")
OBJECT_THREADS = "objects"  # ThreadPoolExecutor prefix of the objects stage (construct/objects/stage.py)


def parse_raw(text: str) -> list[tuple[str, list[str], int]]:
    """py-spy ``--format raw`` lines → (thread name, frames outermost first, samples)."""
    stacks = []
    for record in re.split(r"\n(?=process \d+:|thread \()", text):
        body, _, count = record.strip().rpartition(" ")
        start = body.find("thread (")
        if start < 0 or not count.isdigit():
            continue
        frames = body[start:].split(";")
        thread = frames[0].partition(": ")[2] or frames[0]
        stacks.append((thread, frames[1:], int(count)))
    return stacks


def _project_frame(frames: list[str]) -> str:
    """The innermost frame in the project's code ("function (file:line)"), or the innermost."""
    own = [f for f in frames if any(p in f for p in PROJECT)]
    return own[-1] if own else (frames[-1] if frames else "?")


def summarize(stacks, rate: int, top: int = 25) -> dict:
    """Held seconds per thread group and, in the objects' threads, per project line."""
    by_group: collections.Counter = collections.Counter()
    by_line: collections.Counter = collections.Counter()
    for thread, frames, count in stacks:
        group = OBJECT_THREADS if thread.startswith(OBJECT_THREADS) else thread
        by_group[group] += count
        if group == OBJECT_THREADS:
            by_line[_project_frame(frames)] += count
    return {"rate_hz": rate,
            "held_s_by_thread": {k: round(v / rate, 2) for k, v in by_group.most_common()},
            "objects_threads_held_s": round(by_group[OBJECT_THREADS] / rate, 2),
            "objects_threads_top": [{"where": k, "held_s": round(v / rate, 2)} for k, v in by_line.most_common(top)]}


def record(capture: Path, converted: Path, stages: list[str], rate: int, raw_out: Path) -> dict:
    """Run ``stages`` again on a copy of ``converted`` under py-spy; the copy's stage timings."""
    work = Path(tempfile.mkdtemp(prefix="interpreter_profile_"))
    try:
        out = work / "out"
        shutil.copytree(converted, out)
        script = ("import sys; from phirie_jax.pipeline import run_convert; "
                  "run_convert(sys.argv[1], sys.argv[2], masks='auto', stages=tuple(sys.argv[3:]), "
                  "allow_outside_paths=True)")
        subprocess.run(["py-spy", "record", "--gil", "--threads", "--nonblocking", "--rate", str(rate),
                        "--format", "raw", "-o", str(raw_out), "--", sys.executable, "-c", script,
                        str(capture), str(out), *stages], check=True, stdout=subprocess.DEVNULL)
        timings = json.loads((out / "manifest.json").read_text())["timings"]
        return {k: round(v, 2) for k, v in timings.items() if k.split(".")[0] in stages}
    finally:
        shutil.rmtree(work, ignore_errors=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--capture", type=Path)
    parser.add_argument("--converted", type=Path)
    parser.add_argument("--stages", nargs="+", default=["objects"])
    parser.add_argument("--rate", type=int, default=50, help="samples per second")
    parser.add_argument("--raw", type=Path, default=None, help="summarize this recording instead")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if args.raw is not None:
        result = {"raw": str(args.raw), **summarize(parse_raw(args.raw.read_text()), args.rate)}
    else:
        if args.capture is None or args.converted is None:
            parser.error("--capture and --converted are needed to record (or give --raw)")
        if shutil.which("py-spy") is None:
            parser.error("recording needs py-spy on the PATH (pip install py-spy)")
        with tempfile.TemporaryDirectory(prefix="interpreter_profile_raw_") as folder:
            raw = Path(folder) / "samples.txt"
            timings = record(args.capture, args.converted, args.stages, args.rate, raw)
            result = {"stages": args.stages, "timings_s": timings,
                      **summarize(parse_raw(raw.read_text()), args.rate)}
    text = json.dumps(result, indent=1)
    if args.out:
        args.out.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
