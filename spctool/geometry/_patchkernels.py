"""Numba kernels of the height-patch renderer (:mod:`spctool.stages.render`): ray/box and sphere
tests, the exact crossing of a patch's bilinear terrain, and the fused path for patches without a
shape (register's image-space templates, patch-only photos).

Specification: spc-formats.md §1.3 (the maplet grid), spc-algorithms.md §3.1 (node slopes); the
arithmetic is :func:`spctool.stages.render.trace` → ``shadowed`` → ``shade``'s, checked against them
in ``tests/test_render.py``.

The fused path.  One pass per sub-ray does what trace → shadowed → shade do for patches when there is no
shape, with the same arithmetic in the same order (sphere pre-test, slab, exact bilinear crossing,
bilinear interpolation, normals, the shadow ray from just above the own terrain) but without the
per-batch temporaries and fancy indexing; the photometric law itself stays in :mod:`spctool.photometry`,
applied to the kernel's μ₀, μ, cos α.  Small windows run on the calling thread: a template of a few
thousand rays is a couple of ms of work, less than what waking a thread pool costs on a loaded machine
(parallel=True kernels made a 77×77 template ~8× slower on 2 busy cores).  The helpers are inlined by
LLVM (forceinline): a call per ray with a dozen array arguments cost ~20 % of the work, and numba-level
inlining of this much code compiles several times slower.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from spctool.geometry._heightkernels import (
    _cell_crossing,
    _cell_f,
    _first_crossing,
    _march,
    borrowed,
    lit_from,
    rises_faster,
    slope_bound,
)

#: surface id of a ray that hits nothing / the shape (patches are numbered 0, 1, …)
SKY = -2
SHAPE = -1

_BIG = 1e300

#: a raster or predicted cell is taken only where the ray enters it at least this high (cells) above its
#: terrain: below, the previous cell's formula might already read a crossing there (:func:`_cell_hit`)
_HINT_CLEARANCE = 1e-9


@numba.njit(inline="always", cache=True)
def _slab1(o, d, lo, hi):
    """Entry/exit of o + t·d in [lo, hi] along one axis (±_BIG for parallel rays)."""
    if d == 0.0:
        if lo <= o <= hi:
            return -_BIG, _BIG
        return _BIG, -_BIG
    t1 = (lo - o) / d
    t2 = (hi - o) / d
    if t1 > t2:
        return t2, t1
    return t1, t2


@numba.njit(parallel=True, cache=True)
def _local_slab(origins, dirs, v, rot, inv_scale, lo, hi, o_out, d_out, tn_out, tf_out):
    """Maplet-frame rays (cells; direction per km) and their box entry (≥ 0) / exit parameters."""
    for k in numba.prange(origins.shape[0]):
        px = origins[k, 0] - v[0]
        py = origins[k, 1] - v[1]
        pz = origins[k, 2] - v[2]
        dx = dirs[k, 0]
        dy = dirs[k, 1]
        dz = dirs[k, 2]
        tn = 0.0
        tf = _BIG
        for a in range(3):
            oa = (px * rot[0, a] + py * rot[1, a] + pz * rot[2, a]) * inv_scale
            da = (dx * rot[0, a] + dy * rot[1, a] + dz * rot[2, a]) * inv_scale
            o_out[k, a] = oa
            d_out[k, a] = da
            t1, t2 = _slab1(oa, da, lo[a], hi[a])
            if t1 > tn:
                tn = t1
            if t2 < tf:
                tf = t2
        tn_out[k] = tn
        tf_out[k] = tf


@numba.njit(parallel=True, cache=True)
def _near_spheres(origins, dirs, use, centres, radii2, out):
    """out[k, p] = ray origin + t·dir (t ≥ 0, unit dir) passes within sphere p (rays with ``use``)."""
    npatch = centres.shape[0]
    for k in numba.prange(origins.shape[0]):
        if not use[k]:
            continue
        for p in range(npatch):
            wx = centres[p, 0] - origins[k, 0]
            wy = centres[p, 1] - origins[k, 1]
            wz = centres[p, 2] - origins[k, 2]
            w2 = wx * wx + wy * wy + wz * wz
            tc = wx * dirs[k, 0] + wy * dirs[k, 1] + wz * dirs[k, 2]
            if tc > 0.0:
                w2 -= tc * tc
            out[k, p] = w2 <= radii2[p]


@numba.njit(parallel=True, cache=True)
def _in_boxes(points, use, centres, radii2, vs, rots, inv_scales, los, his, out):
    """out[k] = point k (with ``use``) lies in any patch's maplet-frame box (sphere pre-test first)."""
    npatch = centres.shape[0]
    for k in numba.prange(points.shape[0]):
        if not use[k]:
            continue
        for p in range(npatch):
            dx = points[k, 0] - centres[p, 0]
            dy = points[k, 1] - centres[p, 1]
            dz = points[k, 2] - centres[p, 2]
            if dx * dx + dy * dy + dz * dz > radii2[p]:
                continue
            px = points[k, 0] - vs[p, 0]
            py = points[k, 1] - vs[p, 1]
            pz = points[k, 2] - vs[p, 2]
            inside = True
            for a in range(3):
                c = (px * rots[p, 0, a] + py * rots[p, 1, a] + pz * rots[p, 2, a]) * inv_scales[p]
                if c < los[p, a] or c > his[p, a]:
                    inside = False
            if inside:
                out[k] = True
                break


