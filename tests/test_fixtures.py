"""The tests read pinned fixtures, never the published results: a published campaign folder may be replaced by its
manifest or leave the tree, and a test must not stop it."""

from __future__ import annotations

import re
from pathlib import Path

TESTS = Path(__file__).resolve().parent
FIXTURES = TESTS / "fixtures"
FIXTURES_LIMIT = 300_000  # [bytes] a handful of files, not a data set

# The published folder as a path string (either slash) or as Path arithmetic (ROOT / "docs" / …), the pattern split
# so that this file does not match itself.
PUBLISHED = re.compile(r"docs" + r"""["']?\s*[/\\]\s*["']?""" + r"results")


def test_no_test_reads_the_published_results() -> None:
    readers = [
        f"{path.relative_to(TESTS)}:{number}"
        for path in sorted(TESTS.rglob("*.py"))
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1)
        if PUBLISHED.search(line)
    ]
    assert not readers, "tests must read tests/fixtures/, not the published results: " + ", ".join(readers)


def test_the_pattern_finds_every_spelling() -> None:
    for line in ('p = "docs/' + 'results/falsify"', 'ROOT / "docs" / "' + 'results"', "docs\\" + "results"):
        assert PUBLISHED.search(line), line
    assert not PUBLISHED.search('FIXTURES / "claim" / "breaks"')


def test_fixtures_stay_small_and_documented() -> None:
    files = [path for path in FIXTURES.rglob("*") if path.is_file()]
    size = sum(path.stat().st_size for path in files)
    assert size <= FIXTURES_LIMIT, f"tests/fixtures holds {size} bytes (limit {FIXTURES_LIMIT})"
    listed = (FIXTURES / "README.md").read_text(encoding="utf-8")
    folders = {path.relative_to(FIXTURES).parts[0] for path in files if len(path.relative_to(FIXTURES).parts) > 1}
    assert all(f"`{folder}/" in listed for folder in folders), sorted(folders)
