"""The worker: registration, worker info and the liveliness token over Zenoh, around its served objects.

`serve(session, settings, stop=...)` runs a worker on an open session until `stop` is set. Registrations
are built on one registrar thread (a build can take seconds), so they never run inside a Zenoh callback
and never stall the objects already served; each object then runs on its own thread (see _objects).
"""

from __future__ import annotations

import json
import logging
import os
import re
import secrets
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import zenoh

from badf.protocol import (
    DEFAULT_ENDPOINT,
    DEFAULT_LIMITS,
    BadfError,
    InfoRequest,
    InvalidOptionError,
    KeySpace,
    Limits,
    ObjectExistsError,
    ObjectInfo,
    ObjectNotFoundError,
    ObjectOptions,
    RegisterRequest,
    WorkerBusyError,
    WorkerInfo,
    WorkerUnavailableError,
    ZenohMode,
    check_name,
    config_file_names,
    decode,
    encode,
    zenoh_config,
)
from badf.server._objects import Counters, DistanceFieldLike, ServedObject
from badf.server._replies import answer, engine_errors, refuse, request_bytes

log = logging.getLogger("badf.server")

# How long a starting worker waits for the routers to say whether its id is taken (they answer at once)
_ID_CHECK_TIMEOUT_S = 5.0
# A worker that finds its clock jumped by more than half of Zenoh's lease between two ticks of this many seconds was
# stalled (stopped, paused) long enough that the routers may have taken its token, and clients may have registered
# its objects elsewhere (`Worker._watch_for_stalls`). It then looks for such copies over a window of twice the lease
# (at least _STALL_WINDOW_S), while its links come back.
_STALL_TICK_S = 0.25
_STALL_WINDOW_S = 3.0
_ZENOH_DEFAULT_LEASE_S = 10.0
DEFAULT_STATS_INTERVAL_S = 10.0  # seconds between a worker's stats lines (`--stats-interval`)
# seconds without a frame after which an object gives back what only its next frame would use (`--trim-after`)
DEFAULT_TRIM_AFTER_S = 10.0

FieldBuilder = Callable[[np.ndarray, np.ndarray, ObjectOptions], DistanceFieldLike]


def default_worker_id() -> str:
    """`<host>-<pid>`, reduced to the characters a key-expression chunk allows."""
    return re.sub(r"[^A-Za-z0-9_.\-]", "-", f"{socket.gethostname()}-{os.getpid()}")[:100]


def check_stats_interval(seconds: float, name: str) -> None:
    """ValueError unless the stats line's period is 0.1 to 1e6 seconds (nan and inf fail too): 1e-9 wrote
    36,326 lines in 5 s, and 1e300 overflowed the clock."""
    if not (0.1 <= seconds <= 1e6):
        raise ValueError(f"{name} must be a positive finite number of seconds in 0.1..1e6, got {seconds}")


def check_trim_after(seconds: float, name: str) -> None:
    """ValueError unless the idle time before a trim is 0 (never) or 0.1 to 1e6 seconds (nan and inf fail too)."""
    if not (seconds == 0 or 0.1 <= seconds <= 1e6):
        raise ValueError(f"{name} must be 0 (never) or a finite number of seconds in 0.1..1e6, got {seconds}")


@dataclass(frozen=True)
class WorkerSettings:
    """Everything `badf serve` takes for one worker.

    `listen` None means: with a config file, the file's endpoints; without one, tcp/127.0.0.1:7447 for a
    router that connects to nothing (the embedded default), and no endpoint at all for a worker that joins
    other routers through `connect` (it is reached through them, and takes no port of its own)."""

    worker_id: str = field(default_factory=default_worker_id)
    namespace: str = "badf"
    device: str | None = None
    mode: ZenohMode = "router"
    listen: tuple[str, ...] | None = None
    connect: tuple[str, ...] = ()
    config_file: str | None = None
    limits: Limits = DEFAULT_LIMITS
    stats_interval_s: float = DEFAULT_STATS_INTERVAL_S
    trim_after_s: float = DEFAULT_TRIM_AFTER_S
    max_waiting_requests: int = 32
    max_waiting_registrations: int = 8

    def __post_init__(self) -> None:
        check_name(self.worker_id, what="worker id")
        KeySpace(self.namespace)
        check_stats_interval(self.stats_interval_s, "stats_interval_s")
        check_trim_after(self.trim_after_s, "trim_after_s")
        if self.max_waiting_requests < 1 or self.max_waiting_registrations < 1:
            raise ValueError("max_waiting_requests and max_waiting_registrations must be at least 1")
        if self.mode == "client" and self.config_file is None:
            if not self.connect:
                raise ValueError("a worker in Zenoh's client mode is reached through a router: give the router "
                                 "to connect to (--connect tcp/HOST:7447)")
            if self.listen:
                raise ValueError("a worker in Zenoh's client mode listens on nothing: leave out --listen, or use "
                                 "--mode peer")
        self.zenoh_config()  # InvalidOptionError now, naming a malformed endpoint or config file

    def zenoh_config(self) -> zenoh.Config:
        listen = self.listen
        if listen is None and not config_file_names(self.config_file, "listen"):
            listen = (DEFAULT_ENDPOINT,) if self.mode == "router" and not self.connect else ()
        return zenoh_config(mode=self.mode, listen=listen, connect=self.connect, config_file=self.config_file)


