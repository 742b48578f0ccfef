"""The committed shield's gate: play a campaign spec's cells under ``shield.mode: committed`` and count what
``safelane falsify`` does not count yet — lapses (the cars each kept plan fails on, and whether they left their sets),
plan-forced decisions, uncertified starts, collisions by context, car-decisions outside the sets drawn for them
(those rolling back, the unbraked followers and crashed cars apart) — beside collisions and mean speed.

    python research/committed_gate.py research/committed_subset.yaml --out runs/committed/subset.json

Episodes and seeds are the campaign's (cell ``i``, episode ``k``: ``FALSIFY_SEED_BASE + 10 000·i + k``), the policy
the cell's, override on. ``--match TEXT`` (repeatable) plays only the cells whose axis labels contain every TEXT.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from safelane.running.collisions import classify_collision, collision_partner
from safelane.running.conditions import traffic_seed_base
from safelane.running.falsify.grid import CELL_SEED_STRIDE, FALSIFY_SEED_BASE, load_campaign_spec

CONTEXTS = ("from_certified", "after_lapse", "uncertified")


def play_episode(env: Any, policy: Any, seed: int) -> dict[str, Any]:
    """One episode under the committed shield: its decisions, speed, lapses and collision context."""
    obs, info = env.reset(seed=seed)
    record: dict[str, Any] = {
        "seed": seed, "uncertified_start": bool(info["uncertified_start"]), "decisions": 0, "speeds": [],
        "plan_forced": 0, "fallback": 0, "lapses": [], "collision": None, "escapes": 0, "rolled_back": 0,
        "unbraked_followers": 0, "crashed_escapes": 0,
        "checked": 0,
    }  # fmt: skip
    done = False
    lapsed = False
    escaped_seen: set[int] = set()
    entered_seen: set[int] = set()
    while not done:
        before = env.get_wrapper_attr("result")
        action = int(policy(obs, info))
        obs, _, terminated, truncated, info = env.step(action)
        done = terminated or truncated
        record["decisions"] += 1
        record["speeds"].append(float(info["speed"]))
        record["plan_forced"] += bool(info["plan_forced"])
        record["fallback"] += bool(info["fallback"])
        record["escapes"] += len(info["escaped_cars"])
        after = env.get_wrapper_attr("result")  # the committed verdict: cars checked, escapes rolling back
        record["checked"] += int(getattr(after, "checked", 0))
        record["rolled_back"] += len(info["rolled_back"])
        record["unbraked_followers"] += len(info["unbraked_followers"])
        crashed = info["snapshot"].crashed  # escapes of crashed cars: highway-env stops them beyond ACC_MAX
        record["crashed_escapes"] += sum(bool(crashed[v]) for v in info["escaped_cars"])
        escaped_seen.update(info["escaped_cars"])
        entered_seen.update(info["entered_cars"])
        if info["lapse"]:
            lapsed = True
            # The cars the kept plan fails on, and of them those outside their sets or entering a held lane;
            # the cars outside their sets anywhere on the road apart.
            cars = list(info["lapse_cars"])
            record["lapses"].append({"decision": record["decisions"], "cars": cars,
                                     "escaped": list(info["lapse_escaped_cars"]),
                                     "entered": [v for v in cars if v in info["entered_cars"]],
                                     "escaped_anywhere": list(info["escaped_cars"]),
                                     "entered_anywhere": list(info["entered_cars"]),
                                     "in_model": bool(info["lapse_in_model"])})  # fmt: skip
        if info.get("collision", False) and record["collision"] is None:
            executed = int(info["executed_action"])
            verified = bool(before is not None and before.safe[executed])
            context = "from_certified" if verified else ("after_lapse" if lapsed else "uncertified")
            snap = info["snapshot"]
            partner = collision_partner(snap)
            kind = classify_collision(snap)
            record["collision"] = {
                "decision": record["decisions"], "context": context, "kind": kind, "partner": partner,
                "lapsed_before": lapsed, "partner_left_its_set": partner in escaped_seen,
                "partner_entered_held_lane": partner in entered_seen,
                "others_at_fault": kind == "rear_ended" or partner in entered_seen,
            }  # fmt: skip
    speeds = record.pop("speeds")
    record["mean_speed"] = float(np.mean(speeds)) if speeds else 0.0
    return record


def main(argv: list[str] | None = None) -> int:
    from safelane.env.factory import make_env
    from safelane.running.falsify.grid import cell_config
    from safelane.running.policies import fixed_policy

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("spec")
    parser.add_argument("--match", action="append", default=[])
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    spec = load_campaign_spec(args.spec)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cells = [c for c in spec.cells() if all(m in ",".join(c["labels"].values()) for m in args.match)]
    played = []
    start = time.perf_counter()
    for cell in cells:
        cfg = cell_config(spec, cell).model_copy(deep=True)
        seed = traffic_seed_base(FALSIFY_SEED_BASE, spec.seed) + CELL_SEED_STRIDE * cell["index"]
        env = make_env(cfg)
        policy = fixed_policy(cell["policy"], seed)
        episodes = [play_episode(env, policy, seed + k) for k in range(spec.episodes)]
        env.close()
        played.append({"index": cell["index"], "policy": cell["policy"], "labels": cell["labels"],
                       "episodes": episodes})  # fmt: skip
        print(
            f"cell {cell['index']} {cell['policy']} {cell['labels']}: "
            f"{sum(e['collision'] is not None for e in episodes)} collisions, "
            f"{sum(len(e['lapses']) for e in episodes)} lapses, {time.perf_counter() - start:.0f} s",
            flush=True,
        )
    summary = summarize(played)
    out.write_text(json.dumps({"spec": args.spec, "match": args.match,
                               "summary": summary, "cells": played}, indent=1))  # fmt: skip
    print(json.dumps(summary, indent=1))
    return 0


def summarize(played: list[dict[str, Any]]) -> dict[str, Any]:
    """The gate's figures over the played cells."""
    episodes = [e for c in played for e in c["episodes"]]
    decisions = sum(e["decisions"] for e in episodes)
    lapses = [lapse for e in episodes for lapse in e["lapses"]]
    crashes = [e["collision"] for e in episodes if e["collision"] is not None]
    faster = [e["mean_speed"] for c in played if c["policy"] == "faster" for e in c["episodes"]]
    by_policy = {}
    for policy in sorted({c["policy"] for c in played}):
        eps = [e for c in played if c["policy"] == policy for e in c["episodes"]]
        by_policy[policy] = {"episodes": len(eps), "mean_speed": float(np.mean([e["mean_speed"] for e in eps])),
                             "collisions": sum(e["collision"] is not None for e in eps)}  # fmt: skip
    return {
        "cells": len(played), "episodes": len(episodes), "decisions": decisions,
        "collisions": len(crashes),
        "collision_contexts": {k: sum(c["context"] == k for c in crashes) for k in CONTEXTS},
        "from_certified_others_at_fault": sum(
            c["context"] == "from_certified" and c["others_at_fault"] for c in crashes
        ),
        "from_certified_partner_left_its_set": sum(
            c["context"] == "from_certified" and c["partner_left_its_set"] for c in crashes
        ),
        "lapses_traced_to_escapes": sum(bool(lapse["escaped"]) for lapse in lapses),
        "lapses_traced_to_cut_ins": sum(bool(lapse["entered"]) and not lapse["escaped"] for lapse in lapses),
        "lapse_cars": sum(len(lapse["cars"]) for lapse in lapses),
        "lapse_cars_escaped_or_entered_anywhere": sum(len({*lapse["escaped_anywhere"], *lapse["entered_anywhere"]})
                                          for lapse in lapses),
        "uncertified_starts": sum(e["uncertified_start"] for e in episodes),
        "lapses": len(lapses), "lapses_in_model": sum(lapse["in_model"] for lapse in lapses),
        "car_decisions": sum(e.get("checked", 0) for e in episodes),
        "escaped_car_decisions": sum(e.get("escapes", 0) for e in episodes),
        "escaped_rolling_back": sum(e.get("rolled_back", 0) for e in episodes),
        "escaped_unbraked_followers": sum(e.get("unbraked_followers", 0) for e in episodes),
        "escaped_crashed": sum(e.get("crashed_escapes", 0) for e in episodes),
        "plan_forced_rate": sum(e["plan_forced"] for e in episodes) / max(decisions, 1),
        "no_verified_action_rate": sum(e["fallback"] for e in episodes) / max(decisions, 1),
        "faster_mean_speed": float(np.mean(faster)) if faster else None, "by_policy": by_policy,
    }  # fmt: skip


if __name__ == "__main__":
    raise SystemExit(main())
