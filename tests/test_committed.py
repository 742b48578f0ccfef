"""The committed shield (experimental, safelane.safety.committed): its reachable sets nest in time, a kept plan
stays verified while every car stays inside its set, a car that leaves its set is named at the lapse, and a state
with no verified plan is uncertified."""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safelane.core.spaces import FASTER, IDLE, SLOWER
from safelane.safety.committed.family import CommittedFamily
from safelane.safety.committed.sets import car_sets, envelope, lane_crossing_time, lane_entry_times, speed_bounds
from safelane.safety.ego import ego_trajectories
from safelane.safety.one_decision.reference import evaluate as evaluate_one_decision
from safelane.safety.world import Dynamics, RoadState

DYN = Dynamics(
    decision_period=1.0, frame_dt=0.2, frames_per_decision=5, ego_kp=1 / 0.6,
    target_speeds=tuple(5.0 * k for k in range(7)), lane_width=4.0, lanes_count=3, cut_in_time=0.2,
    ego_leave_time=1.0,
)  # fmt: skip
IDM_CAR: dict[str, Any] = dict(
    brake_max=6.0, accel_max=3.0, can_change_lane=True, idm_delta=4.0, idm_comfort_acc=3.0, idm_comfort_dec=-5.0,
    idm_distance_wanted=10.0, idm_time_wanted=1.5, max_braking_imposed=2.0, linear_speed_gain=np.nan,
    linear_speed_difference_gain=np.nan, linear_distance_gain=np.nan, target_speed=25.0, length=5.0, crashed=False,
    vx=0.0, vy=0.0, heading=0.0,
)  # fmt: skip
FLOATS = ("x", "y", "vx", "vy", "heading", "length", "brake_max", "accel_max", "idm_delta", "idm_comfort_acc",
          "idm_comfort_dec", "idm_distance_wanted", "idm_time_wanted", "max_braking_imposed", "linear_speed_gain",
          "linear_speed_difference_gain", "linear_distance_gain", "target_speed")  # fmt: skip


def scene(cars: list[dict[str, Any]], ego_x: float = 0.0, ego_speed: float = 20.0, set_point: float | None = None,
          ego_lane: int = 1, dyn: Dynamics = DYN) -> RoadState:  # fmt: skip
    """A straight road: the ego in ``ego_lane`` at ``ego_x`` [m], ``ego_speed`` [m/s]; IDM cars given by ``x``,
    ``lane`` and ``vx`` (and any other field)."""
    rows = [{**IDM_CAR, "y": c.get("lane", 1) * dyn.lane_width, **{k: v for k, v in c.items() if k != "lane"}}
            for c in cars]  # fmt: skip
    target = ego_speed if set_point is None else set_point
    return RoadState(
        ego_x=ego_x, ego_y=ego_lane * dyn.lane_width, ego_speed=ego_speed, ego_lane=ego_lane,
        ego_target_lane=ego_lane, ego_target_speed=target, ego_speed_index=round(target / 5.0),
        crashed=np.array([r["crashed"] for r in rows], dtype=bool),
        can_change_lane=np.array([r["can_change_lane"] for r in rows], dtype=bool),
        **{k: np.array([r[k] for r in rows], dtype=float) for k in FLOATS},
    )  # fmt: skip


def advance(x: float, v: float, accelerations: list[float], h: float, a: float, b: float, target: float):
    """A car's exact state after piecewise-constant accelerations (each ``h`` s, in [−b, a]) with its speed kept
    in the driver model's bounds (:func:`speed_bounds`): one history the model allows."""
    v_min, v_max = (float(z[0]) for z in speed_bounds(np.array([v]), np.array([target]), np.array([False])))
    for u in accelerations:
        if u >= 0:
            t_top = max(v_max - v, 0.0) / max(u, 1e-12)
            tt = min(h, t_top)
            x, v = x + v * tt + 0.5 * u * tt * tt + v_max * max(h - t_top, 0.0), min(v + u * h, v_max)
        else:
            t_low = max(v - v_min, 0.0) / -u
            tt = min(h, t_low)
            x, v = x + v * tt + 0.5 * u * tt * tt + v_min * max(h - t_low, 0.0), max(v + u * h, v_min)
    return x, v


