"""Typed, validated configuration: YAML presets + ``--set KEY=VALUE`` overrides.

A configuration has one section per concern. highway-env's own config dict passes through
untouched under ``env`` (highway-env's ``default_config()`` pattern), but every key and value type
is checked against the chosen highway-env class's defaults, so a typo fails with one line instead of
being silently ignored by highway-env; then every value is checked against what highway-env and
safelane can run (:func:`validate_env_keys`: ranges, whole physics frames per decision, the nested
``observation`` and ``action`` dicts), so a bad value fails here rather than deep inside a reset.
The checks run whenever a :class:`SafelaneConfig` is built, so ``load_config``, ``build_config`` and
``make_env`` all reject the same values. Numbers must be finite, and not booleans or strings.

Errors are :class:`ConfigError` (a ``ValueError``) whose message is a single line naming the key and
the allowed values; the CLI prints it without a traceback.
"""

from __future__ import annotations

import copy
import re
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from safelane.config.highway_keys import highway_env_defaults, validate_env_keys
from safelane.core.drivers import (
    ASSUMED_DRIVER,
    DRIVER_TYPES,
    NAMED_MIXES,
    NO_MIX,
    DriverMix,
    check_driver_type,
    idm_parameters,
    parse_driver_mix,
)
from safelane.core.errors import ConfigError
from safelane.safety.rule import (
    DEFAULT_RULE_NAME,
    OPTION_NAMES,
    RULES,
    Rule,
    rule_named,
    unknown_option_error,
)


class _Section(BaseModel):
    """Base for config sections: unknown keys are errors, assignments are validated, numbers are finite."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


class RewardConfig(_Section):
    """The paper's reward, eq. 6: ``r = b·(v − v_min)/(v_max − v_min) − c·collision``."""

    b: float = Field(1.0, ge=0, strict=True, description="Weight of the speed term (per decision).")
    c: float = Field(
        10.0,
        ge=0,
        strict=True,
        description="Collision penalty. A crash also ends the episode, which already costs the "
        "future speed reward; c adds an explicit penalty on top (the paper grid-searched it).",
    )
    v_min: float = Field(
        0.0,
        strict=True,
        description="Speed [m/s] that earns 0 speed reward (clipped below). 0 = the ego's lowest set-point: "
        "every metre per second counts, so surviving slowly still beats crashing (with highway-env's 20, "
        "speeds below 20 m/s all earn 0 and an agent that has slowed down gets no signal to speed up).",
    )
    v_max: float = Field(
        30.0, strict=True, description="Speed [m/s] that earns the full speed reward b (clipped above)."
    )

    lane_centring: float = Field(
        0.5,
        ge=0,
        le=1,
        strict=True,
        description="Continuous actions only: the share of the speed reward lost at a lane's edge; the speed term "
        "is multiplied by 1 − lane_centring·(2·offset/lane width)², so the ego is paid most at a lane's centre.",
    )

    @field_validator("v_max")
    @classmethod
    def _ordered(cls, v_max: float, info: Any) -> float:
        v_min = info.data.get("v_min")
        if v_min is not None and v_max <= v_min:
            raise ValueError(f"must be greater than reward.v_min ({v_min})")
        return v_max


