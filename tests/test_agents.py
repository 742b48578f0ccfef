"""The DQN core and the four methods, on hand-worked numbers (no simulator needed)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from safelane.agents.dqn import (
    AGENT_CLASSES,
    AGENT_PRESETS,
    METHODS,
    RECURRENT_METHODS,
    Batch,
    ConstrainedAgent,
    DQNAgent,
    QMaskAgent,
    QNetwork,
    ReplayBuffer,
    RobustAgent,
    linear_epsilon,
    load_agent_config,
    make_agent,
    parse_methods,
    q_shaping_loss,
    sanitize_mask,
    shaped_q,
    shaping_target,
)
from safelane.agents.registry import agent_class
from safelane.config import ConfigError

T, F_ = True, False


@pytest.fixture(autouse=True)
def _one_torch_thread() -> Iterator[None]:
    """Training runs torch single-threaded; under load, 2 intra-op threads make tiny updates ~40x slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def constant_net(net: nn.Module, values: list[float]) -> None:
    """Make a QNetwork output ``values`` for every input: last layer weights 0, bias = values."""
    last = net.net[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.tensor(values))


def agent_with_constant_q(method: str, values: list[float], **cfg: object) -> DQNAgent:
    agent = make_agent(
        load_agent_config("tuned", method, {"grad_clip": None, "loss": "mse", "shaping_margin": 1.0, **cfg}), seed=0
    )
    constant_net(agent.q_net, values)
    agent.sync_target()
    return agent


def batch_of(n: int, masks: list[list[bool]], next_masks: list[list[bool]], **fields: list) -> Batch:
    def t(name: str, default: float, dtype: torch.dtype) -> torch.Tensor:
        return torch.tensor(fields.get(name, [default] * n), dtype=dtype)

    return Batch(
        obs=torch.zeros(n, 26),
        actions=t("actions", 0, torch.int64),
        rewards=t("rewards", 0.0, torch.float32),
        costs=t("costs", 0.0, torch.float32),
        next_obs=torch.zeros(n, 26),
        dones=t("dones", 0.0, torch.float32),
        masks=torch.tensor(masks),
        next_masks=torch.tensor(next_masks),
    )


# --- network, buffer, schedule -------------------------------------------------------------------
def test_parse_methods() -> None:
    assert parse_methods("all") == METHODS
    assert parse_methods("robust, qmask,robust") == ("robust", "qmask")
    with pytest.raises(ConfigError, match="--methods: got 'dqn,'; allowed: dqn, constrained, qmask, robust"):
        parse_methods("dqn,")


def test_q_network_is_the_papers_table_3() -> None:
    net = QNetwork()
    linears = [m for m in net.modules() if isinstance(m, nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(26, 100), (100, 100), (100, 5)]
    assert sum(isinstance(m, nn.ELU) for m in net.modules()) == 2
    assert net(torch.zeros(7, 26)).shape == (7, 5)


def test_replay_buffer_is_circular_and_samples_typed_batches() -> None:
    buf = ReplayBuffer(3)
    for i in range(5):
        obs = np.full(26, i, dtype=np.float32)
        mask = np.array([i % 2 == 0] * 5)
        buf.add(obs, i % 5, float(i), 1.0, obs + 1, i == 4, mask, ~mask)
    assert len(buf) == 3 and buf.pos == 2
    assert sorted(buf.rewards.tolist()) == [2.0, 3.0, 4.0]  # the two oldest were overwritten
    batch = buf.sample(10, np.random.default_rng(0))
    assert batch.obs.shape == (10, 26) and batch.obs.dtype == torch.float32
    assert batch.actions.dtype == torch.int64 and batch.masks.dtype == torch.bool
    assert torch.equal(batch.next_obs, batch.obs + 1)
    assert torch.equal(batch.dones, (batch.rewards == 4.0).float())  # only the last was terminal
    copy = ReplayBuffer(3)
    copy.load_state_dict(buf.state_dict())
    assert copy.pos == buf.pos and np.array_equal(copy.obs, buf.obs) and np.array_equal(copy.masks, buf.masks)


def test_epsilon_decays_linearly_then_stays() -> None:
    cfg = load_agent_config(
        "tuned", overrides={"eps_start": 1.0, "eps_end": 0.1, "eps_decay_steps": 100, "eps_decay_episodes": None}
    )
    assert linear_epsilon(0, cfg) == 1.0
    assert linear_epsilon(50, cfg) == pytest.approx(0.55)
    assert linear_epsilon(100, cfg) == 0.1 and linear_epsilon(10_000, cfg) == 0.1


# --- configuration -------------------------------------------------------------------------------
def test_paper_preset_is_table_3_literally() -> None:
    cfg = load_agent_config("paper", "dqn")
    assert (cfg.lr, cfg.batch_size, cfg.gamma, cfg.loss) == (0.01, 50, 0.99, "mse")
    for name in AGENT_PRESETS:
        for method in METHODS:
            assert load_agent_config(name, method).method == method


@pytest.mark.parametrize(
    ("overrides", "message"),
    [({"lrr": 1.0}, "agent.lrr: unknown key"), ({"gamma": 1.5}, "agent.gamma"), ({"loss": "l1"}, "agent.loss")],
)
def test_agent_config_errors_are_one_line(overrides: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message) as err:
        load_agent_config("tuned", "dqn", overrides)
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="unknown preset"):
        load_agent_config("nope")


