"""The driver arrays the one-decision rule reads, as the worst case over the driver types each car may be.

The rule reads every car's driver constants from the snapshot (``DRIVER_FIELDS``). In traffic drawn from a mixture
of types (``traffic.driver_mix``) the shields of the hidden-types question differ only in which types each car may
be: ``robust`` every type of the mixture, ``omniscient`` the car's true type, ``belief`` the types whose posterior
exceeds ε. :func:`worst_case_drivers` writes, for each car, one set of constants that is at least as bad for the ego
as each allowed type's, field by field, and the rule reads them as it reads any car's. Pure maths: no simulator.

Which way is worse, field by field (:func:`worst_case_drivers`'s table); one allowed type gives its own constants
exactly. The same field can enter the rule in several roles, and a per-field choice is the worst in every role only
where the roles agree: where they do not, the choice follows the role the rule's safety rests on, said below.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from safelane.core.drivers import IdmParameters
from safelane.core.snapshot import RoadSnapshot


def worst_case_drivers(
    snap: RoadSnapshot, types: tuple[IdmParameters, ...], allowed: np.ndarray, cars: np.ndarray
) -> RoadSnapshot:
    """``snap`` with the driver arrays of the rows ``cars`` (snapshot indices) replaced by the worst case over the
    types ``allowed[row]`` ((n, K) bool, ``types`` the mixture's K types; each row of ``cars`` allows at least one);
    the other rows, and every other field, as they are. Per field, over the allowed types:

    * ``brake_max`` = max ``ACC_MAX``: the hardest a car ahead may brake (every set: 6 m/s²);
    * ``accel_max`` = max ``COMFORT_ACC_MAX``: the hardest a car may speed up — a follower closing in, a cut-in car
      taken at its fastest (the rule's reach of a car is between braking and accelerating at these limits);
    * ``can_change_lane`` = True: every IDM type changes lanes by MOBIL;
    * ``idm_delta``: the car's own (highway-env draws δ per car, whatever the type);
    * ``max_braking_imposed`` = max b_safe: MOBIL lets a car cut in wherever the ego's predicted braking is at most
      b_safe, so the largest lets in the most cut-ins;
    * ``idm_distance_wanted`` = min, ``idm_time_wanted`` = min: a smaller desired gap d* lets a cut-in happen closer
      (MOBIL's criterion ``a ≥ −b_safe``, ``a = free − a·(d*/d)²``) and a follower brake later for the ego;
    * ``idm_comfort_acc`` = min a: MOBIL's room ``(free + b_safe)/a = 1 − (v/v₀)^δ + b_safe/a`` grows as a falls
      (more cut-ins), and a follower that must brake for the ego (``d* > d``) brakes ``a·((d*/d)² − 1)``, less with a
      smaller a. It is the optimistic side for a follower's free-road term ``a·(1 − (d*/d)²)`` while ``d* < d``:
      there the rule's follower bound (``accel_max``, the largest) is what keeps a closing car covered;
    * ``idm_comfort_dec``: the rule reads it only in ``√(a·b)`` (``ab = −a·dec``), whose largest value shrinks d*
      for a car slower than the ego behind it (a cut-in permitted closer) and a follower faster than the ego (it
      brakes later): ``dec = −max(a·b) / min(a)``, so that ``−a·dec`` is the largest product of the allowed types
      with a = their least a (a type's own ``COMFORT_ACC_MIN`` when one type has both);
    * the linear model's gains: NaN (IDM drivers).

    Two MOBIL constants the rule takes for every car as highway-env's ``IDMVehicle``'s (the gain threshold 0.2 m/s²
    and politeness 0, :mod:`safelane.safety.world`) are not in the snapshot and not changed here.
    """
    if cars.size == 0:
        return snap
    a = np.array([t.comfort_acc_max for t in types])
    b = np.array([-t.comfort_acc_min for t in types])
    ab = a * b
    table = {
        "acc_max": np.array([t.acc_max for t in types]),
        "d0": np.array([t.distance_wanted for t in types]),
        "tw": np.array([t.time_wanted for t in types]),
        "mbi": np.array([t.max_braking_imposed for t in types]),
    }
    mask = np.asarray(allowed, dtype=bool)[cars]
    if not mask.any(axis=1).all():
        raise ValueError("worst_case_drivers: every car needs at least one allowed type")

    def most(values: np.ndarray) -> np.ndarray:
        return np.where(mask, values[None, :], -np.inf).max(axis=1)

    def least(values: np.ndarray) -> np.ndarray:
        return np.where(mask, values[None, :], np.inf).min(axis=1)

    a_min = least(a)
    ab_max = most(ab)
    # The type with the least a, and whether it also has the largest a·b: then its own −b, bit for bit.
    k_min = np.argmin(np.where(mask, a[None, :], np.inf), axis=1)
    own = ab[k_min] == ab_max
    dec = np.where(own, -b[k_min], -ab_max / a_min)
    arrays = {name: np.array(getattr(snap, name), copy=True) for name in
              ("brake_max", "accel_max", "can_change_lane", "idm_comfort_acc", "idm_comfort_dec",
               "idm_distance_wanted", "idm_time_wanted", "max_braking_imposed", "linear_speed_gain",
               "linear_speed_difference_gain", "linear_distance_gain")}  # fmt: skip
    arrays["brake_max"][cars] = most(table["acc_max"])
    arrays["accel_max"][cars] = most(a)
    arrays["can_change_lane"][cars] = True
    arrays["idm_comfort_acc"][cars] = a_min
    arrays["idm_comfort_dec"][cars] = dec
    arrays["idm_distance_wanted"][cars] = least(table["d0"])
    arrays["idm_time_wanted"][cars] = least(table["tw"])
    arrays["max_braking_imposed"][cars] = most(table["mbi"])
    for name in ("linear_speed_gain", "linear_speed_difference_gain", "linear_distance_gain"):
        arrays[name][cars] = np.nan
    return dataclasses.replace(snap, **arrays)


def drawn_cars(snap: RoadSnapshot) -> np.ndarray:
    """The snapshot indices of the other vehicles (the cars a mixture's types are drawn for; not the ego, not the
    static objects)."""
    return snap.others(vehicles_only=True)


def every_type(snap: RoadSnapshot, weights: np.ndarray) -> np.ndarray:
    """(n, K) bool: every car may be any type of positive weight (``weights``: (K,), the mixture's): the robust
    shield's sets."""
    return np.broadcast_to(np.asarray(weights) > 0, (snap.n, len(weights))).copy()


def true_type(snap: RoadSnapshot, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, K) bool: each drawn car's own type only (the omniscient shield's sets, read from the snapshot's
    ``driver_type``), and the snapshot indices of the cars that have one (``driver_type`` ≥ 0)."""
    types = snap.driver_type if snap.driver_type is not None else np.full(snap.n, -1)
    cars = np.flatnonzero(types >= 0)
    allowed = np.zeros((snap.n, k), dtype=bool)
    allowed[cars, types[cars]] = True
    return allowed, cars


TYPE_MODES: tuple[str, ...] = ("omniscient", "belief")
"""The shield modes that read a driver mixture's types: the one-decision robust rule on the sets above."""

__all__ = ["TYPE_MODES", "drawn_cars", "every_type", "true_type", "worst_case_drivers"]
