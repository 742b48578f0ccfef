"""numba's disk cache is dropped when a file its kernels compile in changes (safelane.core.kernel_cache)."""

from __future__ import annotations

from pathlib import Path

import pytest

from safelane.core.kernel_cache import drop_stale_kernel_cache


def test_cached_kernels_are_dropped_when_a_source_they_compile_in_changes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    module, callee = tmp_path / "rule.py", tmp_path / "forecast.py"
    module.write_text("# the rule\n")
    callee.write_text("# the forecast, version 1\n")
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    kernel, other = cache / "rule._evaluate-10.py311.nbi", cache / "forecast.forecast_gaps-5.py311.nbi"

    kernel.write_text("stale: no digest yet")
    other.write_text("the callee's own cache")
    drop_stale_kernel_cache(module, (callee,))
    assert not kernel.exists() and other.exists()  # only the module's kernels go
    assert (cache / "rule.kernels.sha256").is_file()

    kernel.write_text("cached with version 1")
    drop_stale_kernel_cache(module, (callee,))
    assert kernel.exists()  # nothing changed: the cache stays

    callee.write_text("# the forecast, version 2\n")
    drop_stale_kernel_cache(module, (callee,))
    assert not kernel.exists()  # the callee changed: the module's cached kernels would run version 1


def test_the_batched_simulator_watches_every_file_of_the_fast_simulator(monkeypatch: pytest.MonkeyPatch) -> None:
    """The batch's kernels compile in the fast simulator's kernels, lanes and numerics and read its layout: an
    edit of any of them must drop the batch's cache."""
    from safelane.env import fast_batch
    from safelane.sim.fast import kernels, lanes, layout, numerics

    watched: list[tuple[str | Path, ...]] = []
    monkeypatch.setattr(fast_batch, "drop_stale_kernel_cache", lambda module, sources: watched.append(sources))
    fast_batch._drop_stale_kernel_cache()
    sources = {Path(s).resolve() for s in watched[0]}
    simulator = {Path(m.__file__).resolve() for m in (kernels, lanes, layout, numerics)}
    assert simulator <= sources
