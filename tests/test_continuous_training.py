"""Training continuous agents (SB3's SAC and PPO, the Lagrangian SAC): run directories, resume, λ, the shield,
evaluation and the one-line errors. Tiny budgets on the fast simulator: seconds per run."""

from __future__ import annotations

import json
import os
import signal
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml
from typer.testing import CliRunner

from safelane.agents.continuous import ALGO_DEFAULTS, build_continuous_agent_config, load_model, require_sb3
from safelane.cli import app
from safelane.config import ConfigError
from safelane.env.factory import make_env
from safelane.reporting.metrics_file import CONTINUOUS_METRIC_COLUMNS, TIMING_COLUMNS, read_metrics
from safelane.running.continuous_training import ContinuousEpisodeReport, train_continuous
from safelane.running.run_directory import (
    TrainConfig,
    load_checkpoint,
    load_continuous_model,
    load_policy,
    load_run_config,
    make_train_config,
)
from safelane.running.training import TrainingInterrupted

runner = CliRunner()

# Short episodes in light traffic, small networks: a few seconds per run.
ROAD = ["simulator=fast", "actions=continuous", "env.duration=6", "env.vehicles_count=8"]
AGENT = {
    "sac": ["agent.learning_starts=20", "agent.batch_size=16", "agent.net_arch=[32, 32]", "agent.buffer_size=150"],
    "ppo": ["agent.n_steps=48", "agent.batch_size=16", "agent.n_epochs=2", "agent.net_arch=[32, 32]"],
}
AGENT["sac-lagrangian"] = [*AGENT["sac"], "agent.lambda_update_interval=10"]
VALUE_COLUMNS = [c for c in CONTINUOUS_METRIC_COLUMNS if c not in TIMING_COLUMNS]


@pytest.fixture(autouse=True)
def _torch_threads_restored() -> Iterator[None]:
    threads = torch.get_num_threads()
    yield
    assert torch.get_num_threads() == threads  # training restores what it changes


def small(algo: str, steps: int = 200, seed: int = 0, extra: list[str] | None = None) -> TrainConfig:
    return make_train_config(
        algo=algo, steps=steps, seed=seed, checkpoint_steps=20, sets=[*ROAD, *AGENT[algo], *(extra or [])]
    )


def metrics(run: Path) -> dict[str, np.ndarray]:
    return read_metrics(run / "metrics.csv", VALUE_COLUMNS)


def same_metrics(a: Path, b: Path) -> bool:
    ma, mb = metrics(a), metrics(b)
    return all(np.array_equal(ma[c], mb[c], equal_nan=True) for c in VALUE_COLUMNS)


def same_networks(a: Path, b: Path) -> bool:
    wa, wb = load_continuous_model(a).policy.state_dict(), load_continuous_model(b).policy.state_dict()
    return wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


def stop_at(episode: int, how: Callable[[], None]) -> Callable[[ContinuousEpisodeReport], None]:
    def progress(report: ContinuousEpisodeReport) -> None:
        if report.episode == episode:
            how()

    return progress


def ctrl_c() -> None:
    os.kill(os.getpid(), signal.SIGINT)


def crash() -> None:  # the process dies here: nothing beyond what is on disk survives
    raise RuntimeError("killed")


# --- a run directory per algorithm ------------------------------------------------------------------------------
@pytest.mark.parametrize("algo", ["sac", "ppo", "sac-lagrangian"])
def test_each_algorithm_trains_a_run_directory(tmp_path: Path, algo: str) -> None:
    reports: list[ContinuousEpisodeReport] = []
    out = train_continuous(small(algo), tmp_path / algo, progress=reports.append)

    run = load_run_config(out)
    assert (run.train.algo, run.train.steps, run.train.method, run.agent.algo) == (algo, 200, None, algo)
    assert yaml.safe_load((out / "config.yaml").read_text())["env"]["actions"] == "continuous"
    header = (out / "metrics.csv").read_text().splitlines()[0].split(",")
    assert tuple(header) == CONTINUOUS_METRIC_COLUMNS
    rows = metrics(out)
    assert list(rows["episode"]) == list(range(1, len(rows["episode"]) + 1)) == [r.episode for r in reports]
    assert np.all(np.diff(rows["env_steps"]) == rows["length"][1:])  # each row ends its episode's decisions
    assert rows["env_steps"][-1] <= load_checkpoint(out)["global_step"] >= 200
    assert np.all(rows["cost"] == np.maximum(rows["collision"], rows["off_road"]))  # both end the episode
    assert np.all(np.isnan(rows["lambda"])) == (algo != "sac-lagrangian")
    assert np.all(rows["shield_interventions"] == 0)  # no shield

    policy = load_policy(out)
    env = make_env(run.env)
    obs, info = env.reset(seed=7)
    action = policy(obs, info)
    assert action.shape == (2,) and action.dtype == np.float32 and np.all(np.abs(action) <= 1)
    env.close()


