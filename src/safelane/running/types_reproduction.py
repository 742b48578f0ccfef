"""The price of robustness against hidden driver types, as one table (``safelane reproduce --preset hidden-types``).

Each **arm** is an agent and the shield it trains and is tested under. The agents: robust Q-masking
(``--method robust``) on each state of :data:`LEARNED` (``paper``: no types; ``paper-stack``; ``paper-belief``;
``paper-types``: the true types, the upper bound), and the fixed policies of :data:`FIXED` (always FASTER, random),
which the shield overrides. The shields: :data:`SHIELDS` (``robust``: the worst case over every type;
``belief``: the types above ε; ``omniscient``: the true types). ``run_table(spec, out_dir)`` trains every learned
(arm, seed) for ``spec.episodes`` episodes into ``out_dir/runs/AGENT.SHIELD-sSEED`` (resuming from the run's
checkpoint), drives its greedy policy on ``spec.test_episodes`` held-out episodes (seeds ``TEST_SEED_BASE + k``,
the discrete reproduction's) under its shield, and writes the run's ``eval.json``; a fixed policy is only tested.
Then ``results.json`` (atomically): per arm the IQM over seeds with its 95 % bootstrap interval of speed, crash
rate and fallback rate, the crashes with a car whose true type the belief had ruled out, and per agent the expense
of robustness (omniscient − robust speed) and the share of it the belief shield recovers; ``report.md`` from it
(:func:`write_types_report`). A run whose ``eval.json`` exists is not run again, so a killed table resumes.
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
from safelane.running.experiments import TEST_SEED_BASE, known_names, run_dir_of, run_then_collect
from safelane.running.reproduction_report import BOOTSTRAP_REPS

PRESET = "hidden-types"
LEARNED: dict[str, str] = {
    "paper": "robust Q-masking, eq. 3 (types hidden)",
    "paper-stack": "robust Q-masking, eq. 3 of the last 4 decisions",
    "paper-belief": "robust Q-masking, eq. 3 and each observed car's posterior over the types",
    "paper-types": "robust Q-masking, eq. 3 and the true types (the upper bound)",
}
"""The learned agents: the ``state:`` the DQN reads, and what it is."""
FIXED: dict[str, str] = {"faster": "always FASTER, the shield overriding", "random": "random, the shield overriding"}
"""The fixed policies (:func:`~safelane.running.policies.fixed_policy`), tested only."""
AGENTS: dict[str, str] = {**LEARNED, **FIXED}
SHIELDS: tuple[str, ...] = ("robust", "belief", "omniscient")
"""The shields (``shield.mode``), each agent's in training and in its test."""
QUICK_SEEDS, QUICK_EPISODES, QUICK_TEST_EPISODES = 2, 5, 3
"""``--quick``: at most these many seeds, training episodes and test episodes per run."""


def parse_names(text: str | None, allowed: dict[str, str] | tuple[str, ...], option: str) -> list[str]:
    """The names of a comma-separated ``option`` (``all`` or None: every allowed name, in order); an unknown or
    missing name is a one-line :class:`ConfigError` naming the allowed values."""
    names = list(allowed)
    if text is None or text.strip() == "all":
        return names
    given = [name.strip() for name in text.split(",") if name.strip()]
    for name in given:
        if name not in names:
            raise ConfigError(f"{option}: unknown name {name!r}; allowed with --preset {PRESET}: "
                              f"{', '.join(names)} or all")  # fmt: skip
    if not given:
        raise ConfigError(f"{option}: none given; allowed with --preset {PRESET}: {', '.join(names)} or all")
    return list(dict.fromkeys(given))


def arm_name(agent: str, shield: str) -> str:
    """An arm's name and run-directory prefix: ``AGENT.SHIELD``."""
    return f"{agent}.{shield}"


class TypesSpec(BaseModel):
    """What to run: agents × shields × seeds, training and test episodes (recorded as ``spec.json``)."""

    model_config = ConfigDict(extra="forbid")

    table: Literal["hidden-types"] = "hidden-types"
    agents: list[str] = Field(default_factory=lambda: list(AGENTS))
    shields: list[str] = Field(default_factory=lambda: list(SHIELDS))
    seeds: list[int] = Field(default_factory=lambda: [0, 1, 2, 3, 4])
    episodes: int = Field(200, ge=1, description="Training episodes per learned run (paper: 200).")
    test_episodes: int = Field(20, ge=1, description="Held-out test episodes per run.")
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

    def tasks(self) -> list[tuple[str, str, int]]:
        """Every (agent, shield, seed) run; always-FASTER is deterministic, so it runs on the first seed only."""
        return [(a, s, seed) for seed in self.seeds for a in self.agents for s in self.shields
                if a != "faster" or seed == self.seeds[0]]  # fmt: skip


def make_types_spec(**fields: Any) -> TypesSpec:
    """A :class:`TypesSpec`, raising a one-line :class:`ConfigError` on bad input."""
    try:
        return TypesSpec(**fields)
    except ValidationError as err:
        raise ConfigError(validation_message(err, TypesSpec, "reproduce.")) from None


