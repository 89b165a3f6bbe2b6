"""Faults against real worker processes (spawned, CPU back-end, free ports of 127.0.0.1): a client killed
in the middle of sending, a worker killed and started again, a viewer that stops reading, frames sent
faster than they can be applied, and connections that speak garbage.

The objects are the soak benchmark's cube, moved by offset(F) along x in frame F: one exact query at the
probe tells which frame an object holds and that the frame is whole (1.5 - offset(F)). Throughout, no
acknowledged update may be lost, and nothing may hang: every wait has a deadline, stated as a liveness
bound far above what the step takes.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import socket
import sys
import threading
import time
import traceback
from contextlib import ExitStack

import numpy as np
import pytest
import zenoh
from conftest import free_endpoint, wait_until
from fault_processes import ask_for_slices, big_cube, send_big_frames_until_killed

from badf.bench.soak import PROBE, cube, expected_probe_distance, frame_vertices
from badf.client import Client, RemoteObject
from badf.protocol import (
    KeySpace,
    ObjectInfo,
    ObjectOptions,
    ObjectUnavailableError,
    WorkerUnavailableError,
    zenoh_config,
)
from badf.server import WorkerSettings, end_process, worker_process

SPAWN = multiprocessing.get_context("spawn")
BASE, FACES = cube(8)
TOLERANCE = 1e-4  # float32 rounding of the exact distance; frame offsets are 0.01 apart


def assert_holds_frame(obj: RemoteObject, frame: int, geometry: int | None = None) -> None:
    """The object answers for `frame`, with the (whole) geometry of frame_vertices(BASE, geometry), by default
    that frame's own."""
    geometry = frame if geometry is None else geometry
    reply = obj.query(PROBE, mode="exact")
    assert reply.frame == frame
    assert abs(float(reply.distance[0]) - expected_probe_distance(geometry)) <= TOLERANCE, (
        f"frame {frame} answered {float(reply.distance[0])}, expected {expected_probe_distance(geometry)}"
    )


def settled(obj: RemoteObject) -> bool:
    """Nothing changed between two info requests (no frame left in flight)."""
    first = obj.info()
    return first.frame == obj.info().frame and first.frames_applied == obj.info().frames_applied


@pytest.fixture(scope="module")
def endpoint() -> str:
    return free_endpoint()


@pytest.fixture(scope="module")
def worker(endpoint: str):
    settings = WorkerSettings(worker_id="sturdy", listen=(endpoint,), device="cpu", stats_interval_s=5.0)
    with worker_process(settings, start_timeout_s=300.0) as process:
        yield process


@pytest.fixture
def client(worker, endpoint: str):
    with Client(endpoint, timeout=60) as connected:
        yield connected
        for info in connected.objects():
            connected.object(info.name).delete()


def test_a_client_killed_while_sending_loses_nothing_acknowledged(worker, endpoint: str, client: Client) -> None:
    """The sender spends most of its time sending 12 MB frames (about 60 ms in each stream() call on this
    machine, against 8 ms preparing the next), so SIGKILL mostly lands in the middle of one; where exactly
    is up to the scheduler, and every outcome must be safe."""
    bystander = client.register("bystander", BASE, FACES, depth=4)
    acknowledged, sending = SPAWN.Value("q", -1), SPAWN.Event()
    sender = SPAWN.Process(
        target=send_big_frames_until_killed, args=(endpoint, "big", acknowledged, sending), daemon=True
    )
    sender.start()
    try:
        assert sending.wait(300), "the sending client did not get going"
        wait_until(lambda: acknowledged.value >= 4, timeout=120, what="an update acknowledged while streaming")
        sender.kill()  # SIGKILL, most likely mid-frame: no goodbye, a half-sent message in the socket
        sender.join(30)
    finally:
        end_process(sender)
    assert worker.is_alive()
    for step in range(1, 4):  # the bystander never noticed
        assert bystander.update(frame_vertices(BASE, step)) == step
        assert_holds_frame(bystander, step)
    big = client.object("big")
    wait_until(lambda: settled(big), timeout=60, what="the killed client's last frame to be applied")
    reply = big.query(PROBE, mode="exact")  # answered after any frame still pending: the newest there is
    assert reply.frame >= acknowledged.value, f"acknowledged frame {acknowledged.value} lost: now {reply.frame}"
    assert abs(float(reply.distance[0]) - expected_probe_distance(reply.frame)) <= TOLERANCE  # a whole frame
    info = big.info()
    assert info.frame == reply.frame and info.frames_rejected == 0 and info.last_error is None
    big_base, _ = big_cube()
    assert big.update(frame_vertices(big_base, reply.frame + 1)) == reply.frame + 1  # another client carries on


