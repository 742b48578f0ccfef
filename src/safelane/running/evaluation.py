"""Run policies on the environment and summarise what happened: collisions, speed, shield activity.

A policy is any callable ``policy(obs, info) -> action index`` (0..4, :mod:`safelane.core.spaces`;
:mod:`safelane.running.policies` has those that need no training). :func:`run_episodes` plays seeded
episodes (episode ``i`` is reset with ``seed + i``) and returns one :class:`EpisodeRecord` per episode;
:func:`summarize` turns records into one JSON-ready dict. The CLI's ``safelane evaluate`` is a thin layer over
:func:`evaluate_fixed`.

Collisions are classified from geometry at the moment of impact
(:func:`safelane.running.collisions.classify_collision`) and against the rule's promise
(:data:`safelane.running.collisions.COLLISION_CONTEXTS`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np

from safelane.config import ConfigError, SafelaneConfig
from safelane.core.snapshot import RoadSnapshot
from safelane.core.spaces import ACTION_NAMES, N_ACTIONS
from safelane.running.collisions import (
    COLLISION_KINDS,
    break_class_of_snapshots,
    classify_collision,
    collision_contexts,
    collision_partner,
)
from safelane.running.policies import Policy, fixed_policy
from safelane.safety.control_shield import ControlShield
from safelane.safety.shield import SafetyShield

if TYPE_CHECKING:
    from safelane.env.fast_batch import FastBatch


# --- episodes -----------------------------------------------------------------------------------


@dataclass
class EpisodeRecord:
    """What happened in one episode. Speeds in m/s, times in s, lengths in decisions."""

    seed: int
    return_: float
    length: int
    collision: bool
    time_to_collision: float | None
    mean_speed: float
    interventions: int
    fallbacks: int
    collision_kind: str | None
    unsafe_actions: int = 0
    """Decisions whose *chosen* action the shield's mask marked unsafe (overridden or not)."""
    actions: list[int] = field(default_factory=lambda: [0] * N_ACTIONS)
    """Histogram of the executed actions (after a shield's override), indexed like ACTION_NAMES."""
    vehicles_passed: int = 0
    """Net overtakes: vehicles ahead of the ego (along the road) at the start minus at the end."""
    invariant_breaks: list[int] = field(default_factory=list)
    """Decisions (1-based) after which the shield found no safe action although the previous state
    had one and an allowed action was taken: counterexamples to the rule's invariant."""
    collision_context: str | None = None
    """Where a collision stands with respect to the shield's promise (None without a collision or a
    shield): see :data:`~safelane.running.collisions.COLLISION_CONTEXTS`."""
    chosen_actions: list[int] | list[list[float]] = field(default_factory=list, repr=False)
    """The action the policy chose at each decision (before any override): with the seed and the
    configuration, enough to replay the episode (:mod:`safelane.running.counterexamples`). Not in
    :meth:`to_dict` (a run's 1 000 test episodes would carry 40 000 of them)."""
    # The committed shield mode's figures (the others leave them at their defaults; :meth:`to_dict` omits them).
    uncertified_start: bool | None = None
    """``committed`` mode: the episode's first state had no verified plan (None: another mode)."""
    lapses: list[int] = field(default_factory=list)
    """``committed`` mode: decisions (1-based) after which the plan kept, verified, no longer verified; with continuous
    actions (:class:`~safelane.safety.control_shield.ControlShield`, which judges a state when it decides there) the
    decision whose judgement found it, before its action ran."""
    lapses_in_model: list[int] = field(default_factory=list)
    """``committed`` mode: the lapses not traced to the model's exits (a car the kept plan fails on inside its
    set, :attr:`safelane.safety.committed.family.CommittedResult.lapse_in_model`): gaps in the construction."""
    lapse_cars: list[list[int]] = field(default_factory=list)
    """``committed`` mode: per lapse, the cars (snapshot indices) the kept plan fails on (``info["lapse_cars"]``)."""
    plan_forced: int = 0
    """``committed`` mode: decisions at which nothing verified and the kept plan's next step drove (counted like
    ``fallbacks``, from the state each step ends in)."""
    courtesy_waived: int = 0
    """``committed`` mode: decisions at which some action was verified but none was safe by the one-decision robust
    rule (:func:`safelane.safety.committed.family.courteous`; counted like ``plan_forced``)."""
    redraws: int = 0
    """``committed`` mode with ``shield.redraw_uncertified``: spawns drawn again before this one
    (:class:`safelane.env.redraw.RedrawUncertified`)."""
    outside_model_cars: list[int] = field(default_factory=list)
    """A collision in context ``outside_model``: the cars (snapshot indices) that had left their sets: those a
    lapse's kept plan failed on, and the crash partner if it had (or rolled back, or did not brake as a follower
    of the plan, by the crash's own decision)."""
    off_road: bool | None = None
    """Continuous actions: the episode ended with the ego off the road (None: meta-actions, which keep it on)."""
    type_ruled_out_crash: bool | None = None
    """``belief`` mode: the ego crashed with a car whose true driver type the belief had ruled out at the decision
    (``info["type_ruled_out_crash"]``: outside the belief's sets; None: another mode)."""
    projection_distance: float | None = None
    """The shield for continuous actions: the distances [normalised actions] from the policy's action to the executed
    one, summed over the episode's decisions (``interventions`` counts the projected ones; None: another shield or
    none)."""
    break_classes: dict[int, str] = field(default_factory=dict, repr=False)
    """Each invariant break's class (:func:`~safelane.running.collisions.break_class_of`) by its decision, where the
    episode loop saw the snapshots before and after it (every loop but the fast batch's). Not in :meth:`to_dict`."""
    executed_actions: list[list[float]] = field(default_factory=list, repr=False)
    """The shield for continuous actions: the ``[acceleration, steering]`` it executed at each decision (float32
    values), which a counterexample file records beside the chosen ones; empty otherwise. Not in :meth:`to_dict`."""

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict of the record (without ``chosen_actions``; the committed mode's fields only for
        that mode, ``off_road`` only for continuous actions, which have no ``actions`` histogram,
        ``projection_distance`` only under the shield for continuous actions)."""
        data = asdict(self)
        del data["chosen_actions"], data["executed_actions"], data["break_classes"]
        if self.uncertified_start is None:
            for name in COMMITTED_FIELDS:
                del data[name]
        if self.off_road is None:
            del data["off_road"]
        else:
            del data["actions"]
        if self.projection_distance is None:
            del data["projection_distance"]
        if self.type_ruled_out_crash is None:
            del data["type_ruled_out_crash"]
        return data


COMMITTED_FIELDS: tuple[str, ...] = (
    "uncertified_start", "lapses", "lapses_in_model", "lapse_cars", "plan_forced", "courtesy_waived", "redraws",
    "outside_model_cars",
)  # fmt: skip
"""The :class:`EpisodeRecord` fields only the ``committed`` shield mode fills."""


Action = int | np.ndarray
"""A meta-action index, or ``[acceleration, steering]`` in [-1, 1] with continuous actions."""

ProgressCallback = Callable[[int, EpisodeRecord], None]
"""Called as ``progress(episode_index, record)`` after each episode."""


def vehicles_ahead(snap: RoadSnapshot) -> int:
    """Number of other vehicles ahead of the ego along the road (x; the roads are straight)."""
    others = snap.others()
    return int(np.count_nonzero(snap.position[others, 0] > snap.position[snap.ego, 0]))


class EpisodeTally:
    """What an episode's steps add up to, step by step: the one bookkeeping of :func:`run_episode` and
    :func:`run_episodes_batched` (so both give the same :class:`EpisodeRecord` for the same steps)."""

    def __init__(self, seed: int, reset_info: dict[str, Any], committed: bool = False) -> None:
        """``reset_info``: the episode's reset ``info``; ``committed``: the shield is the committed mode's."""
        self.seed = seed
        self.ahead_at_start = vehicles_ahead(reset_info["snapshot"])
        self.total_reward = 0.0
        self.speeds: list[float] = []
        self.interventions = self.fallbacks = self.unsafe_actions = 0
        self.breaks: list[int] = []
        self.actions = [0] * N_ACTIONS
        self.chosen: list[Any] = []  # meta-action indices, or [acceleration, steering] per decision
        self.time_to_collision: float | None = None
        self.collision = False
        self.steps = 0
        # The shield for continuous actions judges a state when it decides there: a step's verdict (certified,
        # plan-forced, lapse, escapes) is on the state its action was taken in, where the other shields report the
        # state the step ends in.
        self.judged_before = "projection_distance" in reset_info
        # For the collision's context: whether a shield reports fallbacks (or verdicts), whether any state so far had
        # a safe action (a verified plan), and whether the state the next action is taken in has one.
        self.shielded = "fallback" in reset_info or self.judged_before
        if self.judged_before:
            self.safe_seen = self.state_safe = bool(reset_info["certified"])
        else:
            self.safe_seen = self.state_safe = reset_info.get("fallback") is False
        self.projection_distance = 0.0 if self.judged_before else None
        self.executed: list[list[float]] = []
        self.context: str | None = None
        # The committed mode: lapses, plan-forced decisions, and the cars that left their sets or entered a lane
        # the ego holds, for the collision's context.
        self.committed = committed
        self.uncertified_start = bool(reset_info["uncertified_start"]) if self.committed else None
        self.redraws = int(reset_info.get("redraws", 0))
        self.lapses: list[int] = []
        self.lapses_in_model: list[int] = []
        self.lapse_cars: list[list[int]] = []
        self.plan_forced = 0
        self.courtesy_waived = 0
        self.escaped_seen: set[int] = set()
        self.entered_seen: set[int] = set()
        self.lapse_named: set[int] = set()
        self.outside_model_cars: list[int] = []
        # Continuous actions (the reward reports ``off_road``): the chosen controls, no meta-action histogram.
        self.continuous = "off_road" in reset_info
        self.off_road = bool(reset_info["off_road"]) if self.continuous else None
        # The belief shield: whether a crash came with a car whose true type it had ruled out.
        self.type_ruled_out_crash = False if "type_ruled_out_crash" in reset_info else None
        self.snapshot_before = reset_info.get("snapshot")
        self.break_classes: dict[int, str] = {}

    def add(self, action: Action, reward: float, info: dict[str, Any]) -> None:
        """Count one decision: the ``action`` chosen, the ``reward`` and ``info`` its step returned."""
        self.steps += 1
        if self.continuous:
            self.chosen.append([float(a) for a in np.asarray(action).ravel()])
            self.off_road = bool(info["off_road"])
        else:
            self.chosen.append(int(action))
            self.actions[int(info.get("executed_action", action))] += 1
        if self.judged_before:
            self._count_judged(info)
        self.total_reward += float(reward)
        self.speeds.append(float(info["speed"]))
        self.interventions += bool(info.get("shield_intervened", False))
        self.fallbacks += bool(info.get("fallback", False))
        self.unsafe_actions += bool(info.get("unsafe_action", False))
        if info.get("invariant_break", False):
            self.breaks.append(self.steps)
            if self.snapshot_before is not None and "snapshot" in info:
                self.break_classes[self.steps] = break_class_of_snapshots(self.snapshot_before, info["snapshot"])
        self.snapshot_before = info.get("snapshot")
        if info.get("type_ruled_out_crash", False):
            self.type_ruled_out_crash = True
        if info.get("collision", False) and not self.collision:
            self.collision = True
            self.time_to_collision = info["snapshot"].time
            if self.committed:
                self.context = self._committed_context(info)
            elif self.shielded:
                earlier_break = bool(self.breaks) and self.breaks[0] < self.steps
                # The action *executed* was outside the mask: chosen unsafe and not overridden (an overridden
                # choice executes an allowed action, so its crash is the rule's, from a safe state).
                executed_unsafe = info.get("unsafe_action", False) and not info.get("shield_intervened", False)
                if not self.safe_seen:
                    self.context = "started_unsafe"
                elif earlier_break:
                    self.context = "after_break"
                elif self.state_safe and not executed_unsafe:
                    self.context = "from_safe_state"
                else:
                    self.context = "after_fallback"
        if self.judged_before:
            return
        if self.committed:
            self._count_committed(info)
        self.state_safe = info.get("fallback") is False
        self.safe_seen = self.safe_seen or self.state_safe

    def _count_judged(self, info: dict[str, Any]) -> None:
        """The shield for continuous actions' verdict on the state this decision was taken in (before its action
        ran): some action had a verified plan there (certified, not plan-forced), the action executed and how far
        the shield moved it, and the committed figures (escapes, lapses), all before the step's own collision."""
        self.state_safe = bool(info["certified"]) and not bool(info["plan_forced"])
        self.safe_seen = self.safe_seen or self.state_safe
        self.executed.append([float(a) for a in np.asarray(info["executed_action"]).ravel()])
        self.projection_distance = (self.projection_distance or 0.0) + float(info["projection_distance"])
        if self.committed:
            self._count_committed(info)

    def _count_committed(self, info: dict[str, Any]) -> None:
        """The committed mode's figures of one step (after its collision's context: the crash step's own escapes
        are the impact's, not a cause)."""
        self.plan_forced += bool(info.get("plan_forced", False))
        self.courtesy_waived += bool(info.get("courtesy_waived", False))
        escaped = [int(v) for v in info.get("escaped_cars", ())]
        entered = [int(v) for v in info.get("entered_cars", ())]
        if not self.collision:
            self.escaped_seen.update(escaped)
            self.entered_seen.update(entered)
        if info.get("lapse", False):
            self.lapses.append(self.steps)
            failed = [int(v) for v in info.get("lapse_cars", ())]
            self.lapse_cars.append(sorted(set(failed)))
            self.lapse_named.update(v for v in failed if v in escaped)  # the cars that broke the plan, out of model
            if info.get("lapse_in_model", False):
                self.lapses_in_model.append(self.steps)

    def _committed_context(self, info: dict[str, Any]) -> str:
        """The context of the committed mode's collision at this step (:data:`COLLISION_CONTEXTS`). The escapes
        reported in the crash step's own state are left out, but for the partner's ``rolled_back`` and
        ``unbraked_followers``: highway-env's impact (bodies pushed apart, a crashed car braking at its speed per
        second) puts every crashed body outside any driver model's set, but neither rolls it back nor pushes a
        follower forward."""
        snap = info["snapshot"]
        partner = collision_partner(snap)
        executed_unsafe = info.get("unsafe_action", False) and not info.get("shield_intervened", False)
        # The crash's own decision counts its partner's exits the impact does not make: rolling back (a crashed car
        # brakes to 0 m/s, never below), a follower ahead of the bound the plan drew for it (the impact pushes the
        # bodies apart: a rear-ender back).
        # The shield for continuous actions never judges the state the crash ends in: run_episode adds its trace
        # (crash_state_trace) under "crash_state"; the step's own keys are the state before, counted already.
        own = info.get("crash_state", {}) if self.judged_before else info
        exits = self.escaped_seen | {int(v) for key in ("rolled_back", "unbraked_followers") for v in own.get(key, ())}
        named = sorted(self.lapse_named | ({partner} & exits if partner is not None else set()))
        if not self.safe_seen:
            return "uncertified_start"
        entered = self.entered_seen | {int(v) for v in own.get("entered_cars", ())}  # a cut-in into the crash counts
        if classify_collision(snap) == "rear_ended" or partner in entered:
            return "others_at_fault"
        if named:
            self.outside_model_cars = named
            return "outside_model"
        # A lapse found by the crash's own decision (continuous actions) came before its action.
        first = self.lapses[0] if self.lapses else None
        lapsed = first is not None and (first <= self.steps if self.judged_before else first < self.steps)
        if (self.breaks and self.breaks[0] < self.steps) or lapsed:
            return "after_break"
        if self.state_safe and not executed_unsafe:
            return "from_safe_state"
        return "after_fallback"

    def record(self, last_info: dict[str, Any]) -> EpisodeRecord:
        """The finished episode's record (``last_info``: the info of its last step)."""
        snap = last_info["snapshot"]
        return EpisodeRecord(
            seed=self.seed,
            return_=self.total_reward,
            length=self.steps,
            collision=self.collision,
            time_to_collision=self.time_to_collision,
            mean_speed=float(np.mean(self.speeds)),
            interventions=self.interventions,
            fallbacks=self.fallbacks,
            collision_kind=classify_collision(snap) if self.collision else None,
            unsafe_actions=self.unsafe_actions,
            actions=self.actions,
            vehicles_passed=self.ahead_at_start - vehicles_ahead(snap),
            invariant_breaks=self.breaks,
            collision_context=self.context,
            chosen_actions=self.chosen,
            uncertified_start=self.uncertified_start,
            lapses=self.lapses,
            lapses_in_model=self.lapses_in_model,
            lapse_cars=self.lapse_cars,
            plan_forced=self.plan_forced,
            courtesy_waived=self.courtesy_waived,
            redraws=self.redraws,
            outside_model_cars=self.outside_model_cars,
            off_road=self.off_road,
            type_ruled_out_crash=self.type_ruled_out_crash,
            projection_distance=self.projection_distance,
            executed_actions=self.executed,
            break_classes=self.break_classes,
        )


