"""The ego under continuous controls, as highway-env moves it: the action's mapping to controls, one decision of
its kinematic bicycle model, and the fail-safe controller the plans end with (metres, m/s, radians, seconds).

An action is ``(acceleration, steering)`` normalised to ``[-1, 1]`` and held for a whole decision (highway-env's
``ContinuousAction`` stores it once per decision). :func:`physical` maps it to controls with highway-env's
``lmap`` in float32 (a gymnasium ``Box`` action is float32, and NumPy keeps float32 arithmetic with Python numbers:
the controls are those the simulator applies, to the bit); :func:`roll_out` runs ``Vehicle.step`` frame by frame
(``clip_actions``' speed clamps included) on the ego's state in lane coordinates, which on highway-env's straight
road are its world coordinates. Pure maths: no simulator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from safelane.safety.world import Dynamics

HEADING_WEIGHT = 1.0
"""The fail-safe's steering weighs the ego's heading at the end of a decision, as the lateral drift it makes over
one more decision's path, against its offset from the lane centre then (both in metres)."""
STOPPED_SPEED = 1e-2
"""[m/s] A plan ends stopped when the ego's speed at the horizon's end is within this of 0 (the float32
mapping of the last braking control leaves a residue of the order of 1e-6 m/s)."""


@dataclass(frozen=True)
class ControlLimits:
    """What the ego's actions map to: ``acceleration_range`` [m/s²] and ``steering_range`` [rad], what −1 and 1
    mean (highway-env's ``ContinuousAction`` ranges, read from the environment's config), and the speeds
    ``clip_actions`` holds the ego within [m/s] (``Vehicle.MIN_SPEED`` / ``MAX_SPEED`` or ``speed_range``)."""

    acceleration_range: tuple[float, float] = (-5.0, 5.0)
    steering_range: tuple[float, float] = (-math.pi / 4, math.pi / 4)
    min_speed: float = -40.0
    max_speed: float = 40.0

    @property
    def braking(self) -> float:
        """[m/s²] The hardest braking an action can ask for (≥ 0)."""
        return max(-float(self.acceleration_range[0]), 0.0)

    def braking_decisions(self, decision_period: float) -> int:
        """Decisions a plan may need to brake from the top speed to a standstill."""
        if self.braking <= 0.0:
            raise ValueError(
                f"action.acceleration_range: {list(self.acceleration_range)} cannot brake; allowed: a low end below 0"
            )
        return math.ceil(self.max_speed / (self.braking * decision_period) - 1e-9)


def lmap_float32(value: np.float32, low: float, high: float) -> float:
    """[physical unit] highway-env's ``utils.lmap(value, [-1, 1], [low, high])`` on a float32 ``value``, then
    ``float()``: the control the simulator applies."""
    return float(low + (value - -1) * (high - low) / (1 - -1))


def normalised(control: float, low: float, high: float) -> np.float32:
    """The float32 action in [−1, 1] that maps closest to ``control`` (its mapping, :func:`lmap_float32`, is the
    control the plan then applies)."""
    return np.float32(min(max((control - low) * 2.0 / (high - low) - 1.0, -1.0), 1.0))


def physical(action: np.ndarray, limits: ControlLimits) -> tuple[float, float]:
    """(acceleration [m/s²], steering [rad]) of a float32 action (2,) in [−1, 1]."""
    a = np.asarray(action, dtype=np.float32)
    return (lmap_float32(a[0], *limits.acceleration_range), lmap_float32(a[1], *limits.steering_range))


@dataclass
class EgoState:
    """The ego's state in lane coordinates: ``x`` [m] along the road, ``y`` [m] across it, ``heading`` [rad] from
    the road's and ``speed`` [m/s] along its path (highway-env's ``Vehicle.speed``)."""

    x: float
    y: float
    heading: float
    speed: float


