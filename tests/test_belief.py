"""The belief over each car's hidden driver type (:mod:`safelane.safety.belief`): the exact posterior of hand-built
steps, the compiled kernel against the numpy reference, the filter's bookkeeping, and a real episode."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from highway_env.vehicle.behavior import IDMVehicle
from hypothesis import given, settings
from hypothesis import strategies as st

from safelane.core.drivers import IDM_PARAMETERS, DriverMix, parse_driver_mix
from safelane.core.errors import ConfigError
from safelane.core.snapshot import RoadSnapshot
from safelane.safety.belief import BeliefFilter, DriverTypes
from safelane.sim.drivers import AggressiveDriver, NormalDriver, TimidDriver

MIX = parse_driver_mix("timid-normal-aggressive")
LANE_W = 4.0
FRAMES, SIM_F = 5, 5.0  # highway-fast-v0: 5 frames of 0.2 s per decision


def snapshot(x: list[float], v: list[float], lane: list[int], **over: Any) -> RoadSnapshot:
    """A straight 4-lane road, body 0 the ego; ``x`` [m], ``v`` [m/s], ``lane`` per body (others via ``over``)."""
    n = len(x)
    pos = np.column_stack([np.asarray(x, float), np.asarray(lane, float) * LANE_W])
    idm = IDMVehicle
    fields: dict[str, Any] = dict(
        time=0.0, policy_frequency=1.0, simulation_frequency=SIM_F, lanes_count=4, lane_width=LANE_W,
        lane_origin=np.zeros(2), lane_direction=np.array([1.0, 0.0]), lane_lateral=np.array([0.0, 1.0]),
        speed_limit=30.0, ego=0, ego_target_speed=25.0, ego_speed_index=5, ego_target_speeds=(0.0, 5.0, 25.0),
        ego_kp=0.6, ego_lane_offset=0.0, position=pos, speed=np.asarray(v, float), heading=np.zeros(n),
        target_speed=np.full(n, 25.0), lane=np.asarray(lane), target_lane=np.asarray(lane), length=np.full(n, 5.0),
        width=np.full(n, 2.0), crashed=np.zeros(n, bool), is_vehicle=np.ones(n, bool), brake_max=np.full(n, 6.0),
        accel_max=np.full(n, idm.COMFORT_ACC_MAX), can_change_lane=np.ones(n, bool), idm_delta=np.full(n, 4.0),
        idm_comfort_acc=np.full(n, idm.COMFORT_ACC_MAX), idm_comfort_dec=np.full(n, idm.COMFORT_ACC_MIN),
        idm_distance_wanted=np.full(n, idm.DISTANCE_WANTED), idm_time_wanted=np.full(n, idm.TIME_WANTED),
        max_braking_imposed=np.full(n, 2.0), linear_speed_gain=np.full(n, np.nan),
        linear_speed_difference_gain=np.full(n, np.nan), linear_distance_gain=np.full(n, np.nan),
        politeness=np.full(n, idm.POLITENESS), driver_type=np.array([-1] + [0] * (n - 1)),
    )  # fmt: skip
    fields.update(over)
    return RoadSnapshot(**fields)


def idm_speed_after(v: float, v0: float, delta: float, t: str, lead: tuple[float, float, float] | None) -> float:
    """The speed [m/s] after one decision of a car of type ``t`` at ``v`` [m/s] (set-point ``v0``), frame by frame as
    highway-env integrates it; ``lead``: (gap [m] centre to centre, leader's speed [m/s], its acceleration)."""
    p = IDM_PARAMETERS[t]
    a, b = p.comfort_acc_max, -p.comfort_acc_min
    dt = 1.0 / SIM_F
    gap, vl, al = lead if lead is not None else (0.0, 0.0, 0.0)
    for _ in range(FRAMES):
        acc = a * (1 - (max(v, 0.0) / v0) ** delta)
        if lead is not None:
            d_star = p.distance_wanted + v * p.time_wanted + v * (v - vl) / (2 * math.sqrt(a * b))
            acc -= a * (d_star / gap) ** 2
        acc = min(max(acc, -p.acc_max), p.acc_max)
        gap += (vl - v) * dt
        v += acc * dt
        vl += al * dt
    return v


def test_the_constants_are_the_highway_env_classes() -> None:
    """The pure table the filter and the shields read holds the sim classes' numbers."""
    for name, cls in (("timid", TimidDriver), ("normal", NormalDriver), ("aggressive", AggressiveDriver),
                      ("IDMVehicle", IDMVehicle)):  # fmt: skip
        p = IDM_PARAMETERS[name]
        assert (p.comfort_acc_max, p.comfort_acc_min, p.distance_wanted, p.time_wanted, p.politeness) == (
            cls.COMFORT_ACC_MAX,
            cls.COMFORT_ACC_MIN,
            cls.DISTANCE_WANTED,
            cls.TIME_WANTED,
            cls.POLITENESS,
        )
        assert (p.max_braking_imposed, p.min_acc_gain, p.acc_max) == (
            cls.LANE_CHANGE_MAX_BRAKING_IMPOSED,
            cls.LANE_CHANGE_MIN_ACC_GAIN,
            cls.ACC_MAX,
        )


@pytest.mark.parametrize("engine", ["compiled", "numpy"])
@pytest.mark.parametrize("truth", ["timid", "normal", "aggressive"])
def test_exact_posterior_after_one_known_step(engine: str, truth: str) -> None:
    """A follower 30 m behind a leader braking at 1 m/s²: the posterior is prior × exp(−r²/2σ²), normalised, with
    r each type's residual [m/s²]; the true type's is 0."""
    sigma = 0.2
    x0, v0, lead_v0 = 100.0, 24.0, 20.0
    before = snapshot([0.0, x0, x0 + 30.0], [25.0, v0, lead_v0], [3, 1, 1])
    v_true = idm_speed_after(v0, 25.0, 4.0, truth, (30.0, lead_v0, -1.0))
    x_lead = x0 + 30.0 + sum((lead_v0 - 1.0 * 0.2 * f) * 0.2 for f in range(FRAMES))
    after = snapshot([25.0, x0 + 20.0, x_lead], [25.0, v_true, lead_v0 - 1.0], [3, 1, 1])
    belief = BeliefFilter(MIX, sigma, engine=engine)  # type: ignore[arg-type]
    np.testing.assert_allclose(belief.reset(before)[1], [1 / 3] * 3, rtol=0, atol=1e-15)
    post = belief.update(after)
    r = np.array([v_true - idm_speed_after(v0, 25.0, 4.0, t, (30.0, lead_v0, -1.0)) for t in MIX.types])
    expected = np.exp(-(r**2) / (2 * sigma**2))
    expected /= expected.sum()
    np.testing.assert_allclose(post[1], expected, rtol=1e-9, atol=1e-12)
    assert MIX.types[int(np.argmax(post[1]))] == truth
    assert belief.informative.tolist() == [0, 1, 1]


def test_free_road_at_the_set_point_leaves_the_prior() -> None:
    """Every type predicts 0 m/s² for a car alone at its set-point: the step says nothing."""
    uneven = parse_driver_mix([{"type": "timid", "weight": 0.2}, {"type": "aggressive", "weight": 0.8}])
    belief = BeliefFilter(uneven, 0.05)
    belief.reset(snapshot([0.0, 200.0], [25.0, 25.0], [3, 0]))
    post = belief.update(snapshot([25.0, 225.0], [25.0, 25.0], [3, 0]))
    np.testing.assert_allclose(post[1], [0.2, 0.8], rtol=1e-15)
    assert belief.informative[1] == 1


def test_uninformative_steps_keep_the_posterior() -> None:
    """A lane change, a crash or a leader that changed: the likelihood is flat."""
    belief = BeliefFilter(MIX, 0.05)
    belief.reset(snapshot([0.0, 100.0, 130.0], [25.0, 22.0, 20.0], [3, 1, 1]))
    changing = snapshot([25.0, 120.0, 150.0], [25.0, 23.0, 20.0], [3, 1, 1], target_lane=np.array([3, 2, 1]))
    np.testing.assert_array_equal(belief.update(changing)[1], np.full(3, 1 / 3))
    crashed = snapshot([50.0, 140.0, 170.0], [25.0, 10.0, 20.0], [3, 1, 1], crashed=np.array([0, 1, 0], bool))
    np.testing.assert_array_equal(belief.update(crashed)[1], np.full(3, 1 / 3))
    assert belief.informative[1] == 0


def test_a_car_or_leader_not_yet_straight_is_no_evidence() -> None:
    """A car heading across its lane by more than HEADING_STRAIGHT at either end of the step (finishing a lane
    change), or whose leader does: the step says nothing; within it, the same braking behind the same leader is
    evidence."""
    from safelane.safety.belief import HEADING_STRAIGHT

    def step(heading_before: list[float], heading_after: list[float]) -> BeliefFilter:
        belief = BeliefFilter(MIX, 0.2)
        belief.reset(snapshot([0.0, 100.0, 115.0], [25.0, 22.0, 20.0], [3, 1, 1], heading=np.array(heading_before)))
        belief.update(snapshot([25.0, 120.0, 135.0], [25.0, 19.0, 20.0], [3, 1, 1], heading=np.array(heading_after)))
        return belief

    turning = 1.01 * HEADING_STRAIGHT
    for before, after in (([0, turning, 0], [0, 0, 0]), ([0, 0, 0], [0, -turning, 0]), ([0, 0, turning], [0, 0, 0])):
        belief = step(before, after)
        assert belief.informative[1] == 0
        np.testing.assert_array_equal(belief.posterior[1], np.full(3, 1 / 3))
    straight = step([0, HEADING_STRAIGHT, -HEADING_STRAIGHT], [0, -HEADING_STRAIGHT, 0])
    assert straight.informative[1] == 1 and not np.allclose(straight.posterior[1], 1 / 3)


def test_new_cars_start_at_the_prior_and_gone_ones_are_dropped() -> None:
    uneven = parse_driver_mix([{"type": "timid", "weight": 1}, {"type": "normal", "weight": 3}])
    belief = BeliefFilter(uneven, 0.1)
    belief.reset(snapshot([0.0, 100.0], [25.0, 20.0], [3, 1]))
    post = belief.update(snapshot([25.0, 121.0, 300.0], [25.0, 22.0, 25.0], [3, 1, 2]))
    assert post.shape == (3, 2)
    np.testing.assert_allclose(post[2], [0.25, 0.75], rtol=1e-15)
    assert not np.allclose(post[1], [0.25, 0.75])
    assert belief.update(snapshot([50.0], [25.0], [3])).shape == (1, 2)


def test_linear_drivers_have_no_belief() -> None:
    with pytest.raises(ConfigError, match=r"^traffic\.driver_mix: type 'LinearVehicle'.*allowed: timid, normal"):
        BeliefFilter(parse_driver_mix([{"type": "LinearVehicle", "weight": 1}]))


_speeds = st.floats(0.0, 32.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(
    x=st.lists(st.floats(0.0, 300.0), min_size=6, max_size=6),
    lanes=st.lists(st.integers(0, 3), min_size=6, max_size=6),
    v=st.lists(_speeds, min_size=6, max_size=6),
    dv=st.lists(st.floats(-6.0, 3.0), min_size=6, max_size=6),
    weights=st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3).filter(lambda w: sum(w) > 0.01),
    sigma=st.floats(0.01, 2.0),
    steps=st.integers(1, 3),
    heading=st.lists(st.sampled_from([0.0, 0.01, -0.05, 0.051, -0.2]), min_size=6, max_size=6),
)
def test_compiled_is_the_reference_and_rows_sum_to_one(
    x: list[float], lanes: list[int], v: list[float], dv: list[float], weights: list[float], sigma: float,
    steps: int, heading: list[float],
) -> None:  # fmt: skip
    """Random scenes, several steps: the compiled kernel's posteriors are the reference's bits; every row is a
    distribution; a type of weight 0 stays at 0."""
    mix = DriverMix(("timid", "normal", "aggressive"), tuple(weights))
    filters = [BeliefFilter(mix, sigma, engine=e) for e in ("compiled", "numpy")]  # type: ignore[arg-type]
    snap = snapshot(x, v, lanes)
    for f in filters:
        f.reset(snap)
    for s in range(1, steps + 1):
        new_v = [max(a + b * s / steps, 0.0) for a, b in zip(v, dv, strict=True)]
        turned = np.array(heading) * (s % 2)  # cars turning at every other snapshot: some steps are no evidence
        snap = snapshot([a + b for a, b in zip(x, new_v, strict=True)], new_v, lanes, heading=turned)
        compiled, reference = (f.update(snap) for f in filters)
        np.testing.assert_array_equal(compiled, reference)
        np.testing.assert_allclose(compiled.sum(axis=1), 1.0, rtol=1e-12)
        assert np.all(compiled[:, np.asarray(weights) == 0] == 0)


def test_on_real_traffic_the_true_type_wins() -> None:
    """One hidden-types episode on the fast simulator: after 5 informative steps the most probable type is the true
    one for nearly every car (the residual model's σ small)."""
    from safelane.env.factory import make_env

    env = make_env("hidden-types", simulator="fast")
    _, info = env.reset(seed=3)
    belief = BeliefFilter(MIX, 0.1)
    belief.reset(info["snapshot"])
    for _ in range(15):
        _, _, term, trunc, info = env.step(3)  # FASTER
        post = belief.update(info["snapshot"])
        if term or trunc:
            break
    snap = info["snapshot"]
    seen = [i for i in snap.others() if belief.informative[i] >= 5]
    right = [int(np.argmax(post[i])) == snap.driver_type[i] for i in seen]
    assert len(seen) >= 20 and np.mean(right) >= 0.9
    env.close()


def test_the_leader_is_highway_env_s_front_vehicle_with_cars_placed_behind_the_lane_start() -> None:
    """``traffic.vehicles_behind`` puts cars up to hundreds of metres before the lane's start, where highway-env's
    ``on_lane`` sees no car: every car's leader as the filter reads it (both engines) is the front vehicle
    ``Road.neighbour_vehicles`` gives it on highway-env, at every decision of an episode of the claim grid's
    densest corner (the filter once took the close car ahead at x < −5 m, and ruled a true type out for good)."""
    from safelane.env.factory import make_env
    from safelane.safety.belief import LANE_START, Observation, _leader, leader_reference

    dense = {"env.vehicles_density": 2.0, "traffic.vehicles_behind": 25}
    env = make_env("hidden-types", simulator="highway-env", **dense)
    _, info = env.reset(seed=4004210005)
    behind_start = 0
    for _ in range(3):
        road = env.unwrapped.road
        obs = Observation(info["snapshot"])
        for i, vehicle in enumerate(road.vehicles):
            if i == 0 or not obs.tracked[i]:
                continue
            front, _ = road.neighbour_vehicles(vehicle, vehicle.lane_index)
            expected = road.vehicles.index(front) if front is not None else -1
            lane = int(obs.lane[i])
            assert leader_reference(obs.x, obs.y, i, lane, obs.lane_width) == expected, i
            assert _leader(obs.x, obs.y, i, lane, obs.lane_width) == expected, i
            behind_start += int(obs.x[i] < LANE_START)
        _, _, terminated, truncated, info = env.step(1)
        assert not (terminated or truncated)
    assert behind_start > 20  # the case is exercised: cars before the lane's start, each followed or not
    env.close()


def test_a_car_before_the_lane_start_is_nobody_s_leader() -> None:
    """Hand-built: a car 11 m behind another, both more than 5 m before the lane's start, a third on the lane 67 m
    ahead: the one on the lane leads (highway-env's ``on_lane``), as it does for a car on the lane itself."""
    from safelane.safety.belief import Observation, _leader, leader_reference

    obs = Observation(snapshot([200.0, -57.1, -46.4, 10.0, -4.9], [25.0] * 5, [0, 0, 0, 0, 1]))
    for find in (leader_reference, _leader):
        assert find(obs.x, obs.y, 1, 0, LANE_W) == 3  # not 2, before the start
        assert find(obs.x, obs.y, 2, 0, LANE_W) == 3
    snap = snapshot([200.0, -20.0, -4.9], [25.0] * 3, [0, 0, 0])
    obs = Observation(snap)
    assert leader_reference(obs.x, obs.y, 1, 0, LANE_W) == _leader(obs.x, obs.y, 1, 0, LANE_W) == 2  # on the lane


# --- the shields on the types' sets ------------------------------------------------------------------------------

TYPES = tuple(IDM_PARAMETERS[t] for t in MIX.types)


def test_type_readings_field_by_field() -> None:
    """Car 1 may be timid only (its own constants, bit for bit), car 2 timid or aggressive, car 3 any type: in the
    aggressive reading car 1 is timid, cars 2 and 3 aggressive, each with its type's own constants but ``accel_max``,
    the largest a over its allowed types; the ego (row 0) keeps its arrays."""
    from safelane.safety.driver_sets import type_readings

    snap = snapshot([0.0, 30.0, 60.0, 90.0], [25.0] * 4, [1] * 4, idm_delta=np.array([4.0, 3.6, 3.9, 4.4]))
    allowed = np.array([[1, 1, 1], [1, 0, 0], [1, 0, 1], [1, 1, 1]], bool)
    readings, _ = type_readings(snap, TYPES, allowed, np.array([1, 2, 3]), np.full((4, 3), 1 / 3))
    view = readings[2]
    timid, aggressive = IDM_PARAMETERS["timid"], IDM_PARAMETERS["aggressive"]
    expect = {  # field: (car 1, car 2, car 3)
        "brake_max": (6.0, 6.0, 6.0),
        "accel_max": (0.8, 2.0, 2.0),  # the largest a of its types: the fastest a car speeds up, in every role
        "idm_comfort_acc": (0.8, 2.0, 2.0),
        "idm_comfort_dec": (-1.0, -3.0, -3.0),
        "idm_distance_wanted": (9.0, 5.0, 5.0),
        "idm_time_wanted": (2.0, 1.0, 1.0),
        "max_braking_imposed": (1.0, 3.0, 3.0),
    }
    for name, values in expect.items():
        got = getattr(view, name)
        assert got[0] == getattr(snap, name)[0], name
        assert tuple(got[1:]) == values, name
    assert view.can_change_lane.all() and np.array_equal(view.idm_delta, snap.idm_delta)
    assert np.isnan(view.linear_speed_gain[1:]).all()
    assert (timid.comfort_acc_max, aggressive.comfort_acc_max) == (0.8, 2.0)
    assert view.position is snap.position  # every other field as it is


def test_omniscient_reads_what_the_seen_snapshot_reports() -> None:
    """The true type's worst case is the type's own constants: the seen arm's snapshot arrays, bit for bit."""
    from safelane.core.snapshot import DRIVER_FIELDS
    from safelane.env.factory import make_env
    from safelane.safety.shield import SafetyShield

    shield = make_env("hidden-types", simulator="fast", **{"shield.mode": "omniscient"})
    seen = make_env("hidden-types", simulator="fast", **{"traffic.shield_sees_types": True})
    snap = shield.reset(seed=5)[1]["snapshot"]
    seen_snap = seen.reset(seed=5)[1]["snapshot"]
    view = shield.get_wrapper_attr("driver_view")(snap)
    assert isinstance(shield.unwrapped, object) and isinstance(shield, SafetyShield)
    for name in DRIVER_FIELDS:
        np.testing.assert_array_equal(getattr(view, name), getattr(seen_snap, name), err_msg=name)
    shield.close()
    seen.close()


def test_robust_reads_every_type_under_a_hidden_mixture_and_nothing_else_changes() -> None:
    """Hidden types: one reading per type, every car read as it; seen types and traffic without a mixture: the
    snapshot as it is (the same object)."""
    from safelane.env.factory import make_env

    hidden = make_env("hidden-types", simulator="fast", **{"shield.mode": "robust"})
    snap = hidden.reset(seed=2)[1]["snapshot"]
    readings, _ = hidden.get_wrapper_attr("driver_readings")(snap)
    cars = snap.others()
    assert len(readings) == 3
    for t, view in zip(TYPES, readings, strict=True):
        assert (view.accel_max[cars] == 2.0).all() and (view.idm_comfort_acc[cars] == t.comfort_acc_max).all()
        assert (view.max_braking_imposed[cars] == t.max_braking_imposed).all()
        assert (view.idm_distance_wanted[cars] == t.distance_wanted).all()
    for preset, sets in (("hidden-types", {"traffic.shield_sees_types": True}), ("fast", {})):
        env = make_env(preset, simulator="fast", **{"shield.mode": "robust", **sets})
        snap = env.reset(seed=2)[1]["snapshot"]
        assert env.get_wrapper_attr("driver_view")(snap) is snap
        assert env.get_wrapper_attr("driver_readings")(snap) == ([snap], snap)
        env.close()
    hidden.close()


@pytest.mark.parametrize(
    ("sets", "says"),
    [
        (["shield.mode=belief"], r"^shield\.mode: 'belief' reads the driver types of traffic\.driver_mix, which is "
         r"none; allowed without a mixture: none, nominal, robust, committed$"),
        (["shield.mode=omniscient"], r"^shield\.mode: 'omniscient' reads"),
        (["shield.mode=robust", "shield.belief_epsilon=0.1"], r"^shield\.belief_epsilon: only for shield\.mode "
         r"belief"),
        (["shield.mode=belief", "traffic.driver_mix=[{type: LinearVehicle, weight: 1}]"],
         r"^traffic\.driver_mix: type 'LinearVehicle' .*; allowed: timid, normal, aggressive, IDMVehicle$"),
    ],
)  # fmt: skip
def test_type_modes_config_errors_are_one_line(sets: list[str], says: str) -> None:
    from safelane.config import load_config

    with pytest.raises(ConfigError, match=says) as err:
        load_config("fast", sets=sets)
    assert "\n" not in str(err.value)


def test_belief_sigma_default_is_the_filter_s() -> None:
    from safelane.config import ShieldConfig
    from safelane.safety.belief import SIGMA

    assert ShieldConfig().belief_sigma == SIGMA


class _Scripted:
    """A minimal environment replaying hand-built snapshots (the shield reads nothing else)."""

    def __init__(self, snaps: list[RoadSnapshot]) -> None:
        import gymnasium as gym

        self.snaps = snaps
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (1,))
        self.action_space = gym.spaces.Discrete(5)
        self.metadata: dict[str, Any] = {}
        self.render_mode = None
        self.spec = None
        self.np_random = np.random.default_rng(0)
        self.t = 0

    def road_snapshot(self, refresh: bool = False) -> RoadSnapshot:
        return self.snaps[self.t]

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        self.t = 0
        return np.zeros(1), {"snapshot": self.snaps[0]}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self.t += 1
        snap = self.snaps[self.t]
        return np.zeros(1), 0.0, bool(snap.ego_crashed), False, {"snapshot": snap, "collision": snap.ego_crashed,
                                                                  "speed": snap.ego_speed}  # fmt: skip

    def close(self) -> None:
        pass


