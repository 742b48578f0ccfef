"""Continuous actions in the episode commands: counterexample files that record acceleration and steering exactly
and replay on both simulators, the shield for continuous actions' figures (projections, lapses, collisions against
its promise), falsify, stress, replay and bench with ``--actions`` (real simulators, real shield; tiny episodes: the
shield's numpy reference takes a fraction of a second a decision)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from safelane.cli import app
from safelane.config import ConfigError, config_to_dict, load_config
from safelane.running import evaluation
from safelane.running.collisions import collision_contexts
from safelane.running.counterexamples import (
    Counterexample,
    counterexample_json,
    load_counterexample,
    replay,
)
from safelane.running.evaluation import EpisodeTally, evaluate_fixed

ROOT = Path(__file__).resolve().parents[1]
FALSIFY = ROOT / "configs" / "falsify"
DENSE = {"simulator": "fast", "actions": "continuous", "env": {"vehicles_density": 2.0, "lanes_count": 3}}
SHIELDED = {**DENSE, "shield": {"mode": "committed", "engine": "numpy"}}
runner = CliRunner()


def config(overrides: dict[str, Any], duration: int) -> Any:
    return load_config("fast", overrides={**overrides, "env": {**overrides["env"], "duration": duration}})


def same_log(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Two replays' logs are equal but for the simulator's name."""
    return {**a, "simulator": ""} == {**b, "simulator": ""}


# --- counterexample files ---------------------------------------------------------------------------------------


def test_a_continuous_crash_is_saved_exactly_and_replays_identically_on_both_simulators(tmp_path: Path) -> None:
    """The lane-changing probe without a shield on a dense road: episode seed 3 crashes at its 6th decision, after
    steering by float32 values that no short decimal writes. The file holds those values bit for bit, and the
    replay on the fast simulator and on highway-env logs the same decisions and the same crash."""
    summary = evaluate_fixed(config(DENSE, 6), "weave", 4, 0, counterexamples=tmp_path)
    assert summary["collisions"] >= 1 and len(summary["counterexample_files"]) == summary["collisions"]
    cx = load_counterexample(tmp_path / "seed3-collision-step6.json")
    assert cx.kind == "collision" and cx.executed is None  # no shield: the chosen actions are the executed ones
    steering = np.asarray(cx.actions, dtype=np.float32)[:, 1]
    assert np.any(steering != 0) and np.all(steering.astype(np.float64) == np.asarray(cx.actions)[:, 1])
    logs = []
    for simulator in ("fast", "highway-env"):
        result = replay(cx, simulator)
        assert result.reproduced and result.collision_kind == cx.collision_kind
        assert [d.chosen for d in result.decisions] == [list(a) for a in cx.actions]
        logs.append(result.to_dict())
    assert same_log(*logs)
    for simulator in ("fast", "highway-env"):  # and from the command line
        args = ["replay", str(tmp_path / "seed3-collision-step6.json"), "--simulator", simulator, "--json"]
        result = runner.invoke(app, args)
        assert result.exit_code == 0, result.output
        assert same_log(json.loads(result.stdout), logs[0])


def test_float32_actions_survive_the_file_bit_for_bit() -> None:
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(2_000, 2)).astype(np.float32)
    below_one = np.nextafter(np.float32(1), np.float32(0))
    actions[:4] = np.array([[-0.0, 1e-45], [0.1, 1 / 3], [below_one, -1], [7e-8, 3e-39]], dtype=np.float32)
    data = config_to_dict(load_config("fast", overrides={"actions": "continuous"}))
    pairs = [(float(a), float(s)) for a, s in actions]
    cx = Counterexample(kind="collision", config=data, seed=0, actions=pairs, step=len(pairs), executed=pairs)
    back = Counterexample.model_validate_json(counterexample_json(cx))
    for loaded in (back.actions, back.executed):
        assert np.array_equal(np.asarray(loaded, dtype=np.float32).view(np.uint32), actions.view(np.uint32))


