"""The committed rule for continuous controls: a verified plan kept from one decision to the next, and the action
executed at each decision.

:class:`ControlFamily` judges the agent's action (:meth:`ControlFamily.judge`) in the state of a road snapshot:

* **projection** (the default): the agent's action if verified, else the verified action nearest it
  (:func:`~safelane.safety.continuous.search.project`; the kept plan's next step is one of the candidates);
* **replacement**: the agent's action if verified, else the kept plan's next step if its plan still verifies, else
  the fail-safe's action now (brake, keeping the lane) if verified;
* with no action verified, the kept plan's next step drives (``plan_forced``); with no plan kept either the state
  is **uncertified** and the fail-safe's braking action drives, a best effort.

A decision at which the plan kept (verified) at the last one no longer verifies is a **lapse**, traced to the cars
it fails on as the meta-action committed rule traces its own (:class:`ControlResult.lapse_in_model`). The other
cars' sets are the committed rule's (:mod:`safelane.safety.committed.sets`), carried and intersected between
decisions the same way. Pure maths: no simulator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from safelane.core.snapshot import RoadSnapshot
from safelane.safety.committed.compiled import CarArrays, car_arrays, car_sets_compiled, prepare
from safelane.safety.committed.family import carry_sets, entered_held_lanes, followers_escaped
from safelane.safety.committed.plans import follower_bound, lane_bit
from safelane.safety.committed.sets import (
    CarSets,
    car_sets,
    occupied_lanes,
    rolling_back,
)
from safelane.safety.continuous.compiled import (
    limit_arrays,
    state_arrays,
    tail_gap_compiled,
    verify_action_compiled,
)
from safelane.safety.continuous.controls import ControlLimits, fail_safe_action
from safelane.safety.continuous.plans import (
    ControlPlan,
    ego_state,
    plan_lane,
    replay_trajectory,
    trajectory_gap,
    verify_action,
)
from safelane.safety.continuous.search import ActionSearch, project
from safelane.safety.road import whole_road_state
from safelane.safety.world import Dynamics, Engine, RoadState, check_choices

Intervention = Literal["projection", "replacement"]
INTERVENTIONS: tuple[Intervention, ...] = ("projection", "replacement")


@dataclass(frozen=True)
class ControlResult:
    """The verdict on one decision: the ``executed`` action (2,) float32, the agent's (``wanted``, clipped to
    [−1, 1]); ``projected``: they differ; ``projection_distance`` [normalised]; ``plan`` the executed action's
    verified plan (None when forced or uncertified); ``plan_forced``: nothing verified, the kept plan's next step
    drives; ``certified``: some plan is verified or kept; lapses and the cars they are traced to as
    :class:`~safelane.safety.committed.family.CommittedResult` names them (snapshot indices); ``evaluated``: the
    actions verified to decide."""

    executed: np.ndarray
    wanted: np.ndarray
    projection_distance: float
    plan: ControlPlan | None
    plan_forced: bool = False
    certified: bool = False
    lapse: bool = False
    lapse_cars: tuple[int, ...] = ()
    escaped: tuple[int, ...] = ()
    rolled_back: tuple[int, ...] = ()
    unbraked_followers: tuple[int, ...] = ()
    entered: tuple[int, ...] = ()
    ego_crashed: bool = False
    checked: int = 0
    evaluated: int = 0

    @property
    def projected(self) -> bool:
        """The executed action is not the agent's."""
        return bool(np.any(self.executed != self.wanted))

    @property
    def lapse_in_model(self) -> bool:
        """A lapse not traced to the model's exits, as
        :attr:`safelane.safety.committed.family.CommittedResult.lapse_in_model` defines it."""
        traced = {*self.escaped, *self.entered}
        in_model = not self.lapse_cars or any(v not in traced for v in self.lapse_cars)
        return self.lapse and not self.ego_crashed and in_model

    def info(self) -> dict[str, Any]:
        """The keys the shield adds to a step's ``info``."""
        return {
            "executed_action": self.executed.copy(), "projected": self.projected,
            "projection_distance": self.projection_distance, "shield_intervened": self.projected,
            "plan_forced": self.plan_forced, "certified": self.certified, "lapse": self.lapse,
            "lapse_in_model": self.lapse_in_model, "lapse_cars": self.lapse_cars,
            "lapse_escaped_cars": tuple(v for v in self.lapse_cars if v in self.escaped),
            "escaped_cars": self.escaped, "rolled_back": self.rolled_back,
            "unbraked_followers": self.unbraked_followers, "entered_cars": self.entered,
        }  # fmt: skip


