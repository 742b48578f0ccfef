"""Speed of the simulator, of the safety shield and of the paper observation (``safelane bench``).

Raw and shielded episodes are interleaved (in alternating order) with the same seeds and the same
random actions, so both drive identical trajectories and machine noise hits both alike: the
shielded env differs only by the mask computed at every reset and step, and
``shield_overhead_ratio`` (shielded ÷ raw decisions/s, 1.0 = free) isolates its cost. Only
``env.step`` calls are timed (resets are not decisions). On a busy machine the ratio can come out
slightly above 1: that is noise, run more episodes. The agent's cost comes from a short real training
run timed by its own clocks (:func:`measure_training`), so it too is a ratio within one run. With continuous
actions (``actions="continuous"``) the continuous step is timed beside the discrete one on each simulator
(:func:`continuous_step_figures`).
"""

from __future__ import annotations

import platform
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numba
import numpy as np

from safelane.agents.dqn import parse_methods
from safelane.config import ConfigError, load_config
from safelane.env.factory import make_env
from safelane.env.observations import paper_state_compiled as paper_state
from safelane.env.scenarios import find_shield
from safelane.env.vector import make_vector_env
from safelane.reporting.metrics_file import METRICS_FILE, read_metrics
from safelane.running.policies import fixed_policy
from safelane.running.run_directory import make_train_config
from safelane.running.training import train
from safelane.safety.continuous.controls import ControlLimits
from safelane.safety.continuous.family import ControlFamily
from safelane.safety.control_shield import control_dynamics
from safelane.safety.world import OVERRIDE_ORDER, Dynamics

BENCH_PRESET = "fast"
BENCH_SHIELDS = ("nominal", "robust")
BATCH_SIZES = (1, 16, 64, 256)
"""Batch sizes of ``fast_batched_decisions_per_s``."""
BATCH_DECISIONS = 12_000
"""Decisions per sample of ``fast_batched_decisions_per_s`` (about a second of each batch size)."""
SHARE_BATCH = 64
"""The batch size at which ``batched_shield_share`` is measured."""
SHARE_DECISIONS = 20_000
"""Decisions per sample of ``batched_shield_share`` (four samples: shielded, unshielded, twice)."""
FAST_REPEATS = 5
"""The fast simulator plays each benchmark episode this many times (it takes milliseconds)."""
COMMITTED_EPISODES = 2
"""Episodes (of the bench's first seeds) on which the committed mask is timed beside the robust one: the committed
mode's numpy reference costs milliseconds per decision, so a few dozen decisions keep bench's runtime."""
HIGHER_IS_BETTER = (
    "fast_decisions_per_s",
    "fast_shielded_decisions_per_s",
    "fast_batched_decisions_per_s.64",
    "train_steps_per_s_fast",
    "train_batched_steps_per_s.40",
)
"""The figures :func:`regressions` compares with the baseline (dotted: a key inside a dict), rates [1/s]…"""
LOWER_IS_BETTER = ("shield_mask_us_mean_fast", "committed_mask_us_mean_fast")
"""… and costs [µs]. Ratios to stock highway-env are left out: they move with highway-env's own speed."""


def _play(
    env: Any, seed: int, on_decision: Callable[[], None] | None = None, policy_name: str = "random",
    actions: str = "discrete",
) -> tuple[int, float]:  # fmt: skip
    """One episode with the fixed policy ``policy_name`` (of ``actions``, seeded with ``seed``): (decisions, seconds
    spent in ``env.step``).

    ``on_decision`` runs before every decision, outside the timed ``env.step``."""
    action_config = env.unwrapped.config["action"] if actions == "continuous" else None
    policy = fixed_policy(policy_name, seed, actions, action_config)
    obs, info = env.reset(seed=seed)
    decisions, stepping = 0, 0.0
    done = False
    while not done:
        if on_decision is not None:
            on_decision()
        action = policy(obs, info)
        t0 = time.perf_counter()
        obs, _, terminated, truncated, info = env.step(action)
        stepping += time.perf_counter() - t0
        decisions += 1
        done = terminated or truncated
    return decisions, stepping


