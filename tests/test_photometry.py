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
