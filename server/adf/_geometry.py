"""Geometry shared by every stage: Morton codes, closest point on a triangle, boxes, solid angles.

Conventions used across the engine:
- Morton codes interleave x (most significant of each triple), y, z.
- Radix-tree keys are int64 with the Morton code left-aligned at bit 61, so the common-prefix length of two
  keys, in code bits, is ``clz64(a ^ b) - 2`` whatever the code's length; octree level = prefix // 3.
- Closest features: FACE, the vertices A, B, C, and the edges AB, BC, CA of a face (a, b, c).
"""

from __future__ import annotations

from typing import Any

import warp as wp

from badf.server.adf._tolerances import FEATURE_SNAP

# Closest-feature codes returned by closest_point_on_triangle.
FACE = wp.constant(0)
VERTEX_A = wp.constant(1)
VERTEX_B = wp.constant(2)
VERTEX_C = wp.constant(3)
EDGE_AB = wp.constant(4)
EDGE_BC = wp.constant(5)
EDGE_CA = wp.constant(6)

# Radix-tree keys hold their code in bits 61..0 (see module docstring).
KEY_TOP_BIT = wp.constant(62)

# Width of a triangle (twice its area over its longest edge), relative to that edge, below which its
# Voronoi-region tests (triangle_distance_sq) are not used: they subtract terms of the order of L^4 (L the
# longest edge) to get quantities of the order of (w L)^2, so float32 (2^-24) leaves an error of about
# 2^-24 L^2 / w: 3e-4 L at w = 2e-4 L, within 2e-6 L above 1/32. A narrower triangle goes by its plane, as
# closest_point_on_triangle does, where that is well-conditioned, else by its three edges.
NARROW_WIDTH = wp.constant(1.0 / 32.0)

# The plane of a triangle is taken from its two shortest edges (their cross product), whose rounding tilts
# it by about 2^-24 |e1| |e2| / (w L): little for a needle (one short edge), much for a flat "cap" (two
# long edges nearly in line), whose plane distance is then off by about 2^-24 |e1| |e2| / w, against w / 2
# for its three edges. The plane is used where w^2 > PLANE_CONDITION |e1| |e2|: the smaller of the two.
PLANE_CONDITION = wp.constant(2.0 * 4.0 * 2.0**-24)

_SNAP = wp.constant(FEATURE_SNAP)

# Local stack depth of BVH traversals; the radix tree over unique 62-bit keys is at most 62 levels deep.
STACK_DEPTH = 64
stack_int = wp.types.vector(length=STACK_DEPTH, dtype=wp.int32)
stack_float = wp.types.vector(length=STACK_DEPTH, dtype=wp.float32)


@wp.func
def spread_bits(v: wp.int64) -> wp.int64:
    """Insert two zero bits between each of the low 21 bits of v."""
    x = v & wp.int64(0x1FFFFF)
    x = (x | (x << wp.int64(32))) & wp.int64(0x1F00000000FFFF)
    x = (x | (x << wp.int64(16))) & wp.int64(0x1F0000FF0000FF)
    x = (x | (x << wp.int64(8))) & wp.int64(0x100F00F00F00F00F)
    x = (x | (x << wp.int64(4))) & wp.int64(0x10C30C30C30C30C3)
    x = (x | (x << wp.int64(2))) & wp.int64(0x1249249249249249)
    return x


@wp.func
def compact_bits(v: wp.int64) -> wp.int64:
    """Inverse of spread_bits: gather every third bit of v."""
    x = v & wp.int64(0x1249249249249249)
    x = (x ^ (x >> wp.int64(2))) & wp.int64(0x10C30C30C30C30C3)
    x = (x ^ (x >> wp.int64(4))) & wp.int64(0x100F00F00F00F00F)
    x = (x ^ (x >> wp.int64(8))) & wp.int64(0x1F0000FF0000FF)
    x = (x ^ (x >> wp.int64(16))) & wp.int64(0x1F00000000FFFF)
    x = (x ^ (x >> wp.int64(32))) & wp.int64(0x1FFFFF)
    return x