def engine_field_builder(device: str | None) -> tuple[FieldBuilder, str]:
    """Builds the engine's DistanceField on `device`; returns the builder and the device's resolved name.

    Imports Warp and the engine here, not at module import, and keeps Warp's per-module load messages out
    of the worker's log (warnings and errors still show). Raises ValueError for an unknown device.
    """
    import warp as wp

    from badf.server.adf import DistanceField

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)

    try:
        resolved = wp.get_device(device).alias
    except RuntimeError as error:  # Warp's words for "cuda" where there is no CUDA
        raise ValueError(str(error)) from None

    def build(vertices: np.ndarray, faces: np.ndarray, options: ObjectOptions) -> DistanceFieldLike:
        return DistanceField(
            vertices,
            faces,
            depth=options.depth,
            sign=options.sign,
            band=options.band,
            coherence=options.coherence,
            refine=options.refine,
            halo=options.halo,
            region=options.region,
            bvh=options.bvh,
            rigid=options.rigid,
            device=resolved,
        )

    return build, resolved


@dataclass
class _Staged:
    """A registration decoded and built, not yet served."""

    request: RegisterRequest
    field: DistanceFieldLike
    build_ms: float
    existing: ServedObject | None  # the object it replaces, as found when it was decoded


def _raising(error: BaseException) -> Callable[[], ObjectInfo]:
    """Work for `answer` that raises `error`, so it is answered (and logged) as any error is."""

    def work() -> ObjectInfo:
        raise error

    return work


def warm_up_engine(device: str) -> None:
    """Load every engine kernel on `device` now, so the first object registered is not answered late
    (where Warp's kernel cache is empty this compiles them: 14 s on a 2-core CPU machine, 2026-11-22)."""
    from badf.server.adf import warm_up

    log.info("loading the engine's kernels on %s (compiled on the first run on a machine)", device)
    seconds = warm_up(device)
    log.info("engine kernels ready on %s in %.1f s", device, seconds)


