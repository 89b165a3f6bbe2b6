import os
import pathlib
import socket
import sys
import time

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).parent))

try:
    from hypothesis import settings as _hypothesis_settings

    # The property tests draw the same examples on every run, so a CI result does not depend on luck;
    # BADF_HYPOTHESIS_RANDOM=1 draws fresh ones, to look for new failures.
    _hypothesis_settings.register_profile("badf", derandomize=os.environ.get("BADF_HYPOTHESIS_RANDOM") != "1")
    _hypothesis_settings.load_profile("badf")
except ImportError:  # hypothesis is in the test extra; only the property tests need it
    pass


def _devices() -> list[str]:
    try:
        import warp as wp
    except ImportError:
        return []
    wp.config.log_level = wp.LOG_ERROR
    wp.init()
    return ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


DEVICES = _devices()


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    """Every engine test runs on the CPU back-end, and on the first GPU when there is one."""
    return request.param


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
    deadline = time.monotonic() + timeout
    pause = 0.002
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what}")
        time.sleep(pause)  # polling interval, not synchronisation: the condition decides
        pause = min(pause * 2, 0.05)


def process_group_members(pgid: int) -> list[int]:
    """Process ids whose process group is `pgid` (Linux /proc): a command started in a session of its own,
    and everything it started."""
    members = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as handle:
                fields = handle.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid:  # fields after the name: state, ppid, pgrp
            members.append(int(entry))
    return members


def as_from_a_terminal() -> None:
    """For a command a test signals as a terminal would (`preexec_fn`): SIGINT and SIGHUP at their defaults. A
    suite run under `nohup` (or from a shell script, for SIGINT) hands its children those signals ignored, and the
    commands rightly leave an ignored SIGHUP ignored (`stop_signals`), so the tests that send one failed there:
    two of them in a run of `.ci/run` started with nohup (2026-12-02)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGHUP, signal.SIG_DFL)
