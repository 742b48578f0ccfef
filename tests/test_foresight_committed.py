"""The foresight planner under the committed mask (memory carried by every search node) and the table's committed
rows (real fast simulator, real committed shield; its numpy reference engine)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from safelane.config import ConfigError, load_config
from safelane.core.spaces import FASTER, SLOWER
from safelane.env.factory import make_env
from safelane.env.scenarios import find_shield
from safelane.running.foresight import ForesightPlanner, at_rate, ceiling_table, clone_memory, with_overrides

COMMITTED = {"shield.engine": "numpy"}


def committed_env(duration: int, rate: int = 1):
    cfg = at_rate(load_config("fast", overrides={"simulator": "fast"}), rate)
    sets = {"shield.mode": "committed", "shield.override": True, "env.duration": duration, **COMMITTED}
    return make_env(with_overrides(cfg, sets))


@pytest.mark.parametrize("rate", [1, 2])
def test_committed_planner_plays_only_what_the_committed_mask_allows_at_that_node(rate: int) -> None:
    # replan = horizon: the planner replays whole plans, so every action after a plan's first was judged at a search
    # node with that node's own memory; the environment's shield (its own memory) must allow each one.
    env = committed_env(duration=6, rate=rate)
    obs, info = env.reset(seed=4)
    planner = ForesightPlanner(env, mask="committed", horizon=2.0, beam=3, replan=2.0, engine="numpy")
    shield_memory = find_shield(env).family
    done, played = False, 0
    while not done:
        action = planner(obs, info)
        assert info["action_mask"][action], (played, info["action_mask"], action)
        obs, _, terminated, truncated, info = env.step(action)
        assert not info["shield_intervened"] and not info["crashed"]
        # the planner's record of the episode is the shield's: the same plan kept
        assert planner.memory is not None and planner.memory.kept == shield_memory.kept  # type: ignore[attr-defined]
        done, played = terminated or truncated, played + 1
    assert played == 6 * rate and planner.searches == 3 and planner.nodes > played


def test_clone_memory_is_independent_of_its_source() -> None:
    env = committed_env(duration=4)
    _, info = env.reset(seed=1)
    planner = ForesightPlanner(env, mask="committed", horizon=1.0, beam=2, engine="numpy")
    memory = planner.memory
    assert memory is not None
    mask, _ = planner.allowed(info["snapshot"])
    verified = [a for a in (FASTER, SLOWER) if mask[a]]
    assert verified, mask  # a free road at the start: both verify
    copies = [clone_memory(memory) for _ in verified]
    for copy, action in zip(copies, verified, strict=True):
        copy.commit(action)
    assert memory.kept is None and memory.carried is None  # the source committed nothing
    kept = [c.kept for c in copies]
    assert all(k is not None for k in kept)
    assert [k.action for k in kept] == verified  # type: ignore[union-attr]
    assert copies[0].carried is not copies[-1].carried or len(copies) == 1


def test_ceiling_table_has_the_committed_rows(tmp_path: Path) -> None:
    from safelane.running.run_directory import make_train_config
    from safelane.running.training import train

    run_dir = train(
        make_train_config(method="robust", episodes=1, seed=0, sets=["simulator=fast", "env.duration=4"]),
        tmp_path / "agent",
    )
    cfg = load_config("fast", sets=["env.duration=4", *(f"{k}={v}" for k, v in COMMITTED.items())],
                      overrides={"simulator": "fast"})  # fmt: skip
    out = tmp_path / "ceiling"
    rows = ("foresight_committed", "agent_committed")
    table = ceiling_table(cfg, [1], 2, 7, out, agents={1: str(run_dir)}, horizon=2.0, beam=2, chunk=1, workers=1,
                          rows=rows)  # fmt: skip
    played = table["rates"]["1"]
    assert set(played) == set(rows)
    for row in rows:
        r = played[row]
        assert r["episodes"] == 2 and r["collisions"] == 0
        assert {"plan_forced_rate", "lapses", "lapses_in_model", "uncertified_starts"} <= set(r)
        assert 0 <= r["plan_forced_rate"] <= 1 and r["lapses_in_model"] <= r["lapses"]
    assert played["foresight_committed"]["shield_intervention_rate"] == 0.0  # it plays only what the mask allows
    assert played["foresight_committed"]["mean_speed"] > 0
    assert "foresight under the committed mask" in (out / "ceiling.md").read_text()
    with pytest.raises(ConfigError, match="--rows"):
        ceiling_table(cfg, [1], 1, 7, out, rows=("foresight_committed", "committed"))
    assert np.isfinite(played["agent_committed"]["mean_speed"])
    with pytest.raises(ConfigError, match="takes meta-actions; give it with --agent"):
        ceiling_table(cfg, [1], 1, 7, tmp_path / "c2", rows=("agent_continuous",), continuous_agents={1: str(run_dir)},
                      workers=1)  # fmt: skip


def test_every_search_node_carries_the_memory_the_shield_has_after_its_actions() -> None:
    env = committed_env(duration=8)
    env.reset(seed=6)
    planner = ForesightPlanner(env, mask="committed", horizon=3.0, beam=4, engine="numpy")
    planner.search()
    assert len(planner.last_frontier) > 1
    for actions, memory in planner.last_frontier:
        assert len(actions) == 3 and memory is not None
        replay = committed_env(duration=8)
        _, info = replay.reset(seed=6)
        for action in actions:  # each action was in the committed mask at its node: the shield's own memory agrees
            assert info["action_mask"][action], (actions, info["action_mask"])
            _, _, _, _, info = replay.step(action)
            assert not info["shield_intervened"]
        shield_memory = find_shield(replay).family
        assert memory.kept == shield_memory.kept and memory.kept_verified == shield_memory.kept_verified  # type: ignore[attr-defined]
        replay.close()