class TrafficConfig(_Section):
    """safelane-level traffic options layered on top of highway-env's scene generation."""

    vehicles_behind: int = Field(
        0,
        ge=0,
        strict=True,
        description="How many of env.vehicles_count vehicles spawn behind the ego instead of ahead "
        "(0 = highway-env's own scene, where the ego starts behind everybody).",
    )
    adversary: Literal["none", "brake", "cut_in", "stopped", "cut_in_mobil"] = Field(
        "none",
        description="A scripted adversary placed near the ego at reset (safelane.sim.adversaries): a leader "
        "that brakes at full ACC_MAX at a random time, a car that cuts in ignoring MOBIL, a stopped car, a car "
        "that cuts in as soon as MOBIL's safety criterion allows.",
    )
    driver_mix: str | list[dict[str, Any]] = Field(
        NO_MIX,
        description="Each other car's driver type drawn independently at spawn (safelane.sim.drivers): a named "
        f"mixture ({', '.join(NAMED_MIXES)}) or a list of {{type, weight}} with types among "
        f"{', '.join(DRIVER_TYPES)} (probability weight / sum of weights). 'none': every car is "
        "env.other_vehicles_type.",
    )
    shield_sees_types: bool = Field(
        False,
        strict=True,
        description="With driver_mix: the snapshot (what the shield reads) gives each car its own type's driver "
        "parameters; false: every drawn car reports assumed_driver's (the types are hidden from the shield).",
    )
    assumed_driver: str = Field(
        ASSUMED_DRIVER,
        description="With driver_mix and shield_sees_types false: the driver type the shield is told every drawn car "
        "is (its parameters in the snapshot; each car keeps its own IDM exponent).",
    )

    @field_validator("driver_mix", mode="before")
    @classmethod
    def _known_mix(cls, value: Any) -> Any:
        parse_driver_mix(value)
        return value

    @field_validator("assumed_driver")
    @classmethod
    def _known_assumed(cls, name: str) -> str:
        return check_driver_type(name, "traffic.assumed_driver")

    @model_validator(mode="after")
    def _mix_only_fields(self) -> TrafficConfig:
        """``shield_sees_types`` and ``assumed_driver`` only mean something with a ``driver_mix``."""
        if self.driver_mix == NO_MIX:
            if self.shield_sees_types:
                raise ConfigError("traffic.shield_sees_types: only with traffic.driver_mix; allowed otherwise: false")
            if self.assumed_driver != ASSUMED_DRIVER:
                raise ConfigError(
                    f"traffic.assumed_driver: only with traffic.driver_mix; allowed otherwise: {ASSUMED_DRIVER}"
                )
        return self

    def driver_mixture(self) -> DriverMix | None:
        """The :class:`~safelane.core.drivers.DriverMix` this section draws the other cars' types from (None: no
        mixture), with the type the shield is told of each drawn car (None: its own)."""
        return parse_driver_mix(self.driver_mix, assumed=None if self.shield_sees_types else self.assumed_driver)


MODE_ONLY_FIELDS: dict[str, tuple[str, ...]] = {
    "redraw_uncertified": ("committed",),
    "redraw_tries": ("committed",),
    "formula": ("nominal",),
    "belief_epsilon": ("belief",),
    "belief_sigma": ("belief",),
}
"""The shield's fields that only some modes read (``shield.reading`` too: the committed mode's,
:func:`drop_removed_reading`); every other field is read by each mode with a shield."""


CONTINUOUS_SHIELD_FIELDS = ("intervention", "adaptation_penalty")
"""The shield's fields that only the shield for continuous actions reads."""


