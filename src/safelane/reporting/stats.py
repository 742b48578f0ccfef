"""Statistics for comparing RL runs, with rliable's definitions, in pure numpy.

Scores are either 1-D (one number per run/seed) or 2-D ``(runs × tasks)`` arrays, as in rliable
(Agarwal et al., 2021, "Deep RL at the edge of the statistical precipice"). Every function is pure and
deterministic: the bootstrap draws come from ``numpy.random.default_rng(seed)``.

Degenerate input is an error, never a silent NaN: empty arrays, NaN scores, ``n = 0`` trials, a
non-positive window or an ``alpha`` outside (0, 1) raise :class:`ValueError` with a one-line message.
The one exception is :func:`smooth`, which maps an empty curve to an empty curve.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from statistics import NormalDist

import numpy as np
from numpy.typing import ArrayLike

Statistic = Callable[[np.ndarray], float]
"""A scalar summary of a score array (e.g. :func:`mean`, :func:`iqm`)."""

IQM_TRIM = 0.25
"""Fraction cut from each end by the interquartile mean (rliable: ``trim_mean(x, 0.25)``)."""


def _scores(x: ArrayLike, name: str = "scores", max_ndim: int = 2) -> np.ndarray:
    """``x`` as a float array, checked: non-empty, no NaN, at most ``max_ndim`` dimensions."""
    arr = np.asarray(x, dtype=float)
    if arr.ndim > max_ndim:
        raise ValueError(f"{name}: expected at most {max_ndim}-D (runs × tasks), got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name}: empty array, a statistic of no runs is undefined")
    if np.isnan(arr).any():
        raise ValueError(f"{name}: contains NaN")
    return arr


def _check_alpha(alpha: float) -> None:
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha: must be in (0, 1), got {alpha}")


# --- point estimates -------------------------------------------------------------------------------


def mean(x: ArrayLike) -> float:
    """Mean of all scores (rliable's ``aggregate_mean``: equal to the mean of per-task means)."""
    return float(np.mean(_scores(x)))


def trim_mean(x: ArrayLike, proportion: float) -> float:
    """Mean after cutting ``int(proportion · n)`` of the ``n`` sorted scores from each end.

    Same semantics as ``scipy.stats.trim_mean(x, proportion, axis=None)``: all values are pooled, and the
    number cut is rounded *down*, so fewer than ``1/proportion`` scores are not trimmed at all.
    """
    if not 0.0 <= proportion < 0.5:
        raise ValueError(f"proportion: must be in [0, 0.5), got {proportion}")
    flat = np.sort(_scores(x).ravel())
    cut = int(proportion * flat.size)
    return float(np.mean(flat[cut : flat.size - cut]))


def iqm(x: ArrayLike) -> float:
    """Interquartile mean: the mean of the middle 50 % of all scores (rliable's ``aggregate_iqm``).

    ``iqm([1, 2, 3, 4]) == 2.5`` (cut one each side), ``iqm([0, …, 7]) == 3.5`` (cut two each side).
    """
    return trim_mean(x, IQM_TRIM)


# --- interval estimates ----------------------------------------------------------------------------


def _check_bootstrap(alpha: float, reps: int) -> None:
    _check_alpha(alpha)
    if reps < 1:
        raise ValueError(f"reps: must be at least 1, got {reps}")


def _percentile_interval(draws: np.ndarray, alpha: float) -> tuple[float, float]:
    low, high = np.percentile(draws, [100 * alpha / 2, 100 * (1 - alpha / 2)])
    return float(low), float(high)


def bootstrap_ci(
    scores: ArrayLike,
    statistic: Statistic = mean,
    reps: int = 2000,
    alpha: float = 0.05,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile-bootstrap ``(1 − alpha)`` confidence interval of ``statistic(scores)``.

    Runs (rows; the entries of a 1-D array) are resampled with replacement, ``reps`` times; a resampled
    run keeps all its tasks together. The interval is the ``alpha/2`` and ``1 − alpha/2`` percentiles of
    the ``reps`` bootstrap statistics. Deterministic for a given ``seed``.
    """
    arr = _scores(scores)
    _check_bootstrap(alpha, reps)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, arr.shape[0], size=(reps, arr.shape[0]))
    draws = np.array([statistic(arr[i]) for i in idx])
    return _percentile_interval(draws, alpha)


def stratified_bootstrap_ci(
    scores: ArrayLike,
    statistic: Statistic = mean,
    reps: int = 2000,
    alpha: float = 0.05,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile-bootstrap interval resampling runs independently within each task (rliable's
    ``StratifiedBootstrap``).

    ``scores`` is ``(runs × tasks)`` (1-D is one task, identical to :func:`bootstrap_ci` in
    distribution). Each bootstrap sample draws, for every task column separately, ``runs`` row indices
    with replacement, so every task keeps its weight in the statistic.
    """
    arr = _scores(scores)
    if arr.ndim == 1:
        arr = arr[:, None]
    _check_bootstrap(alpha, reps)
    runs, tasks = arr.shape
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, runs, size=(reps, runs, tasks))
    samples = arr[idx, np.arange(tasks)]  # (reps, runs, tasks)
    draws = np.array([statistic(s) for s in samples])
    return _percentile_interval(draws, alpha)


def probability_of_improvement(x: ArrayLike, y: ArrayLike) -> float:
    """P(X > Y) + ½·P(X = Y) for a run X of method x and a run Y of method y (rliable's definition).

    For 1-D arrays this is the Mann–Whitney U statistic of x over y divided by ``n·m``: every pair
    ``(x_i, y_j)`` scores 1 if ``x_i > y_j``, ½ on a tie, 0 otherwise, and the scores are averaged.
    For ``(runs × tasks)`` arrays (same number of tasks, runs may differ) it is the average over tasks
    of the per-task value. E.g. ``x = [1, 2, 3]``, ``y = [2, 0]``: pairs score 0, 1, ½, 1, 1, 1 → 0.75.
    """
    a, b = _scores(x, "x"), _scores(y, "y")
    if a.ndim == 1:
        a = a[:, None]
    if b.ndim == 1:
        b = b[:, None]
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"x and y: different numbers of tasks ({a.shape[1]} vs {b.shape[1]})")
    diff = a[:, None, :] - b[None, :, :]  # (n, m, tasks)
    pair = (diff > 0) + 0.5 * (diff == 0)
    return float(np.mean(pair.mean(axis=(0, 1))))


