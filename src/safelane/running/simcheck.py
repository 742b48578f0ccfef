"""``safelane sim check``: is the fast simulator highway-env, on *your* configuration?

Two checks, both on the whole safelane environment (simulator, snapshot, observation, reward, shield):

* **Trajectories** (:func:`compare_episode`): the same configuration is built on both simulators, reset
  with the same seed and driven by the same policy (random, always-FASTER, and random under the robust
  shield with override, so the shield's masks must agree too); after every decision every vehicle's
  position, speed and heading must agree within ``tol`` (m, m/s, rad) and its lane, crash flag, driver type
  (``traffic.driver_mix``), the mask, the observation and the reward must be equal. An episode that diverges
  reports its first divergent decision and what differed first.
* **Statistics** (:func:`stat_episodes_of`, :func:`statistical_tests`): each policy of
  :data:`STAT_POLICIES` plays independent episodes on each simulator (disjoint seed ranges); Fisher's
  exact test compares the collision rates and a permutation test the per-episode mean speeds. A
  p-value above 0.01 means no evidence of a difference at 1 % (``p_value_holm``: adjusted for the
  number of tests, :func:`holm_adjusted`).
* **Replay** (``replay_identical_fraction``): the fast simulator plays highway-env's statistical sample
  again, on the same seeds with the same policies: the share of those episodes whose collision, mean
  speed and length are equal. This separates a simulator difference from the luck of a seed draw.

* **Continuous actions** (:func:`compare_continuous_episode`, :func:`continuous_stat_episodes_of`): the same
  configuration's simulators alone (:func:`safelane.env.factory.make_simulator`) with highway-env's
  ``ContinuousAction`` ego (:data:`CONTINUOUS_ACTION`), driven by
  :data:`CONTINUOUS_POLICIES` (uniform random float32 actions; keeping the lane at a random or full
  throttle): the same
  trajectory comparison (plus whether every snapshot was equal, ``RoadSnapshot.__eq__``), the same two
  tests on independent samples and the same replay. Reported apart (``continuous``), Holm-adjusted apart.

The work is cut into units (one trajectory episode, or :data:`STAT_CHUNK` statistics episodes of one
policy on one simulator) that run in a process pool and are appended to a record file as they finish,
so that a check of hours shows partial results and resumes after a kill.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from highway_env.envs.common.action import ContinuousAction

from safelane.config import SafelaneConfig, build_config, config_to_dict, recorded_config
from safelane.core.errors import ConfigError
from safelane.core.snapshot import RoadSnapshot
from safelane.env.factory import make_env, make_simulator
from safelane.reporting import stats
from safelane.running.evaluation import run_episodes
from safelane.running.policies import fixed_policy

TRAJECTORY_POLICIES: tuple[str, ...] = ("random", "faster", "robust_random")
"""Policies of the trajectory check, cycled over episodes (``robust_random``: random under the robust shield)."""
STAT_POLICIES: tuple[str, ...] = ("random", "idle", "slower", "faster", "robust_random")
"""Policies of the statistical comparison."""
TOLERANCE = 1e-6  # [m, m/s, rad] per vehicle and decision
CONTINUOUS_ACTION: dict[str, Any] = {"type": "ContinuousAction"}
"""highway-env's action settings of the continuous check: its defaults (acceleration and steering, clipped,
``ContinuousAction``'s ranges, a kinematic ego)."""
CONTINUOUS_POLICIES: tuple[str, ...] = ("uniform", "random_throttle", "full_throttle")
"""Policies of the continuous check (:func:`continuous_policy`), cycled over its trajectory episodes."""
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


