"""The comparison of continuous agents, bare and under the shield, with one command
(``safelane reproduce --actions continuous``).

Each **arm** is an SB3 algorithm (:mod:`safelane.agents.continuous`) and how the shield for continuous actions
stands between it and the road (:data:`ARMS`: none; ``projection``; ``replacement``; projection with the
adaptation penalty). ``run_comparison(spec, out_dir)`` trains every (arm, seed) for ``spec.decisions`` decisions
into ``out_dir/runs/ARM-sSEED`` (:func:`~safelane.running.continuous_training.train_continuous`, which resumes from
the run's checkpoint), drives its deterministic policy on ``spec.test_episodes`` held-out episodes (seeds
``TEST_SEED_BASE + k``, never trained on) in the run's own environment — a shielded arm under its shield — and
writes the run's ``eval.json``; then ``results.json`` (atomically) and :func:`write_comparison_report`'s
``report.md`` with ``learning_curves.png``. A run whose ``eval.json`` exists is not trained again, so a killed
comparison resumes where it stopped (the discrete reproduction's protocol: :mod:`safelane.running.experiments`).
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np
from matplotlib.figure import Figure
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from safelane.config import ConfigError, validation_message
from safelane.core.files import atomic_write_text
from safelane.reporting import stats
from safelane.reporting.plots import plot_curve_bands
from safelane.running.backend import check_backend, claim_out_dir
from safelane.running.experiments import (
    TEST_SEED_BASE,
    known_names,
    parse_name_list,
    run_dir_of,
    run_then_collect,
)
from safelane.running.reproduction_report import BOOTSTRAP_REPS


class Arm(NamedTuple):
    """One arm of the comparison: the algorithm and the shield it trains and is tested under."""

    algo: str  # safelane.agents.continuous.ALGOS
    intervention: str | None  # shield.intervention, None: no shield
    penalised: bool  # projection with the adaptation penalty (weight: ContinuousSpec.penalty_weight)
    label: str


def _arms() -> dict[str, Arm]:
    names = {"sac": "SAC", "ppo": "PPO", "sac-lagrangian": "Lagrangian SAC"}
    arms: dict[str, Arm] = {}
    for algo, name in names.items():
        arms[algo] = Arm(algo, None, False, name)
    for algo, name in names.items():
        arms[f"{algo}-projection"] = Arm(algo, "projection", False, f"{name}, shield by projection")
        arms[f"{algo}-replacement"] = Arm(algo, "replacement", False, f"{name}, shield by replacement")
        arms[f"{algo}-penalty"] = Arm(algo, "projection", True, f"{name}, projection + adaptation penalty")
    return arms


ARMS: dict[str, Arm] = _arms()
"""Every arm ``--methods`` may name: each algorithm bare (``sac``, ``ppo``, ``sac-lagrangian``) and under the shield
(``ALGO-projection``, ``ALGO-replacement``, ``ALGO-penalty``)."""
DEFAULT_ARMS: tuple[str, ...] = ("sac", "ppo", "sac-lagrangian", "sac-projection", "sac-replacement", "sac-penalty")
"""The arms run when ``--methods`` is left out: the three learners bare and SAC under each way of shielding (the
others, e.g. ``ppo-projection``, on request; ``all`` runs every arm)."""
DEFAULT_DECISIONS = 50_000
"""Training decisions per run by default: past the plateau SAC reaches by 10 000 decisions on one seed, and 50
updates of the Lagrangian SAC's λ (the measured budget estimate in docs/guides/continuous-agents.md). PPO gets the
same budget for a like-for-like table although one 10⁵-decision run of it still left the road."""
PENALTY_WEIGHT = 0.5
"""Weight of the adaptation penalty of the ``*-penalty`` arms (reward minus weight × projection distance)."""
QUICK_SEEDS, QUICK_DECISIONS, QUICK_TEST_EPISODES = 2, 600, 5
"""``--quick``: at most these many seeds, training decisions and test episodes per run (small networks too)."""
QUICK_AGENT_SETS: dict[str, list[str]] = {
    "sac": ["agent.learning_starts=100", "agent.batch_size=32", "agent.net_arch=[32, 32]"],
    "ppo": ["agent.n_steps=128", "agent.batch_size=32", "agent.n_epochs=2", "agent.net_arch=[32, 32]"],
}
"""``--quick``: agent settings small enough for seconds per run (a replay buffer the size of the run, too)."""
QUICK_AGENT_SETS["sac-lagrangian"] = [*QUICK_AGENT_SETS["sac"], "agent.lambda_update_interval=100"]
CURVE_POINTS = 50
"""Points of each run's learning curve, evenly spaced in training decisions."""
CURVE_WINDOW = 0.1
"""Each learning-curve point averages the episodes that ended in the trailing window of this fraction of the run."""


