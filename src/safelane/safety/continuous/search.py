"""The verified actions nearest an agent's: projection, the safe acceleration interval, the verified steerings.

Actions are normalised to ``[-1, 1]²`` (acceleration, steering) and compared by Euclidean distance there.

**The structure the search exploits**: at a fixed steering the verified accelerations form one interval
``[low, high]``. It holds where the lanes a plan occupies do not change across the accelerations (every car's gap
is then monotone in the acceleration: the ego is further along the road at every frame, ahead of the cars behind
and closer to those ahead) and the interval is at least :data:`ACCELERATION_GRID`'s spacing wide; a faster ego also
turns further under the same steering, which can change the lanes. Under it the search is exact in acceleration,
to :data:`ACCELERATION_TOLERANCE`, at each steering it examines: the agent's, the fail-safe's lane-keeping steering
and :data:`STEERING_GRID` (in order of distance from the agent's, stopping once a steering cannot beat the best
found); at each, :data:`ACCELERATION_GRID` from the agent's acceleration outward up to the first verified point,
then bisection between it and the last unverified one (:meth:`ActionSearch.nearest`).
``tests/test_continuous_shield.py`` checks it against a dense grid on recorded states.

Pure maths: no simulator.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from safelane.safety.continuous.plans import ControlPlan

ACCELERATION_GRID = np.linspace(-1.0, 1.0, 9, dtype=np.float32)
"""The normalised accelerations tried at each steering to find the verified interval."""
GRID_SPACING = float(ACCELERATION_GRID[1] - ACCELERATION_GRID[0])
STEERING_GRID = np.linspace(-1.0, 1.0, 9, dtype=np.float32)
"""The normalised steerings the projection examines besides the agent's and the lane-keeping one."""
ACCELERATION_TOLERANCE = 2.0**-10
"""[normalised] The bisection stops when the verified end is known to within this."""

Verifier = Callable[[np.ndarray], "ControlPlan | None"]
"""Verifies an action (2,) float32: its plan, or None."""


@dataclass
class ActionSearch:
    """Memoised verification of actions in one state (``verify``:
    :func:`~safelane.safety.continuous.plans.verify_action` bound to the state); ``evaluated`` counts the actions
    verified."""

    verify: Verifier
    evaluated: int = 0
    _seen: dict[bytes, ControlPlan | None] = field(default_factory=dict)

    def plan(self, acceleration: float, steering: float) -> ControlPlan | None:
        """The verified plan of the action (``acceleration``, ``steering``), normalised, or None."""
        action = np.array([acceleration, steering], dtype=np.float32)
        key = action.tobytes()
        if key not in self._seen:
            self.evaluated += 1
            self._seen[key] = self.verify(action)
        return self._seen[key]

    def interval(self, steering: float) -> tuple[float, float, ControlPlan | None]:
        """(low, high, plan) the verified accelerations at ``steering`` (normalised; nan, nan, None: none found on
        :data:`ACCELERATION_GRID`), both ends found by bisection; ``plan``: the low end's."""
        grid = [float(a) for a in ACCELERATION_GRID]
        inside = [a for a in grid if self.plan(a, steering) is not None]
        if not inside:
            return np.nan, np.nan, None
        low_in, high_in = min(inside), max(inside)
        low, plan = self._bisect(steering, max((a for a in grid if a < low_in), default=low_in), low_in)
        high, _ = self._bisect(steering, min((a for a in grid if a > high_in), default=high_in), high_in)
        return low, high, plan

    def nearest(self, steering: float, wanted: float, radius: float = np.inf) -> tuple[float, ControlPlan | None]:
        """(acceleration, plan) the verified acceleration at ``steering`` nearest ``wanted`` (normalised; nan, None:
        none found). ``wanted`` itself, else the grid's accelerations from the nearest, up to the first verified
        one, then bisection between it and the unverified point before it: under the interval structure the end
        found is the nearest. ``radius``: only an acceleration within this of ``wanted`` is of use (the grid is
        tried there and one spacing beyond, which still meets an interval a spacing wide that reaches within
        it)."""
        plan = self.plan(wanted, steering)
        if plan is not None:
            return wanted, plan
        grid = sorted((float(a) for a in ACCELERATION_GRID if abs(a - wanted) <= radius + GRID_SPACING),
                      key=lambda a: (abs(a - wanted), a))  # fmt: skip
        for point in grid:
            if self.plan(point, steering) is not None:
                toward = [a for a in grid if abs(a - wanted) < abs(point - wanted) and (a < point) == (wanted < point)]
                outside = min(toward, key=lambda a: abs(a - point)) if toward else wanted
                return self._bisect(steering, outside, point)
        return np.nan, None

    def _bisect(self, steering: float, outside: float, inside: float) -> tuple[float, ControlPlan | None]:
        """The verified end between ``outside`` (not verified, or the range's end) and ``inside`` (verified)."""
        if outside == inside or self.plan(outside, steering) is not None:
            return outside, self.plan(outside, steering)
        while abs(inside - outside) > ACCELERATION_TOLERANCE:
            middle = float(np.float32(0.5 * (inside + outside)))
            if middle in (inside, outside):
                break
            if self.plan(middle, steering) is not None:
                inside = middle
            else:
                outside = middle
        return inside, self.plan(inside, steering)


@dataclass(frozen=True)
class Projection:
    """The verified action nearest the agent's (``action``: None when none was found), its plan, its distance
    [normalised] from the agent's and the actions verified to find it."""

    action: np.ndarray | None
    plan: ControlPlan | None
    distance: float
    evaluated: int


def project(search: ActionSearch, wanted: np.ndarray, lane_keeping_steering: float,
            candidates: tuple[tuple[np.ndarray, ControlPlan], ...] = ()) -> Projection:  # fmt: skip
    """The verified action nearest ``wanted`` (2,) (module docstring); ``candidates``: actions already known to be
    verified, with their plans (the kept plan's next step)."""
    wanted = np.asarray(wanted, dtype=np.float32)
    best: tuple[float, np.ndarray, ControlPlan] | None = None
    for action, plan in candidates:
        distance = float(np.hypot(*(np.asarray(action, dtype=np.float64) - wanted)))
        if best is None or distance < best[0]:
            best = (distance, np.asarray(action, dtype=np.float32), plan)
    steerings = sorted({float(wanted[1]), float(np.float32(lane_keeping_steering)), *map(float, STEERING_GRID)},
                       key=lambda s: (abs(s - float(wanted[1])), s))  # fmt: skip
    for steering in steerings:
        if best is not None and abs(steering - float(wanted[1])) >= best[0]:
            break  # no acceleration at this steering or beyond can be nearer
        radius = np.sqrt(max(best[0] ** 2 - (steering - float(wanted[1])) ** 2, 0.0)) if best else np.inf
        acceleration, plan = search.nearest(steering, float(wanted[0]), radius)
        if plan is None:
            continue
        action = np.array([acceleration, steering], dtype=np.float32)
        distance = float(np.hypot(*(action.astype(np.float64) - wanted)))
        if best is None or distance < best[0]:
            best = (distance, action, plan)
    if best is None:
        return Projection(None, None, np.inf, search.evaluated)
    return Projection(best[1], best[2], best[0], search.evaluated)
