"""Configuration and reset: highway-env's ``HighwayEnv._create_vehicles`` replayed draw for draw.

The scene is built in Python from the same ``numpy.random.Generator`` highway-env uses
(``gymnasium.utils.seeding.np_random(seed)``, the env's ``np_random``, which ``HighwayEnv._create_road``
hands to the ``Road``), making the same calls in the same order with the same arguments:

* ego: ``Vehicle.create_random(road, speed=25, lane_id=initial_lane_id, spacing=ego_spacing)`` ->
  ``choice(["0"])``, ``choice(["1"])`` (one-element choices draw nothing, checked at import),
  ``choice(lanes_count)`` unless ``initial_lane_id`` is set, ``uniform(0.9, 1.1)``;
  then ``MDPVehicle(road, position, heading, speed)`` (``Vehicle`` under ``ContinuousAction``: no draws either);
* each other vehicle: ``<other_vehicles_type>.create_random(road, spacing=1/vehicles_density)`` ->
  (with a driver mixture, ``traffic.driver_mix``: its type first, ``choice(K, p=probabilities)``, one double,
  :mod:`safelane.sim.drivers`) ``choice(lanes_count)``, ``uniform(0.7·30, 0.8·30)``, ``uniform(0.9, 1.1)``; then
  ``randomize_behavior()`` -> (LinearVehicle and subclasses: ``uniform(size=3)``, ``uniform(size=2)``
  for ACCELERATION_ / STEERING_PARAMETERS, then) ``uniform(3.5, 4.5)`` (DELTA).

The arithmetic is the same expressions in the same order, so positions, speeds, timers and DELTAs are
bit-identical to highway-env's.

``traffic.vehicles_behind = N`` (safelane's :class:`safelane.sim.traffic.TrafficLayout`, applied right
after highway-env's scene) is :func:`spawn_behind`: the N vehicles farthest ahead leave, N new ones are
drawn behind the ego from the same generator (with a mixture the type first, then ``integers(lanes_count)``,
``uniform(0.7·30, 1.0·30)``, ``uniform(0.9, 1.1)``, then ``randomize_behavior()``), with the same rows order as
``road.vehicles``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium.utils import seeding
from highway_env.road.lane import AbstractLane, StraightLane
from highway_env.utils import class_from_path
from highway_env.vehicle.behavior import IDMVehicle, LinearVehicle
from highway_env.vehicle.controller import ControlledVehicle, MDPVehicle
from highway_env.vehicle.kinematics import Vehicle

from safelane.core.drivers import DriverMix
from safelane.sim.drivers import driver_classes
from safelane.sim.fast import kernels as K
from safelane.sim.fast import layout as L
from safelane.sim.fast.continuous import ContinuousSpec, resolve_continuous
from safelane.sim.fast.lanes import closest_lane

ENV_IDS = ("highway-v0", "highway-fast-v0")
IDM_PATH = "highway_env.vehicle.behavior.IDMVehicle"
OTHER_VEHICLE_TYPES = (
    IDM_PATH,
    "highway_env.vehicle.behavior.LinearVehicle",
    "highway_env.vehicle.behavior.AggressiveVehicle",
    "highway_env.vehicle.behavior.DefensiveVehicle",
)
ACTION_TYPES = ("DiscreteMetaAction", "ContinuousAction")
"""highway-env's ``action.type`` values this simulator reproduces (ContinuousAction: ``dynamical: False``)."""
SPEED_LIMIT = 30  # RoadNetwork.straight_road_network(..., speed_limit=30) in HighwayEnv._create_road
LANE_LENGTH = 10000.0  # straight_road_network's default length

