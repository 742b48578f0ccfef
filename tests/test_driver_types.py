"""Traffic with a mixture of driver types (``traffic.driver_mix``, the ``hidden-types`` preset) on both simulators.

The draw (one ``choice`` per car, the environment's own generator), its frequencies against the weights, the same
types from the same seed on highway-env and the fast simulator, bit-identical episodes, what the snapshot tells
the shield (hidden or seen types), the ``paper-types`` state, and bad mixtures as one-line errors.
"""

from __future__ import annotations

import math
from pathlib import Path

import gymnasium as gym
import highway_env  # noqa: F401  (registers highway-v0 / highway-fast-v0)
import numpy as np
import pytest
import yaml
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle, LinearVehicle
from scipy import stats

import safelane
from safelane.config import ConfigError, load_config
from safelane.core.drivers import DRIVER_TYPES, NAMED_MIXES, DriverMix, parse_driver_mix
from safelane.core.snapshot import DRIVER_FIELDS
from safelane.core.spaces import OBS_SIZE, OBSERVED_VEHICLES
from safelane.env.factory import resolve_env_config
from safelane.env.fast_batch import supports
from safelane.env.observations import observed_vehicles, paper_state
from safelane.env.vector import FastVectorEnv, make_vector_env
from safelane.sim.drivers import AggressiveDriver, NormalDriver, TimidDriver
from safelane.sim.fast import FastHighwayEnv
from safelane.sim.fast import layout as L
from safelane.sim.fast.check import compare_episode, make_oracle, policy_actions
from safelane.sim.fast.scene import build_scene, build_scene_python, make_rng, params, resolve_config
from safelane.sim.traffic import TrafficLayout

TOL = 1e-6
MIX = parse_driver_mix("timid-normal-aggressive")
UNEVEN = parse_driver_mix(
    [{"type": "timid", "weight": 0.2}, {"type": "normal", "weight": 0.5}, {"type": "aggressive", "weight": 0.3}]
)
LINEAR_AND_IDM = parse_driver_mix(
    [{"type": "IDMVehicle", "weight": 1}, {"type": "DefensiveVehicle", "weight": 2},
     {"type": "aggressive", "weight": 1}]
)  # fmt: skip


def _preset(name: str) -> tuple[dict, str]:
    data = yaml.safe_load((Path(safelane.__file__).parent / "presets" / f"{name}.yaml").read_text())
    return data["env"], data["env_id"]


# --- the parameter sets ------------------------------------------------------------------------------------------


def test_the_three_sets_are_sunberg_et_al_s_on_highway_env_s_idm() -> None:
    """a, b, T, s₀ (+ a car's length: highway-env measures centre to centre), p, b_safe, a_thr (strict)."""
    expected = {
        TimidDriver: (0.8, 1.0, 2.0, 4.0, 1.0, 1.0, 0.2),
        NormalDriver: (1.4, 2.0, 1.5, 2.0, 0.5, 2.0, 0.1),
        AggressiveDriver: (2.0, 3.0, 1.0, 0.0, 0.0, 3.0, 0.0),
    }
    for cls, (a, b, tw, s0, p, b_safe, a_thr) in expected.items():
        assert issubclass(cls, IDMVehicle) and not issubclass(cls, LinearVehicle)
        assert (a, b, tw) == (cls.COMFORT_ACC_MAX, -cls.COMFORT_ACC_MIN, cls.TIME_WANTED)
        assert s0 + cls.LENGTH == cls.DISTANCE_WANTED
        assert (p, b_safe) == (cls.POLITENESS, cls.LANE_CHANGE_MAX_BRAKING_IMPOSED)
        assert math.nextafter(a_thr, math.inf) == cls.LANE_CHANGE_MIN_ACC_GAIN
        # what stays highway-env's
        assert (cls.ACC_MAX, cls.DELTA_RANGE, cls.LANE_CHANGE_DELAY) == (
            IDMVehicle.ACC_MAX, IDMVehicle.DELTA_RANGE, IDMVehicle.LANE_CHANGE_DELAY
        )  # fmt: skip


@pytest.mark.parametrize("cls", [TimidDriver, NormalDriver, AggressiveDriver])
def test_a_driver_with_nothing_to_gain_keeps_its_lane(cls: type) -> None:
    """Alone on a three-lane road (every lane as free as its own), MOBIL's strict threshold keeps the car in its lane
    for 20 s; with highway-env's own test and the aggressive set's 0 it would change lanes at every check."""
    road = Road(network=RoadNetwork.straight_road_network(3, speed_limit=30), np_random=np.random.default_rng(0))
    car = cls(road, road.network.get_lane(("0", "1", 1)).position(0, 0), speed=25.0)
    road.vehicles.append(car)
    for _ in range(20 * 15):
        road.act()
        road.step(1 / 15)
        assert car.target_lane_index[2] == 1