@settings(max_examples=300, deadline=None)
@given(
    x=st.floats(-200, 200), v=st.floats(-3, 35), a=st.floats(0.5, 6), b=st.floats(1, 8), target=st.floats(0, 40),
    steps=st.integers(1, 10), fractions=st.lists(st.floats(0, 1), min_size=10, max_size=10),
    change=st.sampled_from([0.0, 1.66]),
)  # fmt: skip
def test_the_longitudinal_set_nests_in_time(x, v, a, b, target, steps, fractions, change) -> None:
    """R(s', [0, H−Δ]) ⊆ R(s, [Δ, H]) for every successor s' the driver model allows after Δ: positions and speeds,
    frame by frame — with the shortfall of the lane change a car driving straight may still begin (``change``
    [m] from the first frame on) in both sets. (A successor that has begun it is granted another: not nested by
    the state alone, closed by memory; docs/research/committed-plans.md.)"""
    h = 0.2
    t = np.arange(66) * h
    v_min, v_max = speed_bounds(np.array([v]), np.array([target]), np.array([False]))
    short = lambda times: np.where(times > 0.0, change, 0.0)[None, :]  # noqa: E731
    lo, hi, vlo, vhi = envelope(np.array([x]), np.array([v]), np.array([a]), np.array([b]), v_min, v_max, t,
                                short(t))  # fmt: skip
    x2, v2 = advance(x, v, [-b + f * (a + b) for f in fractions[:steps]], h, a, b, target)
    v_min2, v_max2 = speed_bounds(np.array([v2]), np.array([target]), np.array([False]))
    assert v_min2[0] >= v_min[0] and v_max2[0] <= v_max[0]
    lo2, hi2, vlo2, vhi2 = envelope(np.array([x2]), np.array([v2]), np.array([a]), np.array([b]), v_min2, v_max2,
                                    t[: t.size - steps], short(t[: t.size - steps]))  # fmt: skip
    tol = 1e-7 * (1 + abs(x))
    assert (lo2[0] >= lo[0, steps:] - tol).all() and (hi2[0] <= hi[0, steps:] + tol).all()
    assert (vlo2[0] >= vlo[0, steps:] - 1e-9).all() and (vhi2[0] <= vhi[0, steps:] + 1e-9).all()
    # ...and the successor itself is inside the set at Δ
    assert lo[0, steps] - tol <= x2 <= hi[0, steps] + tol


def test_an_inadmissible_successor_breaks_the_nesting() -> None:
    """The property test above can fail: a car that brakes harder than its model allows is outside the set."""
    t = np.arange(66) * 0.2
    v_min, v_max = speed_bounds(np.array([20.0]), np.array([25.0]), np.array([False]))
    lo, *_ = envelope(np.array([0.0]), np.array([20.0]), np.array([3.0]), np.array([6.0]), v_min, v_max, t)
    x2, _ = advance(0.0, 20.0, [-9.0] * 5, 0.2, 3.0, 9.0, 25.0)
    assert x2 < lo[0, 5]


@settings(max_examples=200, deadline=None)
@given(
    start=st.integers(0, 4), moved=st.integers(-4, 4), extra=st.floats(0, 3), cut_in=st.sampled_from([0.0, 0.2, 0.4]),
)  # fmt: skip
def test_the_lanes_a_car_can_reach_nest_in_time(start, moved, extra, cut_in) -> None:
    """A car centred in lane ``start``, centred ``moved`` lanes over after Δ (each lane boundary crossed takes at
    least the crossing time), may enter no lane earlier, counted from the first state, than the first set allows."""
    dyn = dataclasses.replace(DYN, lanes_count=5, cut_in_time=cut_in)
    end = start + moved
    if not 0 <= end < dyn.lanes_count:
        return
    delta = abs(moved) * lane_crossing_time(dyn) + extra
    before = lane_entry_times(scene([{"x": 50.0, "lane": start}], dyn=dyn), dyn)[0]
    after = lane_entry_times(scene([{"x": 50.0, "lane": end}], dyn=dyn), dyn)[0]
    assert (delta + after >= before - 1e-9).all()
    assert before[end] <= delta + 1e-9  # the successor itself is inside the set at Δ


