"""The robust rule over a mixture of driver types (:mod:`safelane.safety.driver_sets`,
:mod:`safelane.safety.one_decision.over_types`): a hand-built state that the per-field reading judged looser than one
of the types, one reading as the reference to the bit, and robust inside every assignment of types on recorded
hidden-types states."""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from safelane.core.drivers import IDM_PARAMETERS, parse_driver_mix
from safelane.core.snapshot import RoadSnapshot
from safelane.safety.belief import DriverTypes
from safelane.safety.driver_sets import type_reading, type_readings
from safelane.safety.one_decision.family import OneDecisionFamily
from safelane.safety.one_decision.over_types import evaluate_readings
from safelane.safety.one_decision.reference import evaluate
from safelane.safety.road import road_state
from safelane.safety.shield import SafetyShield, dynamics_of, ego_leave_time_of

MIX = parse_driver_mix("timid-normal-aggressive")
TYPES = tuple(IDM_PARAMETERS[t] for t in MIX.types)
SET_POINTS = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0)  # [m/s] stoppable_action_config's


def scene(x: list[float], v: list[float], lane: list[int], kinds: list[int], ego_index: int) -> RoadSnapshot:
    """A straight 4-lane road at one decision a second, 5 frames; body 0 the ego at set-point ``SET_POINTS[ego_index]``,
    the others drawn cars of the types ``kinds``, reporting highway-env's IDMVehicle (the hidden arm's snapshot)."""
    n = len(x)
    pos = np.column_stack([np.asarray(x, float), np.asarray(lane, float) * 4.0])
    return RoadSnapshot(
        time=0.0, policy_frequency=1.0, simulation_frequency=5.0, lanes_count=4, lane_width=4.0,
        lane_origin=np.zeros(2), lane_direction=np.array([1.0, 0.0]), lane_lateral=np.array([0.0, 1.0]),
        speed_limit=30.0, ego=0, ego_target_speed=SET_POINTS[ego_index], ego_speed_index=ego_index,
        ego_target_speeds=SET_POINTS, ego_kp=0.6, ego_lane_offset=0.0, position=pos, speed=np.asarray(v, float),
        heading=np.zeros(n), target_speed=np.asarray(v, float), lane=np.asarray(lane), target_lane=np.asarray(lane),
        length=np.full(n, 5.0), width=np.full(n, 2.0), crashed=np.zeros(n, bool), is_vehicle=np.ones(n, bool),
        brake_max=np.full(n, 6.0), accel_max=np.full(n, 3.0), can_change_lane=np.ones(n, bool),
        idm_delta=np.full(n, 4.0), idm_comfort_acc=np.full(n, 3.0), idm_comfort_dec=np.full(n, -5.0),
        idm_distance_wanted=np.full(n, 10.0), idm_time_wanted=np.full(n, 1.5), max_braking_imposed=np.full(n, 2.0),
        linear_speed_gain=np.full(n, np.nan), linear_speed_difference_gain=np.full(n, np.nan),
        linear_distance_gain=np.full(n, np.nan), politeness=np.zeros(n), driver_type=np.array([-1, *kinds]),
    )  # fmt: skip


