"""The committed shield mode wherever a shield mode goes: evaluate / stress / falsify figures (lapses, lapses in the
model, plan-forced share, uncertified starts, redraws), its collision contexts, lapse counterexample files and their
replay, the redraw option for uncertified starts, the vector env and training. The other modes' figures unchanged.

Short runs on the fast simulator."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from safelane.config import ConfigError, load_config
from safelane.core.errors import NotSupported
from safelane.core.spaces import FASTER, IDLE
from safelane.running import evaluation
from safelane.running.collisions import COMMITTED_CONTEXTS, collision_contexts
from safelane.running.counterexamples import load_counterexample, replay, save_counterexamples
from safelane.running.evaluation import COMMITTED_FIELDS, EpisodeTally, run_config, summarize
from safelane.running.policies import fixed_policy

COMMITTED = {"simulator": "fast", "shield.mode": "committed", "shield.override": True}
DENSE = {"env.vehicles_density": 2.0, "env.lanes_count": 3, "traffic.vehicles_behind": 12}
"""A dense scene with cars behind: about half the spawns start uncertified."""
SHORT = {"env.duration": 8}


@pytest.fixture(scope="module")
def committed_records() -> list[Any]:
    """Six random-policy episodes under the committed shield on the fast preset: two of them lapse (seeds 3, 5)."""
    cfg = load_config("fast", overrides=COMMITTED)
    return run_config(cfg, fixed_policy("random", 0), 6, 0)


# --- the figures ------------------------------------------------------------------------------------


def test_the_summary_counts_what_the_shield_reported(committed_records: list[Any]) -> None:
    """Lapses, lapses in the model, plan-forced decisions and uncertified starts: the shield's own ``info``, step by
    step, replayed by hand, adds up to the summary's figures."""
    from safelane.env.factory import make_env

    cfg = load_config("fast", overrides=COMMITTED)
    env = make_env(cfg)
    lapses = in_model = forced = uncertified = decisions = 0
    for record in committed_records:
        _, info = env.reset(seed=record.seed)
        uncertified += info["uncertified_start"]
        assert info["redraws"] == 0
        for action in record.chosen_actions:
            _, _, _, _, info = env.step(action)
            lapses += info["lapse"]
            in_model += info["lapse_in_model"]
            forced += info["plan_forced"]
            decisions += 1
    env.close()
    s = summarize(committed_records)
    assert lapses >= 1  # the scene has lapses: the count is not vacuous
    assert (s["lapses"], s["lapses_in_model"], s["uncertified_starts"]) == (lapses, in_model, uncertified)
    assert s["plan_forced_rate"] == pytest.approx(forced / decisions) and s["decisions"] == decisions
    assert s["redraws"] == 0
    assert tuple(s["collision_contexts"]) == collision_contexts(True)
    assert "started_unsafe" not in s["collision_contexts"]
    lapsed = [r for r in committed_records if r.lapses]
    assert all(len(r.lapse_cars) == len(r.lapses) for r in lapsed)
    assert all(cars for r in lapsed for cars in r.lapse_cars)  # every lapse so far traced to a car
    assert set(COMMITTED_FIELDS) <= set(lapsed[0].to_dict())


def test_the_other_modes_report_what_they_reported() -> None:
    """Robust: no committed figure, the four contexts of before, records without the committed fields."""
    cfg = load_config("fast", overrides={"simulator": "fast", "shield.mode": "robust", "shield.override": True,
                                         **SHORT})  # fmt: skip
    records = run_config(cfg, fixed_policy("random", 0), 2, 0)
    s = summarize(records)
    assert not {"lapses", "lapses_in_model", "plan_forced_rate", "uncertified_starts", "redraws"} & set(s)
    assert tuple(s["collision_contexts"]) == ("started_unsafe", "after_break", "from_safe_state", "after_fallback")
    assert not set(COMMITTED_FIELDS) & set(records[0].to_dict())
    assert records[0].uncertified_start is None