class Worker:
    """The objects of one worker and its worker-level keys. `start` declares, `close` undeclares."""

    def __init__(
        self, session: zenoh.Session, settings: WorkerSettings, build_field: FieldBuilder, device: str
    ) -> None:
        self.settings = settings
        self.device = device
        self._session = session
        self._build_field = build_field
        self._keys = KeySpace(settings.namespace)
        self._objects: dict[str, ServedObject] = {}
        self._lock = threading.Condition()
        self._registrations: deque[zenoh.Query] = deque()
        self._closing = False
        self._entities: list = []
        self._started_at = time.monotonic()
        self._registrar = threading.Thread(target=self._register_loop, name="badf-registrar", daemon=True)
        # replacements waiting for their objects' queued requests, each on a thread of its own (see _register_loop)
        self._replacing: set[threading.Thread] = set()
        self._registered_total = 0
        self._retired = Counters()  # what deleted objects had counted (totals never go backwards), and
        # the errors registrations were answered with
        self._last_totals = Counters()
        self._last_stats_at = time.monotonic()
        self._lease_s = _lease_seconds(settings)
        self._stopping = threading.Event()
        self._stall_watch = threading.Thread(target=self._watch_for_stalls, name="badf-stall-watch", daemon=True)
        self.stalls_seen = 0  # stalls past half the lease, and objects withdrawn after them (for tests and logs)
        self.withdrawn_after_stalls = 0

    @property
    def worker_id(self) -> str:
        return self.settings.worker_id

    def start(self) -> None:
        """Declare the worker's keys and its liveliness token, last. InvalidOptionError, before anything is
        declared, if a worker of the same id already serves the namespace: both would answer every request
        to that id, and both build every object placed on it."""
        token_key = self._keys.worker_token(self.worker_id)
        for reply in self._session.liveliness().get(token_key, timeout=_ID_CHECK_TIMEOUT_S):
            if reply.ok is not None:
                raise InvalidOptionError(
                    f"a worker with id {self.worker_id!r} already serves namespace {self.settings.namespace!r}; "
                    "give this one another --worker-id"
                )
        self._registrar.start()
        self._entities = [
            self._session.declare_queryable(self._keys.worker_register(self.worker_id), self._on_register),
            self._session.declare_queryable(self._keys.worker_info(self.worker_id), self._on_worker_info),
            # Declared last: a client that sees the token finds the worker ready.
            self._session.liveliness().declare_token(self._keys.worker_token(self.worker_id)),
        ]
        self._stall_watch.start()

    def close(self) -> None:
        """Stop taking requests, answer what waits with 'unavailable', let what runs finish and answer, stop
        every object, and only then withdraw the liveliness token: a client cancels its requests to a worker
        when the token goes, so withdrawing it first lost the answer of the request in progress."""
        self._stopping.set()
        if self._stall_watch.is_alive():
            self._stall_watch.join()
        entities, self._entities = self._entities, []
        for queryable in entities[:-1]:
            queryable.undeclare()
        try:
            self._stop_serving()
        finally:
            for token in entities[-1:]:  # declared last in start()
                token.undeclare()

    def _stop_serving(self) -> None:
        shutting_down = WorkerUnavailableError(f"worker {self.worker_id} is shutting down")
        with self._lock:
            self._closing = True
            waiting, self._registrations = list(self._registrations), deque()
            self._lock.notify_all()
        for query in waiting:
            refuse(query, shutting_down)
        if self._registrar.is_alive():
            self._registrar.join()  # a build in progress finishes, and is refused below
        with self._lock:
            objects = list(self._objects.values())
            self._objects.clear()
            replacing = list(self._replacing)
        for served in objects:
            served.close(shutting_down)
        for thread in replacing:  # their objects closed: each answers its replacement, refused
            thread.join()

    def objects(self) -> list[ServedObject]:
        with self._lock:
            return list(self._objects.values())

    # --- stalls --------------------------------------------------------------------------------------------

    def _watch_for_stalls(self) -> None:
        """A worker stopped past Zenoh's lease (SIGSTOP, a paused VM) is gone to every client, which may register
        its objects on another worker (`reregister()`); when it resumes it would serve them too, and a lookup by
        name could take its stale copy for good (thirty-sixth outside check: 11 of 30). So after a jump of the
        clock past half the lease, it withdraws each object whose name another worker serves, checking until
        twice the lease has passed (its links to the routers come back meanwhile)."""
        last = time.monotonic()
        while not self._stopping.wait(_STALL_TICK_S):
            now = time.monotonic()
            if now - last > self._lease_s / 2.0:
                self.stalls_seen += 1
                log.warning("worker %s was stalled for %.1f s (Zenoh's lease is %g s): withdrawing its objects that "
                            "another worker serves now", self.worker_id, now - last, self._lease_s)
                deadline = now + max(_STALL_WINDOW_S, 2.0 * self._lease_s)
                while not self._stopping.is_set() and time.monotonic() < deadline:
                    self._withdraw_names_served_elsewhere()
                    self._stopping.wait(_STALL_TICK_S)
            last = time.monotonic()

    def _withdraw_names_served_elsewhere(self) -> None:
        mine = {served.name: served for served in self.objects()}
        if not mine:
            return
        elsewhere: dict[str, str] = {}
        try:
            replies = self._session.get(self._keys.every_object_info, payload=encode(InfoRequest()),
                                        timeout=_STALL_TICK_S * 4, consolidation=zenoh.ConsolidationMode.NONE)
            for reply in replies:
                if reply.ok is None:
                    continue
                try:
                    info = decode(reply.ok.payload.to_bytes(), ObjectInfo, limits=self.settings.limits)
                except BadfError:
                    continue
                if info.worker != self.worker_id and info.name in mine:
                    elsewhere[info.name] = info.worker
        except zenoh.ZError as error:  # no route yet: the next check tries again
            log.debug("looking for copies after a stall: %s", error)
            return
        for name, other in elsewhere.items():
            served = mine[name]
            self._forget(served)
            served.close(ObjectNotFoundError(
                f"object {name!r} was withdrawn from worker {self.worker_id}: worker {other} serves it, registered "
                "while this worker was stalled past Zenoh's lease"))
            self.withdrawn_after_stalls += 1
            log.warning("withdrew %r: worker %s serves it, registered while this worker was stalled", name, other)

    # --- registration ----------------------------------------------------------------------------------

    def _on_register(self, query: zenoh.Query) -> None:
        with self._lock:
            refusal: BadfError | None = None
            if self._closing:
                refusal = WorkerUnavailableError(f"worker {self.worker_id} is shutting down")
            elif len(self._registrations) >= self.settings.max_waiting_registrations:
                refusal = WorkerBusyError(
                    f"worker {self.worker_id} has {len(self._registrations)} registrations waiting"
                )
            else:
                self._registrations.append(query)
                self._lock.notify_all()
        if refusal is not None:
            refuse(query, refusal)
            if isinstance(refusal, WorkerBusyError):
                self._count_error()

    def _count_error(self) -> None:
        """A registration answered with an error: the stats line's errors count it with the objects' own."""
        with self._lock:
            self._retired.errors += 1

    def _register_loop(self) -> None:
        """Build each registration's field in turn. A replacement then waits for the requests already queued
        for its object on a thread of its own, so the registrations after it go on: waiting here held up every
        other registration on the worker, 31 to 41 s behind 33 queued exact queries of 250,000 points on the
        CPU (twelfth outside check)."""
        key = self._keys.worker_register(self.worker_id)
        while True:
            with self._lock:
                self._lock.wait_for(lambda: self._registrations or self._closing)
                if self._closing:
                    return
                query = self._registrations.popleft()
            try:
                staged = self._stage(query.payload)
            except Exception as error:  # noqa: BLE001 - answered as `answer` answers any error
                if isinstance(error, BadfError):
                    self._count_error()
                answer(query, key, _raising(error))
                continue
            if staged.existing is None:
                answer(query, key, lambda: self._install_counted(staged))
                continue
            with self._lock:
                busy = len(self._replacing) >= self.settings.max_waiting_registrations
            if busy:
                self._count_error()
                answer(query, key, _raising(WorkerBusyError(
                    f"worker {self.worker_id} has {self.settings.max_waiting_registrations} replacements waiting "
                    "for their objects' queued requests")))
                continue
            thread = threading.Thread(target=self._replace, args=(query, key, staged), name="badf-replace",
                                      daemon=True)
            with self._lock:
                self._replacing.add(thread)
            thread.start()

    def _replace(self, query: zenoh.Query, key: str, staged: _Staged) -> None:
        try:
            answer(query, key, lambda: self._install_counted(staged))
        finally:
            with self._lock:
                self._replacing.discard(threading.current_thread())

    def _install_counted(self, staged: _Staged) -> ObjectInfo:
        try:
            return self._install(staged)
        except BadfError:
            self._count_error()
            raise

    def _stage(self, payload: zenoh.ZBytes | None) -> _Staged:
        """Decode a registration and build its field (the object it replaces, if any, is left as it is)."""
        limits = self.settings.limits
        request = decode(request_bytes(payload, limits), RegisterRequest, limits=limits)
        with self._lock:
            existing = self._objects.get(request.name)
        if existing is not None and not request.replace:
            raise ObjectExistsError(
                f"object {request.name!r} already exists on worker {self.worker_id}; pass replace=True to swap it"
            )
        started = time.perf_counter()
        with engine_errors():
            built = self._build_field(request.vertices, request.faces, request.options)
        return _Staged(request, built, (time.perf_counter() - started) * 1000, existing)

    def _install(self, staged: _Staged) -> ObjectInfo:
        """Serve a built field: swap it into the object it replaces (after that object's queued requests), or
        serve it as a new object. A replacement whose object went meanwhile (deleted) creates it, and one
        whose name was served again meanwhile (by a registration or another replacement) swaps into that: two
        replacements racing a delete both succeed, the later one last (thirteenth outside check: the second
        was refused with "pass replace=True", which it had)."""
        request, built, build_ms, existing = staged.request, staged.field, staged.build_ms, staged.existing
        registration = secrets.randbits(62)  # tells this registration from any other, in any worker's life
        while True:
            if existing is not None:
                try:
                    info = existing.swap(built, request.options, request.frame, request.vertices, request.faces,
                                         registration)
                    break
                except ObjectNotFoundError:  # deleted while the new field was built: replace=True creates it
                    pass
            served = ServedObject(
                request.name,
                built,
                request.options,
                vertices=request.vertices,
                faces=request.faces,
                frame=request.frame,
                registration=registration,
                worker_id=self.worker_id,
                keys=self._keys,
                limits=self.settings.limits,
                max_waiting_requests=self.settings.max_waiting_requests,
                on_deleted=self._forget,
                trim_after_s=self.settings.trim_after_s,
            )
            info = served.info()  # before anyone can swap another registration in
            with self._lock:
                if self._closing:
                    raise WorkerUnavailableError(f"worker {self.worker_id} is shutting down")
                existing = self._objects.get(request.name)  # served again while this one was built or waited
                if existing is None:
                    self._objects[request.name] = served
            if existing is None:
                served.start(self._session)
                break
            if not request.replace:
                raise ObjectExistsError(
                    f"object {request.name!r} was registered on worker {self.worker_id} while this registration "
                    "was built; pass replace=True to swap it")
        with self._lock:
            self._registered_total += 1
        resolved_sign = info.field_info.get("sign", request.options.sign)
        log.info(
            "%s %r: %d vertices, %d faces, depth %d, sign %s, frame %d, built in %.1f ms on %s",
            "replaced" if existing is not None else "registered",
            request.name, info.vertex_count, info.face_count, request.options.depth, resolved_sign,
            request.frame, build_ms, self.device,
        )  # fmt: skip
        return info

    def _forget(self, served: ServedObject) -> None:
        counters = served.counters()
        with self._lock:
            if self._objects.get(served.name) is served:
                del self._objects[served.name]
            self._retired += counters

    # --- worker info and stats ----------------------------------------------------------------------

    def _on_worker_info(self, query: zenoh.Query) -> None:
        answer(query, self._keys.worker_info(self.worker_id), lambda: self._worker_info(query.payload))

    def _worker_info(self, payload: zenoh.ZBytes | None) -> WorkerInfo:
        decode(request_bytes(payload, self.settings.limits), InfoRequest, limits=self.settings.limits)
        objects = self.objects()
        totals = self.totals()
        with self._lock:
            registrations_waiting = len(self._registrations)
        return WorkerInfo(
            self.worker_id,
            self.device,
            len(objects),
            sum(served.vertex_count for served in objects),
            sum(served.face_count for served in objects),
            time.monotonic() - self._started_at,
            self.settings.limits.to_json(),
            requests_waiting=registrations_waiting + sum(served.waiting_count for served in objects),
            frames_applied=totals.frames_applied,
            queries_answered=totals.queries_answered,
            points_answered=totals.points_answered,
        )

    def totals(self) -> Counters:
        """Counters summed over every object this worker has served."""
        with self._lock:
            totals = self._retired
        for served in self.objects():
            totals += served.counters()
        return totals

    def stats_line(self) -> str:
        """One line of what happened since the previous call."""
        now, totals = time.monotonic(), self.totals()
        delta = {name: value - getattr(self._last_totals, name) for name, value in vars(totals).items()}
        seconds = now - self._last_stats_at
        self._last_totals, self._last_stats_at = totals, now
        return (
            f"stats: {len(self.objects())} objects; last {seconds:.1f} s: frames {delta['frames_applied']} applied, "
            f"{delta['frames_dropped']} dropped, {delta['frames_rejected']} rejected; "
            f"queries {delta['queries_answered']} ({delta['points_answered']} points); errors {delta['errors']}"
        )


