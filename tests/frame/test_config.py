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


@pytest.mark.parametrize("options, option", [
    (dict(marker_size=0.0), "--marker-size"), (dict(marker_size=float("inf")), "--marker-size"),
    (dict(marker_size=0.05, scale=2.0), "--marker-size"),
    (dict(marker_size=0.05, marker_dictionary="DICT_9X9_1"), "--marker-dictionary"),
    (dict(marker_dictionary="DICT_4X4_50"), "--marker-dictionary"),
])
def test_marker_options_are_checked(options, option):
    with pytest.raises(OptionError) as err:
        FrameConfig(**options).checked()
    assert str(err.value).startswith(option + ":")


def test_marker_size_is_an_option_of_convert_and_observe_and_a_scale_of_its_own(tmp_path, capsys):
    assert FrameConfig(marker_size=0.05, marker_dictionary="DICT_APRILTAG_36h11").checked().marker_size == 0.05
    assert merged(FrameConfig(metric=True), FrameConfig(marker_size=0.05)) == FrameConfig(marker_size=0.05)
    for command in ("convert", "observe"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        assert "--marker-size" in capsys.readouterr().out
    out = tmp_path / "out"
    assert main(["convert", str(tmp_path), "--out", str(out), "--marker-size", "-1"]) == 2
    assert capsys.readouterr().err.startswith("phirie: error: --marker-size: -1.0") and not out.exists()


def test_synth_marker_option_is_checked(tmp_path, capsys):
    assert main(["synth", str(tmp_path / "s"), "--preset", "tiny", "--marker", "-0.1"]) == 2
    assert capsys.readouterr().err.startswith("phirie: error: --marker: -0.1")
    assert main(["synth", str(tmp_path / "s"), "--preset", "tiny", "--marker", "2.0"]) == 2
    assert "does not fit on the 1.2 × 0.8 m table top" in capsys.readouterr().err
    assert main(["synth", str(tmp_path / "s"), "--preset", "tiny", "--marker", "0.1", "--fitted"]) == 2
    assert "--marker: given with --fitted" in capsys.readouterr().err


def test_the_up_choices_are_the_axes():
    import typing

    from phirie_jax.frame.config import AXES, Axis

    assert typing.get_args(Axis) == tuple(AXES)
