import pathlib
import sys

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).parent))


def _devices() -> list[str]:
    try:
        import warp as wp
    except ImportError:
        return []
    wp.config.log_level = wp.LOG_ERROR
    wp.init()
    return ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


DEVICES = _devices()


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    """Every engine test runs on the CPU back-end, and on the first GPU when there is one."""
    return request.param
