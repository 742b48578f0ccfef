"""Many runs, one learner: S DQN runs trained as one batched computation, each exactly as alone.

A 26 → 100 → 100 → 5 network updated on 64 transitions is nearly all per-call overhead (Python, autograd,
the optimiser's bookkeeping); S runs trained one by one pay it S times. :class:`BatchedLearner` keeps the
networks of S runs stacked with a leading run dimension and does one forward, one backward and one fused
Adam call for all of them. Every run keeps its own method, replay buffer, random generator, ε schedule,
target network, Lagrange multiplier and Q-shaping settings — the semantics of :mod:`safelane.agents.dqn`.

Bit for bit the same numbers as :class:`safelane.agents.dqn.DQNAgent` (``tests/test_batched_training.py``):

* forward: ``torch.baddbmm`` runs one BLAS gemm per run, the call ``nn.Linear``'s ``addmm`` makes;
* backward: :class:`_StackedLinear` computes the weight gradient as ``gradᵀ·x`` per run — the orientation
  autograd uses for ``nn.Linear`` (``torch.bmm``'s own backward computes ``xᵀ·grad`` and differs in the
  last bit for the 5-output layer);
* gradient clipping: per-run norms of each parameter, then of their stack, as ``clip_grad_norm_``;
* Adam: ``torch._fused_adam_`` on per-run views — the kernel ``torch.optim.Adam(fused=True)`` runs, on
  tensors of the same sizes (one call over the stacked tensors is *not* the same: its vectorised body and
  scalar tail split the elements differently, and they round differently);
* acting: the numba forward of :mod:`safelane.agents.inference`, row by row in float64.

Networks of different shapes (constrained's reward and cost heads) sit in separate groups, each one batched
computation; all groups share one backward. Per-run agents (:attr:`BatchedLearner.agents`) give each run
its initial weights (the same seeds as alone), its generator, and its checkpoint in
:meth:`DQNAgent.state_dict`'s format: a run trained here loads, evaluates and resumes as one trained alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numba
import numpy as np
import torch
import torch.nn.functional as F

from safelane.agents.dqn import AgentConfig, ConstrainedAgent, DQNAgent, ReplayBuffer, make_agent
from safelane.agents.inference import dense_layer
from safelane.core.errors import ConfigError
from safelane.core.spaces import N_ACTIONS, OBS_SIZE

PLAIN_METHODS = ("dqn", "qmask", "robust")
"""Methods with one reward network of 5 outputs: they share a group."""


class _StackedLinear(torch.autograd.Function):
    """``y[s] = x[s]·W[s]ᵀ + b[s]`` for every run ``s``, with ``nn.Linear``'s gradients bit for bit."""

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(x, weight)
        return torch.baddbmm(bias.unsqueeze(1), x, weight.transpose(1, 2))

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor]:
        x, weight = ctx.saved_tensors
        grad_x = torch.bmm(grad, weight) if ctx.needs_input_grad[0] else None
        # gradᵀ·x, not xᵀ·grad transposed: the orientation of nn.Linear's weight gradient (the same sums).
        return grad_x, torch.bmm(grad.transpose(1, 2), x), grad.sum(dim=1)


