"""The environment on the real highway-env: API conformance, the paper's state (eq. 3) on a
hand-built road, the reward (eq. 6), info fields, determinism and the traffic layout."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from safelane.config import ConfigError, load_config
from safelane.core.spaces import OBS_SIZE
from safelane.env import observations as safelane_env
from safelane.env.factory import make_env
from safelane.env.observations import PaperObservation, lane_state, paper_state
from safelane.env.reward import PaperReward
from safelane.sim.highway import DiscardedObservation, HighwayEnvAdapter, snapshot_of

MakeEnv = Callable[..., gym.Env]


def reward_wrapper(env: gym.Env) -> PaperReward:
    """The PaperReward layer of a wrapped env."""
    layer: Any = env
    while not isinstance(layer, PaperReward):
        layer = layer.env
    return layer


# --- API conformance ---------------------------------------------------------------------------------


def test_gymnasium_env_checker_passes() -> None:
    env = make_env(seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "wrapped env" and highway-env's unbounded Box warnings
        check_env(env, skip_render_check=True)
        check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_observation_is_26_float32_numbers_in_the_space(make_fast_env: MakeEnv) -> None:
    env = make_fast_env()
    obs, _ = env.reset(seed=3)
    assert obs.shape == (OBS_SIZE,) == (26,)
    assert obs.dtype == np.float32
    assert env.observation_space.contains(obs)
    obs, *_, info = env.step(1)
    assert obs.shape == (26,) and obs.dtype == np.float32
    assert env.observation_space.contains(obs)
    assert env.action_space.n == 5
    # The observation is eq. 3 of the step's own road snapshot, which is the scene highway-env holds.
    np.testing.assert_array_equal(obs, paper_state(info["snapshot"]))
    np.testing.assert_array_equal(info["snapshot"].position, snapshot_of(env.unwrapped).position)


def test_same_seed_gives_identical_first_50_observations(make_fast_env: MakeEnv) -> None:
    def rollout() -> np.ndarray:
        env = make_fast_env()
        actions = np.random.default_rng(7).integers(5, size=50)
        obs, _ = env.reset(seed=11)
        seen = [obs]
        for action in actions[:49]:
            obs, _, terminated, truncated, _ = env.step(int(action))
            if terminated or truncated:
                obs, _ = env.reset()  # continues the seeded RNG
            seen.append(obs)
        return np.stack(seen)

    first, second = rollout(), rollout()
    assert first.shape == (50, 26)
    np.testing.assert_array_equal(first, second)
    assert not np.array_equal(first[0], first[-1])


def test_different_seeds_give_different_scenes(make_fast_env: MakeEnv) -> None:
    env = make_fast_env()
    a, _ = env.reset(seed=0)
    b, _ = env.reset(seed=1)
    assert not np.array_equal(a, b)


# --- the paper's state (eq. 3) on a hand-built road -------------------------------------------------------


def test_documented_scales() -> None:
    # The hand-computed numbers below use these values.
    assert safelane_env.X_SCALE == 100.0
    assert safelane_env.Y_SCALE == 12.0
    assert safelane_env.REL_SPEED_SCALE == 20.0
    assert pytest.approx(math.pi / 2) == safelane_env.HEADING_SCALE
    assert safelane_env.EGO_SPEED_SCALE == 40.0
    assert safelane_env.PERCEPTION_DISTANCE == 200.0


def test_paper_state_on_a_hand_built_road(make_fast_env: MakeEnv, scene: Callable[..., list[Any]]) -> None:
    env = make_fast_env()
    # Ego in lane 1 (y = 4 m) at x = 100 m, 25 m/s, heading 0.
    scene(
        env,
        ego=(100.0, 1, 25.0),
        others=[
            (130.0, 4.0, 20.0, 0.0),  # A: same lane, 30 m ahead, 5 m/s slower          (distance 30)
            (90.0, 8.0, 30.0, 0.1),  # B: lane 2, 10 m behind, 30 m/s heading 0.1 rad  (distance 10.77)
            (260.0, 4.0, 25.0, 0.0),  # D: 160 m ahead: offset clipped to 1             (distance 160)
            (350.0, 4.0, 25.0, 0.0),  # E: 250 m ahead, beyond 200 m and 5th anyway
            (100.0, 0.0, 25.0, 0.0),  # C: lane 0 alongside, same speed                 (distance 4)
        ],
    )
    h = 0.1
    expected = np.array(
        [
            # C: δx 0, δy −4 m, δv 0, heading 0
            0.0, -4 / 12, 0.0, 0.0, 0.0, 1.0,
            # B: δx −10 m, δy +4 m, δvx 30·cos(0.1) − 25, δvy 30·sin(0.1), heading 0.1 rad
            -0.1, 4 / 12, (30 * math.cos(h) - 25) / 20, 30 * math.sin(h) / 20, h / (math.pi / 2), 1.0,
            # A: δx 30 m, δy 0, δvx −5 m/s
            0.3, 0.0, -0.25, 0.0, 0.0, 1.0,
            # D: δx 160 m → 1.6, clipped to 1
            1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
            # ego: 25 m/s of 40, heading 0
            0.625, 0.0,
        ],
        dtype=np.float32,
    )  # fmt: skip
    state = paper_state(snapshot_of(env.unwrapped))
    assert state.dtype == np.float32
    np.testing.assert_allclose(state, expected, atol=1e-6)


def test_paper_state_zeroes_absent_vehicles(make_fast_env: MakeEnv, scene: Callable[..., list[Any]]) -> None:
    env = make_fast_env()
    scene(
        env,
        ego=(50.0, 2, 20.0),
        others=[
            (350.0, 8.0, 25.0, 0.0),  # 300 m ahead: beyond the perception distance → absent
            (42.0, 12.0, 22.0, 0.0),  # lane 3, 8 m behind, 2 m/s faster
        ],
    )
    state = paper_state(snapshot_of(env.unwrapped))
    expected = np.zeros(26, dtype=np.float32)
    expected[:6] = [-0.08, 4 / 12, 0.1, 0.0, 0.0, 1.0]
    expected[-2:] = [0.5, 0.0]
    np.testing.assert_allclose(state, expected, atol=1e-6)
    assert state[6:24].tolist() == [0.0] * 18  # three absent vehicles: all zeros, flag 0


def test_paper_state_with_an_empty_road(make_fast_env: MakeEnv, scene: Callable[..., list[Any]]) -> None:
    env = make_fast_env()
    scene(env, ego=(10.0, 0, 30.0), others=[])
    state = paper_state(snapshot_of(env.unwrapped))
    assert state[:24].tolist() == [0.0] * 24
    assert state[24] == pytest.approx(0.75)


def test_lane_state_on_a_hand_built_road(make_fast_env: MakeEnv, scene: Callable[..., list[Any]]) -> None:
    env = make_fast_env(state="lanes")
    # Ego in lane 1 of 4 (y = 4 m) at x = 100 m, 25 m/s, set-point 25 m/s.
    scene(
        env,
        ego=(100.0, 1, 25.0),
        others=[
            (130.0, 4.0, 20.0, 0.0),  # own lane, 30 m ahead, 5 m/s slower: first leader
            (200.0, 4.0, 25.0, 0.0),  # own lane, 100 m ahead: second leader
            (240.0, 4.0, 25.0, 0.0),  # own lane, third ahead: not in the state
            (100.0, 0.0, 25.0, 0.0),  # lane 0 (left), alongside: a leader at gap 0
            (90.0, 8.0, 30.0, 0.1),  # lane 2 (right), 10 m behind, forward speed 30·cos(0.1)
            (350.0, 8.0, 25.0, 0.0),  # lane 2, 250 m ahead: beyond 150 m, absent
        ],
    )
    expected = np.array(
        [
            # left lane: exists, leader at gap 0 with δv 0, no second leader, no follower
            1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0,
            # own lane: leaders at 30 m (−5 m/s) and 100 m (0), no follower
            1.0, 30 / 150, -5 / 20, 100 / 150, 0.0, 1.0, 0.0,
            # right lane: nothing ahead within 150 m, follower 10 m behind
            1.0, 1.0, 0.0, 1.0, 0.0, 10 / 150, (30 * math.cos(0.1) - 25) / 20,
            # ego: 25 m/s, heading 0, lane 1 of 0..3, on the lane centre, set-point 25 m/s
            25 / 40, 0.0, 1 / 3, 0.0, 25 / 40,
        ],
        dtype=np.float32,
    )  # fmt: skip
    np.testing.assert_allclose(lane_state(snapshot_of(env.unwrapped)), expected, atol=1e-6)


def test_lane_state_at_the_road_edge(make_fast_env: MakeEnv, scene: Callable[..., list[Any]]) -> None:
    env = make_fast_env(state="lanes")
    ego, *_ = scene(env, ego=(50.0, 0, 20.0), others=[(45.0, 4.0, 22.0, 0.0)])
    ego.position[1] += 1.0  # 1 m off its lane centre, towards lane 1
    state = lane_state(snapshot_of(env.unwrapped))
    assert state[:7].tolist() == [0.0] * 7  # no lane left of lane 0
    np.testing.assert_allclose(state[7:14], [1, 1, 0, 1, 0, 1, 0])  # own lane empty
    np.testing.assert_allclose(state[14:21], [1, 1, 0, 1, 0, 5 / 150, 2 / 20], atol=1e-6)
    np.testing.assert_allclose(state[21:], [0.5, 0.0, 0.0, 0.25, 0.5], atol=1e-6)


def test_lane_state_episodes_are_valid_and_deterministic(make_fast_env: MakeEnv) -> None:
    def rollout() -> np.ndarray:
        env = make_fast_env(state="lanes")
        obs, _ = env.reset(seed=11)
        states = [obs]
        for action in [1, 3, 0, 1, 2, 4, 1, 1]:
            obs, *_ = env.step(action)
            states.append(obs)
        return np.array(states)

    a, b = rollout(), rollout()
    assert a.shape == (9, OBS_SIZE) and a.dtype == np.float32
    assert np.all(np.abs(a) <= 1.0) and np.array_equal(a, b)
    assert set(a[:, 0::7][:, :3].ravel()) <= {0.0, 1.0}  # the lane-exists flags


def test_unknown_state_is_a_one_line_error() -> None:
    with pytest.raises(ConfigError, match="state"):
        make_env("fast", state="pixels")


# --- reward (eq. 6) and info ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("speed", "collision", "reward"),
    [
        (15.0, False, 0.5),  # halfway between v_min 0 and v_max 30
        (0.0, False, 0.0),
        (-2.0, False, 0.0),  # clipped below (reversing)
        (30.0, False, 1.0),
        (38.0, False, 1.0),  # clipped above
        (15.0, True, 0.5 - 10.0),  # c = 10
        (0.0, True, -10.0),
    ],
)
def test_reward_eq6_on_known_speeds(make_fast_env: MakeEnv, speed: float, collision: bool, reward: float) -> None:
    assert reward_wrapper(make_fast_env()).reward_of(speed, collision) == pytest.approx(reward)


def test_reward_uses_the_configured_weights(make_fast_env: MakeEnv) -> None:
    env = make_fast_env(reward={"b": 2.0, "c": 4.0, "v_min": 10.0, "v_max": 30.0})
    layer = reward_wrapper(env)
    assert layer.reward_of(15.0, False) == pytest.approx(2.0 * 0.25)
    assert layer.reward_of(15.0, True) == pytest.approx(0.5 - 4.0)


def test_info_fields_and_step_reward(make_fast_env: MakeEnv) -> None:
    env = make_fast_env()
    _, info = env.reset(seed=5)
    assert info["collision"] is False
    assert info["speed"] == pytest.approx(25.0)
    _, reward, _, _, info = env.step(1)
    assert isinstance(info["speed"], float) and isinstance(info["collision"], bool)
    assert reward == pytest.approx(reward_wrapper(env).reward_of(info["forward_speed"], info["collision"]))
    assert "highway_reward" in info


def test_crash_sets_collision_ends_the_episode_and_costs_c(
    make_fast_env: MakeEnv, scene: Callable[..., list[Any]]
) -> None:
    env = make_fast_env()
    scene(env, ego=(100.0, 1, 25.0), others=[(110.0, 4.0, 0.0, 0.0)])  # stopped car 10 m ahead
    _, reward, terminated, _, info = env.step(1)  # IDLE: 25 m/s into it
    assert info["collision"] is True and info["crashed"] is True
    assert terminated
    assert reward == pytest.approx(reward_wrapper(env).reward_of(info["forward_speed"], True))
    assert reward < -9.0


def test_make_env_rejects_what_highway_env_would_ignore() -> None:
    with pytest.raises(ConfigError, match=r"^env\.lanes_countt: "):
        make_env(env={"lanes_countt": 3})


def test_make_env_accepts_a_config_object_and_overrides() -> None:
    cfg = load_config("fast", sets=["env.lanes_count=3"])
    env = make_env(cfg, env={"vehicles_count": 10}, seed=1)
    base = env.unwrapped
    assert base.config["lanes_count"] == 3
    assert len(base.road.vehicles) == 11
    assert isinstance(env, PaperObservation)
    env.close()


# --- traffic layout --------------------------------------------------------------------------------------


def _xs_behind(env: gym.Env) -> tuple[int, int, np.ndarray]:
    base = env.unwrapped
    ego = base.vehicle
    others = [v for v in base.road.vehicles if v is not ego]
    behind = sum(v.position[0] < ego.position[0] for v in others)
    return behind, len(base.road.vehicles), np.array([v.position for v in base.road.vehicles])


def test_stock_scene_spawns_the_ego_behind_everybody(make_fast_env: MakeEnv) -> None:
    behind, total, _ = _xs_behind(make_fast_env(seed=4))
    assert behind == 0
    assert total == 51


def test_vehicles_behind_moves_traffic_behind_the_ego(make_fast_env: MakeEnv) -> None:
    first = make_fast_env(seed=4, **{"traffic.vehicles_behind": 15})
    behind, total, positions = _xs_behind(first)
    assert behind == 15
    assert total == 51  # same vehicle count as the stock scene
    # Followers sit on lane centres, one vehicle length or more apart and behind the ego's rear.
    ego = first.unwrapped.vehicle
    followers = [v for v in first.unwrapped.road.vehicles if v.position[0] < ego.position[0]]
    assert {v.position[1] for v in followers} <= {0.0, 4.0, 8.0, 12.0}
    xs = np.sort([v.position[0] for v in followers] + [ego.position[0]])
    assert np.diff(xs).min() > ego.LENGTH
    # Deterministic for a seed.
    again = make_fast_env(seed=4, **{"traffic.vehicles_behind": 15})
    np.testing.assert_array_equal(positions, _xs_behind(again)[2])
    obs_a, _ = first.reset(seed=9)
    obs_b, _ = again.reset(seed=9)
    np.testing.assert_array_equal(obs_a, obs_b)


def test_discarding_highway_envs_own_observation_leaves_episodes_unchanged(monkeypatch: pytest.MonkeyPatch) -> None:
    """The adapter swaps highway-env's (discarded) Kinematics observation for a constant; the
    episode — states, rewards, speeds — is the same as with highway-env computing it every step."""

    def episode() -> list[tuple[np.ndarray, float, float]]:
        env = make_env("fast")
        rng = np.random.default_rng(3)
        env.reset(seed=11)
        steps, done = [], False
        while not done and len(steps) < 15:
            obs, reward, terminated, truncated, info = env.step(int(rng.integers(5)))
            steps.append((obs, reward, info["speed"]))
            done = terminated or truncated
        assert isinstance(env.unwrapped.observation_type, DiscardedObservation) == swapped
        return steps

    swapped = True
    with_swap = episode()
    monkeypatch.setattr(HighwayEnvAdapter, "_discard_own_observation", staticmethod(lambda base: None))
    swapped = False
    without = episode()
    assert len(with_swap) == len(without) > 3
    for (o1, r1, v1), (o2, r2, v2) in zip(with_swap, without, strict=True):
        assert np.array_equal(o1, o2) and r1 == r2 and v1 == v2


@pytest.mark.parametrize("simulator", ["highway-env", "fast"])
def test_compiled_states_equal_the_numpy_reference_bit_for_bit(simulator: str) -> None:
    """The environment uses the numba forms of eq. 3 and the lanes state; the numpy functions stay as the
    readable specification and must give the same float32 numbers on every state of real episodes."""
    from safelane.env.observations import lane_state_compiled, paper_state_compiled
    from safelane.running.policies import fixed_policy

    env = make_env("fast", simulator=simulator, **{"env.lanes_count": 3})
    states = 0
    for seed in range(3):
        policy = fixed_policy("random", seed)
        obs, info = env.reset(seed=seed)
        done = False
        while not done:
            snap = info["snapshot"]
            np.testing.assert_array_equal(paper_state_compiled(snap), paper_state(snap))
            np.testing.assert_array_equal(lane_state_compiled(snap), lane_state(snap))
            states += 1
            obs, _, terminated, truncated, info = env.step(policy(obs, info))
            done = terminated or truncated
    assert states > 10
    env.close()


def test_compiled_states_on_hand_built_roads(make_fast_env: MakeEnv, scene: Callable[..., list[Any]]) -> None:
    from safelane.env.observations import lane_state_compiled, paper_state_compiled

    env = make_fast_env()
    for others in ([], [(130.0, 4.0, 20.0, 0.0), (130.0, 8.0, 20.0, 0.0), (70.0, 4.0, 30.0, 0.2)]):
        scene(env, ego=(100.0, 1, 25.0), others=others)
        snap = snapshot_of(env.unwrapped)
        np.testing.assert_array_equal(paper_state_compiled(snap), paper_state(snap))
        np.testing.assert_array_equal(lane_state_compiled(snap), lane_state(snap))
