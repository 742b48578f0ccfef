"""The fast simulator (safelane.sim.fast) against stock highway-env, vehicle by vehicle.

Fast suite: reset scenes for 10 seeds per preset, three whole episodes, determinism, config checks.
``-m slow``: 100 reset scenes per preset and 6 policies x several seeds of whole episodes per preset.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

import safelane
from safelane.core.snapshot import DRIVER_FIELDS, RoadSnapshot
from safelane.sim.fast import FastHighwayEnv
from safelane.sim.fast.check import (
    POLICIES,
    compare_episode,
    compare_states,
    make_oracle,
    oracle_state,
    policy_actions,
)

TOL = 1e-6
PRESETS = ("fast", "paper")


def _preset(name: str) -> tuple[dict, str]:
    data = yaml.safe_load((Path(safelane.__file__).parent / "presets" / f"{name}.yaml").read_text())
    return data["env"], data["env_id"]


_ORACLES: dict[str, object] = {}


def _oracle(name: str):
    if name not in _ORACLES:
        cfg, env_id = _preset(name)
        _ORACLES[name] = make_oracle(cfg, env_id)
    return _ORACLES[name]


def _check_resets(name: str, seeds) -> None:
    cfg, env_id = _preset(name)
    oracle = _oracle(name)
    fast = FastHighwayEnv(cfg, env_id)
    for seed in seeds:
        oracle.reset(seed=seed)
        fast.reset(seed=seed)
        cause, err, bitwise = compare_states(fast.state(), oracle_state(oracle), TOL, full=True)
        assert cause is None, f"{name} seed {seed}: {cause}"
        assert bitwise, f"{name} seed {seed}: reset scene not bit-identical (max error {err})"


@pytest.mark.parametrize("name", PRESETS)
def test_reset_scene_matches_highway_env(name: str) -> None:
    _check_resets(name, range(10))


@pytest.mark.slow
@pytest.mark.parametrize("name", PRESETS)
def test_reset_scene_matches_highway_env_100_seeds(name: str) -> None:
    _check_resets(name, range(100, 200))


def _check_episode(name: str, seed: int, policy: str, stop_at_end: bool = True) -> None:
    cfg, env_id = _preset(name)
    r = compare_episode(
        cfg, env_id, seed, policy_actions(policy, seed), tol=TOL, oracle=_oracle(name), stop_at_end=stop_at_end
    )
    assert r.matched, f"{name} seed {seed} {policy}: diverged after decision {r.divergent_step}: {r.cause}"
    assert r.max_abs_error <= TOL


@pytest.mark.parametrize(
    ("name", "seed", "policy", "stop_at_end"),
    [
        ("fast", 0, "faster", False),  # 40 decisions, the ego crashes on the way: post-crash physics too
        ("fast", 3, "random", False),
        ("paper", 1, "cautious", False),
    ],
)
def test_whole_episode_matches_highway_env(name: str, seed: int, policy: str, stop_at_end: bool) -> None:
    _check_episode(name, seed, policy, stop_at_end)


@pytest.mark.slow
@pytest.mark.parametrize("policy", POLICIES)
@pytest.mark.parametrize("name", PRESETS)
def test_episodes_match_highway_env_slow(name: str, policy: str) -> None:
    for seed in range(10, 14):
        _check_episode(name, seed, policy, stop_at_end=False)


def _rollout(env: FastHighwayEnv, seed: int, actions) -> list[np.ndarray]:
    env.reset(seed=seed)
    out = [np.stack([env.state()[k] for k in ("x", "y", "heading", "speed")])]
    for a in actions:
        env.step(a)
        out.append(np.stack([env.state()[k] for k in ("x", "y", "heading", "speed")]))
    return out


@pytest.mark.parametrize("name", PRESETS)
def test_determinism(name: str) -> None:
    cfg, env_id = _preset(name)
    actions = policy_actions("random", 7)
    a = _rollout(FastHighwayEnv(cfg, env_id), 7, actions)
    env = FastHighwayEnv(cfg, env_id)
    _rollout(env, 8, actions)  # another episode in between must not matter
    b = _rollout(env, 7, actions)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    c = _rollout(env, 9, actions)
    assert not np.array_equal(a[0], c[0])
    assert not all(np.array_equal(x, y) for x, y in zip(a, c, strict=True))


def test_reset_without_seed_continues_the_generator_as_highway_env() -> None:
    """reset(seed) then reset() twice (the generator carries on, with steps in between) == highway-env."""
    cfg, env_id = _preset("fast")
    env = FastHighwayEnv(cfg, env_id)
    oracle = _oracle("fast")
    env.reset(seed=5)
    oracle.reset(seed=5)
    first = env.state()["x"]
    for _ in range(2):
        for a in (3, 1, 0):
            env.step(a)
            oracle.step(a)
        env.reset()
        oracle.reset()
        cause, _, bitwise = compare_states(env.state(), oracle_state(oracle), TOL, full=True)
        assert cause is None and bitwise, cause
    assert not np.array_equal(first, env.state()["x"])


def test_snapshot_and_info() -> None:
    cfg, env_id = _preset("fast")
    env = FastHighwayEnv(cfg, env_id)
    obs, info = env.reset(seed=0)
    assert obs.shape == (2,) and obs.dtype == np.float32
    assert env.action_space.n == 5
    for _ in range(3):
        obs, reward, _, _, info = env.step(3)
    snap = info["snapshot"]
    assert isinstance(snap, RoadSnapshot)
    n = 1 + cfg["vehicles_count"]
    assert snap.n == n and snap.ego == 0
    assert snap.position.shape == (n, 2)
    assert info["speed"] == snap.ego_speed and info["crashed"] == snap.ego_crashed
    assert reward == 0.0
    assert snap.ego_target_speeds == tuple(float(s) for s in cfg["action"]["target_speeds"])
    assert snap.ego_target_speed == snap.ego_target_speeds[snap.ego_speed_index]
    assert snap.time == 3.0 and snap.simulation_frequency == 5.0 and snap.policy_frequency == 1.0
    for f in DRIVER_FIELDS:
        assert getattr(snap, f).shape == (n,)
    assert not snap.can_change_lane[0] and snap.can_change_lane[1:].all()
    assert np.isinf(snap.max_braking_imposed[0]) and (snap.max_braking_imposed[1:] == 2.0).all()
    assert (snap.brake_max == 6.0).all() and snap.accel_max[0] == 6.0 and (snap.accel_max[1:] == 3.0).all()
    assert ((snap.idm_delta[1:] >= 3.5) & (snap.idm_delta[1:] <= 4.5)).all()
    assert snap.ego_lane_offset == pytest.approx(snap.position[0, 1] - snap.lane[0] * snap.lane_width)


def test_snapshot_records_the_impact() -> None:
    cfg, env_id = _preset("fast")
    env = FastHighwayEnv(cfg, env_id)
    env.reset(seed=0)
    for _ in range(40):
        *_, terminated, truncated, info = env.step(3)
        if terminated or truncated:
            break
    snap = info["snapshot"]
    assert snap.ego_crashed
    assert snap.impact_before is not None and snap.impact_after is not None
    assert snap.impact_before.shape == snap.position.shape


@pytest.mark.parametrize(
    ("override", "word"),
    [
        ({"other_vehicles_type": "highway_env.vehicle.kinematics.Vehicle"}, "other_vehicles_type"),
        ({"controlled_vehicles": 2}, "controlled_vehicles"),
        ({"action": {"type": "DiscreteAction"}}, "action.type"),
        ({"some_unknown_key": 1}, "some_unknown_key"),
        ({"manual_control": True}, "manual_control"),
    ],
)
def test_unsupported_config_is_rejected(override: dict, word: str) -> None:
    cfg, env_id = _preset("fast")
    with pytest.raises(ValueError, match=word):
        FastHighwayEnv({**cfg, **override}, env_id)


def test_unknown_env_id_is_rejected() -> None:
    cfg, _ = _preset("fast")
    with pytest.raises(ValueError, match="env_id"):
        FastHighwayEnv(cfg, "merge-v0")


def test_other_settings_match_highway_env() -> None:
    """Other lane counts, densities, frequencies, the default target speeds and initial_lane_id."""
    cfg = {
        "lanes_count": 3,
        "vehicles_count": 15,
        "vehicles_density": 1.5,
        "ego_spacing": 1.5,
        "simulation_frequency": 10,
        "policy_frequency": 2,
        "duration": 6,
        "initial_lane_id": 1,
    }
    for env_id in ("highway-fast-v0", "highway-v0"):
        r = compare_episode(cfg, env_id, 4, policy_actions("random", 4, 12), tol=TOL, stop_at_end=False)
        assert r.matched, f"{env_id}: {r.divergent_step}: {r.cause}"


def test_lane_index_neighbours_equal_the_scan_with_ties() -> None:
    """The binary-searched neighbour query equals highway-env's linear scan, ties and lane edges included."""
    from safelane.sim.fast import lanes
    from safelane.sim.fast import layout as L
    from safelane.sim.fast.scene import params

    P = params()
    rng = np.random.default_rng(0)
    n_lanes = 4
    members = np.empty((n_lanes, 40), dtype=np.int64)
    mx = np.empty((n_lanes, 40))
    cnt = np.zeros(n_lanes, dtype=np.int64)
    for _ in range(300):
        n = int(rng.integers(1, 40))
        F = np.zeros((n, L.NF))
        F[:, L.X] = rng.choice([-6.0, -5.0, 0.0, 10.0, 10.0, 12.5, 30.0, 10004.0, 10005.0], size=n)
        F[:, L.X] += rng.choice([0.0, 0.0, 1e-9], size=n)
        F[:, L.Y] = rng.choice([-3.0, -3.5, 0.0, 1.0, 3.0, 4.0, 7.0, 9.0, 12.0, 15.0, 15.5], size=n)
        lanes.build_lane_index(F, n_lanes, P, members, mx, cnt)
        for j in range(n):
            for lane in range(n_lanes):
                assert lanes.neighbours(F, j, lane, members, mx, cnt) == lanes.neighbours_scan(F, n, j, lane, P)


