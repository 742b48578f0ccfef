"""Many runs, one learner: each run of a batch is the per-run learner's run, bit for bit.

Small runs (6–8 episodes of the fast preset on the fast simulator, learning from decision 64, target syncs
every 50 decisions) so that every piece acts: exploration, updates of every method's loss, target syncs,
λ's dual ascent, runs ending at different decisions and leaving the batch, checkpoints.
"""

from __future__ import annotations

import csv
import time
from pathlib import Path
from typing import Any

import pytest
import torch

from safelane.agents.batched import BatchedLearner
from safelane.agents.dqn import load_agent_config
from safelane.config import ConfigError
from safelane.reporting.metrics_file import METRICS_FILE, TIMING_COLUMNS
from safelane.running.batched_training import train_batched, train_batched_steps_per_s
from safelane.running.run_directory import CHECKPOINT_FILE, load_checkpoint, make_train_config
from safelane.running.training import train

FAST = ["simulator=fast", "agent.learning_starts=64", "agent.target_update_interval=50"]

# Every branch of the batched losses in one batch: the four methods, constrained's two network layouts, runs'
# own learning rates and ε schedules, mse and huber, robust's three shaping targets and its hinge, with and
# without gradient clipping, hard and Polyak target updates.
MIXED: list[tuple[str, int, list[str]]] = [
    ("dqn", 0, ["agent.lr=0.001", "agent.eps_decay_episodes=null", "agent.eps_decay_steps=150"]),
    ("constrained", 0, []),
    ("constrained", 1, ["agent.cost_network=separate", "agent.loss=huber"]),
    ("qmask", 0, ["agent.grad_clip=null"]),
    ("robust", 0, []),
    ("robust", 1, ["agent.shaping_target=safe_min", "agent.shaping_loss=hinge", "agent.loss=huber"]),
    ("robust", 2, ["agent.shaping_target=all_min", "agent.grad_clip=0.5", "agent.tau=0.5"]),
]


def _rows(run_dir: Path) -> list[dict[str, str]]:
    """metrics.csv without its clocks (they vary between identical runs)."""
    with open(run_dir / METRICS_FILE) as f:
        return [{k: v for k, v in row.items() if k not in TIMING_COLUMNS} for row in csv.DictReader(f)]


def _same_networks(a: Path, b: Path) -> bool:
    sa, sb = load_checkpoint(a)["agent"], load_checkpoint(b)["agent"]
    return (
        all(
            torch.equal(sa[part][name][key], sb[part][name][key])
            for part in ("networks", "targets")
            for name in sa[part]
            for key in sa[part][name]
        )
        and sa["rng"] == sb["rng"]
    )


def _cfg(method: str, seed: int, sets: list[str], episodes: int = 6, **fields: Any) -> Any:
    return make_train_config(method=method, seed=seed, episodes=episodes, sets=[*FAST, *sets], **fields)


def test_every_run_of_a_mixed_batch_is_its_run_alone_bit_for_bit(tmp_path: Path) -> None:
    cfgs = [_cfg(m, s, sets) for m, s, sets in MIXED]
    batched = train_batched(cfgs, [tmp_path / f"batched{k}" for k in range(len(cfgs))])
    for k, cfg in enumerate(cfgs):
        alone = train(cfg, tmp_path / f"alone{k}")
        assert _rows(batched[k]) == _rows(alone), f"run {k} ({cfg.method}) differs from the per-run learner"
        assert _same_networks(batched[k], alone)
    # the runs learned (updates and syncs happened) and did not all play the same episodes
    assert all(_rows(b)[-1]["mean_loss"] for b in batched)
    assert len({_rows(b)[0]["return"] for b in batched}) > 1


def test_a_run_in_a_batch_of_four_equals_it_in_a_batch_of_one(tmp_path: Path) -> None:
    cfgs = [_cfg("robust", s, []) for s in range(4)]
    start = time.perf_counter()
    together = train_batched(cfgs, [tmp_path / f"four{s}" for s in range(4)])
    elapsed = time.perf_counter() - start
    # each run's clocks are its share of the batch's: they add up to at most the batch's wall time
    clocks = []
    for run in together:
        with open(run / METRICS_FILE) as f:
            last = list(csv.DictReader(f))[-1]
        clocks.append((float(last["wall_time_s"]), float(last["env_time_s"])))
    assert all(0 < env < wall for wall, env in clocks) and sum(wall for wall, _ in clocks) <= elapsed
    alone = train_batched([cfgs[2]], [tmp_path / "one"])
    assert _rows(together[2]) == _rows(alone[0])
    assert _same_networks(together[2], alone[0])
    assert _rows(together[1]) != _rows(together[2])


