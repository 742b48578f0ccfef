"""Counterexamples as files: a crash, an invariant break or a lapse, saved small and replayed exactly.

A :class:`Counterexample` holds what it takes to play the episode again — the environment configuration
(with its simulator), the reset seed and the actions the policy *chose* (a shield's overrides are
re-derived by the same shield): meta-action indices, or with continuous actions ``[acceleration, steering]``
pairs of float32 values, each written as the shortest decimal that reads back to the same float (exact), with
the actions the shield for continuous actions executed beside them (``executed``; the replay checks it executes
the same) — and the event: a ``collision`` at the last decision, or an
``invariant_break`` (a fallback state reached right after an allowed action in a state that had a safe
one, :class:`safelane.safety.shield.SafetyShield`) after decision ``step``, or (the ``committed`` shield mode) a
``lapse`` or ``lapse_in_model`` after decision ``step`` (:data:`LAPSE_KINDS`; ``cars`` names the cars the kept
plan fails on; with continuous actions the shield judges a state when it decides there, so ``step`` is the decision
whose judgement found the lapse, before its action ran).
Both simulators are deterministic after reset, so :func:`replay` plays the same decisions and checks the same
event happens at the same decision; ``simulator=`` replays a fast-simulator finding on highway-env (the reference).

:func:`save_counterexamples` writes one file per crash, per break and per lapse of a list of
:class:`~safelane.running.evaluation.EpisodeRecord` (``evaluate`` / ``stress`` ``--save-counterexamples``).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from safelane.config import ConfigError, SafelaneConfig, build_config, config_to_dict, recorded_config
from safelane.core.files import atomic_write_text
from safelane.running.collisions import SCENE_RANGE, scene_near_ego

NEAR = SCENE_RANGE
"""[m] Vehicles within this distance of the ego, along the road, are logged."""

EventKind = Literal["collision", "invariant_break", "lapse", "lapse_in_model"]
LAPSE_KINDS: tuple[str, ...] = ("lapse", "lapse_in_model")
"""The committed shield mode's events: a ``lapse`` (the plan kept, verified, no longer verifies) traced to cars
outside the sets drawn for them (or, under ``responsibility``, to a car that entered a lane the ego holds), and a
``lapse_in_model`` (every car inside its set: a gap in the construction)."""


class Counterexample(BaseModel):
    """One replayable finding (see the module docstring). ``step`` is 1-based: the decision after which
    the event was observed."""

    model_config = ConfigDict(extra="forbid")

    format: Literal["safelane-counterexample/1"] = "safelane-counterexample/1"
    kind: EventKind
    config: dict[str, Any] = Field(description="The environment configuration (config_to_dict).")
    seed: int = Field(ge=0, description="Reset seed of the episode.")
    actions: list[int] | list[tuple[float, float]] = Field(
        description="Actions the policy chose, decision by decision: meta-actions (0..4), or with continuous actions "
        "[acceleration, steering] in [-1, 1] (float32 values, written exactly)."
    )
    step: int = Field(ge=1, description="Decision (1-based) after which the event was observed.")
    collision_kind: str | None = None
    source: str = Field("", description="What found it (command, policy, condition).")
    cars: list[int] | None = Field(
        None,
        description="A lapse: the cars (snapshot indices) the kept plan fails on (info lapse_cars); absent for "
        "the other kinds.",
    )
    executed: list[tuple[float, float]] | None = Field(
        None,
        description="Continuous actions under their shield: the [acceleration, steering] it executed at each decision "
        "(float32 values, written exactly); absent otherwise.",
    )

    @model_validator(mode="after")
    def _actions_fit_the_config(self) -> Counterexample:
        """Meta-action indices for a meta-action config, pairs for continuous actions (one-line errors)."""
        continuous = self.config.get("actions") == "continuous"
        pairs = any(isinstance(a, tuple) for a in self.actions)
        if continuous and any(not isinstance(a, tuple) for a in self.actions):
            raise ValueError("actions: the config's actions are continuous; allowed: [acceleration, steering] pairs")
        if not continuous and (pairs or self.executed is not None):
            raise ValueError("actions: the config's actions are meta-actions; allowed: indices 0..4, no executed")
        return self

    def env_config(self, simulator: str | None = None) -> SafelaneConfig:
        """The configuration to replay in (``simulator`` overrides the recorded one)."""
        data = dict(self.config)
        if simulator is not None:
            data["simulator"] = simulator
        return recorded_config(data)


def counterexample_json(cx: Counterexample) -> str:
    """A counterexample file's text: indented JSON without the fields its kind leaves empty (``cars``, ``executed``),
    so a meta-action file reads as it always did."""
    exclude = {name for name in ("cars", "executed") if getattr(cx, name) is None}
    return cx.model_dump_json(indent=1, exclude=exclude)


def _pair(action: Any) -> tuple[float, float]:
    """``[acceleration, steering]`` as Python floats of its float32 values (exact)."""
    a, s = np.asarray(action, dtype=np.float32).ravel()
    return float(a), float(s)


def load_counterexample(path: str | Path) -> Counterexample:
    """Read a counterexample file (a one-line :class:`ConfigError` if it is missing or malformed)."""
    path = Path(path)
    try:
        return Counterexample.model_validate_json(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such counterexample file") from None
    except ValidationError as err:
        e = err.errors()[0]
        where = ".".join(map(str, e["loc"]))  # empty for a check across fields, whose message names them
        message = e["msg"].removeprefix("Value error, ")
        raise ConfigError(f"{path}: not a counterexample ({f'{where}: ' if where else ''}{message})") from None


def counterexample_files(
    folder: str | Path, kind: EventKind, sample: int | None = None, seed: int = 0, limit: int | None = None
) -> list[str]:
    """The paths of ``folder``'s counterexample files of ``kind``, sorted by name: the first ``limit`` of them,
    then (with ``sample``) at most ``sample`` drawn at random with ``seed``, again sorted. A ``sample`` below 1 is
    a one-line :class:`ConfigError`."""
    import random

    if sample is not None and sample < 1:
        raise ConfigError(f"--sample: got {sample}; allowed: a whole number of files >= 1")
    files = sorted(str(p) for p in Path(folder).glob(f"*-{kind}-*.json"))[:limit]
    if sample is not None and sample < len(files):
        files = sorted(random.Random(seed).sample(files, sample))
    return files


def counterexamples_of(records: list[Any], config: SafelaneConfig, source: str = "") -> list[Counterexample]:
    """One :class:`Counterexample` per collision, per invariant break and (the committed mode) per lapse in
    ``records``."""
    found: list[Counterexample] = []
    data = config_to_dict(config)
    continuous = config.actions == "continuous"

    def actions(r: Any, step: int) -> dict[str, Any]:
        """The first ``step`` chosen actions of record ``r`` (and, continuous under a shield, those executed)."""
        if not continuous:
            return {"actions": list(r.chosen_actions[:step])}
        executed = getattr(r, "executed_actions", [])
        return {
            "actions": [_pair(a) for a in r.chosen_actions[:step]],
            "executed": [_pair(a) for a in executed[:step]] if executed else None,
        }

    for r in records:
        for step in r.invariant_breaks:
            found.append(
                Counterexample(
                    kind="invariant_break", config=data, seed=r.seed, step=step, source=source, **actions(r, step)
                )
            )
        for step, cars in zip(getattr(r, "lapses", ()), getattr(r, "lapse_cars", ()), strict=True):
            found.append(
                Counterexample(
                    kind="lapse_in_model" if step in r.lapses_in_model else "lapse",
                    config=data,
                    seed=r.seed,
                    step=step,
                    source=source,
                    cars=list(cars),
                    **actions(r, step),
                )
            )
        if r.collision:
            found.append(
                Counterexample(
                    kind="collision",
                    config=data,
                    seed=r.seed,
                    step=r.length,
                    collision_kind=r.collision_kind,
                    source=source,
                    **actions(r, r.length),
                )
            )
    return found


def save_counterexamples(
    records: list[Any], config: SafelaneConfig, out_dir: str | Path, source: str = "", prefix: str = ""
) -> list[Path]:
    """Write :func:`counterexamples_of` as ``out_dir/PREFIXseedSEED-KIND-stepSTEP.json`` (atomically,
    :func:`counterexample_json`), on the disk when it returns: flushed together, not one ``fsync`` each (a
    campaign under hidden types writes tens of thousands, at about 4 ms an ``fsync`` on this project's machine)."""
    out = Path(out_dir)
    paths = []
    for cx in counterexamples_of(records, config, source):
        path = out / f"{prefix}seed{cx.seed}-{cx.kind}-step{cx.step}.json"
        atomic_write_text(path, counterexample_json(cx), durable=False)
        paths.append(path)
    if paths:
        os.sync()
    return paths


@dataclass
class Decision:
    """One logged decision of a replay. Distances [m], speeds [m/s], time [s]. With continuous actions ``chosen`` and
    ``executed`` are ``[acceleration, steering]`` and there is no mask, gap or fallback (None)."""

    step: int
    time: float
    chosen: int | list[float]
    executed: int | list[float]
    mask: list[bool] | None
    min_gap: list[float | None] | None  # an entry None: no conflict (an infinite gap)
    fallback_before: bool | None
    fallback_after: bool | None
    invariant_break: bool
    collision: bool
    ego: dict[str, float]
    nearby: list[dict[str, float]] = field(default_factory=list)
    committed: dict[str, Any] | None = None
    """The committed mode's verdict after the decision (``lapse``, ``lapse_in_model``, ``plan_forced``,
    ``certified``, ``lapse_cars``, ``escaped_cars``, ``entered_cars``; with continuous actions the verdict at the
    decision, and ``projected``, ``projection_distance``); None for the other modes."""
    off_road: bool | None = None
    """Continuous actions: the ego is off the road after the decision (None: meta-actions)."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (``committed`` only for that mode, the fields continuous actions lack left out)."""
        optional = ("mask", "min_gap", "fallback_before", "fallback_after", "committed", "off_road")
        return {k: v for k, v in self.__dict__.items() if not (k in optional and v is None)}


@dataclass
class ReplayResult:
    """What a replay saw: the decision log and whether the recorded event happened again."""

    counterexample: Counterexample
    simulator: str
    decisions: list[Decision]
    reproduced: bool
    collision_kind: str | None
    final: dict[str, Any] = field(default_factory=dict)
    """The state after the last decision: its mask, worst-case gaps, fallback, ego and nearby vehicles
    (for a break: the state the model found no safe action in)."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {
            "kind": self.counterexample.kind,
            "step": self.counterexample.step,
            "simulator": self.simulator,
            "reproduced": self.reproduced,
            "collision_kind": self.collision_kind,
            "decisions": [d.to_dict() for d in self.decisions],
            "final": self.final,
        }


def replay(cx: Counterexample, simulator: str | None = None) -> ReplayResult:
    """Play ``cx`` again (on ``simulator`` if given) and log every decision up to its event.

    A configuration without a shield is replayed with a robust shield that only observes (no override),
    so the log still shows masks and gaps; the episode is the same.
    """
    from safelane.env.factory import make_env
    from safelane.running.collisions import classify_collision

    cfg = cx.env_config(simulator)
    if cfg.actions == "continuous":
        return _replay_controls(cx, cfg)
    if cfg.shield.mode == "none":
        data = config_to_dict(cfg)
        data["shield"] = {**data["shield"], "mode": "robust", "override": False}
        cfg = build_config(data)
    env = make_env(cfg)
    decisions: list[Decision] = []
    kind = None
    try:
        _, info = env.reset(seed=cx.seed)
        done = False
        for k, action in enumerate(cx.actions[: cx.step], start=1):
            if done:
                break
            result = env.get_wrapper_attr("result")
            ego, nearby = scene_near_ego(info["snapshot"])
            _, _, terminated, truncated, info = env.step(int(action))
            decisions.append(
                Decision(
                    step=k,
                    time=float(info["snapshot"].time),
                    chosen=int(action),
                    executed=int(info.get("executed_action", action)),
                    mask=[bool(m) for m in result.mask],
                    min_gap=[round(float(g), 3) if np.isfinite(g) else None for g in result.min_gap],
                    fallback_before=bool(result.fallback),
                    fallback_after=bool(info["fallback"]),
                    invariant_break=bool(info.get("invariant_break", False)),
                    collision=bool(info.get("collision", False)),
                    ego=ego,
                    nearby=nearby,
                    committed=_committed_verdict(info),
                )
            )
            done = bool(terminated or truncated)
        if decisions and decisions[-1].collision:
            kind = classify_collision(info["snapshot"])
        result = env.get_wrapper_attr("result")
        ego, nearby = scene_near_ego(info["snapshot"])
        final = {
            "time": float(info["snapshot"].time),
            "mask": [bool(m) for m in result.mask],
            "min_gap": [round(float(g), 3) if np.isfinite(g) else None for g in result.min_gap],
            "fallback": bool(result.fallback),
            "ego": ego,
            "nearby": nearby,
        }
    finally:
        env.close()
    return ReplayResult(cx, cfg.simulator, decisions, _reproduced(cx, decisions), kind, final)


def _replay_controls(cx: Counterexample, cfg: SafelaneConfig) -> ReplayResult:
    """:func:`replay` with continuous actions: each chosen ``[acceleration, steering]`` stepped as float32 in
    ``cfg``'s environment (with its shield, if any: no observer shield exists for controls)."""
    from safelane.env.factory import make_env
    from safelane.running.collisions import classify_collision

    env = make_env(cfg)
    decisions: list[Decision] = []
    kind = None
    try:
        _, info = env.reset(seed=cx.seed)
        done = False
        for k, action in enumerate(cx.actions[: cx.step], start=1):
            if done:
                break
            ego, nearby = scene_near_ego(info["snapshot"])
            chosen = np.asarray(action, dtype=np.float32)
            _, _, terminated, truncated, info = env.step(chosen)
            decisions.append(
                Decision(
                    step=k,
                    time=float(info["snapshot"].time),
                    chosen=list(_pair(chosen)),
                    executed=list(_pair(info.get("executed_action", chosen))),
                    mask=None,
                    min_gap=None,
                    fallback_before=None,
                    fallback_after=None,
                    invariant_break=False,
                    collision=bool(info.get("collision", False)),
                    ego=ego,
                    nearby=nearby,
                    committed=_committed_verdict(info),
                    off_road=bool(info["off_road"]),
                )
            )
            done = bool(terminated or truncated)
        if decisions and decisions[-1].collision:
            kind = classify_collision(info["snapshot"])
        ego, nearby = scene_near_ego(info["snapshot"])
        final = {"time": float(info["snapshot"].time), "ego": ego, "nearby": nearby, "off_road": bool(info["off_road"])}
    finally:
        env.close()
    reproduced = _reproduced(cx, decisions)
    if cx.executed is not None:  # the shield executed the same actions, bit for bit
        reproduced = reproduced and [d.executed for d in decisions] == [list(a) for a in cx.executed[: cx.step]]
    return ReplayResult(cx, cfg.simulator, decisions, reproduced, kind, final)


def _reproduced(cx: Counterexample, decisions: list[Decision]) -> bool:
    """Whether the replay's ``decisions`` end in ``cx``'s event at its decision (and not earlier, for a crash)."""
    last = decisions[-1] if len(decisions) == cx.step else None
    if cx.kind == "collision":
        reproduced = last is not None and last.collision and not any(d.collision for d in decisions[:-1])
    elif cx.kind in LAPSE_KINDS:
        verdict = last.committed if last is not None else None
        reproduced = (
            verdict is not None
            and verdict["lapse"]
            and verdict["lapse_in_model"] == (cx.kind == "lapse_in_model")
            and (cx.cars is None or set(verdict["lapse_cars"]) == set(cx.cars))
        )
    else:
        reproduced = last is not None and last.invariant_break
    return bool(reproduced)


def _committed_verdict(info: dict[str, Any]) -> dict[str, Any] | None:
    """The committed mode's verdict of a step's ``info`` (None for the other modes; with continuous actions also
    ``projected`` and ``projection_distance``)."""
    if "lapse" not in info:
        return None
    projection = {}
    if "projection_distance" in info:  # the shield for continuous actions
        projection = {"projected": bool(info["projected"]), "projection_distance": float(info["projection_distance"])}
    return {
        **projection,
        "lapse": bool(info["lapse"]),
        "lapse_in_model": bool(info["lapse_in_model"]),
        "plan_forced": bool(info["plan_forced"]),
        "certified": bool(info["certified"]),
        "lapse_cars": [int(v) for v in info.get("lapse_cars", ())],
        "escaped_cars": [int(v) for v in info["escaped_cars"]],
        "entered_cars": [int(v) for v in info["entered_cars"]],
    }


def render_counterexample(cx: Counterexample, out_path: str | Path) -> Path:
    """Draw the replay (on highway-env, which plays the same episode) to a GIF / MP4 with the mask legend
    (meta-actions only: a one-line :class:`ConfigError` for continuous actions, which have no mask to draw)."""
    from safelane.running.episode_video import render_episode

    if cx.config.get("actions") == "continuous":
        raise ConfigError("--gif: draws meta-action episodes with their mask; allowed with continuous actions: none")

    actions = iter(cx.actions)

    def policy(obs: np.ndarray, info: dict[str, Any]) -> int:
        return next(actions)

    cfg = cx.env_config()
    return render_episode(cfg, policy, cx.seed, out_path, max_steps=cx.step).path


def dump_json(result: ReplayResult) -> str:
    """The replay as one JSON object."""
    return json.dumps(result.to_dict())