def test_a_killed_worker_gives_clear_errors_then_clients_register_again() -> None:
    """SIGKILL the worker: every call fails with WorkerUnavailableError (ObjectUnavailableError, its subclass,
    on the objects' handles); a new worker on the same endpoint; the client's session reconnects by itself,
    and each object is registered again from what its handle kept (faces, options, last vertices, frame)."""
    endpoint = free_endpoint()
    settings = WorkerSettings(worker_id="phoenix", listen=(endpoint,), device="cpu", stats_interval_s=5.0)
    with ExitStack() as stack:
        first = stack.enter_context(worker_process(settings, start_timeout_s=300.0))
        client = stack.enter_context(Client(endpoint, timeout=60))  # outlives the first worker
        objects = [client.register(f"o{index}", BASE, FACES, depth=4) for index in range(2)]
        acknowledged = {obj.name: [obj.update(frame_vertices(BASE, frame)) for frame in (1, 2)][-1] for obj in objects}
        first.kill()
        first.join(30)
        for obj in objects:
            for call in (lambda: obj.query(PROBE, timeout=30), lambda: obj.info(timeout=30),
                         lambda: obj.update(frame_vertices(BASE, obj.frame + 1), timeout=30)):  # fmt: skip
                with pytest.raises(WorkerUnavailableError):
                    call()
        with pytest.raises(WorkerUnavailableError):
            client.register("newcomer", BASE, FACES, timeout=30)
        stack.enter_context(worker_process(settings, start_timeout_s=300.0))  # the same endpoint and id
        wait_until(lambda: [w.worker for w in client.workers(timeout=5)] == ["phoenix"], timeout=60,
                   what="the client's session to reach the new worker")  # fmt: skip
        assert client.objects() == []  # without a state directory, the new worker starts empty
        # the old handles stay unavailable although a worker of that id is back: it holds none of their
        # objects (they once read available again, streamed into nothing and queried ObjectNotFoundError)
        for obj in objects:
            assert not obj.available
            for call in (lambda: obj.query(PROBE, timeout=30),
                         lambda: obj.stream(frame_vertices(BASE, obj.frame + 1))):  # fmt: skip
                with pytest.raises(ObjectUnavailableError, match="came back"):
                    call()
        first_handle, second_handle = objects
        first_handle.reregister(timeout=60)  # the documented recovery, on the handle itself
        assert first_handle.available and first_handle.frame > acknowledged[first_handle.name]
        # the last vertices that went (the acknowledged frame's), under a new number: the update and the
        # stream that failed since used theirs up, and their vertices are not kept
        assert_holds_frame(first_handle, first_handle.frame, geometry=acknowledged[first_handle.name])
        obj = second_handle  # or a new handle from what the old one kept
        again = client.register(obj.name, obj.vertices, obj.faces, frame=obj.frame, **obj.options.to_json())
        assert again.frame == obj.frame > acknowledged[obj.name]
        assert_holds_frame(again, again.frame, geometry=acknowledged[obj.name])
        assert again.update(frame_vertices(BASE, again.frame + 1)) == obj.frame + 1


def _stacks(threads: list[threading.Thread]) -> str:
    """Where each of `threads` that is still running is, as a traceback."""
    frames = sys._current_frames()
    return "\n".join(f"{thread.name}:\n" + "".join(traceback.format_stack(frames[thread.ident]))
                     for thread in threads if thread.is_alive() and thread.ident in frames)


