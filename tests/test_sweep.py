"""Sweeps and the task backend: specs, trials.csv, best.yaml, failures, kills, and both backends (real
training on tiny budgets)."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from safelane.agents.dqn import load_agent_config
from safelane.config import ConfigError
from safelane.running.backend import TaskFailure, run_tasks
from safelane.running.sweeps import SweepSpec, load_sweep_spec, run_sweep

TINY = ["simulator=fast", "env.duration=3", "env.vehicles_count=10"]
SWEEPS = Path(__file__).resolve().parents[1] / "configs" / "sweeps"


def write_spec(path: Path, **fields: object) -> Path:
    data = {
        "name": "tiny",
        "method": "qmask",
        "sets": TINY,
        "space": {"agent.lr": {"grid": [0.001, 0.0005]}, "shield.margin": {"grid": [1.0, 2.0]}},
        "seeds": 1,
        "episodes": 1,
        "test_episodes": 1,
        "objective": {"metric": "mean_speed", "mode": "max", "constraints": ["collision_rate <= 0.5"]},
    }
    data.update(fields)
    path.write_text(yaml.safe_dump(data))
    return path


def rows_of(out: Path) -> list[dict[str, str]]:
    with open(out / "trials.csv") as f:
        return [{k: v for k, v in row.items() if k != "train_wall_time_s"} for row in csv.DictReader(f)]


# --- specs -----------------------------------------------------------------------------------------


def test_points_grid_in_order_and_random_reproducible(tmp_path: Path) -> None:
    spec = load_sweep_spec(write_spec(tmp_path / "s.yaml"))
    assert spec.points() == [
        {"agent.lr": 0.001, "shield.margin": 1.0},
        {"agent.lr": 0.001, "shield.margin": 2.0},
        {"agent.lr": 0.0005, "shield.margin": 1.0},
        {"agent.lr": 0.0005, "shield.margin": 2.0},
    ]
    space = {"agent.lr": {"loguniform": [1e-4, 1e-2]}, "agent.batch_size": {"uniform": [16, 128], "integer": True}}
    random = load_sweep_spec(write_spec(tmp_path / "r.yaml", space=space, search="random", samples=5))
    points = random.points()
    assert points == random.points() and len(points) == 5
    assert all(1e-4 <= p["agent.lr"] <= 1e-2 and isinstance(p["agent.batch_size"], int) for p in points)


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"methd": "dqn"}, "methd: unknown key"),
        ({"space": {"agent.lr": {"uniform": [0.1, 0.01]}}}, "bounds must be increasing"),
        ({"space": {"agent.lr": {"uniform": [0.001, 0.01]}}}, "has a range; give it a grid list"),
        ({"space": {}}, "an empty search space"),
        ({"objective": {"constraints": ["speed < 3"]}}, "expected 'METRIC OP NUMBER'"),
        ({"method": "ppo"}, "method"),
        ({"search": "bayes"}, "search: got 'bayes'; .*'grid', 'random' or 'tpe'"),
        ({"search": "tpe"}, "samples: search tpe needs the number of trials"),
        ({"search": "tpe", "samples": 4, "batch": 0}, "batch: Input should be greater than or equal to 1"),
        ({"batch": 2}, r"batch: only with search: tpe \(search is grid\)"),
        (
            {"search": "tpe", "samples": 4, "space": {"agent.batch_size": {"uniform": [16.2, 16.8], "integer": True}}},
            r"space.agent.batch_size: integer, but no integer lies in \[16.2, 16.8\]",
        ),
    ],
)
def test_bad_specs_are_one_line_errors(tmp_path: Path, fields: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message) as err:
        load_sweep_spec(write_spec(tmp_path / "s.yaml", **fields))
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="no such file"):
        load_sweep_spec(tmp_path / "missing.yaml")


def test_the_shipped_paper_searches_are_valid_specs() -> None:
    specs = {p.stem: load_sweep_spec(p) for p in sorted(SWEEPS.glob("*.yaml"))}
    paper = {"dqn_collision_penalty", "constrained_budget", "qmask_margin", "robust_margin"}
    assert set(specs) == {*paper, "robust_tpe"}
    assert all(s.seeds >= 3 and s.sets == ["simulator=fast"] for s in specs.values())
    grid, tpe = specs["robust_margin"], specs["robust_tpe"]  # TPE over the grid's box, judged the same way
    assert tpe.search == "tpe" and tpe.batch is not None and tpe.objective == grid.objective
    assert (tpe.seeds, tpe.episodes, tpe.test_episodes) == (grid.seeds, grid.episodes, grid.test_episodes)
    for key, dim in tpe.space.items():
        bounds = dim.uniform or dim.loguniform
        assert bounds == (min(grid.space[key].grid), max(grid.space[key].grid))


# --- the local backend ------------------------------------------------------------------------------


def test_local_sweep_writes_rows_best_preset_and_resumes(tmp_path: Path) -> None:
    """A 2×2 grid, one seed each: 4 rows in trials.csv, a summary, a best.yaml that loads as an agent
    preset with the best trial's agent value; re-running trains nothing again."""
    spec = load_sweep_spec(write_spec(tmp_path / "s.yaml"))
    out = tmp_path / "out"
    summary = run_sweep(spec, out, workers=1)
    rows = rows_of(out)
    assert [(r["trial"], r["seed"], r["status"]) for r in rows] == [(str(i), "0", "ok") for i in range(4)]
    assert {r["shield.margin"] for r in rows} == {"1.0", "2.0"}
    best = summary["best"]
    assert best is not None and best["objective"] == max(t["objective"] for t in summary["trials"])
    preset = load_agent_config(str(out / "best.yaml"), "qmask")
    assert preset.lr == best["params"]["agent.lr"]
    assert f"--set shield.margin={best['params']['shield.margin']}" in (out / "best.yaml").read_text()
    assert "**best**" in (out / "summary.md").read_text()
    assert (out / "objective_agent.lr.png").is_file()
    evals = sorted(out.glob("trials/*/runs/*/eval.json"))
    stamps = [p.stat().st_mtime_ns for p in evals]
    again = run_sweep(spec, out, workers=1)
    assert [p.stat().st_mtime_ns for p in evals] == stamps and again["best"] == best
    other = load_sweep_spec(write_spec(tmp_path / "o.yaml", seeds=2))
    with pytest.raises(ConfigError, match="holds a sweep of another spec"):
        run_sweep(other, out, workers=1)


