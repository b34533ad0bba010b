"""Triangle meshes in Wavefront OBJ and legacy VTK POLYDATA files, and shape-file dispatch.

Global shapes reach spctool as SPC ICQ files (:mod:`spctool.formats.icq`,
spc-formats.md §5) or as plain triangle meshes: OBJ files such as the
OSIRIS-REx Bennu models and binary big-endian legacy VTK files such as Gaskell's
SBMT shapes (spc-formats.md §10; fixtures/real/README.md §3–§4).  This module
turns those files into a :class:`TriangleMesh` (vertices in km, body-fixed;
0-based triangles with outward right-hand normals) and back, and
:func:`read_shape` picks the reader from the file's content.

No geometry lives here (areas, volumes, normals of faces: spctool.geometry).

OBJ: ``v x y z`` (extra values ignored), ``vn``, ``f`` with 1-based or negative
(relative) indices in the forms ``i``, ``i/t``, ``i//n``, ``i/t/n``; polygons
with more than three corners are fan-triangulated.  Other statements (``vt``,
``g``, ``o``, ``s``, ``usemtl``, ``l``, …) are ignored; ``#`` lines are kept as
comments.  VTK: legacy ``# vtk DataFile Version`` 2.0–5.1, ``ASCII`` or
``BINARY`` (big-endian), ``DATASET POLYDATA`` with ``POINTS``, ``POLYGONS``
(classic count-prefixed lists or 5.x ``OFFSETS``/``CONNECTIVITY``),
``TRIANGLE_STRIPS``, and ``POINT_DATA`` ``NORMALS``; other attributes are skipped.
"""

from __future__ import annotations

import itertools
import math
import os
import re
from dataclasses import dataclass, field

import numpy as np

from spctool.errors import SpcFormatError
from spctool.formats.atomic import read_text, write_bytes, write_text
from spctool.formats.icq import parse_icq

__all__ = [
    "TriangleMesh",
    "parse_obj",
    "read_obj",
    "format_obj",
    "write_obj",
    "parse_vtk",
    "read_vtk",
    "format_vtk",
    "write_vtk",
    "read_shape",
]


