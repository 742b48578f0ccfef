"""The ``safelane`` command line: parse, call the library, print.

Every command is a thin layer over a library function (:mod:`safelane.running.evaluation`,
:mod:`safelane.running.bench`, :mod:`safelane.config`). Progress goes to stderr, results to stdout (a rich
table, or one JSON object with ``--json``). A bad input (:class:`safelane.config.ConfigError` or
``ValueError``) prints one line ``error: <message>`` on stderr and exits with code 2.
"""

from __future__ import annotations

import functools
import json
import os
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
from safelane.config import (
    ENV_PRESETS,
    ConfigError,
    SafelaneConfig,
    ShieldConfig,
    config_to_dict,
    load_config,
    parse_set,
)

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
sim_app = typer.Typer(help="Check the fast simulator against highway-env.", no_args_is_help=True)
app.add_typer(sim_app, name="sim")

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
EpisodesOpt = Annotated[int, typer.Option("--episodes", "-n", help="Number of episodes (>= 1).")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Random seed: the same seed gives the same numbers.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print one JSON object on stdout instead of a table.")]
CounterexamplesOpt = Annotated[
    Path | None,
    typer.Option(
        "--save-counterexamples",
        help="Save every crash and invariant break as a replayable file in this directory (safelane replay FILE).",
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


def _simulator_of(sets: list[str]) -> str | None:
    """The value of the last ``simulator=`` among ``--set`` strings (None: none)."""
    found = [value for key, value in map(parse_set, sets) if key == "simulator"]
    return str(found[-1]) if found else None


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


def with_simulator(sets: list[str] | None, simulator: str | None) -> list[str]:
    """``sets`` with ``simulator=SIM`` appended when ``--simulator`` was given (validated by the config)."""
    return [*(sets or []), *([f"simulator={simulator}"] if simulator is not None else [])]


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


@sim_app.command("check")
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
        )
    if as_json:
        print_json(result)
        return
    stdout.print(
        f"trajectories: {result['trajectory_match_fraction']:.3f} of {episodes} episodes matched within "
        f"{result['tolerance']:g} (m, m/s, rad); {result['bit_identical_fraction']:.3f} bit-identical"
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


EVALUATE_UNITS = {
    "collision_rate": "per episode",
    "mean_speed": "m/s",
    "mean_length": "decisions",
    "time_to_collision": "s",
    "shield_intervention_rate": "per decision",
    "fallback_rate": "per decision",
    "invariant_breaks": "decisions",
    "invariant_break_rate": "per decision",
    "unsafe_action_rate": "per decision",
    "mean_vehicles_passed": "vehicles / episode",
    "wall_time_s": "s",
}


@app.command()
@cli_errors
def evaluate(
    run_dir: Path | None = typer.Argument(
        None, help="A trained run (safelane train --out) to evaluate greedily, instead of --policy.", metavar="RUN_DIR"
    ),
    policy: Annotated[
        str | None,
        typer.Option("--policy", help="Fixed policy: random, idle, faster, slower, probe.", metavar="POLICY"),
    ] = None,
    episodes: EpisodesOpt = 20,
    seed: SeedOpt = 0,
    preset: PresetOpt = "fast",
    sets: SetOpt = None,
    shield: ShieldOpt = None,
    simulator: SimulatorOpt = None,
    counterexamples: CounterexamplesOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Evaluate a policy: collisions, speed, return, time to collision, shield activity.

    A fixed policy cannot read the shield's mask, so with a shield it runs with
    shield.override=true (unsafe actions replaced by the closest safe one) unless --set says otherwise.
    A trained RUN_DIR runs under the shield it was trained with; --shield none evaluates a masked
    method's raw Q-network (what its values learned about unsafe actions, without the mask).
    """
    from safelane.running.evaluation import FIXED_POLICIES, evaluate_fixed

    sets = with_simulator(sets, simulator)

    if run_dir is not None:
        if policy is not None:
            raise ConfigError("evaluate: give either RUN_DIR or --policy, not both")
        check_positive("--episodes", episodes)
        check_seed(seed)
        summary = evaluate_run(run_dir, episodes, seed, sets, shield, counterexamples)
        if as_json:
            print_json(summary)
        else:
            print_table(f"{summary['method']} run {run_dir}, shield {summary['shield']}", summary, EVALUATE_UNITS)
        return
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
        summary = evaluate_fixed(cfg, policy, episodes, seed, progress=advance, counterexamples=counterexamples)
    if as_json:
        print_json(summary)
        return
    title = f"{policy} on {cfg.preset} ({cfg.env_id}), shield {cfg.shield.mode}, seeds {seed}..{seed + episodes - 1}"
    print_table(title, summary, EVALUATE_UNITS)


BENCH_UNITS = {
    "env_steps_per_s": "decisions/s",
    "shielded_env_steps_per_s": "decisions/s",
    "shield_overhead_ratio": "shielded ÷ raw",
    "snapshot_us_median": "µs",
    "shield_mask_us_median": "µs",
    "obs_us_median": "µs",
    "highway_env_steps_per_s": "decisions/s",
    "neighbour_search_speedup": "numpy ÷ highway-env search",
    "highway_env_decisions_per_s": "decisions/s",
    "fast_decisions_per_s": "decisions/s",
    "fast_raw_speedup": "fast ÷ stock highway-env",
    "fast_shielded_decisions_per_s": "decisions/s",
    "fast_speedup": "fast shielded ÷ stock highway-env",
    "shield_mask_us_median_fast": "µs",
    "fast_batched_decisions_per_s": "N envs: summed decisions/s",
    "envpool_decisions_per_s": "decisions/s",
    "train_steps_per_s": "decisions/s",
    "agent_ms_per_decision": "ms",
    "agent_overhead_fraction": "non-env share of training time",
    "wall_time_s": "s",
}
TRAINING_FIGURES = ("train_steps_per_s", "agent_ms_per_decision", "agent_overhead_fraction")


@app.command()
@cli_errors
def bench(
    episodes: EpisodesOpt = 10,
    seed: SeedOpt = 0,
    shield: Annotated[
        str, typer.Option("--shield", help="Shield to measure: nominal or robust.", metavar="MODE")
    ] = "robust",
    methods: Annotated[
        str,
        typer.Option(
            "--methods",
            help="Methods whose training cost to measure, comma-separated, or all (the first gives the "
            "unsuffixed figures).",
            metavar="LIST",
        ),
    ] = "robust",
    as_json: JsonOpt = False,
) -> None:
    """Measure decisions/s raw and shielded (interleaved episodes), mask, observation and training cost."""
    from safelane.agents.dqn import parse_methods
    from safelane.running.bench import BENCH_SHIELDS, run_bench

    check_positive("--episodes", episodes)
    check_seed(seed)
    if shield not in BENCH_SHIELDS:
        raise ConfigError(f"--shield: bench measures a shield; allowed: {', '.join(BENCH_SHIELDS)}")
    train_methods = parse_methods(methods)
    with episode_progress("bench", episodes) as advance:
        result = run_bench(episodes, seed, shield=shield, progress=lambda i: advance(i, None), methods=train_methods)
    if as_json:
        print_json(result)
        return
    units = dict(BENCH_UNITS)
    for method in train_methods[1:]:
        units.update({f"{key}_{method}": units[key] for key in TRAINING_FIGURES})
    for method in train_methods:
        suffix = "_fast" if method == train_methods[0] else f"_{method}_fast"
        units.update({f"{key}{suffix}": units[key] for key in TRAINING_FIGURES})
    print_table(f"safelane bench: {result['preset']} preset, random policy, {shield} shield", result, units)


def evaluate_run(
    run_dir: Path,
    episodes: int,
    seed: int,
    sets: list[str] | None,
    shield: str | None,
    counterexamples: Path | None = None,
) -> dict[str, Any]:
    """Evaluate a trained run's greedy policy on its own environment config (plus --set / --shield);
    ``counterexamples``: save its crashes and invariant breaks there."""
    from safelane.running.evaluation import run_config, summarize
    from safelane.running.runs import run_env_config
    from safelane.running.training import load_policy, load_run_config

    run = load_run_config(run_dir)
    cfg = run_env_config(run_dir, sets=sets, shield=shield)
    policy = load_policy(run_dir)
    with episode_progress(f"evaluate {run_dir}", episodes) as advance:
        records = run_config(cfg, policy, episodes, seed, advance)
    files: list[Path] = []
    if counterexamples is not None:
        from safelane.running.counterexamples import save_counterexamples

        files = save_counterexamples(records, cfg, counterexamples, f"evaluate {run_dir} --seed {seed}")
    return summarize(
        records,
        counterexample_files=[str(f) for f in files],
        method=run.train.method,
        run_dir=str(run_dir),
        shield=cfg.shield.mode,
        override=cfg.shield.override,
        preset=cfg.preset,
        simulator=cfg.simulator,
        seed=seed,
    )


MethodOpt = Annotated[str, typer.Option("--method", "-m", help="dqn, constrained, qmask or robust.", metavar="METHOD")]


@app.command()
@cli_errors
def train(
    method: MethodOpt = "robust",
    out: Annotated[Path, typer.Option("--out", "-o", help="Run directory (config, metrics, checkpoints).")] = Path(
        "runs/train"
    ),
    episodes: EpisodesOpt = 200,
    seed: SeedOpt = 0,
    preset: PresetOpt = "fast",
    agent_preset: Annotated[
        str, typer.Option("--agent-preset", help="Agent hyper-parameters: paper or tuned.", metavar="NAME")
    ] = "tuned",
    sets: SetOpt = None,
    simulator: TrainSimulatorOpt = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue from the run's last checkpoint.")] = False,
    checkpoint_every: Annotated[int, typer.Option("--checkpoint-every", help="Episodes between checkpoints.")] = 10,
    tensorboard: Annotated[
        bool, typer.Option("--tensorboard", help="Also log every metrics.csv column to RUN_DIR/tensorboard.")
    ] = False,
) -> None:
    """Train a DQN with one of the paper's four methods; Ctrl-C checkpoints, --resume continues."""
    from rich.progress import Progress

    from safelane.running.training import TrainingInterrupted, load_run_config, make_train_config
    from safelane.running.training import train as run_training

    earlier: list[str] | None = None
    if resume and (out / "config.yaml").is_file():
        try:  # resume on the simulator the run was trained on
            earlier = [f"simulator={load_run_config(out).env.simulator}"]
        except ConfigError:
            earlier = None  # the resume itself reports the unreadable config
    sets = training_simulator(sets, simulator, earlier)
    check_positive("--episodes", episodes)
    check_seed(seed)
    cfg = make_train_config(
        method=method,
        agent_preset=agent_preset,
        env_preset=preset,
        episodes=episodes,
        seed=seed,
        sets=list(sets or []),
        checkpoint_every=checkpoint_every,
    )
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("{task.fields[stats]}"),
    )
    with Progress(*columns, console=stderr, transient=False, disable=not stderr.is_terminal) as bar:
        task = bar.add_task(f"train {method}", total=episodes, stats="")

        def report(r: Any) -> None:
            lam = f" λ {r.lam:.2f}" if r.lam is not None else ""
            bar.update(
                task,
                completed=r.episode,
                stats=f"return {r.episode_return:6.2f} collisions {r.collisions} ε {r.epsilon:.2f} "
                f"{r.steps_per_s:.1f} steps/s{lam}",
            )

        try:
            run_training(cfg, out, resume=resume, progress=report, tensorboard=tensorboard)
        except TrainingInterrupted as stop:
            typer.echo(str(stop), err=True)
            raise typer.Exit(130) from None
    typer.echo(f"trained {method} for {episodes} episodes: {out}/metrics.csv, {out}/checkpoint.pt")


@app.command()
@cli_errors
def reproduce(
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Output directory (report.md, figures, results.json).")
    ] = Path("runs/reproduce"),
    preset: PresetOpt = "fast",
    seeds: Annotated[int, typer.Option("--seeds", help="Number of seeds (0..K-1).")] = 5,
    episodes: Annotated[int, typer.Option("--episodes", help="Training episodes per run (paper: 200).")] = 200,
    test_episodes: Annotated[int, typer.Option("--test-episodes", help="Held-out test episodes per run.")] = 20,
    quick: Annotated[bool, typer.Option("--quick", help="A short run (2 seeds, 25 episodes): minutes.")] = False,
    workers: Annotated[int | None, typer.Option("--workers", help="Parallel processes (default: cores).")] = None,
    agent_preset: Annotated[str, typer.Option("--agent-preset", help="paper or tuned.")] = "tuned",
    sets: SetOpt = None,
    simulator: TrainSimulatorOpt = None,
    gifs: Annotated[bool, typer.Option("--gifs/--no-gifs", help="Render one episode GIF per method.")] = True,
    stress_episodes: Annotated[
        int, typer.Option("--stress-episodes", help="Also evaluate every run on the stress conditions (0: skip).")
    ] = 0,
    stress_only: Annotated[
        list[str] | None, typer.Option("--stress-only", help="Stress conditions to use (default: all).")
    ] = None,
    methods: Annotated[
        str, typer.Option("--methods", help="Methods to run, comma-separated, or all.", metavar="LIST")
    ] = "all",
    confirm_on: Annotated[
        str | None,
        typer.Option(
            "--confirm-on",
            help="Re-run every agent's test episodes on this simulator (highway-env) and report both.",
            metavar="SIM",
        ),
    ] = None,
    confirm_episodes: Annotated[
        int | None,
        typer.Option(
            "--confirm-episodes",
            help="With --confirm-on: re-run only each run's first K test episodes (default: all).",
            metavar="K",
        ),
    ] = None,
    backend: BackendOpt = "local",
    address: AddressOpt = None,
) -> None:
    """Train every method × seed, evaluate on held-out episodes, write Table 4 / Fig. 6 / Fig. 7 and claims."""
    from safelane.agents.dqn import parse_methods
    from safelane.reporting.report import render_gifs, write_report
    from safelane.running.experiments import make_spec, run_experiment

    earlier: list[str] | None = None
    if (out / "spec.json").is_file():  # an experiment being resumed keeps its simulator
        try:
            earlier = list(json.loads((out / "spec.json").read_text()).get("sets", []))
        except (OSError, ValueError):
            earlier = None
    sets = training_simulator(sets, simulator, earlier)
    if quick:
        seeds, episodes, test_episodes = min(seeds, 2), min(episodes, 25), min(test_episodes, 7)
    check_positive("--seeds", seeds)
    check_positive("--episodes", episodes)
    check_positive("--test-episodes", test_episodes)
    if workers is not None:
        check_positive("--workers", workers)
    stress_names: list[str] = []
    if stress_episodes > 0:
        from safelane.running.stress import load_conditions

        names = [c.name for c in load_conditions()]
        unknown = [n for n in stress_only or [] if n not in names]
        if unknown:
            raise ConfigError(f"--stress-only: unknown condition '{unknown[0]}'; allowed: {', '.join(names)}")
        stress_names = list(stress_only or names)
    spec = make_spec(
        methods=list(parse_methods(methods)),
        stress_conditions=stress_names,
        stress_episodes=max(stress_episodes, 1),
        seeds=list(range(seeds)),
        episodes=episodes,
        test_episodes=test_episodes,
        env_preset=preset,
        agent_preset=agent_preset,
        sets=list(sets or []),
        quick=quick,
        confirm_on=confirm_on,
        confirm_episodes=confirm_episodes,
    )
    if confirm_on is not None:
        warn_if_numpy_is_not_libm()
    total = len(spec.methods) * len(spec.seeds)
    with episode_progress("reproduce (runs)", total) as advance:
        done = [0]

        def tick(_: Any) -> None:
            advance(done[0], None)
            done[0] += 1

        run_experiment(spec, out, workers=workers, progress=tick, backend=backend, address=address)
    gif_paths = render_gifs(out, max_steps=20 if quick else 40) if gifs else None
    report = write_report(out, gif_paths)
    typer.echo(f"report: {report}")


@app.command()
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
    from safelane.running.sweep import load_sweep_spec, run_sweep

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


@app.command()
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
    as_json: JsonOpt = False,
) -> None:
    """Drive the shield over a grid of traffic conditions, or search them (a spec with a search section:
    cross-entropy method toward the most invariant breaks): collisions, invariant breaks (classified), files."""
    from safelane.running.falsify import run_campaign
    from safelane.running.falsify_search import SearchSpec, load_falsify_spec, run_search

    for option, value in (("--episodes", episodes), ("--sample", sample), ("--workers", workers)):
        if value is not None:
            check_positive(option, value)
    spec = load_falsify_spec(spec_file, {"episodes": episodes, "sample": sample})
    if isinstance(spec, SearchSpec):
        with units_progress(f"falsify search {spec.name} (samples)") as tick:
            summary = run_search(spec, out, backend=backend, workers=workers, address=address, progress=tick)
    else:
        with units_progress(f"falsify {spec.name} (cells)") as tick:
            summary = run_campaign(spec, out, backend=backend, workers=workers, address=address, progress=tick)
    if as_json:
        typer.echo(json.dumps(summary))
        return
    typer.echo((out / "summary.md").read_text())
    typer.echo(f"counterexamples: {out / 'counterexamples'} (safelane replay FILE)")


@app.command()
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
    as_json: JsonOpt = False,
) -> None:
    """The price of robustness: a perfect-foresight planner unmasked / under each mask, the probe, an agent."""
    from safelane.running.foresight import ceiling_table

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
    cfg = resolve_config(preset, sets, overrides={"simulator": "fast"})
    with units_progress("ceiling (chunks)") as tick:
        table = ceiling_table(
            cfg, rate_list, episodes, seed, out, agents=agents, horizon=horizon, beam=beam, workers=workers,
            progress=tick,
        )  # fmt: skip
    if as_json:
        typer.echo(json.dumps(table))
        return
    typer.echo((out / "ceiling.md").read_text())


