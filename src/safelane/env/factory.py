"""The paper's environment: a simulator, safelane's traffic options, the paper's state and reward, the shield.

``make_env`` builds ``gym.make(env_id, config=cfg.env)`` and layers, from the inside out:

1. :class:`safelane.sim.traffic.TrafficLayout` — safelane's traffic options (``traffic.*``: a mixture of
   driver types, vehicles behind the ego, an adversary) and the neighbour-search patch (``neighbour_search``);
2. :class:`safelane.sim.highway.HighwayEnvAdapter` — the road snapshot in ``info["snapshot"]``: every
   layer above reads the scene from it, never from highway-env's objects;
3. :class:`safelane.env.reward.PaperReward` — eq. 6 and the ``collision`` / ``speed`` info fields (with
   ``actions: continuous``, :class:`safelane.env.reward.ContinuousReward`);
4. :class:`safelane.env.observations.PaperObservation` — the paper's 26-number state (eq. 3), or the
   ``lanes`` state (with continuous actions eq. 3 and the ego's place in its lane: 28 numbers), or eq. 3 with the
   observed cars' driver types (``paper-types``) or posteriors over them (``paper-belief``), or eq. 3 of the last
   decisions (``paper-stack``); :func:`observation_size` says how many numbers without building the environment;
5. :class:`safelane.safety.shield.SafetyShield` — only when ``shield.mode`` is not ``none``;
6. :class:`safelane.env.redraw.RedrawUncertified` — the ``committed`` mode only: each reset reports the
   spawns drawn again (``shield.redraw_uncertified``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import gymnasium as gym
import highway_env  # noqa: F401  (registers highway-v0 / highway-fast-v0)
from highway_env.vehicle.controller import MDPVehicle

from safelane.config import (
    ConfigError,
    SafelaneConfig,
    apply_overrides,
    build_config,
    highway_env_defaults,
    load_config,
)
from safelane.core.errors import NotSupported
from safelane.core.snapshot import RoadSnapshot
from safelane.env.observations import PaperObservation, state_size
from safelane.env.redraw import RedrawUncertified
from safelane.env.reward import ContinuousReward, PaperReward
from safelane.safety.belief import DriverTypes
from safelane.safety.control_shield import ControlShield
from safelane.safety.shield import SafetyShield
from safelane.sim.highway import HighwayEnvAdapter
from safelane.sim.traffic import TrafficLayout


class EnvInterface(NamedTuple):
    """What a trained policy depends on: the state it reads, how often it decides, what its actions mean."""

    state: str
    """``paper`` (eq. 3), ``lanes``, or another ``SafelaneConfig.state``."""
    policy_frequency: float
    """[Hz] decisions per second."""
    target_speeds: tuple[float, ...]
    """[m/s] the ego's set-points, which FASTER and SLOWER step through (none with continuous actions)."""
    actions: str = "discrete"
    """``discrete`` (meta-actions) or ``continuous`` (acceleration and steering)."""

    def describe(self) -> str:
        """One-line description, e.g. ``state 'paper', 1 decisions/s, target speeds [20, 25, 30] m/s``."""
        if self.actions == "continuous":
            return f"state '{self.state}', {self.policy_frequency:g} decisions/s, continuous actions"
        speeds = ", ".join(f"{s:g}" for s in self.target_speeds)
        return f"state '{self.state}', {self.policy_frequency:g} decisions/s, target speeds [{speeds}] m/s"


def env_interface(cfg: SafelaneConfig) -> EnvInterface:
    """The :class:`EnvInterface` an environment built from ``cfg`` presents (highway-env's defaults filled in)."""
    defaults = highway_env_defaults(cfg.env_id)
    action = {**defaults.get("action", {}), **cfg.env.get("action", {})}
    speeds = action.get("target_speeds")
    if speeds is None:
        speeds = MDPVehicle.DEFAULT_TARGET_SPEEDS if cfg.actions == "discrete" else ()
    return EnvInterface(
        state=cfg.state,
        policy_frequency=float(cfg.env.get("policy_frequency", defaults["policy_frequency"])),
        target_speeds=tuple(float(s) for s in speeds),
        actions=cfg.actions,
    )


def observation_size(cfg: SafelaneConfig) -> int:
    """Numbers in the observation of an environment built from ``cfg`` (what an agent's network reads): 26 for
    the paper's state (:func:`safelane.env.observations.state_size`)."""
    mix = cfg.traffic.driver_mixture()
    return state_size(cfg.state, cfg.actions == "continuous", len(mix.types) if mix is not None else 0)


def interface_of(info: dict[str, Any]) -> EnvInterface | None:
    """The :class:`EnvInterface` of a running environment, from a step's ``info`` (None if it lacks one)."""
    snap: RoadSnapshot | None = info.get("snapshot")
    state = info.get("state")
    if snap is None or state is None:
        return None
    actions = "discrete" if snap.ego_target_speeds else "continuous"
    return EnvInterface(state, snap.policy_frequency, snap.ego_target_speeds, actions)


def check_same_interface(trained: EnvInterface, actual: EnvInterface, source: str = "the run") -> None:
    """Raise a one-line :class:`ConfigError` naming both interfaces unless they are equal."""
    if trained != actual:
        raise NotSupported(
            f"environment: {actual.describe()}, but {source} was trained with {trained.describe()}; "
            "a trained policy only drives the state kind, decision rate and action set it learned"
        )


