"""A stand-in for the engine's DistanceField, for unit tests of the worker's plumbing only.

Distance is to the nearest vertex (numpy brute force): enough to tell frames apart and check that a reply
belongs to the vertices of the frame it names. `gate` is open (set) at first; a test
that clears it holds `update` until it is set again, to keep an object busy and watch work pile up.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np


@dataclass
class StandInResult:
    frame: int
    distance: np.ndarray | None = None
    closest_point: np.ndarray | None = None
    normal: np.ndarray | None = None
    face: np.ndarray | None = None


class StandInField:
    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        if len(vertices) < 3:
            raise ValueError(f"need at least 3 vertices, got {len(vertices)}")
        self._vertices = np.array(vertices, dtype=np.float32)
        self._faces = np.array(faces, dtype=np.int32)
        self.gate = threading.Event()
        self.gate.set()
        self.frame = 0
        self.updates_started = threading.Semaphore(0)

    @property
    def vertex_count(self) -> int:
        return len(self._vertices)

    @property
    def face_count(self) -> int:
        return len(self._faces)

    def update(self, vertices: np.ndarray) -> int:
        self.updates_started.release()
        self.gate.wait()
        if np.abs(vertices).max() > 1e6:
            raise ValueError("vertices beyond 1e6 are refused by this stand-in")
        self._vertices = np.array(vertices, dtype=np.float32)
        self.frame += 1
        return self.frame

    def query(
        self, points: np.ndarray, *, mode: str = "adf", outputs: tuple[str, ...] = ("distance",)
    ) -> StandInResult:
        nearest = nearest_vertex(points, self._vertices)
        result = StandInResult(self.frame)
        if "distance" in outputs:
            result.distance = np.linalg.norm(points - self._vertices[nearest], axis=1).astype(np.float32)
        if "closest_point" in outputs:
            result.closest_point = self._vertices[nearest]
        if "normal" in outputs:
            offset = points - self._vertices[nearest]
            result.normal = (offset / np.maximum(np.linalg.norm(offset, axis=1, keepdims=True), 1e-12)).astype(
                np.float32
            )
        if "face" in outputs:
            result.face = np.zeros(len(points), dtype=np.int32)
        return result

    def info(self) -> dict:
        return {"sign": "none", "vertex_count": self.vertex_count, "face_count": self.face_count}

    def stats(self) -> dict:
        return {"frame": self.frame}


def nearest_vertex(points: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    d = ((points[:, None, :].astype(np.float64) - vertices[None, :, :]) ** 2).sum(axis=2)
    return np.argmin(d, axis=1)