def _car_state(car: Any, dyn: Dynamics) -> RoadState:
    """The :class:`RoadState` of one highway-env car on a straight road (the ego far behind, never in reach)."""
    h = float(car.heading)
    return scene([{"x": float(car.position[0]), "y": float(car.position[1]), "vx": car.speed * math.cos(h),
                   "vy": car.speed * math.sin(h), "heading": h, "brake_max": 6.0, "accel_max": 6.0,
                   "target_speed": np.nan}], ego_x=-10_000.0, dyn=dyn)  # fmt: skip


@settings(max_examples=200, deadline=None)
@given(
    v=st.floats(-2, 35), target=st.floats(5, 35), gain=st.floats(0.02, 0.5), idm=st.booleans(),
    hz=st.sampled_from([5, 10, 15]), steps=st.integers(1, 10), fractions=st.lists(st.floats(0, 1), min_size=10,
                                                                                   max_size=10),
)  # fmt: skip
def test_the_acceleration_law_bound_nests_in_time(v, target, gain, idm, hz, steps, fractions) -> None:
    """A driver accelerating at most ``min(a, law)`` toward its set-point (linear ``k·(v* − v)`` or IDM's free
    term): from any successor the bound allows after Δ frames, the bound of speed and position is inside the
    first one's from Δ on, and the successor itself inside it at Δ."""
    from safelane.safety.committed.sets import law_rise

    dt = 1.0 / hz
    car = {"x": 0.0, "vx": v, "target_speed": target, "accel_max": 3.0 if idm else 6.0}
    if not idm:
        car |= {"linear_speed_gain": gain, "linear_speed_difference_gain": 0.1, "linear_distance_gain": 0.5}
    first = scene([car])
    speed, dist = law_rise(first, np.array([v]), 40, dt)
    x, u = 0.0, v
    for f in fractions[:steps]:  # a history inside the law: a fraction of the largest acceleration it allows
        law = gain * (target - u) if not idm else 3.0 * (1 - (max(u, 0.0) / target) ** 4.0)
        x, u = x + dt * max(u, 0.0), u + dt * f * min(car["accel_max"], max(law, 0.0))
    assert u <= speed[0, steps] + 1e-9 and x <= dist[0, steps] + 1e-9
    speed2, dist2 = law_rise(scene([{**car, "x": x, "vx": u}]), np.array([u]), 40 - steps, dt)
    assert (speed2[0] <= speed[0, steps:] + 1e-9).all()
    assert (x + dist2[0] <= dist[0, steps:] + 1e-9).all()


@pytest.mark.parametrize("driver", ["IDMVehicle", "LinearVehicle", "AggressiveVehicle", "DefensiveVehicle"])
@pytest.mark.parametrize("hz", [5, 15])
def test_a_driver_stays_below_its_acceleration_law(driver: str, hz: int) -> None:
    """highway-env's drivers on one lane — free, then behind a slower car — stay below the speed and position
    their own acceleration law allows (:func:`~safelane.safety.committed.sets.law_rise`, inside :func:`car_sets`),
    which the linear models reach far below their ACC_MAX bound."""
    from highway_env.road.road import Road, RoadNetwork
    from highway_env.vehicle import behavior

    cls = getattr(behavior, driver)
    dyn = dataclasses.replace(DYN, frame_dt=1.0 / hz, frames_per_decision=hz, lanes_count=1)
    network = RoadNetwork.straight_road_network(1, length=10_000.0)
    road = Road(network, np_random=np.random.RandomState(0))
    car = cls(road, np.array([0.0, 0.0]), speed=12.0, target_speed=28.0, enable_lane_change=False)
    slow = behavior.IDMVehicle(road, np.array([150.0, 0.0]), speed=15.0, target_speed=15.0)
    road.vehicles = [car, slow]
    gains = getattr(car, "ACCELERATION_PARAMETERS", [np.nan] * 3) if driver != "IDMVehicle" else [np.nan] * 3
    fields = dict(brake_max=cls.ACC_MAX, accel_max=cls.COMFORT_ACC_MAX if driver == "IDMVehicle" else cls.ACC_MAX,
                  idm_delta=car.DELTA, idm_comfort_acc=cls.COMFORT_ACC_MAX, linear_speed_gain=gains[0],
                  linear_speed_difference_gain=gains[1], linear_distance_gain=gains[2], target_speed=28.0)  # fmt: skip
    states = []
    for _ in range(20 * hz):
        states.append(scene([{"x": car.position[0], "y": 0.0, "vx": car.speed, **fields}], ego_x=-1e4,
                            ego_lane=0, dyn=dyn))  # fmt: skip
        road.act()
        road.step(1.0 / hz)
    v_top = max(s.vx[0] for s in states)
    plain = []
    for k0 in range(0, len(states), hz):
        sets = car_sets(states[k0], dyn, np.array([0]))
        for k in range(k0, min(len(states), k0 + dyn.times.size)):
            assert states[k].x[0] <= sets.x_hi[0, k - k0] + 1e-6 and states[k].vx[0] <= sets.v_hi[0, k - k0] + 1e-6
        plain.append(sets.x_hi[0, -1] - states[k0].x[0])
    assert 15.0 < v_top < 28.0
    without = dict(fields, linear_speed_gain=np.nan, target_speed=np.nan, idm_comfort_acc=0.0)  # no law: the bound
    assert car_sets(scene([{"x": 0.0, "vx": 12.0, **without}], dyn=dyn), dyn, np.array([0])).x_hi[0, -1] > plain[0]


