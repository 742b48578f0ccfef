"""A sweep's trials on disk: each (trial, seed) trained and tested by the experiment runner's task, its
failures recorded, and the summary files rebuilt from the trial directories (``trials.csv``,
``summary.md`` / ``summary.json``, ``best.yaml``, ``objective_PARAM.png``; see :mod:`safelane.running.sweeps`)."""

from __future__ import annotations

import csv
import io
import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from safelane.core.errors import ConfigError
from safelane.core.files import atomic_write_text
from safelane.running.sweeps.spec import COMMITTED_METRICS, METRICS, SweepSpec


def _value_text(value: Any) -> str:
    """A --set value as YAML (so lists, booleans and strings round-trip)."""
    return yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("...").strip()


def trial_sets(spec: SweepSpec, params: dict[str, Any]) -> list[str]:
    """The --set strings of one trial: the spec's, then the trial's parameters."""
    return [*spec.sets, *(f"{k}={_value_text(v)}" for k, v in params.items())]


def trial_dir(out: Path, index: int) -> Path:
    """Directory of trial ``index``."""
    return out / "trials" / f"t{index:03d}"


def _trial_experiment(spec: SweepSpec, params: dict[str, Any]) -> Any:
    from safelane.running.experiments import make_spec

    return make_spec(
        methods=[spec.method],
        seeds=list(range(spec.seeds)),
        episodes=spec.episodes,
        test_episodes=spec.test_episodes,
        env_preset=spec.env_preset,
        agent_preset=spec.agent_preset,
        sets=trial_sets(spec, params),
    )


def _sweep_task(out_dir: str, spec_json: str, index: int, seed: int, params_json: str | None = None) -> dict[str, Any]:
    """Train and test one (trial, seed); returns its metrics (the run's eval.json holds everything).
    ``params_json``: the trial's parameters (a TPE trial's; by default the spec's point ``index``)."""
    from safelane.running.experiments import run_task

    spec = SweepSpec.model_validate_json(spec_json)
    params = json.loads(params_json) if params_json is not None else spec.points()[index]
    directory = trial_dir(Path(out_dir), index)
    experiment = _trial_experiment(spec, params)
    atomic_write_text(directory / "params.json", json.dumps(params))
    # A ConfigError propagates: the backend reports it as a final TaskFailure and run_sweep writes it.
    record = run_task(str(directory), experiment.model_dump_json(), spec.method, seed)
    return {"trial": index, "seed": seed, "metrics": _metrics_of(record)}


def failure_path(directory: Path, seed: int) -> Path:
    return directory / f"failed-s{seed}.json"


def _write_failure(directory: Path, seed: int, kind: str, message: str) -> None:
    atomic_write_text(failure_path(directory, seed), json.dumps({"kind": kind, "error": message}))


def _metrics_of(record: dict[str, Any]) -> dict[str, float]:
    summary, episodes = record["summary"], record["episodes"]
    metrics = {k: float(summary[k]) for k in (*METRICS, *COMMITTED_METRICS) if k in summary}
    metrics["return_before_collision"] = float(np.mean([e["return_before_collision"] for e in episodes]))
    metrics["collisions"] = float(summary["collisions"])
    metrics["test_episodes"] = float(summary["episodes"])
    metrics["train_wall_time_s"] = float(record["train_wall_time_s"])
    return metrics


def trial_points(out: Path, spec: SweepSpec) -> list[dict[str, Any]]:
    """The trials' parameters in trial order: the spec's points (grid, random) or those a TPE study
    proposed so far (``DIR/trials/tNNN/params.json``, written before the trial runs)."""
    if spec.search != "tpe":
        return spec.points()
    points = []
    for index in range(spec.samples):
        path = trial_dir(out, index) / "params.json"
        if not path.is_file():
            break
        points.append(json.loads(path.read_text()))
    return points


def eval_path(out: Path, spec: SweepSpec, index: int, seed: int) -> Path:
    from safelane.running.experiments import run_dir_of

    return run_dir_of(trial_dir(out, index), spec.method, seed) / "eval.json"