@pytest.mark.parametrize(("truth", "ruled_out"), [(1, True), (0, False)])
def test_a_crash_with_a_car_whose_true_type_was_ruled_out_is_counted(truth: int, ruled_out: bool) -> None:
    """Prior 0.995 timid / 0.005 aggressive and ε = 0.01: aggressive is ruled out from the start. The ego runs into
    car 1: counted as outside the belief's sets when car 1 is aggressive, not when it is timid."""
    import gymnasium as gym

    from safelane.running.evaluation import EpisodeTally, summarize
    from safelane.safety.shield import SafetyShield

    mix = parse_driver_mix([{"type": "timid", "weight": 0.995}, {"type": "aggressive", "weight": 0.005}])
    types = np.array([-1, truth, 0])
    start = snapshot([0.0, 20.0, 200.0], [25.0, 10.0, 25.0], [1, 1, 2], driver_type=types)
    crash = snapshot([14.0, 19.0, 225.0], [20.0, 10.0, 25.0], [1, 1, 2], driver_type=types,
                     crashed=np.array([True, True, False]))  # fmt: skip

    class Env(_Scripted, gym.Env):  # type: ignore[misc]
        pass

    shield = SafetyShield(Env([start, crash]), mode="belief", override=True, driver_types=DriverTypes(mix, 0.01))
    _, info = shield.reset(seed=0)
    assert info["types_ruled_out"] == int(truth == 1) and info["type_ruled_out_crash"] is False
    tally = EpisodeTally(0, info)
    _, reward, _, _, info = shield.step(0)
    tally.add(0, reward, info)
    assert info["type_ruled_out_crash"] is ruled_out
    record = tally.record(info)
    assert record.type_ruled_out_crash is ruled_out and record.to_dict()["type_ruled_out_crash"] is ruled_out
    summary = summarize([record])
    assert summary["collisions_type_ruled_out"] == int(ruled_out)
    # the crash stands against the promise only where the true type was kept: its context, else none
    kept = summary["collision_contexts_types_kept"]
    assert sum(kept.values()) == 1 - int(ruled_out) and kept[record.collision_context] == 1 - int(ruled_out)


