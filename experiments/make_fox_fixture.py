"""Cut a small real test scene from the fox capture: ``tests/fixtures/fox/``.

    python -m experiments.make_fox_fixture [--capture DIR] [--out DIR]

Deterministic: the same capture gives the same files. Steps:

1. The head: the cameras' common focus point (least-squares point nearest every optical
   axis) lies on the wall the head is mounted on. The wall plane is a RANSAC fit (fixed
   seed) to the opaque Gaussians around it; the wall frame has x = wall normal (towards the
   cameras), z = the cameras' mean image-up made orthogonal to it.
2. The head's box prompt (instance 1): in the wall frame, from ``HEAD_OFF_WALL`` in front
   of the wall to the 98th percentile of the opaque Gaussians standing more than
   ``HEAD_CORE`` off it, sideways and vertically their 2nd–98th percentile padded by ``HEAD_PAD``.
   The plaque and the wall stay out. Written to ``box_prompt.json``.
3. The Gaussians: those in a wall-frame box ``CROP_MARGIN`` wider than the head box, reaching
   ``CROP_BEHIND`` behind the wall; at most ``MAX_GAUSSIANS`` of them, the largest
   opacity × projected area first; SH cut to degree ``SH_DEGREE``.
4. ``NUM_VIEWS`` training views spread over the file order (never a held-out one, every
   ``HOLD_OUT_EVERY``-th from the first), images resized to ``SCALE`` with INTER_AREA and
   intrinsics scaled like ``Camera.scaled``; ``transforms.json`` in nerfstudio's layout.
5. ``masks/`` from the box prompt (``phirie_jax.observe.box_prompt``) on the cut Gaussians.
6. ``LICENSE.txt`` copied (the photos' licence asks for it) and a README.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

from phirie_jax.io.atomic import write_bytes, write_text
from phirie_jax.io.ply import write_gaussian_ply
from phirie_jax.io.scene import load_scene
from phirie_jax.io.transforms_json import write_transforms_json
from phirie_jax.observe.box_prompt import BoxPrompt, write_box_masks
from phirie_jax.types import Camera, GaussianSplatData

CAPTURE = Path("/work/shared/data/captures/fox")
OUT = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "fox"
HOLD_OUT_EVERY = 8       # held-out views: every 8th in file order (0001 0012 … 0110)
NUM_VIEWS = 10
SCALE = 0.25             # 540×960 → 135×240
JPEG_QUALITY = 90
MAX_GAUSSIANS = 15_000
SH_DEGREE = 1
OPAQUE = 0.5             # opacity of the Gaussians that locate the wall and the head
MIN_OPACITY = 0.02       # fainter Gaussians are not worth a fixture slot
WALL_RADIUS = 3.5        # capture units around the focus used to fit the wall
WALL_INLIER = 0.08       # RANSAC inlier distance, capture units
RANSAC_TRIES = 3000
HEAD_RADIUS = 2.6        # the head lies within this of the focus
HEAD_CORE = 0.6          # Gaussians this far off the wall are the head (haze and plaque are nearer)
HEAD_OFF_WALL = 0.4      # the box starts here: the plaque and the wall's haze stay out
HEAD_PAD = 0.15
CROP_MARGIN = 1.0
CROP_BEHIND = 0.5
SEED = 0


def focus_point(cameras: list[Camera]) -> np.ndarray:
    """(3,) the point nearest every camera's optical axis (least squares)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for cam in cameras:
        d = cam.camera_to_world[:3, 2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ cam.center
    return np.linalg.solve(A, b)


def wall_frame(points: np.ndarray, cameras: list[Camera], seed: int = SEED) -> np.ndarray:
    """(3, 3) rows: wall normal towards the cameras, along the wall, up the wall; points (N, 3)."""
    rng = np.random.default_rng(seed)
    best, normal, origin = -1, None, None
    for _ in range(RANSAC_TRIES):
        p = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(p[1] - p[0], p[2] - p[0])
        if np.linalg.norm(n) < 1e-9:
            continue
        n /= np.linalg.norm(n)
        count = int((np.abs((points - p[0]) @ n) < WALL_INLIER).sum())
        if count > best:
            best, normal, origin = count, n, p[0]
    centres = np.array([c.center for c in cameras])
    if (centres.mean(0) - origin) @ normal < 0:
        normal = -normal
    up = -np.mean([c.world_to_camera[1, :3] for c in cameras], axis=0)
    up = up - (up @ normal) * normal
    up /= np.linalg.norm(up)
    return np.stack([normal, np.cross(up, normal), up])


def opacity(g: GaussianSplatData) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))


def head_box(g: GaussianSplatData, focus: np.ndarray, frame: np.ndarray) -> BoxPrompt:
    local = (g.means - focus) @ frame.T
    core = (opacity(g) > OPAQUE) & (local[:, 0] > HEAD_CORE) & (np.linalg.norm(g.means - focus, axis=1) < HEAD_RADIUS)
    lo, hi = np.percentile(local[core], [2, 98], axis=0)
    lo = np.r_[HEAD_OFF_WALL, lo[1:] - HEAD_PAD]
    hi = hi + HEAD_PAD
    shift = frame @ focus  # the box is axis-aligned in x_b = frame @ x_c
    return BoxPrompt(1, tuple((lo + shift).tolist()), tuple((hi + shift).tolist()),
                     tuple(tuple(r) for r in frame.tolist()))


