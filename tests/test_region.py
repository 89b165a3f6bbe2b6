"""A region of interest: the octree refined only where a box needs it, and ADF answers outside it exact."""

from __future__ import annotations

import numpy as np
import pytest

import meshes
import oracle
import tolerances as tol
from badf.server.adf import DistanceField, InvalidInputError

ALL_OUTPUTS = ("distance", "closest_point", "normal", "face")


def _lattice(points: np.ndarray, field: DistanceField) -> np.ndarray:
    """Points in finest-cell units of the field's domain (cell i spans [i, i + 1))."""
    info = field.info()
    centre, side = np.asarray(info["domain"]["centre"]), float(info["domain"]["side"])
    return (points - (centre - side / 2)) / (side / (1 << info["depth"]))


def _finest_cells(field: DistanceField) -> np.ndarray:
    levels, cells = field.octree_cells()
    return cells[levels == field.info()["depth"]]


def _codes(cells: np.ndarray) -> np.ndarray:
    cells = np.asarray(cells, dtype=np.int64)
    return (cells[:, 0] << 26) | (cells[:, 1] << 13) | cells[:, 2]


def _inside(points: np.ndarray, region: np.ndarray) -> np.ndarray:
    return np.all((points >= region[0]) & (points <= region[1]), axis=1)


def _part_of_the_box(vertices: np.ndarray, low: float, high: float) -> np.ndarray:
    """The slab of the mesh's bounding box between fractions `low` and `high` of it along x."""
    lo, hi = vertices.min(axis=0).astype(np.float64), vertices.max(axis=0).astype(np.float64)
    margin = 0.05 * (hi - lo)
    region = np.array([lo - margin, hi + margin])
    region[0, 0], region[1, 0] = lo[0] + low * (hi[0] - lo[0]), lo[0] + high * (hi[0] - lo[0])
    return region


def _assert_adf_is_exact_outside(field: DistanceField, points: np.ndarray, region: np.ndarray) -> None:
    outside = points[~_inside(points, region)]
    assert len(outside) > 0
    adf = field.query(outside, mode="adf", outputs=ALL_OUTPUTS)
    exact = field.query(outside, mode="exact", outputs=ALL_OUTPUTS)
    for name in ALL_OUTPUTS:
        np.testing.assert_array_equal(getattr(adf, name), getattr(exact, name), err_msg=name)


def _near_surface_points(vertices, faces, cell: float, rng, count: int = 1200) -> np.ndarray:
    surface = meshes.surface_samples(vertices, faces, 1, rng)
    surface = surface[rng.choice(len(surface), count)]
    direction = rng.normal(size=surface.shape)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return surface + direction * rng.random((len(surface), 1)) * cell


@pytest.mark.parametrize(("name", "refine"), [("spot", "surface"), ("rocker-arm", "surface"), ("spot", "centroid")])
def test_a_region_refines_only_what_it_needs_and_keeps_the_promises_inside_it(device, name, refine):
    vertices, faces = meshes.load(name)
    depth, halo = 6, (1 if refine == "surface" else 0)
    region = _part_of_the_box(vertices, 0.3, 0.6)
    whole = DistanceField(vertices, faces, depth=depth, refine=refine, halo=halo, device=device)
    field = DistanceField(vertices, faces, depth=depth, refine=refine, halo=halo, region=region, device=device)
    assert field.info()["region"] == region.tolist()
    cell = field.info()["domain"]["finest_cell"]
    assert cell == whole.info()["domain"]["finest_cell"]  # the domain still fits the mesh
    rng = np.random.default_rng(11)

    # every finest cell the whole field refines and the region's box meets is refined; none far from the box
    finest = _finest_cells(field)
    wanted = _finest_cells(whole)
    meets = np.all((wanted + 1 > _lattice(region[0], field)) & (wanted <= _lattice(region[1], field)), axis=1)
    assert np.all(np.isin(_codes(wanted[meets]), _codes(finest)))
    reach = 2 * halo + 1  # the surface cells within the halo of the box, and their halo
    lower, upper = np.floor(_lattice(region[0], field)) - reach, np.floor(_lattice(region[1], field)) + reach
    assert np.all((finest >= lower) & (finest <= upper))
    assert len(finest) < 0.75 * len(wanted)
    assert field.stats()["counts"]["unique_corners"] < whole.stats()["counts"]["unique_corners"]

    # every stored corner is exact, and so is the sign away from the surface
    positions, values, _faces = field.corner_samples()
    truth = oracle.nearest(positions, vertices, faces)
    diag = oracle.bbox_diagonal(vertices)
    assert np.all(np.abs(np.abs(values) - truth.distance) <= tol.EXACT_DISTANCE * diag)
    inside = np.abs(oracle.winding_number(positions, vertices, faces)) > 0.5
    clear = truth.distance > tol.SIGN_MARGIN * diag
    assert np.array_equal((values < 0)[clear], inside[clear])

    # within the box, near the surface, the interpolation is held to the same bound as without a region
    points = _near_surface_points(vertices, faces, cell, rng)
    within = points[_inside(points, region)]
    assert len(within) > 200
    error = np.abs(field.query(within).distance - oracle.signed_distance(within, vertices, faces))
    assert error.max() < tol.ADF_NEAR_SURFACE * cell
    # outside it every answer is exact mode's, all four outputs
    _assert_adf_is_exact_outside(field, points, region)


