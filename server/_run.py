"""A worker process: logging, the Zenoh session, SIGINT/SIGTERM, then `serve` until a signal comes; and
`worker_process`, which runs one as a child process (tests, benchmarks, the demo)."""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
from contextlib import contextmanager
from typing import Iterator, Protocol

import zenoh

from badf.protocol import WorkerUnavailableError
from badf.server._worker import WorkerSettings, engine_field_builder, serve

log = logging.getLogger("badf.server")


class _Settable(Protocol):
    def set(self) -> None: ...


def run_worker(settings: WorkerSettings, ready: _Settable | None = None) -> int:
    """Run a worker in this process's main thread until SIGINT or SIGTERM; returns the exit status.

    `ready` (for instance a multiprocessing Event) is set once the worker's keys and liveliness token are
    declared. Exit status 1: the Zenoh session could not be opened (a taken port, a bad config file);
    2: the engine or the device is unavailable.
    """
    if not logging.getLogger().handlers:
        logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(asctime)s badf %(levelname)s %(message)s")
    zenoh.init_log_from_env_or("error")
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda number, _frame: stop.set())
    try:
        build_field, device = engine_field_builder(settings.device)
    except ImportError as error:
        log.error("the distance-field engine is not available: %s", error)
        return 2
    except ValueError as error:
        log.error("cannot use device %r: %s", settings.device, error)
        return 2
    try:
        session = zenoh.open(settings.zenoh_config())
    except zenoh.ZError as error:
        log.error("cannot open the Zenoh session (is the port taken, or the config file wrong?): %s", error)
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


@contextmanager
def worker_process(settings: WorkerSettings, *, start_timeout_s: float = 300.0) -> Iterator[multiprocessing.Process]:
    """Run `run_worker(settings)` in a child process for the duration of the block.

    The child is started with `spawn` (a forked child of a process with a Zenoh session hangs when it opens
    its own). Yields once the worker is ready (Warp imported, kernels loaded, keys declared), or raises
    WorkerUnavailableError if it exits first or is not ready within `start_timeout_s`. Afterwards the
    child gets SIGTERM, and SIGKILL if it has not exited 30 s later.
    """
    context = multiprocessing.get_context("spawn")
    ready = context.Event()
    process = context.Process(
        target=_child_main, args=(settings, ready), name=f"badf-worker-{settings.worker_id}", daemon=True
    )
    process.start()
    try:
        deadline = time.monotonic() + start_timeout_s
        while not ready.wait(0.1):
            if not process.is_alive():
                raise WorkerUnavailableError(
                    f"worker process exited with status {process.exitcode} before it was ready"
                )
            if time.monotonic() > deadline:
                raise WorkerUnavailableError(f"worker process not ready after {start_timeout_s:g} s")
        yield process
    finally:
        end_process(process)


def _child_main(settings: WorkerSettings, ready: _Settable) -> None:
    exit_now(run_worker(settings, ready))  # the exit status tells the parent why a worker did not start


def exit_now(status: int) -> None:
    """End a worker process once `run_worker` has returned: flush the logs and leave without interpreter
    finalisation. By then the worker's threads are joined and its session is closed; finalisation only
    tears down Zenoh's native threads, and one re-entering Python during it made about one exit in three
    abort (SIGABRT, "FATAL: exception not rethrown") in the demo on 2026-11-21."""
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


def end_process(process: multiprocessing.Process, *, grace_s: float = 30.0) -> None:
    """SIGTERM `process` (one this program started), then SIGKILL if it has not exited after `grace_s`."""
    if process.is_alive():
        process.terminate()
        process.join(grace_s)
    if process.is_alive():
        process.kill()
        process.join(grace_s)
