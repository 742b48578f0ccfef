"""Episode frames with the action mask drawn under each, and the video they make.

:func:`draw_action_legend` appends to a frame a legend bar of the five meta-actions
(:data:`safelane.core.spaces.ACTION_NAMES`):

* a safe action is green, an unsafe one (``info["action_mask"][a]`` false) is grey;
* the action the policy chose in that state is blue, or red if it was unsafe;
* if the environment executed another action (``info["executed_action"]`` from a shield override,
  else highway-env's ``info["action"]``), that one is outlined in yellow.

Without an ``action_mask`` in ``info`` (no shield), every action is drawn safe. Boxes are drawn with
numpy; their labels, and a caption with the decision index, ego speed and any collision, with Pillow
when it can be imported (imageio depends on it). The caption also keeps consecutive frames distinct,
which GIF writers would otherwise merge. :func:`write_video` writes the frames as a GIF or MP4.
Playing the episode that gives the frames is :func:`safelane.running.episode_video.render_episode`'s.
"""

from __future__ import annotations

import importlib.util
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from safelane.config import ConfigError
from safelane.core.spaces import ACTION_NAMES, N_ACTIONS

LEGEND_HEIGHT = 28
"""Height [px] of the legend bar appended under each frame."""
BOX_GAP = 2
"""Gap [px] between and around legend boxes."""
OUTLINE_WIDTH = 3
"""Width [px] of the outline marking an executed action that differs from the chosen one."""

BACKGROUND = (30, 30, 30)
SAFE_COLOUR = (60, 150, 80)
UNSAFE_COLOUR = (140, 140, 140)
CHOSEN_COLOUR = (40, 100, 220)
CHOSEN_UNSAFE_COLOUR = (210, 50, 50)
EXECUTED_OUTLINE = (250, 210, 40)
TEXT_COLOUR = (255, 255, 255)

SHORT_NAMES: tuple[str, ...] = ("LEFT", "IDLE", "RIGHT", "FASTER", "SLOWER")
"""Legend labels, in :data:`ACTION_NAMES` order."""
assert len(SHORT_NAMES) == len(ACTION_NAMES)

VIDEO_EXTENSIONS = (".gif", ".mp4")


def legend_box(width: int, action: int) -> tuple[int, int]:
    """Horizontal extent ``[x0, x1)`` [px] of ``action``'s box in a legend of ``width`` pixels.

    The box spans rows ``[BOX_GAP, LEGEND_HEIGHT − BOX_GAP)`` of the legend bar, i.e. rows
    ``frame_height + BOX_GAP …`` of the composed frame.
    """
    if not 0 <= action < N_ACTIONS:
        raise ValueError(f"action: must be in [0, {N_ACTIONS}), got {action}")
    cell = width / N_ACTIONS
    return round(action * cell) + BOX_GAP, round((action + 1) * cell) - BOX_GAP


def mask_of(info: dict[str, Any]) -> np.ndarray:
    """``info["action_mask"]`` as 5 booleans (True = safe); all True when absent."""
    mask = info.get("action_mask")
    if mask is None:
        return np.ones(N_ACTIONS, dtype=bool)
    mask = np.asarray(mask, dtype=bool).ravel()
    if mask.size != N_ACTIONS:
        raise ValueError(f"info['action_mask']: expected {N_ACTIONS} entries, got {mask.size}")
    return mask


def executed_of(info: dict[str, Any]) -> int | None:
    """The action the environment executed, as reported in a step's ``info``, if any."""
    for key in ("executed_action", "action"):
        value = info.get(key)
        if isinstance(value, int | np.integer) and 0 <= int(value) < N_ACTIONS:
            return int(value)
    return None


