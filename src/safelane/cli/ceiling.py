"""``safelane ceiling``: the perfect-foresight planner's speed ceiling against the shielded probe."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from safelane.cli.common import (
    JsonOpt,
    PresetOpt,
    SeedOpt,
    SetOpt,
    check_positive,
    check_seed,
    cli_errors,
    resolve_config,
    units_progress,
)
from safelane.config import ConfigError


@cli_errors
def ceiling(
    preset: PresetOpt = "fast",
    sets: SetOpt = None,
    rates: Annotated[str, typer.Option("--rates", help="Decision rates per second, comma-separated.")] = "1,2,3",
    episodes: Annotated[int, typer.Option("--episodes", "-n", help="Episodes per row and rate.")] = 100,
    seed: SeedOpt = 5000,
    agent: Annotated[
        list[str] | None,
        typer.Option(
            "--agent", help="RATE=RUN_DIR: a trained robust agent for that rate (repeatable).", metavar="RATE=DIR"
        ),
    ] = None,
    horizon: Annotated[float, typer.Option("--horizon", help="Planner look-ahead [s].")] = 4.0,
    beam: Annotated[int, typer.Option("--beam", help="Planner sequences kept per depth.")] = 16,
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Output directory (ceiling.json, ceiling.md, cells/).")
    ] = Path("runs/ceiling"),
    workers: Annotated[int | None, typer.Option("--workers", help="Parallel chunks (default: cores).")] = None,
    rows: Annotated[
        str | None,
        typer.Option(
            "--rows",
            help="Rows to play, comma-separated (default: all; the table lists every row played into --out).",
            metavar="LIST",
        ),
    ] = None,
    as_json: JsonOpt = False,
) -> None:
    """The price of robustness: a perfect-foresight planner unmasked / under each mask, the probe, an agent."""
    from safelane.running.foresight import ROWS, ceiling_table

    check_positive("--episodes", episodes)
    check_positive("--beam", beam)
    check_seed(seed)
    try:
        rate_list = [int(r) for r in rates.split(",") if r.strip()]
    except ValueError:
        raise ConfigError(f"--rates: expected comma-separated integers, e.g. 1,2,3 (got {rates!r})") from None
    agents: dict[int, str] = {}
    for item in agent or []:
        rate_text, sep, path = item.partition("=")
        if not sep or not rate_text.strip().isdigit() or not path:
            raise ConfigError(f"--agent: expected RATE=RUN_DIR, e.g. 1=runs/demo/runs/robust-s0 (got {item!r})")
        agents[int(rate_text)] = path
    row_list = tuple(r.strip() for r in rows.split(",") if r.strip()) if rows is not None else ROWS
    cfg = resolve_config(preset, sets, overrides={"simulator": "fast"})
    with units_progress("ceiling (chunks)") as tick:
        table = ceiling_table(
            cfg, rate_list, episodes, seed, out, agents=agents, horizon=horizon, beam=beam, workers=workers,
            progress=tick, rows=row_list,
        )  # fmt: skip
    if as_json:
        typer.echo(json.dumps(table))
        return
    typer.echo((out / "ceiling.md").read_text())
