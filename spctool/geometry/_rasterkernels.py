"""Numba kernels of the image-space template renderer (private; used by :mod:`spctool.stages.render`).

S16 "Future Retina development" correlates the photo against a rendered prediction of each maplet;
issue 17 asks for that render at maplet-space speed.  The kernels here do the per-window work around
the exact ray casting of :mod:`spctool.geometry._heightkernels` without NumPy temporaries:

* :func:`bin_subrays` — supersample bins: the mean radiance, coverage and shadow fraction of each
  pixel's n×n sub-rays (summed in the order NumPy's ``reshape(...).mean(axis=(1, 3))`` sums them, so
  the pixels are the same to the last bit; n < 8);
* :func:`raster_cells`, :func:`drop_discontinuous`, :func:`block_crossing` — primary visibility by
  forward rasterisation: the maplet's nodes are projected into the photo by the camera's forward
  model and each cell drawn as two triangles into a depth buffer over the sub-ray grid; a sub-ray
  then marches only through the 3×3 block of cells around its hinted cell (the same crossing
  arithmetic), and falls back to the full march when that finds nothing, when it has no hint, or
  next to a depth discontinuity.  Pays where the full march is long (oblique views of rough
  terrain); near-nadir views march ~2 cells and do not use it.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from spctool.geometry._heightkernels import _march


@njit(cache=True, nogil=True)
def bin_subrays(r, hit, sh, surface, nss, rad, cov, shd, sid):
    """Pixel (a, s) of the (lines, samples) outputs from sub-rays m = ((a·nss + u)·width + s)·nss + v
    (line a, sub-line u, sample s, sub-sample v): rad = mean of r, cov / shd = fraction of ``hit`` /
    ``sh``, sid = ``surface`` of the pixel's first sub-ray.  Bit for bit NumPy's means for nss < 8
    (NumPy sums 8 or more terms pairwise; callers use NumPy there)."""
    nl, width = rad.shape
    k = nss * nss
    for a in range(nl):
        for s in range(width):
            m0 = ((a * nss) * width + s) * nss
            acc = 0.0
            nh = 0
            ns = 0
            for u in range(nss):
                row = 0.0  # NumPy: each sub-line's sum (sequential below 8 terms), then their sum
                for v in range(nss):
                    m = ((a * nss + u) * width + s) * nss + v
                    row += r[m]
                    nh += hit[m]
                    ns += sh[m]
                acc += row
            rad[a, s] = acc / k
            cov[a, s] = nh / k
            shd[a, s] = ns / k
            sid[a, s] = surface[m0]


@njit(cache=True, nogil=True)
def raster_cells(xs, ys, zs, ok, hint, zbuf):
    """Forward rasterisation of a maplet's cells into a sub-ray grid with a depth buffer.

    ``xs``, ``ys`` (n, n): the nodes' sub-ray grid coordinates (sub-ray centres at integers), ``zs``
    their depth along the boresight, ``ok`` nodes valid and in front of the camera.  Each cell whose
    four nodes are ok is drawn as its two triangles, split along the (i, j)–(i+1, j+1) diagonal; every
    sub-ray centre inside a triangle (edges included) whose interpolated depth is the nearest so far
    gets the cell: ``hint`` (rows, cols, 2) its (i, j), ``zbuf`` (rows, cols) the depth.
    """
    n0, n1 = xs.shape
    ny, nx = zbuf.shape
    for i in range(n0 - 1):
        for j in range(n1 - 1):
            if not (ok[i, j] and ok[i + 1, j] and ok[i, j + 1] and ok[i + 1, j + 1]):
                continue
            for tri in range(2):
                # corners (i, j), (i+1, j+1) and (i+1, j) or (i, j+1)
                ai, aj = i, j
                bi, bj = i + 1, j + 1
                ci, cj = (i + 1, j) if tri == 0 else (i, j + 1)
                x0, y0, z0 = xs[ai, aj], ys[ai, aj], zs[ai, aj]
                x1, y1, z1 = xs[bi, bj], ys[bi, bj], zs[bi, bj]
                x2, y2, z2 = xs[ci, cj], ys[ci, cj], zs[ci, cj]
                area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
                if area == 0.0 or area != area:
                    continue
                c0 = max(int(math.ceil(min(x0, x1, x2))), 0)
                c1 = min(int(math.floor(max(x0, x1, x2))), nx - 1)
                r0 = max(int(math.ceil(min(y0, y1, y2))), 0)
                r1 = min(int(math.floor(max(y0, y1, y2))), ny - 1)
                inv = 1.0 / area
                for r in range(r0, r1 + 1):
                    for c in range(c0, c1 + 1):
                        # barycentric weights (signed areas), edges included
                        w0 = ((x1 - c) * (y2 - r) - (x2 - c) * (y1 - r)) * inv
                        w1 = ((x2 - c) * (y0 - r) - (x0 - c) * (y2 - r)) * inv
                        w2 = 1.0 - w0 - w1
                        if w0 < -1e-12 or w1 < -1e-12 or w2 < -1e-12:
                            continue
                        depth = w0 * z0 + w1 * z1 + w2 * z2
                        if depth < zbuf[r, c]:
                            zbuf[r, c] = depth
                            hint[r, c, 0] = i
                            hint[r, c, 1] = j


@njit(cache=True, nogil=True)
def drop_discontinuous(hint, jump, radius, out):
    """``out`` = ``hint`` except within ``radius`` sub-rays (Chebyshev) of a depth discontinuity — a sub-ray
    without a cell, or one whose 4-neighbour has none or a cell more than ``jump`` cells away in either
    index — where the hint is dropped (-1): there the nearest triangle and the nearest bilinear surface
    may differ (the bilinear bulges up to a quarter of the cell's twist off its triangles, which an
    oblique view spreads over more than one sub-ray), and the full march decides."""
    ny, nx = hint.shape[0], hint.shape[1]
    edge = np.zeros((ny, nx), np.bool_)
    for r in range(ny):
        for c in range(nx):
            i = hint[r, c, 0]
            j = hint[r, c, 1]
            if i < 0:
                edge[r, c] = True
                continue
            for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                rr = r + dr
                cc = c + dc
                if 0 <= rr < ny and 0 <= cc < nx:
                    i2 = hint[rr, cc, 0]
                    if i2 < 0 or abs(i2 - i) > jump or abs(hint[rr, cc, 1] - j) > jump:
                        edge[r, c] = True
                        break
    # dilate the edges by ``radius`` (separable: along rows, then along columns)
    tmp = np.zeros((ny, nx), np.bool_)
    for r in range(ny):
        for c in range(nx):
            if edge[r, c]:
                for cc in range(max(c - radius, 0), min(c + radius + 1, nx)):
                    tmp[r, cc] = True
    for r in range(ny):
        for c in range(nx):
            drop = False
            for rr in range(max(r - radius, 0), min(r + radius + 1, ny)):
                if tmp[rr, c]:
                    drop = True
                    break
            out[r, c, 0] = -1 if drop else hint[r, c, 0]
            out[r, c, 1] = -1 if drop else hint[r, c, 1]


@njit(cache=True, inline="always")
def block_crossing(h, valid, cmax, p, n, hmin, hmax, u0, w0, z0, du, dw, dz, t_min, t_max, ci, cj):
    """The first crossing of the ray inside the 3×3 block of cells around the hinted cell (ci, cj): the
    march (same arithmetic, so the same t where the full march reaches the block) from where the ray
    enters the block to where it leaves it; nan when it crosses nothing there."""
    lo_u = max(ci - 1.0, 0.0)
    hi_u = min(ci + 2.0, n - 1.0)
    lo_w = max(cj - 1.0, 0.0)
    hi_w = min(cj + 2.0, n - 1.0)
    ta = t_min
    tb = t_max
    if du != 0.0:
        t1 = (lo_u - u0) / du
        t2 = (hi_u - u0) / du
        ta = max(ta, min(t1, t2))
        tb = min(tb, max(t1, t2))
    if dw != 0.0:
        t1 = (lo_w - w0) / dw
        t2 = (hi_w - w0) / dw
        ta = max(ta, min(t1, t2))
        tb = min(tb, max(t1, t2))
    if not ta <= tb:
        return math.nan
    return _march(h, valid, cmax, p, n, n, hmin, hmax, u0, w0, z0, du, dw, dz, ta, tb, cmax, False)
