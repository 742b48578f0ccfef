"""The committed rule (experimental): the ``committed`` shield mode, a verified fail-safe plan kept from one
decision to the next (design and measurement: ``docs/research/committed-plans.md``; ``docs/safety.md`` §9).

A **plan** is the action, the set-point held ``k ∈ {0..3}`` decisions, then SLOWER to a standstill; an action is
**verified** when a plan starting with it keeps the margin to every car's **reachable set** (drawn from the
observable state, nesting in time) at every frame of the horizon. In the lane the ego is in only the cars ahead
count; in a lane it enters, the cars there count ahead and behind; a follower or a car cutting in is at fault.
The **reference** is numpy: :mod:`~safelane.safety.committed.plans` (plans and their gaps) over
:mod:`~safelane.safety.committed.sets` (the reachable sets); the **compiled engine** is
:mod:`~safelane.safety.committed.compiled` (numba, the same bits). Both read
:mod:`~safelane.safety.committed.plan_family` (onsets, the actions verified, the lanes held) and neither imports
the other: :mod:`~safelane.safety.committed.family` (the memory between decisions) picks the engine.
"""
