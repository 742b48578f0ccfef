"""Where experiment tasks run: one interface, two backends (``local`` process pool, ``ray`` Ray Tune).

A *task* is a call ``fn(*args)`` of a picklable, module-level function that writes its own result files
(a run directory) and returns a small JSON-ready dict. :func:`run_tasks` runs a list of them and calls
``on_result(index, result)`` as each finishes, in completion order. Both backends run the same
function on the same arguments, so they produce the same files; the callers (``reproduce``,
``sweep``) skip tasks whose files exist, which is what makes a killed job resumable on either.

* ``local`` (default): a ``ProcessPoolExecutor`` on this machine, no server. A worker process that dies
  (killed, out of memory) breaks the pool; the tasks it had not finished are resubmitted to a new pool,
  each at most ``retries`` more times.
* ``ray``: each task is a Ray Tune trial (``tune.Tuner`` over ``grid_search`` of the task indices, one CPU
  each, ``FailureConfig(max_failures=retries)``) on the cluster at ``address`` (``auto``: the one
  ``ray start --head`` started; None: a local instance of ``workers`` CPUs started for this job). The
  tasks write to the output directory, so on a real cluster it must be on storage every node sees.

A task that raises :class:`ConfigError` (a bad value in its configuration) is not retried: its failure
is reported as a :class:`TaskFailure` with the one-line message, and the other tasks go on.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from safelane.config import ConfigError
from safelane.core.files import atomic_write_text

Backend = Literal["local", "ray"]
BACKENDS: tuple[str, ...] = ("local", "ray")


@dataclass(frozen=True)
class TaskFailure:
    """A task that did not produce a result: ``kind`` ``config`` (bad input, final) or ``error``."""

    kind: str
    message: str


def check_backend(backend: str) -> Backend:
    """``backend`` if known, else a one-line :class:`ConfigError` listing the backends."""
    if backend not in BACKENDS:
        raise ConfigError(f"--backend: got {backend!r}; allowed: {', '.join(BACKENDS)}")
    return backend  # type: ignore[return-value]


def _guarded(fn: Callable[..., dict[str, Any]], args: tuple[Any, ...]) -> dict[str, Any] | TaskFailure:
    """Run one task; a ConfigError becomes a final :class:`TaskFailure` (no retry)."""
    try:
        return fn(*args)
    except ConfigError as err:
        return TaskFailure("config", str(err))


def run_tasks(
    fn: Callable[..., dict[str, Any]],
    tasks: Sequence[tuple[Any, ...]],
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    on_result: Callable[[int, dict[str, Any] | TaskFailure], None] | None = None,
    retries: int = 1,
    name: str = "safelane",
    storage: Path | None = None,
) -> list[dict[str, Any] | TaskFailure]:
    """Run ``fn(*args)`` for every ``args`` in ``tasks`` on ``backend``; results in task order.

    ``workers``: processes (local) or CPUs of a local Ray instance (default: this machine's cores).
    ``retries``: extra attempts for a task whose worker died or that raised anything but a
    ConfigError. ``storage``: where Ray Tune keeps its own trial records (default: a temporary folder).
    """
    backend = check_backend(backend)
    if not tasks:
        return []
    workers = max(1, min(workers or os.cpu_count() or 1, len(tasks)))
    if backend == "ray":
        return _run_ray(fn, tasks, workers, address, on_result, retries, name, storage)
    if address is not None:
        raise ConfigError("--address: only with --backend ray")
    return _run_local(fn, tasks, workers, on_result, retries)


def _run_local(
    fn: Callable[..., dict[str, Any]],
    tasks: Sequence[tuple[Any, ...]],
    workers: int,
    on_result: Callable[[int, dict[str, Any] | TaskFailure], None] | None,
    retries: int,
) -> list[dict[str, Any] | TaskFailure]:
    results: dict[int, dict[str, Any] | TaskFailure] = {}
    attempts = dict.fromkeys(range(len(tasks)), 0)

    def finish(i: int, result: dict[str, Any] | TaskFailure) -> None:
        results[i] = result
        if on_result is not None:
            on_result(i, result)

    if workers == 1:  # in this process: simplest to debug, and what tests of one task use
        for i, args in enumerate(tasks):
            while True:
                attempts[i] += 1
                try:
                    finish(i, _guarded(fn, args))
                    break
                except Exception as err:
                    if attempts[i] > retries:
                        finish(i, TaskFailure("error", _one_line(err)))
                        break
        return [results[i] for i in range(len(tasks))]

    pending = list(range(len(tasks)))
    while pending:
        with ProcessPoolExecutor(max_workers=min(workers, len(pending))) as pool:
            futures: dict[Future[Any], int] = {}
            for i in pending:
                attempts[i] += 1
                futures[pool.submit(_guarded, fn, tasks[i])] = i
            retry: list[int] = []
            for fut in as_completed(futures):
                i = futures[fut]
                try:
                    finish(i, fut.result())
                except BrokenProcessPool:  # a worker died: every unfinished task of this pool is lost
                    if attempts[i] <= retries:
                        retry.append(i)
                    else:
                        finish(i, TaskFailure("error", "its worker process died (killed or out of memory)"))
                except Exception as err:
                    if attempts[i] <= retries:
                        retry.append(i)
                    else:
                        finish(i, TaskFailure("error", _one_line(err)))
        pending = sorted(retry)
    return [results[i] for i in range(len(tasks))]


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0]}" if text else type(err).__name__


def _run_ray(
    fn: Callable[..., dict[str, Any]],
    tasks: Sequence[tuple[Any, ...]],
    workers: int,
    address: str | None,
    on_result: Callable[[int, dict[str, Any] | TaskFailure], None] | None,
    retries: int,
    name: str,
    storage: Path | None,
) -> list[dict[str, Any] | TaskFailure]:
    import json
    import tempfile

    ray, tune = _import_ray()
    started_here = _start_ray(address, workers)
    task_list = list(tasks)

    def trainable(config: dict[str, Any]) -> dict[str, Any]:
        # The result goes through Tune as one JSON string: Tune flattens nested dicts of metrics.
        outcome = _guarded(fn, task_list[config["task"]])
        if isinstance(outcome, TaskFailure):
            return {"failure_kind": outcome.kind, "failure": outcome.message}
        return {"result_json": json.dumps(outcome)}

    tmp = None
    if storage is None:
        tmp = tempfile.TemporaryDirectory(prefix="safelane-ray-")
        storage = Path(tmp.name)
    try:
        tuner = tune.Tuner(
            tune.with_resources(trainable, {"cpu": 1}),
            param_space={"task": tune.grid_search(list(range(len(task_list))))},
            tune_config=tune.TuneConfig(max_concurrent_trials=workers if address is None else None),
            run_config=tune.RunConfig(
                name=name,
                storage_path=str(Path(storage).resolve()),
                failure_config=tune.FailureConfig(max_failures=retries),
                verbose=0,
            ),
        )
        grid = tuner.fit()
        results: list[dict[str, Any] | TaskFailure] = [TaskFailure("error", "no result")] * len(task_list)
        for trial in grid:
            i = int(trial.config["task"])
            metrics = trial.metrics or {}
            if trial.error is not None:
                outcome: dict[str, Any] | TaskFailure = TaskFailure("error", _one_line(trial.error))
            elif "result_json" in metrics:
                outcome = json.loads(metrics["result_json"])
            else:
                outcome = TaskFailure(str(metrics.get("failure_kind", "error")), str(metrics.get("failure", "")))
            results[i] = outcome
            if on_result is not None:
                on_result(i, outcome)
        return results
    finally:
        if started_here:
            ray.shutdown()
        if tmp is not None:
            tmp.cleanup()


def _import_ray() -> tuple[Any, Any]:
    try:
        import ray
        from ray import tune
    except ImportError:
        raise ConfigError("--backend ray: Ray is not installed; pip install 'safelane[ray]'") from None
    return ray, tune


def _start_ray(address: str | None, workers: int) -> bool:
    """Connect to the cluster at ``address`` (None: start a local instance of ``workers`` CPUs) unless
    this process is connected already; whether it connected here (and so must shut Ray down)."""
    ray, _ = _import_ray()
    _check_reachable(address)
    if ray.is_initialized():
        return False
    kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
    if address is None:
        kwargs["num_cpus"] = workers
    try:
        ray.init(address=address, **kwargs)
    except ConnectionError as err:
        raise ConfigError(f"--address {address}: no Ray cluster there ({_one_line(err)})") from None
    return True


@contextmanager
def backend_context(backend: str, workers: int | None = None, address: str | None = None) -> Iterator[None]:
    """Keep ``backend`` up across several :func:`run_tasks` calls (a TPE sweep's batches): on ``ray``,
    one connection (or local instance) for all of them instead of a Ray start per call; ``local``
    needs nothing."""
    backend = check_backend(backend)
    if backend != "ray":
        if address is not None:
            raise ConfigError("--address: only with --backend ray")
        yield
        return
    ray, _ = _import_ray()
    started_here = _start_ray(address, max(1, workers or os.cpu_count() or 1))
    try:
        yield
    finally:
        if started_here:
            ray.shutdown()


def _check_reachable(address: str | None, timeout_s: float = 5.0) -> None:
    """A ``HOST:PORT`` address that does not answer within ``timeout_s`` seconds is a one-line error
    (Ray itself retries for minutes before it gives up)."""
    if address is None or address == "auto" or "://" in address or ":" not in address:
        return
    import socket

    host, _, port = address.rpartition(":")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout_s):
            pass
    except (OSError, ValueError) as err:
        raise ConfigError(f"--address {address}: no Ray cluster answers there ({_one_line(err)})") from None


def claim_out_dir(out: Path, spec_json: str, file_name: str, kind: str) -> None:
    """Create ``out`` and keep the job's spec in ``out/file_name``; a folder already holding another
    spec (or not writable) is a one-line :class:`ConfigError` — a re-run resumes only the same job."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"--out {out}: not writable ({err.strerror})") from None
    path = out / file_name
    if path.is_file() and json.loads(path.read_text()) != json.loads(spec_json):
        raise ConfigError(f"--out {out}: holds a {kind} of another spec ({path}); give a new --out or delete it")
    atomic_write_text(path, spec_json)


def format_failure(failure: TaskFailure) -> str:
    """One line for a failed task."""
    return f"{failure.kind}: {failure.message}"
