"""The committed rule's decision against the same rule at another commit: the same verdicts, and which is cheaper.

Loads the committed package (``safelane.safety.committed``: ``sets``, ``plan_family``, ``plans``, ``compiled``,
``family``) as it is at ``--commit`` into a package of its own (``git show``; the rest of the code is this tree's),
then plays the bench's episodes (the ``fast`` preset on the fast simulator, the random policy, its action replaced
by the closest one the committed mask allows, as ``safelane bench``'s ``committed_mask_figures`` does) with two
committed families side by side, the other commit's and this tree's, each with its own memory. At every decision
it checks that both give the same verdict, bit for bit: the result's every field (mask, safe and available actions,
fallback, the worst gaps, the verified plans, lapse, lapse cars, escaped, rolled back, unbraked followers,
entered, certified, courtesy waived), the sets drawn (after the intersection with the carried ones), and after the
commit of the executed action both memories (the kept plan, the follower bounds, the cars counted ahead). It times,
interleaved state by state in one process: each family's ``evaluate`` (best of ``--reps``, the order alternating)
plus its ``commit``, and the robust shield's mask on the same state (best of ``--reps``): mean, median, p99 [µs]
of each and the committed mean ÷ the robust mean (``safelane bench``'s ``committed_mask_ratio_fast``).

    PYTHONPATH=src:. python research/committed_cost_ab.py --commit 21b6463 --episodes 10 --policy-frequency 1,5
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import re
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for `research.*`

from research import mask_cost_profile as mcp
from safelane.env.factory import make_env
from safelane.env.scenarios import find_shield
from safelane.running.bench import BENCH_PRESET
from safelane.running.policies import fixed_policy
from safelane.safety.committed.family import CommittedFamily
from safelane.safety.world import OVERRIDE_ORDER

ROOT = Path(__file__).resolve().parents[1]
MODULES = ("sets", "plan_family", "plans", "compiled", "family")
"""The committed package's modules loaded from the other commit."""


def family_at(commit: str) -> type:
    """The ``CommittedFamily`` class of ``commit``, its package loaded from ``git show`` into a folder of its own
    (kept, so that numba's cache of its kernels serves the next run)."""
    sha = subprocess.run(["git", "rev-parse", commit], capture_output=True, text=True, cwd=ROOT, check=True)
    package = f"committed_at_{sha.stdout.strip()[:12]}"
    root = Path("/tmp") / "safelane-committed-ab"
    folder = root / package
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "__init__.py").write_text("")
    for name in MODULES:
        text = subprocess.run(["git", "show", f"{commit}:src/safelane/safety/committed/{name}.py"],
                              capture_output=True, text=True, cwd=ROOT, check=True).stdout  # fmt: skip
        text = re.sub(r"\bsafelane\.safety\.committed\.(\w+)\b", rf"{package}.\1", text)
        target = folder / f"{name}.py"
        if not target.is_file() or target.read_text() != text:
            target.write_text(text)
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    return importlib.import_module(f"{package}.family").CommittedFamily


def same(a: Any, b: Any) -> bool:
    """Whether two values are the same bits: arrays (NaN equal to NaN), floats, tuples, dicts, dataclasses."""
    if dataclasses.is_dataclass(a) and dataclasses.is_dataclass(b):
        names = [f.name for f in dataclasses.fields(a)]
        return names == [f.name for f in dataclasses.fields(b)] and all(
            same(getattr(a, n), getattr(b, n)) for n in names
        )
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        x, y = np.asarray(a), np.asarray(b)
        return x.shape == y.shape and x.dtype == y.dtype and np.array_equal(x, y, equal_nan=x.dtype.kind == "f")
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and isinstance(b, float):
        return (a == b and np.signbit(a) == np.signbit(b)) or (a != a and b != b)
    return type(a) is type(b) and a == b


def memory(family: Any) -> tuple:
    """What a committed family carries to the next decision."""
    return family.kept, family.kept_verified, family.followers, family.carried_ahead, family.carried


def _timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    t0 = time.perf_counter()
    out = fn()
    return (time.perf_counter() - t0) * 1e6, out


