"""``safelane reproduce --preset hidden-types``: agents × shields trained, tested and reported per scenario; the
expense of robustness; the learning curves; resumed after a crash, and from a folder of a table from before the
scenarios; the one-line errors. One seed, one learned agent and always-FASTER under the three shields in two
scenarios, two training and two (``dense``: one) test episodes: seconds once the kernels are compiled."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from safelane.cli import app
from safelane.config import ConfigError
from safelane.running.experiments import run_dir_of
from safelane.running.types_reproduction import (
    AGENTS,
    SCENARIO_SETS,
    SCENARIOS,
    SHIELDS,
    expense_of_robustness,
    make_types_spec,
    parse_names,
    run_table,
    types_run_dir,
)

runner = CliRunner()
ARGS = ["reproduce", "--preset", "hidden-types", "--quick", "--seeds", "1", "--methods", "paper,faster",
        "--episodes", "2", "--test-episodes", "2", "--scenarios", "paper,dense", "--scenario-seeds", "1",
        "--scenario-test-episodes", "1", "--workers", "1"]  # fmt: skip
ARMS = [f"{agent}.{shield}" for agent in ("paper", "faster") for shield in SHIELDS]
TEST_EPISODES = {"paper": 2, "dense": 1}


def summaries(out: Path, scenarios: tuple[str, ...] = ("paper", "dense")) -> dict[str, dict[str, object]]:
    """Each run's test summary, without its clock."""
    found = {}
    for scenario in scenarios:
        for arm in ARMS:
            agent, shield = arm.split(".")
            summary = json.loads((types_run_dir(out, scenario, agent, shield, 0) / "eval.json").read_text())["summary"]
            found[f"{scenario}/{arm}"] = {k: v for k, v in summary.items() if "time" not in k}
    return found


def test_table_writes_results_and_report_and_resumes(tmp_path: Path) -> None:
    out = tmp_path / "types"
    result = runner.invoke(app, [*ARGS, "--out", str(out)])
    assert result.exit_code == 0, result.output
    results = json.loads((out / "results.json").read_text())
    assert list(results["scenarios"]) == ["paper", "dense"]
    assert results["scenarios"]["dense"]["sets"] == list(SCENARIO_SETS["dense"])
    # paper's runs where a table from before the scenarios has them; another scenario's in its own folder.
    assert (run_dir_of(out, "paper.robust", 0) / "eval.json").is_file()
    assert (out / "runs" / "dense" / "faster.omniscient-s0" / "eval.json").is_file()
    assert json.loads((out / "runs" / "dense" / "paper.belief-s0" / "eval.json").read_text())["scenario"] == "dense"
    for scenario, n in TEST_EPISODES.items():
        check_scenario(results["scenarios"][scenario], n)
    report = (out / "report.md").read_text()
    assert "| shield | agent | runs | crashes / test episodes | crashes, true type ruled out |" in report
    assert "## Scenario `paper`" in report and "## Scenario `dense`" in report
    assert report.count("### The expense of robustness") == 2 and report.count("| `belief` | `faster` | 1 | ") == 2
    for scenario in TEST_EPISODES:
        assert f"](learning_curves_{scenario}.png)" in report
        assert (out / f"learning_curves_{scenario}.png").read_bytes()[:4] == b"\x89PNG"

    # Killed after one run's training, before its test: tested again from its checkpoint, the others kept.
    first = summaries(out)
    kept = (run_dir_of(out, "faster.belief", 0) / "eval.json").read_text()
    (run_dir_of(out, "paper.belief", 0) / "eval.json").unlink()
    (types_run_dir(out, "dense", "paper", "robust", 0) / "eval.json").unlink()
    (out / "results.json").unlink()
    spec = make_types_spec(**results["spec"])
    run_table(spec, out, workers=1)
    assert summaries(out) == first and (run_dir_of(out, "faster.belief", 0) / "eval.json").read_text() == kept
    # Another table in the same folder is refused.
    result = runner.invoke(app, [*ARGS[:-1], "1", "--test-episodes", "1", "--out", str(out)])
    assert result.exit_code == 2 and "another spec" in result.stderr

    # A folder of a table from before the scenarios (paper only, its spec.json without the scenarios' fields) resumes.
    earlier = tmp_path / "earlier"
    shutil.copytree(out / "runs", earlier / "runs", ignore=shutil.ignore_patterns("dense"))
    paper_only = make_types_spec(**{**results["spec"], "scenarios": ["paper"]})
    old_form = {k: v for k, v in paper_only.model_dump().items() if not k.startswith("scenario")}
    (earlier / "spec.json").write_text(json.dumps(old_form))
    collected = run_table(paper_only, earlier, workers=1)
    assert list(collected["scenarios"]) == ["paper"] and list(collected["scenarios"]["paper"]["arms"]) == ARMS
    for arm in ARMS:  # nothing run again
        evaluation = run_dir_of(out, arm, 0) / "eval.json"
        assert (run_dir_of(earlier, arm, 0) / "eval.json").read_text() == evaluation.read_text()
    assert json.loads((earlier / "spec.json").read_text())["scenarios"] == ["paper"]


