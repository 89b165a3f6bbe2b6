"""`badf bench NAME [flags]`: run one benchmark (engine, accuracy, service, scaleout, soak)."""

from __future__ import annotations

import argparse
import importlib
import sys

from badf.server._mesh_files import MeshFileError

_BENCHMARKS = {
    "engine": ("badf.bench.engine", "per-stage build/update times, memory, and the dense-grid baseline"),
    "service": ("badf.bench.service", "frame + query round trip and query throughput, service beside in-process"),
    "viewer": ("badf.bench.viewer", "slice round trips as the viewer asks, its drawing, and following a stream"),
    "scaleout": ("badf.bench.scaleout", "aggregate frames and query points per second, one worker against N (GPUs)"),
    "accuracy": ("badf.bench.accuracy", "error against run time (ADF depths, exact, dense grid, CPU peers) and the "
                 "stability table"),
    "soak": ("badf.bench.soak", "clients x objects streaming and querying for a bounded time; answers and memory "
             "checked"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", choices=sorted(_BENCHMARKS), help="; ".join(f"{k}: {v[1]}" for k, v in _BENCHMARKS.items()))
    parser.add_argument("rest", nargs=argparse.REMAINDER, help="flags of that benchmark (see badf bench NAME --help)")


def run(args: argparse.Namespace) -> int:
    module = importlib.import_module(_BENCHMARKS[args.name][0])
    sub = argparse.ArgumentParser(prog=f"badf bench {args.name}", description=_BENCHMARKS[args.name][1])
    module.add_arguments(sub)
    try:
        return int(module.run(sub.parse_args(args.rest)) or 0)
    except MeshFileError as error:
        print(f"badf bench {args.name}: {error}", file=sys.stderr)
        return 2
