"""The states with a memory (eq. 3 stacked over the last decisions, eq. 3 with each observed car's belief over the
driver types) and the agents that read a state of any size."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import safelane
from safelane.config import ConfigError, load_config
from safelane.core.drivers import parse_driver_mix
from safelane.core.spaces import OBS_SIZE, OBSERVED_VEHICLES
from safelane.env.factory import observation_size
from safelane.env.observations import STACK_DEPTH, observed_vehicles, paper_state, state_size
from safelane.running.run_directory import load_agent, load_policy, load_run_config, make_train_config
from safelane.running.training import train
from safelane.safety.belief import BeliefFilter

MIX = parse_driver_mix("timid-normal-aggressive")
K = len(MIX.types)


def _hidden(state: str, *sets: str) -> safelane.config.SafelaneConfig:
    return load_config("hidden-types", sets=["simulator=fast", f"state={state}", *sets])


def test_sizes_of_every_state() -> None:
    assert state_size("paper") == state_size("lanes") == OBS_SIZE == 26
    assert state_size("paper", continuous=True) == 28
    assert state_size("paper-types", driver_types=3) == state_size("paper-belief", driver_types=3) == 26 + 4 * 3
    assert state_size("paper-stack") == 26 * STACK_DEPTH == 104
    assert observation_size(load_config("fast")) == 26
    for state in ("paper-types", "paper-belief", "paper-stack", "paper"):
        cfg = _hidden(state)
        assert observation_size(cfg) == safelane.make_env(cfg).observation_space.shape[0]


def test_paper_stack_is_eq3_of_the_last_decisions_oldest_first() -> None:
    env = safelane.make_env(_hidden("paper-stack"))
    obs, info = env.reset(seed=4)
    assert obs.shape == (OBS_SIZE * STACK_DEPTH,) and obs.dtype == np.float32
    blocks = obs.reshape(STACK_DEPTH, OBS_SIZE)
    assert not blocks[:-1].any()  # no decision before the first: zeros
    np.testing.assert_array_equal(blocks[-1], paper_state(info["snapshot"]))
    seen = [paper_state(info["snapshot"])]
    for t in range(6):
        obs, _, terminated, truncated, info = env.step(1)
        assert not (terminated or truncated)
        seen.append(paper_state(info["snapshot"]))
        blocks = obs.reshape(STACK_DEPTH, OBS_SIZE)
        for j in range(STACK_DEPTH):  # block j is the decision STACK_DEPTH − 1 − j ago, or zeros before the start
            ago = STACK_DEPTH - 1 - j
            expected = seen[-1 - ago] if ago < len(seen) else np.zeros(OBS_SIZE, dtype=np.float32)
            np.testing.assert_array_equal(blocks[j], expected, err_msg=f"step {t}, block {j}")
    obs, info = env.reset(seed=5)  # a new episode forgets the last one
    assert not obs.reshape(STACK_DEPTH, OBS_SIZE)[:-1].any()


def test_paper_belief_is_eq3_then_each_observed_car_s_posterior() -> None:
    env = safelane.make_env(_hidden("paper-belief"))
    assert env.observation_space.shape == (OBS_SIZE + OBSERVED_VEHICLES * K,)
    obs, info = env.reset(seed=3)
    reference = BeliefFilter(MIX)
    posterior = reference.reset(info["snapshot"])
    prior = MIX.probabilities.astype(np.float32)
    for t in range(8):
        snap = info["snapshot"]
        assert obs.dtype == np.float32
        np.testing.assert_array_equal(obs[:OBS_SIZE], paper_state(snap))
        rows = obs[OBS_SIZE:].reshape(OBSERVED_VEHICLES, K)
        near = observed_vehicles(snap)
        assert len(near) == OBSERVED_VEHICLES
        for slot, i in enumerate(near):
            np.testing.assert_array_equal(rows[slot], posterior[i].astype(np.float32))
            assert rows[slot].sum() == pytest.approx(1.0, abs=1e-6)
        if t == 0:
            np.testing.assert_array_equal(rows, np.tile(prior, (OBSERVED_VEHICLES, 1)))
        obs, *_, info = env.step(1)
        posterior = reference.update(info["snapshot"])
    assert not np.allclose(obs[OBS_SIZE:].reshape(OBSERVED_VEHICLES, K), prior)  # the motion moved some belief


def test_paper_belief_leaves_empty_slots_zero() -> None:
    env = safelane.make_env(_hidden("paper-belief", "env.vehicles_count=2"))
    obs, info = env.reset(seed=0)
    for _ in range(2):
        obs, *_, info = env.step(1)
    present = len(observed_vehicles(info["snapshot"]))
    assert 1 <= present < OBSERVED_VEHICLES
    rows = obs[OBS_SIZE:].reshape(OBSERVED_VEHICLES, K)
    np.testing.assert_allclose(rows[:present].sum(axis=1), 1.0, atol=1e-6)
    assert not rows[present:].any()


@pytest.mark.parametrize(
    ("sets", "message"),
    [
        (["state=paper-belief"], "state: 'paper-belief' .*needs traffic.driver_mix.*allowed without one"),
        (["state=paper-belief", "traffic.driver_mix=[{type: LinearVehicle, weight: 1}]"], "traffic.driver_mix: .*"),
        (["state=paper-history"], "state"),
    ],
)
def test_bad_states_are_one_line_errors(sets: list[str], message: str) -> None:
    with pytest.raises(ConfigError, match=message) as err:
        load_config("fast", sets=sets)
    assert "\n" not in str(err.value)


def test_paper_stack_needs_no_mixture() -> None:
    env = safelane.make_env(load_config("fast", sets=["state=paper-stack"]))
    obs, _ = env.reset(seed=0)
    assert obs.shape == (104,)


@pytest.mark.parametrize("state", ["paper-types", "paper-stack", "paper-belief"])
def test_the_dqn_trains_on_a_wider_state_and_its_policy_drives(state: str, tmp_path: Path) -> None:
    sets = ["simulator=fast", f"state={state}", "env.duration=3", "env.vehicles_count=8", "agent.learning_starts=2",
            "agent.batch_size=4", "agent.buffer_size=10", "agent.target_update_interval=2"]  # fmt: skip
    cfg = make_train_config(method="robust", env_preset="hidden-types", episodes=2, seed=0, sets=sets)
    out = train(cfg, tmp_path / state)
    run = load_run_config(out)
    size = observation_size(run.env)
    assert size == state_size(state, driver_types=K) > OBS_SIZE
    assert load_agent(out).q_net.net[0].in_features == size
    env = safelane.make_env(run.env)
    policy = load_policy(out)
    obs, info = env.reset(seed=9)
    assert info["action_mask"][policy(obs, info)]
    if state != "paper-stack":  # a mixture of another number of types: the same state's name, another size
        two = "traffic.driver_mix=[{type: timid, weight: 1}, {type: aggressive, weight: 1}]"
        other = safelane.make_env(load_config("hidden-types", sets=["simulator=fast", f"state={state}", two]))
        obs, info = other.reset(seed=9)
        with pytest.raises(ConfigError, match=r"state: .* reads 38 numbers .* gives 34; allowed") as err:
            policy(obs, info)
        assert "\n" not in str(err.value)


def test_the_fast_batch_leaves_the_wider_states_to_the_environment_loop() -> None:
    from safelane.running.batched_training import batchable

    assert batchable(make_train_config(method="qmask", episodes=1, sets=["simulator=fast"])) is None
    for state in ("paper-stack", "paper-types", "paper-belief"):
        sets = ["simulator=fast", f"state={state}"]
        cfg = make_train_config(method="qmask", episodes=1, env_preset="hidden-types", sets=sets)
        assert batchable(cfg) == f"state: {state}"
