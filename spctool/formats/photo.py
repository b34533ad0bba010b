"""Photos: the pixel arrays of pictures, in FITS, PGM, PNG and SPC ``.DAT`` form.

Specification: ``spc-formats.md`` §0.4 (pixels), §7.4 (``IMAGEFILES/<PICNM>.DAT``:
size rule, Laplacian byte-order detection, RAW2PGM header), §8 items 12–13, the
DAT checklist of §9, and ``cli-contract.md`` "Pixel convention".

Pixel convention
----------------
A :class:`Photo` holds ``data`` with shape ``(NLN, NPX)`` and SPC's 1-based
pixel coordinates ``(sample, line)`` with pixel centres at integers:

* ``data[line - 1, sample - 1]`` is the DN of pixel (sample, line);
* line 1 is the **first stored row** of every format: the first record of a
  ``.DAT``, the first raster row of a PGM or PNG, and row 0 of a FITS data
  array (whatever a FITS viewer shows, which usually puts row 0 at the bottom);
* sample 1 is the first stored column;
* a continuous position converts as ``x_spc = x_py + 1``:
  :func:`spc_to_index` gives the 0-based (row, col) of (sample, line) and
  :func:`index_to_spc` the inverse.

Photos stored bottom-up relative to SPC's line order are read (and written)
with ``flip_rows=True``, the explicit, tested option asked for by §7.4's
"orientation trap".

DN types: ``uint8`` (8-bit), ``uint16`` (16-bit stays 16-bit, unsigned, §8
item 12), ``float32`` (FITS only) and ``float64`` (FITS BITPIX −64 or integer
FITS beyond 16 bits).  DN = 0 means "no data" to SPC's sampler; that is the
sampler's business, not this module's.

``.DAT`` files are headerless: NPX and NLN come from the SUM; the pixel size is
2 bytes when the file holds NLN records of 2·NPX bytes, 1 byte when it holds
NLN records of NPX bytes (anything else is an error here); the 16-bit byte
order is detected with SPC's Laplacian-energy test (``xPicInpt``) unless given.
16-bit ``.DAT`` files are written big-endian (MSB first, SPC's normal).
"""

from __future__ import annotations

import io
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spctool.errors import SpcFormatError, SpcUsageError
from spctool.formats.atomic import write_bytes

_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32), np.dtype(np.float64))
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_FITS_SIGNATURE = b"SIMPLE  ="
_WHITESPACE = b" \t\n\r\v\f"
_EXT_FORMAT = {
    ".fits": "fits",
    ".fit": "fits",
    ".fts": "fits",
    ".pgm": "pgm",
    ".png": "png",
    ".dat": "dat",
}


# ----------------------------------------------------------------------------------------------
# pixel convention
# ----------------------------------------------------------------------------------------------


def spc_to_index(sample, line):
    """0-based array position (row, col) of SPC pixel coordinates (sample, line).

    ``row = line − 1``, ``col = sample − 1`` (floats; arrays broadcast).  SPC's pixel
    (1, 1) is ``data[0, 0]``; (sample, line) = (1.5, 1) lies halfway between
    ``data[0, 0]`` and ``data[0, 1]``.
    """
    line = np.asarray(line, dtype=np.float64)
    sample = np.asarray(sample, dtype=np.float64)
    return line - 1.0, sample - 1.0


def index_to_spc(row, col):
    """SPC pixel coordinates (sample, line) of a 0-based array position (row, col).

    ``sample = col + 1``, ``line = row + 1``; the inverse of :func:`spc_to_index`.
    """
    row = np.asarray(row, dtype=np.float64)
    col = np.asarray(col, dtype=np.float64)
    return col + 1.0, row + 1.0


# ----------------------------------------------------------------------------------------------
# the dataclass
# ----------------------------------------------------------------------------------------------