def _control_shield(env: gym.Env) -> ControlShield | None:
    """The :class:`ControlShield` among ``env``'s wrappers (None: none)."""
    layer: Any = env
    while isinstance(layer, gym.Wrapper):
        if isinstance(layer, ControlShield):
            return layer
        layer = layer.env
    return None


def shield_mode(env: gym.Env) -> str:
    """The ``shield.mode`` of the :class:`SafetyShield` among ``env``'s wrappers, ``"committed"`` for the shield for
    continuous actions (:class:`ControlShield`, the committed rule for controls), ``"none"``: no shield."""
    layer: Any = env
    while isinstance(layer, gym.Wrapper):
        if isinstance(layer, SafetyShield):
            return layer.mode
        if isinstance(layer, ControlShield):
            return "committed"
        layer = layer.env
    return "none"


def crash_state_trace(env: gym.Env, info: dict[str, Any]) -> dict[str, tuple[int, ...]]:
    """What the shield for continuous actions would report of the state a step ended in (``info["snapshot"]``),
    which it never judges when the episode ends there: ``rolled_back``, ``unbraked_followers`` and ``entered_cars``
    (snapshot indices), as a committed :class:`SafetyShield` reports them after a crash's step. Empty without that
    shield or before its first decision."""
    shield = _control_shield(env)
    if shield is None or shield.dynamics is None:
        return {}
    _, vehicle, _, trace = shield.family.state_of(info["snapshot"], shield.dynamics)
    names = {"rolled_back": "rolled", "unbraked_followers": "unbraked", "entered_cars": "entered"}
    return {key: tuple(int(v) for v in vehicle[trace[name]]) for key, name in names.items()}


