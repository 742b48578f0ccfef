"""Do the cars stay inside the sets drawn for them? Play episodes, draw every car's reachable set at each decision
from the observable state (:func:`safelane.safety.committed.sets.car_sets`, as the committed shield draws it), then
check each car against it at every physics frame until the next decision (:func:`~safelane.safety.committed.sets.
escaped_cars` on the sets shifted to that frame) and classify every escape.

    python research/set_escape_audit.py --episodes 200 --out docs/results/set-escape-audit/summary.json

One run per driver model (IDM, Linear, Aggressive, Defensive: highway-env's ``other_vehicles_type``) on the
paper's traffic (4 lanes, 50 vehicles, 40 s, 1 decision per second): ``--preset fast`` (default: highway-fast-v0,
5 Hz physics, no collision checks between the other cars) or ``--preset paper`` (highway-v0, 15 Hz, every pair
checked; about 3x slower), ``simulator=highway-env`` unless ``--simulator fast`` (the fast simulator runs a
decision's frames in one call: its cars are checked at the decisions only). The ego: ``--policy`` (default random)
under the robust shield with override, so episodes run their 40 s. Episode ``k`` has seed ``--seed + k``. A *trace*
is one car over one episode.

The tool reads the sets only through ``car_sets``, ``CarSets.shifted`` and ``escaped_cars``: whatever the sets are,
it measures them. It names the component a car left (position, speed, a lane entered early; a component it does
not know is ``other_component``) and the cause (:data:`CLASSES`), with examples (seed, decision, frame, car).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from safelane.core.snapshot import RoadSnapshot
from safelane.safety.committed.sets import CarSets, car_sets, escaped_cars
from safelane.safety.road import whole_road_state  # the committed family's own state: the sets it draws
from safelane.safety.shield import dynamics_of
from safelane.safety.world import LATERAL_MOTION_THRESHOLD, Dynamics, RoadState

try:  # the speed the sets bound, for the figures reported: along the car's path where the sets define it so
    from safelane.safety.committed.sets import path_speed as set_speed
except ImportError:  # sets drawn on the speed along the road

    def set_speed(state: RoadState) -> np.ndarray:
        """[m/s] (cars,) the speed along the road."""
        return state.vx


DRIVERS: dict[str, str] = {
    "IDM": "highway_env.vehicle.behavior.IDMVehicle",
    "Linear": "highway_env.vehicle.behavior.LinearVehicle",
    "Aggressive": "highway_env.vehicle.behavior.AggressiveVehicle",
    "Defensive": "highway_env.vehicle.behavior.DefensiveVehicle",
}
"""The driver models audited, by name: highway-env's ``other_vehicles_type``."""

CLASSES: dict[str, str] = {
    "collision": "the car crashed between the decision and the frame: the impact pushed it",
    "crashed_wall_moves": "a car crashed at the decision (a wall in its set) still moves: highway-env brakes a "
    "crashed car at -speed and pushes it on a further impact",
    "teleport": "more than 20 m outside its position interval: the car was re-spawned or swapped",
    "rolling_back": "rolling back below the set (moving backwards now, or when the set was drawn)",
    "lane_entered_early": "its body overlaps a lane earlier than the set allows",
    "turning_slower": "changing lane (heading off the road in the interval): its speed along the road fell below "
    "the envelope (the heading turns speed away from the road)",
    "turning_faster": "changing lane: its speed along the road rose above the envelope (straightening)",
    "straight_slower": "going straight: below the envelope (braking harder than the bound)",
    "straight_faster": "going straight: above the envelope (accelerating harder than the bound, or above v_max)",
    "other_component": "outside in a component of the set the audit does not name (the sets gained one)",
}
"""Every cause an escape is put under, first match in this order."""
TELEPORT = 20.0  # [m] beyond the position interval: not a drive but a jump
MAX_EXAMPLES = 3


