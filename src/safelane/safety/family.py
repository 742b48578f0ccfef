"""Rule families: what the shield asks of a safety rule, whatever kind of rule it is.

:class:`~safelane.safety.shield.SafetyShield` asks one question per state — which of the 5 meta-actions may the
agent take — of a :class:`RuleFamily`. A family takes the road snapshot (:class:`RoadSnapshot`), the world's
constants with the rule's options (:class:`Dynamics`, its ``rule``) and the ego's lane-leave time [s] for this
state, and returns a :class:`SafetyResult`:

* ``mask``: the allowed actions, never empty; ``safe``: those that satisfy the rule (may be none);
  ``available``: highway-env's available actions;
* ``min_gap`` [m]: each action's worst-case smallest bumper-to-bumper gap under its best fallback;
* ``fallback``: no action was safe, ``mask`` holds the least-bad one;
* ``conflicts``: the conflicts that decided, one per available action — the vehicle and lane whose worst gap
  under the action's best fallback is its ``min_gap`` (:class:`~safelane.safety.model.Conflict`); None where the
  engine does not report them (the compiled kernels return masks and gaps only).

Two families exist, one per ``shield.mode``: ``nominal`` (the paper's Q-masking) and ``robust`` (robust
Q-masking), each a thin adapter (:class:`OneDecisionFamily`) over the one-decision rule of
:mod:`safelane.safety.model` and its compiled port :mod:`safelane.safety.compiled`. A family that judges an
action by more than the next decision (a committed plan) implements the same protocol, keeping what it carries
from one decision to the next inside itself, and is added to :func:`family_for`.

Also :func:`road_state`, the snapshot in the lane coordinates the numpy reference reads.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

import numpy as np

from safelane.core.snapshot import DRIVER_FIELDS, RoadSnapshot
from safelane.safety.compiled import axis_aligned, evaluate_compiled, evaluate_snapshot
from safelane.safety.model import RELEVANCE_RANGE, Dynamics, Formula, Mode, RoadState, SafetyResult, evaluate

Engine = Literal["compiled", "numpy"]
ENGINES: tuple[Engine, ...] = ("compiled", "numpy")


@runtime_checkable
class RuleFamily(Protocol):
    """A kind of safety rule the shield can apply (module docstring)."""

    mode: str
    """The ``shield.mode`` that selects it."""

    def evaluate(self, snap: RoadSnapshot, dyn: Dynamics, ego_leave_time: float) -> SafetyResult:
        """The verdict on the 5 meta-actions in the state of ``snap`` (``ego_leave_time`` [s]: how long the ego
        still overlaps its lane when it changes lane now)."""
        ...


@dataclass(frozen=True)
class OneDecisionFamily:
    """The ``nominal`` or ``robust`` rule: an action is safe when, after one decision under the others' worst
    case, a fallback keeps every gap above the margin (docs/safety.md). ``engine``: ``"compiled"`` (microseconds;
    the state built inside the kernel on an axis-aligned road) or ``"numpy"`` (the reference, which also reports
    the deciding conflicts); the same masks and gaps either way. ``formula``: nominal's ``"kinematic"`` or
    ``"paper"`` (eq. 12, the numpy reference)."""

    mode: Mode
    engine: Engine = "compiled"
    formula: Formula = "kinematic"

    def evaluate(self, snap: RoadSnapshot, dyn: Dynamics, ego_leave_time: float) -> SafetyResult:
        """The rule's verdict in the state of ``snap`` (:class:`RuleFamily`)."""
        if self.engine == "compiled" and (self.mode, self.formula) != ("nominal", "paper") and axis_aligned(snap):
            # The fast path: the RoadState is built inside the kernel (identical to road_state's).
            direction = snap.lane_direction
            lane_heading = math.atan2(direction[1], direction[0])
            return evaluate_snapshot(snap, dyn, self.mode, lane_heading=lane_heading, ego_leave_time=ego_leave_time)
        evaluator = evaluate_compiled if self.engine == "compiled" else evaluate
        state = road_state(snap, dyn.rule.ego_speed_magnitude)
        return evaluator(state, dataclasses.replace(dyn, ego_leave_time=ego_leave_time), self.mode, self.formula)


