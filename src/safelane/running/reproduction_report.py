"""The reproduction report: Table 4, Fig. 6, Fig. 7, speed vs safety, and the paper's claims, from data; beside
them the distribution over runs (interquartile mean with stratified bootstrap CIs, performance profiles, learning
curves with bands).

``write_report(out_dir)`` reads ``results.json`` and every run's ``metrics.csv`` written by
:mod:`safelane.running.experiments` and writes ``report.md`` with PNG figures beside it. Verdicts on the
paper's claims are computed from the numbers (never written by hand). It is the reproduction's last step
(``safelane reproduce``): it reads the experiment's run directories, so it lives in ``running`` and builds on
``reporting``'s statistics and figures, which know nothing of run directories.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from safelane.core.files import atomic_write_text
from safelane.reporting import stats
from safelane.reporting.metrics_file import read_metrics
from safelane.reporting.plots import plot_curve_bands, plot_performance_profiles
from safelane.running.experiments import ExperimentSpec, run_dir_of

LABELS = {"dqn": "Traditional DQN", "constrained": "Constrained Q", "qmask": "Q-masking", "robust": "Robust Q-masking"}
TABLE4_EPISODES = 7
CONVERGENCE_WINDOW = 10
BOOTSTRAP_REPS = 2000
"""Bootstrap samples behind every interval and band of the over-runs statistics (seed 0)."""
PROFILE_POINTS = 201
"""Thresholds at which a performance profile is evaluated."""


def _training_time(methods: dict[str, Any]) -> float:
    """Seconds of training over every run of ``methods`` (results.json's per-seed ``train_wall_time_s``)."""
    return float(sum(p["train_wall_time_s"] for data in methods.values() for p in data["per_seed"].values()))


def _fmt(x: float, digits: int = 2) -> str:
    return f"{x:.{digits}f}"


def training_curves(out_dir: Path, spec: ExperimentSpec) -> dict[str, list[dict[str, np.ndarray]]]:
    """Per method, the metrics.csv columns (return, epsilon, collision) of every seed's run."""
    curves: dict[str, list[dict[str, np.ndarray]]] = {}
    for method in spec.methods:
        for seed in spec.seeds:
            path = run_dir_of(out_dir, method, seed) / "metrics.csv"
            if path.exists():
                curves.setdefault(method, []).append(read_metrics(path, ["episode", "return", "epsilon", "collision"]))
    return curves


def convergence_episodes(curves: dict[str, list[dict[str, np.ndarray]]]) -> dict[str, list[int]]:
    """Convergence episode of each run (:func:`safelane.reporting.stats.convergence_episode` on its return)."""
    out: dict[str, list[int]] = {}
    for method, runs in curves.items():
        eps = []
        for run in runs:
            ret = run["return"]
            window = max(1, min(CONVERGENCE_WINDOW, len(ret) // 4 or 1))
            eps.append(int(stats.convergence_episode(ret, window=window)))
        out[method] = eps
    return out


def fig7(curves: dict[str, list[dict[str, np.ndarray]]]) -> Figure:
    """Paper Fig. 7: each method's mean training return, smoothed and scaled to [0, 1], with ε."""
    fig = Figure(figsize=(7, 4))
    ax = fig.add_subplot()
    ax2 = ax.twinx()
    for method, runs in curves.items():
        n = min(len(r["return"]) for r in runs)
        mean_ret = np.mean([r["return"][:n] for r in runs], axis=0)
        window = max(1, min(CONVERGENCE_WINDOW, n // 4 or 1))
        ax.plot(np.arange(1, n + 1), stats.scale_01(stats.smooth(mean_ret, window)), label=LABELS[method])
        eps = np.mean([r["epsilon"][:n] for r in runs], axis=0)
        ax2.plot(np.arange(1, n + 1), eps, ls=":", lw=1, color="grey")
    ax.set_xlabel("training episode")
    ax.set_ylabel("scaled average reward (smoothed)")
    ax2.set_ylabel("ε (dotted)")
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title("Fig. 7 — convergence (mean over seeds, scaled per method)")
    fig.tight_layout()
    return fig


def fig6(methods: dict[str, Any]) -> Figure:
    """Paper Fig. 6: average total reward before collision, mean and 95 % CI over seeds."""
    fig = Figure(figsize=(6, 3.5))
    ax = fig.add_subplot()
    names = list(methods)
    means = [methods[m]["aggregate"]["return_before_collision"]["mean"] for m in names]
    cis = [methods[m]["aggregate"]["return_before_collision"]["ci95"] for m in names]
    err = np.array(
        [
            [mu - lo for mu, (lo, _) in zip(means, cis, strict=True)],
            [hi - mu for mu, (_, hi) in zip(means, cis, strict=True)],
        ]
    )
    ax.bar([LABELS[m] for m in names], means, yerr=np.maximum(err, 0), capsize=4, color="tab:blue")
    ax.set_ylabel("reward before collision (test)")
    ax.set_title("Fig. 6 — total reward before collision (95 % CI over seeds)")
    ax.tick_params(axis="x", labelsize=8)
    fig.tight_layout()
    return fig


def fig_speed_safety(methods: dict[str, Any]) -> Figure:
    """Mean speed against collision rate per method (each seed a dot, the mean a cross)."""
    fig = Figure(figsize=(5, 4))
    ax = fig.add_subplot()
    for m, data in methods.items():
        xs = [v["collision_rate"] for v in data["per_seed"].values()]
        ys = [v["mean_speed"] for v in data["per_seed"].values()]
        (line,) = ax.plot(xs, ys, "o", alpha=0.5)
        ax.plot(np.mean(xs), np.mean(ys), "x", ms=12, mew=3, color=line.get_color(), label=LABELS[m])
    ax.set_xlabel("test collision rate")
    ax.set_ylabel("mean speed [m/s]")
    ax.legend(fontsize=8)
    ax.set_title("Speed vs safety")
    fig.tight_layout()
    return fig


def run_scores(methods: dict[str, Any], key: str) -> dict[str, np.ndarray]:
    """Per method, one value per run: results.json's ``per_seed[seed][key]`` in seed order."""
    return {m: np.array([p[key] for p in data["per_seed"].values()], dtype=float) for m, data in methods.items()}


def collision_free_rates(methods: dict[str, Any]) -> dict[str, np.ndarray]:
    """Per method, each run's fraction of test episodes without a collision (1 − its collision rate)."""
    return {m: 1.0 - rates for m, rates in run_scores(methods, "collision_rate").items()}


def profile_thresholds(scores: dict[str, np.ndarray], upper: float | None = None) -> np.ndarray:
    """:data:`PROFILE_POINTS` thresholds spanning every run's score, 5 % beyond each end (at most ``upper``)."""
    values = np.concatenate(list(scores.values()))
    lo, hi = float(values.min()), float(values.max())
    pad = 0.05 * (hi - lo) if hi > lo else 0.01 * max(1.0, abs(lo))
    top = hi + pad if upper is None else min(hi + pad, upper)
    return np.linspace(lo - pad, top, PROFILE_POINTS)


def runs_table(methods: dict[str, Any]) -> list[str]:
    """Markdown rows: per method, the IQM over runs of mean speed and collision-free rate, stratified 95 % CIs."""
    speeds, free = run_scores(methods, "mean_speed"), collision_free_rates(methods)
    lines = [
        "| method | runs | mean speed [m/s]: IQM [95 % CI] | collision-free rate: IQM [95 % CI] |",
        "|---|---|---|---|",
    ]
    for m in methods:
        sp = stats.stratified_bootstrap(speeds[m], stats.iqm, reps=BOOTSTRAP_REPS, seed=0)
        cf = stats.stratified_bootstrap(free[m], stats.iqm, reps=BOOTSTRAP_REPS, seed=0)
        lines.append(
            f"| {LABELS[m]} | {speeds[m].size} | {sp.point:.2f} [{sp.low:.2f}, {sp.high:.2f}] | "
            f"{cf.point:.4f} [{cf.low:.4f}, {cf.high:.4f}] |"
        )
    return lines


def fig_performance_profiles(methods: dict[str, Any]) -> Figure:
    """Performance profiles over runs: fraction of runs above each mean-speed and collision-free-rate threshold."""
    speeds, free = run_scores(methods, "mean_speed"), collision_free_rates(methods)
    panels = [
        (
            "mean speed τ [m/s]",
            stats.performance_profile(speeds, profile_thresholds(speeds), reps=BOOTSTRAP_REPS, seed=0),
        ),
        (
            "collision-free rate τ",
            stats.performance_profile(free, profile_thresholds(free, upper=1.0), reps=BOOTSTRAP_REPS, seed=0),
        ),
    ]
    return plot_performance_profiles(panels, LABELS, title="Performance profiles over runs (95 % bootstrap bands)")


def learning_curve_bands(
    curves: dict[str, list[dict[str, np.ndarray]]], column: str, reps: int = BOOTSTRAP_REPS
) -> dict[str, stats.Band]:
    """Per method, the IQM over seeds of each run's smoothed ``column`` per training episode, with a 95 % band.

    Each run's curve is smoothed like Fig. 7 (trailing mean over ``min(10, episodes // 4)`` episodes) and cut
    to the shortest run's length; the band resamples whole runs (:func:`safelane.reporting.stats.curve_band`).
    """
    out: dict[str, stats.Band] = {}
    for method, runs in curves.items():
        n = min(len(r[column]) for r in runs)
        window = max(1, min(CONVERGENCE_WINDOW, n // 4 or 1))
        stacked = np.array([stats.smooth(r[column][:n], window) for r in runs])
        out[method] = stats.curve_band(stacked, "iqm", reps=reps, seed=0)
    return out


def fig_learning_curves(curves: dict[str, list[dict[str, np.ndarray]]]) -> Figure:
    """Training return and training collision rate per episode: IQM over seeds with 95 % bootstrap bands."""
    panels = [
        ("return (smoothed), IQM over seeds", learning_curve_bands(curves, "return")),
        ("collision rate (smoothed), IQM over seeds", learning_curve_bands(curves, "collision")),
    ]
    return plot_curve_bands(panels, LABELS, title="Learning curves (IQM over seeds, 95 % bootstrap bands)")


def runs_statistics_lines(methods: dict[str, Any]) -> list[str]:
    """The report's section on the distribution over runs: the IQM table and the performance profiles."""
    fewest = min(len(data["per_seed"]) for data in methods.values())
    return [
        "## Over runs: interquartile mean and performance profiles",
        "",
        "Each run (seed) contributes one score: its mean speed, or its fraction of collision-free test "
        "episodes. The interquartile mean (IQM) is the mean of the middle 50 % of the runs (a quarter, rounded "
        "down, cut from each end"
        + ("; with fewer than 4 runs nothing is cut and it is the mean" if fewest < 4 else "")
        + f"). Intervals: percentile stratified bootstrap over runs ({BOOTSTRAP_REPS} samples, seed 0; runs "
        "resampled within each task, here the one held-out test environment), after Agarwal et al. (2021), "
        "*Deep RL at the edge of the statistical precipice* (rliable's practice).",
        "",
        *runs_table(methods),
        "",
        "Performance profiles: the fraction of runs scoring above each threshold τ, with its 95 % stratified "
        "bootstrap band; a curve further right is better at every level of the run distribution.",
        "",
        "![performance profiles](performance_profile.png)",
        "",
    ]


def _verdict(ok: bool | None) -> str:
    return {True: "reproduced", False: "not reproduced", None: "inconclusive"}[ok]


def claims(methods: dict[str, Any], convergence: dict[str, list[int]]) -> list[tuple[str, str, str]]:
    """(claim, verdict, evidence) for each claim of the paper, computed from the numbers.

    A comparison is 'reproduced' when the 95 % CIs over seeds do not overlap in the claimed
    direction, 'not reproduced' when they do not overlap the other way, else 'inconclusive'.
    """

    def agg(m: str, key: str) -> dict[str, Any]:
        return methods[m]["aggregate"][key]

    def compare(a: str, b: str, key: str, lower_better: bool) -> bool | None:
        (alo, ahi), (blo, bhi) = agg(a, key)["ci95"], agg(b, key)["ci95"]
        better = ahi < blo if lower_better else alo > bhi
        worse = alo > bhi if lower_better else ahi < blo
        return True if better else (False if worse else None)

    out: list[tuple[str, str, str]] = []
    if "robust" in methods:
        n = methods["robust"]["aggregate"]["test_episodes"]
        c = methods["robust"]["aggregate"]["collisions"]
        out.append(("Robust Q-masking never collides", _verdict(c == 0), f"{c} collisions in {n} test episodes"))
    base = [m for m in ("dqn", "constrained") if m in methods]
    if "qmask" in methods and base:
        results = [compare("qmask", b, "collision_rate", True) for b in base]
        verdict = False if False in results else (True if all(r is True for r in results) else None)
        ev = ", ".join(
            f"{LABELS[m]} {_fmt(agg(m, 'collision_rate')['mean'], 3)} {_ci_str(agg(m, 'collision_rate'))}"
            for m in ["qmask", *base]
        )
        out.append(("Q-masking is the safest baseline", _verdict(verdict), ev))
    if "constrained" in methods and "dqn" in methods:
        v = compare("constrained", "dqn", "collision_rate", True)
        ev = (
            f"collision rate constrained {_fmt(agg('constrained', 'collision_rate')['mean'], 3)} vs DQN "
            f"{_fmt(agg('dqn', 'collision_rate')['mean'], 3)}"
        )
        out.append(("Constrained Q collides less than traditional DQN", _verdict(v), ev))
    if "robust" in convergence and len(convergence) > 1:
        cis = {m: stats.bootstrap_ci([float(e) for e in eps], seed=0) for m, eps in convergence.items()}
        others = [m for m in convergence if m != "robust"]
        faster = all(cis["robust"][1] < cis[m][0] for m in others)
        slower = any(cis["robust"][0] > cis[m][1] for m in others)
        ev = ", ".join(f"{LABELS[m]} {np.mean(eps):.0f}" for m, eps in convergence.items())
        out.append(
            (
                "Robust Q-masking converges fastest",
                _verdict(True if faster else (False if slower else None)),
                "mean convergence episode: " + ev,
            )
        )
    if "dqn" in methods and len(methods) > 1:
        others = [m for m in methods if m != "dqn"]
        res = [compare("dqn", m, "return_before_collision", False) for m in others]
        verdict = True if all(r is True for r in res) else (False if False in res else None)
        ev = ", ".join(f"{LABELS[m]} {_fmt(agg(m, 'return_before_collision')['mean'], 1)}" for m in methods)
        out.append(("Traditional DQN earns the most reward before collision", _verdict(verdict), ev))
    return out


def _ci_str(a: dict[str, Any], digits: int = 3) -> str:
    lo, hi = a["ci95"]
    return f"[{lo:.{digits}f}, {hi:.{digits}f}]"


def _confirm_scope(results: dict[str, Any]) -> str:
    """\" (the first K of each run's)\" when only part of the test episodes were confirmed."""
    spec = results.get("spec", {})
    k, n = spec.get("confirm_episodes"), spec.get("test_episodes")
    return f" (the first {k} of each run's {n})" if k is not None and n is not None and k < n else ""


def write_report(out_dir: str | Path, gifs: dict[str, str] | None = None) -> Path:
    """Write ``report.md`` and its figures from ``out_dir/results.json``; returns the report path."""
    out = Path(out_dir)
    results = json.loads((out / "results.json").read_text())
    spec = ExperimentSpec.model_validate(results["spec"])
    methods = results["methods"]
    curves = training_curves(out, spec)
    convergence = convergence_episodes(curves)
    figures = {"fig6.png": fig6(methods), "fig7.png": fig7(curves), "speed_vs_safety.png": fig_speed_safety(methods)}
    figures["performance_profile.png"] = fig_performance_profiles(methods)
    if curves:
        figures["learning_curves.png"] = fig_learning_curves(curves)
    for name, fig in figures.items():
        fig.savefig(out / name, dpi=110)

    lines = [
        "# safelane reproduction report",
        "",
        f"Preset `{spec.env_preset}`, agent preset `{spec.agent_preset}`, methods {', '.join(spec.methods)}, "
        f"seeds {spec.seeds}, {spec.episodes} training episodes per run, {spec.test_episodes} held-out test "
        f"episodes per run"
        + (" — **quick mode: too few seeds and episodes for conclusions**" if spec.quick else "")
        + f". Training time summed over runs: {_training_time(methods):.0f} s (each run's own clock, resumes "
        f"included); this invocation: {results.get('wall_time_s', float('nan')):.0f} s.",
        "",
        f"## Table 4 — time to collision [s] in the first 7 test episodes (seed {spec.seeds[0]}; – = no collision)",
        "",
        "| | " + " | ".join(LABELS[m] for m in methods) + " |",
        "|---|" + "---|" * len(methods),
    ]
    first_seed = spec.seeds[0]
    by_method = {m: [e for e in results["episodes"] if e["method"] == m and e["seed"] == first_seed] for m in methods}
    for k in range(min(TABLE4_EPISODES, spec.test_episodes)):
        row = []
        for m in methods:
            eps = [e for e in by_method[m] if e["test_episode"] == k]
            ttc = eps[0]["time_to_collision"] if eps else None
            row.append("–" if ttc is None else f"{ttc:.0f}")
        lines.append(f"| Test {k + 1} | " + " | ".join(row) + " |")
    lines += [
        "",
        "What the paper could not show — all test episodes, all seeds:",
        "",
        "| method | collisions / episodes | collision rate (mean over seeds, 95 % bootstrap CI) | mean speed [m/s] "
        "| net vehicles passed / episode | reward before collision | unsafe choices / decision "
        "| no-safe-action rate |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for m, data in methods.items():
        a = data["aggregate"]
        per = list(data["per_seed"].values())
        lines.append(
            f"| {LABELS[m]} | {a['collisions']} / {a['test_episodes']} | {_fmt(a['collision_rate']['mean'], 3)} "
            f"{_ci_str(a['collision_rate'])} | {_fmt(a['mean_speed']['mean'])} {_ci_str(a['mean_speed'], 2)} | "
            f"{np.mean([p['vehicles_passed'] for p in per]):.1f} | "
            f"{_fmt(a['return_before_collision']['mean'], 1)} | "
            f"{np.mean([p['unsafe_action_rate'] for p in per]):.3f} | "
            f"{np.mean([p['fallback_rate'] for p in per]):.4f} |"
        )
    lines += [
        "",
        "Net vehicles passed: vehicles ahead of the ego at an episode's start minus at its end (overtakes "
        "minus being overtaken; the ego spawns behind all traffic).",
        "",
        "Unsafe choices count test decisions whose chosen action is outside the run's own mask (robust for "
        "robust Q-masking, nominal for the others): DQN and constrained Q act without the mask, so these are "
        "the actions a shield would have masked — including lane changes off the road edge, which the mask "
        "excludes and highway-env turns into IDLE; the masked methods choose inside the mask (0 by "
        "construction).",
        "",
        *runs_statistics_lines(methods),
    ]
    confirmed = {m: d["aggregate"]["confirm"] for m, d in methods.items() if "confirm" in d["aggregate"]}
    if confirmed:
        sim = next(iter(confirmed.values()))["simulator"]
        lines += [
            f"## The same test episodes confirmed on {sim}",
            "",
            f"Every trained agent's test episodes{_confirm_scope(results)} played again on {sim} (same seeds, "
            "same greedy policy): an episode counts as identical when its return, length, collision, kind, "
            "mean speed and action counts are equal.",
            "",
            "| method | collisions / episodes (as trained) | "
            f"collisions / episodes on {sim} [Wilson 95 %] | mean speed [m/s] (as trained / {sim}) | "
            "identical episodes |",
            "|---|---|---|---|---|",
        ]
        for m, c in confirmed.items():
            a = methods[m]["aggregate"]
            lo, hi = c["collision_rate_wilson95"]
            lines.append(
                f"| {LABELS[m]} | {a['collisions']} / {a['test_episodes']} | {c['collisions']} / "
                f"{c['test_episodes']} [{lo:.3f}, {hi:.3f}] | {_fmt(a['mean_speed']['mean'])} / "
                f"{_fmt(c['mean_speed'])} | {c['identical_episodes']} / {c['test_episodes']} |"
            )
        lines.append("")
    lines += [
        "## Fig. 6 — total reward before collision",
        "",
        "![fig6](fig6.png)",
        "",
        "## Fig. 7 — convergence",
        "",
        "![fig7](fig7.png)",
        "",
        "Convergence episode (first episode where the smoothed return reaches 90 % of the way to its final "
        "plateau; mean and 95 % bootstrap CI over seeds):",
        "",
        "| method | convergence episode |",
        "|---|---|",
    ]
    for m, eps in convergence.items():
        lo, hi = stats.bootstrap_ci([float(e) for e in eps], seed=0)
        lines.append(f"| {LABELS[m]} | {np.mean(eps):.1f} [{lo:.1f}, {hi:.1f}] |")
    if curves:
        lines += [
            "",
            "## Learning curves over seeds",
            "",
            "Each run's training return and collision indicator per episode, smoothed as in Fig. 7 (not scaled); "
            f"the line is the IQM over seeds at each episode, the band its 95 % bootstrap interval ({BOOTSTRAP_REPS} "
            "samples of whole runs, seed 0).",
            "",
            "![learning curves](learning_curves.png)",
        ]
    lines += ["", "## Speed vs safety", "", "![speed](speed_vs_safety.png)", ""]
    stress_rows = [(m, s) for m, d in methods.items() for p in d["per_seed"].values() for s in p.get("stress", [])]
    if stress_rows:
        lines += [
            "## Generalisation — each method on the stress conditions",
            "",
            "| method | condition | collisions / episodes | mean speed [m/s] |",
            "|---|---|---|---|",
        ]
        for m, s in stress_rows:
            lines.append(f"| {LABELS[m]} | {s['name']} | {s['collisions']} / {s['episodes']} | {s['mean_speed']:.2f} |")
        lines.append("")
    lines += [
        "## The paper's claims, checked against these numbers",
        "",
        "| claim | verdict | evidence |",
        "|---|---|---|",
    ]
    for claim, verdict, evidence in claims(methods, convergence):
        lines.append(f"| {claim} | **{verdict}** | {evidence} |")
    if gifs:
        lines += ["", "## Episodes (seed-0 policy, first test episode; unsafe actions greyed)", ""]
        for m, path in gifs.items():
            lines += [f"### {LABELS[m]}", "", f"![{m}]({path})", ""]
    report = out / "report.md"
    atomic_write_text(report, "\n".join(lines) + "\n")
    return report


def render_gifs(out_dir: str | Path, max_steps: int = 40) -> dict[str, str]:
    """One GIF per method: the first seed's greedy policy on the first test episode."""
    from safelane.running.episode_video import render_episode
    from safelane.running.experiments import TEST_SEED_BASE
    from safelane.running.run_directory import load_policy
    from safelane.running.runs import run_env_config

    out = Path(out_dir)
    spec = ExperimentSpec.model_validate(json.loads((out / "results.json").read_text())["spec"])
    gifs: dict[str, str] = {}
    for m in spec.methods:
        run_dir = run_dir_of(out, m, spec.seeds[0])
        if not (run_dir / "checkpoint.pt").exists():
            continue
        cfg = run_env_config(run_dir)
        render_episode(cfg, load_policy(run_dir), TEST_SEED_BASE, out / f"episode_{m}.gif", max_steps=max_steps)
        gifs[m] = f"episode_{m}.gif"
    return gifs
