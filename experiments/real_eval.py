"""Convert a real capture without ground truth and score it the paper's way (its table 4).

    python -m experiments.real_eval CAPTURE [--masks FOLDER|auto|files] [--box x0 y0 z0 x1 y1 z1]
        [--box-prompt FILE] [--prompts FILE] [--hold-out-every 8] [--out DIR] [--name NAME] [--width W]
        [--up ...] [--scale ...] [--known-size ID=METRES] [--metric] [--config.STAGE.FIELD VALUE ...]

1. Every ``--hold-out-every``-th image in file (name) order is held out. A working copy of
   the capture (symlinked images and Gaussians, a filtered ``transforms.json``, masks of the
   training views only) is what gets converted, so no stage ever sees a held-out view.
   ``--box`` (axis-aligned, capture frame) or ``--box-prompt`` (a JSON like the fox fixture's
   ``box_prompt.json``) makes instance masks (``phirie_jax.observe.box_prompt``) for the
   training views (then ``--masks`` defaults to ``files``) and for the held-out ones (scoring).
   ``--prompts`` (a ``prompts.json``-format file of boxes or clicks in training photos, e.g.
   ``experiments/prompts/fox.json``) is passed to ``phirie convert`` as its prompts
   (``observe.prompts``); the held-out masks are then the prompts' objects rendered at the
   held-out cameras (the Gaussians each prompt took, ``observe/prompts.npz``, as one feature
   channel each, like the training views' masks).
2. Visual cost of conversion at the held-out photos: PSNR/SSIM of (a) the converted initial
   state — ``background.ply`` plus every accepted object's ``visual.ply`` placed at its
   ``pose`` — seen by the held-out camera moved into the output's world frame (manifest
   ``frame.capture_to_world``, a Sim(3) x_w = s R x_c + t: world-to-camera rotation E_R Rᵀ,
   translation s E_t − E_R Rᵀ t; identity without a frame), and (b) the source Gaussians seen
   by the original camera; and (a) − (b).
3. The frame against the capture's hand-found truth (``tests/fixtures/frame_truth.json``), when
   it has one: up's error, the scale over the truth's, whether the truth is inside the band.
4. Per object: silhouette IoU (its placed Gaussians alone, alpha ≥ 0.5) against its instance
   mask in the held-out views, the drop test, the scale of its pose and the frame's scale source.
5. Stage timings (manifest) and peak memory (getrusage, self and children).

Prints the result as JSON and writes ``experiments/results/real_eval_<NAME>.json``.
Frame options (``--up``, ``--scale``, ``--known-size``, ``--known-distance``, ``--metric``) and
``--config.*`` options are those of ``phirie convert``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import shutil
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

from phirie_jax.frame.resolve import world_camera
from phirie_jax.io.scene import find_gaussians, load_scene
from phirie_jax.manifest import Manifest
from phirie_jax.observe.box_prompt import BoxPrompt, box_masks, encode_png
from phirie_jax.records import FrameRecord, ObjectRecord, plain
from phirie_jax.types import Camera

RESULTS = Path(__file__).resolve().parent / "results"
FRAME_TRUTH = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "frame_truth.json"   # hand-found
MIN_ALPHA = 0.5          # a rendered pixel belongs to an object's silhouette from this alpha


# --- the working copy ----------------------------------------------------------------------


def held_out_split(cameras: tuple[Camera, ...], every: int) -> tuple[list[Camera], list[Camera]]:
    """(training, held out): camera k (name order) is held out when k % every == 0."""
    if every < 2:
        raise ValueError(f"--hold-out-every {every}: expected ≥ 2")
    return ([c for k, c in enumerate(cameras) if k % every != 0],
            [c for k, c in enumerate(cameras) if k % every == 0])


def working_copy(capture: Path, held_out: list[Camera], folder: Path) -> Path:
    """A copy of ``capture`` without the held-out views: symlinked Gaussians, images and masks,
    a filtered transforms.json. Only nerfstudio-layout captures are supported."""
    meta_path = capture / "transforms.json"
    if not meta_path.is_file():
        raise SystemExit(f"{capture}: real_eval needs a transforms.json capture (held-out views are "
                         "filtered from it)")
    hidden = {c.image_path.resolve() for c in held_out}
    meta = json.loads(meta_path.read_text())
    kept = []
    for frame in meta.get("frames", []):
        image = (capture / frame["file_path"]).resolve()
        if not image.is_file():
            image = next((image.with_name(image.name + e) for e in (".png", ".jpg", ".jpeg")
                          if image.with_name(image.name + e).is_file()), image)
        if image in hidden:
            continue
        kept.append(frame)
        target = folder / frame["file_path"]
        if image.suffix != target.suffix:
            target = target.with_name(target.name + image.suffix)
        target.parent.mkdir(parents=True, exist_ok=True)
        if not target.exists():
            target.symlink_to(image)
    meta["frames"] = kept
    meta.pop("test_frames", None)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "transforms.json").write_text(json.dumps(meta, indent=1))
    gaussians = find_gaussians(capture)
    if gaussians is None:
        raise SystemExit(f"{capture}: no Gaussian PLY found")
    (folder / "point_cloud.ply").symlink_to(gaussians.resolve())
    if (capture / "masks").is_dir():
        (folder / "masks").mkdir(exist_ok=True)
        for p in sorted((capture / "masks").iterdir()):
            if p.suffix == ".png" and p.stem not in {Path(c.name).stem for c in held_out}:
                (folder / "masks" / p.name).symlink_to(p.resolve())
    return folder


def write_prompt_masks(gaussians, cameras: list[Camera], boxes: list[BoxPrompt], folder: Path) -> None:
    """Box-prompt masks of ``cameras`` into ``folder`` (replacing any linked there)."""
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    for view, labels in box_masks(gaussians, cameras, boxes):
        if not isinstance(labels, str):
            (folder / f"{Path(cameras[view].name).stem}.png").write_bytes(encode_png(labels))


def read_prompt(path: Path) -> BoxPrompt:
    data = json.loads(Path(path).read_text())
    rotation = data.get("rotation")
    return BoxPrompt(int(data.get("id", 1)), tuple(data["lower"]), tuple(data["upper"]),
                     None if rotation is None else tuple(tuple(r) for r in rotation))


# --- frames, rendering, metrics ------------------------------------------------------------


def capture_to_world(manifest: Manifest) -> np.ndarray:
    """(4, 4) the manifest's ``frame.capture_to_world`` Sim(3); identity when there is none."""
    matrix = manifest.capture_to_world()
    return np.eye(4) if matrix is None else matrix


