"""safelane.sim.neighbours must give the same episodes as highway-env, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from safelane.env.factory import make_env


def trajectory(search: str, preset: str, seed: int, policy: str, steps: int) -> list[np.ndarray]:
    env = make_env(preset, **{"neighbour_search": search, "traffic.vehicles_behind": 5})
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(steps):
        action = 4 if policy == "slower" else int(rng.integers(5))
        *_, terminated, truncated, _info = env.step(action)
        road = env.unwrapped.road
        out.append(np.array([[*v.position, v.heading, v.speed] for v in road.vehicles]))
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
