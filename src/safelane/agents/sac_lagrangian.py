"""A Lagrangian SAC on Stable-Baselines3: a cost critic, and a multiplier λ raised while episodes cost too much.

The constrained problem: maximise the return subject to an expected episode cost ≤ ``cost_budget`` (cost 1 per
decision that ends in a crash or off the road, ``info["cost"]``). Its Lagrangian relaxation, as the paper's
constrained Q-learning does it for the DQN (eq. 7, :class:`safelane.agents.dqn.ConstrainedAgent`):

* the **cost critic** ``Q_c(s, a)`` learns the discounted cost ahead, by the TD target
  ``c + γ·(1 − done)·max_j Q_c,target_j(s', a' ~ π)`` — twin heads like the reward critic, the max of the two
  (pessimistic for a cost, as the min is for a reward);
* the **actor** minimises ``α·log π(a|s) − min_j Q_j(s, a) + λ·max_j Q_c,j(s, a)``;
* **λ** follows dual ascent every ``lambda_update_interval`` decisions, on the mean cost of the episodes finished
  since the last update: ``λ ← max(0, λ + lambda_lr·(mean episode cost − cost_budget))``. Episodes that end during
  SAC's warm-up (``learning_starts``: uniform random actions, not the policy's) do not count. An update per
  episode (``lambda_update_interval = 1``, the constrained DQN's rule) lets the hundreds of one-decision episodes of
  an untrained driver push λ to 60 within 5 000 decisions, after which a constraint met lowers it by
  ``lambda_lr·cost_budget`` an episode: the multiplier never comes back.

Everything else (collection, entropy tuning, target updates, saving) is SB3's SAC. The replay buffers here store
the action the environment executed (``info["executed_action"]``, a shield's projection or replacement, when it
reports one): what the agent learns from under a shield.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch as th
import torch.nn.functional as F
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.utils import polyak_update

COST_KEY = "cost"
"""The ``info`` key of a transition's cost (as Safety-Gymnasium names it)."""


def lowest(heads: tuple[th.Tensor, ...]) -> th.Tensor:
    """The lowest of a twin critic's values, per transition: (batch, 1)."""
    return th.cat(heads, dim=1).min(dim=1, keepdim=True).values


def highest(heads: tuple[th.Tensor, ...]) -> th.Tensor:
    """The highest of a twin critic's values, per transition: (batch, 1)."""
    return th.cat(heads, dim=1).max(dim=1, keepdim=True).values


class ExecutedActionReplayBuffer(ReplayBuffer):
    """SB3's replay buffer, storing ``info["executed_action"]`` (the action a shield executed) in place of the
    agent's proposal wherever the environment reports one: the transition the environment really made."""

    def add(
        self, obs: Any, next_obs: Any, action: np.ndarray, reward: Any, done: Any, infos: list[dict[str, Any]]
    ) -> None:
        executed = [info.get("executed_action") for info in infos]
        if any(a is not None for a in executed):
            action = np.array(action, copy=True).reshape((self.n_envs, self.action_dim))
            for i, a in enumerate(executed):
                if a is not None:
                    action[i] = np.asarray(a, dtype=action.dtype).reshape(-1)
        super().add(obs, next_obs, action, reward, done, infos)


class CostReplayBufferSamples(NamedTuple):
    """SB3's :class:`ReplayBufferSamples` with each transition's cost."""

    observations: th.Tensor
    actions: th.Tensor
    next_observations: th.Tensor
    dones: th.Tensor
    rewards: th.Tensor
    costs: th.Tensor