def read_photo(camera: Camera, width: int | None) -> np.ndarray:
    """(H, W, 3) float32 RGB in [0, 1] of the camera's image (resized with INTER_AREA to ``width``)."""
    import cv2

    image = cv2.imread(str(camera.image_path), cv2.IMREAD_COLOR)
    if image is None:
        raise SystemExit(f"{camera.image_path}: not a readable image")
    if width is not None and width != camera.width:
        size = camera.scaled(width / camera.width)
        image = cv2.resize(image, (size.width, size.height), interpolation=cv2.INTER_AREA)
    return image[..., ::-1].astype(np.float32) / 255.0


def image_scores(rendered: np.ndarray, photo: np.ndarray) -> dict:
    import jax.numpy as jnp

    from kernels.image_metrics import psnr, ssim

    a, b = jnp.asarray(np.clip(rendered, 0.0, 1.0), jnp.float32), jnp.asarray(photo, jnp.float32)
    return {"psnr": round(float(psnr(a, b)), 3), "ssim": round(float(ssim(a, b)), 4)}


def converted_scene(out_dir: Path, manifest: Manifest):
    """(background + placed objects as one kernel set, {object id: its placed kernel set})."""
    import jax.numpy as jnp

    from kernels.gaussians import Gaussians, Sim3, concatenate, transform_gaussians
    from phirie_jax import layout
    from phirie_jax.io.ply import read_gaussian_ply

    background = read_gaussian_ply(out_dir / layout.BACKGROUND)
    degree_k = background.sh.shape[1]
    parts, placed = [background.to_kernel()], {}
    for obj in manifest.kept_objects():
        if not obj.visual:
            continue
        splats = read_gaussian_ply(layout.resolve(out_dir, obj.visual))
        sh = np.zeros((splats.num, degree_k, 3), np.float32)
        sh[:, : min(degree_k, splats.sh.shape[1])] = splats.sh[:, :degree_k]
        k = splats.to_kernel()
        g = Gaussians(k.means, k.quats, k.log_scales, k.opacity_logits, jnp.asarray(sh))
        moved = transform_gaussians(g, Sim3.from_matrix(jnp.asarray(obj.pose, jnp.float32)))
        placed[obj.id] = moved
        parts.append(moved)
    return concatenate(parts), placed


