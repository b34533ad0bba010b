"""The fused renderer's exact shortcuts (issue 17) against the plain march they replace.

* :func:`spctool.geometry._heightkernels.horizon_bound` — the shadow march's rise-aware early end — is
  checked by brute force: rays from random points of random cells, sampled finely along their path to
  the grid edge, never pass over a cell whose top exceeds the ray's height there by more than the
  bound allows;
* whole renders of random rough height patches (grazing and steep views, low and high Sun, missing
  nodes, patches partly outside the window, supersample 1–3, smooth and facet shading, shadows on and
  off) with the shortcuts equal the reference (``_render(..., fast=False)``: the fused kernel with the
  full march) — the shortcuts only end marches that cannot find a crossing, so the pictures are equal
  to the last bit, which is what is asserted (stricter than the 1e-12 the issue allows).
"""

import math

import numba
import numpy as np
import pytest

from spctool.geometry._heightkernels import cell_tops, horizon_bound, intersect_rays, lit_from
from spctool.geometry.camera import Camera
from spctool.geometry.frames import look_rotation, orient_frame
from spctool.geometry.surfaces import HeightPatch
from spctool.stages.render import RenderOptions, _render, render


def _direction(azimuth_deg, elevation_deg):
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)


@pytest.mark.parametrize(
    "azimuth, elevation",
    [(0.0, 5.0), (20.0, 30.0), (45.0, 10.0), (90.0, 60.0), (135.0, 2.0), (200.0, 45.0), (260.0, 80.0),
     (315.0, 20.0), (333.0, 0.5)],
)  # fmt: skip
def test_horizon_bound_is_a_true_bound(azimuth, elevation):
    rng = np.random.default_rng(int(azimuth * 10 + elevation))
    n0, n1 = 27, 21
    h = rng.normal(size=(n0 + 1, n1 + 1)) * 2.0 + 6.0 * (rng.uniform(size=(n0 + 1, n1 + 1)) > 0.97)
    valid = rng.uniform(size=h.shape) > 0.03
    tops = cell_tops(np.where(valid, h, 0.0), valid)
    au, aw, az = _direction(azimuth, elevation)
    out = np.empty_like(tops)
    entry = np.empty_like(tops)
    horizon_bound(tops, au, aw, az, out, entry)
    assert np.all(out >= tops)
    rho = np.arange(0.0, 80.0, 0.005)  # horizontal travel
    rise = az / math.hypot(au, aw)  # per unit of horizontal travel
    for _ in range(300):
        i, j = rng.integers(0, n0), rng.integers(0, n1)
        u, w = i + rng.uniform(), j + rng.uniform()
        uu, ww = u + rho * au / math.hypot(au, aw), w + rho * aw / math.hypot(au, aw)
        keep = (uu >= 0) & (uu < n0) & (ww >= 0) & (ww < n1)
        seen = tops[uu[keep].astype(int), ww[keep].astype(int)] - rise * rho[keep]
        assert seen.max() <= out[i, j] + 1e-12
    # entry bounds: rays entering a column (along the dominant axis) at its near edge
    major0 = abs(au) >= abs(aw)
    for _ in range(300):
        i, j = rng.integers(0, n0), rng.integers(0, n1)
        if major0:
            u, w = (float(i) if au > 0 else i + 1.0), j + rng.uniform()
        else:
            u, w = i + rng.uniform(), (float(j) if aw > 0 else j + 1.0)
        r1 = rho + 1e-9  # just inside the column (at its edge a cell index would name the neighbour)
        uu, ww = u + r1 * au / math.hypot(au, aw), w + r1 * aw / math.hypot(au, aw)
        keep = (uu >= 0) & (uu < n0) & (ww >= 0) & (ww < n1)
        seen = tops[uu[keep].astype(int), ww[keep].astype(int)] - rise * rho[keep]
        assert seen.max() <= entry[i, j] + 1e-12


