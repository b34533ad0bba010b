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

Speed: reading and writing go through small numba kernels (an SPC-style
q = 512 shape, 1.58 M vertices, reads or writes in well under a second; files
below ~20 000 vertices use plain Python and never start numba).  The reader
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
from numba import njit

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
# numba kernels: list-directed number reading and F/E writing

_TWO53 = 9007199254740992
_P10 = np.array([float(10**i) for i in range(23)])  # exact doubles
_P10I = np.array([10**i for i in range(19)], dtype=np.int64)
_P5 = np.array([5**i for i in range(28)], dtype=np.uint64)
_MAXSIG = 18  # significant digits kept in an int64 mantissa (10**18 < 2**60)
# Below this many numbers the plain-Python reader/writer is used: the same results, without the
# one-off cost (~0.5–1 s) of starting numba in a fresh process.
_KERNEL_MIN_VALUES = 60_000


@njit(cache=True)
def _mul64(a, b):
    """Full 128-bit product (hi, lo) of two uint64."""
    m32 = np.uint64(0xFFFFFFFF)
    s32 = np.uint64(32)
    a0 = a & m32
    a1 = a >> s32
    b0 = b & m32
    b1 = b >> s32
    p00 = a0 * b0
    p01 = a0 * b1
    p10 = a1 * b0
    p11 = a1 * b1
    mid = (p00 >> s32) + (p01 & m32) + (p10 & m32)
    lo = (mid << s32) | (p00 & m32)
    hi = p11 + (p01 >> s32) + (p10 >> s32) + (mid >> s32)
    return hi, lo


@njit(cache=True)
def _shl128(hi, lo, n):
    """(hi, lo) << n for 0 ≤ n < 128 (the caller guarantees no overflow)."""
    if n == 0:
        return hi, lo
    if n >= 64:
        return lo << np.uint64(n - 64), np.uint64(0)
    return (hi << np.uint64(n)) | (lo >> np.uint64(64 - n)), lo << np.uint64(n)


@njit(cache=True)
def _cmp_mid(m, k, c, e):
    """Sign of m·10^−k − c·2^e, exactly (m < 2^60, c < 2^56, k ≤ 27); 2 if out of range."""
    a = -e - k  # compare m·2^a with c·5^k
    yh, yl = _mul64(np.uint64(c), _P5[k])
    if a >= 0:
        if a > 67:
            return 2
        xh, xl = _shl128(np.uint64(0), np.uint64(m), a)
    else:
        if -a > 9:
            return 2
        xh = np.uint64(0)
        xl = np.uint64(m)
        yh, yl = _shl128(yh, yl, -a)
    if xh > yh:
        return 1
    if xh < yh:
        return -1
    if xl > yl:
        return 1
    if xl < yl:
        return -1
    return 0


@njit(cache=True)
def _decimal_to_double(m, e10):
    """Correctly rounded m·10^e10 (m ≥ 0 int64 < 2^60); returns (value, ok)."""
    if m == 0:
        return 0.0, True
    if m <= _TWO53 and -22 <= e10 <= 22:  # Clinger: one exact operation, one rounding
        if e10 >= 0:
            return float(m) * _P10[e10], True
        return float(m) / _P10[-e10], True
    if e10 == 0:
        return float(m), True  # int64 → double rounds to nearest even
    if e10 > 0 or e10 < -27:
        return 0.0, False
    k = -e10
    if k <= 22:
        c = float(m) / _P10[k]
    else:
        c = float(m) / _P10[22] / _P10[k - 22]
    for _ in range(4):
        fr, ex = math.frexp(c)
        big = np.int64(fr * 9007199254740992.0)  # 53-bit significand
        e = ex - 53
        r = _cmp_mid(m, k, 2 * big + 1, e - 1)  # against the upper midpoint
        if r == 2:
            return 0.0, False
        if r > 0:
            c = np.nextafter(c, np.inf)
            continue
        if r == 0:
            if big & 1:
                c = np.nextafter(c, np.inf)
            return c, True
        if big == 4503599627370496:  # 2^52: the lower neighbour is half as far
            r2 = _cmp_mid(m, k, 4 * big - 1, e - 2)
        else:
            r2 = _cmp_mid(m, k, 2 * big - 1, e - 1)
        if r2 == 2:
            return 0.0, False
        if r2 < 0:
            c = np.nextafter(c, -np.inf)
            continue
        if r2 == 0 and (big & 1):
            c = np.nextafter(c, -np.inf)
        return c, True
    return 0.0, False


@njit(cache=True)
def _is_blank(c):
    return c == 32 or c == 9 or c == 44 or c == 13 or c == 11 or c == 12  # blank, tab, comma, CR, VT, FF