def binomial_ci(successes: int, n: int, alpha: float = 0.05) -> tuple[float, float]:
    """Wilson score ``(1 − alpha)`` interval for a binomial proportion (e.g. a collision rate).

    With ``p = k/n`` and ``z`` the ``1 − alpha/2`` normal quantile::

        centre = (p + z²/(2n)) / (1 + z²/n)
        half   = z / (1 + z²/n) · sqrt(p(1 − p)/n + z²/(4n²))

    Unlike the normal approximation it stays inside [0, 1] and is not degenerate at 0 or n
    successes: ``binomial_ci(0, 50) ≈ (0, 0.0713)``. The bounds are exactly 0 / 1 at ``k = 0`` / ``k = n``.
    """
    _check_alpha(alpha)
    if n <= 0:
        raise ValueError(f"n: the number of trials must be positive, got {n}")
    if not 0 <= successes <= n:
        raise ValueError(f"successes: must be in [0, n={n}], got {successes}")
    z = NormalDist().inv_cdf(1 - alpha / 2)
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z / denom * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == n else min(1.0, centre + half)
    return low, high


# --- two-sample tests (is one simulator's outcome distribution the other's?) -------------------------


def fisher_exact_test(k1: int, n1: int, k2: int, n2: int) -> float:
    """Two-sided p-value of Fisher's exact test that ``k1 / n1`` and ``k2 / n2`` are one rate.

    Conditioned on the total ``k1 + k2`` the first count is hypergeometric; the p-value sums the
    probabilities of every table no more likely than the observed one (R's and SciPy's convention, with
    a relative tolerance of 1e-7 for ties). E.g. ``fisher_exact_test(1, 2, 1, 2) == 1`` and
    ``fisher_exact_test(3, 3, 0, 3) == 0.1`` (2 of the 20 equally likely splits are that extreme).
    """
    for name, k, n in (("k1", k1, n1), ("k2", k2, n2)):
        if n <= 0 or not 0 <= k <= n:
            raise ValueError(f"{name}: must be in [0, n] with n > 0, got {k} of {n}")
    total = k1 + k2
    lo, hi = max(0, total - n2), min(total, n1)
    # log-probabilities for numerical range at thousands of episodes
    log_norm = _log_comb(n1 + n2, total)
    logp = {k: _log_comb(n1, k) + _log_comb(n2, total - k) - log_norm for k in range(lo, hi + 1)}
    observed = logp[k1]
    tol = math.log1p(1e-7)
    return float(min(1.0, sum(math.exp(v) for v in logp.values() if v <= observed + tol)))