def stacked_forward(params: Sequence[torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """Q-values (S, B, A) of S stacked 3-layer ELU networks ``params`` = (W1, b1, W2, b2, W3, b3), each
    with a leading run dimension, for observations ``x`` (S, B, obs_size)."""
    h = x
    for i in range(3):
        h = _StackedLinear.apply(h, params[2 * i], params[2 * i + 1])
        if i < 2:
            h = F.elu(h)
    return h


@numba.njit(cache=True)
def _forward_runs(obs, w1, b1, w2, b2, w3, b3, nets):  # pragma: no cover - compiled
    """Q-values (R, A) float64: row ``r`` through network ``nets[r]`` of the stacked float64 layers, each
    row alone in :func:`safelane.agents.inference.forward`'s order (the same bits as a run acting alone)."""
    x = np.empty(w1.shape[1])
    h1 = np.empty(w1.shape[2])
    h2 = np.empty(w2.shape[2])
    q = np.empty(w3.shape[2])
    out = np.empty((obs.shape[0], w3.shape[2]))
    for r in range(obs.shape[0]):
        s = nets[r]
        for i in range(x.shape[0]):
            x[i] = np.float64(obs[r, i])
        dense_layer(x, w1[s], b1[s], h1, True)
        dense_layer(h1, w2[s], b2[s], h2, True)
        dense_layer(h2, w3[s], b3[s], q, False)
        out[r, :] = q
    return out


def _ell(mse: torch.Tensor | bool, prediction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-element mse or huber loss; ``mse``: one bool for all runs, or a (S, 1[, 1]) bool tensor."""
    if isinstance(mse, bool):
        fn = F.mse_loss if mse else F.smooth_l1_loss
        return fn(prediction, target, reduction="none")
    return torch.where(
        mse,
        F.mse_loss(prediction, target, reduction="none"),
        F.smooth_l1_loss(prediction, target, reduction="none"),
    )


def _uniform_or_tensor(values: list[bool], shape: tuple[int, ...]) -> torch.Tensor | bool:
    if all(values) or not any(values):
        return bool(values[0])
    return torch.tensor(values).reshape(shape)


class _Group:
    """The runs whose networks share one layout, stacked: parameters, targets, Adam state, acting copies."""

    def __init__(
        self, learner: BatchedLearner, runs: list[int], source: tuple[_Group, list[int]] | None = None
    ) -> None:
        """The group of ``runs``: their tensors from their agents, or (``source``) the rows ``keep`` of a
        group they already form part of (runs leaving a batch: no copy through the agents)."""
        self.learner = learner
        agents = [learner.agents[k] for k in runs]
        self.names = tuple(agents[0].networks)
        self.constrained = isinstance(agents[0], ConstrainedAgent)
        self.runs = runs
        if source is not None:
            old, keep = source
            idx = torch.tensor(keep, dtype=torch.int64)
            with torch.no_grad():
                self.params = [p.detach()[idx].clone().requires_grad_() for p in old.params]
                self.targets = [t[idx].clone() for t in old.targets]
                self.exp_avg = [t[idx].clone() for t in old.exp_avg]
                self.exp_avg_sq = [t[idx].clone() for t in old.exp_avg_sq]
            self.steps = [old.steps[j] for j in keep]
        else:
            with torch.no_grad():
                self.params = [
                    torch.stack([list(a.networks[n].parameters())[i].detach() for a in agents]).clone().requires_grad_()
                    for n in self.names
                    for i in range(6)
                ]
                self.targets = [
                    torch.stack([list(a.targets[n].parameters())[i].detach() for a in agents]).clone()
                    for n in self.names
                    for i in range(6)
                ]
            self.exp_avg = [torch.zeros_like(p) for p in self.params]
            self.exp_avg_sq = [torch.zeros_like(p) for p in self.params]
            self.steps = [torch.zeros((), dtype=torch.float32) for _ in runs]
            for j, a in enumerate(agents):  # a resumed agent's Adam state
                self._load_adam(j, a)
        self._refresh_views()
        cfgs = [a.cfg for a in agents]
        n = len(runs)
        self.gamma = torch.tensor([c.gamma for c in cfgs], dtype=torch.float32).reshape(n, 1)
        self.mse = _uniform_or_tensor([c.loss == "mse" for c in cfgs], (n, 1))
        self.mse3 = self.mse if isinstance(self.mse, bool) else self.mse.reshape(n, 1, 1)
        clips = [c.grad_clip for c in cfgs]
        self.clip = torch.tensor([c if c is not None else 1.0 for c in clips], dtype=torch.float32)
        self.clipped = torch.tensor([c is not None for c in clips])
        self.any_clip = any(c is not None for c in clips)
        self.uniform_clip = clips[0] if all(c == clips[0] for c in clips) else None
        self.lr = [c.lr for c in cfgs]
        methods = [a.method for a in agents]
        self.use_mask = torch.tensor([a.uses_mask for a in agents]).reshape(n, 1, 1)
        self.all_mask = all(a.uses_mask for a in agents)
        self.no_mask = not any(a.uses_mask for a in agents)
        robust = [m == "robust" for m in methods]
        self.robust = torch.tensor(robust)
        self.any_robust, self.all_robust = any(robust), all(robust)
        self.shaping_weight = torch.tensor([c.shaping_weight for c in cfgs], dtype=torch.float32)
        self.shaping_margin = torch.tensor([c.shaping_margin for c in cfgs], dtype=torch.float32).reshape(n, 1, 1)
        kinds = [c.shaping_target for c in cfgs]
        self.shaping_kinds = {k: torch.tensor([x == k for x in kinds]).reshape(n, 1, 1) for k in sorted(set(kinds))}
        self.hinge = _uniform_or_tensor([c.shaping_loss == "hinge" for c in cfgs], (n, 1, 1))
        self.acting_dirty = True
        self._acting: list[np.ndarray] = []

    # -- Adam state and views --------------------------------------------------------------------
    def _load_adam(self, j: int, agent: DQNAgent) -> None:
        params = [p for n in self.names for p in agent.networks[n].parameters()]
        states = [agent.optimizer.state.get(p) for p in params]
        if not states[0]:
            return
        with torch.no_grad():
            for i, st in enumerate(states):
                self.exp_avg[i][j].copy_(st["exp_avg"])
                self.exp_avg_sq[i][j].copy_(st["exp_avg_sq"])
        self.steps[j].fill_(float(states[0]["step"]))

    def _refresh_views(self) -> None:
        n = len(self.runs)
        per = [[t.unbind(0) for t in tensors] for tensors in (self.params, self.exp_avg, self.exp_avg_sq)]
        # per[kind][param][run] -> by run: [(param views), (exp_avg views), (exp_avg_sq views)]
        self.run_views = [tuple([v[j] for v in kind] for kind in per) for j in range(n)]

    def export(self, j: int, agent: DQNAgent) -> None:
        """Write run ``j``'s networks, targets and Adam state into ``agent`` (its per-run form)."""
        with torch.no_grad():
            k = 0
            params = []
            for n in self.names:
                for p, tp in zip(agent.networks[n].parameters(), agent.targets[n].parameters(), strict=True):
                    p.copy_(self.params[k][j])
                    tp.copy_(self.targets[k][j])
                    params.append(p)
                    k += 1
            if float(self.steps[j]) > 0:
                for i, p in enumerate(params):
                    agent.optimizer.state[p] = {
                        "step": self.steps[j].clone(),
                        "exp_avg": self.exp_avg[i][j].clone(),
                        "exp_avg_sq": self.exp_avg_sq[i][j].clone(),
                    }
        for acting in agent.acting.values():
            acting.invalidate()

    # -- acting ------------------------------------------------------------------------------------
    def q_values(self, local: np.ndarray, obs: np.ndarray) -> list[np.ndarray]:
        """float64 Q-values (R, A) per network name for rows ``obs`` of local runs ``local``."""
        if self.acting_dirty:
            self._acting = [
                np.ascontiguousarray(
                    t.detach().numpy().transpose(0, 2, 1) if t.dim() == 3 else t.detach().numpy(), dtype=np.float64
                )
                for t in self.params
            ]
            self.acting_dirty = False
        x = np.ascontiguousarray(obs, dtype=np.float32)
        return [_forward_runs(x, *self._acting[6 * i : 6 * i + 6], local) for i in range(len(self.names))]

    # -- learning ----------------------------------------------------------------------------------
    def loss(self, batch: list[torch.Tensor], lam: torch.Tensor | None) -> torch.Tensor:
        """Per-run losses (S,) of the group's methods on a stacked batch (each run's own loss)."""
        obs, actions, rewards, costs, next_obs, dones, masks, next_masks = batch
        p, t = self.params, self.targets
        not_done = 1.0 - dones
        a = actions.unsqueeze(2)
        if self.constrained:
            with torch.no_grad():
                if len(self.names) == 1:
                    both = stacked_forward(t, next_obs)
                    next_r, next_c = both[..., :N_ACTIONS], both[..., N_ACTIONS:]
                else:
                    next_r, next_c = stacked_forward(t[:6], next_obs), stacked_forward(t[6:], next_obs)
                best = (next_r - lam * next_c).argmax(dim=2, keepdim=True)
                y_r = rewards + self.gamma * next_r.gather(2, best).squeeze(2) * not_done
                y_c = costs + self.gamma * next_c.gather(2, best).squeeze(2) * not_done
            if len(self.names) == 1:
                both = stacked_forward(p, obs)
                q_r, q_c = both[..., :N_ACTIONS], both[..., N_ACTIONS:]
            else:
                q_r, q_c = stacked_forward(p[:6], obs), stacked_forward(p[6:], obs)
            taken_r, taken_c = q_r.gather(2, a).squeeze(2), q_c.gather(2, a).squeeze(2)
            return _ell(self.mse, taken_r, y_r).mean(dim=1) + _ell(self.mse, taken_c, y_c).mean(dim=1)
        with torch.no_grad():
            next_q = stacked_forward(t, next_obs)
            if self.no_mask:
                next_v = next_q.max(dim=2).values
            else:
                allowed = next_masks if self.all_mask else next_masks | ~self.use_mask
                next_v = next_q.masked_fill(~allowed, float("-inf")).max(dim=2).values
            y = rewards + self.gamma * next_v * not_done
        q = stacked_forward(p, obs)
        td = _ell(self.mse, q.gather(2, a).squeeze(2), y).mean(dim=1)
        if not self.any_robust:
            return td
        unsafe = ~masks
        refs = {
            "all_min": lambda: q.min(dim=2, keepdim=True).values,
            "safe_min": lambda: q.masked_fill(~masks, float("inf")).min(dim=2, keepdim=True).values,
            "taken_action": lambda: q.gather(2, a),
        }
        ref = None
        for kind, chosen in self.shaping_kinds.items():
            value = refs[kind]()
            ref = value if ref is None else torch.where(chosen, value, ref)
        goal = (ref.detach() - self.shaping_margin).expand_as(q)

        def regression() -> torch.Tensor:
            return _ell(self.mse3, q, goal) * unsafe

        def hinge() -> torch.Tensor:
            excess = torch.clamp(q - goal, min=0.0)
            return _ell(self.mse3, excess, torch.zeros_like(excess)) * unsafe

        if isinstance(self.hinge, bool):
            per_pair = hinge() if self.hinge else regression()
        else:
            per_pair = torch.where(self.hinge, hinge(), regression())
        shaping = per_pair.sum(dim=(1, 2)) / unsafe.sum(dim=(1, 2)).clamp(min=1)
        shaped = td + self.shaping_weight * shaping
        return shaped if self.all_robust else torch.where(self.robust, shaped, td)

    def step(self, local: np.ndarray) -> None:
        """Clip the gradients of local runs ``local`` and take one Adam step for each (their own ``lr``)."""
        grads = [p.grad for p in self.params]
        with torch.no_grad():
            if self.any_clip:
                norms = torch.stack([torch.linalg.vector_norm(g.reshape(g.shape[0], -1), dim=1) for g in grads], dim=1)
                total = torch.linalg.vector_norm(norms, dim=1)
                if self.uniform_clip is not None:
                    coef = self.uniform_clip / (total + 1e-6)  # clip_grad_norm_'s expression, run by run
                else:  # float / tensor is reciprocal × float in torch: the same bits per run
                    coef = (total + 1e-6).reciprocal() * self.clip
                    coef = torch.where(self.clipped, coef, torch.ones_like(coef))
                coef = torch.clamp(coef, max=1.0)
                for g in grads:
                    g.mul_(coef.reshape(-1, *([1] * (g.dim() - 1))))
            grad_views = [g.unbind(0) for g in grads]
            by_lr: dict[float, list[int]] = {}
            for j in local.tolist():
                by_lr.setdefault(self.lr[j], []).append(j)
            for lr, js in by_lr.items():
                ps, gs, ms, vs, ss = [], [], [], [], []
                for j in js:
                    self.steps[j].add_(1)
                    pv, mv, vv = self.run_views[j]
                    ps.extend(pv)
                    ms.extend(mv)
                    vs.extend(vv)
                    gs.extend(g[j] for g in grad_views)
                    ss.extend([self.steps[j]] * len(pv))
                torch._fused_adam_(
                    ps, gs, ms, vs, [], ss, amsgrad=False, lr=lr, beta1=0.9, beta2=0.999, weight_decay=0.0,
                    eps=1e-8, maximize=False,
                )  # fmt: skip
        self.acting_dirty = True

    def sync_target(self, local: list[int], taus: list[float]) -> None:
        """Target ← online for local runs ``local`` (``tau`` = 1), else the Polyak average, run by run."""
        with torch.no_grad():
            for j, tau in zip(local, taus, strict=True):
                for tp, p in zip(self.targets, self.params, strict=True):
                    if tau >= 1.0:
                        tp[j].copy_(p[j])
                    else:
                        tp[j].mul_(1.0 - tau).add_(p[j], alpha=tau)


class BatchedLearner:
    """S runs (``cfgs[k]``, ``seeds[k]``) trained as one computation; run ``k`` behaves as
    ``make_agent(cfgs[k], seeds[k])`` with its own :class:`ReplayBuffer`, bit for bit.

    All runs must share ``batch_size`` (the stacked mini-batch); every other setting is per run. Runs are
    addressed by their index ``k`` in ``cfgs``; arrays of run indices select which runs act or learn.
    """

    def __init__(self, cfgs: Sequence[AgentConfig], seeds: Sequence[int], obs_size: int = OBS_SIZE) -> None:
        if len(cfgs) != len(seeds) or not cfgs:
            raise ConfigError(f"runs: one seed per agent config and at least one run (got {len(cfgs)}, {len(seeds)})")
        sizes = sorted({c.batch_size for c in cfgs})
        if len(sizes) > 1:
            raise ConfigError(f"agent.batch_size: runs trained together share it (got {sizes})")
        self.batch_size = sizes[0]
        self.n_runs = len(cfgs)
        self.agents: list[DQNAgent] = [make_agent(c, s, obs_size) for c, s in zip(cfgs, seeds, strict=True)]
        """Each run's agent: its generator (exploration and replay), λ, and its checkpoint form."""
        capacity = max(c.buffer_size for c in cfgs)
        self.capacity = np.array([c.buffer_size for c in cfgs], dtype=np.int64)
        n = self.n_runs
        self.obs = np.zeros((n, capacity, obs_size), dtype=np.float32)
        self.actions = np.zeros((n, capacity), dtype=np.int64)
        self.rewards = np.zeros((n, capacity), dtype=np.float32)
        self.costs = np.zeros((n, capacity), dtype=np.float32)
        self.next_obs = np.zeros((n, capacity, obs_size), dtype=np.float32)
        self.dones = np.zeros((n, capacity), dtype=np.float32)
        self.masks = np.ones((n, capacity, N_ACTIONS), dtype=bool)
        self.next_masks = np.ones((n, capacity, N_ACTIONS), dtype=bool)
        self.pos = np.zeros(n, dtype=np.int64)
        self.size = np.zeros(n, dtype=np.int64)
        self.uses_mask = np.array([a.uses_mask for a in self.agents])
        self.shaping_margin = np.array([c.shaping_margin for c in cfgs])
        self.method = [a.method for a in self.agents]
        self.active = np.ones(n, dtype=bool)
        self._build_groups()

    # -- groups ------------------------------------------------------------------------------------
    def _layout(self, k: int) -> tuple:
        agent = self.agents[k]
        shapes = tuple((name, net.net[-1].out_features) for name, net in agent.networks.items())
        return (isinstance(agent, ConstrainedAgent), *shapes)

    def _build_groups(self) -> None:
        """Group the active runs by network layout, their tensors read from their agents."""
        layouts: dict[tuple, list[int]] = {}
        for k in np.flatnonzero(self.active).tolist():
            layouts.setdefault(self._layout(k), []).append(k)
        self._set_groups([_Group(self, runs) for runs in layouts.values()])

    def _set_groups(self, groups: list[_Group]) -> None:
        self.groups = groups
        self.where = {k: (g, j) for g in self.groups for j, k in enumerate(g.runs)}

    def export(self, k: int) -> DQNAgent:
        """Run ``k``'s agent with its current networks, targets and Adam state (its per-run form)."""
        if k in self.where:
            group, j = self.where[k]
            group.export(j, self.agents[k])
        return self.agents[k]

    def retire(self, runs: Sequence[int]) -> None:
        """Stop runs ``runs`` (finished): their agents keep their final state, the others continue."""
        for k in runs:
            self.export(k)
            self.active[k] = False
        groups = []
        for group in self.groups:
            keep = [j for j, k in enumerate(group.runs) if self.active[k]]
            if len(keep) == len(group.runs):
                groups.append(group)
            elif keep:
                groups.append(_Group(self, [group.runs[j] for j in keep], source=(group, keep)))
        self._set_groups(groups)

    def load_runs(self, states: dict[int, tuple[dict[str, Any], dict[str, Any]]]) -> None:
        """Restore runs from per-run checkpoints: ``{k: (agent state, buffer state)}`` in the forms of
        ``DQNAgent.state_dict`` and ``ReplayBuffer.state_dict``; before any act or update (the groups are
        rebuilt from the agents)."""
        for k, (agent_state, buffer_state) in states.items():
            self.agents[k].load_state_dict(agent_state)
            buffer = ReplayBuffer(int(self.capacity[k]), self.obs.shape[2])
            buffer.load_state_dict(buffer_state)
            size = buffer.size
            for name in ReplayBuffer.FIELDS:
                getattr(self, name)[k, :size] = getattr(buffer, name)[:size]
            self.pos[k], self.size[k] = buffer.pos, size
        self._build_groups()

    def buffer_state(self, k: int) -> dict[str, Any]:
        """Run ``k``'s replay buffer in :meth:`ReplayBuffer.state_dict`'s form."""
        size = int(self.size[k])
        state: dict[str, Any] = {
            name: torch.from_numpy(getattr(self, name)[k, :size].copy()) for name in ReplayBuffer.FIELDS
        }
        state.update(pos=int(self.pos[k]), size=size, capacity=int(self.capacity[k]))
        return state

    # -- acting ------------------------------------------------------------------------------------
    def greedy(self, runs: np.ndarray, obs: np.ndarray, masks: np.ndarray) -> np.ndarray:
        """Greedy actions (R,) of runs ``runs`` for observations (R, 26) and sanitised masks (R, 5), each
        as :meth:`DQNAgent.greedy_batch` of that run alone."""
        values = np.zeros((len(runs), N_ACTIONS))
        for group in self.groups:
            rows = np.flatnonzero(np.isin(runs, group.runs))
            if rows.size == 0:
                continue
            local = np.array([self.where[k][1] for k in runs[rows].tolist()], dtype=np.int64)
            q = group.q_values(local, obs[rows])
            if group.constrained:
                q_r, q_c = (q[0][:, :N_ACTIONS], q[0][:, N_ACTIONS:]) if len(q) == 1 else (q[0], q[1])
                lam = np.array([[self.agents[k].lam] for k in runs[rows].tolist()])
                values[rows] = q_r - lam * q_c
            else:
                v = q[0]
                robust = np.array([self.method[k] == "robust" for k in runs[rows].tolist()])
                if robust.any():
                    m = masks[rows]
                    margin = self.shaping_margin[runs[rows]][:, None]
                    shaped = np.where(m, v, v.min(axis=1, keepdims=True) - margin)
                    v = np.where(robust[:, None], shaped, v)
                values[rows] = v
        allowed = np.where(self.uses_mask[runs][:, None], masks, True)
        return np.argmax(np.where(allowed, values, -np.inf), axis=1)

    def act(self, runs: np.ndarray, obs: np.ndarray, masks: np.ndarray, eps: np.ndarray) -> np.ndarray:
        """ε-greedy actions (R,) of runs ``runs`` (each draws from its own generator as
        :meth:`DQNAgent.act`); ``masks`` sanitised (:func:`safelane.agents.dqn.sanitize_mask`)."""
        actions = np.zeros(len(runs), dtype=np.int64)
        greedy_rows = []
        for r, k in enumerate(runs.tolist()):
            rng = self.agents[k].rng
            if rng.random() < eps[r]:
                choices = np.flatnonzero(masks[r]) if self.uses_mask[k] else np.arange(N_ACTIONS)
                actions[r] = choices[rng.integers(len(choices))]
            else:
                greedy_rows.append(r)
        if greedy_rows:
            rows = np.array(greedy_rows, dtype=np.int64)
            actions[rows] = self.greedy(runs[rows], obs[rows], masks[rows])
        return actions

    # -- replay and learning -----------------------------------------------------------------------
    def store(
        self,
        runs: np.ndarray,
        obs: np.ndarray,
        actions: np.ndarray,
        rewards: np.ndarray,
        costs: np.ndarray,
        next_obs: np.ndarray,
        terminated: np.ndarray,
        masks: np.ndarray,
        next_masks: np.ndarray,
    ) -> None:
        """Store one transition per run in ``runs`` (as :meth:`ReplayBuffer.add` in each run's buffer)."""
        i = self.pos[runs]
        self.obs[runs, i] = obs
        self.actions[runs, i] = actions
        self.rewards[runs, i] = rewards
        self.costs[runs, i] = costs
        self.next_obs[runs, i] = next_obs
        self.dones[runs, i] = terminated.astype(np.float32)
        self.masks[runs, i] = masks
        self.next_masks[runs, i] = next_masks
        self.pos[runs] = (i + 1) % self.capacity[runs]
        self.size[runs] = np.minimum(self.size[runs] + 1, self.capacity[runs])

    def update(self, runs: np.ndarray) -> np.ndarray:
        """One gradient step for each run in ``runs`` on a mini-batch from its own buffer (drawn with its
        own generator); returns their loss values (R,) float."""
        losses = np.zeros(len(runs))
        fields = ("obs", "actions", "rewards", "costs", "next_obs", "dones", "masks", "next_masks")
        total = None
        plan = []
        for group in self.groups:
            member = [r for r, k in enumerate(runs.tolist()) if k in self.where and self.where[k][0] is group]
            if not member:
                continue
            n = len(group.runs)
            idx = np.zeros((n, self.batch_size), dtype=np.int64)
            local = np.array([self.where[int(runs[r])][1] for r in member], dtype=np.int64)
            for r, j in zip(member, local.tolist(), strict=True):
                k = int(runs[r])
                idx[j] = self.agents[k].rng.integers(0, int(self.size[k]), size=self.batch_size)
            gids = np.array(group.runs)[:, None]
            batch = [torch.from_numpy(getattr(self, f)[gids, idx]) for f in fields]
            lam = None
            if group.constrained:
                lam = torch.tensor([self.agents[k].lam for k in group.runs], dtype=torch.float32).reshape(n, 1, 1)
            per_run = group.loss(batch, lam)
            chosen = per_run if len(local) == n else per_run[torch.from_numpy(local)]
            losses[member] = chosen.detach().numpy()
            total = chosen.sum() if total is None else total + chosen.sum()
            plan.append((group, local))
        if total is None:
            return losses
        for group, _ in plan:
            for p in group.params:
                p.grad = None
        total.backward()
        for group, local in plan:
            group.step(local)
        return losses

    def sync_target(self, runs: np.ndarray) -> None:
        """Move the target networks of runs ``runs`` toward their online ones (each run's ``tau``)."""
        for group in self.groups:
            local = [self.where[k][1] for k in runs.tolist() if k in self.where and self.where[k][0] is group]
            if local:
                group.sync_target(local, [self.agents[group.runs[j]].cfg.tau for j in local])

    def end_episode(self, k: int, episode_cost: float) -> None:
        """Run ``k``'s per-episode hook (constrained's dual ascent of λ)."""
        self.agents[k].end_episode(episode_cost)
