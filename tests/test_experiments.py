"""Experiment runner, report and stress suite on tiny budgets (real highway-env, real torch)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from safelane.config import ConfigError
from safelane.running.conditions import load_conditions
from safelane.running.experiments import make_spec, run_dir_of, run_experiment
from safelane.running.policies import fixed_policy
from safelane.running.reproduction_report import write_report
from safelane.running.stress import run_condition

TINY = ["env.duration=4", "env.vehicles_count=15"]


def tiny_spec(**kw: object) -> object:
    fields = dict(methods=["qmask", "robust"], seeds=[0], episodes=2, test_episodes=2, sets=TINY, quick=True)
    fields.update(kw)
    return make_spec(**fields)


def test_reproduce_writes_report_and_resumes_without_duplicates(tmp_path: Path) -> None:
    spec = tiny_spec(stress_conditions=["vehicles_behind_15"], stress_episodes=1)
    first = run_experiment(spec, tmp_path, workers=1)
    assert set(first["methods"]) == {"qmask", "robust"}
    assert len(first["episodes"]) == 2 * 2
    report = write_report(tmp_path)
    text = report.read_text()
    assert "Table 4" in text and "claims" in text
    assert "Generalisation" in text and "vehicles_behind_15" in text
    for fig in ("fig6.png", "fig7.png", "speed_vs_safety.png"):
        assert (tmp_path / fig).stat().st_size > 1000
    # A crash after one run finished: its evaluation is kept, the other run is redone, nothing doubles.
    (run_dir_of(tmp_path, "robust", 0) / "eval.json").unlink()
    (tmp_path / "results.json").unlink()
    kept = (run_dir_of(tmp_path, "qmask", 0) / "eval.json").read_text()
    second = run_experiment(spec, tmp_path, workers=1)
    assert (run_dir_of(tmp_path, "qmask", 0) / "eval.json").read_text() == kept
    assert len(second["episodes"]) == len(first["episodes"])
    strip = [{k: v for k, v in e.items()} for e in second["episodes"]]
    assert sorted(json.dumps(e, sort_keys=True) for e in strip) == sorted(
        json.dumps(e, sort_keys=True) for e in first["episodes"]
    )


def test_unwritable_output_is_one_clear_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(ConfigError, match="not writable"):
        run_experiment(tiny_spec(), blocker / "out", workers=1)


def test_spec_rejects_bad_input() -> None:
    with pytest.raises(ConfigError, match="episodes"):
        make_spec(episodes=0)
    with pytest.raises(ConfigError, match="methods"):
        make_spec(methods=["dqn", "magic"])


def test_stress_suite_has_enough_conditions() -> None:
    conditions = load_conditions()
    assert len([c for c in conditions if not c.adversarial]) >= 10
    assert {c.name for c in conditions if c.adversarial} >= {
        "adversary_hard_brake",
        "adversary_cut_in",
        "adversary_stopped_car",
        "adversary_cut_in_mobil",
    }


def test_stress_condition_record(tmp_path: Path) -> None:
    rec = run_condition("vehicles_behind_15", fixed_policy("faster"), 1, shield="robust", sets=["env.duration=4"])
    for key in (
        "name",
        "adversarial",
        "episodes",
        "collisions",
        "collision_rate",
        "collision_rate_ci95",
        "mean_speed",
        "shield_intervention_rate",
        "collision_kinds",
    ):
        assert key in rec
    assert rec["episodes"] == 1 and rec["collision_rate_ci95"][0] == 0.0


def test_stress_traffic_seed_draws_fresh_episodes_and_zero_keeps_the_published_ones(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``safelane stress --seed N``: seed 0, the default, resets a condition's episodes with STRESS_SEED_BASE + k as
    always; seed 1 starts them 10¹⁰ further and plays other traffic (the random policy seeded alike); the suite's
    result records the seed; a negative seed is a one-line error."""
    import safelane.running.evaluation as evaluation
    from safelane.running.conditions import TRAFFIC_SEED_STRIDE
    from safelane.running.stress import STRESS_SEED_BASE, run_stress

    seeds: list[int] = []
    real = evaluation.run_config

    def spy(config: object, policy: object, episodes: int, seed: int, *args: object, **kwargs: object) -> object:
        seeds.append(seed)
        return real(config, policy, episodes, seed, *args, **kwargs)

    monkeypatch.setattr(evaluation, "run_config", spy)
    condition = [c for c in load_conditions() if c.name == "vehicles_behind_15"]
    sets = ["env.duration=4", "simulator=fast"]
    default = run_stress(lambda: fixed_policy("random", 0), 2, conditions=condition, sets=sets)
    seeded = run_stress(lambda: fixed_policy("random", 1), 2, conditions=condition, sets=sets, seed=1)
    assert seeds == [STRESS_SEED_BASE, STRESS_SEED_BASE + TRAFFIC_SEED_STRIDE]
    assert (default["seed"], seeded["seed"]) == (0, 1)
    assert default["conditions"][0]["mean_speed"] != seeded["conditions"][0]["mean_speed"]
    with pytest.raises(ConfigError, match="--seed: must be >= 0"):
        run_condition(condition[0], fixed_policy("idle"), 1, seed=-1)


