"""Maplets from a shape model: SPC's height extraction (GET_HEIGHTS) by ray casting — ``make-maplets``.

SPC builds a new maplet's starting topography by projecting the global shape onto the maplet plane
(``GET_HEIGHTS``, spc-algorithms.md §2.2: each node's vertical line is intersected with the ICQ
bilinear patches and the **maximum height** is kept).  Here every node of every maplet is one ray
from above the node along −UZ, all in one batched first-hit query
(:meth:`spctool.geometry.shape.PatchShape.first_hit` uses the same bilinear algebra, errata 13–16);
the first hit from above is the highest surface point on the node's vertical line, i.e. GET_HEIGHTS'
maximum.

Frames follow SPC's ``ORIENT`` (spc-formats.md §1.2): UY = normalise(ẑ × UZ) (East), UX = UY × UZ
(South), with UZ the local surface normal.  The normal of a new landmark is found by projecting the
shape onto the plane normal to the radius, fitting a plane h = a·x + b·y + c to the heights by least
squares (x along UX, y along UY, cells) and tilting UZ to normalise(−a·UX − b·UY + UZ); twice.  The
landmark vector V is then moved along UZ onto the surface (the centre node's height becomes 0).
Heights are in units of SCALE, P = V + SCALE·(x·UX + y·UY + h·UZ) (spc-formats.md §1.3), the albedo
is the shape's (ICQ 4th column, spc-formats.md §5.1) at each hit, or 1.

Nodes whose vertical misses the shape are written as missing (albedo byte 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from spctool.errors import SpcUsageError
from spctool.formats.landmark import Landmark
from spctool.formats.maplet import Maplet
from spctool.geometry.frames import orient_frame
from spctool.geometry.surfaces import ShapeSurface

__all__ = [
    "ProjectedHeights",
    "project_heights",
    "surface_points",
    "fit_normals",
    "landmark_frames",
    "make_maplets",
    "new_landmark",
    "tile_directions",
    "landmark_names",
]


@dataclass
class ProjectedHeights:
    """Heights (M, n, n) in cells, ``valid`` (M, n, n), ``albedo`` (M, n, n) and the body points hit
    (M, n, n, 3) (None when not asked for)."""

    heights: np.ndarray
    valid: np.ndarray
    albedo: np.ndarray
    points: np.ndarray | None


def _as_surface(shape) -> ShapeSurface:
    return ShapeSurface.from_model(shape)


def _frames(v, ux, uy, uz):
    arrs = [np.atleast_2d(np.asarray(a, dtype=np.float64)) for a in (v, ux, uy, uz)]
    m = max(a.shape[0] for a in arrs)
    return [np.broadcast_to(a, (m, 3)) for a in arrs]


def project_heights(
    shape, v, ux, uy, uz, scale, qsz, *, chunk: int = 1 << 20, points: bool = True
) -> ProjectedHeights:
    """GET_HEIGHTS for M frames at once: the highest shape point on each node's vertical line.

    ``v``, ``ux``, ``uy``, ``uz`` are (3,) or (M, 3); ``scale`` (km/cell) a scalar or (M,); the grid is
    (2·qsz+1)² with axis 0 along UX and axis 1 along UY.  Returns heights in cells relative to V (and
    the hit points unless ``points`` is False, which saves (M, n, n, 3) doubles).
    """
    surf = _as_surface(shape)
    v, ux, uy, uz = _frames(v, ux, uy, uz)
    m = v.shape[0]
    s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (m,))
    n = 2 * int(qsz) + 1
    offs = np.arange(n, dtype=np.float64) - qsz
    lo, hi = surf.shape.bounding_box
    top = float(np.linalg.norm(hi - lo)) + 2.0 * float(np.max(np.abs(s))) * n  # above anything
    heights = np.zeros((m, n, n))
    valid = np.zeros((m, n, n), bool)
    albedo = np.zeros((m, n, n))
    pts_out = np.full((m, n, n, 3), np.nan) if points else None
    per = max(1, chunk // (n * n))
    for a in range(0, m, per):
        b = min(m, a + per)
        k = b - a
        # node (r, c): V + s·((r−q)·UX + (c−q)·UY), raised by ``top`` along UZ
        base = v[a:b, None, None, :] + s[a:b, None, None, None] * (
            offs[None, :, None, None] * ux[a:b, None, None, :]
            + offs[None, None, :, None] * uy[a:b, None, None, :]
        )
        org = (base + top * uz[a:b, None, None, :]).reshape(-1, 3)
        dirs = np.broadcast_to(-uz[a:b, None, None, :], (k, n, n, 3)).reshape(-1, 3)
        res = surf.shape.first_hit(org, dirs, t_max=2.0 * top)
        hit = res.hit.reshape(k, n, n)
        h = (top - res.t.reshape(k, n, n)) / s[a:b, None, None]
        heights[a:b] = np.where(hit, h, 0.0)
        valid[a:b] = hit
        if points:
            pts_out[a:b] = res.point.reshape(k, n, n, 3)
        if hit.any():
            alb = np.zeros(res.hit.shape[0])
            mh = res.hit
            alb[mh] = surf.albedo(res.index[mh], res.u[mh], res.v[mh])
            albedo[a:b] = alb.reshape(k, n, n)
    return ProjectedHeights(heights, valid, albedo, pts_out)


def surface_points(shape, directions) -> np.ndarray:
    """Outermost surface point along each radial direction (N, 3) from the body centre (NaN on a miss)."""
    surf = _as_surface(shape)
    d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    lo, hi = surf.shape.bounding_box
    far = 2.0 * float(np.max(np.abs(np.concatenate([lo, hi])))) + 1.0
    res = surf.shape.first_hit(d * far, -d, t_max=2.0 * far)
    return np.where(res.hit[:, None], res.point, np.nan)


def fit_normals(heights, valid, ux, uy, uz) -> np.ndarray:
    """Unit normals (M, 3) of least-squares planes h = a·x + b·y + c over valid nodes (cells).

    x along UX (axis 0), y along UY (axis 1); normal = normalise(−a·UX − b·UY + UZ).  Frames with fewer
    than 3 valid nodes keep UZ.
    """
    h = np.asarray(heights, float)
    m, n, _ = h.shape
    q = (n - 1) / 2.0
    x = (np.arange(n) - q)[:, None] * np.ones((1, n))
    y = np.ones((n, 1)) * (np.arange(n) - q)[None, :]
    ux, uy, uz = (np.broadcast_to(np.atleast_2d(a), (m, 3)) for a in (ux, uy, uz))
    out = np.array(uz, dtype=float, copy=True)
    for k in range(m):
        w = valid[k]
        if w.sum() < 3:
            continue
        a_mat = np.column_stack([x[w], y[w], np.ones(w.sum())])
        coef, *_ = np.linalg.lstsq(a_mat, h[k][w], rcond=None)
        nrm = -coef[0] * ux[k] - coef[1] * uy[k] + uz[k]
        out[k] = nrm / np.linalg.norm(nrm)
    return out


def landmark_frames(shape, centres, scale, qsz, *, normals=None, iterations: int = 2, recentre: bool = True):
    """ORIENT frames at surface points: (V, UX, UY, UZ) arrays (M, 3) each.

    ``normals`` (M, 3) starting normals (default: the radial directions of the centres); the plane fit of
    :func:`fit_normals` refines them ``iterations`` times.  With ``recentre`` V moves along the final UZ
    onto the shape (the highest hit on V's vertical).
    """
    c = np.atleast_2d(np.asarray(centres, dtype=np.float64))
    nz = c / np.linalg.norm(c, axis=1, keepdims=True) if normals is None else np.atleast_2d(normals)
    ux, uy, uz = orient_frame(nz)
    for _ in range(int(iterations)):
        ph = project_heights(shape, c, ux, uy, uz, scale, qsz)
        ux, uy, uz = orient_frame(fit_normals(ph.heights, ph.valid, ux, uy, uz))
    if recentre:
        ph = project_heights(shape, c, ux, uy, uz, scale, 0)
        ok = ph.valid[:, 0, 0]
        s = np.broadcast_to(np.asarray(scale, float), (c.shape[0],))
        c = np.where(ok[:, None], c + (ph.heights[:, 0, 0] * s)[:, None] * uz, c)
    return c, ux, uy, uz


def new_landmark(name: str, scale: float, qsz: int, v, ux, uy, uz) -> Landmark:
    """A fresh LMK (spc-formats.md §4): HFLAG T, HORIZON −1, SIGKM = 0.5·SCALE (the creators' convention,
    §4.1), RMSLMK 0, SIGMA_LMK = (SCALE, SCALE, SCALE) as bigmap writes; no pictures yet."""
    return Landmark(
        name=name,
        hflag="T",
        bigmap_extra=None,
        qsz=int(qsz),
        scale=float(scale),
        horizon=(-1, -1, -1, -1),
        sigkm=0.5 * float(scale),
        rmslmk=0.0,
        vlm=v,
        ux=ux,
        uy=uy,
        uz=uz,
        sigma_lmk=np.full(3, float(scale)),
    )


def make_maplets(
    shape, names, centres, scale: float, qsz: int, *, frames=None, recentre: bool = True, mapvers: int = 0
) -> list[tuple[Maplet, Landmark]]:
    """Maplets (MAP contents) and landmarks (LMK contents) from ``shape`` at ``centres`` (M, 3) km.

    ``frames``: None (ORIENT at the fitted surface normal, V recentred onto the surface when
    ``recentre``) or a tuple (UX, UY, UZ) of (M, 3) arrays to keep (V is then kept as given).
    """
    names = [str(n) for n in names]
    c = np.atleast_2d(np.asarray(centres, dtype=np.float64))
    if len(names) != c.shape[0]:
        raise SpcUsageError(f"{len(names)} names for {c.shape[0]} landmark centres")
    for n in names:
        if not 1 <= len(n) <= 6:
            raise SpcUsageError(f"landmark name {n!r} must have 1 to 6 characters")
    if not (scale > 0 and qsz >= 1):
        raise SpcUsageError("maplet scale must be > 0 and qsz >= 1")
    if frames is None:
        v, ux, uy, uz = landmark_frames(shape, c, scale, qsz, recentre=recentre)
    else:
        ux, uy, uz = (np.atleast_2d(np.asarray(a, float)) for a in frames)
        v = c
    ph = project_heights(shape, v, ux, uy, uz, scale, qsz)
    out = []
    for k, name in enumerate(names):
        if not ph.valid[k].any():
            raise SpcUsageError(f"landmark {name}: the shape is not below any node of the maplet")
        m = Maplet.new(
            scale,
            qsz,
            v[k],
            ux[k],
            uy[k],
            uz[k],
            ph.heights[k],
            ph.albedo[k],
            ph.valid[k],
            mapvers=mapvers,
            sigma=np.full(3, float(scale)),
            name=name,
        )
        out.append((m, new_landmark(name, scale, qsz, v[k], ux[k], uy[k], uz[k])))
    return out


def tile_directions(count: int) -> np.ndarray:
    """``count`` quasi-uniform unit vectors (Fibonacci sphere), deterministic."""
    count = int(count)
    if count < 1:
        raise SpcUsageError("tiling needs at least one landmark")
    k = np.arange(count, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * k / count
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def tile_count(shape, spacing_km: float) -> int:
    """Number of tiles for a spacing: surface area / spacing² (at least 1)."""
    surf = _as_surface(shape)
    if not spacing_km > 0:
        raise SpcUsageError("tile spacing must be > 0")
    return max(1, int(round(surf.shape.area / spacing_km**2)))


def landmark_names(prefix: str, count: int, start: int = 1) -> list[str]:
    """``prefix`` + zero-padded numbers, 6 characters in all (SPC's A6 landmark names)."""
    width = 6 - len(prefix)
    if width < 1:
        raise SpcUsageError(f"landmark prefix {prefix!r} leaves no room for a number in 6 characters")
    if start + count - 1 >= 10**width:
        raise SpcUsageError(f"{count} landmarks do not fit {width}-digit numbers after prefix {prefix!r}")
    return [f"{prefix}{k:0{width}d}" for k in range(start, start + count)]