def _error(a: RoadSnapshot, b: RoadSnapshot) -> float:
    """Largest difference of any vehicle's position, speed or heading (m, m/s, rad); inf if the counts differ."""
    if a.n != b.n:
        return math.inf
    return max(float(np.abs(getattr(a, f) - getattr(b, f)).max(initial=0.0)) for f in ("position", "speed", "heading"))


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
    if (a.driver_type is None) != (b.driver_type is None):
        return f"driver types {'none' if a.driver_type is None else 'drawn'} on highway-env, not on fast"
    if a.driver_type is not None and not np.array_equal(a.driver_type, b.driver_type):
        i = int(np.flatnonzero(a.driver_type != b.driver_type)[0])
        return f"vehicle {i} driver_type: {a.driver_type[i]} on highway-env, {b.driver_type[i]} on fast"
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


def compare_episode_error(
    cfg: SafelaneConfig, seed: int, policy: str, tol: float = TOLERANCE
) -> tuple[Divergence | None, float]:
    """Drive ``cfg`` on highway-env and on the fast simulator with ``policy`` from reset ``seed``: the
    first :class:`Divergence` (None when the whole episode agreed) and the largest position, speed or
    heading difference seen up to it (m, m/s, rad; 0.0 means bit-identical states)."""
    envs = [make_env(on_simulator(cfg, sim, policy)) for sim in ("highway-env", "fast")]
    policies = [_policy(policy, seed), _policy(policy, seed)]
    worst = 0.0

    def check(step: int, obs: tuple[np.ndarray, np.ndarray], infos: tuple[dict, dict]) -> Divergence | None:
        nonlocal worst
        worst = max(worst, _error(infos[0]["snapshot"], infos[1]["snapshot"]))
        cause = _state_difference(obs, infos, tol)
        return None if cause is None else Divergence(seed, policy, step, cause)

    try:
        (obs_a, info_a), (obs_b, info_b) = (env.reset(seed=seed) for env in envs)
        step = 0
        while True:
            found = check(step, (obs_a, obs_b), (info_a, info_b))
            if found is not None:
                return found, worst
            obs_a, r_a, term_a, trunc_a, info_a = envs[0].step(policies[0](obs_a, info_a))
            obs_b, r_b, term_b, trunc_b, info_b = envs[1].step(policies[1](obs_b, info_b))
            step += 1
            if abs(r_a - r_b) > tol:
                return Divergence(seed, policy, step, f"reward {r_a} on highway-env, {r_b} on fast"), worst
            if (term_a, trunc_a) != (term_b, trunc_b):
                cause = (
                    f"episode end (terminated, truncated) {(term_a, trunc_a)} "
                    f"on highway-env, {(term_b, trunc_b)} on fast"
                )
                return Divergence(seed, policy, step, cause), worst
            if term_a or trunc_a:
                return check(step, (obs_a, obs_b), (info_a, info_b)), worst
    finally:
        for env in envs:
            env.close()


def compare_episode(cfg: SafelaneConfig, seed: int, policy: str, tol: float = TOLERANCE) -> Divergence | None:
    """Drive ``cfg`` on highway-env and on the fast simulator with ``policy`` from reset ``seed``;
    the first :class:`Divergence`, or None when the whole episode agreed within ``tol``."""
    return compare_episode_error(cfg, seed, policy, tol)[0]


def stat_episodes_of(
    cfg: SafelaneConfig,
    policy: str,
    simulator: str,
    start: int,
    count: int,
    seed: int,
    sample_of: str | None = None,
) -> dict[str, list[float]]:
    """Episodes ``start … start+count-1`` of ``policy``'s sample on ``simulator``: reset seeds
    ``seed + offset + i`` (an offset per simulator, so the two samples are independent; ``sample_of``:
    use that simulator's offset instead, to replay its sample), the random policy's generator seeded
    per chunk so that a chunk's episodes do not depend on which process plays it. Per episode:
    ``collision`` (0/1), ``mean_speed`` [m/s] and ``length`` (decisions)."""
    offset = HIGHWAY_ENV_SEED_OFFSET if (sample_of or simulator) == "highway-env" else FAST_SEED_OFFSET
    env = make_env(on_simulator(cfg, simulator, policy))
    try:
        records = run_episodes(env, _policy(policy, seed + offset + start), count, seed + offset + start)
    finally:
        env.close()
    return {
        "collision": [float(r.collision) for r in records],
        "mean_speed": [float(r.mean_speed) for r in records],
        "length": [float(r.length) for r in records],
    }


