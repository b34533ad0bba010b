"""Global shape models and ray queries: first hit, any hit (shadow/occlusion) and visibility.

Two representations share one contract (:class:`HitResult`, ``first_hit``, ``any_hit``,
``bounding_box``, ``max_diameter``, ``volume``, ``area``):

* :class:`PatchShape` — an ICQ shape (``spc-formats.md`` §5) whose cells are **bilinear patches**
  through corners 0 = (I, J), 1 = (I+1, J), 2 = (I, J+1), 3 = (I+1, J+1).  Rays are intersected with
  SPC's own algebra (L15 §3.2.1, Eq. 3.21–3.35; ``spc-algorithms.md`` §2.2 "Bilinear-patch inversion
  in detail" and "Which root"), with the seed errata 13–16 of ``spc-algorithms.md`` §11 applied:

  - erratum 13: the test is on \\|A\\| and SPC proceeds only if B² > 4AC strictly; the root is
    (−B + sign(B)·√D)/(2A), computed here as the stable C/q with q = −(B + sign(B)·√D)/2
    (L15's unconditional "−B + √D" picks the wrong root for B < 0);
  - erratum 14: the small-\\|A\\| branch −C/B − AC²/B³ is the first-order series of that same root,
    so C/q needs no branch (:func:`patch_intersect_reference` keeps SPC's literal branch).  SPC's
    switch is on the *absolute* \\|A\\| ≤ 1e-8 (km²), so for metre-size cells the series is used
    with ε = 4AC/B² of ~1e-2 and is off by (C/B)·ε²/8 (~1e-5 in ι₀); C/q is exact there;
  - erratum 15: γ₀ comes from the x or y equation with the larger \\|denominator\\|,
    \\|X₂ + X₃ι₀\\| versus \\|Y₂ + Y₃ι₀\\| (L15 Eq. 3.32 prints X₂ − X₃ι₀);
  - erratum 16: parameters are accepted in [−EPS, 1 + EPS] with EPS = 0.01 (GET_HEIGHTS), not [0, 1].

  L15's two pre-filters are replaced by a bounding-volume hierarchy: the d_max screen (Eq. 3.24–3.25)
  only discards cells that cannot be hit, and the corner cross-product screen (Eq. 3.26) is subsumed
  by the parameter-range test (it would also drop back-facing cells, which never give the first hit
  on a closed body seen from outside).  The nearest hit along the ray wins (L15 end of §3.2.1).

* :class:`TriangleShape` — a triangle mesh (e.g. an OBJ/VTK plate model), Möller–Trumbore in double
  precision over a binned-SAH BVH; optionally Embree (``embreex``, single precision), whose closest
  hit is verified in double precision on the triangle it reports (rays clipped to the model's box
  first, self-hits below ``t_min`` and unverifiable rays re-traced by the numba kernel).  The numba
  BVH is exact (equal to brute force, bit for bit), about as fast as Embree for first hits (Bennu49k;
  faster on 3 M triangles) though ~2× slower for incoherent shadow rays, and gives the same answer
  whether or not ``embreex`` is installed, so ``backend="auto"`` means numba; Embree is opt-in.

Both traversals are numba kernels (:mod:`spctool.geometry._raykernels`; the trees are built by
:mod:`spctool.geometry._bvhkernels`): a stack-based, nearest-child-
first walk with t-pruning for first hits and early exit for any-hit queries over a packed 4-wide
hierarchy (float32 boxes rounded outward), parallel over rays.  Batches of ≥ 4096 rays are traced in
a coherent order (rays sorted by direction, then origin, by an O(n) radix sort) and the results
written back in the caller's order.  A few rays on a patch shape (at most :data:`NUMPY_TRACE_RAYS`,
e.g. lithos-select's occlusion test of one picture's candidates) are traced in numpy instead, every
cell tested with the same arithmetic (:func:`_trace_patches_numpy`, equal to the kernels bit for bit):
no kernel to compile on a first run, and the patch hierarchy is built only when the kernels need it.

The patch hierarchy is built from the ICQ grid itself: six face quadtrees (blocks of 2×2 cells as
leaves) whose boxes are merged bottom-up — O(n), well under a second for q = 512 (1.57 M cells).
Leaf boxes bound each patch *over its accepted parameter range [−EPS, 1+EPS]²*, so the hierarchy
returns exactly what the brute-force search over every cell returns (tested bit for bit).

:func:`visible_from` is the occlusion test of L15 §3.2.1: a point is visible from the camera if the
first surface hit along the line of sight lies within a tolerance of the point (L15: 1 % of the
body's largest diameter; ``spc-algorithms.md`` §2.3 ``occlusion_tol``).

Conventions: body-fixed coordinates in km; ray directions need not be unit — ``t`` is always the
distance along the normalised direction; misses have ``hit = False``, ``index = −1``, ``t = inf`` and
NaN point/parameters (never NaN for a hit).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from spctool.geometry import _bvhkernels as _bvh
from spctool.geometry import _raykernels as _rk

__all__ = [
    "SPC_PATCH_EPS",
    "SPC_SMALL_A",
    "HitResult",
    "PatchHit",
    "PatchShape",
    "TriangleShape",
    "patch_intersect_reference",
    "visible_from",
    "embree_available",
]

SPC_PATCH_EPS = 0.01
"""Parameter margin of GET_HEIGHTS: ι, γ accepted in [−EPS, 1+EPS] (erratum 16; BIGMAP uses 1e-5)."""

SPC_SMALL_A = 1e-8
"""SPC's switch between the closed-form root and its series, on \\|A\\| (erratum 13)."""

_SORT_MIN_RAYS = 4096  # above this many rays, trace them in a coherent order (ray_order)
NUMPY_TRACE_RAYS = 64  # up to this many rays on a patch shape: numpy brute force (no kernel compiled)
_NUMPY_TRACE_CELLS = 1 << 21  # … and while rays × cells stays below this (milliseconds per ray)
_BOX_PAD_REL = 1e-9  # BVH boxes are padded by this fraction of the model's extent (rounding safety)
_EMBREE_SLACK_REL = 2.0**-16  # Embree rays reach this fraction of the model's size past both ends


