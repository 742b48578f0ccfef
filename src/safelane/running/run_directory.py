"""A training run's directory: what it holds and how it is read back.

A run directory holds:

* ``config.yaml`` (:data:`CONFIG_FILE`) — the fully resolved train, agent and environment configuration
  (:class:`RunConfig`, from a :class:`TrainConfig` by :func:`resolve`);
* ``metrics.csv`` — one row per episode (:mod:`safelane.reporting.metrics_file`);
* ``tensorboard/`` — with ``tensorboard=True``, the same per-episode numbers as TensorBoard scalars;
* ``checkpoint.pt`` — networks, targets, optimizer, λ, replay buffer, counters, every RNG state and
  the metrics rows so far (:func:`training_snapshot`), written atomically (temporary file + ``os.replace``).

:func:`prepare_run_dir` checks a directory before a (resumed) run; :func:`load_policy` drives a finished one.
The training loops (:mod:`safelane.running.training`, :mod:`safelane.running.batched_training`) write it.
"""

from __future__ import annotations

import copy
import random
from collections.abc import Callable
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
    DQNAgent,
    ReplayBuffer,
    build_agent_config,
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
from safelane.env.factory import check_same_interface, env_interface, interface_of
from safelane.reporting.metrics_file import METRICS_FILE

CONFIG_FILE = "config.yaml"
CHECKPOINT_FILE = "checkpoint.pt"
CHECKPOINT_FORMAT = 1
TENSORBOARD_DIR = "tensorboard"

TRAIN_SHIELD_MODE: dict[str, str] = {method: cls.train_shield for method, cls in AGENT_CLASSES.items()}
"""Shield mode of the training env per method (``train_shield`` of its agent class; masks are recorded for
all methods, only mask users act on them)."""
ENV_SECTIONS: tuple[str, ...] = tuple(key for key in SafelaneConfig.model_fields if key != "preset")
"""Top-level environment config keys a ``--set`` may start with (``preset`` is chosen by ``--preset``)."""


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


# --- the checkpoint -------------------------------------------------------------------------------
def rng_states() -> dict[str, Any]:
    """The python, numpy (legacy) and torch global RNG states, as a checkpoint stores them."""
    legacy = np.random.get_state()
    return {
        "python": random.getstate(),
        "numpy_legacy": (legacy[0], legacy[1].tolist(), *legacy[2:]),
        "torch": torch.get_rng_state(),
    }


def restore_rng_states(state: dict[str, Any]) -> None:
    """Set the global RNGs back to what :func:`rng_states` returned."""
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
        "rng": rng_states(),
    }


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write ``state`` (a :func:`training_snapshot`) to ``path`` atomically."""
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