def test_horizon_bound_special_directions():
    tops = np.arange(12.0).reshape(3, 4)
    out, entry = np.empty_like(tops), np.empty_like(tops)
    horizon_bound(tops, 0.3, 0.4, -0.1, out, entry)  # a descending ray: no bound
    assert np.all(out == np.inf) and np.all(entry == np.inf)
    horizon_bound(tops, 0.0, 0.0, 1.0, out, entry)  # straight up: its own cell
    np.testing.assert_array_equal(out, tops)


@numba.njit
def _lit_many(h, tops, entry, starts, d, out):
    n0, n1 = h.shape
    for k in range(starts.shape[0]):
        u, w, z = starts[k]
        out[k] = lit_from(h, tops, entry, 0, n0, n1, u, w, z, d[0], d[1], d[2])


def _lit_case(seed, n=24, azimuth=None, el=None, rough=None, holes=None, m=4000, on_lines=False):
    """(lit, crossed) of shadow rays from ``m`` points 1e-3 cells above a random terrain: lit_from's answer
    and whether the exact march (heightfield.intersect_rays) finds a crossing."""
    rng = np.random.default_rng(seed)
    rough = (0.2 + 0.3 * (seed % 3)) if rough is None else rough
    h = np.cumsum(rng.normal(size=(n, n)), 0) * 0.3 + rng.normal(size=(n, n)) * rough
    valid = np.ones((n, n), bool)
    if (seed % 2) if holes is None else holes:
        valid[rng.integers(0, n, 10), rng.integers(0, n, 10)] = False
    h = np.where(valid, h, 0.0)
    tops = cell_tops(h, valid)
    el = [3.0, 15.0, 35.0, 55.0, 75.0][seed % 5] if el is None else el
    azimuth = rng.uniform(0, 360) if azimuth is None else azimuth
    au, aw, az = _direction(azimuth, el)
    out, entry = np.empty_like(tops), np.empty_like(tops)
    horizon_bound(tops, au, aw, az, out, entry)
    uw = rng.uniform(0, n - 1, size=(m, 2))
    if on_lines:  # starts on grid lines and nodes, where a cell index could name either neighbour
        uw[: m // 3, 0] = np.floor(uw[: m // 3, 0])
        uw[m // 3 : 2 * m // 3, 1] = np.floor(uw[m // 3 : 2 * m // 3, 1])
        uw[2 * m // 3 :] = np.floor(uw[2 * m // 3 :])
    i, j = np.minimum(uw.astype(int), n - 2).T
    fu, fw = uw[:, 0] - i, uw[:, 1] - j
    z = (1 - fw) * ((1 - fu) * h[i, j] + fu * h[i + 1, j])
    z += fw * ((1 - fu) * h[i, j + 1] + fu * h[i + 1, j + 1])
    ok = valid[i, j] & valid[i + 1, j] & valid[i, j + 1] & valid[i + 1, j + 1]  # points on full cells
    starts = np.column_stack([uw, z + 1e-3])[ok]
    d = np.array([au, aw, az]) * rng.uniform(0.5, 3.0)  # any scale of the direction
    lit = np.empty(starts.shape[0], bool)
    _lit_many(h, tops, entry, starts, d, lit)
    dirs = np.broadcast_to(d, starts.shape)
    t = np.empty(starts.shape[0])
    intersect_rays(h, valid, starts, np.ascontiguousarray(dirs), np.zeros(len(t)), np.full(len(t), 1e9), t)
    return lit, np.isfinite(t)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(16))
def test_lit_from_never_declares_a_blocked_ray_lit(seed):
    """Shadow rays from random points just above random terrains: wherever lit_from says "lit", the exact
    march (heightfield.intersect_rays) finds no crossing; and it says so for most rays of a high Sun."""
    lit, crossed = _lit_case(seed)
    assert not np.any(lit & crossed)
    assert np.any(lit) or [3.0, 15.0, 35.0, 55.0, 75.0][seed % 5] < 35.0  # the shortcut does fire


@pytest.mark.parametrize(
    "azimuth", [0.0, 90.0, 180.0, 270.0, 45.0, 135.0, 45.0 + 1e-7, 30.0, 200.0, 300.0]
)
@pytest.mark.parametrize("holes", [False, True])
def test_lit_from_on_grid_lines_axes_and_diagonals(azimuth, holes):
    """Starts on grid lines and nodes, Suns along an axis (no minor component), on a diagonal and a hair
    off it, over a rough terrain with and without missing nodes: never "lit" where the march crosses."""
    for el in (20.0, 50.0, 70.0):
        lit, crossed = _lit_case(7, azimuth=azimuth, el=el, rough=1.0, holes=holes, on_lines=True)
        assert not np.any(lit & crossed)


def test_lit_from_walks_the_rows_in_the_rays_order():
    """A hand-built case (found in review): the ray passes a cell with a missing corner and then a cell it
    rises faster than but which lies above it where it comes in (the terrain across the missing cell is
    unknown), so only that order — the missing cell first — says "march"; the march crosses at t = 4/3.
    Walking the column's rows the other way round would have called the ray lit."""
    h = np.zeros((3, 4))
    valid = np.ones((3, 4), bool)
    valid[2, 0] = False
    h[2, 1], h[1, 2], h[2, 2] = 2.0, -3.4, -1.4
    tops = cell_tops(h, valid)
    d = np.array([1.0, 0.6, 0.3])
    out, entry = np.empty_like(tops), np.empty_like(tops)
    horizon_bound(tops, d[0], d[1], d[2], out, entry)
    start = np.array([[0.5, 0.2, 0.001]])
    t = np.empty(1)
    intersect_rays(h, valid, start, d[None, :].copy(), np.zeros(1), np.full(1, 1e9), t)
    assert t[0] == pytest.approx(4.0 / 3.0)
    lit = np.empty(1, bool)
    _lit_many(h, tops, entry, start, d, lit)
    assert not lit[0]


def test_lit_from_leaves_an_all_but_vertical_ray_to_the_march():
    """Horizontal components below the smallest normal double (their reciprocals overflow): no walk, no
    undefined floor of a NaN — the march decides."""
    h = np.zeros((5, 5))
    valid = np.ones((5, 5), bool)
    tops = cell_tops(h, valid)
    for d in ([1e-310, 5e-311, 1.0], [-4e-320, 1e-310, 1.0], [0.0, 1e-315, 1.0]):
        d = np.array(d)
        out, entry = np.empty_like(tops), np.empty_like(tops)
        horizon_bound(tops, d[0], d[1], d[2], out, entry)
        lit = np.empty(3, bool)
        _lit_many(h, tops, entry, np.array([[2.0, 2.0, 0.001], [2.5, 1.0, 0.001], [4.0, 4.0, 0.001]]), d, lit)
        assert not lit.any()


@pytest.mark.parametrize("seed", range(4))
def test_lit_from_clears_most_lit_rays_of_a_rough_terrain(seed):
    """The Monte Carlo's case (issue 17): hills two cells high whose heights are perturbed cell by cell
    (σ 0.25 cells), under a Sun 50° up — a few rays in 1000 shadowed, and near every cell some slope
    steeper than the Sun, so the slope-bound shortcut fails for most rays.  lit_from, following the
    ray over a few columns, clears more than 90 % of the rays the march finds lit (the own cell, the
    next rows and the next column's bound alone cleared 53–55 % of them), and none it finds blocked."""
    rng = np.random.default_rng(seed)
    n, m = 48, 6000
    x = np.arange(n)
    h = 2.0 * np.sin(x[:, None] / 3.0 + rng.uniform(0, 6)) * np.cos(x[None, :] / 4.0 + rng.uniform(0, 6))
    h += rng.normal(size=(n, n)) * 0.25
    valid = np.ones((n, n), bool)
    tops = cell_tops(h, valid)
    d = np.array(_direction(rng.uniform(0, 360), 50.0))
    out, entry = np.empty_like(tops), np.empty_like(tops)
    horizon_bound(tops, d[0], d[1], d[2], out, entry)
    uw = rng.uniform(0, n - 1, size=(m, 2))
    i, j = np.minimum(uw.astype(int), n - 2).T
    fu, fw = uw[:, 0] - i, uw[:, 1] - j
    z = (1 - fw) * ((1 - fu) * h[i, j] + fu * h[i + 1, j])
    z += fw * ((1 - fu) * h[i, j + 1] + fu * h[i + 1, j + 1])
    starts = np.column_stack([uw, z + 1e-3])
    lit = np.empty(m, bool)
    _lit_many(h, tops, entry, starts, d, lit)
    t = np.empty(m)
    dirs = np.ascontiguousarray(np.broadcast_to(d, starts.shape))
    intersect_rays(h, valid, starts, dirs, np.zeros(m), np.full(m, 1e9), t)
    crossed = np.isfinite(t)
    assert np.mean(crossed) < 0.01  # the case: at most a few shadowed rays in 1000
    assert not np.any(lit & crossed)
    assert np.mean(lit[~crossed]) > 0.9


def _world(seed, emission, sun_elev, q, holes):
    """A rough patch (and a second one beside it), a camera ``emission`` deg off the patch normal with
    an OWEN distortion, a Sun ``sun_elev`` deg above the patch plane."""
    rng = np.random.default_rng(seed)
    ux, uy, uz = orient_frame(np.array([0.3, -0.2, 0.9]))
    v = np.array([0.3, -0.1, 0.4])
    scale = 0.002
    n = 2 * q + 1
    patches = []
    for k in range(2):
        h = np.cumsum(np.cumsum(rng.normal(size=(n, n)), 0), 1) * 0.08
        h += rng.normal(size=(n, n)) * 0.6
        h -= h.mean()
        valid = np.ones((n, n), bool)
        if holes:
            valid[rng.integers(0, n, 6), rng.integers(0, n, 6)] = False
            valid[q + 2 : q + 5, q - 6 : q - 3] = False
        alb = 1.0 + 0.2 * rng.uniform(-1, 1, size=(n, n))
        vk = v + k * 1.6 * q * scale * (ux + 0.3 * uy)
        patches.append(HeightPatch(h, scale, vk, ux, uy, uz, albedo=alb, valid=valid))
    el = math.radians(sun_elev)
    saz = rng.uniform(0, 2 * math.pi)
    sun = math.cos(el) * (math.cos(saz) * ux + math.sin(saz) * uy) + math.sin(el) * uz
    e = math.radians(emission)
    caz = rng.uniform(0, 2 * math.pi)
    look = math.cos(e) * uz + math.sin(e) * (math.cos(caz) * ux + math.sin(caz) * uy)
    pos = v + 0.6 * look
    npx = 90
    cam = Camera(
        mmfl=10.0,
        ctr=[(npx + 1) / 2 + 7.0, (npx + 1) / 2 - 5.0],  # the patch partly outside the window
        kmatrix=[[55.0, 0, 0], [0, 55.0, 0]],
        rotation=look_rotation(pos, v, 0.3),
        scobj=-pos,
        npx=npx,
        nln=npx,
        model="OWEN",
        coefficients=np.array([0, 1e-4, 2e-3, 0, 0, 1e-5, 0]),
    )
    return patches, sun, cam


#: (seed, emission, sun_elev, q, holes, ss, shading, shadows) of the worlds whose renders are compared
WORLDS = [
    (1, 10.0, 60.0, 14, False, 2, "smooth", True),
    (2, 65.0, 8.0, 14, True, 1, "facet", True),
    (3, 70.0, 35.0, 10, True, 3, "smooth", True),
    (4, 40.0, 3.0, 14, False, 2, "facet", True),
    (5, 0.0, 85.0, 12, True, 2, "smooth", True),
    (6, 60.0, 20.0, 14, True, 2, "smooth", False),
]


def assert_same_rendering(got, ref):
    """Coverage, shadow and surface equal, radiance to 1e-12 (the rounding the issue allows)."""
    np.testing.assert_array_equal(got.coverage, ref.coverage)
    np.testing.assert_array_equal(got.shadow, ref.shadow)
    np.testing.assert_array_equal(got.surface, ref.surface)
    np.testing.assert_allclose(got.radiance, ref.radiance, rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed, emission, sun_elev, q, holes, ss, shading, shadows", WORLDS)
def test_fast_render_equals_the_full_march(seed, emission, sun_elev, q, holes, ss, shading, shadows):
    patches, sun, cam = _world(seed, emission, sun_elev, q, holes)
    opts = RenderOptions(supersample=ss, shading=shading, shadows=shadows, ray_inverse="grid", threads=1)
    for plist in (patches[:1], patches):
        fast = render(cam, sun, None, plist, opts)
        ref = _render(cam, sun, None, plist, opts, None, None, fused=True, fast=False)
        assert 0.1 < np.mean(ref.coverage > 0) < 0.95  # the patch fills part of the window
        if shadows and sun_elev < 40:
            assert np.count_nonzero(ref.shadow) > 20
        assert_same_rendering(fast, ref)


@pytest.mark.parametrize("nss", [1, 2, 3, 4, 5, 7])
def test_bin_subrays_equals_the_numpy_means_bit_for_bit(nss):
    from spctool.geometry._rasterkernels import bin_subrays

    rng = np.random.default_rng(nss)
    nl, width = 7, 11
    n = nl * width * nss * nss
    r = rng.uniform(size=n) * rng.integers(0, 2, size=n)
    hit = rng.uniform(size=n) > 0.3
    sh = rng.uniform(size=n) > 0.7
    surface = rng.integers(-2, 3, size=n).astype(np.int32)
    rad, cov, shd = np.empty((nl, width)), np.empty((nl, width)), np.empty((nl, width))
    sid = np.empty((nl, width), np.int16)
    bin_subrays(r, hit, sh, surface, nss, rad, cov, shd, sid)
    shape4 = (nl, nss, width, nss)
    np.testing.assert_array_equal(rad, r.reshape(shape4).mean(axis=(1, 3)))
    np.testing.assert_array_equal(cov, hit.reshape(shape4).sum(axis=(1, 3)) / nss**2)
    np.testing.assert_array_equal(shd, sh.reshape(shape4).sum(axis=(1, 3)) / nss**2)
    np.testing.assert_array_equal(sid, surface.reshape(shape4)[:, 0, :, 0])


def test_bin_subrays_one_subray_keeps_the_sums_bits():
    """nss = 1 (image-space templates) copies each sub-ray as the loop of sums does: 0 + r, so −0 → +0
    and every other value (NaN, ±inf, subnormals) unchanged, bit for bit."""
    from spctool.geometry._rasterkernels import bin_subrays

    nl, width = 5, 9
    rng = np.random.default_rng(5)
    r = rng.normal(size=nl * width)
    r[:6] = [-0.0, 0.0, np.nan, np.inf, -np.inf, 5e-324]
    hit = rng.uniform(size=r.size) > 0.5
    sh = rng.uniform(size=r.size) > 0.5
    surface = rng.integers(-2, 3, size=r.size).astype(np.int32)
    rad, cov, shd = np.empty((nl, width)), np.empty((nl, width)), np.empty((nl, width))
    sid = np.empty((nl, width), np.int16)
    bin_subrays(r, hit, sh, surface, 1, rad, cov, shd, sid)
    want = (0.0 + (0.0 + r)).reshape(nl, width)
    np.testing.assert_array_equal(rad.view(np.uint64), want.view(np.uint64))
    assert rad[0, 0] == 0.0 and not np.signbit(rad[0, 0])
    np.testing.assert_array_equal(cov, hit.reshape(nl, width).astype(float))
    np.testing.assert_array_equal(shd, sh.reshape(nl, width).astype(float))
    np.testing.assert_array_equal(sid, surface.reshape(nl, width))


@pytest.mark.parametrize(
    "azimuth, elevation",
    [(0.0, 40.0), (90.0, 55.0), (37.0, 50.0), (210.0, 65.0), (300.0, 30.0), (45.0, 45.0), (123.0, 88.0)],
)
@pytest.mark.parametrize("holes", [False, True])
def test_lit_corridor_clears_only_cells_whose_rays_rise_over_the_terrain(azimuth, elevation, holes):
    """:func:`spctool.geometry._patchkernels.lit_corridor` by brute force: from points of every cleared cell
    (corners and edges included), the ray toward the Sun — sampled every ~0.005 cells of travel up to the
    reach along its dominant axis — stays over full cells and its height above the bilinear terrain never
    decreases (the shortcut's claim: no crossing there).  And it does more than the isotropic ``near``
    bound on a rough terrain: it clears cells where that one does not."""
    from spctool.geometry.surfaces import LIT_CELLS, PatchSet

    rng = np.random.default_rng(int(azimuth) + int(elevation) + 1000 * holes)
    q = 12
    n = 2 * q + 1
    x = np.arange(n)
    h = 5.0 * np.sin(x[:, None] / 3.0) * np.cos(x[None, :] / 4.0) + rng.normal(size=(n, n)) * 0.6
    valid = np.ones((n, n), bool)
    if holes:
        valid[rng.integers(0, n, 8), rng.integers(0, n, 8)] = False
    ux, uy, uz = orient_frame(np.array([0.2, 0.5, 0.8]))
    scale = 0.003
    p = HeightPatch(h, scale, np.array([0.1, 0.2, 0.3]), ux, uy, uz, valid=valid)
    au, aw, az = _direction(azimuth, elevation)
    sun = au * ux + aw * uy + az * uz
    arrays = PatchSet([p]).fused_arrays(sun)
    geo, clear, near = arrays[0], arrays[10][0], arrays[9][0]
    s = sun
    b0, b1, b2 = (
        (s[0] * geo[0, 7 + c] + s[1] * geo[0, 10 + c] + s[2] * geo[0, 13 + c]) * geo[0, 16] for c in range(3)
    )
    hh = np.where(valid, h, 0.0)
    full = valid[:-1, :-1] & valid[1:, :-1] & valid[:-1, 1:] & valid[1:, 1:]
    assert not np.any(clear & ~full)
    lead = max(abs(b0), abs(b1))
    t = np.linspace(0.0, LIT_CELLS / lead, 401)
    for i, j in np.argwhere(clear):
        for fu, fw in [(0.0, 0.0), (1.0, 1.0), (0.0, 1.0), (1.0, 0.0), *rng.uniform(size=(4, 2))]:
            uu, ww = i + fu + b0 * t, j + fw * 1.0 + b1 * t
            inside = (uu >= 0) & (uu <= n - 1) & (ww >= 0) & (ww <= n - 1)
            uu, ww, tt = uu[inside], ww[inside], t[inside]
            ci, cj = np.minimum(uu.astype(int), n - 2), np.minimum(ww.astype(int), n - 2)
            assert full[ci, cj].all()
            gu, gw = uu - ci, ww - cj
            terrain = (1 - gw) * ((1 - gu) * hh[ci, cj] + gu * hh[ci + 1, cj]) + gw * (
                (1 - gu) * hh[ci, cj + 1] + gu * hh[ci + 1, cj + 1]
            )
            above = b2 * tt - terrain
            assert np.all(np.diff(above) >= -1e-9 * (1.0 + np.abs(above[1:])))
    with np.errstate(invalid="ignore"):  # +inf (a missing corner near) × 0 (the Sun along an axis)
        near_ok = b2 > near[..., 2] * abs(b0) + near[..., 3] * abs(b1)
    if 50.0 <= elevation <= 65.0 and not holes:
        assert np.count_nonzero(clear & ~near_ok) > 0.05 * clear.size
