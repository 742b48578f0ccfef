"""Policies that need no training: constant actions, a seeded random one, and the overtaking probe.

A policy is any callable ``policy(obs, info) -> action index`` (0..4, :mod:`safelane.core.spaces`). The
constant and random policies ignore masks (run them with ``shield.override=true`` to have the shield replace
unsafe actions); the overtaking probe (:func:`overtaking_probe`) chooses among the mask's actions.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from safelane.config import ConfigError
from safelane.core.snapshot import RoadSnapshot
from safelane.core.spaces import FASTER, IDLE, LANE_LEFT, LANE_RIGHT, N_ACTIONS, SLOWER

Policy = Callable[[np.ndarray, dict[str, Any]], int]
"""``policy(obs, info) -> action index`` (0..4: LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER)."""

FIXED_POLICIES: tuple[str, ...] = ("random", "idle", "faster", "slower", "probe")
"""Policies that need no training (``safelane evaluate --policy NAME``); ``probe`` is the FASTER-first
overtaking heuristic that reads the road and the shield's mask
(:func:`overtaking_probe`)."""

FREE_ROAD = 1e9  # [m] the room reported for a lane with no car ahead


def fixed_policy(name: str, seed: int = 0) -> Policy:
    """A policy that needs no training: ``random`` (uniform over the 5 actions, its own RNG seeded
    with ``seed``), ``idle``, ``faster`` or ``slower`` (always that action) — these ignore masks: run
    them with ``shield.override=true`` to have the shield replace unsafe actions — or ``probe`` (the
    overtaking heuristic, which chooses among the mask's actions)."""
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
