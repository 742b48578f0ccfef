"""The paper's reward (eq. 6), and its form for continuous actions, computed from the road snapshot."""

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

    def _annotate(self, info: dict[str, Any]) -> float:
        """Write the reward's ``info`` fields; return the forward speed [m/s]."""
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

    def _penalised(self, info: dict[str, Any]) -> bool:
        """Whether the step earns the collision penalty ``c``: the ego crashed."""
        return bool(info["collision"])

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, simulator_reward, terminated, truncated, info = self.env.step(action)
        forward = self._annotate(info)
        info["highway_reward"] = float(simulator_reward)
        return obs, self.reward_of(forward, self._penalised(info)), terminated, truncated, info


def off_road(snap: RoadSnapshot) -> bool:
    """Whether the ego is off the road: more than half a lane width from its lane's centre (highway-env's
    ``Vehicle.on_road``: the lane is the closest one, so only beyond an outer lane's edge)."""
    return abs(snap.ego_lane_offset) > snap.lane_width / 2


class ContinuousReward(PaperReward):
    """Eq. 6 for acceleration and steering (``actions: continuous``):
    ``b·clip((v·cos ψ − v_min)/(v_max − v_min), 0, 1)·(1 − lane_centring·min((2·δ/w)², 1)) − c·(crash or off road)``.

    The speed term is eq. 6's, on the forward speed: progress along the road, so spinning (cos ψ < 0) or stopping
    earns nothing. ``δ`` is the ego's offset from its lane's centre [m] and ``w`` the lane width: at a lane's edge
    the speed term loses ``lane_centring`` of itself, so the ego is paid to drive in a lane and a lane change costs
    a little, as a meta-action's lane change takes about a second between lanes. Leaving the road costs the
    collision penalty (and ends the episode under ``env.offroad_terminal``, on by default with continuous
    actions; without it, every decision that ends off the road costs it). ``info`` gains ``off_road`` (bool)
    beside :class:`PaperReward`'s fields.
    """

    def __init__(
        self, env: gym.Env, b: float, c: float, v_min: float, v_max: float, lane_centring: float
    ) -> None:  # fmt: skip
        super().__init__(env, b, c, v_min, v_max)
        gym.utils.RecordConstructorArgs.__init__(self, b=b, c=c, v_min=v_min, v_max=v_max, lane_centring=lane_centring)
        self.lane_centring = lane_centring
        self._centring = 1.0

    def _annotate(self, info: dict[str, Any]) -> float:
        forward = super()._annotate(info)
        snap: RoadSnapshot = info["snapshot"]
        info["off_road"] = off_road(snap)
        edge = 2.0 * snap.ego_lane_offset / snap.lane_width
        self._centring = 1.0 - self.lane_centring * min(edge * edge, 1.0)
        return forward

    def reward_of(self, forward_speed: float, collision: bool) -> float:
        """The reward for a forward speed [m/s] and a crash-or-off-road flag, at the last state's lane offset."""
        scaled = min(max((forward_speed - self.v_min) / (self.v_max - self.v_min), 0.0), 1.0)
        return float(self.b * scaled * self._centring - self.c * float(collision))

    def _penalised(self, info: dict[str, Any]) -> bool:
        """Whether the step earns the collision penalty ``c``: the ego crashed or left the road."""
        return bool(info["collision"] or info["off_road"])
