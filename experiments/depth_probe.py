"""Which rendered depth lands on a concave object's floor: the alpha-weighted mean, the median
(accumulated opacity first past 0.5) or a higher quantile, against the true depth.

    python -m experiments.depth_probe /tmp/gsplat_scenes/default2001_gsplat_default:2 \
        /tmp/gsplat_scenes/default2002_gsplat_default:1 --out experiments/results/depth_probe_gsplat.json

Each argument is a synthetic scene folder (with gt/) and the id of a true object with an inner
floor (a bowl, a mug). Points on the top of that floor (true mesh samples within ``FLOOR_RADIUS``
of the object's axis, within ``FLOOR_BAND`` of the highest such sample) are projected into every
training camera, at the observation's working width, that sees them unoccluded by the true mesh;
the Gaussians the splat-derived surface renders (``observe.floaters.surface_gaussians``) are
composited at that pixel one by one in depth order with the rasterizer's rules (a slow, per-pixel
reference of ``kernels.composite``), and each depth is compared with the true view depth of the
floor point. Negative: in front of the floor (towards the camera), in metres along the view axis.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

FLOOR_RADIUS = 0.03   # m: floor samples this close to the object's vertical axis
FLOOR_BAND = 0.002    # m: ... and this close to the highest of them (the floor's top)
FLOOR_POINTS = 50     # floor points per object
PIXELS_PER_VIEW = 10  # probed pixels per camera
MIN_VISIBLE = 5       # a camera is used when it sees at least this many floor points
OCCLUSION_TOL = 0.003  # m: a floor point is seen when the true mesh's first hit is this close to it
QUANTILES = (0.5, 0.7, 0.9, 0.95)  # accumulated opacity: 0.5 is the median depth


def composite_pixel(pixel, means2d, conics, opacities, depths):
    """Slow reference of one pixel: Gaussians (rows, already in depth order) composited front to
    back with ``kernels.composite``'s rules. → (expected depth, {quantile: depth}, alpha)."""
    from kernels.composite import ALPHA_MAX, T_MIN
    from kernels.project import ALPHA_MIN

    d = pixel[None] - means2d
    sigma = -0.5 * (conics[:, 0] * d[:, 0] ** 2 + conics[:, 2] * d[:, 1] ** 2) - conics[:, 1] * d[:, 0] * d[:, 1]
    alpha = np.minimum(opacities * np.exp(sigma), ALPHA_MAX)
    trans, weighted = 1.0, 0.0
    at = dict.fromkeys(QUANTILES, np.nan)
    for j in np.flatnonzero(alpha >= ALPHA_MIN):
        after = trans * (1.0 - alpha[j])
        if after < T_MIN:
            break
        weighted += alpha[j] * trans * depths[j]
        for q in QUANTILES:
            if np.isnan(at[q]) and trans >= 1.0 - q > after:
                at[q] = depths[j]
        trans = after
    alpha_sum = 1.0 - trans
    return weighted / max(alpha_sum, 1e-10), at, alpha_sum


def probe(scene_dir: Path, truth_id: int) -> dict:
    import jax.numpy as jnp
    import trimesh

    from kernels.project import project_gaussians
    from phirie_jax.io.scene import load_scene
    from phirie_jax.observe.config import ObserveConfig
    from phirie_jax.observe.floaters import surface_gaussians
    from phirie_jax.observe.stage import working_camera

    scene = load_scene(scene_dir)
    config = ObserveConfig()
    gaussians = surface_gaussians(scene.require_gaussians(), config.surface.floaters)[0].to_kernel()
    truth = next(o for o in json.loads((scene_dir / "gt" / "objects.json").read_text()) if o["id"] == truth_id)
    mesh = trimesh.load(scene_dir / truth["mesh"], force="mesh")
    axis = np.asarray(truth["pose"], np.float64)[:3, 3]
    samples, _ = trimesh.sample.sample_surface(mesh, 40000, seed=0)
    floor = samples[np.linalg.norm(samples[:, :2] - axis[:2], axis=1) < FLOOR_RADIUS]
    floor = floor[floor[:, 2] > floor[:, 2].max() - FLOOR_BAND][:FLOOR_POINTS]
    rays = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)
    errors = {"expected": [], **{f"q{q}": [] for q in QUANTILES}}
    alphas, views = [], 0
    for camera in scene.cameras:
        cam = working_camera(camera, config.working_width)
        w2c = np.asarray(cam.world_to_camera, np.float64)
        centre = np.linalg.inv(w2c)[:3, 3]
        in_cam = floor @ w2c[:3, :3].T + w2c[:3, 3]
        uv = in_cam @ np.asarray(cam.K, np.float64).T
        uv = uv[:, :2] / uv[:, 2:3]
        inside = (in_cam[:, 2] > 0) & np.all((uv >= 0) & (uv < [cam.width, cam.height]), axis=1)
        dirs = floor - centre
        dist = np.linalg.norm(dirs, axis=1)
        hits, ray_ids, _ = rays.intersects_location(np.repeat(centre[None], len(floor), 0), dirs / dist[:, None],
                                                    multiple_hits=False)
        first = np.full(len(floor), np.inf)
        first[ray_ids] = np.linalg.norm(hits - centre, axis=1)
        seen = np.flatnonzero(inside & (first > dist - OCCLUSION_TOL))
        if len(seen) < MIN_VISIBLE:
            continue
        views += 1
        proj = project_gaussians(gaussians, jnp.asarray(cam.K, jnp.float32), jnp.asarray(w2c, jnp.float32),
                                 width=cam.width, height=cam.height)
        visible = np.asarray(proj.visible)
        depths = np.asarray(proj.depths, np.float64)
        order = np.argsort(np.where(visible, depths, np.inf), kind="stable")
        order = order[visible[order]]
        rows = [np.asarray(x, np.float64)[order] for x in (proj.means2d, proj.conics, proj.opacities, proj.depths)]
        for k in seen[:PIXELS_PER_VIEW]:
            expected, at, alpha = composite_pixel(np.floor(uv[k]) + 0.5, *rows)
            errors["expected"].append(expected - in_cam[k, 2])
            for q in QUANTILES:
                errors[f"q{q}"].append(at[q] - in_cam[k, 2])
            alphas.append(alpha)

    def summary(values):
        v = np.asarray(values)
        v = v[np.isfinite(v)]
        return {"pixels": len(v), **{f"p{p}_cm": round(float(np.percentile(v, p)) * 100, 2) for p in (10, 50, 90)}}

    return {"scene": str(scene_dir), "object": truth_id, "category": truth.get("category"), "views": views,
            "alpha_median": round(float(np.median(alphas)), 4) if alphas else None,
            "depth_minus_true": {name: summary(v) for name, v in errors.items()}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("objects", nargs="+", help="SCENE_DIR:TRUE_OBJECT_ID")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    from experiments.report import emit

    rows = []
    for item in args.objects:
        folder, _, ident = item.rpartition(":")
        rows.append(probe(Path(folder), int(ident)))
        print(json.dumps(rows[-1]), flush=True)
    emit({"what": __doc__.split("\n\n")[2].strip(), "quantiles": QUANTILES, "probes": rows}, args.out)


if __name__ == "__main__":
    main()