@wp.func
def morton3(x: int, y: int, z: int) -> wp.int64:
    return (spread_bits(wp.int64(x)) << wp.int64(2)) | (spread_bits(wp.int64(y)) << wp.int64(1)) | spread_bits(
        wp.int64(z)
    )


@wp.func
def morton3_decode(code: wp.int64) -> wp.vec3i:
    return wp.vec3i(
        int(compact_bits(code >> wp.int64(2))), int(compact_bits(code >> wp.int64(1))), int(compact_bits(code))
    )


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __clzll(x);
#else
return x == 0 ? 64 : __builtin_clzll((unsigned long long)x);
#endif
""")
def clz64(x: wp.int64) -> int: ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __popc((unsigned int)x);
#else
return __builtin_popcount((unsigned int)x);
#endif
""")
def popcount(x: int) -> int: ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
__threadfence();
#endif
""")
def thread_fence(): ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
const float4 v = __ldcg(reinterpret_cast<const float4*>(&arr.data[0]) + i);
return wp::vec4(v.x, v.y, v.z, v.w);
#else
return arr.data[i];
#endif
""")
def load_coherent_vec4(arr: wp.array(dtype=wp.vec4), i: int) -> wp.vec4:
    """Read arr[i] from L2 in one 16-byte load, past this SM's L1 (values written in the same launch)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
const float4 v = __ldg(reinterpret_cast<const float4*>(&arr.data[0]) + i);
return wp::vec4(v.x, v.y, v.z, v.w);
#else
return arr.data[i];
#endif
""")
def load_vec4(arr: wp.array(dtype=wp.vec4), i: int) -> wp.vec4:
    """Read arr[i] in one 16-byte load through the read-only cache (arrays no thread of the launch writes)."""
    ...


# A (squared distance, leaf) pair packed in 64 bits, the distance's float bits above the leaf, so that the
# least packed value is the nearest leaf, and the lower leaf index among equals. Squared distances are
# never negative, so their bits order as the floats do; leaf -1 packs above every leaf.
@wp.func_native("""
union { float f; unsigned int u; } bits;
bits.f = d_sq;
return (wp::int64)(((unsigned long long)bits.u << 32) | (unsigned long long)(unsigned int)leaf);
""")
def pack_distance_leaf(d_sq: float, leaf: int) -> wp.int64: ...


@wp.func_native("""
union { float f; unsigned int u; } bits;
bits.u = (unsigned int)((unsigned long long)packed >> 32);
return bits.f;
""")
def packed_distance_sq(packed: wp.int64) -> float: ...


@wp.func_native("""
return (int)(unsigned int)((unsigned long long)packed & 0xffffffffull);
""")
def packed_leaf(packed: wp.int64) -> int: ...


@wp.func_native("""
unsigned long long* address = reinterpret_cast<unsigned long long*>(&arr.data[0]) + i;
#if defined(__CUDA_ARCH__)
atomicMin(address, (unsigned long long)packed);
#else
if ((unsigned long long)packed < *address) *address = (unsigned long long)packed;  // a CPU launch runs its threads one at a time
#endif
""")
def atomic_min_packed(arr: wp.array(dtype=wp.int64), i: int, packed: wp.int64):
    """arr[i] = min(arr[i], packed) for values of pack_distance_leaf, atomically."""
    ...


@wp.func
def quantize(p: wp.vec3, origin: wp.vec3, inv_cell: float, resolution: int) -> wp.vec3i:
    """Integer cell coordinates of p on a grid of `resolution` cells per axis, clamped into the grid. The
    clamp comes before the conversion to int: a coordinate past 2^31 cells (a point 2,000 domain sides away
    with 2^20 cells) converted to int32's lowest on the CPU and landed in cell 0 (review, sixteenth stop)."""
    g = (p - origin) * inv_cell
    top = float(resolution - 1)
    return wp.vec3i(
        int(wp.floor(wp.clamp(g[0], 0.0, top))), int(wp.floor(wp.clamp(g[1], 0.0, top))),
        int(wp.floor(wp.clamp(g[2], 0.0, top))),
    )


