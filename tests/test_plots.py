"""The metrics file read and written, and training-curve figures from synthetic run directories."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

from safelane.reporting.metrics_file import METRIC_COLUMNS, MetricsAppender, read_metrics
from safelane.reporting.metrics_file import write_metrics as write_metrics_file
from safelane.reporting.plots import plot_training_curves
from safelane.reporting.stats import smooth


def write_metrics(run_dir: Path, returns: list[float], epsilon: bool = True) -> None:
    run_dir.mkdir(parents=True)
    header = "episode,return,epsilon,collision,mean_speed" if epsilon else "episode,return,collision,mean_speed"
    lines = [header]
    for i, r in enumerate(returns):
        eps = f"{max(0.05, 1.0 - 0.1 * i):.2f}," if epsilon else ""
        lines.append(f"{i},{r},{eps}{'True' if i % 3 == 0 else 'False'},{20 + i}")
    (run_dir / "metrics.csv").write_text("\n".join(lines) + "\n")


def test_metrics_file_written_and_appended_reads_back(tmp_path: Path) -> None:
    """What the training loops write (a whole file, then rows appended) is what the reader returns."""
    path = tmp_path / "metrics.csv"
    first = {"episode": 1, "return": 0.1 + 0.2, "collision": 0, "mean_loss": None, "wall_time_s": 1.23456789}
    write_metrics_file(path, [first])
    with MetricsAppender(path) as appender:
        appender.append({"episode": 2, "return": -3.0, "collision": 1, "mean_loss": 0.5, "wall_time_s": 2.0})
    assert path.read_text().splitlines()[0] == ",".join(METRIC_COLUMNS)
    data = read_metrics(path, ["episode", "return", "collision", "mean_loss", "wall_time_s"])
    np.testing.assert_array_equal(data["episode"], [1.0, 2.0])
    assert data["return"][0] == 0.1 + 0.2  # full precision: repr, not a rounded format
    np.testing.assert_array_equal(data["mean_loss"], [np.nan, 0.5])
    np.testing.assert_array_equal(data["wall_time_s"], [1.234568, 2.0])  # clocks to the µs


def test_read_metrics_parses_numbers_and_booleans(tmp_path: Path) -> None:
    write_metrics(tmp_path / "a", [1.0, 2.5, 4.0])
    data = read_metrics(tmp_path / "a" / "metrics.csv", ["return", "collision"], optional=["missing"])
    np.testing.assert_array_equal(data["return"], [1.0, 2.5, 4.0])
    np.testing.assert_array_equal(data["collision"], [1.0, 0.0, 0.0])
    assert "missing" not in data
    (tmp_path / "b.csv").write_text("episode,mean_loss\n1,\n2,0.5\n")
    np.testing.assert_array_equal(read_metrics(tmp_path / "b.csv", ["mean_loss"])["mean_loss"], [np.nan, 0.5])
    with pytest.raises(ValueError, match="nope"):
        read_metrics(tmp_path / "a" / "metrics.csv", ["nope"])


def test_plot_training_curves_draws_smoothed_returns_and_epsilon(tmp_path: Path) -> None:
    returns = [0.0, 0.0, 10.0, 10.0, 10.0, 10.0]
    write_metrics(tmp_path / "dqn", returns)
    write_metrics(tmp_path / "masked", [5.0] * 6, epsilon=False)
    fig = plot_training_curves([tmp_path / "dqn", tmp_path / "masked"], window=2)
    assert isinstance(fig, Figure)
    ax, ax_eps = fig.axes
    lines = ax.get_lines()
    assert [line.get_label() for line in lines] == ["dqn", "masked"]
    np.testing.assert_array_equal(lines[0].get_ydata(), smooth(returns, 2))  # [0, 0, 5, 10, 10, 10]
    np.testing.assert_array_equal(lines[0].get_xdata(), np.arange(6))
    assert len(ax_eps.get_lines()) == 1  # only the run that logged ε
    np.testing.assert_allclose(ax_eps.get_lines()[0].get_ydata()[:2], [1.0, 0.9])
    fig.savefig(tmp_path / "curves.png")
    assert (tmp_path / "curves.png").stat().st_size > 0


def test_plot_training_curves_scaled_like_fig7(tmp_path: Path) -> None:
    write_metrics(tmp_path / "run", [2.0, 4.0, 6.0])
    fig = plot_training_curves([tmp_path / "run"], window=1, scaled=True, labels=["A"])
    np.testing.assert_array_equal(fig.axes[0].get_lines()[0].get_ydata(), [0.0, 0.5, 1.0])


def test_plot_training_curves_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="run_dirs"):
        plot_training_curves([])
    with pytest.raises(FileNotFoundError, match=r"metrics\.csv"):
        plot_training_curves([tmp_path / "absent"])
    write_metrics(tmp_path / "run", [1.0])
    with pytest.raises(ValueError, match="labels"):
        plot_training_curves([tmp_path / "run"], labels=["a", "b"])


def test_profile_and_band_figures_draw_one_panel_per_metric() -> None:
    from safelane.reporting.plots import plot_curve_bands, plot_performance_profiles
    from safelane.reporting.stats import curve_band, performance_profile

    profiles = performance_profile({"a": [1.0, 2.0, 3.0], "b": [2.0, 2.0]}, np.linspace(0, 4, 9), reps=50)
    fig = plot_performance_profiles([("speed", profiles), ("rate", profiles)], labels={"a": "A"})
    assert len(fig.axes) == 2
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == ["A", "b"]
    bands = {"a": curve_band(np.arange(12.0).reshape(3, 4), reps=50)}
    fig = plot_curve_bands([("return", bands)])
    assert len(fig.axes) == 1
    np.testing.assert_array_equal(fig.axes[0].lines[0].get_xdata(), [1, 2, 3, 4])
    with pytest.raises(ValueError, match="panels"):
        plot_performance_profiles([])
    with pytest.raises(ValueError, match="panels"):
        plot_curve_bands([])
