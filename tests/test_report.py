"""The reproduction report's statistics over runs, from hand-made run directories (no training)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from safelane.core.files import atomic_write_text
from safelane.reporting import stats
from safelane.running import reproduction_report as report
from safelane.running.experiments import collect, make_spec, run_dir_of

TEST_EPISODES = 4
TRAIN_EPISODES = 12
# Per method and seed: (mean speed [m/s], collisions in the 4 test episodes, training return per episode).
RUNS: dict[str, dict[int, tuple[float, int, float]]] = {
    "dqn": {0: (20.0, 0, 1.0), 1: (21.0, 1, 2.0), 2: (23.0, 2, 3.0), 3: (30.0, 1, 10.0)},
    "qmask": {0: (20.0, 0, 5.0), 1: (24.0, 0, 7.0)},
    "robust": {0: (18.0, 0, 4.0), 1: (18.0, 0, 4.0), 2: (18.0, 0, 4.0), 3: (18.0, 0, 4.0)},
}


def write_run(out: Path, method: str, seed: int, speed: float, collisions: int, ret: float) -> None:
    """One finished run as reproduce leaves it: eval.json (4 test episodes) and metrics.csv (12 episodes)."""
    run_dir = run_dir_of(out, method, seed)
    run_dir.mkdir(parents=True)
    episodes = [
        {
            "method": method,
            "seed": seed,
            "test_episode": k,
            "collision": k < collisions,
            "time_to_collision": 5.0 if k < collisions else None,
            "return_before_collision": 10.0 + k,
        }
        for k in range(TEST_EPISODES)
    ]
    summary = {
        "collision_rate": collisions / TEST_EPISODES,
        "collisions": collisions,
        "episodes": TEST_EPISODES,
        "mean_speed": speed,
        "mean_return": 10.0,
        "shield_intervention_rate": 0.0,
        "unsafe_action_rate": 0.0,
        "mean_vehicles_passed": 0.0,
        "fallback_rate": 0.0,
        "collision_kinds": {"ego_hit_front": collisions, "rear_ended": 0, "side": 0},
    }
    record = {"summary": summary, "episodes": episodes, "stress": [], "train_wall_time_s": 1.0}
    atomic_write_text(run_dir / "eval.json", json.dumps(record))
    lines = ["episode,return,epsilon,collision,wall_time_s"]
    for i in range(TRAIN_EPISODES):
        lines.append(f"{i},{ret},{max(0.05, 1 - 0.1 * i):.2f},{'True' if i < 3 else 'False'},{0.1 * (i + 1):.1f}")
    (run_dir / "metrics.csv").write_text("\n".join(lines) + "\n")


@pytest.fixture
def fake_reproduction(tmp_path: Path) -> Path:
    spec = make_spec(
        methods=list(RUNS), seeds=[0, 1, 2, 3], episodes=TRAIN_EPISODES, test_episodes=TEST_EPISODES, quick=True
    )
    for method, runs in RUNS.items():
        for seed, (speed, collisions, ret) in runs.items():
            write_run(tmp_path, method, seed, speed, collisions, ret)
    results = collect(tmp_path, spec)
    results["wall_time_s"] = 1.0
    atomic_write_text(tmp_path / "results.json", json.dumps(results))
    return tmp_path


def test_report_gains_the_over_runs_sections_and_keeps_the_others(fake_reproduction: Path) -> None:
    text = report.write_report(fake_reproduction).read_text()
    for kept in ("Table 4", "Fig. 6", "Fig. 7", "Speed vs safety", "claims"):
        assert kept in text
    assert "## Over runs: interquartile mean and performance profiles" in text
    assert "## Learning curves over seeds" in text
    assert "![performance profiles](performance_profile.png)" in text
    assert "![learning curves](learning_curves.png)" in text
    assert "with fewer than 4 runs nothing is cut" in text  # Q-masking has 2 runs
    for fig in ("fig6.png", "fig7.png", "speed_vs_safety.png", "performance_profile.png", "learning_curves.png"):
        assert (fake_reproduction / fig).stat().st_size > 1000


def test_iqm_table_matches_a_hand_computation(fake_reproduction: Path) -> None:
    text = report.write_report(fake_reproduction).read_text()
    section = text.split("## Over runs")[1].split("\n## ")[0]
    rows = {line.split(" | ")[0].lstrip("| "): line for line in section.splitlines() if line.startswith("| ")}
    assert set(rows) == {"method", "Traditional DQN", "Q-masking", "Robust Q-masking"}
    # DQN, 4 runs: speeds 20 21 23 30 → cut one each side → (21 + 23) / 2 = 22; collision-free rates
    # 1, 0.75, 0.5, 0.75 → (0.75 + 0.75) / 2 = 0.75.
    dqn = rows["Traditional DQN"].split(" | ")
    assert dqn[1] == "4"
    assert dqn[2].startswith("22.00 [") and dqn[3].startswith("0.7500 [")
    speed = stats.stratified_bootstrap([20.0, 21.0, 23.0, 30.0], stats.iqm, reps=report.BOOTSTRAP_REPS, seed=0)
    assert dqn[2] == f"{speed.point:.2f} [{speed.low:.2f}, {speed.high:.2f}]"
    assert 20.0 <= speed.low <= 22.0 <= speed.high <= 30.0
    # Q-masking, 2 runs 20 and 24: nothing trimmed, and a quarter of the samples repeat each run,
    # so the 95 % interval is the two runs themselves.
    assert rows["Q-masking"] == "| Q-masking | 2 | 22.00 [20.00, 24.00] | 1.0000 [1.0000, 1.0000] |"
    # Identical runs: the interval is the point.
    assert rows["Robust Q-masking"] == "| Robust Q-masking | 4 | 18.00 [18.00, 18.00] | 1.0000 [1.0000, 1.0000] |"


def test_learning_curve_bands_and_profiles_by_hand(fake_reproduction: Path) -> None:
    results = json.loads((fake_reproduction / "results.json").read_text())
    spec = report.ExperimentSpec.model_validate(results["spec"])
    curves = report.training_curves(fake_reproduction, spec)
    returns = report.learning_curve_bands(curves, "return", reps=200)
    # DQN's runs return 1, 2, 3 and 10 every episode: the IQM over seeds is (2 + 3) / 2 at every episode.
    np.testing.assert_array_equal(returns["dqn"].point, np.full(TRAIN_EPISODES, 2.5))
    assert np.all(returns["dqn"].low >= 1.0) and np.all(returns["dqn"].high <= 10.0)
    np.testing.assert_array_equal(returns["robust"].low, np.full(TRAIN_EPISODES, 4.0))
    # Every run collides in its first 3 episodes: smoothed over 3 episodes, the rate stays 1 up to
    # episode 3, then falls by a third per episode to 0.
    collisions = report.learning_curve_bands(curves, "collision", reps=200)
    np.testing.assert_allclose(collisions["qmask"].point[:7], [1, 1, 1, 2 / 3, 1 / 3, 0, 0])

    speeds = report.run_scores(results["methods"], "mean_speed")
    np.testing.assert_array_equal(speeds["dqn"], [20.0, 21.0, 23.0, 30.0])
    taus = report.profile_thresholds(speeds)
    assert taus.size == report.PROFILE_POINTS and taus[0] < 18.0 and taus[-1] > 30.0
    free = report.collision_free_rates(results["methods"])
    assert report.profile_thresholds(free, upper=1.0)[-1] == 1.0
    profiles = stats.performance_profile(speeds, [19.0, 22.0, 25.0], reps=200)
    np.testing.assert_array_equal(profiles["dqn"].fraction, [1.0, 0.5, 0.25])
    np.testing.assert_array_equal(profiles["robust"].fraction, [0.0, 0.0, 0.0])
