"""spctool.stages.render against analytic cases: a tilted plane's brightness, a sphere's terminator, a
block's shadow length; the patch/shape composition rule; windows and supersampling."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool.errors import SpcUsageError
from spctool.formats.icq import IcqShape, icq_cube_grid
from spctool.geometry.camera import Camera
from spctool.geometry.frames import look_rotation, orient_frame
from spctool.geometry.surfaces import HeightPatch, PatchSet, ShapeSurface
from spctool.photometry import phase_angle_deg, reflectance
from spctool.stages.render import SHAPE, SKY, RenderOptions, cull_patches, render, trace


def _camera(position, target, npx=200, nln=200, mmfl=10.0, k=100.0, roll=0.0, model="NONE", coef=()):
    return Camera(
        mmfl=mmfl,
        ctr=[(npx + 1) / 2, (nln + 1) / 2],
        kmatrix=[[k, 0, 0], [0, k, 0]],
        rotation=look_rotation(position, target, roll),
        scobj=-np.asarray(position, float),
        npx=npx,
        nln=nln,
        model=model,
        coefficients=np.asarray(coef, float),
    )


def _frame(normal=(0.3, -0.2, 0.9)):
    ux, uy, uz = orient_frame(np.asarray(normal, float))
    return ux, uy, uz


def _pixels(cam, window=None):
    s0, s1, l0, l1 = window or (1, cam.npx, 1, cam.nln)
    ll, ss = np.mgrid[l0 : l1 + 1, s0 : s1 + 1].astype(float)
    return ss, ll


# ------------------------------------------------------------------------------------------------
# a tilted plane


@pytest.mark.parametrize("model", ["lambert", "spc", "mcewen"])
def test_tilted_plane_brightness_is_the_photometric_law(model):
    ux, uy, uz = _frame()
    v = np.array([0.2, 0.05, 0.3])
    scale, q, a, b = 0.001, 30, 0.3, -0.2
    x = np.arange(-q, q + 1.0)
    heights = a * x[:, None] + b * x[None, :]  # x along UX (axis 0), y along UY (axis 1)
    patch = HeightPatch(heights, scale, v, ux, uy, uz, albedo=np.full(heights.shape, 0.8))
    n = -a * ux - b * uy + uz
    n /= np.linalg.norm(n)
    sun = n + 0.6 * ux + 0.2 * uy
    sun /= np.linalg.norm(sun)
    pos = v + 0.15 * (uz + 0.4 * uy - 0.3 * ux)
    cam = _camera(pos, v, model="OWEN", coef=[0, 1e-4, 2e-3, 0, 0, 1e-5, 0])
    r = render(cam, sun, None, [patch], RenderOptions(photometry=model))
    # independent: ray–plane intersection and the law evaluated by hand
    ss, ll = _pixels(cam)
    d = cam.pixel_to_direction(ss.ravel(), ll.ravel())
    o = cam.position
    t = ((v - o) @ n) / (d @ n)
    hit_pt = o + t[:, None] * d
    loc = (hit_pt - v) @ np.column_stack([ux, uy, uz]) / scale
    inside = (np.abs(loc[:, 0]) < q - 1e-6) & (np.abs(loc[:, 1]) < q - 1e-6)
    e = -d
    want = reflectance(np.full(d.shape[0], n @ sun), e @ n, phase_angle_deg(sun, e), model) * 0.8
    got = r.radiance.ravel()
    assert inside.sum() > 5000
    np.testing.assert_allclose(got[inside], want[inside], rtol=1e-9, atol=1e-12)
    assert np.all(r.surface.ravel()[inside] == 0) and np.all(r.shadow.ravel()[inside] == 0)
    assert np.all(got[~inside & (r.coverage.ravel() == 0)] == 0)
    # the crossing itself is exact
    hits = trace(o, d[inside], None, [patch])
    np.testing.assert_allclose(hits.t, t[inside], rtol=1e-10)


# ------------------------------------------------------------------------------------------------
# a sphere


@pytest.fixture(scope="module")
def sphere():
    q = 32
    g = icq_cube_grid(q)
    return IcqShape(q, g / np.linalg.norm(g, axis=-1, keepdims=True))  # R = 1 km


def test_sphere_terminator_and_lambert_shading(sphere):
    cam = _camera([0.0, -6.0, 0.0], [0.0, 0.0, 0.0], npx=400, nln=400)
    sun = np.array([1.0, 0.0, 0.0])
    r = render(cam, sun, sphere, [], RenderOptions(photometry="lambert"))
    ctr = cam.ctr[0]
    # the terminator (the great circle x = 0) contains the camera: it projects to a straight line
    # through the photo centre; CX = z x CZ = -x, so the lit (x > 0) side is at small samples
    assert cam.rotation[0] @ np.array([1.0, 0, 0]) == pytest.approx(-1.0)
    ss, ll = _pixels(cam)
    d = cam.pixel_to_direction(ss.ravel(), ll.ravel())
    hits = trace(cam.position, d, ShapeSurface.from_model(sphere))
    x = hits.point[:, 0] / np.linalg.norm(hits.point, axis=1)  # the true mu0 = x/R at the hit
    body = (r.coverage == 1.0).ravel()
    # away from the limb (grazing rays: emission ~90°) ...
    centre = -cam.position / np.linalg.norm(cam.position)
    theta = np.arccos(np.clip(d @ centre, -1, 1))
    limb_px = (math.asin(1.0 / np.linalg.norm(cam.position)) - theta) / cam.ifov  # > 0 inside the disc
    inner = body & (limb_px > 3)
    # ... the lit side (x > 0) is lit and the night side dark.  Within about one facet angle of the
    # terminator (q = 32: 2.8°, mu0 < 0.05) the next facet of the ICQ model casts its shadow, as the
    # faceted shape really does; 0.08 leaves room for that.
    rad = r.radiance.ravel()
    assert np.all(rad[inner & (x > 0.08)] > 0)
    assert np.all(rad[inner & (x < -0.005)] == 0)
    # in pixels: the terminator is the photo's centre column
    assert np.all(rad[inner & (ss.ravel() < ctr - 15)] > 0) and np.all(
        rad[inner & (ss.ravel() > ctr + 3)] == 0
    )
    # Lambert on the lit side: mu0 = n.s with n the sphere's radial direction at the hit
    lit = inner & (x > 0.08)
    np.testing.assert_allclose(rad[lit], x[lit], atol=0.01)
    # the limb: every body pixel's ray meets the unit sphere, sky pixels' rays miss it (±1 px)
    assert np.all(body[limb_px > 1.5]) and not np.any(r.coverage.ravel()[limb_px < -1.5])


# ------------------------------------------------------------------------------------------------
# a block's shadow


def test_shadow_length_behind_a_block():
    ux, uy, uz = _frame((0.1, 0.2, 1.0))
    v = np.array([0.05, 0.1, 0.5])
    scale, q, height = 0.001, 40, 6.0
    h = np.zeros((2 * q + 1, 2 * q + 1))
    x0, x1, y0, y1 = 10, 14, -5, 5  # block nodes (cells); walls slope over one cell
    h[q + x0 : q + x1 + 1, q + y0 : q + y1 + 1] = height
    patch = HeightPatch(h, scale, v, ux, uy, uz)
    elev = math.radians(30.0)
    sun = math.cos(elev) * ux + math.sin(elev) * uz  # the Sun low in the +x direction
    cam = _camera(v + 0.25 * uz, v, npx=300, nln=300)  # nadir, 0.25 m per pixel = 4 px per cell
    r = render(cam, sun, None, [patch], RenderOptions(photometry="lambert"))
    ss, ll = _pixels(cam)
    d = cam.pixel_to_direction(ss.ravel(), ll.ravel())
    hits = trace(cam.position, d, None, [patch])
    x, y = hits.local[:, 0], hits.local[:, 1]
    ground = (hits.surface == 0) & (np.abs(hits.local[:, 2]) < 1e-9)
    dark = r.radiance.ravel() == 0
    row = ground & (np.abs(y) < 3) & (x < x0 - 1)
    # the top edge at x0 casts its shadow to x0 − H/tan(elevation)
    end = x0 - height / math.tan(elev)
    shadowed_x = x[row & dark]
    assert shadowed_x.min() == pytest.approx(end, abs=0.3)  # one pixel is 0.25 cells
    assert np.all(~dark[row & (x < end - 0.3)])
    # lit ground is Lambert cos(60°); no shadow beside the block
    assert np.allclose(r.radiance.ravel()[row & (x < end - 0.3)], math.sin(elev), rtol=1e-9)
    beside = ground & (np.abs(y) > y1 + 2) & (x > end) & (x < x0 - 1)
    assert beside.sum() > 100 and not np.any(dark[beside])
    # beyond the wall's foot (where the interpolated normals of the wall tilt away) it is cast shadow
    assert r.shadow.ravel()[row & dark & (x < x0 - 2)].min() == 1.0
    # without shadows the same ground is lit
    r2 = render(cam, sun, None, [patch], RenderOptions(photometry="lambert", shadows=False))
    assert np.all(r2.radiance.ravel()[row & (x < x0 - 2)] > 0.4)


# ------------------------------------------------------------------------------------------------
# composition, windows, supersampling


def test_patch_replaces_the_shape_in_its_footprint(sphere):
    surf = ShapeSurface.from_model(sphere)
    ux, uy, uz = orient_frame(np.array([0.0, 0.0, 1.0]))
    q, scale = 20, 0.01
    x = np.arange(-q, q + 1.0)
    rr = (x[:, None] ** 2 + x[None, :] ** 2) * scale**2
    sphere_h = (np.sqrt(1.0 - rr) - 1.0) / scale  # the sphere under the patch, in cells
    patch = HeightPatch(sphere_h - 0.5, scale, [0, 0, 1.0], ux, uy, uz)  # half a cell *below* the shape
    cam = _camera([0.0, 0.0, 3.0], [0.0, 0.0, 0.0], npx=160, nln=160)
    r = render(cam, [0.3, 0.2, 1.0], surf, [patch])
    ss, ll = _pixels(cam)
    d = cam.pixel_to_direction(ss.ravel(), ll.ravel())
    hits = trace(cam.position, d, surf, [patch])
    in_fp = (np.abs(hits.local[:, 0]) < q) & (np.abs(hits.local[:, 1]) < q)
    assert np.all(hits.surface[hits.surface == 0] == 0) and in_fp.sum() > 1000
    # inside the footprint the lower patch wins although the shape is nearer
    res = surf.shape.first_hit(cam.position, d)
    inner = in_fp & (np.abs(hits.local[:, 0]) < q - 2) & (np.abs(hits.local[:, 1]) < q - 2)
    assert np.all(hits.surface[inner] == 0) and np.all(hits.t[inner] > res.t[inner])
    outside = res.hit & (hits.surface == SHAPE)
    np.testing.assert_array_equal(hits.t[outside], res.t[outside])
    assert np.all(r.surface[r.coverage == 0] == SKY)


def test_window_is_a_crop_and_supersampling_counts_subrays(sphere):
    cam = _camera([0.0, -4.0, 1.0], [0.0, 0.0, 0.0], npx=120, nln=100, k=20.0)
    opt = RenderOptions(supersample=3)
    full = render(cam, [1.0, -0.5, 0.3], sphere, [], opt)
    win = (20, 70, 31, 60)
    part = render(cam, [1.0, -0.5, 0.3], sphere, [], opt, window=win)
    s0, s1, l0, l1 = win
    np.testing.assert_array_equal(part.radiance, full.radiance[l0 - 1 : l1, s0 - 1 : s1])
    np.testing.assert_array_equal(part.coverage, full.coverage[l0 - 1 : l1, s0 - 1 : s1])
    frac = full.coverage * 9
    assert np.allclose(frac, np.round(frac)) and np.any((full.coverage > 0) & (full.coverage < 1))
    with pytest.raises(SpcUsageError):
        render(cam, [1, 0, 0], sphere, [], window=(10, 5, 1, 2))


def test_cull_patches_keeps_what_the_camera_can_see():
    cam = _camera([0.0, 0.0, 2.0], [0.0, 0.0, 0.0], npx=100, nln=100)
    ux, uy, uz = orient_frame(np.array([0.0, 0.0, 1.0]))

    def mk(c):
        return HeightPatch(np.zeros((11, 11)), 0.001, c, ux, uy, uz)

    seen = mk([0.0, 0.0, 1.0])
    off = mk([0.5, 0.0, 1.0])  # ~27° off the boresight; the half field of view is ~2.9°
    behind = mk([0.0, 0.0, 3.0])
    kept = cull_patches(cam, [seen, off, behind])
    assert kept == [seen]


def test_height_patch_validation():
    ux, uy, uz = orient_frame(np.array([0.0, 0.0, 1.0]))
    with pytest.raises(SpcUsageError):
        HeightPatch(np.zeros((4, 4)), 0.001, [0, 0, 1], ux, uy, uz)
    with pytest.raises(SpcUsageError):
        HeightPatch(np.zeros((5, 5)), 0.0, [0, 0, 1], ux, uy, uz)
    with pytest.raises(SpcUsageError):
        HeightPatch(np.zeros((5, 5)), 0.001, [0, 0, 1], ux, uy, uz, valid=np.zeros((5, 5), bool))
    with pytest.raises(SpcUsageError):
        RenderOptions(photometry="phong")


# ------------------------------------------------------------------------------------------------
# the fused patch-only path (register's image-space templates) equals trace → shadowed → shade


def _rough_patches():
    """Two overlapping rough patches (different sizes, a hole of invalid nodes, an albedo map)."""
    rng = np.random.default_rng(7)
    ux, uy, uz = _frame((0.2, -0.1, 1.0))
    v = np.array([0.3, -0.1, 0.9])
    out = []
    for q, scale, shift in ((24, 0.002, 0.0), (15, 0.0015, 0.012)):
        n = 2 * q + 1
        h = rng.normal(size=(n, n)).cumsum(0).cumsum(1) * 0.05
        h -= h.mean()
        h += 3.0 * np.exp(-((np.arange(n)[:, None] - q) ** 2 + (np.arange(n)[None, :] - q) ** 2) / 40.0)
        valid = np.ones((n, n), bool)
        valid[q + 3 : q + 6, q - 8 : q - 5] = False
        alb = 1.0 + 0.2 * rng.uniform(-1, 1, size=(n, n))
        out.append(HeightPatch(h, scale, v + shift * (ux + 0.5 * uy), ux, uy, uz, albedo=alb, valid=valid))
    elev = math.radians(22.0)
    sun = math.cos(elev) * (0.8 * ux + 0.6 * uy) + math.sin(elev) * uz
    cam = _camera(
        v + 0.2 * (uz + 0.35 * ux - 0.2 * uy),
        v,
        npx=110,
        nln=100,
        model="OWEN",
        coef=[0, 1e-4, 2e-3, 0, 0, 1e-5, 0],
    )
    return out, 3.0 * sun, cam  # an unnormalised Sun vector on purpose


@pytest.mark.parametrize(
    "opts",
    [
        RenderOptions(),
        RenderOptions(supersample=2, photometry="mcewen"),
        RenderOptions(photometry="lambert", use_albedo=False),
        RenderOptions(photometry="fixed", shadows=False),
        RenderOptions(shading="facet", ray_inverse="grid", threads=1),
        RenderOptions(shading="gouraud", supersample=2, photometry="mcewen"),
    ],
)
def test_fused_patch_path_equals_the_general_path(opts):
    from spctool.stages.render import _render

    patches, sun, cam = _rough_patches()
    win = (5, 104, 3, 97)
    fast = render(cam, sun, None, patches, opts, window=win)
    ref = _render(cam, sun, None, patches, opts, win, None, fused=False)
    assert np.count_nonzero(ref.surface == 1) > 500 and np.count_nonzero(ref.surface == 0) > 500
    if opts.shadows:
        assert 200 < np.count_nonzero(ref.shadow) < ref.shadow.size // 2
    # rounding relative to the image's scale: near the terminator a pixel is a small difference, and a
    # CPU whose numba build fuses multiply-adds differently rounds it differently (test_register)
    np.testing.assert_allclose(fast.radiance, ref.radiance, rtol=0, atol=1e-12 * np.abs(ref.radiance).max())
    np.testing.assert_array_equal(fast.coverage, ref.coverage)
    np.testing.assert_array_equal(fast.shadow, ref.shadow)
    np.testing.assert_array_equal(fast.surface, ref.surface)
    # one patch alone, as register renders its templates
    fast1 = render(cam, sun, None, patches[:1], opts, window=win)
    ref1 = _render(cam, sun, None, patches[:1], opts, win, None, fused=False)
    scale1 = np.abs(ref1.radiance).max()
    np.testing.assert_allclose(fast1.radiance, ref1.radiance, rtol=0, atol=1e-12 * scale1)
    np.testing.assert_array_equal(fast1.shadow, ref1.shadow)


def test_fused_threads_equal_one_thread_and_bad_rays_are_sky(monkeypatch):
    import spctool.stages.render as rmod

    patches, sun, cam = _rough_patches()
    ss, ll = _pixels(cam)
    d = cam.pixel_to_direction(ss.ravel(), ll.ravel())
    d[::97] = np.nan  # rays without a preimage (a folding distortion) are sky
    ok = np.all(np.isfinite(d), axis=1)
    s = sun / np.linalg.norm(sun)
    pset = PatchSet(patches)
    args = (cam.position, d, ok, s, s, True, 1e-3, pset.fused_arrays())
    one = rmod._trace_fused(*args, threads=1)
    monkeypatch.setattr(rmod, "PARALLEL_MIN_RAYS", 1000)
    three = rmod._trace_fused(*args, threads=3)
    hit = one[0] != SKY
    np.testing.assert_array_equal(one[0], three[0])
    np.testing.assert_array_equal(one[1][hit], three[1][hit])
    np.testing.assert_array_equal(one[2], three[2])
    hit, r, sh, surface = rmod._fused_chunk(cam.position, d, ok, s, pset, RenderOptions())
    assert np.all(surface[~ok] == SKY) and not np.any(hit[~ok] | sh[~ok]) and np.all(r[~ok] == 0)
    ref = trace(cam.position, np.where(ok[:, None], d, 0.0), None, pset)
    np.testing.assert_array_equal(surface[ok], ref.surface[ok])


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    q=st.integers(1, 6),
    base=st.sampled_from([0.0, -3.0, 250.0]),
    holes=st.booleans(),
)
def test_passing_over_cells_below_the_ray_changes_nothing(seed, q, base, holes):
    """The crossing kernel's cell-top skip (cells whose segment lies above their highest corner are
    passed over) gives bit for bit what the kernel gives with no skipping at all (tops = +inf): viewing
    rays from above, shadow-like rays from just above the terrain, and rays with zero direction
    components, against rough terrains with and without missing nodes."""
    from spctool.geometry._heightkernels import _first_crossing

    rng = np.random.default_rng(seed)
    n = 2 * q + 1
    h = base + rng.normal(size=(n, n)).cumsum(0) * rng.uniform(0.1, 2.0)
    valid = rng.uniform(size=(n, n)) > 0.2 if holes else None
    patch = HeightPatch(h, 0.001, [0, 0, 1.0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], valid=valid)
    hh, vv, tops = patch.heights, patch.valid, patch.cell_tops
    lo, hi = patch.height_range
    for k in range(60):
        d = rng.normal(size=3)
        if k % 3 == 0:  # a shadow ray: from just above the terrain at a random point, upward
            u0, w0 = rng.uniform(0, n - 1, size=2)
            z0 = float(patch.interpolate(u0 - q, w0 - q)[0]) + 1e-3
            d[2] = abs(d[2])
        else:  # a viewing ray from above, from anywhere around the grid
            u0, w0 = rng.uniform(-3, n + 2, size=2)
            z0 = hi + rng.uniform(0, 3)
            d[2] = -abs(d[2])
        if k % 5 == 1:
            d[rng.integers(0, 3)] = 0.0
        if k % 11 == 2:
            d[:2] = 0.0
        t0 = 0.0 if k % 2 else rng.uniform(0, 0.5)
        args = (lo, hi, u0, w0, z0, d[0], d[1], d[2], t0, t0 + rng.uniform(0.5, 30.0))
        no_skip = np.where(np.isfinite(tops), np.inf, tops)  # missing-corner cells stay closed
        want = _first_crossing(hh, vv, no_skip, *args)
        got = _first_crossing(hh, vv, tops, *args)
        assert (math.isnan(want) and math.isnan(got)) or got == want, (k, want, got)


# ------------------------------------------------------------------------------------------------
# facet shading (register's --template-shading facet)


def _triangle_hits(o, d, tri):
    """Independent Möller–Trumbore: nearest t and triangle index of rays o + t·d (brute force)."""
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    best_t = np.full(d.shape[0], np.inf)
    best_k = np.full(d.shape[0], -1)
    for k in range(tri.shape[0]):
        p = np.cross(d, e2[k])
        det = p @ e1[k]
        s = o - tri[k, 0]
        u = (p @ s) / det
        qv = np.cross(s, e1[k])
        v = (qv @ d.T) / det
        t = (qv @ e2[k]) / det
        ok = (u >= -1e-12) & (v >= -1e-12) & (u + v <= 1 + 1e-12) & (t > 0) & (t < best_t)
        best_t[ok] = t[ok]
        best_k[ok] = k
    return best_t, best_k


def _planar_facet_scene(seed):
    """A planar-facet scene (heights f(x) + g(y), piecewise linear: every cell is flat, each face tilts
    its own way) and the brute-force crossing of every pixel-centre ray with its triangles (two per
    cell along the (i, j)-(i+1, j+1) diagonal, Möller–Trumbore): a dict of the frame, patch, Sun and
    camera and, per pixel, ``t``, the triangle index ``k`` (−1: no hit), ``hit``, the ray ``d``, the
    ``tris`` and the hit's maplet coordinates ``loc``."""
    ux, uy, uz = _frame()
    v = np.array([0.2, 0.05, 0.3])
    scale, q = 0.001, 8
    rng = np.random.default_rng(seed)
    f = np.concatenate([[0.0], np.cumsum(rng.uniform(-0.8, 0.8, 2 * q))])
    g = np.concatenate([[0.0], np.cumsum(rng.uniform(-0.8, 0.8, 2 * q))])
    heights = f[:, None] + g[None, :]
    alb = 1.0 + 0.3 * rng.uniform(-1, 1, heights.shape)
    patch = HeightPatch(heights, scale, v, ux, uy, uz, albedo=alb)
    sun = 0.5 * ux + 0.3 * uy + uz
    sun /= np.linalg.norm(sun)
    cam = _camera(v + 0.05 * (uz + 0.2 * ux - 0.1 * uy), v, npx=60, nln=60)
    n = 2 * q + 1
    idx = np.arange(n) - q
    xx, yy = np.meshgrid(idx, idx, indexing="ij")
    nodes = patch.to_body(np.stack([xx, yy, heights], -1).reshape(-1, 3)).reshape(n, n, 3)
    tris = []
    for i in range(n - 1):
        for j in range(n - 1):
            tris.append([nodes[i, j], nodes[i + 1, j], nodes[i + 1, j + 1]])
            tris.append([nodes[i, j], nodes[i, j + 1], nodes[i + 1, j + 1]])
    tris = np.array(tris)
    ss, ll = _pixels(cam)
    d = cam.pixel_to_direction(ss.ravel(), ll.ravel())
    t, k = _triangle_hits(cam.position, d, tris)
    hit = k >= 0
    loc = patch.to_local(np.where(hit[:, None], cam.position + t[:, None] * d, v))
    return dict(ux=ux, uy=uy, uz=uz, v=v, q=q, heights=heights, alb=alb, patch=patch, sun=sun, cam=cam,
                tris=tris, d=d, t=t, k=k, hit=hit, loc=loc)  # fmt: skip


