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
from spctool.stages.alignment import gradient_offset, gradient_offset_photo, gradient_offset_symmetric
from spctool.stages.correlate import (
    CorrelateOptions,
    bin_image,
    correlate,
    find_peak,
    ncc_surface,
    parabola_vertex,
    peak_covariance,
    quadric_fit,
    quadric_vertex,
    resampled_noise_footprint,
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


def tilted_field(x, y, seed=5, n=14, lam=(12.0, 40.0), theta_deg=35.0, spread_deg=50.0):
    """Plane waves whose directions cluster around ``theta``: an anisotropic texture whose correlation
    peak is a tilted ellipse (normalised cross term ≈ −0.57 at spacing 1, like sun-shaded terrain)."""
    rng = np.random.default_rng(seed)
    wl = rng.uniform(lam[0], lam[1], n)
    th = math.radians(theta_deg) + rng.uniform(-1.0, 1.0, n) * math.radians(spread_deg)
    ph = rng.uniform(0, 2 * np.pi, n)
    kx, ky = np.cos(th) * 2 * np.pi / wl, np.sin(th) * 2 * np.pi / wl
    return 10.0 + np.sin(x[..., None] * kx + y[..., None] * ky + ph).sum(-1)


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


@pytest.mark.parametrize("n,frac", [(2, 0.0), (3, 0.5), (4, 1.0), (5, 0.3)])
def test_bin_kernel_equals_numpy_block_means_bitwise(n, frac):
    """The binning kernel sums each block's valid pixels in scan order and divides once: bit for bit
    NumPy's unbuffered ``add.at`` in the same order and a masked ``divide``."""
    from spctool.stages.correlate import _block_range

    rng = np.random.default_rng(n)
    v = rng.normal(size=(23, 19)) * 10.0 ** rng.uniform(-3, 3, (23, 19))
    m = rng.random(v.shape) > 0.25
    anchor = (9, 4)
    b, bv, ba = bin_image(v, m, n, anchor, min_fraction=frac)
    r0, r1 = _block_range(v.shape[0], anchor[0], n)
    c0, c1 = _block_range(v.shape[1], anchor[1], n)
    i, j = np.nonzero(m)  # row-major: the kernel's order
    bi = (i - anchor[0] + n // 2) // n - r0
    bj = (j - anchor[1] + n // 2) // n - c0
    sums = np.zeros((r1 - r0 + 1, c1 - c0 + 1))
    cnts = np.zeros_like(sums)
    np.add.at(sums, (bi, bj), v[i, j])
    np.add.at(cnts, (bi, bj), 1.0)
    ok = (cnts > 0) & (cnts >= frac * n * n - 1e-9)
    ref = np.zeros_like(sums)
    np.divide(sums, cnts, out=ref, where=ok)
    assert ba == (-r0, -c0)
    np.testing.assert_array_equal(bv, ok)
    assert b.tobytes() == ref.tobytes()


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


def _grid_peak_reference(s, strict_8):
    """Stage G's grid checks with NumPy: ``(code, (r0, c0))`` as :func:`_k_grid_peak` encodes them."""
    finite = np.isfinite(s)
    if not finite.any():
        return 1, None
    flat = np.where(finite, s, -np.inf)
    r0, c0 = divmod(int(np.argmax(flat)), s.shape[1])
    pk = s[r0, c0]
    if np.count_nonzero(flat == pk) > 1:
        return 2, (r0, c0)
    if r0 in (0, s.shape[0] - 1) or c0 in (0, s.shape[1] - 1):
        return 3, (r0, c0)
    around = np.delete(s[r0 - 1 : r0 + 2, c0 - 1 : c0 + 2].ravel(), 4)  # the 8 neighbours
    if not strict_8:
        around = around[[1, 3, 4, 6]]  # the four along the axes
    if not np.all(around < pk):
        return 4, (r0, c0)
    return 0, (r0, c0)


@settings(max_examples=200, deadline=None)
@given(
    g=st.sampled_from([3, 5, 7, 11]),
    seed=st.integers(0, 2**31 - 1),
    kind=st.sampled_from(["normal", "nan", "ties", "inf", "all-nan"]),
    strict_8=st.booleans(),
)
def test_grid_peak_kernel_equals_the_numpy_reference(g, seed, kind, strict_8):
    """The compiled grid checks of Stage G (:func:`_k_grid_peak`) agree with NumPy's argmax, tie
    count, border and neighbour tests on surfaces with undefined values, ties and infinities."""
    from spctool.stages.correlate import _k_grid_peak

    rng = np.random.default_rng(seed)
    s = rng.normal(size=(g, g))
    if kind == "nan":
        s[rng.random(s.shape) < 0.2] = np.nan
    elif kind == "ties":
        s = np.round(s, 1)
    elif kind == "inf":
        s[rng.random(s.shape) < 0.2] = np.inf * rng.choice([-1.0, 1.0])
    elif kind == "all-nan":
        s[:] = np.nan
    code, r0, c0, all9 = _k_grid_peak(s, strict_8)
    ref, idx = _grid_peak_reference(s, strict_8)
    assert code == ref
    if idx is not None:
        assert (r0, c0) == idx
    if code == 0:
        assert all9 == bool(np.isfinite(s[r0 - 1 : r0 + 2, c0 - 1 : c0 + 2]).all())


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
    par = CorrelateOptions(peak="parabola")
    res = correlate(big, p, options=par)
    assert res.status == "ok" and np.max(np.abs(res.offset - (1.45, -2.35))) < 0.5
    assert np.max(np.abs(correlate(big, p).offset - (1.45, -2.35))) < 0.02  # quadric (default)
    small = smooth_field(*cells(n, (0.05, -0.03)), seed=4)
    res = correlate(small, p, options=par)
    assert np.max(np.abs(res.offset - (0.05, -0.03))) < 0.02


# --------------------------------------------------------------------------------------------------
# the 2-D quadric peak and the measurement covariance


def _ellipse(s1, s2, rho=None, angle_deg=None):
    """2×2 covariance: axis sigmas with a correlation ρ, or principal sigmas rotated by an angle."""
    if rho is not None:
        return np.array([[s1 * s1, rho * s1 * s2], [rho * s1 * s2, s2 * s2]])
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    r = np.array([[c, -s], [s, c]])
    return r @ np.diag([s1 * s1, s2 * s2]) @ r.T


def _grid_offsets(g=11):
    k = (g - 1) // 2
    i, j = np.mgrid[0:g, 0:g].astype(float)
    return np.stack([i - k, j - k], axis=-1)


def _quadratic_peak(d, cov, g=11):
    """1 − ½(x − d)ᵀΣ⁻¹(x − d) on the grid: a quadric, which the least-squares fit must recover exactly."""
    x = _grid_offsets(g) - np.asarray(d)
    return 1.0 - 0.5 * np.einsum("...i,ij,...j->...", x, np.linalg.inv(cov), x)


def _gaussian_peak(d, cov, g=11, amp=0.9):
    x = _grid_offsets(g) - np.asarray(d)
    return amp * np.exp(-0.5 * np.einsum("...i,ij,...j->...", x, np.linalg.inv(cov), x))


def _estimate(surface, peak):
    status, _, idx, sub = find_peak(surface, peak=peak)
    assert status == "ok"
    return np.array(idx, float) - 5 + np.array(sub)


def test_quadric_fit_closed_form_equals_lstsq_and_handles_missing_diagonals():
    rng = np.random.default_rng(7)
    u, v = np.meshgrid((-1, 0, 1), (-1, 0, 1), indexing="ij")
    a = np.stack([np.ones(9), u.ravel(), v.ravel(), u.ravel() ** 2, (u * v).ravel(), v.ravel() ** 2], 1)
    z = rng.normal(size=(3, 3))
    np.testing.assert_allclose(quadric_fit(z), np.linalg.lstsq(a, z.ravel(), rcond=None)[0], atol=1e-12)
    coef = np.array([0.7, 0.1, -0.2, -0.5, 0.3, -0.4])
    zq = (a @ coef).reshape(3, 3)
    miss = zq.copy()
    miss[0, 0] = miss[2, 2] = np.nan  # two undefined diagonals: still exact
    np.testing.assert_allclose(quadric_fit(miss), coef, atol=1e-12)
    nodiag = zq.copy()
    nodiag[[0, 0, 2, 2], [0, 2, 0, 2]] = np.nan  # no diagonal: no cross term, SPC's two parabolas
    c = quadric_fit(nodiag)
    assert c[4] == 0.0
    dr, dc, _, ok = quadric_vertex(nodiag)
    assert (
        ok
        and dr == pytest.approx(parabola_vertex(*zq[:, 1]))
        and dc == pytest.approx(parabola_vertex(*zq[1, :]))
    )
    axis = zq.copy()
    axis[1, 2] = np.nan
    assert np.all(np.isnan(quadric_fit(axis)))


def test_quadric_rejects_saddles_and_far_vertices():
    u, v = np.meshgrid((-1.0, 0.0, 1.0), (-1.0, 0.0, 1.0), indexing="ij")
    saddle = 1.0 - 0.2 * u * u + 0.05 * v * v
    assert not quadric_vertex(saddle)[3]
    far = 1.0 - 0.01 * u * u - 0.2 * v * v + 0.05 * u  # vertex at u = 2.5: outside the neighbourhood
    dr, dc, h, ok = quadric_vertex(far)
    assert not ok and math.isnan(dr) and np.all(np.isfinite(h))
    assert quadric_vertex(far, max_move=3.0)[0] == pytest.approx(2.5)
    # a grid maximum (all 8 neighbours lower) on a diagonal ridge: the quadric is a saddle, so the peak
    # (which passed SPC's checks) takes the parabolas' estimate and their curvature
    ridge = np.array([[0.97, 0.9, 0.9], [0.9, 1.0, 0.9], [0.9, 0.9, 0.999]])
    s = np.zeros((11, 11))
    s[4:7, 4:7] = ridge
    assert find_peak(s) == find_peak(s, peak="parabola")
    from spctool.stages.correlate import _find_peak

    st_, _, _, sub, h, fit = _find_peak(s, 0.3, False, "quadric")
    assert st_ == "ok" and fit == "parabola-fallback" and sub == find_peak(s, peak="parabola")[3]
    np.testing.assert_allclose(h, np.diag([-0.2, -0.2]))
    assert _find_peak(s, 0.3, False, "parabola")[5] == "parabola"
    with pytest.raises(SpcUsageError):
        find_peak(s, peak="spline")
    with pytest.raises(SpcUsageError):
        CorrelateOptions(peak="spline")


@pytest.mark.parametrize(
    "cov",
    [_ellipse(2.0, 1.5, rho=0.5), _ellipse(3.0, 1.2, angle_deg=30), _ellipse(2.5, 1.0, angle_deg=-70)],
    ids=["rho0.5", "rot30", "rot-70"],
)
def test_quadric_is_exact_on_tilted_quadratic_peaks_and_the_parabola_is_not(cov):
    """The coupling bias of SPC's separable parabolas: on a tilted quadratic peak each axis estimate
    is off by −(e/2d)·(other axis's offset) — for ρ = 0.5 about half of it — while the 2-D quadric is
    exact."""
    rng = np.random.default_rng(11)
    worst_q = worst_p = 0.0
    for _ in range(40):
        d = rng.uniform(-0.5, 0.5, 2)
        s = _quadratic_peak(d, cov)
        if find_peak(s)[2] != (5, 5):
            continue
        worst_q = max(worst_q, np.max(np.abs(_estimate(s, "quadric") - d)))
        worst_p = max(worst_p, np.max(np.abs(_estimate(s, "parabola") - d)))
    assert worst_q <= 1e-9
    assert worst_p > 0.05
    # the documented coupling, exactly: parabola along u at v-offset δ_c misses by (e/2d)·δ_c
    d = np.array([0.1, 0.3])
    s = _quadratic_peak(d, cov)
    assert find_peak(s)[2] == (5, 5)
    hinv = np.linalg.inv(cov)  # the surface's Hessian is −Σ⁻¹: d = −Σ⁻¹[0,0]/2, e = −Σ⁻¹[0,1]
    err = _estimate(s, "parabola") - d
    assert err[0] == pytest.approx(hinv[0, 1] / hinv[0, 0] * d[1], abs=1e-12)
    assert err[1] == pytest.approx(hinv[0, 1] / hinv[1, 1] * d[0], abs=1e-12)


@pytest.mark.parametrize(
    "cov",
    [_ellipse(6.0, 4.8, rho=0.5), _ellipse(7.0, 4.0, angle_deg=30), _ellipse(7.0, 4.0, angle_deg=120)],
    ids=["rho0.5", "rot30", "rot120"],
)
def test_quadric_recovers_shifts_of_tilted_gaussian_peaks(cov):
    """Sampled anisotropic Gaussians (not quadrics): the quadric's only error is pixel locking, which
    is ≤ 0.01 cell for peaks this wide at any sub-cell shift and shrinks with the shift; the parabola's
    coupling bias stays above 0.05 cell."""
    rng = np.random.default_rng(3)
    eq, ep = [], []
    for _ in range(60):
        d = rng.uniform(-0.5, 0.5, 2)
        s = _gaussian_peak(d, cov)
        eq.append(_estimate(s, "quadric") - d)
        ep.append(_estimate(s, "parabola") - d)
    assert np.max(np.abs(eq)) <= 0.012
    assert np.max(np.abs(ep)) > 0.05
    # narrower peaks (w ≈ 3 cells) at the small shifts the register loop converges to
    narrow = _ellipse(3.0, 2.4, rho=0.5)
    for _ in range(40):
        d = rng.uniform(-0.1, 0.1, 2)
        assert np.max(np.abs(_estimate(_gaussian_peak(d, narrow), "quadric") - d)) <= 0.01


def test_quadric_recovers_shifts_in_the_ncc_of_a_tilted_texture():
    """End to end: E is a texture shifted by a known (integer + fractional) amount, P the texture; the
    NCC peak is a tilted ellipse (cross term ≈ −0.57).  Quadric ≤ 0.01 cell; parabola > 0.05."""
    n = 45
    p = tilted_field(*cells(n))
    rng = np.random.default_rng(0)
    par = CorrelateOptions(peak="parabola")
    eq, ep = [], []
    for _ in range(20):
        d = rng.uniform(-0.5, 0.5, 2) + rng.integers(-3, 4, 2)
        e = tilted_field(*cells(n, d))
        rq, rp = correlate(e, p), correlate(e, p, options=par)
        assert rq.ok and rp.ok and rq.peak_fit == "quadric" and rp.peak_fit == "parabola"
        eq.append(rq.offset - d)
        ep.append(rp.offset - d)
    h = rq.hessian
    assert h[0, 1] / math.sqrt(h[0, 0] * h[1, 1]) < -0.4  # tilted
    assert np.max(np.abs(eq)) <= 0.01
    assert np.max(np.abs(ep)) > 0.05


# --------------------------------------------------------------------------------------------------
# the least-squares alignment ("gradient")


def _sharp(n, shift=(0.0, 0.0), theta=35.0, seed=5):
    """A sharp anisotropic texture (wavelengths 2.5–6 cells, like sun-shaded terrain at full resolution)."""
    return tilted_field(*cells(n, shift), seed=seed, lam=(2.5, 6.0), theta_deg=theta)


def _blob_mask(n):
    """An asymmetric validity mask: a cut corner and a shadow-like hole off the centre."""
    m = np.ones((n, n), bool)
    m[: n // 3, : n // 4] = False
    yy, xx = np.mgrid[:n, :n]
    m[(yy - 0.7 * n) ** 2 + (xx - 0.3 * n) ** 2 < (0.12 * n) ** 2] = False
    return m


def test_gradient_is_exactly_zero_at_a_perfect_alignment_where_a_vertex_is_not():
    """E = 3·P + 7 placed at a whole-cell offset: the alignment reads that offset to rounding, while the
    quadric's (and the parabolas') vertex of the same, asymmetric, surface is off by more than 1e-3
    cell — the bias a re-centring loop cannot remove (issue #15)."""
    n, d = 61, np.array([2.0, -1.0])
    e = 3.0 * _sharp(n, d) + 7.0
    p = _sharp(n)
    mask = _blob_mask(n)
    g = correlate(e, p, predicted_valid=mask, options=CorrelateOptions(peak="gradient"))
    q = correlate(e, p, predicted_valid=mask)
    par = correlate(e, p, predicted_valid=mask, options=CorrelateOptions(peak="parabola"))
    assert g.ok and g.peak_fit == "gradient" and g.peak == pytest.approx(1.0)
    np.testing.assert_allclose(g.offset, d, rtol=0, atol=1e-9)
    assert np.max(np.abs(q.offset - d)) > 1e-3 and np.max(np.abs(par.offset - d)) > 1e-3
    # the covariance is still the surface's (the quadric's Hessian at the same grid peak)
    np.testing.assert_array_equal(g.hessian, q.hessian)


@settings(max_examples=20, deadline=None)
@given(
    dx=st.floats(-0.5, 0.5),
    dy=st.floats(-0.5, 0.5),
    theta=st.floats(0.0, 180.0),
    seed=st.integers(0, 50),
)
def test_gradient_zero_is_the_true_subpixel_shift_of_rotated_textures(dx, dy, theta, seed):
    """The alignment read with P re-centred on c, F(c), vanishes at the true shift: a root finder on F
    (as register's converged stage re-extracts / re-renders until F < tol) recovers the shift of sharp,
    rotated textures under an asymmetric mask to ≤ 1e-3 cell, where the quadric's fixed point is off
    by up to several 1e-2.  (F's slope is not 1: central differences underestimate a sharp
    texture's gradient, so plain re-centring would oscillate slowly; the zero does not move.)"""
    from scipy.optimize import root

    n = 51
    d = np.array([dx, dy])
    e = _sharp(n, d, theta, seed)
    mask = _blob_mask(n)
    opts = CorrelateOptions(peak="gradient")

    def read(c, o=opts):
        r = correlate(e, _sharp(n, c, theta, seed), predicted_valid=mask, options=o)
        assert r.ok
        return r

    # start where the quadric puts it (within a few 1e-2 cell): the alignment's first-order range
    x0 = read(np.zeros(2), CorrelateOptions()).offset
    sol = root(lambda c: read(c).offset, x0, method="hybr", options={"xtol": 1e-9})
    end = read(sol.x)
    assert end.peak_fit == "gradient" and np.max(np.abs(end.offset)) < 1e-6
    assert np.max(np.abs(sol.x - d)) <= 1e-3


def test_gradient_offset_refuses_degenerate_pairs():
    n = 21
    p = _sharp(n)
    ok = np.ones((n, n), bool)
    assert not gradient_offset(np.full((n, n), 5.0), ok, p, ok, (0, 0))[2]  # no gain
    assert not gradient_offset(-p, ok, p, ok, (0, 0))[2]  # negative gain
    assert not gradient_offset(p, ok, np.full((n, n), 1.0), ok, (0, 0))[2]  # constant prediction
    few = np.zeros((n, n), bool)
    few[5:7, 5:8] = True
    assert not gradient_offset(p, few, p, few, (0, 0))[2]  # < 8 usable pixels
    assert not gradient_offset(p, ok, p, ok, (n, 0))[2]  # no overlap
    # a shift beyond the linear range (> 1 cell) is refused; correlate then keeps the quadric
    far = _sharp(n, (0.9, 0.0))
    dr, dc, good = gradient_offset(far, ok, p, ok, (0, 0), max_move=0.5)
    assert not good and math.isnan(dr) and math.isnan(dc)


def test_peak_covariance_formula_and_degenerate_cases():
    h = np.array([[-0.02, 0.01], [0.01, -0.03]])
    cov = peak_covariance(h, 0.8, 400.0, 2.0)
    np.testing.assert_allclose(cov, (1 - 0.64) / (0.8 * 200.0) * np.linalg.inv(-h), rtol=1e-12)
    assert np.all(np.isnan(peak_covariance(-h, 0.8, 400.0)))  # a minimum
    assert np.all(np.isnan(peak_covariance(h, -0.2, 400.0)))
    assert np.all(peak_covariance(h, 1.0, 400.0) == 0.0)  # a perfect match has no noise
    assert resampled_noise_footprint(2.0) == 1.0 and resampled_noise_footprint(0.5) == pytest.approx(9.0)
    assert math.isnan(resampled_noise_footprint(0.0))


def test_peak_covariance_equals_the_array_formula_bitwise():
    """The element-by-element covariance equals (1 − ρ²)/(ρN/f)·(−H)⁻¹ symmetrised with arrays, bit
    for bit."""
    rng = np.random.default_rng(11)
    for _ in range(500):
        a = rng.normal(size=(2, 2))
        h = -(a @ a.T) - 1e-3 * np.eye(2) if rng.random() < 0.8 else rng.normal(size=(2, 2))
        rho, count, fp = rng.uniform(0.01, 1.0), float(rng.integers(1, 5000)), rng.uniform(0.5, 3.0)
        det = h[0, 0] * h[1, 1] - h[0, 1] * h[1, 0]
        got = peak_covariance(h, rho, count, fp)
        if not (h[0, 0] < 0.0 and det > 0.0):
            assert np.all(np.isnan(got))
            continue
        inv_neg = np.array([[-h[1, 1], h[0, 1]], [h[1, 0], -h[0, 0]]]) / det
        cov = (1.0 - rho * rho) / (rho * count / fp) * inv_neg
        assert got.tobytes() == (0.5 * (cov + cov.T)).tobytes()
        # ``times``: n² for cells of spacing n, bit for bit the array times the integer
        n = int(rng.integers(2, 6))
        assert peak_covariance(h, rho, count, fp, n * n).tobytes() == ((n * n) * got).tobytes()


def _scatter_vs_predicted(make_e, p, footprint, trials, d):
    offs, covs = [], []
    for _ in range(trials):
        r = correlate(make_e(), p, options=CorrelateOptions(min_value=None), noise_footprint=footprint)
        if r.ok:
            offs.append(r.offset)
            covs.append(r.covariance)
    offs = np.array(offs)
    emp = np.cov(offs.T)
    pred = np.mean(covs, axis=0)
    return emp, pred, len(offs)


@pytest.mark.parametrize("noise", [0.3, 1.0, 2.0])
def test_covariance_matches_the_scatter_of_noise_trials(noise):
    """Monte Carlo: the predicted 1σ per axis is within a factor 1.5 of the empirical scatter of the
    offset over noise trials (and the predicted correlation of the axes is within 0.15)."""
    n = 41
    p = tilted_field(*cells(n))
    d = np.array([0.3, -0.2])
    base = tilted_field(*cells(n, d))
    rng = np.random.default_rng(int(noise * 10))
    emp, pred, k = _scatter_vs_predicted(lambda: base + rng.normal(0.0, noise, base.shape), p, 1.0, 200, d)
    assert k >= 195
    ratio = np.sqrt(np.diag(pred) / np.diag(emp))
    assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), ratio
    rho_e = emp[0, 1] / math.sqrt(emp[0, 0] * emp[1, 1])
    rho_p = pred[0, 1] / math.sqrt(pred[0, 0] * pred[1, 1])
    assert abs(rho_e - rho_p) < 0.15


@pytest.mark.parametrize("h", [0.5, 1.5])
def test_covariance_of_a_bilinearly_resampled_photo(h):
    """Maplet space resamples the photo bilinearly onto the cells (h px per cell): the noise of nearby
    cells is then shared and the footprint (resampled_noise_footprint) keeps the prediction within a
    factor 1.5 of the scatter (without it, at h = 0.5, it would be 3× too small)."""
    from scipy.ndimage import map_coordinates

    n = 41
    p = tilted_field(*cells(n))
    d = np.array([0.3, -0.2])
    m = int(np.ceil(n * h)) + 6
    axis = (np.arange(m) - m / 2) / h
    xp, yp = np.meshgrid(axis, axis, indexing="ij")
    photo = tilted_field(xp - d[0], yp - d[1])
    xc, yc = cells(n)
    where = np.stack([xc * h + m / 2, yc * h + m / 2])
    rng = np.random.default_rng(5)

    def make_e():
        return map_coordinates(photo + rng.normal(0.0, 1.0, photo.shape), where, order=1)

    emp, pred, k = _scatter_vs_predicted(make_e, p, resampled_noise_footprint(h), 200, d)
    assert k >= 195
    ratio = np.sqrt(np.diag(pred) / np.diag(emp))
    assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), ratio


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


@pytest.mark.parametrize("min_value", [None, 0.0, 0.4])
def test_validity_kernel_equals_numpy(min_value):
    """correlate's validity test (finite, inside the mask, above ``min_value``) in its kernel equals
    the NumPy expression, with NaN, ±inf and a non-contiguous input."""
    from spctool.stages.correlate import _valid_mask

    rng = np.random.default_rng(7)
    v = rng.normal(size=(30, 42))
    v[rng.random(v.shape) < 0.1] = np.nan
    v[rng.random(v.shape) < 0.05] = np.inf
    v[rng.random(v.shape) < 0.05] = -np.inf
    vm = rng.random(v.shape) > 0.2
    for values, valid in ((v, vm), (v[:, ::2], vm[:, ::2])):
        ref = np.isfinite(values) & valid
        if min_value is not None:
            with np.errstate(invalid="ignore"):
                ref &= values > min_value
        got_v, got_m = _valid_mask(values, valid, min_value)
        np.testing.assert_array_equal(got_m, ref)
        assert got_v.flags.c_contiguous and np.array_equal(got_v, values, equal_nan=True)


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


def _alignment_pixels(e, me, p, mp, origin):
    """The alignment's masked pixels by NumPy: (p, its central-difference gradients along rows and
    columns, e at the origin's offset) over the pixels where both masks and p's four neighbours hold,
    in scan order, and the kernel's window (i0, i1, j0, j1)."""
    o0, o1 = origin
    hp, wp = p.shape
    he, we = e.shape
    i0, i1 = max(1, 1 - o0), min(hp - 1, he - 1 - o0)
    j0, j1 = max(1, 1 - o1), min(wp - 1, we - 1 - o1)

    def win(a, di, dj, oi=0, oj=0):
        return a[i0 + oi + di : i1 + oi + di, j0 + oj + dj : j1 + oj + dj]

    ok = win(mp, 0, 0) & win(me, 0, 0, o0, o1)
    for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        ok &= win(mp, di, dj)
    cols = (
        win(p, 0, 0)[ok],
        0.5 * (win(p, 1, 0) - win(p, -1, 0))[ok],
        0.5 * (win(p, 0, 1) - win(p, 0, -1))[ok],
        win(e, 0, 0, o0, o1)[ok],
    )
    return cols, (i0, i1, j0, j1)


def _gradient_offset_reference(e, me, p, mp, origin):
    """The alignment's least squares with NumPy masks and a dense solve (the kernel's reference)."""
    (pv, gr, gc, ev), _ = _alignment_pixels(e, me, p, mp, origin)
    m = np.stack([pv - pv.mean(), gr - gr.mean(), gc - gc.mean()], axis=1)
    coef = np.linalg.lstsq(m, ev - ev.mean(), rcond=None)[0]
    return -coef[1] / coef[0], -coef[2] / coef[0], coef[0]


@given(seed=st.integers(0, 2**31 - 1), o0=st.integers(-3, 3), o1=st.integers(-3, 3))
@settings(max_examples=40, deadline=None)
def test_gradient_offset_kernel_matches_a_dense_least_squares(seed, o0, o1):
    """The two-pass kernel of the alignment equals NumPy's least squares on the same masked pixels."""
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(17, 19)).cumsum(axis=0).cumsum(axis=1)  # smooth-ish texture
    e = 3.0 * np.roll(p, (1, -1), axis=(0, 1)) + 7.0 + 0.3 * rng.normal(size=p.shape)
    e = np.pad(e, 3, mode="edge")
    mp = rng.random(p.shape) > 0.1
    me = rng.random(e.shape) > 0.1
    dr, dc, good = gradient_offset(e, me, p, mp, (3 + o0, 3 + o1), max_move=1e9)
    rr, rc, gain = _gradient_offset_reference(e, me, p, mp, (3 + o0, 3 + o1))
    assert good == (gain > 0.0)  # a misplaced origin can leave no positive gain: refused by both
    if good:
        np.testing.assert_allclose([dr, dc], [rr, rc], rtol=1e-8, atol=1e-9)


@given(seed=st.integers(0, 2**31 - 1), o0=st.integers(-3, 3), o1=st.integers(-3, 3))
@settings(max_examples=40, deadline=None)
def test_alignment_kernel_sums_equal_sequential_numpy_sums_bitwise(seed, o0, o1):
    """The alignment kernel's normal matrix and right-hand side are, bit for bit, sequential sums in
    scan order (NumPy's cumsum) over the masked pixels, of regressors centred on their sequential means."""
    from spctool.stages.alignment import _k_alignment

    rng = np.random.default_rng(seed)
    p = rng.normal(size=(17, 19)).cumsum(axis=0).cumsum(axis=1)
    e = np.pad(3.0 * p + 7.0 + 0.3 * rng.normal(size=p.shape), 3, mode="edge")
    mp = rng.random(p.shape) > 0.1
    me = rng.random(e.shape) > 0.1
    o0, o1 = 3 + o0, 3 + o1
    (*cols, y), (i0, i1, j0, j1) = _alignment_pixels(e, me, p, mp, (o0, o1))
    n = len(y)

    def seq(x):  # a sequential sum (cumsum adds in order; the kernel starts from 0.0 as well)
        return np.cumsum(np.concatenate([[0.0], x]))[-1]

    x = [c - seq(c) / n for c in cols]
    yc = y - seq(y) / n
    ref_n = np.array([[seq(a * b) for b in x] for a in x])
    ref_r = np.array([seq(a * yc) for a in x])
    normal, rhs = np.zeros((3, 3)), np.zeros(3)
    assert _k_alignment(e, me, p, mp, o0, o1, i0, i1, j0, j1, normal, rhs) == n
    assert normal.tobytes() == ref_n.tobytes() and rhs.tobytes() == ref_r.tobytes()


@given(
    seed=st.integers(0, 2**31 - 1),
    half=st.integers(0, 4),
    shape=st.tuples(st.integers(3, 14), st.integers(3, 14), st.integers(2, 12), st.integers(2, 12)),
    origin=st.tuples(st.integers(-6, 6), st.integers(-6, 6)),
    min_valid=st.sampled_from([1, 4, 25]),
    holes=st.sampled_from([0.0, 0.2, 0.6]),
)
@pytest.mark.slow
@settings(max_examples=150, deadline=None)
def test_ncc_kernel_equals_its_bd3e756_version_bit_for_bit(seed, half, shape, origin, min_valid, holes):
    """The rewritten NCC kernel (unsigned indices, one array per prefix and box sum) keeps every sum's
    operations and order: its surfaces and counts equal the bd3e756 kernel's (``tests/ncc_reference.py``)
    to the last bit — masks with holes, offsets reaching beyond either image, constant images."""
    from ncc_reference import k_ncc_bd3e756

    rng = np.random.default_rng(seed)
    he, we, hp, wp = shape
    e = rng.normal(size=(he, we)) * rng.choice([1.0, 1e-3, 1e3]) + rng.choice([0.0, 5.0])
    p = rng.normal(size=(hp, wp))
    if rng.random() < 0.1:
        p[:] = 2.0  # constant: NaN where it is the whole overlap
    me, mp = rng.random(e.shape) >= holes, rng.random(p.shape) >= holes
    g = 2 * half + 1
    surf, cnts = ncc_surface(e, me, p, mp, grid_half=half, min_valid=min_valid, origin=origin)
    ref, ref_n = np.empty((g, g)), np.empty((g, g))
    k_ncc_bd3e756(e, me, p, mp, origin[0], origin[1], half, float(min_valid), ref, ref_n)
    assert surf.tobytes() == ref.tobytes()
    np.testing.assert_array_equal(cnts, np.rint(ref_n).astype(np.int64))


@pytest.mark.parametrize("spacing", [1, 2, 3])
def test_correlate_valid_is_correlate_for_masks_of_valid_pixels(spacing):
    """Image space's entry (masks already the valid, finite pixels; no ``min_value``) returns what
    correlate returns."""
    from spctool.stages.correlate import correlate_valid

    rng = np.random.default_rng(spacing)
    e = rng.normal(size=(60, 64))
    p = e[9:47, 11:51] + 0.05 * rng.normal(size=(38, 40))
    e[rng.integers(0, 60, 40), rng.integers(0, 64, 40)] = np.nan
    me = rng.uniform(size=e.shape) > 0.05
    mp = rng.uniform(size=p.shape) > 0.05
    opts = CorrelateOptions(grid_half=3, peak="gradient", min_value=None)  # image space's: no DN floor
    ea, pa = (28, 31), (19, 20)
    ref = correlate(
        e, p, extracted_valid=me, predicted_valid=mp, spacing=spacing, options=opts,
        extracted_anchor=ea, predicted_anchor=pa,
    )  # fmt: skip
    got = correlate_valid(e, me & np.isfinite(e), p, mp & np.isfinite(p), spacing, opts, ea, pa)
    assert got.status == ref.status and got.peak_fit == ref.peak_fit
    np.testing.assert_array_equal(got.surface, ref.surface)
    np.testing.assert_array_equal(got.offset, ref.offset)
    np.testing.assert_array_equal(got.covariance, ref.covariance)


# --------------------------------------------------------------------------------------------------
# the alignment the other way round: the prediction fitted on the photo (gradient_offset_photo)


def _photo_alignment_reference(e, me, p, mp, origin):
    """P ≈ α·E + β + c·∇E by dense NumPy least squares over the pixels where both masks and both
    images' four axis neighbours hold (E at + origin); δ = c/α.  Written from the formula, not from
    the kernel."""
    o0, o1 = origin
    rows, pv, ev, gr, gc = [], [], [], [], []
    for i in range(p.shape[0]):
        for j in range(p.shape[1]):
            ie, je = i + o0, j + o1
            if not (1 <= ie < e.shape[0] - 1 and 1 <= je < e.shape[1] - 1):
                continue
            if not (mp[i, j] and me[ie, je] and me[ie - 1, je] and me[ie + 1, je]):
                continue
            if not (me[ie, je - 1] and me[ie, je + 1]):
                continue
            if not (1 <= i < p.shape[0] - 1 and 1 <= j < p.shape[1] - 1):
                continue
            if not (mp[i - 1, j] and mp[i + 1, j] and mp[i, j - 1] and mp[i, j + 1]):
                continue  # P's own axis neighbours valid too (the pixels of the symmetric form)
            pv.append(p[i, j])
            ev.append(e[ie, je])
            gr.append(0.5 * (e[ie + 1, je] - e[ie - 1, je]))
            gc.append(0.5 * (e[ie, je + 1] - e[ie, je - 1]))
            rows.append((i, j))
    a = np.stack([np.asarray(ev), np.asarray(gr), np.asarray(gc), np.ones(len(ev))], axis=1)
    coef = np.linalg.lstsq(a, np.asarray(pv), rcond=None)[0]
    return coef[1] / coef[0], coef[2] / coef[0], coef[0]


def _shifted_pair(seed):
    """A smooth random prediction P (17 × 19), the photo E = 3·P shifted by (1, −1) + 7 + noise,
    padded by 3, and random masks (90 % valid) for the dense-least-squares alignment checks."""
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(17, 19)).cumsum(axis=0).cumsum(axis=1)
    e = 3.0 * np.roll(p, (1, -1), axis=(0, 1)) + 7.0 + 0.3 * rng.normal(size=p.shape)
    e = np.pad(e, 3, mode="edge")
    mp = rng.random(p.shape) > 0.1
    me = rng.random(e.shape) > 0.1
    return p, e, mp, me


