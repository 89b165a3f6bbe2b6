"""Hard inputs for the engine, shared by tests/test_stability.py and `badf bench accuracy`.

Each case states what the engine must do (answer within a stated bound of the float64 oracle, or raise a
specific error and keep its last good state), runs it on one device, and reports what it measured. Bounds
come from badf.bench._tolerances; "diag" is the mesh's bounding-box diagonal.

A general bound used throughout: every stored corner value is an exact distance and the signed distance
to a solid (the unsigned distance to anything) is 1-Lipschitz, so a trilinear blend of a leaf's corners
is within the distance from the point to the leaf's farthest corner: one leaf diagonal.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from badf.bench import _oracle as oracle
from badf.bench import _tolerances as tol
from badf.bench._common import find_mesh
from badf.server._mesh_files import read_mesh

ALL_OUTPUTS = ("distance", "closest_point", "normal", "face")


def folded_sheet(layers: int = 110, strips: int = 20, panels: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """An open sheet folded into `layers` flat layers a 1/(layers - 1) apart across a unit square, each of `strips`
    strips 1 long and 1/`strips` wide (cut across into `panels` panels each), with a fold of as many strips between
    each two. By default 8,760 triangles 20 times as long as wide, 11.8 times the area of the sphere around them (a
    soup by SOUP_AREA), though none crosses another: the winding walks' budget counts only fat nodes (FAT_AREA) for
    such a surface."""
    lift = 1.0 / (layers - 1)
    # the profile in (y, z): across a layer in `panels` steps, then up to the next one
    profile = [(0.0, 0.0)]
    for k in range(layers):
        start, end = (0.0, 1.0) if k % 2 == 0 else (1.0, 0.0)
        profile.extend((start + (end - start) * t, k * lift) for t in np.linspace(0.0, 1.0, panels + 1)[1:])
        if k + 1 < layers:
            profile.append((end, (k + 1) * lift))
    xs = np.linspace(0.0, 1.0, strips + 1)
    vertices = np.array([(x, y, z) for y, z in profile for x in xs], np.float32)
    row = strips + 1
    i, j = np.meshgrid(np.arange(strips), np.arange(len(profile) - 1))
    a = (j * row + i).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + row], 1), np.stack([a + 1, a + row + 1, a + row], 1)])
    return vertices, faces.astype(np.int32)


@dataclass
class Outcome:
    """What one case measured: whether it met its expectation, a one-line account, and the numbers."""

    passed: bool
    measured: str
    numbers: dict = field(default_factory=dict)


@dataclass(frozen=True)
class StabilityCase:
    name: str
    group: str
    expected: str
    run: Callable[[str], Outcome]  # device -> what it measured


# -- shapes ---------------------------------------------------------------------------------------------
def icosphere(subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A unit sphere (float64 vertices, int32 faces), outward-facing."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int32)


def box(extents=(1.0, 1.0, 1.0), centre=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    m = trimesh.creation.box(extents=extents)
    return np.asarray(m.vertices, np.float64) + np.asarray(centre, np.float64), np.asarray(m.faces, np.int32)


def zero_area_and_collinear() -> tuple[np.ndarray, np.ndarray]:
    """A sphere plus 20 zero-area faces (a vertex named twice) and 20 collinear ones (an edge and its midpoint)."""
    v, f = icosphere()
    repeated = np.stack([f[:20, 0], f[:20, 0], f[:20, 1]], axis=1)
    a, b = f[20:40, 0], f[20:40, 1]
    midpoints = (v[a] + v[b]) / 2.0
    mid_index = len(v) + np.arange(20)
    collinear = np.stack([a, b, mid_index], axis=1)
    return np.concatenate([v, midpoints]), np.concatenate([f, repeated, collinear]).astype(np.int32)


def triangle_soup() -> tuple[np.ndarray, np.ndarray]:
    """A sphere whose every face has its own three vertices: each position is repeated about six times."""
    v, f = icosphere()
    return v[f].reshape(-1, 3), np.arange(3 * len(f), dtype=np.int32).reshape(-1, 3)


def sliver_tetrahedron(sliver_count: int = 1000, width: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """A closed unit tetrahedron whose two faces on the x axis are fans of `sliver_count` slivers `width`
    wide and about 1 long (aspect ratio 1 / width), sharing the split points of that axis."""
    xs = np.concatenate([[0.0], 0.5 + width * np.arange(sliver_count + 1), [1.0]])
    base = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)
    y_apex, z_apex = len(base), len(base) + 1
    vertices = np.concatenate([base, [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]])
    i = np.arange(len(base) - 1)
    fan_y = np.stack([i, np.full_like(i, y_apex), i + 1], axis=1)  # the face z = 0, facing -z
    fan_z = np.stack([i, i + 1, np.full_like(i, z_apex)], axis=1)  # the face y = 0, facing -y
    origin, x_end = 0, len(base) - 1
    rest = np.array([[origin, z_apex, y_apex], [x_end, y_apex, z_apex]])  # x = 0 and the slanted face
    return vertices, np.concatenate([fan_y, fan_z, rest]).astype(np.int32)


def single_triangle() -> tuple[np.ndarray, np.ndarray]:
    return np.array([[0, 0, 0], [1, 0, 0], [0.2, 0.9, 0.1]], np.float64), np.array([[0, 1, 2]], np.int32)


def flat_sheet(n: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """An open square of n x n quads lying exactly in the plane z = 0 (zero extent along z)."""
    x, y = np.meshgrid(np.linspace(-1, 1, n + 1), np.linspace(-1, 1, n + 1), indexing="ij")
    vertices = np.stack([x, y, np.zeros_like(x)], axis=-1).reshape(-1, 3)
    idx = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return vertices, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)


def thin_plate(thickness: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """A closed 1 x 1 plate `thickness` thick."""
    return box(extents=(1.0, 1.0, thickness))


def inverted_sphere() -> tuple[np.ndarray, np.ndarray]:
    v, f = icosphere()
    return v, np.ascontiguousarray(f[:, ::-1])


def sphere_with_opposite_duplicates(count: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A sphere with `count` of its faces repeated in the opposite orientation (their edges get four faces)."""
    v, f = icosphere()
    return v, np.concatenate([f, f[:count, ::-1]]).astype(np.int32)


