"""Processes: a worker (`run_worker`), a router alone (`run_router`), and a router with one worker process
per GPU (`run_gpu_workers`), each with logging and SIGINT/SIGTERM handling, running until a signal comes;
and `worker_process` / `router_process`, which run one as a child process (tests, benchmarks, the demo)."""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
import multiprocessing.connection
import signal
import socket
import sys
import threading
import time
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Protocol, Sequence

import zenoh

from badf.protocol import WorkerUnavailableError
from badf.server._router import RouterSettings, listen_endpoints, log_worker_changes
from badf.server._worker import WorkerSettings, engine_field_builder, serve

log = logging.getLogger("badf.server")

_SPAWN = multiprocessing.get_context("spawn")  # a forked child of a process with a Zenoh session hangs


class _Settable(Protocol):
    def set(self) -> None: ...


def run_worker(settings: WorkerSettings, ready: _Settable | None = None) -> int:
    """Run a worker in this process's main thread until SIGINT or SIGTERM; returns the exit status.

    `ready` (for instance a multiprocessing Event) is set once the worker's keys and liveliness token are
    declared. Exit status 1: the Zenoh session could not be opened (a taken port, a bad config file);
    2: the engine or the device is unavailable.
    """
    _configure_logging()
    stop = _stop_on_signals()
    try:
        build_field, device = engine_field_builder(settings.device)
    except ImportError as error:
        log.error("the distance-field engine is not available: %s", error)
        return 2
    except ValueError as error:
        log.error("cannot use device %r: %s", settings.device, error)
        return 2
    session = _open(settings.zenoh_config())
    if session is None:
        return 1
    with session:
        serve(
            session,
            settings,
            stop=stop,
            build_field=build_field,
            device=device,
            on_ready=None if ready is None else (lambda _worker: ready.set()),
        )
    return 0


def run_router(settings: RouterSettings, ready: _Settable | None = None) -> int:
    """Run a Zenoh router alone (no worker, no Warp) until SIGINT or SIGTERM; returns the exit status
    (1: the session could not be opened). Logs the workers of its namespace as they join and leave."""
    _configure_logging()
    stop = _stop_on_signals()
    config = settings.zenoh_config()
    session = _open(config)
    if session is None:
        return 1
    with session:
        watcher = log_worker_changes(session, settings.namespace)
        log.info("router listening on %s", ", ".join(listen_endpoints(config)) or "no endpoint")
        if ready is not None:
            ready.set()
        stop.wait()
        watcher.undeclare()
    log.info("router stopped")
    return 0


def run_gpu_workers(settings: WorkerSettings, gpus: Sequence[int], *, start_timeout_s: float = 900.0) -> int:
    """A router in this process and, for each GPU index N, a worker process on cuda:N connected to it.

    The router listens where `settings` says (see RouterSettings) and joins `settings.connect`; the workers
    reach it on a private loopback port and listen nowhere themselves. Worker N's id is
    `{settings.worker_id}-cuda{N}`. Runs until SIGINT or SIGTERM, then stops the workers and the router
    (status 0). A worker that fails to start stops everything with its status (1: Zenoh, 2: engine or
    device); one that exits later is logged and the others keep serving, until none is left (status 1).
    """
    _configure_logging()
    stop = _stop_on_signals()
    loopback = free_loopback_endpoint()
    router = RouterSettings(settings.namespace, settings.listen, settings.connect, settings.config_file)
    config = router.zenoh_config(extra_listen=(loopback,))
    session = _open(config)
    if session is None:
        return 1
    workers = {
        f"cuda:{index}": dataclasses.replace(
            settings,
            worker_id=f"{settings.worker_id}-cuda{index}",
            device=f"cuda:{index}",
            mode="router",
            listen=(),
            connect=(loopback,),
        )
        for index in gpus
    }
    with session:
        watcher = log_worker_changes(session, settings.namespace)
        log.info("router listening on %s", ", ".join(listen_endpoints(config)))
        status = _supervise(workers, stop, start_timeout_s)
        watcher.undeclare()
    log.info("router stopped")
    return status


