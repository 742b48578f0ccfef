"""The mask's cost profile and the kernel comparison across commits (research/mask_cost_profile.py,
research/kernel_ab.py) on a few real random-policy episodes of the fast simulator."""

from __future__ import annotations

import pytest

from research import kernel_ab, mask_cost_profile


def test_mask_cost_profile_splits_the_time_by_kind_of_state_and_cars_in_range() -> None:
    figures = mask_cost_profile.main(["--episodes", "2", "--reps", "1", "--traffic", "bench"])
    bench = figures["bench"]
    n = bench["all"]["n"]
    assert n > 0
    assert sum(bench["by_kind"][k].get("n", 0) for k in mask_cost_profile.KINDS) == n
    assert sum(f.get("n", 0) for f in bench["by_cars"].values()) == n
    shares = [f["share_of_total"] for f in bench["by_kind"].values() if f.get("n", 0)]
    assert sum(shares) == pytest.approx(1.0)
    a = bench["all"]
    assert 0 < a["median"] <= a["p90"] <= a["p99"] <= a["max"] and a["mean"] > 0
    assert 0 < a["share_top1"] <= a["share_top10"] <= 1


@pytest.mark.slow
def test_kernel_at_this_commit_gives_the_same_results_as_this_tree() -> None:
    """kernel_ab.py against HEAD loads and compiles a second copy of the kernels (a minute or two)."""
    figures = kernel_ab.main(["--commit", "HEAD", "--episodes", "1", "--reps", "1", "--traffic", "bench"])
    assert figures["bench"]["mismatches"] == 0 and figures["bench"]["before"]["n"] > 0