def crop(g: GaussianSplatData, box: BoxPrompt, frame: np.ndarray) -> GaussianSplatData:
    local = g.means @ frame.T
    lo = np.asarray(box.lower) - CROP_MARGIN
    hi = np.asarray(box.upper) + CROP_MARGIN
    lo[0] = box.lower[0] - HEAD_OFF_WALL - CROP_BEHIND
    inside = np.all((local >= lo) & (local <= hi), axis=1) & (opacity(g) >= MIN_OPACITY)
    index = np.flatnonzero(inside)
    scales = np.exp(g.log_scales[index].astype(np.float64))
    area = np.exp(np.log(scales).sum(1) * 2.0 / 3.0)   # (volume)^(2/3): a size-only proxy of screen area
    weight = opacity(g)[index] * area
    keep = np.sort(index[np.argsort(-weight, kind="stable")[:MAX_GAUSSIANS]])
    cut = g.subset(keep)
    k = (SH_DEGREE + 1) ** 2
    return GaussianSplatData(cut.means, cut.quats, cut.log_scales, cut.opacity_logits,
                             np.ascontiguousarray(cut.sh[:, :k]))


def pick_views(cameras: list[Camera]) -> list[Camera]:
    training = [c for i, c in enumerate(cameras) if i % HOLD_OUT_EVERY != 0]
    index = np.unique(np.round(np.linspace(0, len(training) - 1, NUM_VIEWS)).astype(int))
    return [training[i] for i in index]


README = """# `fox/` — a small real fixture cut from the fox capture

Made by `python -m experiments.make_fox_fixture` from `shared/data/captures/fox` (see that
script for every number). Capture frame kept: **not metric, not gravity-aligned**.

| file | what |
| --- | --- |
| `point_cloud.ply` | {num} of the capture's 206,814 Gaussians: those in a box around the head and the wall behind it, the largest opacity × area first; **SH cut to degree {degree}** (the capture has degree 3) to keep the file small |
| `images/*.jpg` | {views} training views (none of the held-out 0001 0012 0027 0042 0073 0089 0110), resized to {w}×{h} with INTER_AREA, JPEG quality {q} |
| `transforms.json` | nerfstudio layout, intrinsics scaled by {scale} (pixel-centre convention kept) |
| `masks/*.png` | 16-bit instance masks from the box prompt: 1 = the fox head, 0 = none |
| `box_prompt.json` | the head's box: `lower`/`upper` in the frame x_b = `rotation` · x_capture (wall-aligned) |
| `LICENSE.txt` | the instant-ngp licence that covers the photos (redistribution requires it) |
"""


def make_fixture(capture: Path, out: Path) -> dict:
    scene = load_scene(capture)
    cameras = list(scene.cameras)
    g = scene.require_gaussians()
    focus = focus_point(cameras)
    near = (opacity(g) > OPAQUE) & (np.linalg.norm(g.means - focus, axis=1) < WALL_RADIUS)
    frame = wall_frame(g.means[near].astype(np.float64), cameras)
    box = head_box(g, focus, frame)
    cut = crop(g, box, frame)
    views = pick_views(cameras)

    import cv2

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        small = []
        for cam in views:
            image = cv2.imread(str(cam.image_path), cv2.IMREAD_COLOR)
            scaled = cam.scaled(SCALE)
            image = cv2.resize(image, (scaled.width, scaled.height), interpolation=cv2.INTER_AREA)
            ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                raise RuntimeError(f"JPEG encoding failed for {cam.name}")
            write_bytes(staging / "images" / cam.name, buf.tobytes())
            small.append(scaled)
        write_transforms_json(staging / "transforms.json", small)
        write_gaussian_ply(staging / "point_cloud.ply", cut)
        result = write_box_masks(cut, small, [box], staging / "masks")
        prompt = {"id": box.id, "lower": list(box.lower), "upper": list(box.upper),
                  "rotation": [list(r) for r in box.rotation], "focus": focus.tolist(),
                  "what": "the fox head; axis-aligned in x_b = rotation @ x_capture (wall frame)"}
        write_text(staging / "box_prompt.json", json.dumps(prompt, indent=1) + "\n")
        shutil.copyfile(capture / "LICENSE.txt", staging / "LICENSE.txt")
        write_text(staging / "README.md", README.format(
            num=f"{cut.num:,}", degree=SH_DEGREE, views=len(small), w=small[0].width, h=small[0].height,
            q=JPEG_QUALITY, scale=SCALE))
        if out.exists():
            shutil.rmtree(out)
        staging.rename(out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return {"out": str(out), "gaussians": cut.num, "views": [c.name for c in small],
            "mask_pixels": [p.get(box.id, 0) for p in result.pixels], "bytes": size,
            "focus": focus.round(4).tolist(), "box": prompt}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--capture", type=Path, default=CAPTURE)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    print(json.dumps(make_fixture(args.capture, args.out), indent=1))


if __name__ == "__main__":
    main()
