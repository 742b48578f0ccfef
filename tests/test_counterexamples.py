"""Counterexample files: every crash and invariant break saved, replayed to the same event (on the fast
simulator and on highway-env), and `safelane replay` (real simulators, real CLI)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from safelane.config import ConfigError, load_config
from safelane.running.counterexamples import (
    break_culprits,
    break_under_options,
    break_with_carried_followers,
    crash_partner,
    load_counterexample,
    repair_break,
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
    fast preset today's rule has no break in 30 random episodes.)"""
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


CAMPAIGN = Path(__file__).resolve().parents[1] / "docs" / "results" / "falsify"
CELL_38 = "cell00038-seed4000380020-collision-step26.json"
CELL_169 = "cell00169-seed4001690001-collision-step34.json"


def test_crash_partner_tells_a_reversing_car_from_one_inside_the_model() -> None:
    """crash_partner: cell 38's crash (the campaign's reversing leader: the car 6 m ahead rolls back at
    2 m/s into the nearly stopped ego) has its partner in the ego's lane, ahead, moving backwards; the
    trained agents' cell 169 (a car two lanes over changing into the lane the ego enters) has a partner
    moving forwards. A break file has no crash partner."""
    reversing = crash_partner(load_counterexample(CAMPAIGN / "grid_100k" / "counterexamples" / CELL_38))
    assert reversing["reversing"] and reversing["lane_vs_ego"] == [0, 0]
    assert reversing["dx"][0] > 0 and min(reversing["speed"]) < 0
    side = crash_partner(load_counterexample(CAMPAIGN / "grid_agents_level_cut_ins" / "counterexamples" / CELL_169))
    assert not side["reversing"] and side["lane_vs_ego"] == [2, 1] and min(side["speed"]) > 10
    breaks = sorted((CAMPAIGN / "grid" / "counterexamples").glob("*invariant_break*.json"))
    with pytest.raises(ConfigError, match="collisions only"):
        crash_partner(load_counterexample(breaks[0]))


def test_claim_campaign_crash_files_replay_to_the_same_crash_on_both_simulators() -> None:
    """The claim campaign's crash files under today's rule (docs/results/falsify/grid_100k_behind_forecast_fallback:
    337, all confirmed on highway-env by examples/confirm_counterexamples.py, confirm_collisions_all.json): every
    28th of them, sorted by name (13 files: 12 unsafe spawns and hole 2879's crash after a break; 1, 2, 3 and 5
    decisions per second; IDM, Linear, Aggressive and Defensive drivers), replays to the same crash at the same
    decision on the fast simulator and on highway-env."""
    files = sorted((CAMPAIGN / "grid_100k_behind_forecast_fallback" / "counterexamples").glob("*-collision-*.json"))
    assert len(files) == 337
    for path in files[::28]:
        cx = load_counterexample(path)
        for simulator in ("fast", "highway-env"):
            result = replay(cx, simulator)
            assert result.reproduced and result.collision_kind == cx.collision_kind, (path.name, simulator)
            assert len(result.decisions) == cx.step and result.decisions[-1].collision


def test_claim_campaign_break_files_keep_their_published_classification() -> None:
    """The claim campaign's 2 842 break files under today's rule (docs/results/falsify/
    grid_100k_behind_forecast_fallback/breaks), classified by examples/repair_breaks.py --culprits
    (break_repairs.json: 133 outside the model, 2 709 in it): every 400th of them, sorted by name (8 files, one
    outside the model, five first-culprit roles), replays to a break at the same decision on the fast simulator
    and on highway-env, and gets the published verdict again — the repair, its best gap to the millimetre and its
    first culprit's role."""
    folder = CAMPAIGN / "grid_100k_behind_forecast_fallback"
    published = json.loads((folder / "break_repairs.json").read_text())
    assert (published["breaks"], published["outside_model"], published["holes"]) == (2842, 133, 2709)
    rows = {row["file"]: row for row in published["rows"]}
    files = sorted((folder / "breaks").glob("*-invariant_break-*.json"))
    assert [path.name for path in files] == sorted(rows)
    for path in files[::400]:
        cx = load_counterexample(path)
        for simulator in ("fast", "highway-env"):
            result = replay(cx, simulator)
            assert result.reproduced and len(result.decisions) == cx.step, (path.name, simulator)
        row = rows[path.name]
        assert {**repair_break(cx), "role": break_culprits(cx)["role"]} == {k: v for k, v in row.items() if k != "file"}


