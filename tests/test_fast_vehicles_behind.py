"""``traffic.vehicles_behind`` on the fast simulator against highway-env + safelane's TrafficLayout.

The reset scene (every vehicle's position, speed, lane, MOBIL timer, IDM DELTA and linear gains, and the
generator's state after the draws) is bit-identical; whole episodes give the same vehicles, snapshots,
observations, rewards and crashes; the batch equals the single environments.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import safelane
from safelane import make_env, make_vector_env
from safelane.core.errors import NotSupported
from safelane.core.snapshot import RoadSnapshot
from safelane.env.factory import resolve_env_config
from safelane.env.fast_batch import supports
from safelane.env.vector import FastVectorEnv
from safelane.sim.fast import FastHighwayEnv
from safelane.sim.fast import layout as L
from safelane.sim.fast.check import compare_episode, compare_states, make_oracle, oracle_state, policy_actions
from safelane.sim.fast.scene import build_scene, make_rng, params, resolve_config, spawn_behind, spawn_behind_python

TOL = 1e-6
LINEAR = "highway_env.vehicle.behavior.AggressiveVehicle"


def _preset(name: str) -> tuple[dict, str]:
    data = yaml.safe_load((Path(safelane.__file__).parent / "presets" / f"{name}.yaml").read_text())
    return data["env"], data["env_id"]


def _config(name: str, **env: Any) -> tuple[dict, str]:
    cfg, env_id = _preset(name)
    return {**cfg, **env}, env_id


# (preset, vehicles_behind, highway-env settings on top)
SCENES = [
    ("fast", 5, {}),
    ("fast", 20, {}),
    ("paper", 5, {}),
    ("paper", 20, {}),
    ("fast", 20, {"lanes_count": 2, "vehicles_density": 1.5}),
    ("fast", 5, {"lanes_count": 3, "vehicles_density": 0.7}),
    ("fast", 20, {"lanes_count": 1}),  # integers(1) draws nothing
    ("fast", 20, {"lanes_count": 6, "vehicles_count": 20}),  # every vehicle moves behind the ego
    ("fast", 20, {"other_vehicles_type": LINEAR, "lanes_count": 3}),  # randomize_behavior's gains
]


@pytest.mark.parametrize(("name", "behind", "env"), SCENES)
def test_reset_scene_matches_highway_env(name: str, behind: int, env: dict) -> None:
    """Positions, speeds, headings, lanes, target speeds, timers, DELTAs, linear gains: bit for bit; the
    generator is left in highway-env's state (the rest of the episode draws the same numbers)."""
    cfg, env_id = _config(name, **env)
    oracle = make_oracle(cfg, env_id, vehicles_behind=behind)
    fast = FastHighwayEnv(cfg, env_id, vehicles_behind=behind)
    for seed in range(6):
        oracle.reset(seed=seed)
        fast.reset(seed=seed)
        ref = oracle_state(oracle)
        cause, err, bitwise = compare_states(fast.state(), ref, TOL, full=True)
        assert cause is None, f"seed {seed}: {cause}"
        assert bitwise, f"seed {seed}: reset scene not bit-identical (max error {err})"
        assert np.array_equal(fast.state()["target_lane"], ref["target_lane"])
        vehicles = oracle.unwrapped.road.vehicles
        if "other_vehicles_type" in env:
            gains = np.array([v.ACCELERATION_PARAMETERS for v in vehicles[1:]])
            steering = np.array([v.STEERING_PARAMETERS for v in vehicles[1:]])
            assert np.array_equal(fast.F[1:, L.AP0 : L.AP2 + 1], gains)
            assert np.array_equal(fast.F[1:, L.SP0 : L.SP1 + 1], steering)
        assert np.array_equal(fast.G[1:, L.CHECK].astype(bool), [v.check_collisions for v in vehicles[1:]])
        assert fast.np_random.bit_generator.state == oracle.unwrapped.np_random.bit_generator.state


def test_replayed_draws_equal_the_generators_own_calls() -> None:
    """The numba replay (scene.spawn_behind) equals its Python twin (the generator's integers / uniform
    calls): same arrays, same generator state, whatever the generator's uint32 buffer holds."""
    cfg, env_id = _preset("fast")
    P = params()
    for typ in ("IDMVehicle", "LinearVehicle"):
        for lanes in (1, 2, 4, 5):
            for behind in (1, 7, 30):
                env = {"lanes_count": lanes, "vehicles_count": 30}
                sc = resolve_config(
                    {**cfg, **env, "other_vehicles_type": f"highway_env.vehicle.behavior.{typ}"}, env_id
                )
                for seed in range(8):
                    r1, r2 = make_rng(seed), make_rng(seed)
                    a, b = build_scene(r1, sc, P), build_scene(r2, sc, P)
                    if seed % 2:  # leaves half a raw output in the generator's uint32 buffer
                        r1.integers(3)
                        r2.integers(3)
                    assert spawn_behind(r1, sc, P, a[0], a[1], behind) == behind
                    assert spawn_behind_python(r2, sc, P, b[0], b[1], behind) == behind
                    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
                    assert r1.bit_generator.state == r2.bit_generator.state


