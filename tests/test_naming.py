"""Names say what a thing is, never when it was made.

Nothing tracked in the repository — code, help text, docs, configs, result files and their folder names, tests —
dates a thing by a round of development ("session", "issue N", "today's rule"). The research record dates its
pages by calendar day (YYYY-MM-DD), which says when a question was asked, not a round.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

DATING = re.compile(
    r"(?<!scope=\")(?<![a-z])sessions?(?:\b|\d)|\bissues? ?#?\d+"
    r"|\btoday'?s (?:rule|code|default)|\b(?:the )?earlier rule\b",
    re.IGNORECASE,
)
"""Words that date a thing by a round of development."""

TEXT_SUFFIXES = {".py", ".md", ".yaml", ".yml", ".toml", ".json", ".csv", ".txt", ".cfg", ".ini", ""}
SKIPPED = {Path(__file__).resolve()}  # this file names the words it forbids


def tracked_files() -> list[Path]:
    """The repository's tracked files (a clean clone's content), or every file under the root without git."""
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    return [ROOT / name for name in out.split("\0") if name]


def test_no_file_or_folder_name_dates_a_thing() -> None:
    offenders = [str(p.relative_to(ROOT)) for p in tracked_files() if DATING.search(str(p.relative_to(ROOT)))]
    offenders += [
        str(p.relative_to(ROOT))
        for p in tracked_files()
        if re.search(r"session|issue\d", str(p.relative_to(ROOT)), re.IGNORECASE)
    ]
    assert offenders == [], f"paths dated by a round of development: {sorted(set(offenders))[:20]}"


def test_no_tracked_text_dates_a_thing_by_a_round_of_development() -> None:
    offenders: list[str] = []
    for path in tracked_files():
        if path.resolve() in SKIPPED or path.suffix not in TEXT_SUFFIXES or not path.is_file():
            continue
        if path.stat().st_size > 2_000_000:
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for number, line in enumerate(text.splitlines(), 1):
            match = DATING.search(line)
            if match:
                offenders.append(f"{path.relative_to(ROOT)}:{number}: {match.group(0)!r}")
    assert offenders == [], f"{len(offenders)} lines date a thing by a round of development:\n" + "\n".join(
        offenders[:40]
    )


@pytest.mark.parametrize(
    "line",
    [
        "On by default since issue 15's ninth session",
        "the earlier rule",
        "today's rule",
        "issue 42",
        "probes/session22/",
        "ceiling_session15",
    ],
)
def test_the_check_catches_dating_words(line: str) -> None:
    assert DATING.search(line)


@pytest.mark.parametrize(
    "line", ["2026-12-05", "the first frame of the decision", "a Ray Tune trial", '@pytest.fixture(scope="session")']
)
def test_the_check_lets_plain_words_through(line: str) -> None:
    assert not DATING.search(line)
