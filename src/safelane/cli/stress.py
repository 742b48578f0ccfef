"""``safelane stress``: the stress suite, a policy over many traffic conditions."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table

from safelane.cli.common import (
    SHIELD_CHOICES,
    ActionsOpt,
    CounterexamplesOpt,
    EpisodesOpt,
    JsonOpt,
    SetOpt,
    SimulatorOpt,
    TrafficSeedOpt,
    actions_of,
    check_positive,
    check_seed,
    cli_errors,
    episode_progress,
    print_json,
    stdout,
    with_simulator,
)
from safelane.config import ConfigError


@cli_errors
def stress(
    run_dir: Path | None = typer.Argument(None, help="A trained run, instead of --policy.", metavar="RUN_DIR"),
    policy: Annotated[
        str | None,
        typer.Option(
            "--policy",
            help="Fixed policy: random, idle, faster, slower, probe; with --actions continuous: random, faster "
            "(full throttle in its lane), weave.",
        ),
    ] = None,
    actions: ActionsOpt = None,
    shield: Annotated[
        str | None,
        typer.Option(
            "--shield",
            help=f"Safety shield, sets shield.mode: {', '.join(SHIELD_CHOICES)} (default: robust; with --actions "
            "continuous committed, the shield for continuous actions).",
            metavar="MODE",
        ),
    ] = None,
    simulator: SimulatorOpt = None,
    episodes: EpisodesOpt = 20,
    conditions: Annotated[
        Path | None, typer.Option("--conditions", help="YAML list of conditions (default: the shipped suite).")
    ] = None,
    only: Annotated[list[str] | None, typer.Option("--only", help="Run only these condition names.")] = None,
    sets: SetOpt = None,
    counterexamples: CounterexamplesOpt = None,
    seed: TrafficSeedOpt = 0,
    as_json: JsonOpt = False,
) -> None:
    """Run the stress suite: collisions (classified), 95 % CI, speed and interventions per condition (with continuous
    actions: projections, episodes off the road)."""
    from safelane.running.conditions import load_conditions
    from safelane.running.policies import CONTINUOUS_POLICIES, FIXED_POLICIES
    from safelane.running.stress import run_stress

    sets = with_simulator(sets, simulator, actions)
    continuous = actions_of(sets) == "continuous"
    check_positive("--episodes", episodes)
    check_seed(seed)
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
        from safelane.running.run_directory import load_policy, load_run_config

        run = load_run_config(run_dir)
        mode, override = shield, None  # the run's own shield unless --shield says otherwise
        trained = load_policy(run_dir)

        def factory() -> Any:
            return trained
    else:
        allowed = CONTINUOUS_POLICIES if continuous else FIXED_POLICIES
        if policy is None or policy not in allowed:
            what = "one of the continuous policies" if continuous else "one of"
            raise ConfigError(f"--policy: give {what} {', '.join(allowed)} (or a RUN_DIR)")
        # The shield for continuous actions always intervenes: it has no override.
        mode, override = shield or ("committed" if continuous else "robust"), not continuous

        def factory() -> Any:
            return policy  # a name: each condition builds it for its own action set

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
            seed=seed,
        )
    if as_json:
        print_json(result)
        return
    seeded = f", traffic seed {seed}" if seed else ""
    kind = ", continuous actions" if continuous else ""
    table = Table(
        title=f"stress: {run_dir or policy}{kind}, shield {result['shield']}, {episodes} episodes per condition{seeded}"
    )
    committed = any("lapses" in r for r in result["conditions"])
    # Continuous actions: the shield projects (no invariant breaks), an episode can end off the road.
    events = "off road" if continuous else "invariant breaks"
    columns = ["condition", "collisions", "rate [95% CI]", "speed m/s", "projected" if continuous else "interventions",
               events, "kinds"]  # fmt: skip
    if committed:  # the committed mode's lapses (those in the model) and plan-forced share
        columns[6:6] = ["lapses (in model)", "plan-forced"]
    for col in columns:
        table.add_column(col)
    for r in result["conditions"]:
        name = r["name"] + (" (adversarial)" if r["adversarial"] else "")
        if "skipped" in r:
            table.add_row(name, "skipped", r["skipped"], *[""] * (len(columns) - 3))
            continue
        lo, hi = r["collision_rate_ci95"]
        kinds = ", ".join(f"{k} {v}" for k, v in r["collision_kinds"].items() if v)
        table.add_row(
            name,
            f"{r['collisions']}/{r['episodes']}",
            f"{r['collision_rate']:.3f} [{lo:.3f}, {hi:.3f}]",
            f"{r['mean_speed']:.2f}",
            f"{r['shield_intervention_rate']:.3f}",
            f"{r.get('off_road_rate', 0.0):.3f}" if continuous else str(r["invariant_breaks"]),
            *([f"{r['lapses']} ({r['lapses_in_model']})", f"{100 * r['plan_forced_rate']:.2f} %"] if committed else []),
            kinds or "-",
        )
    stdout.print(table)
