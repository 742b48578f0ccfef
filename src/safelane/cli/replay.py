"""``safelane replay``: a counterexample file played again, decision by decision."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from safelane.cli.common import JsonOpt, SimulatorOpt, check_positive, cli_errors, warn_if_numpy_is_not_libm
from safelane.config import ConfigError


@cli_errors
def replay(
    file: Path = typer.Argument(..., help="A counterexample file (--save-counterexamples).", metavar="FILE"),
    simulator: SimulatorOpt = None,
    gif: Annotated[
        Path | None, typer.Option("--gif", help="Also draw the replay (.gif or .mp4).", metavar="OUT")
    ] = None,
    last: Annotated[int, typer.Option("--last", help="Decisions of the log to print (the last N).")] = 8,
    as_json: JsonOpt = False,
) -> None:
    """Replay a saved crash, invariant break or lapse (committed shield): the decision log, and whether the event
    happens again."""
    from safelane.core.spaces import ACTION_NAMES
    from safelane.running.counterexamples import dump_json, load_counterexample, render_counterexample
    from safelane.running.counterexamples import replay as replay_counterexample

    if simulator is not None and simulator not in ("fast", "highway-env"):
        raise ConfigError(f"--simulator: got {simulator!r}; allowed: fast, highway-env")
    check_positive("--last", last)
    cx = load_counterexample(file)
    if simulator is not None and simulator != cx.env_config().simulator:
        warn_if_numpy_is_not_libm()
    result = replay_counterexample(cx, simulator)
    if gif is not None:
        render_counterexample(cx, gif)
    if as_json:
        typer.echo(dump_json(result))
    else:
        table = Table(title=f"{file}: {cx.kind} after decision {cx.step}, seed {cx.seed}, on {result.simulator}")
        for column in (
            "t [s]",
            "chosen → executed",
            "mask (L I R F S)",
            "min gap [m] per action",
            "fallback after",
            "ego lane, speed",
            "nearby (lane, dx, v)",
        ):
            table.add_column(column)
        for d in result.decisions[-last:]:
            gaps = " ".join("–" if g is None else f"{g:.1f}" for g in d.min_gap)
            mark = " BREAK" if d.invariant_break else (" CRASH" if d.collision else "")
            if d.committed is not None and d.committed["lapse"]:
                mark += f" LAPSE (cars {d.committed['lapse_cars']})"
            near = "; ".join(f"{v['lane']},{v['dx']:+.0f},{v['speed']:.0f}" for v in d.nearby[:6])
            table.add_row(
                f"{d.time:.1f}",
                f"{ACTION_NAMES[d.chosen]} → {ACTION_NAMES[d.executed]}",
                "".join("■" if m else "·" for m in d.mask),
                gaps,
                f"{d.fallback_after}{mark}",
                f"{d.ego['lane']}, {d.ego['speed']:.1f}",
                near,
            )
        Console().print(table)
        f = result.final
        gaps = " ".join("–" if g is None else f"{g:.1f}" for g in f["min_gap"])
        near = "; ".join(f"{v['lane']},{v['dx']:+.0f},{v['speed']:.0f}" for v in f["nearby"][:8])
        typer.echo(
            f"then, t = {f['time']:.1f} s: mask {''.join('■' if m else '·' for m in f['mask'])}, min gaps {gaps}, "
            f"fallback {f['fallback']}, ego lane {f['ego']['lane']} at {f['ego']['speed']:.1f} m/s; nearby {near}"
        )
        kind = f" ({result.collision_kind})" if result.collision_kind else ""
        verdict = "reproduced" if result.reproduced else "NOT reproduced"
        typer.echo(f"{verdict}: {cx.kind}{kind} after decision {cx.step} on {result.simulator}")
        if gif is not None:
            typer.echo(f"wrote {gif}")
    if not result.reproduced:
        raise typer.Exit(1)
