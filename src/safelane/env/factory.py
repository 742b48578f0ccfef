"""The paper's environment on the real highway-env: factory, 26-number state (eq. 3), reward (eq. 6).

``make_env`` builds ``gym.make(env_id, config=cfg.env)`` and layers, from the inside out:

1. :class:`TrafficLayout` — safelane's traffic options (``traffic.vehicles_behind``);
2. :class:`PaperReward` — eq. 6 and the ``collision`` / ``speed`` info fields;
3. :class:`PaperObservation` — the paper's 26-number state (eq. 3), or the ``lanes`` state;
4. :class:`safelane.safety.shield.SafetyShield` — only when ``shield.mode`` is not ``none``.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import highway_env  # noqa: F401  (registers highway-v0 / highway-fast-v0)
import numpy as np
from highway_env import utils as hw_utils
from highway_env.envs.common.observation import KinematicObservation, ObservationType

from safelane.config import ConfigError, SafelaneConfig, apply_overrides, build_config, load_config
from safelane.sim import neighbours as fastsim
from safelane.sim.adversaries import add_adversary

# --- observation normalisation: every scale in one place, with units --------------------------
OBSERVED_VEHICLES = 4
"""Nearest vehicles in the state (paper Section III.A)."""
FEATURES_PER_VEHICLE = 6
"""δx, δy, δvx, δvy, heading, presence flag."""
OBS_SIZE = OBSERVED_VEHICLES * FEATURES_PER_VEHICLE + 2
"""26: four vehicles plus ego speed and ego heading."""
X_SCALE = 100.0  # [m] longitudinal offset mapped to ±1
Y_SCALE = 12.0  # [m] lateral offset mapped to ±1 (three 4 m lanes)
REL_SPEED_SCALE = 20.0  # [m/s] relative velocity mapped to ±1
HEADING_SCALE = math.pi / 2  # [rad] heading mapped to ±1
EGO_SPEED_SCALE = 40.0  # [m/s] highway-env's Vehicle.MAX_SPEED
PERCEPTION_DISTANCE = 200.0  # [m] vehicles farther than this are absent (highway-env's own range)
# --- the "lanes" state (an alternative to eq. 3 of the same size) ------------------------------
LANE_GAP_SCALE = 150.0  # [m] a gap this long or longer reads as 1 (a free lane)
LANE_FEATURES = 7
"""Per lane: exists, two leaders (gap, δv) and the follower (gap, δv)."""
LANE_WIDTH = 4.0  # [m] highway-env's StraightLane.DEFAULT_WIDTH: the ego's lateral offset is scaled by it


def paper_state(ego: Any, road: Any) -> np.ndarray:
    """The paper's state (eq. 3) for ``ego`` on ``road``, normalised and clipped to [-1, 1].

    Layout: for the 4 nearest vehicles (Euclidean distance, nearest first)
    ``[δx/X_SCALE, δy/Y_SCALE, δvx/REL_SPEED_SCALE, δvy/REL_SPEED_SCALE, ψ/HEADING_SCALE, flag]``,
    then ``[v_ego/EGO_SPEED_SCALE, ψ_ego/HEADING_SCALE]``. Absent vehicles are all zeros, flag 0.
    """
    obs = np.zeros(OBS_SIZE, dtype=np.float32)
    others = [v for v in road.vehicles if v is not ego]
    if others:
        pos = np.array([v.position for v in others], dtype=float)
        heading = np.array([v.heading for v in others], dtype=float)
        speed = np.array([v.speed for v in others], dtype=float)
        rel = pos - ego.position
        dist = np.hypot(rel[:, 0], rel[:, 1])
        near = np.argsort(dist, kind="stable")[:OBSERVED_VEHICLES]
        near = near[dist[near] < PERCEPTION_DISTANCE]
        ego_vel = ego.velocity
        for slot, i in enumerate(near):
            dv = speed[i] * np.array([math.cos(heading[i]), math.sin(heading[i])]) - ego_vel
            base = slot * FEATURES_PER_VEHICLE
            obs[base : base + FEATURES_PER_VEHICLE] = (
                rel[i, 0] / X_SCALE,
                rel[i, 1] / Y_SCALE,
                dv[0] / REL_SPEED_SCALE,
                dv[1] / REL_SPEED_SCALE,
                hw_utils.wrap_to_pi(heading[i]) / HEADING_SCALE,
                1.0,
            )
    obs[-2] = ego.speed / EGO_SPEED_SCALE
    obs[-1] = hw_utils.wrap_to_pi(ego.heading) / HEADING_SCALE
    np.clip(obs, -1.0, 1.0, out=obs)
    return obs


def lane_state(ego: Any, road: Any) -> np.ndarray:
    """A lane-by-lane state of the same size as eq. 3 (26 numbers in [-1, 1]): what an overtaking
    decision needs, which the paper's 4 nearest vehicles often miss in dense traffic (they are mostly
    alongside, and the ego's own lane is not in eq. 3).

    Layout: for the lane left of the ego, its own lane and the lane right of it (7 numbers each):
    ``[exists, gap₁, δv₁, gap₂, δv₂, gap_behind, δv_behind]`` — the two nearest vehicles ahead
    (longitudinal centre distance ≥ 0 [m] / LANE_GAP_SCALE) with their forward speed minus the ego's
    [m/s] / REL_SPEED_SCALE, then the nearest vehicle behind; a vehicle LANE_GAP_SCALE or farther away
    is absent (gap 1, δv 0); a lane that does not exist is all zeros. Then the ego:
    ``[v/EGO_SPEED_SCALE, ψ/HEADING_SCALE, lane index/(lanes − 1), lateral offset from the lane
    centre/LANE_WIDTH, target speed/EGO_SPEED_SCALE]``.
    A vehicle belongs to the lane highway-env assigns it (``lane_index``), also while it changes lanes.
    """
    obs = np.zeros(OBS_SIZE, dtype=np.float32)
    n_lanes = len(road.network.all_side_lanes(ego.lane_index))
    ego_lane = ego.lane_index[2]
    others = [v for v in road.vehicles if v is not ego]
    if others:
        dx = np.array([v.position[0] for v in others], dtype=float) - ego.position[0]
        lane = np.array([v.lane_index[2] for v in others])
        forward = np.array([v.speed * math.cos(v.heading) for v in others], dtype=float)
        dv = forward - ego.speed * math.cos(ego.heading)
    for slot, offset in enumerate((-1, 0, 1)):
        target = ego_lane + offset
        if not 0 <= target < n_lanes:
            continue
        base = slot * LANE_FEATURES
        obs[base : base + LANE_FEATURES] = (1.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0)
        if not others:
            continue
        in_lane = (lane == target) & (np.abs(dx) < LANE_GAP_SCALE)
        ahead = np.flatnonzero(in_lane & (dx >= 0))
        for k, i in enumerate(ahead[np.argsort(dx[ahead], kind="stable")][:2]):
            obs[base + 1 + 2 * k : base + 3 + 2 * k] = (dx[i] / LANE_GAP_SCALE, dv[i] / REL_SPEED_SCALE)
        behind = np.flatnonzero(in_lane & (dx < 0))
        if behind.size:
            i = behind[np.argmax(dx[behind])]
            obs[base + 5 : base + 7] = (-dx[i] / LANE_GAP_SCALE, dv[i] / REL_SPEED_SCALE)
    lateral = ego.lane.local_coordinates(ego.position)[1]
    obs[-5:] = (
        ego.speed / EGO_SPEED_SCALE,
        hw_utils.wrap_to_pi(ego.heading) / HEADING_SCALE,
        ego_lane / (n_lanes - 1) if n_lanes > 1 else 0.0,
        lateral / LANE_WIDTH,
        getattr(ego, "target_speed", ego.speed) / EGO_SPEED_SCALE,
    )
    np.clip(obs, -1.0, 1.0, out=obs)
    return obs


STATE_FUNCTIONS = {"paper": paper_state, "lanes": lane_state}
"""The agent's state by ``SafelaneConfig.state`` name."""


