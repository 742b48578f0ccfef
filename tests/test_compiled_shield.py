"""The compiled safety kernel gives the numpy reference's results, bit for bit, on random and real states."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safelane.core.drivers import IDM_PARAMETERS
from safelane.core.errors import ConfigError, NotSupported
from safelane.core.snapshot import RoadSnapshot
from safelane.env.factory import make_env
from safelane.safety.one_decision import compiled
from safelane.safety.one_decision import reference as model
from safelane.safety.one_decision.reference import Dynamics, RoadState, SafetyResult
from safelane.safety.shield import SafetyShield
from test_safety import LINEAR_AND_TURNING_OPTIONS, PROPERTY_SETTINGS, make_state, road

MODES = ("nominal", "robust")

_evaluated: dict[tuple[Dynamics, str], SafetyResult] = {}
_evaluated_state: list[RoadState] = []


def reference(state: RoadState, dyn: Dynamics, mode: str) -> SafetyResult:
    """``model.evaluate`` (the numpy reference), each (dynamics, mode) evaluated once per state: the property
    tests below ask the same question of one drawn state several times (the reference's IDM follower rollout, a
    Python loop over frames, is a large share of this file's time). Only the latest state is kept; results are
    read only."""
    if not _evaluated_state or _evaluated_state[0] is not state:
        _evaluated.clear()
        _evaluated_state[:] = [state]
    key = (dyn, mode)
    if key not in _evaluated:
        _evaluated[key] = model.evaluate(state, dyn, mode)
    return _evaluated[key]


def assert_same(ref: SafetyResult, got: SafetyResult, what: str = "") -> None:
    """Identical masks and flags; ``min_gap`` equal bit for bit (inf == inf, NaN == NaN, signs of zero too)."""
    for name in ("mask", "safe", "available"):
        a, b = getattr(ref, name), getattr(got, name)
        assert a.dtype == b.dtype == bool and np.array_equal(a, b), f"{what} {name}: {a} != {b}"
    assert ref.fallback == got.fallback, f"{what} fallback"
    assert isinstance(got.fallback, bool)
    gap_a, gap_b = ref.min_gap.view(np.int64), got.min_gap.view(np.int64)
    assert np.array_equal(gap_a, gap_b), f"{what} min_gap: {ref.min_gap.tolist()} != {got.min_gap.tolist()}"


def mismatches(state: RoadState, dyn: Dynamics) -> list[str]:
    """The modes in which the compiled kernel differs from the reference on ``state``."""
    bad = []
    for mode in MODES:
        try:
            assert_same(reference(state, dyn, mode), compiled.evaluate_compiled(state, dyn, mode), mode)
        except AssertionError as err:
            bad.append(str(err))
    return bad


def assert_only_stricter(state: RoadState, off: Dynamics, on: Dynamics, unchanged: Callable[[str], bool]) -> None:
    """In both modes, ``on`` makes no action safe that ``off`` does not and grows no worst gap; in the modes
    where ``unchanged(mode)`` it gives the same result to the bit."""
    for mode in MODES:
        a, b = reference(state, off, mode), reference(state, on, mode)
        assert not (b.safe & ~a.safe).any() and not (b.min_gap > a.min_gap).any()
        if unchanged(mode):
            assert_same(a, b)


def assert_nested(state: RoadState, dyn: Dynamics) -> None:
    """robust ⊆ nominal for the final masks, at any heading with shield.turning_in_nominal (without it, only up to
    0.3 rad: turning_leaders brakes a fast turning leader from its speed along its path, which can leave more
    room than nominal's along the road — hypothesis found it at 1 rad, then at 0.25 rad and 34 m/s)."""
    if dyn.rule.turning_in_nominal or (np.abs(state.heading) <= 0.3).all():
        robust, nominal = reference(state, dyn, "robust"), reference(state, dyn, "nominal")
        assert not (robust.safe & ~nominal.safe).any()
        assert not (robust.mask & ~nominal.mask).any()


@PROPERTY_SETTINGS
@given(road())
def test_random_states_bit_identical(case: tuple) -> None:
    state, dyn, _ = case
    assert mismatches(state, dyn) == []


@settings(max_examples=150, deadline=None)
@given(road(extreme=True))
def test_extreme_states_bit_identical(case: tuple) -> None:
    """Overlapping and crashed vehicles, headings up to ±π/2, one lane, a standstill ego."""
    state, dyn, _ = case
    assert mismatches(state, dyn) == []
    # The ego that can never leave its lane (ego_leave_time = inf) and the paper's eq. 12 (delegated).
    slow = dyn.with_options(ego_leave_time=math.inf)
    assert mismatches(state, slow) == []
    paper = compiled.evaluate_compiled(state, dyn, "nominal", "paper")
    assert_same(model.evaluate(state, dyn, "nominal", "paper"), paper)


# --------------------------------------------------------------------------------------------
# Recorded states of real episodes, both simulators.
# --------------------------------------------------------------------------------------------


def recorded(
    preset: str, simulator: str, override: bool, episodes: int, seed: int, max_steps: int = 1000, **sets: Any
) -> Iterator[tuple[SafetyShield, RoadSnapshot]]:
    """Every decision's snapshot of random-policy episodes, under the robust shield (``override``: it
    replaces the unsafe choices, so the episodes last; else the random actions are executed as chosen)."""
    try:
        env = make_env(preset, simulator=simulator, **{"shield.mode": "robust", "shield.override": override, **sets})
    except NotSupported as err:
        pytest.skip(str(err))
    rng = np.random.default_rng(seed)
    assert isinstance(env, SafetyShield)
    steps = 0
    for episode in range(episodes):
        if steps >= max_steps:
            break
        _, info = env.reset(seed=seed * 1000 + episode)
        yield env, info["snapshot"]
        done = False
        while not done and steps < max_steps:
            _, _, terminated, truncated, info = env.step(int(rng.integers(5)))
            steps += 1
            yield env, info["snapshot"]
            done = terminated or truncated
    env.close()


def check_recorded(shield: SafetyShield, snap: RoadSnapshot) -> int:
    """Compare the reference, the compiled kernel and the shield's fast path on one snapshot, both modes."""
    state, dyn = shield.state_and_dynamics(snap)
    mode, engine = shield.mode, shield.engine
    try:
        for m in MODES:
            ref = reference(state, dyn, m)
            assert_same(ref, compiled.evaluate_compiled(state, dyn, m), f"evaluate_compiled {m}")
            shield.mode, shield.engine = m, "compiled"
            assert_same(ref, shield.compute_result(snap), f"shield (snapshot kernel) {m}")
    finally:
        shield.mode, shield.engine = mode, engine
    return len(MODES)


CASES = [
    (preset, simulator, override)
    for preset in ("fast", "paper")
    for simulator in ("highway-env", "fast")
    for override in (False, True)
]


@pytest.mark.parametrize(("preset", "simulator", "override"), CASES)
def test_recorded_states_bit_identical(preset: str, simulator: str, override: bool) -> None:
    """About 20 decisions of each (preset, simulator, policy): ≈ 150 states in all, both modes."""
    n = 0
    for shield, snap in recorded(preset, simulator, override, episodes=4, seed=7, max_steps=15):
        n += check_recorded(shield, snap)
    assert n >= len(MODES) * 15


LONG_DECISIONS = {"fast": 2000, "highway-env": 500}
"""Decisions per case of the long check (10 000 in all): the compiled simulator's decisions are cheap."""


@pytest.mark.slow
@pytest.mark.parametrize(("preset", "simulator", "override"), CASES)
def test_recorded_states_bit_identical_long(preset: str, simulator: str, override: bool) -> None:
    """10 000 decisions over the 8 cases, both modes: not one bit differs (run with ``-m slow``)."""
    n = 0
    steps = LONG_DECISIONS[simulator]
    for shield, snap in recorded(preset, simulator, override, episodes=10_000, seed=11, max_steps=steps):
        n += check_recorded(shield, snap)
    print(f"{preset}/{simulator}/override={override}: {n // len(MODES)} states x {len(MODES)} modes, 0 mismatches")
    assert n >= len(MODES) * steps


# --------------------------------------------------------------------------------------------
# The shield.
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("simulator", ["highway-env", "fast"])
def test_engines_drive_the_same_episode(simulator: str) -> None:
    """engine=numpy and engine=compiled: the same actions executed, the same masks, the same flags."""
    traces = {}
    for engine in ("numpy", "compiled"):
        env = make_env(
            "fast",
            simulator=simulator,
            **{"shield.mode": "robust", "shield.override": True, "shield.engine": engine},
        )
        rng = np.random.default_rng(5)
        trace = []
        for episode in range(2):
            _, info = env.reset(seed=40 + episode)
            trace.append(info["action_mask"].tolist())
            for _ in range(15):
                _, _, terminated, truncated, info = env.step(int(rng.integers(5)))
                trace.append((info["executed_action"], info["action_mask"].tolist(), info["fallback"]))
                if terminated or truncated:
                    break
        env.close()
        traces[engine] = trace
    assert traces["numpy"] == traces["compiled"]


def test_engine_is_configurable() -> None:
    env = make_env("fast", **{"shield.mode": "robust", "shield.engine": "numpy"})
    assert isinstance(env, SafetyShield) and env.engine == "numpy"
    assert make_env("fast", **{"shield.mode": "robust"}).engine == "compiled"
    with pytest.raises(ConfigError, match=r"^shield\.engine: got 'gpu'; .*'compiled' or 'numpy'"):
        make_env("fast", **{"shield.mode": "robust", "shield.engine": "gpu"})
    with pytest.raises(ValueError, match=r"^shield\.engine: got 'gpu'; allowed: 'compiled', 'numpy'"):
        SafetyShield(env.env, engine="gpu")  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------
# The robust options (shield.body_extent, level_cut_ins, level_entering):
# the same in both engines, and only stricter.
# --------------------------------------------------------------------------------------------

OPTION_SETTINGS = settings(PROPERTY_SETTINGS, max_examples=100)
"""The properties below each check one rule option on both engines, several variants per drawn state: 100 fresh
states a run each (150 made this file a fifth of the suite's time on two cores, against its 8-minute budget); the
plain random and extreme states above keep 150."""


ROBUST_OPTIONS = pytest.mark.parametrize("option", ["body_extent", "level_cut_ins", "level_entering"])
"""The options that only add conflicts (linear_mobil removes some: tested on its own below)."""


@ROBUST_OPTIONS
@OPTION_SETTINGS
@given(case=road())
def test_robust_options_bit_identical_and_only_stricter(option: str, case: tuple) -> None:
    state, dyn, _ = case
    dyn = dyn.with_options(**{option: False})
    strict = dyn.with_options(**{option: True})
    assert mismatches(state, dyn) == [] and mismatches(state, strict) == []
    for mode in MODES:
        base, more = reference(state, dyn, mode), reference(state, strict, mode)
        assert not (more.safe & ~base.safe).any()  # more conflicts: never a new safe action
        if mode == "nominal":
            assert_same(base, more)  # the options belong to the robust rule only


@OPTION_SETTINGS
@given(case=road(extreme=True))
def test_reversing_leaders_bit_identical_and_only_stricter(case: tuple) -> None:
    """shield.reversing_leaders (on by default): a leader rolling backwards keeps its reverse speed. Both
    engines agree either way (extreme roads have speeds down to −5 m/s), it never makes an action safe,
    and without a reversing leader it changes nothing, to the bit."""
    state, dyn, _ = case
    without, with_it = (dyn.with_options(reversing_leaders=v) for v in (False, True))
    assert mismatches(state, without) == [] and mismatches(state, with_it) == []
    for mode in MODES:
        before, after = reference(state, without, mode), reference(state, with_it, mode)
        assert not (after.safe & ~before.safe).any()
        if not ((state.vx < 0) & ~state.crashed).any():
            assert_same(before, after)


@OPTION_SETTINGS
@given(case=road())
def test_level_incentive_bit_identical_and_between_the_rules(case: tuple) -> None:
    """shield.level_cut_ins with MOBIL's incentive (the default) only keeps the level cars
    that gain by moving behind the ego: never stricter than any level car turning in (level_incentive
    false), never looser than the rule without level cut-ins; with level_entering (the default) between
    the two as well, and stricter than the filter applied to every lane; the same in both engines."""
    state, dyn, _ = case
    off = dyn.with_options(level_cut_ins=False)
    plain = dyn.with_options(level_cut_ins=True, level_incentive=False)
    incentive = dyn.with_options(level_cut_ins=True, level_incentive=True, level_entering=True)
    own_lanes = incentive.with_options(level_entering=False)  # the filter into entered lanes too
    for d in (plain, incentive, own_lanes):
        assert mismatches(state, d) == []
    for mode in MODES:
        rules = (off, plain, incentive, own_lanes)
        without, anyone, gaining, filtered = (reference(state, d, mode) for d in rules)
        assert not (anyone.safe & ~gaining.safe).any()
        assert not (gaining.safe & ~filtered.safe).any()  # level_entering only adds conflicts
        assert not (filtered.safe & ~without.safe).any()
        # The filter is lifted only for lanes the ego is entering: IDLE, FASTER and SLOWER stay in the
        # lanes it is in, so their gaps do not depend on level_entering.
        keep = [1, 3, 4]
        assert np.array_equal(gaining.min_gap[keep], filtered.min_gap[keep], equal_nan=True)


@OPTION_SETTINGS
@given(case=road(rates=True, follower=True))
def test_forecast_fallback_bit_identical_and_only_the_fallback_choice(case: tuple) -> None:
    """shield.forecast_fallback ranks the least-bad choice by a nominal forecast first (its collisions alike, its
    cars keeping their lanes): the same in both engines
    (one shared kernel); the same safe set, fallback flag and gaps; the same mask whenever some action is safe;
    in a fallback state one available action, robust ⊆ nominal kept (the forecast is the same in both modes)."""
    state, dyn, _ = case
    off = dyn.with_options(forecast_fallback=False)
    for on in (dyn.with_options(forecast_fallback=True),):
        assert mismatches(state, on) == []
        for mode in MODES:
            a, b = reference(state, off, mode), reference(state, on, mode)
            assert a.safe.tolist() == b.safe.tolist() and a.fallback == b.fallback
            assert np.array_equal(a.min_gap, b.min_gap, equal_nan=True)
            assert a.available.tolist() == b.available.tolist()
            if not a.fallback:
                assert a.mask.tolist() == b.mask.tolist()
            elif not (mode == "robust" and dyn.rule.straight_fallback and model.turning_allowance(dyn) > 0.0):
                assert b.mask.sum() == 1 and (b.mask & b.available).any()
        assert_nested(state, on)


@OPTION_SETTINGS
@given(case=road())
def test_linear_incentive_bit_identical_and_only_removes_linear_turn_ins(case: tuple) -> None:
    """shield.linear_incentive: the same in both engines; it only filters Linear-model drivers' turn-ins behind
    the ego, so no conflict is added — every action safe without it stays safe, no worst gap shrinks — nominal
    mode is untouched, and a road without Linear-model drivers gives the same result to the bit.
    shield.linear_incentive_braking (the incentive also at every frame, the driver's leaders braking) lies in
    between: the same in both engines, never a gap above the plain incentive's nor below the unfiltered rule's."""
    state, dyn, _ = case
    off, on = (dyn.with_options(linear_incentive=v, linear_incentive_braking=False) for v in (False, True))
    braking = on.with_options(linear_incentive_braking=True)
    assert mismatches(state, on) == [] and mismatches(state, braking) == []
    assert_same(reference(state, off, "nominal"), reference(state, on, "nominal"))
    assert_same(reference(state, on, "nominal"), reference(state, braking, "nominal"))
    a, b = reference(state, off, "robust"), reference(state, on, "robust")
    mid = reference(state, braking, "robust")
    assert not (a.safe & ~mid.safe).any() and not (mid.safe & ~b.safe).any()
    assert not (b.min_gap < mid.min_gap).any() and not (mid.min_gap < a.min_gap).any()
    if not np.isfinite(state.linear_speed_gain).any():
        assert_same(a, b)
        assert_same(b, mid)


@OPTION_SETTINGS
@given(case=road(rates=True))
def test_full_horizon_bit_identical_at_every_rate_and_unchanged_at_one_per_second(case: tuple) -> None:
    """shield.full_horizon (default): at 1 decision per second the horizon is the one it always was (13 s),
    to the bit; at 2, 3 and 5 per second it spans the same seconds (26, 39, 65 decisions) and both engines
    agree, in both modes."""
    state, dyn, _ = case
    short, full = (dyn.with_options(full_horizon=v) for v in (False, True))
    assert full.horizon_decisions * full.decision_period >= short.horizon_decisions * 1.0 - 1e-9
    assert mismatches(state, full) == [] and mismatches(state, short) == []
    if dyn.decision_period == 1.0:
        assert full.horizon_decisions == short.horizon_decisions
        for mode in MODES:
            assert_same(reference(state, short, mode), reference(state, full, mode))


@OPTION_SETTINGS
@given(case=road(rates=True))
def test_turning_leaders_bit_identical(case: tuple) -> None:
    """shield.turning_leaders (experimental): moving leaders brake from their speed along their path less
    lane_width·tan(π/8); both engines agree either way, at every decision rate; without a moving vehicle
    that is ahead or may change lane nothing changes (a car behind that may change lane can pass the ego and cut
    in ahead of it, a leader from then on: shield.passing_cut_ins)."""
    state, dyn, _ = case
    off, on = (dyn.with_options(turning_leaders=v) for v in (False, True))
    assert mismatches(state, off) == [] and mismatches(state, on) == []
    may_lead = (state.x >= state.ego_x) | state.can_change_lane
    if not (may_lead & (state.vx > 0) & ~state.crashed).any():
        for mode in MODES:
            assert_same(reference(state, off, mode), reference(state, on, mode))


@OPTION_SETTINGS
@given(case=road(rates=True))
def test_straight_fallback_bit_identical_and_only_the_fallback_mask(case: tuple) -> None:
    """shield.straight_fallback (with turning_leaders): the same in both engines at every rate; the safe set,
    gaps and fallback flag are turning_leaders' own; only a state it leaves without a safe action changes, and
    there the mask is exactly what the rule without turning_leaders allows; off turning_leaders, no effect."""
    state, dyn, _ = case
    turning = dyn.with_options(turning_leaders=True)
    on = turning.with_options(straight_fallback=True)
    assert mismatches(state, on) == []
    assert_same(reference(state, on, "nominal"), reference(state, turning, "nominal"))
    for plain in (dyn.with_options(turning_leaders=False),):  # without turning_leaders no effect, in both modes
        for mode in MODES:
            assert_same(reference(state, plain, mode),
                        reference(state, plain.with_options(straight_fallback=True), mode))  # fmt: skip
    for in_nominal in (False, True):
        a = reference(state, turning.with_options(turning_in_nominal=in_nominal), "robust")
        b = reference(state, on.with_options(turning_in_nominal=in_nominal), "robust")
        assert a.safe.tolist() == b.safe.tolist() and a.fallback == b.fallback
        assert np.array_equal(a.min_gap, b.min_gap, equal_nan=True)
        if not b.fallback:
            assert a.mask.tolist() == b.mask.tolist()
        elif not in_nominal:  # the rule without turning_leaders
            straight = dyn.with_options(turning_leaders=False, turning_in_nominal=False)
            assert b.mask.tolist() == reference(state, straight, "robust").mask.tolist()
        else:  # the rule with nominal's leader bound (turning_in_nominal)
            nominal_leaders = model._evaluate(state, on, "robust", "kinematic", nominal_leaders=True)
            assert b.mask.tolist() == nominal_leaders.mask.tolist()


@OPTION_SETTINGS
@given(case=road(rates=True))
def test_turning_in_nominal_bit_identical_and_only_looser_nominal(case: tuple) -> None:
    """shield.turning_in_nominal (on by default): the same in both engines at every
    rate; robust's safe set and gaps are unchanged to the bit (only a fallback mask, chosen among nominal's
    bounds, can change); nominal only gets looser, and only with a moving leader; robust ⊆ nominal at any
    heading; without turning_leaders it changes nothing."""
    state, dyn, _ = case
    off, on = (dyn.with_options(turning_in_nominal=v) for v in (False, True))
    assert mismatches(state, on) == [] and mismatches(state, off) == []
    a, b = reference(state, off, "robust"), reference(state, on, "robust")
    assert a.safe.tolist() == b.safe.tolist() and np.array_equal(a.min_gap, b.min_gap, equal_nan=True)
    n_off, n_on = reference(state, off, "nominal"), reference(state, on, "nominal")
    assert not (n_off.safe & ~n_on.safe).any() and not (n_on.min_gap < n_off.min_gap).any()
    if not ((state.x >= state.ego_x) & (state.vx > 0) & ~state.crashed).any():
        assert_same(n_off, n_on, "nominal")
    assert_nested(state, on)
    plain_off, plain_on = (d.with_options(turning_leaders=False) for d in (off, on))
    for mode in MODES:
        assert_same(reference(state, plain_off, mode), reference(state, plain_on, mode), mode)


@OPTION_SETTINGS
@given(case=road())
def test_linear_mobil_bit_identical_and_only_looser(case: tuple) -> None:
    """shield.linear_mobil judges Linear-model cut-ins by their criterion: the same in both engines either
    way, and it only removes conflicts (never makes an action unsafe); nominal ignores it."""
    state, dyn, _ = case
    without, with_it = (dyn.with_options(linear_mobil=v) for v in (False, True))
    assert mismatches(state, without) == [] and mismatches(state, with_it) == []
    for mode in MODES:
        before, after = reference(state, without, mode), reference(state, with_it, mode)
        assert not (before.safe & ~after.safe).any()
        if mode == "nominal":
            assert_same(before, after)


@ROBUST_OPTIONS
def test_robust_options_on_recorded_states(option: str) -> None:
    n = 0
    for shield, snap in recorded("fast", "fast", True, episodes=4, seed=5, max_steps=40):
        assert shield.dynamics is not None
        for value in (False, True):
            shield.dynamics = shield.dynamics.with_options(**{option: value})
            n += check_recorded(shield, snap)
    assert n >= 160


def test_ego_speed_magnitude_on_recorded_states() -> None:
    """shield.ego_speed_magnitude (default): the ego's speed in the rule is its controller's; false, its
    component along the road. Both ways the reference, the compiled kernel and the shield's fast path (which
    builds the state in the kernel) agree, on random-policy episodes full of lane changes; the two speeds
    differ exactly when the ego's heading does not follow the road."""
    n = turning = 0
    for shield, snap in recorded("fast", "fast", True, episodes=4, seed=5, max_steps=60):
        assert shield.dynamics is not None
        speeds = []
        for value in (False, True):
            shield.dynamics = shield.dynamics.with_options(ego_speed_magnitude=value)
            n += check_recorded(shield, snap)
            speeds.append(shield.state_and_dynamics(snap)[0].ego_speed)
        e = snap.ego
        assert speeds[1] == float(snap.speed[e])
        assert (speeds[0] != speeds[1]) == (math.cos(float(snap.heading[e])) != 1.0)
        turning += speeds[0] != speeds[1]
    assert n >= 240 and turning >= 5


@pytest.mark.parametrize("simulator", ["fast", "highway-env"])
def test_linear_drivers_mobil_on_recorded_states(simulator: str) -> None:
    """Linear-model drivers (their MOBIL criterion judges the ego with the linear formula and their own
    randomised gains): reference, compiled kernel and the shield's fast path agree on dense roads."""
    n = 0
    linear = {"env.other_vehicles_type": "highway_env.vehicle.behavior.LinearVehicle", "env.vehicles_density": 2}
    steps = 25 if simulator == "highway-env" else 60
    for shield, snap in recorded("fast", simulator, True, episodes=3, seed=9, max_steps=steps, **linear):
        assert np.isfinite(snap.linear_speed_gain[1:]).all() and np.isnan(snap.linear_speed_gain[0])
        n += check_recorded(shield, snap)
    assert n >= 2 * steps


@OPTION_SETTINGS
@given(case=road(extreme=True, rates=True))
def test_reversing_cut_ins_bit_identical_and_only_stricter(case: tuple) -> None:
    """shield.reversing_cut_ins: the same in both engines at every rate; it only adds conflicts (a car moving
    backwards may change into the ego's lane whatever MOBIL says), so no action safe with it is unsafe
    without it and no worst gap grows; a road without a car moving backwards is unchanged to the bit."""
    state, dyn, _ = case
    off, on = (dyn.with_options(reversing_cut_ins=v) for v in (False, True))
    assert mismatches(state, on) == []
    assert_only_stricter(state, off, on, lambda mode: not (state.vx < 0).any())


@OPTION_SETTINGS
@given(case=road(extreme=True, rates=True, chained=True))
def test_crossed_lanes_bit_identical_and_only_stricter(case: tuple) -> None:
    """shield.crossed_lanes: the same in both engines at every rate, with the ego's target up to two lanes away;
    it only adds the lanes the ego crosses (or keeps one it crosses for longer), so no action safe with it is
    unsafe without it and no worst gap grows; an ego keeping its lane crosses nothing and is unchanged to the
    bit. Both modes take the same lanes, so robust ⊆ nominal still holds for the final masks."""
    state, dyn, _ = case
    off, on = (dyn.with_options(crossed_lanes=v) for v in (False, True))
    assert mismatches(state, on) == [] and mismatches(state, off) == []
    assert_only_stricter(state, off, on, lambda mode: state.ego_target_lane == state.ego_lane)
    assert_nested(state, on)


@OPTION_SETTINGS
@given(case=road(extreme=True, rates=True))
def test_reversing_noses_bit_identical_and_only_stricter(case: tuple) -> None:
    """shield.reversing_noses: the same in both engines at every rate; it only adds a lane to a car
    rolling backwards with its nose turned, so nothing becomes safe and no worst gap grows; a road without such
    a car, and nominal mode, are unchanged to the bit."""
    state, dyn, _ = case
    off, on = (dyn.with_options(reversing_noses=v) for v in (False, True))
    assert mismatches(state, on) == []
    turned_back = ((state.vx < 0) & (np.abs(state.heading) > model.LATERAL_MOTION_THRESHOLD)).any()
    assert_only_stricter(state, off, on, lambda mode: mode == "nominal" or not turned_back)


@OPTION_SETTINGS
@given(case=road(extreme=True, rates=True, chained=True, follower=True))
def test_follower_idm_bit_identical(case: tuple) -> None:
    """shield.follower_idm: the same in both engines at every rate (IDM followers of every kind, crashed cars,
    cars between a follower and the ego); robust ⊆ nominal still holds for the final masks (both modes take the same
    follower bound); a road without an IDM car behind the ego in its lane is unchanged to the bit."""
    state, dyn, _ = case
    off, on = (dyn.with_options(follower_idm=v) for v in (False, True))
    assert mismatches(state, on) == []
    assert_nested(state, on)
    near = np.flatnonzero(np.abs(state.x - state.ego_x) < model.RELEVANCE_RANGE)
    if not model.idm_followers(state, on, near).any():
        for mode in ("nominal", "robust"):
            assert_same(reference(state, off, mode), reference(state, on, mode), mode)


@OPTION_SETTINGS
@given(case=road(extreme=True, rates=True))
def test_linear_and_turning_options_leave_nominal_untouched(case: tuple) -> None:
    """The linear-driver and turning options (linear drivers' MOBIL, turning leaders, the straight fallback,
    reversing cut-ins) are all robust-mode parts: nominal (Q-masking) gives the same result to the bit with or
    without them, in both engines — without shield.turning_in_nominal (with it nominal takes turning_leaders'
    bound where it is the looser: test_turning_in_nominal_bit_identical_and_only_looser_nominal)."""
    state, dyn, _ = case
    dyn = dyn.with_options(turning_in_nominal=False)
    on, off = (dyn.with_options(**dict.fromkeys(LINEAR_AND_TURNING_OPTIONS, v)) for v in (True, False))
    assert_same(reference(state, on, "nominal"), reference(state, off, "nominal"))
    assert_same(compiled.evaluate_compiled(state, on, "nominal"), compiled.evaluate_compiled(state, off, "nominal"))


@OPTION_SETTINGS
@given(case=road(extreme=True, rates=True, follower=True))
def test_finishing_changes_bit_identical(case: tuple) -> None:
    """shield.finishing_changes (experimental): the same in both engines at every rate; robust ⊆ nominal still
    holds for the final masks (it only drops a robust conflict); nominal mode, and a road without a car
    moving forward toward its own lane's centre, are unchanged to the bit."""
    state, dyn, _ = case
    off, on = (dyn.with_options(finishing_changes=v) for v in (False, True))
    assert mismatches(state, on) == []
    assert_nested(state, on)
    assert_same(reference(state, off, "nominal"), reference(state, on, "nominal"), "nominal")
    lanes = state.lane_of(state.y, dyn.lanes_count, dyn.lane_width)
    moving = (np.abs(state.heading) > model.LATERAL_MOTION_THRESHOLD) | (np.abs(state.vy) > 0.3)
    toward = (lanes * dyn.lane_width - state.y) * np.where(state.vy > 0, 1, -1) > 0
    if not (moving & toward & (state.vx >= 0)).any():
        assert_same(reference(state, off, "robust"), reference(state, on, "robust"), "robust")


@OPTION_SETTINGS
@given(case=road(extreme=True, rates=True, follower=True))
def test_cut_in_when_permitted_bit_identical(case: tuple) -> None:
    """shield.cut_in_when_permitted (on by default), with and without
    shield.permit_any_speed: the same in both engines at every rate (IDM and linear-model
    drivers, crashed and reversing cars); robust ⊆ nominal still holds for the final masks (it only changes robust
    cut-ins); nominal mode is unchanged to the bit."""
    state, dyn, _ = case
    off, on = (dyn.with_options(cut_in_when_permitted=v) for v in (False, True))
    assert mismatches(state, on) == []
    assert mismatches(state, on.with_options(linear_mobil=False)) == []
    assert mismatches(state, on.with_options(permit_any_speed=False)) == []
    assert_nested(state, on)
    assert_same(reference(state, off, "nominal"), reference(state, on, "nominal"), "nominal")


@OPTION_SETTINGS
@given(case=road(extreme=True, rates=True, follower=True))
def test_passing_cut_ins_bit_identical(case: tuple) -> None:
    """shield.passing_cut_ins (experimental, with cut_in_when_permitted): the same in both engines at every rate
    (IDM and linear-model drivers, with and without their MOBIL, crashed and reversing cars); robust ⊆ nominal
    still holds; nominal is unchanged to the bit."""
    state, dyn, _ = case
    on = dyn.with_options(cut_in_when_permitted=True, passing_cut_ins=True)
    assert mismatches(state, on) == []
    assert mismatches(state, on.with_options(linear_mobil=False)) == []
    assert_nested(state, on)
    assert_same(reference(state, dyn, "nominal"), reference(state, on, "nominal"), "nominal")


@OPTION_SETTINGS
@given(case=road(extreme=True, rates=True, follower=True))
def test_level_when_incentive_bit_identical(case: tuple) -> None:
    """shield.level_when_incentive: the same in both engines at every rate (IDM and linear-model drivers, with
    and without their incentive and its braking variant; the bound over every speed in reach and the
    constant-speed time it replaced); robust ⊆ nominal still holds; nominal is unchanged to the bit."""
    state, dyn, _ = case
    on = dyn.with_options(level_when_incentive=True)
    assert mismatches(state, on) == []
    assert mismatches(state, on.with_options(incentive_any_speed=False)) == []
    assert mismatches(state, on.with_options(linear_incentive_braking=False)) == []
    assert mismatches(state, on.with_options(linear_incentive=False, passing_cut_ins=True)) == []
    assert_nested(state, on)
    assert_same(reference(state, dyn, "nominal"), reference(state, on, "nominal"), "nominal")


@st.composite
def polite_road(draw: st.DrawFn) -> tuple[RoadState, Dynamics]:
    """A random road (:func:`test_safety.road`, every rate, a follower) with a car level with the ego in a next lane,
    a car behind that one in its lane, and a car ahead of it (some of the three), every IDM driver of a hidden type
    (timid, normal or aggressive: their IDM constants and politeness 1, 0.5 or 0): where MOBIL's politeness term can
    decide a turn-in (a level car a little slower than the ego, its follower a little faster)."""
    state, dyn, cars = draw(road(rates=True, follower=True))
    types = [IDM_PARAMETERS[name] for name in ("timid", "normal", "aggressive")]
    sides = [lane for lane in (state.ego_lane - 1, state.ego_lane + 1) if 0 <= lane < dyn.lanes_count]
    if sides:
        side = draw(st.sampled_from(sides))

        def car(dx: float, speed: float) -> dict[str, Any]:
            return {"x": state.ego_x + dx, "y": side * 4.0 + draw(st.floats(-1.0, 1.0)), "speed": max(speed, 0.0),
                    "heading": 0.0, "crashed": False, "delta": 4.0, "idm": True, "linear": False,
                    "target": draw(st.one_of(st.just(math.nan), st.floats(15.0, 30.0)))}  # fmt: skip

        # Its desired gap behind the ego about its distance behind it (MOBIL's own gain about zero: cells 643, 833),
        # d* = s₀ + vT + v·(v − v_ego)/(2√(ab)) solved for v, else about zero.
        level_type = types[draw(st.integers(0, 2))]
        behind = draw(st.floats(0.0, 8.0))
        wanted = behind * draw(st.floats(0.8, 1.2))
        v_ego = max(state.ego_speed, 1.0)
        c = 2 * math.sqrt(-level_type.comfort_acc_max * level_type.comfort_acc_min)
        b_term = level_type.time_wanted - v_ego / c
        disc = b_term * b_term - 4 * (level_type.distance_wanted - wanted) / c
        if disc >= 0.0:
            level_speed = (-b_term + math.sqrt(disc)) * c / 2
        else:
            level_speed = v_ego - (level_type.distance_wanted + v_ego * level_type.time_wanted) * c / v_ego
        level_speed += draw(st.floats(-0.3, 0.3))
        extra = [
            car(-behind, level_speed),
            car(-draw(st.floats(10.0, 60.0)), level_speed + draw(st.floats(-2.0, 8.0))),
            car(draw(st.floats(5.0, 40.0)), level_speed - draw(st.floats(-2.0, 5.0))),
        ]
        chosen = draw(st.lists(st.sampled_from([0, 1, 2]), min_size=1, max_size=3, unique=True))
        cars = [*cars, *(extra[k] for k in chosen)]
        state = make_state(
            state.ego_x, state.ego_lane, state.ego_target_lane, state.ego_speed, state.ego_speed_index, cars
        )
    kinds = np.array(draw(st.lists(st.integers(0, 2), min_size=state.n, max_size=state.n)), dtype=int).reshape(state.n)
    if sides and 0 in chosen:  # the level car is of the type its speed was drawn for
        kinds[len(cars) - len(chosen)] = types.index(level_type)
    idm = state.can_change_lane & ~np.isfinite(state.linear_speed_gain)

    def of_type(name: str, current: np.ndarray) -> np.ndarray:
        return np.where(idm, np.array([getattr(t, name) for t in types])[kinds], current)

    return dataclasses.replace(
        state,
        accel_max=of_type("comfort_acc_max", state.accel_max),
        idm_comfort_acc=of_type("comfort_acc_max", state.idm_comfort_acc),
        idm_comfort_dec=of_type("comfort_acc_min", state.idm_comfort_dec),
        idm_distance_wanted=of_type("distance_wanted", state.idm_distance_wanted),
        idm_time_wanted=of_type("time_wanted", state.idm_time_wanted),
        max_braking_imposed=of_type("max_braking_imposed", state.max_braking_imposed),
        politeness=of_type("politeness", np.zeros(state.n)),
    ), dyn


@OPTION_SETTINGS
@given(case=polite_road())
def test_incentive_politeness_bit_identical_and_only_stricter(case: tuple) -> None:
    """shield.incentive_politeness (default): the same in both engines at every rate, with and without the option;
    it only adds turn-ins (never a new safe action, never a larger worst gap) and leaves nominal untouched; with every
    driver's politeness 0 it changes nothing, to the bit."""
    state, dyn = case
    off = dyn.with_options(incentive_politeness=False)
    assert mismatches(state, dyn) == [] and mismatches(state, off) == []
    assert_only_stricter(state, off, dyn, lambda mode: mode == "nominal" or not (state.politeness > 0).any())


@OPTION_SETTINGS
@given(case=polite_road())
def test_incentive_accelerations_bit_identical_and_only_stricter(case: tuple) -> None:
    """shield.incentive_accelerations (default): a level car's incentive at every frame also with every car at its
    acceleration now; the same in both engines at every rate (IDM's, the linear model's and unknown laws, hidden
    types' constants), with the bound over every speed and without it; it only adds turn-ins and leaves nominal
    untouched."""
    state, dyn = case
    off = dyn.with_options(incentive_accelerations=False)
    assert mismatches(state, dyn) == [] and mismatches(state, off) == []
    assert mismatches(state, dyn.with_options(incentive_any_speed=False)) == []
    assert_only_stricter(state, off, dyn, lambda mode: mode == "nominal")


@OPTION_SETTINGS
@given(case=polite_road())
def test_incentive_first_is_incentive_times_to_the_bit(case: tuple) -> None:
    """The compiled incentive_first is the reference's incentive_times for every car, on an ego path of a
    P-controller towards a set-point, with incentive_accelerations on and off (the branch decides a car's time
    in a few per cent of these states: the rule's gaps above rarely show it)."""
    from safelane.safety.one_decision import compiled_parts, cut_ins

    state, dyn = case
    frames, dt = dyn.frames_per_decision, dyn.frame_dt
    target = dyn.target_speeds[state.ego_speed_index]
    powers = (1.0 - dyn.ego_kp * dt) ** np.arange(frames + 1)
    ego_vs = (state.ego_speed - target) * powers + target
    ego_xs = state.ego_x + np.concatenate(([0.0], np.cumsum(ego_vs[:-1] * dt)))
    near = np.arange(state.n)
    lanes = state.lane_of(state.y, dyn.lanes_count, dyn.lane_width)
    band = cut_ins.band_lanes(state, dyn, near)
    t = np.arange(frames + 1) * dt
    for on in (True, False):
        d = dyn.with_options(incentive_accelerations=on)
        expected = cut_ins.incentive_times(state, d, near, ego_xs, ego_vs)
        now_acc = cut_ins.current_accelerations_of(state, d) if on else np.zeros(0)
        for j in range(state.n):
            got = compiled_parts.incentive_first(
                j, j, state.n, near, lanes, band, state.x, state.vx, state.crashed, state.brake_max,
                state.linear_speed_gain, state.linear_speed_difference_gain, state.linear_distance_gain,
                state.idm_distance_wanted, state.idm_time_wanted, state.idm_comfort_acc, state.idm_comfort_dec,
                True, True, np.repeat(ego_xs[:, None], 4, axis=1), state.ego_speed, float(ego_vs[frames]), target,
                powers, frames, t, dyn.mobil_min_gain, now_acc, on,
            )  # fmt: skip
            assert got == expected[j] or (np.isinf(got) and np.isinf(expected[j])), (on, j)
