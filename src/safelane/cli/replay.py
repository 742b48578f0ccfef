"""``safelane replay``: a counterexample file played again, decision by decision."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console
from rich.table import Table

from safelane.cli.common import (
    JsonOpt,
    SimulatorOpt,
    check_actions,
    check_positive,
    cli_errors,
    warn_if_numpy_is_not_libm,
)
from safelane.config import ConfigError

if TYPE_CHECKING:
    from safelane.running.counterexamples import ReplayResult


@cli_errors
def replay(
    file: Path = typer.Argument(..., help="A counterexample file (--save-counterexamples).", metavar="FILE"),
    simulator: SimulatorOpt = None,
    actions: Annotated[
        str | None,
        typer.Option(
            "--actions",
            help="The action set the file must hold: discrete (meta-actions) or continuous (acceleration and "
            "steering, replayed exactly as float32) (default: the file's own).",
            metavar="KIND",
        ),
    ] = None,
    gif: Annotated[
        Path | None, typer.Option("--gif", help="Also draw the replay (.gif or .mp4).", metavar="OUT")
    ] = None,
    last: Annotated[int, typer.Option("--last", help="Decisions of the log to print (the last N).")] = 8,
    as_json: JsonOpt = False,
) -> None:
    """Replay a saved crash, invariant break or lapse (committed shield): the decision log, and whether the event
    happens again (with continuous actions: the controls chosen and executed, the shield's verdicts)."""
    from safelane.core.spaces import ACTION_NAMES
    from safelane.running.counterexamples import dump_json, load_counterexample, render_counterexample
    from safelane.running.counterexamples import replay as replay_counterexample

    if simulator is not None and simulator not in ("fast", "highway-env"):
        raise ConfigError(f"--simulator: got {simulator!r}; allowed: fast, highway-env")
    check_positive("--last", last)
    check_actions(actions)
    cx = load_counterexample(file)
    held = cx.env_config().actions
    if actions is not None and actions != held:
        raise ConfigError(f"--actions: {file} holds {held} actions; allowed for it: {held}")
    if gif is not None and held == "continuous":
        raise ConfigError("--gif: draws meta-action episodes with their mask; allowed with continuous actions: none")
    if simulator is not None and simulator != cx.env_config().simulator:
        warn_if_numpy_is_not_libm()
    result = replay_counterexample(cx, simulator)
    if gif is not None:
        render_counterexample(cx, gif)
    if as_json:
        typer.echo(dump_json(result))
    elif held == "continuous":
        _print_controls(file, result, last)
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


def _print_controls(file: Path, result: ReplayResult, last: int) -> None:
    """The decision log of a replay with continuous actions: the controls chosen and executed, the shield's verdict."""
    from safelane.running.counterexamples import LAPSE_KINDS
    cx = result.counterexample
    # The shield for continuous actions finds a lapse when it judges the decision, before its action runs.
    when = f"{'at' if cx.kind in LAPSE_KINDS else 'after'} decision {cx.step}"
    table = Table(title=f"{file}: {cx.kind} {when}, seed {cx.seed}, on {result.simulator}")
    for column in (
        "t [s]", "chosen → executed (acc, steer)", "projection", "certified, plan-forced", "ego lane, speed", "event",
        "nearby (lane, dx, v)",
    ):  # fmt: skip
        table.add_column(column)
    for d in result.decisions[-last:]:
        verdict = d.committed
        events = ["CRASH"] * d.collision + ["OFF ROAD"] * bool(d.off_road)
        if verdict is not None and verdict["lapse"]:
            events.append(f"LAPSE (cars {verdict['lapse_cars']})")
        table.add_row(
            f"{d.time:.1f}",
            f"{_controls(d.chosen)} → {_controls(d.executed)}",
            "–" if verdict is None else f"{verdict['projection_distance']:.3f}",
            "–" if verdict is None else f"{verdict['certified']}, {verdict['plan_forced']}",
            f"{d.ego['lane']}, {d.ego['speed']:.1f}",
            " ".join(events),
            "; ".join(f"{v['lane']},{v['dx']:+.0f},{v['speed']:.0f}" for v in d.nearby[:6]),
        )
    Console().print(table)
    f = result.final
    near = "; ".join(f"{v['lane']},{v['dx']:+.0f},{v['speed']:.0f}" for v in f["nearby"][:8])
    typer.echo(
        f"then, t = {f['time']:.1f} s: ego lane {f['ego']['lane']} at {f['ego']['speed']:.1f} m/s"
        f"{', off the road' if f['off_road'] else ''}; nearby {near}"
    )
    kind = f" ({result.collision_kind})" if result.collision_kind else ""
    verdict_line = "reproduced" if result.reproduced else "NOT reproduced"
    executed = ", the shield's actions bit for bit" if cx.executed is not None and result.reproduced else ""
    typer.echo(f"{verdict_line}: {cx.kind}{kind} {when} on {result.simulator}{executed}")


def _controls(action: int | list[float]) -> str:
    """``[acceleration, steering]`` [normalised] as text."""
    acceleration, steering = action  # type: ignore[misc]
    return f"{acceleration:+.3f}, {steering:+.3f}"
