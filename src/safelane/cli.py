"""The ``safelane`` command line: parse, call the library, print.

Every command is a thin layer over a library function (:mod:`safelane.evaluation`,
:mod:`safelane.bench`, :mod:`safelane.config`). Progress goes to stderr, results to stdout (a rich
table, or one JSON object with ``--json``). A bad input (:class:`safelane.config.ConfigError` or
``ValueError``) prints one line ``error: <message>`` on stderr and exits with code 2.
"""

from __future__ import annotations

import functools
import json
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any, NoReturn, TypeVar, get_args

import typer
import yaml
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from safelane import __version__
from safelane.config import ENV_PRESETS, ConfigError, SafelaneConfig, ShieldConfig, config_to_dict, load_config

SHIELD_CHOICES: tuple[str, ...] = get_args(ShieldConfig.model_fields["mode"].annotation)
"""Values of ``--shield`` (``shield.mode``)."""

EXIT_USAGE = 2
"""Exit code of a bad input (same as the option parser's own usage errors)."""

app = typer.Typer(
    name="safelane",
    help="Safe tactical decision making on highways (highway-env): environments, shields, evaluation.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
)
env_app = typer.Typer(help="Inspect environment configurations.", no_args_is_help=True)
app.add_typer(env_app, name="env")

stdout = Console()
stderr = Console(stderr=True)

# --- shared options -------------------------------------------------------------------------------

