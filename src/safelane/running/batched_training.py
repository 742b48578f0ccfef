"""Many training runs as one: their environments in fast batches, their learners one batched computation.

``train_batched(cfgs, out_dirs)`` trains every :class:`~safelane.running.run_directory.TrainConfig` of ``cfgs``
into its own run directory, as :func:`safelane.running.training.train` would — the same ``config.yaml``,
``metrics.csv`` rows and ``checkpoint.pt`` format, the same numbers bit for bit (wall and environment
times aside) — but steps all runs' environments together (one :class:`safelane.env.fast_batch.FastBatch`
per distinct environment configuration: methods train on different shield modes) and updates all their
networks in one batched computation (:class:`safelane.agents.batched.BatchedLearner`). The loop below is
``train``'s loop with a leading run dimension; each run keeps its own episode counter, decision counter,
ε, updates, target syncs, λ and checkpoints. A finished run leaves the batch; the others continue.

Resume: each run continues from its own ``checkpoint.pt`` (written every ``checkpoint_every`` of its
episodes and at its end), so runs may resume at different decision counts — runs are independent, so each
ends exactly as uninterrupted. A run directory trained here can also be resumed, evaluated or loaded by
the per-run tools. Only the fast simulator is batched (:func:`safelane.env.fast_batch.supports`); the
per-run trainer stays for highway-env and as the reference.

Times in ``metrics.csv``: ``wall_time_s`` and ``env_time_s`` are each run's share of the batch's clocks (every
decision's time split evenly among the runs that took one), so they add up over a batch's runs to its wall
time, as the runs' own clocks add up over runs trained one by one.
"""

from __future__ import annotations

import csv
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from safelane.agents.batched import BatchedLearner
from safelane.agents.dqn import RECURRENT_METHODS, ConstrainedAgent, linear_epsilon, load_agent_config
from safelane.config import ConfigError, config_to_dict
from safelane.core.spaces import N_ACTIONS, OBS_SIZE
from safelane.env.factory import observation_size
from safelane.env.fast_batch import FastBatch, supports
from safelane.reporting.metrics_file import METRICS_FILE, MetricsAppender, write_metrics
from safelane.running.run_directory import (
    CHECKPOINT_FILE,
    RunConfig,
    TrainConfig,
    make_train_config,
    prepare_run_dir,
    resolve,
    save_checkpoint,
    training_snapshot,
)
from safelane.running.training import EpisodeReport, deterministic_torch, episode_seed


class _BufferOf:
    """Run ``k``'s replay buffer as ``training_snapshot`` reads it (``state_dict``)."""

    def __init__(self, learner: BatchedLearner, k: int) -> None:
        self.learner, self.k = learner, k

    def state_dict(self) -> dict[str, Any]:
        return self.learner.buffer_state(self.k)


def _sanitized(masks: np.ndarray) -> np.ndarray:
    """Masks with an all-False row made all True (:func:`safelane.agents.dqn.sanitize_mask`, row by row)."""
    out = masks.copy()
    out[~out.any(axis=1)] = True
    return out


def batchable(cfg: TrainConfig) -> str | None:
    """None when :func:`train_batched` trains ``cfg`` (its environment runs in a fast batch), else why not."""
    return refusal(resolve(cfg))


def refusal(run: RunConfig) -> str | None:
    """Why :func:`train_batched` cannot train ``run`` (a recurrent agent, or an environment the fast batch does not
    play), or None."""
    method = getattr(run.agent, "method", None)
    if method in RECURRENT_METHODS:
        return f"method: {method} (the batched learner's agents are feed-forward)"
    return supports(run.env)


