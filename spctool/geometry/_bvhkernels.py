"""Numba kernels behind :mod:`spctool.geometry.shape`: the bounding-volume hierarchies its rays traverse.

Nothing here is public API; :mod:`spctool.geometry.shape` wraps it, and the traversal that reads the
packed trees is :mod:`spctool.geometry._raykernels`.  Both primitive kinds (ICQ cells as bilinear
patches, ``spc-formats.md`` §5 and L15 §3.2.1; triangles) share one tree layout.

Builders produce an n-ary tree (children of a node contiguous):

* ``bounds[n] = (xlo, ylo, zlo, xhi, yhi, zhi)``;
* ``leaf[n] == 0``: children are nodes ``first[n] … first[n] + count[n] − 1``;
* ``leaf[n] == 1``: primitives are ``prims[first[n] … first[n] + count[n] − 1]``;
* every child has a larger node index than its parent (node 0 is the root), so bounds can be
  accumulated in one reverse sweep.

* :func:`build_patch_tree` — O(n) over the ICQ grid: six face quadtrees under one root, leaf boxes
  bounding each patch with its parameter margin (so the tree never culls a hit the brute-force search
  accepts);
* :func:`build_sah_tree` — a binned surface-area-heuristic binary tree over primitive boxes (triangle
  meshes);
* :func:`pack4` — either tree as the 4-wide packed layout the traversal reads (each node holds its
  children's boxes side by side, so a visit touches two small contiguous records).
"""

from __future__ import annotations

import numpy as np
from numba import njit

MAX_SAH_DEPTH = 48  # below this depth SAH ranges are halved by index, so binary depth ≤ 48 + log2(m)


@njit(cache=True)
def pack4(bounds, first, count, leaf):
    """Collapse a BVH (n-ary, ≤ 4 children, or binary) into a packed 4-wide hierarchy.

    Packed node p: ``nc[p, 0]`` = number of slots (1…4), ``nc[p, 1 + j]`` = reference of slot j,
    ``nb[p, :, j]`` = box of slot j (xlo, ylo, zlo, xhi, yhi, zhi).  A reference r ≥ 0 is a packed
    node; r < 0 is a leaf with code −r − 1 = (first primitive << 3) | count.  Binary nodes are widened
    by repeatedly opening the slot with the largest surface area.  Returns (root_box, nb, nc).
    """
    m = 1  # packed nodes ≤ internal source nodes (+1 when the root is a leaf)
    for n in range(bounds.shape[0]):
        if not leaf[n]:
            m += 1
    nb = np.empty((m, 6, 4), np.float64)
    nc = np.zeros((m, 5), np.int32)
    src = np.empty(m, np.int64)
    slots = np.empty(8, np.int64)
    root_box = bounds[0].copy()
    npk = 1
    src[0] = 0
    p = 0
    while p < npk:
        n = src[p]
        ns = 0
        if leaf[n]:  # only possible for the root: one slot holding the root leaf
            slots[0] = n
            ns = 1
        else:
            for c in range(first[n], first[n] + count[n]):
                slots[ns] = c
                ns += 1
        while ns < 4:
            best = -1
            best_a = -1.0
            for j in range(ns):
                c = slots[j]
                if leaf[c] or ns - 1 + count[c] > 4:
                    continue
                ex = bounds[c, 3] - bounds[c, 0]
                ey = bounds[c, 4] - bounds[c, 1]
                ez = bounds[c, 5] - bounds[c, 2]
                a = ex * ey + ey * ez + ez * ex
                if a > best_a:
                    best_a = a
                    best = j
            if best < 0:
                break
            c = slots[best]
            slots[best] = slots[ns - 1]
            ns -= 1
            for g in range(first[c], first[c] + count[c]):
                slots[ns] = g
                ns += 1
        nc[p, 0] = ns
        for j in range(ns):
            c = slots[j]
            for w in range(6):
                nb[p, w, j] = bounds[c, w]
            if leaf[c]:
                nc[p, 1 + j] = -((first[c] << 3) | count[c]) - 1
            else:
                src[npk] = c
                nc[p, 1 + j] = npk
                npk += 1
        for j in range(ns, 4):
            for w in range(6):
                nb[p, w, j] = 0.0
            nc[p, 1 + j] = 0
        p += 1
    return root_box, nb[:npk].copy(), nc[:npk].copy()


