"""The end-to-end job on the embedded default scene (``make demo``).

Today it synthesizes the default tabletop, reloads it through the scene loader
exactly as a real capture would be read, renders previews from the loaded
Gaussians and cameras beside the ground-truth images, and prints a summary with
the time of each stage. Later stages (observe, construct, simulate) extend it.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from phirie_jax.synthetic.scene import write_png

PREVIEW_VIEWS = 4


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def write_previews(scene_dir: Path, out_dir: Path, background, views: int = PREVIEW_VIEWS) -> list[dict]:
    """Render the loaded scene at ``views`` evenly spread cameras; save render | ground truth."""
    import cv2

    from phirie_jax.io.scene import load_scene
    from phirie_jax.render import render

    scene = load_scene(scene_dir)
    gaussians = scene.require_gaussians().to_kernel()
    picks = np.linspace(0, len(scene.cameras) - 1, views).round().astype(int)
    rows = []
    for k in picks:
        cam = scene.cameras[k]
        out = render(gaussians, cam, background=np.asarray(background, np.float32))
        rendered = np.asarray(out.rgb)
        truth = cv2.imread(str(cam.image_path), cv2.IMREAD_COLOR)[..., ::-1] / 255.0
        write_png(out_dir / f"preview_{k:04d}.png", np.concatenate([rendered, truth], axis=1))
        rows.append({"camera": int(k), "name": cam.name, "psnr_db": round(psnr(rendered, truth), 2)})
    return rows


def run_demo(out: Path, preset: str = "default", seed: int = 0) -> dict:
    from rich.console import Console
    from rich.table import Table

    from phirie_jax.synthetic import synthesize

    console = Console()
    timings: dict[str, float] = {}
    scene_dir = out / "scene"
    t0 = time.perf_counter()
    with console.status(f"synthesizing the {preset} tabletop scene (seed {seed})"):
        scene = synthesize(scene_dir, preset=preset, seed=seed)
    timings["synthesize"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    with console.status("rendering previews from the written scene"):
        previews = write_previews(scene_dir, out / "previews", scene.config.background_rgb)
    timings["previews"] = time.perf_counter() - t0

    table = Table(title=f"phirie demo → {out}")
    table.add_column("what")
    table.add_column("value")
    table.add_row("scene", f"{scene_dir} ({len(scene.cameras)} cameras, "
                           f"{scene.config.width}×{scene.config.height})")
    table.add_row("objects", ", ".join(f"{o.id}:{o.shape.category}" for o in scene.objects))
    table.add_row("Gaussians", f"{scene.capture.data.num:,} captured, "
                               f"{scene.background.data.num:,} in the true background")
    for row in previews:
        table.add_row(f"preview {row['name']}", f"re-render vs image: {row['psnr_db']} dB PSNR")
    for stage, seconds in timings.items():
        table.add_row(f"time: {stage}", f"{seconds:.1f} s")
    console.print(table)
    return {"timings": timings, "previews": previews}