# ------------------------------------------------------------------------------------------------
# results
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HitResult:
    """Per-ray result of :meth:`PatchShape.first_hit` / :meth:`TriangleShape.first_hit`.

    ``index`` is the cell index ``(F−1)·q² + J·q + I`` for patches (see
    :meth:`PatchShape.cell_fij`) or the 0-based face index for triangles.  ``u``, ``v`` are the
    bilinear parameters (ι₀ along I, γ₀ along J, in [−EPS, 1+EPS]) for patches, or the barycentric
    weights of the triangle's 2nd and 3rd vertices.  ``point`` is the surface point (bilinear or
    barycentric interpolation of the corners) and ``t`` the distance from the ray origin along the
    unit direction.
    """

    hit: np.ndarray
    t: np.ndarray
    point: np.ndarray
    index: np.ndarray
    u: np.ndarray
    v: np.ndarray

    def __len__(self) -> int:
        return int(self.hit.shape[0])


@dataclass(frozen=True)
class PatchHit:
    """One accepted patch intersection from :func:`patch_intersect_reference`."""

    t: float
    u: float
    v: float
    point: tuple[float, float, float]


# ------------------------------------------------------------------------------------------------
# the literal reference (L15 §3.2.1 + errata), scalar, used by tests
# ------------------------------------------------------------------------------------------------


def patch_intersect_reference(origin, direction, corners, eps: float = SPC_PATCH_EPS,
                              body_x=(1.0, 0.0, 0.0)) -> PatchHit | None:
    """Intersect one ray with one bilinear cell exactly as L15 §3.2.1 describes, with errata 13–16.

    ``corners`` is (4, 3) in SPC's order 0 = (I,J), 1 = (I+1,J), 2 = (I,J+1), 3 = (I+1,J+1)
    (L15's cyclic corners 1, 2, 3, 4 of Fig. 13 are our 0, 2, 3, 1: L15's X₁ = x₄ − x₁ is our
    x₁ − x₀).  Pure Python scalars, one step per equation; the ray origin plays the camera and the
    body frame the camera frame.  The cell is two-sided (no Eq. 3.26 facing screen), and a hit
    behind the origin (z̃ < 0) is rejected.  Returns ``None`` for no hit.
    """
    ox, oy, oz = (float(a) for a in origin)
    dx, dy, dz = (float(a) for a in direction)
    nd = math.sqrt(dx * dx + dy * dy + dz * dz)
    if not (nd > 0.0 and math.isfinite(nd)):
        return None
    # Eq. 3.20/3.21: z̃ along the line of sight, ỹ = z̃ × b_x normalised, x̃ = ỹ × z̃ normalised.
    zt = (dx / nd, dy / nd, dz / nd)
    bx = tuple(float(a) for a in body_x)

    def cross(a, b):
        return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])

    def unit(a):
        n = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
        return (a[0] / n, a[1] / n, a[2] / n)

    yt = cross(zt, bx)
    if yt[0] ** 2 + yt[1] ** 2 + yt[2] ** 2 <= 1e-12:  # footnote 21: any right-handed frame will do
        yt = cross(zt, (0.0, 1.0, 0.0))
    yt = unit(yt)
    xt = unit(cross(yt, zt))
    # Eq. 3.22 (body frame = camera frame here): corner vectors from the ray origin, tilde components.
    xs, ys, zs = [], [], []
    for c in corners:
        p = (float(c[0]) - ox, float(c[1]) - oy, float(c[2]) - oz)
        xs.append(p[0] * xt[0] + p[1] * xt[1] + p[2] * xt[2])
        ys.append(p[0] * yt[0] + p[1] * yt[1] + p[2] * yt[2])
        zs.append(p[0] * zt[0] + p[1] * zt[1] + p[2] * zt[2])
    # Eq. 3.29, 3.30 (SPC corner order, spc-algorithms.md §2.2)
    X0, X1, X2, X3 = xs[0], xs[1] - xs[0], xs[2] - xs[0], xs[0] - xs[1] - xs[2] + xs[3]
    Y0, Y1, Y2, Y3 = ys[0], ys[1] - ys[0], ys[2] - ys[0], ys[0] - ys[1] - ys[2] + ys[3]
    # Eq. 3.33
    A = X1 * Y3 - X3 * Y1
    B = X1 * Y2 - X2 * Y1 - X3 * Y0 + X0 * Y3
    C = X0 * Y2 - X2 * Y0
    # erratum 13: proceed only if B² > 4AC (strictly)
    if not B * B > 4.0 * A * C:
        return None
    if B == 0.0:  # SPC's formulas divide by B (→ NaN → rejected)
        return None
    # Eq. 3.31 as SPC codes it — erratum 13: test |A|, and the root (√(1 − 4AC/B²) − 1)·B/(2A),
    # i.e. (−B + sign(B)·√D)/(2A), not L15's "−B + √D"; erratum 14: the series branch.
    if abs(A) > SPC_SMALL_A:
        iota = (math.sqrt(1.0 - 4.0 * A * C / (B * B)) - 1.0) * B / (2.0 * A)
    else:
        iota = -C / B - A * C * C / B ** 3
    # Eq. 3.32 — erratum 15: |X₂ + X₃ι₀| against |Y₂ + Y₃ι₀|, the larger denominator wins.
    den_x = X2 + X3 * iota
    den_y = Y2 + Y3 * iota
    if abs(den_x) > abs(den_y):
        gamma = -(X0 + X1 * iota) / den_x
    elif den_y != 0.0:
        gamma = -(Y0 + Y1 * iota) / den_y
    else:
        return None
    # erratum 16: accept [−EPS, 1+EPS]
    if not (-eps <= iota <= 1.0 + eps and -eps <= gamma <= 1.0 + eps):
        return None
    # Eq. 3.34/3.35: the distance is the interpolated z̃
    Z0, Z1, Z2, Z3 = zs[0], zs[1] - zs[0], zs[2] - zs[0], zs[0] - zs[1] - zs[2] + zs[3]
    z_int = Z0 + Z1 * iota + Z2 * gamma + Z3 * iota * gamma
    if z_int < 0.0:  # behind the camera
        return None
    w = ((1 - iota) * (1 - gamma), iota * (1 - gamma), (1 - iota) * gamma, iota * gamma)
    point = tuple(sum(w[i] * float(corners[i][a]) for i in range(4)) for a in range(3))
    return PatchHit(t=z_int, u=iota, v=gamma, point=point)


# ------------------------------------------------------------------------------------------------
# shared machinery
# ------------------------------------------------------------------------------------------------


