"""Bad input gets a clear InvalidInputError naming what was expected and what came, and changes nothing."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import meshes
from badf.server.adf import DistanceField, InvalidInputError

VERTICES, FACES = meshes.single_triangle()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"vertices": np.zeros((3, 2))}, r"vertices must have shape \(count, 3\), got \(3, 2\)"),
        ({"vertices": np.array([[0, 0, 0], [1, 0, np.nan], [0, 1, 0]])}, "must be finite, got 1 NaN or Inf"),
        ({"vertices": np.array([[0, 0, 0], [1, 0, np.inf], [0, 1, 0]])}, "must be finite"),
        ({"vertices": np.array([["a", "b", "c"]] * 3)}, "must hold numbers"),
        ({"vertices": np.zeros((0, 3))}, "vertices must not be empty"),
        ({"vertices": np.zeros((3, 3))}, "zero extent"),
        # answers are float32 in world units: at size 1e-45 they were off by 0.2 of the diagonal, at 1e-60
        # every one was 0.0 (thirteenth outside check)
        ({"vertices": VERTICES * 1e-45}, r"extent is 1.4e-45; meshes smaller than 1e-40 are refused"),
        # the faces use one vertex of a spread mesh: the message names the faces' vertices, not all of them
        ({"vertices": np.eye(3), "faces": np.zeros((1, 3), np.int32)}, "the vertices the faces use must not"),
        ({"vertices": np.array([[0, 0, 0], [1e19, 0, 0], [0, 1, 0]])}, r"within \+-1e\+18"),
        # a long double past float64's range was told as NaN or Inf, with numpy's overflow warning
        pytest.param({"vertices": np.array([[0, 0, 0], [np.longdouble("1e400"), 0, 0], [0, 1, 0]], np.longdouble)},
                     r"within \+-1e\+18, got a coordinate of 1.e\+400",
                     marks=pytest.mark.skipif(np.finfo(np.longdouble).max < 1e300, reason="long double is float64 here")),
        # numpy keeps Python ints past 64 bits as objects, which were told only as "dtype object"
        ({"vertices": [[0, 0, 0], [2**64, 0, 0], [0, 1, 0]]}, "a coordinate past 64-bit integers"),
        ({"vertices": [[0, 0, 0], [0.5, -(10**5000), 0], [0, 1, 0]]}, "past 64-bit integers .one of 16610 bits"),
        ({"faces": [[0, 1, 2**64]]}, "faces: an index past 64-bit integers"),
        ({"faces": np.array([[0, 1, 3]])}, r"faces must index vertices 0..2, got indices in \[0, 3\]"),
        ({"faces": np.array([[0, 1, -1]])}, "first at row 0"),
        ({"faces": np.zeros((0, 3), int)}, "faces must not be empty"),
        ({"faces": np.array([[0.0, 1.0, 2.0]])}, "integer vertex indices, got dtype float64"),
        ({"faces": np.array([[True, False, True]])}, "faces must hold integers, got dtype bool"),
        ({"faces": np.array([0, 1, 2])}, r"faces must have shape \(count, 3\)"),
        ({"depth": 0}, "depth must be in 1..10, got 0"),
        ({"depth": 11}, "depth must be in 1..10"),
        ({"depth": 2.5}, "depth must be an integer"),
        ({"sign": "inside"}, "sign must be one of auto, pseudonormal, winding, none"),
        ({"band": -1.0}, "band must be a positive finite number"),
        ({"band": float("nan")}, "band must be a positive finite number"),
        ({"band": np.True_}, "band must be a positive number or None, got np.True_"),  # was a band of 1.0
        ({"band": 10**400}, r"band must be a positive finite number or None, got 1000+\.\.\.0+$"),  # not 401 digits
        ({"refine": "everywhere"}, "refine must be one of surface, centroid"),
        ({"halo": 3}, r"halo must be an integer in 0..2"),
        ({"coherence": "yes"}, "coherence must be True or False"),
        ({"device": "tpu:0"}, "device 'tpu:0' is not available"),
    ],
)
def test_construction_rejects_bad_input(kwargs, message):
    args = {"vertices": VERTICES, "faces": FACES, "device": "cpu"} | kwargs
    with pytest.raises(InvalidInputError, match=message):
        DistanceField(args.pop("vertices"), args.pop("faces"), **args)


@pytest.mark.parametrize(("kwargs", "start"), [
    ({"depth": 10**400}, "depth must be in 1..10, got 1000"),
    ({"halo": 10**400}, "halo must be an integer in 0..2, got 1000"),
    ({"sign": "x" * 5000}, "sign must be one of auto, pseudonormal, winding, none; got 'xxx"),
    ({"refine": "y" * 3000}, "refine must be one of surface, centroid; got 'yyy"),
    ({"coherence": 10**400}, "coherence must be True or False, got 1000"),
])
def test_a_huge_bad_value_is_named_in_a_line(kwargs, start):
    """Every check that names the value it refuses cuts a long one in the middle (the band's 401 digits were
    written out whole, and so were a depth's, a 5,000-character sign's and the others', 2026-12-02)."""
    with pytest.raises(InvalidInputError) as refused:
        DistanceField(VERTICES, FACES, device="cpu", **kwargs)
    message = str(refused.value)
    assert message.startswith(start) and "..." in message and len(message) < 200, message


def test_bad_frames_and_queries_leave_the_field_as_it_was(device):
    vertices, faces = meshes.sphere()
    field = DistanceField(vertices, faces, depth=4, device=device)
    points = np.random.default_rng(0).uniform(-1.5, 1.5, size=(50, 3)).astype(np.float32)
    before = field.query(points, mode="adf", outputs=("distance", "normal"))
    bad_frames = [
        (vertices[:-1], r"must have 642 rows \(the registered vertex count\), got 641"),
        (np.where(np.arange(len(vertices))[:, None] == 5, np.nan, vertices), "must be finite"),
        (vertices.astype(str), "must hold numbers"),
        (vertices.reshape(-1), r"shape \(count, 3\)"),
        (vertices * 1e-42, "meshes smaller than 1e-40 are refused"),
    ]
    for frame, message in bad_frames:
        with pytest.raises(InvalidInputError, match=message):
            field.update(frame)
    bad_queries = [
        ({"points": points[:, :2]}, r"points must have shape \(count, 3\), got \(50, 2\)"),
        ({"points": np.full((2, 3), np.inf)}, "points must be finite"),
        ({"points": [[0, 0, -(2**70)]]}, "points: a coordinate past 64-bit integers"),
        ({"mode": "fast"}, "mode must be one of adf, exact"),
        ({"outputs": ("distance", "curvature")}, r"unknown outputs \['curvature'\]"),
        ({"outputs": ()}, "outputs must name at least one"),
        ({"outputs": b"distance"}, "outputs must be a sequence of names .*, got b'distance'"),  # not its bytes' values
    ]
    for kwargs, message in bad_queries:
        args = {"points": points} | kwargs
        with pytest.raises(InvalidInputError, match=message):
            field.query(args.pop("points"), **args)
    assert field.frame == 0
    after = field.query(points, mode="adf", outputs=("distance", "normal"))
    np.testing.assert_array_equal(before.distance, after.distance)
    np.testing.assert_array_equal(before.normal, after.normal)


def test_bad_float32_frames_leave_the_field_as_it_was(device):
    """A bad float32 frame (the kind recentred on the device) leaves the field as it was, and the next good one
    gets the field that a float64 copy of it gets."""
    vertices, faces = meshes.sphere()
    vertices = vertices.astype(np.float32)
    field = DistanceField(vertices, faces, depth=4, device=device)
    twin = DistanceField(vertices, faces, depth=4, device=device)
    points = np.random.default_rng(1).uniform(-1.5, 1.5, size=(50, 3)).astype(np.float32)
    before = field.query(points, outputs=("distance", "normal"))
    row_5 = np.arange(len(vertices))[:, None] == 5
    for value, message in [(np.nan, "must be finite, got 3 NaN or Inf values in 1 rows"), (-np.inf, "must be finite"),
                           (1e19, r"must lie within \+-1e\+18")]:
        with pytest.raises(InvalidInputError, match=message):
            field.update(np.where(row_5, np.float32(value), vertices))
    assert field.frame == 0
    after = field.query(points, outputs=("distance", "normal"))
    np.testing.assert_array_equal(before.distance, after.distance)
    np.testing.assert_array_equal(before.normal, after.normal)
    # the twin takes the frame in float64, which is recentred on the host
    grown = (vertices * np.float32(1.01)).astype(np.float32)
    assert field.update(grown) == twin.update(grown.astype(np.float64)) == 1
    ours, theirs = field.query(points).distance, twin.query(points).distance
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-5)  # the sphere's radius is 1
    assert np.abs(ours - before.distance).max() > 5e-3  # the field is the new frame's


