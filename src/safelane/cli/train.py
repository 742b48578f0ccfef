"""``safelane train``: train one agent (one method, one seed)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from safelane.cli.common import (
    EpisodesOpt,
    PresetOpt,
    SeedOpt,
    SetOpt,
    TrainSimulatorOpt,
    check_positive,
    check_seed,
    cli_errors,
    stderr,
    training_simulator,
)
from safelane.config import ConfigError

MethodOpt = Annotated[str, typer.Option("--method", "-m", help="dqn, constrained, qmask or robust.", metavar="METHOD")]


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

    from safelane.running.run_directory import load_run_config, make_train_config
    from safelane.running.training import TrainingInterrupted
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
