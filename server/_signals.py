"""The signals that end a long-running command (serve, demo) as Ctrl-C does."""

from __future__ import annotations

import signal
from typing import Callable


def on_stop_signals(handler: Callable) -> None:
    """Call `handler(signum, frame)` on SIGINT, SIGTERM and SIGHUP. SIGHUP too: a closed terminal or SSH
    session ended `badf demo` at once, leaving its worker and viewer running (re-parented to init) on the
    port the next run wants. A SIGHUP already ignored (`nohup badf serve`) stays ignored."""
    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    hangup = getattr(signal, "SIGHUP", None)
    if hangup is not None and signal.getsignal(hangup) is not signal.SIG_IGN:
        signal.signal(hangup, handler)
