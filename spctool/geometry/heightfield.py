"""Maplet grids as geometry: node positions, slopes, normals, sampling and ray marching.

A maplet (``spc-formats.md`` §1.2–1.3, ``spc-algorithms.md`` §1.2) is a (2q+1)×(2q+1) grid of
heights h, **in units of SCALE** (h = 1 is one grid spacing), on the frame (V, UX, UY, UZ).

Conventions used by every function here
---------------------------------------
* Arrays are indexed ``a[r, c]`` exactly as read from the MAP file: r = J + q (NumPy **axis 0**, steps
  along **UX**, ≈ South) and c = I + q (**axis 1**, steps along **UY**, ≈ East).
* **Maplet-frame coordinates** (x, y, z) are in **cells**, relative to the maplet centre V:
  x = J along UX (axis 0), y = I along UY (axis 1), z = height along UZ.  Node (r, c) sits at
  (r − q, c − q, h[r, c]) and its body-frame position is

      P = V + SCALE · (x·UX + y·UY + z·UZ)          (spc-formats.md §1.3)

* Directions in the maplet frame are the components (d·UX, d·UY, d·UZ) of a body-frame vector.
* Heights of missing cells (``valid`` False, albedo byte 0) are never used.

Functions take plain arrays (``heights``, ``valid``, ``scale``, ``v``, ``ux``, ``uy``, ``uz``);
``valid=None`` means every node is valid.
The ``maplet_*`` wrappers accept any object with those attributes (e.g.
:class:`spctool.formats.maplet.Maplet`).

Contents
--------
* :func:`node_offsets`, :func:`node_positions` — grid nodes in the maplet frame (cells) / body frame (km).
* :func:`slopes` — SPC's HGT2SLP seven-stencil fallback table (``spc-algorithms.md`` §3.1).
  **Sign:** SPC stores the *negated* slopes; this module returns the true derivatives
  hx = ∂h/∂x (axis 0, along UX) and hy = ∂h/∂y (axis 1, along UY), dimensionless (cells per cell).
* :func:`normals_maplet`, :func:`normals_body` — n ∝ (−hx, −hy, 1) (L15 Eq. 3.37) and
  normalise(−hx·UX − hy·UY + UZ) (§3.1); :func:`surface_cosines` — n̂·d for one maplet-frame direction.
* :func:`sample_heights` — bilinear heights with a missing-data mask (the height-grid analogue of BRT0,
  §4.2).
* :func:`march` / :func:`visibility` / :func:`cast_shadows` — the one-cell horizon march of §5.3;
  all three return **True = blocked** (invisible / shadowed).
* :func:`intersect_rays` — first crossing of general rays with the bilinear terrain (rendering,
  image-space registration).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from spctool.geometry import _heightkernels as _k
from spctool.geometry import frames

#: Default ray lowering of the visibility / cast-shadow march, in cells (spc-algorithms.md §5.3,
#: ``vis_tol``; [UNVERIFIED] in SPC).
VIS_TOL = 0.05

#: |d_xy| below this (for a unit direction) counts as a vertical ray: the march blocks nothing (§5.3).
NADIR_EPS = 1e-9


class Slopes(NamedTuple):
    """Result of :func:`slopes` (unpacks as ``hx, hy, usable``)."""

    hx: np.ndarray  #: ∂h/∂x, along UX (NumPy axis 0); 0 where not usable
    hy: np.ndarray  #: ∂h/∂y, along UY (NumPy axis 1); 0 where not usable
    usable: np.ndarray  #: bool: both directions had an applicable stencil


# --------------------------------------------------------------------------------------------------
# helpers


def _grid(heights, valid=None):
    """Validated float64 heights with missing cells set to 0, and the bool mask."""
    h = np.asarray(heights, dtype=np.float64)
    if h.ndim != 2 or h.shape[0] != h.shape[1] or h.shape[0] % 2 != 1 or h.shape[0] < 3:
        raise ValueError(f"maplet heights must be a square (2q+1)x(2q+1) array, q >= 1; got shape {h.shape}")
    if valid is None:
        mask = np.ones(h.shape, dtype=bool)
    else:
        mask = np.asarray(valid, dtype=bool)
        if mask.shape != h.shape:
            raise ValueError(f"valid mask shape {mask.shape} differs from heights shape {h.shape}")
    if not mask.all():
        h = np.where(mask, h, 0.0)
    return kernel_array(h, np.float64), kernel_array(mask, np.bool_)


def kernel_array(a, dtype=np.float64):
    """C-contiguous, writeable array of ``dtype`` (one numba signature per kernel; copies if needed)."""
    if type(a) is np.ndarray and a.dtype == dtype and a.flags.c_contiguous and a.flags.writeable:
        return a  # already so: np.require's checks cost ~3 µs a call, several per template render
    return np.require(a, dtype=dtype, requirements=["C", "W"])


def _vec3(a, name):
    out = np.asarray(a, dtype=np.float64)
    if out.shape != (3,):
        raise ValueError(f"{name} must be a 3-vector, got shape {out.shape}")
    return out


def to_maplet_components(vectors, ux, uy, uz) -> np.ndarray:
    """Maplet-frame components (d·UX, d·UY, d·UZ) of body-frame vectors (..., 3) (no scaling, no V)."""
    return np.asarray(vectors, dtype=np.float64) @ frames.map_to_body_matrix(ux, uy, uz)


# --------------------------------------------------------------------------------------------------
# node positions


def node_offsets(heights) -> np.ndarray:
    """Maplet-frame coordinates of every node, in cells: (2q+1, 2q+1, 3) array of (x, y, z).

    ``out[r, c] = (r − q, c − q, heights[r, c])``: x = J along UX, y = I along UY, z = h along UZ.
    """
    h = np.asarray(heights, dtype=np.float64)
    n0, n1 = h.shape
    q0, q1 = (n0 - 1) / 2.0, (n1 - 1) / 2.0
    out = np.empty((n0, n1, 3))
    out[..., 0] = (np.arange(n0, dtype=np.float64) - q0)[:, None]
    out[..., 1] = (np.arange(n1, dtype=np.float64) - q1)[None, :]
    out[..., 2] = h
    return out


def node_positions(heights, scale, v, ux, uy, uz) -> np.ndarray:
    """Body-frame node positions in km, (2q+1, 2q+1, 3): P[r, c] = V + SCALE·((r−q)UX + (c−q)UY + h UZ).

    Missing nodes get whatever height the array holds (0 in SPC files); mask them with ``valid``.
    """
    return frames.maplet_to_body(node_offsets(heights), v, ux, uy, uz, scale)


# --------------------------------------------------------------------------------------------------
# slopes and normals


def slopes(heights, valid=None) -> Slopes:
    """Height derivatives by SPC's HGT2SLP fallback table (spc-algorithms.md §3.1).

    For each direction the first applicable stencil of the seven-row table is used (central
    difference, two one-sided quadratics through {−1, 0, 2} / {−2, 0, 1}, the 3-point backward /
    forward differences, then the 2-point differences).  All are exact for quadratics.

    Returns ``Slopes(hx, hy, usable)``: hx = ∂h/∂x along UX (axis 0), hy = ∂h/∂y along UY (axis 1),
    both in cells per cell.  A node is usable only if in **both** directions one of the pairs
    (−1, +1), (−1, 0), (0, +1) is valid; unusable nodes get hx = hy = 0.  A node may be usable
    without a valid height of its own (central stencil).

    **Sign:** SPC's HGT2SLP stores −∂h; this returns the true derivatives (n ∝ (−hx, −hy, 1)).
    """
    h, mask = _grid(heights, valid)
    hx = np.empty(h.shape)
    hy = np.empty(h.shape)
    usable = np.empty(h.shape, dtype=bool)
    _k.slopes(h, mask, hx, hy, usable)
    return Slopes(hx, hy, usable)


#: node-slope rules of a shaded height patch: SPC's HGT2SLP table (:func:`slopes`) or, where the five
#: nodes along an axis are valid, the fourth-order central difference (:func:`fourth_order_slopes`)
NODE_SLOPES = ("spc", "fourth")


def fourth_order_slopes(heights, valid, hx, hy):
    """Node slopes by the fourth-order central difference (h₋₂ − 8h₋₁ + 8h₊₁ − h₊₂)/12 along each axis
    where the five nodes are valid, else ``hx`` / ``hy`` (SPC's :func:`slopes`, the fallback near the
    border and missing nodes).  Exact for quartics (the central difference only for quadratics), and it
    damps a wave of k cells⁻¹ by (8 sin k − sin 2k)/(6k) instead of sin k / k: it keeps more of a 1 cm
    maplet's cell-scale relief in a template's shading (issue 39: the s16-50m Monte Carlo's image
    floor).  White height noise σ becomes slope noise √130/12 σ = 0.95σ (central: 0.71σ).

    Returns new (hx, hy) arrays, in cells per cell, axis 0 = x (UX), axis 1 = y (UY).
    """
    h, mask = _grid(heights, valid)
    out = []
    for axis, base in ((0, hx), (1, hy)):
        d = np.array(base, dtype=np.float64, copy=True)
        hm, mm, dm = np.moveaxis(h, axis, 0), np.moveaxis(mask, axis, 0), np.moveaxis(d, axis, 0)
        ok = mm[:-4] & mm[1:-3] & mm[3:-1] & mm[4:]
        four = (hm[:-4] - 8.0 * hm[1:-3] + 8.0 * hm[3:-1] - hm[4:]) / 12.0
        inner = dm[2:-2]
        inner[ok] = four[ok]
        out.append(d)
    return out[0], out[1]


def normals_maplet(hx, hy) -> np.ndarray:
    """Unit normals in the maplet frame, (..., 3): (−hx, −hy, 1)/√(1 + hx² + hy²) (L15 Eq. 3.37)."""
    return normals_body(hx, hy, (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def normals_body(hx, hy, ux, uy, uz) -> np.ndarray:
    """Unit normals in the body frame, (..., 3): normalise(−hx·UX − hy·UY + UZ) (spc-algorithms.md §3.1)."""
    hx, hy = np.broadcast_arrays(np.asarray(hx, dtype=np.float64), np.asarray(hy, dtype=np.float64))
    out = np.empty(hx.shape + (3,))
    _k.normals(
        kernel_array(hx, np.float64).reshape(-1),
        kernel_array(hy, np.float64).reshape(-1),
        kernel_array(_vec3(ux, "ux"), np.float64),
        kernel_array(_vec3(uy, "uy"), np.float64),
        kernel_array(_vec3(uz, "uz"), np.float64),
        out.reshape(-1, 3),
    )
    return out


# --------------------------------------------------------------------------------------------------
# sampling


def sample_heights(heights, valid, x, y, *, repair_one_corner: bool = False):
    """Bilinear terrain heights at maplet-frame points (x, y) in cells **relative to the centre**.

    x is along UX (axis 0, index r = x + q) and y along UY (axis 1, index c = y + q); x and y
    broadcast.  Returns ``(values, ok)``; values are 0 where ``ok`` is False.

    Missing-data rule (the height-grid analogue of BRT0, spc-algorithms.md §4.2): a point is ok if it
    lies in the closed grid square −q ≤ x, y ≤ q and every corner with a **non-zero** bilinear weight
    is valid.  For a strictly interior fractional point this is "all four corners valid"; a point
    exactly on a node or grid line only needs the nodes it actually uses, so sampling at a node
    returns that node's height.  The base cell is floor(index), clamped to n − 2 so the last row and
    column are reachable.

    ``repair_one_corner=True`` adds SPC BRT0's repair: if exactly one of the four corners is missing
    (and it is needed), it is rebuilt by planar extrapolation from the other three
    (e.g. h00 ← h10 + h01 − h11; BRT0's max(1, ·) clamp is for DNs and is not applied to heights).
    """
    h, mask = _grid(heights, valid)
    n = h.shape[0]
    q = (n - 1) / 2.0
    u, w = np.broadcast_arrays(np.asarray(x, dtype=np.float64) + q, np.asarray(y, dtype=np.float64) + q)
    inside = (u >= 0.0) & (u <= n - 1.0) & (w >= 0.0) & (w <= n - 1.0)
    uu = np.where(inside, u, 0.0)
    ww = np.where(inside, w, 0.0)
    i = np.minimum(np.floor(uu).astype(np.intp), n - 2)
    j = np.minimum(np.floor(ww).astype(np.intp), n - 2)
    fu = uu - i
    fw = ww - j
    gu = 1.0 - fu
    gw = 1.0 - fw
    h00, h10, h01, h11 = h[i, j], h[i + 1, j], h[i, j + 1], h[i + 1, j + 1]
    v00, v10, v01, v11 = mask[i, j], mask[i + 1, j], mask[i, j + 1], mask[i + 1, j + 1]
    need00 = (gu != 0.0) & (gw != 0.0)
    need10 = (fu != 0.0) & (gw != 0.0)
    need01 = (gu != 0.0) & (fw != 0.0)
    need11 = (fu != 0.0) & (fw != 0.0)
    ok = inside & (v00 | ~need00) & (v10 | ~need10) & (v01 | ~need01) & (v11 | ~need11)
    if repair_one_corner:
        n_missing = (~v00).astype(np.int8) + ~v10 + ~v01 + ~v11
        fix = inside & ~ok & (n_missing == 1)
        h00, h10, h01, h11 = (
            np.where(fix & ~v00, h10 + h01 - h11, h00),
            np.where(fix & ~v10, h00 + h11 - h01, h10),
            np.where(fix & ~v01, h00 + h11 - h10, h01),
            np.where(fix & ~v11, h10 + h01 - h00, h11),
        )
        ok = ok | fix
    values = gw * (gu * h00 + fu * h10) + fw * (gu * h01 + fu * h11)
    return np.where(ok, values, 0.0), ok


# --------------------------------------------------------------------------------------------------
# horizon march (visibility, cast shadows)


def march(heights, valid, direction, tol: float = VIS_TOL, nodes=None) -> np.ndarray:
    """Which nodes have terrain between them and ``direction`` (spc-algorithms.md §5.3).

    ``direction`` is a maplet-frame vector (d·UX, d·UY, d·UZ) (any length).  From each selected
    valid node (r, c) the march steps k = 1, 2, … by one cell horizontally along d_xy/|d_xy|, to the
    point (r + k·d̂x, c + k·d̂y); the ray height there is h0 + k·d_z/|d_xy| − ``tol`` (the ray is
    lowered by ``tol`` cells); terrain heights are bilinear (:func:`sample_heights` rule, missing
    samples block nothing).  The node is blocked at the first k where terrain > ray.  The march stops
    at the maplet edge.  If |d_xy| ≤ NADIR_EPS·|d| nothing is blocked.

    ``nodes`` (bool (2q+1)², default all) selects the start nodes; unselected and invalid nodes are
    returned False.  Returns a bool (2q+1, 2q+1) array, True = blocked.
    """
    h, mask = _grid(heights, valid)
    d = _vec3(direction, "direction")
    if nodes is None:
        sel = mask
    else:
        sel = np.asarray(nodes, dtype=bool)
        if sel.shape != h.shape:
            raise ValueError(f"nodes mask shape {sel.shape} differs from heights shape {h.shape}")
        sel = sel & mask
    out = np.zeros(h.shape, dtype=bool)
    dxy = float(np.hypot(d[0], d[1]))
    norm = float(np.linalg.norm(d))
    if norm == 0.0 or dxy <= NADIR_EPS * norm:
        return out
    _k.march_blocked(
        h, mask, kernel_array(sel, np.bool_), d[0] / dxy, d[1] / dxy, d[2] / dxy, float(tol), out
    )
    return out


def visibility(heights, valid, ux, uy, uz, emission_dir, tol: float = VIS_TOL, nodes=None) -> np.ndarray:
    """Invisible nodes: True where terrain hides the camera (SPC's INV cells, spc-algorithms.md §5.3).

    ``emission_dir`` is the body-frame unit vector from the maplet toward the camera (ê).  Returns a
    bool (2q+1)² array, **True = line of sight blocked** (invisible).  See :func:`march`.
    """
    d = to_maplet_components(_vec3(emission_dir, "emission_dir"), ux, uy, uz)
    return march(heights, valid, d, tol=tol, nodes=nodes)


def cast_shadows(heights, valid, ux, uy, uz, sun_dir, tol: float = VIS_TOL, nodes=None) -> np.ndarray:
    """Nodes in cast shadow: True where terrain hides the Sun (the march along ŝ, §5.3).

    ``sun_dir`` is the body-frame unit vector toward the Sun (ŝ).  Returns a bool (2q+1)² array,
    **True = shadowed**.  SPC skips this march (dead code, L15 footnote 37); the caller decides.
    """
    d = to_maplet_components(_vec3(sun_dir, "sun_dir"), ux, uy, uz)
    return march(heights, valid, d, tol=tol, nodes=nodes)


# --------------------------------------------------------------------------------------------------
# general rays


def intersect_rays(heights, valid, origins, directions, t_min=0.0, t_max=np.inf) -> np.ndarray:
    """First crossing of rays origin + t·direction with the bilinear terrain, in the maplet frame.

    ``origins`` and ``directions`` are (..., 3) maplet-frame coordinates **in cells** (x along UX,
    y along UY relative to the centre, z along UZ in the units of the heights); they broadcast, and
    directions need not be unit (t is in units of |direction|).  Convert body-frame rays with
    ``frames.body_to_maplet`` (origins) and :func:`to_maplet_components` (directions, then divide
    by SCALE to keep t in body-frame km units).  Returns t (...,), NaN where there is
    no crossing in [t_min, t_max].

    Terrain: the bilinear surface over cells whose four corners are valid (cells with a missing
    corner are holes), treated as a solid below the surface, limited to the grid square
    −q ≤ x, y ≤ q.  The crossing is the first t where the ray height falls below the terrain; a ray
    that starts (or enters the grid square or leaves a hole) below the surface hits at that point.

    Step size: instead of a fixed step, the ray is sampled where it crosses the grid lines (an exact
    cell traversal, at most 2·(2q) + 1 segments), plus at the extremum of the ray-minus-terrain
    height inside each cell.  Along a straight line bilinear terrain is quadratic in t, so these
    samples bracket every crossing: no step size to tune, and no crossing can be stepped over (a
    fixed one-cell step misses rays that graze a bump between two samples).  Inside the first
    bracket (last sample above, first sample below) the quadratic has exactly one root, taken in
    numerically stable closed form; bisection to floating-point resolution is the fallback when
    rounding puts that root outside the bracket (closed form: ~0.1 µs per hit instead of ~3 µs for
    50 bisection steps).  The ray is first clipped to z ≤ the highest valid height.
    """
    h, mask = _grid(heights, valid)
    q = (h.shape[0] - 1) / 2.0
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if o.shape[-1:] != (3,) or d.shape[-1:] != (3,):
        raise ValueError("origins and directions must have a last axis of length 3")
    shape = np.broadcast_shapes(o.shape, d.shape)[:-1]
    o = np.broadcast_to(o, shape + (3,)).reshape(-1, 3) + np.array([q, q, 0.0])
    d = kernel_array(np.broadcast_to(d, shape + (3,)).reshape(-1, 3), np.float64)
    m = o.shape[0]
    tmin = kernel_array(np.broadcast_to(np.asarray(t_min, dtype=np.float64), shape).reshape(m), np.float64)
    tmax = kernel_array(np.broadcast_to(np.asarray(t_max, dtype=np.float64), shape).reshape(m), np.float64)
    out = np.empty(m)
    _k.intersect_rays(h, mask, kernel_array(o, np.float64), d, tmin, tmax, out)
    return out.reshape(shape)


# --------------------------------------------------------------------------------------------------
# duck-typed wrappers (any object with heights, valid, scale, v, ux, uy, uz)


def maplet_node_positions(maplet) -> np.ndarray:
    """:func:`node_positions` of a maplet object."""
    return node_positions(maplet.heights, maplet.scale, maplet.v, maplet.ux, maplet.uy, maplet.uz)


def maplet_slopes(maplet) -> Slopes:
    """:func:`slopes` of a maplet object."""
    return slopes(maplet.heights, maplet.valid)


def maplet_normals(maplet):
    """Body-frame unit normals and the usable mask of a maplet object: ``(normals (N, N, 3), usable)``."""
    hx, hy, usable = maplet_slopes(maplet)
    return normals_body(hx, hy, maplet.ux, maplet.uy, maplet.uz), usable


def maplet_visibility(maplet, emission_dir, tol: float = VIS_TOL, nodes=None) -> np.ndarray:
    """:func:`visibility` of a maplet object (True = invisible)."""
    return visibility(
        maplet.heights, maplet.valid, maplet.ux, maplet.uy, maplet.uz, emission_dir, tol=tol, nodes=nodes
    )


def maplet_cast_shadows(maplet, sun_dir, tol: float = VIS_TOL, nodes=None) -> np.ndarray:
    """:func:`cast_shadows` of a maplet object (True = shadowed)."""
    return cast_shadows(
        maplet.heights, maplet.valid, maplet.ux, maplet.uy, maplet.uz, sun_dir, tol=tol, nodes=nodes
    )


def surface_cosines(hx, hy, direction_maplet, inv_norm=None) -> np.ndarray:
    """n̂·d for maplet-frame unit normals n̂ ∝ (−hx, −hy, 1) and one maplet-frame direction d (3,).

    ``inv_norm``: 1/√(1 + hx² + hy²) if already computed (it is shared by several directions).
    """
    d = np.asarray(direction_maplet, dtype=np.float64)
    hx = np.asarray(hx, dtype=np.float64)
    hy = np.asarray(hy, dtype=np.float64)
    if hx.ndim == 2 and hx.shape == hy.shape and (inv_norm is None or np.shape(inv_norm) == hx.shape):
        # a grid: one GIL-free pass (the same operations)
        c = np.ascontiguousarray
        out = np.empty(hx.shape)
        have = inv_norm is not None
        norm = c(inv_norm, dtype=np.float64) if have else hx
        _k.surface_cosines(c(hx), c(hy), float(d[0]), float(d[1]), float(d[2]), norm, have, out)
        return out
    if inv_norm is None:
        inv_norm = 1.0 / np.sqrt(1.0 + hx * hx + hy * hy)
    return (d[2] - hx * d[0] - hy * d[1]) * inv_norm
