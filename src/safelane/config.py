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
import functools
import inspect
import itertools
import math
import re
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from safelane.core.errors import ConfigError


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


class ShieldConfig(_Section):
    """Which safety model masks the actions (``none`` = no shield)."""

    mode: Literal["none", "nominal", "robust"] = "none"
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
    engine: Literal["compiled", "numpy"] = Field(
        "compiled",
        description="How the shield evaluates the safety model: 'compiled' (safelane.safety.compiled, numba, "
        "microseconds a mask) or 'numpy' (safelane.safety.model.evaluate, the readable reference, about a "
        "millisecond). Identical masks.",
    )
    margin: float = Field(
        1.0,
        ge=0,
        strict=True,
        allow_inf_nan=False,
        description="[m] The bumper-to-bumper gap the rule keeps under its worst case (the safety threshold "
        "a sweep may tune; 1 m as derived in docs/safety.md).",
    )
    projected_cut_ins: bool = Field(
        False,
        strict=True,
        description="Robust mode, experimental: a vehicle already moving sideways may also cut in from the lane "
        "it moves to. Measured (docs/safety.md §6b): fewer 'second_lane_cut_in' invariant breaks but more in "
        "total; kept for the next, one-decision-ahead rule.",
    )
    body_extent: bool = Field(
        True,
        strict=True,
        description="Robust mode: a vehicle also occupies every lane its body, rotated by its heading, overlaps "
        "(a slow car turning hard sticks a corner into the lane it leaves; docs/safety.md §6b). On by default "
        "since issue 15's campaign; false gives the earlier rule.",
    )
    linear_mobil: bool = Field(
        True,
        strict=True,
        description="Robust mode: a Linear, Aggressive or Defensive driver cuts in only if its MOBIL criterion, "
        "with its own linear acceleration model and gains, allows it (as for IDM drivers), as highway-env does. "
        "On by default since issue 15's ninth session (docs/safety.md §6b, §6h, §6i); false: any such cut-in is "
        "assumed (the earlier rule).",
    )
    reversing_leaders: bool = Field(
        True,
        strict=True,
        description="A leader moving backwards (highway-env's jammed IDM cars roll back) keeps its reverse speed "
        "over the horizon; false: it counts as stopped (the rule before issue 15's reversing crashes, "
        "docs/safety.md §6d). On by default.",
    )
    level_cut_ins: bool = Field(
        True,
        strict=True,
        description="Robust mode: a car level with or behind the ego in a next lane (its centre behind the ego's now "
        "or at the end of the decision) may turn in behind it after the cut-in time and then follow it; MOBIL's "
        "safety criterion does not protect the ego there (docs/safety.md §6e). On by default since issue 15's "
        "fourth session; false gives the earlier rule.",
    )
    level_incentive: bool = Field(
        True,
        strict=True,
        description="With level_cut_ins: only a car that MOBIL's incentive lets move behind the ego (politeness 0: it "
        "gains acceleration there over its own lane, e.g. stuck in a slow queue) counts; false: any such car "
        "(measured, docs/safety.md §6e).",
    )
    level_entering: bool = Field(
        True,
        strict=True,
        description="With level_incentive: into a lane the ego is only entering (a lane change's new lane) every "
        "level car counts, unfiltered: MOBIL's incentive there is judged without the ego in the lane (docs/safety.md "
        "§6f). On by default since issue 15's fifth session; false gives the earlier rule.",
    )
    least_bad_joint: bool = Field(
        False,
        strict=True,
        description="When no action is safe, allow the one with the largest worst-case gap to any vehicle first "
        "(a follower or a car alongside counts as much as a leader); false (default): to the vehicles ahead "
        "first, the ego's own responsibility (docs/safety.md §6f).",
    )
    full_horizon: bool = Field(
        True,
        strict=True,
        description="The rule's horizon spans the same seconds at every decision rate (13 s with set-points 0-30 "
        "m/s); false: the same number of decisions, 2.6 s at 5 per second, too short for the ego to stop "
        "(docs/safety.md §6f). On by default since issue 15's fifth session; false gives the earlier rule.",
    )
    ego_speed_magnitude: bool = Field(
        True,
        strict=True,
        description="The ego's speed in the rule is its speed controller's (highway-env's vehicle.speed, what "
        "SLOWER's set-point and the P-controller use); false: its component along the road, which a lane "
        "change's heading lowers (docs/safety.md §6f). On by default since issue 15's fifth session; false "
        "gives the earlier rule.",
    )
    turning_leaders: bool = Field(
        True,
        strict=True,
        description="Robust mode: a moving leader brakes from its speed along its path, less what one lane change "
        "can cost it along the road (lane_width·tan(π/8) = 1.66 m), instead of from its speed along the road, "
        "which a lane change's heading lowers (docs/safety.md §6f). On by default since issue 15's ninth session "
        "(§6i); false gives the earlier rule.",
    )
    robust_fallback: bool = Field(
        False,
        strict=True,
        description="Experimental: when no action is safe, robust mode allows the least-bad of every available "
        "action by its robust worst-case gaps; false (default): of the nominally safe actions when there are "
        "some, so the final robust mask stays inside the nominal one (docs/safety.md §6g).",
    )
    straight_fallback: bool = Field(
        True,
        strict=True,
        description="With turning_leaders, robust mode: when no action is safe under it, allow what the rule "
        "without turning_leaders allows (its safe actions, else its least-bad one), so that the stricter leader "
        "bound narrows the promise but not the fallback (docs/safety.md §6i). On by default since issue 15's "
        "ninth session; false: the fallback of the turning bound itself.",
    )
    linear_incentive: bool = Field(
        True,
        strict=True,
        description="With level_incentive: a Linear, Aggressive or Defensive driver level with or behind the ego "
        "turns in behind it only if MOBIL's incentive, with its own linear acceleration model and gains, lets it "
        "(as IDM drivers). On by default since issue 15's ninth session (docs/safety.md §6h, §6i); false: any "
        "such car may (the earlier rule).",
    )
    linear_incentive_braking: bool = Field(
        True,
        strict=True,
        description="With linear_incentive: that incentive is also checked at every physics frame of the decision "
        "with the driver's own leaders braking at their maximum (else: now and at the end, everybody at constant "
        "speed — a Linear car closing fast on a slow one turned in within the decision; docs/safety.md §6h). On "
        "by default since issue 15's ninth session.",
    )
    reversing_cut_ins: bool = Field(
        True,
        strict=True,
        description="A vehicle in a next lane moving backwards may change into the ego's lane whatever MOBIL says: "
        "highway-env's steering assumes forward motion, so reversing, a lane change away from the ego swings the "
        "car's nose into the ego's lane (the agents' cell 615; docs/safety.md §6i). On by default since issue "
        "15's ninth session; false: MOBIL's verdict, as for any car.",
    )
    crossed_lanes: bool = Field(
        True,
        strict=True,
        description="The ego occupies every lane between its lane and its target lane until it is through, not "
        "only those two: a lane change chained onto one under way (lane 0 → 1, then right again → 2) crosses "
        "lane 1 whole, and a car there is a conflict for as long as the ego may be in it (cells 2009 and 2833; "
        "docs/safety.md §6j). On by default since issue 15's tenth session; false: the earlier rule.",
    )
    lateral_schedule: bool = Field(
        False,
        strict=True,
        description="Experimental: the time the ego spends in each lane it overlaps, simulated with highway-env's "
        "lateral controller from its lateral position and heading, instead of a lane change's leave time from a "
        "lane centre restarted at every decision (cell 2569; docs/safety.md §6j). Replaces crossed_lanes' "
        "bookkeeping when on.",
    )
    reversing_noses: bool = Field(
        True,
        strict=True,
        description="A car rolling backwards with its nose turned toward a lane is also in that lane (robust "
        "mode): backwards it moves away from it, and it drives there as soon as it moves forward again (a jammed "
        "IDM car, the trained agents' cell 126; docs/safety.md §6j). On by default since issue 15's tenth "
        "session; false: the earlier rule.",
    )
    follower_idm: bool = Field(
        True,
        strict=True,
        description="The IDM car right behind the ego in its lane (nothing between them) brakes by IDM's own "
        "response to each fallback of the ego, frame by frame, its free-road term bounded by its comfort "
        "acceleration, instead of accelerating for the reaction time whatever the ego does — a bound that does "
        "not restart at every decision (cell 2415; docs/safety.md §6k). Both modes. On by default since issue "
        "15's eleventh session; false: the earlier rule.",
    )
    follower_set_point: bool = Field(
        False,
        strict=True,
        description="Experimental, with follower_idm: the car behind's own speed set-point, read from the "
        "simulator like its other driver parameters, in its IDM free-road term (else that term at its largest), "
        "and linear-model drivers behind the ego by their own formula, which is linear in that set-point (cell "
        "2879; docs/safety.md §6k).",
    )
    finishing_changes: bool = Field(
        True,
        strict=True,
        description="Robust mode: a car moving sideways toward its own lane's centre, short of it — finishing a "
        "lane change into that lane — is not projected into the lane beyond from now (whatever MOBIL says) but is "
        "a cut-in candidate from its lane like any car there, MOBIL-filtered, from the cut-in time (the "
        "'second_lane_cut_in' breaks, cell 2087; docs/safety.md §6l). On by default since issue 15's twelfth "
        "session; false: the earlier rule.",
    )
    cut_in_when_permitted: bool = Field(
        True,
        strict=True,
        description="Robust mode: a car ahead in a next lane cuts into a lane the ego is in only "
        "from the first physics frame of the decision at which MOBIL's safety criterion allows it (the car at "
        "its fastest, the ego on the action's path), plus the cut-in time — instead of from the cut-in time "
        "whenever the criterion allows it now or at the end of the decision (docs/safety.md §6l). On by default since "
        "issue 15's thirteenth session; false: the earlier rule.",
    )
    leaving_lanes_seen: bool = Field(
        False,
        strict=True,
        description="Experimental, with lateral_schedule: a lane the ego is leaving, its centre still within "
        "IDM's band of it (half a lane + 1 m) and never overlapping it from outside that band, keeps MOBIL's "
        "cut-in filter after the ego's lane index has flipped to the lane it enters: highway-env's MOBIL finds "
        "a lane's vehicles by that band (docs/safety.md §6l).",
    )
    permit_any_speed: bool = Field(
        True,
        strict=True,
        description="Robust mode, with cut_in_when_permitted: MOBIL's IDM safety criterion judged at the car's "
        "speed within its reach that makes it loosest (IDM's desired gap falls with the car's speed and goes "
        "negative for a car much faster than the ego; highway-env squares it), and only while the car is ahead "
        "of the ego; false: at the car's fastest, which let highway-env's cars cut in earlier than the rule "
        "allowed (docs/safety.md §6m). On by default since issue 15's thirteenth session.",
    )
    passing_cut_ins: bool = Field(
        True,
        strict=True,
        description="Robust mode, with cut_in_when_permitted: a car behind the ego in a next lane "
        "that MOBIL lets cut into the ego's lane only ahead of it is a leader once in — at least the distance "
        "MOBIL needs ahead of the ego at its decision, then braking at its limit — instead of a follower that "
        "drives on through the ego (docs/safety.md §6m). On by default since issue 15's thirteenth session; "
        "false: the earlier rule.",
    )
    level_when_incentive: bool = Field(
        True,
        strict=True,
        description="Robust mode, with level_cut_ins and level_incentive: a car level with or behind the ego in a "
        "next lane turns in behind it from the first physics frame of the decision at which MOBIL's incentive "
        "allows it (with incentive_any_speed: could allow it, over every speed in reach), plus the cut-in time — "
        "instead of from the cut-in time whenever it allows it now or at the end: a car the ego is overtaking "
        "gains by moving behind it only once the ego is ahead (docs/safety.md §6m, §6n). On by default since "
        "issue 15's fourteenth session; false: the earlier rule.",
    )
    incentive_any_speed: bool = Field(
        True,
        strict=True,
        description="Robust mode, with level_when_incentive: the first frame MOBIL's incentive could allow the "
        "turn-in over every speed the car and the vehicles ahead of it can reach within their braking and "
        "acceleration limits (a bound); false: with the others at constant speed, which highway-env's drivers "
        "beat by a physics frame (docs/safety.md §6n).",
    )
    turning_in_nominal: bool = Field(
        True,
        strict=True,
        description="Nominal mode and robust's straight fallback, with turning_leaders: a moving leader's bound is "
        "the looser of braking from its speed along the road and robust's (braking along its path less a lane "
        "change's cost), so robust ⊆ nominal holds with a fast car changing lanes (docs/safety.md §6o). On by "
        "default since issue 15's fifteenth session; false: the earlier rule (nominal braking along the road only).",
    )

    forecast_fallback: bool = Field(
        True,
        strict=True,
        description="When no action is safe, rank the least-bad choice first by the smallest gap a nominal forecast "
        "predicts (every other car keeps its lane and drives by its own IDM or linear law, the ego among them), "
        "capped at the margin, every forecast collision alike; then by the worst-case gaps (docs/safety.md §6q). "
        "Never makes an action safe. On by default since issue 15's seventeenth session; false: the earlier "
        "ranking (worst-case gaps only).",
    )

    forecast_contact_time: bool = Field(
        False,
        strict=True,
        description="Experimental, off. With forecast_fallback: an action the forecast sees collide ranks by the whole "
        "decisions before its first contact, the more the higher, instead of every forecast collision alike. Never "
        "makes an action safe. Measured on the claim's campaign: more crashes (415 against 337; docs/safety.md §6r).",
    )

    forecast_lane_changes: bool = Field(
        False,
        strict=True,
        description="Experimental, off. With forecast_fallback: the forecast's cars change lane by MOBIL (their own "
        "law and max_braking_imposed, highway-env's IDM gain threshold, checked every frame), counting in both lanes "
        "for 2 s. Never makes an action safe. Measured on the claim's campaign: more crashes (docs/safety.md §6r).",
    )

    def rule_options(self) -> dict[str, bool]:
        """The rule's on/off options by name, as :class:`safelane.safety.shield.SafetyShield` and
        :func:`safelane.safety.shield.dynamics_of` take them (one list for every place that builds a shield)."""
        return {name: getattr(self, name) for name in RULE_OPTIONS}


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
    state: Literal["paper", "lanes"] = Field(
        "paper",
        description="The agent's 26-number state: 'paper' (eq. 3: the 4 nearest vehicles, ego speed and "
        "heading) or 'lanes' (left, own and right lane: two leaders and the follower each, plus the ego's "
        "lane, offset and set-point; safelane.env.factory.lane_state). Beyond the paper: for overtaking.",
    )
    env: dict[str, Any] = Field(default_factory=dict)
    reward: RewardConfig = Field(default_factory=RewardConfig)
    traffic: TrafficConfig = Field(default_factory=TrafficConfig)
    shield: ShieldConfig = Field(default_factory=ShieldConfig)

    @field_validator("preset")
    @classmethod
    def _known_preset(cls, name: str) -> str:
        if name not in ENV_PRESETS:
            raise ValueError(f"unknown preset; allowed: {', '.join(ENV_PRESETS)}")
        return name

    @model_validator(mode="after")
    def _consistent(self) -> SafelaneConfig:
        """highway-env keys (:func:`validate_env_keys`) and the checks that span sections."""
        validate_env_keys(self.env_id, self.env)
        env = {**highway_env_defaults(self.env_id), **self.env}
        if self.traffic.vehicles_behind > env["vehicles_count"]:
            raise ConfigError(
                f"traffic.vehicles_behind: must be at most env.vehicles_count ({env['vehicles_count']}), "
                f"got {self.traffic.vehicles_behind}"
            )
        if self.traffic.adversary in ("cut_in", "cut_in_mobil") and env["lanes_count"] < 2:
            raise ConfigError(
                f"traffic.adversary: '{self.traffic.adversary}' needs env.lanes_count >= 2 (a lane to cut in from), "
                f"got {env['lanes_count']}"
            )
        return self


