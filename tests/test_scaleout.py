"""Scale-out: `badf serve --connect / --router-only / --gpus`, and the client across several workers."""

from __future__ import annotations

import argparse
import threading
import time

import numpy as np
import pytest
import zenoh
from conftest import wait_until
from test_worker_plumbing import FACES, POINTS, VERTICES, ThreadWorker, expected_distance

from badf.client import Client
from badf.protocol import (
    InfoRequest,
    KeySpace,
    NotSupportedError,
    ObjectExistsError,
    ObjectInfo,
    ObjectOptions,
    ObjectUnavailableError,
    WorkerUnavailableError,
    decode,
    encode,
    zenoh_config,
)
from badf.server import RouterSettings, _cli, _cuda

KEYS = KeySpace()


def serve_args(*flags: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    _cli.add_arguments(parser)
    return parser.parse_args(list(flags))


def test_a_worker_that_joins_a_router_takes_no_port_unless_told() -> None:
    alone = _cli.settings_from(serve_args())
    assert alone.zenoh_config().get_json("listen/endpoints") == '["tcp/127.0.0.1:7447"]'
    joining = _cli.settings_from(serve_args("--connect", "tcp/10.0.0.1:7447"))
    assert joining.zenoh_config().get_json("listen/endpoints") == "[]"
    assert joining.zenoh_config().get_json("connect/endpoints") == '["tcp/10.0.0.1:7447"]'
    assert joining.zenoh_config().get_json("mode") == '"router"'
    own = _cli.settings_from(serve_args("--connect", "tcp/10.0.0.1:7447", "--listen", "tcp/0.0.0.0:7448"))
    assert own.zenoh_config().get_json("listen/endpoints") == '["tcp/0.0.0.0:7448"]'


def test_router_only_settings() -> None:
    router = _cli.router_settings_from(serve_args("--router-only", "--listen", "tcp/0.0.0.0:7447", "--namespace", "lab"))
    assert router == RouterSettings(namespace="lab", listen=("tcp/0.0.0.0:7447",))
    config = router.zenoh_config(extra_listen=("tcp/127.0.0.1:9999",))
    assert config.get_json("listen/endpoints") == '["tcp/0.0.0.0:7447","tcp/127.0.0.1:9999"]'
    assert config.get_json("mode") == '"router"'
    assert RouterSettings().zenoh_config().get_json("listen/endpoints") == '["tcp/127.0.0.1:7447"]'
    assert _cli.run(serve_args("--router-only", "--worker-id", "w1")) == 2
    assert _cli.run(serve_args("--router-only", "--mode", "peer")) == 2
    with pytest.raises(SystemExit):
        serve_args("--router-only", "--device", "cpu")  # argparse: not allowed together


def test_gpus_take_all_or_indices() -> None:
    assert _cuda.parse_gpus("all", 2) == [0, 1]
    assert _cuda.parse_gpus("1", 2) == [1]
    assert _cuda.parse_gpus("0,1", 2) == [0, 1]
    for wrong, match in (("2", "only devices 0 to 1"), ("0,0", "twice"), ("one", "'all' or device indices")):
        with pytest.raises(ValueError, match=match):
            _cuda.parse_gpus(wrong, 2)


def test_gpus_without_a_gpu_says_so(monkeypatch, capsys) -> None:
    def none_visible() -> int:
        raise _cuda.NoCudaDeviceError("no CUDA device is visible: the CUDA driver reports none")

    monkeypatch.setattr(_cli, "visible_cuda_device_count", none_visible)
    assert _cli.run(serve_args("--gpus", "all")) == 2
    assert "no CUDA device is visible" in capsys.readouterr().err
    monkeypatch.setattr(_cli, "visible_cuda_device_count", lambda: 2)
    assert _cli.run(serve_args("--gpus", "0,5")) == 2
    assert "only devices 0 to 1" in capsys.readouterr().err
    assert _cli.run(serve_args("--gpus", "all", "--mode", "peer")) == 2


def test_this_machine_reports_its_cuda_devices_or_why_not() -> None:
    try:
        count = _cuda.visible_cuda_device_count()
    except _cuda.NoCudaDeviceError as error:
        assert str(error).startswith("no CUDA device is")
    else:
        assert count >= 1


# --- the client across workers (stand-in fields, workers in threads of this process) ---------------------


def test_workers_report_their_load(endpoint: str) -> None:
    with ThreadWorker(endpoint), Client(endpoint, timeout=10) as client:
        obj = client.register("blob", VERTICES, FACES)
        obj.update(VERTICES + 1)
        obj.query(POINTS)
        [info] = client.workers()
        assert (info.object_count, info.vertex_count, info.face_count) == (1, len(VERTICES), len(FACES))
        assert (info.frames_applied, info.queries_answered, info.points_answered) == (1, 1, len(POINTS))
        assert info.requests_waiting == 0


def test_a_worker_that_leaves_makes_its_objects_unavailable_and_reregister_restores_them(endpoint: str) -> None:
    with ThreadWorker(endpoint, worker_id="w1"), Client(endpoint, timeout=10) as client:
        with ThreadWorker("", worker_id="w2", connect=(endpoint,)):
            wait_until(lambda: len(client.workers()) == 2, what="both workers")
            kept = client.register("kept", VERTICES, FACES)
            moved = client.register("moved", VERTICES[:30], FACES[:2])  # placed on the emptier worker
            assert (kept.worker, moved.worker) == ("w1", "w2")
            last = VERTICES[:30] + 2
            moved.update(VERTICES[:30] + 1)
            moved.update(last)
            assert moved.available
        wait_until(lambda: not moved.available, what="the client to see w2 go")
        for call in (lambda: moved.query(POINTS), lambda: moved.update(last), lambda: moved.stream(last), moved.info):
            with pytest.raises(ObjectUnavailableError, match="worker w2 is gone"):
                call()
        assert kept.available and kept.query(POINTS).frame == 0
        assert [o.name for o in client.objects()] == ["kept"]
        with pytest.raises(WorkerUnavailableError):
            moved.reregister(worker="w2")
        info = moved.reregister()
        assert (info.worker, moved.worker, info.options) == ("w1", "w1", moved.options)
        assert info.frame == moved.frame == 4  # two updates, and the update and stream refused above
        answer = moved.query(POINTS)
        np.testing.assert_allclose(answer.distance, expected_distance(POINTS, last), rtol=1e-6)
        assert moved.update(last + 1) == 5
        assert [o.name for o in client.objects()] == ["kept", "moved"]
        with pytest.raises(ObjectExistsError):
            moved.reregister()
        with pytest.raises(NotSupportedError):
            client.object("kept").reregister()


def test_a_request_in_flight_ends_when_its_worker_goes(endpoint: str) -> None:
    """A worker whose liveliness token goes while its queryable still holds a query: the client ends the
    request on the token's DELETE instead of waiting for the timeout."""
    options = ObjectOptions()
    held: list[zenoh.Query] = []
    received = threading.Event()

    def on_info(query: zenoh.Query) -> None:
        decode(query.payload.to_bytes(), InfoRequest)
        query.reply(KEYS.object_info("ghost"), encode(ObjectInfo("ghost", "ghost-worker", 0, 40, 3, options)))
        query.drop()

    def on_query(query: zenoh.Query) -> None:
        held.append(query)  # never answered
        received.set()

    timeout_s = 30.0
    with ThreadWorker(endpoint), zenoh.open(zenoh_config(mode="client", connect=[endpoint])) as ghost:
        ghost.declare_queryable(KEYS.object_info("ghost"), on_info)
        ghost.declare_queryable(KEYS.object_query("ghost"), on_query)
        token = ghost.liveliness().declare_token(KEYS.worker_token("ghost-worker"))
        with Client(endpoint, timeout=timeout_s) as client:
            handle = client.object("ghost")
            outcome: list[BaseException] = []
            ended = threading.Event()

            def ask() -> None:
                try:
                    handle.query(POINTS)
                except BaseException as error:  # noqa: BLE001 - checked below
                    outcome.append(error)
                ended.set()

            asker = threading.Thread(target=ask)
            asker.start()
            assert received.wait(timeout_s), "the query did not reach the ghost worker"
            token.undeclare()
            gone_at = time.monotonic()
            assert ended.wait(timeout_s + 10)
            latency = time.monotonic() - gone_at
            asker.join()
            for query in held:
                query.drop()
    assert len(outcome) == 1 and isinstance(outcome[0], ObjectUnavailableError), outcome
    assert latency < timeout_s, f"the request ended after {latency:.2f} s, at the timeout: not through liveliness"
    print(f"request in flight ended {latency * 1000:.1f} ms after the worker's token went")
