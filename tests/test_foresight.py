"""The foresight planner and the price-of-robustness table (real fast simulator, real shield, real CLI)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from safelane.cli import app
from safelane.config import ConfigError, load_config
from safelane.core.spaces import FASTER
from safelane.env.factory import make_env
from safelane.running.foresight import ForesightPlanner, at_rate, ceiling_table, with_overrides

runner = CliRunner()


def fast_env(rate: int = 1, shield: str = "none", **sets: object):
    cfg = at_rate(load_config("fast", overrides={"simulator": "fast"}), rate)
    overrides: dict[str, object] = {"shield.mode": shield, **sets}
    if shield != "none":
        overrides["shield.override"] = True
    return make_env(with_overrides(cfg, overrides))


@pytest.mark.parametrize("rate", [1, 3])
def test_set_state_replays_the_same_future(rate: int) -> None:
    env = fast_env(rate)
    sim = env.unwrapped
    env.reset(seed=11)
    rng = np.random.default_rng(0)
    for _ in range(3):
        env.step(int(rng.integers(5)))
    saved = sim.get_state()
    actions = [int(a) for a in rng.integers(5, size=12)]

    def future() -> list[np.ndarray]:
        sim.set_state(saved)
        states = []
        for a in actions:
            _, _, terminated, _, _ = sim.step(a)
            states.append(np.concatenate([sim.F.ravel(), sim.G.ravel().astype(float), [sim.time]]))
            if terminated:
                break
        return states

    first, second = future(), future()
    assert len(first) == len(second) and all(np.array_equal(a, b) for a, b in zip(first, second, strict=True))
    # and set_state copies in: the saved state is not changed by stepping after it
    assert not np.shares_memory(saved.F, sim.F)


def test_planner_avoids_the_crash_always_faster_makes_and_restores_the_state() -> None:
    # always-FASTER crashes in this episode at decision 7 (tests/test_counterexamples.py); the planner
    # knows the future and drives the same 10 decisions without a collision.
    env = fast_env()
    env.reset(seed=0)
    crashed_at = next((k for k in range(1, 11) if env.step(FASTER)[2]), None)
    assert crashed_at is not None and crashed_at <= 8

    obs, info = env.reset(seed=0)
    planner = ForesightPlanner(env, horizon=3.0, beam=4)
    sim = env.unwrapped
    for _ in range(10):
        before = sim.get_state()
        planner.plan = []
        action = planner(obs, info)
        after = sim.get_state()
        assert np.array_equal(before.F, after.F) and before.time == after.time  # the search restored it
        obs, _, terminated, _, info = env.step(action)
        assert not terminated
    assert planner.searches == 10 and planner.nodes > 10


def test_masked_planner_only_takes_actions_its_mask_allows() -> None:
    env = fast_env(shield="robust", **{"env.duration": 12})
    obs, info = env.reset(seed=3)
    planner = ForesightPlanner(env, mask="robust", horizon=2.0, beam=3)
    done = False
    while not done:
        mask = info["action_mask"]
        action = planner(obs, info)
        assert mask[action]
        obs, _, terminated, truncated, info = env.step(action)
        assert not info["shield_intervened"]
        done = terminated or truncated


def test_planner_needs_the_fast_simulator_and_checks_its_settings() -> None:
    hw = make_env(load_config("fast", overrides={"simulator": "highway-env"}))
    with pytest.raises(ConfigError, match="simulator"):
        ForesightPlanner(hw)
    hw.close()
    with pytest.raises(ConfigError, match="mask"):
        ForesightPlanner(fast_env(), mask="strict")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="beam"):
        ForesightPlanner(fast_env(), beam=0)


def test_ceiling_table_writes_cells_and_resumes(tmp_path: Path) -> None:
    cfg = load_config("fast", sets=["env.duration=5"], overrides={"simulator": "fast"})
    out = tmp_path / "ceiling"
    table = ceiling_table(cfg, [1], 2, 7, out, horizon=2.0, beam=2, chunk=1, workers=1)
    rows = table["rates"]["1"]
    assert set(rows) == {
        "foresight", "foresight_nominal", "foresight_robust", "probe_robust", "foresight_committed",
        "foresight_continuous", "foresight_continuous_committed",
    }  # fmt: skip
    assert all(r["episodes"] == 2 for r in rows.values())
    assert rows["foresight_robust"]["shield_intervention_rate"] == 0.0  # the planner respects its mask
    cells = sorted((out / "cells").glob("*.json"))
    assert len(cells) == 14
    stamps = {p.name: p.stat().st_mtime_ns for p in cells}
    cells[0].unlink()  # as if killed before that chunk finished
    again = ceiling_table(cfg, [1], 2, 7, out, horizon=2.0, beam=2, chunk=1, workers=1)
    assert _same_but_wall(again, table)
    assert {p.name: p.stat().st_mtime_ns for p in sorted((out / "cells").glob("*.json")) if p != cells[0]} == {
        k: v for k, v in stamps.items() if k != cells[0].name
    }
    assert "foresight under the robust mask" in (out / "ceiling.md").read_text()


def _same_but_wall(a: dict, b: dict) -> bool:
    """Equal tables apart from wall times (a re-played chunk takes another time)."""

    def strip(t: dict) -> dict:
        return {r: {k: v for k, v in row.items() if k != "wall_time_s"} for r, row in t["rates"]["1"].items()}

    return strip(a) == strip(b)


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--rates", "1,x"], "--rates"),
        (["--agent", "one=runs/x"], "--agent"),
        (["--rates", "1", "--agent", "2=runs/x"], "--agent"),
        (["--episodes", "0"], "--episodes"),
        (["--rows", "foresight,committed"], "--rows"),
    ],
)
def test_ceiling_bad_input_is_one_line(args: list[str], needle: str, tmp_path: Path) -> None:
    result = runner.invoke(app, ["ceiling", "--out", str(tmp_path / "c"), *args])
    assert result.exit_code == 2, result.output
    assert needle in result.output and "Traceback" not in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_ceiling_cli_json(tmp_path: Path) -> None:
    result = runner.invoke(
        app,
        ["ceiling", "--rates", "1", "--episodes", "1", "--beam", "2", "--horizon", "1", "--set", "env.duration=3",
         "--out", str(tmp_path / "c"), "--workers", "1", "--json"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    table = json.loads(result.output)
    assert table["rates"]["1"]["foresight"]["episodes"] == 1