ENV_PRESETS = ("fast", "paper")


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


@functools.cache
def _highway_env_class(env_id: str) -> type:
    import gymnasium as gym
    import highway_env  # noqa: F401  (registers the environments)

    entry = gym.spec(env_id).entry_point
    module, _, name = str(entry).partition(":")
    return getattr(__import__(module, fromlist=[name]), name)


def highway_env_defaults(env_id: str) -> dict[str, Any]:
    """highway-env's ``default_config()`` of the environment class registered as ``env_id`` (a fresh dict)."""
    return _highway_env_class(env_id).default_config()


def _type_name(value: Any) -> str:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int | float):
        return "number"
    return type(value).__name__


# --- what each highway-env key may hold ----------------------------------------------------------
#
# highway-env reads its config dict without checking it: a bad value crashes deep inside a reset (an
# IndexError, a division by zero) or, worse, runs with a meaningless setting. The rules below are the
# values highway-env and safelane actually work with; every message names the key and what is allowed.

ENV_INT_KEYS: dict[str, int] = {
    "lanes_count": 1,
    "vehicles_count": 1,
    "controlled_vehicles": 1,
    "policy_frequency": 1,
    "simulation_frequency": 1,
    "screen_width": 1,
    "screen_height": 1,
}
"""Keys that must be integers (an int, not ``4.0``: highway-env passes them to ``range``), with their minimum.
One lane is allowed (lane changes are then never available); 1 vehicle means the ego plus one other."""

