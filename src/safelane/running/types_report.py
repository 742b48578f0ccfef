"""The hidden-types table's report: ``report.md`` and a learning-curve figure per scenario, from ``results.json`` and
the runs' ``metrics.csv`` (:mod:`safelane.running.types_reproduction` writes both).

Per scenario: the arms' table (IQM over seeds with 95 % bootstrap intervals), the expense of robustness, and
``learning_curves_SCENARIO.png``: per shield, each learned agent's training return and training speed per episode,
the IQM over seeds with its 95 % bootstrap band (smoothed as the discrete reproduction's,
:func:`safelane.running.reproduction_report.learning_curve_bands`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from safelane.core.files import atomic_write_text
from safelane.reporting.metrics_file import METRICS_FILE, read_metrics
from safelane.running.experiments import TEST_SEED_BASE
from safelane.running.reproduction_report import BOOTSTRAP_REPS, learning_curve_bands
from safelane.running.types_reproduction import (
    AGENTS,
    LEARNED,
    PAPER_SCENARIO,
    PRESET,
    TypesSpec,
    arm_name,
    types_run_dir,
)

CURVE_COLUMNS: tuple[tuple[str, str], ...] = (
    ("return", "training return (smoothed)"),
    ("mean_speed", "training speed [m/s] (smoothed)"),
)
"""The ``metrics.csv`` columns of the learning curves, each with its axis label."""


def curves_file(scenario: str) -> str:
    """The name of ``scenario``'s learning-curve figure."""
    return f"learning_curves_{scenario}.png"


def training_curves(out_dir: Path, spec: TypesSpec, scenario: str) -> dict[str, dict[str, list[dict[str, np.ndarray]]]]:
    """Per shield and learned agent, the curve columns of every seed's ``metrics.csv`` in ``scenario`` (the runs
    that have one)."""
    curves: dict[str, dict[str, list[dict[str, np.ndarray]]]] = {}
    for shield in spec.shields:
        for agent in spec.agents:
            if agent not in LEARNED:
                continue
            for seed in spec.seeds_of(scenario):
                path = types_run_dir(out_dir, scenario, agent, shield, seed) / METRICS_FILE
                if path.exists():
                    runs = curves.setdefault(shield, {}).setdefault(agent, [])
                    runs.append(read_metrics(path, [c for c, _ in CURVE_COLUMNS]))
    return curves


def fig_learning_curves(curves: dict[str, dict[str, list[dict[str, np.ndarray]]]], scenario: str) -> Figure:
    """One column per shield, one row per curve column: each learned agent's IQM over seeds per training episode
    with its 95 % bootstrap band."""
    shields = list(curves)
    fig = Figure(figsize=(4.5 * len(shields), 3.4 * len(CURVE_COLUMNS)))
    axes = fig.subplots(len(CURVE_COLUMNS), len(shields), squeeze=False)
    for col, shield in enumerate(shields):
        for row, (column, label) in enumerate(CURVE_COLUMNS):
            ax = axes[row][col]
            for i, (agent, band) in enumerate(learning_curve_bands(curves[shield], column).items()):
                xs = np.arange(1, band.point.size + 1)
                ax.plot(xs, band.point, color=f"C{i % 10}", label=f"{agent} ({len(curves[shield][agent])} seeds)")
                ax.fill_between(xs, band.low, band.high, color=f"C{i % 10}", alpha=0.2, lw=0)
            ax.set_title(f"shield {shield}", fontsize=10)
            ax.set_xlabel("training episode")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
    fig.suptitle(f"Learning curves, scenario {scenario} (IQM over seeds, 95 % bootstrap bands)")
    fig.tight_layout()
    return fig


def _est(agg: dict[str, Any], key: str, digits: int, scale: float = 1.0) -> str:
    a = agg[key]
    lo, hi = a["ci95"]
    return f"{a['iqm'] * scale:.{digits}f} [{lo * scale:.{digits}f}, {hi * scale:.{digits}f}]"


