"""A config surface that cannot crash: every bad value is one ``error:`` line and exit code 2.

Each case goes through the real command line (typer's CliRunner, stderr kept apart from stdout), and
the property test drives every key the shipped presets set, plus every field of the safelane sections,
with wrong types and out-of-range values through ``env show`` and ``evaluate``.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from safelane.cli import app
from safelane.config import (
    ENV_PRESETS,
    ConfigError,
    SafelaneConfig,
    ShieldConfig,
    TrafficConfig,
    build_config,
    config_to_dict,
    load_config,
    parse_set,
    preset_path,
)

runner = CliRunner()
SRC = Path(__file__).resolve().parents[1] / "src"
"""This checkout's package, for the installed script run in a subprocess."""

EVALUATE = ("evaluate", "--policy", "random", "--episodes", "1")
SHOW = ("env", "show")
COMMANDS = (SHOW, EVALUATE)


def assert_config_error(args: list[str], key: str) -> str:
    """``safelane ARGS`` exits 2 with exactly one stderr line ``error: ...`` naming ``key``; returns it."""
    result = runner.invoke(app, args)
    assert result.exit_code == 2, (args, result.output)
    assert result.stdout == "", (args, result.stdout)
    assert "Traceback" not in result.stderr, (args, result.stderr)
    assert result.exception is None or isinstance(result.exception, SystemExit), (args, result.exception)
    lines = result.stderr.splitlines()
    assert len(lines) == 1, (args, result.stderr)
    assert lines[0].startswith("error: "), (args, lines[0])
    assert key in lines[0], (args, key, lines[0])
    return lines[0]


# --- the reported cases ----------------------------------------------------------------------------


@pytest.mark.parametrize("command", COMMANDS, ids=["env-show", "evaluate"])
@pytest.mark.parametrize(
    ("sets", "key", "says"),
    [
        (["env.action.target_speeds=[]"], "env.action.target_speeds", "at least 2"),
        (["env.action.target_speeds=[30,20]"], "env.action.target_speeds", "strictly increasing"),
        (["env.simulation_frequency=3", "env.policy_frequency=2"], "env.simulation_frequency", "whole multiple"),
        (["env.vehicles_density=-1"], "env.vehicles_density", "> 0"),
        (["env.duration=0.5"], "env.duration", "at least one decision period"),
    ],
    ids=["empty-target-speeds", "decreasing-target-speeds", "fractional-frames", "negative-density", "short-duration"],
)
def test_reported_case_is_one_error_line(command: tuple[str, ...], sets: list[str], key: str, says: str) -> None:
    args = [*command]
    for assignment in sets:
        args += ["--set", assignment]
    line = assert_config_error(args, key)
    assert line.startswith(f"error: {key}:"), line
    assert says in line, line


def test_render_to_an_unwritable_place_is_one_error_line() -> None:
    line = assert_config_error(
        ["render", "--policy", "random", "--out", "/proc/x.gif", "--max-steps", "1", "--set", "env.duration=2"],
        "out_path",
    )
    assert "/proc" in line
    assert not Path("/proc/x.gif").exists()


def test_script_render_to_an_unwritable_place_prints_no_traceback(safelane_exe: Path) -> None:
    """The installed script, in its own process: nothing may print a traceback at exit either."""
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy", "PYTHONPATH": str(SRC)}
    args = ["render", "--policy", "random", "--out", "/proc/x.gif", "--max-steps", "1", "--set", "env.duration=2"]
    proc = subprocess.run([str(safelane_exe), *args], capture_output=True, text=True, env=env, timeout=120, check=False)
    assert proc.returncode == 2, proc.stderr
    assert proc.stdout == ""
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: out_path: "), proc.stderr
    assert "Traceback" not in proc.stderr


