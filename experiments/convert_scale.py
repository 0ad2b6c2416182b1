"""Conversion at a capture's real size: wall time per stage and peak memory of the whole process
tree, for a capture as users bring it (no scan mesh, no masks: ``--masks auto``).

    python -m experiments.convert_scale --preset large --seed 11 --scene /tmp/large_scene \\
        --work /tmp/convert_scale --out experiments/results/convert_scale_cpu.json

The 30-object scene on one GPU (issue 30 §5; ``convert_scale_crowded_h100.json``):

    python -m experiments.convert_scale --preset crowded --seed 11 --scene /tmp/crowded_scene \\
        --work /tmp/convert_scale_crowded --out experiments/results/convert_scale_crowded_h100.json

The scene (a ``phirie synth`` folder, synthesized at ``--scene`` when missing) is linked as a
user's capture: without ``surface.ply``, ``masks/``, ``candidates/``, ``gt/`` and ``frame.json``
(up and scale are estimated). ``phirie
convert`` runs in a child process; every ``--sample-s`` the resident memory of it and all its
descendants is summed from /proc (CoACD workers and Open3D included), and the peak reported beside
the manifest's stage timings. Issue 14's targets on 2 cores: a 400K-Gaussian, 50-photo capture
converts in ≤ 10 minutes with a peak ≤ 6 GB; 5 M Gaussians convert on 24 GB.

``--resume STAGE ...`` runs only those stages (and the frame) again on the output of an earlier
run that failed after its observation: its wall time and peak memory are the resumed run's, the
manifest keeps the earlier stages' times.

``--densify K`` stands in for a capture trained to millions of Gaussians: every Gaussian is
replaced by K children (``densified``), so the scene and its images stay those of the preset.

Beside the timings: per object the collision's CoACD tier, threshold, parts, hull-volume ratio and
drop-test verdict, the collision workers and their OpenMP threads, and the background stage's XLA
compilations, crop renders, render launches and target frames.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

from phirie_jax.manifest import Manifest
from phirie_jax.synthetic.scene import PRESETS

# what a user's capture lacks, beside what discovery_eval leaves out: the truth and a declared frame
LEFT_OUT = ("surface.ply", "masks", "candidates", "gt", "frame.json")


def tree_rss_bytes(root: int) -> int:
    """Resident memory of ``root`` and its descendants (Linux /proc)."""
    parents: dict[int, int] = {}
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            try:
                fields = Path(entry.path, "stat").read_text().rsplit(")", 1)[1].split()
                parents[int(entry.name)] = int(fields[1])
            except (OSError, IndexError, ValueError):
                continue
    tree, frontier = {root}, [root]
    while frontier:
        parent = frontier.pop()
        children = [pid for pid, ppid in parents.items() if ppid == parent and pid not in tree]
        tree.update(children)
        frontier.extend(children)
    total = 0
    for pid in tree:
        try:
            for line in Path(f"/proc/{pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) * 1024
                    break
        except OSError:
            continue
    return total


def gpu_names() -> list[str]:
    """The machine's NVIDIA GPUs by name (``nvidia-smi``; none where it is absent). Asked of the
    driver, not of JAX: JAX in this process would take the GPU memory the conversion needs."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], check=False,
                             capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return []
    return [line.strip() for line in out.stdout.splitlines() if line.strip()] if out.returncode == 0 else []


