"""The room the shield asks for behind a leader (scenarios.min_safe_gap), on the real simulator."""

from __future__ import annotations

from safelane.core.spaces import FASTER, IDLE
from safelane.env.scenarios import VehicleSpec, build_scene, min_safe_gap


def test_min_safe_gap_grows_with_speed_and_with_a_slower_leader() -> None:
    """Following needs more room at higher speed and behind a slower leader; FASTER needs more than IDLE."""
    idle_20 = min_safe_gap(20.0, 20.0, IDLE)
    idle_25 = min_safe_gap(25.0, 25.0, IDLE)
    assert 10.0 < idle_20 < idle_25 < min_safe_gap(25.0, 22.0, IDLE)
    assert min_safe_gap(25.0, 25.0, FASTER) > idle_25
    # The bisection's answer is the boundary: safe there, unsafe 1 m closer.
    assert build_scene(1, 25.0, [VehicleSpec(1, idle_25, 25.0)]).result.safe[IDLE]
    assert not build_scene(1, 25.0, [VehicleSpec(1, idle_25 - 1.0, 25.0)]).result.safe[IDLE]
