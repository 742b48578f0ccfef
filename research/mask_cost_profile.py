"""Where the robust mask's time goes: its cost per recorded state, the tail, and what the tail is made of.

Plays random-policy episodes (the policy of ``safelane bench``) on the fast simulator under the robust shield of
the current rule, on the bench's traffic and on dense traffic, records every decision's state, and then times on
each state (best of ``--reps``, the variants interleaved state by state so the machine's noise hits all alike):

* ``kernel``: the shield's compiled kernel as the shield and the batch call it (``snapshot_kernel``: the state
  built inside it), with its arguments prepared outside the timing;
* ``no_forecast``: the same with the rule's ``forecast_fallback`` off (``Rule.with_options``; it changes the
  fallback's choice only), which prices the forecast;
* ``main``, ``straight``, ``straight_forecast``: the rule's kernel (``compiled_rule.evaluate_rule``) on the
  state's ``RoadState``, once per pass: the main pass (turning leaders), the straight fallback's pass without and
  with the forecast. A state whose main pass finds no safe action (a *fallback state*) runs the main pass and
  then the straight one; the forecast runs when the straight pass finds none either.

It prints, per traffic: mean, median, p90, p99, max [µs] and the share of the total time taken by the slowest
1 % and 10 % of states; the same split by kind of state (safe; fallback, straight pass safe; fallback with the
forecast) and by the number of cars in range; and the passes' mean cost per kind.

    PYTHONPATH=src python research/mask_cost_profile.py --episodes 40 --json /tmp/profile.json
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from safelane.env.factory import make_env
from safelane.running.policies import fixed_policy
from safelane.safety.one_decision import reference as model
from safelane.safety.one_decision.compiled import C_RELEVANCE, C_TURNING_ALLOWANCE, kernel_constants, snapshot_kernel
from safelane.safety.one_decision.compiled_rule import evaluate_rule
from safelane.safety.one_decision.cut_ins import politeness_of
from safelane.safety.rule import FLAG_TURNING_IN_NOMINAL
from safelane.safety.shield import SafetyShield

TRAFFIC = {"bench": {}, "dense": {"env.vehicles_density": 2.0}}
"""The traffics profiled: the bench's (the ``fast`` preset as it is) and dense traffic (density 2)."""
KINDS = ("safe", "fallback", "forecast")
"""Kinds of state: a safe action exists; none in the main pass but one in the straight pass; none in either
(the forecast ranks the least-bad choice)."""
CAR_BINS = ((0, 2), (3, 5), (6, 8), (9, 12), (13, 1000))
"""Bins of the number of cars within the rule's range of the ego (inclusive)."""


def best_of(fn: Callable[[], Any], reps: int) -> float:
    """Smallest of ``reps`` timings [µs] of ``fn()`` (on a shared machine the minimum is the cost)."""
    best = math.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e6


def kernel_args(snap: Any, dyn: Any, lane_heading: float, leave: float) -> tuple:
    """The arguments of ``snapshot_kernel`` for ``snap`` (as ``compiled.evaluate_snapshot`` passes them)."""
    e = snap.ego
    return (
        snap.position, snap.speed, snap.heading, snap.length, snap.crashed, snap.brake_max, snap.accel_max,
        snap.can_change_lane, snap.idm_delta, snap.idm_comfort_acc, snap.idm_comfort_dec,
        snap.idm_distance_wanted, snap.idm_time_wanted, snap.max_braking_imposed, snap.linear_speed_gain,
        snap.linear_speed_difference_gain, snap.linear_distance_gain, snap.politeness, snap.target_speed,
        e, int(snap.lane[e]), int(snap.target_lane[e]), snap.ego_target_speed, snap.ego_speed_index,
        snap.lane_origin, snap.lane_direction, snap.lane_lateral, lane_heading, snap.speed_limit,
        *kernel_constants(dyn), True, leave,
    )  # fmt: skip


def rule_args(state: Any, dyn: Any, robust: bool = True) -> tuple:
    """The arguments of ``evaluate_rule`` for a ``RoadState`` but the pass's last three."""
    s = state
    return (
        s.ego_x, s.ego_speed, s.ego_lane, s.ego_target_lane, s.ego_target_speed, s.ego_speed_index,
        s.ego_length, s.speed_limit, s.x, s.y, s.vx, s.vy, s.heading, s.length, s.crashed, s.brake_max,
        s.accel_max, s.can_change_lane, s.idm_delta, s.idm_comfort_acc, s.idm_comfort_dec,
        s.idm_distance_wanted, s.idm_time_wanted, s.max_braking_imposed, s.linear_speed_gain,
        s.linear_speed_difference_gain, s.linear_distance_gain, politeness_of(s), model.set_points(s),
        *kernel_constants(dyn), robust, dyn.ego_leave_time,
    )  # fmt: skip


