"""Illumination functions for maplet prediction and rendering (L15 Eq. 3.41; S16 Eq. 15–17).

All functions take the cosines of incidence ``mu0 = n·s`` and emission
``mu = n·e`` (arrays, broadcast together) and the phase angle in **degrees**,
and return the reflectance without albedo.  Cells facing away from the Sun
(``mu0 <= 0``) or the camera (``mu <= 0``), and the degenerate ``mu0 + mu <= 1e-12``,
are dark (0) — prediction has no cast shadows unless a caller adds them.

* ``spc`` (default) — SPC's lunar-Lambert **without** McEwen's factor 2
  (spc-algorithms.md §3.2 and erratum 17): R = (1−β)·μ0 + β·μ0/(μ0+μ),
  β = exp(−α/60°).  It equals (1 − β/2)·McEwen(L = β/(2−β)); since the
  brightness scale λ absorbs the constant, only the Lambert/Lommel–Seeliger mix
  differs from McEwen's.
* ``mcewen`` — McEwen (1991): R = 2L·μ0/(μ0+μ) + (1−L)·μ0, L = exp(−α/60°).
* ``fixed`` — the SPC form with a constant β (L15's alternative, β = 0.65).
* ``lambert`` — R = μ0.
"""

from __future__ import annotations

import numpy as np

MODELS = ("spc", "mcewen", "fixed", "lambert")
ALPHA0_DEG = 60.0
FIXED_BETA = 0.65


def phase_angle_deg(sun, emission) -> np.ndarray:
    """Angle between unit vectors ``sun`` and ``emission`` (…, 3) in degrees, clipped for safety at 0°."""
    c = np.clip(np.sum(np.asarray(sun, float) * np.asarray(emission, float), axis=-1), -1.0, 1.0)
    return np.degrees(np.arccos(c))


def limb_weight(alpha_deg, alpha0_deg: float = ALPHA0_DEG):
    """β (SPC) or L (McEwen) = exp(−α/α0), α in degrees (S16 Eq. 17)."""
    return np.exp(-np.asarray(alpha_deg, float) / alpha0_deg)


def _dark_mask(mu0, mu):
    return (mu0 <= 0.0) | (mu <= 0.0) | (mu0 + mu <= 1e-12)


def _lommel(mu0, mu, dark):
    denom = np.where(dark, 1.0, mu0 + mu)
    return mu0 / denom


def spc_lunar_lambert(mu0, mu, alpha_deg, alpha0_deg: float = ALPHA0_DEG, beta=None):
    """SPC's function: (1−β)μ0 + β μ0/(μ0+μ); β = exp(−α/α0) unless given (no factor 2, erratum 17)."""
    mu0, mu = np.broadcast_arrays(np.asarray(mu0, float), np.asarray(mu, float))
    b = limb_weight(alpha_deg, alpha0_deg) if beta is None else np.asarray(beta, float)
    dark = _dark_mask(mu0, mu)
    r = (1.0 - b) * mu0 + b * _lommel(mu0, mu, dark)
    return np.where(dark, 0.0, r)


def mcewen_lunar_lambert(mu0, mu, alpha_deg, alpha0_deg: float = ALPHA0_DEG):
    """McEwen (1991): 2L μ0/(μ0+μ) + (1−L) μ0 with L = exp(−α/α0)."""
    mu0, mu = np.broadcast_arrays(np.asarray(mu0, float), np.asarray(mu, float))
    L = limb_weight(alpha_deg, alpha0_deg)
    dark = _dark_mask(mu0, mu)
    r = 2.0 * L * _lommel(mu0, mu, dark) + (1.0 - L) * mu0
    return np.where(dark, 0.0, r)


def lambert(mu0, mu=None, alpha_deg=None):
    """Lambert: μ0 (dark where μ0 ≤ 0, and where μ ≤ 0 when μ is given)."""
    mu0 = np.asarray(mu0, float)
    dark = mu0 <= 0.0
    if mu is not None:
        dark = dark | (np.asarray(mu, float) <= 0.0)
    return np.where(dark, 0.0, mu0)


def reflectance(
    mu0, mu, alpha_deg, model: str = "spc", *, beta: float = FIXED_BETA, alpha0_deg: float = ALPHA0_DEG
):
    """Dispatch on ``model`` in :data:`MODELS`."""
    if model == "spc":
        return spc_lunar_lambert(mu0, mu, alpha_deg, alpha0_deg)
    if model == "mcewen":
        return mcewen_lunar_lambert(mu0, mu, alpha_deg, alpha0_deg)
    if model == "fixed":
        return spc_lunar_lambert(mu0, mu, alpha_deg, beta=beta)
    if model == "lambert":
        return lambert(mu0, mu)
    raise ValueError(f"unknown photometric model {model!r}; expected one of {', '.join(MODELS)}")
