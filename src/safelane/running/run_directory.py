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
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from safelane.agents.continuous import (
    ALGOS,
    Algo,
    ContinuousAgentConfig,
    build_continuous_agent_config,
    load_model,
    predict,
)
from safelane.agents.dqn import (
    AGENT_PRESETS,
    AgentConfig,
    DQNAgent,
    ReplayBuffer,
    build_agent_config,
    load_agent_config,
    sanitize_mask,
)
from safelane.agents.recurrent import SequenceReplay
from safelane.agents.registry import ALL_AGENT_CLASSES, agent_class, make_agent
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
from safelane.env.factory import check_same_interface, env_interface, interface_of, observation_size
from safelane.reporting.metrics_file import METRICS_FILE

CONFIG_FILE = "config.yaml"
CHECKPOINT_FILE = "checkpoint.pt"
CHECKPOINT_FORMAT = 1
TENSORBOARD_DIR = "tensorboard"
DEFAULT_CONTINUOUS_STEPS = 20_000
"""Training decisions of a continuous run when ``steps`` is left out."""
DEFAULT_CHECKPOINT_STEPS = 5_000
"""Decisions between a continuous run's checkpoints when ``checkpoint_steps`` is left out (each holds the replay
buffer: ≈ 30 MB at 10⁵ transitions)."""

TRAIN_SHIELD_MODE: dict[str, str] = {method: cls.train_shield for method, cls in ALL_AGENT_CLASSES.items()}
"""Shield mode of the training env per method (``train_shield`` of its agent class; masks are recorded for
all methods, only mask users act on them)."""
ENV_SECTIONS: tuple[str, ...] = tuple(key for key in SafelaneConfig.model_fields if key != "preset")
"""Top-level environment config keys a ``--set`` may start with (``preset`` is chosen by ``--preset``)."""


