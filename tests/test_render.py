"""Episode videos: the legend bar's colours, and a real highway-env episode written to a GIF."""

from __future__ import annotations

import importlib.util
import itertools
import os
from pathlib import Path
from typing import Any

import gymnasium as gym
import imageio.v3 as iio
import numpy as np
import pytest

from safelane import ConfigError, make_env
from safelane.core.spaces import FASTER, IDLE, LANE_LEFT, LANE_RIGHT, SLOWER
from safelane.reporting import render
from safelane.reporting.render import (
    BOX_GAP,
    CHOSEN_COLOUR,
    CHOSEN_UNSAFE_COLOUR,
    EXECUTED_OUTLINE,
    LEGEND_HEIGHT,
    SAFE_COLOUR,
    UNSAFE_COLOUR,
    draw_action_legend,
    legend_box,
)
from safelane.running.episode_video import render_episode

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

TINY = {"env.vehicles_count": 5, "env.duration": 3}
FAKE_MASK = np.array([True, True, False, True, True])  # LANE_RIGHT unsafe


def fill_pixel(frame: np.ndarray, action: int, frame_height: int) -> np.ndarray:
    """A pixel inside ``action``'s legend box, near its top-left corner (clear of the label)."""
    x0, _ = legend_box(frame.shape[1], action)
    return frame[frame_height + BOX_GAP + 1, x0 + 1, :3].astype(int)


# --- the legend on a synthetic frame ---------------------------------------------------------------


def test_legend_colours_mark_mask_and_choice() -> None:
    frame = np.zeros((50, 500, 3), dtype=np.uint8)
    mask = [True, False, True, False, True]
    out = draw_action_legend(frame, mask, chosen=SLOWER)
    assert out.shape == (50 + LEGEND_HEIGHT, 500, 3)
    assert np.array_equal(out[:50], frame)
    assert tuple(fill_pixel(out, LANE_LEFT, 50)) == SAFE_COLOUR
    assert tuple(fill_pixel(out, IDLE, 50)) == UNSAFE_COLOUR
    assert tuple(fill_pixel(out, FASTER, 50)) == UNSAFE_COLOUR
    assert tuple(fill_pixel(out, SLOWER, 50)) == CHOSEN_COLOUR
    out = draw_action_legend(frame, mask, chosen=IDLE)
    assert tuple(fill_pixel(out, IDLE, 50)) == CHOSEN_UNSAFE_COLOUR  # chosen while unsafe: red


def test_legend_outlines_an_overridden_action() -> None:
    frame = np.zeros((10, 500, 3), dtype=np.uint8)
    out = draw_action_legend(frame, [True] * 5, chosen=FASTER, executed=SLOWER)
    assert tuple(fill_pixel(out, SLOWER, 10)) == EXECUTED_OUTLINE
    assert tuple(fill_pixel(out, FASTER, 10)) == CHOSEN_COLOUR
    same = draw_action_legend(frame, [True] * 5, chosen=FASTER, executed=FASTER)
    assert tuple(fill_pixel(same, FASTER, 10)) == CHOSEN_COLOUR  # no outline when not overridden


def test_legend_boxes_tile_the_width_without_overlap() -> None:
    boxes = [legend_box(600, a) for a in range(5)]
    assert boxes[0][0] == BOX_GAP and boxes[-1][1] == 600 - BOX_GAP
    assert all(a[1] < b[0] for a, b in itertools.pairwise(boxes))
    with pytest.raises(ValueError, match="action"):
        legend_box(600, 5)


# --- a real episode --------------------------------------------------------------------------------


class FakeMask(gym.Wrapper):
    """Adds a fixed ``info["action_mask"]``, as a shield would."""

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        info["action_mask"] = FAKE_MASK.copy()
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        info["action_mask"] = FAKE_MASK.copy()
        return obs, reward, terminated, truncated, info