def instance_mask(source: dict, camera: Camera, instance_id: int, width: int | None) -> np.ndarray | None:
    """(H, W) bool: the instance in a held-out view, from the evaluation's masks (None: no mask)."""
    import cv2

    labels = source.get(camera.name)
    if labels is None:
        return None
    if width is not None and labels.shape[1] != width:
        height = camera.scaled(width / camera.width).height
        labels = cv2.resize(labels.astype(np.uint16), (width, height), interpolation=cv2.INTER_NEAREST)
    return labels == instance_id


def prompt_held_out_masks(out: Path, scene, held_out: list[Camera]) -> dict:
    """Held-out view name → (H, W) labels of the prompts' objects: the Gaussians each prompt took
    (``observe/prompts.npz``, rows of the capture's PLY) rendered with one feature channel per
    prompt at the held-out cameras, labelled like the conversion's own prompt masks."""
    from phirie_jax.observe.config import ObserveConfig
    from phirie_jax.observe.prompt_masks import PROMPT_RECORD, owner_labels
    from phirie_jax.render import render

    path = out / PROMPT_RECORD
    if not path.is_file():
        return {}
    with np.load(path) as data:
        rows, owner = data["rows"], data["owner"]
    gaussians = scene.require_gaussians()
    ids = sorted(int(k) for k in np.unique(owner))
    features = np.zeros((gaussians.num, len(ids)), np.float32)
    features[rows, np.searchsorted(ids, owner)] = 1.0
    config = ObserveConfig().prompts
    found = {}
    for cam in held_out:
        result = render(gaussians.to_kernel(), cam, features=features)
        found[cam.name] = owner_labels(np.asarray(result.features, np.float64), np.asarray(result.alpha, np.float64),
                                       ids, config).astype(np.int64)
    return found


def held_out_masks(args, capture: Path, scene, held_out: list[Camera], boxes: list[BoxPrompt],
                   out: Path | None = None) -> dict:
    """Held-out view name → (H, W) labels, from the box prompt, the prompts' objects, else the
    given mask folder."""
    from phirie_jax.observe.masks import read_label_png

    if args.prompts is not None:
        return prompt_held_out_masks(out, scene, held_out)
    if boxes:
        return {held_out[v].name: labels.astype(np.int64) for v, labels in
                box_masks(scene.require_gaussians(), held_out, boxes) if not isinstance(labels, str)}
    folder = {"files": capture / "masks", "auto": None}.get(str(args.masks), Path(str(args.masks)))
    found = {}
    for cam in held_out:
        path = None if folder is None else folder / f"{Path(cam.name).stem}.png"
        if path is not None and path.is_file():
            found[cam.name] = read_label_png(path, cam)
    return found


# --- the run -------------------------------------------------------------------------------


def convert_options(rest: list[str]):
    """(ConvertConfig from ``--config.*``, FrameConfig from the frame options), parsed like
    ``phirie convert``'s."""
    import tyro

    from phirie_jax.frame.config import FrameConfig
    from phirie_jax.pipeline import ConvertConfig

    frame_args, config_args, i = [], [], 0
    while i < len(rest):
        arg = rest[i]
        target = config_args if arg.startswith("--config.") else frame_args
        if arg.startswith("--config."):
            arg = "--" + arg[len("--config."):]
        target.append(arg)
        i += 1
        while i < len(rest) and not rest[i].startswith("--"):
            target.append(rest[i])
            i += 1
    config = tyro.cli(ConvertConfig, args=config_args, default=ConvertConfig()) if config_args else ConvertConfig()
    frame = tyro.cli(FrameConfig, args=frame_args, default=FrameConfig()) if frame_args else FrameConfig()
    return config, frame.checked()


def peak_memory_mb() -> dict:
    kb = 1024.0 if platform.system() != "Darwin" else 1024.0 * 1024.0
    return {"self_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / kb, 1),
            "children_mb": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / kb, 1)}


