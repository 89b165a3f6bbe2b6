"""The CPU back-end's launches shared out over threads (server/adf/_threads.py): the corner searches, winding
numbers, signs and point queries cut into chunks give, bit for bit, what one launch gives, and the exact answers
hold against the float64 oracle. CPU only: CUDA launches are never cut."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import meshes
import oracle
import tolerances as tol
from badf.server.adf import DistanceField
from badf.server.adf import _sign, _threads
from badf.server.adf._distance import CornerField


def _wobble(vertices: np.ndarray, t: float) -> np.ndarray:
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    phase = 2.0 * np.pi * ((vertices - lo) / (hi - lo) + t)
    return (vertices + 0.01 * float(np.linalg.norm(hi - lo)) * np.sin(phase[:, [1, 2, 0]])).astype(np.float32)


def _answers(vertices, faces, points, options) -> list[np.ndarray]:
    """Corners and queries of a field over two frames: everything the shared-out kernels write."""
    field = DistanceField(vertices, faces, device="cpu", **options)
    answers = []
    for t in (0.0, 0.05):
        field.update(_wobble(vertices, t))
        answers += list(field.corner_samples())
        adf = field.query(points, outputs=("distance", "closest_point", "normal", "face"))
        exact = field.query(points, mode="exact", outputs=("distance", "face"))
        answers += [adf.distance, adf.closest_point, adf.normal, adf.face, exact.distance, exact.face,
                    field.query(points, outputs=("normal",)).normal]
    return answers


@pytest.mark.parametrize(("name", "options", "far_cells"), [
    ("spot", {"depth": 5}, None),  # closed: pseudonormals
    ("sheet", {"depth": 5}, None),  # open: winding numbers beside the searches
    ("fandisk", {"depth": 5, "coherence": False, "halo": 0}, 2),  # far corners listed and searched by subtree
    ("torus", {"depth": 5, "band": 0.05, "sign": "none"}, None),  # a band, unsigned
])
def test_chunks_on_threads_answer_as_one_launch(monkeypatch, name, options, far_cells):
    monkeypatch.setattr(_threads, "MIN_CHUNK", 64)  # many chunks even for small fields
    monkeypatch.setattr(CornerField, "far_cells", far_cells)
    pools = []
    executor = _threads.shared_pool
    monkeypatch.setattr(_threads, "shared_pool", lambda threads: pools.append(threads) or executor(threads))
    vertices, faces = meshes.load(name)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    points = np.random.default_rng(3).uniform(lo - 0.2 * (hi - lo), hi + 0.2 * (hi - lo), (3000, 3)).astype(np.float32)

    monkeypatch.setenv("BADF_CPU_THREADS", "1")
    one = _answers(vertices, faces, points, options)
    assert not pools  # one thread: every launch whole
    monkeypatch.setenv("BADF_CPU_THREADS", "3")
    shared = _answers(vertices, faces, points, options)
    assert pools and set(pools) == {3}
    for whole, chunked in zip(one, shared, strict=True):
        np.testing.assert_array_equal(chunked, whole)

    # and the chunked answers are the exact ones: stored corners and exact queries against the float64 oracle
    frame = _wobble(vertices, 0.05)
    diag = oracle.bbox_diagonal(frame)
    positions, values = shared[10], shared[11]  # the second frame's corners
    at_corners = oracle.nearest(positions, frame, faces).distance
    if "band" in options:  # corners beyond the band hold +-band
        within = np.abs(values) < options["band"]
        assert np.all(at_corners[~within] >= options["band"] - tol.EXACT_DISTANCE * diag)
        values, at_corners = values[within], at_corners[within]
    assert np.all(np.abs(np.abs(values) - at_corners) <= tol.EXACT_DISTANCE * diag)
    truth = oracle.nearest(points, frame, faces).distance
    exact = shared[17]
    if "band" in options:
        near = truth < 0.9 * options["band"]
        assert np.all(np.abs(np.abs(exact[near]) - truth[near]) <= tol.EXACT_DISTANCE * diag)
    else:
        assert np.all(np.abs(np.abs(exact) - truth) <= tol.EXACT_DISTANCE * diag)


def test_a_bad_thread_count_is_refused_before_a_frame_starts(monkeypatch):
    """Refused when the field is built, updated or queried, and the field keeps answering its last frame."""
    vertices, faces = meshes.load("spot")
    field = DistanceField(vertices, faces, depth=5, device="cpu")
    points = np.random.default_rng(4).uniform(vertices.min(axis=0), vertices.max(axis=0), (4000, 3)).astype(np.float32)
    before = field.query(points).distance
    monkeypatch.setenv("BADF_CPU_THREADS", "zero")
    for call in (lambda: field.update(_wobble(vertices, 0.1)), lambda: field.query(points),
                 lambda: DistanceField(vertices, faces, depth=5, device="cpu")):
        with pytest.raises(ValueError, match="BADF_CPU_THREADS"):
            call()
    monkeypatch.delenv("BADF_CPU_THREADS")
    assert field.stats()["frame"] == 0 and not field.info()["failed_update"]
    np.testing.assert_array_equal(field.query(points).distance, before)


def test_a_thread_count_that_is_not_one_is_refused(monkeypatch):
    for bad in ("0", "-2", "many"):
        monkeypatch.setenv("BADF_CPU_THREADS", bad)
        with pytest.raises(ValueError, match="BADF_CPU_THREADS"):
            _threads.cpu_threads()
    monkeypatch.setenv("BADF_CPU_THREADS", "5")
    assert _threads.cpu_threads() == 5
    assert _threads.chunks_for(100_000, 5) == 5 * _threads.CHUNKS_PER_THREAD
    assert _threads.chunks_for(100, 5) == 1 and _threads.chunks_for(100_000, 1) == 1


@pytest.mark.parametrize("sign", ["auto", "winding"])
def test_small_exact_batches_are_shared_out_and_answer_as_one_launch(monkeypatch, sign):
    """An exact batch is cut into chunks of MIN_EXACT_CHUNK points (each point walks the BVH), so a few hundred points
    already share the cores, with the answers of one launch bit for bit and the oracle's distances; an ADF batch of
    as many stays one launch (its points read the octree only)."""
    pools = []
    executor = _threads.shared_pool
    monkeypatch.setattr(_threads, "shared_pool", lambda threads: pools.append(threads) or executor(threads))
    vertices, faces = meshes.load("spot")
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    points = np.random.default_rng(8).uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), (600, 3))
    field = DistanceField(vertices, faces, depth=4, sign=sign, device="cpu")
    outputs = ("distance", "closest_point", "normal", "face")

    monkeypatch.setenv("BADF_CPU_THREADS", "1")
    whole = field.query(points, mode="exact", outputs=outputs)
    monkeypatch.setenv("BADF_CPU_THREADS", "3")
    pools.clear()  # the registration's launches
    field.query(points, outputs=outputs)
    assert not pools  # ADF: one launch
    shared = field.query(points, mode="exact", outputs=outputs)
    assert pools == [3]
    for name in outputs:
        np.testing.assert_array_equal(getattr(shared, name), getattr(whole, name))
    truth = oracle.signed_distance(points, vertices, faces)
    assert np.max(np.abs(shared.distance - truth)) <= tol.EXACT_DISTANCE * oracle.bbox_diagonal(vertices)


@wp.kernel(enable_backward=False)
def _record_items(offset: int, seen: wp.array(dtype=wp.int32), flag: wp.array(dtype=wp.int32)):
    item = offset + wp.tid()
    seen[item] = seen[item] + item + 1
    if item == 4000:
        flag[0] = 1


def test_offset_chunks_cover_every_item_once(monkeypatch):
    """With `offset_at`, each chunk is told where its items begin: every item is handled once, by its own index."""
    monkeypatch.setattr(_threads, "MIN_CHUNK", 64)
    monkeypatch.setenv("BADF_CPU_THREADS", "3")
    seen = wp.zeros(5000, dtype=wp.int32, device="cpu")
    flag = wp.zeros(1, dtype=wp.int32, device="cpu")
    _threads.launch_per_item(_record_items, 4500, inputs=[500], outputs=[seen, flag], sliced=(), offset_at=0,
                             device="cpu")
    expected = np.zeros(5000, np.int64)
    expected[500:] = np.arange(501, 5001)
    counts = seen.numpy()
    # the chunk that answers item 500 first, alone, to load the module, answers it again: 500 is counted twice
    expected[500] *= 2
    np.testing.assert_array_equal(counts, expected)
    assert flag.numpy()[0] == 1


def test_the_look_for_parts_running_into_each_other_decides_as_one_launch(monkeypatch):
    """`auto`'s look beside a closed mesh's faces, at registration and each frame, cut into chunks on threads:
    the same decisions as one launch (two spheres apart, running into each other, apart again)."""
    monkeypatch.setattr(_threads, "MIN_CHUNK", 64)
    vertices, faces = meshes.load("sphere")
    width = np.ptp(vertices[:, 0])
    f = np.concatenate([faces, faces + len(vertices)])

    def placed(gap):
        return np.concatenate([vertices, vertices + [gap * width, 0.0, 0.0]]).astype(np.float32)

    def decisions():
        field = DistanceField(placed(0.6), f, depth=4, device="cpu")  # into each other from the start
        seen = [(field.info()["sign"], field.info()["parts_overlap"])]
        field = DistanceField(placed(1.5), f, depth=4, device="cpu")
        seen.append((field.info()["sign"], field.info()["parts_overlap"]))
        for gap in (0.6, 1.5, 0.7):
            field.update(placed(gap))
            seen.append((field.info()["sign_this_frame"], field.info()["parts_overlap"]))
        return seen

    looks = []  # the looks' sizes in items, at registration and each frame
    launch = _sign.launch_per_item

    def counted(kernel, dim, *args, **kwargs):
        if kernel is _sign._solid_beside_face:
            looks.append(dim)
        launch(kernel, dim, *args, **kwargs)

    monkeypatch.setattr(_sign, "launch_per_item", counted)
    monkeypatch.setenv("BADF_CPU_THREADS", "1")
    one = decisions()
    monkeypatch.setenv("BADF_CPU_THREADS", "3")
    assert decisions() == one == [("winding", True), ("pseudonormal", False), ("winding", True),
                                  ("pseudonormal", False), ("winding", True)]
    assert len(looks) == 10 and all(_threads.chunks_for(dim, 3) > 1 for dim in looks)  # each cut into chunks
