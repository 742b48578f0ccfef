"""A sample of the shield for continuous actions in traffic: the fixed continuous policies, bare and shielded.

Runs ``--episodes`` episodes per (policy, density, decision rate) on the fast simulator under
``shield.mode: committed`` with ``actions: continuous`` and, on the same seeds, without a shield; writes a JSON
summary: collisions (from a certified start or not, rear-ended or not), episodes off the road, lapses (in the
model), plan-forced and projected decisions, the mean projection distance, the mean speed and the shield's
cost per decision.

    python research/continuous_shield_sample.py --episodes 20 --out sample.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from pathlib import Path

import numpy as np

from safelane.env.factory import make_env
from safelane.running.collisions import classify_collision
from safelane.running.policies import CONTINUOUS_POLICIES, continuous_policy

DENSITIES = (1.0, 2.0)
RATES = ((1, 5), (2, 10))


def run_cell(policy: str, density: float, rate: tuple[int, int], shield: bool, episodes: int, seed: int) -> dict:
    """One cell's totals."""
    sets = {"simulator": "fast", "actions": "continuous", "shield.mode": "committed" if shield else "none",
            "env.vehicles_density": density, "env.policy_frequency": rate[0], "env.simulation_frequency": rate[1]}
    env = make_env("fast", **sets)
    out = {"episodes": 0, "decisions": 0, "collisions": 0, "certified_collisions": 0, "rear_ended": 0,
           "uncertified_starts": 0, "off_road": 0, "lapses": 0, "lapses_in_model": 0, "plan_forced": 0,
           "projected": 0, "distance": 0.0, "speed": 0.0, "shield_s": 0.0}
    for episode in range(episodes):
        obs, info = env.reset(seed=seed + episode)
        certified = bool(info.get("certified", False))
        out["uncertified_starts"] += int(shield and not certified)
        act = continuous_policy(policy, seed + episode, env.unwrapped.config["action"])
        while True:
            start = time.perf_counter()
            obs, _, terminated, truncated, info = env.step(act(obs, info))
            out["shield_s"] += time.perf_counter() - start
            out["decisions"] += 1
            out["speed"] += float(info["speed"])
            if shield:
                certified = certified or bool(info["certified"])
                for key in ("lapse", "plan_forced", "projected"):
                    out[{"lapse": "lapses"}.get(key, key)] += int(info[key])
                out["lapses_in_model"] += int(info["lapse_in_model"])
                out["distance"] += float(info["projection_distance"])
            if terminated or truncated:
                break
        out["episodes"] += 1
        if info["crashed"]:
            out["collisions"] += 1
            out["certified_collisions"] += int(shield and certified)
            out["rear_ended"] += int(classify_collision(info["snapshot"]) == "rear_ended")
        out["off_road"] += int(info["off_road"])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    cells = []
    for policy, density, rate, shield in itertools.product(CONTINUOUS_POLICIES, DENSITIES, RATES, (False, True)):
        totals = run_cell(policy, density, rate, shield, args.episodes, args.seed)
        cells.append({"policy": policy, "density": density, "policy_frequency": rate[0], "shield": shield, **totals})
        print(json.dumps(cells[-1]), flush=True)
    summary = {}
    for shield in (False, True):
        rows = [c for c in cells if c["shield"] == shield]
        total = {k: sum(c[k] for c in rows) for k in rows[0] if isinstance(rows[0][k], int | float)
                 and not isinstance(rows[0][k], bool) and k not in ("density", "policy_frequency")}
        total["mean_speed"] = total.pop("speed") / total["decisions"]
        total["ms_per_decision"] = 1000 * total.pop("shield_s") / total["decisions"]
        total["mean_projection_distance"] = total.pop("distance") / total["decisions"]
        summary["shielded" if shield else "bare"] = total
    args.out.write_text(json.dumps({"cells": cells, "summary": summary}, indent=1))
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
