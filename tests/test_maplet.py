"""Tests of spctool.formats.maplet against spc-formats.md §1 (MAP files).

Independent checks: the §1.6 worked example bytes, header fields decoded with the
``struct`` module, the 2021-writer quantisation recomputed with Python floats and
``struct`` float32 rounding, and hypothesis round trips.
"""

from __future__ import annotations

import dataclasses
import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool.errors import SpcFormatError, SpcUsageError
from spctool.formats.maplet import (
    Maplet,
    format_map,
    map_file_size,
    parse_map,
    read_map,
    read_maps,
    write_map,
)

# ---------------------------------------------------------------------------------------------
# helpers (independent of the module)
# ---------------------------------------------------------------------------------------------


def f32(x: float) -> float:
    """Round a Python float to float32 with struct (independent of numpy)."""
    return struct.unpack(">f", struct.pack(">f", x))[0]


def nint(x: float) -> int:
    """Fortran NINT: round half away from zero."""
    return int(math.copysign(math.floor(abs(x) + 0.5), x))


SPEC_96 = bytes.fromhex(
    "0000 0000 0000 3a83 126f 0200 9393 933d"
    "cccc cdbe 4ccc cd3e 9999 9a00 0000 00bf"
    "8000 0000 0000 003f 8000 0000 0000 0000"
    "0000 0000 0000 0000 0000 003f 8000 0038"
    "51b7 173a e305 fb00 0000 00c5 6865 b1e0"
    "669e 5867 8ad0 6800 0065 ec78 66d8 f067".replace(" ", "")
)


def spec_example() -> Maplet:
    """The §1.6 maplet: QSZ=2, SCALE=0.001 km, V=(0.1,-0.2,0.3), UX=(0,-1,0), UY=(1,0,0), UZ=(0,0,1),
    σ=(s,s,s) with s=0.001, cell (J=-2,I=-2) missing, max|h| = 1.5.

    The spec lists the first cells (J=-2: I=-1 → h=-0.75, A=101; the hex continues with
    h=-1.0, -1.25, -1.5 and A=102..104; J=-1: h=0, -0.25, -0.5 with A=101..103), i.e.
    h = 0.5(J+1) - 0.25(I+2) and albedo = 1 + 0.01(I+J+4) over the grid.
    """
    q = 2
    J, I = np.meshgrid(np.arange(-q, q + 1), np.arange(-q, q + 1), indexing="ij")
    h = 0.5 * (J + 1) - 0.25 * (I + 2)
    alb = 1.0 + 0.01 * (I + J + 4)
    valid = np.ones((5, 5), bool)
    valid[0, 0] = False
    return Maplet.new(
        0.001, q, (0.1, -0.2, 0.3), (0, -1, 0), (1, 0, 0), (0, 0, 1), h, alb, valid, sigma=(0.001,) * 3
    )


def random_maplet(rng: np.random.Generator, q: int, missing: float = 0.2) -> Maplet:
    n = 2 * q + 1
    uz = rng.normal(size=3)
    uz /= np.linalg.norm(uz)
    uy = np.cross([0.0, 0.0, 1.0], uz)
    uy /= np.linalg.norm(uy)
    ux = np.cross(uy, uz)
    return Maplet.new(
        float(rng.uniform(1e-4, 0.1)),
        q,
        rng.normal(size=3),
        ux,
        uy,
        uz,
        rng.normal(scale=rng.uniform(0.1, 20), size=(n, n)),
        rng.uniform(0.2, 1.8, size=(n, n)),
        rng.random((n, n)) > missing,
        mapvers=int(rng.integers(0, 256)),
        sigma=rng.uniform(0, 1, size=3),
    )


# ---------------------------------------------------------------------------------------------
# §1.6 worked example
# ---------------------------------------------------------------------------------------------


def test_worked_example_first_96_bytes_exact():
    data = format_map(spec_example())
    assert len(data) == 216 == map_file_size(2)
    assert data[:96] == SPEC_96
    # the last record is zero-filled after the 25th cell (72 + 75 = 147)
    assert data[72 + 75 :] == bytes(216 - 147)