ENV_POSITIVE_KEYS: dict[str, str] = {
    "ego_spacing": "ratio, > 0: the ego's spawn gap in highway-env's spacing law",
    "vehicles_density": "> 0: highway-env spaces the vehicles by 1/vehicles_density",
    "scaling": "> 0 [px/m]",
    "duration": "[s] > 0",
}
"""Keys that must be finite numbers > 0, with what they mean."""

OBSERVATION_TYPES = ("Kinematics",)
"""``env.observation.type`` values: safelane computes its own 26-number state (``state``) and discards
highway-env's observation (a sorted Kinematics one costs nothing), so other types would only cost time."""

KINEMATICS_FEATURES = (
    "presence", "x", "y", "vx", "vy", "heading", "cos_h", "sin_h", "cos_d", "sin_d", "long_off", "lat_off", "ang_off",
)  # fmt: skip
"""Feature names of highway-env's Kinematics observation (``Vehicle.to_dict``)."""

KINEMATICS_ORDERS = ("sorted", "shuffled")

ACTION_TYPES = ("DiscreteMetaAction",)
"""``env.action.type`` values: safelane's 5 meta-actions (lane left, idle, lane right, faster, slower)."""

ACTION_KEYS = ("type", "longitudinal", "lateral", "target_speeds")
"""Keys of ``env.action`` (DiscreteMetaAction's arguments)."""


