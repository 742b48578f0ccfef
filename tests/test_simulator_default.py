"""train and reproduce default to the fast simulator; a resumed run keeps the simulator it was trained on."""

from __future__ import annotations

import json
from pathlib import Path

import yaml
from typer.testing import CliRunner

from safelane.cli import app
from safelane.cli.common import training_simulator

runner = CliRunner()
TINY = ["--set", "env.duration=3", "--set", "env.vehicles_count=10", "--checkpoint-every", "1"]


def simulator_of(run: Path) -> str:
    return yaml.safe_load((run / "config.yaml").read_text())["env"]["simulator"]


def test_train_defaults_to_fast_and_resume_keeps_the_runs_simulator(tmp_path: Path) -> None:
    fast_run, reference_run = tmp_path / "fast", tmp_path / "reference"
    args = ["train", "--method", "qmask", "--episodes", "1", *TINY]
    assert runner.invoke(app, [*args, "--out", str(fast_run)]).exit_code == 0
    assert simulator_of(fast_run) == "fast"
    result = runner.invoke(app, [*args, "--out", str(reference_run), "--set", "simulator=highway-env"])
    assert result.exit_code == 0, result.output
    assert simulator_of(reference_run) == "highway-env"
    # Resuming with the same command line (no --simulator) continues on each run's own simulator.
    more = ["train", "--method", "qmask", "--episodes", "2", *TINY, "--resume"]
    for run, sim in ((fast_run, "fast"), (reference_run, "highway-env")):
        result = runner.invoke(app, [*more, "--out", str(run)])
        assert result.exit_code == 0, result.output
        assert simulator_of(run) == sim


def test_training_simulator_precedence() -> None:
    assert training_simulator([], None, None) == ["simulator=fast"]
    assert training_simulator(["a=1"], "highway-env", None) == ["a=1", "simulator=highway-env"]
    assert training_simulator(["simulator=highway-env"], None, None) == ["simulator=highway-env"]
    # an experiment directory from before the switch (no simulator= in its sets) stays on highway-env
    assert training_simulator([], None, ["env.duration=3"]) == ["simulator=highway-env"]
    assert training_simulator([], None, ["simulator=fast"]) == ["simulator=fast"]


def test_reproduce_defaults_to_fast(tmp_path: Path) -> None:
    args = ["reproduce", "--quick", "--methods", "robust", "--seeds", "1", "--episodes", "1", "--test-episodes", "1"]
    result = runner.invoke(app, [*args, "--no-gifs", "--out", str(tmp_path), "--set", "env.duration=3"])
    assert result.exit_code == 0, result.output
    spec = json.loads((tmp_path / "spec.json").read_text())
    assert spec["sets"][-1] == "simulator=fast"
    assert simulator_of(tmp_path / "runs" / "robust-s0") == "fast"


def test_reproduce_on_fast_renders_its_gifs_on_highway_env(tmp_path: Path) -> None:
    """make demo's path: runs trained on the fast simulator still get their episode GIFs (drawn by
    highway-env, which plays the same episode)."""
    args = ["reproduce", "--quick", "--methods", "robust", "--seeds", "1", "--episodes", "1", "--test-episodes", "1"]
    result = runner.invoke(app, [*args, "--out", str(tmp_path), "--set", "env.duration=3"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "episode_robust.gif").stat().st_size > 1000
