"""Run policies on the environment and summarise what happened: collisions, speed, shield activity.

A policy is any callable ``policy(obs, info) -> action index`` (0..4, :mod:`safelane.core.spaces`).
:func:`run_episodes` plays seeded episodes (episode ``i`` is reset with ``seed + i``) and returns one
:class:`EpisodeRecord` per episode; :func:`summarize` turns records into one JSON-ready dict. The CLI's
``safelane evaluate`` is a thin layer over :func:`evaluate_fixed`.

Collisions are classified from geometry at the moment of impact (:func:`classify_collision`):
``ego_hit_front`` (the ego drove into a vehicle ahead in its lane), ``rear_ended`` (a vehicle behind
drove into the ego) or ``side`` (lateral contact, i.e. during a lane change). highway-env marks both
vehicles ``crashed`` but records nobody's fault, and after the impact it pushes the two bodies apart
and lets the ego slide on, so the geometry at the end of a decision step is unreliable;
:func:`watch_collisions` keeps the positions of the physics frame around the impact instead.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

from safelane.config import ConfigError, SafelaneConfig
from safelane.core.spaces import ACTION_NAMES, FASTER, IDLE, N_ACTIONS, SLOWER

Policy = Callable[[np.ndarray, dict[str, Any]], int]
"""``policy(obs, info) -> action index`` (0..4: LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER)."""

FIXED_POLICIES: tuple[str, ...] = ("random", "idle", "faster", "slower")
"""Policies that need no training (``safelane evaluate --policy NAME``)."""

COLLISION_KINDS: tuple[str, ...] = ("ego_hit_front", "rear_ended", "side")
"""Every value :func:`classify_collision` returns for a crashed ego."""


# --- fixed policies ------------------------------------------------------------------------------


def fixed_policy(name: str, seed: int = 0) -> Policy:
    """A policy that needs no training: ``random`` (uniform over the 5 actions, its own RNG seeded
    with ``seed``), ``idle``, ``faster`` or ``slower`` (always that action). Masks are ignored: run it
    with ``shield.override=true`` to have the shield replace unsafe actions."""
    if name == "random":
        rng = np.random.default_rng(seed)

        def random_policy(obs: np.ndarray, info: dict[str, Any]) -> int:
            return int(rng.integers(N_ACTIONS))

        return random_policy
    constant = {"idle": IDLE, "faster": FASTER, "slower": SLOWER}
    if name not in constant:
        raise ConfigError(f"policy: unknown policy '{name}'; allowed: {', '.join(FIXED_POLICIES)}")
    action = constant[name]

    def constant_policy(obs: np.ndarray, info: dict[str, Any]) -> int:
        return action

    return constant_policy


# --- collision classification -----------------------------------------------------------------


def _bodies(road: Any) -> list[Any]:
    """Everything the ego can crash into: vehicles and collidable objects (obstacles)."""
    return [*road.vehicles, *(o for o in getattr(road, "objects", []) if getattr(o, "collidable", True))]


def _positions(road: Any) -> list[tuple[Any, np.ndarray]]:
    return [(v, np.array(v.position, dtype=float)) for v in _bodies(road)]


class _CrashWatch:
    """Replaces one road's ``step`` (one physics frame) to keep the positions around the ego's first
    crash: ``before`` (start of the impact frame) and ``after`` (end of it, bodies still overlapping,
    before highway-env applies its separating impulse on the next frame).

    Holds the road and the wrapped bound method as attributes, so a ``deepcopy`` of the road gets a
    watch of its own (the bound method is re-bound to the copy).
    """

    def __init__(self, road: Any, ego: Any) -> None:
        self.road = road
        self.ego = ego
        self.inner = road.step
        self.before: list[tuple[Any, np.ndarray]] | None = None
        self.after: list[tuple[Any, np.ndarray]] | None = None

    def __call__(self, dt: float) -> None:
        if self.before is not None or self.ego.crashed:
            self.inner(dt)
            return
        snapshot = _positions(self.road)
        self.inner(dt)
        if self.ego.crashed:
            self.before = snapshot
            self.after = _positions(self.road)


def watch_collisions(env: gym.Env) -> None:
    """Record the impact frame of the ego's next crash on the current road (call after each reset).

    Costs one copy of the vehicle positions per physics frame (tens of µs). Without it,
    :func:`classify_collision` falls back to the (post-impact) geometry at the time of the call.
    """
    base = env.unwrapped
    road = base.road
    if not isinstance(road.__dict__.get("step"), _CrashWatch):
        road.step = _CrashWatch(road, base.vehicle)


def collision_kind(
    before: tuple[float, float],
    after: tuple[float, float],
    half_length: float,
    half_width: float,
) -> str:
    """Classify a contact from the other vehicle's lane-local offset (δs, δr) [m] relative to the ego,
    one physics frame before (``before``) and at (``after``) the impact; ``half_length`` /
    ``half_width`` [m] are the sums of the two bodies' longitudinal / lateral half-extents.

    The face that was hit is the axis along which the bodies came to overlap last. Entry times into
    overlap are linear over the frame; an axis already overlapping before the frame (or not closing,
    which a rotated body allows) entered "before". Lateral overlap first (or together) means a
    front/rear contact: ``ego_hit_front`` if the other was ahead (δs > 0), else ``rear_ended``;
    otherwise ``side``.
    """

    def entry(d0: float, d1: float, half: float) -> float:
        closing = abs(d0) - abs(d1)
        if abs(d0) < half or closing <= 0:
            return -math.inf
        return (abs(d0) - half) / closing

    (s0, r0), (s1, r1) = before, after
    if entry(r0, r1, half_width) > entry(s0, s1, half_length):
        return "side"
    return "ego_hit_front" if s0 > 0 else "rear_ended"


def _extents(vehicle: Any, lane_heading: float) -> tuple[float, float]:
    """(longitudinal, lateral) half-extents [m] of a vehicle's body, rotated by its heading."""
    length, width = float(vehicle.LENGTH), float(vehicle.WIDTH)
    h = float(vehicle.heading) - lane_heading
    c, s = abs(math.cos(h)), abs(math.sin(h))
    return length / 2 * c + width / 2 * s, length / 2 * s + width / 2 * c