@dataclasses.dataclass
class Tally:
    """What one driver model's episodes counted: car-frames (one car at one physics frame), car-decisions (one car
    over one decision interval), checks at the decisions only (what the shield sees), traces (one car over one
    episode), frames (a physics frame with at least one car outside)."""

    episodes: int = 0
    decisions: int = 0
    car_frames: int = 0
    car_frames_out: int = 0
    frames: int = 0
    frames_out: int = 0
    car_decisions: int = 0
    car_decisions_out: int = 0
    at_decisions: int = 0
    at_decisions_out: int = 0
    traces: int = 0
    traces_out: int = 0
    classes_frames: Counter = dataclasses.field(default_factory=Counter)
    classes_decisions: Counter = dataclasses.field(default_factory=Counter)
    components: Counter = dataclasses.field(default_factory=Counter)
    examples: dict[str, list[dict[str, Any]]] = dataclasses.field(default_factory=dict)
    worst_x: dict[str, float] = dataclasses.field(default_factory=dict)
    worst_v: dict[str, float] = dataclasses.field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """The counts, the shares and the classes with their examples (JSON-ready)."""
        share = lambda a, b: a / b if b else 0.0  # noqa: E731
        return {
            "episodes": self.episodes, "decisions": self.decisions, "traces": self.traces,
            "traces_out": self.traces_out, "traces_out_share": share(self.traces_out, self.traces),
            "car_frames": self.car_frames, "car_frames_out": self.car_frames_out,
            "car_frames_out_share": share(self.car_frames_out, self.car_frames),
            "frames": self.frames, "frames_out": self.frames_out,
            "frames_out_share": share(self.frames_out, self.frames),
            "car_decisions": self.car_decisions, "car_decisions_out": self.car_decisions_out,
            "car_decisions_out_share": share(self.car_decisions_out, self.car_decisions),
            "at_decisions": self.at_decisions, "at_decisions_out": self.at_decisions_out,
            "at_decisions_out_share": share(self.at_decisions_out, self.at_decisions),
            "components": dict(self.components),
            "classes": {
                name: {"car_frames": self.classes_frames[name], "car_decisions": self.classes_decisions[name],
                       "largest_position_excess_m": round(self.worst_x.get(name, 0.0), 4),
                       "largest_speed_excess_m_s": round(self.worst_v.get(name, 0.0), 4),
                       "examples": self.examples.get(name, [])}
                for name in CLASSES if self.classes_frames[name]
            },
        }  # fmt: skip


def components(state: RoadState, i: int, sets: CarSets, r: int, dyn: Dynamics, vehicle: np.ndarray) -> list[str]:
    """The components of the set (shifted to now) car ``i`` of ``state`` is outside: ``x_low``/``x_high``,
    ``v_low``/``v_high``, ``lane``, else ``other``. Each is asked of :func:`escaped_cars` on the set with every other
    bound removed, so the audit reads the speed the sets bound (along the road or along the path) as they do."""
    inf = np.full_like(sets.x_lo, np.inf)
    free = {"x_lo": -inf, "x_hi": inf, "v_lo": -inf, "v_hi": inf, "entry": np.zeros_like(sets.entry)}
    probes = {"x_low": ("x_lo",), "x_high": ("x_hi",), "v_low": ("v_lo",), "v_high": ("v_hi",), "lane": ("entry",)}
    out = []
    for name, kept in probes.items():
        only = dataclasses.replace(sets, **{k: v for k, v in free.items() if k not in kept})
        if escaped_cars(state, dyn, only, vehicle)[i]:
            out.append(name)
    return out or ["other"]


def cause(
    parts: list[str],
    crashed_at_draw: bool,
    crashed_now: bool,
    turning: bool,
    vx: float,
    beyond: float,
    backwards_at_draw: bool = False,
) -> str:
    """The class (:data:`CLASSES`) of an escape: its components ``parts``, whether the car was crashed at the
    decision / is now, has turned off the road's heading since the decision, its speed along the road ``vx``
    [m/s] (the speed the sets bound), how far [m] it is outside its position interval ``beyond``, and whether it
    was moving backwards when the set was drawn (``backwards_at_draw``)."""
    if crashed_now and not crashed_at_draw:
        return "collision"
    if crashed_at_draw:
        return "crashed_wall_moves"
    if beyond > TELEPORT:
        return "teleport"
    low = "x_low" in parts or "v_low" in parts
    high = "x_high" in parts or "v_high" in parts
    if low and (vx < 0 or backwards_at_draw):
        return "rolling_back"
    if "lane" in parts:
        return "lane_entered_early"
    if low:
        return "turning_slower" if turning else "straight_slower"
    if high:
        return "turning_faster" if turning else "straight_faster"
    return "other_component"


