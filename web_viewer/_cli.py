"""`badf view`: the web viewer on the workers' objects, at http://127.0.0.1:8080/ by default."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

from badf.client._client import timeout_seconds
from badf.protocol import DEFAULT_ENDPOINT, BadfError, check_name
from badf.web_viewer._process import exit_now
from badf.web_viewer._viewer import RESOLUTIONS, UP_DIRECTIONS, Viewer, ViewerSettings, check_port, check_rate


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--connect", default=DEFAULT_ENDPOINT, metavar="ENDPOINT",
        help=f"Zenoh endpoint of the workers' router (default: {DEFAULT_ENDPOINT})",
    )  # fmt: skip
    parser.add_argument("--port", type=int, default=8080, help="port of the web page (default: 8080; 0: any free)")
    parser.add_argument(
        "--host", default="127.0.0.1", help="address the web page listens on (default: 127.0.0.1; 0.0.0.0: all)"
    )
    parser.add_argument("--namespace", default="badf", help="the workers' key-expression prefix (default: badf)")
    parser.add_argument("--config", default=None, metavar="FILE", help="Zenoh JSON5 config file (TLS, authentication)")
    parser.add_argument("--object", default=None, metavar="NAME", help="object to show first (default: the first by name)")
    parser.add_argument(
        "--resolution", type=int, default=256, choices=RESOLUTIONS, help="slice grid, per side (default: 256)"
    )
    parser.add_argument("--up", default="+y", choices=UP_DIRECTIONS, help="the world's up direction (default: +y)")
    parser.add_argument("--max-slice-hz", type=float, default=20.0,
                        help="most slices asked for per second (default: 20)")
    parser.add_argument("--max-mesh-hz", type=float, default=10.0, help="most mesh fetches per second (default: 10)")
    parser.add_argument("--max-info-hz", type=float, default=20.0,
                        help="most info polls (frame, stats) per second (default: 20)")
    parser.add_argument("--timeout", type=float, default=10.0, metavar="SECONDS",
                        help="longest wait for a worker (default: 10)")


def settings_from(args: argparse.Namespace) -> ViewerSettings:
    # checked under the flags' names first: the settings name their fields ("max_slice_hz must be ...")
    check_port(args.port, "--port")
    for flag, rate in (("--max-slice-hz", args.max_slice_hz), ("--max-mesh-hz", args.max_mesh_hz),
                       ("--max-info-hz", args.max_info_hz)):
        check_rate(rate, flag)
    timeout_seconds(args.timeout, what="--timeout")
    if args.object is not None:
        check_name(args.object, what="--object")
    return ViewerSettings(
        connect=args.connect,
        namespace=args.namespace,
        config_file=args.config,
        host=args.host,
        port=args.port,
        object_name=args.object,
        resolution=args.resolution,
        up=args.up,
        max_slice_hz=args.max_slice_hz,
        max_mesh_hz=args.max_mesh_hz,
        max_info_hz=args.max_info_hz,
        timeout_s=args.timeout,
    )


def run(args: argparse.Namespace) -> int:
    if not logging.getLogger().handlers:
        logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(asctime)s badf %(levelname)s %(message)s")
        logging.getLogger("websockets").setLevel(logging.WARNING)  # viser's web server: no line per start and stop
    stop = threading.Event()  # set by SIGINT or SIGTERM, also one that comes while the viewer starts
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda _number, _frame: stop.set())
    try:
        settings = settings_from(args)
    except (BadfError, ValueError) as error:
        print(f"badf view: {error}", file=sys.stderr)
        return 2
    # The viewer is built on a thread of its own: reaching the routers can block in Zenoh's native code for
    # the whole --timeout, where this thread would not run the signal handlers, so Ctrl-C went unheeded.
    started: dict = {}
    built = threading.Event()

    def build() -> None:
        try:
            started["viewer"] = Viewer(settings)
        except (BadfError, ValueError, ImportError) as error:
            started["error"] = error
        finally:
            built.set()

    print(f"badf view: connecting to {settings.connect} (up to {settings.timeout_s:g} s; Ctrl-C stops)",
          file=sys.stderr, flush=True)
    threading.Thread(target=build, name="badf-view-start", daemon=True).start()
    while not built.wait(0.1):
        if stop.is_set():
            print("badf view: stopped while starting", file=sys.stderr)
            exit_now(0)
    if "error" in started:
        print(f"badf view: {started['error']}", file=sys.stderr)
        return 2
    viewer = started["viewer"]
    with viewer:
        print(f"badf view: open {viewer.url} (workers at {settings.connect}); Ctrl-C stops", file=sys.stderr)
        while not stop.wait(1.0):
            pass
    exit_now(0)
    return 0  # not reached
