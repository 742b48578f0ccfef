"""Could any policy have avoided a campaign's crashes from unsafe spawns? Replay each spawn with perfect foresight.

A crash counted ``started_unsafe`` (``research/classify_crashes.py``) happened in an episode whose every state
before the crash had no safe action: the rule promises nothing there. This asks whether the spawn itself was
hopeless: for each such crash file (or a random sample), the same configuration and reset seed are played by the
unmasked :class:`~safelane.running.foresight.ForesightPlanner` — it knows exactly what every other driver will do
(the fast simulator's drivers are deterministic after reset) and searches meta-action sequences for the fastest
collision-free one. A spawn it cannot drive through without a crash is one this search finds no way through — a
bound of the search only, not of what any policy could do: the forecast-ranked shield of
docs/research/fallback-choice.md drives
96 of the claim campaign's 165 such spawns through; one it survives is a crash a better fallback choice might avoid.

    .venv/bin/python research/spawn_foresight.py runs/falsify/grid_100k_behind_turning_in_nominal \
        --sample 60 --out runs/falsify/grid_100k_behind_turning_in_nominal/spawn_foresight.json
"""

from __future__ import annotations

import argparse
import json
import random
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from safelane.core.files import atomic_write_text
from safelane.running.counterexamples import load_counterexample
from safelane.running.foresight import ForesightPlanner, play, row_config


def drive(path: str, horizon: float, beam: int) -> dict[str, Any]:
    """One crash file's spawn driven by the unmasked foresight planner: did it crash, and its mean speed [m/s]."""
    cx = load_counterexample(path)
    cfg = row_config(cx.env_config(), "foresight")  # the fast simulator, no shield
    result = play(cfg, lambda env: ForesightPlanner(env, mask="none", horizon=horizon, beam=beam), 1, cx.seed)
    drivers = str(cx.config.get("env", {}).get("other_vehicles_type", "")).rsplit(".", 1)[-1]
    rate = cx.config.get("env", {}).get("policy_frequency")
    return {
        "file": Path(path).name,
        "drivers": drivers,
        "rate": rate,
        "crash_step": cx.step,
        "foresight_collision": result["collisions"] > 0,
        "foresight_speed": result["mean_speed"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("campaign", type=Path, help="A falsify output folder with crash_classes.json.")
    parser.add_argument("--sample", type=int, default=None, help="At most this many files, drawn at random.")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--horizon", type=float, default=4.0, help="The planner's search horizon [s].")
    parser.add_argument("--beam", type=int, default=8, help="Sequences the planner keeps per depth.")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    classes = json.loads((args.campaign / "crash_classes.json").read_text())
    names = sorted(r["file"] for r in classes["rows"] if r["context"] == "started_unsafe")
    if args.sample is not None and args.sample < len(names):
        names = sorted(random.Random(args.seed).sample(names, args.sample))
    files = [str(args.campaign / "counterexamples" / name) for name in names]
    with ProcessPoolExecutor(args.workers) as pool:
        rows = list(pool.map(drive, files, [args.horizon] * len(files), [args.beam] * len(files)))
    unavoidable = [r for r in rows if r["foresight_collision"]]
    summary = {
        "campaign": str(args.campaign),
        "started_unsafe_crashes": sum(r["context"] == "started_unsafe" for r in classes["rows"]),
        "replayed": len(rows),
        "planner": {"mask": "none", "horizon_s": args.horizon, "beam": args.beam},
        "foresight_crashed": len(unavoidable),
        "foresight_survived": len(rows) - len(unavoidable),
        "crashed_by_drivers": dict(Counter(r["drivers"] for r in unavoidable)),
        "survived_by_drivers": dict(Counter(r["drivers"] for r in rows if not r["foresight_collision"])),
        "rows": rows,
    }
    atomic_write_text(args.out, json.dumps(summary, indent=1))
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}))


if __name__ == "__main__":
    main()