@njit(cache=True, inline="always")
def _halves(a0, a1, lo, hi):
    """Split the index range [a0, a1) at its midpoint into lo[k] … hi[k] (two parts; one when it holds
    a single index); returns the number of parts."""
    if a1 - a0 > 1:
        am = a0 + (a1 - a0) // 2
        lo[0] = a0
        hi[0] = am
        lo[1] = am
        hi[1] = a1
        return 2
    lo[0] = a0
    hi[0] = a1
    return 1


@njit(cache=True)
def build_patch_tree(verts, q, leaf_side, eps, pad):
    """O(n) BVH over the ICQ grid: six face quadtrees under one root.

    Root → two nodes of three faces each → one quadtree per face.  Each face is split recursively at
    the midpoints of its I and J ranges until a block is at most
    ``leaf_side × leaf_side`` cells; a leaf holds the cells of its block.  Leaf boxes bound every
    patch *including its [−eps, 1+eps] parameter extension* (the bilinear surface over the
    extended square lies in the convex hull of its four extended corners), padded by ``pad``; so the
    tree never culls a hit that the brute-force search over all cells would accept.
    """
    ncell = 6 * q * q
    max_nodes = 2 * ncell + 8
    first = np.zeros(max_nodes, np.int32)
    count = np.zeros(max_nodes, np.int32)
    leaf = np.zeros(max_nodes, np.uint8)
    rf = np.zeros(max_nodes, np.int32)
    ri0 = np.zeros(max_nodes, np.int32)
    ri1 = np.zeros(max_nodes, np.int32)
    rj0 = np.zeros(max_nodes, np.int32)
    rj1 = np.zeros(max_nodes, np.int32)
    prims = np.empty(ncell, np.int32)
    stack = np.empty(4096, np.int32)
    # root → two groups of three faces → six face quadtrees (so no node has more than 4 children)
    first[0] = 1
    count[0] = 2
    first[1] = 3
    count[1] = 3
    first[2] = 6
    count[2] = 3
    nn = 9
    sp = 0
    for f in range(5, -1, -1):
        n = f + 3
        rf[n] = f
        ri0[n] = 0
        ri1[n] = q
        rj0[n] = 0
        rj1[n] = q
        stack[sp] = n
        sp += 1
    npr = 0
    i_lo = np.empty(2, np.int32)
    i_hi = np.empty(2, np.int32)
    j_lo = np.empty(2, np.int32)
    j_hi = np.empty(2, np.int32)
    while sp > 0:
        sp -= 1
        n = stack[sp]
        f = rf[n]
        i0 = ri0[n]
        i1 = ri1[n]
        j0 = rj0[n]
        j1 = rj1[n]
        ni = i1 - i0
        nj = j1 - j0
        if ni <= leaf_side and nj <= leaf_side:
            leaf[n] = 1
            first[n] = npr
            count[n] = ni * nj
            for j in range(j0, j1):
                for i in range(i0, i1):
                    prims[npr] = f * q * q + j * q + i
                    npr += 1
            continue
        nsi = _halves(i0, i1, i_lo, i_hi)
        nsj = _halves(j0, j1, j_lo, j_hi)
        first[n] = nn
        count[n] = nsi * nsj
        c = nn
        for a in range(nsj):
            for b in range(nsi):
                rf[c] = f
                ri0[c] = i_lo[b]
                ri1[c] = i_hi[b]
                rj0[c] = j_lo[a]
                rj1[c] = j_hi[a]
                c += 1
        for c2 in range(c - 1, nn - 1, -1):
            stack[sp] = c2
            sp += 1
        nn = c
    bounds = np.empty((nn, 6), np.float64)
    q1 = q + 1
    ea = -eps
    eb = 1.0 + eps
    for n in range(nn - 1, -1, -1):
        lx = np.inf
        ly = np.inf
        lz = np.inf
        hx = -np.inf
        hy = -np.inf
        hz = -np.inf
        if leaf[n]:
            for m in range(first[n], first[n] + count[n]):
                k = prims[m]
                f = k // (q * q)
                r = k - f * q * q
                j = r // q
                i = r - j * q
                b = f * q1 * q1 + j * q1 + i
                for e in range(4):
                    uu = ea if (e & 1) == 0 else eb
                    vv = ea if (e & 2) == 0 else eb
                    w0 = (1.0 - uu) * (1.0 - vv)
                    w1 = uu * (1.0 - vv)
                    w2 = (1.0 - uu) * vv
                    w3 = uu * vv
                    x = w0 * verts[b, 0] + w1 * verts[b + 1, 0] + w2 * verts[b + q1, 0] + w3 * verts[
                        b + q1 + 1, 0]
                    y = w0 * verts[b, 1] + w1 * verts[b + 1, 1] + w2 * verts[b + q1, 1] + w3 * verts[
                        b + q1 + 1, 1]
                    z = w0 * verts[b, 2] + w1 * verts[b + 1, 2] + w2 * verts[b + q1, 2] + w3 * verts[
                        b + q1 + 1, 2]
                    lx = min(lx, x)
                    ly = min(ly, y)
                    lz = min(lz, z)
                    hx = max(hx, x)
                    hy = max(hy, y)
                    hz = max(hz, z)
            lx -= pad
            ly -= pad
            lz -= pad
            hx += pad
            hy += pad
            hz += pad
        else:
            for ch in range(first[n], first[n] + count[n]):
                lx = min(lx, bounds[ch, 0])
                ly = min(ly, bounds[ch, 1])
                lz = min(lz, bounds[ch, 2])
                hx = max(hx, bounds[ch, 3])
                hy = max(hy, bounds[ch, 4])
                hz = max(hz, bounds[ch, 5])
        bounds[n, 0] = lx
        bounds[n, 1] = ly
        bounds[n, 2] = lz
        bounds[n, 3] = hx
        bounds[n, 4] = hy
        bounds[n, 5] = hz
    return bounds, first[:nn].copy(), count[:nn].copy(), leaf[:nn].copy(), prims