def family_for(mode: str, engine: Engine = "compiled", formula: Formula = "kinematic") -> RuleFamily:
    """The rule family of ``shield.mode`` ``mode``; an unknown mode is a one-line error."""
    if mode not in ("nominal", "robust"):
        raise ValueError(f"shield.mode: got {mode!r}; allowed: 'nominal', 'robust'")
    if engine not in ENGINES:
        raise ValueError(f"shield.engine: got {engine!r}; allowed: 'compiled', 'numpy'")
    if formula not in ("kinematic", "paper"):
        raise ValueError(f"shield.formula: got {formula!r}; allowed: 'kinematic', 'paper'")
    return OneDecisionFamily(mode, engine, formula)  # type: ignore[arg-type]


def _relevant(x: np.ndarray, ego_x: float) -> np.ndarray:
    """Which bodies at ``x`` [m] along the road the rule considers: within RELEVANCE_RANGE of the ego."""
    return (np.abs(x - ego_x) < RELEVANCE_RANGE) & np.isfinite(x)


def road_state_bodies(snap: RoadSnapshot) -> np.ndarray:
    """The snapshot indices of the bodies :func:`road_state` keeps, in its order (its arrays' rows)."""
    others = snap.others(vehicles_only=False)
    if not others.size:
        return others
    x = (snap.position[others] - snap.lane_origin) @ snap.lane_direction
    ego_x = float((snap.position[snap.ego] - snap.lane_origin) @ snap.lane_direction)
    return others[_relevant(x, ego_x)]


def road_state(snap: RoadSnapshot, ego_speed_magnitude: bool = True) -> RoadState:
    """The scene around the ego in lane coordinates (metres, m/s) for the safety model.

    ``ego_speed_magnitude`` (the rule's option): the ego's speed is its speed controller's
    (highway-env's ``vehicle.speed``: what MDPVehicle's set-points and its P-controller act on, exact
    for the model's ego trajectories, and along its path an upper bound on its progress along the road);
    false: the component along the road, which the heading of a lane change lowers (the grid's
    cells 573, 708 and 861: the rule then predicted a shorter stop, by up to 6.7 m, and picked a lower
    SLOWER set-point than highway-env's).

    Only bodies within :data:`safelane.safety.model.RELEVANCE_RANGE` [m] of the ego along the road are
    included — the ones :func:`safelane.safety.model.evaluate` considers.
    """
    e = snap.ego
    start, direction, lateral = snap.lane_origin, snap.lane_direction, snap.lane_lateral
    lane_heading = math.atan2(direction[1], direction[0])
    others = snap.others(vehicles_only=False)
    n = others.size
    pos = snap.position[others] - start
    ego_rel = snap.position[e] - start
    ego_x = float(ego_rel @ direction)
    x_all = pos @ direction if n else np.zeros(0)
    near = np.flatnonzero(_relevant(x_all, ego_x))
    nearby = others[near]
    heading = snap.heading[nearby] - lane_heading
    speed = snap.speed[nearby]
    ego_heading = float(snap.heading[e]) - lane_heading
    return RoadState(
        ego_x=ego_x,
        ego_y=float(ego_rel @ lateral),
        ego_speed=float(snap.speed[e]) if ego_speed_magnitude else float(snap.speed[e] * math.cos(ego_heading)),
        ego_lane=int(snap.lane[e]),
        ego_target_lane=int(snap.target_lane[e]),
        ego_target_speed=snap.ego_target_speed,
        ego_speed_index=snap.ego_speed_index,
        ego_length=float(snap.length[e]),
        ego_heading=ego_heading,
        x=x_all[near],
        y=(pos @ lateral)[near] if n else np.zeros(0),
        vx=speed * np.cos(heading),
        vy=speed * np.sin(heading),
        heading=np.arctan2(np.sin(heading), np.cos(heading)),
        length=snap.length[nearby],
        crashed=snap.crashed[nearby],
        target_speed=snap.target_speed[nearby],
        speed_limit=snap.speed_limit,
        **{name: getattr(snap, name)[nearby] for name in DRIVER_FIELDS},
    )