class _Still(gym.Env):  # type: ignore[misc]
    """An environment showing one snapshot (the shield reads nothing else)."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,))
    action_space = gym.spaces.Discrete(5)

    def __init__(self, snap: RoadSnapshot) -> None:
        self.snap = snap

    def road_snapshot(self, refresh: bool = False) -> RoadSnapshot:
        return self.snap

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        return np.zeros(1), {"snapshot": self.snap}


def _mask(snap: RoadSnapshot, mode: str) -> tuple[list[int], list[int]]:
    shield = SafetyShield(_Still(snap), mode=mode, driver_types=DriverTypes(MIX))  # type: ignore[arg-type]
    _, info = shield.reset()
    result = shield.result
    assert result is not None
    return result.safe.astype(int).tolist(), info["action_mask"].astype(int).tolist()


def test_an_aggressive_follower_the_per_field_reading_let_through() -> None:
    """The ego (15 m/s, lane 1) and an aggressive car 50 m behind it at 7 m/s. The rule bounds the car right behind
    the ego by IDM with its free-road term at its largest, ``a·(1 − (d*/d)²)``: an aggressive car (a = 2 m/s²) closes
    in over the horizon while the ego brakes to a stop. The per-field reading gave every car the least comfort
    acceleration (timid's 0.8) with the other fields' most adverse values, and allowed FASTER; the aggressive type
    forbids it, and so do the robust shield (every type) and the omniscient one (the car's own)."""
    snap = scene([100.0, 50.0], [15.0, 7.0], [1, 1], [2], ego_index=3)
    dyn = dynamics_of(snap)
    leave = ego_leave_time_of(snap, dyn)
    family = OneDecisionFamily("robust")
    chimera = dataclasses.replace(
        snap, accel_max=np.array([3.0, 2.0]), idm_comfort_acc=np.array([3.0, 0.8]),
        idm_comfort_dec=np.array([-5.0, -6.0 / 0.8]), idm_distance_wanted=np.array([10.0, 5.0]),
        idm_time_wanted=np.array([1.5, 1.0]), max_braking_imposed=np.array([2.0, 3.0]),
    )  # fmt: skip
    assert family.evaluate(chimera, dyn, leave).safe.astype(int).tolist() == [1, 0, 1, 1, 0]
    aggressive = type_reading(snap, TYPES, np.array([2]), np.array([1]), np.array([2.0]))
    assert family.evaluate(aggressive, dyn, leave).safe.astype(int).tolist() == [1, 0, 1, 0, 0]
    assert _mask(snap, "omniscient") == ([1, 0, 1, 0, 0], [1, 0, 1, 0, 0])
    assert _mask(snap, "robust") == ([1, 0, 1, 0, 0], [1, 0, 1, 0, 0])


def test_readings_one_per_type_a_car_may_be_among_others() -> None:
    """Car 1 may be timid only, car 2 timid or aggressive, car 3 any type: one reading per type, each car read as
    that type where it may be it (else as its most likely type, the first on ties), ``accel_max`` the largest a of
    its allowed types; the most likely reading each car's own a; a single reading when every car has one type."""
    snap = scene([100.0, 130.0, 160.0, 190.0], [25.0] * 4, [1] * 4, [0, 2, 1], ego_index=5)
    allowed = np.array([[1, 1, 1], [1, 0, 0], [1, 0, 1], [1, 1, 1]], bool)
    cars = np.array([1, 2, 3])
    weight = np.full((4, 3), 1 / 3)
    readings, likely = type_readings(snap, TYPES, allowed, cars, weight)
    a = [t.comfort_acc_max for t in TYPES]
    assert len(readings) == 3
    for k, reading in enumerate(readings):
        read_as = [0, k if k != 1 else 0, k]
        assert reading.idm_comfort_acc[1:].tolist() == [a[t] for t in read_as]
        assert reading.idm_time_wanted[1:].tolist() == [TYPES[t].time_wanted for t in read_as]
        assert reading.accel_max[1:].tolist() == [0.8, 2.0, 2.0]
        assert reading.idm_comfort_dec[0] == snap.idm_comfort_dec[0] and reading.position is snap.position
    assert likely.accel_max[1:].tolist() == [0.8, 0.8, 0.8]
    one, only = type_readings(snap, TYPES, np.eye(3, dtype=bool)[[0, 0, 2, 1]], cars, weight)
    assert len(one) == 1 and one[0] is only and only.accel_max[1:].tolist() == [0.8, 2.0, 1.4]


@pytest.fixture(scope="module")
def recorded() -> list[tuple[RoadSnapshot, SafetyShield]]:
    """Hidden-types states from two short fast-simulator episodes (the ego always FASTER under the omniscient
    shield), with a robust shield to judge them."""
    from safelane.env.factory import make_env

    env = make_env("hidden-types", simulator="fast", **{"shield.mode": "omniscient", "shield.override": True})
    robust = SafetyShield(env.unwrapped, mode="robust", driver_types=DriverTypes(env.get_wrapper_attr("driver_mix")))
    states = []
    for seed in (3, 4):
        _, info = env.reset(seed=seed)
        for _ in range(12):
            states.append(info["snapshot"])
            _, _, term, trunc, info = env.step(3)
            if term or trunc:
                break
    robust.dynamics = env.get_wrapper_attr("dynamics")
    env.close()
    return [(s, robust) for s in states]


def test_one_reading_is_the_reference_to_the_bit(recorded: list[tuple[RoadSnapshot, SafetyShield]]) -> None:
    for snap, shield in recorded[::4]:
        assert shield.dynamics is not None
        dyn = dataclasses.replace(shield.dynamics, ego_leave_time=shield.ego_leave_time(snap))
        state = road_state(snap)
        want, got = evaluate(state, dyn), evaluate_readings([state], state, dyn)
        assert np.array_equal(want.mask, got.mask) and np.array_equal(want.safe, got.safe)
        assert want.fallback == got.fallback and np.array_equal(want.min_gap, got.min_gap)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_robust_is_inside_every_assignment_of_types(
    recorded: list[tuple[RoadSnapshot, SafetyShield]], data: st.DataObject
) -> None:
    """On recorded states, any assignment of the three types to the cars (the true one among them): the robust
    shield's safe actions are safe under it, robust falls back wherever it does, and where neither falls back
    robust's mask is inside its mask."""
    snap, shield = data.draw(st.sampled_from(recorded))
    cars = snap.others()
    kinds = np.array(data.draw(st.lists(st.integers(0, 2), min_size=cars.size, max_size=cars.size)))
    assert shield.dynamics is not None
    leave = shield.ego_leave_time(snap)
    accel = np.array([TYPES[k].comfort_acc_max for k in kinds])
    assigned = OneDecisionFamily("robust").evaluate(
        type_reading(snap, TYPES, kinds, cars, accel), shield.dynamics, leave
    )
    robust = shield.compute_result(snap)
    assert not (robust.safe & ~assigned.safe).any()
    assert robust.fallback or not assigned.fallback
    if not robust.fallback:
        assert not (robust.mask & ~assigned.mask).any()


def test_the_engines_give_the_same_gaps_and_verdicts(recorded: list[tuple[RoadSnapshot, SafetyShield]]) -> None:
    """Each reading's gaps from the compiled kernel are the numpy reference's, bit for bit, in the main and the
    straight fallback's pass; so are the combined verdicts."""
    from safelane.safety.one_decision.compiled import compiled_gaps
    from safelane.safety.one_decision.reference import rule_gaps

    for snap, shield in recorded[::3]:
        assert shield.dynamics is not None
        dyn = dataclasses.replace(shield.dynamics, ego_leave_time=shield.ego_leave_time(snap))
        readings, likely = shield.driver_readings(snap)
        states = [road_state(r) for r in readings]
        for state in states:
            for straight in (False, True):
                want, got = rule_gaps(state, dyn, "robust", straight), compiled_gaps(state, dyn, straight)
                for name in ("available", "joint", "ahead", "nominal_joint", "nominal_ahead", "nominal_ok"):
                    assert np.array_equal(getattr(want, name), getattr(got, name)), name
                assert want.allowance == got.allowance
        numpy, compiled = (
            evaluate_readings(states, road_state(likely), dyn, engine) for engine in ("numpy", "compiled")
        )
        assert np.array_equal(numpy.mask, compiled.mask) and np.array_equal(numpy.min_gap, compiled.min_gap)
        assert numpy.fallback == compiled.fallback


def test_robust_is_inside_omniscient_on_every_recorded_state(recorded: list[tuple[RoadSnapshot, SafetyShield]]) -> None:
    """The true assignment, through the omniscient shield, on every recorded state."""
    robust = recorded[0][1]
    omniscient = SafetyShield(robust.env, mode="omniscient", driver_types=DriverTypes(MIX))
    omniscient.dynamics = robust.dynamics
    for snap, _ in recorded:
        r, o = robust.compute_result(snap), omniscient.compute_result(snap)
        assert not (r.safe & ~o.safe).any() and (r.fallback or not o.fallback)
        assert r.fallback or not (r.mask & ~o.mask).any()