def test_stress_bad_conditions_file(tmp_path: Path) -> None:
    bad = tmp_path / "c.yaml"
    bad.write_text("- name: x\n  preset: fast\n  sets: {}\n  colour: red\n")
    with pytest.raises(ConfigError, match="item 0"):
        load_conditions(bad)
    with pytest.raises(ConfigError, match="unknown 'nope'"):
        run_condition("nope", fixed_policy("idle"), 1)


def test_reproduce_killed_mid_run_resumes_without_loss_or_duplicates(tmp_path: Path) -> None:
    """SIGKILL the real CLI after its first run finished, run it again: nothing lost, nothing twice."""
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "rep"
    exe = Path(sys.executable).with_name("safelane")
    args = [
        str(exe),
        "reproduce",
        "--seeds",
        "1",
        "--episodes",
        "2",
        "--test-episodes",
        "2",
        "--workers",
        "1",
        "--no-gifs",
        "--out",
        str(out),
        "--set",
        "env.duration=3",
        "--set",
        "env.vehicles_count=10",
    ]
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    proc = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    first = run_dir_of(out, "dqn", 0) / "eval.json"
    deadline = time.time() + 240
    while not first.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.2)
    assert first.exists()
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    kept = first.read_text()
    assert not (out / "results.json").exists()
    done = subprocess.run(args, env=env, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr
    results = json.loads((out / "results.json").read_text())
    assert first.read_text() == kept
    keys = [(e["method"], e["seed"], e["test_episode"]) for e in results["episodes"]]
    assert sorted(keys) == sorted({(m, 0, k) for m in ("dqn", "constrained", "qmask", "robust") for k in range(2)})


def test_confirm_on_highway_env_replays_fast_trained_agents_identically(tmp_path: Path) -> None:
    """Trained on the fast simulator, confirmed on highway-env: the same test episodes come out (the
    simulators are the same bit for bit), the report shows both side by side, and asking for the
    confirmation after the run had finished adds it without retraining."""
    spec = tiny_spec(methods=["robust"], sets=[*TINY, "simulator=fast"])
    run_experiment(spec, tmp_path, workers=1)
    eval_path = run_dir_of(tmp_path, "robust", 0) / "eval.json"
    assert "confirm" not in json.loads(eval_path.read_text())
    results = run_experiment(
        tiny_spec(methods=["robust"], sets=[*TINY, "simulator=fast"], confirm_on="highway-env"), tmp_path, workers=1
    )
    confirm = results["methods"]["robust"]["aggregate"]["confirm"]
    assert confirm["simulator"] == "highway-env" and confirm["test_episodes"] == 2
    assert json.loads(eval_path.read_text())["confirm"]["summary"]["simulator"] == "highway-env"
    assert confirm["identical_episodes"] == 2
    assert json.loads(eval_path.read_text())["summary"]["simulator"] == "fast"
    text = write_report(tmp_path).read_text()
    assert "confirmed on highway-env" in text and "| 2 / 2 |" in text
    with pytest.raises(ConfigError, match="confirm_on"):
        make_spec(confirm_on="carla")


def test_confirm_episodes_re_runs_only_the_first_test_episodes(tmp_path: Path) -> None:
    """--confirm-episodes K: highway-env re-plays each run's first K test episodes, the aggregate counts K
    per run, and K outside 1..test_episodes (or without --confirm-on) is refused in one line."""
    spec = tiny_spec(
        methods=["robust"],
        sets=[*TINY, "simulator=fast"],
        test_episodes=3,
        confirm_on="highway-env",
        confirm_episodes=1,
    )
    results = run_experiment(spec, tmp_path, workers=1)
    confirm = results["methods"]["robust"]["aggregate"]["confirm"]
    assert (confirm["test_episodes"], confirm["identical_episodes"]) == (1, 1)
    assert results["methods"]["robust"]["aggregate"]["test_episodes"] == 3
    with pytest.raises(ConfigError, match=r"--confirm-episodes: at most --test-episodes \(3\), got 4"):
        make_spec(test_episodes=3, confirm_on="highway-env", confirm_episodes=4)
    with pytest.raises(ConfigError, match="--confirm-episodes: needs --confirm-on"):
        make_spec(confirm_episodes=2)
