"""``safelane reproduce``: the paper's protocol — methods × seeds trained, tested, stressed and reported."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from safelane.cli.common import (
    AddressOpt,
    BackendOpt,
    PresetOpt,
    SetOpt,
    TrainSimulatorOpt,
    check_positive,
    cli_errors,
    episode_progress,
    training_simulator,
    warn_if_numpy_is_not_libm,
)
from safelane.config import ConfigError


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
    learner: Annotated[
        str,
        typer.Option(
            "--learner",
            help="batched: the fast simulator's runs trained as one batch per worker (the same runs, bit for "
            "bit, several times faster); per-run: one run per task (highway-env runs always are).",
        ),
    ] = "batched",
) -> None:
    """Train every method × seed, evaluate on held-out episodes, write Table 4 / Fig. 6 / Fig. 7 and claims."""
    from safelane.agents.dqn import parse_methods
    from safelane.running.experiments import make_spec, run_experiment
    from safelane.running.reproduction_report import render_gifs, write_report

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
        from safelane.running.conditions import load_conditions

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

        run_experiment(spec, out, workers=workers, progress=tick, backend=backend, address=address, learner=learner)
    gif_paths = render_gifs(out, max_steps=20 if quick else 40) if gifs else None
    report = write_report(out, gif_paths)
    typer.echo(f"report: {report}")
