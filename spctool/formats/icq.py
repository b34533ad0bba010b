"""ICQ global shape models (``SHAPEFILES/SHAPE.TXT``, ``*.ICQ``) — spc-formats.md §5 and the §9 ICQ checklist.

An ICQ ("implicitly connected quadrilateral") shape is a cube whose six faces are
each divided into Q × Q cells and projected onto the body.  The file holds Q on
line 1 (SPC writes ``I12``) and then 6(Q+1)² vertex lines ``x y z`` in km,
body-fixed, in the order **face F = 1…6 (slowest), J = 0…Q, I = 0…Q (fastest)**
(§5.1).  A 4th number on the first vertex line means every line carries a vertex
albedo (§5.1, §8 item 14).

What this module offers:

* :class:`IcqShape` — ``vertices[F-1, J, I, xyz]`` (and optional ``albedo``),
  remembering the parsed text so that an unchanged shape is rewritten byte for
  byte and a partly changed one rewrites only the changed lines (§0.3).
* :func:`parse_icq` / :func:`read_icq` / :func:`format_icq` / :func:`write_icq`.
  Numbers are read list-directed (D/E/Q or letterless exponents, commas,
  trailing text; §0.3).  Writers: ``style="spc"`` (``I12`` then ``3F12.5``, SPC's
  own layout) or ``style="exact"`` (17 significant digits, ``ES24.16``-like, a
  lossless round trip).
* The cube-face geometry of §5.2: :func:`icq_face_point`, :func:`icq_cube_grid`,
  :func:`icq_face_coords`, the 12 seam identities (:func:`seam_identity_pairs`),
  the merge map (:func:`icq_merge_map`, 6Q² + 2 distinct vertices), the
  outward-counter-clockwise quads (:func:`icq_quads`) and their triangles.
* Conversions to and from :class:`spctool.formats.mesh.TriangleMesh` live in
  :mod:`spctool.formats.icq_mesh` (the mesh module reads any shape file, ICQ too).

Speed: reading and writing go through small numba kernels (:mod:`spctool.formats._icqkernels`; an
SPC-style q = 512 shape, 1.58 M vertices, reads or writes in well under a second; files below
~20 000 vertices use plain Python and never start numba: importing this module does not).  The reader
converts decimal numbers with correct rounding (Clinger's fast path, and an
exact 128-bit midpoint check for 16–18 digit mantissas); tokens it cannot settle
(more than 18 significant digits, extreme exponents) go to the tolerant Python
parser :func:`spctool.formats.fortran.parse_number`, so results are always
identical to it.
"""

from __future__ import annotations

import functools
import math
import os
import re
from dataclasses import dataclass, field

import numpy as np

from spctool.errors import SpcFormatError
from spctool.formats import fortran
from spctool.formats.atomic import write_bytes

__all__ = [
    "IcqShape",
    "parse_icq",
    "read_icq",
    "format_icq",
    "write_icq",
    "icq_index",
    "icq_face_point",
    "icq_cube_grid",
    "icq_face_coords",
    "seam_identity_pairs",
    "icq_merge_map",
    "icq_quads",
    "icq_triangles",
    "seam_mismatch",
    "unify_seams",
    "ICQ_STYLES",
]

ICQ_STYLES = ("spc", "exact")

# =============================================================================================
# cube-face geometry (§5.2)


def icq_index(q: int, i, j, face):
    """Zero-based flat vertex index of v(I, J, F) (face 1-based): (F−1)(Q+1)² + J(Q+1) + I (§5.1)."""
    n = q + 1
    return (np.asarray(face) - 1) * n * n + np.asarray(j) * n + np.asarray(i)


def icq_face_point(face, a, b) -> np.ndarray:
    """Point of cube face ``face`` (1…6) at face coordinates (a, b) ∈ [−1, 1]² (§5.2 table).

    ``face``, ``a`` and ``b`` broadcast; the result has a trailing xyz axis.
    F1 +Z (a, −b, 1); F2 −Y (a, −1, −b); F3 −X (−1, −a, −b); F4 +Y (−a, 1, −b);
    F5 +X (1, a, −b); F6 −Z (a, b, −1).
    """
    face, a, b = np.broadcast_arrays(
        np.asarray(face), np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    )
    if face.size and (face.min() < 1 or face.max() > 6):
        raise ValueError("ICQ face numbers run from 1 to 6")
    one = np.ones_like(a)
    x = np.select(
        [face == 1, face == 2, face == 3, face == 4, face == 5, face == 6], [a, a, -one, -a, one, a]
    )
    y = np.select(
        [face == 1, face == 2, face == 3, face == 4, face == 5, face == 6], [-b, -one, -a, one, a, b]
    )
    z = np.select(
        [face == 1, face == 2, face == 3, face == 4, face == 5, face == 6], [one, -b, -b, -b, -b, -one]
    )
    # + 0.0 turns −0.0 into +0.0: seam duplicates come from different faces, and a negated
    # zero on one face only would be written "-0.00000" beside "0.00000".
    return np.stack([x, y, z], axis=-1) + 0.0