def train_batched(
    cfgs: Sequence[TrainConfig],
    out_dirs: Sequence[str | Path],
    resume: bool = False,
    progress: Callable[[int, EpisodeReport], None] | None = None,
) -> list[Path]:
    """Train run ``k`` = ``cfgs[k]`` into ``out_dirs[k]`` for every ``k``, all in one batched loop; return
    the run directories. Each ends as ``train(cfgs[k], out_dirs[k])`` alone (module docstring). With
    ``resume`` each run continues from its own checkpoint. ``progress(k, report)`` after every episode of
    run ``k``. All runs share ``agent.batch_size``; environments must run on the fast batch."""
    if len(cfgs) != len(out_dirs) or not cfgs:
        raise ConfigError(f"runs: one output directory per run and at least one run (got {len(cfgs)}, {len(out_dirs)})")
    outs = [Path(o) for o in out_dirs]
    if len(set(outs)) != len(outs):
        raise ConfigError("out_dirs: each run needs its own directory")
    runs: list[RunConfig] = [resolve(c) for c in cfgs]
    for run in runs:
        why = refusal(run)
        if why is not None:
            raise ConfigError(f"{why}: batched training runs the fast batch; train this run alone")
    n = len(runs)
    sizes = sorted({observation_size(r.env) for r in runs})
    if len(sizes) > 1:
        raise ConfigError(f"state: runs trained together share the observation size (got {sizes} numbers)")
    learner = BatchedLearner([r.agent for r in runs], [c.seed for c in cfgs], sizes[0])
    states = [prepare_run_dir(o, r, resume) for o, r in zip(outs, runs, strict=True)]
    episode = np.zeros(n, dtype=np.int64)
    global_step = np.zeros(n, dtype=np.int64)
    rows: list[list[dict[str, Any]]] = [[] for _ in range(n)]
    wall_before = np.zeros(n)
    env_before = np.zeros(n)
    learner.load_runs({k: (state["agent"], state["buffer"]) for k, state in enumerate(states) if state is not None})
    for k, state in enumerate(states):
        if state is None:
            continue
        episode[k], global_step[k] = int(state["episode"]), int(state["global_step"])
        rows[k] = [dict(r) for r in state["rows"]]
        wall_before[k] = float(state["wall_time_s"])
        env_before[k] = float(rows[k][-1].get("env_time_s") or 0.0) if rows[k] else 0.0
    for k in range(n):
        write_metrics(outs[k] / METRICS_FILE, rows[k])  # truncates rows past the checkpoint
    collisions = np.array([sum(int(r["collision"]) for r in rows[k]) for k in range(n)])
    episodes = np.array([c.episodes for c in cfgs], dtype=np.int64)
    acfg = [r.agent for r in runs]
    learning_starts = np.array([a.learning_starts for a in acfg])
    train_freq = np.array([a.train_freq for a in acfg])
    gradient_steps = np.array([a.gradient_steps for a in acfg])
    target_interval = np.array([a.target_update_interval for a in acfg])
    finished = episode >= episodes
    if finished.any():
        learner.retire(np.flatnonzero(finished).tolist())

    # One fast batch per distinct environment configuration (dqn and constrained train on nominal masks,
    # robust on robust ones); batch_of[k], row_of[k]: run k's batch and row.
    by_env: dict[str, list[int]] = {}
    for k, run in enumerate(runs):
        by_env.setdefault(yaml.safe_dump(config_to_dict(run.env), sort_keys=True), []).append(k)
    batches = [(FastBatch(runs[ks[0]].env, len(ks)), np.array(ks, dtype=np.int64)) for ks in by_env.values()]
    batch_of = np.zeros(n, dtype=np.int64)
    row_of = np.zeros(n, dtype=np.int64)
    for b, (_, ks) in enumerate(batches):
        batch_of[ks], row_of[ks] = b, np.arange(len(ks))

    obs = np.zeros((n, learner.obs.shape[2]), dtype=np.float32)
    mask = np.ones((n, learner.masks.shape[2]), dtype=bool)
    ep_return, speed_sum, ep_cost = np.zeros(n), np.zeros(n), np.zeros(n)
    length, interventions, fallbacks, breaks, n_losses = (np.zeros(n, dtype=np.int64) for _ in range(5))
    loss_sum = np.zeros(n)
    eps_now = np.zeros(n)
    # Each run's share of the batch's clocks: a step's wall and environment time split among its runs.
    wall_share, env_share = np.zeros(n), np.zeros(n)
    env_pending = 0.0  # environment time not yet shared out

    def reset(ks: list[int]) -> None:
        for b, (batch, _) in enumerate(batches):
            mine = [k for k in ks if batch_of[k] == b]
            if mine:
                batch.reset_envs(row_of[mine], [episode_seed(cfgs[k].seed, int(episode[k])) for k in mine])
                obs[mine] = batch.obs[row_of[mine]]
                mask[mine] = _sanitized(batch.masks[row_of[mine]])
        for arr in (ep_return, speed_sum, ep_cost, length, interventions, fallbacks, breaks, n_losses, loss_sum):
            arr[ks] = 0

    appenders = [MetricsAppender(o / METRICS_FILE) for o in outs]  # closed in finally
    t0 = last_charge = time.perf_counter()
    steps0 = global_step.copy()
    try:
        with deterministic_torch():
            t_env = time.perf_counter()
            reset(np.flatnonzero(~finished).tolist())
            env_pending += time.perf_counter() - t_env
            while not finished.all():
                active = np.flatnonzero(~finished)
                for k in active.tolist():
                    eps_now[k] = linear_epsilon(int(global_step[k]), acfg[k], int(episode[k]))
                actions = np.zeros(n, dtype=np.int64)
                actions[active] = learner.act(active, obs[active], mask[active], eps_now[active])
                reward, speed = np.zeros(n), np.zeros(n)
                terminated, truncated, collision, fallback, broke = (np.zeros(n, dtype=bool) for _ in range(5))
                next_obs, next_mask = obs.copy(), mask.copy()
                t_env = time.perf_counter()
                for batch, ks in batches:
                    live = ks[~finished[ks]]
                    if live.size == 0:
                        continue
                    r = row_of[live]
                    out = batch.step(actions[live], r)
                    reward[live], terminated[live], truncated[live] = out.rewards, out.terminated, out.truncated
                    collision[live], speed[live] = out.collision, out.speed
                    fallback[live], broke[live] = out.fallback, out.invariant_break
                    next_obs[live] = batch.obs[r]
                    next_mask[live] = _sanitized(batch.masks[r])
                env_pending += time.perf_counter() - t_env
                unsafe = ~mask[active, actions[active]]
                cost = (unsafe | collision[active]).astype(float)
                learner.store(
                    active, obs[active], actions[active], reward[active], cost, next_obs[active],
                    terminated[active], mask[active], next_mask[active],
                )  # fmt: skip
                global_step[active] += 1
                gs = global_step[active]
                due = active[(gs > learning_starts[active]) & (gs % train_freq[active] == 0)]
                for j in range(int(gradient_steps[due].max()) if due.size else 0):
                    sub = due[gradient_steps[due] > j]
                    loss_sum[sub] += learner.update(sub)
                    n_losses[sub] += 1
                learner.sync_target(active[gs % target_interval[active] == 0])
                ep_return[active] += reward[active]
                length[active] += 1
                speed_sum[active] += speed[active]
                ep_cost[active] += cost
                interventions[active] += unsafe
                fallbacks[active] += fallback[active]
                breaks[active] += broke[active]
                obs[active], mask[active] = next_obs[active], next_mask[active]
                now = time.perf_counter()
                wall_share[active] += (now - last_charge) / active.size
                env_share[active] += env_pending / active.size
                last_charge, env_pending = now, 0.0

                # --- bookkeeping at the episode boundaries of the runs that finished one ----------------
                ended = active[terminated[active] | truncated[active]]
                done_runs: list[int] = []
                for k in ended.tolist():
                    learner.end_episode(k, float(ep_cost[k]))
                    episode[k] += 1
                    collisions[k] += int(collision[k])
                    agent = learner.agents[k]
                    lam = agent.lam if isinstance(agent, ConstrainedAgent) else None
                    elapsed = time.perf_counter() - t0
                    row = {
                        "episode": int(episode[k]),
                        "return": float(ep_return[k]),
                        "length": int(length[k]),
                        "collision": int(collision[k]),
                        "mean_speed": float(speed_sum[k]) / max(int(length[k]), 1),
                        "epsilon": float(eps_now[k]),
                        "mean_loss": float(loss_sum[k]) / int(n_losses[k]) if n_losses[k] else None,
                        "shield_interventions": int(interventions[k]),
                        "fallbacks": int(fallbacks[k]),
                        "invariant_breaks": int(breaks[k]),
                        "lambda": lam,
                        "cost": float(ep_cost[k]),
                        "wall_time_s": float(wall_before[k] + wall_share[k]),
                        "env_time_s": float(env_before[k] + env_share[k]),
                        "env_steps": int(global_step[k]),
                    }
                    rows[k].append(row)
                    appenders[k].append(row)
                    last = episode[k] == episodes[k]
                    if episode[k] % cfgs[k].checkpoint_every == 0 or last:
                        learner.export(k)
                        snapshot = training_snapshot(
                            runs[k], agent, _BufferOf(learner, k), int(episode[k]), int(global_step[k]), rows[k],
                            row["wall_time_s"],
                        )  # fmt: skip
                        save_checkpoint(outs[k] / CHECKPOINT_FILE, snapshot)
                    if progress is not None:
                        progress(
                            k,
                            EpisodeReport(
                                episode=int(episode[k]),
                                episodes=int(episodes[k]),
                                episode_return=row["return"],
                                length=row["length"],
                                collision=bool(collision[k]),
                                collisions=int(collisions[k]),
                                epsilon=row["epsilon"],
                                steps_per_s=float(global_step[k] - steps0[k]) / max(elapsed, 1e-9),
                                env_steps=int(global_step[k]),
                                lam=lam,
                                mean_loss=row["mean_loss"],
                            ),
                        )
                    if last:
                        finished[k] = True
                        done_runs.append(k)
                if done_runs:
                    learner.retire(done_runs)
                restart = [k for k in ended.tolist() if not finished[k]]
                if restart:
                    t_env = time.perf_counter()
                    reset(restart)
                    env_pending += time.perf_counter() - t_env
    finally:
        for appender in appenders:
            appender.close()
        for batch, _ in batches:
            batch.close()
    return outs