def run_episode(env: gym.Env, policy: Policy, seed: int) -> EpisodeRecord:
    """Play one episode reset with ``seed`` until it terminates or is truncated. Continuous actions are stepped as
    float32 (the action space's type: what a counterexample file records and replays)."""
    obs, info = env.reset(seed=seed)
    begin = getattr(policy, "begin_episode", None)
    if begin is not None:  # a stateful policy (a recurrent agent's) forgets the previous episode
        begin()
    tally = EpisodeTally(seed, info, committed=shield_mode(env) == "committed")
    continuous = isinstance(env.action_space, gym.spaces.Box)
    done = False
    while not done:
        chosen = policy(obs, info)
        action = np.asarray(chosen, dtype=np.float32) if continuous else int(chosen)
        obs, reward, terminated, truncated, info = env.step(action)
        if tally.judged_before and tally.committed and info.get("collision", False):
            info = {**info, "crash_state": crash_state_trace(env, info)}
        tally.add(action, float(reward), info)
        done = terminated or truncated
    return tally.record(info)


def run_episodes(
    env: gym.Env,
    policy: Policy,
    episodes: int,
    seed: int,
    progress: ProgressCallback | None = None,
) -> list[EpisodeRecord]:
    """Play ``episodes`` episodes, episode ``i`` reset with ``seed + i``; same inputs, same records."""
    if episodes < 1:
        raise ValueError(f"episodes: must be >= 1 (got {episodes})")
    records: list[EpisodeRecord] = []
    for i in range(episodes):
        record = run_episode(env, policy, seed + i)
        records.append(record)
        if progress is not None:
            progress(i, record)
    return records


