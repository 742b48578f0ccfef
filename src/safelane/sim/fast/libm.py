"""Whether numpy's transcendental functions give libm's bits on this machine (the fast simulator's do).

The fast simulator reproduces highway-env bit for bit because both end in the same libm calls: numba's
``math.tan`` / ``math.atan`` & co. are libm's, and so are numpy's — on most CPUs. On a CPU with
AVX-512, numpy ≥ 2 dispatches its own vectorised ``tan`` and ``arctan`` (also for scalars), which differ
from libm in the last bit for about 0.5 % of arguments (measured on an AMD EPYC with numpy 2.4.6);
highway-env's steering (``arctan(tan(δ)/2)``) then drifts from the fast simulator by ~1e-6 m after a
few dozen decisions, and trajectories are no longer identical (statistically they still are).

:data:`LIBM_NUMPY_ENV` is the environment setting that keeps numpy on its libm paths; it must be set
before numpy is imported (the Makefile exports it for every target, the tests' conftest sets it).
:func:`numpy_matches_libm` tells whether the running process has it right.
"""

from __future__ import annotations

import math

import numpy as np

LIBM_NUMPY_ENV = {"NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR", "OPENBLAS_CORETYPE": "Nehalem"}
"""numpy's AVX-512 dispatch groups turned off (ignored on CPUs without them): its SIMD tan/arctan live there.
And OpenBLAS on its SSE kernels: on an AVX-512 CPU (AMD Zen 4) it picks its SkylakeX kernels, whose ``ddot``
fuses the multiply-adds, so highway-env's ``np.dot(STEERING_PARAMETERS, features)`` (LinearVehicle) is
``fma(a₁, b₁, a₀b₀)`` there — an ulp from ``a₀b₀ + a₁b₁`` in a quarter of cases — where the fast simulator and
every other CPU add two rounded products. Nehalem's kernels run on every x86-64 numpy supports."""


def numpy_matches_libm(samples: int = 4096, seed: int = 0) -> bool:
    """Whether numpy's sin, cos, tan, arctan and arcsin equal libm's (``math``) bit for bit on ``samples``
    seeded arguments in [−3, 3] rad ([−1, 1] for arcsin), as arrays and as scalars, and ``np.dot`` of two
    pairs is the sum of the two rounded products (no fused multiply-add)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-3.0, 3.0, samples)
    y = rng.uniform(-1.0, 1.0, samples)
    pairs = ((np.sin, math.sin, x), (np.cos, math.cos, x), (np.tan, math.tan, x), (np.arctan, math.atan, x),
             (np.arcsin, math.asin, y))  # fmt: skip
    for numpy_f, libm_f, args in pairs:
        expected = np.array([libm_f(float(v)) for v in args])
        if not np.array_equal(numpy_f(args), expected):
            return False
        if any(float(numpy_f(np.float64(v))) != e for v, e in zip(args[:256], expected[:256], strict=True)):
            return False
    pairs_a, pairs_b = x.reshape(-1, 2), y.reshape(-1, 2)
    dots = [float(np.dot(a, b)) for a, b in zip(pairs_a, pairs_b, strict=True)]
    return dots == [float(a[0] * b[0] + a[1] * b[1]) for a, b in zip(pairs_a, pairs_b, strict=True)]
