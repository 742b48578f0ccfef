"""Sort a campaign's crashes against the rule's promise, and tell the ones caused by a vehicle that left
the model (rolling backwards) from the holes of the rule.

For every collision file of a folder (``safelane falsify``'s ``counterexamples/``): its context from the
replay (``started_unsafe``, ``after_break``, ``from_safe_state``, ``after_fallback``, as the campaign
counts them), the crash partner (:func:`research.counterexample_tools.crash_partner`) and, for a crash
after a break, the leave-one-out culprits of the last break before it
(:func:`~research.counterexample_tools.break_culprits`) and its repair
(:func:`~research.counterexample_tools.repair_break`), read from the same folder. A crash is
``outside_model`` when its partner started to roll back or rolled back faster during a decision between the
break and the crash (``partner_rolled_back``), or when the break's state, with every vehicle that did so
in the break's decision put back inside the model, has a safe action (``break_repaired``). The rule's
leader bound lets a braking car stop, or keep a reverse speed it already has — ``shield.reversing_leaders``
— but not accelerate backwards: highway-env lets a jammed IDM car's speed go below zero, which the driver
model does not intend (docs/research/horizon-and-ego-speed.md, docs/research/turning-leaders.md). Crashes that started
unsafe are counted, not analysed.

    .venv/bin/python research/classify_crashes.py runs/falsify/grid_e20/counterexamples \
        --out runs/falsify/grid_e20/crash_classes.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for `research.*`

from research.counterexample_tools import REVERSING_MARGIN, break_culprits, crash_partner, repair_break
from safelane.core.files import atomic_write_text
from safelane.running.counterexamples import load_counterexample, replay


def context_of(decisions: list[Any]) -> str:
    """The collision's context from its replay's decision log (the rules of ``EpisodeTally``)."""
    last = decisions[-1]
    if all(d.fallback_before for d in decisions):
        return "started_unsafe"
    if any(d.invariant_break for d in decisions[:-1]):
        return "after_break"
    if not last.fallback_before and last.chosen == last.executed:
        return "from_safe_state"
    return "after_fallback"


def classify(path: str) -> dict[str, Any]:
    """One crash file: its context, partner and, after a break, the break's culprits and the verdict."""
    cx = load_counterexample(path)
    result = replay(cx)
    row: dict[str, Any] = {"file": Path(path).name, "context": context_of(result.decisions)}
    if row["context"] == "started_unsafe":
        return row
    partner = crash_partner(cx)
    row["partner"] = partner
    reasons = []
    breaks = [d.step for d in result.decisions[:-1] if d.invariant_break]
    # The partner's speed at each decision from the first break (or the last decision) to the crash.
    since = breaks[0] - 1 if breaks else len(result.decisions) - 1
    speeds = [
        next((v["speed"] for v in d.nearby if v["vehicle"] == partner["vehicle"]), None)
        for d in result.decisions[since:]
    ] + [next((v["speed"] for v in result.final["nearby"] if v["vehicle"] == partner["vehicle"]), None)]
    row["partner_speeds"] = speeds
    known = [v for v in speeds if v is not None]
    if any(b < min(a, 0.0) - REVERSING_MARGIN for a, b in itertools.pairwise(known)):
        reasons.append("partner_rolled_back")
    if breaks:
        stem = Path(path).name.split("-collision-")[0]
        break_file = Path(path).parent / f"{stem}-invariant_break-step{breaks[-1]}.json"
        if break_file.exists():
            culprits = break_culprits(load_counterexample(break_file))
            repair = repair_break(load_counterexample(break_file))
            row["break"] = {
                "file": break_file.name,
                "role": culprits["role"],
                "culprits": culprits["culprits"],
                "repair": repair,
            }
            # The break's state with every vehicle that rolled back put back inside the model has a safe
            # action: the break needed the roll-back. (Leave-one-out would also excuse a break whose
            # rolled-back culprit merely stands beside an in-model hole.)
            if repair["safe_after_repair"]:
                reasons.append("break_repaired")
    row["outside_model"] = sorted(set(reasons))
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    files = sorted(str(p) for p in args.folder.glob("*-collision-*.json"))
    # A campaign's cell records say which cells had a crash inside the promise: only those are replayed.
    cells = args.folder.parent / "cells"
    settled: list[dict[str, Any]] = []
    if cells.is_dir():
        inside = set()
        for record in cells.glob("cell*.json"):
            data = json.loads(record.read_text())
            if sum(n for k, n in data.get("collision_contexts", {}).items() if k != "started_unsafe"):
                inside.add(record.stem)
        outside = [f for f in files if Path(f).name.split("-")[0] not in inside]
        settled = [{"file": Path(f).name, "context": "started_unsafe"} for f in outside]
        files = [f for f in files if Path(f).name.split("-")[0] in inside]
    with ProcessPoolExecutor(args.workers) as pool:
        rows = settled + list(pool.map(classify, files))
    contexts: dict[str, int] = {}
    for r in rows:
        contexts[r["context"]] = contexts.get(r["context"], 0) + 1
    analysed = [r for r in rows if r["context"] != "started_unsafe"]
    summary = {
        "folder": str(args.folder),
        "collisions": len(rows),
        "contexts": contexts,
        "inside_promise": len(analysed),
        "outside_model": sum(bool(r["outside_model"]) for r in analysed),
        "holes": [r["file"] for r in analysed if not r["outside_model"]],
        "rows": rows,
    }
    atomic_write_text(args.out, json.dumps(summary, indent=1))
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}, indent=1))


if __name__ == "__main__":
    main()
