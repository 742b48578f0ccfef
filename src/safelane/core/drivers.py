"""Driver types and mixtures of them (``traffic.driver_mix``): each other car's driver drawn at spawn.

Names only, no simulator: :data:`DRIVER_TYPES` maps a type's name to the dotted path of its highway-env vehicle
class (the simulators resolve it), :class:`DriverMix` is a checked mixture and :func:`parse_driver_mix` reads one
from a configuration value. ``timid``, ``normal`` and ``aggressive`` are IDM + MOBIL drivers with Sunberg, Ho &
Kochenderfer's parameter sets (:mod:`safelane.sim.drivers`); the CamelCase names are highway-env's own classes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from safelane.core.errors import ConfigError

DRIVER_TYPES: dict[str, str] = {
    "timid": "safelane.sim.drivers.TimidDriver",
    "normal": "safelane.sim.drivers.NormalDriver",
    "aggressive": "safelane.sim.drivers.AggressiveDriver",
    "IDMVehicle": "highway_env.vehicle.behavior.IDMVehicle",
    "LinearVehicle": "highway_env.vehicle.behavior.LinearVehicle",
    "AggressiveVehicle": "highway_env.vehicle.behavior.AggressiveVehicle",
    "DefensiveVehicle": "highway_env.vehicle.behavior.DefensiveVehicle",
}
"""Every driver type a mixture may name, and the dotted path of its highway-env vehicle class."""

NAMED_MIXES: dict[str, tuple[tuple[str, float], ...]] = {
    "timid-normal-aggressive": (("timid", 1.0), ("normal", 1.0), ("aggressive", 1.0)),
}
"""Mixtures by name: (type, weight) pairs. ``timid-normal-aggressive``: Sunberg et al.'s three sets, equally likely
(their correlated generator draws the aggressiveness uniformly in [0, 1]; these are its ends and middle)."""

NO_MIX = "none"
"""``traffic.driver_mix``'s default: no mixture, every other car is ``env.other_vehicles_type``."""

ASSUMED_DRIVER = "IDMVehicle"
"""The driver the shield is told every car is when it does not see the types (``traffic.assumed_driver``): highway-env's
default driver, the one the safety model was derived for."""


@dataclass(frozen=True)
class DriverMix:
    """A mixture of driver types: each other car's type is drawn independently at spawn with probability
    ``weight / sum(weights)``, by highway-env's ``road.np_random.choice(len(types), p=probabilities)``.

    ``assumed``: the type whose parameters every drawn car's snapshot reports (``RoadSnapshot``'s driver fields: what
    the shield reads), so the shield does not see the drawn types; ``None``: each car's own (the shield sees them).
    """

    types: tuple[str, ...]
    weights: tuple[float, ...]
    assumed: str | None = ASSUMED_DRIVER

    @property
    def probabilities(self) -> np.ndarray:
        """(K,) float64: each type's probability, the weights over their sum (numpy's ``choice`` ``p``)."""
        w = np.asarray(self.weights, dtype=np.float64)
        return w / w.sum()

    @property
    def paths(self) -> tuple[str, ...]:
        """Each type's highway-env vehicle class, as a dotted path."""
        return tuple(DRIVER_TYPES[t] for t in self.types)


@dataclass(frozen=True)
class IdmParameters:
    """One IDM + MOBIL driver type's constants, highway-env's names (its ``IDMVehicle`` class attributes): what a
    belief over the type and the shields that read one need without importing a simulator. IDM's exponent δ is no
    type's: highway-env draws it per car (the snapshot's ``idm_delta``)."""

    comfort_acc_max: float
    """[m/s²] ``COMFORT_ACC_MAX``: IDM's a (the snapshot's ``accel_max`` and ``idm_comfort_acc``)."""
    comfort_acc_min: float
    """[m/s²] < 0, ``COMFORT_ACC_MIN``: IDM's −b (``idm_comfort_dec``)."""
    distance_wanted: float
    """[m] ``DISTANCE_WANTED``, centre to centre: s₀ + a car's length (``idm_distance_wanted``)."""
    time_wanted: float
    """[s] ``TIME_WANTED``: IDM's T (``idm_time_wanted``)."""
    politeness: float
    """MOBIL's p (``POLITENESS``: ``politeness``)."""
    max_braking_imposed: float
    """[m/s²] > 0, ``LANE_CHANGE_MAX_BRAKING_IMPOSED``: MOBIL's b_safe (``max_braking_imposed``)."""
    min_acc_gain: float
    """[m/s²] ``LANE_CHANGE_MIN_ACC_GAIN``: MOBIL's a_thr (not in the snapshot)."""
    acc_max: float = 6.0
    """[m/s²] ``ACC_MAX``: the hardest the car brakes or speeds up (``brake_max``)."""


_CAR_LENGTH = 5.0
"""[m] highway-env's ``Vehicle.LENGTH``: its ``DISTANCE_WANTED`` is a jam distance plus it."""