@functools.lru_cache(maxsize=8)
def _cube_grid_cached(q: int) -> np.ndarray:
    n = q + 1
    # a = −1 + 2I/Q computed as (2I − Q)/Q: one correctly rounded division, so
    # a(Q − I) == −a(I) bit for bit and every seam duplicate is bit-identical.
    a = (2.0 * np.arange(n) - q) / q
    aa = np.broadcast_to(a[None, :], (n, n))  # varies with I (axis 1 of a face)
    bb = np.broadcast_to(a[:, None], (n, n))  # varies with J (axis 0 of a face)
    grid = np.stack([icq_face_point(f, aa, bb) for f in range(1, 7)])
    grid.flags.writeable = False
    return grid


def icq_cube_grid(q: int) -> np.ndarray:
    """The (6, Q+1, Q+1, 3) ICQ grid on the cube [−1, 1]³, indexed [F−1, J, I, xyz] (§5.2).

    Seam duplicates are bit-identical; normalising each point (and scaling)
    gives a sphere or an ellipsoid with the same property.
    """
    _check_q(q)
    return _cube_grid_cached(int(q)).copy()


def icq_face_coords(points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`icq_face_point` for directions: (face 1…6, a, b) of the cube face hit by each ray.

    The face is the one of the dominant coordinate; ties (cube edges) go to the
    first of +Z, −Z, +X, −X, +Y, −Y in that order.  ``a`` and ``b`` are in
    [−1, 1]; the cell containing the point has I = ⌊(a+1)Q/2⌋, J = ⌊(b+1)Q/2⌋
    (clip to Q−1).  Zero vectors raise ``ValueError``.
    """
    p = np.asarray(points, dtype=np.float64)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    ax, ay, az = np.abs(x), np.abs(y), np.abs(z)
    if np.any((ax == 0) & (ay == 0) & (az == 0)):
        raise ValueError("the zero vector has no ICQ face")
    zdom = (az >= ax) & (az >= ay)
    xdom = ~zdom & (ax >= ay)
    face = np.where(zdom, np.where(z > 0, 1, 6), np.where(xdom, np.where(x > 0, 5, 3), np.where(y > 0, 4, 2)))
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.select(
            [face == 1, face == 2, face == 3, face == 4, face == 5, face == 6],
            [x / z, -x / y, y / x, -x / y, y / x, -x / z],
        )
        b = np.select(
            [face == 1, face == 2, face == 3, face == 4, face == 5, face == 6],
            [-y / z, z / y, z / x, -z / y, -z / x, -y / z],
        )
    return face.astype(np.int64), a, b


# the 12 edge identities of §5.2, as ((I, J, F), (I, J, F)) with "t" = running index and
# "Q-t" = Q − running index.
_SEAMS = (
    (("t", "Q", 6), ("Q-t", "Q", 4)),
    (("Q", "t", 6), ("t", "Q", 5)),
    (("t", 0, 6), ("t", "Q", 2)),
    (("Q", "t", 5), (0, "t", 4)),
    (("t", 0, 5), ("Q", "Q-t", 1)),
    (("Q", "t", 4), (0, "t", 3)),
    (("t", 0, 4), ("Q-t", 0, 1)),
    (("Q", "t", 3), (0, "t", 2)),
    (("t", 0, 3), (0, "t", 1)),
    ((0, "t", 6), ("Q-t", "Q", 3)),
    (("t", 0, 2), ("t", "Q", 1)),
    ((0, "t", 5), ("Q", "t", 2)),
)


@functools.lru_cache(maxsize=8)
def _seam_pairs_cached(q: int) -> np.ndarray:
    t = np.arange(q + 1)

    def coord(c):
        if c == "t":
            return t
        if c == "Q-t":
            return q - t
        if c == "Q":
            return np.full_like(t, q)
        return np.full_like(t, int(c))

    out = []
    for (i1, j1, f1), (i2, j2, f2) in _SEAMS:
        out.append(
            np.stack([icq_index(q, coord(i1), coord(j1), f1), icq_index(q, coord(i2), coord(j2), f2)], 1)
        )
    pairs = np.concatenate(out).astype(np.int64)
    pairs.flags.writeable = False
    return pairs


def seam_identity_pairs(q: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat vertex indices ``(a, b)`` with v[a[k]] == v[b[k]] required: the §5.2 edge identities.

    Two (12(Q+1),) int64 arrays, identity by identity in the order of the §5.2
    table (left column then right column, row by row), I = 0…Q within each.  The
    corner relations follow by transitivity.  Read-only.  ``np.stack(..., 1)``
    gives the (12(Q+1), 2) pair table.
    """
    _check_q(q)
    pairs = _seam_pairs_cached(int(q))
    return pairs[:, 0], pairs[:, 1]


@functools.lru_cache(maxsize=8)
def _merge_map_cached(q: int) -> np.ndarray:
    n = 6 * (q + 1) ** 2
    rep = np.arange(n, dtype=np.int64)
    pairs = _seam_pairs_cached(q)
    a, b = pairs[:, 0], pairs[:, 1]
    while True:  # label propagation over the seam graph; converges in a few sweeps
        lo = np.minimum(rep[a], rep[b])
        if np.array_equal(rep[a], lo) and np.array_equal(rep[b], lo):
            break
        np.minimum.at(rep, a, lo)
        np.minimum.at(rep, b, lo)
        rep = rep[rep]
    rep.flags.writeable = False
    return rep


def icq_merge_map(q: int) -> np.ndarray:
    """(6(Q+1)²,) representative of every flat vertex: the lowest index among its seam duplicates.

    There are 6Q² + 2 distinct representatives (``np.unique(map)``).  Read-only.
    """
    _check_q(q)
    return _merge_map_cached(int(q))


def icq_quads(q: int) -> np.ndarray:
    """(6Q², 4) flat vertex indices of the quads f(I, J, F) in F, J, I order (§5.2).

    Corner order v(I,J), v(I,J+1), v(I+1,J+1), v(I+1,J): counter-clockwise seen
    from outside (right-hand normal outward).  Indices are file indices, not merged.
    """
    _check_q(q)
    f, j, i = np.meshgrid(np.arange(1, 7), np.arange(q), np.arange(q), indexing="ij")
    f, j, i = f.ravel(), j.ravel(), i.ravel()
    return np.stack(
        [
            icq_index(q, i, j, f),
            icq_index(q, i, j + 1, f),
            icq_index(q, i + 1, j + 1, f),
            icq_index(q, i + 1, j, f),
        ],
        axis=1,
    ).astype(np.int64)


def icq_triangles(q: int, *, merged: bool = True) -> np.ndarray:
    """(12Q², 3) triangles with outward normals, two per quad in quad order (§5.2).

    Quad (I,J) gives (I,J),(I,J+1),(I+1,J) then (I+1,J),(I,J+1),(I+1,J+1) — the
    split GIANT uses.  ``merged=True`` replaces seam duplicates by their
    representative (:func:`icq_merge_map`), so the triangles share vertices
    across face edges and form a closed surface.
    """
    quads = icq_quads(q)
    tri = np.empty((2 * quads.shape[0], 3), dtype=np.int64)
    tri[0::2] = quads[:, [0, 1, 3]]
    tri[1::2] = quads[:, [3, 1, 2]]
    if merged:
        tri = icq_merge_map(q)[tri]
    return tri


def _check_q(q) -> None:
    if not isinstance(q, (int, np.integer)) or isinstance(q, bool) or q < 1:
        raise ValueError(f"ICQ Q must be a positive integer, got {q!r}")


# =============================================================================================
# the dataclass


@dataclass
class _IcqSource:
    """What was parsed: the file's bytes (LF line ends), and the values as parsed (to detect changes)."""

    data: bytes
    vertices: np.ndarray
    albedo: np.ndarray | None


@dataclass(eq=False)
class IcqShape:
    """An ICQ shape: ``vertices[F−1, J, I, xyz]`` in km (body-fixed), optional ``albedo[F−1, J, I]``.

    ``path`` is the file it came from (for messages).  A parsed shape remembers
    its text; :func:`format_icq` returns it unchanged when the values are unchanged.
    """

    q: int
    vertices: np.ndarray
    albedo: np.ndarray | None = None
    path: str | None = field(default=None, repr=False)
    _source: _IcqSource | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        _check_q(self.q)
        self.q = int(self.q)
        n = self.q + 1
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64)
        if self.vertices.shape != (6, n, n, 3):
            raise ValueError(
                f"ICQ vertices for Q = {self.q} must have shape {(6, n, n, 3)}, got {self.vertices.shape}"
            )
        if self.albedo is not None:
            self.albedo = np.ascontiguousarray(self.albedo, dtype=np.float64)
            if self.albedo.shape != (6, n, n):
                raise ValueError(
                    f"ICQ albedo for Q = {self.q} must have shape {(6, n, n)}, got {self.albedo.shape}"
                )

    @property
    def vertex_count(self) -> int:
        """6(Q+1)², the number of vertex lines (seam duplicates included)."""
        return 6 * (self.q + 1) ** 2

    def flat_vertices(self) -> np.ndarray:
        """(6(Q+1)², 3) vertices in file order (a view)."""
        return self.vertices.reshape(-1, 3)

    def flat_albedo(self) -> np.ndarray | None:
        """(6(Q+1)²,) albedo in file order (a view), or None."""
        return None if self.albedo is None else self.albedo.reshape(-1)

    def copy(self) -> IcqShape:
        """A deep copy that still remembers the parsed text."""
        return IcqShape(
            self.q,
            self.vertices.copy(),
            None if self.albedo is None else self.albedo.copy(),
            self.path,
            self._source,
        )


