"""The landmarks a pose solve can use, and the outlier rejection of ``solve-pose`` (spc-algorithms.md
§10.4; L15 §2): a landmark without a known position, a measured pixel or in front of the a-priori
camera is left out with its reason; after a fit, the landmark whose normalised residual ρᵢ =
‖Wᵢ^(1/2) rᵢ‖ (in ``"estimate"`` mode plus its position-prior term) exceeds ``reject_sigma`` times
the robust scale max(1, median(ρ)/√(2 ln 2)) — or whose pixel residual exceeds ``reject_px`` — is
rejected, worst first, one at a time, and the pose fitted again (:mod:`spctool.stages.pose`).
Every rejection is named with its reason (:class:`Rejection`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Rejection", "fit_rejecting", "outlier_scores", "usable_landmarks"]

#: median of the norm of a 2-D standard normal vector, √(2 ln 2)
_RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))


@dataclass(frozen=True)
class Rejection:
    """One landmark left out of the solution, and why."""

    name: str
    index: int
    reason: str  # short word: "outlier", "no-measurement", "behind-camera", "no-position"
    detail: str
    residual_px: float = math.nan

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "index": self.index,
            "reason": self.reason,
            "detail": self.detail,
            "residual_px": self.residual_px,
        }


def outlier_scores(problem, state, opts):
    """(score, limit, unit, residual px) of every landmark of the fit for the outlier test: the
    residual in px against ``reject_px``, else its weighted size ρ (with the landmark's position-prior
    term in ``"estimate"`` mode), robustly rescaled, against ``reject_sigma``."""
    smp, lin = state.camera.project(problem.pts(state))
    r = problem.meas - np.stack([smp, lin], axis=-1)
    rho2 = np.einsum("mi,mij,mj->m", r, problem.wts, r)
    if state.dlmk is not None:  # "estimate": a landmark's cost also has its position-prior term
        rho2 = rho2 + np.sum(problem.lmk_info * state.dlmk * state.dlmk, axis=1)
    rho = np.sqrt(rho2)
    rpx = np.sqrt(np.sum(r * r, axis=1))
    if opts.reject_px is not None:
        return rpx, float(opts.reject_px), "px", rpx
    c = max(1.0, float(np.median(rho)) / _RAYLEIGH_MEDIAN) if opts.robust_scale else 1.0
    return rho / c, float(opts.reject_sigma), "sigma", rpx


def usable_landmarks(camera, pts_all, meas_all, names):
    """(usable (N,), known position (N,), a-priori predicted pixels (N, 2), status words, rejections):
    a landmark is usable with a known position, a measured pixel and in front of the a-priori camera;
    the others are named with the reason (``no-position``, ``no-measurement``, ``behind-camera``)."""
    status = ["ok"] * pts_all.shape[0]
    rejected: list[Rejection] = []
    pts_finite = np.all(np.isfinite(pts_all), axis=1)
    meas_finite = np.all(np.isfinite(meas_all), axis=1)
    smp0, lin0, front0 = camera.project_with_mask(np.where(pts_finite[:, None], pts_all, 0.0))
    pred0 = np.stack([smp0, lin0], axis=-1)
    pred0[~(pts_finite & front0)] = np.nan
    usable = pts_finite & meas_finite & front0
    for i in np.flatnonzero(~usable):  # only the unusable few
        i = int(i)
        if not pts_finite[i]:
            word, detail = "no-position", "landmark position unknown"
        elif not meas_finite[i]:
            word, detail = "no-measurement", "measured pixel is not a number"
        else:
            word, detail = "behind-camera", "landmark behind the a-priori camera"
        status[i] = word
        rejected.append(Rejection(names[i], i, word, detail))
    return usable, pts_finite, pred0, status, rejected


def fit_rejecting(build, usable, opts, prior, names, status, rejected, warnings):
    """Fit the landmarks ``usable``, then while the outlier test fails drop the worst one and fit again
    (one at a time, at most ``max_reject_fraction`` of them, never below ``min_landmarks``); the
    rejections go to ``status``, ``rejected`` and ``warnings``.  Returns (problem, state, iterations,
    converged, cost history, used)."""
    used = usable.copy()
    max_reject = int(math.floor(opts.max_reject_fraction * int(np.count_nonzero(usable))))
    prior_used = prior.n_equations > 0
    while True:
        problem = build(used)
        state, iterations, converged, history = problem.fit()
        if not opts.reject_outliers:
            break
        idx = np.flatnonzero(used)
        m = idx.size
        if 2 * m + prior.n_equations - 6 <= 0:  # no redundancy: nothing can be tested
            break
        score, limit, unit, rpx = outlier_scores(problem, state, opts)
        worst = int(np.argmax(score))
        if not score[worst] > limit:
            break
        n_rej = int(np.count_nonzero(usable & ~used))
        if m - 1 < max(opts.min_landmarks, 0 if prior_used else 3) or n_rej + 1 > max_reject:
            bad = [names[idx[k]] for k in np.flatnonzero(score > limit)]
            warnings.append(
                f"outlier test fails for {', '.join(bad)} but no more landmarks may be rejected"
                f" ({m} used, min_landmarks {opts.min_landmarks}, max_reject_fraction"
                f" {opts.max_reject_fraction})"
            )
            break
        k = int(idx[worst])
        detail = (
            f"residual {rpx[worst]:.3f} px ({score[worst]:.1f} {unit}) > {limit:g} {unit}"
            if unit == "px"
            else f"residual {rpx[worst]:.3f} px = {score[worst]:.1f} sigma > {limit:g} sigma"
        )
        rejected.append(Rejection(names[k], k, "outlier", detail, float(rpx[worst])))
        status[k] = "rejected-outlier"
        used[k] = False
    return problem, state, iterations, converged, history, used
