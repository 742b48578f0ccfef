"""A falsification campaign: the shield driven by fixed policies over a grid of traffic conditions.

A campaign spec (:class:`CampaignSpec`; the shipped one is ``configs/falsify/grid.yaml``) names *axes*
— each a list of settings, a setting being one or more ``--set`` keys that belong together (a decision
rate with a physics rate it divides) — the policies (``random``, ``faster``, ``idle``, ``slower``, the
overtaking ``probe``, and trained agents as ``run:RUN_DIR``), the
shield, the episodes per cell and the simulator. A *cell* is one combination of the axes and one policy;
``sample`` draws that many cells (seeded) instead of the whole product. ``actions: continuous`` drives the ego by
acceleration and steering (highway-env's ``ContinuousAction``) with the continuous policies (``random``, ``faster``,
``weave``) under the shield for continuous actions (``shield: committed``:
:class:`safelane.safety.control_shield.ControlShield`).

:func:`run_campaign` plays every cell not yet done (on the task backend, as sweeps), writes each cell's record
to ``DIR/cells/CELL.json`` and every crash and invariant break as a replayable file under
``DIR/counterexamples/`` (:mod:`safelane.running.counterexamples`), each break with a *class* from its
replay (:func:`break_class`), and rebuilds ``DIR/cells.csv`` and ``DIR/summary.md`` from the cell files
after each one (kill-safe, resumable).

With continuous actions the summary reports what that shield reports instead of invariant breaks and fallbacks:
collisions against its promise (the committed mode's contexts: uncertified starts, others at fault, outside the model,
after a lapse, from certified states), lapses and those in the model, the share of decisions whose action it
projected and how far, the plan-forced share, episodes ended off the road, the ego's speed.

Break classes (what changed around the ego during the decision that ended in a state with no safe
action — a description of the scene, not yet a proof of what the model missed):

* ``second_lane_cut_in``: a vehicle that was two or more lanes from the ego is now in a lane next to it,
  within 60 m — the rule's cut-in candidates are the vehicles already next to the ego;
* ``adjacent_lane_change``: a vehicle next to the ego, or in its lane, changed lanes (within 60 m);
* ``ego_lane_change``: the ego changed lanes;
* ``other``: none of these.
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from safelane.config import ConfigError, validation_message
from safelane.core.files import atomic_write_text
from safelane.running.collisions import BREAK_CLASSES, break_class_of
from safelane.running.conditions import traffic_seed_base

FALSIFY_SEED_BASE = 4_000_000_000
"""Campaign episodes are reset with ``FALSIFY_SEED_BASE + 10 000·cell + k`` (never used elsewhere); the spec's
``seed`` ``N`` adds ``N ×`` :data:`~safelane.running.conditions.TRAFFIC_SEED_STRIDE`."""
CELL_SEED_STRIDE = 10_000
RUN_PREFIX = "run:"
"""A campaign policy ``run:RUN_DIR`` is the greedy policy of that trained run (its cells at another
decision rate, state or action set are recorded as skipped)."""
BELIEF_FIGURES: tuple[str, ...] = ("collisions_type_ruled_out", "collision_contexts_types_kept")
"""What a cell under the belief shield adds: its crashes with a car whose true driver type the belief had ruled out
(outside its sets), and the promise's contexts of the others."""