@given(seed=st.integers(0, 2**31 - 1), o0=st.integers(-3, 3), o1=st.integers(-3, 3))
@settings(max_examples=30, deadline=None)
def test_photo_alignment_matches_a_dense_least_squares(seed, o0, o1):
    """gradient_offset_photo equals the least squares of the prediction on the photo and its gradient,
    computed pixel by pixel from the formula (P's own axis neighbours must be valid too, so its
    border rows and columns are never used)."""
    p, e, mp, me = _shifted_pair(seed)
    dr, dc, good = gradient_offset_photo(e, me, p, mp, (3 + o0, 3 + o1), max_move=1e9)
    rr, rc, gain = _photo_alignment_reference(e, me, p, mp, (3 + o0, 3 + o1))
    assert good == (gain > 0.0)
    if good:
        np.testing.assert_allclose([dr, dc], [rr, rc], rtol=1e-8, atol=1e-9)


def test_photo_alignment_is_exactly_zero_at_a_perfect_alignment():
    """E = 3·P + 7 at a whole-cell offset under an asymmetric mask: both alignments read the offset to
    rounding (correlate's peak="gradient-photo" reports its own estimator)."""
    n, d = 61, np.array([2.0, -1.0])
    e = 3.0 * _sharp(n, d) + 7.0
    p = _sharp(n)
    mask = _blob_mask(n)
    g = correlate(e, p, predicted_valid=mask, options=CorrelateOptions(peak="gradient-photo"))
    assert g.ok and g.peak_fit == "gradient-photo"
    np.testing.assert_allclose(g.offset, d, rtol=0, atol=1e-9)
    with pytest.raises(SpcUsageError, match="gradient-photo"):
        CorrelateOptions(peak="gradient-photos")


