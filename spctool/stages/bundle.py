"""Landmark refinement — SPC's GEOMETRY step as one sparse bundle adjustment (``spctool geometry``).

Specification: map-refinement.md §1 (S16 Introduction and Fig. 3; L15 §2, the text after Eq. 2.8 and
footnotes 14–17), with the pose conventions of :mod:`spctool.stages.pose` (spc-algorithms.md §10 and
errata 1–4 of §11).  The name of this room is *bundle*: SPC's GEOMETRY command is not the
:mod:`spctool.geometry` package (camera, shapes).

Problem.  P pictures (pose p_j = −SCOBJ, body→camera rotation T_j), L landmarks (VLM V_l, km, body
frame), K measurements y_k = (sample, line) of landmark l(k) in picture j(k) with a 2×2 weight W_k
(the inverse measurement covariance).  Minimise

    Σ_k r_kᵀ W_k r_k  +  Σ_j ‖P_j^(−1/2) (χ_j − χ_j⁰)‖²  +  Σ_l ‖Σ_l^(−1/2) (V_l − V_l⁰)‖²  (+ camera priors)

with r_k = y_k − h_j(V_l) (the full SPC camera model, distortion included), χ_j = [Δp_j; θ_j] exactly as
:mod:`spctool.stages.pose` defines it (Δp body frame, km; θ camera frame, rad, T = Rot(−θ)·T⁰, the prior
residual's derivative J_r(θ)⁻¹), P_j from the SUM's SIGMA_VSO/SIGMA_PTG (INIT_LITHOS ``PICWTS=`` scale
the information), Σ_l from the LMK's SIGMA_LMK (or SIGKM; ``LMKWTS=`` scale the information).  A σ that
is zero, negative or not finite puts no prior on that component.

Jacobians (spc-algorithms.md erratum 3): with x_C = T (V − p) and J_C = ∂(sample, line)/∂x_C,
∂h/∂V = J_C T, ∂h/∂p = −J_C T, ∂h/∂δθ = J_C [x_C×].  Pictures that share intrinsics are projected
together, each observation with its own pose (one kernel pass per camera, not per picture).

Solve (``mode="joint"``, the default).  Levenberg–Marquardt on all unknowns at once.  Each landmark's
3×3 block is eliminated (Schur complement), leaving the reduced system S δx = g over the poses (6 per
picture) and the optional camera terms; S = A − B D⁻¹ Bᵀ is assembled as a sparse matrix (one sparse
product over the measurements) and solved by a sparse direct factorisation; the landmark steps follow
by back-substitution, δV_l = D_l⁻¹ (g_l − B_lᵀ δx).  ``mode="alternate"`` reproduces SPC's alternation
(every V with the poses fixed, then every pose with the V fixed, repeated): the same minimum, reached in
more iterations.

Gauge.  The data term cannot see a common translation, rotation and scale of every landmark and
camera position (7 directions, L15 footnote 14).  Only the priors fix them.  Before solving, the prior
information on these 7 directions is computed; if it is singular the problem is refused with a
:class:`BundleError` naming the free directions (never an arbitrary solution).  The gauge's 1σ implied by
the priors is reported.

Per landmark.  At least ``min_pictures`` usable measurements from pictures that constrain V, and a
parallax (angular spread of the lines of sight, 2·asin √(1 − λ₁) of their scatter matrix, the angle
between them for two pictures) of at least ``min_parallax_deg``; otherwise V keeps its prior, is held
fixed in the solve (its measurements still constrain the poses) and is reported ``undetermined``.
Pictures marked "ignore in Vlm" do not constrain any V: they are left out of the joint solve and their
poses solved afterwards against the refined landmarks, held fixed.

Outliers.  After a fit, a measurement whose normalised residual ρ_k = ‖W_k^(1/2) r_k‖ exceeds
``reject_sigma`` × c, with c = max(1, median(ρ)/√(2 ln 2)) the robust scale of :mod:`spctool.stages.pose`,
is flagged — at most one per landmark per round (the worst), so that one bad measurement cannot take
its landmark's good ones with it — and the problem is refitted, until no measurement is above the
threshold.  Every flag is reported.

Covariance.  The inverse of the (undamped) normal matrix at the solution: pose blocks of S⁻¹, landmark
blocks D_l⁻¹ + D_l⁻¹ B_lᵀ S⁻¹ B_l D_l⁻¹ (``covariance="full"``).  For very large problems
(``covariance="auto"`` above ``max_dense_reduced`` reduced unknowns) the landmark blocks are the
conditional ones, D_l⁻¹ (poses held at their solution), and the result says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from spctool.errors import SpcResultError, SpcUsageError
from spctool.geometry.frames import rot_from_rotvec, rotvec_from_rot, skew
from spctool.stages._bundle_linalg import (
    PairStructure,
    ReducedSystem,
    ReducedSystemError,
    block_diag3,
    inv3,
    landmark_covariances,
    sum_blocks,
)

__all__ = [
    "BUNDLE_MODES",
    "CAMERA_TERMS",
    "BundleError",
    "BundleOptions",
    "BundleProblem",
    "BundleResult",
    "solve_bundle",
    "so3_right_jacobian_inv_batch",
]

BUNDLE_MODES = ("joint", "alternate")
#: camera terms ``estimate_camera`` may free (L15 §1.1.1: K_x fixed and K_xy = 0 for observability)
CAMERA_TERMS = ("focal", "ctr", "ky", "kyx", "owen")
_RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))
#: information given to an undetermined landmark's V (held at its prior), relative to its data
_HOLD = 1e12


class BundleError(SpcResultError):
    """The bundle adjustment cannot be solved as asked (free gauge, nothing to solve): exit code 1."""


@dataclass
class BundleOptions:
    """Settings of :func:`solve_bundle`.

    * ``mode`` — ``"joint"`` (sparse Levenberg–Marquardt on every unknown) or ``"alternate"`` (SPC's
      alternation: landmarks with poses fixed, then poses with landmarks fixed).
    * ``max_iter`` / ``tol`` — iterations and the convergence tolerance (relative cost change, or the
      largest step component in units of its own 1σ).
    * ``reject_outliers``, ``reject_sigma`` (k of the k·c test, 5 as ``solve-pose``), ``robust_scale``,
      ``max_reject_rounds``.
    * ``min_pictures``, ``min_parallax_deg`` — what a landmark needs to be determined.
    * ``estimate_camera`` — camera terms solved as global unknowns per distinct camera
      (:data:`CAMERA_TERMS`), with ``camera_sigma`` an optional prior 1σ (a relative one for ``focal``,
      ``ky``, ``kyx``; pixels for ``ctr``; absolute for ``owen``); None = no prior.
    * ``covariance`` — ``"full"``, ``"conditional"`` or ``"auto"`` (full up to ``max_dense_reduced``
      reduced unknowns).
    """

    mode: str = "joint"
    max_iter: int = 30
    tol: float = 1e-10
    reject_outliers: bool = True
    reject_sigma: float = 5.0
    robust_scale: bool = True
    max_reject_rounds: int = 10
    min_pictures: int = 2
    min_parallax_deg: float = 1.0
    estimate_camera: tuple[str, ...] = ()
    camera_sigma: float | None = None
    covariance: str = "auto"
    max_dense_reduced: int = 4000

    def __post_init__(self):
        if self.mode not in BUNDLE_MODES:
            raise SpcUsageError(f"bundle mode must be one of {', '.join(BUNDLE_MODES)}, got {self.mode!r}")
        bad = [t for t in self.estimate_camera if t not in CAMERA_TERMS]
        if bad:
            if any(t in ("kx", "kxy") for t in bad):
                raise SpcUsageError(
                    "K_x and K_xy cannot be estimated: L15 §1.1.1 fixes K_x and K_xy = 0 (with the focal "
                    "length they are not observable); free 'focal', 'ky' or 'kyx' instead"
                )
            raise SpcUsageError(f"unknown camera term(s) {bad}: choose among {', '.join(CAMERA_TERMS)}")
        self.estimate_camera = tuple(dict.fromkeys(self.estimate_camera))
        if self.covariance not in ("full", "conditional", "auto"):
            raise SpcUsageError(f"covariance must be full, conditional or auto, got {self.covariance!r}")
        if not self.reject_sigma > 0:
            raise SpcUsageError(f"reject_sigma must be positive, got {self.reject_sigma}")

    def as_dict(self) -> dict:
        from dataclasses import asdict

        d = asdict(self)
        d["estimate_camera"] = list(self.estimate_camera)
        return d


@dataclass
class BundleProblem:
    """The measurements and priors of one bundle adjustment (arrays; no files).

    * ``cameras`` — one :class:`spctool.geometry.camera.Camera` per picture (the a-priori pose);
      ``picture_names``.
    * ``sigma_position`` (P, 3) km, body frame; ``sigma_attitude`` (P, 3) rad, camera frame.
    * ``landmark_names``, ``landmark_positions`` (L, 3) km, ``landmark_sigmas`` (L, 3) km.
    * ``obs_picture``, ``obs_landmark`` (K,) indices; ``obs_pixel`` (K, 2) measured (sample, line);
      ``obs_weight`` (K, 2, 2) inverse covariance (px⁻²); ``obs_use`` (K,) False = flagged on input (a
      ``*`` row): never used, its residual still reported.
    * ``vlm_pictures`` (P,) False = the picture does not constrain V ("ignore image in Vlm").
    """

    cameras: list
    picture_names: list[str]
    sigma_position: np.ndarray
    sigma_attitude: np.ndarray
    landmark_names: list[str]
    landmark_positions: np.ndarray
    landmark_sigmas: np.ndarray
    obs_picture: np.ndarray
    obs_landmark: np.ndarray
    obs_pixel: np.ndarray
    obs_weight: np.ndarray
    obs_use: np.ndarray | None = None
    vlm_pictures: np.ndarray | None = None

    def __post_init__(self):
        p, n_l = len(self.cameras), len(self.landmark_names)
        self.picture_names = list(self.picture_names)
        self.landmark_names = list(self.landmark_names)
        if len(self.picture_names) != p:
            raise SpcUsageError(f"{len(self.picture_names)} picture names for {p} cameras")
        self.sigma_position = _shaped(self.sigma_position, (p, 3), "sigma_position")
        self.sigma_attitude = _shaped(self.sigma_attitude, (p, 3), "sigma_attitude")
        self.landmark_positions = _shaped(self.landmark_positions, (n_l, 3), "landmark_positions")
        self.landmark_sigmas = _shaped(self.landmark_sigmas, (n_l, 3), "landmark_sigmas")
        self.obs_picture = np.asarray(self.obs_picture, dtype=np.int64).reshape(-1)
        k = self.obs_picture.size
        self.obs_landmark = np.asarray(self.obs_landmark, dtype=np.int64).reshape(-1)
        self.obs_pixel = _shaped(self.obs_pixel, (k, 2), "obs_pixel")
        self.obs_weight = _shaped(self.obs_weight, (k, 2, 2), "obs_weight")
        self.obs_use = np.ones(k, bool) if self.obs_use is None else np.asarray(self.obs_use, bool).reshape(k)
        self.vlm_pictures = (
            np.ones(p, bool) if self.vlm_pictures is None else np.asarray(self.vlm_pictures, bool).reshape(p)
        )
        if self.obs_landmark.size != k:
            raise SpcUsageError("obs_picture and obs_landmark differ in length")
        if k and (self.obs_picture.min() < 0 or self.obs_picture.max() >= p):
            raise SpcUsageError("a measurement names a picture index out of range")
        if k and (self.obs_landmark.min() < 0 or self.obs_landmark.max() >= n_l):
            raise SpcUsageError("a measurement names a landmark index out of range")
        if not np.all(np.isfinite(self.landmark_positions)):
            raise SpcUsageError("a landmark position is not finite")
        finite = np.all(np.isfinite(self.obs_pixel), axis=1) & np.all(
            np.isfinite(self.obs_weight), axis=(1, 2)
        )
        self.obs_use &= finite


def _shaped(a, shape, what) -> np.ndarray:
    arr = np.array(a, dtype=np.float64)
    if arr.shape != shape:
        raise SpcUsageError(f"{what} must have shape {shape}, got {arr.shape}")
    return arr


@dataclass
class BundleResult:
    """What :func:`solve_bundle` found (every array in the problem's order).

    ``obs_status`` per measurement: ``ok``, ``outlier`` (flagged here), ``flagged`` (a ``*`` on input),
    ``ignored-in-vlm`` (its picture does not constrain V; used for that picture's pose),
    ``undetermined`` (its landmark kept its prior).  ``landmark_status``: ``ok``, ``undetermined``
    (fewer than ``min_pictures`` usable pictures or too little parallax: V kept), ``unobserved``.
    Residuals are measured − predicted (px); ``rho`` the normalised residual ‖W^(1/2) r‖.
    """

    picture_names: list[str]
    landmark_names: list[str]
    cameras: list
    positions0: np.ndarray  # (P, 3) a-priori spacecraft positions (km, body)
    positions: np.ndarray  # (P, 3) solved
    rotations: np.ndarray  # (P, 3, 3) solved body→camera
    delta_position: np.ndarray  # (P, 3) km
    delta_attitude: np.ndarray  # (P, 3) rad (θ, camera frame)
    pose_covariance: np.ndarray  # (P, 6, 6) [Δp, θ]
    landmark_positions0: np.ndarray  # (L, 3)
    landmark_positions: np.ndarray  # (L, 3)
    landmark_covariance: np.ndarray  # (L, 3, 3) km²
    landmark_status: list[str]
    landmark_parallax_deg: np.ndarray
    obs_status: list[str]
    residual_before: np.ndarray  # (K, 2)
    residual_after: np.ndarray  # (K, 2)
    rho_after: np.ndarray  # (K,)
    camera_terms: dict = field(default_factory=dict)  # per camera group: {term: (before, after, sigma)}
    covariance_kind: str = "full"
    iterations: int = 0
    converged: bool = False
    cost_history: list = field(default_factory=list)
    chi2: float = math.nan
    dof: int = 0
    gauge_sigma: dict = field(default_factory=dict)
    outlier_rounds: int = 0
    warnings: list[str] = field(default_factory=list)
    mode: str = "joint"
    timing: dict = field(default_factory=dict)

    @property
    def landmark_sigmas(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diagonal(self.landmark_covariance, axis1=1, axis2=2), 0.0))

    @property
    def pose_sigmas(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diagonal(self.pose_covariance, axis1=1, axis2=2), 0.0))

    @property
    def reduced_chi2(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else math.nan

    def landmark_rms_px(self) -> np.ndarray:
        """Post-fit rms residual (px, per axis) over each landmark's used measurements (NaN if none)."""
        used = np.array([s == "ok" for s in self.obs_status])
        return _group_rms(self.residual_after, self._obs_landmark, used, len(self.landmark_names))

    def picture_rms_px(self) -> np.ndarray:
        used = np.array([s in ("ok", "ignored-in-vlm") for s in self.obs_status])
        return _group_rms(self.residual_after, self._obs_picture, used, len(self.picture_names))

    _obs_picture: np.ndarray = field(default=None, repr=False)
    _obs_landmark: np.ndarray = field(default=None, repr=False)

    def counts(self) -> dict:
        out: dict = {}
        for s in self.obs_status:
            out[s] = out.get(s, 0) + 1
        return out


def _group_rms(res, idx, used, n) -> np.ndarray:
    sq = np.where(used, np.sum(res * res, axis=1) / 2.0, 0.0)
    tot = np.bincount(idx, weights=sq, minlength=n)
    cnt = np.bincount(idx, weights=used.astype(float), minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, np.sqrt(tot / np.maximum(cnt, 1)), np.nan)


# ------------------------------------------------------------------------------------------------
# rotations, vectorised over pictures


def so3_right_jacobian_inv_batch(theta) -> np.ndarray:
    """J_r(θ)⁻¹ (…, 3, 3) for rotation vectors (…, 3): :func:`spctool.stages.pose.so3_right_jacobian_inv`
    vectorised (series below 1e-4 rad)."""
    th = np.asarray(theta, dtype=np.float64)
    t2 = np.sum(th * th, axis=-1)
    t = np.sqrt(t2)
    small = t < 1e-4
    ts = np.where(small, 1.0, t)
    c = np.where(
        small, 1.0 / 12.0 + t2 / 720.0, 1.0 / (ts * ts) - (1.0 + np.cos(ts)) / (2.0 * ts * np.sin(ts))
    )
    k = skew(th)
    return np.eye(3) + 0.5 * k + c[..., None, None] * (k @ k)


# ------------------------------------------------------------------------------------------------
# camera terms


def _camera_term_slots(camera, terms) -> list[tuple[str, int]]:
    """(term label, index into the packed camera vector) of the freed camera terms."""
    out = []
    for t in terms:
        if t == "focal":
            out.append(("focal", 0))
        elif t == "ctr":
            out += [("ctr_sample", 1), ("ctr_line", 2)]
        elif t == "ky":
            out.append(("ky", 7))
        elif t == "kyx":
            out.append(("kyx", 6))
        elif t == "owen":
            if camera.model != "OWEN":
                raise SpcUsageError(
                    f"camera of picture {camera.name or '?'} has distortion model {camera.model}: "
                    "'owen' terms need an INIT_LITHOS DISTORT= OWEN model"
                )
            out += [(f"owen_p{i}", 13 + i) for i in range(camera.coefficients.size)]
    return out


def _packed(camera) -> np.ndarray:
    """mmfl, ctr(2), kmatrix(6), legacy_d(4), coefficients — the vector the camera terms index."""
    return np.concatenate(
        [[camera.mmfl], camera.ctr, camera.kmatrix.reshape(6), camera.legacy_d, camera.coefficients]
    )


def _with_packed(camera, q) -> object:
    n = camera.coefficients.size
    return replace(
        camera,
        mmfl=float(q[0]),
        ctr=q[1:3].copy(),
        kmatrix=q[3:9].reshape(2, 3).copy(),
        legacy_d=q[9:13].copy(),
        coefficients=q[13 : 13 + n].copy(),
    )


def _term_scale(camera, idx) -> float:
    """Typical size of a camera term, for finite-difference steps and relative priors."""
    q = _packed(camera)
    if idx in (1, 2):
        return 1.0  # pixels
    v = abs(q[idx])
    return v if v > 0 else 1e-3


# ------------------------------------------------------------------------------------------------
# the linearised problem


class _Lin:
    """Residuals and Jacobians of every used measurement at one state."""

    __slots__ = ("r", "jv", "jx", "jc", "chi2")


class _Bundle:
    def __init__(self, prob: BundleProblem, opts: BundleOptions):
        self.prob, self.opts = prob, opts
        cams = prob.cameras
        self.n_pic = len(cams)
        self.n_lmk = len(prob.landmark_names)
        self.p0 = np.array([c.position for c in cams], dtype=np.float64).reshape(-1, 3)
        self.t0 = np.array([c.rotation for c in cams], dtype=np.float64).reshape(-1, 3, 3)
        self.v0 = prob.landmark_positions.copy()
        # camera groups (same intrinsics): one kernel pass per group
        keys: dict = {}
        self.group = np.array([keys.setdefault(c.intrinsics_key, len(keys)) for c in cams], dtype=np.int64)
        self.group_camera = [None] * len(keys)
        for j, g in enumerate(self.group):
            if self.group_camera[g] is None:
                self.group_camera[g] = cams[j]
        # camera terms
        self.slots = [_camera_term_slots(c, opts.estimate_camera) for c in self.group_camera]
        self.nc = len(self.slots[0]) if self.slots else 0
        if any(len(s) != self.nc for s in self.slots):
            raise SpcUsageError(
                "the cameras free different numbers of terms (OWEN coefficient counts differ)"
            )
        self.q0 = [_packed(c) for c in self.group_camera]
        # priors (information, 0 = none)
        self.info_pos = _information(prob.sigma_position)
        self.info_att = _information(prob.sigma_attitude)
        self.info_lmk = _information(prob.landmark_sigmas)
        self.info_cam = np.zeros((len(self.group_camera), self.nc))
        if opts.camera_sigma is not None and self.nc:
            for g, cam in enumerate(self.group_camera):
                for i, (_, idx) in enumerate(self.slots[g]):
                    s = opts.camera_sigma * _term_scale(cam, idx)
                    self.info_cam[g, i] = 1.0 / (s * s)
        self.n_red = 6 * self.n_pic + self.nc * len(self.group_camera)
        self._pairs = None
        #: per-measurement weight factor (1, or the robust pre-pass's Cauchy factor)
        self.robust = np.ones(prob.obs_picture.size)

    # -- state -------------------------------------------------------------------------------------
    def start(self):
        q = np.array(self.q0, dtype=np.float64).reshape(len(self.group_camera), -1)
        return {"pos": self.p0.copy(), "rot": self.t0.copy(), "v": self.v0.copy(), "q": q}

    def theta(self, s) -> np.ndarray:
        return -rotvec_from_rot(s["rot"] @ np.swapaxes(self.t0, 1, 2))

    def group_cameras(self, s) -> list:
        if not self.nc:
            return self.group_camera
        return [_with_packed(c, s["q"][g]) for g, c in enumerate(self.group_camera)]

    def moved(self, s, dx, dv) -> dict:
        dxp = dx[: 6 * self.n_pic].reshape(-1, 6)
        rot = rot_from_rotvec(-dxp[:, 3:]) @ s["rot"]
        u, _, vt = np.linalg.svd(rot)  # re-orthonormalise (polar factor)
        rot = u @ vt
        q = s["q"].copy()
        if self.nc:
            dc = dx[6 * self.n_pic :].reshape(len(self.group_camera), self.nc)
            for g in range(len(self.group_camera)):
                for i, (_, idx) in enumerate(self.slots[g]):
                    q[g, idx] += dc[g, i]
        return {"pos": s["pos"] + dxp[:, :3], "rot": rot, "v": s["v"] + dv, "q": q}

    # -- projection ----------------------------------------------------------------------------------
    def project(self, s, k_idx, jacobians: bool):
        """Predicted pixels (and ∂/∂x_C, x_C) of measurements ``k_idx``."""
        prob = self.prob
        pj = prob.obs_picture[k_idx]
        lv = prob.obs_landmark[k_idx]
        rot = s["rot"][pj]
        zc = np.einsum("kij,kj->ki", rot, s["v"][lv] - s["pos"][pj])
        pred = np.empty((k_idx.size, 2))
        jc = np.empty((k_idx.size, 2, 3)) if jacobians else None
        cams = self.group_cameras(s)
        g_of = self.group[pj]
        for g, cam in enumerate(cams):
            sel = np.flatnonzero(g_of == g) if len(cams) > 1 else slice(None)
            if jacobians:
                a, b, j = cam.project_camera_frame_with_jacobian(zc[sel])
                jc[sel] = j
            else:
                a, b = cam.project_camera_frame(zc[sel])
            pred[sel, 0] = a
            pred[sel, 1] = b
        return pred, zc, jc, rot, cams, g_of

    def camera_jacobian(self, cams, g_of, zc) -> np.ndarray:
        """∂(sample, line)/∂(freed camera terms) (K, 2, nc) by central differences of the projection
        (linear in CTR; smooth in the others: the step's truncation error is below 1e-12 px)."""
        out = np.zeros((zc.shape[0], 2, self.nc))
        for g, cam in enumerate(cams):
            sel = np.flatnonzero(g_of == g)
            if sel.size == 0:
                continue
            q = _packed(cam)
            for i, (_, idx) in enumerate(self.slots[g]):
                h = 1e-6 * _term_scale(cam, idx)
                qp, qm = q.copy(), q.copy()
                qp[idx] += h
                qm[idx] -= h
                sp_, lp = _with_packed(cam, qp).project_camera_frame(zc[sel])
                sm, lm = _with_packed(cam, qm).project_camera_frame(zc[sel])
                out[sel, 0, i] = (sp_ - sm) / (2 * h)
                out[sel, 1, i] = (lp - lm) / (2 * h)
        return out

    def residuals(self, s, k_idx) -> np.ndarray:
        pred = self.project(s, k_idx, False)[0]
        return self.prob.obs_pixel[k_idx] - pred

    def weights(self, k_idx) -> np.ndarray:
        return self.prob.obs_weight[k_idx] * self.robust[k_idx, None, None]

    def cost(self, s, k_idx, hold) -> float:
        r = self.residuals(s, k_idx)
        w = self.weights(k_idx)
        chi2 = float(np.einsum("ki,kij,kj->", r, w, r))
        return chi2 + self.prior_cost(s, hold)

    def prior_cost(self, s, hold) -> float:
        dp = s["pos"] - self.p0
        th = self.theta(s)
        dv = s["v"] - self.v0
        c = float(np.sum(self.info_pos * dp * dp) + np.sum(self.info_att * th * th))
        c += float(np.sum(self.info_lmk[~hold] * dv[~hold] ** 2))
        if self.nc:
            dq = np.array(
                [
                    [s["q"][g, idx] - self.q0[g][idx] for _, idx in self.slots[g]]
                    for g in range(len(self.slots))
                ]
            )
            c += float(np.sum(self.info_cam * dq * dq))
        return c

    def linearise(self, s, k_idx):
        lin = _Lin()
        pred, zc, jc, rot, cams, g_of = self.project(s, k_idx, True)
        lin.r = self.prob.obs_pixel[k_idx] - pred
        lin.jv = jc @ rot  # ∂/∂V
        lin.jx = np.concatenate([-lin.jv, jc @ skew(zc)], axis=2)  # ∂/∂(p, δθ)
        lin.jc = self.camera_jacobian(cams, g_of, zc) if self.nc else None
        return lin

    # -- normal equations ------------------------------------------------------------------------
    def normal(self, s, k_idx, hold, lin):
        """Blocks of the normal equations: pose (P, 6, 6) and rhs, landmark (L, 3, 3) and rhs, cross
        terms (K, 6, 3) per measurement, camera blocks."""
        prob = self.prob
        w = self.weights(k_idx)
        pj = prob.obs_picture[k_idx]
        lv = prob.obs_landmark[k_idx]
        wjx = w @ lin.jx  # (K, 2, 6)
        wjv = w @ lin.jv
        n_p, n_l = self.n_pic, self.n_lmk
        a = sum_blocks(np.einsum("kai,kaj->kij", lin.jx, wjx), pj, n_p)
        ga = sum_blocks(np.einsum("kai,ka->ki", wjx, lin.r), pj, n_p)
        d = sum_blocks(np.einsum("kai,kaj->kij", lin.jv, wjv), lv, n_l)
        gd = sum_blocks(np.einsum("kai,ka->ki", wjv, lin.r), lv, n_l)
        b = np.einsum("kai,kaj->kij", wjx, lin.jv)  # (K, 6, 3)
        # priors
        jr = so3_right_jacobian_inv_batch(self.theta(s))  # (P, 3, 3)
        th = self.theta(s)
        dp = s["pos"] - self.p0
        idx3 = np.arange(3)
        a[:, idx3, idx3] += self.info_pos
        ga[:, :3] -= self.info_pos * dp
        jpi = np.swapaxes(jr, 1, 2) * self.info_att[:, None, :]  # Jᵀ·P⁻¹
        a[:, 3:, 3:] += jpi @ jr
        ga[:, 3:] -= np.einsum("pij,pj->pi", jpi, th)
        info_l = np.where(hold[:, None], 0.0, self.info_lmk)
        d[:, idx3, idx3] += info_l
        gd -= info_l * (s["v"] - self.v0)
        # held landmarks: V fixed (a large diagonal, no step)
        if hold.any():
            scale = np.maximum(np.trace(d[hold], axis1=1, axis2=2) / 3.0, 1.0)
            d[hold] += (_HOLD * scale)[:, None, None] * np.eye(3)
            gd[hold] = 0.0
        cam = None
        if self.nc:
            cam = self.camera_blocks(s, lin, w, wjx, wjv, pj, lv)
        return a, ga, d, gd, b, cam

    def camera_blocks(self, s, lin, w, wjx, wjv, pj, lv):
        ng, nc = len(self.group_camera), self.nc
        g_of = self.group[pj]
        wjc = w @ lin.jc  # (K, 2, nc)
        cc = np.zeros((ng, nc, nc))
        gc = np.zeros((ng, nc))
        np.add.at(cc, g_of, np.einsum("kai,kaj->kij", lin.jc, wjc))
        np.add.at(gc, g_of, np.einsum("kai,ka->ki", wjc, lin.r))
        dq = np.array([[s["q"][g, idx] - self.q0[g][idx] for _, idx in self.slots[g]] for g in range(ng)])
        cc[:, np.arange(nc), np.arange(nc)] += self.info_cam
        gc -= self.info_cam * dq
        xc = np.einsum("kai,kaj->kij", wjx, lin.jc)  # pose × camera (K, 6, nc)
        vc = np.einsum("kai,kaj->kij", wjc, lin.jv)  # camera × landmark (K, nc, 3)
        return cc, gc, xc, vc

    def reduced(self, k_idx, blocks, damping):
        """The Schur complement S (sparse CSR, n_red²) and its right-hand side, the damped D⁻¹ (L, 3, 3),
        and the sparse cross-term matrix B (n_red × 3L)."""
        a, ga, d, gd, b, cam = blocks
        prob = self.prob
        pj = prob.obs_picture[k_idx]
        lv = prob.obs_landmark[k_idx]
        n_p, n_l, nc = self.n_pic, self.n_lmk, self.nc
        a = a.copy()
        d = d.copy()
        i6, i3 = np.arange(6), np.arange(3)
        a[:, i6, i6] *= 1.0 + damping
        d[:, i3, i3] *= 1.0 + damping
        dinv = inv3(d)
        # B: rows = reduced unknowns, cols = landmark unknowns
        rows = (6 * pj)[:, None, None] + i6[None, :, None] + 0 * i3[None, None, :]
        cols = (3 * lv)[:, None, None] + i3[None, None, :] + 0 * i6[None, :, None]
        rr, cc_, vv = [rows.ravel()], [cols.ravel()], [b.ravel()]
        # A: block diagonal over pictures (+ camera blocks)
        ar = (6 * np.arange(n_p))[:, None, None] + i6[None, :, None] + 0 * i6[None, None, :]
        ac = (6 * np.arange(n_p))[:, None, None] + i6[None, None, :] + 0 * i6[None, :, None]
        arow, acol, aval = [ar.ravel()], [ac.ravel()], [a.ravel()]
        g = np.concatenate([ga.reshape(-1), np.zeros(self.n_red - 6 * n_p)])
        if nc:
            ccm, gc, xc, vc = cam
            ng = ccm.shape[0]
            inc = np.arange(nc)
            base = 6 * n_p + nc * np.arange(ng)
            ccm = ccm.copy()
            ccm[:, inc, inc] *= 1.0 + damping
            arow.append((base[:, None, None] + inc[None, :, None] + 0 * inc[None, None, :]).ravel())
            acol.append((base[:, None, None] + inc[None, None, :] + 0 * inc[None, :, None]).ravel())
            aval.append(ccm.ravel())
            gk = self.group[pj]
            cb = base[gk]
            # pose × camera, both triangles
            r1 = (6 * pj)[:, None, None] + i6[None, :, None] + 0 * inc[None, None, :]
            c1 = cb[:, None, None] + inc[None, None, :] + 0 * i6[None, :, None]
            arow += [r1.ravel(), c1.ravel()]
            acol += [c1.ravel(), r1.ravel()]
            aval += [xc.ravel(), xc.ravel()]
            # camera × landmark in B
            r2 = cb[:, None, None] + inc[None, :, None] + 0 * i3[None, None, :]
            c2 = (3 * lv)[:, None, None] + i3[None, None, :] + 0 * inc[None, :, None]
            rr.append(r2.ravel())
            cc_.append(c2.ravel())
            vv.append(vc.ravel())
            g[6 * n_p :] = gc.reshape(-1)
        amat = sp.csr_matrix(
            (np.concatenate(aval), (np.concatenate(arow), np.concatenate(acol))),
            shape=(self.n_red, self.n_red),
        )
        bmat = sp.csr_matrix(
            (np.concatenate(vv), (np.concatenate(rr), np.concatenate(cc_))), shape=(self.n_red, 3 * n_l)
        )
        dmat = block_diag3(dinv)
        e = bmat @ dmat  # B D⁻¹
        s_mat = (amat - e @ bmat.T).tocsc()
        rhs = g - e @ gd.reshape(-1)
        return s_mat, rhs, dinv, bmat, gd

    def pairs(self, k_idx) -> PairStructure:
        """The pair structure of measurements ``k_idx`` (kept while the used set does not change)."""
        key = (k_idx.size, hash(k_idx.tobytes()))
        if self._pairs is None or self._pairs[0] != key:
            prob = self.prob
            self._pairs = (
                key,
                PairStructure(prob.obs_picture[k_idx], prob.obs_landmark[k_idx], self.n_pic, self.n_lmk),
            )
        return self._pairs[1]

    def step(self, s, k_idx, blocks, damping):
        """(δx, δV) of one damped Gauss–Newton step."""
        if self.nc:
            s_mat, rhs, dinv, bmat, gd = self.reduced(k_idx, blocks, damping)
            dx = _solve_spd(s_mat, rhs)
            dv = np.einsum("lij,lj->li", dinv, gd - (bmat.T @ dx).reshape(-1, 3))
            return dx, dv
        red, dinv, rhs = self.reduced_poses(k_idx, blocks, damping)
        dx = red.solve(rhs)
        return dx, self.back_substitute(k_idx, blocks, dinv, dx)

    def reduced_poses(self, k_idx, blocks, damping):
        """The factorised pose system (no camera terms), D⁻¹ and the reduced right-hand side."""
        a, ga, d, gd, b, _ = blocks
        prob = self.prob
        pj, lv = prob.obs_picture[k_idx], prob.obs_landmark[k_idx]
        a = a.copy()
        d = d.copy()
        a[:, np.arange(6), np.arange(6)] *= 1.0 + damping
        d[:, np.arange(3), np.arange(3)] *= 1.0 + damping
        dinv = inv3(d)
        try:
            red = ReducedSystem.assemble(self.pairs(k_idx), pj, lv, a, b, dinv)
        except ReducedSystemError as exc:
            raise BundleError(str(exc)) from None
        gk = np.einsum("kij,kjl,kl->ki", b, dinv[lv], gd[lv])  # G_k g_V
        rhs = ga.reshape(-1) - sum_blocks(gk, pj, self.n_pic).reshape(-1)
        return red, dinv, rhs

    def back_substitute(self, k_idx, blocks, dinv, dx) -> np.ndarray:
        """δV_l = D_l⁻¹ (g_l − Σ_k B_kᵀ δx_p(k))."""
        b, gd = blocks[4], blocks[3]
        prob = self.prob
        pj, lv = prob.obs_picture[k_idx], prob.obs_landmark[k_idx]
        btx = np.einsum("kji,kj->ki", b, dx.reshape(-1, 6)[pj])
        return np.einsum("lij,lj->li", dinv, gd - sum_blocks(btx, lv, self.n_lmk))


def _information(sig) -> np.ndarray:
    s = np.asarray(sig, dtype=np.float64)
    ok = np.isfinite(s) & (s > 0)
    out = np.zeros_like(s)
    out[ok] = 1.0 / (s[ok] * s[ok])
    return out


def _solve_spd(s_mat, rhs) -> np.ndarray:
    """Solve the (symmetric positive-definite) reduced system; dense for small systems."""
    n = s_mat.shape[0]
    if n == 0:
        return np.zeros(0)
    if n <= 600:
        m = s_mat.toarray()
        m = 0.5 * (m + m.T)
        try:
            c = np.linalg.cholesky(m)
        except np.linalg.LinAlgError:
            raise BundleError(
                "the reduced normal matrix is not positive definite: the poses are not determined "
                "(too few landmarks per picture, or no prior)"
            ) from None
        y = np.linalg.solve(c, rhs)
        return np.linalg.solve(c.T, y)
    sym = 0.5 * (s_mat + s_mat.T)
    diag = sym.diagonal()
    if np.any(diag <= 0):
        raise BundleError("the reduced normal matrix has a zero diagonal: a picture has no information")
    sc = sp.diags(1.0 / np.sqrt(diag))
    m = (sc @ sym @ sc).tocsc()
    try:
        lu = spla.splu(m, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError as exc:
        raise BundleError(
            f"the reduced normal matrix is singular ({exc}): the poses are not determined"
        ) from None
    return sc @ lu.solve(sc @ rhs)


# ------------------------------------------------------------------------------------------------
# gauge, determinacy


def gauge_information(bundle: _Bundle, s) -> np.ndarray:
    """The priors' information (7×7) on the gauge directions: translation (km), rotation (rad about the
    body axes) and scale (relative), each applied to every camera position and landmark."""
    pos = s["pos"]
    v = s["v"]
    rows = []
    infos = []
    eye = np.broadcast_to(np.eye(3), (pos.shape[0], 3, 3))
    zeros = np.zeros((pos.shape[0], 3, 1))
    # camera positions: δp = t + ω×p + σ p
    rows.append(np.concatenate([eye, -skew(pos), pos[:, :, None]], axis=2))
    infos.append(bundle.info_pos)
    # camera attitudes: θ = T ω (camera frame), no translation or scale
    rows.append(np.concatenate([np.zeros_like(eye), s["rot"], zeros], axis=2))
    infos.append(bundle.info_att)
    # every landmark's prior (a held landmark is held at it: its prior is what fixes it)
    el = np.broadcast_to(np.eye(3), (v.shape[0], 3, 3))
    rows.append(np.concatenate([el, -skew(v), v[:, :, None]], axis=2))
    infos.append(bundle.info_lmk)
    m = np.zeros((7, 7))
    for g, i in zip(rows, infos):
        m += np.einsum("nai,na,naj->ij", g, i, g)
    return m


def _gauge_check(bundle: _Bundle, s, hold) -> dict:
    m = gauge_information(bundle, s)
    radius = float(max(np.max(np.linalg.norm(s["pos"], axis=1), initial=0.0), 1e-6))
    # km-equivalent units: a rotation or a scale change moves points at ``radius`` by radius·angle
    u = np.diag([1.0, 1.0, 1.0, 1 / radius, 1 / radius, 1 / radius, 1 / radius])
    mu = u @ m @ u
    ev, vec = np.linalg.eigh(mu)
    names = [
        "translation x",
        "translation y",
        "translation z",
        "rotation x",
        "rotation y",
        "rotation z",
        "scale",
    ]
    # a direction is free when the priors give it no information, or a 1σ beyond 10⁶ body radii
    weak = (
        ~np.isfinite(ev) | (ev <= 1e-12 * max(float(np.max(ev)), 1e-300)) | (ev * (1e6 * radius) ** 2 < 1.0)
    )
    if weak.any():
        free = sorted({names[int(np.argmax(np.abs(vec[:, i])))] for i in np.flatnonzero(weak)})
        raise BundleError(
            "the gauge is not fixed: the priors leave " + ", ".join(free) + " of the whole solution free "
            "(give SIGMA_VSO/SIGMA_PTG on the pictures or SIGMA_LMK on the landmarks); refusing an "
            "arbitrary solution"
        )
    with np.errstate(divide="ignore", invalid="ignore"):
        cov = np.linalg.inv(m)
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return {
        "translation_km": [float(x) for x in sig[:3]],
        "rotation_rad": [float(x) for x in sig[3:6]],
        "scale": float(sig[6]),
    }


def _parallax(bundle: _Bundle, s, k_idx) -> tuple[np.ndarray, np.ndarray]:
    """(count, parallax in degrees) per landmark over measurements ``k_idx``."""
    prob = bundle.prob
    pj = prob.obs_picture[k_idx]
    lv = prob.obs_landmark[k_idx]
    los = s["v"][lv] - s["pos"][pj]
    los /= np.linalg.norm(los, axis=1, keepdims=True)
    n = bundle.n_lmk
    cnt = np.bincount(lv, minlength=n).astype(float)
    scat = sum_blocks(los[:, :, None] * los[:, None, :], lv, n)
    with np.errstate(invalid="ignore", divide="ignore"):
        scat /= np.maximum(cnt, 1)[:, None, None]
    lam1 = np.linalg.eigvalsh(scat)[:, -1] if n else np.zeros(0)
    par = np.degrees(2.0 * np.arcsin(np.sqrt(np.clip(1.0 - lam1, 0.0, 1.0))))
    return cnt, np.where(cnt >= 2, par, 0.0)


# ------------------------------------------------------------------------------------------------
# solvers


def _fit_joint(bundle: _Bundle, s, k_idx, hold, opts, stats) -> tuple[dict, bool]:
    cost = bundle.cost(s, k_idx, hold)
    history = stats.setdefault("cost", [])
    history.append(cost)
    damping = 1e-6
    converged = False
    for _ in range(opts.max_iter):
        stats["iterations"] = stats.get("iterations", 0) + 1
        lin = bundle.linearise(s, k_idx)
        blocks = bundle.normal(s, k_idx, hold, lin)
        accepted = False
        for _try in range(12):
            dx, dv = bundle.step(s, k_idx, blocks, damping)
            trial = bundle.moved(s, dx, dv)
            c_new = bundle.cost(trial, k_idx, hold)
            if np.isfinite(c_new) and c_new <= cost * (1.0 + 1e-13) + 1e-300:
                accepted = True
                break
            damping = max(damping * 10.0, 1e-4)
        if not accepted:
            converged = True  # no decrease possible: the numerical floor
            break
        rel = abs(cost - c_new) / cost if cost > 0 else 0.0
        step_small = (
            float(np.max(np.abs(dx), initial=0.0)) < 1e-13 and float(np.max(np.abs(dv), initial=0.0)) < 1e-13
        )
        s, cost = trial, c_new
        history.append(cost)
        damping = max(damping / 10.0, 1e-9)
        if rel <= opts.tol or step_small:
            converged = True
            break
    return s, converged


def _fit_alternate(bundle: _Bundle, s, k_idx, hold, opts, stats) -> tuple[dict, bool]:
    """SPC's alternation: all V with the poses fixed, then all poses with V fixed, repeated."""
    cost = bundle.cost(s, k_idx, hold)
    history = stats.setdefault("cost", [])
    history.append(cost)
    converged = False
    for _ in range(opts.max_iter):
        stats["iterations"] = stats.get("iterations", 0) + 1
        lin = bundle.linearise(s, k_idx)
        a, ga, d, gd, *_ = bundle.normal(s, k_idx, hold, lin)
        dv = np.einsum("lij,lj->li", inv3(d), gd)
        s = bundle.moved(s, np.zeros(bundle.n_red), dv)
        lin = bundle.linearise(s, k_idx)
        a, ga, d, gd, b, cam = bundle.normal(s, k_idx, hold, lin)
        dxp = np.linalg.solve(a, ga[..., None])[..., 0] if a.shape[0] else np.zeros((0, 6))
        dx = np.concatenate([dxp.reshape(-1), np.zeros(bundle.n_red - 6 * bundle.n_pic)])
        if bundle.nc:
            cc, gc, *_ = cam
            dx[6 * bundle.n_pic :] = np.linalg.solve(cc, gc[..., None])[..., 0].reshape(-1)
        s = bundle.moved(s, dx, np.zeros_like(s["v"]))
        c_new = bundle.cost(s, k_idx, hold)
        history.append(c_new)
        rel = abs(cost - c_new) / cost if cost > 0 else 0.0
        cost = c_new
        if rel <= opts.tol:
            converged = True
            break
    return s, converged


def _covariance(bundle: _Bundle, s, k_idx, hold, kind):
    """(pose (P, 6, 6), landmark (L, 3, 3), camera terms or None) covariances at the solution."""
    lin = bundle.linearise(s, k_idx)
    blocks = bundle.normal(s, k_idx, hold, lin)
    n_p = bundle.n_pic
    if kind == "conditional":
        a, d = blocks[0], blocks[2]
        return (inv3(a) if n_p else np.zeros((0, 6, 6))), inv3(d), None
    prob = bundle.prob
    pj, lv = prob.obs_picture[k_idx], prob.obs_landmark[k_idx]
    if not bundle.nc:
        red, dinv, _ = bundle.reduced_poses(k_idx, blocks, 0.0)
        sinv = red.inverse()
        pose_cov = sinv.reshape(n_p, 6, n_p, 6)[np.arange(n_p), :, np.arange(n_p), :]
        lcov = landmark_covariances(bundle.pairs(k_idx), pj, lv, blocks[4], dinv, sinv, bundle.n_lmk)
        return pose_cov, lcov, None
    s_mat, _, dinv, bmat, _ = bundle.reduced(k_idx, blocks, 0.0)
    m = s_mat.toarray()
    m = 0.5 * (m + m.T)
    dg = np.sqrt(np.diag(m))
    sinv = np.linalg.inv(m / dg[:, None] / dg[None, :]) / dg[:, None] / dg[None, :]
    sinv = 0.5 * (sinv + sinv.T)
    pose_cov = sinv[: 6 * n_p, : 6 * n_p].reshape(n_p, 6, n_p, 6)[np.arange(n_p), :, np.arange(n_p), :]
    # landmark blocks: D⁻¹ + (B D⁻¹)ᵀ S⁻¹ (B D⁻¹), the diagonal 3×3 blocks, in chunks of landmarks
    e = (bmat @ block_diag3(dinv)).tocsc()
    lcov = dinv.copy()
    n = sinv.shape[0]
    chunk = max(1, int(2e7 // max(n, 1)) // 3)
    for start in range(0, bundle.n_lmk, chunk):
        stop = min(bundle.n_lmk, start + chunk)
        ecd = e[:, 3 * start : 3 * stop].toarray()
        z = sinv @ ecd
        for i in range(3):
            for j in range(3):
                lcov[start:stop, i, j] += np.sum(ecd[:, i::3] * z[:, j::3], axis=0)
    return pose_cov, lcov, sinv[6 * n_p :, 6 * n_p :]


# ------------------------------------------------------------------------------------------------
# public entry point


def solve_bundle(problem: BundleProblem, options: BundleOptions | None = None) -> BundleResult:
    """Refine every landmark position and picture pose from all the measurements (module docstring)."""
    import time

    opts = options or BundleOptions()
    prob = problem
    t_start = time.perf_counter()
    bundle = _Bundle(prob, opts)
    warnings: list[str] = []
    k_all = prob.obs_picture.size
    status = np.array(["ok"] * k_all, dtype=object)
    status[~prob.obs_use] = "flagged"
    in_vlm = prob.vlm_pictures[prob.obs_picture]
    status[prob.obs_use & ~in_vlm] = "ignored-in-vlm"
    s = bundle.start()
    if k_all == 0:
        raise BundleError("no measurements: nothing to refine")

    usable = prob.obs_use & in_vlm
    cnt, par = _parallax(bundle, s, np.flatnonzero(usable))
    keep = (cnt < opts.min_pictures) | (par < opts.min_parallax_deg)
    observed = cnt > 0
    lstatus = np.where(keep, np.where(observed, "undetermined", "unobserved"), "ok").astype(object)
    und = int((keep & observed).sum())
    if und:
        warnings.append(
            f"{und} landmark(s) undetermined (fewer than {opts.min_pictures} usable pictures or parallax "
            f"below {opts.min_parallax_deg:g}°): their VLM keeps its prior"
        )
    # a kept landmark stays in the solve with its prior (its measurements inform the poses, its
    # uncertainty with them); one without a prior on every axis is held fixed
    has_prior = np.all(bundle.info_lmk > 0, axis=1)
    hold = keep & ~has_prior
    gauge = _gauge_check(bundle, s, hold)
    stats: dict = {}
    fit = _fit_joint if opts.mode == "joint" else _fit_alternate
    # pictures that constrain nothing in the joint solve (ignored in Vlm) are solved afterwards
    joint_pics = np.zeros(bundle.n_pic, bool)
    joint_pics[prob.obs_picture[usable]] = True
    rounds = 0
    converged = False
    if opts.reject_outliers:  # a robust fit first; what stands out there is flagged before the plain fits
        k0 = np.flatnonzero((status == "ok") & joint_pics[prob.obs_picture])
        s = _robust_prepass(bundle, s, k0, hold, opts, fit, stats)
        rho0, c0 = _normalised(bundle, s, k0)
        status[k0[rho0 > opts.reject_sigma * (c0 if opts.robust_scale else 1.0)]] = "outlier"
        keep, hold = _recheck_determinacy(bundle, s, status, in_vlm, keep, has_prior, lstatus, opts)
    while True:
        k_idx = np.flatnonzero((status == "ok") & joint_pics[prob.obs_picture])
        s, converged = fit(bundle, s, k_idx, hold, opts, stats)
        if not opts.reject_outliers or rounds >= opts.max_reject_rounds:
            break
        new = _flag_outliers(bundle, s, k_idx, opts)
        if new.size == 0:
            break
        status[new] = "outlier"
        rounds += 1
        keep, hold = _recheck_determinacy(bundle, s, status, in_vlm, keep, has_prior, lstatus, opts)
    used_idx = np.flatnonzero((status == "ok") & joint_pics[prob.obs_picture])
    status[keep[prob.obs_landmark] & (status == "ok")] = "undetermined"  # used, V not refined
    kind = opts.covariance
    if kind == "auto":
        kind = "full" if bundle.n_red <= opts.max_dense_reduced else "conditional"
    if kind == "conditional":
        warnings.append(
            f"{bundle.n_red} reduced unknowns: landmark covariances are conditional on the solved poses "
            "(covariance='full' for the joint ones)"
        )
    pose_cov, lcov, cam_cov = _covariance(bundle, s, used_idx, hold, kind)
    # pictures ignored in Vlm, and pictures with no landmark in the joint solve: poses against fixed V
    s = _solve_ignored(bundle, s, status, joint_pics, hold, pose_cov, warnings)
    # residuals at the solution the poses were fitted with (a kept landmark at its solved V)
    res_before = prob.obs_pixel - bundle.project(bundle.start(), np.arange(k_all), False)[0]
    res_after = prob.obs_pixel - bundle.project(s, np.arange(k_all), False)[0]
    if keep.any():  # kept landmarks: V and σ as they were (nothing written for them is learnt)
        s["v"][keep] = bundle.v0[keep]
        info_k = bundle.info_lmk[keep]
        var = np.where(info_k > 0, 1.0 / np.where(info_k > 0, info_k, 1.0), np.nan)
        lcov[keep] = var[:, :, None] * np.eye(3)
    rho = np.sqrt(np.maximum(np.einsum("ki,kij,kj->k", res_after, prob.obs_weight, res_after), 0.0))
    chi2_idx = used_idx
    chi2 = float(np.sum(rho[chi2_idx] ** 2))
    n_est_l = int((~hold).sum())
    dof = 2 * chi2_idx.size - 6 * int(joint_pics.sum()) - 3 * n_est_l - bundle.nc * len(bundle.group_camera)
    dof += int(np.count_nonzero(bundle.info_pos[joint_pics])) + int(
        np.count_nonzero(bundle.info_att[joint_pics])
    )
    dof += int(np.count_nonzero(bundle.info_lmk[~hold]))
    cam_terms = {}
    if bundle.nc:
        for g, cam in enumerate(bundle.group_camera):
            d = {}
            for i, (label, idx) in enumerate(bundle.slots[g]):
                sig = (
                    math.sqrt(cam_cov[g * bundle.nc + i, g * bundle.nc + i])
                    if cam_cov is not None
                    else math.nan
                )
                d[label] = (float(bundle.q0[g][idx]), float(s["q"][g, idx]), sig)
            cam_terms[cam.name or f"camera{g}"] = d
    cams = bundle.group_cameras(s)
    out_cams = [
        replace(cams[bundle.group[j]], rotation=s["rot"][j], scobj=-s["pos"][j], name=prob.cameras[j].name)
        for j in range(bundle.n_pic)
    ]
    if not converged:
        warnings.append(f"did not converge in {opts.max_iter} iterations")
    if opts.mode == "alternate":
        warnings.append(
            "SPC's alternation stops when a round lowers the cost by less than the tolerance; it crawls "
            "along directions that move landmarks and cameras together, so it may stop short of the joint "
            "minimum (mode joint reaches it)"
        )
    return BundleResult(
        picture_names=prob.picture_names,
        landmark_names=prob.landmark_names,
        cameras=out_cams,
        positions0=bundle.p0,
        positions=s["pos"],
        rotations=s["rot"],
        delta_position=s["pos"] - bundle.p0,
        delta_attitude=bundle.theta(s),
        pose_covariance=pose_cov,
        landmark_positions0=bundle.v0,
        landmark_positions=s["v"],
        landmark_covariance=lcov,
        landmark_status=[str(x) for x in lstatus],
        landmark_parallax_deg=par,
        obs_status=[str(x) for x in status],
        residual_before=res_before,
        residual_after=res_after,
        rho_after=rho,
        camera_terms=cam_terms,
        covariance_kind=kind,
        iterations=int(stats.get("iterations", 0)),
        converged=bool(converged),
        cost_history=[float(c) for c in stats.get("cost", [])],
        chi2=chi2,
        dof=int(dof),
        gauge_sigma=gauge,
        outlier_rounds=rounds,
        warnings=warnings,
        mode=opts.mode,
        timing={"total_s": time.perf_counter() - t_start},
        _obs_picture=prob.obs_picture,
        _obs_landmark=prob.obs_landmark,
    )


def _recheck_determinacy(bundle: _Bundle, s, status, in_vlm, keep, has_prior, lstatus, opts):
    """(keep, hold) after flags: a landmark that lost too many measurements keeps its prior (one without a
    prior is held at it)."""
    cnt, par = _parallax(bundle, s, np.flatnonzero((status == "ok") & in_vlm))
    newly = ~keep & ((cnt < opts.min_pictures) | (par < opts.min_parallax_deg))
    keep = keep | newly
    lstatus[newly] = "undetermined"
    s["v"][newly & ~has_prior] = bundle.v0[newly & ~has_prior]
    return keep, keep & ~has_prior


def _normalised(bundle: _Bundle, s, k_idx) -> tuple[np.ndarray, float]:
    """ρ_k = ‖W^(1/2) r_k‖ of measurements ``k_idx`` and the robust scale c = max(1, median ρ/√(2 ln 2))."""
    r = bundle.residuals(s, k_idx)
    w = bundle.prob.obs_weight[k_idx]
    rho = np.sqrt(np.maximum(np.einsum("ki,kij,kj->k", r, w, r), 0.0))
    c = max(1.0, float(np.median(rho)) / _RAYLEIGH_MEDIAN) if rho.size else 1.0
    return rho, c


def _robust_prepass(bundle: _Bundle, s, k_idx, hold, opts, fit, stats) -> dict:
    """Iteratively reweighted fits with Cauchy weights 1/(1 + (ρ/(k·c/2))²): a few gross errors then
    cannot drag the poses and landmarks, so that the outlier test that follows sees them alone.  The
    final fits use the measurements' own weights (the factors are reset)."""
    s, _ = fit(bundle, s, k_idx, hold, opts, stats)
    for _ in range(4):
        rho, c = _normalised(bundle, s, k_idx)
        if not np.any(rho > opts.reject_sigma * c):
            break
        half = 0.5 * opts.reject_sigma * (c if opts.robust_scale else 1.0)
        bundle.robust[k_idx] = 1.0 / (1.0 + (rho / half) ** 2)
        s, _ = fit(bundle, s, k_idx, hold, opts, stats)
    bundle.robust[:] = 1.0
    return s


def _flag_outliers(bundle: _Bundle, s, k_idx, opts) -> np.ndarray:
    """Measurements to flag this round: above k·c, the worst per landmark only."""
    if k_idx.size == 0:
        return k_idx
    rho, c = _normalised(bundle, s, k_idx)
    bad = rho > opts.reject_sigma * (c if opts.robust_scale else 1.0)
    if not bad.any():
        return np.zeros(0, dtype=np.int64)
    lv = bundle.prob.obs_landmark[k_idx]
    cand = np.flatnonzero(bad)
    order = cand[np.argsort(-rho[cand], kind="stable")]
    _, first = np.unique(lv[order], return_index=True)  # the worst of each landmark
    return k_idx[order[first]]


def _solve_ignored(bundle: _Bundle, s, status, joint_pics, hold, pose_cov, warnings):
    """Poses of pictures outside the joint solve (ignored in Vlm), each against the refined V, held fixed."""
    prob = bundle.prob
    others = np.flatnonzero(~joint_pics)
    if others.size == 0:
        return s
    from spctool.stages.pose import PoseError, PoseOptions, solve_pose

    for j in others:  # one small pose solve per such picture (rare: pictures an analyst set aside)
        k = np.flatnonzero((prob.obs_picture == j) & (status == "ignored-in-vlm"))
        if k.size < 3 and not (bundle.info_pos[j].all() and bundle.info_att[j].all()):
            warnings.append(f"picture {prob.picture_names[j]}: too few measurements for its pose: kept")
            pose_cov[j] = np.diag(
                np.concatenate(
                    [
                        1 / np.sqrt(np.maximum(bundle.info_pos[j], 1e-300)),
                        1 / np.sqrt(np.maximum(bundle.info_att[j], 1e-300)),
                    ]
                )
                ** 2
            )
            continue
        cam = prob.cameras[j]
        try:
            res = solve_pose(
                cam,
                s["v"][prob.obs_landmark[k]],
                prob.obs_pixel[k],
                PoseOptions(reject_outliers=False),
                prior_sigma_position=prob.sigma_position[j],
                prior_sigma_attitude=prob.sigma_attitude[j],
                pixel_covariances=np.linalg.inv(prob.obs_weight[k]),
                names=[prob.landmark_names[i] for i in prob.obs_landmark[k]],
            )
        except PoseError as exc:
            warnings.append(f"picture {prob.picture_names[j]}: pose not solved ({exc}): kept")
            continue
        s["pos"][j] = -np.asarray(res.scobj)
        s["rot"][j] = np.asarray(res.rotation)
        pose_cov[j] = res.covariance
    return s
