"""Numba kernels of the image-space template renderer (private; used by :mod:`spctool.stages.render`).

S16 "Future Retina development" correlates the photo against a rendered prediction of each maplet;
issue 17 asks for that render at maplet-space speed.  The kernels here do the per-window work around
the exact ray casting of :mod:`spctool.geometry._heightkernels` without NumPy temporaries:

* :func:`bin_subrays` — supersample bins: the mean radiance, coverage and shadow fraction of each
  pixel's n×n sub-rays (summed in the order NumPy's ``reshape(...).mean(axis=(1, 3))`` sums them, so
  the pixels are the same to the last bit; n < 8).
* :func:`shade_subrays` — the photometric law of :mod:`spctool.photometry` per sub-ray (times the
  albedo, 0 in shadow), on the fused kernel's (μ0, μ, cos α, albedo) without NumPy temporaries.
* :func:`node_geometry`, :func:`gouraud_subrays` — ``shading="gouraud"``: the shading geometry at a
  patch's nodes (shaded by :func:`shade_subrays`), and per sub-ray: the node radiances interpolated
  bilinearly at the sub-ray's grid position (0 in shadow).
* :func:`terrain_cells` — visibility by rasterisation (issue 17's "render forward"): the maplet's cells,
  projected by the camera's forward model, drawn as two triangles each into a depth buffer on the
  sub-ray lattice; the fused kernel then solves each sub-ray's crossing in the cell found (one quadratic)
  instead of marching the grid from the top of the relief, and marches only where the raster cannot
  vouch for the cell (a sub-ray beside the drawn border, or one whose cell it enters below the terrain).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from spctool.geometry._heightkernels import borrowed


@njit(cache=True, nogil=True)
def bin_subrays(r, hit, sh, surface, nss, rad, cov, shd, sid):
    """Pixel (a, s) of the (lines, samples) outputs from sub-rays m = ((a·nss + u)·width + s)·nss + v
    (line a, sub-line u, sample s, sub-sample v): rad = mean of r, cov / shd = fraction of ``hit`` /
    ``sh``, sid = ``surface`` of the pixel's first sub-ray.  Bit for bit NumPy's means for nss < 8
    (NumPy sums 8 or more terms pairwise; callers use NumPy there)."""
    nl, width = rad.shape
    k = nss * nss
    if nss == 1:  # one sub-ray per pixel: the same sums (0 + r, whose only change is −0 → +0), flat
        for a in range(nl):
            m0 = a * width
            for s in range(width):
                rad[a, s] = (0.0 + (0.0 + r[m0 + s])) / 1
                cov[a, s] = hit[m0 + s] / 1
                shd[a, s] = sh[m0 + s] / 1
                sid[a, s] = surface[m0 + s]
        return
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


#: photometric laws of :mod:`spctool.photometry` by code, for :func:`shade_subrays`
LAW_CODES = {"spc": 0, "mcewen": 1, "fixed": 2, "lambert": 3}


@njit(cache=True, nogil=True)
def shade_subrays(geom, sh, law, beta, alpha0, use_albedo, out):
    """The fused kernel's shading step per sub-ray: ``out[k]`` = R(μ0, μ, α)·albedo, 0 when shadowed.

    ``geom`` (N, 4) = (μ0, μ, cos α, albedo) per sub-ray; ``law`` a :data:`LAW_CODES` code, ``beta`` the
    constant β of ``fixed``, ``alpha0`` (deg) the limb-weight scale.  The arithmetic of
    :func:`spctool.photometry.reflectance` element by element (α = degrees(arccos(clip(cos α, ±1))),
    β = exp(−α/α0), dark where μ0 ≤ 0, μ ≤ 0 or μ0 + μ ≤ 1e-12; Lambert dark where μ0 ≤ 0 or μ ≤ 0),
    without its NumPy temporaries; the arccos and exp are skipped where the ray is dark or shadowed.
    """
    deg = 180.0 / math.pi
    for k in range(geom.shape[0]):
        if sh[k]:
            out[k] = 0.0
            continue
        mu0 = geom[k, 0]
        mu = geom[k, 1]
        if law == 3:
            r = 0.0 if (mu0 <= 0.0 or mu <= 0.0) else mu0
        elif mu0 <= 0.0 or mu <= 0.0 or mu0 + mu <= 1e-12:
            r = 0.0
        else:
            if law == 2:
                b = beta
            else:
                c = min(max(geom[k, 2], -1.0), 1.0)
                b = math.exp(-(math.acos(c) * deg) / alpha0)
            lommel = mu0 / (mu0 + mu)
            if law == 1:
                r = 2.0 * b * lommel + (1.0 - b) * mu0
            else:
                r = (1.0 - b) * mu0 + b * lommel
        out[k] = r * geom[k, 3] if use_albedo else r


@njit(cache=True, nogil=True)
def node_geometry(hx, hy, rot, points, position, sun, out):
    """The shading geometry of every node of a patch, as :func:`shade_subrays` reads it:
    ``out[k]`` = (μ0, μ, cos α, 0) of node k with the unit normal normalise(−hx·UX − hy·UY + UZ)
    (``rot`` = UX, UY, UZ as columns; :func:`spctool.geometry.heightfield.normals_body`), the unit Sun
    ``sun`` and the unit vector from the node's body point ``points[k]`` to ``position``.  ``hx``,
    ``hy``: flat (N,), ``points`` (N, 3)."""
    for k in range(hx.shape[0]):
        a = -hx[k]
        b = -hy[k]
        n0 = a * rot[0, 0] + b * rot[0, 1] + rot[0, 2]
        n1 = a * rot[1, 0] + b * rot[1, 1] + rot[1, 2]
        n2 = a * rot[2, 0] + b * rot[2, 1] + rot[2, 2]
        nn = 1.0 / math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        e0 = position[0] - points[k, 0]
        e1 = position[1] - points[k, 1]
        e2 = position[2] - points[k, 2]
        en = 1.0 / math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        e0 *= en
        e1 *= en
        e2 *= en
        out[k, 0] = (n0 * sun[0] + n1 * sun[1] + n2 * sun[2]) * nn
        out[k, 1] = (n0 * e0 + n1 * e1 + n2 * e2) * nn
        out[k, 2] = sun[0] * e0 + sun[1] * e1 + sun[2] * e2
        out[k, 3] = 0.0


@njit(cache=True, nogil=True)
def gouraud_subrays(pos, surface, sh, planes, ns, out):
    """``shading="gouraud"`` per sub-ray: for every sub-ray k that hit patch p = ``surface[k]`` ≥ 0,
    ``out[k]`` = the bilinear interpolation of ``planes[p]`` (the patch's node radiances, n × n of the
    padded (P, n_max, n_max); ``ns[p]`` = n) at its grid position ``pos[k]`` = (u, w) (index
    coordinates, clamped to the grid; the cell and weights of the fused kernel's own interpolation),
    or 0 where it is in cast shadow (``sh[k]``).  Other sub-rays (sky, the shape) are left as they are.
    """
    for k in range(out.shape[0]):
        p = surface[k]
        if p < 0:
            continue
        if sh[k]:
            out[k] = 0.0
            continue
        n = ns[p]
        u = min(max(pos[k, 0], 0.0), n - 1.0)
        w = min(max(pos[k, 1], 0.0), n - 1.0)
        i = min(int(math.floor(u)), n - 2)
        j = min(int(math.floor(w)), n - 2)
        fu = u - i
        fw = w - j
        out[k] = (
            (1 - fu) * (1 - fw) * planes[p, i, j]
            + fu * (1 - fw) * planes[p, i + 1, j]
            + (1 - fu) * fw * planes[p, i, j + 1]
            + fu * fw * planes[p, i + 1, j + 1]
        )


#: barycentric slack of :func:`terrain_cells`: a sub-ray on a shared edge is inside both triangles
_EDGE_EPS = 1e-9


@njit(cache=True, nogil=True, forceinline=True)
def _barycentric(x, y, x0, y0, x1, y1, x2, y2, inv):
    """Barycentric coordinates of lattice point (x, y) in triangle (0, 1, 2); ``inv``: 1 / its doubled
    signed area."""
    b0 = ((x1 - x) * (y2 - y) - (x2 - x) * (y1 - y)) * inv
    b1 = ((x2 - x) * (y0 - y) - (x0 - x) * (y2 - y)) * inv
    return b0, b1, 1.0 - b0 - b1


@njit(cache=True, nogil=True, forceinline=True)
def _draw(x, y, x0, y0, d0, x1, y1, d1, x2, y2, d2, inv, value, zbuf, out, inner):
    """Lattice point (x, y) into the depth buffer when it lies in triangle (0, 1, 2) (``inv``: 1 / its
    doubled signed area); True when it does.  ``inner`` counts the triangles the point lies strictly
    inside (two or more: surfaces overlap there)."""
    b0, b1, b2 = _barycentric(x, y, x0, y0, x1, y1, x2, y2, inv)
    if b0 >= -_EDGE_EPS and b1 >= -_EDGE_EPS and b2 >= -_EDGE_EPS:
        if b0 > _EDGE_EPS and b1 > _EDGE_EPS and b2 > _EDGE_EPS:
            inner[y, x] += 1
        d = b0 * d0 + b1 * d1 + b2 * d2
        if d < zbuf[y, x]:
            zbuf[y, x] = d
            out[y, x] = value
        return True
    return False


@njit(cache=True, nogil=True, forceinline=True)
def _draw_quad(xa_, ya_, da, xb_, yb_, db, xc, yc, dc, xd, yd, dd, value, zbuf, out, inner):
    """Quad a, b, c, d (a–c its diagonal) as the triangles (a, b, c) and (a, d, c)."""
    ny, nx = out.shape
    lo_x = max(int(math.ceil(min(min(xa_, xb_), min(xc, xd)) - 1e-6)), 0)
    hi_x = min(int(math.floor(max(max(xa_, xb_), max(xc, xd)) + 1e-6)), nx - 1)
    if lo_x > hi_x:
        return
    lo_y = max(int(math.ceil(min(min(ya_, yb_), min(yc, yd)) - 1e-6)), 0)
    hi_y = min(int(math.floor(max(max(ya_, yb_), max(yc, yd)) + 1e-6)), ny - 1)
    if lo_y > hi_y:
        return
    area1 = (xb_ - xa_) * (yc - ya_) - (xc - xa_) * (yb_ - ya_)
    area2 = (xd - xa_) * (yc - ya_) - (xc - xa_) * (yd - ya_)
    ok1 = area1 != 0.0 and math.isfinite(area1)
    ok2 = area2 != 0.0 and math.isfinite(area2)
    inv1 = 1.0 / area1 if ok1 else 0.0
    inv2 = 1.0 / area2 if ok2 else 0.0
    for y in range(lo_y, hi_y + 1):
        for x in range(lo_x, hi_x + 1):
            inside = False
            if ok1:
                inside = _draw(x, y, xa_, ya_, da, xb_, yb_, db, xc, yc, dc, inv1, value, zbuf, out, inner)
            if ok2 and not inside:
                _draw(x, y, xa_, ya_, da, xd, yd, dd, xc, yc, dc, inv2, value, zbuf, out, inner)


@njit(cache=True, nogil=True, forceinline=True)
def _convex(xa_, ya_, xb_, yb_, xc, yc, xd, yd):
    """The quad a, b, c, d (in this order) is strictly convex: its two triangles of either diagonal
    cover the same region, the convex hull of its corners."""
    s1 = (xb_ - xa_) * (yc - yb_) - (yb_ - ya_) * (xc - xb_)
    s2 = (xc - xb_) * (yd - yc) - (yc - yb_) * (xd - xc)
    s3 = (xd - xc) * (ya_ - yd) - (yd - yc) * (xa_ - xd)
    s4 = (xa_ - xd) * (yb_ - ya_) - (ya_ - yd) * (xb_ - xa_)
    positive = s1 > 0.0 and s2 > 0.0 and s3 > 0.0 and s4 > 0.0
    return positive or (s1 < 0.0 and s2 < 0.0 and s3 < 0.0 and s4 < 0.0)


@njit(cache=True, nogil=True, forceinline=True)
def _mark_hull(xa_, ya_, xb_, yb_, xc, yc, xd, yd, inner):
    """Count the lattice points of the triangles (a, b, d) and (b, c, d) — the other diagonal's — twice in
    ``inner``: with those of the facet triangles they cover the corners' convex hull, which holds the
    image of the cell's bilinear surface; a twisted or folded cell's surface can show there although
    neither facet triangle does, so those points go to the march."""
    ny, nx = inner.shape
    for t in range(2):
        if t == 0:
            x0, y0, x1, y1, x2, y2 = xa_, ya_, xb_, yb_, xd, yd
        else:
            x0, y0, x1, y1, x2, y2 = xb_, yb_, xc, yc, xd, yd
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if not (area != 0.0 and math.isfinite(area)):
            continue
        inv = 1.0 / area
        lo_x = max(int(math.ceil(min(x0, min(x1, x2)) - 1e-6)), 0)
        hi_x = min(int(math.floor(max(x0, max(x1, x2)) + 1e-6)), nx - 1)
        lo_y = max(int(math.ceil(min(y0, min(y1, y2)) - 1e-6)), 0)
        hi_y = min(int(math.floor(max(y0, max(y1, y2)) + 1e-6)), ny - 1)
        for y in range(lo_y, hi_y + 1):
            for x in range(lo_x, hi_x + 1):
                b0, b1, b2 = _barycentric(x, y, x0, y0, x1, y1, x2, y2, inv)
                if b0 >= -_EDGE_EPS and b1 >= -_EDGE_EPS and b2 >= -_EDGE_EPS:
                    inner[y, x] += 2


@njit(cache=True, nogil=True, forceinline=True)
def _full_cell(usable, i, j):
    n0, n1 = usable.shape
    if i < 0 or j < 0 or i >= n0 - 1 or j >= n1 - 1:
        return False
    # bitwise: a returned chain of `and` over array elements compiled to slow branchy code (the raster
    # of a 99 × 99 maplet took 30 % longer with it)
    return usable[i, j] & usable[i + 1, j] & usable[i, j + 1] & usable[i + 1, j + 1]


@njit(cache=True, nogil=True, forceinline=True)
def _wall(xs, ys, depth, feet, foot, i0, j0, i1, j1, zbuf, out, inner):
    """The wall below the edge (i0, j0)–(i1, j1), down to the box bottom (``feet[foot[i, j]]``: the
    node (i, j) there)."""
    a = foot[i0, j0]
    b = foot[i1, j1]
    _draw_quad(
        xs[i0, j0], ys[i0, j0], depth[i0, j0],
        xs[i1, j1], ys[i1, j1], depth[i1, j1],
        feet[b, 0], feet[b, 1], feet[b, 2],
        feet[a, 0], feet[a, 1], feet[a, 2],
        -2, zbuf, out, inner,
    )  # fmt: skip


@njit(cache=True, nogil=True)
def terrain_cells(xs, ys, depth, usable, foot, feet, out):
    """The cell of an (n, n) height grid seen by each sub-ray of a window, by rasterisation.

    ``xs``, ``ys`` (n, n): each node's projection in sub-ray lattice units (column, row of ``out``: the
    sub-ray at out[r, c] looks through lattice point (c, r)); ``depth`` (n, n): its depth along the line
    of sight; ``usable`` (n, n): valid and in front of the camera.  Every cell with four usable corners is
    drawn as the two triangles of the facet shading ((i, j), (i+1, j), (i+1, j+1)) and ((i, j), (i, j+1),
    (i+1, j+1)), depth interpolated linearly; the nearest wins.  The grid march
    (:func:`spctool.geometry._heightkernels._march`) also stops where a ray enters a cell's column
    through its side below the terrain — below the grid's border and around missing nodes — so those
    walls are drawn too, down to the patch box's bottom (``feet`` (m, 3): (lattice x, lattice y, depth)
    of the wall nodes there, node (i, j) at row ``foot[i, j]``, −1 for a node on no wall).

    ``out`` (rows, cols) int64: the cell i·(n − 1) + j, where the raster vouches for it; −2 where the
    caller must march: a wall in front; surfaces overlapping (a sub-ray strictly inside two triangles:
    an occluding ridge, a fold, a face seen from behind — where a bilinear cell's bulge past its two
    triangles could change the first crossing); the image of a cell whose projected corners are not a
    convex quad (its bilinear surface can show outside both its triangles, within the corners' hull);
    and the sub-rays next to such a one or, uncovered, next to anything drawn (the straight-edged image
    differs from the exact one by far less than a sub-ray); −1 elsewhere (no terrain)."""
    ny, nx = out.shape
    # the depth buffer and the overlap counts are owned here, for the whole call of _terrain_cells (whose
    # views of them carry no reference count)
    zbuf = np.full((ny, nx), np.inf)
    inner = np.zeros((ny, nx), np.int32)
    _terrain_cells(xs, ys, depth, usable, foot, feet, out, zbuf, inner)


@njit(cache=True, nogil=True)
def _terrain_cells(xs, ys, depth, usable, foot, feet, out, zbuf_, inner_):
    """:func:`terrain_cells` with its scratch arrays (held by the caller)."""
    ny, nx = out.shape
    n0, n1 = xs.shape
    out[:, :] = -1
    # the drawing helpers get views without reference counts (see borrowed): an array argument per
    # call would cost atomic increments and decrements, several times the drawing itself
    zbuf, cells, inner = borrowed(zbuf_), borrowed(out), borrowed(inner_)
    for i in range(n0 - 1):
        for j in range(n1 - 1):
            if not _full_cell(usable, i, j):
                continue
            _draw_quad(
                xs[i, j], ys[i, j], depth[i, j],
                xs[i + 1, j], ys[i + 1, j], depth[i + 1, j],
                xs[i + 1, j + 1], ys[i + 1, j + 1], depth[i + 1, j + 1],
                xs[i, j + 1], ys[i, j + 1], depth[i, j + 1],
                i * (n1 - 1) + j, zbuf, cells, inner,
            )  # fmt: skip
            if not _convex(
                xs[i, j], ys[i, j], xs[i + 1, j], ys[i + 1, j],
                xs[i + 1, j + 1], ys[i + 1, j + 1], xs[i, j + 1], ys[i, j + 1],
            ):  # fmt: skip
                _mark_hull(
                    xs[i, j], ys[i, j], xs[i + 1, j], ys[i + 1, j],
                    xs[i + 1, j + 1], ys[i + 1, j + 1], xs[i, j + 1], ys[i, j + 1], inner,
                )  # fmt: skip
            if not _full_cell(usable, i - 1, j):
                _wall(xs, ys, depth, feet, foot, i, j, i, j + 1, zbuf, cells, inner)
            if not _full_cell(usable, i + 1, j):
                _wall(xs, ys, depth, feet, foot, i + 1, j, i + 1, j + 1, zbuf, cells, inner)
            if not _full_cell(usable, i, j - 1):
                _wall(xs, ys, depth, feet, foot, i, j, i + 1, j, zbuf, cells, inner)
            if not _full_cell(usable, i, j + 1):
                _wall(xs, ys, depth, feet, foot, i, j + 1, i + 1, j + 1, zbuf, cells, inner)
    for y in range(ny):
        for x in range(nx):
            if inner[y, x] < 2:
                continue
            for yy in range(max(y - 1, 0), min(y + 2, ny)):
                for xx in range(max(x - 1, 0), min(x + 2, nx)):
                    cells[yy, xx] = -2
    for y in range(ny):
        for x in range(nx):
            if cells[y, x] != -1:
                continue
            for yy in range(max(y - 1, 0), min(y + 2, ny)):
                for xx in range(max(x - 1, 0), min(x + 2, nx)):
                    if zbuf[yy, xx] < np.inf:  # something drawn next to it
                        cells[y, x] = -2