class TrainConfig(BaseModel):
    """What to train: method, presets, length, seed and ``--set`` overrides."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    method: Literal["dqn", "constrained", "qmask", "robust", "robust-recurrent"] | None = Field(
        "robust",
        description="dqn, constrained, qmask or robust (paper Section IV.1–4), or robust-recurrent (robust on a "
        "recurrent Q-network, safelane.agents.recurrent); none with algo.",
    )
    algo: Algo | None = Field(
        None,
        description=f"Continuous actions: the SB3 algorithm, {', '.join(ALGOS)} (safelane.agents.continuous); "
        "none for the DQN methods.",
    )
    agent_preset: str | None = Field(
        "tuned",
        description=f"Agent preset: {', '.join(AGENT_PRESETS)}, or a YAML file of agent fields (with algo: a YAML "
        "file of its fields, or none for its defaults).",
    )
    env_preset: str = Field("fast", description=f"Environment preset: {', '.join(ENV_PRESETS)}.")
    episodes: int | None = Field(
        200, ge=1, description="Training episodes (the paper trains 200 of 40 s); none with algo, which counts steps."
    )
    steps: int | None = Field(
        None, ge=1, description="With algo: training decisions (SB3's total_timesteps); none for the DQN methods."
    )
    seed: int = Field(0, ge=0, description="Seed of network init, exploration, replay and episodes.")
    checkpoint_every: int | None = Field(
        10, ge=1, description="Episodes between checkpoints (and one at the end); none with algo."
    )
    checkpoint_steps: int | None = Field(
        None,
        ge=1,
        description="With algo: decisions between checkpoints (and one at the end), each taken at the next episode "
        "boundary (SAC) or update (PPO); none for the DQN methods.",
    )
    sets: list[str] = Field(
        default_factory=list,
        description="KEY=VALUE overrides: env.*, reward.*, traffic.*, shield.*, env_id go to the "
        "environment config, agent.* to the agent config (e.g. agent.lr=1e-3).",
    )

    @model_validator(mode="before")
    @classmethod
    def _continuous_defaults(cls, data: Any) -> Any:
        """With ``algo``, the DQN-only fields default to none and ``steps`` to :data:`DEFAULT_CONTINUOUS_STEPS`."""
        if isinstance(data, dict) and data.get("algo") is not None:
            defaults = {"method": None, "episodes": None, "agent_preset": None, "steps": DEFAULT_CONTINUOUS_STEPS,
                        "checkpoint_every": None, "checkpoint_steps": DEFAULT_CHECKPOINT_STEPS}  # fmt: skip
            data = {**defaults, **data}
        return data

    @model_validator(mode="after")
    def _one_learner(self) -> TrainConfig:
        """A DQN method (discrete actions, episodes) or an SB3 algorithm (continuous actions, steps), not both."""
        if self.algo is None:
            if self.method is None or self.episodes is None:
                raise ConfigError("train.method: a DQN run needs a method and episodes (or give algo)")
            for name in ("steps", "checkpoint_steps"):
                if getattr(self, name) is not None:
                    raise ConfigError(f"train.{name}: only with algo; the DQN methods count episodes")
            if self.checkpoint_every is None:
                raise ConfigError("train.checkpoint_every: a DQN run needs it >= 1")
            return self
        if self.method is not None:
            raise ConfigError(f"train.method: the DQN methods take discrete actions; with algo {self.algo!r} "
                              "leave it out")  # fmt: skip
        if self.episodes is not None:
            raise ConfigError(f"train.episodes: algo {self.algo!r} trains for steps (decisions); leave it out")
        if self.steps is None or self.checkpoint_steps is None:
            raise ConfigError(f"train.steps, train.checkpoint_steps: algo {self.algo!r} needs both >= 1")
        if self.checkpoint_every is not None:
            raise ConfigError("train.checkpoint_every: counts episodes, for the DQN methods; with algo use "
                              "checkpoint_steps (decisions)")  # fmt: skip
        if self.agent_preset is not None and Path(self.agent_preset).suffix not in (".yaml", ".yml"):
            raise ConfigError(f"train.agent_preset: with algo, a .yaml file of agent fields or none (got "
                              f"{self.agent_preset!r})")  # fmt: skip
        return self

    @property
    def learner(self) -> str:
        """What the run trains: its algo, else its DQN method."""
        return str(self.algo or self.method)

    @field_validator("agent_preset")
    @classmethod
    def _agent_preset(cls, name: str | None) -> str | None:
        if name is None:
            return None
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
    """A run's fully resolved configuration (a continuous run's agent: a :class:`ContinuousAgentConfig`)."""

    train: TrainConfig
    agent: AgentConfig | ContinuousAgentConfig
    env: SafelaneConfig


# --- configuration resolution -------------------------------------------------------------------
def resolve(cfg: TrainConfig) -> RunConfig:
    """Split ``cfg.sets`` into environment and agent overrides and build both configs.

    The training env's shield mode defaults per method (:data:`TRAIN_SHIELD_MODE`); an explicit
    ``shield.mode`` in ``sets`` wins, but qmask and robust need a mask (not ``none``) and the
    shield's override must stay off (the agent must learn from the action it chose). A continuous run
    (``cfg.algo``) trains without a shield unless ``shield.mode`` says otherwise (:func:`resolve_continuous`).
    """
    if cfg.algo is not None:
        return resolve_continuous(cfg)
    assert cfg.method is not None
    env_sets, agent_overrides = _split_sets(cfg.sets)
    if any(parse_set(a) == ("actions", "continuous") for a in env_sets):
        raise ConfigError(f"actions: continuous is trained by --algo ({', '.join(ALGOS)}), not by the DQN method "
                          f"{cfg.method!r}")  # fmt: skip
    env_sets = [f"shield.mode={TRAIN_SHIELD_MODE[cfg.method]}", *env_sets]
    env_cfg = load_config(cfg.env_preset, sets=env_sets)
    learner_class = agent_class(cfg.method)
    if learner_class.uses_mask and env_cfg.shield.mode == "none":
        raise ConfigError(
            f"shield.mode: {cfg.method} acts on the shield's mask; use nominal, robust or committed, not none"
        )
    if learner_class.needs_cost and env_cfg.shield.mode == "none":
        raise ConfigError(
            f"shield.mode: {cfg.method}'s cost counts actions outside the shield's mask; "
            "use nominal, robust or committed, not none"
        )
    if env_cfg.shield.override:
        raise ConfigError("shield.override: must be false for training (the agent learns from its own action)")
    agent_cfg = load_agent_config(cfg.agent_preset, cfg.method, agent_overrides)
    return RunConfig(cfg, agent_cfg, env_cfg)


def _split_sets(sets: list[str]) -> tuple[list[str], dict[str, Any]]:
    """``--set`` strings split into environment assignments and agent overrides (keys without ``agent.``)."""
    env_sets: list[str] = []
    agent_overrides: dict[str, Any] = {}
    for assignment in sets:
        key, value = parse_set(assignment)
        head, _, rest = key.partition(".")
        if head == "agent":
            if not rest or "." in rest:
                raise ConfigError(f"--set {key}: expected agent.FIELD=VALUE")
            if rest in ("method", "algo"):
                raise ConfigError(f"--set agent.{rest}: choose the {rest} with --{rest}")
            agent_overrides[rest] = value
        elif head in ENV_SECTIONS:
            env_sets.append(assignment)
        else:
            allowed = ", ".join(("agent", *ENV_SECTIONS))
            raise ConfigError(f"--set {key}: unknown section '{head}'; allowed: {allowed}")
    return env_sets, agent_overrides


def resolve_continuous(cfg: TrainConfig) -> RunConfig:
    """The :class:`RunConfig` of a continuous run: the environment needs ``actions: continuous``; the agent's
    fields come from ``cfg.agent_preset`` (a YAML file, or none) and ``agent.*`` sets over the algo's defaults."""
    env_sets, agent_overrides = _split_sets(cfg.sets)
    env_cfg = load_config(cfg.env_preset, sets=env_sets)
    if env_cfg.actions != "continuous":
        raise ConfigError(f"--algo: {cfg.algo} trains continuous actions; add --actions continuous (the discrete "
                          "actions train with --method)")  # fmt: skip
    data: dict[str, Any] = {}
    if cfg.agent_preset is not None:
        path = Path(cfg.agent_preset)
        if not path.is_file():
            raise ConfigError(f"agent preset: no such file {cfg.agent_preset}")
        data = yaml.safe_load(path.read_text()) or {}
    agent_cfg = build_continuous_agent_config({**data, **agent_overrides, "algo": cfg.algo})
    return RunConfig(cfg, agent_cfg, env_cfg)


