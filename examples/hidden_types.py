"""Hidden driver types: the same policy under the robust, belief and omniscient shields, and what the belief learns.

What it shows: ``gym.make("safelane/HighwayHiddenTypesFast-v0", shield=MODE)`` is the paper's highway where each
other car is a timid, normal or aggressive driver (drawn at spawn, hidden from the shield). The always-FASTER policy
drives the same seeds under three shields — ``robust`` (each car may be every type), ``belief`` (each car the types a
per-car Bayes filter has not ruled out) and ``omniscient`` (each car its true type: the bound no belief can beat) —
and the script prints for each the collisions, those with a car whose true type the belief had ruled out (its
promise is probabilistic), the share of decisions with no safe action (fallback) and the mean speed. Then it runs
the belief filter alone along one episode and prints how often its most probable type is the true one.

Run:
    python examples/hidden_types.py                 # 20 episodes of 40 s per shield
    python examples/hidden_types.py --quick         # 1 episode of 10 s per shield: a smoke test

Time: about 5 s on one core as set, 3 s with ``--quick``, once the kernels are compiled (the first run of
safelane on a machine compiles them: a few minutes).
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import safelane  # noqa: F401  (registers the safelane/ ids)
from safelane.core.drivers import parse_driver_mix
from safelane.safety.belief import BeliefFilter

ENV_ID = "safelane/HighwayHiddenTypesFast-v0"
FASTER = 3  # the meta-action index of FASTER (LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER)


def drive(shield: str, episodes: int, duration: float, seed: int) -> tuple[int, int, float, float]:
    """(collisions, collisions with a ruled-out true type, fallback share, mean speed [m/s]) of always-FASTER under
    ``shield`` (override on: the shield replaces an unsafe FASTER), ``episodes`` episodes from seeds ``seed, …``."""
    env = gym.make(ENV_ID, shield=shield, override=True, config={"env.duration": duration})
    collisions = ruled_out = decisions = fallbacks = 0
    speeds: list[float] = []
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        while True:
            _, _, terminated, truncated, info = env.step(FASTER)
            decisions += 1
            fallbacks += int(info.get("fallback", False))
            speeds.append(float(info["speed"]))
            if terminated or truncated:
                break
        collisions += int(info["crashed"])
        ruled_out += int(bool(info.get("type_ruled_out_crash", False)))
    env.close()
    return collisions, ruled_out, fallbacks / decisions, float(np.mean(speeds))


def belief_accuracy(duration: float, seed: int) -> tuple[int, float]:
    """(cars observed, share whose most probable type is the true one) after one episode of IDLE decisions."""
    env = gym.make(ENV_ID, shield="none", config={"env.duration": duration})
    _, info = env.reset(seed=seed)
    belief = BeliefFilter(parse_driver_mix("timid-normal-aggressive"), sigma=0.2)
    posterior = belief.reset(info["snapshot"])  # (cars, types): the prior, rows summing to 1
    while True:
        _, _, terminated, truncated, info = env.step(1)  # IDLE
        if terminated or truncated:
            break
        posterior = belief.update(info["snapshot"])
    env.close()
    snap = info["snapshot"]
    cars = snap.others()
    if len(cars) == 0:
        return 0, float("nan")
    return len(cars), float(np.mean(np.argmax(posterior[cars], axis=1) == snap.driver_type[cars]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=20, help="episodes per shield (default 20)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="1 episode of 10 s per shield: a smoke test")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error("--episodes: must be at least 1")
    episodes, duration = (1, 10.0) if args.quick else (args.episodes, 40.0)
    print(f"always-FASTER on {ENV_ID}, {episodes} episode(s) of {duration:.0f} s per shield")
    print("shield      collisions ruled_out fallback speed")
    for shield in ("robust", "belief", "omniscient"):
        collisions, ruled_out, fallback, speed = drive(shield, episodes, duration, args.seed)
        print(f"{shield:<11} {collisions:>10} {ruled_out:>9} {100 * fallback:>7.2f}% {speed:>5.2f}")
    cars, right = belief_accuracy(duration, args.seed)
    print(f"belief after one episode: {cars} cars, the most probable type is the true one for {100 * right:.0f} %")


if __name__ == "__main__":
    main()