def _is_number(value: Any) -> bool:
    """A finite int or float, not a bool."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _check_int(key: str, value: Any, minimum: int) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
        what = "positive integer" if minimum == 1 else f"integer >= {minimum}"
        raise ConfigError(f"{key}: expected {what}, got {value!r}")


def _check_positive(key: str, value: Any, meaning: str) -> None:
    if not _is_number(value) or value <= 0:
        raise ConfigError(f"{key}: expected a finite number {meaning}, got {value!r}")


def _check_number_pair(key: str, value: Any, increasing: bool) -> None:
    ok = isinstance(value, list | tuple) and len(value) == 2 and all(_is_number(v) for v in value)
    if ok and increasing:
        ok = value[0] < value[1]
    if not ok:
        what = "[low, high] with low < high" if increasing else "[x, y]"
        raise ConfigError(f"{key}: expected two finite numbers {what}, got {value!r}")


def max_vehicle_speed() -> float:
    """highway-env's speed cap [m/s] (``Vehicle.MAX_SPEED``): a set-point above it is never reached."""
    from highway_env.vehicle.kinematics import Vehicle

    return float(Vehicle.MAX_SPEED)


def check_target_speeds(value: Any, key: str = "env.action.target_speeds") -> None:
    """The ego's set-points [m/s]: at least 2, evenly spaced, strictly increasing, in [0, MAX_SPEED].

    highway-env's ``MDPVehicle.speed_to_index`` maps a speed to an index by linear interpolation
    between the first and last set-point (dividing by their difference): with fewer than 2 distinct
    values it fails, and with uneven spacing FASTER can map back to the current set-point and never
    accelerate (``[0, 1, 30]`` stays at 1 m/s).
    """
    top = max_vehicle_speed()
    allowed = f"a list of at least 2 evenly spaced, strictly increasing speeds in [0, {top:g}] m/s, e.g. [20, 25, 30]"
    if not isinstance(value, list | tuple) or len(value) < 2 or not all(_is_number(v) for v in value):
        raise ConfigError(f"{key}: expected {allowed}, got {value!r}")
    speeds = [float(v) for v in value]
    steps = [b - a for a, b in itertools.pairwise(speeds)]
    if speeds[0] < 0 or speeds[-1] > top or min(steps) <= 0:
        raise ConfigError(f"{key}: expected {allowed}, got {value!r}")
    step = (speeds[-1] - speeds[0]) / (len(speeds) - 1)
    if any(abs(s - step) > 1e-6 * step for s in steps):
        raise ConfigError(f"{key}: the speeds must be evenly spaced (highway-env interpolates indices), got {value!r}")


