"""The environment safelane trains on: the simulator, the paper's state and reward, the shield, assembled
by :func:`make_env`; hand-built scenes in :mod:`safelane.env.scenarios`.
"""

from safelane.env.factory import make_env

__all__ = ["make_env"]