@app.command()
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
    """Replay a saved crash or invariant break: the decision log, and whether the event happens again."""
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


@app.command()
@cli_errors
def stress(
    run_dir: Path | None = typer.Argument(None, help="A trained run, instead of --policy.", metavar="RUN_DIR"),
    policy: Annotated[
        str | None, typer.Option("--policy", help="Fixed policy: random, idle, faster, slower, probe.")
    ] = None,
    shield: ShieldOpt = None,
    simulator: SimulatorOpt = None,
    episodes: EpisodesOpt = 20,
    conditions: Annotated[
        Path | None, typer.Option("--conditions", help="YAML list of conditions (default: the shipped suite).")
    ] = None,
    only: Annotated[list[str] | None, typer.Option("--only", help="Run only these condition names.")] = None,
    sets: SetOpt = None,
    counterexamples: CounterexamplesOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Run the stress suite: collisions (classified), 95 % CI, speed and interventions per condition."""
    from safelane.running.evaluation import FIXED_POLICIES, fixed_policy
    from safelane.running.stress import load_conditions, run_stress

    sets = with_simulator(sets, simulator)
    check_positive("--episodes", episodes)
    conds = load_conditions(conditions)
    if only:
        names = {c.name for c in conds}
        unknown = [o for o in only if o not in names]
        if unknown:
            raise ConfigError(f"--only: unknown condition '{unknown[0]}'; allowed: {', '.join(sorted(names))}")
        conds = [c for c in conds if c.name in only]
    if shield is not None and shield not in SHIELD_CHOICES:
        raise ConfigError(f"--shield: unknown shield '{shield}'; allowed: {', '.join(SHIELD_CHOICES)}")
    run = None
    if run_dir is not None:
        from safelane.running.training import load_policy, load_run_config

        run = load_run_config(run_dir)
        mode, override = shield, None  # the run's own shield unless --shield says otherwise
        trained = load_policy(run_dir)

        def factory() -> Any:
            return trained
    else:
        if policy is None or policy not in FIXED_POLICIES:
            raise ConfigError(f"--policy: give one of {', '.join(FIXED_POLICIES)} (or a RUN_DIR)")
        mode, override = shield or "robust", True

        def factory() -> Any:
            return fixed_policy(policy, 0)

    rows: list[dict[str, Any]] = []
    with episode_progress("stress (conditions)", len(conds)) as advance:
        result = run_stress(
            factory,
            episodes,
            mode,
            override,
            conds,
            sets,
            on_condition=lambda r: (rows.append(r), advance(len(rows) - 1, None)),
            run=run,
            counterexamples=counterexamples,
        )
    if as_json:
        print_json(result)
        return
    table = Table(title=f"stress: {run_dir or policy}, shield {result['shield']}, {episodes} episodes per condition")
    for col in ("condition", "collisions", "rate [95% CI]", "speed m/s", "interventions", "invariant breaks", "kinds"):
        table.add_column(col)
    for r in result["conditions"]:
        name = r["name"] + (" (adversarial)" if r["adversarial"] else "")
        if "skipped" in r:
            table.add_row(name, "skipped", r["skipped"], "", "", "", "")
            continue
        lo, hi = r["collision_rate_ci95"]
        kinds = ", ".join(f"{k} {v}" for k, v in r["collision_kinds"].items() if v)
        table.add_row(
            name,
            f"{r['collisions']}/{r['episodes']}",
            f"{r['collision_rate']:.3f} [{lo:.3f}, {hi:.3f}]",
            f"{r['mean_speed']:.2f}",
            f"{r['shield_intervention_rate']:.3f}",
            str(r["invariant_breaks"]),
            kinds or "-",
        )
    stdout.print(table)


@app.command()
@cli_errors
def render(
    run_dir: Path | None = typer.Argument(None, help="A trained run, instead of --policy.", metavar="RUN_DIR"),
    policy: Annotated[
        str | None, typer.Option("--policy", help="Fixed policy: random, idle, faster, slower, probe.")
    ] = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="Output file (.gif, or .mp4 with imageio-ffmpeg).")] = Path(
        "episode.gif"
    ),
    seed: SeedOpt = 0,
    preset: PresetOpt = "fast",
    sets: SetOpt = None,
    shield: ShieldOpt = None,
    max_steps: Annotated[int | None, typer.Option("--max-steps", help="Stop after this many decisions.")] = None,
) -> None:
    """Render one episode offscreen with the action mask and the chosen action drawn on each frame."""
    from safelane.reporting.render import render_episode
    from safelane.running.evaluation import FIXED_POLICIES, fixed_policy

    if run_dir is not None:
        from safelane.running.runs import run_env_config
        from safelane.running.training import load_policy

        cfg = run_env_config(run_dir, sets=sets, shield=shield)
        act = load_policy(run_dir)
    else:
        if policy is None or policy not in FIXED_POLICIES:
            raise ConfigError(f"--policy: give one of {', '.join(FIXED_POLICIES)} (or a RUN_DIR)")
        cfg = resolve_config(preset, sets, shield)
        if cfg.shield.mode != "none":
            cfg = resolve_config(preset, sets, shield, overrides={"shield.override": True})
        act = fixed_policy(policy, seed)
    if cfg.simulator == "fast":  # the renderer draws it on highway-env, which plays the same episode
        typer.echo("render: drawing on highway-env, which plays the fast simulator's episode", err=True)
    result = render_episode(cfg, act, seed, out, max_steps=max_steps)  # checks --out, then builds and closes the env
    typer.echo(f"wrote {result.path} ({result.frames} frames)")


@app.command()
@cli_errors
def plot(
    run_dirs: Annotated[list[Path], typer.Argument(help="One or more run directories.", metavar="RUN_DIR...")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output PNG.")] = Path("training_curves.png"),
    scaled: Annotated[bool, typer.Option("--scaled", help="Scale each curve to [0, 1] (paper Fig. 7).")] = False,
) -> None:
    """Plot training curves (smoothed return, ε) of one or several runs."""
    from safelane.reporting.plots import plot_training_curves

    for d in run_dirs:
        if not (d / "metrics.csv").exists():
            raise ConfigError(f"RUN_DIR {d}: no metrics.csv (not a training run)")
    fig = plot_training_curves(run_dirs, scaled=scaled)
    fig.savefig(out, dpi=110)
    typer.echo(f"wrote {out}")


if __name__ == "__main__":  # pragma: no cover
    app()
