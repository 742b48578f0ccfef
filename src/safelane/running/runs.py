"""A trained run's environment, from one place.

Every command that drives a trained run (``evaluate RUN_DIR``, ``stress RUN_DIR``, ``render RUN_DIR``,
``reproduce``'s test and stress episodes, the examples) builds its environment with
:func:`run_env_config`: the run's own configuration (``config.yaml``: state kind, decision rate,
target speeds, reward, traffic…), then a stress condition, then the caller's ``--set`` overrides, then
the caller's shield. The trained policy refuses an environment whose state kind, decision rate or
action set differs from its training one (:func:`safelane.env.factory.check_same_interface`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, get_args

from safelane.config import (
    ConfigError,
    SafelaneConfig,
    ShieldConfig,
    apply_overrides,
    build_config,
    config_to_dict,
    load_config,
    parse_set,
)
from safelane.env.factory import check_same_interface, env_interface
from safelane.running.conditions import Condition
from safelane.running.run_directory import RunConfig, load_run_config

SHIELD_MODES: tuple[str, ...] = get_args(ShieldConfig.model_fields["mode"].annotation)
"""Values of ``shield.mode``."""


def run_env_config(
    run: RunConfig | str | Path,
    *,
    sets: list[str] | None = None,
    shield: str | None = None,
    override: bool | None = None,
    condition: Condition | None = None,
) -> SafelaneConfig:
    """The environment config to drive the trained ``run`` in (a run directory or its :class:`RunConfig`).

    Layers, later ones winning: the run's own environment config; ``condition`` (a stress condition:
    what its preset changes relative to the run's preset — e.g. the physics of ``paper`` — then its
    ``sets``); the caller's ``--set`` strings; ``shield`` (``shield.mode``) and ``override``
    (``shield.override``). Raises a one-line :class:`ConfigError` if the result drives the policy with
    another state kind, decision rate or action set than it was trained with.
    """
    source = f"run {run}" if not isinstance(run, RunConfig) else "the run"
    run_cfg = run if isinstance(run, RunConfig) else load_run_config(run)
    data = config_to_dict(run_cfg.env)
    if condition is not None:
        apply_overrides(data, preset_difference(run_cfg.env.preset, condition.preset))
        apply_overrides(data, dict(condition.sets))
    for assignment in sets or []:
        key, value = parse_set(assignment)
        apply_overrides(data, {key: value})
    if shield is not None:
        if shield not in SHIELD_MODES:
            raise ConfigError(f"--shield: unknown shield '{shield}'; allowed: {', '.join(SHIELD_MODES)}")
        data["shield"]["mode"] = shield
    if override is not None:
        data["shield"]["override"] = bool(override and data["shield"]["mode"] != "none")
    cfg = build_config(data)
    check_same_interface(env_interface(run_cfg.env), env_interface(cfg), source)
    return cfg


def preset_difference(trained_preset: str, preset: str) -> dict[str, Any]:
    """Dotted keys (and values) of ``preset`` that differ from ``trained_preset`` (empty when equal)."""
    if preset == trained_preset:
        return {}
    mine, theirs = config_to_dict(load_config(trained_preset)), config_to_dict(load_config(preset))
    out: dict[str, Any] = {}

    def walk(a: Any, b: Any, prefix: str) -> None:
        if isinstance(a, dict) and isinstance(b, dict):
            for key in b:
                walk(a.get(key), b[key], f"{prefix}{key}.")
        elif a != b:
            out[prefix.rstrip(".")] = b

    walk(mine, theirs, "")
    out.pop("preset", None)
    return out