def test_frames_of_either_dtype_answer_alike_through_one_graph(device):
    """A float32 frame is moved to local coordinates on the device, as the first work of its frame (inside the
    graph a planned frame replays on CUDA); a float64 one on the host, which the device then leaves as it is (centre
    0, scale 1). The same float32 values give the same field bit for bit whichever dtype brought them, also when one
    graph replays across the switches."""
    vertices, faces = meshes.load("torus")
    base = (vertices + [3.3, -1.7, 2.1]).astype(np.float32)  # off the origin, so the move does something
    mixed = DistanceField(base, faces, depth=5, device=device)
    double = DistanceField(base.astype(np.float64), faces, depth=5, device=device)
    assert mixed._domain.recentres_float32  # the device's move, not the host's float64 one, takes float32 frames
    points = np.random.default_rng(2).uniform(base.min(axis=0) - 0.2, base.max(axis=0) + 0.2, (400, 3))
    extent = float(np.ptp(base, axis=0).max())
    for k in range(1, 7):
        frame = (base + np.float32(0.01 * extent) * np.sin(k + base[:, [1, 2, 0]])).astype(np.float32)
        mixed.update(frame if k % 2 else frame.astype(np.float64))
        double.update(frame.astype(np.float64))
        for mode in ("adf", "exact"):
            ours = mixed.query(points, mode=mode, outputs=("distance", "face"))
            theirs = double.query(points, mode=mode, outputs=("distance", "face"))
            np.testing.assert_array_equal(ours.distance, theirs.distance, err_msg=f"frame {k}, {mode}")
            np.testing.assert_array_equal(ours.face, theirs.face, err_msg=f"frame {k}, {mode}")
    stats = mixed.stats()
    assert stats["domain_moves"] == 0 and stats["replans"] == 0
    if device.startswith("cuda"):
        assert stats["graph_captures"] == 1  # one graph, replayed for float32 and float64 frames alike


