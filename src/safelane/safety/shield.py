"""The safety shield: a gymnasium wrapper that exposes the safety model's mask to any agent.

``SafetyShield(env, mode="robust")`` reads the road snapshot (``info["snapshot"]``, a
:class:`safelane.core.snapshot.RoadSnapshot`) after every reset and step, turns it into a
:class:`safelane.safety.one_decision.reference.RoadState` (SI units, lane coordinates) and asks
:func:`safelane.safety.one_decision.reference.evaluate` which of the 5 meta-actions are safe:

* ``action_masks()`` returns the mask (sb3-contrib's convention, so ``MaskablePPO`` uses it as is);
* ``info["action_mask"]``, ``info["fallback"]`` (no action was safe, the least-bad one is allowed)
  and ``info["shield_intervened"]`` (the override replaced the chosen action) are added;
* with ``override=True`` an unsafe action is replaced by the closest safe one
  (:data:`safelane.safety.one_decision.reference.OVERRIDE_ORDER`), so any agent — SB3's DQN, a random policy, a human —
  drives safely.

Every constant of the dynamics comes from the snapshot, which the simulator fills from its own
classes (``KP_A``, ``ACC_MAX``, ``COMFORT_ACC_MAX``, IDM/MOBIL parameters, lane width, frequencies,
target speeds); lane-change timings come from simulating highway-env's own lateral controller
(:func:`safelane.sim.highway.lane_change_timing`).

To shield a plain highway-env environment (``gym.make("highway-v0")``), wrap it in
:class:`safelane.sim.highway.HighwayEnvAdapter` first; :class:`SafetyShield` does so itself when the
environment below it provides no snapshot.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Any, Literal

import gymnasium as gym
import numpy as np

from safelane.core.drivers import IDM_PARAMETERS, DriverMix, IdmParameters, idm_parameters, least_min_acc_gain
from safelane.core.snapshot import RoadSnapshot
from safelane.safety.belief import DEFAULT_BELIEF_EPSILON, BeliefFilter, DriverTypes
from safelane.safety.driver_sets import TYPE_MODES, drawn_cars, every_type, true_type, type_readings
from safelane.safety.family import RuleFamily, family_for
from safelane.safety.one_decision.over_types import evaluate_readings
from safelane.safety.road import road_state, road_state_bodies
from safelane.safety.rule import DEFAULT_RULE_NAME, Rule, as_rule
from safelane.safety.world import (
    ENGINES,
    OVERRIDE_ORDER,
    SHIELD_MODES,
    Dynamics,
    Engine,
    Formula,
    Mode,
    RoadState,
    SafetyResult,
    check_choices,
)
from safelane.sim.highway import HighwayEnvAdapter, lane_change_timing

DEFAULT_MARGIN = Dynamics.__dataclass_fields__["margin"].default
"""[m] The safety model's default bumper-to-bumper margin (``shield.margin``)."""
__all__ = [
    "ENGINES", "CannotStopWarning", "Engine", "SafetyShield", "dynamics_of", "ego_leave_time_at", "ego_leave_time_of",
    "ego_leave_times", "road_state", "road_state_bodies", "stoppable_action_config",
]  # fmt: skip


class CannotStopWarning(UserWarning):
    """The ego's lowest speed set-point is above 0 m/s: the rule's fallback (SLOWER to a standstill) does
    not exist, so in traffic most states have no safe action and the shield can promise nothing."""


def stoppable_action_config(top_speed: float = 30.0, step: float = 5.0) -> dict[str, Any]:
    """highway-env's ``action`` config with speed set-points ``0, step, …, top_speed`` [m/s]: the ego can
    brake to a standstill, which the safety rule's fallback needs. highway-env's default set-points
    ``[20, 25, 30]`` cannot go below 20 m/s (:class:`CannotStopWarning`).

        env = SafetyShield(gym.make("highway-fast-v0", config={"action": stoppable_action_config()}))
    """
    if not (step > 0 and top_speed >= step and math.isfinite(top_speed)):
        raise ValueError(f"stoppable_action_config: need 0 < step <= top_speed [m/s], got {step!r}, {top_speed!r}")
    count = round(top_speed / step) + 1
    return {"type": "DiscreteMetaAction", "target_speeds": [round(k * step, 9) for k in range(count)]}


