"""The service benchmark runs end to end at tiny sizes: worker and echo processes, the table and the JSON."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import meshes

from badf.bench import _cli


def test_service_benchmark_runs(tmp_path: Path) -> None:
    out = tmp_path / "service.json"
    parser = argparse.ArgumentParser()
    _cli.add_arguments(parser)
    flags = ["--mesh", str(meshes.data_file("spot")), "--device", "cpu", "--depth", "5", "--small"]
    flags += ["--round-trips", "3", "--repeats", "2", "--batches", "256,1024", "--out", str(out)]
    assert _cli.run(parser.parse_args(["service", *flags])) == 0
    report = json.loads(out.read_text())
    names = [timing["what"] for timing in report["timings"]]
    assert "round trip, service" in names and "query 1024 pts, Zenoh echo" in names
    assert all(timing["samples"] > 0 and timing["median_ms"] > 0 for timing in report["timings"])
    assert report["worker_field_stats"]["frame"] > 0
