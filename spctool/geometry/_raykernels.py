"""Numba kernels behind :mod:`spctool.geometry.shape`: ray traversal and the primitive tests.

Nothing here is public API; :mod:`spctool.geometry.shape` wraps it.  The trees are built and packed by
:mod:`spctool.geometry._bvhkernels`; the traversal here reads their packed 4-wide layout (a node holds
up to four children's boxes side by side; a reference r ≥ 0 is a packed node, r < 0 a leaf with code
−r − 1 = (first primitive << 3) | count).  Two primitive kinds share it and one traversal kernel:

* ``KIND_PATCH`` — ICQ cells treated as bilinear patches and inverted with SPC's algebra
  (L15 §3.2.1, Eq. 3.27–3.35, with the errata 13–16 of ``spc-algorithms.md`` §11; the detailed
  GET_HEIGHTS recipe is ``spc-algorithms.md`` §2.2 "Bilinear-patch inversion in detail").
* ``KIND_TRIANGLE`` — triangles, Möller–Trumbore (two-sided, edges inclusive).

Patch cell index convention (``spc-formats.md`` §5): cell ``k = F·q² + J·q + I`` with the 0-based face
``F = 0…5`` (file face number F+1), ``I, J = 0…q−1``; its corners are the vertices
0 = (I, J), 1 = (I+1, J), 2 = (I, J+1), 3 = (I+1, J+1) of the flattened vertex array
``verts[F·(q+1)² + J·(q+1) + I]``.  The patch parameter ``u`` runs along I (corner 0 → 1) and ``v``
along J (corner 0 → 2).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

KIND_PATCH = 0
KIND_TRIANGLE = 1

STACK_SIZE = 256  # traversal stack per ray: ≤ 3·depth + 1 (patch quadtree < 40, SAH trees ≤ 217)
CHUNK = 256  # rays per parallel work item (scratch arrays are allocated once per chunk)
_HUGE = 1e30  # stands in for 1/0 in the slab test (keeps 0·inf and inf − inf out of it)


# ------------------------------------------------------------------------------------------------
# primitive tests
# ------------------------------------------------------------------------------------------------


@njit(cache=True)
def tilde_frame(dx, dy, dz):
    """Tilde frame of L15 Eq. 3.21 in body coordinates for a unit direction (dx, dy, dz).

    z̃ = d̂, ỹ = z̃ × b_x / |z̃ × b_x|, x̃ = ỹ × z̃ with b_x = (1, 0, 0), the body x axis.  When d̂ is
    (nearly) parallel to b_x the body y axis is used instead (L15 footnote 21: any right-handed
    orthonormal frame with z̃ = d̂ works; the root ι₀ does not depend on the choice).
    Returns the nine components (x̃, ỹ, z̃).
    """
    # z̃ × b_x = (0, dz, −dy)
    ny = dy * dy + dz * dz
    if ny > 1e-12:
        s = 1.0 / math.sqrt(ny)
        yx, yy, yz = 0.0, dz * s, -dy * s
    else:  # z̃ × b_y = (−dz, 0, dx)
        s = 1.0 / math.sqrt(dx * dx + dz * dz)
        yx, yy, yz = -dz * s, 0.0, dx * s
    # x̃ = ỹ × z̃ (unit: ỹ ⟂ z̃, both unit)
    xx = yy * dz - yz * dy
    xy = yz * dx - yx * dz
    xz = yx * dy - yy * dx
    return xx, xy, xz, yx, yy, yz, dx, dy, dz


@njit(cache=True)
def _project(verts, b, ox, oy, oz, fr):
    """Tilde-frame coordinates (x̃, ỹ, z̃) of vertex ``b`` relative to the ray origin (Eq. 3.22)."""
    px = verts[b, 0] - ox
    py = verts[b, 1] - oy
    pz = verts[b, 2] - oz
    return (px * fr[0] + py * fr[1] + pz * fr[2], px * fr[3] + py * fr[4] + pz * fr[5],
            px * fr[6] + py * fr[7] + pz * fr[8])


@njit(cache=True)
def _outside(a0, a1, a2, a3, eps):
    """True if the line of sight (x̃ = 0 or ỹ = 0) misses the patch extended to [−eps, 1+eps]²:
    the bilinear function with corner values a0…a3 has one strict sign at all four extended
    corners (the extended patch lies in their convex hull)."""
    e1 = -eps
    e2 = 1.0 + eps
    A1 = a1 - a0
    A2 = a2 - a0
    A3 = a0 - a1 - a2 + a3
    c00 = a0 + A1 * e1 + A2 * e1 + A3 * e1 * e1
    c10 = a0 + A1 * e2 + A2 * e1 + A3 * e2 * e1
    c01 = a0 + A1 * e1 + A2 * e2 + A3 * e1 * e2
    c11 = a0 + A1 * e2 + A2 * e2 + A3 * e2 * e2
    return (c00 > 0.0 and c10 > 0.0 and c01 > 0.0 and c11 > 0.0) or (
        c00 < 0.0 and c10 < 0.0 and c01 < 0.0 and c11 < 0.0)


@njit(cache=True)
def patch_solve(x0, y0, z0, x1, y1, z1, x2, y2, z2, x3, y3, z3, eps):
    """SPC bilinear-patch inversion (L15 §3.2.1 Eq. 3.27–3.35 with errata 13–16) from the tilde-frame
    corner coordinates in SPC's order 0 = (I,J), 1 = (I+1,J), 2 = (I,J+1), 3 = (I+1,J+1).

    Returns ``(ok, t, u, v)``: ``u`` = ι₀ (along I), ``v`` = γ₀ (along J), ``t`` = the interpolated
    z̃ (Eq. 3.34), the distance along the ray.  A sign screen on the extended corners first skips
    patches whose projection cannot contain the line of sight (a pure cull, like L15's Eq. 3.25–3.26
    screens: it never removes a solution the algebra below would accept, up to rounding at the
    patch boundary).
    """
    if _outside(x0, x1, x2, x3, eps) or _outside(y0, y1, y2, y3, eps):
        return False, 0.0, 0.0, 0.0
    # bilinear coefficients (Eq. 3.29, 3.30 in SPC's corner order, spc-algorithms.md §2.2)
    X0 = x0
    X1 = x1 - x0
    X2 = x2 - x0
    X3 = x0 - x1 - x2 + x3
    Y0 = y0
    Y1 = y1 - y0
    Y2 = y2 - y0
    Y3 = y0 - y1 - y2 + y3
    A = X1 * Y3 - X3 * Y1  # Eq. 3.33
    B = X1 * Y2 - X2 * Y1 + X0 * Y3 - X3 * Y0
    C = X0 * Y2 - X2 * Y0
    D = B * B - 4.0 * A * C
    if not D > 0.0:  # erratum 13: SPC proceeds only if B² > 4AC strictly
        return False, 0.0, 0.0, 0.0
    # erratum 13/14: SPC's root (√(1−4AC/B²) − 1)·B/(2A) and its small-|A| series −C/B − AC²/B³ are
    # the stable root C/q, q = −(B + sign(B)√D)/2, evaluated without a branch.
    sq = math.sqrt(D)
    if B >= 0.0:
        qd = -0.5 * (B + sq)
    else:
        qd = -0.5 * (B - sq)
    u = C / qd
    if u < -eps or u > 1.0 + eps:  # erratum 16: accept [−EPS, 1+EPS]
        return False, 0.0, 0.0, 0.0
    # erratum 15: γ from the equation with the larger |denominator|
    dxn = X2 + X3 * u
    dyn = Y2 + Y3 * u
    if abs(dxn) > abs(dyn):
        v = -(X0 + X1 * u) / dxn
    else:
        if dyn == 0.0:
            return False, 0.0, 0.0, 0.0
        v = -(Y0 + Y1 * u) / dyn
    if v < -eps or v > 1.0 + eps:
        return False, 0.0, 0.0, 0.0
    t = z0 + (z1 - z0) * u + (z2 - z0) * v + (z0 - z1 - z2 + z3) * u * v  # Eq. 3.34, 3.35
    return True, t, u, v


@njit(cache=True)
def cell_base(k, q):
    """Flattened vertex index of corner 0 = (I, J) of cell ``k``."""
    qq = q * q
    f = k // qq
    r = k - f * qq
    j = r // q
    i = r - j * q
    q1 = q + 1
    return f * q1 * q1 + j * q1 + i


@njit(cache=True)
def patch_hit(verts, k, q, ox, oy, oz, fr, eps):
    """:func:`patch_solve` for cell ``k``; ``fr`` is the 9-tuple from :func:`tilde_frame`."""
    b = cell_base(k, q)
    q1 = q + 1
    x0, y0, z0 = _project(verts, b, ox, oy, oz, fr)
    x1, y1, z1 = _project(verts, b + 1, ox, oy, oz, fr)
    x2, y2, z2 = _project(verts, b + q1, ox, oy, oz, fr)
    x3, y3, z3 = _project(verts, b + q1 + 1, ox, oy, oz, fr)
    return patch_solve(x0, y0, z0, x1, y1, z1, x2, y2, z2, x3, y3, z3, eps)


@njit(cache=True)
def triangle_hit(verts, faces, k, ox, oy, oz, dx, dy, dz):
    """Möller–Trumbore, two-sided, edges inclusive.  Returns ``(ok, t, u, v)`` (barycentrics of
    vertices 1 and 2)."""
    a = faces[k, 0]
    b = faces[k, 1]
    c = faces[k, 2]
    ax = verts[a, 0]
    ay = verts[a, 1]
    az = verts[a, 2]
    e1x = verts[b, 0] - ax
    e1y = verts[b, 1] - ay
    e1z = verts[b, 2] - az
    e2x = verts[c, 0] - ax
    e2y = verts[c, 1] - ay
    e2z = verts[c, 2] - az
    px = dy * e2z - dz * e2y
    py = dz * e2x - dx * e2z
    pz = dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if det == 0.0:
        return False, 0.0, 0.0, 0.0
    inv = 1.0 / det
    tx = ox - ax
    ty = oy - ay
    tz = oz - az
    u = (tx * px + ty * py + tz * pz) * inv
    if u < 0.0 or u > 1.0:
        return False, 0.0, 0.0, 0.0
    qx = ty * e1z - tz * e1y
    qy = tz * e1x - tx * e1z
    qz = tx * e1y - ty * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    if v < 0.0 or u + v > 1.0:
        return False, 0.0, 0.0, 0.0
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    return True, t, u, v


@njit(cache=True)
def _slab(b0, b1, b2, b3, b4, b5, ox, oy, oz, ix, iy, iz, t0, t1):
    """Slab test of box (b0, b1, b2)–(b3, b4, b5): entry distance clipped to [t0, t1], or +inf."""
    a = (b0 - ox) * ix
    b = (b3 - ox) * ix
    lo = min(a, b)
    hi = max(a, b)
    a = (b1 - oy) * iy
    b = (b4 - oy) * iy
    lo = max(lo, min(a, b))
    hi = min(hi, max(a, b))
    a = (b2 - oz) * iz
    b = (b5 - oz) * iz
    lo = max(lo, min(a, b))
    hi = min(hi, max(a, b))
    lo = max(lo, t0)
    hi = min(hi, t1)
    if lo <= hi:
        return lo
    return np.inf


@njit(cache=True)
def _inv(d):
    if d == 0.0:
        return _HUGE
    return 1.0 / d


# ------------------------------------------------------------------------------------------------
# traversal
# ------------------------------------------------------------------------------------------------


@njit(cache=True)
def _trace_one(kind, any_hit, ox, oy, oz, dx, dy, dz, t0, t1, root_box, nb, nc, prims, verts, faces, q,
               eps, stack_r, stack_t, kid_r, kid_t, kid_lo, kid_hi, pxs, pys, pzs):
    """Trace one ray with unit direction.  Returns ``(index, t, u, v)``; index −1 = no hit."""
    ix = _inv(dx)
    iy = _inv(dy)
    iz = _inv(dz)
    # slab planes as t = plane·inv − origin·inv; near/far plane rows chosen once by direction sign
    oix = ox * ix
    oiy = oy * iy
    oiz = oz * iz
    nx = 0 if ix >= 0.0 else 3
    ny = 1 if iy >= 0.0 else 4
    nz = 2 if iz >= 0.0 else 5
    fx = 3 - nx
    fy = 5 - ny
    fz = 7 - nz
    if kind == KIND_PATCH:
        fr = tilde_frame(dx, dy, dz)
    else:
        fr = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    best_t = t1
    best_k = -1
    best_u = 0.0
    best_v = 0.0
    te = _slab(root_box[0], root_box[1], root_box[2], root_box[3], root_box[4], root_box[5], ox, oy, oz,
               ix, iy, iz, t0, t1)
    if te == np.inf:
        return best_k, best_t, best_u, best_v
    stack_r[0] = 0
    stack_t[0] = te
    sp = 1
    while sp > 0:
        sp -= 1
        ref = stack_r[sp]
        if stack_t[sp] > best_t:
            continue
        if ref < 0:
            code = -ref - 1
            s = code >> 3
            c = code & 7
            if kind == KIND_PATCH and c == 4:
                # a 2×2 block of cells: project its 3×3 vertices once (bit-identical to patch_hit)
                b = cell_base(prims[s], q)
                q1 = q + 1
                for jj in range(3):
                    for ii in range(3):
                        w = jj * 3 + ii
                        pxs[w], pys[w], pzs[w] = _project(verts, b + jj * q1 + ii, ox, oy, oz, fr)
                for m in range(4):
                    w = (m >> 1) * 3 + (m & 1)
                    ok, t, u, v = patch_solve(pxs[w], pys[w], pzs[w], pxs[w + 1], pys[w + 1], pzs[w + 1],
                                              pxs[w + 3], pys[w + 3], pzs[w + 3], pxs[w + 4], pys[w + 4],
                                              pzs[w + 4], eps)
                    k = prims[s + m]
                    if ok and t >= t0 and (t < best_t or (t == best_t and (best_k < 0 or k < best_k))):
                        best_t = t
                        best_k = k
                        best_u = u
                        best_v = v
                        if any_hit:
                            return best_k, best_t, best_u, best_v
                continue
            for m in range(s, s + c):
                k = prims[m]
                if kind == KIND_PATCH:
                    ok, t, u, v = patch_hit(verts, k, q, ox, oy, oz, fr, eps)
                else:
                    ok, t, u, v = triangle_hit(verts, faces, k, ox, oy, oz, dx, dy, dz)
                if ok and t >= t0 and (t < best_t or (t == best_t and (best_k < 0 or k < best_k))):
                    best_t = t
                    best_k = k
                    best_u = u
                    best_v = v
                    if any_hit:
                        return best_k, best_t, best_u, best_v
            continue
        # the four slab tests side by side (branch-free, so LLVM can vectorise them)
        for j in range(4):
            kid_lo[j] = max(max(nb[ref, nx, j] * ix - oix, nb[ref, ny, j] * iy - oiy),
                            max(nb[ref, nz, j] * iz - oiz, t0))
            kid_hi[j] = min(min(nb[ref, fx, j] * ix - oix, nb[ref, fy, j] * iy - oiy),
                            min(nb[ref, fz, j] * iz - oiz, best_t))
        nk = 0
        for j in range(nc[ref, 0]):
            te = kid_lo[j]
            if te <= kid_hi[j]:
                # insertion sort, farthest first (the nearest is pushed last, popped first)
                p = nk
                while p > 0 and kid_t[p - 1] < te:
                    kid_t[p] = kid_t[p - 1]
                    kid_r[p] = kid_r[p - 1]
                    p -= 1
                kid_t[p] = te
                kid_r[p] = nc[ref, 1 + j]
                nk += 1
        for p in range(nk):
            stack_r[sp] = kid_r[p]
            stack_t[sp] = kid_t[p]
            sp += 1
    return best_k, best_t, best_u, best_v


@njit(parallel=True, cache=True)
def trace(kind, any_hit, order, origins, dirs, tmin, tmax, root_box, nb, nc, prims, verts, faces, q, eps,
          out_k, out_t, out_u, out_v, out_p):
    """Trace all rays (first hit, or any hit when ``any_hit``) in parallel chunks.

    ``origins`` (n or 1, 3), ``dirs`` (n or 1, 3), ``tmin``/``tmax`` (n or 1,) — a length-1 input is
    used for every ray; n is the length of the outputs.  ``dirs`` need not be unit; a zero or
    non-finite direction gives no hit.  ``tmin``/``tmax`` are distance limits along the unit
    direction.  Outputs: cell/face index (−1 = none), t
    (inf if none), patch/barycentric parameters and the hit point (NaN if none).  Rays are
    processed in the sequence ``order`` (a permutation from :func:`ray_order`, for cache coherence);
    results are written at the rays' own positions.
    """
    n = out_k.shape[0]
    no = origins.shape[0] > 1
    nd_ = dirs.shape[0] > 1
    n0 = tmin.shape[0] > 1
    n1 = tmax.shape[0] > 1
    nchunks = (n + CHUNK - 1) // CHUNK
    for ci in prange(nchunks):
        stack_r = np.empty(STACK_SIZE, np.int64)
        stack_t = np.empty(STACK_SIZE, np.float64)
        kid_r = np.empty(4, np.int64)
        kid_t = np.empty(4, np.float64)
        kid_lo = np.empty(4, np.float64)
        kid_hi = np.empty(4, np.float64)
        pxs = np.empty(9, np.float64)
        pys = np.empty(9, np.float64)
        pzs = np.empty(9, np.float64)
        ray = np.empty((CHUNK, 8), np.float64)
        res_k = np.empty(CHUNK, np.int64)
        res = np.empty((CHUNK, 6), np.float64)
        lo = ci * CHUNK
        hi = min(n, lo + CHUNK)
        # gather the chunk's rays (independent loads: the memory system overlaps the misses)
        for m in range(hi - lo):
            r = order[lo + m]
            ro = r if no else 0
            rd = r if nd_ else 0
            ray[m, 0] = origins[ro, 0]
            ray[m, 1] = origins[ro, 1]
            ray[m, 2] = origins[ro, 2]
            ray[m, 3] = dirs[rd, 0]
            ray[m, 4] = dirs[rd, 1]
            ray[m, 5] = dirs[rd, 2]
            ray[m, 6] = tmin[r if n0 else 0]
            ray[m, 7] = tmax[r if n1 else 0]
        for m in range(hi - lo):
            ox = ray[m, 0]
            oy = ray[m, 1]
            oz = ray[m, 2]
            dx = ray[m, 3]
            dy = ray[m, 4]
            dz = ray[m, 5]
            t0 = ray[m, 6]
            t1 = ray[m, 7]
            nd = math.sqrt(dx * dx + dy * dy + dz * dz)
            k = -1
            t = np.inf
            u = np.nan
            v = np.nan
            if nd > 0.0 and nd < np.inf and math.isfinite(ox + oy + oz) and t0 <= t1:
                dx /= nd
                dy /= nd
                dz /= nd
                k, t, u, v = _trace_one(kind, any_hit, ox, oy, oz, dx, dy, dz, t0, t1, root_box,
                                        nb, nc, prims, verts, faces, q, eps, stack_r, stack_t, kid_r,
                                        kid_t, kid_lo, kid_hi, pxs, pys, pzs)
            res_k[m] = k
            if k < 0:
                res[m, 0] = np.inf
                for a in range(1, 6):
                    res[m, a] = np.nan
                continue
            res[m, 0] = t
            res[m, 1] = u
            res[m, 2] = v
            if kind == KIND_PATCH:
                b = cell_base(k, q)
                q1 = q + 1
                w0 = (1.0 - u) * (1.0 - v)
                w1 = u * (1.0 - v)
                w2 = (1.0 - u) * v
                w3 = u * v
                for a in range(3):
                    res[m, 3 + a] = (w0 * verts[b, a] + w1 * verts[b + 1, a] + w2 * verts[b + q1, a]
                                     + w3 * verts[b + q1 + 1, a])
            else:
                w0 = 1.0 - u - v
                for a in range(3):
                    res[m, 3 + a] = (w0 * verts[faces[k, 0], a] + u * verts[faces[k, 1], a]
                                     + v * verts[faces[k, 2], a])
        # scatter the results to the rays' own positions
        for m in range(hi - lo):
            r = order[lo + m]
            out_k[r] = res_k[m]
            out_t[r] = res[m, 0]
            out_u[r] = res[m, 1]
            out_v[r] = res[m, 2]
            out_p[r, 0] = res[m, 3]
            out_p[r, 1] = res[m, 4]
            out_p[r, 2] = res[m, 5]


@njit(cache=True)
def _spread2(x):
    """Interleave the low 10 bits of x with zeros (bit b → bit 2b)."""
    x &= 0x3FF
    x = (x | (x << 8)) & 0x00FF00FF
    x = (x | (x << 4)) & 0x0F0F0F0F
    x = (x | (x << 2)) & 0x33333333
    x = (x | (x << 1)) & 0x55555555
    return x


@njit(cache=True)
def _spread3(x):
    """Spread the low 4 bits of x to every third bit."""
    r = 0
    for b in range(4):
        r |= ((x >> b) & 1) << (3 * b)
    return r


@njit(cache=True)
def _octa(dx, dy, dz):
    """Octahedral map of a direction to [−1, 1]² ((0, 0) for a zero or non-finite direction)."""
    s = abs(dx) + abs(dy) + abs(dz)
    if not (s > 0.0 and s < np.inf):
        return 0.0, 0.0
    a = dx / s
    b = dy / s
    if dz < 0.0:
        a, b = (1.0 - abs(b)) * (1.0 if a >= 0 else -1.0), (1.0 - abs(a)) * (1.0 if b >= 0 else -1.0)
    return a, b


@njit(cache=True)
def ray_order(n, origins, dirs):
    """A permutation of the n rays that makes neighbours in it spatially coherent.

    Key (32 bits) = Morton code of the octahedral direction, quantised to 1024 × 1024 over the span of
    the rays' own directions (20 bits), then the Morton code of the origin quantised to 16³ over the
    origins' bounding box (12 bits).  Two 16-bit LSD counting-sort passes, O(n).  Rays from one
    camera therefore come in direction order, parallel (shadow) rays in origin order.  ``origins``
    and ``dirs`` may have one row (shared by every ray) or n.
    """
    no = origins.shape[0] > 1
    nd = dirs.shape[0] > 1
    amin = np.inf
    amax = -np.inf
    bmin = np.inf
    bmax = -np.inf
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for r in range(n):
        rd = r if nd else 0
        a, b = _octa(dirs[rd, 0], dirs[rd, 1], dirs[rd, 2])
        amin = min(amin, a)
        amax = max(amax, a)
        bmin = min(bmin, b)
        bmax = max(bmax, b)
        ro = r if no else 0
        for w in range(3):
            x = origins[ro, w]
            if x < lo[w]:
                lo[w] = x
            if x > hi[w]:
                hi[w] = x
    sa = 1023.999 / (amax - amin) if amax > amin else 0.0
    sb = 1023.999 / (bmax - bmin) if bmax > bmin else 0.0
    so = np.zeros(3)
    for w in range(3):
        if hi[w] > lo[w] and np.isfinite(hi[w] - lo[w]):
            so[w] = 15.999 / (hi[w] - lo[w])
    key = np.empty(n, np.int64)
    for r in range(n):
        rd = r if nd else 0
        a, b = _octa(dirs[rd, 0], dirs[rd, 1], dirs[rd, 2])
        ia = min(max(int((a - amin) * sa), 0), 1023) if sa > 0.0 else 0
        ib = min(max(int((b - bmin) * sb), 0), 1023) if sb > 0.0 else 0
        ro = r if no else 0
        code_o = 0
        for w in range(3):
            x = origins[ro, w]
            ix = 0
            if so[w] > 0.0 and np.isfinite(x):
                ix = min(max(int((x - lo[w]) * so[w]), 0), 15)
            code_o |= _spread3(ix) << w
        key[r] = ((_spread2(ia) | (_spread2(ib) << 1)) << 12) | code_o
    order = np.empty(n, np.int64)
    tmp = np.empty(n, np.int64)
    cnt = np.zeros(65537, np.int64)
    for r in range(n):
        cnt[(key[r] & 0xFFFF) + 1] += 1
    for b in range(65536):
        cnt[b + 1] += cnt[b]
    for r in range(n):
        kk = key[r] & 0xFFFF
        tmp[cnt[kk]] = r
        cnt[kk] += 1
    cnt[:] = 0
    for r in range(n):
        cnt[(key[tmp[r]] >> 16) + 1] += 1
    for b in range(65536):
        cnt[b + 1] += cnt[b]
    for r in range(n):
        kk = key[tmp[r]] >> 16
        order[cnt[kk]] = tmp[r]
        cnt[kk] += 1
    return order


# ------------------------------------------------------------------------------------------------
# brute force (every primitive, same primitive tests) — used by tests and as a fallback
# ------------------------------------------------------------------------------------------------


@njit(cache=True)
def trace_brute(kind, origins, dirs, tmin, tmax, nprim, verts, faces, q, eps, out_k, out_t, out_u,
                out_v):
    """Nearest hit over every primitive for each ray (ties → smaller index)."""
    n = out_k.shape[0]
    for r in range(n):
        z = 0
        ro = r if origins.shape[0] > 1 else z
        rd = r if dirs.shape[0] > 1 else z
        t0 = tmin[r if tmin.shape[0] > 1 else z]
        t1 = tmax[r if tmax.shape[0] > 1 else z]
        ox = origins[ro, 0]
        oy = origins[ro, 1]
        oz = origins[ro, 2]
        dx = dirs[rd, 0]
        dy = dirs[rd, 1]
        dz = dirs[rd, 2]
        nd = math.sqrt(dx * dx + dy * dy + dz * dz)
        out_k[r] = -1
        out_t[r] = np.inf
        out_u[r] = np.nan
        out_v[r] = np.nan
        if not (nd > 0.0 and nd < np.inf):
            continue
        dx /= nd
        dy /= nd
        dz /= nd
        fr = tilde_frame(dx, dy, dz)
        best_t = t1
        for k in range(nprim):
            if kind == KIND_PATCH:
                ok, t, u, v = patch_hit(verts, k, q, ox, oy, oz, fr, eps)
            else:
                ok, t, u, v = triangle_hit(verts, faces, k, ox, oy, oz, dx, dy, dz)
            if ok and t >= t0 and (t < best_t or (t == best_t and out_k[r] < 0)):
                best_t = t
                out_k[r] = k
                out_t[r] = t
                out_u[r] = u
                out_v[r] = v


# ------------------------------------------------------------------------------------------------
# single-precision tracers (Embree): ray preparation and double-precision verification
# ------------------------------------------------------------------------------------------------


@njit(cache=True)
def _clip_one(ox, oy, oz, dx, dy, dz, t0, t1, box):
    """Unit direction and [t_s, t_e] = [t0, t1] ∩ slab interval of ``box`` (t_s > t_e: no overlap;
    nd = 0 for an unusable ray)."""
    nd = math.sqrt(dx * dx + dy * dy + dz * dz)
    if not (nd > 0.0 and nd < np.inf and math.isfinite(ox + oy + oz) and t0 <= t1):
        return 0.0, 0.0, 0.0, 0.0, np.inf, -np.inf
    dx /= nd
    dy /= nd
    dz /= nd
    ts = t0
    te = t1
    for w in range(3):
        o = ox if w == 0 else (oy if w == 1 else oz)
        d = dx if w == 0 else (dy if w == 1 else dz)
        if d == 0.0:
            if o < box[w] or o > box[3 + w]:
                te = -np.inf  # parallel to the slab and outside it
            continue
        a = (box[w] - o) / d
        b = (box[3 + w] - o) / d
        ts = max(ts, min(a, b))
        te = min(te, max(a, b))
    return nd, dx, dy, dz, ts, te


@njit(cache=True, parallel=True)
def clip_rays(n, origins, dirs, tmin, tmax, box, slack, ok, org32, dir32, span32):
    """Prepare rays for a single-precision tracer: clip each ray to ``box`` in double precision.

    A ray's search interval is [t_s, t_e] = [tmin, tmax] ∩ (its slab interval through ``box``),
    computed along the unit direction.  The tracer's ray (``org32``, unit ``dir32``, length
    ``span32``; computed in float64, cast by the caller) starts ``slack`` before t_s and runs
    t_e − t_s + 2·slack.  Its origin thus lies on the box, so single precision works at the scale of
    the model (~1e-7 of its size) instead of that of a far camera (~1e-7 of 1000 km, which Embree's
    float32 intersection arithmetic turned into wrong triangles up to 56 m off on the q = 32 Bennu
    model), and a hit that rounding moves by less than ``slack`` across either end of [t_s, t_e] is
    still reported.
    ``ok`` is False for rays that cannot hit (zero/non-finite direction, non-finite origin,
    tmin > tmax, or missing the box); their other outputs are unset.  ``origins``/``dirs``/
    ``tmin``/``tmax`` have n or 1 rows, as in :func:`trace`.
    """
    # row strides: 1 for per-ray inputs, 0 for a single row shared by every ray
    so = 1 if origins.shape[0] > 1 else 0
    sd = 1 if dirs.shape[0] > 1 else 0
    s0 = 1 if tmin.shape[0] > 1 else 0
    s1 = 1 if tmax.shape[0] > 1 else 0
    for r in prange(n):
        ox = origins[r * so, 0]
        oy = origins[r * so, 1]
        oz = origins[r * so, 2]
        nd, dx, dy, dz, ts, te = _clip_one(ox, oy, oz, dirs[r * sd, 0], dirs[r * sd, 1], dirs[r * sd, 2],
                                           tmin[r * s0], tmax[r * s1], box)
        ok[r] = nd > 0.0 and ts <= te
        if ok[r]:
            s = ts - slack
            org32[r, 0] = ox + s * dx
            org32[r, 1] = oy + s * dy
            org32[r, 2] = oz + s * dz
            dir32[r, 0] = dx
            dir32[r, 1] = dy
            dir32[r, 2] = dz
            span32[r] = (te - ts) + 2.0 * slack


@njit(cache=True, parallel=True)
def verify_triangle_hits(idx, prim, origins, dirs, tmin, tmax, slack, verts, faces, out_k, out_t, out_u,
                         out_v, redo):
    """Check a single-precision tracer's closest hits in double precision.

    For each ray ``r = idx[j]`` the tracer reported triangle ``prim[j]`` (−1: none).  That triangle
    is re-intersected with :func:`triangle_hit`, the test the numba traversal uses:

    * inside the triangle with tmin ≤ t < tmax → the hit (t, u, v bit-identical to the numba
      backend's for that triangle);
    * inside with t ≥ tmax + ``slack``, or no triangle reported → no hit;
    * anything else — t < tmin (a self-hit: the tracer's rounding put the ray's own surface inside
      its range, so a farther hit may be the true answer), t within ``slack`` past tmax (a
      neighbouring triangle may be hit just before tmax), the ray outside the triangle in double
      precision, or parallel to it — sets ``redo[r]``: that ray must be traced exactly.

    Outputs are written at ray positions ``r`` (misses: −1, inf, NaN, NaN).
    """
    so = 1 if origins.shape[0] > 1 else 0
    sd = 1 if dirs.shape[0] > 1 else 0
    s0 = 1 if tmin.shape[0] > 1 else 0
    s1 = 1 if tmax.shape[0] > 1 else 0
    for j in prange(idx.shape[0]):
        r = idx[j]
        out_k[r] = -1
        out_t[r] = np.inf
        out_u[r] = np.nan
        out_v[r] = np.nan
        redo[r] = False
        k = prim[j]
        if k < 0:
            continue
        dx = dirs[r * sd, 0]
        dy = dirs[r * sd, 1]
        dz = dirs[r * sd, 2]
        nd = math.sqrt(dx * dx + dy * dy + dz * dz)
        ok, t, u, v = triangle_hit(verts, faces, k, origins[r * so, 0], origins[r * so, 1],
                                   origins[r * so, 2], dx / nd, dy / nd, dz / nd)
        if ok and t >= tmin[r * s0]:
            t1 = tmax[r * s1]
            if t < t1:
                out_k[r] = k
                out_t[r] = t
                out_u[r] = u
                out_v[r] = v
                continue
            if t - t1 > slack:
                continue
        redo[r] = True


# ------------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------------


@njit(cache=True)
def farthest_pair(points):
    """Exact maximum pairwise distance of ``points`` (pruned all-pairs search).

    Points are sorted by distance r from their centroid, descending; a pair (i, j) cannot exceed
    r_i + r_j, so the scan over i stops once r_i + r_0 ≤ best, and the inner scan once
    r_i + r_j ≤ best.  Worst case O(n²), typically near-linear for compact bodies.
    """
    n = points.shape[0]
    if n < 2:
        return 0.0
    cx = 0.0
    cy = 0.0
    cz = 0.0
    for i in range(n):
        cx += points[i, 0]
        cy += points[i, 1]
        cz += points[i, 2]
    cx /= n
    cy /= n
    cz /= n
    r = np.empty(n)
    for i in range(n):
        r[i] = math.sqrt((points[i, 0] - cx) ** 2 + (points[i, 1] - cy) ** 2 + (points[i, 2] - cz) ** 2)
    order = np.argsort(-r)
    best2 = 0.0
    best = 0.0
    for a in range(n):
        i = order[a]
        if r[i] + r[order[0]] <= best:
            break
        for b in range(a + 1, n):
            j = order[b]
            if r[i] + r[j] <= best:
                break
            d2 = ((points[i, 0] - points[j, 0]) ** 2 + (points[i, 1] - points[j, 1]) ** 2
                  + (points[i, 2] - points[j, 2]) ** 2)
            if d2 > best2:
                best2 = d2
                best = math.sqrt(d2)
    return best


@njit(cache=True, parallel=True)
def directional_extremes(points, dirs, n_chunks):
    """Per direction: (min, max) of points·dir and the indices where they occur.

    Points are split into ``n_chunks`` blocks scanned in parallel (directions innermost, so the
    direction table stays in cache); block results are then reduced.
    """
    n = points.shape[0]
    k = dirs.shape[0]
    lo = np.full((n_chunks, k), np.inf)
    hi = np.full((n_chunks, k), -np.inf)
    ilo = np.zeros((n_chunks, k), np.int64)
    ihi = np.zeros((n_chunks, k), np.int64)
    size = (n + n_chunks - 1) // n_chunks
    for c in prange(n_chunks):
        for i in range(c * size, min(n, (c + 1) * size)):
            x = points[i, 0]
            y = points[i, 1]
            z = points[i, 2]
            for d in range(k):
                v = x * dirs[d, 0] + y * dirs[d, 1] + z * dirs[d, 2]
                if v < lo[c, d]:
                    lo[c, d] = v
                    ilo[c, d] = i
                if v > hi[c, d]:
                    hi[c, d] = v
                    ihi[c, d] = i
    out_lo = np.empty(k)
    out_hi = np.empty(k)
    out_ilo = np.empty(k, np.int64)
    out_ihi = np.empty(k, np.int64)
    for d in range(k):
        out_lo[d] = lo[0, d]
        out_hi[d] = hi[0, d]
        out_ilo[d] = ilo[0, d]
        out_ihi[d] = ihi[0, d]
        for c in range(1, n_chunks):
            if lo[c, d] < out_lo[d]:
                out_lo[d] = lo[c, d]
                out_ilo[d] = ilo[c, d]
            if hi[c, d] > out_hi[d]:
                out_hi[d] = hi[c, d]
                out_ihi[d] = ihi[c, d]
    return out_lo, out_hi, out_ilo, out_ihi
