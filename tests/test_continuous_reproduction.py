"""``safelane reproduce --actions continuous``: arms × seeds trained, tested and reported; resumed after a crash;
the one-line errors. One seed, two arms, a few hundred decisions: seconds."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from typer.testing import CliRunner

from safelane.cli import app
from safelane.config import ConfigError
from safelane.running.continuous_reproduction import (
    ARMS,
    CURVE_POINTS,
    make_continuous_spec,
    parse_arms,
    run_comparison,
)
from safelane.running.experiments import run_dir_of

runner = CliRunner()
ARGS = ["reproduce", "--actions", "continuous", "--quick", "--seeds", "1", "--methods", "sac,sac-projection",
        "--decisions", "200", "--test-episodes", "3", "--workers", "1"]  # fmt: skip


def summaries(out: Path) -> dict[str, dict[str, object]]:
    """Each run's test summary, without its clock."""
    found = {}
    for arm in ("sac", "sac-projection"):
        summary = json.loads((run_dir_of(out, arm, 0) / "eval.json").read_text())["summary"]
        found[arm] = {k: v for k, v in summary.items() if "time" not in k}
    return found


def test_comparison_writes_results_table_and_curves_and_resumes(tmp_path: Path) -> None:
    out = tmp_path / "cmp"
    result = runner.invoke(app, [*ARGS, "--out", str(out)])
    assert result.exit_code == 0, result.output
    results = json.loads((out / "results.json").read_text())
    assert list(results["arms"]) == ["sac", "sac-projection"]
    for data in results["arms"].values():
        run = data["per_seed"]["0"]
        assert run["episodes"] == 3 and 0 <= run["collisions"] + run["off_road"] <= 3
        for key in ("collision_rate", "off_road_rate"):
            assert 0.0 <= run[key] <= 1.0
        assert 0.0 <= run["mean_speed"] < 50.0 and run["train_wall_time_s"] > 0 and run["training_episodes"] >= 1
        curve = run["learning_curve"]
        assert len(curve["decisions"]) == len(curve["return"]) == CURVE_POINTS and curve["decisions"][-1] == 200
        assert all(0.0 <= f <= 1.0 for f in curve["failure_rate"])
        agg = data["aggregate"]
        assert agg["test_episodes"] == 3 and agg["mean_speed"]["iqm"] == pytest.approx(run["mean_speed"])
        assert agg["mean_speed"]["ci95"][0] <= agg["mean_speed"]["iqm"] <= agg["mean_speed"]["ci95"][1]
    assert results["arms"]["sac"]["per_seed"]["0"]["intervention_rate"] is None
    shielded = results["arms"]["sac-projection"]["per_seed"]["0"]
    assert 0.0 <= shielded["intervention_rate"] <= 1.0 and math.isfinite(shielded["mean_length"])
    report = (out / "report.md").read_text()
    assert "| arm | runs | crashes / test episodes |" in report and "| `sac-projection` | 1 | " in report
    arms = results["arms"]
    assert arms["sac-projection"]["aggregate"]["lapses"] >= 0 and "lapses" not in arms["sac"]["aggregate"]
    assert (out / "learning_curves.png").stat().st_size > 1000

    # Killed after training, before its test: the run is tested again from its checkpoint, the other kept.
    first, kept = summaries(out), (run_dir_of(out, "sac-projection", 0) / "eval.json").read_text()
    (run_dir_of(out, "sac", 0) / "eval.json").unlink()
    (out / "results.json").unlink()
    spec = make_continuous_spec(**results["spec"])
    run_comparison(spec, out, workers=1)
    assert summaries(out) == first and (run_dir_of(out, "sac-projection", 0) / "eval.json").read_text() == kept
    # Killed before its first checkpoint: trained again from scratch, to the same numbers.
    for name in ("eval.json", "checkpoint.pt"):
        (run_dir_of(out, "sac-projection", 0) / name).unlink()
    run_comparison(spec, out, workers=1)
    assert summaries(out) == first
    # Another comparison in the same folder is refused.
    result = runner.invoke(app, [*ARGS[:-6], "--test-episodes", "2", "--workers", "1", "--out", str(out)])
    assert result.exit_code == 2 and "--out" in result.stderr and "another spec" in result.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--actions", "continuous", "--methods", "sac,sack"], "--methods: unknown arm 'sack'; allowed"),
        (["--actions", "continuous", "--episodes", "5"], "--episodes: not with --actions continuous"),
        (["--actions", "continuous", "--learner", "batched"], "--learner: not with --actions continuous"),
        (["--actions", "continuous", "--gifs"], "--gifs: not with --actions continuous"),
        (["--actions", "continuous", "--decisions", "0"], "--decisions: must be >= 1"),
        (["--decisions", "100"], "--decisions: only with --actions continuous"),
        (["--actions", "sideways"], "--actions: got 'sideways'; allowed"),
    ],
)
def test_bad_input_is_one_line(tmp_path: Path, args: list[str], message: str) -> None:
    result = runner.invoke(app, ["reproduce", *args, "--out", str(tmp_path / "x")])
    assert result.exit_code == 2 and message in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_arms() -> None:
    assert parse_arms(None) == ["sac", "ppo", "sac-lagrangian", "sac-projection", "sac-replacement", "sac-penalty"]
    assert parse_arms("all") == list(ARMS) and "ppo-replacement" in ARMS
    assert parse_arms("ppo, ppo") == ["ppo"]
    with pytest.raises(ConfigError, match="allowed with --actions continuous: sac, ppo"):
        parse_arms("dqn")