def _shifted_texture():
    """A smooth 61×61 texture P and E = 2·P shifted by d = (0.3, −0.2) cell + 1, with the rms of P's
    gradient per axis (the noise level of the alignment's noise tests): (n, d, P, E, σ)."""
    n, d = 61, np.array([0.3, -0.2])
    x = np.arange(n, dtype=float)

    def tex(s=(0.0, 0.0)):
        r, c = x[:, None] - s[0], x[None, :] - s[1]
        return np.sin(r / 4.0 + 0.3) * np.cos(c / 5.0) + 0.5 * np.sin((r + c) / 6.0)

    clean_p, clean_e = tex(), 2.0 * tex(d) + 1.0
    g = np.gradient(clean_p)
    return n, d, clean_p, clean_e, float(np.sqrt(np.mean(g[0] ** 2 + g[1] ** 2) / 2.0))


def test_noise_biases_the_alignment_whose_regressors_carry_it():
    """Least squares is unbiased for noise in the fitted image and attenuated by noise in its
    regressors.  A smooth texture shifted by (0.3, −0.2) cell, white noise of its gradient's rms on
    one image, 40 draws: the noisy image as the fitted side reads the shift to within a few standard
    errors and the first-order expansion's error (≈ 1 %); as the regressor it reads it shortened by
    the attenuation var(∇P)/(var(∇P) + var(∇noise)) ≈ 2/3."""
    n, d, clean_p, clean_e, sigma = _shifted_texture()
    ok = np.ones((n, n), bool)
    rng = np.random.default_rng(3)
    reads = {"p noisy": ([], []), "e noisy": ([], [])}
    for _ in range(40):
        noisy_p = clean_p + sigma * rng.normal(size=(n, n))
        noisy_e = clean_e + 2.0 * sigma * rng.normal(size=(n, n))
        for key, (e, p) in (("p noisy", (clean_e, noisy_p)), ("e noisy", (noisy_e, clean_p))):
            a = gradient_offset(e, ok, p, ok, (0, 0))
            b = gradient_offset_photo(e, ok, p, ok, (0, 0))
            assert a[2] and b[2]
            reads[key][0].append(a[:2])
            reads[key][1].append(b[:2])
    for key, fitted_noisy, regressor_noisy in (("p noisy", 1, 0), ("e noisy", 0, 1)):
        good = np.asarray(reads[key][fitted_noisy])
        bad = np.asarray(reads[key][regressor_noisy])
        se = good.std(axis=0, ddof=1) / math.sqrt(len(good))
        assert np.all(np.abs(good.mean(axis=0) - d) < 4 * se + 0.01 * np.abs(d)), key
        # the attenuated read: shorter than the shift by more than 20 % on each axis
        assert np.all(np.abs(bad.mean(axis=0)) < 0.8 * np.abs(d)), key