def embree_available() -> bool:
    """True if the optional Embree binding (``embreex``) can be imported."""
    try:
        import embreex.mesh_construction  # noqa: F401
        import embreex.rtcore_scene  # noqa: F401
    except Exception:  # pragma: no cover - depends on the environment
        return False
    return True


def _rays(origins, directions, t_min, t_max):
    """Normalise ray inputs to C-contiguous float64 arrays of n or 1 rows (no broadcast copies)."""
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if o.shape[-1:] != (3,) or d.shape[-1:] != (3,) or o.ndim > 2 or d.ndim > 2:
        raise ValueError(f"origins and directions must be (N, 3) or (3,), got {o.shape} and {d.shape}")
    o = _writable(o.reshape(-1, 3))
    d = _writable(d.reshape(-1, 3))
    t0 = _writable(np.asarray(t_min, dtype=np.float64).reshape(-1))
    t1 = _writable(np.asarray(t_max, dtype=np.float64).reshape(-1))
    rows = (o.shape[0], d.shape[0], t0.shape[0], t1.shape[0])
    n = 0 if 0 in rows else max(rows)  # an empty batch with scalar t_min/t_max is empty, not 1 ray
    for name, a in (("origins", o), ("directions", d), ("t_min", t0), ("t_max", t1)):
        if a.shape[0] not in (1, n):
            raise ValueError(f"{name} has {a.shape[0]} rows, expected 1 or {n}")
    return n, o, d, t0, t1


def _writable(a):
    """C-contiguous and writeable (one numba signature for every call; copies only if needed)."""
    a = np.ascontiguousarray(a)
    return a if a.flags.writeable else a.copy()


