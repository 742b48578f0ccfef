"""Training a continuous agent (SAC, PPO, the Lagrangian SAC) with Stable-Baselines3, into a run directory.

``train_continuous(cfg, out_dir)`` builds the run's environment (:func:`safelane.env.factory.make_env`, the shield
for continuous actions too when ``shield.mode: committed``), wraps it in :class:`TrainingEpisodes` (episode ``i``
reset with :func:`~safelane.running.training.episode_seed`, the cost ``info["cost"]``, the simulator's clock), and
runs SB3's ``learn`` with one callback, :class:`RunRecorder`, which writes ``metrics.csv`` (one row per episode,
:data:`~safelane.reporting.metrics_file.CONTINUOUS_METRIC_COLUMNS`) and ``checkpoint.pt``.

The checkpoint is the one file a run resumes from, written atomically: SB3's ``save`` (networks, optimisers,
entropy coefficient, λ, counters) and ``save_replay_buffer``, as bytes, beside the metrics rows, the episode count
and every RNG state (python, numpy, torch, the action space's). Where it is taken:

* **SAC family** (one gradient step per decision): every ``checkpoint_steps`` decisions, at the next episode
  boundary, once its last transition is stored and trained on. A resume (after a kill or Ctrl-C) continues
  exactly as the uninterrupted run: the same rows, the same networks.
* **PPO**: at the first rollout boundary after every ``checkpoint_steps`` decisions (after the update), usually in
  the middle of an episode. A resume restores networks, optimiser, counters, RNG states and the finished episodes'
  rows; the episode in progress starts again from its reset (SB3 keeps no environment state), so the resumed run
  is a valid continuation, not a bit-identical one.

Ctrl-C asks the run to stop: the SAC family runs to the end of the episode in progress (at most ``env.duration``
decisions), checkpoints and stops; PPO stops at once and checkpoints its last update. A second Ctrl-C stops at
once, keeping the last checkpoint. Either way :class:`~safelane.running.training.TrainingInterrupted` is raised.
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from safelane.agents.continuous import load_model, make_model, model_bytes, replay_buffer_bytes, require_sb3
from safelane.config import ConfigError
from safelane.env.factory import make_env
from safelane.reporting.metrics_file import CONTINUOUS_METRIC_COLUMNS, METRICS_FILE, MetricsAppender, write_metrics
from safelane.running.run_directory import (
    CHECKPOINT_FILE,
    CHECKPOINT_FORMAT,
    TENSORBOARD_DIR,
    RunConfig,
    TrainConfig,
    prepare_run_dir,
    resolve,
    restore_rng_states,
    rng_states,
    run_config_dict,
    save_checkpoint,
)
from safelane.running.training import TrainingInterrupted, deterministic_torch, episode_seed


def transition_cost(info: dict[str, Any]) -> float:
    """The cost of one decision: 1 if it ended in a crash or off the road, else 0."""
    return float(bool(info.get("collision", False)) or bool(info.get("off_road", False)))


class TrainingEpisodes(gym.Wrapper):
    """The training environment's episodes: the ``k``-th reset (0-based, from ``first_episode``) uses the seed
    ``episode_seed(seed, k)`` whatever the caller passes; each step's ``info["cost"]`` (:func:`transition_cost`);
    ``env_time_s`` [s] spent inside the wrapped environment's reset and step."""

    def __init__(self, env: gym.Env, seed: int, first_episode: int = 0, env_time_s: float = 0.0) -> None:
        super().__init__(env)
        self.seed, self.episode, self.env_time_s = seed, first_episode, env_time_s

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        start = time.perf_counter()
        obs, info = self.env.reset(seed=episode_seed(self.seed, self.episode), options=options)
        self.env_time_s += time.perf_counter() - start
        self.episode += 1
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        start = time.perf_counter()
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.env_time_s += time.perf_counter() - start
        info["cost"] = transition_cost(info)
        return obs, reward, terminated, truncated, info


