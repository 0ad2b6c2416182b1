"""``phirie capture --trainer gsplat``: the same training with gsplat's CUDA rasterizer and strategy.

For users who prefer gsplat, and as the baseline the project's trainer is measured against
(``experiments/capture_eval.py``). It follows gsplat 1.5.3's ``examples/simple_trainer.py``
with ``DefaultStrategy``, fed from ``TrainConfig``: the same initial Gaussians
(``train.init_from_points``, same seed), Adam (eps 1e-15) with the same per-parameter rates and
the position's exponential decay, one view per step in the same seeded order, an SH band every
``sh_band_interval`` steps, loss (1 − λ) L1 + λ (1 − SSIM) with SSIM over the valid region (as
simple_trainer's ``fused_ssim(..., padding="valid")``), the config's background (gsplat's: black); densification by
``DefaultStrategy`` with the config's thresholds and schedule (it has no Gaussian limit: 
``max_gaussians`` does not apply). Held-out views are scored on gsplat's own renders, clamped
to [0, 1] as simple_trainer's evaluation does.

Needs ``gsplat`` and PyTorch with CUDA (``pip install 'phirie_jax[gsplat]'``) and an NVIDIA GPU.
gsplat 1.5.3's wheel is Python only: its CUDA code is compiled on first use (minutes, cached in
``~/.cache/torch_extensions``), which the record counts in ``compile_s``.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from phirie_jax.capture.config import TrainConfig
from phirie_jax.errors import OptionError
from phirie_jax.progress import task
from phirie_jax.types import Camera, GaussianSplatData

SSIM_WINDOW, SSIM_SIGMA = 11, 1.5    # Wang et al. 2004, as every 3DGS trainer
SSIM_C1, SSIM_C2 = 0.01**2, 0.03**2
NEVER = 1 << 30                       # a DefaultStrategy interval that never comes


def require_gsplat():
    """(torch, gsplat), or an ``OptionError`` saying how to get them."""
    try:
        import gsplat
        import torch
    except ImportError:
        raise OptionError("--trainer", "gsplat is not installed (expected gsplat and PyTorch with CUDA: "
                          "pip install 'phirie_jax[gsplat]' on a machine with an NVIDIA GPU; or --trainer jax)",
                          "gsplat") from None
    if not torch.cuda.is_available():
        raise OptionError("--trainer", "PyTorch sees no CUDA GPU (expected one for gsplat; or --trainer jax)",
                          "gsplat")
    return torch, gsplat


def _ssim(torch, a, b):
    """Mean SSIM over the valid region of a, b (1, 3, H, W)."""
    import torch.nn.functional as F

    x = torch.arange(SSIM_WINDOW, dtype=a.dtype, device=a.device) - SSIM_WINDOW // 2
    g = torch.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    g = g / g.sum()
    window = (g[:, None] * g[None, :]).expand(3, 1, SSIM_WINDOW, SSIM_WINDOW).contiguous()

    def blur(t):
        return F.conv2d(t, window, groups=3)

    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    num = (2 * mu_a * mu_b + SSIM_C1) * (2 * cov + SSIM_C2)
    return (num / ((mu_a**2 + mu_b**2 + SSIM_C1) * (var_a + var_b + SSIM_C2))).mean()


def train_with_gsplat(cameras: list[Camera], images: list[np.ndarray], train: list[int], test: list[int],
                      points: np.ndarray, colours: np.ndarray, config: TrainConfig, extent: float
                      ) -> tuple[GaussianSplatData, dict]:
    """Train on the views ``train`` and score ``test`` (module docstring). images: (H, W, 3) uint8 RGB;
    points (P, 3) and colours (P, 3) uint8 the SfM points; extent: the scene scale.
    Returns every Gaussian of the last step and the record."""
    torch, gsplat = require_gsplat()
    import torch.nn.functional as F
    from gsplat import DefaultStrategy, rasterization

    from phirie_jax.capture.train import init_from_points

    device = "cuda"
    rng = np.random.default_rng(config.seed)
    torch.manual_seed(config.seed)
    init = init_from_points(points, colours.astype(np.float64) / 255.0, config, rng)

    def tensor(x, dtype=torch.float32):
        return torch.tensor(np.ascontiguousarray(x), dtype=dtype, device=device)

    params = torch.nn.ParameterDict({
        "means": torch.nn.Parameter(tensor(init.means)), "scales": torch.nn.Parameter(tensor(init.log_scales)),
        "quats": torch.nn.Parameter(tensor(init.quats)), "opacities": torch.nn.Parameter(tensor(init.opacity_logits)),
        "sh0": torch.nn.Parameter(tensor(init.sh[:, :1])), "shN": torch.nn.Parameter(tensor(init.sh[:, 1:]))})
    rates = {"means": config.lr_position * extent, "scales": config.lr_scale, "quats": config.lr_rotation,
             "opacities": config.lr_opacity, "sh0": config.lr_colour, "shN": config.lr_colour / 20.0}
    optimizers = {k: torch.optim.Adam([{"params": params[k], "lr": lr, "name": k}], eps=1e-15)
                  for k, lr in rates.items()}
    decay = torch.optim.lr_scheduler.ExponentialLR(
        optimizers["means"], gamma=(config.lr_position_final / config.lr_position) ** (1.0 / config.steps))
    strategy = DefaultStrategy(prune_opa=config.min_opacity, grow_grad2d=config.grad_threshold,
                               grow_scale3d=config.percent_dense, prune_scale3d=config.max_scale,
                               refine_start_iter=config.densify_from, refine_stop_iter=config.densify_until,
                               refine_every=config.densify_interval,
                               reset_every=config.opacity_reset_interval or NEVER)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=extent)

    pixels = tensor(np.stack([images[i] for i in train]), torch.uint8)            # [V, H, W, 3]
    viewmats = tensor(np.stack([cameras[i].world_to_camera for i in train]))       # [V, 4, 4]
    Ks = tensor(np.stack([cameras[i].K for i in train]))                           # [V, 3, 3]
    height, width = pixels.shape[1], pixels.shape[2]

    background = tensor(np.asarray(config.background)[None])                       # [1, 3]

    def render(view_mats, k_mats, sh_degree):
        colors = torch.cat([params["sh0"], params["shN"]], 1)
        return rasterization(means=params["means"], quats=params["quats"], scales=torch.exp(params["scales"]),
                             opacities=torch.sigmoid(params["opacities"]), colors=colors, viewmats=view_mats,
                             Ks=k_mats, width=width, height=height, sh_degree=sh_degree, packed=False,
                             backgrounds=background)

    torch.cuda.reset_peak_memory_stats()
    order: list[int] = []
    losses, first_step_s = [], None
    t0 = time.perf_counter()
    with task(f"training {config.steps} steps on {len(train)} views with gsplat {gsplat.__version__}",
              config.steps) as advance:
        for step in range(config.steps):
            if not order:
                order = list(rng.permutation(len(train)))
            view = int(order.pop(0))
            t_step = time.perf_counter()
            colors, _, info = render(viewmats[view:view + 1], Ks[view:view + 1],
                                     min(step // config.sh_band_interval, config.sh_degree))
            strategy.step_pre_backward(params, optimizers, state, step, info)
            target = pixels[view:view + 1].float() / 255.0
            ssim = _ssim(torch, colors.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2))
            loss = (1 - config.dssim_weight) * F.l1_loss(colors, target) + config.dssim_weight * (1 - ssim)
            loss.backward()
            for optimizer in optimizers.values():
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
            decay.step()
            strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
            losses.append(float(loss.item()))  # waits for the step, as simple_trainer's progress bar does
            if first_step_s is None:
                first_step_s = time.perf_counter() - t_step
            advance()
            if (step + 1) % 100 == 0:
                advance.update(f"gsplat: step {step + 1}/{config.steps}, loss {losses[-1]:.4f}, "
                               f"{len(params['means']):,} Gaussians")
    torch.cuda.synchronize()
    wall = time.perf_counter() - t0
    peak_mb = round(torch.cuda.max_memory_allocated() / 2**20, 1)

    with torch.no_grad():
        scores = []
        for i in test:
            rgb, _, _ = render(tensor(cameras[i].world_to_camera[None]), tensor(cameras[i].K[None]), config.sh_degree)
            target = tensor(images[i], torch.uint8).float() / 255.0
            scores.append(float(10 * torch.log10(1 / F.mse_loss(rgb[0].clamp(0, 1), target))))
        data = GaussianSplatData(**{k: params[name].detach().cpu().numpy().astype(np.float32) for k, name in
                                    (("means", "means"), ("quats", "quats"), ("log_scales", "scales"),
                                     ("opacity_logits", "opacities"))},
                                 sh=torch.cat([params["sh0"], params["shN"]], 1).detach().cpu().numpy().astype(
                                     np.float32))
    params = optimizers = state = pixels = None  # freed before JAX scores the result in this process
    torch.cuda.empty_cache()
    run_s = wall - (first_step_s or 0.0)
    record = {"trainer": f"gsplat {gsplat.__version__}", "torch": torch.__version__, "steps": config.steps,
              "gaussians": data.num, "initial_gaussians": init.num, "loss_first": losses[0], "loss_last": losses[-1],
              "extent": round(extent, 6), "views_trained": len(train), "held_out": [cameras[i].name for i in test],
              "held_out_psnr": round(float(np.mean(scores)), 3) if scores else None,
              "held_out_psnr_per_view": [round(v, 3) for v in scores], "peak_gpu_mb": peak_mb,
              "device": torch.cuda.get_device_name(), "backend": "cuda", "wall_s": round(wall, 3),
              "compile_s": round(first_step_s or 0.0, 3), "run_s": round(run_s, 3),
              "step_s_mean": round(run_s / max(1, config.steps - 1), 5), "config": dataclasses.asdict(config)}
    return data, record
