"""Tests of spctool.stages.predict (Stage B: slopes -> normals -> illumination -> lambda/phi).

Independent references: central differences by np.gradient for the normals, the reflectance written
out by hand, np.corrcoef for Pearson, the erratum-18 raw-moment formula for the background fit, and a
wall whose cast shadow length is H/tan(elevation).
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import appearance_scene as sc
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool.errors import SpcUsageError
from spctool.geometry import frames
from spctool.stages.predict import PredictOptions, fit_brightness, pearson, predict


def _maplet(q=12, heights=None, albedo=None, valid=None, uz=(0.1, -0.3, 1.0)):
    n = 2 * q + 1
    ux, uy, uz = frames.orient_frame(np.asarray(uz, float))
    x = (np.arange(n) - q)[:, None] * np.ones((1, n))
    y = (np.arange(n) - q)[None, :] * np.ones((n, 1))
    if heights is None:
        heights = 0.02 * x * x - 0.03 * x * y + 0.5 * np.sin(y / 3.0)
    if albedo is None:
        albedo = 1.0 + 0.2 * np.cos(x / 2.0) * np.sin(y / 3.0)
    if valid is None:
        valid = np.ones((n, n), bool)
    return SimpleNamespace(heights=np.asarray(heights, float), albedo=np.asarray(albedo, float), valid=valid,
                           scale=0.002, v=np.array([0.3, 0.1, 1.2]), ux=ux, uy=uy, uz=uz)


def _geometry(m, emission_deg=30.0, emission_az=20.0, sun_deg=45.0, sun_az=140.0, rng_km=2.0):
    e = sc.direction(m, emission_deg, emission_az)
    s = sc.direction(m, sun_deg, sun_az)
    return m.v + rng_km * e, s, e


# ------------------------------------------------------------------------------------------------
# pearson and the brightness fit


def test_pearson_matches_corrcoef_on_masked_cells():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(15, 15))
    b = 0.4 * a + rng.normal(size=(15, 15))
    mask = rng.random((15, 15)) > 0.3
    expected = np.corrcoef(a[mask], b[mask])[0, 1]
    assert pearson(a, b, mask) == pytest.approx(expected, abs=1e-14)
    assert pearson(a, b) == pytest.approx(np.corrcoef(a.ravel(), b.ravel())[0, 1], abs=1e-14)


def test_pearson_degenerate_cases_are_nan():
    a = np.arange(9.0).reshape(3, 3)
    one = np.zeros((3, 3), bool)
    one[1, 1] = True
    assert math.isnan(pearson(a, a, one))  # fewer than two cells
    assert math.isnan(pearson(a, np.full((3, 3), 2.0)))  # zero variance
    assert pearson(a, 2 * a + 1) == 1.0  # clipped, exactly 1
    assert pearson(a, -a) == -1.0


@settings(max_examples=50, deadline=None)
@given(st.floats(0.1, 10.0), st.floats(-5.0, 5.0), st.integers(0, 10_000))
def test_pearson_is_invariant_to_affine_maps(k, c, seed):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=40)
    b = rng.normal(size=40) + a
    r = pearson(a, b)
    assert pearson(a, k * b + c) == pytest.approx(r, abs=1e-12)
    assert pearson(k * a + c, b) == pytest.approx(r, abs=1e-12)
    assert pearson(a, -k * b + c) == pytest.approx(-r, abs=1e-12)


def _erratum18(p, e):
    """L15 Eq. 3.43/3.44 with erratum 18, raw moments."""
    mp, me = p.mean(), e.mean()
    mp2, mpe = (p * p).mean(), (p * e).mean()
    phi = (me * mp2 - mp * mpe) / (mp2 - mp * mp)
    return (me - phi) / mp, phi


def test_fit_recovers_gain_and_offset_exactly_with_background_on():
    rng = np.random.default_rng(7)
    p = rng.uniform(0.1, 1.0, (20, 20))
    e = 1.7 * p + 0.3
    mask = rng.random((20, 20)) > 0.2
    fit = fit_brightness(p, e, mask, bg_corr_min=0.5)
    assert fit.background_fitted
    assert fit.lam == pytest.approx(1.7, abs=1e-12)
    assert fit.phi == pytest.approx(0.3, abs=1e-12)
    assert fit.n == mask.sum()
    lam18, phi18 = _erratum18(p[mask], e[mask])
    assert fit.lam == pytest.approx(lam18, rel=1e-10)
    assert fit.phi == pytest.approx(phi18, rel=1e-9)


def test_fit_without_background_is_ratio_of_means():
    rng = np.random.default_rng(8)
    p = rng.uniform(0.1, 1.0, (20, 20))
    e = 1.7 * p + 0.3
    mask = rng.random((20, 20)) > 0.2
    for bg in (1.0, 2.0):  # the SPC default disables phi, even for a perfect (rho = 1) match
        fit = fit_brightness(p, e, mask, bg_corr_min=bg)
        assert not fit.background_fitted and fit.phi == 0.0
        assert fit.lam == pytest.approx(e[mask].mean() / p[mask].mean(), rel=1e-14)
    noisy = e + rng.normal(0.0, 0.5, e.shape)
    rho = pearson(p, noisy, mask)
    fit = fit_brightness(p, noisy, mask, bg_corr_min=rho + 0.01)  # correlation below the threshold
    assert fit.phi == 0.0 and fit.lam == pytest.approx(noisy[mask].mean() / p[mask].mean(), rel=1e-14)
    fit = fit_brightness(p, noisy, mask, bg_corr_min=rho - 0.01)
    lam18, phi18 = _erratum18(p[mask], noisy[mask])
    assert fit.background_fitted
    assert fit.lam == pytest.approx(lam18, rel=1e-10) and fit.phi == pytest.approx(phi18, rel=1e-9, abs=1e-12)


def test_fit_with_empty_mask_is_neutral():
    p = np.ones((3, 3))
    fit = fit_brightness(p, p, np.zeros((3, 3), bool), bg_corr_min=0.0)
    assert (fit.lam, fit.phi, fit.n) == (1.0, 0.0, 0) and math.isnan(fit.correlation)


@settings(max_examples=50, deadline=None)
@given(st.floats(0.05, 20.0), st.floats(-3.0, 3.0), st.integers(0, 10_000))
def test_fit_recovers_random_affine_maps(lam, phi, seed):
    rng = np.random.default_rng(seed)
    p = rng.uniform(0.0, 2.0, 50)
    fit = fit_brightness(p, lam * p + phi, np.ones(50, bool), bg_corr_min=0.0)
    assert fit.lam == pytest.approx(lam, rel=1e-10)
    assert fit.phi == pytest.approx(phi, abs=1e-10 * max(1.0, lam))


# ------------------------------------------------------------------------------------------------
# predict


def test_prediction_matches_hand_computed_illumination():
    m = _maplet()
    pos, sun, e_hat = _geometry(m)
    pr = predict(m, pos, sun)
    hx, hy = np.gradient(m.heights)  # central differences = HGT2SLP's first stencil in the interior
    n_m = np.stack([-hx, -hy, np.ones_like(hx)], axis=-1)
    n_m /= np.linalg.norm(n_m, axis=-1, keepdims=True)
    to_m = np.stack([m.ux, m.uy, m.uz])  # rows: maplet components of a body vector
    mu0 = n_m @ (to_m @ sun)
    mu = n_m @ (to_m @ e_hat)
    alpha = math.degrees(math.acos(float(sun @ e_hat)))
    beta = math.exp(-alpha / 60.0)
    r = np.where((mu0 > 0) & (mu > 0), (1 - beta) * mu0 + beta * mu0 / (mu0 + mu), 0.0)
    inner = (slice(1, -1), slice(1, -1))
    assert pr.alpha_deg == pytest.approx(alpha, abs=1e-10)
    np.testing.assert_allclose(pr.mu0[inner], mu0[inner], atol=1e-13)
    np.testing.assert_allclose(pr.mu[inner], mu[inner], atol=1e-13)
    np.testing.assert_allclose(pr.reflectance[inner], r[inner], atol=1e-13)
    np.testing.assert_allclose(pr.image[inner], (m.albedo * r)[inner], atol=1e-13)
    assert pr.lam == 1.0 and pr.phi == 0.0 and math.isnan(pr.correlation)
    assert pr.valid.all()
    np.testing.assert_allclose(pr.emission_vector, e_hat, atol=1e-15)


def test_one_emission_vector_for_the_whole_maplet():
    """The prediction depends on the direction landmark -> spacecraft only, not the range (S16)."""
    m = _maplet()
    pos, sun, e_hat = _geometry(m, rng_km=0.05)
    near = predict(m, pos, sun)
    far = predict(m, m.v + 1000.0 * e_hat, sun)
    np.testing.assert_allclose(near.image, far.image, atol=1e-12)
    # a per-node view vector would differ by ~ maplet size / range at 50 m: make sure it matters
    assert np.ptp(near.mu) > 0 and np.all(np.isfinite(near.mu))


@pytest.mark.parametrize("model", ["spc", "mcewen", "fixed", "lambert"])
def test_photometric_models(model):
    m = _maplet()
    pos, sun, e_hat = _geometry(m)
    pr = predict(m, pos, sun, PredictOptions(photometry=model, beta=0.4))
    mu0, mu = pr.mu0, pr.mu
    lit = (mu0 > 0) & (mu > 0)
    L = math.exp(-pr.alpha_deg / 60.0)
    expected = {
        "spc": (1 - L) * mu0 + L * mu0 / (mu0 + mu),
        "mcewen": 2 * L * mu0 / (mu0 + mu) + (1 - L) * mu0,
        "fixed": 0.6 * mu0 + 0.4 * mu0 / (mu0 + mu),
        "lambert": mu0,
    }[model]
    np.testing.assert_allclose(pr.reflectance, np.where(lit, expected, 0.0), atol=1e-14)


def test_missing_cells_are_invalid_not_dark():
    m = _maplet()
    m.valid[5, 7] = False
    m.valid[0, :4] = False
    m.albedo = np.where(m.valid, m.albedo, 0.0)
    pos, sun, _ = _geometry(m)
    pr = predict(m, pos, sun)
    assert not pr.valid[5, 7] and pr.image[5, 7] == 0.0
    # the neighbours keep a slope (one-sided stencils), hence stay valid
    assert pr.valid[4, 7] and pr.valid[6, 7] and pr.valid[5, 6] and pr.valid[5, 8]
    assert pr.image[4, 7] > 0
    assert not pr.valid[0, :4].any()


def test_lambda_phi_from_an_extracted_image():
    m = _maplet()
    pos, sun, _ = _geometry(m)
    base = predict(m, pos, sun)
    extracted = np.where(base.lit, 1.7 * base.image + 0.3, 0.0)
    extracted[3, 3] = 0.0  # a missing extracted cell is excluded from the fit
    on = predict(m, pos, sun, PredictOptions(bg_corr_min=0.5), extracted=extracted)
    assert on.background_fitted and on.correlation == pytest.approx(1.0, abs=1e-12)
    assert on.lam == pytest.approx(1.7, abs=1e-12) and on.phi == pytest.approx(0.3, abs=1e-12)
    assert on.n_fit == np.count_nonzero(base.lit) - 1
    np.testing.assert_allclose(on.image[on.fit_mask], extracted[on.fit_mask], atol=1e-12)
    off = predict(m, pos, sun, extracted=extracted)
    mask = base.lit & (extracted > 0)
    assert off.phi == 0.0 and not off.background_fitted
    assert off.lam == pytest.approx(extracted[mask].mean() / base.image[mask].mean(), rel=1e-14)
    np.testing.assert_allclose(off.image, off.lam * base.image, atol=1e-14)
    # an explicit validity mask removes cells from the fit
    ev = extracted > 0
    ev[:, :5] = False
    part = predict(m, pos, sun, extracted=extracted, extracted_valid=ev)
    assert part.n_fit == np.count_nonzero(base.lit & ev)


def test_dark_cells_stay_zero_with_a_background():
    m = _maplet()
    pos, sun, _ = _geometry(m, sun_deg=80.0)  # low Sun: some cells face away
    base = predict(m, pos, sun)
    assert (~base.lit & base.valid).any()
    extracted = np.where(base.lit, 2.0 * base.image + 0.5, 0.0)
    pr = predict(m, pos, sun, PredictOptions(bg_corr_min=0.0), extracted=extracted)
    assert pr.phi == pytest.approx(0.5, abs=1e-12)
    assert np.all(pr.image[~pr.lit] == 0.0)


def test_cast_shadows_behind_a_wall():
    q = 15
    n = 2 * q + 1
    h = np.zeros((n, n))
    h[:, q] = 6.0  # a wall along x (axis 0) at y = 0, 6 cells high
    m = _maplet(q=q, heights=h, albedo=np.ones((n, n)), uz=(0.0, 0.0, 1.0))
    elev = 40.0  # Sun toward +y (UY), 40 deg above the horizon: shadow on the -y side, 6/tan(40) = 7.15 cells
    sun = math.cos(math.radians(elev)) * m.uy + math.sin(math.radians(elev)) * m.uz
    pos = m.v + 3.0 * m.uz
    spc = predict(m, pos, sun, PredictOptions(shadows="spc"))
    cast = predict(m, pos, sun, PredictOptions(shadows="cast"))
    length = 6.0 / math.tan(math.radians(elev))
    ys = np.arange(n) - q
    rows = slice(3, n - 3)
    # the flat ground just behind the wall (beyond the 1-cell ramp of the slopes) is lit without cast shadows
    behind = (ys <= -2) & (ys >= -math.floor(length) + 1)
    beyond = ys <= -math.ceil(length) - 1
    assert np.all(spc.image[rows][:, behind] > 0)
    assert np.all(cast.image[rows][:, behind] == 0) and np.all(cast.shadowed[rows][:, behind])
    assert np.all(cast.image[rows][:, beyond] > 0)
    assert not cast.shadowed[:, ys > 1].any()  # the sunlit side
    assert not spc.shadowed.any()


def _wall_scene():
    q = 15
    n = 2 * q + 1
    h = np.zeros((n, n))
    h[:, q] = 6.0
    m = _maplet(q=q, heights=h, albedo=np.ones((n, n)), uz=(0.0, 0.0, 1.0))
    elev = 40.0
    sun = math.cos(math.radians(elev)) * m.uy + math.sin(math.radians(elev)) * m.uz
    return m, m.v + 3.0 * m.uz, sun


def test_auto_shadows_follow_what_the_photo_shows():
    """shadows="auto": SPC's rule when the extraction zeroed the shadows (they were below T1) or when
    there is no extraction; the maplet's cast shadows when the photo shows them above T1."""
    m, pos, sun = _wall_scene()
    cast = predict(m, pos, sun, PredictOptions(shadows="cast"))
    spc = predict(m, pos, sun, PredictOptions(shadows="spc"))
    assert PredictOptions().shadows == "auto"
    alone = predict(m, pos, sun)  # no photo: nothing says the shadows are not marked
    assert alone.options.shadows == "spc" and np.array_equal(alone.image, spc.image)
    # a photo whose shadows were below T1: the extraction is 0 there (SPC's own case)
    marked = np.where(cast.shadowed, 0.0, 100.0 + 50.0 * spc.reflectance)
    res = predict(m, pos, sun, extracted=marked)
    assert res.options.shadows == "spc" and not res.shadowed.any()
    # the same photo with its shadows at 40 DN, above T1: they are predicted
    unmarked = np.where(cast.shadowed, 40.0, marked)
    res = predict(m, pos, sun, extracted=unmarked)
    assert res.options.shadows == "cast" and np.array_equal(res.shadowed, cast.shadowed)
    assert np.array_equal(res.lit, cast.lit)
    # a precomputed cast-shadow mask gives the same prediction
    from spctool.geometry import heightfield

    mask = heightfield.cast_shadows(m.heights, m.valid, m.ux, m.uy, m.uz, sun / np.linalg.norm(sun))
    again = predict(m, pos, sun, extracted=unmarked, cast_shadows=mask)
    assert np.array_equal(again.image, res.image) and again.options.shadows == "cast"


