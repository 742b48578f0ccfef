"""What a change of the rule does to a campaign's invariant breaks: every break file of a folder (``safelane
falsify``'s ``counterexamples/``, or a random sample of them) replayed to its state — no safe action under the
rule it ran with — and judged with some of the rule's Dynamics fields changed
(:func:`research.counterexample_tools.break_under_options`): how many then have a safe action, by the role
of each break's first leave-one-out culprit. A diagnostic of where breaks come from, not a proof that a change is
sound (a change can only be judged by a campaign and by highway-env).

    .venv/bin/python research/breaks_under_options.py runs/falsify/grid_100k_behind/counterexamples \
        --sample 200 --set follower_reaction=0 --out runs/falsify/grid_100k_behind/breaks_under_options.json

``--carried-followers`` instead judges each break with the follower bounds of the decision before it carried over
(:func:`research.counterexample_tools.break_with_carried_followers`, docs/research/nested-follower-bound.md): those of
the
cars the ego was already in front of in their lane, or with ``--all-followers`` those of every car behind.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for `research.*`

from research.counterexample_tools import (
    break_culprits,
    break_under_options,
    break_with_carried_followers,
    check_rule_options,
)
from safelane.core.errors import ConfigError
from safelane.core.files import atomic_write_text
from safelane.running.counterexamples import counterexample_files, load_counterexample


def parse_option(text: str) -> tuple[str, Any]:
    """``name=value`` → (name, True / False / a float)."""
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise ConfigError(f"--set: got {text!r}; expected NAME=VALUE (a Dynamics field, true/false or a number)")
    if value in ("true", "false"):
        return name, value == "true"
    try:
        return name, float(value)
    except ValueError:
        raise ConfigError(f"--set {name}: got {value!r}; expected true, false or a number") from None


def judge(path: str, options: dict[str, Any] | None, reacting_only: bool = True) -> dict[str, Any]:
    """One break file: its name, its first culprit's role and :func:`break_under_options`'s verdict (``options``
    None: :func:`break_with_carried_followers`' with ``reacting_only``, its ``safe_carried`` as
    ``safe_with_options``)."""
    cx = load_counterexample(path)
    if options is None:
        verdict = break_with_carried_followers(cx, reacting_only=reacting_only)
        verdict["safe_with_options"] = verdict.pop("safe_carried")
    else:
        verdict = break_under_options(cx, options)
    return {"file": Path(path).name, "role": break_culprits(cx)["role"], **verdict}


def main() -> None:
    """Parse the arguments, judge the breaks, write the JSON, print its summary."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--sample", type=int, default=None, help="At most this many files, drawn at random.")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--set", action="append", default=[], help="NAME=VALUE, a Dynamics field (repeatable).")
    parser.add_argument("--carried-followers", action="store_true", help="Carry the follower bounds instead.")
    parser.add_argument(
        "--all-followers", action="store_true", help="With --carried-followers: carry every car behind, not only"
        " the cars the ego was already in front of in their lane.",
    )  # fmt: skip
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    try:
        options = dict(parse_option(text) for text in args.set)
        check_rule_options(options)  # before the workers start: one line, not a worker's traceback
        if args.carried_followers and options:
            raise ConfigError("--carried-followers: judged with the rule as it ran; drop --set")
        if args.all_followers and not args.carried_followers:
            raise ConfigError("--all-followers: a choice of --carried-followers; add it")
        files = counterexample_files(args.folder, "invariant_break", args.sample, args.seed)
    except ConfigError as error:
        parser.exit(2, f"error: {error}\n")
    with ProcessPoolExecutor(args.workers) as pool:
        given = None if args.carried_followers else options
        reacting = [not args.all_followers] * len(files)
        rows = list(pool.map(judge, files, [given] * len(files), reacting, chunksize=4))
    roles, fixed = Counter(r["role"] for r in rows), Counter(r["role"] for r in rows if r["safe_with_options"])
    summary = {
        "folder": str(args.folder),
        "options": ("carried_followers_all" if args.all_followers else "carried_followers_reacting")
        if args.carried_followers
        else options,
        "breaks": len(rows),
        "safe_with_options": sum(fixed.values()),
        "by_role": {role: f"{fixed[role]}/{n}" for role, n in roles.most_common()},
        "rows": rows,
    }
    atomic_write_text(args.out, json.dumps(summary, indent=1))
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}))


if __name__ == "__main__":
    main()