def test_a_stopping_worker_answers_the_request_in_progress_and_refuses_the_waiting() -> None:
    """SIGTERM while one long exact query runs and three wait behind it: the running one is
    answered and the waiting ones refused (WorkerUnavailableError), as documented. The worker withdrew its
    liveliness token first, and the client, which cancels what it sent to a worker whose token goes, lost
    the answer of the running one. Later the object undeclared its keys before the running query replied,
    and that reply was lost in 4 of 9 runs of an outside check (round 4) with three waiting."""
    endpoint = free_endpoint()
    settings = WorkerSettings(worker_id="stopping", listen=(endpoint,), device="cpu", stats_interval_s=60.0)
    # Each query must run long enough that the three behind it are seen waiting: exact queries among a soup of
    # 2,000 large triangles, whose boxes all overlap, so that every search tests most of them (about 2 s on 2 cores
    # for 60,000 points, carried in 0.7 MB). A million points about a 768-face cube, as before, took 0.22 s once the
    # engine had grown faster, no longer than the requests took to arrive: three were seldom seen waiting at once.
    rng = np.random.default_rng(5)
    soup = rng.uniform(-0.5, 0.5, (6000, 3))
    points = rng.uniform(-0.6, 0.6, (60_000, 3)).astype(np.float32)
    outcomes: list = []
    with ExitStack() as stack:
        process = stack.enter_context(worker_process(settings, start_timeout_s=300.0))
        client = stack.enter_context(Client(endpoint, timeout=120))
        obj = client.register("busy", soup, np.arange(6000).reshape(2000, 3), depth=4)

        def ask() -> None:
            try:
                outcomes.append(obj.query(points, mode="exact").distance.shape)
            except Exception as error:  # noqa: BLE001 - any other error fails the test below, which names it
                outcomes.append(error)

        threads = [threading.Thread(target=ask) for _ in range(4)]
        for thread in threads:
            thread.start()
        # three waiting can also be three queued while the object's thread refreshes its snapshot, the fourth
        # still on its way and none running: then all four are refused, rightly (4 of about 45 runs, 2026-11-22).
        # Three waiting for 0.2 s means one runs: each query takes seconds
        streak = []

        def one_running_three_waiting() -> bool:
            if client.workers(timeout=30)[0].requests_waiting != 3:
                streak.clear()
                return False
            streak.append(time.monotonic())
            return streak[-1] - streak[0] >= 0.2

        wait_until(one_running_three_waiting, timeout=120, what="one query to run and the others to wait")
        end_process(process)
        deadline = time.monotonic() + 150.0  # past the client's timeout (120 s), shared by the four
        for thread in threads:
            thread.join(max(0.0, deadline - time.monotonic()))
        assert process.exitcode == 0
        # every request answered or refused; a request still waiting names where it waits (one CI run on 2 cores,
        # 2026-12-07, recorded one outcome of four and took about 5 minutes longer than usual: three waits?)
        assert not any(thread.is_alive() for thread in threads), (outcomes, _stacks(threads))
    answered = [outcome for outcome in outcomes if outcome == (len(points),)]
    refused = [outcome for outcome in outcomes if isinstance(outcome, WorkerUnavailableError)]
    assert len(answered) == 1 and len(refused) == 3, outcomes
    # the worker's "shutting down", or, read after the token went, the client's "gone": unavailable either way,
    # and to a handle as ObjectUnavailableError, which the documented recovery (reregister) catches
    assert all("shutting down" in str(error) or "is gone" in str(error) for error in refused), refused
    assert all(isinstance(error, ObjectUnavailableError) for error in refused), refused


def test_a_viewer_that_stops_reading_stalls_nobody(worker, endpoint: str, client: Client) -> None:
    """A viewer asks for twelve 1024 x 1024 slices (4 MB each) and is then stopped (SIGSTOP): nothing takes
    its replies off the socket. The first reply that does not fit blocks the watched object's thread until
    Zenoh gives up on the viewer (`wait_before_close`, 5 s by default) and closes its transport; the
    other replies then fail at once. Both objects are updated and queried all the while (the other one
    never waits on the viewer), and after the viewer is gone."""
    watched = client.register("watched", BASE, FACES, depth=5)
    other = client.register("other", BASE, FACES, depth=4)
    sent = SPAWN.Event()
    viewer = SPAWN.Process(target=ask_for_slices, args=(endpoint, "watched", 12, 1024, sent), daemon=True)
    viewer.start()
    try:
        assert sent.wait(120), "the viewer did not send its requests"
        os.kill(viewer.pid, signal.SIGSTOP)  # the process this test started
        for step in range(1, 16):
            for obj in (watched, other):
                assert obj.update(frame_vertices(BASE, step)) == step
                assert_holds_frame(obj, step)
        cut = watched.slice("z", 0.0, resolution=64)
        assert cut.frame == 15 and np.isfinite(cut.grid).all()
    finally:
        viewer.kill()  # SIGKILL ends a stopped process too
        viewer.join(30)
    assert worker.is_alive()
    assert watched.update(frame_vertices(BASE, 16)) == 16
    assert_holds_frame(watched, 16)


