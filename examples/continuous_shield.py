"""Shield a continuous-control agent: train SB3's SAC on acceleration and steering, then drive it bare and shielded.

What it shows: ``gym.make("safelane/HighwayContinuousFast-v0", shield="committed")`` is the paper's highway with
the ego driven by acceleration and steering in [-1, 1] under the shield for continuous actions: every action is
executed only if a plan that starts with it and ends stopped in one lane keeps clear of every other car's reachable
set, else the verified action nearest it (projection). The same trained agent plays the same seeds twice — bare and
shielded — and the script prints, for each, the collisions, the episodes that left the road, how often the shield
projected the action and the mean speed.

Run:
    python examples/continuous_shield.py                 # SAC, 5 000 steps, 10 episodes each way
    python examples/continuous_shield.py --quick         # 64 steps, 1 short episode: a smoke test

Time: about 10 minutes on one core as set (the fast simulator steps in about 0.1 ms, SAC's updates dominate; the
shield costs a few milliseconds a decision); ``--quick`` about 20 s.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import safelane  # noqa: F401  (registers the safelane/ ids)

ENV_ID = "safelane/HighwayContinuousFast-v0"


def make_highway(shield: bool, duration: float) -> gym.Env:
    """The continuous highway, bare or under the shield; ``duration`` [s] per episode (one decision a second)."""
    return gym.make(ENV_ID, shield="committed" if shield else "none", config={"env.duration": duration})


def drive(model, shield: bool, episodes: int, duration: float, seed: int) -> tuple[int, int, int, int, float]:
    """(collisions, episodes off the road, decisions, projected decisions, mean speed [m/s]) of ``model`` driving
    ``episodes`` episodes deterministically from seeds ``seed, seed + 1, …``."""
    env = make_highway(shield, duration)
    collisions = off_road = decisions = projected = 0
    speeds: list[float] = []
    for episode in range(episodes):
        obs, info = env.reset(seed=seed + episode)
        while True:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, info = env.step(action)
            decisions += 1
            projected += int(info.get("projected", False))
            speeds.append(float(info["speed"]))
            if terminated or truncated:
                break
        collisions += int(info["crashed"])
        off_road += int(info["off_road"])
    env.close()
    return collisions, off_road, decisions, projected, float(np.mean(speeds))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=5000, help="SAC training steps (default 5000)")
    parser.add_argument("--episodes", type=int, default=10, help="test episodes each way (default 10)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="64 steps, 1 episode of 5 s: a smoke test")
    args = parser.parse_args()
    if args.steps < 1 or args.episodes < 1:
        parser.error("--steps and --episodes: must be at least 1")
    steps, episodes, duration = (64, 1, 5.0) if args.quick else (args.steps, args.episodes, 40.0)

    from stable_baselines3 import SAC

    env = make_highway(False, duration)
    model = SAC("MlpPolicy", env, learning_starts=min(100, steps // 2), seed=args.seed, device="cpu", verbose=0)
    model.learn(total_timesteps=steps)
    env.close()
    print(f"SAC trained {steps} steps on {ENV_ID}; {episodes} test episode(s) each way")
    print("           episodes collisions off_road decisions projected speed")
    for name, shield in (("bare", False), ("shielded", True)):
        collisions, off_road, decisions, projected, speed = drive(model, shield, episodes, duration, 1000)
        print(f"{name:<10} {episodes:>8} {collisions:>10} {off_road:>8} {decisions:>9} {projected:>9} {speed:>5.1f}")


if __name__ == "__main__":
    main()
