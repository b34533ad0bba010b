"""Tests of spctool.stages.extract (Stages C, D, E).

Independent references: scipy's map_coordinates for the bilinear sampler, hand-worked BRT0 cases, an
independent ray-cast renderer (appearance_scene.render) for the end-to-end extraction, hand-built
topography and hand counts for the filter and the statistics, a plain-Python loop for the shadow
enhancement with a diagonal Sun.
"""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import appearance_scene as sc
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.ndimage import map_coordinates

from spctool.errors import SpcUsageError
from spctool.geometry import frames
from spctool.geometry.camera import Camera
from spctool.stages.extract import (
    PRESETS,
    Criteria,
    ExtractOptions,
    brt0,
    extract,
    extract_filter,
    nint,
    shadow_extension,
    shadow_offsets,
    subsample_count,
)
from spctool.stages.predict import pearson, predict

# ------------------------------------------------------------------------------------------------
# BRT0


def test_brt0_matches_bilinear_interpolation_inside():
    rng = np.random.default_rng(3)
    data = rng.uniform(10.0, 200.0, (30, 40))
    s = rng.uniform(1.0, 39.999, 500)
    ln = rng.uniform(1.0, 29.999, 500)
    ref = map_coordinates(data, [ln - 1.0, s - 1.0], order=1)
    np.testing.assert_allclose(brt0(data, s, ln), ref, rtol=1e-13)


def test_brt0_hand_cases():
    data = np.array([[10.0, 20.0, 30.0], [40.0, 50.0, 60.0], [70.0, 80.0, 90.0]])
    # sample 1.5, line 1.25: corners (1,1)=10, (2,1)=20, (1,2)=40, (2,2)=50
    assert brt0(data, 1.5, 1.25) == pytest.approx(10 + 10 * 0.5 + 30 * 0.25)
    assert brt0(data, 1.0, 1.0) == 10.0
    # domain: 1 <= sample < NPX, 1 <= line < NLN
    assert brt0(data, 3.0, 1.5) == 0.0 and brt0(data, 2.999, 1.5) > 0.0
    assert brt0(data, 1.5, 3.0) == 0.0 and brt0(data, 1.5, 2.999) > 0.0
    assert brt0(data, 0.999, 1.5) == 0.0 and brt0(data, 1.5, 0.999) == 0.0
    assert brt0(data, np.nan, 1.5) == 0.0
    out = brt0(data, np.array([[1.5, 2.5]]), np.array([[1.5], [2.5]]))
    assert out.shape == (2, 2)


def test_brt0_one_missing_corner_is_repaired():
    # b0 = (1,1) missing: b0 <- max(1, b1 + b2 - b3)
    d = np.array([[0.0, 20.0], [40.0, 50.0]])
    fx, fy = 0.3, 0.6
    b0 = max(1.0, 20 + 40 - 50)
    expect = b0 + (20 - b0) * fx + (40 - b0) * fy + (b0 + 50 - 20 - 40) * fx * fy
    assert brt0(d, 1 + fx, 1 + fy) == pytest.approx(expect)
    # the repair is clamped at 1 (max(1, 20 + 40 - 100) = 1)
    d = np.array([[0.0, 20.0], [40.0, 100.0]])
    b0 = 1.0
    expect = b0 + (20 - b0) * fx + (40 - b0) * fy + (b0 + 100 - 20 - 40) * fx * fy
    assert brt0(d, 1 + fx, 1 + fy) == pytest.approx(expect)
    # each corner position: b1 = (2,1), b2 = (1,2), b3 = (2,2)
    full = np.array([[10.0, 20.0], [40.0, 70.0]])  # planar: 10 + 10 s + 30 l + 20 s l ... not planar
    for (r, c), rebuilt in {(0, 1): 10 + 70 - 40, (1, 0): 10 + 70 - 20, (1, 1): 20 + 40 - 10}.items():
        d = full.copy()
        d[r, c] = 0.0
        e = d.copy()
        e[r, c] = rebuilt
        assert brt0(d, 1.4, 1.7) == pytest.approx(map_coordinates(e, [[0.7], [0.4]], order=1)[0])
    # two missing corners: invalid
    d = np.array([[0.0, 20.0], [0.0, 50.0]])
    assert brt0(d, 1.5, 1.5) == 0.0


