"""Hand-built road scenes on the real highway-env, for tests, for the stress suite and for users.

Each scenario function returns a :class:`Scene`: a shielded environment whose road has been
replaced by hand-placed vehicles (the ego plus a few highway-env ``IDMVehicle``\\ s at known lanes,
offsets and speeds), ready to ``step``. Lane 0 is the leftmost lane (highway-env's convention);
offsets ``dx`` are centre-to-centre along the road [m], positive ahead of the ego.

    scene = scenarios.stopped_car_ahead(mode="robust")
    scene.mask            # bool (5,) over LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER
    scene.env.step(1)     # and drive on
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
from highway_env.vehicle.behavior import AggressiveVehicle, IDMVehicle, LinearVehicle

from safelane.env.factory import make_env
from safelane.safety.one_decision.reference import Mode, SafetyResult
from safelane.safety.shield import SafetyShield


@dataclass(frozen=True)
class VehicleSpec:
    """One hand-placed vehicle: lane index, offset from the ego [m], speed [m/s], heading [rad]."""

    lane: int
    dx: float
    speed: float
    heading: float = 0.0
    target_lane: int | None = None  # a lane change already under way (None: keep the lane)
    vehicle_class: type = IDMVehicle
    lateral_offset: float = 0.0  # [m] from the lane centre, positive to the right
    # A driver as highway-env drew it (None: the class's own, as a fresh vehicle gets): its set-point [m/s],
    # the seconds since its last MOBIL check (it checks again once more than LANE_CHANGE_DELAY = 1 s has
    # passed), and a linear-model driver's randomised gains (``randomize_behavior``: acceleration, steering).
    target_speed: float | None = None
    lane_change_timer: float | None = None
    acceleration_parameters: tuple[float, float, float] | None = None
    steering_parameters: tuple[float, float] | None = None


@dataclass
class Scene:
    """A shielded environment holding a hand-built road, and the shield's verdict on it."""

    env: gym.Env
    result: SafetyResult
    vehicles: list[Any] = field(default_factory=list)

    @property
    def mask(self) -> np.ndarray:
        """Allowed actions (bool, shape (5,))."""
        return self.result.mask

    @property
    def shield(self) -> SafetyShield:
        """The :class:`SafetyShield` layer of the environment."""
        return find_shield(self.env)


def find_shield(env: gym.Env) -> SafetyShield:
    """The :class:`SafetyShield` layer of a wrapped environment."""
    while not isinstance(env, SafetyShield):
        env = env.env  # type: ignore[attr-defined]
    return env


DrawnDriver = tuple[int, float, float, float, float, tuple[float, float, float], tuple[float, float]]
"""lane, dx [m], speed [m/s], set-point [m/s], MOBIL timer [s], acceleration gains, steering gains."""


def drawn_drivers(cars: list[DrawnDriver], vehicle_class: type) -> list[VehicleSpec]:
    """Linear-model drivers (``vehicle_class``) driving straight in their lanes, each as highway-env drew it: a
    row per car of :data:`DrawnDriver` (the set-point, MOBIL timer and ``randomize_behavior`` gains of a campaign's
    car, for a hole rebuilt from its state)."""
    return [
        VehicleSpec(
            lane, dx, speed, vehicle_class=vehicle_class, target_speed=set_point, lane_change_timer=timer,
            acceleration_parameters=accel, steering_parameters=steer,
        )
        for lane, dx, speed, set_point, timer, accel, steer in cars
    ]  # fmt: skip


def build_scene(
    ego_lane: int,
    ego_speed: float,
    vehicles: list[VehicleSpec],
    *,
    mode: Mode = "robust",
    lanes_count: int = 4,
    ego_target_speed: float | None = None,
    preset: str = "fast",
    ego_lateral: float = 0.0,
    ego_heading: float = 0.0,
    ego_target_lane: int | None = None,
    others_collide: bool = True,
    **overrides: Any,
) -> Scene:
    """Place the ego at ``x = 200 m`` in ``ego_lane`` at ``ego_speed`` [m/s] and ``vehicles`` around it;
    ``ego_lateral`` [m] off the lane's centre and ``ego_heading`` [rad] off its direction (mid lane change),
    heading for ``ego_target_lane`` (None: its own lane). ``others_collide=False`` lets the other vehicles
    pass through each other, as ``highway-fast-v0`` (the presets' environment) does; the ego collides either
    way."""
    env = make_env(
        preset,
        seed=0,
        **{"env.lanes_count": lanes_count, "env.vehicles_count": 1, "shield.mode": mode},
        **overrides,
    )
    base = env.unwrapped
    road = base.road
    ego = base.vehicle
    _from, _to = next(iter(road.network.graph.items()))[0], None
    _to = next(iter(road.network.graph[_from]))
    ego_lane_obj = road.network.get_lane((_from, _to, ego_lane))
    ego.position = ego_lane_obj.position(200.0, ego_lateral)
    ego.heading = ego_lane_obj.heading_at(200.0) + ego_heading
    ego.speed = float(ego_speed)
    ego.lane_index = ego.target_lane_index = (_from, _to, ego_lane)
    if ego_target_lane is not None:
        ego.target_lane_index = (_from, _to, ego_target_lane)
    ego.lane = ego_lane_obj
    target = ego_speed if ego_target_speed is None else ego_target_speed
    ego.speed_index = int(ego.speed_to_index(target))
    ego.target_speed = float(ego.index_to_speed(ego.speed_index))
    placed = []
    road.vehicles = [ego]
    for spec in vehicles:
        lane = road.network.get_lane((_from, _to, spec.lane))
        v = spec.vehicle_class(
            road, lane.position(200.0 + spec.dx, spec.lateral_offset), spec.heading, float(spec.speed)
        )
        if spec.target_lane is not None:
            v.target_lane_index = (_from, _to, spec.target_lane)
        if spec.target_speed is not None:
            v.target_speed = float(spec.target_speed)
        if spec.lane_change_timer is not None:
            v.timer = float(spec.lane_change_timer)
        if spec.acceleration_parameters is not None:
            v.ACCELERATION_PARAMETERS = np.array(spec.acceleration_parameters, dtype=float)
        if spec.steering_parameters is not None:
            v.STEERING_PARAMETERS = np.array(spec.steering_parameters, dtype=float)
        v.check_collisions = others_collide
        road.vehicles.append(v)
        placed.append(v)
    result = find_shield(env).refresh()
    return Scene(env, result, placed)