def play(
    old_family: Any, new_family: Any, robust: Any, dyn_of: Callable, env: Any, episodes: int, seed: int, reps: int,
) -> dict[str, Any]:  # fmt: skip
    """Plays ``episodes`` episodes; returns the timings [µs] per decision and the mismatches."""
    times: dict[str, list[float]] = {"before": [], "after": [], "robust": []}
    mismatches: list[str] = []
    for i in range(-1, episodes):  # episode -1: three untimed decisions compile (or load) the kernels
        policy = fixed_policy("random", seed + max(i, 0))
        obs, info = env.reset(seed=seed + max(i, 0))
        old_family.reset()
        new_family.reset()
        done, decisions = False, 0
        while not done and (i >= 0 or decisions < 3):
            snap = info["snapshot"]
            dyn, leave = dyn_of(snap)
            best = {"before": np.inf, "after": np.inf, "robust": np.inf}
            results: dict[str, Any] = {}
            calls = {
                "before": lambda: old_family.evaluate(snap, dyn, leave),  # noqa: B023
                "after": lambda: new_family.evaluate(snap, dyn, leave),  # noqa: B023
                "robust": lambda: robust.compute_result(snap),  # noqa: B023
            }
            for r in range(reps):
                for k in ("before", "after", "robust") if r % 2 == 0 else ("robust", "after", "before"):
                    us, results[k] = _timed(calls[k])
                    best[k] = min(best[k], us)
            old, new = results["before"], results["after"]
            where = f"episode {i} decision {decisions}"
            if not same(old, new):
                diff = [f.name for f in dataclasses.fields(old) if not same(getattr(old, f.name), getattr(new, f.name))]
                mismatches.append(f"{where}: result fields {diff}")
            if not same(old_family._pending[3], new_family._pending[3]):
                mismatches.append(f"{where}: the sets")
            action = int(policy(obs, info))
            mask = new.mask
            executed = action if mask[action] else next(a for a in OVERRIDE_ORDER[action] if mask[a])
            commit_us = {}
            for k, fam in (("before", old_family), ("after", new_family)):
                commit_us[k], _ = _timed(lambda fam=fam, a=executed: fam.commit(a))
            if not same(memory(old_family), memory(new_family)):
                mismatches.append(f"{where}: the memory after commit")
            if i >= 0:
                times["before"].append(best["before"] + commit_us["before"])
                times["after"].append(best["after"] + commit_us["after"])
                times["robust"].append(best["robust"])
            obs, _, terminated, truncated, info = env.step(executed)
            done, decisions = terminated or truncated, decisions + 1
    return {"times": times, "mismatches": mismatches}


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--commit", default="main", help="The commit whose committed package is compared.")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--engine", default="compiled", choices=("compiled", "numpy"))
    parser.add_argument("--policy-frequency", default="1", help="Decisions per second, comma-separated.")
    args = parser.parse_args(argv)
    old_class = family_at(args.commit)
    figures: dict[str, Any] = {}
    for hz in (int(h) for h in args.policy_frequency.split(",")):
        sets = {"env.policy_frequency": hz}
        env = make_env(BENCH_PRESET, simulator="fast", **sets)
        shield = find_shield(make_env(BENCH_PRESET, simulator="fast", **sets, **{"shield.mode": "committed"}))
        robust = find_shield(make_env(BENCH_PRESET, simulator="fast", **sets, **{"shield.mode": "robust"}))
        robust_engine = robust.family.engine if hasattr(robust.family, "engine") else "?"

        def dyn_of(snap: Any, shield: Any = shield) -> tuple[Any, float]:
            leave = shield.ego_leave_time(snap)
            return shield.dynamics, leave

        try:
            out = play(old_class(engine=args.engine), CommittedFamily(engine=args.engine), robust, dyn_of, env,
                       args.episodes, args.seed, args.reps)  # fmt: skip
        finally:
            env.close()
            shield.close()
            robust.close()
        fig = {k: mcp.summary(np.asarray(v)) for k, v in out["times"].items()}
        fig["ratio_before"] = fig["before"]["mean"] / fig["robust"]["mean"]
        fig["ratio_after"] = fig["after"]["mean"] / fig["robust"]["mean"]
        fig["mismatches"] = out["mismatches"]
        figures[f"{hz}Hz"] = fig
        print(f"{hz} decision/s, engine {args.engine} (robust: {robust_engine}): {fig['after']['n']} decisions, "
              f"{len(out['mismatches'])} with a different verdict, sets or memory")  # fmt: skip
        for m in out["mismatches"][:10]:
            print("  ", m)
        for k in ("before", "after", "robust"):
            f = fig[k]
            label = {"before": f"committed at {args.commit}", "after": "committed, this tree", "robust": "robust"}[k]
            print(f"  {label:<28} mean {f['mean']:8.1f}  median {f['median']:8.1f}  p99 {f['p99']:8.1f} µs")
        print(f"  committed mean / robust mean: {fig['ratio_before']:.2f} at {args.commit}, "
              f"{fig['ratio_after']:.2f} this tree")  # fmt: skip
    return figures


if __name__ == "__main__":
    main()
