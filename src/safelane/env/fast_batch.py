"""Many fast-simulator environments stepped, shielded, observed and rewarded in two numba calls a decision.

:class:`FastBatch` holds ``N`` :class:`safelane.sim.fast.env.FastHighwayEnv` scenes in stacked arrays
(:func:`safelane.sim.fast.env.stacked_storage`). One :meth:`FastBatch.step` runs every scene's physics
in one numba call (:func:`safelane.sim.fast.kernels.simulate` per scene), then the paper's state, the
shield's mask (the compiled safety kernel, :data:`safelane.safety.one_decision.compiled.snapshot_kernel`), the
reward's forward speed and the crash flags of every scene in a second one. The ``committed`` shield mode keeps a
plan per environment: its :class:`~safelane.safety.committed.family.CommittedFamily` (compiled kernels, called once per
environment and decision) judges each scene after the second call. Around them only a few numpy
operations over the batch remain, where :func:`safelane.env.make_env`'s wrapper stack spends ~100 µs of
Python per environment and decision.

It is the same environment, not an approximation: row ``i`` after any sequence of resets and steps has
the observation, reward, flags, mask and fallback of ``make_env(config)`` driven the same way
(``tests/test_vector_env.py``, ``tests/test_evaluation.py``). Supported: the fast simulator with
``state`` ``paper`` or ``lanes``, any ``traffic.vehicles_behind`` and ``traffic.driver_mix``, no
``traffic.adversary``, and any shield mode on the compiled engine except nominal with the ``paper`` formula, the
committed mode without ``shield.redraw_uncertified`` (:func:`supports`);
:func:`safelane.env.vector.make_vector_env` falls back to a loop over ``make_env`` environments otherwise.

Used by :class:`safelane.env.vector.FastVectorEnv` (gymnasium's autoreset) and by the evaluation
runner (:func:`safelane.running.evaluation.run_episodes_fast_batch`: each episode on its own seed).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numba
import numpy as np
from numba import njit, prange

from safelane.config import ConfigError, SafelaneConfig
from safelane.core.errors import NotSupported
from safelane.core.kernel_cache import drop_stale_kernel_cache
from safelane.core.snapshot import DRIVER_FIELDS, RoadSnapshot
from safelane.core.spaces import N_ACTIONS
from safelane.env.observations import OBS_SIZE, lane_state_kernel, paper_state_kernel
from safelane.safety.committed.family import CommittedFamily, CommittedResult
from safelane.safety.one_decision.compiled import N_CONSTS, kernel_constants, snapshot_kernel
from safelane.safety.one_decision.reference import OVERRIDE_ORDER
from safelane.safety.shield import FALLBACK_SLOWDOWN, dynamics_of, ego_leave_time_of, ego_leave_times, with_mixture
from safelane.sim.fast import kernels as K
from safelane.sim.fast import layout as L
from safelane.sim.fast.env import FastHighwayEnv, stacked_storage


def _drop_stale_kernel_cache() -> None:
    """Drop numba's disk cache of this module's kernels when a kernel they compile in changed: the simulator's
    (its kernels, lanes, numerics and layout), the safety rule's (its parts, its forecast, its options' bits) and
    the observations' (:mod:`safelane.core.kernel_cache`)."""
    from safelane.env import observations
    from safelane.safety import rule
    from safelane.safety.one_decision import compiled, compiled_parts, compiled_rule, forecast
    from safelane.sim.fast import lanes, numerics

    safety = (compiled.__file__, compiled_rule.__file__, compiled_parts.__file__, forecast.__file__, rule.__file__)
    simulator = (K.__file__, lanes.__file__, L.__file__, numerics.__file__)
    drop_stale_kernel_cache(__file__, (*simulator, *safety, observations.__file__))


_drop_stale_kernel_cache()

STATE_KINDS = {"paper": 0, "lanes": 1}
"""The kernel's code for each ``SafelaneConfig.state``."""

_OVERRIDE = np.array([OVERRIDE_ORDER[a] for a in range(N_ACTIONS)], dtype=np.int64)