# --------------------------------------------------------------------------------------------------
# the alignment on both images' gradients (gradient_offset_symmetric: w = ½, or w from their noise)


def _symmetric_alignment_reference(e, me, p, mp, origin, weight):
    """D = E − P' on [1, w·E + (1 − w)·P', w·∇E + (1 − w)·∇P'] by dense least squares, pixel by
    pixel from the formula (P' = s·P with s = σ_E/σ_P; both images' four axis neighbours valid);
    δ = −c/(1 + γ(1 − 2w)).  ``weight=None``: w = ν_P/(ν_E + ν_P) from the five-point Laplacians'
    variances beyond their covariance.  Returns (δ_r, δ_c, w, cov(E, P))."""
    o0, o1 = origin
    rows = []
    for i in range(1, p.shape[0] - 1):
        for j in range(1, p.shape[1] - 1):
            ie, je = i + o0, j + o1
            if not (1 <= ie < e.shape[0] - 1 and 1 <= je < e.shape[1] - 1):
                continue
            nb = ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1))
            if not all(mp[i + a, j + b] and me[ie + a, je + b] for a, b in nb):
                continue
            row = []
            for img, a, b in ((p, i, j), (e, ie, je)):
                row += [
                    img[a, b],
                    0.5 * (img[a + 1, b] - img[a - 1, b]),
                    0.5 * (img[a, b + 1] - img[a, b - 1]),
                    img[a - 1, b] + img[a + 1, b] + img[a, b - 1] + img[a, b + 1] - 4 * img[a, b],
                ]
            rows.append(row)
    pv, pgr, pgc, pl, ev, egr, egc, el = np.asarray(rows).T
    s = ev.std() / pv.std()
    pv, pgr, pgc, pl = s * pv, s * pgr, s * pgc, s * pl
    if weight is None:
        shared = np.cov(el, pl, bias=True)[0, 1]
        nu_e, nu_p = max(el.var() - shared, 0.0), max(pl.var() - shared, 0.0)
        weight = nu_p / (nu_e + nu_p)
    w = weight
    mix = [w * ev + (1 - w) * pv, w * egr + (1 - w) * pgr, w * egc + (1 - w) * pgc]
    a = np.stack([np.ones_like(ev), *mix], axis=1)
    beta, gamma, cr, cc = np.linalg.lstsq(a, ev - pv, rcond=None)[0]
    den = 1 + gamma * (1 - 2 * w)
    return -cr / den, -cc / den, w, np.cov(ev, pv)[0, 1]


