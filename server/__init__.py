"""The badf worker: per-object distance fields served over Zenoh (`badf serve`).

Importing this package does not import Warp; the engine (`badf.server.adf`) is loaded when a worker starts.
"""

from badf.server._run import end_process, run_worker, worker_process
from badf.server._worker import Worker, WorkerSettings, serve

__all__ = ["Worker", "WorkerSettings", "end_process", "run_worker", "serve", "worker_process"]
