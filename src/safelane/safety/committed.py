"""Committed fail-safe plans (experimental): a shield that keeps a verified plan from one decision to the next.

The ``committed`` shield mode (experimental; design and measurement: ``docs/research/committed-plans.md``), its
numpy reference: ``engine="compiled"`` runs the arithmetic in :mod:`safelane.safety.committed_compiled`, with the
same bits. Pure maths: no simulator, no highway-env, no torch.

* A **plan** (:class:`Plan`) is a sequence of ego set-points [m/s] and target lanes, one per decision, ending
  with the ego at a standstill. The family: the action, hold the set-point ``k ∈ {0..3}`` decisions, then SLOWER
  at every decision (the ego's exact trajectory: :func:`safelane.safety.ego.ego_trajectories`).
* Every other car gets a **reachable set** (:class:`CarSets`, :mod:`safelane.safety.committed_sets`) drawn from
  the observable state only: an envelope of its speed along its path from its driver model's acceleration bounds,
  its position along the road from it less what a lane change may cost (:func:`envelope`), and, per lane, the
  earliest time it may occupy it (:func:`lane_entry_times`). They nest in time (``R(s', [0, H−Δ]) ⊆ R(s, [Δ, H])``,
  tested in ``tests/test_committed.py``); what does not nest (heading projection, a lane change begun) is closed
  by memory: the sets carried from the last decision are intersected with the new ones.
* Laws apply under a plan where they nest with the plan kept: the drivers' acceleration laws toward their
  set-points (in the sets), MOBIL's safety criterion against the ego's known plan (IDM and linear-model drivers
  entering a lane the ego holds), and followers reacting ``ρ`` after the plan's braking onset — an assumption, not
  IDM's law: a follower that does not brake so is named (``unbraked_followers``) (:func:`verify_plans`).
* An action is **verified** when a plan starting with it keeps ``margin`` to every car's reachable occupancy at
  every frame of the horizon. :class:`CommittedFamily` allows the verified actions; with none it allows only the
  kept plan's next step (``plan_forced``); with no plan at all (uncertified) the one-decision robust rule's mask
  (:class:`~safelane.safety.family.OneDecisionFamily`, ``engine``). A decision at which the plan kept (verified)
  at the last decision no longer verifies is a **lapse**; it names the cars the kept plan fails on and which of
  them left the sets drawn for them (cars by their index in the road snapshot, one car's for a whole episode).
  Whose gap a car is: a car behind the ego in the lane it is in, or one cutting into a lane it holds, is not the
  ego's to avoid (that driver makes the gap); a car in a lane the ego is entering is, ahead or behind.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from safelane.core.snapshot import DRIVER_FIELDS, RoadSnapshot
from safelane.core.spaces import IDLE, LANE_LEFT, LANE_RIGHT, N_ACTIONS, SLOWER
from safelane.safety.committed_compiled import (
    CarArrays,
    car_arrays,
    car_gaps_compiled,
    car_sets_compiled,
    follower_bound_compiled,
    held_lanes,
    prepare,
    verify_plans_compiled,
)
from safelane.safety.committed_sets import (
    ESCAPE_TOLERANCE,
    MAX_SPEED,
    CarSets,
    car_sets,
    envelope,
    escaped_cars,
    fall,
    lane_crossing_time,
    lane_entry_times,
    lanes_now,
    linear_set_point_bound,
    occupied_lanes,
    path_speed,
    rise,
    rolling_back,
    rows_in,
    speed_bounds,
)
from safelane.safety.ego import action_lanes, action_targets, available_actions, ego_trajectories, speed_to_index
from safelane.safety.family import Engine, OneDecisionFamily, road_state
from safelane.safety.model import evaluate as evaluate_one_decision
from safelane.safety.world import MAX_HOLD_DECISIONS, Dynamics, RoadState, SafetyResult

__all__ = [
    "ESCAPE_TOLERANCE", "MAX_SPEED", "CarSets", "CommittedFamily", "CommittedResult", "Lanes", "Plan", "car_gaps",
    "car_sets", "envelope", "escaped_cars", "follower_bound", "lane_crossing_time", "lane_entry_times", "lanes_now",
    "onsets", "path_speed", "plan_gaps", "plan_of", "rolling_back", "speed_bounds", "verify_plans",
]  # fmt: skip


# --------------------------------------------------------------------------------------------
# Plans and their verification.
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Plan:
    """A committed plan: the ego's set-point [m/s] and target lane per decision from now until it stands
    (``set_points``, ``lanes``: the representation open to other families), the lanes it occupies and until when
    (``occupied``: (lane, time [s] from now)), its braking onset [s] from now, and how many frames of the horizon it
    was verified over (``frames``). ``action``/``hold``: the family's parameters that generated it (the action,
    hold ``hold`` decisions, then SLOWER)."""

    action: int
    hold: int
    set_points: tuple[float, ...]
    lanes: tuple[int, ...]
    occupied: tuple[tuple[int, float], ...]
    onset: float
    frames: int
    held: tuple[int, ...] = ()
    """The lanes the ego held (its lane and target lane) when the plan was verified: the line between the cars
    that count and those that do not stays where it was drawn while the plan is kept (:func:`car_gaps`' ``held``)."""

    def next_step(self) -> int:
        """The meta-action that realises the plan's next decision: IDLE while the set-point holds, SLOWER once it
        falls."""
        return IDLE if self.hold >= 1 else SLOWER

    def tail(self) -> tuple[int, int]:
        """(action, hold) whose trajectory from the next state is this plan's tail (a member of that state's
        family; its lanes and onset are this plan's, shifted: :meth:`shifted`)."""
        return (IDLE, self.hold - 1) if self.hold >= 1 else (SLOWER, 0)

    def shifted(self, dyn: Dynamics) -> Plan:
        """This plan one decision later."""
        a, k = self.tail()
        period = dyn.decision_period
        return Plan(a, k, self.set_points[1:] or self.set_points[-1:], self.lanes[1:] or self.lanes[-1:],
                    tuple((lane, until - period) for lane, until in self.occupied), self.onset - period,
                    self.frames - dyn.frames_per_decision, self.held)  # fmt: skip


def plan_of(state: RoadState, dyn: Dynamics, set_points: np.ndarray, action: int, hold: int) -> Plan:
    """The :class:`Plan` of (``action``, ``hold``) in ``state``: its set-points decision by decision, read from
    ``set_points`` [m/s], the plan's set-point per frame (a row of :func:`plan_set_points`), up to the first 0 m/s
    after the hold."""
    f = dyn.frames_per_decision
    points = [float(set_points[0])]
    for d in range(1, dyn.horizon_decisions):
        points.append(float(set_points[d * f]))
        if points[-1] == 0.0 and d > hold:
            break
    occupied = tuple(action_lanes(state, dyn, action))
    lane = occupied[-1][0]
    onset = float(onsets(dyn, action)[hold])
    return Plan(action, hold, tuple(points), (lane,) * len(points), occupied, onset, int(dyn.times.size - 1),
                (int(state.ego_lane), int(state.ego_target_lane)))  # fmt: skip


def onsets(dyn: Dynamics, action: int) -> np.ndarray:
    """(holds,) [s] when each plan of ``action`` first lowers the set-point (its braking onset)."""
    if action == SLOWER:
        return np.zeros(MAX_HOLD_DECISIONS + 1)
    return (1 + np.arange(MAX_HOLD_DECISIONS + 1)) * dyn.decision_period


def plan_set_points(state: RoadState, dyn: Dynamics, ego_v: np.ndarray, action: int) -> np.ndarray:
    """(holds, frames) [m/s] the ego's set-point at each frame of each plan of ``action`` (``ego_v``: its speeds,
    (holds, frames)): the action's, held ``hold`` decisions, then one step below the speed at each decision (SLOWER,
    as :func:`plan_of` lists them)."""
    ts = dyn.target_speeds
    f = dyn.frames_per_decision
    out = np.empty_like(ego_v)
    for hold in range(ego_v.shape[0]):
        point = float(action_targets(state, dyn)[action])
        for d in range(0, math.ceil(ego_v.shape[1] / f)):
            if d > hold:
                point = float(ts[max(int(speed_to_index(ego_v[hold, d * f], ts)) - 1, 0)])
            out[hold, d * f : (d + 1) * f] = point
    return out


def _linear_criterion(
    state: RoadState, sets: CarSets, rows: np.ndarray, gap: np.ndarray, ev: np.ndarray, ego_set: np.ndarray | None,
    dyn: Dynamics,
) -> np.ndarray:  # fmt: skip
    """(rows, holds, frames) whether MOBIL's safety criterion of linear-model drivers could hold: the ego's
    acceleration behind the car by the car's own linear law (:func:`~safelane.safety.others.
    linear_acceleration_behind`), at its largest over the car's set (fastest, farthest: the law is monotone in both)
    and the ego's set-point (the plan's; without it the highest), at least ``−max_braking_imposed``."""
    k0, k1, k2 = (getattr(state, name)[rows][:, None, None] for name in
                  ("linear_speed_gain", "linear_speed_difference_gain", "linear_distance_gain"))  # fmt: skip
    target = (ego_set if ego_set is not None else np.full_like(ev[0], max(dyn.target_speeds)))[None]
    d_safe = state.idm_distance_wanted[rows][:, None, None] + ev * state.idm_time_wanted[rows][:, None, None]
    own = sets.v_hi[rows][:, None, :]  # highway-env reads the car's speed along its path
    pred = k0 * (target - ev) + k1 * np.minimum(own - ev, 0.0) + k2 * np.minimum(gap - d_safe, 0.0)
    return pred >= -state.max_braking_imposed[rows][:, None, None]


def _permit_entry(
    state: RoadState, dyn: Dynamics, sets: CarSets, rows: np.ndarray, ego_x: np.ndarray, ego_v: np.ndarray,
    ego_set: np.ndarray | None = None,
) -> np.ndarray:  # fmt: skip
    """(rows, holds) [s] the first time MOBIL's safety criterion could let each car (IDM and linear-model drivers,
    ahead) move in front of the ego on each plan (its loosest state in reach: the largest gap, the speed that makes
    the criterion loosest, the ego's set-point at the lane's limit for IDM, the plan's ``ego_set`` (holds, frames)
    for the linear models) or could be behind the ego, plus the cut-in time; inf: never in the horizon."""
    t = dyn.times
    acc = state.idm_comfort_acc[rows][:, None, None]
    ab = (-state.idm_comfort_acc * state.idm_comfort_dec)[rows][:, None, None]
    gap = sets.x_hi[rows][:, None, :] - ego_x[None]  # (rows, holds, frames) centre distance
    ev = np.maximum(ego_v[None], 0.0)
    target = max(state.speed_limit, 1e-2)
    free = acc * (1 - np.power(ev / target, state.idm_delta[rows][:, None, None]))
    base = state.idm_distance_wanted[rows][:, None, None] + ev * state.idm_time_wanted[rows][:, None, None]
    d_fast = base + ev * (ev - np.maximum(sets.v_hi[rows], 0.0)[:, None, :]) / (2 * np.sqrt(ab))
    # IDM's desired gap projects the car's velocity on the ego's heading: at most its speed along its path, at
    # least min(its lowest, 0) (both may be turned).
    d_slow = base + ev * (ev - np.minimum(sets.v_lo[rows], 0.0)[:, None, :]) / (2 * np.sqrt(ab))
    lo, hi = np.minimum(d_fast, d_slow), np.maximum(d_fast, d_slow)
    least = np.where(lo > 0.0, lo, np.where(hi < 0.0, -hi, 0.0))
    d = np.maximum(gap, 1e-2)
    ok = free - acc * (least / d) ** 2 >= -state.max_braking_imposed[rows][:, None, None]
    linear = np.isfinite(state.linear_speed_gain[rows])
    if linear.any():
        ok[linear] = _linear_criterion(state, sets, rows[linear], gap[linear], ev, ego_set, dyn)
    ok &= gap > 0.0
    # Once it may be behind the ego, MOBIL protects its new follower, not the ego: it may turn in behind it.
    ok |= sets.x_lo[rows][:, None, :] < ego_x[None]
    first = np.where(ok.any(axis=2), t[np.argmax(ok, axis=2)], np.inf)
    return first + dyn.cut_in_time


Lanes = list[tuple[int, float]]
"""The lanes a plan occupies, each with the time [s] until which it does (:func:`safelane.safety.ego.action_lanes`)."""


def verify_plans(
    state: RoadState, dyn: Dynamics, sets: CarSets, engine: Engine = "numpy", cars: CarArrays | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """(5, holds) each plan's worst bumper-to-bumper gap [m] to every car's reachable occupancy over the horizon
    (−inf: action unavailable, inf: no car in reach), and the ego's positions [m], speeds [m/s] and set-points
    [m/s] (:func:`plan_set_points`; NaN for an unavailable action), each (5, holds, frames + 1) (:func:`plan_gaps`
    for one action). ``engine``: the numpy reference or its compiled kernels (the same bits; ``cars``: the
    state's :func:`~safelane.safety.committed_compiled.car_arrays` when already computed)."""
    available = available_actions(state, dyn)
    verify = available.copy()
    if not math.isfinite(dyn.ego_leave_time):  # too slow to leave the lane: no lane change (docs/safety.md §4)
        verify &= ~np.isin(np.arange(N_ACTIONS), (LANE_LEFT, LANE_RIGHT))
    if engine == "compiled":
        lanes = [action_lanes(state, dyn, a) if available[a] else [] for a in range(N_ACTIONS)]
        plan_onsets = np.stack([onsets(dyn, a) for a in range(N_ACTIONS)])
        cars = car_arrays(state, dyn) if cars is None else cars
        return verify_plans_compiled(state, dyn, sets, available, verify, lanes, plan_onsets, cars)
    ego_x, ego_v = ego_trajectories(state, dyn)
    set_points = np.full_like(ego_v, np.nan)
    for a in np.flatnonzero(available):
        set_points[a] = plan_set_points(state, dyn, ego_v[a], int(a))
    worst = np.full((N_ACTIONS, MAX_HOLD_DECISIONS + 1), -np.inf)
    for a in np.flatnonzero(verify):
        gaps = car_gaps(state, dyn, sets, ego_x[a], ego_v[a], onsets(dyn, int(a)), action_lanes(state, dyn, int(a)),
                        ego_set=set_points[a])  # fmt: skip
        worst[a] = gaps.min(axis=0) if gaps.shape[0] else np.inf
    return worst, ego_x, ego_v, set_points


def plan_gaps(
    state: RoadState, dyn: Dynamics, sets: CarSets, ego_x: np.ndarray, ego_v: np.ndarray, onset: np.ndarray,
    lanes: Lanes, until_frame: int | None = None, carried_followers: dict[int, tuple[int, np.ndarray]] | None = None,
    ego_set: np.ndarray | None = None,
) -> np.ndarray:  # fmt: skip
    """(holds,) the worst bumper-to-bumper gap [m] of plans whose ego moves as ``ego_x``/``ego_v`` (holds, frames)
    over every car (inf: no car in reach): the least of :func:`car_gaps`, which documents the arguments."""
    gaps = car_gaps(state, dyn, sets, ego_x, ego_v, onset, lanes, until_frame, carried_followers, ego_set)
    return gaps.min(axis=0) if gaps.shape[0] else np.full(ego_x.shape[0], np.inf)


def car_gaps(
    state: RoadState, dyn: Dynamics, sets: CarSets, ego_x: np.ndarray, ego_v: np.ndarray, onset: np.ndarray,
    lanes: Lanes, until_frame: int | None = None, carried_followers: dict[int, tuple[int, np.ndarray]] | None = None,
    ego_set: np.ndarray | None = None, held: tuple[int, ...] | None = None,
) -> np.ndarray:  # fmt: skip
    """(cars, holds) each car's worst bumper-to-bumper gap [m] to plans whose ego moves as ``ego_x``/``ego_v``
    (holds, frames) and brakes first at ``onset`` [s] (holds,), occupying ``lanes``, at every frame up to
    ``until_frame`` (default: the horizon's end); inf where the car never reaches the plan. The cars below the
    margin are the ones a plan fails on (a lapse names them).

    In each lane, from each car's entry time on, the car's interval ``[x_lo, x_hi]`` must stay clear of the ego by
    ``margin`` on one side or the other at every frame (a car that may be on either side conflicts). Laws: an IDM driver
    ahead, entering a lane the ego holds from the start, enters only after MOBIL's criterion against the plan could
    allow it (:func:`_permit_entry`); a car in such a lane behind the ego now follows it: accelerates at most until
    ``follower_reaction`` after the plan's braking onset, then brakes (:func:`follower_bound`). In a lane the ego holds,
    only the cars in that lane now (or moving into it) count, and of those in the lane the ego is in (``held``'s first)
    only the ones ahead: a car behind the ego in its lane, or one that cuts in later, is responsible for the gap it
    makes; a car in a lane the ego is entering is the ego's to keep clear of, ahead or behind. ``carried_followers``:
    {row: (lane, highest position [m] per frame)}, the follower bounds a kept plan drew, kept in that lane; ``ego_set``
    (holds, frames): the plans' set-points [m/s] (:func:`plan_set_points`; the linear drivers' MOBIL criterion reads
    it); ``held``: the lanes the ego holds (default: its lane and target lane now; a kept plan's tail passes those it
    held when verified, :attr:`Plan.held`)."""
    t = dyn.times
    half = 0.5 * (state.length + state.ego_length)
    ahead = state.x >= state.ego_x
    # Drivers that change lane by MOBIL with a formula the criterion can be bounded for: IDM, or the linear model
    # with gains ≥ 0 (linear_set_point_bound).
    mobil = (~np.isfinite(state.linear_speed_gain) | linear_set_point_bound(state)) & state.can_change_lane
    mobil &= ~state.crashed & np.isfinite(state.max_braking_imposed)
    holding = held_lanes(state, held)
    in_lane, held = holding[0], set(holding)  # the lane the ego is in, not one it is entering
    n_fb = ego_x.shape[0]
    frames = t <= (t[-1] if until_frame is None else t[min(max(until_frame, 0), t.size - 1)])
    worst = np.full((state.n, n_fb), np.inf)
    for lane, until in lanes:
        held_lane = lane in held
        entry = np.repeat(sets.entry[:, lane][:, None], n_fb, axis=1)  # (cars, holds)
        law = np.flatnonzero(held_lane & ahead & mobil & ~sets.now[:, lane])
        if law.size:
            entry[law] = np.maximum(entry[law], _permit_entry(state, dyn, sets, law, ego_x, ego_v, ego_set))
        count = np.isfinite(entry).any(axis=1)
        if held_lane:  # cut-ins, and cars behind in the ego's lane: theirs to avoid
            count &= sets.now[:, lane] & (ahead | (lane != in_lane))
        # A follower: its own lane is this one (highway-env's IDM sees the ego as its leader only then).
        following = held_lane & ~ahead & (state.lane_of(state.y, dyn.lanes_count, dyn.lane_width) == lane)
        in_time = frames & (t <= until)
        for i in np.flatnonzero(count):
            window = (t[None, :] >= entry[i][:, None]) & in_time[None, :]  # (holds, frames)
            if not window.any():
                continue
            high = sets.x_hi[i][None, :]
            if following[i]:
                react = np.maximum(onset + dyn.follower_reaction, 0.0)  # a past reaction: braking from now
                high = np.minimum(high, follower_bound(state, i, react, t))
            carried = (carried_followers or {}).get(int(i))
            if carried is not None and carried[0] == lane:
                high = np.minimum(high, carried[1][None, :])
            gap = np.maximum(sets.x_lo[i][None, :] - ego_x - half[i], ego_x - high - half[i])
            worst[i] = np.minimum(worst[i], np.where(window, gap, np.inf).min(axis=1))
    return worst


def follower_bound(state: RoadState, i: int, react: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(holds, frames) [m] the highest position of car ``i`` reacting at ``react`` [s] (per plan): its envelope's
    top until then, then braking at its limit from the speed it may have reached."""
    speed = path_speed(state)[i : i + 1]  # along its path: at least its speed along the road
    v0 = np.maximum(speed, 0.0)
    a, b = np.array([state.accel_max[i]]), np.array([state.brake_max[i]])
    v_min, v_max = speed_bounds(speed, state.target_speed[i : i + 1], np.isfinite(state.linear_speed_gain[i : i + 1]))
    r = react[:, None]
    d1, _ = rise(v0, a, v_max, np.minimum(t[None, :], r))
    d_r, v_r = rise(v0, a, v_max, r)
    d2, _ = fall(v_r, b, np.minimum(v_min, 0.0), np.maximum(t[None, :] - r, 0.0))
    return state.x[i] + np.where(t[None, :] <= r, d1, d_r + d2)


# --------------------------------------------------------------------------------------------
# The family: memory between decisions.
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CommittedResult(SafetyResult):
    """:class:`SafetyResult` of the committed family: ``safe`` lists the verified actions, ``fallback`` is set when
    none is; ``plan_forced``: the kept plan's next step drives (nothing verified); ``lapse``: the plan kept, verified,
    at the last decision no longer verifies (a plan driven on after a lapse is not verified again); ``lapse_cars``: at a
    lapse, the cars the kept plan fails on (their own worst gap to its tail below the margin; :attr:`lapse_escaped`
    those of them outside their sets). Cars are named by their index in the road snapshot (the simulator's order of its
    vehicles, which highway-env's road and the fast simulator keep for the whole episode: a car keeps its index).
    ``escaped``: the cars outside the sets drawn for them, anywhere on the road, ``rolled_back`` those of them moving
    backwards (outside IDM, :func:`~safelane.safety.committed_sets.rolling_back`), ``unbraked_followers`` those ahead of
    the follower bound the kept plan drew for them (the follower law is an assumption, not IDM's: a follower far behind
    does not brake at its limit because the ego plans to), ``checked`` how many cars were checked against a set drawn at
    the last decision; ``entered``: those that entered a lane the ego holds since the last decision; ``ego_crashed``:
    the ego has crashed (its motion after an impact is no plan's); ``certified``: some plan is verified or kept;
    ``plans``: the verified plan of each action (None: none)."""

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

    def reset(self) -> None:
        """Forget the kept plan and the carried sets (a new episode)."""
        self.kept, self.kept_verified, self.carried, self.followers, self._pending = None, False, None, {}, None
        self.carried_ahead = None

    def evaluate(self, snap: RoadSnapshot, dyn: Dynamics, ego_leave_time: float) -> CommittedResult:
        """The verdict in the state of ``snap`` (see the class docstring)."""
        dyn = dataclasses.replace(dyn, ego_leave_time=ego_leave_time)
        state, vehicle = _whole_state(snap, dyn)
        return self.evaluate_state(
            state,
            vehicle,
            dyn,
            lambda: OneDecisionFamily("robust", self.engine).evaluate(snap, dyn, ego_leave_time),
            ego_crashed=bool(snap.crashed[snap.ego]),
        )

    def evaluate_state(
        self,
        state: RoadState,
        vehicle: np.ndarray,
        dyn: Dynamics,
        uncertified: Callable[[], SafetyResult] | None = None,
        ego_crashed: bool = False,
    ) -> CommittedResult:
        """:meth:`evaluate` on a :class:`RoadState` (every car, ``vehicle``: their identities, kept from one decision
        to the next) with ``dyn.ego_leave_time`` set; ``uncertified``: the one-decision robust rule's verdict in this
        state (default: the numpy reference's); ``ego_crashed``: the ego has crashed (a :class:`RoadState` holds
        the other cars' flags only)."""
        compiled = self.engine == "compiled"
        if compiled:  # the per-car quantities once, for the sets and the gaps
            prep = prepare(state, dyn)
            sets, cars = car_sets_compiled(state, dyn, vehicle, prep), car_arrays(state, dyn, prep)
        else:
            sets, cars = car_sets(state, dyn, vehicle), None
        escaped = np.zeros(state.n, dtype=bool)
        unbraked = np.zeros(state.n, dtype=bool)
        older: CarSets | None = None
        checked = 0
        entered = np.zeros(state.n, dtype=bool)
        if self.carried is not None:
            kept_held = self.kept.held if self.kept is not None else ()
            entered = _entered_held_lanes(state, self.carried, sets, vehicle, self.carried_ahead, kept_held)
            older = self.carried.shifted(dyn.frames_per_decision, dyn.decision_period)
            unbraked = self._followers_escaped(state, dyn, vehicle)
            escaped = escaped_cars(state, dyn, older, vehicle) | unbraked
            checked = int(np.isin(vehicle, older.vehicle).sum())
            sets = sets.intersect(older, ~escaped)
        worst, ego_x, ego_v, set_points = verify_plans(state, dyn, sets, self.engine, cars)
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
            args = (state, dyn, sets, ego_x[a, k : k + 1], ego_v[a, k : k + 1], np.array([tail.onset]),
                    list(tail.occupied), tail.frames, followers, set_points[a, k : k + 1],
                    tail.held)  # fmt: skip
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
        if not mask.any():  # no plan verified, none kept: uncertified, the one-decision robust rule drives
            robust = uncertified() if uncertified is not None else evaluate_one_decision(state, dyn, "robust")
            mask = robust.mask.copy()
        result = CommittedResult(
            mask, safe, available, not bool(safe.any()), best_gap, None,
            plan_forced=forced, lapse=lapse, lapse_cars=tuple(int(v) for v in vehicle[failed]),
            escaped=tuple(int(v) for v in vehicle[escaped]),
            rolled_back=tuple(int(v) for v in vehicle[rolling_back(state, escaped, older, vehicle)]), checked=checked,
            unbraked_followers=tuple(int(v) for v in vehicle[unbraked]),
            entered=tuple(int(v) for v in vehicle[entered]),
            ego_crashed=ego_crashed, certified=bool(safe.any()) or self.kept is not None, plans=tuple(plans),
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

    def _followers_escaped(self, state: RoadState, dyn: Dynamics, vehicle: np.ndarray) -> np.ndarray:
        """(cars,) the followers of the kept plan (a car behind the ego in a lane it held) still in that lane and
        ahead of the bound their reaction to the plan allowed."""
        out = np.zeros(state.n, dtype=bool)
        occupied = occupied_lanes(state, dyn)
        f = dyn.frames_per_decision
        for i, v in enumerate(vehicle):
            follower = self.followers.get(int(v))
            if follower is not None and occupied[i, follower[0]] and f < follower[1].size:
                out[i] = state.x[i] > follower[1][f] + ESCAPE_TOLERANCE
        return out


def _entered_held_lanes(
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
        for i in np.flatnonzero(sets.now[:, lane]):
            r = rows[i]
            if r < 0:
                continue
            passed = older_ahead is not None and not older_ahead[r] and ahead[i] and lane == in_lane
            out[i] |= not older.now[r, lane] or passed
    return out


def _followers_of(
    state: RoadState, dyn: Dynamics, sets: CarSets, vehicle: np.ndarray, plan: Plan, engine: Engine = "numpy"
) -> dict:
    """{snapshot index: (lane, highest position [m] per frame)} of the cars that follow the ego under ``plan``
    (:func:`plan_gaps`' follower law): the bound a lapse is traced against."""
    held = {state.ego_lane, state.ego_target_lane}
    t = dyn.times
    out: dict[int, tuple[int, np.ndarray]] = {}
    for lane, _ in plan.occupied:
        if lane not in held:
            continue
        own = state.lane_of(state.y, dyn.lanes_count, dyn.lane_width)
        for i in np.flatnonzero((state.x < state.ego_x) & (own == lane)):
            bound = (follower_bound_compiled if engine == "compiled" else follower_bound)(
                state, int(i), np.array([max(plan.onset + dyn.follower_reaction, 0.0)]), t)[0]  # fmt: skip
            out[int(vehicle[i])] = (lane, np.minimum(bound, sets.x_hi[i]))
    return out


def _whole_state(snap: RoadSnapshot, dyn: Dynamics) -> tuple[RoadState, np.ndarray]:
    """The road state with every other body at a finite position (no relevance range: that is the one-decision
    rule's, not a bound on a reachable set) and the snapshot index of each row."""
    others = snap.others(vehicles_only=False)
    bodies = others[np.isfinite(snap.longitudinal(snap.position[others]))]
    direction, lateral = snap.lane_direction, snap.lane_lateral
    lane_heading = math.atan2(direction[1], direction[0])
    base = road_state(snap, dyn.rule.ego_speed_magnitude)
    pos = snap.position[bodies] - snap.lane_origin
    heading = snap.heading[bodies] - lane_heading
    speed = snap.speed[bodies]
    state = dataclasses.replace(
        base, x=pos @ direction, y=pos @ lateral, vx=speed * np.cos(heading), vy=speed * np.sin(heading),
        heading=np.arctan2(np.sin(heading), np.cos(heading)), length=snap.length[bodies],
        crashed=snap.crashed[bodies], target_speed=snap.target_speed[bodies],
        **{name: getattr(snap, name)[bodies] for name in DRIVER_FIELDS},
    )  # fmt: skip
    return state, bodies