def test_the_same_seed_gives_the_same_run(tmp_path: Path) -> None:
    a = train_continuous(small("sac", steps=120, seed=4), tmp_path / "a")
    b = train_continuous(small("sac", steps=120, seed=4), tmp_path / "b")
    assert same_metrics(a, b) and same_networks(a, b)
    c = train_continuous(small("sac", steps=120, seed=5), tmp_path / "c")
    assert not same_metrics(a, c)


# --- resume -------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("algo", "how"), [("sac-lagrangian", ctrl_c), ("sac", crash)])
def test_sac_resumed_after_an_interruption_ends_like_an_uninterrupted_run(
    tmp_path: Path, algo: str, how: Callable[[], None]
) -> None:
    whole = train_continuous(small(algo, seed=2), tmp_path / "whole")
    cut = tmp_path / "cut"
    with pytest.raises(TrainingInterrupted if how is ctrl_c else RuntimeError):
        train_continuous(small(algo, seed=2), cut, progress=stop_at(25, how))
    state = load_checkpoint(cut)
    assert state["at_episode_start"] and 0 < state["episode"] <= 25
    if how is ctrl_c:  # Ctrl-C: the checkpoint at the end of the episode it came in
        assert state["episode"] == 25 and len(metrics(cut)["episode"]) == 25
    else:  # a kill: the last periodic checkpoint; rows past it are on disk until the resume drops them
        assert len(metrics(cut)["episode"]) == 25 > state["episode"]

    train_continuous(small(algo, seed=2), cut, resume=True)
    assert same_metrics(whole, cut)
    assert same_networks(whole, cut)
    if algo == "sac-lagrangian":
        assert load_continuous_model(whole).lam == load_continuous_model(cut).lam > 0


def test_ppo_resume_restores_networks_counters_and_finished_episodes(tmp_path: Path) -> None:
    whole = train_continuous(small("ppo", seed=1), tmp_path / "whole")
    cut = tmp_path / "cut"
    with pytest.raises(TrainingInterrupted):
        train_continuous(small("ppo", seed=1), cut, progress=stop_at(10, ctrl_c))
    state = load_checkpoint(cut)
    before = metrics(cut)
    assert state["episode"] == len(before["episode"]) == 10
    assert all(
        np.array_equal(before[c], metrics(whole)[c][:10], equal_nan=True) for c in VALUE_COLUMNS
    )  # same run so far
    model = load_model("ppo", state["model"])
    assert model.num_timesteps == state["global_step"] >= before["env_steps"][-1]

    train_continuous(small("ppo", seed=1), cut, resume=True)
    after = metrics(cut)
    assert list(after["episode"]) == list(range(1, len(after["episode"]) + 1))  # no duplicated row
    assert all(np.array_equal(after[c][:10], before[c], equal_nan=True) for c in VALUE_COLUMNS)
    assert load_checkpoint(cut)["global_step"] >= 200


def test_resume_refuses_another_configuration(tmp_path: Path) -> None:
    out = train_continuous(small("sac", steps=40), tmp_path / "run")
    with pytest.raises(ConfigError, match="already holds a training run"):
        train_continuous(small("sac", steps=40), out)
    with pytest.raises(ConfigError, match=r"agent\.batch_size"):
        train_continuous(small("sac", steps=40, extra=["agent.batch_size=8"]), out, resume=True)
    with pytest.raises(ConfigError, match="algo"):
        train_continuous(small("ppo", steps=40), out, resume=True)


# --- the Lagrangian multiplier ------------------------------------------------------------------------------------
def expected_lambdas(rows: dict[str, np.ndarray], lr: float, budget: float, interval: int, starts: int) -> list[float]:
    """λ after each episode, worked by hand: every ``interval`` decisions, on the mean cost of the episodes that
    ended since (after the warm-up of ``starts`` decisions), λ ← max(0, λ + lr·(mean − budget))."""
    lam, window, updated_at, out = 0.0, [], starts, []
    for cost, step in zip(rows["cost"], rows["env_steps"], strict=True):
        if step > starts:
            window.append(cost)
            if step - updated_at >= interval:
                lam, window, updated_at = max(0.0, lam + lr * (float(np.mean(window)) - budget)), [], step
        out.append(lam)
    return out