# --- continuous actions: the simulators alone, with highway-env's ContinuousAction ego -----------------------

ContinuousPolicy = Callable[[RoadSnapshot], np.ndarray]
"""``policy(snapshot) -> action``: a ``ContinuousAction`` (float32, [acceleration, steering] in [-1, 1])."""


def lane_keeping_action(
    snap: RoadSnapshot,
    acceleration: float = 1.0,
    lane: int | None = None,
    steering_range: tuple[float, float] = ContinuousAction.STEERING_RANGE,
) -> np.ndarray:
    """A ``ContinuousAction`` (float32 ``[acceleration, steering]``) that holds ``acceleration`` (in action
    units, -1..1) and steers the ego to the centre of ``lane`` (default: its own): towards the heading that
    closes its lateral offset in 2 s at its speed, reached within one decision by the kinematic bicycle
    (heading rate = v·sin β / (L/2), tan β = tan δ / 2); the steering angle δ [rad] is mapped back through
    ``steering_range`` (the inverse of highway-env's ``lmap``) and clipped to [-1, 1]."""
    e = snap.ego
    target = int(snap.lane[e]) if lane is None else lane
    offset = float((snap.position[e] - snap.lane_origin) @ snap.lane_lateral) - target * snap.lane_width
    speed = max(float(snap.speed[e]), 1.0)
    heading = math.remainder(float(snap.heading[e]) - snap.lane_heading, 2 * math.pi)
    wanted = math.atan(-offset / (2.0 * speed))
    rate = (wanted - heading) * snap.policy_frequency  # [rad/s] to reach it in one decision
    beta = math.asin(min(max(rate * float(snap.length[e]) / 2 / speed, -1.0), 1.0))
    steering = math.atan(2 * math.tan(beta))
    low, high = steering_range
    unit = (2 * steering - (high + low)) / (high - low)
    return np.array([acceleration, min(max(unit, -1.0), 1.0)], dtype=np.float32)


def continuous_policy(name: str, seed: int) -> ContinuousPolicy:
    """A policy of the continuous check: ``uniform`` (each action uniform in [-1, 1]², float32 as gymnasium's
    Box samples them, from a generator seeded with ``seed``: the ego soon spins off the road),
    ``random_throttle`` (:func:`lane_keeping_action` at an acceleration uniform in [-1, 1] from that generator:
    the ego stays in traffic) or ``full_throttle`` (:func:`lane_keeping_action` at acceleration 1)."""
    rng = np.random.default_rng(seed)
    if name == "uniform":
        return lambda snap: rng.uniform(-1.0, 1.0, 2).astype(np.float32)
    if name == "random_throttle":
        return lambda snap: lane_keeping_action(snap, float(rng.uniform(-1.0, 1.0)))
    if name == "full_throttle":
        return lane_keeping_action
    raise ConfigError(f"policy: unknown continuous policy '{name}'; allowed: {', '.join(CONTINUOUS_POLICIES)}")


def _continuous_simulator(cfg: SafelaneConfig, simulator: str) -> Any:
    """``cfg``'s simulator tier on ``simulator`` with a :data:`CONTINUOUS_ACTION` ego, or ``cfg``'s own
    ContinuousAction settings where it has them (no shield, no reward; the episode ends off the road only where
    ``cfg`` says so, as for meta-actions)."""
    data = config_to_dict(cfg)
    action = cfg.env.get("action", {})
    action = dict(action) if action.get("type") == "ContinuousAction" else dict(CONTINUOUS_ACTION)
    env = {**data["env"], "action": action, "offroad_terminal": cfg.env.get("offroad_terminal", False)}
    data.update(simulator=simulator, actions="continuous", state="paper", env=env, shield={"mode": "none"})
    return make_simulator(build_config(data))