@dataclass(eq=False)
class TriangleMesh:
    """Vertices (n, 3) float64 km, triangles (m, 3) int64 0-based (right-hand normal outward).

    ``vertex_normals`` (n, 3) when the file had them; ``comments`` are the OBJ
    ``#`` lines without the ``#`` (a VTK file's title line); ``path`` names the
    source file in messages.  Vertices no triangle uses are allowed (the Bennu
    OBJ files keep ICQ seam duplicates that way).
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray | None = None
    comments: list[str] = field(default_factory=list)
    path: str | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(self.faces)
        if faces.size == 0:
            faces = faces.reshape(0, 3)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces must have shape (m, 3), got {faces.shape}")
        if faces.size and (faces.min() < 0 or faces.max() >= self.vertices.shape[0]):
            raise ValueError(f"face indices must lie in 0…{self.vertices.shape[0] - 1}")
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        if self.vertex_normals is not None:
            self.vertex_normals = np.ascontiguousarray(self.vertex_normals, dtype=np.float64)
            if self.vertex_normals.shape != self.vertices.shape:
                raise ValueError("vertex_normals must have the shape of vertices")
        self.comments = list(self.comments)

    @property
    def vertex_count(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def face_count(self) -> int:
        return int(self.faces.shape[0])


# =============================================================================================
# OBJ

_OBJ_IGNORED = frozenset(
    "vt vp l p g o s mg usemtl mtllib maplib usemap bevel c_interp d_interp lod shadow_obj trace_obj "
    "ctech stech cstype deg bmat step curv curv2 surf parm trim hole scrv sp end con call csh".split()
)


def _guard_read(path, what: str) -> bytes:
    from spctool.formats.guard import read_bytes

    return read_bytes(path, what)  # regular files only (a FIFO would block), size checked first


def read_obj(path) -> TriangleMesh:
    """Read a Wavefront OBJ triangle (or polygon) mesh."""
    return parse_obj(read_text(path), path)


def parse_obj(text: str, path=None) -> TriangleMesh:
    """Parse OBJ text.  Malformed statements raise :class:`SpcFormatError` naming the line."""
    where = os.fspath(path) if path is not None else None
    text = text.replace("\r\n", "\n").replace("\r", "\n")
    lines = text.split("\n")
    fast = _parse_obj_fast(lines, where)
    if fast is not None:
        return _checked(fast, where)
    return _checked(_parse_obj_slow(lines, where), where)


#: largest vertex coordinate accepted (km): far beyond any body, small enough that bounding boxes,
#: padding and squared distances stay finite
MAX_COORDINATE_KM = 1e12


def _checked(mesh: TriangleMesh, where) -> TriangleMesh:
    """What every stage needs of a shape model: triangles, and finite coordinates of sane size (a
    file ``validate`` passes must never crash a stage)."""
    if mesh.face_count == 0:
        raise SpcFormatError(
            where,
            None,
            f"expected faces (a shape model is a triangle mesh), found {mesh.vertex_count} vertices only",
        )
    big = np.abs(mesh.vertices) > MAX_COORDINATE_KM
    if big.any():
        k = int(np.flatnonzero(big.any(axis=1))[0])
        raise SpcFormatError(
            where,
            None,
            f"expected vertex coordinates within ±{MAX_COORDINATE_KM:g} km, found vertex {k + 1} at "
            f"{mesh.vertices[k].tolist()}",
        )
    return mesh


def _parse_obj_fast(lines: list[str], where) -> TriangleMesh | None:
    """Vectorised path for the common layout (``v x y z``, ``f i j k`` with positive indices)."""
    vlines = [ln for ln in lines if ln.startswith("v ")]
    flines = [ln for ln in lines if ln.startswith("f ")]
    comments = []
    for ln in lines:
        if ln.startswith(("v ", "f ")):
            continue
        s = ln.strip()
        if not s:
            continue
        if s.startswith("#"):
            comments.append(ln.lstrip()[1:])
            continue
        return None  # anything else (vn, g, tabs, ...): the careful path
    if not vlines:
        return None
    vtok = " ".join(vlines).split()
    ftok = " ".join(flines).split()
    if len(vtok) != 4 * len(vlines) or len(ftok) != 4 * len(flines):
        return None
    if any("/" in t for t in ftok[1::4] + ftok[2::4] + ftok[3::4]):
        return None
    try:
        v = np.array(vtok, dtype=object).reshape(-1, 4)[:, 1:].astype(np.float64)
        f = (
            np.array(ftok, dtype=object).reshape(-1, 4)[:, 1:].astype(np.int64)
            if flines
            else np.empty((0, 3), int)
        )
    except (ValueError, TypeError, OverflowError):
        return None
    if set(vtok[0::4]) != {"v"} or (flines and set(ftok[0::4]) != {"f"}):
        return None
    if not np.all(np.isfinite(v)) or (f.size and (f.min() < 1 or f.max() > v.shape[0])):
        return None
    return TriangleMesh(v, f - 1, None, comments, path=where)


def _parse_obj_slow(lines: list[str], where) -> TriangleMesh:
    verts: list[tuple[float, float, float]] = []
    normals: list[tuple[float, float, float]] = []
    faces: list[tuple[int, int, int]] = []
    face_lines: list[int] = []
    normal_refs_match = True
    comments: list[str] = []
    for lineno, raw in enumerate(lines, start=1):
        s = raw.strip()
        if not s:
            continue
        if s.startswith("#"):
            comments.append(raw.lstrip()[1:])
            continue
        parts = s.split()
        key = parts[0]
        if key in ("v", "vn"):
            if len(parts) < 4:
                raise SpcFormatError(where, lineno, f"expected '{key} x y z', found {len(parts) - 1} values")
            vals = []
            for tok in parts[1:4]:
                try:
                    val = float(tok)
                except ValueError:
                    raise SpcFormatError(
                        where, lineno, f"expected a number in '{key}' statement, found {tok!r}"
                    ) from None
                if not math.isfinite(val):
                    raise SpcFormatError(where, lineno, f"expected a finite number, found {tok!r}")
                vals.append(val)
            (verts if key == "v" else normals).append(tuple(vals))
        elif key == "f":
            refs = parts[1:]
            if len(refs) < 3:
                raise SpcFormatError(where, lineno, f"expected at least 3 vertices in 'f', found {len(refs)}")
            idx = []
            for ref in refs:
                fields = ref.split("/")
                try:
                    i = int(fields[0])
                    n = int(fields[2]) if len(fields) >= 3 and fields[2] else None
                    if len(fields) > 3 or (len(fields) >= 2 and fields[1] and int(fields[1]) == 0):
                        raise ValueError
                except ValueError:
                    raise SpcFormatError(
                        where, lineno, f"expected a vertex reference i, i/t, i//n or i/t/n, found {ref!r}"
                    ) from None
                if i == 0:
                    raise SpcFormatError(
                        where, lineno, "expected a vertex index ≠ 0 (OBJ indices are 1-based)"
                    )
                if abs(i) > 2**62:
                    raise SpcFormatError(
                        where, lineno, f"expected a vertex index of sane size, found {ref!r}"
                    )
                i = i - 1 if i > 0 else len(verts) + i
                if i < 0:
                    raise SpcFormatError(
                        where,
                        lineno,
                        f"expected a relative index within the {len(verts)} vertices so far, found {ref!r}",
                    )
                if n is not None:
                    n = n - 1 if n > 0 else len(normals) + n
                    if n != i:
                        normal_refs_match = False
                idx.append(i)
            for k in range(1, len(idx) - 1):  # fan triangulation
                faces.append((idx[0], idx[k], idx[k + 1]))
                face_lines.append(lineno)
        elif key in _OBJ_IGNORED:
            continue
        else:
            raise SpcFormatError(
                where, lineno, f"expected an OBJ statement (v, vn, f, vt, g, o, s, …), found {key!r}"
            )
    if not verts:
        raise SpcFormatError(where, len(lines), "expected 'v' vertex statements, found none")
    v = np.array(verts, dtype=np.float64)
    f = np.array(faces, dtype=np.int64).reshape(-1, 3)
    if f.size and f.max() >= len(verts):
        k = int(np.flatnonzero(f.max(axis=1) >= len(verts))[0])
        raise SpcFormatError(
            where, face_lines[k], f"expected vertex indices up to {len(verts)}, found {int(f[k].max()) + 1}"
        )
    vn = None
    if normals and len(normals) == len(verts) and normal_refs_match:
        vn = np.array(normals, dtype=np.float64)
    return TriangleMesh(v, f, vn, comments, path=where)


def format_obj(mesh: TriangleMesh) -> str:
    """OBJ text: ``#`` comments, ``v`` lines (shortest exact decimals), ``vn`` if any, ``f`` (1-based)."""
    out = ["#" + c.replace("\n", " ") + "\n" for c in mesh.comments]
    n = mesh.vertex_count
    if n:
        out.append(("v %r %r %r\n" * n) % tuple(mesh.vertices.ravel().tolist()))
    if mesh.vertex_normals is not None and n:
        out.append(("vn %r %r %r\n" * n) % tuple(mesh.vertex_normals.ravel().tolist()))
        ref = "f %d//%d %d//%d %d//%d\n"
        f1 = np.repeat(mesh.faces + 1, 2, axis=1)
        out.append((ref * mesh.face_count) % tuple(f1.ravel().tolist()))
    elif mesh.face_count:
        out.append(("f %d %d %d\n" * mesh.face_count) % tuple((mesh.faces + 1).ravel().tolist()))
    return "".join(out)


