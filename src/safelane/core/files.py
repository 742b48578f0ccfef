"""Atomic file writes: a reader (or a resumed job after a kill) sees the old file or the new one, never half."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


def atomic_write(path: Path, write: Callable[[BinaryIO], object], durable: bool = True) -> None:
    """Write ``path`` through ``write(file)`` on a temporary file in the same directory, then ``os.replace``.

    The parent directory is created if needed; on any error the temporary file is removed and the
    previous ``path`` (if any) is left untouched. ``durable``: the data reaches the disk (``fsync``) before the
    file takes its name; without it a killed process still leaves the old file or the new one (the kernel writes
    what it was given), and a caller writing many files flushes them at once (``os.sync``, a few ms for a hundred
    files where an ``fsync`` each takes a few ms per file).
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            if durable:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def atomic_write_text(path: Path, text: str, durable: bool = True) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (:func:`atomic_write`)."""
    atomic_write(path, lambda f: f.write(text.encode()), durable)