def test_brt0_thresholds_and_clipping():
    d = np.array([[100.0, 200.0], [300.0, 5000.0]])
    # DN above T2 counts as missing (and is then repaired from the other three)
    rebuilt = 200 + 300 - 100
    e = np.array([[100.0, 200.0], [300.0, rebuilt]])
    assert brt0(d, 1.5, 1.5, 0, 4000) == pytest.approx(map_coordinates(e, [[0.5], [0.5]], order=1)[0])
    # DN below T1 likewise; two of them -> invalid
    e = np.array([[max(1, 200 + 300 - 5000), 200.0], [300.0, 5000.0]])
    assert brt0(d, 1.5, 1.5, 150, 6000) == pytest.approx(map_coordinates(e, [[0.5], [0.5]], order=1)[0])
    assert brt0(d, 1.5, 1.5, 250, 6000) == 0.0
    # negative DN allowed by T1 < 0: the result is clipped at 0 (= invalid)
    neg = np.array([[-5.0, -6.0], [-7.0, -8.0]])
    assert brt0(neg, 1.5, 1.5, -100, 100) == 0.0
    # a NaN DN is missing
    d = np.array([[np.nan, 20.0], [40.0, 50.0]])
    assert brt0(d, 1.5, 1.5) == pytest.approx(map_coordinates(np.array([[10.0, 20], [40, 50]]),
                                                              [[0.5], [0.5]], order=1)[0])
    # integer photos are sampled as their DN values
    u16 = np.array([[100, 200], [300, 400]], dtype=np.uint16)
    assert brt0(u16, 1.5, 1.5) == 250.0


@settings(max_examples=50, deadline=None)
@given(st.floats(1.0, 5.999), st.floats(1.0, 4.999), st.integers(0, 1000))
def test_brt0_is_within_the_corner_range(s, ln, seed):
    data = np.random.default_rng(seed).uniform(1.0, 100.0, (5, 6))
    v = float(brt0(data, s, ln))
    i, j = int(s), int(ln)
    corners = data[j - 1:j + 1, i - 1:i + 1]
    assert corners.min() - 1e-12 <= v <= corners.max() + 1e-12


# ------------------------------------------------------------------------------------------------
# end to end against the independent renderer


@pytest.fixture(scope="module")
def scene():
    m = sc.make_maplet(q=24)
    e = sc.direction(m, 25.0, 200.0)
    pos = m.v + 0.5 * e
    cam = sc.look_at_camera(m.v, pos)  # 2 px per cell
    sun = sc.direction(m, 40.0, 60.0)
    photo = sc.render(cam, m, sun, offset=0.0)
    return SimpleNamespace(m=m, cam=cam, sun=sun, photo=photo, pos=pos)


def _ncc(ex, pr):
    both = (ex.image > 0) & (pr.image > 0)
    assert both.sum() > 0.8 * ex.image.size
    return pearson(ex.image, pr.image, both)


def test_extraction_matches_prediction_cells_larger_than_pixels(scene):
    ex = extract(scene.photo, scene.m, scene.cam, scene.sun, (1e-6, 1e9))
    assert ex.subsample == 2 and abs(ex.det_j) == pytest.approx(4 * math.cos(math.radians(25)), rel=0.02)
    assert ex.status == "ok" and ex.cov == 1.0
    pr = predict(scene.m, scene.cam.position, scene.sun, extracted=ex)
    assert _ncc(ex, pr) > 0.99
    assert pr.correlation > 0.99
    assert pr.lam == pytest.approx(2000.0, rel=0.01)  # the renderer's gain
    one = extract(scene.photo, scene.m, scene.cam, scene.sun, (1e-6, 1e9), ExtractOptions(subsample=1))
    assert one.subsample == 1 and _ncc(one, pr) > 0.99
    lin = extract(scene.photo, scene.m, scene.cam, scene.sun, (1e-6, 1e9), ExtractOptions(linearized=True))
    assert _ncc(lin, pr) > 0.99


def test_extraction_matches_prediction_pixels_larger_than_cells():
    m = sc.make_maplet(q=24)
    pos = m.v + 0.5 * sc.direction(m, 15.0, 300.0)
    cam = sc.look_at_camera(m.v, pos, kpx=2.5, npx=80, nln=70)  # 0.5 px per cell, det J ~ 0.24
    sun = sc.direction(m, 35.0, 100.0)
    photo = sc.render(cam, m, sun, offset=0.0, supersample=4)
    ex = extract(photo, m, cam, sun, (1e-6, 1e9))
    assert ex.subsample == 1 and ex.ds == 3 + math.floor(1 / abs(ex.det_j))
    pr = predict(m, cam.position, sun, extracted=ex)
    assert _ncc(ex, pr) > 0.99


