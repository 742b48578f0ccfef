"""Robust Q-masking on a recurrent Q-network (DRQN-style): an agent that remembers the episode's decisions.

With the driver types hidden, a car's type shows only in its motion over several decisions; ``state: paper``
(eq. 3) is one instant. This agent reads ``paper`` decision by decision through a GRU, so its Q-values can depend
on everything it saw since the episode's reset (``paper-stack`` gives a feed-forward network the last 4 instead).

* :class:`RecurrentQNetwork` — ``obs_size`` → 100 ELU → GRU(``recurrent_hidden``) → 5 Q-values: the paper's network
  (Table 3) with its second dense layer replaced by the recurrent one, as DRQN replaces a dense layer by an LSTM.
  A GRU rather than an LSTM: one state tensor to carry and reset, fewer weights, the same memory over the few
  decisions (tens of seconds) a driver's type takes to show.
* :class:`SequenceReplay` — every transition with its decision index in its episode; a sample is a sub-sequence of
  one episode, cut at the episode's start (never crossing it) and zero-padded at its end.
* :class:`RecurrentRobustAgent` — :class:`~safelane.agents.dqn.RobustAgent`'s masking: the shield's mask at action
  time (greedy and random actions), the safe actions of ``s'`` in the target's max, Q-shaping of the unsafe pairs
  in the loss (:func:`~safelane.agents.dqn.q_shaping_loss`); the hidden state reset at each episode's start.

Why sequences start from a zero hidden state, not a stored one: a hidden state stored when acting was computed by
older weights and goes stale as the network learns (R2D2's staleness), and would make the replay and checkpoints
``recurrent_hidden`` numbers per decision larger. A sequence that begins at its episode's first decision starts
exactly as acting does (reset to zero); one that begins later runs ``burn_in`` decisions without loss first, so
the hidden state has warmed up from zero before the ``sequence_length`` decisions that enter the loss.
"""

from __future__ import annotations

from typing import Any, ClassVar, NamedTuple

import numpy as np
import torch
from torch import nn

from safelane.agents.dqn import (
    HIDDEN_SIZES,
    AgentConfig,
    ReplayBuffer,
    RobustAgent,
    masked_max,
    q_shaping_loss,
    sanitize_mask,
    shaped_q,
)
from safelane.core.spaces import N_ACTIONS, OBS_SIZE


