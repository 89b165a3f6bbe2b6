"""Per-stage device times of the last build or update, without synchronising in between."""

from __future__ import annotations

import time
from contextlib import contextmanager

import warp as wp


class StageClock:
    """Records each stage's start and end: CUDA events on a GPU, wall time on the CPU back-end.

    Warp's CPU launches return when their work is done, so wall time is the stage's time there. On CUDA the
    events are read only when `times_ms` is called; the events are reused, so nothing is allocated per frame.
    """

    def __init__(self, device: wp.Device):
        self.device = device
        self._events: dict[str, tuple[wp.Event, wp.Event]] = {}
        self._wall: dict[str, float] = {}
        self._recorded: list[str] = []

    def reset(self) -> None:
        self._recorded.clear()
        self._wall.clear()

    @contextmanager
    def stage(self, name: str):
        if self.device.is_cuda:
            pair = self._events.get(name)
            if pair is None:
                pair = (wp.Event(self.device, enable_timing=True), wp.Event(self.device, enable_timing=True))
                self._events[name] = pair
            wp.record_event(pair[0])
            yield
            wp.record_event(pair[1])
        else:
            start = time.perf_counter()
            yield
            self._wall[name] = self._wall.get(name, 0.0) + (time.perf_counter() - start) * 1e3
        if name not in self._recorded:
            self._recorded.append(name)

    @property
    def recorded(self) -> list[str]:
        return self._recorded

    def replayed(self, names: list[str]) -> None:
        """Stages whose events a replayed CUDA graph recorded (the events are the ones captured)."""
        for name in names:
            if name not in self._recorded:
                self._recorded.append(name)

    def times_ms(self) -> dict[str, float]:
        """Each recorded stage's time; on CUDA this waits for the last stage's end event only (not the
        whole device, where other objects' work may be queued)."""
        if not self.device.is_cuda:
            return {name: round(self._wall[name], 4) for name in self._recorded}
        for name in self._recorded:
            wp.synchronize_event(self._events[name][1])
        return {name: round(wp.get_event_elapsed_time(*self._events[name]), 4) for name in self._recorded}
