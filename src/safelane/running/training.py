"""Training: one explicit loop for all four methods, with exact resume.

``train(cfg, out_dir)`` reads top to bottom: reset → act (ε-greedy) → step → store → sample →
update → target sync → per-episode bookkeeping → checkpoint. The methods differ only inside the
agent (:mod:`safelane.agents.dqn`). What it writes into the run directory (``config.yaml``,
``metrics.csv``, ``tensorboard/``, ``checkpoint.pt``) is :mod:`safelane.running.run_directory`'s format.

Determinism: episode ``i`` (0-based) is reset with seed ``seed·100003 + i``; exploration and replay
sampling draw from the agent's one ``numpy.random.Generator``; torch runs single-threaded with
deterministic algorithms. So the same seed gives the same ``metrics.csv`` (wall time aside), and a
run killed at any moment and resumed from its checkpoint ends exactly as an uninterrupted one.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from safelane.agents.dqn import ConstrainedAgent, linear_epsilon, sanitize_mask
from safelane.agents.registry import make_agent
from safelane.config import ConfigError
from safelane.env.factory import make_env, observation_size
from safelane.reporting.metrics_file import METRIC_COLUMNS, METRICS_FILE, TIMING_COLUMNS, MetricsAppender, write_metrics
from safelane.running.run_directory import (
    CHECKPOINT_FILE,
    TENSORBOARD_DIR,
    TrainConfig,
    prepare_run_dir,
    resolve,
    restore_rng_states,
    save_checkpoint,
    training_snapshot,
)

EPISODE_SEED_STRIDE = 100003
"""Episode ``i`` of a run with seed ``s`` is reset with seed ``s·EPISODE_SEED_STRIDE + i``."""

TENSORBOARD_SCALARS: tuple[str, ...] = tuple(c for c in METRIC_COLUMNS if c not in ("episode", *TIMING_COLUMNS))
"""Columns logged with ``--tensorboard`` (per episode; wall time is TensorBoard's own axis)."""


@dataclass(frozen=True)
class EpisodeReport:
    """What the progress callback receives after each episode."""

    episode: int  # 1-based episode just finished
    episodes: int  # total episodes of the run
    episode_return: float
    length: int  # decisions
    collision: bool
    collisions: int  # collisions so far in the run
    epsilon: float
    steps_per_s: float  # environment decisions per second of wall time since this (re)start
    env_steps: int  # cumulative decisions
    lam: float | None  # constrained's λ, else None
    mean_loss: float | None


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`train`: the last completed episode was checkpointed; resume continues it."""

    def __init__(self, episode: int, checkpoint: Path) -> None:
        super().__init__(f"interrupted: {episode} episodes checkpointed in {checkpoint}; continue with --resume")
        self.episode = episode
        self.checkpoint = checkpoint


def episode_seed(seed: int, episode_index: int) -> int:
    """Reset seed of 0-based episode ``episode_index`` of a run seeded ``seed``."""
    return seed * EPISODE_SEED_STRIDE + episode_index


@contextlib.contextmanager
def deterministic_torch() -> Iterator[None]:
    """Single-threaded, deterministic torch for the duration of training (restored afterwards)."""
    threads = torch.get_num_threads()
    deterministic = torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(deterministic)
        torch.set_num_threads(threads)


def _summary_writer_class() -> Any:
    """torch's TensorBoard ``SummaryWriter``, or a one-line :class:`ConfigError` if not installed."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        raise ConfigError(
            "--tensorboard: the tensorboard package is not installed (pip install 'safelane[tensorboard]')"
        ) from None
    return SummaryWriter


def _mask_of(info: dict[str, Any]) -> np.ndarray:
    return sanitize_mask(info.get("action_mask"))