@dataclass(frozen=True)
class ContinuousEpisodeReport:
    """What the progress callback receives after each episode of a continuous run."""

    episode: int  # 1-based episode just finished
    env_steps: int  # cumulative decisions
    steps: int  # the run's decisions in all
    episode_return: float
    length: int  # decisions
    collision: bool
    off_road: bool
    collisions: int  # crashes so far in the run
    off_roads: int  # episodes ended off the road so far
    steps_per_s: float  # decisions per second of wall time since this (re)start
    lam: float | None  # sac-lagrangian's λ, else None


class EpisodeTally:
    """One episode's sums, step by step."""

    def __init__(self) -> None:
        self.ret = self.speed = self.cost = self.distance = 0.0
        self.length = self.interventions = 0
        self.collision = self.off_road = False

    def add(self, reward: float, info: dict[str, Any]) -> None:
        """Count one decision's ``reward`` and ``info``."""
        self.ret += reward
        self.length += 1
        self.speed += float(info.get("speed", 0.0))
        self.cost += float(info.get("cost", 0.0))
        self.collision = self.collision or bool(info.get("collision", False))
        self.off_road = bool(info.get("off_road", False))
        self.interventions += int(bool(info.get("projected", False)))
        self.distance += float(info.get("projection_distance", 0.0))


# --- the callback: metrics rows, checkpoints, stopping -------------------------------------------------------
class StopRequested(Exception):
    """Raised by :class:`RunRecorder` once it has checkpointed after a stop request (Ctrl-C)."""


def _recorder_base() -> type:
    require_sb3()
    from stable_baselines3.common.callbacks import BaseCallback

    return BaseCallback


def make_recorder(**kwargs: Any) -> Any:
    """A :class:`RunRecorder` (an SB3 ``BaseCallback``, defined on first use: SB3 is optional)."""

    class RunRecorder(_recorder_base()):  # type: ignore[misc]
        """SB3 callback: a ``metrics.csv`` row per finished episode, checkpoints, Ctrl-C (module docstring)."""

        def __init__(
            self,
            run: RunConfig,
            out: Path,
            rows: list[dict[str, Any]],
            episodes: TrainingEpisodes,
            metrics_file: MetricsAppender,
            wall_before: float,
            progress: Callable[[ContinuousEpisodeReport], None] | None,
        ) -> None:
            super().__init__(verbose=0)
            self.run, self.out, self.rows, self.episodes = run, out, rows, episodes
            self.metrics_file, self.wall_before, self.progress = metrics_file, wall_before, progress
            self.tally = EpisodeTally()
            self.pending: list[dict[str, Any]] = []  # finished episodes whose row waits for the agent's update
            self.at_boundary = False  # the last decision ended an episode (SAC family: an exact checkpoint)
            self.checkpointed_step = 0  # the decision count at the last checkpoint (or start)
            self.checkpointed_rows = len(rows)
            self.stop_requested = False
            self.start, self.start_steps = time.perf_counter(), 0
            self.collisions = sum(int(r["collision"]) for r in rows)
            self.off_roads = sum(int(r["off_road"]) for r in rows)

        @property
        def exact(self) -> bool:
            """Whether checkpoints fall on episode boundaries (the off-policy SAC family)."""
            from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

            return isinstance(self.model, OffPolicyAlgorithm)

        def _on_training_start(self) -> None:
            self.start, self.start_steps = time.perf_counter(), self.model.num_timesteps
            self.checkpointed_step = self.model.num_timesteps

        def _on_step(self) -> bool:
            info, reward = self.locals["infos"][0], float(self.locals["rewards"][0])
            self.tally.add(reward, info)
            self.at_boundary = bool(self.locals["dones"][0])
            if self.at_boundary:
                self.pending.append(self._row())
                self.tally = EpisodeTally()
                if not self.exact:  # PPO: no update per decision to wait for
                    self._write_pending()
            return self.exact or not self.stop_requested  # PPO stops at once; its last update is checkpointed

        def _on_rollout_end(self) -> None:
            self._write_pending()  # the SAC family: after the last decision's transition is stored (λ updated)

        def _on_rollout_start(self) -> None:
            due = self.model.num_timesteps - self.checkpointed_step >= int(self.run.train.checkpoint_steps or 1)
            if (due or self.stop_requested) and (self.at_boundary or not self.exact):
                self.checkpoint()
                if self.stop_requested:
                    raise StopRequested

        def _row(self) -> dict[str, Any]:
            t = self.tally
            return {
                "episode": len(self.rows) + len(self.pending) + 1,
                "return": t.ret,
                "length": t.length,
                "collision": int(t.collision),
                "off_road": int(t.off_road),
                "mean_speed": t.speed / max(t.length, 1),
                "cost": t.cost,
                "shield_interventions": t.interventions,
                "mean_projection_distance": t.distance / max(t.length, 1),
                "env_steps": int(self.model.num_timesteps),
            }

        def _write_pending(self) -> None:
            lam = getattr(self.model, "lam", None)
            for row in self.pending:
                elapsed = time.perf_counter() - self.start
                row.update(
                    {"lambda": lam, "wall_time_s": self.wall_before + elapsed, "env_time_s": self.episodes.env_time_s}
                )
                self.rows.append(row)
                self.metrics_file.append(row)
                self.collisions += row["collision"]
                self.off_roads += row["off_road"]
                if self.progress is not None:
                    self.progress(
                        ContinuousEpisodeReport(
                            episode=row["episode"],
                            env_steps=row["env_steps"],
                            steps=int(self.run.train.steps or 0),
                            episode_return=row["return"],
                            length=row["length"],
                            collision=bool(row["collision"]),
                            off_road=bool(row["off_road"]),
                            collisions=self.collisions,
                            off_roads=self.off_roads,
                            steps_per_s=(self.model.num_timesteps - self.start_steps) / max(elapsed, 1e-9),
                            lam=lam,
                        )
                    )
            self.pending = []

        def checkpoint(self) -> None:
            """Save the whole training state to ``checkpoint.pt`` (atomically)."""
            self._write_pending()
            wall = self.wall_before + time.perf_counter() - self.start
            save_checkpoint(
                self.out / CHECKPOINT_FILE,
                training_state(self.run, self.model, self.rows, wall, self.episodes.env_time_s, self.at_boundary),
            )
            self.checkpointed_step = self.model.num_timesteps
            self.checkpointed_rows = len(self.rows)

    return RunRecorder(**kwargs)