def compare_continuous_episode(
    cfg: SafelaneConfig, seed: int, policy: str, tol: float = TOLERANCE
) -> tuple[Divergence | None, float, bool]:
    """:func:`compare_episode_error` with a ``ContinuousAction`` ego on the two simulators alone, the action
    chosen by ``continuous_policy(policy, seed)`` from highway-env's snapshot and handed to both as the same
    object: (the first :class:`Divergence` or None, the largest position, speed or heading difference seen up
    to it, whether every snapshot up to it was equal to the bit, ``RoadSnapshot.__eq__``)."""
    envs = [_continuous_simulator(cfg, sim) for sim in ("highway-env", "fast")]
    act = continuous_policy(policy, seed)
    worst, equal = 0.0, True

    def check(step: int, infos: tuple[dict, dict]) -> Divergence | None:
        nonlocal worst, equal
        a, b = infos[0]["snapshot"], infos[1]["snapshot"]
        worst = max(worst, _error(a, b))
        equal = equal and a == b
        cause = _difference(a, b, tol)
        return None if cause is None else Divergence(seed, policy, step, cause)

    try:
        (_, info_a), (_, info_b) = (env.reset(seed=seed) for env in envs)
        step = 0
        while True:
            found = check(step, (info_a, info_b))
            if found is not None:
                return found, worst, equal
            action = act(info_a["snapshot"])
            _, _, term_a, trunc_a, info_a = envs[0].step(action)
            _, _, term_b, trunc_b, info_b = envs[1].step(action)
            step += 1
            if (bool(term_a), bool(trunc_a)) != (bool(term_b), bool(trunc_b)):
                cause = (
                    f"episode end (terminated, truncated) {(bool(term_a), bool(trunc_a))} "
                    f"on highway-env, {(bool(term_b), bool(trunc_b))} on fast"
                )
                return Divergence(seed, policy, step, cause), worst, equal
            if term_a or trunc_a:
                return check(step, (info_a, info_b)), worst, equal
    finally:
        for env in envs:
            env.close()


def continuous_stat_episodes_of(
    cfg: SafelaneConfig,
    policy: str,
    simulator: str,
    start: int,
    count: int,
    seed: int,
    sample_of: str | None = None,
) -> dict[str, list[float]]:
    """:func:`stat_episodes_of` with a ``ContinuousAction`` ego on the simulator alone: episode ``i`` reset with
    ``seed + offset + i`` and driven by ``continuous_policy(policy, seed + offset + i)`` (its actions depend on
    its seed only). Per episode: ``collision`` (0/1: the ego crashed), ``mean_speed`` [m/s] (its speed after
    each decision, averaged) and ``length`` (decisions)."""
    offset = HIGHWAY_ENV_SEED_OFFSET if (sample_of or simulator) == "highway-env" else FAST_SEED_OFFSET
    env = _continuous_simulator(cfg, simulator)
    out: dict[str, list[float]] = {"collision": [], "mean_speed": [], "length": []}
    try:
        for i in range(start, start + count):
            episode_seed = seed + offset + i
            act = continuous_policy(policy, episode_seed)
            _, info = env.reset(seed=episode_seed)
            speeds: list[float] = []
            while True:
                _, _, terminated, truncated, info = env.step(act(info["snapshot"]))
                speeds.append(info["snapshot"].ego_speed)
                if terminated or truncated:
                    break
            out["collision"].append(float(info["snapshot"].ego_crashed))
            out["mean_speed"].append(float(np.mean(speeds)))
            out["length"].append(float(len(speeds)))
    finally:
        env.close()
    return out