def test_recentring_shifts_every_node(scene):
    """A photo taken with the principal point moved by (3, -2) px, extracted about V's pixel + (3, -2)."""
    base = extract(scene.photo, scene.m, scene.cam, scene.sun, (1e-6, 1e9))
    shift = np.array([3.0, -2.0])
    cam2 = Camera(mmfl=scene.cam.mmfl, ctr=scene.cam.ctr + shift, kmatrix=scene.cam.kmatrix,
                  rotation=scene.cam.rotation, scobj=scene.cam.scobj, npx=200, nln=200)
    photo2 = sc.render(cam2, scene.m, scene.sun, offset=0.0)
    cs, cl = scene.cam.project(scene.m.v)
    ex = extract(photo2, scene.m, scene.cam, scene.sun, (1e-6, 1e9), center_pixel=(cs + 3.0, cl - 2.0))
    np.testing.assert_allclose(ex.sample - base.sample, 3.0, atol=1e-9)
    np.testing.assert_allclose(ex.line - base.line, -2.0, atol=1e-9)
    np.testing.assert_allclose(ex.image, base.image, rtol=1e-9, atol=1e-9)
    lin0 = extract(scene.photo, scene.m, scene.cam, scene.sun, (1e-6, 1e9), ExtractOptions(linearized=True))
    lin = extract(photo2, scene.m, scene.cam, scene.sun, (1e-6, 1e9), ExtractOptions(linearized=True),
                  center_pixel=(cs + 3.0, cl - 2.0))
    assert (lin.center_sample, lin.center_line) == (cs + 3.0, cl - 2.0)
    np.testing.assert_allclose(lin.sample - lin0.sample, 3.0, atol=1e-9)
    np.testing.assert_allclose(lin.image, lin0.image, rtol=1e-9, atol=1e-9)