@pytest.mark.parametrize("mode", ["belief", "omniscient", "robust"])
def test_an_aggressive_turn_in_for_a_small_gain_is_in_the_types_sets(mode: str) -> None:
    """An aggressive car (MOBIL's threshold 0) turns in beside the ego for a gain below IDMVehicle's 0.2 m/s². With
    the rule's threshold at 0.2 for every car the belief and omniscient shields allowed IDLE into it (a side crash
    from a safe state, pinned); under a mixture the rule takes the least threshold of its types, and every type
    shield allows only SLOWER there, the numpy reference and the compiled engine alike."""
    from safelane.config import build_config
    from safelane.env.factory import make_env
    from safelane.running.counterexamples import load_counterexample

    cx = load_counterexample(Path(__file__).parent / "fixtures" / "hidden-types" / "aggressive-turn-in-collision.json")
    masks = {}
    for engine in ("numpy", "compiled"):
        data = copy.deepcopy(cx.config)
        data["shield"] = {**data["shield"], "mode": mode, "override": False, "engine": engine}
        env = make_env(build_config(data))
        _, info = env.reset(seed=cx.seed)
        for action in cx.actions[:-1]:
            _, _, _, _, info = env.step(int(action))
        masks[engine] = info["action_mask"].tolist()
        env.close()
    assert masks["numpy"] == masks["compiled"]
    assert masks["compiled"][:4] == [False, False, False, False]  # IDLE no longer: the aggressive car may turn in


