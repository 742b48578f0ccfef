"""Agents for continuous actions (acceleration and steering): Stable-Baselines3's SAC and PPO, and a Lagrangian SAC.

The agents see observation arrays, rewards and, for the Lagrangian SAC, a cost per transition (``info["cost"]``);
they import nothing from highway-env or the safety model. Stable-Baselines3 is an optional dependency (the ``sb3``
extra): everything here that needs it imports it through :func:`require_sb3`, which names the extra in one line.

* :class:`ContinuousAgentConfig` — every learning setting, each algorithm's defaults filled in
  (:data:`ALGO_DEFAULTS`), the fields of another algorithm refused;
* :func:`make_model`, :func:`load_model`, :func:`model_bytes` — SB3's construction, ``load`` and ``save``;
* :class:`ExecutedActionReplayBuffer` — SB3's replay buffer storing the action the environment executed
  (``info["executed_action"]``, a shield's projection or replacement) instead of the one the agent proposed;
* :mod:`safelane.agents.sac_lagrangian` — the Lagrangian SAC.
"""

from __future__ import annotations

import io
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from safelane.core.errors import ConfigError

Algo = Literal["sac", "ppo", "sac-lagrangian"]
ALGOS: tuple[str, ...] = ("sac", "ppo", "sac-lagrangian")
"""The algorithms ``safelane train --algo`` trains (continuous actions only)."""

SB3_MISSING = "stable-baselines3 is not installed; continuous agents need it: pip install 'safelane[sb3]'"

ALGO_DEFAULTS: dict[str, dict[str, Any]] = {
    "sac": {
        "learning_rate": 3e-4,
        "batch_size": 256,
        "buffer_size": 100_000,
        "learning_starts": 1000,
        "gradient_steps": 1,
        "tau": 0.005,
        "ent_coef": "auto",
        "net_arch": [256, 256],
    },
    "ppo": {
        "learning_rate": 3e-4,
        "batch_size": 64,
        "n_steps": 1024,
        "n_epochs": 10,
        "gae_lambda": 0.95,
        "clip_range": 0.2,
        "ent_coef": 0.0,
        "net_arch": [64, 64],
    },
}
"""Each algorithm's settings where the configuration leaves them out: SB3's defaults, but a replay buffer of 10⁵
transitions (a run's 2·10⁴ decisions fit five times) and PPO rollouts of 1 024 decisions (a 2·10⁴-decision run
updates 19 times, not 9)."""
ALGO_DEFAULTS["sac-lagrangian"] = {
    **ALGO_DEFAULTS["sac"],
    "cost_budget": 0.05,
    "lambda_lr": 1.0,
    "lambda_init": 0.0,
    "lambda_update_interval": 1000,
}

ALGO_FIELDS: dict[str, tuple[str, ...]] = {algo: tuple(defaults) for algo, defaults in ALGO_DEFAULTS.items()}
"""The fields each algorithm reads (beside ``algo`` and ``gamma``); another algorithm's field is an error."""


