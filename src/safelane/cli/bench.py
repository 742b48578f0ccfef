"""``safelane bench``: the simulators', the shield's and training's speed."""

from __future__ import annotations

from typing import Annotated

import typer

from safelane.cli.common import (
    EpisodesOpt,
    JsonOpt,
    SeedOpt,
    check_positive,
    check_seed,
    cli_errors,
    episode_progress,
    print_json,
    print_table,
)
from safelane.config import ConfigError

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
    "fast_batched_decisions_per_s": "N envs: summed decisions/s",
    "envpool_decisions_per_s": "decisions/s",
    "train_steps_per_s": "decisions/s",
    "agent_ms_per_decision": "ms",
    "agent_overhead_fraction": "non-env share of training time",
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
