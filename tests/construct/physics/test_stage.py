"""run_physics / run_droptest on a constructed folder (synthetic ground truth): manifest contract,
files in the canonical frame, MJCF and URDF round trip, scene settle, failed objects, re-runs."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
import trimesh

from phirie_jax.construct.physics.config import CoacdConfig, DropTestConfig, PhysicsConfig
from phirie_jax.construct.physics.mjcf import settle_scene
from phirie_jax.construct.physics.parts import read_part
from phirie_jax.construct.physics.stage import run_droptest, run_physics, start_collision
from phirie_jax.errors import SceneInputError
from phirie_jax.manifest import Manifest
from phirie_jax.records import ObjectRecord
from tests.construct.physics.test_collision import fin_mesh
from tests.fixtures.constructed import constructed_folder
from tests.processes import running, wait_for

C_BACKEND = PhysicsConfig(coacd=CoacdConfig(resolution=1000, preprocess_resolution=30, mcts_iterations=60,
                                            mcts_nodes=10), drop_test=DropTestConfig(backend="mujoco"))
PLACE_TOL = 2e-3      # m: placed collision parts vs the ground-truth world mesh (hull decimation)
SETTLE_LIMIT = 0.03   # m: the bar for the exported scene
BAD = {90: (np.zeros((0, 3)), np.zeros((0, 3), int)), 91: fin_mesh(),
       92: (np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.1, 0.1, 0.0]]), np.array([[0, 1, 2], [1, 3, 2]]))}


@pytest.fixture(scope="module")
def physics(tmp_path_factory):
    out, truth = constructed_folder(tmp_path_factory.mktemp("out"), seed=0, extra=BAD)
    return out, truth, run_physics(None, out, C_BACKEND)


def test_objects_get_the_contract_fields(physics):
    out, truth, manifest = physics
    assert json.loads((out / "manifest.json").read_text())["objects"] == manifest["objects"]
    good = {o["id"]: o for o in manifest["objects"] if o["status"] == "accepted"}
    assert sorted(good) == sorted(t.id for t in truth)
    for obj in good.values():
        prior = obj["physics"]["priors"]
        assert obj["friction"] == 0.5 and obj["mass"] == prior["mass"]
        category = next(t.shape.category for t in truth if t.id == obj["id"])
        assert prior["mass_source"].startswith(f"category {category}: "), prior["mass_source"]
        assert 1 <= len(obj["collision"]) <= 16 and all((out / p).is_file() for p in obj["collision"])
        assert set(obj["drop_test"]) >= {"stable", "drift_m", "final_height_m"}
        assert obj["drop_test"]["stable"] is True                    # the ground truth rests on the table
        settling = obj["checks"]["settling"]
        assert settling["passed"] is True and settling["value"] == obj["drop_test"]["drift_m"]
        report = obj["physics"]["collision"]
        assert report["parts"] == len(obj["collision"]) and report["hull_volume_ratio"] > 0.8
        assert report["method"] in ("coacd", "convex_hull") and report["time_s"] > 0
        assert report["coacd"]["tier"] in ("nearly convex", "concave") and report["coacd"]["threshold"] >= 0.05
    assert {"physics", "physics.collision", "physics.export", "physics.droptest"} <= set(manifest["timings"])
    pool = manifest["physics"]["collision_workers"]
    assert 1 <= pool["workers"] <= len(good) + len(BAD) and pool["omp_threads"] >= 1


def test_bad_meshes_become_failed_objects_with_a_reason(physics):
    _, _, manifest = physics
    failed = {o["id"]: o for o in manifest["objects"] if o["status"] == "failed"}
    assert sorted(failed) == [90, 91, 92]
    assert "empty" in failed[90]["reason"] and "non-manifold" in failed[91]["reason"]
    assert "zero volume" in failed[92]["reason"]
    assert all(o["reason"].startswith("physics:") and o["collision"] == [] for o in failed.values())


def test_collision_parts_are_in_the_canonical_frame_and_the_pose_places_them(physics):
    out, truth, manifest = physics
    objects = {o["id"]: o for o in manifest["objects"]}
    for t in truth:
        obj = objects[t.id]
        parts = [read_part(out / p) for p in obj["collision"]]
        canonical = np.concatenate([p.vertices for p in parts])
        lo, hi = t.shape.mesh.bounds
        assert np.all(canonical >= lo - PLACE_TOL) and np.all(canonical <= hi + PLACE_TOL)
        placed = canonical @ np.asarray(obj["pose"])[:3, :3].T + np.asarray(obj["pose"])[:3, 3]
        world = t.world_mesh()
        np.testing.assert_allclose(placed.min(0), world.bounds[0], atol=PLACE_TOL)
        np.testing.assert_allclose(placed.max(0), world.bounds[1], atol=PLACE_TOL)


def test_mjcf_loads_with_the_masses_inertias_and_placements_of_the_manifest(physics):
    out, _, manifest = physics
    model = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    for obj in (o for o in manifest["objects"] if o["status"] == "accepted"):
        b = model.body(f"object_{obj['id']}")
        props = obj["physics"]["mass_properties"]
        assert b.mass[0] == pytest.approx(obj["mass"])
        np.testing.assert_allclose(model.body_ipos[b.id], props["com"], atol=1e-7)
        np.testing.assert_allclose(np.sort(model.body_inertia[b.id]), np.linalg.eigvalsh(props["inertia"]),
                                   rtol=1e-6)
        pose = np.asarray(obj["pose"])
        np.testing.assert_allclose(data.xpos[b.id], pose[:3, 3], atol=1e-7)
        np.testing.assert_allclose(data.xmat[b.id].reshape(3, 3), pose[:3, :3], atol=1e-7)
    assert model.opt.timestep == pytest.approx(1 / 240) and model.opt.gravity[2] == pytest.approx(-9.81)
    # the scene's solver limits are its own, not the drop test's (one body on a plane converges faster)
    assert (model.opt.iterations, model.opt.ls_iterations) == (C_BACKEND.scene_solver_iterations,
                                                              C_BACKEND.scene_line_search_iterations)
    assert model.opt.iterations != C_BACKEND.drop_test.solver_iterations


def test_urdf_parses_with_the_same_inertial_as_the_mjcf(physics):
    out, _, manifest = physics
    scene = ET.parse(out / "scene.xml").getroot()
    for obj in (o for o in manifest["objects"] if o["status"] == "accepted"):
        urdf = ET.parse(out / obj["physics"]["urdf"]).getroot()
        link = urdf.find("link")
        inertial = link.find("inertial")
        assert float(inertial.find("mass").get("value")) == pytest.approx(obj["mass"])
        com = [float(x) for x in inertial.find("origin").get("xyz").split()]
        body = next(b for b in scene.iter("body") if b.get("name") == f"object_{obj['id']}")
        mj = body.find("inertial")
        assert mj.get("pos").split() == inertial.find("origin").get("xyz").split()      # the same digits
        i = inertial.find("inertia")
        full = [float(i.get(k)) for k in ("ixx", "iyy", "izz", "ixy", "ixz", "iyz")]
        np.testing.assert_allclose([float(x) for x in mj.get("fullinertia").split()], full, rtol=1e-8)
        np.testing.assert_allclose(com, obj["physics"]["mass_properties"]["com"], atol=1e-8)
        meshes = [c.find("geometry/mesh").get("filename") for c in link.findall("collision")]
        assert [str((out / obj["physics"]["urdf"]).parent / m) for m in meshes] == \
               [str(out / p) for p in obj["collision"]]
        assert float(link.find("contact/lateral_friction").get("value")) == 0.5


def test_urdf_loads_in_pybullet_with_its_inertial(physics):
    pybullet = pytest.importorskip("pybullet")
    out, _, manifest = physics
    client = pybullet.connect(pybullet.DIRECT)
    try:
        for obj in (o for o in manifest["objects"] if o["status"] == "accepted"):
            # without this flag PyBullet replaces a URDF's inertia by its collision shapes' boxes
            body = pybullet.loadURDF(str(out / obj["physics"]["urdf"]), flags=pybullet.URDF_USE_INERTIA_FROM_FILE,
                                     physicsClientId=client)
            info = pybullet.getDynamicsInfo(body, -1, physicsClientId=client)
            assert info[0] == pytest.approx(obj["mass"])
            np.testing.assert_allclose(sorted(info[2]), np.linalg.eigvalsh(obj["physics"]["mass_properties"]["inertia"]),
                                       rtol=1e-5)
            np.testing.assert_allclose(info[3], obj["physics"]["mass_properties"]["com"], atol=1e-6)
    finally:
        pybullet.disconnect(client)


def test_a_2s_settle_of_the_exported_scene_moves_no_stable_object_3cm(physics):
    out, _, manifest = physics
    moved = settle_scene(out / "scene.xml", 2.0)
    assert moved == pytest.approx(manifest["physics"]["scene_settle"]["displacement_m"])
    for obj in (o for o in manifest["objects"] if o["status"] == "accepted"):
        if obj["drop_test"]["stable"]:
            assert moved[f"object_{obj['id']}"] < SETTLE_LIMIT


def test_the_support_box_is_the_tabletop(physics):
    _, _, manifest = physics
    geoms = {g["name"]: g for g in manifest["physics"]["background"]}
    assert geoms["floor"]["type"] == "plane" and abs(geoms["floor"]["pos"][2]) < 0.01
    box = geoms["support_0"]
    half = sorted(box["size"][:2])
    assert half == pytest.approx([0.4, 0.6], abs=0.03)            # the 1.2 × 0.8 m tabletop
    assert box["pos"][2] + box["size"][2] == pytest.approx(0.75, abs=1e-6)
    assert "surface" in box["source"]


def test_run_droptest_on_the_exported_folder_gives_the_same_verdicts(physics, tmp_path):
    import shutil

    out, _, manifest = physics
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    again = run_droptest(copy, C_BACKEND)
    for a, b in zip(manifest["objects"], again["objects"]):
        assert a["drop_test"] == b["drop_test"]


def test_a_folder_without_objects_is_an_error_for_people(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"schema": "phirie/1", "timings": {}}))
    with pytest.raises(SceneInputError, match="objects"):
        run_physics(None, tmp_path, C_BACKEND)
    with pytest.raises(SceneInputError, match="objects"):
        run_droptest(tmp_path, C_BACKEND)


def test_pose_scale_goes_into_the_files_and_the_inertia(tmp_path):
    out, truth = constructed_folder(tmp_path / "out", seed=1)
    manifest = json.loads((out / "manifest.json").read_text())
    obj = manifest["objects"][0]
    mesh = trimesh.load(out / obj["mesh"], force="mesh", process=False)
    half = mesh.copy()
    half.apply_scale(0.5)                               # canonical mesh at half size, pose scale 2
    half.export(out / obj["mesh"])
    pose = np.asarray(obj["pose"])
    pose[:3, :3] *= 2.0
    obj["pose"] = pose.tolist()
    manifest["objects"] = [obj]
    (out / "manifest.json").write_text(json.dumps(manifest))
    result = run_physics(None, out, C_BACKEND)["objects"][0]
    assert result["status"] == "accepted" and result["physics"]["scale"] == pytest.approx(2.0)
    assert 'scale="2 2 2"' in (out / "scene.xml").read_text()
    model = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    lowest = min(data.geom_xpos[g, 2] for g in range(model.ngeom) if model.geom_bodyid[g] > 0)
    assert lowest > 0.75 - 0.01                          # parts placed at the true size, on the table
    assert result["drop_test"]["stable"]


def test_parallel_and_in_process_builds_write_the_same_parts(physics, tmp_path):
    from phirie_jax.construct.physics.stage import build_objects

    out, _, manifest = physics
    entries = [ObjectRecord.from_json({k: v for k, v in o.items() if k in ("id", "status", "pose", "mesh")})
               for o in manifest["objects"] if o["id"] in (1, 2, 90)]
    alone = tmp_path / "alone"
    (alone / "objects").mkdir(parents=True)
    for e in entries:
        src = out / "objects" / str(e.id) / "mesh.obj"
        (alone / "objects" / str(e.id)).mkdir()
        (alone / "objects" / str(e.id) / "mesh.obj").write_bytes(src.read_bytes())
    import dataclasses

    outcomes = build_objects(entries, {}, alone, dataclasses.replace(C_BACKEND, workers=1))
    assert "reason" in outcomes[2] and "update" not in outcomes[2]  # the empty mesh fails the same way
    for e, outcome in zip(entries[:2], outcomes[:2]):
        parallel = next(o for o in manifest["objects"] if o["id"] == e.id)
        assert list(outcome["update"]["collision"]) == parallel["collision"]
        for path in parallel["collision"]:
            assert (alone / path).read_bytes() == (out / path).read_bytes()


def test_a_scaled_pose_places_the_collision_parts_at_their_scaled_size():
    """The supports are fitted around the parts as they stand in the scene: a pose of scale 2
    doubles the canonical box once (the body's parts already carry the scale)."""
    from phirie_jax.construct.physics.body import object_body
    from phirie_jax.construct.physics.collision import hull_part
    from phirie_jax.construct.physics.priors import priors
    from phirie_jax.construct.physics.stage import _placed
    from phirie_jax.geometry import sim3_matrix

    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    pose = sim3_matrix(2.0, np.eye(3), [0.0, 0.0, 0.1])
    placed = _placed(object_body(7, [hull_part(np.asarray(box.vertices), 64)], pose, priors(None)), ObjectRecord(id=7))
    np.testing.assert_allclose(placed.points.max(0) - placed.points.min(0), [0.2, 0.2, 0.2], atol=1e-9)


def crashing_build(entry, category, out_dir, config):
    """A collision build that dies in native code on object 2 (as CoACD can), else succeeds."""
    import os
    import signal

    if entry.id == 2:
        os.kill(os.getpid(), signal.SIGSEGV)
    return {"update": {"built": entry.id}}


@pytest.mark.parametrize("ids", [(2,), (1, 2, 3)], ids=["alone", "among-others"])
def test_a_build_that_kills_its_process_is_recorded_and_the_rest_go_on(tmp_path, ids):
    """Also a single object (one worker) builds in a child process: its crash is the object's
    recorded failure, never the conversion's end."""
    from phirie_jax.construct.physics.stage import build_objects

    outcomes = build_objects([ObjectRecord(id=i) for i in ids], {}, tmp_path, PhysicsConfig(workers=0), build=crashing_build)
    by_id = dict(zip(ids, outcomes))
    assert by_id[2] == {"reason": "the collision process died (CoACD crashed on this mesh: SIGSEGV)"}
    assert all(by_id[i] == {"update": {"built": i}} for i in ids if i != 2)


def _started(out, config):
    """``start_collision`` of the kept objects of the folder's manifest, as the pipeline starts it."""
    manifest = Manifest.load(out)
    return start_collision(manifest.objects(), manifest.categories(), out, config)


def test_a_collision_started_ahead_gives_what_the_stage_builds_itself(physics, tmp_path):
    """``start_collision`` (workers busy while the caller does other work) then ``run_physics``
    with it: the same statuses, parts and mass properties as building inside the stage."""
    _, _, built_here = physics
    out, _ = constructed_folder(tmp_path / "out", seed=0, extra=BAD)
    job = _started(out, C_BACKEND)
    manifest = run_physics(None, out, C_BACKEND, collision=job)
    for ahead, here in zip(manifest["objects"], built_here["objects"]):
        assert ahead["status"] == here["status"] and ahead["collision"] == here["collision"]
        if here["status"] == "accepted":
            assert ahead["physics"]["mass_properties"] == here["physics"]["mass_properties"]
            for p in here["collision"]:
                np.testing.assert_array_equal(read_part(out / p).vertices, read_part(physics[0] / p).vertices)
    assert job.seconds > 0
    assert {"physics.collision", "physics.collision_wait"} <= set(manifest["timings"])


def test_a_collision_started_ahead_is_terminated_when_the_work_beside_it_fails(tmp_path):
    out, _ = constructed_folder(tmp_path / "out", seed=0)
    job = _started(out, PhysicsConfig(workers=2))
    with pytest.raises(RuntimeError, match="beside"), job:
        assert wait_for(lambda: job._pool.running_pids(), 60.0), "no collision worker started"
        workers = job._pool.running_pids()
        raise RuntimeError("the work beside the collision failed")
    assert workers and wait_for(lambda: not any(running(pid) for pid in workers), 5.0)
