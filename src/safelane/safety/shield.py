"""The safety shield: a gymnasium wrapper that exposes the safety model's mask to any agent.

``SafetyShield(env, mode="robust")`` reads the road snapshot (``info["snapshot"]``, a
:class:`safelane.core.snapshot.RoadSnapshot`) after every reset and step, turns it into a
:class:`safelane.safety.model.RoadState` (SI units, lane coordinates) and asks
:func:`safelane.safety.model.evaluate` which of the 5 meta-actions are safe:

* ``action_masks()`` returns the mask (sb3-contrib's convention, so ``MaskablePPO`` uses it as is);
* ``info["action_mask"]``, ``info["fallback"]`` (no action was safe, the least-bad one is allowed)
  and ``info["shield_intervened"]`` (the override replaced the chosen action) are added;
* with ``override=True`` an unsafe action is replaced by the closest safe one
  (:data:`safelane.safety.model.OVERRIDE_ORDER`), so any agent — SB3's DQN, a random policy, a human —
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
from highway_env.vehicle.controller import ControlledVehicle

from safelane.config import RULE_OPTIONS
from safelane.core.snapshot import DRIVER_FIELDS, RoadSnapshot
from safelane.safety.compiled import axis_aligned, evaluate_compiled, evaluate_snapshot
from safelane.safety.model import (
    OVERRIDE_ORDER,
    RELEVANCE_RANGE,
    Dynamics,
    Formula,
    Mode,
    RoadState,
    SafetyResult,
    evaluate,
)
from safelane.sim.highway import HighwayEnvAdapter, lane_change_timing

DEFAULT_MARGIN = Dynamics.__dataclass_fields__["margin"].default
"""[m] The safety model's default bumper-to-bumper margin (``shield.margin``)."""
Engine = Literal["compiled", "numpy"]
ENGINES: tuple[Engine, ...] = ("compiled", "numpy")


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


def dynamics_of(
    snap: RoadSnapshot,
    margin: float = DEFAULT_MARGIN,
    projected_cut_ins: bool = False,
    body_extent: bool = True,
    linear_mobil: bool = True,
    reversing_leaders: bool = True,
    level_cut_ins: bool = True,
    level_incentive: bool = True,
    level_entering: bool = True,
    least_bad_joint: bool = False,
    full_horizon: bool = True,
    ego_speed_magnitude: bool = True,
    turning_leaders: bool = True,
    robust_fallback: bool = False,
    straight_fallback: bool = True,
    linear_incentive: bool = True,
    linear_incentive_braking: bool = True,
    reversing_cut_ins: bool = True,
    crossed_lanes: bool = True,
    lateral_schedule: bool = False,
    reversing_noses: bool = True,
    follower_idm: bool = True,
    follower_set_point: bool = False,
    finishing_changes: bool = True,
    cut_in_when_permitted: bool = True,
    leaving_lanes_seen: bool = False,
    permit_any_speed: bool = True,
    passing_cut_ins: bool = True,
    level_when_incentive: bool = True,
    incentive_any_speed: bool = True,
    turning_in_nominal: bool = True,
    forecast_fallback: bool = True,
    forecast_contact_time: bool = False,
    forecast_lane_changes: bool = False,
) -> Dynamics:
    """The :class:`Dynamics` constants of the simulated world a snapshot was taken in; ``margin`` [m]: the
    bumper-to-bumper gap the rule keeps under its worst case; the rule's options as in :class:`Dynamics`."""
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
        projected_cut_ins=projected_cut_ins,
        body_extent=body_extent,
        linear_mobil=linear_mobil,
        reversing_leaders=reversing_leaders,
        level_cut_ins=level_cut_ins,
        level_incentive=level_incentive,
        level_entering=level_entering,
        least_bad_joint=least_bad_joint,
        full_horizon=full_horizon,
        ego_speed_magnitude=ego_speed_magnitude,
        turning_leaders=turning_leaders,
        robust_fallback=robust_fallback,
        straight_fallback=straight_fallback,
        linear_incentive=linear_incentive,
        linear_incentive_braking=linear_incentive_braking,
        reversing_cut_ins=reversing_cut_ins,
        crossed_lanes=crossed_lanes,
        lateral_schedule=lateral_schedule,
        reversing_noses=reversing_noses,
        follower_idm=follower_idm,
        follower_set_point=follower_set_point,
        finishing_changes=finishing_changes,
        cut_in_when_permitted=cut_in_when_permitted,
        leaving_lanes_seen=leaving_lanes_seen,
        permit_any_speed=permit_any_speed,
        passing_cut_ins=passing_cut_ins,
        level_when_incentive=level_when_incentive,
        incentive_any_speed=incentive_any_speed,
        turning_in_nominal=turning_in_nominal,
        forecast_fallback=forecast_fallback,
        forecast_contact_time=forecast_contact_time,
        forecast_lane_changes=forecast_lane_changes,
        # highway-env's lateral controller: ControlledVehicle's gains, which MDPVehicle (the ego) inherits.
        ego_width=float(snap.width[snap.ego]) if len(snap.width) else 2.0,
        kp_lateral=float(ControlledVehicle.KP_LATERAL),
        kp_heading=float(ControlledVehicle.KP_HEADING),
        max_steering=float(ControlledVehicle.MAX_STEERING_ANGLE),
        # The widest other body (every highway-env vehicle has Vehicle.WIDTH): the occupancy bound.
        body_width=float(np.max(snap.width)) if len(snap.width) else 2.0,
    )


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


