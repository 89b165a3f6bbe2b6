"""The signals that end a long-running command (serve, demo) as Ctrl-C does."""

from __future__ import annotations

import signal
from typing import Callable


def _terminal_signals() -> list[int]:
    """SIGINT (Ctrl-C) and SIGHUP (a closed terminal), which a terminal sends to every process of its
    foreground group, where the platform has them."""
    return [signal.SIGINT] + ([signal.SIGHUP] if hasattr(signal, "SIGHUP") else [])


def stop_signals() -> list[int]:
    """SIGINT, SIGTERM and SIGHUP: what ends a long-running command (serve, demo, a benchmark). SIGHUP too: a
    closed terminal or SSH session ended `badf demo` at once, leaving its worker and viewer running
    (re-parented to init) on the port the next run wants. A SIGINT or SIGHUP already ignored (`nohup badf
    serve`, a managed child: `ignore_terminal_signals`) is left out, so it stays ignored."""
    taken = [signal.SIGTERM]
    for signum in _terminal_signals():
        if signal.getsignal(signum) is not signal.SIG_IGN:
            taken.append(signum)
    return sorted(taken)


def ignore_terminal_signals() -> None:
    """For a child that its parent ends (SIGTERM, by its pid: a demo's worker and viewer, `serve --gpus`'
    workers): Ctrl-C or a closed terminal reaches the whole foreground group, and the child stopping by itself
    at that moment failed the parent's request in flight (`badf demo` then exited 1 with "its worker is gone"
    instead of its summary, sixteenth outside check). The parent, which got the same signal, ends it in
    order."""
    for signum in _terminal_signals():
        signal.signal(signum, signal.SIG_IGN)


def on_stop_signals(handler: Callable) -> None:
    """Call `handler(signum, frame)` on each of `stop_signals()`."""
    for signum in stop_signals():
        signal.signal(signum, handler)
