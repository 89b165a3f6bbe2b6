"""The signals that end a long-running command (serve, demo) as Ctrl-C does."""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
from typing import Callable

# Set in a child whose parent ends it (`ignore_terminal_signals`): its SIGINT and SIGHUP stay ignored.
_managed_child = False


def _terminal_signals() -> list[int]:
    """SIGINT (Ctrl-C) and SIGHUP (a closed terminal), which a terminal sends to every process of its
    foreground group, where the platform has them."""
    return [signal.SIGINT] + ([signal.SIGHUP] if hasattr(signal, "SIGHUP") else [])


def stop_signals() -> list[int]:
    """SIGINT, SIGTERM and SIGHUP: what ends a long-running command (serve, demo, a benchmark). SIGHUP too: a
    closed terminal or SSH session ended `badf demo` at once, leaving its worker and viewer running
    (re-parented to init) on the port the next run wants. A SIGHUP already ignored (`nohup badf serve`) is
    left out, so it stays ignored; SIGINT is taken even when ignored (a shell script's `badf serve &` starts
    with it ignored, and `kill -INT` must still end it), except in a child its parent ends."""
    taken = [signal.SIGTERM]
    for signum in _terminal_signals():
        ignored = signal.getsignal(signum) is signal.SIG_IGN
        if not ignored or (signum == signal.SIGINT and not _managed_child):
            taken.append(signum)
    return sorted(taken)


def ignore_terminal_signals() -> None:
    """For a child that its parent ends (SIGTERM, by its pid: a demo's worker and viewer, `serve --gpus`'
    workers): Ctrl-C or a closed terminal reaches the whole foreground group, and the child stopping by itself
    at that moment failed the parent's request in flight (`badf demo` then exited 1 with "its worker is gone"
    instead of its summary, sixteenth outside check). The parent, which got the same signal, ends it in
    order; and should the parent die without doing so (SIGKILL), the child gets SIGTERM from itself."""
    global _managed_child
    _managed_child = True
    for signum in _terminal_signals():
        signal.signal(signum, signal.SIG_IGN)
    end_with_parent()


def end_with_parent() -> None:
    """SIGTERM this process once its multiprocessing parent has exited, however it did (a thread waits on the
    parent's sentinel); nothing for a process that multiprocessing did not start."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        multiprocessing.connection.wait([parent.sentinel])
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="badf-parent-watch", daemon=True).start()


def on_stop_signals(handler: Callable) -> None:
    """Call `handler(signum, frame)` on each of `stop_signals()`."""
    for signum in stop_signals():
        signal.signal(signum, handler)
