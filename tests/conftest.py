"""Shared test setup: headless pygame, small environment helpers, the installed console script."""

from __future__ import annotations

import os

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # highway-env imports pygame; no display in tests
# numpy's AVX-512 tan/arctan are not libm's: keep numpy on libm so highway-env and the fast simulator
# compute the same bits (safelane.sim.fast.libm; must precede numpy's import, the Makefile exports it too)
os.environ.setdefault("NPY_DISABLE_CPU_FEATURES", "X86_V4 AVX512_ICL AVX512_SPR")
os.environ.setdefault("OPENBLAS_CORETYPE", "Nehalem")  # no fused multiply-adds in np.dot (libm.py)

import shutil
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def _step_once(**overrides: Any) -> None:
    from safelane.env.factory import make_env

    env = make_env("fast", seed=0, **overrides)
    env.step(env.action_space.sample())
    env.close()


def _warm_simulators() -> None:
    _step_once(simulator="fast")
    _step_once(simulator="fast", actions="continuous")


def _warm_rules() -> None:
    _step_once(simulator="highway-env", **{"env.vehicles_count": 10, "shield.mode": "robust"})
    _step_once(simulator="highway-env", **{"env.vehicles_count": 10, "shield.mode": "committed"})


_WARM_UPS = {"gw0": _warm_simulators, "gw1": _warm_rules}


def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist, each of the first two workers starts by compiling one half of the kernels most tests
    need (numba caches them on disk), so that the other worker loads them instead of compiling them a second time
    when both need them at once: from a cold cache, about 90 s of CPU (the simulator's decision kernel alone takes
    45 s to compile). With warm caches this costs a few seconds."""
    warm_up = _WARM_UPS.get(os.environ.get("PYTEST_XDIST_WORKER", ""))
    if warm_up is not None:
        warm_up()


@pytest.fixture
def make_fast_env() -> Iterator[Callable[..., gym.Env]]:
    """Factory of ``fast``-preset environments (``make_env`` keyword overrides); all closed after the test."""
    from safelane.env.factory import make_env

    envs: list[gym.Env] = []

    def factory(**overrides: Any) -> gym.Env:
        seed = overrides.pop("seed", 0)
        env = make_env("fast", seed=seed, **overrides)
        envs.append(env)
        return env

    yield factory
    for env in envs:
        env.close()


@pytest.fixture(scope="session")
def safelane_exe() -> Path:
    """The installed ``safelane`` console script of the running interpreter's environment."""
    candidate = Path(sys.executable).parent / "safelane"
    if candidate.exists():
        return candidate
    found = shutil.which("safelane")
    if found is None:
        pytest.skip("the safelane console script is not installed")
    return Path(found)


LANE_WIDTH = 4.0  # [m] highway-env's StraightLane.DEFAULT_WIDTH: lane i is centred at y = 4·i


def place_vehicles(
    env: gym.Env,
    ego: tuple[float, int, float],
    others: list[tuple[float, float, float, float]],
) -> list[Any]:
    """Replace the road's traffic by a hand-built scene (straight road along x).

    ``ego``: (x [m], lane index, speed [m/s]), heading 0, its speed controller aimed at that speed.
    ``others``: (x [m], y [m], speed [m/s], heading [rad]) of IDM vehicles. Returns the vehicles,
    ego first.
    """
    from highway_env.vehicle.behavior import IDMVehicle

    base = env.unwrapped
    road, vehicle = base.road, base.vehicle
    x, lane, speed = ego
    vehicle.position = np.array([x, LANE_WIDTH * lane], dtype=float)
    vehicle.heading = 0.0
    vehicle.speed = speed
    vehicle.on_state_update()
    vehicle.target_lane_index = vehicle.lane_index
    vehicle.speed_index = vehicle.speed_to_index(speed)
    vehicle.target_speed = vehicle.index_to_speed(vehicle.speed_index)
    placed = [vehicle]
    for ox, oy, ospeed, oheading in others:
        placed.append(IDMVehicle(road, np.array([ox, oy], dtype=float), heading=oheading, speed=ospeed))
    road.vehicles = placed
    return placed


@pytest.fixture
def scene() -> Callable[..., list[Any]]:
    """:func:`place_vehicles`, as a fixture."""
    return place_vehicles
