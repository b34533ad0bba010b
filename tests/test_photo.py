"""Tests of spctool.formats.photo: pixel convention, FITS/PGM/PNG/DAT, byte-order detection.

Spec: spc-formats.md §0.4, §7.4, §8 items 12-13; cli-contract.md "Pixel convention".
Files are built independently (raw bytes, astropy, pillow) wherever the reader is tested.
"""

from __future__ import annotations

import io
import warnings

import numpy as np
import pytest
from astropy.io import fits
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from PIL import Image

from spctool.errors import SpcFormatError, SpcUsageError
from spctool.formats.photo import (
    Photo,
    SpcDatWarning,
    dat_byte_plane_energies,
    detect_dat_byte_order,
    format_photo,
    index_to_spc,
    read_dat,
    read_photo,
    spc_to_index,
    write_photo,
)

# ---------------------------------------------------------------------------------------------
# pixel convention
# ---------------------------------------------------------------------------------------------


def test_spc_to_index_and_back():
    assert spc_to_index(1, 1) == (0.0, 0.0)
    row, col = spc_to_index(512.5, 512.5)  # centre of a 1024x1024 frame (§0.4)
    assert (row, col) == (511.5, 511.5)
    row, col = spc_to_index(sample=7, line=3)
    assert (row, col) == (2.0, 6.0)  # line -> row, sample -> col
    assert index_to_spc(2.0, 6.0) == (7.0, 3.0)


@settings(max_examples=50, deadline=None)
@given(
    s=st.floats(-1e6, 1e6, allow_nan=False),
    ln=st.floats(-1e6, 1e6, allow_nan=False),
)
def test_pixel_helpers_inverse(s, ln):
    r, c = spc_to_index(s, ln)
    s2, l2 = index_to_spc(r, c)
    assert s2 == pytest.approx(s, abs=1e-9) and l2 == pytest.approx(ln, abs=1e-9)
    assert c == pytest.approx(s - 1, abs=1e-9) and r == pytest.approx(ln - 1, abs=1e-9)


def test_pixel_helpers_vectorised():
    r, c = spc_to_index(np.array([1.0, 2.5]), np.array([10.0, 20.0]))
    np.testing.assert_array_equal(r, [9.0, 19.0])
    np.testing.assert_array_equal(c, [0.0, 1.5])


def test_photo_dn_and_properties():
    data = np.arange(12, dtype=np.uint16).reshape(3, 4)  # NLN=3, NPX=4
    p = Photo(data, name="P1")
    assert (p.npx, p.nln, p.bits) == (4, 3, 16)
    assert p.dn(1, 1) == 0 and p.dn(4, 1) == 3 and p.dn(1, 3) == 8 and p.dn(4, 3) == 11
    np.testing.assert_array_equal(p.dn(np.array([2, 3]), np.array([2, 3])), [5, 10])
    with pytest.raises(IndexError):
        p.dn(5, 1)
    with pytest.raises(ValueError):
        Photo(np.zeros((2, 2), np.int32))
    with pytest.raises(ValueError):
        Photo(np.zeros((2, 2), np.uint8), bits=16)
    assert Photo(np.zeros((2, 2), np.float32)).bits == 32
    assert Photo(np.zeros((2, 2), ">u2")).data.dtype == np.uint16  # native order


# ---------------------------------------------------------------------------------------------
# DAT
# ---------------------------------------------------------------------------------------------


def smooth_image(nln: int, npx: int, lo: int = 1000, hi: int = 60000) -> np.ndarray:
    """A smooth 16-bit scene: gradients and broad bumps (little high-frequency energy)."""
    y, x = np.mgrid[0:nln, 0:npx].astype(float)
    z = 0.5 + 0.25 * np.sin(x / 17.0) * np.cos(y / 23.0) + 0.2 * (x / npx) - 0.1 * (y / nln)
    z = (z - z.min()) / (z.max() - z.min())
    return np.round(lo + (hi - lo) * z).astype(np.uint16)


