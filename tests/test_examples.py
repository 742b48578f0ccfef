"""The user examples run as a user runs them (``python examples/NAME.py --quick``) and say what they did."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = REPO_ROOT / "examples"
USER_EXAMPLES = (
    "shield_sb3_agent", "train_robust_agent", "campaign_and_replay", "check_fast_simulator", "continuous_shield",
    "hidden_types",
)


def run_example(name: str, *args: str, cwd: Path) -> str:
    """Run ``examples/NAME.py ARGS`` in a fresh interpreter (this checkout's src first); its stdout."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO_ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run(
        [sys.executable, str(EXAMPLES / f"{name}.py"), *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=cwd,
        timeout=600,
    )
    assert out.returncode == 0, f"{name} failed:\n{out.stdout[-2000:]}\n{out.stderr[-3000:]}"
    return out.stdout


@pytest.mark.parametrize("name", USER_EXAMPLES)
def test_example_has_a_docstring_saying_what_how_and_how_long(name: str) -> None:
    doc = ast.get_docstring(ast.parse((EXAMPLES / f"{name}.py").read_text()))
    assert doc is not None
    assert "What it shows:" in doc and "Run:" in doc and "Time:" in doc
    assert f"python examples/{name}.py --quick" in doc


@pytest.mark.parametrize("algo", ["dqn", pytest.param("maskable-ppo", marks=pytest.mark.slow)])
def test_shield_sb3_agent(algo: str, tmp_path: Path) -> None:
    out = run_example("shield_sb3_agent", "--quick", "--algo", algo, cwd=tmp_path)
    rows = {line.split()[0]: line.split()[1:] for line in out.splitlines() if line.startswith(("bare", "shielded"))}
    assert set(rows) == {"bare", "shielded"}
    episodes, collisions, decisions, interventions = (int(v) for v in rows["bare"][:4])
    assert (episodes, interventions) == (1, 0)  # nothing steps in without a shield
    assert 1 <= decisions <= 10 and collisions in (0, 1)
    episodes, collisions, decisions, interventions = (int(v) for v in rows["shielded"][:4])
    assert episodes == 1 and 0 <= interventions <= decisions <= 10


def test_continuous_shield(tmp_path: Path) -> None:
    out = run_example("continuous_shield", "--quick", cwd=tmp_path)
    rows = {line.split()[0]: [int(v) for v in line.split()[1:5]] for line in out.splitlines()
            if line.startswith(("bare", "shielded"))}  # fmt: skip
    assert set(rows) == {"bare", "shielded"}
    assert rows["shielded"][:3] == [1, 0, 0]  # no collision and on the road under the shield
    assert 1 <= rows["shielded"][3] <= 5


def test_hidden_types(tmp_path: Path) -> None:
    out = run_example("hidden_types", "--quick", cwd=tmp_path)
    rows = {line.split()[0]: line.split()[1:] for line in out.splitlines()
            if line.startswith(("robust ", "belief ", "omniscient ")) and len(line.split()) == 5}  # fmt: skip
    assert list(rows) == ["robust", "belief", "omniscient"]
    for collisions, ruled_out, fallback, speed in rows.values():
        assert 0 <= int(ruled_out) <= int(collisions) <= 1 and fallback.endswith("%") and 0 < float(speed) <= 40
    accuracy = re.search(r"(\d+) cars, the most probable type is the true one for (\d+) %", out)
    assert accuracy is not None and int(accuracy.group(1)) > 0 and 0 <= int(accuracy.group(2)) <= 100


def test_train_robust_agent(tmp_path: Path) -> None:
    out = run_example("train_robust_agent", "--quick", "--out", str(tmp_path / "run"), cwd=tmp_path)
    assert "episode    3/3" in out
    assert {"config.yaml", "metrics.csv", "checkpoint.pt"} <= {p.name for p in (tmp_path / "run").iterdir()}
    rows = [line.split() for line in out.splitlines() if line.startswith(("fast ", "highway-env "))]
    assert [r[0] for r in rows] == ["fast", "highway-env"]
    assert rows[0][1:] == rows[1][1:]  # the two simulators play the same test episodes


def test_campaign_and_replay(tmp_path: Path) -> None:
    out = run_example("campaign_and_replay", "--quick", "--out", str(tmp_path / "tiny"), cwd=tmp_path)
    found = re.search(r"campaign tiny: (\d+) episodes, \d+ decisions, (\d+) collisions, (\d+) invariant breaks", out)
    assert found is not None, out
    assert int(found[1]) == 8 * 5
    assert (tmp_path / "tiny" / "summary.md").is_file()
    replays = re.findall(r"replayed on (fast|highway-env)\s*: (reproduced|NOT reproduced)", out)
    assert replays, "the tiny campaign found no counterexample to replay"
    assert all(outcome == "reproduced" for _, outcome in replays)
    assert len(replays) == 2 * len(re.findall(r"\.json: (?:collision|invariant_break) after decision", out))


def test_check_fast_simulator(tmp_path: Path) -> None:
    out = run_example("check_fast_simulator", "--quick", cwd=tmp_path)
    assert "trajectories agreed in 100% of 3 episodes (bit-identical: 100%" in out
    assert "diverged" not in out


def test_examples_reject_bad_counts(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO_ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run(
        [sys.executable, str(EXAMPLES / "campaign_and_replay.py"), "--episodes", "0"],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=120,
    )
    assert out.returncode == 2
    assert "--episodes: must be >= 1" in out.stderr.strip().splitlines()[-1]