def test_worked_example_fields_decoded_with_struct():
    data = format_map(spec_example())
    scale = struct.unpack(">f", data[6:10])[0]
    qsz = data[10] + 256 * data[11]
    v = struct.unpack(">3f", data[15:27])
    ux = struct.unpack(">3f", data[27:39])
    hscale = struct.unpack(">f", data[63:67])[0]
    assert scale == f32(0.001) and qsz == 2
    assert v == (f32(0.1), f32(-0.2), f32(0.3)) and ux == (0.0, -1.0, 0.0)
    assert hscale == f32(f32(1.5) / 30000.0)
    assert tuple(data[12:15]) == (nint(255 / math.sqrt(3)),) * 3 == (147, 147, 147)
    assert struct.unpack(">f", data[67:71])[0] == f32(math.sqrt(3) * 0.001)
    # cell (J=-2, I=-1): H = -15000, A = 101
    h, a = struct.unpack(">hB", data[75:78])
    assert (h, a) == (-15000, 101)


def test_worked_example_parsed_values():
    m = parse_map(format_map(spec_example()))
    assert m.qsz == 2 and m.size == 5
    assert m.scale == f32(0.001)
    assert not m.valid[0, 0] and m.valid[1:, :].all() and m.valid[0, 1:].all()
    assert m.heights[0, 0] == 0.0 and m.albedo[0, 0] == 0.0
    assert m.heights[0, 1] == -15000 * m.hscale
    assert abs(m.heights[0, 1] - (-0.75)) < 1e-6
    assert m.albedo[0, 1] == 1.01
    assert m.heights[4, 0] == 30000 * m.hscale  # J=2, I=-2: h = 1.5 (the maximum)
    np.testing.assert_array_equal(m.rotation_map_to_body, [[0, 1, 0], [-1, 0, 0], [0, 0, 1]])
    assert m.side_km == pytest.approx(5 * 0.001, rel=1e-7)
    assert m.mapvers == 0 and m.sigma_km == f32(math.sqrt(3) * 0.001)


def test_spec_bytes_parse_to_listed_cells():
    """Parse the spec's bytes themselves (padded with zero cells) — independent of the writer."""
    data = SPEC_96 + bytes(216 - 96)
    m = parse_map(data)
    assert m.qsz == 2 and m.scale == f32(0.001)
    np.testing.assert_array_equal(m.v, [f32(0.1), f32(-0.2), f32(0.3)])
    np.testing.assert_array_equal(m.uy, [1, 0, 0])
    assert m.hscale == f32(5e-5)
    assert not m.valid[0, 0]
    assert m.valid[0, 1] and m.heights[0, 1] == -15000 * m.hscale and m.albedo[0, 1] == 1.01
    assert format_map(m) == data


# ---------------------------------------------------------------------------------------------
# cell order and axes
# ---------------------------------------------------------------------------------------------


def test_cell_order_j_outer_i_inner():
    q, n = 3, 7
    J, I = np.meshgrid(np.arange(-q, q + 1), np.arange(-q, q + 1), indexing="ij")
    h = 10.0 * J + I  # distinct per cell
    m = Maplet.new(0.01, q, (0, 0, 1), (1, 0, 0), (0, 1, 0), (0, 0, 1), h, np.ones((n, n)))
    data = format_map(m)
    hs = struct.unpack(">f", data[63:67])[0]
    for j in range(-q, q + 1):
        for i in range(-q, q + 1):
            k = (j + q) * n + (i + q)  # I varies fastest in the file
            hq, a = struct.unpack(">hB", data[72 + 3 * k : 75 + 3 * k])
            assert hq == nint(f32(f32(10.0 * j + i) / hs))
            assert a == 100
            # axis 0 = J (along UX), axis 1 = I (along UY)
            assert m.heights[j + q, i + q] == hq * hs


def test_new_fills_missing_with_zero_bytes_and_nonfinite_cells_missing():
    n = 3
    h = np.array([[1.0, np.nan, 2.0], [0.5, 0.0, -1.0], [3.0, 4.0, np.inf]])
    alb = np.ones((n, n))
    m = Maplet.new(0.01, 1, (0, 0, 1), (1, 0, 0), (0, 1, 0), (0, 0, 1), h, alb)
    assert m.valid.sum() == 7 and not m.valid[0, 1] and not m.valid[2, 2]
    data = format_map(m)
    assert data[72 + 3 : 75 + 3] == b"\0\0\0"
    assert data[72 + 24 : 72 + 27] == b"\0\0\0"


# ---------------------------------------------------------------------------------------------
# 2021-writer quantisation, computed independently
# ---------------------------------------------------------------------------------------------