def test_dat_first_record_is_line_1(tmp_path):
    data = np.arange(6 * 5, dtype=np.uint8).reshape(6, 5)
    p = tmp_path / "PIC.DAT"
    p.write_bytes(data.tobytes())  # record 1 = bytes 0..4
    ph = read_photo(p, npx=5, nln=6)
    assert ph.name == "PIC" and ph.data.dtype == np.uint8 and ph.bits == 8
    assert ph.dn(1, 1) == 0 and ph.dn(5, 1) == 4 and ph.dn(1, 2) == 5
    flipped = read_photo(p, npx=5, nln=6, flip_rows=True)
    np.testing.assert_array_equal(flipped.data, data[::-1])
    assert flipped.dn(1, 1) == data[5, 0]


@pytest.mark.parametrize("order", [">u2", "<u2"])
def test_dat_byte_order_detection_smooth_image(tmp_path, order):
    img = smooth_image(300, 420)
    p = tmp_path / "IMG.DAT"
    p.write_bytes(img.astype(order).tobytes())
    expect = "big" if order == ">u2" else "little"
    assert detect_dat_byte_order(p.read_bytes(), npx=420, nln=300) == expect
    ph = read_dat(p, 420, 300)
    assert ph.data.dtype == np.uint16
    np.testing.assert_array_equal(ph.data, img)
    # an explicit override wins: reading with the wrong order gives byte-swapped DN
    wrong = "little" if expect == "big" else "big"
    np.testing.assert_array_equal(read_dat(p, 420, 300, byte_order=wrong).data, img.byteswap())
    np.testing.assert_array_equal(read_photo(p, npx=420, nln=300, byte_order=expect).data, img)


def test_byte_order_energies_match_fortran_transcription():
    """Brute-force transcription of SPC xPicInpt's loops (1-based, integer division).

    Sizes >= 195 keep SPC's grid one pixel inside the image (no clipping needed).
    """
    rng = np.random.default_rng(0)
    nln, npx = 203, 236
    img = (smooth_image(nln, npx) + rng.integers(0, 40, (nln, npx))).astype(np.uint16)
    raw = img.astype(">u2").tobytes()
    inline = [raw[2 * npx * j : 2 * npx * (j + 1)] for j in range(nln)]  # records 1..NLN -> 0..NLN-1
    z1 = z2 = 0
    for i1 in range(1, 100, 2):
        for j1 in range(1, 100, 2):
            i = (5 + i1 * npx) // 100
            j = (5 + j1 * nln) // 100
            d1, d2 = {}, {}
            for i2 in (-1, 0, 1):
                for j2 in (-1, 0, 1):
                    rec = inline[j + j2 - 1]
                    d1[i2, j2] = rec[2 * (i + i2) - 2]  # inline(2*(i+i2)-1), 1-based
                    d2[i2, j2] = rec[2 * (i + i2) - 1]  # inline(2*(i+i2))
            z1 += (4 * d1[0, 0] - d1[-1, 0] - d1[1, 0] - d1[0, -1] - d1[0, 1]) ** 2
            z2 += (4 * d2[0, 0] - d2[-1, 0] - d2[1, 0] - d2[0, -1] - d2[0, 1]) ** 2
    planes = np.frombuffer(raw, np.uint8).reshape(nln, npx, 2)
    assert dat_byte_plane_energies(planes) == (z1, z2)
    assert z2 > z1  # big-endian: the second byte is the noisy low byte
    assert detect_dat_byte_order(planes) == "big"
    assert detect_dat_byte_order(planes.reshape(nln, 2 * npx)) == "big"


def test_byte_order_small_and_flat_images():
    assert detect_dat_byte_order(np.zeros((2, 8), np.uint8)) == "big"
    assert detect_dat_byte_order(np.full((10, 10, 2), 7, np.uint8)) == "big"
    img = smooth_image(20, 24)  # smaller than the 100-pixel grid: clipped inside
    assert detect_dat_byte_order(img.astype("<u2").tobytes(), 24, 20) == "little"
    assert detect_dat_byte_order(img.astype(">u2").tobytes(), 24, 20) == "big"