def _check_action(action: dict[str, Any]) -> None:
    """``env.action``: a DiscreteMetaAction with both lateral and longitudinal actions (safelane's 5)."""
    for key in action:
        if key not in ACTION_KEYS:
            raise ConfigError(f"env.action.{key}: unknown key; allowed: {', '.join(ACTION_KEYS)}")
    kind = action.get("type")
    if kind not in ACTION_TYPES:
        raise ConfigError(
            f"env.action.type: got {kind!r}; allowed: {', '.join(ACTION_TYPES)} (safelane's 5 meta-actions)"
        )
    for key in ("longitudinal", "lateral"):
        if key in action and action[key] is not True:
            raise ConfigError(f"env.action.{key}: must be true (safelane uses all 5 meta-actions), got {action[key]!r}")
    if action.get("target_speeds") is not None:
        check_target_speeds(action["target_speeds"])


@functools.cache
def _kinematics_keys() -> tuple[str, ...]:
    from highway_env.envs.common.observation import KinematicObservation

    params = inspect.signature(KinematicObservation.__init__).parameters
    return (
        "type",
        *(p for p, spec in params.items() if p not in ("self", "env") and spec.kind == spec.POSITIONAL_OR_KEYWORD),
    )


def _check_observation(obs: dict[str, Any]) -> None:
    """``env.observation``: highway-env's Kinematics observation and its arguments."""
    kind = obs.get("type")
    if kind not in OBSERVATION_TYPES:
        raise ConfigError(
            f"env.observation.type: got {kind!r}; allowed: {', '.join(OBSERVATION_TYPES)} "
            "(safelane replaces highway-env's observation by its own state)"
        )
    allowed_keys = _kinematics_keys()
    for key, value in obs.items():
        name = f"env.observation.{key}"
        if key not in allowed_keys:
            raise ConfigError(f"{name}: unknown key; allowed: {', '.join(allowed_keys)}")
        if key == "vehicles_count":
            _check_int(name, value, 1)
        elif key == "features":
            ok = value is None or (  # None: highway-env's default features
                isinstance(value, list)
                and value
                and all(isinstance(f, str) and f in KINEMATICS_FEATURES for f in value)
            )
            if not ok or (value is not None and len(set(value)) != len(value)):
                raise ConfigError(
                    f"{name}: expected null or a non-empty list of distinct feature names from "
                    f"{', '.join(KINEMATICS_FEATURES)}; got {value!r}"
                )
        elif key == "features_range":
            if value is None:
                continue
            if not isinstance(value, dict) or not all(f in KINEMATICS_FEATURES for f in value):
                raise ConfigError(
                    f"{name}: expected a dict feature -> [low, high] (features: x, y, vx, vy…), got {value!r}"
                )
            for feature, bounds in value.items():
                _check_number_pair(f"{name}.{feature}", bounds, increasing=True)
        elif key == "order":
            if value not in KINEMATICS_ORDERS:
                raise ConfigError(f"{name}: got {value!r}; allowed: {', '.join(KINEMATICS_ORDERS)}")
        elif key != "type" and not isinstance(value, bool):
            raise ConfigError(f"{name}: expected bool (true or false), got {value!r}")