def evaluate(args, rest: list[str]) -> dict:
    import jax

    from phirie_jax.pipeline import run_convert
    from phirie_jax.render import render

    capture = Path(args.capture).resolve()
    config, frame_options = convert_options(rest)
    scene = load_scene(capture)
    training, held_out = held_out_split(scene.require_cameras(), args.hold_out_every)
    boxes = []
    if args.box is not None:
        boxes.append(BoxPrompt.from_corners(1, args.box))
    if args.box_prompt is not None:
        boxes.append(read_prompt(args.box_prompt))
    prompts = ()
    if args.prompts is not None:
        from phirie_jax.observe.prompts import read_prompts_file

        prompts = tuple(read_prompts_file(args.prompts))
        hidden = {c.name for c in held_out} | {Path(c.name).stem for c in held_out}
        for p in prompts:
            if p.image in hidden:
                raise SystemExit(f"{args.prompts}: prompt on {p.image}, a held-out view (expected a training photo)")
        if boxes or args.masks:
            raise SystemExit("--prompts is a mask source of its own (expected no --box, --box-prompt or --masks)")
    masks = args.masks or (None if prompts else "files" if boxes or scene.masks is not None else "auto")

    work = Path(tempfile.mkdtemp(prefix="real_eval_"))
    out = Path(args.out) if args.out else work / "out"
    if out.exists():
        shutil.rmtree(out)
    result: dict = {"capture": str(capture), "held_out": [c.name for c in held_out],
                    "scored_width": args.width or "full size", "training_views": len(training), "masks": str(masks),
                    "boxes": [{"id": b.id, "lower": b.lower, "upper": b.upper, "rotation": b.rotation} for b in boxes],
                    "prompts": [p.as_json() for p in prompts],
                    "frame_options": dataclasses.asdict(frame_options), "out": str(out)}
    try:
        copy = working_copy(capture, held_out, work / "capture")
        if boxes:
            t0 = time.perf_counter()
            write_prompt_masks(scene.require_gaussians(), training, boxes, copy / "masks")
            result["box_masks_s"] = round(time.perf_counter() - t0, 2)
        t0 = time.perf_counter()
        try:
            run_convert(copy, out, config, masks=masks, frame=frame_options, prompts=prompts,
                        allow_outside_paths=True)   # the working copy links the capture's files
            manifest = Manifest.load(out)
            result["convert"] = {"ok": True, "wall_s": round(time.perf_counter() - t0, 2)}
        except Exception as err:  # noqa: BLE001 — recorded: the source is still scored
            result["convert"] = {"ok": False, "wall_s": round(time.perf_counter() - t0, 2),
                                 "error": f"{type(err).__name__}: {err}",
                                 "traceback": traceback.format_exc()[-3000:]}
            manifest = None

        sources = scene.require_gaussians().to_kernel()
        eval_masks = held_out_masks(args, capture, scene, held_out, boxes, out)
        sim3 = capture_to_world(manifest or Manifest(out))
        converted, placed = (converted_scene(out, manifest) if manifest and (out / "background.ply").is_file()
                             else (None, {}))
        views, ious = [], {i: [] for i in placed}
        for cam in held_out:
            photo = read_photo(cam, args.width)
            row = {"view": cam.name, "source": image_scores(np.asarray(render(sources, cam, width=args.width).rgb),
                                                              photo)}
            if converted is not None:
                world_cam = world_camera(cam, sim3)
                row["converted"] = image_scores(np.asarray(render(converted, world_cam, width=args.width).rgb), photo)
                row["difference_db"] = round(row["converted"]["psnr"] - row["source"]["psnr"], 3)
                for object_id, g in placed.items():
                    truth = instance_mask(eval_masks, cam, object_id, args.width)
                    if truth is None:
                        continue
                    ours = np.asarray(render(g, world_cam, width=args.width).alpha) >= MIN_ALPHA
                    union = int((ours | truth).sum())
                    if union:
                        ious[object_id].append(round(float((ours & truth).sum() / union), 4))
            views.append(row)
        result["views"] = views
        result["visual"] = summary(views)
        manifest = manifest or Manifest(out)
        frame = manifest.frame()
        result["frame"] = {k: plain(getattr(frame, k)) for k in ("capture_to_world", "up_source", "scale_source",
                                                                 "scale_uncertainty")} if frame is not None else None
        if frame is not None:
            result["frame_against_truth"] = frame_against_truth(capture.name, frame)
        result["instances"] = [{k: plain(getattr(i, k)) for k in ("id", "category", "views", "num_points", "bounds")}
                               for i in manifest.get("instances", ())]
        if prompts:
            result["prompt_lift"] = (manifest.get("observe") or {}).get("prompts")
        result["objects"] = [object_row(o, ious.get(o.id), frame) for o in manifest.get("objects", ())]
        result["timings"] = manifest.timings.values or None
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    result["peak_memory"] = peak_memory_mb()
    result["machine"] = {"platform": platform.platform(), "jax_backend": jax.default_backend(),
                         "cpus": os.cpu_count(), "load_average_at_end": os.getloadavg()}
    return result


