"""Stage I — ``solve-pose``: spacecraft position and camera attitude from measured landmark pixels.

Specification: spc-algorithms.md §10 (L15 §2 with errata 1–4 of §11) and §13 (defaults); pixel and
frame conventions from spc-formats.md §0.4, §2.5 (SUM SCOBJ, CX/CY/CZ, SIGMA_VSO, SIGMA_PTG) and §4
(LMK VLM, SIGMA_LMK).

Problem.  Given N landmarks at body-fixed positions Vᵢ (km) measured at SPC pixels yᵢ = (sample, line)
(1-based, spc-formats.md §0.4), find the spacecraft position p (= −SCOBJ, body frame, km) and the
body→camera rotation T (rows CX, CY, CZ) that minimise

    Σᵢ (yᵢ − h(p, T, Vᵢ))ᵀ Wᵢ (yᵢ − h(p, T, Vᵢ))  +  ‖P₀^(−1/2) (χ − χ₀)‖²          (spc-algorithms.md §10.3)

with h the full SPC camera model (:class:`spctool.geometry.camera.Camera`: distortion, legacy D terms,
K matrix), Wᵢ = diag(1/σ_sample², 1/σ_line²) (default σ = ``sigma_px`` = 0.1 px, the S16 achieved
accuracy, spc-algorithms.md §13; 1 px is the conservative choice) — or, with per-landmark measurement
covariances Cᵢ (``pixel_covariances``: the correlation surface's, from ``register``), the full 2×2
Wᵢ = (Cᵢ + σ_floor²·I)⁻¹, so a weak, smeared peak counts less than a sharp one and the axes'
correlation is honoured — and the a-priori term built from the SUM's SIGMA_VSO (km) and SIGMA_PTG
(rad) about the a-priori pose χ₀.

State and conventions (everything downstream relies on these):

* χ = [Δp; θ] with Δp = p − p₀ (km, **body frame**, the axes of SIGMA_VSO) and θ the attitude offset
  defined by **T = Rot(−θ)·T₀** (rad, **camera frame**, the axes of SIGMA_PTG — per camera axis as
  spc-formats.md §2.1 infers).  Rot is the exact exponential map (frames.rot_from_rotvec); to first order
  T = (I − [θ×])·T₀, L15 footnote 13.  Because Rot(θ)·θ = θ, θ has the same components in the a-priori
  and the solved camera frame.
* Gauss–Newton steps δθ use the update T⁺ = Rot(−δθ)·T (frames.apply_attitude_update) with
  ∂x_C/∂δθ = [x_C×] and ∂x_C/∂p = −T — spc-algorithms.md erratum 3 (L15 Eq. 2.26/2.27/2.30 use the
  transposed rotation); the focal-plane derivative has third column −x_C, −y_C (erratum 2, L15 Eq. 2.24);
  the distortion derivative is written from the SPC-order OWEN formula (erratum 4 does not arise).
  These Jacobians come from :meth:`Camera.project_with_jacobians`, vectorised over landmarks.
* The a-priori attitude residual is θ itself; its derivative with respect to a step δθ is the inverse
  right Jacobian of SO(3), J_r(θ)⁻¹ (θ⁺ = θ + J_r(θ)⁻¹·δθ + O(δθ²)), so the prior term is exact, not a
  small-angle approximation.
* Normal equations (L15 Eq. 2.19 with erratum 1, Δχ = χ⁺ − χ⁻, weighted and with the prior):
  (HᵀWH + P₀⁻¹)·Δχ = HᵀW·Δy − P₀⁻¹·(χ − χ₀).  They are solved after Jacobi scaling (unit diagonal); the
  **condition number** reported is that of the scaled matrix, and above ``max_condition`` the geometry is
  declared degenerate (:class:`PoseError`, never a singular-matrix traceback).
* Steps are applied with a **pivot retraction**: the camera-frame vector t = T·(c − p) from the camera to
  the landmark centroid c is updated by δt = [t×]·δθ − T·δp (the same step to first order), so a finite
  step orbits the camera about the landmarks.  This follows the nearly degenerate position/attitude
  valley of small landmark clusters (e.g. the real Rosetta picture: 3 landmarks within 40 px, no prior:
  4 iterations instead of 10 with step halving).  The Gauss–Newton system, the covariance and the
  reported state stay in (Δp, θ).
* Each step is safeguarded by backtracking (step halving until the cost does not increase).  Convergence:
  the largest step component is below ``tol`` times its own 1σ, or the relative cost change is below
  ``tol`` (spc-algorithms.md §10.3: 1e-8, at most 10 iterations, §13).
* Covariance (HᵀWH + P₀⁻¹)⁻¹ at the solution, order [Δp (km, body), θ (rad, camera)]; 1σ, correlation.
* Residuals are **measured − predicted** (pixels), before (a-priori pose) and after (solved pose).

Landmark positions (``landmark_mode``):

* ``"fixed"`` — Vᵢ exact (SPC's usual geometry solve);
* ``"estimate"`` — Vᵢ + dᵢ estimated with a-priori dᵢ ~ N(0, diag(σᵢ²)) from the LMK SIGMA_LMK (km,
  body frame), L15 Eq. 2.8 second state form.  The 3×3 landmark blocks are eliminated per landmark
  (Schur complement, vectorised), so the cost stays linear in N;
* ``"consider"`` — Vᵢ fixed in the estimate but their uncertainty inflates the covariance (L15 footnote
  14): P_c = P + P·(Σᵢ Bᵢ Σᵢ Bᵢᵀ)·P with Bᵢ = Hₓ,ᵢᵀ Wᵢ H_V,ᵢ.

Outliers: after a fit, a landmark whose normalised residual ρᵢ = ‖Wᵢ^(1/2) rᵢ‖ (in ``"estimate"`` mode
plus its position-prior term, ρᵢ² += dᵢᵀΣᵢ⁻¹dᵢ) exceeds ``reject_sigma``
times a robust scale c = max(1, median(ρ)/√(2 ln 2)) (the median of a 2-D Gaussian residual norm is
σ√(2 ln 2)) — or, when ``reject_px`` is given, whose pixel residual exceeds ``reject_px`` — is rejected,
worst first, one at a time, and the pose is refitted from the a-priori pose.  Every rejection is named
with its reason in :attr:`PoseResult.rejected`; nothing is dropped silently.

Rooms: the least-squares problem itself (state, normal equations, Jacobi-scaled solve, Gauss–Newton) is
:mod:`spctool.stages._pose_problem`; the consistency tests are :mod:`spctool.stages.pose_consistency`;
the usable landmarks and the outlier rejection are :mod:`spctool.stages.pose_outliers`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from spctool.errors import SpcUsageError
from spctool.stages._pose_problem import (
    PoseError,
    _common_covariance,
    _error_modes,
    _Prior,
    _prior_info,
    _Problem,
    _sandwich_covariance,
    so3_right_jacobian_inv,
)
from spctool.stages.pose_consistency import (
    ChiSquareGate,
    PriorTest,
    chi2_gate,
    model_error,
    prior_scale_step,
    prior_test,
)
from spctool.stages.pose_outliers import Rejection, fit_rejecting, usable_landmarks

__all__ = [
    "PoseError",
    "PoseOptions",
    "PoseResult",
    "POSE_VERDICTS",
    "Rejection",
    "LANDMARK_MODES",
    "solve_pose",
    "so3_right_jacobian_inv",
]

LANDMARK_MODES = ("fixed", "estimate", "consider")
#: :attr:`PoseResult.verdict` words, most serious first
POSE_VERDICTS = ("implausible", "prior-contradicted", "inconsistent", "unchecked", "ok")
#: landmark sigmas ≤ 0 are held (effectively) fixed at this 1σ (km) in "estimate" mode
_TINY_SIGMA_KM = 1e-9


@dataclass
class PoseOptions:
    """Settings of :func:`solve_pose` (defaults: spc-algorithms.md §10.3 and §13).

    * ``max_iter`` / ``tol`` — Gauss–Newton iterations and convergence tolerance (10 / 1e-8, §13).
    * ``sigma_px`` — 1σ measurement noise per pixel component (0.1 px: S16's achieved accuracy; §13
      lists 1 px as the conservative alternative).
    * ``use_prior`` — use the a-priori sigmas (SUM SIGMA_VSO / SIGMA_PTG) passed to :func:`solve_pose`.
    * ``landmark_mode`` — ``"fixed"``, ``"estimate"`` or ``"consider"`` (module docstring);
      ``estimate_landmarks=True`` is a shortcut for ``landmark_mode="estimate"``.
    * ``reject_outliers``, ``reject_sigma`` (k in the k·σ test, 5), ``reject_px`` (absolute pixel
      threshold replacing the k·σ test when given), ``robust_scale`` (scale the k·σ threshold by the
      robust residual scale, so a too-optimistic ``sigma_px`` does not reject every landmark),
      ``max_reject_fraction`` (at most this fraction of the usable landmarks is rejected).
    * ``min_landmarks`` — fewer usable landmarks is a :class:`PoseError` (3; without a prior at least 3
      are always required: 6 unknowns).
    * ``max_condition`` — Jacobi-scaled normal-matrix condition number above which the geometry is
      degenerate (:class:`PoseError`).
    * ``max_halvings`` — step halvings allowed by the backtracking safeguard.
    * ``scale_covariance`` — multiply the covariance by cost/dof when it exceeds 1 (the residuals say
      the pixel noise is larger than ``sigma_px``; the formal covariance stays in
      :attr:`PoseResult.covariance_formal`) (True; not in "consider" mode, whose covariance already
      holds the landmark errors that raise cost/dof).
    * ``max_reduced_chi2`` — cost/dof above which the fit is implausible (100: residuals ~10×
      ``sigma_px``; wrong measurements, another picture's table; real SPC data at 0.75 px against the
      0.1 px default gives ~30, which only scales the covariance): :attr:`PoseResult.implausible`
      names the reason.
    * ``sigma_floor_px`` — added in quadrature to per-landmark covariances (``pixel_covariances``) so
      that a near-perfect correlation (ρ → 1, covariance → 0) cannot take all the weight (0.001 px).
    * ``consistency_quantile`` — the χ² gate and the prior–measurement test
      (:mod:`spctool.stages.pose_consistency`) fail above this quantile (0.999): the pose is
      ``inconsistent`` / ``prior-contradicted`` (:attr:`PoseResult.verdict`), never ``ok``.
    * ``model_error`` — with ``pixel_covariances``: estimate the model error τ (px) the residuals show
      beyond the correlation peaks' covariances (Σᵢ rᵢᵀ(Cᵢ + τ²I)⁻¹rᵢ = dof) and weight with
      (Cᵢ + τ²I)⁻¹ (True), when χ² exceeds its ``model_error_quantile`` (0.9; below it the
      covariances are left as they are); τ is at most ``max_model_error_px`` (None: ``sigma_px``), a
      larger misfit is the χ² gate's.  Reported as :attr:`PoseResult.model_error_px`.
      ``common_model_error`` (True, ``"fixed"`` landmarks): τ also as a shift common to all the
      landmarks (covariance τ²I, through the Woodbury identity as ``common_covariance``) — the model
      errors that leave per-landmark residuals of size τ (a maplet's heights, its photometry) shift a
      picture's landmarks alike too, by a part the residuals cannot show (the pose absorbs it), taken
      as large as the part they show.
    * ``prior_scale`` — factor applied to the a-priori sigmas (1); ``estimate_prior_scale``: when the
      measurements contradict the prior, widen it by the test's √(q/k) and solve again, at most
      ``max_prior_scale_steps`` times, until they agree (the factor is :attr:`PoseResult.prior_scale`).
    """

    max_iter: int = 10
    tol: float = 1e-8
    sigma_px: float = 0.1
    use_prior: bool = True
    landmark_mode: str = "fixed"
    estimate_landmarks: bool = False
    reject_outliers: bool = True
    reject_sigma: float = 5.0
    reject_px: float | None = None
    robust_scale: bool = True
    max_reject_fraction: float = 0.5
    min_landmarks: int = 3
    max_condition: float = 1e12
    max_halvings: int = 30
    scale_covariance: bool = True
    max_reduced_chi2: float = 100.0
    sigma_floor_px: float = 0.001
    consistency_quantile: float = 0.999
    model_error: bool = True
    common_model_error: bool = True
    max_model_error_px: float | None = None
    model_error_quantile: float = 0.9
    prior_scale: float = 1.0
    estimate_prior_scale: bool = False
    max_prior_scale_steps: int = 6

    def __post_init__(self):
        if self.estimate_landmarks:
            if self.landmark_mode not in ("fixed", "estimate"):
                raise SpcUsageError(
                    f"estimate_landmarks=True conflicts with landmark_mode={self.landmark_mode!r}"
                )
            self.landmark_mode = "estimate"
        if self.landmark_mode not in LANDMARK_MODES:
            raise SpcUsageError(
                f"landmark_mode must be one of {', '.join(LANDMARK_MODES)}, got {self.landmark_mode!r}"
            )
        if int(self.max_iter) < 1:
            raise SpcUsageError(f"max_iter must be at least 1, got {self.max_iter}")
        if not (self.tol > 0):
            raise SpcUsageError(f"tol must be positive, got {self.tol}")
        if not (self.sigma_px > 0 and math.isfinite(self.sigma_px)):
            raise SpcUsageError(f"sigma_px must be a positive number of pixels, got {self.sigma_px}")
        if not (self.reject_sigma > 0):
            raise SpcUsageError(f"reject_sigma must be positive, got {self.reject_sigma}")
        if self.reject_px is not None and not (self.reject_px > 0):
            raise SpcUsageError(f"reject_px must be positive, got {self.reject_px}")
        if not (0.0 <= self.max_reject_fraction <= 1.0):
            raise SpcUsageError(f"max_reject_fraction must be in [0, 1], got {self.max_reject_fraction}")
        if int(self.min_landmarks) < 0:
            raise SpcUsageError(f"min_landmarks must be >= 0, got {self.min_landmarks}")
        if not (self.sigma_floor_px >= 0 and math.isfinite(self.sigma_floor_px)):
            raise SpcUsageError(f"sigma_floor_px must be a number >= 0, got {self.sigma_floor_px}")
        if not (self.max_condition > 1):
            raise SpcUsageError(f"max_condition must be > 1, got {self.max_condition}")
        if not (self.max_reduced_chi2 > 0):
            raise SpcUsageError(f"max_reduced_chi2 must be > 0, got {self.max_reduced_chi2}")
        if not (0.0 < self.consistency_quantile < 1.0):
            raise SpcUsageError(f"consistency_quantile must be in (0, 1), got {self.consistency_quantile}")
        if self.max_model_error_px is not None and not (self.max_model_error_px >= 0):
            raise SpcUsageError(f"max_model_error_px must be >= 0, got {self.max_model_error_px}")
        if not (0.0 < self.model_error_quantile < 1.0):
            raise SpcUsageError(f"model_error_quantile must be in (0, 1), got {self.model_error_quantile}")
        if not (self.prior_scale > 0 and math.isfinite(self.prior_scale)):
            raise SpcUsageError(f"prior_scale must be a positive number, got {self.prior_scale}")
        self.max_prior_scale_steps = int(self.max_prior_scale_steps)
        self.max_iter = int(self.max_iter)
        self.min_landmarks = int(self.min_landmarks)
        self.max_halvings = int(self.max_halvings)


@dataclass
class PoseResult:
    """Solved pose, its covariance and per-landmark residuals (module docstring for conventions)."""

    scobj: np.ndarray  # (3,) solved SCOBJ = −position (km, body)
    rotation: np.ndarray  # (3, 3) solved body→camera rotation (rows CX, CY, CZ)
    position: np.ndarray  # (3,) solved spacecraft position (km, body)
    delta_position: np.ndarray  # (3,) position − a-priori position (km, body)
    delta_attitude: np.ndarray  # (3,) θ with T = Rot(−θ)·T₀ (rad, camera frame)
    covariance: np.ndarray  # (6, 6) [Δp km, θ rad]; consider-inflated in "consider" mode
    sigmas: np.ndarray  # (6,) √diag(covariance)
    correlation: np.ndarray  # (6, 6)
    condition_number: float  # of the Jacobi-scaled normal matrix
    iterations: int
    converged: bool
    names: list[str]
    measured: np.ndarray  # (N, 2) measured (sample, line)
    predicted_before: np.ndarray  # (N, 2) at the a-priori pose (NaN where not computable)
    predicted_after: np.ndarray  # (N, 2) at the solved pose (with estimated landmark corrections)
    residuals_before: np.ndarray  # (N, 2) measured − predicted_before
    residuals_after: np.ndarray  # (N, 2) measured − predicted_after
    used: np.ndarray  # (N,) bool
    status: list[str]  # per landmark: "ok", "rejected-outlier", "no-measurement", ...
    rejected: list[Rejection]
    chi2: float  # measurement part of the cost at the solution (used landmarks)
    cost: float  # full cost (measurements + a-priori terms)
    dof: int  # 2·used + prior equations − unknowns
    rms_before: float  # rms pixel residual norm of the used landmarks, a-priori pose
    rms_after: float  # same at the solved pose
    landmark_mode: str = "fixed"
    prior_used: bool = False
    covariance_no_consider: np.ndarray | None = None  # (6, 6) in "consider" mode: before inflation
    landmark_corrections: np.ndarray | None = None  # (N, 3) km ("estimate" mode; 0 for unused)
    landmark_covariances: np.ndarray | None = None  # (N, 3, 3) a-posteriori ("estimate" mode)
    cost_history: list[float] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    covariance_formal: np.ndarray | None = None  # (6, 6) before scaling by cost/dof (None: not scaled)
    covariance_scale: float = 1.0  # factor applied to the covariance: cost/dof when it exceeds 1
    implausible: str = ""  # why the fit is implausible (cost/dof > max_reduced_chi2), "" when plausible
    gate: ChiSquareGate | None = None  # the χ² test of the cost (None: no redundancy)
    prior_check: PriorTest | None = None  # the prior–measurement test (None: no prior)
    prior_scale: float = 1.0  # factor applied to the a-priori sigmas (estimated or given)
    model_error_px: float = 0.0  # τ added in quadrature to the per-landmark covariances (estimated)
    common_covariance: np.ndarray | None = None  # (2, 2) px² error common to the landmarks (given + τ²I)

    # ---- convenience ------------------------------------------------------------------------------
    @property
    def sigma_position(self) -> np.ndarray:
        return self.sigmas[:3].copy()

    @property
    def sigma_attitude(self) -> np.ndarray:
        return self.sigmas[3:].copy()

    @property
    def n_used(self) -> int:
        return int(np.count_nonzero(self.used))

    @property
    def reduced_chi2(self) -> float:
        return self.cost / self.dof if self.dof > 0 else math.nan

    @property
    def plausible(self) -> bool:
        return not self.implausible

    @property
    def consistent(self) -> bool:
        """χ² of the fit within its ``consistency_quantile`` (:mod:`spctool.stages.pose_consistency`)."""
        return self.gate is None or self.gate.consistent

    @property
    def inconsistent(self) -> str:
        """Why the χ² gate fails (one line), "" when it passes."""
        return "" if self.gate is None else self.gate.reason()

    @property
    def prior_contradicted(self) -> str:
        """Why the measurements contradict the prior (one line with the remedy), "" when they agree."""
        return "" if self.prior_check is None else self.prior_check.reason()

    @property
    def unchecked(self) -> str:
        """Why the fit cannot be checked (one line): no redundancy (dof ≤ 0: as many equations as
        unknowns, the residuals zero whatever the measurements' errors), "" when it can."""
        if self.dof > 0:
            return ""
        eq = int(np.count_nonzero(self.used)) * 2
        prior = "" if self.prior_used else ", no prior"
        return (f"no redundancy ({eq} measurement equations for 6 unknowns{prior}, dof {self.dof}): the fit "
                "cannot be checked and its covariance is formal only; add landmarks or the SUM's prior")

    @property
    def verdict(self) -> str:
        """``implausible``, ``prior-contradicted``, ``inconsistent``, ``unchecked`` or ``ok`` (the first
        that holds)."""
        if self.implausible:
            return "implausible"
        if self.prior_contradicted:
            return "prior-contradicted"
        if self.inconsistent:
            return "inconsistent"
        if self.unchecked:
            return "unchecked"
        return "ok"

    @property
    def verdict_reason(self) -> str:
        """The one line behind :attr:`verdict` ("" for ``ok``)."""
        v = self.verdict
        return {
            "implausible": self.implausible,
            "prior-contradicted": self.prior_contradicted,
            "inconsistent": self.inconsistent,
            "unchecked": self.unchecked,
        }.get(v, "")

    @property
    def position_attitude_correlation(self) -> float:
        """The largest |correlation| between a position and an attitude component."""
        block = np.abs(np.asarray(self.correlation)[:3, 3:])
        return float(np.nanmax(block)) if np.isfinite(block).any() else math.nan

    @property
    def landmark_sigmas(self) -> np.ndarray | None:
        if self.landmark_covariances is None:
            return None
        return np.sqrt(np.clip(np.diagonal(self.landmark_covariances, axis1=-2, axis2=-1), 0, None))

    def pose_dict(self) -> dict:
        """The ``"pose"`` object of the solve-pose JSON document (cli-contract.md)."""
        out = {
            "position": self.position,
            "scobj": self.scobj,
            "rotation": self.rotation,
            "delta_position": self.delta_position,
            "delta_attitude": self.delta_attitude,
            "attitude_frame": "camera",
            "state_order": ["dx_km", "dy_km", "dz_km", "tx_rad", "ty_rad", "tz_rad"],
            "covariance": self.covariance,
            "sigma_position": self.sigma_position,
            "sigma_attitude": self.sigma_attitude,
            "correlation": self.correlation,
            "condition_number": self.condition_number,
            "iterations": self.iterations,
            "converged": self.converged,
            "landmarks_used": self.n_used,
            "chi2": self.chi2,
            "cost": self.cost,
            "dof": self.dof,
            "reduced_chi2": self.reduced_chi2,
            "rms_before_px": self.rms_before,
            "rms_after_px": self.rms_after,
            "landmark_mode": self.landmark_mode,
            "prior_used": self.prior_used,
            "rejected": [r.as_dict() for r in self.rejected],
            "warnings": list(self.warnings),
            "covariance_scale": self.covariance_scale,
            "covariance_formal": self.covariance
            if self.covariance_formal is None
            else self.covariance_formal,
            "position_attitude_correlation": self.position_attitude_correlation,
            "plausible": self.plausible,
            "implausible": self.implausible or None,
            "verdict": self.verdict,
            "verdict_reason": self.verdict_reason or None,
            "consistency": None if self.gate is None else self.gate.as_dict(),
            "prior_check": None if self.prior_check is None else self.prior_check.as_dict(),
            "prior_scale": self.prior_scale,
            "model_error_px": self.model_error_px,
            "common_sigma_px": None
            if self.common_covariance is None
            else float(np.sqrt(np.trace(self.common_covariance))),
        }
        if self.landmark_corrections is not None:
            out["landmark_corrections"] = {
                n: c for n, c, u in zip(self.names, self.landmark_corrections.tolist(), self.used) if u
            }
        return out

    def header_lines(self) -> list[str]:
        """The header block of a solve-pose text table: solved pose, 1σ, χ²/dof, correlation, verdict."""
        p, sp, sa = self.position, self.sigma_position, self.sigma_attitude
        return [
            f"position_km {p[0]:.9f} {p[1]:.9f} {p[2]:.9f}  sigma_km {sp[0]:.3e} {sp[1]:.3e} {sp[2]:.3e}",
            "attitude_change_rad {:+.4e} {:+.4e} {:+.4e}  sigma_rad {:.3e} {:.3e} {:.3e}".format(
                *self.delta_attitude, *sa
            ),
            f"chi2 {self.chi2:.4g} cost {self.cost:.4g} dof {self.dof} cost/dof {self.reduced_chi2:.3g}"
            f"  rms_px before {self.rms_before:.4f} after {self.rms_after:.4f}",
            f"covariance_scale {self.covariance_scale:.4g}"
            + (" (cost/dof > 1: sigmas x sqrt)" if self.covariance_scale != 1.0 else "")
            + f"  max |position-attitude correlation| {self.position_attitude_correlation:.3f}",
            "fit: plausible" if self.plausible else f"fit: IMPLAUSIBLE ({self.implausible})",
            f"verdict: {self.verdict}"
            + (f" ({self.verdict_reason})" if self.verdict_reason else "")
            + (f"  prior sigmas x{self.prior_scale:.3g}" if self.prior_scale != 1.0 else ""),
        ]

    def summary_lines(self) -> list[str]:
        """Human summary (pose change, 1σ, rms before/after) for stderr."""
        dp = self.delta_position
        th = self.delta_attitude
        sp = self.sigma_position
        sa = self.sigma_attitude
        lines = [
            f"solved with {self.n_used} landmarks in {self.iterations} iterations"
            f" ({'converged' if self.converged else 'NOT converged'}), landmarks {self.landmark_mode},"
            f" prior {'on' if self.prior_used else 'off'}",
            f"position change (km, body)   {dp[0]:+.6f} {dp[1]:+.6f} {dp[2]:+.6f}"
            f"  |d| = {np.linalg.norm(dp):.6f}",
            f"1-sigma position (km)        {sp[0]:.6f} {sp[1]:.6f} {sp[2]:.6f}",
            f"attitude change (rad, cam)   {th[0]:+.3e} {th[1]:+.3e} {th[2]:+.3e}"
            f"  |t| = {np.linalg.norm(th):.3e}",
            f"1-sigma attitude (rad)       {sa[0]:.3e} {sa[1]:.3e} {sa[2]:.3e}",
            f"rms residual (px) before {self.rms_before:.4f} after {self.rms_after:.4f};"
            f" chi2 {self.chi2:.4g} + prior {self.cost - self.chi2:.4g}, dof {self.dof},"
            f" cost/dof {self.reduced_chi2:.3g}, condition {self.condition_number:.3g}",
        ]
        if self.model_error_px > 0:
            lines.append(f"model error {self.model_error_px:.4f} px added to the landmarks' covariances")
        if self.common_covariance is not None and np.any(self.common_covariance != 0):
            lines.append(
                f"common error {np.sqrt(np.trace(self.common_covariance)):.4f} px (1 sigma, shared by the"
                " landmarks) in the measurement covariance"
            )
        if self.covariance_scale != 1.0:
            lines.append(
                f"covariance scaled by cost/dof = {self.covariance_scale:.3g} (sigmas x "
                f"{math.sqrt(self.covariance_scale):.3g})"
            )
        if self.implausible:
            lines.append(f"warning: implausible fit: {self.implausible}")
        if self.prior_contradicted:
            lines.append(f"warning: prior contradicted: {self.prior_contradicted}")
        if self.inconsistent:
            lines.append(f"warning: inconsistent fit: {self.inconsistent}")
        if self.unchecked:
            lines.append(f"warning: unchecked fit: {self.unchecked}")
        if self.prior_check is not None and self.prior_check.dof > 0:
            pc = self.prior_check
            lines.append(
                f"prior check: normalised change {pc.nis:.3g} ({pc.dof} dof, limit {pc.limit:.3g}),"
                f" prior {100 * pc.share:.0f} % of the cost"
                + (f", prior sigmas x{self.prior_scale:.3g}" if self.prior_scale != 1.0 else "")
            )
        for r in self.rejected:
            lines.append(f"rejected {r.name}: {r.reason} ({r.detail})")
        lines.extend(f"warning: {w}" for w in self.warnings)
        return lines


# ------------------------------------------------------------------------------------------------
# public entry point
# ------------------------------------------------------------------------------------------------


def _per_landmark(a, n, what, allow_scalar=True, width=None) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if width is None:
        return arr
    if allow_scalar and arr.ndim == 0:
        return np.full((n, width), float(arr))
    if arr.shape == (n,):
        return np.repeat(arr[:, None], width, axis=1)
    if arr.shape != (n, width):
        raise SpcUsageError(f"{what} must have shape ({n},) or ({n}, {width}), got {arr.shape}")
    return arr


def _covariance_weights(covs, n, floor, fallback):
    """(W (N, 2, 2), bad (N,)): Wᵢ = (Cᵢ + floor²·I)⁻¹ for finite positive-definite Cᵢ, else fallback."""
    c = np.asarray(covs, dtype=np.float64)
    if c.shape != (n, 2, 2):
        raise SpcUsageError(f"pixel_covariances must have shape ({n}, 2, 2), got {c.shape}")
    c = 0.5 * (c + np.swapaxes(c, 1, 2)) + (floor * floor) * np.eye(2)
    det = c[:, 0, 0] * c[:, 1, 1] - c[:, 0, 1] * c[:, 1, 0]
    good = np.all(np.isfinite(c), axis=(1, 2)) & (c[:, 0, 0] > 0) & (det > 0)
    w = np.array(fallback, dtype=np.float64, copy=True)
    w[good] = np.linalg.inv(c[good])  # finite, positive definite rows only
    return w, ~good


def solve_pose(*args, **kwargs) -> PoseResult:
    """Solve spacecraft position and attitude from N landmark measurements: :func:`_solve_pose`, with
    a linear-algebra failure (absurd but finite input, e.g. a pixel of 1e300) reported as
    :class:`PoseError` instead of numpy's LinAlgError."""
    try:
        return _solve_pose_scaled(*args, **kwargs)
    except np.linalg.LinAlgError as exc:
        raise PoseError(
            f"the pose could not be solved ({exc}): check the measured pixels and landmark positions"
        ) from None


def _solve_pose_scaled(camera, landmark_positions, measured, options: PoseOptions | None = None, *rest, **kw):
    """:func:`_solve_pose`; with ``options.estimate_prior_scale``, while the measurements contradict
    the prior, widen its sigmas by the test's factor (:func:`prior_scale_step`) and solve again."""
    opts = options or PoseOptions()
    res = _solve_pose(camera, landmark_positions, measured, opts, *rest, **kw)
    if not opts.estimate_prior_scale:
        return res
    first = res
    for _ in range(opts.max_prior_scale_steps):
        if res.prior_check is None or not res.prior_check.contradicted:
            break
        step = prior_scale_step(res.prior_check)
        opts = dataclasses.replace(opts, prior_scale=opts.prior_scale * step, estimate_landmarks=False)
        res = _solve_pose(camera, landmark_positions, measured, opts, *rest, **kw)
    if res is not first:
        res.warnings.append(
            f"prior widened x{res.prior_scale:.3g}: the measurements contradicted SIGMA_VSO/SIGMA_PTG"
            f" ({first.prior_contradicted})"
        )
    return res


def _measurement_weights(opts, meas_all, names, pixel_sigmas, pixel_covariances, warnings) -> np.ndarray:
    """(N, 2, 2) weights of the measurements: diag(1/σ²) from ``pixel_sigmas`` (default ``sigma_px``),
    or (Cᵢ + floor²·I)⁻¹ from ``pixel_covariances`` where those are usable (the others named in
    ``warnings``)."""
    n_all = meas_all.shape[0]
    sig_px = _per_landmark(
        opts.sigma_px if pixel_sigmas is None else pixel_sigmas, n_all, "pixel_sigmas", width=2
    )
    if np.any(~(sig_px > 0)):
        raise SpcUsageError("pixel sigmas must be positive")
    wts = np.zeros((n_all, 2, 2))
    wts[:, 0, 0] = 1.0 / (sig_px[:, 0] * sig_px[:, 0])
    wts[:, 1, 1] = 1.0 / (sig_px[:, 1] * sig_px[:, 1])
    if pixel_covariances is not None:
        wts, bad = _covariance_weights(pixel_covariances, n_all, opts.sigma_floor_px, wts)
        bad &= np.all(np.isfinite(meas_all), axis=1)
        if bad.any():
            fallback = "the given pixel sigmas" if pixel_sigmas is not None else f"{opts.sigma_px:g} px"
            warnings.append(
                f"no usable measurement covariance for {', '.join(names[i] for i in np.flatnonzero(bad))}:"
                f" weighted with {fallback}"
            )
    return wts


def _final_covariance(problem, state, mode, used, pts_all, lmk_sig):
    """The pose covariance at the solution (6 × 6), its condition number, and per mode: ``"consider"``
    the covariance without the landmark errors; ``"estimate"`` the landmark corrections and their
    covariances (N, 3) / (N, 3, 3), NaN-free only for used landmarks.  Also the landmark positions
    after the fit."""
    n_all = pts_all.shape[0]
    n, g, extra = problem.normal(state)
    _, cov, cond = problem.solve_scaled(n, g, int(np.count_nonzero(used)))
    cov_plain = lmk_corr = lmk_cov = None
    pts_after = pts_all.copy()
    if mode == "estimate":
        b, dinv = extra["b"], extra["dinv"]
        bd = b @ dinv  # (M, 6, 3)
        cov_l = dinv + np.einsum("mji,jk,mkl->mil", bd, cov, bd)
        lmk_corr = np.zeros((n_all, 3))
        lmk_corr[used] = state.dlmk
        lmk_cov = np.full((n_all, 3, 3), np.nan)
        lmk_cov[used] = cov_l
        pts_after[used] = pts_all[used] + state.dlmk
    elif mode == "consider":
        b = np.einsum("mki,mkj->mij", problem.wts @ extra["hx"], extra["hl"])  # (M, 6, 3)
        c = np.einsum("mij,mj,mkj->ik", b, lmk_sig[used] ** 2, b)
        cov_plain = cov
        cov = cov + cov @ c @ cov
        cov = 0.5 * (cov + cov.T)
    return cov, cond, cov_plain, lmk_corr, lmk_cov, pts_after


def _consistency(problem, state, opts, dof, cost, names, used, prior, cov_plain, cov_formal, cov):
    """The χ² gate and (with a prior) the prior–measurement test of the solution
    (:mod:`spctool.stages.pose_consistency`), on the formal covariance (not scaled, not consider-
    inflated)."""
    smp, lin = state.camera.project(problem.pts(state))
    r = problem.meas - np.stack([smp, lin], axis=-1)
    rho2 = np.einsum("mi,mij,mj->m", r, problem.wts, r)
    if state.dlmk is not None:
        rho2 = rho2 + np.sum(problem.lmk_info * state.dlmk * state.dlmk, axis=1)
    used_names = [names[i] for i in np.flatnonzero(used)]
    q = opts.consistency_quantile
    gate = chi2_gate(cost, dof, rho2, used_names, q) if dof > 0 else None
    prior_check = None
    if prior.n_equations > 0:
        formal = cov_plain if cov_plain is not None else cov_formal if cov_formal is not None else cov
        e = np.concatenate([state.dpos, state.theta])
        term = float(np.sum(prior.info * e * e))
        # the measurements' own noise scale (their χ² over its expected value at the joint solution)
        dof_meas = 2.0 * rho2.size - 6.0 + float(np.sum(prior.info * np.diag(formal)))
        chi2_meas = cost - term
        noise = chi2_meas / dof_meas if dof_meas > 0.5 else 1.0
        prior_check = prior_test(
            e, prior.info, formal, term, cost, q, float(opts.prior_scale), noise_scale=noise
        )
    return gate, prior_check


def _covariance_matrices(covs, n, floor, wts):
    """(N, 2, 2) measurement covariances the weights ``wts`` stand for: Cᵢ + floor²·I where that is
    usable, else the inverse of the fallback weight."""
    c = 0.5 * (np.asarray(covs, dtype=np.float64) + np.swapaxes(np.asarray(covs, dtype=np.float64), 1, 2))
    c = c + (floor * floor) * np.eye(2)
    _, bad = _covariance_weights(covs, n, floor, wts)
    c[bad] = np.linalg.inv(wts[bad]) if bad.any() else c[bad]
    return c


def _model_error(problem, state, covs, opts, prior) -> float:
    """τ (px) of :func:`spctool.stages.pose_consistency.model_error` for the residuals of the fit
    (dof 2M − 6 + prior equations), capped at ``max_model_error_px`` (default ``sigma_px``)."""
    smp, lin = state.camera.project(problem.pts(state))
    r = problem.meas - np.stack([smp, lin], axis=-1)
    cap = opts.sigma_px if opts.max_model_error_px is None else float(opts.max_model_error_px)
    dof = 2 * r.shape[0] + prior.n_equations - 6
    return model_error(r, covs, dof, cap, opts.model_error_quantile)


def _checked_inputs(landmark_positions, measured, names):
    """(positions (N, 3), measured pixels (N, 2), N names) as float arrays and strings; a wrong shape
    or name count is a :class:`SpcUsageError`."""
    pts_all = np.asarray(landmark_positions, dtype=np.float64)
    meas_all = np.asarray(measured, dtype=np.float64)
    if pts_all.ndim != 2 or pts_all.shape[1] != 3:
        raise SpcUsageError(f"landmark_positions must have shape (N, 3), got {pts_all.shape}")
    n_all = pts_all.shape[0]
    if meas_all.shape != (n_all, 2):
        raise SpcUsageError(f"measured must have shape ({n_all}, 2), got {meas_all.shape}")
    names = [f"#{i + 1}" for i in range(n_all)] if names is None else [str(x) for x in names]
    if len(names) != n_all:
        raise SpcUsageError(f"names has {len(names)} entries for {n_all} landmarks")
    return pts_all, meas_all, names


def _landmark_sigmas(mode, landmark_sigmas, n_all):
    """(N, 3) km landmark 1σ for ``"estimate"`` / ``"consider"`` (required there); None for ``"fixed"``."""
    if mode == "fixed":
        return None
    if landmark_sigmas is None:
        raise SpcUsageError(f"landmark_mode {mode!r} needs landmark sigmas (LMK SIGMA_LMK)")
    lmk_sig = _per_landmark(landmark_sigmas, n_all, "landmark_sigmas", width=3)
    if not np.all(np.isfinite(lmk_sig)):
        raise SpcUsageError("landmark sigmas must be finite")
    return lmk_sig


def _pose_prior(opts, prior_sigma_position, prior_sigma_attitude, warnings) -> _Prior:
    """The a-priori term from SIGMA_VSO / SIGMA_PTG (widened by ``prior_scale``); none without
    ``use_prior``."""
    if not opts.use_prior:
        return _Prior(np.zeros(6))
    info = np.concatenate(
        [
            _prior_info(prior_sigma_position, 3, "prior position sigma", warnings),
            _prior_info(prior_sigma_attitude, 3, "prior attitude sigma", warnings),
        ]
    )
    return _Prior(info / (opts.prior_scale * opts.prior_scale))


def _check_count(count, opts, prior_used):
    """:class:`PoseError` unless ``count`` landmarks are enough (3 without a prior: 6 unknowns)."""
    need = opts.min_landmarks if prior_used else max(opts.min_landmarks, 3)
    if count < need:
        why = "" if prior_used else " (6 unknowns and no a-priori pose)"
        raise PoseError(f"too few landmarks: {count} usable, at least {need} needed{why}")


def _fit_with_model_error(
    build, wts_all, modes_all, common, usable, opts, prior, labels, pixel_covariances, error_modes, mode
):
    """:func:`~spctool.stages.pose_outliers.fit_rejecting`; with ``pixel_covariances`` and
    ``opts.model_error``, the model error τ the residuals show beyond the correlation peaks'
    covariances, then the fit again with it (twice:
    the residuals of the refit estimate it again).  ``labels`` = (names, status, rejected, warnings),
    the last three reset before a refit.  Returns (fit, τ, weights, common covariance used)."""
    names, status, rejected, warnings = labels
    before = (list(status), list(rejected), list(warnings))
    fit = fit_rejecting(
        lambda mask: build(mask, wts_all, modes_all), usable, opts, prior, names, status, rejected, warnings
    )
    tau, common_used = 0.0, common
    if pixel_covariances is None or not opts.model_error:
        return fit, tau, wts_all, common_used
    base = _covariance_matrices(pixel_covariances, usable.size, opts.sigma_floor_px, wts_all)
    for _ in range(2):
        new_tau = _model_error(fit[0], fit[1], base[fit[5]], opts, prior)
        if abs(new_tau - tau) <= 0.05 * max(new_tau, 1e-12):
            break
        tau = new_tau
        wts_all = np.linalg.inv(base + (tau * tau) * np.eye(2))
        if opts.common_model_error and mode == "fixed":  # its common part, as large (PoseOptions)
            shared = (tau * tau) * np.eye(2) + (0.0 if common is None else common)
            modes_all = _error_modes(shared, error_modes, usable.size, mode)
            common_used = shared
        status[:], rejected[:], warnings[:] = (list(x) for x in before)
        fit = fit_rejecting(
            lambda mask, w=wts_all, e=modes_all: build(mask, w, e),
            usable, opts, prior, names, status, rejected, warnings,
        )  # fmt: skip
    return fit, tau, wts_all, common_used


def _scaled_covariance(cov, lmk_cov, red, opts):
    """(covariance, formal covariance or None, scale, landmark covariances): residuals larger than
    ``sigma_px`` say so — the covariance is scaled by cost/dof when it exceeds 1 (not in ``"consider"``
    mode, whose covariance already holds the landmark errors that raise cost/dof)."""
    if opts.scale_covariance and opts.landmark_mode != "consider" and red > 1.0:
        scale = float(red)
        return cov * scale, cov, scale, None if lmk_cov is None else lmk_cov * scale
    return cov, None, 1.0, lmk_cov


def _implausible(red, opts) -> str:
    """The reason a fit is implausible (cost/dof above ``max_reduced_chi2``), else ''."""
    if not red > opts.max_reduced_chi2:
        return ""
    return (
        f"cost/dof {red:.3g} > {opts.max_reduced_chi2:g}: the residuals are ~{math.sqrt(red):.3g}x "
        f"sigma_px {opts.sigma_px:g} px (wrong measurements, another picture's table, or sigma_px "
        "too small)"
    )


def _solve_pose(
    camera,
    landmark_positions,
    measured,
    options: PoseOptions | None = None,
    prior_sigma_position=None,
    prior_sigma_attitude=None,
    landmark_sigmas=None,
    names=None,
    pixel_sigmas=None,
    pixel_covariances=None,
    common_covariance=None,
    error_modes=None,
    estimate_weights: str = "covariance",
) -> PoseResult:
    """Solve spacecraft position and attitude from N landmark measurements (module docstring).

    * ``camera`` — :class:`spctool.geometry.camera.Camera` holding the a-priori pose and intrinsics.
    * ``landmark_positions`` (N, 3) — body-fixed km (LMK VLM); NaN rows are left out ("no-position").
    * ``measured`` (N, 2) — measured (sample, line), SPC 1-based pixels; NaN rows left out.
    * ``prior_sigma_position`` (3,) km, body frame (SUM SIGMA_VSO) and ``prior_sigma_attitude`` (3,)
      rad, camera frame (SUM SIGMA_PTG); used when ``options.use_prior``.  None = no prior on that part.
    * ``landmark_sigmas`` (N, 3) km (LMK SIGMA_LMK) — required for ``"estimate"`` / ``"consider"``.
    * ``pixel_sigmas`` — optional per-landmark 1σ in pixels, (N,) or (N, 2); default ``sigma_px``.
    * ``pixel_covariances`` — optional (N, 2, 2) measurement covariances in px² (sample, line), e.g.
      ``register``'s; weights Wᵢ = (Cᵢ + ``sigma_floor_px``²·I)⁻¹.  Rows that are not finite positive
      definite fall back to ``pixel_sigmas``/``sigma_px`` (named in a warning).
    * ``common_covariance`` — optional 2×2 covariance (px²) of an error common to every landmark of the
      picture (a shading-model error shared by its landmarks, :mod:`spctool.stages.model_error`): the
      measurements' covariance becomes blkdiag(Wᵢ⁻¹) + U·C·Uᵀ, applied by the Woodbury identity
      (:mod:`spctool.stages._pose_problem`), so the pose covariance includes it.  ``"fixed"`` landmarks only.
    * ``error_modes`` — optional (N, 2, k) px: k patterns of pixel errors over the landmarks, each with a
      unit-variance coefficient (covariance Σₖ uₖuₖᵀ added to the measurements' covariance; e.g. the
      shift of every landmark under another shading model, :mod:`spctool.stages.model_error`); also by
      Woodbury, also ``"fixed"`` only.
    * ``estimate_weights`` — with ``pixel_covariances``: ``"covariance"`` (weight the fit by the
      measurement covariance R above, the generalised least squares) or ``"uniform"`` (fit with the
      ``pixel_sigmas``/``sigma_px`` weights W and report the covariance that fit has under R, the
      sandwich N⁻¹(HᵀW·R·WH + P₀⁻¹)N⁻¹, N = HᵀWH + P₀⁻¹, τ estimated from the fit's residuals:
      :func:`_sandwich_covariance`) — the estimate of uniform weights with a covariance calibrated by
      what the registration and the shading model's error patterns show (issue #39).

    Raises :class:`PoseError` for too few usable landmarks or degenerate geometry.
    """
    opts = options or PoseOptions()
    pts_all, meas_all, names = _checked_inputs(landmark_positions, measured, names)
    n_all = pts_all.shape[0]
    warnings: list[str] = []
    if estimate_weights not in ("covariance", "uniform"):
        raise SpcUsageError(f"estimate_weights must be 'covariance' or 'uniform', got {estimate_weights!r}")
    sandwich = estimate_weights == "uniform" and pixel_covariances is not None
    mode = opts.landmark_mode
    if sandwich and mode != "fixed":
        raise SpcUsageError("estimate_weights 'uniform' with pixel covariances needs landmark_mode 'fixed'")
    wts_all = _measurement_weights(
        opts, meas_all, names, pixel_sigmas, None if sandwich else pixel_covariances, warnings
    )
    lmk_sig = _landmark_sigmas(mode, landmark_sigmas, n_all)
    prior = _pose_prior(opts, prior_sigma_position, prior_sigma_attitude, warnings)
    common = _common_covariance(common_covariance, mode)
    modes_all = None if sandwich else _error_modes(common, error_modes, n_all, mode)

    # ---- usable landmarks and a-priori residuals ------------------------------------------------
    usable, pts_finite, pred0, status, rejected = usable_landmarks(camera, pts_all, meas_all, names)
    prior_used = prior.n_equations > 0
    _check_count(int(np.count_nonzero(usable)), opts, prior_used)
    lmk_info_all = None
    if mode == "estimate":
        s = np.where(lmk_sig > 0, lmk_sig, _TINY_SIGMA_KM)
        lmk_info_all = 1.0 / (s * s)

    def build(mask, wts, modes):
        return _Problem(
            camera,
            pts_all[mask],
            meas_all[mask],
            wts[mask],
            prior,
            mode,
            None if lmk_info_all is None else lmk_info_all[mask],
            opts,
            None if modes is None else modes[mask],
        )

    # ---- fit, reject, refit (with the model error the residuals show) ------------------------------
    labels = (names, status, rejected, warnings)
    fit, tau, wts_all, common_used = _fit_with_model_error(
        build, wts_all, modes_all, common, usable, opts, prior, labels,
        None if sandwich else pixel_covariances, error_modes, mode,
    )  # fmt: skip
    problem, state, iterations, converged, history, used = fit

    # ---- final linearisation: covariance, residuals -----------------------------------------------
    m = int(np.count_nonzero(used))
    cov, cond, cov_plain, lmk_corr, lmk_cov, pts_after = _final_covariance(
        problem, state, mode, used, pts_all, lmk_sig
    )
    uniform_cov = None
    if sandwich:  # the uniform fit's covariance under the calibrated measurement covariance
        base = _covariance_matrices(pixel_covariances, n_all, opts.sigma_floor_px, wts_all)
        uniform_cov = cov
        cov, tau, common_used = _sandwich_covariance(
            problem, state, cov, base[used], common, error_modes, used, opts, prior
        )
    cost, chi2 = problem.cost(state)
    # unknowns 6 (+3M landmark offsets with 3M a-priori equations in "estimate" mode: same dof)
    dof = 2 * m + prior.n_equations - 6
    red = cost / dof if dof > 0 else math.nan
    cov, cov_formal, scale, lmk_cov = _scaled_covariance(cov, lmk_cov, red, opts)
    implausible = _implausible(red, opts)
    # (the prior test reads the a-posteriori covariance of the weights the fit used: with the
    # sandwich, the uniform fit's own, as its derivation needs P = (A + P₀⁻¹)⁻¹)
    gate, prior_check = _consistency(
        problem, state, opts, dof, cost, names, used, prior,
        cov_plain if uniform_cov is None else uniform_cov, cov_formal, cov,
    )  # fmt: skip
    sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sig, sig)
    smp1, lin1, front1 = state.camera.project_with_mask(np.where(pts_finite[:, None], pts_after, 0.0))
    pred1 = np.stack([smp1, lin1], axis=-1)
    pred1[~(pts_finite & front1)] = np.nan
    resid0, resid1 = meas_all - pred0, meas_all - pred1
    if not converged:
        warnings.append(f"did not converge in {opts.max_iter} iterations")

    def rms(res):
        if m == 0:
            return math.nan
        return float(np.sqrt(np.mean(np.sum(res[used] ** 2, axis=1))))

    return PoseResult(
        scobj=state.camera.scobj.copy(),
        rotation=np.array(state.camera.rotation),
        position=state.camera.position.copy(),
        delta_position=state.dpos.copy(),
        delta_attitude=state.theta.copy(),
        covariance=cov,
        sigmas=sig,
        correlation=corr,
        condition_number=cond,
        iterations=iterations,
        converged=bool(converged),
        names=names,
        measured=meas_all.copy(),
        predicted_before=pred0,
        predicted_after=pred1,
        residuals_before=resid0,
        residuals_after=resid1,
        used=used,
        status=status,
        rejected=rejected,
        chi2=chi2,
        cost=cost,
        dof=int(dof),
        rms_before=rms(resid0),
        rms_after=rms(resid1),
        landmark_mode=mode,
        prior_used=prior_used,
        covariance_no_consider=cov_plain,
        landmark_corrections=lmk_corr,
        landmark_covariances=lmk_cov,
        cost_history=history,
        warnings=warnings,
        covariance_formal=cov_formal,
        covariance_scale=scale,
        implausible=implausible,
        gate=gate,
        prior_check=prior_check,
        prior_scale=float(opts.prior_scale) if prior_used else 1.0,
        model_error_px=float(tau),
        common_covariance=None if common_used is None else np.array(common_used, dtype=np.float64),
    )
