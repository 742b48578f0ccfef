"""highway-env's own keys (``SafelaneConfig.env``): every key and value type checked against the environment
class's ``default_config()``, then every value against what highway-env and safelane can run.

highway-env reads its config dict without checking it: a bad value crashes deep inside a reset (an IndexError, a
division by zero) or, worse, runs with a meaningless setting. The rules below are the values highway-env and
safelane actually work with; every message names the key and what is allowed.
"""

from __future__ import annotations

import functools
import inspect
import itertools
import math
from typing import Any

from safelane.core.errors import ConfigError


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

ACTION_TYPES = ("DiscreteMetaAction", "ContinuousAction")
"""``env.action.type`` values: safelane's 5 meta-actions (lane left, idle, lane right, faster, slower), or
acceleration and steering (``actions: continuous``)."""

ACTION_KEYS = ("type", "longitudinal", "lateral", "target_speeds")
"""Keys of a DiscreteMetaAction ``env.action`` (its arguments)."""


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
    """``env.action``: a DiscreteMetaAction with both lateral and longitudinal actions (safelane's 5), or a
    kinematic ContinuousAction (:func:`_check_continuous_action`)."""
    kind = action.get("type")
    if kind not in ACTION_TYPES:
        raise ConfigError(f"env.action.type: got {kind!r}; allowed: {', '.join(ACTION_TYPES)}")
    if kind == "ContinuousAction":
        _check_continuous_action(action)
        return
    for key in action:
        if key not in ACTION_KEYS:
            raise ConfigError(f"env.action.{key}: unknown key; allowed: {', '.join(ACTION_KEYS)}")
    for key in ("longitudinal", "lateral"):
        if key in action and action[key] is not True:
            raise ConfigError(f"env.action.{key}: must be true (safelane uses all 5 meta-actions), got {action[key]!r}")
    if action.get("target_speeds") is not None:
        check_target_speeds(action["target_speeds"])


@functools.cache
def continuous_action_keys() -> tuple[str, ...]:
    """Keys of a ContinuousAction ``env.action``: ``type`` and highway-env's ``ContinuousAction`` arguments."""
    from highway_env.envs.common.action import ContinuousAction

    params = inspect.signature(ContinuousAction.__init__).parameters
    return ("type", *(p for p, spec in params.items() if p not in ("self", "env") and spec.kind != spec.VAR_KEYWORD))


def _check_continuous_action(action: dict[str, Any]) -> None:
    """``env.action`` of type ContinuousAction: highway-env's arguments, acceleration and steering both on, the
    kinematic ego (``dynamical`` false), ranges as increasing pairs."""
    allowed = continuous_action_keys()
    for key, value in action.items():
        name = f"env.action.{key}"
        if key not in allowed:
            raise ConfigError(f"{name}: unknown key for ContinuousAction; allowed: {', '.join(allowed)}")
        if key in ("longitudinal", "lateral") and value is not True:
            raise ConfigError(f"{name}: must be true (safelane's continuous actions are acceleration and steering)")
        if key == "dynamical" and value is not False:
            raise ConfigError(f"{name}: must be false (the kinematic ego, highway-env's Vehicle), got {value!r}")
        if key == "clip" and not isinstance(value, bool):
            raise ConfigError(f"{name}: expected bool (true or false), got {value!r}")
        if key in ("acceleration_range", "steering_range", "speed_range") and value is not None:
            _check_number_pair(name, value, increasing=True)


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