def statistical_tests(samples: dict[tuple[str, str], dict[str, list[float]]], seed: int) -> list[dict[str, Any]]:
    """Fisher's exact test on the collision rates and a permutation test on the per-episode mean
    speeds of each policy's two samples (``samples[(policy, simulator)]``, as :func:`stat_episodes_of`
    returns); one ``{policy, metric, episodes, highway_env, fast, p_value}`` per test."""
    tests: list[dict[str, Any]] = []
    policies = list(dict.fromkeys(policy for policy, _ in samples))
    for policy in policies:
        hw, fast = samples[(policy, "highway-env")], samples[(policy, "fast")]
        n_hw, n_fast = len(hw["collision"]), len(fast["collision"])
        k_hw, k_fast = int(sum(hw["collision"])), int(sum(fast["collision"]))
        common = {"policy": policy, "episodes": {"highway_env": n_hw, "fast": n_fast}}
        tests.append(
            {
                **common,
                "metric": "collision_rate",
                "highway_env": k_hw / n_hw,
                "fast": k_fast / n_fast,
                "p_value": stats.fisher_exact_test(k_hw, n_hw, k_fast, n_fast),
            }
        )
        tests.append(
            {
                **common,
                "metric": "mean_speed",
                "highway_env": float(np.mean(hw["mean_speed"])),
                "fast": float(np.mean(fast["mean_speed"])),
                "p_value": stats.permutation_test(hw["mean_speed"], fast["mean_speed"], reps=2000, seed=seed),
            }
        )
    return tests


def holm_adjusted(tests: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The tests with ``p_value_holm``: Holm's step-down adjustment over all of them (the family-wise
    error of the whole check; the per-policy samples share their reset seeds, so the tests of one
    configuration are not independent either)."""
    m = len(tests)
    order = sorted(range(m), key=lambda i: tests[i]["p_value"])
    adjusted = [0.0] * m
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * tests[i]["p_value"]))
        adjusted[i] = running
    return [{**t, "p_value_holm": adjusted[i]} for i, t in enumerate(tests)]


# --- the whole check as units of work: parallel, recorded as they finish, resumable -----------------------

STAT_CHUNK = 10
"""Episodes per unit of the statistical comparison (the grain of parallel work and of resuming)."""


def _units(episodes: int, stat_episodes: int, continuous: bool = True) -> list[tuple[Any, ...]]:
    """Every unit of work: the trajectories first, then the statistics chunk by chunk (both simulators,
    every policy), so that a check stopped early has whole trajectory results and a prefix of episodes
    that a re-run with a smaller ``--stat-episodes`` (a multiple of :data:`STAT_CHUNK`) reuses; then (with
    ``continuous``) the continuous check's units in the same order, under their own names."""
    units: list[tuple[Any, ...]] = []
    checks = [("", STAT_POLICIES)] + ([("continuous-", CONTINUOUS_POLICIES)] if continuous else [])
    for kind, policies in checks:
        units += [(f"{kind}trajectory", k) for k in range(episodes)]
        chunks = [(start, min(STAT_CHUNK, stat_episodes - start)) for start in range(0, stat_episodes, STAT_CHUNK)]
        for start, count in chunks:
            units += [(f"{kind}stat", p, sim, start, count) for sim in ("highway-env", "fast") for p in policies]
        for start, count in chunks:  # the fast simulator replaying highway-env's sample
            units += [(f"{kind}replay", policy, start, count) for policy in policies]
    return units


def _unit_key(unit: tuple[Any, ...]) -> str:
    return "/".join(str(part) for part in unit)


def _run_unit(cfg_data: dict[str, Any], seed: int, tol: float, unit: tuple[Any, ...]) -> dict[str, Any]:
    """Play one unit (in a worker process); a JSON-ready record."""
    cfg = build_config(cfg_data)
    if unit[0] == "trajectory":
        k = unit[1]
        policy = TRAJECTORY_POLICIES[k % len(TRAJECTORY_POLICIES)]
        found, worst = compare_episode_error(cfg, seed + k, policy, tol)
        return {"divergence": None if found is None else asdict(found), "max_error": worst}
    if unit[0] == "continuous-trajectory":
        k = unit[1]
        policy = CONTINUOUS_POLICIES[k % len(CONTINUOUS_POLICIES)]
        found, worst, equal = compare_continuous_episode(cfg, seed + k, policy, tol)
        return {"divergence": None if found is None else asdict(found), "max_error": worst, "snapshots_equal": equal}
    play = continuous_stat_episodes_of if unit[0].startswith("continuous-") else stat_episodes_of
    if unit[0].endswith("replay"):
        _, policy, start, count = unit
        return play(cfg, policy, "fast", start, count, seed, sample_of="highway-env")
    _, policy, sim, start, count = unit
    return play(cfg, policy, sim, start, count, seed)