def record(sets: dict[str, Any], episodes: int, seed: int) -> list[dict[str, Any]]:
    """Every decision's state of ``episodes`` random-policy episodes (seeds ``seed``, ``seed + 1``, ...) on the
    fast simulator under the robust shield (no override, as the bench): the kernel's and the passes' arguments,
    the kind of state, the cars in range and the pool the fallback ranks."""
    env = make_env("fast", simulator="fast", **{"shield.mode": "robust", **sets})
    assert isinstance(env, SafetyShield)
    states: list[dict[str, Any]] = []
    for episode in range(episodes):
        policy = fixed_policy("random", seed + episode)
        obs, info = env.reset(seed=seed + episode)
        done = False
        while not done:
            snap = info["snapshot"]
            state, dyn = env.state_and_dynamics(snap)
            base = env.dynamics
            assert base is not None
            direction = snap.lane_direction
            args = kernel_args(snap, base, math.atan2(direction[1], direction[0]), dyn.ego_leave_time)
            quiet = kernel_args(
                snap, base.with_options(forecast_fallback=False), math.atan2(direction[1], direction[0]),
                dyn.ego_leave_time,
            )  # fmt: skip
            rargs = rule_args(state, dyn)
            consts = kernel_constants(dyn)
            allowance = float(consts.consts[C_TURNING_ALLOWANCE])
            nominal_allowance = allowance if consts.flags & FLAG_TURNING_IN_NOMINAL else 0.0
            main = evaluate_rule(*rargs, allowance, 0.0, False)
            straight = evaluate_rule(*rargs, 0.0, nominal_allowance, True)
            nominal = evaluate_rule(*rule_args(state, dyn, robust=False), 0.0, nominal_allowance, False)
            kind = "safe" if not main[4] else ("fallback" if not straight[4] else "forecast")
            pool = int(nominal[1].sum()) if nominal[1].any() else int(nominal[2].sum())
            relevance = float(consts.consts[C_RELEVANCE])
            cars = int(np.sum((np.abs(state.x - state.ego_x) < relevance) & np.isfinite(state.x)))
            out = snapshot_kernel(*args)
            assert bool(out[4]) == bool(main[4])
            states.append(
                {
                    "args": args, "quiet": quiet, "rargs": rargs, "allowance": allowance,
                    "nominal_allowance": nominal_allowance, "kind": kind, "pool": pool, "cars": cars,
                }
            )  # fmt: skip
            obs, _, terminated, truncated, info = env.step(policy(obs, info))
            done = terminated or truncated
    env.close()
    return states


def time_states(states: list[dict[str, Any]], reps: int) -> dict[str, np.ndarray]:
    """Per state: the best-of-``reps`` cost [µs] of each variant (module docstring), interleaved."""
    rows: dict[str, list[float]] = {k: [] for k in ("kernel", "no_forecast", "main", "straight", "straight_forecast")}
    for s in states:
        a, q, r = s["args"], s["quiet"], s["rargs"]
        al, nal = s["allowance"], s["nominal_allowance"]
        calls = {
            "kernel": lambda: snapshot_kernel(*a),  # noqa: B023 (called at once, inside the loop)
            "no_forecast": lambda: snapshot_kernel(*q),  # noqa: B023
            "main": lambda: evaluate_rule(*r, al, 0.0, False),  # noqa: B023
            "straight": lambda: evaluate_rule(*r, 0.0, nal, False),  # noqa: B023
            "straight_forecast": lambda: evaluate_rule(*r, 0.0, nal, True),  # noqa: B023
        }
        for fn in calls.values():
            fn()  # warm (and compile on the first state)
        for _ in range(reps):  # round-robin: each variant once per round, keep each one's best
            for name, fn in calls.items():
                rows[name].append(best_of(fn, 1))
    n = len(states)
    return {k: np.asarray(v).reshape(n, reps).min(axis=1) for k, v in rows.items()}


def summary(us: np.ndarray) -> dict[str, float]:
    """mean, median, p90, p99, max [µs], and the share of the total taken by the slowest 1 % and 10 %."""
    if us.size == 0:
        return {"n": 0}
    ordered = np.sort(us)[::-1]
    total = float(ordered.sum())
    top1 = max(1, math.ceil(0.01 * us.size))
    top10 = max(1, math.ceil(0.10 * us.size))
    return {
        "n": int(us.size),
        "mean": float(us.mean()),
        "median": float(np.median(us)),
        "p90": float(np.percentile(us, 90)),
        "p99": float(np.percentile(us, 99)),
        "max": float(us.max()),
        "share_top1": float(ordered[:top1].sum() / total),
        "share_top10": float(ordered[:top10].sum() / total),
        "share_of_total": total,
    }