# --- the scenario library ----------------------------------------------------------------------


def leader_braking(mode: Mode = "robust", gap: float = 25.0, **kw: Any) -> Scene:
    """A leader ``gap`` m ahead (centre to centre) in the ego lane, 10 m/s slower and braking hard;
    the lane to the left is free, a slow truck blocks the right."""
    return build_scene(1, 25.0, [VehicleSpec(1, gap, 15.0), VehicleSpec(2, 8.0, 25.0)], mode=mode, **kw)


def stopped_car_ahead(mode: Mode = "robust", distance: float = 60.0, **kw: Any) -> Scene:
    """A stopped car ``distance`` m ahead in the ego lane; the neighbouring lanes are free."""
    return build_scene(1, 25.0, [VehicleSpec(1, distance, 0.0)], mode=mode, **kw)


def slow_car_in_target_lane(mode: Mode = "robust", **kw: Any) -> Scene:
    """The left lane has a slow car just ahead (15 m/s, 15 m ahead); the ego lane is free."""
    return build_scene(1, 25.0, [VehicleSpec(0, 15.0, 15.0)], mode=mode, **kw)


def fast_follower_in_target_lane(mode: Mode = "robust", **kw: Any) -> Scene:
    """A fast car (35 m/s) 15 m behind in the left lane; the ego lane is free."""
    return build_scene(1, 25.0, [VehicleSpec(0, -15.0, 35.0)], mode=mode, **kw)


def cut_in_from_left(mode: Mode = "robust", **kw: Any) -> Scene:
    """A car 20 m ahead in the left lane, at ego speed, already steering into the ego lane."""
    return build_scene(1, 25.0, [VehicleSpec(0, 20.0, 22.0, heading=0.15, target_lane=1)], mode=mode, **kw)


def cut_in_from_right(mode: Mode = "robust", **kw: Any) -> Scene:
    """A car 20 m ahead in the right lane, already steering into the ego lane."""
    return build_scene(1, 25.0, [VehicleSpec(2, 20.0, 22.0, heading=-0.15, target_lane=1)], mode=mode, **kw)


def ego_leftmost_lane(mode: Mode = "robust", **kw: Any) -> Scene:
    """The ego alone on the leftmost lane (no LANE_LEFT available)."""
    return build_scene(0, 25.0, [], mode=mode, **kw)


def ego_rightmost_lane(mode: Mode = "robust", **kw: Any) -> Scene:
    """The ego alone on the rightmost lane (no LANE_RIGHT available)."""
    return build_scene(3, 25.0, [], mode=mode, **kw)


def dense_jam(mode: Mode = "robust", **kw: Any) -> Scene:
    """Slow traffic (10 m/s) all around: close leaders in every lane, the ego at 20 m/s."""
    specs = [VehicleSpec(lane, dx, 10.0) for lane in (0, 1, 2) for dx in (25.0, 50.0)]
    specs += [VehicleSpec(lane, -20.0, 12.0) for lane in (0, 2)]
    return build_scene(1, 20.0, specs, mode=mode, lanes_count=3, **kw)


def adjacent_car_ahead(mode: Mode = "robust", dx: float = 45.0, **kw: Any) -> Scene:
    """A car ``dx`` m ahead in the left lane at the ego's speed (25 m/s), driving straight; the ego's
    set-point is 30 m/s. Its lane-change rule (MOBIL) would let it cut in, and then brake."""
    return build_scene(1, 25.0, [VehicleSpec(0, dx, 25.0)], mode=mode, ego_target_speed=30.0, **kw)


