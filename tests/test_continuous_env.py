"""Continuous actions (acceleration and steering): the configuration, the reward, the state, the ids and the fixed
policies, on both simulators."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from typer.testing import CliRunner

from safelane.cli import app
from safelane.config import ConfigError, load_config
from safelane.core.spaces import CONTINUOUS_OBS_SIZE, OBS_SIZE
from safelane.env.factory import make_env
from safelane.env.reward import ContinuousReward, off_road
from safelane.running.evaluation import run_episodes
from safelane.running.policies import CONTINUOUS_POLICIES, continuous_policy, continuous_ranges

SHORT = {"env.duration": 10, "env.vehicles_count": 10}
REPO_ROOT = Path(__file__).resolve().parents[1]


def continuous_env(simulator: str = "fast", **overrides: Any) -> gym.Env:
    return make_env("fast", simulator=simulator, actions="continuous", **{**SHORT, **overrides})


def test_continuous_actions_become_highway_envs_continuous_action() -> None:
    """``actions: continuous`` swaps the preset's meta-actions for ContinuousAction (its own keys kept), and ends
    the episode off the road unless told otherwise."""
    cfg = load_config("fast", sets=["actions=continuous"])
    assert cfg.env["action"] == {"type": "ContinuousAction"}
    assert cfg.env["offroad_terminal"] is True
    cfg = load_config("fast", sets=["actions=continuous", "env.action.clip=false", "env.offroad_terminal=false"])
    assert cfg.env["action"] == {"clip": False, "type": "ContinuousAction"}
    assert cfg.env["offroad_terminal"] is False
    assert load_config("fast").env["action"]["type"] == "DiscreteMetaAction"


@pytest.mark.parametrize(
    ("sets", "starts"),
    [
        (["actions=continuous", "shield.mode=robust"], "shield.mode: 'robust' decides among meta-actions"),
        (["actions=continuous", "state=lanes"], "state: 'lanes' reads the ego's set-point"),
        (["env.action.type=ContinuousAction"], "env.action.type: ContinuousAction needs actions: continuous"),
        (["reward.lane_centring=0.2"], "reward.lane_centring: only for actions: continuous"),
        (["actions=continuous", "env.action.dynamical=true"], "env.action.dynamical: must be false"),
        (["actions=continuous", "env.action.lateral=false"], "env.action.lateral: must be true"),
        (["actions=continuous", "env.action.steering_range=[1, -1]"], "env.action.steering_range: expected two"),
        (["actions=continuous", "env.action.gears=3"], "env.action.gears: unknown key for ContinuousAction"),
        (["actions=sideways"], "actions"),
    ],
)
def test_bad_continuous_settings_are_one_line_errors(sets: list[str], starts: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_config("fast", sets=sets)
    message = str(err.value)
    assert message.startswith(starts), message
    assert "\n" not in message


@pytest.mark.parametrize("simulator", ["fast", "highway-env"])
def test_state_is_eq3_then_the_lane_offset_and_lane(simulator: str) -> None:
    env = continuous_env(simulator)
    obs, info = env.reset(seed=3)
    assert env.observation_space.shape == (CONTINUOUS_OBS_SIZE,) == (OBS_SIZE + 2,)
    assert env.action_space.shape == (2,)
    snap = info["snapshot"]
    for _ in range(3):
        obs, _, _, _, info = env.step(np.array([0.2, 0.05], dtype=np.float32))
        snap = info["snapshot"]
        assert obs.shape == (CONTINUOUS_OBS_SIZE,) and obs.dtype == np.float32
        expected = [
            min(max(2 * snap.ego_lane_offset / snap.lane_width, -1), 1),
            int(snap.lane[snap.ego]) / (snap.lanes_count - 1),
        ]
        assert obs[-2:] == pytest.approx(expected, abs=1e-6)
    assert snap.ego_target_speeds == () and snap.ego_speed_index == -1 and math.isnan(snap.ego_target_speed)


def test_reward_is_eq6_on_forward_speed_times_the_lane_centring_term() -> None:
    """The reward's arithmetic on a recorded state moved across its lane: full pay at the centre, ``1 −
    lane_centring`` at the edge, the collision penalty off the road."""
    env = continuous_env()
    _, info = env.reset(seed=0)
    snap = info["snapshot"]
    reward = ContinuousReward(gym.Env(), b=1.0, c=10.0, v_min=0.0, v_max=30.0, lane_centring=0.5)
    forward = float(snap.speed[snap.ego] * math.cos(snap.heading[snap.ego]))
    for offset, centring in ((0.0, 1.0), (1.0, 1 - 0.5 * 0.25), (2.0, 0.5), (-2.0, 0.5), (3.0, 0.5)):
        moved = dataclasses.replace(snap, ego_lane_offset=offset)
        step_info: dict[str, Any] = {"snapshot": moved}
        assert reward._annotate(step_info) == forward
        assert step_info["off_road"] is (abs(offset) > 2.0) is off_road(moved)
        penalty = 10.0 if step_info["off_road"] else 0.0
        expected = min(forward / 30.0, 1.0) * centring - penalty
        assert reward.reward_of(forward, reward._penalised({**step_info, "collision": False})) == pytest.approx(
            expected
        )


def test_spinning_or_stopping_earns_nothing_and_driving_on_earns_most() -> None:
    """A policy cannot farm the reward by turning in place or standing still: the speed term is progress along the
    road, and leaving it ends the episode with the collision penalty."""
    ranges = continuous_ranges({"type": "ContinuousAction"})
    assert ranges == ((-5.0, 5.0), (-math.pi / 4, math.pi / 4))  # highway-env's own, read from its class

    def returns(policy: Any, episodes: int = 4) -> float:
        env = continuous_env(**{"env.vehicles_count": 1, "env.offroad_terminal": False})
        records = run_episodes(env, policy, episodes, seed=0)
        return float(np.mean([r.return_ for r in records]))

    def spin(obs: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        return np.array([0.0, 1.0], dtype=np.float32)  # full steering lock, throttle 0: circles

    def stop(obs: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        return np.array([-1.0, 0.0], dtype=np.float32)

    faster = returns(continuous_policy("faster", 0, {"type": "ContinuousAction"}))
    random = returns(continuous_policy("random", 0, {"type": "ContinuousAction"}))
    assert faster > 8.0  # 10 decisions, nearly full pay
    assert returns(spin) < 0.25 * faster
    assert returns(stop) < 0.25 * faster
    assert random < 0.5 * faster


@pytest.mark.parametrize("frequency", [1, 5])
def test_the_lane_follower_holds_its_lane_at_full_throttle(frequency: int) -> None:
    env = continuous_env(**{"env.policy_frequency": frequency, "env.vehicles_count": 1, "env.duration": 20})
    policy = continuous_policy("faster", 0, {"type": "ContinuousAction"})
    obs, info = env.reset(seed=1)
    lane = int(info["snapshot"].lane[0])
    done = False
    while not done:
        obs, _, terminated, truncated, info = env.step(policy(obs, info))
        snap = info["snapshot"]
        assert int(snap.lane[snap.ego]) == lane
        assert abs(snap.ego_lane_offset) < 0.5
        done = terminated or truncated
    assert not terminated and snap.ego_speed > 35.0  # highway-env's Vehicle.MAX_SPEED is 40 m/s


def test_the_weaving_probe_changes_lanes_and_stays_on_the_road() -> None:
    env = continuous_env(**{"env.vehicles_count": 1, "env.duration": 30})
    policy = continuous_policy("weave", 0, {"type": "ContinuousAction"})
    obs, info = env.reset(seed=2)
    lanes = {int(info["snapshot"].lane[0])}
    done = False
    while not done:
        obs, _, terminated, truncated, info = env.step(policy(obs, info))
        lanes.add(int(info["snapshot"].lane[0]))
        assert not info["off_road"]
        done = terminated or truncated
    assert len(lanes) >= 3


def test_random_policy_is_seeded() -> None:
    a, b = (continuous_policy("random", 7, {"type": "ContinuousAction"}) for _ in range(2))
    draws = [a(np.zeros(1), {}) for _ in range(5)]
    assert all(np.array_equal(x, b(np.zeros(1), {})) for x in draws)
    assert all(x.dtype == np.float32 and x.shape == (2,) and np.all(np.abs(x) <= 1) for x in draws)
    assert set(CONTINUOUS_POLICIES) == {"random", "faster", "weave"}


@pytest.mark.parametrize("env_id", ["safelane/HighwayContinuous-v0", "safelane/HighwayContinuousFast-v0"])
def test_continuous_ids_make_and_vectorise(env_id: str) -> None:
    env = gym.make(env_id, config={"env.duration": 3})
    obs, info = env.reset(seed=0)
    assert obs.shape == (CONTINUOUS_OBS_SIZE,) and "action_mask" not in info
    env.step(env.action_space.sample())
    with pytest.raises(ConfigError, match=r"^shield\.mode: 'robust' decides among meta-actions"):
        gym.make(env_id, shield="robust")
    vec = gym.make_vec(env_id, num_envs=2, config={"env.duration": 2})
    obs, _ = vec.reset(seed=0)
    obs, rewards, *_ = vec.step(np.zeros((2, 2), dtype=np.float32))
    assert obs.shape == (2, CONTINUOUS_OBS_SIZE) and rewards.shape == (2,)


def test_both_simulators_give_the_same_continuous_episode() -> None:
    """The id pair plays the same episode: observations, rewards and ends equal to the bit."""
    envs = [gym.make(i, config={"env.duration": 8}) for i in ("safelane/HighwayContinuous-v0",
                                                                 "safelane/HighwayContinuousFast-v0")]  # fmt: skip
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(8, 2)).astype(np.float32)
    traces = []
    for env in envs:
        obs, _ = env.reset(seed=11)
        trace = [obs]
        for action in actions:
            obs, reward, terminated, truncated, _ = env.step(action)
            trace += [obs, np.array([reward, terminated, truncated])]
            if terminated or truncated:
                break
        traces.append(trace)
    assert len(traces[0]) == len(traces[1])
    assert all(np.array_equal(a, b) for a, b in zip(*traces, strict=True))


def test_evaluate_continuous_policy_from_the_cli() -> None:
    args = ["evaluate", "--actions", "continuous", "--policy", "faster", "--episodes", "2", "--json"]
    result = CliRunner().invoke(app, [*args, "--set", "env.duration=5"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["episodes"] == 2 and "actions" not in summary
    assert summary["off_road_rate"] == 0.0 and summary["mean_speed"] > 20.0
    result = CliRunner().invoke(app, ["evaluate", "--actions", "continuous", "--policy", "probe"])
    assert result.exit_code == 2
    assert "--policy: unknown continuous policy 'probe'; allowed: random, faster, weave" in result.stderr
    result = CliRunner().invoke(app, ["evaluate", "--actions", "diagonal", "--policy", "faster"])
    assert result.exit_code == 2
    assert "--actions: got 'diagonal'; allowed: discrete, continuous" in result.stderr


def test_sb3_sac_and_ppo_train_on_the_continuous_id() -> None:
    """SB3's SAC and PPO, as their users build them: ``make_vec_env`` on the id, a few updates, a prediction."""
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.env_util import make_vec_env

    short = {"config": {"env.duration": 4}}
    vec = make_vec_env("safelane/HighwayContinuousFast-v0", n_envs=2, seed=0, env_kwargs=short)
    try:
        sac = SAC("MlpPolicy", vec, learning_starts=8, batch_size=8, buffer_size=100, seed=0, device="cpu")
        sac.learn(total_timesteps=24)
        ppo = PPO("MlpPolicy", vec, n_steps=8, batch_size=8, n_epochs=1, seed=0, device="cpu")
        ppo.learn(total_timesteps=16)
        action, _ = ppo.predict(vec.reset(), deterministic=True)
        assert action.shape == (2, 2) and sac.num_timesteps >= 24
    finally:
        vec.close()