def write_obj(path, mesh: TriangleMesh, *, overwrite: bool = True, backup: bool = False):
    """Write ``mesh`` as OBJ atomically; returns the backup path or None."""
    return write_text(path, format_obj(mesh), overwrite=overwrite, backup=backup)


# =============================================================================================
# legacy VTK

_VTK_TYPES = {
    "bit": None,
    "unsigned_char": "u1",
    "char": "i1",
    "unsigned_short": "u2",
    "short": "i2",
    "unsigned_int": "u4",
    "int": "i4",
    "unsigned_long": "u8",
    "long": "i8",
    "float": "f4",
    "double": "f8",
    "vtktypeint8": "i1",
    "vtktypeuint8": "u1",
    "vtktypeint16": "i2",
    "vtktypeuint16": "u2",
    "vtktypeint32": "i4",
    "vtktypeuint32": "u4",
    "vtktypeint64": "i8",
    "vtktypeuint64": "u8",
    "vtktypefloat32": "f4",
    "vtktypefloat64": "f8",
    "vtkidtype": "i8",
}
_CELL_SECTIONS = ("VERTICES", "LINES", "POLYGONS", "TRIANGLE_STRIPS")
_TOKEN = re.compile(rb"\S+")


class _VtkReader:
    """A cursor over a legacy VTK file (binary blocks big-endian, or ASCII tokens)."""

    def __init__(self, data: bytes, where):
        self.data = data
        self.where = where
        self.pos = 0
        self.binary = True
        self.block: tuple[int, int, list | None] = (0, 0, None)  # last data block: start, itemsize, tokens

    # -- places for messages
    def place(self, pos: int):
        if self.binary:
            return f"byte {pos}"
        return self.data.count(b"\n", 0, pos) + 1

    def fail(self, pos: int, expected: str):
        raise SpcFormatError(self.where, self.place(pos), expected)

    # -- lines and words
    def line(self, what: str, *, allow_eof: bool = False) -> tuple[int, str] | None:
        """The next non-blank line (start byte, text)."""
        d = self.data
        while True:
            if self.pos >= len(d):
                if allow_eof:
                    return None
                self.fail(self.pos, f"expected {what}, found the end of the file")
            end = d.find(b"\n", self.pos)
            end = len(d) if end < 0 else end
            start = self.pos
            text = d[start:end].decode("latin-1").strip()
            self.pos = end + 1
            if text:
                return start, text

    def peek_word(self) -> str:
        m = re.compile(rb"\s*(\S+)").match(self.data, self.pos)
        return m.group(1).decode("latin-1").upper() if m else ""

    # -- data blocks
    def values(self, count: int, vtype: str, what: str, start_line: int) -> np.ndarray:
        """``count`` values of VTK type ``vtype`` at the cursor (big-endian if binary)."""
        code = _VTK_TYPES.get(vtype.lower())
        if code is None:
            self.fail(
                start_line, f"expected a VTK data type (float, double, int, …) for {what}, found {vtype!r}"
            )
        if self.binary:
            dt = np.dtype(">" + code)
            nbytes = count * dt.itemsize
            if self.pos + nbytes > len(self.data):
                self.fail(
                    self.pos,
                    f"expected {count} {vtype} values ({nbytes} bytes) for {what}, the file ends after "
                    f"{len(self.data) - self.pos} bytes",
                )
            arr = np.frombuffer(self.data, dtype=dt, count=count, offset=self.pos)
            self.block = (self.pos, dt.itemsize, None)
            self.pos += nbytes
            return arr.astype(np.float64 if code[0] == "f" else np.int64)
        # ASCII: the next ``count`` whitespace-separated tokens
        matches = list(itertools.islice(_TOKEN.finditer(self.data, self.pos), count))
        if len(matches) < count:
            self.fail(
                len(self.data),
                f"expected {count} values for {what}, found {len(matches)} before the end of the file",
            )
        self.block = (self.pos, 0, [m.start() for m in matches])
        self.pos = matches[-1].end() if matches else self.pos
        conv = float if code[0] == "f" else int
        try:
            vals = [conv(m.group()) for m in matches]
        except ValueError:
            bad = next(m for m in matches if not _is_vtk_number(m.group(), code[0] == "f"))
            self.fail(
                bad.start(), f"expected {vtype} values for {what}, found {bad.group().decode('latin-1')!r}"
            )
        if code[0] == "f":  # a "float" array holds float32 values, as VTK itself would store them
            return np.array(vals, dtype=np.float64).astype(code).astype(np.float64)
        return np.array(vals, dtype=np.int64)

    def value_pos(self, index: int) -> int:
        """Byte position of value ``index`` of the last data block read."""
        start, size, tokens = self.block
        if tokens is not None:
            return tokens[index] if index < len(tokens) else start
        return start + size * index

    def end_block(self) -> None:
        """Skip the newline that ends a binary block."""
        if self.binary and self.pos < len(self.data) and self.data[self.pos : self.pos + 1] == b"\n":
            self.pos += 1


