"""A stand-in for the engine's DistanceField, for unit tests of the worker's plumbing only.

Distance is to the nearest vertex (numpy brute force): enough to tell frames apart and check that a reply
belongs to the vertices of the frame it names. `gate` is open (set) at first; a test
that clears it holds `update` until it is set again, to keep an object busy and watch work pile up.
`on_update`, when a test sets it, is called with each frame's vertices once they passed the gate, on the
object's thread, before `update` returns (to make something arrive while a frame is applied).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass
class StandInSlice:
    distance: np.ndarray
    u_range: tuple[float, float]
    v_range: tuple[float, float]
    cell_lower: np.ndarray
    cell_upper: np.ndarray
    cell_level: np.ndarray
    cell_is_leaf: np.ndarray
    cell_is_empty: np.ndarray


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
        self.on_update: Callable[[np.ndarray], None] | None = None
        self.trims = 0

    @property
    def vertex_count(self) -> int:
        return len(self._vertices)

    @property
    def face_count(self) -> int:
        return len(self._faces)

    def update(self, vertices: np.ndarray) -> int:
        self.updates_started.release()
        self.gate.wait()
        if self.on_update is not None:
            self.on_update(vertices)
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

    def slice(self, axis: str, position: float, *, resolution: int, max_level: int) -> StandInSlice:
        """Nearest-vertex distances on the plane over [-1, 1]^2, and one cell per level up to max_level
        (levels 0..max_level, nested boxes [-2**-l, 2**-l]^3; the deepest is a leaf)."""
        axis_index = "xyz".index(axis)
        centres = -1.0 + (np.arange(resolution) + 0.5) * 2.0 / resolution
        v, u = np.meshgrid(centres, centres, indexing="ij")
        points = np.zeros((resolution * resolution, 3), np.float32)
        plane_axes = [a for a in range(3) if a != axis_index]
        points[:, plane_axes[0]], points[:, plane_axes[1]], points[:, axis_index] = u.ravel(), v.ravel(), position
        distance = self.query(points).distance.reshape(resolution, resolution)
        levels = np.arange(max_level + 1, dtype=np.uint8)
        half = 2.0 ** -levels.astype(np.float32)
        return StandInSlice(
            distance, (-1.0, 1.0), (-1.0, 1.0),
            np.repeat(-half[:, None], 3, axis=1), np.repeat(half[:, None], 3, axis=1), levels,
            levels == max_level, np.zeros(len(levels), bool),
        )  # fmt: skip

    def info(self) -> dict:
        return {"sign": "none", "vertex_count": self.vertex_count, "face_count": self.face_count}

    def stats(self) -> dict:
        return {"frame": self.frame, "trims": self.trims}

    def trim(self) -> int:
        self.trims += 1
        return 0


def nearest_vertex(points: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    d = ((points[:, None, :].astype(np.float64) - vertices[None, :, :]) ** 2).sum(axis=2)
    return np.argmin(d, axis=1)
