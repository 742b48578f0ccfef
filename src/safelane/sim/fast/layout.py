"""The fast simulator's state layout: the columns of its vehicle arrays, its parameter vector and the ego's
meta-actions, as integer indices shared by every kernel (numba freezes them at compile time) and every caller.

State layout (``ego`` is row 0, the others follow in highway-env's order):

``F[n, NF]`` float64 columns X, Y, H (heading), V (speed), TSPD (target speed), DELTA (IDM exponent),
TIMER (MOBIL timer), IMPX, IMPY (pending impact), STEER, ACC (last action), COSH, SINH (cos / sin of
the heading, refreshed at the start of every ``Road.act`` phase, during which no heading changes).

Then each driver's own constants: TW (TIME_WANTED), GAIN (LANE_CHANGE_MIN_ACC_GAIN), AP0..AP2 and SP0, SP1
(LinearVehicle's ACCELERATION_ / STEERING_PARAMETERS), CMAX, CMIN (COMFORT_ACC_MAX / _MIN), DW (DISTANCE_WANTED),
POL (POLITENESS), MBI (LANE_CHANGE_MAX_BRAKING_IMPOSED): a driver's models read its own (highway-env's ``self.X``).

``G[n, NI]`` int64 columns LANE, TLANE (target lane), CRASHED, HASIMP (impact pending), CHECK
(check_collisions), ELC (enable_lane_change), IDM (1: IDM-family driver, 0: the ego, an MDPVehicle or, under
ContinuousAction, a Vehicle), LIN (1: LinearVehicle's models), DTYPE (the driver's type: its index in the
traffic's driver mixture; -1: the ego, or no mixture).

``E`` int64 (1,): the ego's speed index (-1 under ContinuousAction: a Vehicle has none).

Under ContinuousAction the ego's STEER / ACC hold its action for the decision and its TSPD what the other
drivers' models read for it (:mod:`safelane.sim.fast.continuous`).

``P[NP]`` float64: highway-env's class constants at the ``P_*`` indices (SI units: metres, m/s, m/s², seconds).
"""

from __future__ import annotations

# float columns (COSH, SINH: cos / sin of the heading, cached for each Road.act phase)
X, Y, H, V, TSPD, DELTA, TIMER, IMPX, IMPY, STEER, ACC, COSH, SINH = range(13)
# per-vehicle driver constants: TW (TIME_WANTED), GAIN (LANE_CHANGE_MIN_ACC_GAIN), LinearVehicle's
# ACCELERATION_PARAMETERS (AP0..2) and STEERING_PARAMETERS (SP0, SP1), IDM's COMFORT_ACC_MAX (CMAX) and
# COMFORT_ACC_MIN (CMIN), DISTANCE_WANTED (DW), MOBIL's POLITENESS (POL) and LANE_CHANGE_MAX_BRAKING_IMPOSED (MBI)
TW, GAIN, AP0, AP1, AP2, SP0, SP1, CMAX, CMIN, DW, POL, MBI = range(13, 25)
NF = 25
# int columns
LANE, TLANE, CRASHED, HASIMP, CHECK, ELC, IDM, LIN, DTYPE = range(9)
NI = 9

# A driver type's constants (a row of the spawn kernels' driver table, scene.driver_constants): linear model?,
# TIME_WANTED, LANE_CHANGE_MIN_ACC_GAIN, ACCELERATION_RANGE (2 x 3), STEERING_RANGE (2 x 2), COMFORT_ACC_MAX,
# COMFORT_ACC_MIN, DISTANCE_WANTED, POLITENESS, LANE_CHANGE_MAX_BRAKING_IMPOSED, DELTA_RANGE (2), LANE_CHANGE_DELAY
D_LIN, D_TW, D_GAIN = range(3)
D_AR = 3  # 6 entries: ACCELERATION_RANGE[0], then [1]
D_SR = 9  # 4 entries: STEERING_RANGE[0], then [1]
D_CMAX, D_CMIN, D_DW, D_POL, D_MBI, D_DLO, D_DHI, D_DELAY = range(13, 21)
ND = 21

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