def test_a_bad_value_fails_its_trial_not_the_sweep(tmp_path: Path) -> None:
    spec = load_sweep_spec(write_spec(tmp_path / "s.yaml", space={"agent.lr": {"grid": [0.001, -1.0]}}))
    summary = run_sweep(spec, tmp_path / "out", workers=1)
    rows = rows_of(tmp_path / "out")
    assert [r["status"] for r in rows] == ["ok", "failed"]
    assert rows[1]["error"].startswith("config: agent.lr") and "\n" not in rows[1]["error"]
    assert summary["best"]["trial"] == 0


def _die_once(marker: str, value: int) -> dict:
    """A task whose worker process dies the first time it runs (to test the retry)."""
    path = Path(marker)
    if not path.exists():
        path.write_text("died")
        os._exit(1)
    return {"value": value}


def _bad_config(value: int) -> dict:
    raise ConfigError(f"agent.lr: bad value {value}")


def test_a_dead_worker_loses_only_its_tasks_which_are_retried(tmp_path: Path) -> None:
    results = run_tasks(_die_once, [(str(tmp_path / "m"), 1), (str(tmp_path / "m"), 2)], workers=2)
    assert results == [{"value": 1}, {"value": 2}]
    failures = run_tasks(_bad_config, [(3,)], workers=1)
    assert failures == [TaskFailure("config", "agent.lr: bad value 3")]