def second_lane_car_moving_over(mode: Mode = "robust", **kw: Any) -> Scene:
    """The ego in the leftmost lane at 25 m/s (set-point 30); a car 45 m ahead two lanes to the right, at
    25 m/s, already steering into the lane next to the ego. Once there it may cut in (MOBIL allows it) and
    brake: the falsification campaign's most common invariant break (``second_lane_cut_in``), which the
    robust rule does not see from here (it projects the car into the lane next to the ego, not beyond)."""
    specs = [VehicleSpec(2, 45.0, 25.0, heading=-0.15, target_lane=1)]
    return build_scene(0, 25.0, specs, mode=mode, ego_target_speed=30.0, **kw)


def slow_car_turning_out(mode: Mode = "robust", dx: float = 10.0, **kw: Any) -> Scene:
    """The ego in lane 2 at 5 m/s (set-point 5); a car ``dx`` m ahead, nearly stopped (2 m/s), turning
    hard out of the ego's lane toward lane 0: its centre is already in lane 1 (0.85 m right of lane 1's
    centre), its heading −0.78 rad. At that angle its rear corner still reaches 1.5 m into lane 2 — the
    falsification campaign's one crash from states the rule called safe (5 decisions/s), which the robust rule
    sees since ``shield.body_extent`` (off in the rule ``basic``)."""
    specs = [VehicleSpec(1, dx, 2.0, heading=-0.78, target_lane=0, lateral_offset=0.85)]
    return build_scene(2, 5.0, specs, mode=mode, ego_target_speed=5.0, **kw)


def linear_car_alongside(mode: Mode = "robust", **kw: Any) -> Scene:
    """The ego in the leftmost lane at 19.35 m/s (set-point 20), a Linear-model driver in the next lane
    just level with it (its centre 0.1 m behind the ego's) at 20.25 m/s, and a Linear leader 42 m ahead at
    17.3 m/s: the falsification campaign's most common break with those drivers (``adjacent_behind``).
    By its own MOBIL rule with the linear formula the car alongside can neither cut in (the ego
    would be its new follower at a gap far below its safe distance: ``shield.linear_mobil: true``) nor gain
    by turning in behind the ego (``shield.linear_incentive: true``); the default rule assumes either, and
    then nothing is safe."""
    specs = [
        VehicleSpec(1, -0.1, 20.25, vehicle_class=LinearVehicle),
        VehicleSpec(0, 42.0, 17.3, vehicle_class=LinearVehicle),
    ]
    return build_scene(0, 19.35, specs, mode=mode, ego_target_speed=20.0, **kw)


def reversing_leader(mode: Mode = "robust", dx: float = 7.0, **kw: Any) -> Scene:
    """The ego nearly stopped (0.1 m/s, set-point 0) in lane 1; the car ``dx`` m ahead rolls *backwards* at
    2 m/s, as highway-env's jammed IDM cars do (speeds are clipped to ±40 m/s only): the campaign's crashes
    of cells 38 and 86 (``cell00038-seed4000380020``). With ``shield.reversing_leaders`` (the default) the
    rule keeps its reverse speed and nothing is safe; with the option off (rule ``basic``) it counts as stopped, 2 m
    away."""
    return build_scene(1, 0.1, [VehicleSpec(1, dx, -2.0)], mode=mode, ego_target_speed=0.0, **kw)


def car_being_overtaken(mode: Mode = "robust", **kw: Any) -> Scene:
    """2 decisions per second; the ego in lane 1 at 29.2 m/s (set-point 30) overtakes a queue of slow cars
    (13 m/s) in lane 0, one of them 3 m ahead of the ego's centre: the campaign's crash from a state called
    safe, ``cell00470-seed4004700006`` (6 lanes there). Within the decision the ego passes that car, which
    then sees the ego as its new *leader*: MOBIL's safety criterion protects its new follower, not the ego,
    and it may turn into the ego's rear flank. ``shield.level_cut_ins`` (on by default; false: the earlier
    rule) counts it as a follower entering the ego's lane after the cut-in time."""
    specs = [VehicleSpec(0, dx, 13.0) for dx in (-6.0, 3.0, 11.0, 19.0)]
    rate = {"env.policy_frequency": 2, "env.simulation_frequency": 10}
    return build_scene(1, 29.2, specs, mode=mode, ego_target_speed=30.0, **rate, **kw)


def car_two_lanes_over(mode: Mode = "robust", **kw: Any) -> Scene:
    """3 lanes; the ego in lane 0 at 20.6 m/s (set-point 20), a car two lanes over (lane 2) 2 m behind the
    ego's centre at 21 m/s with a slower car 81 m ahead of it, and a leader 52 m ahead of the ego: the trained
    agents' crash from a state called safe, ``cell00169-seed4001690001`` (step 34). The ego changes right
    into lane 1 while that car changes left into it: a side impact. When the car decides, the ego is not in
    lane 1, so MOBIL's incentive (which ``shield.level_incentive`` judges *with* the ego there, and which
    then keeps the car out) does not hold; ``shield.level_entering`` (off in the rule ``basic``)
    counts every level car into a lane the ego is only entering."""
    specs = [VehicleSpec(2, -2.0, 21.0), VehicleSpec(0, 52.0, 22.0), VehicleSpec(2, 79.0, 20.0)]
    return build_scene(0, 20.6, specs, mode=mode, lanes_count=3, ego_target_speed=20.0, **kw)


