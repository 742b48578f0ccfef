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
  under the action's best fallback is its ``min_gap`` (:class:`~safelane.safety.world.Conflict`); None where the
  engine does not report them (the compiled kernels return masks and gaps only);
* ``info()``: the keys the shield adds to a step's ``info``.

Between decisions the shield calls :meth:`RuleFamily.reset` (a new episode) and :meth:`RuleFamily.commit` (the
action executed): no-ops for a rule without memory.

The families, one per ``shield.mode`` (:func:`family_for`): ``nominal`` (the paper's Q-masking) and ``robust``
(robust Q-masking), :class:`~safelane.safety.one_decision.family.OneDecisionFamily` over the one-decision rule
(:mod:`safelane.safety.one_decision`); ``committed``, :class:`~safelane.safety.committed.family.CommittedFamily`,
a plan kept from one decision to the next (:mod:`safelane.safety.committed`).
"""

from __future__ import annotations

from typing import Protocol, cast, runtime_checkable

from safelane.core.snapshot import RoadSnapshot
from safelane.safety.committed.family import CommittedFamily
from safelane.safety.one_decision.family import OneDecisionFamily
from safelane.safety.world import SHIELD_MODES, Dynamics, Engine, Formula, Mode, SafetyResult, check_choices


@runtime_checkable
class RuleFamily(Protocol):
    """A kind of safety rule the shield can apply (module docstring)."""

    mode: str
    """The ``shield.mode`` that selects it."""
    engine: Engine
    """The numpy reference or the compiled kernels (the same bits)."""

    def evaluate(self, snap: RoadSnapshot, dyn: Dynamics, ego_leave_time: float) -> SafetyResult:
        """The verdict on the 5 meta-actions in the state of ``snap`` (``ego_leave_time`` [s]: how long the ego
        still overlaps its lane when it changes lane now)."""
        ...

    def reset(self) -> None:
        """Forget the episode (its first state is judged next)."""
        ...

    def commit(self, action: int) -> None:
        """Record that ``action`` was executed in the state last evaluated."""
        ...


def family_for(mode: str, engine: Engine = "compiled", formula: Formula = "kinematic") -> RuleFamily:
    """A new rule family of ``shield.mode`` ``mode`` (``formula``: the nominal mode's); a bad choice is a one-line
    error."""
    check_choices(mode, engine, formula, modes=SHIELD_MODES)
    if mode == "committed":
        return CommittedFamily(engine)
    return OneDecisionFamily(cast(Mode, mode), engine, formula)
