"""``safelane evaluate``: a fixed policy or a trained run, played and summarised."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from safelane.cli.common import (
    ActionsOpt,
    CounterexamplesOpt,
    EpisodesOpt,
    JsonOpt,
    PresetOpt,
    SeedOpt,
    SetOpt,
    ShieldOpt,
    SimulatorOpt,
    check_positive,
    check_seed,
    cli_errors,
    episode_progress,
    print_json,
    print_table,
    resolve_config,
    with_simulator,
)
from safelane.config import ConfigError

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
    "off_road_rate": "per episode",
    "lapses": "decisions",
    "lapses_in_model": "decisions",
    "plan_forced_rate": "per decision",
    "courtesy_waived_rate": "per decision",
    "uncertified_starts": "episodes",
    "redraws": "spawns",
    "wall_time_s": "s",
}


@cli_errors
def evaluate(
    run_dir: Path | None = typer.Argument(
        None, help="A trained run (safelane train --out) to evaluate greedily, instead of --policy.", metavar="RUN_DIR"
    ),
    policy: Annotated[
        str | None,
        typer.Option(
            "--policy",
            help="Fixed policy: random, idle, faster, slower, probe; with --actions continuous: random, faster "
            "(full throttle in its lane), weave.",
            metavar="POLICY",
        ),
    ] = None,
    actions: ActionsOpt = None,
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
    shield.override=true (unsafe actions replaced by the closest safe one) unless --set says otherwise; with
    --actions continuous the shield always executes a verified action (shield.intervention).
    A trained RUN_DIR runs under the shield it was trained with; --shield none evaluates a masked
    method's raw Q-network (what its values learned about unsafe actions, without the mask).
    """
    from safelane.running.evaluation import evaluate_fixed
    from safelane.running.policies import CONTINUOUS_POLICIES, FIXED_POLICIES

    sets = with_simulator(sets, simulator, actions)

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
    cfg = resolve_config(preset, sets, shield)
    allowed = CONTINUOUS_POLICIES if cfg.actions == "continuous" else FIXED_POLICIES
    if policy is None:
        raise ConfigError(f"evaluate: give --policy (one of {', '.join(allowed)})")
    if policy not in allowed:
        what = "continuous policy" if cfg.actions == "continuous" else "policy"
        raise ConfigError(f"--policy: unknown {what} '{policy}'; allowed: {', '.join(allowed)}")
    check_positive("--episodes", episodes)
    check_seed(seed)
    override_set = any(s.split("=", 1)[0].strip() == "shield.override" for s in sets or [])
    if cfg.shield.mode != "none" and not override_set and cfg.actions == "discrete":  # continuous: always projects
        cfg = resolve_config(preset, sets, shield, overrides={"shield.override": True})
    with episode_progress(f"evaluate {policy}", episodes) as advance:
        summary = evaluate_fixed(cfg, policy, episodes, seed, progress=advance, counterexamples=counterexamples)
    if as_json:
        print_json(summary)
        return
    kind = ", continuous actions" if cfg.actions == "continuous" else ""
    title = (
        f"{policy} on {cfg.preset} ({cfg.env_id}){kind}, shield {cfg.shield.mode}, seeds {seed}..{seed + episodes - 1}"
    )
    print_table(title, summary, EVALUATE_UNITS)


def evaluate_run(
    run_dir: Path,
    episodes: int,
    seed: int,
    sets: list[str] | None,
    shield: str | None,
    counterexamples: Path | None = None,
) -> dict[str, Any]:
    """Evaluate a trained run's greedy policy on its own environment config (plus --set / --shield);
    ``counterexamples``: save its crashes, invariant breaks and lapses there."""
    from safelane.running.evaluation import run_config, summarize
    from safelane.running.run_directory import load_policy, load_run_config
    from safelane.running.runs import run_env_config

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
        method=run.train.learner,
        run_dir=str(run_dir),
        shield=cfg.shield.mode,
        override=cfg.shield.override,
        preset=cfg.preset,
        simulator=cfg.simulator,
        seed=seed,
    )