def test_frames_faster_than_the_worker_applies_keep_the_newest(worker, client: Client) -> None:
    """300 frames streamed back to back at an object whose every update takes tens of milliseconds on this
    CPU back-end (a 19,200-triangle cube at depth 6): most are dropped, each drop is counted, and the
    last frame sent is the one applied and answered."""
    base, faces = cube(40)
    obj = client.register("hurried", base, faces, depth=6)
    sent = [obj.stream(frame_vertices(base, frame)) for frame in range(1, 301)]
    wait_until(lambda: obj.info().frame == sent[-1], timeout=120, what="the last streamed frame to be applied")
    wait_until(lambda: settled(obj), timeout=60, what="the counters to settle")
    info = obj.info()
    assert info.frames_applied + info.frames_dropped == len(sent)
    assert info.frames_dropped > 0 and info.frames_rejected == 0
    assert_holds_frame(obj, sent[-1])
    [worker_info] = client.workers()
    assert worker_info.object_count == 1


def test_garbage_connections_leave_the_router_serving(worker, endpoint: str, client: Client) -> None:
    """Raw TCP to the worker's Zenoh port: 64 KiB of random bytes, a connection that sends four bytes and
    then nothing, and one that closes at once. The worker serves on while they are open and after."""
    obj = client.register("steady", BASE, FACES, depth=4)
    host, port = endpoint.split("/")[1].rsplit(":", 1)
    sockets = []
    try:
        noisy = socket.create_connection((host, int(port)), timeout=10)
        sockets.append(noisy)
        try:
            noisy.sendall(os.urandom(64 * 1024))
        except OSError:  # the router may hang up first: that is a fine answer to noise
            pass
        silent = socket.create_connection((host, int(port)), timeout=10)
        sockets.append(silent)
        silent.sendall(b"\x01\x02\x03\x04")
        socket.create_connection((host, int(port)), timeout=10).close()
        for step in range(1, 4):
            assert obj.update(frame_vertices(BASE, step)) == step
            assert_holds_frame(obj, step)
        with Client(endpoint, timeout=60) as newcomer:
            assert newcomer.object("steady").frame == 3
    finally:
        for open_socket in sockets:
            open_socket.close()
    assert obj.update(frame_vertices(BASE, 4)) == 4


def test_an_error_from_zenoh_itself_is_no_sign_of_a_live_worker() -> None:
    """When the router a client reached was its worker and that worker dies, Zenoh may answer the client's
    check on the worker (an info request) with its own error, "Timeout" (seen in about 1 kill in 12 in
    the test above). That is no answer from the worker: the call must end as WorkerUnavailableError, not
    as ObjectNotFoundError (which would tell the caller the object was deleted)."""
    endpoint = free_endpoint()
    keys = KeySpace()

    def zenoh_timeout(query: zenoh.Query) -> None:
        query.reply_err(b"Timeout")  # what Zenoh's own reply looked like: not a badf ErrorReply
        query.drop()

    with zenoh.open(zenoh_config(mode="router", listen=[endpoint])) as router:
        router.declare_queryable(keys.worker_info("departed"), zenoh_timeout)
        with Client(endpoint, timeout=10) as client:
            info = ObjectInfo("o", "departed", 3, 3, 1, ObjectOptions())
            handle = RemoteObject(client, info, vertices=None, faces=None)
            with pytest.raises(WorkerUnavailableError):
                handle.query(PROBE)
