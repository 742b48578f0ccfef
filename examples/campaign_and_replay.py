"""Run a tiny falsification campaign, then replay one of its counterexample files on both simulators.

What it shows: a campaign (``CampaignSpec`` + ``run_campaign``, the engine behind ``safelane falsify``) drives
the robust shield with override on over a small grid of traffic conditions, with policies that ignore the
shield (random, always FASTER), and saves every crash and every invariant break (a state with no safe action,
reached right after an allowed one) as a small replayable file. ``load_counterexample`` + ``replay`` play a
file again, decision by decision: first on the simulator that found it (the fast simulator), then on
highway-env itself, the reference; both must reach the same event at the same decision.

Run:
    python examples/campaign_and_replay.py                 # 8 cells x 20 episodes
    python examples/campaign_and_replay.py --quick         # 8 cells x 5 episodes
    python examples/campaign_and_replay.py --out runs/falsify/tiny --episodes 50

In the replay's log the five actions are L, I, R, F, S (LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER); "safe"
shows the shield's mask before each decision, "no safe action" whether the rule had to fall back.

Time: about 10 s as set, ``--quick`` about 5 s (the fast simulator; a replay on highway-env takes a second).
The same campaign from the command line: write the spec below as YAML (see ``configs/falsify/``) and run
``safelane falsify SPEC.yaml --out DIR``; ``safelane replay FILE --simulator highway-env`` replays a file.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from safelane.running.counterexamples import counterexample_files, load_counterexample, replay
from safelane.running.falsify import CampaignSpec, run_campaign

AGGRESSIVE = "highway_env.vehicle.behavior.AggressiveVehicle"


def tiny_campaign(episodes: int) -> CampaignSpec:
    """Two road widths x two densities of aggressive drivers x two policies: 8 cells."""
    return CampaignSpec(
        name="tiny",
        description="The robust shield, override on, in dense traffic of aggressive drivers.",
        preset="fast",
        simulator="fast",
        shield="robust",
        policies=["random", "faster"],
        episodes=episodes,
        axes={
            "lanes": [{"env.lanes_count": 2}, {"env.lanes_count": 3}],
            "density": [{"env.vehicles_density": 1.0}, {"env.vehicles_density": 2.0}],
            "drivers": [{"env.other_vehicles_type": AGGRESSIVE}],
        },
    )


def show_replay(path: str) -> None:
    """Replay ``path`` on the fast simulator and on highway-env; print its last decisions."""
    cx = load_counterexample(path)
    print(f"\n{Path(path).name}: {cx.kind} after decision {cx.step} (reset seed {cx.seed})")
    for simulator in ("fast", "highway-env"):
        result = replay(cx, simulator=simulator)
        print(f"  replayed on {simulator:11}: {'reproduced' if result.reproduced else 'NOT reproduced'}")
    names = "LIRFS"  # LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER
    print("  decision  chosen  executed  safe  no safe action (before -> after)")
    for d in result.decisions[-3:]:
        safe = "".join(n if m else "." for n, m in zip(names, d.mask, strict=True))
        chosen, executed = names[d.chosen], names[d.executed]
        print(f"  {d.step:>8}  {chosen:>6}  {executed:>8}  {safe}  {d.fallback_before!s:>5} -> {d.fallback_after}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="campaign directory (default: a temporary one)")
    parser.add_argument("--episodes", type=int, default=20, help="episodes per cell")
    parser.add_argument("--quick", action="store_true", help="5 episodes per cell")
    args = parser.parse_args()
    if args.quick:
        args.episodes = 5
    if args.episodes < 1:
        parser.error("--episodes: must be >= 1")

    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp) / "tiny"
        spec = tiny_campaign(args.episodes)
        summary = run_campaign(spec, out)
        print(
            f"campaign {spec.name}: {summary['episodes']} episodes, {summary['decisions']} decisions, "
            f"{summary['collisions']} collisions, {summary['invariant_breaks']} invariant breaks "
            f"(report: {out / 'summary.md'})"
        )
        found = [counterexample_files(out / "counterexamples", kind)[:1] for kind in ("invariant_break", "collision")]
        files = [path for paths in found for path in paths]
        if not files:
            print("no counterexample in this campaign: raise --episodes")
        for path in files:
            show_replay(path)


if __name__ == "__main__":
    main()
