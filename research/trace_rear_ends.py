"""What the ego did before the committed shield's crashes that were the others' fault.

For every collision file of a campaign folder (``safelane falsify``'s ``counterexamples/``) played under the
committed shield: the episode is replayed decision by decision, its collision context taken from the same
bookkeeping the campaign uses (:class:`safelane.running.evaluation.EpisodeTally`), and for each crash counted
``others_at_fault`` the decisions of the last ``--window`` seconds before it are sorted, first match wins:

* ``plan_forced_brake``: a decision at which nothing was verified and the kept plan's next step braked;
* ``override_to_slower``: the policy chose something else and the shield executed SLOWER;
* ``policy_slower``: the policy's own SLOWER, allowed by the mask;
* ``lane_change_into_follower``: the ego changed lane with the crash partner behind it in the target lane;
* ``partner_cut_in``: the partner entered the lane the ego holds behind it (the shield's ``entered_cars``);
* ``no_brake``: none of these (the ego held or raised its set-point and was struck).

For each braking decision in the window it also records whether a non-braking action was verified (the sets did
not require braking: ``brake_not_required``), whether the one-decision robust rule called SLOWER safe there, and
whether some verified action was safe by that rule (the courtesy ordering's alternative existed:
``courteous_alternative``). The ego's mean deceleration over the window's hardest decision before the crash's own
[m/s²] is reported (None for a crash at the first decision).

    .venv/bin/python research/trace_rear_ends.py runs/falsify/claim-committed/counterexamples \
        --out runs/falsify/claim-committed/rear_end_trace.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for `research.*`

from safelane.core.files import atomic_write_text
from safelane.core.spaces import LANE_LEFT, LANE_RIGHT, SLOWER
from safelane.running.counterexamples import counterexample_files, load_counterexample

CLASSES: tuple[str, ...] = (
    "plan_forced_brake", "override_to_slower", "policy_slower", "lane_change_into_follower", "partner_cut_in",
    "no_brake",
)  # fmt: skip


def trace(path: str, window_s: float = 3.0) -> dict[str, Any]:
    """One collision file: its context and, for an ``others_at_fault`` crash, the window's decisions sorted."""
    from safelane.env.factory import make_env
    from safelane.env.scenarios import find_shield
    from safelane.running.collisions import classify_collision, collision_partner
    from safelane.running.evaluation import EpisodeTally
    from safelane.safety.family import family_for

    cx = load_counterexample(path)
    cfg = cx.env_config()
    env = make_env(cfg)
    robust = family_for("robust", cfg.shield.engine)
    period = 1.0 / cfg.env["policy_frequency"]
    log: list[dict[str, Any]] = []
    try:
        _, info = env.reset(seed=cx.seed)
        shield = find_shield(env)
        tally = EpisodeTally(cx.seed, info, committed=shield.mode == "committed")
        for action in cx.actions:
            snap = info["snapshot"]
            result = shield.result
            one = robust.evaluate(snap, shield.dynamics, shield.ego_leave_time(snap))
            _, reward, _, _, info = env.step(int(action))
            tally.add(int(action), float(reward), info)
            e = snap.ego
            log.append({
                "chosen": int(action), "executed": int(info.get("executed_action", action)),
                "verified": [bool(v) for v in result.safe], "robust_safe": [bool(v) for v in one.safe],
                "plan_forced": bool(getattr(result, "plan_forced", False)),
                "speed_before": float(snap.speed[e]),
                "speed_after": float(info["snapshot"].speed[info["snapshot"].ego]),
                "lane": int(snap.lane[e]), "entered": [int(v) for v in info.get("entered_cars", ())],
                "snap": snap,
            })  # fmt: skip
            if info.get("collision", False):
                break
    finally:
        env.close()
    crash = info["snapshot"]
    row: dict[str, Any] = {"file": Path(path).name, "context": tally.context, "kind": classify_collision(crash)}
    if tally.context != "others_at_fault":
        return row
    partner = collision_partner(crash)
    window = log[-max(1, math.ceil(window_s / period) + 1) :]
    braking = [d for d in window if d["executed"] == SLOWER]
    kind = "no_brake"
    if any(d["plan_forced"] and d["executed"] == SLOWER for d in window):
        kind = "plan_forced_brake"
    elif any(d["chosen"] != SLOWER and d["executed"] == SLOWER for d in window):
        kind = "override_to_slower"
    elif braking:
        kind = "policy_slower"
    elif partner is not None and any(_into_follower(d, partner) for d in window):
        kind = "lane_change_into_follower"
    elif partner is not None and any(partner in d["entered"] for d in window):
        kind = "partner_cut_in"
    # The crash's own decision is left out: the impact changes the ego's speed.
    decel = [(d["speed_before"] - d["speed_after"]) / period for d in window[:-1]]
    row.update(
        partner=partner,
        trace=kind,
        braking_decisions=len(braking),
        brake_not_required=any(any(v for a, v in enumerate(d["verified"]) if a != SLOWER) for d in braking),
        slower_robust_safe=all(d["robust_safe"][SLOWER] for d in braking) if braking else None,
        courteous_alternative=any(
            any(v and r for v, r in zip(d["verified"], d["robust_safe"], strict=True)) for d in window
        ),
        hardest_decel=round(max(decel), 2) if decel else None,
    )
    return row


