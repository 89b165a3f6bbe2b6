"""The service benchmark runs end to end (tiny sizes): worker and echo processes, tables and JSON."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import meshes

from badf.bench import _cli


def test_service_benchmark_runs(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    _cli.add_arguments(parser)
    args = parser.parse_args(
        [
            "service",
            "--small",
            "--device",
            "cpu",
            "--mesh",
            str(meshes.data_file("spot")),
            "--round-trips",
            "3",
            "--repeats",
            "2",
            "--batches",
            "256,1024",
            "--out",
            str(tmp_path),
        ]  # fmt: skip
    )
    assert _cli.run(args) == 0
    report = json.loads((tmp_path / "service.json").read_text())
    names = [timing["name"] for timing in report["timings"]]
    assert "round trip, service" in names and "query 1024 pts, Zenoh echo" in names
    assert all(timing["samples"] > 0 and timing["median_ms"] > 0 for timing in report["timings"])
    assert (tmp_path / "service.md").read_text().startswith("# badf service benchmark")
