"""What every ``safelane`` command shares: the options, the one-line error of a bad input, progress bars,
tables and JSON on stdout.

A bad input (:class:`safelane.config.ConfigError` or ``ValueError``) prints one line ``error: <message>`` on
stderr and exits with code 2 (:func:`cli_errors`). Progress goes to stderr, results to stdout (a rich table,
or one JSON object with ``--json``).
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
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from safelane.config import ENV_PRESETS, ConfigError, SafelaneConfig, ShieldConfig, load_config, parse_set

SHIELD_CHOICES: tuple[str, ...] = get_args(ShieldConfig.model_fields["mode"].annotation)
"""Values of ``--shield`` (``shield.mode``)."""
ACTIONS_CHOICES: tuple[str, ...] = get_args(SafelaneConfig.model_fields["actions"].annotation)
"""Values of ``--actions`` (``actions``)."""

EXIT_USAGE = 2
"""Exit code of a bad input (same as the option parser's own usage errors)."""

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
SimulatorOpt = Annotated[
    str | None,
    typer.Option(
        "--simulator",
        help="Simulator (sets simulator=): highway-env, the reference, or fast (default: the config's).",
        metavar="SIM",
    ),
]
TrainSimulatorOpt = Annotated[
    str | None,
    typer.Option(
        "--simulator",
        help="Simulator (sets simulator=): fast (default; bit-identical to highway-env on the checked "
        "configurations, `safelane sim check`) or highway-env, the reference (a resumed run keeps its own).",
        metavar="SIM",
    ),
]
ActionsOpt = Annotated[
    str | None,
    typer.Option(
        "--actions",
        help="The ego's actions (sets actions=): discrete, the paper's 5 meta-actions, or continuous, "
        "acceleration and steering (default: the config's).",
        metavar="KIND",
    ),
]
EpisodesOpt = Annotated[int, typer.Option("--episodes", "-n", help="Number of episodes (>= 1).")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Random seed: the same seed gives the same numbers.")]
TrafficSeedOpt = Annotated[
    int,
    typer.Option(
        "--seed",
        help="Traffic seed: 0 plays the published episodes, another draws fresh traffic (recorded in the results).",
    ),
]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print one JSON object on stdout instead of a table.")]
CounterexamplesOpt = Annotated[
    Path | None,
    typer.Option(
        "--save-counterexamples",
        help="Save every crash, invariant break and lapse (committed shield) as a replayable file in this directory "
        "(safelane replay FILE).",
        metavar="DIR",
    ),
]
BackendOpt = Annotated[
    str,
    typer.Option(
        "--backend",
        help="Where runs execute: local (a process pool here) or ray (Ray Tune; pip install 'safelane[ray]').",
        metavar="local|ray",
    ),
]
AddressOpt = Annotated[
    str | None,
    typer.Option(
        "--address",
        help="With --backend ray: the cluster (auto = the one `ray start --head` started; default: a local "
        "Ray instance for this job).",
    ),
]

F = TypeVar("F", bound=Callable[..., Any])


def fail(message: str) -> NoReturn:
    """Print ``error: <message>`` (one line) on stderr and exit with code 2."""
    one_line = " ".join(str(message).split())
    typer.echo(f"error: {one_line}", err=True)
    raise typer.Exit(EXIT_USAGE)


def cli_errors(fn: F) -> F:
    """Turn ConfigError / ValueError / OSError raised by a command into one ``error:`` line and exit code 2."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except (ConfigError, ValueError) as err:
            fail(str(err))
        except OSError as err:  # full disk, unwritable directory…: earlier files are left intact
            where = f"{err.filename}: " if err.filename else ""
            fail(f"{where}{err.strerror or err} (nothing written; earlier checkpoints and results are intact)")

    return wrapper  # type: ignore[return-value]


def _set_value(sets: list[str] | None, name: str) -> str | None:
    """The value of the last ``NAME=`` among ``--set`` strings (None: none)."""
    found = [value for key, value in map(parse_set, sets or []) if key == name]
    return str(found[-1]) if found else None


def _simulator_of(sets: list[str]) -> str | None:
    """The value of the last ``simulator=`` among ``--set`` strings (None: none)."""
    return _set_value(sets, "simulator")


def actions_of(sets: list[str] | None) -> str:
    """The action set ``--set`` strings ask for: the last ``actions=`` among them (``discrete`` without one)."""
    return _set_value(sets, "actions") or "discrete"


def check_actions(actions: str | None) -> None:
    """A one-line ConfigError naming ``--actions`` and its values unless ``actions`` is None or one of them."""
    if actions is not None and actions not in ACTIONS_CHOICES:
        raise ConfigError(f"--actions: got {actions!r}; allowed: {', '.join(ACTIONS_CHOICES)}")


def training_simulator(sets: list[str] | None, simulator: str | None, earlier_sets: list[str] | None) -> list[str]:
    """``sets`` for ``train`` / ``reproduce``, which default to the fast simulator (bit-identical to
    highway-env on the checked configurations: ``safelane sim check``): ``--simulator`` if given, else a
    ``simulator=`` of ``--set``, else what the run being resumed used (``earlier_sets``: its sets, where
    no ``simulator=`` means highway-env, the default before), else ``fast``."""
    sets = list(sets or [])
    if simulator is not None:
        return with_simulator(sets, simulator)
    if _simulator_of(sets) is not None:
        return sets
    if earlier_sets is not None:
        return with_simulator(sets, _simulator_of(earlier_sets) or "highway-env")
    return with_simulator(sets, "fast")


def with_simulator(sets: list[str] | None, simulator: str | None, actions: str | None = None) -> list[str]:
    """``sets`` with ``simulator=SIM`` and ``actions=KIND`` appended when ``--simulator`` / ``--actions`` were
    given (the simulator validated by the config, the action set here: :func:`check_actions`)."""
    check_actions(actions)
    extra = [f"simulator={simulator}"] if simulator is not None else []
    extra += [f"actions={actions}"] if actions is not None else []
    return [*(sets or []), *extra]


def warn_if_numpy_is_not_libm() -> None:
    """One warning line on stderr when numpy's tan/arctan are not libm's in this process (the fast
    simulator then matches highway-env statistically, not bit for bit): :mod:`safelane.sim.fast.libm`."""
    from safelane.sim.fast.libm import LIBM_NUMPY_ENV, numpy_matches_libm

    if not numpy_matches_libm():
        setting = " ".join(f"{k}='{v}'" for k, v in LIBM_NUMPY_ENV.items())
        stderr.print(
            f"warning: numpy's tan/arctan or dot are not libm's on this CPU (AVX-512): highway-env and the fast "
            f"simulator will drift apart by ~1e-6 m; run with {setting} for identical trajectories",
            markup=False,
            highlight=False,
            soft_wrap=True,
        )


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


def _progress_bar() -> Progress:
    """A transient rich progress bar on stderr (none in logs or pipes)."""
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=stderr,
        transient=True,
        disable=not stderr.is_terminal,
    )


@contextmanager
def episode_progress(description: str, total: int) -> Iterator[Callable[[int, Any], None]]:
    """A rich progress bar on stderr; yields a callback ``(episode_index, record)`` that advances it."""
    with _progress_bar() as progress:
        task = progress.add_task(description, total=total)
        yield lambda index, record: progress.update(task, completed=index + 1)


@contextmanager
def units_progress(description: str) -> Iterator[Callable[[int, int], None]]:
    """A rich progress bar on stderr; yields a callback ``(done, total)`` (the total may be learnt late)."""
    with _progress_bar() as progress:
        task = progress.add_task(description, total=None)
        yield lambda done, total: progress.update(task, completed=done, total=total)


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
    table.add_column("metric", style="bold", no_wrap=True)
    table.add_column("value", justify="right")
    table.add_column("unit")
    for key, value in rows.items():
        table.add_row(key, _fmt(value), (units or {}).get(key, ""))
    stdout.print(table)


# --- commands ---------------------------------------------------------------------------------------
