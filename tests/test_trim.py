"""Trimming an idle object: `DistanceField.trim` gives back what only the next frame, query or slice uses, and
changes no answer; a worker trims an object that has had no frame for `trim_after_s`, once until its next frame."""

from __future__ import annotations

import gc
import threading
import time
import weakref

import numpy as np
import pytest

import meshes
import oracle
import tolerances as tol
from badf.client import Client
from badf.protocol import DEFAULT_LIMITS, KeySpace, ObjectOptions, RejectedInputError, WorkerUnavailableError
from badf.server._objects import ServedObject, _Request
from badf.server.adf import DistanceField
from conftest import wait_until
from stand_in_field import StandInField
from test_worker_plumbing import FACES, POINTS, VERTICES, ThreadWorker

ALL_OUTPUTS = ("distance", "closest_point", "normal", "face")
KEPT_ROLES = ("field", "mesh")  # what a query reads: a trim leaves it alone (and the BVH's shape, not its boxes)
FREED_ROLES = ("coherence", "queries", "rebuild")  # what only a later frame or query uses: a trim frees all of it
PLACEHOLDERS = 64  # bytes: the one-element arrays a kernel is handed where it reads none (last frame's count, ...)


def _assert_same(got, expected) -> None:
    for name in ALL_OUTPUTS:
        np.testing.assert_array_equal(getattr(got, name), getattr(expected, name), err_msg=name)


def test_a_trim_gives_back_what_only_later_frames_use_and_changes_no_answer(device: str) -> None:
    """After a trim the object holds its field, mesh and BVH's shape, and nothing of the frame's scratch, the BVH's
    boxes, last frame's faces or the query buffers; it answers as before, bit for bit (its first query refits the
    boxes), and its next frames are those of a twin never trimmed (the first of them searched from spatial seeds, as
    a first frame is; on CUDA run eagerly and captured again)."""
    vertices, faces = meshes.load("spot")
    rng = np.random.default_rng(17)
    field = DistanceField(vertices, faces, depth=5, device=device)
    twin = DistanceField(vertices, faces, depth=5, device=device)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    points = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), (20_000, 3))
    for k in range(1, 4):  # planned frames, then a graph on CUDA
        for field_of in (field, twin):
            field_of.update(vertices * (1.0 + 0.002 * k))
    before = {mode: field.query(points, mode=mode, outputs=ALL_OUTPUTS) for mode in ("adf", "exact")}
    field.slice("z", float(vertices[:, 2].mean()), resolution=64, max_level=5)
    held, bytes_held = field.stats()["memory_bytes"], field.stats()["device_bytes"]
    assert all(held[role] > 0 for role in ("coherence", "queries"))

    freed = field.trim()
    trimmed, bytes_trimmed = field.stats()["memory_bytes"], field.stats()["device_bytes"]
    assert freed == bytes_held - bytes_trimmed > 0 and field.stats()["trims"] == 1
    assert all(trimmed[role] == held[role] for role in KEPT_ROLES)
    assert all(trimmed[role] <= PLACEHOLDERS for role in FREED_ROLES)
    assert 0 < trimmed["scratch"] < held["scratch"] and 0 < trimmed["bvh"] < held["bvh"]
    assert field.trim() == 0 and field.stats()["trims"] == 1  # nothing left to give: not counted

    for mode, expected in before.items():  # the first query refits the BVH's boxes, triangles and moments again
        _assert_same(field.query(points, mode=mode, outputs=ALL_OUTPUTS), expected)
    assert field.stats()["memory_bytes"]["bvh"] == held["bvh"]
    frame_vertices = vertices * 1.006
    truth = oracle.signed_distance(points, frame_vertices, faces)
    diagonal = oracle.bbox_diagonal(frame_vertices)
    np.testing.assert_allclose(before["exact"].distance, truth, rtol=0, atol=tol.EXACT_DISTANCE * diagonal)

    assert field.trim() > 0  # again: the frame below refits the BVH itself, with no query before it
    captures = field.stats()["graph_captures"]
    for k in range(4):
        bent = frame_vertices + 0.01 * np.sin(3.0 * frame_vertices[:, [1, 2, 0]]) * (k + 1)
        for field_of in (field, twin):
            field_of.update(bent)
        assert field.stats()["counts"]["coherent_frame"] == (k > 0)
        for got, expected in zip(field.corner_samples(), twin.corner_samples()):
            np.testing.assert_array_equal(got, expected)
        for mode in ("adf", "exact"):
            _assert_same(field.query(points, mode=mode, outputs=ALL_OUTPUTS),
                         twin.query(points, mode=mode, outputs=ALL_OUTPUTS))
    if device.startswith("cuda"):
        assert field.stats()["graph_captures"] > captures
    positions, values, _ = field.corner_samples()
    assert np.abs(values - oracle.signed_distance(positions, bent, faces)).max() <= (
        tol.EXACT_DISTANCE * oracle.bbox_diagonal(bent))
    assert field.stats()["memory_bytes"]["coherence"] == twin.stats()["memory_bytes"]["coherence"] > 0