IDM_PARAMETERS: dict[str, IdmParameters] = {
    "timid": IdmParameters(0.8, -1.0, 4.0 + _CAR_LENGTH, 2.0, 1.0, 1.0, math.nextafter(0.2, math.inf)),
    "normal": IdmParameters(1.4, -2.0, 2.0 + _CAR_LENGTH, 1.5, 0.5, 2.0, math.nextafter(0.1, math.inf)),
    "aggressive": IdmParameters(2.0, -3.0, 0.0 + _CAR_LENGTH, 1.0, 0.0, 3.0, math.nextafter(0.0, math.inf)),
    "IDMVehicle": IdmParameters(3.0, -5.0, 5.0 + _CAR_LENGTH, 1.5, 0.0, 2.0, 0.2),
}
"""The IDM + MOBIL driver types of :data:`DRIVER_TYPES` and their constants, the same numbers as their highway-env
classes (:mod:`safelane.sim.drivers`, highway-env's ``IDMVehicle``; a test compares them). The linear-model drivers
have none: their gains are drawn per car."""


def idm_parameters(mix: DriverMix, key: str = "traffic.driver_mix") -> tuple[IdmParameters, ...]:
    """Each type's :class:`IdmParameters`, in the mixture's order; a type without them (a linear-model driver) is a
    one-line :class:`ConfigError` naming ``key`` and the allowed types."""
    for name in mix.types:
        if name not in IDM_PARAMETERS:
            raise ConfigError(
                f"{key}: type {name!r} has no fixed IDM constants (a linear-model driver draws its gains per car) "
                f"for a belief or the types' worst case; allowed: {', '.join(IDM_PARAMETERS)}"
            )
    return tuple(IDM_PARAMETERS[name] for name in mix.types)


def least_min_acc_gain(mix: DriverMix | None, default: float) -> float:
    """[m/s²] The least MOBIL incentive threshold (``LANE_CHANGE_MIN_ACC_GAIN``) among ``default`` and the mixture's
    types with fixed constants: the threshold a rule must assume when it does not know which car is which type."""
    if mix is None:
        return default
    return min([default, *(IDM_PARAMETERS[name].min_acc_gain for name in mix.types if name in IDM_PARAMETERS)])


def _allowed_types() -> str:
    return ", ".join(DRIVER_TYPES)


def check_driver_type(name: Any, key: str) -> str:
    """``name`` if it is a :data:`DRIVER_TYPES` name, else a one-line :class:`ConfigError` naming ``key``."""
    if not isinstance(name, str) or name not in DRIVER_TYPES:
        raise ConfigError(f"{key}: unknown driver type {name!r}; allowed: {_allowed_types()}")
    return name


def parse_driver_mix(
    value: Any, key: str = "traffic.driver_mix", assumed: str | None = ASSUMED_DRIVER
) -> DriverMix | None:
    """The :class:`DriverMix` of a configuration value: a :data:`NAMED_MIXES` name, or a list of
    ``{type: NAME, weight: W}`` (each type once, weights finite and >= 0 with a positive sum); :data:`NO_MIX`: None.
    Bad input is a one-line :class:`ConfigError` naming the field and the allowed values."""
    names = ", ".join((NO_MIX, *NAMED_MIXES))
    if isinstance(value, str):
        if value == NO_MIX:
            return None
        if value not in NAMED_MIXES:
            raise ConfigError(f"{key}: unknown mixture {value!r}; allowed: {names} or a list of {{type, weight}}")
        pairs = NAMED_MIXES[value]
        return DriverMix(tuple(t for t, _ in pairs), tuple(float(w) for _, w in pairs), assumed)
    if not isinstance(value, list | tuple) or not value:
        raise ConfigError(f"{key}: expected a mixture name ({names}) or a non-empty list of {{type, weight}}, "
                          f"got {value!r}")  # fmt: skip
    types: list[str] = []
    weights: list[float] = []
    for i, entry in enumerate(value):
        where = f"{key}[{i}]"
        if not isinstance(entry, dict) or set(entry) != {"type", "weight"}:
            raise ConfigError(f"{where}: expected {{type: NAME, weight: NUMBER}} (keys type, weight), got {entry!r}")
        name = check_driver_type(entry["type"], f"{where}.type")
        if name in types:
            raise ConfigError(f"{where}.type: {name!r} appears twice; allowed: each type once")
        weight = entry["weight"]
        number = isinstance(weight, int | float) and not isinstance(weight, bool)
        if not number or not math.isfinite(weight) or weight < 0:
            raise ConfigError(f"{where}.weight: must be a finite number >= 0, got {weight!r}")
        types.append(name)
        weights.append(float(weight))
    if not sum(weights) > 0:
        raise ConfigError(f"{key}: the weights sum to {sum(weights)!r}; allowed: weights >= 0 with a positive sum")
    return DriverMix(tuple(types), tuple(weights), assumed)