def arms_table(arms: dict[str, Any], spec: TypesSpec) -> list[str]:
    """Markdown rows, grouped by shield: per agent the runs, crashes / test episodes (those with a ruled-out true
    type), the IQM over seeds with its 95 % interval of speed, crash rate and fallback rate, and the time per run."""
    lines = [
        "| shield | agent | runs | crashes / test episodes | crashes, true type ruled out | test speed [m/s] "
        "| crash rate [%] | fallback rate [% of decisions] | training / test time per run [s] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for shield in spec.shields:
        for agent in spec.agents:
            data = arms.get(arm_name(agent, shield))
            if data is None:
                continue
            a = data["aggregate"]
            ruled_out = "–" if a["collisions_type_ruled_out"] is None else str(a["collisions_type_ruled_out"])
            train = f"{a['train_wall_time_s']:.1f}" if agent in LEARNED else "–"
            lines.append(
                f"| `{shield}` | `{agent}` | {len(data['per_seed'])} | {a['collisions']} / {a['test_episodes']} | "
                f"{ruled_out} | {_est(a, 'mean_speed', 2)} | {_est(a, 'collision_rate', 2, 100)} | "
                f"{_est(a, 'fallback_rate', 2, 100)} | {train} / {a['eval_wall_time_s']:.1f} |"
            )
    return lines


def expense_table(expense: dict[str, Any]) -> list[str]:
    """Markdown rows: per agent the expense of robustness and what the belief shield recovers of it."""
    lines = [
        "| agent | seeds | omniscient − robust speed [m/s] | belief − robust [m/s] | share belief recovers |",
        "|---|---|---|---|---|",
    ]
    for agent, e in expense.items():
        lo, hi = e["expense"]["ci95"]
        b = e.get("belief_recovers")
        speed = f"{b['speed']:+.2f}" if b else "–"
        share = "–"
        if b and np.isfinite(b["share"]):
            share = f"{b['share']:.0%} [{b['share_ci95'][0]:.0%}, {b['share_ci95'][1]:.0%}]"
        lines.append(f"| `{agent}` | {e['seeds']} | {e['expense']['point']:+.2f} [{lo:+.2f}, {hi:+.2f}] | {speed} "
                     f"| {share} |")  # fmt: skip
    return lines


def scenario_section(scenario: str, data: dict[str, Any], spec: TypesSpec, curves: str | None) -> list[str]:
    """The report's section of one scenario: what it is, its table, its expense of robustness, its curves."""
    sets = ", ".join(f"`{s}`" for s in data["sets"]) or "none"
    description = data["description"][:1].upper() + data["description"][1:]
    lines = [
        f"## Scenario `{scenario}`",
        "",
        f"{description}. Settings on the preset: {sets}. Seeds {data['seeds']}; {data['test_episodes']} "
        "held-out test episodes per run.",
        "",
        "### Test episodes",
        "",
        *arms_table(data["arms"], spec),
        "",
        "### The expense of robustness",
        "",
        *expense_table(data["expense_of_robustness"]),
        "",
    ]
    if curves is not None:
        lines += ["### Learning curves", "", f"![learning curves, scenario {scenario}]({curves})", ""]
    return lines


def write_types_report(out_dir: str | Path) -> Path:
    """Write ``report.md`` and each scenario's learning-curve figure from ``out_dir/results.json`` (atomically);
    returns the report's path."""
    out = Path(out_dir)
    results = json.loads((out / "results.json").read_text())
    spec = TypesSpec.model_validate(results["spec"])
    scenarios = results["scenarios"]
    figures: dict[str, str | None] = {}
    for scenario in scenarios:
        curves = training_curves(out, spec, scenario)
        figures[scenario] = None
        if curves:
            fig_learning_curves(curves, scenario).savefig(out / curves_file(scenario), dpi=100)
            figures[scenario] = curves_file(scenario)
    train_total = sum(p["train_wall_time_s"] for data in scenarios.values() for arm in data["arms"].values()
                      for p in arm["per_seed"].values())  # fmt: skip
    others = [s for s in spec.scenarios if s != PAPER_SCENARIO]
    budget = f"{spec.test_episodes} held-out test episodes per run (seeds {TEST_SEED_BASE} + k) on seeds {spec.seeds}"
    if PAPER_SCENARIO in spec.scenarios and others:
        budget = (f"in `{PAPER_SCENARIO}` {budget}, in {', '.join(f'`{s}`' for s in others)} "
                  f"{spec.scenario_test_episodes} on seeds {spec.scenario_seeds}")  # fmt: skip
    elif others:
        budget = f"{spec.scenario_test_episodes} held-out test episodes per run on seeds {spec.scenario_seeds}"
    lines = [
        "# safelane reproduction report: the price of robustness against hidden driver types",
        "",
        f"Preset `{PRESET}`{' with ' + ', '.join(f'`{s}`' for s in spec.sets) if spec.sets else ''}; scenarios "
        f"{', '.join(spec.scenarios)}; agents {', '.join(spec.agents)}; shields {', '.join(spec.shields)}; "
        f"{spec.episodes} training episodes per learned run (robust Q-masking, agent preset `{spec.agent_preset}`, "
        f"trained under the shield it is tested under); {budget}; always-FASTER on a scenario's first seed only (it "
        "is deterministic)"
        + (" — **quick mode: too few seeds and episodes for conclusions**" if spec.quick else "")
        + f". Training time summed over runs: {train_total:.0f} s; this invocation: "
        f"{results.get('wall_time_s', float('nan')):.0f} s.",
        "",
        "Each run contributes one score per column (its mean over its test episodes); a table gives the "
        f"interquartile mean (IQM) over runs with its 95 % stratified bootstrap interval ({BOOTSTRAP_REPS} samples, "
        "seed 0; with fewer than 4 runs the IQM is the mean), after Agarwal et al. (2021). Fallback rate: decisions "
        "without a safe action ÷ decisions. The `belief` shield's promise is probabilistic: its crashes with a car "
        "whose true type had been ruled out (posterior ≤ ε) are counted apart (– under the other shields).",
        "",
        "The expense of robustness: per agent, the IQM test speed under the `omniscient` shield (each car's true "
        "type) minus under the `robust` one (every type), and how much of it the `belief` shield recovers: "
        "(belief − robust) ÷ (omniscient − robust). Intervals: 95 % percentiles over resamples of the seeds, the "
        "shields' drawn together (a resample with no positive expense has no share).",
        "",
        "The learning curves: per shield, each learned agent's training return and speed per training episode "
        "(a trailing mean over min(10, episodes ÷ 4) episodes), the IQM over seeds with its 95 % bootstrap band "
        "(whole runs resampled).",
        "",
    ]
    for scenario, data in scenarios.items():
        lines += scenario_section(scenario, data, spec, figures[scenario])
    lines += ["## Agents", "", *[f"- `{agent}`: {AGENTS[agent]}" for agent in spec.agents]]
    report = out / "report.md"
    atomic_write_text(report, "\n".join(lines) + "\n")
    return report
