"""Typed, validated configuration: YAML presets + ``--set KEY=VALUE`` overrides.

A configuration has one section per concern. highway-env's own config dict passes through
untouched under ``env`` (highway-env's ``default_config()`` pattern), but every key and value type
is checked against the chosen highway-env class's defaults, so a typo fails with one line instead of
being silently ignored by highway-env.

Errors are :class:`ConfigError` (a ``ValueError``) whose message is a single line naming the key and
the allowed values; the CLI prints it without a traceback.
"""

from __future__ import annotations

import copy
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from safelane.core.errors import ConfigError


class _Section(BaseModel):
    """Base for config sections: unknown keys are errors, assignments are validated."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class RewardConfig(_Section):
    """The paper's reward, eq. 6: ``r = b·(v − v_min)/(v_max − v_min) − c·collision``."""

    b: float = Field(1.0, ge=0, description="Weight of the speed term (per decision).")
    c: float = Field(
        10.0,
        ge=0,
        description="Collision penalty. A crash also ends the episode, which already costs the "
        "future speed reward; c adds an explicit penalty on top (the paper grid-searched it).",
    )
    v_min: float = Field(
        0.0,
        description="Speed [m/s] that earns 0 speed reward (clipped below). 0 = the ego's lowest set-point: "
        "every metre per second counts, so surviving slowly still beats crashing (with highway-env's 20, "
        "speeds below 20 m/s all earn 0 and an agent that has slowed down gets no signal to speed up).",
    )
    v_max: float = Field(30.0, description="Speed [m/s] that earns the full speed reward b (clipped above).")

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
        description="How many of env.vehicles_count vehicles spawn behind the ego instead of ahead "
        "(0 = highway-env's own scene, where the ego starts behind everybody).",
    )
    adversary: Literal["none", "brake", "cut_in", "stopped"] = Field(
        "none",
        description="A scripted adversary placed near the ego at reset (safelane.sim.adversaries): a leader "
        "that brakes at full ACC_MAX at a random time, a car that cuts in ignoring MOBIL, a stopped car.",
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
        description="Replace an unsafe chosen action by the closest safe action (any agent becomes safe).",
    )


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
        description="How highway-env finds each vehicle's leader and follower: 'numpy' (safelane.sim.neighbours, "
        "identical episodes, ≈2x faster) or 'highway-env' (its own Python loop, the simulator untouched). "
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


ENV_PRESETS = ("fast", "paper")


def preset_path(name: str) -> Path:
    """Path of a preset YAML shipped in the package (``safelane/presets/NAME.yaml``)."""
    if name not in ENV_PRESETS:
        raise ConfigError(f"preset: unknown preset '{name}'; allowed: {', '.join(ENV_PRESETS)}")
    return Path(str(resources.files("safelane") / "presets" / f"{name}.yaml"))


def parse_set(assignment: str) -> tuple[str, Any]:
    """Split ``KEY.PATH=VALUE`` into the dotted key and its YAML-parsed value."""
    if "=" not in assignment:
        raise ConfigError(f"--set '{assignment}': expected KEY=VALUE, e.g. env.lanes_count=5")
    key, _, raw = assignment.partition("=")
    key = key.strip()
    if not key:
        raise ConfigError(f"--set '{assignment}': empty key")
    try:
        value = yaml.safe_load(raw) if raw.strip() else None
    except yaml.YAMLError:
        value = raw
    return key, value


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


def highway_env_defaults(env_id: str) -> dict[str, Any]:
    """highway-env's ``default_config()`` of the environment class registered as ``env_id``."""
    import gymnasium as gym
    import highway_env  # noqa: F401  (registers the environments)

    entry = gym.spec(env_id).entry_point
    module, _, name = str(entry).partition(":")
    cls = getattr(__import__(module, fromlist=[name]), name)
    return cls.default_config()


def _type_name(value: Any) -> str:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int | float):
        return "number"
    return type(value).__name__


def validate_env_keys(env_id: str, env: dict[str, Any]) -> None:
    """Check highway-env keys against the env class's ``default_config()``: names and value types."""
    defaults = highway_env_defaults(env_id)
    for key, value in env.items():
        if key not in defaults:
            allowed = ", ".join(sorted(defaults))
            raise ConfigError(f"env.{key}: unknown highway-env key for {env_id}; allowed: {allowed}")
        default = defaults[key]
        if default is None or value is None:
            continue
        if isinstance(default, bool):
            ok = isinstance(value, bool)
        elif isinstance(default, int | float):
            ok = isinstance(value, int | float) and not isinstance(value, bool)
            if ok and isinstance(default, int) and key.endswith(("_count", "_frequency")):
                ok = float(value).is_integer() and value > 0
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
            if isinstance(default, int) and key.endswith(("_count", "_frequency")):
                want = "positive integer"
            raise ConfigError(f"env.{key}: expected {want} (like {default!r}), got {value!r}")


def validation_message(err: ValidationError, model: Any = None, prefix: str = "") -> str:
    """One line for the first error of a pydantic validation: the key, what was given, what is allowed."""
    e = err.errors()[0]
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
    validate_env_keys(cfg.env_id, cfg.env)
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