def mask_cost_figures(mask_us: Sequence[float], suffix: str = "", prefix: str = "shield") -> dict[str, float]:
    """The mask's cost per decision [µs] from its timings ``mask_us`` [µs]: ``shield_mask_us_median``,
    ``shield_mask_us_mean`` and ``shield_mask_us_p99`` (99th percentile), each name ending in ``suffix`` and
    starting with ``prefix`` instead of ``shield``."""
    if len(mask_us) == 0:
        raise ValueError("mask_us: no mask timings (play at least one decision)")
    samples = np.asarray(mask_us, dtype=float)
    return {
        f"{prefix}_mask_us_median{suffix}": float(np.median(samples)),
        f"{prefix}_mask_us_mean{suffix}": float(np.mean(samples)),
        f"{prefix}_mask_us_p99{suffix}": float(np.percentile(samples, 99)),
    }


def committed_mask_figures(episodes: int = COMMITTED_EPISODES, seed: int = 0) -> dict[str, Any]:
    """The committed shield mode's cost per decision beside the robust mode's, on the same states: ``episodes``
    episodes of the ``fast`` preset on the fast simulator (seeds ``seed``, ``seed + 1``, …) with the random policy,
    its action replaced by the closest one the committed mask allows (as ``shield.override`` does, so the kept plan
    drives as it would). At every decision, untimed between the two: the robust shield's ``compute_result`` and the
    committed shield's (``shield.engine`` as the preset says), plus its
    ``commit`` of the executed action (its memory: the plan kept for the next decision). Both shields are those
    :func:`~safelane.env.factory.make_env` builds from the preset. Figures [µs]: ``committed_mask_us_median_fast``,
    ``…_mean_fast``, ``…_p99_fast`` and the robust mask's on the same states, ``committed_robust_mask_us_…_fast``;
    ``committed_mask_ratio_fast``: the committed mean ÷ the robust mean (the target: ≤ 3);
    ``committed_mask_decisions``: the decisions timed; ``committed_engine``.

    On the same states, the shield for continuous actions judging a uniform random action
    (:class:`~safelane.safety.continuous.family.ControlFamily`, compiled, its memory reset: the ego moved by
    meta-actions, not by its plans): ``projection_mask_us_…_fast`` [µs], ``projection_ratio_fast`` (its mean ÷ the
    committed decision's mean: the target ≤ 3) and ``projection_evaluated_mean`` (actions verified per
    decision)."""
    if episodes < 1:
        raise ValueError(f"episodes: must be >= 1 (got {episodes})")
    env = make_env(BENCH_PRESET, simulator="fast")  # no shield of its own: the two below judge its states
    committed = find_shield(make_env(BENCH_PRESET, simulator="fast", **{"shield.mode": "committed"}))
    robust = find_shield(make_env(BENCH_PRESET, simulator="fast", **{"shield.mode": "robust"}))
    family = committed.family
    committed_us: list[float] = []
    robust_us: list[float] = []
    control, limits, wanted_rng = ControlFamily(), ControlLimits(), np.random.default_rng(seed)
    projection_us: list[float] = []
    evaluated: list[int] = []
    control_dyn: Dynamics | None = None
    try:
        for i in range(-1, episodes):  # episode -1: its first decisions compile (or load) the kernels, untimed
            policy = fixed_policy("random", seed + max(i, 0))
            obs, info = env.reset(seed=seed + max(i, 0))
            family.reset()
            done, decisions = False, 0
            while not done and (i >= 0 or decisions < 3):
                action = int(policy(obs, info))
                t0 = time.perf_counter()
                robust.compute_result(info["snapshot"])
                t1 = time.perf_counter()
                mask = committed.compute_result(info["snapshot"]).mask
                t2 = time.perf_counter()
                executed = action if mask[action] else next(a for a in OVERRIDE_ORDER[action] if mask[a])
                t3 = time.perf_counter()
                family.commit(executed)
                t4 = time.perf_counter()
                control_dyn = control_dyn or control_dynamics(info["snapshot"], limits)
                wanted = wanted_rng.uniform(-1.0, 1.0, size=2).astype(np.float32)
                control.reset()
                t5 = time.perf_counter()
                judged = control.judge(info["snapshot"], control_dyn, wanted)
                t6 = time.perf_counter()
                if i >= 0:
                    robust_us.append((t1 - t0) * 1e6)
                    committed_us.append((t2 - t1 + t4 - t3) * 1e6)
                    projection_us.append((t6 - t5) * 1e6)
                    evaluated.append(judged.evaluated)
                obs, _, terminated, truncated, info = env.step(executed)
                done, decisions = terminated or truncated, decisions + 1
    finally:
        env.close()
        committed.close()
        robust.close()
    figures: dict[str, Any] = {
        **mask_cost_figures(committed_us, "_fast", prefix="committed"),
        **mask_cost_figures(robust_us, "_fast", prefix="committed_robust"),
    }
    figures["committed_mask_ratio_fast"] = (
        figures["committed_mask_us_mean_fast"] / figures["committed_robust_mask_us_mean_fast"]
    )
    figures.update(committed_mask_decisions=len(committed_us), committed_engine=committed.engine)
    figures.update(mask_cost_figures(projection_us, "_fast", prefix="projection"))
    figures["projection_ratio_fast"] = figures["projection_mask_us_mean_fast"] / figures["committed_mask_us_mean_fast"]
    figures["projection_evaluated_mean"] = float(np.mean(evaluated))
    return figures