@numba.njit(parallel=True, cache=True)
def _crossings(h, valid, tops, hmin, hmax, q, o, d, t_min, t_max, out):
    """heightfield.intersect_rays for maplet-frame rays, in parallel (same exact crossing kernel)."""
    for m in numba.prange(o.shape[0]):
        out[m] = _first_crossing(
            h,
            valid,
            tops,
            hmin,
            hmax,
            o[m, 0] + q,
            o[m, 1] + q,
            o[m, 2],
            d[m, 0],
            d[m, 1],
            d[m, 2],
            t_min[m],
            t_max[m],
        )


@numba.njit(inline="always", cache=True)
def _sphere_miss(geo, p, x0, x1, x2, d0, d1, d2):
    """The ray x + t·d (t ≥ 0) passes outside patch p's bounding sphere (_near_spheres)."""
    wx = geo[p, 0] - x0
    wy = geo[p, 1] - x1
    wz = geo[p, 2] - x2
    w2 = wx * wx + wy * wy + wz * wz
    tc = wx * d0 + wy * d1 + wz * d2
    if tc > 0.0:
        w2 -= tc * tc
    return not w2 <= geo[p, 3]


@numba.njit(inline="always", cache=True)
def _to_cells(geo, p, x0, x1, x2):
    """Body-frame vector (x0, x1, x2) (km) in patch p's maplet frame, in cells: (UX·x, UY·x, UZ·x)/SCALE
    (geo[p, 7:16] the maplet → body rotation row by row, geo[p, 16] = 1/SCALE)."""
    inv = geo[p, 16]
    return (
        (x0 * geo[p, 7] + x1 * geo[p, 10] + x2 * geo[p, 13]) * inv,
        (x0 * geo[p, 8] + x1 * geo[p, 11] + x2 * geo[p, 14]) * inv,
        (x0 * geo[p, 9] + x1 * geo[p, 12] + x2 * geo[p, 15]) * inv,
    )


@numba.njit(inline="always", cache=True)
def _slab_local(geo, boxes, p, hi_col, x0, x1, x2, d0, d1, d2):
    """Maplet-frame ray and box entry/exit of patch p (_local_slab); box hi from boxes[p, hi_col:]."""
    oa0, oa1, oa2 = _to_cells(geo, p, x0 - geo[p, 4], x1 - geo[p, 5], x2 - geo[p, 6])
    da0, da1, da2 = _to_cells(geo, p, d0, d1, d2)
    tn = 0.0
    tf = _BIG
    t1, t2 = _slab1(oa0, da0, boxes[p, 0], boxes[p, hi_col])
    if t1 > tn:
        tn = t1
    if t2 < tf:
        tf = t2
    t1, t2 = _slab1(oa1, da1, boxes[p, 1], boxes[p, hi_col + 1])
    if t1 > tn:
        tn = t1
    if t2 < tf:
        tf = t2
    t1, t2 = _slab1(oa2, da2, boxes[p, 2], boxes[p, hi_col + 2])
    if t1 > tn:
        tn = t1
    if t2 < tf:
        tf = t2
    return oa0, oa1, oa2, da0, da1, da2, tn, tf


@numba.njit(inline="always", cache=True)
def _bilinear_at(maps, p, c, i, j, w00, w10, w01, w11):
    return (
        w00 * maps[p, c, i, j]
        + w10 * maps[p, c, i + 1, j]
        + w01 * maps[p, c, i, j + 1]
        + w11 * maps[p, c, i + 1, j + 1]
    )


