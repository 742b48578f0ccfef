"""The stress and generalisation suite: many traffic conditions, per-condition safety statistics.

Conditions are data (``safelane/presets/stress.yaml``, or a user YAML list of
``{name, preset, sets, adversarial}``); each is evaluated with a policy (fixed or trained) and a
shield mode, and reported with collisions, their classification, the collision rate with a 95 %
Wilson interval, mean speed and the shield's intervention rate.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from safelane.config import ConfigError, SafelaneConfig, load_config

STRESS_SEED_BASE = 3_000_000_000
"""Stress episodes are reset with ``STRESS_SEED_BASE + k`` (never used in training or testing)."""


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


def run_condition(
    condition: Condition | str,
    policy: Callable[..., int],
    episodes: int,
    shield: str = "robust",
    override: bool = True,
    sets: list[str] | None = None,
    base: SafelaneConfig | None = None,
    progress: Callable[[int, Any], None] | None = None,
) -> dict[str, Any]:
    """Evaluate ``policy`` on one condition; the per-condition JSON record of ``safelane stress``."""
    from safelane.reporting import stats
    from safelane.running.evaluation import run_config, summarize

    if isinstance(condition, str):
        matches = [c for c in load_conditions() if c.name == condition]
        if not matches:
            allowed = ", ".join(c.name for c in load_conditions())
            raise ConfigError(f"condition: unknown '{condition}'; allowed: {allowed}")
        condition = matches[0]
    if episodes < 1:
        raise ConfigError(f"--episodes: must be >= 1 (got {episodes})")
    cfg = condition_config(condition, shield, override, sets)
    if base is not None:
        # Trained agents keep their own reward and shield settings; only the traffic changes.
        cfg = cfg.model_copy(update={"reward": base.reward})
    start = time.perf_counter()
    records = run_config(cfg, policy, episodes, STRESS_SEED_BASE, progress)
    s = summarize(records)
    return {
        "name": condition.name,
        "adversarial": condition.adversarial,
        "episodes": s["episodes"],
        "collisions": s["collisions"],
        "collision_rate": s["collision_rate"],
        "collision_rate_ci95": list(stats.binomial_ci(s["collisions"], s["episodes"])),
        "mean_speed": s["mean_speed"],
        "shield_intervention_rate": s["shield_intervention_rate"],
        "fallback_rate": s["fallback_rate"],
        "collision_kinds": s["collision_kinds"],
        "wall_time_s": time.perf_counter() - start,
    }


def run_stress(
    policy_factory: Callable[[], Callable[..., int]],
    episodes: int,
    shield: str = "robust",
    override: bool = True,
    conditions: list[Condition] | None = None,
    sets: list[str] | None = None,
    on_condition: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Run every condition; ``policy_factory`` gives a fresh policy per condition (same seeds each)."""
    results = []
    for cond in conditions or load_conditions():
        rec = run_condition(cond, policy_factory(), episodes, shield, override, sets)
        results.append(rec)
        if on_condition:
            on_condition(rec)
    return {"shield": shield, "override": override, "episodes_per_condition": episodes, "conditions": results}