# --- acting --------------------------------------------------------------------------------------
BEST_UNSAFE = [0.0, 1.0, 2.0, 10.0, 3.0]  # action 3 (FASTER) looks best
MASK_NO_3 = np.array([T, T, T, F_, T])


def test_dqn_ignores_the_mask_and_qmask_robust_obey_it() -> None:
    obs = np.zeros(26, dtype=np.float32)
    assert agent_with_constant_q("dqn", BEST_UNSAFE).greedy(obs, MASK_NO_3) == 3
    assert agent_with_constant_q("qmask", BEST_UNSAFE).greedy(obs, MASK_NO_3) == 4
    assert agent_with_constant_q("robust", BEST_UNSAFE).greedy(obs, MASK_NO_3) == 4


@settings(max_examples=30, deadline=None)
@given(
    method=st.sampled_from(["qmask", "robust"]),
    masks=st.lists(st.lists(st.booleans(), min_size=5, max_size=5).filter(any), min_size=1, max_size=20),
    eps=st.sampled_from([0.0, 0.3, 1.0]),
)
def test_masked_actions_are_never_taken(method: str, masks: list[list[bool]], eps: float) -> None:
    agent = make_agent(load_agent_config("tuned", method), seed=1)
    rng = np.random.default_rng(0)
    for m in masks:
        mask = np.array(m)
        for _ in range(5):
            obs = rng.uniform(-1, 1, 26).astype(np.float32)
            assert mask[agent.act(obs, mask, eps)]


def test_exploration_covers_every_safe_action_and_only_those() -> None:
    agent = make_agent(load_agent_config("tuned", "qmask"), seed=0)
    mask = np.array([F_, T, F_, T, T])
    taken = {agent.act(np.zeros(26, np.float32), mask, 1.0) for _ in range(300)}
    assert taken == {1, 3, 4}


# --- Q-shaping (eqs. 13–14) ----------------------------------------------------------------------
def test_shaped_q_puts_unsafe_pairs_below_every_safe_one() -> None:
    q = torch.tensor([[1.0, 3.0, -2.0, 0.5, 4.0]])
    mask = torch.tensor([[T, T, F_, T, F_]])
    assert shaped_q(q, mask).tolist() == [[1.0, 3.0, -3.0, 0.5, -3.0]]  # eq. 14: min over all = -2, minus 1


def test_shaping_targets_hand_computed() -> None:
    q = torch.tensor([[1.0, 3.0, -2.0, 0.5, 4.0]])
    mask = torch.tensor([[T, T, F_, T, F_]])
    taken = torch.tensor([1])
    assert shaping_target(q, mask, taken, "all_min").item() == -3.0  # min all −2, − 1
    assert shaping_target(q, mask, taken, "safe_min").item() == -0.5  # min safe 0.5, − 1
    assert shaping_target(q, mask, taken, "taken_action").item() == 2.0  # Q(s, 1) = 3, − 1


