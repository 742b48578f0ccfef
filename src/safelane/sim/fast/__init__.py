"""A fast simulator: highway-env's straight highway (highway-v0 / highway-fast-v0) on arrays, with numba.

:class:`FastHighwayEnv` reproduces highway-env's scenes and dynamics, with a ``DiscreteMetaAction`` or a
``ContinuousAction`` ego (checked against stock highway-env by :func:`safelane.sim.fast.check.compare_episode`,
``tests/test_fast_sim.py`` and ``tests/test_fast_continuous.py``).
"""

from safelane.sim.fast.env import ACTIONS, FastHighwayEnv

__all__ = ["ACTIONS", "FastHighwayEnv"]
