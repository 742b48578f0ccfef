"""The safety rule as data: every option of the rule declared once, and the named rules.

A :class:`Rule` is the value of every :data:`OPTIONS` entry (on or off). The numpy reference
(:mod:`safelane.safety.one_decision.reference`) reads them by name (``rule.body_extent``); the compiled kernels
(:mod:`safelane.safety.one_decision.compiled`, the fast batch) take one integer, :attr:`Rule.flags`, and test its bits
(``flags & FLAG_BODY_EXTENT``). The named rules (:data:`RULES`) are what a configuration selects
(``shield.rule``); ``shield.options`` switches single options of it for research.

    >>> RULES["worst-case-fallback"] == RULES["forecast-fallback"].with_options(forecast_fallback=False)
    True

Pure data: imports nothing from the simulator, the agents or numba.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

from safelane.core.errors import ConfigError


class RuleOption(NamedTuple):
    """One option of the rule: its ``name``, what it does (``meaning``, one line) and its ``default``."""

    name: str
    meaning: str
    default: bool


OPTIONS: tuple[RuleOption, ...] = (
    RuleOption("body_extent", "Robust: a vehicle also occupies every lane its body, rotated by its heading, "
               "overlaps.", True),
    RuleOption("linear_mobil", "Robust: a Linear, Aggressive or Defensive driver cuts in only when MOBIL's safety "
               "criterion with its own linear model allows it (else any such cut-in is assumed).", True),
    RuleOption("reversing_leaders", "A leader moving backwards keeps its reverse speed over the horizon (else it "
               "counts as stopped).", True),
    RuleOption("level_cut_ins", "Robust: a car level with or behind the ego in a next lane may turn in behind it "
               "after the cut-in time and then follow it.", True),
    RuleOption("level_incentive", "With level_cut_ins: only a car that MOBIL's incentive lets move behind the ego "
               "counts (else any such car).", True),
    RuleOption("level_entering", "With level_incentive: into a lane the ego is only entering, every level car "
               "counts, unfiltered (the incentive is judged without the ego there).", True),
    RuleOption("full_horizon", "The horizon spans the same seconds at every decision rate (else the same number "
               "of decisions).", True),
    RuleOption("ego_speed_magnitude", "The ego's speed is its speed controller's (else its component along the "
               "road, which a lane change's heading lowers).", True),
    RuleOption("turning_leaders", "Robust: a moving leader brakes from its speed along its path, less what one "
               "lane change costs it along the road (else from its speed along the road).", True),
    RuleOption("straight_fallback", "With turning_leaders, when no action is safe: the mask of the rule without "
               "turning_leaders (its safe actions, else its least-bad one).", True),
    RuleOption("linear_incentive", "With level_incentive: a linear-model driver turns in behind the ego only when "
               "MOBIL's incentive with its own model lets it (else any such car may).", True),
    RuleOption("linear_incentive_braking", "With linear_incentive: that incentive is also checked at every frame "
               "of the decision, the driver's leaders braking at their limit.", True),
    RuleOption("reversing_cut_ins", "A car in a next lane moving backwards may enter the ego's lane whatever MOBIL "
               "says (highway-env's steering assumes forward motion).", True),
    RuleOption("crossed_lanes", "The ego occupies every lane between its lane and its target lane until it is "
               "through (else only those two).", True),
    RuleOption("reversing_noses", "Robust: a car rolling backwards with its nose turned is also in the lane its "
               "nose points to.", True),
    RuleOption("follower_idm", "The IDM car right behind the ego in its lane brakes by IDM's own response to each "
               "fallback of the ego (else the follower bound: accelerate for the reaction time, then brake).", True),
    RuleOption("finishing_changes", "Robust: a car finishing a lane change into its own lane is a MOBIL-filtered "
               "cut-in candidate from there (else projected into the lane beyond).", True),
    RuleOption("cut_in_when_permitted", "Robust: a car ahead in a next lane cuts in from the first frame MOBIL's "
               "safety criterion allows it, plus the cut-in time (else from the cut-in time).", True),
    RuleOption("permit_any_speed", "With cut_in_when_permitted: MOBIL's IDM criterion at the car's loosest speed "
               "within reach, and only while it is ahead of the ego (else at its fastest).", True),
    RuleOption("passing_cut_ins", "With cut_in_when_permitted: a car behind the ego that MOBIL lets cut in only "
               "ahead of it is a leader once in (else a follower).", True),
    RuleOption("level_when_incentive", "With level_incentive: a level car turns in from the first frame MOBIL's "
               "incentive allows it, plus the cut-in time (else from the cut-in time).", True),
    RuleOption("incentive_any_speed", "With level_when_incentive: that first frame over every speed the cars can "
               "reach, a bound (else with the others at constant speed).", True),
    RuleOption("turning_in_nominal", "With turning_leaders: nominal's leader bound is the looser of braking along "
               "the road and along its path, so robust ⊆ nominal holds.", True),
    RuleOption("forecast_fallback", "When no action is safe, rank the least-bad choice first by a nominal forecast "
               "of the others (never makes an action safe; else by the worst-case gaps only).", True),
    RuleOption("level_incentive_frames", "With level_when_incentive: a level car also turns in when MOBIL's incentive "
               "allows it at some frame of the decision (else only when it does now or at the end).", True),
    RuleOption("incentive_leaders_band", "MOBIL's incentive counts as a driver's leaders the vehicles ahead within "
               "half a lane + 1 m of its lane's centre, as highway-env's IDM does (else those in its lane).", True),
    RuleOption("incentive_politeness", "With level_incentive: a polite driver's incentive also counts its followers' "
               "gain, MOBIL's p·(Δ new follower + Δ old follower); a car it alone lets turn in does so from the "
               "decision's start (else politeness 0).", True),
    RuleOption("incentive_accelerations", "With level_incentive_frames: a level car's incentive at every frame is "
               "also judged with every car at its acceleration now (its law behind its leader), not only at constant "
               "speed.", True),
)  # fmt: skip
"""Every option of the rule, in the order of :attr:`Rule.flags`' bits (bit ``i``: ``OPTIONS[i]``)."""