def test_resolve_shadows_thresholds():
    from spctool.stages import predict as pr

    valid = np.ones((40, 40), bool)  # 1600 cells: 1 % is 16, below the 20-cell floor
    ext = np.full((40, 40), 10.0)
    few = np.zeros((40, 40), bool)
    few.flat[:19] = True
    assert pr.resolve_shadows(few, ext, valid) == "spc"  # too few shadow cells to matter
    some = np.zeros((40, 40), bool)
    some.flat[:40] = True
    assert pr.resolve_shadows(some, ext, valid) == "cast"  # all above T1
    ext2 = ext.copy()
    ext2.flat[:11] = 0.0  # 29 of 40 (72.5 %) above T1: below the 75 % needed
    assert pr.resolve_shadows(some, ext2, valid) == "spc"
    ext2.flat[10] = 10.0  # 30 of 40: exactly 75 %
    assert pr.resolve_shadows(some, ext2, valid) == "cast"
    big = np.ones((100, 100), bool)  # 1 % of 10000 = 100 cells
    ext3 = np.full((100, 100), 10.0)
    mask = np.zeros((100, 100), bool)
    mask.flat[:99] = True
    assert pr.resolve_shadows(mask, ext3, big) == "spc"
    mask.flat[99] = True
    assert pr.resolve_shadows(mask, ext3, big) == "cast"


def test_options_are_validated():
    with pytest.raises(SpcUsageError):
        PredictOptions(photometry="hapke")
    with pytest.raises(SpcUsageError):
        PredictOptions(shadows="soft")
    with pytest.raises(SpcUsageError):
        PredictOptions(beta=1.5)
    with pytest.raises(SpcUsageError):
        PredictOptions(alpha0_deg=0.0)
    m = _maplet()
    with pytest.raises(SpcUsageError):
        predict(m, m.v, m.uz)  # spacecraft at the landmark: no emission direction
    with pytest.raises(SpcUsageError):
        predict(m, m.v + m.uz, m.uz, extracted=np.ones((3, 3)))
