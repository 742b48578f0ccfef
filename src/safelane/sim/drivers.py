"""Driver types for a mixture of drivers (``traffic.driver_mix``), and how highway-env spawns them.

**The timid, normal and aggressive drivers** are highway-env's ``IDMVehicle`` (IDM for the speed, MOBIL for lane
changes, highway-env's own formulas) with the parameter sets of Sunberg, Ho & Kochenderfer, *The Value of Inferring
the Internal State of Traffic Participants for Autonomous Freeway Driving* (ACC 2017, arXiv:1702.00858), as their
code states them (sisl/Multilane.jl, ``src/behavior_gen.jl``: ``standard_uniform`` gives each parameter's middle and
half-range; the correlated generator's aggressiveness 0, 0.5 and 1 give the three sets; T, s₀, politeness and the
threshold fall as aggressiveness rises):

==========================================  =====  ======  ==========  ===========================================
parameter                                   timid  normal  aggressive  highway-env constant
==========================================  =====  ======  ==========  ===========================================
max. acceleration a [m/s²]                  0.8    1.4     2.0         ``COMFORT_ACC_MAX``
comfortable deceleration b [m/s²]           1.0    2.0     3.0         ``COMFORT_ACC_MIN = -b``
desired time gap T [s]                      2.0    1.5     1.0         ``TIME_WANTED``
jam distance s₀ [m], bumper to bumper       4.0    2.0     0.0         ``DISTANCE_WANTED = s₀ + LENGTH``
politeness p                                1.0    0.5     0.0         ``POLITENESS``
safe braking b_safe [m/s²]                  1.0    2.0     3.0         ``LANE_CHANGE_MAX_BRAKING_IMPOSED``
acceleration threshold a_thr [m/s²]         0.2    0.1     0.0         ``LANE_CHANGE_MIN_ACC_GAIN`` (next double)
==========================================  =====  ======  ==========  ===========================================

highway-env measures the gap between centres, so its ``DISTANCE_WANTED`` is s₀ plus a car's length (its default,
5 m + ``LENGTH``, is a 5 m jam distance). MOBIL's incentive test is strict in Sunberg et al. (a car changes lanes
when its gain exceeds a_thr) and not in highway-env (unless the gain is below ``LANE_CHANGE_MIN_ACC_GAIN``): the next
double above a_thr makes highway-env's test theirs; it matters for the aggressive set's 0, where a car with nothing
to gain would otherwise change lanes at every MOBIL check. What stays highway-env's: the desired speed (a car's spawn
speed, uniform in [21, 24] m/s, highway-env's ``create_random``: their 27.7 / 33.3 / 38.9 m/s would mostly sit on the
30 m/s speed limit IDM clips to), IDM's exponent δ (drawn in [3.5, 4.5] by ``randomize_behavior``; theirs is 4), the
hardest braking ``ACC_MAX`` (6 m/s²) and the lane-change timer.

**Spawning.** :func:`install_driver_mix` makes a highway-env environment draw each other car's type at spawn: its own
``HighwayEnv._create_vehicles`` runs with ``other_vehicles_type`` set to :class:`MixedDriverVehicle`, whose
``create_random`` draws the type with ``road.np_random.choice(K, p=probabilities)`` (one double; numpy's own
inverse-CDF lookup) and then calls that type's ``create_random`` (lane, speed, gap); highway-env then calls the car's
``randomize_behavior()``. Each car keeps its type's index in the mixture as ``driver_type`` (the snapshot's
``driver_type``). The fast simulator replays the same draws (:mod:`safelane.sim.fast.scene`).
"""

from __future__ import annotations

import contextvars
import functools
import math
from typing import Any

import numpy as np
from highway_env.utils import class_from_path
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle

from safelane.core.drivers import DRIVER_TYPES, DriverMix


class TimidDriver(IDMVehicle):
    """IDM + MOBIL with Sunberg et al.'s timid set (module docstring)."""

    COMFORT_ACC_MAX = 0.8  # [m/s²] a
    COMFORT_ACC_MIN = -1.0  # [m/s²] -b
    TIME_WANTED = 2.0  # [s] T
    DISTANCE_WANTED = 4.0 + ControlledVehicle.LENGTH  # [m] s₀ + length (centre to centre)
    POLITENESS = 1.0  # p
    LANE_CHANGE_MAX_BRAKING_IMPOSED = 1.0  # [m/s²] b_safe
    LANE_CHANGE_MIN_ACC_GAIN = math.nextafter(0.2, math.inf)  # [m/s²] a_thr, MOBIL's incentive strict


