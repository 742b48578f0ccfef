"""Statistics on tiny arrays with answers worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safelane.reporting import stats

# --- point estimates -----------------------------------------------------------------------------


def test_mean_pools_runs_and_tasks() -> None:
    assert stats.mean([[1, 2], [3, 6]]) == 3.0


def test_iqm_hand_worked() -> None:
    assert stats.iqm([1, 2, 3, 4]) == 2.5  # cut 1 each side: mean(2, 3)
    assert stats.iqm([0, 1, 2, 3, 4, 5, 6, 7]) == 3.5  # cut 2 each side: mean(2, 3, 4, 5)
    assert stats.iqm([7, 0, 5, 2, 6, 1, 4, 3]) == 3.5  # order does not matter
    assert stats.iqm([100, 1, 2, -100]) == 1.5  # outliers are cut


def test_iqm_rounds_the_cut_down_like_scipy() -> None:
    assert stats.iqm([1, 2, 30]) == 11.0  # int(0.75) = 0: nothing cut
    assert stats.iqm([0, 1, 2, 3, 100]) == 2.0  # int(1.25) = 1: mean(1, 2, 3)
    assert stats.iqm([[0, 1], [2, 3], [4, 5], [6, 7]]) == 3.5  # runs × tasks are pooled


@pytest.mark.parametrize("bad", [[], [[]], [1.0, math.nan]])
def test_point_estimates_reject_empty_and_nan(bad: list) -> None:
    with pytest.raises(ValueError):
        stats.mean(bad)
    with pytest.raises(ValueError):
        stats.iqm(bad)


# --- probability of improvement ------------------------------------------------------------------


def test_probability_of_improvement_hand_worked() -> None:
    # pairs (1,0) (1,3) (2,0) (2,3) -> 1 0 1 0
    assert stats.probability_of_improvement([1, 2], [0, 3]) == 0.5
    # pairs (1,2) (1,0) (2,2) (2,0) (3,2) (3,0) -> 0 1 ½ 1 1 1 = 4.5 / 6
    assert stats.probability_of_improvement([1, 2, 3], [2, 0]) == 0.75
    assert stats.probability_of_improvement([5, 5], [5]) == 0.5
    assert stats.probability_of_improvement([1], [0]) == 1.0


def test_probability_of_improvement_averages_over_tasks() -> None:
    x = [[1, 0], [2, 0]]  # task 0: [1, 2]; task 1: [0, 0]
    y = [[0, 1], [3, 1]]  # task 0: [0, 3]; task 1: [1, 1]
    assert stats.probability_of_improvement(x, y) == (0.5 + 0.0) / 2


def test_probability_of_improvement_is_complementary() -> None:
    x, y = [0.3, 1.2, 1.2, 4.0], [1.2, 0.1, 5.0]
    assert stats.probability_of_improvement(x, y) + stats.probability_of_improvement(y, x) == 1.0


def test_probability_of_improvement_rejects_mismatched_tasks() -> None:
    with pytest.raises(ValueError, match="tasks"):
        stats.probability_of_improvement([[1, 2]], [[1, 2, 3]])


# --- Wilson interval -----------------------------------------------------------------------------


def test_wilson_zero_successes_by_hand() -> None:
    # k = 0: centre = half = (z²/2n)/(1 + z²/n), so the upper bound is (z²/n)/(1 + z²/n).
    z = 1.959963984540054
    expected_high = (z * z / 50) / (1 + z * z / 50)
    low, high = stats.binomial_ci(0, 50)
    assert low == 0.0
    assert high == pytest.approx(expected_high, rel=1e-12)
    assert high == pytest.approx(0.0713, abs=5e-5)


def test_wilson_half_by_hand() -> None:
    # k = 5, n = 10: centre 0.5; half = z/(1 + z²/10)·sqrt(0.025 + z²/400)
    z = 1.959963984540054
    half = z / (1 + z * z / 10) * math.sqrt(0.025 + z * z / 400)
    low, high = stats.binomial_ci(5, 10)
    assert low == pytest.approx(0.5 - half, rel=1e-12)
    assert high == pytest.approx(0.5 + half, rel=1e-12)
    assert (low, high) == pytest.approx((0.2366, 0.7634), abs=1e-4)


def test_wilson_all_successes_and_errors() -> None:
    low, high = stats.binomial_ci(50, 50)
    assert high == 1.0
    assert low == pytest.approx(1 - stats.binomial_ci(0, 50)[1], rel=1e-12)
    with pytest.raises(ValueError, match="n"):
        stats.binomial_ci(0, 0)
    with pytest.raises(ValueError, match="successes"):
        stats.binomial_ci(3, 2)
    with pytest.raises(ValueError, match="alpha"):
        stats.binomial_ci(1, 2, alpha=0.0)


@given(st.integers(1, 500).flatmap(lambda n: st.tuples(st.integers(0, n), st.just(n))))
def test_wilson_contains_the_estimate(kn: tuple[int, int]) -> None:
    k, n = kn
    low, high = stats.binomial_ci(k, n)
    assert 0.0 <= low <= k / n <= high <= 1.0


# --- bootstrap -----------------------------------------------------------------------------------


def test_bootstrap_ci_contains_mean_and_is_deterministic() -> None:
    scores = np.array([0.1, 0.4, 0.35, 0.8, 0.55, 0.6, 0.2, 0.9])
    low, high = stats.bootstrap_ci(scores, seed=3)
    assert low < scores.mean() < high
    assert (low, high) == stats.bootstrap_ci(scores, seed=3)
    assert (low, high) != stats.bootstrap_ci(scores, seed=4)
    assert low >= 0.1 and high <= 0.9  # a mean of resampled values stays within their range


def test_bootstrap_ci_iqm_and_2d() -> None:
    scores = np.arange(20, dtype=float).reshape(10, 2)
    low, high = stats.bootstrap_ci(scores, statistic=stats.iqm, reps=500)
    assert low <= stats.iqm(scores) <= high


def test_bootstrap_of_identical_runs_is_a_point() -> None:
    assert stats.bootstrap_ci([2.0, 2.0, 2.0]) == (2.0, 2.0)
    assert stats.stratified_bootstrap_ci([[1.0, 3.0], [1.0, 3.0]]) == (2.0, 2.0)


def test_stratified_bootstrap_resamples_within_tasks() -> None:
    # Task 0 is always 0, task 1 always 10: any within-task resample keeps the mean at exactly 5,
    # whereas resampling rows of a matrix whose rows differ does not.
    scores = np.array([[0.0, 10.0], [0.0, 10.0], [0.0, 10.0]])
    assert stats.stratified_bootstrap_ci(scores, seed=1) == (5.0, 5.0)
    varied = np.array([[0.0, 10.0], [1.0, 12.0], [2.0, 8.0], [0.5, 11.0]])
    low, high = stats.stratified_bootstrap_ci(varied, statistic=stats.mean, seed=1)
    assert low < stats.mean(varied) < high
    assert (low, high) == stats.stratified_bootstrap_ci(varied, statistic=stats.mean, seed=1)


def test_bootstrap_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="empty"):
        stats.bootstrap_ci([])
    with pytest.raises(ValueError, match="reps"):
        stats.bootstrap_ci([1.0], reps=0)
    with pytest.raises(ValueError, match="alpha"):
        stats.stratified_bootstrap_ci([[1.0]], alpha=1.5)


# --- rliable's statistics: IQM, stratified bootstrap, performance profiles, curve bands --------------

finite = st.floats(-1e6, 1e6, allow_nan=False)
run_scores = st.lists(finite, min_size=1, max_size=24)


def test_interquartile_mean_is_iqm_and_matches_scipy() -> None:
    scipy_stats = pytest.importorskip("scipy.stats")
    x = np.array([3.0, -1.0, 8.0, 2.5, 2.5, 40.0, 0.0, 7.0, 1.0])
    assert stats.interquartile_mean(x) == stats.iqm(x)
    assert stats.interquartile_mean(x) == pytest.approx(scipy_stats.trim_mean(x, 0.25))


@given(st.floats(-1e6, 1e6), st.integers(1, 40))
def test_iqm_of_constant_runs_is_the_constant(value: float, n: int) -> None:
    assert stats.interquartile_mean([value] * n) == pytest.approx(value, rel=1e-12, abs=1e-9)


@given(st.floats(-1e3, 1e3), st.lists(st.floats(0, 1e3), min_size=1, max_size=20))
def test_iqm_equals_the_mean_for_symmetric_data(centre: float, offsets: list[float]) -> None:
    x = np.array([centre + d for d in offsets] + [centre - d for d in offsets])
    assert stats.interquartile_mean(x) == pytest.approx(float(np.mean(x)), abs=1e-6)
    assert stats.interquartile_mean(x) == pytest.approx(centre, abs=1e-6)


@given(run_scores)
def test_iqm_lies_between_the_quartiles(x: list[float]) -> None:
    q1, q3 = np.percentile(x, [25, 75])
    tol = 1e-9 * (1 + float(np.max(np.abs(x))))
    assert q1 - tol <= stats.interquartile_mean(x) <= q3 + tol


def test_optimality_gap_hand_worked() -> None:
    assert stats.optimality_gap([1.0, 0.9, 0.7]) == pytest.approx(0.4 / 3)
    assert stats.optimality_gap([20.0, 25.0, 31.0], gamma=30.0) == pytest.approx((10 + 5 + 0) / 3)
    assert stats.optimality_gap([2.0, 3.0], gamma=1.0) == 0.0


def test_stratified_bootstrap_hand_worked() -> None:
    # Two runs 20 and 24: too few to trim, so the IQM is the mean 22; a quarter of the samples draw
    # run 20 twice and a quarter run 24 twice, so the 2.5th and 97.5th percentiles are 20 and 24.
    assert stats.stratified_bootstrap([20.0, 24.0]) == (22.0, 20.0, 24.0)
    assert stats.stratified_bootstrap([5.0, 5.0, 5.0], stats.mean) == (5.0, 5.0, 5.0)
    est = stats.stratified_bootstrap({"a": [0.0, 0.0], "b": [10.0, 10.0]}, stats.mean, reps=50)
    assert est == (5.0, 5.0, 5.0)  # each task keeps its two runs' weight: the mean cannot move


def test_stratified_bootstrap_agrees_with_the_interval_function() -> None:
    scores = np.array([[0.0, 10.0], [1.0, 12.0], [2.0, 8.0], [0.5, 11.0]])
    est = stats.stratified_bootstrap(scores, stats.mean, reps=500, seed=7, level=0.9)
    assert (est.low, est.high) == pytest.approx(stats.stratified_bootstrap_ci(scores, reps=500, alpha=0.1, seed=7))
    assert est.point == stats.mean(scores)


@settings(max_examples=40, deadline=None)
@given(run_scores, st.integers(0, 2**32 - 1), st.sampled_from(["iqm", "mean"]))
def test_stratified_bootstrap_interval_contains_the_point_and_repeats(x: list[float], seed: int, name: str) -> None:
    statistic = stats.iqm if name == "iqm" else stats.mean
    est = stats.stratified_bootstrap(x, statistic, reps=200, seed=seed)
    tol = 1e-9 * (1 + float(np.max(np.abs(x))))
    assert est.low - tol <= est.point <= est.high + tol
    assert stats.stratified_bootstrap(x, statistic, reps=200, seed=seed) == est


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 8), st.integers(1, 5), st.integers(0, 2**32 - 1))
def test_stratified_resample_never_mixes_tasks(runs: int, tasks: int, seed: int) -> None:
    # Task t's runs score 1000·t + r: a value's task is readable from the value itself.
    scores = 1000.0 * np.arange(tasks)[None, :] + np.arange(runs)[:, None]
    samples = stratified_resample_checked(scores, seed)
    for t in range(tasks):
        assert set(np.unique(samples[:, :, t])) <= set(scores[:, t])
    by_name = {f"task{t}": scores[:, t] for t in range(tasks)}
    np.testing.assert_array_equal(stats.stratified_resample(by_name, 30, seed), samples)


def stratified_resample_checked(scores: np.ndarray, seed: int) -> np.ndarray:
    samples = stats.stratified_resample(scores, 30, seed)
    assert samples.shape == (30, *scores.shape)
    np.testing.assert_array_equal(samples, stats.stratified_resample(scores, 30, seed))
    return samples


def test_stratified_bootstrap_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="same number of runs"):
        stats.stratified_bootstrap({"a": [1.0, 2.0], "b": [1.0]})
    with pytest.raises(ValueError, match="level"):
        stats.stratified_bootstrap([1.0, 2.0], level=95)
    with pytest.raises(ValueError, match="reps"):
        stats.stratified_resample([1.0], reps=0)
    with pytest.raises(ValueError, match="no tasks"):
        stats.stratified_bootstrap({})


def test_performance_profile_hand_worked() -> None:
    profiles = stats.performance_profile({"m": [20.0, 22.0, 24.0, 26.0], "k": [21.0, 21.0]}, [19.0, 21.0, 25.0, 26.0])
    np.testing.assert_array_equal(profiles["m"].fraction, [1.0, 0.75, 0.25, 0.0])  # strictly above τ
    np.testing.assert_array_equal(profiles["k"].fraction, [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(profiles["k"].low, profiles["k"].high)  # identical runs: no spread
    assert profiles["m"].low[0] == profiles["m"].high[0] == 1.0  # every run is above 19 in every sample
    # per task, then averaged over tasks: task a [1, 3] → ½ above 2, task b [5, 5] → all above 2
    two_tasks = stats.performance_profile({"m": {"a": [1.0, 3.0], "b": [5.0, 5.0]}}, [2.0])
    assert two_tasks["m"].fraction[0] == 0.75


@settings(max_examples=30, deadline=None)
@given(st.lists(run_scores, min_size=1, max_size=3), st.integers(0, 1000))
def test_performance_profile_is_monotone_bounded_and_independent_of_other_methods(
    methods: list[list[float]], seed: int
) -> None:
    scores = {f"m{i}": x for i, x in enumerate(methods)}
    taus = np.linspace(-1e6, 1e6, 9)
    profiles = stats.performance_profile(scores, taus, reps=100, seed=seed)
    for prof in profiles.values():
        assert np.all(np.diff(prof.fraction) <= 0)
        assert np.all((prof.low >= 0) & (prof.high <= 1) & (prof.low <= prof.high))
    alone = stats.performance_profile({"m0": methods[0]}, taus, reps=100, seed=seed)["m0"]
    np.testing.assert_array_equal(alone.low, profiles["m0"].low)


def test_curve_band_point_is_the_iqm_at_each_episode() -> None:
    rng = np.random.default_rng(0)
    curves = rng.normal(size=(9, 30)).cumsum(axis=1)
    band = stats.curve_band(curves, "iqm", reps=300)
    np.testing.assert_allclose(band.point, [stats.iqm(curves[:, j]) for j in range(30)], rtol=1e-12)
    assert np.all(band.low <= band.high)
    means = stats.curve_band(curves, "mean", reps=300)
    np.testing.assert_allclose(means.point, curves.mean(axis=0), rtol=1e-12)
    same = stats.curve_band(np.tile([1.0, 2.0, 3.0], (4, 1)), reps=50)
    np.testing.assert_array_equal(same.low, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(same.high, [1.0, 2.0, 3.0])
    first, again = stats.curve_band(curves, reps=300, seed=4), stats.curve_band(curves, reps=300, seed=4)
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a, b)


def test_curve_band_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="statistic"):
        stats.curve_band([[1.0]], "median")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="2-D"):
        stats.curve_band([1.0, 2.0])


# --- curves --------------------------------------------------------------------------------------


def test_smooth_is_trailing() -> None:
    np.testing.assert_array_equal(stats.smooth([0, 3, 6, 9], 2), [0.0, 1.5, 4.5, 7.5])
    np.testing.assert_array_equal(stats.smooth([0, 3, 6, 9], 3), [0.0, 1.5, 3.0, 6.0])
    np.testing.assert_array_equal(stats.smooth([4, 5], 1), [4.0, 5.0])
    assert stats.smooth([], 5).size == 0
    with pytest.raises(ValueError, match="window"):
        stats.smooth([1.0], 0)


def test_scale_01() -> None:
    np.testing.assert_array_equal(stats.scale_01([2, 4, 3, 6]), [0.0, 0.5, 0.25, 1.0])
    np.testing.assert_array_equal(stats.scale_01([7, 7, 7]), [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="empty"):
        stats.scale_01([])


def test_convergence_episode_on_a_step() -> None:
    curve = np.r_[np.zeros(50), np.ones(50)]
    # smoothed s[t] = (t − 49)/10 for t in 50..59; target 0.9 is reached at t = 58
    assert stats.convergence_episode(curve) == 58
    assert stats.convergence_episode(curve, frac=0.5) == 54  # (t − 49)/10 ≥ 0.5
    assert stats.convergence_episode(curve, window=1) == 50  # no smoothing: the step itself


def test_convergence_episode_falling_and_flat() -> None:
    collisions = np.r_[np.ones(30), np.zeros(70)]
    assert stats.convergence_episode(collisions, window=5) == 34  # s = (34 − t)/5 ≤ 0.1 → t ≥ 33.5
    assert stats.convergence_episode(np.full(40, 3.0), window=5) == 4  # flat: first full window
    assert stats.convergence_episode([1.0, 2.0], window=10) == 1  # shorter than a window


def test_convergence_episode_start_is_first_full_window() -> None:
    # step at 5 with window 10: start = s[9] = 0.5, plateau 1, target 0.95 → (t − 4)/10 ≥ 0.95 → t = 14
    curve = np.r_[np.zeros(5), np.ones(95)]
    assert stats.convergence_episode(curve) == 14


def test_convergence_episode_rejects_degenerate_input() -> None:
    with pytest.raises(ValueError, match="empty"):
        stats.convergence_episode([])
    with pytest.raises(ValueError, match="NaN"):
        stats.convergence_episode([0.0, math.nan])
    with pytest.raises(ValueError, match="frac"):
        stats.convergence_episode([0.0, 1.0], frac=0.0)


# --- two-sample tests ----------------------------------------------------------------------------------


def test_fisher_exact_test_hand_worked() -> None:
    from safelane.reporting.stats import fisher_exact_test

    assert fisher_exact_test(1, 2, 1, 2) == pytest.approx(1.0)
    assert fisher_exact_test(3, 3, 0, 3) == pytest.approx(0.1)  # 2 of C(6,3) = 20 splits are as extreme
    assert fisher_exact_test(8, 10, 2, 10) == pytest.approx(0.023014, abs=1e-6)  # R: fisher.test
    assert fisher_exact_test(0, 1000, 0, 1000) == 1.0
    assert fisher_exact_test(20, 1000, 60, 1000) < 1e-4
    with pytest.raises(ValueError, match="k1"):
        fisher_exact_test(3, 2, 0, 2)


def test_permutation_test_separates_shifted_samples_and_not_equal_ones() -> None:
    from safelane.reporting.stats import permutation_test

    rng = np.random.default_rng(0)
    same = permutation_test(rng.normal(20, 3, 300), rng.normal(20, 3, 300), reps=2000, seed=1)
    shifted = permutation_test(rng.normal(20, 3, 300), rng.normal(21.5, 3, 300), reps=2000, seed=1)
    assert same > 0.05
    assert shifted == pytest.approx(1 / 2001)  # no relabelling reaches a 1.5 m/s gap: the smallest p-value
    assert permutation_test([1.0, 2.0], [1.0, 2.0], reps=100) == 1.0


def test_holm_adjustment_is_step_down_and_monotone() -> None:
    from safelane.running.simcheck import holm_adjusted

    tests = [{"p_value": p} for p in (0.04, 0.001, 0.03, 0.5)]
    adjusted = [t["p_value_holm"] for t in holm_adjusted(tests)]
    # sorted: 0.001*4=0.004, 0.03*3=0.09, 0.04*2=0.08 -> 0.09 (monotone), 0.5*1=0.5
    assert adjusted == pytest.approx([0.09, 0.004, 0.09, 0.5])
