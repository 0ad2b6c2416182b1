"""A toy scene for the background branch, with the earlier stages' outputs written by hand.

An orange plane (z = 0) of flat Gaussians with nothing under the objects' contact patches (that
tabletop was never seen), and, by id:

1. a red sphere resting on the plane;
2. a blue sphere resting on the plane, beside it;
3. a green sphere the object stage *rejected* (its Gaussians must stay);
4. a yellow sphere floating 20 cm up with no surface near it (an unsupported region), and
   opaque grey "distractor" blobs near the corners of its box — inside its expanded bounds,
   beyond both removal radii, behind it from some cameras: the occlusion test keeps them.

Masks are rendered like the synthetic scene's (the label with the largest weight where it
covers half the pixel); Q_i are each sphere's surface samples seen from the cameras (no
bottom); assets are icospheres of the true radius. Object 5 is accepted but its observation file
is missing. Ground truth: ``labels`` (0 plane,
k object, 10 distractor).
"""

from __future__ import annotations

import dataclasses
import io
import json
from pathlib import Path

import numpy as np

from kernels.sh import rgb_to_sh_dc
from phirie_jax.io.camera import intrinsics_matrix
from phirie_jax.io.ply import write_gaussian_ply
from phirie_jax.synthetic.capture import tangent_frames
from phirie_jax.synthetic.scene import look_at
from phirie_jax.types import Camera, GaussianSplatData

ORANGE = np.array([0.85, 0.5, 0.2])
COLOURS = {1: (0.9, 0.1, 0.1), 2: (0.1, 0.2, 0.9), 3: (0.1, 0.8, 0.2), 4: (0.9, 0.9, 0.1)}
SPHERES = {1: ((-0.06, -0.02, 0.035), 0.035), 2: ((0.05, 0.03, 0.03), 0.03),
           3: ((0.0, 0.12, 0.03), 0.03), 4: ((0.02, -0.1, 0.22), 0.03)}
DISTRACTOR = 10
PLANE_SPACING = 0.008
SPHERE_SPACING = 0.006
WIDTH, HEIGHT, FOCAL = 96, 72, 110.0
BACKGROUND_RGB = np.array([0.2, 0.2, 0.25])


@dataclasses.dataclass
class ToyScene:
    root: Path
    out: Path
    data: GaussianSplatData
    labels: np.ndarray
    cameras: list[Camera]


def _gaussians(points, normals, rgb, sigma, opacity=0.95, thickness=0.15):
    from scipy.spatial.transform import Rotation

    n = len(points)
    sh = np.zeros((n, 16, 3), np.float32)
    sh[:, 0] = rgb_to_sh_dc(np.asarray(rgb))
    quats = np.roll(Rotation.from_matrix(tangent_frames(normals)).as_quat(), 1, axis=1)
    return GaussianSplatData(
        means=np.asarray(points, np.float32), quats=quats.astype(np.float32),
        log_scales=np.tile(np.log([sigma, sigma, thickness * sigma]), (n, 1)).astype(np.float32),
        opacity_logits=np.full(n, np.log(opacity / (1 - opacity)), np.float32), sh=sh)


def _cat(parts):
    return GaussianSplatData(**{f: np.concatenate([getattr(p, f) for p in parts])
                                for f in ("means", "quats", "log_scales", "opacity_logits", "sh")})


def _sphere_points(centre, radius, spacing, rng):
    n = int(4 * np.pi * radius**2 / spacing**2)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(centre) + radius * d, d


def cameras() -> list[Camera]:
    K = intrinsics_matrix(FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2)
    cams = []
    for k in range(8):
        a = 2 * np.pi * k / 8 + 0.2
        height = 0.35 if k % 2 else 0.5
        eye = np.array([0.42 * np.cos(a), 0.42 * np.sin(a), height])
        cams.append(Camera(f"{k:04d}.png", K, look_at(eye, np.array([0.0, 0.0, 0.05])), WIDTH, HEIGHT))
    return cams