def classify_collision(env: gym.Env) -> str | None:
    """The kind of the ego's crash (one of :data:`COLLISION_KINDS`), or None if it has not crashed.

    The partner is the crashed vehicle nearest to the ego at the impact; offsets are taken in the
    ego lane's local coordinates (the road is straight along x). Uses the impact frame recorded by
    :func:`watch_collisions` when there is one, else the current geometry.
    """
    base = env.unwrapped
    ego, road = base.vehicle, base.road
    if not ego.crashed:
        return None
    watch = road.__dict__.get("step")
    if isinstance(watch, _CrashWatch) and watch.before is not None and watch.after is not None:
        before = {id(v): p for v, p in watch.before}
        after = {id(v): p for v, p in watch.after}
    else:
        before = after = {id(v): p for v, p in _positions(road)}
    lane = ego.lane
    candidates = [v for v in _bodies(road) if v is not ego and getattr(v, "crashed", False) and id(v) in after]
    if not candidates:
        return "side"  # no partner found (not produced by highway-env's straight roads)
    ego_after = after[id(ego)]
    other = min(candidates, key=lambda v: float(np.hypot(*(after[id(v)] - ego_after))))

    def offset(positions: dict[int, np.ndarray]) -> tuple[float, float]:
        s_e, r_e = lane.local_coordinates(positions[id(ego)])
        s_o, r_o = lane.local_coordinates(positions[id(other)])
        return float(s_o - s_e), float(r_o - r_e)

    lane_heading = float(lane.heading_at(lane.local_coordinates(ego_after)[0]))
    ego_long, ego_lat = _extents(ego, lane_heading)
    other_long, other_lat = _extents(other, lane_heading)
    return collision_kind(offset(before), offset(after), ego_long + other_long, ego_lat + other_lat)


# --- episodes -----------------------------------------------------------------------------------


