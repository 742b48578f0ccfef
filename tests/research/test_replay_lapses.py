"""research/replay_lapses.py on the committed claim grid's pinned lapse files (tests/fixtures/claim-committed)."""

from __future__ import annotations

import json
from pathlib import Path

from research.replay_lapses import main

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "claim-committed"


def test_the_lapses_filed_in_the_model_are_none_now_and_a_traced_one_stays_traced(tmp_path: Path) -> None:
    out = tmp_path / "replayed.json"
    traced = FIXTURES / "cell00219-seed4002190002-lapse-step36.json"
    assert main([str(FIXTURES), str(traced), "--out", str(out)]) == 0
    record = json.loads(out.read_text())
    # two lapses gone (a kept plan keeps the lanes it held), three traced to the ego's crash, one to a cut-in
    assert record["summary"]["files"] == 6 and record["summary"]["outcomes"] == {"no lapse": 2, "lapse traced": 4}
    assert record["files"][traced.name]["lapse_cars"] == [49] and not record["summary"]["still_in_the_model"]
