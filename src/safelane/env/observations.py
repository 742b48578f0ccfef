"""The agent's state, computed from a :class:`~safelane.core.snapshot.RoadSnapshot`: eq. 3 or the lanes state.

Both are 26 numbers in [-1, 1] (:data:`safelane.core.spaces.OBS_SIZE`); with continuous actions eq. 3 gains the
ego's lane offset and lane index (28, :data:`safelane.core.spaces.CONTINUOUS_OBS_SIZE`); in traffic with a mixture
of driver types, ``paper-types`` is eq. 3 followed by the observed cars' types (:func:`paper_types_state`) and
``paper-belief`` eq. 3 followed by their posteriors over the types (:func:`paper_belief_state`); ``paper-stack`` is
eq. 3 of the last :data:`STACK_DEPTH` decisions (:class:`StackedState`). :func:`state_size` gives each one's size.
:class:`PaperObservation` replaces the simulator's own observation by one of them, reading ``info["snapshot"]``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numba
import numpy as np

from safelane.core.drivers import DriverMix
from safelane.core.errors import ConfigError
from safelane.core.geometry import wrap_to_pi
from safelane.core.snapshot import RoadSnapshot
from safelane.core.spaces import CONTINUOUS_OBS_SIZE, FEATURES_PER_VEHICLE, OBS_SIZE, OBSERVED_VEHICLES
from safelane.safety.belief import SIGMA, BeliefFilter

# --- observation normalisation: every scale in one place, with units --------------------------
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


def paper_state(snap: RoadSnapshot) -> np.ndarray:
    """The paper's state (eq. 3) of the scene ``snap``, normalised and clipped to [-1, 1].

    Layout: for the 4 nearest vehicles (Euclidean distance, nearest first)
    ``[δx/X_SCALE, δy/Y_SCALE, δvx/REL_SPEED_SCALE, δvy/REL_SPEED_SCALE, ψ/HEADING_SCALE, flag]``,
    then ``[v_ego/EGO_SPEED_SCALE, ψ_ego/HEADING_SCALE]``. Absent vehicles are all zeros, flag 0.
    """
    obs = np.zeros(OBS_SIZE, dtype=np.float32)
    e = snap.ego
    ego_speed, ego_heading = snap.speed[e], snap.heading[e]
    others = snap.others()
    if others.size:
        pos = snap.position[others]
        heading = snap.heading[others]
        speed = snap.speed[others]
        rel = pos - snap.position[e]
        near = _nearest(rel)
        # The ego's velocity as highway-env computes it (speed · [cos ψ, sin ψ] through numpy).
        ego_vel = ego_speed * np.array([np.cos(ego_heading), np.sin(ego_heading)])
        for slot, i in enumerate(near):
            dv = speed[i] * np.array([math.cos(heading[i]), math.sin(heading[i])]) - ego_vel
            base = slot * FEATURES_PER_VEHICLE
            obs[base : base + FEATURES_PER_VEHICLE] = (
                rel[i, 0] / X_SCALE,
                rel[i, 1] / Y_SCALE,
                dv[0] / REL_SPEED_SCALE,
                dv[1] / REL_SPEED_SCALE,
                wrap_to_pi(heading[i]) / HEADING_SCALE,
                1.0,
            )
    obs[-2] = ego_speed / EGO_SPEED_SCALE
    obs[-1] = wrap_to_pi(ego_heading) / HEADING_SCALE
    np.clip(obs, -1.0, 1.0, out=obs)
    return obs


def _nearest(rel: np.ndarray) -> np.ndarray:
    """Rows of ``rel`` (the other vehicles' positions from the ego [m]) that eq. 3 observes, nearest first: the
    :data:`OBSERVED_VEHICLES` nearest (Euclidean; the first of equals first) within :data:`PERCEPTION_DISTANCE`."""
    dist = np.hypot(rel[:, 0], rel[:, 1])
    near = np.argsort(dist, kind="stable")[:OBSERVED_VEHICLES]
    return near[dist[near] < PERCEPTION_DISTANCE]


def observed_vehicles(snap: RoadSnapshot) -> np.ndarray:
    """The snapshot indices of the vehicles eq. 3 observes, in its slots' order (nearest first)."""
    others = snap.others()
    if not others.size:
        return others
    return others[_nearest(snap.position[others] - snap.position[snap.ego])]


def paper_types_state(snap: RoadSnapshot, types: int) -> np.ndarray:
    """Eq. 3 (:func:`paper_state`, 26 numbers) followed by the driver type of each of its 4 observed vehicles, one-hot:
    ``26 + 4·types`` float32 numbers in [0, 1] after eq. 3's.

    Layout after eq. 3: slot ``s`` (0..3, eq. 3's order, nearest first) holds ``types`` numbers at
    ``26 + s·types + t``: 1.0 where ``t`` is the vehicle's ``driver_type`` (its index in ``traffic.driver_mix``),
    else 0.0; an empty slot, or a body of no type (-1), is all zeros.
    """
    obs = np.zeros(OBS_SIZE + OBSERVED_VEHICLES * types, dtype=np.float32)
    obs[:OBS_SIZE] = paper_state_compiled(snap)
    driver_type = snap.driver_type
    if driver_type is None:
        raise ConfigError("state: 'paper-types' reads each car's driver type; this traffic has no traffic.driver_mix")
    for slot, i in enumerate(observed_vehicles(snap)):
        t = int(driver_type[i])
        if 0 <= t < types:
            obs[OBS_SIZE + slot * types + t] = 1.0
    return obs


def lane_state(snap: RoadSnapshot) -> np.ndarray:
    """A lane-by-lane state of the same size as eq. 3 (26 numbers in [-1, 1]): what an overtaking
    decision needs, which the paper's 4 nearest vehicles often miss in dense traffic (they are mostly
    alongside, and the ego's own lane is not in eq. 3).

    Layout: for the lane left of the ego, its own lane and the lane right of it (7 numbers each):
    ``[exists, gap₁, δv₁, gap₂, δv₂, gap_behind, δv_behind]`` — the two nearest vehicles ahead
    (longitudinal centre distance ≥ 0 [m] / LANE_GAP_SCALE) with their forward speed minus the ego's
    [m/s] / REL_SPEED_SCALE, then the nearest vehicle behind; a vehicle LANE_GAP_SCALE or farther away
    is absent (gap 1, δv 0); a lane that does not exist is all zeros. Then the ego:
    ``[v/EGO_SPEED_SCALE, ψ/HEADING_SCALE, lane index/(lanes − 1), lateral offset from the lane
    centre/lane width, target speed/EGO_SPEED_SCALE]``.
    A vehicle belongs to the lane the simulator assigns it (``lane``), also while it changes lanes.
    """
    obs = np.zeros(OBS_SIZE, dtype=np.float32)
    n_lanes = snap.lanes_count
    e = snap.ego
    ego_lane = int(snap.lane[e])
    ego_speed, ego_heading = float(snap.speed[e]), float(snap.heading[e])
    others = snap.others()
    if others.size:
        dx = snap.position[others, 0] - snap.position[e, 0]
        lane = snap.lane[others]
        # math.cos per vehicle, as before the snapshot existed: numpy's vectorised cos may differ in the last bit.
        forward = np.array(
            [s * math.cos(h) for s, h in zip(snap.speed[others].tolist(), snap.heading[others].tolist(), strict=True)],
            dtype=float,
        )
        dv = forward - ego_speed * math.cos(ego_heading)
    for slot, offset in enumerate((-1, 0, 1)):
        target = ego_lane + offset
        if not 0 <= target < n_lanes:
            continue
        base = slot * LANE_FEATURES
        obs[base : base + LANE_FEATURES] = (1.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0)
        if not others.size:
            continue
        in_lane = (lane == target) & (np.abs(dx) < LANE_GAP_SCALE)
        ahead = np.flatnonzero(in_lane & (dx >= 0))
        for k, i in enumerate(ahead[np.argsort(dx[ahead], kind="stable")][:2]):
            obs[base + 1 + 2 * k : base + 3 + 2 * k] = (dx[i] / LANE_GAP_SCALE, dv[i] / REL_SPEED_SCALE)
        behind = np.flatnonzero(in_lane & (dx < 0))
        if behind.size:
            i = behind[np.argmax(dx[behind])]
            obs[base + 5 : base + 7] = (-dx[i] / LANE_GAP_SCALE, dv[i] / REL_SPEED_SCALE)
    obs[-5:] = (
        ego_speed / EGO_SPEED_SCALE,
        wrap_to_pi(ego_heading) / HEADING_SCALE,
        ego_lane / (n_lanes - 1) if n_lanes > 1 else 0.0,
        snap.ego_lane_offset / snap.lane_width,
        snap.ego_target_speed / EGO_SPEED_SCALE,
    )
    np.clip(obs, -1.0, 1.0, out=obs)
    return obs


# --- compiled versions: the same arithmetic, one numba call a decision ---------------------------------


@numba.njit(cache=True)
def _wrap(angle: float) -> float:
    return ((angle + np.pi) % (2 * np.pi)) - np.pi


@numba.njit(cache=True)
def paper_state_kernel(
    position: np.ndarray, speed: np.ndarray, heading: np.ndarray, is_vehicle: np.ndarray, ego: int, obs: np.ndarray
) -> None:
    ex, ey = position[ego, 0], position[ego, 1]
    ev, eh = speed[ego], heading[ego]
    evx, evy = ev * np.cos(eh), ev * np.sin(eh)
    near = np.full(OBSERVED_VEHICLES, -1)
    near_d = np.full(OBSERVED_VEHICLES, np.inf)
    for i in range(speed.shape[0]):  # the 4 nearest, the first of equals first (a stable argsort)
        if i == ego or not is_vehicle[i]:
            continue
        d = np.hypot(position[i, 0] - ex, position[i, 1] - ey)
        slot = OBSERVED_VEHICLES
        while slot > 0 and d < near_d[slot - 1]:
            slot -= 1
        if slot < OBSERVED_VEHICLES:
            for k in range(OBSERVED_VEHICLES - 1, slot, -1):
                near[k], near_d[k] = near[k - 1], near_d[k - 1]
            near[slot], near_d[slot] = i, d
    obs[:] = 0.0
    for slot in range(OBSERVED_VEHICLES):
        i = near[slot]
        if i < 0 or not near_d[slot] < PERCEPTION_DISTANCE:
            break
        h, v = heading[i], speed[i]
        base = slot * FEATURES_PER_VEHICLE
        obs[base] = (position[i, 0] - ex) / X_SCALE
        obs[base + 1] = (position[i, 1] - ey) / Y_SCALE
        obs[base + 2] = (v * math.cos(h) - evx) / REL_SPEED_SCALE
        obs[base + 3] = (v * math.sin(h) - evy) / REL_SPEED_SCALE
        obs[base + 4] = _wrap(h) / HEADING_SCALE
        obs[base + 5] = 1.0
    obs[OBS_SIZE - 2] = ev / EGO_SPEED_SCALE
    obs[OBS_SIZE - 1] = _wrap(eh) / HEADING_SCALE
    for k in range(OBS_SIZE):
        obs[k] = min(max(obs[k], -1.0), 1.0)


def paper_state_compiled(snap: RoadSnapshot) -> np.ndarray:
    """:func:`paper_state` in one numba call: the same numbers, bit for bit (``tests/test_env.py``)."""
    obs = np.empty(OBS_SIZE, dtype=np.float32)
    paper_state_kernel(snap.position, snap.speed, snap.heading, snap.is_vehicle, snap.ego, obs)
    return obs


@numba.njit(cache=True)
def lane_state_kernel(
    position: np.ndarray,
    speed: np.ndarray,
    heading: np.ndarray,
    lane: np.ndarray,
    is_vehicle: np.ndarray,
    ego: int,
    lanes_count: int,
    lane_offset_scaled: float,
    ego_target_speed: float,
    obs: np.ndarray,
) -> None:
    ego_lane = lane[ego]
    ev, eh = speed[ego], heading[ego]
    ego_forward = ev * math.cos(eh)
    ex = position[ego, 0]
    obs[:] = 0.0
    for slot in range(3):
        target = ego_lane + slot - 1
        if not 0 <= target < lanes_count:
            continue
        base = slot * LANE_FEATURES
        obs[base], obs[base + 1], obs[base + 3], obs[base + 5] = 1.0, 1.0, 1.0, 1.0
        # the two nearest ahead (the first of equals first) and the nearest behind (the first of equals)
        a0 = a1 = b0 = -1
        d0 = d1 = np.inf
        db = -np.inf
        for i in range(speed.shape[0]):
            if i == ego or not is_vehicle[i] or lane[i] != target:
                continue
            dx = position[i, 0] - ex
            if not abs(dx) < LANE_GAP_SCALE:
                continue
            if dx >= 0:
                if dx < d0:
                    a1, d1, a0, d0 = a0, d0, i, dx
                elif dx < d1:
                    a1, d1 = i, dx
            elif dx > db:
                b0, db = i, dx
        for k, i in enumerate((a0, a1)):
            if i >= 0:
                dx = position[i, 0] - ex
                obs[base + 1 + 2 * k] = dx / LANE_GAP_SCALE
                obs[base + 2 + 2 * k] = (speed[i] * math.cos(heading[i]) - ego_forward) / REL_SPEED_SCALE
        if b0 >= 0:
            obs[base + 5] = -(position[b0, 0] - ex) / LANE_GAP_SCALE
            obs[base + 6] = (speed[b0] * math.cos(heading[b0]) - ego_forward) / REL_SPEED_SCALE
    obs[OBS_SIZE - 5] = ev / EGO_SPEED_SCALE
    obs[OBS_SIZE - 4] = _wrap(eh) / HEADING_SCALE
    obs[OBS_SIZE - 3] = ego_lane / (lanes_count - 1) if lanes_count > 1 else 0.0
    obs[OBS_SIZE - 2] = lane_offset_scaled
    obs[OBS_SIZE - 1] = ego_target_speed / EGO_SPEED_SCALE
    for k in range(OBS_SIZE):
        obs[k] = min(max(obs[k], -1.0), 1.0)


def lane_state_compiled(snap: RoadSnapshot) -> np.ndarray:
    """:func:`lane_state` in one numba call: the same numbers, bit for bit (``tests/test_env.py``)."""
    obs = np.empty(OBS_SIZE, dtype=np.float32)
    lane_state_kernel(
        snap.position,
        snap.speed,
        snap.heading,
        snap.lane,
        snap.is_vehicle,
        snap.ego,
        snap.lanes_count,
        snap.ego_lane_offset / snap.lane_width,
        snap.ego_target_speed,
        obs,
    )
    return obs


def _with_lane_position(state_of: Callable[[RoadSnapshot], np.ndarray]) -> Callable[[RoadSnapshot], np.ndarray]:
    """``state_of`` followed by :func:`lane_position`."""

    def continuous_state(snap: RoadSnapshot) -> np.ndarray:
        return np.concatenate((state_of(snap), lane_position(snap)))

    return continuous_state


STATE_FUNCTIONS: dict[str, Callable[[RoadSnapshot], np.ndarray]] = {
    "paper": paper_state_compiled,
    "lanes": lane_state_compiled,
}
"""The agent's state by ``SafelaneConfig.state`` name (the compiled form where one exists), but for
:data:`TYPED_STATE`, which also needs the number of driver types, and the states with a memory
(:data:`STACKED_STATE`, :data:`BELIEF_STATE`)."""
TYPED_STATE = "paper-types"
"""Eq. 3 and each observed car's driver type (:func:`paper_types_state`): the matched arm of hidden driver types."""
STACKED_STATE = "paper-stack"
"""Eq. 3 of the last :data:`STACK_DEPTH` decisions (:class:`StackedState`): a frame-stacked agent's state."""
BELIEF_STATE = "paper-belief"
"""Eq. 3 and each observed car's posterior over the driver types (:func:`paper_belief_state`)."""
MIXTURE_STATES = (TYPED_STATE, BELIEF_STATE)
"""The states that read ``traffic.driver_mix`` (a number per type and observed car)."""
STATES: tuple[str, ...] = (*STATE_FUNCTIONS, TYPED_STATE, STACKED_STATE, BELIEF_STATE)
"""Every ``state`` name :class:`PaperObservation` builds."""
STACK_DEPTH = 4
"""Decisions eq. 3 is stacked over in :data:`STACKED_STATE` (4 × 26 = 104 numbers): at one decision a second, 4 s
of motion, 3 speed changes of each car seen throughout; after 3 informative steps the belief filter's most probable
type is the true one for 94 % of cars (docs/research/belief-calibration.md), so the motion to tell types apart is
there."""


def state_size(state: str, continuous: bool = False, driver_types: int = 0) -> int:
    """Numbers in the state ``state`` (:data:`STATES`): 26 for ``paper`` and ``lanes`` (28 with ``continuous``
    actions), ``26 + 4·driver_types`` for :data:`MIXTURE_STATES`, ``26·STACK_DEPTH`` for :data:`STACKED_STATE`."""
    if state in MIXTURE_STATES:
        return OBS_SIZE + OBSERVED_VEHICLES * driver_types
    if state == STACKED_STATE:
        return OBS_SIZE * STACK_DEPTH
    return CONTINUOUS_OBS_SIZE if continuous else OBS_SIZE


def paper_belief_state(snap: RoadSnapshot, posterior: np.ndarray) -> np.ndarray:
    """Eq. 3 (:func:`paper_state`, 26 numbers) followed by the posterior over the K driver types of each of its 4
    observed vehicles: ``26 + 4·K`` float32 numbers, those after eq. 3 in [0, 1].

    ``posterior``: (n, K), a row per snapshot body (:attr:`safelane.safety.belief.BeliefFilter.posterior`). Layout
    after eq. 3 as :func:`paper_types_state`'s: slot ``s`` (nearest first) holds its car's row at
    ``26 + s·K … 26 + s·K + K − 1`` (it sums to 1); an empty slot is all zeros.
    """
    types = int(posterior.shape[1])
    obs = np.zeros(OBS_SIZE + OBSERVED_VEHICLES * types, dtype=np.float32)
    obs[:OBS_SIZE] = paper_state_compiled(snap)
    for slot, i in enumerate(observed_vehicles(snap)):
        start = OBS_SIZE + slot * types
        obs[start : start + types] = posterior[i]
    return obs


class StackedState:
    """:data:`STACKED_STATE`: eq. 3 (:func:`paper_state_compiled`) of the last ``depth`` decisions, oldest first,
    ``26·depth`` float32 numbers; the last 26 are the current decision's eq. 3. Blocks before the episode's first
    decision are all zeros (a real block is all zeros only for a stopped ego, heading straight, alone on the road)."""

    def __init__(self, depth: int = STACK_DEPTH) -> None:
        self.frames = np.zeros((depth, OBS_SIZE), dtype=np.float32)

    def reset(self, snap: RoadSnapshot) -> np.ndarray:
        """The state at an episode's first decision: ``depth − 1`` zero blocks, then eq. 3 of ``snap``."""
        self.frames[:] = 0.0
        self.frames[-1] = paper_state_compiled(snap)
        return self.frames.ravel().copy()

    def update(self, snap: RoadSnapshot) -> np.ndarray:
        """The state one decision on: the oldest block dropped, eq. 3 of ``snap`` appended."""
        self.frames[:-1] = self.frames[1:]
        self.frames[-1] = paper_state_compiled(snap)
        return self.frames.ravel().copy()


class BeliefState:
    """:data:`BELIEF_STATE`: :func:`paper_belief_state` with the posterior of a
    :class:`~safelane.safety.belief.BeliefFilter` over ``mix``'s types (residual deviation ``sigma`` [m/s²]),
    started at each reset and updated at each decision; it reads no car's ``driver_type``."""

    def __init__(self, mix: DriverMix, sigma: float = SIGMA) -> None:
        self.filter = BeliefFilter(mix, sigma)

    def reset(self, snap: RoadSnapshot) -> np.ndarray:
        """Every car at the mixture's weights."""
        return paper_belief_state(snap, self.filter.reset(snap))

    def update(self, snap: RoadSnapshot) -> np.ndarray:
        """One decision observed."""
        return paper_belief_state(snap, self.filter.update(snap))


class _StatelessState:
    """A state computed from the current snapshot alone, with the reset/update interface of the states with a
    memory."""

    def __init__(self, state_of: Callable[[RoadSnapshot], np.ndarray]) -> None:
        self.reset = self.update = state_of


def lane_position(snap: RoadSnapshot) -> np.ndarray:
    """(2,) float32: the ego's offset from its lane's centre / (lane width / 2) and its lane index /
    (lanes − 1) (0 on a one-lane road), clipped to [-1, 1]: what eq. 3 lacks for steering (its heading is
    already eq. 3's last number)."""
    lanes = snap.lanes_count
    out = np.array(
        [
            2.0 * snap.ego_lane_offset / snap.lane_width,
            int(snap.lane[snap.ego]) / (lanes - 1) if lanes > 1 else 0.0,
        ],
        dtype=np.float32,
    )
    return np.clip(out, -1.0, 1.0, out=out)


class PaperObservation(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Replace the simulator's observation by the paper's 26-number state (eq. 3), or with
    ``state="lanes"`` by :func:`lane_state` (same size), computed from ``info["snapshot"]``; ``info``
    gains ``state`` (the state's name), so a trained policy can check it reads what it learned on.
    ``continuous``: eq. 3 followed by :func:`lane_position` (28 numbers, for acceleration and steering).
    ``state="paper-types"``: :func:`paper_types_state` with ``driver_types`` types (``traffic.driver_mix``'s);
    ``"paper-belief"``: :class:`BeliefState` over ``driver_mix``; ``"paper-stack"``: :class:`StackedState`."""

    def __init__(
        self, env: gym.Env, state: str = "paper", continuous: bool = False, driver_types: int = 0,
        driver_mix: DriverMix | None = None,
    ) -> None:  # fmt: skip
        gym.utils.RecordConstructorArgs.__init__(
            self, state=state, continuous=continuous, driver_types=driver_types, driver_mix=driver_mix
        )
        super().__init__(env)
        if state not in STATES:
            raise ConfigError(f"state: got {state!r}; allowed: {', '.join(STATES)}")
        if continuous and state != "paper":
            raise ConfigError(f"state: got {state!r} with continuous actions; allowed: paper")
        if state == BELIEF_STATE:
            if driver_mix is None:
                raise ConfigError(f"state: {BELIEF_STATE!r} needs traffic.driver_mix (got none)")
            driver_types = len(driver_mix.types)
        if state in MIXTURE_STATES and driver_types < 1:
            raise ConfigError(f"state: {state!r} needs traffic.driver_mix (got {driver_types} driver types)")
        self.memory: Any
        if state == TYPED_STATE:
            self.memory = _StatelessState(functools.partial(paper_types_state, types=driver_types))
        elif state == BELIEF_STATE:
            assert driver_mix is not None
            self.memory = BeliefState(driver_mix)
        elif state == STACKED_STATE:
            self.memory = StackedState()
        else:
            state_of = STATE_FUNCTIONS[state]
            self.memory = _StatelessState(_with_lane_position(state_of) if continuous else state_of)
        size = state_size(state, continuous, driver_types)
        self.observation_space = gym.spaces.Box(-1.0, 1.0, shape=(size,), dtype=np.float32)
        self.state = state

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        _, info = self.env.reset(**kwargs)
        info["state"] = self.state
        return self.memory.reset(info["snapshot"]), info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        _, reward, terminated, truncated, info = self.env.step(action)
        info["state"] = self.state
        return self.memory.update(info["snapshot"]), reward, terminated, truncated, info