class DiscardedObservation(ObservationType):
    """Stands in for highway-env's own observation once :class:`PaperObservation` replaces it.

    highway-env builds its Kinematics observation through pandas at every step (≈ 5 % of a
    ``highway-fast-v0`` decision); safelane throws it away, so this returns a constant array of the
    original space's shape instead. The original is read-only and draws no random numbers (order
    ``sorted``), so the episodes are unchanged.
    """

    def __init__(self, env: Any, space: gym.spaces.Space) -> None:
        super().__init__(env)
        self._space = space
        self._constant = np.zeros(space.shape, dtype=space.dtype)

    def space(self) -> gym.spaces.Space:
        """The replaced observation's space."""
        return self._space

    def observe(self) -> np.ndarray:
        """Zeros of the replaced observation's shape."""
        return self._constant.copy()  # a new array each call, as gymnasium expects


class PaperObservation(gym.ObservationWrapper, gym.utils.RecordConstructorArgs):
    """Replace highway-env's observation by the paper's 26-number state (eq. 3), or with
    ``state="lanes"`` by :func:`lane_state` (same size).

    After every reset highway-env's own observation is swapped for a :class:`DiscardedObservation`
    (highway-env rebuilds it at each reset), unless it draws random numbers (``order: shuffled``).
    """

    def __init__(self, env: gym.Env, state: str = "paper") -> None:
        gym.utils.RecordConstructorArgs.__init__(self, state=state)
        super().__init__(env)
        if state not in STATE_FUNCTIONS:
            raise ConfigError(f"state: got {state!r}; allowed: {', '.join(STATE_FUNCTIONS)}")
        self.state_of = STATE_FUNCTIONS[state]
        self.observation_space = gym.spaces.Box(-1.0, 1.0, shape=(OBS_SIZE,), dtype=np.float32)

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = super().reset(**kwargs)
        base = self.env.unwrapped
        observer = getattr(base, "observation_type", None)
        if isinstance(observer, KinematicObservation) and observer.order == "sorted":
            base.observation_type = DiscardedObservation(base, base.observation_space)
        return obs, info

    def observation(self, observation: Any) -> np.ndarray:
        base = self.env.unwrapped
        return self.state_of(base.vehicle, base.road)


