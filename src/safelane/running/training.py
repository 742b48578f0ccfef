"""Training: one explicit loop for all four methods, with exact resume.

``train(cfg, out_dir)`` reads top to bottom: reset → act (ε-greedy) → step → store → sample →
update → target sync → per-episode bookkeeping → checkpoint. The methods differ only inside the
agent (:mod:`safelane.agents.dqn`). A run directory holds:

* ``config.yaml`` — the fully resolved train, agent and environment configuration;
* ``metrics.csv`` — one row per episode (:data:`METRIC_COLUMNS`);
* ``tensorboard/`` — with ``tensorboard=True``, the same per-episode numbers as TensorBoard scalars;
* ``checkpoint.pt`` — networks, targets, optimizer, λ, replay buffer, counters, every RNG state and
  the metrics rows so far, written atomically (temporary file + ``os.replace``).

Determinism: episode ``i`` (0-based) is reset with seed ``seed·100003 + i``; exploration and replay
sampling draw from the agent's one ``numpy.random.Generator``; torch runs single-threaded with
deterministic algorithms. So the same seed gives the same ``metrics.csv`` (wall time aside), and a
run killed at any moment and resumed from its checkpoint ends exactly as an uninterrupted one.
"""

from __future__ import annotations

import contextlib
import copy
import csv
import io
import random
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np
import torch
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from safelane.agents.dqn import (
    AGENT_CLASSES,
    AGENT_PRESETS,
    AgentConfig,
    ConstrainedAgent,
    DQNAgent,
    ReplayBuffer,
    build_agent_config,
    linear_epsilon,
    load_agent_config,
    make_agent,
    sanitize_mask,
)
from safelane.config import (
    ENV_PRESETS,
    ConfigError,
    SafelaneConfig,
    build_config,
    config_to_dict,
    load_config,
    parse_set,
    recorded_config,
    validation_message,
)
from safelane.core.files import atomic_write
from safelane.env.factory import check_same_interface, env_interface, interface_of, make_env

CONFIG_FILE = "config.yaml"
METRICS_FILE = "metrics.csv"
CHECKPOINT_FILE = "checkpoint.pt"
CHECKPOINT_FORMAT = 1
TENSORBOARD_DIR = "tensorboard"
EPISODE_SEED_STRIDE = 100003
"""Episode ``i`` of a run with seed ``s`` is reset with seed ``s·EPISODE_SEED_STRIDE + i``."""

TRAIN_SHIELD_MODE: dict[str, str] = {method: cls.train_shield for method, cls in AGENT_CLASSES.items()}
"""Shield mode of the training env per method (``train_shield`` of its agent class; masks are recorded for
all methods, only mask users act on them)."""
ENV_SECTIONS: tuple[str, ...] = tuple(key for key in SafelaneConfig.model_fields if key != "preset")
"""Top-level environment config keys a ``--set`` may start with (``preset`` is chosen by ``--preset``)."""

METRIC_COLUMNS: tuple[str, ...] = (
    "episode",  # 1-based episode number
    "return",  # sum of eq. 6 rewards
    "length",  # decisions in the episode
    "collision",  # 1 if the episode ended in a crash
    "mean_speed",  # [m/s] mean ego speed after each decision
    "epsilon",  # ε of the episode's last decision
    "mean_loss",  # mean training loss over the episode's gradient steps (empty before learning starts)
    "shield_interventions",  # decisions whose action was unsafe under the mask ("would have been masked")
    "fallbacks",  # decisions where the shield found no safe action and allowed the least-bad one
    "invariant_breaks",  # fallback states reached right after an allowed action in a state with a safe one
    "lambda",  # constrained: λ after the episode's dual update (empty for other methods)
    "cost",  # constrained's episode cost: decisions that were unsafe or ended in a collision
    "wall_time_s",  # [s] cumulative training wall time at the end of the episode
    "env_time_s",  # [s] of it spent inside env.reset / env.step (simulator + shield); the rest is the agent's
    "env_steps",  # cumulative environment decisions
)
TIMING_COLUMNS = ("wall_time_s", "env_time_s")
"""Columns that measure time: they vary between identical runs."""
TENSORBOARD_SCALARS: tuple[str, ...] = tuple(c for c in METRIC_COLUMNS if c not in ("episode", *TIMING_COLUMNS))
"""Columns logged with ``--tensorboard`` (per episode; wall time is TensorBoard's own axis)."""


