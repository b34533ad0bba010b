"""Tests for spctool.formats.icq (spc-formats.md §5, §9 ICQ checklist; fixtures/real/README.md §3)."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from spctool.errors import SpcFormatError, SpcUsageError
from spctool.formats import fortran, icq, icq_mesh
from spctool.formats.mesh import TriangleMesh, read_obj, read_vtk

REAL = Path(__file__).resolve().parents[1] / "fixtures" / "real"
BENNU = {
    32: REAL / "bennu-shapes" / "g_12570mm_alt_obj_0000n00000_v014.obj",
    64: REAL / "bennu-shapes" / "Bennu49k.obj",
}

# spc-formats.md §5.3, verbatim: unit cube of side 1 km, Q = 1
EXAMPLE_53 = """\
           1
    -0.50000     0.50000     0.50000
     0.50000     0.50000     0.50000
    -0.50000    -0.50000     0.50000
     0.50000    -0.50000     0.50000
    -0.50000    -0.50000     0.50000
     0.50000    -0.50000     0.50000
    -0.50000    -0.50000    -0.50000
     0.50000    -0.50000    -0.50000
    -0.50000     0.50000     0.50000
    -0.50000    -0.50000     0.50000
    -0.50000     0.50000    -0.50000
    -0.50000    -0.50000    -0.50000
     0.50000     0.50000     0.50000
    -0.50000     0.50000     0.50000
     0.50000     0.50000    -0.50000
    -0.50000     0.50000    -0.50000
     0.50000    -0.50000     0.50000
     0.50000     0.50000     0.50000
     0.50000    -0.50000    -0.50000
     0.50000     0.50000    -0.50000
    -0.50000    -0.50000    -0.50000
     0.50000    -0.50000    -0.50000
    -0.50000     0.50000    -0.50000
     0.50000     0.50000    -0.50000