class RecurrentQNetwork(nn.Module):
    """``obs_size`` → 100 ELU → GRU(``hidden``) → ``n_actions`` Q-values, over a sequence of decisions."""

    def __init__(self, obs_size: int = OBS_SIZE, n_actions: int = N_ACTIONS, hidden: int = 64) -> None:
        super().__init__()
        self.encoder = nn.Sequential(nn.Linear(obs_size, HIDDEN_SIZES[0]), nn.ELU())
        self.gru = nn.GRU(HIDDEN_SIZES[0], hidden, batch_first=True)
        self.head = nn.Linear(hidden, n_actions)

    def forward(self, obs: torch.Tensor, hidden: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Q-values (B, T, A) of observations (B, T, obs_size), and the hidden state (1, B, H) after the last one;
        ``hidden`` (1, B, H) is the state before the first (None: zeros, an episode's start)."""
        out, last = self.gru(self.encoder(obs), hidden)
        return self.head(out), last


class SequenceBatch(NamedTuple):
    """Sub-sequences of episodes as tensors (B sequences, T = burn_in + sequence_length decisions, A actions).

    Position 0 is the sequence's first decision (its episode's first, or a later one); positions past the
    sequence's ``valid`` ones are zeros. ``next_obs[:, t]`` is ``obs[:, t + 1]`` wherever both are valid.
    """

    obs: torch.Tensor  # (B, T, obs_size) float32
    actions: torch.Tensor  # (B, T) int64
    rewards: torch.Tensor  # (B, T) float32, eq. 6
    costs: torch.Tensor  # (B, T) float32, 1 = unsafe action or collision
    next_obs: torch.Tensor  # (B, T, obs_size) float32
    dones: torch.Tensor  # (B, T) float32, 1 = terminated (a crash); truncation is not terminal
    masks: torch.Tensor  # (B, T, A) bool, safe actions of s
    next_masks: torch.Tensor  # (B, T, A) bool, safe actions of s'
    valid: torch.Tensor  # (B, T) bool, a stored decision (not padding)
    trained: torch.Tensor  # (B, T) bool, a decision in the loss


class SequenceReplay(ReplayBuffer):
    """Fixed-capacity circular replay of whole episodes; samples sub-sequences that stay inside one episode.

    The transitions are :class:`~safelane.agents.dqn.ReplayBuffer`'s; each also keeps its decision index in its
    episode (``steps``, 0 at the reset) and its write count (``stamps``): a transition's predecessors in its episode
    are the slots before it whose stamps count down by one, so an episode whose start was overwritten still yields
    its stored part, and nothing else.
    """

    FIELDS: ClassVar[tuple[str, ...]] = (*ReplayBuffer.FIELDS, "steps", "stamps")

    def __init__(
        self, capacity: int, obs_size: int = OBS_SIZE, burn_in: int = 4, length: int = 8, n_actions: int = N_ACTIONS
    ) -> None:
        super().__init__(capacity, obs_size, n_actions)
        self.burn_in, self.length = burn_in, length
        self.steps = np.zeros(capacity, dtype=np.int64)
        self.stamps = np.zeros(capacity, dtype=np.int64)
        self.written = 0
        self._step = 0  # decision index of the next transition in the current episode

    @property
    def window(self) -> int:
        """Decisions of a sampled sequence: ``burn_in + length``."""
        return self.burn_in + self.length

    def begin_episode(self) -> None:
        """The next transition is the first of a new episode."""
        self._step = 0

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
        """Store the current episode's next transition, overwriting the oldest once full."""
        self.steps[self.pos], self.stamps[self.pos] = self._step, self.written
        super().add(obs, action, reward, cost, next_obs, terminated, mask, next_mask)
        self._step += 1
        self.written += 1

    def windows(self, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For sequences ending at slots ``ends`` (B,): the slots (B, T) from each sequence's first decision on,
        which of them are ``valid`` (B, T) and which are ``trained`` (B, T).

        A sequence reaches back ``window − 1`` decisions, or to its episode's first stored one if that is
        nearer. The loss takes its last ``length`` decisions that follow ``burn_in`` others in the sequence, or,
        in a sequence that starts at its episode's reset (its hidden state is then exactly acting's), its last
        ``length`` decisions whatever precedes them."""
        oldest = self.written - self.size  # the stamp of the oldest stored transition
        back = np.minimum(np.minimum(self.steps[ends], self.window - 1), self.stamps[ends] - oldest)
        count = back + 1  # decisions in each sequence
        at_reset = self.steps[ends] == back  # the sequence starts at its episode's first decision
        offsets = np.arange(self.window)
        slots = (ends[:, None] - back[:, None] + offsets[None, :]) % self.capacity
        valid = offsets[None, :] < count[:, None]
        # A sequence cut by the overwritten part of its episode starts mid-episode: it still needs its burn-in.
        first = np.maximum(count - self.length, np.where(at_reset, 0, self.burn_in))
        trained = valid & (offsets[None, :] >= first[:, None])
        return slots, valid, trained

    def sample(self, batch_size: int, rng: np.random.Generator) -> SequenceBatch:
        """``batch_size`` sequences, each ending at a stored transition drawn uniformly with replacement among those
        that can enter the loss: the ones whose episode's start is stored, or with ``burn_in`` stored
        predecessors (not so only in the oldest, overwritten part of the buffer)."""
        stored = self.stamps[: self.size] - (self.written - self.size)  # stored predecessors, ignoring episodes
        eligible = np.flatnonzero((self.steps[: self.size] <= stored) | (stored >= self.burn_in))
        if eligible.size == 0:  # a buffer smaller than the burn-in: every sequence is cut
            eligible = np.arange(self.size)
        ends = eligible[rng.integers(0, eligible.size, size=batch_size)]
        slots, valid, trained = self.windows(ends)

        def take(name: str) -> torch.Tensor:
            values = getattr(self, name)[slots]
            pad = valid.reshape(valid.shape + (1,) * (values.ndim - 2))
            return torch.from_numpy(np.where(pad, values, np.zeros((), dtype=values.dtype)))

        fields = [take(name) for name in ReplayBuffer.FIELDS]
        return SequenceBatch(*fields, torch.from_numpy(valid), torch.from_numpy(trained))

    def state_dict(self) -> dict[str, Any]:
        """:meth:`ReplayBuffer.state_dict` with the episodes' indices and the write count (for checkpoints)."""
        return {**super().state_dict(), "written": self.written}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a buffer saved by :meth:`state_dict` (same capacity); checkpoints are taken between episodes."""
        if "steps" not in state:
            raise ValueError("replay buffer: a feed-forward agent's transitions, not a recurrent agent's episodes")
        super().load_state_dict(state)
        self.written = int(state["written"])
        self._step = 0


class RecurrentRobustAgent(RobustAgent):
    """Robust Q-masking (:class:`~safelane.agents.dqn.RobustAgent`) on a :class:`RecurrentQNetwork`.

    Acting feeds each decision's observation through the GRU, carrying the hidden state from the previous
    decision; :meth:`begin_episode` resets it to zero. It acts one decision at a time (the hidden state is one
    episode's), so :meth:`greedy_batch` is refused. Learning replays sequences (:class:`SequenceReplay`); the
    target network runs over the same sequence, one decision further, for the values of ``s'``.
    """

    method: ClassVar[str] = "robust-recurrent"
    recurrent: ClassVar[bool] = True

    def __init__(self, cfg: AgentConfig, seed: int = 0, obs_size: int = OBS_SIZE) -> None:
        super().__init__(cfg, seed, obs_size)
        self.acting = {}  # acting goes through torch: the numba kernel is feed-forward only
        self.hidden: torch.Tensor | None = None
        """The GRU's state (1, 1, recurrent_hidden) after the episode's decisions so far (None: the reset's zeros)."""

    def build_networks(self, obs_size: int) -> dict[str, nn.Module]:
        """One recurrent reward network (its target is a copy)."""
        return {"q": RecurrentQNetwork(obs_size, N_ACTIONS, self.cfg.recurrent_hidden)}

    def begin_episode(self) -> None:
        """Forget the previous episode: the hidden state restarts from zero."""
        self.hidden = None

    def new_replay(self, obs_size: int) -> SequenceReplay:  # type: ignore[override]
        """A :class:`SequenceReplay` of ``buffer_size`` transitions and the configured sequences."""
        return SequenceReplay(self.cfg.buffer_size, obs_size, self.cfg.burn_in, self.cfg.sequence_length)

    # -- acting ----------------------------------------------------------------------------------
    def step_values(self, obs: np.ndarray) -> np.ndarray:
        """Q_θ (A,) float64 of the next decision's observation; advances the hidden state by it."""
        x = torch.as_tensor(np.asarray(obs, dtype=np.float32)).reshape(1, 1, -1)
        with torch.no_grad():
            q, self.hidden = self.q_net(x, self.hidden)
        return q[0, 0].double().numpy()

    def greedy(self, obs: np.ndarray, mask: np.ndarray | None = None) -> int:
        """The greedy action for the episode's next observation among the mask's actions (shaped Q, eqs. 13–14:
        its argmax over the safe actions is Q-masking's); ties go to the lowest index."""
        mask = sanitize_mask(mask, self.n_actions)
        q = self.step_values(obs)
        shaped = np.where(mask, q, q.min() - self.cfg.shaping_margin)
        return int(np.argmax(np.where(mask, shaped, -np.inf)))

    def act(self, obs: np.ndarray, mask: np.ndarray | None, eps: float) -> int:
        """ε-greedy among the mask's actions; every observation enters the hidden state, explored or not."""
        mask = sanitize_mask(mask, self.n_actions)
        action = self.greedy(obs, mask)
        if self.rng.random() < eps:
            choices = np.flatnonzero(mask)
            return int(choices[self.rng.integers(len(choices))])
        return action

    def greedy_batch(self, obs: np.ndarray, masks: np.ndarray | None = None) -> np.ndarray:
        """Refused: rows of a batch would share one episode's hidden state."""
        raise ValueError(f"{self.method}: acts one decision of one episode at a time (greedy), not on a batch")

    def acting_values(self, obs: np.ndarray, masks: np.ndarray) -> np.ndarray:
        """Refused, as :meth:`greedy_batch`."""
        raise ValueError(f"{self.method}: acts one decision of one episode at a time (greedy), not on a batch")

    def action_values(self, obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Shaped Q (B, T, A) of sequences (B, T, obs_size) from a zero hidden state, masks (B, T, A)."""
        q = self.q_net(obs)[0]
        return shaped_q(q.flatten(0, 1), mask.flatten(0, 1), self.cfg.shaping_margin).view_as(q)

    # -- learning --------------------------------------------------------------------------------
    def td_target(self, batch: SequenceBatch) -> torch.Tensor:  # type: ignore[override]
        """``r + γ·max_{a' safe in s'} Q_target(s', a')·(1 − done)`` at every decision, shape (B, T); the target
        network reads the sequence's first observation, then each decision's ``s'`` (garbage where not valid)."""
        with torch.no_grad():
            seq = torch.cat([batch.obs[:, :1], batch.next_obs], dim=1)
            next_q = self.targets["q"](seq)[0][:, 1:]
            masks = batch.next_masks | ~batch.valid.unsqueeze(-1)  # padding: any finite max, never used
            next_v = masked_max(next_q.flatten(0, 1), masks.flatten(0, 1)).view_as(batch.rewards)
            return batch.rewards + self.cfg.gamma * next_v * (1.0 - batch.dones)

    def loss(self, batch: SequenceBatch) -> torch.Tensor:  # type: ignore[override]
        """:func:`~safelane.agents.dqn.q_shaping_loss` over the sequences' trained decisions."""
        cfg = self.cfg
        q = self.q_net(batch.obs)[0]
        trained = batch.trained
        return q_shaping_loss(
            q[trained],
            batch.actions[trained],
            self.td_target(batch)[trained],
            batch.masks[trained],
            weight=cfg.shaping_weight,
            kind=cfg.loss,
            target=cfg.shaping_target,
            one_sided=cfg.shaping_loss == "hinge",
            margin=cfg.shaping_margin,
        )

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore the networks and the rest (:meth:`DQNAgent.load_state_dict`); the hidden state restarts."""
        super().load_state_dict(state)
        self.hidden = None