def _relevant(x: np.ndarray, ego_x: float) -> np.ndarray:
    """Which bodies at ``x`` [m] along the road the rule considers: within RELEVANCE_RANGE of the ego."""
    return (np.abs(x - ego_x) < RELEVANCE_RANGE) & np.isfinite(x)


def road_state_bodies(snap: RoadSnapshot) -> np.ndarray:
    """The snapshot indices of the bodies :func:`road_state` keeps, in its order (its arrays' rows)."""
    others = snap.others(vehicles_only=False)
    if not others.size:
        return others
    x = (snap.position[others] - snap.lane_origin) @ snap.lane_direction
    ego_x = float((snap.position[snap.ego] - snap.lane_origin) @ snap.lane_direction)
    return others[_relevant(x, ego_x)]


def road_state(snap: RoadSnapshot, ego_speed_magnitude: bool = True) -> RoadState:
    """The scene around the ego in lane coordinates (metres, m/s) for the safety model.

    ``ego_speed_magnitude`` (``shield.ego_speed_magnitude``): the ego's speed is its speed controller's
    (highway-env's ``vehicle.speed``: what MDPVehicle's set-points and its P-controller act on, exact
    for the model's ego trajectories, and along its path an upper bound on its progress along the road);
    false: the component along the road, which the heading of a lane change lowers (issue 15, the grid's
    cells 573, 708 and 861: the rule then predicted a shorter stop, by up to 6.7 m, and picked a lower
    SLOWER set-point than highway-env's).

    Only bodies within :data:`safelane.safety.model.RELEVANCE_RANGE` [m] of the ego along the road are
    included — the ones :func:`safelane.safety.model.evaluate` considers.
    """
    e = snap.ego
    start, direction, lateral = snap.lane_origin, snap.lane_direction, snap.lane_lateral
    lane_heading = math.atan2(direction[1], direction[0])
    others = snap.others(vehicles_only=False)
    n = others.size
    pos = snap.position[others] - start
    ego_rel = snap.position[e] - start
    ego_x = float(ego_rel @ direction)
    x_all = pos @ direction if n else np.zeros(0)
    near = np.flatnonzero(_relevant(x_all, ego_x))
    nearby = others[near]
    heading = snap.heading[nearby] - lane_heading
    speed = snap.speed[nearby]
    ego_heading = float(snap.heading[e]) - lane_heading
    return RoadState(
        ego_x=ego_x,
        ego_y=float(ego_rel @ lateral),
        ego_speed=float(snap.speed[e]) if ego_speed_magnitude else float(snap.speed[e] * math.cos(ego_heading)),
        ego_lane=int(snap.lane[e]),
        ego_target_lane=int(snap.target_lane[e]),
        ego_target_speed=snap.ego_target_speed,
        ego_speed_index=snap.ego_speed_index,
        ego_length=float(snap.length[e]),
        ego_heading=ego_heading,
        x=x_all[near],
        y=(pos @ lateral)[near] if n else np.zeros(0),
        vx=speed * np.cos(heading),
        vy=speed * np.sin(heading),
        heading=np.arctan2(np.sin(heading), np.cos(heading)),
        length=snap.length[nearby],
        crashed=snap.crashed[nearby],
        target_speed=snap.target_speed[nearby],
        speed_limit=snap.speed_limit,
        **{name: getattr(snap, name)[nearby] for name in DRIVER_FIELDS},
    )