class ShieldConfig(_Section):
    """Which safety model masks the actions (``none`` = no shield)."""

    mode: Literal["none", "nominal", "robust", "committed", "omniscient", "belief"] = "none"
    redraw_uncertified: bool = Field(
        False,
        strict=True,
        description="The committed mode only: redraw an episode's spawn (the environment's next draw) while its "
        "first state has no verified plan, at most shield.redraw_tries times; the redraws are reported. Off: "
        "highway-env's traffic as it is (uncertified starts counted apart).",
    )
    redraw_tries: int = Field(
        20,
        ge=1,
        strict=True,
        description="With shield.redraw_uncertified: the most spawns drawn again for one episode (after that the "
        "episode starts uncertified).",
    )
    formula: Literal["kinematic", "paper"] = Field(
        "kinematic",
        description="Safe-distance formula of the nominal mode: 'kinematic' (derived for highway-env's "
        "real dynamics, docs/safety.md) or 'paper' (eq. 12 as printed, unsound where documented).",
    )
    override: bool = Field(
        False,
        strict=True,
        description="Replace an unsafe chosen action by the closest safe action (any agent becomes safe).",
    )
    belief_epsilon: float = Field(
        0.01,
        ge=0,
        lt=1,
        strict=True,
        allow_inf_nan=False,
        description="The belief mode only: each car may be every driver type whose posterior exceeds this; the "
        "robust rule's worst case over those (a crash with a car whose true type was ruled out is counted).",
    )
    belief_sigma: float = Field(
        0.2,
        gt=0,
        strict=True,
        allow_inf_nan=False,
        description="The belief mode only: [m/s²] the standard deviation of a car's observed mean acceleration "
        "over a decision about its type's IDM prediction (safelane.safety.belief).",
    )
    engine: Literal["compiled", "numpy"] = Field(
        "compiled",
        description="How the shield evaluates the safety model: 'compiled' (numba kernels, microseconds a mask: "
        "safelane.safety.one_decision.compiled) or 'numpy' (the readable reference, about a millisecond: "
        "safelane.safety.one_decision.reference); in the committed mode its numba kernels or the numpy reference "
        "(safelane.safety.committed). Identical masks.",
    )
    intervention: Literal["projection", "replacement"] = Field(
        "projection",
        description="Continuous actions only: what the shield executes when the agent's action has no verified "
        "plan: 'projection' (the verified action nearest it) or 'replacement' (the kept plan's next step, else the "
        "fail-safe's braking action); safelane.safety.continuous.",
    )
    adaptation_penalty: float = Field(
        0.0,
        ge=0,
        strict=True,
        allow_inf_nan=False,
        description="Continuous actions only: the reward loses this weight times the distance (normalised "
        "actions) from the agent's action to the executed one.",
    )
    margin: float = Field(
        1.0,
        ge=0,
        strict=True,
        allow_inf_nan=False,
        description="[m] The bumper-to-bumper gap the rule keeps under its worst case (the safety threshold "
        "a sweep may tune; 1 m as derived in docs/safety.md).",
    )
    rule: str = Field(
        DEFAULT_RULE_NAME,
        description="The named rule (safelane.safety.rule.RULES): 'forecast-fallback' (every option on, the "
        "least-bad choice ranked by the nominal forecast first), 'worst-case-fallback' (the same, ranked by the "
        "worst-case gaps only) or 'basic' (the robust rule without its refinements).",
    )
    options: dict[str, bool] = Field(
        default_factory=dict,
        description="Single options of the rule switched on or off (option -> true/false), over the named rule; "
        "every option and what it does: safelane.safety.rule.OPTIONS.",
    )

    @model_validator(mode="before")
    @classmethod
    def _flat_options(cls, data: Any) -> Any:
        """A rule option given as a key of its own (``shield.body_extent: false``) is read as
        ``shield.options.body_extent``; a removed option is accepted at its old default, else an error (so is
        ``reading``, :func:`drop_removed_reading`)."""
        if isinstance(data, dict):
            return fold_flat_options(drop_removed_reading(data, data.get("mode", "none")))
        return data

    @field_validator("rule")
    @classmethod
    def _known_rule(cls, name: str) -> str:
        rule_named(name)
        return name

    @field_validator("options", mode="before")
    @classmethod
    def _known_options(cls, options: Any) -> Any:
        if not isinstance(options, dict):
            raise ConfigError(f"shield.options: expected a mapping option -> true/false, got {options!r}")
        for name, value in options.items():
            if name not in OPTION_NAMES:
                raise unknown_option_error(name, f"shield.options.{name}")
            if not isinstance(value, bool):
                raise ConfigError(f"shield.options.{name}: expected true or false, got {value!r}")
        return options

    @model_validator(mode="after")
    def _mode_only_fields(self) -> ShieldConfig:
        """A field that only some modes read (:data:`MODE_ONLY_FIELDS`), set away from its default under another
        mode, is a one-line error: it would be silently ignored."""
        for name, modes in MODE_ONLY_FIELDS.items():
            default = type(self).model_fields[name].default
            if getattr(self, name) != default and self.mode not in modes:
                raise ConfigError(
                    f"shield.{name}: only for shield.mode {' or '.join(modes)} (got mode {self.mode!r}); "
                    f"allowed otherwise: {str(default).lower() if isinstance(default, bool) else repr(default)}"
                )
        return self

    def resolved_rule(self) -> Rule:
        """The rule this section selects: the named rule with ``options`` applied."""
        return rule_named(self.rule).with_options(**self.options)