LINEAR_TYPES = ("LinearVehicle", "AggressiveVehicle", "DefensiveVehicle")


@pytest.mark.parametrize("typ", LINEAR_TYPES)
def test_linear_vehicle_scenes_match_highway_env(typ: str) -> None:
    """LinearVehicle & subclasses: their randomize_behavior draws; the replay equals the Python twin."""
    from safelane.sim.fast.scene import build_scene, build_scene_python, make_rng, params, resolve_config

    cfg, env_id = _preset("fast")
    cfg = {**cfg, "other_vehicles_type": f"highway_env.vehicle.behavior.{typ}"}
    sc, P = resolve_config(cfg, env_id), params()
    for seed in range(5):
        r1, r2 = make_rng(seed), make_rng(seed)
        a, b = build_scene(r1, sc, P), build_scene_python(r2, sc, P)
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
        assert r1.bit_generator.state == r2.bit_generator.state
    oracle, fast = make_oracle(cfg, env_id), FastHighwayEnv(cfg, env_id)
    for seed in range(3):
        oracle.reset(seed=seed)
        fast.reset(seed=seed)
        cause, _, bitwise = compare_states(fast.state(), oracle_state(oracle), TOL, full=True)
        assert cause is None and bitwise, cause
        ref = oracle.unwrapped.road.vehicles[1]
        assert np.array_equal(fast.F[1, 15:18], ref.ACCELERATION_PARAMETERS)
        assert np.array_equal(fast.F[1, 18:20], ref.STEERING_PARAMETERS)