# --- throughput ------------------------------------------------------------------------------------
def measure_batched_training(
    runs: int, episodes: int = 10, seed: int = 0, shield: str = "robust", method: str = "robust"
) -> float:
    """All runs' decisions per second together [1/s] of :func:`train_batched` (its loop's clock) with ``runs`` runs of
    ``method`` (seeds ``seed`` … ``seed + runs − 1``, ``episodes`` episodes each, the bench's settings:
    ``tuned`` agent, ``fast`` preset on the fast simulator under ``shield``, learning from decision 64)."""
    sets = [f"shield.mode={shield}", "agent.learning_starts=64", "simulator=fast"]
    cfgs = [make_train_config(method=method, episodes=episodes, seed=seed + i, sets=sets) for i in range(runs)]
    with tempfile.TemporaryDirectory(prefix="safelane-bench-batched-") as tmp:
        outs = [Path(tmp) / f"run{i}" for i in range(runs)]
        train_batched(cfgs, outs)
        last = [_last_row(o) for o in outs]
    # The runs' shares of the batch's clock add up to its loop's wall time (setup excluded, as for one run).
    return sum(int(row["env_steps"]) for row in last) / sum(float(row["wall_time_s"]) for row in last)


def _last_row(run_dir: Path) -> dict[str, str]:
    with open(run_dir / METRICS_FILE) as f:
        return list(csv.DictReader(f))[-1]


