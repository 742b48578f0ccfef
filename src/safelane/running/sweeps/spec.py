"""A sweep's spec: the method, the search space over ``--set`` keys, how to search it, the seeds, the training
length and the objective with its constraints (``configs/sweeps/*.yaml``)."""

from __future__ import annotations

import itertools
import json
import math
import os
import re
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from safelane.config import ConfigError, validation_message

METRICS: tuple[str, ...] = (
    "mean_speed",
    "collision_rate",
    "mean_return",
    "return_before_collision",
    "fallback_rate",
    "shield_intervention_rate",
    "mean_vehicles_passed",
)
"""Test metrics a trial reports (per seed) and an objective or constraint may name."""
COMMITTED_METRICS: tuple[str, ...] = ("plan_forced_rate", "lapses", "lapses_in_model")
"""Test metrics a trial under the committed shield also reports (per seed, beside ``fallback_rate``): the share of
decisions the kept plan drove, and the lapses (counts, pooled over seeds as sums) and those in the model."""

_CONSTRAINT = re.compile(r"^\s*([a-z_]+)\s*(<=|>=|<|>)\s*([-+0-9.eE]+)\s*$")

SEARCHES: tuple[str, ...] = ("grid", "random", "tpe")
TPE_FIELDS: tuple[str, ...] = ("batch", "startup_trials")
"""Spec fields only a ``tpe`` search has (left out of a grid or random sweep's sweep.json)."""


