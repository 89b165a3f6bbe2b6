"""`badf serve`: a distance-field worker that is, by default, also the Zenoh router on 127.0.0.1:7447;
with `--connect`, a worker that joins other routers; with `--router-only`, a router alone; with `--gpus`,
a router and one worker process per GPU."""

from __future__ import annotations

import argparse
import sys

from badf.cli._extras import missing_extra
from badf.protocol import DEFAULT_ENDPOINT, BadfError, check_name, zenoh_config
from badf.protocol._session import with_a_free_port
from badf.server._cuda import (
    NoCudaDeviceError,
    device_problem,
    parse_gpus,
    requested_gpus,
    visible_cuda_device_count,
)
from badf.server._router import RouterSettings
from badf.server._run import exit_now, run_gpu_workers, run_router, run_worker
from badf.server._worker import (
    DEFAULT_STATS_INTERVAL_S,
    DEFAULT_TRIM_AFTER_S,
    WorkerSettings,
    check_stats_interval,
    check_trim_after,
    default_worker_id,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--listen", action="append", metavar="ENDPOINT",
        help=f"Zenoh endpoint to listen on, repeatable (default: {DEFAULT_ENDPOINT}, or no endpoint when "
        "--connect joins other routers; a --config file that names listen gives its own)",
    )  # fmt: skip
    parser.add_argument(
        "--connect", action="append", default=[], metavar="ENDPOINT",
        help="join the Zenoh router at ENDPOINT, e.g. tcp/HOST:7447 (repeatable)",
    )  # fmt: skip
    parser.add_argument(
        "--mode", choices=("router", "peer", "client"), default="router",
        help="Zenoh mode of a single worker (default: router, which also routes for the clients)",
    )  # fmt: skip
    where = parser.add_mutually_exclusive_group()
    where.add_argument(
        "--device", default=None, help="Warp device, e.g. cuda:1 or cpu (default: Warp's default device)"
    )
    where.add_argument(
        "--gpus", default=None, metavar="all|N,M",
        help="a router here and one worker process per GPU (all visible ones, or these indices), each on "
        "cuda:N with the id WORKER_ID-cudaN",
    )  # fmt: skip
    where.add_argument(
        "--router-only", action="store_true",
        help="run only a Zenoh router (no worker, no Warp) for workers and clients to connect to",
    )  # fmt: skip
    parser.add_argument(
        "--namespace", default="badf", help="key-expression prefix shared with the clients (default: badf)"
    )
    parser.add_argument(
        "--config", default=None, metavar="FILE",
        help="Zenoh JSON5 config file (TLS, authentication, access control); used as is, with the flags above on top "
        "(without it: multicast scouting and shared memory are off)",
    )  # fmt: skip
    parser.add_argument(
        "--worker-id", default=None,
        help="this worker's id in key expressions (default: <host>-<pid>); with --gpus, the prefix of the ids",
    )  # fmt: skip
    parser.add_argument(
        "--stats-interval", type=float, default=None, metavar="SECONDS",
        help=f"seconds between a worker's stats lines (default: {DEFAULT_STATS_INTERVAL_S:g})",
    )
    parser.add_argument(
        "--trim-after", type=float, default=None, metavar="SECONDS",
        help="an object that gets no frame for this long gives back what only its next frame would use (frame "
        "scratch, last frame's faces) and its query buffers, once until its next frame; 0: never "
        f"(default: {DEFAULT_TRIM_AFTER_S:g})",
    )  # fmt: skip


def check_endpoint_lists(args: argparse.Namespace) -> None:
    """An endpoint listed twice in --listen (it was 'is a port of ... taken?' at start, exit 1), or both listened
    on and joined (a worker joining itself, which Zenoh then logs each second; eighteenth outside check)."""
    listen = list(args.listen or [])
    for endpoint in listen:
        if listen.count(endpoint) > 1:
            raise ValueError(f"--listen names {endpoint} twice")
        if endpoint in args.connect:
            raise ValueError(f"--connect {endpoint} is this process's own --listen endpoint; name another router")


def settings_from(args: argparse.Namespace) -> WorkerSettings:
    # checked under the flags' names first: the settings name their fields ("stats_interval_s must be ...")
    stats_interval = DEFAULT_STATS_INTERVAL_S if args.stats_interval is None else args.stats_interval
    check_stats_interval(stats_interval, "--stats-interval")
    trim_after = DEFAULT_TRIM_AFTER_S if args.trim_after is None else args.trim_after
    check_trim_after(trim_after, "--trim-after")
    if args.worker_id is not None:
        check_name(args.worker_id, what="--worker-id")
    return WorkerSettings(
        worker_id=default_worker_id() if args.worker_id is None else args.worker_id,
        namespace=args.namespace,
        device=args.device,
        mode=args.mode,
        listen=tuple(args.listen) if args.listen else None,
        connect=tuple(args.connect),
        config_file=args.config,
        stats_interval_s=stats_interval,
        trim_after_s=trim_after,
    )


def router_settings_from(args: argparse.Namespace) -> RouterSettings:
    # a router has no worker, so no stats lines (the interval was taken and ignored; eighteenth outside check)
    for given, flag in ((args.worker_id is not None, "--worker-id"), (args.mode != "router", "--mode"),
                        (args.stats_interval is not None, "--stats-interval"),
                        (args.trim_after is not None, "--trim-after")):
        if given:
            raise ValueError(f"{flag} does not apply to --router-only")
    return RouterSettings(
        namespace=args.namespace,
        listen=tuple(args.listen) if args.listen else None,
        connect=tuple(args.connect),
        config_file=args.config,
    )


def run(args: argparse.Namespace) -> int:
    missing = None if args.router_only else missing_extra("badf serve", ("warp",), "server")
    if missing is not None:
        print(missing, file=sys.stderr)
        return 2
    try:
        check_endpoint_lists(args)
        zenoh_config(mode="router", listen=list(args.listen or []))  # checks their form before any port is taken
        args.listen = [with_a_free_port(endpoint) for endpoint in args.listen] if args.listen else args.listen
        if args.router_only:
            router = router_settings_from(args)
        else:
            settings = settings_from(args)
            gpus = None if args.gpus is None else gpus_from(args)
    except NoCudaDeviceError as error:
        print(f"badf serve --gpus: {error}; run one worker on the CPU with --device cpu", file=sys.stderr)
        return 2
    except (BadfError, ValueError) as error:
        print(f"badf serve: {error}", file=sys.stderr)
        return 2
    # one line, as demo and bench say it, not the worker's traceback (`--device cuda` where there is no CUDA,
    # seventeenth outside check)
    problem = None if args.router_only or gpus is not None or args.device is None else device_problem(args.device)
    if problem is not None:
        print(f"badf serve: {problem}", file=sys.stderr)
        return 2
    if args.router_only:
        exit_now(run_router(router))
    elif gpus is not None:
        exit_now(run_gpu_workers(settings, gpus))
    else:
        exit_now(run_worker(settings))
    return 0  # not reached: exit_now ends the process


def gpus_from(args: argparse.Namespace) -> list[int]:
    """The GPU indices `--gpus` names, checked against the visible devices (NoCudaDeviceError if none)."""
    if args.mode != "router":
        raise ValueError("--mode applies to a single worker; with --gpus the workers join a router in this process")
    requested_gpus(args.gpus)  # a malformed value is told as such, also where no GPU is
    return parse_gpus(args.gpus, visible_cuda_device_count())
