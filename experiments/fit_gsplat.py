"""Fitted benchmark scenes made the way users' trainers make them: gsplat 1.5.3, initialised from
sparse SfM-like points, densified by its ``DefaultStrategy`` (or ``MCMCStrategy``), on a GPU.

    # here (CPU): synthesize each scene, give it SfM-like points (sparse/0/points3D.txt) and copy
    # what a trainer reads (images, cameras, points) to a small folder that travels to the GPU host
    python -m experiments.fit_gsplat prepare --preset default --seeds 2001 2002 2003 \
        --root /tmp/gsplat_scenes --carry gsplat_inputs
    # on the GPU host (torch + CUDA; the gsplat 1.5.3 wheel is pure Python and compiles its CUDA
    # on first use): one .npz per (scene, trainer) and the runs' JSON
    python -m experiments.fit_gsplat fit gsplat_inputs/default2001 ... --strategy default \
        --steps 10000 --seed 0 --out OUT [--own-fit]
    # here: each fit becomes the capture of a copy of its scene folder (gt/ kept, gt/fit.json)
    python -m experiments.fit_gsplat install OUT/*.npz --root /tmp/gsplat_scenes

``prepare`` writes a ``phirie synth`` folder (``--root/<preset><seed>``) whose COLMAP points are
what structure from motion would give: points on the scene's surface that at least
``MIN_TRACK`` cameras see (a ray from the camera meets the surface there), ``--sfm-points`` of
them picked at random, each moved by isotropic noise of ``--sfm-noise`` metres, plus
``--sfm-outliers`` of them replaced by mismatches anywhere in the seen surface's box; colour =
the mean of the pixels it projects to in the views that see it.

``fit`` trains gsplat's ``rasterization`` as its ``examples/simple_trainer.py`` does: the SfM
points as the initial means (scale = mean distance to the 3 nearest, opacity 0.1, random
quaternions), Adam with simple_trainer's learning rates (means 1.6e-4 × scene scale, decaying
100× over the run), one image a step in a seeded order, loss 0.8·L1 + 0.2·(1 − SSIM), an SH band
every 1000 steps up to degree 3, black background, the strategy's densification with its
defaults (``mcmc``: opacity and scale regularisation 0.01, initial opacity 0.5 and scale 0.1, as
simple_trainer's mcmc config; ``--cap-max`` Gaussians). Gaussians with opacity below 0.005 are
dropped at export. ``--own-fit`` also fits each scene with the project's fitter
(``FIT_PRESETS``), the baseline, in the same run. Each fit is exported as
``<scene>_gsplat_<strategy>.npz`` (``<scene>_fitted.npz``): ``experiments.fit_scenes``' arrays,
SH stored as float16 so a few hundred thousand Gaussians fit the 16 MB a file the GPU host hands
back. Prints one JSON object per fit (compile = the first step, gsplat's CUDA JIT included;
run = the other steps), then the list.

``install`` copies ``--root/<scene>`` to ``--root/<scene>_gsplat_<strategy>`` (or ``_fitted``) and
makes the fit its capture (``install_fit``: the ideal set moves to gt/ideal/, gt/labels.npy labels
the fitted Gaussians by the nearest ideal one, gt/fit.json records the fit).

gsplat's CUDA kernels add with atomics, so a rerun with the same seed gives nearly, not exactly,
the same Gaussians.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np

MIN_TRACK = 3          # cameras that must see a surface point for SfM to have triangulated it
SURFACE_SPACING = 0.004  # m between the surface samples the SfM points are drawn from
VISIBLE_TOL = 0.004    # m: a camera sees a sample when its ray meets the surface this close to it
SSIM_WINDOW, SSIM_SIGMA = 11, 1.5
STRATEGIES = ("default", "mcmc")
CARRIED = ("images", "sparse", "transforms.json", "gt/sfm.json")  # what a trainer reads


# --- here: the scene and its SfM-like points -------------------------------------------------


def sfm_points(scene_dir: Path, count: int, noise: float, outliers: float, seed: int
               ) -> tuple[np.ndarray, np.ndarray, dict]:
    """(P, 3) SfM-like points of a synthesized folder, (P, 3) uint8 colours, and a record."""
    import cv2
    import trimesh

    from phirie_jax.io.scene import load_scene
    from phirie_jax.observe.raycast import Raycaster

    rng = np.random.default_rng(seed)
    cameras = list(load_scene(scene_dir, check_images=False).require_cameras())
    surface = trimesh.load(scene_dir / "surface.ply", force="mesh", process=False)
    caster = Raycaster(surface.vertices, surface.faces)
    samples, _ = trimesh.sample.sample_surface(surface, int(surface.area / SURFACE_SPACING**2), seed=seed)
    views = np.zeros(len(samples), np.int64)
    colour = np.zeros((len(samples), 3))
    for cam in cameras:
        uv, depth = cam.project(samples)
        inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        idx = np.flatnonzero(inside)
        rays = samples[idx] - cam.center
        length = np.linalg.norm(rays, axis=1)
        hits = caster.cast(np.broadcast_to(cam.center, rays.shape), rays)
        seen = idx[np.abs(hits.depth - 1.0) * length < VISIBLE_TOL]
        image = cv2.imread(str(cam.image_path), cv2.IMREAD_COLOR)[..., ::-1]
        px = np.floor(uv[seen]).astype(np.int64)
        colour[seen] += image[px[:, 1], px[:, 0]]
        views[seen] += 1
    tracked = np.flatnonzero(views >= MIN_TRACK)
    pick = rng.choice(tracked, size=min(count, len(tracked)), replace=False)
    points = samples[pick] + noise * rng.normal(size=(len(pick), 3))
    rgb = colour[pick] / views[pick, None]
    wrong = rng.random(len(pick)) < outliers
    centres = np.array([c.center for c in cameras])
    lo, hi = np.percentile(samples[tracked], 1, axis=0), np.percentile(samples[tracked], 99, axis=0)
    points[wrong] = rng.uniform(lo, hi, size=(int(wrong.sum()), 3))
    rgb[wrong] = rng.uniform(0, 255, size=(int(wrong.sum()), 3))
    record = {"points": len(pick), "tracked_surface_samples": len(tracked), "noise_m": noise,
              "outliers": int(wrong.sum()), "min_track": MIN_TRACK, "seed": seed,
              "camera_box": [centres.min(0).round(3).tolist(), centres.max(0).round(3).tolist()]}
    return points, np.clip(np.round(rgb), 0, 255).astype(np.uint8), record


def prepare(args) -> None:
    from phirie_jax.io.atomic import write_text
    from phirie_jax.io.colmap import write_colmap_text
    from phirie_jax.io.scene import load_scene
    from phirie_jax.synthetic.fitted import ensure_synthesized

    for seed in args.seeds:
        folder = ensure_synthesized(args.root / f"{args.preset}{seed}", args.preset, seed)
        points, colours, record = sfm_points(folder, args.sfm_points, args.sfm_noise, args.sfm_outliers, seed)
        cameras = list(load_scene(folder, check_images=False).require_cameras())
        write_colmap_text(folder / "sparse" / "0", cameras, points=points, colors=colours)
        write_text(folder / "gt" / "sfm.json", json.dumps({**record, "preset": args.preset, "seed": seed}, indent=2))
        if args.carry is not None:
            carried = args.carry / folder.name
            if carried.exists():
                shutil.rmtree(carried)
            for part in CARRIED:
                (carried / part).parent.mkdir(parents=True, exist_ok=True)
                if (folder / part).is_dir():
                    shutil.copytree(folder / part, carried / part)
                else:
                    shutil.copy2(folder / part, carried / part)
        print(json.dumps({"scene": str(folder), **record}), flush=True)


# --- the GPU host: gsplat training -------------------------------------------------------------


def read_points3d(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP points3D.txt → (P, 3) positions, (P, 3) colours in [0, 1]."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    data = np.array([[float(v) for v in r[1:7]] for r in rows]).reshape(-1, 6)
    return data[:, :3], data[:, 3:6] / 255.0


def _ssim(a, b):
    """Mean SSIM of two (1, 3, H, W) images (Gaussian window, valid region)."""
    import torch
    import torch.nn.functional as F

    x = torch.arange(SSIM_WINDOW, dtype=a.dtype, device=a.device) - SSIM_WINDOW // 2
    g = torch.exp(-x**2 / (2 * SSIM_SIGMA**2))
    g = g / g.sum()
    window = (g[:, None] @ g[None, :]).expand(3, 1, SSIM_WINDOW, SSIM_WINDOW).contiguous()

    def blur(t):
        return F.conv2d(t, window, groups=3)

    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    return (((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))).mean()


def _knn_scale(points):
    """(N,) mean distance to the 3 nearest other points (simple_trainer's initial scale)."""
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(points).query(points, k=4)
    return np.maximum(dist[:, 1:].mean(axis=1), 1e-7)


def train_gsplat(scene_dir: Path, strategy_name: str, steps: int, seed: int, cap_max: int, sh_degree: int = 3,
                 sh_interval: int = 1000):
    """gsplat fit of a prepared folder (module docstring) → (GaussianSplatData, record)."""
    import cv2
    import gsplat
    import torch
    import torch.nn.functional as F
    from gsplat import DefaultStrategy, MCMCStrategy, rasterization

    from phirie_jax.io.scene import load_scene
    from phirie_jax.types import GaussianSplatData

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    device = "cuda"
    cameras = list(load_scene(scene_dir, check_images=False).require_cameras())
    images = [cv2.imread(str(c.image_path), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255.0 for c in cameras]
    width, height = cameras[0].width, cameras[0].height
    pixels = torch.tensor(np.stack(images), device=device)                                   # [V, H, W, 3]
    viewmats = torch.tensor(np.stack([c.world_to_camera for c in cameras]), dtype=torch.float32, device=device)
    Ks = torch.tensor(np.stack([c.K for c in cameras]), dtype=torch.float32, device=device)
    centres = np.array([c.center for c in cameras])
    scene_scale = 1.1 * float(np.max(np.linalg.norm(centres - centres.mean(0), axis=1)))

    points, rgb = read_points3d(scene_dir / "sparse" / "0" / "points3D.txt")
    mcmc = strategy_name == "mcmc"
    init_opacity, init_scale = (0.5, 0.1) if mcmc else (0.1, 1.0)
    n = len(points)
    k = (sh_degree + 1) ** 2
    sh = torch.zeros((n, k, 3))
    sh[:, 0] = (torch.tensor(rgb, dtype=torch.float32) - 0.5) / 0.28209479177387814
    params = torch.nn.ParameterDict({
        "means": torch.nn.Parameter(torch.tensor(points, dtype=torch.float32)),
        "scales": torch.nn.Parameter(torch.log(torch.tensor(_knn_scale(points) * init_scale, dtype=torch.float32))
                                     [:, None].repeat(1, 3)),
        "quats": torch.nn.Parameter(torch.rand((n, 4))),
        "opacities": torch.nn.Parameter(torch.logit(torch.full((n,), init_opacity))),
        "sh0": torch.nn.Parameter(sh[:, :1].clone()),
        "shN": torch.nn.Parameter(sh[:, 1:].clone()),
    }).to(device)
    rates = {"means": 1.6e-4 * scene_scale, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh0": 2.5e-3,
             "shN": 2.5e-3 / 20}
    optimizers = {name: torch.optim.Adam([{"params": params[name], "lr": lr, "name": name}], eps=1e-15)
                  for name, lr in rates.items()}
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizers["means"], gamma=0.01 ** (1.0 / steps))
    strategy = MCMCStrategy(cap_max=cap_max) if mcmc else DefaultStrategy()
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state() if mcmc else strategy.initialize_state(scene_scale=scene_scale)

    order: list[int] = []
    first_step_s, t0 = None, time.perf_counter()
    losses = []
    for step in range(steps):
        if not order:
            order = list(rng.permutation(len(cameras)))
        view = order.pop()
        t_step = time.perf_counter()
        colors, _, info = rasterization(
            means=params["means"], quats=params["quats"], scales=torch.exp(params["scales"]),
            opacities=torch.sigmoid(params["opacities"]), colors=torch.cat([params["sh0"], params["shN"]], 1),
            viewmats=viewmats[view:view + 1], Ks=Ks[view:view + 1], width=width, height=height,
            sh_degree=min(step // sh_interval, sh_degree), packed=False)
        strategy.step_pre_backward(params, optimizers, state, step, info)
        target = pixels[view:view + 1]
        loss = 0.8 * F.l1_loss(colors, target) + 0.2 * (1.0 - _ssim(colors.permute(0, 3, 1, 2),
                                                                     target.permute(0, 3, 1, 2)))
        if mcmc:
            loss = loss + 0.01 * torch.sigmoid(params["opacities"]).mean() + 0.01 * torch.exp(params["scales"]).mean()
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        scheduler.step()
        if mcmc:
            strategy.step_post_backward(params, optimizers, state, step, info, lr=scheduler.get_last_lr()[0])
        else:
            strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
        if step == 0:
            torch.cuda.synchronize()
            first_step_s = time.perf_counter() - t_step
        if step % 500 == 0 or step == steps - 1:
            losses.append((step, float(loss.detach())))
    torch.cuda.synchronize()
    wall = time.perf_counter() - t0

    with torch.no_grad():
        psnr = []
        for view in range(len(cameras)):
            colors, _, _ = rasterization(
                means=params["means"], quats=params["quats"], scales=torch.exp(params["scales"]),
                opacities=torch.sigmoid(params["opacities"]), colors=torch.cat([params["sh0"], params["shN"]], 1),
                viewmats=viewmats[view:view + 1], Ks=Ks[view:view + 1], width=width, height=height,
                sh_degree=sh_degree, packed=False)
            mse = F.mse_loss(colors.clamp(0, 1), pixels[view:view + 1])
            psnr.append(float(10 * torch.log10(1 / mse)))
        keep = torch.sigmoid(params["opacities"]) >= 0.005
        quats = F.normalize(params["quats"][keep], dim=-1)
        data = GaussianSplatData(
            means=params["means"][keep].cpu().numpy().astype(np.float32), quats=quats.cpu().numpy().astype(np.float32),
            log_scales=params["scales"][keep].cpu().numpy().astype(np.float32),
            opacity_logits=params["opacities"][keep].cpu().numpy().astype(np.float32),
            sh=torch.cat([params["sh0"], params["shN"]], 1)[keep].cpu().numpy().astype(np.float32))
    record = {"trainer": f"gsplat {gsplat.__version__}", "torch": torch.__version__, "strategy": strategy_name,
              "steps": steps, "seed": seed, "initial_gaussians": n, "gaussians": data.num,
              "train_psnr": round(float(np.mean(psnr)), 3), "train_psnr_per_view": np.round(psnr, 3).tolist(),
              "losses": losses, "scene_scale": scene_scale, "cap_max": cap_max if mcmc else None,
              "device": torch.cuda.get_device_name(), "backend": "cuda",
              "compile_s": round(first_step_s or 0.0, 3), "run_s": round(wall - (first_step_s or 0.0), 3),
              "wall_s": round(wall, 3), "steps_per_s": round((steps - 1) / max(wall - (first_step_s or 0.0), 1e-9), 2)}
    return data, record


def export(path: Path, data, record: dict) -> None:
    """A fit as ``experiments.fit_scenes``' .npz, its SH as float16 (module docstring)."""
    import io

    from phirie_jax.io.atomic import write_bytes

    buf = io.BytesIO()
    np.savez_compressed(buf, record=np.array(json.dumps(record)), means=data.means, quats=data.quats,
                        log_scales=data.log_scales, opacity_logits=data.opacity_logits, sh=data.sh.astype(np.float16))
    write_bytes(path, buf.getvalue())


def fit(args) -> None:
    import os

    # torch and (with --own-fit) JAX share the GPU: JAX must not take 75 % of it when it starts
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    from experiments.report import emit

    args.out.mkdir(parents=True, exist_ok=True)
    runs = []
    for scene in args.scenes:
        sfm = json.loads((scene / "gt" / "sfm.json").read_text())
        data, record = train_gsplat(scene, args.strategy, args.steps, args.seed, args.cap_max)
        record = {**record, "sfm": sfm, "scene": scene.name}
        export(args.out / f"{scene.name}_gsplat_{args.strategy}.npz", data, record)
        runs.append({k: v for k, v in record.items() if k not in ("train_psnr_per_view", "sfm")})
        print(json.dumps(runs[-1]), flush=True)
        if args.own_fit:  # the baseline: the project's own fitter on the same scene, in the same run
            from phirie_jax.synthetic.fitted import fit_config_for, fit_gaussians, read_training_views
            from phirie_jax.synthetic.scene import PRESETS

            images, cameras = read_training_views(scene)
            result = fit_gaussians(images, cameras, fit_config_for(sfm["preset"]), seed=sfm["seed"],
                                   background=PRESETS[sfm["preset"]].background_rgb)
            own = {**result.record, "trainer": "phirie (kernels.splat_fit)", "scene": scene.name}
            export(args.out / f"{scene.name}_fitted.npz", result.gaussians, own)
            runs.append({k: own[k] for k in ("scene", "trainer", "steps", "gaussians", "train_psnr", "compile_s",
                                            "run_s", "wall_s", "device")})
            print(json.dumps(runs[-1]), flush=True)
    emit({"strategy": args.strategy, "steps": args.steps, "seed": args.seed, "runs": runs},
         args.out / f"fit_gsplat_{args.strategy}.json")


def install(args) -> None:
    from experiments.fit_scenes import read_fit
    from phirie_jax.synthetic.fitted import FitResult, install_fit

    for path in args.fits:
        fitted = read_fit(path)
        scene = fitted.record["scene"]
        dest = args.root / path.stem
        if dest.exists():
            shutil.rmtree(dest)
        shutil.copytree(args.root / scene, dest)
        install_fit(dest, FitResult(fitted.gaussians, fitted.record))
        print(f"{dest}: {fitted.gaussians.num:,} Gaussians from {path.name} "
              f"({fitted.record.get('trainer')}, train PSNR {fitted.record['train_psnr']:.2f} dB)", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("prepare", help="here: synthesize and write SfM-like points")
    p.add_argument("--preset", default="default")
    p.add_argument("--seeds", type=int, nargs="+", required=True)
    p.add_argument("--root", type=Path, required=True)
    p.add_argument("--sfm-points", type=int, default=8000)
    p.add_argument("--sfm-noise", type=float, default=0.003, help="metres (isotropic, per point)")
    p.add_argument("--sfm-outliers", type=float, default=0.02, help="share of mismatched points")
    p.add_argument("--carry", type=Path, default=None, help="also copy what a trainer reads here")
    f = sub.add_parser("fit", help="GPU host: gsplat training of prepared folders")
    f.add_argument("scenes", type=Path, nargs="+")
    f.add_argument("--strategy", choices=STRATEGIES, default="default")
    f.add_argument("--steps", type=int, default=10_000)
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--cap-max", type=int, default=300_000, help="MCMCStrategy's Gaussian budget")
    f.add_argument("--own-fit", action="store_true", help="also the project's own fitter (baseline)")
    f.add_argument("--out", type=Path, required=True)
    i = sub.add_parser("install", help="here: make exported fits the captures of copies of their scenes")
    i.add_argument("fits", type=Path, nargs="+")
    i.add_argument("--root", type=Path, required=True, help="where prepare wrote the scene folders")
    args = parser.parse_args()
    {"prepare": prepare, "fit": fit, "install": install}[args.command](args)


if __name__ == "__main__":
    main()