class CampaignBase(BaseModel):
    """What every campaign names: the preset, simulator, shield, fixed ``--set`` overrides, the policies
    (:class:`CampaignSpec` adds the grid, :class:`safelane.running.falsify.search.SearchSpec` a search)."""

    model_config = ConfigDict(extra="forbid")

    name: str = "campaign"
    description: str = ""
    preset: Literal["fast", "paper", "hidden-types"] = "fast"
    simulator: Literal["fast", "highway-env"] = "fast"
    shield: Literal["nominal", "robust", "committed", "omniscient", "belief"] = Field(
        "robust",
        description="The shield's mode; omniscient and belief read the driver types of a traffic.driver_mix (preset "
        "hidden-types).",
    )
    actions: Literal["discrete", "continuous"] = Field(
        "discrete",
        description="The ego's actions: discrete (meta-actions) or continuous (acceleration and steering; shield "
        "committed, policies random, faster, weave).",
    )
    sets: list[str] = Field(default_factory=list, description="--set overrides of every cell.")
    policies: list[str] = Field(
        default_factory=lambda: ["random", "faster"],
        description="Fixed policies (random, faster, idle, slower, probe; with continuous actions random, faster, "
        "weave) and trained agents as 'run:RUN_DIR'.",
    )
    seed: int = Field(
        0,
        ge=0,
        description="Traffic seed: 0 plays the published episodes, another draws fresh traffic (--seed).",
    )

    @field_validator("policies")
    @classmethod
    def _policies(cls, policies: list[str]) -> list[str]:
        if not policies:
            raise ValueError("no policies; give at least one")
        return policies

    @model_validator(mode="after")
    def _fit_the_actions(self) -> CampaignBase:
        """Every fixed policy drives the action set; continuous actions have one shield (one-line errors)."""
        from safelane.running.policies import CONTINUOUS_POLICIES, FIXED_POLICIES

        continuous = self.actions == "continuous"
        allowed, what = (CONTINUOUS_POLICIES, "continuous policy") if continuous else (FIXED_POLICIES, "policy")
        for policy in self.policies:  # a run's directory is checked when the campaign starts
            if not policy.startswith(RUN_PREFIX) and policy not in allowed:
                raise ConfigError(f"policies: unknown {what} '{policy}'; allowed: {', '.join(allowed)} or run:RUN_DIR")
        if continuous and self.shield != "committed":
            raise ConfigError(
                f"shield: '{self.shield}' decides among meta-actions; allowed with actions continuous: committed"
            )
        return self

    @property
    def continuous(self) -> bool:
        """The ego takes continuous actions (acceleration and steering)."""
        return self.actions == "continuous"

    def record_json(self) -> str:
        """The spec as ``campaign.json`` keeps it: ``seed`` only when it is not 0, ``actions`` only when
        continuous and a grid's ``shard`` only when it has one, so a folder of a campaign whose record predates those
        fields resumes."""
        exclude = {name for name, default in (("seed", 0), ("actions", "discrete")) if getattr(self, name) == default}
        if getattr(self, "shard", "") is None:
            exclude.add("shard")
        return self.model_dump_json(indent=1, exclude=exclude or None)


class CampaignSpec(CampaignBase):
    """What to play (see the module docstring). Units: episodes of the preset's duration."""

    axes: dict[str, list[dict[str, Any]]] = Field(description="AXIS → settings; a setting maps keys to values.")
    episodes: int = Field(20, ge=1, description="Episodes per cell.")
    sample: int | None = Field(None, ge=1, description="Play this many cells drawn at random (default: all).")
    sample_seed: int = Field(0, ge=0)
    shard: str | None = Field(
        None,
        description="'K/N' (1 <= K <= N): play only the cells K-1, K-1+N, K-1+2N, … of the grid, each with the seeds "
        "it has in the whole grid — a campaign split over machines or days; merge the shards' summaries with "
        "--merge.",
    )

    @field_validator("shard")
    @classmethod
    def _shard(cls, shard: str | None) -> str | None:
        if shard is None:
            return None
        k, _, n = shard.partition("/")
        if not (k.isdigit() and n.isdigit() and 1 <= int(k) <= int(n)):
            raise ValueError(f"got {shard!r}; allowed: 'K/N' with whole numbers 1 <= K <= N, e.g. 1/5")
        return f"{int(k)}/{int(n)}"

    def shard_of(self) -> tuple[int, int] | None:
        """(K, N) of :attr:`shard`, or None for the whole grid."""
        if self.shard is None:
            return None
        k, n = self.shard.split("/")
        return int(k), int(n)

    @field_validator("axes")
    @classmethod
    def _axes(cls, axes: dict[str, list[dict[str, Any]]]) -> dict[str, list[dict[str, Any]]]:
        if not axes:
            raise ValueError("no axes; give at least one AXIS with a list of settings")
        for name, settings in axes.items():
            if not settings:
                raise ValueError(f"axis '{name}' has no settings")
        return axes

    def cells(self) -> list[dict[str, Any]]:
        """Every cell: ``{"index", "policy", "labels" (axis → setting text), "sets" (key → value)}``."""
        names = list(self.axes)
        combos = list(itertools.product(*(self.axes[n] for n in names)))
        cells = []
        for combo in combos:
            for policy in self.policies:
                sets: dict[str, Any] = {}
                for setting in combo:
                    sets.update(setting)
                labels = {n: _label(setting) for n, setting in zip(names, combo, strict=True)}
                cells.append({"policy": policy, "labels": labels, "sets": sets})
        if self.sample is not None and self.sample < len(cells):
            rng = np.random.default_rng(self.sample_seed)
            keep = sorted(rng.choice(len(cells), size=self.sample, replace=False).tolist())
            cells = [cells[i] for i in keep]
        for i, cell in enumerate(cells):
            cell["index"] = i
        if (shard := self.shard_of()) is not None:
            k, n = shard
            cells = [c for c in cells if c["index"] % n == k - 1]
        return cells


def _label(setting: dict[str, Any]) -> str:
    """A short text for a setting: last key part = value, a dotted class path by its last part
    (``other_vehicles_type=AggressiveVehicle``, ``vehicles_density=0.5``)."""
    return ",".join(f"{k.split('.')[-1]}={_value_label(v)}" for k, v in setting.items())


