"""Stage B — ``predict``: the appearance of a maplet under a picture's illumination and viewpoint.

Implements L15 §3.3.1 ("Image prediction", Eq. 3.36–3.45) and S16 "Predicted Maplet Rendering"
(Eq. 12–17) as corrected and specified in ``spc-algorithms.md`` §3 (Stage B), §11 (errata 17, 18,
25) and §13 (defaults).  Pure function, no I/O.

What :func:`predict` does, for one maplet and one picture:

1. **Slopes and normals** from the heights by SPC's HGT2SLP fallback hierarchy
   (:func:`spctool.geometry.heightfield.slopes`, spc-algorithms.md §3.1); the maplet-frame unit
   normal is n̂ = (−h_x, −h_y, 1)/√(1 + h_x² + h_y²) (L15 Eq. 3.37).  A cell is **valid** when
   its albedo/height is present *and* its slopes are usable; invalid cells are not "dark", they
   are absent (value 0, ``valid`` False).
2. **One emission vector ê for the whole maplet** (landmark V → spacecraft, S16: "ê … takes on the
   value from the maplet origin") and one Sun vector ŝ (body→Sun, SUM ``SZ``; collimated light).
   μ₀ = n̂·ŝ, μ = n̂·ê per cell, α = ∠(ŝ, ê) in degrees (L15 Eq. 3.38–3.40, S16 Eq. 12–14).
3. **Reflectance** R(μ₀, μ, α) by :func:`spctool.photometry.reflectance` — default ``"spc"``,
   SPC's lunar-Lambert *without* McEwen's factor 2, β = exp(−α/60°) (erratum 17; S16 Eq. 16–17);
   ``"mcewen"`` has the 2, ``"fixed"`` uses β = 0.65 (L15), ``"lambert"`` is μ₀.  R = 0 where
   μ₀ ≤ 0, μ ≤ 0 or μ₀ + μ ≤ 1e-12.
4. **Shadows.**  ``shadows="spc"`` (default): a cell is dark only if its incidence exceeds 90°
   (S16: "dark only if incidence > 90°"; SPC has no cast shadows in the prediction).
   ``shadows="cast"``: additionally zero the cells whose line toward the Sun is blocked by the
   height field (the one-cell horizon march of spc-algorithms.md §5.3,
   :func:`spctool.geometry.heightfield.cast_shadows`, lowered by ``shadow_tol`` cells) — the
   ray-traced shadows of S16's Retina improvement, limited to the maplet's own terrain.
   ``shadows="auto"`` (default): ``"spc"``, unless the extracted image shows that the picture's
   shadow threshold does not mark the maplet's cast shadows (:func:`resolve_shadows`: they cover at
   least 1 % of the valid cells, and 75 % of those are above THRSH T1 in the extraction), then
   ``"cast"``.  SPC's only shadow test is "darker than T1"; a picture whose shadows lie above T1 (a
   dark offset, scattered light, or a T1 of 1 DN written by another tool) otherwise correlates its
   shadows against a lit prediction, a bias along the Sun direction (independent world, Sun 55°
   from the zenith: 0.042 px rms, max 0.10 px in maplet space; 0.007 / 0.011 px with them predicted).
   Without an extracted image ``auto`` is ``spc``.
5. **Brightness scale λ and background φ** (L15 Eq. 3.42–3.45, spc-algorithms.md §3.3) from the
   extracted image when one is given: over the cells valid and non-zero in *both* images (the
   correlator's pixel rule, S16 "both greater than a near-zero threshold"), compute the zero-offset
   Pearson correlation ρ (with the square root, erratum 25).  If ρ > ``bg_corr_min`` fit e ≈ λ·p + φ
   by least squares (erratum 18: φ = (μ_e·μ_p2 − μ_p·μ_pe)/(μ_p2 − μ_p²), λ = (μ_e − φ)/μ_p);
   otherwise λ = μ_e/μ_p and φ = 0 (L15 Eq. 3.42).  The default ``bg_corr_min = 1`` disables φ,
   as SPC runs in practice (φ = 0.000 in every auto-align printout); any value ≥ 1 disables it
   (ρ is clipped to [−1, 1], L15 footnote 31).  Here p = a·R (albedo times reflectance, λ = 1).
6. **Image** I = λ·a·R + φ on valid *lit* cells (R > 0), 0 elsewhere (L15 Eq. 3.45, S16 Eq. 15).
   Dark cells stay 0 even when φ ≠ 0 so that the correlator's non-zero rule keeps excluding them
   (L15 §3.5: "only pixels non-zero in both images count").

:func:`pearson` and :func:`fit_brightness` are shared with the ``correlate`` stage.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import NamedTuple

import numpy as np

from spctool import photometry as phot
from spctool.errors import SpcUsageError
from spctool.geometry import heightfield
from spctool.geometry.frames import unit_vector

__all__ = [
    "BrightnessFit",
    "PHOTOMETRY_MODELS",
    "Prediction",
    "PredictOptions",
    "SHADOW_MODES",
    "cast_shadow_note",
    "fit_brightness",
    "pearson",
    "predict",
    "resolve_shadows",
]

PHOTOMETRY_MODELS = phot.MODELS  # ("spc", "mcewen", "fixed", "lambert")
SHADOW_MODES = ("spc", "cast", "auto")


@dataclass
class PredictOptions:
    """Every constant of Stage B (spc-algorithms.md §3, §13).

    ``photometry``: ``"spc"`` (default), ``"mcewen"``, ``"fixed"`` (constant ``beta``, L15's 0.65) or
    ``"lambert"``; ``alpha0_deg``: α₀ of β = exp(−α/α₀) (60°, S16 Eq. 17).
    ``shadows``: ``"spc"`` (dark only where μ₀ ≤ 0), ``"cast"`` (plus the horizon march toward the
    Sun, lowered by ``shadow_tol`` cells) or ``"auto"`` (``cast`` when the extracted image shows the
    picture's T1 does not mark those shadows, else ``spc``: module docstring item 4).
    ``bg_corr_min``: zero-offset correlation above which the background φ is fitted (1.0 = never,
    L15 footnote 31).
    """

    photometry: str = "spc"
    beta: float = phot.FIXED_BETA
    alpha0_deg: float = phot.ALPHA0_DEG
    shadows: str = "auto"
    shadow_tol: float = heightfield.VIS_TOL
    bg_corr_min: float = 1.0

    def __post_init__(self):
        if self.photometry not in PHOTOMETRY_MODELS:
            raise SpcUsageError(
                f"photometry must be one of {', '.join(PHOTOMETRY_MODELS)}, got {self.photometry!r}"
            )
        if self.shadows not in SHADOW_MODES:
            raise SpcUsageError(f"shadows must be one of {', '.join(SHADOW_MODES)}, got {self.shadows!r}")
        for name in ("beta", "alpha0_deg", "shadow_tol", "bg_corr_min"):
            value = float(getattr(self, name))
            if math.isnan(value):
                raise SpcUsageError(f"prediction option {name} must be a number, got NaN")
            setattr(self, name, value)
        if not 0.0 <= self.beta <= 1.0:
            raise SpcUsageError(f"beta must be in [0, 1], got {self.beta}")
        if not self.alpha0_deg > 0.0:
            raise SpcUsageError(f"alpha0_deg must be > 0, got {self.alpha0_deg}")

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class BrightnessFit(NamedTuple):
    """λ, φ, the zero-offset correlation ρ and the number of cells used (:func:`fit_brightness`)."""

    lam: float
    phi: float
    correlation: float
    n: int
    background_fitted: bool


@dataclass
class Prediction:
    """Result of :func:`predict`.  Arrays are (N, N), N = 2q + 1, axis 0 along UX, axis 1 along UY.

    ``image``: I = λ·a·R + φ on lit valid cells, 0 elsewhere.  ``valid``: present and usable cells.
    ``lit``: valid cells with R > 0.  ``reflectance``: R (no albedo, 0 on invalid cells);
    ``mu0``/``mu``: cosines of incidence/emission of every cell (computed also on invalid cells);
    ``alpha_deg``: phase angle (one value).  ``lam``, ``phi``: brightness scale and background;
    ``correlation``: zero-offset Pearson ρ between a·R and the extracted image over ``fit_mask``
    (NaN without an extracted image or with fewer than 2 usable cells); ``n_fit`` = cells in the
    fit.  ``shadowed``: cells in cast shadow (all False when the shadows used are ``"spc"``;
    ``options.shadows`` says which were used: ``auto`` is resolved).  ``emission_vector``
    and ``sun_vector``: the body-frame unit vectors ê (V → spacecraft) and ŝ.
    """

    image: np.ndarray
    valid: np.ndarray
    lit: np.ndarray
    reflectance: np.ndarray
    mu0: np.ndarray
    mu: np.ndarray
    alpha_deg: float
    lam: float
    phi: float
    correlation: float
    n_fit: int
    background_fitted: bool
    fit_mask: np.ndarray
    shadowed: np.ndarray
    emission_vector: np.ndarray
    sun_vector: np.ndarray
    options: PredictOptions

    @property
    def lit_fraction(self) -> float:
        """Fraction of the N² cells predicted lit (L15 Eq. 3.55 read literally)."""
        return float(np.count_nonzero(self.lit)) / self.lit.size


# --------------------------------------------------------------------------------------------------
# small helpers shared with extract (unit_vector and surface_cosines live in geometry)


def pearson(a, b, mask=None) -> float:
    """Pearson correlation of ``a`` and ``b`` over ``mask`` (all cells when None), with the square root
    in the denominator (L15 Eq. 3.62 / S16 Eq. 18; errata 25, 27, 30).

    C = Σ(a−ā)(b−b̄)/√(Σ(a−ā)²·Σ(b−b̄)²), computed from centred values (two passes) for accuracy,
    clipped to [−1, 1].  Returns NaN when fewer than 2 cells are selected or either variance is 0
    (GIANT's ``sfn_correlator`` returns 0 in those cases; NaN lets callers tell "no data" apart).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"pearson: shapes differ: {a.shape} vs {b.shape}")
    if mask is None:
        av = a.reshape(-1)
        bv = b.reshape(-1)
    else:
        m = np.asarray(mask, dtype=bool)
        if m.shape != a.shape:
            raise ValueError(f"pearson: mask shape {m.shape} differs from {a.shape}")
        av = a[m]
        bv = b[m]
    if av.size < 2:
        return math.nan
    da = av - av.mean()
    db = bv - bv.mean()
    saa = float(da @ da)
    sbb = float(db @ db)
    if not (saa > 0.0 and sbb > 0.0):
        return math.nan
    return float(min(1.0, max(-1.0, float(da @ db) / math.sqrt(saa * sbb))))


def fit_brightness(pred, extr, mask, bg_corr_min: float = 1.0) -> BrightnessFit:
    """Brightness scale λ and background φ of ``extr ≈ λ·pred + φ`` over ``mask`` (spc-algorithms.md §3.3).

    ρ = :func:`pearson` (pred, extr, mask).  If ρ > ``bg_corr_min`` (never when ``bg_corr_min`` ≥ 1),
    the least-squares line (erratum 18):
    φ = (μ_e·μ_p2 − μ_p·μ_pe)/(μ_p2 − μ_p²) and λ = (μ_e − φ)/μ_p — evaluated in the algebraically
    identical centred form λ = Σ(p−μ_p)(e−μ_e)/Σ(p−μ_p)², φ = μ_e − λ·μ_p, which avoids the
    cancellation in μ_p2 − μ_p².  Otherwise λ = μ_e/μ_p, φ = 0 (L15 Eq. 3.42).  With no cell in the
    mask (or μ_p = 0) λ = 1, φ = 0 and ``n`` = 0 tells the caller.
    """
    p = np.asarray(pred, dtype=np.float64)
    e = np.asarray(extr, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if p.shape != e.shape or m.shape != p.shape:
        raise ValueError(f"fit_brightness: shapes differ: {p.shape}, {e.shape}, {m.shape}")
    pv = p[m]
    ev = e[m]
    n = int(pv.size)
    rho = pearson(pv, ev)
    if n == 0:
        return BrightnessFit(1.0, 0.0, rho, 0, False)
    mu_p = float(pv.mean())
    mu_e = float(ev.mean())
    if float(bg_corr_min) < 1.0 and rho > float(bg_corr_min):
        dp = pv - mu_p
        lam = float((dp @ (ev - mu_e)) / (dp @ dp))
        phi = mu_e - lam * mu_p
        return BrightnessFit(lam, phi, rho, n, True)
    if mu_p == 0.0:
        return BrightnessFit(1.0, 0.0, rho, 0, False)
    return BrightnessFit(mu_e / mu_p, 0.0, rho, n, False)


# --------------------------------------------------------------------------------------------------
# the stage


#: ``shadows="auto"``: the maplet's cast shadows must cover at least this fraction of its valid cells
#: (and AUTO_SHADOW_MIN_CELLS cells) for the extracted image to say anything about them …
AUTO_SHADOW_MIN_FRACTION = 0.01
AUTO_SHADOW_MIN_CELLS = 20
#: … and predicting them is chosen when at least this fraction of them is above T1 in the extraction
AUTO_SHADOW_LIT_FRACTION = 0.75


def resolve_shadows(shadowed, extracted_image, valid) -> str:
    """``shadows="auto"`` for one maplet and picture: ``"cast"`` when the picture's shadow threshold
    does not mark the maplet's cast shadows, else ``"spc"``.

    ``shadowed``: the maplet's cast-shadow cells (:func:`spctool.geometry.heightfield.cast_shadows`);
    ``extracted_image``: the extraction, whose cells at or below THRSH T1 (and those of the shadow
    enhancement) are 0; ``valid``: the maplet's valid cells.  ``"cast"`` when the shadow cells are at
    least :data:`AUTO_SHADOW_MIN_FRACTION` of the valid cells and :data:`AUTO_SHADOW_MIN_CELLS`, and
    at least :data:`AUTO_SHADOW_LIT_FRACTION` of them are non-zero in the extraction: the photo shows
    them above T1, where SPC's prediction would call them lit.  Fewer shadow cells cannot bias the
    correlation much either way, and shadows the extraction zeroed are SPC's own case.
    """
    shadowed = np.asarray(shadowed, dtype=bool)
    n_shadow = int(np.count_nonzero(shadowed))
    n_valid = int(np.count_nonzero(valid))
    if n_shadow < max(AUTO_SHADOW_MIN_CELLS, AUTO_SHADOW_MIN_FRACTION * n_valid):
        return "spc"
    above = int(np.count_nonzero(np.asarray(extracted_image)[shadowed] > 0.0))
    return "cast" if above >= AUTO_SHADOW_LIT_FRACTION * n_shadow else "spc"


def cast_shadow_note(names, t1: float) -> str:
    """The one line that says which landmarks ``shadows="auto"`` predicted with their cast shadows."""
    listed = ", ".join(names[:4]) + (", ..." if len(names) > 4 else "")
    return (
        f"{len(names)} landmark(s) predicted with their cast shadows ({listed}): their shadows are "
        f"brighter in the photo than the picture's shadow threshold (THRSH T1 = {t1:g} DN in its SUM "
        "file), so SPC's rule would have predicted them lit; to use SPC's rule, set T1 to the photo's "
        "shadow level or pass --shadows spc"
    )


def predict(
    maplet,
    spacecraft_position,
    sun,
    options: PredictOptions | None = None,
    extracted=None,
    extracted_valid=None,
    *,
    slopes: heightfield.Slopes | None = None,
    cast_shadows: np.ndarray | None = None,
) -> Prediction:
    """Stage B: illuminate ``maplet`` for a spacecraft at ``spacecraft_position`` (body frame, km,
    = −SCOBJ) and the body→Sun direction ``sun`` (3,), then fit λ and φ to ``extracted``.

    ``maplet``: any object with ``heights`` (in SCALE units), ``albedo``, ``valid``, ``v``, ``ux``,
    ``uy``, ``uz`` (:class:`spctool.formats.maplet.Maplet`).  ``extracted``: the extracted image
    (N, N) or an :class:`spctool.stages.extract.Extraction` (its ``image`` and ``valid`` are used);
    ``extracted_valid`` defaults to ``extracted > 0``.  Without ``extracted``: λ = 1, φ = 0,
    correlation NaN.  ``slopes``: precomputed :func:`heightfield.slopes` of the maplet (optional, to
    share the work with :func:`spctool.stages.extract.extract`).  ``cast_shadows``: precomputed
    :func:`heightfield.cast_shadows` of the maplet for this Sun (optional; it depends on the Sun only,
    so a caller predicting for several cameras computes it once).  See the module docstring.
    """
    opts = options if options is not None else PredictOptions()
    heights = np.asarray(maplet.heights, dtype=np.float64)
    mvalid = np.asarray(maplet.valid, dtype=bool)
    albedo = np.asarray(maplet.albedo, dtype=np.float64)
    n = heights.shape[0]
    if heights.shape != (n, n) or mvalid.shape != heights.shape or albedo.shape != heights.shape:
        raise SpcUsageError("maplet heights, albedo and valid must be square arrays of one shape")
    ux, uy, uz = (np.asarray(u, dtype=np.float64) for u in (maplet.ux, maplet.uy, maplet.uz))
    v = np.asarray(maplet.v, dtype=np.float64)

    position = np.asarray(spacecraft_position, dtype=np.float64)
    e_hat = unit_vector(position - v, "landmark-to-spacecraft vector")
    s_hat = unit_vector(sun, "sun")
    sl = slopes if slopes is not None else heightfield.slopes(heights, mvalid)
    hx, hy, usable = sl
    e_m = heightfield.to_maplet_components(e_hat, ux, uy, uz)
    s_m = heightfield.to_maplet_components(s_hat, ux, uy, uz)
    inv_norm = 1.0 / np.sqrt(1.0 + hx * hx + hy * hy)
    mu0 = heightfield.surface_cosines(hx, hy, s_m, inv_norm)
    mu = heightfield.surface_cosines(hx, hy, e_m, inv_norm)
    alpha = float(phot.phase_angle_deg(s_hat, e_hat))

    valid = mvalid & usable
    r = phot.reflectance(mu0, mu, alpha, opts.photometry, beta=opts.beta, alpha0_deg=opts.alpha0_deg)
    mode = opts.shadows
    if mode == "auto" and extracted is None:
        mode = "spc"
    if mode != "spc":
        if cast_shadows is None:
            cast_shadows = heightfield.cast_shadows(heights, mvalid, ux, uy, uz, s_hat, tol=opts.shadow_tol)
        shadowed = np.asarray(cast_shadows, dtype=bool) & valid
        if mode == "auto":
            ext_image = np.asarray(extracted.image if hasattr(extracted, "image") else extracted, float)
            # (a wrong shape is refused below, with the fit)
            mode = resolve_shadows(shadowed, ext_image, valid) if ext_image.shape == heights.shape else "spc"
    if mode == "cast":
        r = np.where(shadowed, 0.0, r)
    else:
        shadowed = np.zeros(heights.shape, dtype=bool)
    if mode != opts.shadows:
        opts = replace(opts, shadows=mode)
    r = np.where(valid, r, 0.0)
    lit = valid & (r > 0.0)
    raw = np.where(lit, albedo * r, 0.0)

    if extracted is not None:
        if hasattr(extracted, "image"):
            if extracted_valid is None:
                extracted_valid = getattr(extracted, "valid", None)
            extracted = extracted.image
        ext = np.asarray(extracted, dtype=np.float64)
        if ext.shape != heights.shape:
            raise SpcUsageError(f"extracted image shape {ext.shape} differs from the maplet's "
                                f"{heights.shape}")
        ev = ext > 0.0 if extracted_valid is None else np.asarray(extracted_valid, dtype=bool) & (ext > 0.0)
        fit_mask = lit & ev & (raw > 0.0)
        fit = fit_brightness(raw, ext, fit_mask, opts.bg_corr_min)
    else:
        fit_mask = np.zeros(heights.shape, dtype=bool)
        fit = BrightnessFit(1.0, 0.0, math.nan, 0, False)

    image = np.where(lit, fit.lam * raw + fit.phi, 0.0)
    return Prediction(
        image=image,
        valid=valid,
        lit=lit,
        reflectance=r,
        mu0=mu0,
        mu=mu,
        alpha_deg=alpha,
        lam=float(fit.lam),
        phi=float(fit.phi),
        correlation=float(fit.correlation),
        n_fit=int(fit.n),
        background_fitted=bool(fit.background_fitted),
        fit_mask=fit_mask,
        shadowed=shadowed,
        emission_vector=e_hat,
        sun_vector=s_hat,
        options=opts,
    )
