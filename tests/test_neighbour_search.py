"""safelane.sim.neighbours (neighbour search and collision pre-check) must give highway-env's episodes, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from safelane.env.factory import make_env


def trajectory(
    search: str, preset: str, seed: int, policy: str, steps: int, density: float = 1.0, behind: int = 5
) -> list[np.ndarray]:
    """Every vehicle's position, heading, speed, crash flag and pending impact after each decision."""
    env = make_env(
        preset, **{"neighbour_search": search, "traffic.vehicles_behind": behind, "env.vehicles_density": density}
    )
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(steps):
        action = 4 if policy == "slower" else int(rng.integers(5))
        *_, terminated, truncated, _info = env.step(action)
        road = env.unwrapped.road
        out.append(
            np.array(
                [
                    [*v.position, v.heading, v.speed, v.crashed, *(v.impact if v.impact is not None else (0, 0))]
                    for v in road.vehicles
                ]
            )
        )
        if terminated or truncated:
            break
    return out


@pytest.mark.parametrize(
    ("preset", "seed", "policy", "steps"),
    [("fast", 0, "slower", 12), ("fast", 1, "random", 12), ("paper", 2, "slower", 4)],
)
def test_numpy_neighbour_search_is_identical(preset: str, seed: int, policy: str, steps: int) -> None:
    original = trajectory("highway-env", preset, seed, policy, steps)
    vectorized = trajectory("numpy", preset, seed, policy, steps)
    assert len(original) == len(vectorized)
    for a, b in zip(original, vectorized, strict=True):
        assert np.array_equal(a, b)


def test_collision_precheck_keeps_crashes_between_other_vehicles() -> None:
    """highway-v0 checks every pair: in dense traffic (seed 8, always SLOWER) two other vehicles crash
    into each other within 3 decisions, and the pre-check must find the same crash at the same frame."""
    original = trajectory("highway-env", "paper", 8, "slower", 3, density=2.0, behind=0)
    vectorized = trajectory("numpy", "paper", 8, "slower", 3, density=2.0, behind=0)
    crashed_others = original[-1][1:, 4]
    assert crashed_others.sum() >= 2 and original[-1][0, 4] == 0
    assert len(original) == len(vectorized)
    for a, b in zip(original, vectorized, strict=True):
        assert np.array_equal(a, b)