def test_render_episode_writes_gif_with_mask(tmp_path: Path) -> None:
    seen_masks: list[np.ndarray] = []

    def idle(obs: np.ndarray, info: dict[str, Any]) -> int:
        seen_masks.append(info["action_mask"])
        return IDLE

    env = FakeMask(make_env("fast", render_mode="rgb_array", **TINY))
    path, n_frames = render_episode(env, idle, seed=0, out_path=tmp_path / "ep.gif", max_steps=3)
    env.close()

    assert path.exists()
    assert n_frames == 4  # 3 decisions + the final state
    assert len(seen_masks) == 3
    frames = iio.imread(path, index=None)
    assert frames.shape[0] >= 3
    height = frames.shape[1] - LEGEND_HEIGHT
    first = frames[0]
    # The scene is drawn (highway-env alone draws nothing under SDL_VIDEODRIVER=dummy): grey road,
    # white lane marks, the green ego.
    colours = {tuple(c) for c in first[:height].reshape(-1, 3)}
    assert len(colours) >= 3
    assert (100, 100, 100) in colours  # highway-env's road colour
    grey = fill_pixel(first, LANE_RIGHT, height)
    green = fill_pixel(first, LANE_LEFT, height)
    blue = fill_pixel(first, IDLE, height)
    assert not np.array_equal(grey, green)  # the unsafe action is drawn differently
    # GIF palettes may shift colours slightly
    assert np.abs(grey - UNSAFE_COLOUR).max() <= 8
    assert np.abs(green - SAFE_COLOUR).max() <= 8
    assert np.abs(blue - CHOSEN_COLOUR).max() <= 8


def test_render_episode_from_factory_and_config(tmp_path: Path) -> None:
    closed: list[bool] = []

    def factory() -> gym.Env:
        env = make_env("fast", render_mode="rgb_array", **TINY)
        original = env.close

        def close() -> None:
            closed.append(True)
            original()

        env.close = close  # type: ignore[method-assign]
        return env

    result = render_episode(factory, lambda obs, info: SLOWER, seed=1, out_path=tmp_path / "a.gif")
    assert closed == [True]
    assert result.frames == 4  # duration 3 s at 1 decision/s: 3 decisions, then truncation

    cfg = make_env("fast", **TINY).safelane_config
    result = render_episode(cfg, lambda obs, info: SLOWER, seed=1, out_path=tmp_path / "b.gif", max_steps=1)
    assert result.frames == 2
    # Without a shield there is no mask: every non-chosen action is drawn safe.
    frame = iio.imread(result.path, index=0)
    height = frame.shape[0] - LEGEND_HEIGHT
    for a in (LANE_LEFT, IDLE, LANE_RIGHT, FASTER):
        assert np.abs(fill_pixel(frame, a, height) - SAFE_COLOUR).max() <= 8


def test_render_episode_rejects_bad_output_and_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(ConfigError, match=r"\.gif"):
        render_episode("fast", lambda o, i: IDLE, seed=0, out_path=tmp_path / "ep.avi")
    monkeypatch.setattr(render, "mp4_writer_available", lambda: False)
    with pytest.raises(ConfigError, match=r"\.gif"):
        render_episode("fast", lambda o, i: IDLE, seed=0, out_path=tmp_path / "ep.mp4")
    env = make_env("fast", **TINY)  # no render_mode
    with pytest.raises(ValueError, match="rgb_array"):
        render_episode(env, lambda o, i: IDLE, seed=0, out_path=tmp_path / "ep.gif")
    assert not (tmp_path / "ep.gif").exists()


@pytest.mark.skipif(importlib.util.find_spec("imageio_ffmpeg") is None, reason="imageio-ffmpeg not installed")
def test_render_episode_mp4(tmp_path: Path) -> None:
    result = render_episode("fast", lambda o, i: IDLE, seed=0, out_path=tmp_path / "ep.mp4", max_steps=2)
    assert result.path.stat().st_size > 0
