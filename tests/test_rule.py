"""The rule as data (safelane.safety.rule): options declared once, named rules, flags, and the config keys."""

from __future__ import annotations

import numpy as np
import pytest

from safelane.config import ConfigError, load_config
from safelane.safety import rule as R
from safelane.safety.rule import OPTION_NAMES, OPTIONS, RULES, Rule


def test_every_option_is_declared_once_with_a_one_line_meaning() -> None:
    assert len(set(OPTION_NAMES)) == len(OPTIONS) == 28
    for option in OPTIONS:
        assert option.meaning and "\n" not in option.meaning and option.meaning.endswith(".")
        assert isinstance(option.default, bool)
        assert getattr(R, f"FLAG_{option.name.upper()}") == 1 << OPTION_NAMES.index(option.name)
    for word in ("issue", "sess" + "ion", "earlier", "today"):  # a meaning says what an option does, not when
        assert not any(word in option.meaning.lower() for option in OPTIONS), word


def test_flags_round_trip() -> None:
    """A rule's bitfield gives back every option's value, and the rule it came from."""
    for option in OPTIONS:
        for value in (False, True):
            rule = RULES["forecast-fallback"].with_options(**{option.name: value})
            assert getattr(rule, option.name) is value
            assert Rule(rule.flags) == rule and Rule.of(rule.options) == rule
            assert bool(rule.flags & getattr(R, f"FLAG_{option.name.upper()}")) is value
    assert Rule(0).options == dict.fromkeys(OPTION_NAMES, False)
    assert Rule(R.ALL_FLAGS).options == dict.fromkeys(OPTION_NAMES, True)
    with pytest.raises(ConfigError, match=r"^Rule\.flags: expected an integer in 0\.\."):
        Rule(R.ALL_FLAGS + 1)


def test_the_named_rules_differ_exactly_in_their_declared_options() -> None:
    default, worst, basic = RULES["forecast-fallback"], RULES["worst-case-fallback"], RULES["basic"]
    assert list(RULES) == ["forecast-fallback", "worst-case-fallback", "basic"]
    assert default == Rule.of() and all(default.options.values())  # every option on by default
    assert worst.differences(default) == {"forecast_fallback": False}
    assert basic.differences(default) == dict.fromkeys(R.BASIC_OFF, False)
    assert set(OPTION_NAMES) - set(R.BASIC_OFF) == {"level_incentive"}  # only filters level_cut_ins (off)


def test_unknown_names_are_one_line_errors() -> None:
    with pytest.raises(ConfigError) as err:
        RULES["basic"].with_options(projected_cut_ins=True)
    message = str(err.value)
    assert message.startswith("projected_cut_ins: not an option of the rule; allowed: body_extent, ")
    assert "\n" not in message and all(name in message for name in OPTION_NAMES)
    with pytest.raises(ConfigError, match=r"^body_extent: expected true or false, got 1$"):
        RULES["basic"].with_options(body_extent=1)
    with pytest.raises(ConfigError, match=r"^rule: unknown rule 'newest'; allowed: forecast-fallback, "):
        R.as_rule("newest")
    with pytest.raises(AttributeError):
        _ = RULES["basic"].not_an_option


def test_the_config_selects_a_rule_by_name_and_switches_options() -> None:
    """``--set shield.rule=NAME`` and ``--set shield.options.OPTION=BOOL``; a flat ``shield.OPTION`` key is read
    as ``shield.options.OPTION``; bad names are one-line errors naming the key and the allowed values."""
    assert load_config("fast").shield.resolved_rule() == RULES["forecast-fallback"]
    assert load_config("fast", ["shield.rule=basic"]).shield.resolved_rule() == RULES["basic"]
    cfg = load_config("fast", ["shield.rule=worst-case-fallback", "shield.options.body_extent=false"])
    assert cfg.shield.resolved_rule() == RULES["worst-case-fallback"].with_options(body_extent=False)
    flat = load_config("fast", ["shield.body_extent=false"])
    assert flat.shield.options == {"body_extent": False}
    assert load_config("fast", ["shield.projected_cut_ins=false"]).shield.options == {}  # its value, dropped
    for sets, pattern in (
        (["shield.rule=newest"], r"^shield\.rule: unknown rule 'newest'; allowed: forecast-fallback, "),
        (["shield.options.nope=true"], r"^shield\.options\.nope: not an option of the rule; allowed: "),
        (["shield.options.body_extent=1"], r"^shield\.options\.body_extent: expected true or false, got 1$"),
        (["shield.lateral_schedule=true"], r"^shield\.lateral_schedule: this option was removed .*changelog"),
    ):
        with pytest.raises(ConfigError, match=pattern) as err:
            load_config("fast", sets)
        assert "\n" not in str(err.value)


def test_shield_takes_a_rule_or_its_name() -> None:
    """``SafetyShield(env, rule=...)``: a name or a Rule; at most 9 parameters (a driver mixture and the belief's
    settings come as one, :class:`~safelane.safety.belief.DriverTypes`)."""
    import inspect

    from safelane.env.factory import make_env
    from safelane.safety.shield import SafetyShield

    assert len(inspect.signature(SafetyShield.__init__).parameters) <= 9
    base = make_env("fast", simulator="fast", **{"env.vehicles_count": 3})
    by_name = SafetyShield(base, rule="basic")
    by_rule = SafetyShield(base, rule=RULES["basic"].with_options(body_extent=True))
    assert by_name.rule == RULES["basic"] and by_rule.rule.body_extent
    with pytest.raises(ConfigError, match=r"^rule: unknown rule"):
        SafetyShield(base, rule="newest")


def test_the_shield_asks_a_rule_family() -> None:
    """Both one-decision modes are :class:`RuleFamily` adapters over the one-decision rule; the numpy reference
    reports the conflict that decided each action (its gap is the action's min_gap), the compiled engine the same
    verdict without them. :func:`family_for` builds every mode, the committed one a new family with its own memory;
    a mode outside them is one line."""
    from safelane.env import scenarios
    from safelane.safety.committed.family import CommittedFamily
    from safelane.safety.family import RuleFamily, family_for
    from safelane.safety.one_decision.family import OneDecisionFamily

    for mode in ("nominal", "robust"):
        results = {}
        for engine in ("numpy", "compiled"):
            scene = scenarios.SCENARIOS["leader_may_turn_out"](mode=mode, **{"shield.engine": engine})
            family = scene.shield.family
            assert isinstance(family, OneDecisionFamily) and family == family_for(mode, engine)
            assert isinstance(family, RuleFamily)
            results[engine] = scene.result
        numpy_result, compiled_result = results["numpy"], results["compiled"]
        assert numpy_result.mask.tolist() == compiled_result.mask.tolist()
        assert compiled_result.conflicts is None and numpy_result.conflicts
        for conflict in numpy_result.conflicts:
            assert conflict.gap == numpy_result.min_gap[conflict.action]
        assert {c.action for c in numpy_result.conflicts} <= set(np.flatnonzero(numpy_result.available).tolist())
    committed = family_for("committed", "numpy")
    assert isinstance(committed, CommittedFamily) and isinstance(committed, RuleFamily)
    assert committed.engine == "numpy" and committed is not family_for("committed", "numpy")
    with pytest.raises(ValueError, match=r"^shield\.mode: got 'strict'; allowed: 'nominal', 'robust', 'committed'$"):
        family_for("strict")
