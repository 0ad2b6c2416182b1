"""How ``phirie capture``'s structure from motion does on the real captures (CPU only).

    python -m experiments.capture_sfm [--captures snowmiku fox] [--out experiments/results/capture_sfm.json]

For each capture in ``../shared/data/captures/NAME/images``: the pictures (``capture.frames``) and
the SfM (``capture.sfm``) with ``SfmConfig()``'s settings, and with COLMAP's own defaults for
comparison (``--colmap-defaults``). Reports pictures registered, mean reprojection error, points,
the seconds of each step and the process's CPU seconds (the wall time depends on the cores).
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import tempfile
import time
from pathlib import Path

CAPTURES = Path(__file__).resolve().parents[2] / "shared" / "data" / "captures"



def _cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run(name: str, config, work: Path) -> dict:
    from phirie_jax.capture.config import FramesConfig
    from phirie_jax.capture.frames import prepare_frames
    from phirie_jax.capture.sfm import run_sfm
    from phirie_jax.errors import SceneInputError

    t0, c0 = time.perf_counter(), _cpu_s()
    frames = prepare_frames(CAPTURES / name / "images", FramesConfig(), work / "frames")
    try:
        record = run_sfm(frames, config, work / "sfm").record
    except SceneInputError as err:  # too few registered: the error is the result
        record = {"error": str(err)}
    record.pop("config", None)
    return {"capture": name, "wall_s": round(time.perf_counter() - t0, 1), "cpu_s": round(_cpu_s() - c0, 1),
            **record}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--captures", nargs="+", default=["snowmiku", "fox"])
    parser.add_argument("--colmap-defaults", action="store_true", help="also run with COLMAP's defaults")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    import os

    from experiments.report import emit
    from phirie_jax.capture.config import COLMAP_DEFAULTS, SfmConfig

    settings = {"phirie": SfmConfig()}
    if args.colmap_defaults:
        settings["colmap_defaults"] = dataclasses.replace(SfmConfig(), **COLMAP_DEFAULTS)
    runs = []
    for name in args.captures:
        for label, config in settings.items():
            with tempfile.TemporaryDirectory() as work:
                result = {"settings": label, **run(name, config, Path(work))}
            print(f"capture_sfm: {result}", flush=True)
            runs.append(result)
    result = {"cpus": os.cpu_count(), "sfm_config": dataclasses.asdict(SfmConfig()), "runs": runs}
    emit(result, args.out)
    return result


if __name__ == "__main__":
    main()