class TrainConfig(BaseModel):
    """What to train: method, presets, length, seed and ``--set`` overrides."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    method: Literal["dqn", "constrained", "qmask", "robust"] = Field(
        "robust", description="dqn, constrained, qmask or robust (paper Section IV.1–4)."
    )
    agent_preset: str = Field(
        "tuned", description=f"Agent preset: {', '.join(AGENT_PRESETS)}, or a YAML file of agent fields."
    )
    env_preset: str = Field("fast", description=f"Environment preset: {', '.join(ENV_PRESETS)}.")
    episodes: int = Field(200, ge=1, description="Training episodes (the paper trains 200 of 40 s).")
    seed: int = Field(0, ge=0, description="Seed of network init, exploration, replay and episodes.")
    checkpoint_every: int = Field(10, ge=1, description="Episodes between checkpoints (and one at the end).")
    sets: list[str] = Field(
        default_factory=list,
        description="KEY=VALUE overrides: env.*, reward.*, traffic.*, shield.*, env_id go to the "
        "environment config, agent.* to the agent config (e.g. agent.lr=1e-3).",
    )

    @field_validator("agent_preset")
    @classmethod
    def _agent_preset(cls, name: str) -> str:
        if name not in AGENT_PRESETS and Path(name).suffix not in (".yaml", ".yml"):
            raise ValueError(f"unknown agent preset '{name}'; allowed: {', '.join(AGENT_PRESETS)} or a .yaml file")
        return name

    @field_validator("env_preset")
    @classmethod
    def _env_preset(cls, name: str) -> str:
        if name not in ENV_PRESETS:
            raise ValueError(f"unknown environment preset '{name}'; allowed: {', '.join(ENV_PRESETS)}")
        return name


def make_train_config(**fields: Any) -> TrainConfig:
    """A :class:`TrainConfig` from keyword fields, raising a one-line :class:`ConfigError`."""
    try:
        return TrainConfig(**fields)
    except ValidationError as err:
        raise ConfigError(validation_message(err, TrainConfig, "train.")) from None


class RunConfig(NamedTuple):
    """A run's fully resolved configuration."""

    train: TrainConfig
    agent: AgentConfig
    env: SafelaneConfig


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


# --- configuration resolution -------------------------------------------------------------------
def resolve(cfg: TrainConfig) -> RunConfig:
    """Split ``cfg.sets`` into environment and agent overrides and build both configs.

    The training env's shield mode defaults per method (:data:`TRAIN_SHIELD_MODE`); an explicit
    ``shield.mode`` in ``sets`` wins, but qmask and robust need a mask (not ``none``) and the
    shield's override must stay off (the agent must learn from the action it chose).
    """
    env_sets: list[str] = [f"shield.mode={TRAIN_SHIELD_MODE[cfg.method]}"]
    agent_overrides: dict[str, Any] = {}
    for assignment in cfg.sets:
        key, value = parse_set(assignment)
        head, _, rest = key.partition(".")
        if head == "agent":
            if not rest or "." in rest:
                raise ConfigError(f"--set {key}: expected agent.FIELD=VALUE")
            if rest == "method":
                raise ConfigError("--set agent.method: choose the method with --method")
            agent_overrides[rest] = value
        elif head in ENV_SECTIONS:
            env_sets.append(assignment)
        else:
            allowed = ", ".join(("agent", *ENV_SECTIONS))
            raise ConfigError(f"--set {key}: unknown section '{head}'; allowed: {allowed}")
    env_cfg = load_config(cfg.env_preset, sets=env_sets)
    agent_class = AGENT_CLASSES[cfg.method]
    if agent_class.uses_mask and env_cfg.shield.mode == "none":
        raise ConfigError(
            f"shield.mode: {cfg.method} acts on the shield's mask; use nominal, robust or committed, not none"
        )
    if agent_class.needs_cost and env_cfg.shield.mode == "none":
        raise ConfigError(
            f"shield.mode: {cfg.method}'s cost counts actions outside the shield's mask; "
            "use nominal, robust or committed, not none"
        )
    if env_cfg.shield.override:
        raise ConfigError("shield.override: must be false for training (the agent learns from its own action)")
    agent_cfg = load_agent_config(cfg.agent_preset, cfg.method, agent_overrides)
    return RunConfig(cfg, agent_cfg, env_cfg)


def run_config_dict(run: RunConfig) -> dict[str, Any]:
    """The YAML-serialisable form of a run configuration (what ``config.yaml`` holds)."""
    return {
        "train": run.train.model_dump(mode="json"),
        "agent": run.agent.model_dump(mode="json"),
        "env": config_to_dict(run.env),
    }