def _verdicts_at_the_end(
    name: str, mode: str, variants: dict[str, dict[str, Any]], override: bool = True, folder: str = "hidden-types"
) -> dict[str, tuple[bool, list]]:
    """Replay the fixture ``name`` (tests/fixtures/``folder``) under ``mode`` with the rule it was recorded with
    (the options ``variants`` name off), the shield overriding the recorded choices or not (``override``: off plays
    them as they are, the same scene under every mode where the policy chose only allowed actions), then judge its
    last state again under each variant — ``{"engine": …, option: value, …}``: ``{variant: (fallback, mask)}``."""
    from safelane.config import build_config
    from safelane.env.factory import make_env
    from safelane.env.scenarios import find_shield
    from safelane.running.counterexamples import load_counterexample

    cx = load_counterexample(Path(__file__).parent / "fixtures" / folder / f"{name}.json")
    options = {k for v in variants.values() for k in v if k != "engine"}
    data = copy.deepcopy(cx.config)
    data["shield"] = {**data["shield"], "mode": mode, "override": override, **dict.fromkeys(options, False)}
    env = make_env(build_config(data))
    env.reset(seed=cx.seed)
    for action in cx.actions[:-1]:
        env.step(int(action))
    shield, recorded = find_shield(env), (find_shield(env).engine, find_shield(env).rule)
    out = {}
    for label, variant in variants.items():
        shield.engine = variant.get("engine", recorded[0])
        shield.rule = recorded[1].with_options(**{k: v for k, v in variant.items() if k != "engine"})
        shield.dynamics = None  # rebuilt from the rule at the next verdict; the family follows the engine
        result = shield.compute_result()
        out[label] = (bool(result.fallback), result.mask.tolist())
    env.close()
    return out