class NormalDriver(IDMVehicle):
    """IDM + MOBIL with Sunberg et al.'s normal set (module docstring)."""

    COMFORT_ACC_MAX = 1.4  # [m/s²]
    COMFORT_ACC_MIN = -2.0  # [m/s²]
    TIME_WANTED = 1.5  # [s]
    DISTANCE_WANTED = 2.0 + ControlledVehicle.LENGTH  # [m]
    POLITENESS = 0.5
    LANE_CHANGE_MAX_BRAKING_IMPOSED = 2.0  # [m/s²]
    LANE_CHANGE_MIN_ACC_GAIN = math.nextafter(0.1, math.inf)  # [m/s²]


class AggressiveDriver(IDMVehicle):
    """IDM + MOBIL with Sunberg et al.'s aggressive set (module docstring); not highway-env's ``AggressiveVehicle``
    (a linear-model driver)."""

    COMFORT_ACC_MAX = 2.0  # [m/s²]
    COMFORT_ACC_MIN = -3.0  # [m/s²]
    TIME_WANTED = 1.0  # [s]
    DISTANCE_WANTED = 0.0 + ControlledVehicle.LENGTH  # [m]
    POLITENESS = 0.0
    LANE_CHANGE_MAX_BRAKING_IMPOSED = 3.0  # [m/s²]
    LANE_CHANGE_MIN_ACC_GAIN = math.nextafter(0.0, math.inf)  # [m/s²]


def driver_classes(mix: DriverMix) -> tuple[type, ...]:
    """Each type's highway-env vehicle class, in the mixture's order."""
    return tuple(class_from_path(path) for path in mix.paths)


def assumed_class(mix: DriverMix) -> type | None:
    """The class whose parameters the snapshot reports for every drawn car (None: each car's own)."""
    return None if mix.assumed is None else class_from_path(DRIVER_TYPES[mix.assumed])


class DriverDraw:
    """A mixture ready to draw from: its classes and probabilities (``draw`` takes one ``choice`` of the road's
    generator)."""

    def __init__(self, mix: DriverMix) -> None:
        self.mix = mix
        self.classes = driver_classes(mix)
        self.probabilities = mix.probabilities
        self.assumed = assumed_class(mix)

    def draw(self, rng: np.random.Generator) -> int:
        """One car's type: its index in the mixture, ``rng.choice(K, p=probabilities)``."""
        return int(rng.choice(len(self.classes), p=self.probabilities))


_SPAWNING: contextvars.ContextVar[DriverDraw | None] = contextvars.ContextVar("driver_mix_spawning", default=None)

MIXED_DRIVER_PATH = f"{__name__}.MixedDriverVehicle"


class MixedDriverVehicle:
    """highway-env's ``other_vehicles_type`` while :func:`install_driver_mix`'s scene is built: not a vehicle, a
    factory with ``Vehicle.create_random``'s signature."""

    @classmethod
    def create_random(cls, road: Any, **kwargs: Any) -> Any:
        """Draw the car's type from the mixture being spawned, then that type's ``create_random(road, **kwargs)``;
        the car keeps its type's index as ``driver_type``."""
        mixture = _SPAWNING.get()
        if mixture is None:
            raise RuntimeError("MixedDriverVehicle: no driver mixture is being spawned (see install_driver_mix)")
        k = mixture.draw(road.np_random)
        vehicle = mixture.classes[k].create_random(road, **kwargs)
        vehicle.driver_type = k
        return vehicle


def _create_vehicles_mixed(env: Any, mixture: DriverDraw) -> None:
    """``type(env)._create_vehicles(env)`` (highway-env's own, with its subclass's changes) with each other car's
    class drawn from ``mixture``."""
    config = env.config
    given = config["other_vehicles_type"]
    token = _SPAWNING.set(mixture)
    config["other_vehicles_type"] = MIXED_DRIVER_PATH
    try:
        type(env)._create_vehicles(env)
    finally:
        config["other_vehicles_type"] = given
        _SPAWNING.reset(token)


def install_driver_mix(env: Any, mix: DriverMix) -> DriverDraw:
    """Make highway-env's ``env`` (``env.unwrapped``, a ``HighwayEnv``) draw each other car's type from ``mix`` at
    every reset, and keep the mixture as ``env.safelane_driver_mix`` (the snapshot reads it); returns it."""
    mixture = DriverDraw(mix)
    env._create_vehicles = functools.partial(_create_vehicles_mixed, env, mixture)
    env.safelane_driver_mix = mixture
    return mixture


__all__ = [
    "MIXED_DRIVER_PATH", "AggressiveDriver", "DriverDraw", "MixedDriverVehicle", "NormalDriver", "TimidDriver",
    "assumed_class", "driver_classes", "install_driver_mix",
]  # fmt: skip