class Dimension(BaseModel):
    """One key's values: exactly one of ``grid`` (the values, in order), ``choice`` (values drawn
    uniformly by random search), ``uniform`` / ``loguniform`` ([low, high] for random search);
    ``integer`` rounds drawn numbers. TPE sees ``grid`` / ``choice`` as categories and the ranges as
    floats or (``integer``) integers, on a log scale for ``loguniform``."""

    model_config = ConfigDict(extra="forbid")

    grid: list[Any] | None = None
    choice: list[Any] | None = None
    uniform: tuple[float, float] | None = None
    loguniform: tuple[float, float] | None = None
    integer: bool = False

    @model_validator(mode="after")
    def _exactly_one(self) -> Dimension:
        given = [k for k in ("grid", "choice", "uniform", "loguniform") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(f"give exactly one of grid, choice, uniform, loguniform (got {given or 'none'})")
        values = self.grid if self.grid is not None else self.choice
        if values is not None and not values:
            raise ValueError("an empty list of values")
        bounds = self.uniform or self.loguniform
        if bounds is not None and not bounds[0] < bounds[1]:
            raise ValueError(f"bounds must be increasing (got {list(bounds)})")
        if self.loguniform is not None and self.loguniform[0] <= 0:
            raise ValueError(f"loguniform bounds must be > 0 (got {list(self.loguniform)})")
        return self

    def draw(self, rng: np.random.Generator) -> Any:
        """One value for random search."""
        if self.grid is not None or self.choice is not None:
            values = self.grid if self.grid is not None else self.choice
            return values[int(rng.integers(len(values)))]  # type: ignore[index, arg-type]
        if self.uniform is not None:
            value = float(rng.uniform(*self.uniform))
        else:
            low, high = self.loguniform  # type: ignore[misc]
            value = float(math.exp(rng.uniform(math.log(low), math.log(high))))
        return round(value) if self.integer else value


class Objective(BaseModel):
    """What ranks the trials: the mean over seeds of a test ``metric``, maximised or minimised, among
    trials whose pooled test metrics satisfy every ``constraints`` entry (``METRIC OP NUMBER``)."""

    model_config = ConfigDict(extra="forbid")

    metric: Literal[METRICS] = "mean_speed"  # type: ignore[valid-type]
    mode: Literal["max", "min"] = "max"
    constraints: list[str] = Field(default_factory=list)

    @field_validator("constraints")
    @classmethod
    def _parse(cls, items: list[str]) -> list[str]:
        for item in items:
            m = _CONSTRAINT.match(item)
            if m is None or m.group(1) not in METRICS:
                raise ValueError(f"'{item}': expected 'METRIC OP NUMBER' with METRIC one of {', '.join(METRICS)}")
        return items

    def satisfied(self, metrics: dict[str, float]) -> bool:
        """Whether ``metrics`` (pooled over a trial's seeds) meet every constraint."""
        return all(v <= 0 for v in self.violations(metrics))

    def violations(self, metrics: dict[str, float]) -> list[float]:
        """Per constraint, how far ``metrics`` are past its bound (in the metric's units): ≤ 0 when it
        holds, > 0 when not (Optuna's convention for constraint values)."""
        out = []
        for item in self.constraints:
            name, op, bound = _CONSTRAINT.match(item).groups()  # type: ignore[union-attr]
            value, limit = metrics[name], float(bound)
            excess = value - limit if op in ("<=", "<") else limit - value
            # A strict bound met with equality is violated: report it as a tiny positive excess.
            out.append(max(excess, 1e-12) if op in ("<", ">") and excess == 0 else excess)
        return out


class SweepSpec(BaseModel):
    """A sweep (see the module docstring). Units: episodes of the environment preset (40 s each)."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field("sweep", description="A name for the sweep (reports).")
    description: str = Field("", description="What the sweep searches and why.")
    method: Literal["dqn", "constrained", "qmask", "robust"]
    agent_preset: str = "tuned"
    env_preset: Literal["fast", "paper"] = "fast"
    sets: list[str] = Field(default_factory=lambda: ["simulator=fast"], description="--set overrides of every trial.")
    space: dict[str, Dimension] = Field(description="KEY → values; KEY is any --set key.")
    search: Literal["grid", "random", "tpe"] = "grid"
    samples: int = Field(8, ge=1, description="random: points drawn; tpe: trials (required).")
    batch: int | None = Field(
        None, ge=1, description="tpe: trials proposed and run at once (default: --workers, else the cores)."
    )
    startup_trials: int | None = Field(
        None, ge=1, description="tpe: random trials before TPE models the results (default: samples // 3, ≥ 2)."
    )
    search_seed: int = Field(0, ge=0, description="random, tpe: seed of the draws.")
    seeds: int = Field(3, ge=1, description="Seeds per point: 0..seeds-1.")
    episodes: int = Field(200, ge=1, description="Training episodes per run.")
    test_episodes: int = Field(100, ge=1, description="Held-out test episodes per run.")
    objective: Objective = Field(default_factory=Objective)

    @field_validator("space")
    @classmethod
    def _space(cls, space: dict[str, Dimension]) -> dict[str, Dimension]:
        if not space:
            raise ValueError("an empty search space; give at least one KEY")
        return space

    @model_validator(mode="after")
    def _fits_the_search(self) -> SweepSpec:
        # ConfigError, not ValueError: validation_message then gives this line as it is (it names the key).
        if self.search == "grid":
            ranged = [k for k, d in self.space.items() if d.grid is None and d.choice is None]
            if ranged:
                raise ConfigError(
                    f"search grid: '{ranged[0]}' has a range; give it a grid list or use search: random or tpe"
                )
        if self.search != "tpe":
            given = [k for k in TPE_FIELDS if getattr(self, k) is not None]
            if given:
                raise ConfigError(f"{given[0]}: only with search: tpe (search is {self.search})")
            return self
        if "samples" not in self.model_fields_set:
            raise ConfigError("samples: search tpe needs the number of trials, e.g. samples: 12")
        for key, dim in self.space.items():
            bounds = dim.uniform or dim.loguniform
            if dim.integer and bounds is not None and math.ceil(bounds[0]) > math.floor(bounds[1]):
                raise ConfigError(f"space.{key}: integer, but no integer lies in {list(bounds)}")
        return self

    def startup(self) -> int:
        """tpe: the random trials before TPE models the results (a third of the budget unless given)."""
        return self.startup_trials if self.startup_trials is not None else max(2, self.samples // 3)

    def record_json(self) -> str:
        """The spec as kept in ``DIR/sweep.json`` (a grid or random sweep without the tpe-only fields, so a
        folder written before they existed still resumes)."""
        exclude = set() if self.search == "tpe" else set(TPE_FIELDS)
        return self.model_dump_json(indent=1, exclude=exclude)

    def with_batch(self, workers: int | None, stored: dict[str, Any] | None = None) -> SweepSpec:
        """tpe: the spec with its batch size fixed: as given, else the batch the folder's study ran with
        (``stored``: its sweep.json; a resumed study keeps its batches whatever ``--workers`` is), else
        ``workers`` (default: this machine's cores)."""
        if self.search != "tpe" or self.batch is not None:
            return self
        if stored is not None and stored.get("batch"):
            mine = json.loads(self.record_json())
            if {**mine, "batch": stored["batch"]} == stored:
                return self.model_copy(update={"batch": int(stored["batch"])})
        return self.model_copy(update={"batch": workers or os.cpu_count() or 1})

    def points(self) -> list[dict[str, Any]]:
        """The trials' parameters, in trial order (the same for every run of the same spec); grid and
        random only (TPE's depend on the results: :func:`~safelane.running.sweeps.trials.trial_points`)."""
        if self.search == "tpe":
            raise ValueError("search tpe: the points come from the study (trial_points)")
        keys = list(self.space)
        if self.search == "grid":
            lists = [self.space[k].grid if self.space[k].grid is not None else self.space[k].choice for k in keys]
            return [dict(zip(keys, combo, strict=True)) for combo in itertools.product(*lists)]  # type: ignore[arg-type]
        rng = np.random.default_rng(self.search_seed)
        return [{k: self.space[k].draw(rng) for k in keys} for _ in range(self.samples)]


def load_sweep_spec(path: str | Path, overrides: dict[str, Any] | None = None) -> SweepSpec:
    """Read a sweep spec YAML (``overrides``: fields set on top, e.g. ``episodes`` for a smoke run);
    a one-line :class:`ConfigError` on a missing file or a bad field."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise ConfigError(f"sweep spec {path}: no such file") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"sweep spec {path}: not valid YAML ({str(err).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"sweep spec {path}: expected a mapping of fields, got {type(data).__name__}")
    data.update({k: v for k, v in (overrides or {}).items() if v is not None})
    try:
        return SweepSpec.model_validate(data)
    except ValidationError as err:
        raise ConfigError(f"sweep spec {path}: {validation_message(err, SweepSpec)}") from None
