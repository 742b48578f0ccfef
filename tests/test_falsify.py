"""The falsification campaign: cells over a grid, counterexample files, break classes, resume (real fast
simulator, real shield)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from safelane.config import ConfigError
from safelane.running.counterexamples import load_counterexample, replay
from safelane.running.falsify.grid import break_class, load_campaign_spec, read_spec_yaml, run_campaign

GRID = Path(__file__).resolve().parents[1] / "configs" / "falsify" / "grid.yaml"
CLAIM = GRID.parent / "claim.yaml"


def write_spec(path: Path, **fields: object) -> Path:
    data = {
        "name": "tiny",
        "sets": ["env.duration=6"],
        "axes": {
            "lanes": [{"env.lanes_count": 3}, {"env.lanes_count": 4}],
            "adversary": [{"traffic.adversary": "none"}, {"traffic.adversary": "brake"}],
        },
        "policies": ["random"],
        "episodes": 4,
    }
    data.update(fields)
    path.write_text(yaml.safe_dump(data))
    return path


def test_shipped_grid_covers_the_issues_axes() -> None:
    spec = load_campaign_spec(GRID)
    assert set(spec.axes) == {"rate", "lanes", "density", "drivers"}
    assert len(spec.cells()) == 4 * 5 * 4 * 4 * 2
    rates = {(s["env.policy_frequency"], s["env.simulation_frequency"]) for s in spec.axes["rate"]}
    assert {r for r, _ in rates} == {1, 2, 3, 5} and all(f % r == 0 for r, f in rates)
    sampled = load_campaign_spec(GRID, {"sample": 7}).cells()
    assert len(sampled) == 7 and sampled == load_campaign_spec(GRID, {"sample": 7}).cells()


def test_the_claim_s_grid_has_every_axis_of_the_issue_and_100k_episodes() -> None:
    """configs/falsify/claim.yaml: grid.yaml's axes, the three scripted policies and
    traffic.vehicles_behind 0–25, ≥ 100 000 episodes, on the fast simulator, the rule named; every shipped grid
    spec loads and names the rule it runs (search specs have their own loader, tests/test_falsify_search.py)."""
    shipped = [p for p in sorted(GRID.parent.glob("*.yaml")) if "search" not in read_spec_yaml(p)]
    assert len(shipped) >= 5 and all(load_campaign_spec(p).name for p in shipped)
    assert all(load_campaign_spec(p).sets[0] == "shield.rule=forecast-fallback" for p in shipped)
    committed = load_campaign_spec(CLAIM.parent / "claim-committed.yaml")  # the claim's grid, another shield
    assert committed.shield == "committed" and committed.sets == ["shield.rule=forecast-fallback"]
    assert committed.model_dump(exclude={"name", "description", "shield", "sets"}) == load_campaign_spec(
        CLAIM
    ).model_dump(exclude={"name", "description", "shield", "sets"})
    spec = load_campaign_spec(CLAIM)
    assert set(spec.axes) == {"rate", "lanes", "density", "drivers", "behind"}
    behind = [s["traffic.vehicles_behind"] for s in spec.axes["behind"]]
    assert min(behind) == 0 and max(behind) == 25
    assert set(spec.policies) == {"random", "faster", "probe"} and spec.simulator == "fast"
    assert len(spec.cells()) * spec.episodes >= 100_000
    assert spec.axes["drivers"] == load_campaign_spec(GRID).axes["drivers"]


def test_campaign_writes_cells_skips_what_the_simulator_lacks_and_resumes(tmp_path: Path) -> None:
    spec = load_campaign_spec(write_spec(tmp_path / "c.yaml"))
    out = tmp_path / "out"
    summary = run_campaign(spec, out, workers=1)
    assert summary["cells"] == 4 and summary["cells_skipped"] == 2  # adversaries: not on the fast simulator
    assert summary["episodes"] == 8
    rows = (out / "cells.csv").read_text().splitlines()
    assert (
        len(rows) == 1 + 4
        and "traffic.adversary: 'brake' not supported by simulator=fast" in (out / "cells.csv").read_text()
    )
    files = sorted((out / "counterexamples").glob("*.json"))
    assert len(files) == summary["invariant_breaks"] + summary["collisions"]
    # What each condition costs beside what it breaks: fallback rate and speed, over the decisions played.
    played = [json.loads(p.read_text()) for p in sorted((out / "cells").glob("*.json"))]
    played = [c for c in played if "skipped" not in c]
    decisions = sum(c["decisions"] for c in played)
    assert summary["fallback_rate"] == pytest.approx(
        sum(c["fallback_rate"] * c["decisions"] for c in played) / decisions
    )
    assert summary["mean_speed"] == pytest.approx(sum(c["mean_speed"] * c["decisions"] for c in played) / decisions)
    assert 0 < summary["mean_speed"] < 40
    markdown = (out / "summary.md").read_text()
    assert "## By policy" in markdown and "## By lanes" in markdown
    header = next(line for line in markdown.splitlines() if line.startswith("| setting"))
    assert "collisions (front / rear / side)" in header and "fallback" in header and "speed [m/s]" in header
    policy_row = next(line for line in markdown.splitlines() if line.startswith("| random |"))
    assert policy_row.split(" | ")[1] == "8" and policy_row.endswith(f"{summary['mean_speed']:.2f} |")
    for path in files[:2]:
        assert replay(load_counterexample(path)).reproduced
    stamps = [p.stat().st_mtime_ns for p in sorted((out / "cells").glob("*.json"))]
    assert run_campaign(spec, out, workers=1) == summary
    assert [p.stat().st_mtime_ns for p in sorted((out / "cells").glob("*.json"))] == stamps
    with pytest.raises(ConfigError, match="holds a campaign of another spec"):
        run_campaign(load_campaign_spec(write_spec(tmp_path / "d.yaml", episodes=5)), out, workers=1)


def test_the_traffic_seed_draws_fresh_episodes_and_zero_keeps_the_published_ones(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A campaign's traffic seed (``seed:``, ``safelane falsify --seed``): 0, the default, resets cell c's episodes
    with FALSIFY_SEED_BASE + 10 000·c + k as always and leaves campaign.json and summary.json without it; seed 1
    starts them 10¹⁰ further, plays other traffic and records the seed in both."""
    import safelane.running.evaluation as evaluation
    from safelane.running.conditions import TRAFFIC_SEED_STRIDE
    from safelane.running.falsify.grid import CELL_SEED_STRIDE, FALSIFY_SEED_BASE

    seeds: list[int] = []
    real = evaluation.run_config

    def spy(config: object, policy: object, episodes: int, seed: int, *args: object, **kwargs: object) -> object:
        seeds.append(seed)
        return real(config, policy, episodes, seed, *args, **kwargs)

    monkeypatch.setattr(evaluation, "run_config", spy)
    fields = {"axes": {"lanes": [{"env.lanes_count": 3}, {"env.lanes_count": 4}]}, "episodes": 2}
    cells = {}
    for seed in (0, 1):
        seeds.clear()
        spec = load_campaign_spec(write_spec(tmp_path / f"s{seed}.yaml", **fields), {"seed": seed})
        out = tmp_path / f"out{seed}"
        summary = run_campaign(spec, out, workers=1)
        first = FALSIFY_SEED_BASE + seed * TRAFFIC_SEED_STRIDE
        assert seeds == [first, first + CELL_SEED_STRIDE]
        recorded = json.loads((out / "campaign.json").read_text())
        assert recorded.get("seed", 0) == seed and summary.get("traffic_seed", 0) == seed
        assert ("seed" in recorded) == ("traffic_seed" in summary) == (seed != 0)
        cells[seed] = [json.loads(p.read_text())["mean_speed"] for p in sorted((out / "cells").glob("*.json"))]
    assert cells[0] != cells[1]


