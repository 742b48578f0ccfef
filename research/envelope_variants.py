"""Which worst-case bound is not nested in time? The same sampled falsification cells with one bound changed.

docs/research/falsification-campaign.md: a follower's bound "accelerate for ρ = 0.5 s, then brake" restarts at every
decision.
Making it longer (ρ = 0.5 s + one decision) should close that gap if it were the cause of the invariant
breaks; measured, it adds breaks instead (143 → 168 on 48 cells × 10 episodes, with the rule before
``shield.body_extent``).

    .venv/bin/python research/envelope_variants.py baseline --sample 48 --episodes 10 --out runs/hypo
    .venv/bin/python research/envelope_variants.py rho1.5 --sample 48 --episodes 10 --out runs/hypo

Runs in one process (the patched bound is a module attribute, so the cells must not go to workers).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import safelane.safety.shield as shield_module
from safelane.running.falsify.grid import load_campaign_spec, run_campaign

VARIANTS = ("baseline", "rho1.5", "rho_inf", "cutin_now")


def patch(variant: str) -> None:
    """Replace the shield's dynamics with one bound changed (``baseline``: unchanged)."""
    original = shield_module.dynamics_of

    def patched(snap: Any, *args: Any, **kwargs: Any) -> Any:  # the original's signature, passed through
        dyn = original(snap, *args, **kwargs)
        if variant == "rho1.5":  # the follower may accelerate one decision longer
            return dataclasses.replace(dyn, follower_reaction=0.5 + dyn.decision_period)
        if variant == "rho_inf":  # the follower never brakes within the horizon
            return dataclasses.replace(dyn, follower_reaction=1e6)
        if variant == "cutin_now":  # a cut-in reaches the lane at once
            return dataclasses.replace(dyn, cut_in_time=0.0)
        return dyn

    shield_module.dynamics_of = patched


def main() -> None:
    """Play the sampled cells of the shipped grid with the variant; print its totals as one JSON line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("variant", choices=VARIANTS)
    parser.add_argument("--sample", type=int, default=48)
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--out", type=Path, default=Path("runs/hypo"))
    args = parser.parse_args()
    patch(args.variant)
    spec = load_campaign_spec("configs/falsify/grid.yaml", {"sample": args.sample, "episodes": args.episodes})
    start = time.perf_counter()
    summary = run_campaign(spec, args.out / args.variant, workers=1)
    keys = ("episodes", "decisions", "collisions", "collision_contexts", "invariant_breaks", "break_classes")
    print(json.dumps({"variant": args.variant, **{k: summary[k] for k in keys}, "wall_s": time.perf_counter() - start}))


if __name__ == "__main__":
    main()
