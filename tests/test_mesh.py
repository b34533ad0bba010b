"""Tests for spctool.formats.mesh: OBJ and legacy VTK meshes, shape dispatch (fixtures/real/README §3–§4)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool.errors import SpcFormatError
from spctool.formats import icq, icq_mesh
from spctool.formats.mesh import (
    TriangleMesh,
    format_obj,
    format_vtk,
    parse_obj,
    parse_vtk,
    read_obj,
    read_shape,
    read_vtk,
    write_obj,
    write_vtk,
)

REAL = Path(__file__).resolve().parents[1] / "fixtures" / "real"
BENNU32 = REAL / "bennu-shapes" / "g_12570mm_alt_obj_0000n00000_v014.obj"
BENNU64 = REAL / "bennu-shapes" / "Bennu49k.obj"
EROS = REAL / "gaskell-vtk" / "Eros_ver64q.vtk"
ITOKAWA = REAL / "gaskell-vtk" / "itokawa_ver64q.vtk"


def volume_area(mesh: TriangleMesh) -> tuple[float, float]:
    """Independent check of a parsed mesh: signed volume and area by the divergence theorem."""
    v, f = mesh.vertices, mesh.faces
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()
    return float(vol), float(area)


def euler_and_manifold(faces: np.ndarray) -> tuple[int, bool]:
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    directed = {tuple(e) for e in edges.tolist()}
    manifold = len(directed) == len(edges) and all((b, a) in directed for a, b in directed)
    return np.unique(faces).size - len(directed) // 2 + faces.shape[0], manifold


# =============================================================================================
# OBJ


@pytest.mark.parametrize(
    "path, nv, nf, volume, area",
    [
        (BENNU32, 6534, 12288, 0.06084015, 0.78282),
        (BENNU64, 25350, 49152, 0.06278472, 0.82577),
    ],
)
def test_bennu_obj(path, nv, nf, volume, area):
    mesh = read_obj(path)
    assert mesh.vertices.shape == (nv, 3) and mesh.faces.shape == (nf, 3)
    assert mesh.faces.dtype == np.int64 and mesh.faces.min() >= 0 and mesh.faces.max() < nv
    assert mesh.comments[0].startswith("Model of the surface of Bennu.")
    assert str(mesh.path) == str(path)
    vol, ar = volume_area(mesh)
    assert vol == pytest.approx(volume, rel=1e-6) and ar == pytest.approx(area, rel=1e-5)  # header values
    chi, manifold = euler_and_manifold(mesh.faces)
    assert chi == 2 and manifold
    # first vertex and facet as written in the file (1-based → 0-based)
    text = path.read_text(encoding="latin-1").split("\n")
    first_v = next(ln for ln in text if ln.startswith("v "))
    first_f = next(ln for ln in text if ln.startswith("f "))
    assert mesh.vertices[0].tolist() == [float(t) for t in first_v.split()[1:]]
    assert (mesh.faces[0] + 1).tolist() == [int(t) for t in first_f.split()[1:]]


def test_obj_round_trip_keeps_comments_and_exact_values(tmp_path):
    mesh = read_obj(BENNU32)
    p = tmp_path / "bennu.obj"
    write_obj(p, mesh)
    back = read_obj(p)
    assert back.comments == mesh.comments
    assert np.array_equal(back.vertices, mesh.vertices) and np.array_equal(back.faces, mesh.faces)
    assert format_obj(back).encode("latin-1") == p.read_bytes()  # UTF-8 quotes in comments kept as bytes
    assert "‘v’".encode() in p.read_bytes()


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(3, 30),
    seed=st.integers(0, 2**32 - 1),
    normals=st.booleans(),
    comments=st.lists(st.text("abc xyz=#-_.0123456789", max_size=30), max_size=3),
)
def test_obj_round_trip_random(n, seed, normals, comments):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-8, 8, size=(n, 1))
    f = rng.integers(0, n, size=(2 * n, 3))
    vn = rng.normal(size=(n, 3)) if normals else None
    mesh = TriangleMesh(v, f, vn, comments)
    back = parse_obj(format_obj(mesh))
    assert np.array_equal(back.vertices.view(np.int64), mesh.vertices.view(np.int64))
    assert np.array_equal(back.faces, mesh.faces)
    assert (back.vertex_normals is None) == (not normals)
    if normals:
        assert np.array_equal(back.vertex_normals, vn)
    assert back.comments == [c.replace("\n", " ") for c in comments]


def test_obj_statement_forms():
    text = "\n".join(
        [
            "# a comment",
            "mtllib x.mtl",
            "o thing",
            "v 0 0 0",
            "v 1 0 0 1.0",  # w ignored
            "v 1 1 0",
            "v 0 1 0",
            "v 0.5 0.5 1 0.1 0.2 0.3",  # vertex colours ignored
            "vt 0 0",
            "vn 0 0 1",
            "g group",
            "s off",
            "usemtl m",
            "f 1/1/1 2/1/1 3/1/1 4/1/1",  # a quad: fan (1,2,3), (1,3,4)
            "f -5//1 -3//1 -1//1",  # negative: relative to the 5 vertices so far → 1, 3, 5
            "f\t2 3 5",
            "l 1 2",
            "",
        ]
    )
    mesh = parse_obj(text)
    assert mesh.vertices.shape == (5, 3) and mesh.vertices[1].tolist() == [1, 0, 0]
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 2, 4], [1, 2, 4]]
    assert mesh.comments == [" a comment"]
    assert mesh.vertex_normals is None  # one vn for five vertices: not per-vertex normals


@pytest.mark.parametrize(
    "line, where, words",
    [
        ("v 1.0 2.O 3.0", 3, "'2.O'"),
        ("v 1.0 2.0", 3, "found 2 values"),
        ("f 1 2 9", 3, "up to 2"),
        ("f 1 2", 3, "at least 3"),
        ("f 1 0 2", 3, "≠ 0"),
        ("f 1 2 -7", 3, "relative index"),
        ("f 1 x 2", 3, "'x'"),
        ("bogus 1 2 3", 3, "'bogus'"),
        ("v nan 0 0", 3, "finite"),
    ],
)
def test_obj_errors_name_the_line(line, where, words):
    text = f"# header\nv 0 0 0\n{line}\nv 1 1 1\n"
    with pytest.raises(SpcFormatError) as exc:
        parse_obj(text, "shape.obj")
    assert exc.value.where == where and words in str(exc.value)
    assert str(exc.value).startswith(f"shape.obj:{where}: expected")


def test_obj_without_vertices_is_an_error():
    with pytest.raises(SpcFormatError):
        parse_obj("# nothing here\n")


# =============================================================================================
# VTK


@pytest.mark.parametrize(
    "path, lo, hi",
    [
        (EROS, (-17.57, -8.28, -6.07), (15.09, 8.60, 5.89)),
        (ITOKAWA, (-0.256, -0.155, -0.120), (0.306, 0.150, 0.124)),
    ],
)
def test_gaskell_vtk(path, lo, hi):
    mesh = read_vtk(path)
    assert mesh.vertices.shape == (25350, 3) and mesh.faces.shape == (49152, 3)
    assert mesh.vertex_normals is not None and mesh.vertex_normals.shape == (25350, 3)
    np.testing.assert_allclose(np.linalg.norm(mesh.vertex_normals, axis=1), 1.0, atol=1e-5)
    decimals = 2 if path == EROS else 3
    assert np.round(mesh.vertices.min(axis=0), decimals).tolist() == list(lo)
    assert np.round(mesh.vertices.max(axis=0), decimals).tolist() == list(hi)
    assert mesh.comments == ["vtk output"]
    # closed, consistently oriented, outward; 24 578 = 6·64² + 2 vertices used
    assert np.unique(mesh.faces).size == 24578
    chi, manifold = euler_and_manifold(mesh.faces)
    assert chi == 2 and manifold
    vol, _ = volume_area(mesh)
    assert vol > 0
    # the data are float32 big-endian, exactly as in the file
    raw = path.read_bytes()
    off = raw.index(b"POINTS 25350 float\n") + len(b"POINTS 25350 float\n")
    assert np.array_equal(mesh.vertices[:5].ravel(), np.frombuffer(raw, ">f4", 15, off).astype(np.float64))


@pytest.mark.parametrize("path", [EROS, ITOKAWA])
def test_gaskell_vtk_rewritten_byte_identically(path, tmp_path):
    mesh = read_vtk(path)
    assert format_vtk(mesh, binary=True, points_type="float") == path.read_bytes()
    out = tmp_path / "copy.vtk"
    write_vtk(out, mesh, points_type="float")
    assert out.read_bytes() == path.read_bytes()


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("points_type", ["double", "float"])
def test_vtk_round_trip(binary, points_type):
    shape = icq.IcqShape(8, icq.icq_cube_grid(8) * np.array([0.3, 0.2, 0.1]) * (1 + 1e-9))
    small = icq_mesh.icq_to_mesh(shape)
    normals = small.vertices / np.linalg.norm(small.vertices, axis=1, keepdims=True)
    mesh = TriangleMesh(small.vertices, small.faces, normals, ["title line"])
    back = parse_vtk(format_vtk(mesh, binary=binary, points_type=points_type))
    expect = mesh.vertices if points_type == "double" else mesh.vertices.astype(np.float32).astype(np.float64)
    assert np.array_equal(back.vertices, expect)
    assert np.array_equal(back.faces, mesh.faces)
    assert back.comments == ["title line"]
    assert back.vertex_normals is not None


def test_vtk_ascii_cells_strips_offsets_and_attributes():
    text = b"""# vtk DataFile Version 2.0
