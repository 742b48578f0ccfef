"""Evaluation: fixed policies, collision classification, episode records and their summary."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from safelane.config import ConfigError, load_config
from safelane.core.spaces import FASTER, IDLE, LANE_LEFT, LANE_RIGHT, SLOWER
from safelane.running.collisions import COLLISION_KINDS, classify_collision, collision_kind
from safelane.running.evaluation import EpisodeRecord, evaluate_fixed, run_episodes, summarize
from safelane.running.policies import FIXED_POLICIES, fixed_policy

MakeEnv = Callable[..., gym.Env]
Scene = Callable[..., list[Any]]
OBS = np.zeros(26, dtype=np.float32)

# --- fixed policies ----------------------------------------------------------------------------------


@pytest.mark.parametrize(("name", "action"), [("idle", IDLE), ("faster", FASTER), ("slower", SLOWER)])
def test_constant_policies(name: str, action: int) -> None:
    policy = fixed_policy(name, seed=3)
    assert {policy(OBS, {}) for _ in range(10)} == {action}


def test_random_policy_is_seeded_and_uses_every_action() -> None:
    first, second, other = fixed_policy("random", 1), fixed_policy("random", 1), fixed_policy("random", 2)
    a = [first(OBS, {}) for _ in range(200)]
    assert a == [second(OBS, {}) for _ in range(200)]
    assert a != [other(OBS, {}) for _ in range(200)]
    assert set(a) == {LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER}


def test_unknown_policy_lists_the_policies() -> None:
    assert FIXED_POLICIES == ("random", "idle", "faster", "slower", "probe")
    allowed = "random, idle, faster, slower, probe"
    with pytest.raises(ConfigError, match=rf"^policy: unknown policy 'fastest'; allowed: {allowed}$"):
        fixed_policy("fastest")


# --- collision geometry (hand-worked offsets, other − ego, lane coordinates) -------------------------------

HALF_LENGTH, HALF_WIDTH = 5.0, 2.0  # two 5 m × 2 m bodies, heading 0


@pytest.mark.parametrize(
    ("before", "after", "kind"),
    [
        ((6.0, 0.0), (4.9, 0.0), "ego_hit_front"),  # closing on the car ahead in the lane
        ((5.8, -1.2), (4.7, -1.0), "ego_hit_front"),  # ahead, half a car off-centre: still its rear face
        ((-6.0, 0.3), (-4.8, 0.3), "rear_ended"),  # a follower closing from behind
        ((1.0, 3.0), (1.0, 1.9), "side"),  # alongside, lateral closing (a lane change)
        ((-2.0, -2.6), (-2.1, -1.8), "side"),
        ((5.5, 2.5), (4.8, 2.2), "side"),  # corner: longitudinal overlap first (t = 0.71), lateral last
        ((5.6, 2.1), (4.6, 1.9), "ego_hit_front"),  # corner: lateral overlap at t = 0.5, longitudinal at 0.6
        ((5.6, 2.1), (4.6, 2.0), "side"),  # corner: longitudinal at t = 0.6, lateral last at t = 1
        ((4.0, -3.0), (4.2, -1.9), "side"),  # already overlapping along the lane
    ],
)
def test_collision_kind_from_geometry(before: tuple[float, float], after: tuple[float, float], kind: str) -> None:
    assert collision_kind(before, after, HALF_LENGTH, HALF_WIDTH) == kind


def _crash(env: gym.Env, actions: list[int]) -> dict[str, Any]:
    info: dict[str, Any] = {}
    for action in actions:
        _, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    return info


@pytest.mark.parametrize(
    ("ego", "other", "actions", "kind"),
    [
        ((100.0, 1, 25.0), (112.0, 4.0, 0.0, 0.0), [IDLE], "ego_hit_front"),  # into a stopped car
        ((100.0, 1, 0.0), (80.0, 4.0, 30.0, 0.0), [IDLE, IDLE], "rear_ended"),  # stopped ego, fast follower
        ((100.0, 1, 25.0), (100.0, 8.0, 25.0, 0.0), [LANE_RIGHT, IDLE], "side"),  # change into a neighbour
        ((100.0, 1, 25.0), (100.0, 0.0, 25.0, 0.0), [LANE_LEFT, IDLE], "side"),
    ],
)
def test_classify_collision_on_hand_built_crashes(
    make_fast_env: MakeEnv,
    scene: Scene,
    ego: tuple[float, int, float],
    other: tuple[float, float, float, float],
    actions: list[int],
    kind: str,
) -> None:
    env = make_fast_env()
    scene(env, ego=ego, others=[other])
    info = _crash(env, actions)
    assert info["collision"]
    assert info["snapshot"].impact_before is not None
    assert classify_collision(info["snapshot"]) == kind


def test_no_collision_no_kind(make_fast_env: MakeEnv, scene: Scene) -> None:
    env = make_fast_env()
    scene(env, ego=(100.0, 1, 25.0), others=[(140.0, 4.0, 25.0, 0.0)])
    info = _crash(env, [IDLE, IDLE])
    assert not info["collision"]
    assert classify_collision(info["snapshot"]) is None


def test_classification_without_an_impact_frame_uses_current_geometry(make_fast_env: MakeEnv, scene: Scene) -> None:
    env = make_fast_env()
    scene(env, ego=(100.0, 1, 25.0), others=[(112.0, 4.0, 0.0, 0.0)])
    _, _, _, _, info = env.step(IDLE)
    snap = dataclasses.replace(info["snapshot"], impact_before=None, impact_after=None)
    assert classify_collision(snap) in COLLISION_KINDS


# --- episodes -----------------------------------------------------------------------------------------------


def test_same_seed_gives_identical_records(make_fast_env: MakeEnv) -> None:
    env = make_fast_env(env={"duration": 12})
    first = run_episodes(env, fixed_policy("random", 5), episodes=3, seed=5)
    second = run_episodes(make_fast_env(env={"duration": 12}), fixed_policy("random", 5), episodes=3, seed=5)
    assert first == second
    assert [r.seed for r in first] == [5, 6, 7]
    for r in first:
        assert 1 <= r.length <= 12
        assert sum(r.actions) == r.length
        assert r.interventions == r.fallbacks == 0  # no shield


def test_always_faster_unshielded_mostly_crashes(make_fast_env: MakeEnv) -> None:
    records = run_episodes(make_fast_env(), fixed_policy("faster"), episodes=4, seed=0)
    crashed = [r for r in records if r.collision]
    assert len(crashed) >= 3
    for r in crashed:
        assert r.collision_kind in COLLISION_KINDS
        assert r.time_to_collision is not None and 0 < r.time_to_collision <= 40
        assert r.time_to_collision == pytest.approx(r.length)  # one decision per second
        assert r.return_ <= r.length * 1.0 - 10.0 + 1e-9  # at most b = 1 per decision, minus c = 10
    for r in records:
        assert r.actions[FASTER] == r.length


def test_progress_callback_sees_every_episode(make_fast_env: MakeEnv) -> None:
    seen: list[tuple[int, int]] = []
    records = run_episodes(
        make_fast_env(env={"duration": 3}),
        fixed_policy("idle"),
        2,
        seed=0,
        progress=lambda i, r: seen.append((i, r.seed)),
    )
    assert seen == [(0, 0), (1, 1)]
    assert len(records) == 2


def test_run_episodes_needs_an_episode(make_fast_env: MakeEnv) -> None:
    with pytest.raises(ValueError, match="episodes"):
        run_episodes(make_fast_env(), fixed_policy("idle"), 0, seed=0)


def test_shielded_always_faster_is_overridden(make_fast_env: MakeEnv) -> None:
    env = make_fast_env(env={"duration": 10}, shield={"mode": "robust", "override": True})
    (record,) = run_episodes(env, fixed_policy("faster"), 1, seed=0)
    assert 0 < record.interventions <= record.length
    assert record.actions[FASTER] < record.length  # executed actions, after the override


# --- summary -------------------------------------------------------------------------------------------------


def _record(seed: int, length: int, kind: str | None, speed: float, interventions: int = 0) -> EpisodeRecord:
    return EpisodeRecord(
        seed=seed,
        return_=float(length) - (10.0 if kind else 0.0),
        length=length,
        collision=kind is not None,
        time_to_collision=float(length) if kind else None,
        mean_speed=speed,
        interventions=interventions,
        fallbacks=1 if interventions else 0,
        collision_kind=kind,
        unsafe_actions=2 * interventions,
        actions=[0, length, 0, 0, 0],
        vehicles_passed=seed - 1,
    )


def test_summarize_hand_worked() -> None:
    records = [
        _record(0, 40, None, 20.0, interventions=4),
        _record(1, 10, "side", 25.0),
        _record(2, 30, "ego_hit_front", 27.0, interventions=2),
        _record(3, 20, "side", 24.0),
    ]
    summary = summarize(records, policy="idle", shield="none", preset="fast", seed=0, wall_time_s=1.5)
    assert summary["episodes"] == 4
    assert summary["decisions"] == 100
    assert summary["collisions"] == 3
    assert summary["collision_rate"] == 0.75
    assert summary["mean_speed"] == 24.0
    assert summary["mean_length"] == 25.0
    assert summary["mean_return"] == pytest.approx((40 + 0 + 20 + 10) / 4)
    assert summary["time_to_collision"] == [None, 10.0, 30.0, 20.0]
    assert summary["shield_intervention_rate"] == 0.06
    assert summary["fallback_rate"] == 0.02
    assert summary["unsafe_action_rate"] == 0.12
    assert summary["mean_vehicles_passed"] == 0.5  # (-1 + 0 + 1 + 2) / 4
    assert summary["collision_kinds"] == {"ego_hit_front": 1, "rear_ended": 0, "side": 2}
    assert summary["actions"]["IDLE"] == 100
    assert summary["policy"] == "idle" and summary["wall_time_s"] == 1.5
    json.dumps(summary, allow_nan=False)


def test_summarize_needs_records() -> None:
    with pytest.raises(ValueError, match="no episodes"):
        summarize([])


def test_evaluate_fixed_adds_its_meta() -> None:
    cfg = load_config("fast", sets=["env.duration=4"])
    summary = evaluate_fixed(cfg, "slower", episodes=2, seed=3)
    assert summary["policy"] == "slower"
    assert summary["shield"] == "none" and summary["override"] is False
    assert summary["preset"] == "fast" and summary["env_id"] == "highway-fast-v0"
    assert summary["seed"] == 3 and summary["episodes"] == 2
    assert summary["decisions"] == 8
    assert summary["wall_time_s"] > 0
    json.dumps(summary, allow_nan=False)


@pytest.mark.parametrize(("episodes", "seed", "option"), [(0, 0, "--episodes"), (2, -1, "--seed")])
def test_evaluate_fixed_validates_its_inputs(episodes: int, seed: int, option: str) -> None:
    with pytest.raises(ConfigError, match=f"^{option}: must be >= "):
        evaluate_fixed(load_config("fast"), "idle", episodes, seed)


def test_vehicles_ahead_counts_overtakes_on_the_real_road() -> None:
    """The ego (25 m/s) passes a slow car (15 m/s, 10 m ahead, next lane) and is passed by a fast one
    (35 m/s, 20 m behind, other lane): net overtakes 1 − 1 = 0, as the episode record computes it."""
    from safelane.env import scenarios
    from safelane.running.evaluation import vehicles_ahead

    specs = [scenarios.VehicleSpec(2, 10.0, 15.0), scenarios.VehicleSpec(0, -20.0, 35.0)]
    scene = scenarios.build_scene(1, 25.0, specs, mode="robust")
    assert vehicles_ahead(scene.shield.snapshot) == 1
    for _ in range(3):
        *_, info = scene.env.step(IDLE)
    assert vehicles_ahead(info["snapshot"]) == 1  # passed the slow one, passed by the fast one
    slow, fast = (v for v in scene.env.unwrapped.road.vehicles if v is not scene.env.unwrapped.vehicle)
    ego_x = scene.env.unwrapped.vehicle.position[0]
    assert slow.position[0] < ego_x < fast.position[0]


# --- batched evaluation ----------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["dqn", "robust"])
def test_batched_evaluation_plays_the_same_episodes_as_one_environment(method: str) -> None:
    """A trained-agent policy played on 4 fast-simulator environments at once (one forward pass per
    round) gives the records of the same episodes played one by one: same seeds, same decisions."""
    from safelane.agents.dqn import make_agent
    from safelane.running.evaluation import BatchPolicy, run_config
    from safelane.running.run_directory import GreedyPolicy, make_train_config, resolve
    from safelane.running.runs import run_env_config

    run = resolve(make_train_config(method=method, episodes=1, seed=0, sets=["simulator=fast"]))
    policy = GreedyPolicy(make_agent(run.agent, seed=3), run)
    assert isinstance(policy, BatchPolicy)
    cfg = run_env_config(run)
    seen: list[int] = []
    one = run_config(cfg, policy, 9, 100, num_envs=1)
    many = run_config(cfg, policy, 9, 100, progress=lambda i, r: seen.append(i), num_envs=4)
    assert [r.to_dict() for r in many] == [r.to_dict() for r in one]
    assert [r.chosen_actions for r in many] == [r.chosen_actions for r in one]
    assert sorted(seen) == list(range(9))
    assert len({r.length for r in one}) > 1 or method == "robust"  # dqn's crashes refill slots mid-round


class _ObservationHashPolicy:
    """A deterministic batch policy that crashes often: the action is a function of the observation's
    bits (the same in any batch), so one-by-one and batched play take the same decisions."""

    def __call__(self, obs: np.ndarray, info: dict) -> int:
        return int(np.abs(obs).sum() * 1000) % 5

    def batch(self, obs: np.ndarray, infos: list[dict]) -> np.ndarray:
        return np.array([self(row, info) for row, info in zip(obs, infos, strict=True)])


@pytest.mark.parametrize(
    ("shield", "override"),
    [("robust", True), ("robust", False), ("nominal", True), ("none", False)],
)  # fmt: skip
def test_fast_batch_records_equal_the_wrapper_stack_with_crashes_and_breaks(shield: str, override: bool) -> None:
    """The fused fast batch (run_config's path on the fast simulator), the loop over make_env stacks
    (run_episodes_batched) and one environment (run_episodes) give the same records, in dense traffic
    where the policy crashes and the robust rule's invariant breaks: collision kinds and contexts,
    breaks, fallbacks, interventions, overtakes."""
    from safelane.env.factory import make_env
    from safelane.running.evaluation import run_config, run_episodes, run_episodes_batched

    cfg = load_config(
        "fast",
        overrides={
            "simulator": "fast",
            "shield.mode": shield,
            "shield.override": override,
            "env.lanes_count": 6,
            "env.vehicles_density": 2.0,
        },
    )
    policy = _ObservationHashPolicy()
    fused = run_config(cfg, policy, 14, 40, num_envs=5)
    stacks = run_episodes_batched([make_env(cfg) for _ in range(5)], policy, 14, 40)
    one = run_episodes(make_env(cfg), policy, 14, 40)
    as_dicts = [[r.to_dict() for r in records] for records in (fused, stacks, one)]
    assert as_dicts[0] == as_dicts[1] == as_dicts[2]
    assert [r.chosen_actions for r in fused] == [r.chosen_actions for r in one]
    if not override:  # crashes happened (and refilled slots mid-round)
        assert sum(r.collision for r in one) >= 3
    if override:
        assert sum(r.interventions for r in one) > 0 and sum(r.fallbacks for r in one) > 0
    if shield == "robust" and override:
        assert sum(len(r.invariant_breaks) for r in one) > 0


@pytest.mark.parametrize("name", ["faster", "slower", "probe"])
def test_deterministic_fixed_policies_play_the_same_episodes_on_the_fast_batch(name: str) -> None:
    """always-FASTER / SLOWER and the probe (which reads every state's snapshot) are batch policies:
    run_config plays them on the fast batch and gets the records of one environment."""
    from safelane.env.factory import make_env
    from safelane.running.evaluation import BatchPolicy, run_config, run_episodes

    cfg = load_config(
        "fast",
        overrides={"simulator": "fast", "shield.mode": "robust", "shield.override": True, "env.vehicles_density": 2.0},
    )
    policy = fixed_policy(name)
    assert isinstance(policy, BatchPolicy)
    batched = run_config(cfg, policy, 8, 900, num_envs=3)
    one = run_episodes(make_env(cfg), policy, 8, 900)
    assert [r.to_dict() for r in batched] == [r.to_dict() for r in one]
    if name == "faster":  # the shield had to replace FASTER
        assert sum(r.interventions for r in one) > 0
    if name == "probe":  # it overtook, choosing inside the mask
        assert sum(r.actions[0] + r.actions[2] for r in one) > 0 and sum(r.interventions for r in one) == 0


def test_run_config_rejects_a_batch_of_no_environments() -> None:
    from safelane.running.evaluation import run_config

    with pytest.raises(ConfigError, match="num_envs: must be >= 1"):
        run_config(load_config("fast", overrides={"simulator": "fast"}), fixed_policy("idle"), 2, 0, num_envs=0)


def test_probe_policy_drives_inside_the_mask() -> None:
    """``probe`` (the overtaking heuristic) only chooses actions the shield allows: never overridden."""
    from safelane.config import load_config
    from safelane.env.factory import make_env
    from safelane.running.evaluation import run_episode

    shielded = {"simulator": "fast", "shield.mode": "robust", "shield.override": True}
    env = make_env(load_config("fast", overrides=shielded))
    record = run_episode(env, fixed_policy("probe"), 5000)
    env.close()
    assert record.length > 0 and record.interventions == 0 and record.mean_speed > 15