# =============================================================================================
# the numba kernels (spctool.formats._icqkernels), imported where a table is large enough to pay for them

# Below this many numbers the plain-Python reader/writer is used: the same results, without the
# one-off cost (~0.5–1 s) of starting numba in a fresh process.
_KERNEL_MIN_VALUES = 60_000
_PLAIN_MAX_VALUES = 1_000_000  # plain rows up to this many values (q ≈ 230) read by _parse_rows_plain


# =============================================================================================
# reading

_INT_RE = re.compile(r"[+-]?\d+")


def parse_icq(text: str, path=None) -> IcqShape:
    """Parse ICQ text (§5.1).  Malformed input raises :class:`SpcFormatError` naming the line."""
    text = text.replace("\r\n", "\n").replace("\r", "\n")
    return _parse_bytes(text.encode("latin-1", errors="replace"), path)


def read_icq(path) -> IcqShape:
    """Read an ICQ file (``SHAPEFILES/SHAPE.TXT`` or ``*.ICQ``)."""
    from spctool.formats.guard import read_bytes

    data = read_bytes(path, "an ICQ shape file")  # regular files only, size checked before reading
    if b"\r" in data:
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    return _parse_bytes(data, path)


def _parse_bytes(data: bytes, path) -> IcqShape:
    # mirrors GET_MODEL.f: READ(49,*) Q; READ(49,FMT='(A100)') LINE; READ(LINE,*) (VEC(K,I,J,F),K=1,3)[,A0]
    where = os.fspath(path) if path is not None else None
    nl = data.find(b"\n")
    first = data[: nl if nl >= 0 else len(data)].decode("latin-1")
    toks = fortran.tokens(first)
    if not toks or not _INT_RE.fullmatch(toks[0]):
        found = toks[0] if toks else "an empty line"
        raise SpcFormatError(
            where, 1, f"expected Q (cells per cube-face edge, an integer) on line 1, found {found!r}"
        )
    q = int(toks[0])
    if q < 1:
        raise SpcFormatError(where, 1, f"expected Q ≥ 1 on line 1, found {q}")
    nvert = 6 * (q + 1) ** 2
    # count the lines first: a wrong Q must not allocate a huge array
    body_lines = data.count(b"\n", nl + 1) + (0 if data.endswith(b"\n") else 1) if nl >= 0 else 0
    if body_lines < nvert:
        raise SpcFormatError(
            where,
            body_lines + 2,
            f"expected 6(Q+1)² = {nvert} vertex lines for Q = {q}, the file ends after {body_lines}",
        )
    second_end = data.find(b"\n", nl + 1)
    second = data[nl + 1 : second_end if second_end >= 0 else len(data)].decode("latin-1")
    # GET_MODEL.f: READ(49,FMT='(A100)') LINE; N counts columns K=2..100 where LINE(K-1) is not blank and
    # LINE(K) is; the vertices are read only when N is 3 (x y z) or 4 (x y z albedo)
    line100 = second[:100].ljust(100)
    n_tok = sum(1 for k in range(1, 100) if line100[k - 1] != " " and line100[k] == " ")
    if n_tok not in (3, 4):
        raise SpcFormatError(
            where,
            2,
            "expected 3 or 4 blank-separated values in columns 1-99 of the first vertex line "
            f"(GET_MODEL counts {n_tok}, and then reads no vertex at all)",
        )
    ncols = n_tok
    what = "x y z albedo" if ncols == 4 else "x y z"
    out, end = _rows_kept(data, nl + 1, nvert, ncols, where, what, q)
    rest = data[end:]
    warnings: list[tuple[int, str]] = []
    if rest.strip():
        # GET_MODEL reads 6(Q+1)² vertex records and closes the file: what follows is never read
        extra_line = nvert + 2 + rest[: len(rest) - len(rest.lstrip())].count(b"\n")
        warnings.append(
            (
                extra_line,
                f"text after the 6(Q+1)² = {nvert} vertex lines for Q = {q} is not read by GET_MODEL",
            )
        )
    table = out.reshape(nvert, ncols)
    n = q + 1
    vertices = np.ascontiguousarray(table[:, :3]).reshape(6, n, n, 3)
    albedo = np.ascontiguousarray(table[:, 3]).reshape(6, n, n) if ncols == 4 else None
    source = _IcqSource(data, vertices.copy(), None if albedo is None else albedo.copy())
    shape = IcqShape(q, vertices, albedo, where, source)
    shape.__dict__["_spc_warnings"] = warnings
    return shape


