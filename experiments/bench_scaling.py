"""Scaling over devices (issue 29): one device against all of them, the same program; one JSON object.

Two workloads, each run on ``devices=1`` and on every device JAX sees, in this process:

- ``worlds``: ``--worlds`` worlds × ``--cameras`` cameras of a converted scene in
  ``interact.batched.BatchedEnvironment`` (the worlds spread over a 1-D mesh, ``kernels.sharding``):
  each world gets its own throw (seeded random velocities), then ``--steps`` steps per timed call
  (world-steps/s) and a render of every world from every camera per timed call (frames/s);
- ``steps``: the worlds' steps alone (no render, no comparison), for world counts whose
  render would not fit a call's time;
- ``droptests``: ``--candidates`` drop tests (the procedural agreement cases of
  ``bench_droptest``, one hull each, the paper's protocol) in the MJX batch program
  (``construct.physics.mjx_batch``, candidates spread over the mesh); and, with MuJoCo Warp
  installed and a GPU, ``droptests_warp``: the same candidates divided over the GPUs, one Warp
  model per GPU (``warp_batch.prepare_split``) against all of them on the first GPU.

``--backend`` picks the worlds' simulator (the ``worlds`` and ``steps`` parts): "mjx" (default;
one hull per object) or "warp" (MuJoCo Warp, the exact CoACD parts; its worlds divided over the
GPUs, one Warp model per GPU, their poses handed to the sharded renderer on their own GPU).

Compile time (``.lower().compile()``, or the first call minus a later one) is reported apart
from run time (median of ``--repeats`` calls after it, ``block_until_ready``). Speedups are run
time on one device over run time on all: ``speedup_worlds`` (steps and render of one timed round),
``speedup_droptests`` (MJX; ``speedup_droptests_warp`` for Warp); ``steps.speedup`` for the
steps alone. Per-world results are compared: the worlds' final state (qpos, qvel) and every
image, the candidates' states after settling and at the end and their verdicts.
``equal_to_single_device`` is true when all of them are equal bit for bit; the largest
differences are beside it. A compiler may vectorise a row's sums differently for another batch
size (XLA:CPU does: 8 worlds vmapped together against 2 per device), so ``first_device_rows``
also compares the first device's rows with one device running as many rows: that comparison
isolates the sharding itself (``docs/scaling.md`` says why even it can differ).

The scene: ``--scene DIR``, a ``phirie convert`` output folder; when DIR has no ``scene.xml``
the demo's scene is made there first (``phirie synth`` of the default preset, seed 0, into
DIR/../capture, converted into DIR: what ``phirie demo`` converts), its time reported.

    python -m experiments.bench_scaling --scene out/scaling/convert --out experiments/results/scaling_2gpu.json

On this CPU, four forced host devices and small sizes check it end to end (Eigen's multi-threaded
contractions split a sum by the threads a device gets: single-threaded, a difference left is the
program's own):

    XLA_FLAGS="--xla_force_host_platform_device_count=4 --xla_cpu_multi_thread_eigen=false" \\
    python -m experiments.bench_scaling --scene out/scaling/convert --worlds 6 --cameras 2 --steps 8 \\
        --width 80 --candidates 16 --repeats 1
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

from experiments.report import emit
from experiments.timing import timed, timed_steps
from kernels.sharding import BatchMesh


def _say(message: str) -> None:
    print(f"bench_scaling: {message}", file=sys.stderr, flush=True)


def ensure_scene(scene: Path) -> float | None:
    """Make the demo's converted scene at ``scene`` unless it is there; seconds taken, or None."""
    if (scene / "scene.xml").is_file():
        return None
    from phirie_jax.pipeline import run_convert
    from phirie_jax.synthetic.scene import synthesize

    capture = scene.parent / "capture"
    t0 = time.perf_counter()
    _say(f"synthesizing the default preset into {capture} and converting it into {scene}")
    synthesize(capture, preset="default", seed=0)
    run_convert(capture, scene)
    return round(time.perf_counter() - t0, 1)


def _largest(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)), initial=0.0))


# --- worlds ------------------------------------------------------------------------------


def throws(env, worlds: int, throw: float, seed: int) -> np.ndarray:
    """(worlds, nv) initial velocities, each ~ N(0, throw): every world thrown its own way."""
    return np.random.default_rng(seed).normal(0.0, throw, (worlds, env.model.nv))


