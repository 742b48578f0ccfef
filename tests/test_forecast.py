"""The nominal forecast that ranks the fallback's choices (safelane.safety.forecast, shield.forecast_fallback):
its predictions against the simulators, and the scene it was made for."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from safelane.core.snapshot import RoadSnapshot
from safelane.core.spaces import IDLE, LANE_LEFT, LANE_RIGHT, SLOWER
from safelane.env import scenarios
from safelane.env.factory import make_env
from safelane.running.counterexamples import load_counterexample
from safelane.running.foresight import with_overrides
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
    alike = model.forecast_ranking(state, dataclasses.replace(dyn, forecast_contact_time=False), ego_x, available)
    assert alike[LANE_RIGHT] == dyn.margin and alike[SLOWER] == -1.0
    # shield.forecast_contact_time (experimental): SLOWER's key tells when it first touches the leader
    ranking = model.forecast_ranking(state, dataclasses.replace(dyn, forecast_contact_time=True), ego_x, available)
    assert ranking[LANE_RIGHT] == dyn.margin and -2.0 <= ranking[SLOWER] < -1.0


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


def test_forecast_keys_rank_collisions_by_first_contact() -> None:
    """forecast_keys: a clear action keeps its gap up to the margin; a forecast collision is −1 whatever its depth,
    or with by_contact_time −2 + (whole decisions before the contact) · decision / horizon — later contact, higher
    key; two contacts within one decision alike; an action with no contact time (a NaN gap, or unavailable)
    lowest."""
    gaps = np.array([2.5, 0.4, -3.0, -0.2, -1.0, np.nan])
    contact = np.array([math.inf, math.inf, 9.4, 1.6, 1.2, math.inf])  # [s]
    alike = forecast_keys(gaps, contact, 1.0, 12.0, 1.0, False)
    assert alike.tolist() == [1.0, 0.4, -1.0, -1.0, -1.0, -1.0]
    by_time = forecast_keys(gaps, contact, 1.0, 12.0, 1.0, True)
    assert by_time.tolist() == [1.0, 0.4, -2.0 + 9.0 / 12.0, -2.0 + 1.0 / 12.0, -2.0 + 1.0 / 12.0, -2.0]
    assert by_time[2] > by_time[3]  # the deeper overlap, nine decisions away, ranks above the shallow one in one
    half = forecast_keys(gaps, contact, 1.0, 12.0, 0.5, True)  # 2 decisions per second: 1.2 s and 1.6 s differ
    assert half[3] > half[4]


SPAWN = (
    Path(__file__).resolve().parent / "fixtures" / "claim" / "crashes" / "cell00127-seed4001270026-collision-step3.json"
)  # fmt: skip


@pytest.mark.parametrize("simulator", ["fast", "highway-env"])
def test_contact_time_drives_a_spawn_through(simulator: str) -> None:
    """The claim campaign's spawn ``cell00127-seed4001270026`` (2 lanes of Defensive drivers, 1 decision per
    second; nothing safe at the start): with every forecast collision alike the shield brakes (SLOWER, the
    worst case's least bad), brakes again, then turns left and is hit at decision 3 — the published crash. Ranked
    by first contact, LANE_LEFT's forecast contact (a Defensive car creeping into the ego stopped at the end of
    its braking fallback) comes later than SLOWER's (the leader ahead): the shield changes lane at once and the
    episode runs 13 decisions without a crash. The same on both simulators. (One spawn only: over the claim's
    whole campaign the option crashes more, docs/safety.md §6r, and it stays off.)"""
    cx = load_counterexample(SPAWN)
    executed: dict[bool, list[int]] = {}
    for contact_time in (False, True):
        env = make_env(with_overrides(cx.env_config(simulator), {"shield.forecast_contact_time": contact_time}))
        env.reset(seed=cx.seed)
        executed[contact_time], crashed = [], False
        for action in [*cx.actions, *[IDLE] * 10]:
            *_, terminated, truncated, info = env.step(int(action))
            executed[contact_time].append(info["executed_action"])
            crashed = bool(info["collision"])
            if crashed or terminated or truncated:
                break
        env.close()
        assert crashed == (not contact_time)
    assert executed[False] == [SLOWER, SLOWER, LANE_LEFT]
    assert executed[True][0] == LANE_LEFT and len(executed[True]) == 13


SIMULTANEOUS = SPAWN.parent / "cell00088-seed4000880026-collision-step3.json"


@pytest.mark.parametrize("simulator", ["fast", "highway-env"])
def test_lane_changes_see_a_car_move_over_with_the_ego(simulator: str) -> None:
    """The claim campaign's spawn ``cell00088-seed4000880026`` (2 lanes of Aggressive drivers, 1 decision per
    second; nothing safe), at its first decision: the ego at 25 m/s in lane 1, a car 18.8 m ahead at 21.5 m/s
    closing on its own leader, lane 0 empty. Keeping every car in its lane, the forecast has LANE_LEFT clear by
    more than the margin; in the episode the ego turns left and the car ahead moves to lane 0 too (MOBIL, the
    ego still in lane 1 for highway-env's neighbour search), and the ego hits it at decision 2. With
    shield.forecast_lane_changes (experimental: over the claim's campaign it crashes more, docs/safety.md §6r) the
    forecast makes the same move and sees LANE_LEFT collide, and SLOWER clear.
    (Which action the shield then allows is not asserted: nominal calls LANE_LEFT safe here, and robust picks its
    least-bad action among nominal's safe ones, so it keeps LANE_LEFT whatever the forecast says.)"""
    cx = load_counterexample(SIMULTANEOUS)
    env = make_env(cx.env_config(simulator))
    env.reset(seed=cx.seed)
    shield = env
    while not isinstance(shield, SafetyShield):
        shield = shield.env  # type: ignore[attr-defined]
    state, dyn = shield.state_and_dynamics(shield.snapshot)
    env.close()
    ego_x, _ = model.ego_trajectories(state, dyn)
    available = model.available_actions(state, dyn)
    keeping = dataclasses.replace(dyn, forecast_contact_time=True, forecast_lane_changes=False)
    changing = dataclasses.replace(dyn, forecast_contact_time=True, forecast_lane_changes=True)
    kept, changed = (model.forecast_ranking(state, d, ego_x, available) for d in (keeping, changing))
    assert kept[LANE_LEFT] == dyn.margin and kept[SLOWER] < -1.0
    assert changed[LANE_LEFT] < -1.0 and changed[SLOWER] == dyn.margin
