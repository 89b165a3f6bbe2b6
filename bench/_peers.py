"""CPU libraries a user might pick instead, where they install from PyPI (`pip install 'badf[peers]'`).

Each peer answers signed distances (negative inside) at float64 world points; missing ones are skipped
with the reason. Open3D's module also needs the system's libusb-1.0 (Debian: `apt-get install libusb-1.0-0`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass
class Peer:
    name: str
    sign: str  # how the peer decides inside from outside
    build_ms: float | None  # one-off set-up per mesh, when the peer has one
    query: Callable[[np.ndarray], np.ndarray]  # (P, 3) float64 -> (P,) signed distances


def open3d_peer(vertices: np.ndarray, faces: np.ndarray, closed: bool) -> Peer:
    import open3d as o3d

    start = time.perf_counter()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)))
    build_ms = (time.perf_counter() - start) * 1e3

    def query(points: np.ndarray) -> np.ndarray:
        tensor = o3d.core.Tensor(np.ascontiguousarray(points, np.float32))
        return scene.compute_signed_distance(tensor).numpy()

    return Peer("Open3D RaycastingScene", "ray parity", build_ms, query)


def libigl_peer(vertices: np.ndarray, faces: np.ndarray, closed: bool) -> Peer:
    import igl

    v = np.ascontiguousarray(vertices, np.float64)
    f = np.ascontiguousarray(faces, np.int64)
    sign_type = igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL if closed else igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER

    def query(points: np.ndarray) -> np.ndarray:
        # the AABB tree is built inside every call
        return np.asarray(igl.signed_distance(np.ascontiguousarray(points, np.float64), v, f, sign_type=sign_type)[0])

    return Peer("libigl signed_distance", "pseudonormal" if closed else "fast winding number", None, query)


PEERS: dict[str, Callable[[np.ndarray, np.ndarray, bool], Peer]] = {"open3d": open3d_peer, "libigl": libigl_peer}


def available_peers(vertices: np.ndarray, faces: np.ndarray, closed: bool) -> tuple[list[Peer], dict[str, str]]:
    """The peers that import here, set up for this mesh, and {name: why skipped} for the others."""
    peers, skipped = [], {}
    for name, make in PEERS.items():
        try:
            peers.append(make(vertices, faces, closed))
        except ImportError as error:
            skipped[name] = f"not importable: {error}"
    return peers, skipped