class SafelaneConfig(_Section):
    """A whole environment configuration: which highway-env, its config, and safelane's layers."""

    preset: str = "fast"
    env_id: Literal["highway-v0", "highway-fast-v0"] = "highway-fast-v0"
    simulator: Literal["highway-env", "fast"] = Field(
        "highway-env",
        description="Which simulator runs env_id: 'highway-env' (the reference) or 'fast' (safelane.sim.fast: "
        "highway-env's highway on compiled arrays, checked against it by `safelane sim check`).",
    )
    neighbour_search: Literal["numpy", "highway-env"] = Field(
        "numpy",
        description="How highway-env finds each vehicle's leader and follower and pre-screens collision pairs: "
        "'numpy' (safelane.sim.neighbours, identical episodes, ≈2x faster) or 'highway-env' (its own Python "
        "loops, the simulator untouched). "
        "Not the choice of simulator.",
    )
    actions: Literal["discrete", "continuous"] = Field(
        "discrete",
        description="The ego's actions: 'discrete' (the paper's five meta-actions, highway-env's "
        "DiscreteMetaAction) or 'continuous' (acceleration and steering in [-1, 1], highway-env's "
        "ContinuousAction with its own ranges: env.action becomes one, keeping its ContinuousAction keys; "
        "env.offroad_terminal defaults to true; the state gains the lane offset and lane index, the reward "
        "its lane-centring term, safelane.env.reward.ContinuousReward).",
    )
    state: Literal["paper", "lanes", "paper-types", "paper-stack", "paper-belief"] = Field(
        "paper",
        description="The agent's state: 'paper' (eq. 3, 26 numbers: the 4 nearest vehicles, ego speed and "
        "heading) or 'lanes' (26 numbers: left, own and right lane: two leaders and the follower each, plus the "
        "ego's lane, offset and set-point; safelane.env.factory.lane_state). Beyond the paper: for overtaking. "
        "'paper-types' (with traffic.driver_mix): eq. 3, then each of the 4 vehicles' driver type one-hot "
        "(26 + 4·types numbers; safelane.env.observations.paper_types_state). 'paper-stack': eq. 3 of the last "
        "4 decisions, oldest first, zeros before the episode's first (104 numbers; "
        "safelane.env.observations.StackedState). 'paper-belief' (with a traffic.driver_mix of IDM types): eq. 3, "
        "then each of the 4 vehicles' posterior over the types from safelane.safety.belief.BeliefFilter (26 + "
        "4·types numbers; safelane.env.observations.paper_belief_state).",
    )
    env: dict[str, Any] = Field(default_factory=dict)
    reward: RewardConfig = Field(default_factory=RewardConfig)
    traffic: TrafficConfig = Field(default_factory=TrafficConfig)
    shield: ShieldConfig = Field(default_factory=ShieldConfig)

    @model_validator(mode="before")
    @classmethod
    def _continuous_action_type(cls, data: Any) -> Any:
        """``actions: continuous`` turns a meta-action ``env.action`` (a preset's) into highway-env's
        ContinuousAction, dropping the meta-actions' set-points and keeping every other key; the episode ends
        off the road unless ``env.offroad_terminal`` says otherwise."""
        if not isinstance(data, dict) or data.get("actions") != "continuous":
            return data
        env = dict(data.get("env") or {})
        action = env.get("action")
        action = dict(action) if isinstance(action, dict) else {}
        if action.get("type", "DiscreteMetaAction") == "DiscreteMetaAction":
            action = {**{k: v for k, v in action.items() if k not in ("type", "target_speeds")},
                      "type": "ContinuousAction"}  # fmt: skip
        env["action"] = action
        env.setdefault("offroad_terminal", True)
        return {**data, "env": env}

    @field_validator("preset")
    @classmethod
    def _known_preset(cls, name: str) -> str:
        if name not in ENV_PRESETS:
            raise ValueError(f"unknown preset; allowed: {', '.join(ENV_PRESETS)}")
        return name

    @model_validator(mode="after")
    def _consistent(self) -> SafelaneConfig:
        """highway-env keys (:func:`validate_env_keys`) and the checks that span sections."""
        env = {**highway_env_defaults(self.env_id), **self.env}
        self._check_actions(env["action"].get("type") if isinstance(env["action"], dict) else None)
        validate_env_keys(self.env_id, self.env)
        if self.traffic.vehicles_behind > env["vehicles_count"]:
            raise ConfigError(
                f"traffic.vehicles_behind: must be at most env.vehicles_count ({env['vehicles_count']}), "
                f"got {self.traffic.vehicles_behind}"
            )
        if self.state in ("paper-types", "paper-belief"):
            if self.traffic.driver_mix == NO_MIX:
                raise ConfigError(
                    f"state: {self.state!r} shows each car's driver type and needs traffic.driver_mix; "
                    "allowed without one: paper, lanes, paper-stack"
                )
            if self.state == "paper-belief":
                idm_parameters(parse_driver_mix(self.traffic.driver_mix))
        if self.shield.mode in ("omniscient", "belief"):
            if self.traffic.driver_mix == NO_MIX:
                raise ConfigError(
                    f"shield.mode: {self.shield.mode!r} reads the driver types of traffic.driver_mix, which is none; "
                    "allowed without a mixture: none, nominal, robust, committed"
                )
            idm_parameters(parse_driver_mix(self.traffic.driver_mix))
        if self.traffic.driver_mix != NO_MIX and "other_vehicles_type" in self.env:
            raise ConfigError("env.other_vehicles_type: traffic.driver_mix draws every car's type; remove one of them")
        if self.traffic.adversary in ("cut_in", "cut_in_mobil") and env["lanes_count"] < 2:
            raise ConfigError(
                f"traffic.adversary: '{self.traffic.adversary}' needs env.lanes_count >= 2 (a lane to cut in from), "
                f"got {env['lanes_count']}"
            )
        return self

    def _check_actions(self, action_type: str | None) -> None:
        """``actions`` agrees with ``env.action.type``; continuous actions have no shield rule and no set-point
        for the ``lanes`` state (one-line errors naming the field)."""
        if self.actions == "discrete" and action_type == "ContinuousAction":
            raise ConfigError("env.action.type: ContinuousAction needs actions: continuous (--actions continuous)")
        if self.actions != "continuous":
            default = RewardConfig.model_fields["lane_centring"].default
            if self.reward.lane_centring != default:
                raise ConfigError(f"reward.lane_centring: only for actions: continuous; allowed otherwise: {default}")
            for name in CONTINUOUS_SHIELD_FIELDS:
                default = ShieldConfig.model_fields[name].default
                if getattr(self.shield, name) != default:
                    raise ConfigError(f"shield.{name}: only for actions: continuous; allowed otherwise: {default!r}")
            return
        if self.shield.mode not in ("none", "committed"):
            raise ConfigError(
                f"shield.mode: {self.shield.mode!r} decides among meta-actions; allowed with actions continuous: "
                "'none', 'committed'"
            )
        if self.shield.override:
            raise ConfigError("shield.override: the shield for continuous actions always intervenes (see "
                              "shield.intervention); allowed with actions continuous: false")

        if self.state != "paper":
            raise ConfigError(
                f"state: {self.state!r} reads the ego's set-point, which continuous actions lack; allowed with "
                "actions continuous: paper"
            )


