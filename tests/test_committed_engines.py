"""The committed shield's two engines give the same bits: each compiled kernel against its numpy reference on
hypothesis states (every driver model, crashed and turning cars, carried follower bounds), the
family's verdicts decision by decision (lapses, escapes, followers), and whole episodes on both simulators."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from safelane.safety.committed import compiled
from safelane.safety.committed import plans as reference
from safelane.safety.committed.family import CommittedFamily
from safelane.safety.committed.plan_family import onsets
from safelane.safety.committed.sets import car_sets
from safelane.safety.ego import action_lanes, ego_trajectories
from safelane.safety.world import Dynamics, RoadState

LANES = 4


def _dynamics(policy_hz: int, sim_hz: int) -> Dynamics:
    return Dynamics(
        decision_period=1.0 / policy_hz, frame_dt=1.0 / sim_hz, frames_per_decision=sim_hz // policy_hz,
        ego_kp=1 / 0.6, target_speeds=(20.0, 25.0, 30.0), lane_width=4.0, lanes_count=LANES,
        ego_leave_time=0.8, cut_in_time=0.4,
    )  # fmt: skip


DYNAMICS = st.sampled_from(
    [_dynamics(1, 5), _dynamics(2, 10), _dynamics(1, 15), dataclasses.replace(_dynamics(1, 5), ego_leave_time=np.inf)]
)  # the last: an ego too slow to leave its lane (no lane change is verified)
finite = st.floats(allow_nan=False, allow_infinity=False)


@st.composite
def cars(draw: Any) -> dict[str, Any]:
    """One other car: IDM or a linear-model driver (gains of either sign), any lane, turning or not, crashed or
    not, set-point known or not."""
    linear = draw(st.booleans())
    gains = [draw(st.floats(-0.3, 1.0)) if linear else np.nan for _ in range(3)]
    turning = draw(st.booleans())
    return dict(
        x=draw(st.floats(-90.0, 160.0)), y=draw(st.floats(-1.0, 4.0 * (LANES - 1) + 1.0)),
        vx=draw(st.floats(-2.0, 38.0)), vy=draw(st.floats(-3.0, 3.0)) if turning else 0.0,
        heading=draw(st.floats(-0.4, 0.4)) if turning else 0.0, length=5.0, crashed=draw(st.booleans()) and
        draw(st.booleans()), brake_max=draw(st.floats(3.0, 8.0)), accel_max=draw(st.floats(2.0, 6.0)),
        can_change_lane=draw(st.booleans()), idm_delta=4.0, idm_comfort_acc=draw(st.floats(2.0, 4.0)),
        idm_comfort_dec=-draw(st.floats(3.0, 6.0)), idm_distance_wanted=draw(st.floats(5.0, 11.0)),
        idm_time_wanted=draw(st.floats(1.0, 1.8)), max_braking_imposed=draw(st.floats(1.5, 3.0)),
        linear_speed_gain=gains[0], linear_speed_difference_gain=gains[1], linear_distance_gain=gains[2],
        target_speed=draw(st.sampled_from([np.nan, 18.0, 25.0, 31.0, 35.0])),
    )  # fmt: skip


@st.composite
def states(draw: Any) -> RoadState:
    """A road state: the ego in any lane (a lane change under way or not), 0–9 other cars."""
    rows = draw(st.lists(cars(), min_size=0, max_size=9))
    lane = draw(st.integers(0, LANES - 1))
    target_lane = min(max(lane + draw(st.sampled_from([0, 0, -1, 1])), 0), LANES - 1)
    index = draw(st.integers(0, 2))
    keys = ("x", "y", "vx", "vy", "heading", "length", "brake_max", "accel_max", "idm_delta", "idm_comfort_acc",
            "idm_comfort_dec", "idm_distance_wanted", "idm_time_wanted", "max_braking_imposed", "linear_speed_gain",
            "linear_speed_difference_gain", "linear_distance_gain", "target_speed")  # fmt: skip
    return RoadState(
        ego_x=0.0, ego_y=4.0 * lane, ego_speed=draw(st.floats(0.0, 32.0)), ego_lane=lane, ego_target_lane=target_lane,
        ego_target_speed=(20.0, 25.0, 30.0)[index], ego_speed_index=index,
        crashed=np.array([r["crashed"] for r in rows], dtype=bool),
        can_change_lane=np.array([r["can_change_lane"] for r in rows], dtype=bool),
        **{k: np.array([r[k] for r in rows], dtype=float) for k in keys},
    )  # fmt: skip


def same(a: np.ndarray, b: np.ndarray) -> bool:
    """The same shape and bits (NaN equal to NaN)."""
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.tobytes() == b.tobytes()


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(state=states(), dyn=DYNAMICS)
def test_the_compiled_sets_and_ego_paths_are_the_references_bits(state: RoadState, dyn: Dynamics) -> None:
    vehicle = np.arange(state.n)
    ours, theirs = compiled.car_sets_compiled(state, dyn, vehicle), car_sets(state, dyn, vehicle)
    for name in ("x_lo", "x_hi", "v_lo", "v_hi", "entry", "now"):
        assert same(getattr(ours, name), getattr(theirs, name)), name
    ego_x, ego_v = ego_trajectories(state, dyn)
    cx, cv = compiled.ego_trajectories_compiled(state, dyn)
    assert same(cx, ego_x) and same(cv, ego_v)
    for a in range(5):
        assert same(compiled.plan_set_points_compiled(state, dyn, ego_v[a], a),
                    reference.plan_set_points(state, dyn, ego_v[a], a))  # fmt: skip
    for i in range(state.n):
        react = np.array([0.0, 0.5, 1.7, 3.2])
        assert same(compiled.follower_bound_compiled(state, i, react, dyn.times),
                    reference.follower_bound(state, i, react, dyn.times))  # fmt: skip


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    state=states(),
    dyn=DYNAMICS,
    action=st.integers(0, 4),
    until=st.one_of(st.none(), st.integers(-2, 80)),
    carried=st.booleans(),
)
def test_the_compiled_car_gaps_are_the_references_bits(
    state: RoadState, dyn: Dynamics, action: int, until: int | None, carried: bool
) -> None:  # fmt: skip
    vehicle = np.arange(state.n)
    sets = car_sets(state, dyn, vehicle)
    ego_x, _ = ego_trajectories(state, dyn)
    lanes = action_lanes(state, dyn, action)
    # A follower bound carried from a kept plan for every other car, in a lane the plan occupies.
    followers = (
        {i: (lanes[i % len(lanes)][0], sets.x_hi[i] - 3.0 * (i % 3)) for i in range(state.n)} if carried else None
    )
    args = (state, dyn, sets, ego_x[action], onsets(dyn, action), lanes, until, followers)
    assert same(compiled.car_gaps_compiled(*args), reference.car_gaps(*args))


def _moved(state: RoadState, rng: np.random.Generator, dyn: Dynamics, sets: Any) -> RoadState:
    """``state`` one decision later: the ego on its way, every car somewhere in (or, now and then, outside) the
    set drawn for it."""
    f = dyn.frames_per_decision
    pick = rng.uniform(-0.2, 1.2, state.n)
    x = sets.x_lo[:, f] + pick * (sets.x_hi[:, f] - sets.x_lo[:, f])
    vx = sets.v_lo[:, f] + rng.uniform(-0.1, 1.1, state.n) * (sets.v_hi[:, f] - sets.v_lo[:, f])
    y = state.y + rng.choice([0.0, 0.0, 0.0, 2.0, -2.0, 4.0], state.n)
    ego_v = state.ego_speed + rng.uniform(-3.0, 2.0)
    return dataclasses.replace(state, x=np.where(np.isfinite(x), x, state.x), vx=np.where(np.isfinite(vx), vx, 0.0),
                               y=y, ego_x=state.ego_x + state.ego_speed * dyn.decision_period,
                               ego_speed=max(ego_v, 0.0))  # fmt: skip


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(state=states(), dyn=DYNAMICS, seed=st.integers(0, 99),
       actions=st.lists(st.integers(0, 4), min_size=3, max_size=3))  # fmt: skip
def test_the_families_verdicts_are_the_same_decision_by_decision(
    state: RoadState, dyn: Dynamics, seed: int, actions: list[int]
) -> None:  # fmt: skip
    """Three decisions, each car moved somewhere in (or just outside) its set: the same mask, gaps, plans, lapses,
    named cars, follower bounds and carried sets from both engines."""
    rng = np.random.default_rng(seed)
    families = {engine: CommittedFamily(engine) for engine in ("numpy", "compiled")}
    vehicle = np.arange(state.n) * 2 + 1  # snapshot indices that are not row numbers
    for action in actions:
        results = {engine: fam.evaluate_state(state, vehicle, dyn) for engine, fam in families.items()}
        ours, theirs = results["compiled"], results["numpy"]
        for name in ("mask", "safe", "available", "min_gap"):
            assert same(getattr(ours, name), getattr(theirs, name)), name
        for name in ("fallback", "plan_forced", "lapse", "lapse_cars", "escaped", "rolled_back", "unbraked_followers",
                     "checked", "entered", "certified", "plans"):  # fmt: skip
            assert getattr(ours, name) == getattr(theirs, name), name
        executed = action if ours.mask[action] else int(np.flatnonzero(ours.mask)[0])
        for fam in families.values():
            fam.commit(executed)
        kept = {engine: (fam.kept, sorted((v, lane, high.tobytes()) for v, (lane, high) in fam.followers.items()))
                for engine, fam in families.items()}  # fmt: skip
        assert kept["compiled"] == kept["numpy"]
        for name in ("x_lo", "x_hi", "v_lo", "v_hi", "entry", "now"):  # the sets carried (intersected) to the next
            assert same(getattr(families["compiled"].carried, name), getattr(families["numpy"].carried, name)), name
        state = _moved(state, rng, dyn, car_sets(state, dyn, vehicle))


def _episode(simulator: str, engine: str, seeds: list[int], policy: str) -> list[tuple]:
    """Each decision's verdict and observation, bytes for bytes, for a few episodes of dense traffic."""
    from safelane.env.factory import make_env
    from safelane.running.policies import fixed_policy

    overrides = {"simulator": simulator, "shield.mode": "committed", "shield.engine": engine, "shield.override": True,
                 "env.vehicles_density": 2.0}  # fmt: skip
    env = make_env("fast", **overrides)
    act = fixed_policy(policy, 7)
    out = []
    for seed in seeds:
        obs, info = env.reset(seed=seed)
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(int(act(obs, info)))
            done = terminated or truncated
            res = env.get_wrapper_attr("result")
            verdict = (info["plan_forced"], info["lapse"], tuple(info["lapse_cars"]), tuple(info["escaped_cars"]))
            out.append((info["executed_action"], res.mask.tobytes(), res.min_gap.tobytes(), *verdict, obs.tobytes()))
    env.close()
    return out