def _log_comb(n: int, k: int) -> float:
    return math.lgamma(n + 1) - math.lgamma(k + 1) - math.lgamma(n - k + 1)


def permutation_test(x: ArrayLike, y: ArrayLike, reps: int = 10_000, seed: int = 0) -> float:
    """Two-sided p-value that samples ``x`` and ``y`` have the same mean, by random relabelling.

    The statistic is ``|mean(x) − mean(y)|``; the p-value is ``(1 + #{relabelled ≥ observed}) / (1 + reps)``
    (never 0), from ``reps`` random splits of the pooled sample drawn with ``seed``. No distributional
    assumption: speeds of crashing and non-crashing episodes are far from normal.
    """
    a, b = _scores(x, "x", 1), _scores(y, "y", 1)
    if a.size == 0 or b.size == 0:
        raise ValueError("x and y: need at least one value each")
    if reps < 1:
        raise ValueError(f"reps: must be >= 1, got {reps}")
    pooled = np.concatenate([a, b])
    observed = abs(a.mean() - b.mean())
    rng = np.random.default_rng(seed)
    hits = 0
    for _ in range(reps):
        perm = rng.permutation(pooled)
        hits += abs(perm[: a.size].mean() - perm[a.size :].mean()) >= observed - 1e-12
    return (1 + hits) / (1 + reps)


# --- learning curves -------------------------------------------------------------------------------


def smooth(curve: ArrayLike, window: int) -> np.ndarray:
    """Trailing moving average: ``s[t] = mean(curve[max(0, t − window + 1) : t + 1])``.

    Same length as ``curve``; the first ``window − 1`` entries average the shorter prefix available
    (so ``s[0] == curve[0]``). ``window = 1`` returns a float copy; an empty curve returns an empty array.
    """
    if window < 1:
        raise ValueError(f"window: must be at least 1, got {window}")
    arr = np.asarray(curve, dtype=float)
    if arr.ndim != 1:
        raise ValueError(f"curve: expected 1-D, got shape {arr.shape}")
    if arr.size == 0:
        return arr.copy()
    sums = np.convolve(arr, np.ones(window))[: arr.size]
    counts = np.minimum(np.arange(1, arr.size + 1), window)
    return sums / counts


def scale_01(curve: ArrayLike) -> np.ndarray:
    """Min–max scaling to [0, 1], as the paper's Fig. 7 scales each method's reward curve.

    ``(curve − min) / (max − min)``; a constant curve maps to all zeros (there is nothing to scale).
    """
    arr = _scores(curve, "curve", max_ndim=1)
    lo, hi = float(arr.min()), float(arr.max())
    if hi == lo:
        return np.zeros_like(arr)
    return (arr - lo) / (hi - lo)


def convergence_episode(
    curve: ArrayLike,
    frac: float = 0.9,
    window: int = 10,
    plateau_frac: float = 0.2,
) -> int:
    """First episode (0-based index into ``curve``) at which training has converged.

    Exactly:

    1. ``s = smooth(curve, window)`` (trailing moving average);
    2. ``w = min(window, len(curve)) − 1``, the first index with a full window;
       ``start = s[w]`` (the mean of the first ``window`` episodes);
    3. ``plateau = mean(s[−k:])`` with ``k = max(1, ceil(plateau_frac · len(curve)))``;
    4. ``target = start + frac · (plateau − start)``;
    5. the answer is the first ``t ≥ w`` with ``s[t] ≥ target`` if ``plateau ≥ start`` (a rising
       curve), else the first ``t ≥ w`` with ``s[t] ≤ target`` (a falling one, e.g. a collision rate).

    A solution always exists (some of the last ``k`` smoothed values reach their own mean). Because
    the average is trailing, a 0→1 step at episode ``e ≥ window`` is reported at
    ``e + ceil(frac · window) − 1``: 0 for episodes 0–49 and 1 afterwards gives 58 with the defaults.
    """
    arr = _scores(curve, "curve", max_ndim=1)
    if not 0.0 < frac <= 1.0:
        raise ValueError(f"frac: must be in (0, 1], got {frac}")
    if not 0.0 < plateau_frac <= 1.0:
        raise ValueError(f"plateau_frac: must be in (0, 1], got {plateau_frac}")
    s = smooth(arr, window)
    w = min(window, arr.size) - 1
    start = s[w]
    k = max(1, math.ceil(plateau_frac * arr.size))
    plateau = float(np.mean(s[-k:]))
    target = start + frac * (plateau - start)
    tail = s[w:]
    reached = tail >= target if plateau >= start else tail <= target
    return int(w + np.argmax(reached))
