from __future__ import annotations

import socket
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = REPO_ROOT.parent / "shared" / "data"  # ../shared/data from the repository root


def free_endpoint() -> str:
    """A Zenoh TCP endpoint on 127.0.0.1 whose port was free a moment ago."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{probe.getsockname()[1]}"


@pytest.fixture
def endpoint() -> str:
    return free_endpoint()


def wait_until(condition, *, timeout: float = 20.0, what: str = "the condition") -> None:
    """Return as soon as `condition()` is true; fail the test when `timeout` seconds pass first."""
    import time

    deadline = time.monotonic() + timeout
    pause = 0.002
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what}")
        time.sleep(pause)  # polling interval, not synchronisation: the condition decides
        pause = min(pause * 2, 0.05)
