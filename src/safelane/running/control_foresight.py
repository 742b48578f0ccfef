"""The price of the shield for continuous actions: a perfect-foresight planner over acceleration and steering.

:class:`ControlForesightPlanner` is :class:`~safelane.running.foresight.ForesightPlanner` for an ego under
highway-env's ``ContinuousAction``: the same beam search over the fast simulator's exact future, over a discretised
control set — :data:`CONTROL_ACCELERATIONS` × the ego's lane and its neighbours, each steered there by the lane
follower of the ``faster`` policy (:func:`~safelane.running.policies.lane_steering`). Unmasked (preferring the
sequences from whose end the ego can brake to a standstill, :meth:`ControlForesightPlanner.can_stop`), it bounds
from below how fast a collision-free continuous policy drives in this traffic; under the shield for continuous actions
(``committed``, :class:`~safelane.safety.control_shield.ControlShield`) it takes at every node of the search only
the controls whose plan verifies there, each node carrying its own copy of the shield's memory (the kept plan, the
carried sets), committed along the node's actions. Where none of its controls verifies, it plays what the shield
executes for its fail-safe action (the nearest verified action, else the kept plan's next step) and ranks the
sequence below those that never needed it, as the meta-action planner ranks fallback states.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from safelane.config import ConfigError
from safelane.core.snapshot import RoadSnapshot
from safelane.running.policies import continuous_ranges, lane_steering, normalised_control, snap_of
from safelane.safety.continuous.family import ControlFamily
from safelane.safety.control_shield import ControlShield
from safelane.sim.fast.env import FastHighwayEnv, SimState

CONTROL_ACCELERATIONS: tuple[float, ...] = (-1.0, -0.5, 0.0, 0.5, 1.0)
"""[normalised] The accelerations the planner tries: with highway-env's default range (±5 m/s²) hard braking,
half braking, coasting, half and full throttle."""
LANE_OFFSETS: tuple[int, ...] = (-1, 0, 1)
"""The target lanes the planner steers for, relative to the ego's lane now (those on the road)."""
SPEED_CLASS = 2.0
"""[m/s] The beam keeps the best sequence of each (lane, speed ÷ this) class first (:func:`control_class`)."""


class ControlNode(NamedTuple):
    """A sequence in the search: its rank (minus the decisions at which none of its controls verified; unshielded,
    minus one where the ego cannot stop from its end, :meth:`ControlForesightPlanner.can_stop`), the ego's
    position [m] along the road and speed [m/s] at its end, the simulator state there, its snapshot, the actions
    (2,) played, and the shield's memory after them (None unshielded)."""

    rank: int
    x: float
    v: float
    state: SimState
    snap: RoadSnapshot
    actions: list[np.ndarray]
    memory: ControlFamily | None


def fast_simulator_of(env: Any) -> FastHighwayEnv:
    """The :class:`FastHighwayEnv` inside a safelane environment (ConfigError if it runs on another simulator)."""
    base = env.unwrapped
    if not isinstance(base, FastHighwayEnv):
        raise ConfigError("simulator: the foresight planner needs 'fast' (it copies the simulator's state)")
    return base


def search_shape(env: Any, horizon: float, beam: int, replan: float) -> tuple[FastHighwayEnv, int, int]:
    """(the fast simulator inside ``env``, decisions per search, decisions between searches) of a foresight
    planner looking ``horizon`` [s] ahead and searching again every ``replan`` [s]; a bad ``horizon``, ``beam`` or
    ``replan`` is a one-line :class:`ConfigError`."""
    if not horizon > 0:
        raise ConfigError(f"horizon: must be > 0 s (got {horizon})")
    if beam < 1:
        raise ConfigError(f"beam: must be >= 1 (got {beam})")
    if not replan > 0:
        raise ConfigError(f"replan: must be > 0 s (got {replan})")
    sim = fast_simulator_of(env)
    rate = float(sim.sim.policy_frequency)
    return sim, max(1, round(horizon * rate)), max(1, round(replan * rate))