def _into_follower(decision: dict[str, Any], partner: int) -> bool:
    """The ego changed lane at ``decision`` with ``partner`` behind it in the target lane."""
    if decision["executed"] not in (LANE_LEFT, LANE_RIGHT):
        return False
    snap = decision["snap"]
    target = decision["lane"] + (-1 if decision["executed"] == LANE_LEFT else 1)
    behind = snap.position[partner, 0] < snap.position[snap.ego, 0]
    return bool(int(snap.lane[partner]) == target and behind)


def table(rows: list[dict[str, Any]]) -> str:
    """The trace as a Markdown table: crashes per class, and the braking columns."""
    traced = [r for r in rows if r.get("trace")]
    lines = [
        f"{len(rows)} crashes replayed, {len(traced)} others at fault "
        f"({dict(Counter(r['context'] for r in rows))}).",
        "",
        "| what the ego did in the window | crashes | braking not required by the sets | SLOWER safe by the "
        "one-decision rule | a verified action the one-decision rule calls safe existed | hardest deceleration, "
        "median [m/s²] |",
        "|---|---|---|---|---|---|",
    ]
    for name in CLASSES:
        rs = [r for r in traced if r["trace"] == name]
        if not rs:
            continue
        decels = sorted(r["hardest_decel"] for r in rs if r["hardest_decel"] is not None)
        median = f"{decels[len(decels) // 2]:.2f}" if decels else "–"
        braked = [r for r in rs if r["braking_decisions"]]
        lines.append(
            f"| {name} | {len(rs)} | {sum(r['brake_not_required'] for r in braked)} / {len(braked)} | "
            f"{sum(bool(r['slower_robust_safe']) for r in braked)} / {len(braked)} | "
            f"{sum(r['courteous_alternative'] for r in rs)} / {len(rs)} | {median} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", help="a campaign's counterexamples/ folder")
    parser.add_argument("--out", required=True, help="JSON file of the rows; a .md table is written beside it")
    parser.add_argument("--window", type=float, default=3.0, help="[s] the decisions before the crash sorted")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args(argv)
    files = counterexample_files(args.folder, "collision")
    with ProcessPoolExecutor(args.workers) as pool:
        rows = list(pool.map(trace, files, [args.window] * len(files), chunksize=4))
    out = Path(args.out)
    atomic_write_text(out, json.dumps({"window_s": args.window, "rows": rows}, indent=1))
    atomic_write_text(out.with_suffix(".md"), table(rows))
    print(table(rows))


if __name__ == "__main__":
    main()
