"""Processes: a worker (`run_worker`), a router alone (`run_router`), and a router with worker processes
behind it (`run_workers`; `run_gpu_workers` for one per GPU), each with logging and SIGINT/SIGTERM
handling, running until a signal comes; and `worker_process`, `router_process` and `workers_process`,
which run one as a child process (tests, benchmarks, the demo)."""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
import multiprocessing.connection
import os
import socket
import sys
import threading
import time
import traceback
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Protocol, Sequence

import zenoh

from badf.protocol import InvalidOptionError, WorkerUnavailableError, zenoh_message
from badf.server._router import RouterSettings, configured_endpoints, log_worker_changes
from badf.server._signals import ignore_terminal_signals, on_stop_signals
from badf.server._worker import WorkerSettings, engine_field_builder, serve, warm_up_engine

log = logging.getLogger("badf.server")

_SPAWN = multiprocessing.get_context("spawn")  # a forked child of a process with a Zenoh session hangs


class _Settable(Protocol):
    def set(self) -> None: ...


def run_worker(settings: WorkerSettings, ready: _Settable | None = None) -> int:
    """Run a worker in this process's main thread until SIGINT or SIGTERM; returns the exit status.

    `ready` (for instance a multiprocessing Event) is set once the engine's kernels are loaded (see
    warm_up_engine) and the worker's keys and liveliness token are declared. Exit status 1: the Zenoh
    session could not be opened (a taken port, a config Zenoh refuses), or a worker of the same id already
    serves the namespace; 2: the engine or the device is unavailable. A signal while the kernels load ends it
    there, with status 0 (see _StoppedWhileLoading).
    """
    _configure_logging()
    loading = threading.Event()
    stop = _stop_on_signals(interrupt_while=loading)
    try:
        build_field, device = engine_field_builder(settings.device)
    except ImportError as error:
        log.error("the distance-field engine is not available: %s", error)
        return 2
    except ValueError as error:
        log.error("cannot use device %r: %s", settings.device, error)
        return 2
    config = settings.zenoh_config()
    session = _open(config, settings.config_file)
    if session is None:
        return 1
    with session:
        log.info("worker listening on %s", ", ".join(configured_endpoints(config, "listen")) or "no endpoint")
        try:
            loading.set()
            warm_up_engine(device)
            loading.clear()  # from here on a signal only sets `stop`, which serve watches
        except _StoppedWhileLoading:
            log.info("stopped while loading the engine's kernels on %s", device)
            return 0
        except Exception:  # noqa: BLE001 - any failure here means the engine cannot serve on this device
            log.exception("the engine failed on %s before serving anything", device)
            return 2
        try:
            serve(
                session,
                settings,
                stop=stop,
                build_field=build_field,
                device=device,
                on_ready=None if ready is None else (lambda _worker: ready.set()),
            )
        except InvalidOptionError as error:  # its id is taken
            log.error("%s", error)
            return 1
    return 0


def run_router(settings: RouterSettings, ready: _Settable | None = None) -> int:
    """Run a Zenoh router alone (no worker, no Warp) until SIGINT or SIGTERM; returns the exit status
    (1: the session could not be opened). Logs the workers of its namespace as they join and leave."""
    _configure_logging()
    stop = _stop_on_signals()
    config = settings.zenoh_config()
    session = _open(config, settings.config_file)
    if session is None:
        return 1
    with session:
        watcher = log_worker_changes(session, settings.namespace)
        log.info("router listening on %s", ", ".join(configured_endpoints(config, "listen")) or "no endpoint")
        if ready is not None:
            ready.set()
        stop.wait()
        watcher.undeclare()
    log.info("router stopped")
    return 0


def run_gpu_workers(settings: WorkerSettings, gpus: Sequence[int]) -> int:
    """`badf serve --gpus`: `run_workers` with one worker per GPU index N, on cuda:N, with the id
    `{settings.worker_id}-cudaN`; the router listens where `settings` says and joins `settings.connect`."""
    router = RouterSettings(settings.namespace, settings.listen, settings.connect, settings.config_file)
    workers = [
        dataclasses.replace(settings, worker_id=f"{settings.worker_id}-cuda{index}", device=f"cuda:{index}")
        for index in gpus
    ]
    return run_workers(router, workers)