def _is_warp(batch) -> bool:
    from phirie_jax.interact.batched import WarpBatchedEnvironment

    return isinstance(batch, WarpBatchedEnvironment)


def world_state(batch) -> dict:
    """The worlds' final qpos and qvel (N, …), of either backend."""
    if _is_warp(batch):   # MuJoCo Warp: the host copy of every world, pads left out
        return {name: batch.worlds.field(name)[: batch.num_worlds] for name in ("qpos", "qvel")}
    return {"qpos": batch.data.qpos, "qvel": batch.data.qvel}


def timed_world_steps(batch, steps: int, repeats: int) -> tuple[float, float]:
    """``timed`` steps of either backend, waiting for the simulator (Warp: every GPU's stream)."""
    if _is_warp(batch):
        return timed(lambda: (batch.step(steps), batch.worlds.synchronize()), repeats)
    return timed_steps(batch, steps, repeats)


def bench_worlds(env, worlds: int, cameras: list[int], steps: int, repeats: int, devices, thrown: np.ndarray,
                 max_images: int, backend: str = "mjx") -> tuple[dict, dict]:
    """One device count: timings, and (final state, images) for the comparison."""
    from phirie_jax.interact.batched import BatchedEnvironment

    t0 = time.perf_counter()
    batch = BatchedEnvironment(env, worlds, devices=devices, backend=backend)
    batch.set_velocities(thrown)
    put_s = time.perf_counter() - t0
    step_first, step_s = timed_world_steps(batch, steps, repeats)
    render_first, render_s = timed(lambda: batch.render(cameras, max_images=max_images).rgb, repeats)
    images = batch.render(cameras, max_images=max_images)
    state = world_state(batch)
    frames = worlds * len(cameras)
    row = {"devices": batch.mesh.size, "worlds_padded": batch.padded_worlds, "put_s": round(put_s, 2),
           "step_compile_s": round(step_first - step_s, 2), "step_s": round(step_s, 4),
           "render_compile_s": round(render_first - render_s, 2), "render_s": round(render_s, 4),
           "world_steps_per_s": round(worlds * steps / step_s, 1), "frames_per_s": round(frames / render_s, 1),
           "round_s": round(step_s + render_s, 4)}
    return row, {"state": state, "images": images}


def compare_worlds(one: dict, many: dict) -> dict:
    """Per-world differences: the final state on the host, the images on the first device (an
    image set of a thousand worlds is gigabytes: only the largest difference per world comes back)."""
    import jax.numpy as jnp

    out = {}
    for name in ("qpos", "qvel"):
        a, b = np.asarray(one["state"][name]), np.asarray(many["state"][name])
        out[f"worlds_equal_{name}"] = int(np.sum(np.all(a == b, axis=1)))
        out[f"max_abs_{name}_difference"] = _largest(a, b)
    device = next(iter(one["images"].rgb.devices()))
    differing, largest = np.zeros(one["images"].rgb.shape[0], bool), 0.0
    for name in ("rgb", "depth", "alpha"):
        a = getattr(one["images"], name)
        b = jax.device_put(getattr(many["images"], name), device)
        per_world = np.asarray(jnp.max(jnp.abs(a - b).reshape(a.shape[0], -1), axis=1))
        differing |= per_world != 0
        largest = max(largest, float(per_world.max(initial=0.0)))
    out["worlds_equal_images"] = int(np.sum(~differing))
    out["max_abs_image_difference"] = largest
    out["equal"] = bool(out["worlds_equal_qpos"] == out["worlds_equal_qvel"] == out["worlds_equal_images"]
                        == len(differing))
    return out


def worlds_part(args, all_devices) -> dict:
    from phirie_jax.interact.environment import Environment

    env = Environment.load(args.scene)
    if args.width is not None:
        env.cameras = [c.scaled(args.width / c.width) for c in env.cameras]
    cameras = list(range(min(args.cameras, len(env.cameras))))
    thrown = throws(env, args.worlds, args.throw, args.seed)
    result = {"worlds": args.worlds, "cameras": len(cameras), "steps_per_call": args.steps,
              "image": [env.cameras[0].width, env.cameras[0].height], "objects": len(env.objects),
              "gaussians": int(env.background.num + env.object_gaussians.num),
              "images_per_device_and_call": args.max_images, "simulator": args.backend,
              "throw": f"every velocity of every world ~ N(0, {args.throw}) (seed {args.seed})"}
    rows, kept = [], []
    for devices in (1, all_devices):
        _say(f"worlds on {len(devices) if devices != 1 else 1} device(s)")
        row, out = bench_worlds(env, args.worlds, cameras, args.steps, args.repeats, devices, thrown, args.max_images,
                                args.backend)
        rows.append(row)
        kept.append(out)
        _say(json.dumps(row))
    result["one_device"], result["all_devices"] = rows
    result["comparison"] = compare_worlds(*kept)
    result["speedup_steps"] = round(rows[0]["step_s"] / rows[1]["step_s"], 3)
    result["speedup_frames"] = round(rows[0]["render_s"] / rows[1]["render_s"], 3)
    result["speedup"] = round(rows[0]["round_s"] / rows[1]["round_s"], 3)
    if rows[1]["devices"] > 1:
        result["first_device_rows"] = first_device_worlds(env, rows[1], args, thrown, kept[1]["state"])
    return result


