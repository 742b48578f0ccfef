"""``safelane sweep``: a hyperparameter sweep from a YAML spec."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from safelane.cli.common import AddressOpt, BackendOpt, JsonOpt, check_positive, cli_errors, units_progress


@cli_errors
def sweep(
    spec_file: Path = typer.Argument(..., help="Sweep spec (YAML; examples in configs/sweeps/).", metavar="SPEC"),
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Output directory (trials.csv, summary.md, best.yaml).")
    ] = Path("runs/sweep"),
    backend: BackendOpt = "local",
    address: AddressOpt = None,
    workers: Annotated[
        int | None, typer.Option("--workers", help="Parallel runs (local processes or local Ray CPUs; default: cores).")
    ] = None,
    episodes: Annotated[
        int | None, typer.Option("--episodes", help="Training episodes per run (overrides the spec).")
    ] = None,
    test_episodes: Annotated[
        int | None, typer.Option("--test-episodes", help="Test episodes per run (overrides the spec).")
    ] = None,
    seeds: Annotated[int | None, typer.Option("--seeds", help="Seeds per point (overrides the spec).")] = None,
    as_json: JsonOpt = False,
) -> None:
    """Search hyperparameters: every point × seed trained and tested, ranked by the spec's objective."""
    from safelane.running.sweeps import load_sweep_spec, run_sweep

    for option, value in (("--episodes", episodes), ("--test-episodes", test_episodes), ("--seeds", seeds)):
        if value is not None:
            check_positive(option, value)
    if workers is not None:
        check_positive("--workers", workers)
    spec = load_sweep_spec(spec_file, {"episodes": episodes, "test_episodes": test_episodes, "seeds": seeds})
    with units_progress(f"sweep {spec.name} (trial × seed)") as tick:
        summary = run_sweep(spec, out, backend=backend, workers=workers, address=address, progress=tick)
    if as_json:
        typer.echo(json.dumps(summary))
        return
    typer.echo((out / "summary.md").read_text())
    best = summary["best"]
    if best is None:
        typer.echo("no trial met the constraints on every seed")
    else:
        typer.echo(f"best: t{best['trial']:03d} {best['params']} → {out / 'best.yaml'}")