def test_a_trained_agent_joins_the_campaign_where_its_interface_fits(tmp_path: Path) -> None:
    """``run:RUN_DIR`` drives the cells at its own decision rate (on the fast batch, the same records
    as one by one) and is recorded as skipped at another; a policy that is neither is one line."""
    from safelane.env.factory import make_env
    from safelane.running.evaluation import run_episodes
    from safelane.running.falsify.grid import cell_config
    from safelane.running.run_directory import load_policy, make_train_config
    from safelane.running.training import train

    run_dir = train(make_train_config(method="robust", episodes=1, seed=0, sets=["simulator=fast"]), tmp_path / "r")
    rates = [
        {"env.policy_frequency": 1, "env.simulation_frequency": 5},
        {"env.policy_frequency": 2, "env.simulation_frequency": 10},
    ]
    path = write_spec(tmp_path / "c.yaml", axes={"rate": rates}, policies=["faster", f"run:{run_dir}"], episodes=3)
    spec = load_campaign_spec(path)
    summary = run_campaign(spec, tmp_path / "out", workers=1)
    assert summary["cells"] == 4 and summary["cells_skipped"] == 1
    cells = [json.loads(p.read_text()) for p in sorted((tmp_path / "out" / "cells").glob("*.json"))]
    trained = [c for c in cells if c["policy"].startswith("run:")]
    assert "skipped" in trained[1] and "decisions/s" in trained[1]["skipped"]
    assert trained[0]["episodes"] == 3
    cell = spec.cells()[trained[0]["index"]]
    one = run_episodes(
        make_env(cell_config(spec, cell)), load_policy(run_dir), 3, trained[0]["index"] * 10_000 + 4_000_000_000
    )
    assert sum(r.length for r in one) == trained[0]["decisions"]
    with pytest.raises(ConfigError, match="unknown policy 'fastest'"):
        load_campaign_spec(write_spec(tmp_path / "d.yaml", policies=["fastest"]))
    missing = load_campaign_spec(write_spec(tmp_path / "e.yaml", policies=[f"run:{tmp_path / 'nothing'}"]))
    with pytest.raises(ConfigError, match="no trained run there"):
        run_campaign(missing, tmp_path / "out2", workers=1)


