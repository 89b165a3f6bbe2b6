"""Real worker and client processes for the integration tests, started with the `spawn` method.

A forked child of a process that has a Zenoh session hangs when it opens its own (FACTS.md), so every
process here is spawned; the test ends only the processes it started, by their handle.
"""

from __future__ import annotations

import multiprocessing
import time
from contextlib import contextmanager
from typing import Iterator

import numpy as np
import pytest

from badf.client import Client
from badf.server import WorkerSettings, run_worker

SPAWN = multiprocessing.get_context("spawn")
# A spawned worker imports Warp and loads the engine's kernels before it is ready (compiled on first use).
WORKER_START_TIMEOUT_S = 300.0


@contextmanager
def worker_process(endpoint: str, *, worker_id: str = "w1", device: str = "cpu") -> Iterator[multiprocessing.Process]:
    """A `badf serve` worker in its own process, the router on `endpoint`; stopped with SIGTERM after."""
    settings = WorkerSettings(worker_id=worker_id, listen=(endpoint,), device=device, stats_interval_s=5.0)
    ready = SPAWN.Event()
    process = SPAWN.Process(target=run_worker, args=(settings, ready), name=f"badf-worker-{worker_id}", daemon=True)
    process.start()
    try:
        deadline = time.monotonic() + WORKER_START_TIMEOUT_S
        while not ready.wait(0.1):
            if not process.is_alive():
                pytest.fail(f"worker process exited with status {process.exitcode} before it was ready")
            if time.monotonic() > deadline:
                pytest.fail(f"worker process not ready after {WORKER_START_TIMEOUT_S} s")
        yield process
    finally:
        stop(process)


def stop(process: multiprocessing.Process) -> None:
    """SIGTERM, then SIGKILL if it has not exited within 30 s."""
    if process.is_alive():
        process.terminate()
        process.join(30)
    if process.is_alive():
        process.kill()
        process.join(30)


def stream_until_killed(endpoint: str, name: str, path: str, streamed: multiprocessing.synchronize.Event) -> None:
    """A client process: register `name` from a sequence file, apply frame 1, then stream round and round.

    Sets `streamed` after 20 streamed frames; bounded at 100,000 frames in case nobody kills it.
    """
    data = np.load(path)
    frames, faces = data["vertices"], data["faces"]
    with Client(endpoint, timeout=60) as client:
        obj = client.register(name, frames[0], faces)
        obj.update(frames[1])
        for count in range(2, 100_000):
            obj.stream(frames[count % len(frames)])
            if count == 21:
                streamed.set()