def run_trial_tasks(
    out: Path,
    spec: SweepSpec,
    tasks: list[tuple[int, int, str | None]],
    done: list[int],
    total: int,
    progress: Callable[[int, int], None] | None,
    *,
    backend: str,
    workers: int | None,
    address: str | None,
    name: str,
) -> None:
    """Run ``(trial, seed, params JSON or None for the spec's point)`` tasks on the backend; after each,
    record its failure (if any), count it in ``done`` (one-element list, shared with the caller), rebuild
    the summary files (a kill loses only the tasks in flight) and report ``progress(done, total)``."""
    from safelane.running.backend import TaskFailure, run_tasks

    _train_batched_first(out, spec, tasks, backend=backend, workers=workers, address=address, name=name)
    spec_json = spec.model_dump_json()

    def finished(i: int, result: dict[str, Any] | TaskFailure) -> None:
        index, seed, _ = tasks[i]
        if isinstance(result, TaskFailure):
            _write_failure(trial_dir(out, index), seed, result.kind, result.message)
        done[0] += 1
        write_results(out, spec)
        if progress is not None:
            progress(done[0], total)

    run_tasks(
        _sweep_task,
        [(str(out), spec_json, index, seed, params) for index, seed, params in tasks],
        backend=backend,
        workers=workers,
        address=address,
        on_result=finished,
        name=name,
        storage=out / "ray",
    )


def _train_batched_first(
    out: Path,
    spec: SweepSpec,
    tasks: list[tuple[int, int, str | None]],
    *,
    backend: str,
    workers: int | None,
    address: str | None,
    name: str,
) -> None:
    """Train the tasks' runs that the fast batch plays as batches, one per worker
    (:func:`safelane.running.batched_training.batches_of`: the same runs, bit for bit); each task then finds
    its run trained, evaluates it, and trains (one by one) or reports whatever a batch left undone."""
    import os

    from safelane.running.backend import run_tasks
    from safelane.running.batched_training import batches_of, train_runs_task
    from safelane.running.experiments import run_dir_of, train_config_of

    points = spec.points() if any(params is None for _, _, params in tasks) else []
    jobs = []
    for index, seed, params_json in tasks:
        params = json.loads(params_json) if params_json is not None else points[index]
        try:
            cfg = train_config_of(_trial_experiment(spec, params), spec.method, seed)
        except ConfigError:  # the task itself reports it
            continue
        jobs.append((cfg, run_dir_of(trial_dir(out, index), spec.method, seed)))
    batches = batches_of(jobs, workers or os.cpu_count() or 1)
    if batches:
        run_tasks(
            train_runs_task, batches, backend=backend, workers=len(batches), address=address,
            name=f"{name}-train", storage=out / "ray",
        )  # fmt: skip


def stored_spec(out: Path) -> dict[str, Any] | None:
    """The spec a sweep folder was started with (its sweep.json), if any."""
    path = out / "sweep.json"
    return json.loads(path.read_text()) if path.is_file() else None


def final_failure(directory: Path, seed: int) -> bool:
    """A config failure is final (the same values fail again); any other is retried by a re-run."""
    path = failure_path(directory, seed)
    return path.is_file() and json.loads(path.read_text()).get("kind") == "config"