# --- the collision contexts, from hand-built steps ----------------------------------------------------


def _step(**info: Any) -> dict[str, Any]:
    base = {"speed": 20.0, "fallback": False, "plan_forced": False, "lapse": False, "lapse_in_model": False,
            "lapse_cars": (), "escaped_cars": (), "entered_cars": (), "certified": True, "snapshot": None}  # fmt: skip
    return {**base, **info}


def _context(
    monkeypatch: pytest.MonkeyPatch, steps: list[dict[str, Any]], start_certified: bool = True, partner: int = 7,
    kind: str = "ego_hit_front",
) -> tuple[str | None, list[int]]:  # fmt: skip
    """The context the tally gives a crash at the last of ``steps`` (the crash partner and kind stubbed)."""
    monkeypatch.setattr(evaluation, "collision_partner", lambda snap: partner)
    monkeypatch.setattr(evaluation, "classify_collision", lambda snap: kind)

    class Snap:
        time = 1.0

    reset = {"fallback": not start_certified, "uncertified_start": not start_certified, "redraws": 0}
    monkeypatch.setattr(evaluation, "vehicles_ahead", lambda snap: 0)
    tally = EpisodeTally(0, {**reset, "snapshot": Snap()}, committed=True)
    for i, info in enumerate(steps):
        tally.add(IDLE, 0.0, {**info, "snapshot": Snap(), "collision": i == len(steps) - 1})
    return tally.context, tally.outside_model_cars