class FrameRecorder:
    """Records a snapshot and the body identities after every physics frame of a highway-env road (wraps the
    frame step the adapter's crash watch calls, so the snapshots keep their impact records)."""

    def __init__(self, env: Any) -> None:
        from safelane.sim.highway import bodies, snapshot_of

        self._bodies, self._snapshot_of = bodies, snapshot_of
        self.base = env.unwrapped
        self.frames: list[tuple[RoadSnapshot, np.ndarray]] = []
        self.ids: dict[int, int] = {}
        self._cache: dict = {}
        road = self.base.road
        watch = road.__dict__.get("step")
        owner, name = (watch, "inner") if watch is not None and hasattr(watch, "inner") else (road, "step")
        inner = getattr(owner, name)

        def step(dt: float) -> None:
            inner(dt)
            self.frames.append(self.current())

        setattr(owner, name, step)

    def identities(self) -> np.ndarray:
        """(bodies,) a number per body, the same for the same object all episode (new objects get new ones)."""
        return np.array([self.ids.setdefault(id(o), len(self.ids)) for o in self._bodies(self.base.road)])

    def current(self) -> tuple[RoadSnapshot, np.ndarray]:
        """The snapshot now and the identity of each of its bodies."""
        return self._snapshot_of(self.base, self._cache), self.identities()


