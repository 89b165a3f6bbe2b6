"""Inside or outside: angle-weighted pseudonormals (Baerentzen and Aanaes 2005) or winding numbers.

`analyse_topology` reads the connectivity once per object, on the host: the edge table, which edges are
open, non-manifold or inconsistently oriented, and the adjacency the pseudonormal kernels gather over
(gathering, not scattering with atomics, keeps the normals bit-for-bit repeatable).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import warp as wp

from badf.server.adf._buffers import DeviceBuffers, HostStaged, KeptViews
from badf.server.adf._bvh import (
    NO_CHILD,
    BvhView,
    entry_distances_sq,
    leaf_triangle,
    rim_corrected,
    wide_stack_int,
    winding_number,
    winding_number_careful,
)
from badf.server.adf._geometry import (
    EDGE_AB,
    EDGE_BC,
    FACE,
    VERTEX_A,
    VERTEX_B,
    VERTEX_C,
    closest_point_on_triangle,
    triangle_distance_sq,
)
from badf.server.adf._threads import launch_per_item
from badf.server.adf._tolerances import (
    CANCELLED_PSEUDONORMAL,
    DEGENERATE_AREA,
    MIN_ENCLOSED_VOLUME,
    RIM_DOUBT,
    RIM_LIMIT,
    SOLID_BESIDE_REACH,
)

SignMethod = Literal["auto", "pseudonormal", "winding", "none"]
SIGN_METHODS: tuple[str, ...] = ("auto", "pseudonormal", "winding", "none")

# Codes of the resolved method, as the kernels see it.
SIGN_NONE = 0
SIGN_PSEUDONORMAL = 1
SIGN_WINDING = 2
_SIGN_CODES = {"none": SIGN_NONE, "pseudonormal": SIGN_PSEUDONORMAL, "winding": SIGN_WINDING}
_DEGENERATE = wp.constant(DEGENERATE_AREA)
_CANCELLED = wp.constant(CANCELLED_PSEUDONORMAL)
# A face counts as "as near as" a point's own face within this factor of the distance, squared (1 + 1e-3)^2:
# past float32's rounding of it, well short of another face's (see _reads_inside_by_a_face_within)
_NEAR_TIE_SQ = wp.constant(1.002001)
_MIN_ENCLOSED = wp.constant(MIN_ENCLOSED_VOLUME)
_RIM_DOUBT = wp.constant(RIM_DOUBT)
_BESIDE_REACH = wp.constant(SOLID_BESIDE_REACH)
# Points per face that beside_points may look beside (the centroid and six more), and the face count up to
# which it does (then 7 x 2,048 points fit the registration's check of 16,384 at once).
POINTS_PER_FACE = 7
COARSE_FACES = 2048
_POINTS_PER_FACE = wp.constant(POINTS_PER_FACE)


@dataclass(frozen=True)
class Topology:
    """Connectivity of a triangle mesh whose vertices at identical positions are welded into one.

    Seams (vertices duplicated for texture coordinates) would otherwise look like open boundaries.
    """

    welded_faces: np.ndarray  # (M, 3) int32: faces over welded vertex ids
    welded_count: int  # distinct vertex positions
    face_edge: np.ndarray  # (M, 3) int32: edge id of edges ab, bc, ca; faces with a repeated vertex get the null edge
    edge_count: int  # edges, plus one null edge (id edge_count) with no faces
    edge_face_start: np.ndarray  # (edge_count + 2,) CSR into edge_face
    edge_face: np.ndarray  # faces around each edge
    corner_fan: np.ndarray  # (M, 3) int32: the fan (see analyse_topology) of each face's corners
    fan_count: int
    fan_corner_start: np.ndarray  # (fan_count + 1,) CSR into fan_corner
    fan_corner: np.ndarray  # 3 * face + corner of each corner in each fan
    boundary_edges: int  # edges with one face
    nonmanifold_edges: int  # edges with more than two faces
    inconsistent_edges: int  # two-face edges that both faces traverse in the same direction
    repeated_vertex_faces: int  # faces naming a vertex twice
    # (K, 2) int32: pairs of distinct vertex ids that the weld joined within one fan (a seam, or a soup's shared
    # corners); the pseudonormals hold only while each pair still coincides (Pseudonormals.choose_frame_method)
    seam_pairs: np.ndarray
    # (R, 3) int64: the edges whose faces' uses do not cancel, as (lower welded id, higher, net use: +1 for each face
    # running the edge from the lower to the higher, -1 for each the other way), in edge order; the rim's source where
    # the weld joined no two of the faces' vertex ids (`rim_fans`)
    rim_edges: np.ndarray

    @property
    def has_fans(self) -> bool:
        """Whether the fans (and seam pairs) were worked out: `analyse_topology(..., fans=False)` leaves them out,
        for a mesh that the pseudonormals will not sign (`with_fans` adds them)."""
        return len(self.corner_fan) == len(self.welded_faces)

    @property
    def closed(self) -> bool:
        """Watertight, manifold and consistently oriented: every edge has exactly two opposite faces."""
        return self.edge_count > 0 and self.boundary_edges == 0 and self.nonmanifold_edges == 0 and (
            self.inconsistent_edges == 0
        )

    def summary(self) -> dict:
        return {
            "closed": self.closed,
            "edges": self.edge_count,
            "boundary_edges": self.boundary_edges,
            "nonmanifold_edges": self.nonmanifold_edges,
            "inconsistent_edges": self.inconsistent_edges,
            "repeated_vertex_faces": self.repeated_vertex_faces,
        }


def analyse_topology(faces: np.ndarray, vertices: np.ndarray, *, fans: bool = True) -> Topology:
    """Welds, edges and their checks, and (`fans`) the fans the vertex pseudonormals are taken over.

    A fan is the corners at one welded vertex that faces sharing an edge through it connect. At a manifold
    vertex that is every corner there. Where parts only touch at a point (by design, or by chance in the
    first frame, as a cone's tip set on a cube's corner), each part's corners make a fan of their own. Its
    pseudonormal is that part's alone, and stays right when the parts move apart in later frames.
    """
    m = len(faces)
    welded_id, vertex_count = weld(vertices)
    f = welded_id[faces].astype(np.int64)
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    start = f  # directed edges ab, bc, ca of every face
    end = np.roll(f, -1, axis=1)
    lo, hi = np.minimum(start, end), np.maximum(start, end)
    keys = lo * vertex_count + hi
    usable = np.repeat(~repeated[:, None], 3, axis=1)
    # edges are the distinct keys, numbered in key order; `order` lists the usable slots by edge, in slot order
    order, inverse, counts = _groups(keys[usable])
    edge_count = len(counts)
    face_edge = np.full((m, 3), edge_count, dtype=np.int32)
    face_edge[usable] = inverse.astype(np.int32)
    # orientation: +1 where the face runs lo -> hi; a consistent two-face edge sums to zero
    direction = np.where(start < end, 1, -1)[usable]
    orientation_sum = np.bincount(inverse, weights=direction, minlength=edge_count).astype(np.int64)
    rim = np.flatnonzero(orientation_sum)
    edge_key = np.empty(edge_count, dtype=np.int64)
    edge_key[inverse] = keys[usable]
    two = counts == 2
    face_of_slot = np.repeat(np.arange(m), 3).reshape(m, 3)[usable]
    edge_face_start = np.zeros(edge_count + 2, dtype=np.int32)
    edge_face_start[1 : edge_count + 1] = np.cumsum(counts)
    edge_face_start[edge_count + 1] = edge_face_start[edge_count]  # the null edge has no faces
    topology = Topology(
        welded_faces=f.astype(np.int32),
        welded_count=vertex_count,
        face_edge=face_edge,
        edge_count=edge_count,
        edge_face_start=edge_face_start,
        edge_face=face_of_slot[order].astype(np.int32),
        corner_fan=np.zeros((0, 3), dtype=np.int32),
        fan_count=0,
        fan_corner_start=np.zeros(1, dtype=np.int32),
        fan_corner=np.zeros(0, dtype=np.int32),
        boundary_edges=int(np.sum(counts == 1)),
        nonmanifold_edges=int(np.sum(counts > 2)),
        inconsistent_edges=int(np.sum(two & (orientation_sum != 0))),
        repeated_vertex_faces=int(np.sum(repeated)),
        seam_pairs=np.zeros((0, 2), dtype=np.int32),
        rim_edges=np.stack([edge_key[rim] // vertex_count, edge_key[rim] % vertex_count, orientation_sum[rim]],
                           axis=1),
    )
    return _add_fans(topology, faces, usable, inverse[order], order) if fans else topology


def with_fans(topology: Topology, faces: np.ndarray) -> Topology:
    """`topology` (of `faces`) with its fans and seam pairs, where `analyse_topology(..., fans=False)` left them out.
    Half of the analysis (the bunny's: 33 of 56 ms on a 2-core CPU, best of 5), which only the pseudonormals need."""
    if topology.has_fans:
        return topology
    usable = topology.face_edge < topology.edge_count
    edge = topology.face_edge[usable]
    order = _stable_order(edge)  # as analyse_topology's edge keys sort: edges are numbered in key order
    return _add_fans(topology, faces, usable, edge[order], order)


def _add_fans(topology: Topology, faces: np.ndarray, usable: np.ndarray, sorted_edge: np.ndarray,
              order: np.ndarray) -> Topology:
    m = len(topology.welded_faces)
    corner_fan, fan_order, fan_sizes = _fans(topology.welded_faces.astype(np.int64), usable, sorted_edge, order)
    fan_count = len(fan_sizes)
    fan_corner_start = np.zeros(fan_count + 1, dtype=np.int32)
    fan_corner_start[1:] = np.cumsum(fan_sizes)
    return replace(topology, corner_fan=corner_fan.reshape(m, 3).astype(np.int32), fan_count=fan_count,
                   fan_corner_start=fan_corner_start, fan_corner=fan_order.astype(np.int32),
                   seam_pairs=_seam_pairs(faces, corner_fan, fan_order, fan_corner_start))


def _seam_pairs(faces: np.ndarray, corner_fan: np.ndarray, fan_order: np.ndarray,
                fan_corner_start: np.ndarray) -> np.ndarray:
    """Each vertex id that a fan's corners name other than the fan's first corner's, with that one.

    A fan is joined through edges, so two ids in one fan are copies welded along an edge: if a later frame
    pulls them apart, the mesh has a crack there that the first frame's edges and fans do not show. Copies
    that are each in a fan of their own (parts touching at a point) are left out: they may part."""
    raw = np.asarray(faces, dtype=np.int64).reshape(-1)
    if len(raw) == 0:
        return np.zeros((0, 2), dtype=np.int32)
    first = raw[fan_order[fan_corner_start[:-1]]]  # the first corner's vertex, per fan
    other = first[corner_fan]
    split = raw != other
    pairs = np.unique(np.stack([raw[split], other[split]], axis=1), axis=0)
    return pairs.astype(np.int32).reshape(-1, 2)


def _fans(f: np.ndarray, usable: np.ndarray, sorted_edge: np.ndarray,
          order: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(fan of each corner (3M,), the corners by fan in corner order, each fan's corner count): corners at one
    welded vertex joined through faces that share an edge there. `order` sorts the usable edge slots
    (row-major) by edge id, `sorted_edge` is their edge ids in that order. Fans are numbered by their first
    corner's welded vertex, then that corner."""
    m = len(f)
    slot = np.flatnonzero(usable.reshape(-1))[order]  # 3 * face + k of each usable slot, by edge
    same = sorted_edge[1:] == sorted_edge[:-1]  # neighbours in that order share their edge
    first, second = slot[:-1][same], slot[1:][same]
    # each slot runs from its corner k to corner k + 1 of its face
    first_end = 3 * (first // 3) + (first % 3 + 1) % 3
    second_end = 3 * (second // 3) + (second % 3 + 1) % 3
    welded = f.reshape(-1)
    aligned = welded[first] == welded[second]  # the two faces run the edge the same way (inconsistent)
    join_start = np.concatenate([first, first_end])
    join_end = np.concatenate([np.where(aligned, second, second_end), np.where(aligned, second_end, second)])
    root = _connected(join_start, join_end, 3 * m)
    # number the fans by (welded vertex, first corner), so a mesh whose vertices are all manifold numbers
    # them as its welded vertices
    key = welded[root] * (3 * m) + root
    fan_order, fan, sizes = _groups(key)
    return fan, fan_order, sizes


def _stable_order(values: np.ndarray) -> np.ndarray:
    """np.argsort(values, kind="stable") of non-negative integers, as a radix sort over 16-bit digits, least
    significant first: numpy sorts 16-bit integers stably by radix, in time linear in their count, where its
    stable sort of wider ones is a merge sort. 260K shuffled keys below 2^31 on a 2-core CPU: 4 against 19 ms
    (numpy 2.4; nearly sorted ones, which the merge sort takes in one pass, 3 against 2 ms)."""
    values = np.asarray(values)
    if len(values) == 0:
        return np.arange(0)
    top, shift = int(values.max()), 0
    order = np.argsort((values & 0xFFFF).astype(np.uint16), kind="stable")
    while top >> (shift + 16):
        shift += 16
        order = order[np.argsort(((values[order] >> shift) & 0xFFFF).astype(np.uint16), kind="stable")]
    return order


def _groups(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What np.unique(values, return_inverse=True, return_counts=True) gives as (inverse, counts), of
    non-negative integers, with the stable order that sorts them, from that one sort: (order, inverse, counts)."""
    order = _stable_order(values)
    if len(values) == 0:
        return order, np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    ordered = values[order]
    new = np.concatenate([[True], ordered[1:] != ordered[:-1]])  # where each group starts, in sorted order
    inverse = np.empty(len(values), dtype=np.int64)
    inverse[order] = np.cumsum(new) - 1
    return order, inverse, np.diff(np.append(np.flatnonzero(new), len(values)))


def weld(vertices: np.ndarray) -> tuple[np.ndarray, int]:
    """(id of each vertex's position, number of distinct positions); ids follow the positions' lexicographic
    (x, y, z) order. -0.0 and 0.0 compare equal, so they weld."""
    v = vertices
    order = np.arange(len(v))
    for axis in (2, 1, 0):  # least significant first, each sort stable: lexicographic, as np.lexsort but by radix
        key = _float_order_key(v[order, axis])
        order = order[_stable_order(key)]
    ordered = v[order]
    new = np.ones(len(v), dtype=bool)
    new[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
    welded_id = np.empty(len(v), dtype=np.int64)
    welded_id[order] = np.cumsum(new) - 1
    return welded_id, int(np.count_nonzero(new))


def _float_order_key(x: np.ndarray) -> np.ndarray:
    """Unsigned integers in the order of the floats `x` (finite, float32 or float64), equal where the floats are:
    the bits with the sign bit set for a positive float and every bit flipped for a negative one, -0.0 first
    made 0.0."""
    bits = (x + x.dtype.type(0)).view(np.uint32 if x.dtype.itemsize == 4 else np.uint64)
    sign = bits.dtype.type(1) << bits.dtype.type(8 * bits.dtype.itemsize - 1)
    return np.where(bits & sign, ~bits, bits | sign)


def face_volumes(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each face's signed volume (of its tetrahedron with the origin) and area, in float64. Summed over a
    closed mesh they give its enclosed volume, positive for outward-facing faces, and its surface area."""
    v = vertices.astype(np.float64)
    # x, y and z of corners a, b and c: the products np.cross and norm take, in half their time (the volume's three
    # terms summed in order; einsum's order left its last bit different on a third of the test meshes)
    (ax, bx, cx), (ay, by, cy), (az, bz, cz) = (v[:, k][faces].T for k in range(3))
    volume = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
    ux, uy, uz, wx, wy, wz = bx - ax, by - ay, bz - az, cx - ax, cy - ay, cz - az
    nx, ny, nz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
    return volume / 6.0, np.sqrt(nx * nx + ny * ny + nz * nz) / 2.0


def encloses_volume(volume, area, extent: float):
    """Whether a volume is clearly more than none for its area (floats, or arrays of them elementwise)."""
    return abs(volume) > MIN_ENCLOSED_VOLUME * area * extent


def face_components(topology: Topology) -> np.ndarray:
    """A label per face, equal for faces that edges or shared vertex positions connect (0..parts-1)."""
    label = _vertex_components(topology.welded_faces, topology.welded_count)[topology.welded_faces[:, 0]]
    return np.unique(label, return_inverse=True)[1].reshape(-1)


def components_disagree(face_volume: np.ndarray, face_area: np.ndarray, label: np.ndarray, extent: float) -> bool:
    """Whether a closed mesh has connected parts (`face_components`) that enclose volume with opposite
    orientations, from its faces' volumes and areas (`face_volumes`).

    A part turned inside out beside the others has winding number -1 within, which the winding-number sign
    counts as inside, while its pseudonormals say outside; a cavity (an inward part nested in an outward
    one) is outside either way. Telling the two apart takes the parts' nesting, so for any such mesh `auto`
    takes winding numbers, which are right for both. Parts that enclose (next to) nothing count for neither.
    """
    if len(face_volume) == 0:
        return False
    count = int(label.max()) + 1
    volume = np.bincount(label, weights=face_volume, minlength=count)
    solid = encloses_volume(volume, np.bincount(label, weights=face_area, minlength=count), extent)
    return bool(np.any(solid & (volume > 0.0)) and np.any(solid & (volume < 0.0)))


def spread_sample(label: np.ndarray, limit: int) -> np.ndarray:
    """Indices of up to about `limit` faces (all of them if there are no more), evenly spread over each part
    (`face_components`), with at least min(8, its faces) from every part, so no part goes unsampled."""
    count = len(label)
    if count <= limit:
        return np.arange(count, dtype=np.int32)
    order = np.argsort(label, kind="stable")
    sizes = np.bincount(label)
    starts = np.cumsum(sizes) - sizes
    share = np.maximum(np.minimum(sizes, 8), (limit * sizes) // count)
    part = np.repeat(np.arange(len(sizes)), share)
    rank = np.arange(len(part)) - np.repeat(np.cumsum(share) - share, share)
    return order[starts[part] + ((2 * rank + 1) * sizes[part]) // (2 * share[part])].astype(np.int32)


def beside_points(faces: np.ndarray, face_count: int) -> np.ndarray:
    """The points `surface_enters_solid` looks beside, as slots face * POINTS_PER_FACE + k: on a mesh of at
    most COARSE_FACES faces each face's centroid and six more points inside it, near its corners and edge
    midpoints (a coarse face's centroid can lie outside another part that crosses the face elsewhere: two
    12-triangle boxes crossing in a "+"); on a finer one the centroids alone."""
    faces = np.asarray(faces, np.int64)
    if face_count > COARSE_FACES:
        return (faces * POINTS_PER_FACE).astype(np.int32)
    return (faces[:, None] * POINTS_PER_FACE + np.arange(POINTS_PER_FACE)).reshape(-1).astype(np.int32)


def surface_enters_solid(bvh: BvhView, sign: SignView, vertices: wp.array, faces: wp.array, sample: np.ndarray,
                         extent: wp.array, device) -> bool:
    """Whether any sampled point (`beside_points` of a `spread_sample` of faces) of a closed, outward-facing
    mesh has the solid just outside it: SOLID_BESIDE_REACH of the mesh's `extent` (a (1,) device array) off
    the face, along its normal, |winding number| > 1/2.

    That is the case where parts are nested (a shell inside a shell facing the same way) or run into each
    other or themselves. Pseudonormals then say "outside" between the inner surface and the outer one,
    where the winding number says inside; so `auto` takes winding numbers. On a mesh without that, every
    such point has a winding number near 0. Also true where such a point reads inside by the pseudonormal of
    a face as near as its own (`sign`: this frame's): faces that coincide facing both ways, as in a flap
    pressed flat, which a search meets in either order. (`Pseudonormals.watch_parts` repeats the check every
    frame.)
    """
    faces_of = wp.array(sample, dtype=wp.int32, device=device)
    start = wp.zeros(1, dtype=wp.int32, device=device)
    found = wp.zeros(1, dtype=wp.int32, device=device)
    _look_beside(len(sample), bvh, sign, vertices, faces, faces_of, start, extent, found, device)
    return bool(found.numpy()[0])


def _look_beside(count: int, bvh: BvhView, sign: SignView, vertices: wp.array, faces: wp.array, slots: wp.array,
                 start: wp.array, extent: wp.array, found: wp.array, device) -> None:
    """Queue `_solid_beside_face` over `count` points of `slots` from start[0] on; on the CPU shared out over its
    threads, each chunk told where its points begin."""
    launch_per_item(_solid_beside_face, count, inputs=[bvh, sign, vertices, faces, slots, start, 0, extent],
                    outputs=[found], sliced=(), offset_at=_SOLID_BESIDE_OFFSET, device=device)


def frame_watch_order(face_count: int) -> np.ndarray:
    """Every point of `beside_points` of every face once, in an order whose every run of consecutive entries
    is spread over the whole mesh (a fixed pseudo-random permutation, so two objects of one mesh check the
    same points frame by frame)."""
    slots = beside_points(np.arange(face_count), face_count)
    return slots[np.random.default_rng(0).permutation(len(slots))]


def resolve_sign(requested: str, topology: Topology, solid: bool) -> str:
    """The method `auto` stands for: pseudonormals for a closed mesh that encloses volume with every part
    facing the same way (`solid`), else winding numbers."""
    if requested != "auto":
        return requested
    return "pseudonormal" if topology.closed and solid else "winding"


def rim_fans(faces: np.ndarray, limit: int = RIM_LIMIT, topology: Topology | None = None) -> np.ndarray | None:
    """Triangles (vertex ids) that close the faces' boundary as a chain, so the mesh and they together bound
    nothing and their winding number is a whole number wherever it is defined (`_bvh.rim_corrected`).

    The rim is each edge's net use: a face's edge a -> b counts +1 for a -> b, and the faces that run it b -> a take
    it back, so an edge two faces share the right way round cancels, a hole's edge is left once, an edge three faces
    use is left once and an edge two faces run the same way is left twice. Seams need no welding: a duplicated
    vertex's two edges are fanned to one centre, and their fans' solid angles cancel in every frame, even one that
    pulls the seam apart. Each rim edge s -> e gets the fan (centre, e, s), centre being its connected part's lowest
    vertex id, so the spokes cancel too (every vertex of the rim starts as many rim edges as end there).
    An empty array for a mesh with no rim; None where the rim needs more than `limit` fans. Given `faces`'
    `topology`, where its weld joined no two of the faces' vertex ids, the edges come from it with no sort of their
    own (the same fans, bit for bit)."""
    f = np.asarray(faces, dtype=np.int64)
    count = int(f.max()) + 1 if f.size else 1
    ids = None if topology is None else ids_by_weld(topology, f)
    low, high, net = _rim_edges_sorted(f, count) if ids is None else _rim_edges_renamed(topology, ids, count)
    copies = np.abs(net)
    total = int(copies.sum())
    if total > limit:
        return None
    if total == 0:
        return np.zeros((0, 3), np.int32)
    rim_start = np.repeat(np.where(net > 0, low, high), copies)
    rim_end = np.repeat(np.where(net > 0, high, low), copies)
    ids, compact = np.unique(np.concatenate([rim_start, rim_end]), return_inverse=True)
    compact = compact.reshape(-1)
    part = _connected(compact[:total], compact[total:], len(ids))
    centre = ids[part[compact[:total]]]
    fans = np.stack([centre, rim_end, rim_start], axis=1)
    fans = fans[(centre != rim_start) & (centre != rim_end)]  # a fan from an edge's own end subtends nothing
    return fans.astype(np.int32)


def _rim_edges_sorted(f: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lower id, higher id, net use) of each edge of faces f (vertex ids below `count`) whose uses do not cancel,
    in the order of their keys lower * count + higher."""
    start, end = f.reshape(-1), np.roll(f, -1, axis=1).reshape(-1)
    used = start != end  # a face with a repeated vertex: its zero-length edge bounds nothing
    start, end = start[used], end[used]
    low, high = np.minimum(start, end), np.maximum(start, end)
    edges, inverse = np.unique(low * count + high, return_inverse=True)
    net = np.zeros(len(edges), np.int64)
    np.add.at(net, inverse.reshape(-1), np.where(start < end, 1, -1))
    left = net != 0
    return edges[left] // count, edges[left] % count, net[left]


def _rim_edges_renamed(topology: Topology, ids: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What `_rim_edges_sorted` finds, from the topology's rim edges, for faces whose weld only renamed their vertex
    ids one to one (`ids_by_weld`): the same edges and net uses, each turned round where the renaming reversed its
    ends' order. (A face the weld finds naming a vertex twice names it twice here too; its uses cancel either way.)"""
    lower, higher, net = (ids[topology.rim_edges[:, 0]], ids[topology.rim_edges[:, 1]], topology.rim_edges[:, 2])
    net = np.where(lower < higher, net, -net)
    low, high = np.minimum(lower, higher), np.maximum(lower, higher)
    order = np.argsort(low * count + high, kind="stable")
    return low[order], high[order], net[order]


def rim_edge_vertices(topology: Topology, faces: np.ndarray) -> np.ndarray:
    """(R, 2) int32: the welded rim's edges (`Topology.rim_edges`: a seam is none), each end named by one of the
    vertex ids that `faces` (the faces `topology` was analysed from) use at that welded vertex."""
    return _an_id_per_weld(topology, faces)[topology.rim_edges[:, :2]].astype(np.int32).reshape(-1, 2)


def ids_by_weld(topology: Topology, faces: np.ndarray) -> np.ndarray | None:
    """The vertex id that `faces` name at each welded vertex of their `topology`; None where the weld made one
    vertex of two or more of their ids."""
    ids = _an_id_per_weld(topology, faces)
    return None if np.any(ids[topology.welded_faces.reshape(-1)] != np.asarray(faces).reshape(-1)) else ids


def _an_id_per_weld(topology: Topology, faces: np.ndarray) -> np.ndarray:
    """One of the vertex ids that `faces` name at each welded vertex of their `topology` (the last written)."""
    ids = np.empty(topology.welded_count, dtype=np.int64)
    ids[topology.welded_faces.reshape(-1)] = np.asarray(faces, dtype=np.int64).reshape(-1)
    return ids


def _vertex_components(faces: np.ndarray, vertex_count: int) -> np.ndarray:
    """A label per vertex, equal for vertices that faces connect."""
    # a face's a-b and b-c join all three; its c-a would join nothing more
    return _connected(faces[:, :2].reshape(-1), faces[:, 1:].reshape(-1), vertex_count)


def _connected(start: np.ndarray, end: np.ndarray, count: int) -> np.ndarray:
    """The smallest member of each of `count` items' classes, joining start[i] with end[i]: hooking and
    pointer jumping, O(log) rounds of numpy work rather than a Python loop over the pairs."""
    parent = np.arange(count, dtype=np.int64)
    start, end = start.astype(np.int64), end.astype(np.int64)
    while True:
        a, b = parent[start], parent[end]
        differ = a != b
        if not differ.any():
            return parent
        np.minimum.at(parent, np.maximum(a, b)[differ], np.minimum(a, b)[differ])
        while True:  # point every item at its root
            jumped = parent[parent]
            if np.array_equal(jumped, parent):
                break
            parent = jumped


@wp.struct
class SignView:
    method: int
    corner_fan: wp.array(dtype=wp.vec3i)  # each face corner's fan: where its vertex normal is
    face_edge: wp.array(dtype=wp.vec3i)
    face_normal: wp.array(dtype=wp.vec3)  # unit, zero for a degenerate face
    vertex_normal: wp.array(dtype=wp.vec3)  # angle-weighted pseudonormal, unit or zero
    edge_normal: wp.array(dtype=wp.vec3)  # sum of the adjacent face normals, unit or zero
    winding_frame: wp.array(dtype=wp.int32)  # (1,) nonzero: this frame encloses nothing or its parts overlap: by winding


class Pseudonormals:
    """Owns the topology on the device and the per-frame face, vertex and edge pseudonormals."""

    def __init__(self, method: str, topology: Topology, faces: wp.array, buffers: DeviceBuffers):
        self.method = method
        self.device = buffers.device
        self.faces = faces
        self._views = KeptViews(SignView)
        self.face_count = faces.shape[0]
        self.edge_count = topology.edge_count
        active = method == "pseudonormal"
        if active and not topology.has_fans:
            raise ValueError("pseudonormals need the topology's fans (analyse_topology(..., fans=True), or with_fans)")
        self.vertex_count = topology.fan_count if active else 1  # a vertex normal per fan
        b = buffers

        def upload(name, data, dtype):
            arr = b.array(name, len(data), dtype)
            if len(data):
                arr.assign(data)
            return arr

        self.corner_fan = upload("sign.corner_fan", topology.corner_fan if active else np.zeros((1, 3), np.int32), wp.vec3i)
        self.face_edge = upload("sign.face_edge", topology.face_edge if active else np.zeros((1, 3), np.int32), wp.vec3i)
        self.edge_face_start = upload("sign.edge_face_start", topology.edge_face_start if active else [0], wp.int32)
        self.edge_face = upload("sign.edge_face", topology.edge_face if active else [0], wp.int32)
        self.fan_corner_start = upload("sign.fan_corner_start", topology.fan_corner_start if active else [0], wp.int32)
        self.fan_corner = upload("sign.fan_corner", topology.fan_corner if active else [0], wp.int32)
        self.face_normal = b.array("sign.face_normal", self.face_count if active else 1, wp.vec3)
        self.face_angles = b.array("sign.face_angles", self.face_count if active else 1, wp.vec3)
        self.vertex_normal = b.array("sign.vertex_normal", self.vertex_count, wp.vec3)
        self.edge_normal = b.array("sign.edge_normal", self.edge_count + 1 if active else 1, wp.vec3)
        self.volume_area = b.array("sign.volume_area", 2, wp.float32)  # this frame's enclosed volume, area
        self.extent = b.array("sign.extent", 1, wp.float32)  # this frame's largest bounding-box side
        self._staged_extent = HostStaged(self.extent)  # stage_extent writes it, upload_extent copies it in the frame
        self.winding_frame = b.array("sign.winding_frame", 1, wp.int32)
        # whether this frame's watched faces found parts running into each other (watch_parts)
        self.parts_overlap = b.array("sign.parts_overlap", 1, wp.int32)
        # whether this frame pulled apart vertices that the first frame's weld joined (Topology.seam_pairs)
        self.seam_pairs = upload("sign.seam_pairs", topology.seam_pairs if active else np.zeros((0, 2), np.int32),
                                 wp.vec2i)
        self.seams_torn = b.array("sign.seams_torn", 1, wp.int32)
        self.seams_torn.zero_()
        self._buffers = b
        self._watched: wp.array | None = None
        self._window_start = None
        self.watch_per_frame = 0
        # what the last frame used (set_frame_method): pseudonormal frames that enclose nothing use winding
        self.frame_method = method
        self.frame_parts_overlap = False
        self.frame_seams_torn = False

    def stage_extent(self, extent: float) -> None:
        """Write the frame's extent, which the enclosed-volume test scales with, for upload_extent."""
        self._staged_extent.host()[0] = extent

    def upload_extent(self) -> None:
        """Queue the staged extent's copy to the device (with the vertices, within the frame)."""
        if self.method == "pseudonormal":
            self._staged_extent.upload()

    def watch_parts(self, order: np.ndarray, per_frame: int) -> None:
        """From the next frame on, look beside `per_frame` points of `order` (frame_watch_order) each frame, a
        window that moves on through it, for parts running into each other (surface_enters_solid), and sign a frame
        where they do by winding numbers. For `auto`, whose first frame had none: a deforming mesh may come
        to overlap itself (an arm through the body)."""
        if self.method != "pseudonormal" or len(order) == 0:
            return
        self._watched = self._buffers.array("sign.watched_faces", len(order), wp.int32)
        self._watched.assign(order)
        self._window_start = self._buffers.array("sign.window_start", 1, wp.int32)
        self.watch_per_frame = min(int(per_frame), len(order))

    def update(self, vertices: wp.array) -> None:
        """This frame's face, vertex and edge normals, the volume it encloses, and whether it pulled welded
        copies apart (read by choose_frame_method)."""
        if self.method != "pseudonormal":
            return
        self.volume_area.zero_()
        threads = min(self.face_count, _VOLUME_THREADS)
        wp.launch(_volume_area, dim=threads, inputs=[vertices, self.faces, self.face_count, threads],
                  outputs=[self.volume_area], device=self.device)
        wp.launch(_face_normals, dim=self.face_count, inputs=[vertices, self.faces],
                  outputs=[self.face_normal, self.face_angles], device=self.device)
        wp.launch(_vertex_normals, dim=self.vertex_count,
                  inputs=[self.fan_corner_start, self.fan_corner, self.face_normal, self.face_angles],
                  outputs=[self.vertex_normal], device=self.device)
        wp.launch(_edge_normals, dim=self.edge_count + 1, inputs=[self.edge_face_start, self.edge_face, self.face_normal],
                  outputs=[self.edge_normal], device=self.device)
        if self.seam_pairs.shape[0] > 0:  # else seams_torn stays zero
            self.seams_torn.zero_()
            wp.launch(_seams_torn, dim=self.seam_pairs.shape[0], inputs=[vertices, self.seam_pairs],
                      outputs=[self.seams_torn], device=self.device)

    def choose_frame_method(self, vertices: wp.array, bvh: BvhView, stream: wp.Stream | None = None) -> None:
        """Whether this frame is signed by its pseudonormals, decided on the device (read with the report).

        Pseudonormals hold only while the mesh is closed and encloses volume, outward, with no part inside
        another: a frame collapsed flat or turned inside out (its faces then coincide or face inwards), one that
        pulls apart vertices welded along an edge in the first frame (a seam, a soup's shared corners: the mesh
        has a crack the first frame's edges do not show), or, where watched, one whose parts run into each
        other, is signed by winding numbers instead. Queued on `stream` (None: the
        current one) after `update`'s normals, with `bvh` refitted to `vertices`; the watch is a short launch
        of long walks, so on CUDA it runs beside the corner searches."""
        if self.method != "pseudonormal":
            return
        with wp.ScopedStream(stream, sync_enter=False) if stream is not None else contextlib.nullcontext():
            self.parts_overlap.zero_()
            if self._watched is not None:
                _look_beside(self.watch_per_frame, bvh, self.view(), vertices, self.faces, self._watched,
                             self._window_start, self.extent, self.parts_overlap, self.device)
                wp.launch(_advance_window, dim=1, inputs=[self._window_start, self.watch_per_frame, len(self._watched)],
                          device=self.device)
            wp.launch(_choose_frame_method, dim=1,
                      inputs=[self.volume_area, self.extent, self.parts_overlap, self.seams_torn],
                      outputs=[self.winding_frame], device=self.device)

    def set_frame_method(self, winding_frame: int, parts_overlap: int, seams_torn: int) -> None:
        """Record what the last frame used, whether its watched faces found parts overlapping and whether it
        pulled welded vertices apart, from its report."""
        self.frame_method = "winding" if self.method == "pseudonormal" and winding_frame else self.method
        self.frame_parts_overlap = bool(parts_overlap)
        self.frame_seams_torn = bool(seams_torn)

    @property
    def code(self) -> int:
        """The method as the kernels take it (SIGN_NONE, SIGN_PSEUDONORMAL or SIGN_WINDING)."""
        return _SIGN_CODES[self.method]

    def view(self) -> SignView:
        return self._views.view(dict(
            method=self.code, winding_frame=self.winding_frame, corner_fan=self.corner_fan, face_edge=self.face_edge,
            face_normal=self.face_normal, vertex_normal=self.vertex_normal, edge_normal=self.edge_normal))


@wp.func
def feature_normal(sign: SignView, face: int, feature: int) -> wp.vec3:
    """Pseudonormal of a closest feature of `face` (see _geometry's feature codes)."""
    if feature == FACE:
        return sign.face_normal[face]
    if feature <= VERTEX_C:
        return sign.vertex_normal[sign.corner_fan[face][feature - VERTEX_A]]
    return sign.edge_normal[sign.face_edge[face][feature - EDGE_AB]]


# What the corners' winding kernel finds of each corner: outside, inside, or a float32 solid angle cancelled
# (a point beside a triangle far longer than it is wide), to be worked out again by `inside_by_winding`
WOUND_OUTSIDE = wp.constant(wp.uint8(0))
WOUND_INSIDE = wp.constant(wp.uint8(1))
WOUND_CANCELLED = wp.constant(wp.uint8(2))


@wp.func
def wound_side(bvh: BvhView, p: wp.vec3) -> wp.uint8:
    """WOUND_INSIDE, WOUND_OUTSIDE or WOUND_CANCELLED: the side by float32 winding numbers, unless they cancelled.
    The rim does not settle a corner's doubt near 1/2 here: handing those corners (1,119 of the bunny's 204,629) to
    the sign kernel, after the searches, made the bunny's update 0.28 ms longer on an H200 (2026-12-02 04:23)."""
    w, cancelled = winding_number(bvh, p)
    if cancelled:
        return WOUND_CANCELLED
    return wp.where(wp.abs(w) > 0.5, WOUND_INSIDE, WOUND_OUTSIDE)


@wp.func
def inside_by_winding(bvh: BvhView, p: wp.vec3) -> bool:
    """|w| > 1/2, so an inside-out mesh gives the same answer as the right way round; solid angles in float64
    where float32 cancels, and w made exact by the rim where it came within RIM_DOUBT of 1/2 (`rim_corrected`):
    queries, and the corners whose float32 cancelled (the corners' kernel takes `wound_side` instead)."""
    w, _cancelled = winding_number_careful(bvh, p)
    if bvh.rim_count > 0 and wp.abs(wp.abs(w) - 0.5) < _RIM_DOUBT:
        w = rim_corrected(bvh, p, w)
    return wp.abs(w) > 0.5


@wp.func
def inside_by_pseudonormal(sign: SignView, bvh: BvhView, p: wp.vec3, face: int, closest: wp.vec3, feature: int) -> bool:
    """By the pseudonormal of p's closest feature; by the winding number where there is none (face < 0:
    nothing within the band) or it is degenerate, or p lies on the feature's tangent plane, and in a frame
    that encloses no volume."""
    if face >= 0 and sign.winding_frame[0] == 0:
        side = wp.dot(p - closest, feature_normal(sign, face, feature))
        if side != 0.0:
            return side < 0.0
    return inside_by_winding(bvh, p)


@wp.func
def lends_no_normal(a: wp.vec3, b: wp.vec3, c: wp.vec3, cross_length: float) -> bool:
    """Whether triangle abc, whose edges' cross product (b - a) x (c - a) has this length, is too degenerate to
    lend a normal: doubled area at most DEGENERATE_AREA of its longest edge squared, or none at all."""
    longest_sq = wp.max(wp.max(wp.length_sq(b - a), wp.length_sq(c - b)), wp.length_sq(a - c))
    return cross_length <= _DEGENERATE * longest_sq or cross_length == 0.0


@wp.func
def _leaf_reads_inside(bvh: BvhView, sign: SignView, p: wp.vec3, leaf: int, reach_sq: float) -> bool:
    a, b, c = leaf_triangle(bvh, leaf)
    if triangle_distance_sq(p, a, b, c) <= reach_sq:
        closest, feature = closest_point_on_triangle(p, a, b, c)
        return wp.dot(p - closest, feature_normal(sign, bvh.leaf_face[leaf], feature)) < 0.0
    return False


@wp.func
def _reads_inside_by_a_face_within(bvh: BvhView, sign: SignView, p: wp.vec3, reach_sq: float) -> bool:
    """Whether p lies on the inner side of the pseudonormal of its closest feature on any face within
    sqrt(reach_sq) of it (not only the nearest face, which a tie between coincident faces leaves to chance)."""
    if bvh.internal_count == 0:
        return _leaf_reads_inside(bvh, sign, p, 0, reach_sq)  # a single triangle, and no tree
    nodes = wide_stack_int()
    nodes[0] = 0
    count = int(1)
    while count > 0:
        count -= 1
        node = nodes[count]
        d = entry_distances_sq(bvh, p, node)
        for j in range(4):
            child = bvh.wide_child[4 * node + j]
            if child != NO_CHILD and d[j] <= reach_sq:
                if child < 0:
                    if _leaf_reads_inside(bvh, sign, p, -1 - child, reach_sq):
                        return True
                else:
                    nodes[count] = child
                    count += 1
    return False


@wp.kernel(enable_backward=False)
def _solid_beside_face(bvh: BvhView, sign: SignView, vertices: wp.array(dtype=wp.vec3), faces: wp.array(dtype=wp.vec3i),
                       slots: wp.array(dtype=wp.int32), start: wp.array(dtype=wp.int32), offset: int,
                       extent: wp.array(dtype=wp.float32), found: wp.array(dtype=wp.int32)):
    """The point slots[(start + offset + i) mod len] for this launch's i (see surface_enters_solid, beside_points;
    `offset`: where a CPU chunk's items begin, launch_per_item). Sets `found` to 1, or leaves it."""
    slot = slots[(start[0] + offset + wp.tid()) % slots.shape[0]]
    tri = faces[slot // _POINTS_PER_FACE]
    a, b, c = vertices[tri[0]], vertices[tri[1]], vertices[tri[2]]
    n = wp.cross(b - a, c - a)
    length = wp.length(n)
    if lends_no_normal(a, b, c, length):
        return  # no direction to step in
    w = _beside_weights(slot % _POINTS_PER_FACE)
    reach = _BESIDE_REACH * extent[0]
    beside = w[0] * a + w[1] * b + w[2] * c + n * (reach / length)
    if inside_by_winding(bvh, beside):  # a false alarm signs a thin solid wrongly
        found[0] = 1
    elif _reads_inside_by_a_face_within(bvh, sign, beside, reach * reach * _NEAR_TIE_SQ):
        # outside, but a face as near as its own (a flap pressed flat: faces coincide, facing both ways)
        # reads it inside: which one a search meets first is chance, so pseudonormals cannot sign this frame
        found[0] = 1


# where _solid_beside_face takes `offset` among its arguments (launch_per_item's offset_at)
_SOLID_BESIDE_OFFSET = [arg.label for arg in _solid_beside_face.adj.args].index("offset")


@wp.func
def _beside_weights(k: int) -> wp.vec3:
    """Barycentric weights of a face's k-th point (beside_points): its centroid, then three near its
    corners and three near its edges' midpoints, each a tenth of the face's height inside."""
    if k == 0:
        return wp.vec3(1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0)
    if k == 1:
        return wp.vec3(0.8, 0.1, 0.1)
    if k == 2:
        return wp.vec3(0.1, 0.8, 0.1)
    if k == 3:
        return wp.vec3(0.1, 0.1, 0.8)
    if k == 4:
        return wp.vec3(0.45, 0.45, 0.1)
    if k == 5:
        return wp.vec3(0.1, 0.45, 0.45)
    return wp.vec3(0.45, 0.1, 0.45)


@wp.kernel(enable_backward=False)
def _advance_window(start: wp.array(dtype=wp.int32), step: int, count: int):
    start[0] = (start[0] + step) % count


@wp.kernel(enable_backward=False)
def _seams_torn(vertices: wp.array(dtype=wp.vec3), pairs: wp.array(dtype=wp.vec2i), torn: wp.array(dtype=wp.int32)):
    pair = pairs[wp.tid()]
    a = vertices[pair[0]]
    b = vertices[pair[1]]
    if a[0] != b[0] or a[1] != b[1] or a[2] != b[2]:
        torn[0] = 1


@wp.kernel(enable_backward=False)
def _choose_frame_method(volume_area: wp.array(dtype=wp.float32), extent: wp.array(dtype=wp.float32),
                         parts_overlap: wp.array(dtype=wp.int32), seams_torn: wp.array(dtype=wp.int32),
                         winding_frame: wp.array(dtype=wp.int32)):
    volume = volume_area[0]
    encloses = wp.abs(volume) > _MIN_ENCLOSED * volume_area[1] * extent[0]
    winding_frame[0] = wp.where(volume > 0.0 and encloses and parts_overlap[0] == 0 and seams_torn[0] == 0, 0, 1)


# Threads that sum a frame's enclosed volume and area, each over every _VOLUME_THREADS-th face, and add its sums
# with one atomic each: two atomics a face on one address (172K of them for the armadillo) queue up behind each other
_VOLUME_THREADS = 4096


@wp.kernel(enable_backward=False)
def _volume_area(vertices: wp.array(dtype=wp.vec3), faces: wp.array(dtype=wp.vec3i), face_count: int, threads: int,
                 volume_area: wp.array(dtype=wp.float32)):
    volume = float(0.0)
    area = float(0.0)
    for f in range(wp.tid(), face_count, threads):
        tri = faces[f]
        a = vertices[tri[0]]
        b = vertices[tri[1]]
        c = vertices[tri[2]]
        volume += wp.dot(a, wp.cross(b, c)) / 6.0
        area += 0.5 * wp.length(wp.cross(b - a, c - a))
    wp.atomic_add(volume_area, 0, volume)
    wp.atomic_add(volume_area, 1, area)


@wp.kernel(enable_backward=False)
def _face_normals(
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    face_normal: wp.array(dtype=wp.vec3),
    face_angles: wp.array(dtype=wp.vec3),
):
    f = wp.tid()
    tri = faces[f]
    a = vertices[tri[0]]
    b = vertices[tri[1]]
    c = vertices[tri[2]]
    n = wp.cross(b - a, c - a)
    length = wp.length(n)
    if lends_no_normal(a, b, c, length):
        face_normal[f] = wp.vec3(0.0)
        face_angles[f] = wp.vec3(0.0)
        return
    face_normal[f] = n / length
    ab = b - a
    bc = c - b
    ca = a - c
    face_angles[f] = wp.vec3(
        wp.atan2(wp.length(wp.cross(ab, -ca)), wp.dot(ab, -ca)),
        wp.atan2(wp.length(wp.cross(bc, -ab)), wp.dot(bc, -ab)),
        wp.atan2(wp.length(wp.cross(ca, -bc)), wp.dot(ca, -bc)),
    )


@wp.func
def _unit_or_zero(v: wp.vec3, weight: float, whole: bool) -> wp.vec3:
    """v, a sum of unit normals with this total weight, as a unit vector; zero where it has cancelled, or is
    not `whole` (a face around the feature lends no normal, so the sum leaves out one side of it: beside a
    sliver spanning a flap's rim, an edge's normal came from the face across the rim alone)."""
    length = wp.length(v)
    if whole and length > _CANCELLED * weight:
        return v / length
    return wp.vec3(0.0)


@wp.kernel(enable_backward=False)
def _vertex_normals(
    corner_start: wp.array(dtype=wp.int32),
    corners: wp.array(dtype=wp.int32),
    face_normal: wp.array(dtype=wp.vec3),
    face_angles: wp.array(dtype=wp.vec3),
    vertex_normal: wp.array(dtype=wp.vec3),
):
    v = wp.tid()
    total = wp.vec3(0.0)
    weight = float(0.0)
    whole = bool(True)
    for i in range(corner_start[v], corner_start[v + 1]):
        slot = corners[i]
        face = slot // 3
        angle = face_angles[face][slot - 3 * face]
        total += angle * face_normal[face]
        weight += angle
        whole = whole and wp.length_sq(face_normal[face]) > 0.0
    vertex_normal[v] = _unit_or_zero(total, weight, whole)


@wp.kernel(enable_backward=False)
def _edge_normals(
    face_start: wp.array(dtype=wp.int32),
    faces_of_edge: wp.array(dtype=wp.int32),
    face_normal: wp.array(dtype=wp.vec3),
    edge_normal: wp.array(dtype=wp.vec3),
):
    e = wp.tid()
    total = wp.vec3(0.0)
    whole = bool(True)
    for i in range(face_start[e], face_start[e + 1]):
        n = face_normal[faces_of_edge[i]]
        total += n
        whole = whole and wp.length_sq(n) > 0.0
    edge_normal[e] = _unit_or_zero(total, float(face_start[e + 1] - face_start[e]), whole)
