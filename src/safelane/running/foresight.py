"""The price of robustness: how fast can a collision-free policy drive, with and without a shield?

:class:`ForesightPlanner` knows the future. On the fast simulator the other drivers are deterministic
after reset (IDM and MOBIL have no noise; the randomness is all in the spawn), so a copy of the
simulator's state (:meth:`safelane.sim.fast.env.FastHighwayEnv.get_state`) predicts exactly what
every car will do for any sequence of ego actions. The planner searches meta-action sequences over a
receding horizon (a beam search: every surviving sequence is extended by each allowed action, crashed
ones are dropped, the ``beam`` that got farthest along the road are kept) and plays the best plan's
first action(s). Unmasked, it bounds the speed any collision-free policy reaches in this traffic (from
below: a deeper search could only drive faster); restricted to the nominal or robust mask at every
node of the search, it gives that shield's real ceiling. The committed mask has memory (the plan kept from one
decision to the next, :class:`~safelane.safety.committed.family.CommittedFamily`): every node of the search carries its
own copy of it, committed along the node's actions (:func:`clone_memory`).

:func:`~safelane.running.policies.overtaking_probe` is a hand-written FASTER-first heuristic (it reads the
snapshot and the mask); :func:`ceiling_table` runs the comparison at several decision rates.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from typing import Any, Literal, NamedTuple

import numpy as np

from safelane.config import ConfigError, SafelaneConfig, apply_overrides, build_config, config_to_dict
from safelane.core.snapshot import RoadSnapshot
from safelane.core.spaces import ACTION_NAMES, N_ACTIONS
from safelane.env.factory import make_env
from safelane.running.control_foresight import ControlForesightPlanner, diverse_beam, search_shape
from safelane.running.policies import overtaking_probe, snap_of
from safelane.safety.belief import DriverTypes
from safelane.safety.committed.family import CommittedFamily
from safelane.safety.shield import SafetyShield
from safelane.safety.world import Engine
from safelane.sim.fast.env import SimState

PlannerMask = Literal["none", "nominal", "robust", "committed", "omniscient"]
PLANNER_MASKS: tuple[str, ...] = ("none", "nominal", "robust", "committed", "omniscient")


def clone_memory(family: CommittedFamily) -> CommittedFamily:
    """An independent copy of a committed family's memory (kept plan, carried sets, follower bounds), sharing
    only the verdict it evaluated last (read, never changed, by :meth:`~CommittedFamily.commit`), so that each
    copy can commit another action in that state."""
    pending = getattr(family, "_pending", None)
    return copy.deepcopy(family, memo={id(pending): pending} if pending is not None else None)


class ForesightPlanner:
    """A policy with perfect foresight: a beam search over the fast simulator's exact future.

    ``env``: the safelane environment it acts in (built with ``simulator: fast``). ``mask``: ``none``
    (any action), ``nominal``, ``robust``, ``omniscient`` or ``committed`` (only actions that shield allows, at every
    node of the search; in a fallback state, the shield's least-bad action; ``committed``: the committed mask with
    ``engine``, its memory carried by every node and, between searches, by :attr:`memory`, which
    records the actions played: the environment must play them). Under a ``traffic.driver_mix`` of the environment's
    configuration (hidden driver types) ``robust`` is the worst case over the types and ``omniscient`` reads each car's
    true type, as the shields of those modes do; ``belief`` is not a planner mask: its filter would have to follow
    every branch of the search. ``horizon`` [s]: how far each search
    looks; ``beam``: sequences kept per depth; ``replan`` [s]: how often it searches again (the plan is
    exact, so replaying it between searches loses nothing but horizon). Call it like any policy:
    ``planner(obs, info) -> action``; it restores the simulator's state after each search.
    """

    def __init__(
        self,
        env: Any,
        mask: PlannerMask = "none",
        horizon: float = 4.0,
        beam: int = 8,
        replan: float = 1.0,
        margin: float | None = None,
        engine: Engine = "compiled",
    ) -> None:
        if mask not in PLANNER_MASKS:
            raise ConfigError(f"mask: got {mask!r}; allowed: {', '.join(PLANNER_MASKS)}")
        # depth: decisions per search; every: decisions between searches
        self.sim, self.depth, self.every = search_shape(env, horizon, beam, replan)
        self.beam = beam
        self.mask_mode: PlannerMask = mask
        kwargs: dict[str, Any] = {} if margin is None else {"margin": margin}
        mix = _driver_mixture(env)
        if mix is not None:  # the shields' types: robust over every type, omniscient on the true ones
            kwargs["driver_types"] = DriverTypes(mix)
        elif mask == "omniscient":
            raise ConfigError("mask: 'omniscient' reads the driver types of a traffic.driver_mix, which is none")
        # A shield over the bare simulator, only to evaluate masks of predicted states (never stepped).
        self.memory: CommittedFamily | None = None
        if mask == "committed":
            self.memory = CommittedFamily(engine)
            self.shield = SafetyShield(self.sim, mode=self.memory, **kwargs)
        else:
            self.shield = None if mask == "none" else SafetyShield(self.sim, mode=mask, **kwargs)
        self.plan: list[int] = []
        self.searches = 0
        self.nodes = 0
        self.search_time = 0.0
        self.last_frontier: list[tuple[list[int], CommittedFamily | None]] = []
        """The sequences the last search ended with, best first, each with the committed mask's memory after it
        (None under the other masks): what a node carries."""

    def allowed(self, snap: RoadSnapshot, memory: CommittedFamily | None = None) -> tuple[np.ndarray, bool]:
        """The actions the planner may take in ``snap`` (bool (5,)) and whether ``snap`` is a fallback
        state of the mask (no action safe: the mask holds the least-bad one; committed: no plan verified).
        ``memory``: the committed mask's memory in ``snap`` (default :attr:`memory`), left holding the verdict
        that its :meth:`~CommittedFamily.commit` then reads."""
        if self.shield is None:
            return np.ones(N_ACTIONS, dtype=bool), False
        if self.memory is None:
            result = self.shield.compute_result(snap)
        else:
            leave = self.shield.ego_leave_time(snap)
            assert self.shield.dynamics is not None
            result = (memory or self.memory).evaluate(snap, self.shield.dynamics, leave)
        return result.mask, bool(result.fallback)

    def search(self) -> list[int]:
        """The best action sequence from the simulator's current state (the state is restored)."""
        start_clock = time.perf_counter()
        sim = self.sim
        root = sim.get_state()
        root_snap = sim.snapshot()
        # A node: (state, snapshot, actions so far). Children that crash are dropped; the deepest
        # crash is kept as a last resort so the planner always returns an action.
        # Under a mask, a sequence that has passed through a fallback state (no safe action) ranks below
        # every one that stayed in the safe set: the planner knows the future, so it can keep the rule's
        # promise. A state is judged when it is extended, so the last depth's states are not judged.
        # Under the committed mask each node carries the mask's memory after its actions (None: no memory).
        root_memory = clone_memory(self.memory) if self.memory is not None else None
        frontier: list[tuple[SimState, RoadSnapshot, list[int], int, CommittedFamily | None]] = [
            (root, root_snap, [], 0, root_memory)
        ]
        best_crashed: tuple[int, float, list[int]] | None = None
        for _ in range(self.depth):
            children: list[Node] = []
            seen: set[tuple[float, float, float, int]] = set()
            for state, snap, actions, fallbacks, memory in frontier:
                mask, fallback = self.allowed(snap, memory)
                fallbacks += int(fallback and bool(actions))
                for action in np.flatnonzero(mask):
                    child_memory = None
                    if memory is not None:  # the mask's memory after this action: the plan it keeps
                        child_memory = clone_memory(memory)
                        child_memory.commit(int(action))
                    sim.set_state(state)
                    _, _, terminated, _, info = sim.step(int(action))
                    self.nodes += 1
                    child = snap_of(info)
                    x, v = float(child.position[0, 0]), float(child.speed[0])
                    seq = [*actions, int(action)]
                    if terminated:
                        key = (len(seq), x)
                        if best_crashed is None or key > best_crashed[:2]:
                            best_crashed = (len(seq), x, seq)
                        continue
                    # FASTER at the top set-point is IDLE, and so on: keep one of identical states.
                    signature = (round(x, 9), round(float(child.position[0, 1]), 9), round(v, 9), child.ego_speed_index)
                    if signature in seen:
                        continue
                    seen.add(signature)
                    children.append(Node(-fallbacks, x, v, sim.get_state(), child, seq, child_memory))
            if not children:
                break
            kept = diverse_beam(children, self.beam, meta_action_class)
            frontier = [(c.state, c.snap, c.actions, -c.rank, c.memory) for c in kept]
            if all(snap.time >= sim.sim.duration for _, snap, _, _, _ in frontier):
                break
        sim.set_state(root)
        self.last_frontier = [(actions, memory) for _, _, actions, _, memory in frontier]
        self.searches += 1
        self.search_time += time.perf_counter() - start_clock
        if frontier and frontier[0][2]:
            return frontier[0][2]
        if best_crashed is not None:
            return best_crashed[2]
        return [int(np.flatnonzero(self.allowed(root_snap, clone_memory(self.memory) if self.memory else None)[0])[-1])]

    def __call__(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        if not self.plan:
            self.plan = self.search()[: self.every]
        action = self.plan.pop(0)
        if self.memory is not None:  # the committed mask's memory follows the episode: this state, this action
            self.allowed(snap_of(info))
            self.memory.commit(action)
        return action

    def reset(self) -> None:
        """Forget the current plan and the committed mask's memory (call at the start of an episode)."""
        self.plan = []
        if self.memory is not None:
            self.memory.reset()


def _driver_mixture(env: Any) -> Any:
    """The driver mixture of the environment's configuration (``env.safelane_config``, set by ``make_env``), or None."""
    cfg = getattr(env, "safelane_config", None)
    return cfg.traffic.driver_mixture() if cfg is not None else None


class Node(NamedTuple):
    """A sequence in the search: its rank (minus the fallback states it passed), the ego's position [m]
    along the road and speed [m/s] at its end, the simulator state there, its snapshot, its actions, and the
    committed mask's memory after them (None under the other masks)."""

    rank: int
    x: float
    v: float
    state: SimState
    snap: RoadSnapshot
    actions: list[int]
    memory: CommittedFamily | None = None


def meta_action_class(node: Node) -> tuple[int, int, int]:
    """A meta-action sequence's class in the beam (:func:`~safelane.running.control_foresight.diverse_beam`): the
    ego's lane, target lane and set-point."""
    snap = node.snap
    return int(snap.lane[0]), int(snap.target_lane[0]), snap.ego_speed_index


def at_rate(cfg: SafelaneConfig, rate: int) -> SafelaneConfig:
    """``cfg`` with ``rate`` decisions per second and physics at 5·rate Hz (the ``fast`` preset's ratio)."""
    return with_overrides(cfg, {"env.policy_frequency": rate, "env.simulation_frequency": 5 * rate})


def with_overrides(cfg: SafelaneConfig, overrides: dict[str, Any]) -> SafelaneConfig:
    """A copy of ``cfg`` with dotted-key overrides, validated again."""
    data = config_to_dict(cfg)
    apply_overrides(data, overrides)
    return build_config(data)


def play(
    cfg: SafelaneConfig,
    policy_of: Callable[[Any], Callable[[np.ndarray, dict[str, Any]], int]],
    episodes: int,
    seed: int,
) -> dict[str, Any]:
    """Play ``episodes`` episodes (reset seeds ``seed + i``) with the policy ``policy_of(env)`` builds;
    collisions, mean speed [m/s] over all decisions, fallback and intervention rates, wall time [s]."""
    from safelane.running.evaluation import COMMITTED_FIGURES, CONTINUOUS_FIGURES, run_episodes, summarize

    env = make_env(cfg)
    try:
        policy = policy_of(env)
        wrapped = _resetting(policy)
        start = time.perf_counter()
        records = run_episodes(env, wrapped, episodes, seed)
        wall = time.perf_counter() - start
    finally:
        env.close()
    summary = summarize(records)
    committed = {k: summary[k] for k in COMMITTED_FIGURES if k in summary}  # the committed shield's rows only
    continuous = {k: summary[k] for k in CONTINUOUS_FIGURES if k in summary}  # continuous actions' rows only
    return {
        "episodes": episodes,
        "decisions": int(summary["decisions"]),
        "collisions": int(sum(r.collision for r in records)),
        "mean_speed": float(summary["mean_speed"]),
        "fallback_rate": float(summary["fallback_rate"]),
        "shield_intervention_rate": float(summary["shield_intervention_rate"]),
        "invariant_breaks": int(summary["invariant_breaks"]),
        "wall_time_s": wall,
        "actions": {name: int(sum(r.actions[i] for r in records)) for i, name in enumerate(ACTION_NAMES)},
        **committed,
        **continuous,
    }


def planner_policy(planner: ForesightPlanner) -> Callable[[np.ndarray, dict[str, Any]], int]:
    """``planner`` as a policy of several episodes: it forgets its plan when a new one starts."""
    return _resetting(planner)


def _resetting(policy: Callable[[np.ndarray, dict[str, Any]], int]) -> Callable[[np.ndarray, dict[str, Any]], int]:
    """``policy`` that forgets a planner's plan when a new episode starts (time 0 in the snapshot)."""
    reset = getattr(policy, "reset", None)

    def act(obs: np.ndarray, info: dict[str, Any]) -> int:
        if reset is not None and info["snapshot"].time == 0.0:
            reset()
        return policy(obs, info)

    return act


# --- the price-of-robustness table ------------------------------------------------------------------

ROWS: tuple[str, ...] = (
    "foresight", "foresight_nominal", "foresight_robust", "probe_robust", "agent_robust", "foresight_committed",
    "agent_committed", "foresight_continuous", "foresight_continuous_committed", "agent_continuous",
)  # fmt: skip
"""The table's rows per decision rate: the planner unmasked / under the nominal / under the robust mask,
the overtaking probe under the robust shield, a trained robust agent (where one is given); the planner under the
committed mask and the same agent under the committed shield (``shield.engine`` of the table's config); with
continuous acceleration and steering, the planner over its control set unshielded and under the shield for
continuous actions (:class:`~safelane.running.control_foresight.ControlForesightPlanner`), and a trained continuous
agent under that shield (where one is given)."""
ROW_SHIELDS = {
    "foresight": "none", "foresight_nominal": "nominal", "foresight_committed": "committed",
    "agent_committed": "committed", "foresight_continuous": "none", "foresight_continuous_committed": "committed",
    "agent_continuous": "committed",
}  # fmt: skip
"""The shield of each row of :data:`ROWS` not under the robust one."""
CONTINUOUS_ROWS = ("foresight_continuous", "foresight_continuous_committed", "agent_continuous")
"""The rows whose ego takes continuous actions (acceleration and steering)."""


def row_config(cfg: SafelaneConfig, row: str) -> SafelaneConfig:
    """The environment of a row: the fast simulator; the shield the row acts under, with override so a
    mask-respecting policy is never overridden (the shield's counters then show it); continuous actions for
    :data:`CONTINUOUS_ROWS` (whose shield executes a verified action, no override)."""
    shield = ROW_SHIELDS.get(row, "robust")
    overrides: dict[str, Any] = {"simulator": "fast", "shield.mode": shield}
    if row in CONTINUOUS_ROWS:
        overrides["actions"] = "continuous"
    elif shield != "none":
        overrides["shield.override"] = True
    return with_overrides(cfg, overrides)


def play_row(
    cfg_data: dict[str, Any], row: str, episodes: int, seed: int, agent_dir: str | None, horizon: float, beam: int
) -> dict[str, Any]:
    """One cell of the table (a task of :func:`safelane.running.backend.run_tasks`: plain arguments)."""
    cfg = row_config(build_config(cfg_data), row)
    if row == "agent_continuous":
        from safelane.running.run_directory import load_policy, load_run_config
        from safelane.running.runs import run_env_config

        if agent_dir is None:
            raise ConfigError("agent: no trained continuous agent given for this rate")
        run = load_run_config(agent_dir)
        if run.env.actions != "continuous":
            raise ConfigError(f"--continuous-agent: {agent_dir} takes meta-actions; give it with --agent")
        env_cfg = run_env_config(run, sets=[f"shield.engine={cfg.shield.engine}"], shield="committed")
        return {"row": row, "agent": agent_dir, **play(env_cfg, lambda env: load_policy(agent_dir), episodes, seed)}
    if row in ("foresight_continuous", "foresight_continuous_committed"):
        controls: list[ControlForesightPlanner] = []

        def make_control(env: Any) -> ControlForesightPlanner:
            controls.append(ControlForesightPlanner(env, horizon=horizon, beam=beam))
            return controls[-1]

        result = play(cfg, make_control, episodes, seed)
        c = controls[0]
        return {"row": row, "horizon_s": horizon, "beam": beam, "searches": c.searches, "nodes": c.nodes, **result}
    if row in ("agent_robust", "agent_committed"):
        from safelane.running.run_directory import greedy_policy, load_agent, load_run_config
        from safelane.running.runs import run_env_config

        if agent_dir is None:
            raise ConfigError("agent: no trained agent given for this rate")
        run = load_run_config(agent_dir)
        if run.env.actions == "continuous":
            raise ConfigError(f"--agent: {agent_dir} takes continuous actions; give it with --continuous-agent")
        agent = load_agent(agent_dir)
        # The committed shield with the table's engine (the run's own config may have none).
        sets = [f"shield.engine={cfg.shield.engine}"]
        shield = cfg.shield.mode
        env_cfg = run_env_config(run, sets=sets if shield == "committed" else None, shield=shield, override=True)
        return {"row": row, "agent": agent_dir, **play(env_cfg, lambda env: greedy_policy(agent, run), episodes, seed)}
    if row == "probe_robust":
        return {"row": row, **play(cfg, lambda env: overtaking_probe, episodes, seed)}
    mask: PlannerMask = cfg.shield.mode if row in ROW_SHIELDS else "robust"  # type: ignore[assignment]
    planners: list[ForesightPlanner] = []

    def make(env: Any) -> ForesightPlanner:
        planners.append(
            ForesightPlanner(env, mask=mask, horizon=horizon, beam=beam, engine=cfg.shield.engine)
        )  # fmt: skip
        return planners[-1]

    result = play(cfg, make, episodes, seed)
    p = planners[0]
    return {"row": row, "horizon_s": horizon, "beam": beam, "searches": p.searches, "nodes": p.nodes, **result}


def _merge(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """One row from its chunks: counts summed, mean speed weighted by episodes, rates by decisions."""
    n = sum(p["episodes"] for p in parts)
    merged: dict[str, Any] = {k: v for k, v in parts[0].items() if k not in ("episodes", "seed", "chunk")}
    merged["episodes"] = n
    merged["collisions"] = sum(p["collisions"] for p in parts)
    merged["invariant_breaks"] = sum(p["invariant_breaks"] for p in parts)
    merged["mean_speed"] = sum(p["mean_speed"] * p["episodes"] for p in parts) / n
    # Continuous rows count no meta-actions: their decisions are recorded (cells from before them have only actions).
    decisions = [p.get("decisions", sum(p["actions"].values())) for p in parts]
    total = max(sum(decisions), 1)
    merged["decisions"] = sum(decisions)
    for key in ("fallback_rate", "shield_intervention_rate"):
        merged[key] = sum(p[key] * d for p, d in zip(parts, decisions, strict=True)) / total
    merged["actions"] = {a: sum(p["actions"][a] for p in parts) for a in ACTION_NAMES}
    merged["wall_time_s"] = sum(p["wall_time_s"] for p in parts)
    if "plan_forced_rate" in parts[0]:  # the committed shield's rows: counts summed, the rate by decisions
        merged["plan_forced_rate"] = (
            sum(p["plan_forced_rate"] * d for p, d in zip(parts, decisions, strict=True)) / total
        )
        for key in ("lapses", "lapses_in_model", "uncertified_starts", "redraws"):
            merged[key] = sum(p[key] for p in parts)
    if "off_road_rate" in parts[0]:  # continuous actions: episodes off the road, projections by decisions
        merged["off_road_rate"] = sum(p["off_road_rate"] * p["episodes"] for p in parts) / n
    if "projection_rate" in parts[0]:
        projected = [p["projection_rate"] * d for p, d in zip(parts, decisions, strict=True)]
        merged["projection_rate"] = sum(projected) / total
        distance = sum((p["mean_projection_distance"] or 0.0) * k for p, k in zip(parts, projected, strict=True))
        merged["mean_projection_distance"] = distance / sum(projected) if sum(projected) > 0 else None
    for key in ("searches", "nodes"):
        if key in parts[0]:
            merged[key] = sum(p[key] for p in parts)
    return merged


def ceiling_table(
    cfg: SafelaneConfig,
    rates: list[int],
    episodes: int,
    seed: int,
    out: Any,
    agents: dict[int, str] | None = None,
    horizon: float = 4.0,
    beam: int = 16,
    chunk: int = 25,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    rows: tuple[str, ...] = ROWS,
    continuous_agents: dict[int, str] | None = None,
) -> dict[str, Any]:
    """The price-of-robustness table: every row of ``rows`` (default :data:`ROWS`) at every decision rate (physics
    at 5·rate Hz) on the same episodes (reset seeds ``seed + i``). Work is cut into chunks of ``chunk``
    episodes written to ``out/cells/`` as they finish, so a killed run resumes where it stopped;
    ``out/ceiling.json`` and ``out/ceiling.md`` are rebuilt from them (with every row's cells there, so rows
    played by earlier calls stay in the table). Rows without an agent are skipped: ``agents`` {rate: run directory}
    the trained robust agents, ``continuous_agents`` the trained continuous ones."""
    import json
    from pathlib import Path

    from safelane.core.files import atomic_write_text
    from safelane.running.backend import TaskFailure, run_tasks

    if episodes < 1:
        raise ConfigError(f"--episodes: must be >= 1 (got {episodes})")
    unknown = [row for row in rows if row not in ROWS]
    if unknown or not rows:
        raise ConfigError(f"--rows: got {','.join(rows)!r}; allowed: {', '.join(ROWS)}")
    for rate in rates:
        if rate < 1:
            raise ConfigError(f"--rates: decision rates must be >= 1 per second (got {rate})")
    agents, continuous_agents = agents or {}, continuous_agents or {}
    for option, given in (("--agent", agents), ("--continuous-agent", continuous_agents)):
        for rate in given:
            if rate not in rates:
                raise ConfigError(f"{option}: rate {rate} is not in --rates ({', '.join(map(str, rates))})")
    out = Path(out)
    cells = out / "cells"
    cells.mkdir(parents=True, exist_ok=True)
    tasks: list[tuple[Any, ...]] = []
    names: list[Path] = []
    for rate in rates:
        data = config_to_dict(at_rate(cfg, rate))
        for row in rows:
            agent = (continuous_agents if row == "agent_continuous" else agents).get(rate)
            if row.startswith("agent_") and agent is None:
                continue
            for start in range(0, episodes, chunk):
                path = cells / f"{rate}hz-{row}-{start:06d}.json"
                if path.is_file():
                    continue
                count = min(chunk, episodes - start)
                tasks.append((data, row, count, seed + start, agent, horizon, beam))
                names.append(path)
    done = [0]

    def on_result(i: int, result: dict[str, Any] | TaskFailure) -> None:
        if not isinstance(result, TaskFailure):
            atomic_write_text(names[i], json.dumps(result) + "\n")
        done[0] += 1
        if progress is not None:
            progress(done[0], len(tasks))

    results = run_tasks(play_row, tasks, workers=workers, on_result=on_result, name="ceiling")
    failures = [r for r in results if isinstance(r, TaskFailure)]
    if failures:
        raise ConfigError(f"ceiling: {len(failures)} task(s) failed, first: {failures[0].message}")
    table: dict[str, Any] = {"episodes": episodes, "seed": seed, "horizon_s": horizon, "beam": beam, "rates": {}}
    for rate in rates:
        rows: dict[str, Any] = {}
        for row in ROWS:
            parts = [json.loads(p.read_text()) for p in sorted(cells.glob(f"{rate}hz-{row}-*.json"))]
            if parts:
                rows[row] = _merge(parts)
        table["rates"][str(rate)] = rows
    atomic_write_text(out / "ceiling.json", json.dumps(table, indent=1) + "\n")
    atomic_write_text(out / "ceiling.md", ceiling_markdown(table))
    return table


ROW_LABELS = {
    "foresight": "foresight, unmasked",
    "foresight_nominal": "foresight under the nominal mask",
    "foresight_robust": "foresight under the robust mask",
    "probe_robust": "overtaking probe, robust shield",
    "agent_robust": "learned robust agent",
    "foresight_committed": "foresight under the committed mask",
    "agent_committed": "learned robust agent, committed shield",
    "foresight_continuous": "foresight, continuous controls, unshielded",
    "foresight_continuous_committed": "foresight, continuous controls, under the shield for continuous actions",
    "agent_continuous": "learned continuous agent, shield for continuous actions",
}


def ceiling_markdown(table: dict[str, Any]) -> str:
    """The table as Markdown: one line per rate and row (speed [m/s], collisions, breaks, fallbacks; the committed
    shields' rows: plan-forced decisions, lapses and those in the model; continuous rows: episodes off the road)."""
    lines = [
        f"Episodes per cell: {table['episodes']} (reset seeds {table['seed']}+); planner horizon "
        f"{table['horizon_s']:g} s, beam {table['beam']}.",
        "",
        "| decisions/s | policy | mean speed [m/s] | collisions | invariant breaks | fallback rate | plan-forced "
        "rate | lapses (in the model) | off the road |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for rate, rows in table["rates"].items():
        for row, r in rows.items():
            committed = (
                f"{r['plan_forced_rate']:.4f} | {r['lapses']} ({r['lapses_in_model']})"
                if "plan_forced_rate" in r
                else "— | —"
            )
            off_road = f"{round(r['off_road_rate'] * r['episodes'])}/{r['episodes']}" if "off_road_rate" in r else "—"
            lines.append(
                f"| {rate} | {ROW_LABELS[row]} | {r['mean_speed']:.2f} | {r['collisions']}/{r['episodes']} | "
                f"{r['invariant_breaks']} | {r['fallback_rate']:.4f} | {committed} | {off_road} |"
            )
    return "\n".join(lines) + "\n"
