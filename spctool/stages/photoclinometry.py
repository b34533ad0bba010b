"""Stereophotoclinometry numerics — SPC LITHOS "Find heights": per-cell slopes and albedo from several
registered pictures, and each picture's brightness scale λ.

Specification: ``map-refinement.md`` §2 (brightness model, per-cell normal equations, the analytic
Jacobian after GIANT's ``illumination.py``, the three-azimuth rule, the λ fit and its pitfalls);
L15 Eq. 3.37–3.45 and S16 Eq. 12–17 (the model SPC predicts with, :mod:`spctool.stages.predict`);
S16 Introduction ¶4 (≥ 3 pictures with different Sun azimuths per cell).  Pure functions, no I/O,
vectorised over every cell and picture at once (no per-cell Python loop).  The slopes → heights
integration is :mod:`spctool.stages.slope_integration`; the outer loop (re-extraction,
re-registration) :mod:`spctool.stages.find_heights`.

Conventions (those of :mod:`spctool.geometry.heightfield`): arrays (N, N), axis 0 along UX, axis 1
along UY; heights in cells; t₁ = ∂h/∂x along UX, t₂ = ∂h/∂y along UY (cells per cell); maplet-frame
unit normal n̂ = (−t₁, −t₂, 1)/√(1 + t₁² + t₂²) (L15 Eq. 3.37); per picture k one maplet-frame Sun
direction ŝ_k and one emission direction ê_k (landmark → spacecraft, as ``predict`` uses), phase α_k.

Brightness model (L15 Eq. 3.41, 3.45; S16 Eq. 15–17)
-----------------------------------------------------
P_k = λ_k · a · R(μ₀, μ) with μ₀ = n̂·ŝ_k, μ = n̂·ê_k and R = c₁·μ₀ + c₂·μ₀/(μ₀ + μ), where
(c₁, c₂) = (1 − β, β), β = exp(−α/60°) for SPC's lunar-Lambert (``"spc"``, no factor 2, erratum 17),
(1 − L, 2L) for McEwen's, (1 − β, β) with a fixed β for ``"fixed"`` and (1, 0) for ``"lambert"``
(:mod:`spctool.photometry`).  A cell with μ₀ ≤ 0 or μ ≤ 0 is dark in that picture and takes no part
in its fit.  The background φ is 0, as SPC runs (φ = 0.000 in every auto-align printout).

Per-cell solve (:func:`solve_cells`; SPC's FIND_TMPL, GIANT's update mode)
-------------------------------------------------------------------------
Unknowns per cell: (t₁, t₂, a).  Gauss–Newton on Σ_k w_k (O_k − P_k)², w_k = 1/λ_k² (each picture
counts in reflectance units, whatever its exposure), with the analytic Jacobian (:func:`jacobian`):
∂P/∂a = λR, ∂P/∂t_i = λa (R_μ₀ ∂μ₀/∂t_i + R_μ ∂μ/∂t_i), R_μ₀ = c₁ + c₂ μ/(μ₀ + μ)²,
R_μ = −c₂ μ₀/(μ₀ + μ)², ∂μ₀/∂t_i = (−s_i − μ₀ t_i/|n|)/|n| (the chain through
∂n̂/∂n = (I − n̂n̂ᵀ)/|n| of map-refinement.md §2, written out).  The 3×3 normal equations of every
cell are formed as six sums over the pictures and solved together by the adjugate, damped
Levenberg–Marquardt style: (A + d·diag(A) + d·ε·max diag(A)) δ = b, d = ``damping`` (GIANT:
5e-3).  Each step's slope change is capped at ``max_step`` per cell; a cell stops iterating when no
component of its step exceeds 1e-9.  The iterations run in a compiled kernel, one cell at a time
(:func:`_k_gauss_newton`; :func:`_gauss_newton_numpy` is the same steps over all cells at once with
numpy, the reference it is tested against).

A cell is **solvable** when at least ``min_azimuths`` (3) of the pictures lit and valid on it have
Sun azimuths (in the maplet plane) at least ``azimuth_separation_deg`` apart (S16; the pictures are
grouped by azimuth, :func:`azimuth_groups`).  Others keep their prior slopes and albedo and are
flagged (:attr:`CellSolution.flagged`), as are cells whose solve diverged (non-finite, or a slope
beyond ``max_slope``).

Brightness scale (:func:`fit_lambda`)
--------------------------------------
λ_k = Σ O·p / Σ p² over the cells valid in picture k, p = a·R (the least-squares scale without
background, L15 Eq. 3.43–3.44 with φ = 0).  λ has no absolute radiometry: scaling every λ by c and
every albedo by 1/c leaves every prediction unchanged, so the albedo is normalised to mean 1 over the
solved cells (:func:`normalise_albedo`) and λ rescaled with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numba
import numpy as np

from spctool import photometry as phot
from spctool.errors import SpcUsageError

__all__ = [
    "CellSolution",
    "PassResult",
    "Pictures",
    "SolveOptions",
    "azimuth_groups",
    "brightness",
    "fit_lambda",
    "heights_pass",
    "jacobian",
    "normalise_albedo",
    "photometric_constants",
    "residual_rms",
    "solvable_cells",
    "solve_cells",
]


@dataclass
class SolveOptions:
    """Constants of the per-cell solve (module docstring).

    ``photometry``: ``"spc"``, ``"mcewen"``, ``"fixed"`` (with ``beta``) or ``"lambert"``;
    ``alpha0_deg``: α₀ of β = exp(−α/α₀).  ``damping``: Levenberg–Marquardt d (5e-3, GIANT);
    ``iterations``: Gauss–Newton steps per solve; ``max_step``: cap on a step's slope change (cells
    per cell); ``max_slope``: a solved |t| beyond this is refused (flagged); ``min_azimuths`` and
    ``azimuth_separation_deg``: the solvability rule; ``albedo_min``/``albedo_max``: bounds of the
    relative albedo (the MAP byte holds 0.01…1.99).
    """

    photometry: str = "spc"
    beta: float = phot.FIXED_BETA
    alpha0_deg: float = phot.ALPHA0_DEG
    damping: float = 5e-3
    iterations: int = 8
    max_step: float = 0.5
    max_slope: float = 4.0
    min_azimuths: int = 3
    azimuth_separation_deg: float = 20.0
    albedo_min: float = 0.05
    albedo_max: float = 1.95

    def __post_init__(self):
        if self.photometry not in phot.MODELS:
            models = ", ".join(phot.MODELS)
            raise SpcUsageError(f"photometry must be one of {models}, got {self.photometry!r}")
        for name in ("beta", "alpha0_deg", "damping", "max_step", "max_slope", "azimuth_separation_deg",
                     "albedo_min", "albedo_max"):
            value = float(getattr(self, name))
            if not math.isfinite(value) or value < 0.0:
                raise SpcUsageError(f"photoclinometry option {name} must be a finite number >= 0, "
                                    f"got {value}")
            setattr(self, name, value)
        if int(self.iterations) < 1:
            raise SpcUsageError(f"photoclinometry iterations must be >= 1, got {self.iterations}")
        self.iterations = int(self.iterations)
        if int(self.min_azimuths) < 1:
            raise SpcUsageError(f"min_azimuths must be >= 1, got {self.min_azimuths}")
        self.min_azimuths = int(self.min_azimuths)
        if not self.albedo_min < self.albedo_max:
            raise SpcUsageError("albedo_min must be below albedo_max")

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class Pictures:
    """The observations of K pictures on one maplet's N×N grid.

    ``observed`` (K, N, N): extracted DN (0 = none); ``valid`` (K, N, N): usable observations;
    ``sun`` (K, 3) and ``emission`` (K, 3): maplet-frame unit vectors ŝ_k, ê_k; ``alpha_deg`` (K,):
    phase angles.
    """

    observed: np.ndarray
    valid: np.ndarray
    sun: np.ndarray
    emission: np.ndarray
    alpha_deg: np.ndarray

    def __post_init__(self):
        self.observed = np.asarray(self.observed, dtype=np.float64)
        self.valid = np.asarray(self.valid, dtype=bool) & np.isfinite(self.observed)
        k = self.observed.shape[0] if self.observed.ndim == 3 else -1
        shape = self.observed.shape
        if k < 0 or shape[1] != shape[2] or self.valid.shape != shape:
            raise SpcUsageError("observations must be (K, N, N) with a validity mask of the same shape")
        self.sun = _unit_rows(self.sun, k, "sun")
        self.emission = _unit_rows(self.emission, k, "emission")
        self.alpha_deg = np.asarray(self.alpha_deg, dtype=np.float64).reshape(k)

    def __len__(self):
        return self.observed.shape[0]


def _unit_rows(v, k: int, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(k, 3)
    n = np.linalg.norm(a, axis=1)
    if not np.all(np.isfinite(n) & (n > 0.0)):
        raise SpcUsageError(f"every {name} vector must be finite and non-zero")
    return a / n[:, None]


@dataclass
class CellSolution:
    """Result of :func:`solve_cells` (arrays (N, N)).

    ``t1``, ``t2``: slopes along UX / UY (the prior where not solved); ``albedo``: relative albedo
    (prior where not solved); ``solved``: cells solved; ``flagged``: valid maplet cells *not* solved
    (too few Sun azimuths, or a diverged solve); ``azimuths``: number of distinct Sun-azimuth groups
    seeing each cell; ``diverged``: cells whose solve was refused.
    """

    t1: np.ndarray
    t2: np.ndarray
    albedo: np.ndarray
    solved: np.ndarray
    flagged: np.ndarray
    azimuths: np.ndarray
    diverged: np.ndarray


# --------------------------------------------------------------------------------------------------
# model and Jacobian


def photometric_constants(alpha_deg, options: SolveOptions) -> tuple[np.ndarray, np.ndarray]:
    """(c₁, c₂) of R = c₁μ₀ + c₂μ₀/(μ₀ + μ) for each phase angle (module docstring)."""
    a = np.asarray(alpha_deg, dtype=np.float64)
    if options.photometry == "lambert":
        return np.ones_like(a), np.zeros_like(a)
    if options.photometry == "fixed":
        b = np.full_like(a, options.beta)
        return 1.0 - b, b
    w = phot.limb_weight(a, options.alpha0_deg)
    if options.photometry == "mcewen":
        return 1.0 - w, 2.0 * w
    return 1.0 - w, w


def _geometry(t1, t2, sun, emission):
    """|n|, μ₀ and μ for slopes (…) and per-picture directions (K, 3): arrays (K, …)."""
    t1 = np.asarray(t1, dtype=np.float64)
    t2 = np.asarray(t2, dtype=np.float64)
    norm = np.sqrt(1.0 + t1 * t1 + t2 * t2)
    shp = (-1,) + (1,) * t1.ndim
    s = [sun[:, i].reshape(shp) for i in range(3)]
    e = [emission[:, i].reshape(shp) for i in range(3)]
    mu0 = (s[2] - t1 * s[0] - t2 * s[1]) / norm
    mu = (e[2] - t1 * e[0] - t2 * e[1]) / norm
    return norm, mu0, mu, s, e


def brightness(t1, t2, albedo, pictures: Pictures, lam, options: SolveOptions | None = None):
    """Predicted brightness P (K, …) and the lit mask (K, …) of every picture on cells with slopes
    ``t1``, ``t2`` and albedo ``albedo`` (same shape), λ (K,)."""
    opts = options if options is not None else SolveOptions()
    c1, c2 = photometric_constants(pictures.alpha_deg, opts)
    norm, mu0, mu, _, _ = _geometry(t1, t2, pictures.sun, pictures.emission)
    shp = (-1,) + (1,) * np.ndim(t1)
    lit = (mu0 > 0.0) & (mu > 0.0)
    den = np.where(lit, mu0 + mu, 1.0)
    r = np.where(lit, c1.reshape(shp) * mu0 + c2.reshape(shp) * mu0 / den, 0.0)
    lam = np.asarray(lam, dtype=np.float64).reshape(shp)
    return lam * np.asarray(albedo, dtype=np.float64) * r, lit


def jacobian(t1, t2, albedo, pictures: Pictures, lam, options: SolveOptions | None = None):
    """(P, J, lit): the prediction (K, …), its analytic derivatives J (K, …, 3) with respect to
    (t₁, t₂, a), and the lit mask (module docstring; zero on dark cells)."""
    opts = options if options is not None else SolveOptions()
    c1, c2 = photometric_constants(pictures.alpha_deg, opts)
    t1 = np.asarray(t1, dtype=np.float64)
    t2 = np.asarray(t2, dtype=np.float64)
    norm, mu0, mu, s, e = _geometry(t1, t2, pictures.sun, pictures.emission)
    shp = (-1,) + (1,) * t1.ndim
    c1 = c1.reshape(shp)
    c2 = c2.reshape(shp)
    lam = np.asarray(lam, dtype=np.float64).reshape(shp)
    a = np.asarray(albedo, dtype=np.float64)
    lit = (mu0 > 0.0) & (mu > 0.0)
    den = np.where(lit, mu0 + mu, 1.0)
    r = np.where(lit, c1 * mu0 + c2 * mu0 / den, 0.0)
    r_mu0 = c1 + c2 * mu / (den * den)
    r_mu = -c2 * mu0 / (den * den)
    inv = 1.0 / norm
    dmu0_1 = (-s[0] - mu0 * t1 * inv) * inv
    dmu0_2 = (-s[1] - mu0 * t2 * inv) * inv
    dmu_1 = (-e[0] - mu * t1 * inv) * inv
    dmu_2 = (-e[1] - mu * t2 * inv) * inv
    la = lam * a
    jac = np.stack(
        [
            la * (r_mu0 * dmu0_1 + r_mu * dmu_1),
            la * (r_mu0 * dmu0_2 + r_mu * dmu_2),
            lam * r * np.ones_like(a),
        ],
        axis=-1,
    )
    jac = np.where(lit[..., None], jac, 0.0)
    return lam * a * r, jac, lit


# --------------------------------------------------------------------------------------------------
# solvability


def azimuth_groups(sun, separation_deg: float) -> np.ndarray:
    """Group index (K,) of each picture's Sun azimuth in the maplet plane: azimuths closer than
    ``separation_deg`` (around the circle, single linkage) share a group.  A Sun within 1e-9 of the
    maplet zenith has no azimuth and gets a group of its own."""
    s = np.asarray(sun, dtype=np.float64).reshape(-1, 3)
    k = s.shape[0]
    groups = np.full(k, -1, dtype=np.int64)
    horizontal = np.hypot(s[:, 0], s[:, 1])
    has_az = horizontal > 1e-9
    az = np.degrees(np.arctan2(s[:, 1], s[:, 0])) % 360.0
    idx = np.flatnonzero(has_az)
    g = 0
    if idx.size:
        order = idx[np.argsort(az[idx])]
        sorted_az = az[order]
        gaps = np.diff(np.concatenate([sorted_az, [sorted_az[0] + 360.0]]))
        # start after a gap wide enough (if none, everything is one group)
        breaks = np.flatnonzero(gaps >= separation_deg)
        if breaks.size == 0:
            groups[order] = 0
            g = 1
        else:
            start = (breaks[0] + 1) % order.size
            rolled = np.roll(order, -start)
            rolled_gaps = np.roll(gaps, -start)
            for i, p in enumerate(rolled):
                groups[p] = g
                if rolled_gaps[i] >= separation_deg:
                    g += 1
    for p in np.flatnonzero(~has_az):
        groups[p] = g
        g += 1
    return groups


def solvable_cells(valid, sun, options: SolveOptions | None = None) -> np.ndarray:
    """Number of distinct Sun-azimuth groups (:func:`azimuth_groups`) among the pictures valid on each
    cell: ``valid`` (K, N, N) → (N, N) ints.  A cell is solvable when this is ≥ ``min_azimuths``."""
    opts = options if options is not None else SolveOptions()
    v = np.asarray(valid, dtype=bool)
    groups = azimuth_groups(sun, opts.azimuth_separation_deg)
    count = np.zeros(v.shape[1:], dtype=np.int64)
    for g in np.unique(groups):  # a handful of groups, each a vectorised reduction over the grid
        count += np.any(v[groups == g], axis=0)
    return count


# --------------------------------------------------------------------------------------------------
# λ and the per-cell solve


def fit_lambda(t1, t2, albedo, pictures: Pictures, mask=None, options: SolveOptions | None = None):
    """λ_k = Σ O·p / Σ p², p = a·R, over the cells valid and lit in picture k (and in ``mask`` (N, N)
    when given); (K,) with NaN where a picture has no such cell."""
    p, lit = brightness(t1, t2, albedo, pictures, np.ones(len(pictures)), options)
    use = pictures.valid & lit & (p > 0.0)
    if mask is not None:
        use &= np.asarray(mask, dtype=bool)[None]
    num = np.sum(np.where(use, pictures.observed * p, 0.0), axis=(1, 2))
    den = np.sum(np.where(use, p * p, 0.0), axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0.0, num / den, np.nan)


def normalise_albedo(albedo, lam, solved):
    """(albedo / m, λ·m) with m the mean albedo over ``solved`` cells (1 when none): predictions are
    unchanged and the solved albedo has mean 1."""
    s = np.asarray(solved, dtype=bool)
    m = float(np.mean(albedo[s])) if np.any(s) else 1.0
    if not (math.isfinite(m) and m > 0.0):
        m = 1.0
    return np.asarray(albedo) / m, np.asarray(lam) * m


def residual_rms(t1, t2, albedo, pictures: Pictures, lam, mask=None, options: SolveOptions | None = None):
    """Per-picture rms of (O − P)/λ (reflectance units) over the cells valid and lit in that picture
    (and in ``mask``): (K,), NaN for a picture with no such cell."""
    p, lit = brightness(t1, t2, albedo, pictures, lam, options)
    use = pictures.valid & lit
    if mask is not None:
        use &= np.asarray(mask, dtype=bool)[None]
    lam = np.asarray(lam, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = (pictures.observed - p) / lam[:, None, None]
        ss = np.sum(np.where(use, r * r, 0.0), axis=(1, 2))
        n = np.count_nonzero(use, axis=(1, 2))
        return np.where(n > 0, np.sqrt(ss / np.maximum(n, 1)), np.nan)


def _solve3(a00, a01, a02, a11, a12, a22, b0, b1, b2) -> np.ndarray:
    """Solutions (M, 3) of M symmetric 3×3 systems by the adjugate (Cramer's rule), vectorised; NaN
    rows where a matrix is singular."""
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(det != 0.0, 1.0 / det, np.nan)
        return np.stack([
            (c00 * b0 + c01 * b1 + c02 * b2) * inv,
            (c01 * b0 + c11 * b1 + c12 * b2) * inv,
            (c02 * b0 + c12 * b1 + c22 * b2) * inv,
        ], axis=1)


def _gauss_newton_numpy(obs, ov, pictures: Pictures, lam, x, opts: SolveOptions) -> np.ndarray:
    """The per-cell Gauss–Newton iterations with numpy arrays over every cell at once — the reference
    :func:`_k_gauss_newton` is tested against (same steps; the kernel stops each cell on its own once
    its step is below 1e-9, this one when every cell's is).  ``x`` (M, 3) is updated and returned."""
    good_pic = np.isfinite(lam) & (lam > 0.0)
    safe_lam = np.where(good_pic, lam, 1.0)
    w = np.where(good_pic, 1.0 / (safe_lam * safe_lam), 0.0)[:, None]  # (K, 1)
    for _ in range(opts.iterations):
        p, jac, lit = jacobian(x[:, 0], x[:, 1], x[:, 2], pictures, safe_lam, opts)  # (K, M), (K, M, 3)
        wk = np.where(ov & lit, w, 0.0)
        wr = wk * (obs - p)
        j0, j1, j2 = jac[..., 0], jac[..., 1], jac[..., 2]
        wj0, wj1, wj2 = wk * j0, wk * j1, wk * j2
        # the 3x3 normal equations of every cell (symmetric: six sums over the pictures)
        a00, a01, a02 = (wj0 * j0).sum(0), (wj0 * j1).sum(0), (wj0 * j2).sum(0)
        a11, a12, a22 = (wj1 * j1).sum(0), (wj1 * j2).sum(0), (wj2 * j2).sum(0)
        b0, b1, b2 = (j0 * wr).sum(0), (j1 * wr).sum(0), (j2 * wr).sum(0)
        scale = np.maximum(np.maximum(a00, a11), a22)
        floor = 1e-6 * scale
        a00 = a00 + opts.damping * (a00 + floor)
        a11 = a11 + opts.damping * (a11 + floor)
        a22 = a22 + opts.damping * (a22 + floor)
        step = _solve3(a00, a01, a02, a11, a12, a22, b0, b1, b2)
        step[~(np.isfinite(step).all(axis=1) & (scale > 0.0))] = 0.0
        slope_step = np.hypot(step[:, 0], step[:, 1])
        shrink = np.where(slope_step > opts.max_step, opts.max_step / np.maximum(slope_step, 1e-300), 1.0)
        step *= shrink[:, None]
        x = x + step
        x[:, 2] = np.clip(x[:, 2], opts.albedo_min, opts.albedo_max)
        if not np.any(np.abs(step) > 1e-9):  # every cell converged
            break
    return x


@numba.njit(cache=True, nogil=True)
def _k_gauss_newton(obs, ov, sun, em, c1, c2, lam, w, x, damping, max_step, amin, amax, iterations):
    """The per-cell Gauss–Newton solve (module docstring) compiled, one cell at a time: the normal
    equations of a cell summed over its K pictures, damped, solved by the adjugate, the slope step
    capped, the albedo clipped; a cell stops when no component of its step exceeds 1e-9.  ``obs``,
    ``ov`` (K, M); ``sun``, ``em`` (K, 3); ``c1``, ``c2``, ``lam``, ``w`` (K,); ``x`` (M, 3) in place."""
    k_n = obs.shape[0]
    for m in range(x.shape[0]):
        t1 = x[m, 0]
        t2 = x[m, 1]
        a = x[m, 2]
        for _ in range(iterations):
            norm = math.sqrt(1.0 + t1 * t1 + t2 * t2)
            inv = 1.0 / norm
            a00 = a01 = a02 = a11 = a12 = a22 = 0.0
            b0 = b1 = b2 = 0.0
            for k in range(k_n):
                if not ov[k, m]:
                    continue
                mu0 = (sun[k, 2] - t1 * sun[k, 0] - t2 * sun[k, 1]) * inv
                mu = (em[k, 2] - t1 * em[k, 0] - t2 * em[k, 1]) * inv
                if not (mu0 > 0.0 and mu > 0.0):
                    continue
                den = mu0 + mu
                r = c1[k] * mu0 + c2[k] * mu0 / den
                r_mu0 = c1[k] + c2[k] * mu / (den * den)
                r_mu = -c2[k] * mu0 / (den * den)
                dmu0_1 = (-sun[k, 0] - mu0 * t1 * inv) * inv
                dmu0_2 = (-sun[k, 1] - mu0 * t2 * inv) * inv
                dmu_1 = (-em[k, 0] - mu * t1 * inv) * inv
                dmu_2 = (-em[k, 1] - mu * t2 * inv) * inv
                la = lam[k] * a
                j0 = la * (r_mu0 * dmu0_1 + r_mu * dmu_1)
                j1 = la * (r_mu0 * dmu0_2 + r_mu * dmu_2)
                j2 = lam[k] * r
                wk = w[k]
                wr = wk * (obs[k, m] - la * r)
                a00 += wk * j0 * j0
                a01 += wk * j0 * j1
                a02 += wk * j0 * j2
                a11 += wk * j1 * j1
                a12 += wk * j1 * j2
                a22 += wk * j2 * j2
                b0 += j0 * wr
                b1 += j1 * wr
                b2 += j2 * wr
            scale = max(a00, a11, a22)
            floor = 1e-6 * scale
            a00 += damping * (a00 + floor)
            a11 += damping * (a11 + floor)
            a22 += damping * (a22 + floor)
            c00 = a11 * a22 - a12 * a12
            c01 = a02 * a12 - a01 * a22
            c02 = a01 * a12 - a02 * a11
            c11 = a00 * a22 - a02 * a02
            c12 = a01 * a02 - a00 * a12
            c22 = a00 * a11 - a01 * a01
            det = a00 * c00 + a01 * c01 + a02 * c02
            s0 = s1 = s2 = 0.0
            if det != 0.0 and scale > 0.0:
                s0 = (c00 * b0 + c01 * b1 + c02 * b2) / det
                s1 = (c01 * b0 + c11 * b1 + c12 * b2) / det
                s2 = (c02 * b0 + c12 * b1 + c22 * b2) / det
                if not (math.isfinite(s0) and math.isfinite(s1) and math.isfinite(s2)):
                    s0 = s1 = s2 = 0.0
            slope_step = math.sqrt(s0 * s0 + s1 * s1)
            if slope_step > max_step:
                f = max_step / slope_step
                s0 *= f
                s1 *= f
                s2 *= f
            t1 += s0
            t2 += s1
            a = min(max(a + s2, amin), amax)
            if abs(s0) <= 1e-9 and abs(s1) <= 1e-9 and abs(s2) <= 1e-9:
                break
        x[m, 0] = t1
        x[m, 1] = t2
        x[m, 2] = a


def solve_cells(t1, t2, albedo, pictures: Pictures, lam, cell_mask=None,
                options: SolveOptions | None = None) -> CellSolution:
    """The per-cell Gauss–Newton solve of (t₁, t₂, a) from the pictures with scales ``lam`` (K,),
    starting from (and keeping, where not solvable) the prior ``t1``, ``t2``, ``albedo`` (N, N).

    ``cell_mask`` (N, N): the maplet's valid cells (default all).  Vectorised over every cell: the
    3×3 normal equations of all cells are formed and solved as one stack each iteration.
    """
    opts = options if options is not None else SolveOptions()
    t1p = np.asarray(t1, dtype=np.float64)
    t2p = np.asarray(t2, dtype=np.float64)
    ap = np.asarray(albedo, dtype=np.float64)
    shape = t1p.shape
    lam = np.asarray(lam, dtype=np.float64).reshape(len(pictures))
    good_pic = np.isfinite(lam) & (lam > 0.0)
    cells = np.ones(shape, dtype=bool) if cell_mask is None else np.asarray(cell_mask, dtype=bool)
    obs_valid = pictures.valid & good_pic[:, None, None] & cells[None]
    n_az = solvable_cells(obs_valid, pictures.sun, opts)
    candidate = cells & (n_az >= opts.min_azimuths)

    idx = np.flatnonzero(candidate.reshape(-1))
    x = np.stack([t1p.reshape(-1)[idx], t2p.reshape(-1)[idx], ap.reshape(-1)[idx]], axis=1)  # (M, 3)
    x[:, 2] = np.clip(np.where(np.isfinite(x[:, 2]) & (x[:, 2] > 0.0), x[:, 2], 1.0),
                      opts.albedo_min, opts.albedo_max)
    obs = pictures.observed.reshape(len(pictures), -1)[:, idx]  # (K, M)
    ov = obs_valid.reshape(len(pictures), -1)[:, idx]
    safe_lam = np.where(good_pic, lam, 1.0)
    w = np.where(good_pic, 1.0 / (safe_lam * safe_lam), 0.0)
    c1, c2 = photometric_constants(pictures.alpha_deg, opts)
    _k_gauss_newton(obs, ov, pictures.sun, pictures.emission, c1, c2, safe_lam, w, x,
                    float(opts.damping), float(opts.max_step), float(opts.albedo_min), float(opts.albedo_max),
                    int(opts.iterations))

    finite = np.all(np.isfinite(x), axis=1)
    steep = np.hypot(x[:, 0], x[:, 1]) > opts.max_slope
    bad = ~finite | steep
    out_t1 = t1p.copy().reshape(-1)
    out_t2 = t2p.copy().reshape(-1)
    out_a = ap.copy().reshape(-1)
    keep = idx[~bad]
    out_t1[keep] = x[~bad, 0]
    out_t2[keep] = x[~bad, 1]
    out_a[keep] = x[~bad, 2]
    solved = np.zeros(shape[0] * shape[1], dtype=bool)
    solved[keep] = True
    diverged = np.zeros_like(solved)
    diverged[idx[bad]] = True
    solved = solved.reshape(shape)
    return CellSolution(
        t1=out_t1.reshape(shape),
        t2=out_t2.reshape(shape),
        albedo=out_a.reshape(shape),
        solved=solved,
        flagged=cells & ~solved,
        azimuths=n_az,
        diverged=diverged.reshape(shape),
    )


# --------------------------------------------------------------------------------------------------
# one pass: λ, cells, integration


@dataclass
class PassResult:
    """Result of :func:`heights_pass` (arrays (N, N)): the new ``heights`` and ``albedo``, the scales
    ``lam`` (K,) after the albedo normalisation, the :class:`CellSolution` ``cells``, and the rms
    height change over the valid cells ``change_rms`` (cells)."""

    heights: np.ndarray
    albedo: np.ndarray
    lam: np.ndarray
    cells: CellSolution
    change_rms: float


def heights_pass(heights, albedo, valid, pictures: Pictures, start_heights, conditioning,
                 weight: float = 0.025, keep_plane: bool = True, lam=None,
                 options: SolveOptions | None = None, cache: dict | None = None) -> PassResult:
    """One pass of "Find heights" on fixed observations: HGT2SLP slopes of ``heights``
    (:func:`spctool.geometry.heightfield.slopes`), λ (:func:`fit_lambda`, unless ``lam`` is given),
    the per-cell solve, the albedo normalised to mean 1, the slopes integrated
    (:func:`spctool.stages.slope_integration.integrate_slopes`) with the ``conditioning`` cells pulled
    toward ``start_heights`` with ``weight`` and the unsolvable cells fixed there, and (``keep_plane``)
    the starting map's best-fit plane restored.  ``cache``: the integration's factorization kept across
    passes (:func:`~spctool.stages.slope_integration.integrate_slopes`)."""
    from spctool.geometry import heightfield
    from spctool.stages import slope_integration as si

    valid = np.asarray(valid, dtype=bool)
    h = np.asarray(heights, dtype=np.float64)
    h0 = np.asarray(start_heights, dtype=np.float64)
    a = np.asarray(albedo, dtype=np.float64)
    t1, t2, _ = heightfield.slopes(h, valid)
    if lam is None:
        lam = fit_lambda(t1, t2, a, pictures, valid, options)
    cells = solve_cells(t1, t2, a, pictures, lam, valid, options)
    new_albedo, lam = normalise_albedo(cells.albedo, lam, cells.solved)
    new_albedo = np.where(cells.flagged, a, new_albedo)
    new_h = si.integrate_slopes(cells.t1, cells.t2, valid, conditioning, h0, weight, fixed=cells.flagged,
                                cache=cache)
    if keep_plane:
        new_h = np.where(cells.flagged, h0, si.keep_plane(new_h, h0, valid))
    new_h = np.where(valid, new_h, 0.0)
    change = float(np.sqrt(np.mean((new_h - h)[valid] ** 2))) if np.any(valid) else 0.0
    return PassResult(new_h, new_albedo, np.asarray(lam, dtype=np.float64), cells, change)
