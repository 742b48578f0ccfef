"""The recurrent robust Q-masking agent: masking, its hidden state, sequence replay, checkpoints, a trained run's
policy, and a memory task only a recurrent network solves."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from safelane.agents.dqn import AgentConfig, ReplayBuffer, RobustAgent, load_agent_config, parse_methods
from safelane.agents.recurrent import RecurrentRobustAgent, SequenceReplay
from safelane.agents.registry import make_agent
from safelane.cli import app
from safelane.config import ConfigError
from safelane.running.batched_training import batchable, batches_of, train_batched
from safelane.running.evaluation import BatchPolicy, run_episode
from safelane.running.run_directory import (
    RecurrentGreedyPolicy,
    TrainConfig,
    load_agent,
    load_checkpoint,
    load_policy,
    make_train_config,
)
from safelane.running.training import deterministic_torch, train

OBS = 26
ALL = np.ones(5, dtype=bool)


def agent_of(**fields: object) -> RecurrentRobustAgent:
    cfg = load_agent_config("tuned", "robust-recurrent", {"recurrent_hidden": 16, **fields})
    agent = make_agent(cfg, seed=3, obs_size=OBS)
    assert isinstance(agent, RecurrentRobustAgent)
    return agent


@pytest.fixture(autouse=True)
def _torch_threads_restored() -> Iterator[None]:
    threads = torch.get_num_threads()
    yield
    assert torch.get_num_threads() == threads


# --- acting --------------------------------------------------------------------------------------
def test_a_masked_action_is_never_chosen() -> None:
    agent = agent_of()
    with torch.no_grad():  # FASTER's value far above every other action's, whatever the hidden state
        agent.q_net.head.bias.copy_(torch.tensor([0.0, 0.0, 0.0, 100.0, 0.0]))
    rng = np.random.default_rng(0)
    no_faster = np.array([True, True, True, False, True])
    agent.begin_episode()
    assert agent.greedy(rng.normal(size=OBS), ALL) == 3  # unmasked, it is the greedy action
    for step in range(200):
        mask = no_faster.copy()
        mask[rng.integers(5)] = False  # a second unsafe action, varying
        obs = rng.normal(size=OBS)
        assert mask[agent.greedy(obs, mask)]
        assert mask[agent.act(obs, mask, eps=1.0 if step % 2 else 0.0)]
    only_slower = np.array([False, False, False, False, True])
    assert agent.greedy(rng.normal(size=OBS), only_slower) == 4


def test_the_hidden_state_resets_at_each_episode() -> None:
    agent = agent_of()
    observations = np.random.default_rng(1).normal(size=(12, OBS)).astype(np.float32)

    def play() -> tuple[list[int], np.ndarray]:
        actions, values = [], []
        for obs in observations:
            values.append(agent.step_values(obs))
            actions.append(int(np.argmax(values[-1])))
        return actions, np.array(values)

    agent.begin_episode()
    first_actions, first_values = play()
    continued = play()[1]  # no reset: the memory of the first episode changes the values
    agent.begin_episode()
    again_actions, again_values = play()
    assert again_actions == first_actions and np.array_equal(again_values, first_values)
    assert not np.allclose(continued, first_values)


def test_a_batch_is_refused_and_the_policy_is_not_a_batch_policy(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="one decision"):
        agent_of().greedy_batch(np.zeros((2, OBS)), None)
    with pytest.raises(ConfigError, match="robust-recurrent trains with safelane train"):
        parse_methods("robust,robust-recurrent")
    cfg = make_train_config(method="robust-recurrent", episodes=2)
    assert batchable(cfg) == "method: robust-recurrent (the batched learner's agents are feed-forward)"
    assert batches_of([(cfg, tmp_path / "run")], workers=1) == []  # reproduce leaves it to the per-run trainer
    with pytest.raises(ConfigError, match=r"method: robust-recurrent .*train this run alone"):
        train_batched([cfg], [tmp_path / "run"])


def test_the_hidden_types_table_trains_paper_recurrent_as_robust_recurrent_on_paper() -> None:
    from safelane.running.run_directory import resolve
    from safelane.running.types_reproduction import LEARNED, make_types_spec, train_config_of

    assert "paper-recurrent" in LEARNED
    run = resolve(train_config_of(make_types_spec(seeds=[0]), "paper", "paper-recurrent", "belief", 0))
    assert (run.agent.method, run.env.state, run.env.shield.mode) == ("robust-recurrent", "paper", "belief")


# --- replay --------------------------------------------------------------------------------------
def fill(buffer: SequenceReplay, lengths: list[int]) -> None:
    """Episodes whose observations say (episode, decision): obs[0] = episode, obs[1] = decision."""
    for episode, length in enumerate(lengths):
        buffer.begin_episode()
        for t in range(length):
            obs = np.array([episode, t], dtype=np.float32)
            buffer.add(obs, t % 5, 0.1, 0.0, obs + np.float32([0, 1]), t == length - 1, ALL, ALL)


def test_a_sampled_sequence_never_crosses_an_episode_boundary() -> None:
    buffer = SequenceReplay(capacity=40, obs_size=2, burn_in=3, length=4)
    lengths = [int(n) for n in np.random.default_rng(2).integers(1, 12, size=30)]
    fill(buffer, lengths)  # 30 episodes in 40 slots: the buffer wrapped, oldest episodes cut
    batch = buffer.sample(500, np.random.default_rng(3))
    obs, nxt, valid, trained = batch.obs.numpy(), batch.next_obs.numpy(), batch.valid.numpy(), batch.trained.numpy()
    for row in range(len(obs)):
        n = int(valid[row].sum())
        assert valid[row, :n].all() and not valid[row, n:].any()  # real decisions first, then padding
        episode, steps = obs[row, :n, 0], obs[row, :n, 1]
        assert (episode == episode[0]).all()  # one episode
        assert np.array_equal(steps, steps[0] + np.arange(n))  # consecutive decisions of it
        assert np.array_equal(nxt[row, : n - 1], obs[row, 1:n])  # s' of a decision is the next one's s
        assert (obs[row, n:] == 0).all()  # zero padding
        k = int(trained[row].sum())
        assert 1 <= k <= buffer.length and trained[row, n - k : n].all()  # the last decisions enter the loss
        if steps[0] != 0:  # a sequence starting mid-episode warms its hidden state up first
            assert n - k >= buffer.burn_in
    assert valid.sum(axis=1).max() == buffer.window


def test_the_replay_round_trips_through_its_state_dict() -> None:
    buffer = SequenceReplay(capacity=25, obs_size=2, burn_in=2, length=3)
    fill(buffer, [7, 9, 5, 8])
    copy = SequenceReplay(capacity=25, obs_size=2, burn_in=2, length=3)
    copy.load_state_dict(buffer.state_dict())
    a, b = buffer.sample(50, np.random.default_rng(4)), copy.sample(50, np.random.default_rng(4))
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    with pytest.raises(ValueError, match="feed-forward"):
        copy.load_state_dict(ReplayBuffer(25, 2).state_dict())


# --- checkpoints ---------------------------------------------------------------------------------
def test_save_and_load_give_identical_q_values() -> None:
    agent = agent_of(batch_size=4)
    buffer = agent.new_replay(OBS)
    rng = np.random.default_rng(5)
    for _ in range(3):
        agent.begin_episode()
        buffer.begin_episode()
        for t in range(6):
            obs = rng.normal(size=OBS).astype(np.float32)
            buffer.add(obs, agent.act(obs, ALL, 0.5), 0.5, 0.0, obs, t == 5, ALL, ALL)
    with deterministic_torch():
        for _ in range(3):
            agent.update(buffer.sample(4, agent.rng))
    data = io.BytesIO()
    torch.save(agent.state_dict(), data)
    data.seek(0)
    other = agent_of(batch_size=4)
    other.load_state_dict(torch.load(data, weights_only=True))
    sequence = torch.from_numpy(rng.normal(size=(2, 9, OBS)).astype(np.float32))
    with torch.no_grad():
        assert torch.equal(agent.q_net(sequence)[0], other.q_net(sequence)[0])
        assert torch.equal(agent.targets["q"](sequence)[0], other.targets["q"](sequence)[0])
    agent.begin_episode()
    other.begin_episode()
    for obs in sequence[0].numpy():
        assert np.array_equal(agent.step_values(obs), other.step_values(obs))
    with pytest.raises(ValueError, match="method"):
        RobustAgent(AgentConfig(method="robust"), obs_size=OBS).load_state_dict(agent.state_dict())


# --- a trained run ---------------------------------------------------------------------------------
SMALL = [
    "env.duration=4",
    "env.vehicles_count=8",
    "agent.learning_starts=4",
    "agent.batch_size=4",
    "agent.buffer_size=10",  # smaller than a run: episodes are overwritten and cut
    "agent.target_update_interval=5",
    "agent.eps_decay_episodes=2",
    "agent.recurrent_hidden=8",
]


def test_a_trained_run_is_evaluated_with_its_hidden_state(tmp_path: Path) -> None:
    runner = CliRunner()
    run = tmp_path / "run"
    sets = [arg for s in SMALL for arg in ("--set", s)]
    args = ["train", "--preset", "hidden-types", "--method", "robust-recurrent", "--episodes", "3", "--out", str(run)]
    result = runner.invoke(app, [*args, *sets])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["evaluate", str(run), "--episodes", "2", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output.strip().splitlines()[-1])
    assert summary["method"] == "robust-recurrent" and summary["episodes"] == 2 and summary["decisions"] > 0

    policy = load_policy(run)
    assert isinstance(policy, RecurrentGreedyPolicy) and not isinstance(policy, BatchPolicy)
    from safelane.env.factory import make_env
    from safelane.running.runs import run_env_config

    env = make_env(run_env_config(run))
    try:
        first = run_episode(env, policy, 7).chosen_actions
        run_episode(env, policy, 8)
        assert run_episode(env, policy, 7).chosen_actions == first  # begin_episode at each reset
        agent = policy.agent
        assert isinstance(agent, RecurrentRobustAgent) and agent.hidden is not None
        agent.hidden = torch.ones_like(agent.hidden)  # a stale memory, unlike any reached from a reset
        obs, info = env.reset(seed=7)  # a loop that never calls begin_episode: the snapshot's clock restarts
        policy(obs, info)
        remembered = agent.hidden.clone()
        policy.begin_episode()
        policy(obs, info)
        assert torch.equal(agent.hidden, remembered)  # the stale memory was dropped at the reset

        obs, info = env.reset(seed=7)
        replay = []
        for _ in range(len(first)):
            replay.append(policy(obs, info))
            obs, _, terminated, truncated, info = env.step(replay[-1])
            if terminated or truncated:
                break
        assert replay == first
    finally:
        env.close()


KILLED = textwrap.dedent(
    """
    import sys, time, pathlib
    from safelane.running.run_directory import make_train_config
    from safelane.running.training import train
    out, marker = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])

    def progress(report):
        if report.episode == 3:  # episode 2 is checkpointed; episode 3's row is already written
            marker.touch()
            time.sleep(120)

    train(make_train_config(method="robust-recurrent", env_preset="hidden-types", episodes=5, seed=1,
          checkpoint_every=2, sets=sys.argv[3:]), out, progress=progress)
    """
)


def test_a_killed_run_resumes_to_the_uninterrupted_runs_end(tmp_path: Path) -> None:
    def cfg() -> TrainConfig:
        return make_train_config(
            method="robust-recurrent", env_preset="hidden-types", episodes=5, seed=1, checkpoint_every=2, sets=SMALL
        )

    reference = train(cfg(), tmp_path / "reference")
    run, marker = tmp_path / "killed", tmp_path / "marker"
    proc = subprocess.Popen(
        [sys.executable, "-c", KILLED, str(run), str(marker), *SMALL], env={**os.environ, "SDL_VIDEODRIVER": "dummy"}
    )
    try:
        deadline = time.monotonic() + 120
        while not marker.exists():
            assert proc.poll() is None, "training subprocess died"
            assert time.monotonic() < deadline, "training subprocess too slow"
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert load_checkpoint(run)["episode"] == 2
    train(cfg(), run, resume=True)
    timing = ("wall_time_s", "env_time_s")
    rows = [
        [{k: v for k, v in r.items() if k not in timing} for r in load_checkpoint(d)["rows"]] for d in (run, reference)
    ]
    assert rows[0] == rows[1] and len(rows[0]) == 5
    weights = [load_agent(d).q_net.state_dict() for d in (run, reference)]
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[1])


# --- the recurrence matters ------------------------------------------------------------------------
CUE_DELAY = 4
"""Decisions between the cue and the question: the answer depends on an observation 4 decisions old."""


def memory_episode(cue: int) -> list[np.ndarray]:
    """Observations of one episode: the cue (one-hot in 0–1) first, blanks, then the question (flag 2)."""
    blank = np.zeros(3, dtype=np.float32)
    first = blank.copy()
    first[cue] = 1.0
    last = blank.copy()
    last[2] = 1.0
    return [first, *[blank] * (CUE_DELAY - 1), last]


QUESTION_MASK = np.array([True, True, False, False, False])  # the answer is action 0 or 1; the rest unsafe


def learn_memory_task(agent: RobustAgent, buffer: ReplayBuffer | SequenceReplay, updates: int) -> float:
    """Fill the replay with random play (reward 1 for answering the cue, at the last decision), train, and return
    the share of questions the greedy policy answers right."""
    rng = np.random.default_rng(0)
    for _ in range(200):
        cue = int(rng.integers(2))
        episode = memory_episode(cue)
        buffer.begin_episode()
        for t, obs in enumerate(episode):
            last = t == len(episode) - 1
            mask = QUESTION_MASK if last else ALL
            action = int(rng.choice(np.flatnonzero(mask)))
            reward = float(last and action == cue)
            nxt = episode[min(t + 1, len(episode) - 1)]
            buffer.add(obs, action, reward, 0.0, nxt, last, mask, QUESTION_MASK if t + 1 == len(episode) - 1 else ALL)
    with deterministic_torch():
        for k in range(updates):
            agent.update(buffer.sample(agent.cfg.batch_size, agent.rng))
            if k % 10 == 9:
                agent.sync_target()
    right = 0
    for cue in (0, 1) * 10:
        agent.begin_episode()
        episode = memory_episode(cue)
        for obs in episode[:-1]:
            agent.greedy(obs, ALL)  # the recurrent agent remembers; the feed-forward one forgets
        right += agent.greedy(episode[-1], QUESTION_MASK) == cue
    return right / 20


def test_a_recurrent_q_network_learns_what_a_feed_forward_one_cannot() -> None:
    fields = {"lr": 3e-3, "batch_size": 32, "gamma": 0.9, "burn_in": 0, "sequence_length": CUE_DELAY + 1,
              "recurrent_hidden": 16}  # fmt: skip
    recurrent = make_agent(load_agent_config("tuned", "robust-recurrent", fields), seed=0, obs_size=3)
    assert learn_memory_task(recurrent, recurrent.new_replay(3), updates=200) == 1.0
    feed_forward = make_agent(load_agent_config("tuned", "robust", fields), seed=0, obs_size=3)
    assert learn_memory_task(feed_forward, feed_forward.new_replay(3), updates=200) == 0.5  # one answer for both cues