def audit_episode(
    env: Any, policy: Callable[[Any, dict], int], seed: int, tally: Tally, per_frame: bool = True
) -> None:
    """Play one episode and add what it shows to ``tally`` (``per_frame``: highway-env's frames are recorded;
    else the cars are checked at the decisions, identified by snapshot index)."""
    obs, info = env.reset(seed=seed)
    recorder = FrameRecorder(env) if per_frame else None
    snap = info["snapshot"]
    dyn = dynamics_of(snap)
    ids = recorder.identities() if recorder else np.arange(snap.n)
    state, rows = whole_road_state(snap, dyn.rule.ego_speed_magnitude)
    vehicle = ids[rows]
    sets = car_sets(state, dyn, vehicle)
    seen_out: set[int] = set()
    traced: set[int] = set(int(v) for v in vehicle)
    decision, done = 0, False
    while not done:
        decision += 1
        if recorder:
            recorder.frames.clear()
        obs, _, terminated, truncated, info = env.step(int(policy(obs, info)))
        done = terminated or truncated
        if recorder:
            frames = [(k + 1, s, i) for k, (s, i) in enumerate(recorder.frames)]
        else:
            frames = [(dyn.frames_per_decision, info["snapshot"], np.arange(info["snapshot"].n))]
        crashed_at_draw = {int(v): bool(c) for v, c in zip(vehicle, state.crashed, strict=True)}
        backwards = {int(v) for v, u in zip(vehicle, set_speed(state), strict=True) if u < 0}
        turned: set[int] = {
            int(v) for v, h in zip(vehicle, state.heading, strict=True) if abs(h) > LATERAL_MOTION_THRESHOLD
        }
        turning_at_draw = set(turned)
        out_this: set[int] = set()
        for k, frame_snap, frame_ids in frames:
            st, fr = whole_road_state(frame_snap, dyn.rule.ego_speed_magnitude)
            fv = frame_ids[fr]
            traced.update(int(v) for v in fv)
            turned.update(int(v) for v, h in zip(fv, st.heading, strict=True) if abs(h) > LATERAL_MOTION_THRESHOLD)
            older = sets.shifted(k, k * dyn.frame_dt)
            out = escaped_cars(st, dyn, older, fv)
            known = np.isin(fv, older.vehicle)
            tally.car_frames += int(known.sum())
            tally.frames += 1
            tally.frames_out += bool(out.any())
            tally.car_frames_out += int(out.sum())
            at_decision = k == dyn.frames_per_decision
            if at_decision:
                tally.at_decisions += int(known.sum())
                tally.at_decisions_out += int(out.sum())
            rows_of = {int(v): r for r, v in enumerate(older.vehicle)}
            speed = set_speed(st)
            for i in np.flatnonzero(out):
                v, r = int(fv[i]), rows_of[int(fv[i])]
                parts = components(st, int(i), older, r, dyn, fv)
                beyond = max(older.x_lo[r, 0] - st.x[i], st.x[i] - older.x_hi[r, 0], 0.0)
                name = cause(parts, crashed_at_draw.get(v, False), bool(st.crashed[i]), v in turned,
                             float(speed[i]), float(beyond), v in backwards)  # fmt: skip
                tally.classes_frames[name] += 1
                over_v = max(older.v_lo[r, 0] - speed[i], speed[i] - older.v_hi[r, 0], 0.0)
                tally.worst_x[name] = max(tally.worst_x.get(name, 0.0), float(beyond))
                tally.worst_v[name] = max(tally.worst_v.get(name, 0.0), float(over_v))
                tally.components.update(parts)
                if v not in out_this:
                    tally.classes_decisions[name] += 1
                    out_this.add(v)
                examples = tally.examples.setdefault(name, [])
                if len(examples) < MAX_EXAMPLES and all(e["car"] != v or e["seed"] != seed for e in examples):
                    examples.append({
                        "seed": seed, "decision": decision, "frame": k, "car": v, "components": parts,
                        "x": round(float(st.x[i]), 3), "x_interval": [round(float(older.x_lo[r, 0]), 3),
                                                                     round(float(older.x_hi[r, 0]), 3)],
                        "speed": round(float(speed[i]), 3), "v_interval": [round(float(older.v_lo[r, 0]), 3),
                                                                       round(float(older.v_hi[r, 0]), 3)],
                        "heading": round(float(st.heading[i]), 4), "turning_at_draw": v in turning_at_draw,
                    })  # fmt: skip
        tally.car_decisions += len(vehicle)
        tally.car_decisions_out += len(out_this)
        seen_out |= out_this
        tally.decisions += 1
        snap = info["snapshot"]
        ids = recorder.identities() if recorder else np.arange(snap.n)
        state, rows = whole_road_state(snap, dyn.rule.ego_speed_magnitude)
        vehicle = ids[rows]
        sets = car_sets(state, dyn, vehicle)
    tally.episodes += 1
    tally.traces += len(traced)
    tally.traces_out += len(seen_out)


def audit_driver(driver: str, episodes: int, seed: int, policy: str, simulator: str, sets: list[str] | None = None,
                 log: Callable[[str], None] = print, preset: str = "fast") -> dict[str, Any]:  # fmt: skip
    """One driver model's audit over ``episodes`` episodes (seeds ``seed …``): :meth:`Tally.summary`."""
    from safelane.config import load_config
    from safelane.env.factory import make_env
    from safelane.running.policies import fixed_policy

    chosen = [f"simulator={simulator}", f"env.other_vehicles_type={DRIVERS[driver]}", "shield.mode=robust",
              "shield.override=true"]  # fmt: skip
    cfg = load_config(preset, chosen + list(sets or []))
    env = make_env(cfg)
    tally = Tally()
    start = time.perf_counter()
    for k in range(episodes):
        audit_episode(env, fixed_policy(policy, seed + k), seed + k, tally, per_frame=simulator == "highway-env")
        if (k + 1) % 10 == 0 or k + 1 == episodes:
            log(f"{driver}: {k + 1}/{episodes} episodes, {tally.car_frames_out} car-frames out of "
                f"{tally.car_frames}, {time.perf_counter() - start:.0f} s")  # fmt: skip
    env.close()
    return {"driver": driver, "other_vehicles_type": DRIVERS[driver], "seconds": round(time.perf_counter() - start),
            **tally.summary()}  # fmt: skip