def train_batched_steps_per_s(
    sizes: Sequence[int] = (10, 40), episodes: int = 10, seed: int = 0, shield: str = "robust"
) -> dict[str, float]:
    """``{str(S): all runs' decisions per second}`` of :func:`measure_batched_training` for each S in
    ``sizes`` (robust runs; call on one thread: ``torch.set_num_threads(1)``, numba's batches on one)."""
    # Compile (or load) the kernels outside the timings: the batch's, and the acting one (ε = 1 acts at random).
    measure_batched_training(1, 1, seed, shield)
    BatchedLearner([load_agent_config()], [seed]).greedy(
        np.zeros(1, dtype=np.int64), np.zeros((1, OBS_SIZE)), np.ones((1, N_ACTIONS), dtype=bool)
    )
    return {str(s): measure_batched_training(s, episodes, seed, shield) for s in sizes}


# --- the backend's task ---------------------------------------------------------------------------
def train_runs_task(cfgs_json: list[str], out_dirs: list[str]) -> dict[str, Any]:
    """The backend's task that trains (or resumes) runs as one batch: ``cfgs_json[k]`` (a
    :class:`~safelane.running.run_directory.TrainConfig` as JSON) into ``out_dirs[k]``. A directory left without a
    checkpoint (killed before its first) is started afresh, as ``reproduce`` does for one run. Returns
    ``{"runs": out_dirs}``; the runs' evaluation tasks then find them trained."""
    import shutil

    import torch

    torch.set_num_threads(1)
    dirs = [Path(d) for d in out_dirs]
    for run_dir in dirs:
        if run_dir.exists() and not (run_dir / CHECKPOINT_FILE).exists():
            shutil.rmtree(run_dir)
    train_batched([TrainConfig.model_validate_json(c) for c in cfgs_json], dirs, resume=True)
    return {"runs": out_dirs}


def batches_of(jobs: Sequence[tuple[TrainConfig, Path]], workers: int) -> list[tuple[list[str], list[str]]]:
    """``jobs`` (config, run directory) that :func:`train_batched` can train, in at most ``workers`` batches
    per mini-batch size, as :func:`train_runs_task`'s arguments; the others (highway-env, or a config that
    does not resolve: its own task reports it) are left out."""
    groups: dict[int, list[tuple[TrainConfig, Path]]] = {}
    for cfg, run_dir in jobs:
        try:
            run = resolve(cfg)
        except ConfigError:
            continue
        if refusal(run) is None:  # the others are trained one by one by their own task
            groups.setdefault(run.agent.batch_size, []).append((cfg, run_dir))
    out = []
    for members in groups.values():
        n = max(1, min(workers, len(members)))
        for i in range(n):
            chunk = members[i::n]
            out.append(([c.model_dump_json() for c, _ in chunk], [str(d) for _, d in chunk]))
    return out
