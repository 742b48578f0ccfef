"""The ego must be able to stop: highway-env's default set-points [20, 25, 30] leave the rule no fallback."""

from __future__ import annotations

import warnings

import gymnasium as gym
import pytest

import safelane
from safelane.core.spaces import IDLE, SLOWER
from safelane.env.scenarios import VehicleSpec, build_scene

STOPPABLE = [0, 5, 10, 15, 20, 25, 30]


def test_stoppable_action_config_gives_set_points_from_zero() -> None:
    assert safelane.stoppable_action_config() == {"type": "DiscreteMetaAction", "target_speeds": STOPPABLE}
    assert safelane.stoppable_action_config(20.0, 2.5)["target_speeds"][-2:] == [17.5, 20.0]
    with pytest.raises(ValueError, match="step"):
        safelane.stoppable_action_config(30.0, 0.0)


def test_a_shield_over_stock_set_points_warns_once_in_one_line() -> None:
    env = safelane.SafetyShield(gym.make("highway-fast-v0", config={"vehicles_count": 5}), mode="robust")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        env.reset(seed=0)
        env.reset(seed=1)
    mine = [w for w in caught if issubclass(w.category, safelane.CannotStopWarning)]
    assert len(mine) == 1
    text = str(mine[0].message)
    assert "\n" not in text and "env.action.target_speeds" in text and "20 m/s" in text
    assert "stoppable_action_config" in text


def test_no_warning_when_the_ego_can_stop() -> None:
    config = {"vehicles_count": 5, "action": safelane.stoppable_action_config()}
    env = safelane.SafetyShield(gym.make("highway-fast-v0", config=config), mode="robust")
    with warnings.catch_warnings():
        warnings.simplefilter("error", safelane.CannotStopWarning)
        env.reset(seed=0)
    assert list(env.unwrapped.vehicle.target_speeds) == STOPPABLE


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
def test_without_a_standstill_set_point_a_stopped_car_ahead_leaves_no_safe_action(engine: str) -> None:
    """A stopped car 120 m ahead at 25 m/s, the only other lane blocked by a car alongside. With set-points
    down to 0 m/s, IDLE and SLOWER keep the gap (25 m, 50 m); with [20, 25, 30] the ego cannot go below
    20 m/s, every action runs into the car (SLOWER by 80 m) and the state is a fallback."""
    scene = [VehicleSpec(1, 120.0, 0.0), VehicleSpec(0, 0.0, 25.0)]
    options = {"shield.engine": engine}
    can_stop = build_scene(1, 25.0, scene, lanes_count=2, **{"env.action.target_speeds": STOPPABLE}, **options)
    assert can_stop.mask.tolist() == [a in (IDLE, SLOWER) for a in range(5)] and not can_stop.result.fallback
    with pytest.warns(safelane.CannotStopWarning):
        stock = build_scene(1, 25.0, scene, lanes_count=2, **{"env.action.target_speeds": [20, 25, 30]}, **options)
    assert stock.result.fallback and not stock.result.safe.any()
    assert stock.result.min_gap[SLOWER] < -50
