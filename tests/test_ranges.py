"""Ranges of numeric settings: every numeric field of every stage config refuses a value outside
its range with one line naming the config, the field, the value and the range; the paper's
defaults pass; the command line names the whole option."""

from __future__ import annotations

import dataclasses
import math
import typing

import pytest

from kernels.registration import SearchSpec
from phirie_jax.cli import main
from phirie_jax.construct.objects.config import PER_CALL_SEARCH_FIELDS, ObjectsConfig, RegistrationConfig
from phirie_jax.construct.physics.config import DropTestConfig, PhysicsConfig
from phirie_jax.errors import ConfigValueError, OptionError
from phirie_jax.interact.rollout import RolloutConfig
from phirie_jax.observe.config import ObserveConfig
from phirie_jax.pipeline import ConvertConfig
from phirie_jax.ranges import (
    AT_LEAST_ONE,
    FRACTION,
    POSITIVE,
    Choice,
    Each,
    Positions,
    Range,
    check_option,
    check_options,
    deferred_checks,
)

BAD_INT = -10**9  # below every integer field's range
BAD_FLOAT = math.nan


def test_ranges_read_as_written_and_refuse_non_finite_values():
    assert str(POSITIVE) == "> 0" and str(AT_LEAST_ONE) == "≥ 1" and str(FRACTION) == "in [0, 1]"
    assert str(Range(0, 1, True, False)) == "in (0, 1]" and str(Range(None, 2, high_open=True)) == "< 2"
    assert str(Range(0.005, bound="voxel")) == "≥ 0.005 (voxel)"
    assert 1e-12 in POSITIVE and 0 not in POSITIVE and math.inf not in POSITIVE and math.nan not in Range()
    assert True not in AT_LEAST_ONE  # a flag is not a number
    assert (1, 4, 16) in Each(AT_LEAST_ONE, increasing=True) and (4, 1) not in Each(AT_LEAST_ONE, increasing=True)
    assert () not in Each(AT_LEAST_ONE) and (0.5, 2) in Positions((FRACTION, AT_LEAST_ONE))


def numeric_fields(cls) -> typing.Iterator[tuple[type, str, object]]:
    """(config class, field, an out-of-range value) for every numeric field under ``cls``."""
    hints = typing.get_type_hints(cls)
    for field in dataclasses.fields(cls):
        kinds = [t for t in typing.get_args(hints[field.name]) or (hints[field.name],) if t is not type(None)]
        kind = kinds[0] if len(kinds) == 1 else None
        if dataclasses.is_dataclass(kind):
            yield from numeric_fields(kind)
        elif kind in (int, float):
            yield cls, field.name, BAD_INT if kind is int else BAD_FLOAT
        elif typing.get_origin(kind) is tuple and typing.get_args(kind)[0] in (int, float):
            values = typing.get_args(kind)
            bad = BAD_INT if values[0] is int else BAD_FLOAT
            yield cls, field.name, (bad,) if values[-1] is Ellipsis else (bad,) * len(values)


def make(cls: type, field: str, value):
    """``cls`` with one field set; the kernel's SearchSpec is checked by the registration config."""
    if cls is SearchSpec:
        return RegistrationConfig(search=SearchSpec(**{field: value}))
    return cls(**{field: value})


CASES = [(cls, field, value) for root in (ConvertConfig, RolloutConfig) for cls, field, value in numeric_fields(root)
         if not (cls is SearchSpec and field in PER_CALL_SEARCH_FIELDS)]


def test_every_stage_config_is_walked():
    owners = {cls for cls, _, _ in CASES}
    assert len(CASES) > 140 and {SearchSpec, DropTestConfig, ObserveConfig, RolloutConfig} <= owners


@pytest.mark.parametrize("cls, field, value", CASES, ids=[f"{c.__name__}.{f}" for c, f, _ in CASES])
def test_every_numeric_field_refuses_a_value_outside_its_range(cls, field, value):
    with pytest.raises(ConfigValueError) as err:
        make(cls, field, value)
    owner = "RegistrationConfig" if cls is SearchSpec else cls.__name__
    name = f"search.{field}" if cls is SearchSpec else field
    assert str(err.value).startswith(f"{owner}.{name} ") and ": expected " in str(err.value)
    assert "\n" not in str(err.value)


def choice_fields(cls) -> typing.Iterator[tuple[type, str, tuple[str, ...]]]:
    """(config class, field, its options) for every ``Literal`` field under ``cls``."""
    hints = typing.get_type_hints(cls)
    for field in dataclasses.fields(cls):
        kinds = [t for t in typing.get_args(hints[field.name]) or (hints[field.name],) if t is not type(None)]
        if typing.get_origin(hints[field.name]) is typing.Literal:
            kinds = [hints[field.name]]
        kind = kinds[0] if len(kinds) == 1 else None
        if dataclasses.is_dataclass(kind):
            yield from choice_fields(kind)
        elif typing.get_origin(kind) is typing.Literal:
            yield cls, field.name, typing.get_args(kind)


CHOICES = [case for root in (ConvertConfig, RolloutConfig) for case in choice_fields(root)]


def test_choices_read_as_written_and_refuse_what_is_not_one():
    options = Choice.of(typing.Literal["auto", "on", "off"])
    assert str(options) == "one of auto, on, off" and "on" in options
    assert "maybe" not in options and None not in options and 1 not in options
    with pytest.raises(TypeError, match="not a Literal of strings"):
        Choice.of(str)