class _Shape:
    """Common part of both shape kinds (BVH arrays, traversal wrappers, statistics)."""

    _kind: int
    _verts: np.ndarray  # (nv, 3) float64, contiguous
    _faces: np.ndarray  # (m, 3) int64 (empty for patches)
    _q: int
    _eps: float
    bvh_root_box: np.ndarray  # (6,) float64
    bvh_boxes: np.ndarray  # (M, 6, 4) float32, rounded outward
    bvh_refs: np.ndarray  # (M, 5) int32
    bvh_prims: np.ndarray  # (P,) int32

    def _set_tree(self, tree):
        bounds, first, count, leaf, prims = tree
        if leaf.any() and count[leaf.astype(bool)].max() > 7:
            raise AssertionError("BVH leaves must hold at most 7 primitives")
        root, nb, nc = _bvh.pack4(bounds, first, count, leaf)
        self.bvh_root_box = root
        self.bvh_boxes = _outward_f32(nb)
        self.bvh_refs = nc
        self.bvh_prims = prims

    # -- queries ---------------------------------------------------------------------------------

    def _trace_numba(self, any_hit, n, o, d, t0, t1):
        out_k = np.empty(n, np.int64)
        out_t = np.empty(n, np.float64)
        out_u = np.empty(n, np.float64)
        out_v = np.empty(n, np.float64)
        out_p = np.empty((n, 3), np.float64)
        if n:
            if n >= _SORT_MIN_RAYS:
                order = _rk.ray_order(n, o, d)
            else:
                order = np.arange(n, dtype=np.int64)
            _rk.trace(self._kind, any_hit, order, o, d, t0, t1, self.bvh_root_box, self.bvh_boxes,
                      self.bvh_refs, self.bvh_prims, self._verts, self._faces, self._q, self._eps,
                      out_k, out_t, out_u, out_v, out_p)
        return out_k, out_t, out_u, out_v, out_p

    def first_hit(self, origins, directions, t_max=np.inf, *, t_min=0.0) -> HitResult:
        """Nearest surface hit along each ray with t_min ≤ t ≤ t_max (t_max, t_min scalar or (N,)).

        Use ``t_min`` > 0 to step off the surface for rays that start on it.
        """
        k, t, u, v, p = self._trace(False, *_rays(origins, directions, t_min, t_max))
        return HitResult(hit=k >= 0, t=t, point=p, index=k, u=u, v=v)

    def any_hit(self, origins, directions, t_max=np.inf, *, t_min=0.0) -> np.ndarray:
        """True where the ray meets the surface anywhere in [t_min, t_max] (shadow/occlusion test;
        the traversal stops at the first accepted primitive)."""
        return self._any(*_rays(origins, directions, t_min, t_max))

    def _trace(self, any_hit, n, o, d, t0, t1):
        return self._trace_numba(any_hit, n, o, d, t0, t1)

    def _any(self, n, o, d, t0, t1):
        return self._trace_numba(True, n, o, d, t0, t1)[0] >= 0

    def brute_force_first_hit(self, origins, directions, t_max=np.inf, *, t_min=0.0) -> HitResult:
        """First hit by testing every primitive (no hierarchy) — for tests and verification."""
        n, o, d, t0, t1 = _rays(origins, directions, t_min, t_max)
        k = np.empty(n, np.int64)
        t = np.empty(n)
        u = np.empty(n)
        v = np.empty(n)
        if n:
            _rk.trace_brute(self._kind, o, d, t0, t1, self.n_primitives, self._verts, self._faces,
                            self._q, self._eps, k, t, u, v)
        p = self._points(k, u, v)
        return HitResult(hit=k >= 0, t=t, point=p, index=k, u=u, v=v)

    def visible_from(self, camera_position, points, tol_km=None) -> np.ndarray:
        """See :func:`visible_from`."""
        return visible_from(self, camera_position, points, tol_km)

    # -- statistics ------------------------------------------------------------------------------

    @property
    def n_primitives(self) -> int:
        raise NotImplementedError

    def _points(self, k, u, v):
        raise NotImplementedError

    @cached_property
    def bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box of the vertices: (lo (3,), hi (3,)) in km."""
        return self._verts.min(axis=0), self._verts.max(axis=0)

    @cached_property
    def bounding_box_diagonal(self) -> float:
        """Length of the bounding-box diagonal (an upper bound of :attr:`max_diameter`)."""
        lo, hi = self.bounding_box
        return float(np.linalg.norm(hi - lo))

    @cached_property
    def max_diameter(self) -> float:
        """The body's largest extent: the maximum distance between two vertices (SPC's MAXLEN).

        L15 §3.2.1 sets the occlusion tolerance to 1 % of it.  Up to :data:`EXACT_DIAMETER_POINTS`
        convex-hull vertices the value is exact (pruned all-pairs search).  Larger, rounder bodies
        (where that pruning degenerates to O(n²): minutes for a q=512 sphere) use
        :func:`approximate_diameter`, which is exact for any body whose diameter is a double-normal
        pair reached from its directional extremes and never more than 0.2 % short in the worst case.
        Bodies with more vertices first try the exact search on the vertices far enough from the
        centroid to end a diameter (a few on any elongated body).  The value is kept on disk per vertex
        array (:mod:`spctool.formats.derived`), so a command on a known shape does not recompute it.
        """
        from spctool.formats import derived

        pts = np.ascontiguousarray(self._verts, dtype=np.float64)
        return float(derived.cached("max-diameter-v1", pts, lambda: _max_diameter(pts)))


def _max_diameter(pts: np.ndarray) -> float:
    """:attr:`_Shape.max_diameter` of the vertices ``pts`` (n, 3), computed."""
    if pts.shape[0] > EXACT_DIAMETER_POINTS:
        # both ends of the diameter D lie at least D_lo − R from the centroid (R the largest
        # distance from it, D_lo ≤ D the directional lower bound): on elongated bodies that leaves
        # a few points, searched exactly, without the convex hull (0.2 s on a q = 64 ICQ)
        d_lo = approximate_diameter(pts)
        r = np.sqrt(np.sum((pts - pts.mean(axis=0)) ** 2, axis=1))
        far = pts[r >= d_lo - float(r.max())]
        if far.shape[0] <= EXACT_DIAMETER_POINTS:
            return max(d_lo, farthest_pair(far))
    pts = np.unique(pts, axis=0)
    if 4 < pts.shape[0] <= 200_000:
        try:
            from scipy.spatial import ConvexHull

            pts = pts[ConvexHull(pts).vertices]
        except Exception:  # flat or degenerate vertex sets: fall back to all vertices
            pass
    pts = np.ascontiguousarray(pts)
    if pts.shape[0] <= EXACT_DIAMETER_POINTS:
        return farthest_pair(pts)
    return approximate_diameter(pts)


#: above this many candidate points :attr:`_Shape.max_diameter` switches to :func:`approximate_diameter`
EXACT_DIAMETER_POINTS = 6000


def approximate_diameter(points, n_directions: int = 1024, refine: int = 8) -> float:
    """Largest pairwise distance of ``points`` (N, 3), from below, in O(N·n_directions).

    The extent along each of ``n_directions`` near-uniform (Fibonacci) directions bounds the
    diameter D from below by D·cos(θ/2), θ the largest angular gap (≈ 0.11 rad for 1024
    directions: at most 0.16 % short).  The extreme pairs of the ``refine`` widest directions are then
    polished by the double-normal iteration (b = farthest from a, a = farthest from b), which
    reaches the exact diameter whenever it lies in that basin (always, in the tests).
    """
    p = np.asarray(points, dtype=np.float64)
    if p.shape[0] < 2:
        return 0.0
    k = np.arange(n_directions) + 0.5
    z = 1.0 - 2.0 * k / n_directions
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (1.0 + 5.0**0.5) * k
    dirs = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    dirs = dirs[dirs[:, 2] >= 0.0]  # a direction and its opposite give the same extent
    lo, hi, ilo, ihi = directional_extremes(p, dirs)
    best = float(np.max(hi - lo))
    sq = np.einsum("ij,ij->i", p, p)

    def farthest(i: int) -> int:  # argmax |p − p_i|² = |p|² − 2 p·p_i + const: no (N, 3) temporary
        return int(np.argmax(sq - 2.0 * (p @ p[i])))

    polished: set = set()
    for d in np.argsort(lo - hi)[:refine]:
        a, b = int(ilo[d]), int(ihi[d])
        for _ in range(4):
            if (a, b) in polished:  # another direction's pair already went this way
                break
            polished.add((a, b))
            b_new = farthest(a)
            a_new = farthest(b_new)
            if (a_new, b_new) == (a, b):
                break
            a, b = a_new, b_new
        # a true pair distance: a lower bound of the diameter whatever the rounding of the search
        best = max(best, float(np.linalg.norm(p[a] - p[b])))
    return best


def directional_extremes(points, dirs, block: int = 2048):
    """Per direction: (min, max) of points·dir and the first indices where they occur — what
    ``_raykernels.directional_extremes`` returns, bit for bit (each dot product summed x, y, then z),
    in numpy blocks of points: a value computed once per shape (and kept, :mod:`spctool.formats.derived`)
    need not compile a kernel on a first run."""
    p = np.asarray(points, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    k = d.shape[0]
    lo, hi = np.full(k, np.inf), np.full(k, -np.inf)
    ilo, ihi = np.zeros(k, np.int64), np.zeros(k, np.int64)
    for i0 in range(0, p.shape[0], block):
        q = p[i0 : i0 + block]
        v = (q[:, 0:1] * d[None, :, 0] + q[:, 1:2] * d[None, :, 1]) + q[:, 2:3] * d[None, :, 2]
        jlo, jhi = np.argmin(v, axis=0), np.argmax(v, axis=0)  # first occurrence, as the kernel keeps
        vlo, vhi = v[jlo, np.arange(k)], v[jhi, np.arange(k)]
        better_lo, better_hi = vlo < lo, vhi > hi  # an earlier block keeps a tie
        lo[better_lo], ilo[better_lo] = vlo[better_lo], i0 + jlo[better_lo]
        hi[better_hi], ihi[better_hi] = vhi[better_hi], i0 + jhi[better_hi]
    return lo, hi, ilo, ihi


def farthest_pair(points, block: int = 256) -> float:
    """Exact largest pairwise distance of ``points`` (n, 3) — ``_raykernels.farthest_pair``'s pruned
    all-pairs search in numpy blocks: rows sorted by their distance r from the centroid, descending; a
    block of rows meets only the points j with r_j > best − r (its first row's), and the search ends
    when no pair can beat the best (r_i + r_0 ≤ best).  Each squared distance is (dx·dx + dy·dy) + dz·dz."""
    p = np.asarray(points, dtype=np.float64)
    n = p.shape[0]
    if n < 2:
        return 0.0
    r = np.sqrt(np.sum((p - p.mean(axis=0)) ** 2, axis=1))
    order = np.argsort(-r, kind="stable")
    p, r = p[order], r[order]
    best2, best = 0.0, 0.0
    for a in range(0, n, block):
        if r[a] + r[0] <= best:
            break
        m = int(np.count_nonzero(r > best - r[a]))  # r is descending: the partners are a prefix
        if m <= a:
            continue
        rows, cols = p[a : min(n, a + block)], p[a:m]  # pairs (i, j >= a): each pair once or twice
        dd = rows[:, None, :] - cols[None, :, :]
        d2 = (dd[..., 0] * dd[..., 0] + dd[..., 1] * dd[..., 1]) + dd[..., 2] * dd[..., 2]
        top = float(d2.max()) if d2.size else 0.0
        if top > best2:
            best2, best = top, math.sqrt(top)
    return best


def as_shape(obj, **kw):
    """A ray-query shape from what :mod:`spctool.formats` reads: an ``IcqShape`` (or its (6, q+1, q+1, 3)
    vertex array) becomes a :class:`PatchShape`, a ``TriangleMesh`` a :class:`TriangleShape`; shapes and
    ``None`` pass through."""
    if obj is None or isinstance(obj, _Shape):
        return obj
    verts = getattr(obj, "vertices", obj)
    if np.ndim(verts) == 4:
        return PatchShape(obj, **kw)
    if getattr(obj, "faces", None) is not None:
        return TriangleShape(obj, **kw)
    raise TypeError(f"cannot use a {type(obj).__name__} as a shape model")


def _outward_f32(nb: np.ndarray) -> np.ndarray:
    """Packed boxes (M, 6, 4) as float32 rounded outward (lo down, hi up): half the memory
    traffic, still conservative."""
    b32 = nb.astype(np.float32)
    lo, hi = b32[:, :3], b32[:, 3:]
    lo[:] = np.where(lo.astype(np.float64) > nb[:, :3], np.nextafter(lo, np.float32(-np.inf)), lo)
    hi[:] = np.where(hi.astype(np.float64) < nb[:, 3:], np.nextafter(hi, np.float32(np.inf)), hi)
    return np.ascontiguousarray(b32)


def _pad_for(verts: np.ndarray) -> float:
    ext = float(np.max(verts.max(axis=0) - verts.min(axis=0))) if verts.size else 0.0
    scale = max(ext, float(np.max(np.abs(verts))) if verts.size else 0.0, 1e-300)
    return _BOX_PAD_REL * scale


# ------------------------------------------------------------------------------------------------
# ICQ bilinear patches
# ------------------------------------------------------------------------------------------------


class PatchShape(_Shape):
    """An ICQ shape whose cells are SPC bilinear patches, with a face-quadtree BVH.

    ``PatchShape(icq)`` takes an object with ``.vertices`` of shape (6, q+1, q+1, 3) indexed
    [F−1, J, I, xyz] (``spctool.formats.icq.IcqShape``) or that array itself.  ``eps`` is the
    parameter margin (erratum 16: 0.01 as GET_HEIGHTS; BIGMAP uses 1e-5); ``leaf_side`` the block
    size of the quadtree leaves.
    """

    _kind = _rk.KIND_PATCH

    def __init__(self, vertices, *, eps: float = SPC_PATCH_EPS, leaf_side: int = 2):
        arr = getattr(vertices, "vertices", vertices)
        v = np.asarray(arr, dtype=np.float64)
        if v.ndim != 4 or v.shape[0] != 6 or v.shape[1] != v.shape[2] or v.shape[3] != 3 or v.shape[1] < 2:
            raise ValueError(f"ICQ vertices must have shape (6, q+1, q+1, 3), got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError("ICQ vertices must be finite")
        if not eps >= 0.0:
            raise ValueError("eps must be >= 0")
        if leaf_side not in (1, 2):
            raise ValueError("leaf_side must be 1 or 2 (a leaf holds at most 7 cells)")
        self._verts = np.array(v.reshape(-1, 3), dtype=np.float64, order="C", copy=True)  # owned
        self.vertices = self._verts.reshape(v.shape)
        self.q = int(v.shape[1] - 1)
        self._q = self.q
        self._eps = float(eps)
        self.eps = float(eps)
        self._faces = np.zeros((0, 3), np.int64)
        self._leaf_side = int(leaf_side)

    def __getattr__(self, name):
        """The ``bvh_*`` arrays, built on first use (a few rays are traced without them)."""
        if name.startswith("bvh_") and "_leaf_side" in self.__dict__ and "bvh_prims" not in self.__dict__:
            self._set_tree(_bvh.build_patch_tree(self._verts, self.q, self._leaf_side, self._eps,
                                                _pad_for(self._verts)))
            return self.__dict__[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def _trace(self, any_hit, n, o, d, t0, t1):
        if 0 < n <= NUMPY_TRACE_RAYS and n * self.n_primitives <= _NUMPY_TRACE_CELLS:
            return _trace_patches_numpy(self._verts, self.q, self._eps, n, o, d, t0, t1)
        return self._trace_numba(any_hit, n, o, d, t0, t1)

    def _any(self, n, o, d, t0, t1):
        return self._trace(True, n, o, d, t0, t1)[0] >= 0

    @property
    def n_primitives(self) -> int:
        return 6 * self.q * self.q

    n_cells = n_primitives

    def cell_fij(self, index):
        """Split cell indices into (F (1…6), I, J) arrays."""
        k = np.asarray(index, dtype=np.int64)
        f, r = np.divmod(k, self.q * self.q)
        j, i = np.divmod(r, self.q)
        return f + 1, i, j

    def cell_index(self, face, i, j):
        """Cell index of face F (1…6) and cell (I, J) (0…q−1)."""
        return (np.asarray(face) - 1) * self.q * self.q + np.asarray(j) * self.q + np.asarray(i)

    def cell_corners(self, index) -> np.ndarray:
        """Corners (…, 4, 3) of cells in SPC's order (I,J), (I+1,J), (I,J+1), (I+1,J+1)."""
        f, i, j = self.cell_fij(index)
        v = self.vertices
        f = f - 1
        return np.stack([v[f, j, i], v[f, j, i + 1], v[f, j + 1, i], v[f, j + 1, i + 1]], axis=-2)

    def surface_point(self, index, u, v) -> np.ndarray:
        """Bilinear point of cell ``index`` at parameters (u along I, v along J)."""
        c = self.cell_corners(index)
        u = np.asarray(u, dtype=np.float64)[..., None]
        v = np.asarray(v, dtype=np.float64)[..., None]
        return ((1 - u) * (1 - v) * c[..., 0, :] + u * (1 - v) * c[..., 1, :] + (1 - u) * v * c[..., 2, :]
                + u * v * c[..., 3, :])

    def _points(self, k, u, v):
        p = np.full((k.shape[0], 3), np.nan)
        m = k >= 0
        if m.any():
            p[m] = self.surface_point(k[m], u[m], v[m])
        return p

    def _all_corners(self):
        v = self.vertices
        return v[:, :-1, :-1], v[:, :-1, 1:], v[:, 1:, :-1], v[:, 1:, 1:]

    @cached_property
    def max_cell_diagonal(self) -> float:
        """L15 Eq. 3.24: the largest cell diagonal, max over cells of \\|c₀ − c₃\\| and \\|c₁ − c₂\\|."""
        c0, c1, c2, c3 = self._all_corners()
        return float(np.sqrt(max(np.max(np.sum((c0 - c3) ** 2, -1)), np.max(np.sum((c1 - c2) ** 2, -1)))))

    @cached_property
    def volume(self) -> float:
        """Enclosed volume of the bilinear surface (km³), by the divergence theorem.

        V = (1/3)∮ P·n dA = −(1/3)Σ∬ P·(P_u × P_v) du dv (P_u × P_v points inward on an ICQ face,
        ``spc-formats.md`` §5.2).  The integrand is of degree 2 in u and v, so a 2×2 Gauss–Legendre
        rule is exact.  Positive for a correctly oriented ICQ model.
        """
        c0, c1, c2, c3 = self._all_corners()
        e1 = c1 - c0
        e2 = c2 - c0
        e3 = c0 - c1 - c2 + c3
        g = 0.5 + 0.5 / math.sqrt(3.0) * np.array([-1.0, 1.0])
        total = 0.0
        for u in g:
            for v in g:
                p = c0 + u * e1 + v * e2 + u * v * e3
                pu = e1 + v * e3
                pv = e2 + u * e3
                total += float(np.sum(p * np.cross(pu, pv)))
        return -total / 4.0 / 3.0

    @cached_property
    def area(self) -> float:
        """Surface area of the bilinear patches (km²), 4×4 Gauss–Legendre per cell."""
        c0, c1, c2, c3 = self._all_corners()
        e1 = c1 - c0
        e2 = c2 - c0
        e3 = c0 - c1 - c2 + c3
        x, w = np.polynomial.legendre.leggauss(4)
        x = 0.5 * (x + 1.0)
        w = 0.5 * w
        total = 0.0
        for u, wu in zip(x, w):
            for v, wv in zip(x, w):
                total += wu * wv * float(np.sum(np.linalg.norm(np.cross(e1 + v * e3, e2 + u * e3), axis=-1)))
        return total


# ------------------------------------------------------------------------------------------------
# triangle meshes
# ------------------------------------------------------------------------------------------------


class TriangleShape(_Shape):
    """A triangle mesh with a binned-SAH BVH (numba) and an optional Embree backend.

    ``TriangleShape(mesh)`` takes an object with ``.vertices`` (n, 3) and ``.faces`` (m, 3) 0-based
    (``spctool.formats.mesh.TriangleMesh``); ``TriangleShape(vertices, faces)`` the arrays.
    ``backend``: ``"numba"`` (the exact double-precision BVH; also what ``"auto"`` selects) or
    ``"embree"`` (requires ``embreex``).  Embree traces in single precision: its closest hit is
    re-intersected in double precision with the numba triangle test and kept only if it lies in
    [t_min, t_max); rays it cannot settle that way (self-hits of rays leaving the surface, rays
    through an edge in single precision only) are traced by the numba kernel.  The two backends
    then agree bit for bit except where single precision cannot resolve the ray's path past an
    edge or vertex: a grazing ray near an edge, or a ray that only touches the model tangentially at
    a silhouette vertex or edge (numba's inclusive edges count that as a hit, Embree may not; about
    1 % of rays aimed *exactly* at vertices from outside; 3 of 2.1 M jittered test rays).
    """

    _kind = _rk.KIND_TRIANGLE

    def __init__(self, vertices, faces=None, *, backend: str = "auto", leaf_size: int = 4):
        if faces is None:
            faces = vertices.faces
            vertices = vertices.vertices
        v = np.array(vertices, dtype=np.float64, order="C", copy=True)  # owned: the BVH depends on it
        f = np.array(faces, dtype=np.int64, order="C", copy=True)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"vertices must be (n, 3), got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
            raise ValueError(f"faces must be (m, 3) with m > 0, got {f.shape}")
        if f.min() < 0 or f.max() >= v.shape[0]:
            raise ValueError("face indices must be 0-based and < number of vertices")
        if not np.all(np.isfinite(v)):
            raise ValueError("vertices must be finite")
        if backend not in ("auto", "numba", "embree"):
            raise ValueError(f"backend must be 'auto', 'numba' or 'embree', got {backend!r}")
        if backend == "auto":  # numba: exact and (measured) as fast as Embree, see the class docstring
            backend = "numba"
        if backend == "embree" and not embree_available():
            raise ValueError("backend='embree' needs the optional package embreex")
        self.vertices = v
        self.faces = f
        self.backend = backend
        self._verts = v
        self._faces = f
        self._q = 0
        self._eps = 0.0
        tri = v[f]
        pad = _pad_for(v)
        lo = tri.min(axis=1) - pad
        hi = tri.max(axis=1) + pad
        if not 1 <= leaf_size <= 7:
            raise ValueError("leaf_size must be 1…7")
        self._set_tree(_bvh.build_sah_tree(np.ascontiguousarray(lo), np.ascontiguousarray(hi),
                                          int(leaf_size), 16))
        self._scene = None
        if backend == "embree":
            self._build_embree()

    @property
    def n_primitives(self) -> int:
        return int(self.faces.shape[0])

    def _points(self, k, u, v):
        p = np.full((k.shape[0], 3), np.nan)
        m = k >= 0
        if m.any():
            tri = self.vertices[self.faces[k[m]]]
            uu = u[m][:, None]
            vv = v[m][:, None]
            p[m] = (1 - uu - vv) * tri[:, 0] + uu * tri[:, 1] + vv * tri[:, 2]
        return p

    # -- Embree ----------------------------------------------------------------------------------

    def _build_embree(self):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh as _EmbreeMesh

        # robust mode: watertight edges (no ray slips between two triangles sharing an edge)
        self._scene = rtcore_scene.EmbreeScene(robust=True)
        _EmbreeMesh(self._scene, self.vertices.astype(np.float32), self.faces.astype(np.int32))
        box = self.bvh_root_box
        size = max(float(np.max(np.abs(box))), float(np.max(box[3:] - box[:3])))
        self._embree_slack = _EMBREE_SLACK_REL * size
        self._embree_box = np.concatenate([box[:3] - self._embree_slack, box[3:] + self._embree_slack])

    def _trace(self, any_hit, n, o, d, t0, t1):
        if self.backend != "embree":
            return self._trace_numba(any_hit, n, o, d, t0, t1)
        k, t, u, v = self._trace_embree(any_hit, n, o, d, t0, t1)
        return k, t, u, v, self._points(k, u, v)

    def _any(self, n, o, d, t0, t1):
        if self.backend != "embree":
            return self._trace_numba(True, n, o, d, t0, t1)[0] >= 0
        return self._trace_embree(True, n, o, d, t0, t1)[0] >= 0

    def _trace_embree(self, any_hit, n, o, d, t0, t1):
        """Embree's closest hit, verified in double precision; rays it cannot settle (see
        :func:`_raykernels.verify_triangle_hits`) are traced by the numba kernel.

        Embree works in single precision, so the rays are first clipped to the model's box in double
        precision (:func:`_raykernels.clip_rays`): Embree then sees an origin on the box, not a far
        camera whose coordinates (and Embree's intersection arithmetic) float32 rounds at ~1e-7 of
        its distance.  A hit is accepted only if the numba triangle test on the triangle Embree
        names gives a hit in [t_min, t_max), so ``index``/``t``/``u``/``v`` are bit-identical to the
        numba backend's whenever Embree names the same triangle.  Any-hit queries use the same
        verified closest hit (Embree's occlusion query cannot be verified: it reports a shadow
        ray's own triangle).

        Unclipped and unverified (before this was fixed), Embree was off by up to 56 m (12 km) for
        cameras 1000 km (1e5 km) from the q = 32 Bennu model, and gave shadow rays leaving the
        surface their own triangle at t ≈ 0 < t_min, up to 0.6 km short of the true hit — which
        made the exact numba backend look wrong next to it.  ``tests/test_shape.py`` checks both.
        """
        k = np.full(n, -1, np.int64)
        t = np.full(n, np.inf)
        u = np.full(n, np.nan)
        v = np.full(n, np.nan)
        ok = np.empty(n, np.bool_)
        org = np.empty((n, 3))
        dirs = np.empty((n, 3))
        span = np.empty(n)
        if n:
            _rk.clip_rays(n, o, d, t0, t1, self._embree_box, self._embree_slack, ok, org, dirs, span)
        idx = np.flatnonzero(ok)
        if idx.size:
            res = self._scene.run(org[idx].astype(np.float32), dirs[idx].astype(np.float32),
                                  dists=span[idx].astype(np.float32), query="INTERSECT", output=False)
            prim = np.ascontiguousarray(res, dtype=np.int64)
            redo = np.zeros(n, np.bool_)
            _rk.verify_triangle_hits(idx, prim, o, d, t0, t1, self._embree_slack, self._verts, self._faces,
                                     k, t, u, v, redo)
            r = np.flatnonzero(redo)
            if r.size:
                rk, rt, ru, rv, _ = self._trace_numba(any_hit, r.size, _rows(o, r), _rows(d, r), _rows(t0, r),
                                                      _rows(t1, r))
                k[r], t[r], u[r], v[r] = rk, rt, ru, rv
        return k, t, u, v

    @cached_property
    def volume(self) -> float:
        """Signed enclosed volume (km³), Σ v₀·(v₁ × v₂)/6 (divergence theorem); positive for
        outward (right-hand-rule) facets."""
        t = self.vertices[self.faces]
        return float(np.sum(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])))) / 6.0

    @cached_property
    def area(self) -> float:
        """Total facet area (km²)."""
        t = self.vertices[self.faces]
        return float(np.sum(np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1))) / 2.0