def _lease_seconds(settings: WorkerSettings) -> float:
    """Zenoh's lease as the worker's configuration sets it (`transport/link/tx/lease`, in ms)."""
    try:
        lease_ms = json.loads(settings.zenoh_config().get_json("transport/link/tx/lease"))
        return float(lease_ms) / 1000.0 if lease_ms else _ZENOH_DEFAULT_LEASE_S
    except (zenoh.ZError, ValueError, TypeError):
        return _ZENOH_DEFAULT_LEASE_S


def serve(
    session: zenoh.Session,
    settings: WorkerSettings,
    *,
    stop: threading.Event,
    build_field: FieldBuilder | None = None,
    device: str | None = None,
    on_ready: Callable[[Worker], None] | None = None,
) -> None:
    """Serve badf objects on `session` until `stop` is set, logging a stats line every stats interval.

    `build_field` defaults to the engine's DistanceField on `settings.device`; tests of the plumbing may
    pass another builder (and a `device` name for the worker info).
    """
    if build_field is None:
        build_field, device = engine_field_builder(settings.device)
    worker = Worker(session, settings, build_field, device or settings.device or "default")
    worker.start()
    try:
        log.info("worker %s serving namespace %r on %s", worker.worker_id, settings.namespace, worker.device)
        if on_ready is not None:
            on_ready(worker)
        while not stop.wait(settings.stats_interval_s):
            log.info(worker.stats_line())
    finally:
        worker.close()
        log.info("worker %s stopped", worker.worker_id)