def test_node_pixels_full_and_linearized(scene):
    m, cam = scene.m, scene.cam
    n = m.heights.shape[0]
    q = (n - 1) // 2
    off = np.stack(np.meshgrid(np.arange(n) - q, np.arange(n) - q, indexing="ij"), axis=-1).astype(float)
    pts = frames.maplet_to_body(np.concatenate([off, m.heights[..., None]], axis=-1), m.v, m.ux, m.uy, m.uz,
                                m.scale)
    s_ref, l_ref = cam.project(pts)
    ex = extract(scene.photo, m, cam, scene.sun, (1e-6, 1e9))
    np.testing.assert_allclose(ex.sample, s_ref, atol=1e-9)
    np.testing.assert_allclose(ex.line, l_ref, atol=1e-9)
    # S16 Eq. 10-11: H by central finite differences at V
    h = np.zeros((2, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = 1e-6
        sp, lp = cam.project(m.v + d)
        sm, lm = cam.project(m.v - d)
        h[:, k] = [(sp - sm) / 2e-6, (lp - lm) / 2e-6]
    cs, cl = cam.project(m.v)
    lin = extract(scene.photo, m, cam, scene.sun, (1e-6, 1e9), ExtractOptions(linearized=True))
    r = pts - m.v
    np.testing.assert_allclose(lin.sample, cs + r @ h[0], atol=1e-4)
    np.testing.assert_allclose(lin.line, cl + r @ h[1], atol=1e-4)
    # J_xy columns: pixels per cell along UX and UY
    np.testing.assert_allclose(ex.jxy, h @ np.stack([m.ux, m.uy], axis=1) * m.scale, rtol=1e-6)


def test_subsample_average_of_a_linear_photo_is_the_node_value(scene):
    nln, npx = 200, 200
    ss, ll = np.meshgrid(np.arange(1, npx + 1, dtype=float), np.arange(1, nln + 1, dtype=float))
    ramp = 500.0 + 3.0 * ss + 2.0 * ll
    for m_sub in (1, 2, 3):
        ex = extract(ramp, scene.m, scene.cam, scene.sun, None,
                     ExtractOptions(subsample=m_sub, apply_filter=False, criteria=None))
        ok = ex.lit
        assert ok.sum() == ok.size
        np.testing.assert_allclose(ex.image[ok], (500.0 + 3.0 * ex.sample + 2.0 * ex.line)[ok], rtol=1e-12)
    assert subsample_count(4.0) == 2 and subsample_count(-4.01) == 3 and subsample_count(0.5) == 1
    assert subsample_count(100.0, 1) == 1 and subsample_count(0.1, 4) == 4


def test_subsample_averages_only_non_zero_samples(scene):
    photo = np.full((200, 200), 100.0)
    photo[:, :90] = 0.0  # missing data on the left
    ex = extract(photo, scene.m, scene.cam, scene.sun, (10, 1000),
                 ExtractOptions(subsample=3, apply_filter=False, criteria=None))
    assert np.all(ex.image[ex.lit] == 100.0)  # never diluted by the zero samples
    edge = ex.lit & (ex.sample < 91.5)  # cells whose 3x3 samples straddle the missing region
    assert edge.any()
    assert not ex.lit[ex.covered & (ex.sample < 88.0)].any()


def test_behind_the_camera_is_outside(scene):
    m = scene.m
    pos = m.v + 0.5 * sc.direction(m, 25.0, 200.0)
    cam = sc.look_at_camera(pos + (pos - m.v), pos)  # looking away from the maplet
    ex = extract(scene.photo, m, cam, scene.sun, (1e-6, 1e9))
    assert ex.status == "outside" and not ex.covered.any() and not ex.valid.any() and ex.cov == 0.0


# ------------------------------------------------------------------------------------------------
# Stage D: the filter on hand-built topography


def _flat(q=10):
    n = 2 * q + 1
    ux, uy, uz = np.eye(3)
    return np.zeros((n, n)), np.ones((n, n), bool), ux, uy, uz


def test_wall_shadow_is_extended_by_ds_plus_edge_and_lateral_cells():
    q = 10
    h, valid, ux, uy, uz = _flat(q)
    n = 2 * q + 1
    img = np.ones((n, n))
    # a shadow from a wall: Sun toward +x (axis 0); shadow cells x in [2, 5] (rows 12..15), y in [-3, 3]
    img[12:16, 7:14] = 0.0
    sun = np.array([1.0, 0.0, 1.0])  # 45 deg elevation
    emission = np.array([0.0, 0.0, 1.0])  # nadir: no emission cut, no march
    det_j = 0.49  # S16: ds = 3 + floor(1/0.49) = 5 (seed), 3 + floor(1/0.7) = 4 (sqrt)
    fr = extract_filter(img, h, valid, ux, uy, uz, sun, emission, det_j, ExtractOptions())
    assert fr.ds == 5
    # edge cells: the lit row just anti-sunward of the shadow, x = 1 (row 11), y in [-3, 3]
    exp_edges = np.zeros((n, n), bool)
    exp_edges[11, 7:14] = True
    np.testing.assert_array_equal(fr.edges, exp_edges)
    # zeroed: rows 11 (the edge) down to 11 - ds = 6, columns widened by lateral = 2 each side
    exp = np.zeros((n, n), bool)
    exp[6:12, 5:16] = True
    np.testing.assert_array_equal(fr.removed_shadow, exp)
    np.testing.assert_array_equal(fr.image == 0, (img == 0) | exp)
    assert fr.inv == 0 and not fr.removed_invisible.any()
    # variants
    fr = extract_filter(img, h, valid, ux, uy, uz, sun, emission, det_j, ExtractOptions(ds_mode="sqrt"))
    exp = np.zeros((n, n), bool)
    exp[7:12, 5:16] = True
    assert fr.ds == 4
    np.testing.assert_array_equal(fr.removed_shadow, exp)
    fr = extract_filter(img, h, valid, ux, uy, uz, sun, emission, det_j,
                        ExtractOptions(shadow_include_edge=False, lateral=0))
    exp = np.zeros((n, n), bool)
    exp[6:11, 7:14] = True  # the literal k = 1..ds: the edge row 11 stays lit
    np.testing.assert_array_equal(fr.removed_shadow, exp)
    fr = extract_filter(img, h, valid, ux, uy, uz, sun, emission, det_j, ExtractOptions(lateral_band=False))
    exp = np.zeros((n, n), bool)
    exp[6:12, 7:14] = True
    exp[6:12, [5, 6, 14, 15]] = True  # +-2 offsets of the edge cells reach every column from 5 to 15
    np.testing.assert_array_equal(fr.removed_shadow, exp)
    # a shadow shorter than 3 cells has no edge
    short = np.ones((n, n))
    short[12:14, 7:14] = 0.0
    fr = extract_filter(short, h, valid, ux, uy, uz, sun, emission, det_j)
    assert not fr.edges.any() and not fr.removed_shadow.any()
    # a Sun at the zenith has no shadow direction
    fr = extract_filter(img, h, valid, ux, uy, uz, np.array([0.0, 0.0, 1.0]), emission, det_j)
    assert not fr.removed_shadow.any()


def _reference_enhancement(img, sxy, ds, lateral):
    """Plain loops: edge cells and zeroed cells of the default enhancement (k = 0..ds, band +-lateral)."""
    n0, n1 = img.shape
    perp = (-sxy[1], sxy[0])
    zero = np.zeros(img.shape, bool)
    for r in range(n0):
        for c in range(n1):
            if img[r, c] <= 0:
                continue
            edge = True
            for k in (1, 2, 3):
                rr, cc = r + nint(k * sxy[0]), c + nint(k * sxy[1])
                if not (0 <= rr < n0 and 0 <= cc < n1) or img[rr, cc] > 0:
                    edge = False
            if not edge:
                continue
            for k in range(0, ds + 1):
                for j in range(-lateral, lateral + 1):
                    rr = r + nint(-k * sxy[0] + j * perp[0])
                    cc = c + nint(-k * sxy[1] + j * perp[1])
                    if 0 <= rr < n0 and 0 <= cc < n1:
                        zero[rr, cc] = True
    return zero


@pytest.mark.parametrize("azimuth", [30.0, 135.0, 200.0, 290.0])
def test_shadow_enhancement_matches_a_loop_reference_for_oblique_suns(azimuth):
    q = 12
    h, valid, ux, uy, uz = _flat(q)
    n = 2 * q + 1
    rng = np.random.default_rng(int(azimuth))
    img = np.ones((n, n))
    for _ in range(6):  # random rectangular "shadows"
        r, c = rng.integers(0, n - 4, 2)
        img[r:r + rng.integers(3, 7), c:c + rng.integers(3, 7)] = 0.0
    a = math.radians(azimuth)
    sxy = (math.cos(a), math.sin(a))
    sun = np.array([sxy[0], sxy[1], 0.8])
    fr = extract_filter(img, h, valid, ux, uy, uz, sun, np.array([0.0, 0.0, 1.0]), 0.3)
    zero = _reference_enhancement(img, sxy, fr.ds, 2)
    assert fr.ds == 6
    np.testing.assert_array_equal(fr.removed_shadow, zero & (img > 0))


def test_shadow_offsets_and_extension():
    checks, zeros = shadow_offsets((0.0, 1.0), 2, lateral=1)
    np.testing.assert_array_equal(checks, [[0, 1], [0, 2], [0, 3]])
    expected = {(dx, -k) for k in (0, 1, 2) for dx in (1, 0, -1)}  # perp = (-1, 0)
    assert {tuple(z) for z in zeros} == expected
    assert shadow_extension(0.49) == 5 and shadow_extension(0.49, "sqrt") == 4
    assert shadow_extension(-2.0) == 3 and shadow_extension(1.0) == 4
    assert shadow_extension(0.0, cap=30) == 33
    with pytest.raises(SpcUsageError):
        shadow_extension(0.0)
    np.testing.assert_array_equal(nint([0.5, -0.5, 1.49, -2.5]), [1, -1, 1, -3])


def _hill(q=15, height=6.0, width=3.0):
    n = 2 * q + 1
    x = (np.arange(n) - q)[:, None]
    y = (np.arange(n) - q)[None, :]
    return height * np.exp(-(x * x + y * y) / (2.0 * width * width)) + 0.0 * y


def test_back_slope_of_a_hill_seen_obliquely_is_removed():
    q = 15
    n = 2 * q + 1
    h = _hill(q)
    valid = np.ones((n, n), bool)
    ux, uy, uz = np.eye(3)
    e = math.radians(60.0)
    emission = np.array([math.sin(e), 0.0, math.cos(e)])  # camera toward +x, 60 deg off the normal
    sun = np.array([0.0, 0.0, 1.0])  # zenith: no shadow enhancement
    img = np.ones((n, n))
    fr = extract_filter(img, h, valid, ux, uy, uz, sun, emission, 1.0)
    # emission cut: n.e < 0.05 with central-difference normals (np.gradient) in the interior
    hx, hy = np.gradient(h)
    cos_e = (-hx * emission[0] - hy * emission[1] + emission[2]) / np.sqrt(1 + hx * hx + hy * hy)
    inner = (slice(1, -1), slice(1, -1))
    np.testing.assert_array_equal(fr.emission_cut[inner], (cos_e < 0.05)[inner])
    assert fr.emission_cut[q - 4:q - 1, q].all()  # the steep back slope (facing -x) is cut
    # cells at the foot of the hill behind it are hidden by the summit: removed by the march
    assert fr.occluded[q - 10:q - 6, q].all() and not fr.emission_cut[q - 10:q - 6, q].any()
    # the front slope and the far ground are kept
    assert fr.visible[q + 1:, q].all() and fr.visible[:3, :].all() and fr.visible[:, :8].all()
    # INV counts the removed cells: (N^2 + 1) in the denominator, rounded half away from zero
    removed = np.count_nonzero((fr.emission_cut | fr.occluded) & (img > 0))
    assert removed == np.count_nonzero(fr.removed_invisible) > 0
    assert fr.inv == math.floor(1000 * removed / (n * n + 1) + 0.5)
    np.testing.assert_array_equal(fr.image == 0, fr.removed_invisible)
    # cells that were already zero are not counted
    img2 = img.copy()
    img2[fr.removed_invisible] = 0.0
    assert extract_filter(img2, h, valid, ux, uy, uz, sun, emission, 1.0).inv == 0
    # switches
    off = extract_filter(img, h, valid, ux, uy, uz, sun, emission, 1.0,
                         ExtractOptions(emission_cut=False, visibility_march=False))
    assert off.inv == 0 and (off.image == 1).all()


def test_cast_shadow_trace_zeroes_cells_behind_a_wall():
    q = 10
    n = 2 * q + 1
    h = np.zeros((n, n))
    h[q, :] = 4.0  # a wall across y at x = 0
    valid = np.ones((n, n), bool)
    ux, uy, uz = np.eye(3)
    sun = np.array([1.0, 0.0, 1.0])  # toward +x at 45 deg: the wall shades x in [-4, -1]
    img = np.ones((n, n))
    nadir = np.array([0.0, 0.0, 1.0])
    opts = ExtractOptions(cast_shadow_trace=True, emission_cut=False, lateral=0, ds_base=0)
    fr = extract_filter(img, h, valid, ux, uy, uz, sun, nadir, 100.0, opts)
    assert fr.shadowed[q - 3:q, :].all() and not fr.shadowed[:q - 5, :].any() and not fr.shadowed[q:, :].any()
    assert (fr.image[fr.shadowed] == 0).all() and fr.removed_shadow[fr.shadowed].all()
    off = extract_filter(img, h, valid, ux, uy, uz, sun, nadir, 100.0, ExtractOptions(emission_cut=False))
    assert not off.shadowed.any()


# ------------------------------------------------------------------------------------------------
# Stage E: statistics by hand count, removal criteria


def _nadir_scene(npx=40, nln=50, ctr=(20.3, 30.6)):
    """Flat q = 10 maplet, UX = x, UY = y; camera 1 km above, looking down:
    sample = ctr1 + 2J, line = ctr2 - 2I."""
    q = 10
    n = 2 * q + 1
    ux, uy, uz = frames.orient_frame(np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(np.stack([ux, uy, uz]), np.eye(3), atol=1e-15)
    m = SimpleNamespace(heights=np.zeros((n, n)), albedo=np.ones((n, n)), valid=np.ones((n, n), bool),
                        scale=0.001, v=np.array([0.0, 0.0, 1.0]), ux=ux, uy=uy, uz=uz)
    rot = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    cam = Camera(mmfl=100.0, ctr=np.array(ctr), kmatrix=np.array([[20.0, 0, 0], [0, 20.0, 0]]), rotation=rot,
                 scobj=-np.array([0.0, 0.0, 2.0]), npx=npx, nln=nln)
    return m, cam


def test_statistics_match_hand_counts():
    m, cam = _nadir_scene()
    photo = np.full((50, 40), 100.0)
    # dark block covering exactly the BRT0 corners of nodes J in [-4, -2] and I in [1, 3]:
    # node (J, I) uses samples 20+2J, 21+2J and lines 30-2I, 31-2I
    photo[30 - 2 * 3 - 1:31 - 2 * 1, 20 - 2 * 4 - 1:21 - 2 * 2] = 0.0
    sun = np.array([0.0, 0.0, 1.0])  # zenith: no shadow direction; nadir view: nothing invisible
    ex = extract(photo, m, cam, sun, (10.0, 1000.0), ExtractOptions(subsample=1))
    assert ex.det_j == pytest.approx(-4.0, rel=1e-12) and ex.res == pytest.approx(0.5, rel=1e-12)
    assert ex.emission_deg == pytest.approx(0.0, abs=1e-6)
    # sample = 20.3 + 2J in [1, 40) -> J in [-9, 9] (19 values); line = 30.6 - 2I in [1, 50) -> I in [-9, 10]
    np.testing.assert_allclose(ex.sample[:, 0], 20.3 + 2 * np.arange(-10, 11), atol=1e-9)
    np.testing.assert_allclose(ex.line[0, :], 30.6 - 2 * np.arange(-10, 11), atol=1e-9)
    assert ex.cov == pytest.approx(19 * 20 / 441)
    dark = 3 * 3
    assert ex.ill == pytest.approx((19 * 20 - dark) / 441)
    assert not ex.lit[10 - 4:10 - 1, 10 + 1:10 + 4].any()
    assert ex.lit[10 - 5, 10 + 1:10 + 4].all() and ex.lit[10 - 4:10 - 1, 10 + 4].all()
    assert ex.inv == 0 and ex.status == "ok"
    # m = 2 (|det J| = 4): sub-samples at +-0.5 px; node J = 10 (sample 40.3) has one at 39.8 < NPX, so it
    # is covered; I = -10 (line 50.6) has both at >= 50 = NLN, so it is not
    ex2 = extract(photo, m, cam, sun, (10.0, 1000.0))
    assert ex2.subsample == 2 and ex2.cov == pytest.approx(20 * 20 / 441)
    assert not (ex2.lit & ~ex2.covered).any() and ex2.covered[20, 1:].all() and not ex2.covered[:, 0].any()
    # ILL from the prediction: every valid cell is lit under a zenith Sun
    pr = predict(m, cam.position, sun)
    exp = extract(photo, m, cam, sun, (10.0, 1000.0), ExtractOptions(subsample=1, ill_source="predicted"))
    assert exp.ill == 1.0 == pr.lit_fraction
    assert extract(photo, m, cam, sun, (10.0, 1000.0), ExtractOptions(subsample=1, ill_source="predicted"),
                   prediction=pr).ill == 1.0


def test_removal_criteria_each_trigger():
    c = Criteria.parse("0,60,.25,.25,0,3")
    assert c == PRESETS["lithos_standard"] == Criteria()
    good = dict(emission_deg=30.0, cov=0.9, ill=0.8, res=1.0, inv=5)
    assert c.status(**good) == "ok"  # INVLIM = 0 disables the INV test
    assert Criteria.parse("4,60,.25,.25,0,3").status(**good) == "removed-invlim"
    assert Criteria.parse("5,60,.25,.25,0,3").status(**good) == "ok"
    assert c.status(**{**good, "emission_deg": 60.0}) == "removed-slim"
    assert c.status(**{**good, "cov": 0.2}) == "removed-clim"
    assert c.status(**{**good, "ill": 0.2}) == "removed-ilim"
    assert Criteria.parse("0,60,.25,.25,1.5,3").status(**good) == "removed-rsmn"
    assert c.status(**{**good, "res": 3.01}) == "removed-rsmx"
    auto = Criteria.parse("autoregister")
    assert auto == Criteria.parse("0 50 .25 0 5") and auto.ilim is None
    assert auto.status(**{**good, "ill": 0.0}) == "ok"  # no ILIM in AUTOREGISTER's five values
    assert auto.status(**{**good, "emission_deg": 55.0}) == "removed-slim"
    assert auto.text() == "0,50,0.25,0,5" and c.as_tuple() == (0, 60, 0.25, 0.25, 0, 3)
    for bad in ("1,2,3", "a,b,c,d,e", [1, 2], "1,2,3,4,5,6,7"):
        with pytest.raises(SpcUsageError):
            Criteria.parse(bad)


def test_removal_through_extract():
    m, cam = _nadir_scene()
    photo = np.full((50, 40), 100.0)
    sun = np.array([0.0, 0.0, 1.0])

    def status(criteria):
        return extract(photo, m, cam, sun, (10, 1000), ExtractOptions(criteria=criteria, subsample=1)).status

    assert status("lithos_standard") == "ok"
    assert status("0,60,.9,.25,0,3") == "removed-clim"  # cov = 380/441 = 0.86
    assert status("0,60,.25,.9,0,3") == "removed-ilim"
    assert status("0,60,.25,.25,0.6,3") == "removed-rsmn"  # res = 0.5
    assert status("0,60,.25,.25,0,0.4") == "removed-rsmx"
    assert status(None) == "ok"
    oblique = sc.look_at_camera(m.v, m.v + 2.0 * np.array([math.sin(1.1), 0.0, math.cos(1.1)]), kpx=20.0,
                                npx=40, nln=50)
    ex = extract(photo, m, oblique, sun, (10, 1000), ExtractOptions(criteria="0,60,0,0,0,3"))
    assert ex.emission_deg == pytest.approx(math.degrees(1.1)) and ex.status == "removed-slim"


def test_options_are_validated():
    assert ExtractOptions(subsample="3").subsample == 3
    for kw in (dict(subsample=0), dict(subsample="x"), dict(ds_mode="area"), dict(ill_source="both"),
               dict(edge_steps=0), dict(lateral=-1), dict(criteria="1,2"), dict(cos_e_min=float("nan"))):
        with pytest.raises(SpcUsageError):
            ExtractOptions(**kw)
    assert ExtractOptions(criteria="autoregister").as_dict()["criteria"] == "0,50,0.25,0,5"


# ------------------------------------------------------------------------------------------------
# real geometry: the Rosetta 67P picture and landmarks (fixtures/real/rosetta-67p)

REAL = Path(__file__).resolve().parents[1] / "fixtures" / "real" / "rosetta-67p"


@pytest.mark.parametrize("name", ["FA0115", "FC0098", "GD0036"])
def test_real_rosetta_geometry_agrees_with_selection_and_sum(name):
    from spctool.formats.landmark import read_lmk
    from spctool.formats.sumfile import read_sum
    from spctool.stages.select import SelectOptions, select_maplets

    pic = read_sum(REAL / "W48230079013.SUM")
    cam = Camera.from_picture(pic)
    lmk = read_lmk(REAL / f"{name}.LMK")
    n = 2 * lmk.qsz + 1
    m = SimpleNamespace(heights=np.zeros((n, n)), valid=np.ones((n, n), bool), albedo=np.ones((n, n)),
                        scale=lmk.scale, v=lmk.vlm, ux=lmk.ux, uy=lmk.uy, uz=lmk.uz)
    photo = np.full((pic.nln, pic.npx), 1000, np.uint16)  # inside THRSH 500..65535
    ex = extract(photo, m, cam, pic.sz, pic.thrsh)
    sel = select_maplets(cam, pic.sz, lmk.vlm[None], lmk.ux[None], lmk.uy[None], lmk.uz[None], [lmk.scale],
                         [lmk.qsz], [name], SelectOptions(jacobian="analytic"))
    measured = next(s for s in pic.landmarks if s.name == name)
    # README "verified facts": the projection lands within 1.2 px of the SUM's measured pixel
    assert abs(ex.center_sample - measured.sample) < 1.2 and abs(ex.center_line - measured.line) < 1.2
    assert ex.emission_deg == pytest.approx(sel.emission[0], abs=1e-9)
    assert ex.res == pytest.approx(sel.resolution_km_px[0] / lmk.scale, rel=1e-7)
    # a constant photo extracts to exactly its DN on every covered cell, and nothing is filtered
    assert ex.cov == 1.0 and ex.ill == 1.0 and np.all(ex.image == 1000.0)
    # the WAC pixel (~34 m) is more than 3 maplet cells (10 m): LITHOS's standard RSMX = 3 removes it,
    # AUTOREGISTER's RSMX = 5 keeps it
    assert ex.res > 3.0 and ex.status == "removed-rsmx"
    auto = extract(photo, m, cam, pic.sz, pic.thrsh, ExtractOptions(criteria="autoregister"))
    assert auto.status == "ok"