def _normalised(header: Any) -> Any:
    """A record header with its configuration re-validated, so that a record written before a config
    key was added still matches the same configuration now — with the value the key had then
    (:func:`safelane.config.recorded_config`): a record made under another shield rule is refused
    rather than resumed under the current one."""
    if not isinstance(header, dict) or not isinstance(header.get("config"), dict):
        return header
    try:
        return {**header, "config": config_to_dict(recorded_config(header["config"]))}
    except ConfigError:
        return header


class CheckRecord:
    """The JSON-lines file of a check's finished units (``--record``): a header naming the configuration,
    seed and tolerance, then one line per unit, appended as each finishes. A killed check re-run with
    the same file plays only what is missing; a file of another check is refused."""

    def __init__(self, path: Path | None, header: dict[str, Any]) -> None:
        self.path = path
        self.done: dict[str, dict[str, Any]] = {}
        if path is None:
            return
        if path.exists() and path.stat().st_size > 0:
            text = path.read_text()
            if not text.endswith("\n"):  # a line cut by a kill: drop it
                text = text[: text.rfind("\n") + 1]
                path.write_text(text)
            lines = [json.loads(line) for line in text.splitlines() if line.strip()]
            if not lines or _normalised(lines[0].get("header")) != _normalised(header):
                raise ConfigError(
                    f"--record {path}: written by a check of another configuration, seed or tolerance; give a new file"
                )
            self.done = {line["unit"]: line["result"] for line in lines[1:]}
        else:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(json.dumps({"header": header}) + "\n")
            except OSError as err:
                raise ConfigError(f"--record {path}: not writable ({err.strerror})") from None

    def add(self, key: str, result: dict[str, Any]) -> None:
        """Keep one finished unit, on disk at once (one appended line)."""
        self.done[key] = result
        if self.path is not None:
            with open(self.path, "a") as f:
                f.write(json.dumps({"unit": key, "result": result}) + "\n")
                f.flush()
                os.fsync(f.fileno())


def _section(
    results: dict[str, dict[str, Any]],
    units: list[tuple[Any, ...]],
    kind: str,
    episodes: int,
    stat_episodes: int,
    seed: int,
) -> dict[str, Any]:
    """One check's figures from its units' records (``kind``: "" the meta-action check, "continuous-" the
    continuous one): trajectory agreement, the Holm-adjusted tests (a family of their own), the replay."""
    trajectories = [results[_unit_key((f"{kind}trajectory", k))] for k in range(episodes)]
    divergences = [t["divergence"] for t in trajectories if t["divergence"] is not None]
    samples: dict[tuple[str, str], dict[str, list[float]]] = {}
    for unit in units:
        if unit[0] == f"{kind}stat":
            sample = samples.setdefault((unit[1], unit[2]), {"collision": [], "mean_speed": [], "length": []})
            for name, values in results[_unit_key(unit)].items():
                sample[name] += values
    replayed = same = 0
    for unit in units:
        if unit[0] == f"{kind}replay":
            _, policy, start, count = unit
            original = results[_unit_key((f"{kind}stat", policy, "highway-env", start, count))]
            again = results[_unit_key(unit)]
            for i in range(count):
                replayed += 1
                same += all(original[name][i] == again[name][i] for name in original)
    errors = [t["max_error"] for t in trajectories if t["divergence"] is None]
    figures = {
        "trajectory_match_fraction": 1.0 - len(divergences) / episodes if episodes else math.nan,
        "bit_identical_fraction": sum(e == 0.0 for e in errors) / episodes if episodes else math.nan,
        "max_error_matched": max(errors, default=0.0),
        "divergences": divergences,
        "tests": holm_adjusted(statistical_tests(samples, seed)) if stat_episodes > 0 else [],
        "replay_episodes": replayed,
        "replay_identical_fraction": same / replayed if replayed else math.nan,
        "mean_length": {f"{p}/{sim}": float(np.mean(v["length"])) for (p, sim), v in samples.items()},
    }
    if kind:  # the continuous check: its action, its policies and the snapshots' equality
        equal = sum(bool(t.get("snapshots_equal")) for t in trajectories if t["divergence"] is None)
        figures = {
            "action": dict(CONTINUOUS_ACTION),
            "policies": list(CONTINUOUS_POLICIES),
            **figures,
            "snapshot_equal_fraction": equal / episodes if episodes else math.nan,
        }
    return figures


