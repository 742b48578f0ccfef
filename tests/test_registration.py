"""Gymnasium ids (safelane.env.registration): gym.make / gym.make_vec, their keywords, and the clients that use them:
SB3's make_vec_env with MaskablePPO, a CleanRL-style loop on gym.make_vec, RL Zoo's train script."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import safelane
from safelane.config import ConfigError
from safelane.env.registration import ENV_IDS, env_config, register_envs
from safelane.env.vector import FastVectorEnv, SafelaneVectorEnv

REPO_ROOT = Path(__file__).resolve().parents[1]
FAST_ID, HIGHWAY_ID = "safelane/HighwayFast-v0", "safelane/Highway-v0"
HIDDEN_FAST_ID, HIDDEN_ID = "safelane/HighwayHiddenTypesFast-v0", "safelane/HighwayHiddenTypes-v0"
SHORT = {"env.duration": 4}  # [s] four decisions an episode at the presets' 1 decision/s


def test_ids_registered_on_import_and_registration_idempotent() -> None:
    assert set(ENV_IDS) == {
        FAST_ID, HIGHWAY_ID, "safelane/HighwayContinuous-v0", "safelane/HighwayContinuousFast-v0", HIDDEN_ID,
        HIDDEN_FAST_ID,
    }  # fmt: skip
    assert all(env_id in gym.registry for env_id in ENV_IDS)
    entry = gym.spec(FAST_ID).entry_point
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # gymnasium warns when an id is registered twice
        register_envs()
    assert gym.spec(FAST_ID).entry_point == entry


def test_module_prefix_makes_the_env_without_importing_safelane() -> None:
    """gymnasium >= 1.0 loads no plugin entry points: ``"safelane:ID"`` imports the package for the caller."""
    code = (
        "import sys, gymnasium as gym\n"
        "assert 'safelane' not in sys.modules\n"
        f"env = gym.make('safelane:{FAST_ID}', config={{'env.duration': 2}})\n"
        "obs, info = env.reset(seed=3)\n"
        "print(env.spec.id, obs.shape, info['action_mask'].shape)\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO_ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == [FAST_ID, "(26,)", "(5,)"]


def _play(env: gym.Env, seed: int, actions: list[int]) -> list[tuple[np.ndarray, float, bool, bool, np.ndarray]]:
    obs, info = env.reset(seed=seed)
    rows = [(obs, 0.0, False, False, info["action_mask"])]
    for action in actions:
        obs, reward, terminated, truncated, info = env.step(action)
        rows.append((obs, float(reward), terminated, truncated, info["action_mask"]))
        if terminated or truncated:
            break
    return rows


def _same(a: list, b: list) -> None:
    assert len(a) == len(b)
    for row_a, row_b in zip(a, b, strict=True):
        np.testing.assert_array_equal(row_a[0], row_b[0])
        assert row_a[1:4] == row_b[1:4]
        np.testing.assert_array_equal(row_a[4], row_b[4])


def test_fast_id_is_make_env_on_the_fast_simulator_with_the_robust_shield() -> None:
    actions = [3, 3, 0, 1, 4, 2]
    env = gym.make(FAST_ID)
    ref = safelane.make_env("fast", simulator="fast", **{"shield.mode": "robust"})
    try:
        cfg = env.get_wrapper_attr("safelane_config")
        assert (cfg.simulator, cfg.preset, cfg.env_id) == ("fast", "fast", "highway-fast-v0")
        assert (cfg.shield.mode, cfg.shield.override) == ("robust", False)
        assert env.spec is not None and env.spec.id == FAST_ID
        _same(_play(env, 11, actions), _play(ref, 11, actions))
        assert env.get_wrapper_attr("action_masks")().shape == (5,)
    finally:
        env.close()
        ref.close()


def test_highway_id_runs_highway_env_and_plays_the_fast_ids_episode() -> None:
    """The two ids are one environment on two simulators: the same episode from the same seed."""
    actions = [3, 1, 3, 4]
    envs = [gym.make(env_id, config=SHORT) for env_id in (HIGHWAY_ID, FAST_ID)]
    try:
        cfg = envs[0].get_wrapper_attr("safelane_config")
        assert cfg.simulator == "highway-env"
        assert type(envs[0].unwrapped).__module__.startswith("highway_env")
        _same(_play(envs[0], 5, actions), _play(envs[1], 5, actions))
    finally:
        for env in envs:
            env.close()


def test_hidden_types_ids_are_the_preset_on_both_simulators() -> None:
    """The two ids play one episode of the hidden-types preset from the same seed; the matched arm through config."""
    actions = [3, 1, 0, 4]
    envs = [gym.make(env_id, config=SHORT) for env_id in (HIDDEN_ID, HIDDEN_FAST_ID)]
    try:
        for env, simulator in zip(envs, ("highway-env", "fast"), strict=True):
            cfg = env.get_wrapper_attr("safelane_config")
            assert (cfg.preset, cfg.simulator, cfg.traffic.driver_mix) == ("hidden-types", simulator,
                                                                           "timid-normal-aggressive")  # fmt: skip
            assert not cfg.traffic.shield_sees_types and cfg.state == "paper"
        _same(_play(envs[0], 4, actions), _play(envs[1], 4, actions))
    finally:
        for env in envs:
            env.close()
    seen = gym.make(HIDDEN_FAST_ID, config={"state": "paper-types", "traffic.shield_sees_types": True, **SHORT})
    try:
        obs, info = seen.reset(seed=4)
        assert obs.shape == (26 + 4 * 3,) and info["snapshot"].driver_type is not None
    finally:
        seen.close()
    # Unshielded, the fast batch plays the mixture; the robust shield judges one reading per type, per environment.
    for shield, kind in (("none", FastVectorEnv), ("robust", SafelaneVectorEnv)):
        vec = gym.make_vec(HIDDEN_FAST_ID, num_envs=2, shield=shield, config=SHORT)
        try:
            obs, _ = vec.reset(seed=0)
            assert isinstance(vec, kind) and obs.shape == (2, 26)
        finally:
            vec.close()


def test_keywords_reach_the_config() -> None:
    cfg = env_config("fast", preset="paper", shield="nominal", override=True, config={"env": {"lanes_count": 3}})
    assert (cfg.preset, cfg.env_id, cfg.simulator) == ("paper", "highway-v0", "fast")
    assert (cfg.shield.mode, cfg.shield.override, cfg.env["lanes_count"]) == ("nominal", True, 3)
    assert env_config("fast", config={"shield.margin": 2.0}).shield.margin == 2.0
    env = gym.make(FAST_ID, shield="none", config={"env.lanes_count": 2, **SHORT})
    try:
        _, info = env.reset(seed=0)
        assert "action_mask" not in info
        assert info["snapshot"].lanes_count == 2
    finally:
        env.close()


def test_override_keyword_replaces_unsafe_actions() -> None:
    """Always FASTER: with override the shield steps in at some decision, without it never."""
    counts = {}
    for override in (False, True):
        env = gym.make(FAST_ID, override=override, config={"env.vehicles_density": 2.0})
        try:
            env.reset(seed=2)
            done, intervened = False, 0
            while not done:
                _, _, terminated, truncated, info = env.step(3)
                intervened += bool(info["shield_intervened"])
                done = terminated or truncated
            counts[override] = intervened
        finally:
            env.close()
    assert counts[False] == 0
    assert counts[True] > 0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"shield": "strong"}, "shield: unknown shield 'strong'; allowed: none, nominal, robust"),
        ({"override": "yes"}, "override: must be True or False"),
        ({"shield": "none", "override": True}, "override: needs a shield"),
        ({"config": {"simulator": "highway-env"}}, "config: 'simulator' is chosen by the id"),
        ({"config": {"shield": {"mode": "none"}}}, "config: 'shield.mode' is chosen by the id or a keyword"),
        ({"config": ["env.lanes_count=3"]}, "config: a dict of settings"),
        ({"preset": "slow"}, "preset: unknown preset 'slow'; allowed: fast, paper"),
    ],
)
def test_bad_keywords_are_one_line_errors(kwargs: dict, message: str) -> None:
    with pytest.raises(ConfigError) as err:
        gym.make(FAST_ID, **kwargs)
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_make_vec_returns_the_batched_fast_simulator() -> None:
    vec = gym.make_vec(FAST_ID, num_envs=3, config=SHORT)
    singles = [gym.make(FAST_ID, config=SHORT) for _ in range(3)]
    try:
        assert isinstance(vec, FastVectorEnv)
        assert vec.spec is not None and vec.spec.id == FAST_ID and vec.num_envs == 3
        obs, infos = vec.reset(seed=20)
        for i, env in enumerate(singles):  # environment i is reset with seed + i
            single_obs, single_info = env.reset(seed=20 + i)
            np.testing.assert_array_equal(obs[i], single_obs)
            np.testing.assert_array_equal(infos["action_mask"][i], single_info["action_mask"])
        np.testing.assert_array_equal(vec.action_masks(), infos["action_mask"])
    finally:
        vec.close()
        for env in singles:
            env.close()
    highway = gym.make_vec(HIGHWAY_ID, num_envs=2, config=SHORT)
    try:
        assert isinstance(highway, SafelaneVectorEnv)
        assert highway.action_masks().shape == (2, 5)
    finally:
        highway.close()
    subprocesses = gym.make_vec(HIGHWAY_ID, num_envs=2, vectorization_mode="async", config=SHORT)
    fast = gym.make(FAST_ID, config=SHORT)
    try:  # gymnasium's own vectorizer: each subprocess builds the id from its entry point
        obs, infos = subprocesses.reset(seed=20)
        np.testing.assert_array_equal(obs[1], fast.reset(seed=21)[0])
        assert infos["action_mask"].shape == (2, 5)
    finally:
        subprocesses.close()
        fast.close()


def test_cleanrl_style_loop_on_make_vec() -> None:
    """The loop CleanRL's scripts run: masked random actions, episode returns read from infos["episode"]."""
    envs = gym.make_vec(FAST_ID, num_envs=4, config=SHORT)
    rng = np.random.default_rng(0)
    returns: list[float] = []
    try:
        obs, infos = envs.reset(seed=1)
        masks = infos["action_mask"]
        for _ in range(10):
            actions = np.array([rng.choice(np.flatnonzero(m)) for m in masks])
            obs, rewards, terminations, truncations, infos = envs.step(actions)
            assert obs.shape == (4, 26) and rewards.shape == (4,)
            masks = infos["action_mask"]
            finished = infos.get("_episode", np.zeros(4, dtype=bool))
            np.testing.assert_array_equal(finished, terminations | truncations)
            if "episode" in infos:
                returns += [float(r) for r in infos["episode"]["r"][infos["_episode"]]]
    finally:
        envs.close()
    assert len(returns) >= 4  # every environment finished at least one four-decision episode
    assert all(np.isfinite(returns))


