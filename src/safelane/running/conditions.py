"""Traffic conditions as data: an environment preset and overrides, for the stress suite and experiments.

The shipped suite is ``safelane/presets/stress.yaml``; a user file is a YAML list of
``{name, preset, sets, adversarial}``.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from safelane.config import ConfigError, SafelaneConfig, load_config

TRAFFIC_SEED_STRIDE = 10_000_000_000
"""How far apart traffic seeds put a command's episode seeds: ``--seed N`` of ``safelane stress`` and ``safelane
falsify`` shifts every episode seed by ``N × 10¹⁰``. Every seed base lies below 2³² and no command's episodes span
10¹⁰ seeds, so seed 0 plays the published episodes and any other seed draws traffic no other seed plays."""


def traffic_seed_base(base: int, seed: int) -> int:
    """The first episode seed of a command whose episodes start at ``base`` under traffic seed ``seed``
    (``base`` itself for seed 0). A negative ``seed`` is a one-line :class:`ConfigError`."""
    if seed < 0:
        raise ConfigError(f"--seed: must be >= 0 (got {seed})")
    return base + seed * TRAFFIC_SEED_STRIDE


class Condition(BaseModel):
    """One traffic condition: an environment preset and overrides."""

    model_config = ConfigDict(extra="forbid")

    name: str
    preset: str = "fast"
    sets: dict[str, Any] = Field(default_factory=dict)
    adversarial: bool = False


def load_conditions(path: str | Path | None = None) -> list[Condition]:
    """Read a conditions YAML list (default: the shipped suite)."""
    source = Path(path) if path else Path(str(resources.files("safelane") / "presets" / "stress.yaml"))
    try:
        data = yaml.safe_load(source.read_text())
    except OSError as err:
        raise ConfigError(f"--conditions {source}: cannot read ({err.strerror})") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"--conditions {source}: not valid YAML ({str(err).splitlines()[0]})") from None
    if not isinstance(data, list):
        raise ConfigError(f"--conditions {source}: expected a YAML list of conditions")
    out = []
    for i, item in enumerate(data):
        try:
            out.append(Condition.model_validate(item))
        except ValidationError as err:
            e = err.errors()[0]
            loc = ".".join(str(p) for p in e["loc"])
            raise ConfigError(f"--conditions {source}: item {i} {loc}: {e['msg']}") from None
    return out


def condition_config(cond: Condition, shield: str, override: bool, sets: list[str] | None = None) -> SafelaneConfig:
    """The environment config of a condition, with the shield mode and extra ``--set`` applied on top."""
    overrides: dict[str, Any] = dict(cond.sets)
    overrides["shield.mode"] = shield
    overrides["shield.override"] = override and shield != "none"
    cfg = load_config(cond.preset, overrides=overrides)
    if sets:
        cfg = load_config(cond.preset, sets=sets, overrides=overrides)
    return cfg
