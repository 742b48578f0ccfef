"""Diagnostics of counterexample files: what an invariant break's model missed, and who a crash involved.

Research tools on top of :mod:`safelane.running.counterexamples` (the file format and its replay): a break
judged with some of the rule's options changed (:func:`break_under_options`) or with the follower bounds of
the decision before it carried over (:func:`break_with_carried_followers`); a break explained by leave-one-out
(:func:`break_culprits`) or repaired by putting vehicles that rolled back inside the model
(:func:`repair_break`); a crash's partner (:func:`crash_partner`). Each uses the numpy reference model on the
shield's own inputs.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from safelane.config import ConfigError
from safelane.running.counterexamples import NEAR, Counterexample

if TYPE_CHECKING:
    from safelane.safety.one_decision.reference import CarriedFollowers


def _snapshots_around_event(env: Any, cx: Counterexample) -> tuple[Any, Any]:
    """Play ``cx`` on the open ``env`` up to its event: the road snapshots of the state its last decision
    was taken in and of the event's state."""
    _, info = env.reset(seed=cx.seed)
    before = info["snapshot"]
    for action in cx.actions[: cx.step]:
        before = info["snapshot"]
        _, _, _, _, info = env.step(int(action))
    return before, info["snapshot"]


def _break_states(cx: Counterexample, simulator: str | None, what: str) -> tuple[Any, Any, Callable[..., Any], Any]:
    """Replay the invariant break ``cx``: the road snapshots of the state before its event and of the
    event's state; ``judge(snapshot, options=None, carried=None)``, the numpy reference model on the shield's own
    inputs for a (possibly edited) snapshot of that episode, its Dynamics fields ``options`` replaced (and
    :class:`~safelane.safety.one_decision.reference.CarriedFollowers` passed on); and the shield. ``what`` names
    the caller's product in the one-line error for a file that is not a break."""

    from safelane.env.factory import make_env
    from safelane.safety.one_decision.reference import evaluate

    if cx.kind != "invariant_break":
        raise ConfigError(f"{cx.kind}: {what} defined for invariant breaks only")
    env = make_env(cx.env_config(simulator))
    try:
        before, after = _snapshots_around_event(env, cx)
        shield = env
        while not hasattr(shield, "state_and_dynamics"):
            shield = shield.env
    finally:
        env.close()

    def judge(snap: Any, options: dict[str, Any] | None = None, carried: Any = None) -> Any:
        state, dyn = shield.state_and_dynamics(snap)
        if options:
            dyn = dyn.with_options(**options)
        return evaluate(state, dyn, shield.mode, carried=carried)

    return before, after, judge, shield


def carried_followers(before: Any, after: Any, reaction: float, reacting_only: bool = True) -> CarriedFollowers:
    """The follower bounds of the decision ``before`` (a road snapshot) carried to the state ``after``
    (:class:`~safelane.safety.one_decision.reference.CarriedFollowers`): every body of ``after``'s road state that was
    behind the ego in ``before``, except one already beyond that bound (outside the model as ``before`` drew it). Bodies
    are matched by their snapshot index (the fast simulator's rows, stable through an episode).

    ``reacting_only``: only the cars whose reaction had begun by ``before``, by the model's own reading of the
    reaction time (docs/safety.md §3: IDM reacts once the ego is in its lane): the ego was then on the car's lane
    or its target lane, as highway-env's ``Road.neighbour_vehicles`` sees it (within half a lane width + 1 m of
    the lane's centre). False: every car behind (docs/research/nested-follower-bound.md's first probe; a car in the
    next lane had no reason to
    react, so its carried bound is not the model's)."""
    from safelane.safety.one_decision.reference import IDM_LANE_MARGIN, CarriedFollowers, follower_positions
    from safelane.safety.shield import road_state_bodies

    bodies = road_state_bodies(after)
    x_before, x_after = before.longitudinal(), after.longitudinal()
    heading = math.atan2(before.lane_direction[1], before.lane_direction[0])
    vx_before = before.speed * np.cos(before.heading - heading)
    age = float(after.time - before.time)
    behind = x_before[bodies] < x_before[before.ego]
    if reacting_only:
        ego_y = float((before.position[before.ego] - before.lane_origin) @ before.lane_lateral)
        reach = 0.5 * before.lane_width + IDM_LANE_MARGIN  # highway-env's on_lane(..., margin=1)

        def ego_on(lanes: np.ndarray) -> np.ndarray:
            return np.abs(ego_y - lanes * before.lane_width) <= reach

        behind &= ego_on(before.lane[bodies]) | ego_on(before.target_lane[bodies])
    bound_now = follower_positions(
        x_before[bodies], vx_before[bodies], after.accel_max[bodies], after.brake_max[bodies], reaction,
        np.array([age]),
    )[:, 0]  # fmt: skip
    keep = behind & (x_after[bodies] <= bound_now)
    return CarriedFollowers(np.where(keep, x_before[bodies], np.nan), np.where(keep, vx_before[bodies], np.nan), age)