def _is_vtk_number(tok: bytes, real: bool) -> bool:
    try:
        float(tok) if real else int(tok)
    except ValueError:
        return False
    return True


def read_vtk(path) -> TriangleMesh:
    """Read a legacy VTK POLYDATA file (binary big-endian or ASCII)."""
    return parse_vtk(_guard_read(path, "a VTK file"), path)


def parse_vtk(data: bytes, path=None) -> TriangleMesh:
    """Parse legacy VTK POLYDATA bytes.  Errors name ``byte N`` (binary) or the line (ASCII)."""
    where = os.fspath(path) if path is not None else None
    r = _VtkReader(data, where)
    start, head = r.line("the '# vtk DataFile Version' header")
    if not head.lower().startswith("# vtk datafile version"):
        r.fail(start, f"expected '# vtk DataFile Version x.y' on line 1, found {head[:40]!r}")
    title_end = data.find(b"\n", r.pos)
    title_end = len(data) if title_end < 0 else title_end
    title = data[r.pos : title_end].decode("latin-1").rstrip("\r")
    r.pos = title_end + 1
    start, fmt = r.line("ASCII or BINARY")
    if fmt.upper() not in ("ASCII", "BINARY"):
        r.fail(start, f"expected ASCII or BINARY on line 3, found {fmt[:40]!r}")
    r.binary = fmt.upper() == "BINARY"
    start, ds = r.line("DATASET POLYDATA")
    if [w.upper() for w in ds.split()[:2]] != ["DATASET", "POLYDATA"]:
        r.fail(start, f"expected 'DATASET POLYDATA', found {ds[:40]!r}")

    points = None
    triangles: list[np.ndarray] = []
    normals = None
    attr_count = None
    attr_kind = None
    while True:
        got = r.line("a section", allow_eof=True)
        if got is None:
            break
        start, text = got
        words = text.split()
        key = words[0].upper()
        try:
            if key == "POINTS":
                n, vtype = int(words[1]), words[2]
                points = r.values(3 * n, vtype, "POINTS", start).reshape(n, 3)
                r.end_block()
            elif key in _CELL_SECTIONS:
                ncells, size = int(words[1]), int(words[2])
                if r.peek_word() == "OFFSETS":  # VTK 5.x layout
                    s2, t2 = r.line("OFFSETS")
                    offsets = r.values(ncells, t2.split()[1], f"{key} OFFSETS", s2)
                    r.end_block()
                    s3, t3 = r.line("CONNECTIVITY")
                    if t3.split()[0].upper() != "CONNECTIVITY":
                        r.fail(s3, f"expected CONNECTIVITY after OFFSETS, found {t3[:40]!r}")
                    conn = r.values(size, t3.split()[1], f"{key} CONNECTIVITY", s3)
                    cells = _cells_from_offsets(offsets, conn, r, start, key, points)
                    r.end_block()
                else:
                    conn = r.values(size, "int", key, start)
                    cells = _cells_from_counts(conn, ncells, r, key, points)
                    r.end_block()
                if key in ("POLYGONS", "TRIANGLE_STRIPS"):
                    triangles.append(_triangulate(cells, key))
            elif key == "METADATA":
                while True:  # a METADATA block ends at a blank line
                    if r.pos >= len(data):
                        break
                    end = data.find(b"\n", r.pos)
                    end = len(data) if end < 0 else end
                    blank = not data[r.pos : end].strip()
                    r.pos = end + 1
                    if blank:
                        break
            elif key in ("POINT_DATA", "CELL_DATA"):
                attr_kind, attr_count = key, int(words[1])
            elif key in (
                "NORMALS",
                "VECTORS",
                "SCALARS",
                "TEXTURE_COORDINATES",
                "TENSORS",
                "COLOR_SCALARS",
                "LOOKUP_TABLE",
                "FIELD",
            ):
                if attr_count is None and key != "LOOKUP_TABLE":
                    r.fail(start, f"expected POINT_DATA or CELL_DATA before {key}")
                arr = _skip_or_read_attribute(r, key, words, attr_count, start)
                if key == "NORMALS" and attr_kind == "POINT_DATA":
                    normals = arr.reshape(-1, 3)
            else:
                r.fail(
                    start,
                    f"expected a VTK POLYDATA section (POINTS, POLYGONS, POINT_DATA, …), found {text[:40]!r}",
                )
        except (IndexError, ValueError):
            r.fail(start, f"expected a well-formed '{key}' line, found {text[:60]!r}")
    if points is None:
        r.fail(len(data), "expected a POINTS section, found the end of the file")
    if not triangles:
        r.fail(len(data), "expected a POLYGONS or TRIANGLE_STRIPS section, found the end of the file")
    faces = np.concatenate(triangles)
    if normals is not None and normals.shape[0] != points.shape[0]:
        normals = None
    return _checked(TriangleMesh(points, faces, normals, [title] if title else [], path=where), where)


