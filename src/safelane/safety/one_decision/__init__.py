"""The one-decision rule: the ``nominal`` and ``robust`` shield modes (paper Section IV; derivation:
``docs/safety.md``).

An action is **safe** when, after executing it for one decision under the others' worst case, a fallback (hold
the speed target ``k`` decisions, then SLOWER to a standstill) keeps every gap above the margin; each state is
judged alone. The **reference** is :mod:`~safelane.safety.one_decision.reference` (numpy, readable, reports the
deciding conflicts), with its parts :mod:`~safelane.safety.one_decision.cut_ins` (who may enter the ego's lanes)
and :mod:`~safelane.safety.one_decision.forecast` (the nominal forecast that ranks the least-bad choice). The
**compiled engine** is :mod:`~safelane.safety.one_decision.compiled` (numba, the same bits; its kernel in
:mod:`~safelane.safety.one_decision.compiled_rule` and :mod:`~safelane.safety.one_decision.compiled_parts`).
:mod:`~safelane.safety.one_decision.family` is the rule as the shield asks it.
"""
