"""Mesh files named on the command line: .npz meshes and sequences, and whatever trimesh reads."""

from __future__ import annotations

import re

import numpy as np
import pytest
import trimesh

from badf.bench._common import find_mesh
from badf.server._mesh_files import MeshFileError, read_frames, read_mesh
from badf.server.adf._sign import rim_fans


@pytest.fixture
def box() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(1.0, 2.0, 3.0))


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".off", ".stl"])
def test_any_file_trimesh_reads_gives_the_same_triangles(box, tmp_path, suffix: str) -> None:
    path = tmp_path / f"box{suffix}"
    box.export(path)
    vertices, faces = read_mesh(path)
    assert vertices.dtype == np.float64 and faces.dtype == np.int32  # trimesh reads float64, and it is kept
    assert faces.shape == box.faces.shape
    # .stl stores each triangle's corners on their own: compare the triangles, not the indices
    np.testing.assert_allclose(np.sort(vertices[faces].reshape(-1, 3), axis=0),
                               np.sort(box.vertices[box.faces].reshape(-1, 3), axis=0), atol=1e-6)


@pytest.mark.parametrize("encoding", ["binary", "ascii"])
def test_an_stl_surface_shares_its_corners_so_its_rim_is_its_holes(tmp_path, encoding: str) -> None:
    """STL gives each triangle corners of its own. Read as they stand, an open surface's rim would be every
    triangle's edges (past RIM_LIMIT: no correction of its winding numbers near 1/2); corners at one position are
    one vertex, in the order they first come, so the rim is the holes' edges, as for the same surface from an OBJ."""
    sphere = trimesh.creation.icosphere(3)
    faces = sphere.faces[sphere.triangles_center[:, 2] < 0.6]  # a cap cut off: one hole
    used = np.unique(faces)
    soup = trimesh.Trimesh(sphere.vertices[faces].reshape(-1, 3), np.arange(faces.size).reshape(-1, 3), process=False)
    path = tmp_path / "cut.stl"
    path.write_bytes(trimesh.exchange.stl.export_stl(soup) if encoding == "binary"
                     else trimesh.exchange.stl.export_stl_ascii(soup).encode())
    vertices, read = read_mesh(path)
    assert len(vertices) == len(used) and read.shape == faces.shape
    np.testing.assert_allclose(vertices[read], sphere.vertices[faces], atol=1e-6)  # the same triangles, in order
    first = np.unique(read.reshape(-1), return_index=True)[1]
    assert np.all(np.diff(first) > 0)  # vertices numbered in the order their first corner comes
    fans = rim_fans(read)
    assert fans is not None and len(fans) == len(rim_fans(np.searchsorted(used, faces)))


def test_an_npz_mesh_and_an_npz_sequence(box, tmp_path) -> None:
    np.savez(tmp_path / "one.npz", vertices=box.vertices, faces=box.faces.astype(np.int64))
    frames = np.stack([box.vertices + k for k in range(4)])
    np.savez(tmp_path / "four.npz", vertices=frames, faces=box.faces)
    vertices, faces = read_mesh(tmp_path / "one.npz")
    np.testing.assert_array_equal(faces, box.faces)
    np.testing.assert_allclose(vertices, box.vertices)
    read, _ = read_frames(tmp_path / "four.npz")
    assert read.shape == (4, len(box.vertices), 3)
    np.testing.assert_allclose(read[3], box.vertices + 3)
    np.testing.assert_allclose(read_mesh(tmp_path / "four.npz")[0], box.vertices)  # a sequence's first frame


def test_float64_files_keep_their_precision_and_others_become_float32(box, tmp_path) -> None:
    """A float64 mesh far from the origin would lose its shape in float32 (a unit box 1e7 out: its float32
    steps are 1.0), so float64 stays float64; float32 and integer coordinates come back float32."""
    far = box.vertices.astype(np.float64) * 0.25 + 1e7
    np.savez(tmp_path / "far64.npz", vertices=far, faces=box.faces)
    np.savez(tmp_path / "near32.npz", vertices=box.vertices.astype(np.float32), faces=box.faces)
    np.savez(tmp_path / "integers.npz", vertices=np.rint(box.vertices * 2).astype(np.int64), faces=box.faces)
    vertices, _ = read_mesh(tmp_path / "far64.npz")
    assert vertices.dtype == np.float64
    np.testing.assert_array_equal(vertices, far)
    assert read_mesh(tmp_path / "near32.npz")[0].dtype == np.float32
    assert read_frames(tmp_path / "integers.npz")[0].dtype == np.float32