def object_row(obj: ObjectRecord, ious: list[float] | None, frame: FrameRecord | None) -> dict:
    pose = obj.pose
    return {"id": obj.id, "status": str(obj.status), "reason": obj.reason,
            "candidate": obj.candidate, "drop_test": obj.drop_test,
            "pose_scale": None if pose is None else round(float(np.cbrt(np.linalg.det(pose[:3, :3]))), 5),
            "scale_source": None if frame is None else frame.scale_source,
            "scale_uncertainty": None if frame is None else frame.scale_uncertainty,
            "silhouette_iou": ious, "silhouette_iou_mean": round(float(np.mean(ious)), 4) if ious else None}


def summary(views: list[dict]) -> dict:
    def mean(part: str, metric: str):
        values = [v[part][metric] for v in views if part in v]
        return round(float(np.mean(values)), 3) if values else None

    out = {"source_psnr": mean("source", "psnr"), "source_ssim": mean("source", "ssim"),
           "converted_psnr": mean("converted", "psnr"), "converted_ssim": mean("converted", "ssim")}
    if out["converted_psnr"] is not None:
        out["difference_db"] = round(out["converted_psnr"] - out["source_psnr"], 3)
        out["difference_ssim"] = round(out["converted_ssim"] - out["source_ssim"], 4)
    return out


def frame_against_truth(capture: str, frame: FrameRecord) -> dict | None:
    """The frame the conversion used against the capture's hand-found truth (``FRAME_TRUTH``,
    ``experiments/frame_eval.py``'s): up's error in degrees, the scale over the truth's and
    whether the truth lies inside the stated uncertainty. None for a capture without truth."""
    truth = json.loads(FRAME_TRUTH.read_text()).get(capture) if FRAME_TRUTH.is_file() else None
    if not isinstance(truth, dict) or frame.capture_up is None or frame.scale is None:
        return None
    up = np.asarray(truth["up"], np.float64)
    ours = np.asarray(frame.capture_up, np.float64)
    cosine = float(ours @ up / (np.linalg.norm(ours) * np.linalg.norm(up)))
    band = float(frame.scale_uncertainty or 1.0)
    return {"up_error_deg": round(float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))), 3),
            "up_tolerance_deg": truth.get("up_tolerance_deg"), "scale": frame.scale, "truth_scale": truth["scale"],
            "scale_over_truth": round(frame.scale / truth["scale"], 4),
            "truth_in_band": bool(frame.scale / band <= truth["scale"] <= frame.scale * band)}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("capture", type=Path)
    parser.add_argument("--masks", default=None, help="files | auto | FOLDER (default: files with a box "
                                                      "prompt or masks/, else auto)")
    parser.add_argument("--box", type=float, nargs=6, default=None, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                        help="axis-aligned box prompt (capture frame) for instance 1")
    parser.add_argument("--box-prompt", type=Path, default=None, help="JSON box prompt (id, lower, upper, rotation)")
    parser.add_argument("--prompts", type=Path, default=None, help="prompts.json-format file: boxes or clicks in "
                                                                  "training photos (phirie convert --prompt)")
    parser.add_argument("--hold-out-every", type=int, default=8)
    parser.add_argument("--out", type=Path, default=None, help="conversion output (default: a temporary folder)")
    parser.add_argument("--name", default=None, help="results name (default: the capture folder's name)")
    parser.add_argument("--width", type=int, default=None, help="score at this image width (default: full size)")
    parser.add_argument("--keep", action="store_true", help="keep the working copy")
    args, rest = parser.parse_known_args(argv)
    result = evaluate(args, rest)
    name = args.name or Path(args.capture).resolve().name
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"real_eval_{name}.json"
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(result, indent=1, default=float) + "\n")
    tmp.replace(path)
    print(json.dumps({k: v for k, v in result.items() if k != "views"}, indent=1, default=float))
    return result


if __name__ == "__main__":
    main()