def test_meta_action_files_read_and_write_as_they_always_did() -> None:
    """Every meta-action counterexample file among the fixtures (crashes, breaks, lapses) writes back byte for byte:
    the published manifests' checksums stay valid."""
    files = [p for p in (ROOT / "tests" / "fixtures").rglob("*.json") if '"safelane-counterexample/1"' in p.read_text()]
    assert len(files) >= 20
    for path in files:
        assert counterexample_json(Counterexample.model_validate_json(path.read_text())) == path.read_text(), path


def test_actions_that_do_not_fit_the_config_are_a_one_line_error(tmp_path: Path) -> None:
    continuous = config_to_dict(load_config("fast", overrides={"actions": "continuous"}))
    discrete = config_to_dict(load_config("fast"))
    for data, actions in ((continuous, [3, 3]), (discrete, [[1.0, 0.0]])):
        path = tmp_path / "bad.json"
        path.write_text(json.dumps({"kind": "collision", "config": data, "seed": 0, "actions": actions, "step": 1}))
        with pytest.raises(ConfigError, match=r"^\S+: not a counterexample \(actions: the config's actions are"):
            load_counterexample(path)


def test_a_shielded_continuous_lapse_replays_with_the_shield_s_actions_bit_for_bit(tmp_path: Path) -> None:
    """Full throttle under the shield for continuous actions on a dense road: episode seed 0's plan lapses when the
    shield judges its 2nd decision (traced to a car that cut in: not in the model). The file records the chosen and
    the executed actions; both simulators replay the lapse with the same executed actions, and a file whose executed
    actions were altered is not reproduced."""
    summary = evaluate_fixed(config(SHIELDED, 3), "faster", 1, 0, counterexamples=tmp_path)
    assert summary["lapses"] == 1 and summary["lapses_in_model"] == 0
    assert summary["projection_rate"] > 0 and summary["mean_projection_distance"] > 0
    path = tmp_path / "seed0-lapse-step2.json"
    cx = load_counterexample(path)
    assert cx.executed is not None and len(cx.executed) == len(cx.actions) == 2 and cx.executed != cx.actions
    for simulator in ("fast", "highway-env"):
        result = replay(cx, simulator)
        assert result.reproduced and result.decisions[-1].committed["lapse"]
        assert result.decisions[-1].committed["projected"]
    tampered = cx.model_copy(update={"executed": [cx.executed[0], (0.0, 0.0)]})
    assert not replay(tampered).reproduced
    result = runner.invoke(app, ["replay", str(path), "--actions", "discrete"])
    assert result.exit_code == 2 and "--actions:" in result.stderr and "allowed for it: continuous" in result.stderr
    result = runner.invoke(app, ["replay", str(path), "--gif", str(tmp_path / "x.gif")])
    assert result.exit_code == 2 and "--gif:" in result.stderr
    result = runner.invoke(app, ["replay", str(path)])
    assert result.exit_code == 0, result.output
    assert "reproduced: lapse at decision 2 on fast, the shield's actions bit for bit" in result.stdout


# --- the tally under the shield for continuous actions -----------------------------------------------------------


def judged(**info: Any) -> dict[str, Any]:
    """A step's ``info`` from the shield for continuous actions: its verdict on the state the action was taken in."""
    base = {"speed": 20.0, "off_road": False, "executed_action": np.zeros(2, dtype=np.float32), "projected": False,
            "projection_distance": 0.0, "shield_intervened": False, "unsafe_action": False, "plan_forced": False,
            "certified": True, "lapse": False, "lapse_in_model": False, "lapse_cars": (), "escaped_cars": (),
            "rolled_back": (), "unbraked_followers": (), "entered_cars": ()}  # fmt: skip
    return {**base, **info}


def context(monkeypatch: pytest.MonkeyPatch, steps: list[dict[str, Any]], certified: bool = True,
            kind: str = "ego_hit_front") -> tuple[str | None, list[int]]:  # fmt: skip
    """The context the tally gives a crash at the last of ``steps`` (partner 7)."""
    monkeypatch.setattr(evaluation, "collision_partner", lambda snap: 7)
    monkeypatch.setattr(evaluation, "classify_collision", lambda snap: kind)
    monkeypatch.setattr(evaluation, "vehicles_ahead", lambda snap: 0)
    snap = type("Snap", (), {"time": 1.0})()
    reset = {"off_road": False, "certified": certified, "uncertified_start": not certified, "projected": False,
             "projection_distance": 0.0, "redraws": 0, "snapshot": snap}  # fmt: skip
    tally = EpisodeTally(0, reset, committed=True)
    for i, info in enumerate(steps):
        tally.add(np.zeros(2, dtype=np.float32), 0.0, {**info, "snapshot": snap, "collision": i == len(steps) - 1})
    return tally.context, tally.outside_model_cars


