"""`badf demo` end to end, headless: it exits 0, prints its stats, and leaves no process behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import as_from_a_terminal, free_endpoint, process_group_members, wait_until

DEMO_TIMEOUT_S = 900  # includes the first kernel compilation on a 2-core machine


def _start(*args: str) -> subprocess.Popen:
    # its own session, so the demo and everything it starts share one process group to inspect
    return subprocess.Popen(
        [sys.executable, "-m", "badf.cli", "demo", *args, "--no-viewer", "--listen", free_endpoint()],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
        preexec_fn=as_from_a_terminal,
    )  # fmt: skip


def _finish(process: subprocess.Popen, timeout: float) -> str:
    try:
        output, _ = process.communicate(timeout=timeout)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    return output


def _assert_nothing_left(pgid: int) -> None:
    wait_until(lambda: not process_group_members(pgid), timeout=60, what=f"every process of the demo's group {pgid} to end")


@pytest.mark.parametrize("scene", ["morph", "cloth"])
def test_demo_runs_frames_prints_stats_and_cleans_up(scene):
    process = _start(scene, "--frames", "30")
    output = _finish(process, DEMO_TIMEOUT_S)
    assert process.returncode == 0, output
    assert "summary: 30 frames" in output, output
    assert "frame    30" in output
    if scene == "cloth":
        assert "all finite" in output
    _assert_nothing_left(process.pid)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGHUP, signal.SIGTERM], ids=["ctrl-c", "hangup", "term"])
def test_ctrl_c_ends_the_demo_cleanly(signum, tmp_path):
    """SIGHUP (a closed terminal) ended the demo at once, leaving its worker and viewer running (outside
    check 2026-11-22); it now ends it as Ctrl-C does. Both go to the whole process group, as a terminal sends
    them: the worker, which stopped by itself then, failed the demo's request in flight, and the demo exited 1
    with "its worker is gone" instead of its summary (sixteenth outside check). SIGTERM to the group (`timeout`,
    a service manager) did the same in 5 runs of 6 (eighteenth outside check). A one-triangle sequence keeps
    requests in flight nearly all the time. SIGTERM, which the worker takes as well, is sent right after the
    built-in shape's first frame, when the next is being sent (the old code failed 2 runs of 2 so from a script,
    and passed 6 of 6 in this test: `test_a_worker_gone_with_the_stop_signal_ends_the_frame` checks the rule
    itself)."""
    sequence = tmp_path / "triangle.npz"
    frames = np.eye(3)[None] * np.linspace(1.0, 2.0, 4)[:, None, None]
    np.savez(sequence, vertices=frames, faces=np.array([[0, 1, 2]]))
    if signum == signal.SIGTERM:  # the built-in shape's requests: the signal often comes while one is in flight
        process = _start("morph")
    else:
        process = _start("morph", "--sequence", str(sequence))
    lines = []
    deadline = time.monotonic() + DEMO_TIMEOUT_S
    try:
        for line in process.stdout:  # until the demo has streamed a few frames
            lines.append(line)
            if line.startswith("frame    20" if signum != signal.SIGTERM else "frame "):
                break
            assert time.monotonic() < deadline, "no frames before the deadline"
        os.killpg(process.pid, signum)
        rest = _finish(process, 120)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    output = "".join(lines) + rest
    assert process.returncode == 0, output
    assert "summary:" in output
    _assert_nothing_left(process.pid)


def test_a_worker_gone_with_the_stop_signal_ends_the_frame():
    """The rule behind the SIGTERM case above: within a frame, a worker that is going away ends the loop
    quietly when a stop signal has come or comes within the grace; otherwise its error stands."""
    from badf.protocol import ObjectUnavailableError, WorkerUnavailableError
    from badf.server import _demo

    saved = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        stop = _demo._StopFlag()
    finally:
        for signum, handler in saved.items():  # the flag's handlers are not for pytest's process
            signal.signal(signum, handler)
    with pytest.raises(WorkerUnavailableError, match="shutting down"):
        with stop.frame():
            raise WorkerUnavailableError("worker w is shutting down")  # no signal came: the error stands
    with pytest.raises(ValueError):
        with stop.frame():
            raise ValueError("any other error stands")
    stop.stopped = True
    with stop.frame():
        raise ObjectUnavailableError("object 'blob' is unavailable: its worker w is gone")
