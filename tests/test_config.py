"""Configuration: presets, ``--set`` parsing, Python overrides, and one-line error messages."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safelane.config import (
    ENV_PRESETS,
    ConfigError,
    build_config,
    config_to_dict,
    load_config,
    parse_set,
    preset_path,
)


def error_of(**kwargs: object) -> str:
    """The message of the ConfigError that ``load_config(**kwargs)`` raises (asserted one line)."""
    with pytest.raises(ConfigError) as info:
        load_config(**kwargs)  # type: ignore[arg-type]
    message = str(info.value)
    assert "\n" not in message
    return message


# --- presets ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ENV_PRESETS)
def test_presets_load_with_the_papers_traffic(name: str) -> None:
    cfg = load_config(name)
    assert cfg.preset == name
    assert preset_path(name).exists()
    assert cfg.env["lanes_count"] == 4
    assert cfg.env["vehicles_count"] == 50
    assert cfg.env["duration"] == 40
    assert cfg.env["policy_frequency"] == 1
    assert cfg.shield.mode == "none"


def test_presets_pick_their_highway_env() -> None:
    assert load_config("fast").env_id == "highway-fast-v0"
    assert load_config("paper").env_id == "highway-v0"


def test_config_round_trips_through_a_plain_dict() -> None:
    cfg = load_config("fast", sets=["shield.mode=robust", "reward.c=3"])
    assert build_config(config_to_dict(cfg)) == cfg


# --- error messages ----------------------------------------------------------------------------------


def test_unknown_top_level_key_lists_the_sections() -> None:
    message = error_of(sets=["rewards.c=1"])
    assert message.startswith("rewards: unknown key")
    assert "env, reward, traffic, shield" in message


def test_unknown_section_key_lists_the_sections_keys() -> None:
    message = error_of(sets=["reward.d=1"])
    assert message.startswith("reward.d: unknown key")
    assert "b, c, v_min, v_max" in message


def test_unknown_highway_env_key_names_it_and_the_allowed_keys() -> None:
    message = error_of(sets=["env.lanes_countt=3"])
    assert message.startswith("env.lanes_countt: unknown highway-env key for highway-fast-v0")
    assert "lanes_count" in message.split("allowed:")[1]


def test_wrong_type_for_a_highway_env_key_names_the_key() -> None:
    message = error_of(sets=["env.lanes_count=banana"])
    assert message.startswith("env.lanes_count:")
    assert "positive integer" in message
    assert "'banana'" in message


@pytest.mark.parametrize(
    ("assignment", "key"),
    [
        ("env.lanes_count=0", "env.lanes_count"),
        ("env.lanes_count=2.5", "env.lanes_count"),
        ("env.duration=true", "env.duration"),
        ("env.offroad_terminal=1", "env.offroad_terminal"),
        ("env.observation=Kinematics", "env.observation"),
    ],
)
def test_wrong_highway_env_values_are_rejected(assignment: str, key: str) -> None:
    assert error_of(sets=[assignment]).startswith(f"{key}: expected")


def test_bad_shield_mode_lists_the_modes() -> None:
    message = error_of(sets=["shield.mode=strict"])
    assert message.startswith("shield.mode: got 'strict'")
    for mode in ("none", "nominal", "robust"):
        assert f"'{mode}'" in message


def test_a_field_of_another_mode_is_an_error_not_ignored() -> None:
    """``shield.formula`` is the nominal mode's: under another mode a value away from the default is one line
    naming the field and its allowed value; so are ``shield.redraw_uncertified`` and ``shield.redraw_tries`` away
    from the committed mode. ``shield.reading`` accepts only the committed mode's one reading, under that mode."""
    assert load_config("fast", sets=["shield.mode=nominal", "shield.formula=paper"]).shield.formula == "paper"
    for mode in ("none", "robust", "committed"):
        with pytest.raises(ConfigError, match=r"^shield\.formula: only for shield\.mode nominal .*'kinematic'$"):
            load_config("fast", sets=[f"shield.mode={mode}", "shield.formula=paper"])
    assert load_config("fast", sets=["shield.mode=robust", "shield.formula=kinematic"]).shield.mode == "robust"
    with pytest.raises(ConfigError, match=r"^shield\.reading: 'sound' was removed") as err:
        load_config("fast", sets=["shield.mode=committed", "shield.reading=sound"])
    assert "\n" not in str(err.value)
    cfg = load_config("fast", sets=["shield.mode=committed", "shield.reading=responsibility"])
    assert "reading" not in cfg.shield.model_dump()
    for mode in ("none", "nominal", "robust"):
        reading_error = rf"^shield\.reading: only for shield\.mode committed \(got mode '{mode}'\)"
        with pytest.raises(ConfigError, match=reading_error):
            load_config("fast", sets=[f"shield.mode={mode}", "shield.reading=responsibility"])
        with pytest.raises(ConfigError, match=r"^shield\.redraw_uncertified: only for shield\.mode committed .*false$"):
            load_config("fast", sets=[f"shield.mode={mode}", "shield.redraw_uncertified=true"])
        with pytest.raises(ConfigError, match=r"^shield\.redraw_tries: only for shield\.mode committed .*20$"):
            load_config("fast", sets=[f"shield.mode={mode}", "shield.redraw_tries=5"])
    assert load_config("fast", sets=["shield.mode=committed", "shield.redraw_tries=5"]).shield.redraw_tries == 5


