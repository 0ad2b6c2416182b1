"""Benchmark of the JAX tile rasterizer; prints one JSON object.

Scenes:
  (default)      100K random Gaussians (SH degree 3) in front of a 640×480 camera.
  --scene garden  Mip-NeRF 360 "garden" COLMAP points (shared/data/garden/test_garden.npz)
                  as isotropic Gaussians: σ = mean distance to the 3 nearest neighbours,
                  opacity 0.8, SH DC from the point colours; its 3 real cameras (648×420).
  --tile-scene   (with --scene garden) 10 offset copies (≈1.4M Gaussians) rendered at
                  1920×1080 (K scaled by 1920/648, principal point re-centred).

Times: compile (``.lower().compile()``), forward, forward+backward with the custom VJP
and with plain autodiff (fixed-length scan); medians of ``--repeats`` runs after a
warm-up, ``block_until_ready``. When ``torch`` and ``gsplat`` import (a CUDA machine),
gsplat's ``rasterization`` is timed on the same Gaussians and cameras in the same run
and the ratios ours / gsplat are printed; otherwise the JSON says it was unavailable.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from experiments.report import emit
from kernels.composite import TileGrid  # noqa: E402
from kernels.composite_pallas import PallasSettings  # noqa: E402
from kernels.gaussians import Gaussians  # noqa: E402
from kernels.project import project_gaussians  # noqa: E402
from kernels.raster import RasterConfig, bin_gaussians, rasterize  # noqa: E402
from kernels.sh import rgb_to_sh_dc  # noqa: E402
from phirie_jax.render import next_power_of_two, quarter_octave, room_for  # noqa: E402

# the binning buffer for the busiest camera's intersections: the renderer's own rule first
CAPACITY_RULES = {"renderer": room_for, "power-of-two": next_power_of_two, "quarter-octave": quarter_octave}

GARDEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "garden" / "test_garden.npz"
GARDEN_OPACITY = 0.8
TILE_COPIES = 10


def random_scene(n=100_000, width=640, height=480, seed=0):
    rng = np.random.default_rng(seed)
    f = 0.8 * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], np.float32)
    z = rng.uniform(2.0, 10.0, n)
    xy = (rng.uniform(-0.6, 0.6, (n, 2)) * np.array([width, height]) / f) * z[:, None]
    g = Gaussians(
        means=jnp.asarray(np.concatenate([xy, z[:, None]], 1), jnp.float32),
        quats=jnp.asarray(rng.normal(size=(n, 4)), jnp.float32),
        log_scales=jnp.asarray(rng.normal(np.log(0.012), 0.5, (n, 3)), jnp.float32),
        opacity_logits=jnp.asarray(rng.normal(0.0, 1.5, n), jnp.float32),
        sh=jnp.asarray(rng.normal(0.0, 0.2, (n, 16, 3)), jnp.float32),
    )
    return g, K[None], np.eye(4, dtype=np.float32)[None], width, height


def garden_scene(tile_scene: bool, path: Path = GARDEN):
    from scipy.spatial import cKDTree

    data = np.load(path)
    pts = data["means3d"].astype(np.float64)
    dist, _ = cKDTree(pts).query(pts, k=4)  # itself + 3 neighbours
    sigma = np.maximum(dist[:, 1:].mean(axis=1), 1e-4)
    colours = data["colors"].astype(np.float64) / 255.0
    Ks, viewmats = data["Ks"].astype(np.float32), data["viewmats"].astype(np.float32)
    width, height = int(data["width"]), int(data["height"])
    if tile_scene:
        extent = np.percentile(pts, 95, axis=0) - np.percentile(pts, 5, axis=0)
        # Copies side by side along the two widest axes of the scene, half an extent apart,
        # so that most of them are in view and overlap in depth.
        a, b = np.argsort(extent)[::-1][:2]
        offsets = []
        for k in range(TILE_COPIES):
            o = np.zeros(3)
            o[a] = 0.5 * extent[a] * (k % 5 - 2)
            o[b] = 0.5 * extent[b] * (k // 5 - 0.5)
            offsets.append(o)
        pts = np.concatenate([pts + o for o in offsets])
        sigma = np.tile(sigma, TILE_COPIES)
        colours = np.tile(colours, (TILE_COPIES, 1))
        s = 1920 / width
        Ks = Ks.copy()
        Ks[:, :2] *= s
        Ks[:, 1, 2] -= (s * height - 1080) / 2
        width, height = 1920, 1080
    n = len(pts)
    logit = np.log(GARDEN_OPACITY / (1 - GARDEN_OPACITY))
    g = Gaussians(
        means=jnp.asarray(pts, jnp.float32),
        quats=jnp.asarray(np.tile([1.0, 0, 0, 0], (n, 1)), jnp.float32),
        log_scales=jnp.asarray(np.repeat(np.log(sigma)[:, None], 3, 1), jnp.float32),
        opacity_logits=jnp.full((n,), logit, jnp.float32),
        sh=jnp.asarray(rgb_to_sh_dc(colours)[:, None, :], jnp.float32),
    )
    return g, Ks, viewmats, width, height


def median_ms(fn, repeats):
    jax.block_until_ready(fn())  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(1e3 * (time.perf_counter() - t))
    return statistics.median(times)


def timed_compile(jitted, *args):
    t = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    return compiled, time.perf_counter() - t


def compiled_memory_mb(compiled) -> float | None:
    """Device memory one compiled program needs beyond its inputs: temporaries + outputs (MB)."""
    try:
        stats = compiled.memory_analysis()
        return round((stats.temp_size_in_bytes + stats.output_size_in_bytes) / 2**20, 1)
    except Exception:  # noqa: BLE001 (not every backend reports it)
        return None


def bench_jax(g, Ks, viewmats, width, height, base: RasterConfig, repeats, with_autodiff,
              capacity_rule=room_for):
    render = jax.jit(lambda g, K, W, cfg: rasterize(g, K, W, width=width, height=height,
                                                    config=cfg), static_argnums=3)
    # Fit the capacities on every camera first (the host wrapper's job, done by hand here).
    needed = longest = 0
    for K, W in zip(Ks, viewmats):
        out = render(g, K, W, dataclasses.replace(base, capacity=next_power_of_two(8 * g.num)))
        if bool(out.overflow):
            out = render(g, K, W, dataclasses.replace(
                base, capacity=next_power_of_two(int(out.num_intersections))))
        needed = max(needed, int(out.num_intersections))
        longest = max(longest, int(out.max_tile_intersections))
    config = dataclasses.replace(base, capacity=capacity_rule(needed))
    weights = jax.random.uniform(jax.random.key(0), (height, width, 3))

    def loss(g, K, W, cfg):
        out = rasterize(g, K, W, width=width, height=height, config=cfg)
        return jnp.sum(out.rgb * weights) + jnp.sum(out.depth)

    grad = jax.jit(jax.grad(loss), static_argnums=3)
    fwd_c, fwd_compile = timed_compile(jax.jit(partial_render(width, height, config)), g,
                                       Ks[0], viewmats[0])
    grad_c, grad_compile = timed_compile(jax.jit(lambda g, K, W: grad(g, K, W, config)), g,
                                         Ks[0], viewmats[0])
    compositor = config.resolved_compositor()
    result = {
        "compositor": compositor,
        "capacity": config.capacity, "num_intersections_max": needed,
        "longest_tile_list": longest,
        "compile_s": {"forward": round(fwd_compile, 2), "grad_custom_vjp": round(grad_compile, 2)},
        "memory_mb": {"forward": compiled_memory_mb(fwd_c), "grad": compiled_memory_mb(grad_c)},
        "forward_ms": [], "fwd_bwd_custom_vjp_ms": [],
    }
    if compositor == "pallas":
        result["pallas"] = dataclasses.asdict(config.pallas)
    else:
        result.update(slots=config.resolved_slots(
            -(-width // config.tile_size) * -(-height // config.tile_size)),
            chunk=config.chunk, sequential_forward=config.resolved_sequential())
    result["loop_steps"] = [int(fwd_c(g, K, W).steps) for K, W in zip(Ks, viewmats)]
    for K, W in zip(Ks, viewmats):
        result["forward_ms"].append(round(median_ms(lambda: fwd_c(g, K, W), repeats), 3))
        result["fwd_bwd_custom_vjp_ms"].append(
            round(median_ms(lambda: grad_c(g, K, W), repeats), 3))
    # Where the forward time goes (first camera): projection, + binning, + compositing.
    grid = TileGrid(width, height, config.tile_size)
    project = jax.jit(lambda g, K, W: project_gaussians(g, K, W, width=width, height=height))
    binned = jax.jit(lambda g, K, W: bin_gaussians(
        project_gaussians(g, K, W, width=width, height=height), grid, config.capacity))
    result["forward_stages_ms"] = {
        "project": round(median_ms(lambda: project(g, Ks[0], viewmats[0]), repeats), 3),
        "project_and_bin": round(median_ms(lambda: binned(g, Ks[0], viewmats[0]), repeats), 3),
        "all": result["forward_ms"][0],
    }
    if with_autodiff:
        auto = dataclasses.replace(config, backward="autodiff", compositor="jax",
                                   tile_capacity=next_power_of_two(longest + 1))
        auto_c, auto_compile = timed_compile(jax.jit(lambda g, K, W: grad(g, K, W, auto)), g,
                                             Ks[0], viewmats[0])
        result["compile_s"]["grad_autodiff"] = round(auto_compile, 2)
        result["fwd_bwd_autodiff_ms"] = [
            round(median_ms(lambda: auto_c(g, K, W), repeats), 2) for K, W in zip(Ks, viewmats)]
        # The two gradients agree (a sanity check that we timed the same thing).
        a, b = grad_c(g, Ks[0], viewmats[0]), auto_c(g, Ks[0], viewmats[0])
        result["grad_max_rel_diff_custom_vs_autodiff"] = float(max(
            jnp.max(jnp.abs(x - y)) / (jnp.max(jnp.abs(y)) + 1e-30)
            for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b))))
    return result, (fwd_c, grad_c)


def agreement(g, Ks, viewmats, programs_a, programs_b) -> dict:
    """Largest differences between two renderers' images and gradients (first camera); the
    gradients per Gaussian field, relative to that field's largest entry (a field whose
    gradient is zero up to rounding, e.g. the quaternions of isotropic Gaussians, compares
    rounding noise) and to the largest entry of every field."""
    (fwd_a, grad_a), (fwd_b, grad_b) = programs_a, programs_b
    out_a, out_b = fwd_a(g, Ks[0], viewmats[0]), fwd_b(g, Ks[0], viewmats[0])
    ga, gb = grad_a(g, Ks[0], viewmats[0]), grad_b(g, Ks[0], viewmats[0])
    fields = [f.name for f in dataclasses.fields(ga)]
    diff = {f: float(jnp.max(jnp.abs(getattr(ga, f) - getattr(gb, f)))) for f in fields}
    scale = {f: float(jnp.max(jnp.abs(getattr(gb, f)))) for f in fields}
    return {
        "rgb_max_abs_diff": float(jnp.max(jnp.abs(out_a.rgb - out_b.rgb))),
        "alpha_max_abs_diff": float(jnp.max(jnp.abs(out_a.alpha - out_b.alpha))),
        "grad_max_abs_diff": diff, "grad_max_abs": scale,
        "grad_max_rel_diff_overall": max(diff.values()) / (max(scale.values()) + 1e-30),
    }


def partial_render(width, height, config):
    return lambda g, K, W: rasterize(g, K, W, width=width, height=height, config=config)


def load_prebuilt_gsplat(path: Path) -> None:
    """Use a gsplat CUDA extension built earlier (``gsplat_cuda.so`` from its JIT build folder)
    instead of compiling it at import: gsplat imports ``gsplat.csrc`` first."""
    import importlib.util
    import sys

    import torch  # noqa: F401 (the extension links against torch's libraries)

    spec = importlib.util.spec_from_file_location("gsplat_cuda", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sys.modules["gsplat.csrc"] = module


def ratio_over_gsplat(ours: dict, gs: dict) -> dict:
    """Ours over gsplat, forward and forward+backward: the median of our per-camera times over the
    median of gsplat's (``bench_jax``'s and ``bench_gsplat``'s results)."""
    return {"forward": round(statistics.median(ours["forward_ms"]) / statistics.median(gs["forward_ms"]), 3),
            "fwd_bwd": round(statistics.median(ours["fwd_bwd_custom_vjp_ms"]) / statistics.median(gs["fwd_bwd_ms"]), 3)}