def _comparable(data: dict[str, Any]) -> dict[str, Any]:
    """The parts of a run config that change results (episodes, checkpointing and raw sets do not),
    re-validated: a key added to safelane since the run was written compares equal at its default."""
    data = yaml.safe_load(yaml.safe_dump(data))
    train = {k: v for k, v in data["train"].items() if k not in ("episodes", "checkpoint_every", "sets")}
    agent = build_agent_config(data["agent"]).model_dump(mode="json")
    env = config_to_dict(build_config(data["env"]))
    return yaml.safe_load(yaml.safe_dump({"train": train, "agent": agent, "env": env}))


def _first_difference(a: Any, b: Any, prefix: str = "") -> str:
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            if a.get(key) != b.get(key):
                return _first_difference(a.get(key), b.get(key), f"{prefix}{key}.")
    return f"{prefix.rstrip('.')}: run has {a!r}, requested {b!r}"


def load_run_config(run_dir: str | Path) -> RunConfig:
    """The resolved configuration of a run directory (raises a one-line :class:`ConfigError`)."""
    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise ConfigError(f"{run_dir}: not a safelane training run (no {CONFIG_FILE})")
    try:
        data = yaml.safe_load(path.read_text())
        train = TrainConfig.model_validate(data["train"])
        agent = build_agent_config(data["agent"])
        env = recorded_config(data["env"])
    except ConfigError as err:
        raise ConfigError(f"{path}: incompatible run config ({err})") from None
    except (yaml.YAMLError, KeyError, TypeError, ValidationError) as err:
        raise ConfigError(f"{path}: unreadable run config ({type(err).__name__})") from None
    return RunConfig(train, agent, env)


# --- files ----------------------------------------------------------------------------------------
def format_metrics_row(row: dict[str, Any]) -> dict[str, str]:
    out: dict[str, str] = {}
    for key in METRIC_COLUMNS:
        value = row.get(key)
        if value is None:
            out[key] = ""
        elif isinstance(value, float):
            out[key] = f"{value:.6f}" if key in TIMING_COLUMNS else repr(value)  # to the µs: a decision costs tens
        else:
            out[key] = str(value)
    return out


