"""The README and the documentation site: the strict build, every example, the README's size.

* The site builds with ``mkdocs build --strict`` (broken links and anchors, pages missing from the
  navigation, docstrings griffe cannot parse: all fail).
* Every ```python block of the README, getting started and the guides runs, in order per file in one
  namespace, in a temporary directory (``docs/`` and ``configs/`` linked into it), with the small budgets
  the examples are written with.
* Every ``safelane …`` line of their ```bash blocks names a real command and only options that command
  has (read from its ``--help``); the commands are not run, since their documented budgets are the real
  ones.
* Every ```yaml block that is a sweep or falsification spec (grid or search) validates as one.
* The README is at most 6 000 characters and its relative links point to files that exist.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from safelane.cli import app

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
EXAMPLE_PAGES = [README, ROOT / "docs" / "getting-started.md", *sorted((ROOT / "docs" / "guides").glob("*.md"))]
README_LIMIT = 6000

FENCE = re.compile(r"^```(\w+)[^\n]*\n(.*?)^```[ \t]*$", re.S | re.M)
OPTION = re.compile(r"(?<![\w-])(--[a-z][a-z0-9-]*|-[a-zA-Z])(?![\w-])")


def blocks(path: Path, language: str) -> list[str]:
    """The fenced code blocks of ``path`` in ``language``, in order."""
    return [body for lang, body in FENCE.findall(path.read_text(encoding="utf-8")) if lang == language]


def _id(path: Path) -> str:
    return str(path.relative_to(ROOT))


def test_readme_is_short() -> None:
    size = len(README.read_text(encoding="utf-8"))
    assert size <= README_LIMIT, f"README.md has {size} characters (limit {README_LIMIT}): move detail into docs/"


def test_readme_links_exist() -> None:
    text = README.read_text(encoding="utf-8")
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    local = [link for link in links if "://" not in link]
    assert local, "the README links into the site"
    missing = [link for link in local if not (ROOT / link).exists()]
    assert not missing, f"README.md links to missing files: {missing}"


def test_site_builds_strictly(tmp_path: Path) -> None:
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1", "PYTHONPATH": str(ROOT / "src")}
    command = [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(ROOT / "mkdocs.yml")]
    proc = subprocess.run(
        [*command, "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    problems = [line for line in proc.stderr.splitlines() if line.startswith(("WARNING", "ERROR"))]
    shown = problems or proc.stderr.splitlines()[-20:]
    assert proc.returncode == 0, "mkdocs build --strict failed:\n" + "\n".join(shown)
    assert (tmp_path / "site" / "reference" / "shield" / "index.html").exists()


@pytest.mark.parametrize("page", [p for p in EXAMPLE_PAGES if blocks(p, "python")], ids=_id)
def test_python_examples_run(page: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("docs", "configs"):
        (tmp_path / name).symlink_to(ROOT / name)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    namespace: dict[str, object] = {"__name__": "__docs_example__"}
    for i, code in enumerate(blocks(page, "python"), start=1):
        try:
            exec(compile(code, f"{_id(page)}, python block {i}", "exec"), namespace)
        except Exception as err:
            raise AssertionError(f"{_id(page)}, python block {i} failed: {type(err).__name__}: {err}") from err


def _commands(page: Path) -> list[list[str]]:
    """The ``safelane …`` command lines of ``page``'s bash blocks (continuation lines joined, comments cut)."""
    lines = []
    for body in blocks(page, "bash"):
        for line in body.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            if words and words[0] == "safelane":
                lines.append(words)
    return lines


_HELP: dict[tuple[str, ...], str] = {}


def _help(path: tuple[str, ...]) -> str:
    if path not in _HELP:
        result = CliRunner().invoke(app, [*path, "--help"], env={"COLUMNS": "250", "NO_COLOR": "1"}, color=False)
        assert result.exit_code == 0, f"safelane {' '.join(path)} --help exited {result.exit_code}"
        _HELP[path] = result.output
    return _HELP[path]


def _command_path(words: list[str]) -> tuple[str, ...]:
    """The subcommand words of a ``safelane`` line (``sim check``, ``env show``, ``train``)."""
    path: tuple[str, ...] = ()
    for word in words[1:]:
        if word.startswith("-"):
            break
        text = _help(path)
        commands = text[text.find("Commands") :] if "Commands" in text else ""
        if not re.search(rf"^\W {re.escape(word)}\s", commands, re.M):
            break
        path = (*path, word)
    return path


@pytest.mark.parametrize("page", [p for p in EXAMPLE_PAGES if _commands(p)], ids=_id)
def test_cli_lines_use_real_commands_and_options(page: Path) -> None:
    bad = []
    for words in _commands(page):
        path = _command_path(words)
        if not path:
            bad.append(f"{shlex.join(words)}: no such command")
            continue
        text = _help(path)
        for word in words[1 + len(path) :]:
            option = word.split("=", 1)[0]
            if OPTION.fullmatch(option) and not re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", text):
                bad.append(f"{shlex.join(words)}: safelane {' '.join(path)} has no option {option}")
    assert not bad, "\n".join(bad)


def _specs() -> list[tuple[str, str]]:
    return [(f"{_id(page)}#{i}", body) for page in EXAMPLE_PAGES for i, body in enumerate(blocks(page, "yaml"), 1)]


@pytest.mark.parametrize(("where", "body"), _specs(), ids=[where for where, _ in _specs()])
def test_yaml_specs_validate(where: str, body: str, tmp_path: Path) -> None:
    from safelane.running.falsify.grid import load_campaign_spec
    from safelane.running.falsify.search import SearchSpec, check_parameters, load_falsify_spec
    from safelane.running.sweeps import load_sweep_spec

    data = yaml.safe_load(body)
    spec = tmp_path / "spec.yaml"
    spec.write_text(body, encoding="utf-8")
    if "axes" in data:
        assert load_campaign_spec(spec).cells()
    elif "space" in data:
        load_sweep_spec(spec)
    elif "search" in data:  # a falsification search (a sweep's search: is its method, with a space)
        search = load_falsify_spec(spec)
        assert isinstance(search, SearchSpec)
        check_parameters(search)
    else:
        pytest.fail(f"{where}: a yaml block that is neither a sweep nor a falsification spec")