def test_render_next_to_a_file_is_one_error_line(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("keep me")
    out = blocker / "episode.gif"
    assert_config_error(["render", "--policy", "idle", "--out", str(out), "--max-steps", "1"], "out_path")
    assert blocker.read_text() == "keep me"


def test_render_into_a_new_directory_still_works(tmp_path: Path) -> None:
    out = tmp_path / "new" / "dir" / "episode.gif"
    result = runner.invoke(app, ["render", "--policy", "idle", "--out", str(out), "--max-steps", "1"])
    assert result.exit_code == 0, result.output
    assert out.stat().st_size > 0
    assert [p.name for p in out.parent.iterdir()] == ["episode.gif"]  # the write probe leaves nothing behind


# --- more bad values, each naming its key ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("assignment", "key"),
    [
        ("env.action.target_speeds=[0, 1, 30]", "env.action.target_speeds"),  # uneven: FASTER would stick at 1 m/s
        ("env.action.target_speeds=[20, 20]", "env.action.target_speeds"),
        ("env.action.target_speeds=[-5, 0, 5]", "env.action.target_speeds"),
        ("env.action.target_speeds=[20, 60, 100]", "env.action.target_speeds"),  # above highway-env's 40 m/s cap
        ("env.action.target_speeds=[20, .nan]", "env.action.target_speeds"),
        ("env.action.target_speeds=[20, true]", "env.action.target_speeds"),
        ("env.action.target_speeds=25", "env.action.target_speeds"),
        ("env.action.type=ContinuousAction", "env.action.type"),
        ("env.action.type=DiscreteAction", "env.action.type"),
        ("env.action.lateral=false", "env.action.lateral"),
        ("env.action.target_speed=[20, 30]", "env.action.target_speed"),  # a typo, ignored by highway-env
        ("env.action=DiscreteMetaAction", "env.action"),
        ("env.action=", "env.action"),
        ("env.action={}", "env.action.type"),
        ("env.observation.type=Grayscale", "env.observation.type"),
        ("env.observation.vehicles_count=0", "env.observation.vehicles_count"),
        ("env.observation.features=[presence, speed]", "env.observation.features"),
        ("env.observation.features=[]", "env.observation.features"),
        ("env.observation.order=random", "env.observation.order"),
        ("env.observation.normalize=1", "env.observation.normalize"),
        ("env.observation.features_range={x: [1, -1]}", "env.observation.features_range.x"),
        ("env.observation.vehicle_count=3", "env.observation.vehicle_count"),
        ("env.lanes_count=4.0", "env.lanes_count"),
        ("env.lanes_count=-2", "env.lanes_count"),
        ("env.vehicles_count=.inf", "env.vehicles_count"),
        ("env.duration=-40", "env.duration"),
        ("env.duration=.nan", "env.duration"),
        ("env.duration=", "env.duration"),
        ("env.duration=forty", "env.duration"),
        ("env.policy_frequency=0", "env.policy_frequency"),
        ("env.policy_frequency=2", "env.simulation_frequency"),  # 5 Hz physics (fast) is not a multiple of 2
        ("env.simulation_frequency=true", "env.simulation_frequency"),
        ("env.ego_spacing=0", "env.ego_spacing"),
        ("env.ego_spacing=-1.5", "env.ego_spacing"),
        ("env.vehicles_density=0", "env.vehicles_density"),
        ("env.vehicles_density=.inf", "env.vehicles_density"),
        ("env.controlled_vehicles=2", "env.controlled_vehicles"),
        ("env.initial_lane_id=4", "env.initial_lane_id"),
        ("env.other_vehicles_type=highway_env.vehicle.behavior.NoSuchVehicle", "env.other_vehicles_type"),
        ("env.other_vehicles_type=os.path", "env.other_vehicles_type"),
        ("env.reward_speed_range=[30, 20]", "env.reward_speed_range"),
        ("env.screen_width=0", "env.screen_width"),
        ("env.collision_reward=.nan", "env.collision_reward"),
        ("env=[1, 2]", "env"),
        ("reward.c=.nan", "reward.c"),
        ("reward.b=.inf", "reward.b"),
        ("reward.b=true", "reward.b"),
        ("reward.c='3'", "reward.c"),
        ("reward=5", "reward"),
        ("traffic.vehicles_behind=2.0", "traffic.vehicles_behind"),
        ("traffic.vehicles_behind=51", "traffic.vehicles_behind"),  # more than the 50 vehicles there are
        ("traffic.vehicles_behind=false", "traffic.vehicles_behind"),
        ("traffic.adversary=ghost", "traffic.adversary"),
        ("shield.override=1", "shield.override"),
        ("shield.mode=true", "shield.mode"),
        ("shield.engine=gpu", "shield.engine"),
        ("state=pixels", "state"),
        ("neighbour_search=gpu", "neighbour_search"),
        ("simulator=warp", "simulator"),
        ("env_id=highway-v9", "env_id"),
        ("preset=moon", "preset"),
    ],
)
def test_bad_value_is_one_error_line_naming_the_key(assignment: str, key: str) -> None:
    line = assert_config_error([*SHOW, "--set", assignment], key)
    assert line.startswith(f"error: {key}:"), line