def _lane_changing_car(hz: int, v0: float, accel: float, changes: int) -> list[Any]:
    """Frames of a highway-env ControlledVehicle on a straight 3-lane road from the middle lane at ``v0`` [m/s],
    accelerating at ``accel`` [m/s²] (braking to a stop, or up to 30 m/s), changing lane ``changes`` times, each
    as soon as the last is over and its timer (``LANE_CHANGE_DELAY``, 1 s) lets it: its states, one per frame."""
    from highway_env.road.road import Road, RoadNetwork
    from highway_env.vehicle.controller import ControlledVehicle

    dyn = dataclasses.replace(DYN, frame_dt=1.0 / hz, frames_per_decision=hz, lanes_count=3)
    network = RoadNetwork.straight_road_network(3, length=10_000.0)
    road = Road(network, np_random=np.random.RandomState(0))
    car = ControlledVehicle(road, network.get_lane(("0", "1", 1)).position(0.0, 0.0), speed=v0)
    road.vehicles = [car]
    states, lane, since, done = [], 1, 1.0, 0
    for _ in range(8 * hz):
        states.append(_car_state(car, dyn))
        since += 1.0 / hz
        if done < changes and since > 1.0 and car.lane_index == car.target_lane_index:
            lane = 2 if lane != 2 else 0  # across the road and back
            car.target_lane_index = ("0", "1", lane)
            since, done = 0.0, done + 1
        car.act()
        car.action["acceleration"] = accel if (accel < 0 < car.speed) or (accel >= 0 and car.speed < 30.0) else 0.0
        car.step(1.0 / hz)
        car.speed = max(car.speed, 0.0)
    return states


def _outside(states: list[RoadState], dyn: Dynamics, hz: int) -> int:
    """How many (decision, frame) pairs find the car outside the set drawn for it at the decision (position along
    the road, speed along the path)."""
    from safelane.safety.committed.sets import path_speed

    out = 0
    for k0 in range(0, len(states), hz):
        sets = car_sets(states[k0], dyn, np.array([0]))
        for k in range(k0, min(len(states), k0 + dyn.times.size)):
            s, f = states[k], k - k0
            out += not (sets.x_lo[0, f] - 1e-6 <= s.x[0] <= sets.x_hi[0, f] + 1e-6)
            out += not (sets.v_lo[0, f] - 1e-6 <= path_speed(s)[0] <= sets.v_hi[0, f] + 1e-6)
    return out