def test_points_just_outside_a_face_of_the_region_are_answered_exactly(device):
    """A point 1e-12 to 1e-8 outside a face of the box (in float64) rounded onto it in float32 and was
    interpolated: -0.016332 where exact mode says -0.016387 (thirteenth outside check). The box is now
    rounded inward past float32's rounding."""
    vertices, faces = meshes.load("sphere")
    region = np.array([[-2.0, -2.0, -2.0], [0.3, 2.0, 2.0]])
    field = DistanceField(vertices, faces, depth=5, region=region, device=device)
    rng = np.random.default_rng(4)
    points = rng.uniform(-0.8, 0.8, size=(40, 3))
    for step in (1e-12, 1e-9, 1e-8, 3e-8):
        points[:, 0] = 0.3 + step
        for dtype in (np.float64, np.float32):
            outside = points.astype(dtype)
            outside = outside[outside[:, 0].astype(np.float64) > 0.3]  # float32 may round onto the face
            _assert_adf_is_exact_outside(field, outside, region)


def test_a_small_region_holds_memory_for_its_own_cells(device):
    """The first frame's cell set was sized from the whole mesh's area, and buffers keep their size: a box
    4% of spot across held 28 MiB of scratch at depth 8 and 452 MiB at depth 10 for a few hundred cells
    (thirteenth outside check). It is sized from the area of the faces near the box."""
    vertices, faces = meshes.load("spot")
    lo, hi = vertices.min(axis=0).astype(np.float64), vertices.max(axis=0).astype(np.float64)
    centre, extent = (lo + hi) / 2, hi - lo
    region = np.array([centre - 0.02 * extent, centre + 0.02 * extent + [0, 0, 0.5 * extent[2]]])
    whole = DistanceField(vertices, faces, depth=7, device=device)
    small = DistanceField(vertices, faces, depth=7, region=region, device=device)
    small.update(vertices)
    held = {name: sum(field.stats()["memory_bytes"].values()) for name, field in (("whole", whole), ("small", small))}
    assert 0 < small.stats()["counts"]["surface_cells"] < whole.stats()["counts"]["surface_cells"] / 20
    assert held["small"] < held["whole"] / 5, held  # 2.6 against 20.5 MB on the CPU; 9.9 before


def test_a_region_over_the_whole_domain_is_the_field_without_one(device):
    vertices, faces = meshes.load("spot")
    whole = DistanceField(vertices, faces, depth=5, device=device)
    info = whole.info()["domain"]
    centre, half = np.asarray(info["centre"]), info["side"]
    field = DistanceField(vertices, faces, depth=5, region=[centre - half, centre + half], device=device)
    np.testing.assert_array_equal(_codes(_finest_cells(field)), _codes(_finest_cells(whole)))
    points = _near_surface_points(vertices, faces, info["finest_cell"], np.random.default_rng(3), count=500)
    for name in ALL_OUTPUTS:
        np.testing.assert_array_equal(getattr(field.query(points, outputs=ALL_OUTPUTS), name),
                                      getattr(whole.query(points, outputs=ALL_OUTPUTS), name), err_msg=name)


