"""The other vehicles' worst cases: leaders braking, followers surging, an IDM follower responding to the ego,
and the acceleration a driver's own model predicts for the ego behind it (MOBIL's criterion). Metres, m/s, s."""

from __future__ import annotations

import math

import numpy as np

from safelane.safety.world import IDM_LANE_MARGIN, LATERAL_MOTION_THRESHOLD, NOT_ZERO, Dynamics, RoadState

# --------------------------------------------------------------------------------------------
# Other vehicles' worst cases.
# --------------------------------------------------------------------------------------------


def turning_allowance(dyn: Dynamics) -> float:
    """[m] What a lane change can cost a leader along the road, with the rule's ``turning_leaders`` (else 0).

    The leader bound brakes from the car's speed along the road, ``v·cos h``: a car turning out of the ego's
    lane has a lower one, which the next decision's bound keeps for the whole horizon — not nested in time
    (21 of the 22 holes of the 100 800-episode campaign). With the option a moving leader brakes
    from its speed along its path, less this allowance, ``lane_width·tan(π/8)`` (1.66 m: one lane width at
    the π/4 that highway-env holds a heading to); the same for a straight and a turning car (one lane change
    within the horizon). Not a closed-form bound — the path turns by ``heading + β`` (slip angle) — but
    measured against highway-env's controller: from any frame of a lane change at 1–30 m/s braking at up to
    ACC_MAX, 5–15 Hz physics, the car stays within 1.59 m of the braking bound
    (``tests/test_safety.py::test_turning_allowance_covers_highway_env_s_lane_change``)."""
    return dyn.lane_width * math.tan(math.pi / 8) if dyn.rule.turning_leaders else 0.0


def braking_positions(
    x0: np.ndarray, v0: np.ndarray, brake: np.ndarray, t: np.ndarray, reversing: bool = False
) -> np.ndarray:
    """Positions [m] of vehicles braking at ``brake`` [m/s²] from speed ``v0`` [m/s] until standstill.

    A vehicle moving backwards (``v0 < 0``) counts as stopped, or with ``reversing`` keeps moving back at
    ``v0`` for the whole of ``t``: IDM has no bound on how long a jammed car rolls back (highway-env clips
    speeds to ±40 m/s only), and the ego behind it cannot reverse (docs/research/reversing-cars.md)."""
    v_signed = v0[:, None]
    v0 = np.maximum(v0, 0.0)[:, None]
    b = np.maximum(brake, 1e-6)[:, None]
    tt = np.minimum(t[None, :], v0 / b)
    x = x0[:, None] + v0 * tt - 0.5 * b * tt**2
    if reversing:
        x = np.where(v_signed < 0.0, x + v_signed * t[None, :], x)
    return x


def follower_positions(
    x0: np.ndarray, v0: np.ndarray, accel: np.ndarray, brake: np.ndarray, reaction: float, t: np.ndarray
) -> np.ndarray:
    """Positions [m] of vehicles accelerating at ``accel`` for ``reaction`` s, then braking to a stop."""
    v0 = np.maximum(v0, 0.0)[:, None]
    a = accel[:, None]
    b = np.maximum(brake, 1e-6)[:, None]
    t_r = min(reaction, float(t[-1]))
    t1 = np.minimum(t[None, :], t_r)
    x1 = x0[:, None] + v0 * t1 + 0.5 * a * t1**2
    v1 = v0 + a * t_r
    t2 = np.clip(t[None, :] - t_r, 0.0, None)
    t2 = np.minimum(t2, v1 / b)
    return x1 + v1 * t2 - 0.5 * b * t2**2


def idm_acceleration_behind(
    state: RoadState,
    who: np.ndarray,
    gap_centres: np.ndarray,
    ego_speed: np.ndarray,
    ego_target: np.ndarray,
    own_speed: np.ndarray | None = None,
) -> np.ndarray:
    """IDM acceleration [m/s²] that vehicles ``who`` predict for the ego following them.

    This is the quantity of MOBIL's safety criterion (highway-env ``IDMVehicle.mobil``), computed
    with the cutting vehicle's own IDM parameters; ``gap_centres`` is the centre-to-centre distance
    [m] (highway-env's ``lane_distance_to``), ``ego_target`` the ego's set-point clipped to the
    speed limit; ``own_speed`` [m/s] the cutting vehicle's speed (default: its speed now).
    """
    acc = state.idm_comfort_acc[who]
    target = np.where(np.abs(ego_target) < 1e-2, 1e-2, ego_target)
    free = acc * (1 - np.power(np.maximum(ego_speed, 0.0) / np.abs(target), state.idm_delta[who]))
    ab = -acc * state.idm_comfort_dec[who]
    dv = ego_speed - (state.vx[who] if own_speed is None else own_speed)
    d_star = (
        state.idm_distance_wanted[who] + ego_speed * state.idm_time_wanted[who] + ego_speed * dv / (2 * np.sqrt(ab))
    )
    d = np.where(np.abs(gap_centres) < 1e-2, 1e-2, gap_centres)
    return free - acc * (d_star / d) ** 2