@dataclass(eq=False)
class Photo:
    """A photo's pixel array in SPC order: ``data[line − 1, sample − 1]`` (module docstring).

    ``bits`` is the bit size of one stored DN: 8 (uint8), 16 (uint16), 32 (float32)
    or 64 (float64); it is derived from ``data`` when not given.
    """

    data: np.ndarray
    name: str = ""
    bits: int = 0

    def __post_init__(self) -> None:
        data = np.asarray(self.data)
        if data.ndim != 2:
            raise ValueError(f"photo data must be 2-D (NLN, NPX), got shape {data.shape}")
        if data.dtype.newbyteorder("=") not in _DTYPES:
            raise ValueError(f"photo data must be uint8, uint16, float32 or float64, got {data.dtype}")
        if not data.dtype.isnative:
            data = data.astype(data.dtype.newbyteorder("="))
        self.data = data
        bits = 8 * data.dtype.itemsize
        if self.bits == 0:
            self.bits = bits
        elif self.bits != bits:
            raise ValueError(f"bits={self.bits} does not match data type {data.dtype}")

    @property
    def npx(self) -> int:
        """Samples per line (number of columns)."""
        return int(self.data.shape[1])

    @property
    def nln(self) -> int:
        """Number of lines (rows)."""
        return int(self.data.shape[0])

    def dn(self, sample, line):
        """DN at integer SPC pixel(s) (sample, line), 1-based: ``data[line − 1, sample − 1]``."""
        s = np.asarray(sample)
        ln = np.asarray(line)
        if s.dtype.kind not in "iu" or ln.dtype.kind not in "iu":
            raise TypeError("dn() takes integer sample and line (use a sampler for fractional pixels)")
        if np.any((s < 1) | (s > self.npx) | (ln < 1) | (ln > self.nln)):
            raise IndexError(f"pixel outside the photo (1..{self.npx}, 1..{self.nln})")
        return self.data[ln - 1, s - 1]

    def flipped(self) -> Photo:
        """The same photo with the line order reversed (line 1 ↔ line NLN)."""
        return Photo(np.ascontiguousarray(self.data[::-1]), name=self.name)

    def __eq__(self, other) -> bool:
        if not isinstance(other, Photo):
            return NotImplemented
        return (
            self.name == other.name
            and self.data.dtype == other.data.dtype
            and self.data.shape == other.data.shape
            and np.array_equal(self.data, other.data, equal_nan=self.data.dtype.kind == "f")
        )

    __hash__ = None  # mutable array


# ----------------------------------------------------------------------------------------------
# DAT
# ----------------------------------------------------------------------------------------------


def _normalise_order(byte_order: str | None) -> str:
    key = "auto" if byte_order is None else str(byte_order).strip().lower()
    if key == "auto":
        return "auto"
    if key in ("big", "msb", ">", "be"):
        return "big"
    if key in ("little", "lsb", "<", "le"):
        return "little"
    raise SpcUsageError(f"byte order must be auto, big or little, not {byte_order!r}")


def _grid(n: int) -> np.ndarray:
    """SPC's 50 sample positions along an axis of n pixels, 0-based, kept one pixel inside.

    xPicInpt uses i = (5 + i1·n)/100 (integer division, 1-based) for i1 = 1, 3, …, 99.
    The clip only matters for axes under 195 pixels (and i1 = 99 never reaches n),
    where SPC itself would read outside the image.
    """
    k = np.arange(1, 100, 2)
    i = (5 + k * n) // 100
    return np.clip(i, 2, n - 1) - 1


