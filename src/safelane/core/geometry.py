"""Small geometric helpers shared by the observations, the forensics and the safety model (no simulator)."""

from __future__ import annotations

import numpy as np


def wrap_to_pi(angle: float | np.ndarray) -> float | np.ndarray:
    """``angle`` [rad] wrapped to [-π, π) — the same arithmetic as highway-env's ``utils.wrap_to_pi``."""
    return ((angle + np.pi) % (2 * np.pi)) - np.pi