def dynamics_of(snap: RoadSnapshot, margin: float = DEFAULT_MARGIN, rule: Rule | str = DEFAULT_RULE_NAME) -> Dynamics:
    """The :class:`Dynamics` constants of the simulated world a snapshot was taken in; ``margin`` [m]: the
    bumper-to-bumper gap the rule keeps under its worst case; ``rule``: a :class:`Rule` or the name of one
    (:data:`safelane.safety.rule.RULES`)."""
    sim_f, pol_f = snap.simulation_frequency, snap.policy_frequency
    # Fastest cut-in over plausible speeds; slowest ego exit (at low speed the lateral motion is slower).
    enter = min(lane_change_timing(sim_f, s)[1] for s in (15.0, 25.0, 35.0))
    return Dynamics(
        decision_period=1.0 / pol_f,
        frame_dt=1.0 / sim_f,
        frames_per_decision=int(sim_f // pol_f),
        ego_kp=snap.ego_kp,
        target_speeds=snap.ego_target_speeds,
        lane_width=snap.lane_width,
        lanes_count=snap.lanes_count,
        cut_in_time=max(enter - 1.0 / sim_f, 0.0),
        margin=margin,
        rule=as_rule(rule),
        # The widest other body (every highway-env vehicle has Vehicle.WIDTH): the occupancy bound.
        body_width=float(np.max(snap.width)) if len(snap.width) else 2.0,
    )


def with_mixture(dyn: Dynamics, mix: DriverMix | None) -> Dynamics:
    """``dyn`` for traffic drawn from the driver mixture ``mix`` (None: ``dyn``): MOBIL's incentive threshold the
    least of its types' (:func:`~safelane.core.drivers.least_min_acc_gain`), which the snapshot does not carry."""
    gain = least_min_acc_gain(mix, dyn.mobil_min_gain)
    return dyn if gain == dyn.mobil_min_gain else dataclasses.replace(dyn, mobil_min_gain=gain)


FALLBACK_SLOWDOWN = 4.5
"""[m/s] What a fallback SLOWER removes from the ego's speed within the next second (the leave time is
taken at the ego's speed or set-point minus this)."""
LEAVE_TIME_MAX_SPEED = 40.0
"""[m/s] The leave time is looked up at speeds rounded down to 0.5 m/s in [0, this]."""


def ego_leave_time_at(dyn: Dynamics, speed: float) -> float:
    """[s] The time the ego takes to leave its lane when changing lane at ``speed`` [m/s] (a multiple of
    0.5 in [0, 40]), plus one frame, because the change starts at the next physics frame."""
    return lane_change_timing(1.0 / dyn.frame_dt, speed)[0] + dyn.frame_dt


def ego_leave_times(dyn: Dynamics) -> np.ndarray:
    """[s] :func:`ego_leave_time_at` for the speeds 0, 0.5, …, 40 m/s (entry ``k``: speed ``k / 2``), the
    table a batched kernel looks the leave time up in, exactly as :class:`SafetyShield` computes it."""
    count = int(LEAVE_TIME_MAX_SPEED * 2) + 1
    return np.array([ego_leave_time_at(dyn, k / 2) for k in range(count)])


def ego_leave_time_of(snap: RoadSnapshot, dyn: Dynamics) -> float:
    """[s] The time the ego takes to leave its lane in the state of ``snap`` (what the shield gives the rule)."""
    # The ego's speed along the road, as road_state computes it (the compiled path builds no RoadState).
    e = snap.ego
    ego_speed = float(snap.speed[e] * math.cos(float(snap.heading[e]) - snap.lane_heading))
    # The ego leaves its old lane more slowly at low speed (the steering turns the car in
    # proportion to its speed; at a standstill it never leaves). Time it at the lowest speed
    # the ego may have while still changing lane — its speed or set-point, minus what a
    # fallback SLOWER removes in the next second (4.5 m/s) — rounded down to 0.5 m/s so the
    # simulation is cached, plus one frame because the change starts at the next physics frame.
    slowest = min(ego_speed, snap.ego_target_speed) - FALLBACK_SLOWDOWN
    if math.isfinite(slowest):  # the numpy expression below with Python scalars (≈3 µs less, same value)
        speed = min(max(math.floor(slowest * 2) / 2, 0.0), LEAVE_TIME_MAX_SPEED)
    else:
        speed = float(np.clip(np.floor(slowest * 2) / 2, 0.0, LEAVE_TIME_MAX_SPEED))
    return ego_leave_time_at(dyn, speed)


class SafetyShield(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Gymnasium wrapper exposing the safety model's action mask (and optionally enforcing it).

    ``mode``: ``"nominal"`` (the paper's Q-masking) or ``"robust"`` (robust Q-masking).
    ``override``: replace an unsafe chosen action by the closest safe one.
    ``margin`` [m]: the bumper-to-bumper gap kept under the worst case (the rule's safety threshold).
    ``rule``: the rule's options, a :class:`~safelane.safety.rule.Rule` or the name of one in
    :data:`safelane.safety.rule.RULES` (default ``"forecast-fallback"``; ``Rule.with_options`` switches single
    options, each declared with its meaning in :data:`safelane.safety.rule.OPTIONS`).
    ``engine``: ``"compiled"`` (:mod:`safelane.safety.one_decision.compiled`, microseconds) or ``"numpy"`` (the
    reference :func:`safelane.safety.one_decision.reference.evaluate`, about a millisecond); the same masks either way.
    ``formula``: ``"kinematic"`` (derived for highway-env, docs/safety.md) or ``"paper"`` (eq. 12, nominal).
    ``mode="committed"`` (experimental, :mod:`safelane.safety.committed`; its ``engine`` ``"compiled"``,
    :mod:`safelane.safety.committed.compiled`, gives the numpy reference's bits): a plan verified against the
    others' reachable sets is kept between decisions; ``info`` gains ``plan_forced``, ``lapse``, ``lapse_in_model``,
    ``lapse_cars`` (the cars the lapse's kept plan fails on), ``lapse_escaped_cars`` (those of them outside their
    sets), ``escaped_cars`` (every car outside its set), ``rolled_back``, ``unbraked_followers``, ``entered_cars``,
    ``certified``, ``courtesy_waived`` (no verified action was safe by the one-decision robust rule, so every verified
    one was allowed) (and ``uncertified_start`` after a reset); cars by their snapshot index.
    ``mode`` may also be a :class:`~safelane.safety.family.RuleFamily` of the caller's (its memory the caller's
    to read; its ``engine`` then overrides ``engine``).

    ``driver_types``: the traffic's mixture of driver types and the belief's settings
    (:class:`~safelane.safety.belief.DriverTypes`; the mixture's ``assumed`` None when the snapshot shows each
    car's own constants). With the types hidden, ``mode="robust"`` judges each action against
    every type of the mixture for every drawn car, mixed assignments included: one reading of the scene per type
    (:func:`~safelane.safety.driver_sets.type_readings`), their worst gaps combined before the fallback is chosen
    (:func:`~safelane.safety.one_decision.over_types.evaluate_readings`, with the ``engine``'s gaps; a mixture with a
    linear-model driver keeps the snapshot's assumed constants). ``mode="omniscient"``:
    the robust rule on each car's true type (the snapshot's ``driver_type``; one reading, the ``engine``'s);
    ``mode="belief"``: on the types whose posterior (:class:`~safelane.safety.belief.BeliefFilter`, residual deviation
    ``sigma`` [m/s²]) exceeds ``epsilon``, the same way. The belief's promise is probabilistic: a car
    whose true type was ruled out is outside the sets, and ``info`` counts it: ``types_ruled_out`` (the drawn cars
    whose true type is at or below ε at this decision) and ``type_ruled_out_crash`` (the ego crashed in this step
    with a car whose true type was ruled out at the decision).
    """

    def __init__(
        self,
        env: gym.Env,
        mode: Mode | Literal["committed"] | RuleFamily = "robust",
        override: bool = False,
        margin: float = DEFAULT_MARGIN,
        rule: Rule | str = DEFAULT_RULE_NAME,
        engine: Engine = "compiled",
        formula: Formula = "kinematic",
        driver_types: DriverTypes | None = None,
    ) -> None:
        if not (isinstance(margin, int | float) and math.isfinite(margin) and margin >= 0):
            raise ValueError(f"shield.margin: must be a finite number >= 0 [m] (got {margin!r})")
        driver_mix = driver_types.mix if driver_types is not None else None
        family: RuleFamily | None = None
        if isinstance(mode, RuleFamily):  # a family of the caller's (the committed mode's memory, say)
            family, mode, engine = mode, mode.mode, mode.engine  # type: ignore[assignment]
        check_choices(mode, engine, formula, modes=(*SHIELD_MODES, *TYPE_MODES))
        if mode in TYPE_MODES and driver_mix is None:
            raise ValueError(
                f"shield.mode: {mode!r} reads the types of a driver mixture and needs traffic.driver_mix; allowed "
                f"without one: {', '.join(SHIELD_MODES)}"
            )
        resolved = as_rule(rule)
        gym.utils.RecordConstructorArgs.__init__(
            self, mode=family or mode, override=override, margin=margin, rule=rule, engine=engine, formula=formula,
            driver_types=driver_types,
        )  # fmt: skip
        try:
            env.get_wrapper_attr("road_snapshot")
        except AttributeError:  # a plain highway-env environment: read its scene through the adapter
            env = HighwayEnvAdapter(env)
        super().__init__(env)
        self.mode: Mode = mode  # type: ignore[assignment]
        self.formula: Formula = formula
        self.override = override
        self.engine: Engine = engine
        self.margin = float(margin)
        self.rule: Rule = resolved
        self._family: tuple[tuple[str, str, str], RuleFamily] | None = None
        if family is not None:
            self._family = ((self.mode, self.engine, self.formula), family)
        self.dynamics: Dynamics | None = None
        self.result: SafetyResult | None = None
        self.snapshot: RoadSnapshot | None = None
        self._warned_cannot_stop = False
        # The driver types the rule reads each car as (None: the snapshot's constants as they are).
        self.driver_mix = driver_mix
        self.belief_epsilon = float(driver_types.epsilon) if driver_types is not None else DEFAULT_BELIEF_EPSILON
        self.types: tuple[IdmParameters, ...] | None = None
        hidden_idm = (
            driver_mix is not None and driver_mix.assumed is not None
            and all(t in IDM_PARAMETERS for t in driver_mix.types)
        )  # fmt: skip
        if mode in TYPE_MODES or (mode == "robust" and hidden_idm):
            assert driver_mix is not None
            self.types = idm_parameters(driver_mix)
        self.belief: BeliefFilter | None = None
        if mode == "belief":
            assert driver_mix is not None
            assert driver_types is not None
            self.belief = BeliefFilter(driver_mix, driver_types.sigma)
        self._ruled_out = np.zeros(0, dtype=bool)  # drawn cars whose true type the last decision ruled out

    def driver_view(self, snap: RoadSnapshot) -> RoadSnapshot:
        """The snapshot the rule reads when it reads one: ``snap`` itself when the rule reads the constants as they
        are; under the types' sets, each drawn car as its most likely allowed type (the fallback's forecast reads it;
        the omniscient shield's only reading)."""
        return self.driver_readings(snap)[1]

    def driver_readings(self, snap: RoadSnapshot) -> tuple[list[RoadSnapshot], RoadSnapshot]:
        """The readings of ``snap`` the rule judges at once (one per type some car may be among others: the mode's
        sets, class docstring) and the most likely one; ``([snap], snap)`` when the rule reads the constants as
        they are."""
        if self.types is None or self.driver_mix is None:
            return [snap], snap
        if self.mode == "omniscient":
            allowed, cars = true_type(snap, len(self.types))
            weight = allowed.astype(float)
        else:
            allowed, cars = self.allowed_types(snap), drawn_cars(snap)
            weight = np.broadcast_to(self.driver_mix.probabilities, allowed.shape)
            if self.belief is not None:  # the posterior's most likely type (the prior's for a car it has no row for)
                weight = np.array(weight, copy=True)
                rows = min(snap.n, self.belief.log_post.shape[0])
                weight[:rows] = self.belief.log_post[:rows]
        return type_readings(snap, self.types, allowed, cars, weight)

    def allowed_types(self, snap: RoadSnapshot) -> np.ndarray:
        """(n, K) bool: the types each car of ``snap`` may be — the belief's above ε (a car it has no row for: the
        prior's), else every type of positive weight."""
        assert self.driver_mix is not None
        allowed = every_type(snap, self.driver_mix.probabilities)
        if self.belief is not None:
            allowed &= self.driver_mix.probabilities[None, :] > self.belief_epsilon  # the prior's, for new rows
            rows = min(snap.n, self.belief.log_post.shape[0])
            allowed[:rows] = self.belief.allowed(self.belief_epsilon)[:rows]
        return allowed

    def _true_type_ruled_out(self, snap: RoadSnapshot) -> np.ndarray:
        """(n,) bool: the drawn cars of ``snap`` whose true type the belief's sets leave out."""
        truth = snap.driver_type if snap.driver_type is not None else np.full(snap.n, -1)
        out = np.zeros(snap.n, dtype=bool)
        cars = np.flatnonzero(truth >= 0)
        out[cars] = ~self.allowed_types(snap)[cars, truth[cars]]
        return out

    @property
    def family(self) -> RuleFamily:
        """The rule family that judges the states (:mod:`safelane.safety.family`), for the shield's ``mode``,
        ``engine`` and ``formula`` as they are now (the types' modes: the robust rule's)."""
        key = ("robust" if self.mode in TYPE_MODES else self.mode, self.engine, self.formula)
        if self._family is None or self._family[0] != key:  # one family per shield: it keeps the episode's memory
            self._family = (key, family_for(*key))
        return self._family[1]

    def compute_result(self, snap: RoadSnapshot | None = None) -> SafetyResult:
        """Evaluate the safety model on ``snap`` (default: the last snapshot seen; no caching)."""
        snap = self.snapshot if snap is None else snap
        if snap is None:
            raise RuntimeError("SafetyShield: reset the environment first")
        leave = self._ego_leave_time(snap)
        assert self.dynamics is not None
        readings, likely = self.driver_readings(snap)
        if len(readings) == 1:
            return self.family.evaluate(readings[0], self.dynamics, leave)
        dyn = dataclasses.replace(self.dynamics, ego_leave_time=leave)
        speed = dyn.rule.ego_speed_magnitude
        states = [road_state(reading, speed) for reading in readings]
        return evaluate_readings(states, road_state(likely, speed), dyn, self.engine)

    def state_and_dynamics(self, snap: RoadSnapshot) -> tuple[RoadState, Dynamics]:
        """The (RoadState, Dynamics) that :meth:`compute_result` evaluates for ``snap`` (the numpy engine's
        inputs; the compiled engine builds the same state inside its kernel; under the types' sets with several
        readings, the most likely one's)."""
        leave = self._ego_leave_time(snap)
        assert self.dynamics is not None
        dyn = self.dynamics
        state = road_state(self.driver_view(snap), dyn.rule.ego_speed_magnitude)
        return state, dataclasses.replace(dyn, ego_leave_time=leave)

    def ego_leave_time(self, snap: RoadSnapshot) -> float:
        """[s] The time the ego takes to leave its lane in the state of ``snap``: what :meth:`compute_result` gives
        the family (with it, and :attr:`dynamics`, a caller can judge ``snap`` with a family of its own)."""
        return self._ego_leave_time(snap)

    def _ego_leave_time(self, snap: RoadSnapshot) -> float:
        """The time [s] the ego takes to leave its lane in the state of ``snap``."""
        if self.dynamics is None:
            self.dynamics = with_mixture(dynamics_of(snap, self.margin, self.rule), self.driver_mix)
        return ego_leave_time_of(snap, self.dynamics)

    def refresh(self) -> SafetyResult:
        """Re-read the scene from the simulator and recompute the verdict (after editing the road by hand)."""
        self.dynamics = None
        self.snapshot = self.env.get_wrapper_attr("road_snapshot")(refresh=True)
        self.result = self.compute_result()
        return self.result

    def compute_mask(self) -> np.ndarray:
        """The mask of safe actions, recomputed on the last snapshot (bool, shape (5,)); after editing the
        scene by hand call :meth:`refresh`, which re-reads it."""
        return self.compute_result().mask

    def action_masks(self) -> np.ndarray:
        """The mask of the current state (sb3-contrib convention): bool array of shape (5,)."""
        if self.result is None:
            self.result = self.compute_result()
        return self.result.mask.copy()

    def _annotate(self, info: dict[str, Any]) -> None:
        self.snapshot = info["snapshot"]
        self.result = self.compute_result()
        info.update(self.result.info())
        if self.belief is not None:
            self._ruled_out = self._true_type_ruled_out(self.snapshot)
            info["types_ruled_out"] = int(np.count_nonzero(self._ruled_out))

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        self.dynamics = None
        self.result = None
        self.family.reset()  # a family with memory (committed plans) starts each episode afresh
        obs, info = self.env.reset(**kwargs)
        if self.belief is not None:
            self.belief.reset(info["snapshot"])
        self._annotate(info)
        if self.belief is not None:
            info["type_ruled_out_crash"] = False
        if self.mode == "committed":
            info["uncertified_start"] = not info["certified"]
        info["shield_intervened"] = False
        self._warn_if_the_ego_cannot_stop()
        return obs, info

    def _crash_with_ruled_out(self, before: RoadSnapshot, after: RoadSnapshot) -> bool:
        """Whether the ego crashed in the step from ``before`` to ``after`` together with a car (crashed in the same
        step) whose true type the decision's sets had ruled out."""
        ego = after.ego
        if not after.crashed[ego] or before.crashed[ego]:
            return False
        rows = min(before.n, after.n, self._ruled_out.shape[0])
        partners = after.crashed[:rows] & ~before.crashed[:rows]
        partners[ego] = False
        return bool((partners & self._ruled_out[:rows]).any())

    def _warn_if_the_ego_cannot_stop(self) -> None:
        """One warning per shield when the lowest set-point is above 0 m/s (highway-env's default [20, 25, 30]):
        measured, a random policy under the robust shield then crashes in 14 of 30 dense episodes, every
        one from states with no safe action (docs/guides/shield.md); with set-points from 0 m/s, in none."""
        assert self.dynamics is not None
        lowest = self.dynamics.target_speeds[0]
        if lowest > 0 and not self._warned_cannot_stop:
            self._warned_cannot_stop = True
            warnings.warn(
                f"SafetyShield: env.action.target_speeds starts at {lowest:g} m/s, so the ego cannot stop and "
                "the rule's fallback does not exist (most states in traffic get no safe action); give the "
                "environment config={'action': safelane.stoppable_action_config()} (set-points 0, 5, ..., 30 m/s)",
                CannotStopWarning,
                stacklevel=3,
            )

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        chosen = int(action)
        mask = self.action_masks()
        # The rule's promise: after an allowed action in a state with a safe action, the next state has
        # one again (while the others stay inside the model). A fallback state reached right after one
        # is a counterexample, found hundreds of times more often than the crash it may lead to.
        promised = self.result is not None and not self.result.fallback
        executed = chosen
        if self.override and not mask[chosen]:
            executed = next(a for a in OVERRIDE_ORDER[chosen] if mask[a])
        self.family.commit(executed)  # a family with memory keeps the plan of the action executed
        before = self.snapshot
        obs, reward, terminated, truncated, info = self.env.step(executed)
        info["shield_intervened"] = executed != chosen
        info["unsafe_action"] = not bool(mask[chosen])
        info["executed_action"] = executed
        if self.belief is not None:
            assert before is not None
            info["type_ruled_out_crash"] = self._crash_with_ruled_out(before, info["snapshot"])
            self.belief.update(info["snapshot"])
        self._annotate(info)
        info["invariant_break"] = bool(promised and mask[executed] and info["fallback"])
        return obs, reward, terminated, truncated, info
