"""Experiment runner: every method × seed trained, evaluated on held-out test episodes, collected.

``run_experiment(spec, out_dir)`` trains each (method, seed) into ``out_dir/runs/METHOD-sSEED``
(resuming a run that was interrupted), evaluates its greedy policy on ``test_episodes`` episodes
whose seeds are never used in training, and writes ``out_dir/results.json`` atomically. A task whose
evaluation file exists is skipped, so re-running after a crash loses nothing and duplicates
nothing. Tasks run on :mod:`safelane.running.backend` (``local``: a process pool of ``workers``, default all
cores; ``ray``: Ray Tune trials).
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from safelane.config import ConfigError, validation_message
from safelane.core.files import atomic_write_text
from safelane.running.backend import TaskFailure, check_backend, format_failure, run_tasks

METHODS: tuple[str, ...] = ("dqn", "constrained", "qmask", "robust")
LEARNERS: tuple[str, ...] = ("batched", "per-run")
"""How an experiment trains its fast-simulator runs (:func:`run_experiment`'s ``learner``)."""
TEST_SEED_BASE = 2_000_000_000
"""Test episodes are reset with ``TEST_SEED_BASE + k``: far from every training seed
(``seed·EPISODE_SEED_STRIDE + episode``), so the agents never saw them."""


class ExperimentSpec(BaseModel):
    """What to run: methods × seeds, training length and test episodes."""

    model_config = ConfigDict(extra="forbid")

    methods: list[Literal["dqn", "constrained", "qmask", "robust"]] = Field(default_factory=lambda: list(METHODS))
    seeds: list[int] = Field(default_factory=lambda: [0, 1, 2, 3, 4])
    episodes: int = Field(200, ge=1, description="Training episodes per run (paper: 200).")
    test_episodes: int = Field(20, ge=1, description="Held-out test episodes per run (paper: 20).")
    env_preset: Literal["fast", "paper"] = "fast"
    agent_preset: str = "tuned"
    sets: list[str] = Field(default_factory=list, description="--set overrides for every run.")
    quick: bool = False
    stress_conditions: list[str] = Field(
        default_factory=list, description="Stress-suite conditions each trained run is also evaluated on."
    )
    stress_episodes: int = Field(10, ge=1)
    confirm_on: Literal["highway-env"] | None = Field(
        None,
        description="Re-run every trained agent's test episodes on this simulator too (runs trained on "
        "simulator=fast are confirmed on the reference) and report both side by side.",
    )
    confirm_episodes: int | None = Field(
        None,
        ge=1,
        description="With confirm_on: how many of each run's test episodes (the first ones) to re-run "
        "(null = all; highway-env plays ≈ 10 decisions/s, so 1 000 test episodes × 40 runs take a day).",
    )

    @model_validator(mode="after")
    def _confirm_within_test(self) -> ExperimentSpec:
        if self.confirm_episodes is not None and self.confirm_on is None:
            raise ConfigError("--confirm-episodes: needs --confirm-on (the simulator to confirm on)")
        if self.confirm_episodes is not None and self.confirm_episodes > self.test_episodes:
            raise ConfigError(
                f"--confirm-episodes: at most --test-episodes ({self.test_episodes}), got {self.confirm_episodes}"
            )
        return self

    def confirm_count(self) -> int:
        """Test episodes per run re-run on ``confirm_on``."""
        return self.test_episodes if self.confirm_episodes is None else self.confirm_episodes


def make_spec(**fields: Any) -> ExperimentSpec:
    """An :class:`ExperimentSpec`, raising a one-line :class:`ConfigError` on bad input."""
    try:
        return ExperimentSpec(**fields)
    except ValidationError as err:
        raise ConfigError(validation_message(err, ExperimentSpec, "reproduce.")) from None


def run_dir_of(out_dir: Path, method: str, seed: int) -> Path:
    """Directory of the (method, seed) run."""
    return out_dir / "runs" / f"{method}-s{seed}"


def train_config_of(spec: ExperimentSpec, method: str, seed: int) -> Any:
    """The :class:`~safelane.running.run_directory.TrainConfig` of the (``method``, ``seed``) run of ``spec``."""
    from safelane.running.run_directory import make_train_config

    return make_train_config(
        method=method,
        agent_preset=spec.agent_preset,
        env_preset=spec.env_preset,
        episodes=spec.episodes,
        seed=seed,
        sets=spec.sets,
        checkpoint_every=max(1, min(25, spec.episodes // 4)),
    )


def _batched_training(
    spec: ExperimentSpec,
    out: Path,
    tasks: list[tuple[str, int]],
    workers: int | None,
    backend: str,
    address: str | None,
) -> None:
    """Train the runs of ``tasks`` not yet evaluated as batches, one per worker, where the fast batch plays
    them (:func:`safelane.running.batched_training.batches_of`); :func:`run_task` then evaluates them (and
    trains, one by one, whatever a batch left undone)."""
    import os

    from safelane.running.batched_training import batches_of, train_runs_task

    jobs = [
        (train_config_of(spec, m, s), run_dir_of(out, m, s))
        for m, s in sorted(tasks)  # by method, then seed: each batch gets a share of every method's seeds
        if not (run_dir_of(out, m, s) / "eval.json").exists()
    ]
    batches = batches_of(jobs, workers or os.cpu_count() or 1)
    if batches:
        run_tasks(
            train_runs_task, batches, backend=backend, workers=len(batches), address=address,
            name="reproduce-train", storage=out.resolve() / "ray",
        )  # fmt: skip


def run_task(out_dir: str, spec_json: str, method: str, seed: int) -> dict[str, Any]:
    """The backend's task of an experiment: train (or resume) the (``method``, ``seed``) run of the experiment
    ``spec_json`` under ``out_dir`` and evaluate it; returns its evaluation record (also on disk)."""
    import torch

    from safelane.reporting.metrics_file import METRICS_FILE, read_metrics
    from safelane.running.evaluation import run_config, summarize
    from safelane.running.run_directory import load_policy, load_run_config
    from safelane.running.runs import run_env_config
    from safelane.running.training import train

    torch.set_num_threads(1)
    spec = ExperimentSpec.model_validate_json(spec_json)
    run_dir = run_dir_of(Path(out_dir), method, seed)
    eval_path = run_dir / "eval.json"
    if eval_path.exists():
        record = json.loads(eval_path.read_text())
        if spec.confirm_on is not None and "confirm" not in record:  # asked for after the run was done
            record["confirm"] = confirm_test_episodes(run_dir, spec, record["episodes"])
            atomic_write_text(eval_path, json.dumps(record))
        return record
    cfg = train_config_of(spec, method, seed)
    resume = (run_dir / "checkpoint.pt").exists()
    if not resume and run_dir.exists():
        # Killed before its first checkpoint: nothing to resume, the partial files are redone.
        shutil.rmtree(run_dir)
    train(cfg, run_dir, resume=resume)
    # The run's own clock: cumulative over resumes (a perf_counter here would count only the last part).
    train_time = float(read_metrics(run_dir / METRICS_FILE, ["wall_time_s"])["wall_time_s"][-1])
    eval_start = time.perf_counter()
    run = load_run_config(run_dir)
    policy = load_policy(run_dir)
    reward_c = run.env.reward.c
    records = run_config(run_env_config(run), policy, spec.test_episodes, TEST_SEED_BASE)
    episodes = []
    for k, r in enumerate(records):
        d = r.to_dict()
        d.update(
            method=method,
            seed=seed,
            test_episode=k,
            # Fig. 6: reward earned before the collision (the eq. 6 speed terms, without the penalty)
            return_before_collision=r.return_ + (reward_c if r.collision else 0.0),
        )
        episodes.append(d)
    stress: list[dict[str, Any]] = []
    if spec.stress_conditions:
        from safelane.running.stress import run_condition

        for name in spec.stress_conditions:
            stress.append(run_condition(name, policy, spec.stress_episodes, shield=None, override=None, run=run))
    summary = summarize(records, method=method, seed=seed, simulator=run.env.simulator)
    record = {
        "method": method,
        "seed": seed,
        "summary": summary,
        "episodes": episodes,
        "stress": stress,
        "train_wall_time_s": train_time,
        "eval_wall_time_s": time.perf_counter() - eval_start,
    }
    if spec.confirm_on is not None:
        record["confirm"] = confirm_test_episodes(run_dir, spec, episodes)
    atomic_write_text(eval_path, json.dumps(record))
    return record


CONFIRM_FIELDS = ("return_", "length", "collision", "mean_speed", "collision_kind", "actions")
"""Fields of a test episode that must agree for it to count as the same episode on both simulators."""


def confirm_test_episodes(run_dir: Path, spec: ExperimentSpec, episodes: list[dict[str, Any]]) -> dict[str, Any]:
    """Play the run's first ``spec.confirm_count()`` test episodes again (same seeds, same greedy policy)
    on ``spec.confirm_on``: their summary, and how many came out the same as the recorded ``episodes``."""
    from safelane.running.evaluation import run_config, summarize
    from safelane.running.run_directory import load_policy, load_run_config
    from safelane.running.runs import run_env_config

    run = load_run_config(run_dir)
    cfg = run_env_config(run).model_copy(update={"simulator": spec.confirm_on})
    start = time.perf_counter()
    count = spec.confirm_count()
    records = run_config(cfg, load_policy(run_dir), count, TEST_SEED_BASE)
    same = sum(
        all(r.to_dict()[f] == e[f] for f in CONFIRM_FIELDS) for r, e in zip(records, episodes[:count], strict=True)
    )
    return {
        "simulator": cfg.simulator,
        "summary": summarize(records, simulator=cfg.simulator),
        "identical_episodes": same,
        "episodes": len(records),
        "wall_time_s": time.perf_counter() - start,
    }


def _validate_runs(spec: ExperimentSpec) -> None:
    """Resolve each method's run configuration once (raises the one-line :class:`ConfigError` of a bad value)."""
    from safelane.running.run_directory import make_train_config, resolve

    for method in spec.methods:
        resolve(
            make_train_config(
                method=method,
                agent_preset=spec.agent_preset,
                env_preset=spec.env_preset,
                episodes=spec.episodes,
                sets=spec.sets,
            )
        )


def run_experiment(
    spec: ExperimentSpec,
    out_dir: str | Path,
    workers: int | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
    backend: str = "local",
    address: str | None = None,
    learner: str = "batched",
) -> dict[str, Any]:
    """Run every (method, seed) task not yet done, then collect all into ``out_dir/results.json``.

    ``backend`` / ``address``: where the tasks run (:mod:`safelane.running.backend`; same results).
    ``learner``: ``batched`` trains the runs on the fast simulator as one batch per worker
    (:mod:`safelane.running.batched_training`), ``per-run`` one run per task; the same runs, bit for bit
    (highway-env runs always train one by one). A batched run's ``train_wall_time_s`` is its share of its batch's clock.
    """
    if learner not in LEARNERS:
        raise ConfigError(f"--learner: got {learner!r}; allowed: {', '.join(LEARNERS)}")
    check_backend(backend)
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as err:
        raise ConfigError(f"--out {out}: not writable ({err.strerror})") from None
    atomic_write_text(out / "spec.json", spec.model_dump_json(indent=2))
    _validate_runs(spec)  # a bad --set fails here in one line, not once per task
    tasks = [(m, s) for s in spec.seeds for m in spec.methods]
    start = time.perf_counter()
    if learner == "batched":
        _batched_training(spec, out, tasks, workers, backend, address)
    return run_then_collect(
        run_task, tasks, out, spec.model_dump_json(), lambda t: f"{t[0]} seed {t[1]}", lambda: collect(out, spec),
        "reproduce", start, backend=backend, workers=workers, address=address, progress=progress,
    )  # fmt: skip


def known_names(names: list[str], allowed: Any, what: str) -> list[str]:
    """``names`` if each is one of ``allowed``; else a ValueError naming the first unknown one and the allowed ones
    (a spec's field validator: pydantic turns it into the field's one-line error)."""
    unknown = [n for n in names if n not in allowed]
    if unknown:
        raise ValueError(f"unknown {what} {unknown[0]!r}; allowed: {', '.join(allowed)}")
    return names


def parse_name_list(text: str, allowed: Any, option: str, noun: str, where: str) -> list[str]:
    """The names of a comma-separated ``option`` (``all``: every allowed one, in order), each once, in the order
    given; an unknown or missing name is a one-line :class:`ConfigError` naming the ``noun``, the allowed values and
    ``where`` they are allowed (``--preset hidden-types``)."""
    allowed = list(allowed)
    if text.strip() == "all":
        return allowed
    given = [name.strip() for name in text.split(",") if name.strip()]
    for name in given:
        if name not in allowed:
            raise ConfigError(f"{option}: unknown {noun} {name!r}; allowed with {where}: {', '.join(allowed)} or all")
    if not given:
        raise ConfigError(f"{option}: no {noun} given; allowed with {where}: {', '.join(allowed)} or all")
    return list(dict.fromkeys(given))


def run_then_collect(
    task: Callable[..., dict[str, Any]], tasks: list[tuple[Any, ...]], out: Path, spec_json: str,
    label: Callable[[tuple[Any, ...]], str], collect_results: Callable[[], dict[str, Any]], name: str, start: float,
    backend: str = "local", workers: int | None = None, address: str | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """The step every reproduction ends with: ``task(out_dir, spec_json, *args)`` for each of ``tasks`` on
    ``backend`` (``progress`` called with each run's record), a one-line ConfigError naming the first failed run
    (``label`` of its args), then ``collect_results()`` with ``wall_time_s`` [s] since ``start`` written atomically
    to ``out/results.json`` and returned."""
    failures: list[str] = []

    def finished(i: int, result: dict[str, Any] | TaskFailure) -> None:
        if isinstance(result, TaskFailure):
            failures.append(f"{label(tasks[i])}: {format_failure(result)}")
        elif progress:
            progress(result)

    run_tasks(
        task,
        [(str(out.resolve()), spec_json, *args) for args in tasks],  # absolute: a Ray worker runs elsewhere
        backend=backend,
        workers=workers,
        address=address,
        on_result=finished,
        name=name,
        storage=out.resolve() / "ray",
    )
    if failures:
        raise ConfigError(f"reproduce: {len(failures)} run(s) failed; first: {failures[0]}")
    results = collect_results()
    results["wall_time_s"] = time.perf_counter() - start
    atomic_write_text(out / "results.json", json.dumps(results, indent=1))
    return results


def collect(out_dir: Path, spec: ExperimentSpec) -> dict[str, Any]:
    """Gather every run's evaluation into one dict: per-episode records and per-method aggregates."""
    from safelane.reporting import stats

    methods: dict[str, Any] = {}
    all_episodes: list[dict[str, Any]] = []
    for method in spec.methods:
        per_seed: dict[str, Any] = {}
        for seed in spec.seeds:
            path = run_dir_of(out_dir, method, seed) / "eval.json"
            if not path.exists():
                continue
            rec = json.loads(path.read_text())
            all_episodes.extend(rec["episodes"])
            s = rec["summary"]
            per_seed[str(seed)] = {
                "collision_rate": s["collision_rate"],
                "collisions": s["collisions"],
                "episodes": s["episodes"],
                "mean_speed": s["mean_speed"],
                "mean_return": s["mean_return"],
                "return_before_collision": float(
                    sum(e["return_before_collision"] for e in rec["episodes"]) / len(rec["episodes"])
                ),
                "shield_intervention_rate": s["shield_intervention_rate"],
                # NaN for eval.json written before safelane counted these (shown as "nan").
                "unsafe_action_rate": s.get("unsafe_action_rate", float("nan")),
                "vehicles_passed": s.get("mean_vehicles_passed", float("nan")),
                "fallback_rate": s["fallback_rate"],
                "collision_kinds": s["collision_kinds"],
                "train_wall_time_s": rec["train_wall_time_s"],
                "stress": rec.get("stress", []),
            }
            if "confirm" in rec:
                c = rec["confirm"]
                per_seed[str(seed)]["confirm"] = {
                    "simulator": c["simulator"],
                    "collision_rate": c["summary"]["collision_rate"],
                    "collisions": c["summary"]["collisions"],
                    "mean_speed": c["summary"]["mean_speed"],
                    "identical_episodes": c["identical_episodes"],
                    "episodes": c["episodes"],
                }
        if not per_seed:
            continue
        agg: dict[str, Any] = {}
        for key in ("collision_rate", "mean_speed", "mean_return", "return_before_collision"):
            values = [v[key] for v in per_seed.values()]
            agg[key] = {
                "mean": stats.mean(values),
                "iqm": stats.iqm(values),
                "ci95": list(stats.bootstrap_ci(values, seed=0)),  # one seed: [value, value]
            }
        collisions = sum(v["collisions"] for v in per_seed.values())
        n = sum(v["episodes"] for v in per_seed.values())
        agg["collisions"] = collisions
        agg["test_episodes"] = n
        agg["collision_rate_wilson95"] = list(stats.binomial_ci(collisions, n))
        confirms = [v["confirm"] for v in per_seed.values() if "confirm" in v]
        if confirms:
            c_coll, c_n = sum(c["collisions"] for c in confirms), sum(c["episodes"] for c in confirms)
            agg["confirm"] = {
                "simulator": confirms[0]["simulator"],
                "runs": len(confirms),
                "collisions": c_coll,
                "test_episodes": c_n,
                "collision_rate_wilson95": list(stats.binomial_ci(c_coll, c_n)),
                "mean_speed": stats.mean([c["mean_speed"] for c in confirms]),
                "identical_episodes": sum(c["identical_episodes"] for c in confirms),
            }
        methods[method] = {"per_seed": per_seed, "aggregate": agg}
    return {"spec": spec.model_dump(), "methods": methods, "episodes": all_episodes}
