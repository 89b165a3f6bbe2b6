"""Scale-out: `badf serve --connect / --router-only / --gpus`, and the client across several workers."""

from __future__ import annotations

import argparse

import pytest

from badf.server import RouterSettings, _cli, _cuda


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
