"""The shield's compiled kernel against the same kernel at another commit: same masks, and which is cheaper.

Loads the kernel's modules (``compiled``, ``compiled_rule``, ``compiled_parts``, ``forecast``) as they are at
``--commit`` into a temporary package, records the random-policy states of :mod:`mask_cost_profile` (the bench's
traffic and dense traffic), checks that both kernels return the same mask, safe and available actions, fallback
flag and gaps (bit for bit) on every state, and times both on every state (best of ``--reps``, interleaved state
by state, in one process): mean, median, p99 [µs] of each.

    PYTHONPATH=src python research/kernel_ab.py --commit main --episodes 40
"""

from __future__ import annotations

import argparse
import importlib
import re
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for `research.*`

from research import mask_cost_profile as mcp
from safelane.safety.one_decision.compiled import snapshot_kernel

KERNEL_MODULES = ("compiled_parts", "forecast", "compiled_rule", "compiled")
"""The modules of the compiled shield that are loaded from the other commit (the rest is this tree's)."""


def reference_kernel(commit: str, package: str = "kernel_at_commit") -> Any:
    """The ``snapshot_kernel`` of ``commit`` (loaded from ``git show`` into a temporary package)."""
    root = Path(tempfile.mkdtemp(prefix="safelane-kernel-ab-"))
    folder = root / package
    folder.mkdir()
    (folder / "__init__.py").write_text("")
    for name in KERNEL_MODULES:
        text = _source_at(commit, name)
        for other in KERNEL_MODULES:  # its own modules from the package, the rest (reference, rule, core) from here
            text = re.sub(rf"\bsafelane\.safety\.(one_decision\.)?{other}\b", f"{package}.{other}", text)
        text = re.sub(r"\bsafelane\.safety\.model\b", "safelane.safety.one_decision.reference", text)  # older layout
        text = re.sub(
            r"from (safelane\.safety(?:\.one_decision)?) import ([\w, ]+)\n",
            lambda m: _split_import(m.group(2), package, m.group(1)),
            text,
        )
        (folder / f"{name}.py").write_text(text)
    sys.path.insert(0, str(root))
    return importlib.import_module(f"{package}.compiled").snapshot_kernel


def _source_at(commit: str, name: str) -> str:
    """The text of kernel module ``name`` at ``commit``: in ``safety/one_decision/``, or at older commits
    ``safety/``."""
    for folder in ("src/safelane/safety/one_decision", "src/safelane/safety"):
        shown = subprocess.run(
            ["git", "show", f"{commit}:{folder}/{name}.py"],
            capture_output=True,
            text=True,
            cwd=Path(__file__).resolve().parents[1],
        )
        if shown.returncode == 0:
            return shown.stdout
    raise FileNotFoundError(f"{name}.py: not in src/safelane/safety[/one_decision] at {commit}")


def _split_import(names: str, package: str, source: str = "safelane.safety") -> str:
    """``from SOURCE import NAMES`` with the kernel modules taken from ``package`` and the rest from ``source``
    (an older commit's ``model``: this tree's one-decision reference)."""
    ours = [n.strip() for n in names.split(",") if n.strip() in KERNEL_MODULES]
    theirs = [n.strip() for n in names.split(",") if n.strip() not in KERNEL_MODULES]
    lines = [f"from {package} import {', '.join(ours)}\n"] if ours else []
    for name in theirs:
        if name == "model":
            lines.append("from safelane.safety.one_decision import reference as model\n")
        else:
            lines.append(f"from {source} import {name}\n")
    return "".join(lines)


def same(a: tuple, b: tuple) -> bool:
    """Whether two kernel results are the same bits (NaN equal to NaN)."""
    pairs = [(np.asarray(x), np.asarray(y)) for x, y in zip(a, b, strict=True)]
    return all(np.array_equal(x, y, equal_nan=x.dtype.kind == "f") for x, y in pairs)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--commit", default="main", help="The commit whose kernel is compared with this tree's.")
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--traffic", default="bench,dense")
    args = parser.parse_args(argv)
    before = reference_kernel(args.commit)
    figures: dict[str, Any] = {}
    for name in args.traffic.split(","):
        states = mcp.record(mcp.TRAFFIC[name], args.episodes, args.seed)
        mismatches = sum(not same(before(*s["args"]), snapshot_kernel(*s["args"])) for s in states)
        times: dict[str, list[float]] = {"before": [], "after": []}
        for s in states:
            a = s["args"]
            calls = {"before": lambda: before(*a), "after": lambda: snapshot_kernel(*a)}  # noqa: B023
            best = {k: float("inf") for k in calls}
            for _ in range(args.reps):
                for k, fn in calls.items():
                    best[k] = min(best[k], mcp.best_of(fn, 1))
            for k in calls:
                times[k].append(best[k])
        fig = {k: mcp.summary(np.asarray(v)) for k, v in times.items()}
        fig["mismatches"] = mismatches
        figures[name] = fig
        print(f"{name}: {len(states)} states, {mismatches} with a different result")
        for k in ("before", "after"):
            f = fig[k]
            print(f"  {k:<6} ({args.commit if k == 'before' else 'this tree'}): mean {f['mean']:.1f} median "
                  f"{f['median']:.1f} p99 {f['p99']:.1f} max {f['max']:.1f} µs")  # fmt: skip
    return figures


if __name__ == "__main__":
    main()
