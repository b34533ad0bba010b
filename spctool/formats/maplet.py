"""SPC maplets and bigmaps: ``MAPFILES/<NAME>.MAP`` (binary) <-> :class:`Maplet`.

Specification: ``spc-formats.md`` §1 (records, header, cells, endianness, writer
variants, worked example §1.6), §8 items 1–4 and the MAP checklist of §9.

File layout (72-byte Fortran direct-access records, no record markers):

* record 1, the header: bytes 1–6 unused (writer dependent), SCALE (float32 BE,
  km per cell), QSZ (uint16 **little-endian**), bytes 13–15 the σ direction, V,
  UX, UY, UZ (3×float32 BE each), HSCALE (float32 BE), bytes 68–71 |σ| (float32
  BE), byte 72 the map version;
* records 2…: (2·QSZ+1)² cells of 3 bytes, int16 BE height ``H`` then uint8
  albedo ``A``; J outer, I inner (I fastest); the last record is padded.

Decoding (§1.3): height h = H·HSCALE in units of SCALE, relative albedo A/100,
``A == 0`` means *missing* (its height is ignored and reported as 0.0, §8 item 3).
Array axes follow the NumPy recipe of §1.3: ``heights[r, c]`` with r = J + q
(axis 0, steps along UX, i.e. South for ORIENT frames) and c = I + q (axis 1,
steps along UY, East), so the body-frame point of a cell is
``P[r, c] = V + SCALE·((r−q)·UX + (c−q)·UY + h[r, c]·UZ)``.

Writing:

* an unchanged parsed map is written back **byte for byte** (the raw header with
  its writer-specific bytes 1–6, 13–15, 68–72, the raw ``H``/``A`` cells and the
  raw padding, including the QSZ ≤ 1 padding quirk of §1.3);
* changed header fields (SCALE, V, UX, UY, UZ) are re-encoded in place, the
  unknown bytes are kept;
* changed heights (or a changed valid mask) are re-quantised with the 2021
  ``WRITE_MAP`` rules of §1.3: HSCALE = float32(max|h|/30000) over valid cells
  (all-flat guard: 1/30000, §8 item 4), H = NINT(h/HSCALE) in single precision
  with Fortran's round-half-away-from-zero; changed albedo: A = clip(NINT(100·alb),
  1, 199) on valid cells; missing cells are written 0/0; the padding after the
  last cell is zero-filled whenever cells are re-encoded;
* :meth:`Maplet.new` builds a map in the 2021 writer layout (§1.5 first row).

GIANT's ``DOUBLE`` variant (§1.4) is not SPC and is rejected.

Performance: a parsed maplet keeps the file bytes and decodes ``heights``,
``albedo`` and ``valid`` on first access (they behave as ordinary attributes).
Reading thousands of maplets for selection, which needs only the header, then
costs a file read and a header decode each (:func:`read_maps`).
"""

from __future__ import annotations

import math
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spctool.errors import SpcFormatError
from spctool.formats.atomic import write_bytes

RECORD = 72
"""Bytes per MAP record (header and data)."""

CELLS_PER_RECORD = 24
"""3-byte cells per data record."""

QSZ_MAX = 65535
"""QSZ is an unsigned 16-bit field (§1.1)."""

# The header as one structured record.  Offsets 0-based, see §1.2.
HEADER_DTYPE = np.dtype(
    {
        "names": ["unused", "scale", "qsz", "sigdir", "v", "ux", "uy", "uz", "hscale", "sigma", "mapvers"],
        "formats": [
            "V6",
            ">f4",
            "<u2",
            ("u1", (3,)),
            (">f4", (3,)),
            (">f4", (3,)),
            (">f4", (3,)),
            (">f4", (3,)),
            ">f4",
            ">f4",
            "u1",
        ],
        "offsets": [0, 6, 10, 12, 15, 27, 39, 51, 63, 67, 71],
        "itemsize": RECORD,
    }
)

CELL_DTYPE = np.dtype([("h", ">i2"), ("a", "u1")])
"""One data cell: int16 big-endian height quantum, uint8 albedo byte."""

