"""The mask's cost figures of ``safelane bench``: median, mean and 99th percentile from the timings."""

from __future__ import annotations

import numpy as np
import pytest

from safelane.running.bench import mask_cost_figures


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