def test_bad_campaign_keys_fail_once_in_one_line(tmp_path: Path) -> None:
    spec = load_campaign_spec(write_spec(tmp_path / "c.yaml", axes={"lanes": [{"env.lanes_cont": 3}]}))
    with pytest.raises(ConfigError, match="lanes_cont") as err:
        run_campaign(spec, tmp_path / "out", workers=1)
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="no axes"):
        load_campaign_spec(write_spec(tmp_path / "e.yaml", axes={}))


def _result(
    ego_before: int, ego_after: int, before: list[tuple[int, int, float]], after: list[tuple[int, int, float]]
) -> SimpleNamespace:
    """A replay's last decision and final state: (vehicle, lane, dx [m]) before and after it."""

    def scene(vs: list[tuple[int, int, float]]) -> list[dict]:
        return [{"vehicle": v, "lane": lane, "dx": dx, "speed": 20.0} for v, lane, dx in vs]

    last = SimpleNamespace(nearby=scene(before), ego={"lane": ego_before})
    return SimpleNamespace(decisions=[last], final={"nearby": scene(after), "ego": {"lane": ego_after}})


@pytest.mark.parametrize(
    ("ego", "before", "after", "kind"),
    [
        ((0, 0), [(7, 2, 10.0)], [(7, 1, 8.0)], "second_lane_cut_in"),  # lane 2 → next to the ego in lane 0
        ((0, 0), [(7, 2, 90.0)], [(7, 1, 70.0)], "other"),  # same move, too far along the road
        ((1, 1), [(7, 2, 10.0)], [(7, 1, 8.0)], "adjacent_lane_change"),  # cuts into the ego's lane
        ((1, 2), [(7, 0, 30.0)], [(7, 0, 25.0)], "ego_lane_change"),
        ((1, 1), [(7, 1, 30.0)], [(7, 1, 25.0)], "other"),
    ],
)
def test_break_classes_on_hand_built_scenes(ego: tuple[int, int], before: list, after: list, kind: str) -> None:
    assert break_class(_result(ego[0], ego[1], before, after)) == kind