def table(results: list[dict[str, Any]]) -> str:
    """The summary as a markdown table: per driver model, the shares, then the car-frames per class."""
    lines = ["| driver | episodes | traces (out) | car-frames out | frames with a car out | car-decisions out | "
             "out at the decisions |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    pct = lambda s: f"{100 * s:.3f} %"  # noqa: E731
    for r in results:
        lines.append(f"| {r['driver']} | {r['episodes']} | {r['traces']} ({r['traces_out']}) | "
                     f"{r['car_frames_out']} / {r['car_frames']} ({pct(r['car_frames_out_share'])}) | "
                     f"{r['frames_out']} / {r['frames']} ({pct(r['frames_out_share'])}) | "
                     f"{r['car_decisions_out']} / {r['car_decisions']} ({pct(r['car_decisions_out_share'])}) | "
                     f"{r['at_decisions_out']} / {r['at_decisions']} "
                     f"({pct(r['at_decisions_out_share'])}) |")  # fmt: skip
    head = "| class: car-frames / car-decisions (by the first frame out) | "
    lines += ["", head + " | ".join(r["driver"] for r in results) + " |",
              "|---|" + "---|" * len(results)]  # fmt: skip
    for name in CLASSES:
        cells = [r["classes"].get(name, {}) for r in results]
        if any(cells):
            lines.append(
                f"| {name} | "
                + " | ".join(f"{c.get('car_frames', 0)} frames / {c.get('car_decisions', 0)} decisions" for c in cells)
                + " |"
            )
    return "\n".join(lines) + "\n"


def report(data: dict[str, Any]) -> str:
    """The markdown page of a summary: what was played, the command, :func:`table`."""
    where = {"fast": "highway-fast-v0, 5 Hz physics", "paper": "highway-v0, 15 Hz physics"}[data["preset"]]
    checked = "every physics frame" if data["simulator"] == "highway-env" else "the decisions only"
    return (
        f"# Set-escape audit: {data['simulator']} ({where}), checked at {checked}\n\n"
        f"The paper's traffic; the ego: the {data['policy']} policy, shield {data['ego_shield']}; a trace is "
        f"{data['trace']}. Classes and reading: [the research page](../../research/set-escape-audit.md).\n\n"
        f"    {data['command']}\n\n" + table(data["drivers"])
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=200, help="episodes per driver model")
    parser.add_argument("--seed", type=int, default=0, help="episode k has seed SEED + k")
    parser.add_argument("--drivers", nargs="+", default=list(DRIVERS), choices=list(DRIVERS))
    parser.add_argument("--policy", default="random", choices=("random", "faster", "idle", "slower", "probe"))
    parser.add_argument(
        "--preset",
        default="fast",
        choices=("fast", "paper"),
        help="fast: highway-fast-v0, 5 Hz physics; paper: highway-v0, 15 Hz (3x slower)",
    )
    parser.add_argument("--simulator", default="highway-env", choices=("highway-env", "fast"))
    parser.add_argument("--set", dest="sets", action="append", default=[], help="config overrides KEY=VALUE")
    parser.add_argument("--out", required=True, help="summary JSON (a markdown table beside it, .md)")
    parser.add_argument("--report-only", action="store_true", help="rewrite the .md beside --out from its JSON")
    args = parser.parse_args(argv)
    if args.report_only:
        Path(args.out).with_suffix(".md").write_text(report(json.loads(Path(args.out).read_text())))
        return 0
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    results = []
    for driver in args.drivers:
        results.append(
            audit_driver(driver, args.episodes, args.seed, args.policy, args.simulator, args.sets, preset=args.preset)
        )
        command = "python research/set_escape_audit.py " + " ".join(sys.argv[1:] if argv is None else argv)
        data = {"command": command, "preset": args.preset, "simulator": args.simulator, "policy": args.policy,
                "ego_shield": "robust, override", "seed": args.seed, "trace": "one car over one episode",
                "classes": CLASSES, "drivers": results}  # fmt: skip
        out.write_text(json.dumps(data, indent=1))
        out.with_suffix(".md").write_text(report(data))
    print(table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