class ContinuousAgentConfig(BaseModel):
    """Every learning setting of a continuous agent. Units: steps are environment decisions; a field left out
    takes its algorithm's default (:data:`ALGO_DEFAULTS`), a field of another algorithm is a one-line error."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)

    algo: Algo = Field("sac", description="sac, ppo or sac-lagrangian (SAC with a cost critic and a multiplier λ).")
    gamma: float = Field(
        0.9, ge=0, lt=1, description="Discount factor per decision (the DQN methods' 0.9: a horizon of ≈ 10 s)."
    )
    learning_rate: float | None = Field(None, gt=0, description="Adam learning rate of every network.")
    batch_size: int | None = Field(None, ge=1, description="Transitions per gradient step (mini-batch).")
    net_arch: list[int] | None = Field(None, description="Hidden layer sizes of the actor and of each critic.")
    ent_coef: float | str | None = Field(
        None, description="Entropy coefficient: a number ≥ 0, or for SAC 'auto' (learned, SB3's 'auto_INIT' too)."
    )
    buffer_size: int | None = Field(None, ge=1, description="SAC: replay buffer capacity [transitions].")
    learning_starts: int | None = Field(None, ge=0, description="SAC: decisions of uniform random actions first.")
    gradient_steps: int | None = Field(None, ge=1, description="SAC: gradient steps after every decision.")
    tau: float | None = Field(None, gt=0, le=1, description="SAC: Polyak weight of the target critics per step.")
    n_steps: int | None = Field(None, ge=2, description="PPO: decisions per rollout (one update per rollout).")
    n_epochs: int | None = Field(None, ge=1, description="PPO: passes over each rollout.")
    gae_lambda: float | None = Field(None, ge=0, le=1, description="PPO: λ of the generalised advantage estimate.")
    clip_range: float | None = Field(None, gt=0, description="PPO: clipping of the probability ratio.")
    cost_budget: float | None = Field(
        None,
        ge=0,
        description="sac-lagrangian: [cost per episode] the expected episode cost allowed; cost 1 per decision "
        "that ends in a crash or off the road (both end the episode: at most 1 per episode, so 0.05 allows one "
        "such episode in 20).",
    )
    lambda_lr: float | None = Field(
        None,
        ge=0,
        description="sac-lagrangian: dual-ascent step of λ per update, per unit of mean episode cost over the "
        "budget: λ ← max(0, λ + lambda_lr·(mean episode cost − cost_budget)).",
    )
    lambda_update_interval: int | None = Field(
        None,
        ge=1,
        description="sac-lagrangian: [decisions] between λ's updates, each on the episodes finished since the last "
        "(1: after every episode).",
    )
    lambda_init: float | None = Field(None, ge=0, description="sac-lagrangian: initial Lagrange multiplier λ.")

    @model_validator(mode="after")
    def _algorithm_defaults(self) -> ContinuousAgentConfig:
        """Fill each of the algorithm's fields left out; refuse another algorithm's field."""
        mine = ALGO_FIELDS[self.algo]
        for name in {n for fields in ALGO_FIELDS.values() for n in fields}:
            value = getattr(self, name)
            if name in mine and value is None:
                object.__setattr__(self, name, ALGO_DEFAULTS[self.algo][name])
            elif name not in mine and value is not None:
                users = [a for a, fields in ALGO_FIELDS.items() if name in fields]
                raise ConfigError(
                    f"agent.{name}: only for algo {' or '.join(users)} (got algo {self.algo!r}); remove it"
                )
        ent = self.ent_coef
        if isinstance(ent, str) and not (self.algo != "ppo" and (ent == "auto" or ent.startswith("auto_"))):
            raise ConfigError(
                f"agent.ent_coef: got {ent!r}; allowed: a number >= 0" + (", 'auto'" if self.algo != "ppo" else "")
            )
        if isinstance(ent, float) and ent < 0:
            raise ConfigError(f"agent.ent_coef: must be >= 0 (got {ent})")
        if self.net_arch is not None and (not self.net_arch or min(self.net_arch) < 1):
            raise ConfigError(f"agent.net_arch: a list of layer sizes >= 1 (got {self.net_arch})")
        return self


def build_continuous_agent_config(data: dict[str, Any]) -> ContinuousAgentConfig:
    """Validate a plain dict into a :class:`ContinuousAgentConfig` (raises a one-line :class:`ConfigError`)."""
    try:
        return ContinuousAgentConfig.model_validate(data)
    except ValidationError as err:
        e = err.errors()[0]
        cause = e.get("ctx", {}).get("error")
        if isinstance(cause, ConfigError):
            raise cause from None
        key = "agent." + ".".join(str(p) for p in e["loc"] if not str(p).startswith(("float", "str", "int")))
        if e["type"] == "extra_forbidden":
            allowed = ", ".join(ContinuousAgentConfig.model_fields)
            raise ConfigError(f"{key}: unknown key; allowed: {allowed}") from None
        if e["type"] == "literal_error":
            raise ConfigError(f"{key}: got {e.get('input')!r}; allowed: {', '.join(ALGOS)}") from None
        raise ConfigError(f"{key}: {e['msg']} (got {e.get('input')!r})") from None


# --- Stable-Baselines3 ----------------------------------------------------------------------------
def require_sb3() -> Any:
    """The ``stable_baselines3`` module, or a one-line :class:`ConfigError` naming the ``sb3`` extra."""
    try:
        import stable_baselines3
    except ImportError:
        raise ConfigError(SB3_MISSING) from None
    return stable_baselines3


def algo_class(algo: str) -> Any:
    """The SB3 algorithm class of ``algo`` (:data:`ALGOS`)."""
    sb3 = require_sb3()
    if algo == "sac-lagrangian":
        from safelane.agents.sac_lagrangian import SACLagrangian

        return SACLagrangian
    if algo == "sac":
        return sb3.SAC
    if algo == "ppo":
        return sb3.PPO
    raise ConfigError(f"algo: got {algo!r}; allowed: {', '.join(ALGOS)}")


def make_model(cfg: ContinuousAgentConfig, env: Any, seed: int) -> Any:
    """A new SB3 model of ``cfg.algo`` on ``env`` (an SB3 ``VecEnv``), seeded with ``seed``, on the CPU, silent.
    The SAC family learns from the executed action (:class:`ExecutedActionReplayBuffer`)."""
    cls = algo_class(cfg.algo)
    policy_kwargs = {"net_arch": list(cfg.net_arch or [])}
    common = {
        "learning_rate": cfg.learning_rate,
        "gamma": cfg.gamma,
        "batch_size": cfg.batch_size,
        "ent_coef": cfg.ent_coef,
        "policy_kwargs": policy_kwargs,
        "seed": seed,
        "device": "cpu",
        "verbose": 0,
    }
    if cfg.algo == "ppo":
        return cls(
            "MlpPolicy",
            env,
            n_steps=cfg.n_steps,
            n_epochs=cfg.n_epochs,
            gae_lambda=cfg.gae_lambda,
            clip_range=cfg.clip_range,
            **common,
        )
    sac = {
        "buffer_size": cfg.buffer_size,
        "learning_starts": cfg.learning_starts,
        "train_freq": 1,
        "gradient_steps": cfg.gradient_steps,
        "tau": cfg.tau,
    }
    if cfg.algo == "sac-lagrangian":
        sac.update(
            cost_budget=cfg.cost_budget,
            lambda_lr=cfg.lambda_lr,
            lambda_init=cfg.lambda_init,
            lambda_update_interval=cfg.lambda_update_interval,
        )
    else:
        sac["replay_buffer_class"] = executed_action_buffer_class()
    return cls("MlpPolicy", env, **sac, **common)


def model_bytes(model: Any) -> bytes:
    """``model`` in SB3's zip format (``model.save``), as bytes."""
    buffer = io.BytesIO()
    model.save(buffer)
    return buffer.getvalue()