@pytest.mark.parametrize(
    ("name", "behind", "env", "seed", "policy"),
    [
        ("fast", 5, {}, 0, "faster"),  # the ego crashes on the way: post-crash physics too
        ("fast", 20, {}, 3, "random"),
        ("fast", 20, {"lanes_count": 3, "vehicles_density": 1.5}, 2, "weave"),
        ("fast", 20, {"other_vehicles_type": LINEAR}, 4, "slower"),  # followers close in on a slow ego
        ("paper", 20, {}, 1, "cautious"),
    ],
)
def test_whole_episode_matches_highway_env(name: str, behind: int, env: dict, seed: int, policy: str) -> None:
    """40 decisions played on both (past the end of the episode): every vehicle, bit for bit."""
    cfg, env_id = _config(name, **env)
    r = compare_episode(
        cfg, env_id, seed, policy_actions(policy, seed), tol=TOL, stop_at_end=False, vehicles_behind=behind
    )
    assert r.matched, f"diverged after decision {r.divergent_step}: {r.cause}"
    assert r.steps == 40 and r.bitwise and r.max_abs_error == 0.0


def _same_snapshot(a: RoadSnapshot, b: RoadSnapshot) -> None:
    for field in dataclasses.fields(RoadSnapshot):
        x, y = getattr(a, field.name), getattr(b, field.name)
        if x is None or y is None:
            assert x is None and y is None, field.name
        elif isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            x, y = np.asarray(x), np.asarray(y)
            same = np.array_equal(x, y, equal_nan=x.dtype.kind == "f" and y.dtype.kind == "f")
            assert same and x.shape == y.shape, field.name
        else:
            assert x == y, field.name


@pytest.mark.parametrize(("behind", "density", "seed"), [(5, 1.0, 0), (20, 1.3, 5)])
def test_make_env_episode_equals_highway_envs(behind: int, density: float, seed: int) -> None:
    """make_env(simulator=fast) vs make_env(simulator=highway-env) with traffic.vehicles_behind: the same
    snapshots, observations, rewards, crashes and flags at every step of a fixed action sequence."""
    sets = {"traffic.vehicles_behind": behind, "env.vehicles_density": density}
    ref = make_env("fast", simulator="highway-env", **sets)
    fast = make_env("fast", simulator="fast", **sets)
    obs_r, info_r = ref.reset(seed=seed)
    obs_f, info_f = fast.reset(seed=seed)
    assert np.array_equal(obs_r, obs_f)
    _same_snapshot(info_r["snapshot"], info_f["snapshot"])
    snap = info_f["snapshot"]
    assert int(np.sum(snap.position[1:, 0] < snap.position[0, 0])) == behind
    for a in policy_actions("random", seed, 30):
        obs_r, rew_r, term_r, trunc_r, info_r = ref.step(a)
        obs_f, rew_f, term_f, trunc_f, info_f = fast.step(a)
        assert np.array_equal(obs_r, obs_f)
        assert rew_r == rew_f and (term_r, trunc_r) == (term_f, trunc_f)
        assert info_r["collision"] == info_f["collision"] and info_r["crashed"] == info_f["crashed"]
        _same_snapshot(info_r["snapshot"], info_f["snapshot"])
        if term_f or trunc_f:
            break
    ref.close()
    fast.close()


def _rollout(env: FastHighwayEnv, seed: int, actions: list[int]) -> list[np.ndarray]:
    env.reset(seed=seed)
    out = [env.F[:, : L.TIMER + 1].copy()]
    for a in actions:
        env.step(a)
        out.append(env.F[:, : L.TIMER + 1].copy())
    return out


