"""Gymnasium ids of the paper's environment: ``gym.make("safelane/Highway-v0")`` and friends.

``import safelane`` registers four ids (:func:`register_envs`); gymnasium's ``"module:id"`` form imports the
package for a caller that has not, so ``gym.make("safelane:safelane/HighwayFast-v0")`` needs no import at all:

* ``safelane/Highway-v0`` — the paper's environment on highway-env, the reference simulator;
* ``safelane/HighwayFast-v0`` — the same environment on safelane's compiled simulator (``simulator: fast``,
  the same episodes as highway-env, checked by ``safelane sim check``; hundreds of times faster with the shield
  on, docs/results/speed.md; no rendering);
* ``safelane/HighwayContinuous-v0`` and ``safelane/HighwayContinuousFast-v0`` — the same road and traffic with the
  ego driven by acceleration and steering (``actions: continuous``), without a shield unless ``shield="committed"``
  (the shield for continuous actions, :class:`safelane.safety.control_shield.ControlShield`);
* ``safelane/HighwayHiddenTypes-v0`` and ``safelane/HighwayHiddenTypesFast-v0`` — the ``hidden-types`` preset: each
  other car's driver type drawn from timid, normal and aggressive IDM + MOBIL sets, hidden from the agent and the
  shield (the matched arm through ``config``: ``{"state": "paper-types"}``, ``{"traffic.shield_sees_types": True}``).
  Their keywords are the first two ids' but ``preset``.

Both take the same keywords, all optional (:func:`make_highway`): ``preset`` (``"fast"``: highway-fast-v0's
5 Hz physics; ``"paper"``: highway-v0's 15 Hz), ``shield`` (``"robust"``, ``"nominal"``, ``"committed"`` or ``"none"``),
``override`` (replace an unsafe chosen action by the closest safe one) and ``config`` (any other setting of
:class:`safelane.config.SafelaneConfig` as dotted keys or section dicts, e.g. ``{"env.lanes_count": 3}``).
The default shield is ``"robust"`` without override: every step reports ``info["action_mask"]`` and the
environment has ``action_masks()`` (sb3-contrib's MaskablePPO reads it), and every chosen action is executed.

``gym.make_vec(id, num_envs=N)`` returns :func:`safelane.make_vector_env`'s batch (gymnasium's
``vector_entry_point``): on the fast simulator every environment is stepped in two numba calls
(:class:`safelane.env.vector.FastVectorEnv`), with ``action_masks()`` of shape ``(N, 5)``.
"""

from __future__ import annotations

from typing import Any, get_args

import gymnasium as gym

from safelane.config import ConfigError, SafelaneConfig, ShieldConfig
from safelane.env.factory import make_env, resolve_env_config
from safelane.env.vector import FastVectorEnv, SafelaneVectorEnv, make_vector_env

ENV_IDS: dict[str, str] = {
    "safelane/Highway-v0": "highway-env",
    "safelane/HighwayFast-v0": "fast",
    "safelane/HighwayContinuous-v0": "highway-env",
    "safelane/HighwayContinuousFast-v0": "fast",
    "safelane/HighwayHiddenTypes-v0": "highway-env",
    "safelane/HighwayHiddenTypesFast-v0": "fast",
}
"""Each registered id and the simulator it runs on (the ``Continuous`` ids: acceleration and steering)."""
SHIELD_MODES: tuple[str, ...] = get_args(ShieldConfig.model_fields["mode"].annotation)
OWN_KEYS = ("simulator", "actions", "preset", "shield.mode", "shield.override")
"""Settings the id and the keywords own: ``config`` may not set them."""


def _flat_keys(config: dict[str, Any]) -> set[str]:
    """Dotted keys of a ``config`` dict given as dotted keys or section dicts."""
    keys: set[str] = set()
    for key, value in config.items():
        if isinstance(value, dict) and "." not in key:
            keys.update(f"{key}.{sub}" for sub in value)
        keys.add(key)
    return keys


def env_config(
    simulator: str,
    preset: str = "fast",
    shield: str = "robust",
    override: bool = False,
    config: dict[str, Any] | None = None,
    actions: str = "discrete",
) -> SafelaneConfig:
    """The :class:`SafelaneConfig` an id's keywords describe (a one-line :class:`ConfigError` on bad input)."""
    if shield not in SHIELD_MODES:
        raise ConfigError(f"shield: unknown shield '{shield}'; allowed: {', '.join(SHIELD_MODES)}")
    if not isinstance(override, bool):
        raise ConfigError(f"override: must be True or False (got {override!r})")
    if override and shield == "none":
        raise ConfigError("override: needs a shield to override with; give shield='robust', 'nominal' or 'committed'")
    if config is not None and not isinstance(config, dict):
        raise ConfigError(f"config: a dict of settings, e.g. {{'env.lanes_count': 3}} (got {type(config).__name__})")
    owned = sorted(_flat_keys(config or {}) & set(OWN_KEYS))
    if owned:
        raise ConfigError(
            f"config: '{owned[0]}' is chosen by the id or a keyword (simulator, actions: the id; "
            "preset, shield, override: keywords), not by config"
        )
    overrides = {
        **(config or {}), "simulator": simulator, "actions": actions, "shield.mode": shield, "shield.override": override
    }  # fmt: skip
    return resolve_env_config(preset, **overrides)