def lane_keeping_action(state: RoadState, dyn: Dynamics, limits: ControlLimits) -> np.ndarray:
    """(2,) float32 the fail-safe's action now: brake toward a standstill, steering for the nearest lane."""
    ego = ego_state(state)
    return fail_safe_action(ego, plan_lane(ego.y, dyn) * dyn.lane_width, True, dyn, limits, state.ego_length)


@dataclass(frozen=True)
class DecisionContext:
    """One state as :meth:`ControlFamily.context` reads it: whether the ego has crashed, the road state, the
    world's constants, the other cars' sets (carried), their snapshot indices, the trace of the carried sets
    (:meth:`ControlFamily.state_of`), the kept plan's tail if it still verifies, whether it lapsed and the cars it
    fails on, the memoised verifier of actions and the fail-safe's action (2,)."""

    ego_crashed: bool
    state: RoadState
    dyn: Dynamics
    sets: CarSets
    vehicle: np.ndarray
    trace: dict[str, Any]
    tail: ControlPlan | None
    lapse: bool
    failed: np.ndarray
    search: ActionSearch
    lane_keeping: np.ndarray


@dataclass
class _Judged:
    """What :meth:`ControlFamily.commit` needs of the last judgement: the verdict and the state it was read in."""

    result: ControlResult
    ctx: DecisionContext