def bench_gsplat(g, Ks, viewmats, width, height, repeats):
    try:
        t0 = time.perf_counter()
        import torch
        from gsplat import rasterization
        import_s = time.perf_counter() - t0  # includes gsplat's JIT build of its CUDA code if any
    except Exception as exc:  # noqa: BLE001 (any import failure means: not available here)
        return {"available": False, "reason": f"{type(exc).__name__}: {exc}"}
    if not torch.cuda.is_available():
        return {"available": False, "reason": "torch has no CUDA device"}
    dev = torch.device("cuda")
    t = lambda x: torch.tensor(np.asarray(x), device=dev)  # noqa: E731
    params = {
        "means": t(g.means), "quats": t(g.quats), "scales": t(np.exp(np.asarray(g.log_scales))),
        "opacities": t(1 / (1 + np.exp(-np.asarray(g.opacity_logits)))), "colors": t(g.sh),
    }
    for p in params.values():
        p.requires_grad_(True)
    degree = int(round(np.sqrt(g.sh.shape[1]))) - 1
    weights = torch.rand((height, width, 3), device=dev)

    cameras = [(t(K)[None], t(W)[None]) for K, W in zip(Ks, viewmats)]  # on the GPU before timing

    def run(K, W, backward):
        img, _, _ = rasterization(
            params["means"], params["quats"], params["scales"], params["opacities"],
            params["colors"], W, K, width, height, sh_degree=degree,
            near_plane=0.01, eps2d=0.3, render_mode="RGB+D", packed=False)
        if backward:
            ((img[0, ..., :3] * weights).sum() + img[0, ..., 3].sum()).backward()

    def median(fn):
        fn()
        torch.cuda.synchronize()
        times = []
        for _ in range(repeats):
            torch.cuda.synchronize()
            s = time.perf_counter()
            fn()
            torch.cuda.synchronize()
            times.append(1e3 * (time.perf_counter() - s))
        return statistics.median(times)

    def peak_mb(fn):
        """Peak memory allocated by ``fn`` beyond what was allocated before (MB)."""
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        before = torch.cuda.memory_allocated()
        fn()
        torch.cuda.synchronize()
        return round((torch.cuda.max_memory_allocated() - before) / 2**20, 1)

    fwd, both = [], []
    for K, W in cameras:
        with torch.no_grad():
            fwd.append(round(median(lambda: run(K, W, False)), 3))
        both.append(round(median(lambda: run(K, W, True)), 3))
    K, W = cameras[0]
    with torch.no_grad():
        memory = {"forward": peak_mb(lambda: run(K, W, False))}
    memory["grad"] = peak_mb(lambda: run(K, W, True))
    import gsplat

    return {"available": True, "version": gsplat.__version__, "import_s": round(import_s, 1),
            "torch": torch.__version__, "forward_ms": fwd, "fwd_bwd_ms": both,
            "memory_mb": memory}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", choices=["random", "garden"], default="random")
    parser.add_argument("--tile-scene", action="store_true")
    parser.add_argument("--garden", type=Path, default=GARDEN, help="test_garden.npz")
    parser.add_argument("--gaussians", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--compositor", choices=["auto", "pallas", "jax"], default="auto",
                        help="RasterConfig.compositor (auto: Pallas on a GPU)")
    parser.add_argument("--compare-jax", action="store_true",
                        help="also time the pure-JAX compositor and compare images and gradients")
    parser.add_argument("--pallas-chunk", type=int, default=PallasSettings.chunk)
    parser.add_argument("--pallas-warps", type=int, default=PallasSettings.num_warps)
    parser.add_argument("--pallas-backward-chunk", type=int, default=PallasSettings.backward_chunk)
    parser.add_argument("--pallas-backward-warps", type=int,
                        default=PallasSettings.backward_num_warps)
    parser.add_argument("--pallas-prefetch", type=int, choices=[0, 1],
                        default=int(PallasSettings.prefetch))
    parser.add_argument("--slots", type=int, default=None)
    parser.add_argument("--chunk", type=int, default=32, help="the JAX compositor's chunk")
    parser.add_argument("--no-autodiff", action="store_true")
    parser.add_argument("--no-gsplat", action="store_true")
    parser.add_argument("--gsplat-extension", type=Path, default=None,
                        help="a prebuilt gsplat_cuda.so (skips gsplat's JIT build)")
    parser.add_argument("--sequential", action="store_true",
                        help="fused sequential chunk forward (RasterConfig.sequential)")
    parser.add_argument("--capacity-rule", choices=list(CAPACITY_RULES), default="renderer",
                        help="the buffer for the busiest camera's intersections: the renderer's (an eighth to spare, "
                             "a quarter octave: phirie_jax.render.room_for), the next power of two, or the next "
                             "2^k x (1, 1.25, 1.5, 1.75) (phirie_jax.render.quarter_octave)")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args()

    if args.scene == "garden":
        g, Ks, viewmats, width, height = garden_scene(args.tile_scene, args.garden)
    else:
        g, Ks, viewmats, width, height = random_scene(args.gaussians)
    base = RasterConfig(chunk=args.chunk, slots=args.slots, sequential=args.sequential,
                        compositor=args.compositor,
                        pallas=PallasSettings(chunk=args.pallas_chunk,
                                              backward_chunk=args.pallas_backward_chunk,
                                              num_warps=args.pallas_warps,
                                              backward_num_warps=args.pallas_backward_warps,
                                              prefetch=bool(args.pallas_prefetch)))
    result = {
        "scene": args.scene + ("-tiled" if args.tile_scene else ""),
        "backend": jax.default_backend(), "device": str(jax.devices()[0]),
        "jax": jax.__version__, "num_gaussians": g.num, "width": width, "height": height,
        "cameras": len(Ks), "sh_degree": g.sh_degree,
    }
    ours, programs = bench_jax(g, Ks, viewmats, width, height, base, args.repeats,
                               not args.no_autodiff, CAPACITY_RULES[args.capacity_rule])
    result["ours"] = ours
    ours["capacity_rule"] = args.capacity_rule
    ours["gaussians_per_s_forward"] = round(g.num / (statistics.median(ours["forward_ms"]) / 1e3))
    if args.compare_jax and ours["compositor"] != "jax":
        reference, ref_programs = bench_jax(g, Ks, viewmats, width, height,
                                            dataclasses.replace(base, compositor="jax"),
                                            args.repeats, False)
        result["ours_jax_compositor"] = reference
        result["pallas_vs_jax_compositor"] = agreement(g, Ks, viewmats, programs, ref_programs)
        result["ratio_pallas_over_jax_compositor"] = {
            "forward": round(statistics.median(ours["forward_ms"])
                             / statistics.median(reference["forward_ms"]), 3),
            "fwd_bwd": round(statistics.median(ours["fwd_bwd_custom_vjp_ms"])
                             / statistics.median(reference["fwd_bwd_custom_vjp_ms"]), 3),
        }
    if args.no_gsplat:
        gs = {"available": False, "reason": "--no-gsplat"}
    else:
        if args.gsplat_extension is not None:
            load_prebuilt_gsplat(args.gsplat_extension)
        gs = bench_gsplat(g, Ks, viewmats, width, height, args.repeats)
    result["gsplat"] = gs
    if gs.get("available"):
        result["ratio_ours_over_gsplat"] = ratio_over_gsplat(ours, gs)
    emit(result, args.out)


if __name__ == "__main__":
    main()