@pytest.mark.parametrize(
    ("target", "unsafe_mean"),
    [
        ("all_min", ((-2 + 3) ** 2 + (4 + 3) ** 2) / 2),  # target −3 → (1 + 49) / 2 = 25
        ("safe_min", ((-2 + 0.5) ** 2 + (4 + 0.5) ** 2) / 2),  # target −0.5 → (2.25 + 20.25) / 2 = 11.25
        ("taken_action", ((-2 - 2) ** 2 + (4 - 2) ** 2) / 2),  # target 3 − 1 = 2 → (16 + 4) / 2 = 10
    ],
)
def test_robust_agent_loss_matches_hand_computation_from_network_outputs(target: str, unsafe_mean: float) -> None:
    values = [1.0, 3.0, -2.0, 0.5, 4.0]  # every state: last layer weights 0, bias = values
    agent = agent_with_constant_q("robust", values, gamma=0.9, shaping_weight=0.5, shaping_target=target)
    assert isinstance(agent, RobustAgent)
    batch = batch_of(
        2,
        masks=[[T, T, F_, T, F_], [T, T, T, T, T]],
        next_masks=[[F_, T, T, F_, T], [T, T, T, T, T]],
        actions=[1, 3],
        rewards=[1.0, -10.0],
        dones=[0.0, 1.0],
    )
    # y0 = 1 + 0.9 · max over safe next actions {3, −2, 4} = 4.6; y1 = −10 (terminal, no bootstrap)
    assert agent.td_target(batch).tolist() == pytest.approx([4.6, -10.0])
    # TD (mse): ((3 − 4.6)² + (0.5 + 10)²) / 2 = (2.56 + 110.25) / 2 = 56.405; row 1 has no unsafe pair
    assert agent.loss(batch).item() == pytest.approx(56.405 + 0.5 * unsafe_mean)


def test_q_shaping_loss_gradient_stops_at_the_target() -> None:
    q = torch.tensor([[1.0, 3.0, -2.0, 0.5, 4.0], [2.0, 2.0, 2.0, 2.0, 2.0]], requires_grad=True)
    mask = torch.tensor([[T, T, F_, T, F_], [T, T, T, T, F_]])
    actions = torch.tensor([1, 0])
    y = torch.tensor([2.5, 1.0])
    # TD: ((3 − 2.5)² + (2 − 1)²) / 2 = 0.625; targets: row 0: 3 − 1 = 2, row 1: 2 − 1 = 1
    # unsafe pairs: (0,2): (−2 − 2)² = 16; (0,4): (4 − 2)² = 4; (1,4): (2 − 1)² = 1 → mean 7
    loss = q_shaping_loss(q, actions, y, mask, weight=0.5, kind="mse", target="taken_action")
    assert loss.item() == pytest.approx(0.625 + 0.5 * 7.0)
    loss.backward()
    assert q.grad is not None
    assert q.grad[0, 0] == 0 and q.grad[0, 3] == 0  # safe, not taken: no gradient
    assert q.grad[0, 1].item() == pytest.approx(2 * 0.5 / 2)  # TD only: the target is detached
    assert q.grad[0, 4].item() == pytest.approx(0.5 * 2 * 2 / 3)  # weight · 2·(q − t) / n_unsafe


