"""A belief over each car's hidden driver type: a per-car Bayesian filter over the K types of a mixture.

The traffic's cars draw their driver at spawn from a mixture (``traffic.driver_mix``, :mod:`safelane.core.drivers`):
IDM + MOBIL drivers that differ in their constants (a, b, T, s₀, b_safe, …). :class:`BeliefFilter` keeps, for every
other vehicle of the snapshot (by its index, the simulators' order, which stays fixed within an episode), the
posterior probability of each type given the motion observed so far:

* **prior**: the mixture's weights (a car first seen starts there);
* **likelihood of one decision step** (snapshot t → t + Δ): the car's observed speed change over the step against
  each type's prediction: highway-env's ``IDMVehicle.acceleration`` with the type's constants (and the car's own
  exponent δ and set-point, which the snapshot shows whatever the type), integrated frame by frame as
  ``IDMVehicle.act`` and ``Vehicle.step`` do (``a`` clipped to ±``ACC_MAX``; ``x += v·dt``, then ``v += a·dt``), its
  leader (the nearest body ahead within half a lane + 1 m of its lane's centre, highway-env's ``neighbour_vehicles``)
  moving at the constant acceleration its own observed speed change gives. The residual, the observed minus the
  predicted mean acceleration over the step [m/s²], is Gaussian with standard deviation ``sigma`` (:data:`SIGMA`):
  ``log L_k = −½ (r_k / σ)²``. σ stands for what the model leaves out (the leader's acceleration is not constant
  within the step, the projected speeds of a car that turns), and sets how fast the posterior concentrates;
* **uninformative steps** (the likelihood is flat, the posterior kept): the car crashed, is changing lanes (its lane
  and target lane differ, or its lane changed), it or its leader heads across the lane by more than
  :data:`HEADING_STRAIGHT` at either end of the step (IDM's approach rate is projected on the car's own direction),
  its leader changed between the two snapshots or crashed — where the frame-by-frame model above is not the car's
  (MOBIL's lane changes are not used as evidence).

Two engines give the same bits (a test checks it): :func:`update_reference`, Python over numpy arrays with
``math``'s libm calls, and :func:`update_compiled`, the same arithmetic in numba. Pure maths: no simulator.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import numpy as np
from numba import njit

from safelane.core.drivers import DriverMix, IdmParameters, idm_parameters
from safelane.core.snapshot import RoadSnapshot

SIGMA = 0.2
"""[m/s²] The default standard deviation of the residual of a car's mean acceleration over one decision step
(observed minus the type's prediction). Measured on the ``hidden-types`` preset (docs/research/belief-calibration.md):
0.1 is better calibrated but rules a car's true type out (posterior ≤ 0.01) in 4 × 10⁻⁵ of car-decisions; 0.2 errs
on the cautious side (above 0.4 the true type is more frequent than predicted) and, with :data:`HEADING_STRAIGHT`,
ruled it out in none of 300 episodes' car-decisions."""

HEADING_STRAIGHT = 0.05
"""[rad] A step is evidence only if the car and its leader head along their lanes within this at both of its ends.
IDM's desired gap reads the approach rate projected on the car's own direction (``Δv = v − v_leader·cos(h_leader −
h)``), which the filter's model along the lane leaves out: a car that has just crossed into a lane still turns back
for about a second (0.2 rad two frames after its lane switched) and, behind a close leader, brakes up to 2 m/s²
harder than the model of its own type predicts, enough at σ = 0.2 to rule its true type out for good. Measured in
docs/research/belief-calibration.md."""

LANE_MARGIN = 1.0
"""[m] highway-env's ``neighbour_vehicles``: a body is on a lane within half its width plus this of its centre."""

LANE_START = -5.0
"""[m] highway-env's ``AbstractLane.on_lane`` also asks ``-Vehicle.LENGTH <= longitudinal``: a body more than a car's
length (5 m) before the lane's start is on no lane, so no car follows it. ``traffic.vehicles_behind`` places cars
there (hundreds of metres behind the ego, which starts near the road's beginning): a car right behind one of them
follows the first car ahead that is on the lane, tens of metres further. Read as the leader, the close one made
every type's prediction miss by metres per second squared, and the type that missed least was certain within two
steps (a ``normal`` car read as ``timid`` at posterior 1.000 for a whole episode)."""

NOT_ZERO = 1e-2
"""highway-env's ``utils.not_zero`` threshold."""

BeliefEngine = Literal["compiled", "numpy"]

_A, _B, _D0, _T, _ACC_MAX = range(5)


def type_table(types: tuple[IdmParameters, ...]) -> np.ndarray:
    """(K, 5) float64: each type's a [m/s²], b [m/s²] (> 0), DISTANCE_WANTED [m], TIME_WANTED [s], ACC_MAX
    [m/s²]: the columns the kernels read."""
    return np.array(
        [[t.comfort_acc_max, -t.comfort_acc_min, t.distance_wanted, t.time_wanted, t.acc_max] for t in types],
        dtype=np.float64,
    )


class Observation:
    """What the filter reads of one snapshot, as arrays over its bodies: ``x`` [m] along the road, ``y`` [m] across
    it, ``v`` [m/s] speed, ``lane``, ``target_lane``, ``crashed``, ``tracked`` (the other vehicles), ``target``
    [m/s] the set-point clipped to [0, the speed limit], ``delta`` (IDM's δ), ``heading`` [rad] relative to the
    lane's."""

    def __init__(self, snap: RoadSnapshot) -> None:
        rel = snap.position - snap.lane_origin
        self.x = np.ascontiguousarray(rel @ snap.lane_direction, dtype=np.float64)
        self.y = np.ascontiguousarray(rel @ snap.lane_lateral, dtype=np.float64)
        self.v = np.ascontiguousarray(snap.speed, dtype=np.float64)
        self.lane = np.ascontiguousarray(snap.lane, dtype=np.int64)
        self.target_lane = np.ascontiguousarray(snap.target_lane, dtype=np.int64)
        self.crashed = np.ascontiguousarray(snap.crashed, dtype=np.bool_)
        tracked = snap.is_vehicle.astype(np.bool_)
        tracked[snap.ego] = False
        self.tracked = tracked
        target = np.where(np.isfinite(snap.target_speed), snap.target_speed, 0.0)
        self.target = np.ascontiguousarray(np.clip(target, 0.0, snap.speed_limit), dtype=np.float64)
        self.delta = np.ascontiguousarray(snap.idm_delta, dtype=np.float64)
        self.heading = np.ascontiguousarray(snap.heading - snap.lane_heading, dtype=np.float64)
        self.lane_width = float(snap.lane_width)
        self.frames = int(snap.simulation_frequency // snap.policy_frequency)
        self.dt = 1.0 / float(snap.simulation_frequency)

    @property
    def n(self) -> int:
        """Number of bodies."""
        return int(self.x.shape[0])


# --- the numpy reference ---------------------------------------------------------------------------------------


def _not_zero(x: float) -> float:
    if abs(x) > NOT_ZERO:
        return x
    return NOT_ZERO if x >= 0.0 else -NOT_ZERO


def leader_reference(x: np.ndarray, y: np.ndarray, i: int, lane: int, lane_width: float) -> int:
    """The body nearest ahead of body ``i`` (x ≥ its x) on lane ``lane`` (within half a lane + 1 m of its centre, at
    most a car's length before the lane's start: :data:`LANE_START`); -1: none."""
    centre = lane * lane_width
    best, best_x = -1, math.inf
    for j in range(x.shape[0]):
        if j == i or not abs(y[j] - centre) <= 0.5 * lane_width + LANE_MARGIN or not x[j] >= LANE_START:
            continue
        if x[j] >= x[i] and x[j] < best_x:
            best, best_x = j, float(x[j])
    return best


def step_log_likelihood_reference(
    before: Observation, after: Observation, i: int, table: np.ndarray, inv_two_sigma2: float,
    straight: float = HEADING_STRAIGHT,
) -> np.ndarray | None:  # fmt: skip
    """(K,) ``log L_k`` of car ``i``'s step from ``before`` to ``after`` under each type (module docstring); None
    when the step is uninformative (``straight`` [rad]: :data:`HEADING_STRAIGHT`)."""
    if before.crashed[i] or after.crashed[i]:
        return None
    lane = int(before.lane[i])
    if before.target_lane[i] != lane or after.lane[i] != lane or after.target_lane[i] != lane:
        return None
    lead = leader_reference(before.x, before.y, i, lane, before.lane_width)
    if lead != leader_reference(after.x, after.y, i, lane, after.lane_width):
        return None
    if lead >= 0 and (before.crashed[lead] or after.crashed[lead]):
        return None
    for j in (i, lead) if lead >= 0 else (i,):
        if not (abs(before.heading[j]) <= straight and abs(after.heading[j]) <= straight):
            return None
    frames, dt = before.frames, before.dt
    period = frames * dt
    lead_acc = (after.v[lead] - before.v[lead]) / period if lead >= 0 else 0.0
    target = abs(_not_zero(float(before.target[i])))
    delta = float(before.delta[i])
    out = np.empty(table.shape[0])
    for k in range(table.shape[0]):
        a, b, d0, tw, acc_max = (float(c) for c in table[k])
        two_sqrt_ab = 2.0 * math.sqrt(a * b)
        xf, vf = float(before.x[i]), float(before.v[i])
        xl = float(before.x[lead]) if lead >= 0 else 0.0
        vl = float(before.v[lead]) if lead >= 0 else 0.0
        for _ in range(frames):
            sp = vf if vf > 0.0 else 0.0
            acc = a * (1.0 - math.pow(sp / target, delta))
            if lead >= 0:
                d_star = d0 + vf * tw + vf * (vf - vl) / two_sqrt_ab
                acc -= a * math.pow(d_star / _not_zero(xl - xf), 2.0)
            acc = min(max(acc, -acc_max), acc_max)
            xf += vf * dt
            vf += acc * dt
            xl += vl * dt
            vl += lead_acc * dt
        r = (float(after.v[i]) - vf) / period
        out[k] = -(r * r) * inv_two_sigma2
    return out


def _normalise_reference(row: np.ndarray) -> None:
    """Log-probabilities ``row`` normalised in place (log-sum-exp)."""
    top = -math.inf
    for k in range(row.shape[0]):
        top = max(top, float(row[k]))
    total = 0.0
    for k in range(row.shape[0]):
        total += math.exp(float(row[k]) - top)
    shift = top + math.log(total)
    for k in range(row.shape[0]):
        row[k] = row[k] - shift


def update_reference(
    log_post: np.ndarray, informative: np.ndarray, before: Observation, after: Observation, table: np.ndarray,
    inv_two_sigma2: float, straight: float = HEADING_STRAIGHT,
) -> None:  # fmt: skip
    """One Bayes step for every car tracked in both observations (rows ``< min(n_before, n_after)``), in place on
    ``log_post`` (n, K) and on ``informative`` (n,): the count of informative steps per car."""
    n = min(before.n, after.n, log_post.shape[0])
    for i in range(n):
        if not (before.tracked[i] and after.tracked[i]):
            continue
        ll = step_log_likelihood_reference(before, after, i, table, inv_two_sigma2, straight)
        if ll is None:
            continue
        best = -math.inf
        for k in range(table.shape[0]):
            best = max(best, float(ll[k]))
        for k in range(table.shape[0]):  # less the best type's: a residual common to all types cancels exactly
            log_post[i, k] = log_post[i, k] + (ll[k] - best)
        _normalise_reference(log_post[i])
        informative[i] += 1


# --- the compiled engine: the same arithmetic in numba -------------------------------------------------------


@njit(cache=True, error_model="numpy", inline="always")
def _nz(x):
    if abs(x) > NOT_ZERO:
        return x
    return NOT_ZERO if x >= 0.0 else -NOT_ZERO


@njit(cache=True, error_model="numpy")
def _leader(x, y, i, lane, lane_width):
    centre = lane * lane_width
    best = -1
    best_x = math.inf
    for j in range(x.shape[0]):
        if j == i or not abs(y[j] - centre) <= 0.5 * lane_width + LANE_MARGIN or not x[j] >= LANE_START:
            continue
        if x[j] >= x[i] and x[j] < best_x:
            best = j
            best_x = x[j]
    return best


@njit(cache=True, error_model="numpy")
def _update_kernel(
    log_post, informative, x0, y0, v0, lane0, tl0, crashed0, tracked0, target0, delta0, h0,
    x1, y1, v1, lane1, tl1, crashed1, tracked1, h1, lane_width, frames, dt, table, inv_two_sigma2, straight,
):  # fmt: skip
    n = min(x0.shape[0], x1.shape[0], log_post.shape[0])
    n_types = table.shape[0]
    period = frames * dt
    ll = np.empty(n_types)
    for i in range(n):
        if not (tracked0[i] and tracked1[i]) or crashed0[i] or crashed1[i]:
            continue
        lane = lane0[i]
        if tl0[i] != lane or lane1[i] != lane or tl1[i] != lane:
            continue
        lead = _leader(x0, y0, i, lane, lane_width)
        if lead != _leader(x1, y1, i, lane, lane_width):
            continue
        if lead >= 0 and (crashed0[lead] or crashed1[lead]):
            continue
        if not (abs(h0[i]) <= straight and abs(h1[i]) <= straight):
            continue
        if lead >= 0 and not (abs(h0[lead]) <= straight and abs(h1[lead]) <= straight):
            continue
        lead_acc = (v1[lead] - v0[lead]) / period if lead >= 0 else 0.0
        target = abs(_nz(target0[i]))
        delta = delta0[i]
        for k in range(n_types):
            a = table[k, 0]
            b = table[k, 1]
            d0 = table[k, 2]
            tw = table[k, 3]
            acc_max = table[k, 4]
            two_sqrt_ab = 2.0 * math.sqrt(a * b)
            xf = x0[i]
            vf = v0[i]
            xl = x0[lead] if lead >= 0 else 0.0
            vl = v0[lead] if lead >= 0 else 0.0
            for _ in range(frames):
                sp = vf if vf > 0.0 else 0.0
                acc = a * (1.0 - math.pow(sp / target, delta))
                if lead >= 0:
                    d_star = d0 + vf * tw + vf * (vf - vl) / two_sqrt_ab
                    acc -= a * math.pow(d_star / _nz(xl - xf), 2.0)
                acc = min(max(acc, -acc_max), acc_max)
                xf += vf * dt
                vf += acc * dt
                xl += vl * dt
                vl += lead_acc * dt
            r = (v1[i] - vf) / period
            ll[k] = -(r * r) * inv_two_sigma2
        best = -math.inf
        for k in range(n_types):
            best = max(best, ll[k])
        top = -math.inf
        for k in range(n_types):
            log_post[i, k] = log_post[i, k] + (ll[k] - best)
            top = max(top, log_post[i, k])
        total = 0.0
        for k in range(n_types):
            total += math.exp(log_post[i, k] - top)
        shift = top + math.log(total)
        for k in range(n_types):
            log_post[i, k] = log_post[i, k] - shift
        informative[i] += 1


def update_compiled(
    log_post: np.ndarray, informative: np.ndarray, before: Observation, after: Observation, table: np.ndarray,
    inv_two_sigma2: float, straight: float = HEADING_STRAIGHT,
) -> None:  # fmt: skip
    """:func:`update_reference` in numba: the same bits."""
    b, a = before, after
    _update_kernel(log_post, informative, b.x, b.y, b.v, b.lane, b.target_lane, b.crashed, b.tracked, b.target,
                   b.delta, b.heading, a.x, a.y, a.v, a.lane, a.target_lane, a.crashed, a.tracked, a.heading,
                   b.lane_width, b.frames, b.dt, table, inv_two_sigma2, float(straight))  # fmt: skip


# --- the filter ----------------------------------------------------------------------------------------------


class BeliefFilter:
    """Per-car posterior over a mixture's driver types from the observed motion (module docstring).

    ``mix``: the mixture (its types IDM + MOBIL drivers with fixed constants, :data:`~safelane.core.drivers.
    IDM_PARAMETERS`; else a one-line ``ConfigError``); ``sigma`` [m/s²] > 0: the residual's standard deviation;
    ``engine``: ``"compiled"`` or ``"numpy"`` (the same posteriors). Cars are the snapshot's bodies by index; rows of
    bodies that are not tracked (the ego, static objects) stay at the prior. A snapshot with more bodies than the
    last one starts the new ones at the prior; one with fewer drops the rows past its end.
    """

    def __init__(self, mix: DriverMix, sigma: float = SIGMA, engine: BeliefEngine = "compiled") -> None:
        if not (isinstance(sigma, int | float) and math.isfinite(sigma) and sigma > 0):
            raise ValueError(f"belief sigma: must be a finite number > 0 [m/s²] (got {sigma!r})")
        if engine not in ("compiled", "numpy"):
            raise ValueError(f"belief engine: {engine!r}; allowed: compiled, numpy")
        self.mix = mix
        self.types = idm_parameters(mix)
        self.table = type_table(self.types)
        self.sigma = float(sigma)
        self.engine: BeliefEngine = engine
        with np.errstate(divide="ignore"):  # a type of weight 0 has prior log 0 = −inf: never believed
            self.log_prior = np.log(mix.probabilities)
        self.log_post = np.zeros((0, len(self.types)))
        self.informative = np.zeros(0, dtype=np.int64)
        self.steps = np.zeros(0, dtype=np.int64)
        self._last: Observation | None = None

    @property
    def k(self) -> int:
        """Number of types."""
        return int(self.table.shape[0])

    def _resize(self, n: int) -> None:
        """Rows for ``n`` bodies: the new ones at the prior, those past ``n`` dropped."""
        old = self.log_post.shape[0]
        if n > old:
            self.log_post = np.vstack([self.log_post, np.tile(self.log_prior, (n - old, 1))])
            self.informative = np.concatenate([self.informative, np.zeros(n - old, dtype=np.int64)])
            self.steps = np.concatenate([self.steps, np.zeros(n - old, dtype=np.int64)])
        elif n < old:
            self.log_post, self.informative, self.steps = self.log_post[:n], self.informative[:n], self.steps[:n]

    def reset(self, snap: RoadSnapshot) -> np.ndarray:
        """Start an episode at ``snap``: every car at the prior; returns the posterior (n, K)."""
        self.log_post = np.zeros((0, self.k))
        self.informative = np.zeros(0, dtype=np.int64)
        self.steps = np.zeros(0, dtype=np.int64)
        self._resize(snap.n)
        self._last = Observation(snap)
        return self.posterior

    def update(self, snap: RoadSnapshot) -> np.ndarray:
        """One decision step observed, from the last snapshot to ``snap``; returns the posterior (n, K)."""
        if self._last is None:
            return self.reset(snap)
        after = Observation(snap)
        n = min(self._last.n, after.n)
        self._resize(max(self.log_post.shape[0], after.n))
        update = update_compiled if self.engine == "compiled" else update_reference
        update(self.log_post, self.informative, self._last, after, self.table, 0.5 / (self.sigma * self.sigma),
               HEADING_STRAIGHT)  # fmt: skip
        self.steps[:n] += (self._last.tracked[:n] & after.tracked[:n]).astype(np.int64)
        self._resize(after.n)
        self._last = after
        return self.posterior

    @property
    def posterior(self) -> np.ndarray:
        """(n, K) each body's probability of each type (rows sum to 1; the prior for untracked bodies)."""
        return np.exp(self.log_post)

    def allowed(self, epsilon: float) -> np.ndarray:
        """(n, K) bool: the types each car may still be, those whose posterior exceeds ``epsilon``; a row where
        none does (``epsilon`` at or above its largest probability) keeps its most probable type."""
        post = self.posterior
        keep = post > epsilon
        empty = ~keep.any(axis=1)
        if empty.any():
            keep[empty, np.argmax(post[empty], axis=1)] = True
        return keep


__all__ = [
    "HEADING_STRAIGHT", "SIGMA", "BeliefEngine", "BeliefFilter", "Observation", "leader_reference",
    "step_log_likelihood_reference", "type_table", "update_compiled", "update_reference",
]  # fmt: skip


DEFAULT_BELIEF_EPSILON = 0.01
"""The belief shield's ε: a car may be every type whose posterior exceeds it (``shield.belief_epsilon``)."""


@dataclasses.dataclass(frozen=True)
class DriverTypes:
    """What a shield knows of the traffic's driver types: the ``mix`` (``traffic.driver_mix``; its ``assumed`` None
    when the snapshot shows each car's own constants), and for ``mode="belief"`` the posterior threshold ``epsilon``
    (``shield.belief_epsilon``: a car may be every type above it) and the filter's residual deviation ``sigma``
    [m/s²] (``shield.belief_sigma``)."""

    mix: DriverMix
    epsilon: float = DEFAULT_BELIEF_EPSILON
    sigma: float = SIGMA

    def __post_init__(self) -> None:
        if not (isinstance(self.epsilon, int | float) and 0 <= self.epsilon < 1):
            raise ValueError(f"shield.belief_epsilon: must be a number in [0, 1) (got {self.epsilon!r})")