class CostReplayBuffer(ExecutedActionReplayBuffer):
    """:class:`ExecutedActionReplayBuffer` that also keeps each transition's ``info["cost"]``."""

    def __init__(self, buffer_size: int, *args: Any, **kwargs: Any) -> None:
        super().__init__(buffer_size, *args, **kwargs)
        self.costs = np.zeros((self.buffer_size, self.n_envs), dtype=np.float32)

    def add(
        self, obs: Any, next_obs: Any, action: np.ndarray, reward: Any, done: Any, infos: list[dict[str, Any]]
    ) -> None:
        try:
            self.costs[self.pos] = np.array([float(info[COST_KEY]) for info in infos], dtype=np.float32)
        except KeyError:
            raise KeyError(f"CostReplayBuffer: the environment's info has no '{COST_KEY}'") from None
        super().add(obs, next_obs, action, reward, done, infos)

    def _get_samples(self, batch_inds: np.ndarray, env: Any = None) -> CostReplayBufferSamples:  # type: ignore[override]
        env_indices = np.random.randint(0, high=self.n_envs, size=(len(batch_inds),))  # as SB3 draws them
        data = (
            self._normalize_obs(self.observations[batch_inds, env_indices, :], env),
            self.actions[batch_inds, env_indices, :],
            self._normalize_obs(self.next_observations[batch_inds, env_indices, :], env),
            (self.dones[batch_inds, env_indices] * (1 - self.timeouts[batch_inds, env_indices])).reshape(-1, 1),
            self._normalize_reward(self.rewards[batch_inds, env_indices].reshape(-1, 1), env),
            self.costs[batch_inds, env_indices].reshape(-1, 1),
        )
        return CostReplayBufferSamples(*map(self.to_torch, data))