def test_a_non_finite_vertex_that_no_face_uses_is_refused(device):
    """The bounds that place the domain leave out vertices no face uses, but every vertex is checked."""
    vertices, faces = meshes.sphere()
    vertices = np.vstack([vertices, [[5.0, 5.0, 5.0]]]).astype(np.float32)
    field = DistanceField(vertices, faces, depth=3, device=device)
    for dtype in (np.float32, np.float64):
        frame = vertices.astype(dtype)
        frame[-1] = np.nan
        with pytest.raises(InvalidInputError, match="must be finite, got 3 NaN or Inf values in 1 rows"):
            field.update(frame)
    assert field.frame == 0 and field.update(vertices) == 1


def test_empty_query_and_unrequested_outputs(device):
    vertices, faces = meshes.sphere()
    field = DistanceField(vertices, faces, depth=3, device=device)
    empty = field.query(np.zeros((0, 3)), outputs=("distance", "face"))
    assert empty.distance.shape == (0,) and empty.face.shape == (0,)
    only_normal = field.query(np.ones((4, 3)), outputs=("normal",))
    assert only_normal.distance is None and only_normal.normal.shape == (4, 3)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"axis": "w"}, "axis must be 'x', 'y' or 'z'"),
        ({"position": float("nan")}, "position must be finite"),
        ({"position": 10**400}, "position must be finite"),
        ({"position": 1e19}, r"position must lie within \+-1e\+18, got 1e\+19"),
        ({"resolution": 0}, "resolution must be 1..2048"),
        ({"resolution": (10, 5000)}, "resolution must be 1..2048"),
        ({"resolution": "16"}, r"resolution must be an int or \(cols, rows\) of ints"),
        ({"resolution": (2.7, 3)}, r"resolution must be an int or \(cols, rows\) of ints"),
        ({"resolution": (True, 4)}, r"resolution must be an int or \(cols, rows\) of ints"),
        ({"resolution": True}, r"resolution must be an int or \(cols, rows\) of ints"),
        ({"resolution": (4, 4, 4)}, r"resolution must be an int or \(cols, rows\) of ints"),
        ({"position": "0.5"}, "position must be a number"),
        ({"position": True}, "position must be a number"),
        ({"max_level": 9}, r"max_level must be an integer in 0..3"),
    ],
)
def test_slice_rejects_bad_requests(kwargs, message):
    vertices, faces = meshes.sphere()
    field = DistanceField(vertices, faces, depth=3, device="cpu")
    args = {"axis": "x", "position": 0.0} | kwargs
    with pytest.raises(InvalidInputError, match=message):
        field.slice(args.pop("axis"), args.pop("position"), **args)


