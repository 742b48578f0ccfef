"""``FastHighwayEnv``: highway-env's ``highway-v0`` / ``highway-fast-v0`` on arrays, one numba call a decision.

Reward: highway-env's reward is not reproduced; :meth:`FastHighwayEnv.step` returns ``0.0`` (safelane
computes its own reward from ``info["snapshot"]``). Observation: a placeholder ``zeros((2,), float32)``
(safelane builds its observations from the snapshot as well).

Everything else follows highway-env: ``reset(seed)`` builds the same scene from the same random draws
(:mod:`safelane.sim.fast.scene`), ``step(action)`` runs ``int(simulation_frequency // policy_frequency)``
frames exactly as ``AbstractEnv._simulate`` (:func:`safelane.sim.fast.kernels.simulate`), ``time``
advances by ``1 / policy_frequency`` a step, ``terminated`` = ego crashed (or off-road when
``offroad_terminal``), ``truncated`` = ``time >= duration``.

Actions: ``DiscreteMetaAction`` (an ``MDPVehicle`` ego, ``Discrete(5)``) or ``ContinuousAction`` with
``dynamical: False`` (a kinematic ``Vehicle`` ego, ``Box(-1, 1, (size,), float32)``;
:mod:`safelane.sim.fast.continuous`). Its snapshot has no set-points: ``ego_target_speed``, ``ego_kp`` and
the ego's ``target_speed`` NaN, ``ego_speed_index`` -1, ``ego_target_speeds`` ().

Supported: any ``action.target_speeds`` (2 or more, last != first), ``lanes_count``, ``vehicles_count``,
``vehicles_density``, ``ego_spacing``, ``initial_lane_id``, ``duration``, ``policy_frequency``,
``simulation_frequency``, ``offroad_terminal``, ``other_vehicles_type`` in
:data:`safelane.sim.fast.scene.OTHER_VEHICLE_TYPES` (IDMVehicle; LinearVehicle, AggressiveVehicle,
DefensiveVehicle). Any other setting that changes the dynamics raises ValueError naming it
(:func:`safelane.sim.fast.scene.resolve_config`); rendering, reward and observation settings are accepted
and have no effect. ``vehicles_behind`` (safelane's ``traffic.vehicles_behind``, not a highway-env
setting) moves that many vehicles behind the ego at reset as :class:`safelane.sim.traffic.TrafficLayout`
does on highway-env (:func:`safelane.sim.fast.scene.spawn_behind`). ``driver_mix`` (``traffic.driver_mix``) draws
each other car's driver type at spawn as :func:`safelane.sim.drivers.install_driver_mix` does on highway-env, and its
snapshot reports each car's ``driver_type`` and (unless the mixture lets the shield see the types) the assumed
type's driver parameters, as :func:`safelane.sim.highway.snapshot_of` does.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar, NamedTuple

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle

from safelane.core.drivers import DriverMix
from safelane.core.snapshot import RoadSnapshot
from safelane.sim.drivers import assumed_class
from safelane.sim.fast import continuous as C
from safelane.sim.fast import kernels as K
from safelane.sim.fast import layout as L
from safelane.sim.fast.lanes import on_lane
from safelane.sim.fast.scene import SPEED_LIMIT, build_scene, params, resolve_config, spawn_behind

ACTIONS = {0: "LANE_LEFT", 1: "IDLE", 2: "LANE_RIGHT", 3: "FASTER", 4: "SLOWER"}
_SNAPSHOT_FIELDS = (
    "time", "policy_frequency", "simulation_frequency", "lanes_count", "lane_width", "lane_origin",
    "lane_direction", "lane_lateral", "speed_limit", "ego", "ego_target_speed", "ego_speed_index",
    "ego_target_speeds", "ego_kp", "ego_lane_offset", "position", "speed", "heading", "target_speed", "lane",
    "target_lane",
    "length", "width", "crashed", "is_vehicle", "brake_max", "accel_max", "can_change_lane", "idm_delta",
    "idm_comfort_acc", "idm_comfort_dec", "idm_distance_wanted", "idm_time_wanted", "max_braking_imposed",
    "impact_before", "impact_after", "linear_speed_gain", "linear_speed_difference_gain", "linear_distance_gain",
    "politeness", "driver_type",
)  # fmt: skip
_MODEL_FIELDS = (
    "brake_max", "accel_max", "idm_comfort_acc", "idm_comfort_dec", "idm_distance_wanted", "idm_time_wanted",
    "max_braking_imposed", "politeness",
)  # fmt: skip
"""The snapshot's driver fields that are a driver class's constants (:func:`_model_row`)."""


def _model_row(cls: type) -> np.ndarray:
    """An other vehicle of class ``cls``: its :data:`_MODEL_FIELDS`, then 1.0 for the linear model (else 0.0), as
    :func:`safelane.sim.highway.snapshot_of` reads them (IDM's ``COMFORT_ACC_MAX`` as the highest acceleration of an
    IDM driver, ``ACC_MAX`` of a linear one; MOBIL's braking criterion with either model)."""
    idm_formula = cls.acceleration is IDMVehicle.acceleration
    acc_max = float(getattr(cls, "ACC_MAX", IDMVehicle.ACC_MAX))
    return np.array([
        acc_max, float(cls.COMFORT_ACC_MAX) if idm_formula else acc_max, float(cls.COMFORT_ACC_MAX),
        float(cls.COMFORT_ACC_MIN), float(cls.DISTANCE_WANTED), float(cls.TIME_WANTED),
        float(cls.LANE_CHANGE_MAX_BRAKING_IMPOSED), float(cls.POLITENESS), 0.0 if idm_formula else 1.0,
    ])  # fmt: skip


_EGO_ROW = np.array([
    float(IDMVehicle.ACC_MAX), float(IDMVehicle.ACC_MAX), float(IDMVehicle.COMFORT_ACC_MAX),
    float(IDMVehicle.COMFORT_ACC_MIN), float(IDMVehicle.DISTANCE_WANTED), float(IDMVehicle.TIME_WANTED), np.inf,
    0.0, 0.0,
])  # fmt: skip
"""The ego's :func:`_model_row` (an MDPVehicle or a Vehicle: IDM's defaults, no MOBIL)."""


class SimState(NamedTuple):
    """Everything :meth:`FastHighwayEnv.step` reads or writes (copies): the per-vehicle float and integer
    arrays, the ego's set-point index, the clock [s], the frame count, and the last crash's record."""

    F: np.ndarray
    G: np.ndarray
    E: np.ndarray
    time: float
    steps: int
    rec: np.ndarray
    before: np.ndarray
    after: np.ndarray


class SceneStorage(NamedTuple):
    """The arrays a scene lives in (every reset writes into them, every step updates them in place):
    per-vehicle floats ``F`` (n, NF) and integers ``G`` (n, NI), the ego's set-point index ``E`` (1,),
    the positions [m] at the start / end of the ego's crash frame ``before`` / ``after`` (n, 2), and the
    crash flag ``rec`` (1,). A batch hands each environment views of its stacked arrays, so one numba
    call steps them all (:func:`stacked_storage`)."""

    F: np.ndarray
    G: np.ndarray
    E: np.ndarray
    before: np.ndarray
    after: np.ndarray
    rec: np.ndarray

    @classmethod
    def allocate(cls, n: int) -> SceneStorage:
        """Fresh arrays for ``n`` bodies (the ego included)."""
        return stacked_storage(1, n).row(0)

    def row(self, i: int) -> SceneStorage:
        """Environment ``i``'s views of stacked arrays (each array with a leading batch axis)."""
        return SceneStorage(*(a[i] for a in self))


def stacked_storage(num_envs: int, n: int) -> SceneStorage:
    """:class:`SceneStorage` for ``num_envs`` scenes of ``n`` bodies, each array with a leading batch axis."""
    return SceneStorage(
        np.zeros((num_envs, n, L.NF)),
        np.zeros((num_envs, n, L.NI), dtype=np.int64),
        np.zeros((num_envs, 1), dtype=np.int64),
        np.zeros((num_envs, n, 2)),
        np.zeros((num_envs, n, 2)),
        np.zeros((num_envs, 1), dtype=np.int64),
    )


class FastHighwayEnv(gym.Env):
    """A gymnasium-style env reproducing highway-env's straight highway (see the module docstring).

    ``state()`` gives every vehicle's arrays (row 0: the ego, then highway-env's ``road.vehicles`` order).
    ``continuous``: the ego's resolved ``ContinuousAction`` (:class:`safelane.sim.fast.continuous.ContinuousSpec`;
    None under meta-actions).
    ``storage``: the arrays to live in (default: its own; :class:`SceneStorage`).
    ``vehicles_behind``: how many vehicles (at most ``vehicles_count``) each reset moves from the front
    of the scene to behind the ego, as safelane's ``traffic.vehicles_behind`` on highway-env.
    ``driver_mix``: each other car's driver type drawn from it at spawn (``traffic.driver_mix``).
    Seeding is gymnasium's (``Env.reset(seed=...)`` -> ``self.np_random``), as in highway-env.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(
        self,
        config: dict[str, Any] | None = None,
        env_id: str = "highway-fast-v0",
        storage: SceneStorage | None = None,
        vehicles_behind: int = 0,
        driver_mix: DriverMix | None = None,
    ) -> None:
        self.env_id = env_id
        self.sim = resolve_config(config, env_id, driver_mix)
        whole = isinstance(vehicles_behind, int | np.integer) and not isinstance(vehicles_behind, bool)
        if not whole or vehicles_behind < 0:
            raise ValueError(f"vehicles_behind: {vehicles_behind!r} is not supported; allowed: an integer >= 0")
        self.vehicles_behind = int(vehicles_behind)
        self.config = self.sim.config
        self.continuous = self.sim.continuous  # the ego's ContinuousAction (None: meta-actions)
        if self.continuous is None:
            self.action_space: spaces.Space = spaces.Discrete(5)
        else:  # ContinuousAction.space()
            self.action_space = spaces.Box(-1.0, 1.0, shape=(self.continuous.size,), dtype=np.float32)
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float32)
        self.P = params()
        self._P_ego = None if self.continuous is None else C.ego_params(self.P, self.continuous)
        self._obs = np.zeros(2, dtype=np.float32)
        n = 1 + self.sim.vehicles_count
        if storage is None:
            storage = SceneStorage.allocate(n)
        elif storage.F.shape != (n, L.NF):
            raise ValueError(f"storage: arrays for {storage.F.shape[0]} bodies, this configuration has {n}")
        self.storage = storage
        self._before = storage.before
        self._after = storage.after
        self._rec = storage.rec
        self._buffers = (storage.F, storage.G, storage.E)
        self._static_cache()
        self.time = 0.0
        self.steps = 0

    # --- static per-body arrays, built once -------------------------------------------------------
    def _static_cache(self) -> None:
        n = 1 + self.sim.vehicles_count
        from highway_env.vehicle.kinematics import Vehicle

        self._length = np.full(n, float(Vehicle.LENGTH))
        self._width = np.full(n, float(Vehicle.WIDTH))
        self._is_vehicle = np.ones(n, dtype=bool)
        idm = np.ones(n, dtype=bool)
        idm[0] = False
        self._can_change_lane = idm.copy()
        # The snapshot's class constants per row, looked up in one table: each type's row, the assumed type's,
        # the ego's (:func:`_model_row`).
        mix = self.sim.driver_mix
        assumed = assumed_class(mix) if mix is not None else None
        models = [_model_row(c) for c in self.sim.other_classes]
        self._model_table = np.stack([*models, _model_row(assumed) if assumed else models[0], _EGO_ROW])
        self._assumed_gains = np.asarray(getattr(assumed, "ACCELERATION_PARAMETERS", [np.nan] * 3), dtype=np.float64)
        self._conceal = assumed is not None
        self._no_gains = np.full(n, np.nan)
        self._no_gains.flags.writeable = False
        # Linear-model drivers draw their gains per vehicle at spawn (randomize_behavior): read at reset.
        self._linear_model = bool(self.sim.drivers[0, L.D_LIN])
        rows = np.zeros(n, dtype=np.int64)
        rows[0] = -1  # the ego's row of the table
        self._set_model_fields(rows)
        for a in (self._length, self._width, self._is_vehicle, self._can_change_lane):
            a.flags.writeable = False
        self._origin = np.zeros(2)
        self._direction = np.array([1.0, 0.0])
        self._lateral = np.array([0.0, 1.0])
        # a continuous ego (a plain Vehicle) has no set-points and no speed controller
        self._ts_tuple = () if self.continuous else tuple(float(s) for s in self.sim.target_speeds)
        self._delta: np.ndarray | None = None
        self._driver_type: np.ndarray | None = None
        self._lane_w = float(self.P[L.P_LANE_WIDTH])
        self._pol_f = float(self.sim.policy_frequency)
        self._sim_f = float(self.sim.simulation_frequency)
        self._kp = math.nan if self.continuous else float(ControlledVehicle.KP_A)
        assert set(RoadSnapshot.__dataclass_fields__) == set(_SNAPSHOT_FIELDS), "RoadSnapshot changed"

    def _set_model_fields(self, rows: np.ndarray) -> None:
        """The snapshot's class-constant driver fields, each body's from row ``rows[k]`` of the model table."""
        table = self._model_table[rows]
        for column, name in enumerate(_MODEL_FIELDS):
            values = table[:, column].copy()
            values.flags.writeable = False
            setattr(self, f"_{name}", values)
        self._linear_rows = table[:, len(_MODEL_FIELDS)] != 0.0

    def _driver_fields_at_reset(self) -> None:
        """The per-episode driver fields: each body's IDM exponent and linear gains (drawn at spawn); with a driver
        mixture also each body's type and its class constants (the assumed type's for a drawn car, unless the
        shield sees the types)."""
        self._delta = self.F[:, L.DELTA].copy()
        self._delta.flags.writeable = False
        types = self.G[:, L.DTYPE]
        if self.sim.driver_mix is not None:
            self._driver_type = types.copy()
            self._driver_type.flags.writeable = False
            n_types = len(self.sim.other_classes)
            rows = np.where(types < 0, n_types + 1, n_types if self._conceal else types)
            self._set_model_fields(rows)
        self._linear_gains = [self._no_gains] * 3
        if self.sim.driver_mix is not None and self._conceal:
            if self._linear_rows[1:].any():  # the assumed type is linear: its nominal gains
                self._linear_gains = [np.where(types >= 0, g, np.nan) for g in self._assumed_gains]
        elif self.G[:, L.LIN].any():
            linear = self.G[:, L.LIN] != 0  # the ego is not a linear-model driver
            self._linear_gains = [np.where(linear, self.F[:, c], np.nan) for c in (L.AP0, L.AP1, L.AP2)]
        for gains in self._linear_gains:
            gains.flags.writeable = False

    # --- gymnasium API -----------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        if options:
            raise ValueError("reset(options=...) is not supported by the fast simulator")
        super().reset(seed=seed)
        scene = build_scene(self.np_random, self.sim, self.P, self._buffers)
        for array, built in zip(self._buffers, scene, strict=True):
            if array is not built:  # the Python path (a non-PCG64 generator) builds new arrays
                array[...] = built
        self.F, self.G, self.E = self._buffers
        if self.continuous is not None:  # Vehicle(road, position, heading, speed): no speed index, no set-point
            self.E[0] = -1
            self.F[0, L.TSPD] = 0.0
        if self.vehicles_behind:  # TrafficLayout, right after highway-env's scene
            spawn_behind(self.np_random, self.sim, self.P, self.F, self.G, self.vehicles_behind)
        self.time = 0.0
        self.steps = 0
        self._rec[0] = 0
        self._driver_fields_at_reset()
        self._episode_fields = self._constant_fields()
        return self._obs.copy(), self._info()

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One decision: a meta-action (0..4), or a continuous action (``continuous.size`` numbers in [-1, 1],
        float32 as gymnasium's Box gives them, float64 or a list; mapped as highway-env maps that very object)."""
        sc = self.sim
        if self.continuous is not None:
            acceleration, steering = C.controls(action, self.continuous)
            self.time += 1 / sc.policy_frequency
            C.simulate(
                self.F, self.G, self.P, self._P_ego, acceleration, steering, self._linear_model, sc.frames, sc.dt,
                sc.lanes_count, self._before, self._after, self._rec,
            )  # fmt: skip
        else:
            a = int(action)
            if not 0 <= a < 5:
                raise ValueError(f"action {action!r} not in Discrete(5)")
            self.time += 1 / sc.policy_frequency
            K.simulate(
                self.F, self.G, self.E, sc.target_speeds, self.P, a, sc.frames, sc.dt, sc.lanes_count,
                self._before, self._after, self._rec,
            )  # fmt: skip
        self.steps += sc.frames
        terminated = bool(self.G[0, L.CRASHED]) or (sc.offroad_terminal and not self.on_road)
        truncated = bool(self.time >= sc.duration)
        return self._obs.copy(), 0.0, terminated, truncated, self._info()

    # --- state ---------------------------------------------------------------------------------------
    @property
    def on_road(self) -> bool:
        """``ego.on_road``: on its (closest) lane, no margin."""
        lane = int(self.G[0, L.LANE])
        return bool(on_lane(self.F[0, L.X], self.F[0, L.Y], lane, 0.0, self.P))

    def state(self) -> dict[str, np.ndarray]:
        """Copies of every vehicle's state (row 0: the ego; a continuous ego's target speed is NaN and its
        speed index -1: it has neither)."""
        F, G = self.F, self.G
        target_speed = F[:, L.TSPD].copy()
        if self.continuous is not None:
            target_speed[0] = np.nan
        return {
            "x": F[:, L.X].copy(),
            "y": F[:, L.Y].copy(),
            "heading": F[:, L.H].copy(),
            "speed": F[:, L.V].copy(),
            "target_speed": target_speed,
            "delta": F[:, L.DELTA].copy(),
            "timer": F[:, L.TIMER].copy(),
            "driver_type": G[:, L.DTYPE].copy(),
            "lane": G[:, L.LANE].copy(),
            "target_lane": G[:, L.TLANE].copy(),
            "crashed": G[:, L.CRASHED].astype(bool),
            "speed_index": self.E.copy(),
        }

    def get_state(self) -> SimState:
        """A copy of everything a step reads or writes (every vehicle, the ego's set-point index, the
        clock, the crash record): :meth:`set_state` puts it back exactly, so a planner can try action
        sequences from one state (the other drivers are deterministic after reset)."""
        return SimState(
            self.F.copy(), self.G.copy(), self.E.copy(), self.time, self.steps,
            self._rec.copy(), self._before.copy(), self._after.copy(),
        )  # fmt: skip

    def set_state(self, state: SimState) -> None:
        """Restore a state taken by :meth:`get_state` in this episode (copied in: ``state`` stays reusable)."""
        self.F[...] = state.F
        self.G[...] = state.G
        self.E[...] = state.E
        self.time = state.time
        self.steps = state.steps
        self._rec[...] = state.rec
        self._before[...] = state.before
        self._after[...] = state.after

    def _info(self) -> dict[str, Any]:
        return {
            "speed": float(self.F[0, L.V]),
            "crashed": bool(self.G[0, L.CRASHED]),
            "snapshot": self.snapshot(),
        }

    def road_snapshot(self, refresh: bool = False) -> RoadSnapshot:
        """The scene now (the simulator-side interface the shield's ``refresh`` uses, like
        :class:`safelane.sim.highway.HighwayEnvAdapter`'s; nothing is cached, so ``refresh`` changes nothing)."""
        return self.snapshot()

    def _constant_fields(self) -> dict[str, Any]:
        """The snapshot fields that stay the same for a whole episode (shared, read-only arrays)."""
        return {
            "policy_frequency": self._pol_f,
            "simulation_frequency": self._sim_f,
            "lanes_count": self.sim.lanes_count,
            "lane_width": self._lane_w,
            "lane_origin": self._origin,
            "lane_direction": self._direction,
            "lane_lateral": self._lateral,
            "speed_limit": float(SPEED_LIMIT),
            "ego": 0,
            "ego_target_speeds": self._ts_tuple,
            "ego_kp": self._kp,
            "length": self._length,
            "width": self._width,
            "is_vehicle": self._is_vehicle,
            "can_change_lane": self._can_change_lane,
            "idm_delta": self._delta,
            **{name: getattr(self, f"_{name}") for name in _MODEL_FIELDS},
            "linear_speed_gain": self._linear_gains[0],
            "linear_speed_difference_gain": self._linear_gains[1],
            "linear_distance_gain": self._linear_gains[2],
            "driver_type": self._driver_type if self.sim.driver_mix is not None else None,
        }

    def snapshot(self) -> RoadSnapshot:
        """The scene as a :class:`RoadSnapshot` (fresh per-step arrays; the static ones are shared, read-only)."""
        F, G = self.F, self.G
        kin = F[:, : L.TSPD + 1].T.copy()  # rows x, y, heading, speed, set-point
        ints = G[:, : L.CRASHED + 1].T.copy()  # rows lane, target lane, crashed
        crashed_once = bool(self._rec[0])
        # RoadSnapshot is a frozen dataclass without __post_init__: filling its __dict__ is what its
        # __init__ does, minus one object.__setattr__ per field (a decision takes ~100 µs: it counts).
        snap = object.__new__(RoadSnapshot)
        fields = snap.__dict__
        fields.update(self._episode_fields)
        fields["time"] = float(self.time)
        if self.continuous is not None:  # a plain Vehicle: no set-point (the column holds the others' view of it)
            kin[L.TSPD, 0] = math.nan
        fields["ego_target_speed"] = float(kin[L.TSPD, 0])
        fields["ego_speed_index"] = int(self.E[0])
        fields["ego_lane_offset"] = float(kin[1, 0] - int(ints[0, 0]) * self._lane_w)
        # (n, 2) C-ordered like highway-env's, not the F-ordered view kin[:2].T: numba compiles a kernel once per
        # array layout, and every kernel that reads positions would compile twice in a process that runs both.
        fields["position"] = F[:, : L.Y + 1].copy()
        fields["speed"] = kin[L.V]
        fields["heading"] = kin[L.H]
        fields["target_speed"] = kin[L.TSPD]
        fields["lane"] = ints[L.LANE]
        fields["target_lane"] = ints[L.TLANE]
        fields["crashed"] = ints[L.CRASHED].astype(bool)
        fields["impact_before"] = self._before.copy() if crashed_once else None
        fields["impact_after"] = self._after.copy() if crashed_once else None
        return snap