_F32_30000 = np.float32(30000.0)
_F32_100 = np.float32(100.0)
_HEADER_FLOATS = struct.Struct(">13f")  # V, UX, UY, UZ, HSCALE at offset 15
_SCALE = struct.Struct(">f")  # SCALE at offset 6

# Byte offsets of header fields, for error messages and in-place re-encoding.
_OFF_SCALE, _OFF_QSZ, _OFF_V, _OFF_UX, _OFF_UY, _OFF_UZ = 6, 10, 15, 27, 39, 51
_OFF_HSCALE, _OFF_SIGMA = 63, 67


def map_file_size(qsz: int) -> int:
    """Size in bytes of a MAP file with half-size ``qsz``: 72·(1 + ⌈(2Q+1)²/24⌉) (§1.1)."""
    n = (2 * int(qsz) + 1) ** 2
    return RECORD * (1 + -(-n // CELLS_PER_RECORD))


# ----------------------------------------------------------------------------------------------
# rounding and encoding (2021 WRITE_MAP rules, §1.3)
# ----------------------------------------------------------------------------------------------


def _nint(x: np.ndarray) -> np.ndarray:
    """Fortran NINT (round half away from zero) of float32 values, exact: evaluated in float64,
    where |x| + 0.5 is exact (numpy.rint would round half to even)."""
    x64 = np.asarray(x, dtype=np.float64)
    return np.sign(x64) * np.floor(np.abs(x64) + 0.5)


def hscale_2021(heights: np.ndarray, valid: np.ndarray) -> np.float32:
    """HSCALE of the 2021 ``WRITE_MAP``: float32(max|h| / 30000) over valid cells.

    Computed in single precision like the Fortran (REAL*4 HMAX / 30000).  An all-flat
    (or all-missing) map would give 0/0 in SPC; it falls back to the older writers'
    floor 1/30000 (§1.3, §8 item 4).
    """
    h32 = np.asarray(heights, dtype=np.float32)
    hmax = np.float32(np.max(np.abs(h32[np.asarray(valid, bool)]), initial=np.float32(0.0)))
    if not hmax > 0:
        hmax = np.float32(1.0)
    return np.float32(hmax / _F32_30000)


def encode_heights(heights: np.ndarray, valid: np.ndarray, hscale: float) -> np.ndarray:
    """Int16 height quanta H = NINT(h/HSCALE) in single precision; 0 for missing cells."""
    hs = np.float32(hscale)
    h32 = np.asarray(heights, dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        q = _nint(np.where(valid, h32 / hs, np.float32(0.0)))
    bad = valid & ~(np.abs(q) <= 32767)
    if np.any(bad):
        r, c = np.argwhere(bad)[0]
        raise ValueError(
            f"height {heights[r, c]!r} at cell [{r}, {c}] does not fit int16 with HSCALE {float(hs)!r}"
        )
    return q.astype(np.int16)


def encode_albedo(albedo: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Albedo bytes A = clip(NINT(100·alb), 1, 199) in single precision on valid cells, else 0."""
    a32 = np.asarray(albedo, dtype=np.float32)
    if np.any(valid & ~np.isfinite(a32)):
        raise ValueError("albedo must be finite on valid cells")
    with np.errstate(invalid="ignore", over="ignore"):
        a = np.clip(_nint(a32 * _F32_100), 1, 199)
    return np.where(valid, a, 0).astype(np.uint8)


# ----------------------------------------------------------------------------------------------
# the dataclass
# ----------------------------------------------------------------------------------------------


class _Decoded:
    """Data descriptor for ``heights``/``albedo``/``valid``: an ordinary attribute whose value,
    when not set (None), is decoded from the maplet's raw file bytes on first access."""

    def __set_name__(self, owner, name: str) -> None:
        self.name = name

    def __get__(self, obj, objtype=None):
        if obj is None:
            raise AttributeError(self.name)  # tells dataclasses: no default value
        value = obj.__dict__.get(self.name)
        if value is None:
            obj._decode()
            value = obj.__dict__[self.name]
        return value

    def __set__(self, obj, value) -> None:
        obj.__dict__[self.name] = value


def _vec3(x) -> np.ndarray:
    return np.array(x, dtype=np.float64).reshape(3)


@dataclass(eq=False)
class Maplet:
    """One maplet (or bigmap): a (2q+1)×(2q+1) height/albedo grid in a local frame.

    ``heights[r, c]`` and ``albedo[r, c]``: axis 0 = J + q (along UX, South), axis 1 =
    I + q (along UY, East), exactly the NumPy recipe of spc-formats §1.3.  Heights
    are in units of SCALE; both arrays hold 0.0 where ``valid`` is False.
    Float fields hold the float32 values of the file header as float64.

    ``_raw`` keeps the file bytes so that :func:`format_map` rewrites an unchanged
    map byte for byte; ``_header``, ``_h``, ``_a`` and ``_tail`` expose its header
    record, raw int16 heights, raw albedo bytes and padding.  A maplet built from a
    file may be given ``heights``/``albedo``/``valid`` = None: they are then decoded
    from ``_raw`` when first read.
    """

    scale: float
    qsz: int
    v: np.ndarray
    ux: np.ndarray
    uy: np.ndarray
    uz: np.ndarray
    hscale: float
    heights: np.ndarray = _Decoded()
    albedo: np.ndarray = _Decoded()
    valid: np.ndarray = _Decoded()
    name: str = ""
    _raw: bytes | None = field(default=None, repr=False)

    # -- raw content ---------------------------------------------------------------------------
    @property
    def _header(self) -> bytes | None:
        """The raw 72-byte header record (None for a maplet not built from bytes)."""
        return None if self._raw is None else self._raw[:RECORD]

    def _raw_cells(self) -> np.ndarray | None:
        """Raw cells (n, n) structured ``CELL_DTYPE`` view of ``_raw`` (None if absent)."""
        if self._raw is None:
            return None
        q = _raw_qsz(self._raw)
        n = 2 * q + 1
        return np.frombuffer(self._raw, dtype=CELL_DTYPE, count=n * n, offset=RECORD).reshape(n, n)

    @property
    def _h(self) -> np.ndarray | None:
        """Raw int16 height quanta H as stored (native byte order copy)."""
        cells = self._raw_cells()
        return None if cells is None else cells["h"].astype(np.int16)

    @property
    def _a(self) -> np.ndarray | None:
        """Raw albedo bytes A as stored."""
        cells = self._raw_cells()
        return None if cells is None else np.ascontiguousarray(cells["a"])

    @property
    def _tail(self) -> bytes | None:
        """Bytes after the last cell (the padding of the last record)."""
        if self._raw is None:
            return None
        n = 2 * _raw_qsz(self._raw) + 1
        return self._raw[RECORD + 3 * n * n :]

    def _decode(self) -> None:
        """Fill unset heights/albedo/valid from ``_raw`` (with the *stored* HSCALE)."""
        cells = self._raw_cells()
        if cells is None:
            raise AttributeError("maplet has no heights/albedo/valid and no raw file bytes to decode")
        hs = _SCALE.unpack_from(self._raw, _OFF_HSCALE)[0]
        heights, albedo, valid = _decode_cells(cells["h"], cells["a"], hs)
        d = self.__dict__
        for key, val in (("heights", heights), ("albedo", albedo), ("valid", valid)):
            if d.get(key) is None:
                d[key] = val

    def _decoded_untouched(self) -> bool:
        """True when none of heights/albedo/valid has been decoded or set since parsing."""
        d = self.__dict__
        return d.get("heights") is None and d.get("albedo") is None and d.get("valid") is None

    # -- derived properties ------------------------------------------------------------------
    @property
    def size(self) -> int:
        """Grid points per side, 2·QSZ + 1."""
        return 2 * int(self.qsz) + 1

    @property
    def rotation_map_to_body(self) -> np.ndarray:
        """3×3 map→body rotation with UX, UY, UZ as **columns** (§8 item 7)."""
        return np.column_stack([self.ux, self.uy, self.uz])

    @property
    def side_km(self) -> float:
        """Side length (2q+1)·SCALE in km."""
        return self.size * float(self.scale)

    @property
    def mapvers(self) -> int:
        """Header byte 72 (map version; 0 when absent).  Stored as an unsigned byte."""
        return 0 if self._raw is None else self._raw[71]

    @property
    def sigma_km(self) -> float:
        """Header bytes 68–71 (|σ| of the landmark position, km; writer dependent, §1.5)."""
        return 0.0 if self._raw is None else _SCALE.unpack_from(self._raw, _OFF_SIGMA)[0]

    def __eq__(self, other) -> bool:
        """Field-by-field equality of the public content (arrays compared exactly, NaN = NaN)."""
        if not isinstance(other, Maplet):
            return NotImplemented
        if self.qsz != other.qsz or self.name != other.name:
            return False
        if not (_same(self.scale, other.scale) and _same(self.hscale, other.hscale)):
            return False
        for a in ("v", "ux", "uy", "uz", "heights", "albedo", "valid"):
            x, y = np.asarray(getattr(self, a)), np.asarray(getattr(other, a))
            if x.shape != y.shape or not np.array_equal(x, y, equal_nan=x.dtype.kind == "f"):
                return False
        return True

    __hash__ = None  # mutable arrays

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def new(
        cls,
        scale: float,
        qsz: int,
        v,
        ux,
        uy,
        uz,
        heights,
        albedo,
        valid=None,
        mapvers: int = 0,
        sigma=None,
        name: str = "",
    ) -> Maplet:
        """A new map in the 2021 ``WRITE_MAP`` layout (§1.5 first row).

        ``heights`` (units of SCALE) and ``albedo`` (relative, nominal 1.0) are
        (2q+1)×(2q+1) with axis 0 = J (UX), axis 1 = I (UY).  ``valid`` defaults to
        every cell whose height and albedo are finite.  ``sigma`` is the landmark
        position-uncertainty vector (km) written to bytes 13–15 (direction) and
        68–71 (magnitude); None writes zeros.  A negative ``mapvers`` is stored +256.

        The returned maplet holds exactly what a reader of the encoded file gets
        (float32 header values, quantised heights, albedo bytes/100).
        """
        qsz = int(qsz)
        if not 0 <= qsz <= QSZ_MAX:
            raise ValueError(f"qsz must be in 0..{QSZ_MAX}, got {qsz}")
        n = 2 * qsz + 1
        heights = np.asarray(heights, dtype=np.float64)
        albedo = np.asarray(albedo, dtype=np.float64)
        if heights.shape != (n, n) or albedo.shape != (n, n):
            raise ValueError(f"heights and albedo must be {n}x{n} for qsz={qsz}")
        if valid is None:
            valid = np.isfinite(heights) & np.isfinite(albedo)
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != (n, n):
            raise ValueError(f"valid must be {n}x{n} for qsz={qsz}")
        if np.any(valid & ~np.isfinite(heights)):
            raise ValueError("heights must be finite on valid cells")
        mapvers = int(mapvers)
        if not -128 <= mapvers <= 255:
            raise ValueError("mapvers must fit one byte (-128..255)")
        header = np.zeros(1, dtype=HEADER_DTYPE)
        header["scale"] = scale
        header["qsz"] = qsz
        header["v"] = _vec3(v)
        header["ux"] = _vec3(ux)
        header["uy"] = _vec3(uy)
        header["uz"] = _vec3(uz)
        if sigma is not None:
            # SPC's landmark sigmas are REAL*8: magnitude and direction in double precision,
            # then stored as float32 / bytes (reproduces the §1.6 bytes 0x93 and 3ae305fb)
            s = np.abs(_vec3(sigma))
            mag = math.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
            if not math.isfinite(mag):
                raise ValueError("sigma must be finite")
            if mag > 0:
                header["sigdir"] = np.clip(_nint(255.0 * s / mag), 0, 255).astype(np.uint8)
            header["sigma"] = mag
        header["mapvers"] = mapvers % 256
        hs = hscale_2021(heights, valid)
        header["hscale"] = hs
        cells_h = encode_heights(heights, valid, hs)
        data = _assemble(header.tobytes(), cells_h, encode_albedo(albedo, valid), None)
        return parse_map(data, name=name)


def _same(a, b) -> bool:
    a, b = float(a), float(b)
    return a == b or (math.isnan(a) and math.isnan(b))


# ----------------------------------------------------------------------------------------------
# reading
# ----------------------------------------------------------------------------------------------


def _err(path, offset: int, expected: str) -> SpcFormatError:
    return SpcFormatError(path, f"byte {offset}", expected)


def _raw_qsz(data: bytes) -> int:
    """QSZ of bytes already validated by :func:`_qsz_from` (little-endian, else big-endian)."""
    q = data[10] + 256 * data[11]
    return q if map_file_size(q) == len(data) else 256 * data[10] + data[11]


def _qsz_from(data, path) -> int:
    """QSZ from bytes 11–12, validated against the file size (§1.4)."""
    size = len(data)
    if size < RECORD:
        raise _err(path, size, f"a 72-byte MAP header record (file has only {size} bytes)")
    if data[0:6] == b"DOUBLE":
        raise _err(
            path,
            0,
            "an SPC single-precision MAP: bytes 1-6 'DOUBLE' mark GIANT's double-precision "
            "maplet variant, which is not SPC and not supported",
        )
    q_le = data[10] + 256 * data[11]
    need = map_file_size(q_le)
    if size == need:
        return q_le
    q_be = 256 * data[10] + data[11]
    if map_file_size(q_be) == size:
        return q_be
    if size >= RECORD + 3 * (2 * q_le + 1) ** 2:
        # READ_MAP (xCommon.f) reads records 1..N only: a longer file (an older WRITE_MAP rewrote it in
        # place without truncating) or an unpadded last record is read -- see parse_map
        return q_le
    if size < need:
        raise _err(
            path,
            size,
            f"{need} bytes for QSZ={q_le} (72*(1+ceil((2Q+1)^2/24))): file truncated at {size} bytes "
            f"(or QSZ in bytes 11-12 is wrong)",
        )
    if size % RECORD:
        raise _err(
            path,
            size - size % RECORD,
            f"whole 72-byte records (file size {size} is not a multiple of 72; "
            f"QSZ={q_le} needs {need} bytes)",
        )
    raise _err(
        path,
        10,
        f"QSZ (bytes 11-12, little-endian) consistent with the file size: QSZ={q_le} needs {need} bytes, "
        f"file has {size} bytes ({size // RECORD} records)",
    )


def _check_header(floats, scale: float, path) -> None:
    """Reject a non-finite or non-positive SCALE and non-finite V, UX, UY, UZ (``floats[:12]``)."""
    if not (math.isfinite(scale) and scale > 0):
        raise _err(path, _OFF_SCALE, f"a positive finite SCALE (float32 big-endian), got {scale!r}")
    isfinite = math.isfinite
    for k, off, what in ((0, _OFF_V, "V"), (3, _OFF_UX, "UX"), (6, _OFF_UY, "UY"), (9, _OFF_UZ, "UZ")):
        if not (isfinite(floats[k]) and isfinite(floats[k + 1]) and isfinite(floats[k + 2])):
            raise _err(path, off, f"finite {what} components (3 float32 big-endian)")
    if not isfinite(floats[12]):
        # READ_MAP: HT = HSCALE*IX2 -- a NaN/Inf HSCALE would make every height NaN/Inf
        raise _err(path, _OFF_HSCALE, f"a finite HSCALE (float32 big-endian), got {floats[12]!r}")


def parse_map(data: bytes, path=None, *, name: str | None = None) -> Maplet:
    """Decode the bytes of a MAP file (§1).  ``path`` names the file in errors and gives ``name``.

    Mirrors xCommon.f READ_MAP: ``READ(20,REC=1) BLINE`` (header), ``READ(20,REC=NREC) BLINE`` for the cells.

    Heights, albedo and valid are decoded from the kept bytes on first access.
    """
    if not isinstance(data, bytes):
        if not isinstance(data, bytearray | memoryview):
            raise TypeError("parse_map expects bytes")
        data = bytes(data)
    q = _qsz_from(data, path)
    warnings: list[tuple[str, str]] = []
    need = map_file_size(q)
    if len(data) != need and map_file_size(256 * data[10] + data[11]) != len(data):
        # READ_MAP reads records 1..N: bytes past them are never read, a short last record is zero-padded
        if len(data) > need:
            warnings.append(
                (
                    f"byte {need}",
                    f"{len(data) - need} bytes after record {need // RECORD} are not read by READ_MAP",
                )
            )
            data = data[:need]
        else:
            warnings.append(
                (f"byte {len(data)}", "the last record is not padded to 72 bytes (READ_MAP reads it)")
            )
            data = data + bytes(need - len(data))
    fl = _HEADER_FLOATS.unpack_from(data, _OFF_V)
    scale = _SCALE.unpack_from(data, _OFF_SCALE)[0]
    _check_header(fl, scale, path)
    vec = np.array(fl[:12], dtype=np.float64)
    if name is None:
        name = "" if path is None else Path(os.fspath(path)).stem
    m = Maplet(
        scale=scale,
        qsz=q,
        v=vec[0:3],
        ux=vec[3:6],
        uy=vec[6:9],
        uz=vec[9:12],
        hscale=fl[12],
        heights=None,
        albedo=None,
        valid=None,
        name=name,
        _raw=data,
    )
    m.__dict__["_spc_warnings"] = warnings
    return m


def _decode_cells(raw_h: np.ndarray, raw_a: np.ndarray, hscale: float):
    """Heights (units of SCALE, exact products H·HSCALE), albedo A/100, valid A != 0 (§1.3, §8 item 3)."""
    valid = raw_a != 0
    keep = valid & (raw_h != 0)
    with np.errstate(invalid="ignore", over="ignore"):
        heights = np.where(keep, raw_h * np.float64(hscale), 0.0)
    albedo = raw_a / 100.0
    return heights, albedo, valid


def read_map(path) -> Maplet:
    """Read ``MAPFILES/<NAME>.MAP``; the maplet's ``name`` is the file stem."""
    from spctool.formats.guard import MAX_QSZ, read_bytes

    path = Path(path)
    # regular files only, sparse files refused, and no more bytes than a QSZ <= MAX_QSZ maplet holds:
    # a header cannot make this reader allocate more than the file's own (real) content
    data = read_bytes(path, f"a MAP file (QSZ <= {MAX_QSZ})", max_bytes=map_file_size(MAX_QSZ))
    return parse_map(data, path)


def read_maps(paths) -> list[Maplet]:
    """Read many MAP files (same result as ``[read_map(p) for p in paths]``).

    Fast because a parsed maplet is only its bytes plus a ``struct``-decoded header;
    the grids are decoded per maplet on first access.
    """
    return [read_map(p) for p in paths]


# ----------------------------------------------------------------------------------------------
# writing
# ----------------------------------------------------------------------------------------------


def _assemble(header: bytes, raw_h: np.ndarray, raw_a: np.ndarray, tail: bytes | None) -> bytes:
    """Header record + cells + padding (``tail``; None = zero-filled last record)."""
    n = raw_h.shape[0]
    ncell = n * n
    cells = np.empty(ncell, dtype=CELL_DTYPE)
    cells["h"] = raw_h.reshape(-1)
    cells["a"] = raw_a.reshape(-1)
    pad_len = map_file_size((n - 1) // 2) - RECORD - 3 * ncell
    if tail is None or len(tail) != pad_len:
        tail = bytes(pad_len)
    return bytes(header) + cells.tobytes() + tail


def format_map(m: Maplet) -> bytes:
    """Encode a maplet as MAP file bytes (§1).

    Unchanged parsed maps come back byte-identical; see the module docstring for
    what is re-encoded when fields change.
    """
    q = int(m.qsz)
    if not 0 <= q <= QSZ_MAX:
        raise ValueError(f"qsz must be in 0..{QSZ_MAX}, got {q}")
    n = 2 * q + 1
    raw = m._raw
    raw_q = _raw_qsz(raw) if raw is not None else -1

    # ---- header: start from the raw record (keeps bytes 1-6, 13-15, 68-72) -------------------
    header = bytearray(raw[:RECORD]) if raw is not None else bytearray(RECORD)  # new map: zeros

    def put(off: int, vals) -> None:
        new = [float(x) for x in np.asarray(vals, dtype=np.float64).reshape(-1)]
        if raw is not None:
            olds = struct.unpack_from(f">{len(new)}f", header, off)
            # rewrite only values that differ from what is stored (keeps NaN payloads and -0.0)
            if all(_same(a, b) and math.copysign(1, a) == math.copysign(1, b) for a, b in zip(new, olds)):
                return
        header[off : off + 4 * len(new)] = np.asarray(new, dtype=">f4").tobytes()

    put(_OFF_SCALE, [m.scale])
    put(_OFF_V, m.v)
    put(_OFF_UX, m.ux)
    put(_OFF_UY, m.uy)
    put(_OFF_UZ, m.uz)
    if q != raw_q:
        header[10] = q & 0xFF  # QSZ little-endian (a big-endian original is kept while QSZ is unchanged)
        header[11] = q >> 8
    hs_stored = _SCALE.unpack_from(header, _OFF_HSCALE)[0]

    # ---- cells: raw when unchanged, else the 2021 encoding ------------------------------------
    raw_ok = raw is not None and raw_q == q
    if raw_ok and m._decoded_untouched() and _same(m.hscale, hs_stored):
        return bytes(header) + raw[RECORD:]  # fast path: grids never read or set
    heights = np.asarray(m.heights, dtype=np.float64)
    albedo = np.asarray(m.albedo, dtype=np.float64)
    valid = np.asarray(m.valid, dtype=bool)
    for what, arr in (("heights", heights), ("albedo", albedo), ("valid", valid)):
        if arr.shape != (n, n):
            raise ValueError(f"{what} must be {n}x{n} for qsz={q}, got {arr.shape}")
    if raw_ok:
        cells = m._raw_cells()
        raw_h, raw_a = cells["h"].astype(np.int16), np.ascontiguousarray(cells["a"])
        dec_h, dec_a, dec_v = _decode_cells(raw_h, raw_a, hs_stored)
        same_valid = np.array_equal(valid, dec_v)
        same_grid = same_valid and np.array_equal(heights, dec_h, equal_nan=True)
        same_h = same_grid and _same(m.hscale, hs_stored)
        same_a = same_valid and np.array_equal(albedo, dec_a)
    else:
        raw_h = raw_a = None
        same_grid = same_h = same_a = False

    if not same_h:
        if np.any(valid & ~np.isfinite(heights)):
            raise ValueError("heights must be finite on valid cells")
        # only HSCALE was changed by the caller: honour it; otherwise the 2021 rule
        hs = np.float32(m.hscale) if same_grid else hscale_2021(heights, valid)
        header[_OFF_HSCALE : _OFF_HSCALE + 4] = np.asarray([hs], dtype=">f4").tobytes()
        raw_h = encode_heights(heights, valid, hs)
    if not same_a:
        raw_a = encode_albedo(albedo, valid)
    tail = raw[RECORD + 3 * n * n :] if (same_h and same_a) else None
    return _assemble(bytes(header), raw_h, raw_a, tail)


def write_map(path, m: Maplet, *, overwrite: bool = True, backup: bool = False):
    """Write ``m`` to ``path`` atomically (see :func:`spctool.formats.atomic.write_bytes`)."""
    return write_bytes(path, format_map(m), overwrite=overwrite, backup=backup)


__all__ = [
    "CELL_DTYPE",
    "HEADER_DTYPE",
    "Maplet",
    "encode_albedo",
    "encode_heights",
    "format_map",
    "hscale_2021",
    "map_file_size",
    "parse_map",
    "read_map",
    "read_maps",
    "write_map",
]
