"""The soak benchmark as a test: 8 client processes x 4 objects on one worker (CPU back-end), streaming,
updating, querying and slicing for BADF_SOAK_SECONDS (20 s by default in CI; 60 s for the table in
docs/hardening.md), bounded also by a round count and a deadline for the whole run.

Held: every acknowledged update is the frame then applied and answered; every answer fits the frame it
names; no error replies at all; each object's counters account for every frame sent; the worker's
resident memory grows by at most 16 MiB after the warm-up and the engine's device bytes not at all.
"""

from __future__ import annotations

import os

from badf.bench.soak import SoakSettings, run_soak

SOAK_SECONDS = float(os.environ.get("BADF_SOAK_SECONDS", "20"))
RSS_GROWTH_BOUND_MIB = 16.0


def test_soak_loses_nothing_and_stays_flat() -> None:
    report = run_soak(SoakSettings(clients=8, objects_per_client=4, seconds=SOAK_SECONDS, device="cpu", depth=4))
    assert report.errors == {}, report.final_failures[:5]
    assert report.wrong_answers == []
    assert report.final_failures == []
    assert all(client["rounds"] >= 1 for client in report.clients), "a client made no progress"
    assert report.totals["updates_acknowledged"] == sum(
        client["updates_acknowledged"] for client in report.clients
    ) >= len(report.clients) * 4
    assert report.rss_growth_mib <= RSS_GROWTH_BOUND_MIB, report.rss_mib
    assert report.device_bytes_growth <= 0, report.device_bytes
    assert report.worker_exit_code == 0, "the worker did not stop cleanly"
