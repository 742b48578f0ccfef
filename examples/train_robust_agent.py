"""Train the paper's robust Q-masking agent with safelane's own API, then evaluate it on both simulators.

What it shows: ``make_train_config`` + ``train`` (the loop behind ``safelane train``: a DQN that chooses among
the robust shield's safe actions, with exact resume), ``load_policy`` (the trained run's greedy policy) and
``run_env_config`` + ``run_config`` + ``summarize`` (the episodes behind ``safelane evaluate RUN_DIR``). The
agent trains on the fast simulator (safelane's compiled copy of highway-env, ~100x faster), then plays the
same test seeds there and on highway-env itself: the two simulators play the same episodes, so the rows agree.

Run:
    python examples/train_robust_agent.py                  # 200 episodes of 40 s (the paper's length)
    python examples/train_robust_agent.py --quick          # 3 training episodes, 2 test episodes
    python examples/train_robust_agent.py --out runs/robust --episodes 50 --test-episodes 100

Time: about 40 s as set (8 000 training decisions on the fast simulator, then 800 test decisions on each
simulator); ``--quick`` about 15 s. The run directory
(``config.yaml``, ``metrics.csv``, ``checkpoint.pt``) is what ``safelane evaluate``, ``stress`` and ``render``
read.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from safelane.running.evaluation import run_config, summarize
from safelane.running.run_directory import load_policy, make_train_config
from safelane.running.runs import run_env_config
from safelane.running.training import EpisodeReport, train


def train_robust(out: Path, episodes: int, seed: int) -> Path:
    """Train robust Q-masking (paper Section IV.4) for ``episodes`` episodes on the fast simulator into ``out``."""
    cfg = make_train_config(method="robust", episodes=episodes, seed=seed, sets=["simulator=fast"])

    def progress(r: EpisodeReport) -> None:
        if r.episode == r.episodes or r.episode % max(1, r.episodes // 10) == 0:
            print(
                f"  episode {r.episode:>4}/{r.episodes}: return {r.episode_return:7.2f}, "
                f"{r.length:>2} decisions, collisions so far {r.collisions}, ε {r.epsilon:.2f}"
            )

    return train(cfg, out, progress=progress)


def evaluate(run_dir: Path, simulator: str, episodes: int, seed: int) -> dict:
    """The trained greedy policy on its own environment, on ``simulator``: the summary of ``episodes`` episodes."""
    config = run_env_config(run_dir, sets=[f"simulator={simulator}"])
    records = run_config(config, load_policy(run_dir), episodes, seed)
    return summarize(records, simulator=simulator)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="run directory (default: a temporary one)")
    parser.add_argument("--episodes", type=int, default=200, help="training episodes")
    parser.add_argument("--test-episodes", type=int, default=20, help="test episodes on each simulator")
    parser.add_argument("--seed", type=int, default=0, help="training seed (network, exploration, episodes)")
    parser.add_argument("--quick", action="store_true", help="3 training episodes, 2 test episodes")
    args = parser.parse_args()
    if args.quick:
        args.episodes, args.test_episodes = 3, 2
    if args.episodes < 1 or args.test_episodes < 1:
        parser.error("--episodes and --test-episodes: must be >= 1")

    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp) / "robust"
        print(f"training robust Q-masking for {args.episodes} episodes into {out} …")
        train_robust(out, args.episodes, args.seed)
        test_seed = 1_000_000 + args.seed  # seeds training never resets with
        print(f"{'simulator':12} {'episodes':>8} {'collisions':>10} {'speed m/s':>9} {'fallback %':>10} {'breaks':>6}")
        for simulator in ("fast", "highway-env"):
            s = evaluate(out, simulator, args.test_episodes, test_seed)
            print(
                f"{simulator:12} {s['episodes']:>8} {s['collisions']:>10} {s['mean_speed']:>9.2f} "
                f"{100 * s['fallback_rate']:>10.2f} {s['invariant_breaks']:>6}"
            )


if __name__ == "__main__":
    main()
