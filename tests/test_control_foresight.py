"""The foresight planner over continuous controls and the price table's continuous rows (real fast simulator, real
shield for continuous actions, a real trained agent)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from safelane.config import ConfigError, load_config
from safelane.env.factory import make_env
from safelane.running.continuous_training import train_continuous
from safelane.running.control_foresight import CONTROL_ACCELERATIONS, ControlForesightPlanner, control_set, shield_of
from safelane.running.foresight import at_rate, ceiling_table, with_overrides
from safelane.running.policies import continuous_ranges
from safelane.running.run_directory import make_train_config


def continuous_env(shield: str, duration: int = 6, rate: int = 1):
    cfg = at_rate(load_config("fast", overrides={"simulator": "fast"}), rate)
    return make_env(with_overrides(cfg, {"actions": "continuous", "shield.mode": shield, "env.duration": duration}))


def test_control_set_steers_for_the_lanes_on_the_road() -> None:
    env = continuous_env("none")
    _, info = env.reset(seed=3)
    snap = info["snapshot"]
    ranges = continuous_ranges(dict(env.unwrapped.config["action"]))
    actions = control_set(snap, *ranges)
    lanes = [lane for lane in (snap.lane[0] - 1, snap.lane[0], snap.lane[0] + 1) if 0 <= lane < snap.lanes_count]
    assert len(actions) == len(CONTROL_ACCELERATIONS) * len(lanes)
    assert [float(a[0]) for a in actions[:5]] == list(CONTROL_ACCELERATIONS)
    steerings = sorted({float(a[1]) for a in actions})
    assert len(steerings) == len(lanes)
    # at a lane's centre, heading along the road: its own lane's steering is straight, a lane to the left (higher
    # index, larger y) steers left (positive), one to the right the other way
    assert snap.ego_lane_offset == 0.0 and snap.heading[0] == 0.0
    by_lane = dict(zip(lanes, [float(actions[5 * i][1]) for i in range(len(lanes))], strict=True))
    assert by_lane[int(snap.lane[0])] == 0.0
    assert all(math.copysign(1.0, s) == math.copysign(1.0, lane - snap.lane[0]) for lane, s in by_lane.items()
               if lane != snap.lane[0])  # fmt: skip


@pytest.mark.parametrize("rate", [1, 2])
def test_shielded_planner_plays_only_actions_the_shield_verifies(rate: int) -> None:
    # replan = horizon: the planner replays whole plans, so every action after a plan's first was verified at a
    # search node with that node's own copy of the shield's memory; the environment's shield, with its own memory,
    # must execute each one unchanged (a projection would show the copies went wrong; where none of the control set
    # verified at a node, the planner played what the shield executes there: the kept plan's next step).
    env = continuous_env("committed", rate=rate)
    obs, info = env.reset(seed=4)
    planner = ControlForesightPlanner(env, horizon=2.0, beam=3, replan=2.0)
    assert planner.shield is shield_of(env) is not None
    done, played = False, 0
    while not done:
        action = planner(obs, info)
        obs, _, terminated, truncated, info = env.step(action)
        assert not info["projected"] and not info["crashed"] and not info["lapse_in_model"], played
        np.testing.assert_array_equal(info["executed_action"], action)
        done, played = terminated or truncated, played + 1
    assert played == 6 * rate and planner.searches == 3 and planner.nodes > played


def test_unshielded_planner_is_deterministic_and_stops_in_time() -> None:
    def episode() -> list[np.ndarray]:
        env = continuous_env("none", duration=8)
        obs, info = env.reset(seed=5003)  # without the stopping check the search crashes here at decision 6
        planner = ControlForesightPlanner(env, horizon=2.0, beam=4)
        actions, done = [], False
        while not done:
            actions.append(planner(obs, info))
            obs, _, terminated, truncated, info = env.step(actions[-1])
            assert not info["crashed"] and not info["off_road"]
            done = terminated or truncated
        return actions

    first = episode()
    assert len(first) == 8
    np.testing.assert_array_equal(np.array(first), np.array(episode()))


def test_planner_needs_continuous_actions_on_the_fast_simulator() -> None:
    cfg = load_config("fast", overrides={"simulator": "fast"})
    with pytest.raises(ConfigError, match="actions"):
        ControlForesightPlanner(make_env(cfg))
    with pytest.raises(ConfigError, match="beam"):
        ControlForesightPlanner(continuous_env("none"), beam=0)


def test_ceiling_table_has_the_continuous_rows(tmp_path: Path) -> None:
    road = ["simulator=fast", "actions=continuous", "env.duration=3", "env.vehicles_count=8"]
    agent = ["agent.learning_starts=10", "agent.batch_size=16", "agent.net_arch=[32, 32]", "agent.buffer_size=100"]
    sets = [*road, *agent]
    run = train_continuous(make_train_config(algo="sac", steps=30, seed=0, sets=sets), tmp_path / "sac")
    cfg = load_config("fast", sets=["env.duration=3"], overrides={"simulator": "fast"})
    rows = ("foresight_continuous", "foresight_continuous_committed", "agent_continuous")
    table = ceiling_table(cfg, [1], 2, 7, tmp_path / "ceiling", horizon=2.0, beam=2, workers=1, rows=rows,
                          continuous_agents={1: str(run)})  # fmt: skip
    got = table["rates"]["1"]
    assert set(got) == set(rows)
    for row in rows:
        assert got[row]["episodes"] == 2 and got[row]["decisions"] > 0 and "off_road_rate" in got[row]
    assert got["foresight_continuous_committed"]["projection_rate"] == 0.0  # it plays verified actions only
    assert got["foresight_continuous_committed"]["lapses_in_model"] == 0
    assert "projection_rate" not in got["foresight_continuous"]  # unshielded
    assert got["agent_continuous"]["agent"] == str(run)
    text = (tmp_path / "ceiling" / "ceiling.md").read_text()
    assert "foresight, continuous controls, under the shield for continuous actions" in text
    with pytest.raises(ConfigError, match="--continuous-agent"):
        ceiling_table(cfg, [1], 1, 7, tmp_path / "c2", rows=rows, continuous_agents={2: str(run)})
    with pytest.raises(ConfigError, match="takes continuous actions; give it with --continuous-agent"):
        ceiling_table(cfg, [1], 1, 7, tmp_path / "c3", rows=("agent_robust",), agents={1: str(run)}, workers=1)
