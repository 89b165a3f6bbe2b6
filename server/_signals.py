"""The signals that end a long-running command (serve, demo) as Ctrl-C does."""

from __future__ import annotations

import signal
from typing import Callable


def stop_signals() -> list[int]:
    """SIGINT, SIGTERM and SIGHUP: what ends a long-running command (serve, demo, a benchmark). SIGHUP too: a
    closed terminal or SSH session ended `badf demo` at once, leaving its worker and viewer running
    (re-parented to init) on the port the next run wants. A SIGHUP already ignored (`nohup badf serve`) is
    left out, so it stays ignored."""
    taken = [signal.SIGINT, signal.SIGTERM]
    hangup = getattr(signal, "SIGHUP", None)
    if hangup is not None and signal.getsignal(hangup) is not signal.SIG_IGN:
        taken.append(hangup)
    return taken


def on_stop_signals(handler: Callable) -> None:
    """Call `handler(signum, frame)` on each of `stop_signals()`."""
    for signum in stop_signals():
        signal.signal(signum, handler)