@pytest.mark.parametrize("where", ["far away", "in the empty middle", "a point"])
def test_a_region_the_surface_stays_out_of_still_answers(device, where):
    vertices, faces = meshes.load("torus")
    lo, hi = vertices.min(axis=0).astype(np.float64), vertices.max(axis=0).astype(np.float64)
    middle = (lo + hi) / 2
    region = {
        "far away": np.array([hi + 10.0, hi + 11.0]),
        "in the empty middle": np.array([middle - 0.02 * (hi - lo), middle + 0.02 * (hi - lo)]),
        "a point": np.array([middle, middle]),
    }[where]
    field = DistanceField(vertices, faces, depth=6, region=region, device=device)
    counts = field.stats()["counts"]
    assert 1 <= counts["surface_cells"] <= 64
    rng = np.random.default_rng(4)
    points = np.concatenate([rng.uniform(lo - 0.1, hi + 0.1, (800, 3)), middle + rng.normal(size=(50, 3)) * 1e-3])
    truth = oracle.signed_distance(points, vertices, faces)
    result = field.query(points)
    diag = oracle.bbox_diagonal(vertices)
    inside = _inside(points, region)
    assert np.all(np.abs(result.distance - truth)[~inside] <= tol.EXACT_DISTANCE * diag)
    if where == "in the empty middle":  # the box is far from the surface: a coarse leaf, within its diagonal
        assert inside.sum() > 10
        assert np.all(np.abs(result.distance - truth)[inside] <= 0.05 * diag)
    _assert_adf_is_exact_outside(field, points, region)


@pytest.mark.parametrize("coherence", [True, False])
def test_a_region_stays_put_in_the_world_while_the_mesh_moves(device, coherence):
    vertices, faces = meshes.load("spot")
    region = _part_of_the_box(vertices, 0.2, 0.5)
    field = DistanceField(vertices, faces, depth=6, region=region, coherence=coherence, device=device)
    span = np.ptp(vertices, axis=0).astype(np.float64)
    rng = np.random.default_rng(8)
    for step in range(1, 4):
        # sliding along x by a third of the mesh per frame: the domain moves, the region does not
        moved = (vertices + np.array([step * span[0] / 3.0, 0.0, 0.0])).astype(np.float32)
        field.update(moved)
        cell = field.info()["domain"]["finest_cell"]
        points = _near_surface_points(moved, faces, cell, rng, count=800)
        within = points[_inside(points, region)]
        if len(within):
            error = np.abs(field.query(within).distance - oracle.signed_distance(within, moved, faces))
            assert error.max() < tol.ADF_NEAR_SURFACE * cell
        _assert_adf_is_exact_outside(field, points, region)
    assert field.stats()["domain_moves"] >= 1
    assert field.info()["region"] == region.tolist()


@pytest.mark.parametrize(
    ("region", "message"),
    [
        ([0.0, 0.0, 0.0], "shape"),
        ([[0.0, 0.0], [1.0, 1.0]], "shape"),
        ([[0.0, 0.0, np.nan], [1.0, 1.0, 1.0]], "finite"),
        ([[0.0, 0.0, 0.0], [1.0, np.inf, 1.0]], "finite"),
        ([[0.0, 2.0, 0.0], [1.0, 1.0, 1.0]], "on y it runs from 2 to 1"),
        ("everywhere", "region must be None or a box"),
        ([["a", "b", "c"], ["d", "e", "f"]], "numbers"),
        (True, "region must be None or a box"),
        # a long double past float64's range was told as NaN or Inf, with numpy's overflow warning
        pytest.param(np.array([[0, 0, 0], [np.longdouble("1e4000"), 1, 1]], np.longdouble), r"within \+-1e\+18",
                     marks=pytest.mark.skipif(np.finfo(np.longdouble).max < 1e300, reason="long double is float64 here")),
    ],
)
def test_a_bad_region_is_refused_with_what_came(region, message):
    vertices, faces = meshes.load("sphere")
    with pytest.raises(InvalidInputError, match=message):
        DistanceField(vertices, faces, depth=3, region=region, device="cpu")