@numba.njit(forceinline=True, cache=True)
def _cell_hit(hts, near, p, n, i, j, u0, w0, z0, du, dw, dz, t_lo, t_hi, hmax, reach):
    """The first crossing of a grid ray (index coordinates) with the terrain when the raster says it lies
    in cell (i, j) — what :func:`_march` returns, with the same clip (z ≤ hmax) and the same cell step
    (:func:`_cell_crossing`) — or nan when that cannot be vouched for (the caller then marches).

    Vouched for when the ray enters the cell's column above the terrain, and, from the height ``hmax``
    of the highest node down to that column, stays within ``reach`` cells of it and descends faster than
    any slope of the terrain there (``near`` (P, n − 1, n − 1, 2): the largest steps along x and y over
    those cells, +inf near missing nodes): its height above the terrain then only falls on the way, so
    no earlier cell was crossed.  Where the march could read the same crossing through another cell's
    bilinear formula (a few ulp apart), the march decides: the cell must be the one the march assigns
    to the ray's segment there (its midpoint's, as :func:`_march` computes it: a ray along a grid line
    lies in two columns), the ray must enter it more than :data:`_HINT_CLEARANCE` above the terrain
    (not on a shared edge), and the crossing must not lie at its exit within 1e-12 (a node, an edge).
    ``n``: the patch's nodes per side."""
    if not dz < 0.0:
        return math.nan
    if not dz < -(near[p, i, j, 0] * abs(du) + near[p, i, j, 1] * abs(dw)):
        return math.nan
    t_top = (hmax - z0) / dz
    t_lo = max(t_lo, t_top)
    ta, tb = _slab1(u0, du, float(i), i + 1.0)  # the cell's column, as the march's grid-line counters
    t_lo = max(t_lo, ta)
    t_hi = min(t_hi, tb)
    ta, tb = _slab1(w0, dw, float(j), j + 1.0)
    t_lo = max(t_lo, ta)
    t_hi = min(t_hi, tb)
    if not t_lo <= t_hi:
        return math.nan
    if (t_lo - t_top) * max(abs(du), abs(dw)) > reach:
        return math.nan  # the way down is longer than the slope bound covers
    tm = 0.5 * (t_lo + t_hi)  # the march's cell for this segment
    if min(max(int(math.floor(u0 + tm * du)), 0), n - 2) != i:
        return math.nan
    if min(max(int(math.floor(w0 + tm * dw)), 0), n - 2) != j:
        return math.nan
    fa = _cell_f(hts, p, i, j, u0, w0, z0, du, dw, dz, t_lo)
    if not fa > _HINT_CLEARANCE:
        return math.nan
    tp = _cell_crossing(hts, p, i, j, u0, w0, z0, du, dw, dz, t_lo, t_hi, fa)
    if t_hi - tp < 1e-12 * abs(t_hi):
        return math.nan  # at the exit: the next cell's formula may give the march's value
    return tp


@numba.njit(forceinline=True, cache=True)
def _patch_ray(
    k, origin, dirs, ok, sun_lit, sun, shadows, offset, facet, geo, boxes, maps, hts, valids, tops, ns,
    upmax, horizon, entry, near, clear, cand, surf, geom, sh, cells, pos,
):  # fmt: skip
    """Sub-ray k: nearest patch hit → surf[k] (SKY or the patch), geom[k] = (μ₀, μ, cos α, albedo) and
    the cast shadow sh[k] (tested where the normal faces ``sun_lit``, as :func:`render` does); rays
    without ``ok`` or a finite direction are sky (geom (0, 0, 1, 0): dark).
    ``facet``: shade with the normal of the flat triangle under the hit (two per cell,
    split along the (i, j)–(i+1, j+1) diagonal) instead of the interpolated node slopes.  ``upmax``
    (P, n − 1, n − 1): :func:`_upwind_max` of each patch for this Sun — the own-patch shadow march ends
    where the rising ray passes the highest cell ahead of it (nothing beyond can be crossed: the same
    answer, fewer cells); ``horizon``, ``entry`` (P, n − 1, n − 1): ``_heightkernels.horizon_bound`` — the
    shadow march ends where the ray is above it, and ``lit_from`` declares a shadow ray lit without a march
    where it provably clears every cell on its way, over a few columns, up to the grid's edge or a
    column's entry bound (+inf: no shortcut, the reference); ``clear`` (P, n − 1, n − 1):
    :func:`lit_corridor`, the cells from which a shadow ray rises over the terrain within the reach (False: no
    shortcut).  ``cand`` (one patch; empty: march every ray): the raster's cell under each sub-ray
    (:func:`spctool.geometry._rasterkernels.terrain_cells`): −1 no terrain (sky), ≥ 0 the cell i·(n − 1) + j
    whose crossing is taken (:func:`_cell_hit`) when the ray enters its column above the terrain and descends
    more steeply than the terrain's steepest slope (then the first crossing is there: the same hit as the
    march's), −2 or else: the march.  ``cells`` (empty: not wanted) gets the cell i·(n − 1) + j of the hit
    (one patch; :func:`_fused_rays` writes −2 first for every ray), which a later render of the same patch
    can pass as its ``cand``."""
    if _sky(k, dirs, ok, surf, geom, sh):
        return
    c = cand[k] if cand.shape[0] > 0 else -2
    if c == -1:
        return
    best, lx, ly = _patch_hit(k, origin, dirs, geo, boxes, hts, valids, tops, ns, near, c)
    if best < 0:
        return
    _patch_shade(
        k, best, lx, ly, origin, dirs, sun_lit, sun, shadows, offset, facet, geo, boxes, maps, hts, valids,
        tops, ns, upmax, horizon, entry, near, clear, surf, geom, sh, cells, pos,
    )  # fmt: skip


