"""The shield for continuous actions: a gymnasium wrapper that executes a verified action at every decision.

``ControlShield(env)`` wraps an environment whose ego takes highway-env's ``ContinuousAction`` (acceleration and
steering in ``[-1, 1]``, safelane's ``safelane/HighwayContinuous-v0`` or ``highway-env``'s own with that action
type) and judges each action with the committed rule for continuous controls
(:mod:`safelane.safety.continuous`): a plan that starts with the action and ends stopped in one lane must keep the
margin to every other car's reachable set.

* ``intervention="projection"`` (default): the agent's action if verified, else the verified action nearest it;
  ``"replacement"``: else the kept plan's next step or the fail-safe's braking action;
* ``info``: ``executed_action``, ``projected`` (the executed action is not the agent's), ``projection_distance``
  (normalised), ``plan_forced``, ``certified``, lapses and the cars they are traced to as the committed shield
  names them, and ``uncertified_start`` after a reset;
* ``adaptation_penalty``: the reward loses this weight × ``projection_distance`` (``info["adaptation_penalty"]``);
* :meth:`ControlShield.safe_acceleration_interval` and :meth:`ControlShield.verified_steerings`: the safe set, for
  an agent that squashes its own output into it.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import gymnasium as gym
import numpy as np

from safelane.core.snapshot import RoadSnapshot
from safelane.safety.continuous.controls import ControlLimits
from safelane.safety.continuous.family import (
    INTERVENTIONS,
    ControlFamily,
    ControlResult,
    Intervention,
    lane_keeping_action,
)
from safelane.safety.continuous.search import STEERING_GRID
from safelane.safety.road import whole_road_state
from safelane.safety.rule import DEFAULT_RULE_NAME, Rule
from safelane.safety.shield import DEFAULT_MARGIN, dynamics_of
from safelane.safety.world import BASE_DECISION_PERIOD, Dynamics, Engine
from safelane.sim.fast.continuous import resolve_continuous
from safelane.sim.highway import HighwayEnvAdapter


def control_limits(action_config: dict[str, Any]) -> ControlLimits:
    """The :class:`ControlLimits` of a highway-env ``ContinuousAction`` config (its ranges as configured, read with
    highway-env's defaults); an action type or option the shield cannot judge is a one-line error."""
    if action_config.get("type") != "ContinuousAction":
        raise ValueError(
            f"env.action.type: {action_config.get('type')!r} is not judged by the shield for continuous actions; "
            "allowed: 'ContinuousAction'"
        )
    spec = resolve_continuous(action_config)
    if not (spec.longitudinal and spec.lateral):
        raise ValueError("env.action.longitudinal, env.action.lateral: the shield needs both; allowed: true, true")
    low, high = spec.speed_bounds
    return ControlLimits(spec.acceleration_range, spec.steering_range, low, high)


def control_dynamics(snap: RoadSnapshot, limits: ControlLimits, margin: float = DEFAULT_MARGIN,
                     rule: Rule | str = DEFAULT_RULE_NAME) -> Dynamics:  # fmt: skip
    """The world's constants read from ``snap`` (:func:`~safelane.safety.shield.dynamics_of`), the horizon long
    enough for an ego under ``limits`` to stop from its top speed at its hardest braking: the braking decisions
    counted at :data:`~safelane.safety.world.BASE_DECISION_PERIOD`, as the horizon's other decisions are, when the
    rule's ``full_horizon`` spans as many seconds at a faster rate; else at the decision period."""
    dyn = dynamics_of(snap, margin, rule)
    braking = limits.braking_decisions(BASE_DECISION_PERIOD if dyn.rule.full_horizon else dyn.decision_period)
    return dataclasses.replace(dyn, target_speeds=(), braking_decisions=braking)


class ControlShield(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """The shield for continuous actions (module docstring). ``margin`` [m], ``rule`` and ``engine`` as for
    :class:`~safelane.safety.shield.SafetyShield` (the rule's options shape the other cars' sets; ``"compiled"``:
    :mod:`safelane.safety.continuous.compiled`, the numpy reference's bits)."""

    def __init__(
        self,
        env: gym.Env,
        intervention: Intervention = "projection",
        margin: float = DEFAULT_MARGIN,
        rule: Rule | str = DEFAULT_RULE_NAME,
        adaptation_penalty: float = 0.0,
        engine: Engine = "compiled",
    ) -> None:
        if intervention not in INTERVENTIONS:
            raise ValueError(f"shield.intervention: got {intervention!r}; allowed: 'projection', 'replacement'")
        if not (isinstance(margin, int | float) and math.isfinite(margin) and margin >= 0):
            raise ValueError(f"shield.margin: must be a finite number >= 0 [m] (got {margin!r})")
        if not (isinstance(adaptation_penalty, int | float) and math.isfinite(adaptation_penalty)
                and adaptation_penalty >= 0):  # fmt: skip
            raise ValueError(f"shield.adaptation_penalty: must be a finite number >= 0 (got {adaptation_penalty!r})")
        gym.utils.RecordConstructorArgs.__init__(
            self, intervention=intervention, margin=margin, rule=rule, adaptation_penalty=adaptation_penalty,
            engine=engine,
        )
        try:
            env.get_wrapper_attr("road_snapshot")
        except AttributeError:  # a plain highway-env environment: read its scene through the adapter
            env = HighwayEnvAdapter(env)
        super().__init__(env)
        self.limits = control_limits(dict(env.unwrapped.config["action"]))
        self.family = ControlFamily(self.limits, intervention, engine)
        self.margin = float(margin)
        self.rule = rule
        self.adaptation_penalty = float(adaptation_penalty)
        self.dynamics: Dynamics | None = None
        self.snapshot: RoadSnapshot | None = None
        self.result: ControlResult | None = None

    def _dynamics(self, snap: RoadSnapshot) -> Dynamics:
        """The world's constants read from the episode's first snapshot, the horizon long enough to stop from
        the top speed at the hardest braking."""
        if self.dynamics is None:
            self.dynamics = control_dynamics(snap, self.limits, self.margin, self.rule)
        return self.dynamics

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        self.dynamics, self.result = None, None
        self.family.reset()
        obs, info = self.env.reset(**kwargs)
        self.snapshot = info["snapshot"]
        certified = self.family.certified(self.snapshot, self._dynamics(self.snapshot))
        info.update(certified=certified, uncertified_start=not certified, projected=False, projection_distance=0.0,
                    shield_intervened=False)  # fmt: skip
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        if self.snapshot is None:
            raise RuntimeError("ControlShield: reset the environment first")
        if np.shape(action) != (2,):
            raise ValueError(f"action {action!r} not in Box(-1, 1, (2,)): 2 numbers expected")
        self.result = self.family.judge(self.snapshot, self._dynamics(self.snapshot), np.asarray(action))
        self.family.commit()
        obs, reward, terminated, truncated, info = self.env.step(self.result.executed.copy())
        info.update(self.result.info())
        info["unsafe_action"] = self.result.projected
        penalty = self.adaptation_penalty * self.result.projection_distance
        info["adaptation_penalty"] = penalty
        self.snapshot = info["snapshot"]
        return obs, float(reward) - penalty, terminated, truncated, info

    def _lane_keeping_steering(self) -> float:
        """The fail-safe's steering now [normalised] (brake, steer for the nearest lane)."""
        assert self.snapshot is not None
        state, _ = whole_road_state(self.snapshot, True)
        return float(lane_keeping_action(state, self._dynamics(self.snapshot), self.limits)[1])

    def _intervals(self, *steerings: float) -> list[tuple[float, float]]:
        """(low, high) the verified accelerations at each of ``steerings`` in the current state."""
        assert self.snapshot is not None
        dyn = self._dynamics(self.snapshot)
        state, _, sets, trace = self.family.state_of(self.snapshot, dyn)
        search = self.family.search(state, dyn, sets, trace["cars"])
        return [search.interval(float(np.float32(s)))[:2] for s in steerings]

    def safe_acceleration_interval(self, steering: float) -> tuple[float, float]:
        """(low, high) [normalised] the verified accelerations in the current state at ``steering`` [normalised]
        (nan, nan: none), for an agent that squashes its acceleration into them."""
        if self.snapshot is None:
            raise RuntimeError("ControlShield: reset the environment first")
        return self._intervals(steering)[0]

    def verified_steerings(self) -> list[tuple[float, float, float]]:
        """(steering, low, high) [normalised] for each steering the projection examines (the lane-keeping one and
        :data:`~safelane.safety.continuous.search.STEERING_GRID`) with some verified acceleration."""
        if self.snapshot is None:
            raise RuntimeError("ControlShield: reset the environment first")
        steerings = sorted({float(np.float32(self._lane_keeping_steering())), *map(float, STEERING_GRID)})
        return [(s, lo, hi) for s, (lo, hi) in zip(steerings, self._intervals(*steerings), strict=True)
                if not math.isnan(lo)]  # fmt: skip