@pytest.mark.parametrize(("simulator", "seeds"), [("fast", [3, 8]), ("highway-env", [3])])
def test_whole_episodes_are_the_same_on_both_engines(simulator: str, seeds: list[int]) -> None:
    """always-FASTER in dense traffic (seed 3: plan-forced decisions and two lapses): the same decisions, masks,
    gaps and observations from either engine, on either simulator."""
    numpy_run = _episode(simulator, "numpy", seeds, "faster")
    assert len(numpy_run) == 40 * len(seeds)
    assert sum(d[3] for d in numpy_run) >= 2 and sum(d[4] for d in numpy_run) >= 1  # plan-forced; lapses
    assert numpy_run == _episode(simulator, "compiled", seeds, "faster")


def test_signed_zeros_are_the_references() -> None:
    """A car standing with a speed of −0.0 (numpy's minimum and maximum return the second of −0.0 and 0.0; a
    kernel that returns the first differs in the sign bit)."""
    row = dict(x=[10.0], y=[0.0], vx=[-0.0], vy=[0.0], heading=[-0.0], length=[5.0], crashed=[False],
               brake_max=[6.0], accel_max=[3.0], can_change_lane=[False], idm_delta=[4.0], idm_comfort_acc=[3.0],
               idm_comfort_dec=[-5.0], idm_distance_wanted=[10.0], idm_time_wanted=[1.5], max_braking_imposed=[2.0],
               linear_speed_gain=[np.nan], linear_speed_difference_gain=[np.nan], linear_distance_gain=[np.nan],
               target_speed=[np.nan])  # fmt: skip
    state = RoadState(ego_x=0.0, ego_y=0.0, ego_speed=20.0, ego_lane=0, ego_target_lane=0, ego_target_speed=20.0,
                      ego_speed_index=0, **{k: np.array(v) for k, v in row.items()})  # fmt: skip
    dyn = _dynamics(1, 5)
    ours, theirs = compiled.car_sets_compiled(state, dyn, np.array([0])), car_sets(state, dyn, np.array([0]))
    for name in ("x_lo", "x_hi", "v_lo", "v_hi"):
        assert same(getattr(ours, name), getattr(theirs, name)), name