@pytest.mark.parametrize("hz", [5, 15])
@pytest.mark.parametrize(("v0", "accel"), [(25.0, -6.0), (15.0, 6.0), (8.0, -3.0), (30.0, 0.0)])
def test_a_car_changing_lane_stays_inside_the_sets_drawn_for_it(hz: int, v0: float, accel: float) -> None:
    """highway-env's own controller moves a car along ``heading + β`` at its speed along the path: a car changing
    lane (and, from a frame inside the change, the change under way) while braking or accelerating at its limits
    stays inside every set drawn for it at any earlier decision — position along the road and speed along the
    path — although its speed along the road falls faster than any driver brakes."""
    dyn = dataclasses.replace(DYN, frame_dt=1.0 / hz, frames_per_decision=hz, lanes_count=3)
    states = _lane_changing_car(hz, v0, accel, changes=1)
    assert _outside(states, dyn, hz) == 0
    drops = [(a.vx[0] - b.vx[0]) * hz for a, b in itertools.pairwise(states)]
    assert max(drops) > 1.0 - accel  # its speed along the road falls faster than its speed along the path


def test_a_second_lane_change_within_the_horizon_leaves_the_set() -> None:
    """The sets count the lane change under way and one more (``LANE_CHANGES_BEGUN``): a car that goes across the
    road and back within the horizon at its timer's pace is outside them — the set can fail, and names it."""
    dyn = dataclasses.replace(DYN, lanes_count=3)
    assert _outside(_lane_changing_car(5, 25.0, -6.0, changes=3), dyn, 5) > 0


# --------------------------------------------------------------------------------------------
# Scenes.
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("distance", "verified"), [(60.0, [SLOWER]), (80.0, [IDLE, SLOWER]), (40.0, [])])
def test_a_stopped_car_ahead(distance: float, verified: list[int]) -> None:
    """One lane, the ego at 20 m/s, a stopped car ahead: FASTER is never verified; SLOWER from 60 m, IDLE from 80;
    at 40 m nothing is (an uncertified state)."""
    dyn = dataclasses.replace(DYN, lanes_count=1)
    state = scene([{"x": distance, "lane": 0}], ego_lane=0, dyn=dyn)
    result = CommittedFamily().evaluate_state(state, np.array([7]), dyn)
    assert np.flatnonzero(result.safe).tolist() == verified
    if verified:
        assert result.mask.tolist() == result.safe.tolist() and not result.fallback
    assert not result.safe[FASTER]


def _followed(state: RoadState, dyn: Dynamics, action: int, hold: int) -> tuple[float, float, float]:
    """The ego's position [m], speed [m/s] and set-point [m/s] one decision into plan (``action``, ``hold``)."""
    xs, vs = ego_trajectories(state, dyn)
    f = dyn.frames_per_decision
    set_point = {FASTER: state.ego_target_speed + 5.0, SLOWER: state.ego_target_speed - 5.0}.get(
        action, state.ego_target_speed
    )
    return float(xs[action, hold, f]), float(vs[action, hold, f]), set_point


LEADER = [{"x": 70.0, "lane": 1, "vx": 20.0}]


@settings(max_examples=40, deadline=None)
@given(fractions=st.lists(st.floats(0, 1), min_size=5, max_size=5))
def test_a_kept_plan_stays_verified_while_the_cars_stay_in_their_sets(fractions) -> None:
    """FASTER is verified behind a leader 70 m ahead; after it, whatever the leader does within its model (here
    any acceleration history between −6 m/s² and IDM's free term), the kept plan's tail still verifies: no lapse,
    and its next step is allowed, with a worst gap no smaller than when it was kept."""
    state = scene(LEADER)
    family = CommittedFamily()
    first = family.evaluate_state(state, np.array([0]), DYN)
    assert first.safe[FASTER]
    plan = first.plans[FASTER]
    family.commit(FASTER)
    ego_x, ego_v, set_point = _followed(state, DYN, FASTER, plan.hold)
    x, v = 70.0, 20.0
    for f in fractions:  # highway-env's Euler frames, the acceleration anywhere IDM lets it be (its free term on top)
        top = min(3.0, max(3.0 * (1.0 - (max(v, 0.0) / 25.0) ** 4), 0.0))
        x, v = x + 0.2 * v, max(v + 0.2 * (-6.0 + f * (6.0 + top)), 0.0)
    after = scene([{"x": x, "lane": 1, "vx": v}], ego_x=ego_x, ego_speed=ego_v, set_point=set_point)
    result = family.evaluate_state(after, np.array([0]), DYN)
    assert not result.lapse and not result.escaped and not result.plan_forced
    assert result.mask[plan.next_step()]
    assert result.min_gap[plan.next_step()] >= first.min_gap[FASTER] - 1e-6


