"""The fast simulator's ``ContinuousAction`` ego against stock highway-env, to the bit.

Whole episodes: every vehicle's position, heading, speed, lane, target lane and crash flag, the flags, and the
two simulators' snapshots (``RoadSnapshot.__eq__``) after the reset and every decision; random float32 actions
(gymnasium's), float64 and lists, steering off the road, crashes and what follows them, 2 to 5 lanes, 1 and 5
decisions a second, vehicles spawned behind the ego (which MOBIL then sees as a follower), linear-model
drivers, one-axis actions, unclipped actions and a speed range. Plus highway-env's own action mapping (float32
arithmetic included) and the one-line refusals.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safelane.core.snapshot import RoadSnapshot
from safelane.running.simcheck import lane_keeping_action
from safelane.sim.fast import FastHighwayEnv
from safelane.sim.fast.check import compare_episode
from safelane.sim.fast.continuous import controls, resolve_continuous

CONTINUOUS = {"type": "ContinuousAction"}
FAST, FULL = "highway-fast-v0", "highway-v0"


def _uniform(seed: int, n: int, size: int = 2, low: float = -1.0, high: float = 1.0, dtype: Any = np.float32):
    """``n`` actions drawn uniformly in [low, high]^size from a seeded generator, as ``dtype`` arrays."""
    rng = np.random.default_rng(seed)
    return [rng.uniform(low, high, size).astype(dtype) for _ in range(n)]


def _hold(action: list[float], n: int) -> list[np.ndarray]:
    return [np.array(action, dtype=np.float32) for _ in range(n)]


Driver = Callable[[int, RoadSnapshot, np.random.Generator], Any]
"""``driver(decision, snapshot, rng) -> action``: a feedback policy, played on the fast simulator first; its
actions are then replayed on both (the same states give the same actions)."""


def _keep(acceleration: float, lanes: Callable[[int], int | None] = lambda k: None, scale: float = 1.0) -> Driver:
    """Lane keeping (``lane_keeping_action``) at ``acceleration``, towards lane ``lanes(decision)``, × ``scale``."""
    return lambda k, snap, rng: lane_keeping_action(snap, acceleration, lanes(k)) * np.float32(scale)


def _weave(k: int) -> int:
    return (1, 2, 1, 0)[(k // 3) % 4]


def _driven(config: dict[str, Any], env_id: str, seed: int, driver: Driver, n: int, behind: int = 0) -> list[Any]:
    """The actions ``driver`` takes over ``n`` decisions from ``reset(seed)`` on the fast simulator."""
    env = FastHighwayEnv(config, env_id, vehicles_behind=behind)
    _, info = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    actions = []
    for k in range(n):
        actions.append(driver(k, info["snapshot"], rng))
        *_, info = env.step(actions[-1])
    return actions


def _mixed(k: int, snap: RoadSnapshot, rng: np.random.Generator) -> Any:
    """Lane keeping at a random throttle, as float32, float64 and a list of Python floats in turn (each maps in
    its own arithmetic)."""
    a = lane_keeping_action(snap, float(rng.uniform(-0.3, 0.3))).astype(np.float64)
    a[0] = rng.uniform(-0.3, 0.3)
    return (a.astype(np.float32), a, a.tolist())[k % 3]


def _random_throttle(low: float, high: float, lanes: Callable[[int], int | None] = lambda k: None) -> Driver:
    return lambda k, snap, rng: lane_keeping_action(snap, float(rng.uniform(low, high)), lanes(k))


LINEAR = "highway_env.vehicle.behavior.AggressiveVehicle"
# (id, env_id, highway-env settings, vehicles_behind, seed, decisions, driver or None (uniform random), play on)
CASES: list[tuple[str, str, dict[str, Any], int, int, int, Driver | None, bool]] = [
    ("uniform-random", FAST, {}, 0, 0, 10, None, False),
    ("uniform-random-highway-v0", FULL, {"vehicles_count": 15}, 0, 1, 6, None, False),
    ("weaving-highway-v0", FULL, {"vehicles_count": 15}, 0, 1, 8, _random_throttle(-0.2, 0.2, _weave), False),
    ("weaving-two-lanes-5hz", FAST, {"lanes_count": 2, "vehicles_count": 15, "policy_frequency": 5}, 0, 2, 30,
     _random_throttle(-0.3, 0.3, lambda k: (k // 10) % 2), False),
    ("three-lanes-mixed-dtypes", FAST, {"lanes_count": 3, "vehicles_count": 20}, 0, 3, 15, _mixed, False),
    ("weaving-five-lanes", FAST, {"lanes_count": 5, "vehicles_count": 25, "vehicles_density": 1.5}, 0, 4, 15,
     _random_throttle(-0.2, 0.2, lambda k: (k // 4) % 5), False),
    ("full-throttle-crash", FAST, {"vehicles_count": 30}, 0, 0, 20, _keep(1.0), True),
    ("braking-before-followers", FAST, {"vehicles_count": 20, "lanes_count": 3}, 12, 5, 15,
     _random_throttle(-0.4, 0.1), False),
    # MOBIL's linear drivers see the ego (their new follower) without a speed-tracking term: not ego.speed - 0
    ("linear-drivers-behind", FAST, {"vehicles_count": 20, "lanes_count": 2, "other_vehicles_type": LINEAR}, 12, 1,
     15, _random_throttle(-0.4, 0.1), False),
    ("longitudinal-only", FAST, {"vehicles_count": 20, "action": {**CONTINUOUS, "lateral": False}}, 5, 7, 15,
     lambda k, snap, rng: rng.uniform(-0.5, 0.5, 1).astype(np.float32), False),
    ("lateral-only", FAST, {"vehicles_count": 20, "action": {**CONTINUOUS, "longitudinal": False}}, 0, 8, 12,
     lambda k, snap, rng: lane_keeping_action(snap, 0.0, _weave(k))[1:], False),
    ("unclipped", FAST, {"vehicles_count": 20, "action": {**CONTINUOUS, "clip": False}}, 0, 9, 12,
     _keep(2.5, scale=1.6), False),
]  # fmt: skip


@pytest.mark.parametrize(
    ("env_id", "env", "behind", "seed", "n", "driver", "play_on"), [c[1:] for c in CASES], ids=[c[0] for c in CASES]
)
def test_continuous_episode_matches_highway_env_to_the_bit(
    env_id: str, env: dict[str, Any], behind: int, seed: int, n: int, driver: Driver | None, play_on: bool
) -> None:
    config = {"action": CONTINUOUS, **env}
    actions = _uniform(seed, n) if driver is None else _driven(config, env_id, seed, driver, n, behind)
    r = compare_episode(
        config, env_id, seed, actions, tol=0.0, stop_at_end=not play_on, vehicles_behind=behind, snapshots=True
    )
    assert r.matched, f"diverged after decision {r.divergent_step}: {r.cause}"
    assert r.bitwise and r.max_abs_error == 0.0


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_whole_episodes_match_highway_env(seed: int) -> None:
    """highway-fast-v0's own settings (50 vehicles, 30 decisions): whole episodes, to the episode's end
    (a crash or the time limit), under uniform random float32 actions (even seeds) or lane keeping at a
    random throttle (odd)."""
    config = {"action": CONTINUOUS}
    n = 30
    driver = _random_throttle(-0.5, 0.5)
    actions = _uniform(seed, n) if seed % 2 == 0 else _driven(config, FAST, seed, driver, n)
    r = compare_episode(config, FAST, seed, actions, tol=0.0, snapshots=True)
    assert r.matched and r.bitwise, f"diverged after decision {r.divergent_step}: {r.cause}"


@settings(max_examples=8, deadline=None)
@given(
    env_id=st.sampled_from([FAST, FULL]),
    lanes=st.integers(2, 5),
    policy_frequency=st.sampled_from([1, 2, 5]),
    vehicles=st.integers(3, 20),
    behind=st.integers(0, 3),
    seed=st.integers(0, 2**16),
)
def test_random_settings_match_highway_env(
    env_id: str, lanes: int, policy_frequency: int, vehicles: int, behind: int, seed: int
) -> None:
    """Any lane count, decision rate, traffic and vehicles behind: 6 decisions of lane keeping at a random
    throttle towards random lanes, bit for bit."""
    config = {"action": CONTINUOUS, "lanes_count": lanes, "policy_frequency": policy_frequency}
    config["vehicles_count"] = vehicles
    rng = np.random.default_rng(seed)
    lanes_wanted = rng.integers(0, lanes, 6)
    driver = _random_throttle(-0.5, 0.5, lambda k: int(lanes_wanted[k]))
    actions = _driven(config, env_id, seed, driver, 6, behind)
    r = compare_episode(config, env_id, seed, actions, tol=0.0, vehicles_behind=behind, snapshots=True)
    assert r.matched and r.bitwise, f"diverged after decision {r.divergent_step}: {r.cause}"


def _play(config: dict[str, Any], seed: int, actions: list[Any], env_id: str = FAST) -> tuple[FastHighwayEnv, list]:
    """The fast env after ``actions`` from ``reset(seed)`` (stopping at the episode's end) and its infos."""
    env = FastHighwayEnv(config, env_id)
    _, info = env.reset(seed=seed)
    infos = [info]
    for a in actions:
        *_, terminated, truncated, info = env.step(a)
        infos.append(info)
        if terminated or truncated:
            break
    return env, infos


def test_steering_off_the_road_ends_the_episode_as_on_highway_env() -> None:
    """Hard steering leaves the road: with ``offroad_terminal`` both simulators end the episode at the same
    decision, the ego off its (closest) lane, not crashed."""
    config = {"action": CONTINUOUS, "vehicles_count": 10, "offroad_terminal": True, "initial_lane_id": 0}
    actions = _hold([0.0, -1.0], 4)
    r = compare_episode(config, FAST, 11, actions, tol=0.0, snapshots=True)
    assert r.matched and r.bitwise, r.cause
    env, infos = _play(config, 11, actions)
    assert len(infos) - 1 == r.steps < len(actions) and not env.on_road
    assert not infos[-1]["crashed"] and infos[-1]["snapshot"].ego_lane_offset < -2.0


def test_crash_is_reproduced_and_the_crashed_ego_brakes_to_a_stop() -> None:
    """Full throttle into traffic, then random actions: the ego crashes at the same decision on both simulators,
    and from then on ``clip_actions`` overrides every action (steering 0: the heading stays; acceleration
    −speed: the speed decays to nothing), on both, bit for bit."""
    config = {"action": CONTINUOUS, "vehicles_count": 30}
    actions = _hold([1.0, 0.0], 6) + _uniform(0, 8)
    r = compare_episode(config, FAST, 0, actions, tol=0.0, stop_at_end=False, snapshots=True)
    assert r.matched and r.bitwise and r.steps == len(actions), r.cause
    env = FastHighwayEnv(config, FAST)
    env.reset(seed=0)
    infos = [env.step(a)[-1] for a in actions]
    crash = next(k for k, info in enumerate(infos) if info["crashed"])
    assert crash < 6 and infos[crash]["speed"] > 30.0 and infos[crash]["snapshot"].impact_before is not None
    headings = [info["snapshot"].ego_heading for info in infos[crash + 1 :]]
    assert len(set(headings)) == 1 and infos[-1]["speed"] < 1e-2 * infos[crash]["speed"]


def test_speed_range_bounds_the_ego_speed_as_on_highway_env() -> None:
    """``speed_range`` sets the ego's MIN_SPEED / MAX_SPEED: ``clip_actions`` pulls it back to [5, 28] m/s under
    full throttle and full braking (8 m/s²), on both simulators."""
    action = {**CONTINUOUS, "speed_range": [5, 28], "acceleration_range": [-8, 8.0]}
    config = {"action": action, "vehicles_count": 5, "vehicles_density": 0.5}
    actions = _driven(config, FAST, 0, lambda k, snap, rng: lane_keeping_action(snap, 1.0 if k < 4 else -1.0), 10)
    r = compare_episode(config, FAST, 0, actions, tol=0.0, snapshots=True)
    assert r.matched and r.bitwise and r.steps == 10, r.cause
    speeds = [info["speed"] for info in _play(config, 0, actions)[1]]
    # a frame (0.2 s × 8 m/s²) may overshoot a bound by 1.6 m/s, the next pulls the speed back
    assert 28.0 < max(speeds) < 29.6 and 3.4 < min(speeds) < 5.0
    assert speeds[4] == pytest.approx(28.0, abs=1e-2) and speeds[-1] == pytest.approx(5.0, abs=1e-2)


def test_continuous_snapshot_has_no_set_points_on_both_simulators() -> None:
    from safelane.sim.fast.check import make_oracle

    config = {"action": CONTINUOUS, "vehicles_count": 10}
    oracle = make_oracle(config, FAST, snapshots=True)
    fast = FastHighwayEnv(config, FAST)
    assert fast.action_space == oracle.action_space == gym.spaces.Box(-1, 1, (2,), np.float32)
    for (_, info), env in ((oracle.reset(seed=3), oracle), (fast.reset(seed=3), fast)):
        _, _, _, _, info = env.step(np.array([0.5, 0.05], dtype=np.float32))
        snap = info["snapshot"]
        assert math.isnan(snap.ego_target_speed) and math.isnan(snap.ego_kp) and math.isnan(snap.target_speed[0])
        assert snap.ego_speed_index == -1 and snap.ego_target_speeds == ()
        assert snap.target_lane[0] == snap.lane[0] and not np.isnan(snap.target_speed[1:]).any()
        assert snap.ego_lane_offset == snap.position[0, 1] - snap.lane[0] * snap.lane_width != 0.0


# --- highway-env's action mapping, float32 included ------------------------------------------------------------

_ORACLE: dict[str, Any] = {}


def _highway_env_controls(action: Any, config: dict[str, Any]) -> tuple[float, float]:
    """highway-env's own ``ContinuousAction(env, **config).get_action(action)``, then clip_actions' float()."""
    from highway_env.envs.common.action import ContinuousAction

    if "env" not in _ORACLE:
        env = gym.make(FAST, config={"action": CONTINUOUS, "vehicles_count": 1})
        env.reset(seed=0)
        _ORACLE["env"] = env.unwrapped
    mapped = ContinuousAction(_ORACLE["env"], **config).get_action(action)
    return float(mapped["acceleration"]), float(mapped["steering"])


_numbers = st.floats(-3.0, 3.0, allow_nan=False, width=32)


@settings(max_examples=150, deadline=None)
@given(
    values=st.lists(_numbers, min_size=2, max_size=2),
    kind=st.sampled_from(["float32", "float64", "list"]),
    clip=st.booleans(),
    acceleration_range=st.sampled_from([None, [-3, 3], [-2.5, 4.0]]),
)
def test_controls_are_highway_env_s_mapping(
    values: list[float], kind: str, clip: bool, acceleration_range: list[float] | None
) -> None:
    action: Any = values if kind == "list" else np.array(values, dtype=kind)
    config = {"type": "ContinuousAction", "clip": clip, "acceleration_range": acceleration_range}
    ours = controls(action, resolve_continuous(config))
    assert ours == _highway_env_controls(action, config)


def test_a_float32_action_maps_in_float32_as_on_highway_env() -> None:
    """NEP 50: ``lmap`` keeps a float32 scalar float32, so 0.3 maps to exactly 1.5 m/s² (float64: 1.5000000596…)."""
    spec = resolve_continuous(CONTINUOUS)
    single = controls(np.array([0.3, 0.1], dtype=np.float32), spec)
    double = controls(np.array([0.3, 0.1], dtype=np.float32).astype(np.float64), spec)
    assert single[0] == 1.5 and double[0] == 1.5000000596046448
    assert single[1] != double[1]
    assert single == _highway_env_controls(np.array([0.3, 0.1], dtype=np.float32), CONTINUOUS)


def test_highway_env_s_ego_state_stays_float64_under_float32_actions() -> None:
    """The experiment behind the kernels' float64 state: ``lmap`` gives float32 controls, but ``clip_actions``
    stores ``float()`` of them, so highway-env's ego keeps a Python-float speed and float64 heading and position."""
    env = gym.make(FAST, config={"action": CONTINUOUS, "vehicles_count": 3}).unwrapped
    env.reset(seed=0)
    ego = env.vehicle
    action = np.array([0.3, 0.1], dtype=np.float32)
    assert type(env.action_type.get_action(action)["acceleration"]) is np.float32
    for _ in range(2):
        env.step(action)
        assert type(ego.action["acceleration"]) is float and type(ego.action["steering"]) is float
        assert type(ego.speed) is float and type(ego.heading) is np.float64 and ego.position.dtype == np.float64


def test_get_state_and_set_state_replay_a_continuous_decision() -> None:
    """A planner's try-and-restore: the held action (with clip_actions' changes) is part of the state."""
    env = FastHighwayEnv({"action": CONTINUOUS, "vehicles_count": 10})
    env.reset(seed=2)
    for a in _uniform(2, 2):
        env.step(a)
    saved = env.get_state()
    tries = [[env.step(a)[-1]["snapshot"] for a in _uniform(7, 3)]]
    env.set_state(saved)
    tries.append([env.step(a)[-1]["snapshot"] for a in _uniform(7, 3)])
    assert all(a == b for a, b in zip(*tries, strict=True))


# --- refusals, in one line ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("action", "words"),
    [
        ({"dynamical": True}, "action.dynamical: True is not supported; allowed: False"),
        ({"target_speeds": [20, 30]}, "action keys not supported by the fast simulator: ['target_speeds']"),
        ({"longitudinal": False, "lateral": False}, "action.longitudinal, action.lateral: both False"),
        ({"steering_range": [0.1]}, "action.steering_range: [0.1] is not supported"),
        ({"speed_range": [0, float("inf")]}, "action.speed_range"),
        ({"acceleration_range": [np.float32(-1), np.float32(1)]}, "action.acceleration_range"),
    ],
)
def test_unsupported_continuous_settings_are_refused_in_one_line(action: dict[str, Any], words: str) -> None:
    with pytest.raises(ValueError, match=r"^[^\n]*$") as err:
        FastHighwayEnv({"action": {**CONTINUOUS, **action}})
    assert words in str(err.value)


