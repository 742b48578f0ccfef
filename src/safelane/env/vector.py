"""Many environments stepped as one batch: ``make_vector_env`` (gymnasium) and ``sb3_vec_env`` (SB3).

:class:`SafelaneVectorEnv` is a ``gymnasium.vector.VectorEnv`` over ``num_envs`` copies of the paper's
environment (by default on the fast simulator). One ``step(actions)`` call steps them all and returns
the batch as arrays: observations ``(N, 26)``, rewards, terminations, truncations, and in ``infos``
one array per field — ``action_mask`` ``(N, 5)`` and the shield's ``fallback``, ``shield_intervened``,
``unsafe_action``, ``invariant_break``, ``executed_action``, plus ``speed`` [m/s] and ``collision`` (and, under the
``committed`` shield mode, ``plan_forced``, ``lapse``, ``lapse_in_model``).

Autoreset is gymnasium's ``SAME_STEP`` mode: an environment that finishes is reset inside the same
call, so the returned row is the *new* episode's first observation and mask; the finished episode's
last observation and mask are kept in ``infos["final_obs"]`` and ``infos["final_action_mask"]``
(rows valid where ``infos["_final_obs"]``), and its return and length in ``infos["episode"]``
(``r``, ``l``; rows valid where ``infos["_episode"]``), the way CleanRL's loops read them.

Seeding: ``reset(seed=S)`` resets environment ``i`` with ``S + i``; later autoresets continue each
environment's own generator, so the same seed gives the same batch of episodes.

On the fast simulator :func:`make_vector_env` returns a :class:`FastVectorEnv` (the same contract on
:class:`safelane.env.fast_batch.FastBatch`: every environment stepped, shielded and observed in two
numba calls); elsewhere, and for the few settings the batch does not run
(:func:`safelane.env.fast_batch.supports`), a :class:`SafelaneVectorEnv` over ``make_env`` copies.
"""

from __future__ import annotations

import functools
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from safelane.config import ConfigError, SafelaneConfig
from safelane.core.spaces import N_ACTIONS
from safelane.env.factory import make_env, resolve_env_config
from safelane.env.fast_batch import FastBatch, supports
from safelane.env.observations import OBS_SIZE

BOOL_INFO = ("collision", "fallback", "shield_intervened", "unsafe_action", "invariant_break")
"""Per-environment flags of a step, batched as bool arrays (False where the env does not report one)."""
COMMITTED_INFO = ("plan_forced", "lapse", "lapse_in_model")
"""The committed shield mode's flags of a step, batched like :data:`BOOL_INFO` when the environments report them."""
PROJECTION_INFO = ("projected", "projection_distance")
"""The shield for continuous actions' projection of a step (bool; normalised distance), batched when reported."""