def build(root: Path) -> ToyScene:
    """Write the scene folder under ``root/scene`` and the earlier stages' outputs under ``root/out``."""
    import cv2
    import jax.numpy as jnp
    import trimesh

    from phirie_jax.io.transforms_json import write_transforms_json
    from phirie_jax.render import render

    rng = np.random.default_rng(0)
    scene_dir, out = root / "scene", root / "out"
    xs = np.arange(-0.2, 0.2 + 1e-9, PLANE_SPACING)
    xy = np.stack(np.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2) + rng.uniform(-1e-3, 1e-3, (len(xs) ** 2, 2))
    hidden = np.zeros(len(xy), bool)
    for k in (1, 2, 3):
        (cx, cy, _), r = SPHERES[k]
        hidden |= np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) < 0.45 * r  # the contact patch
    plane_pts = np.concatenate([xy[~hidden], np.zeros((int((~hidden).sum()), 1))], axis=1)
    parts = [_gaussians(plane_pts, np.tile([0.0, 0, 1], (len(plane_pts), 1)), ORANGE, 0.9 * PLANE_SPACING)]
    labels = [np.zeros(len(plane_pts), np.int64)]
    q_points = {}
    for k, ((cx, cy, cz), r) in SPHERES.items():
        pts, normals = _sphere_points((cx, cy, cz), r, SPHERE_SPACING, rng)
        parts.append(_gaussians(pts, normals, COLOURS[k], 0.9 * SPHERE_SPACING))
        labels.append(np.full(len(pts), k))
        q_points[k] = pts[normals[:, 2] > -0.4]  # the cameras never see the bottom
    (cx, cy, cz), r = SPHERES[4]
    # on the horizontal diagonals, low: behind the sphere from cameras on the opposite side, which
    # look down at about 30°; 7.4 cm from its centre (beyond r + 3 cm), inside its box + 2 cm
    blobs = np.array([[cx + sx * 0.045, cy + sy * 0.045, cz - 0.035] for sx in (-1, 1) for sy in (-1, 1)])
    parts.append(_gaussians(blobs, np.tile([0.0, 0, 1], (4, 1)), (0.5, 0.5, 0.5), 0.004, opacity=0.98, thickness=1.0))
    labels.append(np.full(4, DISTRACTOR))
    data, labels = _cat(parts), np.concatenate(labels)
    write_gaussian_ply(scene_dir / "point_cloud.ply", data)

    cams = cameras()
    write_transforms_json(scene_dir / "transforms.json", cams)
    ids = np.array(sorted(SPHERES))
    one_hot = jnp.asarray(labels[:, None] == ids[None], jnp.float32)
    g = data.to_kernel()
    views = {k: [] for k in SPHERES}
    for v, cam in enumerate(cams):
        res = render(g, cam, background=jnp.asarray(BACKGROUND_RGB, jnp.float32), features=one_hot)
        w = np.asarray(res.features)
        best = np.argmax(w, axis=-1)
        covered = np.take_along_axis(w, best[..., None], -1)[..., 0] >= 0.5
        mask = np.where(covered, ids[best], 0).astype(np.uint16)
        (scene_dir / "images").mkdir(parents=True, exist_ok=True)
        (scene_dir / "masks").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(scene_dir / "images" / cam.name),
                    np.round(np.asarray(res.rgb)[..., ::-1] * 255).astype(np.uint8))
        cv2.imwrite(str(scene_dir / "masks" / cam.name), mask)
        for k in SPHERES:
            rows, cols = np.nonzero(mask == k)
            if len(rows) >= 4:
                views[k].append((v, len(rows), [cols.min(), rows.min(), cols.max(), rows.max()]))

    instances, objects = [], []
    for k, ((cx, cy, cz), r) in SPHERES.items():
        rel = f"observe/instance_{k}.npz"
        buf = io.BytesIO()
        np.savez(buf, points=q_points[k].astype(np.float32), views=np.array([v for v, _, _ in views[k]], np.int32),
                 labels=np.full(len(views[k]), k, np.int64),
                 mask_paths=np.array([str(scene_dir / "masks" / cams[v].name) for v, _, _ in views[k]]),
                 pixels=np.array([p for _, p, _ in views[k]], np.int64),
                 bboxes=np.array([b for _, _, b in views[k]], np.int32).reshape(-1, 4))
        (out / "observe").mkdir(parents=True, exist_ok=True)
        (out / rel).write_bytes(buf.getvalue())
        instances.append({"id": k, "category": None, "views": [v for v, _, _ in views[k]],
                          "num_points": len(q_points[k]), "points": rel, "source": "files",
                          "bounds": [q_points[k].min(0).tolist(), q_points[k].max(0).tolist()],
                          "support": {"height": 0.0 if k != 4 else cz - r, "source": "test", "hits": 0,
                                      "normal": [0.0, 0.0, 1.0]}})
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=r)
        (out / "objects" / str(k)).mkdir(parents=True, exist_ok=True)
        mesh.export(out / "objects" / str(k) / "mesh.obj")
        pose = np.eye(4)
        pose[:3, 3] = [cx, cy, cz]
        objects.append({"id": k, "status": "rejected" if k == 3 else "accepted", "reason": None,
                        "pose": pose.tolist(), "mesh": f"objects/{k}/mesh.obj"})
    # 5: accepted, but its observation file is gone: recorded as failed, the others go on
    instances.append({"id": 5, "category": None, "views": [], "num_points": 0, "points": "observe/missing.npz",
                      "source": "files", "bounds": [[0, 0, 0], [0, 0, 0]]})
    objects.append({"id": 5, "status": "accepted", "reason": None, "pose": np.eye(4).tolist(), "mesh": None})
    manifest = {"schema": "phirie/1", "timings": {}, "instances": instances, "objects": objects,
                "construct": {"gravity": {"up": [0.0, 0.0, 1.0], "source": "test"}}}
    (out / "manifest.json").write_text(json.dumps(manifest))
    return ToyScene(root, out, data, labels, cams)
