"""Acting without torch (safelane.agents.inference): the same values as torch, the same action for a row
alone or in any batch, and the current weights after every update."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from safelane.agents import inference
from safelane.agents.dqn import METHODS, QNetwork, ReplayBuffer, load_agent_config, make_agent


def random_obs(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(0, 1.5, size=(n, 26)).astype(np.float32)


def test_forward_equals_torch_in_float64() -> None:
    torch.manual_seed(3)
    net = QNetwork()
    obs = random_obs(50, 0)
    np.testing.assert_allclose(
        inference.forward(inference.layers_of(net), obs), inference.torch_forward(net, obs), rtol=0, atol=1e-12
    )
    with torch.no_grad():  # and float32 torch is within its own rounding of it
        np.testing.assert_allclose(
            inference.forward(inference.layers_of(net), obs), net(torch.from_numpy(obs)).numpy(), atol=1e-5
        )


@settings(max_examples=25, deadline=None)
@given(rows=st.integers(1, 70), seed=st.integers(0, 10_000), pick=st.integers(0, 69))
def test_a_row_gets_the_same_bits_alone_and_in_any_batch(rows: int, seed: int, pick: int) -> None:
    torch.manual_seed(seed)
    layers = inference.layers_of(QNetwork())
    obs = random_obs(rows, seed)
    r = pick % rows
    assert np.array_equal(inference.forward(layers, obs)[r], inference.forward(layers, obs[r : r + 1])[0])


def test_acting_follows_optimizer_steps_and_checkpoint_loads() -> None:
    agent = make_agent(load_agent_config("tuned", "dqn"), seed=0)
    buffer = ReplayBuffer(100)
    rng = np.random.default_rng(0)
    for _ in range(100):
        buffer.add(
            rng.random(26), int(rng.integers(5)), 1.0, 0.0, rng.random(26), False, np.ones(5, bool), np.ones(5, bool)
        )
    obs = random_obs(8, 1)
    before = agent.acting_values(obs, np.ones((8, 5), bool))
    for _ in range(20):
        agent.update(buffer.sample(64, agent.rng))
    after = agent.acting_values(obs, np.ones((8, 5), bool))
    assert not np.allclose(before, after)  # the update was seen ...
    with torch.no_grad():  # ... and matches the torch network it views
        np.testing.assert_allclose(after, agent.q_net(torch.from_numpy(obs)).numpy(), atol=1e-5)
    fresh = make_agent(load_agent_config("tuned", "dqn"), seed=5)
    assert not np.allclose(fresh.acting_values(obs, np.ones((8, 5), bool)), after)  # its copy is built ...
    fresh.load_state_dict(agent.state_dict())  # ... and rebuilt after the load
    assert np.array_equal(fresh.acting_values(obs, np.ones((8, 5), bool)), after)


@pytest.mark.parametrize("method", METHODS)
def test_acting_values_are_the_torch_action_values_of_each_method(method: str) -> None:
    agent = make_agent(load_agent_config("tuned", method), seed=1)
    if method == "constrained":
        agent.lam = 0.7
    obs = random_obs(40, 2)
    masks = np.random.default_rng(3).random((40, 5)) > 0.4
    masks[~masks.any(axis=1), 1] = True
    with torch.no_grad():
        reference = agent.action_values(torch.from_numpy(obs), torch.from_numpy(masks)).numpy()
    np.testing.assert_allclose(agent.acting_values(obs, masks), reference, atol=1e-5)
    batch = agent.greedy_batch(obs, masks)
    assert [agent.greedy(o, m) for o, m in zip(obs, masks, strict=True)] == batch.tolist()
    if agent.uses_mask:
        assert masks[np.arange(40), batch].all()


def test_greedy_batch_rejects_masks_of_the_wrong_shape() -> None:
    agent = make_agent(load_agent_config("tuned", "qmask"), seed=0)
    with pytest.raises(ValueError, match=r"expected shape \(3, 5\)"):
        agent.greedy_batch(random_obs(3, 0), np.ones((3, 4), bool))
