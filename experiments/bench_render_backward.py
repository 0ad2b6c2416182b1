"""The Pallas compositor's backward settings at 1080p against gsplat, in one process; prints
one JSON object.

    python -m experiments.bench_render_backward [--garden NPZ] [--repeats 7]
        [--gsplat-extension gsplat_cuda.so] [--settings 4x16,8x16,...] [--out JSON]

The scene and timings are ``experiments.bench_render``'s ``--scene garden --tile-scene
--no-autodiff`` (≈1.4M Gaussians, 1920×1080, 3 cameras, the renderer's capacity rule), run
for each backward setting ``WARPSxCHUNK`` (``PallasSettings.backward_num_warps`` and
``backward_chunk``, an ``e`` suffix for entries-major backward blocks; the forward keeps its
defaults), each followed by gsplat on the same Gaussians and cameras: every setting has its
own same-run ratio. The first setting is timed again last, to show the drift over the run.
The device time per kernel of the forward+backward program (camera 0, 20 calls) is traced
for the first setting and the fastest.
"""

from __future__ import annotations

import argparse
import re
import statistics
import sys
from pathlib import Path

import jax

from experiments.bench_render import (
    GARDEN,
    bench_gsplat,
    bench_jax,
    garden_scene,
    load_prebuilt_gsplat,
    ratio_over_gsplat,
)
from experiments.profiling import traced
from experiments.report import emit
from kernels.composite_pallas import PallasSettings
from kernels.raster import RasterConfig

DEFAULT_SETTINGS = "4x16,2x16,8x16,16x16,4x8,8x8,4x32,8x32,16x32,8x16e"
TRACE_CALLS = 20


SETTING = re.compile(r"(\d+)x(\d+)(e?)")


def parse_setting(text: str) -> PallasSettings:
    """'WARPSxCHUNK' (an 'e' suffix: entries-major backward blocks) → the settings."""
    match = SETTING.fullmatch(text)
    if match is None:
        raise SystemExit(f"bench_render_backward: --settings: {text!r} (expected WARPSxCHUNK, e.g. 4x16 or 8x16e)")
    warps, chunk, entries_major = match.groups()
    return PallasSettings(backward_num_warps=int(warps), backward_chunk=int(chunk),
                          backward_entries_major=bool(entries_major))


def traced_kernels(grad_program, g, K: jax.Array, W: jax.Array) -> dict:
    """Device time per kernel of ``TRACE_CALLS`` calls of the forward+backward program (g the
    Gaussians, K (3, 3) and W (4, 4) one camera), after one untraced call."""
    jax.block_until_ready(grad_program(g, K, W))
    return traced(lambda: jax.block_until_ready(grad_program(g, K, W)), TRACE_CALLS, top=15)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--garden", type=Path, default=GARDEN, help="test_garden.npz")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--settings", default=DEFAULT_SETTINGS,
                        help="comma-separated backward settings WARPSxCHUNK[e]")
    parser.add_argument("--gsplat-extension", type=Path, default=None,
                        help="a prebuilt gsplat_cuda.so (skips gsplat's JIT build)")
    parser.add_argument("--no-trace", action="store_true")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args()
    settings = [parse_setting(name) for name in args.settings.split(",")]
    if jax.default_backend() != "gpu":
        raise SystemExit("bench_render_backward: the Pallas compositor's settings are timed on a GPU "
                         f"(this JAX's backend: {jax.default_backend()})")

    g, Ks, viewmats, width, height = garden_scene(True, args.garden)
    if args.gsplat_extension is not None:
        load_prebuilt_gsplat(args.gsplat_extension)
    names = args.settings.split(",")
    names.append(names[0])  # the first again, last: the drift over the run
    settings.append(settings[0])
    result = {"device": str(jax.devices()[0]), "jax": jax.__version__, "num_gaussians": g.num,
              "width": width, "height": height, "cameras": len(Ks), "repeats": args.repeats,
              "runs": []}
    programs = {}
    for name, pallas in zip(names, settings):
        config = RasterConfig(compositor="pallas", pallas=pallas)
        ours, (_, grad_c) = bench_jax(g, Ks, viewmats, width, height, config, args.repeats, False)
        programs[name] = grad_c
        gs = bench_gsplat(g, Ks, viewmats, width, height, args.repeats)
        run = {"setting": name, "pallas": ours.get("pallas"), "capacity": ours["capacity"],
               "compile_s": ours["compile_s"], "ours_forward_ms": ours["forward_ms"],
               "ours_fwd_bwd_ms": ours["fwd_bwd_custom_vjp_ms"],
               "ours_forward_stages_ms": ours["forward_stages_ms"]}
        if gs.get("available"):
            run.update(gsplat_forward_ms=gs["forward_ms"], gsplat_fwd_bwd_ms=gs["fwd_bwd_ms"],
                       ratio_ours_over_gsplat=ratio_over_gsplat(ours, gs))
            result["gsplat"] = {k: gs[k] for k in ("version", "torch")}
        else:
            result["gsplat"] = gs
        result["runs"].append(run)
        print(f"bench_render_backward: {name} {run}", file=sys.stderr, flush=True)
    best = min(result["runs"], key=lambda r: statistics.median(r["ours_fwd_bwd_ms"]))
    result["fastest_fwd_bwd"] = best["setting"]
    if not args.no_trace:
        result["fwd_bwd_kernels"] = {name: traced_kernels(programs[name], g, Ks[0], viewmats[0])
                                     for name in dict.fromkeys([names[0], best["setting"]])}
    emit(result, args.out)


if __name__ == "__main__":
    main()