def test_the_views_kept_for_queries_let_go_of_what_a_trim_or_a_frame_replaced(device: str) -> None:
    """Queries reuse their kernels' views while the arrays in them stay the same (`KeptViews`); a kept view holds its
    arrays, so a trim must let go of the BVH's boxes and triangles for their memory to be freed, and a frame whose
    octree outgrew its arrays must let go of the old ones. Answers after both are those of a twin whose views were
    made after them, bit for bit."""
    vertices, faces = meshes.load("spot")
    points = np.random.default_rng(5).uniform(vertices.min(axis=0), vertices.max(axis=0), (200, 3))
    field, twin = (DistanceField(vertices, faces, depth=4, device=device) for _ in range(2))
    field.query(points, outputs=ALL_OUTPUTS)
    boxes = weakref.ref(field._bvh.wide.planes)
    field.trim()
    gc.collect()
    assert boxes() is None
    _assert_same(field.query(points, outputs=ALL_OUTPUTS), twin.query(points, outputs=ALL_OUTPUTS))
    # a crumpled frame has many more surface cells than the plan holds: the octree's arrays grow
    nodes = weakref.ref(field._octree.first_child)
    crumpled = vertices + 0.05 * np.sin(40.0 * vertices[:, [1, 2, 0]])
    field.update(crumpled)
    gc.collect()
    assert nodes() is None
    twin.trim()
    twin.update(crumpled)
    for mode in ("adf", "exact"):
        _assert_same(field.query(points, mode=mode, outputs=ALL_OUTPUTS),
                     twin.query(points, mode=mode, outputs=ALL_OUTPUTS))


def test_a_rigid_body_trimmed_mid_run_keeps_its_pose(device: str) -> None:
    """A trim between rigid frames frees the same and keeps the pose: queries still answer for where the mesh is."""
    vertices, faces = meshes.load("spot")
    field = DistanceField(vertices, faces, depth=4, device=device)
    twin = DistanceField(vertices, faces, depth=4, device=device)
    shifted = vertices + np.array([0.3, -0.1, 0.2], dtype=vertices.dtype)
    for field_of in (field, twin):
        field_of.update(shifted)
    assert field.stats()["rigid_frames"] == 1
    assert field.trim() > 0
    points = np.random.default_rng(5).uniform(shifted.min(axis=0), shifted.max(axis=0), (3_000, 3))
    for mode in ("adf", "exact"):
        _assert_same(field.query(points, mode=mode, outputs=ALL_OUTPUTS), twin.query(points, mode=mode, outputs=ALL_OUTPUTS))
    truth = oracle.signed_distance(points, shifted, faces)
    np.testing.assert_allclose(field.query(points, mode="exact").distance, truth, rtol=0,
                               atol=tol.EXACT_DISTANCE * oracle.bbox_diagonal(shifted))


