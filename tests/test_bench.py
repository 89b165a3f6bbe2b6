"""The service benchmark runs end to end at tiny sizes: worker and echo processes, the table and the JSON."""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import meshes
import pytest
import tolerances as tol
from conftest import as_from_a_terminal, process_group_members, wait_until

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
    # the times' accuracy: the served answers equal the engine's in-process ones, and the oracle bounds both
    assert report["accuracy"]["service_equals_in_process"]
    assert report["accuracy"]["points"] == 1000 and 0 < report["accuracy"]["max_error_diag"] < 0.5
    assert next(t for t in report["timings"] if t["what"] == "update, service")["request_bytes"] > 0


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
    # none measured but the build, where its estimate from the area missed
    assert first["moving_domain_moves"] == 3 and first["moving_measured_frames"] <= 1
    assert first["builds_measured"] == 0  # spot is smooth at depth 4: its first frames are planned from the area
    assert 0 <= first["adf_vs_exact_max_error_diag"] < 1
    assert report["dense_baseline"]["query_ms"] > 0
    # each speed with its accuracy against the float64 oracle: exact queries within the exact tolerance, ADF
    # interpolation's error larger on average, and bounded
    assert first["exact_vs_oracle"]["points"] == 1000
    assert first["exact_vs_oracle"]["max_error_diag"] <= tol.EXACT_DISTANCE
    assert first["exact_vs_oracle"]["mean_error_diag"] <= first["adf_vs_oracle"]["mean_error_diag"]
    assert 0 < first["adf_vs_oracle"]["max_error_diag"] < 0.5
    assert report["dense_baseline"]["grid_vs_oracle"]["points"] == 1000
    # a run of rigid frames gives back the frame scratch
    rigid = report["rigid"]["rigid"]
    assert rigid["scratch_given_back"] == 1 and rigid["device_mib_after_run"] < rigid["device_mib_before_run"]
    assert len(rigid["rebuild_after_run_wall_ms"]) == 3
    # the violent frame's rows: each phase timed, the plan never held more after the give-back's frames than
    # while the violent frame's was kept, and the corners after it all exact
    violent = report["violent"]
    assert list(violent["phases"]) == ["calm before", "the violent frame", "calm, its plan kept", "calm, plan given back"]
    assert all(phase["update_gpu_ms"] > 0 and phase["corners"] > 0 for phase in violent["phases"].values())
    assert violent["phases"]["calm, plan given back"]["device_mib"] <= violent["phases"]["calm, its plan kept"]["device_mib"]
    assert violent["corners_vs_oracle"]["max_error_diag"] <= tol.EXACT_DISTANCE and violent["domain_moves"] == 0


def test_engine_benchmark_runs_on_the_sah_tree(tmp_path: Path) -> None:
    """`badf bench engine --quick --bvh sah`: the main configuration on the SAH-shaped BVH, exact as on the
    Morton one, the shape's host time reported."""
    report = _run_engine_bench(tmp_path, "--depth", "4", "--repeat", "2", "--quick", "--bvh", "sah")
    (first,) = report["configurations"]
    assert first["options"] == {"depth": 4, "bvh": "sah"} and first["bvh_shape_ms"] > 0
    assert first["exact_vs_oracle"]["max_error_diag"] <= tol.EXACT_DISTANCE
    assert first["update_gpu_ms"] > 0 and first["moving_domain_moves"] == 2


