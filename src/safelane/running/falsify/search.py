"""A cross-entropy-method (CEM) search for the traffic conditions where the shield breaks its invariant most often.

The grid campaign (:mod:`safelane.running.falsify.grid`) plays every combination of a few settings. A
search spec (:class:`SearchSpec`; the shipped one is ``configs/falsify/search_cem.yaml``) instead names
traffic *parameters* — continuous ranges (``env.vehicles_density``, ``env.ego_spacing``; ``integer:
true`` for counts such as ``traffic.vehicles_behind``) and categorical choices (``env.lanes_count``, a
decision rate with its physics rate, a driver model) — and the CEM loop below steers the sampling
distribution toward the conditions with the most invariant breaks per 1 000 decisions:

1. draw ``population`` conditions from the current distribution (a Gaussian per range, clipped to it;
   a categorical distribution per choice), seeded by ``(search.seed, iteration)``;
2. play each one as a campaign cell (:func:`safelane.running.falsify.grid.play_cell`: ``episodes_per_sample``
   episodes, every crash and break saved as a replayable file, breaks classed);
3. rank the samples by the objective (ties: more collisions first, then the earlier sample), keep the
   best ``elite_fraction`` (:func:`select_elite`) and refit the distribution to them (:func:`cem_update`:
   the elite's mean and standard deviation, its choice frequencies; mixed with the old distribution by
   ``smoothing``; σ kept above ``min_std`` × the range's width). An iteration whose samples all tie (no
   breaks anywhere) leaves the distribution as it was.

With continuous actions (``actions: continuous``, whose shield reports no invariant breaks) the objective is the
shield's lapses per 1 000 decisions (the plan kept, verified, no longer verifies: the same question, asked of the
committed rule for controls).

Only traffic inside the model is searched: ``env.*`` keys (every value checked by the config's own
validation, so a sample is always a legal highway-env configuration) and ``traffic.vehicles_behind``;
no adversaries, no shield settings.

:func:`run_search` writes each sample's record to ``DIR/samples/sampleNNNNN.json`` and its files to
``DIR/counterexamples/sampleNNNNN-…``, and after each iteration ``DIR/search.json``, ``DIR/samples.csv``
and ``DIR/summary.md`` (atomically). A killed search re-run with the same spec resumes: the draws are a
function of the seed and of the records already written, so it redraws the same samples and plays
only the missing ones. Episode seeds: ``SEARCH_SEED_BASE + 10 000·sample + k`` (sample = iteration ×
population + its place in the iteration), never used elsewhere; the same seed gives the same numbers.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from safelane.config import ConfigError, validation_message
from safelane.core.files import atomic_write_text
from safelane.running.conditions import traffic_seed_base
from safelane.running.falsify.grid import (
    BREAK_CLASSES,
    CELL_SEED_STRIDE,
    CampaignBase,
    CampaignSpec,
    cell_config,
    continuous_figures,
    load_campaign_spec,
    open_campaign,
    play_cell,
    read_spec_yaml,
)

SEARCH_SEED_BASE = 4_200_000_000
"""Search episodes are reset with ``SEARCH_SEED_BASE + 10 000·sample + k`` (never used elsewhere); the spec's
``seed`` ``N`` adds ``N ×`` :data:`~safelane.running.conditions.TRAFFIC_SEED_STRIDE`."""
MAX_SAMPLES = 9_000
"""At most ``iterations × population`` samples, so that every episode seed stays below 2³²."""
SEARCHABLE_KEYS: tuple[str, ...] = ("traffic.vehicles_behind",)
"""Keys outside ``env.*`` a search may vary (traffic inside the model; not ``traffic.adversary``)."""
VALUE_DECIMALS = 3
"""A continuous sample is rounded to this many decimals (readable configs and file names)."""
BEST_SHOWN = 5
"""Samples listed as the best conditions found (search.json, summary.md)."""

Distribution = dict[str, dict[str, Any]]
"""The search distribution: parameter → ``{"mean", "std"}`` (a range, in its own units) or ``{"probs"}``
(a choice, one probability per choice, in the spec's order)."""


class RangeParameter(BaseModel):
    """A continuous (or, with ``integer``, whole-number) parameter searched in ``[low, high]``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    low: float
    high: float
    integer: bool = Field(False, description="Round each sample to a whole number (counts).")

    @property
    def width(self) -> float:
        """``high − low``, in the parameter's units."""
        return self.high - self.low


class ChoiceParameter(BaseModel):
    """A categorical parameter: each choice a value of the key, or a setting (keys → values) like a grid axis's."""

    model_config = ConfigDict(extra="forbid")

    choices: list[Any]


def _searchable(key: str) -> bool:
    return (key.startswith("env.") and len(key) > 4) or key in SEARCHABLE_KEYS


def _parameter(name: str, raw: Any) -> RangeParameter | ChoiceParameter:
    """One entry of ``search.parameters``, checked (a one-line ConfigError naming it otherwise)."""
    where = f"search.parameters.{name}"
    allowed = "env.* keys and " + ", ".join(SEARCHABLE_KEYS)
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: expected {{low: L, high: H}} or {{choices: [...]}}, got {raw!r}")
    model: type[RangeParameter] | type[ChoiceParameter] = ChoiceParameter if "choices" in raw else RangeParameter
    try:
        parameter = model.model_validate(raw)
    except ValidationError as err:
        raise ConfigError(validation_message(err, model, prefix=f"{where}.")) from None
    if isinstance(parameter, RangeParameter):
        if not _searchable(name):
            raise ConfigError(f"{where}: not a searchable key; allowed: {allowed} (traffic inside the model)")
        if parameter.high <= parameter.low:
            raise ConfigError(f"{where}.high: must be greater than low ({parameter.low:g}), got {parameter.high:g}")
        if parameter.integer and not (parameter.low.is_integer() and parameter.high.is_integer()):
            raise ConfigError(
                f"{where}: integer: true needs whole low and high, got {parameter.low:g}, {parameter.high:g}"
            )
        return parameter
    choices = parameter.choices
    if len(choices) < 2:
        raise ConfigError(f"{where}.choices: give at least 2 (a single value belongs in sets), got {choices!r}")
    settings = [isinstance(c, dict) for c in choices]
    if any(settings) and not all(settings):
        raise ConfigError(f"{where}.choices: either all values of {name} or all settings (KEY: VALUE maps)")
    keys = [k for c in choices for k in c] if all(settings) else [name]
    if all(settings) and any(not c for c in choices):
        raise ConfigError(f"{where}.choices: a setting is empty")
    for key in keys:
        if not _searchable(str(key)):
            raise ConfigError(
                f"{where}: '{key}' is not a searchable key; allowed: {allowed} (traffic inside the model)"
            )
    return parameter


class SearchSettings(BaseModel):
    """The ``search`` section: the CEM's sizes, its seed and the parameters it searches."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    method: Literal["cem"] = "cem"
    iterations: int = Field(5, ge=1, description="CEM iterations (distribution refits).")
    population: int = Field(16, ge=2, description="Conditions drawn per iteration.")
    elite_fraction: float = Field(0.2, gt=0, le=1, description="Share of each population the refit keeps.")
    episodes_per_sample: int = Field(10, ge=1, description="Episodes played per drawn condition.")
    seed: int = Field(0, ge=0, description="Seed of the draws (iteration i uses (seed, i)).")
    smoothing: float = Field(
        0.7, gt=0, le=1, description="Weight of the elite's fit in the next distribution (1: the elite's fit alone)."
    )
    init_std: float = Field(0.5, gt=0, description="A range's first σ, as a fraction of its width.")
    min_std: float = Field(0.05, ge=0, description="A range's σ floor, as a fraction of its width.")
    parameters: dict[str, RangeParameter | ChoiceParameter]

    @field_validator("parameters", mode="before")
    @classmethod
    def _parameters(cls, value: Any) -> dict[str, RangeParameter | ChoiceParameter]:
        if not isinstance(value, dict) or not value:
            raise ConfigError(
                "search.parameters: give at least one KEY: {low: L, high: H} or NAME: {choices: [...]}, "
                f"got {value!r}"
            )
        return {str(name): _parameter(str(name), raw) for name, raw in value.items()}

    @model_validator(mode="after")
    def _size(self) -> SearchSettings:
        if self.iterations * self.population > MAX_SAMPLES:
            raise ConfigError(
                f"search: iterations × population must be at most {MAX_SAMPLES} (episode seeds), "
                f"got {self.iterations} × {self.population}"
            )
        return self

    @property
    def elites(self) -> int:
        """Samples kept per refit: ``elite_fraction × population`` rounded half up, at least 1."""
        return max(1, math.floor(self.elite_fraction * self.population + 0.5))


class SearchSpec(CampaignBase):
    """A falsification search: the campaign's preset, simulator, shield, ``sets`` and one policy, and a
    ``search`` section (:class:`SearchSettings`) in place of the grid's axes."""

    policies: list[str] = Field(
        default_factory=lambda: ["faster"], description="The one policy that drives every sample."
    )
    search: SearchSettings

    @field_validator("policies")
    @classmethod
    def _one_policy(cls, policies: list[str]) -> list[str]:
        if len(policies) != 1:
            raise ValueError(f"a search plays one policy; got {len(policies)} (run one search per policy)")
        return policies


def load_falsify_spec(path: str | Path, overrides: dict[str, Any] | None = None) -> CampaignSpec | SearchSpec:
    """A campaign YAML: a :class:`SearchSpec` if it has a ``search`` section, else a grid
    (:func:`safelane.running.falsify.grid.load_campaign_spec`). ``overrides``: ``episodes`` (episodes per
    cell, or per sample of a search), ``sample`` (grids only), ``seed`` (the traffic seed), ``shield`` and
    ``actions``; None is ignored.
    Bad input: a one-line ConfigError."""
    path = Path(path)
    data = read_spec_yaml(path)
    if "search" not in data:
        return load_campaign_spec(path, overrides)
    overrides = {k: v for k, v in (overrides or {}).items() if v is not None}
    for option in ("sample", "shard"):
        if option in overrides:
            raise ConfigError(f"--{option}: {path} is a search (it has a search section); --{option} takes a grid's "
                              "cells")  # fmt: skip
    if "episodes" in overrides and isinstance(data["search"], dict):
        data["search"] = {**data["search"], "episodes_per_sample": overrides.pop("episodes")}
    data.update(overrides)
    try:
        return SearchSpec.model_validate(data)
    except ValidationError as err:
        raise ConfigError(f"campaign spec {path}: {validation_message(err, SearchSpec)}") from None


# --- the CEM, as pure functions ----------------------------------------------------------------------


def initial_distribution(settings: SearchSettings) -> Distribution:
    """Each range: mean in its middle, σ = ``init_std`` × its width; each choice: uniform."""
    dist: Distribution = {}
    for name, p in settings.parameters.items():
        if isinstance(p, RangeParameter):
            dist[name] = {"mean": (p.low + p.high) / 2, "std": settings.init_std * p.width}
        else:
            dist[name] = {"probs": [1 / len(p.choices)] * len(p.choices)}
    return dist


def draw_samples(settings: SearchSettings, dist: Distribution, rng: np.random.Generator) -> list[dict[str, Any]]:
    """``population`` samples: parameter → value (a range: a Gaussian draw clipped to ``[low, high]``,
    rounded to :data:`VALUE_DECIMALS` or, with ``integer``, to a whole ``int``) or choice index (``int``).
    Parameters are drawn in the spec's order, each for the whole population at once."""
    n = settings.population
    columns: dict[str, list[Any]] = {}
    for name, p in settings.parameters.items():
        d = dist[name]
        if isinstance(p, RangeParameter):
            x = np.clip(rng.normal(d["mean"], d["std"], size=n), p.low, p.high)
            if p.integer:
                columns[name] = [int(v) for v in np.rint(x)]
            else:
                columns[name] = [min(max(round(float(v), VALUE_DECIMALS), p.low), p.high) for v in x]
        else:
            columns[name] = [int(i) for i in rng.choice(len(p.choices), size=n, p=np.asarray(d["probs"]))]
    return [{name: columns[name][j] for name in settings.parameters} for j in range(n)]


def select_elite(scores: Sequence[float | None], count: int, tiebreak: Sequence[float] | None = None) -> list[int]:
    """Indices of the ``count`` best scores, best first; ties go to the larger ``tiebreak``, then to the
    earlier index. A ``None`` score (a sample the simulator skipped) is never chosen. No elite at all
    when every scored sample ties (score and tiebreak: e.g. no breaks anywhere) — such an iteration says
    nothing about where breaks are, and refitting to the first samples would only narrow the search."""
    scored = [i for i, s in enumerate(scores) if s is not None]
    ties = tiebreak if tiebreak is not None else [0.0] * len(scores)
    if len({(scores[i], ties[i]) for i in scored}) <= 1 and len(scored) > 1:
        return []
    ranked = sorted(scored, key=lambda i: (-float(scores[i]), -float(ties[i]), i))  # type: ignore[arg-type]
    return ranked[:count]


def cem_update(settings: SearchSettings, dist: Distribution, elite: Sequence[dict[str, Any]]) -> Distribution:
    """The next distribution from the elite samples: for a range, ``α·mean(elite) + (1 − α)·mean`` and
    ``max(α·std(elite) + (1 − α)·std, min_std·width)`` (population std, ``ddof=0``); for a choice,
    ``α·frequency(elite) + (1 − α)·probs`` (α = ``smoothing``). No elite: the distribution unchanged."""
    if not elite:
        return {name: dict(d) for name, d in dist.items()}
    a = settings.smoothing
    new: Distribution = {}
    for name, p in settings.parameters.items():
        d = dist[name]
        if isinstance(p, RangeParameter):
            values = np.array([s[name] for s in elite], dtype=np.float64)
            mean = a * float(values.mean()) + (1 - a) * d["mean"]
            std = a * float(values.std()) + (1 - a) * d["std"]
            new[name] = {"mean": mean, "std": max(std, settings.min_std * p.width)}
        else:
            freq = np.bincount([s[name] for s in elite], minlength=len(p.choices)) / len(elite)
            probs = a * freq + (1 - a) * np.asarray(d["probs"], dtype=np.float64)
            new[name] = {"probs": [float(v) for v in probs / probs.sum()]}
    return new


# --- samples as campaign cells ------------------------------------------------------------------------


def _short(value: Any) -> str:
    """A value's label: a dotted class path by its last part."""
    return value.split(".")[-1] if isinstance(value, str) else str(value)


def _choice_label(choice: Any) -> str:
    """A choice's label: its value, or a setting's ``key=value`` pairs by the keys' last parts."""
    if isinstance(choice, dict):
        return ",".join(f"{k.split('.')[-1]}={_short(v)}" for k, v in choice.items())
    return _short(choice)


def sample_cell(spec: SearchSpec, iteration: int, place: int, sample: dict[str, Any]) -> dict[str, Any]:
    """The campaign cell of one sample: ``index`` (iteration × population + place), the policy, ``sets``
    (key → value), ``labels`` (parameter → text) and the sample's ``values``."""
    sets: dict[str, Any] = {}
    labels: dict[str, str] = {}
    for name, p in spec.search.parameters.items():
        value = sample[name]
        if isinstance(p, RangeParameter):
            sets[name] = value
            labels[name] = _short(value)
            continue
        choice = p.choices[value]
        if isinstance(choice, dict):
            sets.update(choice)
        else:
            sets[name] = choice
        labels[name] = _choice_label(choice)
    return {
        "index": iteration * spec.search.population + place,
        "iteration": iteration,
        "sample": place,
        "policy": spec.policies[0],
        "sets": sets,
        "labels": labels,
        "values": sample,
    }


def _sample_path(out: Path, index: int) -> Path:
    return out / "samples" / f"sample{index:05d}.json"


def objective(record: dict[str, Any], continuous: bool = False) -> float | None:
    """The search's objective of a played sample: invariant breaks per 1 000 decisions, or with ``continuous`` actions
    the shield's lapses per 1 000 decisions (None: skipped)."""
    if "skipped" in record:
        return None
    events = record.get("lapses", 0) if continuous else record["invariant_breaks"]
    return 1000 * events / max(record["decisions"], 1)


def _sample_task(out_dir: str, spec_json: str, cell_json: str) -> dict[str, Any]:
    """Play one sample as a campaign cell; write its record (and its counterexample files); return it."""
    spec = SearchSpec.model_validate_json(spec_json)
    cell = json.loads(cell_json)
    out = Path(out_dir)
    index = cell["index"]
    played = play_cell(
        spec,
        cell,
        traffic_seed_base(SEARCH_SEED_BASE, spec.seed) + CELL_SEED_STRIDE * index,
        spec.search.episodes_per_sample,
        out / "counterexamples",
        f"falsify search {spec.name} sample {index}",
        f"sample{index:05d}-",
    )
    record = {k: cell[k] for k in ("index", "iteration", "sample", "policy", "values", "labels")} | played
    record["objective"] = objective(record, spec.continuous)
    atomic_write_text(_sample_path(out, index), json.dumps(record))
    return record


def _read_sample(out: Path, cell: dict[str, Any]) -> dict[str, Any] | None:
    """A sample's record if it was played already (None if not); one of another draw is an error."""
    path = _sample_path(out, cell["index"])
    if not path.is_file():
        return None
    record = json.loads(path.read_text())
    if record.get("values") != cell["values"]:
        raise ConfigError(
            f"--out {out}: {path.name} holds {record.get('values')}, but this search draws {cell['values']} "
            "there; give a new --out or delete it"
        )
    return record


def check_parameters(spec: SearchSpec) -> None:
    """Build the configuration at each parameter's extremes (each range's low and high, every choice),
    the others at their first distribution's mean or first choice: a bad key or value fails here, once,
    in one line, before anything is played."""
    settings = spec.search
    middle: dict[str, Any] = {}
    for name, p in settings.parameters.items():
        if isinstance(p, RangeParameter):
            mid = (p.low + p.high) / 2
            middle[name] = round(mid) if p.integer else round(mid, VALUE_DECIMALS)
        else:
            middle[name] = 0
    for name, p in settings.parameters.items():
        if isinstance(p, RangeParameter):
            extremes: list[Any] = [int(p.low), int(p.high)] if p.integer else [p.low, p.high]
        else:
            extremes = list(range(len(p.choices)))
        for value in extremes:
            try:
                cell_config(spec, sample_cell(spec, 0, 0, {**middle, name: value}))
            except ConfigError as err:
                shown = value if isinstance(p, RangeParameter) else f"choice {p.choices[value]!r}"
                raise ConfigError(f"search.parameters.{name} at {shown}: {err}") from None


def run_search(
    spec: SearchSpec,
    out_dir: str | Path,
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Run the CEM search of ``spec`` into ``out_dir`` (resuming a killed one); returns search.json's dict."""
    check_parameters(spec)  # before anything is written
    out = open_campaign(spec, out_dir, backend)
    settings = spec.search
    total = settings.iterations * settings.population
    dist = initial_distribution(settings)
    rows: list[dict[str, Any]] = []
    played: list[dict[str, Any]] = []
    done = [0]
    result: dict[str, Any] = {}
    for iteration in range(settings.iterations):
        samples = draw_samples(settings, dist, np.random.default_rng([settings.seed, iteration]))
        cells = [sample_cell(spec, iteration, j, sample) for j, sample in enumerate(samples)]
        records = _play_samples(out, spec, cells, backend, workers, address, done, total, progress)
        scores = [objective(r, spec.continuous) for r in records]
        elite = select_elite(scores, settings.elites, [r.get("collisions", 0) for r in records])
        rows.append(_iteration_row(iteration, dist, records, elite, spec.continuous))
        dist = cem_update(settings, dist, [samples[i] for i in elite])
        played += records
        result = write_search_results(out, spec, rows, dist, played)
    return result


def _play_samples(
    out: Path,
    spec: SearchSpec,
    cells: list[dict[str, Any]],
    backend: str,
    workers: int | None,
    address: str | None,
    done: list[int],
    total: int,
    progress: Callable[[int, int], None] | None,
) -> list[dict[str, Any]]:
    """Play the cells of one iteration not yet played (on the task backend); their records, in order.
    ``done``: samples finished so far (updated), reported to ``progress`` with ``total``."""
    from safelane.running.backend import TaskFailure, format_failure, run_tasks

    todo = [cell for cell in cells if _read_sample(out, cell) is None]
    done[0] += len(cells) - len(todo)
    if progress is not None:
        progress(done[0], total)
    failures: list[str] = []

    def finished(i: int, outcome: dict[str, Any] | TaskFailure) -> None:
        if isinstance(outcome, TaskFailure):
            failures.append(f"sample {todo[i]['index']}: {format_failure(outcome)}")
        done[0] += 1
        if progress is not None:
            progress(done[0], total)

    run_tasks(
        _sample_task,
        [(str(out.resolve()), spec.model_dump_json(), json.dumps(cell)) for cell in todo],
        backend=backend,
        workers=workers,
        address=address,
        on_result=finished,
        name=f"falsify-search-{spec.name}",
        storage=out.resolve() / "ray",
    )
    if failures:
        raise ConfigError(f"falsify search: {len(failures)} sample(s) failed; first: {failures[0]}")
    return [_read_sample(out, cell) or {} for cell in cells]


# --- results ------------------------------------------------------------------------------------------


def _iteration_row(
    iteration: int, dist: Distribution, records: list[dict[str, Any]], elite: list[int], continuous: bool = False
) -> dict[str, Any]:
    """One iteration: its objective's mean, best and elite mean [events / 1 000 decisions], its totals and
    the distribution it was drawn from."""
    scores = [s for s in (objective(r, continuous) for r in records) if s is not None]
    live = [r for r in records if "skipped" not in r]
    best = max(live, key=lambda r: (r["objective"], r["collisions"], -r["index"]), default=None)
    return {
        "iteration": iteration,
        "samples": len(records),
        "samples_skipped": len(records) - len(live),
        "mean_objective": float(np.mean(scores)) if scores else None,
        "best_objective": best["objective"] if best else None,
        "best_sample": best["index"] if best else None,
        "elite_mean_objective": float(np.mean([records[i]["objective"] for i in elite])) if elite else None,
        "elite_samples": [records[i]["index"] for i in elite],
        "episodes": sum(r["episodes"] for r in live),
        "decisions": sum(r["decisions"] for r in live),
        "invariant_breaks": sum(r["invariant_breaks"] for r in live),
        **({"lapses": sum(r.get("lapses", 0) for r in live)} if continuous else {}),
        "collisions": sum(r["collisions"] for r in live),
        "distribution": dist,
    }


def write_search_results(
    out: Path, spec: SearchSpec, rows: list[dict[str, Any]], dist: Distribution, records: list[dict[str, Any]]
) -> dict[str, Any]:
    """Write search.json, samples.csv and summary.md (atomically) from the iterations so far; returns
    search.json's dict (totals, the iterations, the final distribution, the best samples)."""
    from safelane.running.collisions import collision_contexts
    from safelane.running.evaluation import CONTINUOUS_FIGURES

    live = [r for r in records if "skipped" not in r]
    kinds: dict[str, int] = {}
    contexts = dict.fromkeys(collision_contexts(spec.shield == "committed"), 0)
    classes = dict.fromkeys(BREAK_CLASSES, 0)
    for r in live:
        for table, counts in ((kinds, r["collision_kinds"]), (contexts, r["collision_contexts"])):
            for k, v in counts.items():
                table[k] = table.get(k, 0) + v
        for k, v in r["break_classes"].items():
            classes[k] += v
    decisions = sum(r["decisions"] for r in live)
    breaks = sum(r["invariant_breaks"] for r in live)
    ranked = sorted(live, key=lambda r: (-r["objective"], -r["collisions"], r["index"]))
    keep = ("index", "iteration", "labels", "values", "objective", "invariant_breaks", "decisions", "episodes",
            "collisions", "collision_contexts", "break_classes", "mean_speed")  # fmt: skip
    if spec.continuous:
        keep = (*(k for k in keep if k not in ("invariant_breaks", "break_classes")), "lapses", "lapses_in_model")
    summary = {
        "name": spec.name,
        "method": spec.search.method,
        "shield": spec.shield,
        "simulator": spec.simulator,
        "policy": spec.policies[0],
        "seed": spec.search.seed,
        **({"traffic_seed": spec.seed} if spec.seed else {}),  # absent: 0, the published episodes
        "iterations_done": len(rows),
        "iterations": rows,
        "final_distribution": dist,
        "best": [{k: r[k] for k in keep} for r in ranked[:BEST_SHOWN]],
        "samples": len(records),
        "samples_skipped": len(records) - len(live),
        "episodes": sum(r["episodes"] for r in live),
        "decisions": decisions,
        "invariant_breaks": breaks,
        "breaks_per_1000_decisions": 1000 * breaks / decisions if decisions else None,
        "break_classes": classes,
        "collisions": sum(r["collisions"] for r in live),
        "collision_kinds": kinds,
        "collision_contexts": contexts,
    }
    if spec.shield == "committed":
        counted = [r for r in live if "lapses" in r]
        forced = sum(r["plan_forced_rate"] * r["decisions"] for r in counted)
        summary.update(
            lapses=sum(r["lapses"] for r in counted),
            lapses_in_model=sum(r["lapses_in_model"] for r in counted),
            plan_forced_rate=forced / max(sum(r["decisions"] for r in counted), 1),
            uncertified_starts=sum(r["uncertified_starts"] for r in counted),
            redraws=sum(r["redraws"] for r in counted),
        )
    if spec.continuous:  # its shield reports lapses, projections and episodes off the road, not breaks or fallbacks
        for key in ("invariant_breaks", "breaks_per_1000_decisions", "break_classes"):
            del summary[key]
        lapses = summary.get("lapses", 0)
        summary.update(lapses_per_1000_decisions=1000 * lapses / decisions if decisions else None,
                       actions=spec.actions, **continuous_figures(live))  # fmt: skip
    names = list(spec.search.parameters)
    columns = ["index", "iteration", "sample", *names, "episodes", "decisions", "invariant_breaks", "objective",
               *BREAK_CLASSES, "collisions", "fallback_rate", "mean_speed", "skipped"]  # fmt: skip
    if spec.continuous:
        columns = ["index", "iteration", "sample", *names, "episodes", "decisions", "lapses", "objective",
                   "lapses_in_model", "collisions", *CONTINUOUS_FIGURES, "mean_speed", "skipped"]  # fmt: skip
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for r in records:
        writer.writerow({**r, **r["labels"], **r.get("break_classes", {})})
    atomic_write_text(out / "samples.csv", buffer.getvalue())
    atomic_write_text(out / "search.json", json.dumps(summary, indent=1))
    atomic_write_text(out / "summary.md", _markdown(spec, summary))
    return summary


def _describe(p: RangeParameter | ChoiceParameter, d: dict[str, Any]) -> str:
    """A distribution's parameter in a table cell: ``μ ± σ`` or the likeliest choice with its probability."""
    if isinstance(p, RangeParameter):
        return f"{d['mean']:.3g} ± {d['std']:.2g}"
    i = int(np.argmax(d["probs"]))
    choice = p.choices[i]
    return f"{_choice_label(choice)} ({d['probs'][i]:.2f})"


def _number(value: float | None, digits: int = 2) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def _markdown(spec: SearchSpec, summary: dict[str, Any]) -> str:
    s = spec.search
    names = list(s.parameters)
    if spec.continuous:  # the objective counts the shield's lapses
        events, key, headline = "lapses", "lapses", (
            f"**{summary.get('lapses', 0)} lapses** ({_number(summary['lapses_per_1000_decisions'])} per 1 000 "
            f"decisions, {summary.get('lapses_in_model', 0)} in the model), **{summary['collisions']} collisions** "
            f"{summary['collision_kinds']} (against the shield's promise: {summary['collision_contexts']}); the shield "
            f"projected {_number(100 * (summary['projection_rate'] or 0.0))} % of the actions, "
            f"{_number(100 * (summary['off_road_rate'] or 0.0))} % of the episodes ended off the road."
        )
        title = "continuous actions, the shield for continuous actions"
    else:
        events, key, headline = "invariant breaks", "invariant_breaks", (
            f"**{summary['invariant_breaks']} invariant breaks** ({_number(summary['breaks_per_1000_decisions'])} "
            f"per 1 000 decisions) {summary['break_classes']}, **{summary['collisions']} collisions** "
            f"{summary['collision_kinds']} (against the rule's promise: {summary['collision_contexts']})."
        )
        title = f"{spec.shield} shield (override on)"
    short = "lapses" if spec.continuous else "breaks"
    lines = [
        f"# Falsification search {spec.name}: CEM, {title}, {spec.simulator} simulator, policy {spec.policies[0]}",
        "",
        spec.description.strip(),
        "",
        f"{summary['iterations_done']} / {s.iterations} iterations × {s.population} samples × "
        f"{s.episodes_per_sample} episodes (elite {s.elites}, smoothing {s.smoothing:g}, seed {s.seed}): "
        f"{summary['episodes']} episodes, {summary['decisions']} decisions, " + headline,
        "",
        "## Iterations",
        "",
        f"Objective: {events} per 1 000 decisions of a sample. Distribution: the one the iteration "
        "drew from (a range: mean ± σ; a choice: the likeliest, with its probability).",
        "",
        f"| iteration | mean | best | elite mean | {short} | collisions | " + " | ".join(names) + " |",
        "|---" * (6 + len(names)) + "|",
    ]
    for row in summary["iterations"]:
        cells = [_describe(s.parameters[n], row["distribution"][n]) for n in names]
        lines.append(
            f"| {row['iteration']} | {_number(row['mean_objective'])} | {_number(row['best_objective'])} | "
            f"{_number(row['elite_mean_objective'])} | {row.get(key, 0)} | {row['collisions']} | "
            + " | ".join(cells)
            + " |"
        )
    final = [_describe(s.parameters[n], summary["final_distribution"][n]) for n in names]
    lines += [
        "| final | | | | | | " + " | ".join(final) + " |",
        "",
        "## Best conditions found",
        "",
        f"| sample | iteration | {' | '.join(names)} | {short} / 1 000 decisions | {short} | decisions | collisions |",
        "|---" * (6 + len(names)) + "|",
    ]
    for r in summary["best"]:
        lines.append(
            f"| {r['index']} | {r['iteration']} | "
            + " | ".join(r["labels"][n] for n in names)
            + f" | {r['objective']:.2f} | {r.get(key, 0)} | {r['decisions']} | {r['collisions']} |"
        )
    lines.append("")
    return "\n".join(lines)
