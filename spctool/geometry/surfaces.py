"""The surfaces a rendering meets: maplet-like height patches and a global shape.

Specification: ``spc-formats.md`` §1.3 (maplet grids: P = V + SCALE·(x·UX + y·UY + h·UZ), x along UX =
axis 0, y along UY = axis 1), §5 (ICQ shapes; ray algebra of ``spc-algorithms.md`` §2.2 via
:class:`spctool.geometry.shape.PatchShape`) and ``spc-algorithms.md`` §3.1 (shading normals from SPC's
node slopes, the HGT2SLP table); S16 "Future Retina development" (image-space templates) and issue 17
(their render-ready packing).  Rendering itself — rays, shadows, photometry, pixels — is
:mod:`spctool.stages.render`; this module holds what it renders:

* :class:`HeightPatch` — one maplet as a bilinear height field in the body frame, with the derived grids
  the ray kernels read (node slopes, cell tops, the near-slope bounds of the raster path and the lit
  shortcut, the raster's node and wall-foot points), each computed once and cached;
* :class:`PatchSet` — the patches of one rendering packed for the batch and fused kernels of
  :mod:`spctool.geometry._patchkernels` (bounding spheres, boxes, stacked maps, the Sun's upwind maxima
  and horizon bounds), built once and reusable by every render of the same patches (register's
  image-space templates keep one per maplet);
* :class:`ShapeSurface` — a global shape (ICQ cells or a triangle mesh) with interpolated vertex normals
  and albedo at hits;
* :func:`local_rays`, :func:`intersect_patch` — the exact ray–terrain crossing of one patch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from spctool.errors import SpcUsageError
from spctool.geometry import heightfield
from spctool.geometry._patchgrids import patch_grids, patch_maps, sun_bounds
from spctool.geometry._patchkernels import (
    _crossings,
    _in_boxes,
    _local_slab,
    _near_spheres,
    lit_corridor,
)
from spctool.geometry.heightfield import Slopes, kernel_array
from spctool.geometry.shape import PatchShape, TriangleShape

__all__ = [
    "HeightPatch",
    "PatchSet",
    "ShapeSurface",
    "NEAR_CELLS",
    "LIT_CELLS",
    "SHADOW_PATCH_EPS",
    "finite_vec3",
    "local_rays",
    "intersect_patch",
]

#: the raster path vouches for a cell when the ray, from the height of the patch's highest node down to
#: that cell, stays within this many cells of it and descends faster than every slope there
#: (:attr:`HeightPatch.near_steps`)
NEAR_CELLS = 4

#: a shadow ray is lit without a march when it rises faster than every slope within this many cells of
#: its hit and, where it leaves them, clears the terrain ahead (:attr:`HeightPatch.near_steps`; 2 cells
#: took the shortcut for 71 % of the hits of the S16 scene, 4 cells for 51 %)
LIT_CELLS = 2

#: parameter margin of the ICQ cells for shadow rays (see :attr:`ShapeSurface.shadow_shape`)
SHADOW_PATCH_EPS = 1e-7


def finite_vec3(a, name):
    """``a`` as a finite float 3-vector; :class:`SpcUsageError` naming ``name`` otherwise."""
    out = np.asarray(a, dtype=np.float64).reshape(-1)
    # three Python floats tested one by one: ~0.5 µs against ~4 µs for np.all(np.isfinite(·)) — a patch's
    # four vectors and each render's Sun
    if out.shape != (3,) or not all(map(math.isfinite, out.tolist())):
        raise SpcUsageError(f"{name} must be a finite 3-vector")
    return out


@dataclass(frozen=True, eq=False)
class HeightPatch:
    """A maplet-like height field: heights in cells on the frame (V, UX, UY, UZ) with SCALE km/cell.

    ``heights``, ``albedo`` and ``valid`` are (2q+1)×(2q+1) with axis 0 along UX (J) and axis 1 along
    UY (I) (``spc-formats.md`` §1.3).  ``albedo`` defaults to 1, ``valid`` to all nodes.
    ``node_slopes``: the node slopes its smooth shading interpolates, ``"spc"`` (SPC's HGT2SLP table)
    or ``"fourth"`` (:func:`spctool.geometry.heightfield.fourth_order_slopes`, SPC's where the five
    nodes are not valid).
    """

    heights: np.ndarray
    scale: float
    v: np.ndarray
    ux: np.ndarray
    uy: np.ndarray
    uz: np.ndarray
    albedo: np.ndarray | None = None
    valid: np.ndarray | None = None
    name: str = ""
    node_slopes: str = "spc"

    def __post_init__(self):
        set_ = object.__setattr__
        h = np.ascontiguousarray(self.heights, dtype=np.float64)
        if h.ndim != 2 or h.shape[0] != h.shape[1] or h.shape[0] % 2 != 1 or h.shape[0] < 3:
            raise SpcUsageError(
                f"patch {self.name!r}: heights must be (2q+1)x(2q+1) with q >= 1, got {h.shape}"
            )
        if self.node_slopes not in heightfield.NODE_SLOPES:
            raise SpcUsageError(
                f"patch {self.name!r}: node_slopes must be one of {', '.join(heightfield.NODE_SLOPES)}, "
                f"got {self.node_slopes!r}"
            )
        valid = np.ones(h.shape, bool) if self.valid is None else np.ascontiguousarray(self.valid, dtype=bool)
        alb = np.ones(h.shape) if self.albedo is None else np.ascontiguousarray(self.albedo, dtype=np.float64)
        if valid.shape != h.shape or alb.shape != h.shape:
            raise SpcUsageError(f"patch {self.name!r}: albedo and valid must have the shape of heights")
        # one pass (patch_maps): valid & finite heights, heights and albedo 0 elsewhere, written into the
        # stacked maps the fused renderer reads (heights, hx, hy, albedo; the slopes on first use), and
        # the valid heights' extremes
        maps = np.empty((4,) + h.shape)
        ok = np.empty(h.shape, bool)
        zlo, zhi = patch_maps(h, valid, alb, maps, ok)
        if not zlo <= zhi:
            raise SpcUsageError(f"patch {self.name!r} has no valid node")
        set_(self, "heights", maps[0])
        set_(self, "valid", ok)
        set_(self, "albedo", maps[3])
        set_(self, "_maps", maps)
        set_(self, "_big", max(abs(zlo), abs(zhi)))
        if zlo == 0.0 or zhi == 0.0:  # a zero's sign is numpy's reduction's (max(−0, +0) is either)
            hv = maps[0][ok]
            zlo, zhi = hv.min(), hv.max()
        set_(self, "_height_range", (float(zlo), float(zhi)))
        scale = float(self.scale)
        if not (scale > 0 and math.isfinite(scale)):
            raise SpcUsageError(f"patch {self.name!r}: scale must be > 0")
        set_(self, "scale", scale)
        for k in ("v", "ux", "uy", "uz"):
            set_(self, k, finite_vec3(getattr(self, k), k))

    @classmethod
    def from_maplet(cls, maplet, name: str | None = None, node_slopes: str = "spc") -> HeightPatch:
        """A patch from any object with heights, albedo, valid, scale, v, ux, uy, uz (e.g. ``Maplet``)."""
        return cls(
            maplet.heights,
            maplet.scale,
            maplet.v,
            maplet.ux,
            maplet.uy,
            maplet.uz,
            albedo=getattr(maplet, "albedo", None),
            valid=getattr(maplet, "valid", None),
            name=getattr(maplet, "name", "") if name is None else name,
            node_slopes=node_slopes,
        )

    @property
    def qsz(self) -> int:
        return (self.heights.shape[0] - 1) // 2

    @cached_property
    def rotation(self) -> np.ndarray:
        """Maplet → body rotation, UX, UY, UZ as columns."""
        return np.column_stack([self.ux, self.uy, self.uz])

    @property
    def height_range(self) -> tuple[float, float]:
        """(lowest, highest) valid height (cells)."""
        return self._height_range

    @cached_property
    def _grids(self):
        """(stacked maps, usable, cell tops, near steps): :func:`spctool.geometry._patchgrids.patch_grids`
        fills the slopes' planes of the maps and computes the other grids, every derived grid in one call."""
        n = self.heights.shape[0]
        usable = np.empty((n, n), bool)
        tops = np.empty((n - 1, n - 1))
        near = np.empty((n - 1, n - 1, 4))
        patch_grids(self._maps, self.valid, self._big, NEAR_CELLS, LIT_CELLS, usable, tops, near)
        if self.node_slopes == "fourth":  # the geometry's grids (tops, near) come from the heights alone
            hx, hy = heightfield.fourth_order_slopes(self._maps[0], self.valid, self._maps[1], self._maps[2])
            self._maps[1], self._maps[2] = hx, hy
        return self._maps, usable, tops, near

    @cached_property
    def slopes(self) -> Slopes:
        """SPC node slopes (:func:`spctool.geometry.heightfield.slopes`): hx, hy, usable."""
        maps, usable = self._grids[:2]
        return Slopes(maps[1], maps[2], usable)

    @property
    def cell_tops(self) -> np.ndarray:
        """(2q)×(2q) cell tops for the crossing kernel (:func:`spctool.geometry._heightkernels.cell_tops`)."""
        return self._grids[2]

    @property
    def stacked_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """((4, n, n) heights, hx, hy, albedo; valid) as the fused renderer reads them (``heights`` and
        ``albedo`` are its planes 0 and 3)."""
        return self._grids[0], self.valid

    def _nodes_at(self, z) -> np.ndarray:
        """(n, n, 3) body positions (km) of the grid nodes at heights ``z`` (cells; array or scalar)."""
        q = self.qsz
        t = np.arange(-q, q + 1, dtype=np.float64)
        x, y = np.meshgrid(t, t, indexing="ij")
        return self.to_body(np.stack([x, y, np.broadcast_to(z, x.shape)], axis=-1))

    @cached_property
    def node_points(self) -> np.ndarray:
        """(n, n, 3) body positions (km) of the grid nodes (invalid nodes at height 0)."""
        return self._nodes_at(self.heights)

    @property
    def near_steps(self) -> np.ndarray:
        """(n − 1, n − 1, 4): for each cell, the largest height step between valid neighbours along x and
        along y (cells) over the full cells within :data:`NEAR_CELLS` (channels 0, 1) and
        :data:`LIT_CELLS` (2, 3) cells of it (Chebyshev), +inf where that block holds a cell with a
        missing corner (:func:`spctool.geometry._heightkernels.near_steps`) — bounds of the bilinear
        terrain's slopes |∂h/∂x|, |∂h/∂y| near the cell: the raster path's and the lit shortcut's proof
        that a ray crossed nothing."""
        return self._grids[3]

    @cached_property
    def bottom_points(self) -> np.ndarray:
        """(n, n, 3) body positions (km) of the grid nodes at the bottom of :meth:`box`."""
        return self._nodes_at(self.box()[0][2])

    @cached_property
    def wall_index(self) -> np.ndarray:
        """(n, n) int64: each node's row in the wall feet of :attr:`raster_points` (after the n² nodes),
        −1 for a node on no wall — the nodes of an edge between a full cell and no cell (the grid's
        border, missing nodes), where the march meets a wall below the terrain."""
        v = self.valid
        full = v[:-1, :-1] & v[1:, :-1] & v[:-1, 1:] & v[1:, 1:]
        pad = np.zeros((full.shape[0] + 2, full.shape[1] + 2), bool)
        pad[1:-1, 1:-1] = full
        # a full cell with a non-full neighbour across an edge: all four corners (a superset of the feet)
        edge = full & ~(pad[:-2, 1:-1] & pad[2:, 1:-1] & pad[1:-1, :-2] & pad[1:-1, 2:])
        nodes = np.zeros(v.shape, bool)
        for di in (0, 1):
            for dj in (0, 1):
                nodes[di : di + edge.shape[0], dj : dj + edge.shape[1]] |= edge
        index = np.full(v.shape, -1, np.int64)
        index[nodes] = np.arange(int(nodes.sum()))
        return index

    @cached_property
    def raster_points(self) -> np.ndarray:
        """(n² + m, 3) body positions (km) the raster projects: the nodes (row-major), then the m wall
        feet (:attr:`wall_index`) at the bottom of :meth:`box`."""
        feet = self.bottom_points[self.wall_index >= 0]
        return np.ascontiguousarray(np.concatenate([self.node_points.reshape(-1, 3), feet]))

    def _cells(self, x, y):
        """(i, j, fu, fw): the cell under maplet-frame (x, y) cells (clamped to the grid) and the fractions
        of the way across it along axes 0 and 1."""
        n = self.heights.shape[0]
        q = self.qsz
        u = np.clip(np.asarray(x, dtype=np.float64) + q, 0.0, n - 1.0)
        w = np.clip(np.asarray(y, dtype=np.float64) + q, 0.0, n - 1.0)
        i = np.minimum(np.floor(u).astype(np.intp), n - 2)
        j = np.minimum(np.floor(w).astype(np.intp), n - 2)
        return i, j, u - i, w - j

    def facet_slopes(self, x, y):
        """(hx, hy): slopes of the flat triangle under maplet-frame (x, y) (two per cell, split along the
        (i, j)–(i+1, j+1) diagonal), the shading of ``shading="facet"``."""
        i, j, fu, fw = self._cells(x, y)
        h = self.heights
        lower = fu >= fw
        hx = np.where(lower, h[i + 1, j] - h[i, j], h[i + 1, j + 1] - h[i, j + 1])
        hy = np.where(lower, h[i + 1, j + 1] - h[i + 1, j], h[i, j + 1] - h[i, j])
        return hx, hy

    def to_local(self, points) -> np.ndarray:
        """Body points (N, 3) km → maplet-frame (x, y, z) in cells."""
        return ((np.asarray(points, dtype=np.float64) - self.v) @ self.rotation) / self.scale

    def dirs_to_local(self, directions) -> np.ndarray:
        """Body directions (N, 3) → maplet components divided by SCALE (keeps the ray parameter in km)."""
        return (np.asarray(directions, dtype=np.float64) @ self.rotation) / self.scale

    def to_body(self, local) -> np.ndarray:
        """Maplet-frame cells (N, 3) → body km."""
        return self.v + self.scale * (np.asarray(local, dtype=np.float64) @ self.rotation.T)

    def interpolate(self, x, y):
        """Bilinear (height, hx, hy, albedo) at maplet-frame (x, y) cells; x along UX, y along UY."""
        i, j, fu, fw = self._cells(x, y)
        w00 = (1 - fu) * (1 - fw)
        w10 = fu * (1 - fw)
        w01 = (1 - fu) * fw
        w11 = fu * fw
        hx, hy, _ = self.slopes
        out = []
        for a in (self.heights, hx, hy, self.albedo):
            out.append(w00 * a[i, j] + w10 * a[i + 1, j] + w01 * a[i, j + 1] + w11 * a[i + 1, j + 1])
        return tuple(out)

    def normals_at(self, x, y) -> np.ndarray:
        """Unit body-frame shading normals at maplet-frame (x, y): interpolated slopes (§3.1)."""
        _, hx, hy, _ = self.interpolate(x, y)
        return heightfield.normals_body(hx, hy, self.ux, self.uy, self.uz)

    def box(self, top_extra: float = 0.0):
        """Local bounding box (lo (3,), hi (3,)) in cells: the footprint column with a 1-cell margin."""
        zlo, zhi = self.height_range
        q = float(self.qsz)
        return np.array([-q, -q, zlo - 1.0]), np.array([q, q, zhi + 1.0 + top_extra])


class PatchSet:
    """The patches of one rendering, with packed arrays for the batch kernels."""

    @classmethod
    def of(cls, patches) -> PatchSet:
        """``patches`` as a set: a :class:`PatchSet` as it is (its packing reused), else one made of
        :class:`HeightPatch` objects or maplets (:meth:`HeightPatch.from_maplet`)."""
        if isinstance(patches, PatchSet):
            return patches
        return cls(p if isinstance(p, HeightPatch) else HeightPatch.from_maplet(p) for p in patches)

    def __init__(self, patches):
        self.patches = list(patches)
        n = len(self.patches)
        self.centres = np.zeros((n, 3))
        self.radii2 = np.zeros(n)
        self.vs = np.zeros((n, 3))
        self.rots = np.zeros((n, 3, 3))
        self.inv = np.zeros(n)
        self.los = np.zeros((n, 3))
        self.his = np.zeros((n, 3))
        self._fused = None
        self._up = None
        #: the renderer's node radiances for ``shading="gouraud"`` (its cache: one camera position and Sun)
        self._node_radiance = None
        for k, p in enumerate(self.patches):
            lo, hi = p.box()
            zc = 0.5 * (lo[2] + hi[2])
            self.centres[k] = p.v + p.scale * zc * p.uz
            # a sphere around the box raised by the relief (the shadow test's own-column box)
            half = 0.5 * (hi[2] - lo[2]) + (p.height_range[1] - p.height_range[0]) + 1.0
            self.radii2[k] = (p.scale * 1.0001) ** 2 * (2.0 * p.qsz**2 + (half + 1.0) ** 2)
            self.vs[k] = p.v
            self.rots[k] = p.rotation
            self.inv[k] = 1.0 / p.scale
            self.los[k] = lo
            self.his[k] = hi

    def __len__(self):
        return len(self.patches)

    def fused_arrays(self, sun=None, fast=True):
        """The patches packed for the fused kernel (:func:`spctool.geometry._patchkernels._fused_rays`;
        built once per set), with each patch's upwind maximum and horizon bound
        (:mod:`spctool.geometry._heightkernels`) for the unit Sun direction ``sun`` (+inf, no effect,
        when None; ``fast=False``: no horizon shortcut, the reference march).

        ``geo`` (P, 23): bounding-sphere centre (0–2) and radius² (3), V (4–6), the maplet→body rotation
        row by row (7–15), 1/SCALE (16), SCALE (17), QSZ (18), lowest/highest valid height (19, 20),
        :data:`NEAR_CELLS` (21), :data:`LIT_CELLS` (22); ``near`` (P, n − 1, n − 1, 4):
        :attr:`HeightPatch.near_steps` (+inf padding);
        ``boxes`` (P, 9): box lo (0–2), hi (3–5) and hi of the relief-raised shadow box (6–8);
        ``maps`` (P, 4, n, n): heights, hx, hy, albedo (zero-padded to the largest patch);
        ``valids`` (P, n, n); ``tops`` (P, n − 1, n − 1): :attr:`HeightPatch.cell_tops` (padded with −inf);
        ``ns`` (P,): each patch's 2·QSZ + 1; ``upmax``, ``horizon``, ``entry`` (P, n − 1, n − 1);
        ``clear`` (P, n − 1, n − 1) bool: :func:`spctool.geometry._patchkernels.lit_corridor` for ``sun``
        (False everywhere when None or ``fast=False``).
        """
        up, hor, ent, clear = self._upmax(sun)
        *packed, near = self._packed()
        if not fast:  # the reference: no shortcut, no raster vouching (near slopes unbounded)
            hor = ent = np.full_like(hor, np.inf)
            near = np.full_like(near, np.inf)
            clear = np.zeros_like(clear)
        return (*packed, up, hor, ent, near, clear)

    def _upmax(self, sun):
        if sun is None:
            key = None
        else:  # the Sun's three floats (tolist: one call rather than a float() each)
            key = tuple(sun.tolist() if type(sun) is np.ndarray else (float(v) for v in sun))
        if self._up is None or self._up[0] != key:
            nmax = max(p.heights.shape[0] for p in self.patches)
            shape = (len(self), nmax - 1, nmax - 1)
            if sun is None or any(p.heights.shape[0] < nmax for p in self.patches):
                up, hor, ent = (np.full(shape, np.inf) for _ in range(3))  # +inf: no bound (padding)
            else:
                up, hor, ent = (np.empty(shape) for _ in range(3))  # sun_bounds writes every value
            clear = np.zeros(shape, bool)
            if sun is not None:
                for k, p in enumerate(self.patches):
                    su, sw, sz = np.asarray(sun, dtype=np.float64) @ p.rotation
                    sun_bounds(p.cell_tops, float(su), float(sw), float(sz), k, up, hor, ent)
                geo, _, maps, valids, _, ns, _ = self._packed()
                lit_corridor(geo, maps, valids, ns, kernel_array(sun), clear)
            self._up = (key, up, hor, ent, clear)
        return self._up[1:]

    def _packed(self):
        if self._fused is None:
            npatch = len(self)
            nmax = max(p.heights.shape[0] for p in self.patches)
            geo = np.zeros((npatch, 23))
            boxes = np.zeros((npatch, 9))
            if npatch == 1:  # the common case (templates): the patch's own arrays, no copy
                maps, valids = (a[None] for a in self.patches[0].stacked_maps)
                tops = self.patches[0].cell_tops[None]
                near = self.patches[0].near_steps[None]
            else:
                maps = np.zeros((npatch, 4, nmax, nmax))
                valids = np.zeros((npatch, nmax, nmax), bool)
                tops = np.full((npatch, nmax - 1, nmax - 1), -np.inf)
                near = np.full((npatch, nmax - 1, nmax - 1, 4), np.inf)
            ns = np.zeros(npatch, np.int64)
            for k, p in enumerate(self.patches):
                n = p.heights.shape[0]
                zlo, zhi = p.height_range
                geo[k, 0:3] = self.centres[k]
                geo[k, 3] = self.radii2[k]
                geo[k, 4:7] = self.vs[k]
                geo[k, 7:16] = self.rots[k].reshape(-1)
                geo[k, 16] = self.inv[k]
                geo[k, 17:21] = p.scale, float(p.qsz), zlo, zhi
                geo[k, 21:23] = NEAR_CELLS, LIT_CELLS
                boxes[k, 0:3] = self.los[k]
                boxes[k, 3:6] = self.his[k]
                boxes[k, 6:9] = p.box(top_extra=(zhi - zlo) + 1.0)[1]
                if npatch > 1:
                    maps[k, :, :n, :n], valids[k, :n, :n] = p.stacked_maps
                    tops[k, : n - 1, : n - 1] = p.cell_tops
                    near[k, : n - 1, : n - 1] = p.near_steps
                ns[k] = n
            self._fused = geo, boxes, maps, valids, tops, ns, near
        return self._fused

    def near(self, origins, dirs, use=None):
        """(N, P) bool: rays that may meet each patch's box (bounding-sphere test)."""
        n = dirs.shape[0]
        out = np.zeros((n, len(self)), bool)
        if len(self) and n:
            u = np.ones(n, bool) if use is None else np.ascontiguousarray(use, dtype=bool)
            _near_spheres(kernel_array(origins), kernel_array(dirs), u, self.centres, self.radii2, out)
        return out

    def in_footprint(self, points, use):
        out = np.zeros(points.shape[0], bool)
        if len(self) and points.shape[0]:
            _in_boxes(
                kernel_array(points),
                np.ascontiguousarray(use, dtype=bool),
                self.centres,
                self.radii2,
                self.vs,
                self.rots,
                self.inv,
                self.los,
                self.his,
                out,
            )
        return out


def local_rays(patch, origins, dirs, top_extra=0.0):
    """(o_local, d_local, t_enter ≥ 0, t_exit) of rays against the patch box (numba, no temporaries)."""
    n = dirs.shape[0]
    o = np.empty((n, 3))
    d = np.empty((n, 3))
    tn = np.empty(n)
    tf = np.empty(n)
    lo, hi = patch.box(top_extra)
    o_, d_, rot = kernel_array(origins), kernel_array(dirs), kernel_array(patch.rotation)
    _local_slab(o_, d_, patch.v, rot, 1.0 / patch.scale, lo, hi, o, d, tn, tf)
    return o, d, tn, tf


def intersect_patch(patch, o, d, tmin, tmax):
    """Exact first crossing (km along the body ray) of maplet-frame rays with the patch terrain."""
    out = np.empty(o.shape[0])
    if o.shape[0]:
        zlo, zhi = patch.height_range
        _crossings(
            patch.heights,
            patch.valid,
            patch.cell_tops,
            zlo,
            zhi,
            float(patch.qsz),
            kernel_array(o),
            kernel_array(d),
            kernel_array(tmin),
            kernel_array(tmax),
            out,
        )
    return out


class ShapeSurface:
    """A global shape for rendering: ray queries plus shading normals and albedo at hits.

    ``ShapeSurface.from_model(obj)`` accepts an ``IcqShape`` (→ SPC bilinear patches, with its albedo
    column), a ``TriangleMesh`` (→ triangles), or a ready ``PatchShape`` / ``TriangleShape``.
    ``vertex_albedo``: (6, q+1, q+1) for patches, (n,) for triangles, or None (albedo 1).
    """

    def __init__(self, shape, vertex_albedo=None):
        if not isinstance(shape, PatchShape | TriangleShape):
            raise SpcUsageError(f"not a ray-traceable shape: {type(shape).__name__}")
        self.shape = shape
        self.is_patch = isinstance(shape, PatchShape)
        if vertex_albedo is not None:
            vertex_albedo = np.asarray(vertex_albedo, dtype=np.float64)
            want = shape.vertices.shape[:-1]
            if vertex_albedo.shape != want:
                raise SpcUsageError(f"shape albedo must have shape {want}, got {vertex_albedo.shape}")
        self.vertex_albedo = vertex_albedo

    @classmethod
    def from_model(cls, model, *, backend: str = "auto") -> ShapeSurface:
        """Wrap an ICQ shape, a triangle mesh or a geometry shape object."""
        if isinstance(model, ShapeSurface):
            return model
        if isinstance(model, PatchShape | TriangleShape):
            return cls(model)
        verts = getattr(model, "vertices", None)
        if verts is not None and np.ndim(verts) == 4:  # IcqShape
            return cls(PatchShape(verts), getattr(model, "albedo", None))
        if verts is not None and getattr(model, "faces", None) is not None:  # TriangleMesh
            return cls(TriangleShape(model.vertices, model.faces, backend=backend))
        raise SpcUsageError(f"cannot render a shape of type {type(model).__name__}")

    @cached_property
    def cell_size(self) -> float:
        """Typical primitive edge length (km): √(area / number of primitives)."""
        n = self.shape.n_primitives * (1 if self.is_patch else 0.5)
        return math.sqrt(self.shape.area / n)

    @cached_property
    def shadow_shape(self):
        """The shape for shadow rays.  ICQ cells are intersected over [−EPS, 1+EPS]² (EPS = 0.01 as in
        GET_HEIGHTS, erratum 16) so that first hits never slip through seams; on a concave edge the
        1 % flap of the neighbouring cell then shadows the strip of this cell under it.  Shadow rays
        therefore use the same cells with a margin of 1e-7 (a second, lazily built hierarchy)."""
        if self.is_patch:
            return PatchShape(self.shape.vertices, eps=SHADOW_PATCH_EPS)
        return self.shape

    @cached_property
    def vertex_normals(self) -> np.ndarray:
        """Unit outward vertex normals, area-weighted over adjacent cells/faces (seams merged)."""
        if self.is_patch:
            from spctool.formats.icq import icq_merge_map

            v = self.shape.vertices
            q = self.shape.q
            c0, c1, c2, c3 = v[:, :-1, :-1], v[:, :-1, 1:], v[:, 1:, :-1], v[:, 1:, 1:]
            pu = 0.5 * (c1 - c0 + c3 - c2)  # along I
            pv = 0.5 * (c2 - c0 + c3 - c1)  # along J
            cn = -np.cross(pu, pv)  # ∂P/∂I × ∂P/∂J points inward on every ICQ face (spc-formats.md §5.2)
            acc = np.zeros_like(v)
            acc[:, :-1, :-1] += cn
            acc[:, :-1, 1:] += cn
            acc[:, 1:, :-1] += cn
            acc[:, 1:, 1:] += cn
            flat = acc.reshape(-1, 3)
            rep = icq_merge_map(q)
            merged = np.zeros_like(flat)
            np.add.at(merged, rep, flat)
            out = merged[rep]
            out /= np.linalg.norm(out, axis=1, keepdims=True)
            return out.reshape(v.shape)
        tri = self.shape.vertices[self.shape.faces]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        acc = np.zeros_like(self.shape.vertices)
        for k in range(3):
            np.add.at(acc, self.shape.faces[:, k], fn)
        nrm = np.linalg.norm(acc, axis=1, keepdims=True)
        return acc / np.where(nrm == 0, 1.0, nrm)

    def _corner_weights(self, index, u, v):
        if self.is_patch:
            f, i, j = self.shape.cell_fij(index)
            f = f - 1
            idx = (f, j, i), (f, j, i + 1), (f, j + 1, i), (f, j + 1, i + 1)
            w = ((1 - u) * (1 - v), u * (1 - v), (1 - u) * v, u * v)
            return idx, w
        faces = self.shape.faces[index]
        return (faces[:, 0], faces[:, 1], faces[:, 2]), (1 - u - v, u, v)

    def normals(self, index, u, v) -> np.ndarray:
        """Interpolated unit shading normals at hits (cell/face index and parameters)."""
        idx, w = self._corner_weights(index, u, v)
        vn = self.vertex_normals
        n = sum(wk[:, None] * vn[ik] for ik, wk in zip(idx, w))
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def albedo(self, index, u, v) -> np.ndarray:
        """Interpolated vertex albedo at hits (1 when the shape has none)."""
        if self.vertex_albedo is None:
            return np.ones(np.shape(index))
        idx, w = self._corner_weights(index, u, v)
        return sum(wk * self.vertex_albedo[ik] for ik, wk in zip(idx, w))
