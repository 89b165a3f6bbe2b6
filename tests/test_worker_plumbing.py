"""The worker's Zenoh plumbing, with a stand-in field so these tests need no engine.

Each test runs a worker in a thread of this process (its own router session on a free port) and talks to
it through the real client, or through a raw Zenoh session for requests the client would refuse to send.
"""

from __future__ import annotations

import dataclasses
import struct
import threading
import weakref

import numpy as np
import pytest
import zenoh
from conftest import free_endpoint, wait_until
from stand_in_field import StandInField, nearest_vertex

from badf.client import Client
from badf.client._client import _close_session as close_session
from badf.protocol import (
    CELL_LEAF,
    BadfError,
    ErrorReply,
    Frame,
    FrameAck,
    IndexRangeError,
    InfoRequest,
    InvalidOptionError,
    KeySpace,
    LimitExceededError,
    Limits,
    MalformedMessageError,
    MeshRequest,
    MetadataError,
    NonFiniteError,
    NotSupportedError,
    ObjectExistsError,
    ObjectNotFoundError,
    QueryReply,
    QueryRequest,
    RegisterRequest,
    RejectedInputError,
    StaleFrameError,
    TruncatedMessageError,
    VertexCountMismatchError,
    WorkerBusyError,
    WorkerTimeoutError,
    WorkerUnavailableError,
    WrongKindError,
    decode,
    encode,
    error_for_code,
    zenoh_config,
)
from badf.server import Worker, WorkerSettings, serve

KEYS = KeySpace("badf")
rng = np.random.default_rng(3)
VERTICES = rng.normal(size=(40, 3)).astype(np.float32)
FACES = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 39]], dtype=np.int32)
POINTS = rng.normal(size=(25, 3)).astype(np.float32)


class ThreadWorker:
    """A worker serving StandInFields from a thread of this process."""

    def __init__(
        self, endpoint: str, *, worker_id: str = "w1", mode: str = "router", connect: tuple[str, ...] = (), **settings
    ):
        listen = (endpoint,) if mode == "router" and endpoint else None
        self.settings = WorkerSettings(worker_id=worker_id, mode=mode, listen=listen, connect=connect, **settings)
        self.fields: list[StandInField] = []
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self._session: zenoh.Session | None = None
        self.running: Worker | None = None

    def _build(self, vertices, faces, options) -> StandInField:
        field = StandInField(vertices, faces)
        self.fields.append(field)
        return field

    def __enter__(self) -> ThreadWorker:
        self._session = zenoh.open(self.settings.zenoh_config())
        self._thread = threading.Thread(
            target=serve,
            args=(self._session, self.settings),
            kwargs={"stop": self._stop, "build_field": self._build, "device": "stand-in", "on_ready": self._on_ready},
        )
        self._thread.start()
        assert self._ready.wait(20), "worker did not start"
        return self

    def _on_ready(self, running: Worker) -> None:
        self.running = running
        self._ready.set()

    def stop(self) -> None:
        self._stop.set()

    def __exit__(self, *_exc) -> None:
        self._stop.set()
        for field in self.fields:
            field.gate.set()
        self._thread.join(timeout=30)
        self._session.close()


@pytest.fixture
def worker(endpoint: str):
    with ThreadWorker(endpoint, max_waiting_requests=4, limits=Limits(max_points=1000)) as running:
        yield running


@pytest.fixture
def client(worker: ThreadWorker, endpoint: str):
    with Client(endpoint, timeout=10) as connected:
        yield connected


@pytest.fixture
def raw(worker: ThreadWorker, endpoint: str):
    """A plain Zenoh session, for requests the client would refuse to build."""
    with zenoh.open(zenoh_config(mode="client", connect=[endpoint])) as session:
        yield session


def raw_error(session: zenoh.Session, key: str, payload: bytes | bytearray, timeout: float = 10) -> BadfError:
    replies = list(session.get(key, payload=payload, timeout=timeout))
    assert len(replies) == 1 and replies[0].err is not None, f"expected one error reply on {key}"
    error = decode(replies[0].err.payload.to_bytes(), ErrorReply)
    return error_for_code(error.code, error.message)