def test_dat_size_rule(tmp_path):
    # xPicInpt: READ(10,REC=NLN,ERR=20) with RECL=2*NPX picks 16 bits when record NLN has a byte in the
    # file (gfortran zero-pads a short last record), else 8 bits; bytes after the image are never read
    p = tmp_path / "BAD.DAT"
    p.write_bytes(bytes(range(5 * 4)) + b"xyz")
    photo = read_dat(p, 5, 4)
    assert photo.data.dtype == np.uint8 and photo.data[3, 4] == 19 and photo.__dict__["_spc_warnings"]
    p.write_bytes(bytes(2 * 5 * 3 + 1))
    assert read_dat(p, 5, 4).data.dtype == np.uint16  # one byte into record 4: 16-bit, zero-padded
    p.write_bytes(bytes(5 * 3))
    with pytest.raises(SpcFormatError) as e:
        read_dat(p, 5, 4)
    s = str(e.value)
    assert "BAD.DAT" in s and "20" in s and "40" in s and "15" in s
    with pytest.raises(SpcUsageError):
        read_photo(p)  # .DAT without NPX/NLN
    with pytest.raises(SpcUsageError):
        read_dat(p, 5, 4, byte_order="middle")


def test_dat_writer_big_endian(tmp_path):
    img = np.array([[1, 256], [513, 65535]], np.uint16)
    p = tmp_path / "W.DAT"
    write_photo(p, Photo(img))
    assert p.read_bytes() == bytes([0, 1, 1, 0, 2, 1, 255, 255])
    with pytest.raises(SpcUsageError):
        write_photo(tmp_path / "F.DAT", Photo(np.zeros((2, 2), np.float32)))


# ---------------------------------------------------------------------------------------------
# PGM
# ---------------------------------------------------------------------------------------------


def test_pgm_8bit_writer_follows_raw2pgm(tmp_path):
    img = np.arange(6, dtype=np.uint8).reshape(2, 3)
    p = tmp_path / "D.pgm"
    write_photo(p, Photo(img))
    assert p.read_bytes() == b"P5\n#.\n3 2\n255\n" + bytes([0, 1, 2, 3, 4, 5])


def test_pgm_16bit_is_big_endian(tmp_path):
    img = np.array([[1, 258]], np.uint16)
    p = tmp_path / "D16.pgm"
    write_photo(p, Photo(img))
    assert p.read_bytes() == b"P5\n#.\n2 1\n65535\n" + bytes([0, 1, 1, 2])
    # pillow reads it back the same way (independent reader)
    with Image.open(p) as im:
        np.testing.assert_array_equal(np.asarray(im).astype(np.uint16), img)


def test_pgm_reader_comments_maxval_and_plain(tmp_path):
    p = tmp_path / "c.pgm"
    raster = np.array([[0, 4095], [17, 300]], ">u2").tobytes()
    p.write_bytes(b"P5 # a comment\n# another\n2\t2\n4095\n" + raster)
    ph = read_photo(p)
    assert ph.data.dtype == np.uint16
    np.testing.assert_array_equal(ph.data, [[0, 4095], [17, 300]])
    p2 = tmp_path / "plain.pgm"
    p2.write_bytes(b"P2\n# plain\n3 2\n255\n0 1 2\n# mid\n3 4 255\n")
    ph2 = read_photo(p2)
    assert ph2.data.dtype == np.uint8
    np.testing.assert_array_equal(ph2.data, [[0, 1, 2], [3, 4, 255]])


@pytest.mark.parametrize(
    "content, where",
    [
        (b"P5\n4 4\n255\n" + bytes(10), "byte 21"),  # truncated raster
        (b"P5\n4 x\n255\n" + bytes(16), "byte 5"),  # bad height
        (b"P5\n2 1\n100\n" + bytes([5, 101]), "byte 12"),  # value above maxval (2nd pixel)
        (b"P5\n2 1\n70000\n" + bytes(4), "byte 7"),  # maxval out of range
        (b"P2\n2 2\n255\n1 2 3\n", "byte 17"),  # too few plain values (end of file)
        (b"P6\n2 2\n255\n" + bytes(12), "byte 0"),  # colour PPM
    ],
)
def test_pgm_corrupt(tmp_path, content, where):
    p = tmp_path / "bad.pgm"
    p.write_bytes(content)
    with pytest.raises(SpcFormatError) as e:
        read_photo(p)
    assert f"bad.pgm:{where}" in str(e.value)


