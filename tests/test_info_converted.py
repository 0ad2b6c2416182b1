"""``phirie info OUT_DIR`` on a converted folder, ``phirie --version``, and the line that says how
to get scene.usda when pxr is missing."""

from __future__ import annotations

import json
from importlib.metadata import version
from pathlib import Path

import pytest

from phirie_jax import layout
from phirie_jax.cli import main
from phirie_jax.info import outcome_lines
from phirie_jax.manifest import Manifest
from phirie_jax.records import ObjectRecord
from tests.fixtures.box_scene import BOXES, converted_folder


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return converted_folder(tmp_path_factory.mktemp("info"))


def test_info_summarises_a_converted_folder(folder, capsys):
    assert main(["info", str(folder), "--json"]) == 0
    facts = json.loads(capsys.readouterr().out)
    assert facts["root"] == str(folder)
    assert [o["id"] for o in facts["objects"]] == sorted(BOXES)
    manifest = json.loads((folder / layout.MANIFEST).read_text())
    for row, entry in zip(facts["objects"], manifest["objects"]):
        assert row["status"] == "accepted" and row["candidate"] == "box" and row["parts"] == 1
        assert row["mass"] == entry["mass"] and row["drop_test"].startswith("stable")
    assert facts["files"][layout.SCENE_MJCF] == (folder / layout.SCENE_MJCF).stat().st_size
    assert facts["files"][layout.REPORT] == "not written"   # not written for this folder
    assert "2 of 2 objects accepted" in facts["outcome"]
    assert main(["info", str(folder)]) == 0
    table = capsys.readouterr().out
    assert "converted" in table and "objects" in table and "box" in table


def test_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"phirie {version('phirie_jax')}"


def test_a_missing_pxr_is_one_line_that_says_how(folder):
    manifest = json.loads((folder / layout.MANIFEST).read_text())
    manifest["physics"]["usd"] = {"path": None, "reason": "pxr is not importable (pip install 'phirie_jax[usd]')"}
    lines = [line for line in outcome_lines(Manifest.from_json(folder, manifest)) if "scene.usda" in line]
    assert lines == ["scene.usda not written: pxr is not importable (pip install 'phirie_jax[usd]')"]


def test_an_object_kept_with_a_failed_check_is_unverified_everywhere(folder, tmp_path, capsys, monkeypatch):
    import shutil

    from phirie_jax.report.config import ReportConfig
    from phirie_jax.report.page import write_report
    from phirie_jax.view.panel import object_markdown

    copy = Path(shutil.copytree(folder, tmp_path / "copy"))
    manifest = json.loads((copy / layout.MANIFEST).read_text())
    first = manifest["objects"][0]
    first.update(status="unverified", unresolved_checks=["registration"],
                 reason="kept with failed checks: registration (use --strict to reject)")
    (copy / layout.MANIFEST).write_text(json.dumps(manifest))
    assert main(["info", str(copy), "--json"]) == 0
    facts = json.loads(capsys.readouterr().out)
    assert facts["objects"][0]["status"] == "unverified" and facts["objects"][0]["failed_checks"] == ["registration"]
    assert f"1 of 2 objects accepted, 1 kept unverified ({first['id']}: failed registration)" in facts["outcome"]
    monkeypatch.setenv("COLUMNS", "240")   # the table on one line per row
    assert main(["info", str(copy)]) == 0
    assert "unverified (failed registration)" in capsys.readouterr().out
    write_report(copy, ReportConfig(views=1, width=32, thumbnail=16))
    assert '<td class="status-unverified">unverified (failed registration)</td>' in (copy / layout.REPORT).read_text()
    assert object_markdown(ObjectRecord.from_json(first)).startswith("🟡 **unverified (failed registration)**")


@pytest.mark.parametrize("value", ["3", "x=1", "3=-0.2", "3=nan"])
def test_a_bad_mass_option_is_one_line(value, tmp_path, capsys):
    assert main(["convert", str(tmp_path), "--out", str(tmp_path / "out"), "--mass", value]) == 2
    assert capsys.readouterr().err == (f"phirie: error: --mass: {value!r} (expected ID=KG with a positive mass, "
                                       "e.g. 3=0.35)\n")