@wp.func
def box_distance_sq(p: wp.vec3, lower: wp.vec3, upper: wp.vec3) -> float:
    d = wp.max(wp.max(lower - p, p - upper), wp.vec3(0.0))
    return wp.dot(d, d)


@wp.func
def _closest_on_segment(p: wp.vec3, a: wp.vec3, b: wp.vec3, feature_a: int, feature_b: int, feature_edge: int):
    ab = b - a
    length_sq = wp.dot(ab, ab)
    t = float(0.0)
    if length_sq > 0.0:
        t = wp.clamp(wp.dot(p - a, ab) / length_sq, 0.0, 1.0)
    feature = feature_edge
    if t <= _SNAP:
        feature = feature_a
    elif t >= 1.0 - _SNAP:
        feature = feature_b
    return a + t * ab, feature


@wp.func
def _reliable_plane(a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """(n, usable): the triangle's normal (unnormalised, as cross(b - a, c - a)) from its two shortest edges,
    and whether its plane is better than its edges (PLANE_CONDITION)."""
    ab = b - a
    bc = c - b
    ca = a - c
    ab_sq = wp.dot(ab, ab)
    bc_sq = wp.dot(bc, bc)
    ca_sq = wp.dot(ca, ca)
    n = wp.cross(ca, -bc)  # at c: cross(a - c, b - c)
    longest_sq = ab_sq
    shorter_product_sq = bc_sq * ca_sq
    if bc_sq > longest_sq:
        n = wp.cross(ab, -ca)  # at a: cross(b - a, c - a)
        longest_sq = bc_sq
        shorter_product_sq = ab_sq * ca_sq
    if ca_sq > longest_sq:
        n = wp.cross(bc, -ab)  # at b: cross(c - b, a - b)
        longest_sq = ca_sq
        shorter_product_sq = ab_sq * bc_sq
    n_sq = wp.dot(n, n)
    width_sq = n_sq / wp.max(longest_sq, 1.0e-30)
    usable = width_sq * width_sq > PLANE_CONDITION * PLANE_CONDITION * shorter_product_sq and n_sq > 0.0
    return n, usable


@wp.func
def _inside(q: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, n: wp.vec3) -> bool:
    return wp.dot(wp.cross(b - a, q - a), n) >= 0.0 and wp.dot(wp.cross(c - b, q - b), n) >= 0.0 and (
        wp.dot(wp.cross(a - c, q - c), n) >= 0.0
    )


@wp.func
def _narrow_distance_sq(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> float:
    """triangle_distance_sq of a narrow triangle: to its plane where the projection falls inside and the
    plane is reliable, else to the nearest of its edges."""
    n, usable = _reliable_plane(a, b, c)
    if usable:
        h = wp.dot(p - a, n)
        n_sq = wp.dot(n, n)
        if _inside(p - (h / n_sq) * n, a, b, c, n):
            return h * h / n_sq
    return wp.min(wp.min(_segment_distance_sq(p, a, b), _segment_distance_sq(p, b, c)), _segment_distance_sq(p, c, a))


@wp.func
def _segment_distance_sq(p: wp.vec3, a: wp.vec3, b: wp.vec3) -> float:
    """_closest_on_segment's distance alone. Calling it instead cost the bunny's distance stage 4% on the
    H100 (1.63-1.64 ms against 1.56-1.57, alternated three times, 2026-11-22 12:37), though the searches
    take this only for narrow triangles: its feature codes and branch are not compiled away."""
    ab = b - a
    t = wp.clamp(wp.dot(p - a, ab) / wp.max(wp.dot(ab, ab), 1.0e-30), 0.0, 1.0)
    return wp.length_sq(p - (a + t * ab))


@wp.func
def closest_point_on_triangle(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """Closest point to p on triangle (a, b, c) and its feature code; exact for narrow and degenerate ones.

    The triangle is tried first by projection onto its plane (see PLANE_CONDITION); when the projection
    falls outside, or the plane is ill-conditioned, the nearest of its three edges (as segments) wins.
    """
    n, usable = _reliable_plane(a, b, c)
    if usable:
        q = p - (wp.dot(p - a, n) / wp.dot(n, n)) * n
        if _inside(q, a, b, c, n):
            return q, FACE
    q_ab, f_ab = _closest_on_segment(p, a, b, VERTEX_A, VERTEX_B, EDGE_AB)
    q_bc, f_bc = _closest_on_segment(p, b, c, VERTEX_B, VERTEX_C, EDGE_BC)
    q_ca, f_ca = _closest_on_segment(p, c, a, VERTEX_C, VERTEX_A, EDGE_CA)
    best = q_ab
    feature = f_ab
    best_sq = wp.length_sq(p - q_ab)
    d_sq = wp.length_sq(p - q_bc)
    if d_sq < best_sq:
        best = q_bc
        feature = f_bc
        best_sq = d_sq
    d_sq = wp.length_sq(p - q_ca)
    if d_sq < best_sq:
        best = q_ca
        feature = f_ca
    return best, feature


@wp.func
def feature_on_surface(q: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, feature: int) -> int:
    """The feature of triangle (a, b, c) that q, a point on it, lies on: `feature`, or for FACE, the edge or
    vertex within FEATURE_SNAP (barycentric) of it. A point on an edge projects inside both faces (the
    projection test counts the boundary in), so on the surface FACE alone would name either face."""
    if feature != FACE:
        return feature
    n = wp.cross(b - a, c - a)
    n_sq = wp.dot(n, n)
    if n_sq == 0.0:
        return feature
    at_a = wp.dot(wp.cross(c - b, q - b), n) / n_sq  # barycentric weights of q
    at_b = wp.dot(wp.cross(a - c, q - c), n) / n_sq
    at_c = wp.dot(wp.cross(b - a, q - a), n) / n_sq
    if at_b <= _SNAP and at_c <= _SNAP:
        return VERTEX_A
    if at_c <= _SNAP and at_a <= _SNAP:
        return VERTEX_B
    if at_a <= _SNAP and at_b <= _SNAP:
        return VERTEX_C
    if at_c <= _SNAP:
        return EDGE_AB
    if at_a <= _SNAP:
        return EDGE_BC
    if at_b <= _SNAP:
        return EDGE_CA
    return feature


@wp.func
def triangle_distance_sq(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> float:
    """Squared distance from p to triangle (a, b, c): what the searches compare, so it is kept short.

    A triangle goes by the Voronoi regions of its vertices, edges and face (Ericson, Real-Time Collision
    Detection, 5.1.5): six dot products and at most one division, where the projection and three segments
    of closest_point_on_triangle take four. The two agree to rounding. A narrow triangle (see NARROW_WIDTH)
    goes by _narrow_distance_sq: the plane and edges of closest_point_on_triangle, as a distance alone.
    """
    ab = b - a
    ac = c - a
    bc = c - b
    n = wp.cross(ab, ac)
    n_sq = wp.dot(n, n)
    longest_sq = wp.max(wp.max(wp.dot(ab, ab), wp.dot(bc, bc)), wp.dot(ac, ac))
    width_limit = NARROW_WIDTH * longest_sq
    if n_sq <= width_limit * width_limit:
        return _narrow_distance_sq(p, a, b, c)
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return wp.dot(ap, ap)  # vertex a
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return wp.dot(bp, bp)  # vertex b
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        return wp.length_sq(ap - (d1 / (d1 - d3)) * ab)  # edge ab
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return wp.dot(cp, cp)  # vertex c
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        return wp.length_sq(ap - (d2 / (d2 - d6)) * ac)  # edge ac
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
        return wp.length_sq(bp - ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * bc)  # edge bc
    # the face: the distance to its plane
    h = wp.dot(ap, n)
    return h * h / n_sq


@wp.func
def _tangent_terms(p: Any, a: Any, b: Any, c: Any):
    """The numerator and denominator of tan(omega / 2) for triangle (a, b, c) seen from p (Van Oosterom and
    Strackee 1983), and the product of the three lengths from p, in the points' precision."""
    x = a - p
    y = b - p
    z = c - p
    lx = wp.length(x)
    ly = wp.length(y)
    lz = wp.length(z)
    lengths = lx * ly * lz
    det = wp.dot(x, wp.cross(y, z))
    denominator = lengths + wp.dot(x, y) * lz + wp.dot(x, z) * ly + wp.dot(y, z) * lx
    return det, denominator, lengths


# Where both terms of a solid angle's tangent are below this fraction of the product of the three lengths,
# float32 has cancelled most of their digits (a point beside a long thin triangle, near the line of an edge,
# sees it as about a half-sphere)
_HALF_SPHERE_CANCELLED = wp.constant(1.0e-3)


@wp.func
def solid_angle_checked(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """Signed solid angle of triangle (a, b, c) seen from p, in float32, and whether float32 cancelled most of
    its digits (then `solid_angle_careful` is right, and this may not be)."""
    det, denominator, lengths = _tangent_terms(p, a, b, c)
    cancelled = wp.max(wp.abs(det), wp.abs(denominator)) < _HALF_SPHERE_CANCELLED * lengths
    return 2.0 * wp.atan2(det, denominator), cancelled


@wp.func
def solid_angle_careful(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> float:
    """The solid angle, worked out again in float64 where float32 cancels: beside a needle 1e-4 of its length
    thick, the winding numbers of points just outside came out near 1 instead of 0."""
    angle, cancelled = solid_angle_checked(p, a, b, c)
    if cancelled:
        det64, denominator64, _lengths64 = _tangent_terms(wp.vec3d(p), wp.vec3d(a), wp.vec3d(b), wp.vec3d(c))
        return float(wp.float64(2.0) * wp.atan2(det64, denominator64))
    return angle


@wp.func
def _separated_on_axis(axis: wp.vec3, v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, half: float) -> bool:
    # Box centred at the origin with half-size `half`; triangle v0, v1, v2 relative to the box centre.
    p0 = wp.dot(axis, v0)
    p1 = wp.dot(axis, v1)
    p2 = wp.dot(axis, v2)
    r = half * (wp.abs(axis[0]) + wp.abs(axis[1]) + wp.abs(axis[2]))
    return wp.min(wp.min(p0, p1), p2) > r or wp.max(wp.max(p0, p1), p2) < -r


@wp.func
def triangle_overlaps_cube(a: wp.vec3, b: wp.vec3, c: wp.vec3, centre: wp.vec3, half: float) -> bool:
    """Separating-axis test of triangle (a, b, c) against the axis-aligned cube (centre, half-size).

    The 13 axes: the cube's 3 face normals, the triangle's normal, and the 9 edge-by-axis cross products.
    A zero axis (degenerate triangle) never separates, so the test stays conservative.
    """
    v0 = a - centre
    v1 = b - centre
    v2 = c - centre
    lo = wp.min(wp.min(v0, v1), v2)
    hi = wp.max(wp.max(v0, v1), v2)
    for k in range(3):
        if lo[k] > half or hi[k] < -half:
            return False
    if _separated_on_axis(wp.cross(v1 - v0, v2 - v0), v0, v1, v2, half):
        return False
    edges = wp.matrix_from_rows(v1 - v0, v2 - v1, v0 - v2)
    for i in range(3):
        e = edges[i]
        if _separated_on_axis(wp.vec3(0.0, -e[2], e[1]), v0, v1, v2, half):
            return False
        if _separated_on_axis(wp.vec3(e[2], 0.0, -e[0]), v0, v1, v2, half):
            return False
        if _separated_on_axis(wp.vec3(-e[1], e[0], 0.0), v0, v1, v2, half):
            return False
    return True