def closing_in_at_five_per_second(mode: Mode = "robust", **kw: Any) -> Scene:
    """5 decisions per second (15 Hz physics), one lane: the ego at 27.66 m/s (set-point 25) closes in on a
    car 39.22 m ahead at 15.82 m/s — the falsification grid's cell 812 (``cell00812-seed4008120005``, step 6)
    one decision before its invariant break. Braking from here takes the ego ≈ 6 s; the rule's horizon of
    13 *decisions* is 2.6 s at this rate, and the tail it credits beyond (the ego decaying to a set-point
    of 0) ends 1 m short of where the ego really stops. ``shield.full_horizon`` (off in the rule
    ``basic``) makes the horizon 13 *seconds* at every rate: nothing is safe here."""
    rate = {"env.policy_frequency": 5, "env.simulation_frequency": 15}
    specs = [VehicleSpec(0, 39.22, 15.82)]
    return build_scene(0, 27.66, specs, mode=mode, lanes_count=1, ego_target_speed=25.0, **rate, **kw)


def ego_turning_into_its_lane(mode: Mode = "robust", **kw: Any) -> Scene:
    """3 decisions per second, 3 lanes: the ego finishing a lane change into lane 2 (1.91 m short of its
    centre, heading 0.206 rad) at 22.77 m/s, set-point 20, a car 20.07 m ahead in lane 2 at 17.58 m/s —
    the falsification grid's cell 573 (``cell00573-seed4005730010``) one decision before its break. Along
    the road the ego moves at 22.29 m/s, which rounds to the 20 m/s set-point, so with
    ``shield.ego_speed_magnitude`` off (rule ``basic``) the rule took SLOWER to 15 m/s; highway-env rounds the
    controller's
    22.77 m/s to 25 and SLOWER goes to 20 m/s, 7 m less room. With the controller's speed (the default)
    SLOWER keeps 0.5 m, less than the margin."""
    rate = {"env.policy_frequency": 3, "env.simulation_frequency": 15}
    specs = [VehicleSpec(2, 20.07, 17.58)]
    return build_scene(
        2, 22.77, specs, mode=mode, lanes_count=3, ego_target_speed=20.0, ego_lateral=-1.91, ego_heading=0.206,
        **rate, **kw,
    )  # fmt: skip


def leader_may_turn_out(mode: Mode = "robust", **kw: Any) -> Scene:
    """2 decisions per second, one lane: the ego at 25 m/s (set-point 25) 24.62 m behind a car at 23.25 m/s —
    the 100 800-episode campaign's cell 332 (``cell00332-seed4003320017``) one decision before its break:
    the car braked at its limit *and* turned out of the lane (heading 0.25 rad), so its speed along the road
    fell faster than braking alone allows, and the next state's leader bound ended 2.1 m shorter.
    ``shield.turning_leaders`` (experimental, off) brakes a moving leader from its speed along its path less
    one lane change's cost along the road (1.66 m): IDLE is then unsafe here."""
    rate = {"env.policy_frequency": 2, "env.simulation_frequency": 10}
    return build_scene(0, 25.0, [VehicleSpec(0, 24.62, 23.25)], mode=mode, lanes_count=1, ego_target_speed=25.0,
                       **rate, **kw)  # fmt: skip


def reversing_car_beside(mode: Mode = "robust", **kw: Any) -> Scene:
    """5 lanes; the ego in lane 0 at 10.1 m/s (set-point 10), a leader 22.6 m ahead at 16.11 m/s; in lane 1 an
    Aggressive driver 8.9 m ahead rolls *backwards* at 3.01 m/s behind a car at 1.77 m/s, 15 m ahead — the
    trained agents' cell 615 (``cell00615-seed4006150077``) at the decision before its crash. Within that
    decision the reversing car began a lane change *away* from the ego: highway-env's steering assumes
    forward motion, so reversing, its nose swung 0.49 rad into the ego's lane and hit it. By its MOBIL rule
    (``shield.linear_mobil``) it would not cut in, and IDLE, FASTER and SLOWER are safe; with
    ``shield.reversing_cut_ins`` a car moving backwards may enter the ego's lane whatever MOBIL says, and
    nothing is safe (both options on, as in ``forecast-fallback``). With ``shield.linear_mobil`` off (rule
    ``basic``) any cut-in of a linear-model driver is assumed: nothing safe either."""
    specs = [
        VehicleSpec(1, 8.9, -3.01, vehicle_class=AggressiveVehicle),
        VehicleSpec(1, 15.0, 1.77, vehicle_class=AggressiveVehicle),
        VehicleSpec(0, 22.6, 16.11, vehicle_class=AggressiveVehicle),
    ]
    return build_scene(0, 10.1, specs, mode=mode, lanes_count=5, ego_target_speed=10.0, **kw)


