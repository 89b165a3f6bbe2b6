"""The viewer benchmark runs end to end at tiny sizes: a worker process, the client rows, the viewer's own
work, a running viewer following a stream, the table and the JSON; and the slider's way, which must move on every
call."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import meshes
import numpy as np
import pytest

from badf.bench import _cli, viewer


def test_viewer_benchmark_runs(tmp_path: Path) -> None:
    out = tmp_path / "viewer.json"
    parser = argparse.ArgumentParser()
    _cli.add_arguments(parser)
    flags = ["--mesh", str(meshes.data_file("spot")), "--device", "cpu", "--depth", "4", "--resolution", "64"]
    # two timed calls: the fewest that once came back to where the warm-up had left the slider and waited for good
    flags += ["--repeats", "2", "--follow-s", "1", "--stream-fps", "20", "--out", str(out)]
    assert _cli.run(parser.parse_args(["viewer", *flags])) == 0
    report = json.loads(out.read_text())
    names = [timing["what"] for timing in report["timings"]]
    assert "slice 64x64 + cells (the viewer's request)" in names
    assert any(name.startswith("viewer end to end") for name in names)
    assert all(timing["samples"] == 2 and timing["median_ms"] > 0 for timing in report["timings"])
    assert [f["what"] for f in report["following"]] == ["defaults (slices <= 20/s)", "lifted (1000/s)"]
    assert all(f["frames_streamed"] > 0 and f["slices_drawn"] > 0 for f in report["following"])
    # the slices' accuracy against the float64 oracle, beside their times
    assert report["accuracy"]["points"] == 1000 and 0 < report["accuracy"]["max_error_diag"] < 0.5


@pytest.mark.parametrize("count", [1, 2, 3, 4, 5, 7, 100])
def test_the_slider_moves_on_every_call_warm_up_included(count: int) -> None:
    """The end-to-end row waits for a slice at the slider's new position, so no call may leave it where it was."""
    vertices = np.random.default_rng(count).normal(size=(50, 3))
    slider = viewer._slider(vertices, 0, count)
    calls = [slider[k % len(slider)] for k in range(viewer._WARM_UP + count + len(slider))]
    assert all(a != b for a, b in zip(calls, calls[1:]))
    low, high = vertices[:, 0].min(), vertices[:, 0].max()
    assert low < slider.min() and slider.max() < high
    sweep = viewer._sweep(vertices, 0, count)
    assert len(sweep) == count and all(a != b for a, b in zip(sweep, sweep[1:]))