CONTINUOUS_BENCH_POLICY = "weave"
"""The continuous policy of :func:`continuous_step_figures`: it changes lanes and keeps its speed (the random one
leaves the road within a decision or two, ending its episodes)."""
SIMULATORS = ("highway-env", "fast")


def continuous_step_figures(episodes: int, seed: int = 0) -> dict[str, Any]:
    """The continuous step beside the discrete one, on each simulator: ``episodes`` episodes of the ``fast`` preset
    (seeds ``seed``, ``seed + 1``, …) through safelane's gymnasium stack (paper observation and reward, no shield),
    a continuous one (:data:`CONTINUOUS_BENCH_POLICY`) and a discrete one (the random policy) interleaved, once each
    on highway-env and :data:`FAST_REPEATS` times each on the fast simulator; only ``env.step`` is timed. Figures,
    each ``{"highway-env": …, "fast": …}``: ``continuous_decisions_per_s`` and ``discrete_decisions_per_s``
    [decisions/s], ``continuous_step_ratio`` (continuous ÷ discrete decisions/s: below 1, the continuous step costs
    more).

    The shield for continuous actions is timed on the committed decision's states (:func:`committed_mask_figures`:
    ``projection_…``)."""
    if episodes < 1:
        raise ValueError(f"episodes: must be >= 1 (got {episodes})")
    policies = {"discrete": "random", "continuous": CONTINUOUS_BENCH_POLICY}
    envs = {
        (simulator, actions): make_env(BENCH_PRESET, simulator=simulator, actions=actions)
        for simulator in SIMULATORS
        for actions in policies
    }
    played = dict.fromkeys(envs, 0)
    seconds = dict.fromkeys(envs, 0.0)
    try:
        for actions, name in policies.items():  # compiles (or loads) the fast kernels outside the timed episodes
            _play(envs["fast", actions], seed, policy_name=name, actions=actions)
        for i in range(episodes):
            order = list(policies) if i % 2 == 0 else list(policies)[::-1]  # alternate: drifts favour neither
            for simulator in SIMULATORS:
                for _ in range(1 if simulator == "highway-env" else FAST_REPEATS):
                    for actions in order:
                        n, s = _play(envs[simulator, actions], seed + i, policy_name=policies[actions], actions=actions)
                        played[simulator, actions] += n
                        seconds[simulator, actions] += s
    finally:
        for env in envs.values():
            env.close()
    rate = {key: played[key] / seconds[key] for key in envs}
    return {
        "continuous_decisions_per_s": {sim: rate[sim, "continuous"] for sim in SIMULATORS},
        "discrete_decisions_per_s": {sim: rate[sim, "discrete"] for sim in SIMULATORS},
        "continuous_step_ratio": {sim: rate[sim, "continuous"] / rate[sim, "discrete"] for sim in SIMULATORS},
    }