@pytest.mark.parametrize("action", [[0.1], np.zeros(3, np.float32), 0.5, [float("nan"), 0.0]])
def test_bad_actions_are_refused_in_one_line(action: Any) -> None:
    env = FastHighwayEnv({"action": CONTINUOUS, "vehicles_count": 3})
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"^action [^\n]*$"):
        env.step(action)


def test_the_fast_batch_refuses_continuous_actions() -> None:
    from safelane.config import load_config
    from safelane.env.fast_batch import supports

    cfg = load_config("fast", sets=["simulator=fast"])
    continuous = cfg.model_copy(update={"env": {**cfg.env, "action": CONTINUOUS}})
    assert supports(cfg) is None
    assert supports(continuous) == "action.type: ContinuousAction (the batch runs meta-actions)"


# --- safelane sim check's continuous section ----------------------------------------------------------------


def test_sim_check_names_a_continuous_divergence(monkeypatch: pytest.MonkeyPatch) -> None:
    """The continuous check catches a fast side a hair off (an acceleration range 0.02 % wider: the ego a few
    µm ahead after one decision) and names it; with the same settings both agree to the bit."""
    from safelane.config import load_config
    from safelane.running import simcheck

    cfg = load_config("fast", sets=["env.duration=3", "env.vehicles_count=10"])
    found, worst, equal = simcheck.compare_continuous_episode(cfg, 0, "full_throttle")
    assert found is None and worst == 0.0 and equal
    original = simcheck._continuous_simulator

    def skewed(c: Any, simulator: str) -> Any:
        if simulator == "highway-env":
            return original(c, simulator)
        wider = c.model_copy(update={"env": {**c.env, "action": {**CONTINUOUS, "acceleration_range": [-5, 5.001]}}})
        return original(wider, "fast")

    monkeypatch.setattr(simcheck, "_continuous_simulator", skewed)
    found, worst, equal = simcheck.compare_continuous_episode(cfg, 0, "full_throttle", tol=1e-9)
    assert found is not None and found.first_step == 1 and found.cause.startswith("vehicle 0 position differs")
    assert 0.0 < worst < 1e-2 and not equal


def test_sim_check_prints_the_continuous_section() -> None:
    from typer.testing import CliRunner

    from safelane.cli import app

    args = ["sim", "check", "--episodes", "1", "--workers", "1", "--set", "env.duration=2"]
    args += ["--set", "env.vehicles_count=8"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())  # rich wraps long lines
    policies = "uniform, random_throttle, full_throttle"
    assert f"continuous actions (ContinuousAction ego, the simulators alone; {policies}):" in text
    assert "snapshots: 1.000 of 1 episodes equal at every step" in text
    plain = CliRunner().invoke(app, [*args, "--no-continuous", "--json"])
    assert plain.exit_code == 0 and '"continuous": null' in plain.stdout