class PaperReward(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """The paper's reward (eq. 6): ``b·clip((v − v_min)/(v_max − v_min), 0, 1) − c·collision``.

    ``v`` is the ego's forward speed (speed·cos heading) [m/s], as highway-env itself uses. ``info``
    gains ``collision`` (bool), ``forward_speed`` [m/s] and ``highway_reward`` (highway-env's own
    reward); highway-env's fields (``speed``, ``crashed``, ``rewards``…) are kept.
    """

    def __init__(self, env: gym.Env, b: float, c: float, v_min: float, v_max: float) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, b=b, c=c, v_min=v_min, v_max=v_max)
        super().__init__(env)
        self.b, self.c, self.v_min, self.v_max = b, c, v_min, v_max

    def reward_of(self, forward_speed: float, collision: bool) -> float:
        """Eq. 6 for a forward speed [m/s] and a collision flag."""
        scaled = np.clip((forward_speed - self.v_min) / (self.v_max - self.v_min), 0.0, 1.0)
        return float(self.b * scaled - self.c * float(collision))

    def _annotate(self, info: dict[str, Any]) -> float:
        ego = self.env.unwrapped.vehicle
        forward = float(ego.speed * math.cos(ego.heading))
        info["collision"] = bool(ego.crashed)
        info["speed"] = float(ego.speed)
        info["forward_speed"] = forward
        return forward

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self._annotate(info)
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, highway_reward, terminated, truncated, info = self.env.step(action)
        forward = self._annotate(info)
        info["highway_reward"] = float(highway_reward)
        return obs, self.reward_of(forward, info["collision"]), terminated, truncated, info