PresetOpt = Annotated[
    str,
    typer.Option("--preset", "-p", help=f"Environment preset: {', '.join(ENV_PRESETS)}.", metavar="PRESET"),
]
SetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="Override a config key, KEY=VALUE with a YAML value (repeatable), e.g. env.lanes_count=5.",
        metavar="KEY=VALUE",
    ),
]
ShieldOpt = Annotated[
    str | None,
    typer.Option(
        "--shield",
        help=f"Safety shield, sets shield.mode: {', '.join(SHIELD_CHOICES)} (default: the config's).",
        metavar="MODE",
    ),
]
EpisodesOpt = Annotated[int, typer.Option("--episodes", "-n", help="Number of episodes (>= 1).")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Seed of the first episode; episode i uses seed + i.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print one JSON object on stdout instead of a table.")]

F = TypeVar("F", bound=Callable[..., Any])


def fail(message: str) -> NoReturn:
    """Print ``error: <message>`` (one line) on stderr and exit with code 2."""
    one_line = " ".join(str(message).split())
    typer.echo(f"error: {one_line}", err=True)
    raise typer.Exit(EXIT_USAGE)


def cli_errors(fn: F) -> F:
    """Turn ConfigError / ValueError raised by a command into one ``error:`` line and exit code 2."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except (ConfigError, ValueError) as err:
            fail(str(err))

    return wrapper  # type: ignore[return-value]


def check_positive(option: str, value: int) -> None:
    """Raise a ConfigError naming ``option`` unless ``value >= 1``."""
    if value < 1:
        raise ConfigError(f"{option}: must be >= 1 (got {value})")


def check_seed(value: int) -> None:
    """Raise a ConfigError unless the seed is a non-negative integer (what gymnasium accepts)."""
    if value < 0:
        raise ConfigError(f"--seed: must be >= 0 (got {value})")


def resolve_config(
    preset: str,
    sets: list[str] | None,
    shield: str | None = None,
    overrides: dict[str, Any] | None = None,
) -> SafelaneConfig:
    """The config of a command: ``preset``, then ``--set`` strings, then ``--shield``, then ``overrides``."""
    merged: dict[str, Any] = {}
    if shield is not None:
        if shield not in SHIELD_CHOICES:
            raise ConfigError(f"--shield: unknown shield '{shield}'; allowed: {', '.join(SHIELD_CHOICES)}")
        merged["shield.mode"] = shield
    merged.update(overrides or {})
    return load_config(preset, sets=sets, overrides=merged)


@contextmanager
def episode_progress(description: str, total: int) -> Iterator[Callable[[int, Any], None]]:
    """A rich progress bar on stderr; yields a callback ``(episode_index, record)`` that advances it."""
    progress = Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=stderr,
        transient=True,
        disable=not stderr.is_terminal,  # no bar in logs or pipes
    )
    with progress:
        task = progress.add_task(description, total=total)
        yield lambda index, record: progress.update(task, completed=index + 1)


def print_json(data: dict[str, Any]) -> None:
    """One JSON object on one line of stdout."""
    sys.stdout.write(json.dumps(data) + "\n")
    sys.stdout.flush()


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, dict):
        return ", ".join(f"{k} {_fmt(v)}" for k, v in value.items())
    if isinstance(value, list):
        return ", ".join("-" if v is None else _fmt(v) for v in value)
    return str(value)


def print_table(title: str, rows: dict[str, Any], units: dict[str, str] | None = None) -> None:
    """A two-column (metric, value) rich table on stdout."""
    table = Table(title=title)
    table.add_column("metric", style="bold")
    table.add_column("value", justify="right")
    table.add_column("unit")
    for key, value in rows.items():
        table.add_row(key, _fmt(value), (units or {}).get(key, ""))
    stdout.print(table)


# --- commands ---------------------------------------------------------------------------------------


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


@env_app.command("show")
@cli_errors
def env_show(preset: PresetOpt = "fast", sets: SetOpt = None, shield: ShieldOpt = None) -> None:
    """Print the resolved environment configuration as YAML."""
    cfg = resolve_config(preset, sets, shield)
    sys.stdout.write(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))


EVALUATE_UNITS = {
    "collision_rate": "per episode",
    "mean_speed": "m/s",
    "mean_length": "decisions",
    "time_to_collision": "s",
    "shield_intervention_rate": "per decision",
    "fallback_rate": "per decision",
    "wall_time_s": "s",
}


@app.command()
@cli_errors
def evaluate(
    run_dir: Path | None = typer.Argument(
        None, help="A trained run to evaluate (not supported yet: use --policy).", metavar="RUN_DIR"
    ),
    policy: Annotated[
        str | None,
        typer.Option("--policy", help="Fixed policy: random, idle, faster, slower.", metavar="POLICY"),
    ] = None,
    episodes: EpisodesOpt = 20,
    seed: SeedOpt = 0,
    preset: PresetOpt = "fast",
    sets: SetOpt = None,
    shield: ShieldOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Evaluate a policy: collisions, speed, return, time to collision, shield activity.

    A fixed policy cannot read the shield's mask, so with a shield it runs with
    shield.override=true (unsafe actions replaced by the closest safe one) unless --set says otherwise.
    """
    from safelane.evaluation import FIXED_POLICIES, evaluate_fixed

    if run_dir is not None:
        raise ConfigError("evaluate RUN_DIR: trained runs are not supported yet")
    if policy is None:
        raise ConfigError(f"evaluate: give --policy (one of {', '.join(FIXED_POLICIES)})")
    if policy not in FIXED_POLICIES:
        raise ConfigError(f"--policy: unknown policy '{policy}'; allowed: {', '.join(FIXED_POLICIES)}")
    check_positive("--episodes", episodes)
    check_seed(seed)
    cfg = resolve_config(preset, sets, shield)
    override_set = any(s.split("=", 1)[0].strip() == "shield.override" for s in sets or [])
    if cfg.shield.mode != "none" and not override_set:
        cfg = resolve_config(preset, sets, shield, overrides={"shield.override": True})
    with episode_progress(f"evaluate {policy}", episodes) as advance:
        summary = evaluate_fixed(cfg, policy, episodes, seed, progress=advance)
    if as_json:
        print_json(summary)
        return
    title = f"{policy} on {cfg.preset} ({cfg.env_id}), shield {cfg.shield.mode}, seeds {seed}..{seed + episodes - 1}"
    print_table(title, summary, EVALUATE_UNITS)


BENCH_UNITS = {
    "env_steps_per_s": "decisions/s",
    "shielded_env_steps_per_s": "decisions/s",
    "shield_overhead_ratio": "shielded ÷ raw",
    "shield_mask_us_median": "µs",
    "obs_us_median": "µs",
    "wall_time_s": "s",
}


@app.command()
@cli_errors
def bench(
    episodes: EpisodesOpt = 10,
    seed: SeedOpt = 0,
    shield: Annotated[
        str, typer.Option("--shield", help="Shield to measure: nominal or robust.", metavar="MODE")
    ] = "robust",
    as_json: JsonOpt = False,
) -> None:
    """Measure decisions/s raw and shielded (interleaved episodes), mask and observation cost."""
    from safelane.bench import BENCH_SHIELDS, run_bench

    check_positive("--episodes", episodes)
    check_seed(seed)
    if shield not in BENCH_SHIELDS:
        raise ConfigError(f"--shield: bench measures a shield; allowed: {', '.join(BENCH_SHIELDS)}")
    with episode_progress("bench", episodes) as advance:
        result = run_bench(episodes, seed, shield=shield, progress=lambda i: advance(i, None))
    if as_json:
        print_json(result)
        return
    print_table(f"safelane bench: {result['preset']} preset, random policy, {shield} shield", result, BENCH_UNITS)


if __name__ == "__main__":  # pragma: no cover
    app()