OPTION_NAMES: tuple[str, ...] = tuple(o.name for o in OPTIONS)
_BIT: dict[str, int] = {o.name: 1 << i for i, o in enumerate(OPTIONS)}
ALL_FLAGS = (1 << len(OPTIONS)) - 1

# The bits as module constants: the compiled kernels read them as globals (numba freezes them at compile time;
# safelane.safety.one_decision.compiled drops its cache when this file changes).
FLAG_BODY_EXTENT = _BIT["body_extent"]
FLAG_LINEAR_MOBIL = _BIT["linear_mobil"]
FLAG_REVERSING_LEADERS = _BIT["reversing_leaders"]
FLAG_LEVEL_CUT_INS = _BIT["level_cut_ins"]
FLAG_LEVEL_INCENTIVE = _BIT["level_incentive"]
FLAG_LEVEL_ENTERING = _BIT["level_entering"]
FLAG_FULL_HORIZON = _BIT["full_horizon"]
FLAG_EGO_SPEED_MAGNITUDE = _BIT["ego_speed_magnitude"]
FLAG_TURNING_LEADERS = _BIT["turning_leaders"]
FLAG_STRAIGHT_FALLBACK = _BIT["straight_fallback"]
FLAG_LINEAR_INCENTIVE = _BIT["linear_incentive"]
FLAG_LINEAR_INCENTIVE_BRAKING = _BIT["linear_incentive_braking"]
FLAG_REVERSING_CUT_INS = _BIT["reversing_cut_ins"]
FLAG_CROSSED_LANES = _BIT["crossed_lanes"]
FLAG_REVERSING_NOSES = _BIT["reversing_noses"]
FLAG_FOLLOWER_IDM = _BIT["follower_idm"]
FLAG_FINISHING_CHANGES = _BIT["finishing_changes"]
FLAG_CUT_IN_WHEN_PERMITTED = _BIT["cut_in_when_permitted"]
FLAG_PERMIT_ANY_SPEED = _BIT["permit_any_speed"]
FLAG_PASSING_CUT_INS = _BIT["passing_cut_ins"]
FLAG_LEVEL_WHEN_INCENTIVE = _BIT["level_when_incentive"]
FLAG_INCENTIVE_ANY_SPEED = _BIT["incentive_any_speed"]
FLAG_TURNING_IN_NOMINAL = _BIT["turning_in_nominal"]
FLAG_FORECAST_FALLBACK = _BIT["forecast_fallback"]
FLAG_LEVEL_INCENTIVE_FRAMES = _BIT["level_incentive_frames"]
FLAG_INCENTIVE_LEADERS_BAND = _BIT["incentive_leaders_band"]
FLAG_INCENTIVE_POLITENESS = _BIT["incentive_politeness"]
FLAG_INCENTIVE_ACCELERATIONS = _BIT["incentive_accelerations"]


