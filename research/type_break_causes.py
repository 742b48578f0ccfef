"""What decides the invariant breaks of a campaign with hidden driver types: the conflict that makes the least-bad
action unsafe at the break, in each reading of the drivers the shield judged.

A break file (``safelane falsify … --out DIR`` writes them under ``DIR/counterexamples/``) is replayed on its
simulator under the numpy reference up to the break; there, in every reading of the drivers (one per type some car
may be; one under ``omniscient``), the action with the largest worst-case gap and the conflict that decided it: a
*leader*, a *follower* whose path ends inside the ego (a bumper gap in (−1, 0) m: a car closing on the ego's
fallback stop, with its IDM desired distance ``d0`` [m centre to centre] printed), a deeper follower overlap, or
none below 0 (only the 1 m margin eaten). ``--own-set-point`` judges the same states again with the IDM follower's
free-road term at the car's own set-point and δ instead of the bound ``v0 = ∞``, and counts the breaks that remain.

    .venv/bin/python research/type_break_causes.py runs/falsify/claim-hidden-types-omniscient-sample --files 100
    .venv/bin/python research/type_break_causes.py runs/falsify/claim-hidden-types-omniscient-sample --files 60 \
        --own-set-point
"""

from __future__ import annotations

import argparse
import collections
import copy
import json
import math
import random
from pathlib import Path
from typing import Any

import numpy as np

import safelane.safety.one_decision.reference as reference
from safelane.config import build_config
from safelane.env.factory import make_env
from safelane.env.scenarios import find_shield
from safelane.running.counterexamples import load_counterexample
from safelane.safety.road import road_state
from safelane.safety.world import NOT_ZERO, Dynamics, RoadState


def follower_with_own_set_point(
    state: RoadState, dyn: Dynamics, i: int, ego_x: np.ndarray, ego_v: np.ndarray
) -> np.ndarray:
    """:func:`safelane.safety.others.idm_follower_positions` with the free-road term ``acc·(1 − (v/v0)^δ)`` at the
    car's own set-point ``v0`` (``state.target_speed``) and δ, not bounded by ``acc``; positions [m], (F, T)."""
    acc = float(state.idm_comfort_acc[i])
    two_sqrt_ab = 2.0 * math.sqrt(-acc * float(state.idm_comfort_dec[i]))
    d0, tw = float(state.idm_distance_wanted[i]), float(state.idm_time_wanted[i])
    a_max, b_max = float(state.accel_max[i]), float(state.brake_max[i])
    v0, delta = max(abs(float(state.target_speed[i])), NOT_ZERO), float(state.idm_delta[i])
    n_f, n_t = ego_x.shape
    out = np.empty((n_f, n_t))
    xf, vf = np.full(n_f, float(state.x[i])), np.full(n_f, float(state.vx[i]))
    out[:, 0] = xf
    for k in range(n_t - 1):
        d = ego_x[:, k] - xf
        d = np.where(np.abs(d) > NOT_ZERO, d, np.where(d >= 0.0, NOT_ZERO, -NOT_ZERO))
        ratio = (d0 + vf * tw + vf * (vf - ego_v[:, k]) / two_sqrt_ab) / d
        a = acc * (1.0 - np.power(np.maximum(vf, 0.0) / v0, delta)) - acc * ratio * ratio
        a = np.maximum(np.minimum(a, a_max), -b_max)
        xf, vf = xf + vf * dyn.frame_dt, vf + a * dyn.frame_dt
        out[:, k + 1] = xf
    r = dyn.follower_reaction
    v = np.maximum(vf, 0.0)
    out[:, -1] += v * r + 0.5 * a_max * r * r + (v + a_max * r) ** 2 / (2.0 * max(b_max, 1e-6))
    return out


def deciding_kinds(shield: Any) -> tuple[str, ...]:
    """The kinds of conflict that decide the least-bad action in each reading of the shield's last snapshot."""
    readings, _ = shield.driver_readings(shield.snapshot)
    _, dyn = shield.state_and_dynamics(shield.snapshot)
    kinds = set()
    for reading in readings:
        state = road_state(reading, dyn.rule.ego_speed_magnitude)
        result = reference.evaluate(state, dyn, "robust")
        best = int(np.argmax(np.where(result.available, result.min_gap, -np.inf)))
        deciding = [c for c in result.conflicts or () if c.action == best]
        if not deciding or result.min_gap[best] >= 0.0:
            continue
        conflict = deciding[0]
        if conflict.ahead:
            kinds.add("leader")
        elif -1.0 < conflict.gap < 0.0:
            kinds.add(f"follower into the stopped ego, d0={state.idm_distance_wanted[conflict.vehicle]:.0f} m")
        else:
            kinds.add("follower, deeper")
    return tuple(sorted(kinds)) or ("only the margin eaten",)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("campaign", type=Path, help="a campaign's --out folder")
    parser.add_argument("--files", type=int, default=100, help="break files drawn at random")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--own-set-point", action="store_true")
    args = parser.parse_args()
    files = sorted((args.campaign / "counterexamples").glob("*invariant_break*.json"))
    picked = random.Random(args.seed).sample(files, min(args.files, len(files)))
    counts: collections.Counter[str] = collections.Counter()
    original = reference.idm_follower_positions
    for path in picked:
        cx = load_counterexample(path)
        data = copy.deepcopy(cx.config)
        data["shield"] = {**data["shield"], "engine": "numpy"}
        env = make_env(build_config(data))
        env.reset(seed=cx.seed)
        for action in cx.actions[: cx.step]:
            env.step(int(action))
        shield = find_shield(env)
        if args.own_set_point:
            reference.idm_follower_positions = follower_with_own_set_point
            try:
                counts["still a break" if shield.compute_result().fallback else "a safe action"] += 1
            finally:
                reference.idm_follower_positions = original
        else:
            counts[" + ".join(deciding_kinds(shield))] += 1
        env.close()
    print(json.dumps({"campaign": str(args.campaign), "files": len(picked), "counts": dict(counts.most_common())}))


if __name__ == "__main__":
    main()