def shield_of(env: Any) -> ControlShield | None:
    """The :class:`ControlShield` among ``env``'s wrappers, or None."""
    inner = env
    while inner is not None:
        if isinstance(inner, ControlShield):
            return inner
        inner = getattr(inner, "env", None)
    return None


def control_set(snap: RoadSnapshot, acceleration_range: tuple[float, float], steering_range: tuple[float, float],
                accelerations: tuple[float, ...] = CONTROL_ACCELERATIONS) -> list[np.ndarray]:  # fmt: skip
    """The planner's actions (2,) float32 [normalised] in ``snap``: each of ``accelerations`` with the steering
    toward each lane of :data:`LANE_OFFSETS` on the road (``acceleration_range`` [m/s²], ``steering_range`` [rad]:
    the action's, for the normalisation)."""
    lane = int(snap.lane[snap.ego])
    targets = [lane + d for d in LANE_OFFSETS if 0 <= lane + d < snap.lanes_count]
    steerings = [normalised_control(lane_steering(snap, t), steering_range) for t in targets]
    return [np.array([a, s], dtype=np.float32) for s in steerings for a in accelerations]


def diverse_beam(children: list[Any], beam: int, kind: Callable[[Any], tuple[int, ...]]) -> list[Any]:
    """The ``beam`` children (search nodes with ``rank``, ``x`` [m], ``v`` [m/s]) to extend, best first by (rank,
    position, speed): the best of each class ``kind(child)`` first, so that a slower or other-lane sequence survives
    beside the greedy ones (a beam of only the farthest can lose every sequence that brakes in time for a jam
    ahead); then the best of the rest."""
    ranked = sorted(children, key=lambda c: (c.rank, c.x, c.v), reverse=True)
    firsts: dict[tuple[int, ...], int] = {}
    for i, c in enumerate(ranked):
        firsts.setdefault(kind(c), i)
    chosen = sorted(firsts.values())[:beam]
    if len(chosen) < beam:
        taken = set(chosen)
        chosen += [i for i in range(len(ranked)) if i not in taken][: beam - len(chosen)]
    return [ranked[i] for i in sorted(chosen)]


