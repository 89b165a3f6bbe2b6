"""How many CUDA devices this process may use, asked of the CUDA driver without creating a context, so the
process that starts one worker per GPU neither imports Warp nor holds GPU memory; and, for command lines
that name a device, whether Warp has it (`device_problem`, which does import Warp)."""

from __future__ import annotations

import ctypes
import os

_CUDA_ERROR_NO_DEVICE = 100


class NoCudaDeviceError(RuntimeError):
    """No CUDA device is visible to this process; the message says why."""


def visible_cuda_device_count() -> int:
    """The number of CUDA devices visible here (CUDA_VISIBLE_DEVICES applies); NoCudaDeviceError if none."""
    driver = _driver()
    count = ctypes.c_int(0)
    _check(driver.cuDeviceGetCount(ctypes.byref(count)))
    if count.value == 0:
        mask = os.environ.get("CUDA_VISIBLE_DEVICES")
        hidden = f" (CUDA_VISIBLE_DEVICES={mask!r})" if mask is not None else ""
        raise NoCudaDeviceError(f"no CUDA device is visible: the CUDA driver reports none{hidden}")
    return count.value


def cuda_device_names() -> list[str]:
    """The names of the visible CUDA devices, in index order (for reports)."""
    driver = _driver()
    names = []
    for index in range(visible_cuda_device_count()):
        handle = ctypes.c_int(0)
        _check(driver.cuDeviceGet(ctypes.byref(handle), index))
        name = ctypes.create_string_buffer(256)
        _check(driver.cuDeviceGetName(name, len(name), handle))
        names.append(name.value.decode(errors="replace"))
    return names


def _driver() -> ctypes.CDLL:
    try:
        driver = ctypes.CDLL("libcuda.so.1")
    except OSError:
        raise NoCudaDeviceError(
            "no CUDA device is visible: the NVIDIA driver's library libcuda.so.1 is not installed on this machine"
        ) from None
    status = driver.cuInit(0)
    if status == _CUDA_ERROR_NO_DEVICE:
        raise NoCudaDeviceError("no CUDA device is visible: the CUDA driver reports none")
    _check(status)
    return driver


def _check(status: int) -> None:
    if status != 0:
        raise NoCudaDeviceError(f"no CUDA device is usable: the CUDA driver failed with error {status}")


def requested_gpus(text: str) -> list[int] | None:
    """The device indices `--gpus` names (comma-separated, such as `0,2`), or None for `all`; ValueError for
    anything else, before any device is looked for."""
    if text.strip() == "all":
        return None
    try:
        indices = [int(part) for part in text.split(",")]
    except ValueError:
        raise ValueError(f"--gpus takes 'all' or device indices such as 0,1; got {text!r}") from None
    if any(index < 0 for index in indices):
        raise ValueError(f"--gpus takes 'all' or device indices such as 0,1; got {text!r}")
    return indices


def parse_gpus(text: str, visible: int) -> list[int]:
    """`all`, or comma-separated device indices such as `0,2`, as a list of indices below `visible`."""
    indices = requested_gpus(text)
    if indices is None:
        return list(range(visible))
    for index in indices:
        if not 0 <= index < visible:
            raise ValueError(f"--gpus names device {index}, but only devices 0 to {visible - 1} are visible")
    if len(set(indices)) != len(indices):
        raise ValueError(f"--gpus names a device twice: {text!r}")
    return indices


def device_problem(device: str) -> str | None:
    """Why Warp has no device `device` here ("--device ... is not a device here"), or None; None too where
    Warp is not installed (what runs on the device says so itself). For command lines, before they start."""
    try:
        import warp as wp
    except ImportError:
        return None
    wp.config.log_level = wp.LOG_ERROR  # no banner before the one line
    wp.init()
    try:
        wp.get_device(device)
    except (RuntimeError, ValueError, KeyError) as error:
        here = ", ".join(d.alias for d in wp.get_devices())
        return f"--device {device!r} is not a device here ({error}); the devices here: {here}"
    return None