def _check_vehicle_class(path: Any) -> None:
    """``env.other_vehicles_type``: the dotted path of a highway-env ``Vehicle`` subclass."""
    from highway_env.vehicle.kinematics import Vehicle

    allowed = "a dotted class path such as highway_env.vehicle.behavior.IDMVehicle"
    try:
        module, _, name = str(path).rpartition(".")
        cls = getattr(__import__(module, fromlist=[name]), name) if module else None
    except Exception:  # any import failure of the user's path is the same config error
        cls = None
    if not (isinstance(cls, type) and issubclass(cls, Vehicle)):
        raise ConfigError(f"env.other_vehicles_type: expected {allowed} (a highway-env Vehicle), got {path!r}")


def _check_env_values(env: dict[str, Any]) -> None:
    """The allowed values of highway-env keys (``env`` merged over the defaults, types already checked)."""
    for key, minimum in ENV_INT_KEYS.items():
        _check_int(f"env.{key}", env[key], minimum)
    for key, meaning in ENV_POSITIVE_KEYS.items():
        _check_positive(f"env.{key}", env[key], meaning)
    if env["controlled_vehicles"] != 1:
        raise ConfigError(
            f"env.controlled_vehicles: must be 1 (safelane drives one ego vehicle), got {env['controlled_vehicles']!r}"
        )
    pol_f, sim_f = env["policy_frequency"], env["simulation_frequency"]
    if sim_f % pol_f:
        raise ConfigError(
            f"env.simulation_frequency: must be a whole multiple of env.policy_frequency ({pol_f} Hz) so that each "
            f"decision lasts a whole number of physics frames, got {sim_f} ({sim_f / pol_f:g} frames per decision)"
        )
    if env["duration"] < 1 / pol_f:
        raise ConfigError(
            f"env.duration: must be at least one decision period, 1/env.policy_frequency = {1 / pol_f:g} s, "
            f"got {env['duration']!r}"
        )
    lane = env["initial_lane_id"]
    if lane is not None and (not isinstance(lane, int) or isinstance(lane, bool) or not 0 <= lane < env["lanes_count"]):
        raise ConfigError(
            f"env.initial_lane_id: expected null (random) or a lane index 0..{env['lanes_count'] - 1}, got {lane!r}"
        )
    _check_number_pair("env.reward_speed_range", env["reward_speed_range"], increasing=True)
    _check_number_pair("env.centering_position", env["centering_position"], increasing=False)
    _check_vehicle_class(env["other_vehicles_type"])
    _check_observation(env["observation"])
    _check_action(env["action"])