@runtime_checkable
class BatchPolicy(Protocol):
    """A policy that also acts on many environments at once (a trained agent's greedy policy).

    ``batch(obs (N, 26), infos)`` must give row ``k`` the action ``policy(obs[k], infos[k])`` gives:
    :func:`run_episodes_batched` relies on it to play the same episodes as :func:`run_episodes`.
    """

    def __call__(self, obs: np.ndarray, info: dict[str, Any]) -> int: ...

    def batch(self, obs: np.ndarray, infos: list[dict[str, Any]]) -> np.ndarray: ...


def run_episodes_batched(
    envs: list[gym.Env],
    policy: BatchPolicy,
    episodes: int,
    seed: int,
    progress: ProgressCallback | None = None,
) -> list[EpisodeRecord]:
    """:func:`run_episodes` on ``len(envs)`` environments at once: one ``policy.batch`` call per round of
    decisions. Episode ``i`` is still reset with ``seed + i`` (handed to the next free environment), so
    the records, returned in episode order, equal :func:`run_episodes`'s; ``progress`` is called as
    episodes finish."""
    if episodes < 1:
        raise ValueError(f"episodes: must be >= 1 (got {episodes})")
    records: list[EpisodeRecord | None] = [None] * episodes
    next_episode = 0

    def start(env: gym.Env) -> tuple[int, EpisodeTally, np.ndarray, dict[str, Any]]:
        nonlocal next_episode
        index, next_episode = next_episode, next_episode + 1
        obs, info = env.reset(seed=seed + index)
        return index, EpisodeTally(seed + index, info, committed=shield_mode(env) == "committed"), obs, info

    active = list(envs[:episodes])
    slots = [start(env) for env in active]
    while active:
        actions = policy.batch(np.stack([slot[2] for slot in slots]), [slot[3] for slot in slots])
        keep_envs, keep_slots = [], []
        for env, (index, tally, _, _), action in zip(active, slots, actions, strict=True):
            obs, reward, terminated, truncated, info = env.step(int(action))
            tally.add(int(action), float(reward), info)
            if not (terminated or truncated):
                keep_envs.append(env)
                keep_slots.append((index, tally, obs, info))
                continue
            record = tally.record(info)
            records[index] = record
            if progress is not None:
                progress(index, record)
            if next_episode < episodes:
                keep_envs.append(env)
                keep_slots.append(start(env))
        active, slots = keep_envs, keep_slots
    return [r for r in records if r is not None]


