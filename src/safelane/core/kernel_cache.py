"""numba's disk cache, kept honest across files.

numba keys a cached function to its own source file only. A kernel that compiles in kernels from other
files (the compiled safety rule calls the forecast; the batched simulator calls the rule, the simulator and
the observations) would, after an edit of one of those files, run the old code from the cache. A digest of
every file involved, kept beside the cache, tells when to drop it.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path


def drop_stale_kernel_cache(module_file: str | Path, sources: tuple[str | Path, ...]) -> None:
    """Delete numba's cached kernels of ``module_file`` when any of ``sources`` (its own file included or not)
    changed since they were cached. The cache is numba's default (``__pycache__`` beside the module) or
    ``NUMBA_CACHE_DIR``; a read-only install is left alone (numba then caches elsewhere, or not at all)."""
    module = Path(module_file)
    files = (module, *(Path(s) for s in sources))
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in files)).hexdigest()
    custom = os.environ.get("NUMBA_CACHE_DIR")
    cache_dir = Path(custom) if custom else module.parent / "__pycache__"
    stamp = cache_dir / f"{module.stem}.kernels.sha256"
    pattern = f"{module.stem}.*.nb[ic]"
    try:
        if stamp.is_file() and stamp.read_text() == digest:
            return
        for cached in cache_dir.rglob(pattern) if custom else cache_dir.glob(pattern):
            cached.unlink(missing_ok=True)
        cache_dir.mkdir(parents=True, exist_ok=True)
        stamp.write_text(digest)
    except OSError:
        pass