@pytest.mark.parametrize("v_max", ["0", "-10"])
def test_reward_v_max_must_exceed_v_min(v_max: str) -> None:
    message = error_of(sets=[f"reward.v_max={v_max}"])
    assert message.startswith("reward.v_max: must be greater than reward.v_min (0.0)")
    assert "Value error" not in message


def test_negative_reward_weight_is_rejected() -> None:
    assert error_of(sets=["reward.c=-1"]).startswith("reward.c: ")


def test_unknown_preset_lists_the_presets() -> None:
    assert error_of(preset="fastest") == "preset: unknown preset 'fastest'; allowed: fast, paper, hidden-types"


def test_config_error_is_a_value_error() -> None:
    assert issubclass(ConfigError, ValueError)


def test_setting_a_value_below_a_value_is_an_error() -> None:
    assert error_of(sets=["reward.c.x=1"]) == "reward.c.x: 'c' is a value, not a section"


# --- --set parsing ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("assignment", "expected"),
    [
        ("env.lanes_count=5", ("env.lanes_count", 5)),
        ("reward.c=2.5", ("reward.c", 2.5)),
        ("shield.override=true", ("shield.override", True)),
        ("shield.mode=robust", ("shield.mode", "robust")),
        ("env.action.target_speeds=[10, 20]", ("env.action.target_speeds", [10, 20])),
        (" env.duration = 7", ("env.duration", 7)),
        ("env.duration=", ("env.duration", None)),
        ("a=b=c", ("a", "b=c")),
        # YAML 1.1 reads an exponent without a dot as a string; --set means a number, at any depth
        ("reward.c=1e-3", ("reward.c", 0.001)),
        ("env.action.target_speeds=[1e-09, 1e-09]", ("env.action.target_speeds", [1e-09, 1e-09])),
        ("env.action.target_speeds=[0, 1.5e1, -2E+1]", ("env.action.target_speeds", [0, 15.0, -20.0])),
        ('shield.mode="1e-3"', ("shield.mode", "1e-3")),  # quoted: a string
    ],
)
def test_parse_set(assignment: str, expected: tuple[str, object]) -> None:
    assert parse_set(assignment) == expected


@pytest.mark.parametrize(("assignment", "fragment"), [("env.lanes_count", "expected KEY=VALUE"), ("=5", "empty key")])
def test_parse_set_errors(assignment: str, fragment: str) -> None:
    with pytest.raises(ConfigError, match=fragment):
        parse_set(assignment)


@settings(max_examples=25, deadline=None)
@given(st.integers(min_value=1, max_value=9), st.floats(min_value=0, max_value=100, allow_nan=False))
def test_set_values_reach_the_config(lanes: int, c: float) -> None:
    cfg = load_config("fast", sets=[f"env.lanes_count={lanes}", f"reward.c={c!r}"])
    assert cfg.env["lanes_count"] == lanes
    assert cfg.reward.c == c


def test_nested_set_keeps_the_rest_of_the_section() -> None:
    cfg = load_config("fast", sets=["env.action.target_speeds=[20, 25, 30]"])
    assert cfg.env["action"] == {"type": "DiscreteMetaAction", "target_speeds": [20, 25, 30]}


# --- Python overrides ----------------------------------------------------------------------------------


def test_section_dict_override_merges_into_the_preset() -> None:
    cfg = load_config("fast", overrides={"env": {"lanes_count": 5}, "reward": {"c": 3.0}})
    assert cfg.env["lanes_count"] == 5
    assert cfg.env["vehicles_count"] == 50  # untouched keys of the section stay
    assert cfg.reward.c == 3.0
    assert cfg.reward.v_max == 30.0


def test_dotted_override_and_order_sets_then_overrides() -> None:
    cfg = load_config("fast", sets=["shield.mode=nominal", "reward.b=2"], overrides={"shield.mode": "robust"})
    assert cfg.shield.mode == "robust"  # Python overrides come last
    assert cfg.reward.b == 2.0


def test_overrides_are_validated_like_sets() -> None:
    with pytest.raises(ConfigError, match=r"^env\.lanes_count: expected positive integer"):
        load_config("fast", overrides={"env": {"lanes_count": "banana"}})


def test_overrides_do_not_alias_the_callers_objects() -> None:
    speeds = [20, 25, 30]
    cfg = load_config("fast", overrides={"env.action.target_speeds": speeds})
    speeds.append(35)
    assert cfg.env["action"]["target_speeds"] == [20, 25, 30]


