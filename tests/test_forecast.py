"""The nominal forecast that ranks the fallback's choices (safelane.safety.one_decision.forecast,
shield.forecast_fallback): its predictions against the simulators, and the scene it was made for."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safelane.core.snapshot import RoadSnapshot
from safelane.core.spaces import IDLE, LANE_RIGHT, SLOWER
from safelane.env import scenarios
from safelane.env.factory import make_env
from safelane.safety.one_decision import reference as model
from safelane.safety.one_decision.forecast import forecast_keys
from safelane.safety.one_decision.reference import MAX_HOLD_DECISIONS, RELEVANCE_RANGE
from safelane.safety.shield import SafetyShield
from safelane.safety.world import Dynamics, RoadState


def road_indices(snap: RoadSnapshot, ego_x: float) -> np.ndarray:
    """The snapshot index of each entry of ``shield.road_state``'s arrays (the same selection)."""
    others = snap.others(vehicles_only=False)
    x_all = (snap.position[others] - snap.lane_origin) @ snap.lane_direction
    return others[np.flatnonzero((np.abs(x_all - ego_x) < RELEVANCE_RANGE) & np.isfinite(x_all))]


@pytest.mark.parametrize("simulator", ["highway-env", "fast"])
@pytest.mark.parametrize("drivers", ["IDMVehicle", "DefensiveVehicle"])
def test_forecast_is_the_simulator_on_one_lane(simulator: str, drivers: str) -> None:
    """On one lane nobody can change lane, so the forecast — every car by its own law behind its leader, the ego
    on the model's trajectory — is the simulator's own integration: each forecast car's position at every
    decision of IDLE held one decision and then SLOWER equals the simulator's, to rounding (on a road short
    enough that every car is within the forecast's range: a car out of it would lead one in it)."""
    env = make_env(
        "fast",
        simulator=simulator,
        **{
            "env.lanes_count": 1,
            "env.vehicles_count": 6,
            "env.vehicles_density": 1.5,
            "env.other_vehicles_type": f"highway_env.vehicle.behavior.{drivers}",
            "traffic.vehicles_behind": 4,
            "shield.mode": "robust",
        },
    )
    assert isinstance(env, SafetyShield)
    compared = 0
    for seed in range(6):
        _, info = env.reset(seed=seed)
        snap = info["snapshot"]
        state, dyn = env.state_and_dynamics(snap)
        fallback = 1
        pick, history, _ = model.forecast_of(state, dyn, IDLE, fallback)
        ego_path = model.ego_trajectories(state, dyn)[0][IDLE, fallback]
        index = road_indices(snap, state.ego_x)[pick]
        if pick.size != state.n:  # a car out of the forecast's range would lead one in it: another seed
            continue
        frames = dyn.frames_per_decision
        actions = [IDLE] * (1 + fallback) + [SLOWER] * 4
        for d, action in enumerate(actions, start=1):
            _, _, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                break
            now = info["snapshot"]
            x_now = (now.position[index] - now.lane_origin) @ now.lane_direction
            ego_now = float((now.position[now.ego] - now.lane_origin) @ now.lane_direction)
            assert ego_now == pytest.approx(ego_path[d * frames], abs=1e-6)
            assert x_now == pytest.approx(history[:, d * frames], abs=1e-6)
            compared += pick.size
    env.close()
    assert compared >= 50  # several seeds, every decision, every car


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
def test_forecast_fallback_changes_lane_out_of_a_squeeze(engine: str) -> None:
    """The scene of ``scenarios.squeeze_beside_a_free_lane`` on highway-env: nothing is safe in either mode; the
    worst case ranks SLOWER least bad (−16.27 m nominal, −17.92 m robust), but the forecast sees the leader brake
    at its limit now and SLOWER run into it, while LANE_RIGHT keeps more than the margin: with
    shield.forecast_fallback both modes change lane. The safe set, the fallback flag and the worst-case gaps do
    not move."""
    for mode, gap in (("nominal", -16.27), ("robust", -17.92)):
        kw = {"shield.engine": engine}
        earlier = {"shield.forecast_fallback": False}
        off = scenarios.SCENARIOS["squeeze_beside_a_free_lane"](mode=mode, **kw, **earlier).result
        on = scenarios.SCENARIOS["squeeze_beside_a_free_lane"](mode=mode, **kw)  # the default
        assert off.fallback and on.result.fallback and not on.result.safe.any()
        assert off.mask.tolist() == [False, False, False, False, True]
        assert on.mask.tolist() == [False, False, True, False, False]
        assert round(float(off.min_gap[SLOWER]), 2) == gap
        assert on.result.min_gap.tolist() == off.min_gap.tolist()
    state, dyn = on.shield.state_and_dynamics(on.shield.snapshot)
    fallbacks = range(MAX_HOLD_DECISIONS + 1)
    best = {a: max(model.forecast_of(state, dyn, a, k)[2] for k in fallbacks) for a in (LANE_RIGHT, SLOWER)}
    assert best[LANE_RIGHT] > dyn.margin and best[SLOWER] < 0.0  # SLOWER runs into the braking leader in the forecast
    ego_x, _ = model.ego_trajectories(state, dyn)
    available = model.available_actions(state, dyn)
    alike = model.forecast_ranking(state, dyn, ego_x, available)
    assert alike[LANE_RIGHT] == dyn.margin and alike[SLOWER] == -1.0


