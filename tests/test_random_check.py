"""The random check (badf.bench.random_check) on a fixed run of seeds: random meshes, options and frames, every
answer within the stability table's bounds of the float64 oracle, and no exception but a clear refusal."""

from __future__ import annotations

import pytest

from badf.bench import random_check

CASES = 60


@pytest.mark.timeout(600)  # bounded: CASES cases of at most 3 frames and 180 points each
def test_random_meshes_options_and_frames_answer_within_their_bounds(device):
    result = random_check.check(seconds=480.0, cases=CASES, seed=0, device=device)
    assert result["cases"] == CASES, f"only {result['cases']} cases ran in the time allowed"
    assert result["problems"] == [], "\n".join(str(p) for p in result["problems"])
    # most cases get as far as comparing answers: a run of refusals would check nothing
    assert result["compared"] >= CASES // 2 and result["refused"] < CASES // 4
