"""The stages' records and their one serialized form: a manifest written before the records existed
(``fixtures/manifest_phirie1.json``, the tiny scene converted by the code of 2c91423) reads into
records and writes back byte for byte; another schema is refused in one line naming it; a bad
field names the file and the field."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from phirie_jax.errors import SceneInputError
from phirie_jax.manifest import SCHEMA, Manifest
from phirie_jax.records import (
    BackgroundRecord,
    Check,
    FrameRecord,
    InstanceRecord,
    ObjectRecord,
    ObjectStatus,
    PhysicsRecord,
)

OLD = Path(__file__).parent / "fixtures" / "manifest_phirie1.json"


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "manifest.json").write_bytes(OLD.read_bytes())
    return tmp_path


def test_a_manifest_of_the_previous_version_reads_into_records(folder):
    manifest = Manifest.load(folder)
    assert isinstance(manifest.frame(), FrameRecord) and manifest.frame().capture_to_world.shape == (4, 4)
    assert all(isinstance(i, InstanceRecord) for i in manifest.instances())
    assert [i.id for i in manifest.instances()] == [1, 2, 3]
    objects = manifest.objects()
    assert all(isinstance(o, ObjectRecord) and isinstance(o.status, ObjectStatus) for o in objects)
    assert [o.status for o in objects] == [ObjectStatus.UNVERIFIED, ObjectStatus.ACCEPTED, ObjectStatus.UNVERIFIED]
    assert [o.id for o in manifest.kept_objects()] == [1, 2, 3]
    assert [o.id for o in manifest.accepted_objects()] == [2]
    first = objects[0]
    assert first.pose.shape == (4, 4) and first.failed_checks == first.unresolved_checks == ["registration"]
    settling = first.check("settling")
    assert isinstance(settling, Check) and settling.passed is True and settling.details["status"] == "run"
    assert isinstance(manifest.physics(), PhysicsRecord) and manifest.physics().scene == "scene.xml"
    assert isinstance(manifest.background(), BackgroundRecord) and manifest.background().path == "background.ply"
    assert manifest.categories() == {1: None, 2: None, 3: None}
    np.testing.assert_array_equal(manifest.up(), [0.0, 0.0, 1.0])


def test_reading_and_writing_it_again_gives_the_same_file(folder):
    Manifest.load(folder).write()
    assert (folder / "manifest.json").read_bytes() == OLD.read_bytes()
    data = json.loads(OLD.read_text())
    assert Manifest.from_json(folder, data).to_json() == data


def test_a_record_changed_is_a_new_record(folder):
    first = Manifest.load(folder).objects()[0]
    changed = first.with_fields(status=ObjectStatus.ACCEPTED, unresolved_checks=[], note="kept")
    assert first.status == ObjectStatus.UNVERIFIED and first.unresolved_checks == ["registration"]
    assert changed.to_json()["status"] == "accepted" and changed.extra["note"] == "kept"
    assert list(changed.to_json())[:13] == list(first.to_json())[:13]   # the contract fields first, in order
    with pytest.raises(dataclasses.FrozenInstanceError):
        first.status = ObjectStatus.ACCEPTED


@pytest.mark.parametrize("schema", ["phirie/0", "phirie/2", None])
def test_another_schema_is_refused_in_one_line_naming_it(folder, schema):
    data = json.loads(OLD.read_text())
    data["schema"] = schema
    (folder / "manifest.json").write_text(json.dumps(data))
    with pytest.raises(SceneInputError) as err:
        Manifest.load(folder)
    message = str(err.value)
    assert "\n" not in message and repr(schema) in message and f"expected {SCHEMA!r}" in message
    assert "manifest.json: schema" in message


def test_a_bad_status_names_the_file_and_the_field(folder):
    data = json.loads(OLD.read_text())
    data["objects"][1]["status"] = "maybe"
    (folder / "manifest.json").write_text(json.dumps(data))
    with pytest.raises(SceneInputError, match=r"manifest.json: objects.status: 'maybe' is not readable"):
        Manifest.load(folder)
    data["objects"][1] = {"status": "accepted"}
    (folder / "manifest.json").write_text(json.dumps(data))
    with pytest.raises(SceneInputError, match=r"manifest.json: objects.id: missing"):
        Manifest.load(folder)


def test_a_folder_from_before_the_frame_section_keeps_its_up(tmp_path):
    """Up recorded by the object stage (``construct.gravity``) before the frame stage existed."""
    (tmp_path / "manifest.json").write_text(json.dumps({
        "schema": SCHEMA, "timings": {}, "construct": {"gravity": {"up": [0.0, 1.0, 0.0]}},
        "objects": [{"id": 4, "status": "rejected", "reason": "strict"}]}))
    manifest = Manifest.load(tmp_path)
    np.testing.assert_array_equal(manifest.up(), [0.0, 1.0, 0.0])
    assert manifest.kept_objects() == () and manifest.objects()[0].checks == ()
    assert manifest.to_json()["objects"][0]["checks"] == {}
