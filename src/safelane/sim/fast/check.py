"""Alignment check: step :class:`FastHighwayEnv` and stock highway-env side by side and compare every vehicle.

``compare_episode(config, env_id, seed, actions)`` resets both with ``seed``, compares the scene, then
after every decision compares each vehicle's position, speed, heading, target speed, IDM DELTA and MOBIL
timer (tolerance ``tol``, in m, m/s, rad, s), lane, target lane and crashed flag, the ego's speed index,
``info["speed"]`` and the terminated / truncated flags. It returns an :class:`Alignment` holding the
first divergent step (``None``: the whole episode matched) and why, plus the largest difference seen and
whether everything matched bit for bit.

A ``ContinuousAction`` ego takes array actions (handed to both simulators as they are); the ego then has
no target speed (NaN) nor speed index (-1). ``snapshots=True`` also requires both simulators'
``info["snapshot"]`` to be equal to the bit (:func:`snapshot_difference`).

Command line (the future ``safelane sim check``): ``python -m safelane.sim.fast.check --preset all
--seeds 0:5`` plays :data:`POLICIES` on both presets and exits 1 if any episode diverged; ``--continuous``
plays :data:`CONTINUOUS_POLICIES` with a ``ContinuousAction`` ego, snapshots compared.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from safelane.core.drivers import ASSUMED_DRIVER, NO_MIX, DriverMix, parse_driver_mix
from safelane.core.snapshot import RoadSnapshot
from safelane.sim.fast import layout as L
from safelane.sim.fast.env import FastHighwayEnv


@dataclass
class Alignment:
    seed: int
    steps: int
    """Decisions compared (the episode ends at the oracle's termination / truncation or the actions' end)."""
    divergent_step: int | None
    """First decision after which the two differ (0: the reset scene); None: none did."""
    cause: str | None
    max_abs_error: float
    """Largest |difference| of a continuous field over the compared steps."""
    bitwise: bool
    """Every continuous field was bit-identical at every compared step."""

    @property
    def matched(self) -> bool:
        return self.divergent_step is None


def make_oracle(
    config: dict[str, Any],
    env_id: str,
    vehicles_behind: int = 0,
    snapshots: bool = False,
    driver_mix: DriverMix | None = None,
) -> Any:
    """Stock highway-env, as the project makes it: ``gym.make(env_id, config=config)``; with
    ``vehicles_behind`` > 0 or a ``driver_mix`` wrapped in :class:`safelane.sim.traffic.TrafficLayout`
    (highway-env's own neighbour search kept), which moves that many vehicles behind the ego at reset and draws
    each other car's driver type from the mixture; with ``snapshots`` in
    :class:`safelane.sim.highway.HighwayEnvAdapter` (``info["snapshot"]``, read from highway-env's objects)."""
    import gymnasium as gym
    import highway_env  # noqa: F401  (registers the envs)

    env = gym.make(env_id, config=config)
    if vehicles_behind or driver_mix is not None:
        from safelane.sim.traffic import TrafficLayout

        env = TrafficLayout(env, vehicles_behind, vectorized=False, driver_mix=driver_mix)
    if snapshots:
        from safelane.sim.highway import HighwayEnvAdapter

        env = HighwayEnvAdapter(env)
    return env


def oracle_state(env: Any) -> dict[str, np.ndarray]:
    """The same fields as :meth:`FastHighwayEnv.state` read from highway-env's ``road.vehicles``."""
    base = env.unwrapped
    vs = base.road.vehicles
    ego = base.vehicle
    return {
        "x": np.array([float(v.position[0]) for v in vs]),
        "y": np.array([float(v.position[1]) for v in vs]),
        "heading": np.array([float(v.heading) for v in vs]),
        "speed": np.array([float(v.speed) for v in vs]),
        # a ContinuousAction ego (a plain Vehicle) has no set-point, target lane or speed index
        "target_speed": np.array([float(getattr(v, "target_speed", np.nan)) for v in vs]),
        "lane": np.array([int(v.lane_index[2]) for v in vs]),
        "target_lane": np.array([int(getattr(v, "target_lane_index", v.lane_index)[2]) for v in vs]),
        "crashed": np.array([bool(v.crashed) for v in vs]),
        "speed_index": np.array([int(getattr(ego, "speed_index", -1))]),
        "is_ego_first": np.array([vs[0] is ego]),
        "delta": np.array([float(getattr(v, "DELTA", np.nan)) for v in vs[1:]]),
        "timer": np.array([float(getattr(v, "timer", np.nan)) for v in vs[1:]]),
        "driver_type": np.array([int(getattr(v, "driver_type", -1)) for v in vs]),
    }


_CONT = ("x", "y", "heading", "speed", "target_speed")
_DISC = ("lane", "target_lane", "crashed", "speed_index", "driver_type")


def compare_states(fast: dict[str, np.ndarray], ref: dict[str, np.ndarray], tol: float, full: bool = False):
    """(cause or None, max abs error, bitwise) comparing two state dicts (NaN equals NaN: a field a body
    does not have)."""
    if not ref["is_ego_first"][0]:
        return "highway-env's ego is not road.vehicles[0]", np.inf, False
    if fast["x"].shape != ref["x"].shape:
        return f"vehicle count {fast['x'].shape[0]} != {ref['x'].shape[0]}", np.inf, False
    fields = _CONT + (("delta", "timer") if full else ())
    err = 0.0
    bitwise = True
    cause = None
    for f in fields:
        a = fast[f][1:] if f in ("delta", "timer") else fast[f]
        b = ref[f]
        d = np.abs(a - b)
        d[np.isnan(a) & np.isnan(b)] = 0.0
        d[np.isnan(d)] = np.inf  # NaN on one side only
        if d.size:
            e = float(np.max(d))
            err = max(err, e)
            if not np.array_equal(a, b, equal_nan=True):
                bitwise = False
            if cause is None and e > tol:
                i = int(np.argmax(d))
                cause = f"{f} of vehicle {i + (1 if f in ('delta', 'timer') else 0)}: {a[i]!r} vs {b[i]!r}"
    for f in _DISC:
        a, b = fast[f], ref[f]
        if cause is None and not np.array_equal(a, b):
            i = int(np.flatnonzero(a != b)[0])
            cause = f"{f} of vehicle {i}: {a[i]!r} vs {b[i]!r}"
    return cause, err, bitwise


def compare_episode(
    config: dict[str, Any],
    env_id: str,
    seed: int,
    actions: Sequence[int],
    tol: float = 1e-6,
    oracle: Any = None,
    fast: FastHighwayEnv | None = None,
    stop_at_end: bool = True,
    vehicles_behind: int = 0,
    snapshots: bool = False,
    driver_mix: DriverMix | None = None,
) -> Alignment:
    """Run ``actions`` from ``reset(seed=seed)`` in both simulators and report the first divergence.

    ``actions``: meta-actions (ints), or continuous actions (arrays or lists, handed to both simulators as
    they are: a float32 action maps in float32 on both) when ``config`` has ``action.type: ContinuousAction``.
    ``snapshots``: also require the two ``info["snapshot"]`` to be equal (``RoadSnapshot.__eq__``: every
    field, to the bit) after the reset and every decision (the oracle is then made with ``snapshots``).
    ``oracle`` / ``fast``: envs to reuse (made from ``config`` / ``env_id`` / ``vehicles_behind`` when None).
    ``vehicles_behind``, ``driver_mix``: safelane's ``traffic.vehicles_behind`` and ``traffic.driver_mix`` (see
    :func:`make_oracle`).
    ``stop_at_end``: stop at the oracle's termination / truncation (False: play every action, which
    also checks the crashed ego and the traffic after the episode would have ended).
    """
    oracle = oracle if oracle is not None else make_oracle(config, env_id, vehicles_behind, snapshots, driver_mix)
    fast = fast if fast is not None else FastHighwayEnv(config, env_id, vehicles_behind=vehicles_behind,
                                                        driver_mix=driver_mix)  # fmt: skip
    _, info_o = oracle.reset(seed=seed)
    _, info_f = fast.reset(seed=seed)
    cause, err, bitwise = compare_states(fast.state(), oracle_state(oracle), tol, full=True)
    if cause is None and snapshots:
        cause = snapshot_difference(info_f["snapshot"], info_o["snapshot"])
    if cause is not None:
        return Alignment(seed, 0, 0, "reset: " + cause, err, bitwise)
    max_err = err
    steps = 0
    for t, a in enumerate(actions, start=1):
        action = int(a) if np.ndim(a) == 0 else a
        _, _, term_o, trunc_o, info_o = oracle.step(action)
        _, _, term_f, trunc_f, info_f = fast.step(action)
        steps = t
        cause, err, bw = compare_states(fast.state(), oracle_state(oracle), tol, full=True)
        if cause is None and snapshots:
            cause = snapshot_difference(info_f["snapshot"], info_o["snapshot"])
        max_err = max(max_err, err)
        bitwise = bitwise and bw
        if cause is None and (bool(term_o), bool(trunc_o)) != (term_f, trunc_f):
            cause = f"terminated/truncated {(term_f, trunc_f)} vs {(bool(term_o), bool(trunc_o))}"
        if cause is None and abs(info_f["speed"] - float(info_o["speed"])) > tol:
            cause = "info speed"
        if cause is not None:
            return Alignment(seed, steps, t, cause, max_err, bitwise)
        if stop_at_end and (term_o or trunc_o):
            break
    return Alignment(seed, steps, None, None, max_err, bitwise)


def snapshot_difference(fast: RoadSnapshot, ref: RoadSnapshot) -> str | None:
    """What first differs between two snapshots (``RoadSnapshot.__eq__``'s test), None when they are equal."""
    name = fast.first_difference(ref)
    if name is None:
        return None
    return f"snapshot {name}: {getattr(fast, name)!r} vs {getattr(ref, name)!r}"


def random_actions(seed: int, n: int = 40) -> list[int]:
    """Uniform random meta-actions (reproducible from ``seed``)."""
    return [int(a) for a in np.random.default_rng(10_000 + seed).integers(0, 5, size=n)]


POLICIES = ("random", "faster", "idle", "slower", "weave", "cautious")


def policy_actions(policy: str, seed: int, n: int = 40) -> list[int]:
    """Action sequences for the checks: ``random``; always ``faster``; always ``idle``; ``slower``
    (SLOWER to a standstill, then IDLE); ``weave`` (LEFT, IDLE, RIGHT, IDLE ...); ``cautious`` (random,
    mostly IDLE / SLOWER)."""
    rng = np.random.default_rng(20_000 + seed)
    if policy == "random":
        return random_actions(seed, n)
    if policy == "faster":
        return [3] * n
    if policy == "idle":
        return [1] * n
    if policy == "slower":
        return [4] * 8 + [1] * (n - 8)
    if policy == "weave":
        return [(0, 1, 2, 1)[i % 4] for i in range(n)]
    if policy == "cautious":
        return [int(a) for a in rng.choice(5, size=n, p=[0.1, 0.45, 0.1, 0.1, 0.25])]
    raise ValueError(f"policy: {policy!r} is not supported; allowed: {', '.join(POLICIES)}")


CONTINUOUS_POLICIES = ("uniform", "throttle", "brake")


def continuous_actions(policy: str, seed: int, n: int = 40) -> list[np.ndarray]:
    """``ContinuousAction`` sequences (float32, as gymnasium's Box gives them): ``uniform`` (uniform in [-1, 1]²,
    reproducible from ``seed``); ``throttle`` (full throttle, no steering: the heading stays 0, the lane is
    kept); ``brake`` (a third of full braking, no steering, to a standstill and backwards)."""
    if policy == "uniform":
        rng = np.random.default_rng(30_000 + seed)
        return [rng.uniform(-1.0, 1.0, 2).astype(np.float32) for _ in range(n)]
    held = {"throttle": [1.0, 0.0], "brake": [-1 / 3, 0.0]}
    if policy not in held:
        raise ValueError(f"policy: {policy!r} is not supported; allowed: {', '.join(CONTINUOUS_POLICIES)}")
    return [np.array(held[policy], dtype=np.float32) for _ in range(n)]


__all__ = [
    "CONTINUOUS_POLICIES",
    "POLICIES",
    "Alignment",
    "compare_episode",
    "compare_states",
    "continuous_actions",
    "make_oracle",
    "oracle_state",
    "policy_actions",
    "random_actions",
    "snapshot_difference",
]


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m safelane.sim.fast.check [--preset fast|paper|hidden-types|all] [--seeds 0:10] [--policies ...]
    [--continuous]``

    Compares whole episodes against stock highway-env and prints one line per episode and a summary;
    exit status 1 if any episode diverged. ``--continuous``: the ego under ``ContinuousAction`` instead,
    driven by :data:`CONTINUOUS_POLICIES`, the snapshots compared too.
    """
    import argparse
    import json
    from importlib import resources
    from pathlib import Path

    import yaml

    ap = argparse.ArgumentParser(prog="python -m safelane.sim.fast.check")
    ap.add_argument("--preset", default="all", help="fast, paper, hidden-types or all")
    ap.add_argument("--seeds", default="0:5", help="start:stop")
    ap.add_argument("--policies", default=None, help="default: every policy of the action kind")
    ap.add_argument("--continuous", action="store_true", help="a ContinuousAction ego (default: meta-actions)")
    ap.add_argument("--decisions", type=int, default=40)
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--stop-at-end", action="store_true", help="stop at termination (default: play on)")
    args = ap.parse_args(argv)
    presets = ("fast", "paper", "hidden-types") if args.preset == "all" else (args.preset,)
    a, b = (int(v) for v in args.seeds.split(":"))
    total = matched = bitwise = 0
    policies = args.policies.split(",") if args.policies else (CONTINUOUS_POLICIES if args.continuous else POLICIES)
    for name in presets:
        data = yaml.safe_load((Path(str(resources.files("safelane"))) / "presets" / f"{name}.yaml").read_text())
        cfg, env_id = data["env"], data["env_id"]
        traffic = data.get("traffic", {})
        hidden = traffic.get("assumed_driver", ASSUMED_DRIVER) if not traffic.get("shield_sees_types") else None
        mix = parse_driver_mix(traffic.get("driver_mix", NO_MIX), assumed=hidden)
        if args.continuous:
            cfg = {**cfg, "action": {"type": "ContinuousAction"}}
        oracle = make_oracle(cfg, env_id, snapshots=args.continuous, driver_mix=mix)
        fast = FastHighwayEnv(cfg, env_id, driver_mix=mix)
        for seed in range(a, b):
            for policy in policies:
                actions = (continuous_actions if args.continuous else policy_actions)(policy, seed, args.decisions)
                r = compare_episode(
                    cfg, env_id, seed, actions, args.tol, oracle, fast, stop_at_end=args.stop_at_end,
                    snapshots=args.continuous,
                )  # fmt: skip
                total += 1
                matched += r.matched
                bitwise += r.matched and r.bitwise
                row = {"preset": name, "seed": seed, "policy": policy, "steps": r.steps}
                row.update(divergent_step=r.divergent_step, cause=r.cause, max_abs_error=r.max_abs_error)
                row.update(bitwise=r.bitwise, ego_crashed=bool(fast.G[0, L.CRASHED]))
                print(json.dumps(row), flush=True)
    print(f"{matched}/{total} episodes matched within {args.tol}, {bitwise}/{total} bit for bit")
    return 0 if matched == total else 1


if __name__ == "__main__":
    raise SystemExit(main())