def test_every_choice_field_is_walked():
    assert {(cls.__name__, field) for cls, field, _ in CHOICES} >= {
        ("CoacdConfig", "preprocess"), ("PhysicsConfig", "background"), ("DropTestConfig", "backend"),
        ("DropTestConfig", "solver"), ("DropTestConfig", "jacobian"), ("ObserveConfig", "surface_source"),
        ("SurfaceConfig", "backend"), ("ObjectsConfig", "selection"), ("SearchSpec", "rotation"),
        ("TargetsConfig", "inpaint")}


@pytest.mark.parametrize("cls, field, options", CHOICES, ids=[f"{c.__name__}.{f}" for c, f, _ in CHOICES])
def test_every_choice_field_refuses_a_word_it_does_not_know(cls, field, options):
    for option in options:  # each named option is accepted
        assert getattr(make(cls, field, option), "search" if cls is SearchSpec else field) is not None
    with pytest.raises(ConfigValueError) as err:
        make(cls, field, "bogus")
    owner = "RegistrationConfig" if cls is SearchSpec else cls.__name__
    name = f"search.{field}" if cls is SearchSpec else field
    assert str(err.value) == f"{owner}.{name} bogus: expected one of {', '.join(options)}"


def test_the_command_line_shows_the_choices_and_refuses_others(capsys):
    with pytest.raises(SystemExit):
        main(["convert", "--help"])
    shown = capsys.readouterr().out
    assert "--config.physics.coacd.preprocess {auto,on,off}" in shown
    assert "--config.physics.drop-test.backend {auto,mjx,warp,mujoco}" in shown
    assert "--up {None,+x,-x,+y,-y,+z,-z}" in shown
    with pytest.raises(SystemExit):
        main(["convert", "scene", "--out", "out", "--config.physics.coacd.preprocess", "maybe"])
    assert "maybe" in capsys.readouterr().err


def test_the_paper_defaults_pass():
    check_options(ConvertConfig(), "--config")
    RolloutConfig()
    assert PhysicsConfig().max_hull_vertices <= DropTestConfig().vertex_budget


def test_a_category_mass_must_be_positive():
    with pytest.raises(ConfigValueError, match=r"PhysicsConfig.category_masses mug 0: expected a mass > 0"):
        PhysicsConfig(category_masses=(("mug", 0.0),))


def test_deferred_checks_then_name_the_whole_option_innermost_first():
    with deferred_checks():
        bad = ConvertConfig(observe=ObserveConfig(voxel=-1.0))  # built, not checked
        with pytest.raises(OptionError) as err:
            check_options(bad, "--config")
        assert str(err.value) == "--config.observe.voxel -1: expected > 0"
        with deferred_checks():
            nested = ConvertConfig(objects=ObjectsConfig(registration=RegistrationConfig(search=SearchSpec(num_yaws=0))))
        with pytest.raises(OptionError, match=r"^--config.objects.registration.search.num-yaws 0: expected ≥ 1$"):
            check_options(nested, "--config")
        with deferred_checks():  # the drop test's budget is the cause; max_hull_vertices only exceeds it
            physics = PhysicsConfig(drop_test=DropTestConfig(vertex_budget=2))
        with pytest.raises(OptionError, match=r"^--config.drop-test.vertex-budget 2: expected ≥ 4$"):
            check_options(physics, "--config")
    with pytest.raises(ConfigValueError):  # the deferral ends with its block
        ObserveConfig(voxel=-1.0)


def test_a_plain_option_is_checked_in_the_same_form():
    check_option("--width", None, AT_LEAST_ONE)
    with pytest.raises(OptionError, match=r"^--width 0: expected ≥ 1$"):
        check_option("--width", 0, AT_LEAST_ONE)


@pytest.mark.parametrize("args, line", [
    (["--config.observe.voxel", "-1"], "--config.observe.voxel -1: expected > 0"),
    (["--config.observe.voxel", "0"], "--config.observe.voxel 0: expected > 0"),
    (["--config.objects.registration.search.num-yaws", "0"],
     "--config.objects.registration.search.num-yaws 0: expected ≥ 1"),
    (["--config.physics.drop-test.part-buckets", "4", "1"],
     "--config.physics.drop-test.part-buckets 4 1: expected one or more increasing values, each ≥ 1"),
    (["--observe-width", "-2"], "--observe-width -2: expected ≥ 0"),
])
def test_the_command_line_reports_one_line_before_any_work(tmp_path, capsys, args, line):
    out = tmp_path / "out"
    assert main(["convert", str(tmp_path), "--out", str(out), *args]) == 2
    assert capsys.readouterr().err == f"phirie: error: {line}\n"
    assert not out.exists()
    ObserveConfig()  # the checks are back on after the command
    with pytest.raises(ConfigValueError):
        ObserveConfig(voxel=0.0)


def test_observe_and_droptest_name_their_config_options(tmp_path, capsys):
    assert main(["observe", str(tmp_path), "--out", str(tmp_path / "o"), "--config.surface.voxel", "0"]) == 2
    assert capsys.readouterr().err == "phirie: error: --config.surface.voxel 0: expected > 0\n"
    assert main(["droptest", str(tmp_path), "--config.mass", "-0.3"]) == 2
    assert capsys.readouterr().err == "phirie: error: --config.mass -0.3: expected > 0\n"
    assert main(["simulate", str(tmp_path), "--frames", "0"]) == 2
    assert capsys.readouterr().err == "phirie: error: --frames 0: expected ≥ 1\n"


def test_none_is_unset_for_optional_fields():
    assert ObserveConfig(support_clearance=None).support_clearance is None
    assert RegistrationConfig(hypothesis_batch=None).hypothesis_batch is None
