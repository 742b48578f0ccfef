"""``safelane reproduce``: the paper's protocol — methods × seeds trained, tested, stressed and reported."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from safelane.cli.common import (
    ActionsOpt,
    AddressOpt,
    BackendOpt,
    PresetOpt,
    SetOpt,
    TrainSimulatorOpt,
    actions_of,
    check_actions,
    check_positive,
    cli_errors,
    episode_progress,
    training_simulator,
    warn_if_numpy_is_not_libm,
)
from safelane.config import ConfigError, parse_set


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
    gifs: Annotated[
        bool | None,
        typer.Option("--gifs/--no-gifs", help="Render one episode GIF per method (default: on; DQN methods only)."),
    ] = None,
    stress_episodes: Annotated[
        int, typer.Option("--stress-episodes", help="Also evaluate every run on the stress conditions (0: skip).")
    ] = 0,
    stress_only: Annotated[
        list[str] | None, typer.Option("--stress-only", help="Stress conditions to use (default: all).")
    ] = None,
    methods: Annotated[
        str | None,
        typer.Option(
            "--methods",
            help="Methods to run, comma-separated, or all (default). With --actions continuous the arms: sac, ppo, "
            "sac-lagrangian bare, ALGO-projection, ALGO-replacement, ALGO-penalty under the shield (default: the "
            "three bare and sac's three shielded). With --preset hidden-types the agents: paper, paper-stack, "
            "paper-belief, paper-types (robust Q-masking on that state), faster, random, foresight (the "
            "perfect-foresight planner under the robust and omniscient masks: the ceiling) (default: all).",
            metavar="LIST",
        ),
    ] = None,
    shields: Annotated[
        str | None,
        typer.Option(
            "--shields",
            help="With --preset hidden-types: the shields each agent trains and is tested under, comma-separated: "
            "robust, belief, omniscient (default: all).",
            metavar="LIST",
        ),
    ] = None,
    scenarios: Annotated[
        str | None,
        typer.Option(
            "--scenarios",
            help="With --preset hidden-types: the scenarios, comma-separated: paper (the preset as it is), dense "
            "(density 2), aggressive (timid/normal/aggressive weighted 1/1/3), rate3 (3 decisions/s), or all "
            "(default: paper). paper runs --seeds × --test-episodes, every other one --scenario-seeds × "
            "--scenario-test-episodes.",
            metavar="LIST",
        ),
    ] = None,
    scenario_seeds: Annotated[
        int | None,
        typer.Option(
            "--scenario-seeds",
            help="With --preset hidden-types: seeds (0..K-1) of every scenario but paper (default 3).",
            metavar="K",
        ),
    ] = None,
    scenario_test_episodes: Annotated[
        int | None,
        typer.Option(
            "--scenario-test-episodes",
            help="With --preset hidden-types: held-out test episodes per run of every scenario but paper "
            "(default 200).",
            metavar="N",
        ),
    ] = None,
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
        str | None,
        typer.Option(
            "--learner",
            help="batched: the fast simulator's runs trained as one batch per worker (the same runs, bit for "
            "bit, several times faster); per-run: one run per task (highway-env runs always are). Default: "
            "batched (DQN methods only).",
        ),
    ] = None,
    actions: ActionsOpt = None,
    decisions: Annotated[
        int | None,
        typer.Option(
            "--decisions",
            help="With --actions continuous: training decisions per run (default 50 000: past SAC's plateau at "
            "about 10 000 on one seed, 50 updates of the Lagrangian SAC's λ; --quick: 600).",
            metavar="N",
        ),
    ] = None,
) -> None:
    """Train every method × seed, evaluate on held-out episodes, write Table 4 / Fig. 6 / Fig. 7 and claims
    (with --actions continuous: SB3 agents bare and under the shield, their table and learning curves;
    with --preset hidden-types: agents × shields against hidden driver types, per scenario, the expense of
    robustness and the learning curves)."""
    check_actions(actions)
    if preset == "hidden-types":
        refused = {
            "--actions": actions is not None,
            "--decisions": decisions is not None,
            "--stress-episodes": stress_episodes > 0,
            "--stress-only": bool(stress_only),
            "--confirm-on": confirm_on is not None,
            "--confirm-episodes": confirm_episodes is not None,
            "--learner": learner is not None,
            "--gifs": bool(gifs),
        }
        for option, given in refused.items():
            if given:
                raise ConfigError(f"{option}: not with --preset hidden-types (its runs train for --episodes and "
                                  "are tested under their own shield)")  # fmt: skip
        _reproduce_types(out, seeds, episodes, test_episodes, quick, workers, agent_preset,
                         training_simulator(sets, simulator, None), methods, shields, backend, address,
                         scenarios, scenario_seeds, scenario_test_episodes)  # fmt: skip
        return
    if shields is not None:
        raise ConfigError("--shields: only with --preset hidden-types (the other presets' methods have their shield)")
    only_types = {
        "--scenarios": scenarios is not None,
        "--scenario-seeds": scenario_seeds is not None,
        "--scenario-test-episodes": scenario_test_episodes is not None,
    }
    for option, given in only_types.items():
        if given:
            raise ConfigError(f"{option}: only with --preset hidden-types (the other presets' traffic is --set's)")
    if actions == "continuous" or (actions is None and actions_of(sets) == "continuous"):
        refused = {
            "--episodes": episodes != 200,
            "--agent-preset": agent_preset != "tuned",
            "--stress-episodes": stress_episodes > 0,
            "--stress-only": bool(stress_only),
            "--confirm-on": confirm_on is not None,
            "--confirm-episodes": confirm_episodes is not None,
            "--simulator": simulator not in (None, "fast"),
            "--learner": learner is not None,
            "--gifs": bool(gifs),
        }
        for option, given in refused.items():
            if given:
                raise ConfigError(f"{option}: not with --actions continuous (its runs train for --decisions on the "
                                  "fast simulator)")  # fmt: skip
        _reproduce_continuous(out, preset, seeds, decisions, test_episodes, quick, workers, sets, methods, backend,
                              address)  # fmt: skip
        return
    if decisions is not None:
        raise ConfigError("--decisions: only with --actions continuous (the DQN methods train for --episodes)")
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
        methods=list(parse_methods("all" if methods is None else methods)),
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

        run_experiment(
            spec, out, workers=workers, progress=tick, backend=backend, address=address, learner=learner or "batched"
        )
    gif_paths = render_gifs(out, max_steps=20 if quick else 40) if gifs is not False else None
    report = write_report(out, gif_paths)
    typer.echo(f"report: {report}")


def _reproduce_continuous(
    out: Path, preset: str, seeds: int, decisions: int | None, test_episodes: int, quick: bool,
    workers: int | None, sets: list[str] | None, methods: str | None, backend: str, address: str | None,
) -> None:  # fmt: skip
    """``reproduce --actions continuous``: every arm × seed trained, tested and reported
    (:mod:`safelane.running.continuous_reproduction`)."""
    from safelane.running.continuous_reproduction import (
        DEFAULT_DECISIONS,
        QUICK_DECISIONS,
        QUICK_SEEDS,
        QUICK_TEST_EPISODES,
        make_continuous_spec,
        parse_arms,
        run_comparison,
        write_comparison_report,
    )

    decisions = DEFAULT_DECISIONS if decisions is None else decisions
    if quick:
        seeds, decisions = min(seeds, QUICK_SEEDS), min(decisions, QUICK_DECISIONS)
        test_episodes = min(test_episodes, QUICK_TEST_EPISODES)
    check_positive("--seeds", seeds)
    check_positive("--decisions", decisions)
    check_positive("--test-episodes", test_episodes)
    if workers is not None:
        check_positive("--workers", workers)
    spec = make_continuous_spec(
        arms=parse_arms(methods),
        seeds=list(range(seeds)),
        decisions=decisions,
        test_episodes=test_episodes,
        env_preset=preset,
        sets=[s for s in sets or [] if parse_set(s)[0] != "actions"],  # every arm's runs are continuous
        quick=quick,
    )
    with episode_progress("reproduce (runs)", len(spec.arms) * len(spec.seeds)) as advance:
        done = [0]

        def tick(_: Any) -> None:
            advance(done[0], None)
            done[0] += 1

        run_comparison(spec, out, workers=workers, progress=tick, backend=backend, address=address)
    typer.echo(f"report: {write_comparison_report(out)}")


def _reproduce_types(
    out: Path, seeds: int, episodes: int, test_episodes: int, quick: bool, workers: int | None, agent_preset: str,
    sets: list[str], agents: str | None, shields: str | None, backend: str, address: str | None,
    scenarios: str | None, scenario_seeds: int | None, scenario_test_episodes: int | None,
) -> None:  # fmt: skip
    """``reproduce --preset hidden-types``: every agent × shield × seed trained, tested and reported
    (:mod:`safelane.running.types_reproduction`)."""
    from safelane.running.types_report import write_types_report
    from safelane.running.types_reproduction import (
        AGENTS,
        QUICK_EPISODES,
        QUICK_SEEDS,
        QUICK_TEST_EPISODES,
        SCENARIO_SEEDS,
        SCENARIO_TEST_EPISODES,
        SCENARIOS,
        SHIELDS,
        make_types_spec,
        parse_names,
        run_table,
    )

    scenario_seeds = SCENARIO_SEEDS if scenario_seeds is None else scenario_seeds
    scenario_test_episodes = SCENARIO_TEST_EPISODES if scenario_test_episodes is None else scenario_test_episodes
    check_positive("--scenario-seeds", scenario_seeds)
    check_positive("--scenario-test-episodes", scenario_test_episodes)
    if quick:
        seeds, episodes = min(seeds, QUICK_SEEDS), min(episodes, QUICK_EPISODES)
        test_episodes = min(test_episodes, QUICK_TEST_EPISODES)
        scenario_seeds = min(scenario_seeds, QUICK_SEEDS)
        scenario_test_episodes = min(scenario_test_episodes, QUICK_TEST_EPISODES)
    check_positive("--seeds", seeds)
    check_positive("--episodes", episodes)
    check_positive("--test-episodes", test_episodes)
    if workers is not None:
        check_positive("--workers", workers)
    spec = make_types_spec(
        agents=parse_names(agents, AGENTS, "--methods"),
        shields=parse_names(shields, SHIELDS, "--shields"),
        scenarios=parse_names("paper" if scenarios is None else scenarios, SCENARIOS, "--scenarios"),
        seeds=list(range(seeds)),
        episodes=episodes,
        test_episodes=test_episodes,
        scenario_seeds=list(range(scenario_seeds)),
        scenario_test_episodes=scenario_test_episodes,
        agent_preset=agent_preset,
        sets=sets,
        quick=quick,
    )
    with episode_progress("reproduce (runs)", len(spec.tasks())) as advance:
        done = [0]

        def tick(_: Any) -> None:
            advance(done[0], None)
            done[0] += 1

        run_table(spec, out, workers=workers, progress=tick, backend=backend, address=address)
    typer.echo(f"report: {write_types_report(out)}")
