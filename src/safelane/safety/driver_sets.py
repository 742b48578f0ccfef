"""The driver arrays the one-decision rule reads, per type, for the shields that judge a mixture of driver types.

The rule reads every car's driver constants from the snapshot (``DRIVER_FIELDS``). In traffic drawn from a mixture
of types (``traffic.driver_mix``) the shields of the hidden-types question differ only in which types each car may
be: ``robust`` every type of the mixture, ``omniscient`` the car's true type, ``belief`` the types whose posterior
exceeds ε. Pure maths: no simulator.

**Why not one set of constants per car.** An earlier reading wrote, for each car, the most adverse value of each
field over its types (the largest b_safe, the least a, T, s₀, the largest a·b) and judged that chimera. A field
enters the rule in several roles that disagree on which way is adverse, so the chimera was looser than some type
in some states (the robust shield fell back less often than the omniscient one): the least comfort acceleration a
is the optimistic side of an IDM follower's free-road term (the car right behind the ego closes in at ``a·(1 −
(d*/d)²)``, so an aggressive follower's a = 2 m/s² outruns the chimera's 0.8) and of MOBIL's incentive (the gain
``a·((d*/d)²_leader − (d*/d)²_ego)`` a car needs to turn in behind the ego scales with a), and the largest a·b the
optimistic side of IDM's desired gap ``d* = s₀ + vT + v·Δv/(2√(ab))`` whenever the car is faster than the one it
would follow (Δv < 0: the gap d* shrinks as √(ab) falls, so a timid car's 0.8 m/s² lets it cut in closer than the
chimera's 6). No single set of constants is below every type in every role.

**What the rule reads instead** (:func:`type_readings`): one snapshot per type k — every car that may be k read as
k with k's own constants, every other car as its most likely type — and the rule's worst-case gaps of each reading
combined per action and fallback by their minimum (:func:`safelane.safety.one_decision.over_types.evaluate_readings`).
Every conflict of the rule is one car's, so the minimum over the readings is the minimum over every (car, type),
and the joint fallback (one fallback for every conflict at once) is judged against every *mixed* assignment of
types to cars, not only the K in which all cars share one type. The rule's one term that reads two cars — MOBIL's
incentive to turn in behind the ego, its leader's reach at ``accel_max`` — is made per car by giving every car in
every reading ``accel_max`` = the largest a over its allowed types, which is the adverse side of each of its roles
(a follower closing in, a cut-in car at its fastest, the speed range a MOBIL test is taken over).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from safelane.core.drivers import IdmParameters
from safelane.core.snapshot import RoadSnapshot, freeze

_FIELDS = ("brake_max", "accel_max", "can_change_lane", "idm_comfort_acc", "idm_comfort_dec", "idm_distance_wanted",
           "idm_time_wanted", "max_braking_imposed", "linear_speed_gain", "linear_speed_difference_gain",
           "linear_distance_gain", "politeness")  # fmt: skip
"""The driver arrays a reading writes (``idm_delta`` stays the car's own: highway-env draws δ per car)."""


def type_reading(
    snap: RoadSnapshot, types: tuple[IdmParameters, ...], kinds: np.ndarray, cars: np.ndarray, accel: np.ndarray
) -> RoadSnapshot:
    """``snap`` with the rows ``cars`` (snapshot indices) read as the types ``kinds`` (one index into ``types`` per
    row of ``cars``): each row gets its type's constants (``ACC_MAX`` as ``brake_max``, IDM's a, −b, s₀ + length, T,
    MOBIL's b_safe and politeness, IDM's formula, a lane-change rule), but ``accel_max`` = ``accel`` [m/s²] (per
    row of ``cars``) and its own δ; the other rows and fields as they are."""
    if cars.size == 0:
        return snap
    kinds = np.asarray(kinds, dtype=np.int64)
    arrays = {name: np.array(getattr(snap, name), copy=True) for name in _FIELDS}
    arrays["brake_max"][cars] = np.array([t.acc_max for t in types])[kinds]
    arrays["accel_max"][cars] = accel
    arrays["can_change_lane"][cars] = True
    arrays["idm_comfort_acc"][cars] = np.array([t.comfort_acc_max for t in types])[kinds]
    arrays["idm_comfort_dec"][cars] = np.array([t.comfort_acc_min for t in types])[kinds]
    arrays["idm_distance_wanted"][cars] = np.array([t.distance_wanted for t in types])[kinds]
    arrays["idm_time_wanted"][cars] = np.array([t.time_wanted for t in types])[kinds]
    arrays["max_braking_imposed"][cars] = np.array([t.max_braking_imposed for t in types])[kinds]
    arrays["politeness"][cars] = np.array([t.politeness for t in types])[kinds]
    for name in ("linear_speed_gain", "linear_speed_difference_gain", "linear_distance_gain"):
        arrays[name][cars] = np.nan
    freeze(arrays.values())  # read-only as the snapshot's own: the rule's kernels compile once for both
    return dataclasses.replace(snap, **arrays)


def type_readings(
    snap: RoadSnapshot, types: tuple[IdmParameters, ...], allowed: np.ndarray, cars: np.ndarray, weight: np.ndarray
) -> tuple[list[RoadSnapshot], RoadSnapshot]:
    """The readings of ``snap`` the rule judges together, and the most likely one (what the fallback's forecast
    reads).

    ``allowed``: (n, K) bool, the types each row may be (``types`` the mixture's K; each row of ``cars``, the drawn
    cars' snapshot indices, allows at least one); ``weight``: (n, K), how likely each type is (the mixture's weights,
    a posterior): a car's most likely type is its allowed type of largest weight, the first on ties. One reading per
    type k that some car may be among others (module docstring; cars that may be one type only are that type in
    every reading); a single reading when every car may be one type only (the omniscient shield's). Every car's
    ``accel_max`` is the largest a of its allowed types in every reading; in the most likely one, its type's own.
    """
    mask = np.asarray(allowed, dtype=bool)[cars]
    if not mask.any(axis=1).all():
        raise ValueError("type_readings: every car needs at least one allowed type")
    a = np.array([t.comfort_acc_max for t in types])
    likely = np.argmax(np.where(mask, np.asarray(weight, dtype=float)[cars], -np.inf), axis=1)
    accel = np.where(mask, a[None, :], -np.inf).max(axis=1)
    several = mask.sum(axis=1) > 1
    kinds = [k for k in range(len(types)) if (mask[:, k] & several).any()]
    readings = [type_reading(snap, types, np.where(mask[:, k], k, likely), cars, accel) for k in kinds]
    most_likely = type_reading(snap, types, likely, cars, a[likely])
    if not readings:  # every car one type: the most likely reading is the only one (and its a is the car's own)
        readings = [most_likely]
    return readings, most_likely


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

__all__ = ["TYPE_MODES", "drawn_cars", "every_type", "true_type", "type_reading", "type_readings"]