def profile(states: list[dict[str, Any]], times: dict[str, np.ndarray]) -> dict[str, Any]:
    """The figures of one traffic (module docstring)."""
    kernel = times["kernel"]
    total = float(kernel.sum())
    kinds = np.array([s["kind"] for s in states])
    cars = np.array([s["cars"] for s in states])
    pools = np.array([s["pool"] for s in states])
    out: dict[str, Any] = {"all": summary(kernel), "by_kind": {}, "by_cars": {}, "passes_mean_us": {}}
    for kind in KINDS:
        sel = kinds == kind
        fig = summary(kernel[sel])
        if sel.any():
            fig["share_of_total"] = float(kernel[sel].sum() / total)
            fig["share_of_states"] = float(sel.mean())
            out["passes_mean_us"][kind] = {k: float(v[sel].mean()) for k, v in times.items()}
        out["by_kind"][kind] = fig
    for lo, hi in CAR_BINS:
        sel = (cars >= lo) & (cars <= hi)
        fig = summary(kernel[sel])
        if sel.any():
            fig["share_of_total"] = float(kernel[sel].sum() / total)
        out["by_cars"][f"{lo}-{hi}"] = fig
    slowest = np.argsort(kernel)[::-1][: max(1, math.ceil(0.01 * kernel.size))]
    out["slowest_1pct_kinds"] = {k: int(np.sum(kinds[slowest] == k)) for k in KINDS}
    forecast = kinds == "forecast"
    out["forecast_states_pool"] = {str(p): int(np.sum(pools[forecast] == p)) for p in sorted(set(pools[forecast]))}
    out["forecast_price_mean_us"] = float((kernel - times["no_forecast"]).mean())
    return out


def show(name: str, fig: dict[str, Any]) -> None:
    def line(label: str, f: dict[str, float]) -> str:
        if f.get("n", 0) == 0:
            return f"  {label:<22} (none)"
        share = f" | {100 * f['share_of_total']:5.1f} % of time" if "share_of_states" in f or label[0].isdigit() else ""
        states = f" | {100 * f['share_of_states']:5.1f} % of states" if "share_of_states" in f else ""
        return (
            f"  {label:<22} n={f['n']:5d} mean {f['mean']:7.1f} median {f['median']:7.1f} p90 {f['p90']:7.1f} "
            f"p99 {f['p99']:7.1f} max {f['max']:7.1f}{share}{states}"
        )

    a = fig["all"]
    print(f"{name}: {a['n']} states")
    print(line("all", a))
    print(f"  slowest 1 % of states: {100 * a['share_top1']:.1f} % of the time; slowest 10 %: "
          f"{100 * a['share_top10']:.1f} %; kinds among the slowest 1 %: {fig['slowest_1pct_kinds']}")  # fmt: skip
    for kind, f in fig["by_kind"].items():
        print(line(kind, f))
    for label, f in fig["by_cars"].items():
        print(line(f"{label} cars", f))
    for kind, p in fig["passes_mean_us"].items():
        print(f"  mean µs, {kind:<9}: " + ", ".join(f"{k} {v:.1f}" for k, v in p.items()))
    print(f"  forecast's price (kernel − no_forecast), mean over all states: {fig['forecast_price_mean_us']:.1f} µs")
    print(f"  forecast states by the size of the pool it ranks: {fig['forecast_states_pool']}")


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=40, help="Random-policy episodes per traffic.")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--reps", type=int, default=5, help="Timings per state and variant (the best is kept).")
    parser.add_argument("--traffic", default="bench,dense", help="Comma-separated: bench, dense.")
    parser.add_argument("--json", default=None, help="Also write the figures to this JSON file.")
    args = parser.parse_args(argv)
    figures: dict[str, Any] = {}
    for name in args.traffic.split(","):
        if name not in TRAFFIC:
            raise SystemExit(f"--traffic: got {name!r}; allowed: {', '.join(TRAFFIC)}")
        states = record(TRAFFIC[name], args.episodes, args.seed)
        figures[name] = profile(states, time_states(states, args.reps))
        show(name, figures[name])
    if args.json:
        with open(args.json, "w") as f:
            json.dump(figures, f, indent=1)
    return figures


if __name__ == "__main__":
    main()
