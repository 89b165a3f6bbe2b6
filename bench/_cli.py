"""`badf bench NAME`: the project's benchmarks, each a module with `add_arguments(parser)` and `run(args)`."""

from __future__ import annotations

import argparse
import importlib

# name -> (module, one-line description)
_BENCHMARKS: dict[str, tuple[str, str]] = {
    "service": ("badf.bench._service", "round trip (frame + query) and query throughput, service beside in-process"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    benchmarks = parser.add_subparsers(dest="benchmark", required=True, metavar="BENCHMARK")
    for name, (module, description) in _BENCHMARKS.items():
        importlib.import_module(module).add_arguments(
            benchmarks.add_parser(name, help=description, description=description)
        )


def run(args: argparse.Namespace) -> int:
    return int(importlib.import_module(_BENCHMARKS[args.benchmark][0]).run(args) or 0)
