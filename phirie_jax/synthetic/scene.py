"""Procedural tabletop scenes with ground truth, written exactly like a real capture.

``synthesize(out_dir, preset, seed)`` writes a standard scene folder:

    point_cloud.ply        the 3DGS "capture" (INRIA PLY, SH degree 3)
    transforms.json        nerfstudio cameras        sparse/0/*.txt   the same, as COLMAP text
    images/NNNN.png        renders of the capture    masks/NNNN.png   16-bit instance ids
    surface.ply            the scene surface mesh (floor, table, objects)
    frame.json             the capture's frame as declared: metric, +z up
    gt/objects.json        per object: id, category, world and canonical mesh, pose
    gt/objects/<id>/{canonical,world}.obj
    gt/background.ply      floor + table Gaussians including the tabletop under the objects
    gt/labels.npy          (N,) uint16 instance label of every capture Gaussian
    gt/markers.json        with ``marker``: the printed marker's dictionary, id, side, corners

Everything is seeded: the same preset and seed give the same files.
"""

from __future__ import annotations

import dataclasses
import io
import json
from pathlib import Path

import numpy as np

from phirie_jax.frame.config import SCENE_FRAME_FILE
from phirie_jax.io.atomic import write_bytes, write_text
from phirie_jax.io.camera import intrinsics_matrix
from phirie_jax.io.colmap import write_colmap_text
from phirie_jax.io.ply import write_gaussian_ply
from phirie_jax.io.transforms_json import write_transforms_json
from phirie_jax.synthetic import shapes
from phirie_jax.synthetic.capture import LabelledGaussians, blob_gaussians, sample_surface, surface_gaussians
from phirie_jax.synthetic.marker import TRUTH_FILE as MARKER_TRUTH
from phirie_jax.synthetic.marker import PrintedMarker, place_marker
from phirie_jax.types import Camera

MASK_COVERAGE = 0.5     # a mask pixel needs this much of one instance's rendered weight
SPARSE_POINTS = 20_000  # COLMAP points3D written beside the cameras
CONTACT_HEIGHT = 0.004  # object vertices this close to the table form its contact patch
PLACEMENT_GAP = 0.02    # minimum clearance between object footprints
TABLE_MARGIN = 0.06     # keep objects this far inside the tabletop edge

TRUTH_OBJECTS = "gt/objects.json"   # the ground truth: what marks a folder as written by phirie synth


@dataclasses.dataclass(frozen=True)
class SynthConfig:
    """One preset of the synthetic tabletop. Spacings are Gaussian sample spacings in metres."""

    num_objects: tuple[int, int] = (4, 6)
    num_cameras: int = 36
    rings: tuple[tuple[float, float], ...] = ((1.25, 1.25), (0.95, 1.6), (1.5, 1.0))  # (radius, height)
    width: int = 320
    height: int = 240
    fov_deg: float = 55.0
    object_spacing: float = 0.003
    table_spacing: float = 0.006
    floor_spacing: float = 0.02
    floor_size: float = 3.0
    table_top: tuple[float, float] = (1.2, 0.8)  # tabletop size in x, y (metres)
    floaters: int = 40
    boundary_blobs: int = 24  # per object
    background_rgb: tuple[float, float, float] = (0.62, 0.66, 0.72)


PRESETS = {
    "tiny": SynthConfig(num_objects=(3, 3), num_cameras=12, rings=((1.2, 1.35), (0.9, 1.5)), width=128, height=96,
                        object_spacing=0.008, table_spacing=0.018, floor_spacing=0.06,
                        floor_size=2.0, floaters=8, boundary_blobs=6),
    "default": SynthConfig(),
    "large": SynthConfig(num_cameras=60, width=640, height=480, object_spacing=0.0015,
                         table_spacing=0.003, floor_spacing=0.01, floaters=120, boundary_blobs=48),
    # a crowded scene: 30 objects (categories repeat) on a 2 m × 1.4 m table, cameras further out
    "crowded": SynthConfig(num_objects=(30, 30), num_cameras=48, rings=((2.0, 1.6), (1.6, 2.1), (2.4, 1.3)),
                           width=480, height=360, floor_size=5.0, table_top=(2.0, 1.4), floaters=80,
                           boundary_blobs=12),
}