def test_a_state_without_driver_models_has_no_forecast() -> None:
    """A hand-built RoadState that leaves the driver models out: the forecast refuses to guess (inspection
    raises; the ranking gives every available action the same key, so the worst-case order decides)."""
    state = model.RoadState(
        ego_x=200.0, ego_y=0.0, ego_speed=25.0, ego_lane=0, ego_target_lane=0, ego_target_speed=25.0,
        ego_speed_index=5, x=np.array([213.0]), y=np.array([0.0]), vx=np.array([22.0]), vy=np.array([0.0]),
        heading=np.array([0.0]), length=np.array([5.0]), crashed=np.array([False]),
    )  # fmt: skip
    dyn = model.Dynamics(
        decision_period=1.0, frame_dt=0.2, frames_per_decision=5, ego_kp=1 / 0.6,
        target_speeds=(0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0), lane_width=4.0, lanes_count=2,
    )  # fmt: skip
    with pytest.raises(ValueError, match="driver models"):
        model.forecast_of(state, dyn, IDLE, 0)
    available = model.available_actions(state, dyn)
    ranking = model.forecast_ranking(state, dyn, model.ego_trajectories(state, dyn)[0], available)
    assert ranking[available].tolist() == [dyn.margin] * int(available.sum())


def test_forecast_keys_rank_every_collision_alike() -> None:
    """forecast_keys: a clear action keeps its gap up to the margin; a forecast collision is −1 whatever its depth,
    as is a NaN gap or an unavailable action (−inf)."""
    gaps = np.array([2.5, 0.4, -3.0, -0.2, -1.0, np.nan, -np.inf])
    assert forecast_keys(gaps, 1.0).tolist() == [1.0, 0.4, -1.0, -1.0, -1.0, -1.0, -1.0]


def _forecast_arguments(state: RoadState, dyn: Dynamics, available: np.ndarray) -> tuple:
    """The arguments of forecast_gaps_of / forecast_keys_of for one state, as the rule builds them."""
    from safelane.safety.ego import ego_last_frames, ego_trajectories
    from safelane.safety.others import set_points

    ego_x, _ = ego_trajectories(state, dyn)
    head = (ego_x, ego_last_frames(state, dyn, available), available)
    tail = (
        dyn.frame_dt, state.ego_x, state.ego_length, dyn.lanes_count, dyn.lane_width, state.speed_limit, state.x,
        state.y, state.vx, state.vy, state.length, state.crashed, state.brake_max, state.accel_max, state.idm_delta,
        state.idm_comfort_acc, state.idm_comfort_dec, state.idm_distance_wanted, state.idm_time_wanted,
        state.linear_speed_gain, state.linear_speed_difference_gain, state.linear_distance_gain, set_points(state),
    )  # fmt: skip
    return head, tail