def kill_after_first_trial_and_rerun(spec_path: Path, out: Path) -> subprocess.CompletedProcess:
    """Run ``safelane sweep`` as a process, SIGKILL it once a first trial has finished, run it again to
    the end; assert the finished trials' results were not rewritten. Returns the second run."""
    args = [sys.executable, "-m", "safelane.cli", "sweep", str(spec_path), "--out", str(out), "--workers", "1"]
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    proc = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 240
    while not list(out.glob("trials/*/runs/*/eval.json")) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    first = sorted(out.glob("trials/*/runs/*/eval.json"))
    assert first, "the sweep was killed before its first trial finished"
    kept = {p: p.read_text() for p in first}
    done = subprocess.run(args, env=env, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr
    assert all(p.read_text() == text for p, text in kept.items())
    return done


def test_a_killed_sweep_resumes_without_repeating_or_losing_rows(tmp_path: Path) -> None:
    spec_path = write_spec(tmp_path / "s.yaml")
    out = tmp_path / "out"
    done = kill_after_first_trial_and_rerun(spec_path, out)
    rows = rows_of(out)
    assert sorted((r["trial"], r["seed"]) for r in rows) == [(str(i), "0") for i in range(4)]
    assert "best: t" in done.stdout


# --- the Ray backend ----------------------------------------------------------------------------------


def test_ray_backend_gives_the_local_rows(tmp_path: Path) -> None:
    """The same sweep (two points: one trial per Ray worker; the 2×2 grid took 15 s longer) on a local Ray
    instance (2 CPUs) gives the local backend's rows."""
    pytest.importorskip("ray.tune")
    spec = load_sweep_spec(write_spec(tmp_path / "s.yaml", space={"agent.lr": {"grid": [0.001, 0.0005]}}))
    run_sweep(spec, tmp_path / "local", workers=2)
    run_sweep(spec, tmp_path / "ray", backend="ray", workers=2)
    assert rows_of(tmp_path / "ray") == rows_of(tmp_path / "local")


@pytest.mark.slow  # a second Ray instance (≈ 25 s); the tasks go through the same backend as the sweep's above
def test_reproduce_on_ray_gives_the_local_results(tmp_path: Path) -> None:
    """reproduce on Ray gives the local runner's results."""
    pytest.importorskip("ray.tune")
    from safelane.running.experiments import make_spec, run_experiment

    small = make_spec(methods=["dqn", "robust"], seeds=[0], episodes=1, test_episodes=2, sets=TINY, quick=True)
    local = run_experiment(small, tmp_path / "rep-local", workers=2)
    remote = run_experiment(small, tmp_path / "rep-ray", workers=2, backend="ray")
    assert json.dumps(remote["episodes"], sort_keys=True) == json.dumps(local["episodes"], sort_keys=True)


def test_backend_names_are_checked() -> None:
    with pytest.raises(ConfigError, match="--backend: got 'slurm'; allowed: local, ray"):
        run_tasks(_bad_config, [(1,)], backend="slurm")
    with pytest.raises(ConfigError, match="--address: only with --backend ray"):
        run_tasks(_bad_config, [(1,)], address="auto")
    pytest.importorskip("ray")
    with pytest.raises(ConfigError, match=r"--address 127\.0\.0\.1:9: no Ray cluster answers there"):
        run_tasks(_bad_config, [(1,)], backend="ray", address="127.0.0.1:9")


# --- TPE (Optuna) -------------------------------------------------------------------------------------

TPE_SPACE = {"agent.lr": {"loguniform": [1e-4, 1e-2]}, "shield.margin": {"choice": [1.0, 2.0]}}


def tpe_spec(tmp_path: Path, **fields: object) -> SweepSpec:
    return load_sweep_spec(
        write_spec(tmp_path / "tpe.yaml", **{"space": TPE_SPACE, "search": "tpe", "samples": 4, "batch": 2, **fields})
    )


def test_tpe_proposals_are_seeded_typed_and_steered_by_the_constraints(tmp_path: Path) -> None:
    """No training: the study alone. The same seed gives the same points; each key gets its kind of
    value; told "faster below, infeasible under 1 m", the model-based proposals gather near 1 m."""
    pytest.importorskip("optuna")
    from safelane.running.sweeps.tpe import TpeSearch

    space = {
        "agent.lr": {"loguniform": [1e-4, 1e-2]},
        "agent.batch_size": {"uniform": [16, 128], "integer": True},
        "agent.hidden": {"choice": [[64], [100, 100]]},  # a list value: TPE sees its position only
    }

    def proposals(seed: int) -> list[dict]:
        search = TpeSearch(tpe_spec(tmp_path, space=space, samples=6, search_seed=seed))
        asked = [search.ask() for _ in range(6)]
        for number, params in asked:
            search.tell(number, (params["agent.lr"], []) if number != 2 else None)  # trial 2 failed
        return [params for _, params in asked] + [search.ask()[1]]

    points = proposals(0)
    assert points == proposals(0) and points != proposals(1)
    assert all(1e-4 <= p["agent.lr"] <= 1e-2 and isinstance(p["agent.lr"], float) for p in points)
    assert all(isinstance(p["agent.batch_size"], int) and 16 <= p["agent.batch_size"] <= 128 for p in points)
    assert {tuple(p["agent.hidden"]) for p in points} <= {(64,), (100, 100)}

    margin = {"shield.margin": {"uniform": [0.0, 4.0]}}
    spec = tpe_spec(tmp_path, space=margin, samples=20, startup_trials=6, search_seed=0)
    search, margins = TpeSearch(spec), []
    for _ in range(10):
        batch = [search.ask() for _ in range(2)]
        for number, params in batch:
            x = params["shield.margin"]
            margins.append(x)
            search.tell(number, (-x, [1.0 - x]))  # objective: -margin; constraint value > 0 below 1 m
    late = margins[10:]
    # Uniform draws would put a quarter of them in [0.5, 1.5] (≥ 5 of 10: p ≈ 0.08).
    assert sum(0.5 <= x <= 1.5 for x in late) >= 5, late


def test_tpe_batch_defaults_to_workers_and_a_resumed_study_keeps_its_own(tmp_path: Path) -> None:
    spec = tpe_spec(tmp_path, batch=None)
    assert spec.batch is None and spec.with_batch(3).batch == 3
    stored = json.loads(spec.with_batch(2).record_json())  # the folder's sweep.json after a --workers 2 run
    assert spec.with_batch(1, stored).batch == 2
    other = json.loads(tpe_spec(tmp_path, batch=None, samples=6).with_batch(2).record_json())
    assert spec.with_batch(1, other).batch == 1  # another spec: claim_out_dir then refuses the folder
    assert "batch" not in json.loads(load_sweep_spec(write_spec(tmp_path / "g.yaml")).record_json())


def test_constraint_values_are_the_excess_past_each_bound(tmp_path: Path) -> None:
    objective = load_sweep_spec(
        write_spec(tmp_path / "s.yaml", objective={"constraints": ["collision_rate <= 0.01", "mean_speed > 20"]})
    ).objective
    assert objective.violations({"collision_rate": 0.03, "mean_speed": 21.5}) == pytest.approx([0.02, -1.5])
    assert not objective.satisfied({"collision_rate": 0.03, "mean_speed": 21.5})
    at_bounds = objective.violations({"collision_rate": 0.01, "mean_speed": 20.0})
    assert at_bounds[0] == 0 and at_bounds[1] > 0  # <= holds at its bound, > does not
    assert objective.satisfied({"collision_rate": 0.0, "mean_speed": 20.1})


def test_tpe_without_optuna_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "optuna", None)  # import optuna now raises ImportError
    spec = tpe_spec(tmp_path)
    with pytest.raises(ConfigError, match=r"^search tpe: Optuna is not installed; pip install 'safelane\[tune\]'$"):
        run_sweep(spec, tmp_path / "out", workers=1)
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def tpe_local(tmp_path_factory: pytest.TempPathFactory) -> tuple[SweepSpec, Path]:
    """A finished tiny TPE sweep (4 trials in 2 batches, one seed, one worker) and its folder."""
    pytest.importorskip("optuna")
    base = tmp_path_factory.mktemp("tpe")
    spec = tpe_spec(base)
    run_sweep(spec, base / "local", workers=1)
    return spec, base / "local"