@njit(cache=True)
def build_sah_tree(lo, hi, leaf_max, n_bins):
    """Binary BVH by binned surface-area heuristic (all three axes, ``n_bins`` bins).

    ``lo``/``hi`` are the (padded) primitive boxes.  Leaves hold at most ``leaf_max`` primitives.
    A range is halved by index instead when all its centroids coincide or it lies deeper than
    ``MAX_SAH_DEPTH`` (so pathological inputs cannot make the tree deeper than the fixed stacks).
    """
    m = lo.shape[0]
    prims = np.arange(m).astype(np.int32)
    cen = 0.5 * (lo + hi)
    max_nodes = 2 * m + 1
    bounds = np.empty((max_nodes, 6), np.float64)
    first = np.zeros(max_nodes, np.int32)
    count = np.zeros(max_nodes, np.int32)
    leaf = np.zeros(max_nodes, np.uint8)
    st_n = np.empty(256, np.int64)
    st_s = np.empty(256, np.int64)
    st_e = np.empty(256, np.int64)
    st_d = np.empty(256, np.int64)  # depth: beyond MAX_SAH_DEPTH ranges are halved (depth ≤ ~72)
    bin_cnt = np.zeros(n_bins, np.int64)
    bin_box = np.empty((n_bins, 6), np.float64)
    right_area = np.empty(n_bins, np.float64)
    right_cnt = np.empty(n_bins, np.int64)
    st_n[0] = 0
    st_s[0] = 0
    st_e[0] = m
    st_d[0] = 0
    sp = 1
    nn = 1
    while sp > 0:
        sp -= 1
        n = st_n[sp]
        s = st_s[sp]
        e = st_e[sp]
        depth = st_d[sp]
        bx0 = np.inf
        by0 = np.inf
        bz0 = np.inf
        bx1 = -np.inf
        by1 = -np.inf
        bz1 = -np.inf
        cx0 = np.inf
        cy0 = np.inf
        cz0 = np.inf
        cx1 = -np.inf
        cy1 = -np.inf
        cz1 = -np.inf
        for a in range(s, e):
            p = prims[a]
            bx0 = min(bx0, lo[p, 0])
            by0 = min(by0, lo[p, 1])
            bz0 = min(bz0, lo[p, 2])
            bx1 = max(bx1, hi[p, 0])
            by1 = max(by1, hi[p, 1])
            bz1 = max(bz1, hi[p, 2])
            cx0 = min(cx0, cen[p, 0])
            cy0 = min(cy0, cen[p, 1])
            cz0 = min(cz0, cen[p, 2])
            cx1 = max(cx1, cen[p, 0])
            cy1 = max(cy1, cen[p, 1])
            cz1 = max(cz1, cen[p, 2])
        bounds[n, 0] = bx0
        bounds[n, 1] = by0
        bounds[n, 2] = bz0
        bounds[n, 3] = bx1
        bounds[n, 4] = by1
        bounds[n, 5] = bz1
        cnt = e - s
        if cnt <= leaf_max:
            leaf[n] = 1
            first[n] = s
            count[n] = cnt
            continue
        best_cost = np.inf
        best_axis = -1
        best_bin = -1
        cmin = (cx0, cy0, cz0)
        cmax = (cx1, cy1, cz1)
        for axis in range(3 if depth < MAX_SAH_DEPTH else 0):
            c0 = cmin[axis]
            ext = cmax[axis] - c0
            if not ext > 0.0:
                continue
            scale = n_bins / ext
            bin_cnt[:] = 0
            for b in range(n_bins):
                bin_box[b, 0] = np.inf
                bin_box[b, 1] = np.inf
                bin_box[b, 2] = np.inf
                bin_box[b, 3] = -np.inf
                bin_box[b, 4] = -np.inf
                bin_box[b, 5] = -np.inf
            for a in range(s, e):
                p = prims[a]
                b = int((cen[p, axis] - c0) * scale)
                if b >= n_bins:
                    b = n_bins - 1
                bin_cnt[b] += 1
                for w in range(3):
                    bin_box[b, w] = min(bin_box[b, w], lo[p, w])
                    bin_box[b, 3 + w] = max(bin_box[b, 3 + w], hi[p, w])
            # sweep from the right
            rx0 = np.inf
            ry0 = np.inf
            rz0 = np.inf
            rx1 = -np.inf
            ry1 = -np.inf
            rz1 = -np.inf
            rc = 0
            for b in range(n_bins - 1, 0, -1):
                if bin_cnt[b] > 0:
                    rx0 = min(rx0, bin_box[b, 0])
                    ry0 = min(ry0, bin_box[b, 1])
                    rz0 = min(rz0, bin_box[b, 2])
                    rx1 = max(rx1, bin_box[b, 3])
                    ry1 = max(ry1, bin_box[b, 4])
                    rz1 = max(rz1, bin_box[b, 5])
                rc += bin_cnt[b]
                right_cnt[b] = rc
                if rc > 0:
                    ddx = rx1 - rx0
                    ddy = ry1 - ry0
                    ddz = rz1 - rz0
                    right_area[b] = ddx * ddy + ddy * ddz + ddz * ddx
                else:
                    right_area[b] = 0.0
            lx0 = np.inf
            ly0 = np.inf
            lz0 = np.inf
            lx1 = -np.inf
            ly1 = -np.inf
            lz1 = -np.inf
            lc = 0
            for b in range(n_bins - 1):  # split between bin b and b+1
                if bin_cnt[b] > 0:
                    lx0 = min(lx0, bin_box[b, 0])
                    ly0 = min(ly0, bin_box[b, 1])
                    lz0 = min(lz0, bin_box[b, 2])
                    lx1 = max(lx1, bin_box[b, 3])
                    ly1 = max(ly1, bin_box[b, 4])
                    lz1 = max(lz1, bin_box[b, 5])
                lc += bin_cnt[b]
                if lc == 0 or right_cnt[b + 1] == 0:
                    continue
                ddx = lx1 - lx0
                ddy = ly1 - ly0
                ddz = lz1 - lz0
                la = ddx * ddy + ddy * ddz + ddz * ddx
                cost = la * lc + right_area[b + 1] * right_cnt[b + 1]
                if cost < best_cost:
                    best_cost = cost
                    best_axis = axis
                    best_bin = b
        if best_axis < 0:
            mid = (s + e) // 2  # all centroids coincide (or too deep): halve by index
        else:
            c0 = cmin[best_axis]
            scale = n_bins / (cmax[best_axis] - c0)
            a = s
            z = e - 1
            while a <= z:
                b = int((cen[prims[a], best_axis] - c0) * scale)
                if b >= n_bins:
                    b = n_bins - 1
                if b <= best_bin:
                    a += 1
                else:
                    tmp = prims[a]
                    prims[a] = prims[z]
                    prims[z] = tmp
                    z -= 1
            mid = a
            if mid == s or mid == e:
                mid = (s + e) // 2
        c = nn
        nn += 2
        first[n] = c
        count[n] = 2
        st_n[sp] = c + 1
        st_s[sp] = mid
        st_e[sp] = e
        st_d[sp] = depth + 1
        sp += 1
        st_n[sp] = c
        st_s[sp] = s
        st_e[sp] = mid
        st_d[sp] = depth + 1
        sp += 1
    return bounds[:nn].copy(), first[:nn].copy(), count[:nn].copy(), leaf[:nn].copy(), prims
