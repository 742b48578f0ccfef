"""Replay a folder of counterexample files on highway-env (or another simulator) and count how many
reproduce: the falsification campaign's fast-simulator findings, confirmed on the reference.

    .venv/bin/python examples/confirm_counterexamples.py runs/falsify/grid/counterexamples \
        --kind collision --workers 2 --out runs/falsify/grid/confirm_collisions.json [--sample 300 --seed 0]
"""

from __future__ import annotations

import argparse
import json
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from safelane.core.errors import ConfigError
from safelane.core.files import atomic_write_text
from safelane.running.counterexamples import counterexample_files, load_counterexample, replay


def confirm(path: str, simulator: str) -> dict:
    """Replay one file; its name, kind, whether it reproduced and the crash kind seen."""
    cx = load_counterexample(path)
    result = replay(cx, simulator)
    return {
        "file": Path(path).name,
        "kind": cx.kind,
        "recorded_collision_kind": cx.collision_kind,
        "reproduced": result.reproduced,
        "collision_kind": result.collision_kind,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    kinds = ["collision", "invariant_break", "lapse", "lapse_in_model"]
    parser.add_argument("--kind", choices=kinds, default="collision")
    parser.add_argument("--simulator", default="highway-env")
    parser.add_argument("--limit", type=int, default=None, help="At most this many files (sorted by name).")
    parser.add_argument("--sample", type=int, default=None, help="At most this many files, drawn at random.")
    parser.add_argument("--seed", type=int, default=0, help="The draw's seed (with --sample).")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    try:
        files = counterexample_files(args.folder, args.kind, args.sample, args.seed, args.limit)
    except ConfigError as error:
        parser.exit(2, f"error: {error}\n")
    with ProcessPoolExecutor(args.workers) as pool:
        rows = list(pool.map(confirm, files, [args.simulator] * len(files)))
    summary = {
        "simulator": args.simulator,
        "kind": args.kind,
        "files": len(rows),
        **({"sample": args.sample, "seed": args.seed} if args.sample is not None else {}),
        "reproduced": sum(r["reproduced"] for r in rows),
        "same_collision_kind": sum(r["collision_kind"] == r["recorded_collision_kind"] for r in rows),
        "rows": rows,
    }
    atomic_write_text(args.out, json.dumps(summary, indent=1))
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}))


if __name__ == "__main__":
    main()