@dataclass
class EpisodeRecord:
    """What happened in one episode. Speeds in m/s, times in s, lengths in decisions."""

    seed: int
    return_: float
    length: int
    collision: bool
    time_to_collision: float | None
    mean_speed: float
    interventions: int
    fallbacks: int
    collision_kind: str | None
    unsafe_actions: int = 0
    """Decisions whose *chosen* action the shield's mask marked unsafe (overridden or not)."""
    actions: list[int] = field(default_factory=lambda: [0] * N_ACTIONS)
    """Histogram of the executed actions (after a shield's override), indexed like ACTION_NAMES."""
    vehicles_passed: int = 0
    """Net overtakes: vehicles ahead of the ego (along the road) at the start minus at the end."""

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict of the record."""
        return asdict(self)


ProgressCallback = Callable[[int, EpisodeRecord], None]
"""Called as ``progress(episode_index, record)`` after each episode."""


def vehicles_ahead(env: gym.Env) -> int:
    """Number of other vehicles ahead of the ego along the road (x; highway-env's roads are straight)."""
    base = env.unwrapped
    ego = base.vehicle
    return sum(1 for v in base.road.vehicles if v is not ego and v.position[0] > ego.position[0])


def run_episode(env: gym.Env, policy: Policy, seed: int) -> EpisodeRecord:
    """Play one episode reset with ``seed`` until it terminates or is truncated."""
    obs, info = env.reset(seed=seed)
    watch_collisions(env)
    ahead_at_start = vehicles_ahead(env)
    total_reward = 0.0
    speeds: list[float] = []
    interventions = fallbacks = unsafe_actions = 0
    actions = [0] * N_ACTIONS
    time_to_collision: float | None = None
    collision = False
    steps = 0
    done = False
    while not done:
        action = int(policy(obs, info))
        obs, reward, terminated, truncated, info = env.step(action)
        steps += 1
        total_reward += float(reward)
        speeds.append(float(info["speed"]))
        interventions += bool(info.get("shield_intervened", False))
        fallbacks += bool(info.get("fallback", False))
        unsafe_actions += bool(info.get("unsafe_action", False))
        actions[int(info.get("executed_action", action))] += 1
        if info.get("collision", False) and not collision:
            collision = True
            time_to_collision = float(env.unwrapped.time)
        done = terminated or truncated
    return EpisodeRecord(
        seed=seed,
        return_=total_reward,
        length=steps,
        collision=collision,
        time_to_collision=time_to_collision,
        mean_speed=float(np.mean(speeds)) if speeds else float(env.unwrapped.vehicle.speed),
        interventions=interventions,
        fallbacks=fallbacks,
        collision_kind=classify_collision(env) if collision else None,
        unsafe_actions=unsafe_actions,
        actions=actions,
        vehicles_passed=ahead_at_start - vehicles_ahead(env),
    )


def run_episodes(
    env: gym.Env,
    policy: Policy,
    episodes: int,
    seed: int,
    progress: ProgressCallback | None = None,
) -> list[EpisodeRecord]:
    """Play ``episodes`` episodes, episode ``i`` reset with ``seed + i``; same inputs, same records."""
    if episodes < 1:
        raise ValueError(f"episodes: must be >= 1 (got {episodes})")
    records: list[EpisodeRecord] = []
    for i in range(episodes):
        record = run_episode(env, policy, seed + i)
        records.append(record)
        if progress is not None:
            progress(i, record)
    return records


def summarize(records: list[EpisodeRecord], **meta: Any) -> dict[str, Any]:
    """Aggregate records into one JSON-ready dict; ``meta`` (policy, shield, preset…) is merged in.

    ``mean_speed`` [m/s] is the mean over episodes of each episode's mean speed;
    ``mean_vehicles_passed`` the mean net overtakes per episode; the intervention, fallback and
    unsafe-choice rates are per decision; ``time_to_collision`` lists one entry per episode (seconds,
    or None without a collision).
    """
    if not records:
        raise ValueError("summarize: no episodes")
    n = len(records)
    decisions = sum(r.length for r in records)
    kinds = dict.fromkeys(COLLISION_KINDS, 0)
    for r in records:
        if r.collision_kind is not None:
            kinds[r.collision_kind] += 1
    actions = [sum(r.actions[a] for r in records) for a in range(N_ACTIONS)]
    collisions = sum(r.collision for r in records)
    summary: dict[str, Any] = {
        "episodes": n,
        "decisions": decisions,
        "collisions": collisions,
        "collision_rate": collisions / n,
        "mean_speed": float(np.mean([r.mean_speed for r in records])),
        "mean_return": float(np.mean([r.return_ for r in records])),
        "mean_length": decisions / n,
        "time_to_collision": [r.time_to_collision for r in records],
        "shield_intervention_rate": sum(r.interventions for r in records) / max(decisions, 1),
        "fallback_rate": sum(r.fallbacks for r in records) / max(decisions, 1),
        "unsafe_action_rate": sum(r.unsafe_actions for r in records) / max(decisions, 1),
        "mean_vehicles_passed": float(np.mean([r.vehicles_passed for r in records])),
        "collision_kinds": kinds,
        "actions": dict(zip(ACTION_NAMES, actions, strict=True)),
    }
    summary.update(meta)
    return summary


def run_config(
    config: SafelaneConfig,
    policy: Policy,
    episodes: int,
    seed: int,
    progress: ProgressCallback | None = None,
) -> list[EpisodeRecord]:
    """Build the environment of ``config``, play :func:`run_episodes` on it, and close it."""
    from safelane.env.factory import make_env

    env = make_env(config)
    try:
        return run_episodes(env, policy, episodes, seed, progress)
    finally:
        env.close()


def evaluate_fixed(
    config: SafelaneConfig,
    policy: str,
    episodes: int,
    seed: int,
    progress: ProgressCallback | None = None,
) -> dict[str, Any]:
    """Evaluate a fixed policy (:data:`FIXED_POLICIES`) on ``config``: the summary dict of
    :func:`summarize` with ``policy``, ``shield``, ``override``, ``preset``, ``env_id``, ``backend``, ``seed`` and
    ``wall_time_s`` added. With a shield the config should set ``shield.override`` (a fixed policy
    cannot read the mask)."""

    if episodes < 1:
        raise ConfigError(f"--episodes: must be >= 1 (got {episodes})")
    if seed < 0:
        raise ConfigError(f"--seed: must be >= 0 (got {seed})")
    act = fixed_policy(policy, seed)
    start = time.perf_counter()
    records = run_config(config, act, episodes, seed, progress)
    return summarize(
        records,
        policy=policy,
        shield=config.shield.mode,
        override=config.shield.override,
        preset=config.preset,
        env_id=config.env_id,
        backend=config.backend,
        seed=seed,
        wall_time_s=time.perf_counter() - start,
    )