@dataclasses.dataclass(frozen=True)
class PlacedObject:
    id: int
    shape: shapes.ObjectShape
    pose: np.ndarray  # (4, 4) canonical → world

    def world_mesh(self):
        mesh = self.shape.mesh.copy()
        mesh.apply_transform(self.pose)
        return mesh


def place_objects(rng, config: SynthConfig, furniture: shapes.Furniture, seed: int,
                  keep_clear: tuple[tuple[np.ndarray, float], ...] = ()) -> list[PlacedObject]:
    """Non-overlapping random placements and yaws on the tabletop (rejection sampling), clear of
    the (centre (2,), radius) discs in ``keep_clear``."""
    count = int(rng.integers(config.num_objects[0], config.num_objects[1] + 1))
    categories = (list(rng.permutation(shapes.CATEGORIES))[:count] if count <= len(shapes.CATEGORIES)
                  else list(rng.choice(shapes.CATEGORIES, count)))   # more objects than categories: repeats
    placed: list[tuple[np.ndarray, float]] = list(keep_clear)
    objects = []
    half = furniture.top_extent / 2 - TABLE_MARGIN
    for index, category in enumerate(categories):
        shape = shapes.make_object(category, rng, seed * 100 + index)
        radius = float(np.max(np.linalg.norm(shape.mesh.vertices[:, :2], axis=1)))
        for _ in range(1000):
            xy = rng.uniform(-half + radius, half - radius)
            if all(np.linalg.norm(xy - c) > radius + r + PLACEMENT_GAP for c, r in placed):
                break
        else:
            raise RuntimeError(f"could not place {category} without overlap (seed {seed})")
        placed.append((xy, radius))
        yaw = rng.uniform(0, 2 * np.pi)
        pose = np.eye(4)
        pose[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
        pose[:3, 3] = [xy[0], xy[1], furniture.table_top_z]
        objects.append(PlacedObject(index + 1, shape, pose))
    return objects


def ring_cameras(config: SynthConfig, rng, target_z: float) -> list[Camera]:
    """Cameras on rings around the table, looking at jittered points over the tabletop."""
    per_ring = np.full(len(config.rings), config.num_cameras // len(config.rings))
    per_ring[: config.num_cameras % len(config.rings)] += 1
    focal = 0.5 * config.width / np.tan(np.deg2rad(config.fov_deg) / 2)
    K = intrinsics_matrix(focal, focal, config.width / 2, config.height / 2)
    cameras = []
    for (radius, height), n in zip(config.rings, per_ring):
        offset = rng.uniform(0, 2 * np.pi)
        for angle in offset + np.linspace(0, 2 * np.pi, n, endpoint=False):
            eye = np.array([radius * np.cos(angle), radius * np.sin(angle), height])
            target = np.array([*rng.uniform(-0.1, 0.1, 2), target_z])
            cameras.append(Camera(name=f"{len(cameras):04d}.png", K=K,
                                  world_to_camera=look_at(eye, target),
                                  width=config.width, height=config.height))
    return cameras


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(4, 4) world-to-camera, OpenCV axes (x right, y down, z forward)."""
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rot = np.stack([right, down, forward])
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, -rot @ eye
    return out


def _inside_footprint(points_xy: np.ndarray, obj: PlacedObject) -> np.ndarray:
    """Which tabletop points lie under the object's contact patch (convex hull of its low vertices)."""
    from scipy.spatial import Delaunay

    verts = obj.world_mesh().vertices
    low = verts[verts[:, 2] < obj.pose[2, 3] + CONTACT_HEIGHT][:, :2]
    if len(low) < 3:
        return np.zeros(len(points_xy), bool)
    return Delaunay(low).find_simplex(points_xy) >= 0


@dataclasses.dataclass(frozen=True)
class SyntheticScene:
    config: SynthConfig
    seed: int
    furniture: shapes.Furniture
    objects: list[PlacedObject]
    capture: LabelledGaussians      # what the "reconstruction" holds
    background: LabelledGaussians   # true background, hidden tabletop included
    cameras: list[Camera]
    marker: PrintedMarker | None = None


def build_scene(preset: str = "default", seed: int = 0, marker: float = 0.0) -> SyntheticScene:
    """Geometry, Gaussians and cameras of one synthetic scene (no files, no rendering); ``marker``
    > 0: an ArUco marker of that side (metres) printed on the table top (``synthetic.marker``)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r} (expected one of {sorted(PRESETS)})")
    config = PRESETS[preset]
    rng = np.random.default_rng(seed)
    furniture = shapes.make_furniture(floor_size=config.floor_size, top=config.table_top)
    printed = (place_marker(marker, furniture.top_extent, furniture.table_top_z, TABLE_MARGIN) if marker > 0
               else None)
    clear = () if printed is None else ((printed.centre[:2], printed.sheet / np.sqrt(2)),)
    objects = place_objects(rng, config, furniture, seed, clear)

    parts, hidden_parts = [], []
    for mesh, colour, spacing in ((furniture.floor, shapes.floor_colour, config.floor_spacing),
                                  (furniture.table, shapes.table_colour, config.table_spacing)):
        pts, normals = sample_surface(mesh, spacing, rng)
        keep = pts[:, 2] > -0.005  # only the upper side of the floor slab is ever visible
        pts, normals = pts[keep], normals[keep]
        g = surface_gaussians(pts, normals, colour, pts, spacing, 0, 0.02, rng)
        hidden = np.zeros(len(pts), bool)
        on_top = np.abs(pts[:, 2] - furniture.table_top_z) < 1e-6
        for obj in objects:
            hidden[on_top] |= _inside_footprint(pts[on_top, :2], obj)
        if printed is not None:  # the sheet replaces the table top under it
            under = np.zeros(len(pts), bool)
            under[on_top] = printed.covers(pts[on_top, :2])
            g, hidden = g.subset(~under), hidden[~under]
        parts.append(g)
        hidden_parts.append(hidden)
    if printed is not None:
        parts.append(printed.gaussians(rng))
        hidden_parts.append(np.zeros(parts[-1].data.num, bool))
    background = LabelledGaussians.concatenate(parts)
    hidden = np.concatenate(hidden_parts)

    object_parts = []
    for obj in objects:
        pts_c, normals_c = sample_surface(obj.shape.mesh, config.object_spacing, rng)
        rot, trans = obj.pose[:3, :3], obj.pose[:3, 3]
        object_parts.append(surface_gaussians(pts_c @ rot.T + trans, normals_c @ rot.T, obj.shape.colour,
                                              pts_c, config.object_spacing, obj.id, obj.shape.shininess, rng))
        # blurry, low-opacity Gaussians straddling the object/table contact line
        verts = obj.world_mesh().vertices
        ring = verts[verts[:, 2] < trans[2] + 0.01]
        if len(ring) and config.boundary_blobs:
            picks = ring[rng.integers(len(ring), size=config.boundary_blobs)]
            colour = 0.5 * obj.shape.colour(picks @ rot - trans @ rot) + 0.5 * np.array([0.55, 0.37, 0.22])
            object_parts.append(blob_gaussians(picks + [0, 0, 0.003], rng.uniform(0.006, 0.012, len(picks)),
                                               colour, rng.uniform(0.12, 0.3, len(picks)), obj.id))
    floaters = blob_gaussians(
        rng.uniform([-0.8, -0.8, 0.8], [0.8, 0.8, 1.5], size=(config.floaters, 3)),
        rng.uniform(0.005, 0.02, config.floaters), rng.uniform(0.2, 0.9, (config.floaters, 3)),
        rng.uniform(0.15, 0.5, config.floaters), 0)
    capture = LabelledGaussians.concatenate([background.subset(~hidden), *object_parts, floaters])
    cameras = ring_cameras(config, rng, furniture.table_top_z + 0.08)
    return SyntheticScene(config, seed, furniture, objects, capture, background, cameras, printed)


def surface_mesh(scene: SyntheticScene):
    import trimesh

    return trimesh.util.concatenate([scene.furniture.floor, scene.furniture.table,
                                     *[o.world_mesh() for o in scene.objects]])


def ground_truth_json(scene: SyntheticScene) -> list[dict]:
    return [{"id": o.id, "category": o.shape.category,
             "mesh": f"gt/objects/{o.id}/world.obj", "canonical_mesh": f"gt/objects/{o.id}/canonical.obj",
             "pose": o.pose.round(12).tolist()} for o in scene.objects]


def write_mesh(path: Path, mesh) -> None:
    """Mesh file written atomically (format from the suffix)."""
    data = mesh.export(file_type=path.suffix[1:])
    write_bytes(path, data.encode() if isinstance(data, str) else data)


def write_ground_truth(scene: SyntheticScene, out: Path) -> None:
    for o in scene.objects:
        write_mesh(out / "gt" / "objects" / str(o.id) / "canonical.obj", o.shape.mesh)
        write_mesh(out / "gt" / "objects" / str(o.id) / "world.obj", o.world_mesh())
    write_text(out / TRUTH_OBJECTS, json.dumps(ground_truth_json(scene), indent=2))
    write_gaussian_ply(out / "gt" / "background.ply", scene.background.data)
    if scene.marker is not None:
        write_text(out / MARKER_TRUTH, json.dumps([scene.marker.truth()], indent=2))
    buf = io.BytesIO()
    np.save(buf, scene.capture.labels)
    write_bytes(out / "gt" / "labels.npy", buf.getvalue())


def write_png(path: Path, image: np.ndarray) -> None:
    """PNG written atomically; float rgb in [0, 1] → 8-bit, uint16 stays 16-bit."""
    import cv2

    if image.dtype != np.uint16:
        image = np.clip(np.round(np.asarray(image) * 255.0), 0, 255).astype(np.uint8)
        if image.ndim == 3:
            image = image[..., ::-1]  # RGB → OpenCV's BGR
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError(f"PNG encoding failed for {path}")
    write_bytes(path, buf.tobytes())


def render_views(scene: SyntheticScene, progress=None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """RGB images (H, W, 3) in [0, 1] and 16-bit instance masks (H, W) for every camera.

    Masks come from per-Gaussian labels rendered as one-hot features: a pixel gets
    instance k where k's accumulated weight is the largest and covers at least half
    of the pixel (MASK_COVERAGE), else 0.
    """
    import jax.numpy as jnp

    from phirie_jax.render import render

    gaussians = scene.capture.data.to_kernel()
    ids = np.array([0] + [o.id for o in scene.objects])
    one_hot = jnp.asarray(scene.capture.labels[:, None] == ids[None, 1:], jnp.float32)
    background = jnp.asarray(scene.config.background_rgb, jnp.float32)
    images, masks = [], []
    for cam in scene.cameras:
        out = render(gaussians, cam, background=background, features=one_hot)
        weights = np.asarray(out.features)
        best = np.argmax(weights, axis=-1)
        covered = np.take_along_axis(weights, best[..., None], axis=-1)[..., 0] >= MASK_COVERAGE
        images.append(np.asarray(out.rgb))
        masks.append(np.where(covered, ids[1:][best], 0).astype(np.uint16))
        if progress is not None:
            progress()
    return images, masks


def synthesize(out_dir: str | Path, preset: str = "default", seed: int = 0, progress=None,
               marker: float = 0.0) -> SyntheticScene:
    """Build, render and write one synthetic scene folder (see the module docstring); ``marker``
    > 0 prints a marker of that side (metres) on the table top."""
    out = Path(out_dir)
    scene = build_scene(preset, seed, marker)
    images, masks = render_views(scene, progress)
    for cam, image, mask in zip(scene.cameras, images, masks):
        write_png(out / "images" / cam.name, image)
        write_png(out / "masks" / cam.name, mask)
    data = scene.capture.data
    rng = np.random.default_rng(seed + 7)
    picks = rng.choice(data.num, size=min(SPARSE_POINTS, data.num), replace=False)
    colours = np.clip(data.sh[picks, 0] * 0.28209479177387814 + 0.5, 0, 1)
    write_colmap_text(out / "sparse" / "0", scene.cameras, points=data.means[picks],
                      colors=np.round(colours * 255).astype(np.uint8))
    write_transforms_json(out / "transforms.json", scene.cameras)
    write_gaussian_ply(out / "point_cloud.ply", data)
    write_mesh(out / "surface.ply", surface_mesh(scene))
    write_text(out / SCENE_FRAME_FILE, json.dumps({"metric": True, "up": "+z"}) + "\n")
    write_ground_truth(scene, out)
    return scene
