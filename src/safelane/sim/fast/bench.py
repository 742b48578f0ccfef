"""Speed: decisions/s of FastHighwayEnv vs stock highway-env, same config, same process, random policy.

PYTHONPATH=src python -m safelane.sim.fast.bench [--preset fast] [--stock-decisions 200] [--fast-decisions 50000]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import yaml

import safelane
from safelane.sim.fast import FastHighwayEnv
from safelane.sim.fast.check import make_oracle


def run(env, decisions: int, seed: int = 0) -> tuple[float, int]:
    """Seconds for ``decisions`` random decisions (resets at episode ends included), episodes started."""
    rng = np.random.default_rng(seed)
    actions = rng.integers(0, 5, size=decisions)
    episodes = 1
    t0 = time.perf_counter()
    env.reset(seed=seed)
    for a in actions:
        _, _, terminated, truncated, _ = env.step(int(a))
        if terminated or truncated:
            episodes += 1
            env.reset()
    return time.perf_counter() - t0, episodes


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--stock-decisions", type=int, default=200)
    ap.add_argument("--fast-decisions", type=int, default=50_000)
    args = ap.parse_args()
    data = yaml.safe_load((Path(safelane.__file__).parent / "presets" / f"{args.preset}.yaml").read_text())
    cfg, env_id = data["env"], data["env_id"]
    fast = FastHighwayEnv(cfg, env_id)
    run(fast, 100)  # compile / load the numba cache
    stock = make_oracle(cfg, env_id)
    ts, es = run(stock, args.stock_decisions)
    tf, ef = run(fast, args.fast_decisions)
    rs, rf = args.stock_decisions / ts, args.fast_decisions / tf
    print(f"preset {args.preset} ({env_id})")
    print(f"stock highway-env: {args.stock_decisions} decisions ({es} episodes) in {ts:.2f} s = {rs:.1f} decisions/s")
    print(f"FastHighwayEnv:    {args.fast_decisions} decisions ({ef} episodes) in {tf:.2f} s = {rf:.0f} decisions/s")
    print(f"speed-up: {rf / rs:.0f}x")


if __name__ == "__main__":
    main()