def write_metrics(path: Path, rows: list[dict[str, Any]]) -> None:
    def write(f: io.BufferedWriter) -> None:
        text = io.StringIO()
        writer = csv.DictWriter(text, fieldnames=METRIC_COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows(format_metrics_row(r) for r in rows)
        f.write(text.getvalue().encode())

    atomic_write(path, write)


def _rng_states() -> dict[str, Any]:
    legacy = np.random.get_state()
    return {
        "python": random.getstate(),
        "numpy_legacy": (legacy[0], legacy[1].tolist(), *legacy[2:]),
        "torch": torch.get_rng_state(),
    }


def _restore_rng_states(state: dict[str, Any]) -> None:
    random.setstate(state["python"])
    name, keys, *rest = state["numpy_legacy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), *rest))
    torch.set_rng_state(state["torch"])


def training_snapshot(
    run: RunConfig,
    agent: DQNAgent,
    buffer: ReplayBuffer,
    episode: int,
    global_step: int,
    rows: list[dict[str, Any]],
    wall_time_s: float,
) -> dict[str, Any]:
    """A self-contained copy of the training state at an episode boundary."""
    return {
        "format": CHECKPOINT_FORMAT,
        "config": run_config_dict(run),
        "episode": episode,
        "global_step": global_step,
        "agent": copy.deepcopy(agent.state_dict()),
        "buffer": buffer.state_dict(),
        "rows": [dict(r) for r in rows],
        "wall_time_s": wall_time_s,
        "rng": _rng_states(),
    }


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    atomic_write(path, lambda f: torch.save(state, f))


def load_checkpoint(run_dir: str | Path) -> dict[str, Any]:
    """The checkpoint of a run directory (raises a one-line :class:`ConfigError` if missing/corrupt)."""
    path = Path(run_dir) / CHECKPOINT_FILE
    if not path.is_file():
        raise ConfigError(f"{run_dir}: no {CHECKPOINT_FILE} (train first, or the run never reached a checkpoint)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises many types for a damaged file
        raise ConfigError(f"{path}: corrupt or unreadable checkpoint ({type(err).__name__})") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise ConfigError(f"{path}: not a safelane checkpoint of format {CHECKPOINT_FORMAT}")
    return state


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


def prepare_run_dir(out: Path, run: RunConfig, resume: bool) -> dict[str, Any] | None:
    """Check the run directory, write ``config.yaml``; return the checkpoint to resume from, if any."""
    out.mkdir(parents=True, exist_ok=True)
    config_path = out / CONFIG_FILE
    wanted = run_config_dict(run)
    state = None
    if resume:
        if config_path.is_file():
            stored = yaml.safe_load(config_path.read_text()) or {}
            try:
                old, new = _comparable(stored), _comparable(wanted)
            except (KeyError, TypeError, AttributeError):
                raise ConfigError(f"{config_path}: unreadable run config; cannot resume") from None
            if old != new:
                raise ConfigError(f"--resume: {out} was trained with another config ({_first_difference(old, new)})")
        if (out / CHECKPOINT_FILE).is_file():
            state = load_checkpoint(out)
            if _comparable(state["config"]) != _comparable(wanted):
                raise ConfigError(f"--resume: {out / CHECKPOINT_FILE} belongs to another config")
            if state["config"]["agent"]["method"] != run.agent.method:
                raise ConfigError(f"--resume: checkpoint method differs from {run.agent.method}")
    elif (out / CHECKPOINT_FILE).exists() or (out / METRICS_FILE).exists():
        raise ConfigError(f"{out}: already holds a training run; pass --resume to continue it or choose another --out")
    atomic_write(config_path, lambda f: f.write(yaml.safe_dump(wanted, sort_keys=False).encode()))
    return state


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

    agent = make_agent(acfg, seed=cfg.seed)
    buffer = ReplayBuffer(acfg.buffer_size)
    rows: list[dict[str, Any]] = []
    episode, global_step, wall_before, env_time = 0, 0, 0.0, 0.0
    if state is not None:
        agent.load_state_dict(state["agent"])
        buffer.load_state_dict(state["buffer"])
        _restore_rng_states(state["rng"])
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
        with deterministic_torch(), open(metrics_path, "a", newline="") as metrics_file:
            writer = csv.DictWriter(metrics_file, fieldnames=METRIC_COLUMNS, lineterminator="\n")
            while episode < cfg.episodes:
                # --- one episode -------------------------------------------------------------
                t_env = time.perf_counter()
                obs, info = env.reset(seed=episode_seed(cfg.seed, episode))
                env_time += time.perf_counter() - t_env
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
                writer.writerow(format_metrics_row(row))
                metrics_file.flush()
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


# --- using a trained run ------------------------------------------------------------------------
class GreedyPolicy:
    """The greedy policy of a trained run: ``policy(obs, info) -> action``.

    qmask and robust choose among ``info["action_mask"]`` (all actions if the env has no shield);
    dqn and constrained ignore the mask. It refuses (one-line :class:`ConfigError`) to drive an
    environment whose state kind, decision rate or target speeds differ from the ones it was trained
    on, as ``info`` reports them.
    """

    def __init__(self, agent: DQNAgent, run: RunConfig, name: str = "the run") -> None:
        self.agent = agent
        self.run = run
        self.method = agent.method
        self.name = name
        self.interface = env_interface(run.env)

    def _check(self, info: dict[str, Any]) -> None:
        actual = interface_of(info)
        if actual is not None and actual != self.interface:
            check_same_interface(self.interface, actual, self.name)

    def __call__(self, obs: np.ndarray, info: dict[str, Any] | None = None) -> int:
        """The greedy action for one observation (26,) (its mask read from ``info`` for mask users)."""
        if info is not None:
            self._check(info)
        mask = info.get("action_mask") if (info is not None and self.agent.uses_mask) else None
        return self.agent.greedy(obs, mask)

    def batch(self, obs: np.ndarray, infos: list[dict[str, Any]]) -> np.ndarray:
        """Greedy actions (N,) for observations (N, 26) of N environments, one forward pass; row ``k``
        gets the action ``self(obs[k], infos[k])`` gives (:meth:`DQNAgent.greedy_batch`)."""
        for info in infos:
            self._check(info)
        masks = None
        if self.agent.uses_mask:
            masks = np.stack([sanitize_mask(info.get("action_mask")) for info in infos])
        return self.agent.greedy_batch(obs, masks)


def load_agent(run_dir: str | Path) -> DQNAgent:
    """The trained agent of a run directory, networks restored from its checkpoint."""
    run = load_run_config(run_dir)
    state = load_checkpoint(run_dir)
    agent = make_agent(run.agent, seed=run.train.seed)
    try:
        agent.load_state_dict(state["agent"])
    except (KeyError, ValueError, RuntimeError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"{run_dir}: checkpoint does not match config.yaml ({first})") from None
    return agent


def load_policy(run_dir: str | Path) -> Callable[[np.ndarray, dict[str, Any]], int]:
    """The greedy policy of a trained run (see :class:`GreedyPolicy`)."""
    return GreedyPolicy(load_agent(run_dir), load_run_config(run_dir), f"run {run_dir}")