def break_with_carried_followers(
    cx: Counterexample, simulator: str | None = None, reacting_only: bool = True
) -> dict[str, Any]:  # fmt: skip
    """An invariant break judged with the follower bounds of the decision before it carried over
    (:func:`carried_followers`; docs/research/nested-follower-bound.md): whether the rule's follower bound, nested in
    time instead of
    started again at every decision, would leave the break state a safe action. ``carried``: how many cars
    behind had a bound carried; ``best_gap`` / ``best_gap_carried`` [m]; ``safe_carried`` and ``unlocks`` as in
    :func:`break_under_options`. A diagnostic: the numpy reference model, the follower bound only (the
    IDM-response bound of ``follower_idm`` depends on the ego's path and is not carried). ``reacting_only`` as in
    :func:`carried_followers`."""
    before, after, judge, shield = _break_states(cx, simulator, "carried followers are")
    carried = carried_followers(before, after, shield.dynamics.follower_reaction, reacting_only)
    plain, nested = judge(after), judge(after, carried=carried)
    return {
        "carried": int(np.isfinite(carried.x).sum()),
        "best_gap": round(float(np.max(np.where(plain.available, plain.min_gap, -np.inf))), 3),
        "best_gap_carried": round(float(np.max(np.where(nested.available, nested.min_gap, -np.inf))), 3),
        "safe_carried": not nested.fallback,
        "unlocks": [int(a) for a in np.flatnonzero(nested.safe)],
    }


def check_rule_options(options: dict[str, Any]) -> None:
    """Raise a one-line :class:`ConfigError` naming the first key of ``options`` that is not a field of the
    rule's :class:`~safelane.safety.one_decision.reference.Dynamics`, with the allowed names."""
    import dataclasses

    from safelane.safety.one_decision.reference import Dynamics
    from safelane.safety.rule import OPTION_NAMES

    fields = {f.name for f in dataclasses.fields(Dynamics)} | set(OPTION_NAMES)
    unknown = sorted(set(options) - fields)
    if unknown:
        raise ConfigError(f"{unknown[0]}: not a rule option; allowed: {', '.join(sorted(fields))}")


def break_under_options(
    cx: Counterexample, options: dict[str, Any], simulator: str | None = None
) -> dict[str, Any]:  # fmt: skip
    """What a change of the rule does to an invariant break: replay ``cx`` to its event's state (no safe action
    under the rule it ran with) and judge that state with the rule's
    :class:`~safelane.safety.one_decision.reference.Dynamics` fields ``options`` replaced (e.g. ``{"follower_reaction":
    0.0}``, ``{"level_when_incentive": False}``). ``safe_with_options``: it then has a safe action (the change reaches
    what broke it — a diagnostic, not a proof that the change is sound); ``unlocks``: those actions; ``best_gap`` /
    ``best_gap_with_options`` [m]: the largest worst-case gap over the available actions, as it ran and with the
    options. Uses the numpy reference model on the shield's inputs; an unknown field is a one-line
    :class:`ConfigError`."""
    check_rule_options(options)
    _, after, judge, _ = _break_states(cx, simulator, "options are")
    plain, changed = judge(after), judge(after, options)
    return {
        "best_gap": round(float(np.max(np.where(plain.available, plain.min_gap, -np.inf))), 3),
        "best_gap_with_options": round(float(np.max(np.where(changed.available, changed.min_gap, -np.inf))), 3),
        "safe_with_options": not changed.fallback,
        "unlocks": [int(a) for a in np.flatnonzero(changed.safe)],
    }


