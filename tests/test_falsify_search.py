"""The falsification search: the CEM update (pure functions), determinism, resume, a tiny search on the
fast simulator that writes its files (real simulator, real shield), and bad input in one line."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from safelane.cli import app
from safelane.config import ConfigError
from safelane.running.counterexamples import load_counterexample, replay
from safelane.running.falsify.grid import CampaignSpec
from safelane.running.falsify.search import (
    SearchSettings,
    SearchSpec,
    cem_update,
    check_parameters,
    draw_samples,
    initial_distribution,
    load_falsify_spec,
    run_search,
    select_elite,
)

SHIPPED = Path(__file__).resolve().parents[1] / "configs" / "falsify" / "search.yaml"


def settings(**fields: Any) -> SearchSettings:
    data: dict[str, Any] = {
        "iterations": 3,
        "population": 5,
        "parameters": {"env.vehicles_density": {"low": 0.0, "high": 10.0}, "env.lanes_count": {"choices": [2, 3, 4]}},
    }
    data.update(fields)
    return SearchSettings.model_validate(data)


def test_elite_selection_and_refit_on_a_hand_worked_example() -> None:
    """5 samples, elite 3 (0.6 × 5), smoothing 0.5. Scores 3.0 tie between samples 1 and 4: sample 4 has
    more collisions and goes first; sample 3 was skipped (None) and never joins, though its x is best."""
    s = settings(elite_fraction=0.6, smoothing=0.5, min_std=0.05)
    dist = {"env.vehicles_density": {"mean": 5.0, "std": 2.0}, "env.lanes_count": {"probs": [1 / 3] * 3}}
    xs, lanes = [1.0, 4.0, 6.0, 9.0, 2.0], [0, 2, 2, 1, 0]
    samples = [{"env.vehicles_density": x, "env.lanes_count": c} for x, c in zip(xs, lanes, strict=True)]
    elite = select_elite([0.5, 3.0, 2.0, None, 3.0], s.elites, tiebreak=[0, 0, 5, 0, 1])
    assert s.elites == 3 and elite == [4, 1, 2]
    new = cem_update(s, dist, [samples[i] for i in elite])
    # elite x = 2, 4, 6: mean 4, std √(8/3); mixed half and half with mean 5, std 2
    assert new["env.vehicles_density"]["mean"] == pytest.approx(4.5, abs=1e-12)
    assert new["env.vehicles_density"]["std"] == pytest.approx(0.5 * math.sqrt(8 / 3) + 1.0, abs=1e-12)
    # elite lanes (indices) 0, 2, 2: frequencies 1/3, 0, 2/3, mixed with the uniform 1/3 each
    assert new["env.lanes_count"]["probs"] == pytest.approx([1 / 3, 1 / 6, 1 / 2], abs=1e-12)
    # the σ floor: identical elites, no smoothing → min_std × width = 0.05 × 10
    same = cem_update(settings(smoothing=1.0), dist, [samples[1], samples[1]])
    assert same["env.vehicles_density"] == {"mean": 4.0, "std": 0.5}
    assert same["env.lanes_count"]["probs"] == [0.0, 0.0, 1.0]
    # every sample ties (no breaks anywhere): no elite, the distribution unchanged
    assert select_elite([0.0, 0.0, None, 0.0], 2, tiebreak=[0, 0, 0, 0]) == []
    assert cem_update(s, dist, []) == dist


def test_cem_moves_toward_the_optimum_of_a_toy_objective() -> None:
    """A toy objective peaked at density 7.3 and 4 lanes (choice 2): the mean walks from 5 to 7.3 and the
    choice's probability from 1/3 to nearly 1."""
    s = settings(population=20, elite_fraction=0.2, smoothing=0.7)
    dist = initial_distribution(s)
    assert dist["env.vehicles_density"] == {"mean": 5.0, "std": 5.0}
    rng = np.random.default_rng(0)
    for _ in range(15):
        samples = draw_samples(s, dist, rng)
        assert all(0.0 <= x["env.vehicles_density"] <= 10.0 for x in samples)
        scores = [-((x["env.vehicles_density"] - 7.3) ** 2) - 4.0 * (x["env.lanes_count"] != 2) for x in samples]
        dist = cem_update(s, dist, [samples[i] for i in select_elite(scores, s.elites)])
    assert abs(dist["env.vehicles_density"]["mean"] - 7.3) < 0.3
    assert dist["env.vehicles_density"]["std"] < 1.0
    assert dist["env.lanes_count"]["probs"][2] > 0.9


