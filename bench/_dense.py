"""The dense-grid baseline a Warp user would write instead of an ADF: a wp.Mesh, `mesh_query_point_*` at
every point of a regular lattice at the octree's finest resolution over the same domain, and a trilinear
lookup for queries.

The sign is Warp's pseudonormal test (`mesh_query_point_sign_normal`), the cheapest of its signed queries and
the one the engine benchmark's baseline uses; on an open mesh it is unreliable near the holes, which the
wrong-sign rates show. (Warp's winding-number query costs several times more per point, too much for a
513^3 lattice of a million triangles in the GPU run's time.) Coordinates are local (relative to the domain
centre), as in the engine.
"""

from __future__ import annotations

import numpy as np
import warp as wp


class DenseGrid:
    """Signed distances on a (2**depth + 1)^3 lattice of the cube (centre, side), with its own wp.Mesh."""

    def __init__(self, local_vertices: np.ndarray, faces: np.ndarray, *, side: float, depth: int, device: str):
        self.device = device
        self.count = (1 << depth) + 1
        self.step = side / float(1 << depth)
        self.origin = wp.vec3(-side / 2.0, -side / 2.0, -side / 2.0)
        self.points = wp.array(np.ascontiguousarray(local_vertices, np.float32), dtype=wp.vec3, device=device)
        self.indices = wp.array(np.ascontiguousarray(faces, np.int32).reshape(-1), dtype=wp.int32, device=device)
        self.values = wp.empty(self.count**3, dtype=wp.float32, device=device)
        self.mesh: wp.Mesh | None = None

    def build(self) -> None:
        """A new BVH over the vertices, then every lattice value."""
        self.mesh = wp.Mesh(points=self.points, indices=self.indices)
        self._fill()

    def update(self, local_vertices: np.ndarray) -> None:
        """New vertex positions (same topology): refit the BVH, then every lattice value."""
        host = wp.array(np.ascontiguousarray(local_vertices, np.float32), dtype=wp.vec3, device="cpu")
        wp.copy(self.points, host)
        self.mesh.refit()
        self._fill()

    def query(self, local_points: np.ndarray) -> np.ndarray:
        """Trilinear interpolation of the lattice at (P, 3) local points (clamped to the cube)."""
        points = wp.array(np.ascontiguousarray(local_points, np.float32), dtype=wp.vec3, device=self.device)
        out = wp.empty(len(local_points), dtype=wp.float32, device=self.device)
        wp.launch(_trilinear, dim=len(local_points), inputs=[self.values, self.count, self.origin, 1.0 / self.step,
                                                             points], outputs=[out], device=self.device)
        return out.numpy()

    def nbytes(self) -> int:
        """Lattice, vertices and indices (the BVH's own nodes are not counted)."""
        return self.values.capacity + self.points.capacity + self.indices.capacity

    def _fill(self) -> None:
        wp.launch(_fill_lattice, dim=self.count**3,
                  inputs=[self.mesh.id, self.origin, self.step, self.count],
                  outputs=[self.values], device=self.device)


@wp.kernel(enable_backward=False)
def _fill_lattice(mesh: wp.uint64, origin: wp.vec3, step: float, n: int, values: wp.array(dtype=wp.float32)):
    i = wp.tid()
    p = origin + wp.vec3(float(i // (n * n)), float((i // n) % n), float(i % n)) * step
    q = wp.mesh_query_point_sign_normal(mesh, p, 1.0e30)
    d = wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v))
    values[i] = wp.where(q.sign < 0.0, -d, d)


@wp.kernel(enable_backward=False)
def _trilinear(values: wp.array(dtype=wp.float32), n: int, origin: wp.vec3, inv_step: float,
               points: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.float32)):
    i = wp.tid()
    g = (points[i] - origin) * inv_step
    top = float(n - 1)
    g = wp.vec3(wp.clamp(g[0], 0.0, top), wp.clamp(g[1], 0.0, top), wp.clamp(g[2], 0.0, top))
    x = wp.min(int(g[0]), n - 2)
    y = wp.min(int(g[1]), n - 2)
    z = wp.min(int(g[2]), n - 2)
    tx = g[0] - float(x)
    ty = g[1] - float(y)
    tz = g[2] - float(z)
    value = float(0.0)
    for corner in range(8):
        cx = (corner >> 2) & 1
        cy = (corner >> 1) & 1
        cz = corner & 1
        weight = wp.where(cx == 1, tx, 1.0 - tx) * wp.where(cy == 1, ty, 1.0 - ty) * wp.where(cz == 1, tz, 1.0 - tz)
        value += weight * values[((x + cx) * n + (y + cy)) * n + (z + cz)]
    out[i] = value