def make_highway(
    *,
    preset: str = "fast",
    shield: str = "robust",
    override: bool = False,
    config: dict[str, Any] | None = None,
    render_mode: str | None = None,
) -> gym.Env:
    """``safelane/Highway-v0``: the paper's environment on highway-env (:func:`safelane.make_env`)."""
    return make_env(env_config("highway-env", preset, shield, override, config), render_mode=render_mode)


def make_highway_fast(
    *,
    preset: str = "fast",
    shield: str = "robust",
    override: bool = False,
    config: dict[str, Any] | None = None,
    render_mode: str | None = None,
) -> gym.Env:
    """``safelane/HighwayFast-v0``: the paper's environment on the compiled simulator. It draws nothing:
    ``render_mode`` is accepted and ignored (SB3's ``make_vec_env`` asks every environment for ``rgb_array``),
    ``render()`` raises; ``safelane/Highway-v0`` renders the same episodes."""
    return make_env(env_config("fast", preset, shield, override, config))


def make_highway_vector(
    num_envs: int = 1,
    *,
    preset: str = "fast",
    shield: str = "robust",
    override: bool = False,
    config: dict[str, Any] | None = None,
    render_mode: str | None = None,
) -> SafelaneVectorEnv:
    """``gym.make_vec("safelane/Highway-v0", num_envs=N)``: ``N`` highway-env copies in one vector env."""
    if render_mode is not None:
        raise ConfigError("render_mode: a vector environment does not render; render one gym.make environment")
    cfg = env_config("highway-env", preset, shield, override, config)
    return make_vector_env(cfg, num_envs=num_envs)  # type: ignore[return-value]


def make_highway_fast_vector(
    num_envs: int = 1,
    *,
    preset: str = "fast",
    shield: str = "robust",
    override: bool = False,
    config: dict[str, Any] | None = None,
    render_mode: str | None = None,
) -> FastVectorEnv | SafelaneVectorEnv:
    """``gym.make_vec("safelane/HighwayFast-v0", num_envs=N)``: the batched fast simulator
    (:class:`safelane.env.vector.FastVectorEnv`; a loop over environments for the few settings it lacks)."""
    if render_mode is not None:
        raise ConfigError("render_mode: the fast simulator does not render; use safelane/Highway-v0 to render")
    return make_vector_env(env_config("fast", preset, shield, override, config), num_envs=num_envs)


def make_highway_continuous(
    *,
    preset: str = "fast",
    shield: str = "none",
    config: dict[str, Any] | None = None,
    render_mode: str | None = None,
) -> gym.Env:
    """``safelane/HighwayContinuous-v0``: the paper's road and traffic on highway-env, the ego driven by
    acceleration and steering (``actions: continuous``: highway-env's ContinuousAction, 28-number state,
    :class:`safelane.env.reward.ContinuousReward`). ``shield``: ``"none"`` or ``"committed"``, the shield for
    continuous actions (:class:`safelane.safety.control_shield.ControlShield`, projection by default; its other
    settings through ``config``, e.g. ``{"shield.intervention": "replacement"}``); the one-decision modes decide
    among meta-actions only (a one-line error)."""
    cfg = env_config("highway-env", preset, shield, False, config, actions="continuous")
    return make_env(cfg, render_mode=render_mode)


def make_highway_continuous_fast(
    *,
    preset: str = "fast",
    shield: str = "none",
    config: dict[str, Any] | None = None,
    render_mode: str | None = None,
) -> gym.Env:
    """``safelane/HighwayContinuousFast-v0``: :func:`make_highway_continuous` on the compiled simulator (the same
    episodes, ``safelane sim check``); ``render_mode`` accepted and ignored as for ``safelane/HighwayFast-v0``."""
    return make_env(env_config("fast", preset, shield, False, config, actions="continuous"))