def test_the_same_values_as_float32_or_float64_make_the_same_field(device):
    """The domain is fitted in float64 whatever the input's dtype: float32 rounding of the bounding box's
    centre and extent once gave a float32 mesh far from the origin another domain than its float64 copy."""
    vertices, faces = meshes.load("torus")
    single = (vertices + [12345.77, 12345.77, 12346.8]).astype(np.float32)
    double = single.astype(np.float64)
    a = DistanceField(single, faces, depth=5, device=device)
    b = DistanceField(double, faces, depth=5, device=device)
    assert a.info()["domain"] == b.info()["domain"]
    points = double[::7] + 0.03 * np.ptp(double, axis=0)
    diag = float(np.linalg.norm(np.ptp(double, axis=0)))
    for mode in ("adf", "exact"):
        np.testing.assert_allclose(a.query(points, mode=mode).distance, b.query(points, mode=mode).distance,
                                   rtol=0, atol=1e-6 * diag)


def test_a_mesh_that_shrinks_to_a_third_gets_a_field_as_fine_as_a_fresh_one(device):
    """A mesh updated to a third of its size kept its domain until it shrank below 1/8 of it, so its cells
    were 3 times coarser than a fresh field's of the same frame, with no sign of it but the domain's side
    (eleventh outside check). It now refits below about half its size: the field equals a fresh one."""
    vertices, faces = meshes.load("spot")
    field = DistanceField(vertices, faces, depth=5, device=device)
    small = (vertices * 0.33).astype(np.float32)
    field.update(small)
    fresh = DistanceField(small, faces, depth=5, device=device)
    assert field.info()["domain"]["side"] == pytest.approx(fresh.info()["domain"]["side"], rel=1e-6)
    points = np.random.default_rng(5).uniform(-0.4, 0.4, size=(2000, 3)).astype(np.float32)
    np.testing.assert_array_equal(field.query(points).distance, fresh.query(points).distance)