# ---------------------------------------------------------------------------------------------
# PNG and FITS
# ---------------------------------------------------------------------------------------------


def test_png_rows_and_depths(tmp_path):
    img16 = np.array([[0, 1000], [40000, 65535], [7, 8]], np.uint16)
    p = tmp_path / "a.png"
    Image.fromarray(img16).save(p)  # written by pillow, read by us
    ph = read_photo(p)
    assert ph.data.dtype == np.uint16 and ph.dn(2, 2) == 65535 and ph.nln == 3
    rgb = tmp_path / "rgb.png"
    Image.new("RGB", (3, 2)).save(rgb)
    with pytest.raises(SpcFormatError, match="grayscale"):
        read_photo(rgb)
    trunc = tmp_path / "t.png"
    buf = io.BytesIO()
    Image.fromarray(smooth_image(50, 60)).save(buf, format="PNG")
    trunc.write_bytes(buf.getvalue()[: len(buf.getvalue()) // 2])
    with pytest.raises(SpcFormatError, match="t.png"):
        read_photo(trunc)


def test_fits_row0_is_line1_and_header(tmp_path):
    img = np.arange(12, dtype=np.float32).reshape(3, 4)
    p = tmp_path / "f.fits"
    fits.PrimaryHDU(img).writeto(p)  # written by astropy
    ph = read_photo(p)
    assert ph.data.dtype == np.float32 and ph.dn(1, 1) == 0.0 and ph.dn(4, 3) == 11.0
    np.testing.assert_array_equal(read_photo(p, flip_rows=True).data, img[::-1])
    out = tmp_path / "o.fits"
    cards = {"PICTURE": "P0001", "LMK": ("AB0001", "name")}
    write_photo(out, Photo(img.astype(np.uint16) * 5000), header=cards)
    with fits.open(out) as hl:
        assert hl[0].header["PICTURE"] == "P0001" and hl[0].header.comments["LMK"] == "name"
        assert hl[0].header["BITPIX"] == 16 and hl[0].header["BZERO"] == 32768
        np.testing.assert_array_equal(hl[0].data, img.astype(np.uint16) * 5000)


def test_fits_extension_signed_and_3d(tmp_path):
    p = tmp_path / "e.fits"
    signed = np.array([[-5, 3], [100, 0]], np.int16)
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(signed)]).writeto(p)
    ph = read_photo(p)
    assert ph.data.dtype == np.float32
    np.testing.assert_array_equal(ph.data, signed)
    p2 = tmp_path / "pos.fits"
    fits.PrimaryHDU(np.array([[[5, 3], [100, 0]]], np.int16)).writeto(p2)
    ph2 = read_photo(p2)
    assert ph2.data.dtype == np.uint16 and ph2.data.shape == (2, 2)
    p3 = tmp_path / "trunc.fits"
    p3.write_bytes((tmp_path / "pos.fits").read_bytes()[:2884])  # inside the 8 data bytes
    with pytest.raises(SpcFormatError, match="trunc.fits"):
        read_photo(p3)
    p4 = tmp_path / "nodata.fits"
    fits.PrimaryHDU().writeto(p4)
    with pytest.raises(SpcFormatError, match="2-D"):
        read_photo(p4)


def test_unknown_content(tmp_path):
    p = tmp_path / "x.bin"
    p.write_bytes(b"hello world")
    with pytest.raises(SpcFormatError, match="byte 0"):
        read_photo(p)
    with pytest.raises(SpcUsageError):
        write_photo(tmp_path / "x.jpg", Photo(np.zeros((2, 2), np.uint8)))
    # a raw file with another extension is read as DAT when NPX/NLN are given
    p.write_bytes(bytes(range(6)))
    np.testing.assert_array_equal(read_photo(p, npx=3, nln=2).data, [[0, 1, 2], [3, 4, 5]])