def make_highway_continuous_vector(
    num_envs: int = 1,
    *,
    preset: str = "fast",
    shield: str = "none",
    config: dict[str, Any] | None = None,
    render_mode: str | None = None,
) -> SafelaneVectorEnv:
    """``gym.make_vec("safelane/HighwayContinuous-v0", num_envs=N)``: ``N`` environments in one vector env."""
    if render_mode is not None:
        raise ConfigError("render_mode: a vector environment does not render; render one gym.make environment")
    cfg = env_config("highway-env", preset, shield, False, config, actions="continuous")
    return make_vector_env(cfg, num_envs=num_envs)  # type: ignore[return-value]


def make_highway_continuous_fast_vector(
    num_envs: int = 1,
    *,
    preset: str = "fast",
    shield: str = "none",
    config: dict[str, Any] | None = None,
    render_mode: str | None = None,
) -> FastVectorEnv | SafelaneVectorEnv:
    """``gym.make_vec("safelane/HighwayContinuousFast-v0", num_envs=N)`` (a loop over fast environments: the
    batched kernels step meta-actions)."""
    if render_mode is not None:
        raise ConfigError("render_mode: the fast simulator does not render; use safelane/HighwayContinuous-v0")
    cfg = env_config("fast", preset, shield, False, config, actions="continuous")
    return make_vector_env(cfg, num_envs=num_envs)


HIDDEN_TYPES_PRESET = "hidden-types"
"""The preset of the ``HiddenTypes`` ids (docs/guides/hidden-types.md)."""


def make_highway_hidden_types(
    *,
    shield: str = "robust",
    override: bool = False,
    config: dict[str, Any] | None = None,
    render_mode: str | None = None,
) -> gym.Env:
    """``safelane/HighwayHiddenTypes-v0``: :func:`make_highway` on the ``hidden-types`` preset (highway-env)."""
    return make_highway(preset=HIDDEN_TYPES_PRESET, shield=shield, override=override, config=config,
                        render_mode=render_mode)  # fmt: skip


def make_highway_hidden_types_fast(
    *,
    shield: str = "robust",
    override: bool = False,
    config: dict[str, Any] | None = None,
    render_mode: str | None = None,
) -> gym.Env:
    """``safelane/HighwayHiddenTypesFast-v0``: :func:`make_highway_fast` on the ``hidden-types`` preset."""
    return make_highway_fast(preset=HIDDEN_TYPES_PRESET, shield=shield, override=override, config=config,
                             render_mode=render_mode)  # fmt: skip


def make_highway_hidden_types_vector(
    num_envs: int = 1,
    *,
    shield: str = "robust",
    override: bool = False,
    config: dict[str, Any] | None = None,
    render_mode: str | None = None,
) -> SafelaneVectorEnv:
    """``gym.make_vec("safelane/HighwayHiddenTypes-v0", num_envs=N)``: :func:`make_highway_vector` on the preset."""
    return make_highway_vector(num_envs, preset=HIDDEN_TYPES_PRESET, shield=shield, override=override, config=config,
                               render_mode=render_mode)  # fmt: skip


def make_highway_hidden_types_fast_vector(
    num_envs: int = 1,
    *,
    shield: str = "robust",
    override: bool = False,
    config: dict[str, Any] | None = None,
    render_mode: str | None = None,
) -> FastVectorEnv | SafelaneVectorEnv:
    """``gym.make_vec("safelane/HighwayHiddenTypesFast-v0", num_envs=N)``: :func:`make_highway_fast_vector` on the
    preset (the batched fast simulator for the hidden arm; a loop over environments for ``state: paper-types``)."""
    return make_highway_fast_vector(num_envs, preset=HIDDEN_TYPES_PRESET, shield=shield, override=override,
                                    config=config, render_mode=render_mode)  # fmt: skip


_ENTRY_POINTS = {
    "safelane/Highway-v0": ("make_highway", "make_highway_vector"),
    "safelane/HighwayFast-v0": ("make_highway_fast", "make_highway_fast_vector"),
    "safelane/HighwayContinuous-v0": ("make_highway_continuous", "make_highway_continuous_vector"),
    "safelane/HighwayContinuousFast-v0": ("make_highway_continuous_fast", "make_highway_continuous_fast_vector"),
    "safelane/HighwayHiddenTypes-v0": ("make_highway_hidden_types", "make_highway_hidden_types_vector"),
    "safelane/HighwayHiddenTypesFast-v0": ("make_highway_hidden_types_fast", "make_highway_hidden_types_fast_vector"),
}


def register_envs() -> None:
    """Register :data:`ENV_IDS` with gymnasium (idempotent: ids already registered are left as they are)."""
    for env_id, (single, vector) in _ENTRY_POINTS.items():
        if env_id in gym.registry:
            continue
        gym.register(
            id=env_id,
            entry_point=f"{__name__}:{single}",
            vector_entry_point=f"{__name__}:{vector}",
            # the environment ends its own episodes (``env.duration``): no TimeLimit on top
            max_episode_steps=None,
        )
