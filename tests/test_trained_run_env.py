"""A trained run is driven in its own environment (state kind, decision rate, action set) by every command.

The run here is trained with ``state=lanes`` at 3 decisions per second on 5 s episodes (15 decisions):
a command that rebuilt the environment from the preset instead would drive the paper state at one
decision per second on 40 s episodes (40 decisions), and nothing would complain — both states are 26
floats.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from safelane.cli import app
from safelane.config import ConfigError
from safelane.env.factory import make_env
from safelane.running.evaluation import run_episodes
from safelane.running.run_directory import load_policy, load_run_config, make_train_config
from safelane.running.runs import run_env_config
from safelane.running.training import train

runner = CliRunner()
RUN_SETS = [
    "state=lanes",
    "env.policy_frequency=3",
    "env.simulation_frequency=15",
    "env.duration=5",
    "agent.learning_starts=10000",  # no gradient steps: the test is about the environment, not learning
]
DECISIONS = 16  # 5 s at 3 decisions/s: 15, plus one (highway-env sums 1/15 s frames to just under 5 s)


@pytest.fixture(scope="module")
def lanes_3hz_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 1-episode robust run trained with the lanes state at 3 decisions/s."""
    cfg = make_train_config(method="robust", episodes=1, seed=0, checkpoint_every=1, sets=RUN_SETS)
    return train(cfg, tmp_path_factory.mktemp("runs") / "robust-lanes-3hz")


def test_run_env_config_keeps_the_runs_own_settings(lanes_3hz_run: Path) -> None:
    cfg = run_env_config(lanes_3hz_run, shield="nominal", sets=["traffic.vehicles_behind=3"])
    assert cfg.state == "lanes"
    assert cfg.env["policy_frequency"] == 3 and cfg.env["simulation_frequency"] == 15 and cfg.env["duration"] == 5
    assert cfg.shield.mode == "nominal" and cfg.traffic.vehicles_behind == 3


def test_stress_run_dir_drives_the_runs_environment(lanes_3hz_run: Path) -> None:
    result = runner.invoke(
        app, ["stress", str(lanes_3hz_run), "--only", "training", "--only", "lanes_3", "--episodes", "1", "--json"]
    )
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)
    assert out["shield"] == "robust"  # the run's own shield
    for record in out["conditions"]:
        assert record["episodes"] == 1
        assert record["mean_length"] <= DECISIONS  # 3 decisions/s for 5 s, not 40 decisions at 1 Hz


def test_stress_run_dir_skips_a_condition_with_another_decision_rate(lanes_3hz_run: Path) -> None:
    result = runner.invoke(app, ["stress", str(lanes_3hz_run), "--only", "decisions_2hz", "--episodes", "1", "--json"])
    assert result.exit_code == 0, result.output
    (record,) = json.loads(result.stdout)["conditions"]
    assert "2 decisions/s" in record["skipped"] and "3 decisions/s" in record["skipped"]


def test_render_run_dir_with_a_shield_keeps_the_runs_environment(lanes_3hz_run: Path, tmp_path: Path) -> None:
    gif = tmp_path / "episode.gif"
    result = runner.invoke(app, ["render", str(lanes_3hz_run), "--shield", "nominal", "--out", str(gif)])
    assert result.exit_code == 0, result.output
    frames = int(re.search(r"\((\d+) frames\)", result.stdout).group(1))  # type: ignore[union-attr]
    assert frames <= DECISIONS + 1  # one frame per decision plus the last state


def test_evaluate_run_dir_refuses_another_decision_rate_in_one_line(lanes_3hz_run: Path) -> None:
    result = runner.invoke(
        app,
        [
            "evaluate",
            str(lanes_3hz_run),
            "--episodes",
            "1",
            "--set",
            "env.policy_frequency=1",
            "--set",
            "env.simulation_frequency=5",
        ],
    )
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: environment: ")
    assert "1 decisions/s" in lines[0] and "3 decisions/s" in lines[0] and "state 'lanes'" in lines[0]


def test_run_env_config_refuses_another_action_set(lanes_3hz_run: Path) -> None:
    with pytest.raises(ConfigError, match=r"^environment: .*target speeds \[20, 25, 30\] m/s, but run .* was trained"):
        run_env_config(lanes_3hz_run, sets=["env.action.target_speeds=[20,25,30]"])


def test_a_trained_policy_refuses_an_environment_it_was_not_trained_on(lanes_3hz_run: Path) -> None:
    policy = load_policy(lanes_3hz_run)
    own = make_env(run_env_config(lanes_3hz_run))
    (record,) = run_episodes(own, policy, 1, seed=0)
    assert record.length <= DECISIONS
    with pytest.raises(ConfigError, match=r"^environment: state 'paper', 1 decisions/s.*state 'lanes', 3 decisions/s"):
        run_episodes(make_env("fast"), policy, 1, seed=0)
    # Built without run_env_config (which refuses it up front): the policy itself refuses at its first decision.
    other_speeds = make_env(load_run_config(lanes_3hz_run).env, **{"env.action.target_speeds": [20, 25, 30]})
    with pytest.raises(ConfigError, match=r"target speeds \[20, 25, 30\] m/s"):
        run_episodes(other_speeds, policy, 1, seed=0)