@pytest.mark.parametrize(("size", "offset"), [(1.0, 1.0001234e9), (1e-3, 1.2345678e6)])
def test_a_small_mesh_far_from_the_origin_keeps_its_domain(device, size, offset):
    """A float64 mesh small against float32's spacing where it lies: snapping the domain's centre to float32
    once widened the domain by the rounding (18.4 instead of 2.4 for a unit sphere at 1e9), coarsening the
    octree, and every identical frame moved the domain again."""
    vertices, faces = meshes.load("sphere")
    far = vertices.astype(np.float64) * size + [offset, -offset / 3, 0.0]
    near = DistanceField(vertices.astype(np.float64) * size, faces, depth=5, device=device)
    field = DistanceField(far, faces, depth=5, device=device)
    assert field.info()["domain"]["side"] == near.info()["domain"]["side"]
    for _ in range(3):
        field.update(far)
    assert field.stats()["domain_moves"] == 0
    rng = np.random.default_rng(43)
    offsets = rng.uniform(-1.2, 1.2, size=(500, 3)) * size
    for mode in ("adf", "exact"):
        np.testing.assert_allclose(field.query(offsets + [offset, -offset / 3, 0.0], mode=mode).distance,
                                   near.query(offsets, mode=mode).distance, rtol=0, atol=1e-5 * size)


@pytest.mark.parametrize("distance", [10.0, 1e3, 1e6])
def test_vertices_no_face_uses_do_not_set_the_domain(device, distance):
    """A vertex left over from editing, or parked far away, once widened the domain: 220 corners instead of
    285K for a unit sphere with one unused vertex at 1e3, and ADF errors of 5.9 there."""
    vertices, faces = meshes.load("sphere")
    parked = np.concatenate([vertices, [[distance] * 3]])
    plain = DistanceField(vertices, faces, depth=5, device=device)
    field = DistanceField(parked, faces, depth=5, device=device)
    assert field.info()["domain"] == plain.info()["domain"]
    assert field.info()["sign"] == plain.info()["sign"]
    grown = vertices * np.float32(1.1)
    field.update(np.concatenate([grown, [[-distance] * 3]]))  # the unused vertex jumps; the others grow a little
    plain.update(grown)
    assert field.info()["domain"] == plain.info()["domain"]
    points = np.random.default_rng(47).uniform(-1.5, 1.5, size=(500, 3))
    for mode in ("adf", "exact"):
        np.testing.assert_array_equal(field.query(points, mode=mode).distance, plain.query(points, mode=mode).distance)


def test_an_update_that_fails_on_the_way_leaves_no_wrong_answers(device, monkeypatch):
    """Valid input that fails inside the pipeline (here an allocation the device refuses) may leave the buffers
    half this frame and half the last. Queries then answered wrongly (1.0 off on a unit sphere); now they raise
    FieldUnavailableError until an update goes through, rebuilt in full."""
    from badf.server.adf import DeviceMemoryError, FieldUnavailableError
    from badf.server.adf._buffers import DeviceBuffers

    vertices, faces = meshes.load("sphere")
    field = DistanceField(vertices, faces, depth=5, device=device)
    wrinkled = vertices * (1.0 + 0.3 * np.sin(9.0 * vertices[:, :1]) * np.cos(7.0 * vertices[:, 1:2]))

    def refused(self, name, count, dtype, *, zeroed):
        raise DeviceMemoryError(f"the device could not allocate {name} (simulated)")

    with monkeypatch.context() as patch:
        patch.setattr(DeviceBuffers, "_allocate", refused)
        with pytest.raises(MemoryError, match="simulated"):
            field.update(wrinkled * 3.0)  # a larger frame: the domain moves and buffers grow
    points = np.random.default_rng(47).uniform(-1.5, 1.5, size=(300, 3))
    for ask in (lambda: field.query(points), lambda: field.query(points, mode="exact"), lambda: field.slice("x", 0.0)):
        with pytest.raises(FieldUnavailableError, match="the next update failed"):
            ask()
    assert field.frame == 0 and "simulated" in field.info()["failed_update"]
    assert field.update(wrinkled) == 1 and field.info()["failed_update"] is None
    fresh = DistanceField(wrinkled, faces, depth=5, device=device)
    for mode in ("adf", "exact"):
        np.testing.assert_allclose(field.query(points, mode=mode).distance, fresh.query(points, mode=mode).distance,
                                   rtol=0, atol=1e-6)


