"""How many of a campaign's invariant breaks lie outside the rule's model: every break file of a folder
(``safelane falsify``'s ``counterexamples/``, or a random sample of them) replayed to its state and
repaired (:func:`research.counterexample_tools.repair_break`: every vehicle that rolled back beyond the
model in the break's decision put back inside it). A break whose repaired state has a safe action needed
the roll-back (outside the model); the rest are holes of the rule.

    .venv/bin/python research/repair_breaks.py runs/falsify/grid/counterexamples --sample 600 \
        --out runs/falsify/grid/break_repairs.json [--culprits]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for `research.*`

from research.counterexample_tools import break_culprits, repair_break
from safelane.core.errors import ConfigError
from safelane.core.files import atomic_write_text
from safelane.running.counterexamples import counterexample_files, load_counterexample

QUANTILES = (0.0, 0.1, 0.25, 0.5, 0.75, 0.9, 1.0)
"""The quantiles of the breaks' best gap [m] the summary prints."""


def repair(path: str, culprits: bool = False) -> dict[str, Any]:
    """One break file: its name, :func:`repair_break`'s verdict and, with ``culprits``, the role of its first
    leave-one-out culprit (:func:`~research.counterexample_tools.break_culprits`)."""
    cx = load_counterexample(path)
    row: dict[str, Any] = {"file": Path(path).name, **repair_break(cx)}
    if culprits:
        row["role"] = break_culprits(cx)["role"]
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--sample", type=int, default=None, help="At most this many files, drawn at random.")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--culprits", action="store_true", help="Also the role of each break's first culprit.")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    try:
        files = counterexample_files(args.folder, "invariant_break", args.sample, args.seed)
    except ConfigError as error:
        parser.exit(2, f"error: {error}\n")
    with ProcessPoolExecutor(args.workers) as pool:
        rows = list(pool.map(repair, files, [args.culprits] * len(files), chunksize=8))
    outside = [r for r in rows if r["safe_after_repair"]]
    summary = {
        "folder": str(args.folder),
        "breaks": len(rows),
        "with_roll_back": sum(bool(r["repaired"]) for r in rows),
        "outside_model": len(outside),
        "holes": len(rows) - len(outside),
        # How deep below the margin the breaks go: a break at >= 0 m still has a fallback the model calls
        # collision-free (the margin was eaten), one below 0 m does not.
        "best_gap_below_zero": sum(r["best_gap"] < 0.0 for r in rows),
        "best_gap_quantiles": [round(float(q), 3) for q in np.quantile([r["best_gap"] for r in rows], QUANTILES)]
        if rows
        else [],
        **({"roles": dict(Counter(r["role"] for r in rows).most_common())} if args.culprits else {}),
        "rows": rows,
    }
    atomic_write_text(args.out, json.dumps(summary, indent=1))
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}))


if __name__ == "__main__":
    main()
