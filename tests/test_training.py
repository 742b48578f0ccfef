"""The training loop on the real simulator: artefacts, masks, determinism, resume after SIGKILL/Ctrl-C."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from safelane.agents.dqn import METHODS
from safelane.config import ConfigError
from safelane.env.factory import make_env
from safelane.reporting.metrics_file import METRIC_COLUMNS, TIMING_COLUMNS
from safelane.running.run_directory import (
    CHECKPOINT_FILE,
    TrainConfig,
    load_checkpoint,
    load_policy,
    load_run_config,
    make_train_config,
    resolve,
)
from safelane.running.training import EpisodeReport, TrainingInterrupted, train

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

# Short episodes in light traffic: a few seconds per run.
SMALL = [
    "env.duration=4",
    "env.vehicles_count=8",
    "agent.learning_starts=4",
    "agent.batch_size=8",
    "agent.buffer_size=10",  # smaller than a run: the circular overwrite is exercised and checkpointed
    "agent.target_update_interval=5",
    "agent.eps_decay_episodes=2",
]


@pytest.fixture(autouse=True)
def _torch_threads_restored() -> Iterator[None]:
    threads = torch.get_num_threads()
    yield
    assert torch.get_num_threads() == threads  # train() restores what it changes


def small(method: str, episodes: int = 4, seed: int = 0) -> TrainConfig:
    return make_train_config(method=method, episodes=episodes, seed=seed, checkpoint_every=2, sets=SMALL)


def read_metrics(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def without_wall_time(rows: list[dict[str, str]]) -> list[dict[str, str]]:
    return [{k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in rows]


def network_weights(run_dir: Path) -> dict[str, torch.Tensor]:
    state = load_checkpoint(run_dir)["agent"]
    return {
        f"{kind}.{net}.{k}": v
        for kind in ("networks", "targets")
        for net, sd in state[kind].items()
        for k, v in sd.items()
    }


@pytest.mark.parametrize("method", METHODS)
def test_each_method_trains_and_its_policy_drives(method: str, tmp_path: Path) -> None:
    reports: list[EpisodeReport] = []
    out = train(small(method, episodes=4), tmp_path / method, progress=reports.append)
    rows = read_metrics(out)
    assert [r["episode"] for r in rows] == ["1", "2", "3", "4"] and tuple(rows[0]) == METRIC_COLUMNS
    assert [r.episode for r in reports] == [1, 2, 3, 4] and reports[-1].env_steps == int(rows[-1]["env_steps"])
    assert all(r["mean_loss"] for r in rows[1:])  # learning started after 4 steps
    assert all((r["lambda"] != "") == (method == "constrained") for r in rows)
    if method in ("qmask", "robust"):
        assert all(r["shield_interventions"] == "0" for r in rows)  # never took a masked action
    run = load_run_config(out)
    assert run.agent.method == method and run.env.shield.mode == ("robust" if method == "robust" else "nominal")
    assert run.env.env["duration"] == 4 and run.agent.batch_size == 8

    policy = load_policy(out)
    env = make_env(run.env)
    obs, info = env.reset(seed=123)
    for _ in range(4):
        action = policy(obs, info)
        if method in ("qmask", "robust"):
            assert info["action_mask"][action]
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    env.close()


def test_masked_actions_never_taken_while_exploring_in_the_simulator(tmp_path: Path) -> None:
    """A fully exploring qmask agent over many decisions: every action is safe under the shield."""
    cfg = small("qmask", episodes=6)
    cfg.sets = [*SMALL, "agent.eps_end=1.0", "agent.eps_start=1.0"]  # random among safe actions throughout
    rows = read_metrics(train(cfg, tmp_path / "explore"))
    assert sum(int(r["length"]) for r in rows) >= 20
    assert all(r["shield_interventions"] == "0" and r["epsilon"] == "1.0" for r in rows)


def test_same_seed_same_metrics_other_seed_other_metrics(tmp_path: Path) -> None:
    a = train(small("constrained", seed=5), tmp_path / "a")
    b = train(small("constrained", seed=5), tmp_path / "b")
    c = train(small("constrained", seed=6), tmp_path / "c")
    assert without_wall_time(read_metrics(a)) == without_wall_time(read_metrics(b))
    assert without_wall_time(read_metrics(a)) != without_wall_time(read_metrics(c))
    assert all(torch.equal(x, y) for x, y in zip(network_weights(a).values(), network_weights(b).values(), strict=True))


def test_resume_with_more_episodes_equals_one_longer_run(tmp_path: Path) -> None:
    straight = train(small("robust", episodes=5), tmp_path / "straight")
    cfg = small("robust", episodes=3)
    train(cfg, tmp_path / "staged")
    cfg.episodes = 5
    staged = train(cfg, tmp_path / "staged", resume=True)
    assert without_wall_time(read_metrics(staged)) == without_wall_time(read_metrics(straight))
    weights_a, weights_b = network_weights(straight), network_weights(staged)
    assert all(torch.equal(weights_a[k], weights_b[k]) for k in weights_a)


def test_ctrl_c_checkpoints_the_last_episode_and_resume_is_identical(tmp_path: Path) -> None:
    reference = train(small("dqn", episodes=5), tmp_path / "reference")

    def interrupt_at_3(report: EpisodeReport) -> None:
        if report.episode == 3:
            raise KeyboardInterrupt

    with pytest.raises(TrainingInterrupted) as err:
        train(small("dqn", episodes=5), tmp_path / "run", progress=interrupt_at_3)
    assert err.value.episode == 3  # checkpoint_every=2, yet episode 3 was saved on Ctrl-C
    assert load_checkpoint(tmp_path / "run")["episode"] == 3 and len(read_metrics(tmp_path / "run")) == 3
    train(small("dqn", episodes=5), tmp_path / "run", resume=True)
    assert without_wall_time(read_metrics(tmp_path / "run")) == without_wall_time(read_metrics(reference))


SCRIPT = textwrap.dedent(
    """
    import sys, time, pathlib
    from safelane.running.run_directory import make_train_config
    from safelane.running.training import train
    out, marker = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])

    def progress(report):
        if report.episode == 3:  # a checkpoint exists (episode 2); episode 3's row is already written
            marker.touch()
            time.sleep(120)

    train(make_train_config(method="qmask", episodes=6, seed=2, checkpoint_every=2, sets=sys.argv[3:]), out,
          progress=progress)
    """
)


def test_sigkill_mid_run_then_resume_ends_like_an_uninterrupted_run(tmp_path: Path) -> None:
    reference = train(small("qmask", episodes=6, seed=2), tmp_path / "reference")

    run, marker = tmp_path / "killed", tmp_path / "marker"
    proc = subprocess.Popen(
        [sys.executable, "-c", SCRIPT, str(run), str(marker), *SMALL], env={**os.environ, "SDL_VIDEODRIVER": "dummy"}
    )
    try:
        deadline = time.monotonic() + 120
        while not marker.exists():
            assert proc.poll() is None, "training subprocess died"
            assert time.monotonic() < deadline, "training subprocess too slow"
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    assert load_checkpoint(run)["episode"] == 2 and len(read_metrics(run)) == 3

    train(small("qmask", episodes=6, seed=2), run, resume=True)
    rows = read_metrics(run)
    assert [r["episode"] for r in rows] == [str(i) for i in range(1, 7)]  # no duplicated rows
    assert without_wall_time(rows) == without_wall_time(read_metrics(reference))
    weights_a, weights_b = network_weights(reference), network_weights(run)
    assert weights_a.keys() == weights_b.keys()
    assert all(torch.equal(weights_a[k], weights_b[k]) for k in weights_a)


# --- errors --------------------------------------------------------------------------------------
def test_run_directory_errors_are_one_line(tmp_path: Path) -> None:
    out = train(small("dqn", episodes=2), tmp_path / "run")
    with pytest.raises(ConfigError, match="already holds a training run"):
        train(small("dqn", episodes=2), out)
    other = small("dqn", episodes=2)
    other.sets = [*SMALL, "agent.lr=0.1"]
    with pytest.raises(ConfigError, match=r"agent\.lr"):
        train(other, out, resume=True)
    with pytest.raises(ConfigError, match=r"no config\.yaml"):
        load_policy(tmp_path / "nothing")
    (out / CHECKPOINT_FILE).write_bytes(b"not a checkpoint")
    with pytest.raises(ConfigError, match="corrupt") as err:
        load_policy(out)
    assert "\n" not in str(err.value)
    (out / CHECKPOINT_FILE).unlink()
    with pytest.raises(ConfigError, match=r"no checkpoint\.pt"):
        load_policy(out)


@pytest.mark.parametrize(
    ("method", "sets", "message"),
    [
        ("dqn", ["foo.bar=1"], "unknown section 'foo'"),
        ("dqn", ["agent.method=robust"], "--method"),
        ("dqn", ["agent.nope=1"], "agent.nope: unknown key"),
        ("qmask", ["shield.mode=none"], "shield.mode"),
        ("robust", ["shield.override=true"], "shield.override"),
        ("dqn", ["env.lanes_cont=3"], "env.lanes_cont"),
    ],
)
def test_resolve_rejects_bad_overrides(method: str, sets: list[str], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        resolve(make_train_config(method=method, sets=sets))


def test_resolve_routes_overrides_and_picks_the_shield_per_method() -> None:
    run = resolve(make_train_config(method="qmask", sets=["agent.gamma=0.5", "reward.c=3", "shield.mode=robust"]))
    assert run.agent.gamma == 0.5 and run.env.reward.c == 3 and run.env.shield.mode == "robust"
    assert resolve(make_train_config(method="dqn")).env.shield.mode == "nominal"
    with pytest.raises(ConfigError, match="unknown agent preset"):
        make_train_config(method="dqn", agent_preset="fancy")


def test_policy_of_a_masking_method_respects_any_mask(tmp_path: Path) -> None:
    out = train(small("robust", episodes=2), tmp_path / "run")
    policy = load_policy(out)
    rng = np.random.default_rng(0)
    for _ in range(200):
        mask = rng.random(5) < 0.4
        if not mask.any():
            continue
        assert mask[policy(rng.uniform(-1, 1, 26).astype(np.float32), {"action_mask": mask})]


def test_tensorboard_logs_every_episode_of_metrics_csv(tmp_path: Path) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = train(small("dqn", episodes=3), tmp_path / "tb", tensorboard=True)
    events = EventAccumulator(str(out / "tensorboard"))
    events.Reload()
    returns = [e.value for e in events.Scalars("train/return")]
    rows = read_metrics(out)
    assert [e.step for e in events.Scalars("train/return")] == [1, 2, 3]
    assert returns == pytest.approx([float(r["return"]) for r in rows])
    assert [e.value for e in events.Scalars("train/length")] == [float(r["length"]) for r in rows]


def test_env_time_is_the_simulators_share_of_wall_time(tmp_path: Path) -> None:
    """env_time_s grows every episode and stays within wall_time_s: the difference is the agent's cost. Both are
    written to the microsecond (a decision of the fast simulator costs tens of them)."""
    rows = read_metrics(train(small("robust", episodes=3), tmp_path / "timed"))
    env_times = [float(r["env_time_s"]) for r in rows]
    walls = [float(r["wall_time_s"]) for r in rows]
    assert all(0 < e <= w for e, w in zip(env_times, walls, strict=True))
    assert env_times == sorted(env_times) and len(set(env_times)) == 3