def validate_env_keys(env_id: str, env: dict[str, Any]) -> None:
    """Check highway-env keys against the env class's ``default_config()`` (names and value types), then
    their allowed values (ranges, consistency between keys, the nested ``observation`` / ``action``)."""
    defaults = highway_env_defaults(env_id)
    for key, value in env.items():
        if key not in defaults:
            allowed = ", ".join(sorted(defaults))
            raise ConfigError(f"env.{key}: unknown highway-env key for {env_id}; allowed: {allowed}")
        default = defaults[key]
        if default is None:
            continue
        if isinstance(default, bool):
            ok = isinstance(value, bool)
        elif isinstance(default, int | float):
            ok = _is_number(value)
            if ok and isinstance(default, int) and key.endswith(("_count", "_frequency")):
                ok = isinstance(value, int) and value > 0
        elif isinstance(default, dict):
            ok = isinstance(value, dict)
        elif isinstance(default, list | tuple):
            ok = isinstance(value, list | tuple)
        elif isinstance(default, str):
            ok = isinstance(value, str)
        else:
            ok = True
        if not ok:
            want = _type_name(default)
            if want == "number":
                want = "finite number"
            if isinstance(default, int) and key.endswith(("_count", "_frequency")):
                want = "positive integer"
            raise ConfigError(f"env.{key}: expected {want} (like {default!r}), got {value!r}")
    _check_env_values({**defaults, **env})


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


