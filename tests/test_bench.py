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


def _run_engine_bench(tmp_path: Path, *flags: str) -> dict:
    """`badf bench engine` on the CPU on spot with these flags; the JSON it wrote."""
    out = tmp_path / "engine.json"
    parser = argparse.ArgumentParser()
    _cli.add_arguments(parser)
    common = ["--mesh", str(meshes.data_file("spot")), "--device", "cpu", "--out", str(out)]
    assert _cli.run(parser.parse_args(["engine", *common, *flags])) == 0
    return json.loads(out.read_text())


def test_engine_benchmark_runs(tmp_path: Path) -> None:
    """`badf bench engine --quick` at a small depth: the table's figures, frames that move the domain
    (each one planned, none measured again), the query error against exact queries, the dense baseline."""
    report = _run_engine_bench(tmp_path, "--depth", "4", "--repeat", "3", "--quick")
    (first,) = report["configurations"]
    for key in ("build_gpu_ms", "update_gpu_ms", "update_wall_ms", "moving_update_gpu_ms", "moving_update_wall_ms"):
        assert first[key] > 0, key
    assert first["moving_domain_moves"] == 3 and first["moving_measured_frames"] == 1  # the build only
    assert 0 <= first["adf_vs_exact_max_error_diag"] < 1
    assert report["dense_baseline"]["query_ms"] > 0


def test_engine_sign_sweep_runs(tmp_path: Path) -> None:
    """`badf bench engine --sign-sweep`: each sign method resolved as asked (auto: pseudonormals on a closed
    mesh), with its update's stage times."""
    report = _run_engine_bench(tmp_path, "--depth", "3", "--repeat", "2", "--sign-sweep")
    resolved = {r["options"]["sign"]: r["sign_resolved"] for r in report["signs"]}
    assert resolved == {"auto": "pseudonormal", "pseudonormal": "pseudonormal", "winding": "winding", "none": "none"}
    assert all(r["update_gpu_ms"] > 0 and "normals" in r["update_stages_ms"] for r in report["signs"])