def first_device_worlds(env, sharded: dict, args, thrown: np.ndarray, state: dict) -> dict:
    """The first device's worlds of the sharded run against one device stepping as many worlds
    (the same vmapped size): equal bit for bit when the sharding itself changes nothing, whatever
    a compiler makes of a different batch size."""
    from phirie_jax.interact.batched import BatchedEnvironment

    per = sharded["worlds_padded"] // sharded["devices"]
    batch = BatchedEnvironment(env, per, devices=1, backend=args.backend)
    batch.set_velocities(thrown[:per])
    for _ in range(1 + args.repeats):     # the step calls of ``bench_worlds``
        batch.step(args.steps)
    alone = world_state(batch)
    same = [np.array_equal(np.asarray(alone[name]), np.asarray(state[name])[:per]) for name in ("qpos", "qvel")]
    return {"worlds": per, "equal": bool(all(same)),
            "max_abs_qpos_difference": _largest(alone["qpos"], np.asarray(state["qpos"])[:per])}


def steps_part(args, all_devices) -> dict:
    """The ``worlds`` part's MJX steps alone on one device and on all: ``speedup`` is the
    median call's time on one over that on all."""
    from phirie_jax.interact.batched import BatchedEnvironment
    from phirie_jax.interact.environment import Environment

    env = Environment.load(args.scene)
    rows = []
    for devices in (1, all_devices):
        batch = BatchedEnvironment(env, args.worlds, devices=devices, backend=args.backend)
        batch.set_velocities(throws(env, args.worlds, args.throw, args.seed))
        first, step_s = timed_world_steps(batch, args.steps, args.repeats)
        rows.append({"devices": batch.mesh.size, "step_compile_s": round(first - step_s, 2), "step_s": round(step_s, 4),
                     "world_steps_per_s": round(args.worlds * args.steps / step_s, 1)})
        _say(json.dumps(rows[-1]))
    return {"worlds": args.worlds, "steps_per_call": args.steps, "simulator": args.backend,
            "one_device": rows[0], "all_devices": rows[1],
            "speedup": round(rows[0]["step_s"] / rows[1]["step_s"], 3)}


# --- drop tests ----------------------------------------------------------------------------


def drop_inputs(count: int, seed: int, config):
    from experiments.bench_droptest import bodies_for
    from phirie_jax.construct.physics.droptest import build_model, spawn_qpos

    _, bodies = bodies_for(count, seed)
    models = [build_model(b, 1, config) for b in bodies]
    return models, np.stack([spawn_qpos(b) for b in bodies])


def bench_mjx_drops(models, qpos0, config, repeats: int, devices) -> tuple[dict, tuple]:
    from phirie_jax.construct.physics import mjx_batch
    from phirie_jax.construct.physics.droptest import bucket_template

    mesh = BatchMesh.over(devices)
    t0 = time.perf_counter()
    template_model, template = bucket_template(1, config)
    params = mjx_batch.stack_params(template_model, models, config.vertex_budget)
    batch = mjx_batch.padded_count(len(models), config, mesh)
    if batch < len(models):
        raise ValueError(f"{len(models)} candidates exceed one batch ({batch}, DropTestConfig.max_batch)")
    args = mjx_batch.device_args(template, params, qpos0, mesh)
    prep_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    compiled = mjx_batch.lower(template, params, qpos0, config, mesh).compile()
    compile_s = time.perf_counter() - t0
    first, run_s = timed(lambda: compiled(*args), repeats)
    settled, final = (np.asarray(o, np.float64)[: len(models)] for o in compiled(*args))
    steps = len(models) * (config.settle_steps + config.free_steps)
    return ({"devices": mesh.size, "batch": args[-1].shape[0], "prep_s": round(prep_s, 2),
             "compile_s": round(compile_s, 2), "first_run_s": round(first, 4), "run_s": round(run_s, 4),
             "steps_per_s": round(steps / run_s, 1), "candidates_per_s": round(len(models) / run_s, 1)},
            (settled, final))