"""

FAST = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(params=["python", "kernel", "plain"])
def path_kind(request, monkeypatch):
    """Run a test through the plain-Python reader/writer, through the numba kernels, and through the
    plain-rows reader (files it does not take go to the kernels)."""
    monkeypatch.setattr(icq, "_KERNEL_MIN_VALUES", 10**12 if request.param == "python" else 0)
    monkeypatch.setattr(icq, "_PLAIN_MAX_VALUES", 10**12 if request.param == "plain" else -1)
    monkeypatch.setattr(icq, "_kernel_cached", lambda: request.param != "plain")
    monkeypatch.setattr(icq, "_KEEP_MIN_VALUES", 10**12)  # each reader reads: no rows kept from before
    return request.param


def bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64).view(np.int64)


def sphere(q: int, radius: float = 1.0) -> np.ndarray:
    g = icq.icq_cube_grid(q)
    return radius * g / np.sqrt(g[..., 0] ** 2 + g[..., 1] ** 2 + g[..., 2] ** 2)[..., None]


def perturbed_shape(q: int, seed: int, amp: float, radius: float, with_albedo: bool) -> icq.IcqShape:
    """A random shape on the ICQ grid: perturbed sphere, one random value per distinct vertex."""
    rng = np.random.default_rng(seed)
    n = q + 1
    rep = icq.icq_merge_map(q)
    unit = sphere(q).reshape(-1, 3)
    r = radius * (1.0 + amp * rng.uniform(-1, 1, size=unit.shape[0]))[rep]
    v = (unit * r[:, None]).reshape(6, n, n, 3)
    alb = rng.uniform(0.01, 2.0, size=unit.shape[0])[rep].reshape(6, n, n) if with_albedo else None
    return icq.IcqShape(q, v, alb)


# =============================================================================================
# face table, seams, quads


def face_point_by_table(f: int, a: float, b: float) -> tuple[float, float, float]:
    """§5.2 table transcribed literally (independent of the vectorised implementation)."""
    return {
        1: (a, -b, 1.0),
        2: (a, -1.0, -b),
        3: (-1.0, -a, -b),
        4: (-a, 1.0, -b),
        5: (1.0, a, -b),
        6: (a, b, -1.0),
    }[f]


@pytest.mark.parametrize("q", [1, 2, 5, 8])
def test_cube_grid_follows_face_table(q):
    g = icq.icq_cube_grid(q)
    assert g.shape == (6, q + 1, q + 1, 3)
    assert not np.any(np.signbit(g) & (g == 0))  # no −0.0: it would print as "-0.00000" on one face only
    for f in range(1, 7):
        for j in range(q + 1):
            for i in range(q + 1):
                expected = face_point_by_table(f, -1 + 2 * i / q, -1 + 2 * j / q)
                np.testing.assert_allclose(g[f - 1, j, i], expected, rtol=0, atol=1e-15)
    # I runs left→right, J top→bottom seen from outside: ∂P/∂I × ∂P/∂J points inward
    for f in range(6):
        di = g[f, 0, 1] - g[f, 0, 0]
        dj = g[f, 1, 0] - g[f, 0, 0]
        centre = g[f, q // 2, q // 2] if q % 2 == 0 else g[f].reshape(-1, 3).mean(axis=0)
        assert np.dot(np.cross(di, dj), centre) < 0


def test_example_53_is_the_half_cube_grid():
    shape = icq.parse_icq(EXAMPLE_53)
    assert shape.q == 1 and shape.albedo is None
    assert np.array_equal(shape.vertices, 0.5 * icq.icq_cube_grid(1))


@pytest.mark.parametrize("q", [1, 2, 3, 8, 17])
def test_seam_pairs_match_geometry_exactly(q):
    """The 12 identities of §5.2 give exactly the classes of coincident cube-grid points."""
    g = icq.icq_cube_grid(q).reshape(-1, 3)
    a, b = icq.seam_identity_pairs(q)  # two index arrays, as the cli's validator uses them
    assert a.shape == b.shape == (12 * (q + 1),) and a.dtype == np.int64
    pairs = np.stack([a, b], axis=1)
    assert np.array_equal(bits(g[pairs[:, 0]]), bits(g[pairs[:, 1]]))
    # classes by integer cube coordinates (2I − Q etc. are integers on the cube)
    key = np.rint(g * q).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    rep = icq.icq_merge_map(q)
    assert np.array_equal(rep, first[inverse.ravel()])  # representative = lowest file index of the class
    assert np.unique(rep).size == 6 * q * q + 2
    # the pairs join vertices on different faces only, and every shared vertex is in some pair
    nv = (q + 1) ** 2
    assert np.all(pairs[:, 0] // nv != pairs[:, 1] // nv)
    shared = np.flatnonzero(np.bincount(inverse.ravel())[inverse.ravel()] > 1)
    assert set(shared.tolist()) == set(pairs.ravel().tolist())


@pytest.mark.parametrize("q", [1, 4, 9])
def test_seam_identities_hold_on_a_normalised_grid(q):
    v = sphere(q, 3.7).reshape(-1, 3)
    pairs = np.stack(icq.seam_identity_pairs(q), axis=1)
    assert np.array_equal(bits(v[pairs[:, 0]]), bits(v[pairs[:, 1]]))


@pytest.mark.parametrize("q", [1, 3, 8])
def test_quads_point_outward_on_a_sphere(q):
    v = sphere(q).reshape(-1, 3)
    quads = icq.icq_quads(q)
    assert quads.shape == (6 * q * q, 4)
    a, b, c, d = (v[quads[:, k]] for k in range(4))
    normal = np.cross(c - a, d - b)  # diagonals of v(I,J) → v(I,J+1) → v(I+1,J+1) → v(I+1,J)
    assert np.all(np.einsum("ij,ij->i", normal, a + b + c + d) > 0)
    # corner order: v(I,J), v(I,J+1), v(I+1,J+1), v(I+1,J)
    n = q + 1
    f, j, i = 3, 1 % q, q - 1
    k = (f - 1) * q * q + j * q + i
    assert quads[k].tolist() == [
        (f - 1) * n * n + j * n + i,
        (f - 1) * n * n + (j + 1) * n + i,
        (f - 1) * n * n + (j + 1) * n + i + 1,
        (f - 1) * n * n + j * n + i + 1,
    ]
    tri = icq.icq_triangles(q, merged=False)
    t0, t1, t2 = (v[tri[:, k]] for k in range(3))
    centroid = (t0 + t1 + t2) / 3
    assert np.all(np.einsum("ij,ij->i", np.cross(t1 - t0, t2 - t0), centroid) > 0)


@pytest.mark.parametrize("q", [1, 2, 6])
def test_merged_sphere_mesh_is_closed(q):
    shape = icq.IcqShape(q, sphere(q))
    mesh = icq_mesh.icq_to_mesh(shape)
    faces = mesh.faces
    assert faces.shape == (12 * q * q, 3)
    used = np.unique(faces)
    assert used.size == 6 * q * q + 2
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    directed = {tuple(e) for e in edges.tolist()}
    assert len(directed) == edges.shape[0]  # no directed edge twice: consistent orientation
    assert all((b, a) in directed for a, b in directed)  # every edge shared by exactly two faces, opposite
    n_edges = len(directed) // 2
    assert used.size - n_edges + faces.shape[0] == 2
    v = mesh.vertices
    volume = np.einsum("ij,ij->i", v[faces[:, 0]], np.cross(v[faces[:, 1]], v[faces[:, 2]])).sum() / 6
    assert volume > 0
    compact = icq_mesh.icq_to_mesh(shape, compact=True)
    assert compact.vertices.shape[0] == 6 * q * q + 2
    assert np.array_equal(compact.vertices[compact.faces], mesh.vertices[mesh.faces])


def test_face_coords_invert_face_point():
    rng = np.random.default_rng(3)
    p = rng.normal(size=(5000, 3)) * rng.uniform(0.1, 10, size=(5000, 1))
    face, a, b = icq.icq_face_coords(p)
    assert np.all((a >= -1) & (a <= 1) & (b >= -1) & (b <= 1))
    back = icq.icq_face_point(face, a, b)
    cos = np.einsum("ij,ij->i", back, p) / np.linalg.norm(back, axis=1) / np.linalg.norm(p, axis=1)
    np.testing.assert_allclose(cos, 1.0, atol=1e-14)
    # interior grid points come back on their own face with their own (a, b)
    q = 4
    g = icq.icq_cube_grid(q)[:, 1:q, 1:q]
    face, a, b = icq.icq_face_coords(g.reshape(-1, 3))
    assert np.array_equal(face, np.repeat(np.arange(1, 7), (q - 1) ** 2))
    i = np.rint((a + 1) * q / 2).astype(int).reshape(6, q - 1, q - 1)
    assert np.array_equal(i[0], np.broadcast_to(np.arange(1, q), (q - 1, q - 1)))
    with pytest.raises(ValueError):
        icq.icq_face_coords([0.0, 0.0, 0.0])


def test_shape_validation():
    with pytest.raises(ValueError):
        icq.IcqShape(2, np.zeros((6, 2, 2, 3)))
    with pytest.raises(ValueError):
        icq.IcqShape(0, np.zeros((6, 1, 1, 3)))
    s = icq.IcqShape(2, np.zeros((6, 3, 3, 3)))
    assert s.vertex_count == 54 and s.flat_vertices().shape == (54, 3)
    assert np.shares_memory(s.flat_vertices(), s.vertices)


# =============================================================================================
# the §5.3 example, byte-exact rewriting


def test_example_53_byte_identical(tmp_path, path_kind):
    shape = icq.parse_icq(EXAMPLE_53)
    assert icq.format_icq(shape) == EXAMPLE_53
    # a fresh shape with the same values is written the same way (SPC style = I12, 3F12.5)
    fresh = icq.IcqShape(1, shape.vertices.copy())
    assert icq.format_icq(fresh) == EXAMPLE_53
    p = tmp_path / "SHAPE.TXT"
    icq.write_icq(p, fresh)
    assert p.read_bytes() == EXAMPLE_53.encode()
    again = icq.read_icq(p)
    assert str(again.path) == str(p)
    icq.write_icq(p, again)
    assert p.read_bytes() == EXAMPLE_53.encode()


def test_unchanged_foreign_layout_is_kept_and_changes_touch_only_their_lines(path_kind):
    # a file in another writer's layout: D exponents, 80-column padding, a trailing blank line
    q = 1
    v = 0.5 * icq.icq_cube_grid(q).reshape(-1, 3)
    lines = ["1".rjust(12).ljust(80)]
    for x, y, z in v:
        lines.append(" ".join(fortran.format_d(t, 20, 10) for t in (x, y, z)).ljust(80))
    text = "\n".join(lines) + "\n\n"
    shape = icq.parse_icq(text)
    assert np.array_equal(shape.flat_vertices(), v)
    assert icq.format_icq(shape) == text
    assert icq.format_icq(shape, style="exact") == text  # unchanged: the style does not matter
    # move one corner (and its seam duplicates, to keep the shape an ICQ)
    rep = icq.icq_merge_map(q)
    moved = np.flatnonzero(rep == rep[0])
    assert moved.size == 3  # a cube corner is on three faces
    shape.flat_vertices()[moved] *= 1.25
    out = icq.format_icq(shape).split("\n")
    old = text.split("\n")
    assert len(out) == len(old)
    changed = [k for k in range(len(old)) if out[k] != old[k]]
    assert changed == sorted((moved + 1).tolist())
    assert all(out[k] == "".join(f"{t:12.5f}" for t in v[k - 1] * 1.25) for k in changed)


def test_seam_policy_on_write(path_kind):
    shape = icq.IcqShape(2, sphere(2))
    shape.vertices[0, 0, 0] += 1e-9  # corner vertex 0 alone: its duplicates now differ
    with pytest.raises(ValueError, match="seam"):
        icq.format_icq(shape)
    assert icq.seam_mismatch(shape) == pytest.approx(1e-9, rel=1e-3)
    unified = icq.parse_icq(icq.format_icq(shape, style="exact", seams="unify"))
    assert icq.seam_mismatch(unified) == 0.0
    kept = icq.parse_icq(icq.format_icq(shape, style="exact", seams="keep"))
    assert np.array_equal(kept.vertices, shape.vertices)
    assert icq.seam_mismatch(icq.unify_seams(shape)) == 0.0


def test_spc_style_refuses_values_that_do_not_fit(path_kind):
    big = icq.IcqShape(1, 20000.0 * icq.icq_cube_grid(1))  # −20000.00000 leaves no blank between fields
    with pytest.raises(ValueError, match="style='exact'"):
        icq.format_icq(big)
    back = icq.parse_icq(icq.format_icq(big, style="exact"))
    assert np.array_equal(back.vertices, big.vertices)
    ok = icq.IcqShape(1, 9999.99999 * icq.icq_cube_grid(1))
    assert np.array_equal(icq.parse_icq(icq.format_icq(ok)).vertices, ok.vertices)


def test_write_refuses_to_overwrite_and_keeps_backups(tmp_path):
    p = tmp_path / "SHAPE.TXT"
    shape = icq.parse_icq(EXAMPLE_53)
    icq.write_icq(p, shape)
    with pytest.raises(SpcUsageError):
        icq.write_icq(p, shape, overwrite=False)
    kept = icq.write_icq(p, shape, style="exact", backup=True)
    assert kept is not None and kept.read_bytes() == EXAMPLE_53.encode()
    assert np.array_equal(icq.read_icq(p).vertices, shape.vertices)


# =============================================================================================
# round trips (hypothesis)


@FAST
@given(
    q=st.integers(1, 7),
    seed=st.integers(0, 2**32 - 1),
    amp=st.sampled_from([0.0, 1e-6, 0.05, 0.3]),
    radius=st.sampled_from([1e-4, 0.25, 1.0, 17.3, 1234.5]),
    with_albedo=st.booleans(),
)
def test_exact_style_round_trip_is_lossless(path_kind, q, seed, amp, radius, with_albedo):
    shape = perturbed_shape(q, seed, amp, radius, with_albedo)
    text = icq.format_icq(shape, style="exact")
    lines = text.split("\n")
    assert lines[0] == str(q).rjust(12) and len(lines) == shape.vertex_count + 2 and lines[-1] == ""
    back = icq.parse_icq(text)
    assert back.q == q
    assert np.array_equal(bits(back.vertices), bits(shape.vertices))
    if with_albedo:
        assert np.array_equal(bits(back.albedo), bits(shape.albedo))
    else:
        assert back.albedo is None
    # duplicated seam vertices are written with identical text
    pairs = np.stack(icq.seam_identity_pairs(q), axis=1)
    body = lines[1:-1]
    assert all(body[a] == body[b] for a, b in pairs.tolist())


@FAST
@given(
    q=st.integers(1, 7),
    seed=st.integers(0, 2**32 - 1),
    amp=st.sampled_from([0.0, 0.01, 0.3]),
    radius=st.sampled_from([0.25, 1.0, 17.3, 999.9]),
    with_albedo=st.booleans(),
)
def test_spc_style_round_trip(path_kind, q, seed, amp, radius, with_albedo):
    shape = perturbed_shape(q, seed, amp, radius, with_albedo)
    text = icq.format_icq(shape)
    width = 49 if with_albedo else 37
    assert all(len(ln) == width - 1 for ln in text.split("\n")[1:-1])
    back = icq.parse_icq(text)
    assert np.max(np.abs(back.vertices - shape.vertices)) <= 5e-6 + 1e-12 * radius
    if with_albedo:
        assert np.max(np.abs(back.albedo - shape.albedo)) <= 5e-6 + 1e-12
    assert icq.format_icq(back) == text  # unchanged: byte-identical
    fresh = icq.IcqShape(q, back.vertices.copy(), None if back.albedo is None else back.albedo.copy())
    assert icq.format_icq(fresh) == text  # and the F12.5 writer is idempotent
    # every value is exactly Python's %12.5f (= correctly rounded, ties to even)
    table = shape.flat_vertices() if not with_albedo else np.c_[shape.flat_vertices(), shape.flat_albedo()]
    row = int(seed % table.shape[0])
    assert text.split("\n")[row + 1] == "".join(f"{t:12.5f}" for t in table[row])


reals = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False, min_value=-1e300, max_value=1e300),
    st.floats(min_value=-1e5, max_value=1e5, allow_nan=False),
    st.integers(-(10**9), 10**9).map(lambda k: k / 64.0),  # binary ties for F12.5
    st.integers(-(10**10), 10**10).map(lambda k: k / 1e5),
    st.sampled_from([0.0, -0.0, 5e-324, 1e-300, 1e-6, 1e-5, 0.001, 9.999999999999999e15, 1e16, 123.456]),
    # just below / at powers of ten (the decade of the 17-digit form)
    st.integers(-6, 15).map(lambda k: float(np.nextafter(10.0**k, 0.0))),
    st.integers(-6, 15).map(lambda k: 10.0**k),
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(values=st.lists(reals, min_size=3, max_size=60))
def test_kernel_writers_equal_python_formatting(monkeypatch, values):
    n = len(values) // 3 * 3
    table = np.array(values[:n], dtype=np.float64).reshape(-1, 3)
    monkeypatch.setattr(icq, "_KERNEL_MIN_VALUES", 0)
    exact = bytes(icq._format_rows(table, "exact")).decode()
    # Python's "%24.16E" whenever that leaves a blank before the value (2-digit exponents)
    assert exact == "".join("".join(f" {t:23.16E}" for t in row) + "\n" for row in table)
    # lossless through the three readers
    for limit, plain in ((0, -1), (10**12, -1), (0, 10**12)):
        monkeypatch.setattr(icq, "_KERNEL_MIN_VALUES", limit)
        monkeypatch.setattr(icq, "_PLAIN_MAX_VALUES", plain)
        monkeypatch.setattr(icq, "_kernel_cached", lambda cached=plain < 0: cached)
        q1 = "1".rjust(12) + "\n"
        # pad to a full Q = 1 file (24 lines) by repeating the rows
        rows = np.resize(table, (24, 3))
        text = q1 + bytes(icq._format_rows(rows, "exact")).decode()
        assert np.array_equal(bits(icq.parse_icq(text).flat_vertices()), bits(rows))
    small = table[np.all(np.abs(table) < 9999.0, axis=1)]
    if small.size:
        monkeypatch.setattr(icq, "_KERNEL_MIN_VALUES", 0)
        fixed = bytes(icq._format_rows(small, "spc")).decode()
        assert fixed == "".join("".join(f"{t:12.5f}" for t in row) + "\n" for row in small)


# Fortran list-directed numbers, generated from the §0.3 grammar
digits = st.text("0123456789", min_size=0, max_size=22)


@st.composite
def fortran_token(draw):
    a, b = draw(digits), draw(digits)
    if not a and not b:
        a = "0"
    point = draw(st.sampled_from([".", ""])) if b == "" else "." + b
    mant = draw(st.sampled_from(["", "+", "-"])) + a + point
    kind = draw(st.sampled_from(["", "E", "D", "d", "e", "Q", "letterless"]))
    if kind == "":
        return mant
    e = draw(st.integers(-330, 330))
    if kind == "letterless":
        return f"{mant}{e:+03d}"
    return f"{mant}{kind}{draw(st.sampled_from(['', '+'])) if e >= 0 else ''}{e}"


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    drawn=st.lists(fortran_token(), min_size=3, max_size=12),
    sep=st.sampled_from([" ", "  ", ",", " , ", "\t"]),
)
def test_readers_agree_with_fortran_parse_number(path_kind, drawn, sep):
    toks = (drawn * 24)[:72]  # a full Q = 1 file
    def value(t):
        try:
            return fortran.parse_number(t)
        except ValueError:  # overflowing exponent: refused (gfortran would store Infinity)
            return np.inf

    expected = np.array([value(t) for t in toks])
    if not np.all(np.isfinite(expected)):
        with pytest.raises(SpcFormatError):
            icq.parse_icq("1\n" + "".join(" ".join(toks[3 * k : 3 * k + 3]) + "\n" for k in range(24)))
        return
    # trailing text is ignored (list-directed), except on the first vertex line, where a 4th token
    # within 100 columns would announce an albedo column (GET_MODEL)
    lines = [" " + sep.join(toks[3 * k : 3 * k + 3]) + (" trailing text" if k else "") for k in range(24)]
    # GET_MODEL counts blank-ended tokens on the first vertex line (commas do not separate there): write
    # it blank-separated, as it must be for SPC to read any vertex
    lines[0] = " " + " ".join(toks[0:3])
    if len(lines[0]) > 99:  # GET_MODEL counts tokens ending in columns 1-99 only: it would read no vertex
        with pytest.raises(SpcFormatError, match="GET_MODEL counts"):
            icq.parse_icq("1\n" + "\n".join(lines) + "\n")
        return
    text = "1\n" + "\n".join(lines) + "\n"
    got = icq.parse_icq(text).flat_vertices().ravel()
    assert np.array_equal(bits(got), bits(expected))


def test_list_directed_forms(path_kind):
    body = [
        "0.5D+00 -5.0-01 .5",
        "5.E-1,-0.5Q0, +0.5  extra words",
        "0.5d0\t-0.5e+0\t0.50000000000000000000001",
    ]
    text = "           1   trailing\n" + "\n".join(body * 8) + "\n"
    v = icq.parse_icq(text).flat_vertices()
    assert np.array_equal(v[0], [0.5, -0.5, 0.5]) and np.array_equal(v[1], [0.5, -0.5, 0.5])
    assert v[2, 2] == fortran.parse_number("0.50000000000000000000001")


def test_albedo_column(path_kind):
    rows = 0.5 * icq.icq_cube_grid(1).reshape(-1, 3)
    alb = np.linspace(0.5, 1.5, 24)
    text = "1\n" + "".join(f"{x} {y} {z} {a}\n" for (x, y, z), a in zip(rows, alb))
    shape = icq.parse_icq(text)
    assert np.array_equal(shape.flat_albedo(), alb)
    out = icq.format_icq(icq.IcqShape(1, shape.vertices, shape.albedo), seams="keep")
    assert out.split("\n")[1] == "    -0.50000     0.50000     0.50000     0.50000"
    # a 4th number only after column 100 of the first vertex line is not an albedo column (GET_MODEL)
    text2 = "1\n" + "".join(f"{x} {y} {z}".ljust(100) + " 7\n" for x, y, z in rows)
    assert icq.parse_icq(text2).albedo is None


# =============================================================================================
# malformed input


def _err(text: str) -> SpcFormatError:
    with pytest.raises(SpcFormatError) as exc:
        icq.parse_icq(text, "SHAPE.TXT")
    return exc.value


def test_errors_name_the_line(path_kind):
    lines = EXAMPLE_53.split("\n")
    # too few vertex lines
    e = _err("\n".join(lines[:-3]) + "\n")
    assert e.where == 24 and "24 vertex lines" in str(e) and str(e).startswith("SHAPE.TXT:24: expected")
    # too many
    # GET_MODEL reads 6(Q+1)² vertex records and closes the file: an extra line is a warning, not an error
    extra = icq.parse_icq(EXAMPLE_53 + "  1.0 2.0 3.0\n")
    assert extra.__dict__["_spc_warnings"][0][0] == 26
    assert np.array_equal(extra.vertices, icq.parse_icq(EXAMPLE_53).vertices)
    # one extra token on the first vertex line: GET_MODEL counts N = 5 and reads no vertex -> refused
    first_lines = EXAMPLE_53.split("\n")
    first_lines[1] += " 9.0 9.0"
    e = _err("\n".join(first_lines))
    assert e.where == 2 and "GET_MODEL counts 5" in str(e)
    # garbage number on line 7
    bad = list(lines)
    bad[6] = "     0.50000    -0.5OOOO     0.50000"
    e = _err("\n".join(bad))
    assert e.where == 7 and "'-0.5OOOO'" in str(e) and "value 2" in str(e)
    # too few numbers on line 12
    bad = list(lines)
    bad[11] = "    -0.50000     0.50000"
    e = _err("\n".join(bad))
    assert e.where == 12 and "found 2" in str(e)
    # blank line in the middle
    bad = list(lines)
    bad.insert(5, "")
    assert _err("\n".join(bad)).where == 6
    # Q
    assert _err("  one\n" + "\n".join(lines[1:])).where == 1
    assert _err("").where == 1
    assert _err("0\n1 2 3\n").where == 1
    # a huge Q must fail fast on the line count, not allocate
    e = _err("     1000000\n1 2 3\n")
    assert e.where == 3 and "6000012000006" in str(e)
    # albedo missing on a later line
    rows = ["1 2 3 0.5"] + ["1 2 3"] * 23
    assert _err("1\n" + "\n".join(rows) + "\n").where == 3
    # number out of range
    bad = list(lines)
    bad[3] = "1.0D+999 0 0"
    assert _err("\n".join(bad)).where == 4


def test_errors_from_files(tmp_path):
    p = tmp_path / "BROKEN.TXT"
    lines = EXAMPLE_53.split("\n")
    assert lines[8] == "     0.50000    -0.50000    -0.50000"
    lines[8] = "     0.50000    -0.50000    -x.50000"
    p.write_text("\n".join(lines))
    with pytest.raises(SpcFormatError) as exc:
        icq.read_icq(p)
    assert str(exc.value).startswith(f"{p}:9: expected 3 numbers")


# =============================================================================================
# real Bennu shapes (fixtures/real/README.md §3)


@pytest.mark.parametrize("q", [32, 64])
def test_bennu_obj_vertex_lists_are_exact_icq_grids(q, tmp_path):
    mesh = read_obj(BENNU[q])
    n = q + 1
    assert mesh.vertices.shape == (6 * n * n, 3)
    pairs = np.stack(icq.seam_identity_pairs(q), axis=1)
    v = mesh.vertices
    assert np.array_equal(bits(v[pairs[:, 0]]), bits(v[pairs[:, 1]]))  # all 12 identities, bit-exact
    rep = icq.icq_merge_map(q)
    assert np.unique(v, axis=0).shape[0] == 6 * q * q + 2
    # the facets use exactly the seam representatives (lowest file index of each duplicate set)
    assert np.array_equal(np.unique(mesh.faces), np.unique(rep))
    # face layout: every OBJ triangle lies in one ICQ quad, with the same orientation
    quads = icq.icq_quads(q)
    qsets = {}
    for k, quad in enumerate(rep[quads].tolist()):
        for tri in itertools.combinations(sorted(quad), 3):
            qsets.setdefault(tri, []).append(k)
    owner = [qsets.get(tuple(sorted(t)), []) for t in mesh.faces.tolist()]
    assert all(len(o) == 1 for o in owner)
    qv = quads[[o[0] for o in owner]]
    n_quad = np.cross(v[qv[:, 2]] - v[qv[:, 0]], v[qv[:, 3]] - v[qv[:, 1]])
    f = mesh.faces
    n_tri = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert np.all(np.einsum("ij,ij->i", n_tri, n_quad) > 0)
    # OBJ → ICQ → OBJ-style mesh: the same vertices exactly
    shape = icq_mesh.mesh_to_icq(mesh)
    assert shape.q == q and shape.albedo is None
    assert np.array_equal(bits(shape.flat_vertices()), bits(v))
    assert np.array_equal(bits(icq_mesh.icq_to_mesh(shape).vertices), bits(v))
    # and through an ICQ file, losslessly in exact style
    p = tmp_path / "SHAPE.TXT"
    icq.write_icq(p, shape, style="exact")
    back = icq.read_icq(p)
    assert np.array_equal(bits(back.vertices), bits(shape.vertices))
    icq.write_icq(p, back, style="exact")
    assert icq.format_icq(icq.read_icq(p)) == p.read_text()
    # SPC style: within 5e-6 km, and byte-identical on the second rewrite
    icq.write_icq(p, shape)
    first = p.read_bytes()
    spc = icq.read_icq(p)
    assert np.max(np.abs(spc.vertices - shape.vertices)) <= 5e-6
    icq.write_icq(p, icq.IcqShape(q, spc.vertices.copy()))
    assert p.read_bytes() == first


def test_mesh_to_icq_explains_non_icq_vertex_lists():
    q = 3
    n = q + 1
    v = sphere(q).reshape(-1, 3)
    with pytest.raises(SpcFormatError, match="6\\(Q\\+1\\)² vertices"):
        icq_mesh.mesh_to_icq(TriangleMesh(v[:-1], np.zeros((0, 3), int)))
    swapped = v.reshape(6, n * n, 3)[[1, 0, 2, 3, 4, 5]].reshape(-1, 3)  # faces 1 and 2 exchanged
    with pytest.raises(SpcFormatError, match="not in ICQ order"):
        icq_mesh.mesh_to_icq(TriangleMesh(swapped, np.zeros((0, 3), int)))


def test_gaskell_vtk_is_near_icq_only():
    """README §4: ICQ layout, but seam duplicates differ by up to 2.9 m (Eros)."""
    mesh = read_vtk(REAL / "gaskell-vtk" / "Eros_ver64q.vtk")
    with pytest.raises(SpcFormatError, match="seam pairs differ") as exc:
        icq_mesh.mesh_to_icq(mesh)
    assert "Eros_ver64q.vtk" in str(exc.value)
    shape = icq_mesh.mesh_to_icq(mesh, seam_tolerance=0.003)
    assert shape.q == 64 and icq.seam_mismatch(shape) == 0.0
    rep = icq.icq_merge_map(64)
    assert np.array_equal(shape.flat_vertices(), mesh.vertices[rep])
