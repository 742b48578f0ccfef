"""highway-env's MOBIL terms behind a car turning in at the ego: what made it change lane.

A crash file (``safelane falsify … --out DIR`` writes them under ``DIR/counterexamples/``) is replayed on
highway-env; during its last ``--last`` decisions every lane-change evaluation (``IDMVehicle.mobil``) of a car
within 8 m of the ego (centre to centre, along the road) into the ego's lane is recorded with its terms: the car's
own gain ``a(new leader) − a(old leader)`` [m/s²], the changes it imposes on its new and old followers, its
politeness p and threshold, MOBIL's ``jerk = own + p·(new follower + old follower)`` and the verdict. The first
evaluation that turned the car in is named as driven by its *own gain* (own ≥ threshold) or by *politeness*
(own < threshold ≤ jerk: a courtesy change for its old follower, which the rule's incentive models with its
``incentive_politeness``).

    .venv/bin/python research/mobil_terms.py runs/falsify/X/counterexamples/cell00643-…-collision-step17.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from highway_env.vehicle.behavior import IDMVehicle

from safelane.env.factory import make_env
from safelane.running.counterexamples import load_counterexample

NEAR = 8.0
"""[m] How far along the road from the ego a car's evaluations are recorded."""


def _acceleration(car: IDMVehicle, follower: Any, leader: Any) -> float:
    """``car.acceleration(ego_vehicle=follower, front_vehicle=leader)`` as MOBIL takes it (0 without a follower)."""
    return float(car.acceleration(ego_vehicle=follower, front_vehicle=leader)) if follower is not None else 0.0


def mobil_terms(path: Path, last: int) -> dict[str, Any]:
    """The MOBIL evaluations into the ego's lane of the cars near it in the last ``last`` decisions of ``path``."""
    cx = load_counterexample(path)
    env = make_env(cx.env_config("highway-env"))
    evaluations: list[dict[str, Any]] = []
    recording = [False]
    decision = [0]
    original = IDMVehicle.mobil

    def mobil(car: IDMVehicle, lane_index: Any) -> bool:
        verdict = original(car, lane_index)
        ego = env.unwrapped.vehicle
        if recording[0] and abs(car.position[0] - ego.position[0]) < NEAR and lane_index[2] == ego.lane_index[2]:
            new_leader, new_follower = car.road.neighbour_vehicles(car, lane_index)
            old_leader, old_follower = car.road.neighbour_vehicles(car)
            own = _acceleration(car, car, new_leader) - _acceleration(car, car, old_leader)
            new_change = _acceleration(car, new_follower, car) - _acceleration(car, new_follower, new_leader)
            old_change = _acceleration(car, old_follower, old_leader) - _acceleration(car, old_follower, car)
            evaluations.append({
                "decision": decision[0], "offset": round(float(car.position[0] - ego.position[0]), 2),
                "type": type(car).__name__, "politeness": car.POLITENESS, "threshold": car.LANE_CHANGE_MIN_ACC_GAIN,
                "own_gain": round(own, 3), "new_follower_change": round(new_change, 3),
                "old_follower_change": round(old_change, 3),
                "jerk": round(own + car.POLITENESS * (new_change + old_change), 3),
                "new_leader_is_ego": new_leader is ego, "turned_in": bool(verdict),
            })  # fmt: skip
        return verdict

    IDMVehicle.mobil = mobil
    try:
        env.reset(seed=cx.seed)
        for k, action in enumerate(cx.actions[: cx.step], start=1):
            recording[0], decision[0] = k > cx.step - last, k
            _, _, terminated, truncated, _ = env.step(int(action))
            if terminated or truncated:
                break
    finally:
        IDMVehicle.mobil = original
        env.close()
    turn_in = next((e for e in evaluations if e["turned_in"]), None)
    driven_by = None
    if turn_in is not None:
        driven_by = "own gain" if turn_in["own_gain"] >= turn_in["threshold"] else "politeness"
    return {"file": str(path), "evaluations": evaluations, "turn_in": turn_in, "driven_by": driven_by}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("file", type=Path, help="a crash file")
    parser.add_argument("--last", type=int, default=1, help="decisions before the crash whose evaluations to record")
    args = parser.parse_args()
    print(json.dumps(mobil_terms(args.file, args.last)))


if __name__ == "__main__":
    main()