def roll_out(
    ego: EgoState, acceleration: float, steering: float, frames: int, dt: float, limits: ControlLimits, length: float,
    out: np.ndarray | None = None,
) -> EgoState:  # fmt: skip
    """The ego's state after ``frames`` frames of ``dt`` [s] holding the controls, each frame as highway-env's
    ``Vehicle.step`` (``clip_actions`` keeps the clamped acceleration for the frames after); ``out`` (frames, 4):
    filled with (x, y, heading, speed) after each frame. ``length`` [m]: the ego's."""
    x, y, heading, speed = ego.x, ego.y, ego.heading, ego.speed
    acc = float(acceleration)
    # libm's functions, in highway-env's order of operations: numpy's scalar functions are libm's wherever the
    # simulators agree (`safelane sim check`), and the compiled engine calls the same ones.
    beta = math.atan(1 / 2 * math.tan(float(steering)))
    sin_beta = math.sin(beta)
    for j in range(frames):
        if speed > limits.max_speed:
            acc = min(acc, 1.0 * (limits.max_speed - speed))
        elif speed < limits.min_speed:
            acc = max(acc, 1.0 * (limits.min_speed - speed))
        hb = heading + beta
        x += speed * math.cos(hb) * dt
        y += speed * math.sin(hb) * dt
        heading += speed * sin_beta / (length / 2) * dt
        speed += acc * dt
        if out is not None:
            out[j, 0], out[j, 1], out[j, 2], out[j, 3] = x, y, heading, speed
    return EgoState(x, y, heading, speed)


def decision_distance(speed: float, acceleration: float, frames: int, dt: float, limits: ControlLimits) -> float:
    """[m] The path length the ego covers in one decision holding ``acceleration`` from ``speed`` [m/s] (the sum
    of its speeds per frame, :func:`roll_out`'s clamps included)."""
    acc, total = float(acceleration), 0.0
    for _ in range(frames):
        if speed > limits.max_speed:
            acc = min(acc, 1.0 * (limits.max_speed - speed))
        elif speed < limits.min_speed:
            acc = max(acc, 1.0 * (limits.min_speed - speed))
        total += speed * dt
        speed += acc * dt
    return total


def fail_safe_action(ego: EgoState, lane_centre: float, braking: bool, dyn: Dynamics, limits: ControlLimits,
                     length: float) -> np.ndarray:  # fmt: skip
    """(2,) float32 the fail-safe's action for the next decision: acceleration 0 (``braking`` False: hold the
    speed) or toward a standstill at the end of the decision, no harder than the range allows; steering for
    ``lane_centre`` [m]: the slip angle that best removes the ego's offset and heading by the decision's end
    (:data:`HEADING_WEIGHT`), within the steering range."""
    period = dyn.decision_period
    low, high = limits.acceleration_range
    wanted = -ego.speed / period if braking else 0.0
    a_norm = normalised(wanted, low, high)
    acceleration = lmap_float32(a_norm, low, high)
    path = decision_distance(ego.speed, acceleration, dyn.frames_per_decision, dyn.frame_dt, limits)
    steer_low, steer_high = limits.steering_range
    steering = 0.0
    if path > 1e-3:
        # Small angles over the decision's path D: the heading turns by 2Dβ/L and the ego drifts Dψ + D²β/L + Dβ.
        # The slip angle β minimises (offset at the end)² + w·(D · heading at the end)², a least-squares step.
        drift = ego.y - lane_centre + path * ego.heading
        drift_gain = path * (1.0 + path / length)
        heading_drift = path * ego.heading
        heading_gain = 2.0 * path * path / length
        beta = -(drift * drift_gain + HEADING_WEIGHT * heading_drift * heading_gain) / (
            drift_gain * drift_gain + HEADING_WEIGHT * heading_gain * heading_gain)
        beta_limit = min(abs(math.atan(0.5 * math.tan(s))) for s in (steer_low, steer_high))
        beta = max(-beta_limit, min(beta_limit, beta))
        steering = math.atan(2.0 * math.tan(beta))
    return np.array([a_norm, normalised(steering, steer_low, steer_high)], dtype=np.float32)
