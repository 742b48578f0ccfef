"""Is the sim check's statistical test calibrated? The spread of 200-episode means over seed blocks.

``safelane sim check`` draws its two statistical samples from disjoint seed blocks (10 000 000+ for
highway-env, 20 000 000+ for the fast simulator). The fast simulator replays highway-env's sample
episode for episode, so the fast simulator alone can play many blocks and show (a) how far a block's
mean moves by the seed draw alone, (b) whether blocks behave like independent samples (the variance of
the block means equals the within-block variance / n: ratio ≈ 1 ± sqrt(2 / (K − 1))), and (c) how often
the check's own test (the permutation test of :func:`safelane.reporting.stats.permutation_test`)
rejects at 1 % between two blocks of the *same* simulator — its real size. Block ``k`` is seeds
``10 000 000 + k · step + [0, n)``: block 0 is highway-env's sample, block 10 (step 1 000 000) the fast
simulator's.

    .venv/bin/python research/seed_ranges.py --preset paper --policies faster idle --blocks 100 \
        --out docs/results/simcheck/seed-blocks-paper.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from safelane.config import load_config
from safelane.core.files import atomic_write_text
from safelane.reporting import stats
from safelane.running.simcheck import FAST_SEED_OFFSET, HIGHWAY_ENV_SEED_OFFSET, stat_episodes_of


def block_means(preset: str, policy: str, blocks: int, step: int, episodes: int) -> list[list[float]]:
    """Per-episode mean speeds [m/s] of ``policy`` on the fast simulator, one list per seed block."""
    cfg = load_config(preset)
    # stat_episodes_of with sample_of="highway-env" plays seeds seed + HIGHWAY_ENV_SEED_OFFSET + i.
    return [
        stat_episodes_of(cfg, policy, "fast", 0, episodes, k * step, sample_of="highway-env")["mean_speed"]
        for k in range(blocks)
    ]


def calibration(samples: list[list[float]], step: int) -> dict:
    """Dispersion of the block means and the permutation test's rejection rate between disjoint pairs."""
    arrays = [np.asarray(s) for s in samples]
    n, k = len(arrays[0]), len(arrays)
    means = np.array([a.mean() for a in arrays])
    within = float(np.mean([a.var(ddof=1) for a in arrays]))
    ratio = float(means.var(ddof=1) / (within / n))
    pairs = [stats.permutation_test(arrays[2 * i], arrays[2 * i + 1], reps=2000, seed=0) for i in range(k // 2)]
    fast_block = (FAST_SEED_OFFSET - HIGHWAY_ENV_SEED_OFFSET) // step
    sd_mean = math.sqrt(within / n)
    return {
        "blocks": k,
        "episodes_per_block": n,
        "grand_mean": float(means.mean()),
        "sd_of_block_means": float(means.std(ddof=1)),
        "expected_sd_if_independent": sd_mean,
        "variance_ratio": ratio,
        "variance_ratio_sd_if_independent": math.sqrt(2 / (k - 1)),
        "disjoint_pairs": len(pairs),
        "pairs_rejected_at_1pct": int(sum(p < 0.01 for p in pairs)),
        "pairs_rejected_at_5pct": int(sum(p < 0.05 for p in pairs)),
        "check_blocks": {
            "highway_env_block_mean": float(means[0]),
            "highway_env_z": float((means[0] - means.mean()) / sd_mean),
            **(
                {
                    "fast_block_mean": float(means[fast_block]),
                    "fast_z": float((means[fast_block] - means.mean()) / sd_mean),
                    "difference_z": float((means[0] - means[fast_block]) / (sd_mean * math.sqrt(2))),
                }
                if fast_block < k
                else {}
            ),
        },
        "block_means": means.round(4).tolist(),
    }


def main() -> None:
    """Play the blocks, print one line per policy, write the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--policies", nargs="+", default=["faster", "idle"])
    parser.add_argument("--blocks", type=int, default=100)
    parser.add_argument("--step", type=int, default=1_000_000, help="Seeds between block starts.")
    parser.add_argument("--episodes", type=int, default=200, help="Episodes per block (the check's sample).")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    result: dict = {"preset": args.preset, "simulator": "fast", "step": args.step, "policies": {}}
    for policy in args.policies:
        cal = calibration(block_means(args.preset, policy, args.blocks, args.step, args.episodes), args.step)
        result["policies"][policy] = cal
        print(
            f"{policy}: {cal['blocks']} blocks x {cal['episodes_per_block']}: sd of block means "
            f"{cal['sd_of_block_means']:.3f} (independent: {cal['expected_sd_if_independent']:.3f}), variance "
            f"ratio {cal['variance_ratio']:.2f} ± {cal['variance_ratio_sd_if_independent']:.2f}; same-simulator "
            f"pairs rejected at 1 %: {cal['pairs_rejected_at_1pct']}/{cal['disjoint_pairs']}, at 5 %: "
            f"{cal['pairs_rejected_at_5pct']}/{cal['disjoint_pairs']}; the check's blocks: {cal['check_blocks']}"
        )
    if args.out is not None:
        atomic_write_text(args.out, json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