def measure_envpool(cfg: dict[str, Any], decisions: int, seed: int) -> float | None:
    """Decisions per second of EnvPool's C++ ``HighwayFast-v0`` (1 env, 1 thread, the same traffic as
    ``cfg``: lanes, vehicles, duration, frequencies, spacing, density; random actions), or None when the
    optional ``envpool`` package is not installed. Its ego keeps EnvPool's fixed target speeds
    [20, 25, 30] m/s: EnvPool cannot be configured otherwise."""
    try:
        import envpool  # type: ignore[import-not-found]
    except ImportError:
        return None
    env = envpool.make(
        "HighwayFast-v0",
        env_type="gymnasium",
        num_envs=1,
        batch_size=1,
        num_threads=1,
        seed=seed,
        lanes_count=int(cfg["lanes_count"]),
        vehicles_count=int(cfg["vehicles_count"]),
        duration=int(cfg["duration"]),
        max_episode_steps=int(cfg["duration"] * cfg["policy_frequency"]),
        simulation_frequency=int(cfg["simulation_frequency"]),
        policy_frequency=int(cfg["policy_frequency"]),
        ego_spacing=float(cfg["ego_spacing"]),
        vehicles_density=float(cfg["vehicles_density"]),
    )
    rng = np.random.default_rng(seed)
    actions = rng.integers(5, size=(decisions, 1))
    env.reset()
    start = time.perf_counter()
    for a in actions:  # EnvPool resets finished episodes by itself
        env.step(a)
    rate = decisions / (time.perf_counter() - start)
    env.close()
    return rate


