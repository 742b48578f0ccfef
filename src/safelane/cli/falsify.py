"""``safelane falsify``: a falsification campaign (a grid or a search) from a YAML spec."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from safelane.cli.common import (
    AddressOpt,
    BackendOpt,
    JsonOpt,
    SetOpt,
    check_actions,
    check_positive,
    check_seed,
    cli_errors,
    units_progress,
)


@cli_errors
def falsify(
    spec_file: Path = typer.Argument(
        ..., help="Campaign spec (YAML; configs/falsify/grid.yaml, or a search: search_cem.yaml).", metavar="SPEC"
    ),
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Output directory (cells.csv, summary.md, counterexamples/).")
    ] = Path("runs/falsify"),
    backend: BackendOpt = "local",
    address: AddressOpt = None,
    workers: Annotated[int | None, typer.Option("--workers", help="Parallel cells (default: cores).")] = None,
    episodes: Annotated[
        int | None, typer.Option("--episodes", help="Episodes per cell or search sample (overrides the spec).")
    ] = None,
    sample: Annotated[int | None, typer.Option("--sample", help="Play this many cells drawn at random.")] = None,
    shard: Annotated[
        str | None,
        typer.Option(
            "--shard",
            help="Play one shard of the grid, K/N: the cells K-1, K-1+N, … (their seeds as in the whole grid), for a "
            "campaign split over machines or days.",
            metavar="K/N",
        ),
    ] = None,
    merge: Annotated[
        list[Path] | None,
        typer.Option(
            "--merge",
            help="Play nothing: merge these shards' folders (each with campaign.json and summary.json, as --shard "
            "writes them) into --out's summary (repeatable).",
            metavar="DIR",
        ),
    ] = None,
    seed: Annotated[
        int | None,
        typer.Option(
            "--seed",
            help="Traffic seed (overrides the spec's; 0, the default, plays the published episodes; another draws "
            "fresh traffic, recorded in campaign.json and summary.json).",
        ),
    ] = None,
    shield: Annotated[
        str | None,
        typer.Option(
            "--shield",
            help="Play the spec under this shield: nominal, robust, committed, or with a driver mixture (preset "
            "hidden-types) omniscient, belief (default: the spec's).",
            metavar="MODE",
        ),
    ] = None,
    actions: Annotated[
        str | None,
        typer.Option(
            "--actions",
            help="The ego's actions (sets the spec's actions): discrete, the paper's 5 meta-actions, or continuous, "
            "acceleration and steering (policies random, faster, weave; shield committed) (default: the spec's).",
            metavar="KIND",
        ),
    ] = None,
    sets: SetOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Drive the shield over a grid of traffic conditions, or search them (a spec with a search section:
    cross-entropy method toward the most invariant breaks): collisions, invariant breaks (classified), files.
    With continuous actions: collisions against the shield's promise, lapses, projections, episodes off the road."""
    from safelane.config import ConfigError
    from safelane.running.falsify.grid import merge_shards, run_campaign
    from safelane.running.falsify.search import SearchSpec, load_falsify_spec, run_search

    for option, value in (("--episodes", episodes), ("--sample", sample), ("--workers", workers)):
        if value is not None:
            check_positive(option, value)
    if seed is not None:
        check_seed(seed)
    check_actions(actions)
    if merge and shard is not None:
        raise ConfigError("--merge: merges shards into the whole campaign's summary; allowed: without --shard")
    overrides = {"episodes": episodes, "sample": sample, "seed": seed, "shield": shield, "actions": actions,
                 "shard": shard}  # fmt: skip
    spec = load_falsify_spec(spec_file, overrides)
    if sets:  # after the spec's own: a campaign's record keeps them, so a resume under others is refused
        spec = spec.model_copy(update={"sets": [*spec.sets, *sets]})
    if merge:
        if isinstance(spec, SearchSpec):
            raise ConfigError(f"--merge: {spec_file} is a search; allowed: a grid's shards")
        summary = merge_shards(spec, merge, out)
    elif isinstance(spec, SearchSpec):
        with units_progress(f"falsify search {spec.name} (samples)") as tick:
            summary = run_search(spec, out, backend=backend, workers=workers, address=address, progress=tick)
    else:
        with units_progress(f"falsify {spec.name} (cells)") as tick:
            summary = run_campaign(spec, out, backend=backend, workers=workers, address=address, progress=tick)
    if as_json:
        typer.echo(json.dumps(summary))
        return
    typer.echo((out / "summary.md").read_text())
    if not merge:
        typer.echo(f"counterexamples: {out / 'counterexamples'} (safelane replay FILE)")