def test_cell_records_are_json(tmp_path: Path) -> None:
    spec = load_campaign_spec(write_spec(tmp_path / "c.yaml", axes={"lanes": [{"env.lanes_count": 3}]}, episodes=2))
    run_campaign(spec, tmp_path / "out", workers=1)
    record = json.loads((tmp_path / "out" / "cells" / "cell00000.json").read_text())
    assert record["episodes"] == 2 and set(record["break_classes"]) >= {"second_lane_cut_in", "other"}


def test_cell_labels_are_short() -> None:
    cells = load_campaign_spec(GRID).cells()
    assert cells[0]["labels"]["drivers"] == "other_vehicles_type=IDMVehicle"
    assert cells[0]["labels"]["rate"] == "policy_frequency=1,simulation_frequency=5"
    # numbers whole: 0.5 and 1.5 were both "5" once, which merged their rows in the summaries
    assert {c["labels"]["density"] for c in cells} == {f"vehicles_density={d}" for d in (0.5, 1.0, 1.5, 2.0)}


FIXTURES = Path(__file__).resolve().parent / "fixtures"  # pinned campaign files: fixtures/README.md
CRASHES = FIXTURES / "grid"


@pytest.mark.parametrize(
    ("name", "context"),
    [
        ("cell00018-seed4000180007-collision-step3.json", "started_unsafe"),  # spawned into a crash
        ("cell00444-seed4004440003-collision-step7.json", "after_break"),
        ("cell00537-seed4005370010-collision-step122.json", "from_safe_state"),  # the rule's own hole
        # FASTER chosen, overridden to SLOWER (safe, 15.2 m), then a Linear car stuck behind a slow one turned
        # in behind the ego within the decision: from a safe state, once filed as "after_fallback" because
        # the *chosen* action was unsafe.
        ("../linear-mobil-incentive/cell00535-seed4005350015-collision-step3.json", "from_safe_state"),
        # The first 100 800-episode campaign's one "after_fallback" crash, the same kind: FASTER overridden to
        # IDLE at 29.9 m/s beside a car level with the ego (the class level_cut_ins closed later).
        ("../grid-100k/cell00649-seed4006490057-collision-step12.json", "from_safe_state"),
    ],
)
def test_collision_context_says_where_a_crash_stands_against_the_promise(name: str, context: str) -> None:
    from safelane.env.factory import make_env
    from safelane.running.evaluation import run_episode, summarize

    cx = load_counterexample(CRASHES / name)
    env = make_env(cx.env_config())
    actions = iter(cx.actions)
    record = run_episode(env, lambda obs, info: next(actions), cx.seed)
    env.close()
    assert record.collision and record.length == cx.step
    assert record.collision_context == context
    assert summarize([record])["collision_contexts"][context] == 1


def test_collision_context_is_none_without_a_shield() -> None:
    from safelane.config import load_config
    from safelane.env.factory import make_env
    from safelane.running.evaluation import run_episode
    from safelane.running.policies import fixed_policy

    env = make_env(load_config("fast", overrides={"simulator": "fast"}))
    record = run_episode(env, fixed_policy("faster"), 0)
    env.close()
    assert record.collision and record.collision_context is None


def test_the_cli_plays_a_spec_under_another_shield(tmp_path: Path) -> None:
    """``--shield`` and ``--set`` play a spec's cells under another shield without copying the spec: the campaign
    records both (a resume under others is refused), the summary has the committed mode's figures; a bad mode or
    key is one line."""
    from typer.testing import CliRunner

    from safelane.cli import app

    spec = write_spec(tmp_path / "s.yaml", axes={"lanes": [{"env.lanes_count": 3}]}, episodes=2)
    out = tmp_path / "out"
    args = ["falsify", str(spec), "--out", str(out), "--workers", "1", "--json"]
    # shield.reading=responsibility: what the published committed campaigns pass, the committed mode's one reading.
    result = CliRunner().invoke(app, [*args, "--shield", "committed", "--set", "shield.reading=responsibility"])
    assert result.exit_code == 0, result.output
    record = json.loads((out / "campaign.json").read_text())
    assert record["shield"] == "committed" and record["sets"][-1] == "shield.reading=responsibility"
    summary = json.loads((out / "summary.json").read_text())
    assert {"lapses", "lapses_in_model", "plan_forced_rate"} <= set(summary)
    again = CliRunner().invoke(app, [*args, "--shield", "robust"])
    assert again.exit_code == 2 and len(again.output.strip().splitlines()) == 1
    for bad, word in ((["--shield", "strong"], "shield"), (["--set", "shield.nope=1"], "shield.nope")):
        result = CliRunner().invoke(app, ["falsify", str(spec), "--out", str(tmp_path / "o2"), *bad])
        assert result.exit_code == 2 and word in result.output and "Traceback" not in result.output
        assert len(result.output.strip().splitlines()) == 1


