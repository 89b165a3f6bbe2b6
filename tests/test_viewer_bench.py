"""The viewer benchmark runs end to end at tiny sizes: a worker process, the client rows, the viewer's own
work, a running viewer following a stream, the table and the JSON."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import meshes

from badf.bench import _cli


def test_viewer_benchmark_runs(tmp_path: Path) -> None:
    out = tmp_path / "viewer.json"
    parser = argparse.ArgumentParser()
    _cli.add_arguments(parser)
    flags = ["--mesh", str(meshes.data_file("spot")), "--device", "cpu", "--depth", "4", "--resolution", "64"]
    flags += ["--repeats", "3", "--follow-s", "1", "--stream-fps", "20", "--out", str(out)]
    assert _cli.run(parser.parse_args(["viewer", *flags])) == 0
    report = json.loads(out.read_text())
    names = [timing["what"] for timing in report["timings"]]
    assert "slice 64x64 + cells (the viewer's request)" in names
    assert any(name.startswith("viewer end to end") for name in names)
    assert all(timing["samples"] == 3 and timing["median_ms"] > 0 for timing in report["timings"])
    assert [f["what"] for f in report["following"]] == ["defaults (slices <= 20/s)", "lifted (1000/s)"]
    assert all(f["frames_streamed"] > 0 and f["slices_drawn"] > 0 for f in report["following"])
    # the slices' accuracy against the float64 oracle, beside their times
    assert report["accuracy"]["points"] == 1000 and 0 < report["accuracy"]["max_error_diag"] < 0.5
