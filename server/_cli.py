"""`badf serve`: a distance-field worker that is, by default, also the Zenoh router on 127.0.0.1:7447."""

from __future__ import annotations

import argparse
import sys

from badf.protocol import DEFAULT_ENDPOINT, BadfError
from badf.server._run import exit_now, run_worker
from badf.server._worker import WorkerSettings, default_worker_id


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--listen", action="append", metavar="ENDPOINT",
        help=f"Zenoh endpoint to listen on, repeatable (default for a router without --config: {DEFAULT_ENDPOINT})",
    )  # fmt: skip
    parser.add_argument(
        "--connect", action="append", default=[], metavar="ENDPOINT", help="Zenoh endpoint to connect to, repeatable"
    )
    parser.add_argument(
        "--mode", choices=("router", "peer", "client"), default="router",
        help="Zenoh mode: router (default, nothing else needs starting), or peer/client behind another router",
    )  # fmt: skip
    parser.add_argument(
        "--device", default=None, help="Warp device, e.g. cuda:0 or cpu (default: Warp's default device)"
    )
    parser.add_argument(
        "--namespace", default="badf", help="key-expression prefix shared with the clients (default: badf)"
    )
    parser.add_argument(
        "--config", default=None, metavar="FILE",
        help="Zenoh JSON5 config file (TLS, authentication, access control); used as is, with the flags above on top "
        "(without it: multicast scouting and shared memory are off)",
    )  # fmt: skip
    parser.add_argument("--worker-id", default=None, help="this worker's id in key expressions (default: <host>-<pid>)")
    parser.add_argument(
        "--stats-interval", type=float, default=10.0, metavar="SECONDS", help="seconds between stats lines"
    )


def settings_from(args: argparse.Namespace) -> WorkerSettings:
    return WorkerSettings(
        worker_id=args.worker_id or default_worker_id(),
        namespace=args.namespace,
        device=args.device,
        mode=args.mode,
        listen=tuple(args.listen) if args.listen else None,
        connect=tuple(args.connect),
        config_file=args.config,
        stats_interval_s=args.stats_interval,
    )


def run(args: argparse.Namespace) -> int:
    try:
        settings = settings_from(args)
    except (BadfError, ValueError) as error:
        print(f"badf serve: {error}", file=sys.stderr)
        return 2
    exit_now(run_worker(settings))
    return 0  # not reached: exit_now ends the process