def test_a_campaign_under_the_belief_shield_splits_its_crashes_by_the_true_type(tmp_path: Path) -> None:
    """Hidden driver types under the belief shield: each cell and the totals count the crashes with a car whose
    true type had been ruled out apart from the others' contexts (together every crash); a mixture's label is
    short; the spec's three shields are one flag apart."""
    spec = load_campaign_spec(
        write_spec(
            tmp_path / "b.yaml", preset="hidden-types", shield="belief", episodes=10,
            sets=["env.duration=20", "env.vehicles_density=3.0"], policies=["random", "faster"],
            axes={"mix": [{"traffic.driver_mix": [{"type": "timid", "weight": 1},
                                                  {"type": "aggressive", "weight": 3}]}]},
        )
    )  # fmt: skip
    assert spec.cells()[0]["labels"]["mix"] == "driver_mix=timid:1+aggressive:3"
    summary = run_campaign(spec, tmp_path / "out", workers=1)
    kept = summary["collision_contexts_types_kept"]  # this dense traffic spawns the ego into two crashes
    assert summary["collisions"] >= 1
    assert summary["collisions_type_ruled_out"] + sum(kept.values()) == summary["collisions"]
    cells = [json.loads(p.read_text()) for p in sorted((tmp_path / "out" / "cells").glob("*.json"))]
    assert sum(c["collisions_type_ruled_out"] for c in cells) == summary["collisions_type_ruled_out"]
    assert "collisions_type_ruled_out" in (tmp_path / "out" / "cells.csv").read_text().splitlines()[0]
    assert "ruled out" in (tmp_path / "out" / "summary.md").read_text()
    shipped = load_campaign_spec(GRID.parent / "claim-hidden-types.yaml")
    assert shipped.shield == "belief" and len(shipped.cells()) * shipped.episodes >= 100_000
    assert load_campaign_spec(GRID.parent / "claim-hidden-types.yaml", {"shield": "robust"}).shield == "robust"
    with pytest.raises(ConfigError, match=r"shield\.mode: 'belief' reads the driver types"):
        run_campaign(load_campaign_spec(write_spec(tmp_path / "n.yaml", shield="belief")), tmp_path / "o2")