def expected_distance(points: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    return np.linalg.norm(points - vertices[nearest_vertex(points, vertices)], axis=1)


def test_register_update_query_info_delete(client: Client) -> None:
    obj = client.register("blob", VERTICES, FACES, depth=5, sign="none")
    assert (obj.name, obj.worker, obj.frame, obj.vertex_count, obj.face_count) == ("blob", "w1", 0, 40, 3)
    res = obj.query(POINTS, outputs=("distance", "closest_point"))
    assert res.frame == 0 and res.normal is None and res.face is None
    np.testing.assert_allclose(res.distance, expected_distance(POINTS, VERTICES), rtol=1e-6)
    moved = VERTICES + 0.5
    assert obj.update(moved) == 1
    res = obj.query(POINTS, mode="exact")
    assert res.frame == 1
    np.testing.assert_allclose(res.distance, expected_distance(POINTS, moved), rtol=1e-6)
    info = obj.info()
    assert (info.frame, info.frames_applied, info.queries_answered, info.points_answered) == (1, 1, 2, 50)
    assert info.options.depth == 5 and info.options.sign == "none" and info.field_info["sign"] == "none"
    assert [o.name for o in client.objects()] == ["blob"]
    [worker_info] = client.workers()
    assert (worker_info.worker, worker_info.object_count, worker_info.vertex_count) == ("w1", 1, 40)
    assert obj.delete() == 1
    with pytest.raises(ObjectNotFoundError):
        obj.query(POINTS)
    assert client.objects() == [] and client.workers()[0].object_count == 0
    np.testing.assert_array_equal(obj.vertices, moved)
    np.testing.assert_array_equal(obj.faces, FACES)


def test_stream_keeps_only_the_newest_pending_frame(worker: ThreadWorker, client: Client) -> None:
    obj = client.register("blob", VERTICES, FACES)
    field = worker.fields[0]
    field.gate.clear()
    obj.stream(VERTICES + 1)  # frame 1: the object's thread takes it and waits at the gate
    assert field.updates_started.acquire(timeout=20)
    for step in range(2, 11):  # frames 2..10 pile up; each replaces the one pending before it
        obj.stream(VERTICES + step)
    wait_until(lambda: obj.info().frames_dropped == 8, what="8 replaced frames")
    field.gate.set()
    wait_until(lambda: obj.info().frame == 10, what="the newest streamed frame to be applied")
    assert obj.update(VERTICES + 11) == 11
    info = obj.info()
    assert (info.frame, info.frames_applied, info.frames_dropped) == (11, 3, 8)
    np.testing.assert_allclose(obj.query(POINTS).distance, expected_distance(POINTS, VERTICES + 11), rtol=1e-6)


def test_engine_stats_catch_up_after_a_burst(worker: ThreadWorker, client: Client) -> None:
    obj = client.register("blob", VERTICES, FACES)
    for step in range(1, 6):
        obj.update(VERTICES + step)
    wait_until(lambda: obj.info().field_stats.get("frame") == 5, what="the engine's stats of the last frame")


def test_a_busy_object_stalls_no_other(worker: ThreadWorker, client: Client) -> None:
    slow = client.register("slow", VERTICES, FACES)
    fast = client.register("fast", VERTICES * 2, FACES)
    worker.fields[0].gate.clear()
    slow.stream(VERTICES + 1)
    assert worker.fields[0].updates_started.acquire(timeout=20)
    for step in range(1, 4):
        assert fast.update(VERTICES * 2 + step) == step
        assert fast.query(POINTS).frame == step
    assert slow.info().frame == 0  # answered from the snapshot while the object is busy
    assert len(client.objects()) == 2
    worker.fields[0].gate.set()
    assert slow.update(VERTICES + 2) == 2


def test_replacing_a_busy_object_holds_up_no_other_registration(worker: ThreadWorker, client: Client,
                                                                 endpoint: str) -> None:
    """A replace=True of an object with requests queued waited for them on the worker's one registrar thread,
    so every other registration waited too: 31 to 41 s behind 33 queued exact queries, where a registration
    with a 10 s timeout timed out and was applied all the same (twelfth outside check). A replacement also
    found a full queue BUSY."""
    busy = client.register("busy", VERTICES, FACES)
    worker.fields[0].gate.clear()
    busy.stream(VERTICES + 1)  # the object's thread takes it and waits at the gate
    assert worker.fields[0].updates_started.acquire(timeout=20)
    waiting = [threading.Thread(target=lambda: busy.query(POINTS)) for _ in range(4)]  # fills its queue (4)
    for thread in waiting:
        thread.start()
    wait_until(lambda: worker.running.objects()[0].waiting_count == 4, what="four queries queued")
    replaced: list = []
    with Client(endpoint, timeout=30) as other:
        replacing = threading.Thread(
            target=lambda: replaced.append(other.register("busy", VERTICES * 3, FACES, replace=True)))
        replacing.start()
        # built, and waiting behind the object's queue, off the registrar: another registration goes on
        wait_until(lambda: len(worker.fields) == 2, what="the replacement's field built")
        assert client.register("fresh", VERTICES * 2, FACES, timeout=5).name == "fresh"
        assert not replaced and replacing.is_alive()
        worker.fields[0].gate.set()
        replacing.join(timeout=30)
        for thread in waiting:
            thread.join(timeout=30)
        [info] = [remote.info() for remote in replaced]
    assert info.registration != busy._registration and info.frame == 0
    np.testing.assert_allclose(client.object("busy").query(POINTS).distance,
                               expected_distance(POINTS, VERTICES * 3), rtol=1e-6)


def test_a_full_queue_is_answered_busy(worker: ThreadWorker, client: Client, raw: zenoh.Session) -> None:
    obj = client.register("blob", VERTICES, FACES)
    worker.fields[0].gate.clear()
    obj.stream(VERTICES + 1)
    assert worker.fields[0].updates_started.acquire(timeout=20)
    payload = encode(QueryRequest("blob", POINTS))
    waiting = [raw.get(KEYS.object_query("blob"), payload=payload, timeout=20) for _ in range(4)]  # fills the queue
    errors_before = worker.running.totals().errors
    wait_until(lambda: _queue_is_full(raw, payload), what="a busy answer")
    assert worker.running.totals().errors > errors_before  # the stats line counts BUSY answers as errors
    worker.fields[0].gate.set()
    for handler in waiting:
        [reply] = list(handler)
        assert decode(reply.ok.payload.to_bytes(), QueryReply).frame == 1


def _queue_is_full(session: zenoh.Session, payload: bytearray) -> bool:
    [reply] = list(session.get(KEYS.object_query("blob"), payload=payload, timeout=20))
    if reply.err is None:
        return False
    error = decode(reply.err.payload.to_bytes(), ErrorReply)
    assert isinstance(error_for_code(error.code, error.message), WorkerBusyError)
    return True


def test_bad_requests_get_specific_errors_and_change_nothing(
    worker: ThreadWorker, client: Client, raw: zenoh.Session
) -> None:
    obj = client.register("blob", VERTICES, FACES)
    obj.update(VERTICES + 1)
    before = obj.query(POINTS, outputs=("distance", "normal"))
    query_key, frame_key = KEYS.object_query("blob"), KEYS.object_frame("blob")
    register_key = KEYS.worker_register("w1")
    good_query = bytes(encode(QueryRequest("blob", POINTS)))
    nan_points = bytearray(good_query)
    struct.pack_into("<f", nan_points, len(nan_points) - 4, float("nan"))
    bad_faces = bytearray(encode(RegisterRequest("other", VERTICES, FACES)))
    struct.pack_into("<i", bad_faces, len(bad_faces) - 4, 40)
    cases = [
        (query_key, b"", MalformedMessageError),
        (query_key, b"not a badf message at all", MalformedMessageError),
        (query_key, good_query[:-8], TruncatedMessageError),
        (query_key, encode(Frame("blob", 5, VERTICES)), WrongKindError),
        (query_key, nan_points, NonFiniteError),
        (query_key, encode(QueryRequest("blob", np.zeros((1001, 3)))), LimitExceededError),
        (query_key, encode(QueryRequest("other", POINTS)), MetadataError),
        (frame_key, encode(Frame("blob", 2, VERTICES[:10])), VertexCountMismatchError),
        (frame_key, encode(Frame("blob", 1, VERTICES)), StaleFrameError),
        (frame_key, encode(Frame("blob", 3, VERTICES * 1e7)), RejectedInputError),
        (register_key, bad_faces, IndexRangeError),
        (register_key, encode(RegisterRequest("blob", VERTICES, FACES)), ObjectExistsError),
        (KEYS.object_slice("blob"), encode(InfoRequest("blob")), WrongKindError),
        (KEYS.object_info("blob"), encode(InfoRequest("other")), MetadataError),
    ]
    for key, payload, expected in cases:
        error = raw_error(raw, key, payload)
        assert isinstance(error, expected), f"{key}: expected {expected.__name__}, got {type(error).__name__}: {error}"
        assert error.message
    with pytest.raises(NotSupportedError):
        obj.slice("z", 0.0, corners=True)
    info = obj.info()
    assert (info.frame, info.frames_applied, info.frames_rejected) == (1, 1, 2)
    assert info.last_error is not None
    after = obj.query(POINTS, outputs=("distance", "normal"))
    assert after.frame == before.frame
    np.testing.assert_array_equal(after.distance, before.distance)
    np.testing.assert_array_equal(after.normal, before.normal)
    assert [o.name for o in client.objects()] == ["blob"]


def test_slices_pass_through(worker: ThreadWorker, client: Client) -> None:
    obj = client.register("blob", VERTICES, FACES, depth=4)
    obj.update(VERTICES + 1)
    cut = obj.slice("y", 0.25, resolution=16, levels=(2, 9))
    assert (cut.frame, cut.axis, cut.position, cut.extent) == (1, "y", 0.25, ((-1.0, -1.0), (1.0, 1.0)))
    assert cut.grid.shape == (16, 16) and cut.grid.dtype == np.float32
    column_centre, row_centre = -1.0 + 5.5 / 8, -1.0 + 2.5 / 8  # sample (2, 5): u = x, v = z for a y-plane
    expected = expected_distance(np.array([[column_centre, 0.25, row_centre]], np.float32), VERTICES + 1)[0]
    assert cut.grid[2, 5] == pytest.approx(expected, rel=1e-5)
    np.testing.assert_array_equal(cut.cell_levels, [2, 3, 4])  # levels 0..4 (depth caps 9), lowest 2
    np.testing.assert_array_equal(cut.cell_flags, [0, 0, CELL_LEAF])
    np.testing.assert_allclose(cut.cell_boxes[:, 1, 0], [0.25, 0.125, 0.0625])
    bare = obj.slice("x", 0.0, resolution=4, cells=False)
    assert bare.cell_boxes is None and bare.cell_levels is None and bare.cell_flags is None
    by_index = obj.slice(np.int64(1), 0.25, resolution=16, levels=(2, 9))  # the engine's axis indices, as it takes them
    assert by_index.axis == "y"
    np.testing.assert_array_equal(by_index.grid, cut.grid)
    for bad in (3, -1, True):
        with pytest.raises(InvalidOptionError, match="axis"):
            obj.slice(bad, 0.0)


def test_mesh_follows_the_applied_frame(worker: ThreadWorker, client: Client, raw: zenoh.Session) -> None:
    obj = client.register("blob", VERTICES, FACES, frame=3)
    first = obj.mesh()
    assert first.frame == 3
    np.testing.assert_array_equal(first.vertices, VERTICES)
    np.testing.assert_array_equal(first.faces, FACES)
    worker.fields[0].gate.clear()
    obj.stream(VERTICES + 1)  # frame 4: taken by the object's thread, held at the gate
    assert worker.fields[0].updates_started.acquire(timeout=20)
    held = obj.mesh(faces=False)  # answered at once, with the frame applied before
    assert held.frame == 3 and held.faces is None
    np.testing.assert_array_equal(held.vertices, VERTICES)
    worker.fields[0].gate.set()
    wait_until(lambda: obj.mesh(faces=False).frame == 4, what="the mesh of frame 4")
    np.testing.assert_array_equal(obj.mesh(faces=False).vertices, VERTICES + 1)
    replaced = client.register("blob", VERTICES[:20], FACES[:2], replace=True, frame=0)
    after = replaced.mesh()
    assert after.frame == 0 and after.vertices.shape == (20, 3)
    np.testing.assert_array_equal(after.faces, FACES[:2])
    error = raw_error(raw, KEYS.object_mesh("blob"), encode(MeshRequest("other")))
    assert isinstance(error, MetadataError)
    error = raw_error(raw, KEYS.object_mesh("blob"), encode(InfoRequest("blob")))
    assert isinstance(error, WrongKindError)
    replaced.delete()
    with pytest.raises(ObjectNotFoundError):
        replaced.mesh()


def test_failed_registrations_count_as_errors(worker: ThreadWorker, client: Client, raw: zenoh.Session) -> None:
    """A registration the worker refuses (here a name it holds, sent past the client's own check) counts in
    the stats line's errors, as refused object requests do."""
    client.register("blob", VERTICES, FACES)
    before = worker.running.totals().errors
    [reply] = list(raw.get(KEYS.worker_register("w1"), payload=encode(RegisterRequest("blob", VERTICES, FACES)),
                           timeout=20))  # fmt: skip
    error = decode(reply.err.payload.to_bytes(), ErrorReply)
    assert isinstance(error_for_code(error.code, error.message), ObjectExistsError)
    assert worker.running.totals().errors == before + 1


def test_client_checks_before_sending(client: Client) -> None:
    obj = client.register("blob", VERTICES, FACES)
    with pytest.raises(VertexCountMismatchError):
        obj.update(VERTICES[:5])
    with pytest.raises(NonFiniteError):
        obj.stream(np.full_like(VERTICES, np.inf))
    with pytest.raises(IndexRangeError):
        client.register("bad", VERTICES, FACES + 40)
    with pytest.raises(ObjectExistsError):
        client.register("blob", VERTICES, FACES)
    assert obj.frame == 0 and obj.info().frames_applied == 0


def test_replace_swaps_the_field_in_place(worker: ThreadWorker, client: Client) -> None:
    old = client.register("blob", VERTICES, FACES)
    old.update(VERTICES + 1)
    new = client.register("blob", VERTICES[:20], FACES[:2], replace=True, frame=7)
    assert (new.vertex_count, new.frame) == (20, 7)
    res = new.query(POINTS)
    assert res.frame == 7
    np.testing.assert_allclose(res.distance, expected_distance(POINTS, VERTICES[:20]), rtol=1e-6)
    assert new.update(VERTICES[:20] - 1) == 8


class HeldBuildWorker(ThreadWorker):
    """A ThreadWorker whose next build waits for `release` once `hold` is set (it sets `building`)."""

    def __init__(self, endpoint: str, **kwargs) -> None:
        super().__init__(endpoint, **kwargs)
        self.hold, self.building, self.release = threading.Event(), threading.Event(), threading.Event()

    def _build(self, vertices, faces, options) -> StandInField:
        if self.hold.is_set():
            self.building.set()
            assert self.release.wait(30), "the test never released the build"
        return super()._build(vertices, faces, options)


def test_a_replace_racing_a_delete_leaves_the_new_object(endpoint: str) -> None:
    """Another client deleted the object while a replace built its field: the replace failed with
    ObjectNotFoundError and left no object. replace=True creates the object when it is gone."""
    with HeldBuildWorker(endpoint) as worker, Client(endpoint, timeout=20) as client:
        first = client.register("blob", VERTICES, FACES)
        first_registration = first.info().registration
        worker.hold.set()
        outcome: list[object] = []
        replacing = threading.Thread(target=lambda: outcome.append(
            client.register("blob", VERTICES[:20], FACES[:2], replace=True, frame=3)))
        replacing.start()
        try:
            assert worker.building.wait(20), "the replace never started building"
            assert first.delete() == 0  # answered by the object's own thread while the registration builds
        finally:
            worker.release.set()
            replacing.join(30)
        assert len(outcome) == 1, "the replace raised"
        info = client.object("blob").info()
        assert (info.vertex_count, info.frame) == (20, 3)
        assert info.registration != first_registration


def test_a_handle_on_a_replaced_registration_reads_and_deletes_nothing_of_the_new_one(
        worker: ThreadWorker, client: Client, endpoint: str) -> None:
    """A handle held across another client's replace=True answered its queries, info and mesh from the new
    mesh, and its delete() deleted the new object; a handle whose own delete() was followed by another
    registration of the name read that too (thirteenth outside check). Its requests now name its
    registration."""
    old = client.register("blob", VERTICES, FACES)
    with Client(endpoint, timeout=10) as other:
        new = other.register("blob", VERTICES * 3, FACES, replace=True)
        calls = {"query": lambda: old.query(POINTS), "slice": lambda: old.slice("z", 0.0, resolution=8),
                 "info": old.info, "mesh": old.mesh, "delete": old.delete}
        for what, call in calls.items():
            with pytest.raises(ObjectNotFoundError, match="since been deleted or replaced"):
                call()
                pytest.fail(f"{what} from the old handle was answered")
        np.testing.assert_allclose(new.query(POINTS).distance, expected_distance(POINTS, VERTICES * 3), rtol=1e-6)
        assert client.object("blob").info().registration == new.info().registration
        new.delete()
        again = other.register("blob", VERTICES * 5, FACES)
        with pytest.raises(ObjectNotFoundError, match="since been deleted or replaced"):
            new.query(POINTS)
        assert again.query(POINTS).frame == 0


def test_reregister_of_a_served_object_gives_advice_it_can_follow(worker: ThreadWorker, client: Client) -> None:
    """reregister() of an object still served said "pass replace=True", which reregister() does not take."""
    obj = client.register("blob", VERTICES, FACES)
    with pytest.raises(ObjectExistsError, match=r"still served.*Client.object\(name\)") as raised:
        obj.reregister()
    assert "pass replace=True" not in str(raised.value)
    assert obj.query(POINTS).frame == 0  # the handle still works


def test_frames_pending_when_a_replace_swaps_are_counted_dropped(
        worker: ThreadWorker, client: Client, endpoint: str) -> None:
    """A frame still pending for the old mesh when a replacement swapped the field in vanished from the
    counters: 199 of 200 streamed frames were counted applied or dropped (thirteenth outside check)."""
    obj = client.register("blob", VERTICES, FACES)
    field, served = worker.fields[0], worker.running.objects()[0]
    field.gate.clear()
    obj.stream(VERTICES + 1)  # the object's thread takes frame 1 alone and waits at the gate
    assert field.updates_started.acquire(timeout=20)
    replaced: list = []
    with Client(endpoint, timeout=30) as other:
        replacing = threading.Thread(
            target=lambda: replaced.append(other.register("blob", VERTICES * 3, FACES, replace=True)))
        replacing.start()
        wait_until(lambda: served.waiting_count == 1, what="the swap queued behind frame 1")
        obj.stream(VERTICES + 2)  # taken with the swap, so applied before it
        wait_until(lambda: served.pending_kinds == ("stream",), what="frame 2 pending")

        def third_frame_while_the_second_applies(vertices: np.ndarray) -> None:
            if vertices[0, 0] == VERTICES[0, 0] + 2:
                obj.stream(VERTICES + 3)  # pending when the swap runs: dropped with the old mesh
                wait_until(lambda: served.pending_kinds == ("stream",), what="frame 3 pending")

        field.on_update = third_frame_while_the_second_applies
        field.gate.set()
        replacing.join(timeout=30)
    assert len(replaced) == 1
    totals = served.counters()  # the name's, the replaced registration's included
    assert (totals.frames_applied, totals.frames_dropped, totals.frames_rejected) == (2, 1, 0)


def test_two_replacements_racing_a_delete_both_succeed(endpoint: str) -> None:
    """Two replace=True waiting behind a delete both found the object gone and fell back to creating it;
    the second was refused "pass replace=True to swap it", which it had (thirteenth outside check). It now
    swaps into the object the first created."""
    with ThreadWorker(endpoint) as worker, Client(endpoint, timeout=30) as client:
        first = client.register("blob", VERTICES, FACES)
        field, served = worker.fields[0], worker.running.objects()[0]
        field.gate.clear()
        first.stream(VERTICES + 1)
        assert field.updates_started.acquire(timeout=20)
        deleting = threading.Thread(target=first.delete)
        deleting.start()
        wait_until(lambda: served.waiting_count == 1, what="the delete queued")
        outcomes: list = []

        def replace(scale: int) -> None:
            with Client(endpoint, timeout=30) as other:
                try:
                    handle = other.register("blob", VERTICES * scale, FACES, replace=True)
                except BadfError as error:
                    outcomes.append(error)
                    return
                outcomes.append(scale)
                swapped.wait(30)  # keep the client open until both are in
                try:
                    handle.query(POINTS)
                    answered.append(scale)
                except ObjectNotFoundError:  # the other replacement came after this one
                    pass

        swapped, answered = threading.Event(), []

        replacing = [threading.Thread(target=replace, args=(scale,)) for scale in (3, 5)]
        for thread in replacing:
            thread.start()
        wait_until(lambda: served.waiting_count == 3, what="both swaps queued behind the delete")
        field.gate.set()
        wait_until(lambda: len(outcomes) == 2, what="both replacements answered")
        swapped.set()
        for thread in [deleting, *replacing]:
            thread.join(timeout=30)
        assert sorted(outcomes) == [3, 5], outcomes
        assert len(answered) == 1  # the later one's handle; the earlier one's registration was replaced
        np.testing.assert_allclose(client.object("blob").query(POINTS).distance,
                                   expected_distance(POINTS, VERTICES * answered[0]), rtol=1e-6)
        assert [obj.name for obj in worker.running.objects()] == ["blob"]


def test_shutdown_answers_waiting_requests(endpoint: str) -> None:
    with ThreadWorker(endpoint) as worker, Client(endpoint, timeout=20) as client:
        obj = client.register("blob", VERTICES, FACES)
        worker.fields[0].gate.clear()
        obj.stream(VERTICES + 1)
        assert worker.fields[0].updates_started.acquire(timeout=20)
        outcome: list[BaseException] = []

        def ask() -> None:
            try:
                obj.query(POINTS)
            except BadfError as error:
                outcome.append(error)

        asker = threading.Thread(target=ask)
        asker.start()
        wait_until(lambda: _waiting_count(worker) == 1, what="the query to wait")
        worker.stop()
        asker.join(timeout=30)
        assert len(outcome) == 1 and isinstance(outcome[0], WorkerUnavailableError), outcome
        worker.fields[0].gate.set()


def _waiting_count(worker: ThreadWorker) -> int:
    return sum(served.waiting_count for served in worker.running.objects())


def test_a_stuck_worker_gives_a_timeout(worker: ThreadWorker, client: Client) -> None:
    obj = client.register("blob", VERTICES, FACES)
    worker.fields[0].gate.clear()
    obj.stream(VERTICES + 1)
    assert worker.fields[0].updates_started.acquire(timeout=20)
    with pytest.raises(WorkerTimeoutError):
        obj.query(POINTS, timeout=0.5)
    worker.fields[0].gate.set()


def test_two_workers_share_a_namespace(endpoint: str) -> None:
    with (
        ThreadWorker(endpoint, worker_id="w1"),
        ThreadWorker("", worker_id="w2", mode="peer", connect=(endpoint,)) as second,
    ):
        with Client(endpoint, timeout=10) as client:
            wait_until(lambda: len(client.workers()) == 2, what="both workers")
            first = client.register("a", VERTICES, FACES)
            other = client.register("b", VERTICES[:30], FACES[:2])  # placed on the emptier worker
            assert {first.worker, other.worker} == {"w1", "w2"}
            assert [o.name for o in client.objects()] == ["a", "b"]
            assert other.update(VERTICES[:30] + 1) == 1
            assert len(second.fields) == 1


def test_a_second_worker_of_the_same_id_is_refused(endpoint: str) -> None:
    """Two workers started with one --worker-id both served: both built every object placed on that id,
    and workers() listed it twice. The second now refuses to start, before it declares anything."""
    with ThreadWorker(endpoint, worker_id="twin"), Client(endpoint, timeout=10) as client:
        settings = WorkerSettings(worker_id="twin", mode="client", connect=(endpoint,))
        with zenoh.open(settings.zenoh_config()) as session:
            second = Worker(session, settings, lambda *args: None, "stand-in")
            with pytest.raises(InvalidOptionError, match="a worker with id 'twin' already serves namespace 'badf'"):
                second.start()
            assert [info.worker for info in client.workers()] == ["twin"]
            other = Worker(session, dataclasses.replace(settings, worker_id="other"), lambda *args: None, "stand-in")
            other.start()  # another id is welcome
            wait_until(lambda: [info.worker for info in client.workers()] == ["other", "twin"], what="both ids")
            other.close()


def test_closing_a_client_never_raises_zenohs_close_timeout(caplog) -> None:
    """After streaming 12 MB frames to a worker stopped with SIGSTOP, Zenoh's session close timed out (10 s)
    and `with Client(...)` ended in a raw zenoh.ZError. The error is logged instead."""

    class StuckSession:
        closes = 0

        def is_closed(self) -> bool:
            return False

        def close(self) -> None:
            self.closes += 1
            raise zenoh.ZError("close operation timed out! at /root/.cargo/zenoh/src/api/session.rs:1")

    client = Client.__new__(Client)  # no session of its own: only close() is under test
    client._session, client._publishers, client._publishing = StuckSession(), {}, threading.Lock()
    client._liveliness = type("Subscriber", (), {"undeclare": lambda self: None})()
    client._finalizer = weakref.finalize(client, close_session, client._session, client._liveliness,
                                         client._publishers, client._publishing)  # as Client() makes it
    with caplog.at_level("WARNING", logger="badf.client"):
        client.close()
    assert client._session.closes == 1
    assert "close operation timed out!" in caplog.text and "cargo" not in caplog.text


def test_no_router_is_a_clear_error() -> None:
    with pytest.raises(WorkerUnavailableError, match="cannot reach"):
        Client(free_endpoint(), timeout=0.5)


@pytest.mark.parametrize("timeout", [0, -1, float("inf"), float("nan"), True, "5", 1e20, 1e300])
def test_timeouts_are_positive_finite_seconds(client: Client, timeout) -> None:
    """Client(timeout=inf) raised OverflowError from Zenoh, and a call's timeout of inf or nan a misleading
    'negative timeout'; so did 1e20, and Client(timeout=1e300) a Zenoh error with Rust source paths."""
    message = "timeout must be a positive number of seconds up to 1e[+]06"
    with pytest.raises(ValueError, match=message):
        Client(free_endpoint(), timeout=timeout)
    obj = client.register("blob", VERTICES, FACES)
    with pytest.raises(InvalidOptionError, match=message):  # a BadfError too, as other bad options are
        obj.query(POINTS, timeout=timeout)
    with pytest.raises(InvalidOptionError, match=message):
        client.workers(timeout=timeout)


def test_stats_line_counts_what_happened(worker: ThreadWorker, client: Client, raw: zenoh.Session) -> None:
    worker.running.stats_line()  # starts a fresh interval
    obj = client.register("blob", VERTICES, FACES)
    obj.update(VERTICES + 1)
    obj.query(POINTS)
    assert isinstance(
        raw_error(raw, KEYS.object_frame("blob"), encode(Frame("blob", 9, VERTICES[:3]))), VertexCountMismatchError
    )
    line = worker.running.stats_line()
    assert (
        "1 objects" in line and "frames 1 applied" in line and "1 rejected" in line and "queries 1 (25 points)" in line
    )


def test_serve_flags_become_settings(tmp_path) -> None:
    import argparse

    from badf.server import _cli

    parser = argparse.ArgumentParser()
    _cli.add_arguments(parser)
    settings = _cli.settings_from(parser.parse_args([]))
    assert settings.mode == "router" and settings.listen is None and settings.namespace == "badf"
    assert settings.zenoh_config().get_json("listen/endpoints") == '["tcp/127.0.0.1:7447"]'
    assert settings.zenoh_config().get_json("transport/shared_memory/enabled") == "false"
    args = parser.parse_args(
        [
            "--listen",
            "tcp/127.0.0.1:9000",
            "--connect",
            "tcp/10.0.0.1:7447",
            "--namespace",
            "lab/a",
            "--worker-id",
            "gpu-3",
            "--device",
            "cuda:1",
        ]
    )
    settings = _cli.settings_from(args)
    assert (settings.listen, settings.connect, settings.namespace, settings.worker_id, settings.device) == (
        ("tcp/127.0.0.1:9000",),
        ("tcp/10.0.0.1:7447",),
        "lab/a",
        "gpu-3",
        "cuda:1",
    )
    assert _cli.run(parser.parse_args(["--worker-id", "no/slashes"])) == 2


def test_config_file_is_the_base(tmp_path, endpoint: str) -> None:
    config = tmp_path / "zenoh.json5"
    config.write_text('{ listen: { endpoints: ["%s"] }, scouting: { multicast: { enabled: false } } }' % endpoint)
    with ThreadWorker("", config_file=str(config)):  # no --listen: the file's endpoint is used
        with Client(endpoint, timeout=10) as client:
            assert client.workers()[0].worker == "w1"


@pytest.mark.parametrize("update_arrives_first", [True, False], ids=["update-first", "stream-first"])
def test_the_higher_numbered_of_a_pending_stream_and_update_wins(
    worker: ThreadWorker, client: Client, raw: zenoh.Session, update_arrives_first: bool
) -> None:
    """Zenoh may deliver an update (a query) before frames its client streamed earlier (puts). Whichever
    arrives first, the update (frame 3) is applied and acknowledged and the streamed frame 2 is dropped as
    stale: a late stream never displaces a newer update, and an older pending stream is not applied."""
    obj = client.register("blob", VERTICES, FACES)
    served, field = worker.running.objects()[0], worker.fields[0]
    field.gate.clear()
    obj.stream(VERTICES + 1)  # frame 1: the object's thread takes it and waits at the gate
    assert field.updates_started.acquire(timeout=20)
    arrivals = ["update", "stream"] if update_arrives_first else ["stream", "update"]
    update = None
    for kind in arrivals:
        if kind == "update":
            update = raw.get(KEYS.object_frame("blob"), payload=encode(Frame("blob", 3, VERTICES + 3)), timeout=20)
        else:
            raw.put(KEYS.object_frame("blob"), encode(Frame("blob", 2, VERTICES + 2)))
        wait_until(lambda: kind in served.pending_kinds, what=f"the {kind} to be pending")
    field.gate.set()
    [reply] = list(update)
    assert reply.err is None, decode(reply.err.payload.to_bytes(), ErrorReply).message
    assert decode(reply.ok.payload.to_bytes(), FrameAck).frame == 3
    wait_until(lambda: obj.info().frames_dropped == 1, what="frame 2 to be dropped")
    info = obj.info()
    assert (info.frame, info.frames_applied, info.frames_dropped, info.frames_rejected) == (3, 2, 1, 0)
    np.testing.assert_allclose(obj.query(POINTS).distance, expected_distance(POINTS, VERTICES + 3), rtol=1e-6)