def run_episodes_fast_batch(
    batch: FastBatch,
    policy: BatchPolicy,
    episodes: int,
    seed: int,
    progress: ProgressCallback | None = None,
) -> list[EpisodeRecord]:
    """:func:`run_episodes_batched` on a :class:`safelane.env.fast_batch.FastBatch`: the same records
    (episode ``i`` reset with ``seed + i`` on the next free environment, one ``policy.batch`` call per
    round), the environments stepped in one call. The policy sees each episode's full reset ``info``
    (snapshot and state: a trained policy checks its interface there) and afterwards the step's flags
    and mask, plus the snapshot for a policy with ``needs_snapshot``."""
    if episodes < 1:
        raise ValueError(f"episodes: must be >= 1 (got {episodes})")
    records: list[EpisodeRecord | None] = [None] * episodes
    shielded = batch.shielded
    needs_snapshot = bool(getattr(policy, "needs_snapshot", False))
    slots: dict[int, tuple[int, EpisodeTally]] = {}
    infos: dict[int, dict[str, Any]] = {}
    next_episode = 0

    def start(i: int) -> None:
        nonlocal next_episode
        index, next_episode = next_episode, next_episode + 1
        batch.reset_env(i, seed + index)
        info = batch.reset_info(i)
        slots[i] = (index, EpisodeTally(seed + index, info, committed=batch.committed))
        infos[i] = info

    for i in range(min(batch.num_envs, episodes)):
        start(i)
    while slots:
        rows = np.fromiter(slots, dtype=np.int64, count=len(slots))
        actions = np.asarray(policy.batch(batch.obs[rows], [infos[i] for i in rows.tolist()]), dtype=np.int64)
        out = batch.step(actions, rows)
        done = out.terminated | out.truncated
        for j, i in enumerate(rows.tolist()):
            info: dict[str, Any] = {"speed": float(out.speed[j]), "collision": bool(out.collision[j])}
            if shielded:
                info.update(
                    fallback=bool(out.fallback[j]),
                    shield_intervened=bool(out.shield_intervened[j]),
                    unsafe_action=bool(out.unsafe_action[j]),
                    invariant_break=bool(out.invariant_break[j]),
                    executed_action=int(out.executed[j]),
                    action_mask=batch.masks[i].copy(),
                )
            if batch.committed:
                info.update(batch.committed_info(i))
            if out.collision[j] or done[j] or needs_snapshot:
                info["snapshot"] = batch.snapshot(i)
            index, tally = slots[i]
            tally.add(int(actions[j]), float(out.rewards[j]), info)
            infos[i] = info
            if not done[j]:
                continue
            record = tally.record(info)
            records[index] = record
            if progress is not None:
                progress(index, record)
            del slots[i], infos[i]
            if next_episode < episodes:
                start(i)
    return [r for r in records if r is not None]


