"""The nominal forecast that ranks the fallback's choices (safelane.safety.forecast, shield.forecast_fallback):
its predictions against the simulators, and the scene it was made for."""

from __future__ import annotations

import numpy as np
import pytest

from safelane.core.snapshot import RoadSnapshot
from safelane.core.spaces import IDLE, LANE_RIGHT, SLOWER
from safelane.env import scenarios
from safelane.env.factory import make_env
from safelane.safety import model
from safelane.safety.forecast import forecast_keys
from safelane.safety.model import MAX_HOLD_DECISIONS, RELEVANCE_RANGE
from safelane.safety.shield import SafetyShield


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
