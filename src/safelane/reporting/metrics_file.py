"""A training run's ``metrics.csv``: its columns, its writer and its reader, in one place.

The training loops (:mod:`safelane.running.training`, :mod:`safelane.running.batched_training`) write it,
one row per episode; the figures, the report and the bench read it back. It lives here, below both, so
the format has one definition and ``reporting`` needs nothing from ``running`` to read it.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from safelane.core.files import atomic_write

METRICS_FILE = "metrics.csv"
"""Per-episode training metrics in a run directory (columns :data:`METRIC_COLUMNS`)."""

METRIC_COLUMNS: tuple[str, ...] = (
    "episode",  # 1-based episode number
    "return",  # sum of eq. 6 rewards
    "length",  # decisions in the episode
    "collision",  # 1 if the episode ended in a crash
    "mean_speed",  # [m/s] mean ego speed after each decision
    "epsilon",  # ε of the episode's last decision
    "mean_loss",  # mean training loss over the episode's gradient steps (empty before learning starts)
    "shield_interventions",  # decisions whose action was unsafe under the mask ("would have been masked")
    "fallbacks",  # decisions where the shield found no safe action and allowed the least-bad one
    "invariant_breaks",  # fallback states reached right after an allowed action in a state with a safe one
    "lambda",  # constrained: λ after the episode's dual update (empty for other methods)
    "cost",  # constrained's episode cost: decisions that were unsafe or ended in a collision
    "wall_time_s",  # [s] cumulative training wall time at the end of the episode
    "env_time_s",  # [s] of it spent inside env.reset / env.step (simulator + shield); the rest is the agent's
    "env_steps",  # cumulative environment decisions
)
CONTINUOUS_METRIC_COLUMNS: tuple[str, ...] = (
    "episode",  # 1-based episode number
    "return",  # sum of the continuous reward (safelane.env.reward.ContinuousReward), less any adaptation penalty
    "length",  # decisions in the episode
    "collision",  # 1 if the episode ended in a crash
    "off_road",  # 1 if the episode ended with the ego off the road
    "mean_speed",  # [m/s] mean ego speed after each decision
    "cost",  # decisions that ended in a crash or off the road (the Lagrangian SAC's cost)
    "lambda",  # sac-lagrangian: λ after the episode's dual update (empty for the other algorithms)
    "shield_interventions",  # decisions whose action the shield projected or replaced
    "mean_projection_distance",  # mean distance (normalised actions) from the proposed to the executed action
    "wall_time_s",  # [s] cumulative training wall time at the end of the episode
    "env_time_s",  # [s] of it spent inside env.reset / env.step (simulator + shield); the rest is the agent's
    "env_steps",  # cumulative environment decisions
)
"""The columns of a continuous run's ``metrics.csv`` (``safelane train --algo``)."""
TIMING_COLUMNS = ("wall_time_s", "env_time_s")
"""Columns that measure time: they vary between identical runs."""

_BOOLEANS = {"true": 1.0, "false": 0.0}


def format_metrics_row(row: dict[str, Any], columns: Sequence[str] = METRIC_COLUMNS) -> dict[str, str]:
    """One row as written: ``None`` → empty cell, times to the µs, other floats in full (``repr``)."""
    out: dict[str, str] = {}
    for key in columns:
        value = row.get(key)
        if value is None:
            out[key] = ""
        elif isinstance(value, float):
            out[key] = f"{value:.6f}" if key in TIMING_COLUMNS else repr(value)  # to the µs: a decision costs tens
        else:
            out[key] = str(value)
    return out


def write_metrics(path: Path, rows: Iterable[dict[str, Any]], columns: Sequence[str] = METRIC_COLUMNS) -> None:
    """Write ``path`` anew, atomically: the header of ``columns`` and ``rows`` (a resume truncates rows past its
    checkpoint)."""

    def write(f: io.BufferedWriter) -> None:
        text = io.StringIO()
        writer = csv.DictWriter(text, fieldnames=columns, lineterminator="\n")
        writer.writeheader()
        writer.writerows(format_metrics_row(r, columns) for r in rows)
        f.write(text.getvalue().encode())

    atomic_write(path, write)


class MetricsAppender:
    """Appends rows to a ``metrics.csv`` that :func:`write_metrics` started, each flushed at once, so a run
    killed mid-episode keeps every finished episode's row."""

    def __init__(self, path: Path, columns: Sequence[str] = METRIC_COLUMNS) -> None:
        self._file = open(path, "a", newline="")  # noqa: SIM115 - closed in close()
        self._columns = tuple(columns)
        self._writer = csv.DictWriter(self._file, fieldnames=self._columns, lineterminator="\n")

    def append(self, row: dict[str, Any]) -> None:
        """Write one episode's row and flush it."""
        self._writer.writerow(format_metrics_row(row, self._columns))
        self._file.flush()

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> MetricsAppender:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, err: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def read_metrics(path: str | Path, columns: Sequence[str], optional: Sequence[str] = ()) -> dict[str, np.ndarray]:
    """The numeric ``columns`` (required) and ``optional`` columns (when present) of a metrics CSV.

    Values become float arrays (``True``/``False`` → 1/0, an empty cell → NaN, as training writes
    for e.g. ``mean_loss`` before learning starts). Raises :class:`FileNotFoundError` for a
    missing file and :class:`ValueError` naming the file for a missing required column or a
    non-numeric value.
    """
    path = Path(path)
    with path.open(newline="") as handle:
        reader = csv.DictReader(handle)
        header = reader.fieldnames or []
        missing = [c for c in columns if c not in header]
        if missing:
            raise ValueError(f"{path}: missing column(s) {missing}; has {header}")
        wanted = [*columns, *(c for c in optional if c in header)]
        values: dict[str, list[float]] = {c: [] for c in wanted}
        for line, row in enumerate(reader, start=2):
            for c in wanted:
                text = (row[c] or "").strip()
                try:
                    key = text.lower()
                    values[c].append(_BOOLEANS[key] if key in _BOOLEANS else float(text or "nan"))
                except ValueError:
                    raise ValueError(f"{path}:{line}: column {c!r} is not a number: {text!r}") from None
    return {c: np.asarray(v, dtype=float) for c, v in values.items()}