def test_cut_in_adversary_needs_a_second_lane() -> None:
    line = assert_config_error(
        [*SHOW, "--set", "env.lanes_count=1", "--set", "traffic.adversary=cut_in"], "lanes_count"
    )
    assert line.startswith("error: traffic.adversary:"), line


def test_nan_in_a_run_config_is_rejected_on_load() -> None:
    data = config_to_dict(load_config("fast"))
    data["env"]["ego_spacing"] = float("nan")
    with pytest.raises(ConfigError, match=r"^env\.ego_spacing: "):
        build_config(data)


# --- the library rejects what the command line rejects ----------------------------------------------------


LIBRARY_CASES = [
    ({"env.action.target_speeds": []}, "env.action.target_speeds"),
    ({"env": {"simulation_frequency": 3, "policy_frequency": 2}}, "env.simulation_frequency"),
    ({"env.vehicles_density": -1}, "env.vehicles_density"),
    ({"env.duration": 0.5}, "env.duration"),
    ({"reward.c": math.nan}, "reward.c"),
]


@pytest.mark.parametrize(("overrides", "key"), LIBRARY_CASES)
def test_load_config_and_make_env_reject(overrides: dict[str, Any], key: str) -> None:
    from safelane.env.factory import make_env

    with pytest.raises(ConfigError, match=rf"^{key}: "):
        load_config("fast", overrides=overrides)
    with pytest.raises(ConfigError, match=rf"^{key}: "):
        make_env("fast", **overrides)
    with pytest.raises(ConfigError, match=rf"^{key}: "):
        make_env(load_config("fast"), **overrides)


def test_a_config_built_directly_is_validated_too() -> None:
    with pytest.raises(ValueError, match=r"env\.vehicles_density"):
        SafelaneConfig(env={"vehicles_density": -1})
    cfg = SafelaneConfig()
    with pytest.raises(ValueError, match=r"env\.duration"):
        cfg.env = {"duration": 0}


# --- the allowed edges stay allowed ------------------------------------------------------------------------


@pytest.mark.parametrize("name", ENV_PRESETS)
def test_presets_are_valid(name: str) -> None:
    result = runner.invoke(app, [*SHOW, "--preset", name])
    assert result.exit_code == 0, result.output
    assert yaml.safe_load(result.stdout)["preset"] == name


@pytest.mark.parametrize(
    "sets",
    [
        ["env.action.target_speeds=[20, 25, 30]"],
        ["env.action.target_speeds=[0, 40]"],
        ["env.action.target_speeds=[0.0, 2.5, 5.0, 7.5]"],
        ["env.lanes_count=1"],
        ["env.vehicles_count=1"],
        ["env.policy_frequency=5", "env.simulation_frequency=5"],
        ["env.policy_frequency=2", "env.simulation_frequency=10", "env.duration=0.5"],
        ["env.duration=1"],
        ["env.duration=40.5"],
        ["env.ego_spacing=0.1", "env.vehicles_density=1e-3"],
        ["env.initial_lane_id=3"],
        ["env.initial_lane_id=null"],
        ["env.observation.order=shuffled", "env.observation.features=[presence, x, vx]"],
        ["env.observation.features=null", "env.observation.features_range=null", "env.action.target_speeds=null"],
        ["env.other_vehicles_type=highway_env.vehicle.behavior.AggressiveVehicle"],
        ["traffic.vehicles_behind=50", "traffic.adversary=cut_in"],
        ["reward.v_min=-5", "reward.b=0", "reward.c=1e-3"],
        ["env.action.longitudinal=true", "env.action.lateral=true"],
    ],
)
def test_allowed_edge_values_are_accepted(sets: list[str]) -> None:
    load_config("fast", sets=sets)
    load_config("paper", sets=sets)