def test_the_committed_contexts_read_the_verdict_on_the_state_each_action_was_taken_in(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    assert context(monkeypatch, [judged(), judged()]) == ("from_safe_state", [])
    # Nothing verified before the crash: no state was certified.
    assert context(monkeypatch, [judged(certified=False)], certified=False)[0] == "uncertified_start"
    # A crash from a plan-forced decision (nothing verified there, the kept plan drove): not from a certified state.
    assert context(monkeypatch, [judged(), judged(plan_forced=True)])[0] == "after_fallback"
    # The crash's own decision found a lapse before its action ran: the crash came after it.
    assert context(monkeypatch, [judged(), judged(lapse=True, lapse_cars=(4,))])[0] == "after_break"
    # The partner's escape reported by the crash's own decision is the state before the crash: a cause.
    assert context(monkeypatch, [judged(), judged(escaped_cars=(7,))]) == ("outside_model", [7])
    # The state the crash ends in (never judged by the shield: run_episode adds its trace) counts the partner rolling
    # back, not its other escapes.
    crash = {"rolled_back": (7,), "unbraked_followers": (), "entered_cars": ()}
    assert context(monkeypatch, [judged(), judged(crash_state=crash)]) == ("outside_model", [7])
    assert context(monkeypatch, [judged(), judged()], kind="rear_ended")[0] == "others_at_fault"


def test_a_shielded_continuous_summary_reports_projections_and_no_courtesy() -> None:
    summary = evaluate_fixed(config(SHIELDED, 2), "random", 1, 0)
    assert tuple(summary["collision_contexts"]) == collision_contexts(True)
    assert {"projection_rate", "mean_projection_distance", "off_road_rate", "lapses", "lapses_in_model",
            "plan_forced_rate", "uncertified_starts"} <= set(summary)  # fmt: skip
    assert "courtesy_waived_rate" not in summary and "actions" not in summary
    unshielded = evaluate_fixed(config(DENSE, 2), "random", 1, 0)
    assert "projection_rate" not in unshielded and "lapses" not in unshielded


# --- falsify -----------------------------------------------------------------------------------------------------


def test_the_continuous_claim_grid_is_the_committed_claim_s_with_the_continuous_policies() -> None:
    from safelane.running.falsify.grid import load_campaign_spec

    spec = load_campaign_spec(FALSIFY / "claim-continuous.yaml")
    committed = load_campaign_spec(FALSIFY / "claim-committed.yaml")
    assert spec.axes == committed.axes and spec.shield == "committed" and spec.actions == "continuous"
    assert set(spec.policies) == {"random", "faster", "weave"} and spec.simulator == "fast"
    assert len(spec.cells()) * spec.episodes >= 100_000
    assert '"actions"' not in committed.record_json() and '"actions": "continuous"' in spec.record_json()


def write_spec(path: Path, **fields: Any) -> Path:
    data = {"name": "tiny-continuous", "shield": "committed", "actions": "continuous", "policies": ["faster"],
            "episodes": 1, "sets": ["shield.engine=numpy", "env.duration=2", "env.vehicles_density=2.0"],
            "axes": {"lanes": [{"env.lanes_count": 3}]}}  # fmt: skip
    path.write_text(yaml.safe_dump({**data, **fields}))
    return path


def test_a_continuous_campaign_reports_what_its_shield_reports(tmp_path: Path) -> None:
    args = ["falsify", str(write_spec(tmp_path / "c.yaml")), "--out", str(tmp_path / "out"), "--workers", "1", "--json"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert tuple(summary["collision_contexts"]) == collision_contexts(True) and summary["actions"] == "continuous"
    for key in ("lapses", "lapses_in_model", "plan_forced_rate", "projection_rate", "mean_projection_distance",
                "off_road_rate", "mean_speed", "uncertified_starts"):  # fmt: skip
        assert key in summary
    assert not {"invariant_breaks", "fallback_rate", "break_classes", "courtesy_waived_rate"} & set(summary)
    cell = json.loads((tmp_path / "out" / "cells" / "cell00000.json").read_text())
    assert summary["projection_rate"] == pytest.approx(cell["projection_rate"])
    header = (tmp_path / "out" / "cells.csv").read_text().splitlines()[0].split(",")
    assert {"projection_rate", "off_road_rate", "lapses_in_model"} <= set(header) and "invariant_breaks" not in header
    text = (tmp_path / "out" / "summary.md").read_text()
    assert "from certified states" in text and "lapses" in text and "projected" in text


@pytest.mark.parametrize(
    ("fields", "args", "message"),
    [
        ({"policies": ["probe"]}, [], "policies: unknown continuous policy 'probe'; allowed: random, faster, weave"),
        ({"shield": "robust"}, [], "shield: 'robust' decides among meta-actions; allowed with actions continuous"),
        ({}, ["--actions", "bogus"], "--actions: got 'bogus'; allowed: discrete, continuous"),
        (
            {"actions": "discrete", "policies": ["weave"]},
            ["--actions", "continuous", "--shield", "robust"],
            "shield: 'robust' decides among meta-actions",
        ),
    ],
)
def test_bad_continuous_campaigns_are_one_line_errors(tmp_path: Path, fields: dict, args: list, message: str) -> None:
    result = runner.invoke(app, ["falsify", str(write_spec(tmp_path / "c.yaml", **fields)), *args,
                                 "--out", str(tmp_path / "out")])  # fmt: skip
    assert result.exit_code == 2
    assert message in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_a_continuous_search_chases_lapses() -> None:
    from safelane.running.falsify.search import objective

    record = {"invariant_breaks": 0, "lapses": 3, "decisions": 1_500}
    assert objective(record, continuous=True) == 2.0 and objective(record) == 0.0


# --- stress and bench ----------------------------------------------------------------------------------------------


def test_stress_with_continuous_actions() -> None:
    args = ["stress", "--actions", "continuous", "--policy", "faster", "--only", "training", "--episodes", "1",
            "--set", "simulator=fast", "--set", "shield.engine=numpy", "--set", "env.duration=2"]  # fmt: skip
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    (record,) = json.loads(result.stdout)["conditions"]
    assert json.loads(result.stdout)["shield"] == "committed" and record["actions"] == "continuous"
    assert {"projection_rate", "mean_projection_distance", "off_road_rate", "lapses"} <= set(record)
    table = runner.invoke(app, args)
    assert table.exit_code == 0 and "faster, continuous actions, shield committed" in table.stdout
    result = runner.invoke(app, ["stress", "--actions", "continuous", "--policy", "probe"])
    assert result.exit_code == 2
    assert "--policy: give one of the continuous policies random, faster, weave" in result.stderr
    result = runner.invoke(app, ["stress", "--actions", "sideways", "--policy", "faster"])
    assert result.exit_code == 2 and "--actions: got 'sideways'; allowed: discrete, continuous" in result.stderr


def test_bench_times_the_continuous_step_beside_the_discrete_one() -> None:
    from safelane.running.bench import continuous_step_figures

    figures = continuous_step_figures(1, 0)
    for simulator in ("highway-env", "fast"):
        continuous = figures["continuous_decisions_per_s"][simulator]
        discrete = figures["discrete_decisions_per_s"][simulator]
        assert continuous > 0 and discrete > 0
        assert figures["continuous_step_ratio"][simulator] == pytest.approx(continuous / discrete)
    assert figures["continuous_decisions_per_s"]["fast"] > 10 * figures["continuous_decisions_per_s"]["highway-env"]
    result = runner.invoke(app, ["bench", "--actions", "bogus"])
    assert result.exit_code == 2 and "--actions: got 'bogus'; allowed: discrete, continuous" in result.stderr