def test_reencode_matches_independent_2021_rules():
    rng = np.random.default_rng(5)
    m = parse_map(format_map(random_maplet(rng, 4)))
    m.heights = m.heights * 3.7 + 0.1 * m.valid
    m.albedo = np.where(m.valid, rng.uniform(-0.5, 2.5, size=m.albedo.shape), 0.0)
    data = format_map(m)
    n = m.size
    valid = m.valid
    hmax = max(abs(f32(h)) for h in m.heights[valid])
    hs = f32(f32(hmax) / 30000.0)
    assert struct.unpack(">f", data[63:67])[0] == hs
    for k in range(n * n):
        r, c = divmod(k, n)
        hq, a = struct.unpack(">hB", data[72 + 3 * k : 75 + 3 * k])
        if valid[r, c]:
            assert hq == nint(f32(f32(m.heights[r, c]) / hs))
            assert a == min(199, max(1, nint(f32(100.0 * f32(m.albedo[r, c])))))
        else:
            assert (hq, a) == (0, 0)
    # header fields untouched
    assert data[:63] == m._header[:63] and data[67:72] == m._header[67:72]


def test_round_half_away_from_zero():
    # HSCALE = 2/30000; heights that are exact .5 multiples of HSCALE in float32
    hs = np.float32(np.float32(2.0) / np.float32(30000.0))
    half = [float(np.float32(k) * hs) for k in (2.5, -2.5, 0.5)]
    h = np.array([[2.0, half[0]], [half[1], half[2]]])
    # heights padded to a 3x3 grid (q=1)
    grid = np.zeros((3, 3))
    grid[:2, :2] = h
    m = Maplet.new(1.0, 1, (0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), grid, np.ones((3, 3)))
    data = format_map(m)
    assert struct.unpack(">f", data[63:67])[0] == float(hs)
    cells = [struct.unpack(">hB", data[72 + 3 * k : 75 + 3 * k])[0] for k in range(9)]
    q = [float(np.float32(x) / hs) for x in (h[0, 1], h[1, 0], h[1, 1])]
    assert [nint(x) for x in q] == [cells[1], cells[3], cells[4]]
    # the exact halves round away from zero (numpy.rint would give 2, -2, 0)
    assert q == [2.5, -2.5, 0.5]
    assert (cells[1], cells[3], cells[4]) == (3, -3, 1)
    assert cells[0] == 30000


def test_flat_map_hscale_guard():
    m = Maplet.new(0.01, 2, (0, 0, 1), (1, 0, 0), (0, 1, 0), (0, 0, 1), np.zeros((5, 5)), np.ones((5, 5)))
    assert m.hscale == f32(1.0 / 30000.0)
    assert np.all(m.heights == 0.0)
    none_valid = Maplet.new(
        0.01, 1, (0, 0, 1), (1, 0, 0), (0, 1, 0), (0, 0, 1), np.ones((3, 3)), np.ones((3, 3)),
        np.zeros((3, 3), bool),
    )
    assert none_valid.hscale == f32(1.0 / 30000.0) and not none_valid.valid.any()


def test_albedo_clip_and_mapvers_negative():
    alb = np.array([[0.0, 0.004, 0.006], [1.0, 1.994, 1.996], [5.0, -1.0, 0.5]])
    m = Maplet.new(0.01, 1, (0, 0, 1), (1, 0, 0), (0, 1, 0), (0, 0, 1), np.zeros((3, 3)), alb, mapvers=-1)
    assert m.valid.all()  # albedo 0 on a valid cell is stored as A=1, not as missing
    np.testing.assert_array_equal(m._a, [[1, 1, 1], [100, 199, 199], [199, 1, 50]])
    assert format_map(m)[71] == 255 and m.mapvers == 255


# ---------------------------------------------------------------------------------------------
# byte-exact rewrite
# ---------------------------------------------------------------------------------------------


