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
    continuous_agent: Annotated[
        list[str] | None,
        typer.Option(
            "--continuous-agent",
            help="RATE=RUN_DIR: a trained continuous agent (safelane train --actions continuous) for that rate, "
            "played under the shield for continuous actions (repeatable).",
            metavar="RATE=DIR",
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
    agents = _rate_dirs("--agent", agent, "runs/demo/runs/robust-s0")
    continuous_agents = _rate_dirs("--continuous-agent", continuous_agent, "runs/sac-s0")
    row_list = tuple(r.strip() for r in rows.split(",") if r.strip()) if rows is not None else ROWS
    cfg = resolve_config(preset, sets, overrides={"simulator": "fast"})
    with units_progress("ceiling (chunks)") as tick:
        table = ceiling_table(
            cfg, rate_list, episodes, seed, out, agents=agents, horizon=horizon, beam=beam, workers=workers,
            progress=tick, rows=row_list, continuous_agents=continuous_agents,
        )  # fmt: skip
    if as_json:
        typer.echo(json.dumps(table))
        return
    typer.echo((out / "ceiling.md").read_text())


def _rate_dirs(option: str, items: list[str] | None, example: str) -> dict[int, str]:
    """{rate: run directory} from ``RATE=RUN_DIR`` items (a one-line error naming ``option`` otherwise)."""
    out: dict[int, str] = {}
    for item in items or []:
        rate_text, sep, path = item.partition("=")
        if not sep or not rate_text.strip().isdigit() or not path:
            raise ConfigError(f"{option}: expected RATE=RUN_DIR, e.g. 1={example} (got {item!r})")
        out[int(rate_text)] = path
    return out