def test_same_seeds_twice_same_numbers_and_resume_after_a_kill_ends_the_same(tmp_path: Path) -> None:
    cfgs = [_cfg(m, s, [], episodes=8, checkpoint_every=2) for m, s in (("dqn", 0), ("constrained", 1), ("robust", 2))]
    first = train_batched(cfgs, [tmp_path / f"a{k}" for k in range(3)])
    second = train_batched(cfgs, [tmp_path / f"b{k}" for k in range(3)])
    for a, b in zip(first, second, strict=True):
        assert _rows(a) == _rows(b) and _same_networks(a, b)

    def kill(k: int, report: Any) -> None:  # run 2 reaches episode 5: the others are elsewhere
        if k == 2 and report.episode == 5:
            raise KeyboardInterrupt

    killed = [tmp_path / f"c{k}" for k in range(3)]
    with pytest.raises(KeyboardInterrupt):
        train_batched(cfgs, killed, progress=kill)
    assert len(_rows(killed[2])) == 5 and load_checkpoint(killed[2])["episode"] == 4
    train_batched(cfgs, killed, resume=True)
    for a, c in zip(first, killed, strict=True):
        assert _rows(a) == _rows(c) and _same_networks(a, c)


def test_a_batched_run_resumes_with_the_per_run_trainer(tmp_path: Path) -> None:
    short = _cfg("constrained", 0, [], episodes=4)
    (run,) = train_batched([short], [tmp_path / "run"])
    longer = _cfg("constrained", 0, [], episodes=6)
    train(longer, run, resume=True)
    alone = train(longer, tmp_path / "alone")
    assert _rows(run) == _rows(alone) and _same_networks(run, alone)
    assert (run / CHECKPOINT_FILE).is_file()


def test_bad_batches_are_one_line_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"agent\.batch_size"):
        BatchedLearner([load_agent_config(), load_agent_config(overrides={"batch_size": 32})], [0, 1])
    stock = make_train_config(method="dqn", episodes=1, sets=["simulator=highway-env"])
    with pytest.raises(ConfigError, match="simulator: highway-env"):
        train_batched([stock], [tmp_path / "stock"])
    with pytest.raises(ConfigError, match="out_dirs"):
        train_batched([_cfg("dqn", 0, []), _cfg("dqn", 1, [])], [tmp_path / "x", tmp_path / "x"])


def test_the_bench_figure_counts_every_runs_decisions() -> None:
    rates = train_batched_steps_per_s(sizes=(2,), episodes=1)
    assert set(rates) == {"2"} and rates["2"] > 0


def _same_tables(per_run: dict[str, Any], batched: dict[str, Any]) -> None:
    """The per-method means and bootstrap CIs of speed and collision rate overlap (here: are equal, every
    test episode the same)."""
    for method, entry in per_run["methods"].items():
        a, b = entry["aggregate"], batched["methods"][method]["aggregate"]
        for key in ("mean_speed", "collision_rate"):
            (lo_a, hi_a), (lo_b, hi_b) = a[key]["ci95"], b[key]["ci95"]
            assert lo_a <= hi_b and lo_b <= hi_a, f"{method} {key}: {a[key]} vs {b[key]}"
            assert a[key]["mean"] == b[key]["mean"]
    assert per_run["episodes"] == batched["episodes"]


def test_reproduce_trains_fast_runs_batched_by_default_with_the_same_results(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import safelane.running.batched_training as batched_training
    from safelane.running.experiments import make_spec, run_experiment

    batches: list[int] = []
    real = batched_training.train_batched

    def counting(cfgs: Any, out_dirs: Any, **kw: Any) -> Any:
        batches.append(len(cfgs))
        return real(cfgs, out_dirs, **kw)

    monkeypatch.setattr(batched_training, "train_batched", counting)  # workers=1: tasks run in this process
    spec = make_spec(methods=["dqn", "robust"], seeds=[0, 1], episodes=3, test_episodes=2, sets=FAST)
    batched = run_experiment(spec, tmp_path / "batched", workers=1)
    assert batches == [4]
    per_run = run_experiment(spec, tmp_path / "per-run", workers=1, learner="per-run")
    assert batches == [4]
    _same_tables(per_run, batched)
    with pytest.raises(ConfigError, match="--learner"):
        run_experiment(spec, tmp_path / "bad", workers=1, learner="stacked")


@pytest.mark.slow
def test_small_protocol_gives_the_per_run_learners_table(tmp_path: Path) -> None:
    """4 methods × 3 seeds × 60 episodes, 100 test episodes: the per-run learner's table."""
    from safelane.running.experiments import make_spec, run_experiment

    spec = make_spec(seeds=[0, 1, 2], episodes=60, test_episodes=100, sets=["simulator=fast"])
    per_run = run_experiment(spec, tmp_path / "per-run", workers=1, learner="per-run")
    batched = run_experiment(spec, tmp_path / "batched", workers=1)
    _same_tables(per_run, batched)