def test_draws_are_legal_and_seeded() -> None:
    s = settings(parameters={"traffic.vehicles_behind": {"low": 0, "high": 25, "integer": True}}, population=50)
    dist = initial_distribution(s)
    a = draw_samples(s, dist, np.random.default_rng([7, 0]))
    b = draw_samples(s, dist, np.random.default_rng([7, 0]))
    c = draw_samples(s, dist, np.random.default_rng([7, 1]))
    values = [x["traffic.vehicles_behind"] for x in a]
    assert a == b and a != c
    assert all(type(v) is int and 0 <= v <= 25 for v in values) and {0, 25} <= set(values)  # clipped to the range


def write_search(path: Path, **search: Any) -> Path:
    data: dict[str, Any] = {
        "name": "tiny",
        "sets": [
            "env.duration=10",
            "env.lanes_count=3",
            "env.other_vehicles_type=highway_env.vehicle.behavior.LinearVehicle",
        ],
        "policies": ["faster"],
        "search": {
            "iterations": 2,
            "population": 3,
            "episodes_per_sample": 2,
            "seed": 3,
            "parameters": {
                "env.vehicles_density": {"low": 1.5, "high": 3.0},
                "traffic.vehicles_behind": {"low": 0, "high": 10, "integer": True},
                "rate": {
                    "choices": [
                        {"env.policy_frequency": 1, "env.simulation_frequency": 5},
                        {"env.policy_frequency": 2, "env.simulation_frequency": 10},
                    ]
                },
            },
        },
    }
    data["search"].update(search)
    path.write_text(yaml.safe_dump(data))
    return path


def test_a_tiny_search_writes_its_files_is_deterministic_and_resumes(tmp_path: Path) -> None:
    """2 iterations × 3 samples × 2 episodes on the fast simulator: every break and crash a replayable
    file; the same seed again (through the CLI) gives the same numbers; a killed search resumes."""
    spec = load_falsify_spec(write_search(tmp_path / "s.yaml"))
    assert isinstance(spec, SearchSpec)
    out = tmp_path / "out"
    result = run_search(spec, out, workers=1)
    assert result["iterations_done"] == 2 and result["samples"] == 6 and result["episodes"] == 12
    records = [json.loads(p.read_text()) for p in sorted((out / "samples").glob("sample*.json"))]
    assert [r["index"] for r in records] == list(range(6))
    assert sum(r["invariant_breaks"] for r in records) == result["invariant_breaks"] > 0
    files = sorted((out / "counterexamples").glob("sample*.json"))
    assert len(files) == result["invariant_breaks"] + result["collisions"]
    assert replay(load_counterexample(files[0])).reproduced
    r0 = records[0]
    assert r0["objective"] == pytest.approx(1000 * r0["invariant_breaks"] / r0["decisions"])
    assert 1.5 <= r0["values"]["env.vehicles_density"] <= 3.0 and r0["labels"]["rate"].startswith("policy_frequency=")
    best = result["best"][0]
    assert best["objective"] == max(r["objective"] for r in records)
    # iteration 1 drew from the refit of iteration 0's elite (elite 1 of 3: 0.2 × 3 rounds to 1)
    row0, row1 = result["iterations"]
    assert row0["elite_samples"] == [max(records[:3], key=lambda r: (r["objective"], r["collisions"]))["index"]]
    assert row1["distribution"] != row0["distribution"]
    assert (out / "summary.md").read_text().startswith("# Falsification search tiny")
    assert len((out / "samples.csv").read_text().splitlines()) == 1 + 6

    cli = CliRunner().invoke(app, ["falsify", str(tmp_path / "s.yaml"), "--out", str(tmp_path / "again"), "--json"])
    assert cli.exit_code == 0, cli.output
    assert json.loads(cli.output.strip().splitlines()[-1]) == result
    other = load_falsify_spec(write_search(tmp_path / "t.yaml", seed=4))
    assert run_search(other, tmp_path / "other", workers=1)["iterations"][0]["best_objective"] is not None
    assert json.loads((tmp_path / "other" / "samples" / "sample00000.json").read_text())["values"] != r0["values"]

    # killed during iteration 1: one sample and the results missing; the re-run plays only that sample
    (out / "samples" / "sample00004.json").unlink()
    (out / "search.json").unlink()
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "samples").glob("*.json")}
    assert run_search(spec, out, workers=1) == result
    assert {p.name: p.stat().st_mtime_ns for p in (out / "samples").glob("*.json") if p.name in stamps} == stamps
    with pytest.raises(ConfigError, match="holds a campaign of another spec"):
        run_search(other, out, workers=1)