def crash_partner(cx: Counterexample, simulator: str | None = None) -> dict[str, Any]:
    """Who the ego crashed into, and whether that vehicle stayed inside the rule's model: replay the crash
    ``cx`` and return the partner's index, its lane relative to the ego's, its offset along the road [m] and
    its speed [m/s] at the last decision before the crash and at the crash, with ``reversing`` set when it
    moved backwards at either. The rule's leader bound lets a braking car stop, not roll back: a car
    *starting* to reverse (highway-env lets IDM's speed go below zero in a jam) breaks its own driver
    model (docs/research/horizon-and-ego-speed.md); one already reversing keeps its speed under
    ``shield.reversing_leaders``."""
    from safelane.env.factory import make_env
    from safelane.running.collisions import collision_partner

    if cx.kind != "collision":
        raise ConfigError(f"{cx.kind}: a crash partner is defined for collisions only")
    env = make_env(cx.env_config(simulator))
    try:
        before, crash = _snapshots_around_event(env, cx)
    finally:
        env.close()
    j = collision_partner(crash)
    if j is None:
        return {"vehicle": None, "reversing": False}
    e = crash.ego
    speeds = [round(float(before.speed[j]), 2), round(float(crash.speed[j]), 2)]
    return {
        "vehicle": j,
        "lane_vs_ego": [int(before.lane[j]) - int(before.lane[before.ego]), int(crash.lane[j]) - int(crash.lane[e])],
        "dx": [
            round(float(before.position[j, 0] - before.position[before.ego, 0]), 2),
            round(float(crash.position[j, 0] - crash.position[e, 0]), 2),
        ],
        "speed": speeds,
        "reversing": min(speeds) < 0.0,
    }


CULPRIT_ROLES: tuple[str, ...] = (
    "came_from_two_lanes",
    "adjacent_ahead",
    "adjacent_behind",
    "leader",
    "follower",
    "two_lanes_away",
    "moved_away",
    "overtook",
    "ego_changed_lane",
    "joint",
)
"""What the vehicle whose removal alone gives the break state a safe action was, before and after the
decision (lanes relative to the ego's; ahead / behind along the road): ``came_from_two_lanes`` — two
or more lanes away before, next to or in the ego's lane after; ``adjacent_ahead`` / ``adjacent_behind``
— in a lane next to the ego's both times; ``leader`` / ``follower`` — in the ego's lane both times;
``two_lanes_away`` — two or more lanes away both times; ``moved_away`` — farther in lanes after than
before; ``overtook`` — it changed from behind to ahead of the ego or back; ``ego_changed_lane`` — the
ego's lane changed; ``joint`` — no single vehicle: only removing several helps (the robust rule's one
fallback for all conflicts)."""


def culprit_role(dx: tuple[float, float], lanes: tuple[int, int], ego_changed_lane: bool) -> str:
    """The :data:`CULPRIT_ROLES` entry of a culprit from its offset along the road [m] and its lane
    relative to the ego's, before and after the decision."""
    (dx_before, dx_after), (lane_before, lane_after) = dx, lanes
    if (dx_before >= 0) != (dx_after >= 0):
        return "overtook"
    if ego_changed_lane:
        return "ego_changed_lane"
    if abs(lane_before) >= 2 and abs(lane_after) <= 1:
        return "came_from_two_lanes"
    if lane_after == 0 and lane_before == 0:
        return "leader" if dx_after >= 0 else "follower"
    if abs(lane_after) == 1 and abs(lane_before) == 1:
        return "adjacent_ahead" if dx_after >= 0 else "adjacent_behind"
    if abs(lane_before) >= 2 and abs(lane_after) >= 2:
        return "two_lanes_away"
    return "moved_away"