def control_class(node: ControlNode) -> tuple[int, int]:
    """A continuous sequence's class in the beam: the ego's lane and its speed ÷ :data:`SPEED_CLASS`."""
    return int(node.snap.lane[node.snap.ego]), int(node.v // SPEED_CLASS)


class ControlForesightPlanner:
    """A continuous policy with perfect foresight (module docstring). ``env``: the safelane environment it acts in
    (``simulator: fast``, ``actions: continuous``); under its :class:`ControlShield` the search keeps to verified
    controls, reading the shield's memory at each search (the environment must execute the planner's actions: the
    shield does, since they verify). ``horizon`` [s], ``beam``, ``replan`` [s] as for
    :class:`~safelane.running.foresight.ForesightPlanner`; ``accelerations`` [normalised] the control set's."""

    def __init__(
        self,
        env: Any,
        horizon: float = 4.0,
        beam: int = 8,
        replan: float = 1.0,
        accelerations: tuple[float, ...] = CONTROL_ACCELERATIONS,
    ) -> None:
        self.sim, self.depth, self.every = search_shape(env, horizon, beam, replan)
        if self.sim.continuous is None:
            raise ConfigError("actions: the continuous foresight planner needs 'continuous'")
        self.beam = beam
        self.accelerations = tuple(float(a) for a in accelerations)
        self.shield = shield_of(env)
        self.ranges = continuous_ranges(dict(self.sim.config["action"]))
        self.plan: list[np.ndarray] = []
        self.searches = 0
        self.nodes = 0
        self.search_time = 0.0

    def options(
        self, snap: RoadSnapshot, memory: ControlFamily | None
    ) -> tuple[list[tuple[np.ndarray, ControlFamily | None]], bool]:
        """([(action, its memory after it)], whether none of the control set verified) in ``snap`` with the
        shield's ``memory`` there (None unshielded: the whole control set, no memory)."""
        actions = control_set(snap, *self.ranges, self.accelerations)
        if memory is None or self.shield is None:
            return [(a, None) for a in actions], False
        assert self.shield.dynamics is not None  # read at reset
        ctx = memory.context(snap, self.shield.dynamics)
        verified = [a for a in actions if ctx.search.plan(float(a[0]), float(a[1])) is not None]
        # None verified: what the shield executes for its fail-safe action (the nearest verified, else the kept plan).
        wanted = verified or [ctx.lane_keeping]
        out: list[tuple[np.ndarray, ControlFamily | None]] = []
        for action in wanted:
            child = copy.deepcopy(memory)
            executed = child.decide(ctx, action).executed
            child.commit()
            out.append((executed, child))
        return out, not verified

    def search(self) -> list[np.ndarray]:
        """The best action sequence from the simulator's current state (restored after)."""
        start_clock = time.perf_counter()
        sim = self.sim
        root = sim.get_state()
        memory = copy.deepcopy(self.shield.family) if self.shield is not None else None
        frontier = [ControlNode(0, 0.0, 0.0, root, sim.snapshot(), [], memory)]
        best_crashed: tuple[int, float, list[np.ndarray]] | None = None
        for _ in range(self.depth):
            children: list[ControlNode] = []
            seen: set[tuple[float, ...]] = set()
            for node in frontier:
                options, unverified = self.options(node.snap, node.memory)
                rank = node.rank - int(unverified)
                for action, child_memory in options:
                    sim.set_state(node.state)
                    _, _, terminated, _, info = sim.step(action)
                    self.nodes += 1
                    child = snap_of(info)
                    e = child.ego
                    x, v = float(child.position[e, 0]), float(child.speed[e])
                    seq = [*node.actions, action]
                    if terminated:  # crashed or off the road
                        if best_crashed is None or (len(seq), x) > best_crashed[:2]:
                            best_crashed = (len(seq), x, seq)
                        continue
                    signature = (round(x, 9), round(float(child.position[e, 1]), 9), round(v, 9),
                                 round(float(child.heading[e]), 9))  # fmt: skip
                    if signature in seen:
                        continue
                    seen.add(signature)
                    node_child = ControlNode(rank, x, v, sim.get_state(), child, seq, child_memory)
                    if self.shield is None and not self.can_stop(node_child):
                        node_child = node_child._replace(rank=rank - 1)
                    children.append(node_child)
            if not children:
                break
            frontier = diverse_beam(children, self.beam, control_class)
            if all(c.snap.time >= sim.sim.duration for c in frontier):
                break
        sim.set_state(root)
        self.searches += 1
        self.search_time += time.perf_counter() - start_clock
        if frontier and frontier[0].actions:
            return frontier[0].actions
        if best_crashed is not None:
            return best_crashed[2]
        return [self.options(sim.snapshot(), memory)[0][-1][0]]

    def can_stop(self, node: ControlNode) -> bool:
        """Whether the ego comes to a standstill from ``node`` braking as hard as it can, steering for its lane,
        without a crash or leaving the road (or reaches the episode's end first). Unshielded, a sequence that ends
        where it cannot ranks as one that passed a fallback state: a planner greedy for distance at up to 40 m/s
        otherwise ends its horizon where no action avoids the car ahead. The shield's plans end stopped, so under
        it no such check is needed. Leaves the simulator in the last state it reached."""
        sim = self.sim
        sim.set_state(node.state)
        snap = node.snap
        while float(snap.speed[snap.ego]) > 0.0 and snap.time < sim.sim.duration:
            steering = normalised_control(lane_steering(snap, int(snap.lane[snap.ego])), self.ranges[1])
            _, _, terminated, _, info = sim.step(np.array([-1.0, steering], dtype=np.float32))
            self.nodes += 1
            if terminated:
                return False
            snap = snap_of(info)
        return True

    def __call__(self, obs: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        if not self.plan:
            self.plan = self.search()[: self.every]
        return self.plan.pop(0).copy()

    def reset(self) -> None:
        """Forget the current plan (call at the start of an episode; the shield forgets its own memory)."""
        self.plan = []


__all__ = [
    "CONTROL_ACCELERATIONS", "ControlForesightPlanner", "control_class", "control_set", "diverse_beam",
    "fast_simulator_of", "search_shape", "shield_of",
]  # fmt: skip