@pytest.mark.parametrize(
    ("search", "message"),
    [
        ({"method": "ga"}, "search.method: got 'ga'; input should be 'cem'"),
        ({"iteration": 3}, "search.iteration: unknown key; allowed: method, iterations"),
        ({"elite_fraction": 1.5}, "search.elite_fraction"),
        ({"parameters": {}}, "search.parameters: give at least one"),
        ({"parameters": {"env.vehicles_density": {"low": 3, "high": 1}}}, "vehicles_density.high: must be greater"),
        ({"parameters": {"env.vehicles_density": {"low": 1, "hi": 3}}}, "vehicles_density.high: Field required"),
        (
            {"parameters": {"env.vehicles_density": {"low": 1, "high": 3, "step": 1}}},
            "vehicles_density.step: unknown key; allowed: low, high, integer",
        ),
        ({"parameters": {"traffic.adversary": {"choices": ["none", "brake"]}}}, "not a searchable key; allowed: env."),
        ({"parameters": {"shield.margin": {"low": 0, "high": 2}}}, "shield.margin: not a searchable key"),
        ({"parameters": {"env.lanes_count": {"choices": [3]}}}, "lanes_count.choices: give at least 2"),
        ({"parameters": {"rate": {"choices": [{"env.policy_frequency": 1}, 2]}}}, "either all values of rate"),
        ({"parameters": {"traffic.vehicles_behind": {"low": 0, "high": 2.5, "integer": True}}}, "needs whole low"),
        ({"iterations": 1000, "population": 10}, "at most 9000"),
    ],
)
def test_bad_search_specs_fail_in_one_line(tmp_path: Path, search: dict[str, Any], message: str) -> None:
    path = write_search(tmp_path / "s.yaml", **search)
    with pytest.raises(ConfigError) as err:
        load_falsify_spec(path)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_bad_values_fail_before_anything_is_played(tmp_path: Path) -> None:
    """Keys and values are checked at each parameter's extremes by the config's own validation."""
    typo = load_falsify_spec(
        write_search(tmp_path / "a.yaml", parameters={"env.vehicles_densty": {"low": 1, "high": 2}})
    )
    with pytest.raises(ConfigError, match=r"env\.vehicles_densty: unknown highway-env key"):
        run_search(typo, tmp_path / "out", workers=1)  # type: ignore[arg-type]
    zero = load_falsify_spec(
        write_search(tmp_path / "b.yaml", parameters={"env.vehicles_density": {"low": 0, "high": 2}})
    )
    with pytest.raises(ConfigError, match=r"search.parameters.env.vehicles_density at 0.0: env.vehicles_density"):
        check_parameters(zero)  # type: ignore[arg-type]
    assert not (tmp_path / "out").exists()
    with pytest.raises(ConfigError, match=r"--sample: .* is a search"):
        load_falsify_spec(tmp_path / "a.yaml", {"sample": 3})
    data = yaml.safe_load((tmp_path / "a.yaml").read_text())
    (tmp_path / "c.yaml").write_text(yaml.safe_dump({**data, "policies": ["faster", "random"]}))
    with pytest.raises(ConfigError, match="policies: a search plays one policy; got 2"):
        load_falsify_spec(tmp_path / "c.yaml")
    result = CliRunner().invoke(app, ["falsify", str(tmp_path / "c.yaml"), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2 and "a search plays one policy" in result.output
    assert "Traceback" not in result.output and len(result.output.strip().splitlines()) == 1


def test_the_shipped_search_is_in_range_and_a_grid_still_loads_as_one() -> None:
    spec = load_falsify_spec(SHIPPED, {"episodes": 3})
    assert isinstance(spec, SearchSpec) and spec.search.episodes_per_sample == 3 and spec.shield == "robust"
    p = spec.search.parameters
    assert (p["env.vehicles_density"].low, p["env.vehicles_density"].high) == (0.5, 3.0)  # type: ignore[union-attr]
    assert p["traffic.vehicles_behind"].integer and p["traffic.vehicles_behind"].high == 25  # type: ignore[union-attr]
    rates = [(c["env.policy_frequency"], c["env.simulation_frequency"]) for c in p["rate"].choices]  # type: ignore[union-attr]
    assert rates == [(1, 5), (2, 10), (3, 15), (5, 15)]
    check_parameters(spec)
    grid = load_falsify_spec(SHIPPED.parent / "grid.yaml", {"episodes": 3})
    assert isinstance(grid, CampaignSpec) and grid.episodes == 3