@pytest.mark.parametrize("mode", ["omniscient", "robust", "belief"])
@pytest.mark.parametrize("fixture", ["slow-aggressive-turn-in-collision", "slow-timid-turn-in-collision"])
def test_a_level_car_whose_incentive_holds_within_the_decision_turns_in(fixture: str, mode: str) -> None:
    """A car level with the ego in the next lane and much slower than it: IDM's desired gap behind the ego
    ``d* = s₀ + vT + v·Δv/(2√(ab))`` passes through zero while the ego accelerates, so MOBIL's incentive holds at a
    frame within the decision though not now nor at its end. The omniscient shield allowed FASTER and the car
    (aggressive 7 m/s slower; timid 3 m/s slower) turned into the ego's flank (pinned, 2 and 10 decisions per second).
    With ``level_incentive_frames`` the incentive's first frame decides which level cars turn in: FASTER is out on
    both engines; without the option it was allowed under the omniscient shield."""
    on = {"level_incentive_frames": True, "incentive_politeness": False}  # as recorded, and the option
    variants = {"numpy": {**on, "engine": "numpy"}, "compiled": {**on, "engine": "compiled"}, "off": {}}
    verdicts = _verdicts_at_the_end(fixture, mode, variants, override=False)  # the probe chose allowed actions
    assert verdicts["numpy"] == verdicts["compiled"]
    assert not verdicts["compiled"][1][3]  # FASTER: the level car may turn in within the decision
    assert verdicts["compiled"][1][4]  # SLOWER stays
    if mode == "omniscient":
        assert verdicts["off"][1][3]  # the now-and-end incentive alone let FASTER through