def test_every_stress_condition_is_still_valid() -> None:
    from safelane.running.conditions import condition_config, load_conditions

    for cond in load_conditions():
        condition_config(cond, "robust", True)


# --- property: any wrong value of any preset key ---------------------------------------------------------


def _leaves(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Every dotted key of a nested dict, sections included, with its value."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        dotted = f"{prefix}{key}"
        out[dotted] = value
        if isinstance(value, dict):
            out.update(_leaves(value, f"{dotted}."))
    return out


def _preset_keys() -> dict[str, Any]:
    """Every key the shipped presets set (read from their YAML), plus the safelane sections' fields."""
    keys: dict[str, Any] = {}
    for name in ENV_PRESETS:
        keys.update(_leaves(yaml.safe_load(preset_path(name).read_text())))
    for section, model in (("traffic", TrafficConfig), ("shield", ShieldConfig)):
        keys[section] = {}
        for field, info in model.model_fields.items():
            keys[f"{section}.{field}"] = info.default
    for field, info in SafelaneConfig.model_fields.items():  # env_id, state, simulator…: the scalar fields
        if field not in keys and field != "preset":
            keys[field] = info.default
    return dict(sorted(keys.items()))


PRESET_KEYS = _preset_keys()
NEGATIVE_ALLOWED = {"reward.v_min"}
"""Numeric keys for which a negative number is a valid value (every other one must be >= 0, env ones > 0)."""


def to_yaml(value: Any) -> str:
    """``value`` as the YAML text of a ``--set`` (strings always quoted, so they stay strings)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null"
    if isinstance(value, float) and not math.isfinite(value):
        return ".nan" if math.isnan(value) else (".inf" if value > 0 else "-.inf")
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(to_yaml(v) for v in value) + "]"
    return "{" + ", ".join(f"{json.dumps(k)}: {to_yaml(v)}" for k, v in value.items()) + "}"


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a):
        return math.isnan(b)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return type(a) is type(b) and a == b


NON_FINITE = st.sampled_from([math.nan, math.inf, -math.inf])
TEXT = st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=8)
"""Printable ASCII: what a user types, and what YAML's double quotes carry unchanged."""
BAD_STRINGS = st.one_of(st.just(""), TEXT.map(lambda s: s + "?!"))
"""Strings no key accepts (no allowed name holds '?')."""
NUMBERS = st.one_of(st.integers(-(10**6), 10**6), st.floats(allow_nan=False, allow_infinity=False, width=32))
SCALARS = st.one_of(st.booleans(), st.none(), NUMBERS, BAD_STRINGS)
CONTAINERS = st.one_of(st.lists(SCALARS, max_size=3), st.dictionaries(TEXT, SCALARS, max_size=2))


def _bad_numbers(key: str, example: Any) -> st.SearchStrategy[Any]:
    """Wrong types, non-finite numbers and out-of-range numbers for a numeric key."""
    wrong = [st.booleans(), st.none(), BAD_STRINGS, CONTAINERS, NON_FINITE]
    if key not in NEGATIVE_ALLOWED:
        negative = st.one_of(
            st.integers(max_value=-1), st.floats(max_value=-1e-6, allow_nan=False, allow_infinity=False)
        )
        wrong.append(negative)
        if key.startswith("env."):
            wrong.append(st.just(0))  # counts, frequencies, durations, spacings and densities are all > 0
    if key.endswith(("_count", "_frequency", "vehicles_behind")):  # counts and frequencies are whole numbers
        wrong.append(st.floats(allow_nan=False, allow_infinity=False).filter(lambda x: not float(x).is_integer()))
        wrong.append(st.integers(1, 60).map(float))
    if key == "reward.v_max":
        wrong.append(st.floats(max_value=0, allow_nan=False, allow_infinity=False))  # must exceed v_min = 0
    return st.one_of(*wrong)


def _bad_lists(key: str) -> st.SearchStrategy[Any]:
    """Wrong types and out-of-range lists for a list key."""
    # null is allowed (highway-env's defaults), so the wrong scalars leave it out
    scalars = st.one_of(st.booleans(), NUMBERS, BAD_STRINGS)
    wrong = [scalars, st.dictionaries(TEXT, SCALARS, max_size=2), st.just([])]
    if key.endswith("target_speeds"):
        from highway_env.vehicle.kinematics import Vehicle

        speed = st.floats(0, Vehicle.MAX_SPEED)
        wrong += [
            st.lists(st.one_of(st.booleans(), st.none(), BAD_STRINGS, NON_FINITE), min_size=1, max_size=4),
            st.lists(speed, max_size=1),  # fewer than 2 set-points
            st.lists(speed, min_size=2, max_size=5, unique=True).map(lambda s: sorted(s, reverse=True)),
            speed.map(lambda v: [v, v]),
            st.floats(1, 20).map(lambda step: [-step, 0.0, step]),
            st.floats(1, 20).map(lambda step: [Vehicle.MAX_SPEED, Vehicle.MAX_SPEED + step]),
        ]
    else:  # observation features: names highway-env's Kinematics observation does not know
        wrong += [st.lists(st.one_of(BAD_STRINGS, NUMBERS, st.booleans()), min_size=1, max_size=3)]
    return st.one_of(*wrong)


@st.composite
def bad_assignment(draw: st.DrawFn) -> tuple[str, Any]:
    """A preset key and a value it must not accept (or an unknown key below a section)."""
    key = draw(st.sampled_from(list(PRESET_KEYS)))
    example = PRESET_KEYS[key]
    if isinstance(example, bool):
        return key, draw(st.one_of(NUMBERS, st.none(), BAD_STRINGS, CONTAINERS))
    if isinstance(example, int | float):
        return key, draw(_bad_numbers(key, example))
    if isinstance(example, str):
        return key, draw(st.one_of(BAD_STRINGS, NUMBERS, st.booleans(), st.none(), CONTAINERS))
    if isinstance(example, list):
        return key, draw(_bad_lists(key))
    if draw(st.booleans()):  # a section given as a non-dict
        return key, draw(st.one_of(SCALARS, st.lists(SCALARS, max_size=3)))
    name = draw(st.from_regex(r"[a-z][a-z_]{0,10}", fullmatch=True))
    return f"{key}.{name}_typo", draw(SCALARS)  # unknown key inside a section


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    assignment=bad_assignment(),
    command=st.sampled_from(COMMANDS),
    preset=st.sampled_from(ENV_PRESETS),
)
def test_any_bad_value_of_any_preset_key_is_one_error_line(
    assignment: tuple[str, Any], command: tuple[str, ...], preset: str
) -> None:
    key, value = assignment
    text = to_yaml(value)
    assert _same(parse_set(f"{key}={text}")[1], value)  # the CLI sees exactly the generated value
    assert_config_error([*command, "--preset", preset, "--set", f"{key}={text}"], key)


def test_the_property_covers_every_key_the_presets_set() -> None:
    for name in ENV_PRESETS:
        for key in _leaves(yaml.safe_load(preset_path(name).read_text())):
            assert key in PRESET_KEYS
    assert {"state", "env_id", "simulator"} <= set(PRESET_KEYS)
    for key in ("env.action.target_speeds", "env.observation.type", "traffic.vehicles_behind", "shield.override"):
        assert key in PRESET_KEYS
    assert {"state", "env_id", "simulator"} <= set(PRESET_KEYS)