@numba.njit(forceinline=True, cache=True)
def _sky(k, dirs, ok, surf, geom, sh):
    """Sub-ray k's outputs as sky; True when it stays so (no ``ok`` or a direction not finite)."""
    surf[k] = SKY
    sh[k] = False
    geom[k, 0] = 0.0  # sky: dark (μ₀ = μ = 0, α = 0, albedo 0), radiance exactly 0 under every law
    geom[k, 1] = 0.0
    geom[k, 2] = 1.0
    geom[k, 3] = 0.0
    d0, d1, d2 = dirs[k, 0], dirs[k, 1], dirs[k, 2]
    return not (ok[k] and math.isfinite(d0) and math.isfinite(d1) and math.isfinite(d2))


@numba.njit(forceinline=True, cache=True)
def _patch_hit(k, origin, dirs, geo, boxes, hts, valids, tops, ns, near, c):
    """(patch, x, y) of sub-ray k's nearest hit (maplet-frame cells), patch −1 when none; ``c``: the
    raster's cell (≥ 0, one patch) or −2 (march)."""
    d0 = dirs[k, 0]
    d1 = dirs[k, 1]
    d2 = dirs[k, 2]
    o0 = origin[0]
    o1 = origin[1]
    o2 = origin[2]
    npatch = geo.shape[0]
    t = np.inf
    best = -1
    lx = 0.0
    ly = 0.0
    for p in range(npatch):
        if _sphere_miss(geo, p, o0, o1, o2, d0, d1, d2):
            continue
        a0, a1, a2, b0, b1, b2, tn, tf = _slab_local(geo, boxes, p, 3, o0, o1, o2, d0, d1, d2)
        tmax = tf if tf < t else t
        if tmax >= tn:
            n = ns[p]
            q = geo[p, 18]
            tp = math.nan
            if c >= 0:  # the raster's cell, where _cell_hit can vouch for it
                tp = _cell_hit(
                    hts, near, p, n, c // (n - 1), c % (n - 1), a0 + q, a1 + q, a2, b0, b1, b2, tn, tmax,
                    geo[p, 20], geo[p, 21],
                )  # fmt: skip
            if math.isnan(tp):
                tp = _march(
                    hts, valids, tops, p, n, n, geo[p, 19], geo[p, 20],
                    a0 + q, a1 + q, a2, b0, b1, b2, tn, tmax, tops, False,
                )  # fmt: skip
            if math.isfinite(tp) and tp < t:
                t = tp
                best = p
                lx = a0 + tp * b0
                ly = a1 + tp * b1
    return best, lx, ly


