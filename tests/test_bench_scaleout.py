"""The scale-out benchmark runs end to end at tiny sizes on the CPU: router and worker processes, client
processes, placement, the table and the JSON. (Its CPU numbers are not scaling evidence: the workers share
this machine's cores.)"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import meshes

from badf.bench import _cli


def test_scaleout_benchmark_runs(tmp_path: Path) -> None:
    out = tmp_path / "scaleout.json"
    parser = argparse.ArgumentParser()
    _cli.add_arguments(parser)
    flags = ["--mesh", str(meshes.data_file("spot")), "--device", "cpu", "--workers", "2", "--clients", "2"]
    flags += ["--points", "256", "--seconds", "1", "--depth", "4", "--warmup", "2", "--out", str(out)]
    assert _cli.run(parser.parse_args(["scaleout", *flags])) == 0
    report = json.loads(out.read_text())
    runs = report["runs"]
    assert [(run["workers"], run["clients"]) for run in runs] == [(1, 2), (2, 2)]
    assert runs[0]["placement"] == {"w0": 2} and runs[1]["placement"] == {"w0": 1, "w1": 1}
    assert sorted(client["worker"] for client in runs[1]["per_client"]) == ["w0", "w1"]
    for run in runs:
        clients = run["per_client"]
        assert run["round_trips"] == sum(client["round_trips"] for client in clients) > 0
        assert all(client["points"] == client["round_trips"] * 256 for client in clients)
        # a warm-up frame that a warm-up query overtook may be applied inside the timed window
        assert all(client["frames_applied"] <= client["round_trips"] + 1 for client in clients)
        assert sum(client["frames_applied"] for client in clients) > 0
        assert run["frames_per_s"] > 0 and run["points_per_s"] > 0 and run["median_ms"] > 0
        answered = sum(worker["points_answered"] for worker in run["per_worker"].values())
        assert 0 < answered <= sum(client["points"] for client in clients)
    assert runs[0]["frames_speedup"] == runs[0]["points_speedup"] == 1.0
    # the answers' accuracy beside the speeds: an object on each worker against the float64 oracle
    assert [run["accuracy"]["objects"] for run in runs] == [1, 2]
    assert all(run["accuracy"]["points"] == 1000 and 0 < run["accuracy"]["max_error_diag"] < 0.5 for run in runs)
