"""The ego under highway-env's ``ContinuousAction`` (``dynamical: False``): a plain kinematic ``Vehicle``.

highway-env maps an action ``a`` in ``[-1, 1]^size`` (``Box(-1, 1, (size,), float32)``) to the ego's controls
once per decision (``ContinuousAction.get_action``): ``np.clip(a, -1, 1)`` (with ``clip``), then
``utils.lmap(a[i], [-1, 1], range)``, stored by ``Vehicle.act(dict)``. ``road.act()`` then calls the ego's
``act()`` with no action at every frame, which keeps it, and ``Vehicle.step`` runs ``clip_actions``
(crashed: steering 0, acceleration ``-speed``; the ``MAX_SPEED`` / ``MIN_SPEED`` clamps, which
``speed_range`` sets), the kinematic bicycle model and ``on_state_update`` (lane = the closest lane).

float32: gymnasium's actions are float32, and under NumPy 2's promotion rules (NEP 50) a float32 scalar
combined with Python numbers stays float32, so ``lmap`` computes the controls in float32 (e.g. 0.3 maps to
an acceleration of exactly 1.5, where float64 arithmetic on the same number gives 1.5000000596…).
``clip_actions`` then stores ``float(...)`` of each control: from there on the ego's speed, heading and
position are float64 (Python floats), as the kernels compute them. :func:`controls` therefore runs
highway-env's own ``np.clip`` and ``lmap`` on the action object as given (float32, float64 or a list: each
keeps its arithmetic) and hands the kernel the two floats.

The other drivers see the ego as highway-env's IDM / MOBIL code does: not a ``ControlledVehicle`` (MOBIL's
abort rule skips it: its target lane is kept equal to its lane), and without ``target_speed``, whose
``getattr`` defaults differ by model: 0 for IDM's formula, the ego's own speed for the linear model's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from highway_env.envs.common.action import ContinuousAction
from highway_env.utils import lmap
from highway_env.vehicle.kinematics import Vehicle
from numba import njit

from safelane.core.kernel_cache import drop_stale_kernel_cache
from safelane.sim.fast import kernels, lanes, layout, numerics
from safelane.sim.fast.kernels import act_traffic, step_traffic, step_vehicle
from safelane.sim.fast.lanes import build_lane_index
from safelane.sim.fast.layout import (
    ACC,
    CRASHED,
    LANE,
    P_DIAGONAL,
    P_MAX_SPEED,
    P_MIN_SPEED,
    STEER,
    TLANE,
    TSPD,
    V,
    X,
    Y,
)

# This kernel compiles in the simulator's kernels, lanes and numerics: numba's cache watches this file only.
drop_stale_kernel_cache(__file__, (kernels.__file__, layout.__file__, numerics.__file__, lanes.__file__))

ACTION_KEYS = frozenset(
    {"type", "longitudinal", "lateral", "acceleration_range", "steering_range", "speed_range", "clip", "dynamical"}
)
"""``ContinuousAction``'s arguments this simulator reads (anything else in ``action`` is refused)."""


@dataclass(frozen=True)
class ContinuousSpec:
    """A resolved ``ContinuousAction`` configuration (``dynamical: False``).

    The ranges keep the numbers as configured (int or float): they enter numpy's type promotion in ``lmap``.
    """

    longitudinal: bool
    lateral: bool
    acceleration_range: tuple[Any, Any]
    """[m/s²] what -1 and 1 map to."""
    steering_range: tuple[Any, Any]
    """[rad] what -1 and 1 map to."""
    speed_range: tuple[float, float] | None
    """[m/s] the ego's (MIN_SPEED, MAX_SPEED); None: ``Vehicle``'s."""
    clip: bool

    @property
    def size(self) -> int:
        """Numbers in one action: 2 (acceleration, steering) or 1 when one of them is off."""
        return 2 if self.longitudinal and self.lateral else 1

    @property
    def speed_bounds(self) -> tuple[float, float]:
        """[m/s] (MIN_SPEED, MAX_SPEED) that ``clip_actions`` applies to the ego."""
        if self.speed_range is None:
            return float(Vehicle.MIN_SPEED), float(Vehicle.MAX_SPEED)
        return float(self.speed_range[0]), float(self.speed_range[1])


