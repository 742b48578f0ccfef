"""The stress and generalisation suite: many traffic conditions, per-condition safety statistics.

Conditions are data (``safelane/presets/stress.yaml``, or a user YAML list of
``{name, preset, sets, adversarial}``); each is evaluated with a policy (fixed or trained) and a
shield mode, and reported with collisions, their classification, the collision rate with a 95 %
Wilson interval, mean speed and the shield's intervention rate. With continuous actions (``--set actions=continuous``:
acceleration and steering, the shield for continuous actions) also the episodes ended off the road and the
shield's projections.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from safelane.config import ConfigError
from safelane.core.errors import NotSupported
from safelane.running.conditions import Condition, condition_config, load_conditions, traffic_seed_base

if TYPE_CHECKING:
    from safelane.running.policies import Policy
    from safelane.running.run_directory import RunConfig

STRESS_SEED_BASE = 3_000_000_000
"""Stress episodes are reset with ``STRESS_SEED_BASE + k`` (never used in training or testing); traffic seed ``N``
adds ``N ×`` :data:`~safelane.running.conditions.TRAFFIC_SEED_STRIDE`."""


def run_condition(
    condition: Condition | str,
    policy: Policy | str,
    episodes: int,
    shield: str | None = "robust",
    override: bool | None = True,
    sets: list[str] | None = None,
    run: RunConfig | None = None,
    progress: Callable[[int, Any], None] | None = None,
    counterexamples: Path | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """Evaluate ``policy`` on one condition; the per-condition JSON record of ``safelane stress``.

    ``policy``: a callable, or a fixed policy's name (:func:`~safelane.running.policies.fixed_policy`, built for the
    condition's action set: with continuous actions its acceleration and steering ranges; seeded with ``seed``).

    ``seed``: the traffic seed (0: the published episodes, ``STRESS_SEED_BASE + k``; another draws fresh
    traffic, :func:`~safelane.running.conditions.traffic_seed_base`).

    ``counterexamples``: a directory where every crash and invariant break is saved as a replayable
    file (:mod:`safelane.running.counterexamples`), named after the condition.

    For a trained ``run`` the environment is the run's own (:func:`safelane.running.runs.run_env_config`)
    with the condition on top, and ``shield`` / ``override`` of None keep the run's shield; a condition
    that changes what the policy reads or how often it decides is refused with a one-line error.
    """
    from safelane.reporting import stats
    from safelane.running.evaluation import COMMITTED_FIGURES, CONTINUOUS_FIGURES, run_config, summarize
    from safelane.running.policies import fixed_policy

    if isinstance(condition, str):
        matches = [c for c in load_conditions() if c.name == condition]
        if not matches:
            allowed = ", ".join(c.name for c in load_conditions())
            raise ConfigError(f"condition: unknown '{condition}'; allowed: {allowed}")
        condition = matches[0]
    if episodes < 1:
        raise ConfigError(f"--episodes: must be >= 1 (got {episodes})")
    first_seed = traffic_seed_base(STRESS_SEED_BASE, seed)
    if run is not None:
        from safelane.running.runs import run_env_config

        cfg = run_env_config(run, sets=sets, shield=shield, override=override, condition=condition)
    else:
        cfg = condition_config(condition, shield or "robust", bool(override), sets)
    if isinstance(policy, str):
        policy = fixed_policy(policy, seed, cfg.actions, cfg.env.get("action"))
    start = time.perf_counter()
    records = run_config(cfg, policy, episodes, first_seed, progress)
    s = summarize(records)
    files: list[Path] = []
    if counterexamples is not None:
        from safelane.running.counterexamples import save_counterexamples

        files = save_counterexamples(records, cfg, counterexamples, f"stress {condition.name}", f"{condition.name}-")
    return {
        "name": condition.name,
        "adversarial": condition.adversarial,
        "simulator": cfg.simulator,
        **({"actions": cfg.actions} if cfg.actions == "continuous" else {}),
        "episodes": s["episodes"],
        "collisions": s["collisions"],
        "collision_rate": s["collision_rate"],
        "collision_rate_ci95": list(stats.binomial_ci(s["collisions"], s["episodes"])),
        "mean_speed": s["mean_speed"],
        "mean_length": s["mean_length"],
        "shield_intervention_rate": s["shield_intervention_rate"],
        "fallback_rate": s["fallback_rate"],
        "invariant_breaks": s["invariant_breaks"],
        "invariant_break_rate": s["invariant_break_rate"],
        "collision_kinds": s["collision_kinds"],
        "collision_contexts": s["collision_contexts"],
        # The committed mode's lapses (in the model), plan-forced share, uncertified starts, redraws.
        **{k: s[k] for k in COMMITTED_FIGURES if k in s},
        # Continuous actions: episodes off the road, the shield's projections.
        **{k: s[k] for k in CONTINUOUS_FIGURES if k in s},
        "counterexample_files": [str(f) for f in files],
        "wall_time_s": time.perf_counter() - start,
    }


def run_stress(
    policy_factory: Callable[[], Policy | str],
    episodes: int,
    shield: str | None = "robust",
    override: bool | None = True,
    conditions: list[Condition] | None = None,
    sets: list[str] | None = None,
    on_condition: Callable[[dict[str, Any]], None] | None = None,
    run: RunConfig | None = None,
    counterexamples: Path | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """Run every condition; ``policy_factory`` gives a fresh policy per condition (same seeds each), or a fixed
    policy's name (:func:`run_condition` builds it for each condition);
    ``counterexamples``: save every crash and invariant break there; ``seed``: the traffic seed, recorded in
    the result (:func:`run_condition`).

    Conditions that cannot run as asked — a trained ``run``'s policy in another decision rate, state or
    action set, a traffic option the chosen simulator does not model — are recorded as
    ``{"name", "adversarial", "skipped": reason}`` instead of failing the suite.
    """
    results = []
    for cond in conditions or load_conditions():
        try:
            rec = run_condition(
                cond,
                policy_factory(),
                episodes,
                shield,
                override,
                sets,
                run=run,
                counterexamples=counterexamples,
                seed=seed,
            )
        except NotSupported as err:
            rec = {"name": cond.name, "adversarial": cond.adversarial, "skipped": str(err)}
        results.append(rec)
        if on_condition:
            on_condition(rec)
    mode = shield if shield is not None or run is None else run.env.shield.mode
    return {
        "shield": mode,
        "override": override,
        "episodes_per_condition": episodes,
        "seed": seed,
        "conditions": results,
    }