def test_tpe_sweep_writes_the_proposed_trials(tpe_local: tuple[SweepSpec, Path]) -> None:
    _, out = tpe_local
    rows = rows_of(out)
    assert [(r["trial"], r["seed"], r["status"]) for r in rows] == [(str(i), "0", "ok") for i in range(4)]
    stored = [json.loads((out / "trials" / f"t{i:03d}" / "params.json").read_text()) for i in range(4)]
    assert [float(r["agent.lr"]) for r in rows] == [p["agent.lr"] for p in stored]
    assert len({p["agent.lr"] for p in stored}) == 4 and {p["shield.margin"] for p in stored} <= {1.0, 2.0}
    summary = json.loads((out / "summary.json").read_text())
    assert summary["search"] == {"kind": "tpe", "samples": 4, "search_seed": 0, "batch": 2, "startup_trials": 2}
    assert summary["complete"] and summary["best"] is not None
    table = (out / "summary.md").read_text()
    assert "Search: Optuna TPE, 4 trials in batches of 2" in table
    assert f"| t000 | {stored[0]['agent.lr']:.4g} | " in table.replace(" **best**", "")  # short in the table


def test_a_tpe_sweep_resumes_by_replaying_the_study(tpe_local: tuple[SweepSpec, Path], tmp_path: Path) -> None:
    """A kill during the second batch, as the folder shows it: t002 finished, t003 proposed but its run
    lost, trials.csv gone. The re-run tells t000–t002 from their files (no training) and runs t003
    at the same point: the rows of the uninterrupted sweep. An edited trial stops it in one line."""
    spec, full = tpe_local
    out = tmp_path / "out"
    shutil.copytree(full, out)
    shutil.rmtree(out / "trials" / "t003" / "runs")
    (out / "trials.csv").unlink()
    kept = sorted(out.glob("trials/*/runs/*/eval.json"))
    stamps = [p.stat().st_mtime_ns for p in kept]
    assert len(kept) == 3
    run_sweep(spec, out, workers=2)  # another --workers: the spec's batch keeps the same study
    assert [p.stat().st_mtime_ns for p in kept] == stamps
    assert rows_of(out) == rows_of(full)

    edited = out / "trials" / "t001" / "params.json"
    edited.write_text(json.dumps({**json.loads(edited.read_text()), "agent.lr": 0.005}))
    with pytest.raises(ConfigError, match=r"trial t001 holds .* but the study now proposes") as err:
        run_sweep(spec, out, workers=1)
    assert "\n" not in str(err.value)