# Config keys that do not change the dynamics (rendering, reward, observation: this simulator's reward
# is 0.0 and its observation a placeholder; safelane computes both from the snapshot).
_NO_DYNAMICS_KEYS = frozenset(
    {
        "observation",
        "screen_width",
        "screen_height",
        "centering_position",
        "scaling",
        "show_trajectories",
        "render_agent",
        "offscreen_rendering",
        "real_time_rendering",
        "collision_reward",
        "right_lane_reward",
        "high_speed_reward",
        "lane_change_reward",
        "reward_speed_range",
        "normalize_reward",
        # on a single straight road there are no connected lane segments: the search is the same
        "neighbour_vehicles_connected_lanes",
    }
)
_DYNAMICS_KEYS = frozenset(
    {
        "action",
        "simulation_frequency",
        "policy_frequency",
        "other_vehicles_type",
        "manual_control",
        "lanes_count",
        "vehicles_count",
        "controlled_vehicles",
        "initial_lane_id",
        "duration",
        "ego_spacing",
        "vehicles_density",
        "offroad_terminal",
    }
)


def default_config(env_id: str) -> dict[str, Any]:
    """highway-env's default config for ``env_id`` (``HighwayEnv`` / ``HighwayEnvFast.default_config``)."""
    from highway_env.envs.highway_env import HighwayEnv, HighwayEnvFast

    if env_id == "highway-v0":
        return HighwayEnv.default_config()
    if env_id == "highway-fast-v0":
        return HighwayEnvFast.default_config()
    raise ValueError(f"env_id: {env_id!r} is not supported; allowed: {', '.join(ENV_IDS)}")


@dataclass(frozen=True)
class SimConfig:
    """The resolved settings the kernels need."""

    env_id: str
    lanes_count: int
    vehicles_count: int
    duration: float
    ego_spacing: float
    vehicles_density: float
    policy_frequency: float
    simulation_frequency: float
    frames: int
    dt: float
    initial_lane_id: int | None
    offroad_terminal: bool
    others_check_collisions: bool
    target_speeds: np.ndarray
    """[m/s] the meta-action ego's set-points (``MDPVehicle.DEFAULT_TARGET_SPEEDS``, unused, for a continuous ego)."""
    continuous: ContinuousSpec | None
    """The ego's ``ContinuousAction`` (None: ``DiscreteMetaAction``, an ``MDPVehicle`` ego)."""
    config: dict[str, Any]
    other_classes: tuple[type, ...]
    """The other vehicles' classes: ``other_vehicles_type``'s alone, or the driver mixture's types."""
    drivers: np.ndarray
    """(types, layout.ND): :func:`driver_constants` of each class of ``other_classes``."""
    type_cdf: np.ndarray
    """The mixture's normalised cumulative probabilities, numpy ``choice``'s (empty: no mixture, no type draw)."""
    driver_mix: DriverMix | None = None


