"""Replay one episode of a finished training run and log its last decisions (e.g. a training crash).

Training is deterministic, so re-training a run's config up to episode N reproduces episode N exactly;
this wraps the environment to record, for that episode, every decision's action, the shield's mask of
the state it was taken in, whether the next state was a fallback (no safe action), the ego after the
decision and the vehicles within 80 m before it (all read from the road snapshots), and writes the last
``--keep`` decisions as JSON with the crash classification.

    python research/replay_training_episode.py runs/beyond3/runs/robust-s2 --episode 199 --out crash.json

Re-training costs as much as the original run up to N. ``--work DIR`` keeps the re-trained run there
(with checkpoints every 50 episodes), so a second replay of a later episode resumes instead.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Any

import gymnasium as gym
import yaml

import safelane.running.run_directory as run_directory
import safelane.running.training as training
from safelane.running.collisions import classify_collision

NEAR = 80.0  # [m] vehicles logged around the ego, along the road


class EpisodeLogger(gym.Wrapper):
    """Records the decisions of the ``target``-th episode (1-based) and writes them when it ends."""

    def __init__(self, env: gym.Env, target: int, out: Path, keep: int, first_episode: int) -> None:
        super().__init__(env)
        self.target, self.out, self.keep = target, out, keep
        self.episode = first_episode
        self.log: list[dict[str, Any]] = []

    def reset(self, **kwargs: Any) -> Any:
        self.episode += 1
        self.log = []
        obs, info = self.env.reset(**kwargs)
        self.snapshot = info["snapshot"]
        return obs, info

    def step(self, action: Any) -> Any:
        if self.episode != self.target:
            obs, reward, terminated, truncated, info = self.env.step(action)
            self.snapshot = info["snapshot"]
            return obs, reward, terminated, truncated, info
        before = self.snapshot
        e = before.ego
        near = [
            {
                "dx": float(before.position[i, 0] - before.position[e, 0]),
                "y": float(before.position[i, 1]),
                "speed": float(before.speed[i]),
                "heading": float(before.heading[i]),
                "lane": int(before.lane[i]),
                "target_lane": int(before.target_lane[i]),
            }
            for i in before.others()
            if abs(before.position[i, 0] - before.position[e, 0]) < NEAR
        ]
        mask = self.env.action_masks() if hasattr(self.env, "action_masks") else None
        obs, reward, terminated, truncated, info = self.env.step(action)
        after = self.snapshot = info["snapshot"]
        self.log.append(
            {
                "decision": len(self.log),
                "action": int(action),
                "mask": None if mask is None else [bool(m) for m in mask],
                "next_state_fallback": bool(info.get("fallback", False)),
                "ego_after": {
                    "x": float(after.position[after.ego, 0]),
                    "y": float(after.position[after.ego, 1]),
                    "speed": after.ego_speed,
                    "lane": int(after.lane[after.ego]),
                    "target_lane": int(after.target_lane[after.ego]),
                    "target_speed": after.ego_target_speed,
                },
                "near_before": near,
                "collision": bool(info.get("collision", False)),
            }
        )
        if terminated or truncated:
            kind = classify_collision(after) if info.get("collision") else None
            record = {"episode": self.target, "collision_kind": kind, "decisions": self.log[-self.keep :]}
            self.out.write_text(json.dumps(record, indent=1))
        return obs, reward, terminated, truncated, info


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--episode", type=int, required=True, help="1-based training episode to log")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--keep", type=int, default=15, help="how many of the last decisions to write")
    parser.add_argument("--work", type=Path, default=None, help="where to re-train (default: a temp dir)")
    args = parser.parse_args()
    stored = yaml.safe_load((args.run_dir / run_directory.CONFIG_FILE).read_text())["train"]
    cfg = run_directory.make_train_config(
        method=stored["method"],
        agent_preset=stored["agent_preset"],
        env_preset=stored["env_preset"],
        seed=stored["seed"],
        sets=stored["sets"],
        episodes=args.episode,
        checkpoint_every=50,
    )
    work = args.work or Path(tempfile.mkdtemp(prefix="safelane-replay-")) / "run"
    resume = (work / run_directory.CHECKPOINT_FILE).is_file()
    first = run_directory.load_checkpoint(work)["episode"] if resume else 0
    make_env = training.make_env

    def logged_env(*a: Any, **k: Any) -> gym.Env:
        return EpisodeLogger(make_env(*a, **k), args.episode, args.out, args.keep, first)

    training.make_env = logged_env  # the training loop builds its env through this name
    training.train(cfg, work, resume=resume)
    print(json.dumps({"out": str(args.out), "work": str(work)}))


if __name__ == "__main__":
    main()