_PLAIN = b"0123456789.+-eE \t\r\n"  # the bytes of plain decimal rows


#: parsed rows are kept (formats/derived.py) for files of this many values or more (q = 64: 76,050 values
#: parsed in ~40 ms, read back from the cache in ~4 ms with the file's digest) up to
#: ``_PLAIN_MAX_VALUES`` (8 MB an entry)
_KEEP_MIN_VALUES = 20_000
_ROWS_KIND = "icq-rows-v1"  # the readers' version: a change to what they return needs a new name


def _rows_kept(data: bytes, pos: int, nvert: int, ncols: int, where, what: str, q: int):
    """The vertex rows of ``data`` as (values, offset after the rows), read by :func:`_parse_rows`
    or, when this file's exact bytes were read before, from the cache of derived values (keyed by a
    digest of every byte of the file: a changed file is read again; the entry holds the values and,
    last, the offset)."""
    n_values = nvert * ncols
    if not _KEEP_MIN_VALUES <= n_values <= _PLAIN_MAX_VALUES:
        return _parse_rows(data, pos, nvert, ncols, where, what, q)
    from spctool.formats import derived

    key = derived.digest(np.frombuffer(data, dtype=np.uint8))
    kept = derived.lookup_array(_ROWS_KIND, key, (n_values + 1,))
    if kept is not None and 0 <= kept[-1] <= len(data) and kept[-1] == int(kept[-1]):
        return kept[:-1], int(kept[-1])
    out, end = _parse_rows(data, pos, nvert, ncols, where, what, q)
    derived.store_array(_ROWS_KIND, key, np.append(out, float(end)))
    return out, end


