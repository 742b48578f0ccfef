"""What a campaign's lapses in the model are under this checkout's code: replay every ``lapse_in_model`` file of a
campaign folder (or the files given) on the fast simulator and count what each becomes — no lapse at that decision,
a lapse traced (to a car that left its set or cut in, or to the ego's crash), or still a lapse in the model (named,
for the next look).

    python research/replay_lapses.py runs/falsify/claim-committed/counterexamples --out runs/replayed_lapses.json

Prints a summary (counts and the files still in the model); ``--out`` keeps the verdict of every file.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path
from typing import Any


def replay_lapse(path: Path) -> dict[str, Any]:
    """The committed verdict at a lapse file's decision, replayed on the fast simulator under this code."""
    from safelane.running.counterexamples import load_counterexample, replay

    result = replay(load_counterexample(path), "fast")
    verdict = result.decisions[-1].committed or {}
    outcome = "no lapse"
    if verdict.get("lapse"):
        outcome = "lapse in the model" if verdict.get("lapse_in_model") else "lapse traced"
    return {"outcome": outcome, **{key: verdict.get(key) for key in ("lapse_cars", "escaped_cars", "entered_cars")}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="+", type=Path, help="lapse files, or folders of counterexample files")
    parser.add_argument("--out", type=Path, help="write every file's verdict here (JSON)")
    args = parser.parse_args(argv)
    files: list[Path] = []
    for path in args.paths:
        files += sorted(path.glob("*-lapse_in_model-*.json")) if path.is_dir() else [path]
    verdicts = {path.name: replay_lapse(path) for path in files}
    summary = {
        "files": len(verdicts),
        "outcomes": dict(Counter(v["outcome"] for v in verdicts.values())),
        "still_in_the_model": sorted(name for name, v in verdicts.items() if v["outcome"] == "lapse in the model"),
    }
    if args.out is not None:
        args.out.write_text(json.dumps({"summary": summary, "files": verdicts}, indent=1))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