def _raw_map(rng: np.random.Generator, q: int, junk_padding: bool) -> bytes:
    """A valid MAP with arbitrary unknown header bytes, arbitrary cells (incl. H != 0 with A = 0)."""
    n = 2 * q + 1
    head = bytearray(rng.integers(0, 256, 72, dtype=np.uint8).tobytes())
    head[6:10] = struct.pack(">f", float(rng.uniform(1e-4, 1)))
    head[10:12] = bytes([q & 0xFF, q >> 8])
    head[15:63] = struct.pack(">12f", *rng.normal(size=12))
    head[63:67] = struct.pack(">f", float(rng.uniform(1e-6, 1e-3)))
    cells = rng.integers(0, 256, 3 * n * n, dtype=np.uint8).tobytes()
    pad = map_file_size(q) - 72 - 3 * n * n
    tail = rng.integers(0, 256, pad, dtype=np.uint8).tobytes() if junk_padding else bytes(pad)
    return bytes(head) + cells + tail


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), q=st.integers(0, 5), junk=st.booleans())
def test_unchanged_parsed_map_is_byte_identical(seed, q, junk):
    data = _raw_map(np.random.default_rng(seed), q, junk)
    m = parse_map(data)
    assert m.qsz == q
    assert format_map(m) == data


def test_qsz1_padding_quirk_kept_then_zeroed_on_change():
    rng = np.random.default_rng(2)
    data = _raw_map(rng, 1, junk_padding=True)
    assert len(data) == 144 and data[72 + 27 :] != bytes(144 - 99)
    m = parse_map(data)
    assert format_map(m) == data
    m.albedo = m.albedo.copy()
    m.albedo[1, 1] = 1.23
    m.valid = m.valid.copy()
    m.valid[1, 1] = True
    new = format_map(m)
    assert new[72 + 27 :] == bytes(144 - 99)
    assert new[:72] == data[:72]  # no height change: HSCALE and header kept


def test_header_change_keeps_unknown_bytes_and_cells():
    rng = np.random.default_rng(3)
    data = _raw_map(rng, 3, junk_padding=True)
    m = parse_map(data)
    m.v = m.v + 1.0
    new = format_map(m)
    assert new[15:27] == struct.pack(">3f", *(f32(x) for x in m.v))
    keep = list(range(0, 15)) + list(range(27, 72))
    assert bytes(new[i] for i in keep) == bytes(data[i] for i in keep)
    assert new[72:] == data[72:]


def test_albedo_only_change_keeps_heights():
    rng = np.random.default_rng(4)
    m = parse_map(_raw_map(rng, 2, junk_padding=False))
    old = format_map(m)
    m.albedo = np.where(m.valid, 0.5, 0.0)
    new = format_map(m)
    assert new[63:67] == old[63:67]
    n = m.size
    for k in range(n * n):
        hq_old, a_old = struct.unpack(">hB", old[72 + 3 * k : 75 + 3 * k])
        hq_new, a_new = struct.unpack(">hB", new[72 + 3 * k : 75 + 3 * k])
        assert hq_new == hq_old
        assert a_new == (50 if a_old else 0)


def test_big_endian_qsz_fallback_reads_and_rewrites():
    rng = np.random.default_rng(8)
    data = bytearray(_raw_map(rng, 3, junk_padding=False))
    data[10:12] = bytes([0, 3])  # QSZ written big-endian
    m = parse_map(bytes(data))
    assert m.qsz == 3
    assert format_map(m) == bytes(data)


# ---------------------------------------------------------------------------------------------
# hypothesis round trips of new maplets
# ---------------------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), q=st.integers(0, 8), missing=st.floats(0.0, 1.0))
def test_new_maplet_bytes_maplet_identical(seed, q, missing):
    m = random_maplet(np.random.default_rng(seed), q, missing)
    data = format_map(m)
    assert len(data) == map_file_size(q)
    back = parse_map(data)
    assert back == m
    assert format_map(back) == data
    # what the file stores is what the maplet says
    n = m.size
    cells = np.frombuffer(data, dtype=[("h", ">i2"), ("a", "u1")], count=n * n, offset=72).reshape(n, n)
    np.testing.assert_array_equal(cells["a"] != 0, m.valid)
    np.testing.assert_array_equal(np.where(m.valid, cells["h"] * m.hscale, 0.0), m.heights)
    np.testing.assert_array_equal(cells["a"] / 100.0, m.albedo)
    assert np.all(np.abs(cells["h"]) <= 30000)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), q=st.integers(1, 6))
def test_changed_heights_reencode_close_to_requested(seed, q):
    rng = np.random.default_rng(seed)
    m = parse_map(format_map(random_maplet(rng, q)))
    target = rng.normal(scale=5.0, size=m.heights.shape)
    m.heights = np.where(m.valid, target, 0.0)
    back = parse_map(format_map(m))
    if m.valid.any():
        tol = back.hscale * 0.5 * (1 + 1e-5) + np.abs(target) * 2e-7
        assert np.all(np.abs(back.heights - m.heights)[m.valid] <= tol[m.valid])
    np.testing.assert_array_equal(back.valid, m.valid)