def _parse_rows(data: bytes, pos: int, nvert: int, ncols: int, where, what: str, q: int):
    """The vertex rows read by the fastest reader that can read them (errors name the line)."""
    n_values = nvert * ncols
    plain = n_values <= _PLAIN_MAX_VALUES and (n_values < _KERNEL_MIN_VALUES or not _kernel_cached())
    fast = _parse_rows_plain(data, pos, nvert, ncols) if plain else None
    if fast is not None:
        return fast
    if n_values < _KERNEL_MIN_VALUES:
        return _parse_rows_python(data, pos, nvert, ncols, where, what)
    return _parse_rows_kernel(data, pos, nvert, ncols, where, what, q)


def _kernel_cached() -> bool:
    """Whether the reader kernel is in numba's on-disk cache (then it is the fastest reader; until it
    is, plain rows are read without compiling it: a first run spends no 3 s on it)."""
    try:
        from spctool.formats._icqkernels import parse_records

        return os.path.exists(parse_records._cache._cache_file._index_path)
    except Exception:  # another numba's internals: compile as before
        return True


def _parse_rows_plain(data: bytes, pos: int, nvert: int, ncols: int):
    """The common case at C speed, or None: every vertex line holds exactly ``ncols`` plain decimal
    numbers (``[+-]digits[.digits][E[+-]digits]``, as SPC writes them), converted by Python's
    correctly rounded ``float`` (the value :func:`fortran.parse_number` and the kernel give).  Any
    other line (Fortran's ``D`` or letterless exponents, commas, repeat counts, extra values, an
    error to report) returns None: the exact readers take the file (no numba compilation for the
    plain files of a first run)."""
    lines = data[pos:].split(b"\n", nvert)
    if len(lines) < nvert:
        return None
    body = lines[:nvert]
    if any(b.translate(None, _PLAIN) for b in body):  # a byte outside the plain set
        return None
    toks = b" ".join(body).split()
    if len(toks) != nvert * ncols or any(len(b.split()) != ncols for b in body):
        return None
    try:
        out = np.array([float(t) for t in toks], dtype=np.float64)
    except ValueError:  # e.g. Fortran's letterless exponent 1.0-05
        return None
    if not np.isfinite(out).all():
        return None
    end = len(data) if len(lines) <= nvert else len(data) - len(lines[nvert])
    return out, end


