"""Tests of spctool.stages.correlate (Stages F–G, spc-algorithms.md §7–§8).

Every number is checked against an independent computation: a brute-force Pearson loop over offsets
(np.corrcoef), an explicit block-average loop for the binning, the parabola through three points, and
images shifted by known amounts through an analytic function.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool.errors import SpcUsageError
from spctool.stages.correlate import (
    CorrelateOptions,
    bin_image,
    correlate,
    find_peak,
    ncc_surface,
    parabola_vertex,
)

# --------------------------------------------------------------------------------------------------
# independent references


def brute_surface(e, me, p, mp, half, min_valid, origin=(0, 0)):
    """C[u+k, v+k] = corrcoef over pairs e[i, j] ↔ p[i − o0 − u, j − o1 − v], both valid (plain loops)."""
    g = 2 * half + 1
    surf = np.full((g, g), np.nan)
    cnt = np.zeros((g, g), int)
    for a in range(g):
        for b in range(g):
            u, v = a - half, b - half
            ee, pp = [], []
            for i in range(e.shape[0]):
                for j in range(e.shape[1]):
                    ii, jj = i - origin[0] - u, j - origin[1] - v
                    if 0 <= ii < p.shape[0] and 0 <= jj < p.shape[1] and me[i, j] and mp[ii, jj]:
                        ee.append(e[i, j])
                        pp.append(p[ii, jj])
            cnt[a, b] = len(ee)
            if len(ee) >= min_valid and np.std(ee) > 0 and np.std(pp) > 0:
                surf[a, b] = np.corrcoef(ee, pp)[0, 1]
    return surf, cnt


def brute_bin(values, valid, n, anchor):
    """Block means by explicit index arithmetic: pixel i belongs to block floor((i − anchor + n//2)/n)."""
    h = n // 2
    blocks = {}
    for i in range(values.shape[0]):
        for j in range(values.shape[1]):
            key = ((i - anchor[0] + h) // n, (j - anchor[1] + h) // n)
            s, c = blocks.get(key, (0.0, 0))
            if valid[i, j]:
                s, c = s + values[i, j], c + 1
            blocks[key] = (s, c)
    return blocks


def smooth_field(x, y, seed=3, n=12, lam=(12.0, 40.0)):
    """A smooth, non-periodic analytic test image (sum of plane waves), evaluable at any (x, y)."""
    rng = np.random.default_rng(seed)
    wl = rng.uniform(lam[0], lam[1], n)
    th = rng.uniform(0, 2 * np.pi, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    kx, ky = np.cos(th) * 2 * np.pi / wl, np.sin(th) * 2 * np.pi / wl
    return 10.0 + np.sin(x[..., None] * kx + y[..., None] * ky + ph).sum(-1)


def blob_image(n, shift=(0.0, 0.0), sigma=4.0, centre=(0.0, 0.0), background=1.0):
    """An isotropic Gaussian blob on a constant background, moved by ``shift`` cells: a smooth image
    whose correlation peak is smooth and untilted (the case L15's separable 1-D fits assume)."""
    x, y = cells(n, shift)
    return background + np.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (2.0 * sigma**2))


def cells(n, shift=(0.0, 0.0)):
    q = (n - 1) // 2
    x = np.arange(n, dtype=float)[:, None] - q - shift[0] + 0.0 * np.arange(n)[None, :]
    y = np.arange(n, dtype=float)[None, :] - q - shift[1] + 0.0 * np.arange(n)[:, None]
    return x, y


# --------------------------------------------------------------------------------------------------
# the NCC grid


@settings(max_examples=25, deadline=None)
@given(
    he=st.integers(8, 18),
    we=st.integers(8, 18),
    hp=st.integers(6, 16),
    wp=st.integers(6, 16),
    o0=st.integers(-4, 8),
    o1=st.integers(-4, 8),
    half=st.integers(1, 4),
    frac=st.floats(0.0, 0.5),
    seed=st.integers(0, 10_000),
)
def test_ncc_matches_brute_force(he, we, hp, wp, o0, o1, half, frac, seed):
    rng = np.random.default_rng(seed)
    e = rng.normal(size=(he, we)) * 3.0 + 100.0
    p = rng.normal(size=(hp, wp)) * 0.01 - 5.0
    me = rng.random((he, we)) >= frac
    mp = rng.random((hp, wp)) >= frac
    surf, cnt = ncc_surface(e, me, p, mp, half, 6, (o0, o1))
    ref, rcnt = brute_surface(e, me, p, mp, half, 6, (o0, o1))
    np.testing.assert_array_equal(cnt, rcnt)
    np.testing.assert_array_equal(np.isnan(surf), np.isnan(ref))
    ok = np.isfinite(ref)
    np.testing.assert_allclose(surf[ok], ref[ok], rtol=0, atol=1e-11)


def test_ncc_same_grid_with_blob_masks():
    rng = np.random.default_rng(0)
    e = rng.random((31, 31))
    p = rng.random((31, 31))
    me = np.ones((31, 31), bool)
    me[5:12, 8:20] = False  # a "shadow" blob
    mp = rng.random((31, 31)) > 0.05
    surf, cnt = ncc_surface(e, me, p, mp, 5, 25)
    ref, rcnt = brute_surface(e, me, p, mp, 5, 25)
    np.testing.assert_array_equal(cnt, rcnt)
    np.testing.assert_allclose(surf, ref, atol=1e-12)


def test_ncc_is_invariant_to_affine_brightness():
    rng = np.random.default_rng(1)
    e = rng.random((21, 21))
    p = rng.random((21, 21))
    m = np.ones((21, 21), bool)
    s1, _ = ncc_surface(e, m, p, m, 3, 10)
    s2, _ = ncc_surface(5.0 * e + 1e4, m, 0.01 * p - 3.0, m, 3, 10)
    np.testing.assert_allclose(s1, s2, atol=1e-10)


def test_ncc_of_an_image_with_itself_peaks_at_one_at_zero_offset():
    x, y = cells(41)
    img = smooth_field(x, y)
    m = np.ones(img.shape, bool)
    surf, cnt = ncc_surface(img, m, img, m, 5, 25)
    assert surf[5, 5] == pytest.approx(1.0, abs=1e-12)
    assert cnt[5, 5] == 41 * 41 and cnt[0, 0] == 36 * 36
    assert np.nanargmax(surf) == 60


def test_ncc_min_valid_and_constant_images_give_nan():
    rng = np.random.default_rng(2)
    e = rng.random((10, 10))
    m = np.ones((10, 10), bool)
    surf, cnt = ncc_surface(e, m, e, m, 2, 91)  # only offset 0 has 100 ≥ 91 pairs (±1: 90)
    assert np.isfinite(surf[2, 2]) and np.isnan(surf).sum() == 24
    flat = np.full((10, 10), 7.0)
    surf, _ = ncc_surface(e, m, flat, m, 2, 4)
    assert np.all(np.isnan(surf))


# --------------------------------------------------------------------------------------------------
# binning


@pytest.mark.parametrize("n", [2, 3, 4, 5, 10])
@pytest.mark.parametrize("shape,anchor", [((21, 21), (10, 10)), ((17, 23), (4, 15)), ((9, 30), (0, 29))])
def test_bin_image_matches_explicit_blocks(n, shape, anchor):
    rng = np.random.default_rng(n)
    v = rng.random(shape)
    m = rng.random(shape) > 0.3
    b, bv, ba = bin_image(v, m, n, anchor)
    ref = brute_bin(v, m, n, anchor)
    keys = np.array(list(ref))
    assert b.shape == (keys[:, 0].max() - keys[:, 0].min() + 1, keys[:, 1].max() - keys[:, 1].min() + 1)
    for (r, c), (s, k) in ref.items():
        i, j = r + ba[0], c + ba[1]
        assert bv[i, j] == (k > 0)
        if k:
            assert b[i, j] == pytest.approx(s / k, rel=1e-12)
    # block (0, 0) contains the anchor and, for odd n, is centred on it (L15 Eq. 3.57, erratum 24)
    lo = anchor[0] - n // 2
    assert (anchor[0] - lo) == n // 2


def test_bin_image_min_fraction_and_identity():
    v = np.arange(36.0).reshape(6, 6)
    m = np.ones((6, 6), bool)
    m[0, 0] = False
    b, bv, ba = bin_image(v, m, 3, (1, 1), min_fraction=1.0)
    assert ba == (0, 0) and not bv[0, 0] and bv[1, 1]
    b, bv, _ = bin_image(v, m, 3, (1, 1))
    assert bv[0, 0] and b[0, 0] == pytest.approx(np.mean([1, 2, 6, 7, 8, 12, 13, 14]))
    b1, bv1, a1 = bin_image(v, m, 1)
    np.testing.assert_array_equal(b1, np.where(m, v, 0.0))
    assert a1 == (2, 2)


def test_binned_grid_equals_shifting_then_binning():
    """L15: binned images offset by (u, v) bins give exactly the correlation of the prediction moved by
    n·(u, v) full cells and then binned (same bin phase), over the same bins."""
    n, nb = 3, 21  # 21 full bins of 3 cells: 63 cells, bin 0 centred on the centre cell
    size, pad = n * nb, 5 * n
    big = smooth_field(*cells(size + 2 * pad), seed=5, lam=(4.0, 15.0))
    e = big[pad:-pad, pad:-pad]
    m = np.ones(e.shape, bool)
    res = correlate(e, e.copy(), spacing=n, options=CorrelateOptions(min_valid=9))
    eb, _, _ = bin_image(e, m, n)
    for u, v in [(1, 0), (-2, 1), (3, -3), (-5, 5)]:
        moved = big[pad - n * u : pad - n * u + size, pad - n * v : pad - n * v + size]  # P(m − n·(u, v))
        pb, _, _ = bin_image(moved, m, n)
        # bins whose source bin m − (u, v) lies inside the prediction's binned extent
        i = np.arange(nb)[:, None] - u
        j = np.arange(nb)[None, :] - v
        keep = (i >= 0) & (i < nb) & (j >= 0) & (j < nb)
        ref = np.corrcoef(eb[keep], pb[keep])[0, 1]
        assert res.surface[u + 5, v + 5] == pytest.approx(ref, abs=1e-12)
        assert res.counts[u + 5, v + 5] == keep.sum()
    assert res.surface[5, 5] == pytest.approx(1.0, abs=1e-12)


# --------------------------------------------------------------------------------------------------
# the sub-pixel peak


def test_parabola_vertex_hand_example_and_seed_sign_error():
    # spc-algorithms.md §0.2 item 1: (0.5, 1.0, 0.8) → +0.2143; L15 Eq. 3.65 as printed gives −0.045
    assert parabola_vertex(0.5, 1.0, 0.8) == pytest.approx(0.3 / 1.4, abs=1e-12)
    seed = -((0.8 - 0.5) / 2) / (0.8 + 0.5 + 2 * 1.0)
    assert seed == pytest.approx(-0.045, abs=5e-4)
    assert math.isnan(parabola_vertex(1.0, 1.0, 1.0))


@settings(max_examples=60, deadline=None)
@given(x0=st.floats(-0.499, 0.499), a=st.floats(0.01, 5.0), c=st.floats(-1.0, 1.0))
def test_parabola_vertex_is_exact_for_parabolas(x0, a, c):
    y = [c - a * (t - x0) ** 2 for t in (-1.0, 0.0, 1.0)]
    assert parabola_vertex(*y) == pytest.approx(x0, abs=1e-9)
    assert abs(parabola_vertex(*y)) <= 0.5 + 1e-12


def test_parabola_vertex_vectorised():
    ym = np.array([0.5, 0.9, 0.2])
    y0 = np.array([1.0, 1.0, 0.3])
    yp = np.array([0.8, 0.9, 0.1])
    d = parabola_vertex(ym, y0, yp)
    np.testing.assert_allclose(d, [0.3 / 1.4, 0.0, (0.1 - 0.2) / (2 * (0.6 - 0.3))])


def _surface_with_peak(r, c, g=11, width=2.0):
    i, j = np.mgrid[0:g, 0:g]
    return 0.9 * np.exp(-((i - r) ** 2 + (j - c) ** 2) / (2 * width**2))


def test_find_peak_statuses():
    st_, peak, idx, sub = find_peak(_surface_with_peak(5.3, 4.8))
    assert st_ == "ok" and idx == (5, 5) and peak == pytest.approx(0.9 * math.exp(-(0.09 + 0.04) / 8))
    assert sub[0] > 0 and sub[1] < 0
    # on the border of the grid
    st_, _, idx, _ = find_peak(_surface_with_peak(0.2, 6.0))
    assert st_ == "edge-peak" and idx[0] == 0
    st_, _, idx, _ = find_peak(_surface_with_peak(4.0, 10.4))
    assert st_ == "edge-peak" and idx[1] == 10
    # flat surfaces: no clearly defined peak
    assert find_peak(np.full((11, 11), 0.7))[0] == "not-found"
    tied = _surface_with_peak(5, 5)
    tied[0, 0] = tied[5, 5]  # the maximum twice: not a clearly defined peak
    assert find_peak(tied)[0] == "not-found"
    plateau = np.full((11, 11), 0.2)
    plateau[4:7, 4:7] = 0.8
    assert find_peak(plateau)[0] == "not-found"
    assert find_peak(np.full((11, 11), np.nan))[0] == "not-found"
    nan_nb = _surface_with_peak(5, 5)
    nan_nb[5, 6] = np.nan
    assert find_peak(nan_nb)[0] == "not-found"
    # below the threshold
    assert find_peak(0.25 / 0.9 * _surface_with_peak(5, 5))[0] == "low-correlation"
    assert find_peak(0.25 / 0.9 * _surface_with_peak(5, 5), corr_min=0.2)[0] == "ok"


def test_find_peak_strict_8():
    s = _surface_with_peak(5, 5)
    s[4, 4] = np.nan  # an undefined diagonal neighbour (too few common pixels there)
    assert find_peak(s)[0] == "ok"
    assert find_peak(s, strict_8=True)[0] == "not-found"


# --------------------------------------------------------------------------------------------------
# the stage: sign convention and sub-pixel recovery


def test_sign_convention_integer_shift():
    """E(m) = P(m − Δ) must peak at Δ (spc-algorithms.md §7.3): unit test before anything else."""
    n = 41
    x, y = cells(n)
    p = smooth_field(x, y)
    for d in [(3, -2), (-4, 1), (0, 5 - 1)]:
        xe, ye = cells(n, d)
        e = smooth_field(xe, ye)  # e(m) = f(m − Δ)
        res = correlate(e, p)
        assert res.status == "ok"
        assert res.peak_index == (5 + d[0], 5 + d[1])
        np.testing.assert_allclose(res.offset, d, atol=0.02)


@settings(max_examples=40, deadline=None)
@given(dx=st.floats(-3.9, 3.9), dy=st.floats(-3.9, 3.9), sigma=st.floats(2.5, 6.0))
def test_subpixel_recovery_of_fractional_shifts(dx, dy, sigma):
    """Smooth (untilted) correlation peaks: known fractional shifts are recovered to ≤ 0.02 cell."""
    n = 45
    p = blob_image(n, sigma=sigma)
    e = blob_image(n, (dx, dy), sigma=sigma)
    res = correlate(e, p)
    assert res.status == "ok"
    assert abs(res.offset[0] - dx) <= 0.02 and abs(res.offset[1] - dy) <= 0.02


def test_separable_fit_on_a_tilted_peak_is_biased_but_iteration_removes_it():
    """L15's two 1-D fits assume an untilted peak; a textured image with a tilted peak leaves a
    sub-cell bias, which shrinks with the residual shift (the register loop re-extracts at the
    updated place, so the last correlation sees a near-zero shift)."""
    n = 45
    p = smooth_field(*cells(n), seed=4)
    big = smooth_field(*cells(n, (1.45, -2.35)), seed=4)
    res = correlate(big, p)
    assert res.status == "ok" and np.max(np.abs(res.offset - (1.45, -2.35))) < 0.5
    small = smooth_field(*cells(n, (0.05, -0.03)), seed=4)
    res = correlate(small, p)
    assert np.max(np.abs(res.offset - (0.05, -0.03))) < 0.02


@pytest.mark.parametrize("spacing", [2, 3, 4])
def test_binned_correlation_recovers_large_shifts(spacing):
    n = 81
    d = (3.7 * spacing, -2.6 * spacing)
    p = blob_image(n, sigma=2.5 * spacing)
    e = blob_image(n, d, sigma=2.5 * spacing)
    res = correlate(e, p, spacing=spacing, options=CorrelateOptions(min_valid=16))
    assert res.status == "ok" and res.spacing == spacing
    assert res.peak_index == (5 + round(d[0] / spacing), 5 + round(d[1] / spacing))
    np.testing.assert_allclose(res.offset, d, atol=0.05 * spacing)


def test_masks_zero_pixels_and_min_value():
    n = 41
    p = blob_image(n)
    e = blob_image(n, (1.3, -0.7))
    e[1:8, 25:38] = 0.0  # shadow: 0 = no data
    res = correlate(e, p)
    assert res.status == "ok"
    np.testing.assert_allclose(res.offset, (1.3, -0.7), atol=0.02)
    # the same cells declared invalid by mask give the same surface
    e2 = e.copy()
    e2[1:8, 25:38] = 123.0
    mask = np.ones(e.shape, bool)
    mask[1:8, 25:38] = False
    res2 = correlate(e2, p, extracted_valid=mask)
    np.testing.assert_allclose(res.surface, res2.surface, atol=1e-12)
    # min_value=None keeps the zeros (they then spoil the match)
    res3 = correlate(e, p, options=CorrelateOptions(min_value=None))
    assert res3.peak < res.peak - 0.01


def test_flat_and_edge_inputs_are_rejected_with_status():
    n = 31
    p = smooth_field(*cells(n))
    res = correlate(np.full((n, n), 100.0), p)
    assert res.status == "not-found" and np.all(np.isnan(res.surface)) and np.all(np.isnan(res.offset))
    e = smooth_field(*cells(n, (8.0, 0.0)))  # beyond the ±5 grid at spacing 1
    res = correlate(e, p)
    assert res.status == "edge-peak" and res.peak_index[0] == 10
    assert res.offset[0] == 5.0 and res.subpixel == (0.0, 0.0)
    rng = np.random.default_rng(0)
    res = correlate(rng.random((n, n)) + 1, p)  # unrelated images
    assert res.status in ("not-found", "edge-peak", "low-correlation")
    assert not res.ok


def test_image_space_anchors():
    """A template cut from a larger image is found at its true place: E is the search window, P the
    template, anchors give where P's anchor sits in E at zero offset."""
    big = blob_image(81, sigma=3.0, centre=(4.0, -3.0)) + 0.5 * blob_image(81, sigma=5.0, centre=(-6.0, 5.0))
    tmpl = big[30:51, 25:48]  # 21 x 23, anchor index (10, 11) ↔ big (40, 36)
    res = correlate(big, tmpl, extracted_anchor=(40 - 2, 36 + 3), predicted_anchor=(10, 11))
    assert res.status == "ok" and res.peak == pytest.approx(1.0, abs=1e-12)
    assert res.peak_index == (7, 2)
    np.testing.assert_allclose(res.offset, (2, -3), atol=0.02)
    with pytest.raises(SpcUsageError):
        correlate(big, tmpl)


def test_options_are_validated():
    with pytest.raises(SpcUsageError):
        CorrelateOptions(grid_half=0)
    with pytest.raises(SpcUsageError):
        CorrelateOptions(min_valid=1)
    with pytest.raises(SpcUsageError):
        CorrelateOptions(corr_min=1.5)
    with pytest.raises(SpcUsageError):
        CorrelateOptions(bin_min_fraction=2.0)
    p = np.ones((5, 5))
    with pytest.raises(SpcUsageError):
        correlate(p, p, spacing=0)
    with pytest.raises(SpcUsageError):
        correlate(p, p, extracted_valid=np.ones((4, 4), bool))


def test_grid_half_changes_the_grid():
    n = 41
    p = blob_image(n)
    e = blob_image(n, (6.2, -7.1))
    res = correlate(e, p, options=CorrelateOptions(grid_half=8))
    assert res.surface.shape == (17, 17) and res.grid_half == 8 and res.status == "ok"
    np.testing.assert_allclose(res.offset, (6.2, -7.1), atol=0.02)
