"""A worker process: logging, the Zenoh session, SIGINT/SIGTERM, then `serve` until a signal comes."""

from __future__ import annotations

import logging
import signal
import sys
import threading
from typing import Protocol

import zenoh

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