@given(
    seed=st.integers(0, 2**31 - 1),
    o0=st.integers(-3, 3),
    o1=st.integers(-3, 3),
    weight=st.sampled_from([0.5, 0.2, 0.9, None]),
)
@settings(max_examples=40, deadline=None)
def test_symmetric_alignment_matches_a_dense_least_squares(seed, o0, o1, weight):
    """gradient_offset_symmetric equals the formula's least squares computed pixel by pixel, for a
    fixed w and for the w it estimates from the two images' Laplacians."""
    p, e, mp, me = _shifted_pair(seed)
    dr, dc, w, good = gradient_offset_symmetric(e, me, p, mp, (3 + o0, 3 + o1), weight, max_move=1e9)
    rr, rc, rw, cov = _symmetric_alignment_reference(e, me, p, mp, (3 + o0, 3 + o1), weight)
    assert good == (cov > 0.0)  # a misplaced origin can leave the images anti-correlated: refused
    if good:
        np.testing.assert_allclose([dr, dc, w], [rr, rc, rw], rtol=1e-7, atol=1e-9)


def test_symmetric_alignment_at_its_ends_is_each_one_sided_fit():
    """w = 0 is gradient_offset's fit and w = 1 gradient_offset_photo's (same pixels when every pixel
    is valid): the regressors span the same space and δ = −c/(1 + γ(1 − 2w)) reads the same shift."""
    rng = np.random.default_rng(11)
    p = rng.normal(size=(23, 21)).cumsum(axis=0).cumsum(axis=1)
    e = 2.0 * np.roll(p, (1, 0), axis=(0, 1)) + 1.0 + 2.0 * rng.normal(size=p.shape)
    ok = np.ones(p.shape, bool)
    sym0 = gradient_offset_symmetric(e, ok, p, ok, (0, 0), 0.0, max_move=1e9)
    sym1 = gradient_offset_symmetric(e, ok, p, ok, (0, 0), 1.0, max_move=1e9)
    one0 = gradient_offset(e, ok, p, ok, (0, 0), max_move=1e9)
    one1 = gradient_offset_photo(e, ok, p, ok, (0, 0), max_move=1e9)
    np.testing.assert_allclose(sym0[:2], one0[:2], atol=1e-10)
    np.testing.assert_allclose(sym1[:2], one1[:2], atol=1e-10)
    assert abs(sym0[0] - sym1[0]) > 0.01  # the noise makes the two ends differ: the check can fail