def test_a_crash_after_a_car_left_its_set_is_outside_the_model_and_names_the_car(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The partner (7) left its set at decision 2; the crash at decision 3, from a verified plan.
    context, cars = _context(monkeypatch, [_step(), _step(escaped_cars=(7,)), _step()])
    assert (context, cars) == ("outside_model", [7])
    # A car a lapse named, not the partner: still outside the model (the lapse traced to it came first).
    context, cars = _context(monkeypatch, [_step(lapse=True, lapse_cars=(4,), escaped_cars=(4,), fallback=True,
                                                 plan_forced=True), _step()])  # fmt: skip
    assert (context, cars) == ("outside_model", [4])
    # Another car that left its set and caused no lapse: the plan still verified, the crash is the rule's own.
    assert _context(monkeypatch, [_step(escaped_cars=(4,)), _step()]) == ("from_safe_state", [])
    # The escapes the crash step itself reports are the impact's: not a cause.
    assert _context(monkeypatch, [_step(), _step(escaped_cars=(7,))]) == ("from_safe_state", [])


def test_under_a_bare_shield_a_rear_end_is_others_at_fault(monkeypatch: pytest.MonkeyPatch) -> None:
    """A ``SafetyShield`` with a committed family of its own, no ``make_env`` wrapper above it: every reset and step
    reports the committed keys, and the tally sees a rear-end as ``others_at_fault`` (the follower's gap)."""
    from safelane.env.factory import make_env
    from safelane.safety.committed.family import CommittedFamily
    from safelane.safety.shield import SafetyShield

    env = SafetyShield(make_env("fast", simulator="fast", **SHORT), mode=CommittedFamily(), override=True)
    _, reset = env.reset(seed=0)
    assert "uncertified_start" in reset and "redraws" not in reset
    _, _, _, _, info = env.step(IDLE)
    assert {"lapse_cars", "lapse_escaped_cars", "rolled_back", "unbraked_followers", "entered_cars"} <= set(info)
    env.close()
    monkeypatch.setattr(evaluation, "collision_partner", lambda snap: 7)
    monkeypatch.setattr(evaluation, "classify_collision", lambda snap: "rear_ended")
    monkeypatch.setattr(evaluation, "vehicles_ahead", lambda snap: 0)
    tally = EpisodeTally(0, {**reset, "fallback": False, "uncertified_start": False}, committed=True)
    tally.add(IDLE, 0.0, {**_step(), "snapshot": info["snapshot"], "collision": True})
    assert tally.context == "others_at_fault"


def test_a_crash_with_a_car_rolling_back_or_unbraked_is_outside_the_model(monkeypatch: pytest.MonkeyPatch) -> None:
    """The partner rolling back, or a follower ahead of the bound the plan drew for it, at the crash's own decision
    (exits the impact does not make): ``outside_model``, the car named. Its other escapes there are the impact's."""
    for key in ("rolled_back", "unbraked_followers"):
        context, cars = _context(monkeypatch, [_step(), _step(escaped_cars=(7,), **{key: (7,)})])
        assert (context, cars) == ("outside_model", [7])
    # Another car rolling back, not the partner: not a cause.
    assert _context(monkeypatch, [_step(), _step(rolled_back=(4,), escaped_cars=(4,))])[0] == "from_safe_state"


def test_a_lapse_names_only_the_cars_that_failed_the_plan(monkeypatch: pytest.MonkeyPatch) -> None:
    """The record's lapse cars are the shield's ``lapse_cars``; a crash after the lapse names those of them that
    left their sets, not the other escapes on the road."""
    lapse = _step(lapse=True, lapse_cars=(4,), lapse_escaped_cars=(4,), escaped_cars=(4, 30, 31), fallback=True,
                  plan_forced=True)  # fmt: skip
    context, cars = _context(monkeypatch, [lapse, _step()], partner=2)
    assert (context, cars) == ("outside_model", [4])
    # The car the plan failed on was inside its set (a car ahead it could not avoid, say): nothing outside the model
    # is named.
    lapse = _step(lapse=True, lapse_cars=(5,), escaped_cars=(30,), fallback=True, plan_forced=True)
    assert _context(monkeypatch, [lapse, _step()], partner=2) == ("after_break", [])


def test_the_committed_contexts_in_their_order(monkeypatch: pytest.MonkeyPatch) -> None:
    # No state before the crash had a verified plan: an uncertified start (never "started_unsafe").
    assert _context(monkeypatch, [_step(fallback=True), _step(fallback=True)], start_certified=False)[0] == (
        "uncertified_start"
    )
    # Rear-ended: the follower's fault.
    assert _context(monkeypatch, [_step()], kind="rear_ended")[0] == "others_at_fault"
    # Hit by a car that entered a lane the ego holds (at the crash's own decision too).
    assert _context(monkeypatch, [_step(), _step(entered_cars=(7,))])[0] == "others_at_fault"
    # A lapse in the model came first: after_break (the lapse is the hole).
    lapse = _step(lapse=True, lapse_in_model=True, fallback=True, plan_forced=True)
    assert _context(monkeypatch, [lapse, _step(fallback=True, plan_forced=True)])[0] == "after_break"
    # An unverified action executed without override from a state with no plan: after_fallback.
    assert _context(monkeypatch, [_step(fallback=True), _step(unsafe_action=True)])[0] == "after_fallback"
    assert set(COMMITTED_CONTEXTS) <= set(collision_contexts(True))


# --- lapse files and their replay --------------------------------------------------------------------


def test_lapses_are_saved_and_replay_to_the_same_lapse(committed_records: list[Any], tmp_path: Path) -> None:
    cfg = load_config("fast", overrides=COMMITTED)
    files = save_counterexamples(committed_records, cfg, tmp_path, "test")
    lapse_files = [p for p in files if "-lapse-" in p.name]
    assert len(lapse_files) == sum(len(r.lapses) - len(r.lapses_in_model) for r in committed_records) >= 1
    cx = load_counterexample(lapse_files[0])
    assert cx.kind == "lapse" and cx.cars and len(cx.actions) == cx.step
    result = replay(cx)
    assert result.reproduced and result.decisions[-1].committed["lapse"]
    verdict = result.decisions[-1].committed
    assert verdict["lapse_cars"] == cx.cars and set(cx.cars) <= {*verdict["escaped_cars"], *verdict["entered_cars"]}
    assert "committed" in result.to_dict()["decisions"][-1]
    # Filed as a lapse in the model it is not one (a car is outside its set): not reproduced; nor traced to other cars.
    assert not replay(cx.model_copy(update={"kind": "lapse_in_model"})).reproduced
    assert not replay(cx.model_copy(update={"cars": [*cx.cars, 999]})).reproduced
    # The cars are a set: one named twice in a file is the same car.
    assert replay(cx.model_copy(update={"cars": [*cx.cars, cx.cars[0]]})).reproduced
    assert json.loads(lapse_files[0].read_text())["cars"] == cx.cars


def test_a_lapse_replays_on_highway_env(committed_records: list[Any], tmp_path: Path) -> None:
    cfg = load_config("fast", overrides=COMMITTED)
    files = [p for p in save_counterexamples(committed_records, cfg, tmp_path) if "-lapse" in p.name]
    result = replay(load_counterexample(files[0]), simulator="highway-env")
    assert result.simulator == "highway-env" and result.reproduced


# --- redrawing uncertified starts --------------------------------------------------------------------


def test_redraw_uncertified_draws_the_next_spawn_until_a_plan_verifies() -> None:
    from safelane.env.factory import make_env

    plain = make_env("fast", **COMMITTED, **DENSE)
    _, info = plain.reset(seed=1)
    assert info["uncertified_start"] and info["redraws"] == 0  # seed 1 spawns uncertified
    # The redraws are the environment's next draws: reset without a seed after the seeded one.
    draws = [info["uncertified_start"]]
    first_obs = []
    while draws[-1] and len(draws) < 20:
        obs, info = plain.reset()
        draws.append(info["uncertified_start"])
        first_obs.append(obs)
    assert not draws[-1]
    plain.close()

    redraw = make_env("fast", **COMMITTED, **DENSE, **{"shield.redraw_uncertified": True})
    obs, info = redraw.reset(seed=1)
    assert not info["uncertified_start"] and info["redraws"] == len(draws) - 1 >= 1
    np.testing.assert_array_equal(obs, first_obs[-1])
    obs_again, _ = redraw.reset(seed=1)  # the same seed, the same episode
    np.testing.assert_array_equal(obs_again, obs)
    redraw.close()
    # At most redraw_tries: then the episode starts uncertified, the redraws reported.
    bounded = make_env("fast", **COMMITTED, **DENSE, **{"shield.redraw_uncertified": True,
                                                             "shield.redraw_tries": 1})  # fmt: skip
    _, info = bounded.reset(seed=1)
    assert info["redraws"] == 1 and info["uncertified_start"] == draws[1]
    bounded.close()


def test_redraws_are_reported_in_the_summary() -> None:
    cfg = load_config("fast", overrides={**COMMITTED, **DENSE, **SHORT, "shield.redraw_uncertified": True})
    records = run_config(cfg, fixed_policy("faster"), 3, 0)
    s = summarize(records)
    assert s["redraws"] == sum(r.redraws for r in records) >= 1  # seed 1 is redrawn
    assert s["uncertified_starts"] == 0


def test_redraw_is_refused_for_the_other_modes() -> None:
    for mode in ("none", "nominal", "robust"):
        with pytest.raises(ConfigError, match=r"^shield\.redraw_uncertified: only for shield\.mode committed"):
            load_config("fast", overrides={"shield.mode": mode, "shield.redraw_uncertified": True})
    with pytest.raises(ConfigError, match=r"shield\.redraw_tries"):
        load_config("fast", overrides={**COMMITTED, "shield.redraw_tries": 0})


# --- the vector env, the batch, training --------------------------------------------------------------


def test_the_fast_batch_runs_committed_as_the_single_environments_do() -> None:
    """The fast batch (one family per environment) and the loop over ``make_env`` environments give the same rows:
    observations, rewards, masks, executed actions and the committed flags, across autoresets; the batch refuses
    ``shield.redraw_uncertified`` in one line."""
    from safelane.env.factory import make_env
    from safelane.env.fast_batch import FastBatch
    from safelane.env.vector import FastVectorEnv, SafelaneVectorEnv, make_vector_env

    overrides = {**COMMITTED, "env.vehicles_density": 2.0}
    cfg = load_config("fast", overrides=overrides)
    fast = make_vector_env(cfg, num_envs=3, seed=3)
    loop = SafelaneVectorEnv([make_env(cfg) for _ in range(3)])
    loop.reset(seed=3)
    assert isinstance(fast, FastVectorEnv)
    assert np.array_equal(fast.action_masks(), loop.action_masks())
    forced = lapses = 0
    for _ in range(42):  # always FASTER, as the shield allows: seeds 3 and 5 drive on kept plans and lapse
        actions = np.full(3, FASTER)
        got, want = fast.step(actions), loop.step(actions)
        for a, b in zip(got[:4], want[:4], strict=True):
            assert np.array_equal(a, b)
        for key in ("action_mask", "executed_action", "fallback", "collision", "plan_forced", "lapse",
                    "lapse_in_model"):  # fmt: skip
            assert np.array_equal(got[4][key], want[4][key]), key
        forced += int(got[4]["plan_forced"].sum())
        lapses += int(got[4]["lapse"].sum())
    assert forced >= 2 and lapses >= 1
    fast.close()
    loop.close()
    redraw = load_config("fast", overrides={**COMMITTED, "shield.redraw_uncertified": True})
    with pytest.raises(NotSupported) as err:
        FastBatch(redraw, 2)
    message = str(err.value)
    assert "\n" not in message and "shield.redraw_uncertified" in message


def test_training_under_the_committed_shield(tmp_path: Path) -> None:
    from safelane.running.run_directory import load_run_config, make_train_config
    from safelane.running.training import train

    sets = ["shield.mode=committed", "simulator=fast", "env.duration=4", "env.vehicles_count=8",
            "agent.learning_starts=4", "agent.batch_size=8", "agent.buffer_size=10"]  # fmt: skip
    out = train(make_train_config(method="robust", episodes=2, seed=0, checkpoint_every=2, sets=sets), tmp_path / "r")
    rows = list(csv.DictReader((out / "metrics.csv").open()))
    assert [r["episode"] for r in rows] == ["1", "2"]
    assert all(r["shield_interventions"] == "0" for r in rows)  # the agent acts within the committed mask
    assert load_run_config(out).env.shield.mode == "committed"


# --- stress and falsify ------------------------------------------------------------------------------


def test_stress_reports_the_committed_figures() -> None:
    from safelane.running.conditions import Condition
    from safelane.running.stress import run_condition

    cond = Condition(name="short", sets={"simulator": "fast", **SHORT})
    committed = run_condition(cond, fixed_policy("faster"), 2, shield="committed")
    assert {"lapses", "lapses_in_model", "plan_forced_rate", "uncertified_starts", "redraws"} <= set(committed)
    assert tuple(committed["collision_contexts"]) == collision_contexts(True)
    robust = run_condition(cond, fixed_policy("faster"), 2, shield="robust")
    assert "lapses" not in robust and tuple(robust["collision_contexts"]) == collision_contexts(False)


def test_falsify_reports_the_committed_figures(tmp_path: Path) -> None:
    from safelane.running.evaluation import COMMITTED_FIGURES
    from safelane.running.falsify.grid import load_campaign_spec, run_campaign

    spec_path = tmp_path / "c.yaml"
    # ``shield.reading=responsibility``: an older spec's, accepted as the committed mode's one reading.
    spec_path.write_text(yaml.safe_dump({"name": "c", "shield": "committed", "policies": ["random"], "episodes": 2,
                                         "sets": ["env.duration=8", "shield.reading=responsibility"],
                                         "axes": {"lanes": [{"env.lanes_count": 3}]}}))  # fmt: skip
    summary = run_campaign(load_campaign_spec(spec_path), tmp_path / "out", workers=1)
    cell = json.loads((tmp_path / "out" / "cells" / "cell00000.json").read_text())
    for key in COMMITTED_FIGURES:
        assert summary[key] == cell[key]
    header = (tmp_path / "out" / "cells.csv").read_text().splitlines()[0].split(",")
    assert set(COMMITTED_FIGURES) <= set(header)
    assert tuple(summary["collision_contexts"]) == collision_contexts(True)
    assert "lapses" in (tmp_path / "out" / "summary.md").read_text()


def test_evaluation_on_the_fast_batch_gives_the_committed_records_of_one_environment() -> None:
    """``run_config``'s fast batch, the loop over ``make_env`` stacks and one environment give the same committed
    records: lapses (and their cars), plan-forced decisions, uncertified starts, collision contexts."""
    from safelane.env.factory import make_env
    from safelane.running.evaluation import run_episodes, run_episodes_batched

    overrides = {**COMMITTED, "env.vehicles_density": 2.0}
    cfg = load_config("fast", overrides=overrides)
    policy = fixed_policy("faster")
    fused = run_config(cfg, policy, 6, 3, num_envs=3)
    stacks = run_episodes_batched([make_env(cfg) for _ in range(3)], policy, 6, 3)
    one = run_episodes(make_env(cfg), policy, 6, 3)
    as_dicts = [[r.to_dict() for r in records] for records in (fused, stacks, one)]
    assert as_dicts[0] == as_dicts[1] == as_dicts[2]
    assert sum(len(r.lapses) for r in one) >= 1 and sum(r.plan_forced for r in one) >= 2


FOUND = Path(__file__).resolve().parent / "fixtures" / "claim-committed"


@pytest.mark.parametrize(
    "name",
    ["cell01017-seed4010170025-lapse_in_model-step3.json", "cell01703-seed4017030000-lapse_in_model-step98.json"],
)
def test_a_kept_plan_keeps_the_lanes_it_held_when_the_ego_finishes_a_lane_change(name: str) -> None:
    """Two lapses the claim grid filed in the model: the ego finished a lane change between two
    decisions, so the lane it left was no longer held and a car that might turn into it two lanes away counted
    against the kept plan. The plan keeps the lanes it held when verified (``Plan.held``): no lapse now."""
    cx = load_counterexample(FOUND / name)
    result = replay(cx, "fast")
    assert not result.reproduced and not result.decisions[-1].committed["lapse"]
    assert result.decisions[-1].committed["certified"]


@pytest.mark.parametrize(
    "name",
    [
        "cell01698-seed4016980002-lapse_in_model-step8.json",
        "cell02293-seed4022930002-lapse_in_model-step15.json",
        "cell02303-seed4023030019-lapse_in_model-step14.json",
    ],
)
def test_a_lapse_at_the_step_the_ego_is_rear_ended_is_the_impacts(name: str) -> None:
    """The three lapses the claim grid still filed in the model: each at the decision a car
    behind rear-ended the ego, whose impact pushed it toward the leader its plan brakes behind. The lapse stays a
    lapse, traced to the crash, not one in the model."""
    cx = load_counterexample(FOUND / name)
    result = replay(cx, "fast")
    last = result.decisions[-1]
    assert len(result.decisions) == cx.step and last.collision and result.collision_kind == "rear_ended"
    assert last.committed["lapse"] and not last.committed["lapse_in_model"] and not result.reproduced
    assert not any(d.committed["lapse"] for d in result.decisions[:-1])


def test_a_car_overtaking_beside_the_ego_is_a_traced_cut_in_on_replay() -> None:
    """The claim grid's overtaking lapse: a lapse traced to the car that passed the ego while it may turn
    in (``entered_cars``), not one in the model."""
    cx = load_counterexample(FOUND / "cell00219-seed4002190002-lapse-step36.json")
    result = replay(cx, "fast")
    verdict = result.decisions[-1].committed
    assert result.reproduced and verdict["lapse"] and not verdict["lapse_in_model"]
    assert verdict["lapse_cars"] == [49] and 49 in verdict["entered_cars"]
