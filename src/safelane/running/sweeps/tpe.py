"""A model-based sweep: Optuna's TPE sampler proposes the trials, the task backend runs them (``search: tpe``).

The driver — this process, never a worker — owns the study: an in-memory Optuna study with
``TPESampler(seed=search_seed, n_startup_trials=…)``, used through ask/tell in synchronous batches of
``batch`` trials. Each batch is asked, written (``DIR/trials/tNNN/params.json``), run trial × seed
through :func:`safelane.running.backend.run_tasks` on either backend, and told back in trial order. The
proposals depend only on the seed and on what was told, and what is told is read from the trial
directories, so the same spec gives the same trials on ``local`` and ``ray``.

What is told: the objective's mean over the trial's seeds (the summary's number), with one constraint
value per spec constraint (how far the pooled metric is past its bound; > 0 infeasible), so TPE ranks
infeasible trials below every feasible one, by how far they miss. A trial with any failed seed is told
``FAIL``: TPE leaves it out of its model rather than learning from a made-up penalty, and its rows say
why. That failure is final for the study (a re-run does not retry it: the later proposals were drawn
without it).

Resuming: a re-run rebuilds the study by replaying it from a fresh seeded sampler. For each batch it
asks the points; a trial whose directory holds the same parameters and every seed's result (or
failure) is told from its files without running; the rest run. A stored trial whose parameters differ
from the replayed proposal (another Optuna version, an edited file) stops the sweep with a one-line
error naming it.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from safelane.config import ConfigError
from safelane.core.files import atomic_write_text
from safelane.running.sweeps.spec import SweepSpec
from safelane.running.sweeps.trials import (
    eval_path,
    failure_path,
    pooled_metrics,
    run_trial_tasks,
    trial_dir,
    trial_rows,
)

INSTALL_HINT = "search tpe: Optuna is not installed; pip install 'safelane[tune]'"


def check_optuna() -> None:
    """A one-line :class:`ConfigError` when Optuna (the ``tune`` extra) is missing."""
    try:
        import optuna  # noqa: F401
    except ImportError:
        raise ConfigError(INSTALL_HINT) from None


class TpeSearch:
    """The study of one TPE sweep: :meth:`ask` the next trial's parameters, :meth:`tell` its outcome.

    ``grid`` / ``choice`` keys are categorical over their values' positions (so any YAML value, a list
    too, can be a choice; TPE's categorical kernel only sees which one anyway); ``uniform`` /
    ``loguniform`` are floats, or integers with ``integer``, on a log scale for ``loguniform``.
    """

    def __init__(self, spec: SweepSpec) -> None:
        check_optuna()
        import optuna

        self.spec = spec
        # The study's own log says "Trial N finished" per tell; the sweep's progress and files say it.
        optuna.logging.set_verbosity(optuna.logging.WARNING)
        self._constraints = bool(spec.objective.constraints)
        # Optuna 5 reads constraints set on the trial; older versions only through constraints_func.
        self._set_constraint = hasattr(optuna.trial.Trial, "set_constraint")
        kwargs: dict[str, Any] = {}
        if self._constraints and not self._set_constraint:
            kwargs["constraints_func"] = lambda trial: trial.user_attrs["constraints"]
        with warnings.catch_warnings():
            # multivariate / constant_liar / constraints_func are "experimental" in some Optuna 3–4
            # releases; they are fixed here, so the warning would only be noise on every sweep.
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            sampler = optuna.samplers.TPESampler(
                seed=spec.search_seed,
                n_startup_trials=spec.startup(),
                # The margins of a shield interact; a joint model of the keys fits that better.
                multivariate=True,
                # A batch's later proposals see its earlier, still running ones as bad results and so
                # spread out instead of landing on the same spot.
                constant_liar=True,
                **kwargs,
            )
        direction = "maximize" if spec.objective.mode == "max" else "minimize"
        self.study = optuna.create_study(direction=direction, sampler=sampler)
        self._distributions = {key: _distribution(dim) for key, dim in spec.space.items()}
        self._trials: dict[int, Any] = {}

    def ask(self) -> tuple[int, dict[str, Any]]:
        """The next trial: its number (0, 1, …) and its parameters (the spec's values)."""
        from optuna.exceptions import ExperimentalWarning

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ExperimentalWarning)  # as above, raised when sampling in 3–4
            trial = self.study.ask(dict(self._distributions))
        self._trials[trial.number] = trial
        params = {}
        for key, dim in self.spec.space.items():
            value = trial.params[key]
            values = dim.grid if dim.grid is not None else dim.choice
            params[key] = values[value] if values is not None else value
        # Through JSON, as params.json stores it, so a replay compares like with like.
        return trial.number, json.loads(json.dumps(params))

    def tell(self, number: int, outcome: tuple[float, list[float]] | None) -> None:
        """Tell trial ``number`` its (objective, constraint values), or None: it failed."""
        from optuna.trial import TrialState

        trial = self._trials.pop(number)
        if outcome is None:
            self.study.tell(trial, state=TrialState.FAIL)
            return
        value, violations = outcome
        if self._constraints:
            if self._set_constraint:
                for i, excess in enumerate(violations):
                    trial.set_constraint(f"c{i}", excess)
            else:
                trial.set_user_attr("constraints", violations)
        self.study.tell(trial, value)