@pytest.mark.parametrize("drivers", ["IDMVehicle", "AggressiveVehicle"])
def test_forecast_keys_of_stops_early_with_the_same_keys(drivers: str) -> None:
    """forecast_keys_of stops rollouts whose key can no longer win; its keys are forecast_keys(forecast_gaps_of)'s
    to the bit — on dense traffic's states (where the forecast collides and squeezes), for every pool of the
    available actions, at margins from 0.1 m (every key capped early) to 50 m (nothing capped), and with the
    vehicles' speeds jittered so that gaps cross zero at other frames."""
    from safelane.safety.ego import available_actions
    from safelane.safety.one_decision.forecast import forecast_gaps_of, forecast_keys_of

    env = make_env(
        "fast",
        simulator="fast",
        **{"env.vehicles_density": 2.0, "env.other_vehicles_type": f"highway_env.vehicle.behavior.{drivers}",
           "shield.mode": "robust"},
    )  # fmt: skip
    assert isinstance(env, SafetyShield)
    rng = np.random.default_rng(7)
    compared = stopped_differently = 0
    for seed in range(3):
        _, info = env.reset(seed=seed)
        for _ in range(12):
            state, dyn = env.state_and_dynamics(info["snapshot"])
            available = available_actions(state, dyn)
            for jitter in (0.0, 3.0):
                vx = state.vx + jitter * rng.standard_normal(state.n)
                (xs, last, avail), tail = _forecast_arguments(state, dyn, available)
                tail = (*tail[:8], vx, *tail[9:])  # the others' speeds
                for pool_bits in range(1, 32):
                    pool = avail & ((pool_bits >> np.arange(5)) & 1).astype(bool)
                    if not pool.any():
                        continue
                    gaps = forecast_gaps_of(xs, last, avail, pool, *tail)
                    for margin in (0.1, 1.0, 5.0, 50.0):
                        keys = forecast_keys_of(xs, last, avail, pool, *tail, margin)
                        expected = forecast_keys(gaps, margin)
                        assert np.array_equal(keys, expected), (seed, pool, margin, keys, expected)
                        compared += 1
                        stopped_differently += int(np.any((gaps < 0) & (gaps > -np.inf)))
            _, _, terminated, truncated, info = env.step(int(rng.integers(5)))
            if terminated or truncated:
                break
    assert compared > 1000 and stopped_differently > 0  # collisions forecast: the early stops were exercised


@st.composite
def _one_lane_scenes(draw: st.DrawFn) -> tuple:
    """A one-lane scene for the forecast kernels: the ego's 5 × 4 paths (each action's own speed; fallback k holds
    it k + 1 decisions, then brakes 5 m/s per second to a stop: the paths share their prefixes bit for bit, as the
    rule's do) and up to six others around it — IDM drivers and bodies with no law that keep their speed (they
    run into the ego from behind, so holding longer can avoid a crash that braking early meets)."""
    frames_per_decision, decisions = 5, 11
    dt = 1.0 / frames_per_decision
    n_t = frames_per_decision * decisions + 1
    xs = np.empty((5, 4, n_t))
    for a in range(5):
        v0 = draw(st.floats(5.0, 30.0))
        for k in range(4):
            x, v = 0.0, v0
            for f in range(n_t):
                xs[a, k, f] = x
                if f >= (k + 1) * frames_per_decision:
                    v = max(v - 5.0 * dt, 0.0)
                x += v * dt
    n = draw(st.integers(1, 6))
    x = np.array(draw(st.lists(st.floats(-120.0, 120.0), min_size=n, max_size=n)))
    vx = np.array(draw(st.lists(st.floats(0.0, 35.0), min_size=n, max_size=n)))
    lawless = np.array(draw(st.lists(st.booleans(), min_size=n, max_size=n)))
    target = np.where(lawless, np.nan, np.array(draw(st.lists(st.floats(15.0, 30.0), min_size=n, max_size=n))))
    ones = np.ones(n)
    tail = (
        dt, 0.0, 5.0, 1, 4.0, 40.0, x, np.zeros(n), vx, np.zeros(n), 5.0 * ones, np.zeros(n, dtype=bool), 6.0 * ones,
        6.0 * ones, 4.0 * ones, 3.0 * ones, -5.0 * ones, 10.0 * ones, 1.5 * ones, np.full(n, np.nan),
        np.full(n, np.nan), np.full(n, np.nan), target,
    )  # fmt: skip
    last = np.full((5, 1), n_t - 1, dtype=np.int64)
    return xs, last, tail


