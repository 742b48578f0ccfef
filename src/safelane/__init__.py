"""safelane: safe tactical decision making on highways with deep reinforcement learning.

Reproduces and extends "Reinforcement Learning Based Safe Decision Making for Highway Autonomous
Driving" (Mohammadhasani et al.) on the real highway-env.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("safelane")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"

from safelane.config import ConfigError, SafelaneConfig, load_config
from safelane.env.factory import make_env
from safelane.env.registration import register_envs
from safelane.env.vector import make_vector_env, sb3_vec_env
from safelane.safety.control_shield import ControlShield
from safelane.safety.shield import CannotStopWarning, SafetyShield, stoppable_action_config

register_envs()  # gym.make("safelane/Highway-v0") / ("safelane/HighwayFast-v0"): safelane.env.registration

__all__ = [
    "CannotStopWarning",
    "ConfigError",
    "ControlShield",
    "SafelaneConfig",
    "SafetyShield",
    "__version__",
    "load_config",
    "make_env",
    "make_vector_env",
    "sb3_vec_env",
    "stoppable_action_config",
]