def _distribution(dim: Any) -> Any:
    from optuna.distributions import CategoricalDistribution, FloatDistribution, IntDistribution

    values = dim.grid if dim.grid is not None else dim.choice
    if values is not None:
        return CategoricalDistribution(list(range(len(values))))
    low, high = dim.uniform if dim.uniform is not None else dim.loguniform
    log = dim.loguniform is not None
    if dim.integer:
        return IntDistribution(math.ceil(low), math.floor(high), log=log)
    return FloatDistribution(float(low), float(high), log=log)


def trial_outcome(out: Path, spec: SweepSpec, index: int, params: dict[str, Any]) -> tuple[float, list[float]] | None:
    """What to tell for a finished trial, from its files: (mean objective over seeds, constraint
    values), or None when a seed failed (or the objective is not a number)."""
    from safelane.reporting import stats

    rows = trial_rows(out, spec, index, params)
    ok = [r for r in rows if r["status"] == "ok"]
    if len(ok) < spec.seeds:
        return None
    value = stats.mean([r[spec.objective.metric] for r in ok])
    if not math.isfinite(value):
        return None
    return value, spec.objective.violations(pooled_metrics(ok))


def _seed_settled(out: Path, spec: SweepSpec, index: int, seed: int) -> bool:
    """A TPE trial's seed is settled when it has a result or a failure of any kind: once told, a
    failure stays (see the module docstring)."""
    return eval_path(out, spec, index, seed).is_file() or failure_path(trial_dir(out, index), seed).is_file()


def _stored_params(out: Path, index: int) -> dict[str, Any] | None:
    path = trial_dir(out, index) / "params.json"
    return json.loads(path.read_text()) if path.is_file() else None


def run_tpe(
    spec: SweepSpec,
    out: Path,
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> None:
    """Run (or resume) the TPE sweep ``spec`` (its ``batch`` fixed, see :meth:`SweepSpec.with_batch`)
    into ``out``, batch by batch; the summary files are rebuilt after every task."""
    from safelane.running.backend import backend_context

    assert spec.batch is not None, "fix the batch first (SweepSpec.with_batch)"
    search = TpeSearch(spec)
    total = spec.samples * spec.seeds
    done = [0]
    with backend_context(backend, workers, address):
        for start in range(0, spec.samples, spec.batch):
            proposals = [search.ask() for _ in range(min(spec.batch, spec.samples - start))]
            tasks: list[tuple[int, int, str]] = []
            for index, params in proposals:
                stored = _stored_params(out, index)
                if stored is None:
                    # Written before the trial runs: a kill now leaves the proposal, checked on replay.
                    atomic_write_text(trial_dir(out, index) / "params.json", json.dumps(params))
                elif stored != params:
                    raise ConfigError(
                        f"--out {out}: trial t{index:03d} holds {stored} but the study now proposes {params} "
                        "(another Optuna version, or an edited params.json); give a new --out"
                    )
                todo = [s for s in range(spec.seeds) if not _seed_settled(out, spec, index, s)]
                done[0] += spec.seeds - len(todo)
                tasks += [(index, seed, json.dumps(params)) for seed in todo]
            if progress is not None:
                progress(done[0], total)

            run_trial_tasks(
                out, spec, tasks, done, total, progress, backend=backend, workers=workers,
                address=address, name=f"sweep-{spec.name}-b{start // spec.batch:03d}",
            )  # fmt: skip
            # In trial order, whatever order the tasks finished in: the study is then the same everywhere.
            for index, params in proposals:
                search.tell(index, trial_outcome(out, spec, index, params))