def _parse_rows_python(data: bytes, pos: int, nvert: int, ncols: int, where, what: str):
    """The tolerant line-by-line reader (fortran.read_reals), for small files: no numba start-up."""
    lines = data[pos:].decode("latin-1").split("\n", nvert)
    out = np.empty(nvert * ncols, dtype=np.float64)
    for k in range(nvert):
        vals = fortran.read_reals(lines[k], ncols, path=where, line=k + 2, what=f"numbers ({what})")
        if not all(map(math.isfinite, vals)):
            raise SpcFormatError(
                where, k + 2, f"expected finite numbers ({what}), found {lines[k].strip()!r}"
            )
        out[k * ncols : (k + 1) * ncols] = vals
    end = len(data) if len(lines) <= nvert else len(data) - len(lines[nvert].encode("latin-1"))
    return out, end


def _parse_rows_kernel(data: bytes, pos: int, nvert: int, ncols: int, where, what: str, q: int):
    from spctool.formats._icqkernels import parse_records  # numba only for shapes that pay for it

    buf = np.frombuffer(data, dtype=np.uint8)
    out = np.empty(nvert * ncols, dtype=np.float64)
    slow = np.empty((min(4096, nvert * ncols), 3), dtype=np.int64)
    status, rec, col, bpos, end, nslow = parse_records(buf, pos, nvert, ncols, out, slow)
    if status == 4:  # many tokens need the Python parser: rerun with room for all of them
        slow = np.empty((nvert * ncols, 3), dtype=np.int64)
        status, rec, col, bpos, end, nslow = parse_records(buf, pos, nvert, ncols, out, slow)
    if status != 0:
        line = rec + 2
        if status == 1:
            stop = bpos
            while stop < len(data) and data[stop] not in b" \t,\r\n" and stop - bpos < 40:
                stop += 1
            tok = data[bpos:stop].decode("latin-1")
            raise SpcFormatError(
                where, line, f"expected {ncols} numbers ({what}), found {tok!r} at value {col + 1}"
            )
        if status == 2:
            raise SpcFormatError(where, line, f"expected {ncols} numbers ({what}), found {col}")
        raise SpcFormatError(
            where, line, f"expected 6(Q+1)² = {nvert} vertex lines for Q = {q}, the file ends after {rec}"
        )
    for s, e, idx in slow[:nslow].tolist():
        tok = data[s:e].decode("latin-1")
        try:
            value = fortran.parse_number(tok)
        except ValueError:  # an exponent beyond double precision (gfortran would store Infinity)
            value = math.inf
        if not math.isfinite(value):
            raise SpcFormatError(where, idx // ncols + 2, f"expected a finite number ({what}), found {tok!r}")
        out[idx] = value
    return out, end


# =============================================================================================
# writing


def format_icq(shape: IcqShape, style: str = "spc", *, seams: str = "check") -> str:
    """ICQ text for ``shape``.

    * An unchanged parsed shape returns its original text (byte-identical).  If
      only some values changed, only those vertex lines are regenerated (§0.3).
    * ``style="spc"``: Q as ``I12``, vertices ``3F12.5`` (albedo as a 4th
      ``F12.5``), SPC's own layout; values round to 1e−5 km.  A value that does
      not fit (|x| ≥ 1e5 km, or ≥ 1e4 km if negative, so that a blank still
      separates the fields) raises ``ValueError`` — use ``style="exact"``.
    * ``style="exact"``: 17 significant digits (``ES24.16``-like, same text as
      Python ``'%24.16E'``), so reading the file back gives identical doubles.
    * ``seams``: ``"check"`` (default) refuses to write seam duplicates
      (§5.2) that differ; ``"unify"`` writes every duplicate with its
      representative's value (:func:`icq_merge_map`); ``"keep"`` writes them as they are.
    """
    return bytes(_format_bytes(shape, style, seams)).decode("latin-1")


def write_icq(
    path,
    shape: IcqShape,
    *,
    style: str = "spc",
    seams: str = "check",
    overwrite: bool = True,
    backup: bool = False,
):
    """Write ``shape`` to ``path`` atomically (see :func:`format_icq`); returns the backup path or None."""
    return write_bytes(path, _format_bytes(shape, style, seams), overwrite=overwrite, backup=backup)


def _format_bytes(shape: IcqShape, style: str, seams: str):
    if style not in ICQ_STYLES:
        raise ValueError(f"ICQ style must be one of {ICQ_STYLES}, got {style!r}")
    if seams not in ("check", "unify", "keep"):
        raise ValueError(f"seams must be 'check', 'unify' or 'keep', got {seams!r}")
    q = shape.q
    vertices = shape.flat_vertices()
    albedo = shape.flat_albedo()
    src = shape._source
    same_layout = (
        src is not None
        and src.vertices.shape == shape.vertices.shape
        and (src.albedo is None) == (albedo is None)
    )
    if same_layout:
        changed = np.any(src.vertices.reshape(-1, 3) != vertices, axis=1)
        if albedo is not None:
            changed |= src.albedo.reshape(-1) != albedo
        if not changed.any():
            return src.data
    if seams == "unify":
        rep = icq_merge_map(q)
        vertices = vertices[rep]
        albedo = None if albedo is None else albedo[rep]
    elif seams == "check":
        _check_seams(q, vertices, albedo, shape.path)
    table = vertices if albedo is None else np.concatenate([vertices, albedo[:, None]], axis=1)
    if same_layout:
        changed = np.any(src.vertices.reshape(-1, 3) != vertices, axis=1)
        if albedo is not None:
            changed |= src.albedo.reshape(-1) != albedo
        rows = np.flatnonzero(changed)
        if rows.size < table.shape[0]:
            lines = src.data.decode("latin-1").split("\n")
            new = bytes(_format_rows(table[rows], style, rows)).decode("latin-1").split("\n")
            for k, row in enumerate(rows.tolist()):
                lines[row + 1] = new[k]
            return "\n".join(lines).encode("latin-1", errors="replace")
    head = fortran.format_i(q, 12).encode("latin-1") + b"\n"
    return _format_rows(table, style, head=head)


def _format_rows(table: np.ndarray, style: str, index: np.ndarray | None = None, head: bytes = b""):
    """``head`` followed by the vertex lines (each ending in a newline) for the (n, 3 or 4) ``table``.

    Returns bytes or a uint8 array (a buffer, to spare a copy of large files).
    ``index`` gives the 0-based vertex numbers of the rows (for messages).
    """
    table = np.ascontiguousarray(table, dtype=np.float64)
    rows, cols = table.shape
    if rows == 0:
        return head

    def label(r: int) -> str:
        return f"vertex {int(index[r]) if index is not None else r} (0-based, file order)"

    if not np.all(np.isfinite(table)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(table), axis=1))[0])
        raise ValueError(f"{label(bad)} is not finite: {table[bad].tolist()}")
    if style == "spc":
        if table.size < _KERNEL_MIN_VALUES:
            text = _format_fixed_python(table)
            text = None if text is None else head + text
        else:
            from spctool.formats._icqkernels import format_fixed

            flat, out = _buffer(head, rows, cols * 12 + 1)
            r, c = format_fixed(table, 12, 5, out)
            text = None if r >= 0 else flat
        if text is None:
            big = np.flatnonzero(np.any((table >= 99999.999995) | (table <= -9999.999995), axis=1))
            r = int(big[0]) if big.size else 0
            raise ValueError(
                f"{label(r)}, {table[r].tolist()}, does not fit SPC's F12.5 "
                "(|x| < 1e5 km, < 1e4 km if negative); write with style='exact'"
            )
        return text
    if table.size < _KERNEL_MIN_VALUES:
        return head + _format_exact_python(table)
    from spctool.formats._icqkernels import EXACT_WIDTH as _EXACT_WIDTH
    from spctool.formats._icqkernels import format_exact

    flat, out = _buffer(head, rows, cols * _EXACT_WIDTH + 1)
    fallback = np.zeros((rows, cols), dtype=np.bool_)
    format_exact(table, out, fallback)
    if fallback.any():
        for r, c in np.argwhere(fallback).tolist():
            text = f" {table[r, c]:23.16E}"
            if len(text) != _EXACT_WIDTH:  # 3-digit exponents: give up on fixed columns
                return head + _format_exact_python(table)
            out[r, c * _EXACT_WIDTH : (c + 1) * _EXACT_WIDTH] = np.frombuffer(
                text.encode("latin-1"), np.uint8
            )
    return flat


