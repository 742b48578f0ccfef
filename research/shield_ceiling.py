"""How fast can any policy drive under the shield? A FASTER-first overtaking heuristic that reads the
whole road snapshot (an upper-bound probe with full knowledge of the scene, not a learner).

Each decision: FASTER when the mask allows it; else a lane change allowed by the mask into a lane whose
next car ahead is more than 10 m farther than in the ego's lane (the farther one); else IDLE; else the
last allowed action (SLOWER first). Episodes are reset with seeds ``seed … seed + episodes − 1``.

    python research/shield_ceiling.py --shield robust --episodes 10 --policy-frequency 2

prints one JSON line: collisions, mean speed over all decisions [m/s], fallback rate (per decision).
``--policy-frequency F`` runs F decisions per second with physics at 5·F Hz (the ``fast`` preset has
F = 1).
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from safelane.env.factory import make_env
from safelane.running.policies import overtaking_probe  # the heuristic described above (also --policy probe)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shield", choices=["nominal", "robust"], default="robust")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=5000)
    parser.add_argument("--policy-frequency", type=int, default=1)
    args = parser.parse_args()
    pf = args.policy_frequency
    env = make_env(
        "fast", **{"shield.mode": args.shield, "env.policy_frequency": pf, "env.simulation_frequency": 5 * pf}
    )
    collisions, speeds, fallbacks = 0, [], 0
    for k in range(args.episodes):
        obs, info = env.reset(seed=args.seed + k)
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(overtaking_probe(obs, info))
            speeds.append(info["speed"])
            fallbacks += bool(info["fallback"])
            done = terminated or truncated
        collisions += bool(info["collision"])
    print(
        json.dumps(
            {
                "shield": args.shield,
                "policy_frequency": pf,
                "episodes": args.episodes,
                "collisions": collisions,
                "mean_speed": float(np.mean(speeds)),
                "fallback_rate": fallbacks / len(speeds),
            }
        )
    )


if __name__ == "__main__":
    main()