def ego_crossing_a_lane(mode: Mode = "robust", **kw: Any) -> Scene:
    """5 decisions per second, 6 lanes: the ego in lane 1 at 10.43 m/s (set-point 10), 1.90 m right of its
    centre and turning at 0.764 rad, already heading for lane **3** (a lane change chained onto one under
    way); a Defensive driver 7.16 m behind in lane 2 — the lane the ego must cross — at 19.95 m/s, another
    13.77 m ahead in lane 1 at 18.01 m/s: the 100 800-episode campaign's cell 2833 (``cell02833-seed4028330025``)
    at its break, one decision before the ego was rear-ended in lane 2. With ``shield.crossed_lanes`` off (rule
    ``basic``) the ego is in its
    lane and its target only, so the car in lane 2 was nobody's follower and IDLE, FASTER and SLOWER kept
    7.11 m; with ``shield.crossed_lanes`` (on in ``forecast-fallback``) lane 2 is the ego's until it is through, and
    nothing is safe."""
    from highway_env.vehicle.behavior import DefensiveVehicle

    rate = {"env.policy_frequency": 5, "env.simulation_frequency": 15}
    specs = [
        VehicleSpec(2, -7.16, 19.95, vehicle_class=DefensiveVehicle),
        VehicleSpec(1, 13.77, 18.01, vehicle_class=DefensiveVehicle),
    ]
    return build_scene(
        1, 10.43, specs, mode=mode, lanes_count=6, ego_target_speed=10.0, ego_lateral=1.90, ego_heading=0.764,
        ego_target_lane=3, **rate, **kw,
    )  # fmt: skip


def ego_leaving_its_lane(mode: Mode = "robust", **kw: Any) -> Scene:
    """5 decisions per second, 4 lanes of Aggressive drivers braking hard: the ego in lane 1, 0.80 m left of its
    centre and turned -0.163 rad, 0.2 s into a change to lane 0, at 27.53 m/s (set-point 30); cars 20.9 and
    31.55 m ahead in lane 1, 41.03 and 51.44 m ahead in lane 0, followers in every lane — the 100 800-episode
    campaign's cell 2569 (``cell02569-seed4025690016``) at the decision before its break. LANE_LEFT keeps the
    change under way and is safe (2.74 m): the ego is out of lane 1 before the braking leader there matters.
    The rule times that exit from a lane centre at every decision, so one decision later it promises it 0.2 s
    later than now, and nothing is safe (the break); and IDLE, which in highway-env keeps the change under way
    just as LANE_LEFT does, counts lane 1 as the ego's for good."""
    rate = {"env.policy_frequency": 5, "env.simulation_frequency": 15}
    cars = [(2, 9.65, 20.12), (1, 20.9, 21.08), (1, 31.55, 23.31), (0, 41.03, 19.56), (0, 51.44, 22.66),
            (2, -11.96, 23.54), (1, -23.65, 24.47), (0, -34.97, 26.94), (3, -48.0, 28.01)]  # fmt: skip
    specs = [VehicleSpec(lane, dx, speed, vehicle_class=AggressiveVehicle) for lane, dx, speed in cars]
    return build_scene(
        1, 27.53, specs, mode=mode, lanes_count=4, ego_target_speed=30.0, ego_lateral=-0.80, ego_heading=-0.163,
        ego_target_lane=0, **rate, **kw,
    )  # fmt: skip


def car_rolling_back_turned_in(mode: Mode = "robust", **kw: Any) -> Scene:
    """2 lanes, a jam in lane 0: the ego in lane 1 at 10 m/s (set-point 10); 22.38 m ahead in lane 0 a car
    changing into the ego's lane (0.44 m off its centre, nose turned 0.166 rad toward lane 1) but rolling
    *backwards* at 0.086 m/s, as highway-env's IDM lets a jammed car do; more cars ahead — the trained agents'
    cell 126 (``cell00126-seed4001260042``) at its break. Backwards, its lateral
    motion points away from the ego, so the rule's heading projection put it in no lane of the ego's and IDLE
    kept 18.16 m; one decision later it moved forward, into the ego's lane, and nothing was safe (it hit the
    car two decisions later). ``shield.reversing_noses`` (on in ``forecast-fallback``) puts a car rolling backwards in
    the
    lane its nose points to: only SLOWER is safe (5.28 m)."""
    specs = [
        VehicleSpec(0, 22.38, -0.086, heading=0.1659, target_lane=1, lateral_offset=0.441),
        VehicleSpec(0, 32.74, 0.956),
        VehicleSpec(1, 45.19, 2.728, heading=0.4665, target_lane=1, lateral_offset=1.372),
    ]
    return build_scene(1, 10.0, specs, mode=mode, lanes_count=2, ego_target_speed=10.0, **kw)