def test_linear_vehicle_episode_matches_highway_env() -> None:
    cfg, env_id = _preset("fast")
    cfg = {**cfg, "other_vehicles_type": "highway_env.vehicle.behavior.AggressiveVehicle"}
    r = compare_episode(cfg, env_id, 1, policy_actions("random", 1), tol=TOL, stop_at_end=False)
    assert r.matched, f"{r.divergent_step}: {r.cause}"


@pytest.mark.slow
@pytest.mark.parametrize("typ", LINEAR_TYPES)
@pytest.mark.parametrize("name", PRESETS)
def test_linear_vehicle_episodes_match_highway_env_slow(name: str, typ: str) -> None:
    cfg, env_id = _preset(name)
    cfg = {**cfg, "other_vehicles_type": f"highway_env.vehicle.behavior.{typ}"}
    oracle = make_oracle(cfg, env_id)
    for seed, policy in ((20, "random"), (21, "faster"), (22, "weave")):
        r = compare_episode(cfg, env_id, seed, policy_actions(policy, seed), tol=TOL, oracle=oracle, stop_at_end=False)
        assert r.matched, f"{name} {typ} seed {seed} {policy}: {r.divergent_step}: {r.cause}"


def test_numpy_computes_libm_bits_here() -> None:
    """The bit-for-bit comparisons with highway-env need numpy's tan/arctan to be libm's (they are not
    with its AVX-512 kernels): a failure here says why those comparisons would diverge."""
    from safelane.sim.fast.libm import LIBM_NUMPY_ENV, numpy_matches_libm

    assert numpy_matches_libm(), f"numpy's transcendental functions are not libm's here; set {LIBM_NUMPY_ENV}"


