"""The fast simulator's state layout: the columns of its vehicle arrays, its parameter vector and the ego's
meta-actions, as integer indices shared by every kernel (numba freezes them at compile time) and every caller.

State layout (``ego`` is row 0, the others follow in highway-env's order):

``F[n, NF]`` float64 columns X, Y, H (heading), V (speed), TSPD (target speed), DELTA (IDM exponent),
TIMER (MOBIL timer), IMPX, IMPY (pending impact), STEER, ACC (last action), COSH, SINH (cos / sin of
the heading, refreshed at the start of every ``Road.act`` phase, during which no heading changes).

``G[n, NI]`` int64 columns LANE, TLANE (target lane), CRASHED, HASIMP (impact pending), CHECK
(check_collisions), ELC (enable_lane_change), IDM (1: IDM-family driver, 0: the ego, an MDPVehicle or, under
ContinuousAction, a Vehicle), LIN (1: LinearVehicle's models).

``E`` int64 (1,): the ego's speed index (-1 under ContinuousAction: a Vehicle has none).

Under ContinuousAction the ego's STEER / ACC hold its action for the decision and its TSPD what the other
drivers' models read for it (:mod:`safelane.sim.fast.continuous`).

``P[NP]`` float64: highway-env's class constants at the ``P_*`` indices (SI units: metres, m/s, m/s², seconds).
"""

from __future__ import annotations

# float columns (COSH, SINH: cos / sin of the heading, cached for each Road.act phase)
X, Y, H, V, TSPD, DELTA, TIMER, IMPX, IMPY, STEER, ACC, COSH, SINH = range(13)
# per-vehicle driver constants: TW (TIME_WANTED), GAIN (LANE_CHANGE_MIN_ACC_GAIN), LinearVehicle's
# ACCELERATION_PARAMETERS (AP0..2) and STEERING_PARAMETERS (SP0, SP1)
TW, GAIN, AP0, AP1, AP2, SP0, SP1 = range(13, 20)
NF = 20
# int columns
LANE, TLANE, CRASHED, HASIMP, CHECK, ELC, IDM, LIN = range(8)
NI = 8

# Parameter vector P (float64), filled by the env from highway-env's class constants.
(
    P_LANE_WIDTH,
    P_LANE_LENGTH,
    P_VEHICLE_LENGTH_LANE,  # AbstractLane.VEHICLE_LENGTH (on_lane / is_reachable_from margins)
    P_SPEED_LIMIT,
    P_LENGTH,  # Vehicle.LENGTH
    P_WIDTH,  # Vehicle.WIDTH
    P_DIAGONAL,
    P_MAX_SPEED,
    P_MIN_SPEED,
    P_TAU_PURSUIT,
    P_KP_A,
    P_KP_HEADING,
    P_KP_LATERAL,
    P_MAX_STEERING,
    P_ACC_MAX,
    P_COMFORT_ACC_MAX,
    P_COMFORT_ACC_MIN,
    P_DISTANCE_WANTED,
    P_TIME_WANTED,
    P_POLITENESS,
    P_MIN_ACC_GAIN,
    P_MAX_BRAKING_IMPOSED,
    P_LANE_CHANGE_DELAY,
    P_SQUARE,  # 2.0, read at run time: highway-env's ``x ** 2`` on a float is libm's pow (see kernels._linear_steering)
) = range(24)
NP = 24

# Ego meta-actions (DiscreteMetaAction.ACTIONS_ALL)
LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER = 0, 1, 2, 3, 4
