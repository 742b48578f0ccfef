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
    with the others at constant speed (model.incentive_times) 5 of the 45 came a physics frame earlier."""
    import json

    script = ROOT / "research" / "turn_in_timing.py"
    out = subprocess.run([sys.executable, str(script), "--cases", "600", "--seed", "1"], check=True,
                         capture_output=True, text=True).stdout  # fmt: skip
    summary = json.loads(out)
    assert summary["turn_ins_within_the_decision"] == 45
    assert summary["before_any_speed_time"] == 0 and summary["any_speed_never"] == 0
    assert summary["before_incentive_time"] == 5