def densified(data, copies: int, seed: int = 0):
    """``data`` with each Gaussian replaced by ``copies`` children: centres drawn inside the parent
    (N(0, (0.3 σ)²) along its axes), axes 0.9 σ, the parent's rotation, opacity and colour. The
    children overlap as the parent did, so renders stay close to the parent's."""
    import dataclasses

    import numpy as np

    from phirie_jax.rotations import quat_to_matrix

    n = data.num
    quats = data.quats.astype(np.float64)
    quats /= np.maximum(np.linalg.norm(quats, axis=1, keepdims=True), 1e-12)
    rot = quat_to_matrix(quats)                                             # (N, 3, 3)
    sigma = np.exp(data.log_scales.astype(np.float64))                      # (N, 3)
    rng = np.random.default_rng(seed)
    offsets = rng.normal(size=(copies, n, 3)) * 0.3 * sigma                # (K, N, 3) local
    means = data.means[None] + np.einsum("nij,knj->kni", rot, offsets)

    def repeat(a):
        return np.concatenate([a] * copies)

    return dataclasses.replace(
        data, means=means.reshape(-1, 3).astype(np.float32), quats=repeat(data.quats),
        log_scales=repeat(data.log_scales + np.float32(np.log(0.9))), opacity_logits=repeat(data.opacity_logits),
        sh=repeat(data.sh), extra={k: repeat(v) for k, v in data.extra.items()})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="large", choices=sorted(PRESETS))
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--scene", type=Path, default=Path("/tmp/convert_scale_scene"))
    parser.add_argument("--work", type=Path, default=Path("/tmp/convert_scale"))
    parser.add_argument("--sample-s", type=float, default=0.5)
    parser.add_argument("--densify", type=int, default=1, help="children per Gaussian (5 M from the large preset: 11)")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--resume", nargs="+", default=None, metavar="STAGE",
                        help="run only these stages (and the frame) on the existing capture and output of an "
                             "earlier run whose later stages failed; its manifest keeps the earlier stages' times")
    parser.add_argument("--config", nargs="+", default=(), metavar="FIELD=VALUE",
                        help="convert's config fields, e.g. objects.workers=1 (passed as --config.FIELD VALUE)")
    args = parser.parse_args()

    from experiments.discovery_eval import user_capture
    from experiments.report import emit
    from phirie_jax.io.ply import ply_element_counts

    # synthesized in a process of its own: JAX in this one would keep most of the GPU's memory for
    # the whole run, and the timed conversion would get the rest
    subprocess.run([sys.executable, "-c", ("import sys; from phirie_jax.synthetic.fitted import ensure_synthesized; "
                    "ensure_synthesized(sys.argv[1], sys.argv[2], int(sys.argv[3]))"),
                    str(args.scene), args.preset, str(args.seed)], check=True)
    scene = args.scene
    out = args.work / "out"
    if args.resume:
        capture = args.work / "capture"
        command = [sys.executable, "-c", ("import sys; from phirie_jax.pipeline import run_convert; "
                   "run_convert(sys.argv[1], sys.argv[2], masks='auto', stages=tuple(sys.argv[3:]), "
                   "allow_outside_paths=True)"),
                   str(capture), str(out), *args.resume]
    else:
        capture = user_capture(scene, args.work / "capture", LEFT_OUT)
        if args.densify > 1:
            from phirie_jax.io.ply import read_gaussian_ply, write_gaussian_ply

            (capture / "point_cloud.ply").unlink()
            write_gaussian_ply(capture / "point_cloud.ply",
                               densified(read_gaussian_ply(scene / "point_cloud.ply"), args.densify))
        shutil.rmtree(out, ignore_errors=True)
        # the capture links the synthesized scene's files: images outside its folder, read on purpose
        command = [sys.executable, "-m", "phirie_jax.cli", "convert", str(capture), "--out", str(out), "--masks", "auto",
                   "--allow-outside-paths"]
        for field in args.config:
            name, _, value = field.partition("=")
            command += [f"--config.{name}", value]
    start, peak = time.perf_counter(), 0
    child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    log: list[str] = []
    import threading

    reader = threading.Thread(target=lambda: log.extend(child.stdout), daemon=True)
    reader.start()
    while child.poll() is None:
        peak = max(peak, tree_rss_bytes(child.pid))
        time.sleep(args.sample_s)
    wall = time.perf_counter() - start
    reader.join(timeout=5)
    manifest = Manifest.load_or_create(out)   # empty when the run wrote none
    objects, timings = manifest.get("objects", ()), manifest.timings.values
    physics, background, frame = manifest.physics(), manifest.background(), manifest.frame()
    collisions = {o.id: o.physics["collision"] for o in objects if (o.physics or {}).get("collision")}
    by_id = {o.id: o for o in objects}
    transforms = json.loads((scene / "transforms.json").read_text())
    image = transforms["frames"][0]
    emit({"preset": args.preset, "seed": args.seed, "gaussians": ply_element_counts(capture / "point_cloud.ply")["vertex"],
          "densify": args.densify, "resumed_stages": args.resume, "config": list(args.config),
          "views": len(transforms["frames"]),
          "image": [image.get("w", transforms.get("w")), image.get("h", transforms.get("h"))],
          "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "gpus": gpu_names(),
                      "load_average_at_end": os.getloadavg()},
          "exit_code": child.returncode, "wall_s": round(wall, 1), "peak_rss_gb": round(peak / 2**30, 2),
          "stage_s": {k: round(v, 1) for k, v in timings.items() if "." not in k},
          "step_s": {k: round(v, 1) for k, v in timings.items() if "." in k},
          # of the whole wall; physics.collision runs beside the background stage, so shares overlap
          "stage_share": {k: round(v / wall, 3) for k, v in timings.items() if "." not in k},
          "collision_s_per_object": {str(i): round(c["total_time_s"], 1) for i, c in collisions.items()
                                     if c.get("total_time_s")},
          "collision_per_object": {str(i): {
              **{k: (c.get("coacd") or {}).get(k) for k in ("tier", "threshold")},
              "parts": c["parts"], "hull_volume_ratio": round(c["hull_volume_ratio"], 4),
              "stable": (by_id[i].drop_test or {}).get("stable")} for i, c in collisions.items()},
          "collision_workers": None if physics is None else physics.collision_workers,
          "background_compiles": None if background is None else background.extra.get("compiles"),
          "background_renders": {k: None if background is None else background.extra.get(k)
                                 for k in ("renders", "render_launches")},
          "background_frames": 0 if background is None else len((background.extra.get("targets") or {}).get("frames")
                                                                  or []),
          "frame": {k: None if frame is None else getattr(frame, k) for k in ("up_source", "scale", "scale_source")},
          "instances": len(manifest.get("instances", ())),
          "accepted": len(manifest.accepted_objects()),
          "output_tail": "".join(log[-15:])}, args.out)


if __name__ == "__main__":
    main()
