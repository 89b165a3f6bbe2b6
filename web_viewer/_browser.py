"""A headless Chromium on a viewer's page: for the browser test, the README's screenshot and the benchmark.

Debian's `chromium` (or `chromium-headless-shell`) draws WebGL in software (SwiftShader). The browser runs
in a process group of its own, and the whole group is ended afterwards: ending only the parent process
leaves about ten of its helpers running.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

CHROMIUM_NAMES = ("chromium", "chromium-browser", "chromium-headless-shell")
_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--no-first-run",
    "--hide-scrollbars",
)


def find_chromium() -> str | None:
    """The path of a Chromium on PATH, or None."""
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path is not None:
            return path
    return None


def _command(url: str, profile: str, width: int, height: int, extra: tuple[str, ...] = ()) -> list[str]:
    executable = find_chromium()
    if executable is None:
        raise FileNotFoundError(
            f"no Chromium on PATH (looked for {', '.join(CHROMIUM_NAMES)}); "
            "on Debian: apt-get install chromium (./dev test does it when run as root)"
        )
    return [executable, *_FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}", *extra, url]


@contextmanager
def headless_chromium(url: str, *, width: int = 1280, height: int = 800) -> Iterator[subprocess.Popen]:
    """A headless Chromium showing `url` for the duration of the block; its process group is ended after."""
    with tempfile.TemporaryDirectory(prefix="badf-chromium-") as profile:
        process = subprocess.Popen(
            _command(url, profile, width, height),
            start_new_session=True,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            yield process
        finally:
            end_process_group(process)


def screenshot(url: str, path: str | Path, *, width: int = 1400, height: int = 900, budget_ms: int = 20_000) -> None:
    """Load `url` in a headless Chromium and write what the window shows (page and canvas) to `path` (PNG).

    `budget_ms` is the browser's virtual time for loading and drawing; the whole run is bounded at four
    times that in real time.
    """
    path = Path(path).resolve()
    with tempfile.TemporaryDirectory(prefix="badf-chromium-") as profile:
        extra = (f"--screenshot={path}", f"--virtual-time-budget={budget_ms}")
        process = subprocess.Popen(
            _command(url, profile, width, height, extra),
            start_new_session=True,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            process.wait(timeout=4 * budget_ms / 1000 + 30)
        finally:
            end_process_group(process)
    if not path.exists():
        raise RuntimeError(f"Chromium wrote no screenshot of {url} to {path}")


def end_process_group(process: subprocess.Popen, *, timeout_s: float = 10.0) -> None:
    """End every process in the group that `process` leads (it was started with start_new_session=True),
    and wait until the group is gone or `timeout_s` passes."""
    try:
        os.killpg(process.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    process.wait(timeout=timeout_s)
    deadline = time.monotonic() + timeout_s
    while group_alive(process.pid) and time.monotonic() < deadline:
        time.sleep(0.05)  # polling the group's end; the kill above is what ends it


def group_alive(group: int) -> bool:
    """Whether any process of process group `group` still exists."""
    try:
        os.killpg(group, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
