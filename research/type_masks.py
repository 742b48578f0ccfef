"""Is the robust shield's reading of a hidden driver mixture a worst case over the types? Play ``hidden-types``
episodes on the fast simulator (the ego: a fixed policy under the ``--drive`` shield with override) and at every
decision judge the state with the ``robust`` shield (every type of the mixture) and the ``omniscient`` one (each car's
true type). A reading that is the worst case over the types has ``safe(robust) ⊆ safe(omniscient)`` in every state,
falls back wherever omniscient does, and its mask is inside omniscient's wherever neither falls back.

    python research/type_masks.py --policy faster --drive omniscient --episodes 50 --dump /tmp/violations.pkl

Each shield's fallback rate in ``safelane evaluate`` is measured on its own episodes: the states differ (the ego under
the omniscient shield drives faster), so only the states judged by both say whether one shield's masks are inside
the other's.

Counts, per decision: states, each shield's fallbacks, states where robust's safe set is not inside omniscient's
(``safe_violations``), where robust's mask is not inside omniscient's and robust did not fall back
(``mask_violations``), and where it is not whatever the fallbacks (``mask_violations_any``). ``--explain``: for each
safe-set violation, the car that makes it (robust's view with that car alone read as its true type forbids the
action) and, for that car, the driver fields each of which, set alone to the true type's value, forbids it (the
per-field reading's roles that are not the worst case). ``--dump``: the first violating snapshots, pickled, with the
action. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
import sys
import time
from collections import Counter
from typing import Any

import numpy as np

from safelane.core.drivers import idm_parameters
from safelane.core.snapshot import RoadSnapshot
from safelane.core.spaces import FASTER
from safelane.env.factory import make_env
from safelane.safety.belief import DriverTypes
from safelane.safety.driver_sets import true_type
from safelane.safety.shield import SafetyShield

FIELDS = ("accel_max", "idm_comfort_acc", "idm_comfort_dec", "idm_distance_wanted", "idm_time_wanted",
          "max_braking_imposed", "politeness")  # fmt: skip
"""The driver arrays in which the mixture's types differ (``brake_max`` is 6 m/s² for every type)."""


def _explain(robust: SafetyShield, omni: SafetyShield, snap: RoadSnapshot, action: int) -> list[str]:
    """The car (and its fields) whose true type alone forbids ``action`` in robust's view, as ``car:field`` labels
    (``car:-`` when no single field does, ``joint`` when no single car does)."""
    view = robust.driver_view(snap)
    truth = omni.driver_view(snap)
    _, cars = true_type(snap, len(robust.types or ()))
    dyn = robust.dynamics
    assert dyn is not None
    leave = robust.ego_leave_time(snap)

    def unsafe(s: RoadSnapshot) -> bool:
        return not bool(robust.family.evaluate(s, dyn, leave).safe[action])

    labels = []
    for c in cars:
        arrays = {f: np.array(getattr(view, f), copy=True) for f in FIELDS}
        for f in FIELDS:
            arrays[f][c] = getattr(truth, f)[c]
        if not unsafe(dataclasses.replace(view, **arrays)):
            continue
        found = []
        for f in FIELDS:
            one = np.array(getattr(view, f), copy=True)
            one[c] = getattr(truth, f)[c]
            if unsafe(dataclasses.replace(view, **{f: one})):
                found.append(f)
        kind = ["timid", "normal", "aggressive"][int(snap.driver_type[c])]  # type: ignore[index]
        labels.append(f"{kind}:{'+'.join(found) or '-'}")
    return labels or ["joint"]


def run(
    policy: str, drive: str, episodes: int, seed: int, explain: bool, dump: str | None, keep: int
) -> dict[str, Any]:
    env = make_env("hidden-types", simulator="fast", **{"shield.mode": drive, "shield.override": True})
    mix = env.get_wrapper_attr("driver_mix")
    omni = SafetyShield(env.unwrapped, mode="omniscient", driver_types=DriverTypes(mix))
    robust = SafetyShield(env.unwrapped, mode="robust", driver_types=DriverTypes(mix))
    assert robust.types is not None and len(idm_parameters(mix)) == 3
    rng = np.random.default_rng(seed)
    counts: Counter[str] = Counter()
    causes: Counter[str] = Counter()
    dumped: list[dict[str, Any]] = []
    start = time.perf_counter()
    for k in range(episodes):
        _, info = env.reset(seed=seed + k)
        done = False
        while True:
            snap = info["snapshot"]
            robust.dynamics = omni.dynamics = env.get_wrapper_attr("dynamics")  # the episode's constants
            r = robust.compute_result(snap)
            o = omni.compute_result(snap)
            counts["states"] += 1
            counts["robust_fallbacks"] += int(r.fallback)
            counts["omniscient_fallbacks"] += int(o.fallback)
            bad_safe = r.safe & ~o.safe
            bad_mask = r.mask & ~o.mask
            counts["safe_violations"] += int(bad_safe.any())
            counts["mask_violations_any"] += int(bad_mask.any())
            counts["mask_violations"] += int(bad_mask.any() and not r.fallback)
            counts["omniscient_fallback_not_robust"] += int(o.fallback and not r.fallback)
            if bad_safe.any():
                action = int(np.flatnonzero(bad_safe)[0])
                if explain:
                    for label in _explain(robust, omni, snap, action):
                        causes[label] += 1
                if dump and len(dumped) < keep:
                    dumped.append({"snapshot": snap, "action": action, "robust": r.mask, "omniscient": o.mask})
            if done:
                break
            action = FASTER if policy == "faster" else int(rng.integers(5))
            _, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
    env.close()
    if dump:
        with open(dump, "wb") as fh:
            pickle.dump(dumped, fh)
    wall = round(time.perf_counter() - start, 1)
    return {"policy": policy, "drive": drive, "episodes": episodes, "seed": seed, **counts,
            "causes": dict(causes.most_common()), "wall_s": wall}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--policy", choices=("faster", "random"), default="faster")
    p.add_argument("--drive", choices=("robust", "omniscient"), default="robust", help="the ego's shield")
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--explain", action="store_true")
    p.add_argument("--dump", default=None)
    p.add_argument("--keep", type=int, default=50)
    args = p.parse_args(argv)
    print(json.dumps(run(args.policy, args.drive, args.episodes, args.seed, args.explain, args.dump, args.keep)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
