"""The paper's environment: a simulator, safelane's traffic options, the paper's state and reward, the shield.

``make_env`` builds ``gym.make(env_id, config=cfg.env)`` and layers, from the inside out:

1. :class:`safelane.sim.traffic.TrafficLayout` — safelane's traffic options (``traffic.*``) and the
   neighbour-search patch (``neighbour_search``);
2. :class:`safelane.sim.highway.HighwayEnvAdapter` — the road snapshot in ``info["snapshot"]``: every
   layer above reads the scene from it, never from highway-env's objects;
3. :class:`safelane.env.reward.PaperReward` — eq. 6 and the ``collision`` / ``speed`` info fields;
4. :class:`safelane.env.observations.PaperObservation` — the paper's 26-number state (eq. 3), or the
   ``lanes`` state;
5. :class:`safelane.safety.shield.SafetyShield` — only when ``shield.mode`` is not ``none``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import highway_env  # noqa: F401  (registers highway-v0 / highway-fast-v0)

from safelane.config import ConfigError, SafelaneConfig, apply_overrides, build_config, load_config
from safelane.env.observations import PaperObservation
from safelane.env.reward import PaperReward
from safelane.safety.shield import SafetyShield
from safelane.sim.highway import HighwayEnvAdapter
from safelane.sim.traffic import TrafficLayout


def resolve_env_config(config: SafelaneConfig | str | None = None, **overrides: Any) -> SafelaneConfig:
    """``config`` (a :class:`SafelaneConfig`, a preset name or None for ``fast``) with ``overrides`` on top."""
    if config is None or isinstance(config, str):
        return load_config(config or "fast", overrides=overrides)
    if not overrides:
        return config
    data = config.model_dump()
    apply_overrides(data, overrides)
    return build_config(data)


def make_env(
    config: SafelaneConfig | str | None = None,
    *,
    seed: int | None = None,
    render_mode: str | None = None,
    **overrides: Any,
) -> gym.Env:
    """Build the paper's environment on highway-env.

    ``config``: a :class:`SafelaneConfig`, a preset name (``"fast"``, default, or ``"paper"``) or None.
    ``overrides``: dotted keys or section dicts applied on top, e.g. ``make_env(env={"lanes_count": 5})``
    or ``make_env(**{"shield.mode": "robust"})``. With ``seed`` the env is reset once with that seed
    (gymnasium's seeding) and its action space is seeded, so the same seed gives the same episodes.
    """
    cfg = resolve_env_config(config, **overrides)
    try:
        env = gym.make(cfg.env_id, config=dict(cfg.env), render_mode=render_mode)
    except (TypeError, ValueError, KeyError, AttributeError, ImportError) as err:
        raise ConfigError(f"env: highway-env rejected the configuration ({err})") from None
    env = TrafficLayout(
        env,
        cfg.traffic.vehicles_behind,
        vectorized=cfg.neighbour_search == "numpy",
        adversary=cfg.traffic.adversary,
    )
    env = HighwayEnvAdapter(env)
    env = PaperReward(env, cfg.reward.b, cfg.reward.c, cfg.reward.v_min, cfg.reward.v_max)
    env = PaperObservation(env, cfg.state)
    if cfg.shield.mode != "none":
        env = SafetyShield(env, mode=cfg.shield.mode, formula=cfg.shield.formula, override=cfg.shield.override)
    env.safelane_config = cfg  # type: ignore[attr-defined]
    if seed is not None:
        env.reset(seed=seed)
        env.action_space.seed(seed)
    return env