def test_retrained_agents_crashes_after_breaks_replay_with_a_partner_rolling_back() -> None:
    """The agents' campaign with make demo's agents retrained under today's rule (docs/results/falsify/
    grid_agents_retrained: 1 065 crashes, 1 059 unsafe spawns, 6 after breaks, 0 from safe states): each of the 6
    crash files after a break replays to the same crash at the same decision on both simulators, and its partner is
    a car rolling backwards at the last decision (outside the driver model, docs/safety.md §6f)."""
    files = sorted((CAMPAIGN / "grid_agents_retrained" / "counterexamples").glob("*-collision-*.json"))
    assert len(files) == 6
    for path in files:
        cx = load_counterexample(path)
        for simulator in ("fast", "highway-env"):
            result = replay(cx, simulator)
            assert result.reproduced and result.collision_kind == cx.collision_kind, (path.name, simulator)
            assert len(result.decisions) == cx.step and result.decisions[-1].collision
        partner = crash_partner(cx)
        assert partner["reversing"] and partner["speed"][0] < 0.0, path.name


def test_classify_crashes_finds_the_agents_crashes_after_breaks_outside_the_model(tmp_path: Path) -> None:
    """examples/classify_crashes.py on the trained agents' 4 crashes after breaks (and the breaks before
    them): every one is outside the model — a vehicle rolled back faster than the rule's bound lets it (a
    reversing car keeps its speed): cell 615's partner (−0.35 → −3.01 m/s in the break's decision); cell
    760's break has a safe action (SLOWER) once the leader 44 m ahead (−0.43 → −1.26 m/s) is put back
    inside the model."""
    import sys

    folder = CAMPAIGN / "grid_agents_level_entering" / "counterexamples"
    out = tmp_path / "classes.json"
    script = Path(__file__).resolve().parents[1] / "examples" / "classify_crashes.py"
    subprocess.run([sys.executable, str(script), str(folder), "--workers", "1", "--out", str(out)], check=True)
    summary = json.loads(out.read_text())
    assert summary["contexts"] == {"after_break": 4} and summary["outside_model"] == 4 and summary["holes"] == []
    reasons = {r["file"].split("-")[0]: r["outside_model"] for r in summary["rows"]}
    assert reasons["cell00760"] == ["break_repaired"]
    assert reasons["cell00615"] == ["partner_rolled_back"]


def test_repair_break_excuses_a_break_only_when_the_roll_back_was_needed() -> None:
    """repair_break: the in-model adversaries' cell 6 (highway-env: a stopped car 34 m ahead rolled back
    0.48 → −0.28 m/s while the ego braked; two cars beside the ego block the lane changes) has SLOWER safe
    again once that car is put back where it stopped — outside the model, although leave-one-out also
    names the two cars beside it. The 100 800-episode campaign's turning-leader hole (cell 2270, fast
    simulator: nobody rolled back) repairs nothing and stays a break. ``best_gap``, the break state's largest
    worst-case gap as it is: 0.944 m (just under the 1 m margin) and −9.049 m. Crash files are refused."""
    adversary = CAMPAIGN / "adversaries_session11" / "counterexamples"
    repaired = repair_break(load_counterexample(adversary / "cell00006-seed4000060000-invariant_break-step8.json"))
    assert repaired == {"best_gap": 0.944, "repaired": [6], "safe_after_repair": True, "unlocks": [4]}
    hole = CAMPAIGN / "grid_100k_behind_turning_leaders" / "counterexamples"
    kept = repair_break(load_counterexample(hole / "cell02270-seed4022700029-invariant_break-step2.json"))
    assert kept == {"best_gap": -9.049, "repaired": [], "safe_after_repair": False, "unlocks": []}
    with pytest.raises(ConfigError, match="invariant breaks only"):
        repair_break(load_counterexample(adversary / "cell00006-seed4000060000-collision-step9.json"))


def test_repair_breaks_counts_a_campaign_s_breaks_outside_the_model(tmp_path: Path) -> None:
    """examples/repair_breaks.py on the turning-leaders campaign's 10 breaks (the ones before its crashes):
    3 with a vehicle rolling back beyond the model, 2 that needed it (cells 1842 and 2710; cell 694's two
    rolled-back cars were not what broke it), the first culprits' roles counted."""
    import sys

    folder = CAMPAIGN / "grid_100k_behind_turning_leaders" / "counterexamples"
    out = tmp_path / "repairs.json"
    script = Path(__file__).resolve().parents[1] / "examples" / "repair_breaks.py"
    args = [sys.executable, str(script), str(folder), "--culprits", "--workers", "1", "--out", str(out)]
    subprocess.run(args, check=True, capture_output=True)
    summary = json.loads(out.read_text())
    assert (summary["breaks"], summary["with_roll_back"], summary["outside_model"]) == (10, 3, 2)
    outside = sorted(r["file"].split("-")[0] for r in summary["rows"] if r["safe_after_repair"])
    assert outside == ["cell01842", "cell02710"]
    assert sum(summary["roles"].values()) == 10 and summary["roles"]["leader"] == 5
    gaps = sorted(r["best_gap"] for r in summary["rows"])
    assert summary["best_gap_below_zero"] == sum(g < 0 for g in gaps) and max(gaps) < 1.0
    assert summary["best_gap_quantiles"][0] == gaps[0] and summary["best_gap_quantiles"][-1] == gaps[-1]


