"""When highway-env's drivers decide a turn-in behind the ego, against the rule's incentive times.

``shield.level_when_incentive`` (docs/research/cut-ins.md, docs/research/turn-in-timing.md) starts a level car's
turn-in behind the ego at the
first frame of the decision at which MOBIL's incentive lets it, instead of from now: with
``shield.incentive_any_speed`` (the default) the first frame at which it *could*, over every speed the car and
the vehicles ahead of it can reach (``model.incentive_times_any_speed``, a bound); without, with the others at
constant speed or at their acceleration now (``model.incentive_times``; ``shield.incentive_accelerations``, the
constant speed alone without it: ``before_constant_speed_time``). This drives the real thing: on highway-env, an
IDM or Linear driver in the next lane that the ego overtakes, a slow leader ahead of it (so that moving behind the
ego pays), random rates, speeds and gaps; for every such car that decides to change into the ego's lane within the
decision, its decision frame against the times (``before_any_speed_time`` must be 0).

    .venv/bin/python research/turn_in_timing.py --cases 300 --seed 0 [--all-drivers]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from highway_env.vehicle.behavior import AggressiveVehicle, DefensiveVehicle, IDMVehicle, LinearVehicle

from safelane.env.scenarios import VehicleSpec, build_scene, find_shield
from safelane.safety.one_decision import reference as model


def one_case(rng: np.random.Generator, all_drivers: bool = False) -> dict | None:
    """One random scene; the decision time [s] and the rule's incentive times [s], or None if no turn-in. The
    driver: IDM (60 %) or Linear; with ``all_drivers`` IDM, Linear, Aggressive or Defensive, a quarter each."""
    pol, sim = [(1, 5), (2, 10), (3, 15), (5, 15)][int(rng.integers(4))]
    ve = float(rng.choice([15.0, 20.0, 25.0, 30.0]))
    vc = float(rng.uniform(3.0, ve - 3.0))
    dx, gap, vl = float(rng.uniform(-4.0, 15.0)), float(rng.uniform(7.0, 30.0)), 0.0
    vl = float(rng.uniform(0.0, vc))
    if all_drivers:
        driver = [IDMVehicle, LinearVehicle, AggressiveVehicle, DefensiveVehicle][int(rng.integers(4))]
    else:
        driver = IDMVehicle if rng.random() < 0.6 else LinearVehicle
    action = int(rng.choice([1, 3]))  # IDLE or FASTER
    specs = [VehicleSpec(2, dx, vc, vehicle_class=driver), VehicleSpec(2, dx + gap, vl, vehicle_class=driver)]
    sets = {"env.policy_frequency": pol, "env.simulation_frequency": sim}
    scene = build_scene(1, ve, specs, lanes_count=3, ego_target_speed=ve, **sets)
    car, leader = scene.vehicles
    leader.enable_lane_change = False
    shield = find_shield(scene.env)
    state, dyn = shield.state_and_dynamics(shield.snapshot)
    ego_x, ego_v = model.ego_trajectories(state, dyn)
    frames = dyn.frames_per_decision
    near = np.flatnonzero(np.abs(state.x - state.ego_x) > 1e-9)
    row = int(np.argmin(np.abs(state.x[near] - (state.ego_x + dx))))
    path = (ego_x[action, 0, : frames + 1], ego_v[action, 0, : frames + 1])
    incentive = float(model.incentive_times(state, dyn, near, *path)[row])
    constant_dyn = dyn.with_options(incentive_accelerations=False)
    constant = float(model.incentive_times(state, constant_dyn, near, *path)[row])
    bound = float(model.incentive_times_any_speed(state, dyn, near, *path)[row])
    frames_done, decided = [0], []
    policy, step = car.change_lane_policy, car.step

    def watched_policy() -> None:
        before = car.target_lane_index[2]
        policy()
        if car.target_lane_index[2] == 1 and before != 1 and not decided:
            decided.append(frames_done[0])

    def watched_step(dt: float) -> None:
        step(dt)
        frames_done[0] += 1

    car.change_lane_policy, car.step = watched_policy, watched_step
    scene.env.step(action)
    scene.env.close()
    if not decided:
        return None
    return {"driver": driver.__name__, "rate": [pol, sim], "decided_s": decided[0] * dyn.frame_dt,
            "incentive_s": incentive, "constant_speed_s": constant, "any_speed_s": bound}  # fmt: skip


def main() -> None:
    """Parse the arguments, drive the cases, print a JSON summary."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=300, help="random scenes to drive")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--all-drivers", action="store_true", help="also Aggressive and Defensive drivers")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    rows = [r for r in (one_case(rng, args.all_drivers) for _ in range(args.cases)) if r is not None]
    early = [r for r in rows if r["decided_s"] < r["incentive_s"] - 1e-9]
    never = [r for r in rows if not np.isfinite(r["incentive_s"])]
    early_bound = [r for r in rows if r["decided_s"] < r["any_speed_s"] - 1e-9]
    early_constant = [r for r in rows if r["decided_s"] < r["constant_speed_s"] - 1e-9]
    summary = {"cases": args.cases, "turn_ins_within_the_decision": len(rows), "before_incentive_time": len(early),
               "before_constant_speed_time": len(early_constant), "incentive_never": len(never),
               "before_any_speed_time": len(early_bound),
               "any_speed_never": sum(not np.isfinite(r["any_speed_s"]) for r in rows),
               "early": early, "early_any_speed": early_bound}  # fmt: skip
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