class SafelaneVectorEnv(VectorEnv):
    """``num_envs`` safelane environments stepped in one call (see the module docstring)."""

    def __init__(self, envs: list[gym.Env]) -> None:
        if not envs:
            raise ConfigError("num_envs: must be >= 1 (got 0)")
        self.envs = envs
        self.num_envs = len(envs)
        self.single_observation_space = envs[0].observation_space
        self.single_action_space = envs[0].action_space
        # acceleration and steering (a Box) or a meta-action index (Discrete)
        self.continuous = isinstance(self.single_action_space, gym.spaces.Box)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}
        self.render_mode = None
        space = self.single_observation_space
        self._obs = np.zeros((self.num_envs, *space.shape), dtype=space.dtype)
        self._masks = np.ones((self.num_envs, N_ACTIONS), dtype=bool)
        self._returns = np.zeros(self.num_envs)
        self._lengths = np.zeros(self.num_envs, dtype=np.int64)

    def _mask_of(self, info: dict[str, Any]) -> np.ndarray:
        mask = info.get("action_mask")
        return np.ones(N_ACTIONS, dtype=bool) if mask is None else mask

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every environment (``seed``: environment ``i`` gets ``seed + i``, or a list of seeds)."""
        seeds = _seeds_of(seed, self.num_envs)
        speeds = np.zeros(self.num_envs)
        for i, (env, s) in enumerate(zip(self.envs, seeds, strict=True)):
            obs, info = env.reset(seed=s, options=options)
            self._obs[i] = obs
            self._masks[i] = self._mask_of(info)
            speeds[i] = float(info.get("speed", 0.0))
        self._returns[:] = 0.0
        self._lengths[:] = 0
        return self._obs.copy(), {"action_mask": self._masks.copy(), "speed": speeds}

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every environment with its action (shape ``(N,)``, with continuous actions ``(N, 2)``); finished
        ones are reset at once."""
        if self.continuous:
            actions = np.asarray(actions, dtype=np.float32).reshape(self.num_envs, *self.single_action_space.shape)
        else:
            actions = np.asarray(actions).reshape(self.num_envs)
        n = self.num_envs
        rewards = np.zeros(n)
        terminated = np.zeros(n, dtype=bool)
        truncated = np.zeros(n, dtype=bool)
        flags = {key: np.zeros(n, dtype=bool) for key in BOOL_INFO}
        committed = {key: np.zeros(n, dtype=bool) for key in COMMITTED_INFO}
        reported = False
        speeds = np.zeros(n)
        projected, distance = np.zeros(n, dtype=bool), np.zeros(n)
        executed = actions.copy() if self.continuous else np.asarray(actions, dtype=np.int64).copy()
        final_obs = np.zeros_like(self._obs)
        final_masks = np.zeros((n, N_ACTIONS), dtype=bool)
        episode_r = np.zeros(n)
        episode_l = np.zeros(n, dtype=np.int64)
        for i, env in enumerate(self.envs):
            obs, reward, term, trunc, info = env.step(actions[i] if self.continuous else int(actions[i]))
            rewards[i], terminated[i], truncated[i] = reward, term, trunc
            for key in BOOL_INFO:
                flags[key][i] = bool(info.get(key, False))
            reported = reported or "lapse" in info
            for key in COMMITTED_INFO:
                committed[key][i] = bool(info.get(key, False))
            speeds[i] = float(info.get("speed", 0.0))
            if not self.continuous:
                executed[i] = int(info.get("executed_action", actions[i]))
            elif "executed_action" in info:  # the shield for continuous actions: what it executed, and how far
                executed[i] = info["executed_action"]
                projected[i], distance[i] = bool(info["projected"]), float(info["projection_distance"])
            self._returns[i] += float(reward)
            self._lengths[i] += 1
            if term or trunc:
                final_obs[i] = obs
                final_masks[i] = self._mask_of(info)
                episode_r[i], episode_l[i] = self._returns[i], self._lengths[i]
                self._returns[i], self._lengths[i] = 0.0, 0
                obs, info = env.reset()
            self._obs[i] = obs
            self._masks[i] = self._mask_of(info)
        done = terminated | truncated
        infos: dict[str, Any] = {
            **flags,
            **(committed if reported else {}),
            **({"projected": projected, "projection_distance": distance} if self.continuous and reported else {}),
            "speed": speeds,
            "executed_action": executed,
            "action_mask": self._masks.copy(),
        }
        if done.any():
            infos.update(
                final_obs=final_obs,
                _final_obs=done.copy(),
                final_action_mask=final_masks,
                episode={"r": episode_r, "l": episode_l},
                _episode=done.copy(),
            )
        return self._obs.copy(), rewards, terminated, truncated, infos

    def action_masks(self) -> np.ndarray:
        """Masks of the current observations (bool, shape ``(N, 5)``; all True without a shield)."""
        return self._masks.copy()

    def close_extras(self, **kwargs: Any) -> None:
        """Close every environment."""
        for env in self.envs:
            env.close()