# --- the draw ------------------------------------------------------------------------------------------------------


def test_mixture_frequencies_match_the_weights() -> None:
    """Types over 200 fast-simulator resets (10 000 cars) against the weights: each count inside its two-sided
    binomial interval at a family-wise level of 1e-6 (Bonferroni over the types)."""
    cfg, env_id = _preset("fast")
    env = FastHighwayEnv(cfg, env_id, driver_mix=UNEVEN)
    counts = np.zeros(len(UNEVEN.types), dtype=np.int64)
    for seed in range(200):
        _, info = env.reset(seed=seed)
        counts += np.bincount(info["snapshot"].driver_type[1:], minlength=len(UNEVEN.types))
    n = int(counts.sum())
    assert n == 200 * cfg["vehicles_count"]
    alpha = 1e-6 / len(UNEVEN.types)
    for count, p in zip(counts, UNEVEN.probabilities, strict=True):
        low, high = stats.binom.interval(1 - alpha, n, p)
        assert low <= count <= high, (counts, UNEVEN.probabilities)


def test_one_choice_per_car_from_the_road_generator() -> None:
    """The Python twin (the generator's own calls) and the replay from raw outputs build the same scene and leave
    the generator in the same state as highway-env's spawn; a zero weight is never drawn."""
    cfg, env_id = _preset("fast")
    zero = parse_driver_mix(
        [{"type": "timid", "weight": 1}, {"type": "normal", "weight": 0}, {"type": "aggressive", "weight": 1}]
    )
    for mix in (MIX, UNEVEN, LINEAR_AND_IDM, zero):
        sc, P = resolve_config(cfg, env_id, mix), params()
        oracle = make_oracle(cfg, env_id, driver_mix=mix)
        for seed in range(5):
            oracle.reset(seed=seed)
            rng_a, rng_b = make_rng(seed), make_rng(seed)
            fa, ga, _ = build_scene(rng_a, sc, P)
            fb, gb, _ = build_scene_python(rng_b, sc, P)
            assert np.array_equal(fa, fb) and np.array_equal(ga, gb)
            assert rng_a.bit_generator.state == rng_b.bit_generator.state
            assert rng_a.bit_generator.state == oracle.unwrapped.np_random.bit_generator.state
            types = [getattr(v, "driver_type", -1) for v in oracle.unwrapped.road.vehicles]
            assert types == ga[:, L.DTYPE].tolist()
            assert [type(v) for v in oracle.unwrapped.road.vehicles[1:]] == [sc.other_classes[t] for t in types[1:]]
        if mix is zero:
            assert 1 not in ga[:, L.DTYPE]


@pytest.mark.parametrize("behind", [0, 15])
def test_same_seed_same_types_on_both_simulators(behind: int) -> None:
    """make_env on the hidden-types preset: the same seed gives the same types (and the same scene) on both."""
    sets = [f"traffic.vehicles_behind={behind}"]
    envs = [safelane.make_env(load_config("hidden-types", sets=[*sets, f"simulator={sim}"]))
            for sim in ("highway-env", "fast")]  # fmt: skip
    seen = []
    for seed in range(6):
        snaps = [env.reset(seed=seed)[1]["snapshot"] for env in envs]
        assert snaps[0] == snaps[1], snaps[0].first_difference(snaps[1])
        assert snaps[0].driver_type[0] == -1 and (snaps[0].driver_type[1:] >= 0).all()
        seen.append(snaps[0].driver_type)
    assert not all(np.array_equal(seen[0], s) for s in seen[1:])  # another seed, other types


# --- bit-identical episodes ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "mix", "seed", "policy", "behind"),
    [
        ("fast", MIX, 0, "random", 0),
        ("fast", UNEVEN, 1, "faster", 10),
        ("paper", MIX, 2, "cautious", 0),  # highway-v0: 15 Hz, every pair's collisions
        ("fast", LINEAR_AND_IDM, 3, "weave", 0),
    ],
)
def test_whole_episode_is_bit_identical(name: str, mix: DriverMix, seed: int, policy: str, behind: int) -> None:
    cfg, env_id = _preset(name)
    r = compare_episode(cfg, env_id, seed, policy_actions(policy, seed), tol=TOL, stop_at_end=False,
                        vehicles_behind=behind, snapshots=True, driver_mix=mix)  # fmt: skip
    assert r.matched, f"diverged after decision {r.divergent_step}: {r.cause}"
    assert r.bitwise


