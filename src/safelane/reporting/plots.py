"""Figures from run directories. Each function returns a matplotlib ``Figure``; the caller saves it.

Figures are built with ``matplotlib.figure.Figure`` directly, not pyplot: no global state, no GUI
backend, and ``fig.savefig`` renders with Agg.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from safelane.reporting.metrics_file import METRICS_FILE, read_metrics
from safelane.reporting.stats import Band, Profile, scale_01, smooth


def plot_training_curves(
    run_dirs: Sequence[str | Path],
    window: int = 10,
    scaled: bool = False,
    labels: Sequence[str] | None = None,
) -> Figure:
    """Smoothed episode return vs episode for each run, with ε on a twin axis (dashed).

    Reads ``run_dir/metrics.csv`` (columns ``episode`` and ``return``; ``epsilon`` is drawn when
    present). Returns are smoothed with :func:`safelane.reporting.stats.smooth` (trailing ``window``-episode
    mean). ``scaled=True`` min–max scales each smoothed return curve to [0, 1] as in the paper's
    Fig. 7, to compare convergence speed regardless of final level. ``labels`` default to the run
    directories' names.
    """
    if not run_dirs:
        raise ValueError("run_dirs: no run directories given")
    dirs = [Path(d) for d in run_dirs]
    names = list(labels) if labels is not None else [d.name for d in dirs]
    if len(names) != len(dirs):
        raise ValueError(f"labels: {len(names)} labels for {len(dirs)} run directories")

    fig = Figure(figsize=(8, 4.5), layout="constrained")
    ax = fig.add_subplot()
    ax_eps = ax.twinx()
    any_eps = False
    for i, (run_dir, name) in enumerate(zip(dirs, names, strict=True)):
        path = run_dir / METRICS_FILE
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no {METRICS_FILE} in run directory {run_dir}")
        data = read_metrics(path, ["episode", "return"], optional=["epsilon"])
        curve = smooth(data["return"], window)
        if scaled and curve.size:
            curve = scale_01(curve)
        colour = f"C{i % 10}"
        ax.plot(data["episode"], curve, color=colour, label=name)
        if "epsilon" in data:
            ax_eps.plot(data["episode"], data["epsilon"], color=colour, linestyle="--", alpha=0.6)
            any_eps = True

    ax.set_xlabel("episode")
    ax.set_ylabel(f"return (scaled to [0, 1], {window}-episode mean)" if scaled else f"return ({window}-episode mean)")
    if any_eps:
        ax_eps.set_ylabel("ε (dashed)")
        ax_eps.set_ylim(0.0, 1.05)
    else:
        ax_eps.set_axis_off()
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    return fig


def plot_performance_profiles(
    panels: Sequence[tuple[str, Mapping[str, Profile]]],
    labels: Mapping[str, str] | None = None,
    title: str = "Performance profiles",
) -> Figure:
    """One panel per metric: for each method the fraction of runs scoring above each threshold, with its band.

    ``panels`` are ``(x-axis label, {method: Profile})`` pairs (:func:`safelane.reporting.stats.performance_profile`);
    the fraction is drawn as a step line and its bootstrap band shaded. ``labels`` rename methods in the legend.
    """
    if not panels:
        raise ValueError("panels: no performance profiles given")
    names = dict(labels or {})
    fig = Figure(figsize=(5 * len(panels), 4))
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, (xlabel, profiles) in zip(axes, panels, strict=True):
        for i, (method, prof) in enumerate(profiles.items()):
            colour = f"C{i % 10}"
            ax.step(prof.thresholds, prof.fraction, where="post", color=colour, label=names.get(method, method))
            ax.fill_between(prof.thresholds, prof.low, prof.high, step="post", color=colour, alpha=0.2, lw=0)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("fraction of runs with score > τ")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def plot_curve_bands(
    panels: Sequence[tuple[str, Mapping[str, Band]]],
    labels: Mapping[str, str] | None = None,
    xlabel: str = "training episode",
    title: str = "Learning curves",
    x: Sequence[float] | None = None,
) -> Figure:
    """One panel per quantity: each method's curve over runs (e.g. the IQM over seeds) with its shaded band.

    ``panels`` are ``(y-axis label, {method: Band})`` pairs (:func:`safelane.reporting.stats.curve_band`);
    point ``j`` is drawn at ``x[j]``, by default at ``j + 1`` (training episodes count from 1). ``labels`` rename
    methods in the legend.
    """
    if not panels:
        raise ValueError("panels: no curves given")
    names = dict(labels or {})
    fig = Figure(figsize=(5 * len(panels), 4))
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, (ylabel, bands) in zip(axes, panels, strict=True):
        for i, (method, band) in enumerate(bands.items()):
            colour = f"C{i % 10}"
            xs = np.arange(1, band.point.size + 1) if x is None else np.asarray(x, dtype=float)
            ax.plot(xs, band.point, color=colour, label=names.get(method, method))
            ax.fill_between(xs, band.low, band.high, color=colour, alpha=0.2, lw=0)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig
