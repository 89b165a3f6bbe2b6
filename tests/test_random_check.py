"""The random check (badf.bench.random_check) on a fixed run of seeds: random meshes, options and frames, every
answer within the stability table's bounds of the float64 oracle, and no exception but a clear refusal."""

from __future__ import annotations

import numpy as np
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


class _FlippedAt:
    """A field whose exact answers at one point come with the sign flipped: a wrong side no walk's budget explains."""

    def __init__(self, field, point: np.ndarray) -> None:
        self._field, self._point = field, point

    def info(self) -> dict:
        return self._field.info()

    def stats(self) -> dict:
        return self._field.stats()

    def query(self, points, **options):
        result = self._field.query(points, **options)
        result.distance[np.all(points == self._point, axis=1)] *= -1.0
        return result


def test_a_wrong_side_is_a_problem_unless_its_walk_was_cut(device):
    """In a soup (3,000 random triangles across the unit cube) the winding walks are cut at the budget and their sides
    are estimates, as documented (`last_query_walks_cut`): the check takes those for estimates, each asked alone, and
    only those. A sound sphere's answer with its sign flipped is not taken for one."""
    from badf.bench import _cases
    from badf.server.adf import DistanceField

    count = 3000
    vertices = np.random.default_rng(3).random((3 * count, 3))
    faces = np.arange(3 * count).reshape(-1, 3)
    soup = DistanceField(vertices, faces, depth=3, sign="winding", device=device)
    points = _cases.probe_points(soup, vertices, faces, 60, np.random.default_rng(2))
    wrong = _cases.wrong_sides(soup, vertices, faces, points)
    estimated = random_check.signs_estimated(soup, vertices, faces, points)
    soup.query(points, mode="exact")
    assert soup.stats()["last_query_walks_cut"] > len(points) // 2
    assert set(estimated) <= set(wrong.tolist())
    for index in set(wrong.tolist()) - set(estimated):  # a wrong side from a walk that ran whole is a fault
        pytest.fail(f"point {points[index]} is on the wrong side and its walk was not cut")
    if device == "cpu":
        assert len(estimated) == 10  # as seen on this back-end (2026-12-07): the check above is not empty

    vertices, faces = _cases.icosphere(2)
    sphere = DistanceField(vertices, faces, depth=4, sign="winding", device=device)
    points = np.array([[0.1, 0.2, 0.0], [3.0, 0.0, 0.0], [0.0, -2.0, 1.0]])
    flipped = _FlippedAt(sphere, points[1])
    assert _cases.wrong_sides(sphere, vertices, faces, points).tolist() == []
    assert _cases.wrong_sides(flipped, vertices, faces, points).tolist() == [1]
    assert random_check.signs_estimated(flipped, vertices, faces, points) == []


def test_depths_are_drawn_from_the_range_asked_for(device, capsys):
    """`--depths LO HI` (default 3 6, the draws of every seed before it) moves the check to deeper fields; LO past HI
    is refused before anything runs."""
    import argparse

    from badf.bench import _cli

    rng = np.random.default_rng(0)
    drawn = {random_check.random_options(rng, np.zeros(3), np.ones(3), (7, 9))["depth"] for _ in range(60)}
    assert drawn == {7, 8, 9}
    assert random_check.random_options(np.random.default_rng(5), np.zeros(3), np.ones(3))["depth"] == \
        int(np.random.default_rng(5).integers(3, 7))  # the default draws as before --depths
    result = random_check.check(seconds=120.0, cases=2, seed=7, device=device, depths=(8, 8))
    assert result["depths"] == [8, 8] and result["cases"] == 2 and result["problems"] == []
    flags = argparse.Namespace(name="random-check", rest=["--depths", "6", "4", "--cases", "1"])
    assert _cli.run(flags) == 2
    assert "--depths takes LO before HI" in capsys.readouterr().err