@dataclass
class ControlFamily:
    """The committed rule under continuous controls (module docstring), with memory: :meth:`judge` decides one
    action without changing it, :meth:`commit` records the executed one, :meth:`reset` forgets the episode."""

    limits: ControlLimits = field(default_factory=ControlLimits)
    intervention: Intervention = "projection"
    engine: Engine = "compiled"
    kept: ControlPlan | None = None
    kept_verified: bool = False
    carried: CarSets | None = None
    carried_ahead: np.ndarray | None = None
    followers: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)
    _judged: _Judged | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.intervention not in INTERVENTIONS:
            raise ValueError(f"shield.intervention: got {self.intervention!r}; allowed: 'projection', 'replacement'")
        check_choices(engine=self.engine)
        self._limit_arrays = limit_arrays(self.limits)

    def reset(self) -> None:
        """Forget the kept plan and the carried sets (a new episode)."""
        self.kept, self.kept_verified, self.carried, self.carried_ahead = None, False, None, None
        self.followers, self._judged = {}, None

    def state_of(self, snap: RoadSnapshot, dyn: Dynamics) -> tuple[RoadState, np.ndarray, CarSets, dict[str, Any]]:
        """(state, vehicle, sets, trace) in the state of ``snap``: the sets drawn now, intersected with those carried
        from the last decision for the cars still inside them (``trace``: escaped, entered, unbraked followers,
        rolled back, checked; ``cars``: the compiled engine's per-car arrays, None for the reference)."""
        state, vehicle = whole_road_state(snap, True)
        cars: CarArrays | None = None
        if self.engine == "compiled":
            prep = prepare(state, dyn)
            sets, cars = car_sets_compiled(state, dyn, vehicle, prep), car_arrays(state, dyn, prep)
        else:
            sets = car_sets(state, dyn, vehicle)
        escaped = entered = unbraked = np.zeros(state.n, dtype=bool)
        rolled: np.ndarray | None = None
        checked = 0
        if self.carried is not None:
            held = self.kept.held if self.kept is not None else ()
            entered = entered_held_lanes(state, self.carried, sets, vehicle, self.carried_ahead, held)
            occupied = occupied_lanes(state, dyn)
            unbraked = followers_escaped(self.followers, state, dyn, vehicle, occupied)
            sets, escaped, rolled, checked = carry_sets(state, dyn, sets, self.carried, vehicle, unbraked, occupied,
                                                        cars is not None)  # fmt: skip
        if rolled is None:
            rolled = rolling_back(state, escaped)
        trace = {"escaped": escaped, "entered": entered, "unbraked": unbraked, "rolled": rolled, "checked": checked,
                 "cars": cars}  # fmt: skip
        return state, vehicle, sets, trace

    def search(self, state: RoadState, dyn: Dynamics, sets: CarSets, cars: CarArrays | None = None) -> ActionSearch:
        """A memoised verifier of actions in ``state`` against ``sets`` (``cars``: the compiled engine's)."""
        if self.engine == "compiled":
            arrays = state_arrays(state, sets, car_arrays(state, dyn) if cars is None else cars)
            limits = self._limit_arrays
            return ActionSearch(lambda action: verify_action_compiled(state, dyn, limits, sets, arrays, action))
        return ActionSearch(lambda action: verify_action(state, dyn, self.limits, sets, action))

    def context(self, snap: RoadSnapshot, dyn: Dynamics) -> DecisionContext:
        """What judging any action in the state of ``snap`` needs, computed once (``dyn``: with
        ``braking_decisions`` for these limits): the sets, the kept plan's tail, the verifier, the fail-safe's
        action. A planner that judges several actions in one state reads it once and decides each with
        :meth:`decide`."""
        state, vehicle, sets, trace = self.state_of(snap, dyn)
        tail, lapse, failed = self._kept_tail(state, dyn, sets, vehicle, trace["escaped"], trace["cars"])
        search = self.search(state, dyn, sets, trace["cars"])
        lane_keeping = lane_keeping_action(state, dyn, self.limits)
        return DecisionContext(bool(snap.crashed[snap.ego]), state, dyn, sets, vehicle, trace, tail, lapse, failed,
                               search, lane_keeping)  # fmt: skip

    def judge(self, snap: RoadSnapshot, dyn: Dynamics, wanted: np.ndarray) -> ControlResult:
        """The action to execute for the agent's ``wanted`` (2,) in the state of ``snap`` (``dyn``: with
        ``braking_decisions`` for these limits)."""
        return self.decide(self.context(snap, dyn), wanted)

    def decide(self, ctx: DecisionContext, wanted: np.ndarray) -> ControlResult:
        """The action to execute for the agent's ``wanted`` (2,) in the state ``ctx`` was read in (by this family's
        memory, or an identical copy's); :meth:`commit` then records it."""
        wanted = np.clip(np.asarray(wanted, dtype=np.float32), -1, 1).astype(np.float32)
        tail, search, lane_keeping, vehicle, trace = ctx.tail, ctx.search, ctx.lane_keeping, ctx.vehicle, ctx.trace
        candidates = ((tail.actions[0], tail),) if tail is not None else ()
        executed: np.ndarray | None = None
        plan: ControlPlan | None = None
        if self.intervention == "projection":
            found = project(search, wanted, float(lane_keeping[1]), candidates)
            executed, plan = found.action, found.plan
        else:
            for action, plan in ((wanted, None), *candidates, (lane_keeping, None)):
                plan = plan or search.plan(float(action[0]), float(action[1]))
                if plan is not None:
                    executed = np.asarray(action, dtype=np.float32)
                    break
        forced = executed is None and self.kept is not None
        if executed is None:
            plan = None
            executed = (self.kept.next_action() if self.kept is not None else lane_keeping).astype(np.float32)
        distance = float(np.hypot(*(executed.astype(np.float64) - wanted)))
        result = ControlResult(
            executed, wanted, distance, plan, plan_forced=forced,
            certified=plan is not None or self.kept is not None, lapse=ctx.lapse,
            lapse_cars=tuple(int(v) for v in vehicle[ctx.failed]),
            escaped=tuple(int(v) for v in vehicle[trace["escaped"]]),
            rolled_back=tuple(int(v) for v in vehicle[trace["rolled"]]),
            unbraked_followers=tuple(int(v) for v in vehicle[trace["unbraked"]]),
            entered=tuple(int(v) for v in vehicle[trace["entered"]]),
            ego_crashed=ctx.ego_crashed, checked=trace["checked"], evaluated=search.evaluated,
        )  # fmt: skip
        self._judged = _Judged(result, ctx)
        return result

    def _kept_tail(self, state: RoadState, dyn: Dynamics, sets: CarSets, vehicle: np.ndarray, escaped: np.ndarray,
                   cars: CarArrays | None) -> tuple[ControlPlan | None, bool, np.ndarray]:  # fmt: skip
        """(the kept plan's tail as a plan when it still verifies, lapse, the cars it fails on)."""
        failed = np.zeros(state.n, dtype=bool)
        if self.kept is None:
            return None, False, failed
        f, period = dyn.frames_per_decision, dyn.decision_period
        rows = {int(v): r for r, v in enumerate(vehicle)}
        followers = {
            rows[v]: (lane, np.concatenate([high[f:], np.full(f, np.inf)]))
            for v, (lane, high) in self.followers.items()
            if v in rows and not escaped[rows[v]]
        }
        onset = self.kept.onset - period
        frames = self.kept.frames - f
        if cars is not None:
            gaps, lanes, trajectory = tail_gap_compiled(state, dyn, self._limit_arrays, sets, cars,
                                                        self.kept.tail_actions(), onset, self.kept.held, frames,
                                                        followers)  # fmt: skip
        else:
            trajectory = replay_trajectory(state, dyn, self.limits, self.kept.tail_actions())
            gaps, lanes = trajectory_gap(state, dyn, sets, trajectory, onset, self.kept.held, frames, followers)
        gap = float(gaps.min()) if gaps.size else math.inf
        lapse = self.kept_verified and not gap >= dyn.margin
        if lapse and gaps.size == state.n:
            failed = ~(gaps >= dyn.margin)
        if not gap >= dyn.margin:
            return None, lapse, failed
        tail = ControlPlan(trajectory.actions[: len(self.kept.tail_actions())], trajectory.states[:, 0].copy(), lanes,
                           onset, self.kept.held, frames, gap)  # fmt: skip
        return tail, lapse, failed

    def commit(self) -> None:
        """Record that the last judged action was executed: its verified plan is kept (the kept plan's tail goes on
        when forced or chosen); with none the memory of a plan ends."""
        if self._judged is None:
            return
        result, ctx = self._judged.result, self._judged.ctx
        state, dyn = ctx.state, ctx.dyn
        plan = result.plan
        same_plan = plan is not None and plan is ctx.tail
        self.kept_verified = plan is not None
        if plan is None and result.plan_forced and self.kept is not None:
            kept = self.kept
            period, f = dyn.decision_period, dyn.frames_per_decision
            plan = replace(kept, actions=kept.tail_actions(), onset=kept.onset - period, frames=kept.frames - f,
                           lanes=tuple((lane, until - period) for lane, until in kept.lanes))  # fmt: skip
            same_plan = True
        self.kept = plan
        self.carried = ctx.sets
        self.carried_ahead = state.x >= state.ego_x
        if plan is None:
            self.followers = {}
        else:
            fresh = _followers_of(state, dyn, ctx.sets, ctx.vehicle, plan)
            self.followers = carried_follower_bounds(self.followers if same_plan else {}, fresh,
                                                     dyn.frames_per_decision)  # fmt: skip
        self._judged = None

    def certified(self, snap: RoadSnapshot, dyn: Dynamics) -> bool:
        """Some action has a verified plan in the state of ``snap`` (or a plan is kept): the search from the
        fail-safe's action, which tries every steering it examines until one verifies."""
        if self.kept is not None:
            return True
        state, _, sets, trace = self.state_of(snap, dyn)
        lane_keeping = lane_keeping_action(state, dyn, self.limits)
        return project(self.search(state, dyn, sets, trace["cars"]), lane_keeping, float(lane_keeping[1])).action \
            is not None

    def safe_acceleration_interval(self, snap: RoadSnapshot, dyn: Dynamics, steering: float) -> tuple[float, float]:
        """(low, high) [normalised] the verified accelerations at ``steering`` [normalised] in the state of
        ``snap`` (nan, nan: none), by the search's interval structure (:mod:`~safelane.safety.continuous.search`)."""
        state, _, sets, trace = self.state_of(snap, dyn)
        low, high, _ = self.search(state, dyn, sets, trace["cars"]).interval(float(np.float32(steering)))
        return low, high