@njit(cache=True)
def _parse_records(buf, pos, nrec, ncols, out, slow):
    """List-directed read of ``ncols`` reals from each of ``nrec`` lines starting at byte ``pos``.

    Extra values on a line are ignored (list-directed semantics).  Tokens whose
    value cannot be settled here are recorded in ``slow`` as (start, end, index).
    Returns (status, record, value, byte, end, nslow): status 0 ok, 1 bad token
    at ``byte``, 2 too few values on ``record``, 3 data end before ``record``,
    4 ``slow`` is full.
    """
    n = buf.shape[0]
    p = pos
    nslow = 0
    for r in range(nrec):
        if p >= n:
            return 3, r, 0, p, p, nslow
        for col in range(ncols):
            while p < n and _is_blank(buf[p]):
                p += 1
            if p >= n or buf[p] == 10:
                return 2, r, col, p, p, nslow
            start = p
            neg = False
            ch = buf[p]
            if ch == 43 or ch == 45:
                neg = ch == 45
                p += 1
            m = np.int64(0)
            nsig = 0
            ndig = 0
            e10 = 0
            lost = False
            while p < n and 48 <= buf[p] <= 57:
                d = buf[p] - 48
                ndig += 1
                if nsig < _MAXSIG:
                    if m != 0 or d != 0:
                        m = m * 10 + d
                        nsig += 1
                else:
                    e10 += 1
                    if d != 0:
                        lost = True
                p += 1
            if p < n and buf[p] == 46:
                p += 1
                while p < n and 48 <= buf[p] <= 57:
                    d = buf[p] - 48
                    ndig += 1
                    if nsig < _MAXSIG:
                        if m != 0 or d != 0:
                            m = m * 10 + d
                            nsig += 1
                        e10 -= 1
                    elif d != 0:
                        lost = True
                    p += 1
            if ndig == 0:
                return 1, r, col, start, p, nslow
            if p < n:
                ch = buf[p]
                has_exp = False
                esign = 1
                if ch == 69 or ch == 101 or ch == 68 or ch == 100 or ch == 81 or ch == 113:  # E e D d Q q
                    has_exp = True
                    p += 1
                    if p < n and (buf[p] == 43 or buf[p] == 45):
                        esign = -1 if buf[p] == 45 else 1
                        p += 1
                elif ch == 43 or ch == 45:  # letterless exponent 1.5-06
                    has_exp = True
                    esign = -1 if ch == 45 else 1
                    p += 1
                if has_exp:
                    edig = 0
                    ev = 0
                    while p < n and 48 <= buf[p] <= 57:
                        if ev < 100000:
                            ev = ev * 10 + (buf[p] - 48)
                        edig += 1
                        p += 1
                    if edig == 0:
                        return 1, r, col, start, p, nslow
                    e10 += esign * ev
            if p < n and not (_is_blank(buf[p]) or buf[p] == 10):
                return 1, r, col, start, p, nslow
            while m != 0 and m % 10 == 0:
                m //= 10
                e10 += 1
            idx = r * ncols + col
            ok = False
            if not lost:
                v, ok = _decimal_to_double(m, e10)
            if ok:
                out[idx] = -v if neg else v
            else:
                if nslow >= slow.shape[0]:
                    return 4, r, col, start, p, nslow
                slow[nslow, 0] = start
                slow[nslow, 1] = p
                slow[nslow, 2] = idx
                nslow += 1
        while p < n and buf[p] != 10:
            p += 1
        if p < n:
            p += 1
    return 0, nrec, 0, p, p, nslow


@njit(cache=True)
def _two_prod(a, b):
    """a·b = p + e exactly (Dekker/Veltkamp; no FMA needed)."""
    p = a * b
    t = 134217729.0 * a
    ah = t - (t - a)
    al = a - ah
    t = 134217729.0 * b
    bh = t - (t - b)
    bl = b - bh
    e = ((ah * bh - p) + ah * bl + al * bh) + al * bl
    return p, e


@njit(cache=True)
def _round_exact(p, e):
    """Nearest integer (ties to even) to the exact sum p + e (|e| ≤ ulp(p)/2), as int64."""
    r = np.rint(p)
    dd = p - r
    fe = np.floor(e)
    fre = e - fe
    if abs(p) >= 9007199254740992.0:
        n = np.int64(fe)
        if fre > 0.5:
            n += 1
        elif fre == 0.5 and (np.int64(r) + n) & 1:
            n += 1
        return np.int64(r) + n
    if dd == 0.5 and e > 0:
        return np.int64(r) + 1
    if dd == -0.5 and e < 0:
        return np.int64(r) - 1
    if dd == 0.0 and abs(e) == 0.5 and np.int64(r) & 1:
        return np.int64(r) + (1 if e > 0 else -1)
    return np.int64(r)