def squeezed_by_a_follower(mode: Mode = "robust", **kw: Any) -> Scene:
    """5 decisions per second, 3 lanes of IDM drivers: the ego in lane 1 at 18.32 m/s (set-point 15) 9.36 m
    behind a car at 16.87 m/s that has braked at its limit for a second, an IDM car 36.3 m behind at 21.57 m/s,
    both next lanes taken — the 100 800-episode campaign's cell 2415 (``cell02415-seed4024150004``) at its
    break. One decision earlier IDLE and SLOWER kept 1.37 m; the follower bound (accelerate for the reaction
    time, then brake) starts again at every decision, so 0.2 s later, with the follower already braking and the
    leader no worse than its bound, they kept 0.745 m, and nothing was safe. ``shield.follower_idm`` (on in
    ``forecast-fallback``) lets the car behind brake by IDM's own response to the ego: IDLE and SLOWER keep 1.415 m."""
    rate = {"env.policy_frequency": 5, "env.simulation_frequency": 15}
    cars = [(1, 9.36, 16.87), (1, 20.66, 17.0), (1, 32.68, 18.34), (0, 48.39, 21.82), (2, 59.65, 21.62),
            (2, -9.98, 23.02), (0, -20.28, 25.02), (1, -36.3, 21.57), (2, -47.6, 23.71)]  # fmt: skip
    specs = [VehicleSpec(lane, dx, speed) for lane, dx, speed in cars]
    return build_scene(1, 18.32, specs, mode=mode, lanes_count=3, ego_target_speed=15.0, **rate, **kw)


def squeeze_beside_a_free_lane(mode: Mode = "robust", **kw: Any) -> Scene:
    """A spawn with no safe action, two lanes of Defensive drivers (the linear model, 2.5 s time gap): the ego
    in lane 0 at 25 m/s, 13.4 m behind a car at 22 m/s that its own leader, 28.8 m further at 22.1 m/s, makes
    brake at its limit; lane 1 free for 28 m (a car there at 22.7 m/s) — the claim campaign's
    ``cell00117-seed4001170018`` at its first decision, rebuilt. Every action collides in the worst case and
    SLOWER least; the forecast of the leader's own law has it brake now and SLOWER run into it, changing lane
    get away: ``shield.forecast_fallback`` (on in ``forecast-fallback``) picks LANE_RIGHT."""
    from highway_env.vehicle.behavior import DefensiveVehicle

    cars = [(0, 13.4, 22.0), (1, 28.0, 22.7), (0, 42.2, 22.1), (0, 56.9, 23.3)]
    specs = [VehicleSpec(lane, dx, speed, vehicle_class=DefensiveVehicle) for lane, dx, speed in cars]
    return build_scene(0, 25.0, specs, mode=mode, lanes_count=2, **kw)


def queue_braking_beside_the_ego(mode: Mode = "robust", **kw: Any) -> Scene:
    """A hole of the rule, not closed (docs/research/fallback-choice.md, the next-lane class of
    docs/research/remaining-breaks.md): 5 lanes of Aggressive
    drivers (the linear model, each with the gains highway-env drew for it), the ego in lane 3 at 20.66 m/s
    (set-point 20); its right lane is a queue braking at its limit, the first of it 6.88 m ahead at 16.87 m/s,
    and 6.78 m behind in that lane a car at 23.05 m/s (set-point 29.05) — the claim campaign's
    ``cell00552-seed4005520033`` one decision before its invariant break, rebuilt from the highway-env state
    with the 7 cars that keep its masks, gaps, break and crash. SLOWER alone is safe (18.70 m). One decision
    later the ego (15.75 m/s) and the car behind (17.05 m/s, braking for the queue) are level, 4.08 m apart
    centre to centre: turning in behind the ego now pays under MOBIL, and nothing is safe. It turns in and
    rear-ends the ego during the next decision. The car behind was not a turn-in candidate one decision before
    (MOBIL's incentive could not pay during that decision), so the rule's one-state turn-in bound restarted;
    extending it over the whole horizon made breaks 25 times more frequent (docs/research/remaining-breaks.md)."""
    cars = [
        (4, 6.88, 16.87, 22.87, 0.2, (0.278, 0.275, 1.408), (4.979, 7.970)),
        (4, 15.45, 15.65, 21.65, 1.01, (0.323, 0.203, 2.828), (4.975, 7.876)),
        (4, 31.73, 16.26, 21.27, 0.2, (0.210, 0.447, 1.191), (4.938, 7.026)),
        (2, 68.87, 15.10, 21.10, 0.4, (0.323, 0.417, 2.514), (5.041, 8.006)),
        (4, -6.78, 23.05, 29.05, 0.8, (0.351, 0.195, 1.687), (5.043, 9.554)),
        (3, -23.70, 15.16, 21.16, 0.8, (0.198, 0.284, 2.967), (5.004, 8.275)),
    ]
    specs = drawn_drivers(cars, AggressiveVehicle)
    specs.append(
        VehicleSpec(
            0, 53.0, 16.86, heading=0.3762, target_lane=1, vehicle_class=AggressiveVehicle, lateral_offset=0.941,
            target_speed=22.86, lane_change_timer=0.2, acceleration_parameters=(0.162, 0.369, 2.435),
            steering_parameters=(5.029, 8.065),
        )
    )  # fmt: skip
    return build_scene(3, 20.66, specs, mode=mode, lanes_count=5, ego_target_speed=20.0, others_collide=False, **kw)