@pytest.mark.slow  # ≈ 100 s on 2 loaded cores: every batch starts Ray Tune trial processes
def test_tpe_on_ray_gives_the_local_rows(tpe_local: tuple[SweepSpec, Path], tmp_path: Path) -> None:
    """The same TPE spec on a local Ray instance (2 CPUs): the same proposals, the same rows."""
    pytest.importorskip("ray.tune")
    spec, local = tpe_local
    run_sweep(spec, tmp_path / "ray", backend="ray", workers=2)
    assert rows_of(tmp_path / "ray") == rows_of(local)


@pytest.mark.slow  # ≈ 1 min: a CLI process killed and re-run (the fast test above reads the same state)
def test_a_killed_tpe_sweep_resumes_without_repeating_or_losing_rows(
    tpe_local: tuple[SweepSpec, Path], tmp_path: Path
) -> None:
    _, full = tpe_local
    spec_path = tmp_path / "tpe.yaml"
    shutil.copy(full.parent / "tpe.yaml", spec_path)
    out = tmp_path / "out"
    kill_after_first_trial_and_rerun(spec_path, out)
    assert rows_of(out) == rows_of(full)


def test_a_committed_shield_sweep_reports_plan_forced_decisions_and_lapses_beside_the_fallback_rate(
    tmp_path: Path,
) -> None:
    committed = ["shield.mode=committed", "shield.engine=numpy"]
    spec = load_sweep_spec(
        write_spec(tmp_path / "s.yaml", sets=[*TINY, *committed], space={"agent.lr": {"grid": [0.001]}})
    )
    out = tmp_path / "out"
    summary = run_sweep(spec, out, workers=1)
    (row,) = rows_of(out)
    assert row["status"] == "ok"
    for key in ("plan_forced_rate", "lapses", "lapses_in_model", "fallback_rate"):
        assert row[key] != "", key
    assert 0 <= float(row["plan_forced_rate"]) <= 1 and 0 <= float(row["lapses_in_model"]) <= float(row["lapses"])
    pooled = summary["trials"][0]["metrics"]
    assert {"plan_forced_rate", "lapses", "lapses_in_model", "fallback_rate"} <= set(pooled)
    assert pooled["plan_forced_rate"] == float(row["plan_forced_rate"])
    assert "plan-forced rate" in (out / "summary.md").read_text()


def test_a_sweep_under_another_shield_has_no_committed_columns(tmp_path: Path) -> None:
    from safelane.running.sweeps.trials import pooled_metrics, summarize_trials, summary_markdown

    spec = load_sweep_spec(write_spec(tmp_path / "s.yaml", space={"agent.lr": {"grid": [0.001]}}))
    ok = {"trial": 0, "seed": 0, "agent.lr": 0.001, "status": "ok", "mean_speed": 20.0, "collision_rate": 0.0,
          "fallback_rate": 0.01, "collisions": 0.0, "test_episodes": 1.0}  # fmt: skip
    assert "plan_forced_rate" not in pooled_metrics([ok])
    text = summary_markdown(spec, summarize_trials(spec, [ok]))
    assert "plan-forced" not in text and "| t000 **best** | 0.001 | 20.000" in text