def _skip_or_read_attribute(r: _VtkReader, key: str, words: list[str], count: int | None, start: int):
    """Read (and return) one POINT_DATA/CELL_DATA attribute block."""
    if key in ("NORMALS", "VECTORS"):
        arr = r.values(3 * count, words[2], key, start)
    elif key == "TENSORS":
        arr = r.values(9 * count, words[2], key, start)
    elif key == "TEXTURE_COORDINATES":
        arr = r.values(int(words[2]) * count, words[3], key, start)
    elif key == "SCALARS":
        ncomp = int(words[3]) if len(words) > 3 else 1
        if r.peek_word() == "LOOKUP_TABLE":
            r.line("LOOKUP_TABLE")
        arr = r.values(ncomp * count, words[2], key, start)
    elif key == "COLOR_SCALARS":
        arr = r.values(int(words[2]) * count, "unsigned_char" if r.binary else "float", key, start)
    elif key == "LOOKUP_TABLE":
        arr = r.values(4 * int(words[2]), "unsigned_char" if r.binary else "float", key, start)
    else:  # FIELD name numArrays, then arrays "name ncomp ntuples type"
        for _ in range(int(words[2])):
            s, t = r.line("a FIELD array")
            w = t.split()
            if w[0] == "NULL_ARRAY":
                continue
            r.values(int(w[1]) * int(w[2]), w[3], f"FIELD array {w[0]}", s)
            r.end_block()
        return None
    r.end_block()
    return arr