def test_recorded_configs_keep_the_rule_they_ran_with() -> None:
    """A configuration read back from a run or a counterexample file that names its rule by options as keys of
    their own replays with the options it lacks off (the rule it was written under); one with ``shield.rule``, or
    a new configuration, gets the named rule."""
    from safelane.config import recorded_config
    from safelane.safety.rule import OPTION_NAMES, RULES

    data = config_to_dict(load_config("fast"))
    assert data["shield"]["rule"] == "forecast-fallback" and data["shield"]["options"] == {}
    assert recorded_config(data).shield.resolved_rule() == RULES["forecast-fallback"]
    flat = {k: v for k, v in data["shield"].items() if k not in ("rule", "options")}
    every = {**data, "shield": {**flat, **dict.fromkeys(OPTION_NAMES, True)}}  # a file listing every option on
    assert recorded_config(every).shield.rule == "forecast-fallback" and recorded_config(every).shield.options == {}
    old = {**data, "shield": {**flat, **dict.fromkeys([n for n in OPTION_NAMES if n != "body_extent"], True)}}
    cfg = recorded_config(old)
    assert cfg.shield.rule == "forecast-fallback" and cfg.shield.options == {"body_extent": False}
    assert build_config(old).shield.resolved_rule() == RULES["forecast-fallback"]  # a key of its own: an override
    assert recorded_config({**data, "shield": flat}).shield.rule == "basic"  # no option named: the basic rule
    worst = {**data, "shield": {**flat, **dict.fromkeys(OPTION_NAMES, True), "forecast_fallback": False}}
    assert recorded_config(worst).shield.rule == "worst-case-fallback"


def test_recorded_configs_with_a_removed_option() -> None:
    """A removed option (measured, not adopted) in a recorded file: at the value it always had it is dropped; at
    the other one the file cannot replay: a one-line error naming the option and the commit that has it."""
    from safelane.config import recorded_config

    data = config_to_dict(load_config("fast"))
    flat = {k: v for k, v in data["shield"].items() if k not in ("rule", "options")}
    cfg = recorded_config({**data, "shield": {**flat, "projected_cut_ins": False, "body_extent": True}})
    assert cfg.shield.rule == "basic" and cfg.shield.options == {"body_extent": True}
    with pytest.raises(ConfigError, match=r"^shield\.robust_fallback: .*removed.*changelog") as err:
        recorded_config({**data, "shield": {**flat, "robust_fallback": True}})
    assert "\n" not in str(err.value)


def test_a_check_record_of_an_earlier_rule_is_not_resumed(tmp_path) -> None:
    """A sim-check record that names its rule by options and lacks shield.body_extent was made without it:
    resuming it under the default rule would mix two rules in one sample, so it is refused in one line."""
    import json

    import pytest

    from safelane.config import ConfigError, config_to_dict, load_config
    from safelane.running.simcheck import CheckRecord
    from safelane.safety.rule import OPTION_NAMES

    header = {"config": config_to_dict(load_config("fast")), "seed": 0, "tolerance": 1e-6}
    record = tmp_path / "check.jsonl"
    CheckRecord(record, header)  # written now: resumes
    assert CheckRecord(record, header).done == {}
    flat = {k: v for k, v in header["config"]["shield"].items() if k not in ("rule", "options")}
    flat |= {name: True for name in OPTION_NAMES if name != "body_extent"}  # options as keys of their own
    old = {**header, "config": {**header["config"], "shield": flat}}
    earlier = tmp_path / "earlier.jsonl"
    earlier.write_text(json.dumps({"header": old}) + "\n")
    with pytest.raises(ConfigError, match="another configuration"):
        CheckRecord(earlier, header)


def test_every_rule_option_reaches_the_shield_of_make_env_and_of_the_batch() -> None:
    """Each rule option, flipped in the config (``shield.options``), is flipped in the rule of the shield
    ``make_env`` builds and in the flags the fast batch hands its kernel (one rule feeds both)."""
    import numpy as np

    from safelane.env.factory import make_env
    from safelane.env.fast_batch import FastBatch
    from safelane.safety.one_decision.compiled import KernelConstants
    from safelane.safety.rule import OPTIONS, RULES
    from safelane.safety.shield import SafetyShield

    for option in OPTIONS:
        value = not option.default
        sets = {"shield.mode": "robust", f"shield.options.{option.name}": value, "env.vehicles_count": 5}
        env = make_env("fast", seed=0, simulator="fast", **sets)
        assert isinstance(env, SafetyShield) and getattr(env.dynamics.rule, option.name) is value
        assert env.dynamics.rule == RULES["forecast-fallback"].with_options(**{option.name: value})
        batch = FastBatch(env.safelane_config, 1)
        batch.reset_envs(np.array([0]), [0])
        assert batch._kernel_args is not None
        constants = KernelConstants(*batch._kernel_args[7:])  # after the leave times, speed limit and lane frame
        assert constants.flags == env.dynamics.rule.flags