def first_device_drops(models, qpos0, config, sharded: dict, states: tuple) -> dict:
    """The first device's candidates of the sharded run against one device running as many rows
    (``first_device_worlds``)."""
    from phirie_jax.construct.physics import mjx_batch
    from phirie_jax.construct.physics.droptest import bucket_template

    per = min(len(models), sharded["batch"] // sharded["devices"])
    mesh = BatchMesh.over(1)
    template_model, template = bucket_template(1, config)
    params = mjx_batch.stack_params(template_model, models[:per], config.vertex_budget)
    args = mjx_batch.device_args(template, params, qpos0[:per], mesh)
    out = mjx_batch.lower(template, params, qpos0[:per], config, mesh).compile()(*args)
    settled, final = (np.asarray(o, np.float64) for o in out)
    return {"candidates": per, "equal": bool(np.array_equal(settled, states[0][:per])
                                             and np.array_equal(final, states[1][:per])),
            "max_abs_qpos_difference": max(_largest(settled, states[0][:per]), _largest(final, states[1][:per]))}


def bench_warp_drops(models, qpos0, config, repeats: int, devices: list[str], parallel_launch: bool = True
                     ) -> tuple[dict, tuple]:
    from phirie_jax.construct.physics import warp_batch

    t0 = time.perf_counter()
    parts = warp_batch.prepare_split(models, qpos0, config, devices=devices)
    prep_s = time.perf_counter() - t0
    first, run_s = timed(lambda: warp_batch.simulate_all(parts, parallel_launch).final, repeats)
    out = warp_batch.simulate_all(parts, parallel_launch)
    steps = len(models) * (config.settle_steps + config.free_steps)
    return ({"devices": devices, "parallel_launch": parallel_launch, "prep_s": round(prep_s, 2), "first_run_s": round(first, 4),
             "run_s": round(run_s, 4), "steps_per_s": round(steps / run_s, 1),
             "candidates_per_s": round(len(models) / run_s, 1)}, (out.settled, out.final))


def compare_drops(models, qpos0, config, one: tuple, many: tuple, backend: str) -> dict:
    from phirie_jax.construct.physics.droptest import verdict

    def verdicts(states):
        return [verdict(m, q, s, f, config, backend).stable for m, q, s, f in zip(models, qpos0, *states)]

    stable_one, stable_many = verdicts(one), verdicts(many)
    same = np.all(one[0] == many[0], axis=1) & np.all(one[1] == many[1], axis=1)
    return {"candidates_equal": int(same.sum()), "max_abs_qpos_difference": max(_largest(one[0], many[0]),
                                                                                _largest(one[1], many[1])),
            "verdicts_equal": int(sum(a == b for a, b in zip(stable_one, stable_many))),
            "stable": int(sum(bool(s) for s in stable_one)), "equal": bool(same.all())}


def _one_against_all(runs: list[tuple[str, object]], bench) -> tuple[list[dict], list]:
    """``bench(devices)`` for each (label, devices) of ``runs``, said as it goes: its rows and
    what each kept for the comparison."""
    rows, kept = [], []
    for label, devices in runs:
        _say(label)
        row, out = bench(devices)
        rows.append(row)
        kept.append(out)
        _say(json.dumps(row))
    return rows, kept


def droptests_part(args, all_devices) -> tuple[dict, dict | None]:
    from phirie_jax.construct.physics import warp_batch
    from phirie_jax.construct.physics.config import DropTestConfig

    config = DropTestConfig(max_batch=max(DropTestConfig().max_batch, args.candidates))
    t0 = time.perf_counter()
    models, qpos0 = drop_inputs(args.candidates, args.seed, config)
    result = {"candidates": args.candidates, "steps_per_candidate": config.settle_steps + config.free_steps,
              "models_s": round(time.perf_counter() - t0, 2)}
    rows, kept = _one_against_all(
        [(f"MJX drop tests on {n} device(s)", d) for n, d in ((1, 1), (len(all_devices), all_devices))],
        lambda devices: bench_mjx_drops(models, qpos0, config, args.repeats, devices))
    result["one_device"], result["all_devices"] = rows
    result["comparison"] = compare_drops(models, qpos0, config, *kept, "mjx")
    result["speedup"] = round(rows[0]["run_s"] / rows[1]["run_s"], 3)
    if rows[1]["devices"] > 1:
        result["first_device_rows"] = first_device_drops(models, qpos0, config, rows[1], kept[1])
    ok, why = warp_batch.available()
    if args.skip_warp or not ok:
        return result, {"skipped": "--skip-warp" if args.skip_warp else why}
    gpus = warp_batch.warp_devices(None)
    if gpus == ["cpu"]:
        return result, {"skipped": "Warp sees no GPU: nothing to divide"}
    warp = {"candidates": args.candidates}
    rows, kept = _one_against_all([(f"Warp drop tests on {names}", names) for names in (gpus[:1], gpus)],
                                  lambda names: bench_warp_drops(models, qpos0, config, args.repeats, names))
    warp["one_device"], warp["all_devices"] = rows
    warp["comparison"] = compare_drops(models, qpos0, config, *kept, "warp")
    warp["speedup"] = round(rows[0]["run_s"] / rows[1]["run_s"], 3)
    if len(gpus) > 1:  # the lever: every device's graphs launched from one thread, in turn
        (serial,), (out,) = _one_against_all([(f"Warp drop tests on {gpus}, one launching thread", gpus)],
                                             lambda names: bench_warp_drops(models, qpos0, config, args.repeats,
                                                                            names, parallel_launch=False))
        warp["all_devices_one_launching_thread"] = serial
        warp["one_launching_thread_equal"] = bool(np.array_equal(out[1], kept[1][1]))
    return result, warp


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, default=Path("out/scaling/convert"),
                        help="a converted folder (made from the default preset when it has no scene.xml)")
    parser.add_argument("--worlds", type=int, default=1024)
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--steps", type=int, default=240, help="simulator steps per timed call")
    parser.add_argument("--width", type=int, default=None, help="render width (default: the cameras')")
    parser.add_argument("--max-images", type=int, default=256, help="images per device and rasterization call")
    parser.add_argument("--throw", type=float, default=0.3, help="std of the worlds' random initial velocities")
    parser.add_argument("--candidates", type=int, default=4096)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--parts", nargs="+", choices=["worlds", "steps", "droptests"], default=["worlds", "droptests"])
    parser.add_argument("--backend", choices=["mjx", "warp"], default="mjx",
                        help="the worlds' simulator (the worlds and steps parts)")
    parser.add_argument("--skip-warp", action="store_true", help="no MuJoCo Warp drop-test rows")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)

    all_devices = list(jax.devices())
    result = {"backend": jax.default_backend(), "devices": [str(d) for d in all_devices],
              "device_kind": all_devices[0].device_kind, "jax": jax.__version__, "machine": platform.platform(),
              "cpus": os.cpu_count(), "xla_flags": os.environ.get("XLA_FLAGS", ""),
              "load_average_at_start": list(os.getloadavg())}
    with contextlib.redirect_stdout(sys.stderr):   # stdout carries the JSON alone (Warp prints a banner)
        if {"worlds", "steps"} & set(args.parts):
            result["scene"] = str(args.scene)
            made = ensure_scene(args.scene)
            if made is not None:
                result["scene_made_s"] = made
        if "worlds" in args.parts:
            result["worlds"] = worlds_part(args, all_devices)
            result["speedup_worlds"] = result["worlds"]["speedup"]
        if "steps" in args.parts:
            result["steps"] = steps_part(args, all_devices)
        if "droptests" in args.parts:
            result["droptests"], result["droptests_warp"] = droptests_part(args, all_devices)
            result["speedup_droptests"] = result["droptests"]["speedup"]
            if "speedup" in result["droptests_warp"]:
                result["speedup_droptests_warp"] = result["droptests_warp"]["speedup"]
    compared = [result[k]["comparison"]["equal"] for k in ("worlds", "droptests", "droptests_warp")
                if k in result and "comparison" in result[k]]
    result["equal_to_single_device"] = bool(compared) and all(compared)
    result["shardy_partitioner"] = bool(jax.config.jax_use_shardy_partitioner)   # off: GSPMD (kernels.sharding)
    result["load_average_at_end"] = list(os.getloadavg())
    emit(result, args.out)


if __name__ == "__main__":
    main()
