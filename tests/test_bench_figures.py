"""The mask's cost figures of ``safelane bench``: median, mean and 99th percentile from the timings."""

from __future__ import annotations

import numpy as np
import pytest

from safelane.running.bench import committed_mask_figures, mask_cost_figures


def test_mask_cost_figures_report_the_tail_the_median_hides() -> None:
    # 98 cheap masks and two expensive ones (fallback states): the median stays cheap, the mean and p99 do not.
    samples = [20.0] * 98 + [400.0, 600.0]
    figures = mask_cost_figures(samples, "_fast")
    assert list(figures) == ["shield_mask_us_median_fast", "shield_mask_us_mean_fast", "shield_mask_us_p99_fast"]
    assert figures["shield_mask_us_median_fast"] == 20.0
    assert figures["shield_mask_us_mean_fast"] == pytest.approx((98 * 20.0 + 1000.0) / 100)
    assert figures["shield_mask_us_p99_fast"] == pytest.approx(float(np.percentile(samples, 99)))
    assert figures["shield_mask_us_median_fast"] <= figures["shield_mask_us_mean_fast"]
    assert figures["shield_mask_us_median_fast"] <= figures["shield_mask_us_p99_fast"]


def test_mask_cost_figures_without_timings_is_an_error() -> None:
    with pytest.raises(ValueError, match="mask_us"):
        mask_cost_figures([])


def test_committed_mask_is_timed_beside_the_robust_one_on_the_same_states() -> None:
    figures = committed_mask_figures(episodes=1, seed=3)
    for who in ("committed", "committed_robust"):
        median, mean, p99 = (figures[f"{who}_mask_us_{stat}_fast"] for stat in ("median", "mean", "p99"))
        assert 0 < median <= p99 and mean > 0
    assert figures["committed_mask_ratio_fast"] == pytest.approx(
        figures["committed_mask_us_mean_fast"] / figures["committed_robust_mask_us_mean_fast"]
    )
    assert 1 <= figures["committed_mask_decisions"] <= 40  # one episode of the fast preset: 40 s at 1 decision/s
    assert figures["committed_engine"] in ("compiled", "numpy")


def test_committed_mask_figures_need_an_episode() -> None:
    with pytest.raises(ValueError, match="episodes"):
        committed_mask_figures(episodes=0)
