"""``safelane sim check``: is the fast simulator highway-env, on *your* configuration?

Two checks, both on the whole safelane environment (simulator, snapshot, observation, reward, shield):

* **Trajectories** (:func:`compare_episode`): the same configuration is built on both simulators, reset
  with the same seed and driven by the same policy (random, always-FASTER, and random under the robust
  shield with override, so the shield's masks must agree too); after every decision every vehicle's
  position, speed and heading must agree within ``tol`` (m, m/s, rad) and its lane, crash flag, the
  mask, the observation and the reward must be equal. An episode that diverges reports its first
  divergent decision and what differed first.
* **Statistics** (:func:`compare_statistics`): each policy of :data:`STAT_POLICIES` plays independent
  episodes on each simulator (disjoint seed ranges); Fisher's exact test compares the collision rates
  and a permutation test the per-episode mean speeds. A p-value above 0.01 means no evidence of a
  difference at 1 %.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from safelane.config import SafelaneConfig, build_config, config_to_dict
from safelane.core.snapshot import RoadSnapshot
from safelane.env.factory import make_env
from safelane.reporting import stats
from safelane.running.evaluation import fixed_policy, run_episodes

TRAJECTORY_POLICIES: tuple[str, ...] = ("random", "faster", "robust_random")
"""Policies of the trajectory check, cycled over episodes (``robust_random``: random under the robust shield)."""
STAT_POLICIES: tuple[str, ...] = ("random", "idle", "slower", "faster", "robust_random")
"""Policies of the statistical comparison."""
TOLERANCE = 1e-6  # [m, m/s, rad] per vehicle and decision
HIGHWAY_ENV_SEED_OFFSET = 10_000_000
FAST_SEED_OFFSET = 20_000_000
"""The statistics use seeds ``seed + offset + i``: two independent samples, one per simulator."""


@dataclass(frozen=True)
class Divergence:
    """Where an episode of the two simulators first differed."""

    seed: int
    policy: str
    first_step: int
    """Decision after which they differed (0: right after the reset)."""
    cause: str


def on_simulator(cfg: SafelaneConfig, simulator: str, policy: str) -> SafelaneConfig:
    """``cfg`` on ``simulator``; for ``robust_random`` with the robust shield overriding unsafe actions."""
    data = config_to_dict(cfg)
    data["simulator"] = simulator
    if policy == "robust_random":
        data["shield"] = {**data["shield"], "mode": "robust", "override": True}
    return build_config(data)


def _policy(policy: str, seed: int) -> Callable[[np.ndarray, dict[str, Any]], int]:
    return fixed_policy("random" if policy == "robust_random" else policy, seed)


def _difference(a: RoadSnapshot, b: RoadSnapshot, tol: float) -> str | None:
    """What first differs between two snapshots (None: they agree)."""
    if a.n != b.n:
        return f"{a.n} bodies on highway-env, {b.n} on fast"
    for name in ("position", "speed", "heading"):
        x, y = getattr(a, name), getattr(b, name)
        err = np.abs(x - y).reshape(a.n, -1).max(axis=1)
        if (err > tol).any():
            i = int(np.argmax(err > tol))
            return f"vehicle {i} {name} differs by {float(err[i]):.3g}"
    for name in ("lane", "crashed"):
        x, y = getattr(a, name), getattr(b, name)
        if not np.array_equal(x, y):
            i = int(np.flatnonzero(x != y)[0])
            return f"vehicle {i} {name}: {x[i]} on highway-env, {y[i]} on fast"
    return None


def _state_difference(obs: tuple[np.ndarray, np.ndarray], infos: tuple[dict, dict], tol: float) -> str | None:
    """What first differs between the two simulators' states after a reset or step (None: nothing)."""
    cause = _difference(infos[0]["snapshot"], infos[1]["snapshot"], tol)
    masks = infos[0].get("action_mask"), infos[1].get("action_mask")
    if cause is None and not np.array_equal(*masks):
        cause = f"shield mask {masks[0]} on highway-env, {masks[1]} on fast"
    if cause is None and np.abs(obs[0] - obs[1]).max() > tol:
        cause = f"observation differs by {float(np.abs(obs[0] - obs[1]).max()):.3g}"
    return cause