@njit(cache=True)
def _format_fixed(vals, width, decimals, out):
    """Fortran ``Fw.d`` (as Python ``%w.df``: correctly rounded, ties to even) for every value.

    ``out`` is (rows, cols·width + 1) uint8; each line ends with a newline.
    Every field keeps at least one leading blank.  Returns (row, col) of the
    first value that does not fit (or is not finite), else (−1, −1).
    """
    rows, cols = vals.shape
    scale = _P10[decimals]
    pd = _P10I[decimals]
    for r in range(rows):
        for c in range(cols):
            x = vals[r, c]
            base = c * width
            if not (abs(x) < 1e9):  # also rejects NaN and infinities
                return r, c
            p, e = _two_prod(x, scale)
            k = _round_exact(p, e)
            neg = x < 0 or (x == 0.0 and math.copysign(1.0, x) < 0)
            kk = -k if k < 0 else k
            ip = kk // pd
            fr = kk - ip * pd
            nd = 1
            t = ip // 10
            while t > 0:
                nd += 1
                t //= 10
            length = nd + 1 + decimals + (1 if neg else 0)
            if length > width - 1:
                return r, c
            for t in range(width - length):
                out[r, base + t] = 32
            q = base + width - 1
            for _ in range(decimals):
                out[r, q] = 48 + fr % 10
                fr //= 10
                q -= 1
            out[r, q] = 46
            q -= 1
            for _ in range(nd):
                out[r, q] = 48 + ip % 10
                ip //= 10
                q -= 1
            if neg:
                out[r, q] = 45
        out[r, cols * width] = 10
    return -1, -1


_EXACT_WIDTH = 24  # " " + "%23.16E": one blank, sign or blank, d.dddddddddddddddd, E±ee


@njit(cache=True)
def _format_exact(vals, out, fallback):
    """17 significant digits, ``ES24.16``-like (identical to Python ``'%24.16E'``), lossless.

    Values outside 1e−6 ≤ |x| < 1e16 are flagged in ``fallback`` for Python formatting.
    """
    rows, cols = vals.shape
    w = 24
    for r in range(rows):
        for c in range(cols):
            x = vals[r, c]
            base = c * w
            for t in range(w):
                out[r, base + t] = 32
            neg = x < 0 or (x == 0.0 and math.copysign(1.0, x) < 0)
            ax = abs(x)
            m = np.int64(0)
            d = 0
            if ax != 0.0:
                if not (ax >= 1e-6 and ax < 1e16):
                    fallback[r, c] = True
                    continue
                d = int(math.floor(math.log10(ax)))
                good = False
                for _ in range(3):
                    j = 16 - d
                    if j < 0 or j > 22:
                        break
                    p, e = _two_prod(ax, _P10[j])
                    # the decade is decided on the exact product p + e, before rounding
                    if p < 1e16 or (p == 1e16 and e < 0):
                        d -= 1
                        continue
                    if p > 1e17 or (p == 1e17 and e >= 0):
                        d += 1
                        continue
                    m = _round_exact(p, e)
                    if m == 100000000000000000:  # 9.99…95 rounds up into the next decade
                        m = 10000000000000000
                        d += 1
                    good = True
                    break
                # p + e is x·10^j exactly and m its correct rounding: the correctly rounded
                # 17-digit decimal, which always reads back as x (no re-check needed).
                if not good:
                    fallback[r, c] = True
                    continue
            q = base + w - 1
            ed = -d if d < 0 else d
            out[r, q] = 48 + ed % 10
            out[r, q - 1] = 48 + (ed // 10) % 10
            out[r, q - 2] = 45 if d < 0 else 43
            out[r, q - 3] = 69
            q -= 4
            for _ in range(16):
                out[r, q] = 48 + m % 10
                m //= 10
                q -= 1
            out[r, q] = 46
            out[r, q - 1] = 48 + m % 10
            if neg:
                out[r, q - 2] = 45
        out[r, cols * w] = 10


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
    if nvert * ncols < _KERNEL_MIN_VALUES:
        out, end = _parse_rows_python(data, nl + 1, nvert, ncols, where, what)
    else:
        out, end = _parse_rows_kernel(data, nl + 1, nvert, ncols, where, what, q)
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
    buf = np.frombuffer(data, dtype=np.uint8)
    out = np.empty(nvert * ncols, dtype=np.float64)
    slow = np.empty((min(4096, nvert * ncols), 3), dtype=np.int64)
    status, rec, col, bpos, end, nslow = _parse_records(buf, pos, nvert, ncols, out, slow)
    if status == 4:  # many tokens need the Python parser: rerun with room for all of them
        slow = np.empty((nvert * ncols, 3), dtype=np.int64)
        status, rec, col, bpos, end, nslow = _parse_records(buf, pos, nvert, ncols, out, slow)
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
            flat, out = _buffer(head, rows, cols * 12 + 1)
            r, c = _format_fixed(table, 12, 5, out)
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
    flat, out = _buffer(head, rows, cols * _EXACT_WIDTH + 1)
    fallback = np.zeros((rows, cols), dtype=np.bool_)
    _format_exact(table, out, fallback)
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
            "(spc-formats.md §5.2) — use seams='unify' or 'keep'"
        )