def run_sim_check(
    cfg: SafelaneConfig,
    episodes: int,
    seed: int,
    stat_episodes: int = 0,
    tol: float = TOLERANCE,
    workers: int = 1,
    record: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
    continuous: bool = True,
) -> dict[str, Any]:
    """The JSON record of ``safelane sim check``: trajectory agreement over ``episodes`` episodes (reset
    seeds ``seed …``, policies cycled over :data:`TRAJECTORY_POLICIES`) and, with ``stat_episodes`` > 0,
    the statistical tests on ``stat_episodes`` episodes per policy and simulator; with ``continuous`` the same
    again with a ``ContinuousAction`` ego (:data:`CONTINUOUS_POLICIES`), under the key ``continuous`` (None
    without). Units of work run in ``workers`` processes; with ``record`` each finished unit is appended to
    that file and a re-run with it resumes. ``progress(done, total)`` after each unit."""
    start_time = time.perf_counter()
    cfg_data = config_to_dict(cfg)
    header = {"config": cfg_data, "seed": seed, "tolerance": tol, "stat_chunk": STAT_CHUNK}
    book = CheckRecord(None if record is None else Path(record), header)
    units = _units(episodes, stat_episodes, continuous)
    todo = [u for u in units if _unit_key(u) not in book.done]
    finished = len(units) - len(todo)
    if progress is not None:
        progress(finished, len(units))
    if workers <= 1 or len(todo) <= 1:
        for unit in todo:
            book.add(_unit_key(unit), _run_unit(cfg_data, seed, tol, unit))
            finished += 1
            if progress is not None:
                progress(finished, len(units))
    else:
        with ProcessPoolExecutor(max_workers=min(workers, len(todo))) as pool:
            futures = {pool.submit(_run_unit, cfg_data, seed, tol, u): _unit_key(u) for u in todo}
            for fut in as_completed(futures):
                book.add(futures[fut], fut.result())
                finished += 1
                if progress is not None:
                    progress(finished, len(units))
    results = {_unit_key(u): book.done[_unit_key(u)] for u in units}
    meta = _section(results, units, "", episodes, stat_episodes, seed)
    return {
        "preset": cfg.preset,
        "env_id": cfg.env_id,
        "config": cfg_data,
        "episodes": episodes,
        "tolerance": tol,
        **{key: meta[key] for key in ("trajectory_match_fraction", "bit_identical_fraction", "max_error_matched")},
        "divergences": meta["divergences"],
        "stat_episodes": stat_episodes,
        **{key: meta[key] for key in ("tests", "replay_episodes", "replay_identical_fraction", "mean_length")},
        "continuous": _section(results, units, "continuous-", episodes, stat_episodes, seed) if continuous else None,
        "workers": workers,
        "units_resumed": len(units) - len(todo),
        "wall_time_s": time.perf_counter() - start_time,
    }
