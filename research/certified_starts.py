"""Which spawns each rule can vouch for: the committed rule's certified starts beside the one-decision rule's safe
ones, and the cars whose sets leave a spawn uncertified.

For every traffic condition of a campaign spec (its axes without the policies: spawns do not depend on the
policy) ``--spawns`` resets are drawn with the campaign's traffic seeds; at each first state the script records
whether the one-decision robust rule has a safe action (``robust_safe``) and whether the committed rule verifies
a plan (``certified``). For a spawn the robust rule calls safe and the committed rule does not, the plan with the
fewest failing cars (numpy reference, :func:`safelane.safety.committed.plans.car_gaps`) names the cars that block it,
each put in a class by where it is against the ego now (its lane against the ego's, ahead / beside within
``BESIDE`` m / behind).

    .venv/bin/python research/certified_starts.py configs/falsify/claim-committed.yaml --spawns 10 \
        --out runs/certified-starts.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for `research.*`

from safelane.core.files import atomic_write_text

BESIDE = 10.0
"""[m] A car whose centre is within this distance of the ego's along the road is beside it."""


def position_class(lane_offset: int, dx: float) -> str:
    """Where a car is against the ego: ``same`` / ``next`` / ``far`` lane, then ``ahead`` / ``beside`` /
    ``behind`` (``dx`` [m] along the road, car minus ego)."""
    lane = "same" if lane_offset == 0 else "next" if abs(lane_offset) == 1 else "far"
    where = "beside" if abs(dx) < BESIDE else "ahead" if dx > 0 else "behind"
    return f"{lane}_{where}"


def blocking_cars(snap: Any, dyn: Any) -> list[str]:
    """The classes of the cars failing the plan with the fewest failing cars in ``snap``'s state."""
    from safelane.core.spaces import N_ACTIONS
    from safelane.safety.committed.plan_family import onsets
    from safelane.safety.committed.plans import car_gaps
    from safelane.safety.committed.sets import car_sets
    from safelane.safety.ego import action_lanes, available_actions, ego_trajectories
    from safelane.safety.road import whole_road_state

    state, vehicle = whole_road_state(snap, dyn.rule.ego_speed_magnitude)
    sets = car_sets(state, dyn, vehicle)
    ego_x, _ = ego_trajectories(state, dyn)
    available = available_actions(state, dyn)
    best: np.ndarray | None = None
    for a in range(N_ACTIONS):
        if not available[a]:
            continue
        gaps = car_gaps(state, dyn, sets, ego_x[a], onsets(dyn, a), action_lanes(state, dyn, a))
        failing = ~(gaps >= dyn.margin)  # (cars, holds)
        for k in range(failing.shape[1]):
            if best is None or failing[:, k].sum() < best.sum():
                best = failing[:, k]
    if best is None:
        return []
    lanes = state.lane_of(state.y, dyn.lanes_count, dyn.lane_width)
    return [position_class(int(lanes[i]) - int(state.ego_lane), float(state.x[i] - state.ego_x))
            for i in np.flatnonzero(best)]  # fmt: skip


def condition_spawns(spec_path: str, index: int, spawns: int) -> dict[str, Any]:
    """One traffic condition (``index`` into the spec's cells of its first policy): ``spawns`` first states."""
    from safelane.env.factory import make_env
    from safelane.env.scenarios import find_shield
    from safelane.running.falsify.grid import (
        CELL_SEED_STRIDE,
        FALSIFY_SEED_BASE,
        cell_config,
        load_campaign_spec,
        traffic_seed_base,
    )
    from safelane.safety.family import family_for

    spec = load_campaign_spec(spec_path)
    cells = spec.cells()
    cell = cells[index]
    env = make_env(cell_config(spec, cell))
    robust = family_for("robust", "compiled")
    seed = traffic_seed_base(FALSIFY_SEED_BASE, spec.seed) + CELL_SEED_STRIDE * index
    shield = find_shield(env)
    rows = []
    try:
        for k in range(spawns):
            _, info = env.reset(seed=seed + k)
            snap = info["snapshot"]
            robust_safe = not robust.evaluate(snap, shield.dynamics, shield.ego_leave_time(snap)).fallback
            certified = not info["uncertified_start"]
            row: dict[str, Any] = {"robust_safe": bool(robust_safe), "certified": bool(certified)}
            if robust_safe and not certified:
                dyn = dataclasses.replace(shield.dynamics, ego_leave_time=shield.ego_leave_time(snap))
                row["blocking"] = blocking_cars(snap, dyn)
            rows.append(row)
    finally:
        env.close()
    return {"index": index, "labels": cell["labels"], "spawns": rows}


def summary(conditions: list[dict[str, Any]]) -> str:
    """Markdown: the shares side by side, per axis setting, and the blocking cars' classes."""
    spawns = [s for c in conditions for s in c["spawns"]]
    n = len(spawns)
    robust = sum(s["robust_safe"] for s in spawns)
    certified = sum(s["certified"] for s in spawns)
    gap = [s for s in spawns if s["robust_safe"] and not s["certified"]]
    lines = [
        f"{len(conditions)} traffic conditions × {n // max(len(conditions), 1)} spawns = {n} first states: "
        f"**one-decision rule safe {robust} ({100 * robust / n:.1f} %), committed rule certified {certified} "
        f"({100 * certified / n:.1f} %)**; safe by the one-decision rule but uncertified: {len(gap)}; certified "
        f"but not safe by the one-decision rule: {sum(s['certified'] and not s['robust_safe'] for s in spawns)}.",
        "",
        "| axis | setting | spawns | one-decision safe | committed certified |",
        "|---|---|---|---|---|",
    ]
    for axis in conditions[0]["labels"] if conditions else []:
        for value in sorted({c["labels"][axis] for c in conditions}):
            ss = [s for c in conditions if c["labels"][axis] == value for s in c["spawns"]]
            lines.append(
                f"| {axis} | {value} | {len(ss)} | {100 * sum(s['robust_safe'] for s in ss) / len(ss):.1f} % | "
                f"{100 * sum(s['certified'] for s in ss) / len(ss):.1f} % |"
            )
    classes = Counter(b for s in gap for b in s.get("blocking", []))
    one = Counter(s["blocking"][0] for s in gap if len(s.get("blocking", [])) == 1)
    lines += [
        "",
        f"Cars failing the least-blocked plan of the {len(gap)} spawns safe by the one-decision rule but uncertified "
        f"(class: cars; spawns where that car alone blocks it):",
        "",
        "| where the car is | cars | sole blocker |",
        "|---|---|---|",
        *(f"| {name} | {count} | {one.get(name, 0)} |" for name, count in classes.most_common()),
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("spec", help="a campaign spec (its axes are the traffic conditions)")
    parser.add_argument("--spawns", type=int, default=10, help="first states per condition")
    parser.add_argument("--out", required=True, help="JSON of every spawn; a .md summary is written beside it")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args(argv)
    from safelane.running.falsify.grid import load_campaign_spec

    spec = load_campaign_spec(args.spec)
    first_policy = [c["index"] for c in spec.cells() if c["policy"] == spec.policies[0]]
    with ProcessPoolExecutor(args.workers) as pool:
        conditions = list(pool.map(condition_spawns, [args.spec] * len(first_policy), first_policy,
                                   [args.spawns] * len(first_policy), chunksize=8))  # fmt: skip
    out = Path(args.out)
    atomic_write_text(out, json.dumps({"spec": args.spec, "spawns": args.spawns, "conditions": conditions}))
    atomic_write_text(out.with_suffix(".md"), summary(conditions))
    print(summary(conditions))


if __name__ == "__main__":
    main()
