"""``safelane plot``: a run's training curves."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from safelane.cli.common import cli_errors
from safelane.config import ConfigError


@cli_errors
def plot(
    run_dirs: Annotated[list[Path], typer.Argument(help="One or more run directories.", metavar="RUN_DIR...")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output PNG.")] = Path("training_curves.png"),
    scaled: Annotated[bool, typer.Option("--scaled", help="Scale each curve to [0, 1] (paper Fig. 7).")] = False,
) -> None:
    """Plot training curves (smoothed return, ε) of one or several runs."""
    from safelane.reporting.plots import plot_training_curves

    for d in run_dirs:
        if not (d / "metrics.csv").exists():
            raise ConfigError(f"RUN_DIR {d}: no metrics.csv (not a training run)")
    fig = plot_training_curves(run_dirs, scaled=scaled)
    fig.savefig(out, dpi=110)
    typer.echo(f"wrote {out}")
