"""Frame options: bad values are one clear line naming the option; a scene folder's ``frame.json``
declares what the command line may override."""

from __future__ import annotations

import json

import pytest

from phirie_jax.cli import main
from phirie_jax.errors import OptionError, SceneInputError
from phirie_jax.frame.config import FrameConfig, merged, scene_frame_config


@pytest.mark.parametrize("options, option", [
    (dict(scale=0.0), "--scale"), (dict(scale=-2.0), "--scale"), (dict(scale=float("nan")), "--scale"),
    (dict(up="x"), "--up"), (dict(up="+w"), "--up"), (dict(known_size="3"), "--known-size"),
    (dict(known_size="a=0.1"), "--known-size"), (dict(known_size="3=-1"), "--known-size"),
    (dict(known_distance=(0, 0, 0, 0, 0, 0, 1.0)), "--known-distance"),
    (dict(known_distance=(0, 0, 0, 1, 0, 0, 0.0)), "--known-distance"),
    (dict(scale=2.0, metric=True), "--metric"),
])
def test_unusable_options_name_the_option(options, option):
    with pytest.raises(OptionError) as err:
        FrameConfig(**options).checked()
    assert str(err.value).startswith(option + ":") and "\n" not in str(err.value)


def test_known_size_parses():
    assert FrameConfig(known_size="7=0.125").checked().known_size_of() == (7, 0.125)
    assert FrameConfig().known_size_of() is None


def test_cli_prints_one_line_and_leaves_the_output_folder_alone(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["convert", str(tmp_path), "--out", str(out), "--scale", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "phirie: error: --scale: 0.0 (expected a positive number of metres per capture unit)"
    assert not out.exists()
    assert main(["convert", str(tmp_path), "--out", str(out), "--known-size", "x=1"]) == 2
    assert "--known-size" in capsys.readouterr().err and not out.exists()


def test_scene_declaration_and_command_line(tmp_path):
    assert scene_frame_config(tmp_path) == FrameConfig()
    (tmp_path / "frame.json").write_text(json.dumps({"metric": True, "up": "+y"}))
    declared = scene_frame_config(tmp_path)
    assert declared == FrameConfig(up="+y", metric=True)
    assert merged(declared, FrameConfig()) == declared
    assert merged(declared, FrameConfig(scale=2.0)) == FrameConfig(up="+y", scale=2.0)   # a scale replaces "metric"
    assert merged(declared, FrameConfig(up="-z")) == FrameConfig(up="-z", metric=True)
    (tmp_path / "frame.json").write_text(json.dumps({"scale": -1}))
    with pytest.raises(SceneInputError, match="frame.json: scale: -1"):
        scene_frame_config(tmp_path)
    (tmp_path / "frame.json").write_text(json.dumps({"metres": 2}))
    with pytest.raises(SceneInputError, match="metres: unknown key"):
        scene_frame_config(tmp_path)
