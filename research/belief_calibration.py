"""How well calibrated is the belief over each car's hidden driver type? Play ``hidden-types`` episodes on the fast
simulator, run :class:`safelane.safety.belief.BeliefFilter` at several residual deviations σ on the same episodes,
and compare each posterior with the truth (the snapshot's ``driver_type``, which the filter never reads).

    python research/belief_calibration.py --episodes 100 --sigmas 0.05,0.1,0.2,0.4 --out /tmp/calibration.json

The ego: a random policy under the robust shield with override (episodes run their 40 s unless it crashes), episode
``k`` seeded ``--seed + k``. Every other car at every decision is one sample: its posterior on its true type against
the seconds it has been observed (all cars are seen from the reset: the fast simulator keeps the whole road) and
against its informative steps (:attr:`BeliefFilter.informative`); the reliability table bins every predicted
probability (each car, each type, each decision) and gives the frequency with which that type was the true one.
Prints the tables as markdown; ``--out`` writes them as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import numpy as np

from safelane.core.drivers import parse_driver_mix
from safelane.env.factory import make_env
from safelane.safety.belief import BeliefFilter

BINS = np.linspace(0.0, 1.0, 11)
"""Reliability bins of the predicted probability: [0, 0.1), …, [0.9, 1]."""
EPSILONS = (0.01, 0.001)
"""The belief shield's thresholds ε whose misses are counted: samples whose true type has posterior ≤ ε."""


class Tally:
    """One σ's running sums: P(true type) by seconds observed and by informative steps, the reliability bins."""

    def __init__(self, horizon: int, k: int) -> None:
        self.by_time = np.zeros((horizon + 1, 3))  # sum of p_true, count, argmax right
        self.by_steps = np.zeros((horizon + 1, 3))
        self.bins = np.zeros((len(BINS) - 1, 3))  # sum of predicted p, count, true-type hits
        self.ruled_out = np.zeros(len(EPSILONS))  # samples whose true type is at or below each ε
        self.samples = 0
        self.k = k

    def add(self, post: np.ndarray, truth: np.ndarray, cars: np.ndarray, t: int, informative: np.ndarray) -> None:
        p = post[cars]
        true = truth[cars]
        p_true = p[np.arange(cars.size), true]
        right = np.argmax(p, axis=1) == true
        for table, key in ((self.by_time, np.full(cars.size, t)), (self.by_steps, informative[cars])):
            np.add.at(table[:, 0], key, p_true)
            np.add.at(table[:, 1], key, 1.0)
            np.add.at(table[:, 2], key, right)
        self.ruled_out += (p_true[None, :] <= np.asarray(EPSILONS)[:, None]).sum(axis=1)
        self.samples += cars.size
        flat = p.ravel()
        hits = (np.arange(self.k)[None, :] == true[:, None]).ravel()
        b = np.clip(np.digitize(flat, BINS) - 1, 0, len(BINS) - 2)
        np.add.at(self.bins[:, 0], b, flat)
        np.add.at(self.bins[:, 1], b, 1.0)
        np.add.at(self.bins[:, 2], b, hits)

    def figures(self) -> dict[str, Any]:
        def rows(table: np.ndarray) -> list[dict[str, float]]:
            return [
                {"at": i, "samples": int(c), "mean_p_true": s / c, "argmax_right": r / c}
                for i, (s, c, r) in enumerate(table)
                if c > 0
            ]

        bins = [
            {"bin": f"[{BINS[i]:.1f}, {BINS[i + 1]:.1f})", "samples": int(c), "mean_predicted": s / c,
             "observed_frequency": h / c}
            for i, (s, c, h) in enumerate(self.bins) if c > 0
        ]  # fmt: skip
        n = self.bins[:, 1].sum()
        ece = float(sum(abs(s / c - h / c) * c for s, c, h in self.bins if c > 0) / n)
        ruled_out = {str(e): r / self.samples for e, r in zip(EPSILONS, self.ruled_out, strict=True)}
        return {"by_seconds_observed": rows(self.by_time), "by_informative_steps": rows(self.by_steps),
                "reliability": bins, "expected_calibration_error": ece, "true_type_ruled_out": ruled_out}  # fmt: skip


