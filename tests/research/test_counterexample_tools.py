"""The counterexample diagnostics of :mod:`research.counterexample_tools` and the scripts built on them: a crash's
partner, a break repaired, explained by leave-one-out, judged with other options or with carried follower bounds
(real simulators, real scripts)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from research.counterexample_tools import (
    break_culprits,
    break_under_options,
    break_with_carried_followers,
    crash_partner,
    culprit_role,
    repair_break,
)
from safelane.config import ConfigError
from safelane.running.counterexamples import load_counterexample, replay

ROOT = Path(__file__).resolve().parents[2]
FIXTURES = ROOT / "tests" / "fixtures"  # pinned campaign files: tests/fixtures/README.md
CRASHES = FIXTURES / "grid"
CELL_38 = "cell00038-seed4000380020-collision-step26.json"
CELL_169 = "cell00169-seed4001690001-collision-step34.json"


def test_crash_partner_tells_a_reversing_car_from_one_inside_the_model() -> None:
    """crash_partner: cell 38's crash (the campaign's reversing leader: the car 6 m ahead rolls back at
    2 m/s into the nearly stopped ego) has its partner in the ego's lane, ahead, moving backwards; the
    trained agents' cell 169 (a car two lanes over changing into the lane the ego enters) has a partner
    moving forwards. A break file has no crash partner."""
    reversing = crash_partner(load_counterexample(FIXTURES / "grid-100k" / CELL_38))
    assert reversing["reversing"] and reversing["lane_vs_ego"] == [0, 0]
    assert reversing["dx"][0] > 0 and min(reversing["speed"]) < 0
    side = crash_partner(load_counterexample(FIXTURES / "agents-level-cut-ins" / CELL_169))
    assert not side["reversing"] and side["lane_vs_ego"] == [2, 1] and min(side["speed"]) > 10
    breaks = sorted((FIXTURES / "grid").glob("*invariant_break*.json"))
    with pytest.raises(ConfigError, match="collisions only"):
        crash_partner(load_counterexample(breaks[0]))


def test_claim_campaign_break_files_keep_their_published_classification() -> None:
    """The claim campaign's break files under the rule forecast-fallback (2 842, classified by repair_breaks
    --culprits: 133 outside the model, 2 709 in it): every 400th of them, sorted by name, and the two holes'
    breaks (10 files, one outside the model, five first-culprit roles) replay to a break at the same decision on
    the fast simulator and on highway-env, and get the published verdict again — the repair, its best gap to the
    millimetre and its first culprit's role (their rows of the campaign's break_repairs.json)."""
    folder = FIXTURES / "claim"
    published = json.loads((folder / "break_repairs.json").read_text())
    rows = {row["file"]: row for row in published["rows"]}
    files = sorted((folder / "breaks").glob("*-invariant_break-*.json"))
    assert [path.name for path in files] == sorted(rows) and len(files) == 10
    for path in files:
        cx = load_counterexample(path)
        for simulator in ("fast", "highway-env"):
            result = replay(cx, simulator)
            assert result.reproduced and len(result.decisions) == cx.step, (path.name, simulator)
        row = rows[path.name]
        assert {**repair_break(cx), "role": break_culprits(cx)["role"]} == {k: v for k, v in row.items() if k != "file"}


def test_retrained_agents_crashes_after_breaks_replay_with_a_partner_rolling_back() -> None:
    """The claim campaign's agents (make demo's agents, trained under the rule forecast-fallback: 1 065 crashes,
    1 059 unsafe spawns, 6 after breaks, 0 from safe states): each of the 6
    crash files after a break replays to the same crash at the same decision on both simulators, and its partner is
    a car rolling backwards at the last decision (outside the driver model, docs/research/horizon-and-ego-speed.md)."""
    files = sorted((FIXTURES / "claim-agents" / "crashes").glob("*-collision-*.json"))
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
    """research/classify_crashes.py on the trained agents' 4 crashes after breaks (and the breaks before
    them): every one is outside the model — a vehicle rolled back faster than the rule's bound lets it (a
    reversing car keeps its speed): cell 615's partner (−0.35 → −3.01 m/s in the break's decision); cell
    760's break has a safe action (SLOWER) once the leader 44 m ahead (−0.43 → −1.26 m/s) is put back
    inside the model."""
    import sys

    folder = FIXTURES / "agents-level-entering"
    out = tmp_path / "classes.json"
    script = ROOT / "research" / "classify_crashes.py"
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
    adversary = FIXTURES / "adversaries-stopped-car"
    repaired = repair_break(load_counterexample(adversary / "cell00006-seed4000060000-invariant_break-step8.json"))
    assert repaired == {"best_gap": 0.944, "repaired": [6], "safe_after_repair": True, "unlocks": [4]}
    hole = FIXTURES / "turning-leaders"
    kept = repair_break(load_counterexample(hole / "cell02270-seed4022700029-invariant_break-step2.json"))
    assert kept == {"best_gap": -9.049, "repaired": [], "safe_after_repair": False, "unlocks": []}
    with pytest.raises(ConfigError, match="invariant breaks only"):
        repair_break(load_counterexample(adversary / "cell00006-seed4000060000-collision-step9.json"))


def test_repair_breaks_counts_a_campaign_s_breaks_outside_the_model(tmp_path: Path) -> None:
    """research/repair_breaks.py on the turning-leaders campaign's 10 breaks (the ones before its crashes):
    3 with a vehicle rolling back beyond the model, 2 that needed it (cells 1842 and 2710; cell 694's two
    rolled-back cars were not what broke it), the first culprits' roles counted."""
    import sys

    folder = FIXTURES / "turning-leaders"
    out = tmp_path / "repairs.json"
    script = ROOT / "research" / "repair_breaks.py"
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
    """docs/research/nested-follower-bound.md: the claim campaign's hole 2879 judged with the follower bounds of the
    decision before
    it carried over (a car behind bounded also by accelerating for the reaction time from where it was 0.2 s
    earlier, then braking) has IDLE safe at 1.362 m, where the rule as it ran has nothing (−0.638 m): the
    follower bound's restart is the whole of this break. Carrying only the 3 cars the ego was already in front of
    in their lane (their reaction had begun, as the model reads it) closes it as carrying all 25 cars behind
    does. The same on both simulators (one file)."""
    cx = load_counterexample(
        FIXTURES / "claim" / "breaks" / "cell02879-seed4028790006-invariant_break-step11.json"
    )  # fmt: skip
    reacting = break_with_carried_followers(cx, simulator)
    every = break_with_carried_followers(cx, simulator, reacting_only=False)
    assert reacting["carried"] == 3 and every["carried"] == 25
    for verdict in (reacting, every):
        assert verdict["best_gap"] == pytest.approx(-0.638, abs=1e-3)
        assert verdict["safe_carried"] and verdict["unlocks"] == [1]
        assert verdict["best_gap_carried"] == pytest.approx(1.362, abs=1e-3)