def test_engine_sign_sweep_runs(tmp_path: Path) -> None:
    """`badf bench engine --sign-sweep`: each sign method resolved as asked (auto: pseudonormals on a closed
    mesh), with its update's stage times."""
    report = _run_engine_bench(tmp_path, "--depth", "3", "--repeat", "2", "--sign-sweep")
    resolved = {r["options"]["sign"]: r["sign_resolved"] for r in report["signs"]}
    assert resolved == {"auto": "pseudonormal", "pseudonormal": "pseudonormal", "winding": "winding", "none": "none"}
    assert all(r["update_gpu_ms"] > 0 and "normals" in r["update_stages_ms"] for r in report["signs"])


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP], ids=["sigterm", "hangup"])
def test_a_signal_ends_a_benchmark_and_the_processes_it_started(tmp_path: Path, signum) -> None:
    """SIGTERM or SIGHUP to `badf bench service` ended it at once and left its worker and echo router running,
    still listening on their ports (outside check, 2026-11-22). They now end a run as Ctrl-C does."""
    command = [sys.executable, "-m", "badf.cli", "bench", "service", "--mesh", str(meshes.data_file("spot")),
               "--device", "cpu", "--depth", "4", "--small", "--round-trips", "100000", "--batches", "1024",
               "--out", str(tmp_path / "service.json")]  # fmt: skip
    # a session of its own, so the benchmark and everything it starts share one process group to inspect
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               start_new_session=True, preexec_fn=as_from_a_terminal)  # fmt: skip
    try:
        # the benchmark, the resource tracker, the echo router and the worker
        wait_until(lambda: len(process_group_members(process.pid)) >= 4, timeout=300,
                   what="the benchmark's worker and echo router to start")  # fmt: skip
        os.kill(process.pid, signum)
        output, _ = process.communicate(timeout=180)
        assert process.returncode == 130, output
        assert "stopped before the end" in output
        wait_until(lambda: not process_group_members(process.pid), timeout=120,
                   what="every process the benchmark started to end")  # fmt: skip
        assert not (tmp_path / "service.json").exists()
    finally:
        if process_group_members(process.pid):
            os.killpg(process.pid, signal.SIGKILL)  # the group this test started
        if process.poll() is None:
            process.wait()


def test_interleave_times_variants_in_turn_and_holds_their_answers_to_the_oracle(tmp_path: Path) -> None:
    """`python3 -m badf.bench.interleave` with the working tree twice: each variant in its own process imports the
    folder it was given, runs its rounds, and answers the same points as the other, within the oracle's bounds."""
    from badf.bench import interleave

    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "interleave.json"
    flags = ["--variant", f"a={root}", "--variant", f"b={root}", "--mesh", str(meshes.data_file("spot")),
             "--depth", "3", "--device", "cpu", "--rounds", "2", "--frames", "1", "--warm-up", "1", "--points", "50",
             "--queries", "1", "--out", str(out)]
    assert interleave.main(flags) == 0
    report = json.loads(out.read_text())
    a, b = report["variants"]["a"], report["variants"]["b"]
    for variant in (a, b):
        assert variant["engine"] == str(root / "server" / "adf" / "__init__.py")
        assert variant["wall_ms"]["frames"] == 2 and variant["wall_ms"]["median"] > 0
        assert variant["exact_max_error_diag"] <= tol.EXACT_DISTANCE
        assert 0 < variant["adf_max_error_diag"] < 0.5
    assert b["adf_max_difference_from_first_diag"] == 0.0  # the same code answers the same, bit for bit
    assert a["wall_vs_first_ms"] == a["after_upload_vs_first_ms"] == 0.0  # the first against itself, round by round
    assert abs(b["wall_vs_first_ms"]) < max(a["wall_ms"]["p90"], b["wall_ms"]["p90"])
    for batch in ("near", "box"):  # --queries: each variant timed both batches, and the same code answers alike
        assert a["queries"][batch]["median_ms"] > 0 and a["queries"][batch]["vs_first_ms"] == 0.0
        assert b["queries"][batch]["answered_exactly"] == a["queries"][batch]["answered_exactly"]
    with pytest.raises(SystemExit):
        interleave.main(["--variant", f"a={root}", "--mesh", "spot"])  # one variant compares nothing
    with pytest.raises(SystemExit, match="has no"):
        interleave.main(["--variant", f"a={root}", "--variant", f"b={tmp_path}", "--mesh", "spot", "--device", "cpu"])
