"""The badf worker: per-object distance fields served over Zenoh (`badf serve`), and the Zenoh router that
several workers share (`badf serve --router-only`, `badf serve --gpus all`).

Importing this package does not import Warp; the engine (`badf.server.adf`) is loaded when a worker starts.
"""

from badf.server._router import RouterSettings
from badf.server._run import (
    end_process,
    router_process,
    run_gpu_workers,
    run_router,
    run_worker,
    run_workers,
    worker_process,
    workers_process,
)
from badf.server._worker import Worker, WorkerSettings, serve

__all__ = [
    "RouterSettings",
    "Worker",
    "WorkerSettings",
    "end_process",
    "router_process",
    "run_gpu_workers",
    "run_router",
    "run_worker",
    "run_workers",
    "serve",
    "worker_process",
    "workers_process",
]
