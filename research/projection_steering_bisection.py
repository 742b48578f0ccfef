"""Would a bisection in steering project an agent's continuous action less far, and at what cost?

On recorded states of the shield for continuous actions (fast simulator, the default preset at 1 and at 5 decisions
per second), an agent's action is drawn near the fail-safe's lane-keeping steering (acceleration uniform in
[-0.3, 0.6], steering the lane-keeping one plus Gaussian noise sigma) and projected as the shield projects it; then,
from the steering of the verified action found, ``steps`` bisections in steering toward the agent's look for a
nearer verified action. Prints, per rate and sigma, the share of actions projected, the mean projection distance
of the projected ones and the actions verified per decision, for 0, 4 and 8 bisections.

    python research/projection_steering_bisection.py --episodes 3 --decisions 30

Results: docs/research/continuous-shield.md.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from safelane.env.factory import make_env
from safelane.safety.continuous.family import lane_keeping_action
from safelane.safety.continuous.search import ActionSearch, Projection, project

BISECTIONS = (0, 4, 8)


def refine(search: ActionSearch, wanted: np.ndarray, found: Projection, steps: int) -> Projection:
    """``found`` improved by ``steps`` bisections in steering between its steering (verified) and the agent's."""
    if found.action is None or steps == 0:
        return found
    steering, acceleration = float(wanted[1]), float(wanted[0])
    best = (found.distance, found.action, found.plan)
    outside, inside = steering, float(found.action[1])
    for _ in range(steps):
        middle = float(np.float32(0.5 * (inside + outside)))
        if middle in (inside, outside):
            break
        radius = np.sqrt(max(best[0] ** 2 - (middle - steering) ** 2, 0.0))
        nearest, plan = search.nearest(middle, acceleration, radius)
        if plan is None:
            outside = middle
            continue
        inside = middle  # within the radius: no farther than the best
        action = np.array([nearest, middle], dtype=np.float32)
        distance = float(np.hypot(*(action.astype(np.float64) - wanted)))
        if distance < best[0]:
            best = (distance, action, plan)
    return Projection(best[1], best[2], best[0], search.evaluated)


def measure(rate: int, frequency: int, sigma: float, episodes: int, decisions: int, rng: np.random.Generator) -> None:
    """Print one row per bisection count for the rate (decisions/s, physics ``frequency`` Hz) and ``sigma``."""
    env = make_env("fast", simulator="fast", actions="continuous", **{
        "shield.mode": "committed", "env.policy_frequency": rate, "env.simulation_frequency": frequency})  # fmt: skip
    family = env.get_wrapper_attr("family")
    rows = []
    for episode in range(episodes):
        _, info = env.reset(seed=episode)
        for _ in range(decisions):
            dyn = env.get_wrapper_attr("_dynamics")(info["snapshot"])
            state, _, sets, trace = family.state_of(info["snapshot"], dyn)
            keeping = lane_keeping_action(state, dyn, family.limits)
            wanted = np.clip([rng.uniform(-0.3, 0.6), keeping[1] + rng.normal(0.0, sigma)], -1, 1).astype(np.float32)
            row = []
            for steps in BISECTIONS:
                search = family.search(state, dyn, sets, trace["cars"])
                start = time.perf_counter()
                found = refine(search, wanted, project(search, wanted, float(keeping[1])), steps)
                distance = found.distance if found.action is not None else np.nan
                row.append((distance, search.evaluated, time.perf_counter() - start))
            rows.append(row)
            _, _, terminated, truncated, info = env.step(wanted)
            if terminated or truncated:
                break
    table = np.array(rows)
    projected = table[:, 0, 0] > 0
    print(f"{rate} decisions/s, sigma {sigma}: {len(table)} decisions, {projected.mean():.0%} projected")
    for k, steps in enumerate(BISECTIONS):
        print(f"  {steps} bisections: mean distance {np.nanmean(table[projected, k, 0]):.3f}, "
              f"{table[:, k, 1].mean():.1f} actions verified, {1000 * table[:, k, 2].mean():.2f} ms")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--decisions", type=int, default=30)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    for rate, frequency in ((1, 5), (5, 15)):
        for sigma in (0.05, 0.2):
            measure(rate, frequency, sigma, args.episodes, args.decisions, rng)


if __name__ == "__main__":
    main()