a square, a strip and extras
ASCII

DATASET POLYDATA
POINTS 5 float
0 0 0  1 0 0  1 1 0
0 1 0  2 2 2
METADATA
INFORMATION 0

VERTICES 1 2
1 4
POLYGONS 2 9
4 0 1 2 3
3 0 2 4
TRIANGLE_STRIPS 1 6
5 0 1 3 2 4
POINT_DATA 5
SCALARS height float 1
LOOKUP_TABLE default
0 1 2 3 4
FIELD FieldData 1
temps 1 5 double
1 2 3 4 5
NORMALS Normals float
0 0 1 0 0 1 0 0 1 0 0 1 0 0 1
CELL_DATA 4
COLOR_SCALARS rgb 3
1 0 0 0 1 0 0 0 1 1 1 1
"""
    mesh = parse_vtk(text)
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 2, 4], [0, 1, 3], [3, 1, 2], [3, 2, 4]]
    assert mesh.vertex_normals.tolist() == [[0, 0, 1]] * 5
    assert mesh.comments == ["a square, a strip and extras"]
    v51 = b"""# vtk DataFile Version 5.1
vtk output
ASCII
DATASET POLYDATA
POINTS 4 double
0 0 0 1 0 0 1 1 0 0 1 0
POLYGONS 3 7
OFFSETS vtktypeint64
0 3 7
CONNECTIVITY vtktypeint64
0 1 2 0 1 2 3
"""
    assert parse_vtk(v51).faces.tolist() == [[0, 1, 2], [0, 1, 2], [0, 2, 3]]


def test_vtk_errors_name_the_byte_or_line():
    raw = EROS.read_bytes()
    poly = raw.index(b"POLYGONS")
    data_start = raw.index(b"\n", poly) + 1
    # truncated inside the polygon data
    with pytest.raises(SpcFormatError) as exc:
        parse_vtk(raw[: data_start + 1000], "eros.vtk")
    assert exc.value.where == f"byte {data_start}" and "196608 int values" in str(exc.value)
    assert str(exc.value).startswith(f"eros.vtk:byte {data_start}: expected")
    # truncated inside the points
    with pytest.raises(SpcFormatError) as exc:
        parse_vtk(raw[:5000])
    assert exc.value.where == "byte 81"
    # a point index out of range, at its exact byte
    bad = bytearray(raw)
    bad[data_start + 4 * 6 : data_start + 4 * 7] = (99999).to_bytes(4, "big")
    with pytest.raises(SpcFormatError) as exc:
        parse_vtk(bytes(bad))
    assert exc.value.where == f"byte {data_start + 24}" and "99999" in str(exc.value)
    # garbage where a section keyword should be
    bad = raw[:data_start] + raw[data_start : data_start + 4 * 196608] + b"\nGARBAGE 12\n"
    with pytest.raises(SpcFormatError) as exc:
        parse_vtk(bad)
    assert exc.value.where == f"byte {data_start + 4 * 196608 + 1}" and "GARBAGE" in str(exc.value)
    # not POLYDATA / not VTK
    with pytest.raises(SpcFormatError, match="DATASET POLYDATA"):
        parse_vtk(b"# vtk DataFile Version 3.0\nx\nASCII\nDATASET UNSTRUCTURED_GRID\n")
    with pytest.raises(SpcFormatError, match="vtk DataFile"):
        parse_vtk(b"hello\n")
    # ASCII errors name the line
    text = b"# vtk DataFile Version 3.0\nx\nASCII\nDATASET POLYDATA\nPOINTS 3 float\n0 0 0\n1 0 zero\n0 1 0\n"
    with pytest.raises(SpcFormatError) as exc:
        parse_vtk(text + b"POLYGONS 1 4\n3 0 1 2\n", "a.vtk")
    assert exc.value.where == 7 and "'zero'" in str(exc.value)
    text = b"# vtk DataFile Version 3.0\nx\nASCII\nDATASET POLYDATA\nPOINTS 3 float\n0 0 0\n1 0 0\n0 1 0\n"
    with pytest.raises(SpcFormatError) as exc:
        parse_vtk(text + b"POLYGONS 1 4\n3 0 1\n7\n")
    assert exc.value.where == 11 and "found 7" in str(exc.value)
    with pytest.raises(SpcFormatError, match="POLYGONS or TRIANGLE_STRIPS"):
        parse_vtk(text)


# =============================================================================================
# dispatch


def test_read_shape_dispatches_on_content(tmp_path):
    shape_txt = tmp_path / "SHAPE.TXT"
    q = 2
    g = icq.icq_cube_grid(q)
    icq.write_icq(shape_txt, icq.IcqShape(q, g / np.linalg.norm(g, axis=-1, keepdims=True)))
    assert isinstance(read_shape(shape_txt), icq.IcqShape)
    misnamed = tmp_path / "shape.obj"  # content decides, not the name
    misnamed.write_bytes(shape_txt.read_bytes())
    assert isinstance(read_shape(misnamed), icq.IcqShape)
    assert isinstance(read_shape(BENNU32), TriangleMesh)
    eros = read_shape(EROS)
    assert isinstance(eros, TriangleMesh) and eros.faces.shape == (49152, 3)
    # an ICQ with the wrong number of lines is reported as an ICQ error
    short = tmp_path / "SHORT.TXT"
    short.write_text("\n".join(shape_txt.read_text().split("\n")[:-5]) + "\n")
    with pytest.raises(SpcFormatError, match="vertex lines") as exc:
        read_shape(short)
    assert exc.value.where == 52
    junk = tmp_path / "junk.dat"
    junk.write_text("hello world\n")
    with pytest.raises(SpcFormatError) as exc:
        read_shape(junk)
    assert exc.value.where == 1 and str(exc.value).startswith(f"{junk}:1: expected a shape file")
    binary = tmp_path / "junk.bin"
    binary.write_bytes(b"ab\0cd")
    with pytest.raises(SpcFormatError, match="byte 2"):
        read_shape(binary)


def test_triangle_mesh_validation():
    with pytest.raises(ValueError):
        TriangleMesh(np.zeros((3, 3)), [[0, 1, 3]])
    with pytest.raises(ValueError):
        TriangleMesh(np.zeros((3, 3)), [[0, 1]])
    m = TriangleMesh(np.zeros((3, 3)), np.zeros((0, 3), int))
    assert m.face_count == 0 and m.vertex_count == 3
