"""The committed rule as a :class:`~safelane.safety.family.RuleFamily`: memory between decisions.

:class:`CommittedFamily` allows the actions with a verified plan, ordered by courtesy to the cars behind
(:func:`courteous`: those the one-decision robust rule also calls safe, where there are any); with none it allows
only the kept plan's next step (``plan_forced``); with no plan at all (uncertified) the one-decision robust rule's mask
(:class:`~safelane.safety.one_decision.family.OneDecisionFamily`, ``engine``). A decision at which the plan kept
(verified) at the last decision no longer verifies is a **lapse**; it names the cars the kept plan fails on and
which of them left the sets drawn for them (cars by their index in the road snapshot, one car's for a whole
episode). The engine is chosen here: the numpy reference (:mod:`safelane.safety.committed.plans`,
:mod:`safelane.safety.committed.sets`) or the compiled kernels (:mod:`safelane.safety.committed.compiled`), the
same bits.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from safelane.core.snapshot import RoadSnapshot
from safelane.core.spaces import IDLE, N_ACTIONS
from safelane.safety.committed.compiled import (
    CarArrays,
    car_arrays,
    car_gaps_compiled,
    car_sets_compiled,
    carry_compiled,
    follower_bounds_compiled,
    prepare,
    verify_plans_compiled,
)
from safelane.safety.committed.plan_family import held_lanes
from safelane.safety.committed.plans import Plan, car_gaps, follower_bound, lane_bit, plan_of, verify_plans
from safelane.safety.committed.sets import (
    ESCAPE_TOLERANCE,
    CarSets,
    car_sets,
    escaped_cars,
    occupied_lanes,
    rolling_back,
    rows_in,
)
from safelane.safety.ego import available_actions
from safelane.safety.one_decision.family import OneDecisionFamily
from safelane.safety.one_decision.reference import evaluate as evaluate_one_decision
from safelane.safety.road import whole_road_state
from safelane.safety.world import Dynamics, Engine, RoadState, SafetyResult, check_choices


@dataclass(frozen=True)
class CommittedResult(SafetyResult):
    """:class:`SafetyResult` of the committed family: ``safe`` lists the verified actions, ``fallback`` is set when
    none is; ``plan_forced``: the kept plan's next step drives (nothing verified); ``lapse``: the plan kept, verified,
    at the last decision no longer verifies (a plan driven on after a lapse is not verified again); ``lapse_cars``: at a
    lapse, the cars the kept plan fails on (their own worst gap to its tail below the margin; :attr:`lapse_escaped`
    those of them outside their sets). Cars are named by their index in the road snapshot (the simulator's order of its
    vehicles, which highway-env's road and the fast simulator keep for the whole episode: a car keeps its index).
    ``escaped``: the cars outside the sets drawn for them, anywhere on the road, ``rolled_back`` those of them moving
    backwards (outside IDM, :func:`~safelane.safety.committed.sets.rolling_back`), ``unbraked_followers`` those ahead of
    the follower bound the kept plan drew for them (the follower law is an assumption, not IDM's: a follower far behind
    does not brake at its limit because the ego plans to), ``checked`` how many cars were checked against a set drawn at
    the last decision; ``entered``: those that entered a lane the ego holds since the last decision; ``ego_crashed``:
    the ego has crashed (its motion after an impact is no plan's); ``certified``: some plan is verified or kept;
    ``plans``: the verified plan of each action (None: none); ``courtesy_waived``: some action is verified but none
    is safe by the one-decision robust rule (:func:`courteous`)."""

    plan_forced: bool = False
    lapse: bool = False
    lapse_cars: tuple[int, ...] = ()
    escaped: tuple[int, ...] = ()
    rolled_back: tuple[int, ...] = ()
    unbraked_followers: tuple[int, ...] = ()
    checked: int = 0
    entered: tuple[int, ...] = ()
    ego_crashed: bool = False
    certified: bool = False
    plans: tuple[Plan | None, ...] = ()
    courtesy_waived: bool = False

    @property
    def lapse_escaped(self) -> tuple[int, ...]:
        """The cars the lapse's kept plan fails on that are outside the sets drawn for them."""
        return tuple(v for v in self.lapse_cars if v in self.escaped)

    @property
    def lapse_in_model(self) -> bool:
        """A lapse not traced to the model's exits: some car the kept plan fails on is inside its set and did not enter
        a lane the ego holds since the last decision (such a car made the gap it
        is responsible for), or no car is named. With every car inside its set the sets nest and the plan verifies
        again, so this is a gap in the construction. A car outside its set that the plan does not fail on (far
        ahead, in another lane) traces nothing. A lapse in a state where the ego has crashed is the impact's: the
        simulator pushes the bodies apart and brakes a crashed car at its speed per second, so the ego is no longer
        where its plan put it (struck from behind, pushed toward its leader)."""
        traced = {*self.escaped, *self.entered}
        in_model = not self.lapse_cars or any(v not in traced for v in self.lapse_cars)
        return self.lapse and not self.ego_crashed and in_model

    def info(self) -> dict[str, Any]:
        """The keys the shield adds to a step's ``info``: :class:`SafetyResult`'s, then ``plan_forced``, ``lapse``,
        ``lapse_in_model``, ``lapse_cars``, ``lapse_escaped_cars``, ``escaped_cars``, ``rolled_back``,
        ``unbraked_followers``, ``entered_cars``, ``certified`` and ``courtesy_waived`` (cars by snapshot index)."""
        return {
            **super().info(), "plan_forced": self.plan_forced, "lapse": self.lapse,
            "lapse_in_model": self.lapse_in_model, "lapse_cars": self.lapse_cars,
            "lapse_escaped_cars": self.lapse_escaped, "escaped_cars": self.escaped, "rolled_back": self.rolled_back,
            "unbraked_followers": self.unbraked_followers, "entered_cars": self.entered, "certified": self.certified,
            "courtesy_waived": self.courtesy_waived,
        }  # fmt: skip


def courteous(verified: np.ndarray, one_decision: SafetyResult) -> tuple[np.ndarray, bool]:
    """(mask, waived) the verified actions (``verified``, (5,) bool, some True) courtesy allows, by the one-decision
    robust rule's verdict in the same state: those it calls safe (every follower, under its own driver law, and every
    car that may turn in keeps its room), or every verified one where none is (``waived``). It orders the verified
    actions, never adds one: the promise stays the plans'."""
    preferred = verified & one_decision.safe
    if preferred.any():
        return preferred, False
    return verified.copy(), True


@dataclass
class CommittedFamily:
    """The ``committed`` shield mode (experimental, module docstring): a :class:`~safelane.safety.family.RuleFamily`
    with memory. :meth:`evaluate` judges a state without changing the memory (it may be called again on the same
    state); :meth:`commit` records the executed action; :meth:`reset` forgets the episode."""

    engine: Engine = "compiled"
    mode: str = "committed"
    kept: Plan | None = None
    kept_verified: bool = False
    carried: CarSets | None = None
    carried_ahead: np.ndarray | None = None
    followers: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)
    _pending: tuple[CommittedResult, RoadState, Dynamics, CarSets, np.ndarray] | None = field(default=None, repr=False)
    _dynamics: tuple[Dynamics, str, Dynamics] | None = field(default=None, repr=False)
    """(dyn, leave time as ``float.hex``, dyn with that leave time): the last Dynamics evaluated, kept while the caller
    passes the same one and the same leave time, so that what the kernels read of it is built once."""

    def __post_init__(self) -> None:
        check_choices(engine=self.engine)

    def reset(self) -> None:
        """Forget the kept plan and the carried sets (a new episode)."""
        self.kept, self.kept_verified, self.carried, self.followers, self._pending = None, False, None, {}, None
        self.carried_ahead = None

    def evaluate(self, snap: RoadSnapshot, dyn: Dynamics, ego_leave_time: float) -> CommittedResult:
        """The verdict in the state of ``snap`` (see the class docstring)."""
        # The one-decision rule is given ``dyn`` as passed (it takes the leave time apart): the caller's one Dynamics
        # for an episode, whose kernel constants it caches.
        one_decision = functools.partial(OneDecisionFamily("robust", self.engine).evaluate, snap, dyn, ego_leave_time)
        state, vehicle = whole_road_state(snap, dyn.rule.ego_speed_magnitude)
        return self.evaluate_state(
            state,
            vehicle,
            self._with_leave_time(dyn, ego_leave_time),
            one_decision,
            ego_crashed=bool(snap.crashed[snap.ego]),
        )

    def _with_leave_time(self, dyn: Dynamics, ego_leave_time: float) -> Dynamics:
        """``dyn`` with ``ego_leave_time``: the same object as at the last decision when both are the same (the bits:
        ``float.hex`` tells −0.0 from 0.0)."""
        leave = float(ego_leave_time).hex()
        hit = self._dynamics
        if hit is None or hit[0] is not dyn or hit[1] != leave:
            hit = self._dynamics = (dyn, leave, dataclasses.replace(dyn, ego_leave_time=ego_leave_time))
        return hit[2]

    def evaluate_state(
        self,
        state: RoadState,
        vehicle: np.ndarray,
        dyn: Dynamics,
        one_decision: Callable[[], SafetyResult] | None = None,
        ego_crashed: bool = False,
    ) -> CommittedResult:
        """:meth:`evaluate` on a :class:`RoadState` (every car, ``vehicle``: their identities, kept from one decision
        to the next) with ``dyn.ego_leave_time`` set; ``one_decision``: the one-decision robust rule's verdict in this
        state (default: the numpy reference's), which orders the verified actions (:func:`courteous`) and drives an
        uncertified state; ``ego_crashed``: the ego has crashed (a :class:`RoadState` holds
        the other cars' flags only)."""
        compiled = self.engine == "compiled"
        cars: CarArrays | None = None
        if compiled:  # the per-car quantities once, for the sets and the gaps
            prep = prepare(state, dyn)
            sets, cars = car_sets_compiled(state, dyn, vehicle, prep), car_arrays(state, dyn, prep)
        else:
            sets = car_sets(state, dyn, vehicle)
        escaped = np.zeros(state.n, dtype=bool)
        unbraked = np.zeros(state.n, dtype=bool)
        rolled: np.ndarray | None = None
        checked = 0
        entered = np.zeros(state.n, dtype=bool)
        if self.carried is not None:
            kept_held = self.kept.held if self.kept is not None else ()
            entered = entered_held_lanes(state, self.carried, sets, vehicle, self.carried_ahead, kept_held)
            occupied = occupied_lanes(state, dyn)
            unbraked = followers_escaped(self.followers, state, dyn, vehicle, occupied)
            sets, escaped, rolled, checked = carry_sets(state, dyn, sets, self.carried, vehicle, unbraked, occupied,
                                                        compiled)  # fmt: skip
        if compiled:
            worst, ego_x, _, set_points = verify_plans_compiled(state, dyn, sets, cars)
        else:
            worst, ego_x, _, set_points = verify_plans(state, dyn, sets)
        verified = worst >= dyn.margin  # (5, holds)
        available = available_actions(state, dyn)
        best = np.argmax(np.where(verified, worst, -np.inf), axis=1)
        plans: list[Plan | None] = [
            plan_of(state, dyn, set_points[a, best[a]], a, int(best[a])) if verified[a].any() else None
            for a in range(N_ACTIONS)
        ]
        lapse = forced = False
        failed = np.zeros(state.n, dtype=bool)
        if self.kept is not None:
            tail = self.kept.shifted(dyn)
            a, k = tail.action, tail.hold
            if not available[a]:  # SLOWER at the lowest set-point holds 0 m/s, as IDLE does
                a, k = IDLE, 0
            rows = {int(v): r for r, v in enumerate(vehicle)}
            f = dyn.frames_per_decision
            followers = {
                rows[v]: (lane, np.concatenate([high[f:], np.full(f, np.inf)]))
                for v, (lane, high) in self.followers.items()
                if v in rows and not escaped[rows[v]]
            }
            args = (state, dyn, sets, ego_x[a, k : k + 1], np.array([tail.onset]), list(tail.occupied),
                    tail.frames, followers, tail.held)  # fmt: skip
            gaps = (car_gaps_compiled(*args, cars=cars) if compiled else car_gaps(*args))[:, 0]
            gap = gaps.min() if gaps.size else np.inf
            # A lapse: the plan verified at the last decision no longer is (a plan kept on after one stays unverified);
            # the cars it fails on are those whose own gap to the tail is below the margin.
            lapse = self.kept_verified and not gap >= dyn.margin
            if lapse:
                failed = ~(gaps >= dyn.margin)
            step = self.kept.next_step() if available[self.kept.next_step()] else IDLE
            if gap >= dyn.margin and plans[step] is None:  # the kept plan itself still verifies: its step is allowed
                plans[step] = dataclasses.replace(tail, action=a, hold=k)
            forced = not any(p is not None for p in plans)
            if forced:
                step = self.kept.next_step() if available[self.kept.next_step()] else IDLE
        safe = np.array([p is not None for p in plans])
        mask = safe.copy()
        if forced:
            mask[step] = True
        best_gap = np.where(available, worst.max(axis=1), -np.inf)
        one_decision = one_decision or (lambda: evaluate_one_decision(state, dyn, "robust"))
        courtesy_waived = False
        if safe.any():
            mask, courtesy_waived = courteous(safe, one_decision())
        elif not mask.any():  # no plan verified, none kept: uncertified, the one-decision robust rule drives
            mask = one_decision().mask.copy()
        result = CommittedResult(
            mask, safe, available, not bool(safe.any()), best_gap, None,
            plan_forced=forced, lapse=lapse, lapse_cars=tuple(int(v) for v in vehicle[failed]),
            escaped=tuple(int(v) for v in vehicle[escaped]),
            rolled_back=tuple(int(v) for v in vehicle[rolling_back(state, escaped) if rolled is None else rolled]),
            checked=checked,
            unbraked_followers=tuple(int(v) for v in vehicle[unbraked]),
            entered=tuple(int(v) for v in vehicle[entered]),
            ego_crashed=ego_crashed, certified=bool(safe.any()) or self.kept is not None, plans=tuple(plans),
            courtesy_waived=courtesy_waived,
        )  # fmt: skip
        self._pending = (result, state, dyn, sets, vehicle)
        return result

    def commit(self, action: int) -> None:
        """Record that ``action`` was executed in the state last evaluated: its verified plan is kept; the kept
        plan's next step, forced, keeps the kept plan (shifted); any other action leaves no plan."""
        if self._pending is None:
            return
        result, state, dyn, sets, vehicle = self._pending
        plan = result.plans[action]
        self.kept_verified = plan is not None
        # The same plan goes on: the kept plan's tail, verified (its step) or forced.
        same_plan = plan is not None and self.kept is not None and plan.onset == self.kept.onset - dyn.decision_period
        if plan is None and self.kept is not None and result.plan_forced and result.mask[action]:
            plan = self.kept.shifted(dyn)
            same_plan = True
        self.kept = plan
        self.carried = sets
        # Which cars counted as ahead of the ego: the line the kept plan counts cars by.
        self.carried_ahead = state.x >= state.ego_x
        if plan is None:
            self.followers = {}
        else:  # the follower bounds of this plan, inside those carried for the same plan (a nested law)
            fresh = _followers_of(state, dyn, sets, vehicle, plan, self.engine)
            f = dyn.frames_per_decision
            for v, (lane, high) in self.followers.items() if same_plan else ():
                shifted = np.concatenate([high[f:], np.full(f, np.inf)])
                now = fresh.get(v)  # a car no longer following keeps the bound: it may come back
                fresh[v] = (lane, shifted if now is None or now[0] != lane else np.minimum(now[1], shifted))
            self.followers = fresh
        self._pending = None


def followers_escaped(
    followers: dict[int, tuple[int, np.ndarray]], state: RoadState, dyn: Dynamics, vehicle: np.ndarray,
    occupied: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """(cars,) the followers of the kept plan (``followers``: {snapshot index: (lanes, highest position [m] per
    frame)}, a car behind the ego in a lane it held, ``lanes`` the bitmask of those it followed in) still in one of
    those lanes and ahead of the bound their reaction to the plan allowed; ``occupied``: :func:`occupied_lanes` of
    ``state``."""
    out = np.zeros(state.n, dtype=bool)
    f = dyn.frames_per_decision
    for i, v in enumerate(vehicle):
        follower = followers.get(int(v))
        if follower is not None and occupied[i][lanes_of(follower[0], occupied.shape[1])].any() \
                and f < follower[1].size:  # fmt: skip
            out[i] = state.x[i] > follower[1][f] + ESCAPE_TOLERANCE
    return out


def carry_sets(
    state: RoadState, dyn: Dynamics, sets: CarSets, carried: CarSets, vehicle: np.ndarray, unbraked: np.ndarray,
    occupied: np.ndarray, compiled: bool,
) -> tuple[CarSets, np.ndarray, np.ndarray, int]:  # fmt: skip
    """The fresh ``sets`` against those ``carried`` from the last decision: (the sets intersected with the carried
    ones for the cars still inside them, escaped (``unbraked`` followers included), rolled back, the cars checked
    against a carried set); ``compiled``: in one kernel (the same bits as the numpy steps)."""
    if compiled:
        return carry_compiled(state, dyn, sets, carried, vehicle, unbraked, occupied)
    older = carried.shifted(dyn.frames_per_decision, dyn.decision_period)
    escaped = escaped_cars(state, dyn, older, vehicle) | unbraked
    checked = int(np.isin(vehicle, older.vehicle).sum())
    return sets.intersect(older, ~escaped), escaped, rolling_back(state, escaped, older, vehicle), checked


def entered_held_lanes(
    state: RoadState, older: CarSets, sets: CarSets, vehicle: np.ndarray, older_ahead: np.ndarray | None = None,
    kept_held: tuple[int, ...] = (),
) -> np.ndarray:  # fmt: skip
    """(cars,) the cars in (or moving into) a lane the ego holds now that were not at the last decision, and (with
    ``older_ahead``, each carried row's place then: ahead of the ego or not) those in it then but behind the ego and
    ahead of it now in the lane the ego was in (a car behind there did not count; one behind in a lane the ego was
    entering did): a car that overtook the ego beside it while it may turn in. Both cut in after the plan was
    drawn. The held lanes: the ego's lane and target lane now and those the kept plan held
    when verified (``kept_held``, the lane the ego was in first)."""
    rows = rows_in(older.vehicle, vehicle)
    ahead = state.x >= state.ego_x
    in_lane = held_lanes(state, kept_held)[0]
    out = np.zeros(state.n, dtype=bool)
    for lane in {state.ego_lane, state.ego_target_lane, *kept_held}:
        i = np.flatnonzero(sets.now[:, lane] & (rows >= 0))  # in the lane now, with a row then
        r = rows[i]
        passed = ~older_ahead[r] & ahead[i] if older_ahead is not None and lane == in_lane else False
        out[i] |= ~older.now[r, lane] | passed
    return out


def _followers_of(
    state: RoadState, dyn: Dynamics, sets: CarSets, vehicle: np.ndarray, plan: Plan, engine: Engine = "numpy"
) -> dict:
    """{snapshot index: (lane bitmask, highest position [m] per frame)} of the cars that follow the ego under ``plan``
    (:func:`plan_gaps`' follower law): the bound a lapse is traced against."""
    held = {state.ego_lane, state.ego_target_lane}
    lanes = [lane for lane, _ in plan.occupied if lane in held]
    out: dict[int, tuple[int, np.ndarray]] = {}
    if not lanes:
        return out
    t = dyn.times
    react = np.array([max(plan.onset + dyn.follower_reaction, 0.0)])
    own = state.lane_of(state.y, dyn.lanes_count, dyn.lane_width)
    behind = state.x < state.ego_x
    for lane in lanes:
        rows = np.flatnonzero(behind & (own == lane))
        if engine == "compiled":
            bounds = follower_bounds_compiled(state, rows, react, t)
        else:
            bounds = [follower_bound(state, int(i), react, t)[0] for i in rows]
        for i, bound in zip(rows, bounds, strict=True):
            out[int(vehicle[i])] = (lane_bit(lane), np.minimum(bound, sets.x_hi[i]))
    return out


def lanes_of(lanes: int, count: int) -> np.ndarray:
    """(count,) bool: the lanes of the bitmask ``lanes`` (:func:`~safelane.safety.committed.plans.lane_bit`)."""
    return (lanes >> np.arange(count)) & 1 == 1