def test_seen_types_episode_is_bit_identical_too() -> None:
    cfg, env_id = _preset("fast")
    seen = DriverMix(LINEAR_AND_IDM.types, LINEAR_AND_IDM.weights, assumed=None)
    r = compare_episode(cfg, env_id, 4, policy_actions("random", 4), tol=TOL, snapshots=True, driver_mix=seen)
    assert r.matched and r.bitwise, r.cause


@pytest.mark.slow
@pytest.mark.parametrize("name", ["fast", "paper"])
def test_episodes_are_bit_identical_slow(name: str) -> None:
    cfg, env_id = _preset(name)
    oracle = make_oracle(cfg, env_id, snapshots=True, driver_mix=MIX)
    fast = FastHighwayEnv(cfg, env_id, driver_mix=MIX)
    for seed in range(10, 16):
        for policy in ("random", "faster", "slower", "weave"):
            r = compare_episode(cfg, env_id, seed, policy_actions(policy, seed), TOL, oracle, fast, stop_at_end=False,
                                snapshots=True)  # fmt: skip
            assert r.matched and r.bitwise, (seed, policy, r.cause)


def test_sim_check_on_the_preset_compares_the_types() -> None:
    from safelane.running.simcheck import run_sim_check

    cfg = load_config("hidden-types", sets=["env.duration=6"])
    result = run_sim_check(cfg, episodes=2, seed=0, stat_episodes=0, continuous=False)
    assert result["trajectory_match_fraction"] == 1.0 and result["bit_identical_fraction"] == 1.0, result


def test_batch_equals_the_single_environments() -> None:
    """FastBatch plays the hidden-types preset with the types seen by the robust shield: row i is
    make_env(simulator=fast, seed=S+i) driven by the same actions (observations, rewards, flags, masks), autoresets
    included. With the types hidden the robust shield judges one reading per type at once, which the batch's kernel
    does not: it leaves those to the environments one by one."""
    hidden = resolve_env_config("hidden-types", simulator="fast", **{"shield.mode": "robust"})
    assert "hidden driver types" in str(supports(hidden))
    sets = {"env.duration": 4, "shield.mode": "robust", "traffic.shield_sees_types": True}
    assert supports(resolve_env_config("hidden-types", simulator="fast", **sets)) is None
    n, seed = 3, 31
    vector = make_vector_env("hidden-types", num_envs=n, **sets)
    assert isinstance(vector, FastVectorEnv)
    singles = [safelane.make_env("hidden-types", simulator="fast", **sets) for _ in range(n)]
    obs, infos = vector.reset(seed=seed)
    for i, env in enumerate(singles):
        o, info = env.reset(seed=seed + i)
        assert np.array_equal(obs[i], o) and np.array_equal(infos["action_mask"][i], info["action_mask"])
    rng = np.random.default_rng(3)
    for _ in range(8):
        actions = rng.integers(5, size=n)
        obs, rewards, terminated, truncated, infos = vector.step(actions)
        for i, env in enumerate(singles):
            o, r, te, tr, info = env.step(int(actions[i]))
            assert rewards[i] == r and terminated[i] == te and truncated[i] == tr
            if te or tr:
                o, info = env.reset()
            assert np.array_equal(obs[i], o)
            assert np.array_equal(vector.action_masks()[i], info["action_mask"])
    vector.close()


# --- what the shield reads ------------------------------------------------------------------------------------------


def _fields(snap, name: str) -> np.ndarray:
    return np.asarray(getattr(snap, name))


