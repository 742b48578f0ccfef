"""One DQN core and the paper's four methods as small overrides of it (Sections IV.1–4, V).

The agents see observation arrays, safe-action masks and rewards only; they import nothing from
highway-env or the safety model. The pieces, from the bottom up:

* :class:`QNetwork` — the paper's network (Table 3): 26 → 100 → 100 → 5, ELU, densely connected (the input is
  the state's size, ``obs_size``: 26 for the paper's state, more for the states beyond it).
* :class:`ReplayBuffer` / :class:`Batch` — experience replay; every transition keeps the safe-action
  mask of ``s`` and of ``s'`` so that every method can use them.
* :class:`DQNAgent` — traditional Q-learning (Section IV.1): ε-greedy acting, TD target
  ``r + γ·max_a' Q_target(s', a')·(1 − done)``, MSE or Huber loss, Adam, target network.
* :class:`ConstrainedAgent` — Lagrangian constrained Q-learning (eq. 7).
* :class:`QMaskAgent` — Q-masking (Fig. 3): unsafe actions removed from acting and bootstrapping.
* :class:`RobustAgent` — robust Q-masking with Q-shaping (eqs. 13–14).
* ``robust-recurrent`` — the same robust Q-masking on a recurrent Q-network over the decisions of an episode
  (:mod:`safelane.agents.recurrent`, built on this module; :mod:`safelane.agents.registry` makes every method).

The subclasses override only ``action_values`` (what acting maximises), ``allowed`` (which actions
may be taken), ``td_target`` and ``loss``; the training loop (:mod:`safelane.running.training`) is shared.
"""

from __future__ import annotations

import copy
from importlib import resources
from pathlib import Path
from typing import Any, ClassVar, Literal, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from torch import nn

from safelane.agents import inference
from safelane.core.errors import ConfigError
from safelane.core.spaces import N_ACTIONS, OBS_SIZE

HIDDEN_SIZES = (100, 100)
"""Two hidden layers of 100 neurons (Table 3); fixed by the paper, not a setting."""
SHAPING_MARGIN = 1.0
"""The "− 1" of eq. 14: an unsafe pair is shaped to ``min_a Q_θ(s, a) − SHAPING_MARGIN``."""

Method = Literal["dqn", "constrained", "qmask", "robust", "robust-recurrent"]
METHODS: tuple[str, ...] = ("dqn", "constrained", "qmask", "robust")
"""The paper's four methods: what ``all`` means and what ``reproduce`` and ``bench`` compare."""
RECURRENT_METHODS: tuple[str, ...] = ("robust-recurrent",)
"""Methods on a recurrent Q-network (:mod:`safelane.agents.recurrent`): trained by ``safelane train`` alone."""
AGENT_PRESETS: tuple[str, ...] = ("paper", "tuned")


def parse_methods(text: str) -> tuple[str, ...]:
    """``all`` or a comma-separated list of methods → the methods (a one-line ConfigError otherwise)."""
    methods = METHODS if text.strip() == "all" else tuple(dict.fromkeys(m.strip() for m in text.split(",")))
    recurrent = [m for m in methods if m in RECURRENT_METHODS]
    if recurrent:
        raise ConfigError(f"--methods: {recurrent[0]} trains with safelane train --method {recurrent[0]}; allowed "
                          f"here: {', '.join(METHODS)} (comma-separated) or all")  # fmt: skip
    if any(m not in METHODS for m in methods):
        raise ConfigError(f"--methods: got {text!r}; allowed: {', '.join(METHODS)} (comma-separated) or all")
    return methods


