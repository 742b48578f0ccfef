"""``safelane train``: train one agent (one method, one seed): a DQN method on the meta-actions, or with
``--actions continuous`` an SB3 algorithm (``--algo``) on acceleration and steering."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from safelane.cli.common import (
    ActionsOpt,
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
from safelane.config import ConfigError, parse_set

MethodOpt = Annotated[
    str | None,
    typer.Option(
        "--method",
        "-m",
        help="dqn, constrained, qmask or robust (default robust), or robust-recurrent (robust on a GRU).",
        metavar="METHOD",
    ),
]
ALGOS = ("sac", "ppo", "sac-lagrangian")  # safelane.agents.continuous.ALGOS, without importing torch for --help
AlgoOpt = Annotated[
    str | None,
    typer.Option(
        "--algo",
        help=f"With --actions continuous: {', '.join(ALGOS)} (default sac; Stable-Baselines3, the sb3 extra).",
        metavar="ALGO",
    ),
]


def continuous_learner(
    algo: str | None, actions: str | None, sets: list[str], method: str | None, episodes: int | None,
    steps: int | None, cost_budget: float | None,
) -> str | None:  # fmt: skip
    """The SB3 algorithm a ``train`` call asks for (None: a DQN method), checking the options that go together
    (one-line :class:`ConfigError` naming the option); ``--cost-budget`` is appended to ``sets``."""
    if algo is not None and algo not in ALGOS:
        raise ConfigError(f"--algo: got {algo!r}; allowed: {', '.join(ALGOS)}")
    continuous = actions == "continuous" or (actions is None and ("actions", "continuous") in map(parse_set, sets))
    if not continuous:
        if algo is not None:
            raise ConfigError(f"--algo: {algo} trains continuous actions; add --actions continuous (the discrete "
                              "actions train with --method)")  # fmt: skip
        for name, value in (("--steps", steps), ("--cost-budget", cost_budget)):
            if value is not None:
                raise ConfigError(f"{name}: only with --actions continuous (the DQN methods train for --episodes)")
        return None
    if method is not None:
        raise ConfigError(f"--method: {method} trains the discrete meta-actions; with --actions continuous choose "
                          f"--algo ({', '.join(ALGOS)})")  # fmt: skip
    if episodes is not None:
        raise ConfigError("--episodes: continuous agents train for --steps (decisions), not episodes")
    algo = algo or "sac"
    if cost_budget is not None:
        if algo != "sac-lagrangian":
            raise ConfigError(f"--cost-budget: only for --algo sac-lagrangian (got --algo {algo})")
        sets.append(f"agent.cost_budget={cost_budget!r}")
    return algo


@cli_errors
def train(
    method: MethodOpt = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="Run directory (config, metrics, checkpoints).")] = Path(
        "runs/train"
    ),
    episodes: Annotated[
        int | None, typer.Option("--episodes", "-n", help="DQN methods: training episodes (default 200).")
    ] = None,
    actions: ActionsOpt = None,
    algo: AlgoOpt = None,
    steps: Annotated[
        int | None, typer.Option("--steps", help="With --algo: training decisions (default 20 000).")
    ] = None,
    cost_budget: Annotated[
        float | None,
        typer.Option(
            "--cost-budget",
            help="sac-lagrangian: [cost per episode] allowed, cost 1 for a crash or leaving the road (default 0.05; "
            "sets agent.cost_budget).",
        ),
    ] = None,
    seed: SeedOpt = 0,
    preset: PresetOpt = "fast",
    agent_preset: Annotated[
        str | None,
        typer.Option(
            "--agent-preset",
            help="Agent hyper-parameters: paper or tuned (default), or a YAML file of agent fields (with --algo: "
            "a YAML file only).",
            metavar="NAME",
        ),
    ] = None,
    sets: SetOpt = None,
    simulator: TrainSimulatorOpt = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue from the run's last checkpoint.")] = False,
    checkpoint_every: Annotated[
        int | None,
        typer.Option(
            "--checkpoint-every",
            help="Between checkpoints: episodes (DQN methods, default 10); with --algo decisions (default 5 000), the "
            "checkpoint taken at the next episode end (SAC) or update (PPO).",
        ),
    ] = None,
    tensorboard: Annotated[
        bool, typer.Option("--tensorboard", help="Also log every metrics.csv column to RUN_DIR/tensorboard.")
    ] = False,
) -> None:
    """Train a DQN with one of the paper's four methods, or with --actions continuous an SB3 agent (--algo);
    Ctrl-C checkpoints, --resume continues."""

    from safelane.running.run_directory import load_run_config, make_train_config

    earlier: list[str] | None = None
    if resume and (out / "config.yaml").is_file():
        try:  # resume on the simulator the run was trained on
            earlier = [f"simulator={load_run_config(out).env.simulator}"]
        except ConfigError:
            earlier = None  # the resume itself reports the unreadable config
    sets = training_simulator(sets, simulator, earlier)
    if actions is not None:
        sets.append(f"actions={actions}")
    algo = continuous_learner(algo, actions, sets, method, episodes, steps, cost_budget)
    check_seed(seed)
    if algo is not None:
        if steps is not None:
            check_positive("--steps", steps)
        given = {"steps": steps, "agent_preset": agent_preset, "checkpoint_steps": checkpoint_every}
        fields: dict[str, Any] = {key: value for key, value in given.items() if value is not None}
        cfg = make_train_config(algo=algo, env_preset=preset, seed=seed, sets=list(sets), **fields)
        _train_continuous(cfg, out, resume, tensorboard)
        return
    episodes = 200 if episodes is None else episodes
    check_positive("--episodes", episodes)
    cfg = make_train_config(
        method=method or "robust",
        agent_preset=agent_preset or "tuned",
        env_preset=preset,
        episodes=episodes,
        seed=seed,
        sets=list(sets or []),
        checkpoint_every=10 if checkpoint_every is None else checkpoint_every,
    )
    _train_dqn(cfg, out, resume, tensorboard)


def _progress_columns() -> tuple[Any, ...]:
    return (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("{task.fields[stats]}"),
    )


def _train_dqn(cfg: Any, out: Path, resume: bool, tensorboard: bool) -> None:
    """Train a DQN method with a progress bar of episodes."""
    from safelane.running.training import TrainingInterrupted
    from safelane.running.training import train as run_training

    with Progress(*_progress_columns(), console=stderr, transient=False, disable=not stderr.is_terminal) as bar:
        task = bar.add_task(f"train {cfg.method}", total=cfg.episodes, stats="")

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
    typer.echo(f"trained {cfg.method} for {cfg.episodes} episodes: {out}/metrics.csv, {out}/checkpoint.pt")


def _train_continuous(cfg: Any, out: Path, resume: bool, tensorboard: bool) -> None:
    """Train an SB3 algorithm with a progress bar of decisions."""
    from safelane.running.continuous_training import train_continuous
    from safelane.running.training import TrainingInterrupted

    with Progress(*_progress_columns(), console=stderr, transient=False, disable=not stderr.is_terminal) as bar:
        task = bar.add_task(f"train {cfg.algo}", total=cfg.steps, stats="")

        def report(r: Any) -> None:
            lam = f" λ {r.lam:.2f}" if r.lam is not None else ""
            bar.update(
                task,
                completed=r.env_steps,
                stats=f"episode {r.episode} return {r.episode_return:6.2f} crashes {r.collisions} off road "
                f"{r.off_roads} {r.steps_per_s:.1f} steps/s{lam}",
            )

        try:
            train_continuous(cfg, out, resume=resume, progress=report, tensorboard=tensorboard)
        except TrainingInterrupted as stop:
            typer.echo(str(stop), err=True)
            raise typer.Exit(130) from None
    typer.echo(f"trained {cfg.algo} for {cfg.steps} decisions: {out}/metrics.csv, {out}/checkpoint.pt")