# ---------------------------------------------------------------------------------------------
# malformed input
# ---------------------------------------------------------------------------------------------


def _good() -> bytes:
    return format_map(random_maplet(np.random.default_rng(11), 4))


def test_truncated_file(tmp_path):
    p = tmp_path / "TRUNC1.MAP"
    data = _good()
    p.write_bytes(data[: len(data) - 72])
    with pytest.raises(SpcFormatError) as e:
        read_map(p)
    s = str(e.value)
    assert str(p) in s and f"byte {len(data) - 72}" in s and str(len(data)) in s and "truncated" in s


def test_longer_file_and_short_last_record_are_read():
    # READ_MAP (xCommon.f) reads records 1..N with READ(20,REC=NREC): bytes after record N are never read,
    # and gfortran reads a short last record zero-padded (oracle: ios 0) -- both load, with a warning
    good = _good()
    longer = parse_map(good + b"\0" * 10, "X.MAP")
    assert longer == parse_map(good, "X.MAP")
    assert "not read by READ_MAP" in longer.__dict__["_spc_warnings"][0][1]
    n = 2 * parse_map(good).qsz + 1
    short = parse_map(good[: 72 + 3 * n * n], "S.MAP")
    assert short == parse_map(good, "S.MAP") and "not padded" in short.__dict__["_spc_warnings"][0][1]
    with pytest.raises(SpcFormatError, match="S.MAP:byte"):
        parse_map(good[: 72 + 3 * n * n - 1], "S.MAP")  # a cell missing: READ_MAP would hit end of file


def test_qsz_inconsistent_with_size():
    data = bytearray(_good())  # q = 4: 81 cells, 4 data records
    data[10] = 9  # q = 9 would need 17 data records -> but the file is 5 records
    data2 = bytearray(data)
    with pytest.raises(SpcFormatError) as e:
        parse_map(bytes(data), "Q.MAP")
    assert "Q.MAP:byte" in str(e.value) and "QSZ=9" in str(e.value)
    data2[10] = 1  # q = 1: READ_MAP reads records 1-2 only, as a 3x3 maplet; the rest is warned about
    m = parse_map(bytes(data2), "Q.MAP")
    assert m.qsz == 1 and m.__dict__["_spc_warnings"]


def test_short_header_double_and_bad_floats():
    with pytest.raises(SpcFormatError, match="byte 30"):
        parse_map(b"\0" * 30, "S.MAP")
    data = bytearray(_good())
    giant = b"DOUBLE" + bytes(data[6:])
    with pytest.raises(SpcFormatError, match="DOUBLE"):
        parse_map(giant, "G.MAP")
    bad = bytearray(data)
    bad[6:10] = struct.pack(">f", float("nan"))
    with pytest.raises(SpcFormatError, match="byte 6"):
        parse_map(bytes(bad), "N.MAP")
    bad = bytearray(data)
    bad[31:35] = struct.pack(">f", float("inf"))
    with pytest.raises(SpcFormatError, match="byte 27.*UX"):
        parse_map(bytes(bad), "N.MAP")
    bad = bytearray(data)
    bad[6:10] = struct.pack(">f", -1.0)
    with pytest.raises(SpcFormatError, match="SCALE"):
        parse_map(bytes(bad), "R.MAP")


# ---------------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------------


def test_read_maps_equals_read_map(tmp_path):
    rng = np.random.default_rng(12)
    paths = []
    for k in range(9):
        q = [1, 2, 4][k % 3]
        p = tmp_path / f"AB{k:04d}.MAP"
        write_map(p, random_maplet(rng, q))
        paths.append(p)
    many = read_maps(paths)
    one = [read_map(p) for p in paths]
    assert [m.name for m in many] == [f"AB{k:04d}" for k in range(9)]
    for a, b, p in zip(many, one, paths):
        assert a == b
        assert format_map(a) == p.read_bytes()
    bad = tmp_path / "BAD.MAP"
    bad.write_bytes(p.read_bytes()[:72])  # header only: no cells
    with pytest.raises(SpcFormatError, match="BAD.MAP"):
        read_maps(paths + [bad])