def _check_indices(conn: np.ndarray, is_count: np.ndarray | None, r: _VtkReader, key: str, points) -> None:
    """Point indices must lie in 0…n−1 (POINTS comes first in a POLYDATA file)."""
    if points is None:
        r.fail(r.value_pos(0), f"expected POINTS before {key}")
    bad = (conn < 0) | (conn >= points.shape[0])
    if is_count is not None:
        bad &= ~is_count
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        r.fail(
            r.value_pos(k), f"expected {key} point indices in 0…{points.shape[0] - 1}, found {int(conn[k])}"
        )


def _cells_from_counts(conn: np.ndarray, ncells: int, r: _VtkReader, key: str, points) -> list:
    """Split a classic count-prefixed cell list; uniform lists are reshaped at once."""
    if ncells == 0:
        return []
    is_count = np.zeros(conn.size, dtype=bool)
    k = int(conn[0]) if conn.size else 0
    if k >= 1 and conn.size == ncells * (k + 1) and np.all(conn[:: k + 1] == k):
        is_count[:: k + 1] = True
        _check_indices(conn, is_count, r, key, points)
        return [conn.reshape(ncells, k + 1)[:, 1:]]
    cells = []
    p = 0
    for c in range(ncells):
        if p >= conn.size:
            r.fail(r.value_pos(p), f"expected {ncells} {key} cells, found {c}")
        k = int(conn[p])
        if k < 1 or p + 1 + k > conn.size:
            r.fail(r.value_pos(p), f"expected a valid point count for {key} cell {c}, found {k}")
        is_count[p] = True
        cells.append(conn[p + 1 : p + 1 + k][None, :])
        p += 1 + k
    if p != conn.size:
        r.fail(
            r.value_pos(p),
            f"expected {conn.size} {key} values to hold {ncells} cells, {conn.size - p} left over",
        )
    _check_indices(conn, is_count, r, key, points)
    return cells


