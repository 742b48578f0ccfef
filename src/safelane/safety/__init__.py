"""The safety side: the rules that mask unsafe meta-actions and the gymnasium shield that applies them.

Shared by every rule: :mod:`~safelane.safety.world` (the world's constants, the road state, the verdict),
:mod:`~safelane.safety.road` (the snapshot in lane coordinates), :mod:`~safelane.safety.ego` (the ego's exact
trajectories), :mod:`~safelane.safety.others` (the other drivers' bounds), :mod:`~safelane.safety.rule` (the rule's
options) and :mod:`~safelane.safety.family` (what the shield asks of a rule). The rules:
:mod:`~safelane.safety.one_decision` (``nominal``, ``robust``) and :mod:`~safelane.safety.committed`
(``committed``). The shield: :mod:`~safelane.safety.shield`.
"""