def unknown_option_error(name: str, key: str | None = None) -> ConfigError:
    """The one-line error for ``name``, not an option of the rule (``key``: how the caller names it)."""
    return ConfigError(f"{key or name}: not an option of the rule; allowed: {', '.join(OPTION_NAMES)}")


@dataclass(frozen=True)
class Rule:
    """The values of every rule option, as one bitfield (:attr:`flags`, bit ``i``: :data:`OPTIONS` ``[i]``).

    Read an option by name (``rule.follower_idm``), all of them with :attr:`options`, change some with
    :meth:`with_options`. Hashable and comparable: two rules are equal when every option is."""

    flags: int

    def __post_init__(self) -> None:
        if not isinstance(self.flags, int) or isinstance(self.flags, bool) or not 0 <= self.flags <= ALL_FLAGS:
            raise ConfigError(f"Rule.flags: expected an integer in 0..{ALL_FLAGS}, got {self.flags!r}")

    def __getattr__(self, name: str) -> bool:
        bit = _BIT.get(name)
        if bit is None or name.startswith("_"):
            raise AttributeError(name)
        return bool(self.flags & bit)

    @classmethod
    def of(cls, options: Mapping[str, bool] | None = None, **changes: bool) -> Rule:
        """The rule with every option at its default, then ``options`` and ``changes`` (by name)."""
        return DEFAULTS.with_options(**{**(options or {}), **changes})

    @property
    def options(self) -> dict[str, bool]:
        """Every option's value by name, in :data:`OPTIONS` order."""
        return {name: bool(self.flags & bit) for name, bit in _BIT.items()}

    def with_options(self, **changes: Any) -> Rule:
        """This rule with the named options set (``rule.with_options(body_extent=False)``); an unknown name or a
        value that is not a bool is a one-line :class:`ConfigError`."""
        flags = self.flags
        for name, value in changes.items():
            bit = _BIT.get(name)
            if bit is None:
                raise unknown_option_error(name)
            if not isinstance(value, bool):
                raise ConfigError(f"{name}: expected true or false, got {value!r}")
            flags = flags | bit if value else flags & ~bit
        return Rule(flags)

    def differences(self, other: Rule) -> dict[str, bool]:
        """The options whose value differs from ``other``'s, with this rule's values."""
        return {name: value for name, value in self.options.items() if value != getattr(other, name)}

    def __repr__(self) -> str:
        name = next((n for n, r in RULES.items() if r == self), None) if "RULES" in globals() else None
        off = [n for n, v in self.options.items() if not v]
        return f"Rule({name!r})" if name else f"Rule(off={off})"


DEFAULTS = Rule(sum(_BIT[o.name] for o in OPTIONS if o.default))
"""Every option at its declared default."""

BASIC_OFF: tuple[str, ...] = tuple(o.name for o in OPTIONS if o.name != "level_incentive")
"""The options the basic rule has off: every refinement of the rule that changed its verdicts.
``level_incentive`` only filters ``level_cut_ins``, which the basic rule has off, so it keeps its default."""

RULES: dict[str, Rule] = {
    "forecast-fallback": DEFAULTS,
    "worst-case-fallback": DEFAULTS.with_options(forecast_fallback=False),
    "basic": DEFAULTS.with_options(**dict.fromkeys(BASIC_OFF, False)),
}
"""The named rules. ``forecast-fallback`` (the default): every option on, the least-bad choice ranked by the
nominal forecast first; ``worst-case-fallback``: the same, the least-bad choice ranked by the worst-case gaps
only; ``basic``: the robust rule without any refinement (every option that changes a verdict off)."""

DEFAULT_RULE_NAME = "forecast-fallback"


def rule_named(name: str, key: str = "shield.rule") -> Rule:
    """The rule called ``name`` in :data:`RULES`; an unknown name is a one-line :class:`ConfigError`."""
    rule = RULES.get(name) if isinstance(name, str) else None
    if rule is None:
        raise ConfigError(f"{key}: unknown rule {name!r}; allowed: {', '.join(RULES)}")
    return rule


def as_rule(rule: Rule | str) -> Rule:
    """``rule`` itself, or the rule it names."""
    return rule if isinstance(rule, Rule) else rule_named(rule, "rule")