def supports(cfg: SafelaneConfig) -> str | None:
    """None when :class:`FastBatch` plays ``cfg``, else why not (one line)."""
    if cfg.simulator != "fast":
        return f"simulator: {cfg.simulator} (the batch steps the fast simulator)"
    if cfg.state not in STATE_KINDS:
        return f"state: {cfg.state}"
    action = cfg.env.get("action", {}).get("type", "DiscreteMetaAction")
    if action != "DiscreteMetaAction":
        return f"action.type: {action} (the batch runs meta-actions)"
    if cfg.traffic.adversary != "none":  # make_env refuses it on the fast simulator: so does the batch
        return f"traffic.adversary: {cfg.traffic.adversary} (the fast simulator places no adversary)"
    shield = cfg.shield
    if shield.mode == "committed" and shield.redraw_uncertified:
        return "shield.redraw_uncertified: true (the batch plays highway-env's spawns as they are)"
    if shield.mode in ("omniscient", "belief"):
        return f"shield.mode: {shield.mode} (the driver types' sets are read per environment)"
    mix = cfg.traffic.driver_mixture()
    if shield.mode == "robust" and mix is not None and mix.assumed is not None:
        return "shield.mode: robust with hidden driver types (the readings of the types are judged per environment)"
    if shield.mode in ("nominal", "robust") and shield.engine != "compiled":
        return f"shield.engine: {shield.engine} (the batch runs the compiled kernel)"
    if shield.mode == "nominal" and shield.formula == "paper":
        return "shield.formula: paper (eq. 12 is evaluated by the numpy reference only)"
    return None


@njit(cache=True, error_model="numpy")
def _simulate_one(i, F, G, E, ts, P, actions, frames, dt, n_lanes, before, after, rec):
    """``kernels.simulate`` for scene ``i`` with its action ``actions[i]``."""
    K.simulate(F[i], G[i], E[i], ts, P, actions[i], frames, dt, n_lanes, before[i], after[i], rec[i])


@njit(cache=True, error_model="numpy")
def _simulate_rows(F, G, E, ts, P, actions, frames, dt, n_lanes, before, after, rec, rows):
    """``kernels.simulate`` for every scene in ``rows`` with its action ``actions[i]``."""
    for r in range(rows.shape[0]):
        _simulate_one(rows[r], F, G, E, ts, P, actions, frames, dt, n_lanes, before, after, rec)


@njit(cache=True, error_model="numpy", parallel=True)
def _simulate_rows_threads(F, G, E, ts, P, actions, frames, dt, n_lanes, before, after, rec, rows):
    """:func:`_simulate_rows` with the scenes shared among numba's threads (each scene is independent)."""
    for r in prange(rows.shape[0]):
        _simulate_one(rows[r], F, G, E, ts, P, actions, frames, dt, n_lanes, before, after, rec)