def resolve_env_config(config: SafelaneConfig | str | None = None, **overrides: Any) -> SafelaneConfig:
    """``config`` (a :class:`SafelaneConfig`, a preset name or None for ``fast``) with ``overrides`` on top."""
    if config is None or isinstance(config, str):
        return load_config(config or "fast", overrides=overrides)
    if not overrides:
        return config
    data = config.model_dump()
    apply_overrides(data, overrides)
    return build_config(data)


def _highway_env(cfg: SafelaneConfig, render_mode: str | None) -> gym.Env:
    """highway-env itself, with safelane's traffic options and the snapshot adapter."""
    try:
        env = gym.make(cfg.env_id, config=dict(cfg.env), render_mode=render_mode)
    except (TypeError, ValueError, KeyError, AttributeError, ImportError) as err:
        raise ConfigError(f"env: highway-env rejected the configuration ({err})") from None
    env = TrafficLayout(
        env,
        cfg.traffic.vehicles_behind,
        vectorized=cfg.neighbour_search == "numpy",
        adversary=cfg.traffic.adversary,
        driver_mix=cfg.traffic.driver_mixture(),
    )
    return HighwayEnvAdapter(env)


def _fast_simulator(cfg: SafelaneConfig, render_mode: str | None) -> gym.Env:
    """safelane's compiled simulator of the same highway (it produces the snapshot itself)."""
    if render_mode is not None:
        raise NotSupported("simulator: fast does not render; use simulator=highway-env to render an episode")
    if cfg.traffic.adversary != "none":
        adversary = cfg.traffic.adversary
        raise NotSupported(
            f"traffic.adversary: '{adversary}' not supported by simulator=fast; allowed there: none "
            "(or use simulator=highway-env)"
        )
    from safelane.sim.fast.env import FastHighwayEnv

    try:
        return FastHighwayEnv(
            dict(cfg.env), cfg.env_id, vehicles_behind=cfg.traffic.vehicles_behind,
            driver_mix=cfg.traffic.driver_mixture(),
        )  # fmt: skip
    except ValueError as err:  # a highway-env option the fast simulator does not model
        raise NotSupported(str(err)) from None


def make_simulator(config: SafelaneConfig) -> gym.Env:
    """The simulator tier of :func:`make_env` alone, on ``config.simulator``: highway-env with safelane's traffic
    layout and the snapshot adapter, or the fast simulator; ``info["snapshot"]`` after every reset and step,
    the simulator's own reward and observation (none of safelane's layers, no shield)."""
    if config.simulator == "fast":
        return _fast_simulator(config, None)
    return _highway_env(config, None)


def make_env(
    config: SafelaneConfig | str | None = None,
    *,
    seed: int | None = None,
    render_mode: str | None = None,
    **overrides: Any,
) -> gym.Env:
    """Build the paper's environment on highway-env (``simulator: highway-env``) or on safelane's compiled
    simulator of the same highway (``simulator: fast``).

    ``config``: a :class:`SafelaneConfig`, a preset name (``"fast"``, default, or ``"paper"``) or None.
    ``overrides``: dotted keys or section dicts applied on top, e.g. ``make_env(env={"lanes_count": 5})``
    or ``make_env(**{"shield.mode": "robust"})``. With ``seed`` the env is reset once with that seed
    (gymnasium's seeding) and its action space is seeded, so the same seed gives the same episodes.
    """
    cfg = resolve_env_config(config, **overrides)
    env = _fast_simulator(cfg, render_mode) if cfg.simulator == "fast" else _highway_env(cfg, render_mode)
    reward = cfg.reward
    if cfg.actions == "continuous":
        env = ContinuousReward(env, reward.b, reward.c, reward.v_min, reward.v_max, reward.lane_centring)
    else:
        env = PaperReward(env, reward.b, reward.c, reward.v_min, reward.v_max)
    mix = cfg.traffic.driver_mixture()
    env = PaperObservation(env, cfg.state, continuous=cfg.actions == "continuous",
                           driver_types=len(mix.types) if mix is not None else 0, driver_mix=mix)  # fmt: skip
    if cfg.shield.mode != "none" and cfg.actions == "continuous":
        shield = cfg.shield
        env = ControlShield(env, shield.intervention, shield.margin, shield.resolved_rule(), shield.adaptation_penalty,
                            shield.engine)
        env = RedrawUncertified(env, shield.redraw_tries if shield.redraw_uncertified else 0)
    elif cfg.shield.mode != "none":
        shield = cfg.shield
        env = SafetyShield(
            env,
            mode=shield.mode,
            override=shield.override,
            margin=shield.margin,
            rule=shield.resolved_rule(),
            engine=shield.engine,
            formula=shield.formula,
            driver_types=None if mix is None else DriverTypes(mix, shield.belief_epsilon, shield.belief_sigma),
        )
        if shield.mode == "committed":  # its starts reported (redraws), redrawn if asked
            env = RedrawUncertified(env, shield.redraw_tries if shield.redraw_uncertified else 0)
    env.safelane_config = cfg  # type: ignore[attr-defined]
    if seed is not None:
        env.reset(seed=seed)
        env.action_space.seed(seed)
    return env
