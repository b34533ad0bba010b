"""Bicubic interpolation of a camera's inverse distortion on a grid of exact inverses (private; used
by :meth:`spctool.geometry.camera.Camera.pixel_to_direction_grid` and ``pixel_to_direction_lattice``).

Issue 17 (image-space registration speed) suggests inverting the distortion once on a grid and
interpolating instead of a Newton solve per template ray.  The grid holds x̄, ȳ (normalised focal
plane) of nodes ``step`` px apart; a point in cell (a, b) takes the tensor cubic Lagrange interpolant
of the 4×4 nodes around it (error O(step⁴) where the map is smooth) — only in cells that the camera
module's ``_k_cubic_cells`` found exact to the tolerance asked; the others are flagged for Newton.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@numba.njit(inline="always", **_JIT)
def rotation_tuple(rot):
    """The 3×3 ``rot`` as a row-major 9-tuple of scalars (read once per kernel, not per point)."""
    return (
        rot[0, 0], rot[0, 1], rot[0, 2], rot[1, 0], rot[1, 1], rot[1, 2], rot[2, 0], rot[2, 1], rot[2, 2]
    )  # fmt: skip


@numba.njit(inline="always", **_JIT)
def focal_direction(xn, yn, rr):
    """Unit body-frame direction Rᵀ·(x̄, ȳ, 1)/‖(x̄, ȳ, 1)‖ of a normalised focal-plane point
    (``rr`` = :func:`rotation_tuple` of R, the body→camera rotation)."""
    nrm = 1.0 / math.sqrt(xn * xn + yn * yn + 1.0)
    cx = xn * nrm
    cy = yn * nrm
    return (
        rr[0] * cx + rr[3] * cy + rr[6] * nrm,
        rr[1] * cx + rr[4] * cy + rr[7] * nrm,
        rr[2] * cx + rr[5] * cy + rr[8] * nrm,
    )


@numba.njit(inline="always", **_JIT)
def _cubic_weights(t):
    """Cubic Lagrange weights of the nodes −1, 0, 1, 2 at fraction t of the middle interval."""
    tp = t + 1.0
    tm = t - 1.0
    t2 = t - 2.0
    return -t * tm * t2 / 6.0, tp * tm * t2 / 2.0, -tp * t * t2 / 2.0, tp * t * tm / 6.0


@numba.njit(inline="always", **_JIT)
def _cubic_at(g, a, b, wa, wb):
    """Σᵢⱼ wa[i]·wb[j]·g[a − 1 + i, b − 1 + j] (unrolled)."""
    wb0, wb1, wb2, wb3 = wb
    r0 = wb0 * g[a - 1, b - 1] + wb1 * g[a - 1, b] + wb2 * g[a - 1, b + 1] + wb3 * g[a - 1, b + 2]
    r1 = wb0 * g[a, b - 1] + wb1 * g[a, b] + wb2 * g[a, b + 1] + wb3 * g[a, b + 2]
    r2 = wb0 * g[a + 1, b - 1] + wb1 * g[a + 1, b] + wb2 * g[a + 1, b + 1] + wb3 * g[a + 1, b + 2]
    r3 = wb0 * g[a + 2, b - 1] + wb1 * g[a + 2, b] + wb2 * g[a + 2, b + 1] + wb3 * g[a + 2, b + 2]
    return wa[0] * r0 + wa[1] * r1 + wa[2] * r2 + wa[3] * r3


@numba.njit(**_JIT)
def _k_cubic(smp, lin, gxn, gyn, s0, l0, step, good, rot, dirs, redo):
    """Directions from the bicubic interpolant of the grid's exact inverses (no Newton step) in the
    cells that ``_camerakernels._k_cubic_cells`` found ``good``; ``redo`` elsewhere."""
    rr = rotation_tuple(rot)
    ns = gxn.shape[0]
    nl = gxn.shape[1]
    inv = 1.0 / step
    for i in range(smp.shape[0]):
        u = (smp[i] - s0) * inv
        w = (lin[i] - l0) * inv
        a = int(math.floor(u))
        b = int(math.floor(w))
        if not (0 <= a < ns and 0 <= b < nl and good[a, b]):
            redo[i] = True
            continue
        redo[i] = False
        wa = _cubic_weights(u - a)
        wb = _cubic_weights(w - b)
        xn = _cubic_at(gxn, a, b, wa, wb)
        yn = _cubic_at(gyn, a, b, wa, wb)
        dirs[i, 0], dirs[i, 1], dirs[i, 2] = focal_direction(xn, yn, rr)


@numba.njit(**_JIT)
def _k_cubic_lattice(smp, lin, gxn, gyn, s0, l0, step, good, rot, dirs, redo):
    """:func:`_k_cubic` on the lattice lines × samples (``dirs`` (nl, ns, 3), ``redo`` (nl, ns)), the
    same arithmetic in the same order: each line's weights and the grid columns' sums over lines once
    per line, each sample's weights once per call (4 + 4 products per point instead of 16 + 16).
    Returns the number of points flagged in ``redo``."""
    rr = rotation_tuple(rot)
    ng = gxn.shape[0]
    mg = gxn.shape[1]
    inv = 1.0 / step
    m = smp.shape[0]
    acol = np.empty(m, np.int64)
    wcol = np.empty((m, 4))
    for c in range(m):
        u = (smp[c] - s0) * inv
        a = int(math.floor(u))
        acol[c] = a if 0 <= a < ng else -1
        wcol[c, 0], wcol[c, 1], wcol[c, 2], wcol[c, 3] = _cubic_weights(u - a)
    rx = np.empty(ng)
    ry = np.empty(ng)
    nredo = 0
    for r in range(lin.shape[0]):
        w = (lin[r] - l0) * inv
        b = int(math.floor(w))
        if not (1 <= b < mg - 2):
            for c in range(m):
                redo[r, c] = True
            nredo += m
            continue
        gb = good[:, b]
        wb0, wb1, wb2, wb3 = _cubic_weights(w - b)
        for a in range(ng):
            rx[a] = wb0 * gxn[a, b - 1] + wb1 * gxn[a, b] + wb2 * gxn[a, b + 1] + wb3 * gxn[a, b + 2]
            ry[a] = wb0 * gyn[a, b - 1] + wb1 * gyn[a, b] + wb2 * gyn[a, b + 1] + wb3 * gyn[a, b + 2]
        for c in range(m):
            a = acol[c]
            if a < 0 or not gb[a]:
                redo[r, c] = True
                nredo += 1
                continue
            redo[r, c] = False
            wa0, wa1, wa2, wa3 = wcol[c, 0], wcol[c, 1], wcol[c, 2], wcol[c, 3]
            xn = wa0 * rx[a - 1] + wa1 * rx[a] + wa2 * rx[a + 1] + wa3 * rx[a + 2]
            yn = wa0 * ry[a - 1] + wa1 * ry[a] + wa2 * ry[a + 1] + wa3 * ry[a + 2]
            dirs[r, c, 0], dirs[r, c, 1], dirs[r, c, 2] = focal_direction(xn, yn, rr)
    return nredo