@pytest.mark.parametrize("sim", ["highway-env", "fast"])
def test_hidden_types_give_the_shield_the_assumed_driver_only(sim: str) -> None:
    """Hidden (the preset's default): every drawn car reports IDMVehicle's parameters but its own IDM exponent;
    seen: its own type's."""
    hidden = safelane.make_env(load_config("hidden-types", sets=[f"simulator={sim}"]))
    seen = safelane.make_env(load_config("hidden-types", sets=[f"simulator={sim}", "traffic.shield_sees_types=true"]))
    snap_h = hidden.reset(seed=3)[1]["snapshot"]
    snap_s = seen.reset(seed=3)[1]["snapshot"]
    assert np.array_equal(snap_h.position, snap_s.position) and np.array_equal(snap_h.driver_type, snap_s.driver_type)
    others = snap_h.others()
    assumed = {"idm_comfort_acc": IDMVehicle.COMFORT_ACC_MAX, "idm_comfort_dec": IDMVehicle.COMFORT_ACC_MIN,
               "idm_distance_wanted": IDMVehicle.DISTANCE_WANTED, "idm_time_wanted": IDMVehicle.TIME_WANTED,
               "max_braking_imposed": IDMVehicle.LANE_CHANGE_MAX_BRAKING_IMPOSED,
               "accel_max": IDMVehicle.COMFORT_ACC_MAX, "brake_max": IDMVehicle.ACC_MAX,
               "politeness": IDMVehicle.POLITENESS}  # fmt: skip
    classes = (TimidDriver, NormalDriver, AggressiveDriver)
    for name, value in assumed.items():
        assert (_fields(snap_h, name)[others] == value).all(), name
        own = np.array([getattr(classes[t], _CLASS_ATTR[name]) for t in snap_s.driver_type[others]])
        assert np.array_equal(_fields(snap_s, name)[others], own), name
    for name in ("idm_delta", "can_change_lane", "linear_speed_gain"):
        assert np.array_equal(_fields(snap_h, name), _fields(snap_s, name), equal_nan=name != "can_change_lane")
    assert len({float(x) for x in snap_h.idm_delta[others]}) > 1  # each car's own drawn exponent


_CLASS_ATTR = {
    "idm_comfort_acc": "COMFORT_ACC_MAX", "idm_comfort_dec": "COMFORT_ACC_MIN",
    "idm_distance_wanted": "DISTANCE_WANTED", "idm_time_wanted": "TIME_WANTED",
    "max_braking_imposed": "LANE_CHANGE_MAX_BRAKING_IMPOSED", "accel_max": "COMFORT_ACC_MAX", "brake_max": "ACC_MAX",
    "politeness": "POLITENESS",
}  # fmt: skip


def test_hidden_snapshot_does_not_depend_on_the_drawn_types() -> None:
    """Two mixtures that draw the same scene but other types (the draw is one double per car either way): with the
    types hidden, the shield reads the same driver fields."""
    cfg, env_id = _preset("fast")
    one = DriverMix(("timid", "aggressive"), (1.0, 1.0))
    other = DriverMix(("aggressive", "timid"), (1.0, 1.0))
    envs = [FastHighwayEnv(cfg, env_id, driver_mix=m) for m in (one, other)]
    snaps = [env.reset(seed=5)[1]["snapshot"] for env in envs]
    assert np.array_equal(snaps[0].position, snaps[1].position)
    assert (envs[0].F[1:, L.TW] != envs[1].F[1:, L.TW]).all()  # every car drives with the other set's time gap
    for name in DRIVER_FIELDS:
        assert np.array_equal(_fields(snaps[0], name), _fields(snaps[1], name), equal_nan=name != "can_change_lane")


def test_assumed_linear_driver_reports_its_nominal_gains_on_both_simulators() -> None:
    cfg, env_id = _preset("fast")
    mix = DriverMix(MIX.types, MIX.weights, assumed="DefensiveVehicle")
    r = compare_episode(cfg, env_id, 7, policy_actions("random", 7)[:5], tol=TOL, snapshots=True, driver_mix=mix)
    assert r.matched and r.bitwise, r.cause
    snap = FastHighwayEnv(cfg, env_id, driver_mix=mix).reset(seed=7)[1]["snapshot"]
    from highway_env.vehicle.behavior import DefensiveVehicle

    assert snap.linear_speed_gain[1] == DefensiveVehicle.ACCELERATION_PARAMETERS[0]
    assert np.isnan(snap.linear_speed_gain[0])


# --- the matched arm's state -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("sim", ["highway-env", "fast"])
def test_paper_types_state_appends_each_observed_car_s_type(sim: str) -> None:
    env = safelane.make_env(load_config("hidden-types", sets=[f"simulator={sim}", "state=paper-types"]))
    k = len(MIX.types)
    assert env.observation_space.shape == (OBS_SIZE + OBSERVED_VEHICLES * k,)
    obs, info = env.reset(seed=1)
    for _ in range(3):
        obs, *_, info = env.step(1)
    snap = info["snapshot"]
    assert obs.shape == env.observation_space.shape and obs.dtype == np.float32
    np.testing.assert_array_equal(obs[:OBS_SIZE], paper_state(snap))
    onehot = obs[OBS_SIZE:].reshape(OBSERVED_VEHICLES, k)
    near = observed_vehicles(snap)
    assert len(near) == OBSERVED_VEHICLES
    for slot, i in enumerate(near):
        assert onehot[slot].sum() == 1.0 and onehot[slot, snap.driver_type[i]] == 1.0
        assert obs[slot * 6 + 5] == 1.0  # eq. 3's presence flag of the same slot


