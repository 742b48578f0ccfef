"""``safelane render``: one episode drawn to a GIF or MP4."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from safelane.cli.common import PresetOpt, SeedOpt, SetOpt, ShieldOpt, cli_errors, resolve_config
from safelane.config import ConfigError


@cli_errors
def render(
    run_dir: Path | None = typer.Argument(None, help="A trained run, instead of --policy.", metavar="RUN_DIR"),
    policy: Annotated[
        str | None, typer.Option("--policy", help="Fixed policy: random, idle, faster, slower, probe.")
    ] = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="Output file (.gif, or .mp4 with imageio-ffmpeg).")] = Path(
        "episode.gif"
    ),
    seed: SeedOpt = 0,
    preset: PresetOpt = "fast",
    sets: SetOpt = None,
    shield: ShieldOpt = None,
    max_steps: Annotated[int | None, typer.Option("--max-steps", help="Stop after this many decisions.")] = None,
) -> None:
    """Render one episode offscreen with the action mask and the chosen action drawn on each frame."""
    from safelane.running.episode_video import render_episode
    from safelane.running.policies import FIXED_POLICIES, fixed_policy

    if run_dir is not None:
        from safelane.running.run_directory import load_policy
        from safelane.running.runs import run_env_config

        cfg = run_env_config(run_dir, sets=sets, shield=shield)
        act = load_policy(run_dir)
    else:
        if policy is None or policy not in FIXED_POLICIES:
            raise ConfigError(f"--policy: give one of {', '.join(FIXED_POLICIES)} (or a RUN_DIR)")
        cfg = resolve_config(preset, sets, shield)
        if cfg.shield.mode != "none":
            cfg = resolve_config(preset, sets, shield, overrides={"shield.override": True})
        act = fixed_policy(policy, seed)
    if cfg.simulator == "fast":  # the renderer draws it on highway-env, which plays the same episode
        typer.echo("render: drawing on highway-env, which plays the fast simulator's episode", err=True)
    result = render_episode(cfg, act, seed, out, max_steps=max_steps)  # checks --out, then builds and closes the env
    typer.echo(f"wrote {result.path} ({result.frames} frames)")
