"""The badf client: register objects on workers, stream their frames, and query them, over Zenoh.

Every call that waits has a timeout (the client's default, or its own `timeout=`), and a worker that is
gone is reported as WorkerUnavailableError, a worker that does not answer in time as WorkerTimeoutError.
Errors the worker answers with are raised as the badf.protocol exception of their code, with its message.

The client follows the workers' liveliness tokens: once an object's worker is gone, every call on the
object's handle raises ObjectUnavailableError at once (requests in flight to it are cancelled), and
`RemoteObject.reregister()` puts the object on another worker from what the handle kept.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import weakref
from typing import Sequence, TypeVar

import numpy as np
import zenoh

from badf.protocol import (
    DEFAULT_ENDPOINT,
    DEFAULT_LIMITS,
    MAX_COORDINATE,
    QUERY_OUTPUTS,
    AccessDeniedError,
    BadfError,
    BvhShape,
    RigidMode,
    InvalidOptionError,
    Deleted,
    DeleteRequest,
    ErrorReply,
    Frame,
    FrameAck,
    InfoRequest,
    KeySpace,
    Limits,
    MeshReply,
    MeshRequest,
    Message,
    MessageError,
    NotSupportedError,
    ObjectExistsError,
    ObjectInfo,
    ObjectNotFoundError,
    ObjectOptions,
    ObjectUnavailableError,
    QueryMode,
    QueryOutput,
    QueryReply,
    QueryRequest,
    RefineMethod,
    RegisterRequest,
    RejectedInputError,
    SignMethod,
    SliceReply,
    SliceRequest,
    VertexCountMismatchError,
    WorkerInfo,
    WorkerTimeoutError,
    WorkerUnavailableError,
    check_sizes,
    decode,
    encode,
    error_for_code,
    zenoh_config,
    zenoh_message,
)

M = TypeVar("M", bound=Message)

log = logging.getLogger("badf.client")


class Client:
    """A connection to the badf workers behind a Zenoh router (by default the embedded one of `badf serve`).

    Use as a context manager, or call `close()` (clients still open when the interpreter exits are closed
    then, and one dropped without it when it is collected). Like a file, it closes at the end of any `with`
    block on it, an inner one included. `connect` is a router's endpoint or a list of them, tried in turn
    until one answers. `timeout` (seconds) bounds connecting (all of the list) and is the default for every
    call; `namespace` must match the workers'. `config_file` is a Zenoh JSON5 file (TLS, authentication)
    used as the base configuration. `limits` bound the replies taken and the requests sent: a request past
    them is refused before it goes (the workers' defaults are the same).
    """

    def __init__(
        self,
        connect: str | Sequence[str] = DEFAULT_ENDPOINT,
        *,
        namespace: str = "badf",
        timeout: float = 10.0,
        config_file: str | None = None,
        limits: Limits = DEFAULT_LIMITS,
    ) -> None:
        endpoints = [connect] if isinstance(connect, str) else connect
        if not isinstance(endpoints, (list, tuple)) or not endpoints:
            raise InvalidOptionError(f"connect must be an endpoint like {DEFAULT_ENDPOINT} or a non-empty list of "
                                     f"them, got {connect!r}")
        endpoints = list(endpoints)
        if not isinstance(limits, Limits):
            raise InvalidOptionError(f"limits must be a badf.protocol.Limits, got {limits!r}")
        self.keys = KeySpace(namespace)
        self.timeout = timeout_seconds(timeout)
        self.limits = limits
        self._session = _open_session(endpoints, config_file, self.timeout)
        self._publishers: dict[str, zenoh.Publisher] = {}
        # one thread at a time uses the publishers: Zenoh refuses a publisher that another thread is putting
        # through ("Already borrowed"), which made close() or delete() beside a streaming thread raise
        self._publishing = threading.Lock()
        self._lock = threading.Lock()
        self._live: set[str] = set()  # workers whose liveliness token this client sees
        self._gone: set[str] = set()  # workers whose liveliness token this client saw go (and not come back)
        # how often each worker's token was seen to go: a handle belongs to one life of its worker, as a
        # worker started again under the same id (the same token) holds none of the last one's objects
        self._deaths: dict[str, int] = {}
        self._cancellations: dict[str, zenoh.CancellationToken] = {}  # per worker, for requests in flight
        # Zenoh holds the callback for as long as the session lives, so it must not hold the client: a client
        # dropped without close() would never be collected, and kept its session and threads until exit
        # (tenth outside check). The finalizer closes the session once the client is collected.
        self._liveliness = self._session.liveliness().declare_subscriber(
            self.keys.every_worker_token, _weak_callback(self, Client._on_liveliness), history=True
        )
        self._finalizer = weakref.finalize(
            self, _close_session, self._session, self._liveliness, self._publishers, self._publishing
        )
        _OPEN_CLIENTS.add(self)

    def __enter__(self) -> Client:
        self._check_open()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the Zenoh session; objects on the workers stay. Never raises: a link that no longer moves
        (a worker stopped with frames queued towards it) can make Zenoh's close time out, after 10 s, with
        an error that would otherwise end a `with Client(...)` block with a raw `zenoh.ZError`. A client
        dropped without it is closed when it is collected."""
        self._finalizer()

    # --- objects -------------------------------------------------------------------------------------

    def register(
        self,
        name: str,
        vertices: np.ndarray,
        faces: np.ndarray,
        *,
        depth: int = 7,
        sign: SignMethod = "auto",
        band: float | None = None,
        coherence: bool = True,
        refine: RefineMethod = "surface",
        halo: int = 1,
        region=None,
        bvh: BvhShape = "auto",
        rigid: RigidMode = "auto",
        frame: int = 0,
        replace: bool = False,
        worker: str | None = None,
        timeout: float | None = None,
    ) -> RemoteObject:
        """Create object `name` from (N, 3) vertices and (M, 3) faces (indices into the vertices).

        Placed on `worker`, or on the least-loaded worker; an existing object of that name is an
        ObjectExistsError unless `replace`. `frame` numbers the initial vertices. Blocks until the worker
        has built the field; see ObjectOptions for depth, sign, band, coherence, refine, halo, region, bvh and
        rigid.
        """
        options = ObjectOptions(depth=depth, sign=sign, band=band, coherence=coherence, refine=refine, halo=halo,
                                region=region, bvh=bvh, rigid=rigid)
        request = RegisterRequest(name, vertices, faces, options, frame=frame, replace=replace)
        info = self._register(request, worker=worker, timeout=timeout)
        return RemoteObject(self, info, vertices=_owned(request.vertices, vertices), faces=_owned(request.faces, faces))

    def _register(self, request: RegisterRequest, *, worker: str | None, timeout: float | None) -> ObjectInfo:
        target = self._place(request.name, replace=request.replace, worker=worker, timeout=timeout)
        info = self._ask(self.keys.worker_register(target), request, ObjectInfo, timeout=timeout, worker=target)
        # after replace=True too: where the name was not there, it was placed as a new one, and races alike
        self._settle_a_double_registration(info, timeout)
        return info

    def _settle_a_double_registration(self, mine: ObjectInfo, timeout: float | None) -> None:
        """Two clients registering one new name on two workers at once can both succeed (placement's check is a
        query before the registration, not a lock), and the name was then served twice: each handle's requests
        met the other worker's refusals, and neither was usable (twenty-eighth outside check). The registration
        on the lowest worker id keeps the name; any other is withdrawn by whichever client sees it, and a client
        whose own registration is withdrawn gets ObjectExistsError."""
        key = self.keys.object_info(mine.name)
        served: list[ObjectInfo] = []
        for reply in self._get(key, InfoRequest(mine.name), timeout=timeout, fan_out=True):
            try:
                served.append(self._read_reply(reply, ObjectInfo, key, timeout))
            except BadfError:
                continue  # a worker that cannot say: it does not hold the name for this purpose
        if len({(info.worker, info.registration) for info in served}) <= 1:
            return
        keeper = min(served, key=lambda info: info.worker)
        for other in served:
            if (other.worker, other.registration) == (keeper.worker, keeper.registration):
                continue
            try:
                self._ask(self.keys.object_delete(mine.name), DeleteRequest(mine.name, registration=other.registration),
                          Deleted, timeout=timeout, worker=other.worker, name=mine.name,
                          registration=other.registration)  # fmt: skip
            except BadfError:
                pass  # withdrawn already, by the client that registered it, or its worker went
        if (mine.worker, mine.registration) != (keeper.worker, keeper.registration):
            raise ObjectExistsError(
                f"object {mine.name!r} was registered on worker {keeper.worker} at the same moment; this "
                f"registration on worker {mine.worker} was withdrawn"
            )

    def object(self, name: str, *, timeout: float | None = None) -> RemoteObject:
        """A handle on an existing object (registered by any client); ObjectNotFoundError if there is none."""
        info = self._find(name, timeout=timeout)
        if info is None:
            raise self._nobody_answered(self.keys.object_info(name), name=name, worker=None, timeout=timeout)
        return RemoteObject(self, info, vertices=None, faces=None)

    def objects(self, *, timeout: float | None = None) -> list[ObjectInfo]:
        """Every object of every worker in the namespace, sorted by name: of the workers that answer, so empty
        where none does, whether none runs or this client is cut off from them (`register` raises then)."""
        infos = self._ask_all(self.keys.every_object_info, InfoRequest(), ObjectInfo, timeout=timeout)
        return sorted(infos, key=lambda info: info.name)

    def workers(self, *, timeout: float | None = None) -> list[WorkerInfo]:
        """Every worker in the namespace, with its load, sorted by id: those that answer, so empty where none
        does, whether none runs or this client is cut off from them."""
        infos = self._ask_all(self.keys.every_worker_info, InfoRequest(), WorkerInfo, timeout=timeout)
        return sorted(infos, key=lambda info: info.worker)

    def _find(self, name: str, *, timeout: float | None) -> ObjectInfo | None:
        key = self.keys.object_info(name)
        for reply in self._get(key, InfoRequest(name), timeout=timeout):
            return self._read_reply(reply, ObjectInfo, key, timeout)
        return None

    def _place(self, name: str, *, replace: bool, worker: str | None, timeout: float | None) -> str:
        existing = self._find(name, timeout=timeout)
        if existing is not None:
            if not replace:
                raise ObjectExistsError(
                    f"object {name!r} already exists on worker {existing.worker}; pass replace=True to swap it"
                )
            if worker is not None and worker != existing.worker:
                raise ObjectExistsError(
                    f"object {name!r} lives on worker {existing.worker}, not {worker}; replace it there"
                )
            return existing.worker
        if worker is not None:
            return worker
        workers = self.workers(timeout=timeout)
        if not workers:
            raise WorkerUnavailableError(
                f"no badf worker answered in namespace {self.keys.namespace!r}; is `badf serve` running?"
            )
        least_loaded = min(
            workers, key=lambda info: (info.face_count, info.requests_waiting, info.object_count, info.worker)
        )
        return least_loaded.worker

    # --- the workers' liveliness -------------------------------------------------------------------

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        worker = str(sample.key_expr).rsplit("/", 1)[-1]
        cancellation = None
        with self._lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._live.discard(worker)
                self._gone.add(worker)
                self._deaths[worker] = self._deaths.get(worker, 0) + 1
                cancellation = self._cancellations.pop(worker, None)
            else:
                self._live.add(worker)
                self._gone.discard(worker)
        if cancellation is not None:
            cancellation.cancel()  # the requests in flight to that worker end now, with no reply

    def _worker_gone(self, worker: str, life: int | None = None) -> bool:
        """Whether the client has seen `worker` go; with `life` (a handle's `_life`), also whether it has
        seen it go since that life began, though it came back."""
        with self._lock:
            return worker in self._gone or (life is not None and self._deaths.get(worker, 0) != life)

    def _gone_error(self, worker: str, name: str | None) -> WorkerUnavailableError:
        """The error for a worker this client has seen go, saying whether it has come back since."""
        with self._lock:
            back = worker in self._live
        return _worker_gone_error(worker, name, seen_going=True, back=back)

    def _life(self, worker: str) -> int:
        """The current life of `worker`, as handles on its objects remember it."""
        with self._lock:
            return self._deaths.get(worker, 0)

    def _cancellation(self, worker: str) -> zenoh.CancellationToken:
        """The token that cancels requests to `worker` when its liveliness token goes (a fresh one per life)."""
        with self._lock:
            token = self._cancellations.get(worker)
            if token is None:
                token = self._cancellations[worker] = zenoh.CancellationToken()
            return token

    def _check_worker(self, worker: str, name: str | None, life: int | None = None) -> None:
        """Raise at once, without a round trip, when the client has seen `worker` go (since `life`)."""
        if self._worker_gone(worker, life):
            raise self._gone_error(worker, name)

    # --- requests ----------------------------------------------------------------------------------

    def _get(
        self,
        key: str,
        request: Message,
        *,
        timeout: float | None,
        fan_out: bool = False,
        cancellation: zenoh.CancellationToken | None = None,
    ) -> zenoh.Handler:
        seconds = self.timeout if timeout is None else timeout_seconds(timeout)
        self._check_open()
        check_sizes(request, self.limits)
        try:
            return self._session.get(
                key,
                payload=encode(request),
                timeout=seconds,
                consolidation=zenoh.ConsolidationMode.NONE if fan_out else None,
                cancellation_token=cancellation,
            )
        except zenoh.ZError as error:
            raise WorkerUnavailableError(f"cannot send a request on {key}: {zenoh_message(error)}") from None

    def _ask(
        self,
        key: str,
        request: Message,
        expect: type[M],
        *,
        timeout: float | None,
        worker: str,
        name: str | None = None,
        life: int | None = None,
        registration: int | None = None,
    ) -> M:
        """The one reply of `worker` to `request` on `key`, decoded as `expect`, or the error it carries;
        `life` (a handle's) makes a worker that went since then, even if back, count as gone, and
        `registration` (a handle's) an object registered again since then a different object."""
        self._check_worker(worker, name, life)
        try:
            # a handle's request takes every reply, not one consolidated: should two workers serve the name for
            # a moment (see _settle_a_double_registration), the other one's refusal must not hide its own answer
            replies = self._get(key, request, timeout=timeout, cancellation=self._cancellation(worker),
                                fan_out=registration is not None)  # fmt: skip
        except WorkerUnavailableError:
            if self._worker_gone(worker, life):  # its token went as the request left: "Query was cancelled"
                raise self._gone_error(worker, name) from None
            raise
        refused: BadfError | None = None
        for reply in replies:
            try:
                return self._read_reply(reply, expect, key, timeout)
            except BadfError as error:
                # a request cancelled because its worker went may end in Zenoh's error reply ("Query was
                # cancelled") rather than with no reply, and one that reached the worker's next life finds
                # no such object: the same news either way
                if self._worker_gone(worker, life):
                    raise self._gone_error(worker, name) from None
                if (name is not None and type(error) is WorkerUnavailableError and reply.ok is None
                        and _is_error_reply(reply.err.payload.to_bytes())):
                    # the object's worker answered UNAVAILABLE (not Zenoh: "Query was cancelled" from a worker
                    # still alive stays WorkerUnavailableError): it is shutting down, and its token goes next. A
                    # handle's caller recovers from ObjectUnavailableError, as after a kill (thirty-sixth outside
                    # check: a SIGTERM's refusals escaped `except ObjectUnavailableError: reregister()`)
                    error = ObjectUnavailableError(
                        f"object {name!r} is unavailable: {error.message}. Its worker takes the object's state "
                        "with it: once the handle's `available` turns False (its liveliness token goes, within "
                        "moments), reregister() restores the object on another worker")
                if registration is None:
                    raise error from None
                refused = refused or error
        if refused is not None:
            raise refused
        if self._worker_gone(worker, life):
            raise self._gone_error(worker, name)
        raise self._nobody_answered(key, name=name, worker=worker, timeout=timeout, registration=registration)

    def _ask_all(self, key: str, request: Message, expect: type[M], *, timeout: float | None) -> list[M]:
        """Every worker's reply. A worker that fails to answer (hung, or its reply cut off) is left out, with
        a warning, as long as another answered: one stopped worker made workers(), objects() and placement
        fail for the whole deployment, the others' replies thrown away (twelfth outside check)."""
        answers: list[M] = []
        errors: list[BadfError] = []
        for reply in self._get(key, request, timeout=timeout, fan_out=True):
            try:
                answers.append(self._read_reply(reply, expect, key, timeout))
            except BadfError as error:
                errors.append(error)
        if errors and not answers:
            raise errors[0]
        for error in errors:
            log.warning("left out of the answers on %s: %s", key, error)
        return answers

    def _read_reply(self, reply: zenoh.Reply, expect: type[M], key: str, timeout: float | None) -> M:
        if reply.ok is not None:
            return decode(reply.ok.payload.to_bytes(), expect, limits=self.limits)
        raise self._reply_error(reply.err.payload.to_bytes(), key, timeout)

    def _reply_error(self, data: bytes, key: str, timeout: float | None) -> BadfError:
        try:
            error = decode(data, ErrorReply, limits=self.limits)
        except MessageError:
            text = data.decode("utf-8", "replace")
            if text.strip().lower() == "timeout":
                seconds = self.timeout if timeout is None else timeout
                return WorkerTimeoutError(f"no answer on {key} within {seconds:g} s")
            return WorkerUnavailableError(f"Zenoh error on {key}: {text[:200]}")
        return error_for_code(error.code, error.message)

    def _nobody_answered(self, key: str, *, name: str | None, worker: str | None, timeout: float | None,
                         registration: int | None = None) -> BadfError:
        """Why no queryable answered: the worker is gone, there is no worker, there is no such object (or,
        for a handle's `registration`, not that registration of it: deleted or replaced and registered again
        while the request was on its way), or the request was not delivered although the worker and the
        object answer their info (access control)."""
        if worker is not None and not self._is_alive(worker, timeout):
            return _worker_gone_error(worker, name, seen_going=self._worker_gone(worker))
        if worker is None and not self._live and not self.workers(timeout=timeout):
            return WorkerUnavailableError(f"no badf worker is reachable in namespace {self.keys.namespace!r}")
        if name is not None:
            found = self._find(name, timeout=timeout) if key != self.keys.object_info(name) else None
            if found is not None and registration is not None and found.registration != registration:
                # not access control: the object went while the request was on its way, and another
                # registration of the name answers now (twelfth outside check: 29 to 277 false denials in 12 s)
                return ObjectNotFoundError(
                    f"object {name!r} was deleted or replaced while the request was on its way, and is registered "
                    "again: take a handle on the new registration (Client.object(name))")
            if found is not None:
                return AccessDeniedError(f"object {name!r} answers its info but nobody answered on {key}: {_DENIED}")
            return ObjectNotFoundError(
                f"no object {name!r} in namespace {self.keys.namespace!r} (deleted, or never registered)"
            )
        if worker is not None:  # it answered its info in _is_alive
            return AccessDeniedError(f"worker {worker} answers its info but nobody answered on {key}: {_DENIED}")
        return WorkerUnavailableError(f"nobody answered on {key}")

    def _is_alive(self, worker: str, timeout: float | None) -> bool:
        """False once the liveliness subscriber has seen `worker` go; otherwise whether `worker` answers an
        info request. A request to a worker that dies ends as soon as the router sees its connection close,
        which can be before this client hears of the token going, so `_live` alone would call the object
        not found; and a liveliness get is no substitute: with a liveliness subscriber on the session,
        Zenoh 1.10 was seen here to answer it with no tokens for a while. Only the worker's own answers
        count (its info, or an ErrorReply): when the router the client reached was that worker and it died,
        Zenoh itself answers the info request with an error ("Timeout"), which says nobody is there."""
        if self._worker_gone(worker):
            return False
        try:
            replies = self._get(
                self.keys.worker_info(worker), InfoRequest(), timeout=timeout, cancellation=self._cancellation(worker)
            )
        except WorkerUnavailableError:
            if self._worker_gone(worker):  # its token went as the request left: "Query was cancelled"
                return False
            raise
        return any(reply.ok is not None or _is_error_reply(reply.err.payload.to_bytes()) for reply in replies)

    def _check_open(self) -> None:
        if self._session.is_closed():
            raise WorkerUnavailableError("this client is closed; open a new Client")

    def _put(self, key: str, message: Message) -> None:
        """Put `message` through the key's publisher (declared on first use), checked against the limits as
        `_get` checks a request."""
        self._check_open()
        check_sizes(message, self.limits)
        payload = encode(message)
        with self._publishing:
            publisher = self._publishers.get(key)
            if publisher is None:
                publisher = self._session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                self._publishers[key] = publisher
            publisher.put(payload)

    def _drop_publisher(self, key: str) -> None:
        with self._publishing:
            publisher = self._publishers.pop(key, None)
            if publisher is not None:
                publisher.undeclare()


class RemoteObject:
    """An object on a worker. Keeps what a re-registration needs: faces, options and the last vertices sent
    (faces and vertices are None for a handle from `Client.object`, which did not register it).

    Once its worker is gone (`available` turns False within milliseconds of the worker's liveliness token
    going), every call raises ObjectUnavailableError; `reregister()` restores the object elsewhere. If the
    token comes back with the worker still serving the same registration (a router restart), calls work
    again. A handle is on one registration of its name: once that is deleted, or replaced by a registration
    with replace=True (another client's, say), its queries, slices, info, mesh and delete raise
    ObjectNotFoundError and its frames StaleFrameError, rather than reach the other mesh;
    `Client.object(name)` gives a handle on the new one."""

    def __init__(
        self, client: Client, info: ObjectInfo, *, vertices: np.ndarray | None, faces: np.ndarray | None
    ) -> None:
        self._client = client
        self.name = info.name
        self._adopt(info)
        self._vertices = vertices
        self._faces = faces

    def _adopt(self, info: ObjectInfo) -> None:
        self.worker = info.worker
        self._life = self._client._life(info.worker)  # see Client._deaths
        self.vertex_count = info.vertex_count
        self.face_count = info.face_count
        self.options = info.options
        self._registration = info.registration  # which registration of the name this handle is on
        self._frame = info.frame
        self._vertices_frame = info.frame  # the number of the frame whose vertices this handle keeps
        self._deleted = False  # set by delete(); a reregister() serves the object again

    def __repr__(self) -> str:
        return f"RemoteObject({self.name!r}, worker={self.worker!r}, frame={self._frame})"

    @property
    def frame(self) -> int:
        """The newest frame number this handle knows of: the last it sent, or the last a reply named."""
        return self._frame

    @property
    def available(self) -> bool:
        """False once this client has seen the object's worker go (its liveliness token), or was closed; no
        round trip. If the worker comes back still serving the object (a router restart), the handle's
        next call takes it up again, and this turns True."""
        return not self._client._session.is_closed() and not self._client._worker_gone(self.worker, self._life)

    @property
    def vertices(self) -> np.ndarray | None:
        """(N, 3) float32, or float64 as given: the last vertices this handle sent (registered, updated or
        streamed)."""
        return self._vertices

    @property
    def faces(self) -> np.ndarray | None:
        """(M, 3) int32: the topology this handle registered."""
        return self._faces

    def update(self, vertices: np.ndarray, *, timeout: float | None = None) -> int:
        """Send (N, 3) vertices as the next frame and wait until the worker has applied it; returns its number.
        A frame that fails (refused, or its worker gone) uses up its number, but `vertices`, which a
        re-registration restores, stay the last ones before it."""
        kept = self._vertices, self._vertices_frame
        frame = self._next_frame(vertices)
        try:
            ack = self._ask(self._client.keys.object_frame(self.name), frame, FrameAck, timeout)
        except BadfError:
            self._vertices, self._vertices_frame = kept
            raise
        self._saw(ack.frame)
        return ack.frame

    def stream(self, vertices: np.ndarray) -> int:
        """Send (N, 3) vertices as the next frame without waiting; returns its number. The worker applies
        the newest frame it has and drops older pending ones (see `info().frames_dropped`). Raises
        ObjectUnavailableError once the client has seen the object's worker go (a frame sent in the few
        milliseconds before that is lost without a word), and ObjectNotFoundError after `delete()` on this
        handle. A frame streamed to an object that another client deleted is dropped by the router unseen:
        `update()` waits for the worker's answer instead. So is a frame the worker refuses (one whose used
        vertices span more than 0 but less than 1e-40; a frame collapsed to one point keeps the last frame's
        cube), which still becomes the vertices `reregister()` sends; a wrong shape,
        NaN, Inf and coordinates past +-1e18 are refused here, before the frame is kept."""
        if self._deleted:
            raise ObjectNotFoundError(f"{self.name!r} was deleted through this handle; reregister() serves it again")
        # a frame that fails to go uses up its number, as in update(), but is not kept for reregister(): a
        # stream() that raised had made its vertices the ones reregister() put back (tenth outside check)
        kept = self._vertices, self._vertices_frame
        frame = self._next_frame(vertices)
        try:
            self._rejoin_if_back()
            self._client._check_worker(self.worker, self.name, self._life)
            self._client._put(self._client.keys.object_frame(self.name), frame)
        except BaseException as error:
            self._vertices, self._vertices_frame = kept
            if isinstance(error, zenoh.ZError):
                raise WorkerUnavailableError(f"cannot stream to {self.name!r}: {zenoh_message(error)}") from None
            raise
        return frame.frame

    def query(
        self,
        points: np.ndarray,
        *,
        mode: QueryMode = "adf",
        outputs: Sequence[QueryOutput] = ("distance",),
        timeout: float | None = None,
    ) -> QueryReply:
        """Evaluate the field at (P, 3) points, from the ADF ("adf") or exactly ("exact").

        The reply holds the outputs asked for: distance (P,) float32, signed, negative inside;
        closest_point (P, 3); normal (P, 3); face (P,) int32; and `frame`, the frame that answered.
        Its arrays are read-only views of the received message (copy them to change them).
        """
        if isinstance(outputs, str):
            outputs = (outputs,)  # "distance" as the engine takes it
        elif not isinstance(outputs, (list, tuple)):
            raise InvalidOptionError(f"outputs must be a sequence of {', '.join(QUERY_OUTPUTS)}, got {outputs!r}")
        request = QueryRequest(self.name, points, mode=mode, outputs=outputs,  # type: ignore[arg-type]
                               registration=self._registration)
        reply = self._ask(self._client.keys.object_query(self.name), request, QueryReply, timeout)
        self._saw(reply.frame)
        return reply

    def slice(
        self,
        axis: str | int,
        position: float,
        *,
        resolution: int = 256,
        levels: tuple[int, int] | None = None,
        cells: bool = True,
        corners: bool = False,
        timeout: float | None = None,
    ) -> SliceReply:
        """Signed distances on the plane `axis` = `position` and the octree cells it crosses (SliceRequest).
        `axis` is "x", "y" or "z", or 0, 1 or 2 as the engine's `DistanceField.slice` takes it."""
        if isinstance(axis, (int, np.integer)) and not isinstance(axis, (bool, np.bool_)) and 0 <= axis <= 2:
            axis = "xyz"[int(axis)]
        request = SliceRequest(
            self.name, axis, position, resolution=resolution, levels=levels, cells=cells, corners=corners,
            registration=self._registration,
        )  # type: ignore[arg-type]
        reply = self._ask(self._client.keys.object_slice(self.name), request, SliceReply, timeout)
        self._saw(reply.frame)
        return reply

    def info(self, *, timeout: float | None = None) -> ObjectInfo:
        """The worker's report on this object: frame, counters, the engine's info and stats."""
        request = InfoRequest(self.name, registration=self._registration)
        info = self._ask(self._client.keys.object_info(self.name), request, ObjectInfo, timeout)
        self._saw(info.frame)
        return info

    def mesh(self, *, faces: bool = True, timeout: float | None = None) -> MeshReply:
        """The object's newest applied vertices (N, 3) and their `frame`, and its faces (M, 3) when `faces`
        (they change only when the object is re-registered: leave them out when polling). The arrays are
        read-only views of the received message."""
        request = MeshRequest(self.name, faces, registration=self._registration)
        reply = self._ask(self._client.keys.object_mesh(self.name), request, MeshReply, timeout)
        self._saw(reply.frame)
        return reply

    def reregister(self, *, worker: str | None = None, timeout: float | None = None) -> ObjectInfo:
        """Register the object again from what this handle kept: its faces, options and the last vertices it
        sent, numbered as the frame that sent them, or, if a later number went out or was seen (an update
        that failed or timed out), the next number (later frames keep counting up). Placed on `worker`, or on
        the least-loaded worker; the handle then points there. For an object whose worker is gone
        (ObjectUnavailableError). ObjectExistsError if the object is still served (by its worker, or
        registered again by another client: `Client.object(name)` finds it); NotSupportedError for a handle
        from `Client.object`, which keeps no topology."""
        if self._faces is None or self._vertices is None:
            raise NotSupportedError(
                f"this handle on {self.name!r} came from Client.object and keeps no faces or vertices; "
                "register the object with Client.register"
            )
        # A frame number names one geometry: the kept vertices keep their frame's number, unless a later
        # number went out (an update that failed or timed out, and may have been applied as the worker went)
        # or came back from a reply; then they take a new one.
        frame = self._frame if self._vertices_frame == self._frame else self._frame + 1
        request = RegisterRequest(self.name, self._vertices, self._faces, self.options, frame=frame)
        try:
            info = self._client._register(request, worker=worker, timeout=timeout)
        except ObjectExistsError:
            # the placement's message advises replace=True, which reregister() does not take (thirteenth
            # outside check)
            raise ObjectExistsError(
                f"{self.name!r} is still served (this registration, or one made since): reregister() restores "
                "an object whose worker is gone; Client.object(name) gives a handle on what is served, and "
                "Client.register(..., replace=True) swaps it") from None
        except RejectedInputError as error:
            # a frame the worker takes can be one a registration cannot (all vertices at one point), and a
            # streamed frame the worker refused is still the one kept (seventeenth outside check)
            raise RejectedInputError(
                f"reregister() sends the last vertices this handle sent (frame {self._vertices_frame}), and the "
                f"worker refuses them as a new registration: {error.message}; register the object again with "
                "Client.register and vertices it takes") from None
        self._adopt(info)
        return info

    def delete(self, *, timeout: float | None = None) -> int:
        """Delete the object on its worker; returns its last applied frame."""
        request = DeleteRequest(self.name, registration=self._registration)
        deleted = self._ask(self._client.keys.object_delete(self.name), request, Deleted, timeout)
        self._client._drop_publisher(self._client.keys.object_frame(self.name))
        self._deleted = True
        return deleted.frame

    def _ask(self, key: str, request: Message, expect: type[M], timeout: float | None) -> M:
        self._rejoin_if_back()
        return self._client._ask(key, request, expect, timeout=timeout, worker=self.worker, name=self.name,
                                 life=self._life, registration=self._registration)

    def _rejoin_if_back(self) -> None:
        """Take the worker's new life when its token went and came back but the worker still serves this
        registration of the object: a router restart, or a network cut, ends every token without ending a
        worker. Left as it is otherwise (a worker restarted, the object registered again): the call then
        raises ObjectUnavailableError."""
        client = self._client
        life = client._life(self.worker)
        if life == self._life or client._worker_gone(self.worker):
            return
        try:
            info = client._ask(client.keys.object_info(self.name), InfoRequest(self.name), ObjectInfo,
                               timeout=None, worker=self.worker, name=self.name, life=life)  # fmt: skip
        except BadfError:
            return
        if info.worker == self.worker and info.registration == self._registration:
            self._life = life

    def _next_frame(self, vertices: np.ndarray) -> Frame:
        frame = Frame(self.name, self._frame + 1, vertices, registration=self._registration)
        _check_coordinates(frame.vertices)
        if len(frame.vertices) != self.vertex_count:
            raise VertexCountMismatchError(
                f"{self.name} has {self.vertex_count} vertices as this handle registered or found it; got "
                f"{len(frame.vertices)} (if it was registered again since, with replace=True, take the new "
                "handle, or Client.object(name))"
            )
        self._frame = self._vertices_frame = frame.frame
        self._vertices = _owned(frame.vertices, vertices)
        return frame

    def _saw(self, frame: int) -> None:
        self._frame = max(self._frame, frame)


def _open_session(endpoints: list[str], config_file: str | None, timeout: float) -> zenoh.Session:
    """A client session to the first of `endpoints` that answers within `timeout` seconds in all.

    With a connect timeout, Zenoh (1.10.2) in client mode fails to open whenever the first endpoint of its
    list cannot be reached, however long the timeout (eclipse-zenoh/zenoh#1602; seventeenth outside check:
    a client given [a router that is down, one that serves] never connected). So each endpoint in turn leads
    the list, for an equal share of what is left of the timeout; the session keeps the whole list."""
    deadline = time.monotonic() + timeout
    error: zenoh.ZError | None = None
    for k in range(len(endpoints)):
        share = max(0.001, (deadline - time.monotonic()) / (len(endpoints) - k))
        config = zenoh_config(mode="client", connect=endpoints[k:] + endpoints[:k], config_file=config_file,
                              connect_timeout_s=share)
        try:
            return zenoh.open(config)
        except zenoh.ZError as failed:
            error = failed
    raise WorkerUnavailableError(
        f"cannot reach a Zenoh router at {', '.join(endpoints)}: {zenoh_message(error)}") from None


def _check_coordinates(vertices: np.ndarray) -> None:
    """Refuses, as the worker would, a frame's coordinate past the engine's +-MAX_COORDINATE, before the frame
    is sent or kept: stream() sent such a frame unchecked, the worker refused it unseen, and it became the
    vertices reregister() sends, which the worker then refused (seventeenth outside check)."""
    if vertices.size and not (vertices.min() >= -MAX_COORDINATE and vertices.max() <= MAX_COORDINATE):
        raise RejectedInputError(
            f"vertices must lie within +-{MAX_COORDINATE:g}, got a coordinate of {float(np.abs(vertices).max()):g}")


# Clients not closed yet. At the interpreter's exit, before it waits for threads, they are closed: the
# thread that Zenoh runs the liveliness callback on is one it waits for, so a script that never closed its
# client did not exit (tenth outside check).
_OPEN_CLIENTS: weakref.WeakSet[Client] = weakref.WeakSet()


def _weak_callback(client: Client, method):
    """`method` of `client` as a callback that does not keep the client alive."""
    ref = weakref.ref(client)

    def callback(sample: zenoh.Sample) -> None:
        target = ref()
        if target is not None:
            method(target, sample)

    return callback


def _close_session(session: zenoh.Session, liveliness, publishers: dict, publishing: threading.Lock) -> None:
    """Close a client's session (its `close()`, or its finalizer once it is collected). A client collected on
    one of Zenoh's own threads (its last reference dropped in a callback) has its session closed on a thread
    of its own, since Zenoh would wait there for the very thread it runs on."""
    if isinstance(threading.current_thread(), threading._DummyThread):  # type: ignore[attr-defined]
        threading.Thread(target=_close_session, args=(session, liveliness, publishers, publishing),
                         name="badf-client-close", daemon=True).start()
        return
    if session.is_closed():
        return
    with publishing:
        try:
            liveliness.undeclare()
            for publisher in publishers.values():
                publisher.undeclare()
        except zenoh.ZError as error:
            log.warning("closing the client's Zenoh session: %s", zenoh_message(error))
        publishers.clear()
        try:
            session.close()
        except zenoh.ZError as error:
            log.warning("closing the client's Zenoh session: %s", zenoh_message(error))


def _close_open_clients() -> None:
    for client in list(_OPEN_CLIENTS):
        client.close()


threading._register_atexit(_close_open_clients)  # type: ignore[attr-defined]  # runs before the thread joins


def _is_error_reply(data: bytes) -> bool:
    """Whether an error reply is a worker's ErrorReply, rather than Zenoh's own (a timeout, say)."""
    try:
        decode(data, ErrorReply)
    except MessageError:
        return False
    return True


_DENIED = (
    "the request was not delivered, as Zenoh's access control does to what this client's user is not allowed "
    "(the router's --config file)"
)


def _worker_gone_error(worker: str, name: str | None, *, seen_going: bool, back: bool = False) -> WorkerUnavailableError:
    if name is None:
        if seen_going:
            return WorkerUnavailableError(f"worker {worker} is gone: its liveliness token went away")
        return WorkerUnavailableError(
            f"worker {worker} does not answer: not started, gone, or not yet visible through the routers"
        )
    how = "went away and came back (a new start under the same id)" if back else "is gone"
    return ObjectUnavailableError(
        f"object {name!r} is unavailable: its worker {worker} {how}: its liveliness token went away (a worker "
        "that ended, or one stalled or cut off past Zenoh's lease). A worker that ended took the object's state "
        "with it: register it again, e.g. with reregister() on a handle that registered it; one that resumes "
        "still serving it answers the handle again"
    )


# Zenoh takes timeouts in whole milliseconds of 64 bits, and Python's waits overflow long before that
MAX_TIMEOUT_S = 1.0e6


def timeout_seconds(timeout: object, *, what: str = "timeout") -> float:
    """A timeout as float seconds: a positive number up to MAX_TIMEOUT_S, else InvalidOptionError (a
    ValueError and a BadfError) saying what came (1e300 was a raw Zenoh error with Rust source paths, 1e20 a
    "negative timeout"); `what` names it there (a command line's flag)."""
    is_number = isinstance(timeout, (int, float, np.integer, np.floating)) and not isinstance(timeout, bool)
    if not (is_number and math.isfinite(timeout) and 0 < timeout <= MAX_TIMEOUT_S):  # type: ignore[operator]
        raise InvalidOptionError(f"{what} must be a positive number of seconds up to {MAX_TIMEOUT_S:g}, got {timeout!r}")
    return float(timeout)  # type: ignore[arg-type]


def _owned(canonical: np.ndarray, given: object) -> np.ndarray:
    """`canonical` (a message's array), copied when it is still the caller's own array, which may change."""
    return canonical.copy() if canonical is given else canonical
