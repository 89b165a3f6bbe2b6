"""A headless Chromium on a viewer's page: for the browser test, the README's screenshot and the benchmark.

Debian's `chromium` (or `chromium-headless-shell`) draws WebGL in software (SwiftShader). The browser runs
in a process group of its own, and the whole group is ended afterwards: ending only the parent process
leaves about ten of its helpers running. Screenshots of the whole window (page and canvas) are taken
over the DevTools protocol (with `websockets`, which viser needs anyway).
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path
from types import TracebackType

import numpy as np

CHROMIUM_NAMES = ("chromium", "chromium-browser", "chromium-headless-shell")
_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--no-first-run",
    "--hide-scrollbars",
    "--remote-debugging-port=0",  # a free port, written to DevToolsActivePort in the profile
)


def find_chromium() -> str | None:
    """The path of a Chromium on PATH, or None."""
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path is not None:
            return path
    return None


class HeadlessChromium:
    """A headless Chromium showing `url` while the `with` block runs; its process group is ended after.

    `start_timeout_s` bounds the wait for the browser's DevTools endpoint and for the page to be listed.
    """

    def __init__(self, url: str, *, width: int = 1280, height: int = 800, start_timeout_s: float = 60.0) -> None:
        self.url = url
        self.width, self.height = width, height
        self.start_timeout_s = start_timeout_s
        self.process: subprocess.Popen | None = None
        self._profile: tempfile.TemporaryDirectory | None = None
        self._page: object | None = None  # the DevTools connection to the page
        self._message_id = 0

    def __enter__(self) -> HeadlessChromium:
        executable = find_chromium()
        if executable is None:
            raise FileNotFoundError(
                f"no Chromium on PATH (looked for {', '.join(CHROMIUM_NAMES)}); "
                "on Debian: apt-get install chromium (./dev test does it when run as root)"
            )
        self._profile = tempfile.TemporaryDirectory(prefix="badf-chromium-")
        command = [executable, *_FLAGS, f"--user-data-dir={self._profile.name}",
                   f"--window-size={self.width},{self.height}", self.url]  # fmt: skip
        self.process = subprocess.Popen(
            command, start_new_session=True, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )  # fmt: skip
        return self

    def __exit__(self, kind: type | None, error: BaseException | None, trace: TracebackType | None) -> None:
        if self._page is not None:
            self._page.close()  # type: ignore[attr-defined]
            self._page = None
        if self.process is not None:
            end_process_group(self.process)
        if self._profile is not None:
            self._profile.cleanup()

    def screenshot(self) -> bytes:
        """PNG bytes of what the window shows now: the page and its canvas."""
        result = self._call("Page.captureScreenshot", {"format": "png"})
        return base64.b64decode(result["data"])

    def evaluate(self, expression: str) -> object:
        """The value of a JavaScript expression in the page."""
        result = self._call("Runtime.evaluate", {"expression": expression, "returnByValue": True})
        return result.get("result", {}).get("value")

    def _call(self, method: str, params: dict) -> dict:
        page = self._connect()
        self._message_id += 1
        page.send(json.dumps({"id": self._message_id, "method": method, "params": params}))  # type: ignore
        while True:
            message = json.loads(page.recv(timeout=120))  # type: ignore[attr-defined]
            if message.get("id") == self._message_id:
                if "error" in message:
                    raise RuntimeError(f"Chromium refused {method}: {message['error']}")
                return message["result"]

    def _connect(self) -> object:
        if self._page is not None:
            return self._page
        from websockets.sync.client import connect

        deadline = time.monotonic() + self.start_timeout_s
        port_file = Path(self._profile.name) / "DevToolsActivePort"  # type: ignore[union-attr]
        while True:
            target = _page_target(port_file)
            if target is not None:
                self._page = connect(target, max_size=None, open_timeout=self.start_timeout_s)
                return self._page
            if self.process is None or self.process.poll() is not None:
                raise RuntimeError(f"Chromium exited before showing {self.url}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"Chromium listed no page for {self.url} within {self.start_timeout_s:g} s")
            time.sleep(0.1)  # polling for the browser's endpoint to appear


def _page_target(port_file: Path) -> str | None:
    """The DevTools WebSocket address of the browser's page, once the browser has written its port."""
    try:
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as response:
            targets = json.load(response)
    except (FileNotFoundError, IndexError, ValueError, OSError):
        return None
    pages = [t["webSocketDebuggerUrl"] for t in targets if t.get("type") == "page" and "webSocketDebuggerUrl" in t]
    return pages[0] if pages else None


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
        time.sleep(0.05)  # polling for the group's end; the kill above is what ends it


def group_alive(group: int) -> bool:
    """Whether any process of process group `group` still exists."""
    try:
        os.killpg(group, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def slice_missing(rgb: np.ndarray) -> dict[str, str]:
    """What a render (H, W, 3) of the viewer's canvas lacks of a slice, by name: "inside" (blue) and
    "outside" (red) colours, the zero "contour" (near-black), "colours" (more than one). Empty when
    nothing is missing."""
    pixels = np.asarray(rgb)[..., :3].reshape(-1, 3).astype(int)
    red, blue = pixels[:, 0], pixels[:, 2]
    inside = np.mean((blue - red > 40) & (blue > 120))
    outside = np.mean((red - blue > 40) & (red > 120))
    dark = np.mean(pixels.max(axis=1) < 60)
    missing = {}
    if inside < 0.002:
        missing["inside"] = f"inside (blue) pixels: {inside:.4f} of the render"
    if outside < 0.01:
        missing["outside"] = f"outside (red) pixels: {outside:.4f} of the render"
    if dark < 0.0002:
        missing["contour"] = f"zero contour (near-black) pixels: {dark:.5f} of the render"
    if pixels.std(axis=0).min() < 10:
        missing["colours"] = "more than one colour"
    return missing