class FastVectorEnv(VectorEnv):
    """:class:`SafelaneVectorEnv`'s contract on a :class:`safelane.env.fast_batch.FastBatch`: the same rows,
    flags, autoresets and seeds, every environment stepped in two numba calls instead of a Python loop
    over wrapper stacks. ``envs``: the batch's :class:`safelane.sim.fast.env.FastHighwayEnv` objects."""

    def __init__(self, batch: FastBatch) -> None:
        self.batch = batch
        self.envs = batch.envs
        self.num_envs = batch.num_envs
        self.single_observation_space = gym.spaces.Box(-1.0, 1.0, shape=(OBS_SIZE,), dtype=np.float32)
        self.single_action_space = gym.spaces.Discrete(N_ACTIONS)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}
        self.render_mode = None
        self._rows = np.arange(self.num_envs, dtype=np.int64)
        self._returns = np.zeros(self.num_envs)
        self._lengths = np.zeros(self.num_envs, dtype=np.int64)

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every environment (``seed``: environment ``i`` gets ``seed + i``, or a list of seeds)."""
        if options:
            raise ValueError("reset(options=...) is not supported by the fast simulator")
        self.batch.reset_envs(self._rows, _seeds_of(seed, self.num_envs))
        self._returns[:] = 0.0
        self._lengths[:] = 0
        return self.batch.obs.copy(), {"action_mask": self.batch.masks.copy(), "speed": self.batch.speeds()}

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every environment with its action (shape ``(N,)``); finished ones are reset at once."""
        batch = self.batch
        out = batch.step(np.asarray(actions).reshape(self.num_envs), self._rows)
        self._returns += out.rewards
        self._lengths += 1
        done = out.terminated | out.truncated
        infos: dict[str, Any] = {
            "collision": out.collision,
            "fallback": out.fallback,
            "shield_intervened": out.shield_intervened,
            "unsafe_action": out.unsafe_action,
            "invariant_break": out.invariant_break,
            "speed": out.speed,
            "executed_action": out.executed,
        }
        if batch.committed:  # read before the finished rows restart
            flags = [batch.committed_info(i) for i in range(self.num_envs)]
            infos.update({key: np.array([f[key] for f in flags], dtype=bool) for key in COMMITTED_INFO})
        if done.any():
            infos.update(
                final_obs=np.where(done[:, None], batch.obs, 0.0).astype(batch.obs.dtype),
                _final_obs=done.copy(),
                final_action_mask=np.where(done[:, None], batch.masks, False),
                episode={"r": np.where(done, self._returns, 0.0), "l": np.where(done, self._lengths, 0)},
                _episode=done.copy(),
            )
            batch.reset_envs(np.flatnonzero(done))
            self._returns[done] = 0.0
            self._lengths[done] = 0
        infos["action_mask"] = batch.masks.copy()
        return batch.obs.copy(), out.rewards, out.terminated, out.truncated, infos

    def action_masks(self) -> np.ndarray:
        """Masks of the current observations (bool, shape ``(N, 5)``; all True without a shield)."""
        return self.batch.masks.copy()

    def close_extras(self, **kwargs: Any) -> None:
        """Close every environment."""
        self.batch.close()


def _seeds_of(seed: int | list[int | None] | None, num_envs: int) -> list[int | None]:
    """Per-environment seeds: ``seed + i``, None for all, or a list of ``num_envs`` seeds."""
    if seed is None or isinstance(seed, int):
        return [None if seed is None else seed + i for i in range(num_envs)]
    seeds = list(seed)
    if len(seeds) != num_envs:
        raise ConfigError(f"seed: a list of {num_envs} seeds (one per environment), got {len(seeds)}")
    return seeds


def make_vector_env(
    config: SafelaneConfig | str | None = "fast",
    num_envs: int = 8,
    seed: int | None = None,
    simulator: str | None = None,
    threads: int = 1,
    **overrides: Any,
) -> SafelaneVectorEnv | FastVectorEnv:
    """``num_envs`` copies of :func:`safelane.make_env`'s environment as one vector environment: a
    :class:`FastVectorEnv` on the fast simulator, else a :class:`SafelaneVectorEnv` (the same rows).

    ``config`` and ``overrides`` as for ``make_env``; ``simulator`` defaults to ``fast`` for a preset
    name (the point of a batch is speed) and to the config's own for a :class:`SafelaneConfig`. With
    ``seed`` the batch is reset once (environment ``i`` with ``seed + i``). ``threads``: numba threads
    sharing a :class:`FastVectorEnv`'s steps (:class:`safelane.env.fast_batch.FastBatch`; the same rows).
    """
    if not isinstance(num_envs, int) or num_envs < 1:
        raise ConfigError(f"num_envs: must be an integer >= 1 (got {num_envs!r})")
    if simulator is None and not isinstance(config, SafelaneConfig):
        simulator = "fast"
    if simulator is not None:
        overrides = {**overrides, "simulator": simulator}
    cfg = resolve_env_config(config, **overrides)
    vector: SafelaneVectorEnv | FastVectorEnv
    if supports(cfg) is None:
        vector = FastVectorEnv(FastBatch(cfg, num_envs, threads))
    else:
        vector = SafelaneVectorEnv([make_env(cfg) for _ in range(num_envs)])
    if seed is not None:
        vector.reset(seed=seed)
        vector.action_space.seed(seed)
    return vector


