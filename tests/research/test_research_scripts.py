"""Research scripts that drive the simulators: perfect foresight on a campaign's unsafe spawns, and the decision
times of highway-env's turn-ins behind the ego against the rule's incentive bound (real simulators, real scripts)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_spawn_foresight_drives_unsafe_spawns_with_perfect_foresight(tmp_path: Path) -> None:
    """research/spawn_foresight.py on two crashes from unsafe spawns of the claim's grid (tests/fixtures/spawns):
    the unmasked planner drives the Defensive drivers' spawn of cell 1100 through without a crash and crashes in
    the IDM spawn of cell 1550 (3 decisions per second) — the first a crash a better fallback could have
    avoided, the second one no policy this search finds could."""
    import subprocess
    import sys

    root = ROOT
    campaign = root / "tests" / "fixtures" / "spawns"  # two rows of a campaign's crash_classes.json and their files
    out = tmp_path / "spawns.json"
    script = root / "research" / "spawn_foresight.py"
    args = [sys.executable, str(script), str(campaign), "--sample", "2", "--workers", "1", "--out", str(out)]
    subprocess.run(args, check=True, capture_output=True)
    summary = json.loads(out.read_text())
    assert summary["started_unsafe_crashes"] == 2 and summary["replayed"] == 2
    rows = {r["file"].split("-")[0]: r for r in summary["rows"]}
    assert set(rows) == {"cell01100", "cell01550"}
    assert not rows["cell01100"]["foresight_collision"] and rows["cell01100"]["drivers"] == "DefensiveVehicle"
    assert rows["cell01550"]["foresight_collision"] and rows["cell01550"]["rate"] == 3
    assert (summary["foresight_crashed"], summary["foresight_survived"]) == (1, 1)


def test_turn_ins_behind_the_ego_decide_no_earlier_than_the_incentive_bound() -> None:
    """research/turn_in_timing.py drives IDM and Linear drivers in the next lane that the ego overtakes, a slow
    leader ahead of them, on highway-env at 1–5 decisions per second. Every turn-in behind the ego decided within
    the decision comes no earlier than model.incentive_times_any_speed (shield.incentive_any_speed, the bound);
    with the others at constant speed alone 5 of the 45 came a physics frame earlier, and none with each car also
    at its acceleration now (model.incentive_times with shield.incentive_accelerations, a timing)."""
    import json

    script = ROOT / "research" / "turn_in_timing.py"
    out = subprocess.run([sys.executable, str(script), "--cases", "600", "--seed", "1"], check=True,
                         capture_output=True, text=True).stdout  # fmt: skip
    summary = json.loads(out)
    assert summary["turn_ins_within_the_decision"] == 45
    assert summary["before_any_speed_time"] == 0 and summary["any_speed_never"] == 0
    assert summary["before_constant_speed_time"] == 5 and summary["before_incentive_time"] == 0


def test_the_rear_end_trace_sorts_what_the_ego_did_before_each_crash(tmp_path: Path) -> None:
    """research/trace_rear_ends.py on three crashes of the committed shield (tests/fixtures/claim-sample): the
    override to SLOWER with IDLE or FASTER verified and the policy's own SLOWER are others at fault, traced; the
    crash from an uncertified spawn is counted and not traced."""
    out = tmp_path / "trace.json"
    script = ROOT / "research" / "trace_rear_ends.py"
    folder = ROOT / "tests" / "fixtures" / "claim-sample"
    subprocess.run([sys.executable, str(script), str(folder), "--out", str(out), "--workers", "1"], check=True,
                   capture_output=True)  # fmt: skip
    rows = {r["file"].split("-")[0]: r for r in json.loads(out.read_text())["rows"]}
    assert rows["cell00011"]["context"] == "uncertified_start" and "trace" not in rows["cell00011"]
    override, own = rows["cell00082"], rows["cell00134"]
    assert override["context"] == own["context"] == "others_at_fault"
    assert override["trace"] == "override_to_slower" and override["brake_not_required"]
    assert not override["courteous_alternative"] and override["hardest_decel"] > 6.0
    assert own["trace"] == "policy_slower" and not own["brake_not_required"]
    assert "| override_to_slower | 1 |" in out.with_suffix(".md").read_text()


def test_certified_starts_sets_the_two_rules_side_by_side_on_the_grid_s_spawns() -> None:
    """research/certified_starts.py on one dense condition of the claim grid (5 lanes, density 2, IDM drivers, 12
    behind, 5 decisions/s), its first two spawns: the first safe by the one-decision rule and certified, the second
    neither; the summary counts them and names no blocking car (none safe and uncertified)."""
    from research.certified_starts import condition_spawns, position_class, summary

    condition = condition_spawns(str(ROOT / "configs" / "falsify" / "claim-committed.yaml"), 2703, 2)
    assert condition["spawns"] == [{"robust_safe": True, "certified": True}, {"robust_safe": False, "certified": False}]
    text = summary([condition])
    assert "one-decision rule safe 1 (50.0 %), committed rule certified 1 (50.0 %)" in text
    assert "safe by the one-decision rule but uncertified: 0" in text
    assert position_class(-1, -12.0) == "next_behind" and position_class(0, 4.0) == "same_beside"


def test_type_break_causes_names_what_decides_a_break_under_hidden_types() -> None:
    """research/type_break_causes.py on three breaks of the omniscient shield on the claim grid with hidden types
    (tests/fixtures/hidden-types-breaks): the least-bad action is decided by an aggressive follower (IDM's desired
    distance 5 m centre to centre, a jam distance of 0) whose own IDM path ends inside the ego stopped by the fallback,
    by a leader, and by nothing below 0 m (only the 1 m margin eaten). With the follower's own set-point instead of
    the bound v0 = ∞ all three stay breaks."""
    script = ROOT / "research" / "type_break_causes.py"
    folder = ROOT / "tests" / "fixtures" / "hidden-types-breaks"
    runs = {}
    for extra in ([], ["--own-set-point"]):
        out = subprocess.run([sys.executable, str(script), str(folder), "--files", "3", *extra], check=True,
                             capture_output=True, text=True).stdout  # fmt: skip
        runs[bool(extra)] = json.loads(out)["counts"]
    assert runs[False] == {"follower into the stopped ego, d0=5 m": 1, "leader": 1, "only the margin eaten": 1}
    assert runs[True] == {"still a break": 3}


def test_mobil_terms_names_what_turned_a_car_in_at_the_ego() -> None:
    """research/mobil_terms.py on the two turn-ins the rule's incentive missed (tests/fixtures/hidden-types-turn-ins):
    the timid car turned in for its old follower's sake (politeness 1: its own gain below its 0.2 m/s² threshold,
    the jerk above it), the aggressive one for its own gain, small and positive, behind the ego."""
    script = ROOT / "research" / "mobil_terms.py"
    folder = ROOT / "tests" / "fixtures" / "hidden-types-turn-ins"
    found = {}
    for name in ("polite-timid", "knife-edge-aggressive"):
        out = subprocess.run([sys.executable, str(script), str(folder / f"{name}-turn-in-collision.json")],
                             check=True, capture_output=True, text=True).stdout  # fmt: skip
        found[name] = json.loads(out)
    timid, aggressive = found["polite-timid"], found["knife-edge-aggressive"]
    assert timid["driven_by"] == "politeness" and aggressive["driven_by"] == "own gain"
    turn = timid["turn_in"]
    assert turn["type"] == "TimidDriver" and turn["politeness"] == 1.0 and turn["new_leader_is_ego"]
    assert turn["own_gain"] < turn["threshold"] <= turn["jerk"] and turn["old_follower_change"] > 0.0
    turn = aggressive["turn_in"]
    assert turn["type"] == "AggressiveDriver" and turn["politeness"] == 0.0 and turn["new_leader_is_ego"]
    assert 0.0 < turn["own_gain"] < 0.2 and turn["offset"] < 0.0