def trial_rows(out: Path, spec: SweepSpec, index: int, params: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per seed of trial ``index`` that finished or failed, from its directory."""
    rows: list[dict[str, Any]] = []
    for seed in range(spec.seeds):
        row: dict[str, Any] = {"trial": index, "seed": seed, **params}
        result = eval_path(out, spec, index, seed)
        failure = failure_path(trial_dir(out, index), seed)
        if result.is_file():
            row.update(status="ok", **_metrics_of(json.loads(result.read_text())), error="")
        elif failure.is_file():
            info = json.loads(failure.read_text())
            row.update(status="failed", error=f"{info['kind']}: {info['error']}")
        else:
            continue
        rows.append(row)
    return rows


def read_trials(out: Path, spec: SweepSpec) -> list[dict[str, Any]]:
    """One row per (trial, seed) that finished or failed, from the trial directories."""
    return [row for index, params in enumerate(trial_points(out, spec)) for row in trial_rows(out, spec, index, params)]


def pooled_metrics(ok: list[dict[str, Any]]) -> dict[str, float]:
    """A trial's test metrics over its finished seeds: means, and the collision rate of all its episodes; under the
    committed shield also the mean ``plan_forced_rate`` and the lapses summed (:data:`COMMITTED_METRICS`)."""
    episodes = sum(int(r["test_episodes"]) for r in ok)
    pooled = {m: float(np.mean([r[m] for r in ok])) for m in METRICS if m in ok[0]}
    pooled["collision_rate"] = sum(int(r["collisions"]) for r in ok) / episodes
    if all(m in r for r in ok for m in COMMITTED_METRICS):
        pooled["plan_forced_rate"] = float(np.mean([r["plan_forced_rate"] for r in ok]))
        pooled["lapses"] = float(sum(r["lapses"] for r in ok))
        pooled["lapses_in_model"] = float(sum(r["lapses_in_model"] for r in ok))
    return pooled


def summarize_trials(
    spec: SweepSpec, rows: list[dict[str, Any]], points: list[dict[str, Any]] | None = None
) -> dict[str, Any]:
    """Per trial: objective mean over seeds with a bootstrap 95 % CI, pooled metrics, feasibility; the best.
    ``points``: the trials' parameters (default: the spec's; a TPE sweep's from :func:`trial_points`)."""
    from safelane.reporting import stats

    points = spec.points() if points is None else points
    metric, trials = spec.objective.metric, []
    for index, params in enumerate(points):
        ok = [r for r in rows if r["trial"] == index and r["status"] == "ok"]
        failed = [r for r in rows if r["trial"] == index and r["status"] == "failed"]
        entry: dict[str, Any] = {"trial": index, "params": params, "seeds_done": len(ok), "failed": len(failed)}
        if failed:
            entry["error"] = failed[0]["error"]
        if ok:
            values = [r[metric] for r in ok]
            episodes = sum(int(r["test_episodes"]) for r in ok)
            collisions = sum(int(r["collisions"]) for r in ok)
            pooled = pooled_metrics(ok)
            entry.update(
                objective=stats.mean(values),
                objective_ci95=list(stats.bootstrap_ci(values, seed=0)),
                metrics=pooled,
                collisions=collisions,
                test_episodes=episodes,
                collision_rate_wilson95=list(stats.binomial_ci(collisions, episodes)),
                feasible=spec.objective.satisfied(pooled),
            )
        trials.append(entry)
    complete = [t for t in trials if t["seeds_done"] == spec.seeds and t.get("feasible")]
    sign = 1.0 if spec.objective.mode == "max" else -1.0
    best = max(complete, key=lambda t: (sign * t["objective"], -t["trial"]), default=None)
    planned = spec.samples if spec.search == "tpe" else len(points)
    return {
        "name": spec.name,
        "method": spec.method,
        "search": search_info(spec),
        "objective": spec.objective.model_dump(),
        "trials": trials,
        "best": best,
        "complete": len(trials) == planned and all(t["seeds_done"] + t["failed"] == spec.seeds for t in trials),
    }


def search_info(spec: SweepSpec) -> dict[str, Any]:
    """How the points were chosen (summary.json's ``search``)."""
    if spec.search == "grid":
        return {"kind": "grid"}
    info: dict[str, Any] = {"kind": spec.search, "samples": spec.samples, "search_seed": spec.search_seed}
    if spec.search == "tpe":
        info.update(batch=spec.batch, startup_trials=spec.startup())
    return info


def _search_text(spec: SweepSpec, n_trials: int) -> str:
    if spec.search == "grid":
        return f"Search: grid, {n_trials} points."
    if spec.search == "random":
        return f"Search: random, {spec.samples} points drawn with seed {spec.search_seed}."
    return (
        f"Search: Optuna TPE, {spec.samples} trials in batches of {spec.batch} (the first {spec.startup()} "
        f"random), seed {spec.search_seed}; {n_trials} proposed so far."
    )


def write_results(out: Path, spec: SweepSpec) -> dict[str, Any]:
    """Rebuild trials.csv, summary.json / summary.md, best.yaml and the plots from the trial directories."""
    rows = read_trials(out, spec)
    keys = list(spec.space)
    extra = ["collisions", "test_episodes", "train_wall_time_s"]
    committed = [m for m in COMMITTED_METRICS if any(m in r for r in rows)]  # committed-shield trials only
    columns = ["trial", "seed", *keys, "status", *METRICS, *committed, *extra, "error"]
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({c: (_value_text(row[c]) if c in keys else row.get(c, "")) for c in columns})
    atomic_write_text(out / "trials.csv", buffer.getvalue())
    summary = summarize_trials(spec, rows, trial_points(out, spec))
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1))
    atomic_write_text(out / "summary.md", summary_markdown(spec, summary))
    if summary["best"] is not None:
        atomic_write_text(out / "best.yaml", best_preset_yaml(spec, summary["best"]))
    _plot_objective(out, spec, summary)
    return summary


