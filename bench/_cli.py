"""`badf bench NAME [flags]`: run one benchmark (engine, accuracy, service, scaleout, soak)."""

from __future__ import annotations

import argparse
import importlib
import math
import pathlib
import signal
import sys
import tempfile
import threading
from contextlib import contextmanager
from typing import Iterator

from badf.bench._common import BenchFlagError
from badf.cli._extras import missing_extra
from badf.protocol import DEFAULT_LIMITS
from badf.server._cuda import device_problem
from badf.server._mesh_files import MeshFileError
from badf.server._signals import on_stop_signals, stop_signals
from badf.web_viewer._viewer import RESOLUTIONS

_BENCHMARKS = {
    "engine": ("badf.bench.engine", "per-stage build/update times, memory, and the dense-grid baseline"),
    "service": ("badf.bench.service", "frame + query round trip and query throughput, service beside in-process"),
    "viewer": ("badf.bench.viewer", "slice round trips as the viewer asks, its drawing, and following a stream"),
    "scaleout": ("badf.bench.scaleout", "aggregate frames and query points per second, one worker against N (GPUs)"),
    "accuracy": ("badf.bench.accuracy", "error against run time (ADF depths, exact, dense grid, CPU peers) and the "
                 "stability table"),
    "soak": ("badf.bench.soak", "clients x objects streaming and querying for a bounded time; answers and memory "
             "checked"),
    "random-check": ("badf.bench.random_check", "random meshes, options and frames against the float64 oracle, for "
                     "a bounded time; every problem printed with the seed that reproduces it"),
}

# What the benchmarks import beyond the client (all of it in badf[bench]), checked before a run starts: it
# was a traceback, and for accuracy's plots (matplotlib) one after the whole run.
_NEEDS = ("warp", "trimesh")
_NEEDS_MORE = {"accuracy": ("tqdm", "matplotlib")}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", choices=sorted(_BENCHMARKS), help="; ".join(f"{k}: {v[1]}" for k, v in _BENCHMARKS.items()))
    parser.add_argument("rest", nargs=argparse.REMAINDER, help="flags of that benchmark (see badf bench NAME --help)")


def run(args: argparse.Namespace) -> int:
    module = importlib.import_module(_BENCHMARKS[args.name][0])
    sub = argparse.ArgumentParser(prog=f"badf bench {args.name}", description=_BENCHMARKS[args.name][1])
    module.add_arguments(sub)
    flags = sub.parse_args(args.rest)
    missing = missing_extra(f"badf bench {args.name}", _NEEDS + _NEEDS_MORE.get(args.name, ()), "bench")
    if missing is not None:
        print(missing, file=sys.stderr)
        return 2
    try:
        check_flags(flags)
        with _stop_signals_as_ctrl_c():
            return int(module.run(flags) or 0)
    except (MeshFileError, BenchFlagError) as error:
        print(f"badf bench {args.name}: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\nbadf bench {args.name}: stopped before the end", file=sys.stderr)
        return 130


def main_of(name: str) -> int:
    """`python -m badf.bench.NAME [flags]`, each benchmark's main(): the run `badf bench NAME [flags]` makes,
    flag checks, one-line errors and stop signals included (the modules parsed their flags and ran on their
    own, so `--seconds 0` ran and a missing --mesh file was a traceback; eleventh outside check)."""
    return run(argparse.Namespace(name=name, rest=sys.argv[1:]))


@contextmanager
def _stop_signals_as_ctrl_c() -> Iterator[None]:
    """SIGTERM and SIGHUP end a run as Ctrl-C does (KeyboardInterrupt), so the benchmarks' `finally` blocks
    end the workers and clients they started. Before, `bench service`, `soak`, `scaleout` and `viewer` died at
    once on either and left them running on their ports (outside check, 2026-11-22). The handlers before
    are put back afterwards (the benchmarks also run inside other programs, tests among them)."""
    if threading.current_thread() is not threading.main_thread():
        yield  # only the main thread may set handlers; a caller on another thread keeps its own
        return
    before = {signum: signal.getsignal(signum) for signum in stop_signals()}
    on_stop_signals(signal.default_int_handler)
    try:
        yield
    finally:
        for signum, handler in before.items():
            signal.signal(signum, handler)


# What each flag of the benchmarks may be, by its name (argparse's dest); a flag left at None is not checked.
_AT_LEAST_ONE = {"cases", "repeat", "repeats", "round_trips", "points", "near_points", "query_batch", "large_batch",
                 "workers", "objects", "grid", "max_rounds"}
_DEPTHS = {"depth", "dense_max_depth", "switch_depth", "far_sweep", "split_sweep"}
_POSITIVE_SECONDS = {"seconds", "follow_s", "stream_fps", "budget"}
_NOT_NEGATIVE = {"warm_up", "warmup"}
_COMMA_LISTS = {"depths": _DEPTHS, "batches": _AT_LEAST_ONE, "clients": _AT_LEAST_ONE}


