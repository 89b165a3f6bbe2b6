"""One served object: its distance field, its Zenoh keys, and the one thread that touches the field.

Zenoh callbacks only check sizes and hand work over: a streamed frame replaces the pending streamed frame,
a blocking update the pending update (the replaced one is counted as dropped), other requests join a
bounded queue. A stream and an update may both be pending: Zenoh keeps one session's puts in order but
may deliver a query (the update) before puts sent earlier, so the object's thread applies the one with the
higher frame number and finds the other stale. The object's thread alternates between applying the
pending frame and answering one waiting request, so queries always see a fully applied frame, a stream
cannot starve queries, and a slow object delays only its own requests.
Info and mesh requests are answered at once: the frame, counters and newest applied vertices are current
(the object keeps a reference to them; the engine is not asked); the engine's own info and stats
are a snapshot the object's thread refreshes at most every 0.25 s (on a GPU, reading the engine's stage
timers waits for the object's last stage and takes the device's lock, which every frame need not pay).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Protocol

import numpy as np
import zenoh

from badf.protocol import (
    CELL_EMPTY,
    CELL_LEAF,
    BadfError,
    Deleted,
    DeleteRequest,
    Frame,
    FrameAck,
    InfoRequest,
    KeySpace,
    Limits,
    MeshReply,
    MeshRequest,
    MetadataError,
    NotSupportedError,
    ObjectInfo,
    ObjectNotFoundError,
    ObjectOptions,
    QueryReply,
    QueryRequest,
    SliceReply,
    SliceRequest,
    StaleFrameError,
    VertexCountMismatchError,
    WorkerBusyError,
    decode,
)
from badf.server._memory import release_freed_memory
from badf.server._replies import answer, engine_errors, refuse, request_bytes

log = logging.getLogger("badf.server")

# How often, at most, the object's thread refreshes the engine's info and stats for info replies.
_SNAPSHOT_PERIOD_S = 0.25


class DistanceFieldLike(Protocol):
    """What the worker needs of the engine's DistanceField (badf.server.adf)."""

    @property
    def vertex_count(self) -> int: ...

    @property
    def face_count(self) -> int: ...

    def update(self, vertices: np.ndarray) -> int: ...

    def query(self, points: np.ndarray, *, mode: str, outputs: tuple[str, ...]) -> Any: ...

    def slice(self, axis: str, position: float, *, resolution: int, max_level: int) -> Any: ...

    def info(self) -> dict[str, Any]: ...

    def stats(self) -> dict[str, Any]: ...

    def trim(self) -> int: ...


@dataclass
class Counters:
    frames_applied: int = 0
    frames_dropped: int = 0
    frames_rejected: int = 0
    queries_answered: int = 0
    points_answered: int = 0
    errors: int = 0

    def __add__(self, other: Counters) -> Counters:
        return Counters(**{name: value + getattr(other, name) for name, value in vars(self).items()})


@dataclass
class _PendingFrame:
    payload: zenoh.ZBytes | None
    query: zenoh.Query | None  # None for a streamed frame

    @property
    def kind(self) -> str:
        return "stream" if self.query is None else "update"


@dataclass
class _Request:
    run: Callable[[], None]
    fail: Callable[[BadfError], None]  # answers the request with an error instead of running it