def test_sb3_make_vec_env_with_maskable_ppo() -> None:
    """SB3's make_vec_env builds the id; MaskablePPO reads each environment's mask through env_method."""
    from sb3_contrib import MaskablePPO
    from sb3_contrib.common.maskable.utils import get_action_masks
    from stable_baselines3.common.env_util import make_vec_env

    vec = make_vec_env(FAST_ID, n_envs=2, seed=0, env_kwargs={"config": SHORT})
    try:
        vec.reset()
        masks = get_action_masks(vec)
        assert masks.shape == (2, 5) and masks.dtype == bool
        model = MaskablePPO("MlpPolicy", vec, n_steps=16, batch_size=16, n_epochs=1, seed=0, device="cpu")
        model.learn(total_timesteps=32)
        obs = vec.reset()
        action, _ = model.predict(obs, action_masks=get_action_masks(vec), deterministic=True)
        assert all(get_action_masks(vec)[i, a] for i, a in enumerate(action))
    finally:
        vec.close()


def test_sb3_vec_env_over_make_vec() -> None:
    """The batched environment as SB3's VecEnv (safelane.sb3_vec_env): MaskablePPO trains on it."""
    from sb3_contrib import MaskablePPO

    vec = safelane.sb3_vec_env(gym.make_vec(FAST_ID, num_envs=2, config=SHORT))
    try:
        model = MaskablePPO("MlpPolicy", vec, n_steps=8, batch_size=16, n_epochs=1, seed=0, device="cpu")
        model.learn(total_timesteps=16)
        assert np.asarray(vec.env_method("action_masks")).shape == (2, 5)
    finally:
        vec.close()