def _largest_cube_grid() -> int:
    """The finest `soak --grid` whose cube (6 (g+1)^2 vertices, 12 g^2 faces) a worker takes."""
    grid = math.isqrt(DEFAULT_LIMITS.max_faces // 12)
    while 6 * (grid + 1) ** 2 > DEFAULT_LIMITS.max_vertices:
        grid -= 1
    return grid


# Sizes past what a worker takes in one message: the run would build them (minutes, gigabytes) to be refused.
_IN_ONE_MESSAGE = "what a worker takes in one message"
# Counts and times past any run's use: 1e10 round trips asked for 74.5 GiB of timings, and 10^20 seconds or
# repeats ended in tracebacks, some after the worker had started (seventeenth outside check).
_BEYOND_USE = "a bound on what a run can use"
_WEEK_S = 7 * 24 * 3600
_AT_MOST: dict[str, tuple[float, str]] = {
    **{dest: (DEFAULT_LIMITS.max_points, _IN_ONE_MESSAGE) for dest in ("points", "batches")},
    **{dest: (10**8, _BEYOND_USE) for dest in ("near_points", "query_batch", "large_batch")},  # in-process queries
    "grid": (_largest_cube_grid(), _IN_ONE_MESSAGE),
    **{dest: (10**6, _BEYOND_USE) for dest in ("repeat", "repeats", "round_trips", "max_rounds")},
    **{dest: (256, _BEYOND_USE) for dest in ("workers", "clients")},
    "objects": (10_000, _BEYOND_USE),
    **{dest: (_WEEK_S, "a week") for dest in ("seconds", "follow_s", "budget", "warm_up", "warmup")},
    "stream_fps": (10_000, _BEYOND_USE),
}


def _check_writable(folder: pathlib.Path, flag: str) -> None:
    """BenchFlagError unless a file can be made in `folder`, tried by making one: results were lost at the
    end of a run whose folder could not be written (/proc, a read-only mount; seventeenth outside check)."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as error:
        raise BenchFlagError(f"{flag}: cannot write in {str(folder)!r}: {error.strerror or error}") from None


def check_flags(flags: argparse.Namespace) -> None:
    """BenchFlagError naming the first flag whose value no run could use, before anything starts (a
    benchmark that fails after minutes, or that measures nothing and reports success, helps nobody)."""
    from badf.server.adf._tolerances import MAX_DEPTH

    for dest, value in vars(flags).items():
        if value is None:
            continue
        flag = "--" + dest.replace("_", "-")
        if dest in _COMMA_LISTS:
            if isinstance(value, str):
                try:
                    value = [int(part) for part in value.split(",")]
                except ValueError:
                    raise BenchFlagError(f"{flag} takes integers separated by commas, got {value!r}") from None
            rule = _COMMA_LISTS[dest]
        else:
            rule = {dest} & (_AT_LEAST_ONE | _DEPTHS | _POSITIVE_SECONDS | _NOT_NEGATIVE)
        values = value if isinstance(value, list) else [value]
        if rule & _DEPTHS and not all(1 <= v <= MAX_DEPTH for v in values):
            raise BenchFlagError(f"{flag} must be in 1..{MAX_DEPTH}, got {value}")
        if rule & _AT_LEAST_ONE and not all(v >= 1 for v in values):
            raise BenchFlagError(f"{flag} must be at least 1, got {value}")
        if rule & _POSITIVE_SECONDS and not (math.isfinite(value) and value > 0):
            raise BenchFlagError(f"{flag} must be a positive finite number, got {value}")
        if rule & _NOT_NEGATIVE and not (math.isfinite(value) and value >= 0):
            raise BenchFlagError(f"{flag} must be a finite number >= 0, got {value}")
        if dest in _AT_MOST and not all(v <= _AT_MOST[dest][0] for v in values):
            most, why = _AT_MOST[dest]
            raise BenchFlagError(f"{flag} must be at most {most:,} ({why}), got {value}")
    for dest in ("out", "screenshot"):  # written at the end: a folder that is not there would lose the run
        path = getattr(flags, dest, None)
        if path is None:
            continue
        folder = pathlib.Path(path).resolve().parent
        if not folder.is_dir():
            raise BenchFlagError(f"--{dest}: the folder of {path!r} does not exist")
        if pathlib.Path(path).is_dir():  # the run's results were lost at the end
            raise BenchFlagError(f"--{dest}: {path!r} is a folder; name a file in it")
        _check_writable(folder, f"--{dest}")
    resolution = getattr(flags, "resolution", None)  # the viewer's: it refused others after the run had begun
    if resolution is not None and resolution not in RESOLUTIONS:
        raise BenchFlagError(f"--resolution must be one of {', '.join(map(str, RESOLUTIONS))}, got {resolution}")
    out_dir = getattr(flags, "out_dir", None)  # made if missing; a file there would fail the run at its end
    if out_dir is not None and pathlib.Path(out_dir).exists() and not pathlib.Path(out_dir).is_dir():
        raise BenchFlagError(f"--out-dir: {out_dir!r} is a file; name a folder")
    if out_dir is not None:
        try:
            pathlib.Path(out_dir).mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise BenchFlagError(f"--out-dir: cannot make {out_dir!r}: {error.strerror or error}") from None
        _check_writable(pathlib.Path(out_dir), "--out-dir")
    render = getattr(flags, "render", None)
    if render is not None and not pathlib.Path(render).is_file():
        raise BenchFlagError(f"--render: no such file {render!r}")
    device = getattr(flags, "device", None)
    problem = None if device is None else device_problem(device)
    if problem is not None:
        raise BenchFlagError(problem)