def _value_label(value: Any) -> str:
    """A setting's value as a label: a dotted path by its last part, a driver mixture's list as
    ``type:weight+…`` (``timid:3+normal:1+aggressive:1``)."""
    if isinstance(value, str):
        return value.split(".")[-1]
    if isinstance(value, list) and all(isinstance(v, dict) and set(v) == {"type", "weight"} for v in value):
        return "+".join(f"{v['type']}:{v['weight']:g}" for v in value)
    return str(value)


def read_spec_yaml(path: Path) -> dict[str, Any]:
    """A campaign spec file as a dict; a one-line ConfigError if it is missing or not a YAML mapping."""
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise ConfigError(f"campaign spec {path}: no such file") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"campaign spec {path}: not valid YAML ({str(err).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"campaign spec {path}: expected a mapping of fields (name, axes, policies…)")
    return data


def load_campaign_spec(path: str | Path, overrides: dict[str, Any] | None = None) -> CampaignSpec:
    """Read a campaign YAML (``overrides``: fields on top, None ignored); a one-line ConfigError on bad input."""
    path = Path(path)
    data = read_spec_yaml(path)
    data.update({k: v for k, v in (overrides or {}).items() if v is not None})
    try:
        return CampaignSpec.model_validate(data)
    except ValidationError as err:
        raise ConfigError(f"campaign spec {path}: {validation_message(err, CampaignSpec)}") from None


def cell_config(spec: CampaignBase, cell: dict[str, Any]) -> Any:
    """The environment config of a cell: the preset, the spec's sets, the cell's, the action set, the shield with
    override (meta-actions; the shield for continuous actions always intervenes, it has no override)."""
    from safelane.config import load_config

    overrides = {**cell["sets"], "simulator": spec.simulator, "shield.mode": spec.shield, "actions": spec.actions,
                 "shield.override": not spec.continuous}  # fmt: skip
    return load_config(spec.preset, sets=spec.sets, overrides=overrides)


BREAK_FILE = re.compile(r"seed(\d+)-invariant_break-step(\d+)\.json$")
"""A break file's name: its episode's seed and its decision."""


def break_class(result: Any) -> str:
    """The class of an invariant break from its replay (:func:`~safelane.running.collisions.break_class_of` of the
    scenes before and after its decision)."""
    last = result.decisions[-1]
    return break_class_of(last.ego["lane"], last.nearby, result.final["ego"]["lane"], result.final["nearby"])


def _cell_policy(name: str, seed: int, config: Any) -> Any:
    """A cell's policy: a fixed one (seeded, for ``config``'s action set) or a trained run's greedy policy
    (``run:RUN_DIR``)."""
    from safelane.running.policies import fixed_policy

    if name.startswith(RUN_PREFIX):
        from safelane.running.run_directory import load_policy

        return load_policy(name[len(RUN_PREFIX) :])
    return fixed_policy(name, seed, config.actions, config.env.get("action"))


def _cell_path(out: Path, index: int) -> Path:
    return out / "cells" / f"cell{index:05d}.json"


def _cell_task(out_dir: str, spec_json: str, index: int) -> dict[str, Any]:
    """Play one cell; write its record (and its counterexample files); return the record."""
    spec = CampaignSpec.model_validate_json(spec_json)
    cell = next(c for c in spec.cells() if c["index"] == index)  # a shard's cells keep their grid indices
    out = Path(out_dir)
    base = {"index": index, "policy": cell["policy"], **{f"axis_{k}": v for k, v in cell["labels"].items()}}
    seed = traffic_seed_base(FALSIFY_SEED_BASE, spec.seed) + CELL_SEED_STRIDE * index
    played = play_cell(
        spec, cell, seed, spec.episodes, out / "counterexamples", f"falsify cell {index}", f"cell{index:05d}-"
    )
    record = {**base, **played}
    atomic_write_text(_cell_path(out, index), json.dumps(record))
    return record