# --- configuration ------------------------------------------------------------------------------
class AgentConfig(BaseModel):
    """Every learning setting of an agent. Units: steps are environment decisions (1 s each at the paper's rate)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    method: Method = Field(
        "dqn",
        description="dqn (traditional, IV.1), constrained (Lagrangian, eq. 7), qmask (Q-masking, IV.3) "
        "or robust (robust Q-masking with Q-shaping, eqs. 13–14); robust-recurrent: robust on a recurrent "
        "Q-network (safelane.agents.recurrent).",
    )
    lr: float = Field(5e-4, gt=0, description="Adam learning rate (the paper's α).")
    gamma: float = Field(0.9, ge=0, lt=1, description="Discount factor γ per decision.")
    batch_size: int = Field(
        64, ge=1, description="Transitions per gradient step (mini-batch); robust-recurrent: sequences per step."
    )
    buffer_size: int = Field(15000, ge=1, description="Replay buffer capacity [transitions].")
    learning_starts: int = Field(200, ge=0, description="Environment steps collected before the first update.")
    train_freq: int = Field(1, ge=1, description="Environment steps between updates.")
    gradient_steps: int = Field(1, ge=1, description="Gradient steps per update.")
    target_update_interval: int = Field(200, ge=1, description="Environment steps between target-network updates.")
    tau: float = Field(1.0, gt=0, le=1, description="Target update weight: 1 = copy (hard), < 1 = Polyak average.")
    eps_start: float = Field(1.0, ge=0, le=1, description="Exploration rate ε at step 0.")
    eps_end: float = Field(0.05, ge=0, le=1, description="Final exploration rate ε.")
    eps_decay_steps: int = Field(
        3200,
        ge=0,
        description="Environment steps over which ε decays linearly from eps_start to eps_end (used when "
        "eps_decay_episodes is null).",
    )
    eps_decay_episodes: int | None = Field(
        None,
        ge=1,
        description="If set, ε decays linearly over this many *episodes* instead (constant within an "
        "episode). Crashing episodes are short, so a per-step schedule explores far longer for a method "
        "that crashes (dqn) than for a shielded one; a per-episode schedule gives every method the same.",
    )
    loss: Literal["mse", "huber"] = Field(
        "huber", description="TD loss: mse (the paper's quadratic cost, eq. 15) or huber (smooth L1, δ = 1)."
    )
    grad_clip: float | None = Field(
        10.0, gt=0, description="Clip the global gradient L2 norm to this value (null = no clipping)."
    )
    cost_budget: float = Field(
        1.0,
        ge=0,
        description="constrained: per-episode cost budget C (eq. 7); cost 1 per step whose action was "
        "unsafe under the shield's mask or that ended in a collision.",
    )
    lambda_lr: float = Field(
        0.02, ge=0, description="constrained: dual-ascent step for λ per episode, per unit of excess cost."
    )
    lambda_init: float = Field(0.0, ge=0, description="constrained: initial Lagrange multiplier λ.")
    cost_network: Literal["separate", "shared"] = Field(
        "separate",
        description="constrained: how Q_c is represented. separate = a second network like the paper's "
        "(26 → 100 → 100 → 5); shared = one trunk with 10 outputs, the reward head and the cost head "
        "(26 → 100 → 100 → 5 + 5): half the arithmetic per decision, and the cost head learns from the same "
        "features as the reward head.",
    )
    shaping_weight: float = Field(
        1.0, ge=0, description="robust: weight of the unsafe-pair regression (Q-shaping) in the loss."
    )
    shaping_target: Literal["taken_action", "safe_min", "all_min"] = Field(
        "taken_action",
        description="robust: what an unsafe pair of s is regressed to, minus 1: the (detached) value of the "
        "action taken in s (anchored by its TD target), the minimum over safe actions, or eq. 14's minimum "
        "over all actions. Only taken_action has a fixed point in practice: all_min chases itself − 1, "
        "safe_min cascades through rarely taken safe actions (see q_shaping_loss).",
    )
    shaping_margin: float = Field(
        SHAPING_MARGIN,
        gt=0,
        description="robust: how far below its reference an unsafe pair is regressed (eq. 14's 1). In "
        "reward units: with rewards in [0, 1] per decision the gaps between actions' values are ≈ 0.1, so "
        "a margin of 1 also teaches 'this action is much worse' to neighbouring states where it is safe.",
    )
    shaping_loss: Literal["regression", "hinge"] = Field(
        "regression",
        description="robust: regression pulls every unsafe pair onto its target (both ways); hinge only "
        "pushes an unsafe pair down while it is above its target — the inequality the paper asks for "
        "(unsafe below the safe values) without dragging already-low values, so less of the 'unsafe is "
        "bad' signal leaks into neighbouring states where the action is safe.",
    )
    sequence_length: int = Field(
        8,
        ge=1,
        description="robust-recurrent: decisions of a replayed sequence that enter the loss (after its burn-in).",
    )
    burn_in: int = Field(
        4,
        ge=0,
        description="robust-recurrent: decisions before them that only warm up the hidden state from zero (no "
        "loss); a sequence cut by its episode's start needs none, its hidden state starts as acting's does.",
    )
    recurrent_hidden: int = Field(
        64,
        ge=1,
        description="robust-recurrent: units of the GRU's hidden state (the memory carried between decisions).",
    )


def agent_preset_path(name: str) -> Path:
    """Path of an agent preset: one shipped in the package (``safelane/presets/agents/NAME.yaml``) or a
    YAML file of AgentConfig fields (e.g. a sweep's ``best.yaml``)."""
    if name in AGENT_PRESETS:
        return Path(str(resources.files("safelane") / "presets" / "agents" / f"{name}.yaml"))
    path = Path(name)
    if path.suffix in (".yaml", ".yml"):
        if not path.is_file():
            raise ConfigError(f"agent preset: no such file {name}")
        return path
    raise ConfigError(f"agent preset: unknown preset '{name}'; allowed: {', '.join(AGENT_PRESETS)} or a .yaml file")


def build_agent_config(data: dict[str, Any]) -> AgentConfig:
    """Validate a plain dict into an :class:`AgentConfig` (raises a one-line :class:`ConfigError`)."""
    try:
        return AgentConfig.model_validate(data)
    except ValidationError as err:
        e = err.errors()[0]
        key = "agent." + ".".join(str(p) for p in e["loc"])
        if e["type"] == "extra_forbidden":
            raise ConfigError(f"{key}: unknown key; allowed: {', '.join(AgentConfig.model_fields)}") from None
        raise ConfigError(f"{key}: {e['msg']} (got {e.get('input')!r})") from None


def load_agent_config(
    preset: str = "tuned", method: str | None = None, overrides: dict[str, Any] | None = None
) -> AgentConfig:
    """Load an agent preset, set ``method`` and apply ``overrides`` (keys without the ``agent.`` prefix)."""
    with open(agent_preset_path(preset)) as f:
        data = yaml.safe_load(f) or {}
    if method is not None:
        data["method"] = method
    data.update(overrides or {})
    return build_agent_config(data)


def linear_epsilon(step: int, cfg: AgentConfig, episode: int = 0) -> float:
    """ε at environment step ``step`` of 0-based episode ``episode``: linear from ``eps_start`` to
    ``eps_end`` over ``eps_decay_episodes`` episodes if set, else over ``eps_decay_steps`` steps; then
    constant."""
    if cfg.eps_decay_episodes is not None:
        progress, span = episode, cfg.eps_decay_episodes
    else:
        progress, span = step, cfg.eps_decay_steps
    if span <= 0 or progress >= span:
        return cfg.eps_end
    return cfg.eps_start + (cfg.eps_end - cfg.eps_start) * progress / span


# --- network and replay -------------------------------------------------------------------------
class QNetwork(nn.Module):
    """The paper's DQN (Table 3): ``obs_size`` inputs (26, eq. 3), two dense hidden layers of 100 ELU units, 5
    Q-values."""

    def __init__(self, obs_size: int = OBS_SIZE, n_actions: int = N_ACTIONS) -> None:
        super().__init__()
        h1, h2 = HIDDEN_SIZES
        self.net = nn.Sequential(
            nn.Linear(obs_size, h1), nn.ELU(), nn.Linear(h1, h2), nn.ELU(), nn.Linear(h2, n_actions)
        )

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Q-values, shape (batch, n_actions), for observations of shape (batch, obs_size)."""
        return self.net(obs)


class Batch(NamedTuple):
    """A mini-batch of transitions as tensors (B = batch size, A = number of actions)."""

    obs: torch.Tensor  # (B, obs_size) float32
    actions: torch.Tensor  # (B,) int64
    rewards: torch.Tensor  # (B,) float32, eq. 6
    costs: torch.Tensor  # (B,) float32, 1 = unsafe action or collision
    next_obs: torch.Tensor  # (B, obs_size) float32
    dones: torch.Tensor  # (B,) float32, 1 = terminated (a crash); truncation is not terminal
    masks: torch.Tensor  # (B, A) bool, safe actions of s
    next_masks: torch.Tensor  # (B, A) bool, safe actions of s'


def sanitize_mask(mask: np.ndarray | None, n_actions: int = N_ACTIONS) -> np.ndarray:
    """A bool mask of shape (n_actions,); ``None`` or an all-False mask means every action is allowed."""
    if mask is None:
        return np.ones(n_actions, dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != (n_actions,):
        raise ValueError(f"action mask: expected shape ({n_actions},), got {mask.shape}")
    return mask if mask.any() else np.ones(n_actions, dtype=bool)


class ReplayBuffer:
    """Fixed-capacity circular experience replay in preallocated numpy arrays."""

    FIELDS: ClassVar[tuple[str, ...]] = (
        "obs",
        "actions",
        "rewards",
        "costs",
        "next_obs",
        "dones",
        "masks",
        "next_masks",
    )

    def __init__(self, capacity: int, obs_size: int = OBS_SIZE, n_actions: int = N_ACTIONS) -> None:
        self.capacity = capacity
        self.obs = np.zeros((capacity, obs_size), dtype=np.float32)
        self.actions = np.zeros(capacity, dtype=np.int64)
        self.rewards = np.zeros(capacity, dtype=np.float32)
        self.costs = np.zeros(capacity, dtype=np.float32)
        self.next_obs = np.zeros((capacity, obs_size), dtype=np.float32)
        self.dones = np.zeros(capacity, dtype=np.float32)
        self.masks = np.ones((capacity, n_actions), dtype=bool)
        self.next_masks = np.ones((capacity, n_actions), dtype=bool)
        self.pos = 0
        self.size = 0

    def __len__(self) -> int:
        return self.size

    def add(
        self,
        obs: np.ndarray,
        action: int,
        reward: float,
        cost: float,
        next_obs: np.ndarray,
        terminated: bool,
        mask: np.ndarray,
        next_mask: np.ndarray,
    ) -> None:
        """Store one transition, overwriting the oldest once full."""
        i = self.pos
        self.obs[i] = obs
        self.actions[i] = action
        self.rewards[i] = reward
        self.costs[i] = cost
        self.next_obs[i] = next_obs
        self.dones[i] = float(terminated)
        self.masks[i] = mask
        self.next_masks[i] = next_mask
        self.pos = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def begin_episode(self) -> None:
        """A new episode starts: nothing to note for single transitions (a sequence replay notes it)."""

    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        """``batch_size`` transitions drawn uniformly with replacement using ``rng``."""
        idx = rng.integers(0, self.size, size=batch_size)
        return Batch(*(torch.from_numpy(getattr(self, name)[idx]) for name in self.FIELDS))

    def state_dict(self) -> dict[str, Any]:
        """The filled part of the buffer as tensors, plus the write position (for checkpoints)."""
        state: dict[str, Any] = {
            name: torch.from_numpy(getattr(self, name)[: self.size].copy()) for name in self.FIELDS
        }
        state.update(pos=self.pos, size=self.size, capacity=self.capacity)
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a buffer saved by :meth:`state_dict` (same capacity)."""
        if int(state["capacity"]) != self.capacity:
            raise ValueError(f"replay buffer capacity {state['capacity']} != {self.capacity}")
        self.size, self.pos = int(state["size"]), int(state["pos"])
        for name in self.FIELDS:
            getattr(self, name)[: self.size] = state[name].numpy()


# --- pure helpers for the losses (tested on hand-worked numbers) --------------------------------
def elementwise_loss(kind: str, prediction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-element squared error (``mse``, eq. 15) or smooth-L1 with δ = 1 (``huber``)."""
    if kind == "mse":
        return F.mse_loss(prediction, target, reduction="none")
    return F.smooth_l1_loss(prediction, target, reduction="none")


def masked_max(q: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``max_a q[:, a]`` over actions where ``mask`` is True (Q-masking's bootstrap)."""
    return q.masked_fill(~mask, float("-inf")).max(dim=1).values


def shaped_q(q: torch.Tensor, mask: torch.Tensor, margin: float = SHAPING_MARGIN) -> torch.Tensor:
    """Q-shaping (eqs. 13–14): ``Q(s, a) = Q_θ(s, a) + Q_u(s, a)``.

    Eq. 14 sets ``Q_u = 0`` on safe pairs. On an unsafe pair it writes ``Q_u = min_a Q_θ(s, a) − 1``;
    read as an additive correction that makes the *sum* ``Q_θ + Q_u`` equal ``min_a Q_θ(s, ·) − 1``
    (the paper's stated intent: "the Q of an unsafe pair will be less than the minimum of the safe
    pairs"), ``Q_u = (min_a Q_θ(s, ·) − 1) − Q_θ(s, a)``. So the shaped value is ``Q_θ(s, a)`` for a
    safe pair and ``min_a Q_θ(s, ·) − 1`` (minimum over all actions) for an unsafe one, strictly below
    every safe value: the argmax and the max of shaped Q are those over safe actions only. ``margin``
    replaces eq. 14's 1 (``AgentConfig.shaping_margin``).
    """
    floor = q.min(dim=1, keepdim=True).values - margin
    return torch.where(mask, q, floor)


def shaping_target(
    q: torch.Tensor,
    mask: torch.Tensor,
    actions: torch.Tensor,
    kind: str = "taken_action",
    margin: float = SHAPING_MARGIN,
) -> torch.Tensor:
    """The (detached) value an unsafe pair of each row is regressed to, shape (B, 1).

    ``all_min``: ``min_a Q_θ(s, a) − 1``, eq. 14 as printed; ``safe_min``: the minimum over safe
    actions − 1; ``taken_action``: ``Q_θ(s, a_taken) − 1`` (the taken action is safe and anchored by
    its TD target). ``margin`` replaces the 1 (``shaping_margin``). See :func:`q_shaping_loss` for why
    the default is ``taken_action``.
    """
    if kind == "all_min":
        ref = q.min(dim=1, keepdim=True).values
    elif kind == "safe_min":
        ref = q.masked_fill(~mask, float("inf")).min(dim=1, keepdim=True).values
    else:
        ref = q.gather(1, actions.unsqueeze(1))
    return ref.detach() - margin


def q_shaping_loss(
    q: torch.Tensor,
    actions: torch.Tensor,
    td_target: torch.Tensor,
    mask: torch.Tensor,
    weight: float = 1.0,
    kind: str = "mse",
    target: str = "taken_action",
    one_sided: bool = False,
    margin: float = SHAPING_MARGIN,
) -> torch.Tensor:
    """Robust Q-masking loss: TD loss of the taken actions + ``weight`` × unsafe-pair regression.

    ``TD = mean_b ℓ(Q_θ(s_b, a_b), y_b)``; ``shaping = mean over unsafe pairs (b, a) of
    ℓ(Q_θ(s_b, a), t_b)`` with ``t_b`` = :func:`shaping_target` (no gradient; 0 when the batch has no
    unsafe pair); ``loss = TD + weight · shaping``. ``ℓ`` is the squared error (mse) or smooth L1
    (huber); with ``one_sided`` (hinge) only the excess ``max(0, Q_θ(s_b, a) − t_b)`` is penalised.
    The regression teaches the network itself the low value of unsafe pairs, so it
    generalises to nearby states instead of staying high as under Q-masking.

    Why the target is anchored to the taken action: with eq. 14's minimum over all actions an unsafe
    value that is the minimum is pulled to itself − 1 at every step (no fixed point; two unsafe actions
    leapfrog) and Q diverges within a few thousand updates. With the minimum over safe actions the
    chase goes through safe actions that are rarely taken (no TD anchor): in safelane's state the
    road edge is not observed, so LANE_LEFT (unsafe at the left edge) and LANE_RIGHT (unsafe at the
    right edge) push each other down, and after 20 000 decisions their values reached −5·10⁴. The
    taken action's value is tied to rewards by its own TD target, so the regression has a fixed point.
    """
    q_taken = q.gather(1, actions.unsqueeze(1)).squeeze(1)
    td = elementwise_loss(kind, q_taken, td_target).mean()
    unsafe = ~mask
    goal = shaping_target(q, mask, actions, target, margin).expand_as(q)
    if one_sided:
        excess = torch.clamp(q - goal, min=0.0)
        per_pair = elementwise_loss(kind, excess, torch.zeros_like(excess)) * unsafe
    else:
        per_pair = elementwise_loss(kind, q, goal) * unsafe
    shaping = per_pair.sum() / unsafe.sum().clamp(min=1)
    return td + weight * shaping


# --- the core -----------------------------------------------------------------------------------
class DQNAgent:
    """Traditional DQN (Section IV.1, Section V): the core every method overrides in small places.

    ``act(obs, mask, eps)`` is ε-greedy over ``allowed(mask)``; ``update(batch)`` does one Adam step on
    ``loss(batch)``; ``sync_target()`` moves the target network(s) toward the online one(s).
    """

    method: ClassVar[str] = "dqn"
    uses_mask: ClassVar[bool] = False
    """True when the safe-action mask restricts acting (and bootstrapping)."""
    train_shield: ClassVar[str] = "nominal"
    """Shield mode of the training environment: the masks every method records (only mask users act on
    them; constrained counts their violations as cost)."""
    needs_cost: ClassVar[bool] = False
    """True when the agent learns from a per-step cost (constrained's eq. 7)."""
    recurrent: ClassVar[bool] = False
    """True when acting carries a hidden state across an episode's decisions (reset by :meth:`begin_episode`)."""

    def __init__(self, cfg: AgentConfig, seed: int = 0, obs_size: int = OBS_SIZE) -> None:
        self.cfg = cfg
        self.n_actions = N_ACTIONS
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.networks: dict[str, nn.Module] = self.build_networks(obs_size)
        self.targets: dict[str, nn.Module] = {k: copy.deepcopy(v) for k, v in self.networks.items()}
        for target in self.targets.values():
            target.requires_grad_(False)
        params = [p for net in self.networks.values() for p in net.parameters()]
        # fused: one kernel for all parameters instead of ~10 small ops each (≈ 15 % of a gradient
        # step on this network); results are deterministic, as with the default implementation.
        self.optimizer = torch.optim.Adam(params, lr=cfg.lr, fused=True)
        self.acting: dict[str, inference.ActingNetwork] = {
            k: inference.ActingNetwork(v) for k, v in self.networks.items()
        }
        """The online networks' forward passes for acting, without torch (:mod:`.inference`)."""
        self.rng = np.random.default_rng(seed)
        """The one generator for exploration and replay sampling (saved in checkpoints)."""
        self._all_allowed = np.ones(self.n_actions, dtype=bool)

    # -- overridable pieces ----------------------------------------------------------------------
    def build_networks(self, obs_size: int) -> dict[str, nn.Module]:
        """The online networks by name (targets are copies)."""
        return {"q": QNetwork(obs_size, N_ACTIONS)}

    @property
    def q_net(self) -> nn.Module:
        """The online reward Q-network."""
        return self.networks["q"]

    def allowed(self, mask: np.ndarray) -> np.ndarray:
        """Actions the agent may take given the safe-action mask (all of them for dqn)."""
        return self._all_allowed

    def action_values(self, obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """The values acting maximises, shape (B, A) (Q_θ for dqn)."""
        return self.q_net(obs)

    def acting_values(self, obs: np.ndarray, masks: np.ndarray) -> np.ndarray:
        """:meth:`action_values` computed without torch (float64, (B, A)): what acting maximises."""
        return self.acting["q"](obs)

    def td_target(self, batch: Batch) -> torch.Tensor:
        """``r + γ·max_a' Q_target(s', a')·(1 − done)``, shape (B,)."""
        with torch.no_grad():
            next_v = self.targets["q"](batch.next_obs).max(dim=1).values
            return batch.rewards + self.cfg.gamma * next_v * (1.0 - batch.dones)

    def loss(self, batch: Batch) -> torch.Tensor:
        """TD loss of the taken actions (mse = eq. 15, or huber)."""
        q_taken = self.q_net(batch.obs).gather(1, batch.actions.unsqueeze(1)).squeeze(1)
        return elementwise_loss(self.cfg.loss, q_taken, self.td_target(batch)).mean()

    def end_episode(self, episode_cost: float) -> None:
        """Per-episode hook (constrained updates λ here)."""

    def begin_episode(self) -> None:
        """Hook at each reset, before the episode's first decision (a recurrent agent forgets its hidden state)."""

    def new_replay(self, obs_size: int) -> ReplayBuffer:
        """The agent's empty replay buffer of ``buffer_size`` transitions (a recurrent agent's keeps episodes)."""
        return ReplayBuffer(self.cfg.buffer_size, obs_size)

    # -- shared machinery -------------------------------------------------------------------------
    def greedy(self, obs: np.ndarray, mask: np.ndarray | None = None) -> int:
        """The greedy action for one observation (26,) among ``allowed(mask)``."""
        mask = sanitize_mask(mask, self.n_actions)
        return int(self.greedy_batch(np.asarray(obs, dtype=np.float32)[None, :], mask[None, :])[0])

    def greedy_batch(self, obs: np.ndarray, masks: np.ndarray | None = None) -> np.ndarray:
        """Greedy actions (B,) int64 for observations (B, 26) and safe-action masks (B, 5) (None, or an
        all-False row: every action allowed). Row ``b``'s action depends on row ``b`` only, so a batch
        gives each row the action it gets alone (:mod:`safelane.agents.inference`); ties go to the
        lowest action index."""
        obs = np.asarray(obs, dtype=np.float32)
        if masks is None:
            masks = np.ones((obs.shape[0], self.n_actions), dtype=bool)
        else:
            masks = np.array(masks, dtype=bool)
            if masks.shape != (obs.shape[0], self.n_actions):
                raise ValueError(f"action masks: expected shape ({obs.shape[0]}, {self.n_actions}), got {masks.shape}")
            masks[~masks.any(axis=1)] = True
        values = self.acting_values(obs, masks)
        allowed = masks if self.uses_mask else np.ones_like(masks)
        return np.argmax(np.where(allowed, values, -np.inf), axis=1)

    def act(self, obs: np.ndarray, mask: np.ndarray | None, eps: float) -> int:
        """ε-greedy: with probability ``eps`` a uniform action among ``allowed(mask)``, else greedy."""
        mask = sanitize_mask(mask, self.n_actions)
        if self.rng.random() < eps:
            choices = np.flatnonzero(self.allowed(mask))
            return int(choices[self.rng.integers(len(choices))])
        return self.greedy(obs, mask)

    def update(self, batch: Batch) -> float:
        """One gradient step on ``loss(batch)``; returns the loss value."""
        loss = self.loss(batch)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.cfg.grad_clip is not None:
            params = [p for group in self.optimizer.param_groups for p in group["params"]]
            nn.utils.clip_grad_norm_(params, self.cfg.grad_clip)
        self.optimizer.step()
        for acting in self.acting.values():
            acting.invalidate()
        return float(loss.detach())

    def sync_target(self) -> None:
        """Target ← online (``tau = 1``) or ``target ← (1 − τ)·target + τ·online``."""
        tau = self.cfg.tau
        with torch.no_grad():
            for name, net in self.networks.items():
                target = self.targets[name]
                if tau >= 1.0:
                    target.load_state_dict(net.state_dict())
                else:
                    for tp, p in zip(target.parameters(), net.parameters(), strict=True):
                        tp.mul_(1.0 - tau).add_(p, alpha=tau)

    def extra_state(self) -> dict[str, Any]:
        """Method-specific state to checkpoint (λ for constrained)."""
        return {}

    def load_extra_state(self, state: dict[str, Any]) -> None:
        """Restore :meth:`extra_state`."""

    def state_dict(self) -> dict[str, Any]:
        """Networks, targets, optimizer, exploration generator and method state (for checkpoints)."""
        return {
            "method": self.method,
            "networks": {k: v.state_dict() for k, v in self.networks.items()},
            "targets": {k: v.state_dict() for k, v in self.targets.items()},
            "optimizer": self.optimizer.state_dict(),
            "rng": self.rng.bit_generator.state,
            "extra": self.extra_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (raises ValueError on a different method or network)."""
        if state.get("method") != self.method:
            raise ValueError(f"checkpoint is for method {state.get('method')!r}, not {self.method!r}")
        if sorted(state["networks"]) != sorted(self.networks):
            raise ValueError(f"checkpoint has networks {sorted(state['networks'])}, not {sorted(self.networks)}")
        for k, net in self.networks.items():
            net.load_state_dict(state["networks"][k])
            self.targets[k].load_state_dict(state["targets"][k])
        self.optimizer.load_state_dict(state["optimizer"])
        for acting in self.acting.values():
            acting.invalidate()
        self.rng.bit_generator.state = state["rng"]
        self.load_extra_state(state.get("extra", {}))


class ConstrainedAgent(DQNAgent):
    """Lagrangian constrained Q-learning (eq. 7) with a per-episode cost budget ``C``.

    A second network — or, with ``cost_network: shared``, a second head on the reward network's trunk —
    learns the cost value ``Q_c`` (cost 1 per step whose action the shield marked unsafe, or that ended
    in a collision) by its own TD target. Acting and bootstrapping maximise the
    Lagrangian ``Q_r − λ·Q_c``: ``a* = argmax_a' (Q_r^tgt − λ·Q_c^tgt)(s', a')``,
    ``y_r = r + γ·Q_r^tgt(s', a*)``, ``y_c = c + γ·Q_c^tgt(s', a*)``. λ ≥ 0 follows dual ascent after each
    episode: ``λ ← max(0, λ + lambda_lr·(episode_cost − C))``.
    """

    method: ClassVar[str] = "constrained"
    needs_cost: ClassVar[bool] = True

    def __init__(self, cfg: AgentConfig, seed: int = 0, obs_size: int = OBS_SIZE) -> None:
        super().__init__(cfg, seed, obs_size)
        self.lam = float(cfg.lambda_init)
        """The Lagrange multiplier λ ≥ 0 (reward units per unit of cost)."""

    def build_networks(self, obs_size: int) -> dict[str, nn.Module]:
        """Reward and cost Q: two networks (``q``, ``cost``) or one with both heads (``q_cost``)."""
        if self.cfg.cost_network == "shared":
            return {"q_cost": QNetwork(obs_size, 2 * N_ACTIONS)}
        return {"q": QNetwork(obs_size, N_ACTIONS), "cost": QNetwork(obs_size, N_ACTIONS)}

    def reward_and_cost(self, obs: torch.Tensor, target: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """``(Q_r, Q_c)``, each (B, A), from the online networks or (``target=True``) the target ones."""
        nets = self.targets if target else self.networks
        if "q_cost" in nets:
            both = nets["q_cost"](obs)
            return both[:, : self.n_actions], both[:, self.n_actions :]
        return nets["q"](obs), nets["cost"](obs)

    def action_values(self, obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """``Q_r − λ·Q_c``."""
        q_r, q_c = self.reward_and_cost(obs)
        return q_r - self.lam * q_c

    def acting_values(self, obs: np.ndarray, masks: np.ndarray) -> np.ndarray:
        """``Q_r − λ·Q_c`` without torch."""
        if "q_cost" in self.acting:
            both = self.acting["q_cost"](obs)
            q_r, q_c = both[:, : self.n_actions], both[:, self.n_actions :]
        else:
            q_r, q_c = self.acting["q"](obs), self.acting["cost"](obs)
        return q_r - self.lam * q_c

    def _targets(self, batch: Batch) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            next_r, next_c = self.reward_and_cost(batch.next_obs, target=True)
            best = (next_r - self.lam * next_c).argmax(dim=1, keepdim=True)
            not_done = 1.0 - batch.dones
            y_r = batch.rewards + self.cfg.gamma * next_r.gather(1, best).squeeze(1) * not_done
            y_c = batch.costs + self.cfg.gamma * next_c.gather(1, best).squeeze(1) * not_done
        return y_r, y_c

    def td_target(self, batch: Batch) -> torch.Tensor:
        """The reward target ``y_r`` (the cost target is in :meth:`loss`)."""
        return self._targets(batch)[0]

    def loss(self, batch: Batch) -> torch.Tensor:
        """TD loss of ``Q_r`` toward ``y_r`` plus TD loss of ``Q_c`` toward ``y_c``."""
        y_r, y_c = self._targets(batch)
        a = batch.actions.unsqueeze(1)
        q_r_all, q_c_all = self.reward_and_cost(batch.obs)
        q_r, q_c = q_r_all.gather(1, a).squeeze(1), q_c_all.gather(1, a).squeeze(1)
        kind = self.cfg.loss
        return elementwise_loss(kind, q_r, y_r).mean() + elementwise_loss(kind, q_c, y_c).mean()

    def end_episode(self, episode_cost: float) -> None:
        """Dual ascent toward the budget: ``λ ← max(0, λ + lambda_lr·(episode_cost − C))``."""
        self.lam = max(0.0, self.lam + self.cfg.lambda_lr * (episode_cost - self.cfg.cost_budget))

    def extra_state(self) -> dict[str, Any]:
        """λ."""
        return {"lambda": self.lam}

    def load_extra_state(self, state: dict[str, Any]) -> None:
        """Restore λ."""
        self.lam = float(state["lambda"])


class QMaskAgent(DQNAgent):
    """Q-masking (Section IV.3, Fig. 3): unsafe actions are never taken nor bootstrapped from.

    Greedy and random actions are both drawn among the safe actions of ``s``; the TD target's max
    runs over the safe actions of ``s'``. The network's values of unsafe pairs are otherwise left as
    they are — the weakness the paper points out (high values of masked actions generalise).
    """

    method: ClassVar[str] = "qmask"
    uses_mask: ClassVar[bool] = True

    def allowed(self, mask: np.ndarray) -> np.ndarray:
        """The safe actions."""
        return mask

    def td_target(self, batch: Batch) -> torch.Tensor:
        """``r + γ·max_{a' safe in s'} Q_target(s', a')·(1 − done)``."""
        with torch.no_grad():
            next_v = masked_max(self.targets["q"](batch.next_obs), batch.next_masks)
            return batch.rewards + self.cfg.gamma * next_v * (1.0 - batch.dones)


class RobustAgent(QMaskAgent):
    """Robust Q-masking with Q-shaping (Section IV.4, eqs. 13–14); masks come from the robust shield.

    It *acts and bootstraps exactly as Q-masking* does, so it derives from :class:`QMaskAgent`: the shaped
    Q (:func:`shaped_q`) equals Q_θ on safe pairs and lies below every safe value on unsafe ones, so its
    argmax over the allowed (safe) actions is Q-masking's, and the max of the shaped target Q of ``s'`` is
    the max over the safe actions of ``s'`` — Q-masking's TD target (masks are never empty:
    :func:`sanitize_mask`). ``tests/test_agents.py`` keeps this equivalence. What differs is the mask (the
    robust shield's) and the loss (:func:`q_shaping_loss`): a regression of every unsafe pair of ``s``
    toward a value ``shaping_margin`` below a reference (``shaping_target``: by default the taken action's
    value; eq. 14's minimum diverges as a target), so the network learns the low value and generalises it.
    """

    method: ClassVar[str] = "robust"
    train_shield: ClassVar[str] = "robust"

    def action_values(self, obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Shaped Q (eqs. 13–14) with the configured margin; its argmax over safe actions is Q-masking's."""
        return shaped_q(self.q_net(obs), mask, self.cfg.shaping_margin)

    def acting_values(self, obs: np.ndarray, masks: np.ndarray) -> np.ndarray:
        """Shaped Q without torch (as :func:`shaped_q`)."""
        q = self.acting["q"](obs)
        return np.where(masks, q, q.min(axis=1, keepdims=True) - self.cfg.shaping_margin)

    def loss(self, batch: Batch) -> torch.Tensor:
        """:func:`q_shaping_loss` with the configured weight, loss kind and regression target."""
        cfg = self.cfg
        return q_shaping_loss(
            self.q_net(batch.obs),
            batch.actions,
            self.td_target(batch),
            batch.masks,
            weight=cfg.shaping_weight,
            kind=cfg.loss,
            target=cfg.shaping_target,
            one_sided=cfg.shaping_loss == "hinge",
            margin=cfg.shaping_margin,
        )


AGENT_CLASSES: dict[str, type[DQNAgent]] = {
    cls.method: cls for cls in (DQNAgent, ConstrainedAgent, QMaskAgent, RobustAgent)
}


def make_agent(cfg: AgentConfig, seed: int = 0, obs_size: int = OBS_SIZE) -> DQNAgent:
    """The agent for ``cfg.method`` (one of :data:`METHODS`), networks initialised from ``seed``; a recurrent method's
    agent: :func:`safelane.agents.registry.make_agent`."""
    if cfg.method not in AGENT_CLASSES:
        raise ValueError(f"make_agent: {cfg.method} is made by safelane.agents.registry.make_agent")
    return AGENT_CLASSES[cfg.method](cfg, seed, obs_size)