@pytest.mark.parametrize("mode", ["omniscient", "robust", "belief"])
@pytest.mark.parametrize(
    ("fixture", "option"),
    [("polite-timid-turn-in-collision", "incentive_politeness"),
     ("knife-edge-aggressive-turn-in-collision", "incentive_accelerations")],
)  # fmt: skip
def test_a_turn_in_the_incentive_missed_is_seen(fixture: str, option: str, mode: str) -> None:
    """Two side crashes of the grid under ``belief`` (pinned, tests/fixtures/hidden-types-turn-ins;
    ``research/mobil_terms.py`` prints the terms), both into the ego's flank under the SLOWER the shield allowed:

    * a timid car (politeness 1) just behind the overtaking ego in the next lane gains nothing itself by moving
      behind it, but its old follower gains 0.94 m/s² from its leaving, and MOBIL lets it change lanes
      (``incentive_politeness`` counts the followers' gain; 5 frames per second);
    * an aggressive car (threshold 0) 0.9 m ahead of the ego's centre at 10.8 m/s, braking at 0.54 m/s² behind a
      timid car 15 m ahead, the ego overtaking at 18.7 m/s (2 decisions and 10 frames a second): IDM's desired gap
      behind the ego is about its distance there, so MOBIL's gain turns on tenths of a m/s — −1.4 m/s² at 0.2 s
      with every car at constant speed, +0.16 with each at its acceleration now (``incentive_accelerations``;
      highway-env's: +0.149 a frame later).

    With the option no action is safe there under every type shield (the shield promises nothing, and says so), on
    both engines; without it SLOWER was safe under the omniscient and belief shields (the robust one, over every
    type, had no safe action either way)."""
    on = {option: True}
    variants = {"numpy": {**on, "engine": "numpy"}, "compiled": {**on, "engine": "compiled"}, "off": {}}
    verdicts = _verdicts_at_the_end(fixture, mode, variants, override=False, folder="hidden-types-turn-ins")
    assert verdicts["numpy"] == verdicts["compiled"] == (True, [False, False, False, False, True])
    assert verdicts["off"] == (mode == "robust", [False, False, False, False, True])


