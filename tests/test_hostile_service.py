"""Hostile input at a real worker (a spawned process, CPU back-end): broken messages on every key it
answers, and meshes that are valid but nasty (the engine's stability cases of bench/_cases.py that are
meshes, and four only a service meets), each then sent five nasty frames (collapsed, scaled, moved away).

Held for every broken request: exactly one reply; when the request does not decode, the error code the
protocol's own decoder gives for those bytes (so the worker reports the same specific error as `decode`);
when it does, an answer or an error about the object's state, never INTERNAL. Streamed (put) garbage gets
no reply and must change nothing it should not. Every nasty mesh is either registered or refused with
RejectedInputError, and every later request on it is answered without INTERNAL. Afterwards the worker
still serves a plain object exactly as before.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import zenoh
from conftest import free_endpoint
from hostile_messages import MESSAGES, MUTATIONS, Parts, object_options
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from badf.bench import _cases as cases
from badf.bench.soak import PROBE, cube, expected_probe_distance, frame_vertices
from badf.client import Client
from badf.protocol import (
    DEFAULT_LIMITS,
    BadfError,
    DeleteRequest,
    ErrorCode,
    ErrorReply,
    Frame,
    InfoRequest,
    MeshRequest,
    InternalWorkerError,
    KeySpace,
    MessageError,
    QueryRequest,
    RegisterRequest,
    RejectedInputError,
    SliceRequest,
    decode,
    encode,
    zenoh_config,
)
from badf.server import WorkerSettings, worker_process

KEYS = KeySpace()
WORKER = "hardy"
TARGET = "target"
BASE, FACES = cube(8)
# What a request that decodes may still be answered with: it does not fit the object's state.
STATE_ERRORS = {
    ErrorCode.BAD_METADATA,  # a name other than the key's object
    ErrorCode.ALREADY_EXISTS,
    ErrorCode.STALE_FRAME,
    ErrorCode.VERTEX_COUNT_MISMATCH,
    ErrorCode.REJECTED_INPUT,
    ErrorCode.NOT_SUPPORTED,
    ErrorCode.BUSY,
}


@pytest.fixture(scope="module")
def endpoint() -> str:
    return free_endpoint()


@pytest.fixture(scope="module")
def worker(endpoint: str):
    settings = WorkerSettings(worker_id=WORKER, listen=(endpoint,), device="cpu", stats_interval_s=10.0)
    with worker_process(settings, start_timeout_s=300.0) as process:
        yield process


@pytest.fixture(scope="module")
def client(worker, endpoint: str):
    with Client(endpoint, timeout=120) as connected:
        yield connected


@pytest.fixture(scope="module")
def target(client: Client):
    obj = client.register(TARGET, BASE, FACES, depth=4)
    yield obj
    for info in client.objects():
        client.object(info.name).delete()


@pytest.fixture(scope="module")
def raw(worker, endpoint: str):
    with zenoh.open(zenoh_config(mode="client", connect=[endpoint])) as session:
        yield session


# --- broken messages on every key ------------------------------------------------------------------


@st.composite
def small_registrations(draw) -> RegisterRequest:
    """Registrations the CPU back-end builds quickly: depth 1 to 5 (the protocol itself refuses those outside
    the engine's 1..10), and some under the target's own name (ALREADY_EXISTS)."""
    request = draw(MESSAGES[RegisterRequest])
    depth = draw(st.sampled_from([1, 2, 3, 4, 5]))
    name = draw(st.sampled_from([request.name, TARGET]))
    return dataclasses.replace(
        request, name=name, replace=False, options=dataclasses.replace(draw(object_options()), depth=depth)
    )


@st.composite
def addressed(draw, cls: type):
    """A message of `cls` for the target: its own name, and for frames now and then the right vertex count."""
    message = draw(MESSAGES[cls])
    if cls is Frame and draw(st.booleans()):
        number = draw(st.integers(1, 2**40))
        return Frame(TARGET, number, frame_vertices(BASE, number))
    if cls is InfoRequest:
        return InfoRequest(draw(st.sampled_from([None, TARGET])))
    return dataclasses.replace(message, name=TARGET)


KEY_CASES = {
    "register": (KEYS.worker_register(WORKER), RegisterRequest, small_registrations()),
    "worker info": (KEYS.worker_info(WORKER), InfoRequest, addressed(InfoRequest)),
    "frame (update)": (KEYS.object_frame(TARGET), Frame, addressed(Frame)),
    "query": (KEYS.object_query(TARGET), QueryRequest, addressed(QueryRequest)),
    "slice": (KEYS.object_slice(TARGET), SliceRequest, addressed(SliceRequest)),
    "mesh": (KEYS.object_mesh(TARGET), MeshRequest, addressed(MeshRequest)),
    "info": (KEYS.object_info(TARGET), InfoRequest, addressed(InfoRequest)),
    "delete": (KEYS.object_delete(TARGET), DeleteRequest, addressed(DeleteRequest)),
}


@st.composite
def broken_requests(draw, cls: type, valid: st.SearchStrategy) -> bytes:
    """A valid request, broken by one of the twelve mutations, or a valid message of another type."""
    how = draw(st.sampled_from(sorted(MUTATIONS) + ["another type"]))
    if how == "another type":
        other = draw(st.sampled_from([other for other in MESSAGES if other is not cls]))
        return bytes(encode(draw(MESSAGES[other])))
    data = bytes(encode(draw(valid)))
    broken, _ = MUTATIONS[how](draw(st.data()), data, Parts.of(data))
    return broken


def expected_decode_error(data: bytes, cls: type) -> MessageError | None:
    try:
        decode(data, cls, limits=DEFAULT_LIMITS)
    except MessageError as error:
        return error
    return None


@pytest.mark.parametrize("case", sorted(KEY_CASES))
def test_broken_requests_get_the_decoders_own_error(case: str, target, raw: zenoh.Session, client: Client) -> None:
    key, cls, valid = KEY_CASES[case]
    sent: list[int] = []

    @settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
    @given(broken_requests(cls, valid))
    def send(data: bytes) -> None:
        assume(data)  # an empty payload is MALFORMED at the worker, TRUNCATED for decode: tested elsewhere
        expected = expected_decode_error(data, cls)
        if expected is None:  # it decodes: keep the target (the other tests use it)
            assume(cls is not DeleteRequest)
            assume(not (cls is RegisterRequest and decode(data, cls).replace))
        replies = list(raw.get(key, payload=data, timeout=120))
        sent.append(len(data))
        assert len(replies) == 1, f"{len(replies)} replies on {key}"
        [reply] = replies
        if reply.ok is not None:
            assert expected is None, f"answered although decode says {expected!r}"
            return
        error = decode(reply.err.payload.to_bytes(), ErrorReply)
        if expected is not None:
            assert error.code == expected.code, f"worker said {error.code} {error.message!r}; decode: {expected!r}"
        else:
            assert error.code in STATE_ERRORS, f"a request that decodes was answered {error.code}: {error.message}"

    send()
    assert len(sent) >= 40, f"only {len(sent)} broken requests were sent"
    assert target.info().name == TARGET  # still served
    restore(raw)
    for info in client.objects():  # registrations that went through
        if info.name != TARGET:
            client.object(info.name).delete()


_restored = iter(range(2**60, 2**61))


def restore(raw: zenoh.Session) -> None:
    """Give the target a frame numbered above anything the broken requests may have carried, whose
    geometry matches its number (a broken request may have paired another number with its vertices)."""
    number = next(_restored)
    payload = encode(Frame(TARGET, number, frame_vertices(BASE, number)))
    [reply] = list(raw.get(KEYS.object_frame(TARGET), payload=payload, timeout=120))
    assert reply.ok is not None, decode(reply.err.payload.to_bytes(), ErrorReply).message


def test_broken_streamed_frames_change_nothing_they_should_not(target, raw: zenoh.Session, client: Client) -> None:
    """Garbage put on the frame key (no reply comes to a stream): afterwards the target answers for a whole
    frame, and a blocking update applies as usual."""

    @settings(max_examples=80, deadline=None, suppress_health_check=list(HealthCheck))
    @given(broken_requests(Frame, addressed(Frame)))
    def stream(data: bytes) -> None:
        assume(data)
        raw.put(KEYS.object_frame(TARGET), data)
        sent.append(len(data))

    sent: list[int] = []
    stream()
    assert len(sent) >= 60, f"only {len(sent)} broken frames were streamed"
    restore(raw)
    reply = target.query(PROBE, mode="exact")
    assert abs(float(reply.distance[0]) - expected_probe_distance(reply.frame)) <= 1e-4
    assert target.info().frame == reply.frame >= 2**60


# --- valid but nasty meshes --------------------------------------------------------------------------


def every_face_on_one_vertex():
    return np.zeros((3, 3)), np.array([[0, 0, 0], [1, 1, 1], [0, 1, 2]])


def every_vertex_at_one_point():
    return np.ones((12, 3)), cases.icosphere(1)[1] % 12


def with_far_unreferenced_vertices():
    vertices, faces = cases.icosphere()
    return np.concatenate([vertices, [[1e6, 0, 0], [-1e6, 0, 0]]]), faces


# The engine's stability cases (bench/_cases.py) that are meshes, and four more only a service meets.
NASTY_MESHES = {
    "zero-area and collinear triangles": cases.zero_area_and_collinear,
    "repeated vertices (triangle soup)": cases.triangle_soup,
    "slivers of aspect ratio 1e6": cases.sliver_tetrahedron,
    "a single triangle": cases.single_triangle,
    "flat (coplanar) open mesh": cases.flat_sheet,
    "thin plate 1e-4 of its size thick": cases.thin_plate,
    "inverted winding": cases.inverted_sphere,
    "duplicate faces of opposite orientation": cases.sphere_with_opposite_duplicates,
    "non-manifold edges (two cubes sharing an edge)": cases.boxes_sharing_an_edge,
    "offset by 1e5": cases.scaled_sphere(1.0, 1e5),
    "scaled by 1e-5": cases.scaled_sphere(1e-5, 0.0),
    "scaled by 1e5": cases.scaled_sphere(1e5, 0.0),
    "scaled by 1e15": cases.scaled_sphere(1e15, 0.0),
    "every face on one vertex": every_face_on_one_vertex,
    "every vertex at one point": every_vertex_at_one_point,
    "unreferenced vertices 1e6 away": with_far_unreferenced_vertices,
}


def nasty_frames(vertices: np.ndarray) -> dict[str, np.ndarray]:
    centre = (vertices.min(axis=0) + vertices.max(axis=0)) / 2
    flat = vertices.copy()
    flat[:, 2] = centre[2]
    return {
        "collapsed onto a plane": flat,
        "collapsed onto a point": np.repeat(centre[None], len(vertices), axis=0),
        "scaled by 1e3": centre + (vertices - centre) * 1e3,
        "moved 1e6 away": vertices + 1e6,
        "jittered": vertices + np.random.default_rng(0).normal(scale=0.1 * np.ptp(vertices), size=vertices.shape),
    }


def _answered_or_specific(call, what: str, failures: list[str]):
    """Run a request; a specific BadfError is an answer too. INTERNAL (a bug on the worker) is collected."""
    try:
        return call()
    except InternalWorkerError as error:
        failures.append(f"{what}: INTERNAL: {error}")
    except BadfError as error:
        return error
    return None


@pytest.mark.parametrize("mesh", sorted(NASTY_MESHES))
def test_nasty_meshes_never_take_the_worker_down(mesh: str, client: Client, target, worker) -> None:
    vertices, faces = NASTY_MESHES[mesh]()
    vertices, faces = np.asarray(vertices, np.float32), np.asarray(faces, np.int32)
    name = "nasty"
    failures: list[str] = []
    try:
        obj = client.register(name, vertices, faces, depth=5)
    except RejectedInputError as refused:
        assert refused.message, "a refusal says why"
        obj = None
    if obj is not None:
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        points = np.random.default_rng(1).uniform(lo - (hi - lo) - 1, hi + (hi - lo) + 1, size=(500, 3))
        points = np.concatenate([points, vertices[:50], [[0, 0, 0], [1e9, -1e9, 1e9]]]).astype(np.float32)
        for label, frame in [("initial", None), *nasty_frames(vertices.astype(np.float64)).items()]:
            if frame is not None:
                _answered_or_specific(lambda: obj.update(frame.astype(np.float32)), f"{mesh}, update {label}", failures)
            for mode in ("exact", "adf"):
                reply = _answered_or_specific(
                    lambda: obj.query(points, mode=mode, outputs=("distance", "closest_point", "normal", "face")),
                    f"{mesh}, {label}, {mode} query", failures,
                )  # fmt: skip
                if reply is not None and not isinstance(reply, BadfError):
                    assert np.isfinite(reply.distance).all(), f"{mesh}, {label}: non-finite {mode} distances"
            _answered_or_specific(lambda: obj.slice("z", float(points[0, 2]), resolution=32), f"{mesh} slice", failures)
        obj.stream(np.full_like(vertices, 3.0))  # all in one point, unacknowledged
        info = obj.info()
        assert info.name == name
        obj.delete()
    assert not failures, failures
    assert worker.is_alive()
    reply = target.query(PROBE, mode="exact")  # the plain object answers as before
    assert abs(float(reply.distance[0]) - expected_probe_distance(reply.frame)) <= 1e-4