@njit(cache=True, error_model="numpy")
def _observe_one(
    i, F, G, E, length, is_vehicle, can_change_lane, drivers, state_kind, lane_width, lanes_count,
    shielded, robust, leave_table, slowdown, speed_limit, origin, direction, lateral, lane_heading,
    ts, t, powers, tie_break, consts, flags,
    obs, masks, fallback, forward, crashed_ego, speed_ego, bad,
):  # fmt: skip
    """Scene ``i``: the agent's state into ``obs[i]``, the ego's forward and total speed [m/s] and crash
    flag, and with ``shielded`` the shield's mask and fallback (``bad[i]``: the ego's speed is not a
    number, so no leave time exists)."""
    n = F.shape[1]
    # The snapshot's per-step arrays, as FastHighwayEnv.snapshot copies them out of F and G.
    position = np.empty((n, 2))
    speed = np.empty(n)
    heading = np.empty(n)
    crashed = np.empty(n, dtype=np.bool_)
    lane = np.empty(n, dtype=np.int64)
    target_speed = np.empty(n)  # FastHighwayEnv.snapshot: the set-points of vehicles (NaN: other bodies)
    for k in range(n):
        target_speed[k] = F[i, k, L.TSPD] if is_vehicle[i, k] else np.nan
        position[k, 0] = F[i, k, L.X]
        position[k, 1] = F[i, k, L.Y]
        speed[k] = F[i, k, L.V]
        heading[k] = F[i, k, L.H]
        crashed[k] = G[i, k, L.CRASHED] != 0
        lane[k] = G[i, k, L.LANE]
    speed_ego[i] = speed[0]
    forward[i] = speed[0] * math.cos(heading[0])  # PaperReward: speed · cos(heading)
    crashed_ego[i] = crashed[0]
    if state_kind == 0:
        paper_state_kernel(position, speed, heading, is_vehicle[i], 0, obs[i])
    else:
        offset = F[i, 0, L.Y] - lane[0] * lane_width
        lane_state_kernel(
            position, speed, heading, lane, is_vehicle[i], 0, lanes_count, offset / lane_width,
            F[i, 0, L.TSPD], obs[i],
        )  # fmt: skip
    if not shielded:
        return
    # SafetyShield._ego_leave_time: the speed or set-point minus a fallback's slowdown, rounded
    # down to 0.5 m/s in [0, 40], looked up in the table of ego_leave_times.
    ego_speed = speed[0] * math.cos(heading[0] - lane_heading)
    target = F[i, 0, L.TSPD]
    if ego_speed != ego_speed or target != target:
        bad[i] = True
        return
    slowest = min(ego_speed, target) - slowdown
    top = leave_table.shape[0] - 1  # the table's last entry: the fastest speed it holds
    if slowest * 2 >= top:
        row = top
    elif slowest < 0.0:
        row = 0
    else:
        row = math.floor(slowest * 2)
    leave = leave_table[row]
    d = drivers[i]
    out = snapshot_kernel(
        position, speed, heading, length[i], crashed, d[0], d[1], can_change_lane[i], d[2], d[3], d[4],
        d[5], d[6], d[7], d[8], d[9], d[10], d[11], target_speed,
        0, lane[0], G[i, 0, L.TLANE], target, E[i, 0], origin, direction, lateral, lane_heading,
        speed_limit, ts, t, powers, tie_break, consts, flags, robust, leave,
    )  # fmt: skip
    masks[i] = out[0]
    fallback[i] = out[4]


@njit(cache=True, error_model="numpy")
def _observe_rows(rows, args):
    """:func:`_observe_one` for every scene in ``rows`` (``args``: its arguments after the scene)."""
    for r in range(rows.shape[0]):
        _observe_one(rows[r], *args)


@njit(cache=True, error_model="numpy", parallel=True)
def _observe_rows_threads(rows, args):
    """:func:`_observe_rows` with the scenes shared among numba's threads."""
    for r in prange(rows.shape[0]):
        _observe_one(rows[r], *args)


_FLOAT_DRIVERS = tuple(name for name in DRIVER_FIELDS if name != "can_change_lane")
"""The per-vehicle driver fields the kernel takes as one float table, in its argument order."""


class BatchStep(NamedTuple):
    """What :meth:`FastBatch.step` returns for the stepped rows (arrays in the order of ``rows``)."""

    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    collision: np.ndarray
    speed: np.ndarray
    """[m/s] the ego's speed after the step (``info["speed"]``)."""
    executed: np.ndarray
    fallback: np.ndarray
    shield_intervened: np.ndarray
    unsafe_action: np.ndarray
    invariant_break: np.ndarray