def run_workers(
    router: RouterSettings,
    workers: Sequence[WorkerSettings],
    ready: _Settable | None = None,
    *,
    start_timeout_s: float = 900.0,
) -> int:
    """A router in this process and one spawned process per worker, until SIGINT or SIGTERM.

    The workers join the router on a private loopback port and listen nowhere themselves (their own
    `mode`, `listen` and `connect` are replaced). `ready` is set once every worker is. On a signal the
    workers and the router stop (status 0). A worker that fails to start stops everything with its status
    (1: Zenoh, 2: engine or device); one that exits later is logged and the others keep serving, until
    none is left (status 1).
    """
    _configure_logging()
    stop = _stop_on_signals()
    loopback = free_loopback_endpoint()
    config = router.zenoh_config(extra_listen=(loopback,))
    session = _open(config, router.config_file)
    if session is None:
        return 1
    joined = [dataclasses.replace(w, mode="router", listen=(), connect=(loopback,)) for w in workers]
    with session:
        watcher = log_worker_changes(session, router.namespace)
        log.info("router listening on %s", ", ".join(configured_endpoints(config, "listen")))
        status = _supervise(joined, stop, ready, start_timeout_s)
        watcher.undeclare()
    log.info("router stopped")
    return status


def _supervise(
    workers: Sequence[WorkerSettings], stop: threading.Event, ready: _Settable | None, start_timeout_s: float
) -> int:
    """Start a process per worker, wait until all are ready, then until `stop` or until none is left."""
    children = [_spawn(_worker_main, settings, name=f"badf-worker-{settings.worker_id}") for settings in workers]
    try:
        deadline = time.monotonic() + start_timeout_s
        starting = set(range(len(workers)))
        while starting and not stop.is_set():
            for index in sorted(starting):
                (process, started), worker = children[index], workers[index]
                if started.is_set():
                    log.info("worker %s ready on %s (pid %d)", worker.worker_id, worker.device, process.pid)
                    starting.discard(index)
                elif not process.is_alive():
                    log.error("worker %s exited with status %s before it was ready", worker.worker_id, process.exitcode)
                    return process.exitcode if process.exitcode and process.exitcode > 0 else 1
            if time.monotonic() > deadline:
                log.error("%d workers not ready after %g s", len(starting), start_timeout_s)
                return 1
            stop.wait(0.1)
        if ready is not None and not stop.is_set():
            ready.set()
        running = {process.sentinel: index for index, (process, _) in enumerate(children)}
        while running and not stop.is_set():
            for sentinel in multiprocessing.connection.wait(list(running), timeout=0.2):
                index = running.pop(sentinel)  # type: ignore[call-overload]
                log.error(
                    "worker %s exited with status %s; the other workers keep serving",
                    workers[index].worker_id, children[index][0].exitcode,
                )  # fmt: skip
        return 0 if stop.is_set() else 1
    finally:
        for process, _ in children:
            if process.is_alive():
                process.terminate()  # all at once, so they shut down side by side
        for process, _ in children:
            end_process(process)


@contextmanager
def worker_process(settings: WorkerSettings, *, start_timeout_s: float = 300.0) -> Iterator[multiprocessing.Process]:
    """Run `run_worker(settings)` in a child process for the duration of the block.

    Yields once the worker is ready (Warp imported, kernels loaded, keys declared), or raises
    WorkerUnavailableError if it exits first or is not ready within `start_timeout_s`. Afterwards the
    child gets SIGTERM, and SIGKILL if it has not exited 30 s later. The child ignores SIGINT and SIGHUP,
    which a terminal sends the whole group: the caller takes them and the block ends the child.
    """
    with _child(_worker_main, settings, f"badf-worker-{settings.worker_id}", start_timeout_s) as process:
        yield process


@contextmanager
def router_process(settings: RouterSettings, *, start_timeout_s: float = 60.0) -> Iterator[multiprocessing.Process]:
    """Run `run_router(settings)` in a child process for the duration of the block (as `worker_process`)."""
    with _child(_router_main, settings, "badf-router", start_timeout_s) as process:
        yield process


@contextmanager
def workers_process(
    router: RouterSettings, workers: Sequence[WorkerSettings], *, start_timeout_s: float = 600.0
) -> Iterator[multiprocessing.Process]:
    """Run `run_workers(router, workers)` in a child process for the duration of the block (as
    `worker_process`): ready once the router and every worker are."""
    # Not a daemon: a daemonic process may not start the worker processes.
    with _child(_workers_main, (router, list(workers)), "badf-workers", start_timeout_s, daemon=False) as process:
        yield process


@contextmanager
def _child(
    main: Callable[[Any, _Settable], None], settings: Any, name: str, start_timeout_s: float, *, daemon: bool = True
) -> Iterator[multiprocessing.Process]:
    process, ready = _spawn(main, settings, name=name, daemon=daemon)
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


def _spawn(
    main: Callable[[Any, _Settable], None], settings: Any, *, name: str, daemon: bool = True
) -> tuple[multiprocessing.Process, Any]:
    ready = _SPAWN.Event()
    process = _SPAWN.Process(target=main, args=(settings, ready), name=name, daemon=daemon)
    process.start()
    return process, ready