def test_a_device_that_cannot_hold_the_bvh_again_refuses_the_query_and_leaves_the_object_whole(monkeypatch) -> None:
    """The BVH's geometry comes back in three allocations; where the last is refused, the query raises
    DeviceMemoryError, none of the three is kept, and once the device has room the object answers as before."""
    from badf.server.adf._buffers import DeviceBuffers, DeviceMemoryError

    vertices, faces = meshes.load("spot")
    field = DistanceField(vertices, faces, depth=4, device="cpu")
    points = np.random.default_rng(3).uniform(vertices.min(axis=0), vertices.max(axis=0), (2_000, 3))
    expected = field.query(points, mode="exact", outputs=ALL_OUTPUTS)
    field.trim()
    trimmed = field.stats()["device_bytes"]
    allocate = DeviceBuffers._allocate

    def refuse_the_boxes(self, name, count, dtype, *, zeroed):
        if name == "bvh.wide.planes":
            raise DeviceMemoryError(f"{name}: refused by the test")
        return allocate(self, name, count, dtype, zeroed=zeroed)

    monkeypatch.setattr(DeviceBuffers, "_allocate", refuse_the_boxes)
    with pytest.raises(DeviceMemoryError):
        field.query(points, mode="exact")
    assert field.stats()["device_bytes"] == trimmed
    monkeypatch.setattr(DeviceBuffers, "_allocate", allocate)
    _assert_same(field.query(points, mode="exact", outputs=ALL_OUTPUTS), expected)


def test_a_worker_trims_an_object_without_frames_once_until_its_next_frame(endpoint: str) -> None:
    """With trim_after_s set, an object that gets no frame for that long is trimmed once; queries do not undo that
    (nor trim it again), nor does a frame the engine refuses, and a frame it takes arms it again."""
    trim_after = 0.2
    with ThreadWorker(endpoint, trim_after_s=trim_after) as worker, Client(endpoint, timeout=10) as client:
        obj = client.register("still", VERTICES, FACES)
        field = worker.fields[0]
        wait_until(lambda: field.trims == 1, timeout=10, what="the first trim")
        with pytest.raises(RejectedInputError):  # the stand-in refuses vertices beyond 1e6, as the engine bad input
            obj.update(VERTICES * 1e7)
        # queries for five times the idle time: each is a round trip through the object's thread, none a frame
        until = time.monotonic() + 5 * trim_after
        while time.monotonic() < until:
            obj.query(POINTS)
            assert field.trims == 1
        obj.update(VERTICES * 1.01)
        wait_until(lambda: field.trims == 2, timeout=10, what="the trim after the next frame")
        wait_until(lambda: obj.info().field_stats.get("trims") == 2, timeout=10, what="the info's stats")


def test_an_object_whose_requests_never_let_up_is_trimmed_all_the_same() -> None:
    """Requests that come more often than the idle time (a static obstacle queried every step by several clients)
    keep the object's thread from ever waiting that long; the trim comes between them. Here each request queues the
    next before it ends, so the thread never finds its queue empty."""
    field = StandInField(VERTICES, FACES)
    served = ServedObject("busy", field, ObjectOptions(), vertices=VERTICES, faces=FACES, frame=0, registration=1,
                          worker_id="w1", keys=KeySpace("badf"), limits=DEFAULT_LIMITS, max_waiting_requests=4,
                          on_deleted=lambda _obj: None, trim_after_s=0.2)
    runs, stop = [], threading.Event()

    def request() -> _Request:
        def run() -> None:
            runs.append(field.query(POINTS).distance)
            if not stop.is_set():
                served._enqueue(request())
        return _Request(run, lambda _error: None)

    served._thread.start()  # the object's thread alone: no Zenoh keys are declared for this test
    try:
        served._enqueue(request())
        wait_until(lambda: field.trims == 1, timeout=10, what="a trim between requests that never let up")
        assert len(runs) > 1
    finally:
        stop.set()
        served.close(WorkerUnavailableError("the test is over"))


def test_a_worker_with_trims_off_never_trims(endpoint: str) -> None:
    """trim_after_s=0 turns trims off; the object's thread still wakes for its stats snapshot."""
    with ThreadWorker(endpoint, trim_after_s=0.0) as worker, Client(endpoint, timeout=10) as client:
        obj = client.register("kept", VERTICES, FACES)
        field = worker.fields[0]
        until = time.monotonic() + 1.0
        while time.monotonic() < until:
            obj.query(POINTS)
        assert field.trims == 0