def summary_markdown(spec: SweepSpec, summary: dict[str, Any]) -> str:
    """The summary table: one line per trial (objective mean [95 % CI], collisions, feasibility; under the committed
    shield, its fallback and plan-forced rates and lapses)."""
    metric = spec.objective.metric
    keys = list(spec.space)
    committed = any("plan_forced_rate" in t.get("metrics", {}) for t in summary["trials"])
    extra = " fallback rate | plan-forced rate | lapses (in the model) |" if committed else ""
    constraint = " and ".join(spec.objective.constraints) or "none"
    lines = [
        f"# Sweep {spec.name}: {spec.method}",
        "",
        spec.description.strip(),
        "",
        f"Objective: {spec.objective.mode} test `{metric}` (mean over {spec.seeds} seeds, bootstrap 95 % CI); "
        f"constraints: {constraint}. {spec.episodes} training episodes, {spec.test_episodes} test episodes per run.",
        _search_text(spec, len(summary["trials"])),
        "",
        "| trial | "
        + " | ".join(f"`{k}`" for k in keys)
        + f" | {metric} [95 % CI] | collisions (Wilson 95 %) | feasible |{extra}",
        "|---" * (len(keys) + 4 + 3 * committed) + "|",
    ]
    best = summary["best"]["trial"] if summary["best"] else None
    for t in summary["trials"]:
        values = " | ".join(_cell(t["params"][k]) for k in keys)
        if "objective" in t:
            lo, hi = t["objective_ci95"]
            clo, chi = t["collision_rate_wilson95"]
            obj = f"{t['objective']:.3f} [{lo:.3f}, {hi:.3f}]"
            col = f"{t['collisions']} / {t['test_episodes']} ({clo:.3f}–{chi:.3f})"
            feas = "yes" if t["feasible"] else "no"
        else:
            obj, col, feas = "—", "—", f"failed: {t.get('error', 'not run')}" if t["failed"] else "not run"
        mark = " **best**" if t["trial"] == best else ""
        line = f"| t{t['trial']:03d}{mark} | {values} | {obj} | {col} | {feas} |"
        if committed:
            m = t.get("metrics", {})
            line += (
                f" {m['fallback_rate']:.4f} | {m['plan_forced_rate']:.4f} | {m['lapses']:.0f} "
                f"({m['lapses_in_model']:.0f}) |"
                if "plan_forced_rate" in m
                else " — | — | — |"
            )
        lines.append(line)
    lines.append("")
    return "\n".join(lines)


def _cell(value: Any) -> str:
    """A parameter in the summary table: a drawn float to 4 significant digits (trials.csv, params.json
    and best.yaml keep every digit), anything else as in the spec."""
    if isinstance(value, float) and len(repr(value)) > 8:
        return f"{value:.4g}"
    return _value_text(value)


def best_preset_yaml(spec: SweepSpec, best: dict[str, Any]) -> str:
    """The agent preset of the best trial: the spec's preset with its ``agent.*`` values; the trial's
    other keys as ``--set`` lines in the header."""
    from safelane.agents.dqn import agent_preset_path

    base = yaml.safe_load(Path(agent_preset_path(spec.agent_preset)).read_text()) or {}
    base["method"] = spec.method
    agent = {k.removeprefix("agent."): v for k, v in best["params"].items() if k.startswith("agent.")}
    for key in spec.sets:
        if key.startswith("agent."):
            name, _, value = key.partition("=")
            agent.setdefault(name.removeprefix("agent."), yaml.safe_load(value))
    base.update(agent)
    others = [f"{k}={_value_text(v)}" for k, v in best["params"].items() if not k.startswith("agent.")]
    others += [s for s in spec.sets if not s.startswith("agent.")]
    header = [
        f"# Best trial t{best['trial']:03d} of sweep '{spec.name}' ({spec.objective.mode} {spec.objective.metric} = "
        f"{best['objective']:.4f} over {best['seeds_done']} seeds).",
        "# Use: --agent-preset best.yaml" + (" with " + " ".join(f"--set {o}" for o in others) if others else ""),
    ]
    return "\n".join(header) + "\n" + yaml.safe_dump(base, sort_keys=False)


def _plot_objective(out: Path, spec: SweepSpec, summary: dict[str, Any]) -> None:
    from matplotlib.figure import Figure

    done = [t for t in summary["trials"] if "objective" in t]
    if not done:
        return
    for key in spec.space:
        xs = [t["params"][key] for t in done]
        if not all(isinstance(x, int | float) and not isinstance(x, bool) for x in xs):
            continue  # categorical values: the table says it
        ys = np.array([t["objective"] for t in done])
        lo = ys - np.array([t["objective_ci95"][0] for t in done])
        hi = np.array([t["objective_ci95"][1] for t in done]) - ys
        fig = Figure(figsize=(5, 3.5))
        ax = fig.add_subplot()
        colors = ["tab:blue" if t["feasible"] else "tab:red" for t in done]
        ax.errorbar(xs, ys, yerr=[lo, hi], fmt="none", ecolor="grey", capsize=3)
        ax.scatter(xs, ys, c=colors, zorder=3)
        if spec.space[key].loguniform is not None:
            ax.set_xscale("log")  # the scale the values were drawn on
        ax.set_xlabel(key)
        ax.set_ylabel(f"test {spec.objective.metric}")
        ax.set_title(f"{spec.name} ({spec.method}); red: constraints not met", fontsize=9)
        fig.tight_layout()
        safe = re.sub(r"[^A-Za-z0-9_.-]", "_", key)
        fig.savefig(out / f"objective_{safe}.png", dpi=100)