def _trace_patches_numpy(verts, q, eps, n, o, d, t0, t1):
    """First hits of ``n`` rays on the ICQ patches (``verts`` (6(q+1)², 3)) by testing every cell in
    numpy: :func:`_raykernels.trace_brute`'s search (L15 Eq. 3.21–3.35 with errata 13–16, each
    operation in the kernels' order, so the result is theirs bit for bit; ties → the smaller cell)
    without compiling anything.  Inputs as :func:`_rays` returns them; returns ``(k, t, u, v, p)``."""
    qq = q * q
    k = np.arange(6 * qq, dtype=np.int64)
    f, r = np.divmod(k, qq)
    j, i = np.divmod(r, q)
    q1 = q + 1
    b = f * q1 * q1 + j * q1 + i  # _raykernels.cell_base
    out_k = np.full(n, -1, np.int64)
    out_t = np.full(n, np.inf)
    out_u = np.full(n, np.nan)
    out_v = np.full(n, np.nan)
    out_p = np.full((n, 3), np.nan)
    vx, vy, vz = verts[:, 0], verts[:, 1], verts[:, 2]
    e1, e2 = -eps, 1.0 + eps

    def outside(a0, a1, a2, a3):  # _raykernels._outside
        A1 = a1 - a0
        A2 = a2 - a0
        A3 = a0 - a1 - a2 + a3
        c00 = a0 + A1 * e1 + A2 * e1 + A3 * e1 * e1
        c10 = a0 + A1 * e2 + A2 * e1 + A3 * e2 * e1
        c01 = a0 + A1 * e1 + A2 * e2 + A3 * e1 * e2
        c11 = a0 + A1 * e2 + A2 * e2 + A3 * e2 * e2
        return ((c00 > 0.0) & (c10 > 0.0) & (c01 > 0.0) & (c11 > 0.0)) | (
            (c00 < 0.0) & (c10 < 0.0) & (c01 < 0.0) & (c11 < 0.0))

    with np.errstate(all="ignore"):
        for r in range(n):  # a few rays; every cell at once (screened, then solved)
            ox, oy, oz = (float(x) for x in o[r if o.shape[0] > 1 else 0])
            dx, dy, dz = (float(x) for x in d[r if d.shape[0] > 1 else 0])
            lo = float(t0[r if t0.shape[0] > 1 else 0])
            hi = float(t1[r if t1.shape[0] > 1 else 0])
            nd = math.sqrt(dx * dx + dy * dy + dz * dz)
            if not (0.0 < nd < math.inf and math.isfinite(ox + oy + oz) and lo <= hi):
                continue
            dx, dy, dz = dx / nd, dy / nd, dz / nd
            ny = dy * dy + dz * dz  # _raykernels.tilde_frame
            if ny > 1e-12:
                s = 1.0 / math.sqrt(ny)
                yx, yy, yz = 0.0, dz * s, -dy * s
            else:
                s = 1.0 / math.sqrt(dx * dx + dz * dz)
                yx, yy, yz = -dz * s, 0.0, dx * s
            fr = (yy * dz - yz * dy, yz * dx - yx * dz, yx * dy - yy * dx, yx, yy, yz, dx, dy, dz)
            px = vx - ox  # _raykernels._project, every vertex
            py = vy - oy
            pz = vz - oz
            X = px * fr[0] + py * fr[1] + pz * fr[2]
            Y = px * fr[3] + py * fr[4] + pz * fr[5]
            # a superset of the cells the sign screen keeps, cheaply: the extended corners (weights summing
            # to 1, the negative ones 2·eps(1+eps) at most) lie within that fraction of the corners' span
            # around it (doubled here; 1e-9·max|a| covers rounding); the exact arithmetic below runs on
            # these cells only
            cx = np.stack((X[b], X[b + 1], X[b + q1], X[b + q1 + 1]))
            cy = np.stack((Y[b], Y[b + 1], Y[b + q1], Y[b + q1 + 1]))
            keep = np.ones(b.shape[0], bool)
            for cc in (cx, cy):
                clo, chi = cc.min(axis=0), cc.max(axis=0)
                slack = 4.0 * eps * (1.0 + eps) * (chi - clo) + 1e-9 * np.maximum(np.abs(clo), np.abs(chi))
                keep &= (clo - slack <= 0.0) & (chi + slack >= 0.0)
            cells = np.flatnonzero(keep)
            if cells.size == 0:
                continue
            bc = b[cells]
            x0, x1, x2, x3 = (c[cells] for c in cx)
            y0, y1, y2, y3 = (c[cells] for c in cy)
            ok = ~(outside(x0, x1, x2, x3) | outside(y0, y1, y2, y3))  # _raykernels.patch_solve
            X1 = x1 - x0
            X2 = x2 - x0
            X3 = x0 - x1 - x2 + x3
            Y1 = y1 - y0
            Y2 = y2 - y0
            Y3 = y0 - y1 - y2 + y3
            A = X1 * Y3 - X3 * Y1
            B = X1 * Y2 - X2 * Y1 + x0 * Y3 - X3 * y0
            C = x0 * Y2 - X2 * y0
            D = B * B - 4.0 * A * C
            ok &= D > 0.0
            sq = np.sqrt(np.where(ok, D, 0.0))
            qd = np.where(B >= 0.0, -0.5 * (B + sq), -0.5 * (B - sq))
            u = C / qd
            ok &= (u >= -eps) & (u <= 1.0 + eps)
            dxn = X2 + X3 * u
            dyn = Y2 + Y3 * u
            use_x = np.abs(dxn) > np.abs(dyn)
            ok &= use_x | (dyn != 0.0)
            v = np.where(use_x, -(x0 + X1 * u) / dxn, -(y0 + Y1 * u) / dyn)
            ok &= (v >= -eps) & (v <= 1.0 + eps)
            zi = (bc, bc + 1, bc + q1, bc + q1 + 1)
            z0, z1, z2, z3 = (px[i] * fr[6] + py[i] * fr[7] + pz[i] * fr[8] for i in zi)
            t = z0 + (z1 - z0) * u + (z2 - z0) * v + (z0 - z1 - z2 + z3) * u * v
            ok &= (t >= lo) & (t <= hi)
            if not ok.any():
                continue
            t = np.where(ok, t, np.inf)
            j = int(np.argmin(t))  # the nearest; ties → the smaller cell (the first minimum; cells ascend)
            uu, vv = float(u[j]), float(v[j])
            out_k[r], out_t[r], out_u[r], out_v[r] = cells[j], t[j], uu, vv
            c = bc[j]
            w0 = (1.0 - uu) * (1.0 - vv)
            w1 = uu * (1.0 - vv)
            w2 = (1.0 - uu) * vv
            w3 = uu * vv
            out_p[r] = w0 * verts[c] + w1 * verts[c + 1] + w2 * verts[c + q1] + w3 * verts[c + q1 + 1]
    return out_k, out_t, out_u, out_v, out_p


