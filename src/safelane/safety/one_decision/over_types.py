"""The one-decision rule judged against several readings of the other cars' drivers at once: the robust rule over a
mixture of driver types whose assignment to the cars is unknown (:mod:`safelane.safety.driver_sets`).

An action is safe when **one** fallback keeps every gap above the margin whatever each car's type is. Each conflict of
the rule is one car's (the rule's worst gaps per action and fallback are minima over conflicts,
:func:`~safelane.safety.one_decision.reference.rule_gaps`), so the worst case over every assignment of types to cars,
mixed ones included, is the minimum over the readings of each reading's gaps, per action and fallback, taken *before*
the fallback is chosen. Judging each reading alone and intersecting the safe sets would let each assignment with all
cars of one type pick a fallback of its own: a timid car allowed to cut in ahead (the ego must brake now) and an
aggressive one closing in behind (the ego must keep its speed) can each be handled in a reading of their own, and
not together. With one reading this is :func:`~safelane.safety.one_decision.reference.evaluate` to the bit. Either
engine gives the gaps (the compiled kernel's :func:`~safelane.safety.one_decision.compiled.compiled_gaps`, the same bits
as the numpy reference's); the verdict is the reference's, in Python; the deciding conflicts are not reported
(``conflicts`` None).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from safelane.safety.one_decision.compiled import compiled_gaps
from safelane.safety.one_decision.reference import RuleGaps, rule_gaps, rule_verdict
from safelane.safety.world import Dynamics, Engine, RoadState, SafetyResult


def combined_gaps(gaps: Sequence[RuleGaps]) -> RuleGaps:
    """The gaps [m] of every reading at once: per action and fallback the least of each kind, and an action nominally
    sound only where it is in every reading (the readings share the ego, so its available actions)."""
    first = gaps[0]

    def least(name: str) -> np.ndarray:
        return np.minimum.reduce([getattr(g, name) for g in gaps])

    return dataclasses.replace(
        first,
        joint=least("joint"),
        ahead=least("ahead"),
        nominal_joint=least("nominal_joint"),
        nominal_ahead=least("nominal_ahead"),
        nominal_ok=np.logical_and.reduce([g.nominal_ok for g in gaps]),
        conflicts=None,
    )


def evaluate_readings(
    readings: Sequence[RoadState],
    likely: RoadState,
    dyn: Dynamics,
    engine: Engine = "compiled",
    nominal_leaders: bool = False,
) -> SafetyResult:
    """The robust rule's verdict on the scene read as each of ``readings`` at once (the same scene, the others'
    driver arrays differing; module docstring): safe, the straight fallback's mask or the least-bad action, whose
    forecast reads ``likely`` (the others as they will most likely drive). ``dyn`` carries the ego's leave time.
    ``engine``: which computes each reading's gaps (the same bits). ``nominal_leaders``: the leaders bounded as
    nominal mode bounds them (the straight fallback's pass)."""
    if not readings:
        raise ValueError("evaluate_readings: no reading")
    if engine == "compiled":
        gaps = [compiled_gaps(state, dyn, nominal_leaders) for state in readings]
    else:
        gaps = [rule_gaps(state, dyn, "robust", nominal_leaders) for state in readings]
    return rule_verdict(
        combined_gaps(gaps), likely, dyn, "robust",
        lambda: evaluate_readings(readings, likely, dyn, engine, nominal_leaders=True),
    )  # fmt: skip


__all__ = ["combined_gaps", "evaluate_readings"]
