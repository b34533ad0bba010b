"""spctool.sim.terrain: procedural craters, boulders, roughness and albedo (S16 simulation substitute)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool.errors import SpcUsageError
from spctool.sim.terrain import (
    AlbedoField,
    Boulders,
    Craters,
    Roughness,
    Terrain,
    boulder_profile,
    crater_profile,
    gradient_noise,
)

NO_CRATERS = Craters(coefficient=0.0)
NO_BOULDERS = Boulders(coefficient=0.0)
NO_ROUGH = Roughness(amplitude_km=0.0)
NO_ALBEDO = AlbedoField(contrast=0.0)


def _points(n, seed=0, scale=0.05, centre=(0.2, 0.1, 0.05)):
    rng = np.random.default_rng(seed)
    return np.asarray(centre) + rng.uniform(-scale, scale, size=(n, 3))


def test_deterministic_and_order_independent():
    t = Terrain(seed=11)
    p = _points(3000)
    h1, a1 = t.evaluate(p)
    h2, a2 = t.evaluate(p)
    assert np.array_equal(h1, h2) and np.array_equal(a1, a2)
    perm = np.random.default_rng(1).permutation(p.shape[0])
    h3, a3 = t.evaluate(p[perm])
    assert np.array_equal(h3, h1[perm]) and np.array_equal(a3, a1[perm])
    # shape of the input is kept
    h4, a4 = t.evaluate(p.reshape(30, 100, 3))
    assert h4.shape == (30, 100) and np.array_equal(h4.ravel(), h1)
    h5, _ = Terrain(seed=12).evaluate(p)
    assert not np.allclose(h5, h1)


@settings(max_examples=25, deadline=None)
@given(split=st.floats(min_value=1e-4, max_value=0.2), seed=st.integers(0, 2**40))
def test_bands_add_up_to_the_full_terrain(split, seed):
    t = Terrain(seed=seed)
    p = _points(200, seed=seed % 1000)
    full = t.heights(p)
    lo = t.heights(p, (0.0, split))
    hi = t.heights(p, (split, math.inf))
    np.testing.assert_allclose(lo + hi, full, rtol=0, atol=1e-15)


def _brute_force(t: Terrain, p, band=(0.0, math.inf)):
    """Heights and albedo from the enumerated features with the reference profiles (no kernel code)."""
    # every feature that can reach a point: craters reach one diameter, boulders half of one
    pad_c, pad_b = t.craters.max_diameter_km, 0.5 * t.boulders.max_diameter_km
    lo, hi = p.min(axis=0), p.max(axis=0)
    h = np.zeros(p.shape[0])
    alb = np.zeros(p.shape[0])
    cr = t.features("craters", lo - pad_c, hi + pad_c, band)
    top = np.zeros(p.shape[0])
    boff = np.zeros(p.shape[0])
    bo = t.features("boulders", lo - pad_b, hi + pad_b, band)
    for a in range(0, cr.diameters.size, 500):
        c, d, r = cr.centres[a : a + 500], cr.diameters[a : a + 500], cr.spare[a : a + 500]
        rho = np.linalg.norm(p[:, None, :] - c[None], axis=2) / (0.5 * d)
        h += crater_profile(rho, d, t.craters.depth_ratio, t.craters.rim_ratio).sum(axis=1)
        alb += np.where(rho < 1, t.craters.albedo * r * (1 - rho**2), 0.0).sum(axis=1)
    for a in range(0, bo.diameters.size, 500):
        c, d, r = bo.centres[a : a + 500], bo.diameters[a : a + 500], bo.spare[a : a + 500]
        rho = np.linalg.norm(p[:, None, :] - c[None], axis=2) / (0.5 * d)
        hb = boulder_profile(rho, d, t.boulders.height_ratio)
        h += hb.sum(axis=1)
        k = np.argmax(hb, axis=1)
        best = hb[np.arange(p.shape[0]), k]
        take = best > top  # features are enumerated in the kernel's order, so ties resolve alike
        top = np.where(take, best, top)
        boff = np.where(take, t.boulders.albedo_spread * (2 * r[k] - 1), boff)
    return h, np.clip(1.0 + alb + boff, t.albedo.min, t.albedo.max)


@pytest.mark.parametrize("band", [(0.0, math.inf), (0.0, 0.004), (0.004, math.inf)])
def test_features_match_a_brute_force_sum_of_reference_profiles(band):
    t = Terrain(
        seed=5,
        craters=Craters(coefficient=0.1, min_diameter_km=0.002, max_diameter_km=0.02),
        boulders=Boulders(coefficient=0.002, min_diameter_km=0.001, max_diameter_km=0.006),
        roughness=NO_ROUGH,
        albedo=NO_ALBEDO,
    )
    p = _points(1500, scale=0.015)
    h, a = t.evaluate(p, band)
    hb, ab = _brute_force(t, p, band)
    assert np.count_nonzero(h) > 500  # the region is well covered
    np.testing.assert_allclose(h, hb, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(a, ab, rtol=1e-12, atol=1e-15)


def test_surface_density_follows_the_power_law():
    """Spheres meeting a plane per km², N(>D), is coefficient·D^−slope (the documented semantics)."""
    coef, slope = 1e-3, 2.5
    t = Terrain(
        seed=3,
        craters=Craters(coefficient=coef, slope=slope, min_diameter_km=0.001, max_diameter_km=0.016),
        boulders=NO_BOULDERS,
    )
    half = 0.25
    feats = t.features("craters", [-half, -half, -0.02], [half, half, 0.02])
    cut = np.abs(feats.centres[:, 2]) < 0.5 * feats.diameters  # the sphere meets the plane z = 0
    inside = (np.abs(feats.centres[:, 0]) < half - 0.02) & (np.abs(feats.centres[:, 1]) < half - 0.02)
    d = feats.diameters[cut & inside]
    area = (2 * (half - 0.02)) ** 2
    for dmin in (0.001, 0.002, 0.004):
        n = np.count_nonzero(d >= dmin)
        expected = area * coef * (dmin**-slope - 0.016**-slope)
        assert n > 100
        assert abs(n - expected) < 4 * math.sqrt(expected) + 0.02 * expected, (dmin, n, expected)
    assert d.min() >= 0.001 and d.max() < 0.016


def test_profiles_by_hand():
    # crater of D = 10 m: depth 2 m, rim 0.4 m
    np.testing.assert_allclose(
        crater_profile([0.0, 1.0, 2.0, 3.0], 0.01), [0.0004 - 0.002, 0.0004, 0.0, 0.0], atol=1e-15
    )
    np.testing.assert_allclose(crater_profile(1.5, 0.01), 0.0004 * (1 / 3.375 - 0.125) * 8 / 7)
    np.testing.assert_allclose(boulder_profile([0.0, 0.6, 1.0], 0.004), [0.002, 0.002 * 0.8, 0.0])


def test_single_octave_roughness_amplitudes_follow_hurst():
    hurst = 0.7
    t = Terrain(
        seed=9,
        craters=NO_CRATERS,
        boulders=NO_BOULDERS,
        albedo=NO_ALBEDO,
        roughness=Roughness(
            amplitude_km=0.001, hurst=hurst, min_wavelength_km=0.001, max_wavelength_km=0.016
        ),
    )
    p = np.random.default_rng(2).uniform(-1, 1, size=(20000, 3))
    rms = []
    for k in range(4):
        lam = 0.016 * 0.5**k
        h = t.heights(p, (lam * 0.99, lam * 1.01))
        rms.append(np.sqrt(np.mean(h**2)))
    ratios = np.array(rms[1:]) / np.array(rms[:-1])
    np.testing.assert_allclose(ratios, 0.5**hurst, rtol=0.05)


def test_gradient_noise_is_zero_on_the_lattice_and_bounded():
    lattice = np.random.default_rng(0).integers(-1000, 1000, size=(500, 3)).astype(float)
    assert np.all(gradient_noise(lattice, seed=4) == 0.0)
    p = np.random.default_rng(1).uniform(-50, 50, size=(20000, 3))
    v = gradient_noise(p, seed=4)
    assert np.abs(v).max() < 1.5 and 0.1 < v.std() < 0.5
    # continuity: tiny steps give tiny changes
    dv = gradient_noise(p + 1e-7, seed=4) - v
    assert np.abs(dv).max() < 1e-5


def test_albedo_is_clipped_and_varies():
    t = Terrain(seed=2, albedo=AlbedoField(contrast=2.0, min=0.5, max=1.5))
    a = t.albedo_at(_points(5000, scale=0.1))
    assert a.min() >= 0.5 and a.max() <= 1.5
    assert np.any(a == 0.5) and np.any(a == 1.5)


def test_fbm_band_is_separate_from_the_feature_band():
    t = Terrain(seed=1)
    p = _points(500)
    only_fbm = t.albedo_at(p, (0.0, 0.0), fbm_band=(0.0, math.inf))
    no_feat = Terrain(seed=1, craters=NO_CRATERS, boulders=NO_BOULDERS).albedo_at(p)
    np.testing.assert_array_equal(only_fbm, no_feat)


def test_bad_specifications_are_usage_errors():
    with pytest.raises(SpcUsageError, match="min < max"):
        Craters(min_diameter_km=0.01, max_diameter_km=0.001)
    with pytest.raises(SpcUsageError, match="density too high"):
        Terrain(boulders=Boulders(coefficient=1e3))
    with pytest.raises(SpcUsageError):
        Terrain(seed=-1)
    with pytest.raises(SpcUsageError):
        AlbedoField(min=1.0, max=0.5)
