"""The hand-found truth of the real captures' frames (``tests/fixtures/frame_truth.json``), recomputed
from what was picked in their photos.

Picks are pixel positions as image viewers and OpenCV give them (the top-left pixel's centre is
(0, 0)); the cameras' pixel centres are at i + 0.5, hence the half pixel added here.
- plumb edges: straight segments along door frames, wall corners, wardrobe and picture-frame
  edges; the vertical is the direction every segment's plane (through its camera) contains;
- points: one physical point clicked in several photos, triangulated;
- lines: one straight edge traced in several photos, the 3D line where their planes meet.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from phirie_jax.types import Camera

TRUTH = Path(__file__).resolve().parents[1] / "fixtures" / "frame_truth.json"


def load_truth() -> dict:
    return json.loads(TRUTH.read_text())


def _rays(camera: Camera, pixels: np.ndarray) -> np.ndarray:
    """(P, 3) world directions of (P, 2) picked pixels."""
    local = np.column_stack([np.asarray(pixels, np.float64) + 0.5, np.ones(len(pixels))]) @ np.linalg.inv(camera.K).T
    return local @ camera.world_to_camera[:3, :3]


def _segment_normal(camera: Camera, segment) -> np.ndarray:
    a, b = _rays(camera, np.reshape(segment, (2, 2)))
    n = np.cross(a, b)
    return n / np.linalg.norm(n)


def plumb(cameras: dict[str, Camera], segments: list, sign: np.ndarray) -> np.ndarray:
    """(3,) the direction in every [image, x0, y0, x1, y1] segment's plane, signed like ``sign``."""
    normals = np.array([_segment_normal(cameras[s[0]], s[1:]) for s in segments])
    v = np.linalg.eigh(normals.T @ normals)[1][:, 0]
    return v if v @ sign >= 0 else -v


def triangulate(cameras: dict[str, Camera], picks: list) -> tuple[np.ndarray, float]:
    """(3,) the point clicked at [image, u, v] in several photos, and the worst miss (pixels)."""
    rows = []
    for name, u, v in picks:
        cam = cameras[name]
        pose = cam.K @ cam.world_to_camera[:3]
        rows += [(u + 0.5) * pose[2] - pose[0], (v + 0.5) * pose[2] - pose[1]]
    solution = np.linalg.svd(np.asarray(rows))[2][-1]
    point = solution[:3] / solution[3]
    miss = max(float(np.linalg.norm(cameras[n].project(point[None])[0][0] - [u + 0.5, v + 0.5])) for n, u, v in picks)
    return point, miss


def line(cameras: dict[str, Camera], segments: list) -> tuple[np.ndarray, np.ndarray]:
    """(point (3,), direction (3,)) of the 3D line traced by [image, x0, y0, x1, y1] segments."""
    normals = np.array([_segment_normal(cameras[s[0]], s[1:]) for s in segments])
    offsets = np.array([n @ cameras[s[0]].center for n, s in zip(normals, segments)])
    direction = np.linalg.svd(normals)[2][-1]
    point = np.linalg.lstsq(np.vstack([normals, direction]), np.append(offsets, 0.0), rcond=None)[0]
    return point, direction


def vertical_in_wall(v: np.ndarray, wall_normal: np.ndarray) -> np.ndarray:
    """``v`` made orthogonal to a plumb wall's normal (a picture hung on a wire leans out at the
    top; its edges are plumb only within the wall)."""
    n = wall_normal / np.linalg.norm(wall_normal)
    u = v - (v @ n) * n
    return u / np.linalg.norm(u)


def derive(name: str, cameras: dict[str, Camera], truth: dict, vote: np.ndarray) -> dict:
    """The truth of one capture recomputed from its picks: {"up", "scale", "scale_range", ...}."""
    t = truth[name]
    up = plumb(cameras, t["plumb_segments"], vote)
    if t.get("wall_normal") is not None:
        up = vertical_in_wall(up, np.asarray(t["wall_normal"]))
    out = {"up": up}
    lengths = {}
    for key, spec in t["lengths"].items():
        if spec["kind"] == "height":   # a picked point's height over a traced horizontal line
            top, _ = triangulate(cameras, spec["point"])
            base, _ = line(cameras, spec["line"])
            lengths[key] = float(up @ (top - base))
        else:                          # the distance between two picked points
            a, _ = triangulate(cameras, spec["from"])
            b, _ = triangulate(cameras, spec["to"])
            lengths[key] = float(np.linalg.norm(a - b))
    low = min(t["lengths"][k]["metres"][0] / lengths[k] for k in lengths)
    high = max(t["lengths"][k]["metres"][1] / lengths[k] for k in lengths)
    out.update(lengths=lengths, scale_range=(low, high), scale=float(np.sqrt(low * high)))
    return out