def run(episodes: int, seed: int, sigmas: list[float]) -> dict[str, Any]:
    """The figures of ``episodes`` episodes for each σ in ``sigmas`` [m/s²]."""
    env = make_env("hidden-types", simulator="fast", **{"shield.mode": "robust", "shield.override": True})
    mix = parse_driver_mix(env.safelane_config.traffic.driver_mix)  # type: ignore[attr-defined]
    horizon = int(env.safelane_config.env.get("duration", 40))  # type: ignore[attr-defined]
    tallies = {s: Tally(horizon + 1, len(mix.types)) for s in sigmas}
    filters = {s: BeliefFilter(mix, s) for s in sigmas}
    rng = np.random.default_rng(seed)
    start = time.perf_counter()
    for e in range(episodes):
        _, info = env.reset(seed=seed + e)
        snap = info["snapshot"]
        for f in filters.values():
            f.reset(snap)
        t = 0
        while True:
            cars = snap.others()
            for s, f in filters.items():
                tallies[s].add(f.posterior, snap.driver_type, cars, t, f.informative)
            _, _, term, trunc, info = env.step(int(rng.integers(5)))
            snap = info["snapshot"]
            t += 1
            for f in filters.values():
                f.update(snap)
            if term or trunc:
                break
    env.close()
    return {"episodes": episodes, "seed": seed, "mixture": list(mix.types), "prior": mix.probabilities.tolist(),
            "wall_time_s": time.perf_counter() - start,
            "sigmas": {str(s): tallies[s].figures() for s in sigmas}}  # fmt: skip


def markdown(result: dict[str, Any], every: int = 5) -> str:
    """The tables: mean P(true type) every ``every`` s observed per σ, and each σ's reliability bins."""
    sigmas = list(result["sigmas"])
    lines = ["| seconds observed | " + " | ".join(f"σ = {s}: P(true), argmax right" for s in sigmas) + " |",
             "|---|" + "---|" * len(sigmas)]  # fmt: skip
    tables = {s: {r["at"]: r for r in result["sigmas"][s]["by_seconds_observed"]} for s in sigmas}
    for t in sorted(tables[sigmas[0]]):
        if t % every:
            continue
        cells = [f"{tables[s][t]['mean_p_true']:.3f}, {tables[s][t]['argmax_right']:.3f}" for s in sigmas]
        lines.append(f"| {t} | " + " | ".join(cells) + f" |  <!-- {tables[sigmas[0]][t]['samples']} samples -->")
    for s in sigmas:
        fig = result["sigmas"][s]
        out = ", ".join(f"{float(r):.2e} at ε = {e}" for e, r in fig["true_type_ruled_out"].items())
        lines += ["", f"σ = {s} m/s²: expected calibration error {fig['expected_calibration_error']:.3f}; true type "
                  f"ruled out (posterior ≤ ε) in {out} of the car-decisions", "",
                  "| predicted | samples | mean predicted | observed frequency |", "|---|---|---|---|"]  # fmt: skip
        lines += [f"| {b['bin']} | {b['samples']} | {b['mean_predicted']:.3f} | {b['observed_frequency']:.3f} |"
                  for b in fig["reliability"]]  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sigmas", default="0.05,0.1,0.2,0.4", help="residual deviations σ [m/s²], comma-separated")
    parser.add_argument("--out", default=None, help="write the figures as JSON here")
    args = parser.parse_args(argv)
    result = run(args.episodes, args.seed, [float(s) for s in args.sigmas.split(",")])
    print(markdown(result))
    print(f"\n{args.episodes} episodes in {result['wall_time_s']:.0f} s")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(result, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
