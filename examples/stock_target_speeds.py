"""What a new user meets: the robust shield over stock ``highway-fast-v0`` in dense traffic on a wide road.

highway-env's default ego set-points are ``[20, 25, 30]`` m/s: the ego cannot brake below 20 m/s, so the
safety rule's fallback (SLOWER to a standstill) does not exist and most states in traffic have no safe
action. This plays a random policy under ``SafetyShield(mode="robust", override=True)`` with the stock
set-points and with :func:`safelane.stoppable_action_config` (0, 5, ..., 30 m/s), and prints, per set-up,
the collisions and whether each crash came after a state with a safe action.

    python examples/stock_target_speeds.py [--lanes 5] [--density 2] [--episodes 30]

docs/guides/shield.md quotes its output (14/30 crashes with the stock set-points, all from states with no
safe action before them; 0/30 with set-points from 0 m/s).
"""

from __future__ import annotations

import argparse
import json
import warnings

import gymnasium as gym
import numpy as np

import safelane


def play(lanes: int, density: float, episodes: int, stoppable: bool) -> dict[str, object]:
    """Crashes of a random policy (seeded 0) under the robust shield, episodes seeded 0..episodes-1."""
    config: dict[str, object] = {"lanes_count": lanes, "vehicles_density": density}
    if stoppable:
        config["action"] = safelane.stoppable_action_config()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", safelane.CannotStopWarning)  # the point of the stock run
        env = safelane.SafetyShield(gym.make("highway-fast-v0", config=config), mode="robust", override=True)
        rng = np.random.default_rng(0)
        crashes = {"never_a_safe_state": 0, "after_a_safe_state": 0}
        fallback_states = states = 0
        for episode in range(episodes):
            _, info = env.reset(seed=episode)
            saw_safe = not info["fallback"]
            done = False
            while not done:
                _, _, terminated, truncated, info = env.step(int(rng.integers(5)))
                states += 1
                fallback_states += bool(info["fallback"])
                if info["crashed"]:
                    crashes["after_a_safe_state" if saw_safe else "never_a_safe_state"] += 1
                saw_safe |= not info["fallback"]
                done = terminated or truncated
    speeds = [float(s) for s in env.unwrapped.vehicle.target_speeds]
    return {"target_speeds": speeds, "episodes": episodes, "collisions": sum(crashes.values()),
            **crashes, "fallback_rate": fallback_states / max(states, 1)}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lanes", type=int, default=5)
    parser.add_argument("--density", type=float, default=2.0)
    parser.add_argument("--episodes", type=int, default=30)
    args = parser.parse_args()
    for stoppable in (False, True):
        print(json.dumps(play(args.lanes, args.density, args.episodes, stoppable)))


if __name__ == "__main__":
    main()