def summarize(records: list[EpisodeRecord], **meta: Any) -> dict[str, Any]:
    """Aggregate records into one JSON-ready dict; ``meta`` (policy, shield, preset…) is merged in.

    ``mean_speed`` [m/s] is the mean over episodes of each episode's mean speed;
    ``mean_vehicles_passed`` the mean net overtakes per episode; the intervention, fallback,
    unsafe-choice and invariant-break rates are per decision (``invariant_breaks``: their count, see
    :class:`EpisodeRecord`); ``time_to_collision`` lists one entry per episode (seconds,
    or None without a collision).
    """
    if not records:
        raise ValueError("summarize: no episodes")
    n = len(records)
    decisions = sum(r.length for r in records)
    kinds = dict.fromkeys(COLLISION_KINDS, 0)
    for r in records:
        if r.collision_kind is not None:
            kinds[r.collision_kind] += 1
    actions = [sum(r.actions[a] for r in records) for a in range(N_ACTIONS)]
    collisions = sum(r.collision for r in records)
    contexts = collision_contexts(any(r.uncertified_start is not None for r in records))
    summary: dict[str, Any] = {
        "episodes": n,
        "decisions": decisions,
        "collisions": collisions,
        "collision_rate": collisions / n,
        "mean_speed": float(np.mean([r.mean_speed for r in records])),
        "mean_return": float(np.mean([r.return_ for r in records])),
        "mean_length": decisions / n,
        "time_to_collision": [r.time_to_collision for r in records],
        "shield_intervention_rate": sum(r.interventions for r in records) / max(decisions, 1),
        "fallback_rate": sum(r.fallbacks for r in records) / max(decisions, 1),
        "unsafe_action_rate": sum(r.unsafe_actions for r in records) / max(decisions, 1),
        "invariant_breaks": sum(len(r.invariant_breaks) for r in records),
        "invariant_break_rate": sum(len(r.invariant_breaks) for r in records) / max(decisions, 1),
        "mean_vehicles_passed": float(np.mean([r.vehicles_passed for r in records])),
        "collision_kinds": kinds,
        "collision_contexts": {c: sum(r.collision_context == c for r in records) for c in contexts},
        "actions": dict(zip(ACTION_NAMES, actions, strict=True)),
    }
    continuous = [r for r in records if r.off_road is not None]
    if continuous:  # acceleration and steering: how many episodes ended off the road, no meta-action histogram
        del summary["actions"]
        summary["off_road_rate"] = sum(bool(r.off_road) for r in continuous) / len(continuous)
    summary.update(projection_figures(records))
    summary.update(committed_figures(records))
    believed = [r for r in records if r.type_ruled_out_crash is not None]
    if believed:  # the belief shield: the crashes outside its sets (a true type ruled out), beside the others
        summary["collisions_type_ruled_out"] = sum(bool(r.type_ruled_out_crash) for r in believed)
        # The promise's contexts of the crashes inside the belief's sets (a true type kept), the robust rule's
        # promise over the types kept: a hole of the rule is a "from_safe_state" here.
        summary["collision_contexts_types_kept"] = {
            c: sum(r.collision_context == c and not r.type_ruled_out_crash for r in believed) for c in contexts
        }
    summary.update(meta)
    return summary


