"""``safelane sim check``: the fast simulator checked against highway-env."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from safelane.cli.common import (
    EpisodesOpt,
    JsonOpt,
    PresetOpt,
    SeedOpt,
    SetOpt,
    check_positive,
    check_seed,
    cli_errors,
    print_json,
    resolve_config,
    stdout,
    units_progress,
    warn_if_numpy_is_not_libm,
)
from safelane.config import ConfigError


@cli_errors
def sim_check(
    preset: PresetOpt = "fast",
    sets: SetOpt = None,
    episodes: EpisodesOpt = 20,
    seed: SeedOpt = 0,
    stat_episodes: Annotated[
        int,
        typer.Option(
            "--stat-episodes",
            help="Episodes per policy and simulator for the statistical tests (0: trajectories only).",
        ),
    ] = 0,
    workers: Annotated[int | None, typer.Option("--workers", help="Parallel processes (default: cores).")] = None,
    record: Annotated[
        Path | None,
        typer.Option(
            "--record",
            help="JSON-lines file: each finished unit of work is appended at once; a re-run with the same "
            "file resumes (a long check shows its partial results there).",
        ),
    ] = None,
    continuous: Annotated[
        bool,
        typer.Option(
            "--continuous/--no-continuous",
            help="Also check an ego under highway-env's ContinuousAction (the simulators alone, as many "
            "episodes): reported under 'continuous'.",
        ),
    ] = True,
    as_json: JsonOpt = False,
) -> None:
    """Compare the fast simulator with highway-env on a configuration: trajectories and statistics."""
    from safelane.running.simcheck import run_sim_check

    check_positive("--episodes", episodes)
    if workers is not None:
        check_positive("--workers", workers)
    check_seed(seed)
    if stat_episodes < 0:
        raise ConfigError(f"--stat-episodes: must be >= 0 (got {stat_episodes})")
    cfg = resolve_config(preset, sets)
    warn_if_numpy_is_not_libm()
    with units_progress("sim check") as tick:
        result = run_sim_check(
            cfg,
            episodes,
            seed,
            stat_episodes=stat_episodes,
            workers=workers or os.cpu_count() or 1,
            record=record,
            progress=tick,
            continuous=continuous,
        )
    if as_json:
        print_json(result)
        return
    tolerance = result["tolerance"]
    _print_check(result, episodes, stat_episodes, tolerance)
    section = result["continuous"]
    if section is not None:
        policies = ", ".join(section["policies"])
        stdout.print(f"continuous actions ({section['action']['type']} ego, the simulators alone; {policies}):")
        _print_check(section, episodes, stat_episodes, tolerance)
        stdout.print(f"snapshots: {section['snapshot_equal_fraction']:.3f} of {episodes} episodes equal at every step")


def _print_check(result: dict, episodes: int, stat_episodes: int, tolerance: float) -> None:
    """One check's lines: trajectory agreement, its divergences, the tests' table and the replay."""
    stdout.print(
        f"trajectories: {result['trajectory_match_fraction']:.3f} of {episodes} episodes matched within "
        f"{tolerance:g} (m, m/s, rad); {result['bit_identical_fraction']:.3f} bit-identical"
    )
    for d in result["divergences"]:
        stdout.print(f"  seed {d['seed']} ({d['policy']}): step {d['first_step']}: {d['cause']}")
    if result["tests"]:
        table = Table(title=f"{stat_episodes} episodes per policy and simulator")
        for col in ("policy", "metric", "highway-env", "fast", "p-value", "Holm"):
            table.add_column(col)
        for t in result["tests"]:
            values = (f"{t['highway_env']:.4g}", f"{t['fast']:.4g}", f"{t['p_value']:.3g}", f"{t['p_value_holm']:.3g}")
            table.add_row(t["policy"], t["metric"], *values)
        stdout.print(table)
        stdout.print(
            f"replay: {result['replay_identical_fraction']:.3f} of highway-env's {result['replay_episodes']} "
            "statistics episodes came out the same on the fast simulator (same seeds, same policies)"
        )