def break_culprits(cx: Counterexample, simulator: str | None = None) -> dict[str, Any]:
    """Explain an invariant break by leave-one-out: replay ``cx`` to the state before its event and the
    event's state (which has no safe action), remove each other vehicle in turn from the latter, and
    keep those whose removal alone makes an action safe. Each culprit comes with its role
    (:data:`CULPRIT_ROLES`) and its state at both decisions; ``role`` is the first culprit's (nearest
    first), ``joint`` if there is none. Uses the numpy reference model on the shield's own inputs."""
    import dataclasses

    before, after, judge, _ = _break_states(cx, simulator, "culprits are")
    base = judge(after)
    e = after.ego
    ego_lane_before, ego_lane_after = int(before.lane[before.ego]), int(after.lane[e])
    order = sorted(
        (j for j in range(after.n) if j != e), key=lambda j: abs(float(after.position[j, 0] - after.position[e, 0]))
    )
    culprits = []
    for j in order:
        dx_after = float(after.position[j, 0] - after.position[e, 0])
        if abs(dx_after) > NEAR:
            continue
        position = after.position.copy()
        position[j, 0] += 1e6  # far beyond the model's range (250 m): as if the vehicle were not there
        result = judge(dataclasses.replace(after, position=position))
        if result.fallback:
            continue
        dx_before = float(before.position[j, 0] - before.position[before.ego, 0])
        lane_before, lane_after = int(before.lane[j]) - ego_lane_before, int(after.lane[j]) - ego_lane_after
        role = culprit_role((dx_before, dx_after), (lane_before, lane_after), ego_lane_before != ego_lane_after)
        culprits.append(
            {
                "vehicle": j,
                "role": role,
                "dx": [round(dx_before, 2), round(dx_after, 2)],
                "lane_vs_ego": [lane_before, lane_after],
                "speed": [round(float(before.speed[j]), 2), round(float(after.speed[j]), 2)],
                "heading": [round(float(before.heading[j]), 4), round(float(after.heading[j]), 4)],
                "unlocks": [int(a) for a in np.flatnonzero(result.safe)],
            }
        )
    return {
        "role": culprits[0]["role"] if culprits else "joint",
        "culprits": culprits,
        "ego_speed": [round(float(before.speed[before.ego]), 2), round(float(after.speed[e]), 2)],
        "ego_lane": [ego_lane_before, ego_lane_after],
        "chosen": int(cx.actions[cx.step - 1]),
        "fallback_confirmed": bool(base.fallback),
    }


REVERSING_MARGIN = 0.1
"""[m/s] A vehicle rolled back beyond the rule's model during a decision when its speed after it is this
much below ``min(its speed before, 0)`` (the leader bound lets a car stop, or keep a reverse speed it
already has — ``shield.reversing_leaders`` — but not start or speed up backwards)."""


def repair_break(cx: Counterexample, simulator: str | None = None) -> dict[str, Any]:
    """Whether an invariant break is the model's fault or a vehicle's: replay ``cx`` to the state before its
    event and the event's state (no safe action), put every vehicle that rolled back beyond the model
    during that decision (:data:`REVERSING_MARGIN`) back inside it — at ``max(x, x_before + min(v_before,
    0)·T)`` [m] along the road and ``max(v, min(v_before, 0))`` [m/s], where the rule's bound from the
    state before allowed it to be — and evaluate the repaired state. ``repaired``: those vehicles;
    ``safe_after_repair``: it has a safe action (the break needed the roll-back: outside the model, as the
    invariant promises a safe action only while the others stay inside it); ``unlocks``: the safe actions.
    Unlike leave-one-out (:func:`break_culprits`) it changes only what left the model, so a roll-back
    beside an in-model hole does not excuse it. ``best_gap`` [m]: the break state's largest worst-case gap
    over the available actions, as it is (below the margin, as a break is; ≥ 0: the model still has a
    collision-free fallback, only the margin was eaten). Uses the numpy reference model on the shield's
    inputs."""
    import dataclasses

    before, after, judge, _ = _break_states(cx, simulator, "a repair is")
    period = float(after.time - before.time)
    position, speed = after.position.copy(), after.speed.copy()
    repaired = []
    for j in range(after.n):
        if j == after.ego:
            continue
        v_before = float(before.speed[j])
        floor = min(v_before, 0.0)
        if float(after.speed[j]) < floor - REVERSING_MARGIN:
            repaired.append(j)
            speed[j] = floor
            position[j, 0] = max(float(position[j, 0]), float(before.position[j, 0]) + floor * period)
    result = judge(dataclasses.replace(after, position=position, speed=speed))
    plain = judge(after) if repaired else result
    return {
        "best_gap": round(float(np.max(np.where(plain.available, plain.min_gap, -np.inf))), 3),
        "repaired": repaired,
        "safe_after_repair": bool(repaired) and not result.fallback,
        "unlocks": [int(a) for a in np.flatnonzero(result.safe)] if repaired else [],
    }
