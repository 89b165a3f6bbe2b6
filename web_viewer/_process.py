"""The viewer in a child process of its own, for programs that also run workers and clients (the demo)."""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.connection
import os
import queue
import signal
import sys
import threading
import time
from contextlib import contextmanager
from typing import Any, Iterator

from badf.protocol import DEFAULT_ENDPOINT, BadfError
from badf.web_viewer._viewer import Viewer, ViewerSettings, _import_viser


@contextmanager
def viewer_process(
    *,
    connect: str = DEFAULT_ENDPOINT,
    host: str = "127.0.0.1",
    port: int = 8080,
    start_timeout_s: float = 120.0,
    **settings: Any,
) -> Iterator[str]:
    """Run a viewer (ViewerSettings: `connect`, `host`, `port` and any other field) in a child process for
    the duration of the block; yields the URL of its page.

    The child is started with `spawn` (a forked child of a process with a Zenoh session hangs when it opens
    its own), so a script that calls this needs `if __name__ == "__main__":` around the call: the child imports
    the script again. Raises ImportError, saying what to install, when viser is missing; RuntimeError when the
    child exits (saying so where the guard is missing), or is not serving within `start_timeout_s`. Afterwards the child gets SIGTERM, and SIGKILL if it
    has not exited 10 s later.
    """
    _import_viser()  # here, with its actionable message, rather than in the child
    viewer_settings = ViewerSettings(connect=connect, host=host, port=port, **settings)
    context = multiprocessing.get_context("spawn")
    urls = context.Queue()
    started = context.Event()  # set once the child runs _serve, past importing the parent's main module
    process = context.Process(target=_serve, args=(viewer_settings, urls, started), name="badf-viewer", daemon=True)
    process.start()
    try:
        deadline = time.monotonic() + start_timeout_s
        while True:
            try:
                url = urls.get(timeout=0.1)
                break
            except queue.Empty:
                if not process.is_alive() and not started.is_set():
                    raise RuntimeError(
                        f"the viewer process exited with status {process.exitcode} while starting: a script that "
                        'calls viewer_process needs `if __name__ == "__main__":` around the call (the child is '
                        "spawned, and imports the script again)")
                if not process.is_alive():
                    raise RuntimeError(f"the viewer process exited with status {process.exitcode} before serving")
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the viewer process was not serving after {start_timeout_s:g} s") from None
        yield url
    finally:
        if process.is_alive():
            process.terminate()
            process.join(10)
        if process.is_alive():
            process.kill()
            process.join(10)
        urls.close()


def _serve(settings: ViewerSettings, urls: Any, started: Any) -> None:
    """The child: serve the viewer until SIGTERM from its parent; exit status 1 if it cannot start.

    It ignores Ctrl-C and SIGHUP, which a terminal sends its whole foreground group: the parent (`badf demo`)
    takes them and ends its children in order, as `badf.server._signals.ignore_terminal_signals` says. Should
    the parent die without ending it (SIGKILL), it stops by itself."""
    started.set()
    stop = threading.Event()
    for signum in [signal.SIGINT] + ([signal.SIGHUP] if hasattr(signal, "SIGHUP") else []):
        signal.signal(signum, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda _number, _frame: stop.set())
    parent = multiprocessing.parent_process()
    if parent is not None:
        threading.Thread(target=lambda: (multiprocessing.connection.wait([parent.sentinel]), stop.set()),
                         name="badf-parent-watch", daemon=True).start()
    if not logging.getLogger().handlers:
        logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(asctime)s badf %(levelname)s %(message)s")
        logging.getLogger("websockets").setLevel(logging.WARNING)  # viser's web server: no line per start and stop
    try:
        viewer = Viewer(settings)
    except (BadfError, ValueError, ImportError) as error:
        print(f"badf viewer: {error}", file=sys.stderr)
        sys.exit(1)
    with viewer:
        urls.put(viewer.url)
        while not stop.wait(1.0):
            pass
    exit_now(0)


def exit_now(status: int) -> None:
    """End a viewer process once its viewer is closed: flush the logs and leave without interpreter
    finalisation, which only tears down Zenoh's native threads, and in which one re-entering Python can abort
    the process (SIGABRT, "FATAL: exception not rethrown"; seen here, and in main's demo)."""
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)