CONTINUOUS_FIGURES: tuple[str, ...] = ("off_road_rate", "projection_rate", "mean_projection_distance")
"""The figures a summary adds with continuous actions (``off_road_rate``) and their shield
(:func:`projection_figures`), as stress and falsify records carry them."""


def projection_figures(records: list[EpisodeRecord]) -> dict[str, Any]:
    """The shield for continuous actions' figures of ``records`` (empty without it): ``projection_rate`` (decisions
    whose action it moved ÷ decisions) and ``mean_projection_distance`` (the mean distance [normalised actions] from
    the policy's action to the executed one over those decisions; None when it moved none)."""
    shielded = [r for r in records if r.projection_distance is not None]
    if not shielded:
        return {}
    projected = sum(r.interventions for r in shielded)
    distance = sum(r.projection_distance or 0.0 for r in shielded)
    return {
        "projection_rate": projected / max(sum(r.length for r in shielded), 1),
        "mean_projection_distance": distance / projected if projected else None,
    }


COMMITTED_FIGURES: tuple[str, ...] = (
    "lapses", "lapses_in_model", "plan_forced_rate", "courtesy_waived_rate", "uncertified_starts", "redraws",
)  # fmt: skip
"""The committed mode's figures a summary adds (:func:`committed_figures`), as stress and falsify records carry
them."""


