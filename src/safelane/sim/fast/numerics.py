"""The fast simulator's scalar numerics, each bit-identical to highway-env's numpy scalars: trigonometry exact
at ``±0``, ``not_zero``, ``wrap_to_pi``, ``clip``, and numpy's ``Generator`` draws from raw PCG64 outputs.

Trigonometric calls go through :func:`sin` & co., which return IEEE's exact values at ``±0`` without
calling libm (``sin(±0) = ±0``, ``cos(±0) = 1``...): most vehicles drive with heading and steering
exactly ``0.0``, and those calls would otherwise dominate. ``error_model="numpy"``: a division by zero
gives IEEE's inf / nan, as highway-env's numpy scalars do, instead of raising.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy", inline="always")
def sin(x):
    """``math.sin(x)`` (x in radians), ``x`` itself at ``±0`` without calling libm."""
    return x if x == 0.0 else math.sin(x)


@njit(cache=True, error_model="numpy", inline="always")
def cos(x):
    """``math.cos(x)`` (x in radians), ``1.0`` at ``±0`` without calling libm."""
    return 1.0 if x == 0.0 else math.cos(x)


@njit(cache=True, error_model="numpy", inline="always")
def tan(x):
    """``math.tan(x)`` (x in radians), ``x`` itself at ``±0`` without calling libm."""
    return x if x == 0.0 else math.tan(x)


@njit(cache=True, error_model="numpy", inline="always")
def atan(x):
    """``math.atan(x)`` in radians, ``x`` itself at ``±0`` without calling libm."""
    return x if x == 0.0 else math.atan(x)


@njit(cache=True, error_model="numpy", inline="always")
def asin(x):
    """``math.asin(x)`` in radians, ``x`` itself at ``±0`` without calling libm."""
    return x if x == 0.0 else math.asin(x)


@njit(cache=True, error_model="numpy", inline="always")
def not_zero(x, eps=1e-2):
    """highway-env's ``utils.not_zero``: ``x``, or ``eps`` with x's sign (``+eps`` for 0) when ``|x| <= eps``."""
    if abs(x) > eps:
        return x
    elif x >= 0:
        return eps
    else:
        return -eps


@njit(cache=True, error_model="numpy", inline="always")
def wrap_to_pi(x):
    """highway-env's ``utils.wrap_to_pi``: the angle ``x`` [rad] brought into ``[-π, π)``."""
    # ((x + pi) % (2 pi)) - pi with Python/numpy floor-mod semantics; for 0 <= x + pi < 2 pi the
    # remainder is x + pi itself (exactly), so the fmod call is skipped.
    t = x + np.pi
    if t >= 0.0 and t < 2 * np.pi:
        return t - np.pi
    return (t % (2 * np.pi)) - np.pi


@njit(cache=True, error_model="numpy", inline="always")
def clip(x, lo, hi):
    """``np.clip`` of a scalar: ``x`` bounded to ``[lo, hi]``."""
    if x < lo:
        return lo
    if x > hi:
        return hi
    return x


# --- the reset's draws (HighwayEnv._create_vehicles) from the generator's raw 64-bit outputs ----------
# numpy's Generator on PCG64: ``uniform(lo, hi) = lo + (hi - lo) * next_double`` with
# ``next_double = (raw >> 11) / 2**53``; ``choice(n)`` = ``integers(0, n)`` = Lemire's bounded draw on
# ``next_uint32``, which takes the low half of a raw output and keeps the high half in the bit
# generator's ``has_uint32`` / ``uinteger`` buffer for the next call. ``st`` = [raws used, has_uint32,
# uinteger]; ``st[0] < 0`` flags that ``raws`` ran out (draw more and replay).


@njit(cache=True, error_model="numpy")
def _next_uint32(raws, st):
    if st[1]:
        st[1] = 0
        return np.uint64(st[2])
    if st[0] < 0 or st[0] >= raws.size:
        st[0] = -1
        return np.uint64(0)
    r = raws[st[0]]
    st[0] += 1
    st[1] = 1
    st[2] = np.int64(r >> np.uint64(32))
    return r & np.uint64(0xFFFFFFFF)


@njit(cache=True, error_model="numpy")
def integers(raws, st, n):
    """Generator.integers(0, n) (== choice(n)) for int64, n <= 2**32."""
    rng = n - 1
    if rng == 0:
        return 0
    excl = np.uint64(rng + 1)
    m = _next_uint32(raws, st) * excl
    left = m & np.uint64(0xFFFFFFFF)
    if left < excl:
        thr = (np.uint64(0xFFFFFFFF) - np.uint64(rng)) % excl
        while left < thr:
            m = _next_uint32(raws, st) * excl
            left = m & np.uint64(0xFFFFFFFF)
    return np.int64(m >> np.uint64(32))


@njit(cache=True, error_model="numpy")
def uniform(raws, st, lo, hi):
    """``Generator.uniform(lo, hi)`` from the next raw output (``lo`` when ``raws`` ran out: ``st[0] = -1``)."""
    if st[0] < 0 or st[0] >= raws.size:
        st[0] = -1
        return lo
    r = raws[st[0]]
    st[0] += 1
    return lo + (hi - lo) * ((r >> np.uint64(11)) * (1.0 / 9007199254740992.0))
