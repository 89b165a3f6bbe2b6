"""`badf bench accuracy` end to end on a small configuration, so the GPU run does not meet a broken script."""

from __future__ import annotations

import argparse
import json

from badf.bench import _tolerances as tol
from badf.bench import accuracy


def test_small_accuracy_run_writes_consistent_results(tmp_path):
    parser = argparse.ArgumentParser()
    accuracy.add_arguments(parser)
    args = parser.parse_args([
        "--device", "cpu", "--meshes", "spot", "--depths", "3,4", "--dense-max-depth", "4", "--switch-depth", "4",
        "--points", "60", "--near-points", "40", "--query-batch", "2000", "--repeat", "1", "--switch-meshes", "spot",
        "--no-stability", "--workers", "1", "--out-dir", str(tmp_path),
    ])
    assert accuracy.run(args) == 0
    report = json.loads((tmp_path / "results" / "accuracy-cpu.json").read_text())
    assert (tmp_path / "accuracy-cpu.md").read_text().count("| ADF, surface-coverage refinement |") == 2
    assert (tmp_path / "accuracy-cpu-error-vs-time.png").stat().st_size > 0
    assert (tmp_path / "accuracy-cpu-error-vs-depth.png").stat().st_size > 0
    rows = {(r["mode"], r["depth"]): r for r in report["rows"]}
    assert set(rows) == {(m, d) for m in ("adf-surface", "adf-centroid", "dense") for d in (3, 4)} | {("exact", 4)}
    for row in report["rows"]:
        for point_set in accuracy.POINT_SETS:
            assert row["errors"][point_set]["nonfinite"] == 0
    for point_set in accuracy.POINT_SETS:
        assert rows["exact", 4]["errors"][point_set]["max"] <= tol.EXACT_DISTANCE
    # a finer lattice halves the dense grid's error near the surface (fixed seeds: the same points every run)
    assert rows["dense", 4]["errors"]["near"]["max"] < rows["dense", 3]["errors"]["near"]["max"]
    assert len(report["switches"]) == 7
