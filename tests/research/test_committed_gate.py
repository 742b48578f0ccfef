"""The committed shield's gate script (:mod:`research.committed_gate`): its figures from the episodes it records, and
a short campaign played end to end (fast simulator)."""

from __future__ import annotations

import json
from pathlib import Path

from research.committed_gate import main, summarize


def _episode(decisions: int, forced: int, speed: float, lapses: list[dict], collision: dict | None) -> dict:
    return {"decisions": decisions, "plan_forced": forced, "fallback": forced, "mean_speed": speed,
            "lapses": lapses, "collision": collision, "uncertified_start": collision is None, "checked": 10 * decisions,
            "escapes": len(lapses), "rolled_back": 0, "unbraked_followers": len(lapses),
            "crashed_escapes": 0}  # fmt: skip


def test_the_gate_figures_count_what_the_episodes_recorded() -> None:
    """Rates per decision, lapses in the model apart from those traced, collisions by context, always-FASTER's
    speed from its cells only."""
    crash = {"context": "from_certified", "others_at_fault": True, "partner_left_its_set": False}
    traced = {"cars": [3], "escaped": [3], "entered": [], "escaped_anywhere": [3, 8], "entered_anywhere": [5],
              "in_model": False}  # fmt: skip
    untraced = {"cars": [4], "escaped": [], "entered": [], "escaped_anywhere": [], "entered_anywhere": [],
                "in_model": True}  # fmt: skip
    played = [
        {"policy": "faster", "episodes": [_episode(40, 2, 20.0, [traced], None)]},
        {"policy": "random", "episodes": [_episode(10, 0, 5.0, [untraced], crash)]},
    ]
    s = summarize(played)
    assert s["decisions"] == 50 and s["plan_forced_rate"] == 2 / 50
    assert s["lapses"] == 2 and s["lapses_in_model"] == 1 and s["lapses_traced_to_escapes"] == 1
    assert s["lapse_cars"] == 2 and s["lapse_cars_escaped_or_entered_anywhere"] == 3
    assert s["collisions"] == 1 and s["collision_contexts"]["from_certified"] == 1
    assert s["from_certified_others_at_fault"] == 1 and s["faster_mean_speed"] == 20.0
    assert s["uncertified_starts"] == 1
    assert s["car_decisions"] == 500 and s["escaped_car_decisions"] == 2 and s["escaped_rolling_back"] == 0
    assert s["escaped_unbraked_followers"] == 2 and s["escaped_crashed"] == 0


def test_a_short_campaign_is_played_under_the_committed_shield(tmp_path: Path) -> None:
    """One cell, one short episode: the file holds the summary and the episode, its decisions counted."""
    spec = tmp_path / "spec.yaml"
    spec.write_text(
        "name: tiny\npreset: fast\nsimulator: fast\nshield: committed\n"
        "sets: ['shield.engine=numpy', 'env.duration=8']\npolicies: [faster]\nepisodes: 1\n"
        "axes:\n  lanes:\n    - {env.lanes_count: 3, env.vehicles_count: 10}\n"
    )
    out = tmp_path / "subset.json"
    assert main([str(spec), "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["summary"]["episodes"] == 1
    episode = data["cells"][0]["episodes"][0]
    assert data["summary"]["decisions"] == episode["decisions"] > 0
    assert isinstance(episode["uncertified_start"], bool)
    assert 0 < episode["checked"] == data["summary"]["car_decisions"]