@pytest.mark.parametrize("peak", ["gradient-symmetric", "gradient-weighted"])
def test_symmetric_alignment_is_exactly_zero_at_a_perfect_alignment(peak):
    """E = 3·P + 7 at a whole-cell offset under an asymmetric mask: the offset to rounding, whatever w."""
    n, d = 61, np.array([2.0, -1.0])
    e = 3.0 * _sharp(n, d) + 7.0
    p = _sharp(n)
    mask = _blob_mask(n)
    g = correlate(e, p, predicted_valid=mask, options=CorrelateOptions(peak=peak))
    assert g.ok and g.peak_fit == peak
    np.testing.assert_allclose(g.offset, d, rtol=0, atol=1e-9)


def test_symmetric_alignment_halves_the_bias_of_noise_on_either_side():
    """The texture of the one-sided test above, shifted by (0.3, −0.2) cell, white noise on one image,
    40 draws.  The one-sided fit with the noisy image as regressor reads the shift short by ~30 %; the
    mean of both gradients carries half that noise amplitude and is off by at most half as much
    (measured about a third) whichever image is noisy; the noise-weighted fit finds the noisy side
    (w within 0.1 of the clean image's end) and reads the shift as the unbiased one-sided fit does."""
    n, d, clean_p, clean_e, sigma = _shifted_texture()
    ok = np.ones((n, n), bool)
    rng = np.random.default_rng(3)
    for noisy in ("p", "e"):
        keys = ("one-sided, noisy regressor", "one-sided, clean regressor", "symmetric", "weighted")
        reads = {k: [] for k in keys}
        weights = []
        for _ in range(40):
            e = clean_e + (2.0 * sigma * rng.normal(size=(n, n)) if noisy == "e" else 0.0)
            p = clean_p + (sigma * rng.normal(size=(n, n)) if noisy == "p" else 0.0)
            a, b = gradient_offset(e, ok, p, ok, (0, 0)), gradient_offset_photo(e, ok, p, ok, (0, 0))
            bad, good = (a, b) if noisy == "p" else (b, a)
            reads["one-sided, noisy regressor"].append(bad[:2])
            reads["one-sided, clean regressor"].append(good[:2])
            reads["symmetric"].append(gradient_offset_symmetric(e, ok, p, ok, (0, 0))[:2])
            wr = gradient_offset_symmetric(e, ok, p, ok, (0, 0), None)
            reads["weighted"].append(wr[:2])
            weights.append(wr[2])
        bias = {k: np.abs(np.mean(v, axis=0) - d) for k, v in reads.items()}
        se = np.std(reads["weighted"], axis=0, ddof=1) / math.sqrt(40)
        assert np.all(bias["one-sided, noisy regressor"] > 0.2 * np.abs(d)), noisy
        assert np.all(bias["symmetric"] <= 0.5 * bias["one-sided, noisy regressor"]), noisy
        assert np.all(bias["weighted"] < 4 * se + 0.01 * np.abs(d)), noisy
        assert (min(weights) > 0.9) if noisy == "p" else (max(weights) < 0.1), noisy


def test_symmetric_alignment_refuses_degenerate_pairs():
    n = 15
    ok = np.ones((n, n), bool)
    p = np.add.outer(np.arange(n) ** 2, np.arange(n)).astype(float)
    assert not gradient_offset_symmetric(np.full((n, n), 5.0), ok, p, ok, (0, 0))[3]  # flat photo
    assert not gradient_offset_symmetric(-p, ok, p, ok, (0, 0))[3]  # anti-correlated
    few = np.zeros((n, n), bool)
    few[5:8, 5:8] = True
    assert not gradient_offset_symmetric(p, few, p, few, (0, 0))[3]  # < 8 usable pixels
    assert not gradient_offset_symmetric(p, ok, p, ok, (n, 0))[3]  # no overlap
