"""``safelane bench``: the simulators', the shield's and training's speed."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from safelane.cli.common import (
    EpisodesOpt,
    JsonOpt,
    SeedOpt,
    check_actions,
    check_positive,
    check_seed,
    cli_errors,
    episode_progress,
    print_json,
    print_table,
    stderr,
)
from safelane.config import ConfigError

PUBLISHED_BENCH = Path("docs/results/bench/forecast-fallback.json")
"""The last published bench run (in a checkout of the repository): the default ``--baseline``."""

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
    "shield_mask_us_mean_fast": "µs",
    "shield_mask_us_p99_fast": "µs",
    **{
        f"{who}_mask_us_{stat}_fast": "µs"
        for who in ("committed", "committed_robust")
        for stat in ("median", "mean", "p99")
    },
    "committed_mask_ratio_fast": "committed ÷ robust, mean µs on the same states",
    "committed_mask_decisions": "decisions",
    "fast_batched_decisions_per_s": "N envs: summed decisions/s",
    "envpool_decisions_per_s": "decisions/s",
    "train_steps_per_s": "decisions/s",
    "agent_ms_per_decision": "ms",
    "agent_overhead_fraction": "non-env share of training time",
    "continuous_decisions_per_s": "decisions/s",
    "discrete_decisions_per_s": "decisions/s",
    "continuous_step_ratio": "continuous ÷ discrete decisions/s",
    "wall_time_s": "s",
}
TRAINING_FIGURES = ("train_steps_per_s", "agent_ms_per_decision", "agent_overhead_fraction")


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
    baseline: Annotated[
        str,
        typer.Option(
            "--baseline",
            help="Published bench JSON to compare with: figures worse by more than their measured noise are "
            "listed under regressions (default: the repository's last published run, when run in a checkout; "
            "none: no comparison).",
            metavar="FILE|none",
        ),
    ] = str(PUBLISHED_BENCH),
    actions: Annotated[
        str,
        typer.Option(
            "--actions",
            help="discrete: the figures above, meta-actions; continuous: also the continuous step (acceleration and "
            "steering) timed beside the discrete one on each simulator.",
            metavar="KIND",
        ),
    ] = "discrete",
    as_json: JsonOpt = False,
) -> None:
    """Measure decisions/s raw and shielded (interleaved episodes), mask, observation and training cost
    (with --actions continuous: the continuous step beside the discrete one on each simulator)."""
    from safelane.agents.dqn import parse_methods
    from safelane.running.bench import BENCH_SHIELDS, run_bench, with_regressions

    check_positive("--episodes", episodes)
    check_seed(seed)
    check_actions(actions)
    if shield not in BENCH_SHIELDS:
        raise ConfigError(f"--shield: bench measures a shield; allowed: {', '.join(BENCH_SHIELDS)}")
    train_methods = parse_methods(methods)
    published = None
    if baseline != "none" and (baseline != str(PUBLISHED_BENCH) or PUBLISHED_BENCH.is_file()):
        try:  # read before the run: a bad file is an error now, not after minutes of measuring
            published = json.loads(Path(baseline).read_text())
        except (OSError, ValueError) as exc:
            raise ConfigError(f"--baseline: {baseline} is not a readable bench JSON ({exc}); or none") from None
    with episode_progress("bench", episodes) as advance:
        result = run_bench(
            episodes, seed, shield=shield, progress=lambda i: advance(i, None), methods=train_methods, actions=actions
        )
    result = with_regressions(result, published, baseline if published is not None else None)
    for found in result["regressions"]:
        stderr.print(
            f"[yellow]regression[/yellow]: {found['figure']} {found['measured']:.4g}, published "
            f"{found['published']:.4g} ({found['change']:+.0%}; noise {found['noise']:.0%})"
        )
    if as_json:
        print_json(result)
        return
    units = dict(BENCH_UNITS)
    for method in train_methods[1:]:
        units.update({f"{key}_{method}": units[key] for key in TRAINING_FIGURES})
    for method in train_methods:
        suffix = "_fast" if method == train_methods[0] else f"_{method}_fast"
        units.update({f"{key}{suffix}": units[key] for key in TRAINING_FIGURES})
    kind = ", continuous actions beside" if actions == "continuous" else ""
    print_table(f"safelane bench: {result['preset']} preset, random policy, {shield} shield{kind}", result, units)
