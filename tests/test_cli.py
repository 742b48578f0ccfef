"""The command line: in-process with typer's CliRunner, and as the installed ``safelane`` script."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from safelane import __version__
from safelane.cli import app

runner = CliRunner()

SUMMARY_FIELDS = {
    "episodes",
    "collisions",
    "collision_rate",
    "mean_speed",
    "mean_return",
    "mean_length",
    "time_to_collision",
    "shield_intervention_rate",
    "unsafe_action_rate",
    "fallback_rate",
    "collision_kinds",
    "policy",
    "shield",
    "preset",
    "seed",
    "wall_time_s",
}
SHORT = ["--set", "env.duration=3"]  # 3-decision episodes keep the CLI tests fast


def assert_one_error_line(stderr: str, starts: str) -> None:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith(f"error: {starts}"), lines[0]
    assert "Traceback" not in stderr


# --- basics -------------------------------------------------------------------------------------------------


def test_version() -> None:
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0
    assert result.stdout.strip() == f"safelane {__version__}"


def test_help_lists_the_commands() -> None:
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    for command in ("evaluate", "bench", "env"):
        assert command in result.stdout


def test_evaluate_help_documents_the_shared_options() -> None:
    result = runner.invoke(app, ["evaluate", "--help"])
    assert result.exit_code == 0
    for option in ("--policy", "--episodes", "--seed", "--preset", "--set", "--shield", "--json", "RUN_DIR"):
        assert option in result.stdout


# --- env show ---------------------------------------------------------------------------------------------


def test_env_show_applies_set() -> None:
    result = runner.invoke(app, ["env", "show", "--set", "env.lanes_count=5", "--set", "reward.c=2"])
    assert result.exit_code == 0, result.output
    shown = yaml.safe_load(result.stdout)
    assert shown["env"]["lanes_count"] == 5
    assert shown["env"]["vehicles_count"] == 50
    assert shown["reward"]["c"] == 2.0


def test_env_show_preset_and_shield() -> None:
    result = runner.invoke(app, ["env", "show", "--preset", "paper", "--shield", "robust"])
    assert result.exit_code == 0, result.output
    shown = yaml.safe_load(result.stdout)
    assert shown["preset"] == "paper" and shown["env_id"] == "highway-v0"
    assert shown["shield"]["mode"] == "robust"


# --- errors: one line, exit code 2, no traceback -------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "starts"),
    [
        (["env", "show", "--set", "env.lanes_count=banana"], "env.lanes_count: expected positive integer"),
        (["env", "show", "--set", "env.lanes_countt=3"], "env.lanes_countt: unknown highway-env key"),
        (["env", "show", "--set", "lanes_count"], "--set 'lanes_count': expected KEY=VALUE"),
        (["env", "show", "--preset", "fastest"], "preset: unknown preset 'fastest'; allowed: fast, paper"),
        (["env", "show", "--shield", "strict"], "--shield: unknown shield 'strict'; allowed: none, nominal, robust"),
        (["evaluate", "--policy", "slower", "--set", "env.lanes_count=banana"], "env.lanes_count"),
        (["evaluate", "--policy", "slower", "--episodes", "0"], "--episodes: must be >= 1 (got 0)"),
        (["evaluate", "--policy", "slower", "--episodes", "-3"], "--episodes: must be >= 1 (got -3)"),
        (["evaluate", "--policy", "slower", "--seed", "-1"], "--seed: must be >= 0"),
        (["evaluate", "--policy", "fastest"], "--policy: unknown policy 'fastest'; allowed: random, idle, faster"),
        (["evaluate"], "evaluate: give --policy"),
        (["evaluate", "runs/dqn", "--policy", "idle"], "evaluate: give either RUN_DIR or --policy, not both"),
        (["evaluate", "--policy", "idle", "--set", "reward.v_max=-10"], "reward.v_max: must be greater than"),
        (["bench", "--episodes", "0"], "--episodes: must be >= 1"),
        (["bench", "--shield", "none"], "--shield: bench measures a shield; allowed: nominal, robust"),
        (["bench", "--methods", "dqn,ppo"], "--methods: got 'dqn,ppo'; allowed: dqn, constrained, qmask, robust"),
    ],
)
def test_bad_input_is_one_error_line(args: list[str], starts: str) -> None:
    result = runner.invoke(app, args)
    assert result.exit_code == 2
    assert result.stdout == ""
    assert_one_error_line(result.stderr, starts)
    assert result.exception is None or isinstance(result.exception, SystemExit)


# --- evaluate -------------------------------------------------------------------------------------------------


def test_evaluate_json_is_one_object_on_stdout() -> None:
    result = runner.invoke(app, ["evaluate", "--policy", "idle", "--episodes", "2", "--seed", "4", "--json", *SHORT])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert set(summary) >= SUMMARY_FIELDS
    assert summary["episodes"] == 2 and summary["seed"] == 4 and summary["policy"] == "idle"
    assert summary["shield"] == "none"
    assert len(summary["time_to_collision"]) == 2
    assert set(summary["collision_kinds"]) == {"ego_hit_front", "rear_ended", "side"}


def test_evaluate_is_deterministic() -> None:
    args = ["evaluate", "--policy", "random", "--episodes", "2", "--seed", "1", "--json", *SHORT]
    first, second = (json.loads(runner.invoke(app, args).stdout) for _ in range(2))
    first.pop("wall_time_s"), second.pop("wall_time_s")
    assert first == second


def test_evaluate_with_a_shield_overrides_a_fixed_policy() -> None:
    args = ["evaluate", "--policy", "faster", "-n", "1", "--shield", "robust", "--json", "--set", "env.duration=8"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["shield"] == "robust" and summary["override"] is True
    assert 0.0 < summary["shield_intervention_rate"] <= 1.0
    assert 0.0 <= summary["fallback_rate"] <= 1.0
    # With the override on, every unsafe choice is replaced: the two rates agree.
    assert summary["unsafe_action_rate"] == summary["shield_intervention_rate"]


def test_evaluate_respects_an_explicit_override_setting() -> None:
    args = ["evaluate", "--policy", "faster", "-n", "1", "--shield", "nominal", "--json"]
    result = runner.invoke(app, [*args, "--set", "shield.override=false", *SHORT])
    summary = json.loads(result.stdout)
    assert summary["override"] is False
    assert summary["shield_intervention_rate"] == 0.0


def test_evaluate_prints_a_table_without_json() -> None:
    result = runner.invoke(app, ["evaluate", "--policy", "slower", "--episodes", "1", *SHORT])
    assert result.exit_code == 0, result.output
    for row in ("collision_rate", "mean_speed", "time_to_collision", "shield_intervention_rate"):
        assert row in result.stdout


# --- bench ----------------------------------------------------------------------------------------------------


def test_bench_json(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # The report's figures, noise and regressions, not the rates: two batch sizes, short batched samples.
    monkeypatch.setattr("safelane.running.bench.BATCH_SIZES", (1, 64))
    monkeypatch.setattr("safelane.running.bench.BATCH_DECISIONS", 300)
    monkeypatch.setattr("safelane.running.bench.SHARE_DECISIONS", 300)
    # A published run far faster than any machine (and one figure it lacks): bench lists the regression.
    published = tmp_path / "published.json"
    published.write_text(json.dumps({"fast_decisions_per_s": 1e12, "shield_mask_us_mean_fast": 1e-6}))
    args = ["bench", "--episodes", "1", "--methods", "robust,constrained", "--baseline", str(published), "--json"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)
    assert out["baseline"] == str(published)
    # The mask's cost rose beyond any noise; the rate fell below 1e12 × (1 − noise) unless this busy run measured
    # a spread of 100 % or more (then no drop is beyond its noise).
    flagged = {r["figure"] for r in out["regressions"]}
    assert "shield_mask_us_mean_fast" in flagged
    assert ("fast_decisions_per_s" in flagged) == (out["noise"]["fast_decisions_per_s"] < 1)
    assert flagged <= {"fast_decisions_per_s", "shield_mask_us_mean_fast"}
    # every compared figure has its noise (a busy machine may measure a spread beyond 100 %)
    assert set(out["noise"]) >= {"fast_decisions_per_s", "shield_mask_us_mean_fast", "train_batched_steps_per_s.40"}
    assert all(noise >= 0 for noise in out["noise"].values())
    assert out["train_method"] == "robust" and "agent_overhead_fraction_robust" not in out
    assert 0 < out["agent_overhead_fraction_constrained"] < 1 and out["agent_ms_per_decision_constrained"] > 0
    for key in (
        "env_steps_per_s",
        "shielded_env_steps_per_s",
        "shield_mask_us_median",
        "obs_us_median",
        "highway_env_steps_per_s",
        "agent_ms_per_decision",
        "train_steps_per_s",
        "snapshot_us_median",
        "highway_env_decisions_per_s",
        "fast_decisions_per_s",
    ):
        assert out[key] > 0
    assert 0 < out["agent_overhead_fraction"] < 1
    assert out["neighbour_search_speedup"] == pytest.approx(out["env_steps_per_s"] / out["highway_env_steps_per_s"])
    assert out["shield_overhead_ratio"] == pytest.approx(out["shielded_env_steps_per_s"] / out["env_steps_per_s"])
    assert out["preset"] == "fast" and out["shield"] == "robust"
    assert out["fast_raw_speedup"] == pytest.approx(out["fast_decisions_per_s"] / out["highway_env_decisions_per_s"])
    assert out["fast_raw_speedup"] > 10  # measured ≈ 10² or more; a regression to Python speed fails here
    assert ("envpool_decisions_per_s" in out) == (importlib.util.find_spec("envpool") is not None)
    assert out["fast_speedup"] == pytest.approx(
        out["fast_shielded_decisions_per_s"] / out["highway_env_decisions_per_s"]
    )
    assert 0 < out["shield_mask_us_median_fast"] <= out["shield_mask_us_p99_fast"]
    assert out["shield_mask_us_mean_fast"] > 0
    # the committed mode's decision beside the robust mask's, on the same states
    for who in ("committed", "committed_robust"):
        assert 0 < out[f"{who}_mask_us_median_fast"] <= out[f"{who}_mask_us_p99_fast"]
    assert out["committed_mask_ratio_fast"] == pytest.approx(
        out["committed_mask_us_mean_fast"] / out["committed_robust_mask_us_mean_fast"]
    )
    assert out["committed_mask_decisions"] >= 1
    assert set(out["fast_batched_decisions_per_s"]) == {"1", "64"}
    assert all(rate > 0 for rate in out["fast_batched_decisions_per_s"].values())
    for n, rate in out["fast_batched_decisions_per_s"].items():
        assert out["fast_batched_speedup"][n] == pytest.approx(rate / out["highway_env_decisions_per_s"])
    assert set(out["fast_batched_threaded_decisions_per_s"]) == {"1", "64"}
    assert out["fast_batched_threads"] >= 1 and set(out["fast_batched_threaded_speedup"]) == {"1", "64"}
    assert 0 < out["shield_mask_share_fast"] < 1 and out["batched_shield_share"] < 1
    for key in ("train_steps_per_s_fast", "agent_ms_per_decision_fast", "train_steps_per_s_constrained_fast"):
        assert out[key] > 0
    assert set(out["train_batched_steps_per_s"]) == set(out["train_batched_speedup"]) == {"10", "40"}
    assert all(rate > 0 for rate in out["train_batched_steps_per_s"].values())


def test_bench_baseline_that_cannot_be_read_is_a_one_line_error_before_measuring(tmp_path: Path) -> None:
    for bad in (tmp_path / "missing.json", tmp_path):
        result = runner.invoke(app, ["bench", "--episodes", "1", "--baseline", str(bad)])
        assert result.exit_code == 2
        assert "--baseline" in result.output and "none" in result.output and "Traceback" not in result.output


# --- sim check ---------------------------------------------------------------------------------------------


def test_sim_check_json_reports_trajectories_and_tests() -> None:
    args = ["sim", "check", "--episodes", "3", "--stat-episodes", "2", "--seed", "5", "--json"]
    result = runner.invoke(app, [*args, "--set", "env.duration=6"])
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)
    assert out["episodes"] == 3 and out["trajectory_match_fraction"] == 1.0 and out["divergences"] == []
    policies = ("random", "idle", "slower", "faster", "robust_random")
    metrics = ("collision_rate", "mean_speed")
    assert {(t["policy"], t["metric"]) for t in out["tests"]} == {(p, m) for p in policies for m in metrics}
    assert all(0 < t["p_value"] <= t["p_value_holm"] <= 1 for t in out["tests"])
    assert out["replay_episodes"] == 5 * 2 and out["replay_identical_fraction"] == 1.0
    continuous = out["continuous"]  # the same check with a ContinuousAction ego
    assert continuous["action"] == {"type": "ContinuousAction"} and continuous["divergences"] == []
    assert continuous["trajectory_match_fraction"] == continuous["snapshot_equal_fraction"] == 1.0
    continuous_policies = ("uniform", "random_throttle", "full_throttle")
    assert {(t["policy"], t["metric"]) for t in continuous["tests"]} == {
        (p, m) for p in continuous_policies for m in metrics
    }
    assert continuous["replay_episodes"] == 3 * 2 and continuous["replay_identical_fraction"] == 1.0


def test_sim_check_records_units_and_resumes_after_a_kill(tmp_path: Path) -> None:
    """With --record every finished unit is on disk at once; a re-run with the file plays nothing again
    and gives the same JSON as a check without it; a record of another configuration is refused."""
    record = tmp_path / "check.jsonl"
    args = ["sim", "check", "--episodes", "2", "--stat-episodes", "2", "--seed", "3", "--json"]
    args += ["--set", "env.duration=4"]
    first = runner.invoke(app, [*args, "--record", str(record), "--workers", "2"])
    assert first.exit_code == 0, first.output
    lines = record.read_text().splitlines()
    # header, 2 trajectories, 5 policies x 2 simulators, 5 replays; the same for the 3 continuous policies
    assert len(lines) == 1 + 2 + 2 * 5 + 5 + 2 + 2 * 3 + 3
    # A kill in the middle of writing the last line: the cut line is dropped and its unit played again.
    record.write_text("\n".join(lines[:-1]) + "\n" + lines[-1][:10])
    again = runner.invoke(app, [*args, "--record", str(record)])
    assert again.exit_code == 0, again.output
    plain = runner.invoke(app, args)
    a, b, c = (json.loads(r.stdout) for r in (first, again, plain))
    assert b["units_resumed"] == len(lines) - 2 and c["units_resumed"] == 0
    for key in ("trajectory_match_fraction", "divergences", "tests", "mean_length"):
        assert a[key] == b[key] == c[key]
    other = runner.invoke(app, [*args[:-1], "env.duration=5", "--record", str(record)])
    assert other.exit_code == 2 and "--record" in other.output and "Traceback" not in other.output


def test_sim_check_names_a_divergence(monkeypatch: pytest.MonkeyPatch) -> None:
    """A deliberately different configuration on the fast side (one vehicle fewer) is caught at the
    reset: the check can fail."""
    from safelane.config import load_config
    from safelane.running import simcheck

    cfg = load_config("fast", sets=["env.duration=3"])
    original = simcheck.on_simulator

    def skewed(c: object, sim: str, policy: str) -> object:  # the fast side gets one vehicle fewer
        data = original(c, sim, policy)
        if sim == "fast":
            return data.model_copy(update={"env": {**data.env, "vehicles_count": 49}})
        return data

    monkeypatch.setattr(simcheck, "on_simulator", skewed)
    found = simcheck.compare_episode(cfg, 0, "random")
    assert found is not None and found.first_step == 0 and "bodies" in found.cause


# --- the installed script, as a user runs it ---------------------------------------------------------------


def _run(exe: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    return subprocess.run([str(exe), *args], capture_output=True, text=True, env=env, timeout=120, check=False)


def test_script_evaluate_json(safelane_exe: Path) -> None:
    proc = _run(safelane_exe, "evaluate", "--policy", "slower", "--episodes", "3", "--seed", "0", "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert set(summary) >= SUMMARY_FIELDS
    assert summary["episodes"] == 3
    assert summary["collisions"] == summary["collision_kinds"]["ego_hit_front"] + sum(
        summary["collision_kinds"][k] for k in ("rear_ended", "side")
    )
    assert summary["time_to_collision"] == [None, None, None]  # always SLOWER stops safely
    assert summary["mean_length"] == 40


def test_script_bad_value_is_one_line_without_traceback(safelane_exe: Path) -> None:
    proc = _run(safelane_exe, "evaluate", "--policy", "slower", "--set", "env.lanes_count=banana")
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert_one_error_line(proc.stderr, "env.lanes_count: expected positive integer")


def test_script_version(safelane_exe: Path) -> None:
    proc = _run(safelane_exe, "--version")
    assert proc.returncode == 0
    assert proc.stdout.strip() == f"safelane {__version__}"


def test_stress_on_the_fast_simulator_skips_what_it_does_not_model() -> None:
    args = ["stress", "--policy", "random", "--simulator", "fast", "--episodes", "1", "--json"]
    only = ["--only", "training", "--only", "vehicles_behind_15", "--only", "adversary_hard_brake"]
    result = runner.invoke(app, [*args, *only])
    assert result.exit_code == 0, result.output
    training, behind, adversary = json.loads(result.stdout)["conditions"]
    assert training["simulator"] == "fast" and training["episodes"] == 1
    assert behind["simulator"] == "fast" and behind["episodes"] == 1 and "skipped" not in behind
    assert "traffic.adversary: 'brake' not supported by simulator=fast" in adversary["skipped"]


def test_sim_check_warns_in_one_line_when_numpy_is_not_libm(monkeypatch: pytest.MonkeyPatch) -> None:
    """On a CPU where numpy's tan/arctan are not libm's the trajectories cannot be identical: say so."""
    import safelane.sim.fast.libm as libm

    monkeypatch.setattr(libm, "numpy_matches_libm", lambda: False)
    args = ["sim", "check", "--episodes", "1", "--stat-episodes", "0", "--workers", "1", "--json"]
    result = runner.invoke(app, [*args, "--set", "env.duration=2"])
    assert result.exit_code == 0, result.output
    lines = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert len(lines) == 1 and "NPY_DISABLE_CPU_FEATURES" in lines[0]
