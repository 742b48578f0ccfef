"""research/campaign_manifest.py: one digest pins a campaign's files; a changed, added or missing file changes it."""

from __future__ import annotations

import json
from pathlib import Path

from research.campaign_manifest import main, manifest


def _campaign(folder: Path) -> Path:
    (folder / "counterexamples").mkdir(parents=True)
    (folder / "cells.csv").write_text("index,collisions\n0,1\n")
    for name in ("cell00000-seed1-collision-step3.json", "cell00000-seed1-lapse-step2.json",
                 "cell00001-seed2-lapse_in_model-step5.json"):  # fmt: skip
        (folder / "counterexamples" / name).write_text(json.dumps({"name": name}))
    return folder


def test_the_digest_pins_every_file_and_counts_the_kinds(tmp_path: Path) -> None:
    folder = _campaign(tmp_path / "run")
    found = manifest(folder)
    assert found["files_count"] == 4
    assert found["files_by_kind"] == {"cells.csv": 1, "collision": 1, "lapse": 1, "lapse_in_model": 1}
    pinned = tmp_path / "manifest.json"
    assert main([str(folder), "--out", str(pinned), "--command", "safelane falsify x.yaml"]) == 0
    assert main([str(folder), "--check", str(pinned)]) == 0
    (folder / "counterexamples" / "cell00000-seed1-lapse-step2.json").write_text("{}")
    assert main([str(folder), "--check", str(pinned)]) == 1
    assert manifest(folder)["listing_sha256"] != found["listing_sha256"]
    assert main([str(tmp_path / "nothing")]) == 2
