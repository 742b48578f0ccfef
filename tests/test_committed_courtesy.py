"""The committed mode's courtesy: among the verified actions, those the one-decision robust rule also calls safe.

Hand-built scenes with exact masks, and a property: courtesy orders the verified actions, it never allows one that
is not verified (the committed promise is unchanged).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from safelane.safety.committed.family import CommittedFamily
from safelane.safety.one_decision.reference import evaluate as evaluate_one_decision
from safelane.safety.rule import RULES
from test_committed import DYN, scene

RULED = dataclasses.replace(DYN, rule=RULES["forecast-fallback"])


def _verdicts(state, engine: str = "numpy"):
    result = CommittedFamily(engine).evaluate_state(state, np.arange(state.n), RULED)
    return result, evaluate_one_decision(state, RULED, "robust")


def test_a_fast_follower_takes_slower_out_of_the_mask() -> None:
    """The ego at 20 m/s, a leader 70 m ahead, a car 12 m behind at 25 m/s in the ego's lane: under the
    responsibility reading SLOWER is verified (the car behind is its driver's to avoid), but the one-decision rule's
    follower would come within 0.56 m of the ego, so the courteous mask is IDLE and FASTER only."""
    state = scene([{"x": 70.0, "lane": 1, "vx": 20.0}, {"x": -12.0, "lane": 1, "vx": 25.0}])
    result, robust = _verdicts(state)
    assert result.safe.astype(int).tolist() == [0, 1, 0, 1, 1]  # IDLE, FASTER, SLOWER verified
    assert robust.safe.astype(int).tolist() == [0, 1, 0, 1, 0]
    assert result.mask.astype(int).tolist() == [0, 1, 0, 1, 0]
    assert not result.courtesy_waived and not result.fallback


def test_with_no_courteous_verified_action_the_verified_one_stays() -> None:
    """A stopped car 50 m ahead and the same fast follower: only SLOWER is verified and the one-decision rule calls
    nothing safe; courtesy is waived and the mask is the verified set (the plan's promise before the follower)."""
    state = scene([{"x": 50.0, "lane": 1, "vx": 0.0}, {"x": -12.0, "lane": 1, "vx": 25.0}])
    result, robust = _verdicts(state)
    assert not robust.safe.any()
    assert result.safe.astype(int).tolist() == [0, 0, 0, 0, 1]
    assert result.mask.astype(int).tolist() == [0, 0, 0, 0, 1]
    assert result.courtesy_waived


def test_the_engines_agree_on_the_courteous_mask() -> None:
    state = scene([{"x": 70.0, "lane": 1, "vx": 20.0}, {"x": -12.0, "lane": 1, "vx": 25.0}])
    numpy_result, _ = _verdicts(state, "numpy")
    compiled_result, _ = _verdicts(state, "compiled")
    assert numpy_result.mask.tolist() == compiled_result.mask.tolist()
    assert numpy_result.courtesy_waived == compiled_result.courtesy_waived


CAR = st.fixed_dictionaries({
    "x": st.floats(-60.0, 80.0), "lane": st.integers(0, 2), "vx": st.floats(0.0, 30.0),
})  # fmt: skip


@settings(max_examples=60, deadline=None)
@given(cars=st.lists(CAR, min_size=1, max_size=5), ego_speed=st.floats(0.0, 30.0))
def test_courtesy_only_orders_the_verified_actions(cars, ego_speed) -> None:
    """In any scene: with a verified action the mask is the verified actions the one-decision rule calls safe, or
    (none of them) every verified one; it never holds an action that is not verified."""
    cars = [c for c in cars if abs(c["x"]) > 6.0 or c["lane"] != 1]  # no body overlapping the ego's
    if not cars:
        return
    state = scene(cars, ego_speed=ego_speed, set_point=5.0 * round(ego_speed / 5.0))
    result, robust = _verdicts(state)
    if not result.safe.any():
        return
    courteous = result.safe & robust.safe
    expected = courteous if courteous.any() else result.safe
    assert result.mask.tolist() == expected.tolist()
    assert result.courtesy_waived == (not courteous.any())
    assert result.mask.any() and not (result.mask & ~result.safe).any()