def test_rl_zoo_trains_sac_on_the_continuous_id(tmp_path) -> None:
    """RL Zoo's train script with a user's own hyperparameter file for the continuous id."""
    conf = tmp_path / "sac.yml"
    conf.write_text(
        "safelane/HighwayContinuousFast-v0:\n  policy: MlpPolicy\n  n_timesteps: 40\n  learning_starts: 10\n"
        "  buffer_size: 200\n  batch_size: 8\n  env_kwargs:\n    config: {env.duration: 4}\n"
    )
    cmd = [
        sys.executable, "-m", "rl_zoo3.train", "--algo", "sac", "--env", "safelane/HighwayContinuousFast-v0",
        "--gym-packages", "safelane", "-n", "40", "--conf-file", str(conf), "--log-folder", str(tmp_path / "logs"),
        "--seed", "0", "--eval-freq", "-1", "--save-freq", "-1", "--vec-env", "dummy",
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO_ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    from stable_baselines3 import SAC

    model = SAC.load(tmp_path / "logs/sac/safelane-HighwayContinuousFast-v0_1/safelane-HighwayContinuousFast-v0.zip")
    assert model.observation_space.shape == (CONTINUOUS_OBS_SIZE,) and model.action_space.shape == (2,)
    assert model.num_timesteps == 40