def least_desired_gap(
    state: RoadState, who: np.ndarray, ego_speed: float, speed_low: np.ndarray, speed_high: np.ndarray
) -> np.ndarray:
    """The least ``|d*|`` [m] of IDM's desired gap that vehicles ``who`` (their own parameters) predict for the
    ego (at ``ego_speed`` [m/s]) following them, over their speeds in ``[speed_low, speed_high]`` [m/s]:
    ``d* = d₀ + v·T + v·(v − v_car)/(2√(ab))`` is monotone in ``v_car``, so 0 where it changes sign in the
    range, else its endpoint nearer 0."""
    ab = -state.idm_comfort_acc[who] * state.idm_comfort_dec[who]
    base = state.idm_distance_wanted[who] + ego_speed * state.idm_time_wanted[who]
    d_hi = base + ego_speed * (ego_speed - speed_high) / (2 * np.sqrt(ab))  # the car at its fastest
    d_lo = base + ego_speed * (ego_speed - speed_low) / (2 * np.sqrt(ab))  # at its slowest
    lo, hi = np.minimum(d_hi, d_lo), np.maximum(d_hi, d_lo)
    return np.where(lo > 0.0, lo, np.where(hi < 0.0, -hi, 0.0))


def idm_acceleration_behind_gap(
    state: RoadState, who: np.ndarray, gap_centres: np.ndarray, ego_speed: np.ndarray, ego_target: np.ndarray,
    desired_gap: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """:func:`idm_acceleration_behind` with IDM's desired gap ``desired_gap`` [m] given (e.g.
    :func:`least_desired_gap`) instead of computed from one speed of the car."""
    acc = state.idm_comfort_acc[who]
    target = np.where(np.abs(ego_target) < 1e-2, 1e-2, ego_target)
    free = acc * (1 - np.power(np.maximum(ego_speed, 0.0) / np.abs(target), state.idm_delta[who]))
    d = np.where(np.abs(gap_centres) < 1e-2, 1e-2, gap_centres)
    return free - acc * (desired_gap / d) ** 2


def linear_acceleration_behind(
    state: RoadState,
    who: np.ndarray,
    gap_centres: np.ndarray,
    ego_speed: np.ndarray,
    ego_target: np.ndarray,
    own_speed: np.ndarray | None = None,
) -> np.ndarray:
    """The acceleration [m/s²] a linear-model driver ``who`` (``LinearVehicle.acceleration``) predicts for
    the ego following it: ``k₀·(v* − v) + k₁·min(v_who − v, 0) + k₂·min(d − d_safe, 0)`` with
    ``d_safe = DISTANCE_WANTED + max(v, 0)·TIME_WANTED`` — MOBIL's safety criterion for Linear, Aggressive
    and Defensive drivers. ``gap_centres`` [m] centre to centre, ``ego_target`` [m/s] the ego's set-point
    (not clipped: highway-env reads ``target_speed``); the driver's speed is its whole speed (≥ its
    speed along the road), which can only make the criterion allow more; ``own_speed`` [m/s] overrides it."""
    if own_speed is None:
        own_speed = np.hypot(state.vx[who], state.vy[who])
    d_safe = state.idm_distance_wanted[who] + np.maximum(ego_speed, 0.0) * state.idm_time_wanted[who]
    return (
        state.linear_speed_gain[who] * (ego_target - ego_speed)
        + state.linear_speed_difference_gain[who] * np.minimum(own_speed - ego_speed, 0.0)
        + state.linear_distance_gain[who] * np.minimum(gap_centres - d_safe, 0.0)
    )


def set_points(state: RoadState) -> np.ndarray:
    """Each vehicle's speed set-point [m/s] (``RoadState.target_speed``), NaN where the state has none."""
    if state.target_speed.shape == state.x.shape:
        return state.target_speed
    return np.full(state.n, np.nan)


def idm_followers(state: RoadState, dyn: Dynamics, near: np.ndarray) -> np.ndarray:
    """Which vehicles ``near`` follow the ego by IDM, with the rule's ``follower_idm`` (else none): bool per row.

    highway-env's IDM brakes for the nearest body ahead of it within half a lane + 1 m of its lane's centre
    (``Road.neighbour_vehicles``, ``Lane.on_lane(margin=1)``) at every physics frame. The car right behind the
    ego in the ego's lane, driving straight (not moving sideways), with IDM's formula (not the linear model)
    and a lane-change rule (a driver, not an object), has the ego as that body: nothing else's centre lies
    between the two in the band. A linear-model driver does not count: its formula is linear in its own
    set-point, which the rule does not observe, so it has no bound without it."""
    rows = np.zeros(near.shape[0], dtype=bool)
    if not dyn.rule.follower_idm:
        return rows
    centre = state.ego_lane * dyn.lane_width
    in_band = np.abs(state.y - centre) <= 0.5 * dyn.lane_width + IDM_LANE_MARGIN
    lanes = state.lane_of(state.y, dyn.lanes_count, dyn.lane_width)
    for r, i in enumerate(near):
        if not (
            state.x[i] < state.ego_x
            and not state.crashed[i]
            and state.can_change_lane[i]
            and np.isnan(state.linear_speed_gain[i])
            and abs(state.heading[i]) <= LATERAL_MOTION_THRESHOLD
            and abs(state.vy[i]) <= 0.3
            and lanes[i] == state.ego_lane
        ):
            continue
        between = in_band & (state.x >= state.x[i]) & (state.x <= state.ego_x)
        between[i] = False
        rows[r] = not between.any()
    return rows


def idm_follower_positions(state: RoadState, dyn: Dynamics, i: int, ego_x: np.ndarray, ego_v: np.ndarray) -> np.ndarray:
    """Positions [m] of follower ``i`` (:func:`idm_followers`) braking by IDM for the ego, per fallback.

    ``ego_x``, ``ego_v``: (F, T) the ego's positions [m] and speeds [m/s] of one action's fallbacks. Frame
    by frame as highway-env's ``IDMVehicle.act`` then ``Vehicle.step``: ``a = acc·(1 − (v/v₀)^δ) −
    acc·(d*/d)²`` with ``d* = d₀ + v·T + v·(v − v_ego)/(2√(acc·b))`` and ``d`` the centre distance, clipped to
    ``[−brake_max, accel_max]``; then ``x += v·dt``, ``v += a·dt``. The driver's own set-point v₀ is not
    observed, so the free-road term is bounded by ``acc`` (v₀ = ∞): an upper bound on its acceleration in
    every state, not a proven envelope of its path (docs/research/car-behind.md). Beyond the last frame the car is
    credited what the follower bound lets it still cover (accelerate for the reaction time, then brake).
    Returns (F, T)."""
    acc = float(state.idm_comfort_acc[i])
    two_sqrt_ab = 2.0 * math.sqrt(-acc * float(state.idm_comfort_dec[i]))
    d0, tw = float(state.idm_distance_wanted[i]), float(state.idm_time_wanted[i])
    a_max, b_max = float(state.accel_max[i]), float(state.brake_max[i])
    dt = dyn.frame_dt
    n_f, n_t = ego_x.shape
    out = np.empty((n_f, n_t))
    xf = np.full(n_f, float(state.x[i]))
    vf = np.full(n_f, float(state.vx[i]))
    out[:, 0] = xf
    for k in range(n_t - 1):
        d = ego_x[:, k] - xf
        d = np.where(np.abs(d) > NOT_ZERO, d, np.where(d >= 0.0, NOT_ZERO, -NOT_ZERO))
        ratio = (d0 + vf * tw + vf * (vf - ego_v[:, k]) / two_sqrt_ab) / d
        a = acc - acc * (ratio * ratio)  # the free-road term at its largest, acc
        a = np.maximum(np.minimum(a, a_max), -b_max)
        xf = xf + vf * dt
        vf = vf + a * dt
        out[:, k + 1] = xf
    reaction = dyn.follower_reaction
    v = np.maximum(vf, 0.0)
    v1 = v + a_max * reaction
    out[:, -1] += v * reaction + 0.5 * a_max * (reaction * reaction) + v1 * v1 / (2.0 * max(b_max, 1e-6))
    return out