ENV_PRESETS = ("fast", "paper", "hidden-types")


def preset_path(name: str) -> Path:
    """Path of a preset YAML shipped in the package (``safelane/presets/NAME.yaml``)."""
    if name not in ENV_PRESETS:
        raise ConfigError(f"preset: unknown preset '{name}'; allowed: {', '.join(ENV_PRESETS)}")
    return Path(str(resources.files("safelane") / "presets" / f"{name}.yaml"))


def parse_set(assignment: str) -> tuple[str, Any]:
    """Split ``KEY.PATH=VALUE`` into the dotted key and its YAML-parsed value (``1e-3`` is a number)."""
    if "=" not in assignment:
        raise ConfigError(f"--set '{assignment}': expected KEY=VALUE, e.g. env.lanes_count=5")
    key, _, raw = assignment.partition("=")
    key = key.strip()
    if not key:
        raise ConfigError(f"--set '{assignment}': empty key")
    try:
        value = yaml.load(raw, Loader=_SetLoader) if raw.strip() else None
    except yaml.YAMLError:
        value = raw
    return key, value


class _SetLoader(yaml.SafeLoader):
    """PyYAML's safe loader, reading an unquoted ``1e-3`` (no dot) as a number at any depth, as YAML 1.2
    does: YAML 1.1 makes it a string, which ``--set env.action.target_speeds=[0, 1e1]`` never means."""


_SetLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float", re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+$"), list("-+0123456789.")
)


def _assign(tree: dict[str, Any], dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    node = tree
    for part in parts[:-1]:
        child = node.get(part)
        if child is None:
            child = node[part] = {}
        if not isinstance(child, dict):
            raise ConfigError(f"{dotted}: '{part}' is a value, not a section")
        node = child
    node[parts[-1]] = value


def validation_message(err: ValidationError, model: Any = None, prefix: str = "") -> str:
    """One line for the first error of a pydantic validation: the key, what was given, what is allowed."""
    e = err.errors()[0]
    cause = e.get("ctx", {}).get("error")
    if isinstance(cause, ConfigError):  # a model validator's message already names its key
        return str(cause)
    loc = prefix + ".".join(str(p) for p in e["loc"])
    msg = e["msg"]
    if e["type"] == "extra_forbidden" and model is not None:
        section = e["loc"][:-1]
        for part in section:
            model = model.model_fields[str(part)].annotation
        allowed = ", ".join(model.model_fields)
        return f"{loc}: unknown key; allowed: {allowed}"
    if e["type"] == "literal_error":
        return f"{loc}: got {e.get('input')!r}; {msg.lower()}"
    if e["type"] == "value_error":
        msg = msg.removeprefix("Value error, ")  # pydantic's prefix for a validator's ValueError
    return f"{loc}: {msg} (got {e.get('input')!r})"


RENAMED_KEYS: dict[str, tuple[str, dict[Any, Any]]] = {
    "backend": ("neighbour_search", {"vectorized": "numpy", "highway-env": "highway-env"}),
}
"""Keys of older run configs: old name → (new name, old value → new value). Read, never written."""


REMOVED_OPTIONS: dict[str, bool] = {
    "projected_cut_ins": False, "least_bad_joint": False, "robust_fallback": False, "lateral_schedule": False,
    "leaving_lanes_seen": False, "follower_set_point": False, "forecast_contact_time": False,
    "forecast_lane_changes": False,
}  # fmt: skip
"""Options measured and not adopted, removed from the rule, with the value they always had: a file that sets one
to it still loads; any other value is an error (the changelog names the commit that still runs them)."""

KEPT_READING = "responsibility"
"""The committed mode's one reading of whose gap a car is: ``shield.reading`` may still name it (older specs and
published campaign files pass ``shield.reading=responsibility``); the other reading, ``sound``, is removed."""


def drop_removed_reading(shield: dict[str, Any], mode: str) -> dict[str, Any]:
    """``shield`` without ``reading`` (the committed mode has one reading, :data:`KEPT_READING`); a ``reading``
    under another ``mode``, or other than it, is a one-line :class:`ConfigError`."""
    if "reading" not in shield:
        return shield
    if mode != "committed":
        raise ConfigError(f"shield.reading: only for shield.mode committed (got mode {mode!r}); remove it")
    if shield["reading"] != KEPT_READING:
        raise ConfigError(
            f"shield.reading: 'sound' was removed (measured: it verified a plan at about 5 % of decisions in "
            f"traffic); the committed mode reads cars by responsibility, got {shield['reading']!r}"
        )
    return {k: v for k, v in shield.items() if k != "reading"}


RECORDED_DEFAULTS: dict[str, bool] = RULES["basic"].options
"""The value a rule option has in a *recorded* configuration (a run's config.yaml, a counterexample file) that
names neither ``shield.rule`` nor the option: such a file lists the options as keys of their own and was written
before the keys it lacks existed, with the rule's behaviour then — each such option off: the ``basic`` rule's
values (:func:`recorded_config`)."""


def fold_flat_options(shield: dict[str, Any]) -> dict[str, Any]:
    """``shield`` with every rule option given as a key of its own moved into ``options`` (the key of its own wins
    where both name it: a dumped configuration has ``options`` only, so such a key is an override) and every
    removed option dropped: at its old value (:data:`REMOVED_OPTIONS`), else a
    one-line :class:`ConfigError`."""
    flat = {k: v for k, v in shield.items() if k in OPTION_NAMES or k in REMOVED_OPTIONS}
    if not flat:
        return shield
    out = {k: v for k, v in shield.items() if k not in flat}
    options = {}
    for name, value in flat.items():
        if name in REMOVED_OPTIONS:
            if value is not REMOVED_OPTIONS[name]:
                raise ConfigError(
                    f"shield.{name}: this option was removed from the rule (measured, not adopted; "
                    f"docs/changelog.md); only {str(REMOVED_OPTIONS[name]).lower()} is accepted, got {value!r}"
                )
            continue
        options[name] = value
    given = out.get("options")
    out["options"] = {**given, **options} if isinstance(given, dict) else (given if given is not None else options)
    return out


def recorded_config(data: dict[str, Any]) -> SafelaneConfig:
    """:func:`build_config` for a configuration read back from a file. A file without ``shield.rule`` names its
    rule by options as keys of their own: each option it lacks takes its value then
    (:data:`RECORDED_DEFAULTS`), and the options become the named rule closest to them (the fewest options
    differ; the first in :data:`RULES` of equals) with the options that differ from it."""
    shield = data.get("shield")
    if isinstance(shield, dict) and "rule" not in shield:
        folded = fold_flat_options(shield)
        given = folded.get("options") if isinstance(folded.get("options"), dict) else {}
        unknown = sorted(set(given) - set(OPTION_NAMES))
        if unknown:
            raise unknown_option_error(unknown[0], f"shield.options.{unknown[0]}")
        values = {**RECORDED_DEFAULTS, **given}
        rule = Rule.of(values) if all(isinstance(v, bool) for v in values.values()) else None
        if rule is not None:
            name = min(RULES, key=lambda n: len(rule.differences(RULES[n])))  # the closest named rule
            folded = {**folded, "rule": name, "options": rule.differences(RULES[name])}
        else:  # a non-bool value: build_config names it
            folded = {**folded, "options": values}
        data = {**data, "shield": folded}
    return build_config(data)


def build_config(data: dict[str, Any]) -> SafelaneConfig:
    """Validate a plain dict into a :class:`SafelaneConfig` (raises :class:`ConfigError`)."""
    for old, (new, values) in RENAMED_KEYS.items():
        if old in data and new not in data:
            data = {**data, new: values.get(data[old], data[old])}
            del data[old]
    try:
        cfg = SafelaneConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(validation_message(err, SafelaneConfig)) from None
    return cfg


def load_config(
    preset: str = "fast",
    sets: list[str] | None = None,
    overrides: dict[str, Any] | None = None,
) -> SafelaneConfig:
    """Load a preset, apply ``--set`` strings then Python overrides (dotted keys or section dicts)."""
    with open(preset_path(preset)) as f:
        data = yaml.safe_load(f) or {}
    data["preset"] = preset
    for assignment in sets or []:
        _assign(data, *parse_set(assignment))
    apply_overrides(data, overrides or {})
    return build_config(data)


def apply_overrides(data: dict[str, Any], overrides: dict[str, Any]) -> None:
    """Apply Python overrides to a config dict in place: dotted keys (``"env.lanes_count"``) or section
    dicts (``env={"lanes_count": 5}``, merged into the section rather than replacing it)."""
    for key, value in overrides.items():
        if isinstance(value, dict) and "." not in key and isinstance(data.get(key), dict):
            for sub, v in value.items():
                _assign(data, f"{key}.{sub}", copy.deepcopy(v))
        else:
            _assign(data, key, copy.deepcopy(value))


def config_to_dict(cfg: SafelaneConfig) -> dict[str, Any]:
    """A plain, YAML-serialisable dict of a config (fully resolved)."""
    return cfg.model_dump(mode="json")