class SACLagrangian(SAC):
    """SAC with a cost critic and a Lagrange multiplier λ (module docstring). ``cost_budget`` [cost per episode],
    ``lambda_lr`` [λ per update per unit of excess mean episode cost], ``lambda_init`` λ's start,
    ``lambda_update_interval`` [decisions] between λ's updates; the rest is SAC's."""

    def __init__(
        self,
        policy: Any,
        env: Any,
        cost_budget: float = 0.05,
        lambda_lr: float = 1.0,
        lambda_init: float = 0.0,
        lambda_update_interval: int = 1000,
        **kwargs: Any,
    ) -> None:
        self.cost_budget, self.lambda_lr, self.lam = float(cost_budget), float(lambda_lr), float(lambda_init)
        self.lambda_update_interval = int(lambda_update_interval)
        self.episode_costs: list[float] = []  # of the episodes in progress, one per environment
        self.finished_costs: list[float] = []  # of the episodes finished since λ's last update
        self.lambda_updated_at = 0  # the decision count at λ's last update
        kwargs.setdefault("replay_buffer_class", CostReplayBuffer)
        super().__init__(policy, env, **kwargs)

    def _setup_model(self) -> None:
        super()._setup_model()
        self.cost_critic = self.policy.make_critic()
        self.cost_critic_target = self.policy.make_critic()
        self.cost_critic_target.load_state_dict(self.cost_critic.state_dict())
        self.cost_critic_target.set_training_mode(False)
        self.cost_critic.optimizer = self.policy.optimizer_class(
            self.cost_critic.parameters(), lr=self.lr_schedule(1), **self.policy.optimizer_kwargs
        )
        self.episode_costs = [0.0] * self.n_envs
        self.lambda_updated_at = max(self.lambda_updated_at, self.learning_starts)

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        return [*state_dicts, "cost_critic", "cost_critic_target", "cost_critic.optimizer"], variables

    # --- the multiplier -------------------------------------------------------------------------------
    def update_lambda(self, mean_episode_cost: float) -> None:
        """One dual-ascent step: λ rises while the mean episode cost is over the budget, falls (to 0) under it."""
        self.lam = max(0.0, self.lam + self.lambda_lr * (float(mean_episode_cost) - self.cost_budget))

    def end_episode(self, episode_cost: float) -> None:
        """Count a finished episode of cost ``episode_cost``; update λ once ``lambda_update_interval`` decisions
        have passed since its last update (episodes of the warm-up do not count)."""
        if self.num_timesteps <= self.learning_starts:
            return
        self.finished_costs.append(float(episode_cost))
        if self.num_timesteps - self.lambda_updated_at >= self.lambda_update_interval:
            self.update_lambda(float(np.mean(self.finished_costs)))
            self.finished_costs, self.lambda_updated_at = [], self.num_timesteps

    def _store_transition(
        self,
        replay_buffer: Any,
        buffer_action: np.ndarray,
        new_obs: Any,
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        for i, info in enumerate(infos):
            self.episode_costs[i] += float(info.get(COST_KEY, 0.0))
            if dones[i]:
                self.end_episode(self.episode_costs[i])
                self.episode_costs[i] = 0.0
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)

    # --- the update: SAC's, with the cost critic and λ·Q_c in the actor's loss -------------------------
    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        self.policy.set_training_mode(True)
        optimizers = [self.actor.optimizer, self.critic.optimizer, self.cost_critic.optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        self._update_learning_rate(optimizers)
        actor_losses, critic_losses, cost_losses, ent_coefs = [], [], [], []

        for gradient_step in range(gradient_steps):
            batch: CostReplayBufferSamples = self.replay_buffer.sample(batch_size)  # type: ignore[union-attr,assignment]
            actions_pi, log_prob = self.actor.action_log_prob(batch.observations)
            log_prob = log_prob.reshape(-1, 1)

            # entropy coefficient α (SAC's automatic tuning, or a constant)
            if self.ent_coef_optimizer is not None and self.log_ent_coef is not None:
                ent_coef = th.exp(self.log_ent_coef.detach())
                ent_coef_loss = -(self.log_ent_coef * (log_prob + self.target_entropy).detach()).mean()
                self.ent_coef_optimizer.zero_grad()
                ent_coef_loss.backward()
                self.ent_coef_optimizer.step()
            else:
                ent_coef = self.ent_coef_tensor
            ent_coefs.append(ent_coef.item())

            # TD targets: reward with SAC's min of twin targets and entropy bonus; cost with the max of twin targets
            with th.no_grad():
                next_actions, next_log_prob = self.actor.action_log_prob(batch.next_observations)
                next_q = lowest(self.critic_target(batch.next_observations, next_actions))
                next_q = next_q - ent_coef * next_log_prob.reshape(-1, 1)
                target_q = batch.rewards + (1 - batch.dones) * self.gamma * next_q
                next_qc = highest(self.cost_critic_target(batch.next_observations, next_actions))
                target_qc = batch.costs + (1 - batch.dones) * self.gamma * next_qc

            critic_loss = 0.5 * sum(F.mse_loss(q, target_q) for q in self.critic(batch.observations, batch.actions))
            self.critic.optimizer.zero_grad()
            critic_loss.backward()  # type: ignore[union-attr]
            self.critic.optimizer.step()
            critic_losses.append(critic_loss.item())

            current_qc = self.cost_critic(batch.observations, batch.actions)
            cost_loss = 0.5 * sum(F.mse_loss(qc, target_qc) for qc in current_qc)
            self.cost_critic.optimizer.zero_grad()
            cost_loss.backward()  # type: ignore[union-attr]
            self.cost_critic.optimizer.step()
            cost_losses.append(cost_loss.item())

            # actor: SAC's loss plus λ times the (pessimistic) cost value of its action
            q_pi = lowest(self.critic(batch.observations, actions_pi))
            qc_pi = highest(self.cost_critic(batch.observations, actions_pi))
            actor_loss = (ent_coef * log_prob - q_pi + self.lam * qc_pi).mean()
            self.actor.optimizer.zero_grad()
            actor_loss.backward()
            self.actor.optimizer.step()
            actor_losses.append(actor_loss.item())

            if gradient_step % self.target_update_interval == 0:
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                polyak_update(self.cost_critic.parameters(), self.cost_critic_target.parameters(), self.tau)
                polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)

        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/ent_coef", np.mean(ent_coefs))
        self.logger.record("train/actor_loss", np.mean(actor_losses))
        self.logger.record("train/critic_loss", np.mean(critic_losses))
        self.logger.record("train/cost_critic_loss", np.mean(cost_losses))
        self.logger.record("train/lambda", self.lam)
