"""The fast simulator as a ``gymnasium.Env``, so safelane's wrappers (reward, observation, shield) stack on it."""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from safelane.core.snapshot import RoadSnapshot
from safelane.sim.fast.env import FastHighwayEnv


class FastSimulatorEnv(gym.Env):
    """:class:`FastHighwayEnv` behind gymnasium's ``Env`` interface; ``road_snapshot()`` gives the scene now.

    Like :class:`safelane.sim.highway.HighwayEnvAdapter` on highway-env, every reset and step puts the
    :class:`RoadSnapshot` in ``info["snapshot"]``.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, config: dict[str, Any], env_id: str) -> None:
        self.simulator = FastHighwayEnv(config, env_id)
        self.config = self.simulator.config
        self.action_space = self.simulator.action_space
        self.observation_space = self.simulator.observation_space

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Reset to the scene highway-env would build for ``seed``."""
        super().reset(seed=seed)
        return self.simulator.reset(seed=seed, options=options)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One decision: ``simulation_frequency // policy_frequency`` physics frames."""
        return self.simulator.step(int(action))

    def road_snapshot(self, refresh: bool = False) -> RoadSnapshot:
        """The snapshot of the scene now (``refresh`` is accepted for the adapter's interface; nothing is cached)."""
        return self.simulator.snapshot()

    @property
    def time(self) -> float:
        """[s] simulated time since the reset."""
        return self.simulator.time