def draw_action_legend(
    frame: np.ndarray,
    mask: Sequence[bool] | np.ndarray,
    chosen: int | None = None,
    executed: int | None = None,
    caption: str | None = None,
) -> np.ndarray:
    """``frame`` (H, W, 3) uint8 with a legend bar of the five actions appended below it.

    ``mask[a]`` true means action ``a`` is safe (green), false unsafe (grey); ``chosen`` is filled blue
    (red when unsafe); ``executed``, when given and different from ``chosen``, is outlined in yellow.
    ``caption`` (e.g. the step and speed) is written in the frame's top-left corner. Returns a new
    (H + LEGEND_HEIGHT, W, 3) array; ``frame`` is not modified.
    """
    frame = np.asarray(frame)
    if frame.ndim != 3 or frame.shape[2] < 3:
        raise ValueError(f"frame: expected (H, W, 3) RGB, got shape {frame.shape}")
    mask = np.asarray(mask, dtype=bool)
    width = frame.shape[1]
    bar = np.empty((LEGEND_HEIGHT, width, 3), dtype=np.uint8)
    bar[:] = BACKGROUND
    top, bottom = BOX_GAP, LEGEND_HEIGHT - BOX_GAP
    for a in range(N_ACTIONS):
        x0, x1 = legend_box(width, a)
        if a == chosen:
            colour = CHOSEN_COLOUR if mask[a] else CHOSEN_UNSAFE_COLOUR
        else:
            colour = SAFE_COLOUR if mask[a] else UNSAFE_COLOUR
        bar[top:bottom, x0:x1] = colour
        if executed is not None and a == executed and executed != chosen:
            w = OUTLINE_WIDTH
            bar[top : top + w, x0:x1] = EXECUTED_OUTLINE
            bar[bottom - w : bottom, x0:x1] = EXECUTED_OUTLINE
            bar[top:bottom, x0 : x0 + w] = EXECUTED_OUTLINE
            bar[top:bottom, x1 - w : x1] = EXECUTED_OUTLINE
    out = np.concatenate([frame[:, :, :3].astype(np.uint8), bar], axis=0)
    _write_text(out, frame.shape[0], caption)
    return out


def _write_text(image: np.ndarray, frame_height: int, caption: str | None) -> None:
    """Write the action names centred in their boxes and ``caption`` top-left, in place.

    A no-op without Pillow (the boxes alone still show the mask).
    """
    try:
        from PIL import Image, ImageDraw, ImageFont
    except ImportError:  # pragma: no cover - Pillow ships with imageio
        return
    pil = Image.fromarray(image)
    draw = ImageDraw.Draw(pil)
    font = ImageFont.load_default()
    for a, name in enumerate(SHORT_NAMES):
        x0, x1 = legend_box(image.shape[1], a)
        left, top, right, bottom = draw.textbbox((0, 0), name, font=font)
        x = (x0 + x1 - (right - left)) / 2 - left
        y = frame_height + (LEGEND_HEIGHT - (bottom - top)) / 2 - top
        draw.text((x, y), name, fill=TEXT_COLOUR, font=font)
    if caption:
        left, top, right, bottom = draw.textbbox((4, 4), caption, font=font)
        draw.rectangle((left - 3, top - 3, right + 3, bottom + 3), fill=BACKGROUND)
        draw.text((4, 4), caption, fill=TEXT_COLOUR, font=font)
    image[:] = np.asarray(pil)


def caption_of(step: int, info: dict[str, Any]) -> str:
    """``t=<decision>  v=<ego speed> m/s`` and, after a crash, ``COLLISION``."""
    text = f"t={step}"
    if "speed" in info:
        text += f"  v={float(info['speed']):.1f} m/s"
    if info.get("collision") or info.get("crashed"):
        text += "  COLLISION"
    return text


def mp4_writer_available() -> bool:
    """Whether imageio can write MP4 here (it needs the ``imageio-ffmpeg`` package)."""
    return importlib.util.find_spec("imageio_ffmpeg") is not None


def write_video(frames: list[np.ndarray], out_path: Path, fps: float) -> None:
    import imageio.v2 as imageio

    if out_path.suffix.lower() == ".gif":
        imageio.mimsave(out_path, frames, duration=1000.0 / fps, loop=0)
        return
    # libx264/yuv420p needs even sizes: pad by one black row/column rather than let imageio resize.
    h, w = frames[0].shape[:2]
    pad = ((0, h % 2), (0, w % 2), (0, 0))
    imageio.mimsave(out_path, [np.pad(f, pad) for f in frames], fps=fps, macro_block_size=1)


def check_out_path(out_path: Path) -> None:
    """Fail early, in one line, unless a video can be written at ``out_path``.

    Checks the extension, then creates the directory (as the write would) and writes a temporary
    probe file in it, so an unwritable place (``/proc``, a read-only mount, a file in the way) is a
    :class:`ConfigError` before the episode is played rather than an error while saving.
    """
    suffix = out_path.suffix.lower()
    if suffix not in VIDEO_EXTENSIONS:
        raise ConfigError(f"out_path: unsupported video extension {suffix!r}; use .gif (or .mp4)")
    if suffix == ".mp4" and not mp4_writer_available():
        raise ConfigError("out_path: .mp4 needs the imageio-ffmpeg package, not installed; use .gif")
    if out_path.is_dir():
        raise ConfigError(f"out_path: {out_path} is a directory; give a file name ending in {suffix}")
    directory = out_path.parent
    if directory.exists() and not directory.is_dir():
        raise ConfigError(f"out_path: {directory} is a file, not a directory; choose a writable directory")
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError as err:
        reason = err.strerror or type(err).__name__
        raise ConfigError(
            f"out_path: cannot write a file in {directory} ({reason}); choose a writable directory"
        ) from None
