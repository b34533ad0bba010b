"""Render a photo of surfaces — a global shape and maplet-like height patches — seen by an SPC camera.

A pure function of (camera, Sun direction, surfaces, options) → image, used by ``spctool render``
and the simulator (:mod:`spctool.sim.simulate`), and register's image-space templates (S16
"Future Retina development": correlation against a ray-traced prediction with cast shadows).  No
files are read or written here.

Surfaces (:mod:`spctool.geometry.surfaces`)
--------------------------------------------
* a **shape** (:class:`ShapeSurface`): an ICQ model as SPC bilinear patches (``spc-formats.md``
  §5; ray algebra of ``spc-algorithms.md`` §2.2 via :class:`spctool.geometry.shape.PatchShape`) or a
  triangle mesh; shading normals are interpolated vertex normals, albedo the ICQ 4th column
  (``spc-formats.md`` §5.1) or 1;
* **height patches** (:class:`HeightPatch`): maplet grids (``spc-formats.md`` §1.3,
  P = V + SCALE·(x·UX + y·UY + h·UZ), x along UX = axis 0, y along UY = axis 1) — real maplets or
  the simulator's fine truth patches.  Rays meet the bilinear terrain exactly
  (:func:`spctool.geometry.heightfield.intersect_rays`); shading normals are the bilinear
  interpolation of SPC's node slopes (HGT2SLP table, ``spc-algorithms.md`` §3.1), albedo the
  bilinear map albedo (``shading="facet"``: the flat triangle's normal; ``shading="gouraud"``: the
  radiance computed at the nodes, as SPC's prediction computes it (``spc-algorithms.md`` §3.2), and
  interpolated bilinearly at the hit, :func:`node_radiance`).

Composition rule: inside a patch's footprint — the column |x|, |y| ≤ QSZ and
h_min − 1 ≤ z ≤ h_max + 1 (cells) — the patch *replaces* the shape.  Each ray takes the nearest of
its patch hits and its shape hit when the shape hit lies outside every footprint; a ray that hits
the shape inside a footprint but misses the patch (a grazing ray over a patch edge) keeps the shape
hit.

Per ray (the pixel's line of sight from :meth:`spctool.geometry.camera.Camera.pixel_to_direction`,
so the SUM pose, the K-matrix and any ``DISTORT=`` model are honoured exactly):

1. nearest surface hit (above);
2. μ₀ = n̂·ŝ, μ = n̂·ê with ê the unit vector from the hit toward the camera (per pixel, not per
   maplet), phase α = ∠(ŝ, ê);
3. reflectance R(μ₀, μ, α) of :mod:`spctool.photometry` (default ``"spc"``: SPC's lunar-Lambert
   without McEwen's factor 2, ``spc-algorithms.md`` §3.2 / erratum 17) times the albedo;
4. cast shadow: a ray toward the Sun (the Sun at infinity, SUM ``SZ``) that meets any patch
   (exact bilinear crossing) or the shape → radiance 0.  Shadow rays leave a patch point from
   just above its terrain (``shadow_offset_cells``) and ignore the shape inside the point's own
   patch column; shadow rays from shape points start ``shadow_lift_shape`` shape cells above the
   shape and may hit it after ``shadow_offset_shape`` shape cells, on ICQ cells whose parameter
   margin is 1e-7 instead of GET_HEIGHTS' 0.01 (whose flaps would shadow strips along concave
   edges; :attr:`ShapeSurface.shadow_shape`).
   (Prediction in SPC has no cast shadows — ``spc-algorithms.md`` §3.2 — this renderer has them
   because it renders the *truth*; ``shadows=False`` switches them off.)

Pixels are averaged over ``supersample``² sub-pixel rays on a regular grid; ``coverage`` is the
fraction of sub-rays that hit a surface (sky contributes 0).  Pixels are SPC pixels (1-based,
centres at integers, ``spc-formats.md`` §0.4): the image array is ``radiance[line − l0, sample − s0]``.

Speed: scenes of patches without a shape (register's image-space templates) take a fused per-ray
kernel that equals the batch functions :func:`trace` → :func:`shadowed` → :func:`shade` up to rounding
(≤ 1e-12 relative; the "fused path" section below), runs on the calling thread for small windows and
reuses each patch's packed maps between renders (``benchmarks/bench_render.py``).  Its shadow rays
take exact shortcuts (issue 17): a rise-aware horizon bound ends the march, a ray that provably
clears its own cell and that bound is lit without one, and so is a ray that rises faster than every
slope near its hit until it is above the highest cell ahead (``_render(..., fast=False)`` is the plain
march, the reference; ``tests/test_render_fast.py``).  With ``visibility="raster"`` a one-patch window
finds each sub-ray's cell by drawing the patch with the camera's forward model (issue 17: "render
forward") and solves the crossing there, where a local slope bound proves it is the first
(:func:`_raster_cells`; the same pictures, ``tests/test_render_raster.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from spctool.errors import SpcUsageError
from spctool.geometry import heightfield
from spctool.geometry._patchkernels import SHAPE, SKY, _fused_rays, predict_cells, usable_cells
from spctool.geometry._rasterkernels import (
    LAW_CODES,
    bin_subrays,
    gouraud_subrays,
    node_geometry,
    shade_subrays,
    terrain_cells,
)
from spctool.geometry.heightfield import kernel_array
from spctool.geometry.surfaces import (
    HeightPatch,
    PatchSet,
    ShapeSurface,
    finite_vec3,
    intersect_patch,
    local_rays,
)
from spctool.photometry import ALPHA0_DEG, FIXED_BETA, phase_angle_deg, reflectance
from spctool.photometry import MODELS as PHOTOMETRY_MODELS
from spctool.stages.render_modes import SHADINGS, VISIBILITIES

__all__ = [
    "RenderOptions",
    "Rendering",
    "SurfaceHits",
    "render",
    "node_radiance",
    "predicted_cells",
    "trace",
    "shade",
    "shadowed",
    "cull_patches",
    "sky",
    "SKY",
    "SHAPE",
    "SHADINGS",
]


# SHADINGS (shading normals of height patches) and VISIBILITIES (how a one-patch window finds each
# sub-ray's terrain) of :class:`RenderOptions` are named in spctool.stages.render_modes (an options
# check imports no renderer)

# ------------------------------------------------------------------------------------------------
# options and results
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RenderOptions:
    """How to render (module docstring).

    ``photometry``: a model of :mod:`spctool.photometry` (``spc``, ``mcewen``, ``fixed``, ``lambert``);
    ``supersample``: n for n×n sub-pixel rays; ``shadows``: trace cast shadows; ``use_albedo``: multiply
    by the surface albedo; ``chunk``: rays per batch (memory bound); ``shadow_offset_cells``: height
    above a patch's terrain where its shadow rays start (cells); ``shadow_offset_shape``: distance, in
    shape cells, before a shadow ray from a shape point may hit the shape; ``shadow_lift_shape``: such
    rays start this far (shape cells) above the shape along its shading normal.  ``shading``: patch
    shading normals ``"smooth"`` (bilinear interpolation of SPC's node slopes) or ``"facet"`` (the flat
    triangle under the hit, two per cell; albedo stays bilinear), or ``"gouraud"``: the radiance
    R·albedo computed at the nodes (each node's slopes, its view direction; :func:`node_radiance`) and
    interpolated bilinearly at the hit, the brightness interpolated instead of the normals (cast
    shadows as the others; shape hits shaded as always).  ``ray_inverse``: pixel → ray by
    ``"newton"`` per sub-ray (:meth:`Camera.pixel_to_direction`) or ``"grid"`` (exact inverses on a
    coarse grid, interpolated bicubically where that is exact to 1e-7 px, else one Newton step per
    sub-ray: :meth:`Camera.pixel_to_direction_lattice`, the same rays to ~1e-7 px).  ``threads``:
    Python threads a large patch-only window is split over (None: numba's count; register's templates
    use 1 and parallelise across landmarks instead).  ``visibility`` (a window of one patch without a
    shape): ``"march"`` steps every sub-ray through the grid from the top of the relief (the
    reference); ``"raster"`` draws the patch's cells into a depth buffer with the camera's forward model
    and solves each sub-ray's crossing in the cell drawn there where a local slope bound proves it is
    the first, marching the others (walls, overlaps, twisted cells, the drawn border) — the same
    pictures as the march (:func:`_raster_cells`, ``tests/test_render_raster.py``).
    """

    photometry: str = "spc"
    supersample: int = 1
    shadows: bool = True
    use_albedo: bool = True
    chunk: int = 1 << 18
    shadow_offset_cells: float = 1e-3
    shadow_offset_shape: float = 0.02
    shadow_lift_shape: float = 0.002
    shading: str = "smooth"
    ray_inverse: str = "newton"
    threads: int | None = None
    visibility: str = "march"

    def __post_init__(self):
        if self.visibility not in VISIBILITIES:
            raise SpcUsageError(
                f"visibility must be one of {', '.join(VISIBILITIES)}, got {self.visibility!r}"
            )
        if self.shading not in SHADINGS:
            raise SpcUsageError(f"shading must be one of {', '.join(SHADINGS)}, got {self.shading!r}")
        if self.ray_inverse not in ("newton", "grid"):
            raise SpcUsageError(f"ray_inverse must be newton or grid, got {self.ray_inverse!r}")
        if self.photometry not in PHOTOMETRY_MODELS:
            raise SpcUsageError(
                f"unknown photometric model {self.photometry!r}; "
                f"expected one of {', '.join(PHOTOMETRY_MODELS)}"
            )
        if not 1 <= int(self.supersample) <= 16:
            raise SpcUsageError("supersample must be 1 … 16")
        if int(self.chunk) < 1:
            raise SpcUsageError("chunk must be >= 1")


@dataclass
class SurfaceHits:
    """Nearest hits of a batch of rays (:func:`trace`).

    ``surface``: SKY (−2), SHAPE (−1) or the patch index; ``t`` km along the unit direction (inf for
    sky); ``point`` body km; ``normal`` unit shading normal; ``albedo``; ``local``: maplet-frame (x, y, z)
    cells for patch hits (NaN otherwise).
    """

    surface: np.ndarray
    t: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    local: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.surface != SKY


@dataclass
class Rendering:
    """A rendered image window: ``radiance[line − l0, sample − s0]`` = mean of R·albedo over sub-rays.

    ``coverage``: fraction of sub-rays hitting a surface; ``shadow``: fraction of sub-rays on a lit-facing
    surface (μ₀ > 0) but in cast shadow; ``surface``: the surface id of each pixel's first sub-ray;
    ``window`` = (s0, s1, l0, l1), 1-based inclusive.
    """

    radiance: np.ndarray
    coverage: np.ndarray
    shadow: np.ndarray
    surface: np.ndarray
    window: tuple[int, int, int, int]
    options: RenderOptions = field(default_factory=RenderOptions)
    #: ``render(..., return_cells=True)`` of one patch without a shape: (lines·nss, samples·nss) int64,
    #: the terrain cell i·(n − 1) + j each sub-ray hit (−2: none) — a later render's ``cells``; else None
    cells: np.ndarray | None = None
    #: with ``cells``: (lines·nss, samples·nss, 2) float64, the grid position (u, w) of each sub-ray's hit
    #: (index coordinates, NaN: none), from which :func:`predicted_cells` places a later render's rays
    positions: np.ndarray | None = None

    @property
    def mask(self) -> np.ndarray:
        """Pixels where any sub-ray hit a surface."""
        return self.coverage > 0


# ------------------------------------------------------------------------------------------------
# tracing
# ------------------------------------------------------------------------------------------------


def trace(
    origins, directions, shape: ShapeSurface | None = None, patches=(), *, albedo_fn=None, shading="smooth"
) -> SurfaceHits:
    """Nearest hits of rays (origins (N, 3) or (3,) body km, unit directions (N, 3)) on the shape and
    the patches (composition rule of the module docstring), with shading normals and albedo.

    ``albedo_fn(points) -> albedo`` replaces the shape's own albedo at shape hits (the simulator paints
    its terrain albedo this way).  ``shading="facet"``: patch normals of the flat triangle under each hit
    (:meth:`HeightPatch.facet_slopes`) instead of the interpolated node slopes.
    """
    d = kernel_array(directions)
    o = kernel_array(np.broadcast_to(np.asarray(origins, dtype=np.float64), d.shape))
    pset = PatchSet.of(patches)
    n = d.shape[0]
    surface = np.full(n, SKY, dtype=np.int32)
    t = np.full(n, np.inf)
    local = np.full((n, 3), np.nan)
    # -- patches: nearest patch hit per ray
    near = pset.near(o, d)
    for k, patch in enumerate(pset.patches):
        sel = np.flatnonzero(near[:, k])
        if sel.size == 0:
            continue
        ol, dl, tn, tf = local_rays(patch, o[sel], d[sel])
        tmax = np.minimum(tf, t[sel])
        ok = tmax >= tn
        tp = np.full(sel.size, np.nan)
        tp[ok] = intersect_patch(patch, ol[ok], dl[ok], tn[ok], tmax[ok])
        good = np.isfinite(tp) & (tp < t[sel])
        idx = sel[good]
        t[idx] = tp[good]
        surface[idx] = k
        local[idx] = ol[good] + tp[good, None] * dl[good]
    # -- shape
    take = None
    if shape is not None:
        res = shape.shape.first_hit(o, d)
        in_fp = pset.in_footprint(res.point, res.hit)
        take = res.hit & (((~in_fp) & (res.t < t)) | (surface == SKY))
        t[take] = res.t[take]
        surface[take] = SHAPE
    # -- points, normals, albedo
    point = np.full((n, 3), np.nan)
    normal = np.full((n, 3), np.nan)
    albedo = np.zeros(n)
    for k, patch in enumerate(pset.patches):
        m = np.flatnonzero(surface == k)
        if m.size == 0:
            continue
        z, hx, hy, alb = patch.interpolate(local[m, 0], local[m, 1])
        if shading == "facet":
            hx, hy = patch.facet_slopes(local[m, 0], local[m, 1])
        local[m, 2] = z  # on the terrain (the crossing is exact; this removes rounding)
        point[m] = patch.to_body(local[m])
        normal[m] = heightfield.normals_body(hx, hy, patch.ux, patch.uy, patch.uz)
        albedo[m] = alb
    if take is not None:
        m = np.flatnonzero(take)
        if m.size:
            point[m] = res.point[m]
            normal[m] = shape.normals(res.index[m], res.u[m], res.v[m])
            albedo[m] = (
                albedo_fn(point[m])
                if albedo_fn is not None
                else shape.albedo(res.index[m], res.u[m], res.v[m])
            )
    return SurfaceHits(surface, t, point, normal, albedo, local)


def shadowed(
    hits: SurfaceHits,
    sun,
    shape: ShapeSurface | None = None,
    patches=(),
    *,
    options: RenderOptions = RenderOptions(),
    which=None,
) -> np.ndarray:
    """True where the ray from a hit toward the Sun meets a patch or the shape (cast shadow).

    ``which`` (bool (N,)) limits the test to some hits (others are reported False).
    """
    sun = finite_vec3(sun, "sun")
    sun = sun / np.linalg.norm(sun)
    pset = PatchSet.of(patches)
    n = hits.surface.shape[0]
    sel = np.flatnonzero(hits.hit if which is None else (hits.hit & which))
    out = np.zeros(n, bool)
    if sel.size == 0:
        return out
    pts = kernel_array(hits.point[sel])
    surf = hits.surface[sel]
    dirs = kernel_array(np.broadcast_to(sun, pts.shape))
    blocked = np.zeros(sel.size, bool)
    t_shape_min = np.zeros(sel.size)
    if shape is not None:
        t_shape_min[:] = options.shadow_offset_shape * shape.cell_size
        on_shape = surf == SHAPE
        if on_shape.any():  # lift off the shape (rounding, and mm mismatches at patch borders)
            pts[on_shape] += (options.shadow_lift_shape * shape.cell_size) * hits.normal[sel[on_shape]]
    near = pset.near(pts, dirs)
    for k, patch in enumerate(pset.patches):
        own = surf == k
        cand = np.flatnonzero((near[:, k] | own) & ~blocked)
        if cand.size == 0:
            continue
        zlo, zhi = patch.height_range
        # one slab pass against the box raised by the relief: for the patch's own points its exit is
        # where the shadow ray leaves the patch column (the shape is replaced by the patch inside it)
        ol, dl, tn, tf = local_rays(patch, pts[cand], dirs[cand], top_extra=(zhi - zlo) + 1.0)
        mine = own[cand]
        if mine.any():
            ol[mine] = hits.local[sel[cand[mine]]]
            ol[mine, 2] += options.shadow_offset_cells
            tn[mine] = 0.0
            t_shape_min[cand[mine]] = np.maximum(t_shape_min[cand[mine]], tf[mine])
        ok = tf >= tn
        tp = np.full(cand.size, np.nan)
        tp[ok] = intersect_patch(patch, ol[ok], dl[ok], tn[ok], tf[ok])
        blocked[cand[np.isfinite(tp)]] = True
    if shape is not None:
        rest = np.flatnonzero(~blocked)
        if rest.size:
            blocked[rest] = shape.shadow_shape.any_hit(pts[rest], dirs[rest], t_min=t_shape_min[rest])
    out[sel] = blocked
    return out


def shade(
    hits: SurfaceHits, directions, sun, *, options: RenderOptions = RenderOptions(), shadow=None
) -> np.ndarray:
    """Radiance R(μ₀, μ, α)·albedo of each hit (0 for sky and, when given, where ``shadow`` is True)."""
    sun = finite_vec3(sun, "sun")
    sun = sun / np.linalg.norm(sun)
    d = np.asarray(directions, dtype=np.float64)
    e = -d / np.linalg.norm(d, axis=1, keepdims=True)  # toward the camera
    out = np.zeros(hits.surface.shape[0])
    m = np.flatnonzero(hits.hit)
    if m.size == 0:
        return out
    nrm = hits.normal[m]
    mu0 = nrm @ sun
    mu = np.sum(nrm * e[m], axis=1)
    alpha = phase_angle_deg(sun, e[m])
    r = reflectance(mu0, mu, alpha, options.photometry)
    if options.use_albedo:
        r = r * hits.albedo[m]
    if shadow is not None:
        r = np.where(shadow[m], 0.0, r)
    out[m] = r
    return out


def _window(camera, window):
    if window is None:
        return 1, camera.npx, 1, camera.nln
    s0, s1, l0, l1 = (int(v) for v in window)
    if not (1 <= s0 <= s1 and 1 <= l0 <= l1):
        raise SpcUsageError(f"render window must satisfy 1 <= s0 <= s1 and 1 <= l0 <= l1, got {window}")
    return s0, s1, l0, l1


def render(
    camera,
    sun,
    shape=None,
    patches=(),
    options: RenderOptions | None = None,
    *,
    window=None,
    albedo_fn=None,
    progress=None,
    cells=None,
    return_cells: bool = False,
) -> Rendering:
    """Render the pixels of ``window`` = (s0, s1, l0, l1) (1-based, inclusive; default the whole photo).

    ``camera``: a :class:`spctool.geometry.camera.Camera` (pose and intrinsics); ``sun``: body→Sun
    direction (SUM ``SZ``); ``shape``: an ICQ/mesh/geometry shape or :class:`ShapeSurface` (or None);
    ``patches``: :class:`HeightPatch` objects or maplets.

    Without a shape the rays run through one fused kernel (:func:`_patch_ray`; one thread below
    :data:`PARALLEL_MIN_RAYS` rays) that equals :func:`trace` → :func:`shadowed` → :func:`shade` up to
    rounding (≤ 1e-12 relative, ``tests/test_render.py``).  ``progress(n)`` is called with the number
    of lines done after each batch of rays.

    ``cells``: where each sub-ray is expected to hit the single patch — the :attr:`Rendering.cells` of an
    earlier render over the same window and supersampling, with any camera, or, better,
    :func:`predicted_cells` from it (register's templates at another sub-pixel phase): each sub-ray's
    crossing is first sought in that cell, and taken from there only where a local slope bound proves
    the ray crossed nothing before (as with the raster's cells, ``visibility``); elsewhere the march.
    The rendering is the same to the last bit with or without it (``tests/test_render_raster.py``); a
    hint of another shape is ignored.  ``return_cells``: keep each sub-ray's hit cell in
    :attr:`Rendering.cells` and its grid position in :attr:`Rendering.positions` (one patch without a
    shape; 24 bytes per sub-ray, so asked for, not kept for every photo).
    """
    return _render(
        camera, sun, shape, patches, options, window, albedo_fn, fused=True, progress=progress, hint=cells,
        keep_cells=return_cells,
    )  # fmt: skip


# ------------------------------------------------------------------------------------------------
# fused path: patches without a shape (register's image-space templates, patch-only photos); its
# kernels, and why they look as they do, are spctool.geometry._patchkernels
# ------------------------------------------------------------------------------------------------

#: rays from which :func:`_trace_fused` splits a window over threads (when numba has more than one)
PARALLEL_MIN_RAYS = 1 << 15


def _trace_fused(
    origin, dirs, ok, sun_lit, sun, shadows, offset, arrays, threads=None, facet=False, cand=None,
    cells=None, pos=None,
):  # fmt: skip
    """(surface, geom, shadow) of sub-rays by :func:`_fused_rays` (``cand``: the raster's cell of each
    sub-ray, :func:`terrain_cells`, or an earlier render's; None: march them all; ``cells``: an int64
    array that gets each hit's cell, or None; ``pos``: an (n, 2) float64 array that gets each hit's grid
    position, or None); windows of at least
    :data:`PARALLEL_MIN_RAYS` rays are split over ``threads`` (default: numba's thread count) Python
    threads (the kernel releases the GIL; no parallel compilation, no thread pool for small windows)."""
    n = dirs.shape[0]
    surface = np.empty(n, np.int32)
    geom = np.empty((n, 4))
    sh = np.empty(n, bool)
    origin, dirs, ok = kernel_array(origin), kernel_array(dirs), kernel_array(ok, np.bool_)
    sun_lit, sun = kernel_array(sun_lit), kernel_array(sun)
    shadows, offset, facet = bool(shadows), float(offset), bool(facet)
    cand = _NO_CELLS if cand is None else kernel_array(cand, np.int64)
    cells = _NO_CELLS if cells is None else cells
    pos = _NO_POS if pos is None else pos
    if n >= PARALLEL_MIN_RAYS:  # numba's count asked only when it matters (spctool.threads)
        from spctool.threads import numba_threads

        threads = numba_threads() if threads is None else int(threads)
    if n < PARALLEL_MIN_RAYS or threads < 2:  # the calling thread, whole arrays (no views to make)
        _fused_rays(
            origin, dirs, ok, sun_lit, sun, shadows, offset, facet, *arrays, cand, surface, geom, sh, cells,
            pos,
        )  # fmt: skip
        return surface, geom, sh

    def run(a, b):
        _fused_rays(
            origin,
            dirs[a:b],
            ok[a:b],
            sun_lit,
            sun,
            shadows,
            offset,
            facet,
            *arrays,
            cand[a:b] if cand.shape[0] else cand,
            surface[a:b],
            geom[a:b],
            sh[a:b],
            cells[a:b] if cells.shape[0] else cells,
            pos[a:b] if pos.shape[0] else pos,
        )

    from concurrent.futures import ThreadPoolExecutor

    cuts = np.linspace(0, n, threads + 1).astype(np.intp)
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(run, cuts[:-1], cuts[1:]))
    return surface, geom, sh


#: "no raster cells" for :func:`_fused_rays` (march every sub-ray)
_NO_CELLS = np.empty(0, np.int64)
#: "no hit positions wanted" for :func:`_fused_rays`
_NO_POS = np.empty((0, 2))


def _raster_cells(camera, patch: HeightPatch, s0, l0, width, height, nss):
    """(height·nss, width·nss) int64: :func:`terrain_cells` of ``patch`` on the window's sub-ray lattice
    (sub-ray column c looks through sample s0 + (c + ½)/nss − ½, row r through line l0 + (r + ½)/nss − ½,
    as :func:`_render` lays them out)."""
    n = patch.heights.shape[0]
    pts = patch.raster_points
    smp, lin, front = camera.project_with_mask(pts)
    xs = (smp - (s0 - 0.5)) * nss - 0.5
    ys = (lin - (l0 - 0.5)) * nss - 0.5
    # depth along the line of sight to V: along any one sub-ray it grows with the distance
    axis = patch.v - camera.position
    depth = pts @ (axis / np.linalg.norm(axis))
    k = n * n
    if not (front.all() and np.isfinite(xs).all() and np.isfinite(ys).all()):
        # a node or a wall's foot behind the camera (never for a template): march the whole window
        return np.full((height * nss, width * nss), -2, np.int64)
    out = np.empty((height * nss, width * nss), np.int64)
    terrain_cells(
        xs[:k].reshape(n, n), ys[:k].reshape(n, n), depth[:k].reshape(n, n), patch.valid,
        patch.wall_index, np.column_stack([xs[k:], ys[k:], depth[k:]]), out,
    )  # fmt: skip
    return out


def _fused_chunk(
    origin, dirs, ok, sun, pset: PatchSet, options: RenderOptions, fast=True, cand=None, cells=None,
    pos=None,
):  # fmt: skip
    """(hit, radiance, shadow, surface) of sub-rays through patches only, by the fused kernel (``fast=False``:
    without the exact shadow shortcuts, as the reference for them; ``cand``, ``cells``:
    :func:`_trace_fused`'s)."""
    sun_shade = sun / np.linalg.norm(sun)  # shadowed() and shade() normalise once more
    gouraud = options.shading == "gouraud"
    if gouraud and pos is None:  # the hits' grid positions, where the node radiances are interpolated
        pos = np.empty((dirs.shape[0], 2))
    surface, geom, sh = _trace_fused(
        origin,
        dirs,
        ok,
        sun,
        sun_shade,
        options.shadows,
        options.shadow_offset_cells,
        # the Sun's bounds only serve the cast-shadow test (without it: +inf, computed once per set)
        pset.fused_arrays(sun_shade if options.shadows else None, fast),
        threads=options.threads,
        facet=options.shading == "facet",
        cand=cand,
        cells=cells,
        pos=pos,
    )
    hit = surface != SKY
    # shade(): the photometric law of spctool.photometry on (μ₀, μ, α), times the albedo — on every
    # sub-ray (the kernel leaves sky dark: 0), element by element the arithmetic of the hits alone
    r = np.empty(geom.shape[0])
    if gouraud:
        planes, ns = _node_radiance_planes(pset, origin, sun_shade, options)
        r[:] = 0.0  # sky
        gouraud_subrays(pos, surface, sh, planes, ns, r)
        return hit, r, sh, surface
    law = LAW_CODES[options.photometry]
    shade_subrays(geom, sh, law, FIXED_BETA, ALPHA0_DEG, bool(options.use_albedo), r)
    return hit, r, sh, surface


def node_radiance(patch: HeightPatch, position, sun, options: RenderOptions | None = None) -> np.ndarray:
    """(n, n) radiance of every node of ``patch`` for ``shading="gouraud"``: R(μ₀, μ, α) of
    ``options.photometry`` with the node's shading normal (its node slopes, the ones ``"smooth"``
    interpolates: :attr:`HeightPatch.slopes`), the unit Sun ``sun`` and the unit vector from the node to
    ``position`` (the camera, body km), times the node's albedo when ``options.use_albedo``; 0 where
    the node is not valid.  What :func:`spctool.stages.predict.predict` computes at the nodes (SPC's
    prediction, with a view direction per node)."""
    options = options or RenderOptions()
    hx, hy, _ = patch.slopes
    s = np.asarray(sun, dtype=np.float64)
    n = hx.size
    geom = np.empty((n, 4))
    node_geometry(
        kernel_array(hx).reshape(-1), kernel_array(hy).reshape(-1), kernel_array(patch.rotation),
        kernel_array(patch.node_points).reshape(-1, 3), kernel_array(position),
        kernel_array(s / np.linalg.norm(s)), geom,
    )  # fmt: skip
    geom[:, 3] = patch.albedo.reshape(-1)
    r = np.empty(n)
    law = LAW_CODES[options.photometry]
    shade_subrays(geom, np.zeros(n, bool), law, FIXED_BETA, ALPHA0_DEG, bool(options.use_albedo), r)
    return np.where(patch.valid, r.reshape(hx.shape), 0.0)


def _node_radiance_planes(pset: PatchSet, origin, sun, options: RenderOptions):
    """(planes (P, n_max, n_max), ns (P,)): :func:`node_radiance` of every patch of ``pset`` (zero-padded),
    kept on the set for one camera position, Sun and photometry (a template re-rendered at another
    sub-pixel phase moves the camera's CTR, not its position: one computation per landmark and pose)."""
    key = (
        tuple(np.asarray(origin, dtype=np.float64).tolist()),
        tuple(np.asarray(sun, dtype=np.float64).tolist()),
        options.photometry,
        bool(options.use_albedo),
    )
    got = pset._node_radiance
    if got is None or got[0] != key:
        ns = np.array([p.heights.shape[0] for p in pset.patches], np.int64)
        nmax = int(ns.max())
        planes = np.zeros((len(pset.patches), nmax, nmax))
        for k, p in enumerate(pset.patches):
            planes[k, : ns[k], : ns[k]] = node_radiance(p, origin, sun, options)
        got = pset._node_radiance = (key, planes, ns)
    return got[1], got[2]


def _gouraud_hits(hits: SurfaceHits, pset: PatchSet, origin, sun, options: RenderOptions, sh, r) -> None:
    """``shading="gouraud"`` on the reference path (:func:`trace` → :func:`shade`): the patch hits' ``r``
    replaced by the node radiances interpolated at their maplet-frame position (0 in cast shadow)."""
    m = np.flatnonzero(hits.surface >= 0)
    if m.size == 0:
        return
    planes, ns = _node_radiance_planes(pset, origin, sun, options)
    pos = np.empty((m.size, 2))
    q = ((ns - 1) // 2)[hits.surface[m]]
    pos[:, 0] = hits.local[m, 0] + q
    pos[:, 1] = hits.local[m, 1] + q
    out = r[m].copy()
    gouraud_subrays(pos, hits.surface[m].astype(np.int64), np.asarray(sh, bool)[m], planes, ns, out)
    r[m] = out


def _render(
    camera, sun, shape, patches, options, window, albedo_fn, *, fused: bool, progress=None, fast=True,
    hint=None, keep_cells=False,
) -> Rendering:  # fmt: skip
    """:func:`render`; ``fused=False`` forces trace → shadowed → shade (the reference for the fused path),
    ``fast=False`` the fused path without its exact shortcuts (the reference for them)."""
    options = options or RenderOptions()
    sun = finite_vec3(sun, "sun")
    sun = sun / np.linalg.norm(sun)
    surf = None if shape is None else ShapeSurface.from_model(shape)
    plist = PatchSet.of(patches)
    use_fused = fused and surf is None and len(plist) > 0
    s0, s1, l0, l1 = _window(camera, window)
    nss = int(options.supersample)
    offs = (np.arange(nss) + 0.5) / nss - 0.5
    width = s1 - s0 + 1
    height = l1 - l0 + 1
    # every line of the window is binned below (each chunk's lines, every sample)
    rad = np.empty((height, width))
    cov = np.empty((height, width))
    shd = np.empty((height, width))
    sid = np.empty((height, width), dtype=np.int16)
    rays_per_line = width * nss * nss
    lines_per_chunk = max(1, int(options.chunk) // rays_per_line)
    one = use_fused and len(plist) == 1
    # the fused kernel writes every sub-ray's cell (−2 without a hit) and position (NaN without one)
    out_cells = np.empty((height * nss, width * nss), np.int64) if one and keep_cells else None
    out_pos = np.empty((height * nss, width * nss, 2)) if one and keep_cells else None
    cells = None
    if one and hint is not None and np.shape(hint) == (height * nss, width * nss):
        cells = _usable_hint(hint, plist.patches[0].heights.shape[0])
    elif one and options.visibility == "raster":
        cells = _raster_cells(camera, plist.patches[0], s0, l0, width, height, nss)
    origin = camera.position
    samples = np.arange(s0, s1 + 1, dtype=np.float64)
    sub_samples = (samples[:, None] + offs[None, :]).reshape(-1)
    for a in range(0, height, lines_per_chunk):
        b = min(height, a + lines_per_chunk)
        lines = np.arange(l0 + a, l0 + b, dtype=np.float64)
        # sub-ray grid: (line, sub-line, sample, sub-sample), i.e. the lattice sub-lines × sub-samples
        shape4 = (b - a, nss, width, nss)
        sub_lines = (lines[:, None] + offs[None, :]).reshape(-1)
        if options.ray_inverse == "grid":
            dirs = camera.pixel_to_direction_lattice(sub_samples, sub_lines).reshape(-1, 3)
        else:
            ll, ss = np.broadcast_arrays(sub_lines[:, None], sub_samples[None, :])
            dirs = camera.pixel_to_direction(ss.reshape(-1), ll.reshape(-1))
        if use_fused:  # the kernel makes rays without a finite direction sky
            ok = np.ones(dirs.shape[0], bool)
            cand = None if cells is None else cells[a * nss : b * nss].reshape(-1)
            got = None if out_cells is None else out_cells[a * nss : b * nss].reshape(-1)
            got_pos = None if out_pos is None else out_pos[a * nss : b * nss].reshape(-1, 2)
            hit, r, sh, surface = _fused_chunk(
                origin, dirs, ok, sun, plist, options, fast, cand, got, got_pos
            )  # fmt: skip
        else:
            ok = np.all(np.isfinite(dirs), axis=1)
            hits = trace(
                origin,
                np.where(ok[:, None], dirs, np.array([0.0, 0.0, 1.0])),
                surf,
                plist,
                albedo_fn=albedo_fn,
                shading=options.shading,
            )
            if not ok.all():
                hits.surface[~ok] = SKY
            lit_facing = hits.hit & (np.sum(np.nan_to_num(hits.normal) * sun, axis=1) > 0)
            sh = (
                shadowed(hits, sun, surf, plist, options=options, which=lit_facing)
                if options.shadows
                else np.zeros(hits.surface.shape[0], bool)
            )
            r = shade(hits, dirs, sun, options=options, shadow=sh)
            if options.shading == "gouraud":
                _gouraud_hits(hits, plist, origin, sun, options, sh, r)
            hit, surface = hits.hit, hits.surface
        if progress is not None:
            progress(b - a)
        if nss < 8:  # pixel means of the sub-rays, bit for bit the NumPy means below
            bin_subrays(r, hit, sh, surface, nss, rad[a:b], cov[a:b], shd[a:b], sid[a:b])
            continue
        k = nss * nss
        sid[a:b] = surface.reshape(shape4)[:, 0, :, 0]
        rad[a:b] = r.reshape(shape4).mean(axis=(1, 3))
        cov[a:b] = hit.reshape(shape4).sum(axis=(1, 3)) / k
        shd[a:b] = sh.reshape(shape4).sum(axis=(1, 3)) / k
    return Rendering(rad, cov, shd, sid, (s0, s1, l0, l1), options, out_cells, out_pos)


def predicted_cells(
    previous: Rendering, shift, n: int, shape=None, supersample: int | None = None
) -> np.ndarray | None:
    """The cells a render of the same single patch at the same supersampling is expected to hit (its
    ``cells`` hint), from ``previous`` (a ``return_cells`` render): this render's pixel (sample, line) of
    its window sits where ``previous``'s window pixel + ``shift`` (samples, lines; fractional) sat — e.g.
    a template at another sub-pixel phase f of the same camera and window: its rays through p − f are
    the earlier ones' through p + (f_prev − f), shift f_prev − f.  ``n``: the patch's nodes per side;
    ``shape``: this render's (lines·nss, samples·nss) when its window differs (default ``previous``'s).
    The hit positions interpolated there (:func:`predict_cells`) find the right cell for most rays
    whatever the shift, where the earlier render's own cells (the shift rounded) miss about half of
    them at a quarter pixel (each miss costs a march; the rendering is the same either way).
    ``supersample``: this render's sub-rays per pixel axis m when they differ from ``previous``'s k
    (e.g. a 2 × 2 template after a one-ray draft): sub-ray c of this render looks through
    s0 + (c + ½)/m − ½ − f, which ``previous``'s lattice holds at c·k/m + k/(2m) − ½ + k·shift
    (``shape`` then required).  None when ``previous`` kept no positions or the shift is not finite."""
    pos = previous.positions
    if pos is None or not np.all(np.isfinite(shift)):
        return None
    k = int(previous.options.supersample)
    m = k if supersample is None else int(supersample)
    if shape is None and m != k:
        raise ValueError("predicted_cells: another supersampling needs the output shape")
    out = np.empty(pos.shape[:2] if shape is None else tuple(int(v) for v in shape), np.int64)
    if m == k:
        predict_cells(pos, float(shift[0]) * k, float(shift[1]) * k, int(n), out)
    else:
        step, base = k / m, k / (2.0 * m) - 0.5
        predict_cells(pos, base + float(shift[0]) * k, base + float(shift[1]) * k, int(n), out, step)
    return out


def _usable_hint(hint, n: int) -> np.ndarray:
    """An earlier render's cells as ``cand`` for :func:`_fused_rays`: a cell index of this grid where it
    is one, else −2 (march; never −1, the raster's "no terrain here", which only the raster of this very
    camera can claim)."""
    h = np.asarray(hint, dtype=np.int64)
    out = np.empty(h.shape, np.int64)
    usable_cells(h.reshape(-1), (n - 1) * (n - 1), out.reshape(-1))
    return out


def cull_patches(camera, patches, window=None, margin_px: float = 4.0) -> list:
    """The patches whose bounding sphere can appear in the window (default the whole photo).

    A cheap pre-selection for working directories with many maplets: the sphere around each patch box
    is projected (centre pixel ± its angular radius in pixels, ×1.2 for distortion, + ``margin_px``);
    patches behind the camera or off the window are dropped; a camera inside a sphere keeps it.
    """
    plist = [p if isinstance(p, HeightPatch) else HeightPatch.from_maplet(p) for p in patches]
    if not plist:
        return []
    s0, s1, l0, l1 = _window(camera, window)
    pset = PatchSet(plist)
    c = pset.centres
    rad = np.sqrt(pset.radii2)
    rel = c - camera.position
    dist = np.linalg.norm(rel, axis=1)
    ahead = rel @ camera.boresight
    smp, lin = camera.project(c)
    r_px = 1.2 * np.arcsin(np.clip(rad / np.maximum(dist, 1e-300), 0, 1)) / camera.ifov + margin_px
    ok = (
        (smp + r_px >= s0)
        & (smp - r_px <= s1)
        & (lin + r_px >= l0)
        & (lin - r_px <= l1)
        & (ahead > 0)
        & np.isfinite(smp)
        & np.isfinite(lin)
    )
    # spheres reaching behind the camera plane project badly: keep them when they could be in view
    near = (dist <= rad) | ((ahead <= rad) & (ahead > -rad))
    keep = ok | near
    return [p for p, k in zip(plist, keep) if k]


def sky(camera, window=None) -> Rendering:
    """An empty rendering (nothing hit) of the window — handy for callers that skip empty views."""
    s0, s1, l0, l1 = _window(camera, window)
    shp = (l1 - l0 + 1, s1 - s0 + 1)
    return Rendering(
        np.zeros(shp), np.zeros(shp), np.zeros(shp), np.full(shp, SKY, np.int16), (s0, s1, l0, l1)
    )