def arm_sets(spec: TypesSpec, agent: str, shield: str) -> list[str]:
    """The ``--set`` strings of an arm's runs: the spec's, then the arm's state and shield (last: an arm is what
    its name says whatever ``--set`` asks); a fixed policy has the shield override its action."""
    sets = [*spec.sets, f"shield.mode={shield}"]
    if agent in LEARNED:
        return [*sets, f"state={agent}"]
    return [*sets, "shield.override=true"]


def train_config_of(spec: TypesSpec, agent: str, shield: str, seed: int) -> Any:
    """The :class:`~safelane.running.run_directory.TrainConfig` of a learned (``agent``, ``shield``, ``seed``) run."""
    from safelane.running.run_directory import make_train_config

    return make_train_config(
        method="robust",
        agent_preset=spec.agent_preset,
        env_preset=PRESET,
        episodes=spec.episodes,
        seed=seed,
        sets=arm_sets(spec, agent, shield),
        checkpoint_every=max(1, min(25, spec.episodes // 4)),
    )


def run_arm_task(out_dir: str, spec_json: str, agent: str, shield: str, seed: int) -> dict[str, Any]:
    """The backend's task: train (or resume) and test the (``agent``, ``shield``, ``seed``) run of ``spec_json``
    under ``out_dir``; returns its evaluation record (also ``eval.json`` in the run directory)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one run per core: the workers share the machine
    try:
        return _train_and_test(Path(out_dir), TypesSpec.model_validate_json(spec_json), agent, shield, seed)
    finally:
        torch.set_num_threads(threads)


def _train_and_test(out: Path, spec: TypesSpec, agent: str, shield: str, seed: int) -> dict[str, Any]:
    from safelane.config import load_config
    from safelane.reporting.metrics_file import METRICS_FILE, read_metrics
    from safelane.running.evaluation import run_config, summarize
    from safelane.running.policies import fixed_policy
    from safelane.running.run_directory import load_policy, load_run_config
    from safelane.running.runs import run_env_config
    from safelane.running.training import train

    run_dir = run_dir_of(out, arm_name(agent, shield), seed)
    eval_path = run_dir / "eval.json"
    if eval_path.exists():
        return dict(json.loads(eval_path.read_text()))
    train_time = 0.0
    if agent in LEARNED:
        resume = (run_dir / "checkpoint.pt").exists()
        if not resume and run_dir.exists():  # killed before its first checkpoint: nothing to resume
            shutil.rmtree(run_dir)
        train(train_config_of(spec, agent, shield, seed), run_dir, resume=resume)
        # The run's own clock: cumulative over resumes (a perf_counter here would count only the last part).
        train_time = float(read_metrics(run_dir / METRICS_FILE, ["wall_time_s"])["wall_time_s"][-1])
        config = run_env_config(load_run_config(run_dir))
        policy = load_policy(run_dir)
    else:
        run_dir.mkdir(parents=True, exist_ok=True)
        config = load_config(PRESET, sets=arm_sets(spec, agent, shield))
        policy = fixed_policy(agent, seed)
    start = time.perf_counter()
    records = run_config(config, policy, spec.test_episodes, TEST_SEED_BASE)
    record = {
        "agent": agent,
        "shield": shield,
        "seed": seed,
        "summary": summarize(records, method=arm_name(agent, shield), seed=seed, simulator=config.simulator),
        "train_wall_time_s": train_time,
        "eval_wall_time_s": time.perf_counter() - start,
    }
    atomic_write_text(eval_path, json.dumps(record))
    return record


def _validate(spec: TypesSpec) -> None:
    """Resolve every arm's configuration once: a bad ``--set`` fails here in one line, not once per task."""
    from safelane.config import load_config
    from safelane.running.run_directory import resolve

    for agent in spec.agents:
        for shield in spec.shields:
            if agent in LEARNED:
                resolve(train_config_of(spec, agent, shield, spec.seeds[0]))
            else:
                load_config(PRESET, sets=arm_sets(spec, agent, shield))


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
    claim_out_dir(out, spec.model_dump_json(indent=2), "spec.json", "reproduction")
    tasks = spec.tasks()
    return run_then_collect(
        run_arm_task, tasks, out, spec.model_dump_json(), lambda t: f"{arm_name(t[0], t[1])} seed {t[2]}",
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


def collect(out_dir: Path, spec: TypesSpec) -> dict[str, Any]:
    """Every run's evaluation gathered into one dict: per-run rows, per-arm aggregates over seeds and, per agent,
    the expense of robustness (:func:`expense_of_robustness`)."""
    arms: dict[str, Any] = {}
    expense: dict[str, Any] = {}
    for agent in spec.agents:
        speeds: dict[str, dict[str, float]] = {}
        for shield in spec.shields:
            per_seed: dict[str, Any] = {}
            for seed in spec.seeds:
                path = run_dir_of(out_dir, arm_name(agent, shield), seed) / "eval.json"
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
    return {"spec": spec.model_dump(), "arms": arms, "expense_of_robustness": expense}


# --- the report -------------------------------------------------------------------------------------------------
def _est(agg: dict[str, Any], key: str, digits: int, scale: float = 1.0) -> str:
    a = agg[key]
    lo, hi = a["ci95"]
    return f"{a['iqm'] * scale:.{digits}f} [{lo * scale:.{digits}f}, {hi * scale:.{digits}f}]"


def arms_table(arms: dict[str, Any], spec: TypesSpec) -> list[str]:
    """Markdown rows, grouped by shield: per agent the runs, crashes / test episodes (those with a ruled-out true
    type), the IQM over seeds with its 95 % interval of speed, crash rate and fallback rate, and the time per run."""
    lines = [
        "| shield | agent | runs | crashes / test episodes | crashes, true type ruled out | test speed [m/s] "
        "| crash rate [%] | fallback rate [% of decisions] | training / test time per run [s] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for shield in spec.shields:
        for agent in spec.agents:
            data = arms.get(arm_name(agent, shield))
            if data is None:
                continue
            a = data["aggregate"]
            ruled_out = "–" if a["collisions_type_ruled_out"] is None else str(a["collisions_type_ruled_out"])
            train = f"{a['train_wall_time_s']:.1f}" if agent in LEARNED else "–"
            lines.append(
                f"| `{shield}` | `{agent}` | {len(data['per_seed'])} | {a['collisions']} / {a['test_episodes']} | "
                f"{ruled_out} | {_est(a, 'mean_speed', 2)} | {_est(a, 'collision_rate', 2, 100)} | "
                f"{_est(a, 'fallback_rate', 2, 100)} | {train} / {a['eval_wall_time_s']:.1f} |"
            )
    return lines


def expense_table(expense: dict[str, Any]) -> list[str]:
    """Markdown rows: per agent the expense of robustness and what the belief shield recovers of it."""
    lines = [
        "| agent | seeds | omniscient − robust speed [m/s] | belief − robust [m/s] | share belief recovers |",
        "|---|---|---|---|---|",
    ]
    for agent, e in expense.items():
        lo, hi = e["expense"]["ci95"]
        b = e.get("belief_recovers")
        speed = f"{b['speed']:+.2f}" if b else "–"
        share = "–"
        if b and np.isfinite(b["share"]):
            share = f"{b['share']:.0%} [{b['share_ci95'][0]:.0%}, {b['share_ci95'][1]:.0%}]"
        lines.append(f"| `{agent}` | {e['seeds']} | {e['expense']['point']:+.2f} [{lo:+.2f}, {hi:+.2f}] | {speed} "
                     f"| {share} |")  # fmt: skip
    return lines


def write_types_report(out_dir: str | Path) -> Path:
    """Write ``report.md`` from ``out_dir/results.json`` (atomically); returns its path."""
    out = Path(out_dir)
    results = json.loads((out / "results.json").read_text())
    spec = TypesSpec.model_validate(results["spec"])
    arms = results["arms"]
    train_total = sum(p["train_wall_time_s"] for d in arms.values() for p in d["per_seed"].values())
    lines = [
        "# safelane reproduction report: the price of robustness against hidden driver types",
        "",
        f"Preset `{PRESET}`{' with ' + ', '.join(f'`{s}`' for s in spec.sets) if spec.sets else ''}; agents "
        f"{', '.join(spec.agents)}; shields {', '.join(spec.shields)}; seeds {spec.seeds}; {spec.episodes} training "
        f"episodes per learned run (robust Q-masking, agent preset `{spec.agent_preset}`, trained under the shield "
        f"it is tested under); {spec.test_episodes} held-out test episodes per run (seeds {TEST_SEED_BASE} + k); "
        "always-FASTER on the first seed only (it is deterministic)"
        + (" — **quick mode: too few seeds and episodes for conclusions**" if spec.quick else "")
        + f". Training time summed over runs: {train_total:.0f} s; this invocation: "
        f"{results.get('wall_time_s', float('nan')):.0f} s.",
        "",
        "## Test episodes",
        "",
        "Each run contributes one score per column (its mean over its test episodes); the table gives the "
        f"interquartile mean (IQM) over runs with its 95 % stratified bootstrap interval ({BOOTSTRAP_REPS} samples, "
        "seed 0; with fewer than 4 runs the IQM is the mean), after Agarwal et al. (2021). Fallback rate: decisions "
        "without a safe action ÷ decisions. The `belief` shield's promise is probabilistic: its crashes with a car "
        "whose true type had been ruled out (posterior ≤ ε) are counted apart (– under the other shields).",
        "",
        *arms_table(arms, spec),
        "",
        "## The expense of robustness",
        "",
        "Per agent, the IQM test speed under the `omniscient` shield (each car's true type) minus under the "
        "`robust` one (every type), and how much of it the `belief` shield recovers: (belief − robust) ÷ "
        "(omniscient − robust). Intervals: 95 % percentiles over resamples of the seeds, the shields' drawn "
        "together (a resample with no positive expense has no share).",
        "",
        *expense_table(results["expense_of_robustness"]),
        "",
        "## Agents",
        "",
        *[f"- `{agent}`: {AGENTS[agent]}" for agent in spec.agents],
    ]
    report = out / "report.md"
    atomic_write_text(report, "\n".join(lines) + "\n")
    return report
