"""How fast can many runs in one learner train on one core? The arithmetic floor of the batched learner.

Times, in one process on one thread, for S runs of the robust method (``tuned`` agent):

* ``update``: one :meth:`BatchedLearner.update` for all S runs on full replay buffers [ms per run];
* ``act``: one :meth:`BatchedLearner.act` (greedy, ε = 0) [ms per run];
* ``env``: one shielded decision of the fast batch with S environments (``make_vector_env``, robust shield) [ms per
  environment];
* the network's arithmetic per run-update (two forwards of 64 transitions, the backward ≈ two more) and the
  GFLOP/s it runs at, beside ``torch.baddbmm``'s on the layer's shape (the per-run gemm the learner must call to
  stay bit for bit the per-run learner).

The ceiling of S runs' decisions per second together is 1 ÷ (update + act + env), with nothing else paid; the
bench's single run (``train_steps_per_s_fast``) divided into it is the most ``train_batched_speedup`` can reach.

    PYTHONPATH=src python research/learner_floor.py --runs 1,10,40 --out floor.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from safelane.agents.batched import BatchedLearner
from safelane.agents.dqn import load_agent_config
from safelane.core.spaces import N_ACTIONS, OBS_SIZE
from safelane.env.vector import make_vector_env

HIDDEN = (100, 100)
"""The paper's network: 26 → 100 → 100 → 5."""


def flops_per_update(batch_size: int) -> float:
    """Floating-point operations of one run's gradient step: a forward of the online network on the batch, one of
    the target network on the next states, and a backward of about two forwards' cost."""
    sizes = (OBS_SIZE, *HIDDEN, N_ACTIONS)
    forward = sum(2 * batch_size * a * b for a, b in itertools.pairwise(sizes))
    return 4.0 * forward


def best_seconds(fn: Callable[[], Any], repeats: int, calls: int) -> float:
    """The fastest of ``repeats`` timings of ``calls`` calls of ``fn``, per call [s]."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(calls):
            fn()
        best = min(best, (time.perf_counter() - t0) / calls)
    return best


def filled_learner(runs: int, seed: int = 0) -> BatchedLearner:
    """A robust-method learner of ``runs`` runs whose buffers hold 5 000 random transitions each."""
    learner = BatchedLearner([load_agent_config(method="robust")] * runs, list(range(seed, seed + runs)))
    rng = np.random.default_rng(seed)
    everyone = np.arange(runs)
    for _ in range(5_000):
        masks = rng.random((runs, N_ACTIONS)) < 0.8
        masks[:, 1] = True
        learner.store(
            everyone, rng.standard_normal((runs, OBS_SIZE)).astype(np.float32), rng.integers(N_ACTIONS, size=runs),
            rng.standard_normal(runs), np.zeros(runs), rng.standard_normal((runs, OBS_SIZE)).astype(np.float32),
            np.zeros(runs, dtype=bool), masks, masks,
        )  # fmt: skip
    return learner


def measure(runs: int, repeats: int = 3) -> dict[str, float]:
    """The floor's figures for ``runs`` runs (module docstring)."""
    learner = filled_learner(runs)
    everyone = np.arange(runs)
    obs = np.zeros((runs, OBS_SIZE), dtype=np.float32)
    masks = np.ones((runs, N_ACTIONS), dtype=bool)
    update = best_seconds(lambda: learner.update(everyone), repeats, 20)
    act = best_seconds(lambda: learner.act(everyone, obs, masks, np.zeros(runs)), repeats, 50)
    vector = make_vector_env("fast", num_envs=runs, seed=0, **{"shield.mode": "robust"})
    rng = np.random.default_rng(0)
    vector.reset(seed=0)
    env = best_seconds(lambda: vector.step(rng.integers(N_ACTIONS, size=runs)), repeats, max(2_000 // runs, 20))
    vector.close()
    batch = learner.batch_size
    a = torch.randn(runs, batch, HIDDEN[0])
    w = torch.randn(runs, HIDDEN[1], HIDDEN[0])
    b = torch.randn(runs, 1, HIDDEN[1])
    gemm = best_seconds(lambda: torch.baddbmm(b, a, w.transpose(1, 2)), repeats, 50)
    per_run = {"update_ms": 1e3 * update / runs, "act_ms": 1e3 * act / runs, "env_ms": 1e3 * env / runs}
    flops = flops_per_update(batch)
    return {
        "runs": runs,
        **per_run,
        "ceiling_decisions_per_s": 1e3 / sum(per_run.values()),
        "update_gflops": flops * runs / update / 1e9,
        "gemm_gflops": 2 * runs * batch * HIDDEN[0] * HIDDEN[1] / gemm / 1e9,
        "flops_per_update": flops,
    }


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", default="1,10,40", help="Numbers of runs, comma-separated.")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    figures = {"rows": [measure(int(s), args.repeats) for s in args.runs.split(",")]}
    for row in figures["rows"]:
        print(
            f"S={row['runs']:>3}: update {row['update_ms']:.3f} act {row['act_ms']:.3f} env {row['env_ms']:.3f} "
            f"ms per run → ceiling {row['ceiling_decisions_per_s']:.0f}/s; update {row['update_gflops']:.1f} "
            f"GFLOP/s, the layer's gemm {row['gemm_gflops']:.1f}"
        )
    if args.out is not None:
        args.out.write_text(json.dumps(figures, indent=1) + "\n")
    return figures


if __name__ == "__main__":
    main()