def _worker_main(settings: WorkerSettings, ready: _Settable) -> None:
    ignore_terminal_signals()  # the parent ends it
    exit_now(run_worker(settings, ready))  # the exit status tells the parent why a worker did not start


def exit_now(status: int) -> None:
    """End a badf process (worker, router) once its `run_*` has returned: flush the logs and leave without
    interpreter finalisation. By then its threads are joined and its session is closed; finalisation only
    tears down Zenoh's native threads, and one re-entering Python during it made about one exit in three
    abort (SIGABRT, "FATAL: exception not rethrown") in the demo on 2026-11-21."""
    _SHUTDOWN_REPORTED.set()  # ended in time: no report
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


def _router_main(settings: RouterSettings, ready: _Settable) -> None:
    ignore_terminal_signals()  # the parent ends it
    exit_now(run_router(settings, ready))


def _workers_main(settings: tuple[RouterSettings, list[WorkerSettings]], ready: _Settable) -> None:
    ignore_terminal_signals()  # the parent ends it
    router, workers = settings
    exit_now(run_workers(router, workers, ready))


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


def _open(config: zenoh.Config, config_file: str | None) -> zenoh.Session | None:
    zenoh.init_log_from_env_or("error")
    try:
        return zenoh.open(config)
    except zenoh.ZError as error:
        log.error("cannot open the Zenoh session (%s): %s", _open_hint(config, config_file), zenoh_message(error))
        return None


def _open_hint(config: zenoh.Config, config_file: str | None) -> str:
    """What to look at when a session does not open, from what it was to listen on and connect to."""
    listen, connect = configured_endpoints(config, "listen"), configured_endpoints(config, "connect")
    hints = []
    if listen:
        hints.append(f"is a port of {', '.join(listen)} taken?")
    if connect:
        hints.append(f"is a router listening at {', '.join(connect)}?")
    if not listen and not connect:
        hints.append("it has nothing to listen on or connect to: give --listen or --connect")
    if config_file is not None:
        hints.append(f"is {config_file} right?")
    return " ".join(hints)


def _configure_logging() -> None:
    if not logging.getLogger().handlers:
        logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(asctime)s badf %(levelname)s %(message)s")


# A process still running this long after SIGINT/SIGTERM writes every thread's stack to stderr, so a stuck
# shutdown says where it is stuck (the process then goes on; its parent may still end it).
SHUTDOWN_REPORT_AFTER_S = 10.0
_SHUTDOWN_REPORTED = threading.Event()  # set once the process ends in time, or has reported


class _StoppedWhileLoading(BaseException):
    """Raised in the main thread by a stop signal that comes while the engine's kernels load. With a cold kernel
    cache that takes tens of seconds on a CPU (39 s on a 2-core machine), and a worker that only noted the signal
    exited 33 to 35 s after it (2026-12-02). Nothing is declared on Zenoh yet, and Warp moves a compiled module into
    its cache by renaming it, so leaving in the middle loses nothing. A BaseException, as KeyboardInterrupt is, so
    that no `except Exception` on the way (Warp's, the warm-up's) takes it for a failure."""


def _stop_on_signals(interrupt_while: threading.Event | None = None) -> threading.Event:
    """An event set by the first stop signal (`stop_signals`), which also starts the shutdown report; while
    `interrupt_while` is set, the signal raises _StoppedWhileLoading in the main thread as well (once)."""
    stop = threading.Event()

    def on_signal(_number, _frame) -> None:
        if not stop.is_set():
            threading.Thread(target=_report_if_still_running, args=(SHUTDOWN_REPORT_AFTER_S,),
                             name="badf-shutdown-report", daemon=True).start()
        stop.set()
        if interrupt_while is not None and interrupt_while.is_set():
            interrupt_while.clear()
            raise _StoppedWhileLoading

    on_stop_signals(on_signal)
    return stop


def _report_if_still_running(after_s: float) -> None:
    """Write every thread's stack to stderr unless the process has ended (`exit_now`) within `after_s`. It reads
    the stacks holding the interpreter's lock: faulthandler's watchdog, used before, reads them without it, and
    reading the main thread's while Warp generated code crashed the worker (SIGSEGV, 2 of 4 stops during a
    cold-cache warm-up, in an outside check of 2026-12-02)."""
    if _SHUTDOWN_REPORTED.wait(after_s):
        return
    _SHUTDOWN_REPORTED.set()
    names = {thread.ident: thread.name for thread in threading.enumerate()}
    lines = [f"badf: still running {after_s:.0f} s after the stop signal; where each thread is:"]
    for ident, frame in sys._current_frames().items():
        lines.append(f"thread {names.get(ident, ident)}:")
        lines.extend(line.rstrip("\n") for line in traceback.format_stack(frame))
    sys.stderr.write("\n".join(lines) + "\n")
    sys.stderr.flush()