def _buffer(head: bytes, rows: int, width: int):
    """A flat uint8 buffer starting with ``head`` and its (rows, width) line view."""
    flat = np.empty(len(head) + rows * width, dtype=np.uint8)
    flat[: len(head)] = np.frombuffer(head, dtype=np.uint8)
    return flat, flat[len(head) :].reshape(rows, width)


def _format_fixed_python(table: np.ndarray) -> bytes | None:
    """F12.5 per value with Python's ``%12.5f``; None if a value leaves no leading blank."""
    cols = table.shape[1]
    text = (("%12.5f" * cols + "\n") * table.shape[0]) % tuple(table.ravel().tolist())
    if len(text) != table.shape[0] * (12 * cols + 1) or any(
        ln[k * 12] != " " for ln in text.splitlines() for k in range(cols)
    ):
        return None
    return text.encode("latin-1")


def _format_exact_python(table: np.ndarray) -> bytes:
    cols = table.shape[1]
    # " %23.16E" is Python's "%24.16E" whenever that leaves a blank (always, for 2-digit exponents)
    return (((" %23.16E" * cols + "\n") * table.shape[0]) % tuple(table.ravel().tolist())).encode("latin-1")


def seam_mismatch(shape: IcqShape) -> float:
    """Largest |difference| (km, and albedo units) between seam duplicates; 0.0 for an exact ICQ."""
    pairs = _seam_pairs_cached(shape.q)
    v = shape.flat_vertices()
    worst = float(np.max(np.abs(v[pairs[:, 0]] - v[pairs[:, 1]]), initial=0.0))
    alb = shape.flat_albedo()
    if alb is not None:
        worst = max(worst, float(np.max(np.abs(alb[pairs[:, 0]] - alb[pairs[:, 1]]), initial=0.0)))
    return worst


