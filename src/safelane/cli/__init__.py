"""The ``safelane`` command line: the Typer app and the registration of its commands.

Every command is a thin layer over a library function and lives in its own module of this package (one per
command group: :mod:`safelane.cli.evaluate`, :mod:`safelane.cli.train`, :mod:`safelane.cli.falsify`, …), on
the options and output helpers of :mod:`safelane.cli.common`. Progress goes to stderr, results to stdout (a rich
table, or one JSON object with ``--json``). A bad input (:class:`safelane.config.ConfigError` or ``ValueError``)
prints one line ``error: <message>`` on stderr and exits with code 2.
"""

from __future__ import annotations

from typing import Annotated

import typer

from safelane import __version__
from safelane.cli import (
    bench,
    ceiling,
    env,
    evaluate,
    falsify,
    plot,
    render,
    replay,
    reproduce,
    sim,
    stress,
    sweep,
    train,
)

app = typer.Typer(
    name="safelane",
    help="Safe tactical decision making on highways (highway-env): environments, shields, evaluation.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
)
env_app = typer.Typer(help="Inspect environment configurations.", no_args_is_help=True)
app.add_typer(env_app, name="env")
sim_app = typer.Typer(help="Check the fast simulator against highway-env.", no_args_is_help=True)
app.add_typer(sim_app, name="sim")


def _version(value: bool) -> None:
    if value:
        typer.echo(f"safelane {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: Annotated[
        bool,
        typer.Option("--version", callback=_version, is_eager=True, help="Print the version and exit."),
    ] = False,
) -> None:
    """Safe tactical decision making on highways (highway-env): environments, shields, evaluation."""


env_app.command("show")(env.env_show)
sim_app.command("check")(sim.sim_check)
for command in (
    evaluate.evaluate,
    bench.bench,
    train.train,
    reproduce.reproduce,
    sweep.sweep,
    falsify.falsify,
    ceiling.ceiling,
    replay.replay,
    stress.stress,
    render.render,
    plot.plot,
):
    app.command()(command)