def play_cell(
    spec: CampaignBase, cell: dict[str, Any], seed: int, episodes: int, counterexamples: Path, source: str, prefix: str
) -> dict[str, Any]:
    """Play ``episodes`` episodes of one cell (``cell["sets"]`` on the spec's config, ``cell["policy"]``),
    seeds ``seed, seed + 1, …``; save every crash and invariant break as ``counterexamples/PREFIX…json``
    and class the breaks (as they happened, or from their replays). Returns the cell's statistics (episodes, decisions,
    collisions and their kinds and contexts, invariant breaks and their classes, fallback rate, mean
    speed [m/s], file names, the committed mode's and continuous actions' figures, ``wall_time_s`` [s]), or
    ``{"skipped": why}`` where the simulator lacks a setting.
    The one episode loop of every campaign: the grid's cells and the search's samples."""
    from safelane.core.errors import NotSupported
    from safelane.running.counterexamples import load_counterexample, replay, save_counterexamples
    from safelane.running.evaluation import COMMITTED_FIGURES, CONTINUOUS_FIGURES, run_config, summarize

    try:
        cfg = cell_config(spec, cell)
        start = time.perf_counter()
        records = run_config(cfg, _cell_policy(cell["policy"], seed, cfg), episodes, seed)
    except NotSupported as err:
        return {"skipped": str(err)}
    s = summarize(records)
    files = save_counterexamples(records, cfg, counterexamples, source, prefix)
    classes = dict.fromkeys(BREAK_CLASSES, 0)
    file_classes: dict[str, str] = {}
    # Classed as they happened where the episode loop saw every snapshot, else from the file's replay (the same
    # scenes, so the same class: the fast batch shows the loop only the snapshots it needs).
    seen = {(r.seed, step): kind for r in records for step, kind in r.break_classes.items()}
    for path in files:
        if "invariant_break" in path.name:
            match = BREAK_FILE.search(path.name)
            key = (int(match.group(1)), int(match.group(2))) if match else None
            kind = seen.get(key) if key is not None else None
            file_classes[path.name] = kind if kind is not None else break_class(replay(load_counterexample(path)))
            classes[file_classes[path.name]] += 1
    return {
        "episodes": s["episodes"],
        "decisions": s["decisions"],
        "collisions": s["collisions"],
        "collision_kinds": s["collision_kinds"],
        "collision_contexts": s["collision_contexts"],
        "invariant_breaks": s["invariant_breaks"],
        "break_classes": classes,
        "fallback_rate": s["fallback_rate"],
        "mean_speed": s["mean_speed"],
        "counterexample_files": [p.name for p in files],
        "break_file_classes": file_classes,
        **{k: s[k] for k in COMMITTED_FIGURES if k in s},  # the committed mode's lapses, plan-forced decisions…
        **{k: s[k] for k in CONTINUOUS_FIGURES if k in s},  # continuous actions: off road, projections
        **{k: s[k] for k in BELIEF_FIGURES if k in s},  # the belief shield: crashes with a true type ruled out
        "wall_time_s": time.perf_counter() - start,
    }


def check_policies(spec: CampaignBase) -> None:
    """Every ``run:RUN_DIR`` policy names a trained run (a one-line ConfigError otherwise)."""
    for policy in spec.policies:
        if policy.startswith(RUN_PREFIX) and not (Path(policy[len(RUN_PREFIX) :]) / "config.yaml").is_file():
            raise ConfigError(f"policies: '{policy}': no trained run there (no config.yaml)")


def open_campaign(spec: CampaignBase, out_dir: str | Path, backend: str) -> Path:
    """The checks every campaign kind runs before playing (backend, ``run:`` policies), then ``out_dir`` claimed
    for ``spec`` (a killed run of the same spec resumes there; another spec is refused). Returns it."""
    from safelane.running.backend import check_backend, claim_out_dir

    check_backend(backend)
    check_policies(spec)
    out = Path(out_dir)
    claim_out_dir(out, spec.record_json(), "campaign.json", "campaign")
    return out