def parse_arms(text: str | None) -> list[str]:
    """The arms ``--methods`` names: comma-separated arm names, ``all`` (every arm) or None (:data:`DEFAULT_ARMS`);
    an unknown name is a one-line :class:`ConfigError` naming the allowed values."""
    if text is None:
        return list(DEFAULT_ARMS)
    return parse_name_list(text, ARMS, "--methods", "arm", "--actions continuous")


class ContinuousSpec(BaseModel):
    """What to run: arms × seeds, training decisions and test episodes (recorded as ``spec.json``)."""

    model_config = ConfigDict(extra="forbid")

    actions: Literal["continuous"] = "continuous"
    arms: list[str] = Field(default_factory=lambda: list(DEFAULT_ARMS))
    seeds: list[int] = Field(default_factory=lambda: [0, 1, 2, 3, 4])
    decisions: int = Field(DEFAULT_DECISIONS, ge=1, description="Training decisions per run.")
    test_episodes: int = Field(20, ge=1, description="Held-out test episodes per run.")
    env_preset: Literal["fast", "paper"] = "fast"
    sets: list[str] = Field(default_factory=list, description="--set overrides for every run (before the arm's).")
    penalty_weight: float = Field(PENALTY_WEIGHT, ge=0, description="The *-penalty arms' adaptation penalty.")
    quick: bool = False

    @field_validator("arms")
    @classmethod
    def _known_arms(cls, arms: list[str]) -> list[str]:
        return known_names(arms, ARMS, "arm")


def make_continuous_spec(**fields: Any) -> ContinuousSpec:
    """A :class:`ContinuousSpec`, raising a one-line :class:`ConfigError` on bad input."""
    try:
        return ContinuousSpec(**fields)
    except ValidationError as err:
        raise ConfigError(validation_message(err, ContinuousSpec, "reproduce.")) from None


def arm_sets(spec: ContinuousSpec, arm: str) -> list[str]:
    """The ``--set`` strings of an arm's runs: the continuous fast simulator, the spec's, then the arm's shield
    (last: an arm is what its name says whatever ``--set shield.*`` asks)."""
    a = ARMS[arm]
    sets = ["simulator=fast", "actions=continuous", *spec.sets]
    if spec.quick:
        sets += QUICK_AGENT_SETS[a.algo]
        if a.algo != "ppo":  # the off-policy learners' replay buffer: the whole run, no more
            sets.append(f"agent.buffer_size={spec.decisions}")
    if a.intervention is None:
        return [*sets, "shield.mode=none"]
    penalty = spec.penalty_weight if a.penalised else 0.0
    return [*sets, "shield.mode=committed", f"shield.intervention={a.intervention}",
            f"shield.adaptation_penalty={penalty!r}"]  # fmt: skip