def measure_batched(num_envs: int, decisions: int, seed: int, shield: str, threads: int = 1) -> float:
    """Summed decisions per second of :func:`safelane.env.vector.make_vector_env` with ``num_envs``
    fast-simulator environments under ``shield`` (``none`` for no shield; random actions, autoresets
    included) on ``threads`` numba threads, over about ``decisions`` decisions after one warm-up step."""
    vector = make_vector_env(BENCH_PRESET, num_envs=num_envs, seed=seed, threads=threads, **{"shield.mode": shield})
    rng = np.random.default_rng(seed)
    steps = max(decisions // num_envs, 4)
    actions = rng.integers(5, size=(steps + 1, num_envs))
    try:
        vector.step(actions[0])
        start = time.perf_counter()
        for a in actions[1:]:
            vector.step(a)
        elapsed = time.perf_counter() - start
    finally:
        vector.close()
    return steps * num_envs / elapsed


def measure_training(
    episodes: int, seed: int, shield: str, method: str = "robust", simulator: str = "highway-env"
) -> dict[str, float]:
    """Train ``method`` (``tuned`` preset, ``fast`` env on ``simulator`` with ``shield``) for ``episodes``
    episodes in a temporary directory with the real loop of :func:`safelane.running.training.train`, and read its
    own clocks: decisions per second of training, and the share of its wall time spent outside the
    environment (acting, storing, gradient steps, bookkeeping, checkpoints)."""
    with tempfile.TemporaryDirectory(prefix="safelane-bench-") as tmp:
        # Learning starts after one batch, so nearly every timed decision carries a gradient step.
        sets = [f"shield.mode={shield}", "agent.learning_starts=64", f"simulator={simulator}"]
        cfg = make_train_config(method=method, episodes=episodes, seed=seed, sets=sets)
        out = train(cfg, Path(tmp) / "run")
        clocks = read_metrics(out / METRICS_FILE, ["wall_time_s", "env_time_s", "env_steps"])
    wall, env_time, steps = (float(clocks[c][-1]) for c in ("wall_time_s", "env_time_s", "env_steps"))
    return {
        "train_steps_per_s": steps / wall,
        "agent_ms_per_decision": 1e3 * (wall - env_time) / steps,
        "agent_overhead_fraction": (wall - env_time) / wall,
    }


def run_bench(
    episodes: int = 10,
    seed: int = 0,
    shield: str = "robust",
    progress: Callable[[int], None] | None = None,
    methods: Sequence[str] = ("robust",),
    actions: str = "discrete",
) -> dict[str, Any]:
    """Measure, on the ``fast`` preset with a random policy, interleaving raw and shielded episodes
    (pair ``i`` uses seed ``seed + i``; ``progress(i)`` is called after each pair):

    * ``env_steps_per_s``: raw decisions per second [1/s];
    * ``shielded_env_steps_per_s``: decisions per second with the ``shield`` (nominal or robust) [1/s];
    * ``shield_overhead_ratio``: shielded ÷ raw (≤ 1; 1 means the shield is free);
    * ``snapshot_us_median``: building one road snapshot from highway-env's objects [µs], median;
    * ``shield_mask_us_median``: one ``SafetyShield.compute_mask()`` on it [µs], median over decisions;
    * ``obs_us_median``: one paper observation (eq. 3, the compiled form the environment uses) [µs], median;
    * ``highway_env_steps_per_s``: raw decisions per second with highway-env's own neighbour search
      (``neighbour_search=highway-env``; identical episodes) and ``neighbour_search_speedup`` = raw ÷ that;
    * ``highway_env_decisions_per_s``: stock highway-env (``gym.make`` with the preset's config: its own
      neighbour search and observation, no safelane layer), same seeds and actions;
    * ``fast_decisions_per_s``: the fast simulator through safelane's gymnasium stack (paper observation
      and reward, no shield), same seeds and actions, each episode played :data:`FAST_REPEATS` times;
      ``fast_raw_speedup`` = that ÷ stock highway-env;
    * ``fast_shielded_decisions_per_s``: the same with the ``shield`` on (1 env) and ``fast_speedup`` =
      that ÷ stock highway-env (unshielded); ``shield_mask_us_median_fast``: the mask's median cost [µs]
      on the fast simulator's states (``shield_mask_us_median``: on highway-env's), and beside it its mean
      and 99th percentile (``shield_mask_us_mean_fast``, ``shield_mask_us_p99_fast`` [µs],
      :func:`mask_cost_figures`): the mean is what a decision pays on average, and the fallback states'
      second pass and forecast sit in the tail the median hides;
    * ``shield_mask_share_fast``: that median mask cost as a share of a shielded fast decision
      (median µs × ``fast_shielded_decisions_per_s``);
    * ``committed_mask_us_median_fast`` / ``_mean_fast`` / ``_p99_fast`` [µs]: the committed mode's decision
      (evaluate and commit) and ``committed_robust_mask_us_…_fast`` the robust
      mask's on the same states, ``committed_mask_ratio_fast`` committed ÷ robust (means), on the first
      ``min(episodes, COMMITTED_EPISODES)`` seeds (:func:`committed_mask_figures`), and on the same states the
      shield for continuous actions, ``projection_mask_us_…_fast``, ``projection_ratio_fast`` (its mean ÷ the
      committed decision's) and ``projection_evaluated_mean``;
    * ``fast_batched_decisions_per_s``: ``{N: summed decisions/s}`` of ``make_vector_env`` with N
      shielded fast-simulator environments on one thread, N in :data:`BATCH_SIZES`
      (:func:`measure_batched`), and ``fast_batched_speedup`` each ÷ stock highway-env;
      ``batched_shield_share``: the shield's share of a batched decision at N = :data:`SHARE_BATCH`
      (1 − shielded ÷ unshielded rate, the two measured alternately, twice each);
      ``fast_batched_threaded_decisions_per_s`` / ``_speedup``: the same batches shared among
      ``fast_batched_threads`` numba threads (all of this machine's cores);
    * ``envpool_decisions_per_s``: the peer, EnvPool's C++ port (:func:`measure_envpool`), only when the
      optional ``envpool`` extra is installed;
    * ``train_steps_per_s``: decisions per second of a real training run of ``episodes`` episodes of
      ``methods[0]`` (``train_method``; :func:`measure_training`), ``agent_ms_per_decision`` [ms] what
      training adds to a decision, and ``agent_overhead_fraction`` the share of training wall time
      outside the environment, from the run's own clocks (``metrics.csv``: ``wall_time_s``,
      ``env_time_s``); each further method of ``methods`` adds the same three figures with the suffix
      ``_METHOD`` (e.g. ``agent_overhead_fraction_constrained``); the same training on the fast simulator
      adds them with the suffix ``_fast`` (``_METHOD_fast`` for the further methods);
    * ``train_batched_steps_per_s``, ``train_batched_speedup``: :func:`batched_training_figures`;
    * with ``actions="continuous"``: ``continuous_decisions_per_s``, ``discrete_decisions_per_s`` and
      ``continuous_step_ratio`` on each simulator (:func:`continuous_step_figures`).
    """
    if episodes < 1:
        raise ConfigError(f"--episodes: must be >= 1 (got {episodes})")
    if shield not in BENCH_SHIELDS:
        raise ConfigError(f"--shield: bench measures a shield; allowed: {', '.join(BENCH_SHIELDS)}")
    if actions not in ("discrete", "continuous"):
        raise ConfigError(f"--actions: got {actions!r}; allowed: discrete, continuous")
    methods = parse_methods(",".join(methods))
    start = time.perf_counter()
    raw = make_env(BENCH_PRESET)
    shielded = make_env(BENCH_PRESET, **{"shield.mode": shield})
    original = make_env(BENCH_PRESET, neighbour_search="highway-env")
    mask_us: list[float] = []
    obs_us: list[float] = []
    snapshot_us: list[float] = []
    take_snapshot = shielded.get_wrapper_attr("road_snapshot")

    def time_extras() -> None:
        t0 = time.perf_counter()
        snap = take_snapshot()
        t1 = time.perf_counter()
        shielded.compute_mask()
        t2 = time.perf_counter()
        paper_state(snap)
        t3 = time.perf_counter()
        snapshot_us.append((t1 - t0) * 1e6)
        mask_us.append((t2 - t1) * 1e6)
        obs_us.append((t3 - t2) * 1e6)

    raw_n = shield_n = orig_n = stock_n = fast_n = fast_shield_n = 0
    raw_s = shield_s = orig_s = stock_s = fast_s = fast_shield_s = 0.0
    # Per pass over the episodes (FAST_REPEATS passes): decisions and seconds, for the figures' noise.
    pass_n = np.zeros((2, FAST_REPEATS))
    pass_s = np.zeros((2, FAST_REPEATS))
    # Stock highway-env (its own neighbour search and observation, no safelane layer) and the fast
    # simulator through safelane's whole gymnasium stack (paper observation, reward; no shield).
    preset_cfg = load_config(BENCH_PRESET)
    stock = gym.make(preset_cfg.env_id, config=dict(preset_cfg.env))
    fast = make_env(BENCH_PRESET, simulator="fast")
    fast_shielded = make_env(BENCH_PRESET, simulator="fast", **{"shield.mode": shield})
    fast_mask_us: list[float] = []

    def time_fast_mask() -> None:
        t0 = time.perf_counter()
        fast_shielded.compute_mask()
        fast_mask_us.append((time.perf_counter() - t0) * 1e6)

    _play(fast, seed)  # compiles (or loads) the numba kernels outside the timed episodes
    _play(fast_shielded, seed)
    try:
        for i in range(episodes):
            # Alternate which of the pair runs first, so warm-up and drifts favour neither.
            for shielded_turn in (i % 2 == 1, i % 2 == 0):
                if shielded_turn:
                    n, s = _play(shielded, seed + i, on_decision=time_extras)
                    shield_n, shield_s = shield_n + n, shield_s + s
                else:
                    n, s = _play(raw, seed + i)
                    raw_n, raw_s = raw_n + n, raw_s + s
            n, s = _play(original, seed + i)
            orig_n, orig_s = orig_n + n, orig_s + s
            n, s = _play(stock, seed + i)
            stock_n, stock_s = stock_n + n, stock_s + s
            for rep in range(FAST_REPEATS):  # the same episode again: milliseconds each, so time several
                n, s = _play(fast, seed + i)
                fast_n, fast_s = fast_n + n, fast_s + s
                pass_n[0, rep], pass_s[0, rep] = pass_n[0, rep] + n, pass_s[0, rep] + s
                n, s = _play(fast_shielded, seed + i)
                fast_shield_n, fast_shield_s = fast_shield_n + n, fast_shield_s + s
                pass_n[1, rep], pass_s[1, rep] = pass_n[1, rep] + n, pass_s[1, rep] + s
            _play(fast_shielded, seed + i, on_decision=time_fast_mask)  # untimed: the mask's own cost
            if progress is not None:
                progress(i)
    finally:
        raw.close()
        shielded.close()
        original.close()
        stock.close()
        fast.close()
        fast_shielded.close()
    committed = committed_mask_figures(min(episodes, COMMITTED_EPISODES), seed)
    envpool_rate = measure_envpool(dict(preset_cfg.env), max(fast_n, 1000), seed)
    batch_decisions = max(fast_n, BATCH_DECISIONS)
    batched = {str(n): measure_batched(n, batch_decisions, seed, shield) for n in BATCH_SIZES}
    # The shield's share of a batched decision: N = 64 with and without it, alternating, one thread.
    with_shield = without_shield = 0.0
    batch_samples = [batched[str(SHARE_BATCH)]]
    for _ in range(2):  # a few seconds each: shorter samples swing by ±15 % on a shared machine
        batch_samples.append(measure_batched(SHARE_BATCH, SHARE_DECISIONS, seed, shield))
        with_shield += batch_samples[-1]
        without_shield += measure_batched(SHARE_BATCH, SHARE_DECISIONS, seed, "none")
    threads = numba.config.NUMBA_NUM_THREADS
    threaded = {str(n): measure_batched(n, batch_decisions, seed, shield, threads) for n in BATCH_SIZES}
    training: dict[str, Any] = {"train_method": methods[0], **measure_training(episodes, seed, shield, methods[0])}
    for method in methods[1:]:
        figures = measure_training(episodes, seed, shield, method)
        training.update({f"{key}_{method}": value for key, value in figures.items()})
    for method in methods:  # the same training on the fast simulator
        figures = measure_training(episodes, seed, shield, method, simulator="fast")
        suffix = "_fast" if method == methods[0] else f"_{method}_fast"
        training.update({f"{key}{suffix}": value for key, value in figures.items()})
    training.update(batched_training_figures(episodes, seed, shield))
    continuous: dict[str, Any] = {}
    if actions == "continuous":
        continuous = continuous_step_figures(episodes, seed)  # the projection's cost: committed_mask_figures
    raw_rate = raw_n / raw_s
    shield_rate = shield_n / shield_s
    noise = {
        "fast_decisions_per_s": relative_spread(pass_n[0] / pass_s[0]),
        "fast_shielded_decisions_per_s": relative_spread(pass_n[1] / pass_s[1]),
        "fast_batched_decisions_per_s.64": relative_spread(np.asarray(batch_samples)),
    }
    return {
        "preset": BENCH_PRESET,
        "shield": shield,
        **({"actions": actions} if actions == "continuous" else {}),
        "policy": "random",
        "episodes": episodes,
        "seed": seed,
        "decisions": raw_n,
        "env_steps_per_s": raw_rate,
        "shielded_env_steps_per_s": shield_rate,
        "shield_overhead_ratio": shield_rate / raw_rate,
        "snapshot_us_median": float(np.median(snapshot_us)),
        "shield_mask_us_median": float(np.median(mask_us)),
        "obs_us_median": float(np.median(obs_us)),
        "highway_env_steps_per_s": orig_n / orig_s,
        "neighbour_search_speedup": raw_rate / (orig_n / orig_s),
        "highway_env_decisions_per_s": stock_n / stock_s,
        "fast_decisions_per_s": fast_n / fast_s,
        "fast_raw_speedup": (fast_n / fast_s) / (stock_n / stock_s),
        "fast_shielded_decisions_per_s": fast_shield_n / fast_shield_s,
        "fast_speedup": (fast_shield_n / fast_shield_s) / (stock_n / stock_s),
        **mask_cost_figures(fast_mask_us, "_fast"),
        "shield_mask_share_fast": float(np.median(fast_mask_us)) * 1e-6 * (fast_shield_n / fast_shield_s),
        **committed,
        "fast_batched_decisions_per_s": batched,
        "fast_batched_speedup": {n: rate / (stock_n / stock_s) for n, rate in batched.items()},
        # time share = 1 − (time without ÷ time with) = 1 − (rate with ÷ rate without)
        "batched_shield_share": 1.0 - with_shield / without_shield,
        "fast_batched_threads": threads,
        "fast_batched_threaded_decisions_per_s": threaded,
        "fast_batched_threaded_speedup": {n: rate / (stock_n / stock_s) for n, rate in threaded.items()},
        **({"envpool_decisions_per_s": envpool_rate} if envpool_rate is not None else {}),
        **training,
        **continuous,
        # One sample each (training, the mask's mean over every decision): the widest spread measured above.
        "noise": {
            **noise,
            **{key: max(noise.values()) for key in (*HIGHER_IS_BETTER, *LOWER_IS_BETTER) if key not in noise},
        },
        "python": platform.python_version(),
        "wall_time_s": time.perf_counter() - start,
    }


def batched_training_figures(episodes: int = 10, seed: int = 0, shield: str = "robust") -> dict[str, Any]:
    """Many runs, one learner, on one thread: ``train_batched_steps_per_s`` = ``{"10": …, "40": …}``, all
    runs' decisions per second together of :func:`safelane.running.batched_training.train_batched` (robust
    runs of ``episodes`` episodes, the settings of :func:`measure_training`), and ``train_batched_speedup``:
    each ÷ one run's ``train_steps_per_s`` on the fast simulator measured just before (the same process)."""
    from safelane.running.batched_training import train_batched_steps_per_s

    one = measure_training(episodes, seed, shield, "robust", simulator="fast")["train_steps_per_s"]
    rates = train_batched_steps_per_s((10, 40), episodes, seed, shield)
    return {"train_batched_steps_per_s": rates, "train_batched_speedup": {s: r / one for s, r in rates.items()}}


def relative_spread(samples: np.ndarray) -> float:
    """The noise of a figure from its repeated samples: (largest − smallest) ÷ median (0 for one sample)."""
    return float((np.max(samples) - np.min(samples)) / np.median(samples)) if len(samples) > 1 else 0.0


def _figure(result: dict[str, Any], key: str) -> float | None:
    """A figure of a bench result by its dotted ``key`` (``fast_batched_decisions_per_s.64``), None if absent."""
    value: Any = result
    for part in key.split("."):
        if not isinstance(value, dict) or part not in value:
            return None
        value = value[part]
    return float(value)


def regressions(measured: dict[str, Any], published: dict[str, Any]) -> list[dict[str, Any]]:
    """The figures of ``measured`` (a :func:`run_bench` result with its ``noise``) that are worse than the
    ``published`` run's by more than the noise measured for them: a rate [1/s] below ``published × (1 − noise)``,
    a cost [µs] above ``published × (1 + noise)``. Each entry: ``figure``, ``published``, ``measured``,
    ``change`` (measured ÷ published − 1) and ``noise``. Figures either run lacks are skipped."""
    found = []
    for key in (*HIGHER_IS_BETTER, *LOWER_IS_BETTER):
        now, before = _figure(measured, key), _figure(published, key)
        if now is None or before is None or before <= 0:
            continue
        noise = float(measured.get("noise", {}).get(key, 0.0))
        worse = now < before * (1 - noise) if key in HIGHER_IS_BETTER else now > before * (1 + noise)
        if worse:
            found.append(
                {"figure": key, "published": before, "measured": now, "change": now / before - 1, "noise": noise}
            )
    return found


def with_regressions(measured: dict[str, Any], published: dict[str, Any] | None, source: str | None) -> dict[str, Any]:
    """``measured`` with ``baseline`` (``source``, the published run's file, or None) and ``regressions``
    (:func:`regressions` against ``published``; empty without one)."""
    found = regressions(measured, published) if published is not None else []
    return {**measured, "baseline": source, "regressions": found}