def resolve_config(config: dict[str, Any] | None, env_id: str, driver_mix: DriverMix | None = None) -> SimConfig:
    """Merge ``config`` into highway-env's defaults as ``AbstractEnv.configure`` does (a shallow update)
    and check that every setting is one this simulator reproduces; anything else raises ValueError.
    ``driver_mix``: each other car's type drawn from it (``other_vehicles_type`` then unused)."""
    cfg = default_config(env_id)
    if config:
        cfg.update(config)
    unknown = sorted(set(cfg) - _NO_DYNAMICS_KEYS - _DYNAMICS_KEYS)
    if unknown:
        raise ValueError(f"config keys not supported by the fast simulator: {unknown}")
    if driver_mix is None and cfg["other_vehicles_type"] not in OTHER_VEHICLE_TYPES:
        raise ValueError(
            f"other_vehicles_type: {cfg['other_vehicles_type']!r} is not supported; allowed: "
            + ", ".join(OTHER_VEHICLE_TYPES)
        )
    if int(cfg["controlled_vehicles"]) != 1:
        raise ValueError(f"controlled_vehicles: {cfg['controlled_vehicles']!r} is not supported; allowed: 1")
    if cfg["manual_control"]:
        raise ValueError("manual_control: True is not supported; allowed: False")
    action = dict(cfg["action"])
    continuous = None
    if action.get("type") == "ContinuousAction":
        continuous = resolve_continuous(action)
        # the scene's draws do not depend on the ego's class; its speed index is discarded (a Vehicle has none)
        target_speeds = np.array(MDPVehicle.DEFAULT_TARGET_SPEEDS, dtype=np.float64)
    elif action.get("type") == "DiscreteMetaAction":
        target_speeds = _meta_action_speeds(action)
    else:
        raise ValueError(f"action.type: {action.get('type')!r} is not supported; allowed: {', '.join(ACTION_TYPES)}")
    sim_f = cfg["simulation_frequency"]
    pol_f = cfg["policy_frequency"]
    lanes = int(cfg["lanes_count"])
    if lanes < 1:
        raise ValueError(f"lanes_count: {lanes} is not supported; allowed: >= 1")
    init_lane = cfg["initial_lane_id"]
    if init_lane is not None and not 0 <= int(init_lane) < lanes:
        raise ValueError(f"initial_lane_id: {init_lane!r} is not supported; allowed: None or 0..{lanes - 1}")
    if driver_mix is None:
        classes: tuple[type, ...] = (class_from_path(cfg["other_vehicles_type"]),)
        type_cdf = np.zeros(0)
    else:
        classes = driver_classes(driver_mix)
        type_cdf = mixture_cdf(driver_mix.probabilities)
        models = {issubclass(c, LinearVehicle) for c in classes}
        if continuous is not None and len(models) > 1:
            raise ValueError(
                "traffic.driver_mix: IDM and linear-model drivers together with a ContinuousAction ego are not "
                "supported by the fast simulator; allowed there: IDM types only or linear types only"
            )
    return SimConfig(
        env_id=env_id,
        lanes_count=lanes,
        vehicles_count=int(cfg["vehicles_count"]),
        duration=cfg["duration"],
        ego_spacing=cfg["ego_spacing"],
        vehicles_density=cfg["vehicles_density"],
        policy_frequency=pol_f,
        simulation_frequency=sim_f,
        frames=int(sim_f // pol_f),
        dt=1 / sim_f,
        initial_lane_id=None if init_lane is None else int(init_lane),
        offroad_terminal=bool(cfg["offroad_terminal"]),
        others_check_collisions=env_id != "highway-fast-v0",
        target_speeds=target_speeds,
        continuous=continuous,
        config=cfg,
        other_classes=classes,
        drivers=np.stack([driver_constants(c) for c in classes]),
        type_cdf=type_cdf,
        driver_mix=driver_mix,
    )


def mixture_cdf(probabilities: np.ndarray) -> np.ndarray:
    """numpy ``Generator.choice(K, p=probabilities)``'s cumulative probabilities: ``cumsum``, then divided by its
    last entry (the draw is the number of entries at or below one ``random()`` double)."""
    cdf = np.asarray(probabilities, dtype=np.float64).cumsum()
    cdf /= cdf[-1]
    return cdf


def _meta_action_speeds(action: dict[str, Any]) -> np.ndarray:
    """A ``DiscreteMetaAction`` config's target speeds [m/s] (highway-env's default when unset), checked."""
    for flag in ("longitudinal", "lateral"):
        if not action.get(flag, True):
            raise ValueError(f"action.{flag}: False is not supported; allowed: True")
    extra = sorted(set(action) - {"type", "longitudinal", "lateral", "target_speeds"})
    if extra:
        raise ValueError(f"action keys not supported by the fast simulator: {extra}")
    ts = action.get("target_speeds")
    target_speeds = np.array(ts if ts is not None else MDPVehicle.DEFAULT_TARGET_SPEEDS, dtype=np.float64)
    if target_speeds.ndim != 1 or target_speeds.size < 2 or target_speeds[-1] == target_speeds[0]:
        raise ValueError(f"action.target_speeds: {ts!r} is not supported; allowed: 2 or more speeds, last != first")
    return target_speeds


def driver_constants(cls: type) -> np.ndarray:
    """A driver class's constants, one row of the spawn kernels' driver table (``layout.D_*``): [linear?,
    TIME_WANTED [s], LANE_CHANGE_MIN_ACC_GAIN [m/s²], ACCELERATION_RANGE (2x3), STEERING_RANGE (2x2),
    COMFORT_ACC_MAX, COMFORT_ACC_MIN [m/s²], DISTANCE_WANTED [m], POLITENESS, LANE_CHANGE_MAX_BRAKING_IMPOSED [m/s²],
    DELTA_RANGE (2), LANE_CHANGE_DELAY [s]]. Every class must share IDMVehicle's ACC_MAX (the kernels' one clip)."""
    if cls.ACC_MAX != IDMVehicle.ACC_MAX or cls.LANE_CHANGE_DELAY != IDMVehicle.LANE_CHANGE_DELAY:
        raise ValueError(f"{cls.__name__}: ACC_MAX and LANE_CHANGE_DELAY must be IDMVehicle's for the fast simulator")
    d = np.zeros(L.ND)
    lin = issubclass(cls, LinearVehicle)
    d[L.D_LIN] = 1.0 if lin else 0.0
    d[L.D_TW] = cls.TIME_WANTED
    d[L.D_GAIN] = cls.LANE_CHANGE_MIN_ACC_GAIN
    if lin:
        d[L.D_AR : L.D_AR + 6] = np.asarray(cls.ACCELERATION_RANGE, dtype=np.float64).reshape(6)
        d[L.D_SR : L.D_SR + 4] = np.asarray(cls.STEERING_RANGE, dtype=np.float64).reshape(4)
    d[L.D_CMAX] = cls.COMFORT_ACC_MAX
    d[L.D_CMIN] = cls.COMFORT_ACC_MIN
    d[L.D_DW] = cls.DISTANCE_WANTED
    d[L.D_POL] = cls.POLITENESS
    d[L.D_MBI] = cls.LANE_CHANGE_MAX_BRAKING_IMPOSED
    d[L.D_DLO], d[L.D_DHI] = cls.DELTA_RANGE
    d[L.D_DELAY] = cls.LANE_CHANGE_DELAY
    return d


def _draws_per_car(sc: SimConfig) -> int:
    """The fewest doubles one other car's spawn takes: its type (with a mixture), speed, gap, DELTA, and a linear
    driver's five gains when every type is one (a mixed table's extra draws are found by the replay's retries)."""
    linear = bool(sc.drivers[:, L.D_LIN].all())
    return (1 if sc.type_cdf.size else 0) + 3 + (5 if linear else 0)


def params() -> np.ndarray:
    """The kernels' parameter vector, read from highway-env's class constants."""
    P = np.zeros(L.NP)
    P[L.P_LANE_WIDTH] = StraightLane.DEFAULT_WIDTH
    P[L.P_LANE_LENGTH] = LANE_LENGTH
    P[L.P_VEHICLE_LENGTH_LANE] = AbstractLane.VEHICLE_LENGTH
    P[L.P_SPEED_LIMIT] = SPEED_LIMIT
    P[L.P_LENGTH] = Vehicle.LENGTH
    P[L.P_WIDTH] = Vehicle.WIDTH
    P[L.P_DIAGONAL] = np.sqrt(Vehicle.LENGTH**2 + Vehicle.WIDTH**2)
    P[L.P_MAX_SPEED] = Vehicle.MAX_SPEED
    P[L.P_MIN_SPEED] = Vehicle.MIN_SPEED
    P[L.P_TAU_PURSUIT] = ControlledVehicle.TAU_PURSUIT
    P[L.P_KP_A] = ControlledVehicle.KP_A
    P[L.P_KP_HEADING] = ControlledVehicle.KP_HEADING
    P[L.P_KP_LATERAL] = ControlledVehicle.KP_LATERAL
    P[L.P_MAX_STEERING] = ControlledVehicle.MAX_STEERING_ANGLE
    P[L.P_ACC_MAX] = IDMVehicle.ACC_MAX
    P[L.P_COMFORT_ACC_MAX] = IDMVehicle.COMFORT_ACC_MAX
    P[L.P_COMFORT_ACC_MIN] = IDMVehicle.COMFORT_ACC_MIN
    P[L.P_DISTANCE_WANTED] = IDMVehicle.DISTANCE_WANTED
    P[L.P_TIME_WANTED] = IDMVehicle.TIME_WANTED
    P[L.P_POLITENESS] = IDMVehicle.POLITENESS
    P[L.P_MIN_ACC_GAIN] = IDMVehicle.LANE_CHANGE_MIN_ACC_GAIN
    P[L.P_MAX_BRAKING_IMPOSED] = IDMVehicle.LANE_CHANGE_MAX_BRAKING_IMPOSED
    P[L.P_LANE_CHANGE_DELAY] = IDMVehicle.LANE_CHANGE_DELAY
    P[L.P_SQUARE] = 2.0
    return P


def _one_element_choice_draws_nothing() -> bool:
    rng = np.random.default_rng(12345)
    before = rng.bit_generator.state
    rng.choice(["0"])
    return rng.bit_generator.state == before


_SKIP_NODE_CHOICES = _one_element_choice_draws_nothing()


def make_rng(seed: int | None) -> np.random.Generator:
    """gymnasium's ``Env.reset(seed=...)`` generator."""
    rng, _ = seeding.np_random(seed)
    return rng


def build_scene(
    rng: np.random.Generator, sc: SimConfig, P: np.ndarray, out: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``HighwayEnv._create_vehicles`` on arrays: returns (F, G, E) in kernels' layout (written into ``out``).

    On PCG64 (gymnasium's generator) the draws are replayed from the generator's raw outputs in one numba
    call (:func:`safelane.sim.fast.kernels.spawn`), leaving the generator in exactly the state the
    ``choice`` / ``uniform`` calls would; other bit generators take :func:`build_scene_python`.
    """
    bg = rng.bit_generator
    if type(bg) is not np.random.PCG64:
        return build_scene_python(rng, sc, P)
    n = 1 + sc.vehicles_count
    if out is None:
        out = (np.zeros((n, L.NF)), np.zeros((n, L.NI), dtype=np.int64), np.zeros(1, dtype=np.int64))
    F, G, E = out
    n_int = sc.vehicles_count + (1 if sc.initial_lane_id is None else 0) if sc.lanes_count > 1 else 0
    n_dbl = 1 + _draws_per_car(sc) * sc.vehicles_count
    ego_lane = -1 if sc.initial_lane_id is None else sc.initial_lane_id
    lanes_factor = float(np.exp(-5 / 40 * sc.lanes_count))

    def draw(raws: np.ndarray, st: np.ndarray) -> bool:
        return K.spawn(
            raws, st, ego_lane, float(sc.ego_spacing), float(1 / sc.vehicles_density), lanes_factor,
            0.7 * SPEED_LIMIT, 0.8 * SPEED_LIMIT, float(IDMVehicle.DELTA), float(IDMVehicle.TIME_WANTED), sc.drivers,
            sc.type_cdf, 1 if sc.others_check_collisions else 0, sc.target_speeds, sc.lanes_count,
            P, F, G, E,
        )  # fmt: skip

    _replay(bg, n_int, n_dbl, draw)
    return F, G, E


def _replay(bg: np.random.PCG64, n_int: int, n_dbl: int, draw: Callable[[np.ndarray, np.ndarray], bool]) -> None:
    """Run ``draw(raws, st)`` (a numba kernel's draws) on the generator's next raw outputs, then leave the
    generator exactly where the same ``integers`` / ``uniform`` calls would.

    ``n_int`` bounded 32-bit draws and ``n_dbl`` doubles is what the draws take without rejections: the
    fewest raw outputs (a bounded draw takes half of one, through the generator's ``has_uint32`` buffer);
    a rejected draw makes ``draw`` return False, and it is replayed with one more output.
    """
    state = bg.state
    has = int(state["has_uint32"])
    st0 = np.array([0, has, int(state["uinteger"])], dtype=np.int64)
    need = n_dbl + (max(n_int - has, 0) + 1) // 2  # the fewest raw outputs the draws can take
    raws = bg.random_raw(need)
    while True:
        st = st0.copy()
        if draw(raws, st):
            break
        raws = np.concatenate([raws, bg.random_raw(1)])  # a rejected bounded draw: one more output
    assert st[0] == raws.size, (st, raws.size, need, has)
    if int(st[1]) != has or int(st[2]) != int(state["uinteger"]):
        state = bg.state
        state["has_uint32"] = int(st[1])
        state["uinteger"] = int(st[2])
        bg.state = state


def _driver_type_python(rng: np.random.Generator, sc: SimConfig) -> int:
    """The next car's type with the generator's own call, ``choice(K, p=probabilities)`` (-1: no mixture, no
    draw): the reference twin of ``kernels._driver_type``."""
    if sc.driver_mix is None:
        return -1
    return int(rng.choice(len(sc.other_classes), p=sc.driver_mix.probabilities))


def _place_python(
    rng: np.random.Generator, sc: SimConfig, t: int, k: int, x: float, y: float, speed: float, check: int,
    n_lanes: int, P: np.ndarray, F: np.ndarray, G: np.ndarray,
) -> None:  # fmt: skip
    """Row ``k`` (zeros): a driver of type ``t`` (``sc.other_classes[max(t, 0)]``) created as ``cls(road, (x, y)
    [m], heading 0, speed [m/s])`` — target speed = speed, the lane-change timer ``(np.sum(position) · π) %
    LANE_CHANGE_DELAY`` (a sum of two: ``x + y``), the closest lane, its class's constants — then
    ``randomize_behavior()`` with the generator's own calls (a linear driver's gains first). The reference twin of
    ``kernels._place_vehicle``, shared by :func:`build_scene_python` and :func:`spawn_behind_python`."""
    cls = sc.other_classes[max(t, 0)]
    uniform = rng.uniform
    F[k, L.X] = x
    F[k, L.Y] = y
    F[k, L.H] = 0.0
    F[k, L.V] = speed
    F[k, L.TSPD] = speed
    F[k, L.TIMER] = ((x + y) * np.pi) % cls.LANE_CHANGE_DELAY
    F[k, L.TW] = cls.TIME_WANTED
    F[k, L.GAIN] = cls.LANE_CHANGE_MIN_ACC_GAIN
    F[k, L.CMAX] = cls.COMFORT_ACC_MAX
    F[k, L.CMIN] = cls.COMFORT_ACC_MIN
    F[k, L.DW] = cls.DISTANCE_WANTED
    F[k, L.POL] = cls.POLITENESS
    F[k, L.MBI] = cls.LANE_CHANGE_MAX_BRAKING_IMPOSED
    if issubclass(cls, LinearVehicle):  # LinearVehicle.randomize_behavior, then IDMVehicle's
        ar, sr = cls.ACCELERATION_RANGE, cls.STEERING_RANGE
        ua = uniform(size=np.shape(cls.ACCELERATION_PARAMETERS))
        F[k, L.AP0 : L.AP2 + 1] = ar[0] + ua * (ar[1] - ar[0])
        ub = uniform(size=np.shape(cls.STEERING_PARAMETERS))
        F[k, L.SP0 : L.SP1 + 1] = sr[0] + ub * (sr[1] - sr[0])
        G[k, L.LIN] = 1
    d_lo, d_hi = cls.DELTA_RANGE
    F[k, L.DELTA] = uniform(low=d_lo, high=d_hi)
    lane = closest_lane(x, y, 0.0, n_lanes, P)
    G[k, L.LANE] = lane
    G[k, L.TLANE] = lane
    G[k, L.CHECK] = check
    G[k, L.ELC] = 1
    G[k, L.IDM] = 1
    G[k, L.DTYPE] = t


def build_scene_python(
    rng: np.random.Generator, sc: SimConfig, P: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``HighwayEnv._create_vehicles`` with the generator's own calls (the reference for :func:`build_scene`)."""
    n_lanes = sc.lanes_count
    n = 1 + sc.vehicles_count
    F = np.zeros((n, L.NF))
    G = np.zeros((n, L.NI), dtype=np.int64)
    E = np.zeros(1, dtype=np.int64)
    width = float(P[L.P_LANE_WIDTH])
    lanes_factor = np.exp(-5 / 40 * n_lanes)
    uniform = rng.uniform
    choice = rng.choice

    # --- the ego: Vehicle.create_random(road, speed=25.0, lane_id=initial_lane_id, spacing=ego_spacing)
    if not _SKIP_NODE_CHOICES:
        choice(["0"])
        choice(["1"])
    lane_id = sc.initial_lane_id if sc.initial_lane_id is not None else choice(n_lanes)
    speed = 25.0
    default_spacing = 12 + 1.0 * speed
    offset = sc.ego_spacing * default_spacing * lanes_factor
    x0 = 3 * offset
    x0 += offset * uniform(0.9, 1.1)
    x, y = float(x0), float(lane_id * width)
    # MDPVehicle(road, position, heading, speed)
    F[0, L.X] = x
    F[0, L.Y] = y
    F[0, L.H] = 0.0
    F[0, L.V] = speed
    lane = closest_lane(x, y, 0.0, n_lanes, P)
    G[0, L.LANE] = lane
    G[0, L.TLANE] = lane
    G[0, L.CHECK] = 1
    G[0, L.IDM] = 0
    G[0, L.DTYPE] = -1
    ts = sc.target_speeds
    si = K.speed_to_index(speed, ts)
    E[0] = si
    F[0, L.TSPD] = ts[si]
    F[0, L.DELTA] = IDMVehicle.DELTA
    F[0, L.TW] = IDMVehicle.TIME_WANTED
    x_max = x

    # --- the others: IDMVehicle.create_random(road, spacing=1 / vehicles_density); randomize_behavior()
    spacing = 1 / sc.vehicles_density
    lo, hi = 0.7 * SPEED_LIMIT, 0.8 * SPEED_LIMIT
    check = 1 if sc.others_check_collisions else 0
    for k in range(1, n):
        t = _driver_type_python(rng, sc)  # MixedDriverVehicle.create_random: the type, then create_random
        if not _SKIP_NODE_CHOICES:
            choice(["0"])
            choice(["1"])
        lane_id = choice(n_lanes)
        speed = uniform(lo, hi)
        default_spacing = 12 + 1.0 * speed
        offset = spacing * default_spacing * lanes_factor
        x0 = x_max
        x0 += offset * uniform(0.9, 1.1)
        x, y = float(x0), float(lane_id * width)
        _place_python(rng, sc, t, k, x, y, speed, check, n_lanes, P, F, G)
        if x > x_max:
            x_max = x
    return F, G, E


def _make_room(F: np.ndarray, G: np.ndarray, count: int) -> tuple[int, int]:
    """Remove the ``count`` vehicles farthest ahead (at most all but the ego) as TrafficLayout does:
    the largest x [m] by a stable sort, as Python's ``list.sort``; the others keep their order
    (``road.vehicles.remove``) and move up. Returns (the first free row, how many rows are free)."""
    n_others = F.shape[0] - 1
    count = max(min(int(count), n_others), 0)
    if count == 0:
        return F.shape[0], 0
    order = np.argsort(F[1:, L.X], kind="stable") + 1
    keep = np.sort(order[: n_others - count])
    F[1 : 1 + keep.size] = F[keep]
    G[1 : 1 + keep.size] = G[keep]
    first = 1 + keep.size
    F[first:] = 0.0
    G[first:] = 0
    return first, count


def spawn_behind(
    rng: np.random.Generator, sc: SimConfig, P: np.ndarray, F: np.ndarray, G: np.ndarray, count: int
) -> int:
    """``TrafficLayout._spawn_behind`` (safelane's ``traffic.vehicles_behind``) on a built scene's arrays,
    in place; returns how many vehicles moved (``count``, at most ``vehicles_count``).

    The ``count`` vehicles farthest ahead leave; the others keep their rows and order, and the new ones
    take the last rows (highway-env's ``road.vehicles`` after ``remove`` / ``append``). On PCG64 the
    draws are replayed from the generator's raw outputs in one numba call
    (:func:`safelane.sim.fast.kernels.spawn_behind`), leaving the generator where the ``integers`` /
    ``uniform`` calls would; other bit generators take :func:`spawn_behind_python`.
    """
    bg = rng.bit_generator
    if type(bg) is not np.random.PCG64:
        return spawn_behind_python(rng, sc, P, F, G, count)
    first, count = _make_room(F, G, count)
    if count == 0:
        return 0
    limit = SPEED_LIMIT or 30.0  # lane.speed_limit or 30.0
    x = float(F[0, L.X])  # ego.lane.local_coordinates(ego.position)[0]

    def draw(raws: np.ndarray, st: np.ndarray) -> bool:
        return K.spawn_behind(
            raws, st, first, count, x, 0.7 * limit, 1.0 * limit, math.exp(-5 / 40 * sc.lanes_count),
            float(sc.vehicles_density), sc.drivers, sc.type_cdf, 1 if sc.others_check_collisions else 0,
            sc.lanes_count, P, F, G,
        )  # fmt: skip

    n_int = count if sc.lanes_count > 1 else 0
    _replay(bg, n_int, _draws_per_car(sc) * count, draw)
    return count


def spawn_behind_python(
    rng: np.random.Generator, sc: SimConfig, P: np.ndarray, F: np.ndarray, G: np.ndarray, count: int
) -> int:
    """``TrafficLayout._spawn_behind`` on a built scene's arrays (in place) with the generator's own calls
    (the reference for :func:`spawn_behind`); returns how many vehicles moved.

    ``count`` vehicles (at most ``vehicles_count``) leave: the ones farthest ahead (largest x [m], a
    stable sort as Python's ``list.sort``); the others keep their rows and order (``road.vehicles.remove``),
    and the new vehicles take the last rows (``road.vehicles.append``). Going backwards from the ego's x
    [m], each draws its type (with a mixture), its lane (``integers(lanes_count)``), its speed [m/s]
    (``uniform(0.7·limit, 1.0·limit)``, limit 30 m/s) and its gap [m]
    (``(12 + speed)·exp(-5/40·lanes_count) / vehicles_density`` times ``uniform(0.9, 1.1)``), then its driver
    parameters (``randomize_behavior()``), from ``rng`` with the generator's own calls in TrafficLayout's order,
    so the draws and the arithmetic are highway-env's.
    """
    first, count = _make_room(F, G, count)
    if count == 0:
        return 0
    n_lanes = sc.lanes_count
    width = float(P[L.P_LANE_WIDTH])
    limit = SPEED_LIMIT or 30.0  # lane.speed_limit or 30.0
    lanes_factor = math.exp(-5 / 40 * n_lanes)
    density = sc.vehicles_density
    check = 1 if sc.others_check_collisions else 0
    uniform = rng.uniform
    # ego.lane.local_coordinates(ego.position)[0]: lane i starts at (0, i·w) with direction (1, 0)
    x = float(F[0, L.X])
    for k in range(first, first + count):
        t = _driver_type_python(rng, sc)
        lane_id = int(rng.integers(n_lanes))
        speed = float(uniform(0.7 * limit, 1.0 * limit))
        offset = (12 + speed) * lanes_factor / density
        x -= offset * uniform(0.9, 1.1)
        y = float(lane_id * width)  # lane.position(x, 0) on lane lane_id
        # IDMVehicle(road, position, heading=lane.heading_at(x) = 0, speed): target speed = speed,
        # timer = (np.sum(position) * pi) % LANE_CHANGE_DELAY, lane = the closest lane
        _place_python(rng, sc, t, k, x, y, speed, check, n_lanes, P, F, G)
    return count