def test_shards_split_the_grid_and_merge_to_the_whole_campaigns_totals(tmp_path: Path) -> None:
    """``--shard K/N`` plays the cells K-1, K-1+N, … with their grid indices (so their seeds): the shards partition
    the grid; ``--merge`` over every shard gives the whole campaign's totals, with the shards named and the merge
    complete; one shard alone merges incomplete; a shard twice, another campaign's shard, a folder that is no
    shard, or a bad K/N is one line."""
    from typer.testing import CliRunner

    from safelane.cli import app

    spec_path = write_spec(tmp_path / "s.yaml", policies=["random", "faster"], episodes=2)
    whole = load_campaign_spec(spec_path)
    shards = [load_campaign_spec(spec_path, {"shard": f"{k}/3"}) for k in (1, 2, 3)]
    indices = [[c["index"] for c in s.cells()] for s in shards]
    assert sorted(i for shard in indices for i in shard) == [c["index"] for c in whole.cells()] == list(range(8))
    assert indices[1] == [1, 4, 7]
    assert [c["sets"] for c in shards[1].cells()] == [whole.cells()[i]["sets"] for i in (1, 4, 7)]

    runner = CliRunner()
    small = write_spec(tmp_path / "small.yaml", axes={"lanes": [{"env.lanes_count": 3}, {"env.lanes_count": 4}]},
                       policies=["random", "faster"], episodes=1)  # fmt: skip
    base = ["falsify", str(small), "--workers", "1", "--json"]
    totals = json.loads(runner.invoke(app, [*base, "--out", str(tmp_path / "whole")]).output)
    for k in (1, 2):
        result = runner.invoke(app, [*base, "--shard", f"{k}/2", "--out", str(tmp_path / f"shard{k}")])
        assert result.exit_code == 0, result.output
        assert json.loads(result.output)["shard"] == f"{k}/2"
    folders = [str(tmp_path / f"shard{k}") for k in (2, 1)]
    result = runner.invoke(app, [*base, *(x for f in folders for x in ("--merge", f)), "--out", str(tmp_path / "m")])
    assert result.exit_code == 0, result.output
    merged = json.loads(result.output)
    assert merged["shards"] == ["1/2", "2/2"] and merged["complete"]
    for key in ("cells", "cells_done", "episodes", "decisions", "collisions", "collision_kinds", "collision_contexts",
                "invariant_breaks", "break_classes"):
        assert merged[key] == totals[key], key
    for key in ("mean_speed", "fallback_rate", "invariant_break_rate"):
        assert merged[key] == pytest.approx(totals[key], rel=1e-12), key
    assert "2/2" in (tmp_path / "m" / "summary.md").read_text()

    one = runner.invoke(app, [*base, "--merge", folders[0], "--out", str(tmp_path / "m1")])
    assert one.exit_code == 0 and not json.loads(one.output)["complete"]
    other = write_spec(tmp_path / "o.yaml", axes={"lanes": [{"env.lanes_count": 3}, {"env.lanes_count": 4}]},
                       policies=["random", "faster"], episodes=2)  # fmt: skip
    for args, word in (
        (["--merge", folders[0], "--merge", folders[0]], "twice"),
        (["--merge", str(tmp_path / "whole")], "not a shard"),
        (["--merge", str(tmp_path / "nothing")], "campaign.json"),
        (["--shard", "0/2"], "shard"),
        (["--shard", "3/2"], "shard"),
        (["--shard", "1/2", "--merge", folders[0]], "--merge"),
    ):
        result = runner.invoke(app, [*base, *args, "--out", str(tmp_path / "bad")])
        assert result.exit_code == 2 and word in result.output and "Traceback" not in result.output, result.output
        assert len(result.output.strip().splitlines()) == 1
    result = runner.invoke(app, ["falsify", str(other), "--merge", folders[0], "--out", str(tmp_path / "bad2")])
    assert result.exit_code == 2 and "another campaign" in result.output


def test_breaks_classed_as_they_happen_are_classed_as_their_replays(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Where the episode loop sees every snapshot, a cell classes its invariant breaks as they happen (no replay):
    the class each file's replay gives is the same (hidden types, where breaks are frequent)."""
    import safelane.running.counterexamples as counterexamples
    from safelane.running.falsify.grid import play_cell

    def no_replay(*_: object, **__: object) -> None:
        raise AssertionError("a break was replayed to be classed")

    spec = load_campaign_spec(write_spec(
        tmp_path / "t.yaml", preset="hidden-types", episodes=3, policies=["random"],
        sets=["env.duration=20", "env.vehicles_density=2.0", "traffic.vehicles_behind=12"],
        axes={"rate": [{"env.policy_frequency": 3, "env.simulation_frequency": 15}]},
    ))  # fmt: skip
    with monkeypatch.context() as patch:
        patch.setattr(counterexamples, "replay", no_replay)
        played = play_cell(spec, spec.cells()[0], 7, 3, tmp_path / "cx", "test", "c-")
    assert played["invariant_breaks"] >= 2
    assert len(played["break_file_classes"]) == played["invariant_breaks"]
    for name, kind in played["break_file_classes"].items():
        assert break_class(replay(load_counterexample(tmp_path / "cx" / name))) == kind