def squeezed_by_a_linear_follower(mode: Mode = "robust", **kw: Any) -> Scene:
    """A hole of the rule, not closed (docs/research/car-behind.md, docs/research/nested-follower-bound.md): 5
    decisions per second, Linear drivers
    (``LinearVehicle``, each with the set-point, MOBIL timer and gains highway-env drew for it), the ego in the
    leftmost lane at 13.34 m/s (set-point 10) 15.08 m behind a car at 9.74 m/s, a car 77.1 m behind it at
    26.33 m/s (set-point 29.97), and in the next lane a car 19.69 m behind at 22.28 m/s — the claim campaign's
    ``cell02879-seed4028790006`` one decision before its invariant break, rebuilt from the highway-env state
    with the 10 cars that keep the masks of all nine states, both states' gaps, the break and the crash (on 3
    lanes: the campaign's other 3, empty by then, change none of these). IDLE and SLOWER keep 1.32 m. 0.2 s
    later the leader brakes at its limit and the car behind has begun to brake; the follower bound (accelerate
    for the 0.5 s reaction time, then brake) starts again, and nothing is safe (IDLE −0.64 m); with the car
    behind braking from now (a diagnostic, not a bound) IDLE and SLOWER would keep 1.36 and 2.36 m. Three
    fallback decisions later the least-bad action is LANE_RIGHT, and the car behind in that lane rear-ends the
    braking ego."""
    rate = {"env.policy_frequency": 5, "env.simulation_frequency": 15}
    cars = [
        (0, 15.08, 9.74, 21.74, 0.867, (0.354, 0.224, 2.947), (5.062, 6.902)),
        (0, 35.41, 12.04, 23.28, 1.0, (0.173, 0.213, 2.089), (4.959, 7.066)),
        (1, 44.08, 11.20, 23.20, 0.4, (0.304, 0.204, 2.020), (5.022, 9.636)),
        (1, 50.73, 13.62, 21.73, 0.667, (0.285, 0.368, 2.628), (4.947, 8.709)),
        (2, 59.14, 10.40, 22.40, 0.267, (0.232, 0.157, 1.297), (5.061, 9.468)),
        (2, 75.17, 19.67, 21.34, 0.8, (0.378, 0.433, 1.864), (5.004, 9.545)),
        (2, -7.32, 23.01, 29.78, 0.667, (0.205, 0.340, 1.794), (5.046, 7.493)),
        (1, -19.69, 22.28, 28.09, 0.733, (0.394, 0.273, 1.706), (5.032, 7.718)),
        (0, -77.10, 26.33, 29.97, 0.467, (0.303, 0.284, 1.129), (4.956, 8.809)),
    ]
    specs = drawn_drivers(cars, LinearVehicle)
    specs.append(  # finishing a change from lane 3 into lane 2
        VehicleSpec(
            2, -92.26, 26.0, heading=0.0569, target_lane=2, vehicle_class=LinearVehicle, lateral_offset=-0.365,
            target_speed=27.82, lane_change_timer=1.0, acceleration_parameters=(0.377, 0.163, 1.415),
            steering_parameters=(4.937, 9.558),
        )
    )  # fmt: skip
    return build_scene(
        0, 13.34, specs, mode=mode, lanes_count=3, ego_target_speed=10.0, others_collide=False, **rate, **kw
    )


def car_settling_next_to_the_ego(mode: Mode = "robust", **kw: Any) -> Scene:
    """6 lanes; the ego in lane 5 at 29.34 m/s (set-point 30); 25.18 m ahead a car at 17.16 m/s that has just
    crossed from lane 3 into lane 4, the lane next to the ego, 1.27 m short of its centre and still turned
    0.188 rad toward it (its target lane is lane 4) — a break the 100 800-episode campaign found with the
    overtaking probe at 1 decision per second, of the ``second_lane_cut_in`` class. With
    ``shield.finishing_changes`` off (rule ``basic``) the heading projection put the car in the ego's lane from now,
    braking: nothing was safe. With ``shield.finishing_changes`` (on in ``forecast-fallback``)
    it is a car finishing its change into lane 4, a cut-in candidate from there, and MOBIL would not let it cut
    in 25 m ahead of a car closing at 12 m/s: IDLE and SLOWER are safe."""
    specs = [
        VehicleSpec(3, 7.29, 15.11, heading=-0.4212, target_lane=2, lateral_offset=-1.053),
        VehicleSpec(4, 25.18, 17.16, heading=0.1878, target_lane=4, lateral_offset=-1.267),
        VehicleSpec(3, 44.13, 22.76),
    ]
    return build_scene(5, 29.34, specs, mode=mode, lanes_count=6, ego_target_speed=30.0, **kw)


