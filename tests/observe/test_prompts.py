"""Prompts as the user gives them: ``--prompt`` values and ``prompts.json``, checked against the
cameras before any work, and the viewer's merge-on-write of ``prompts.json``."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from phirie_jax.errors import OptionError, SceneInputError
from phirie_jax.io.scene import load_scene
from phirie_jax.observe.prompts import (
    Prompt,
    check_prompts,
    parse_prompt,
    read_prompts_file,
    scene_prompts,
    update_prompts,
)
from phirie_jax.types import Camera


def _cameras(count: int = 12, width: int = 128, height: int = 96) -> tuple[Camera, ...]:
    K = np.array([[100.0, 0, width / 2], [0, 100.0, height / 2], [0, 0, 1]])
    return tuple(Camera(f"{k:04d}.png", K, np.eye(4), width, height) for k in range(count))


def test_a_box_and_a_click_parse_with_an_optional_label():
    box = parse_prompt("0007.jpg:120,80,260,240")
    assert box == Prompt("0007.jpg", box=(120.0, 80.0, 260.0, 240.0))
    assert parse_prompt("0007.jpg:260,240,120,80").box == (120.0, 80.0, 260.0, 240.0)   # corners in any order
    click = parse_prompt("images/0007.jpg:12.5,40=coffee mug")
    assert click.point == (12.5, 40.0) and click.box is None and click.label == "coffee mug"
    assert click.image == "images/0007.jpg"
    assert parse_prompt(click.as_text()) == click


@pytest.mark.parametrize("text, said", [
    ("0007.jpg", "expected IMAGE:X0,Y0,X1,Y1"),
    (":1,2", "expected IMAGE:X0,Y0,X1,Y1"),
    ("0007.jpg:1,2,3", "3 numbers"),
    ("0007.jpg:1,2,3,4,5", "5 numbers"),
    ("0007.jpg:a,b", "are not numbers"),
    ("0007.jpg:nan,3", "non-finite"),
])
def test_a_malformed_prompt_is_one_line_naming_the_option(text, said):
    with pytest.raises(OptionError) as err:
        parse_prompt(text)
    message = str(err.value)
    assert message.startswith(f"--prompt {text!r}:") and said in message and "\n" not in message


def test_images_are_named_as_the_cameras_name_them_or_by_stem():
    cameras = _cameras()
    checked = check_prompts([parse_prompt("0003:10,10,50,40"), parse_prompt("0004.png:3,4")], cameras)
    assert [p.image for p in checked] == ["0003.png", "0004.png"]


def test_an_unknown_image_lists_a_few_names():
    with pytest.raises(OptionError) as err:
        check_prompts([parse_prompt("0099.png:1,1,9,9")], _cameras())
    message = str(err.value)
    assert message.startswith("--prompt '0099.png:1,1,9,9': no image '0099.png'")
    assert "0000.png, 0001.png" in message and "(12 images)" in message and "0011.png" not in message


@pytest.mark.parametrize("text, said", [
    ("0001:-1,0,50,50", "leaves the image 0001.png (expected 0 ≤ x ≤ 128, 0 ≤ y ≤ 96)"),
    ("0001:10,10,129,50", "leaves the image"),
    ("0001:10,10,10.5,50", "less than a pixel"),
    ("0001:128,5", "outside the image 0001.png (expected 0 ≤ u < 128, 0 ≤ v < 96)"),
    ("0001:5,-0.5", "outside the image"),
])
def test_a_box_or_click_outside_its_photo_is_refused(text, said):
    with pytest.raises(OptionError, match="--prompt") as err:
        check_prompts([parse_prompt(text)], _cameras())
    assert said in str(err.value)


def test_prompts_json_is_read_with_labels_and_its_errors_name_the_file_and_field(tmp_path):
    path = tmp_path / "prompts.json"
    path.write_text(json.dumps({"prompts": [{"image": "0002.png", "box": [1, 2, 30, 40], "label": "mug"},
                                            {"image": "0005", "point": [7, 8]}], "note": "kept"}))
    prompts, source = scene_prompts(tmp_path, _cameras())
    assert source == path
    assert [(p.image, p.kind, p.label) for p in prompts] == [("0002.png", "box", "mug"), ("0005.png", "point", None)]
    assert prompts[0].origin == "prompts.json[0]"
    bad = {
        '{"objects": []}': "prompts: expected {",
        '{"prompts": [{"image": "0002.png"}]}': "prompts[0]: expected exactly one of box",
        '{"prompts": [{"image": "0002.png", "box": [1, 2, 3]}]}': "prompts[0].box: [1, 2, 3] (expected [x0, y0, x1, y1]",
        '{"prompts": [{"image": "0002.png", "point": [1, true]}]}': "prompts[0].point",
        '{"prompts": [{"image": "0002.png", "point": [1, 2], "lable": "x"}]}': "prompts[0].lable: unknown key",
        '{"prompts": [{"image": 7, "point": [1, 2]}]}': "prompts[0].image: 7",
        '{"prompts": [{"image": "0002.png", "point": [1, 2], "label": ""}]}': "prompts[0].label",
        '{"prompts": [': "not valid JSON",
    }
    for text, said in bad.items():
        path.write_text(text)
        with pytest.raises(SceneInputError) as err:
            scene_prompts(tmp_path, _cameras())
        assert str(err.value).startswith(str(path)) and said in str(err.value), (text, str(err.value))
    path.write_text('{"prompts": [{"image": "0002.png", "point": [500, 2]}]}')
    with pytest.raises(SceneInputError, match=r"prompts\.json: prompts\[0\]: point \[500, 2\] is outside"):
        scene_prompts(tmp_path, _cameras())


def test_option_prompts_come_before_the_file_and_no_file_means_none(tmp_path):
    assert scene_prompts(tmp_path, _cameras()) == ((), None)
    (tmp_path / "prompts.json").write_text('{"prompts": [{"image": "0002.png", "point": [5, 5]}]}')
    given, source = scene_prompts(tmp_path, _cameras(), ["0003:1,1,20,20=box"])
    assert source is None and [p.as_text() for p in given] == ["0003.png:1,1,20,20=box"]


def test_update_keeps_what_the_file_holds_and_removes_only_what_is_named(tmp_path):
    path = tmp_path / "prompts.json"
    theirs = {"image": "0001.png", "box": [1, 2, 30, 40], "label": "mug"}
    path.write_text(json.dumps({"prompts": [theirs], "author": "someone"}))
    click = Prompt("0003.png", point=(10.5, 20.0), label="toy")
    held = update_prompts(path, add=[click])
    data = json.loads(path.read_text())
    assert data["author"] == "someone" and data["prompts"] == [theirs, click.as_json()]
    assert [p.as_json() for p in held] == data["prompts"]
    update_prompts(path, add=[click])                    # the same click twice is one prompt
    assert len(json.loads(path.read_text())["prompts"]) == 2
    update_prompts(path, remove=[click])
    assert json.loads(path.read_text())["prompts"] == [theirs]
    assert [p.name for p in tmp_path.iterdir()] == ["prompts.json"]     # no temporary left behind
    path.write_text("{not json")
    with pytest.raises(SceneInputError, match="left as it is"):
        update_prompts(path, add=[click])
    assert path.read_text() == "{not json"
    fresh = tmp_path / "new" / "prompts.json"
    update_prompts(fresh, add=[click])
    assert read_prompts_file(fresh) == [Prompt("0003.png", point=(10.5, 20.0), label="toy", origin="prompts.json[0]")]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from phirie_jax.synthetic import synthesize

    root = tmp_path_factory.mktemp("prompted") / "scene"
    synthesize(root, preset="tiny")
    return root


@pytest.mark.parametrize("args, said", [
    (["--prompt", "nope.png:1,2,3,4"],
     "--prompt 'nope.png:1,2,3,4': no image 'nope.png' in the cameras (expected one of 0000.png"),
    (["--prompt", "0003:1,2,300,4"], "box [1, 2, 300, 4] leaves the image 0003.png"),
    (["--prompt", "0003:1,2,3"], "3 numbers"),
    (["--prompt", "0003:5,5", "--masks", "auto"], "--prompt: and --masks auto are two mask sources"),
    (["--prompt", "0003:50,50", "--prompt", "0004:50,50", "--known-size", "3=0.1"],
     "--prompt: --known-size: no instance 3 in the prompts (their instance ids: 1, 2)"),
])
def test_the_command_refuses_bad_prompts_before_any_work(tiny, tmp_path, capsys, args, said):
    from phirie_jax.cli import main

    out = tmp_path / "out"
    assert main(["convert", str(tiny), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert said in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_a_bad_prompts_json_is_refused_and_masks_leave_it_unused(tiny, tmp_path, capsys):
    from phirie_jax.cli import main

    scene = tmp_path / "scene"
    shutil.copytree(tiny, scene)
    (scene / "prompts.json").write_text('{"prompts": [{"image": "0003.png", "point": [500, 5]}]}')
    assert main(["observe", str(scene), "--out", str(tmp_path / "out")]) == 2
    assert "prompts.json: prompts[0]: point [500, 5] is outside the image" in capsys.readouterr().err
    from phirie_jax.pipeline import scene_prompts as pipeline_prompts

    loaded = load_scene(scene)
    assert pipeline_prompts(loaded, "files", (), None) == ((), None)
    assert "prompts.json is not used (--masks files given)" in capsys.readouterr().err