def test_breaks_under_options_script_carries_the_reacting_followers(tmp_path: Path) -> None:
    """research/breaks_under_options.py --carried-followers on a folder holding hole 2879's break: 1 of 1 gets a
    safe action, labelled with the cars it carried (the reacting ones by default); --all-followers alone, or
    with --set, is a one-line error (exit 2) before any worker starts."""
    import shutil
    import sys

    name = "cell02879-seed4028790006-invariant_break-step11.json"
    folder = tmp_path / "breaks"
    folder.mkdir()
    shutil.copy(FIXTURES / "claim" / "breaks" / name, folder / name)
    script = [sys.executable, str(ROOT / "research" / "breaks_under_options.py")]
    out = tmp_path / "verdicts.json"
    run = [*script, str(folder), "--carried-followers", "--workers", "1", "--out", str(out)]
    subprocess.run(run, check=True, capture_output=True)
    summary = json.loads(out.read_text())
    assert summary["options"] == "carried_followers_reacting" and summary["breaks"] == 1
    assert summary["safe_with_options"] == 1 and summary["rows"][0]["carried"] == 3
    for wrong in (["--all-followers"], ["--carried-followers", "--all-followers", "--set", "margin=2"]):
        bad = subprocess.run([*script, str(folder), *wrong, "--out", str(out)], capture_output=True, text=True)
        assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1, bad.stderr


def test_break_under_options_finds_the_follower_bound_in_hole_2879() -> None:
    """break_under_options (research/breaks_under_options.py's engine) on the claim's-grid hole 2879 (a Linear
    follower squeeze, docs/research/car-behind.md): as it ran nothing is safe (best −0.64 m); with the followers braking
    from now (follower_reaction 0 — a diagnostic, not a bound) IDLE and SLOWER are (2.36 m): the follower's
    bound, restarted at every decision, is what broke it. A rule option that does not touch it leaves the state
    as it was; a name that is not a Dynamics field is a one-line error."""
    cx = load_counterexample(
        FIXTURES / "passing-cut-ins" / "cell02879-seed4028790006-invariant_break-step11.json"
    )  # fmt: skip
    verdict = break_under_options(cx, {"follower_reaction": 0.0})
    assert verdict["best_gap"] == pytest.approx(-0.638, abs=1e-3)
    assert verdict["safe_with_options"] and verdict["unlocks"] == [1, 4]
    assert verdict["best_gap_with_options"] == pytest.approx(2.362, abs=1e-3)
    same = break_under_options(cx, {"reversing_leaders": False})
    assert not same["safe_with_options"] and same["best_gap_with_options"] == same["best_gap"]
    with pytest.raises(ConfigError, match="follower_reactions: not a rule option"):
        break_under_options(cx, {"follower_reactions": 0.0})


def test_break_culprits_name_the_vehicle_the_model_missed() -> None:
    """Leave-one-out on a recorded break: the Linear car drawing level in the next lane is the culprit
    (removing it alone makes SLOWER safe), not the leader 42 m ahead; a crash file is refused."""
    cx = load_counterexample(CRASHES / "cell00011-seed4000110013-invariant_break-step40.json")
    result = break_culprits(cx)
    assert result["fallback_confirmed"] and result["role"] == "adjacent_behind"
    first = result["culprits"][0]
    assert first["lane_vs_ego"] == [1, 1] and first["dx"][1] < 0 and 4 in first["unlocks"]
    with pytest.raises(ConfigError, match="invariant breaks only"):
        break_culprits(load_counterexample(CRASHES / "cell00018-seed4000180007-collision-step3.json"))


@pytest.mark.parametrize(
    ("dx", "lanes", "ego_changed", "role"),
    [
        ((5.0, -1.0), (0, 0), False, "overtook"),
        ((30.0, 28.0), (2, 1), False, "came_from_two_lanes"),
        ((-3.0, -0.1), (1, 1), False, "adjacent_behind"),
        ((40.0, 35.0), (0, 0), False, "leader"),
        ((-8.0, -6.0), (0, 0), False, "follower"),
        ((20.0, 18.0), (2, 2), False, "two_lanes_away"),
        ((10.0, 9.0), (0, -1), False, "moved_away"),
        ((10.0, 9.0), (1, 0), True, "ego_changed_lane"),
    ],
)
def test_culprit_roles(dx: tuple, lanes: tuple, ego_changed: bool, role: str) -> None:
    assert culprit_role(dx, lanes, ego_changed) == role
