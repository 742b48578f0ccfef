"""Shield a Stable-Baselines3 agent: train it on highway-env, then drive it with and without safelane's shield.

What it shows: ``safelane.SafetyShield(env, mode="robust", override=True)`` wraps any highway-env environment;
with ``override=True`` an unsafe action is replaced by the closest safe one, so an agent that cannot read a
mask (SB3's DQN) drives under the shield unchanged. The same trained agent plays the same seeds twice — bare
and shielded — and the script prints the collisions of each and how often the shield stepped in. With
``--algo maskable-ppo`` the agent is sb3-contrib's MaskablePPO, which reads the shield's ``action_masks()``
while it learns and, shielded, while it drives.

Run:
    python examples/shield_sb3_agent.py                      # DQN, 20 000 steps, 20 episodes each way
    python examples/shield_sb3_agent.py --algo maskable-ppo
    python examples/shield_sb3_agent.py --quick              # 100 steps, 1 short episode: a smoke test

Time: about 10 minutes on one core as set (highway-env's ``highway-fast-v0`` plays a few dozen decisions a
second); ``--quick`` about 10 s. The environment is stock highway-env with set-points down to 0 m/s
(``safelane.stoppable_action_config``): with its default ``[20, 25, 30]`` m/s the ego cannot stop and
no shield can keep it clear of a slow car ahead.
"""

from __future__ import annotations

import argparse
from typing import Any

import gymnasium as gym
import numpy as np

import safelane  # also registers highway-env's environments
from safelane import SafetyShield


def make_highway(shield: str | None = None, duration: float = 30.0) -> gym.Env:
    """Stock ``highway-fast-v0`` with stoppable set-points: bare (``shield=None``), under the robust shield that
    only masks (``"mask"``) or under the robust shield that overrides unsafe actions (``"override"``).
    ``duration`` [s]: episode length (one decision a second)."""
    config = {"action": safelane.stoppable_action_config(), "duration": duration}
    env = gym.make("highway-fast-v0", config=config)
    if shield is not None:
        env = SafetyShield(env, mode="robust", override=shield == "override")
    return env


def train_agent(algo: str, timesteps: int, seed: int, duration: float) -> Any:
    """An SB3 agent trained on bare highway-env (DQN) or under the shield's masks (MaskablePPO)."""
    if algo == "dqn":
        from stable_baselines3 import DQN

        env = make_highway(None, duration)
        model = DQN("MlpPolicy", env, learning_starts=min(200, timesteps // 2), seed=seed, device="cpu", verbose=0)
    else:
        from sb3_contrib import MaskablePPO

        env = make_highway("mask", duration)  # it learns from its own actions, among the safe ones
        model = MaskablePPO("MlpPolicy", env, n_steps=min(256, timesteps), batch_size=64, seed=seed, device="cpu")
    model.learn(total_timesteps=timesteps)
    env.close()
    return model


def evaluate(model: Any, algo: str, shielded: bool, episodes: int, seed: int, duration: float) -> dict[str, float]:
    """Play ``episodes`` episodes (reset seeds ``seed, seed + 1, …``): collisions, decisions, interventions."""
    env = make_highway("override" if shielded else None, duration)
    read_masks = shielded and algo == "maskable-ppo"
    collisions = decisions = interventions = 0
    speeds: list[float] = []
    for i in range(episodes):
        obs, info = env.reset(seed=seed + i)
        done = False
        while not done:
            kwargs = {"action_masks": env.get_wrapper_attr("action_masks")()} if read_masks else {}
            action, _ = model.predict(obs, deterministic=True, **kwargs)
            obs, _, terminated, truncated, info = env.step(int(action))
            decisions += 1
            interventions += bool(info.get("shield_intervened", False))
            speeds.append(float(env.unwrapped.vehicle.speed))
            done = terminated or truncated
        collisions += bool(env.unwrapped.vehicle.crashed)
    env.close()
    return {
        "episodes": episodes,
        "collisions": collisions,
        "decisions": decisions,
        "interventions": interventions,
        "mean_speed": float(np.mean(speeds)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algo", choices=["dqn", "maskable-ppo"], default="dqn")
    parser.add_argument("--timesteps", type=int, default=20_000, help="training decisions")
    parser.add_argument("--episodes", type=int, default=20, help="evaluation episodes, each way")
    parser.add_argument("--duration", type=float, default=30.0, help="[s] episode length (stock: 30)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="100 training steps, 1 episode of 10 s each way")
    args = parser.parse_args()
    if args.quick:
        args.timesteps, args.episodes, args.duration = 100, 1, 10.0
    if args.timesteps < 1 or args.episodes < 1 or args.duration <= 0:
        parser.error("--timesteps, --episodes: must be >= 1; --duration: must be > 0")

    print(f"training {args.algo} for {args.timesteps} decisions on highway-fast-v0 …")
    model = train_agent(args.algo, args.timesteps, args.seed, args.duration)
    eval_seed = 1_000_000 + args.seed  # test episodes the agent did not train on
    print(f"{'':10} {'episodes':>8} {'collisions':>10} {'decisions':>9} {'interventions':>13} {'speed m/s':>9}")
    for label, shielded in (("bare", False), ("shielded", True)):
        r = evaluate(model, args.algo, shielded, args.episodes, eval_seed, args.duration)
        print(
            f"{label:10} {r['episodes']:>8} {r['collisions']:>10} {r['decisions']:>9} "
            f"{r['interventions']:>13} {r['mean_speed']:>9.2f}"
        )


if __name__ == "__main__":
    main()