def detect_dat_byte_order(raw, npx: int | None = None, nln: int | None = None) -> str:
    """Byte order of a 16-bit raw image by SPC's Laplacian-energy test (§7.4, §8 item 13).

    ``raw``: the file bytes (give ``npx`` and ``nln``), or a uint8 array of shape
    (NLN, NPX, 2) or (NLN, 2·NPX).  At SPC's 50×50 grid the squared discrete
    Laplacian 4·c − (4 neighbours) is summed over the first byte of each pixel
    (z1) and over the second (z2); the plane with more high-frequency energy is
    the low-order byte: z1 > z2 → ``"little"``, z2 > z1 → ``"big"``.  A tie (e.g. a
    flat image, or an image under 3×3) gives ``"big"``, SPC's normal order.
    """
    if isinstance(raw, bytes | bytearray | memoryview):
        if npx is None or nln is None:
            raise TypeError("detect_dat_byte_order(bytes) needs npx and nln")
        buf = np.frombuffer(raw, dtype=np.uint8)
        if buf.size < 2 * npx * nln:
            raise ValueError(f"{buf.size} bytes cannot hold {nln} lines of {npx} 16-bit pixels")
        planes = buf[: 2 * npx * nln].reshape(nln, npx, 2)
    else:
        arr = np.asarray(raw)
        if arr.dtype != np.uint8:
            raise TypeError("detect_dat_byte_order expects bytes or a uint8 array")
        if arr.ndim == 3 and arr.shape[2] == 2:
            planes = arr
        elif arr.ndim == 2 and arr.shape[1] % 2 == 0:
            planes = arr.reshape(arr.shape[0], arr.shape[1] // 2, 2)
        else:
            raise ValueError(f"expected a (NLN, NPX, 2) or (NLN, 2*NPX) uint8 array, got shape {arr.shape}")
    z1, z2 = dat_byte_plane_energies(planes)
    return "little" if z1 > z2 else "big"


def dat_byte_plane_energies(planes: np.ndarray) -> tuple[int, int]:
    """SPC's (z1, z2): summed squared Laplacians of byte planes 1 and 2 at the 50×50 grid.

    ``planes``: uint8 (NLN, NPX, 2).  Grid and stencil as in SPC ``xPicInpt``:
    sample i = (5 + i1·NPX)/100, line j = (5 + j1·NLN)/100 (integer division,
    1-based) for i1, j1 = 1, 3, …, 99, stencil 4·c − left − right − up − down.
    Below 195 pixels along an axis SPC's first grid point is pixel 1, whose stencil
    leaves the image; there the points are clipped one pixel inside.  Images under
    3×3 give (0, 0).
    """
    nl, ns = planes.shape[:2]
    if nl < 3 or ns < 3:
        return 0, 0
    rows = _grid(nl)[:, None]
    cols = _grid(ns)[None, :]
    z = []
    for b in (0, 1):
        d = planes[:, :, b]
        lap = (
            4 * d[rows, cols].astype(np.int64)
            - d[rows, cols - 1]
            - d[rows, cols + 1]
            - d[rows - 1, cols]
            - d[rows + 1, cols]
        )
        z.append(int(np.sum(lap * lap)))
    return z[0], z[1]


def dat_layout(size: int, npx: int, nln: int) -> int:
    """Bytes per pixel SPC uses for a ``.DAT`` of ``size`` bytes (xPicInpt.f), or 0 if it cannot read it.

    xPicInpt opens the file with ``RECL=2*NPX`` and tries ``READ(10,REC=NLN,ERR=20)``: gfortran reads a
    record that has at least one byte in the file (a short last record comes zero-padded) and takes the
    ERR branch only when record NLN starts past the end (oracle-checked).  So 2 bytes per pixel whenever
    size > 2·NPX·(NLN−1), else 1 byte, which the 8-bit loop can read when size > NPX·(NLN−1).
    """
    if size == npx * nln and nln == 1:
        return 1  # one-line image: SPC's test would say 16-bit; the exact 8-bit size is taken (a warning)
    if size > 2 * npx * (nln - 1):
        return 2
    if size > npx * (nln - 1):
        return 1
    return 0


def _dat_from_bytes(data: bytes, path, npx, nln, byte_order: str, warnings: list | None = None) -> np.ndarray:
    if npx is None or nln is None:
        raise SpcUsageError(f"{path}: a .DAT photo needs NPX and NLN (from the picture's SUM)")
    npx, nln = int(npx), int(nln)
    if npx < 1 or nln < 1:
        raise SpcUsageError(f"NPX and NLN must be positive, got {npx} {nln}")
    order = _normalise_order(byte_order)
    size = len(data)
    warnings = [] if warnings is None else warnings
    nbytes = dat_layout(size, npx, nln)
    if nbytes == 0:
        raise SpcFormatError(
            path,
            f"byte {size}",
            f"{npx * nln} bytes (8-bit) or {2 * npx * nln} bytes (16-bit) for NPX={npx} NLN={nln} "
            f"(one or two bytes per pixel, NPX x NLN pixels); the file has {size} bytes",
        )
    need = nbytes * npx * nln
    if nbytes == 1:
        _refuse_cut_sixteen_bit(data, path, npx, nln, size)
    if nln == 1 and nbytes == 1:
        warnings.append((None, "a one-line 8-bit .DAT: SPC's record test (xPicInpt) would read it as 16-bit"))
    if size > need:
        warnings.append(
            (f"byte {need}", f"{size - need} bytes after the {nln} lines are not read by SPC (xPicInpt)")
        )
    elif size < need:
        warnings.append((f"byte {size}", "the last line is short: SPC reads it zero-padded (DN 0 = no data)"))
    data = bytes(data[:need]) + bytes(max(0, need - size))
    if nbytes == 2:
        if order == "auto":
            buf = np.frombuffer(data, dtype=np.uint8).reshape(nln, npx, 2)
            z1, z2 = dat_byte_plane_energies(buf)
            order = "little" if z1 > z2 else "big"
            if z1 == z2 and any(data):
                # xPicInpt sets no DN on a tie (its IF tests > and <): SPC sees an all-zero picture, which
                # is no reading of this file at all -- refused with one line (issue #40 item 6)
                raise SpcFormatError(
                    path,
                    None,
                    "a 16-bit .DAT whose byte order SPC's test can tell (xPicInpt: the byte plane with more "
                    "Laplacian energy is the low byte); here both planes tie -- e.g. 8-bit data x257 -- so "
                    "SPC assigns no DN at all (rewrite it as 8-bit, or give the byte order explicitly)",
                )
        dt = ">u2" if order == "big" else "<u2"
        return np.frombuffer(data, dtype=dt).reshape(nln, npx).astype(np.uint16)
    return np.frombuffer(data, dtype=np.uint8).reshape(nln, npx).copy()


#: byte-plane energy ratio above which 8-bit-sized DAT bytes are taken for 16-bit pixels (a cut file)
CUT_DAT_RATIO = 20
#: smallest image (pixels along each axis) on which the cut-file test speaks
CUT_DAT_MIN = 64


def _refuse_cut_sixteen_bit(data: bytes, path, npx: int, nln: int, size: int) -> None:
    """SpcFormatError when bytes that SPC's size rule reads as 8-bit look like 16-bit pixels: a 16-bit
    photo cut to half its size (or less) has the 8-bit size, and xPicInpt would read its high and low
    bytes as neighbouring pixels.  SPC's own byte-plane test tells them apart: the two byte planes of
    16-bit data differ by orders of magnitude in Laplacian energy (high bytes smooth, low bytes busy),
    those of an 8-bit image (even and odd columns) are alike."""
    lines = min(nln, size // (2 * npx))  # the complete 16-bit lines the bytes would hold
    if npx < CUT_DAT_MIN or lines < CUT_DAT_MIN // 2:
        return
    planes = np.frombuffer(data, dtype=np.uint8, count=lines * 2 * npx).reshape(lines, npx, 2)
    z1, z2 = dat_byte_plane_energies(planes)
    low, high = min(z1, z2), max(z1, z2)
    if high > 0 and high > CUT_DAT_RATIO * low:
        raise SpcFormatError(
            path,
            f"byte {size}",
            f"{2 * npx * nln} bytes for a 16-bit NPX={npx} NLN={nln} photo: the file has {size} bytes, "
            f"which SPC's size rule reads as 8-bit, but they are 16-bit pixels (byte-plane Laplacian "
            f"energies {z1} and {z2}, SPC's byte-order test): a 16-bit photo cut short",
        )


def read_dat(path, npx: int, nln: int, byte_order: str = "auto") -> Photo:
    """Read an SPC raw image ``IMAGEFILES/<PICNM>.DAT`` (§7.4); line 1 = first record.

    Mirrors xPicInpt.f: ``READ(10,REC=NLN,ERR=20)`` picks 16 or 8 bits, the Laplacian test the order.
    """
    path = Path(path)
    data = _read_bytes(path)
    warnings: list = []
    photo = Photo(_dat_from_bytes(data, path, npx, nln, byte_order, warnings), name=path.stem)
    photo.__dict__["_spc_warnings"] = warnings
    return photo


class SpcDatWarning(UserWarning):
    """A ``.DAT`` written so that SPC's byte-order test (xPicInpt) would misread it."""


def dat_write_check(data: np.ndarray) -> str | None:
    """Why SPC would misread ``data`` written as a 16-bit MSB-first ``.DAT`` (None when it reads it right).

    xPicInpt takes the byte plane with more Laplacian energy as the low byte: when the high bytes are
    busier (e.g. 8-bit data scaled ×256) SPC reads the file byte-swapped, and on a tie (×257) it sets no DN.
    """
    arr = np.asarray(data)
    if arr.dtype != np.uint16 or arr.ndim != 2:
        return None
    planes = np.ascontiguousarray(arr.astype(">u2")).view(np.uint8).reshape(arr.shape[0], arr.shape[1], 2)
    z1, z2 = dat_byte_plane_energies(planes)
    if z1 > z2:
        return "its high bytes vary more than its low bytes: SPC's byte-order test would read it byte-swapped"
    if z1 == z2 and arr.any() and min(arr.shape) >= 3:
        return "its two byte planes tie in SPC's byte-order test: SPC would read no DN at all"
    return None


# ----------------------------------------------------------------------------------------------
# PGM
# ----------------------------------------------------------------------------------------------


def _pgm_header(data: bytes, path) -> tuple[str, int, int, int, int]:
    """(magic, width, height, maxval, offset of the raster) of a PGM (netpbm rules)."""
    magic = data[:2].decode("latin-1")
    pos = 2
    values = []
    starts = []
    while len(values) < 3:
        # skip whitespace and comments
        while pos < len(data):
            c = data[pos : pos + 1]
            if c not in _WHITESPACE + b"#":
                break
            if c == b"#":
                end = data.find(b"\n", pos)
                end2 = data.find(b"\r", pos)
                ends = [e for e in (end, end2) if e >= 0]
                pos = min(ends) if ends else len(data)
            else:
                pos += 1
        start = pos
        while pos < len(data) and data[pos : pos + 1].isdigit():
            pos += 1
        if pos == start:
            what = ("the width", "the height", "the maximum value")[len(values)]
            raise SpcFormatError(path, f"byte {start}", f"{what} of the PGM header (a decimal integer)")
        values.append(int(data[start:pos]))
        starts.append(start)
    if pos >= len(data) or data[pos : pos + 1] not in _WHITESPACE:
        raise SpcFormatError(path, f"byte {pos}", "one whitespace character after the PGM maximum value")
    width, height, maxval = values
    if width < 1 or height < 1:
        raise SpcFormatError(path, "byte 2", f"a positive PGM width and height, got {width} {height}")
    if not 1 <= maxval <= 65535:
        raise SpcFormatError(path, f"byte {starts[2]}", f"a PGM maximum value 1..65535, got {maxval}")
    return magic, width, height, maxval, pos + 1


def _pgm_from_bytes(data: bytes, path) -> np.ndarray:
    magic, width, height, maxval, off = _pgm_header(data, path)
    npix = width * height
    dtype = np.uint8 if maxval < 256 else np.uint16
    if magic == "P5":
        nbytes = 1 if maxval < 256 else 2
        need = npix * nbytes
        if len(data) - off < need:
            raise SpcFormatError(
                path,
                f"byte {len(data)}",
                f"{need} raster bytes for a {width}x{height} PGM with maximum {maxval} after byte {off}; "
                f"the file ends after {len(data) - off}",
            )
        extra = data[off + need :]
        if extra.strip(_WHITESPACE):  # a wrong width/height would otherwise read a sheared image
            raise SpcFormatError(
                path,
                f"byte {off + need}",
                f"the end of the file after the {need} raster bytes of a {width}x{height} PGM "
                f"(found {len(extra)} more bytes: is the width or height wrong?)",
            )
        raw = np.frombuffer(data, dtype=np.uint8 if nbytes == 1 else ">u2", count=npix, offset=off)
        vals = raw.astype(dtype)
    else:  # P2: plain (ASCII) PGM
        lines = [ln.split(b"#", 1)[0] for ln in data[off:].splitlines()]
        toks = b" ".join(lines).split()
        if len(toks) < npix:
            raise SpcFormatError(
                path,
                f"byte {len(data)}",
                f"{npix} pixel values for a {width}x{height} plain PGM, found {len(toks)}",
            )
        if len(toks) > npix:
            raise SpcFormatError(
                path,
                f"byte {off}",
                f"{npix} pixel values for a {width}x{height} plain PGM, found {len(toks)} "
                "(is the width or height wrong?)",
            )
        if not all(t.isdigit() for t in toks[:npix]):
            raise SpcFormatError(path, f"byte {off}", "non-negative decimal pixel values in a plain PGM")
        vals = np.array([int(t) for t in toks[:npix]], dtype=np.int64)
    above = np.flatnonzero(vals > maxval)
    if above.size:
        k = int(above[0])
        where = f"byte {off + k * (1 if maxval < 256 else 2)}" if magic == "P5" else f"byte {off}"
        raise SpcFormatError(path, where, f"pixel values <= the PGM maximum value {maxval} (pixel {k + 1})")
    return vals.astype(dtype, copy=False).reshape(height, width)


def format_pgm(data: np.ndarray) -> bytes:
    """Binary PGM (P5) bytes: 8-bit with SPC RAW2PGM's header ``P5\\n#.\\nNPX NLN\\n255\\n`` (§7.4);
    16-bit with maximum 65535 and big-endian samples (netpbm)."""
    nln, npx = data.shape
    if data.dtype == np.uint8:
        return b"P5\n#.\n%d %d\n255\n" % (npx, nln) + np.ascontiguousarray(data).tobytes()
    if data.dtype == np.uint16:
        return b"P5\n#.\n%d %d\n65535\n" % (npx, nln) + data.astype(">u2").tobytes()
    raise SpcUsageError(f"PGM holds 8- or 16-bit integers, not {data.dtype}; use FITS for floating point")


# ----------------------------------------------------------------------------------------------
# PNG
# ----------------------------------------------------------------------------------------------


def _png_from_bytes(data: bytes, path) -> np.ndarray:
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(io.BytesIO(data)) as im:
                w, h = im.size  # from the header: checked before the pixels are decoded
                if w < 1 or h < 1:
                    raise SpcFormatError(path, None, f"a PNG of at least 1 x 1 pixels, found {w} x {h}")
                _check_pixels(w, h, 2, path)
                im.load()
                mode = im.mode
                arr = np.asarray(im)
    except SpcFormatError:
        raise
    except Exception as exc:  # pillow raises many kinds (OSError, SyntaxError, ValueError…)
        raise SpcFormatError(path, None, f"a readable PNG image ({type(exc).__name__}: {exc})") from None
    if mode == "L":
        return np.ascontiguousarray(arr, dtype=np.uint8)
    if mode in ("I;16", "I;16B", "I;16L", "I;16N"):
        return arr.astype(np.uint16)
    if mode == "I":
        if arr.size and (arr.min() < 0 or arr.max() > 65535):
            raise SpcFormatError(path, None, "a grayscale PNG with 16-bit values")
        return arr.astype(np.uint16)
    raise SpcFormatError(path, None, f"a grayscale PNG (8 or 16 bit); found PIL mode {mode!r}")


def format_png(data: np.ndarray) -> bytes:
    """PNG bytes of an 8-bit (gray) or 16-bit (gray, 16-bit) array."""
    from PIL import Image

    if data.dtype == np.uint8:
        im = Image.fromarray(np.ascontiguousarray(data))
    elif data.dtype == np.uint16:
        im = Image.fromarray(np.ascontiguousarray(data, dtype=np.uint16))
    else:
        raise SpcUsageError(f"PNG holds 8- or 16-bit integers, not {data.dtype}; use FITS for floating point")
    buf = io.BytesIO()
    im.save(buf, format="PNG")
    return buf.getvalue()


# ----------------------------------------------------------------------------------------------
# FITS
# ----------------------------------------------------------------------------------------------


def _fits_dn(arr: np.ndarray) -> np.ndarray:
    """FITS data → one of the Photo DN types, exactly (no value changes)."""
    arr = arr.astype(arr.dtype.newbyteorder("="), copy=False)
    kind, size = arr.dtype.kind, arr.dtype.itemsize
    if arr.dtype in _DTYPES:
        return np.ascontiguousarray(arr)
    if kind == "i" and size == 2:
        # signed 16-bit without BZERO: DN are unsigned in SPC (§8 item 12)
        return arr.astype(np.uint16) if not np.any(arr < 0) else arr.astype(np.float32)
    if kind in "iu":
        return arr.astype(np.float64)
    if kind == "f":
        return arr.astype(np.float64)
    raise ValueError(f"unsupported FITS data type {arr.dtype}")


def _fits_from_bytes(data: bytes, path) -> np.ndarray:
    from astropy.io import fits

    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with fits.open(io.BytesIO(data), memmap=False) as hdul:
                for k, hdu in enumerate(hdul):  # what each header promises, before the block layout
                    _check_fits_header(hdu.header, len(data), path, k)
                _check_fits_layout(hdul, data, path)
                for k, hdu in enumerate(hdul):
                    arr = hdu.data
                    _check_fits_warnings(caught, path, k)
                    if arr is None or not isinstance(arr, np.ndarray) or arr.dtype.names:
                        continue
                    shape = arr.shape
                    while arr.ndim > 2 and arr.shape[0] == 1:
                        arr = arr[0]
                    if arr.ndim != 2:
                        if len(shape) > 2:
                            raise SpcFormatError(path, f"HDU {k}", f"a 2-D image, found shape {shape}")
                        continue
                    if arr.size == 0:
                        raise SpcFormatError(
                            path, f"HDU {k}", f"an image of at least 1 x 1 pixels, found {shape}"
                        )
                    return _fits_dn(np.array(arr))
    except SpcFormatError:
        raise
    except Exception as exc:  # astropy raises OSError, TypeError, ValueError, VerifyError…
        raise SpcFormatError(path, None, f"a readable FITS file ({type(exc).__name__}: {exc})") from None
    raise SpcFormatError(path, None, "a FITS file with a 2-D image HDU")


def _check_pixels(width: int, height: int, bytes_per_pixel: int, path, where=None) -> None:
    """Refuse an image whose header promises more pixels than the input cap (before decoding)."""
    from spctool.formats.guard import MAX_INPUT_BYTES, check_allocation

    check_allocation(
        float(width) * float(height) * bytes_per_pixel,
        f"a {width} x {height} image",
        MAX_INPUT_BYTES,
        where=path,
    )


def _check_fits_header(header, size: int, path, k: int) -> None:
    """The data an HDU header promises (NAXISn, BITPIX) must fit in the file and the cap."""
    try:
        naxis = int(header.get("NAXIS", 0))
        bitpix = int(header.get("BITPIX", 8))
        dims = [int(header.get(f"NAXIS{i}", 0)) for i in range(1, naxis + 1)]
    except (TypeError, ValueError, OverflowError):
        raise SpcFormatError(path, f"HDU {k}", "integer NAXIS, NAXISn and BITPIX header values") from None
    if naxis < 0 or any(d < 0 for d in dims) or bitpix not in (8, 16, 32, 64, -32, -64):
        raise SpcFormatError(
            path, f"HDU {k}", f"valid NAXIS/BITPIX values, found NAXIS={naxis} BITPIX={bitpix}"
        )
    if not dims or header.get("XTENSION", "IMAGE").strip() not in ("IMAGE", "", "IUEIMAGE"):
        return
    nbytes = float(np.prod([float(d) for d in dims])) * abs(bitpix) // 8
    if nbytes > size:
        raise SpcFormatError(
            path,
            f"HDU {k}",
            f"{nbytes:.0f} data bytes for an image of {' x '.join(map(str, dims))} at BITPIX {bitpix}; "
            f"the file has {size} bytes in all",
        )


#: FITS files are made of 2880-byte blocks (FITS standard 4.0, section 3.1)
FITS_BLOCK = 2880


def _check_fits_layout(hdul, data: bytes, path) -> None:
    """The file is whole 2880-byte blocks, every HDU header has an END card, and the HDUs (each
    header, then its data padded to a block) end exactly where the file ends, or where zero-filled
    blocks after them begin: bytes inserted, removed or appended anywhere else shift that sum
    (astropy alone reads such a file, shifted)."""
    size = len(data)
    hdul.readall()
    end = 0
    for k in range(len(hdul)):
        info = hdul.fileinfo(k)
        if info is None:  # pragma: no cover - an HDU not from the file
            continue
        head_bytes = info["datLoc"] - info["hdrLoc"]
        if info["hdrLoc"] != end or head_bytes <= 0 or head_bytes % FITS_BLOCK:
            raise SpcFormatError(
                path,
                f"byte {info['hdrLoc']}",
                f"HDU {k} to start at byte {end} with a header of whole {FITS_BLOCK}-byte blocks "
                f"(the header spans bytes {info['hdrLoc']}-{info['datLoc']})",
            )
        if not _has_end_card(data[info["hdrLoc"] : info["datLoc"]]):
            raise SpcFormatError(path, f"HDU {k}", "an END card closing the header")
        end = info["datLoc"] + info["datSpan"]
    if size % FITS_BLOCK or end > size or data[end:].strip(b"\0"):
        raise SpcFormatError(
            path,
            f"byte {min(end, size)}",
            f"a FITS file of whole {FITS_BLOCK}-byte blocks ending after its last HDU at byte {end}; the "
            f"file has {size} bytes (bytes inserted, removed or appended)",
        )


def _has_end_card(head: bytes) -> bool:
    """True when the header bytes hold an 80-byte card ``END`` (followed by blanks)."""
    return any(head[i : i + 80].rstrip(b" ") == b"END" for i in range(0, len(head) - 79, 80))


def _check_fits_warnings(caught, path, k: int) -> None:
    """Astropy pads a truncated data unit with zeros and only warns: that is an error here."""
    for w in caught:
        text = str(w.message)
        if "truncated" in text.lower() or "smaller than the expected" in text.lower():
            raise SpcFormatError(path, f"HDU {k}", f"complete image data ({' '.join(text.split())[:160]})")


def format_fits(data: np.ndarray, header: dict | None = None) -> bytes:
    """FITS bytes with ``data`` as the primary HDU (row 0 = line 1); ``header``: extra cards.

    uint16 is written as BITPIX 16 with BZERO 32768 (the FITS unsigned convention).
    Values of ``header`` may be ``value`` or ``(value, comment)``.
    """
    from astropy.io import fits

    if data.dtype not in _DTYPES:
        raise SpcUsageError(f"cannot write {data.dtype} pixels to FITS")
    hdu = fits.PrimaryHDU(data=np.ascontiguousarray(data))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for key, value in (header or {}).items():
            hdu.header[key] = value
        buf = io.BytesIO()
        hdu.writeto(buf, output_verify="fix")
    return buf.getvalue()


# ----------------------------------------------------------------------------------------------
# dispatch
# ----------------------------------------------------------------------------------------------


def _read_bytes(path: Path) -> bytes:
    from spctool.formats.guard import read_bytes

    return read_bytes(path, "a photo file")  # regular files only, size checked first


def detect_format(path, head: bytes, *, have_size: bool = False) -> str:
    """Photo format of a file from its first bytes, then its extension: fits, pgm, png or dat."""
    ext = Path(os.fspath(path)).suffix.lower()
    if ext == ".dat":  # raw DN could start with any bytes: the extension decides
        return "dat"
    if head.startswith(_FITS_SIGNATURE):
        return "fits"
    if head.startswith(_PNG_SIGNATURE):
        return "png"
    if head[:2] in (b"P5", b"P2") and (len(head) < 3 or head[2:3] in _WHITESPACE + b"#"):
        return "pgm"
    if head[:1] == b"P" and head[1:2] in b"134567" and head[1:2] != b"":
        raise SpcFormatError(path, "byte 0", f"a grayscale PGM (P5 or P2), found netpbm type {head[:2]!r}")
    if ext in _EXT_FORMAT:
        return _EXT_FORMAT[ext]
    if have_size:
        return "dat"
    raise SpcFormatError(path, "byte 0", "a FITS, PGM (P5/P2), PNG or SPC .DAT photo")


def read_photo(
    path,
    *,
    flip_rows: bool = False,
    npx: int | None = None,
    nln: int | None = None,
    byte_order: str = "auto",
) -> Photo:
    """Read a photo in SPC pixel order (module docstring "Pixel convention").

    The format is detected from the content (FITS, PNG, PGM signatures) and the
    extension (``.DAT`` always raw; a file with another extension is raw when
    ``npx`` and ``nln`` are given and no signature matches).  ``.DAT`` needs
    ``npx``/``nln`` (SUM line 3) and honours ``byte_order`` (auto, big, little).
    ``flip_rows=True`` reverses the line order (for bottom-up photos).
    """
    path = Path(path)
    data = _read_bytes(path)
    notes: list = []
    fmt = detect_format(path, data[:16], have_size=npx is not None and nln is not None)
    if fmt == "fits":
        arr = _fits_from_bytes(data, path)
    elif fmt == "png":
        arr = _png_from_bytes(data, path)
    elif fmt == "pgm":
        if not data.startswith((b"P5", b"P2")):
            raise SpcFormatError(path, "byte 0", "a PGM magic number P5 or P2")
        arr = _pgm_from_bytes(data, path)
    else:
        arr = _dat_from_bytes(data, path, npx, nln, byte_order, notes)
    if flip_rows:
        arr = np.ascontiguousarray(arr[::-1])
    photo = Photo(arr, name=path.stem)
    photo.__dict__["_spc_warnings"] = notes  # validate prints how SPC reads the .DAT differently
    return photo


def format_photo(photo: Photo | np.ndarray, fmt: str, *, flip_rows: bool = False, header=None) -> bytes:
    """The bytes of ``photo`` in ``fmt`` (fits, pgm, png, dat); see :func:`write_photo`."""
    if not isinstance(photo, Photo):
        photo = Photo(np.asarray(photo))
    data = photo.data[::-1] if flip_rows else photo.data
    fmt = fmt.lower().lstrip(".")
    if fmt in ("fits", "fit", "fts"):
        return format_fits(data, header)
    if fmt == "pgm":
        return format_pgm(data)
    if fmt == "png":
        return format_png(data)
    if fmt == "dat":
        if data.dtype == np.uint8:
            return np.ascontiguousarray(data).tobytes()
        if data.dtype == np.uint16:
            if data.size and int(data.max()) <= 255:
                # fits in 8 bits: write 8-bit, which SPC's record test reads without a byte-order guess
                return np.ascontiguousarray(data.astype(np.uint8)).tobytes()
            problem = dat_write_check(data)
            if problem is not None:
                import warnings

                warnings.warn(SpcDatWarning(f"16-bit .DAT: {problem} (xPicInpt)"), stacklevel=2)
            return data.astype(">u2").tobytes()  # MSB first, SPC's normal order
        raise SpcUsageError(f".DAT holds 8- or 16-bit integers, not {data.dtype}; use FITS for floats")
    raise SpcUsageError(f"unknown photo format {fmt!r} (fits, pgm, png or dat)")


def write_photo(
    path,
    photo: Photo | np.ndarray,
    *,
    fmt: str | None = None,
    flip_rows: bool = False,
    overwrite: bool = True,
    backup: bool = False,
    header: dict | None = None,
):
    """Write a photo atomically; the format comes from ``fmt`` or the extension.

    ``.fits``/``.fit`` (any DN type; ``header`` adds cards), ``.pgm`` (8-bit with the
    RAW2PGM header, 16-bit big-endian), ``.png`` (8/16-bit gray), ``.dat`` (raw,
    16-bit big-endian).  ``header`` is ignored for formats other than FITS.
    ``flip_rows=True`` writes the lines in reverse order.
    """
    path = Path(path)
    if fmt is None:
        ext = path.suffix.lower()
        if ext not in _EXT_FORMAT:
            raise SpcUsageError(f"{path}: cannot tell the photo format from the extension (use fmt=)")
        fmt = _EXT_FORMAT[ext]
    return write_bytes(
        path, format_photo(photo, fmt, flip_rows=flip_rows, header=header), overwrite=overwrite, backup=backup
    )


__all__ = [
    "Photo",
    "dat_byte_plane_energies",
    "dat_layout",
    "dat_write_check",
    "SpcDatWarning",
    "detect_dat_byte_order",
    "detect_format",
    "format_photo",
    "index_to_spc",
    "read_dat",
    "read_photo",
    "spc_to_index",
    "write_photo",
]