def _edge_mask(obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """FASTER unsafe when obs[0] > 0 (observable); LANE_LEFT or LANE_RIGHT unsafe at random, like a road
    edge, which safelane's state does not show."""
    mask = np.ones(5, dtype=bool)
    mask[3] = obs[0] <= 0
    edge = rng.random()
    if edge < 0.25:
        mask[0] = False
    elif edge < 0.5:
        mask[2] = False
    return mask


@pytest.mark.parametrize(("target", "bounded"), [("taken_action", True), ("safe_min", False), ("all_min", False)])
def test_only_the_taken_action_target_keeps_q_bounded(target: str, bounded: bool) -> None:
    """Rewards in [0, 1], γ = 0.9, IDLE taken 90 %: true values ≤ 10. Regressing unsafe pairs to eq. 14's
    minimum (over all or over safe actions) has no fixed point: LANE_LEFT and LANE_RIGHT drag each other
    down through their untrained safe values. The taken action's value is anchored by its TD target."""
    agent = make_agent(
        load_agent_config(
            "tuned", "robust", {"shaping_target": target, "lr": 1e-3, "loss": "huber", "shaping_margin": 1.0}
        ),
        seed=0,
    )
    rng = np.random.default_rng(0)
    buf = ReplayBuffer(2000)
    for _ in range(2000):
        obs, nxt = rng.uniform(-1, 1, (2, 26)).astype(np.float32)
        mask = _edge_mask(obs, rng)
        action = 1 if rng.random() < 0.9 else int(rng.choice(np.flatnonzero(mask)))
        buf.add(obs, action, float(rng.random()), 0.0, nxt, False, mask, _edge_mask(nxt, rng))
    for step in range(1, 501):
        agent.update(buf.sample(64, agent.rng))
        if step % 200 == 0:
            agent.sync_target()
    with torch.no_grad():
        q = agent.q_net(torch.from_numpy(buf.obs))
    assert bool(q.min() > -20) is bounded


def test_robust_regression_lowers_unsafe_values_below_safe_ones() -> None:
    agent = make_agent(load_agent_config("tuned", "robust", {"lr": 1e-2, "loss": "huber", "shaping_margin": 1.0}), 0)
    rng = np.random.default_rng(0)
    obs = torch.from_numpy(rng.uniform(-1, 1, (32, 26)).astype(np.float32))
    mask = torch.tensor([[T, T, T, F_, T]] * 32)
    batch = Batch(
        obs, torch.ones(32, dtype=torch.int64), torch.zeros(32), torch.zeros(32), obs, torch.ones(32), mask, mask
    )
    constant_net(agent.q_net, BEST_UNSAFE)
    for _ in range(300):
        agent.update(batch)
    with torch.no_grad():
        q = agent.q_net(obs)
    # learned by the network itself (not just masked): FASTER now below every safe action
    assert bool((q[:, 3] < q[:, [0, 1, 2, 4]].min(dim=1).values).all())


# --- Q-masking and constrained -------------------------------------------------------------------
def test_qmask_bootstraps_over_safe_actions_only() -> None:
    agent = agent_with_constant_q("qmask", BEST_UNSAFE, gamma=0.5)
    assert isinstance(agent, QMaskAgent)
    batch = batch_of(1, masks=[[T] * 5], next_masks=[[T, T, T, F_, T]], rewards=[1.0])
    assert agent.td_target(batch).item() == pytest.approx(1 + 0.5 * 3.0)  # not 1 + 0.5 · 10
    dqn = agent_with_constant_q("dqn", BEST_UNSAFE, gamma=0.5)
    assert dqn.td_target(batch).item() == pytest.approx(1 + 0.5 * 10.0)


def constant_reward_and_cost(agent: ConstrainedAgent, reward: list[float], cost: list[float]) -> None:
    """Make both of the agent's Q estimates constant, whichever way they are represented."""
    if agent.cfg.cost_network == "shared":
        constant_net(agent.networks["q_cost"], reward + cost)
    else:
        constant_net(agent.networks["q"], reward)
        constant_net(agent.networks["cost"], cost)
    agent.sync_target()


@pytest.mark.parametrize("cost_network", ["separate", "shared"])
def test_constrained_acts_and_bootstraps_on_the_lagrangian(cost_network: str) -> None:
    cfg = load_agent_config("tuned", "constrained", {"gamma": 0.5, "cost_network": cost_network})
    agent = make_agent(cfg, seed=0)
    assert isinstance(agent, ConstrainedAgent)
    constant_reward_and_cost(agent, [1.0, 2.0, 3.0, 0.0, 0.0], [0.0, 0.0, 5.0, 0.0, 0.0])
    obs = np.zeros(26, np.float32)
    agent.lam = 0.0
    assert agent.greedy(obs) == 2
    agent.lam = 1.0  # 3 − 1·5 = −2 < 2
    assert agent.greedy(obs) == 1
    batch = batch_of(1, masks=[[T] * 5], next_masks=[[T] * 5], rewards=[1.0], costs=[1.0])
    y_r, y_c = agent._targets(batch)  # a* = 1: y_r = 1 + 0.5·2, y_c = 1 + 0.5·0
    assert (y_r.item(), y_c.item()) == pytest.approx((2.0, 1.0))


def test_constrained_shared_trunk_is_the_papers_network_with_a_cost_head() -> None:
    shared = make_agent(load_agent_config("tuned", "constrained", {"cost_network": "shared"}), seed=0)
    separate = make_agent(load_agent_config("tuned", "constrained", {"cost_network": "separate"}), seed=0)
    assert list(shared.networks) == ["q_cost"] and sorted(separate.networks) == ["cost", "q"]
    sizes = [tuple(p.shape) for p in shared.networks["q_cost"].parameters()]
    assert sizes == [(100, 26), (100,), (100, 100), (100,), (10, 100), (10,)]
    # Half the parameters of two networks: the trunk is shared, only the last layer doubles.
    n_shared = sum(p.numel() for p in shared.networks["q_cost"].parameters())
    n_separate = sum(p.numel() for net in separate.networks.values() for p in net.parameters())
    assert n_shared == 2700 + 10100 + 1010 and n_separate == 2 * (2700 + 10100 + 505)
    with pytest.raises(ValueError, match="networks"):
        separate.load_state_dict(shared.state_dict())


def test_constrained_lambda_dual_ascent() -> None:
    agent = make_agent(load_agent_config("tuned", "constrained", {"cost_budget": 2.0, "lambda_lr": 0.1}), 0)
    assert isinstance(agent, ConstrainedAgent) and agent.lam == 0.0
    agent.end_episode(7.0)  # over budget by 5 → +0.5
    assert agent.lam == pytest.approx(0.5)
    agent.end_episode(0.0)  # under budget by 2 → −0.2
    assert agent.lam == pytest.approx(0.3)
    agent.end_episode(0.0)
    agent.end_episode(0.0)
    assert agent.lam == 0.0  # never below 0


# --- update and state -----------------------------------------------------------------------------
@pytest.mark.parametrize("method", METHODS)
def test_update_reduces_the_loss_and_state_round_trips(method: str) -> None:
    cfg = load_agent_config("tuned", method, {"lr": 1e-3})
    agent = make_agent(cfg, seed=3)
    rng = np.random.default_rng(3)
    buf = ReplayBuffer(64)
    for _ in range(64):
        mask = rng.random(5) > 0.3
        mask[1] = True
        buf.add(
            rng.uniform(-1, 1, 26).astype(np.float32),
            int(rng.integers(5)),
            float(rng.random()),
            float(rng.random() < 0.2),
            rng.uniform(-1, 1, 26).astype(np.float32),
            bool(rng.random() < 0.1),
            mask,
            mask,
        )
    batch = buf.sample(64, rng)
    first = agent.loss(batch).item()
    for _ in range(50):
        agent.update(batch)
    assert agent.loss(batch).item() < first

    clone = make_agent(cfg, seed=99)
    clone.load_state_dict(agent.state_dict())
    obs = rng.uniform(-1, 1, 26).astype(np.float32)
    assert [clone.act(obs, None, 0.5) for _ in range(20)] == [agent.act(obs, None, 0.5) for _ in range(20)]
    with pytest.raises(ValueError, match="method"):
        make_agent(load_agent_config("tuned", "dqn" if method != "dqn" else "qmask"), 0).load_state_dict(
            agent.state_dict()
        )


def test_epsilon_per_episode_schedule_ignores_steps() -> None:
    cfg = load_agent_config(
        "tuned", overrides={"eps_start": 1.0, "eps_end": 0.1, "eps_decay_steps": 100, "eps_decay_episodes": 10}
    )
    assert linear_epsilon(10_000, cfg, episode=0) == 1.0  # steps do not matter any more
    assert linear_epsilon(0, cfg, episode=5) == pytest.approx(0.55)
    assert linear_epsilon(0, cfg, episode=10) == 0.1 and linear_epsilon(0, cfg, episode=99) == 0.1


def test_hinge_shaping_only_penalises_unsafe_values_above_the_target() -> None:
    q = torch.tensor([[1.0, 3.0, -2.0, 0.5, 4.0]], requires_grad=True)
    mask = torch.tensor([[T, T, F_, T, F_]])
    actions = torch.tensor([1])
    y = torch.tensor([3.0])  # TD error 0
    # target 3 − 1 = 2: unsafe pair 2 (−2) is already below → 0; pair 4 (4) exceeds by 2 → 4; mean over 2 → 2
    loss = q_shaping_loss(q, actions, y, mask, weight=1.0, kind="mse", target="taken_action", one_sided=True)
    assert loss.item() == pytest.approx(2.0)
    loss.backward()
    assert q.grad is not None
    assert q.grad[0, 2] == 0  # below the target: left alone (regression would pull it up to 2)
    assert q.grad[0, 4].item() == pytest.approx(2 * 2 / 2)


def test_shaping_margin_sets_how_far_below_the_reference() -> None:
    q = torch.tensor([[1.0, 3.0, -2.0, 0.5, 4.0]])
    mask = torch.tensor([[T, T, F_, T, F_]])
    taken = torch.tensor([1])
    assert shaping_target(q, mask, taken, "taken_action", margin=0.25).item() == 2.75  # Q(s, 1) = 3, − 0.25


def test_shaped_q_uses_the_configured_margin() -> None:
    q = torch.tensor([[1.0, 3.0, -2.0, 0.5, 4.0]])
    mask = torch.tensor([[T, T, F_, T, F_]])
    assert shaped_q(q, mask, margin=0.1)[0].tolist() == pytest.approx([1.0, 3.0, -2.1, 0.5, -2.1])
    agent = agent_with_constant_q("robust", [1.0, 3.0, -2.0, 0.5, 4.0], shaping_margin=0.25)
    values = agent.action_values(torch.zeros(1, 26), mask)
    assert values[0].tolist() == pytest.approx([1.0, 3.0, -2.25, 0.5, -2.25])


@settings(max_examples=60, deadline=None)
@given(
    q=st.lists(st.floats(-50, 50, allow_nan=False), min_size=5, max_size=5),
    mask=st.lists(st.booleans(), min_size=5, max_size=5),
    next_mask=st.lists(st.booleans(), min_size=5, max_size=5),
    margin=st.floats(0.01, 5.0),
    done=st.booleans(),
)
def test_robust_acts_and_bootstraps_exactly_like_qmask(
    q: list[float], mask: list[bool], next_mask: list[bool], margin: float, done: bool
) -> None:
    """RobustAgent derives acting and its TD target from QMaskAgent: same network, same greedy action
    over the safe actions and the same target (the max of the shaped target Q is the max over safe
    actions). Only the loss (Q-shaping's regression) differs."""
    assert issubclass(RobustAgent, QMaskAgent) and RobustAgent.td_target is QMaskAgent.td_target
    robust = agent_with_constant_q("robust", q, shaping_margin=margin, gamma=0.9)
    qmask = agent_with_constant_q("qmask", q, gamma=0.9)
    m = sanitize_mask(np.array(mask))
    assert robust.greedy(np.zeros(26, np.float32), m) == qmask.greedy(np.zeros(26, np.float32), m)
    nm = sanitize_mask(np.array(next_mask))
    batch = batch_of(1, masks=[m.tolist()], next_masks=[nm.tolist()], rewards=[0.5], dones=[float(done)])
    shaped_next = shaped_q(robust.targets["q"](batch.next_obs), batch.next_masks, margin).max(dim=1).values
    expected = batch.rewards + 0.9 * shaped_next * (1.0 - batch.dones)  # eq. 13's bootstrap, written out
    assert torch.equal(robust.td_target(batch), expected)
    assert torch.equal(robust.td_target(batch), qmask.td_target(batch))


def test_method_properties_live_on_the_agent_classes() -> None:
    from safelane.running.run_directory import TRAIN_SHIELD_MODE

    classes = {m: agent_class(m) for m in (*AGENT_CLASSES, *RECURRENT_METHODS)}
    assert {m: (c.uses_mask, c.needs_cost, c.train_shield) for m, c in classes.items()} == {
        "dqn": (False, False, "nominal"),
        "constrained": (False, True, "nominal"),
        "qmask": (True, False, "nominal"),
        "robust": (True, False, "robust"),
        "robust-recurrent": (True, False, "robust"),
    }
    assert {m: c.train_shield for m, c in classes.items()} == TRAIN_SHIELD_MODE