class ServedObject:
    """A registered object. Create, `start` (declares its keys), and `close`, or delete it over Zenoh."""

    def __init__(
        self,
        name: str,
        field: DistanceFieldLike,
        options: ObjectOptions,
        *,
        vertices: np.ndarray,
        faces: np.ndarray,
        frame: int,
        registration: int,
        worker_id: str,
        keys: KeySpace,
        limits: Limits,
        max_waiting_requests: int,
        on_deleted: Callable[[ServedObject], None],
        trim_after_s: float = 0.0,
    ) -> None:
        self.name = name
        self.worker_id = worker_id
        self._field = field
        self._vertex_count = field.vertex_count
        self._face_count = field.face_count
        self._options = options
        self._frame = frame
        self._registration = registration  # the worker's number for this registration (see ObjectInfo)
        self._vertices = vertices  # of the newest applied frame, for mesh requests
        self._faces = faces
        self._keys = keys
        self._limits = limits
        self._max_waiting = max_waiting_requests
        self._on_deleted = on_deleted
        # an object that gets no frame for this long (0: never) gives back what only its next frame would use, once
        # until the next frame comes (`_trim_if_idle`)
        self._trim_after_s = trim_after_s
        self._last_frame_at = time.monotonic()
        self._trimmed = False
        self._counters = Counters()  # since this registration (the object's info)
        self._replaced_counters = Counters()  # what the registrations it replaced had counted
        self._last_error: str | None = None
        self._field_info: dict[str, Any] = {}
        self._field_stats: dict[str, Any] = {}
        self._snapshot_at = 0.0
        self._snapshot_stale = False
        self._lock = threading.Condition()
        self._pending: dict[str, _PendingFrame] = {}  # by kind: at most one stream and one update
        self._waiting: deque[_Request] = deque()
        self._closing: BadfError | None = None
        self._entities: list[Any] = []
        self._thread = threading.Thread(target=self._run, name=f"badf-object-{name}", daemon=True)
        self._refresh_snapshot(force=True)

    # --- life cycle ---------------------------------------------------------------------------------

    def start(self, session: zenoh.Session) -> None:
        self._thread.start()
        frame_key = self._keys.object_frame(self.name)
        # the info last, and undeclared first (`_undeclare`): a client that finds the object by its info and meets
        # nobody on another of its keys calls that access control, which it would be while the info answers (a
        # mesh request right after `Client.object` on a register-and-delete loop: 48 and 87 such errors in 30 s,
        # thirty-fifth outside check)
        self._entities = [
            session.declare_subscriber(frame_key, self._on_frame_sample),
            session.declare_queryable(frame_key, self._on_frame_query),
            session.declare_queryable(self._keys.object_query(self.name), self._on_query),
            session.declare_queryable(self._keys.object_slice(self.name), self._on_slice),
            session.declare_queryable(self._keys.object_delete(self.name), self._on_delete),
            session.declare_queryable(self._keys.object_mesh(self.name), self._on_mesh),
            session.declare_queryable(self._keys.object_info(self.name), self._on_info),
        ]

    def close(self, reason: BadfError) -> None:
        """Refuse the waiting requests and any that come with `reason`, let the one running finish and
        answer, end the object's thread, and only then undeclare the object's keys: a reply sent after its
        queryable was undeclared could be lost (the answer of a query in progress at SIGTERM, 4 of 9 runs)."""
        self._begin_closing(reason)
        if threading.current_thread() is not self._thread:
            self._thread.join()
        self._undeclare()

    def _undeclare(self) -> None:
        entities, self._entities = self._entities, []
        for entity in reversed(entities):  # the info first
            entity.undeclare()

    def _begin_closing(self, reason: BadfError) -> None:
        """From now on refuse everything with `reason`, including what waits (not what is running)."""
        with self._lock:
            if self._closing is None:
                self._closing = reason
            self._lock.notify_all()
        self._fail_waiting()

    def _fail_waiting(self) -> None:
        with self._lock:
            reason = self._closing
            frames, self._pending = list(self._pending.values()), {}
            waiting, self._waiting = list(self._waiting), deque()
        for frame in frames:
            if frame.query is not None:
                refuse(frame.query, reason)  # type: ignore[arg-type]
        for request in waiting:
            request.fail(reason)  # type: ignore[arg-type]

    # --- what others may read ------------------------------------------------------------------------

    @property
    def vertex_count(self) -> int:
        return self._vertex_count

    @property
    def face_count(self) -> int:
        return self._face_count

    @property
    def pending_kinds(self) -> tuple[str, ...]:
        """The frames waiting to be applied: "stream", "update", both or none."""
        with self._lock:
            return tuple(sorted(self._pending))

    @property
    def waiting_count(self) -> int:
        """Requests queued for the object's thread."""
        with self._lock:
            return len(self._waiting)

    def counters(self) -> Counters:
        """Everything counted under this name since it was first registered, replaced registrations
        included: the worker's totals, which never go backwards."""
        with self._lock:
            return self._counters + self._replaced_counters

    def info(self) -> ObjectInfo:
        with self._lock:
            return ObjectInfo(
                self.name,
                self.worker_id,
                self._frame,
                self._vertex_count,
                self._face_count,
                self._options,
                frames_applied=self._counters.frames_applied,
                frames_dropped=self._counters.frames_dropped,
                frames_rejected=self._counters.frames_rejected,
                queries_answered=self._counters.queries_answered,
                points_answered=self._counters.points_answered,
                registration=self._registration,
                last_error=self._last_error,
                field_info=self._field_info,
                field_stats=self._field_stats,
            )

    # --- Zenoh callbacks: cheap, never touch the field ------------------------------------------------

    def _on_frame_sample(self, sample: zenoh.Sample) -> None:
        self._offer_frame(_PendingFrame(sample.payload, None))

    def _on_frame_query(self, query: zenoh.Query) -> None:
        self._offer_frame(_PendingFrame(query.payload, query))

    def _offer_frame(self, frame: _PendingFrame) -> None:
        with self._lock:
            closing = self._closing
            if closing is None:
                replaced = self._pending.get(frame.kind)
                self._pending[frame.kind] = frame
                if replaced is not None:
                    self._counters.frames_dropped += 1
                self._lock.notify_all()
        if closing is not None:
            if frame.query is not None:
                refuse(frame.query, closing)
            return
        if replaced is not None and replaced.query is not None:
            refuse(replaced.query, StaleFrameError("a newer frame arrived before this one was applied"))

    def _on_query(self, query: zenoh.Query) -> None:
        self._enqueue_query(self._answer_query, query)

    def _on_slice(self, query: zenoh.Query) -> None:
        self._enqueue_query(self._answer_slice, query)

    def _on_delete(self, query: zenoh.Query) -> None:
        self._enqueue_query(self._answer_delete, query)

    def _on_info(self, query: zenoh.Query) -> None:
        answer(query, self._keys.object_info(self.name), lambda: self._info_for(query))

    def _info_for(self, query: zenoh.Query) -> ObjectInfo:
        request = decode(request_bytes(query.payload, self._limits), InfoRequest, limits=self._limits)
        if request.name is not None:
            self._check_addressed_to_me(request.name)
        info = self.info()
        self._check_registration(request, info.registration)
        return info

    def _on_mesh(self, query: zenoh.Query) -> None:
        answer(query, self._keys.object_mesh(self.name), lambda: self._mesh_for(query))

    def _mesh_for(self, query: zenoh.Query) -> MeshReply:
        request = decode(request_bytes(query.payload, self._limits), MeshRequest, limits=self._limits)
        self._check_addressed_to_me(request.name)
        with self._lock:
            frame, vertices, faces, registration = self._frame, self._vertices, self._faces, self._registration
        self._check_registration(request, registration)
        return MeshReply(self.name, frame, vertices, faces if request.faces else None)

    def _enqueue_query(self, run: Callable[[zenoh.Query], None], query: zenoh.Query) -> None:
        self._enqueue(_Request(lambda: run(query), lambda error: refuse(query, error)))

    def _enqueue(self, request: _Request, *, bounded: bool = True) -> None:
        """Queue `request` for the object's thread, or fail it at once when the queue is full (unless not
        `bounded`: the worker's own replacement of the object) or closed."""
        with self._lock:
            refusal = self._closing
            if refusal is None and bounded and len(self._waiting) >= self._max_waiting:
                refusal = WorkerBusyError(
                    f"{len(self._waiting)} requests for {self.name!r} are already waiting; try again"
                )
            if refusal is None:
                self._waiting.append(request)
                self._lock.notify_all()
                return
        request.fail(refusal)
        if isinstance(refusal, WorkerBusyError):  # an error the caller sees, so the stats count it
            self._note_answered(refusal)

    # --- the object's thread ---------------------------------------------------------------------------

    def _run(self) -> None:
        while True:
            with self._lock:
                timeouts = [self._trim_due_in()]
                if self._snapshot_stale:
                    timeouts.append(max(0.0, self._snapshot_at + _SNAPSHOT_PERIOD_S - time.monotonic()))
                timeout = min((t for t in timeouts if t is not None), default=None)
                if not self._lock.wait_for(self._has_work, timeout=timeout):
                    frames, request = [], None  # idle with a stale snapshot: refresh it below
                elif self._closing is not None:
                    break
                else:
                    frames, self._pending = list(self._pending.values()), {}
                    request = self._waiting.popleft() if self._waiting else None
            if not frames:  # also between queries, which may come more often than the trim's wait
                self._trim_if_idle()
            if not frames and request is None:
                try:
                    self._refresh_snapshot(force=True)
                except Exception:  # noqa: BLE001 - a failing report must not end the object's thread
                    log.exception("reading the engine's info and stats for %r failed", self.name)
            if frames:
                self._apply_newest(frames)
            if request is not None:
                request.run()
        self._fail_waiting()
        # nothing runs on the field once this thread ends: its memory goes now (not when the last reference to
        # this object does), and the C library is asked to hand it back
        self._field = None  # type: ignore[assignment]
        release_freed_memory()

    def _has_work(self) -> bool:
        return bool(self._pending or self._waiting or self._closing)

    def _trim_due_in(self) -> float | None:
        """Seconds until the object is due a trim (0: now), or None: trims are off, or it was trimmed since its last
        frame."""
        if self._trim_after_s <= 0 or self._trimmed:
            return None
        return max(0.0, self._last_frame_at + self._trim_after_s - time.monotonic())

    def _trim_if_idle(self) -> None:
        """Trim the field once it has had no frame for `trim_after_s` (the engine's `trim`: its frame scratch, last
        frame's faces, and its query and slice buffers, which a later query allocates again)."""
        if self._trim_due_in() != 0.0:
            return
        self._trimmed = True
        try:
            freed = self._field.trim()
        except Exception:  # noqa: BLE001 - a failing trim must not end the object's thread (the field keeps answering)
            log.exception("trimming %r failed", self.name)
            return
        release_freed_memory()  # on the CPU back-end the buffers were the process's heap: hand it back
        log.debug("%r had no frame for %g s: trimmed, %.1f MiB given back", self.name, self._trim_after_s,
                  freed / 2**20)

    def _apply_newest(self, frames: list[_PendingFrame]) -> None:
        """Apply the pending frame with the highest number first; `_apply` then finds the other one (if a
        stream and an update were both pending) stale, or malformed, and answers or counts it as such."""
        if len(frames) > 1:
            frames.sort(key=self._order, reverse=True)
        for frame in frames:
            self._apply(frame)

    def _order(self, pending: _PendingFrame) -> tuple[int, bool]:
        """(frame number, is an update): on equal numbers the update, which someone waits for, goes first;
        a payload that does not decode goes last (its error is answered when `_apply` decodes it again)."""
        try:
            number = decode(request_bytes(pending.payload, self._limits), Frame, limits=self._limits).frame
        except BadfError:
            number = -1
        return number, pending.query is not None

    def _apply(self, pending: _PendingFrame) -> None:
        def note(error: BadfError) -> None:
            if isinstance(error, StaleFrameError):
                with self._lock:
                    self._counters.frames_dropped += 1
            else:
                self._note_error(error, frame=True, answered=pending.query is not None)

        if pending.query is not None:
            key = self._keys.object_frame(self.name)
            answer(pending.query, key, lambda: self._apply_frame(pending.payload), on_error=note)
            return
        try:
            self._apply_frame(pending.payload)
        except BadfError as error:
            note(error)

    def _apply_frame(self, payload: zenoh.ZBytes | None) -> FrameAck:
        frame = decode(request_bytes(payload, self._limits), Frame, limits=self._limits)
        self._check_addressed_to_me(frame.name)
        if frame.registration is not None and frame.registration != self._registration:
            # the sender's handle is on a registration since replaced: its frame is for another mesh, which
            # may have the same vertex count (a handle held across another client's replace=True)
            raise StaleFrameError(
                f"frame {frame.frame} was sent for a registration of {self.name!r} that has since been replaced "
                "(registered again, with replace=True); take a handle on the new one (Client.object(name)) or "
                "register it again")
        if frame.frame <= self._frame:
            raise StaleFrameError(f"frame {frame.frame} is not newer than the applied frame {self._frame}")
        if len(frame.vertices) != self._vertex_count:
            raise VertexCountMismatchError(
                f"{self.name} has {self._vertex_count} vertices; frame {frame.frame} has {len(frame.vertices)}"
            )
        refused = False  # the engine's InvalidInputError: the field is as it was, and so is the trim's clock
        try:
            with engine_errors():
                try:
                    self._field.update(frame.vertices)
                except ValueError:
                    refused = True
                    raise
        finally:
            if not refused:  # applied, or failed on the way: either way the field holds a frame's memory again
                self._last_frame_at, self._trimmed = time.monotonic(), False
        with self._lock:
            self._frame, self._vertices = frame.frame, frame.vertices
            self._counters.frames_applied += 1
        self._refresh_snapshot()
        return FrameAck(self.name, frame.frame)

    def _answer_query(self, query: zenoh.Query) -> None:
        key = self._keys.object_query(self.name)
        answer(query, key, lambda: self._run_query(query.payload), on_error=self._note_answered)

    def _run_query(self, payload: zenoh.ZBytes | None) -> QueryReply:
        request = decode(request_bytes(payload, self._limits), QueryRequest, limits=self._limits)
        self._check_addressed_to_me(request.name)
        self._check_registration(request, self._registration)  # the object's thread: no swap meanwhile
        with engine_errors():
            result = self._field.query(request.points, mode=request.mode, outputs=request.outputs)
        outputs = {name: getattr(result, name) for name in request.outputs}
        reply = QueryReply(self.name, self._frame, **outputs)
        with self._lock:
            self._counters.queries_answered += 1
            self._counters.points_answered += len(request.points)
        self._refresh_snapshot()
        return reply

    def _answer_slice(self, query: zenoh.Query) -> None:
        key = self._keys.object_slice(self.name)
        answer(query, key, lambda: self._run_slice(query.payload), on_error=self._note_answered)

    def _run_slice(self, payload: zenoh.ZBytes | None) -> SliceReply:
        request = decode(request_bytes(payload, self._limits), SliceRequest, limits=self._limits)
        self._check_addressed_to_me(request.name)
        self._check_registration(request, self._registration)  # the object's thread: no swap meanwhile
        if request.corners:
            raise NotSupportedError("corner sample points on a slice are not served yet; ask with corners=False")
        lowest, highest = request.levels if request.levels is not None else (0, self._options.depth)
        with engine_errors():
            cut = self._field.slice(
                request.axis,
                request.position,
                resolution=request.resolution,
                max_level=min(highest, self._options.depth),
            )
        cells: dict[str, np.ndarray] = {}
        if request.cells:
            keep = cut.cell_level >= lowest
            cells = {
                "cell_boxes": np.stack([cut.cell_lower[keep], cut.cell_upper[keep]], axis=1),
                "cell_levels": cut.cell_level[keep],
                "cell_flags": cut.cell_is_leaf[keep] * np.uint8(CELL_LEAF)
                | cut.cell_is_empty[keep] * np.uint8(CELL_EMPTY),
            }
        extent = ((cut.u_range[0], cut.v_range[0]), (cut.u_range[1], cut.v_range[1]))
        self._refresh_snapshot()
        return SliceReply(self.name, self._frame, request.axis, request.position, extent, cut.distance, **cells)

    def _answer_delete(self, query: zenoh.Query) -> None:
        answer(query, self._keys.object_delete(self.name), lambda: self._delete(query.payload))

    def _delete(self, payload: zenoh.ZBytes | None) -> Deleted:
        request = decode(request_bytes(payload, self._limits), DeleteRequest, limits=self._limits)
        self._check_addressed_to_me(request.name)
        self._check_registration(request, self._registration)  # the object's thread: no swap meanwhile
        self._undeclare()
        self._on_deleted(self)
        self._begin_closing(ObjectNotFoundError(f"object {self.name!r} was deleted"))
        log.info("deleted %r at frame %d", self.name, self._frame)
        return Deleted(self.name, self._frame)

    def swap(
        self,
        field: DistanceFieldLike,
        options: ObjectOptions,
        frame: int,
        vertices: np.ndarray,
        faces: np.ndarray,
        registration: int,
    ) -> ObjectInfo:
        """Replace the field (a re-registration), on the object's thread after the requests waiting before
        it; blocks until done. A frame still pending for the old topology is dropped. Raises what closed
        the object (ObjectNotFoundError once deleted) if it closed first."""
        done = threading.Event()
        failure: list[BadfError] = []
        swapped: list[ObjectInfo] = []  # this registration's info, read before another swap can follow it

        def run() -> None:
            with self._lock:
                # frames pending for the old mesh are dropped, and counted so by the registration they came to
                # (they went uncounted: 199 of 200 streamed frames in the stats; thirteenth outside check)
                stale, self._pending = list(self._pending.values()), {}
                self._counters.frames_dropped += len(stale)
                self._field, self._options, self._frame = field, options, frame
                self._registration = registration
                self._vertices, self._faces = vertices, faces
                self._vertex_count, self._face_count = field.vertex_count, field.face_count
                self._replaced_counters += self._counters
                self._counters = Counters()
                self._last_error = None
                self._last_frame_at, self._trimmed = time.monotonic(), False  # a new field, with a frame's memory
            for pending in stale:
                if pending.query is not None:
                    refuse(pending.query, StaleFrameError(f"{self.name} was replaced before this frame was applied"))
            self._refresh_snapshot(force=True)
            swapped.append(self.info())
            done.set()

        def fail(error: BadfError) -> None:
            failure.append(error)
            done.set()

        self._enqueue(_Request(run, fail), bounded=False)  # one per replacement the worker has waiting
        done.wait()
        if failure:
            raise failure[0]
        return swapped[0]

    # --- helpers -----------------------------------------------------------------------------------

    def _check_addressed_to_me(self, name: str) -> None:
        if name != self.name:
            raise MetadataError(f"the message names object {name!r} but was sent to {self.name!r}")

    def _check_registration(self, request: QueryRequest | SliceRequest | InfoRequest | MeshRequest | DeleteRequest,
                            registration: int) -> None:
        """A request that names a registration (a handle's) other than the one served now was meant for an
        object since replaced: it is not answered from another mesh, nor does it delete the object another
        client registered in its place (thirteenth outside check: an old handle read the new mesh, and its
        delete() removed it)."""
        if request.registration is not None and request.registration != registration:
            raise ObjectNotFoundError(
                f"{type(request).__name__} was sent for a registration of {self.name!r} that has since been "
                "deleted or replaced (registered again); take a handle on the new one (Client.object(name)) or "
                "register it again")

    def _note_answered(self, error: BadfError) -> None:
        self._note_error(error, answered=True)

    def _note_error(self, error: BadfError, *, answered: bool, frame: bool = False) -> None:
        """Count an error; log it when nobody was answered (a streamed frame), once per distinct message."""
        with self._lock:
            repeated = error.message == self._last_error
            self._counters.errors += 1
            if frame:
                self._counters.frames_rejected += 1
            self._last_error = error.message
        if not answered and not repeated:
            log.warning("streamed frame for %r rejected: %s", self.name, error.message)
        else:
            log.debug("request for %r answered with %s: %s", self.name, error.code.name, error.message)

    def _refresh_snapshot(self, *, force: bool = False) -> None:
        """Read the engine's info and stats, unless the last read is recent (then mark the snapshot stale)."""
        now = time.monotonic()
        if not force and now - self._snapshot_at < _SNAPSHOT_PERIOD_S:
            self._snapshot_stale = True
            return
        info, stats = self._field.info(), self._field.stats()
        with self._lock:
            self._field_info, self._field_stats, self._snapshot_at = info, stats, now
            self._snapshot_stale = False