def test_linear_steering_squares_the_speed_with_pow_as_highway_env() -> None:
    """LinearVehicle.steering_features divides by ``not_zero(speed) ** 2``: libm's pow on a float, which is
    an ulp away from speed·speed for about 1 speed in 1 200; the kernel calls pow too (a product would
    differ from highway-env's steering for some of these speeds: checked below)."""
    from highway_env.vehicle.behavior import LinearVehicle

    from safelane.sim.fast import kernels as K
    from safelane.sim.fast import layout as L
    from safelane.sim.fast.scene import params

    oracle = _oracle("fast")
    oracle.reset(seed=0)
    road = oracle.unwrapped.road
    P = params()
    rng = np.random.default_rng(0)
    speeds = [s for s in rng.uniform(5.0, 30.0, 40_000).tolist() if s**2 != s * s][:25]
    assert len(speeds) == 25
    F = np.zeros((1, L.NF))
    product_differs = 0
    for k, s in enumerate(speeds):
        v = LinearVehicle(road, [100.0, 4.0 + 0.05 * (k + 1)], heading=0.002 * k, speed=s)
        v.randomize_behavior()
        lane = v.target_lane_index
        ref = v.steering_control(lane)
        F[0, L.X], F[0, L.Y], F[0, L.H], F[0, L.V] = v.position[0], v.position[1], v.heading, v.speed
        F[0, L.SP0 : L.SP1 + 1] = v.STEERING_PARAMETERS
        assert K._linear_steering(F, 0, lane[2], P) == ref, f"speed {s!r}"
        f0 = v.steering_features(lane)[0]
        f1_product = -v.lane.local_coordinates(v.position)[1] * v.LENGTH / (s * s)
        product_differs += float(np.dot(v.STEERING_PARAMETERS, [f0, f1_product])) != ref
    assert product_differs > 0


@pytest.mark.parametrize("preset", ["fast", "hidden-types"])
def test_snapshot_arrays_are_typed_alike_on_both_simulators(preset: str) -> None:
    """Every array of a snapshot has the same layout and the same read-only flag on both simulators (and in the
    robust shield's readings of the types), so each compiled kernel of the shield compiles once, not once per
    simulator: numba types an argument by its dtype, layout and writeability."""
    from dataclasses import fields as dataclass_fields

    from safelane.core.snapshot import READ_ONLY_FIELDS

    def typing(snap: RoadSnapshot) -> dict[str, tuple[str, bool, bool]]:
        return {f.name: (str(a.dtype), a.flags.c_contiguous, a.flags.writeable) for f in dataclass_fields(snap)
                if isinstance(a := getattr(snap, f.name), np.ndarray)}  # fmt: skip

    seen = {}
    for simulator in ("fast", "highway-env"):
        env = safelane.make_env(preset, simulator=simulator, **{"shield.mode": "robust"})
        _, info = env.reset(seed=3)
        _, _, _, _, info = env.step(1)
        snap = info["snapshot"]
        seen[simulator] = typing(snap)
        assert all(not seen[simulator][n][2] for n in READ_ONLY_FIELDS if n in seen[simulator])
        assert all(c for _, c, _ in seen[simulator].values())  # C-ordered, positions included
        shield = env.get_wrapper_attr("driver_readings")
        for reading in shield(snap)[0]:
            assert typing(reading) == seen[simulator]
        env.close()
    assert seen["fast"] == seen["highway-env"]