# ---------------------------------------------------------------------------------------------
# hypothesis round trips: every format, both bit depths (and floats in FITS)
# ---------------------------------------------------------------------------------------------

_shape = st.tuples(st.integers(1, 12), st.integers(1, 12))


@settings(max_examples=25, deadline=None)
@given(
    data=st.one_of(
        hnp.arrays(np.uint8, _shape),
        hnp.arrays(np.uint16, _shape),
    ),
    fmt=st.sampled_from(["dat", "pgm", "png", "fits"]),
    flip=st.booleans(),
)
def test_roundtrip_integer_formats(tmp_path_factory, data, fmt, flip):
    d = tmp_path_factory.mktemp("rt")
    p = d / f"PIC.{fmt}"
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        write_photo(p, Photo(data), flip_rows=flip)
    # random 16-bit DNs can look byte-swapped to SPC's test: the DAT writer says so, and only that
    assert all(issubclass(w.category, SpcDatWarning) and "byte-order" in str(w.message) for w in said)
    assert not said or (fmt == "dat" and data.dtype == np.uint16)
    nln, npx = data.shape
    order = "big" if fmt == "dat" and data.dtype == np.uint16 else "auto"  # tiny random images: no detection
    back = read_photo(p, npx=npx, nln=nln, flip_rows=flip, byte_order=order)
    if fmt == "dat" and data.size and int(data.max()) <= 255:
        data = data.astype(np.uint8)  # the DAT writer writes 8-bit when the DNs fit (SPC's record test)
    assert back.data.dtype == data.dtype and back.bits == 8 * data.dtype.itemsize
    np.testing.assert_array_equal(back.data, data)
    assert back == Photo(data, name="PIC")
    plain = read_photo(p, npx=npx, nln=nln, byte_order=order)
    np.testing.assert_array_equal(plain.data, data[::-1] if flip else data)


@settings(max_examples=25, deadline=None)
@given(data=st.one_of(hnp.arrays(np.float32, _shape), hnp.arrays(np.float64, _shape)))
def test_roundtrip_fits_floats(data):
    raw = format_photo(Photo(data), "fits")
    with fits.open(io.BytesIO(raw)) as hl:
        np.testing.assert_array_equal(hl[0].data, data)  # astropy agrees, incl. NaN/inf
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "F.fits"
        p.write_bytes(raw)
        back = read_photo(p)
    assert back.data.dtype == data.dtype
    assert back == Photo(data, name="F")


@settings(max_examples=15, deadline=None)
@given(lo=st.integers(0, 2000), span=st.integers(3000, 60000), seed=st.integers(0, 1000))
def test_roundtrip_dat_16bit_autodetect(tmp_path_factory, lo, span, seed):
    rng = np.random.default_rng(seed)
    img = smooth_image(60, 80, lo, lo + span) + rng.integers(0, 3, (60, 80)).astype(np.uint16)
    p = tmp_path_factory.mktemp("dat") / "S.DAT"
    write_photo(p, Photo(img))
    back = read_photo(p, npx=80, nln=60)  # auto byte order
    np.testing.assert_array_equal(back.data, img)


def test_write_photo_overwrite_and_backup(tmp_path):
    p = tmp_path / "IMAGEFILES" / "P1.DAT"
    a = Photo(np.full((2, 3), 7, np.uint8))
    b = Photo(np.full((2, 3), 9, np.uint8))
    write_photo(p, a)
    with pytest.raises(SpcUsageError):
        write_photo(p, b, overwrite=False)
    kept = write_photo(p, b, backup=True)
    assert kept.read_bytes() == bytes([7] * 6) and p.read_bytes() == bytes([9] * 6)
    # a bare array is accepted, and fmt= overrides the extension
    write_photo(tmp_path / "raw.bin", np.arange(4, dtype=np.uint8).reshape(2, 2), fmt="pgm")
    assert read_photo(tmp_path / "raw.bin").dn(2, 2) == 3