def train_config_of(spec: ContinuousSpec, arm: str, seed: int) -> Any:
    """The :class:`~safelane.running.run_directory.TrainConfig` of the (``arm``, ``seed``) run of ``spec``."""
    from safelane.running.run_directory import DEFAULT_CHECKPOINT_STEPS, make_train_config

    return make_train_config(
        algo=ARMS[arm].algo,
        steps=spec.decisions,
        seed=seed,
        env_preset=spec.env_preset,
        sets=arm_sets(spec, arm),
        checkpoint_steps=min(DEFAULT_CHECKPOINT_STEPS, max(1, spec.decisions // 2)),
    )


def learning_curve(rows: dict[str, np.ndarray], decisions: int, points: int = CURVE_POINTS) -> dict[str, list[float]]:
    """A run's learning curve on ``points`` evenly spaced training-decision counts: at each, the mean episode
    return, failure rate (a crash or off the road) and mean speed [m/s] of the episodes that ended in the trailing
    :data:`CURVE_WINDOW` of the run (an empty window repeats the point before it; before the first episode, the
    first episode's values)."""
    grid = decisions * np.arange(1, points + 1) / points
    ends = rows["env_steps"]
    failure = np.maximum(rows["collision"], rows["off_road"])
    window = max(CURVE_WINDOW * decisions, 1.0)
    curve: dict[str, list[float]] = {"decisions": grid.tolist(), "return": [], "failure_rate": [], "mean_speed": []}
    columns = {"return": rows["return"], "failure_rate": failure, "mean_speed": rows["mean_speed"]}
    for key, values in columns.items():
        last = float(values[0]) if values.size else float("nan")
        for g in grid:
            inside = (ends > g - window) & (ends <= g)
            last = float(values[inside].mean()) if inside.any() else last
            curve[key].append(last)
    return curve


def run_arm_task(out_dir: str, spec_json: str, arm: str, seed: int) -> dict[str, Any]:
    """The backend's task: train (or resume) the (``arm``, ``seed``) run of ``spec_json`` under ``out_dir`` and
    test it; returns its evaluation record (also ``eval.json`` in the run directory)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one run per core: the workers share the machine
    try:
        return _train_and_test(Path(out_dir), ContinuousSpec.model_validate_json(spec_json), arm, seed)
    finally:
        torch.set_num_threads(threads)


def _train_and_test(out: Path, spec: ContinuousSpec, arm: str, seed: int) -> dict[str, Any]:
    from safelane.reporting.metrics_file import METRICS_FILE, read_metrics
    from safelane.running.continuous_training import train_continuous
    from safelane.running.evaluation import run_config, summarize
    from safelane.running.run_directory import CHECKPOINT_FILE, load_checkpoint, load_policy, load_run_config
    from safelane.running.runs import run_env_config

    run_dir = run_dir_of(out, arm, seed)
    eval_path = run_dir / "eval.json"
    if eval_path.exists():
        return dict(json.loads(eval_path.read_text()))
    resume = (run_dir / CHECKPOINT_FILE).exists()
    if not resume and run_dir.exists():  # killed before its first checkpoint: nothing to resume
        shutil.rmtree(run_dir)
    train_continuous(train_config_of(spec, arm, seed), run_dir, resume=resume)
    train_time = float(load_checkpoint(run_dir)["wall_time_s"])  # the run's own clock, resumes included
    eval_start = time.perf_counter()
    run = load_run_config(run_dir)
    records = run_config(run_env_config(run), load_policy(run_dir), spec.test_episodes, TEST_SEED_BASE)
    rows = read_metrics(run_dir / METRICS_FILE, ["env_steps", "return", "collision", "off_road", "mean_speed"])
    record = {
        "arm": arm,
        "seed": seed,
        "summary": summarize(records, method=arm, seed=seed, simulator=run.env.simulator),
        "training_episodes": int(rows["return"].size),
        "learning_curve": learning_curve(rows, spec.decisions),
        "train_wall_time_s": train_time,
        "eval_wall_time_s": time.perf_counter() - eval_start,
    }
    atomic_write_text(eval_path, json.dumps(record))
    return record


def run_comparison(
    spec: ContinuousSpec,
    out_dir: str | Path,
    workers: int | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
    backend: str = "local",
    address: str | None = None,
) -> dict[str, Any]:
    """Run every (arm, seed) not yet done on ``backend`` (:mod:`safelane.running.backend`), then collect all into
    ``out_dir/results.json``; a folder holding another spec is refused in one line (a re-run resumes only the same
    comparison)."""
    check_backend(backend)
    out = Path(out_dir)
    claim_out_dir(out, spec.model_dump_json(indent=2), "spec.json", "reproduction")
    from safelane.running.run_directory import resolve

    for arm in spec.arms:  # a bad --set fails here in one line, not once per task
        resolve(train_config_of(spec, arm, spec.seeds[0]))
    tasks = [(a, s) for s in spec.seeds for a in spec.arms]
    return run_then_collect(
        run_arm_task, tasks, out, spec.model_dump_json(), lambda t: f"{t[0]} seed {t[1]}",
        lambda: collect(out, spec), "reproduce-continuous", time.perf_counter(), backend=backend, workers=workers,
        address=address, progress=progress,
    )  # fmt: skip


SCORES: tuple[str, ...] = ("collision_rate", "off_road_rate", "mean_speed", "intervention_rate", "mean_return")
"""Per-run scores aggregated over seeds in ``results.json`` (IQM with a 95 % bootstrap interval)."""


def _run_scores(rec: dict[str, Any]) -> dict[str, Any]:
    """One run's row of ``results.json`` from its ``eval.json``."""
    s = rec["summary"]
    n = s["episodes"]
    off_road = s.get("off_road_rate", 0.0)
    return {
        "episodes": n,
        "collisions": s["collisions"],
        "collision_rate": s["collision_rate"],
        "off_road": round(off_road * n),
        "off_road_rate": off_road,
        "mean_speed": s["mean_speed"],
        "mean_return": s["mean_return"],
        "mean_length": s["mean_length"],
        # Decisions whose action the shield moved (projected or replaced) ÷ decisions; None without a shield.
        "intervention_rate": s.get("projection_rate"),
        "mean_projection_distance": s.get("mean_projection_distance"),
        "plan_forced_rate": s.get("plan_forced_rate"),
        "lapses": s.get("lapses"),  # the shield's plan broke (committed mode); None without a shield
        "lapses_in_model": s.get("lapses_in_model"),
        "train_wall_time_s": rec["train_wall_time_s"],
        "eval_wall_time_s": rec["eval_wall_time_s"],
        "training_episodes": rec["training_episodes"],
        "learning_curve": rec["learning_curve"],
    }


def collect(out_dir: Path, spec: ContinuousSpec) -> dict[str, Any]:
    """Every run's evaluation gathered into one dict: per-run rows and per-arm aggregates over seeds."""
    arms: dict[str, Any] = {}
    for arm in spec.arms:
        per_seed: dict[str, Any] = {}
        for seed in spec.seeds:
            path = run_dir_of(out_dir, arm, seed) / "eval.json"
            if path.exists():
                per_seed[str(seed)] = _run_scores(json.loads(path.read_text()))
        if not per_seed:
            continue
        agg: dict[str, Any] = {}
        for key in SCORES:
            values = [v[key] for v in per_seed.values() if v[key] is not None]
            if values:
                est = stats.stratified_bootstrap(values, stats.iqm, reps=BOOTSTRAP_REPS, seed=0)
                agg[key] = {"iqm": est.point, "ci95": [est.low, est.high], "mean": stats.mean(values)}
        runs = list(per_seed.values())
        agg["collisions"] = sum(v["collisions"] for v in runs)
        agg["off_road"] = sum(v["off_road"] for v in runs)
        agg["test_episodes"] = sum(v["episodes"] for v in runs)
        if ARMS[arm].intervention is not None:
            agg["lapses"] = sum(v["lapses"] or 0 for v in runs)
            agg["lapses_in_model"] = sum(v["lapses_in_model"] or 0 for v in runs)
        agg["collision_rate_wilson95"] = list(stats.binomial_ci(agg["collisions"], agg["test_episodes"]))
        agg["train_wall_time_s"] = stats.mean([v["train_wall_time_s"] for v in runs])
        agg["decisions_per_s"] = spec.decisions / max(agg["train_wall_time_s"], 1e-9)
        arms[arm] = {"label": ARMS[arm].label, "per_seed": per_seed, "aggregate": agg}
    return {"spec": spec.model_dump(), "arms": arms}


# --- the report -------------------------------------------------------------------------------------------------
def curve_bands(arms: dict[str, Any], key: str) -> dict[str, stats.Band]:
    """Per arm, the IQM over seeds of each run's learning-curve ``key`` at every point, with a 95 % band (whole
    runs resampled: :func:`safelane.reporting.stats.curve_band`)."""
    out: dict[str, stats.Band] = {}
    for arm, data in arms.items():
        curves = np.array([p["learning_curve"][key] for p in data["per_seed"].values()], dtype=float)
        out[arm] = stats.curve_band(curves, "iqm", reps=BOOTSTRAP_REPS, seed=0)
    return out


def fig_learning_curves(arms: dict[str, Any], decisions: int) -> Figure:
    """Training return and failure rate (crash or off the road) against decisions: IQM over seeds, 95 % bands."""
    panels = [
        ("episode return, IQM over seeds", curve_bands(arms, "return")),
        ("episodes crashed or off the road", curve_bands(arms, "failure_rate")),
    ]
    x = decisions * np.arange(1, CURVE_POINTS + 1) / CURVE_POINTS
    labels = {arm: arm for arm in arms}
    return plot_curve_bands(panels, labels, xlabel="training decision", x=x,
                            title="Learning curves (IQM over seeds, 95 % bootstrap bands)")  # fmt: skip


def _est(agg: dict[str, Any], key: str, digits: int) -> str:
    if key not in agg:
        return "–"
    a = agg[key]
    return f"{a['iqm']:.{digits}f} [{a['ci95'][0]:.{digits}f}, {a['ci95'][1]:.{digits}f}]"


def comparison_table(arms: dict[str, Any]) -> list[str]:
    """Markdown rows: per arm the test crashes and off-road episodes (counts), and the IQM over seeds with its 95 %
    stratified bootstrap interval of each run's crash rate, off-road rate, mean speed and intervention rate; the
    shield's lapses (in the model); the mean training time per run."""
    lines = [
        "| arm | runs | crashes / test episodes | crash rate | off-road rate | mean speed [m/s] | intervention rate "
        "| lapses (in model) | training time per run [s] | decisions/s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for arm, data in arms.items():
        a = data["aggregate"]
        lapses = f"{a['lapses']} ({a['lapses_in_model']})" if "lapses" in a else "–"
        lines.append(
            f"| `{arm}` | {len(data['per_seed'])} | {a['collisions']} / {a['test_episodes']} | "
            f"{_est(a, 'collision_rate', 3)} | {_est(a, 'off_road_rate', 3)} | {_est(a, 'mean_speed', 2)} | "
            f"{_est(a, 'intervention_rate', 3)} | {lapses} | {a['train_wall_time_s']:.1f} | "
            f"{a['decisions_per_s']:.0f} |"
        )
    return lines


def write_comparison_report(out_dir: str | Path) -> Path:
    """Write ``report.md`` and ``learning_curves.png`` from ``out_dir/results.json``; returns the report path."""
    out = Path(out_dir)
    results = json.loads((out / "results.json").read_text())
    spec = ContinuousSpec.model_validate(results["spec"])
    arms = results["arms"]
    if arms:
        fig_learning_curves(arms, spec.decisions).savefig(out / "learning_curves.png", dpi=110)
    train_total = sum(p["train_wall_time_s"] for d in arms.values() for p in d["per_seed"].values())
    lines = [
        "# safelane reproduction report: continuous acceleration and steering",
        "",
        f"Preset `{spec.env_preset}` on the fast simulator, arms {', '.join(spec.arms)}, seeds {spec.seeds}, "
        f"{spec.decisions} training decisions per run, {spec.test_episodes} held-out test episodes per run (seeds "
        f"{TEST_SEED_BASE} + k, each run's deterministic policy in its own environment: a shielded arm under its "
        "shield)"
        + (" — **quick mode: too few seeds and decisions for conclusions**" if spec.quick else "")
        + f". Training time summed over runs: {train_total:.0f} s; this invocation: "
        f"{results.get('wall_time_s', float('nan')):.0f} s.",
        "",
        "## Test episodes",
        "",
        "Each run contributes one score per column (its rate over its test episodes); the table gives the "
        "interquartile mean (IQM) over runs with its 95 % stratified bootstrap interval "
        f"({BOOTSTRAP_REPS} samples, seed 0; with fewer than 4 runs the IQM is the mean), after Agarwal et al. "
        "(2021). Intervention rate: decisions whose action the shield projected or replaced ÷ decisions (– without "
        "a shield); lapses: test decisions at which the plan kept, verified, no longer verified (in the model: with "
        "the car it fails on inside the set drawn for it). The `*-penalty` arms pay "
        f"{spec.penalty_weight} × the projection distance per decision.",
        "",
        *comparison_table(arms),
        "",
        "## Arms",
        "",
        *[f"- `{arm}`: {data['label']}" for arm, data in arms.items()],
        "",
        "## Learning curves",
        "",
        "Each run's training episodes that ended in the trailing tenth of the run, at 50 points: episode return "
        "(the penalty arms' includes the penalty) and the fraction of episodes that crashed or left the road.",
        "",
        "![learning curves](learning_curves.png)",
    ]
    report = out / "report.md"
    atomic_write_text(report, "\n".join(lines) + "\n")
    return report