@pytest.mark.parametrize("simulator", ["fast", "highway-env"])
def test_carried_follower_bounds_close_hole_2879(simulator: str) -> None:
    """docs/safety.md §6s, §6t: the claim campaign's hole 2879 judged with the follower bounds of the decision before
    it carried over (a car behind bounded also by accelerating for the reaction time from where it was 0.2 s
    earlier, then braking) has IDLE safe at 1.362 m, where the rule as it ran has nothing (−0.638 m): the
    follower bound's restart is the whole of this break. Carrying only the 3 cars the ego was already in front of
    in their lane (their reaction had begun, as the model reads it) closes it as carrying all 25 cars behind
    does. The same on both simulators (one file)."""
    cx = load_counterexample(
        CAMPAIGN / "grid_100k_behind_forecast_fallback" / "counterexamples"
        / "cell02879-seed4028790006-invariant_break-step11.json"
    )  # fmt: skip
    reacting = break_with_carried_followers(cx, simulator)
    every = break_with_carried_followers(cx, simulator, reacting_only=False)
    assert reacting["carried"] == 3 and every["carried"] == 25
    for verdict in (reacting, every):
        assert verdict["best_gap"] == pytest.approx(-0.638, abs=1e-3)
        assert verdict["safe_carried"] and verdict["unlocks"] == [1]
        assert verdict["best_gap_carried"] == pytest.approx(1.362, abs=1e-3)


def test_breaks_under_options_script_carries_the_reacting_followers(tmp_path: Path) -> None:
    """examples/breaks_under_options.py --carried-followers on a folder holding hole 2879's break: 1 of 1 gets a
    safe action, labelled with the cars it carried (the reacting ones by default); --all-followers alone, or
    with --set, is a one-line error (exit 2) before any worker starts."""
    import shutil
    import sys

    name = "cell02879-seed4028790006-invariant_break-step11.json"
    folder = tmp_path / "breaks"
    folder.mkdir()
    shutil.copy(CAMPAIGN / "grid_100k_behind_forecast_fallback" / "counterexamples" / name, folder / name)
    script = [sys.executable, str(Path(__file__).resolve().parents[1] / "examples" / "breaks_under_options.py")]
    out = tmp_path / "verdicts.json"
    run = [*script, str(folder), "--carried-followers", "--workers", "1", "--out", str(out)]
    subprocess.run(run, check=True, capture_output=True)
    summary = json.loads(out.read_text())
    assert summary["options"] == "carried_followers_reacting" and summary["breaks"] == 1
    assert summary["safe_with_options"] == 1 and summary["rows"][0]["carried"] == 3
    for wrong in (["--all-followers"], ["--carried-followers", "--all-followers", "--set", "margin=2"]):
        bad = subprocess.run([*script, str(folder), *wrong, "--out", str(out)], capture_output=True, text=True)
        assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1, bad.stderr


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
        shutil.copy(CAMPAIGN / "grid_100k_behind_forecast_fallback" / "counterexamples" / name, folder / name)
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


def test_break_under_options_finds_the_follower_bound_in_hole_2879() -> None:
    """break_under_options (examples/breaks_under_options.py's engine) on the claim's-grid hole 2879 (a Linear
    follower squeeze, docs/safety.md §6k): as it ran nothing is safe (best −0.64 m); with the followers braking
    from now (follower_reaction 0 — a diagnostic, not a bound) IDLE and SLOWER are (2.36 m): the follower's
    bound, restarted at every decision, is what broke it. A rule option that does not touch it leaves the state
    as it was; a name that is not a Dynamics field is a one-line error."""
    cx = load_counterexample(
        CAMPAIGN / "grid_100k_behind_passing_cut_ins" / "counterexamples"
        / "cell02879-seed4028790006-invariant_break-step11.json"
    )  # fmt: skip
    verdict = break_under_options(cx, {"follower_reaction": 0.0})
    assert verdict["best_gap"] == pytest.approx(-0.638, abs=1e-3)
    assert verdict["safe_with_options"] and verdict["unlocks"] == [1, 4]
    assert verdict["best_gap_with_options"] == pytest.approx(2.362, abs=1e-3)
    same = break_under_options(cx, {"body_extent": True})
    assert not same["safe_with_options"] and same["best_gap_with_options"] == same["best_gap"]
    with pytest.raises(ConfigError, match="follower_reactions: not a rule option"):
        break_under_options(cx, {"follower_reactions": 0.0})