def test_facet_shading_is_per_triangle_lambert():
    """A planar-facet scene (heights f(x) + g(y), piecewise linear: every cell is flat, each face tilts
    its own way) rendered with ``shading="facet"`` equals an independent computation: rays through the
    pixel centres meet the triangles (brute-force Möller–Trumbore), radiance = Lambert μ₀ of the hit
    triangle's normal times the bilinear albedo.  The smooth shading (interpolated node slopes) does
    not: that is what the option is for."""
    sc = _planar_facet_scene(5)
    ux, uy, uz, v, q, patch, sun, cam = (sc[x] for x in ("ux", "uy", "uz", "v", "q", "patch", "sun", "cam"))
    opts = RenderOptions(photometry="lambert", shadows=False, shading="facet")
    got = render(cam, sun, None, [patch], opts)
    smooth = render(cam, sun, None, [patch], RenderOptions(photometry="lambert", shadows=False))
    tris, k, hit, loc = sc["tris"], sc["k"], sc["hit"], sc["loc"]
    nrm = np.cross(tris[k, 1] - tris[k, 0], tris[k, 2] - tris[k, 0])
    nrm *= np.sign(nrm @ uz)[:, None]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    a = patch.interpolate(loc[:, 0], loc[:, 1])[3]
    want = np.where(hit, np.maximum(nrm @ sun, 0.0) * a, 0.0)
    inner = hit & (np.abs(loc[:, 0]) < q - 0.01) & (np.abs(loc[:, 1]) < q - 0.01)
    assert inner.sum() > 1500
    np.testing.assert_allclose(got.radiance.ravel()[inner], want[inner], rtol=1e-9, atol=1e-12)
    assert np.max(np.abs(smooth.radiance.ravel()[inner] - want[inner])) > 0.05