def boxes_sharing_an_edge() -> tuple[np.ndarray, np.ndarray]:
    """Two closed unit cubes touching along one edge (welded): that edge has four faces."""
    v1, f1 = box(centre=(0.5, 0.5, 0.5))
    v2, f2 = box(centre=(1.5, 1.5, 0.5))
    return np.concatenate([v1, v2]), np.concatenate([f1, f2 + len(v1)]).astype(np.int32)


def shared_mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    """A mesh of the shared data set by name; the first frame of a sequence."""
    return read_mesh(find_mesh(name))


# -- points ---------------------------------------------------------------------------------------------
def surface_samples(vertices: np.ndarray, faces: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` points uniform by area on the surface (float64)."""
    tri = np.asarray(vertices, np.float64)[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    weights = area / area.sum() if area.sum() > 0 else None
    pick = rng.choice(len(faces), size=count, p=weights)
    r1, r2 = rng.random((2, count))
    flip = r1 + r2 > 1.0
    r1, r2 = np.where(flip, 1.0 - r1, r1), np.where(flip, 1.0 - r2, r2)
    t = tri[pick]
    return t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])


def near_surface(samples: np.ndarray, reach: float, rng: np.random.Generator) -> np.ndarray:
    """Each sample moved in a random direction by a random length up to `reach`."""
    direction = rng.normal(size=samples.shape)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return samples + direction * rng.random((len(samples), 1)) * reach


def domain_of(distance_field) -> tuple[np.ndarray, float, float]:
    """(centre, side, finest cell size) of a field's domain cube."""
    info = distance_field.info()["domain"]
    return np.asarray(info["centre"], np.float64), float(info["side"]), float(info["finest_cell"])


def probe_points(distance_field, vertices, faces, count: int, rng: np.random.Generator) -> np.ndarray:
    """Uniform points in the domain, points within two finest cells of the surface, surface samples, and
    eight points 50 diagonals away."""
    centre, side, cell = domain_of(distance_field)
    diag = oracle.bbox_diagonal(vertices)
    uniform = centre + (rng.random((count, 3)) - 0.5) * side
    on = surface_samples(vertices, faces, count, rng)
    near = near_surface(on, 2.0 * cell, rng)
    far = centre + rng.normal(size=(8, 3)) * 50.0 * diag
    return np.concatenate([uniform, near, on[: count // 2], far])


def leaf_sides(distance_field, points: np.ndarray) -> np.ndarray:
    """Side length of the octree leaf holding each point; NaN outside the domain (answered exactly there)."""
    centre, side, cell = domain_of(distance_field)
    depth = distance_field.info()["depth"]
    levels, cells = distance_field.octree_cells()
    g = (np.asarray(points, np.float64) - (centre - side / 2.0)) / cell
    inside = np.all((g >= 0.0) & (g <= float(1 << depth)), axis=1)
    at = np.clip(np.floor(g), 0, (1 << depth) - 1).astype(np.int64)
    deepest = np.full(len(points), -1)
    for level in range(depth + 1):
        nodes = cells[levels == level]
        keys = set(map(tuple, nodes))
        mine = at >> (depth - level)
        present = np.fromiter((tuple(c) in keys for c in mine), bool, len(mine))
        deepest = np.where(present, level, deepest)
    leaf_level = np.minimum(deepest + 1, depth)
    return np.where(inside, side / 2.0 ** leaf_level, np.nan)



# corner c of a cell lies at this offset from its lowest corner, in cells (the engine's corner order)
CORNER_OFFSETS = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)])


def finest_leaf_corners(distance_field, points: np.ndarray) -> np.ndarray:
    """(P, 8) float64: the field's values at the corners (CORNER_OFFSETS) of each point's leaf where that leaf is one
    of the finest level, NaN rows elsewhere; from the field's own lists (`corner_samples`, `octree_cells`)."""
    centre, side, cell = domain_of(distance_field)
    depth = distance_field.info()["depth"]
    low = centre - side / 2.0
    positions, values, _ = distance_field.corner_samples()
    value_at = dict(zip(map(tuple, np.rint((positions - low) / cell).astype(np.int64)), values.astype(np.float64)))
    levels, cells = distance_field.octree_cells()
    finest = set(map(tuple, cells[levels == depth]))
    corners = np.full((len(points), 8), np.nan)
    for i, base in enumerate(np.floor((np.asarray(points, np.float64) - low) / cell).astype(np.int64)):
        if tuple(base) in finest:
            corners[i] = [value_at[tuple(base + offset)] for offset in CORNER_OFFSETS]
    return corners


def rim_cells(distance_field, vertices: np.ndarray, faces: np.ndarray) -> set[tuple[int, int, int]]:
    """The finest cells (integer coordinates in the field's domain) that the mesh's rim passes through: the engine's
    rim edges (`_sign.rim_edge_vertices`, welded), each sampled every eighth of a cell. These cells are among the
    leaves the engine marks (`mark_rim_leaves`, which widens each piece's box)."""
    from badf.server.adf._sign import analyse_topology, rim_edge_vertices

    centre, side, cell = domain_of(distance_field)
    low = centre - side / 2.0
    v = np.asarray(vertices, np.float64)
    edges = rim_edge_vertices(analyse_topology(np.asarray(faces, np.int64), v, fans=False), faces)
    cells: set[tuple[int, int, int]] = set()
    for a, b in v[edges]:
        t = np.linspace(0.0, 1.0, int(np.ceil(8.0 * np.linalg.norm(b - a) / cell)) + 2)[:, None]
        cells.update(map(tuple, np.floor((a + t * (b - a) - low) / cell).astype(np.int64)))
    return cells

# -- measurements ---------------------------------------------------------------------------------------
def nonfinite_count(result) -> int:
    return int(sum(np.count_nonzero(~np.isfinite(a)) for a in (result.distance, result.closest_point, result.normal)
                   if a is not None))


def _normals_are_unit_or_zero(normal: np.ndarray) -> bool:
    length = np.linalg.norm(normal, axis=1)
    return bool(np.all((np.abs(length - 1.0) < 1e-4) | (length == 0.0)))


def _oracle_sides(points: np.ndarray, vertices: np.ndarray, faces, truth: np.ndarray, *, signed: bool):
    """(the oracle's signed distances, where its side is sure): a side counts where the winding number is more
    than WINDING_CONFIDENCE from 1/2 and the point more than SIGN_MARGIN diagonals from the surface."""
    near = truth <= tol.SIGN_MARGIN * oracle.bbox_diagonal(vertices)
    if not signed:
        return truth, ~near
    w = oracle.winding_number(points, vertices, faces)
    return np.where(np.abs(w) > 0.5, -truth, truth), (np.abs(np.abs(w) - 0.5) > tol.WINDING_CONFIDENCE) & ~near


def wrong_sides(distance_field, vertices, faces, points: np.ndarray) -> np.ndarray:
    """The indices of the points whose exact answer is on the other side from the oracle's, where its side is sure."""
    vertices = np.asarray(vertices, np.float64)
    truth = oracle.nearest(points, vertices, faces).distance
    truth_signed, confident = _oracle_sides(points, vertices, faces, truth,
                                            signed=distance_field.info()["sign"] != "none")
    exact = distance_field.query(points, mode="exact").distance
    return np.flatnonzero(_on_wrong_side(exact, truth_signed, confident))


def _on_wrong_side(distance: np.ndarray, truth_signed: np.ndarray, confident: np.ndarray) -> np.ndarray:
    """Where an answer's side is not the oracle's, among the points whose side the oracle is sure of."""
    return confident & ((distance < 0) != (truth_signed < 0))


def compare_with_oracle(distance_field, vertices, faces, points: np.ndarray, *, solid: bool) -> dict:
    """Exact and ADF answers at `points` against the oracle, as ratios to their bounds (<= 1 passes).

    solid: the oracle's signed distance is continuous (the winding number is 0 or 1 off the surface), so
    the ADF bound applies to the signed values; otherwise only |adf| <= |truth| + bound is guaranteed.
    """
    vertices = np.asarray(vertices, np.float64)
    truth = oracle.nearest(points, vertices, faces).distance
    signed = distance_field.info()["sign"] != "none"
    diag = oracle.bbox_diagonal(vertices)
    truth_signed, confident = _oracle_sides(points, vertices, faces, truth, signed=signed)
    exact = distance_field.query(points, mode="exact", outputs=ALL_OUTPUTS)
    adf = distance_field.query(points, mode="adf", outputs=ALL_OUTPUTS)
    exact_allowed = tol.EXACT_DISTANCE * diag + tol.FLOAT32_RELATIVE * truth
    exact_error = np.abs(np.abs(exact.distance) - truth)
    wrong_signs = int(np.count_nonzero(_on_wrong_side(exact.distance, truth_signed, confident)))
    leaf = leaf_sides(distance_field, points)
    adf_allowed = np.where(np.isnan(leaf), exact_allowed, tol.ADF_LEAF_DIAGONALS * math.sqrt(3.0) * np.nan_to_num(leaf)
                           + tol.EXACT_DISTANCE * diag)
    if solid or not signed:
        adf_error = np.abs(adf.distance - truth_signed)
    else:
        adf_error = np.maximum(np.abs(adf.distance) - truth, 0.0)
    faces_ok = bool(np.all((exact.face >= 0) & (exact.face < len(faces))))
    return {
        "points": len(points),
        "nonfinite": nonfinite_count(exact) + nonfinite_count(adf),
        "exact_max_error_diag": float(exact_error.max() / diag),
        "exact_bound_ratio": float(np.max(exact_error / exact_allowed)),
        "sign_checked": int(confident.sum()),
        "wrong_signs": wrong_signs,
        "adf_max_error_diag": float(adf_error.max() / diag),
        "adf_bound_ratio": float(np.max(adf_error / adf_allowed)),
        "unit_normals": _normals_are_unit_or_zero(exact.normal) and _normals_are_unit_or_zero(adf.normal),
        "faces_in_range": faces_ok,
    }


def _verdict(numbers: dict) -> Outcome:
    passed = (
        numbers["nonfinite"] == 0
        and numbers["exact_bound_ratio"] <= 1.0
        and numbers["wrong_signs"] == 0
        and numbers["adf_bound_ratio"] <= 1.0
        and numbers["unit_normals"]
        and numbers["faces_in_range"]
    )
    text = (f"exact max {numbers['exact_max_error_diag']:.1e} diag ({numbers['exact_bound_ratio']:.2f} of bound), "
            f"wrong signs {numbers['wrong_signs']}/{numbers['sign_checked']}, adf max "
            f"{numbers['adf_max_error_diag']:.1e} diag ({numbers['adf_bound_ratio']:.2f} of bound), "
            f"non-finite {numbers['nonfinite']}")
    if not numbers["unit_normals"]:
        text += ", normals not unit"
    if not numbers["faces_in_range"]:
        text += ", face index out of range"
    return Outcome(passed, text, numbers)


def mesh_case(make: Callable[[], tuple[np.ndarray, np.ndarray]], *, solid: bool, depth: int = 5, sign: str = "auto",
              count: int = 200) -> Callable[[str], Outcome]:
    """A case that builds a field of `make()` and compares exact and ADF answers with the oracle."""

    def run(device: str) -> Outcome:
        from badf.server.adf import DistanceField

        vertices, faces = make()
        distance_field = DistanceField(vertices, faces, depth=depth, sign=sign, device=device)
        points = probe_points(distance_field, vertices, faces, count, np.random.default_rng(0))
        outcome = _verdict(compare_with_oracle(distance_field, vertices, faces, points, solid=solid))
        outcome.numbers["sign"] = distance_field.info()["sign"]
        outcome.measured = f"sign={outcome.numbers['sign']}: " + outcome.measured
        return outcome

    return run


MESH_EXPECTED = ("finite; exact |d| within 1e-5 diag (+1e-6 relative); signs of the winding oracle; "
                 "adf within one leaf diagonal")


# -- extreme scales -------------------------------------------------------------------------------------
def scaled_sphere(scale: float, offset: float) -> Callable[[], tuple[np.ndarray, np.ndarray]]:
    """The unit sphere scaled by `scale` and moved by `offset` along every axis, in float64."""

    def make():
        v, f = icosphere()
        return v * scale + offset, f

    return make


def float32_input_case(offset: float, depth: int = 5, count: int = 200) -> Callable[[str], Outcome]:
    """The unit sphere at `offset`, handed to the engine as float32 vertices and points; measured against the
    float64 truth of the unrounded shape, so the error is what float32 input costs."""

    def run(device: str) -> Outcome:
        from badf.server.adf import DistanceField

        vertices, faces = scaled_sphere(1.0, offset)()
        distance_field = DistanceField(vertices.astype(np.float32), faces, depth=depth, device=device)
        rng = np.random.default_rng(0)
        points = probe_points(distance_field, vertices, faces, count, rng)[: -8]  # no far points here
        truth = oracle.signed_distance(points, vertices, faces)
        diag = oracle.bbox_diagonal(vertices)
        exact = distance_field.query(points.astype(np.float32), mode="exact").distance
        error = np.abs(exact - truth)
        magnitude = float(np.abs(points).max())
        rounding = 2.0 * math.sqrt(3.0) * tol.FLOAT32_INPUT_ROUNDING * magnitude
        allowed = tol.EXACT_DISTANCE * diag + rounding
        numbers = {"exact_max_error_diag": float(error.max() / diag), "rounding_bound_diag": rounding / diag,
                   "bound_ratio": float(error.max() / allowed), "nonfinite": int(np.count_nonzero(~np.isfinite(exact)))}
        passed = numbers["nonfinite"] == 0 and numbers["bound_ratio"] <= 1.0
        text = (f"exact max {numbers['exact_max_error_diag']:.1e} diag; float32 rounding of the input alone allows "
                f"{numbers['rounding_bound_diag']:.1e} diag ({numbers['bound_ratio']:.2f} of bound)")
        return Outcome(passed, text, numbers)

    return run


# -- extreme queries ------------------------------------------------------------------------------------
def features_case(depth: int = 6) -> Callable[[str], Outcome]:
    """Points exactly on the vertices, edge midpoints and face centroids of a closed mesh (spot)."""

    def run(device: str) -> Outcome:
        from badf.server.adf import DistanceField

        vertices, faces = shared_mesh("spot")
        v = vertices.astype(np.float64)
        distance_field = DistanceField(vertices, faces, depth=depth, device=device)
        _, _, cell = domain_of(distance_field)
        diag = oracle.bbox_diagonal(v)
        rng = np.random.default_rng(0)
        pick = rng.choice(len(faces), 300, replace=False)
        tri = v[faces[pick]]
        groups = {"vertices": v[rng.choice(len(v), 300, replace=False)], "edges": (tri[:, 0] + tri[:, 1]) / 2.0,
                  "faces": tri.mean(axis=1)}
        numbers = {"nonfinite": 0, "unit_normals": True}
        passed = True
        for name, points in groups.items():
            truth = oracle.nearest(points, v, faces).distance  # zero up to the rounding of the midpoints
            exact = distance_field.query(points, mode="exact", outputs=ALL_OUTPUTS)
            adf = distance_field.query(points, mode="adf", outputs=ALL_OUTPUTS)
            exact_error = float(np.abs(np.abs(exact.distance) - truth).max())
            adf_error = float(np.abs(adf.distance - truth).max())
            numbers[f"{name}_exact_max_diag"] = exact_error / diag
            numbers[f"{name}_adf_max_cells"] = adf_error / cell
            numbers["nonfinite"] += nonfinite_count(exact) + nonfinite_count(adf)
            numbers["unit_normals"] &= _normals_are_unit_or_zero(exact.normal) and _normals_are_unit_or_zero(adf.normal)
            passed &= exact_error <= tol.EXACT_DISTANCE * diag and adf_error <= tol.ADF_NEAR_SURFACE * cell
        passed &= numbers["nonfinite"] == 0 and numbers["unit_normals"]
        text = ", ".join(f"{name}: exact {numbers[f'{name}_exact_max_diag']:.1e} diag, adf "
                         f"{numbers[f'{name}_adf_max_cells']:.2f} cells" for name in groups)
        return Outcome(passed, text + f", non-finite {numbers['nonfinite']}", numbers)

    return run


def far_points_case(distance: float = 1e6) -> Callable[[str], Outcome]:
    """Points `distance` diagonals from the mesh in every direction; both modes answer exactly there."""

    def run(device: str) -> Outcome:
        from badf.server.adf import DistanceField

        vertices, faces = shared_mesh("spot")
        distance_field = DistanceField(vertices, faces, depth=5, device=device)
        diag = oracle.bbox_diagonal(vertices)
        directions = np.random.default_rng(0).normal(size=(200, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        points = vertices.astype(np.float64).mean(axis=0) + directions * distance * diag
        truth = oracle.nearest(points, vertices, faces).distance
        worst, nonfinite, negative = 0.0, 0, 0
        for mode in ("exact", "adf"):
            result = distance_field.query(points, mode=mode, outputs=ALL_OUTPUTS)
            worst = max(worst, float(np.max(np.abs(result.distance - truth) / truth)))
            nonfinite += nonfinite_count(result)
            negative += int(np.count_nonzero(result.distance < 0))
        numbers = {"max_relative_error": worst, "nonfinite": nonfinite, "negative": negative}
        passed = worst <= tol.FLOAT32_RELATIVE and nonfinite == 0 and negative == 0
        return Outcome(passed, f"max relative error {worst:.1e}, negative {negative}, non-finite {nonfinite}", numbers)

    return run


def empty_batch_case(device: str) -> Outcome:
    from badf.server.adf import DistanceField

    vertices, faces = icosphere(2)
    distance_field = DistanceField(vertices, faces, depth=4, device=device)
    shapes = {}
    for mode in ("exact", "adf"):
        result = distance_field.query(np.zeros((0, 3)), mode=mode, outputs=ALL_OUTPUTS)
        shapes[mode] = [getattr(result, name).shape for name in ALL_OUTPUTS]
    expected = [(0,), (0, 3), (0, 3), (0,)]
    passed = all(s == expected for s in shapes.values())
    return Outcome(passed, f"shapes {shapes['adf']} (adf), {shapes['exact']} (exact)", {"passed": passed})


def large_batch_case(count: int = 10_000_000, mode: str = "adf") -> Callable[[str], Outcome]:
    """`count` uniform points in one call: answered in chunks, so device memory does not grow with the batch.

    Memory is read from stats()["device_bytes"] after a first batch larger than one chunk and again after
    the big one; a sample of the answers is checked against the oracle.
    """

    def run(device: str) -> Outcome:
        from badf.server.adf import DistanceField

        vertices, faces = shared_mesh("spot")
        distance_field = DistanceField(vertices, faces, depth=6, device=device)
        centre, side, _ = domain_of(distance_field)
        rng = np.random.default_rng(0)
        distance_field.query(centre + (rng.random((2_500_000, 3), np.float32) - 0.5) * side, mode=mode)
        before = distance_field.stats()["device_bytes"]
        points = (rng.random((count, 3), np.float32) - 0.5) * np.float32(side) + centre.astype(np.float32)
        result = distance_field.query(points, mode=mode)
        after = distance_field.stats()["device_bytes"]
        nonfinite = int(np.count_nonzero(~np.isfinite(result.distance)))
        sample = rng.choice(count, 500, replace=False)
        truth = oracle.signed_distance(points[sample], vertices, faces)
        leaf = leaf_sides(distance_field, points[sample].astype(np.float64))
        allowed = tol.ADF_LEAF_DIAGONALS * math.sqrt(3.0) * leaf + tol.EXACT_DISTANCE * oracle.bbox_diagonal(vertices)
        ratio = float(np.max(np.abs(result.distance[sample] - truth) / allowed))
        numbers = {"points": count, "device_bytes_before": before, "device_bytes_after": after,
                   "nonfinite": nonfinite, "sample_bound_ratio": ratio}
        passed = after == before and nonfinite == 0 and ratio <= 1.0
        text = (f"{count:,} points: device bytes {before:,} before, {after:,} after; non-finite {nonfinite}; "
                f"500 sampled within {ratio:.2f} of the leaf bound")
        return Outcome(passed, text, numbers)

    return run


# -- stiff motion between two frames --------------------------------------------------------------------
def _move(vertices: np.ndarray, how: str) -> np.ndarray:
    v = vertices.astype(np.float64)
    size = oracle.bbox_diagonal(v)
    centre = (v.min(axis=0) + v.max(axis=0)) / 2.0
    if how == "translate":
        return v + np.array([0.8, -0.48, 0.36]) * 10.0 * size  # a unit direction, 10 diagonals
    if how == "scale":
        return centre + (v - centre) * 100.0
    if how == "collapse":
        flat = v.copy()
        flat[:, 2] = centre[2]
        return flat
    if how == "jitter":
        return v + np.random.default_rng(1).normal(scale=0.05 * size, size=v.shape)
    raise ValueError(how)


def stiff_motion_case(how: str, *, signs_defined: bool, depth: int = 5, count: int = 200) -> Callable[[str], Outcome]:
    """One frame of drastic motion after the first, with coherence on: every answer of the new frame must be
    exact (corner values and exact queries) and equal to a field built without coherence. Where the motion
    leaves inside and outside undefined (a collapsed or self-intersecting mesh), signs are only reported."""

    def run(device: str) -> Outcome:
        from badf.server.adf import DistanceField

        vertices, faces = shared_mesh("spot")
        moved = _move(vertices, how)
        coherent = DistanceField(vertices, faces, depth=depth, coherence=True, device=device)
        coherent.update(moved)
        fresh = DistanceField(vertices, faces, depth=depth, coherence=False, device=device)
        fresh.update(moved)
        diag = oracle.bbox_diagonal(moved)
        positions, values, _ = coherent.corner_samples()
        _, fresh_values, _ = fresh.corner_samples()
        pick = np.random.default_rng(2).choice(len(positions), min(400, len(positions)), replace=False)
        corner_truth = oracle.nearest(positions[pick], moved, faces).distance
        corner_error = float(np.abs(np.abs(values[pick]) - corner_truth).max())
        if len(values) != len(fresh_values):
            raise RuntimeError(f"the coherent field has {len(values)} corners, a fresh one {len(fresh_values)}")
        difference_to_fresh = float(np.abs(np.abs(values) - np.abs(fresh_values)).max())
        signs_unlike_fresh = int(np.count_nonzero((values < 0) != (fresh_values < 0)))
        points = probe_points(coherent, moved, faces, count, np.random.default_rng(3))
        truth = oracle.nearest(points, moved, faces).distance
        exact = coherent.query(points, mode="exact", outputs=ALL_OUTPUTS)
        exact_error = np.abs(np.abs(exact.distance) - truth)
        allowed = tol.EXACT_DISTANCE * diag + tol.FLOAT32_RELATIVE * truth
        inside = np.abs(oracle.winding_number(points, moved, faces)) > 0.5
        clear = truth > tol.SIGN_MARGIN * diag
        wrong_signs = int(np.count_nonzero((exact.distance < 0)[clear] != inside[clear]))
        numbers = {
            "coherent_frame": bool(coherent.stats()["counts"]["coherent_frame"]),
            "corner_max_error_diag": corner_error / diag,
            "max_difference_to_fresh_diag": difference_to_fresh / diag,
            "corner_signs_unlike_fresh": signs_unlike_fresh,
            "exact_max_error_diag": float(exact_error.max() / diag),
            "wrong_signs": wrong_signs,
            "sign_checked": int(clear.sum()),
            "nonfinite": nonfinite_count(exact) + nonfinite_count(coherent.query(points, mode="adf")),
        }
        passed = (
            corner_error <= tol.EXACT_DISTANCE * diag
            and difference_to_fresh <= tol.EXACT_DISTANCE * diag
            and bool(np.all(exact_error <= allowed))
            and numbers["nonfinite"] == 0
            and (wrong_signs == 0 or not signs_defined)
        )
        text = (f"|corner| max error {numbers['corner_max_error_diag']:.1e} diag, |corner| vs no coherence "
                f"{numbers['max_difference_to_fresh_diag']:.1e} diag ({signs_unlike_fresh} signs differ), exact max "
                f"{numbers['exact_max_error_diag']:.1e} diag, signs unlike the winding oracle {wrong_signs}/"
                f"{numbers['sign_checked']}, non-finite {numbers['nonfinite']}")
        return Outcome(passed, text, numbers)

    return run


# -- non-finite input -----------------------------------------------------------------------------------
def bad_values_case(target: str, value: float) -> Callable[[str], Outcome]:
    """A NaN or Inf in a frame's vertices, a query's points, or a new object's vertices: InvalidInputError
    saying values must be finite, and the object answers exactly as before (same frame, same distances)."""

    def run(device: str) -> Outcome:
        from badf.server.adf import DistanceField, InvalidInputError

        vertices, faces = icosphere(2)
        bad = vertices.copy()
        bad[7, 1] = value
        distance_field = DistanceField(vertices, faces, depth=4, device=device)
        points = np.random.default_rng(0).uniform(-1.5, 1.5, size=(100, 3))
        before = distance_field.query(points, mode="adf", outputs=("distance", "normal"))
        calls = {
            "update": lambda: distance_field.update(bad),
            "points": lambda: distance_field.query(np.concatenate([points, bad[5:8]]), mode="exact"),
            "construction": lambda: DistanceField(bad, faces, depth=4, device=device),
        }
        try:
            calls[target]()
            error = "no error"
        except InvalidInputError as raised:
            error = str(raised)
        after = distance_field.query(points, mode="adf", outputs=("distance", "normal"))
        kept = (distance_field.frame == 0 and np.array_equal(before.distance, after.distance)
                and np.array_equal(before.normal, after.normal))
        passed = "must be finite" in error and kept
        return Outcome(passed, f"InvalidInputError: {error!r}; state kept: {kept}", {"error": error, "kept": kept})

    return run


# -- the table ------------------------------------------------------------------------------------------
_SOLID = True
_OPEN = False
_LARGE_BATCH = 10_000_000


def stability_cases(*, large_batch: int = _LARGE_BATCH) -> list[StabilityCase]:
    """Every case, in the order of the stability table."""
    g = "degenerate geometry"
    cases = [
        StabilityCase("zero-area and collinear triangles", g, MESH_EXPECTED, mesh_case(zero_area_and_collinear, solid=_SOLID)),
        StabilityCase("repeated vertices (triangle soup)", g, MESH_EXPECTED, mesh_case(triangle_soup, solid=_SOLID)),
        StabilityCase("slivers of aspect ratio 1e6", g, MESH_EXPECTED, mesh_case(sliver_tetrahedron, solid=_SOLID)),
        StabilityCase("a single triangle", g, MESH_EXPECTED, mesh_case(single_triangle, solid=_OPEN)),
        StabilityCase("flat (coplanar) open mesh", g, MESH_EXPECTED, mesh_case(flat_sheet, solid=_OPEN)),
        StabilityCase("thin plate 1e-4 of its size thick", g, MESH_EXPECTED, mesh_case(thin_plate, solid=_SOLID)),
        StabilityCase("inverted winding", g, MESH_EXPECTED, mesh_case(inverted_sphere, solid=_SOLID)),
        StabilityCase("duplicate faces of opposite orientation", g, MESH_EXPECTED,
                      mesh_case(sphere_with_opposite_duplicates, solid=_SOLID)),
        StabilityCase("non-manifold edges (two cubes sharing an edge)", g, MESH_EXPECTED,
                      mesh_case(boxes_sharing_an_edge, solid=_SOLID)),
        StabilityCase("open mesh: the bunny's holes", g, MESH_EXPECTED,
                      mesh_case(lambda: shared_mesh("stanford-bunny"), solid=_OPEN)),
        StabilityCase("open mesh: the horse", g, MESH_EXPECTED,
                      mesh_case(lambda: shared_mesh("sumner_horse_gallop"), solid=_OPEN)),
    ]
    g = "extreme scale"
    relative = "the same as at unit size, relative to size: " + MESH_EXPECTED
    cases += [
        StabilityCase("offset by 1e5 (float64 input)", g, relative, mesh_case(scaled_sphere(1.0, 1e5), solid=_SOLID)),
        StabilityCase("scaled by 1e-5", g, relative, mesh_case(scaled_sphere(1e-5, 0.0), solid=_SOLID)),
        StabilityCase("scaled by 1e5", g, relative, mesh_case(scaled_sphere(1e5, 0.0), solid=_SOLID)),
        StabilityCase("scaled by 1e-30", g, relative, mesh_case(scaled_sphere(1e-30, 0.0), solid=_SOLID)),
        StabilityCase("scaled by 1e12", g, relative, mesh_case(scaled_sphere(1e12, 0.0), solid=_SOLID)),
        StabilityCase("offset by 1e5 (float32 input)", g,
                      "exact within 1e-5 diag + the float32 rounding of the input coordinates (2*sqrt(3)*2^-24*|x|)",
                      float32_input_case(1e5)),
    ]
    g = "extreme queries"
    cases += [
        StabilityCase("points exactly on vertices, edges, faces", g,
                      "exact |d| <= 1e-5 diag, adf <= 1 finest cell, normals unit, finite", features_case()),
        StabilityCase("points 1e6 sizes away", g, "relative error <= 1e-6, positive, finite", far_points_case()),
        StabilityCase("an empty batch", g, "empty arrays of the right shapes, both modes", empty_batch_case),
        StabilityCase(f"a batch of {large_batch:,} points (adf)", g,
                      "device memory unchanged by the batch size, finite, a sample within the leaf bound",
                      large_batch_case(large_batch)),
    ]
    g = "stiff motion (coherence on)"
    motion = "|d| exact at corners and queries, equal to a field without coherence; signs of the winding oracle"
    cases += [
        StabilityCase("moved 10 times its size", g, motion, stiff_motion_case("translate", signs_defined=True)),
        StabilityCase("scaled by 100", g, motion, stiff_motion_case("scale", signs_defined=True)),
        StabilityCase("collapsed onto a plane", g, motion + " (nothing is inside)",
                      stiff_motion_case("collapse", signs_defined=True)),
        StabilityCase("every vertex jittered (0.05 diag)", g,
                      "|d| exact, equal to a field without coherence; the mesh self-intersects, so signs are reported only",
                      stiff_motion_case("jitter", signs_defined=False)),
    ]
    g = "NaN or Inf"
    kept = "InvalidInputError 'must be finite'; the object keeps its last good state"
    cases += [
        StabilityCase("NaN in a frame's vertices", g, kept, bad_values_case("update", float("nan"))),
        StabilityCase("Inf in a frame's vertices", g, kept, bad_values_case("update", float("inf"))),
        StabilityCase("NaN in query points", g, kept, bad_values_case("points", float("nan"))),
        StabilityCase("-Inf in query points", g, kept, bad_values_case("points", float("-inf"))),
        StabilityCase("NaN in a new object's vertices", g, kept, bad_values_case("construction", float("nan"))),
    ]
    return cases


# Cases the engine does not meet yet, by name, with the reason: the tests mark them xfail(strict) and the
# benchmark says so. The collapsed frame was one until the engine re-chose the sign per frame (2026-11-21).
KNOWN_ENGINE_BUGS: dict[str, str] = {}