def test_a_car_changing_in_ahead_of_a_level_car_is_its_leader_for_mobil() -> None:
    """A timid car level with the ego in the next lane, 2.9 m behind the ego's centre and 4.4 m/s slower; ahead of it
    a car changing into its lane, its centre 2.7 m off the lane's, still nearer the lane it leaves, 34 m ahead at
    8.8 m/s. highway-env's IDM sees that car as the timid car's leader (half a lane + 1 m): behind it the timid car
    brakes, behind the ego it would not, so MOBIL lets it turn in — it did, into the ego braking under SLOWER (the
    belief shield's side crash from a safe state, its type kept; 5 decisions per second). Reading the leaders by
    lane alone, the rule allowed SLOWER as safe; with ``incentive_leaders_band`` nothing is safe there (the shield
    promises nothing, and says so), on both engines."""
    on = {"incentive_leaders_band": True, "incentive_politeness": False}  # the rule it was recorded with, and the band
    verdicts = _verdicts_at_the_end(
        "leader-changing-in-turn-in-collision",
        "belief",
        {"numpy": {**on, "engine": "numpy"}, "compiled": {**on, "engine": "compiled"}, "off": {}},
    )
    assert verdicts["numpy"] == verdicts["compiled"] and verdicts["compiled"][0]
    assert verdicts["off"] == (False, [False, False, False, False, True])
