"""bench's regressions: a figure worse than the published run's by more than the noise measured for it."""

from __future__ import annotations

import numpy as np
import pytest

from safelane.running.bench import regressions, relative_spread, with_regressions

PUBLISHED = {
    "fast_decisions_per_s": 10_000.0,
    "fast_shielded_decisions_per_s": 6_000.0,
    "fast_batched_decisions_per_s": {"64": 5_000.0},
    "shield_mask_us_mean_fast": 30.0,
}


def measured(**figures: float) -> dict:
    base = {
        "fast_decisions_per_s": 10_000.0,
        "fast_shielded_decisions_per_s": 6_000.0,
        "fast_batched_decisions_per_s": {"64": 5_000.0, "256": 5_100.0},
        "shield_mask_us_mean_fast": 30.0,
        "noise": {"fast_decisions_per_s": 0.05, "fast_shielded_decisions_per_s": 0.05,
                  "fast_batched_decisions_per_s.64": 0.05, "shield_mask_us_mean_fast": 0.05},
    }  # fmt: skip
    for key, value in figures.items():
        if key == "batch64":
            base["fast_batched_decisions_per_s"]["64"] = value
        else:
            base[key] = value
    return base


def test_the_same_figures_are_no_regression() -> None:
    assert regressions(measured(), PUBLISHED) == []


def test_a_drop_within_the_noise_is_no_regression_and_beyond_it_is() -> None:
    assert regressions(measured(fast_shielded_decisions_per_s=5_800.0), PUBLISHED) == []  # −3 %, noise 5 %
    (found,) = regressions(measured(fast_shielded_decisions_per_s=5_000.0), PUBLISHED)  # −17 %
    assert found["figure"] == "fast_shielded_decisions_per_s"
    assert found["change"] == pytest.approx(5_000 / 6_000 - 1) and found["noise"] == 0.05


def test_a_dotted_figure_and_a_cost_that_rises() -> None:
    found = regressions(measured(batch64=4_000.0, shield_mask_us_mean_fast=40.0), PUBLISHED)
    assert [f["figure"] for f in found] == ["fast_batched_decisions_per_s.64", "shield_mask_us_mean_fast"]
    assert regressions(measured(shield_mask_us_mean_fast=10.0), PUBLISHED) == []  # cheaper is no regression


def test_figures_either_run_lacks_are_skipped() -> None:
    assert regressions(measured(fast_decisions_per_s=1.0), {"train_steps_per_s_fast": 1e9}) == []


def test_with_regressions_names_its_baseline() -> None:
    out = with_regressions(measured(fast_decisions_per_s=1.0), PUBLISHED, "published.json")
    assert out["baseline"] == "published.json" and out["regressions"][0]["figure"] == "fast_decisions_per_s"
    assert with_regressions(measured(), None, None) == {**measured(), "baseline": None, "regressions": []}


def test_relative_spread() -> None:
    assert relative_spread(np.array([90.0, 100.0, 110.0])) == pytest.approx(0.2)
    assert relative_spread(np.array([5.0])) == 0.0


def test_the_committed_mask_cost_counts_only_against_a_baseline_that_has_it() -> None:
    run = {**measured(), "committed_mask_us_mean_fast": 5_000.0}
    run["noise"] = {**run["noise"], "committed_mask_us_mean_fast": 0.05}
    assert regressions(run, PUBLISHED) == []  # the published run predates the figure: no regression
    (found,) = regressions(run, {**PUBLISHED, "committed_mask_us_mean_fast": 50.0})
    assert found["figure"] == "committed_mask_us_mean_fast" and found["change"] == pytest.approx(99.0)
    assert regressions(run, {**PUBLISHED, "committed_mask_us_mean_fast": 6_000.0}) == []  # cheaper now
