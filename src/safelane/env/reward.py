"""The paper's reward (eq. 6), computed from the road snapshot."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym

from safelane.core.snapshot import RoadSnapshot


class PaperReward(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """The paper's reward (eq. 6): ``b·clip((v − v_min)/(v_max − v_min), 0, 1) − c·collision``.

    ``v`` is the ego's forward speed (speed·cos heading) [m/s], as highway-env itself uses. ``info``
    gains ``collision`` (bool), ``speed`` and ``forward_speed`` [m/s] (from ``info["snapshot"]``) and
    ``highway_reward`` (the simulator's own reward); the simulator's other fields are kept.
    """

    def __init__(self, env: gym.Env, b: float, c: float, v_min: float, v_max: float) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, b=b, c=c, v_min=v_min, v_max=v_max)
        super().__init__(env)
        self.b, self.c, self.v_min, self.v_max = b, c, v_min, v_max

    def reward_of(self, forward_speed: float, collision: bool) -> float:
        """Eq. 6 for a forward speed [m/s] and a collision flag."""
        # min/max, not np.clip: the same double, without numpy's ≈ 50 µs per scalar call
        scaled = min(max((forward_speed - self.v_min) / (self.v_max - self.v_min), 0.0), 1.0)
        return float(self.b * scaled - self.c * float(collision))

    @staticmethod
    def _annotate(info: dict[str, Any]) -> float:
        snap: RoadSnapshot = info["snapshot"]
        speed = snap.speed[snap.ego]
        forward = float(speed * math.cos(snap.heading[snap.ego]))
        info["collision"] = snap.ego_crashed
        info["speed"] = float(speed)
        info["forward_speed"] = forward
        return forward

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self._annotate(info)
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, simulator_reward, terminated, truncated, info = self.env.step(action)
        forward = self._annotate(info)
        info["highway_reward"] = float(simulator_reward)
        return obs, self.reward_of(forward, info["collision"]), terminated, truncated, info