def test_same_seed_same_numbers() -> None:
    """The same seed gives the same episode (another episode in between does not matter); another seed,
    another one; reset() without a seed continues the generator exactly as highway-env's does."""
    cfg, env_id = _preset("fast")
    actions = policy_actions("random", 7)
    a = _rollout(FastHighwayEnv(cfg, env_id, vehicles_behind=15), 7, actions)
    env = FastHighwayEnv(cfg, env_id, vehicles_behind=15)
    _rollout(env, 8, actions)
    b = _rollout(env, 7, actions)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    c = _rollout(env, 9, actions)
    assert not np.array_equal(a[0], c[0])
    oracle = make_oracle(cfg, env_id, vehicles_behind=15)
    env.reset(seed=5)
    oracle.reset(seed=5)
    for _ in range(2):
        for act in (3, 1, 0):
            env.step(act)
            oracle.step(act)
        env.reset()
        oracle.reset()
        cause, _, bitwise = compare_states(env.state(), oracle_state(oracle), TOL, full=True)
        assert cause is None and bitwise, cause


@pytest.mark.parametrize(("behind", "count"), [(5, 50), (20, 50), (10, 10), (30, 10)])
def test_the_count_behind_the_ego_at_reset_is_n(behind: int, count: int) -> None:
    """N vehicles start behind the ego (at most vehicles_count: all of them), the rest ahead; the
    vehicle count is unchanged; the followers are on lane centres, heading 0, 21–30 m/s, in order."""
    cfg, env_id = _config("fast", vehicles_count=count)
    env = FastHighwayEnv(cfg, env_id, vehicles_behind=behind)
    for seed in range(5):
        env.reset(seed=seed)
        x, y = env.F[:, L.X], env.F[:, L.Y]
        n = min(behind, count)
        assert x.size == 1 + count
        assert int(np.sum(x[1:] < x[0])) == n and int(np.sum(x[1:] > x[0])) == count - n
        followers = slice(1 + count - n, None)  # highway-env appends them: the last rows
        assert np.all(x[followers] < x[0]) and np.all(np.diff(x[followers]) < 0)
        assert set(y[followers] / 4.0) <= set(range(cfg["lanes_count"]))
        assert np.all(env.F[followers, L.H] == 0.0)
        assert np.all((env.F[followers, L.V] >= 21.0) & (env.F[followers, L.V] <= 30.0))


def test_batch_equals_the_single_environments() -> None:
    """FastBatch plays traffic.vehicles_behind: row i is make_env(simulator=fast, seed=S+i) driven by the
    same actions (observations, rewards, flags, masks), autoresets included."""
    sets = {"env.duration": 4, "shield.mode": "robust", "traffic.vehicles_behind": 20}
    assert supports(resolve_env_config("fast", simulator="fast", **sets)) is None
    n, seed = 3, 21
    vector = make_vector_env("fast", num_envs=n, **sets)
    assert isinstance(vector, FastVectorEnv)
    singles = [make_env("fast", simulator="fast", **sets) for _ in range(n)]
    obs, infos = vector.reset(seed=seed)
    for i, env in enumerate(singles):
        o, info = env.reset(seed=seed + i)
        assert np.array_equal(obs[i], o)
        assert np.array_equal(infos["action_mask"][i], info["action_mask"])
    rng = np.random.default_rng(2)
    finished = 0
    for _ in range(10):
        actions = rng.integers(5, size=n)
        obs, rewards, terminated, truncated, infos = vector.step(actions)
        for i, env in enumerate(singles):
            o, r, te, tr, info = env.step(int(actions[i]))
            assert rewards[i] == r and terminated[i] == te and truncated[i] == tr
            if te or tr:
                finished += 1
                assert np.array_equal(infos["final_obs"][i], o)
                o, info = env.reset()
            assert np.array_equal(obs[i], o)
            assert np.array_equal(vector.action_masks()[i], info["action_mask"])
    assert finished >= n
    vector.close()
    for env in singles:
        env.close()


def test_other_traffic_options_are_still_refused() -> None:
    """vehicles_behind builds; an adversary is still refused on the fast simulator, by make_env and by
    the batch (which sends it to the make_env loop); a negative count is a one-line ValueError."""
    env = make_env("fast", simulator="fast", **{"traffic.vehicles_behind": 5})
    env.close()
    with pytest.raises(NotSupported, match=r"traffic\.adversary"):
        make_env("fast", simulator="fast", **{"traffic.adversary": "brake"})
    assert "traffic.adversary" in (
        supports(resolve_env_config("fast", simulator="fast", **{"traffic.adversary": "brake"})) or ""
    )
    with pytest.raises(NotSupported, match=r"traffic\.adversary"):
        make_vector_env("fast", num_envs=2, **{"traffic.adversary": "brake"})
    cfg, env_id = _preset("fast")
    with pytest.raises(ValueError, match="vehicles_behind"):
        FastHighwayEnv(cfg, env_id, vehicles_behind=-1)