def test_unreadable_files_are_named_with_what_is_wrong(box, tmp_path) -> None:
    (tmp_path / "text.npz").write_text("not a zip archive")
    (tmp_path / "empty.obj").write_text("# no faces\nv 0 0 0\n")
    np.savez(tmp_path / "no-faces.npz", vertices=box.vertices)
    np.savez(tmp_path / "float-faces.npz", vertices=box.vertices, faces=box.faces.astype(np.float64))
    np.savez(tmp_path / "past-the-end.npz", vertices=box.vertices[:4], faces=box.faces)
    np.savez(tmp_path / "flat.npz", vertices=box.vertices[:, :2], faces=box.faces)
    np.savez(tmp_path / "pickled.npz", vertices=np.array([object()], dtype=object), faces=box.faces)
    with_nan = box.vertices.copy()
    with_nan[5, 1] = np.nan
    np.savez(tmp_path / "nan.npz", vertices=with_nan, faces=box.faces)
    with np.errstate(over="ignore"):
        frames = np.stack([box.vertices, box.vertices * 1e39]).astype(np.float32)  # inf in the second frame
    np.savez(tmp_path / "huge.npz", vertices=frames, faces=box.faces)
    np.savez(tmp_path / "tiny.npz", vertices=box.vertices * 1e-41, faces=box.faces)  # below the engine's 1e-40
    late = np.stack([box.vertices, box.vertices * 0.0, box.vertices * 1e-42])  # a point is taken, then too small
    np.savez(tmp_path / "tiny-later.npz", vertices=late, faces=box.faces)
    np.savez(tmp_path / "far.npz", vertices=box.vertices + 1e19, faces=box.faces)  # past the engine's 1e18
    np.savez(tmp_path / "point.npz", vertices=np.zeros((3, 3)), faces=[[0, 1, 2]])
    cases = {
        tmp_path / "missing.obj": "no such file",
        tmp_path: "not a file",
        tmp_path / "text.npz": "not an .npz archive",
        tmp_path / "empty.obj": "holds no triangles",
        tmp_path / "no-faces.npz": "no faces array",
        tmp_path / "float-faces.npz": "faces of dtype float64, expected integers",
        tmp_path / "past-the-end.npz": "face indices span 0..7, but there are 4 vertices",
        tmp_path / "flat.npz": "expected (N, 3) or frames (T, N, 3)",
        tmp_path / "pickled.npz": "not a readable .npz",
        tmp_path / "nan.npz": "vertex 5 is [",
        tmp_path / "huge.npz": "vertex 0 of frame 1 is [",
        tmp_path / "far.npz": "a coordinate of 1e+19; the engine takes coordinates within +-1e+18",
        tmp_path / "point.npz": "the vertices its faces use all coincide",
        tmp_path / "tiny.npz": "the mesh's extent is 3e-41; the engine refuses meshes smaller than 1e-40",
        tmp_path / "tiny-later.npz": "the mesh's extent in frame 2 is 3e-42; the engine refuses",
    }
    for path, message in cases.items():
        with pytest.raises(MeshFileError, match=re.escape(message)) as raised:
            read_frames(path)
        assert str(path) in str(raised.value)


def test_benchmarks_take_a_path_where_they_take_a_mesh_name(tmp_path) -> None:
    assert find_mesh(str(tmp_path / "part.obj")) == tmp_path / "part.obj"
    assert find_mesh("spot").name == "spot.npz"  # bundled with the tests
    with pytest.raises(FileNotFoundError, match="no-such-mesh.npz is in none of"):
        find_mesh("no-such-mesh")


def test_relative_obj_indices_name_the_vertices_before_the_face(tmp_path) -> None:
    # trimesh reads them against the file's last vertex: this file loaded as two copies of its second triangle
    # (thirty-first outside check)
    path = tmp_path / "relative.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf -3/-1 -2/-1 -1/-1\nv 0 0 5\nv 1 0 5\nv 0 1 5\nf -3 -2 -1\n"
                    "f 1 -2 -1\n")
    vertices, faces = read_mesh(path)
    assert vertices[faces].tolist() == [[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 0, 5], [1, 0, 5], [0, 1, 5]],
                                        [[0, 0, 0], [1, 0, 5], [0, 1, 5]]]


@pytest.mark.parametrize(("face", "message"), [
    ("f 1 2 0", "line 5: face index 0 (OBJ indices count from 1)"),
    ("f 1 2 -5", "line 5: relative face index -5, but only 4 vertices come before it"),
    ("f 1/0 2/1 3/1", "line 5: face index 0"),
])
def test_obj_face_indices_that_name_no_vertex_are_refused(tmp_path, face: str, message: str) -> None:
    path = tmp_path / "bad.obj"
    path.write_text(f"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n{face}\n")
    with pytest.raises(MeshFileError, match=re.escape(message)):
        read_mesh(path)


def test_an_npz_declaring_more_than_the_machine_has_is_refused_before_it_is_unpacked(tmp_path) -> None:
    import io
    import zipfile

    header = io.BytesIO()  # a header that declares 2.4e13 bytes, and no data: np.load would allocate first
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (10**12, 3)})
    faces = io.BytesIO()
    np.save(faces, np.array([[0, 1, 2]], np.int32))
    path = tmp_path / "bomb.npz"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("vertices.npy", header.getvalue())
        archive.writestr("faces.npy", faces.getvalue())
    with pytest.raises(MeshFileError, match=r"declare 22351\.7 GiB, more than the .* GiB this machine has available"):
        read_mesh(path)


def test_an_empty_name_is_not_the_current_folder() -> None:
    with pytest.raises(MeshFileError, match="an empty name where a mesh file was expected"):
        read_mesh("")