def test_gouraud_shading_interpolates_the_node_radiances():
    """``shading="gouraud"`` equals an independent computation on the planar-facet scene of the facet
    test (every cell flat, so each ray's hit is a brute-force triangle crossing): the radiance at each
    node — Lambert μ₀ of the normal from the central-difference node slopes, times the albedo —
    interpolated bilinearly at the hit.  It differs from the smooth shading (the interpolated slopes
    shaded), and :func:`node_radiance` is SPC's prediction (Stage B) at the nodes."""
    from spctool.stages.predict import PredictOptions, predict
    from spctool.stages.render import node_radiance

    sc = _planar_facet_scene(11)
    ux, uy, uz, v, q, patch, sun, cam = (sc[x] for x in ("ux", "uy", "uz", "v", "q", "patch", "sun", "cam"))
    heights, alb = sc["heights"], sc["alb"]
    opts = RenderOptions(photometry="lambert", shadows=False, shading="gouraud")
    got = render(cam, sun, None, [patch], opts)
    smooth = render(cam, sun, None, [patch], RenderOptions(photometry="lambert", shadows=False))
    # independent: node normals from central differences (interior nodes), Lambert at the nodes
    n = 2 * q + 1
    hx = np.zeros((n, n))
    hy = np.zeros((n, n))
    hx[1:-1] = 0.5 * (heights[2:] - heights[:-2])
    hy[:, 1:-1] = 0.5 * (heights[:, 2:] - heights[:, :-2])
    nrm = -hx[..., None] * ux - hy[..., None] * uy + uz
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    node_r = np.maximum(nrm @ sun, 0.0) * alb
    hit, loc = sc["hit"], sc["loc"]
    # cells whose four corners are interior nodes (central differences there)
    inner = hit & (np.abs(loc[:, 0]) < q - 1.01) & (np.abs(loc[:, 1]) < q - 1.01)
    assert inner.sum() > 1000
    u, w = loc[inner, 0] + q, loc[inner, 1] + q
    i, j = np.floor(u).astype(int), np.floor(w).astype(int)
    fu, fw = u - i, w - j
    want = (
        (1 - fu) * (1 - fw) * node_r[i, j] + fu * (1 - fw) * node_r[i + 1, j]
        + (1 - fu) * fw * node_r[i, j + 1] + fu * fw * node_r[i + 1, j + 1]
    )  # fmt: skip
    np.testing.assert_allclose(got.radiance.ravel()[inner], want, rtol=1e-9, atol=1e-12)
    assert np.max(np.abs(smooth.radiance.ravel()[inner] - want)) > 0.01
    # node_radiance is the prediction at the nodes (a camera far along the view: one view direction)
    e = uz + 0.2 * ux - 0.1 * uy
    far = v + 1e9 * e / np.linalg.norm(e)
    for model in ("spc", "lambert"):
        pred = predict(patch, far, sun, PredictOptions(photometry=model, shadows="spc"))
        nr = node_radiance(patch, far, sun, RenderOptions(photometry=model))
        np.testing.assert_allclose(nr[pred.lit], pred.image[pred.lit], rtol=1e-9)
        assert pred.lit.sum() > 200 and np.all(nr[~pred.lit] <= 1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("angle", [0.0, 20.0, 45.0, 90.0, 135.0, 200.0, 260.0, 315.0, 333.0])
def test_upwind_max_bounds_every_cell_a_ray_passes(angle):
    """_upwind_max (the shadow march's early end) is a true bound: rays from random points of a cell,
    sampled finely along their horizontal path to the grid edge, never pass over a cell whose top
    exceeds the cell's value."""
    from spctool.geometry._heightkernels import _upwind_max

    rng = np.random.default_rng(int(angle))
    tops = rng.normal(size=(23, 19)) + 3.0 * (rng.uniform(size=(23, 19)) > 0.95)
    au, aw = math.cos(math.radians(angle)), math.sin(math.radians(angle))
    out = np.empty_like(tops)
    _upwind_max(tops, au, aw, out)
    n0, n1 = tops.shape
    for _ in range(400):
        i, j = rng.integers(0, n0), rng.integers(0, n1)
        u, w = i + rng.uniform(), j + rng.uniform()
        rho = np.arange(0.0, 60.0, 0.01)
        uu, ww = u + rho * au, w + rho * aw
        keep = (uu >= 0) & (uu < n0) & (ww >= 0) & (ww < n1)
        seen = tops[uu[keep].astype(int), ww[keep].astype(int)]
        assert seen.max() <= out[i, j]
    assert np.all(out >= tops)
