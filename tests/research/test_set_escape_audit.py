"""The set-escape audit (:mod:`research.set_escape_audit`): the components and causes it names, and short episodes
played on highway-env (every physics frame) and on the fast simulator (the decisions), counted consistently; sets
drawn too small are caught."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import research.set_escape_audit as audit
from safelane.safety.committed.sets import CarSets
from safelane.safety.world import Dynamics, RoadState

TINY = ["env.duration=3", "env.vehicles_count=8", "env.lanes_count=2"]


def _dyn() -> Dynamics:
    return Dynamics(decision_period=1.0, frame_dt=0.2, frames_per_decision=5, ego_kp=0.6,
                    target_speeds=(0.0, 10.0, 20.0), lane_width=4.0, lanes_count=3)  # fmt: skip


def _state(x: float, vx: float, y: float = 0.0, heading: float = 0.0) -> RoadState:
    return RoadState(ego_x=-100.0, ego_y=0.0, ego_speed=20.0, ego_lane=0, ego_target_lane=0, ego_target_speed=20.0,
                     ego_speed_index=2, x=np.array([x]), y=np.array([y]), vx=np.array([vx]), vy=np.array([0.0]),
                     heading=np.array([heading]), length=np.array([5.0]), crashed=np.array([False]))  # fmt: skip


def _sets(entry: tuple[float, float, float] = (0.0, 0.5, 1.0)) -> CarSets:
    one = lambda v: np.array([[v, v]])  # noqa: E731
    return CarSets(np.array([7]), one(10.0), one(12.0), one(19.0), one(21.0), np.array([entry]),
                   np.array([[True, False, False]]))  # fmt: skip


@pytest.mark.parametrize(
    ("x", "vx", "y", "expected"),
    [
        (11.0, 20.0, 0.0, []),
        (9.0, 20.0, 0.0, ["x_low"]),
        (13.0, 22.0, 0.0, ["x_high", "v_high"]),
        (11.0, 18.0, 0.0, ["v_low"]),
        (11.0, 20.0, 3.0, ["lane"]),  # its body overlaps lane 1, allowed only from 0.5 s
    ],
)
def test_the_components_a_car_left_are_named(x: float, vx: float, y: float, expected: list[str]) -> None:
    state = _state(x, vx, y)
    parts = audit.components(state, 0, _sets(), 0, _dyn(), np.array([7]))
    assert parts == (expected or ["other"])


def test_the_causes_follow_the_classes_order() -> None:
    assert audit.cause(["x_high"], False, True, False, 20.0, 1.0) == "collision"
    assert audit.cause(["x_high"], True, True, False, 1.0, 1.0) == "crashed_wall_moves"
    assert audit.cause(["x_high"], False, False, False, 20.0, 25.0) == "teleport"
    assert audit.cause(["v_low"], False, False, False, -0.5, 0.0) == "rolling_back"
    assert audit.cause(["x_low"], False, False, False, 0.5, 0.1, backwards_at_draw=True) == "rolling_back"
    assert audit.cause(["x_low", "lane"], False, False, True, 15.0, 0.1) == "lane_entered_early"
    assert audit.cause(["v_low"], False, False, True, 15.0, 0.0) == "turning_slower"
    assert audit.cause(["x_high"], False, False, True, 15.0, 0.1) == "turning_faster"
    assert audit.cause(["v_low"], False, False, False, 15.0, 0.0) == "straight_slower"
    assert audit.cause(["v_high"], False, False, False, 15.0, 0.0) == "straight_faster"
    assert audit.cause(["other"], False, False, False, 15.0, 0.0) == "other_component"
    assert set(audit.CLASSES) >= {"collision", "lane_entered_early", "turning_slower", "other_component"}


def test_a_short_episode_on_highway_env_is_checked_at_every_frame(tmp_path: Path) -> None:
    """Every car at every physics frame: 5 frames a decision at 5 Hz (preset ``fast``) and 1 decision per second;
    the shares are those of the counts; the summary and its table are written."""
    out = tmp_path / "summary.json"
    args = ["--episodes", "1", "--drivers", "IDM", "--out", str(out)] + [a for s in TINY for a in ("--set", s)]
    assert audit.main(args) == 0
    data = json.loads(out.read_text())
    (r,) = data["drivers"]
    assert data["simulator"] == "highway-env" and r["driver"] == "IDM" and r["episodes"] == 1
    cars = r["traces"]
    assert cars == 8 and r["decisions"] == 3  # 8 other vehicles; 3 s at 1 decision per second
    assert r["frames"] == 5 * r["decisions"] and r["car_frames"] == cars * r["frames"]
    assert r["car_decisions"] == cars * r["decisions"] and r["at_decisions"] == r["car_decisions"]
    assert r["car_frames_out_share"] == r["car_frames_out"] / r["car_frames"]
    assert sum(c["car_frames"] for c in r["classes"].values()) == r["car_frames_out"]
    assert sum(c["car_decisions"] for c in r["classes"].values()) == r["car_decisions_out"]
    assert "| IDM | 1 |" in out.with_suffix(".md").read_text()


def test_the_fast_simulator_is_checked_at_the_decisions() -> None:
    result = audit.audit_driver("Linear", 1, 3, "faster", "fast", TINY, log=lambda _: None)
    assert result["frames"] == result["decisions"] == 3 and result["car_frames"] == result["at_decisions"]
    assert result["car_frames"] == result["traces"] * 3


def test_sets_drawn_too_small_are_caught(monkeypatch: pytest.MonkeyPatch) -> None:
    """Sets that only hold the cars' positions at the decision (no motion at all): every moving car leaves them
    at the first frame, and the audit says so."""
    real = audit.car_sets

    def frozen(state: RoadState, dyn: Dynamics, vehicle: np.ndarray) -> CarSets:
        sets = real(state, dyn, vehicle)
        here = np.repeat(state.x[:, None], sets.x_lo.shape[1], axis=1)
        return CarSets(sets.vehicle, here, here.copy(), sets.v_lo, sets.v_hi, sets.entry, sets.now)

    monkeypatch.setattr(audit, "car_sets", frozen)
    result = audit.audit_driver("IDM", 1, 0, "faster", "highway-env", TINY, log=lambda _: None)
    assert result["car_decisions_out"] == result["car_decisions"]  # every car moves: every car leaves
    assert result["classes"]["straight_faster"]["car_decisions"] > 0