def _rows(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Rows ``idx`` of a per-ray input that has n rows, or the input itself if it has one."""
    return a if a.shape[0] == 1 else np.ascontiguousarray(a[idx])


# ------------------------------------------------------------------------------------------------
# occlusion
# ------------------------------------------------------------------------------------------------


def visible_from(shape, camera_position, points, tol_km=None) -> np.ndarray:
    """L15 §3.2.1 occlusion test: is each surface point the first thing the camera sees along its
    line of sight?

    A ray from ``camera_position`` (3,) toward each point (N, 3) is traced up to the point's
    distance plus ``tol_km``; the point is visible if the first hit lies within ``tol_km`` of it.
    ``tol_km`` (scalar or (N,)) defaults to 1 % of ``shape.max_diameter`` (L15; configurable as
    ``occlusion_tol`` in ``spc-algorithms.md`` §2.3).  A line of sight that meets no surface within
    reach (a point off the body) is reported not visible.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cam = np.asarray(camera_position, dtype=np.float64).reshape(3)
    if tol_km is None:
        tol_km = 0.01 * shape.max_diameter
    tol = np.broadcast_to(np.asarray(tol_km, dtype=np.float64), (pts.shape[0],))
    d = pts - cam
    dist = np.linalg.norm(d, axis=1)
    res = shape.first_hit(np.broadcast_to(cam, pts.shape), d, t_max=dist + tol)
    close = np.linalg.norm(np.where(res.hit[:, None], res.point, 0.0) - pts, axis=1) <= tol
    return res.hit & close