@settings(max_examples=300, deadline=None)
@given(scene=_one_lane_scenes(), margin=st.sampled_from([0.5, 1.0, 5.0, 50.0]), pool_bits=st.integers(1, 31))
def test_forecast_keys_of_is_forecast_keys_of_the_gaps(scene: tuple, margin: float, pool_bits: int) -> None:
    """Property: on any one-lane scene, forecast_keys_of's early stops give forecast_keys(forecast_gaps_of)'s keys
    to the bit, for any pool of actions."""
    from safelane.safety.one_decision.forecast import forecast_gaps_of, forecast_keys_of

    xs, last, tail = scene
    available = np.ones(5, dtype=bool)
    pool = ((pool_bits >> np.arange(5)) & 1).astype(bool)
    expected = forecast_keys(forecast_gaps_of(xs, last, available, pool, *tail), margin)
    assert np.array_equal(forecast_keys_of(xs, last, available, pool, *tail, margin), expected)


def test_current_accelerations_are_highway_env_s() -> None:
    """forecast.current_accelerations (the rule's incentive_accelerations reads it) gives each car the acceleration
    highway-env's own ``acceleration(car, its front vehicle)`` commands, clipped to ±ACC_MAX: a timid car 11 m behind
    a slower aggressive one brakes at the limit, the aggressive one with a free lane at its set-point holds, an IDM car
    closing on a slower one brakes at the limit, one below its set-point with a free lane accelerates."""
    from safelane.env import scenarios
    from safelane.safety.one_decision.cut_ins import current_accelerations_of
    from safelane.sim.drivers import AggressiveDriver, TimidDriver

    cars = [
        scenarios.VehicleSpec(1, -3.0, 20.0, vehicle_class=TimidDriver),
        scenarios.VehicleSpec(1, 12.0, 15.0, vehicle_class=AggressiveDriver),
        scenarios.VehicleSpec(2, 30.0, 22.0),
        scenarios.VehicleSpec(2, 45.0, 18.0, target_speed=25.0),
    ]
    scene = scenarios.build_scene(0, 20.0, cars, mode="robust")
    shield = scene.shield
    state, dyn = shield.state_and_dynamics(shield.snapshot)
    got = current_accelerations_of(state, dyn)
    road = scene.env.unwrapped.road
    expected = []
    for car in scene.vehicles:
        front, _ = road.neighbour_vehicles(car)
        expected.append(float(np.clip(car.acceleration(car, front), -car.ACC_MAX, car.ACC_MAX)))
    order = np.argsort(state.x)  # the state's rows and the scene's cars, both by position along the road
    assert got[order] == pytest.approx(np.array(expected)[np.argsort([c.position[0] for c in scene.vehicles])],
                                       abs=1e-9)  # fmt: skip
    assert np.count_nonzero(got == -6.0) == 2 and np.count_nonzero(got == 0.0) == 1 and (got > 2.0).sum() == 1