@numba.njit(forceinline=True, cache=True)
def _patch_shade(
    k, p, lx, ly, origin, dirs, sun_lit, sun, shadows, offset, facet, geo, boxes, maps, hts, valids, tops,
    ns, upmax, horizon, entry, near, clear, surf, geom, sh, cells, pos,
):  # fmt: skip
    """Shading geometry and cast shadow of sub-ray k, which hits patch p at maplet-frame (lx, ly) (and
    its cell in ``cells`` and its grid position (u, w) in ``pos`` unless they are empty)."""
    d0 = dirs[k, 0]
    d1 = dirs[k, 1]
    d2 = dirs[k, 2]
    best = p
    npatch = geo.shape[0]
    surf[k] = p
    # height, slopes and albedo at the hit (HeightPatch.interpolate)
    n = ns[p]
    q = geo[p, 18]
    u = min(max(lx + q, 0.0), n - 1.0)
    w = min(max(ly + q, 0.0), n - 1.0)
    i = min(int(math.floor(u)), n - 2)
    j = min(int(math.floor(w)), n - 2)
    fu = u - i
    fw = w - j
    w00 = (1 - fu) * (1 - fw)
    w10 = fu * (1 - fw)
    w01 = (1 - fu) * fw
    w11 = fu * fw
    if cells.shape[0] > 0:
        cells[k] = i * (n - 1) + j
    if pos.shape[0] > 0:
        pos[k, 0] = u
        pos[k, 1] = w
    z = _bilinear_at(maps, p, 0, i, j, w00, w10, w01, w11)
    if facet:  # the flat triangle's slopes (HeightPatch.facet_slopes)
        if fu >= fw:  # corners (i, j), (i+1, j), (i+1, j+1)
            hx = maps[p, 0, i + 1, j] - maps[p, 0, i, j]
            hy = maps[p, 0, i + 1, j + 1] - maps[p, 0, i + 1, j]
        else:  # corners (i, j), (i, j+1), (i+1, j+1)
            hx = maps[p, 0, i + 1, j + 1] - maps[p, 0, i, j + 1]
            hy = maps[p, 0, i, j + 1] - maps[p, 0, i, j]
    else:
        hx = _bilinear_at(maps, p, 1, i, j, w00, w10, w01, w11)
        hy = _bilinear_at(maps, p, 2, i, j, w00, w10, w01, w11)
    alb = _bilinear_at(maps, p, 3, i, j, w00, w10, w01, w11)
    # unit shading normal (heightfield.normals_body) and the shading geometry (shade)
    a_ = -hx
    b_ = -hy
    n0 = a_ * geo[p, 7] + b_ * geo[p, 8] + geo[p, 9]
    n1 = a_ * geo[p, 10] + b_ * geo[p, 11] + geo[p, 12]
    n2 = a_ * geo[p, 13] + b_ * geo[p, 14] + geo[p, 15]
    nin = 1.0 / math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    n0 = n0 * nin
    n1 = n1 * nin
    n2 = n2 * nin
    dn = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    e0 = -d0 / dn
    e1 = -d1 / dn
    e2 = -d2 / dn
    s0 = sun[0]
    s1 = sun[1]
    s2 = sun[2]
    geom[k, 0] = n0 * s0 + n1 * s1 + n2 * s2
    geom[k, 1] = n0 * e0 + n1 * e1 + n2 * e2
    geom[k, 2] = s0 * e0 + s1 * e1 + s2 * e2
    geom[k, 3] = alb
    if not shadows or not (n0 * sun_lit[0] + n1 * sun_lit[1] + n2 * sun_lit[2] > 0.0):
        return
    # cast shadow (shadowed): first the own patch's quick answers — the ray rises above the highest cell
    # ahead (upmax), or provably clears its own cell and its horizon (lit_from; shortcuts on where the
    # horizon bound is finite) — with the Sun in maplet cells exactly as _slab_local computes it
    b0, b1, b2 = _to_cells(geo, p, s0, s1, s2)
    own_lit = False
    if (
        npatch == 1
        and b2 > 0.0
        and (clear[p, i, j] or b2 > near[p, i, j, 2] * abs(b0) + near[p, i, j, 3] * abs(b1))
    ):
        # the ray rises faster than the terrain wherever it can be within geo[p, 22] cells (clear[p, i, j],
        # :func:`lit_corridor`) or than every slope within those cells of the hit (near[p, i, j]): its
        # height above the terrain only grows from the offset it starts at while it stays there, so it
        # crosses nothing there; it is lit (the march's answer; issue 17) when it is above the highest
        # cell ahead (upmax) before it leaves those cells, or, where it leaves them, above the horizon
        # bound of the cell it is in (no crossing from there on), or off the grid
        reach = geo[p, 22]
        lead = max(abs(b0), abs(b1))
        if (upmax[p, i, j] - z - offset) * lead <= reach * b2:
            return
        t = reach / lead if lead > 0.0 else 0.0
        q = geo[p, 18]
        u_t = lx + q + b0 * t
        w_t = ly + q + b1 * t
        if u_t < 0.0 or u_t > n - 1.0 or w_t < 0.0 or w_t > n - 1.0:
            return
        i_t = min(int(math.floor(u_t)), n - 2)
        j_t = min(int(math.floor(w_t)), n - 2)
        if z + offset + b2 * t > horizon[p, i_t, j_t]:
            return
    if b2 > 0.0:
        top = upmax[p, i, j]
        own_lit = z + offset > top
        if not own_lit and horizon[p, i, j] < np.inf:
            q = geo[p, 18]
            own_lit = lit_from(hts, tops, entry, p, n, n, lx + q, ly + q, z + offset, b0, b1, b2)
    if own_lit and npatch == 1:
        return
    # the ray toward the Sun from the hit's body point (HeightPatch.to_body)
    scale = geo[p, 17]
    x0 = geo[p, 4] + scale * (lx * geo[p, 7] + ly * geo[p, 8] + z * geo[p, 9])
    x1 = geo[p, 5] + scale * (lx * geo[p, 10] + ly * geo[p, 11] + z * geo[p, 12])
    x2 = geo[p, 6] + scale * (lx * geo[p, 13] + ly * geo[p, 14] + z * geo[p, 15])
    for p in range(npatch):
        own = p == best
        if own and own_lit:
            continue
        if not own and _sphere_miss(geo, p, x0, x1, x2, s0, s1, s2):
            continue
        # the box raised by the relief: for the own patch its exit is where the ray leaves the column
        a0, a1, a2, b0, b1, b2, tn, tf = _slab_local(geo, boxes, p, 6, x0, x1, x2, s0, s1, s2)
        if own:  # start on the terrain (exact local hit), just above it
            a0 = lx
            a1 = ly
            a2 = z + offset
            tn = 0.0
            if b2 > 0.0:  # rising: the march ends above the highest cell ahead
                tc = (upmax[p, i, j] - a2) / b2
                if tc < tf:
                    tf = tc
        if tf >= tn:
            n = ns[p]
            q = geo[p, 18]
            tp = _march(
                hts, valids, tops, p, n, n, geo[p, 19], geo[p, 20],
                a0 + q, a1 + q, a2, b0, b1, b2, tn, tf, horizon, True,
            )  # fmt: skip
            if math.isfinite(tp):
                sh[k] = True
                return


