"""Policies that need no training: constant actions, a seeded random one, and the overtaking probe.

A policy is any callable ``policy(obs, info) -> action index`` (0..4, :mod:`safelane.core.spaces`). The
constant and random policies ignore masks (run them with ``shield.override=true`` to have the shield replace
unsafe actions); the overtaking probe (:func:`overtaking_probe`) chooses among the mask's actions.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from safelane.config import ConfigError
from safelane.core.snapshot import RoadSnapshot
from safelane.core.spaces import FASTER, IDLE, LANE_LEFT, LANE_RIGHT, N_ACTIONS, SLOWER

Policy = Callable[[np.ndarray, dict[str, Any]], Any]
"""``policy(obs, info) -> action``: an index 0..4 (LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER), or with continuous
actions ``[acceleration, steering]`` in [-1, 1] (float32)."""

FIXED_POLICIES: tuple[str, ...] = ("random", "idle", "faster", "slower", "probe")
"""Policies that need no training (``safelane evaluate --policy NAME``); ``probe`` is the FASTER-first
overtaking heuristic that reads the road and the shield's mask
(:func:`overtaking_probe`)."""

FREE_ROAD = 1e9  # [m] the room reported for a lane with no car ahead


def fixed_policy(
    name: str, seed: int = 0, actions: str = "discrete", action_config: dict[str, Any] | None = None
) -> Policy:
    """A policy that needs no training: ``random`` (uniform over the 5 actions, its own RNG seeded
    with ``seed``), ``idle``, ``faster`` or ``slower`` (always that action) — these ignore masks: run
    them with ``shield.override=true`` to have the shield replace unsafe actions — or ``probe`` (the
    overtaking heuristic, which chooses among the mask's actions). With ``actions="continuous"`` one of
    :data:`CONTINUOUS_POLICIES` for the ``env.action`` ``action_config`` (:func:`continuous_policy`)."""
    if actions == "continuous":
        return continuous_policy(name, seed, action_config or {"type": "ContinuousAction"})
    if name == "random":
        rng = np.random.default_rng(seed)

        def random_policy(obs: np.ndarray, info: dict[str, Any]) -> int:
            return int(rng.integers(N_ACTIONS))

        return random_policy
    if name == "probe":
        return ProbePolicy()
    constant = {"idle": IDLE, "faster": FASTER, "slower": SLOWER}
    if name not in constant:
        raise ConfigError(f"policy: unknown policy '{name}'; allowed: {', '.join(FIXED_POLICIES)}")
    return ConstantPolicy(constant[name])


class ConstantPolicy:
    """Always ``action`` (0–4), whatever the state; one environment or a batch
    (:class:`~safelane.running.evaluation.BatchPolicy`)."""

    def __init__(self, action: int) -> None:
        self.action = int(action)

    def __call__(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        return self.action

    def batch(self, obs: np.ndarray, infos: list[dict[str, Any]]) -> np.ndarray:
        """``action`` for every row."""
        return np.full(len(obs), self.action, dtype=np.int64)


class ProbePolicy:
    """The overtaking probe (:func:`overtaking_probe`) as a :class:`~safelane.running.evaluation.BatchPolicy`;
    it reads each state's snapshot (``needs_snapshot``: a batch runner puts it in every ``info``)."""

    needs_snapshot = True

    def __call__(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        return overtaking_probe(obs, info)

    def batch(self, obs: np.ndarray, infos: list[dict[str, Any]]) -> np.ndarray:
        """The probe's action for every row."""
        return np.array([self(row, info) for row, info in zip(obs, infos, strict=True)], dtype=np.int64)


# --- the overtaking probe ----------------------------------------------------------------------------


def snap_of(info: dict[str, Any]) -> RoadSnapshot:
    """The road snapshot of a step's ``info``."""
    return info["snapshot"]


def room_ahead(snap: RoadSnapshot, lane: int) -> float:
    """Distance [m] along the road from the ego to the next car ahead in ``lane`` (FREE_ROAD if none)."""
    others = snap.others()
    dx = snap.position[others, 0] - snap.position[snap.ego, 0]
    ahead = dx[(snap.lane[others] == lane) & (dx > 0)]
    return float(ahead.min()) if ahead.size else FREE_ROAD


def overtaking_probe(obs: np.ndarray, info: dict[str, Any]) -> int:
    """The FASTER-first overtaking heuristic (reads the snapshot and the shield's mask in ``info``):
    FASTER when allowed; else an allowed lane change into a lane whose next car is > 10 m farther than
    in the ego's lane (the farthest); else IDLE; else the last allowed action (SLOWER first)."""
    snap: RoadSnapshot = info["snapshot"]
    mask = info.get("action_mask", np.ones(N_ACTIONS, dtype=bool))
    if mask[FASTER]:
        return FASTER
    lane = int(snap.lane[snap.ego])
    own = room_ahead(snap, lane)
    options = [(room_ahead(snap, lane + (-1 if a == LANE_LEFT else 1)), a) for a in (LANE_LEFT, LANE_RIGHT) if mask[a]]
    better = [o for o in options if o[0] > own + 10.0]
    if better:
        return max(better)[1]
    if mask[IDLE]:
        return IDLE
    return int(np.flatnonzero(mask)[-1])


# --- continuous actions: acceleration and steering ---------------------------------------------------------

CONTINUOUS_POLICIES: tuple[str, ...] = ("random", "faster", "weave")
"""Continuous policies that need no training (``--actions continuous --policy NAME``): ``random`` (uniform
over [-1, 1]², its own RNG), ``faster`` (full throttle, steering to hold its lane) and ``weave`` (a probe: to
the next lane every :data:`WEAVE_PERIOD` seconds, back at the road's edges, holding :data:`WEAVE_SPEED`)."""

HEADING_GAIN = 0.35
"""The share of the lateral error the lane follower removes per decision. With the steering held over a
decision, the error's recursion has the roots of λ² − (1 − k/2)·λ + k/2; k = 0.35 puts both near 0.42 (no
overshoot worth the name at any decision rate)."""
MAX_HEADING = math.pi / 8  # [rad] the steepest heading the lane follower aims for
WEAVE_PERIOD = 4.0  # [s] between the weaving probe's lane changes
WEAVE_SPEED = 25.0  # [m/s] the weaving probe's speed
SPEED_GAIN = 1.0  # [1/s] the weaving probe's speed controller: acceleration per m/s of error


def continuous_ranges(action_config: dict[str, Any]) -> tuple[tuple[float, float], tuple[float, float]]:
    """The acceleration [m/s²] and steering [rad] ranges of an ``env.action`` ContinuousAction config, with
    highway-env's own defaults where it names none."""
    from highway_env.envs.common.action import ContinuousAction

    acc = action_config.get("acceleration_range") or ContinuousAction.ACCELERATION_RANGE
    steer = action_config.get("steering_range") or ContinuousAction.STEERING_RANGE
    return (float(acc[0]), float(acc[1])), (float(steer[0]), float(steer[1]))


def normalised_control(value: float, bounds: tuple[float, float]) -> float:
    """``value`` mapped from ``bounds`` to [-1, 1] (the inverse of highway-env's ``lmap``), clipped."""
    low, high = bounds
    return min(max(2.0 * (value - low) / (high - low) - 1.0, -1.0), 1.0)


def lane_steering(snap: RoadSnapshot, target_lane: int) -> float:
    """[rad] The front-wheel angle that, held for one decision, turns the ego towards the heading that removes
    :data:`HEADING_GAIN` of its lateral distance to ``target_lane``'s centre in that decision (highway-env's
    kinematic bicycle: heading rate ``v·sin β/(L/2)``, ``tan δ = 2·tan β``)."""
    e = snap.ego
    period = 1.0 / snap.policy_frequency
    speed = max(float(snap.speed[e]), 1.0)  # a stopped ego steers as if it crept
    lateral = float((snap.position[e] - snap.lane_origin) @ snap.lane_lateral) - target_lane * snap.lane_width
    heading = math.remainder(float(snap.heading[e]) - snap.lane_heading, math.tau)
    aim = min(max(-HEADING_GAIN * lateral / (speed * period), -MAX_HEADING), MAX_HEADING)
    rate = (aim - heading) / period
    half_length = float(snap.length[e]) / 2.0
    slip = math.asin(min(max(rate * half_length / speed, -1.0), 1.0))
    return math.atan(2.0 * math.tan(slip))


class LaneFollower:
    """Full throttle (``target_speed`` None) or a speed held by a P-controller, steering by :func:`lane_steering`
    to its lane; ``period`` [s] > 0: to the next lane every ``period`` seconds, turning back at the road's edges."""

    needs_snapshot = True

    def __init__(
        self, action_config: dict[str, Any], target_speed: float | None = None, period: float | None = None
    ) -> None:  # fmt: skip
        self.acceleration_range, self.steering_range = continuous_ranges(action_config)
        self.target_speed, self.period = target_speed, period
        self.lane: int | None = None
        self.direction = 1
        self.changed_at = 0.0

    def _target_lane(self, snap: RoadSnapshot) -> int:
        lane = int(snap.lane[snap.ego])
        if self.lane is None or snap.time == 0.0:  # a new episode
            self.lane, self.direction, self.changed_at = lane, 1, 0.0
        if self.period is not None and snap.time - self.changed_at >= self.period and snap.lanes_count > 1:
            if not 0 <= self.lane + self.direction < snap.lanes_count:
                self.direction = -self.direction
            self.lane += self.direction
            self.changed_at = snap.time
        return self.lane

    def __call__(self, obs: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        snap: RoadSnapshot = info["snapshot"]
        steering = lane_steering(snap, self._target_lane(snap))
        if self.target_speed is None:
            acceleration = 1.0
        else:
            wanted = SPEED_GAIN * (self.target_speed - float(snap.speed[snap.ego]))
            acceleration = normalised_control(wanted, self.acceleration_range)
        return np.array([acceleration, normalised_control(steering, self.steering_range)], dtype=np.float32)


def continuous_policy(name: str, seed: int, action_config: dict[str, Any]) -> Policy:
    """A continuous policy of :data:`CONTINUOUS_POLICIES` (``random``: its own RNG seeded with ``seed``)."""
    if name == "random":
        rng = np.random.default_rng(seed)

        def random_policy(obs: np.ndarray, info: dict[str, Any]) -> np.ndarray:
            return rng.uniform(-1.0, 1.0, size=2).astype(np.float32)

        return random_policy
    if name == "faster":
        return LaneFollower(action_config)
    if name == "weave":
        return LaneFollower(action_config, target_speed=WEAVE_SPEED, period=WEAVE_PERIOD)
    raise ConfigError(f"policy: unknown continuous policy '{name}'; allowed: {', '.join(CONTINUOUS_POLICIES)}")