def build_run_agent_config(train: dict[str, Any], agent: dict[str, Any]) -> AgentConfig | ContinuousAgentConfig:
    """A recorded agent config, validated as the run's kind: continuous when ``train`` names an algo."""
    if train.get("algo") is not None:
        return build_continuous_agent_config(agent)
    return build_agent_config(agent)


def run_config_dict(run: RunConfig) -> dict[str, Any]:
    """The YAML-serialisable form of a run configuration (what ``config.yaml`` holds)."""
    return {
        "train": run.train.model_dump(mode="json"),
        "agent": run.agent.model_dump(mode="json"),
        "env": config_to_dict(run.env),
    }


LENGTH_KEYS = ("episodes", "steps", "checkpoint_every", "checkpoint_steps", "sets")
"""Train keys a resume may change: how long a run trains and how often it checkpoints (and the raw sets, whose
effect the resolved sections hold)."""


def _comparable(data: dict[str, Any]) -> dict[str, Any]:
    """The parts of a run config that change results (episodes, checkpointing and raw sets do not),
    re-validated: a key added to safelane since the run was written compares equal at its default."""
    data = yaml.safe_load(yaml.safe_dump(data))
    train = {k: v for k, v in data["train"].items() if k not in LENGTH_KEYS}
    agent = build_run_agent_config(data["train"], data["agent"]).model_dump(mode="json")
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
        agent = build_run_agent_config(data["train"], data["agent"])
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
    buffer: ReplayBuffer | SequenceReplay,
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
            if state["config"]["train"].get("algo") != run.train.algo or (
                state["config"]["agent"].get("method") != getattr(run.agent, "method", None)
            ):
                raise ConfigError(f"--resume: checkpoint method differs from {run.train.learner}")
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
        self.obs_size = observation_size(run.env)

    def _check(self, info: dict[str, Any]) -> None:
        actual = interface_of(info)
        if actual is not None and actual != self.interface:
            check_same_interface(self.interface, actual, self.name)

    def _check_size(self, obs: np.ndarray) -> None:
        # The state's name can agree while its size does not: paper-types on a mixture of another number of types.
        if np.shape(obs)[-1] != self.obs_size:
            raise ConfigError(
                f"state: {self.name} reads {self.obs_size} numbers ({self.interface.state!r}), the environment gives "
                f"{np.shape(obs)[-1]}; allowed: the traffic.driver_mix types it was trained on"
            )

    def __call__(self, obs: np.ndarray, info: dict[str, Any] | None = None) -> int:
        """The greedy action for one observation (26 numbers, or the run's state's size; its mask read from
        ``info`` for mask users)."""
        if info is not None:
            self._check(info)
        self._check_size(obs)
        mask = info.get("action_mask") if (info is not None and self.agent.uses_mask) else None
        return self.agent.greedy(obs, mask)

    def batch(self, obs: np.ndarray, infos: list[dict[str, Any]]) -> np.ndarray:
        """Greedy actions (N,) for observations (N, state size) of N environments, one forward pass; row ``k``
        gets the action ``self(obs[k], infos[k])`` gives (:meth:`DQNAgent.greedy_batch`)."""
        for info in infos:
            self._check(info)
        self._check_size(obs)
        masks = None
        if self.agent.uses_mask:
            masks = np.stack([sanitize_mask(info.get("action_mask")) for info in infos])
        return self.agent.greedy_batch(obs, masks)


