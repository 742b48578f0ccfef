"""``safelane reproduce --preset hidden-types``: agents × shields trained, tested and reported; the expense of
robustness; resumed after a crash; the one-line errors. One seed, one learned agent and always-FASTER under the
three shields, two training and two test episodes: seconds once the kernels are compiled."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from safelane.cli import app
from safelane.config import ConfigError
from safelane.running.experiments import run_dir_of
from safelane.running.types_reproduction import (
    AGENTS,
    SHIELDS,
    expense_of_robustness,
    make_types_spec,
    parse_names,
    run_table,
)

runner = CliRunner()
ARGS = ["reproduce", "--preset", "hidden-types", "--quick", "--seeds", "1", "--methods", "paper,faster",
        "--episodes", "2", "--test-episodes", "2", "--workers", "1"]  # fmt: skip
ARMS = [f"{agent}.{shield}" for agent in ("paper", "faster") for shield in SHIELDS]


def summaries(out: Path) -> dict[str, dict[str, object]]:
    """Each run's test summary, without its clock."""
    found = {}
    for arm in ARMS:
        summary = json.loads((run_dir_of(out, arm, 0) / "eval.json").read_text())["summary"]
        found[arm] = {k: v for k, v in summary.items() if "time" not in k}
    return found


def test_table_writes_results_and_report_and_resumes(tmp_path: Path) -> None:
    out = tmp_path / "types"
    result = runner.invoke(app, [*ARGS, "--out", str(out)])
    assert result.exit_code == 0, result.output
    results = json.loads((out / "results.json").read_text())
    assert list(results["arms"]) == ARMS
    for name, data in results["arms"].items():
        run = data["per_seed"]["0"]
        assert run["episodes"] == 2 and 0 <= run["collisions"] <= 2
        assert 0.0 <= run["fallback_rate"] <= 1.0 and 0.0 < run["mean_speed"] < 40.0
        assert (run["train_wall_time_s"] > 0) == name.startswith("paper.")
        # Only the belief shield counts the crashes with a ruled-out true type.
        assert (run["collisions_type_ruled_out"] is not None) == name.endswith(".belief")
        agg = data["aggregate"]
        assert agg["test_episodes"] == 2 and agg["mean_speed"]["iqm"] == pytest.approx(run["mean_speed"])
    for agent in ("paper", "faster"):
        e = results["expense_of_robustness"][agent]
        speed = {s: results["arms"][f"{agent}.{s}"]["per_seed"]["0"]["mean_speed"] for s in SHIELDS}
        assert e["expense"]["point"] == pytest.approx(speed["omniscient"] - speed["robust"])
        assert e["belief_recovers"]["speed"] == pytest.approx(speed["belief"] - speed["robust"])
    report = (out / "report.md").read_text()
    assert "| shield | agent | runs | crashes / test episodes | crashes, true type ruled out |" in report
    assert "| `belief` | `faster` | 1 | " in report and "## The expense of robustness" in report

    # Killed after one run's training, before its test: tested again from its checkpoint, the others kept.
    first = summaries(out)
    kept = (run_dir_of(out, "faster.belief", 0) / "eval.json").read_text()
    (run_dir_of(out, "paper.belief", 0) / "eval.json").unlink()
    (out / "results.json").unlink()
    spec = make_types_spec(**results["spec"])
    run_table(spec, out, workers=1)
    assert summaries(out) == first and (run_dir_of(out, "faster.belief", 0) / "eval.json").read_text() == kept
    # Another table in the same folder is refused.
    result = runner.invoke(app, [*ARGS[:-4], "--test-episodes", "1", "--workers", "1", "--out", str(out)])
    assert result.exit_code == 2 and "another spec" in result.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--preset", "hidden-types", "--methods", "paper,dqn"], "--methods: unknown name 'dqn'; allowed"),
        (["--preset", "hidden-types", "--shields", "nominal"], "--shields: unknown name 'nominal'; allowed"),
        (["--preset", "hidden-types", "--shields", ","], "--shields: none given"),
        (["--preset", "hidden-types", "--decisions", "5"], "--decisions: not with --preset hidden-types"),
        (["--preset", "hidden-types", "--confirm-on", "highway-env"], "--confirm-on: not with --preset hidden-types"),
        (["--preset", "hidden-types", "--episodes", "0"], "--episodes: must be >= 1"),
        (["--preset", "hidden-types", "--learner", "per-run"], "--learner: not with --preset hidden-types"),
        (["--preset", "hidden-types", "--gifs"], "--gifs: not with --preset hidden-types"),
        (["--shields", "robust"], "--shields: only with --preset hidden-types"),
    ],
)
def test_bad_input_is_one_line(tmp_path: Path, args: list[str], message: str) -> None:
    result = runner.invoke(app, ["reproduce", *args, "--out", str(tmp_path / "x")])
    assert result.exit_code == 2 and message in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_names() -> None:
    assert parse_names(None, AGENTS, "--methods") == list(AGENTS)
    assert parse_names("all", SHIELDS, "--shields") == ["robust", "belief", "omniscient"]
    assert parse_names("belief, belief,robust", SHIELDS, "--shields") == ["belief", "robust"]
    with pytest.raises(ConfigError, match="allowed with --preset hidden-types: paper, paper-stack"):
        parse_names("sac", AGENTS, "--methods")
    assert make_types_spec(seeds=[0, 1], agents=["faster", "random"], shields=["robust"]).tasks() == [
        ("faster", "robust", 0), ("random", "robust", 0), ("random", "robust", 1)]  # fmt: skip


def test_expense_of_robustness() -> None:
    seeds = [str(k) for k in range(6)]
    speeds = {
        "robust": dict.fromkeys(seeds, 20.0),
        "belief": dict(zip(seeds, [20.5, 20.5, 20.5, 20.5, 20.5, 20.5], strict=True)),
        "omniscient": dict(zip(seeds, [21.0, 21.0, 21.0, 21.0, 21.0, 21.0], strict=True)),
    }
    e = expense_of_robustness(speeds)
    assert e is not None and e["seeds"] == 6
    assert e["expense"]["point"] == pytest.approx(1.0) and e["expense"]["ci95"] == pytest.approx([1.0, 1.0])
    assert e["belief_recovers"]["share"] == pytest.approx(0.5)
    assert e["belief_recovers"]["speed"] == pytest.approx(0.5)
    assert expense_of_robustness({"robust": speeds["robust"], "belief": speeds["belief"]}) is None
    without_belief = expense_of_robustness({"robust": speeds["robust"], "omniscient": speeds["omniscient"]})
    assert without_belief is not None and "belief_recovers" not in without_belief