def training_state(
    run: RunConfig,
    model: Any,
    rows: list[dict[str, Any]],
    wall_time_s: float,
    env_time_s: float,
    at_episode_start: bool,
) -> dict[str, Any]:
    """A self-contained copy of a continuous run's training state (what ``checkpoint.pt`` holds)."""
    return {
        "format": CHECKPOINT_FORMAT,
        "config": run_config_dict(run),
        "algo": run.train.algo,
        "episode": len(rows),
        "global_step": int(model.num_timesteps),
        "at_episode_start": bool(at_episode_start),
        "model": model_bytes(model),
        "replay_buffer": replay_buffer_bytes(model),
        "rows": [dict(r) for r in rows],
        "wall_time_s": float(wall_time_s),
        "env_time_s": float(env_time_s),
        "rng": rng_states(),
        "action_space_rng": model.action_space.np_random.bit_generator.state,
    }


@contextlib.contextmanager
def deferred_interrupt(recorder: Any) -> Iterator[None]:
    """While training: the first Ctrl-C asks ``recorder`` to stop at its next checkpoint, a second one stops at
    once (a ``KeyboardInterrupt``). Only in the main thread (elsewhere signals cannot be caught)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def ask_to_stop(signum: int, frame: Any) -> None:
        if recorder.stop_requested:
            raise KeyboardInterrupt
        recorder.stop_requested = True

    previous = signal.signal(signal.SIGINT, ask_to_stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


# --- the run ----------------------------------------------------------------------------------------------------
def train_continuous(
    cfg: TrainConfig,
    out_dir: str | Path,
    resume: bool = False,
    progress: Callable[[ContinuousEpisodeReport], None] | None = None,
    tensorboard: bool = False,
) -> Path:
    """Train ``cfg.algo`` for ``cfg.steps`` decisions into ``out_dir``; return ``out_dir``.

    With ``resume`` the run continues from ``out_dir/checkpoint.pt`` (rows of ``metrics.csv`` past it are dropped;
    what is restored: module docstring). ``progress`` is called after every episode with a
    :class:`ContinuousEpisodeReport`. Ctrl-C checkpoints and raises
    :class:`~safelane.running.training.TrainingInterrupted`. ``tensorboard``: SB3's own logs (losses, λ) in
    ``out_dir/tensorboard``.
    """
    if cfg.algo is None or cfg.steps is None:
        raise ConfigError("train_continuous: the config names no algo; the DQN methods train with train()")
    require_sb3()
    from stable_baselines3.common.vec_env import DummyVecEnv

    if tensorboard:
        try:
            import tensorboard as _  # noqa: F401  (SB3 writes through torch's SummaryWriter)
        except ImportError:
            raise ConfigError(
                "--tensorboard: the tensorboard package is not installed (pip install 'safelane[tensorboard]')"
            ) from None
    run = resolve(cfg)
    out = Path(out_dir)
    state = prepare_run_dir(out, run, resume)
    checkpoint_path, metrics_path = out / CHECKPOINT_FILE, out / METRICS_FILE
    rows = [dict(r) for r in state["rows"]] if state is not None else []
    write_metrics(metrics_path, rows, CONTINUOUS_METRIC_COLUMNS)  # truncates rows past the checkpoint

    env = TrainingEpisodes(
        make_env(run.env),
        cfg.seed,
        first_episode=len(rows),
        env_time_s=float(state["env_time_s"]) if state is not None else 0.0,
    )
    vec = DummyVecEnv([lambda: env])
    board = str(out / TENSORBOARD_DIR) if tensorboard else None
    try:
        with deterministic_torch():
            if state is None:
                model = make_model(run.agent, vec, cfg.seed)  # type: ignore[arg-type]
            else:
                model = load_model(cfg.algo, state["model"], env=vec, replay_buffer=state["replay_buffer"])
                restore_rng_states(state["rng"])
                model.action_space.np_random.bit_generator.state = state["action_space_rng"]
                model._last_obs = vec.reset()  # the episode the checkpoint was taken in, from its reset
                model._last_episode_starts = np.ones((vec.num_envs,), dtype=bool)
                if hasattr(model, "episode_costs"):  # the Lagrangian SAC's cost so far of the episode restarted
                    model.episode_costs = [0.0] * vec.num_envs
            model.tensorboard_log = board
            wall_before = float(state["wall_time_s"]) if state is not None else 0.0
            with MetricsAppender(metrics_path, CONTINUOUS_METRIC_COLUMNS) as metrics_file:
                recorder = make_recorder(
                    run=run,
                    out=out,
                    rows=rows,
                    episodes=env,
                    metrics_file=metrics_file,
                    wall_before=wall_before,
                    progress=progress,
                )
                remaining = cfg.steps - int(model.num_timesteps)
                try:
                    with deferred_interrupt(recorder):
                        if remaining > 0:  # else: the run is finished, its checkpoint stands
                            model.learn(
                                remaining, callback=recorder, reset_num_timesteps=state is None, tb_log_name=cfg.algo
                            )
                            if recorder.stop_requested:  # PPO stopped at once
                                raise StopRequested
                            recorder.checkpoint()
                except StopRequested:
                    if recorder.checkpointed_rows != len(rows) or not checkpoint_path.exists():
                        recorder.checkpoint()
                    raise TrainingInterrupted(len(rows), checkpoint_path) from None
                except KeyboardInterrupt:  # a second Ctrl-C: the last checkpoint stands
                    kept = rows[: recorder.checkpointed_rows]
                    write_metrics(metrics_path, kept, CONTINUOUS_METRIC_COLUMNS)
                    raise TrainingInterrupted(len(kept), checkpoint_path) from None
    finally:
        vec.close()
    return out
