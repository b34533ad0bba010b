"""Illumination functions (L15 Eq. 3.41, S16 Eq. 16–17, errata 17)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool import photometry as ph

cosines = st.floats(0.01, 1.0)
phases = st.floats(0.0, 150.0)


def test_hand_values():
    # mu0 = 0.5, mu = 1, alpha = 60 deg: beta = exp(-1)
    b = np.exp(-1.0)
    assert ph.spc_lunar_lambert(0.5, 1.0, 60.0) == pytest.approx((1 - b) * 0.5 + b * 0.5 / 1.5, rel=1e-15)
    assert ph.mcewen_lunar_lambert(0.5, 1.0, 60.0) == pytest.approx(
        2 * b * 0.5 / 1.5 + (1 - b) * 0.5, rel=1e-15
    )
    assert ph.reflectance(0.5, 1.0, 10.0, "fixed") == pytest.approx(0.35 * 0.5 + 0.65 * 0.5 / 1.5, rel=1e-15)
    assert ph.reflectance(0.3, 0.9, 0.0, "lambert") == 0.3


@settings(max_examples=200, deadline=None)
@given(cosines, cosines, phases)
def test_spc_is_scaled_mcewen(mu0, mu, alpha):
    """R_SPC(β) = (1 − β/2)·R_McEwen(L = β/(2−β)) (spc-algorithms.md §3.2, checked independently)."""
    b = np.exp(-alpha / 60.0)
    L = b / (2 - b)
    mcewen_L = 2 * L * mu0 / (mu0 + mu) + (1 - L) * mu0
    assert ph.spc_lunar_lambert(mu0, mu, alpha) == pytest.approx((1 - b / 2) * mcewen_L, rel=1e-12)


def test_dark_cells_and_vectorisation():
    mu0 = np.array([-0.1, 0.0, 0.5, 0.5])
    mu = np.array([0.5, 0.5, -0.2, 0.5])
    for model in ph.MODELS:
        r = ph.reflectance(mu0, mu, 30.0, model)
        assert r.shape == (4,)
        assert np.all(r[:3] == 0) and r[3] > 0
        assert np.all(np.isfinite(r))


def test_phase_angle():
    s = np.array([1.0, 0, 0])
    e = np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0]])
    np.testing.assert_allclose(ph.phase_angle_deg(s, e), [0, 90, 180], atol=1e-12)


def test_unknown_model():
    with pytest.raises(ValueError, match="unknown photometric model"):
        ph.reflectance(0.5, 0.5, 0.0, "vesta")


@pytest.mark.parametrize("model", ph.MODELS)
@pytest.mark.parametrize("use_albedo", [True, False])
def test_render_kernel_law_equals_numpy_law(model, use_albedo):
    """The fused renderer's per-sub-ray law (geometry._rasterkernels.shade_subrays) equals
    reflectance() on degrees(arccos(clip(cos α))), times the albedo, 0 in shadow (≤ 1e-13 relative),
    on random inputs with dark (μ0 ≤ 0, μ ≤ 0, μ0 + μ tiny), shadowed, α ≈ 0°/180° and |cos α| > 1."""
    from spctool.geometry._rasterkernels import LAW_CODES, shade_subrays

    rng = np.random.default_rng(17)
    n = 4000
    mu0 = rng.uniform(-0.3, 1.0, n)
    mu = rng.uniform(-0.3, 1.0, n)
    cosa = rng.uniform(-1.0, 1.0, n)
    alb = rng.uniform(0.0, 2.0, n)
    edge = [
        (0.0, 0.5, 1.0),
        (0.5, 0.0, 1.0),
        (-1e-300, 0.5, 0.3),
        (1e-13, 1e-13, 0.2),
        (6e-13, 5e-13, 0.2),
        (0.7, 0.6, 1.0),
        (0.7, 0.6, 1.0 - 1e-16),
        (0.7, 0.6, 1.0 + 1e-15),
        (0.7, 0.6, -1.0),
        (0.7, 0.6, -1.0 + 1e-16),
        (0.7, 0.6, -1.0 - 1e-15),
        (1.0, 1.0, 0.0),
    ]
    for i, (a, b, c) in enumerate(edge):
        mu0[i], mu[i], cosa[i] = a, b, c
    sh = rng.random(n) < 0.2
    sh[: len(edge)] = False
    geom = np.column_stack([mu0, mu, cosa, alb])
    out = np.full(n, np.nan)
    shade_subrays(geom, sh, LAW_CODES[model], ph.FIXED_BETA, ph.ALPHA0_DEG, use_albedo, out)
    alpha = np.degrees(np.arccos(np.clip(cosa, -1.0, 1.0)))
    ref = ph.reflectance(mu0, mu, alpha, model)
    if use_albedo:
        ref = ref * alb
    ref = np.where(sh, 0.0, ref)
    assert np.count_nonzero(ref == 0.0) > n // 5 and np.count_nonzero(ref > 0.0) > n // 3
    np.testing.assert_array_equal(out == 0.0, ref == 0.0)
    np.testing.assert_allclose(out, ref, rtol=1e-13, atol=0.0)
    assert set(LAW_CODES) == set(ph.MODELS)