class RecurrentGreedyPolicy(GreedyPolicy):
    """The greedy policy of a recurrent run: stateful, its hidden state carried from one decision to the next.

    The hidden state restarts at :meth:`begin_episode` (the evaluation loop calls it after each reset) and, for a
    loop that does not, whenever the snapshot's clock in ``info`` is not later than at the previous call (a reset).
    It plays one environment at a time: :meth:`batch` is refused, so evaluation plays the episodes one by one.
    """

    def __init__(self, agent: DQNAgent, run: RunConfig, name: str = "the run") -> None:
        super().__init__(agent, run, name)
        self._clock: float | None = None  # [s] the snapshot's time at the previous decision

    def begin_episode(self) -> None:
        """A new episode: forget the previous one."""
        self.agent.begin_episode()
        self._clock = None

    def __call__(self, obs: np.ndarray, info: dict[str, Any] | None = None) -> int:
        """The greedy action for the episode's next observation (advances the hidden state)."""
        snap = info.get("snapshot") if info is not None else None
        if snap is not None:
            if self._clock is not None and snap.time <= self._clock:
                self.agent.begin_episode()
            self._clock = float(snap.time)
        return super().__call__(obs, info)

    batch = None  # type: ignore[assignment]
    """No batch: each environment would need its own hidden state."""


def greedy_policy(agent: DQNAgent, run: RunConfig, name: str = "the run") -> GreedyPolicy:
    """The greedy policy of a trained agent: :class:`RecurrentGreedyPolicy` for a recurrent one, else
    :class:`GreedyPolicy`."""
    return (RecurrentGreedyPolicy if agent.recurrent else GreedyPolicy)(agent, run, name)


def load_agent(run_dir: str | Path) -> DQNAgent:
    """The trained agent of a run directory, networks restored from its checkpoint."""
    run = load_run_config(run_dir)
    if not isinstance(run.agent, AgentConfig):
        raise ConfigError(f"{run_dir}: a continuous run ({run.train.algo}) has no DQN agent; use load_policy")
    state = load_checkpoint(run_dir)
    agent = make_agent(run.agent, seed=run.train.seed, obs_size=observation_size(run.env))
    try:
        agent.load_state_dict(state["agent"])
    except (KeyError, ValueError, RuntimeError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"{run_dir}: checkpoint does not match config.yaml ({first})") from None
    return agent


class ContinuousPolicy:
    """The deterministic policy of a trained continuous run (SAC's mean action, PPO's mean):
    ``policy(obs, info) -> [acceleration, steering]``; refuses another interface as :class:`GreedyPolicy` does."""

    def __init__(self, model: Any, run: RunConfig, name: str = "the run") -> None:
        self.model = model
        self.run = run
        self.method = run.train.learner
        self.name = name
        self.interface = env_interface(run.env)

    def __call__(self, obs: np.ndarray, info: dict[str, Any] | None = None) -> np.ndarray:
        """The action (2,) float32 in [-1, 1] for one observation (28,)."""
        if info is not None:
            actual = interface_of(info)
            if actual is not None and actual != self.interface:
                check_same_interface(self.interface, actual, self.name)
        return predict(self.model, obs)


def load_continuous_model(run_dir: str | Path) -> Any:
    """The trained SB3 model of a continuous run directory, from its checkpoint."""
    run = load_run_config(run_dir)
    state = load_checkpoint(run_dir)
    if run.train.algo is None or "model" not in state:
        raise ConfigError(f"{run_dir}: not a continuous run (no algo in {CONFIG_FILE}, or no model in the checkpoint)")
    try:
        return load_model(run.train.algo, state["model"])
    except (KeyError, ValueError, RuntimeError) as err:
        raise ConfigError(f"{run_dir}: checkpoint does not match config.yaml ({type(err).__name__})") from None


def load_policy(run_dir: str | Path) -> Callable[[np.ndarray, dict[str, Any]], Any]:
    """The greedy policy of a trained run (see :class:`GreedyPolicy`; a continuous run's: :class:`ContinuousPolicy`)."""
    run = load_run_config(run_dir)
    if run.train.algo is not None:
        return ContinuousPolicy(load_continuous_model(run_dir), run, f"run {run_dir}")
    return greedy_policy(load_agent(run_dir), run, f"run {run_dir}")