def replay_buffer_bytes(model: Any) -> bytes | None:
    """``model``'s replay buffer as SB3 pickles it (``save_replay_buffer``); None for an on-policy model."""
    if getattr(model, "replay_buffer", None) is None:
        return None
    buffer = io.BytesIO()
    model.save_replay_buffer(buffer)
    return buffer.getvalue()


def load_model(algo: str, data: bytes, env: Any = None, replay_buffer: bytes | None = None) -> Any:
    """The SB3 model of ``algo`` saved as ``data`` (:func:`model_bytes`), on ``env`` if given, with its replay
    buffer if given (:func:`replay_buffer_bytes`)."""
    model = algo_class(algo).load(io.BytesIO(data), env=env, device="cpu")
    if replay_buffer is not None:
        model.load_replay_buffer(io.BytesIO(replay_buffer))
    return model


def predict(model: Any, obs: np.ndarray) -> np.ndarray:
    """The deterministic action ``[acceleration, steering]`` (float32, in [-1, 1]) of ``model`` for one observation."""
    action, _ = model.predict(np.asarray(obs, dtype=np.float32), deterministic=True)
    return np.asarray(action, dtype=np.float32).reshape(-1)


def executed_action_buffer_class() -> type:
    """:class:`ExecutedActionReplayBuffer` (defined on first use: it subclasses SB3's ``ReplayBuffer``)."""
    from safelane.agents.sac_lagrangian import ExecutedActionReplayBuffer

    return ExecutedActionReplayBuffer
