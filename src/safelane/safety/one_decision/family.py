"""The one-decision rule as a :class:`~safelane.safety.family.RuleFamily`: the ``nominal`` and ``robust`` modes."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from safelane.core.snapshot import RoadSnapshot
from safelane.safety.one_decision.compiled import axis_aligned, evaluate_compiled, evaluate_snapshot
from safelane.safety.one_decision.reference import evaluate
from safelane.safety.road import road_state
from safelane.safety.world import Dynamics, Engine, Formula, Mode, SafetyResult, check_choices


@dataclass(frozen=True)
class OneDecisionFamily:
    """The ``nominal`` or ``robust`` rule: an action is safe when, after one decision under the others' worst
    case, a fallback keeps every gap above the margin (docs/safety.md). ``engine``: ``"compiled"`` (microseconds;
    the state built inside the kernel on an axis-aligned road) or ``"numpy"`` (the reference, which also reports
    the deciding conflicts); the same masks and gaps either way. ``formula``: nominal's ``"kinematic"`` or
    ``"paper"`` (eq. 12, the numpy reference). No memory: :meth:`reset` and :meth:`commit` do nothing."""

    mode: Mode
    engine: Engine = "compiled"
    formula: Formula = "kinematic"

    def __post_init__(self) -> None:
        check_choices(self.mode, self.engine, self.formula)

    def evaluate(self, snap: RoadSnapshot, dyn: Dynamics, ego_leave_time: float) -> SafetyResult:
        """The rule's verdict in the state of ``snap`` (:class:`~safelane.safety.family.RuleFamily`)."""
        if self.engine == "compiled" and (self.mode, self.formula) != ("nominal", "paper") and axis_aligned(snap):
            # The fast path: the RoadState is built inside the kernel (identical to road_state's).
            return evaluate_snapshot(
                snap, dyn, self.mode, lane_heading=snap.lane_heading, ego_leave_time=ego_leave_time
            )
        evaluator = evaluate_compiled if self.engine == "compiled" else evaluate
        state = road_state(snap, dyn.rule.ego_speed_magnitude)
        return evaluator(state, dataclasses.replace(dyn, ego_leave_time=ego_leave_time), self.mode, self.formula)

    def reset(self) -> None:
        """Nothing to forget: the rule judges each state alone."""

    def commit(self, action: int) -> None:
        """Nothing to keep: the rule judges each state alone."""