class TrafficLayout(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """safelane traffic options applied right after highway-env builds its scene.

    Also switches the road to :mod:`safelane.sim.neighbours`'s vectorised neighbour search when
    ``vectorized`` (config ``backend``), which gives identical episodes, faster.

    ``vehicles_behind = N`` removes the N vehicles farthest ahead and spawns N vehicles *behind* the
    ego with highway-env's own rules mirrored backwards: random lane and spacing from
    ``road.np_random`` (same spacing law as ``Vehicle.create_random``), speeds uniform in
    [0.7, 1.0]·speed limit so that some are faster than the ego. highway-env alone spawns the ego
    behind every other vehicle, so followers and cut-ins from behind never happen in the stock scene.
    """

    def __init__(
        self, env: gym.Env, vehicles_behind: int = 0, vectorized: bool = True, adversary: str = "none"
    ) -> None:
        gym.utils.RecordConstructorArgs.__init__(
            self, vehicles_behind=vehicles_behind, vectorized=vectorized, adversary=adversary
        )
        super().__init__(env)
        self.vehicles_behind = vehicles_behind
        self.vectorized = vectorized
        self.adversary = adversary

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        fastsim.enable(self.env.unwrapped.road, self.vectorized)
        if self.vehicles_behind > 0:
            self._spawn_behind()
        if self.adversary != "none":
            base = self.env.unwrapped
            add_adversary(base.road, base.vehicle, self.adversary)
        return obs, info

    def _spawn_behind(self) -> None:
        base = self.env.unwrapped
        road, ego = base.road, base.vehicle
        others = [v for v in road.vehicles if v is not ego]
        n = min(self.vehicles_behind, len(others))
        if n == 0:
            return
        others.sort(key=lambda v: v.position[0])
        vehicle_cls = type(others[0])
        check_collisions = others[0].check_collisions
        for v in others[-n:]:
            road.vehicles.remove(v)
        lanes = road.network.graph
        _from = next(iter(lanes))
        _to = next(iter(lanes[_from]))
        n_lanes = len(lanes[_from][_to])
        x = ego.lane.local_coordinates(ego.position)[0]
        for _ in range(n):
            lane_id = int(road.np_random.integers(n_lanes))
            lane = road.network.get_lane((_from, _to, lane_id))
            limit = lane.speed_limit or 30.0
            speed = float(road.np_random.uniform(0.7 * limit, 1.0 * limit))
            offset = (12 + speed) * math.exp(-5 / 40 * n_lanes) / base.config["vehicles_density"]
            x -= offset * road.np_random.uniform(0.9, 1.1)
            v = vehicle_cls(road, lane.position(x, 0), lane.heading_at(x), speed)
            if hasattr(v, "randomize_behavior"):
                v.randomize_behavior()
            v.check_collisions = check_collisions
            road.vehicles.append(v)


def make_env(
    config: SafelaneConfig | str | None = None,
    *,
    seed: int | None = None,
    render_mode: str | None = None,
    **overrides: Any,
) -> gym.Env:
    """Build the paper's environment on highway-env.

    ``config``: a :class:`SafelaneConfig`, a preset name (``"fast"``, default, or ``"paper"``) or None.
    ``overrides``: dotted keys or section dicts applied on top, e.g. ``make_env(env={"lanes_count": 5})``
    or ``make_env(**{"shield.mode": "robust"})``. With ``seed`` the env is reset once with that seed
    (gymnasium's seeding) and its action space is seeded, so the same seed gives the same episodes.
    """
    if config is None or isinstance(config, str):
        cfg = load_config(config or "fast", overrides=overrides)
    else:
        cfg = config
        if overrides:
            data = cfg.model_dump()
            apply_overrides(data, overrides)
            cfg = build_config(data)
    try:
        env = gym.make(cfg.env_id, config=dict(cfg.env), render_mode=render_mode)
    except (TypeError, ValueError, KeyError, AttributeError, ImportError) as err:
        raise ConfigError(f"env: highway-env rejected the configuration ({err})") from None
    env = TrafficLayout(
        env, cfg.traffic.vehicles_behind, vectorized=cfg.backend == "vectorized", adversary=cfg.traffic.adversary
    )
    env = PaperReward(env, cfg.reward.b, cfg.reward.c, cfg.reward.v_min, cfg.reward.v_max)
    env = PaperObservation(env, cfg.state)
    if cfg.shield.mode != "none":
        from safelane.safety.shield import SafetyShield

        env = SafetyShield(env, mode=cfg.shield.mode, formula=cfg.shield.formula, override=cfg.shield.override)
    env.safelane_config = cfg  # type: ignore[attr-defined]
    if seed is not None:
        env.reset(seed=seed)
        env.action_space.seed(seed)
    return env