@numba.njit(cache=True, nogil=True)
def _fused_rays(
    origin, dirs, ok, sun_lit, sun, shadows, offset, facet, geo, boxes, maps, valids, tops, ns, upmax,
    horizon, entry, near, clear, cand, surf, geom, sh, cells, pos,
):  # fmt: skip
    """:func:`_patch_ray` for every sub-ray (releases the GIL); ``cand``: the raster's (or an earlier
    render's) cells or empty; ``cells``: where to write each sub-ray's cell (−2 without a hit), or empty;
    ``pos`` (n, 2): where to write each sub-ray's grid position (u, w) (index coordinates, clamped to the
    grid; NaN without a hit), or empty."""
    # per-ray helpers get views without reference counts (borrowed: no atomic operations per call) and
    # the heights as one (P, n, n) view, indexed in place by the march (no view per ray)
    origin, dirs, ok = borrowed(origin), borrowed(dirs), borrowed(ok)
    sun_lit, sun, geo, boxes = borrowed(sun_lit), borrowed(sun), borrowed(geo), borrowed(boxes)
    maps, valids, tops, ns = borrowed(maps), borrowed(valids), borrowed(tops), borrowed(ns)
    upmax, horizon, entry, cand = borrowed(upmax), borrowed(horizon), borrowed(entry), borrowed(cand)
    near, clear = borrowed(near), borrowed(clear)
    surf, geom, sh, cells = borrowed(surf), borrowed(geom), borrowed(sh), borrowed(cells)
    pos = borrowed(pos)
    hts = borrowed(maps[:, 0])
    if cells.shape[0] > 0:  # no hit: cell −2 (march), position NaN (the hits overwrite theirs)
        for k in range(cells.shape[0]):
            cells[k] = -2
    if pos.shape[0] > 0:
        for k in range(pos.shape[0]):
            pos[k, 0] = math.nan
            pos[k, 1] = math.nan
    if cand.shape[0] == 0:
        for k in range(dirs.shape[0]):
            _patch_ray(
                k, origin, dirs, ok, sun_lit, sun, shadows, offset, facet, geo, boxes, maps, hts, valids,
                tops, ns, upmax, horizon, entry, near, clear, cand, surf, geom, sh, cells, pos,
            )  # fmt: skip
        return
    # the raster's cells: every hit first (one quadratic per sub-ray, the march where the cell cannot
    # vouch), then the shading and shadows of the hits — two short loops run faster than one long one
    n = dirs.shape[0]
    where = np.empty((n, 2))  # indexed here only: plain arrays (a borrowed view of a local array
    which = np.full(n, -1, np.int64)  # would outlive its owner, freed after the owner's last use)
    for k in range(n):
        if _sky(k, dirs, ok, surf, geom, sh) or cand[k] == -1:
            continue
        best, lx, ly = _patch_hit(k, origin, dirs, geo, boxes, hts, valids, tops, ns, near, cand[k])
        which[k] = best
        where[k, 0] = lx
        where[k, 1] = ly
    for k in range(n):
        if which[k] >= 0:
            _patch_shade(
                k, which[k], where[k, 0], where[k, 1], origin, dirs, sun_lit, sun, shadows, offset, facet,
                geo, boxes, maps, hts, valids, tops, ns, upmax, horizon, entry, near, clear, surf, geom, sh,
                cells, pos,
            )  # fmt: skip


