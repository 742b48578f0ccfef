"""Statistics for comparing RL runs, with rliable's definitions, in pure numpy.

Scores are either 1-D (one number per run/seed) or 2-D ``(runs × tasks)`` arrays, as in rliable
(Agarwal et al., 2021, "Deep RL at the edge of the statistical precipice"). Every function is pure and
deterministic: the bootstrap draws come from ``numpy.random.default_rng(seed)``.

Degenerate input is an error, never a silent NaN: empty arrays, NaN scores, ``n = 0`` trials, a
non-positive window or an ``alpha`` outside (0, 1) raise :class:`ValueError` with a one-line message.
The one exception is :func:`smooth`, which maps an empty curve to an empty curve.

Why not the ``rliable`` library itself: rliable 1.2.0 needs ``arch < 8``, and ``arch`` 7.2 fails to import
against pandas 3 (``TypeError: deprecate_kwarg() missing 1 required positional argument``), so rliable cannot
be imported beside this project's pandas. Its few definitions used here (IQM, stratified bootstrap,
performance profiles, optimality gap) are re-stated below with the same semantics.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from statistics import NormalDist
from typing import Literal, NamedTuple

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


interquartile_mean = iqm
"""The interquartile mean under its long name (same function as :func:`iqm`)."""


def optimality_gap(x: ArrayLike, gamma: float = 1.0) -> float:
    """Mean shortfall below the target ``gamma``: ``mean(max(gamma − x, 0))`` over all scores (rliable).

    In the units of the scores; 0 when every run reaches ``gamma``. For a collision-free rate with
    ``gamma = 1`` it is the mean collision rate: ``optimality_gap([1.0, 0.9, 0.7]) == 0.4 / 3``.
    """
    return float(np.mean(np.maximum(gamma - _scores(x), 0.0)))


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


def _task_matrix(scores_by_task: ArrayLike | Mapping[str, ArrayLike]) -> np.ndarray:
    """``scores_by_task`` as a checked ``(runs × tasks)`` float matrix.

    Accepts a ``(runs × tasks)`` array, a 1-D array (one task) or a mapping ``task → run scores``
    (one column per task, in the mapping's order; every task needs the same number of runs).
    """
    if isinstance(scores_by_task, Mapping):
        columns = {task: _scores(v, f"scores_by_task[{task!r}]", 1) for task, v in scores_by_task.items()}
        if not columns:
            raise ValueError("scores_by_task: no tasks given")
        counts = {task: c.size for task, c in columns.items()}
        if len(set(counts.values())) > 1:
            raise ValueError(f"scores_by_task: every task needs the same number of runs, got {counts}")
        return np.stack(list(columns.values()), axis=1)
    arr = _scores(scores_by_task, "scores_by_task")
    return arr[:, None] if arr.ndim == 1 else arr


def stratified_resample(scores_by_task: ArrayLike | Mapping[str, ArrayLike], reps: int, seed: int = 0) -> np.ndarray:
    """``reps`` stratified bootstrap samples of a ``(runs × tasks)`` score matrix: shape ``(reps, runs, tasks)``.

    Agarwal et al. (2021), "Deep RL at the edge of the statistical precipice" (rliable's
    ``StratifiedBootstrap``): each sample draws, for every task separately and independently, ``runs``
    of that task's runs with replacement. A task's column only ever holds that task's own scores, and
    every task keeps its weight, however the runs of the tasks differ. With one task it is the ordinary
    bootstrap over runs. Deterministic for a given ``seed`` (``numpy.random.default_rng``).
    """
    arr = _task_matrix(scores_by_task)
    if reps < 1:
        raise ValueError(f"reps: must be at least 1, got {reps}")
    runs, tasks = arr.shape
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, runs, size=(reps, runs, tasks))
    return arr[idx, np.arange(tasks)]


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
    with replacement, so every task keeps its weight in the statistic. :func:`stratified_bootstrap` is the
    same with the point estimate and a confidence ``level``.
    """
    arr = _scores(scores)
    _check_bootstrap(alpha, reps)
    samples = stratified_resample(arr, reps, seed)  # (reps, runs, tasks)
    draws = np.array([statistic(s) for s in samples])
    return _percentile_interval(draws, alpha)


class Estimate(NamedTuple):
    """A point estimate and its confidence interval, in the units of the scores."""

    point: float
    low: float
    high: float


def _check_level(level: float) -> None:
    if not 0.0 < level < 1.0:
        raise ValueError(f"level: must be in (0, 1), got {level}")


def _percentiles(draws: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """The ``(1 − level)/2`` and ``(1 + level)/2`` percentiles of ``draws`` along axis 0."""
    low, high = np.percentile(draws, [50 * (1 - level), 50 * (1 + level)], axis=0)
    return low, high


def stratified_bootstrap(
    scores_by_task: ArrayLike | Mapping[str, ArrayLike],
    statistic: Statistic = iqm,
    reps: int = 2000,
    seed: int = 0,
    level: float = 0.95,
) -> Estimate:
    """``statistic`` of the runs and its stratified-bootstrap percentile interval at confidence ``level``.

    Agarwal et al. (2021), rliable's practice: the ``reps`` samples of :func:`stratified_resample` (runs
    drawn with replacement within each task independently), the aggregate ``statistic`` recomputed on
    each ``(runs × tasks)`` sample, the interval between the ``(1 − level)/2`` and ``(1 + level)/2``
    percentiles of those ``reps`` values. ``point`` is ``statistic`` of the scores themselves. E.g. two
    runs scoring 20 and 24 on one task: ``point`` 22 (too few runs to trim), interval [20, 24] (a quarter of
    the samples draw a run twice). Deterministic for a given ``seed``.
    """
    _check_level(level)
    arr = _task_matrix(scores_by_task)
    samples = stratified_resample(arr, reps, seed)
    draws = np.array([statistic(s) for s in samples])
    low, high = _percentiles(draws, level)
    return Estimate(float(statistic(arr)), float(low), float(high))


class Profile(NamedTuple):
    """A performance profile: at each threshold, the fraction of runs scoring above it, with a band."""

    thresholds: np.ndarray
    fraction: np.ndarray
    low: np.ndarray
    high: np.ndarray


_CHUNK_ELEMENTS = 4_000_000
"""Largest intermediate array (elements) built at once by the vectorised bootstraps (≈ 32 MB of floats)."""


def _fraction_above(samples: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """Per sample of ``(…, runs, tasks)``, the mean over tasks of the fraction of runs above each threshold."""
    above = samples[..., None] > thresholds  # (…, runs, tasks, thresholds)
    return above.mean(axis=-3).mean(axis=-2)


def performance_profile(
    scores_by_method: Mapping[str, ArrayLike | Mapping[str, ArrayLike]],
    thresholds: ArrayLike,
    reps: int = 2000,
    seed: int = 0,
    level: float = 0.95,
) -> dict[str, Profile]:
    """Each method's score distribution: the fraction of its runs with score ``> τ`` at each threshold ``τ``.

    Agarwal et al. (2021), rliable's ``create_performance_profile``: per task the fraction of runs scoring
    strictly above ``τ``, averaged over tasks. The band is the ``level`` percentile interval over ``reps``
    stratified bootstrap samples (:func:`stratified_resample`, runs resampled within each task). Every method
    draws from ``seed`` itself, so its band does not depend on which other methods are given. Scores of a
    method are a ``(runs × tasks)`` array, a 1-D array (one task) or a mapping ``task → run scores``. E.g.
    runs scoring 20, 22, 24, 26 give 0.75 at ``τ = 21`` and 0 at ``τ = 26``.
    """
    _check_level(level)
    taus = _scores(thresholds, "thresholds", 1)
    if reps < 1:
        raise ValueError(f"reps: must be at least 1, got {reps}")
    out: dict[str, Profile] = {}
    for method, scores in scores_by_method.items():
        arr = _task_matrix(scores)
        samples = stratified_resample(arr, reps, seed)
        chunk = max(1, _CHUNK_ELEMENTS // max(1, arr.size * taus.size))
        draws = np.concatenate([_fraction_above(samples[i : i + chunk], taus) for i in range(0, reps, chunk)])
        low, high = _percentiles(draws, level)
        out[method] = Profile(taus.copy(), _fraction_above(arr, taus), low, high)
    if not out:
        raise ValueError("scores_by_method: no methods given")
    return out


def _trimmed_mean_axis(x: np.ndarray, proportion: float, axis: int) -> np.ndarray:
    """:func:`trim_mean` along one axis (the same ``int(proportion · n)`` cut each side)."""
    n = x.shape[axis]
    cut = int(proportion * n)
    return np.mean(np.take(np.sort(x, axis=axis), np.arange(cut, n - cut), axis=axis), axis=axis)


class Band(NamedTuple):
    """A curve over runs at each point (e.g. episode) and its pointwise confidence band."""

    point: np.ndarray
    low: np.ndarray
    high: np.ndarray


def curve_band(
    curves: ArrayLike,
    statistic: Literal["iqm", "mean"] = "iqm",
    reps: int = 1000,
    seed: int = 0,
    level: float = 0.95,
) -> Band:
    """The IQM (or mean) over runs of ``curves`` (``runs × points``, e.g. a learning curve per seed) at each
    point, with a pointwise percentile-bootstrap band at confidence ``level``.

    A bootstrap sample draws whole runs with replacement (a run's curve stays together, as rliable's
    learning-curve intervals); the statistic is taken over runs at every point. ``point[j]`` equals
    ``iqm(curves[:, j])`` (or the mean). Deterministic for a given ``seed``.
    """
    if statistic not in ("iqm", "mean"):
        raise ValueError(f"statistic: must be 'iqm' or 'mean', got {statistic!r}")
    _check_level(level)
    arr = _scores(curves, "curves")
    if arr.ndim != 2:
        raise ValueError(f"curves: expected 2-D (runs × points), got shape {arr.shape}")
    if reps < 1:
        raise ValueError(f"reps: must be at least 1, got {reps}")
    proportion = IQM_TRIM if statistic == "iqm" else 0.0
    runs = arr.shape[0]
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, runs, size=(reps, runs))
    chunk = max(1, _CHUNK_ELEMENTS // arr.size)
    draws = np.concatenate(
        [_trimmed_mean_axis(arr[idx[i : i + chunk]], proportion, axis=1) for i in range(0, reps, chunk)]
    )
    low, high = _percentiles(draws, level)
    return Band(_trimmed_mean_axis(arr, proportion, axis=0), low, high)


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
