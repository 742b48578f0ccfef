"""What a robust mask costs: the numpy reference against the compiled kernel, on the same recorded states.

Plays random-policy episodes under the robust shield (override on) and, in one process, times on every
recorded decision: the numpy ``evaluate``, ``evaluate_compiled`` (from a RoadState), the shield's fast
path (``compute_result``: the state built inside the kernel) and ``road_state``. Then splits a shielded
decision of the fast simulator into simulator (everything below the shield) and shield.

    PYTHONPATH=src python research/shield_cost.py --simulator fast --episodes 3

``--rate P/S`` plays P decisions per second on S Hz physics; ``--compare OPTION[,OPTION…]`` also times the
compiled kernel with those rule options (``Dynamics`` fields, e.g. ``full_horizon``) all off and all on, side
by side on the same states (interleaved, so the machine's noise hits both alike).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from safelane.env.factory import make_env
from safelane.safety.one_decision.compiled import evaluate_compiled
from safelane.safety.one_decision.reference import evaluate
from safelane.safety.shield import SafetyShield, road_state


def best_of(fn: Callable[[], Any], reps: int) -> float:
    """Smallest of ``reps`` timings [µs] of ``fn()`` (the machine may be shared: the minimum is the cost)."""
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times) * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--simulator", default="fast", choices=["fast", "highway-env"])
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--reps", type=int, default=20)
    parser.add_argument("--rate", default=None, help="P/S: P decisions per second on S Hz physics.")
    parser.add_argument(
        "--compare", default=None, help="Rule options (Dynamics fields, comma-separated) to time all off and all on."
    )
    args = parser.parse_args()

    sets: dict[str, Any] = {"shield.mode": "robust", "shield.override": True}
    if args.rate:
        policy_hz, sim_hz = (int(v) for v in args.rate.split("/"))
        sets.update({"env.policy_frequency": policy_hz, "env.simulation_frequency": sim_hz})
    env = make_env(args.preset, simulator=args.simulator, **sets)
    assert isinstance(env, SafetyShield)
    rng = np.random.default_rng(0)
    rows: dict[str, list[float]] = {k: [] for k in ("numpy", "compiled", "shield", "road_state", "sim", "step")}
    n_near = []
    recorded = []
    for episode in range(args.episodes):
        _, info = env.reset(seed=episode)
        done = False
        while not done:
            snap = info["snapshot"]
            state, dyn = env.state_and_dynamics(snap)
            n_near.append(state.n)
            recorded.append((state, dyn))
            # (the lambdas run at once, inside the loop: binding the loop variables late is what is meant)
            rows["numpy"].append(best_of(lambda: evaluate(state, dyn, "robust"), max(2, args.reps // 10)))  # noqa: B023
            rows["compiled"].append(best_of(lambda: evaluate_compiled(state, dyn, "robust"), args.reps))  # noqa: B023
            rows["shield"].append(best_of(lambda: env.compute_result(snap), args.reps))  # noqa: B023
            rows["road_state"].append(best_of(lambda: road_state(snap), args.reps))  # noqa: B023
            # One shielded decision, and the part of it below the shield (simulator, reward, observation).
            action = int(rng.integers(5))
            inner = env.env.step
            spent = [0.0]

            def timed_inner(a: int, inner: Callable = inner, spent: list = spent) -> Any:
                t0 = time.perf_counter()
                out = inner(a)
                spent[0] = time.perf_counter() - t0
                return out

            env.env.step = timed_inner  # type: ignore[method-assign]
            t0 = time.perf_counter()
            _, _, terminated, truncated, info = env.step(action)
            rows["step"].append((time.perf_counter() - t0) * 1e6)
            del env.env.step
            rows["sim"].append(spent[0] * 1e6)
            done = terminated or truncated
    if args.compare:
        for flag in (False, True):
            rows[f"{args.compare}={flag}"] = []
        for state, dyn in recorded:
            for flag in (False, True):
                variant = dyn.with_options(**dict.fromkeys(args.compare.split(","), flag))
                evaluate_compiled(state, variant, "robust")  # compile / warm up outside the timing
                rows[f"{args.compare}={flag}"].append(
                    best_of(lambda: evaluate_compiled(state, variant, "robust"), args.reps)  # noqa: B023
                )
    med = {k: float(np.median(v)) for k, v in rows.items()}
    print(f"{args.preset}/{args.simulator}: {len(n_near)} states, median {np.median(n_near):.0f} vehicles in range")
    print(f"robust mask, numpy evaluate      : {med['numpy']:9.1f} µs")
    print(f"robust mask, evaluate_compiled   : {med['compiled']:9.1f} µs  ({med['numpy'] / med['compiled']:.0f}x)")
    print(f"robust mask, shield fast path    : {med['shield']:9.1f} µs  (state built in the kernel)")
    print(f"road_state (numpy path only)     : {med['road_state']:9.1f} µs")
    shield_part = med["step"] - med["sim"]
    print(
        f"shielded decision {med['step']:.1f} µs = below the shield {med['sim']:.1f} µs + shield {shield_part:.1f} µs "
        f"({100 * shield_part / med['step']:.0f} %)"
    )
    if args.compare:
        off, on = med[f"{args.compare}=False"], med[f"{args.compare}=True"]
        print(f"compiled mask, {args.compare} off / on : {off:9.1f} / {on:.1f} µs (x{on / off:.2f})")


if __name__ == "__main__":
    main()
