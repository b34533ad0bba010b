"""The converged stage's sub-cell offset: two images aligned by linearised least squares.

Specification: spc-algorithms.md §8 (Stage G, the sub-pixel peak) and its ``peak="gradient"`` note;
L15 §3.5.1 reads the offset from a parabola through the correlation surface, S16 "Correlation and Peak
Finding" from a fitted surface: any vertex of a sampled surface is biased where the surface is
asymmetric about its maximum, which shading and masks make it.  Here the two binned images are
aligned at the grid peak instead (the Lucas–Kanade linearisation of the brightness difference), which
is exactly zero where they agree.  Three forms, by which image supplies the regressors:

* :func:`gradient_offset` — the photo E fitted on the prediction P and its gradient,
  E ≈ a·P + b − a·δ·∇P (``register``'s converged stage);
* :func:`gradient_offset_photo` — P fitted on E and its gradient, P ≈ α·E + β + α·δ·∇E (predictions
  noisier than the photo: maplets with per-node height errors, the S16 Monte Carlo);
* :func:`gradient_offset_symmetric` — the difference regressed on a mix of both gradients, w = ½ or
  w from each image's estimated noise (measured, not adopted: docs/benchmarks.md).

The normal equations are summed by the compiled :func:`_k_alignment` (unsigned indices, bitwise
validity tests: :func:`_k_usable`); :func:`spctool.stages.correlate.correlate_valid` calls these at
the grid peak (``CorrelateOptions.peak``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["gradient_offset", "gradient_offset_photo", "gradient_offset_symmetric"]


def _contiguous(e, me, p, mp):
    """The two images as C-contiguous float64 and their masks as bool (the kernels' one signature)."""
    f, b = np.float64, np.bool_
    return (np.ascontiguousarray(e, dtype=f), np.ascontiguousarray(me, dtype=b),
            np.ascontiguousarray(p, dtype=f), np.ascontiguousarray(mp, dtype=b))  # fmt: skip


@numba.njit(cache=True, inline="always")
def _k_usable(me, mp, i, j, ie, je):  # pragma: no cover - compiled
    """P pixel (i, j) valid with its four axis neighbours, and E pixel (ie, je) valid (every index is
    inside both images: the caller's ranges).  Bitwise ``&``: a chain of ``and`` over array elements
    compiled to a branch per element, which made the alignment's first pass ~6× slower.  Unsigned
    indices (np.uint64): numba adds a negative-index wrap-around test to every signed index it cannot
    prove non-negative, which halved the speed of this pass."""
    one = np.uint64(1)
    return mp[i, j] & me[ie, je] & mp[i - one, j] & mp[i + one, j] & mp[i, j - one] & mp[i, j + one]


@numba.njit(cache=True, nogil=True)
def _k_alignment(e, me, p, mp, o0, o1, i0, i1, j0, j1, normal, rhs):  # pragma: no cover - compiled
    """:func:`gradient_offset`'s least squares in two passes, over P rows i0 ≤ i < i1, columns
    j0 ≤ j < j1 (E at + (o0, o1)), over the pixels valid in both whose four axis neighbours are valid
    in P: the first finds those pixels, keeps their regressors (P, g_r, g_c) and E in scan order and
    sums them for the means; the second forms the normal matrix of the centred regressors and its
    right-hand side with the centred E from the kept values (the same sums in the same order as
    recomputing them from the images, without a second pass over the masks).  Returns the count.
    The caller's ranges keep every index ≥ 0, so they are unsigned (see :func:`_k_usable`)."""
    u = np.uint64
    one = u(1)
    kept = np.empty((max(0, (i1 - i0) * (j1 - j0)), 4))
    n = 0
    sp = se = sr = sc = 0.0
    for i_ in range(i0, i1):
        i = u(i_)
        ie = u(i_ + o0)
        for t in range(u(max(0, j1 - j0))):
            j = u(j0) + t
            je = u(j0 + o1) + t
            if not _k_usable(me, mp, i, j, ie, je):
                continue
            x0 = p[i, j]
            x1 = 0.5 * (p[i + one, j] - p[i - one, j])
            x2 = 0.5 * (p[i, j + one] - p[i, j - one])
            y = e[ie, je]
            kept[n, 0] = x0
            kept[n, 1] = x1
            kept[n, 2] = x2
            kept[n, 3] = y
            n += 1
            sp += x0
            se += y
            sr += x1
            sc += x2
    if n == 0:
        return 0
    mp_ = sp / n
    me_ = se / n
    mr = sr / n
    mc = sc / n
    # the nine sums in registers, each accumulated in scan order from the caller's initial value
    a00, a01, a02 = normal[0, 0], normal[0, 1], normal[0, 2]
    a11, a12, a22 = normal[1, 1], normal[1, 2], normal[2, 2]
    b0, b1, b2 = rhs[0], rhs[1], rhs[2]
    for k in range(u(n)):
        x0 = kept[k, 0] - mp_
        x1 = kept[k, 1] - mr
        x2 = kept[k, 2] - mc
        y = kept[k, 3] - me_
        a00 += x0 * x0
        a01 += x0 * x1
        a02 += x0 * x2
        a11 += x1 * x1
        a12 += x1 * x2
        a22 += x2 * x2
        b0 += x0 * y
        b1 += x1 * y
        b2 += x2 * y
    normal[0, 0], normal[0, 1], normal[0, 2] = a00, a01, a02
    normal[1, 0], normal[1, 1], normal[1, 2] = a01, a11, a12
    normal[2, 0], normal[2, 1], normal[2, 2] = a02, a12, a22
    rhs[0], rhs[1], rhs[2] = b0, b1, b2
    return n


def gradient_offset(e, me, p, mp, origin, max_move: float = 1.0):
    """Sub-cell offset (δ_r, δ_c) of E relative to P placed at ``origin``, by least-squares alignment:
    ``(δ_r, δ_c, ok)``.

    Pairs E[i + o0, j + o1] with P[i, j] (``origin`` = (o0, o1), the grid peak's placement) and fits,
    over the pixels valid in both whose axis neighbours are valid in P,

        E ≈ a·P + b + c_r·g_r + c_c·g_c,     δ = −(c_r, c_c)/a

    the first-order expansion of E(m) = a·P(m − δ) + b (an affine change of brightness and a shift δ),
    with g = ∇P the prediction's central-difference gradient.  Only the prediction's: it carries no
    photo noise (the mean of both images' gradients converges in fewer steps but puts the photo's
    noise into the regressors, which doubled the s16-50m Monte Carlo's worst maplet-space bias, 0.046 →
    0.109 px).  Why (issue #15): a peak read off a sampled
    correlation surface — parabola or quadric — is biased wherever the surface is not symmetric about
    its maximum, and a correlation surface of shaded terrain over a masked window is not: at a
    perfect alignment (E = a·P + b) the 3×3 quadric still moves by up to 0.05 px, and re-centring
    cannot remove it.  This estimate is exactly zero there whatever the gradients' errors, so a loop
    that re-extracts (or re-renders) until it is below a tolerance stops at the least-squares
    alignment.  ``ok`` is False (δ NaN) with fewer than 8 usable pixels, a singular system, a
    non-positive gain a, or |δ| > ``max_move`` along an axis (outside the linear range).
    """
    return _gradient_offset(*_contiguous(e, me, p, mp), int(origin[0]), int(origin[1]), max_move)


def _window(p_shape, e_shape, o0: int, o1: int):
    """(i0, i1, j0, j1): P's rows i0 ≤ i < i1 and columns j0 ≤ j < j1 that have both axis neighbours
    in P (central differences) and whose pixel (i + o0, j + o1) and its neighbours lie inside E, for P
    placed at (o0, o1); None when fewer than one row or column is left."""
    hp, wp = p_shape
    he, we = e_shape
    i0, i1 = max(1, 1 - o0), min(hp - 1, he - 1 - o0)
    j0, j1 = max(1, 1 - o1), min(wp - 1, we - 1 - o1)
    return None if i1 - i0 < 1 or j1 - j0 < 1 else (i0, i1, j0, j1)


def _gradient_offset(e, me, p, mp, o0: int, o1: int, max_move: float = 1.0):
    """:func:`gradient_offset` on C-contiguous float64 images and bool masks, P placed at (o0, o1)."""
    nan = (math.nan, math.nan, False)
    window = _window(p.shape, e.shape, o0, o1)
    if window is None:
        return nan
    i0, i1, j0, j1 = window
    normal = np.zeros((3, 3))
    rhs = np.zeros(3)
    count = _k_alignment(e, me, p, mp, o0, o1, i0, i1, j0, j1, normal, rhs)
    if count < 8 or not normal[0, 0] > 0.0:
        return nan
    try:
        coef = np.linalg.solve(normal, rhs)
    except np.linalg.LinAlgError:
        return nan
    a, cr, cc = coef.tolist()
    if not (a > 0.0 and math.isfinite(cr) and math.isfinite(cc)):
        return nan
    dr, dc = -cr / a, -cc / a
    if not (abs(dr) <= max_move and abs(dc) <= max_move):
        return nan
    return dr, dc, True


def gradient_offset_photo(e, me, p, mp, origin, max_move: float = 1.0):
    """:func:`gradient_offset` with the roles of the images exchanged: ``(δ_r, δ_c, ok)``, the same
    offset of E relative to P placed at ``origin``, from the fit of the prediction on the photo

        P ≈ α·E + β + c_r·∇_r E + c_c·∇_c E,     δ = (c_r, c_c)/α

    (E(m) = a·P(m − δ) + b ⇔ P(m) = (E(m + δ) − b)/a, to first order P ≈ E/a − b/a + δ·∇E/a).
    Least squares is unbiased for noise in the fitted image and biased by noise in its regressors:
    this form suits a prediction noisier than the photo.  On the s16-50m Monte Carlo (per-node height
    errors of a third of a cell, S16 Table 2) the prediction's shading noise in the regressors of
    :func:`gradient_offset` moved the landmarks' mean errors by up to 0.041 px from their
    zero-perturbation registration; here by at most 0.007 px (docs/benchmarks.md).  With a clean
    prediction and a noisy photo it is the other way round: the photo's noise is then in the
    regressors.

    Pixels: valid in both images with their four axis neighbours valid in both — P's too, although
    P is not differentiated (the pixels of :func:`gradient_offset_symmetric`; this is its w = 1).  A
    prediction pixel beside an invalid one (a node shadowed or dark in the prediction) lies on the
    prediction's shadow edge, where the photo's gradient is steepest and the prediction least
    faithful; with the photo's gradient as regressor those few pixels (≈ 5 per invalid node, ~50 of
    9,600) had the most leverage: on the s16-50m preset they raised the worst zero-perturbation
    floor from 0.043 to 0.065 px and the exact-maplet control world's from 0.068 to 0.081 px.

    Exactly zero, like :func:`gradient_offset`, when P = a'·E + b'.  It is :func:`gradient_offset`
    called with the images exchanged (P's mask shrunk to its interior), the origin negated and its
    offset negated."""
    return _gradient_offset_photo(*_contiguous(e, me, p, mp), int(origin[0]), int(origin[1]), max_move)


def _gradient_offset_photo(e, me, p, mp, o0: int, o1: int, max_move: float = 1.0):
    """:func:`gradient_offset_photo` on C-contiguous float64 images and bool masks."""
    dr, dc, ok = _gradient_offset(p, _interior(mp), e, me, -o0, -o1, max_move)
    return (-dr, -dc, True) if ok else (dr, dc, False)


def _interior(m):
    """The pixels of mask ``m`` whose four axis neighbours are in ``m`` too (none on the border)."""
    out = np.zeros_like(m)
    out[1:-1, 1:-1] = m[1:-1, 1:-1] & m[:-2, 1:-1] & m[2:, 1:-1] & m[1:-1, :-2] & m[1:-1, 2:]
    return out


def gradient_offset_symmetric(e, me, p, mp, origin, weight: float | None = 0.5, max_move: float = 1.0):
    """The alignment of :func:`gradient_offset` with both images' gradients as regressors:
    ``(δ_r, δ_c, w, ok)``, the offset of E relative to P placed at ``origin``, and the weight w used.

    P is first brought to E's scale, P' = s·(P − P̄) + Ē with s = σ_E/σ_P over the pixels used (the
    symmetric, reduced-major-axis gain: it names neither image the fitted one).  The model
    E(m + w·δ) = g·P'(m − (1 − w)·δ) + b, to first order in δ and g − 1, is linear:

        D = E − P' ≈ β + γ·(w·E + (1 − w)·P') + c_r·G_r + c_c·G_c,   G = w·∇E + (1 − w)·∇P'

        δ = −(c_r, c_c) / (1 + γ·(1 − 2w))

    (w = 0 is :func:`gradient_offset`'s fit, w = 1 :func:`gradient_offset_photo`'s, both exactly:
    the regressors span the same space.)  ``weight`` w = ½ is the symmetric ("efficient second-order
    minimisation") form: the difference regressed on the mean of the two gradients, second-order
    exact in δ for a pure shift.  Noise in either image enters the regressors at half its amplitude,
    so the one-sided fits' attenuation (a quarter of the variance) and their bias from a prediction
    noisier than the photo, or the other way round, are about halved.  ``weight=None`` estimates w
    from the two images' own noise, the errors-in-variables weighting w = ν_P/(ν_E + ν_P) that gives
    G the least noise: ν is each image's Laplacian energy (the five-point Laplacian on P' and E, the
    high-frequency band where a smooth terrain's shading has little power and white noise most of
    its) beyond the part both images share, ν_E = var(ΔE) − cov(ΔE, ΔP'), ν_P = var(ΔP') −
    cov(ΔE, ΔP'), each at least 0 (w = ½ when both are 0).  A prediction noisier than the photo
    thus leans on the photo's gradient, an exact maplet on its own.

    Pixels: those valid in both images whose four axis neighbours are valid in both.  Exactly zero
    when P = a'·E + b' (a' > 0): then D = γ·M + β with c = 0, whatever w and s.  ``ok`` is False
    (δ NaN) with fewer than 8 usable pixels, a flat image, a non-positive covariance of E and P, a
    singular system, a non-positive 1 + γ(1 − 2w), or |δ| > ``max_move`` along an axis.
    """
    e = np.ascontiguousarray(e, dtype=np.float64)
    p = np.ascontiguousarray(p, dtype=np.float64)
    me = np.ascontiguousarray(me, dtype=np.bool_)
    mp = np.ascontiguousarray(mp, dtype=np.bool_)
    return _gradient_offset_symmetric(e, me, p, mp, int(origin[0]), int(origin[1]), weight, max_move)


def _gradient_offset_symmetric(e, me, p, mp, o0: int, o1: int, weight=0.5, max_move: float = 1.0):
    """:func:`gradient_offset_symmetric` on float64 images and bool masks, P placed at (o0, o1)."""
    nan = (math.nan, math.nan, math.nan, False)
    window = _window(p.shape, e.shape, o0, o1)
    if window is None:
        return nan
    i0, i1, j0, j1 = window

    def five(a, oi, oj):  # centre, row −1, row +1, column −1, column +1 windows
        r0, r1, c0, c1 = i0 + oi, i1 + oi, j0 + oj, j1 + oj
        return (
            a[r0:r1, c0:c1], a[r0 - 1 : r1 - 1, c0:c1], a[r0 + 1 : r1 + 1, c0:c1],
            a[r0:r1, c0 - 1 : c1 - 1], a[r0:r1, c0 + 1 : c1 + 1],
        )  # fmt: skip

    ok = np.ones((i1 - i0, j1 - j0), dtype=np.bool_)
    for m in five(mp, 0, 0) + five(me, o0, o1):
        ok &= m
    if np.count_nonzero(ok) < 8:
        return nan
    pc, pu, pd, pl, pr = (a[ok] for a in five(p, 0, 0))
    ec, eu, ed, el, er = (a[ok] for a in five(e, o0, o1))
    ec = ec - ec.mean()
    pm = pc.mean()
    sd_e, sd_p = float(np.sqrt(np.mean(ec * ec))), float(np.sqrt(np.mean((pc - pm) ** 2)))
    if not (sd_e > 0.0 and sd_p > 0.0 and float(np.mean(ec * (pc - pm))) > 0.0):
        return nan
    s = sd_e / sd_p
    pc = s * (pc - pm)
    pgr, pgc = 0.5 * s * (pd - pu), 0.5 * s * (pr - pl)
    egr, egc = 0.5 * (ed - eu), 0.5 * (er - el)
    if weight is None:
        lap_e = (eu + ed + el + er) - 4.0 * ec  # ec lacks E's mean: a constant, removed next
        lap_e = lap_e - lap_e.mean()
        lap_p = s * (pu + pd + pl + pr) - 4.0 * pc
        lap_p = lap_p - lap_p.mean()
        shared = float(np.mean(lap_e * lap_p))
        nu_e = max(float(np.mean(lap_e * lap_e)) - shared, 0.0)
        nu_p = max(float(np.mean(lap_p * lap_p)) - shared, 0.0)
        tiny = 1e-12 * float(np.mean(lap_e * lap_e) + np.mean(lap_p * lap_p))  # rounding of a perfect pair
        w = nu_p / (nu_e + nu_p) if nu_e + nu_p > tiny else 0.5
    else:
        w = float(weight)
    d = ec - pc
    mix = w * ec + (1.0 - w) * pc
    gr = w * egr + (1.0 - w) * pgr
    gc = w * egc + (1.0 - w) * pgc
    x = np.stack([mix - mix.mean(), gr - gr.mean(), gc - gc.mean()], axis=1)
    try:
        gamma, cr, cc = np.linalg.solve(x.T @ x, x.T @ (d - d.mean())).tolist()
    except np.linalg.LinAlgError:
        return nan
    den = 1.0 + gamma * (1.0 - 2.0 * w)
    if not (den > 0.0 and math.isfinite(cr) and math.isfinite(cc)):
        return nan
    dr, dc = -cr / den, -cc / den
    if not (abs(dr) <= max_move and abs(dc) <= max_move):
        return nan
    return dr, dc, w, True
