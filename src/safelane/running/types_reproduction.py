"""The price of robustness against hidden driver types, as one table per scenario (``safelane reproduce --preset
hidden-types``).

Each **arm** is an agent and the shield it trains and is tested under. The agents: robust Q-masking
(``--method robust``) on each state of :data:`LEARNED` (``paper``: no types; ``paper-stack``; ``paper-belief``;
``paper-types``: the true types, the upper bound), and the fixed policies of :data:`FIXED` (always FASTER, random),
which the shield overrides. The shields: :data:`SHIELDS` (``robust``: the worst case over every type;
``belief``: the types above ε; ``omniscient``: the true types). The **scenarios** (:data:`SCENARIOS`) are the
traffic the arms drive in: ``paper`` (the preset as it is) on ``spec.seeds`` with ``spec.test_episodes`` test
episodes per run, each other one (:data:`SCENARIO_SETS`: denser, more aggressive, three decisions a second) on
``spec.scenario_seeds`` with ``spec.scenario_test_episodes``. ``run_table(spec, out_dir)`` trains every learned
(scenario, arm, seed) for ``spec.episodes`` episodes into :func:`types_run_dir` (``runs/AGENT.SHIELD-sSEED`` for
``paper``, ``runs/SCENARIO/AGENT.SHIELD-sSEED`` for another; resuming from the run's checkpoint), drives its greedy
policy on the held-out test episodes (seeds ``TEST_SEED_BASE + k``, the discrete reproduction's) under its shield,
and writes the run's ``eval.json``; a fixed policy is only tested. Then ``results.json`` (atomically): per scenario
and arm the IQM over seeds with its 95 % bootstrap interval of speed, crash rate and fallback rate, the crashes
with a car whose true type the belief had ruled out, and per agent the expense of robustness (omniscient − robust
speed) and the share of it the belief shield recovers; ``report.md`` and the learning curves from it
(:func:`safelane.running.types_report.write_types_report`). A run whose ``eval.json`` exists is not run again, so
a killed table resumes; so does a folder of a table from before the scenarios (its runs are the ``paper`` ones).
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from safelane.config import ConfigError, validation_message
from safelane.core.files import atomic_write_text
from safelane.reporting import stats
from safelane.running.backend import check_backend, claim_out_dir
from safelane.running.experiments import (
    TEST_SEED_BASE,
    known_names,
    parse_name_list,
    run_dir_of,
    run_then_collect,
)
from safelane.running.reproduction_report import BOOTSTRAP_REPS

PRESET = "hidden-types"
LEARNED: dict[str, str] = {
    "paper": "robust Q-masking, eq. 3 (types hidden)",
    "paper-stack": "robust Q-masking, eq. 3 of the last 4 decisions",
    "paper-belief": "robust Q-masking, eq. 3 and each observed car's posterior over the types",
    "paper-types": "robust Q-masking, eq. 3 and the true types (the upper bound)",
    "paper-recurrent": "robust Q-masking on a GRU over eq. 3's decisions (--method robust-recurrent)",
}
"""The learned agents: the ``state:`` the DQN reads (a recurrent one's: :data:`RECURRENT`), and what it is."""
RECURRENT: dict[str, str] = {"paper-recurrent": "paper"}
"""The learned agents on a recurrent Q-network (``--method robust-recurrent``), and the ``state:`` each reads."""
FIXED: dict[str, str] = {
    "faster": "always FASTER, the shield overriding",
    "random": "random, the shield overriding",
    "foresight": "perfect foresight under the shield's mask: its ceiling (robust and omniscient only)",
}
"""The policies tested only: the fixed ones (:func:`~safelane.running.policies.fixed_policy`) and the perfect-foresight
planner (:class:`~safelane.running.foresight.ForesightPlanner`, searching under the arm's mask; the ``belief`` mask
would need its filter along every branch of the search, so that arm is not played)."""
AGENTS: dict[str, str] = {**LEARNED, **FIXED}
DETERMINISTIC: tuple[str, ...] = ("faster", "foresight")
"""The agents played on a scenario's first seed only: the same episodes give the same actions."""
PLANNER_SHIELDS: tuple[str, ...] = ("robust", "omniscient")
"""The shields whose masks the planner searches under."""
SHIELDS: tuple[str, ...] = ("robust", "belief", "omniscient")
"""The shields (``shield.mode``), each agent's in training and in its test."""
QUICK_SEEDS, QUICK_EPISODES, QUICK_TEST_EPISODES = 2, 5, 3
"""``--quick``: at most these many seeds, training episodes and test episodes per run (in every scenario)."""
PAPER_SCENARIO = "paper"
SCENARIOS: dict[str, str] = {
    PAPER_SCENARIO: "the preset as it is: 4 lanes, density 1, timid, normal and aggressive drivers 1/3 each, "
    "1 decision/s",
    "dense": "twice the traffic density (env.vehicles_density=2)",
    "aggressive": "timid, normal and aggressive drivers weighted 1/1/3 (traffic.driver_mix)",
    "rate3": "3 decisions/s on 15 Hz physics (env.policy_frequency=3, env.simulation_frequency=15)",
}
"""The scenarios of the table, each a name and what its traffic is."""
SCENARIO_SETS: dict[str, tuple[str, ...]] = {
    PAPER_SCENARIO: (),
    "dense": ("env.vehicles_density=2",),
    "aggressive": (
        "traffic.driver_mix=[{type: timid, weight: 1}, {type: normal, weight: 1}, {type: aggressive, weight: 3}]",
    ),
    "rate3": ("env.policy_frequency=3", "env.simulation_frequency=15"),
}
"""Each scenario's ``--set`` strings on the preset (applied before ``--set`` and the arm's own)."""
SCENARIO_SEEDS, SCENARIO_TEST_EPISODES = 3, 200
"""The default budget of a scenario other than ``paper``: seeds and test episodes per run."""


def parse_names(text: str | None, allowed: dict[str, str] | tuple[str, ...], option: str) -> list[str]:
    """The names of a comma-separated ``option`` (``all`` or None: every allowed name, in order); an unknown or
    missing name is a one-line :class:`ConfigError` naming the allowed values."""
    return parse_name_list("all" if text is None else text, allowed, option, "name", f"--preset {PRESET}")


def arm_name(agent: str, shield: str) -> str:
    """An arm's name and run-directory prefix: ``AGENT.SHIELD``."""
    return f"{agent}.{shield}"


def types_run_dir(out_dir: Path, scenario: str, agent: str, shield: str, seed: int) -> Path:
    """The directory of a (scenario, agent, shield, seed) run: ``runs/AGENT.SHIELD-sSEED`` for ``paper`` (where a
    table from before the scenarios has its runs, so it resumes), ``runs/SCENARIO/AGENT.SHIELD-sSEED`` else."""
    if scenario == PAPER_SCENARIO:
        return run_dir_of(out_dir, arm_name(agent, shield), seed)
    return out_dir / "runs" / scenario / f"{arm_name(agent, shield)}-s{seed}"


class TypesSpec(BaseModel):
    """What to run: scenarios × agents × shields × seeds, training and test episodes (recorded as ``spec.json``).
    ``seeds`` and ``test_episodes`` are the ``paper`` scenario's, ``scenario_seeds`` and ``scenario_test_episodes``
    every other one's; every learned run trains for ``episodes``."""

    model_config = ConfigDict(extra="forbid")

    table: Literal["hidden-types"] = "hidden-types"
    agents: list[str] = Field(default_factory=lambda: list(AGENTS))
    shields: list[str] = Field(default_factory=lambda: list(SHIELDS))
    seeds: list[int] = Field(default_factory=lambda: [0, 1, 2, 3, 4])
    episodes: int = Field(200, ge=1, description="Training episodes per learned run (paper: 200).")
    test_episodes: int = Field(20, ge=1, description="Held-out test episodes per run of the paper scenario.")
    scenarios: list[str] = Field(default_factory=lambda: [PAPER_SCENARIO], min_length=1)
    scenario_seeds: list[int] = Field(default_factory=lambda: list(range(SCENARIO_SEEDS)), min_length=1)
    scenario_test_episodes: int = Field(
        SCENARIO_TEST_EPISODES, ge=1, description="Held-out test episodes per run of every other scenario."
    )
    agent_preset: str = "tuned"
    sets: list[str] = Field(default_factory=list, description="--set overrides for every run (before the arm's).")
    quick: bool = False

    @field_validator("agents")
    @classmethod
    def _known_agents(cls, agents: list[str]) -> list[str]:
        return known_names(agents, AGENTS, "agent")

    @field_validator("shields")
    @classmethod
    def _known_shields(cls, shields: list[str]) -> list[str]:
        return known_names(shields, SHIELDS, "shield")

    @field_validator("scenarios")
    @classmethod
    def _known_scenarios(cls, scenarios: list[str]) -> list[str]:
        return known_names(scenarios, SCENARIOS, "scenario")

    def seeds_of(self, scenario: str) -> list[int]:
        """The seeds of ``scenario``'s runs."""
        return self.seeds if scenario == PAPER_SCENARIO else self.scenario_seeds

    def test_episodes_of(self, scenario: str) -> int:
        """The held-out test episodes of each of ``scenario``'s runs."""
        return self.test_episodes if scenario == PAPER_SCENARIO else self.scenario_test_episodes

    def tasks(self) -> list[tuple[str, str, str, int]]:
        """Every (scenario, agent, shield, seed) run, scenario by scenario; always-FASTER is deterministic, so it
        runs on a scenario's first seed only."""
        return [(sc, a, s, seed) for sc in self.scenarios for seed in self.seeds_of(sc) for a in self.agents
                for s in self.shields
                if (a not in DETERMINISTIC or seed == self.seeds_of(sc)[0])
                and (a != "foresight" or s in PLANNER_SHIELDS)]  # fmt: skip


def make_types_spec(**fields: Any) -> TypesSpec:
    """A :class:`TypesSpec`, raising a one-line :class:`ConfigError` on bad input."""
    try:
        return TypesSpec(**fields)
    except ValidationError as err:
        raise ConfigError(validation_message(err, TypesSpec, "reproduce.")) from None


def arm_sets(spec: TypesSpec, scenario: str, agent: str, shield: str) -> list[str]:
    """The ``--set`` strings of an arm's runs in ``scenario``: the scenario's, the spec's, then the arm's state and
    shield (last: an arm is what its name says whatever ``--set`` asks); a fixed policy has the shield override its
    action."""
    sets = [*SCENARIO_SETS[scenario], *spec.sets, f"shield.mode={shield}"]
    if agent in LEARNED:
        return [*sets, f"state={RECURRENT.get(agent, agent)}"]
    return [*sets, "shield.override=true"]


def train_config_of(spec: TypesSpec, scenario: str, agent: str, shield: str, seed: int) -> Any:
    """The :class:`~safelane.running.run_directory.TrainConfig` of a learned (``scenario``, ``agent``, ``shield``,
    ``seed``) run."""
    from safelane.running.run_directory import make_train_config

    return make_train_config(
        method="robust-recurrent" if agent in RECURRENT else "robust",
        agent_preset=spec.agent_preset,
        env_preset=PRESET,
        episodes=spec.episodes,
        seed=seed,
        sets=arm_sets(spec, scenario, agent, shield),
        checkpoint_every=max(1, min(25, spec.episodes // 4)),
    )


def run_arm_task(out_dir: str, spec_json: str, scenario: str, agent: str, shield: str, seed: int) -> dict[str, Any]:
    """The backend's task: train (or resume) and test the (``scenario``, ``agent``, ``shield``, ``seed``) run of
    ``spec_json`` under ``out_dir``; returns its evaluation record (also ``eval.json`` in the run directory)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one run per core: the workers share the machine
    try:
        spec = TypesSpec.model_validate_json(spec_json)
        return _train_and_test(Path(out_dir), spec, scenario, agent, shield, seed)
    finally:
        torch.set_num_threads(threads)


def _train_and_test(out: Path, spec: TypesSpec, scenario: str, agent: str, shield: str, seed: int) -> dict[str, Any]:
    from safelane.config import load_config
    from safelane.reporting.metrics_file import METRICS_FILE, read_metrics
    from safelane.running.evaluation import run_config, summarize
    from safelane.running.policies import fixed_policy
    from safelane.running.run_directory import load_policy, load_run_config
    from safelane.running.runs import run_env_config
    from safelane.running.training import train

    run_dir = types_run_dir(out, scenario, agent, shield, seed)
    eval_path = run_dir / "eval.json"
    if eval_path.exists():
        return dict(json.loads(eval_path.read_text()))
    train_time = 0.0
    if agent in LEARNED:
        resume = (run_dir / "checkpoint.pt").exists()
        if not resume and run_dir.exists():  # killed before its first checkpoint: nothing to resume
            shutil.rmtree(run_dir)
        train(train_config_of(spec, scenario, agent, shield, seed), run_dir, resume=resume)
        # The run's own clock: cumulative over resumes (a perf_counter here would count only the last part).
        train_time = float(read_metrics(run_dir / METRICS_FILE, ["wall_time_s"])["wall_time_s"][-1])
        config = run_env_config(load_run_config(run_dir))
        policy = load_policy(run_dir)
    else:
        run_dir.mkdir(parents=True, exist_ok=True)
        config = load_config(PRESET, sets=arm_sets(spec, scenario, agent, shield))
        policy = None if agent == "foresight" else fixed_policy(agent, seed)
    start = time.perf_counter()
    if policy is None:
        records = _foresight_records(config, shield, spec.test_episodes_of(scenario))
    else:
        records = run_config(config, policy, spec.test_episodes_of(scenario), TEST_SEED_BASE)
    record = {
        "scenario": scenario,
        "agent": agent,
        "shield": shield,
        "seed": seed,
        "summary": summarize(records, method=arm_name(agent, shield), seed=seed, simulator=config.simulator),
        "train_wall_time_s": train_time,
        "eval_wall_time_s": time.perf_counter() - start,
    }
    atomic_write_text(eval_path, json.dumps(record))
    return record


def _foresight_records(config: Any, shield: str, episodes: int) -> list[Any]:
    """The perfect-foresight planner's held-out episodes under the ``shield``'s mask (its default search, on the
    fast simulator: it copies the simulator's state), the shield overriding nothing it allows."""
    from safelane.env.factory import make_env
    from safelane.running.evaluation import run_episodes
    from safelane.running.foresight import ForesightPlanner, planner_policy

    env = make_env(config)
    try:
        planner = ForesightPlanner(env, mask=shield)  # type: ignore[arg-type]
        return run_episodes(env, planner_policy(planner), episodes, TEST_SEED_BASE)
    finally:
        env.close()


def _validate(spec: TypesSpec) -> None:
    """Resolve every arm's configuration once: a bad ``--set`` fails here in one line, not once per task."""
    from safelane.config import load_config
    from safelane.running.run_directory import resolve

    for scenario in spec.scenarios:
        for agent in spec.agents:
            for shield in spec.shields:
                if agent in LEARNED:
                    resolve(train_config_of(spec, scenario, agent, shield, spec.seeds_of(scenario)[0]))
                else:
                    load_config(PRESET, sets=arm_sets(spec, scenario, agent, shield))


def _keep_earlier_spec_file(out: Path, spec: TypesSpec) -> None:
    """Rewrite ``out/spec.json`` in today's form where it holds a table from before the scenarios (no
    ``scenarios`` field: its runs are the ``paper`` ones) that ``spec``, of the ``paper`` scenario only, continues,
    so that :func:`claim_out_dir` lets it resume."""
    path = out / "spec.json"
    if spec.scenarios != [PAPER_SCENARIO] or not path.is_file():
        return
    try:
        earlier = json.loads(path.read_text())
    except (OSError, ValueError):
        return  # not a spec: claim_out_dir refuses the folder
    scenario_fields = {"scenarios", "scenario_seeds", "scenario_test_episodes"}
    if not isinstance(earlier, dict) or scenario_fields & set(earlier):
        return
    if earlier == json.loads(spec.model_dump_json(exclude=scenario_fields)):
        atomic_write_text(path, spec.model_dump_json(indent=2))


def run_table(
    spec: TypesSpec,
    out_dir: str | Path,
    workers: int | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
    backend: str = "local",
    address: str | None = None,
) -> dict[str, Any]:
    """Run every (agent, shield, seed) not yet done on ``backend`` (:mod:`safelane.running.backend`), then collect
    all into ``out_dir/results.json``; a folder holding another spec is refused in one line."""
    check_backend(backend)
    out = Path(out_dir)
    _validate(spec)
    _keep_earlier_spec_file(out, spec)
    claim_out_dir(out, spec.model_dump_json(indent=2), "spec.json", "reproduction")
    tasks = spec.tasks()
    return run_then_collect(
        run_arm_task, tasks, out, spec.model_dump_json(), lambda t: f"{t[0]}: {arm_name(t[1], t[2])} seed {t[3]}",
        lambda: collect(out, spec), "reproduce-hidden-types", time.perf_counter(), backend=backend, workers=workers,
        address=address, progress=progress,
    )  # fmt: skip


SCORES: tuple[str, ...] = ("mean_speed", "collision_rate", "fallback_rate", "shield_intervention_rate")
"""Per-run scores aggregated over seeds in ``results.json`` (IQM with a 95 % stratified bootstrap interval)."""


def _run_scores(rec: dict[str, Any]) -> dict[str, Any]:
    """One run's row of ``results.json`` from its ``eval.json``."""
    s = rec["summary"]
    row = {key: s[key] for key in ("episodes", "decisions", "collisions", *SCORES)}
    # Counted by the belief shield only: crashes with a car whose true type it had ruled out (None elsewhere).
    row["collisions_type_ruled_out"] = s.get("collisions_type_ruled_out")
    row["invariant_breaks"] = s["invariant_breaks"]
    row["train_wall_time_s"] = rec["train_wall_time_s"]
    row["eval_wall_time_s"] = rec["eval_wall_time_s"]
    return row


def _aggregate(per_seed: dict[str, Any]) -> dict[str, Any]:
    runs = list(per_seed.values())
    agg: dict[str, Any] = {}
    for key in SCORES:
        values = [v[key] for v in runs]
        est = stats.stratified_bootstrap(values, stats.iqm, reps=BOOTSTRAP_REPS, seed=0)
        agg[key] = {"iqm": est.point, "ci95": [est.low, est.high], "mean": stats.mean(values)}
    for key in ("collisions", "invariant_breaks", "decisions"):
        agg[key] = sum(v[key] for v in runs)
    ruled_out = [v["collisions_type_ruled_out"] for v in runs if v["collisions_type_ruled_out"] is not None]
    agg["collisions_type_ruled_out"] = sum(ruled_out) if ruled_out else None
    agg["test_episodes"] = sum(v["episodes"] for v in runs)
    agg["collision_rate_wilson95"] = list(stats.binomial_ci(agg["collisions"], agg["test_episodes"]))
    agg["train_wall_time_s"] = stats.mean([v["train_wall_time_s"] for v in runs])
    agg["eval_wall_time_s"] = stats.mean([v["eval_wall_time_s"] for v in runs])
    return agg


def expense_of_robustness(speeds: dict[str, dict[str, float]], reps: int = BOOTSTRAP_REPS) -> dict[str, Any] | None:
    """From each shield's per-seed test speed [m/s] (``speeds[shield][seed]``): the expense of robustness, the IQM
    over seeds of the omniscient arm's speed − the robust arm's, and the share of it the belief arm recovers,
    (IQM belief − IQM robust) ÷ (IQM omniscient − IQM robust); each with a 95 % percentile interval from ``reps``
    resamples of the seeds the shields share, drawn together (a resample whose expense is not positive has no
    share: the interval is over the others). None without both the robust and the omniscient arm."""
    if "robust" not in speeds or "omniscient" not in speeds:
        return None
    shields = [s for s in SHIELDS if s in speeds]
    seeds = sorted(set.intersection(*(set(speeds[s]) for s in shields)))
    if not seeds:
        return None
    table = {s: np.array([speeds[s][k] for k in seeds]) for s in shields}

    def figures(rows: np.ndarray) -> tuple[float, float]:
        iqm = {s: stats.iqm(table[s][rows]) for s in shields}
        expense = iqm["omniscient"] - iqm["robust"]
        if "belief" not in iqm or expense <= 0:
            return expense, float("nan")
        return expense, (iqm["belief"] - iqm["robust"]) / expense

    rng = np.random.default_rng(0)
    draws = np.array([figures(rng.integers(len(seeds), size=len(seeds))) for _ in range(reps)])
    expense, share = figures(np.arange(len(seeds)))
    result: dict[str, Any] = {"seeds": len(seeds), "expense": {"point": expense,
                              "ci95": np.percentile(draws[:, 0], [2.5, 97.5]).tolist()}}  # fmt: skip
    if "belief" in table:
        shares = draws[:, 1][np.isfinite(draws[:, 1])]
        ci = np.percentile(shares, [2.5, 97.5]).tolist() if shares.size else [float("nan")] * 2
        result["belief_recovers"] = {"speed": stats.iqm(table["belief"]) - stats.iqm(table["robust"]),
                                     "share": share, "share_ci95": ci}  # fmt: skip
    return result


def collect_scenario(out_dir: Path, spec: TypesSpec, scenario: str) -> dict[str, Any]:
    """One scenario's evaluations gathered: what it is, per-run rows, per-arm aggregates over seeds and, per agent,
    the expense of robustness (:func:`expense_of_robustness`)."""
    arms: dict[str, Any] = {}
    expense: dict[str, Any] = {}
    for agent in spec.agents:
        speeds: dict[str, dict[str, float]] = {}
        for shield in spec.shields:
            per_seed: dict[str, Any] = {}
            for seed in spec.seeds_of(scenario):
                path = types_run_dir(out_dir, scenario, agent, shield, seed) / "eval.json"
                if path.exists():
                    per_seed[str(seed)] = _run_scores(json.loads(path.read_text()))
            if not per_seed:
                continue
            speeds[shield] = {k: v["mean_speed"] for k, v in per_seed.items()}
            arms[arm_name(agent, shield)] = {"agent": agent, "shield": shield, "label": AGENTS[agent],
                                             "per_seed": per_seed, "aggregate": _aggregate(per_seed)}  # fmt: skip
        figures = expense_of_robustness(speeds)
        if figures is not None:
            expense[agent] = figures
    return {
        "description": SCENARIOS[scenario],
        "sets": list(SCENARIO_SETS[scenario]),
        "seeds": spec.seeds_of(scenario),
        "test_episodes": spec.test_episodes_of(scenario),
        "arms": arms,
        "expense_of_robustness": expense,
    }


def collect(out_dir: Path, spec: TypesSpec) -> dict[str, Any]:
    """Every run's evaluation gathered into one dict: the spec and, per scenario, :func:`collect_scenario`."""
    return {"spec": spec.model_dump(), "scenarios": {sc: collect_scenario(out_dir, spec, sc) for sc in spec.scenarios}}