def _supervise(workers: dict[str, WorkerSettings], stop: threading.Event, start_timeout_s: float) -> int:
    """Start a process per worker, wait until all are ready, then until `stop` or until none is left."""
    children = {device: _spawn(_worker_main, settings, name=f"badf-worker-{settings.worker_id}")
                for device, settings in workers.items()}  # fmt: skip
    try:
        deadline = time.monotonic() + start_timeout_s
        starting = dict(children)
        while starting and not stop.is_set():
            for device, (process, ready) in list(starting.items()):
                if ready.is_set():
                    log.info("worker %s ready on %s (pid %d)", workers[device].worker_id, device, process.pid)
                    del starting[device]
                elif not process.is_alive():
                    log.error("worker on %s exited with status %s before it was ready", device, process.exitcode)
                    return process.exitcode if process.exitcode and process.exitcode > 0 else 1
            if time.monotonic() > deadline:
                log.error("workers on %s not ready after %g s", ", ".join(starting), start_timeout_s)
                return 1
            stop.wait(0.1)
        running = {process.sentinel: device for device, (process, _) in children.items()}
        while running and not stop.is_set():
            for sentinel in multiprocessing.connection.wait(list(running), timeout=0.2):
                device = running.pop(sentinel)  # type: ignore[call-overload]
                log.error(
                    "worker %s on %s exited with status %s; the other workers keep serving",
                    workers[device].worker_id, device, children[device][0].exitcode,
                )  # fmt: skip
        return 0 if stop.is_set() else 1
    finally:
        for process, _ in children.values():
            if process.is_alive():
                process.terminate()  # all at once, so they shut down side by side
        for process, _ in children.values():
            end_process(process)


@contextmanager
def worker_process(settings: WorkerSettings, *, start_timeout_s: float = 300.0) -> Iterator[multiprocessing.Process]:
    """Run `run_worker(settings)` in a child process for the duration of the block.

    Yields once the worker is ready (Warp imported, kernels loaded, keys declared), or raises
    WorkerUnavailableError if it exits first or is not ready within `start_timeout_s`. Afterwards the
    child gets SIGTERM, and SIGKILL if it has not exited 30 s later.
    """
    with _child(_worker_main, settings, f"badf-worker-{settings.worker_id}", start_timeout_s) as process:
        yield process


@contextmanager
def router_process(settings: RouterSettings, *, start_timeout_s: float = 60.0) -> Iterator[multiprocessing.Process]:
    """Run `run_router(settings)` in a child process for the duration of the block (as `worker_process`)."""
    with _child(_router_main, settings, "badf-router", start_timeout_s) as process:
        yield process


@contextmanager
def _child(
    main: Callable[[Any, _Settable], None], settings: Any, name: str, start_timeout_s: float
) -> Iterator[multiprocessing.Process]:
    process, ready = _spawn(main, settings, name=name)
    try:
        deadline = time.monotonic() + start_timeout_s
        while not ready.wait(0.1):
            if not process.is_alive():
                raise WorkerUnavailableError(f"{name} exited with status {process.exitcode} before it was ready")
            if time.monotonic() > deadline:
                raise WorkerUnavailableError(f"{name} not ready after {start_timeout_s:g} s")
        yield process
    finally:
        end_process(process)


def _spawn(main: Callable[[Any, _Settable], None], settings: Any, *, name: str) -> tuple[multiprocessing.Process, Any]:
    ready = _SPAWN.Event()
    process = _SPAWN.Process(target=main, args=(settings, ready), name=name, daemon=True)
    process.start()
    return process, ready


def _worker_main(settings: WorkerSettings, ready: _Settable) -> None:
    sys.exit(run_worker(settings, ready))  # the exit status tells the parent why a worker did not start


def _router_main(settings: RouterSettings, ready: _Settable) -> None:
    sys.exit(run_router(settings, ready))


def end_process(process: multiprocessing.Process, *, grace_s: float = 30.0) -> None:
    """SIGTERM `process` (one this program started), then SIGKILL if it has not exited after `grace_s`."""
    if process.is_alive():
        process.terminate()
        process.join(grace_s)
    if process.is_alive():
        process.kill()
        process.join(grace_s)


def free_loopback_endpoint() -> str:
    """A Zenoh TCP endpoint on 127.0.0.1 whose port was free a moment ago."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{probe.getsockname()[1]}"


def _open(config: zenoh.Config) -> zenoh.Session | None:
    zenoh.init_log_from_env_or("error")
    try:
        return zenoh.open(config)
    except zenoh.ZError as error:
        log.error("cannot open the Zenoh session (is the port taken, or the config file wrong?): %s", error)
        return None


def _configure_logging() -> None:
    if not logging.getLogger().handlers:
        logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(asctime)s badf %(levelname)s %(message)s")


def _stop_on_signals() -> threading.Event:
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda number, _frame: stop.set())
    return stop