def test_lambda_rises_by_dual_ascent_while_episodes_cost_more_than_the_budget(tmp_path: Path) -> None:
    budget, lr, interval = 0.05, 0.1, 10
    extra = [f"agent.cost_budget={budget}", f"agent.lambda_lr={lr}", f"agent.lambda_update_interval={interval}"]
    rows = metrics(train_continuous(small("sac-lagrangian", steps=120, extra=extra), tmp_path / "tight"))
    assert rows["cost"].mean() > budget  # an untrained driver leaves the road
    np.testing.assert_allclose(rows["lambda"], expected_lambdas(rows, lr, budget, interval, 20), rtol=0, atol=1e-9)
    assert np.all(np.diff(rows["lambda"]) >= 0) and rows["lambda"][-1] > 0
    assert np.all(rows["lambda"][rows["env_steps"] <= 20] == 0)  # the warm-up's random episodes do not count

    extra = ["agent.cost_budget=1", f"agent.lambda_update_interval={interval}"]
    loose = metrics(train_continuous(small("sac-lagrangian", steps=120, extra=extra), tmp_path / "loose"))
    assert np.all(loose["lambda"] == 0.0)  # an episode costs at most 1: never over this budget


def test_lambda_falls_to_zero_under_the_budget(tmp_path: Path) -> None:
    model = load_continuous_model(train_continuous(small("sac-lagrangian", steps=30), tmp_path / "run"))
    model.lam, model.lambda_lr, model.cost_budget = 0.3, 0.1, 0.5
    model.update_lambda(0.0)
    assert model.lam == pytest.approx(0.25)
    for _ in range(10):
        model.update_lambda(0.0)
    assert model.lam == 0.0


# --- the shield -------------------------------------------------------------------------------------------------
SHIELD = ["shield.mode=committed", "shield.engine=numpy", "env.duration=3"]


def test_the_sac_replay_buffer_stores_the_action_the_shield_executed() -> None:
    require_sb3()
    from safelane.agents.sac_lagrangian import ExecutedActionReplayBuffer

    env = make_env(load_config_of(SHIELD))
    obs, _ = env.reset(seed=4)
    proposed = np.array([1.0, 1.0], dtype=np.float32)  # full throttle, the wheels turned as far as they go
    next_obs, reward, terminated, _, info = env.step(proposed)
    env.close()
    assert info["projected"] and not np.array_equal(info["executed_action"], proposed)
    buffer = ExecutedActionReplayBuffer(4, env.observation_space, env.action_space, device="cpu")
    buffer.add(obs, next_obs, proposed[None], np.array([reward]), np.array([terminated]), [info])
    np.testing.assert_array_equal(buffer.actions[0, 0], info["executed_action"])
    buffer.add(obs, next_obs, proposed[None], np.array([reward]), np.array([terminated]), [{}])  # no shield
    np.testing.assert_array_equal(buffer.actions[1, 0], proposed)


def load_config_of(sets: list[str]) -> Any:
    from safelane.config import load_config

    return load_config("fast", sets=[*ROAD, *sets])


@pytest.mark.parametrize(("algo", "intervention", "penalty"), [("sac", "projection", 0.5), ("ppo", "replacement", 0.0)])
def test_training_under_the_shield_for_continuous_actions(
    tmp_path: Path, algo: str, intervention: str, penalty: float
) -> None:
    extra = [*SHIELD, f"shield.intervention={intervention}", f"shield.adaptation_penalty={penalty}"]
    extra += ["agent.learning_starts=2"] if algo == "sac" else ["agent.n_steps=4"]
    extra += ["agent.batch_size=4"]
    cfg = make_train_config(algo=algo, steps=6, seed=0, sets=[*ROAD, *AGENT[algo], *extra])
    out = train_continuous(cfg, tmp_path / algo)
    run = load_run_config(out)
    assert (run.env.shield.mode, run.env.shield.intervention) == ("committed", intervention)
    rows = metrics(out)
    assert rows["length"].sum() == 6 and np.all(rows["collision"] == 0) and np.all(rows["off_road"] == 0)
    assert rows["shield_interventions"].sum() > 0  # an untrained agent's proposals are projected or replaced
    if penalty > 0:
        assert np.all(rows["mean_projection_distance"][rows["shield_interventions"] > 0] > 0)


# --- evaluate and the command line --------------------------------------------------------------------------------
def test_evaluate_a_trained_continuous_run(tmp_path: Path) -> None:
    out = train_continuous(small("ppo", steps=60), tmp_path / "run")
    result = runner.invoke(app, ["evaluate", str(out), "--episodes", "3", "--seed", "2000000000", "--json"])
    assert result.exit_code == 0, result.stderr
    summary = json.loads(result.stdout)
    assert (summary["method"], summary["episodes"], summary["shield"]) == ("ppo", 3, "none")
    assert 0 <= summary["off_road_rate"] <= 1 and 0 <= summary["collisions"] <= 3 and summary["mean_speed"] >= 0
    assert "actions" not in summary  # no meta-action histogram for acceleration and steering


