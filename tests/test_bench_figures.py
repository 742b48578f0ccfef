"""The mask's cost figures of ``safelane bench``: median, mean and 99th percentile from the timings, and the
committed mode's figures under the names its docstring documents."""

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
    assert mask_cost_figures(samples, prefix="committed")["committed_mask_us_median"] == 20.0


def test_mask_cost_figures_without_timings_is_an_error() -> None:
    with pytest.raises(ValueError, match="mask_us"):
        mask_cost_figures([])


def test_committed_mask_figures_are_the_documented_ones() -> None:
    """Exactly the names :func:`committed_mask_figures` documents (the bench JSON's keys), its timed decisions
    those of the one episode played."""
    figures = committed_mask_figures(episodes=1, seed=3)
    stats = ("median", "mean", "p99")
    who = ("committed", "committed_robust", "projection")
    timings = {f"{name}_mask_us_{stat}_fast" for name in who for stat in stats}
    ratios = {"committed_mask_ratio_fast", "projection_ratio_fast", "projection_evaluated_mean"}
    assert set(figures) == timings | ratios | {"committed_mask_decisions", "committed_engine"}
    assert all(isinstance(figures[k], float) for k in (*timings, *ratios))
    assert figures["projection_evaluated_mean"] >= 1.0  # at least the agent's action is verified
    assert 1 <= figures["committed_mask_decisions"] <= 40  # one episode of the fast preset: 40 s at 1 decision/s
    assert figures["committed_engine"] in ("compiled", "numpy")


def test_committed_mask_figures_need_an_episode() -> None:
    with pytest.raises(ValueError, match="episodes"):
        committed_mask_figures(episodes=0)