def check_scenario(data: dict[str, Any], test_episodes: int) -> None:
    """One scenario's arms: their runs' rows, aggregates and the expense of robustness."""
    assert list(data["arms"]) == ARMS and data["test_episodes"] == test_episodes
    for name, arm in data["arms"].items():
        run = arm["per_seed"]["0"]
        assert run["episodes"] == test_episodes and 0 <= run["collisions"] <= test_episodes
        assert 0.0 <= run["fallback_rate"] <= 1.0 and 0.0 < run["mean_speed"] < 40.0
        assert (run["train_wall_time_s"] > 0) == name.startswith("paper.")
        # Only the belief shield counts the crashes with a ruled-out true type.
        assert (run["collisions_type_ruled_out"] is not None) == name.endswith(".belief")
        agg = arm["aggregate"]
        assert agg["test_episodes"] == test_episodes and agg["mean_speed"]["iqm"] == pytest.approx(run["mean_speed"])
    for agent in ("paper", "faster"):
        e = data["expense_of_robustness"][agent]
        speed = {s: data["arms"][f"{agent}.{s}"]["per_seed"]["0"]["mean_speed"] for s in SHIELDS}
        assert e["expense"]["point"] == pytest.approx(speed["omniscient"] - speed["robust"])
        assert e["belief_recovers"]["speed"] == pytest.approx(speed["belief"] - speed["robust"])


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--preset", "hidden-types", "--methods", "paper,dqn"], "--methods: unknown name 'dqn'; allowed"),
        (["--preset", "hidden-types", "--shields", "nominal"], "--shields: unknown name 'nominal'; allowed"),
        (["--preset", "hidden-types", "--shields", ","], "--shields: no name given"),
        (["--preset", "hidden-types", "--decisions", "5"], "--decisions: not with --preset hidden-types"),
        (["--preset", "hidden-types", "--confirm-on", "highway-env"], "--confirm-on: not with --preset hidden-types"),
        (["--preset", "hidden-types", "--episodes", "0"], "--episodes: must be >= 1"),
        (["--preset", "hidden-types", "--learner", "per-run"], "--learner: not with --preset hidden-types"),
        (["--preset", "hidden-types", "--gifs"], "--gifs: not with --preset hidden-types"),
        (["--preset", "hidden-types", "--scenarios", "paper,city"], "--scenarios: unknown name 'city'; allowed"),
        (["--preset", "hidden-types", "--scenarios", " , "], "--scenarios: no name given"),
        (["--preset", "hidden-types", "--scenario-seeds", "0"], "--scenario-seeds: must be >= 1"),
        (["--preset", "hidden-types", "--scenario-test-episodes", "0"], "--scenario-test-episodes: must be >= 1"),
        (["--shields", "robust"], "--shields: only with --preset hidden-types"),
        (["--scenarios", "dense"], "--scenarios: only with --preset hidden-types"),
        (["--scenario-seeds", "2"], "--scenario-seeds: only with --preset hidden-types"),
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
        ("paper", "faster", "robust", 0), ("paper", "random", "robust", 0),
        ("paper", "random", "robust", 1)]  # fmt: skip
    assert parse_names("all", SCENARIOS, "--scenarios") == ["paper", "dense", "aggressive", "rate3"]
    assert set(SCENARIO_SETS) == set(SCENARIOS) and SCENARIO_SETS["paper"] == ()
    spec = make_types_spec(scenarios=["dense", "paper"], seeds=[0, 1], scenario_seeds=[5], scenario_test_episodes=9,
                           agents=["faster", "paper"], shields=["belief"])  # fmt: skip
    assert spec.tasks() == [("dense", "faster", "belief", 5), ("dense", "paper", "belief", 5),
                            ("paper", "faster", "belief", 0), ("paper", "paper", "belief", 0),
                            ("paper", "paper", "belief", 1)]  # fmt: skip
    assert (spec.test_episodes_of("dense"), spec.test_episodes_of("paper")) == (9, 20)
    with pytest.raises(ConfigError, match=r"reproduce\.scenarios: .*unknown scenario 'city'"):
        make_types_spec(scenarios=["city"])
    # The planner: the first seed only (it is deterministic), under the robust and the omniscient mask only.
    assert make_types_spec(seeds=[0, 1], agents=["foresight"]).tasks() == [
        ("paper", "foresight", "robust", 0), ("paper", "foresight", "omniscient", 0)]  # fmt: skip


def test_the_foresight_ceiling_searches_under_the_types_masks(tmp_path: Path) -> None:
    """The planner under the robust mask reads every type, under the omniscient one the true types (the shields'
    readings), and stays inside the mask it searches under; it is refused the omniscient mask without a mixture."""
    import safelane
    from safelane.running.foresight import ForesightPlanner, planner_policy

    for mask, readings in (("robust", 3), ("omniscient", 1)):
        env = safelane.make_env("hidden-types", simulator="fast", **{"shield.mode": mask, "shield.override": True})
        planner = ForesightPlanner(env, mask=mask, horizon=2.0, beam=4)
        assert planner.shield is not None and planner.shield.types is not None and len(planner.shield.types) == 3
        policy = planner_policy(planner)
        obs, info = env.reset(seed=5)
        assert len(planner.shield.driver_readings(info["snapshot"])[0]) == readings
        for _ in range(4):
            action = policy(obs, info)
            assert info["action_mask"][action] or info.get("fallback", False)
            obs, _, done, cut, info = env.step(action)
            assert not info["shield_intervened"]
            if done or cut:
                break
        env.close()
    with pytest.raises(ConfigError, match=r"omniscient.*traffic\.driver_mix"):
        ForesightPlanner(safelane.make_env("fast", simulator="fast"), mask="omniscient")


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