def carried_follower_bounds(kept: dict[int, tuple[int, np.ndarray]], fresh: dict[int, tuple[int, np.ndarray]],
                            frames: int) -> dict[int, tuple[int, np.ndarray]]:  # fmt: skip
    """{car: (lanes bitmask, highest position [m] per frame)} the follower bounds a plan kept for one more decision
    carries: ``fresh``, those drawn now (:func:`_followers_of`), with the ``kept`` ones moved on by one decision
    (``frames`` frames). Each is a bound on the car's position, drawn in a lane where it followed the ego; a car
    keeps the lower of its bounds and every lane it followed in while the plan was kept: a car no longer following
    may come back, and one that moves from lane to lane (into the other lane the plan holds, then out of it) still
    overlaps a lane it followed in with its body after IDM has stopped seeing the ego there (its centre has left):
    the bound must apply in each such lane (a car that kept only the lane it left, or only the new one, was the
    claim sample's lapses in the model)."""
    out = dict(fresh)
    for v, (lanes, high) in kept.items():
        shifted = np.concatenate([high[frames:], np.full(frames, np.inf)])
        now = fresh.get(v)
        out[v] = (lanes, shifted) if now is None else (lanes | now[0], np.minimum(now[1], shifted))
    return out


def _followers_of(state: RoadState, dyn: Dynamics, sets: CarSets, vehicle: np.ndarray, plan: ControlPlan) -> dict:
    """{snapshot index: (lane bitmask, highest position [m] per frame)} of the cars that follow the ego under
    ``plan`` in the lanes it holds (the follower law): the bound a lapse is traced against."""
    held = set(plan.held)
    lanes = [lane for lane, _ in plan.lanes if lane in held]
    out: dict[int, tuple[int, np.ndarray]] = {}
    t = dyn.times
    react = np.array([max(plan.onset + dyn.follower_reaction, 0.0)])
    own = state.lane_of(state.y, dyn.lanes_count, dyn.lane_width)
    behind = state.x < state.ego_x
    for lane in lanes:
        for i in np.flatnonzero(behind & (own == lane)):
            out[int(vehicle[i])] = (lane_bit(lane), np.minimum(follower_bound(state, int(i), react, t)[0],
                                                               sets.x_hi[i]))  # fmt: skip
    return out