def _cells_from_offsets(
    offsets: np.ndarray, conn: np.ndarray, r: _VtkReader, start: int, key: str, points
) -> list:
    if offsets.size == 0:
        return []
    if offsets[0] != 0 or offsets[-1] != conn.size or np.any(np.diff(offsets) < 1):
        r.fail(start, f"expected increasing {key} OFFSETS from 0 to {conn.size}")
    _check_indices(conn, None, r, key, points)
    sizes = np.diff(offsets)
    if sizes.size and np.all(sizes == sizes[0]):
        return [conn.reshape(-1, int(sizes[0]))]
    return [conn[a:b][None, :] for a, b in zip(offsets[:-1].tolist(), offsets[1:].tolist())]


def _triangulate(cells: list, key: str) -> np.ndarray:
    """Triangles of polygons (fans) or triangle strips (alternating), in cell order."""
    out = []
    for block in cells:  # each block: (ncells, k) cells with a common k, in file order
        k = block.shape[1]
        if k < 3:
            continue
        if key == "TRIANGLE_STRIPS":
            tris = [
                block[:, [t, t + 1, t + 2]] if t % 2 == 0 else block[:, [t + 1, t, t + 2]]
                for t in range(k - 2)
            ]
        else:
            tris = [block[:, [0, t, t + 1]] for t in range(1, k - 1)]
        out.append(np.stack(tris, axis=1).reshape(-1, 3))
    if not out:
        return np.empty((0, 3), np.int64)
    return np.concatenate(out).astype(np.int64)