def test_a_car_leaving_its_set_makes_a_lapse_that_names_it() -> None:
    """The same plan, but the leader stops dead 12 m ahead of the ego one decision later (no driver model brakes
    so hard): a lapse, the leader named, nothing verified, and the kept plan's next step (SLOWER) drives."""
    state = scene([*LEADER, {"x": -30.0, "lane": 0, "vx": 20.0}])
    family = CommittedFamily()
    first = family.evaluate_state(state, np.array([4, 9]), DYN)
    plan = first.plans[FASTER]
    assert plan is not None and plan.next_step() == SLOWER
    family.commit(FASTER)
    ego_x, ego_v, set_point = _followed(state, DYN, FASTER, plan.hold)
    after = scene([{"x": ego_x + 12.0, "lane": 1, "vx": 0.0}, {"x": -10.0, "lane": 0, "vx": 20.0}],
                  ego_x=ego_x, ego_speed=ego_v, set_point=set_point)  # fmt: skip
    result = family.evaluate_state(after, np.array([4, 9]), DYN)
    assert result.lapse and result.escaped == (4,) and not result.lapse_in_model
    assert result.plan_forced and result.mask.tolist() == [False, False, False, False, True]
    assert result.fallback and not result.safe.any() and result.certified


def test_a_lapse_names_the_cars_that_failed_the_plan_not_every_car_outside_its_set() -> None:
    """The leader stops dead 12 m ahead (outside its set; the kept plan fails on it) while a car 500 m ahead brakes
    10 m/s in one second (outside its set too, far from the plan): the lapse names the leader alone, and of it
    that it left its set; the far car is among the escapes, not a cause."""
    state = scene([*LEADER, {"x": 500.0, "lane": 1, "vx": 25.0}])
    family = CommittedFamily()
    first = family.evaluate_state(state, np.array([4, 9]), DYN)
    plan = first.plans[FASTER]
    assert plan is not None
    family.commit(FASTER)
    ego_x, ego_v, set_point = _followed(state, DYN, FASTER, plan.hold)
    after = scene([{"x": ego_x + 12.0, "lane": 1, "vx": 0.0}, {"x": 500.0 + 20.0, "lane": 1, "vx": 15.0}],
                  ego_x=ego_x, ego_speed=ego_v, set_point=set_point)  # fmt: skip
    result = family.evaluate_state(after, np.array([4, 9]), DYN)
    assert result.lapse and result.escaped == (4, 9)
    assert result.lapse_cars == (4,) and result.lapse_escaped == (4,) and not result.lapse_in_model
    # The same far car, the leader braking within its model: no lapse, nobody named, the far car still escaped.
    family = CommittedFamily()
    family.evaluate_state(state, np.array([4, 9]), DYN)
    family.commit(FASTER)
    inside = scene([{"x": 70.0 + 20.0, "lane": 1, "vx": 20.0}, {"x": 500.0 + 20.0, "lane": 1, "vx": 15.0}],
                   ego_x=ego_x, ego_speed=ego_v, set_point=set_point)  # fmt: skip
    result = family.evaluate_state(inside, np.array([4, 9]), DYN)
    assert not result.lapse and result.lapse_cars == () and result.escaped == (9,)


def test_a_lapse_in_the_model_is_one_a_car_inside_its_set_failed() -> None:
    """``lapse_in_model``: a lapse with a car the kept plan fails on that is inside its set and
    entered no lane the ego holds, or with no car named; a car outside its set elsewhere traces nothing."""
    base = CommittedFamily().evaluate_state(scene(LEADER), np.array([4]), DYN)

    def lapse(**fields: Any) -> bool:
        return dataclasses.replace(base, lapse=True, **fields).lapse_in_model

    assert not lapse(lapse_cars=(4,), escaped=(4,))
    assert not lapse(lapse_cars=(4,), entered=(4,))  # a cut-in: its gap to keep
    assert lapse(lapse_cars=(4,), escaped=(9,))  # the car that broke the plan was inside its set
    assert lapse(lapse_cars=(4, 5), escaped=(4,))  # one of two traced: the other is a gap in the construction
    assert lapse(lapse_cars=())  # a lapse no car explains
    assert not lapse(lapse_cars=(4,), escaped=(9,), ego_crashed=True)  # the impact moved the ego off its plan
    assert not dataclasses.replace(base, lapse=False, lapse_cars=(4,)).lapse_in_model


