"""A campaign's files pinned by one digest: what ``safelane falsify`` wrote into its ``--out`` folder (its
``cells.csv`` and every counterexample file), counted by kind and hashed, so that a rerun at the same commit can be
checked file for file without keeping thousands of files (or a per-file list of megabytes) in the repository.

    python research/campaign_manifest.py runs/falsify/claim-committed --command "safelane falsify …" \\
        --out docs/results/falsify/claim-committed/manifest.json
    python research/campaign_manifest.py runs/falsify/claim-committed \\
        --check docs/results/falsify/claim-committed/manifest.json

The digest is the sha256 of the lines ``NAME SHA256`` (every file, sorted by name); ``--check`` recomputes it on a
folder and prints the files' counts, exit status 1 if anything differs.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
from collections import Counter
from pathlib import Path
from typing import Any

KINDS = ("collision", "invariant_break", "lapse_in_model", "lapse")
"""Counterexample kinds by file name (``cellNNNNN-seedS-KIND-stepK.json``); ``lapse_in_model`` before ``lapse``."""


def file_digests(folder: Path) -> dict[str, str]:
    """{name relative to ``folder``: sha256} of ``cells.csv`` and every file in ``counterexamples/``."""
    names = [folder / "cells.csv", *sorted((folder / "counterexamples").glob("*.json"))]
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in names if p.is_file()}


def kind_of(name: str) -> str:
    """A counterexample file's kind from its name ('cells.csv' for the table)."""
    return next((kind for kind in KINDS if f"-{kind}-" in name), "cells.csv" if name == "cells.csv" else "other")


def manifest(folder: Path) -> dict[str, Any]:
    """The digest, the count of files and the count per kind of the campaign in ``folder``."""
    digests = file_digests(folder)
    listing = "".join(f"{name} {digest}\n" for name, digest in sorted(digests.items()))
    return {
        "files_count": len(digests),
        "files_by_kind": dict(sorted(Counter(kind_of(name) for name in digests).items())),
        "cells_csv_sha256": digests.get("cells.csv"),
        "listing_sha256": hashlib.sha256(listing.encode()).hexdigest(),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="the campaign's --out folder")
    parser.add_argument("--out", type=Path, help="write the manifest here")
    parser.add_argument("--command", default="", help="the command that wrote the folder (recorded)")
    parser.add_argument("--check", type=Path, help="compare the folder with this manifest")
    parser.add_argument("--commit", help="the commit that wrote the folder (default: this checkout's)")
    args = parser.parse_args(argv)
    if not (args.folder / "cells.csv").is_file():
        print(f"folder: {args.folder} has no cells.csv (not a campaign's --out folder)", file=sys.stderr)
        return 2
    found = manifest(args.folder)
    if args.check is not None:
        pinned = json.loads(args.check.read_text())
        same = all(pinned.get(key) == value for key, value in found.items())
        print(json.dumps({"same": same, **found}, indent=1))
        return 0 if same else 1
    commit = (
        args.commit
        or subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    )
    record = {"command": args.command, "commit": commit, **found}
    text = json.dumps(record, indent=1) + "\n"
    if args.out is not None:
        args.out.write_text(text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