def unify_seams(shape: IcqShape) -> IcqShape:
    """A copy whose seam duplicates all hold their representative's values (:func:`icq_merge_map`)."""
    rep = icq_merge_map(shape.q)
    n = shape.q + 1
    vertices = shape.flat_vertices()[rep].reshape(6, n, n, 3)
    albedo = None if shape.albedo is None else shape.flat_albedo()[rep].reshape(6, n, n)
    return IcqShape(shape.q, vertices, albedo, shape.path, shape._source)


def _check_seams(q: int, vertices: np.ndarray, albedo: np.ndarray | None, path) -> None:
    pairs = _seam_pairs_cached(q)
    bad = np.any(vertices[pairs[:, 0]] != vertices[pairs[:, 1]], axis=1)
    if albedo is not None:
        bad |= albedo[pairs[:, 0]] != albedo[pairs[:, 1]]
    if bad.any():
        a, b = pairs[np.flatnonzero(bad)[0]].tolist()
        diff = float(np.max(np.abs(vertices[pairs[bad, 0]] - vertices[pairs[bad, 1]])))
        raise ValueError(
            f"{path or 'ICQ shape'}: {int(bad.sum())} of {len(pairs)} seam duplicate pairs differ (up to "
            f"{diff:.3g} km), e.g. vertices {a} and {b} (0-based); an ICQ writer must write them identically "
            "(the six faces share their edge vertices) — use seams='unify' or 'keep'"
        )