def car_passing_a_stopped_ego(mode: Mode = "robust", **kw: Any) -> Scene:
    """3 lanes; the ego stopped in lane 0 (set-point 0); in lane 1 a car 3.09 m ahead passing it at 20.64 m/s —
    the 100 800-episode campaign's cell 615 (``cell00615-seed4006150027``, the random policy, 1 decision per
    second) at its break. MOBIL's safety criterion forbids the car to cut in now (the ego, 3 m behind it, would
    have to brake at 28 m/s²) but allows it at the end of the decision, 24 m ahead; with the option off (rule ``basic``)
    that is a cut-in from the cut-in time (0 s at 5 Hz physics), 3 m ahead: nothing was safe. With
    ``shield.cut_in_when_permitted`` (on in ``forecast-fallback``) the cut-in starts from
    the first frame MOBIL allows it: IDLE is safe."""
    return build_scene(0, 0.0, [VehicleSpec(1, 3.09, 20.64)], mode=mode, lanes_count=3, ego_target_speed=0.0, **kw)


def car_passing_in_the_next_lane(mode: Mode = "robust", **kw: Any) -> Scene:
    """2 lanes, 2 decisions per second; the ego stopped in lane 0 (set-point 0); in lane 1 a car 1.05 m behind
    it at 25.66 m/s, passing — the 100 800-episode campaign's cell 723 (``cell00723-seed4007230023``, the
    overtaking probe) at its break, the largest class of the breaks left (the culprit in the next lane, behind).
    MOBIL lets it cut in only ahead of the ego, at least 7.75 m ahead; the rule bounded it as a follower in the
    ego's lane, driving on through the ego: nothing safe. With ``shield.passing_cut_ins`` (on in
    ``forecast-fallback``) it is a leader from its cut-in: IDLE keeps 5.50 m, FASTER 1.36 m."""
    sets = {"env.policy_frequency": 2, "env.simulation_frequency": 10}
    specs = [VehicleSpec(1, -1.05, 25.66)]
    return build_scene(0, 0.0, specs, mode=mode, lanes_count=2, ego_target_speed=0.0, **sets, **kw)


SCENARIOS: dict[str, Callable[..., Scene]] = {
    "leader_braking": leader_braking,
    "stopped_car_ahead": stopped_car_ahead,
    "slow_car_in_target_lane": slow_car_in_target_lane,
    "fast_follower_in_target_lane": fast_follower_in_target_lane,
    "cut_in_from_left": cut_in_from_left,
    "cut_in_from_right": cut_in_from_right,
    "ego_leftmost_lane": ego_leftmost_lane,
    "ego_rightmost_lane": ego_rightmost_lane,
    "dense_jam": dense_jam,
    "adjacent_car_ahead": adjacent_car_ahead,
    "second_lane_car_moving_over": second_lane_car_moving_over,
    "slow_car_turning_out": slow_car_turning_out,
    "linear_car_alongside": linear_car_alongside,
    "reversing_leader": reversing_leader,
    "car_being_overtaken": car_being_overtaken,
    "car_two_lanes_over": car_two_lanes_over,
    "closing_in_at_five_per_second": closing_in_at_five_per_second,
    "ego_turning_into_its_lane": ego_turning_into_its_lane,
    "leader_may_turn_out": leader_may_turn_out,
    "reversing_car_beside": reversing_car_beside,
    "ego_crossing_a_lane": ego_crossing_a_lane,
    "ego_leaving_its_lane": ego_leaving_its_lane,
    "car_rolling_back_turned_in": car_rolling_back_turned_in,
    "squeezed_by_a_follower": squeezed_by_a_follower,
    "car_settling_next_to_the_ego": car_settling_next_to_the_ego,
    "car_passing_a_stopped_ego": car_passing_a_stopped_ego,
    "car_passing_in_the_next_lane": car_passing_in_the_next_lane,
    "squeeze_beside_a_free_lane": squeeze_beside_a_free_lane,
    "queue_braking_beside_the_ego": queue_braking_beside_the_ego,
    "squeezed_by_a_linear_follower": squeezed_by_a_linear_follower,
}
"""Every scenario by name."""


def min_safe_gap(
    ego_speed: float,
    leader_speed: float,
    action: int,
    *,
    mode: Mode = "robust",
    resolution: float = 0.5,
    max_gap: float = 400.0,
    **kw: Any,
) -> float:
    """Smallest centre-to-centre distance [m] to a leader in the ego's lane at which ``action`` is safe.

    The ego (lane 1, at ``ego_speed`` [m/s], set-point the nearest target speed) follows one leader at
    ``leader_speed`` [m/s]; bisection to ``resolution`` [m] on the real shield (a farther leader is never
    less safe). ``inf`` if the action is unsafe even ``max_gap`` m behind it. This is the room the
    shield asks for, so it bounds how densely — and so how fast through traffic — any policy can drive.
    """

    def safe(gap: float) -> bool:
        scene = build_scene(1, ego_speed, [VehicleSpec(1, gap, leader_speed)], mode=mode, **kw)
        try:
            return bool(scene.result.safe[action])
        finally:
            scene.env.close()

    low, high = 5.0, max_gap
    if not safe(high):
        return float("inf")
    if safe(low):
        return low
    while high - low > resolution:
        mid = 0.5 * (low + high)
        if safe(mid):
            high = mid
        else:
            low = mid
    return high