def compare_episode(cfg: SafelaneConfig, seed: int, policy: str, tol: float = TOLERANCE) -> Divergence | None:
    """Drive ``cfg`` on highway-env and on the fast simulator with ``policy`` from reset ``seed``;
    the first :class:`Divergence`, or None when the whole episode agreed."""
    envs = [make_env(on_simulator(cfg, sim, policy)) for sim in ("highway-env", "fast")]
    policies = [_policy(policy, seed), _policy(policy, seed)]
    try:
        (obs_a, info_a), (obs_b, info_b) = (env.reset(seed=seed) for env in envs)
        step = 0
        while True:
            cause = _state_difference((obs_a, obs_b), (info_a, info_b), tol)
            if cause is not None:
                return Divergence(seed, policy, step, cause)
            obs_a, r_a, term_a, trunc_a, info_a = envs[0].step(policies[0](obs_a, info_a))
            obs_b, r_b, term_b, trunc_b, info_b = envs[1].step(policies[1](obs_b, info_b))
            step += 1
            if abs(r_a - r_b) > tol:
                return Divergence(seed, policy, step, f"reward {r_a} on highway-env, {r_b} on fast")
            if (term_a, trunc_a) != (term_b, trunc_b):
                return Divergence(
                    seed,
                    policy,
                    step,
                    f"episode end (terminated, truncated) {(term_a, trunc_a)} "
                    f"on highway-env, {(term_b, trunc_b)} on fast",
                )
            if term_a or trunc_a:
                cause = _state_difference((obs_a, obs_b), (info_a, info_b), tol)
                return None if cause is None else Divergence(seed, policy, step, cause)
    finally:
        for env in envs:
            env.close()


def compare_statistics(
    cfg: SafelaneConfig,
    episodes: int,
    seed: int,
    policies: tuple[str, ...] = STAT_POLICIES,
    progress: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Collision rate (Fisher's exact test) and mean speed (permutation test) of each policy, ``episodes``
    independent episodes per simulator; one ``{policy, metric, highway_env, fast, p_value}`` per test."""
    tests: list[dict[str, Any]] = []
    for policy in policies:
        results = {}
        for sim, offset in (("highway-env", HIGHWAY_ENV_SEED_OFFSET), ("fast", FAST_SEED_OFFSET)):
            env = make_env(on_simulator(cfg, sim, policy))
            try:
                records = run_episodes(env, _policy(policy, seed + offset), episodes, seed + offset)
            finally:
                env.close()
            results[sim] = records
            if progress is not None:
                progress(f"{policy} on {sim}")
        hw, fast = results["highway-env"], results["fast"]
        k_hw, k_fast = sum(r.collision for r in hw), sum(r.collision for r in fast)
        tests.append(
            {
                "policy": policy,
                "metric": "collision_rate",
                "highway_env": k_hw / episodes,
                "fast": k_fast / episodes,
                "p_value": stats.fisher_exact_test(k_hw, episodes, k_fast, episodes),
            }
        )
        speeds_hw, speeds_fast = [r.mean_speed for r in hw], [r.mean_speed for r in fast]
        tests.append(
            {
                "policy": policy,
                "metric": "mean_speed",
                "highway_env": float(np.mean(speeds_hw)),
                "fast": float(np.mean(speeds_fast)),
                "p_value": stats.permutation_test(speeds_hw, speeds_fast, reps=2000, seed=seed),
            }
        )
    return tests


def run_sim_check(
    cfg: SafelaneConfig,
    episodes: int,
    seed: int,
    stat_episodes: int = 0,
    tol: float = TOLERANCE,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """The JSON record of ``safelane sim check``: trajectory agreement over ``episodes`` episodes (reset
    seeds ``seed …``, policies cycled over :data:`TRAJECTORY_POLICIES`) and, with ``stat_episodes`` > 0,
    the statistical tests."""
    start = time.perf_counter()
    divergences: list[Divergence] = []
    for k in range(episodes):
        policy = TRAJECTORY_POLICIES[k % len(TRAJECTORY_POLICIES)]
        found = compare_episode(cfg, seed + k, policy, tol)
        if found is not None:
            divergences.append(found)
        if progress is not None:
            progress(f"trajectory {k + 1}/{episodes}")
    tests = compare_statistics(cfg, stat_episodes, seed, progress=progress) if stat_episodes > 0 else []
    return {
        "preset": cfg.preset,
        "env_id": cfg.env_id,
        "episodes": episodes,
        "tolerance": tol,
        "trajectory_match_fraction": 1.0 - len(divergences) / episodes if episodes else math.nan,
        "divergences": [asdict(d) for d in divergences],
        "stat_episodes": stat_episodes,
        "tests": tests,
        "wall_time_s": time.perf_counter() - start,
    }
