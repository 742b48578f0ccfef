"""How much a 200-episode mean moves with the seed range alone (the fast simulator, always-FASTER).

``safelane sim check`` draws its two statistical samples from disjoint seed ranges (10 000 000+ for
highway-env, 20 000 000+ for the fast simulator). The fast simulator replays highway-env's sample
episode for episode, so a difference between the two samples is the seed draw; this script shows its
size: FASTER's mean speed [m/s] over 200 and over 2 000 episodes of four seed ranges.

    .venv/bin/python examples/seed_ranges.py
"""

from __future__ import annotations

import numpy as np

from safelane.config import load_config
from safelane.env.factory import make_env
from safelane.running.evaluation import fixed_policy, run_episodes
from safelane.running.simcheck import on_simulator


def main() -> None:
    """Print FASTER's mean speed per seed range and sample size."""
    env = make_env(on_simulator(load_config("fast"), "fast", "faster"))
    for base in (10_000_000, 20_000_000, 30_000_000, 40_000_000):
        for n in (200, 2000):
            records = run_episodes(env, fixed_policy("faster", base), n, base)
            mean = np.mean([r.mean_speed for r in records])
            print(f"seeds {base}+[0, {n}): FASTER mean speed {mean:.3f} m/s")
    env.close()


if __name__ == "__main__":
    main()