def format_vtk(
    mesh: TriangleMesh, *, binary: bool = True, points_type: str = "double", title: str | None = None
) -> bytes:
    """Legacy VTK 3.0 POLYDATA bytes (big-endian if binary): POINTS, POLYGONS, POINT_DATA NORMALS if any.

    ``points_type`` ``"double"`` (lossless, default) or ``"float"`` (Gaskell's SBMT files).
    """
    if points_type not in ("float", "double"):
        raise ValueError("points_type must be 'float' or 'double'")
    if mesh.vertex_count >= 2**31:
        raise ValueError("too many vertices for 32-bit VTK indices")
    if title is None:
        title = mesh.comments[0].strip() if mesh.comments else "spctool shape"
    title = (title.replace("\n", " ") or "spctool shape")[:255]
    n, m = mesh.vertex_count, mesh.face_count
    dt = ">f4" if points_type == "float" else ">f8"
    parts = [
        f"# vtk DataFile Version 3.0\n{title}\n{'BINARY' if binary else 'ASCII'}\nDATASET POLYDATA\n"
        f"POINTS {n} {points_type}\n".encode("latin-1")
    ]
    cells = np.empty((m, 4), dtype=np.int64)
    cells[:, 0] = 3
    cells[:, 1:] = mesh.faces
    fmt = "%.9g" if points_type == "float" else "%r"
    if binary:
        parts.append(mesh.vertices.astype(dt).tobytes() + b"\n")
        parts.append(f"POLYGONS {m} {4 * m}\n".encode() + cells.astype(">i4").tobytes() + b"\n")
    else:
        vals = (
            mesh.vertices.astype(np.float32).astype(np.float64) if points_type == "float" else mesh.vertices
        )
        parts.append(((f"{fmt} {fmt} {fmt}\n" * n) % tuple(vals.ravel().tolist())).encode())
        parts.append(
            f"POLYGONS {m} {4 * m}\n".encode()
            + (("%d %d %d %d\n" * m) % tuple(cells.ravel().tolist())).encode()
        )
    if mesh.vertex_normals is not None:
        parts.append(f"POINT_DATA {n}\nNORMALS Normals {points_type}\n".encode())
        if binary:
            parts.append(mesh.vertex_normals.astype(dt).tobytes() + b"\n")
        else:
            vals = mesh.vertex_normals
            if points_type == "float":
                vals = vals.astype(np.float32).astype(np.float64)
            parts.append(((f"{fmt} {fmt} {fmt}\n" * n) % tuple(vals.ravel().tolist())).encode())
    return b"".join(parts)


def write_vtk(
    path,
    mesh: TriangleMesh,
    binary: bool = True,
    *,
    points_type: str = "double",
    overwrite: bool = True,
    backup: bool = False,
):
    """Write ``mesh`` as legacy VTK POLYDATA atomically (see :func:`format_vtk`)."""
    return write_bytes(
        path, format_vtk(mesh, binary=binary, points_type=points_type), overwrite=overwrite, backup=backup
    )


# =============================================================================================
# dispatch

_SINGLE_INT = re.compile(r"\s*[+-]?\d+\s*")


def read_shape(path):
    """Read a global shape: an ICQ file (→ ``IcqShape``), an OBJ or a legacy VTK file (→ ``TriangleMesh``).

    Decided by content, not by name: ``# vtk DataFile`` starts a VTK file; a
    first line holding a single integer starts an ICQ file (which must then have
    6(Q+1)² vertex lines); ``v``/``f`` statements make an OBJ file.
    """
    data = _guard_read(path, "a shape model")
    if data.lstrip()[:14].lower() == b"# vtk datafile":
        return parse_vtk(data, path)
    if b"\0" in data[:4096]:
        raise SpcFormatError(
            path,
            "byte " + str(data.index(b"\0")),
            "expected an ICQ, OBJ or VTK shape file, found binary data",
        )
    text = data.decode("latin-1").replace("\r\n", "\n").replace("\r", "\n")
    first = text.split("\n", 1)[0]
    if _SINGLE_INT.fullmatch(first):
        if len(first.strip().lstrip("+-")) > 9:  # no Q has 10 digits (and int() refuses 4300+)
            raise SpcFormatError(
                path, 1, f"expected the ICQ resolution Q, found a {len(first.strip())}-digit number"
            )
        return parse_icq(text, path)
    if re.search(r"(?m)^\s*v\s", text):
        return parse_obj(text, path)
    raise SpcFormatError(
        path,
        1,
        "expected a shape file: ICQ (Q on line 1), OBJ ('v x y z' lines) or legacy VTK "
        f"('# vtk DataFile Version'), found {first[:40]!r}",
    )
