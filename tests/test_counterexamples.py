"""Counterexample files: every crash and invariant break saved, replayed to the same event (on the fast
simulator and on highway-env), and `safelane replay` (real simulators, real CLI)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from safelane.config import ConfigError, load_config
from safelane.running.counterexamples import (
    load_counterexample,
    replay,
)
from safelane.running.evaluation import evaluate_fixed

FAST = {"simulator": "fast"}


def test_crashes_are_saved_and_replay_to_the_same_crash_on_both_simulators(tmp_path: Path) -> None:
    """Always-FASTER without a shield crashes (seed 0: into the car ahead after 7 decisions); its file
    replays to the same crash at the same decision on the fast simulator and on highway-env."""
    summary = evaluate_fixed(load_config("fast", overrides=FAST), "faster", 1, 0, counterexamples=tmp_path)
    assert summary["collisions"] == 1 and len(summary["counterexample_files"]) == 1
    cx = load_counterexample(summary["counterexample_files"][0])
    assert (cx.kind, cx.seed, cx.step, cx.collision_kind) == ("collision", 0, 7, "ego_hit_front")
    assert cx.actions == [3] * 7
    for simulator in ("fast", "highway-env"):
        result = replay(cx, simulator)
        assert result.reproduced and result.collision_kind == "ego_hit_front"
        assert len(result.decisions) == 7 and result.decisions[-1].collision
        assert not any(d.collision for d in result.decisions[:-1])


def test_invariant_breaks_are_saved_and_replay_to_the_same_break(tmp_path: Path) -> None:
    """Random actions under the robust shield (override on) on the fast preset, 3 lanes at density 2: episode
    seed 3 reaches a fallback state right after its second, allowed, decision. The file replays to that break,
    on highway-env too, with the state before it logged (a safe action existed: not a fallback). (On the stock
    fast preset the rule forecast-fallback has no break in 30 random episodes.)"""
    overrides = {**FAST, "env": {"lanes_count": 3, "vehicles_density": 2.0}}
    cfg = load_config("fast", overrides={**overrides, "shield": {"mode": "robust", "override": True}})
    summary = evaluate_fixed(cfg, "random", 4, 0, counterexamples=tmp_path)
    assert summary["invariant_breaks"] >= 1
    path = tmp_path / "seed3-invariant_break-step2.json"
    assert str(path) in summary["counterexample_files"]
    cx = load_counterexample(path)
    for simulator in ("fast", "highway-env"):
        result = replay(cx, simulator)
        assert result.reproduced
        last = result.decisions[-1]
        assert last.invariant_break and last.fallback_after and not last.fallback_before
        assert last.mask[last.executed]


def test_a_tampered_file_is_not_reproduced_and_a_broken_one_is_one_line(tmp_path: Path, safelane_exe: Path) -> None:
    summary = evaluate_fixed(load_config("fast", overrides=FAST), "faster", 1, 0, counterexamples=tmp_path)
    path = Path(summary["counterexample_files"][0])
    ok = subprocess.run([str(safelane_exe), "replay", str(path), "--json"], capture_output=True, text=True, check=False)
    assert ok.returncode == 0, ok.stderr
    assert json.loads(ok.stdout)["reproduced"] is True
    table = subprocess.run([str(safelane_exe), "replay", str(path)], capture_output=True, text=True, check=False)
    assert "reproduced: collision (ego_hit_front) after decision 7 on fast" in table.stdout
    data = json.loads(path.read_text())
    data["actions"] = [4] * 7  # SLOWER instead: no crash
    tampered = tmp_path / "tampered.json"
    tampered.write_text(json.dumps(data))
    bad = subprocess.run([str(safelane_exe), "replay", str(tampered)], capture_output=True, text=True, check=False)
    assert bad.returncode == 1 and "NOT reproduced" in bad.stdout
    (tmp_path / "junk.json").write_text('{"kind": "crash"}')
    junk = subprocess.run(
        [str(safelane_exe), "replay", str(tmp_path / "junk.json")], capture_output=True, text=True, check=False
    )
    assert junk.returncode == 2 and junk.stderr.count("\n") == 1 and "not a counterexample" in junk.stderr
    with pytest.raises(ConfigError, match="no such counterexample file"):
        load_counterexample(tmp_path / "missing.json")


FIXTURES = Path(__file__).resolve().parent / "fixtures"  # pinned campaign files: fixtures/README.md


def test_claim_campaign_crash_files_replay_to_the_same_crash_on_both_simulators() -> None:
    """The claim campaign's crash files under the rule forecast-fallback (337, all confirmed on highway-env):
    every 28th of them, sorted by name, and cells 88 and 127 (15 files: 14 unsafe spawns and hole 2879's crash
    after a break; 1, 2, 3 and 5 decisions per second; IDM, Linear, Aggressive and Defensive drivers), replays to
    the same crash at the same decision on the fast simulator and on highway-env."""
    files = sorted((FIXTURES / "claim" / "crashes").glob("*-collision-*.json"))
    assert len(files) == 15
    for path in files:
        cx = load_counterexample(path)
        for simulator in ("fast", "highway-env"):
            result = replay(cx, simulator)
            assert result.reproduced and result.collision_kind == cx.collision_kind, (path.name, simulator)
            assert len(result.decisions) == cx.step and result.decisions[-1].collision


def test_confirm_script_replays_a_random_sample_of_a_folder(tmp_path: Path) -> None:
    """examples/confirm_counterexamples.py --sample 1 on a folder holding the two holes' breaks replays one of
    them, drawn by the seed, to the same break (on the fast simulator here) and records the draw; --sample 0 is a
    one-line error (exit 2)."""
    import shutil
    import sys

    names = [
        "cell00552-seed4005520033-invariant_break-step2.json",
        "cell02879-seed4028790006-invariant_break-step11.json",
    ]
    folder = tmp_path / "breaks"
    folder.mkdir()
    for name in names:
        shutil.copy(FIXTURES / "claim" / "breaks" / name, folder / name)
    script = [sys.executable, str(Path(__file__).resolve().parents[1] / "examples" / "confirm_counterexamples.py")]
    out = tmp_path / "confirm.json"
    common = [str(folder), "--kind", "invariant_break", "--simulator", "fast", "--workers", "1", "--out", str(out)]
    subprocess.run([*script, *common, "--sample", "1", "--seed", "3"], check=True, capture_output=True)
    summary = json.loads(out.read_text())
    assert (summary["files"], summary["reproduced"], summary["sample"], summary["seed"]) == (1, 1, 1, 3)
    assert summary["rows"][0]["file"] in names
    bad = subprocess.run([*script, *common, "--sample", "0"], capture_output=True, text=True)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1, bad.stderr
    assert "--sample" in bad.stderr


def test_counterexample_files_are_flushed_together_not_one_fsync_each(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The scene above's break files are written atomically without an fsync each, then flushed once; every file
    is whole and no temporary file is left (a hidden-types campaign writes tens of thousands)."""
    import os

    calls = {"fsync": 0, "sync": 0}
    real_fsync, real_sync = os.fsync, os.sync

    def fsync(fd: int) -> None:
        calls["fsync"] += 1
        real_fsync(fd)

    def sync() -> None:
        calls["sync"] += 1
        real_sync()

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "sync", sync)
    overrides = {**FAST, "env": {"lanes_count": 3, "vehicles_density": 2.0}}
    cfg = load_config("fast", overrides={**overrides, "shield": {"mode": "robust", "override": True}})
    summary = evaluate_fixed(cfg, "random", 4, 0, counterexamples=tmp_path)
    files = summary["counterexample_files"]
    assert files and calls == {"fsync": 0, "sync": 1}
    assert all(load_counterexample(f).kind == "invariant_break" for f in files)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(Path(f).name for f in files)  # no .tmp left