def test_cars_braking_at_their_limit_stay_in_their_sets_and_a_lapse_names_the_cut_in() -> None:
    """The fast preset, seeds 3 and 9, one decision of IDLE: cars 480–1 000 m ahead turn and
    brake at exactly ``ACC_MAX`` (6 m/s in 1 s along their path), inside the sets drawn for them (the speed along
    the path and a lane change's shortfall; the speed along the road left them); the lapse names the one car that
    entered the ego's lane and broke the plan, not the others that entered a lane the ego holds far ahead."""
    from safelane.env.factory import make_env

    env = make_env("fast", simulator="fast", **{"shield.mode": "committed", "shield.override": True})
    for seed, car in ((3, 2), (9, 1)):
        _, info = env.reset(seed=seed)
        before = info["snapshot"]
        _, _, _, _, info = env.step(IDLE)
        after = info["snapshot"]
        braked = np.flatnonzero(after.speed - before.speed <= -6.0 + 1e-9)
        assert braked.size and (after.position[braked, 0] - after.position[after.ego, 0] > 400.0).all()
        assert info["escaped_cars"] == ()
        assert info["lapse"] and info["lapse_cars"] == (car,) and info["lapse_escaped_cars"] == ()
        assert car in info["entered_cars"] and len(info["entered_cars"]) > 1 and not info["lapse_in_model"]
    env.close()


def test_a_car_rolling_back_is_named_outside_the_model() -> None:
    """A jammed car 150 m ahead rolling back at 0.5 m/s: one decision later it has rolled 3 m back and moves forward
    again — outside the set drawn for it (its lowest position) and named as rolled back; a car that braked harder
    than its model allows is outside its set but not rolled back."""
    state = scene([{"x": 150.0, "lane": 1, "vx": -0.5}, {"x": 60.0, "lane": 0, "vx": 20.0}])
    family = CommittedFamily()
    first = family.evaluate_state(state, np.array([3, 8]), DYN)
    family.commit(int(np.flatnonzero(first.safe)[0]))
    after = scene([{"x": 147.0, "lane": 1, "vx": 0.5}, {"x": 60.0 + 12.0, "lane": 0, "vx": 10.0}], ego_x=20.0)
    result = family.evaluate_state(after, np.array([3, 8]), DYN)
    assert result.escaped == (3, 8) and result.rolled_back == (3,)


def test_a_state_with_no_verified_plan_is_an_uncertified_start() -> None:
    """A stopped car 8 m ahead, cars beside in both next lanes: no plan verifies; with none kept the state is
    uncertified and the one-decision robust rule's mask drives."""
    cars = [{"x": 8.0, "lane": 1}, {"x": 0.0, "lane": 0, "vx": 20.0}, {"x": 0.0, "lane": 2, "vx": 20.0}]
    state = scene(cars)
    result = CommittedFamily().evaluate_state(state, np.arange(3), DYN)
    assert not result.safe.any() and not result.certified and result.fallback
    assert not result.plan_forced and not result.lapse
    assert result.mask.tolist() == evaluate_one_decision(state, DYN, "robust").mask.tolist()


def test_a_follower_that_does_not_brake_for_the_plan_is_named() -> None:
    """The follower law is an assumption, not IDM's: a follower that keeps accelerating at its limit while the ego
    carries out a plan that brakes leaves the bound drawn for it — named as an unbraked follower (and escaped),
    though inside its envelope."""
    state = scene([*LEADER, {"x": -40.0, "lane": 1, "vx": 20.0}])
    family = CommittedFamily()
    first = family.evaluate_state(state, np.arange(2), DYN)
    action = SLOWER if first.safe[SLOWER] else IDLE
    plan = first.plans[action]
    assert plan is not None
    family.commit(action)
    ego_x, ego_v, set_point = _followed(state, DYN, action, plan.hold)
    cars = [{"x": 70.0 + 20.0, "lane": 1, "vx": 20.0}, {"x": -40.0 + 20.0 + 1.5, "lane": 1, "vx": 23.0}]
    result = family.evaluate_state(scene(cars, ego_x=ego_x, ego_speed=ego_v, set_point=set_point), np.arange(2), DYN)
    assert result.unbraked_followers == (1,) and result.escaped == (1,)