def _is_number(value: Any) -> bool:
    """A finite Python int or float (numpy float64 included; bools and float32 are not: they would change the
    arithmetic highway-env does with them)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _pair(action: dict[str, Any], key: str, default: tuple[Any, Any] | None) -> tuple[Any, Any] | None:
    """``action[key]`` as highway-env reads it (``value if value else default``), checked to be two numbers."""
    value = action.get(key)
    if isinstance(value, list | tuple) and len(value) == 2 and all(_is_number(v) for v in value):
        return (value[0], value[1])  # the numbers themselves: their types enter lmap's arithmetic
    if value is None or (isinstance(value, list | tuple) and not value):  # highway-env's `value if value else ...`
        return default
    raise ValueError(f"action.{key}: {value!r} is not supported; allowed: two finite numbers [low, high]")


def resolve_continuous(action: dict[str, Any]) -> ContinuousSpec:
    """Check a ``ContinuousAction`` config (``type: ContinuousAction``) and resolve it with highway-env's
    defaults (``ContinuousAction.ACCELERATION_RANGE`` / ``STEERING_RANGE``); anything this simulator does not
    reproduce raises a one-line ValueError naming the key."""
    extra = sorted(set(action) - ACTION_KEYS)
    if extra:
        raise ValueError(f"action keys not supported by the fast simulator: {extra}")
    if action.get("dynamical", False):
        raise ValueError(f"action.dynamical: {action['dynamical']!r} is not supported; allowed: False")
    longitudinal = bool(action.get("longitudinal", True))
    lateral = bool(action.get("lateral", True))
    if not (longitudinal or lateral):
        raise ValueError("action.longitudinal, action.lateral: both False is not supported; allowed: one True at least")
    acceleration = _pair(action, "acceleration_range", ContinuousAction.ACCELERATION_RANGE)
    steering = _pair(action, "steering_range", ContinuousAction.STEERING_RANGE)
    speeds = _pair(action, "speed_range", None)
    assert acceleration is not None and steering is not None
    return ContinuousSpec(
        longitudinal=longitudinal,
        lateral=lateral,
        acceleration_range=acceleration,
        steering_range=steering,
        speed_range=None if speeds is None else (float(speeds[0]), float(speeds[1])),
        clip=bool(action.get("clip", True)),
    )


def controls(action: Any, spec: ContinuousSpec) -> tuple[float, float]:
    """(acceleration [m/s²], steering [rad]) of one decision: ``ContinuousAction.get_action(action)`` then
    ``Vehicle.clip_actions``' ``float()``, with highway-env's own ``np.clip`` and ``lmap`` on ``action`` as
    given, so a float32 action maps in float32 as it does there (module docstring).

    ``action``: ``spec.size`` numbers (an array of any float dtype, a list or a tuple). A wrong shape, or a
    non-finite control (highway-env would carry NaN / inf into the physics), raises ValueError.
    """
    if np.shape(action) != (spec.size,):
        raise ValueError(f"action {action!r} not in Box(-1, 1, ({spec.size},)): {spec.size} numbers expected")
    a = np.clip(action, -1, 1) if spec.clip else action
    acceleration: Any = 0
    steering: Any = 0
    if spec.longitudinal:
        acceleration = lmap(a[0], [-1, 1], spec.acceleration_range)
    if spec.lateral:
        steering = lmap(a[1 if spec.longitudinal else 0], [-1, 1], spec.steering_range)
    acc, steer = float(acceleration), float(steering)
    if not (math.isfinite(acc) and math.isfinite(steer)):
        raise ValueError(f"action {action!r} is not supported; allowed: finite controls (got {acc!r}, {steer!r})")
    return acc, steer


def ego_params(P: np.ndarray, spec: ContinuousSpec) -> np.ndarray:
    """The parameter vector the ego's ``Vehicle.step`` reads: ``P`` with its MIN_SPEED / MAX_SPEED [m/s]."""
    out = P.copy()
    out[P_MIN_SPEED], out[P_MAX_SPEED] = spec.speed_bounds
    out.flags.writeable = False
    return out


@njit(cache=True, error_model="numpy")
def simulate(F, G, P, P_ego, acceleration, steering, linear_others, frames, dt, n_lanes, before, after, rec):
    """``AbstractEnv._simulate(action)`` with a ``ContinuousAction`` ego: :func:`safelane.sim.fast.kernels.simulate`
    frame for frame, but for the ego (row 0):

    * its action (``acceleration`` [m/s²], ``steering`` [rad], :func:`controls`) is stored once, at the
      decision's first frame, and kept (``Vehicle.act(None)``), with the changes ``clip_actions`` makes to it;
    * its ``Vehicle.step`` clamps the speed to ``P_ego``'s MIN_SPEED / MAX_SPEED (``speed_range``);
    * its target lane stays its lane (a ``Vehicle`` has none: MOBIL's abort rule skips it), and its
      target-speed column holds what the other drivers' models read for it (``linear_others``: the linear
      model's default, its speed; else IDM's, 0).

    ``rec`` / ``before`` / ``after``: the ego's first crash, as in ``kernels.simulate``.
    """
    n = F.shape[0]
    pa = np.empty((5, 2))
    pb = np.empty((5, 2))
    res = np.zeros(2)
    members = np.empty((n_lanes, n), dtype=np.int64)
    mx = np.empty((n_lanes, n))
    cnt = np.zeros(n_lanes, dtype=np.int64)
    reach = (P[P_DIAGONAL] + P[P_DIAGONAL]) / 2 + (P[P_MAX_SPEED] + 1.0) * dt + 1.0
    cand = np.empty(n, dtype=np.int64)
    order = np.empty(n, dtype=np.int64)
    # ContinuousAction.act: Vehicle.act(dict), before the decision's first Road.act
    F[0, ACC] = acceleration
    F[0, STEER] = steering
    for frame in range(frames):
        was_crashed = G[0, CRASHED]
        if rec[0] == 0 and not was_crashed:
            for k in range(n):
                before[k, 0] = F[k, X]
                before[k, 1] = F[k, Y]
        # Road.act: the ego's act() keeps its action; the others decide
        if frame == 0:
            order[:] = np.argsort(F[:, X], kind="mergesort")
        build_lane_index(F, n_lanes, P, members, mx, cnt, order)
        # getattr(ego, "target_speed", default) in the others' models: the linear one's default is the
        # ego's speed (no speed-tracking term), IDM's is 0
        F[0, TSPD] = F[0, V] if linear_others else 0.0
        act_traffic(F, G, 1, n_lanes, P, members, mx, cnt)
        # Road.step
        step_vehicle(F, G, 0, dt, n_lanes, P_ego)
        G[0, TLANE] = G[0, LANE]
        step_traffic(F, G, 1, dt, n_lanes, P, pa, pb, res, reach, cand, order)
        if rec[0] == 0 and not was_crashed and G[0, CRASHED]:
            rec[0] = 1
            for k in range(n):
                after[k, 0] = F[k, X]
                after[k, 1] = F[k, Y]


__all__ = ["ACTION_KEYS", "ContinuousSpec", "controls", "ego_params", "resolve_continuous", "simulate"]