@numba.njit(inline="always", cache=True)
def _max2(x, y):
    """The larger of two floats (a select: loops of it vectorise where ``max`` does not)."""
    return x if x > y else y


@numba.njit(cache=True, nogil=True)
def lit_corridor(geo, maps, valids, ns, sun, out):
    """out (P, n − 1, n − 1) bool: for every cell of each patch, a shadow ray from any point of it (the Sun
    ``sun`` in maplet cells as :func:`_patch_shade` computes it) rises faster than the bilinear terrain in
    every cell it can pass within ``geo[p, 22]`` cells along its dominant axis — its height above the terrain
    only grows there (the ``near`` shortcut's argument for the cells the ray can reach rather than every cell
    around the hit). A cell's directional slope is largest at a corner (``slope_bound`` and ``rises_faster``,
    what ``lit_from`` tests cell by cell); the cells the ray can pass are those of the cell's own box moved by
    up to the reach toward the Sun (one row of slack at the far side); a cell with a missing corner clears
    nothing.  False where the Sun is not above the maplet plane (and on the padding of smaller patches).

    Computed once per patch and Sun (:meth:`spctool.geometry.surfaces.PatchSet.fused_arrays`): on the
    s16-50m maplets 79 % of the cells clear, where the isotropic ``near`` bound lets through 24 % of the
    hits (the rest went on to ``lit_from``'s column walk)."""
    s0 = sun[0]
    s1 = sun[1]
    s2 = sun[2]
    for p in range(geo.shape[0]):
        out[p] = False
        n = ns[p]
        m = n - 1
        b0, b1, b2 = _to_cells(geo, p, s0, s1, s2)
        if not b2 > 0.0 or m < 1:
            continue
        lead = max(abs(b0), abs(b1))
        t = geo[p, 22] / lead if lead > 0.0 else 0.0
        # the cells the ray can be in: rows i + di_lo … i + di_hi, columns j + dj_lo … j + dj_hi
        di_lo = int(math.floor(min(0.0, b0 * t) - 1e-9))
        di_hi = int(math.floor(1.0 + max(0.0, b0 * t) + 1e-9))
        dj_lo = int(math.floor(min(0.0, b1 * t) - 1e-9))
        dj_hi = int(math.floor(1.0 + max(0.0, b1 * t) + 1e-9))
        # whole rows at a time, indexed from non-negative bases (loops that vectorise): the slopes, +inf on
        # the cells of a missing node, then the maxima over each cell's columns and over its rows
        slope = np.empty((m, m))
        for i in range(m):
            r0 = maps[p, 0, i]
            r1 = maps[p, 0, i + 1]
            srow = slope[i]
            for j in range(m):
                srow[j] = slope_bound(r0[j], r1[j], r0[j + 1], r1[j + 1], b0, b1)
        for i in range(n):
            for j in range(n):
                if not valids[p, i, j]:
                    for ci in range(max(i - 1, 0), min(i, m - 1) + 1):
                        for cj in range(max(j - 1, 0), min(j, m - 1) + 1):
                            slope[ci, cj] = np.inf
        rows = np.full((m, m), -np.inf)
        for d in range(dj_lo, dj_hi + 1):
            src, dst = max(d, 0), max(-d, 0)
            for i in range(m):
                srow = slope[i]
                rrow = rows[i]
                for k in range(m - abs(d)):
                    rrow[dst + k] = _max2(rrow[dst + k], srow[src + k])
        top = np.full((m, m), -np.inf)
        for d in range(di_lo, di_hi + 1):
            src, dst = max(d, 0), max(-d, 0)
            for k in range(m - abs(d)):
                rrow = rows[src + k]
                trow = top[dst + k]
                for j in range(m):
                    trow[j] = _max2(trow[j], rrow[j])
        for i in range(m):
            for j in range(m):
                out[p, i, j] = rises_faster(b2, top[i, j])