# --- the loop --------------------------------------------------------------------------------------
def train(
    cfg: TrainConfig,
    out_dir: str | Path,
    resume: bool = False,
    progress: Callable[[EpisodeReport], None] | None = None,
    tensorboard: bool = False,
) -> Path:
    """Train ``cfg.method`` for ``cfg.episodes`` episodes into ``out_dir``; return ``out_dir``.

    With ``resume`` the run continues from ``out_dir/checkpoint.pt`` (rows of ``metrics.csv`` past it
    are dropped) and ends exactly as an uninterrupted run would. ``progress`` is called after every
    episode with an :class:`EpisodeReport`. Ctrl-C checkpoints the last completed episode and raises
    :class:`TrainingInterrupted`. With ``tensorboard`` every numeric ``metrics.csv`` column is also
    logged to ``out_dir/tensorboard`` (needs the ``tensorboard`` package: ``safelane[tensorboard]``).
    """
    run = resolve(cfg)
    summary_writer_class = _summary_writer_class() if tensorboard else None
    acfg = run.agent
    out = Path(out_dir)
    state = prepare_run_dir(out, run, resume)
    checkpoint_path, metrics_path = out / CHECKPOINT_FILE, out / METRICS_FILE

    obs_size = observation_size(run.env)  # 26 for the paper's state; the network's input follows the state
    agent = make_agent(acfg, seed=cfg.seed, obs_size=obs_size)
    buffer = agent.new_replay(obs_size)  # transitions; a recurrent agent's keeps whole episodes
    rows: list[dict[str, Any]] = []
    episode, global_step, wall_before, env_time = 0, 0, 0.0, 0.0
    if state is not None:
        agent.load_state_dict(state["agent"])
        buffer.load_state_dict(state["buffer"])
        restore_rng_states(state["rng"])
        episode, global_step = int(state["episode"]), int(state["global_step"])
        rows, wall_before = [dict(r) for r in state["rows"]], float(state["wall_time_s"])
        env_time = float(rows[-1].get("env_time_s") or 0.0) if rows else 0.0
    write_metrics(metrics_path, rows)  # truncates rows past the checkpoint
    collisions = sum(int(r["collision"]) for r in rows)

    env = make_env(run.env)
    board = None
    if summary_writer_class is not None:
        # purge_step drops events a killed run logged past its checkpoint, as metrics.csv does.
        board = summary_writer_class(str(out / TENSORBOARD_DIR), purge_step=episode + 1)
    t0 = time.perf_counter()
    steps0 = global_step
    snapshot = state if state is not None else training_snapshot(run, agent, buffer, 0, 0, rows, 0.0)
    try:
        with deterministic_torch(), MetricsAppender(metrics_path) as metrics_file:
            while episode < cfg.episodes:
                # --- one episode -------------------------------------------------------------
                t_env = time.perf_counter()
                obs, info = env.reset(seed=episode_seed(cfg.seed, episode))
                env_time += time.perf_counter() - t_env
                agent.begin_episode()  # a recurrent agent's hidden state restarts with the episode
                buffer.begin_episode()
                mask = _mask_of(info)
                ep_return, length, speed_sum, ep_cost = 0.0, 0, 0.0, 0.0
                interventions, fallbacks, loss_sum, n_losses = 0, 0, 0.0, 0
                breaks = 0
                eps, collision, done = acfg.eps_start, False, False
                while not done:
                    eps = linear_epsilon(global_step, acfg, episode)
                    action = agent.act(obs, mask, eps)
                    t_env = time.perf_counter()
                    next_obs, reward, terminated, truncated, info = env.step(action)
                    env_time += time.perf_counter() - t_env
                    next_mask = _mask_of(info)
                    collision = bool(info.get("collision", False))
                    unsafe = not mask[action]
                    cost = 1.0 if (unsafe or collision) else 0.0
                    buffer.add(obs, action, reward, cost, next_obs, terminated, mask, next_mask)
                    global_step += 1

                    if global_step > acfg.learning_starts and global_step % acfg.train_freq == 0:
                        for _ in range(acfg.gradient_steps):
                            loss_sum += agent.update(buffer.sample(acfg.batch_size, agent.rng))
                            n_losses += 1
                    if global_step % acfg.target_update_interval == 0:
                        agent.sync_target()

                    ep_return += float(reward)
                    length += 1
                    speed_sum += float(info.get("speed", 0.0))
                    ep_cost += cost
                    interventions += int(unsafe)
                    fallbacks += int(bool(info.get("fallback", False)))
                    breaks += int(bool(info.get("invariant_break", False)))
                    obs, mask = next_obs, next_mask
                    done = terminated or truncated

                # --- bookkeeping at the episode boundary ---------------------------------------
                agent.end_episode(ep_cost)
                episode += 1
                collisions += int(collision)
                lam = agent.lam if isinstance(agent, ConstrainedAgent) else None
                elapsed = time.perf_counter() - t0
                row = {
                    "episode": episode,
                    "return": ep_return,
                    "length": length,
                    "collision": int(collision),
                    "mean_speed": speed_sum / max(length, 1),
                    "epsilon": eps,
                    "mean_loss": loss_sum / n_losses if n_losses else None,
                    "shield_interventions": interventions,
                    "fallbacks": fallbacks,
                    "invariant_breaks": breaks,
                    "lambda": lam,
                    "cost": ep_cost,
                    "wall_time_s": wall_before + elapsed,
                    "env_time_s": env_time,
                    "env_steps": global_step,
                }
                rows.append(row)
                metrics_file.append(row)
                if board is not None:
                    for key in TENSORBOARD_SCALARS:
                        if row[key] is not None:
                            board.add_scalar(f"train/{key}", float(row[key]), episode)
                snapshot = training_snapshot(run, agent, buffer, episode, global_step, rows, wall_before + elapsed)
                if episode % cfg.checkpoint_every == 0 or episode == cfg.episodes:
                    save_checkpoint(checkpoint_path, snapshot)
                if progress is not None:
                    progress(
                        EpisodeReport(
                            episode=episode,
                            episodes=cfg.episodes,
                            episode_return=ep_return,
                            length=length,
                            collision=collision,
                            collisions=collisions,
                            epsilon=eps,
                            steps_per_s=(global_step - steps0) / max(elapsed, 1e-9),
                            env_steps=global_step,
                            lam=lam,
                            mean_loss=row["mean_loss"],
                        )
                    )
    except KeyboardInterrupt:
        save_checkpoint(checkpoint_path, snapshot)
        write_metrics(metrics_path, snapshot["rows"])
        raise TrainingInterrupted(int(snapshot["episode"]), checkpoint_path) from None
    finally:
        env.close()
        if board is not None:
            board.close()
    return out