RULE_OPTIONS = (
    "projected_cut_ins", "body_extent", "linear_mobil", "reversing_leaders", "level_cut_ins", "level_incentive",
    "level_entering", "least_bad_joint", "full_horizon", "ego_speed_magnitude", "turning_leaders",
    "robust_fallback", "straight_fallback", "linear_incentive", "linear_incentive_braking", "reversing_cut_ins",
    "crossed_lanes", "lateral_schedule", "reversing_noses", "follower_idm", "follower_set_point",
    "finishing_changes", "cut_in_when_permitted", "leaving_lanes_seen", "permit_any_speed", "passing_cut_ins",
    "level_when_incentive", "incentive_any_speed", "turning_in_nominal", "forecast_fallback",
    "forecast_contact_time", "forecast_lane_changes",
)  # fmt: skip
"""The :class:`ShieldConfig` fields that switch parts of the safety rule on or off (``ShieldConfig.rule_options``)."""


RULE_CHANGES: dict[str, Any] = {
    "body_extent": False, "reversing_leaders": False, "level_cut_ins": False, "level_entering": False,
    "full_horizon": False, "ego_speed_magnitude": False,
    # issue 15's ninth session (docs/safety.md §6i)
    "linear_mobil": False, "linear_incentive": False, "linear_incentive_braking": False, "turning_leaders": False,
    "straight_fallback": False, "reversing_cut_ins": False,
    # issue 15's tenth session (docs/safety.md §6j)
    "crossed_lanes": False, "reversing_noses": False,
    # issue 15's eleventh session (docs/safety.md §6k)
    "follower_idm": False,
    # issue 15's twelfth session (docs/safety.md §6l)
    "finishing_changes": False,
    # issue 15's thirteenth session (docs/safety.md §6m)
    "cut_in_when_permitted": False, "permit_any_speed": False, "passing_cut_ins": False,
    # issue 15's fourteenth session (docs/safety.md §6n)
    "level_when_incentive": False, "incentive_any_speed": False,
    # issue 15's fifteenth session (docs/safety.md §6o)
    "turning_in_nominal": False,
    # issue 15's seventeenth session (docs/safety.md §6q)
    "forecast_fallback": False,
}  # fmt: skip
"""Shield keys added with a new default that changes the rule: a *recorded* configuration (a run's
config.yaml, a counterexample file) written before the key existed had the old behaviour, given here,
so that it replays as it ran (:func:`recorded_config`)."""


def recorded_config(data: dict[str, Any]) -> SafelaneConfig:
    """:func:`build_config` for a configuration read back from a file: shield keys it predates take the
    value they had when it was written (:data:`RULE_CHANGES`), not today's default."""
    shield = data.get("shield")
    if isinstance(shield, dict):
        missing = {k: v for k, v in RULE_CHANGES.items() if k not in shield}
        if missing:
            data = {**data, "shield": {**shield, **missing}}
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