def test_a_car_behind_in_the_egos_lane_is_its_drivers_to_avoid() -> None:
    """A fast car 15 m behind in the ego's lane does not count: IDLE is verified (the gap it closes is its
    driver's)."""
    state = scene([*LEADER, {"x": -15.0, "lane": 1, "vx": 30.0}])
    assert CommittedFamily().evaluate_state(state, np.arange(2), DYN).safe[IDLE]


def test_a_car_beside_the_ego_in_the_lane_it_is_entering_is_the_egos_to_keep_clear_of() -> None:
    """The ego, still in lane 1 (its centre nearer lane 1's), changing into lane 2 beside a faster car 4 m behind
    in lane 2: going on (IDLE keeps the target lane) is not verified — the car is in the lane the ego is entering,
    not behind it in its own lane. Once the ego is in lane 2, a car behind it there is its driver's to avoid
    again."""
    car = {"x": -4.0, "lane": 2, "vx": 27.0}
    entering = dataclasses.replace(scene([car]), ego_y=1.4 * DYN.lane_width, ego_target_lane=2)
    assert not CommittedFamily().evaluate_state(entering, np.arange(1), DYN).safe[IDLE]
    inside = scene([{**car, "x": -15.0}], ego_lane=2)
    assert CommittedFamily().evaluate_state(inside, np.arange(1), DYN).safe[IDLE]


def test_a_car_that_overtakes_the_ego_while_it_may_turn_in_is_a_cut_in() -> None:
    """A car beside and behind the ego, turning toward its lane, does not count when IDLE is
    kept; a decision later it has passed the ego and counts: the kept plan fails on it, a lapse traced to a car that
    cut in after the plan was drawn (``entered``), not a gap in the construction."""
    turning = {"lane": 2, "y": 7.0, "vx": 30.0, "vy": -1.0, "heading": -0.05, "target_speed": 35.0}
    before = scene([{**turning, "x": -8.0}])
    family = CommittedFamily()
    first = family.evaluate_state(before, np.array([4]), DYN)
    assert first.safe[IDLE]
    family.commit(IDLE)
    after = scene([{**turning, "x": 22.0, "y": 6.2}], ego_x=20.0)
    result = family.evaluate_state(after, np.array([4]), DYN)
    assert result.lapse and result.lapse_cars == (4,) and not result.escaped
    assert result.entered == (4,) and not result.lapse_in_model


def test_the_shield_reports_the_committed_mode() -> None:
    """``shield.mode: committed``: the info keys; ``shield.reading`` accepted at ``responsibility`` only (older
    specs name it), ``sound`` refused in one line."""
    from safelane.config import ConfigError
    from safelane.env.factory import make_env
    from safelane.env.scenarios import find_shield

    env = make_env("fast", simulator="fast", **{"shield.mode": "committed", "shield.reading": "responsibility",
                                                "shield.override": True, "env.vehicles_count": 5})  # fmt: skip
    _, info = env.reset(seed=3)
    assert isinstance(info["uncertified_start"], bool)
    family = find_shield(env).family
    assert isinstance(family, CommittedFamily)
    for _ in range(3):
        _, _, _, _, info = env.step(FASTER)
        assert {"plan_forced", "lapse", "lapse_in_model", "escaped_cars", "certified"} <= set(info)
    env.close()
    # The fast batch runs the committed mode (a family per environment), but not the redrawing of spawns.
    from safelane.config import load_config
    from safelane.env.fast_batch import supports

    assert supports(load_config("fast", overrides={"shield.mode": "committed", "simulator": "fast"})) is None
    redraw = {"shield.mode": "committed", "simulator": "fast", "shield.redraw_uncertified": True}
    assert "shield.redraw_uncertified" in (supports(load_config("fast", overrides=redraw)) or "")
    for removed in ("sound", "lenient"):
        with pytest.raises(ConfigError, match=r"^shield\.reading: 'sound' was removed .*5 %.*responsibility") as err:
            make_env("fast", **{"shield.mode": "committed", "shield.reading": removed})
        assert "\n" not in str(err.value)
