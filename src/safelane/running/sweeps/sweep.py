"""Run a sweep: every (trial, seed) of a spec not yet done, on either backend, then its summary files."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from safelane.running.sweeps.spec import SweepSpec
from safelane.running.sweeps.trials import (
    eval_path,
    final_failure,
    run_trial_tasks,
    stored_spec,
    trial_dir,
    write_results,
)


def run_sweep(
    spec: SweepSpec,
    out_dir: str | Path,
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Run every (trial, seed) of ``spec`` not yet done into ``out_dir`` and write the summary files
    (``search: tpe``: batch by batch as the study proposes them, :func:`safelane.running.sweeps.tpe.run_tpe`).

    ``progress(done, total)`` is called as tasks finish. Returns the summary (also ``summary.json``).
    """
    from safelane.running.backend import check_backend, claim_out_dir

    check_backend(backend)
    out = Path(out_dir)
    if spec.search == "tpe":
        from safelane.running.sweeps.tpe import check_optuna, run_tpe

        check_optuna()  # before the folder is claimed: a missing extra leaves nothing behind
        spec = spec.with_batch(workers, stored_spec(out))
        claim_out_dir(out, spec.record_json(), "sweep.json", "sweep")
        run_tpe(spec, out, backend=backend, workers=workers, address=address, progress=progress)
        return write_results(out, spec)
    claim_out_dir(out, spec.record_json(), "sweep.json", "sweep")
    points = spec.points()
    tasks = [
        (index, seed)
        for index in range(len(points))
        for seed in range(spec.seeds)
        if not eval_path(out, spec, index, seed).is_file() and not final_failure(trial_dir(out, index), seed)
    ]
    total = len(points) * spec.seeds
    done = [total - len(tasks)]
    if progress is not None:
        progress(done[0], total)
    run_trial_tasks(
        out, spec, [(index, seed, None) for index, seed in tasks], done, total, progress,
        backend=backend, workers=workers, address=address, name=f"sweep-{spec.name}",
    )  # fmt: skip
    return write_results(out, spec)
