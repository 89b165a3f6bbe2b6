"""Real worker and client processes for the integration tests, started with the `spawn` method.

A forked child of a process that has a Zenoh session hangs when it opens its own (FACTS.md), so every
process here is spawned; the test ends only the processes it started, by their handle.
"""

from __future__ import annotations

import multiprocessing
from contextlib import contextmanager
from typing import Iterator

import numpy as np

from badf.client import Client
from badf.server import WorkerSettings, worker_process

SPAWN = multiprocessing.get_context("spawn")


@contextmanager
def worker_on(endpoint: str, *, worker_id: str = "w1", device: str = "cpu") -> Iterator[multiprocessing.Process]:
    """A `badf serve` worker in its own process, the router on `endpoint`; stopped with SIGTERM after.
    It imports Warp and loads the engine's kernels (compiled on first use) before it is ready."""
    settings = WorkerSettings(worker_id=worker_id, listen=(endpoint,), device=device, stats_interval_s=5.0)
    with worker_process(settings, start_timeout_s=300.0) as process:
        yield process


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