class SafetyShield(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Gymnasium wrapper exposing the safety model's action mask (and optionally enforcing it).

    ``mode``: ``"nominal"`` (the paper's Q-masking) or ``"robust"`` (robust Q-masking).
    ``formula``: ``"kinematic"`` (derived for highway-env, docs/safety.md) or ``"paper"`` (eq. 12).
    ``override``: replace an unsafe chosen action by the closest safe one.
    ``engine``: ``"compiled"`` (:mod:`safelane.safety.compiled`, microseconds) or ``"numpy"`` (the
    reference :func:`safelane.safety.model.evaluate`, about a millisecond); the same masks either way.
    ``margin`` [m]: the bumper-to-bumper gap kept under the worst case (the rule's safety threshold).
    ``projected_cut_ins``: robust mode also counts cut-ins from the lane a sideways-moving vehicle moves to.
    ``body_extent``: robust mode also puts a vehicle in every lane its rotated body overlaps.
    ``linear_mobil``: robust mode applies a linear-model driver's MOBIL criterion with its own formula.
    ``reversing_leaders``: a leader moving backwards keeps its reverse speed (else it counts as stopped).
    ``level_cut_ins``: robust mode lets a car level with or behind the ego in a next lane turn in behind it;
    ``level_incentive``: only when MOBIL's incentive lets it (else any such car may);
    ``level_entering``: any such car into a lane the ego is only entering (the incentive assumes it there).
    ``least_bad_joint``: with no safe action, rank by the worst gap to anybody first (else: to vehicles ahead).
    ``full_horizon``: the rule's horizon spans the same seconds at every decision rate (else: decisions).
    ``ego_speed_magnitude``: the ego's speed is its controller's (else: its component along the road).
    ``turning_leaders``: robust mode, a moving leader brakes along its path, less a lane change's cost.
    ``robust_fallback`` (experimental): with no safe action, robust mode takes the least-bad of every available
    action by its robust gaps (else: of the nominally safe ones when there are some).
    ``straight_fallback``: with ``turning_leaders`` and no safe action, the mask of the rule
    without ``turning_leaders`` (its safe actions, else its least-bad one).
    ``linear_incentive``: with ``level_incentive``, a Linear, Aggressive or Defensive driver turns in behind the
    ego only when MOBIL's incentive with its own linear model lets it (else any such car may);
    ``linear_incentive_braking``: that incentive also at every frame of the decision, its leaders braking fully.
    ``reversing_cut_ins``: a car in a next lane moving backwards may change into the ego's lane whatever MOBIL
    says (highway-env's steering assumes forward motion: reversing, a lane change away swings its nose in).
    ``crossed_lanes``: the ego occupies every lane between its lane and its target (a lane change chained onto
    one under way crosses the lane in between whole), not only the two.
    ``lateral_schedule`` (experimental): the ego's time in each lane simulated with highway-env's lateral
    controller from its lateral position and heading (else: a lane change from a lane centre, restarted at
    every decision).
    ``reversing_noses``: robust mode also puts a car rolling backwards with its nose turned in the
    lane its nose points to (it moves there as soon as it moves forward again).
    ``follower_idm``: the IDM car right behind the ego in its lane brakes by IDM's response to each fallback
    of the ego (else: it accelerates for the reaction time, whatever the ego does).
    ``follower_set_point`` (experimental): ``follower_idm`` with the car's own set-point read from the
    simulator, and linear-model drivers behind the ego by their own formula.
    ``finishing_changes``: robust mode does not project a car finishing a lane change into its own lane (moving
    toward that lane's centre, short of it) into the lane beyond; it may cut in from its lane, MOBIL-filtered,
    like any car there.
    ``cut_in_when_permitted``: robust mode starts a permitted cut-in at the first frame of the
    decision at which MOBIL's safety criterion allows it, plus the cut-in time (else: from the cut-in time).
    ``leaving_lanes_seen`` (experimental, with ``lateral_schedule``): cut-ins into a lane the ego is leaving, while
    MOBIL still sees it there, are MOBIL-filtered as in its own lane.
    ``permit_any_speed``: with ``cut_in_when_permitted``, MOBIL's IDM criterion at the car's loosest speed within
    its reach (else at its fastest, which is not the loosest when IDM's desired gap goes negative).
    ``passing_cut_ins`` (with ``cut_in_when_permitted``): a car behind the ego in a next lane that
    MOBIL lets cut in ahead of it is a leader once in (else bounded as a follower).
    ``level_when_incentive``: a car level with or behind the ego turns in behind it from the
    first frame MOBIL's incentive allows it (else from the cut-in time whenever it allows it now or at the end).
    ``incentive_any_speed`` (with ``level_when_incentive``): that first frame over every speed the car and the
    vehicles ahead of it can reach, a bound (else with the others at constant speed, which highway-env beat).
    ``turning_in_nominal`` (with ``turning_leaders``): nominal's bound for a moving leader, and robust's straight
    fallback's, is the looser of braking along the road and robust's along its path, so robust ⊆ nominal holds
    with a fast car changing lanes.
    ``forecast_fallback``: with no safe action, rank the least-bad choice first by the gap a nominal forecast of
    the others predicts (:mod:`safelane.safety.forecast`: every car keeps its lane and drives by its own law),
    capped at ``margin``, a forecast collision ranking as one; then as before (on by default since issue 15's
    seventeenth session).
    ``forecast_contact_time`` (with ``forecast_fallback``, experimental, off): a forecast collision ranks by the
    whole decisions before its first contact, the more the higher (measured worse: docs/safety.md §6r).
    ``forecast_lane_changes`` (with ``forecast_fallback``, experimental, off): the forecast's cars change lane by
    MOBIL (measured worse: docs/safety.md §6r).
    """

    def __init__(
        self,
        env: gym.Env,
        mode: Mode = "robust",
        formula: Formula = "kinematic",
        override: bool = False,
        engine: Engine = "compiled",
        margin: float = DEFAULT_MARGIN,
        projected_cut_ins: bool = False,
        body_extent: bool = True,
        linear_mobil: bool = True,
        reversing_leaders: bool = True,
        level_cut_ins: bool = True,
        level_incentive: bool = True,
        level_entering: bool = True,
        least_bad_joint: bool = False,
        full_horizon: bool = True,
        ego_speed_magnitude: bool = True,
        turning_leaders: bool = True,
        robust_fallback: bool = False,
        straight_fallback: bool = True,
        linear_incentive: bool = True,
        linear_incentive_braking: bool = True,
        reversing_cut_ins: bool = True,
        crossed_lanes: bool = True,
        lateral_schedule: bool = False,
        reversing_noses: bool = True,
        follower_idm: bool = True,
        follower_set_point: bool = False,
        finishing_changes: bool = True,
        cut_in_when_permitted: bool = True,
        leaving_lanes_seen: bool = False,
        permit_any_speed: bool = True,
        passing_cut_ins: bool = True,
        level_when_incentive: bool = True,
        incentive_any_speed: bool = True,
        turning_in_nominal: bool = True,
        forecast_fallback: bool = True,
        forecast_contact_time: bool = False,
        forecast_lane_changes: bool = False,
    ) -> None:
        if not (math.isfinite(margin) and margin >= 0):
            raise ValueError(f"shield.margin: must be a finite number >= 0 [m] (got {margin!r})")
        if mode not in ("nominal", "robust"):
            raise ValueError(f"shield.mode: got {mode!r}; allowed: 'nominal', 'robust'")
        if formula not in ("kinematic", "paper"):
            raise ValueError(f"shield.formula: got {formula!r}; allowed: 'kinematic', 'paper'")
        if engine not in ENGINES:
            raise ValueError(f"shield.engine: got {engine!r}; allowed: 'compiled', 'numpy'")
        gym.utils.RecordConstructorArgs.__init__(
            self,
            mode=mode,
            formula=formula,
            override=override,
            engine=engine,
            margin=margin,
            projected_cut_ins=projected_cut_ins,
            body_extent=body_extent,
            linear_mobil=linear_mobil,
            reversing_leaders=reversing_leaders,
            level_cut_ins=level_cut_ins,
            level_incentive=level_incentive,
            level_entering=level_entering,
            least_bad_joint=least_bad_joint,
            full_horizon=full_horizon,
            ego_speed_magnitude=ego_speed_magnitude,
            turning_leaders=turning_leaders,
            robust_fallback=robust_fallback,
            straight_fallback=straight_fallback,
            linear_incentive=linear_incentive,
            linear_incentive_braking=linear_incentive_braking,
            reversing_cut_ins=reversing_cut_ins,
            crossed_lanes=crossed_lanes,
            lateral_schedule=lateral_schedule,
            reversing_noses=reversing_noses,
            follower_idm=follower_idm,
            follower_set_point=follower_set_point,
            finishing_changes=finishing_changes,
            cut_in_when_permitted=cut_in_when_permitted,
            leaving_lanes_seen=leaving_lanes_seen,
            permit_any_speed=permit_any_speed,
            passing_cut_ins=passing_cut_ins,
            level_when_incentive=level_when_incentive,
            incentive_any_speed=incentive_any_speed,
            turning_in_nominal=turning_in_nominal,
            forecast_fallback=forecast_fallback,
            forecast_contact_time=forecast_contact_time,
            forecast_lane_changes=forecast_lane_changes,
        )
        try:
            env.get_wrapper_attr("road_snapshot")
        except AttributeError:  # a plain highway-env environment: read its scene through the adapter
            env = HighwayEnvAdapter(env)
        super().__init__(env)
        self.mode: Mode = mode
        self.formula: Formula = formula
        self.override = override
        self.engine: Engine = engine
        self.margin = float(margin)
        self.projected_cut_ins = bool(projected_cut_ins)
        self.body_extent = bool(body_extent)
        self.linear_mobil = bool(linear_mobil)
        self.reversing_leaders = bool(reversing_leaders)
        self.level_cut_ins = bool(level_cut_ins)
        self.level_incentive = bool(level_incentive)
        self.level_entering = bool(level_entering)
        self.least_bad_joint = bool(least_bad_joint)
        self.full_horizon = bool(full_horizon)
        self.ego_speed_magnitude = bool(ego_speed_magnitude)
        self.turning_leaders = bool(turning_leaders)
        self.robust_fallback = bool(robust_fallback)
        self.straight_fallback = bool(straight_fallback)
        self.linear_incentive = bool(linear_incentive)
        self.linear_incentive_braking = bool(linear_incentive_braking)
        self.reversing_cut_ins = bool(reversing_cut_ins)
        self.crossed_lanes = bool(crossed_lanes)
        self.lateral_schedule = bool(lateral_schedule)
        self.reversing_noses = bool(reversing_noses)
        self.follower_idm = bool(follower_idm)
        self.follower_set_point = bool(follower_set_point)
        self.finishing_changes = bool(finishing_changes)
        self.cut_in_when_permitted = bool(cut_in_when_permitted)
        self.leaving_lanes_seen = bool(leaving_lanes_seen)
        self.permit_any_speed = bool(permit_any_speed)
        self.passing_cut_ins = bool(passing_cut_ins)
        self.level_when_incentive = bool(level_when_incentive)
        self.incentive_any_speed = bool(incentive_any_speed)
        self.turning_in_nominal = bool(turning_in_nominal)
        self.forecast_fallback = bool(forecast_fallback)
        self.forecast_contact_time = bool(forecast_contact_time)
        self.forecast_lane_changes = bool(forecast_lane_changes)
        self._rule_options = {name: getattr(self, name) for name in RULE_OPTIONS}  # dynamics_of's keywords
        self.dynamics: Dynamics | None = None
        self.result: SafetyResult | None = None
        self.snapshot: RoadSnapshot | None = None
        self._warned_cannot_stop = False

    def compute_result(self, snap: RoadSnapshot | None = None) -> SafetyResult:
        """Evaluate the safety model on ``snap`` (default: the last snapshot seen; no caching)."""
        snap = self.snapshot if snap is None else snap
        if snap is None:
            raise RuntimeError("SafetyShield: reset the environment first")
        lane_heading, leave, lateral_speed = self._ego_leave_time(snap)
        dyn = self.dynamics
        assert dyn is not None
        if self.engine == "compiled" and (self.mode, self.formula) != ("nominal", "paper") and axis_aligned(snap):
            # The fast path: the RoadState is built inside the kernel (identical to road_state's).
            return evaluate_snapshot(
                snap, dyn, self.mode, lane_heading=lane_heading, ego_leave_time=leave, ego_lateral_speed=lateral_speed
            )
        evaluator = evaluate_compiled if self.engine == "compiled" else evaluate
        state = road_state(snap, dyn.ego_speed_magnitude)
        dyn = dataclasses.replace(dyn, ego_leave_time=leave, ego_lateral_speed=lateral_speed)
        return evaluator(state, dyn, self.mode, self.formula)

    def state_and_dynamics(self, snap: RoadSnapshot) -> tuple[RoadState, Dynamics]:
        """The (RoadState, Dynamics) that :meth:`compute_result` evaluates for ``snap`` (the numpy engine's
        inputs; the compiled engine builds the same state inside its kernel)."""
        _, leave, lateral_speed = self._ego_leave_time(snap)
        assert self.dynamics is not None
        dyn = self.dynamics
        state = road_state(snap, dyn.ego_speed_magnitude)
        return state, dataclasses.replace(dyn, ego_leave_time=leave, ego_lateral_speed=lateral_speed)

    def _ego_leave_time(self, snap: RoadSnapshot) -> tuple[float, float, float]:
        """(lane heading [rad], the time [s] the ego takes to leave its lane, the speed [m/s] that time is
        taken at — ``Dynamics.ego_lateral_speed``) for ``snap``."""
        if self.dynamics is None:
            self.dynamics = dynamics_of(snap, self.margin, **self._rule_options)
        dyn = self.dynamics
        # The ego's speed along the road, as road_state computes it (the compiled path builds no RoadState).
        direction = snap.lane_direction
        lane_heading = math.atan2(direction[1], direction[0])
        e = snap.ego
        ego_speed = float(snap.speed[e] * math.cos(float(snap.heading[e]) - lane_heading))
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
        return lane_heading, ego_leave_time_at(dyn, speed), speed

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
        info["action_mask"] = self.result.mask.copy()
        info["fallback"] = bool(self.result.fallback)

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        self.dynamics = None
        obs, info = self.env.reset(**kwargs)
        self._annotate(info)
        info["shield_intervened"] = False
        self._warn_if_the_ego_cannot_stop()
        return obs, info

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
        obs, reward, terminated, truncated, info = self.env.step(executed)
        info["shield_intervened"] = executed != chosen
        info["unsafe_action"] = not bool(mask[chosen])
        info["executed_action"] = executed
        self._annotate(info)
        info["invariant_break"] = bool(promised and mask[executed] and info["fallback"])
        return obs, reward, terminated, truncated, info