def test_train_command_writes_a_continuous_run(tmp_path: Path) -> None:
    out = tmp_path / "cli"
    args = ["train", "--actions", "continuous", "--algo", "sac-lagrangian", "--cost-budget", "0.2", "--steps", "30"]
    sets = [s for a in AGENT["sac"] + ROAD[2:] for s in ("--set", a)]
    result = runner.invoke(app, [*args, *sets, "--out", str(out)])
    assert result.exit_code == 0, result.stderr
    run = load_run_config(out)
    assert (run.train.algo, run.agent.cost_budget, run.env.simulator) == ("sac-lagrangian", 0.2, "fast")
    result = runner.invoke(app, [*args, *sets, "--out", str(out), "--resume"])
    assert result.exit_code == 0, result.stderr


@pytest.mark.parametrize(
    ("args", "starts"),
    [
        (["--actions", "continuous", "--algo", "dqn"], "--algo: got 'dqn'; allowed: sac, ppo, sac-lagrangian"),
        (["--algo", "sac"], "--algo: sac trains continuous actions; add --actions continuous"),
        (["--actions", "discrete", "--algo", "ppo"], "--algo: ppo trains continuous actions"),
        (["--actions", "continuous", "--method", "robust"], "--method: robust trains the discrete meta-actions"),
        (["--actions", "continuous", "--episodes", "5"], "--episodes: continuous agents train for --steps"),
        (["--steps", "100"], "--steps: only with --actions continuous"),
        (["--actions", "continuous", "--cost-budget", "0.1"], "--cost-budget: only for --algo sac-lagrangian"),
        (["--actions", "continuous", "--steps", "0"], "--steps: must be >= 1"),
        (["--actions", "continuous", "--set", "agent.n_steps=8"], "agent.n_steps: only for algo ppo"),
        (["--actions", "continuous", "--set", "agent.algo=ppo"], "--set agent.algo: choose the algo with --algo"),
        (["--actions", "continuous", "--set", "agent.ent_coef=auto", "--algo", "ppo"], "agent.ent_coef: got 'auto'"),
        (["--actions", "continuous", "--agent-preset", "paper"], "train.agent_preset: with algo, a .yaml file"),
        (["--set", "actions=continuous", "--set", "shield.mode=robust"], "shield.mode: 'robust' decides among"),
        (["--set", "actions=continuous", "--method", "qmask"], "--method: qmask trains the discrete meta-actions"),
    ],
)
def test_bad_continuous_training_input_is_one_error_line(tmp_path: Path, args: list[str], starts: str) -> None:
    result = runner.invoke(app, ["train", *args, "--out", str(tmp_path / "run")])
    assert result.exit_code == 2, result.stdout
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {starts}"), result.stderr
    assert not (tmp_path / "run" / "metrics.csv").exists()


def test_config_errors_name_the_field() -> None:
    with pytest.raises(ConfigError, match=r"^train\.episodes: algo 'sac' trains for steps"):
        make_train_config(algo="sac", episodes=5)
    with pytest.raises(ConfigError, match=r"^train\.method: the DQN methods take discrete actions"):
        make_train_config(algo="ppo", method="robust")
    with pytest.raises(ConfigError, match=r"^train\.steps: only with algo"):
        make_train_config(method="dqn", steps=10)
    with pytest.raises(ConfigError, match=r"^agent\.cost_budget: only for algo sac-lagrangian"):
        build_continuous_agent_config({"algo": "sac", "cost_budget": 0.1})
    with pytest.raises(ConfigError, match=r"^agent\.cost_budget: Input should be greater than or equal to 0"):
        build_continuous_agent_config({"algo": "sac-lagrangian", "cost_budget": -1})
    filled = build_continuous_agent_config({"algo": "sac-lagrangian"})
    assert {k: getattr(filled, k) for k in ALGO_DEFAULTS["sac-lagrangian"]} == ALGO_DEFAULTS["sac-lagrangian"]


def test_a_missing_stable_baselines3_is_one_line_naming_the_extra(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "stable_baselines3", None)  # import stable_baselines3 → ImportError
    with pytest.raises(ConfigError, match=r"pip install 'safelane\[sb3\]'"):
        train_continuous(small("sac", steps=10), tmp_path / "run")
    result = runner.invoke(app, ["train", "--actions", "continuous", "--out", str(tmp_path / "cli")])
    assert result.exit_code == 2
    assert result.stderr.strip().splitlines() == [
        "error: stable-baselines3 is not installed; continuous agents need it: pip install 'safelane[sb3]'"
    ]