class FastBatch:
    """``num_envs`` environments of ``cfg`` (see the module docstring): reset one by one, stepped together.

    ``threads`` > 1 shares the scenes of a step among that many of numba's threads (the same numbers;
    numba's OpenMP layer is not fork-safe, so keep 1 in a process that forks workers afterwards).

    After :meth:`reset_env` / :meth:`step` the current state of environment ``i`` is ``obs[i]`` (its
    observation), ``masks[i]`` (the shield's mask; all True without a shield) and ``fallback[i]``.
    """

    def __init__(self, cfg: SafelaneConfig, num_envs: int, threads: int = 1) -> None:
        why = supports(cfg)
        if why is not None:
            raise NotSupported(f"{why}: not supported by the fast batch")
        if not isinstance(num_envs, int) or num_envs < 1:
            raise ConfigError(f"num_envs: must be an integer >= 1 (got {num_envs!r})")
        most = numba.config.NUMBA_NUM_THREADS
        if not isinstance(threads, int) or not 1 <= threads <= most:
            raise ConfigError(f"threads: must be an integer in 1..{most} (this machine's cores; got {threads!r})")
        self.threads = threads
        # Several threads: numba's parallel loop over the scenes (the same numbers: each is independent).
        self._simulate_rows = _simulate_rows_threads if threads > 1 else _simulate_rows
        self._observe_rows = _observe_rows_threads if threads > 1 else _observe_rows
        self.cfg = cfg
        self.num_envs = num_envs
        probe = self._make_env(None)
        n = 1 + probe.sim.vehicles_count
        self.storage = stacked_storage(num_envs, n)
        self.envs = [self._make_env(self.storage.row(i)) for i in range(num_envs)]
        self.sim = self.envs[0].sim
        self.P = self.envs[0].P
        self.state_kind = STATE_KINDS[cfg.state]
        shield = cfg.shield
        self.shielded = shield.mode != "none"
        self.robust = shield.mode == "robust"
        # The committed mode keeps a plan per environment: its family judges each state after the kernel ran.
        self.committed = shield.mode == "committed"
        self.families = [CommittedFamily(shield.engine) for _ in range(num_envs if self.committed else 0)]
        self.results: list[CommittedResult | None] = [None] * (num_envs if self.committed else 0)
        self._dynamics = None
        self.override = bool(shield.override)
        reward = cfg.reward
        self._reward = (float(reward.b), float(reward.c), float(reward.v_min), float(reward.v_max))
        self.period = 1 / self.sim.policy_frequency
        # Per-episode constants of each scene (driver models are drawn at reset).
        self.length = np.zeros((num_envs, n))
        self.is_vehicle = np.zeros((num_envs, n), dtype=bool)
        self.can_change_lane = np.zeros((num_envs, n), dtype=bool)
        self.drivers = np.zeros((num_envs, len(_FLOAT_DRIVERS), n))
        self._statics_set = np.zeros(num_envs, dtype=bool)
        # The current state of each scene.
        self.obs = np.zeros((num_envs, OBS_SIZE), dtype=np.float32)
        self.masks = np.ones((num_envs, N_ACTIONS), dtype=bool)
        self.fallback = np.zeros(num_envs, dtype=bool)
        self.times = np.zeros(num_envs)
        self._forward = np.zeros(num_envs)
        self._crashed = np.zeros(num_envs, dtype=bool)
        self._speed = np.zeros(num_envs)
        self._bad = np.zeros(num_envs, dtype=bool)
        self._actions = np.zeros(num_envs, dtype=np.int64)
        self._kernel_args: tuple | None = None

    def _make_env(self, storage: Any) -> FastHighwayEnv:
        try:
            return FastHighwayEnv(
                dict(self.cfg.env), self.cfg.env_id, storage=storage, vehicles_behind=self.cfg.traffic.vehicles_behind,
                driver_mix=self.cfg.traffic.driver_mixture(),
            )
        except ValueError as err:  # a highway-env option the fast simulator does not model
            raise NotSupported(str(err)) from None

    # --- resets ------------------------------------------------------------------------------------
    def reset_env(self, i: int, seed: int | None = None) -> None:
        """Reset environment ``i`` (``seed``: gymnasium's; None continues its own generator)."""
        self.reset_envs(np.array([i], dtype=np.int64), [seed])

    def reset_envs(self, rows: np.ndarray, seeds: list[int | None] | None = None) -> None:
        """Reset the environments ``rows`` (int array; ``seeds``: one per row, default None: each
        continues its own generator), then observe them all in one call."""
        for k, i in enumerate(rows.tolist()):
            _, info = self.envs[i].reset(seed=None if seeds is None else seeds[k])
            snap: RoadSnapshot = info["snapshot"]
            # The per-episode driver parameters (IDM's DELTA, the linear models' gains) are drawn at
            # reset; the other per-body constants depend on the configuration only.
            for row, name in enumerate(_FLOAT_DRIVERS):
                self.drivers[i, row] = getattr(snap, name)
            if not self._statics_set[i]:
                self.length[i] = snap.length
                self.is_vehicle[i] = snap.is_vehicle
                self.can_change_lane[i] = snap.can_change_lane
                self._statics_set[i] = True
            if self.committed:
                self.families[i].reset()
                if self._dynamics is None:
                    self._dynamics = dynamics_of(snap, self.cfg.shield.margin, self.cfg.shield.resolved_rule())
            elif self.shielded and self._kernel_args is None:
                self._kernel_args = self._shield_constants(snap)
        self.times[rows] = 0.0
        self._observe(rows)

    def _shield_constants(self, snap: RoadSnapshot) -> tuple:
        """The safety kernel's arguments that stay the same for the batch (SafetyShield's dynamics)."""
        shield = self.cfg.shield
        dyn = with_mixture(dynamics_of(snap, shield.margin, shield.resolved_rule()), self.cfg.traffic.driver_mixture())
        return (
            ego_leave_times(dyn), FALLBACK_SLOWDOWN, float(snap.speed_limit),
            *(_readonly(np.array(a, dtype=float)) for a in (snap.lane_origin, snap.lane_direction, snap.lane_lateral)),
            snap.lane_heading, *kernel_constants(dyn),
        )  # fmt: skip

    def reset_info(self, i: int) -> dict[str, Any]:
        """The ``info`` ``make_env(config).reset`` returns for environment ``i``'s current state."""
        snap = self.snapshot(i)
        info: dict[str, Any] = {
            "speed": float(self._speed[i]),
            "crashed": bool(self._crashed[i]),
            "snapshot": snap,
            "collision": bool(self._crashed[i]),
            "forward_speed": float(self._forward[i]),
            "state": self.cfg.state,
        }
        if self.shielded:
            info.update(action_mask=self.masks[i].copy(), fallback=bool(self.fallback[i]), shield_intervened=False)
        if self.committed:
            info.update(self.committed_info(i), uncertified_start=not self.results[i].certified)
        return info

    def committed_info(self, i: int) -> dict[str, Any]:
        """The committed mode's ``info`` keys of environment ``i``'s current state (``SafetyShield``'s)."""
        result = self.results[i]
        assert result is not None
        return result.info()

    def speeds(self) -> np.ndarray:
        """[m/s] Every ego's speed now (``info["speed"]``), shape ``(N,)``."""
        return self._speed.copy()

    def snapshot(self, i: int) -> RoadSnapshot:
        """Environment ``i``'s road snapshot now."""
        return self.envs[i].snapshot()

    # --- steps -------------------------------------------------------------------------------------
    def step(self, actions: np.ndarray, rows: np.ndarray) -> BatchStep:
        """Step the environments ``rows`` (int array) with ``actions`` (one per row, 0–4), as
        ``SafetyShield.step`` over ``PaperObservation`` / ``PaperReward`` / ``FastHighwayEnv`` does."""
        chosen = np.asarray(actions, dtype=np.int64)
        if chosen.shape != rows.shape or ((chosen < 0) | (chosen >= N_ACTIONS)).any():
            raise ValueError(f"actions: one action in 0..4 per stepped environment (got {actions!r})")
        m = rows.size
        if self.shielded:
            before_masks = self.masks[rows]
            promised = ~self.fallback[rows]
            allowed = before_masks[np.arange(m), chosen]
            executed = chosen.copy()
            if self.override:
                for j in np.flatnonzero(~allowed):  # the closest safe action (SafetyShield.step)
                    order = _OVERRIDE[chosen[j]]
                    executed[j] = order[np.argmax(before_masks[j][order])]
        else:
            executed = chosen
        for j, i in enumerate(rows.tolist() if self.committed else ()):  # each kept plan follows the action
            self.families[i].commit(int(executed[j]))
        self._actions[rows] = executed
        sc = self.sim
        st = self.storage
        if self.threads > 1:
            numba.set_num_threads(self.threads)
        self._simulate_rows(
            st.F, st.G, st.E, sc.target_speeds, self.P, self._actions, sc.frames, sc.dt, sc.lanes_count,
            st.before, st.after, st.rec, rows,
        )  # fmt: skip
        self.times[rows] += self.period
        for i in rows.tolist():  # the env objects keep their clocks (snapshots, get_state)
            env = self.envs[i]
            env.time = float(self.times[i])
            env.steps += sc.frames
        self._observe(rows)
        crashed = self._crashed[rows]
        terminated = crashed.copy()
        if sc.offroad_terminal:
            terminated |= np.array([not self.envs[i].on_road for i in rows.tolist()], dtype=bool)
        b, c, v_min, v_max = self._reward
        # PaperReward.reward_of, element by element: the same doubles
        scaled = np.minimum(np.maximum((self._forward[rows] - v_min) / (v_max - v_min), 0.0), 1.0)
        rewards = b * scaled - c * crashed.astype(float)
        if self.shielded:
            fallback = self.fallback[rows]
            intervened = executed != chosen
            unsafe = ~allowed
            breaks = promised & before_masks[np.arange(m), executed] & fallback
        else:
            fallback = intervened = unsafe = breaks = np.zeros(m, dtype=bool)
        return BatchStep(
            rewards, terminated, self.times[rows] >= sc.duration, crashed, self._speed[rows], executed,
            fallback, intervened, unsafe, breaks,
        )  # fmt: skip

    def _observe(self, rows: np.ndarray) -> None:
        st = self.storage
        shield_args = self._kernel_args
        if shield_args is None:  # no shield: the kernel's shield arguments are placeholders
            shield_args = (np.zeros(1), 0.0, 0.0, *_NO_FRAME, 0.0, *_NO_SHIELD)
        self._bad[rows] = False
        if self.threads > 1:
            numba.set_num_threads(self.threads)
        args = (
            st.F, st.G, st.E, self.length, self.is_vehicle, self.can_change_lane, self.drivers,
            self.state_kind, float(self.P[L.P_LANE_WIDTH]), self.sim.lanes_count, self.shielded and not self.committed,
            self.robust,
            *shield_args, self.obs, self.masks, self.fallback, self._forward, self._crashed, self._speed, self._bad,
        )  # fmt: skip
        self._observe_rows(rows, args)
        for i in rows.tolist() if self.committed else ():  # the committed family, environment by environment
            snap = self.snapshot(i)
            result = self.families[i].evaluate(snap, self._dynamics, ego_leave_time_of(snap, self._dynamics))
            self.results[i] = result
            self.masks[i], self.fallback[i] = result.mask, result.fallback
        if self.shielded and self._bad[rows].any():
            i = int(rows[np.argmax(self._bad[rows])])
            raise RuntimeError(f"fast batch: environment {i}'s ego speed is not a number; no mask exists")

    def close(self) -> None:
        """Close every environment."""
        for env in self.envs:
            env.close()


def _readonly(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


_NO_FRAME = tuple(_readonly(np.zeros(2)) for _ in range(3))
_NO_SHIELD = (
    _readonly(np.zeros(1)), _readonly(np.zeros(1)), _readonly(np.zeros(1)), np.zeros(1, dtype=np.int64),
    _readonly(np.zeros(N_CONSTS)), 0,
)  # fmt: skip
"""Placeholders of :class:`safelane.safety.one_decision.compiled.KernelConstants`'s fields when no shield runs (typed
as the real ones, so both cases share one compiled kernel)."""