def sb3_vec_env(vector: SafelaneVectorEnv | FastVectorEnv) -> Any:
    """A Stable-Baselines3 ``VecEnv`` over ``vector`` (needs the optional ``stable-baselines3``):
    ``env_method("action_masks")`` gives each environment's mask, as sb3-contrib's ``MaskablePPO``
    asks for it; a finished episode's last observation is in ``infos[i]["terminal_observation"]``."""
    try:
        from stable_baselines3.common.vec_env import VecEnv
    except ImportError:
        raise ConfigError("sb3_vec_env: needs stable-baselines3 (pip install 'safelane[sb3]')") from None

    class SafelaneSB3VecEnv(VecEnv):
        """SB3's view of a :class:`SafelaneVectorEnv` (SB3's auto-reset convention is gymnasium's SAME_STEP)."""

        def __init__(self, vector: SafelaneVectorEnv | FastVectorEnv) -> None:
            self.vector = vector  # before VecEnv.__init__, which asks the environments for render_mode
            super().__init__(vector.num_envs, vector.single_observation_space, vector.single_action_space)
            self._actions = np.zeros(vector.num_envs, dtype=np.int64)

        def reset(self) -> np.ndarray:
            seeds = list(self._seeds)
            obs, _ = self.vector.reset(seed=seeds if any(s is not None for s in seeds) else None)
            self._reset_seeds()
            return obs

        def step_async(self, actions: np.ndarray) -> None:
            self._actions = np.asarray(actions)

        def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
            obs, rewards, terminated, truncated, infos = self.vector.step(self._actions)
            dones = terminated | truncated
            per_env: list[dict[str, Any]] = []
            for i in range(self.num_envs):
                info = {key: infos[key][i] for key in (*BOOL_INFO, "speed", "executed_action")}
                if dones[i]:
                    info["terminal_observation"] = infos["final_obs"][i]
                    info["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
                    info["episode"] = {"r": float(infos["episode"]["r"][i]), "l": int(infos["episode"]["l"][i])}
                per_env.append(info)
            return obs, rewards.astype(np.float32), dones, per_env

        def close(self) -> None:
            self.vector.close()

        def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
            if attr_name == "action_masks":  # each environment's mask, read from the batch's masks
                return [functools.partial(self._mask_of, i) for i in self._get_indices(indices)]
            return [self.vector.envs[i].get_wrapper_attr(attr_name) for i in self._get_indices(indices)]

        def _mask_of(self, i: int) -> np.ndarray:
            return self.vector.action_masks()[i]

        def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
            for i in self._get_indices(indices):
                self.vector.envs[i].set_wrapper_attr(attr_name, value)

        def env_method(self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any) -> list:
            if method_name == "action_masks":  # the batch's masks of the current observations
                masks = self.vector.action_masks()
                return [masks[i] for i in self._get_indices(indices)]
            return [
                self.vector.envs[i].get_wrapper_attr(method_name)(*method_args, **method_kwargs)
                for i in self._get_indices(indices)
            ]

        def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: Any = None) -> list[bool]:
            out = []
            for i in self._get_indices(indices):
                env, found = self.vector.envs[i], False
                while isinstance(env, gym.Wrapper):
                    found = found or isinstance(env, wrapper_class)
                    env = env.env
                out.append(found)
            return out

    return SafelaneSB3VecEnv(vector)
