"""What the benchmarks share: finding meshes, a smooth deformation for frames, tables, device names."""

from __future__ import annotations

import datetime
import os
import pathlib

import numpy as np


# The repository's root when running from a checkout (an editable install).
REPOSITORY = pathlib.Path(__file__).resolve().parents[1]


class BenchFlagError(ValueError):
    """A benchmark flag whose value would fail the run, or make it measure nothing (`badf bench` exits 2)."""


def mesh_folders() -> list[pathlib.Path]:
    """Where named meshes are looked for: $BADF_SHARED_DATA, the bundled test data, the shared folder beside
    the checkout."""
    folders = [REPOSITORY / "tests" / "data", REPOSITORY.parent / "shared" / "data"]
    if os.environ.get("BADF_SHARED_DATA"):
        folders.insert(0, pathlib.Path(os.environ["BADF_SHARED_DATA"]))
    return folders


def names_a_path(name: str) -> bool:
    """Whether a --mesh(es) value is a file's path by its form (a suffix, or a folder), not a shared mesh's name."""
    given = pathlib.Path(name)
    return bool(given.suffix) or len(given.parts) > 1


def find_mesh(name: str) -> pathlib.Path:
    """A mesh file's path as given, or the .npz of a named mesh (e.g. "stanford-bunny"); FileNotFoundError
    naming the folders searched."""
    given = pathlib.Path(name)
    if names_a_path(name) or given.is_file():  # a path: its reader says what is wrong with it
        return given
    for folder in mesh_folders():
        path = folder / f"{name}.npz"
        if path.exists():
            return path
    raise FileNotFoundError(f"{name}.npz is in none of {', '.join(map(str, mesh_folders()))}; "
                            "set BADF_SHARED_DATA to a folder that holds it")


def deform(vertices: np.ndarray, t: float, amplitude: float = 0.01) -> np.ndarray:
    """A smooth, time-varying wobble of `amplitude` bounding-box diagonals: a stand-in for an animation."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    diag = float(np.linalg.norm((hi - lo).astype(np.float64)))
    phase = 2.0 * np.pi * ((vertices - lo) / np.maximum(hi - lo, 1e-30) + t)
    return (vertices + amplitude * diag * np.sin(phase[:, [1, 2, 0]])).astype(np.float32)


def timestamp() -> str:
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def start_warp(requested: str | None) -> str:
    """Initialise Warp quietly; the device asked for, else the first GPU, else the CPU."""
    import warp as wp

    wp.config.log_level = wp.LOG_ERROR
    wp.init()
    if requested is not None:
        return requested
    return "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"


def fill_sized_defaults(args, small: dict, full: dict) -> None:
    """Give every flag left unset its CPU-sized default (with --small) or its full one."""
    for name, value in (small if args.small else full).items():
        if getattr(args, name) is None:
            setattr(args, name, value)


def bench_device_name(device: str) -> str:
    import warp as wp

    d = wp.get_device(device)
    if d.is_cuda:
        return f"{d.name} ({device})"
    import platform

    return f"CPU back-end: {platform.processor() or platform.machine()}, {_cpu_count()} cores"


def _cpu_count() -> int:
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def print_table(title: str, header: list[str], rows: list[list]) -> None:
    cells = [[str(h) for h in header]] + [[f"{c:.4g}" if isinstance(c, float) else str(c) for c in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    print(f"\n{title}")
    for k, row in enumerate(cells):
        print("  ".join(cell.rjust(w) for cell, w in zip(row, widths)))
        if k == 0:
            print("  ".join("-" * w for w in widths))
