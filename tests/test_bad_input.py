"""Bad input gives one clear line and a non-zero exit, and never destroys earlier good files."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest
from typer.testing import CliRunner

from safelane.cli import app

runner = CliRunner()
TINY = ["--set", "env.duration=3", "--set", "env.vehicles_count=10"]


def invoke(*args: str) -> tuple[int, str]:
    result = runner.invoke(app, list(args))
    return result.exit_code, result.output


def assert_one_line_error(code: int, output: str, *needles: str) -> None:
    lines = [line for line in output.strip().splitlines() if line.strip()]
    assert code != 0
    assert len(lines) == 1 and lines[0].startswith("error: "), output
    assert "Traceback" not in output
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("run") / "qmask"
    code, output = invoke(
        "train", "--method", "qmask", "--episodes", "2", "--out", str(out), "--checkpoint-every", "1", *TINY
    )
    assert code == 0, output
    return out


def copy_run(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for f in src.iterdir():
        (dst / f.name).write_bytes(f.read_bytes())
    return dst


def test_full_disk_while_saving_keeps_the_last_good_checkpoint(
    trained: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = copy_run(trained, tmp_path / "run")
    before = {f.name: f.read_bytes() for f in run.iterdir()}

    def no_space(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("safelane.core.files.os.fsync", no_space)
    code, output = invoke(
        "train", "--method", "qmask", "--episodes", "4", "--out", str(run), "--resume", "--checkpoint-every", "1", *TINY
    )
    assert_one_line_error(code, output, "No space left on device")
    assert (run / "checkpoint.pt").read_bytes() == before["checkpoint.pt"]
    assert (run / "metrics.csv").read_bytes() == before["metrics.csv"]
    assert not [f for f in run.iterdir() if f.name.endswith(".tmp")]


def test_corrupt_checkpoint(trained: Path, tmp_path: Path) -> None:
    run = copy_run(trained, tmp_path / "run")
    (run / "checkpoint.pt").write_bytes(b"not a checkpoint")
    assert_one_line_error(*invoke("evaluate", str(run), "--episodes", "1"), "corrupt")


def test_missing_checkpoint(trained: Path, tmp_path: Path) -> None:
    run = copy_run(trained, tmp_path / "run")
    (run / "checkpoint.pt").unlink()
    assert_one_line_error(*invoke("evaluate", str(run), "--episodes", "1"), "checkpoint")


def test_run_dir_from_an_incompatible_version(trained: Path, tmp_path: Path) -> None:
    run = copy_run(trained, tmp_path / "run")
    text = (run / "config.yaml").read_text().replace("env:", "env:\n  warp_drive: true", 1)
    (run / "config.yaml").write_text(text)
    assert_one_line_error(*invoke("evaluate", str(run), "--episodes", "1"), "config")


def test_not_a_run_dir(tmp_path: Path) -> None:
    assert_one_line_error(*invoke("evaluate", str(tmp_path), "--episodes", "1"), "not a safelane training run")


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["train", "--method", "magic", "--episodes", "1"], "method"),
        (["train", "--method", "dqn", "--episodes", "0"], "--episodes"),
        (["evaluate", "--policy", "faster", "--episodes", "-3"], "--episodes"),
        (["evaluate", "--policy", "faster", "--preset", "moon"], "preset"),
        (["evaluate", "--policy", "teleport"], "--policy"),
        (["evaluate", "--policy", "idle", "--set", "env.lanes_countt=3"], "env.lanes_countt"),
        (["evaluate", "--policy", "idle", "--set", "env.lanes_count=banana"], "env.lanes_count"),
        (["stress", "--policy", "random", "--only", "moonbase"], "moonbase"),
        (["stress", "--policy", "random", "--seed", "-1"], "--seed: must be >= 0"),
        (["falsify", "campaign.yaml", "--seed", "-2"], "--seed: must be >= 0"),
        (["reproduce", "--seeds", "0"], "--seeds"),
        (["reproduce", "--methods", "robust,ppo"], "--methods: got 'robust,ppo'; allowed: dqn, constrained"),
    ],
)
def test_bad_arguments(args: list[str], needle: str) -> None:
    assert_one_line_error(*invoke(*args), needle)


def test_unwritable_output(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("keep me")
    code, output = invoke("train", "--method", "qmask", "--episodes", "1", "--out", str(blocker / "run"), *TINY)
    assert_one_line_error(code, output)
    assert blocker.read_text() == "keep me"


def test_fresh_train_into_an_existing_run_refuses_to_overwrite(trained: Path, tmp_path: Path) -> None:
    run = copy_run(trained, tmp_path / "run")
    before = (run / "checkpoint.pt").read_bytes()
    assert_one_line_error(*invoke("train", "--method", "qmask", "--episodes", "2", "--out", str(run), *TINY))
    assert (run / "checkpoint.pt").read_bytes() == before