def committed_figures(records: list[EpisodeRecord]) -> dict[str, Any]:
    """The committed shield mode's figures of ``records`` (empty for the other modes, whose summaries keep their
    keys): ``lapses`` and ``lapses_in_model`` (counts), ``plan_forced_rate`` (plan-forced decisions ÷ decisions),
    ``courtesy_waived_rate`` (decisions with no verified action the one-decision rule calls safe ÷ decisions; not
    with continuous actions, whose shield has no such rule), ``uncertified_starts`` (episodes) and ``redraws`` (spawns
    drawn again, ``shield.redraw_uncertified``)."""
    committed = [r for r in records if r.uncertified_start is not None]
    if not committed:
        return {}
    decisions = sum(r.length for r in committed)
    figures = {
        "lapses": sum(len(r.lapses) for r in committed),
        "lapses_in_model": sum(len(r.lapses_in_model) for r in committed),
        "plan_forced_rate": sum(r.plan_forced for r in committed) / max(decisions, 1),
        "courtesy_waived_rate": sum(r.courtesy_waived for r in committed) / max(decisions, 1),
        "uncertified_starts": sum(bool(r.uncertified_start) for r in committed),
        "redraws": sum(r.redraws for r in committed),
    }
    if all(r.projection_distance is not None for r in committed):  # the shield for continuous actions
        del figures["courtesy_waived_rate"]
    return figures


DEFAULT_BATCH_ENVS = 16
"""Environments played at once by :func:`run_config` for a :class:`BatchPolicy` on the fast simulator."""


def run_config(
    config: SafelaneConfig,
    policy: Policy,
    episodes: int,
    seed: int,
    progress: ProgressCallback | None = None,
    num_envs: int | None = None,
) -> list[EpisodeRecord]:
    """Build the environment(s) of ``config``, play the episodes on them, and close them.

    A :class:`BatchPolicy` plays ``num_envs`` environments at once (default: :data:`DEFAULT_BATCH_ENVS`
    on the fast simulator, 1 on highway-env, whose steps cost milliseconds); any other policy, one.
    The records are the same for every ``num_envs``.
    """
    from safelane.env.factory import make_env
    from safelane.env.fast_batch import FastBatch, supports

    if num_envs is None:
        num_envs = DEFAULT_BATCH_ENVS if config.simulator == "fast" else 1
    if num_envs < 1:
        raise ConfigError(f"num_envs: must be >= 1 (got {num_envs})")
    batched = isinstance(policy, BatchPolicy) and num_envs > 1 and episodes > 1
    if batched and supports(config) is None:  # the fast simulator: all environments in one call
        batch = FastBatch(config, min(num_envs, episodes))
        try:
            return run_episodes_fast_batch(batch, policy, episodes, seed, progress)  # type: ignore[arg-type]
        finally:
            batch.close()
    envs = [make_env(config) for _ in range(min(num_envs, episodes) if batched else 1)]
    try:
        if batched:
            return run_episodes_batched(envs, policy, episodes, seed, progress)  # type: ignore[arg-type]
        return run_episodes(envs[0], policy, episodes, seed, progress)
    finally:
        for env in envs:
            env.close()


def evaluate_fixed(
    config: SafelaneConfig,
    policy: str,
    episodes: int,
    seed: int,
    progress: ProgressCallback | None = None,
    counterexamples: str | Path | None = None,
) -> dict[str, Any]:
    """Evaluate a fixed policy (:data:`~safelane.running.policies.FIXED_POLICIES`) on ``config``: the summary dict of
    :func:`summarize` with ``policy``, ``shield``, ``override``, ``preset``, ``env_id``, ``simulator``,
    ``neighbour_search``, ``seed`` and ``wall_time_s`` added. With a shield the config should set
    ``shield.override`` (a fixed policy cannot read the mask). ``counterexamples``: a directory where
    every crash and invariant break is saved as a replayable file (``counterexample_files`` counts them)."""

    if episodes < 1:
        raise ConfigError(f"--episodes: must be >= 1 (got {episodes})")
    if seed < 0:
        raise ConfigError(f"--seed: must be >= 0 (got {seed})")
    act = fixed_policy(policy, seed, config.actions, config.env.get("action"))
    start = time.perf_counter()
    records = run_config(config, act, episodes, seed, progress)
    files: list[Path] = []
    if counterexamples is not None:
        from safelane.running.counterexamples import save_counterexamples

        files = save_counterexamples(records, config, counterexamples, f"evaluate --policy {policy} --seed {seed}")
    return summarize(
        records,
        counterexample_files=[str(f) for f in files],
        policy=policy,
        shield=config.shield.mode,
        override=config.shield.override,
        preset=config.preset,
        env_id=config.env_id,
        simulator=config.simulator,
        neighbour_search=config.neighbour_search,
        seed=seed,
        wall_time_s=time.perf_counter() - start,
    )