@numba.njit(cache=True, nogil=True)
def predict_cells(pos, ds, dl, n, out, step=1.0):
    """out (H, W) int64: the terrain cell i·(n − 1) + j (n nodes per side) where each sub-ray of a render
    is expected to hit, from ``pos`` (H', W', 2), an earlier render's hit positions (u, w) on a lattice
    ``step`` times this one's spacing (1: the same; ½: this render has twice its sub-rays per pixel
    axis; NaN: no hit): sub-ray (r, c) of this render sits where the earlier one's
    (r·step + ``dl``, c·step + ``ds``) sat.  The positions interpolated there (bilinear where all four
    neighbours hit, else the nearest lattice point's), −2 (march) where none is known.  A hint for
    :func:`_fused_rays`' ``cand``: a wrong cell costs a march, never a different hit (:func:`_cell_hit`)."""
    nl, ns = pos.shape[0], pos.shape[1]
    last = n - 2
    w_out = out.shape[1]
    # per column (the same for every line): the interpolation's column and weight, the nearest column
    col = np.empty(w_out, np.int64)
    fxs = np.empty(w_out)
    near = np.empty(w_out, np.int64)
    for c in range(w_out):
        x = c * step + ds  # c + ds exactly at step 1
        a = min(int(math.floor(x)), ns - 2)
        fx = x - a
        col[c] = a if (0 <= a and 0.0 <= fx <= 1.0) else -1
        fxs[c] = fx
        cn = int(math.floor(x + 0.5))
        near[c] = cn if 0 <= cn < ns else -1
    for r in range(out.shape[0]):
        y = r * step + dl
        b = min(int(math.floor(y)), nl - 2)  # the last line itself interpolates with weight 1
        fy = y - b
        rows = 0 <= b and 0.0 <= fy <= 1.0
        rn = int(math.floor(y + 0.5))
        rn_ok = 0 <= rn < nl
        for c in range(w_out):
            out[r, c] = -2
            u = math.nan
            w = math.nan
            a = col[c]
            if rows and a >= 0:
                u00, w00 = pos[b, a, 0], pos[b, a, 1]
                u01, w01 = pos[b, a + 1, 0], pos[b, a + 1, 1]
                u10, w10 = pos[b + 1, a, 0], pos[b + 1, a, 1]
                u11, w11 = pos[b + 1, a + 1, 0], pos[b + 1, a + 1, 1]
                if not (math.isnan(u00) or math.isnan(u01) or math.isnan(u10) or math.isnan(u11)):
                    fx = fxs[c]
                    g00 = (1.0 - fx) * (1.0 - fy)
                    g01 = fx * (1.0 - fy)
                    g10 = (1.0 - fx) * fy
                    g11 = fx * fy
                    u = g00 * u00 + g01 * u01 + g10 * u10 + g11 * u11
                    w = g00 * w00 + g01 * w01 + g10 * w10 + g11 * w11
            if math.isnan(u):  # an edge of the hits (or of the lattice): the nearest sub-ray's
                cn = near[c]
                if rn_ok and cn >= 0:
                    u = pos[rn, cn, 0]
                    w = pos[rn, cn, 1]
            if not (math.isnan(u) or math.isnan(w)):
                i = min(max(int(math.floor(u)), 0), last)
                j = min(max(int(math.floor(w)), 0), last)
                out[r, c] = i * (n - 1) + j


@numba.njit(cache=True, nogil=True)
def usable_cells(hint, ncells, out):
    """out[k] = hint[k] where it is a cell index of a grid of ``ncells`` cells, else −2 (march; never −1,
    the raster's "no terrain here", which only the raster of the very camera rendered can claim)."""
    for k in range(hint.shape[0]):
        h = hint[k]
        out[k] = h if 0 <= h < ncells else -2