def test_hidden_arm_state_is_the_paper_s() -> None:
    env = safelane.make_env(load_config("hidden-types", sets=["simulator=fast"]))
    obs, info = env.reset(seed=2)
    assert obs.shape == (OBS_SIZE,)
    np.testing.assert_array_equal(obs, paper_state(info["snapshot"]))


# --- the existing traffic is untouched --------------------------------------------------------------------------------


@pytest.mark.parametrize("preset", ["fast", "paper"])
def test_existing_presets_draw_nothing_more(preset: str) -> None:
    """Without a mixture the environment's highway-env is highway-env's own: the same scene and generator state as
    a bare gym.make, no driver types in the snapshot."""
    cfg = load_config(preset)
    env = safelane.make_env(cfg)
    bare = gym.make(cfg.env_id, config=dict(cfg.env))
    for seed in (0, 1):
        _, info = env.reset(seed=seed)
        bare.reset(seed=seed)
        assert info["snapshot"].driver_type is None
        x = [v.position[0] for v in bare.unwrapped.road.vehicles]
        assert np.array_equal(info["snapshot"].position[:, 0], x)
        assert env.unwrapped.np_random.bit_generator.state == bare.unwrapped.np_random.bit_generator.state
    fast = FastHighwayEnv(dict(cfg.env), cfg.env_id)
    assert fast.reset(seed=0)[1]["snapshot"].driver_type is None


# --- bad mixtures ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("assignment", "key", "says"),
    [
        ("traffic.driver_mix=[{type: reckless, weight: 1}]", "traffic.driver_mix[0].type", "timid, normal"),
        ("traffic.driver_mix=[{type: timid, weight: -1}]", "traffic.driver_mix[0].weight", ">= 0"),
        ("traffic.driver_mix=[{type: timid, weight: 0}, {type: normal, weight: 0}]", "traffic.driver_mix",
         "positive sum"),
        ("traffic.driver_mix=[{type: timid, weight: .nan}]", "traffic.driver_mix[0].weight", "finite"),
        ("traffic.driver_mix=[{type: timid, weight: 1}, {type: timid, weight: 2}]", "traffic.driver_mix[1].type",
         "each type once"),
        ("traffic.driver_mix=[{type: timid}]", "traffic.driver_mix[0]", "type, weight"),
        ("traffic.driver_mix=[]", "traffic.driver_mix", "timid-normal-aggressive"),
        ("traffic.driver_mix=sunny", "traffic.driver_mix", "timid-normal-aggressive"),
        ("traffic.assumed_driver=reckless", "traffic.assumed_driver", "IDMVehicle"),
        ("traffic.shield_sees_types=true", "traffic.shield_sees_types", "driver_mix"),
        ("state=paper-types", "state", "driver_mix"),
    ],
)  # fmt: skip
def test_bad_mixture_is_one_line_naming_the_field(assignment: str, key: str, says: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_config("fast", sets=[assignment])
    message = str(err.value)
    assert "\n" not in message and message.startswith(key) and says in message, message


def test_a_mixture_replaces_other_vehicles_type() -> None:
    with pytest.raises(ConfigError, match=r"^env\.other_vehicles_type: .*driver_mix"):
        load_config("hidden-types", sets=["env.other_vehicles_type=highway_env.vehicle.behavior.IDMVehicle"])


def test_every_named_mixture_and_type_resolves() -> None:
    for name in NAMED_MIXES:
        mix = parse_driver_mix(name)
        assert mix is not None and math.isclose(float(mix.probabilities.sum()), 1.0)
    sc = resolve_config(None, "highway-fast-v0", DriverMix(tuple(DRIVER_TYPES), (1.0,) * len(DRIVER_TYPES)))
    assert sc.drivers.shape == (len(DRIVER_TYPES), L.ND)


def test_fast_simulator_refuses_idm_and_linear_types_with_a_continuous_ego() -> None:
    with pytest.raises(ValueError, match=r"^traffic\.driver_mix: .*allowed there"):
        FastHighwayEnv({"action": {"type": "ContinuousAction"}}, "highway-fast-v0", driver_mix=LINEAR_AND_IDM)


def test_traffic_layout_records_its_mixture() -> None:
    cfg, env_id = _preset("fast")
    env = TrafficLayout(gym.make(env_id, config=cfg), driver_mix=MIX)
    env.reset(seed=0)
    assert env.unwrapped.safelane_driver_mix.mix == MIX
    assert env.unwrapped.config["other_vehicles_type"] == cfg.get(
        "other_vehicles_type", "highway_env.vehicle.behavior.IDMVehicle"
    )  # the spawn swaps it only while the scene is built
