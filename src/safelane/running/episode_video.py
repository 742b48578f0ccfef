"""Episode videos: one episode played and written, each frame with the action mask drawn under it.

:func:`render_episode` plays one episode with highway-env's ``render_mode="rgb_array"`` (offscreen,
``SDL_VIDEODRIVER=dummy``), one frame per decision, each with the legend bar of
:func:`safelane.reporting.render.draw_action_legend` (the mask, the chosen and the executed action), and
writes them with :func:`safelane.reporting.render.write_video`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from safelane.config import SafelaneConfig
from safelane.env.factory import make_env, resolve_env_config
from safelane.reporting.render import caption_of, check_out_path, draw_action_legend, executed_of, mask_of, write_video
from safelane.running.policies import Policy


class RenderedEpisode(NamedTuple):
    """What :func:`render_episode` wrote."""

    path: Path
    frames: int
    """Frames rendered: decisions + 1 (the last state). A GIF writer merges identical consecutive
    frames into one longer frame, so a GIF read back may hold fewer."""


def _open_env(env: Any) -> tuple[Any, bool]:
    """The rgb_array env to render and whether this module owns (and must close) it."""
    if isinstance(env, SafelaneConfig | str):
        cfg = resolve_env_config(env)
        if cfg.simulator == "fast":  # it does not draw; highway-env plays the same episode, bit for bit
            cfg = cfg.model_copy(update={"simulator": "highway-env"})
        return make_env(cfg, render_mode="rgb_array"), True
    if hasattr(env, "step") and hasattr(env, "reset"):
        owned = False
    elif callable(env):
        env, owned = env(), True
    else:
        raise TypeError(f"env: expected a gymnasium Env, an env factory or a config, got {type(env)!r}")
    if getattr(env, "render_mode", None) != "rgb_array":
        mode = getattr(env, "render_mode", None)
        if owned:
            env.close()
        raise ValueError(
            f"env: render_mode must be 'rgb_array' (got {mode!r}); "
            "build it with safelane.make_env(cfg, render_mode='rgb_array')"
        )
    return env, owned


def _enable_drawing(env: Any) -> None:
    """Make highway-env actually draw under ``SDL_VIDEODRIVER=dummy``.

    highway-env 1.12's ``EnvViewer.__init__`` sets ``enabled = False`` when the driver is ``dummy``,
    and ``display()`` then draws nothing: every ``rgb_array`` frame is black. Drawing onto the
    viewer's pygame Surface works under the dummy driver, so the flag is switched back on.
    """
    base = env.unwrapped
    if getattr(base, "viewer", None) is None:
        env.render()  # creates the viewer
    viewer = getattr(base, "viewer", None)
    if viewer is not None and hasattr(viewer, "enabled"):
        viewer.enabled = True


def render_episode(
    env: Any,
    policy: Policy,
    seed: int,
    out_path: str | Path,
    max_steps: int | None = None,
    fps: float | None = None,
) -> RenderedEpisode:
    """Play one episode of ``policy`` and write it, with the action legend, to ``out_path``.

    ``env``: a gymnasium Env built with ``render_mode="rgb_array"``, a zero-argument factory returning
    one (closed afterwards), or a :class:`SafelaneConfig` / preset name passed to
    ``make_env(..., render_mode="rgb_array")`` (a ``simulator: fast`` config is drawn on highway-env,
    which plays the same episode). The env is reset with ``seed``; the episode runs until
    termination, truncation or ``max_steps`` decisions. Frame ``t`` shows the state before decision
    ``t`` with that state's mask, the chosen action and (if different) the executed one; the last frame
    shows the final state with no action chosen. ``fps`` defaults to the env's ``policy_frequency``
    (real time). ``out_path`` must end in ``.gif``, or ``.mp4`` when imageio-ffmpeg is installed
    (otherwise :class:`~safelane.config.ConfigError`, a ``ValueError``).
    """
    out_path = Path(out_path)
    check_out_path(out_path)
    if max_steps is not None and max_steps < 0:
        raise ValueError(f"max_steps: must be non-negative, got {max_steps}")
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    env, owned = _open_env(env)
    try:
        if fps is None:
            fps = float(getattr(env.unwrapped, "config", {}).get("policy_frequency", 1))
        if fps <= 0:
            raise ValueError(f"fps: must be positive, got {fps}")
        obs, info = env.reset(seed=seed)
        _enable_drawing(env)
        frames: list[np.ndarray] = []
        steps = 0
        done = False
        while not done and (max_steps is None or steps < max_steps):
            raw = np.asarray(env.render())
            mask, caption = mask_of(info), caption_of(steps, info)
            action = int(policy(obs, info))
            obs, _, terminated, truncated, info = env.step(action)
            executed = executed_of(info)
            frames.append(draw_action_legend(raw, mask, action, executed, caption))
            steps += 1
            done = bool(terminated or truncated)
        final = np.asarray(env.render())
        frames.append(draw_action_legend(final, mask_of(info), caption=caption_of(steps, info)))
    finally:
        if owned:
            env.close()
    out_path.parent.mkdir(parents=True, exist_ok=True)
    write_video(frames, out_path, fps)
    return RenderedEpisode(out_path, len(frames))