RL_ZOO_DECISIONS = 8  # [decisions] an episode: env.duration 8 s at one decision a second
RL_ZOO_CONF = f"""\
safelane/HighwayFast-v0:
  policy: MlpPolicy
  n_timesteps: 200
  learning_starts: 50
  buffer_size: 1000
  batch_size: 16
  train_freq: 4
  env_kwargs:
    override: true
    config: {{env.duration: {RL_ZOO_DECISIONS}}}
  monitor_kwargs: "dict(info_keywords=('crashed', 'shield_intervened'))"  # RL Zoo evaluates it: SB3 needs a tuple
"""


def test_rl_zoo_trains_a_dqn_on_the_id(tmp_path) -> None:
    """RL Zoo's train script, as its users run it: the id, ``--gym-packages safelane`` and a hyperparameter file.
    Its DQN reads no mask, so the file asks for ``override``: every monitored episode runs its full length
    without a crash, the model is saved for the environment's spaces."""
    if importlib.util.find_spec("rl_zoo3") is None:  # make test installs it (Makefile: the rl_zoo3 line)
        pytest.fail("rl_zoo3 is not installed: pip install --no-deps rl_zoo3==2.9.2 sb3-team-hf-integration==3.2")
    from stable_baselines3 import DQN

    conf = tmp_path / "dqn.yml"
    conf.write_text(RL_ZOO_CONF)
    logs = tmp_path / "logs"
    cmd = [
        sys.executable, "-m", "rl_zoo3.train", "--algo", "dqn", "--env", FAST_ID, "--gym-packages", "safelane",
        "-n", "200", "--conf-file", str(conf), "--log-folder", str(logs), "--seed", "0",
        "--eval-freq", "-1", "--save-freq", "-1", "--vec-env", "dummy",
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO_ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    run = logs / "dqn" / "safelane-HighwayFast-v0_1"
    header, columns, *rows = (run / "0.monitor.csv").read_text().splitlines()
    assert f'"env_id": "{FAST_ID}"' in header
    assert columns == "r,l,t,crashed,shield_intervened"
    episodes = [row.split(",") for row in rows]
    assert len(episodes) == 200 // RL_ZOO_DECISIONS  # every episode ran its eight decisions: none crashed
    assert {(length, crashed) for _, length, _, crashed, _ in episodes} == {(str(RL_ZOO_DECISIONS), "False")}
    model = DQN.load(run / "safelane-HighwayFast-v0.zip", device="cpu")
    assert model.observation_space.shape == (26,) and model.action_space.n == 5
    assert model.num_timesteps == 200