def test_write_map_overwrite_and_backup(tmp_path):
    rng = np.random.default_rng(13)
    p = tmp_path / "MAPFILES" / "CC0001.MAP"
    a, b = random_maplet(rng, 2), random_maplet(rng, 2)
    write_map(p, a)
    assert read_map(p).name == "CC0001"
    with pytest.raises(SpcUsageError):
        write_map(p, b, overwrite=False)
    kept = write_map(p, b, backup=True)
    assert kept is not None and kept.read_bytes() == format_map(a)
    assert p.read_bytes() == format_map(b)


def test_geometry_recipe_with_rotation():
    """P[r,c] = V + SCALE((r-q)UX + (c-q)UY + h UZ): the body point of cell (J,I) is V + s·R·(J, I, h)."""
    rng = np.random.default_rng(14)
    m = random_maplet(rng, 3)
    R = m.rotation_map_to_body
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-6)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-6)
    q = m.qsz
    r, c = 1, 5
    p = m.v + m.scale * ((r - q) * m.ux + (c - q) * m.uy + m.heights[r, c] * m.uz)
    p2 = m.v + m.scale * R @ np.array([r - q, c - q, m.heights[r, c]])
    np.testing.assert_allclose(p, p2, rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# lazy grids, direct construction
# ---------------------------------------------------------------------------------------------


def test_grids_decode_lazily_and_changes_are_seen(tmp_path):
    rng = np.random.default_rng(21)
    p = tmp_path / "LZ0001.MAP"
    p.write_bytes(_raw_map(rng, 3, junk_padding=True))
    m = read_map(p)
    assert m.__dict__.get("heights") is None  # header only so far
    assert format_map(m) == p.read_bytes()  # fast path, no decode
    cell_dtype = [("h", ">i2"), ("a", "u1")]
    cells = np.frombuffer(p.read_bytes(), dtype=cell_dtype, count=49, offset=72).reshape(7, 7)
    hs = struct.unpack(">f", p.read_bytes()[63:67])[0]
    np.testing.assert_array_equal(m.valid, cells["a"] != 0)
    np.testing.assert_array_equal(m.heights, np.where(cells["a"] != 0, cells["h"] * hs, 0.0))
    np.testing.assert_array_equal(m.albedo, cells["a"] / 100.0)
    assert format_map(m) == p.read_bytes()  # decoded but unchanged: still byte-identical
    m.valid[2, 3] = True
    m.heights[2, 3] += 2.0  # in-place edit of the decoded array
    new = parse_map(format_map(m))
    assert new.valid[2, 3]
    assert abs(new.heights[2, 3] - m.heights[2, 3]) <= new.hscale
    assert dataclasses.replace(m, name="OTHER").name == "OTHER"


def test_hscale_only_change_is_honoured():
    rng = np.random.default_rng(22)
    data = _raw_map(rng, 2, junk_padding=False)
    m = parse_map(data)
    old_hs = m.hscale
    m.hscale = old_hs * 4  # before the grids are read: they still decode with the stored HSCALE
    assert np.all(m.heights == np.where(m.valid, m._h * old_hs, 0.0))
    out = format_map(m)
    assert struct.unpack(">f", out[63:67])[0] == f32(old_hs * 4)
    back = parse_map(out)
    for r in range(5):
        for c in range(5):
            if m.valid[r, c]:
                assert back._h[r, c] == nint(f32(f32(m.heights[r, c]) / f32(old_hs * 4)))


def test_direct_construction_without_raw():
    n = 3
    h = np.array([[0.0, 1.0, -2.0], [0.5, 0.25, 0.0], [3.0, 0.0, 0.0]])
    m = Maplet(
        scale=0.002, qsz=1, v=np.zeros(3), ux=np.array([1.0, 0, 0]), uy=np.array([0, 1.0, 0]),
        uz=np.array([0, 0, 1.0]), hscale=0.0, heights=h, albedo=np.full((n, n), 1.2),
        valid=np.ones((n, n), bool), name="DIRECT",
    )
    data = format_map(m)
    assert data[:6] == bytes(6) and data[12:15] == bytes(3) and data[67:72] == bytes(5)
    back = parse_map(data, name="DIRECT")
    assert back.hscale == f32(f32(3.0) / 30000.0)
    np.testing.assert_allclose(back.heights, h, atol=back.hscale / 2)
    np.testing.assert_array_equal(back.albedo, 1.2)
    with pytest.raises(ValueError):
        Maplet.new(0.01, 1, (0, 0, 1), (1, 0, 0), (0, 1, 0), (0, 0, 1), np.zeros((5, 5)), np.ones((5, 5)))