def run_campaign(
    spec: CampaignSpec,
    out_dir: str | Path,
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Play every cell of ``spec`` not yet done into ``out_dir``; returns the totals (also summary.json)."""
    from safelane.running.backend import TaskFailure, format_failure, run_tasks

    out = open_campaign(spec, out_dir, backend)
    cells = spec.cells()
    if cells:
        cell_config(spec, cells[0])  # a bad key fails here, once, in one line
    todo = [c["index"] for c in cells if not _cell_path(out, c["index"]).is_file()]
    done = [len(cells) - len(todo)]
    failures: list[str] = []
    if progress is not None:
        progress(done[0], len(cells))

    def finished(i: int, result: dict[str, Any] | TaskFailure) -> None:
        if isinstance(result, TaskFailure):
            failures.append(f"cell {todo[i]}: {format_failure(result)}")
        done[0] += 1
        if done[0] % 10 == 0 or done[0] == len(cells):
            write_summary(out, spec)
        if progress is not None:
            progress(done[0], len(cells))

    spec_json = spec.model_dump_json()
    run_tasks(
        _cell_task,
        [(str(out.resolve()), spec_json, i) for i in todo],
        backend=backend,
        workers=workers,
        address=address,
        on_result=finished,
        name=f"falsify-{spec.name}",
        storage=out.resolve() / "ray",
    )
    summary = write_summary(out, spec)
    if failures:
        raise ConfigError(f"falsify: {len(failures)} cell(s) failed; first: {failures[0]}")
    return summary


def write_summary(out: Path, spec: CampaignSpec) -> dict[str, Any]:
    """Rebuild cells.csv, summary.json and summary.md from the cell files."""
    from safelane.running.evaluation import COMMITTED_FIGURES, CONTINUOUS_FIGURES

    committed, continuous = spec.shield == "committed", spec.continuous
    records = [json.loads(p.read_text()) for p in sorted((out / "cells").glob("cell*.json"))]
    # The labels from the spec, not the files: a cell file may carry an ambiguous label (some recorded
    # "vehicles_density=5" for both 0.5 and 1.5).
    labels = {c["index"]: c["labels"] for c in spec.cells()}
    for r in records:
        r.update({f"axis_{k}": v for k, v in labels[r["index"]].items()})
    played = [r for r in records if "skipped" not in r]
    axes = [f"axis_{a}" for a in spec.axes]
    if continuous:  # the shield for continuous actions reports no invariant breaks, fallbacks or courtesy
        figures = [k for k in COMMITTED_FIGURES if k != "courtesy_waived_rate"]
        columns = ["index", "policy", *axes, "episodes", "decisions", "collisions", *figures, *CONTINUOUS_FIGURES,
                   "mean_speed", "skipped"]  # fmt: skip
    else:
        columns = ["index", "policy", *axes, "episodes", "decisions", "collisions", "invariant_breaks",
                   *BREAK_CLASSES, "fallback_rate", "mean_speed", *(COMMITTED_FIGURES if committed else ()),
                   *(("collisions_type_ruled_out",) if spec.shield == "belief" else ()), "skipped"]  # fmt: skip
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for r in records:
        writer.writerow({**r, **r.get("break_classes", {})})
    atomic_write_text(out / "cells.csv", buffer.getvalue())
    summary = campaign_totals(spec, played, len(spec.cells()), len(records), len(records) - len(played))
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1))
    atomic_write_text(out / "summary.md", _markdown(spec, summary, played))
    return summary


def campaign_totals(spec: CampaignSpec, played: list[dict[str, Any]], cells: int, cells_done: int,
                    cells_skipped: int) -> dict[str, Any]:  # fmt: skip
    """summary.json's totals over ``played``: the records of the cells played, or the summaries of a campaign's
    shards (the same counts and per-decision figures, each weighted by its decisions or episodes); ``cells``,
    ``cells_done``, ``cells_skipped``: the counts it reports."""
    from safelane.reporting import stats
    from safelane.running.collisions import collision_contexts

    committed, continuous = spec.shield == "committed", spec.continuous
    episodes = sum(r["episodes"] for r in played)
    decisions = sum(r["decisions"] for r in played)
    collisions = sum(r["collisions"] for r in played)
    breaks = sum(r.get("invariant_breaks", 0) for r in played)
    kinds: dict[str, int] = {}
    contexts = dict.fromkeys(collision_contexts(committed), 0)
    classes = dict.fromkeys(BREAK_CLASSES, 0)
    for r in played:
        for k, v in r["collision_kinds"].items():
            kinds[k] = kinds.get(k, 0) + v
        for k, v in r.get("collision_contexts", {}).items():  # cells of campaigns before contexts lack it
            contexts[k] = contexts.get(k, 0) + v
        for k, v in r.get("break_classes", {}).items():
            classes[k] += v
    summary = {
        "name": spec.name,
        "shield": spec.shield,
        "simulator": spec.simulator,
        **({"actions": spec.actions} if continuous else {}),
        "cells": cells,
        "cells_done": cells_done,
        "cells_skipped": cells_skipped,
        **({"shard": spec.shard} if spec.shard else {}),
        **({"traffic_seed": spec.seed} if spec.seed else {}),  # absent: 0, the published episodes
        "episodes": episodes,
        "decisions": decisions,
        "collisions": collisions,
        "collision_rate_wilson95": list(stats.binomial_ci(collisions, episodes)) if episodes else None,
        "collision_kinds": kinds,
        "collision_contexts": contexts,
        "invariant_breaks": breaks,
        "invariant_break_rate": breaks / decisions if decisions else None,
        "break_classes": classes,
        # Per decision, as each cell reports them: the share of decisions the shield fell back at and the
        # ego's mean speed [m/s] — what a condition costs, beside what it breaks.
        "fallback_rate": _per_decision([r for r in played if "fallback_rate" in r], "fallback_rate"),
        "mean_speed": _per_decision(played, "mean_speed"),
    }
    if continuous:  # what its shield does not report
        for key in ("invariant_breaks", "invariant_break_rate", "break_classes", "fallback_rate"):
            del summary[key]
        summary.update(continuous_figures(played))
    if spec.shield == "belief":
        kept = dict.fromkeys(collision_contexts(False), 0)
        for r in played:
            for k, v in r.get("collision_contexts_types_kept", {}).items():
                kept[k] = kept.get(k, 0) + v
        summary.update(
            collisions_type_ruled_out=sum(r.get("collisions_type_ruled_out", 0) for r in played),
            collision_contexts_types_kept=kept,
        )
    if committed:  # cells played before the committed figures were counted lack them: left out of the totals
        counted = [r for r in played if "lapses" in r]
        summary.update(
            lapses=sum(r["lapses"] for r in counted),
            lapses_in_model=sum(r["lapses_in_model"] for r in counted),
            plan_forced_rate=_per_decision(counted, "plan_forced_rate"),
            courtesy_waived_rate=_per_decision([r for r in counted if "courtesy_waived_rate" in r],
                                               "courtesy_waived_rate"),
            uncertified_starts=sum(r["uncertified_starts"] for r in counted),
            redraws=sum(r["redraws"] for r in counted),
        )  # fmt: skip
        if continuous:
            del summary["courtesy_waived_rate"]
    return summary


def _per_decision(cells: list[dict[str, Any]], field: str) -> float | None:
    """A per-decision figure of ``cells`` (``fallback_rate``, or ``mean_speed`` [m/s]) over all their decisions:
    each cell's value weighted by its decisions; None without decisions."""
    decisions = sum(c["decisions"] for c in cells)
    return sum(c[field] * c["decisions"] for c in cells) / decisions if decisions else None


def continuous_figures(cells: list[dict[str, Any]]) -> dict[str, float | None]:
    """The continuous actions' figures of ``cells`` over all their episodes and decisions: ``off_road_rate``
    (episodes ended off the road ÷ episodes), ``projection_rate`` (decisions whose action the shield projected ÷
    decisions) and ``mean_projection_distance`` [normalised actions] (over the projected decisions); None without
    episodes, decisions or projections."""
    episodes = sum(c["episodes"] for c in cells)
    projected = sum(c.get("projection_rate", 0.0) * c["decisions"] for c in cells)
    distance = sum((c.get("mean_projection_distance") or 0.0) * c.get("projection_rate", 0.0) * c["decisions"]
                   for c in cells)  # fmt: skip
    return {
        "off_road_rate": sum(c.get("off_road_rate", 0.0) * c["episodes"] for c in cells) / episodes
        if episodes else None,
        "projection_rate": _per_decision([c for c in cells if "projection_rate" in c], "projection_rate"),
        "mean_projection_distance": distance / projected if projected else None,
    }  # fmt: skip


COMMITTED_COLUMNS = (
    "uncertified start", "others at fault", "outside the model", "after a break or lapse", "from certified states",
)  # fmt: skip
"""The committed mode's context columns of a summary table (:func:`_group_table`), in its contexts' order."""
CONTINUOUS_COLUMNS = (
    "uncertified start", "others at fault", "outside the model", "after a lapse", "from certified states",
)  # fmt: skip
"""The same with continuous actions, whose shield has lapses and no invariant breaks."""


def _share(value: float | None, digits: int = 2) -> str:
    """A share as a percentage (``–`` for None)."""
    return "–" if value is None else f"{100 * value:.{digits}f} %"


def _number(value: float | None, digits: int = 2) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def _group_table(
    title: str, key: str, played: list[dict[str, Any]], committed: bool = False, continuous: bool = False
) -> list[str]:
    """One table of the summary: every value of ``key`` (a cell's policy, or one axis's setting), with what
    a campaign reports per condition — episodes, collisions with their kinds and against the promise, invariant
    breaks, fallback rate, speed; ``committed``: the committed mode's contexts, lapses and plan-forced share;
    ``continuous``: no breaks or fallbacks, the projections and episodes off the road instead."""
    from safelane.running.collisions import COLLISION_KINDS, collision_contexts

    context_names = collision_contexts(committed)[:5] if committed else ("started_unsafe", "after_break",
                                                                         "from_safe_state")  # fmt: skip
    if continuous:
        headers: tuple[str, ...] = CONTINUOUS_COLUMNS
        figures: tuple[str, ...] = ("lapses (in the model)", "plan-forced", "projected", "mean projection distance",
                                    "off road", "speed [m/s]")  # fmt: skip
    else:
        headers = COMMITTED_COLUMNS if committed else ("started unsafe", "after a break", "from safe states")
        figures = ("invariant breaks", "breaks / 1 000 decisions", "fallback", "speed [m/s]",
                   *(("lapses (in the model)", "plan-forced") if committed else ()))  # fmt: skip
    columns = ("setting", "episodes", "collisions (front / rear / side)", *headers, *figures)
    lines = [f"## By {title}", "", "| " + " | ".join(columns) + " |", "|---" * len(columns) + "|"]
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in played:
        groups.setdefault(str(r[key]), []).append(r)
    for value, rs in groups.items():
        d = sum(r["decisions"] for r in rs)
        b = sum(r["invariant_breaks"] for r in rs)
        kinds = [sum(r["collision_kinds"].get(k, 0) for r in rs) for k in COLLISION_KINDS]  # front, rear, side
        # Cells of campaigns written before the contexts were counted lack them: 0.
        contexts = [sum(r.get("collision_contexts", {}).get(c, 0) for r in rs) for c in context_names]
        fallback, speed = _per_decision(rs, "fallback_rate"), _per_decision(rs, "mean_speed")
        counted = [r for r in rs if "lapses" in r]
        forced = _per_decision(counted, "plan_forced_rate")
        lapses = f"{sum(r['lapses'] for r in counted)} ({sum(r['lapses_in_model'] for r in counted)})"
        line = (
            f"| {value} | {sum(r['episodes'] for r in rs)} | {sum(r['collisions'] for r in rs)} "
            f"({' / '.join(map(str, kinds))}) | {' | '.join(map(str, contexts))} |"
        )
        if continuous:
            figures = continuous_figures(rs)
            line += (
                f" {lapses} | {_share(forced)} | {_share(figures['projection_rate'])} | "
                f"{_number(figures['mean_projection_distance'], 3)} | {_share(figures['off_road_rate'])} | "
                f"{_number(speed)} |"
            )
        else:
            line += (
                f" {b} | {1000 * b / max(d, 1):.2f} | {_share(fallback)} | {_number(speed)} |"
                + (f" {lapses} | {_share(forced)} |" if committed else "")
            )
        lines.append(line)
    return [*lines, ""]


def _markdown(spec: CampaignSpec, summary: dict[str, Any], played: list[dict[str, Any]]) -> str:
    """summary.md: the totals, then a table per policy and per axis over the cells ``played`` (none: no tables)."""
    if spec.continuous:
        return _continuous_markdown(spec, summary, played)
    fallback, speed = summary["fallback_rate"], summary["mean_speed"]
    lines = [
        f"# Falsification campaign {spec.name}: {spec.shield} shield (override on), {spec.simulator} simulator",
        "",
        spec.description.strip(),
        "",
        f"{summary['cells_done']} / {summary['cells']} cells ({summary['cells_skipped']} skipped as not "
        f"supported), {summary['episodes']} episodes, {summary['decisions']} decisions: "
        f"**{summary['collisions']} collisions** {summary['collision_kinds']} "
        f"(against the rule's promise: {summary['collision_contexts']}), "
        f"**{summary['invariant_breaks']} invariant breaks** {summary['break_classes']}"
        + (f"; the shield fell back at {100 * fallback:.3f} % of decisions" if fallback is not None else "")
        + (f", the ego's mean speed {speed:.2f} m/s." if speed is not None else "."),
        "",
    ]
    if "collisions_type_ruled_out" in summary:
        kept, ruled_out = summary["collision_contexts_types_kept"], summary["collisions_type_ruled_out"]
        lines += [
            f"The belief's sets (each car every type whose posterior exceeds ε): **{ruled_out} collisions with a "
            f"car whose true type had been ruled out** (outside the sets: the belief's promise is "
            f"probabilistic); the {summary['collisions'] - ruled_out} others against the "
            f"rule's promise: {kept} (**{kept.get('from_safe_state', 0)} from safe states**).",
            "",
        ]
    committed = spec.shield == "committed"
    if committed and "lapses" in summary:
        forced, waived = summary["plan_forced_rate"], summary.get("courtesy_waived_rate")
        lines += [
            f"Committed plans: **{summary['lapses']} lapses, {summary['lapses_in_model']} in the model** (every car "
            f"inside its set); plan-forced decisions {_share(forced, 3)}; "
            f"courtesy waived at {_share(waived, 3)} of decisions; "
            f"{summary['uncertified_starts']} uncertified starts, {summary['redraws']} spawns redrawn.",
            "",
        ]
    for axis, field in (("policy", "policy"), *((a, f"axis_{a}") for a in spec.axes)) if played else ():
        lines += _group_table(axis, field, played, committed)
    return "\n".join(lines)


def _continuous_markdown(spec: CampaignSpec, summary: dict[str, Any], played: list[dict[str, Any]]) -> str:
    """summary.md of a campaign with continuous actions: what the shield for continuous actions reports."""
    contexts = summary["collision_contexts"]
    lines = [
        f"# Falsification campaign {spec.name}: continuous actions, the shield for continuous actions "
        f"(committed plans, projection), {spec.simulator} simulator",
        "",
        spec.description.strip(),
        "",
        f"{summary['cells_done']} / {summary['cells']} cells ({summary['cells_skipped']} skipped as not "
        f"supported), {summary['episodes']} episodes, {summary['decisions']} decisions: "
        f"**{summary['collisions']} collisions** {summary['collision_kinds']}: "
        f"**{contexts['from_safe_state']} from certified states**, {contexts['uncertified_start']} from uncertified "
        f"starts, {contexts['others_at_fault']} with others at fault, {contexts['outside_model']} outside the model, "
        f"{contexts['after_break']} after a lapse, {contexts['after_fallback']} after a plan-forced or uncertified "
        f"decision.",
        "",
        f"Committed plans: **{summary.get('lapses', 0)} lapses, {summary.get('lapses_in_model', 0)} in the model** "
        f"(every car inside its set); plan-forced decisions {_share(summary.get('plan_forced_rate'), 3)}; "
        f"the shield projected {_share(summary['projection_rate'], 3)} of the actions (mean distance "
        f"{_number(summary['mean_projection_distance'], 3)}, normalised actions); "
        f"{_share(summary['off_road_rate'], 3)} of the episodes ended off the road; "
        f"{summary.get('uncertified_starts', 0)} uncertified starts, {summary.get('redraws', 0)} spawns redrawn; "
        f"the ego's mean speed {_number(summary['mean_speed'])} m/s.",
        "",
    ]
    for axis, field in (("policy", "policy"), *((a, f"axis_{a}") for a in spec.axes)) if played else ():
        lines += _group_table(axis, field, played, True, True)
    return "\n".join(lines)


def merge_shards(spec: CampaignSpec, dirs: list[Path], out_dir: str | Path) -> dict[str, Any]:
    """Merge the summaries of a campaign's shards into ``out_dir``'s summary.json and summary.md: the totals over
    them (:func:`campaign_totals`), the ``shards`` merged and whether they make the whole grid (``complete``: every
    shard of N, each with all its cells done). Each of ``dirs`` holds a shard's campaign.json and summary.json, as
    ``falsify --shard K/N`` writes them and a published result folder keeps them; a folder of another campaign
    than ``spec`` (its shard aside), not a shard, or a shard twice is a one-line ConfigError."""
    whole = spec.model_copy(update={"shard": None})
    found: dict[int, tuple[int, dict[str, Any]]] = {}
    for folder in map(Path, dirs):
        try:
            record = CampaignSpec.model_validate_json((folder / "campaign.json").read_text())
            summary = json.loads((folder / "summary.json").read_text())
        except (OSError, ValueError) as err:
            raise ConfigError(f"--merge {folder}: no campaign.json and summary.json of a campaign there ({err})") \
                from None  # fmt: skip
        shard = record.shard_of()
        if shard is None:
            raise ConfigError(f"--merge {folder}: not a shard (its campaign.json has no shard); allowed: the folders "
                              "of falsify --shard K/N")  # fmt: skip
        if record.model_copy(update={"shard": None}) != whole:
            raise ConfigError(f"--merge {folder}: a shard of another campaign than {spec.name!r} as given")
        k, n = shard
        if k in found or any(m != n for m, _ in found.values()):
            raise ConfigError(f"--merge {folder}: shard {k}/{n} twice, or beside shards of another N")
        found[k] = (n, summary)
    if not found:
        raise ConfigError("--merge: no folder given; allowed: the folders of falsify --shard K/N")
    summaries = [summary for _, (_, summary) in sorted(found.items())]
    n = next(iter(found.values()))[0]
    merged = campaign_totals(whole, summaries, len(whole.cells()), sum(s["cells_done"] for s in summaries),
                             sum(s["cells_skipped"] for s in summaries))  # fmt: skip
    merged["shards"] = [f"{k}/{n}" for k in sorted(found)]
    merged["complete"] = len(found) == n and all(s["cells_done"] == s["cells"] for s in summaries)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "summary.json", json.dumps(merged, indent=1))
    kept = all("collision_contexts_types_kept" in s for s in summaries)  # the belief shield: its types kept apart
    rows = [f"| {k}/{n} | {s['cells_done']} / {s['cells']} | {s['episodes']} | {s['collisions']} | "
            f"{s['collision_contexts'].get('from_safe_state', 0)} | "
            + (f"{s['collision_contexts_types_kept'].get('from_safe_state', 0)} | " if kept else "")
            + f"{s.get('lapses_in_model', '–')} |"
            for k, (_, s) in sorted(found.items())]  # fmt: skip
    head = "| shard | cells | episodes | collisions | from safe or certified states | " + (
        "… the true types kept | " if kept else "") + "lapses in the model |"
    shards = ["", f"Merged from {len(found)} of {n} shards ({'the whole grid' if merged['complete'] else 'not all'}):",
              "", head, "|---" * head.count(" | ") + "|---|", *rows, ""]  # fmt: skip
    atomic_write_text(out / "summary.md", _markdown(whole, merged, []) + "\n".join(shards))
    return merged