def test_info_says_which_band_is_in_force_after_the_domain_grew(device):
    """A band near the smallest one is widened with a domain that grows (to 2^-40 of its side, what float32
    resolves); info() reported only the band asked for, while far points were clamped at the wider one."""
    vertices, faces = meshes.sphere()
    side = DistanceField(vertices, faces, depth=3, device=device).info()["domain"]["side"]
    band = 4 * 2.0**-40 * side
    field = DistanceField(vertices, faces, depth=3, band=band, device=device)
    assert field.info()["band_in_force"] == pytest.approx(band)
    field.update(vertices * 1e3)
    in_force = field.info()["band_in_force"]
    assert field.info()["band"] == band and in_force > 100 * band
    for mode in ("exact", "adf"):  # a point beyond 2^40 sides too, which is moved in before the search
        far = field.query(np.array([[5e3, 0.0, 0.0], [1e17, 0.0, 0.0]]), mode=mode).distance
        np.testing.assert_allclose(far, in_force, rtol=1e-6)


@pytest.mark.parametrize(("scale", "band"), [(1e-6, 1e35), (1.0, 1e300)])
def test_a_band_wider_than_any_distance_changes_nothing_and_info_stays_json(device, scale, band):
    """A band whose local value passed float32's range (1e35 on a mesh of 1e-6) was reported as an infinite
    band_in_force, which is not JSON (the worker could not send the object's info)."""
    import json

    vertices, faces = meshes.sphere()
    vertices = vertices * scale
    banded = DistanceField(vertices, faces, depth=4, band=band, device=device)
    plain = DistanceField(vertices, faces, depth=4, device=device)
    assert banded.info()["band_in_force"] == band
    json.dumps(banded.info(), allow_nan=False)
    json.dumps(banded.stats(), allow_nan=False)
    points = np.random.default_rng(3).uniform(-2.0, 2.0, (500, 3)) * scale
    points = np.vstack([points, [[1e15 * scale, 0.0, 0.0], [3e17, 0.0, 0.0]]])
    for mode in ("adf", "exact"):
        got, want = banded.query(points, mode=mode).distance, plain.query(points, mode=mode).distance
        assert np.all(np.isfinite(got))
        np.testing.assert_array_equal(got, want)


def test_a_band_below_the_floor_is_refused_as_engine_md_says(device):
    """docs/engine.md gave `band` as "None or > 0", while a band below 2^-40 of the domain's side raises
    InvalidInputError at registration (eleventh outside check): the doc now says what the code does."""
    vertices, faces = meshes.sphere()
    with pytest.raises(InvalidInputError, match="band must be at least .* of the domain's side"):
        DistanceField(vertices, faces, depth=3, band=1e-20, device=device)
    row = next(line for line in (meshes.ROOT / "docs" / "engine.md").read_text().splitlines()
               if line.startswith("| `band` |"))
    assert "at least 2^-40 of the domain's side" in row.split("|")[2]
    assert "a smaller band raises `InvalidInputError`" in row


def test_a_far_unused_vertex_beside_a_tiny_mesh_warns_of_nothing(device):
    """A vertex no face uses, at 1e18 beside a mesh of size 1e-24, passed float32's range in local coordinates:
    numpy's overflow warning reached the caller, though nothing reads that vertex (thirteenth outside check)."""
    vertices, faces = meshes.load("sphere")
    for dtype in (np.float64, np.float32):
        parked = np.vstack([vertices * 1e-24, [[1e18, 1e18, 1e18]]]).astype(dtype)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            field = DistanceField(parked, faces, depth=3, device=device)
            field.update(parked)
            distance = field.query(vertices[:4].astype(np.float64) * 1.5e-24, mode="exact").distance
        np.testing.assert_allclose(distance, 0.5e-24, rtol=1e-5)
