"""How much could a better forecast save? Replay a campaign's crashes from unsafe spawns with the fallback's choice
made by the exact future.

The fast simulator's drivers are deterministic after reset, so a copy of its state
(:meth:`safelane.sim.fast.env.FastHighwayEnv.get_state`) shows what every car will really do. Each crash file that
``research/classify_crashes.py`` counted ``started_unsafe`` is played again (the recorded policy actions, then IDLE
to the episode's end) under its recorded rule, except that in every fallback state the allowed action is chosen
with that knowledge: each candidate action is tried on a copy, followed by holding it, braking, IDLE or FASTER for
``--depth`` decisions, and is *clear* when one of these continuations is collision-free. The shield's own least-bad
action is kept when it is clear, else the first clear one in the order SLOWER, IDLE, LANE_LEFT, LANE_RIGHT, FASTER,
else the shield's. ``--pool`` restricts the candidates, as the rule does, to nominal's safe actions when there are
some (robust ⊆ nominal); ``--no-lane-changes`` switches the other cars' lane changes off in the copies (MOBIL off;
a change already under way goes on), which is what a forecast that keeps every car in its lane could know at best.
A bound of this search (its depth, its continuations), not of every policy; a ceiling for a ranking of the
fallback's choice, measured on the crashes only — docs/research/fallback-choice.md shows why such replays overstate a
change.

    .venv/bin/python research/fallback_oracle.py docs/results/falsify/grid_100k_behind_forecast_fallback \
        --pool --out runs/fallback_oracle_pool.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from safelane.core.files import atomic_write_text
from safelane.core.spaces import FASTER, IDLE, LANE_LEFT, LANE_RIGHT, SLOWER
from safelane.env.factory import make_env
from safelane.running.control_foresight import fast_simulator_of
from safelane.running.counterexamples import load_counterexample
from safelane.safety.one_decision.reference import evaluate
from safelane.safety.shield import SafetyShield
from safelane.sim.fast import layout

PREFERENCE = (SLOWER, IDLE, LANE_LEFT, LANE_RIGHT, FASTER)
TAIL_DECISIONS = 400  # IDLE after the recorded actions, until the episode ends


def clear(sim: Any, state: Any, action: int, depth: int, lane_changes: bool) -> bool:
    """Whether ``action`` followed by one of the continuations stays collision-free for ``depth`` decisions."""
    continuations = ([SLOWER] * depth, [IDLE] * depth, [action] * depth, [FASTER] * depth)
    for continuation in continuations:
        sim.set_state(state)
        if not lane_changes:
            sim.G[1:, layout.ELC] = 0  # the others' MOBIL off (the ego is row 0)
        for a in [action, *continuation[: depth - 1]]:
            sim.step(int(a))
            if sim.G[0, layout.CRASHED]:
                break
        else:
            return True
    return False


def drive(path: str, depth: int, pool: bool, lane_changes: bool) -> dict[str, Any]:
    """One spawn played with the oracle's fallback choice: did it crash, and how many choices it changed."""
    cx = load_counterexample(path)
    env = make_env(cx.env_config())
    shield = env
    while not isinstance(shield, SafetyShield):
        shield = shield.env
    sim = fast_simulator_of(env)
    env.reset(seed=cx.seed)
    changed, crashed, decisions = 0, False, 0
    for chosen in [*cx.actions, *[IDLE] * TAIL_DECISIONS]:
        decisions += 1
        result = shield.result
        if result.fallback:
            choice = int(np.argmax(result.mask))
            candidates = set(np.flatnonzero(result.available).tolist())
            if pool:
                state_now, dyn = shield.state_and_dynamics(shield.snapshot)
                nominal = evaluate(state_now, dyn, "nominal")
                if nominal.safe.any():
                    candidates = set(np.flatnonzero(nominal.safe).tolist())
            state = sim.get_state()
            if not (choice in candidates and clear(sim, state, choice, depth, lane_changes)):
                for a in PREFERENCE:
                    if a in candidates and clear(sim, state, a, depth, lane_changes):
                        changed += a != choice
                        choice = a
                        break
            sim.set_state(state)
            mask = np.zeros(5, dtype=bool)
            mask[choice] = True
            shield.result = dataclasses.replace(result, mask=mask)
        *_, terminated, truncated, info = env.step(int(chosen))
        if info["collision"]:
            crashed = True
            break
        if terminated or truncated:
            break
    env.close()
    return {"file": Path(path).name, "crashed": crashed, "choices_changed": changed, "decisions": decisions}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("campaign", type=Path, help="A falsify output folder with crash_classes.json.")
    parser.add_argument("--depth", type=int, default=4, help="Decisions each candidate is tried for.")
    parser.add_argument("--pool", action="store_true", help="Only nominal's safe actions when there are some.")
    parser.add_argument("--no-lane-changes", action="store_true", help="The others' MOBIL off in the copies.")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    classes = json.loads((args.campaign / "crash_classes.json").read_text())
    names = sorted(r["file"] for r in classes["rows"] if r["context"] == "started_unsafe")
    files = [str(args.campaign / "counterexamples" / name) for name in names]
    n = len(files)
    with ProcessPoolExecutor(args.workers) as workers:
        rows = list(workers.map(drive, files, [args.depth] * n, [args.pool] * n, [not args.no_lane_changes] * n))
    summary = {
        "campaign": str(args.campaign),
        "replayed": n,
        "oracle": {"depth": args.depth, "pool": args.pool, "lane_changes": not args.no_lane_changes},
        "crashed": sum(r["crashed"] for r in rows),
        "rows": rows,
    }
    atomic_write_text(args.out, json.dumps(summary, indent=1))
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}))


if __name__ == "__main__":
    main()
