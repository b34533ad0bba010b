"""The pose solve's least-squares problem (private; used by :mod:`spctool.stages.pose`): the a-priori
information, the state, the normal equations with the landmark blocks eliminated, the Jacobi-scaled
solve with its condition check, the pivot-retraction step and the Gauss–Newton loop; the correlated
error modes and the covariance of a uniformly weighted fit under a calibrated measurement covariance
(the sandwich N⁻¹(HᵀW·R·WH + P₀⁻¹)N⁻¹, :func:`_sandwich_covariance`).

Conventions and equations: :mod:`spctool.stages.pose` (spc-algorithms.md §10 and errata 1–4 of §11).

**Correlated measurement errors** (issue #39): the pixel errors of one picture's landmarks need not be
independent — a shading-model error shifts every landmark of the picture alike (along the Sun's
azimuth), or in a pattern that varies smoothly over the picture, and the residuals cannot reveal the
part of it a pose change absorbs.  Such errors are k *modes*: columns of U (2M × k, the block Uᵢ
(2 × k) per landmark) with unit-variance coefficients, so the measurement covariance of the M
landmarks is R = blkdiag(W₁⁻¹ … W_M⁻¹) + U·Uᵀ — a shift common to all landmarks with 2×2 covariance
C is Uᵢ = L (L·Lᵀ = C) for every i.  By the Woodbury identity

    R⁻¹ = W − W·U·K·Uᵀ·W,   K = (I + Uᵀ·W·U)⁻¹ = (I + Σᵢ UᵢᵀWᵢUᵢ)⁻¹   (k × k),

so with G = Σᵢ UᵢᵀWᵢHᵢ (k × 6) and w = Σᵢ UᵢᵀWᵢrᵢ every quantity of the weighted problem gains one
rank-k term: HᵀR⁻¹H = Σ HᵢᵀWᵢHᵢ − GᵀKG, HᵀR⁻¹r = Σ HᵢᵀWᵢrᵢ − GᵀKw, rᵀR⁻¹r = Σ rᵢᵀWᵢrᵢ − wᵀKw —
O(M·k²) work, never a 2M × 2M matrix (tests/test_pose_consistency.py compares it with the dense
inverse).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from spctool.errors import SpcResultError, SpcUsageError
from spctool.geometry.frames import apply_attitude_update, rotvec_from_rot, skew
from spctool.stages.pose_consistency import model_error


class PoseError(SpcResultError):
    """The pose cannot be solved: too few landmarks or degenerate geometry (exit code 1)."""


# ------------------------------------------------------------------------------------------------
# SO(3) helper
# ------------------------------------------------------------------------------------------------


def so3_right_jacobian_inv(theta) -> np.ndarray:
    """J_r(θ)⁻¹ = I + ½[θ×] + (1/t² − (1 + cos t)/(2 t sin t))·[θ×]², t = |θ| (series below 1e-4 rad).

    With T = Rot(−θ)·T₀ and the step T⁺ = Rot(−δθ)·T, the offset becomes θ⁺ = θ + J_r(θ)⁻¹·δθ + O(δθ²).
    """
    th = np.asarray(theta, dtype=np.float64)
    t2 = float(th @ th)
    t = math.sqrt(t2)
    if t < 1e-4:
        c = 1.0 / 12.0 + t2 / 720.0
    else:
        c = 1.0 / t2 - (1.0 + math.cos(t)) / (2.0 * t * math.sin(t))
    k = skew(th)
    return np.eye(3) + 0.5 * k + c * (k @ k)


# ------------------------------------------------------------------------------------------------
# internals
# ------------------------------------------------------------------------------------------------


@dataclass
class _Prior:
    """A-priori information on [Δp; θ]: inverse variances (0 = unconstrained component)."""

    info: np.ndarray  # (6,)

    @property
    def n_equations(self) -> int:
        return int(np.count_nonzero(self.info))


def _prior_info(sig, n, what, warnings) -> np.ndarray:
    if sig is None:
        return np.zeros(n)
    s = np.asarray(sig, dtype=np.float64).reshape(-1)
    if s.size == 1:
        s = np.full(n, s[0])
    if s.shape != (n,):
        raise SpcUsageError(f"{what} must have {n} components, got shape {np.shape(sig)}")
    ok = np.isfinite(s) & (s > 0)
    if not ok.all():
        warnings.append(
            f"{what} components {np.flatnonzero(~ok).tolist()} are not positive finite numbers:"
            " no a-priori constraint on them"
        )
    info = np.zeros(n)
    info[ok] = 1.0 / (s[ok] * s[ok])
    return info


@dataclass
class _State:
    camera: object
    dpos: np.ndarray  # (3,)
    theta: np.ndarray  # (3,)
    dlmk: np.ndarray | None  # (M, 3)


class _Problem:
    """The least-squares problem over a fixed set of used landmarks (M of them)."""

    def __init__(self, camera0, points, meas, wts, prior: _Prior, mode, lmk_info, opts, modes=None):
        self.camera0 = camera0
        self.p0 = camera0.position.copy()
        self.t0 = np.array(camera0.rotation)
        self.points = points  # (M, 3)
        self.meas = meas  # (M, 2)
        w = np.asarray(wts, dtype=np.float64)
        if w.ndim == 2:  # per-axis weights (M, 2): diagonal Wᵢ
            w = w[:, :, None] * np.eye(2)
        self.wts = w  # (M, 2, 2) weight matrices Wᵢ (symmetric)
        # correlated error modes Uᵢ (M, 2, k) and the Woodbury kernel K (module docstring); None: independent
        self.modes = self.kernel = None
        if modes is not None and np.asarray(modes).shape[-1] > 0 and np.any(np.asarray(modes) != 0.0):
            u = np.asarray(modes, dtype=np.float64)
            s_ = np.einsum("mik,mij,mjl->kl", u, w, u)
            k = np.linalg.inv(np.eye(u.shape[2]) + 0.5 * (s_ + s_.T))
            self.modes, self.kernel = u, 0.5 * (k + k.T)
        self.prior = prior
        self.mode = mode
        self.lmk_info = lmk_info  # (M, 3) inverse variances, "estimate" mode
        self.opts = opts
        self.pivot = points.mean(axis=0) if points.shape[0] else self.p0.copy()

    # -- state helpers ------------------------------------------------------------------------------
    def start(self) -> _State:
        d = np.zeros_like(self.points) if self.mode == "estimate" else None
        return _State(self.camera0, np.zeros(3), np.zeros(3), d)

    def moved(self, s: _State, dx, dd, alpha) -> _State:
        """Apply a step (δp, δθ) with the pivot retraction (module docstring).

        The step is converted to t = T·(c − p), the camera-frame vector from the camera to the pivot
        c (landmark centroid): δt = [t×]·δθ − T·δp, equal to (δp, δθ) to first order, then
        T⁺ = Rot(−δθ)·T, t⁺ = t + δt, p⁺ = c − T⁺ᵀ·t⁺.  A finite step thus orbits the camera about
        the landmarks instead of moving it along a straight line, which follows the nearly
        degenerate position/attitude valley of small landmark clusters (few iterations, no halving).
        """
        rot0 = np.asarray(s.camera.rotation)
        dp = alpha * dx[:3]
        dth = alpha * dx[3:]
        t = rot0 @ (self.pivot - s.camera.position)
        t_new = t + np.cross(t, dth) - rot0 @ dp
        rot = apply_attitude_update(rot0, dth)
        pos = self.pivot - rot.T @ t_new
        dpos = pos - self.p0
        theta = -rotvec_from_rot(rot @ self.t0.T)
        cam = s.camera.with_pose(position=pos, rotation=rot)
        d = None if s.dlmk is None else s.dlmk + alpha * dd
        return _State(cam, dpos, theta, d)

    def pts(self, s: _State) -> np.ndarray:
        return self.points if s.dlmk is None else self.points + s.dlmk

    def cost(self, s: _State) -> tuple[float, float]:
        smp, lin = s.camera.project(self.pts(s))
        r = self.meas - np.stack([smp, lin], axis=-1)
        chi2 = float(np.einsum("mi,mij,mj->", r, self.wts, r))
        if self.kernel is not None:
            w = np.einsum("mik,mij,mj->k", self.modes, self.wts, r)
            chi2 -= float(w @ self.kernel @ w)
        e = np.concatenate([s.dpos, s.theta])
        total = chi2 + float(np.sum(self.prior.info * e * e))
        if s.dlmk is not None:
            total += float(np.sum(self.lmk_info * s.dlmk * s.dlmk))
        return total, chi2

    # -- linear algebra -----------------------------------------------------------------------------
    def normal(self, s: _State):
        """Reduced normal matrix N (6×6), right-hand side g, and the pieces needed afterwards."""
        j = s.camera.project_with_jacobians(self.pts(s))
        pred = np.stack([j.sample, j.line], axis=-1)
        r = self.meas - pred
        hx = np.concatenate([j.position, j.attitude], axis=-1)  # (M, 2, 6)
        hw = self.wts @ hx  # Wᵢ·Hᵢ (M, 2, 6)
        h2 = hx.reshape(-1, 6)
        hw2 = hw.reshape(-1, 6)
        n = hw2.T @ h2
        g = hw2.T @ r.reshape(-1)
        if self.kernel is not None:  # correlated errors (module docstring): rank-k corrections
            gw = np.einsum("mik,mij->kj", self.modes, hw)  # G = Σ UᵢᵀWᵢHᵢ (k, 6)
            w = np.einsum("mik,mij,mj->k", self.modes, self.wts, r)
            n = n - gw.T @ self.kernel @ gw
            n = 0.5 * (n + n.T)
            g = g - gw.T @ (self.kernel @ w)
        # a-priori term: residual e = [Δp; θ], de/dχ = diag(I, J_r(θ)⁻¹)
        jp = np.eye(6)
        jp[3:, 3:] = so3_right_jacobian_inv(s.theta)
        e = np.concatenate([s.dpos, s.theta])
        jpi = jp.T * self.prior.info  # Jᵀ·P₀⁻¹
        n = n + jpi @ jp
        g = g - jpi @ e
        extra = {"hx": hx, "pred": pred, "r": r, "hl": j.point, "g_full": g}
        if self.mode == "estimate":
            hl = j.point  # (M, 2, 3)
            hlw = self.wts @ hl
            b = np.einsum("mki,mkj->mij", hw, hl)  # (M, 6, 3)
            d = np.einsum("mki,mkj->mij", hlw, hl)
            d[:, [0, 1, 2], [0, 1, 2]] += self.lmk_info
            gl = np.einsum("mki,mk->mi", hlw, r) - self.lmk_info * s.dlmk
            dinv = np.linalg.inv(d)
            bdinv = b @ dinv  # (M, 6, 3)
            n = n - np.einsum("mij,mkj->ik", bdinv, b)
            g = g - np.einsum("mij,mj->i", bdinv, gl)
            extra.update(b=b, dinv=dinv, gl=gl)
        return n, g, extra

    def solve_scaled(self, n, g, n_used):
        """Δχ = N⁻¹g and N⁻¹ with Jacobi scaling; PoseError if degenerate."""
        diag = np.diag(n).copy()
        if not np.all(np.isfinite(n)):
            raise PoseError(
                f"degenerate geometry: the normal matrix of {n_used} landmark(s) is not finite"
                " (a landmark in the camera's focal plane?)"
            )
        if np.any(diag <= 0.0):
            raise PoseError(
                f"degenerate geometry: {n_used} landmark(s) leave pose component(s) "
                f"{np.flatnonzero(~(diag > 0)).tolist()} without information"
            )
        sc = 1.0 / np.sqrt(diag)
        ns = n * sc[:, None] * sc[None, :]
        ns = 0.5 * (ns + ns.T)
        ev = np.linalg.eigvalsh(ns)
        cond = float(ev[-1] / ev[0]) if ev[0] > 0 else math.inf
        if not cond <= self.opts.max_condition:
            raise PoseError(
                f"degenerate geometry: {n_used} landmark(s) give a normal-matrix condition number "
                f"{cond:.3g} > {self.opts.max_condition:.3g} (collinear or too few landmarks, or no prior)"
            )
        cov = np.linalg.inv(ns) * sc[:, None] * sc[None, :]
        cov = 0.5 * (cov + cov.T)
        dx = cov @ g
        return dx, cov, cond

    def landmark_step(self, extra, dx):
        if self.mode != "estimate":
            return None
        return np.einsum("mij,mj->mi", extra["dinv"], extra["gl"] - np.einsum("mji,j->mi", extra["b"], dx))

    # -- Gauss–Newton -------------------------------------------------------------------------------
    def fit(self):
        opts = self.opts
        m = self.points.shape[0]
        s = self.start()
        cost, _ = self.cost(s)
        history = [cost]
        converged = False
        iterations = 0
        for it in range(1, opts.max_iter + 1):
            iterations = it
            n, g, extra = self.normal(s)
            dx, cov, _ = self.solve_scaled(n, g, m)
            dd = self.landmark_step(extra, dx)
            # predicted cost decrease /2 along the full step: (full gradient)ᵀ·(full step)
            predicted = float(extra["g_full"] @ dx) + (0.0 if dd is None else float(np.sum(extra["gl"] * dd)))
            alpha = 1.0
            accepted = False
            for _ in range(opts.max_halvings + 1):
                trial = self.moved(s, dx, dd, alpha)
                c_new, _ = self.cost(trial)
                if c_new <= cost * (1.0 + 1e-12) + 1e-300:
                    accepted = True
                    break
                alpha *= 0.5
            if not accepted:
                # numerical floor: no decrease is possible any more
                converged = predicted <= 1e-6 * max(1.0, cost)
                break
            sig = np.sqrt(np.diag(cov))
            step = float(np.max(np.abs(alpha * dx) / sig))
            rel = abs(cost - c_new) / cost if cost > 0 else 0.0
            s, cost = trial, c_new
            history.append(cost)
            if step <= opts.tol or rel <= opts.tol:
                converged = True
                break
        return s, iterations, converged, history


# ------------------------------------------------------------------------------------------------
# correlated errors and the sandwich covariance (used by spctool.stages.pose)


def _sandwich_covariance(problem, state, cov_w, base, common, patterns, used, opts, prior):
    """(P, τ, common C) of a fit weighted with W (``problem.wts``) under the measurement covariance
    R = blkdiag(Cᵢ + τ²I) + U·Uᵀ (``base`` Cᵢ of the used landmarks; modes U: ``patterns`` rows
    ``used`` and the common C + τ²I): P = N⁻¹(HᵀW·R·WH + Nₚ)N⁻¹ with N⁻¹ = ``cov_w`` and Nₚ the prior's
    information (an honest prior).  τ from the fit's residuals (:func:`model_error`)."""
    j = state.camera.project_with_jacobians(problem.pts(state))
    r = problem.meas - np.stack([j.sample, j.line], axis=-1)
    hx = np.concatenate([j.position, j.attitude], axis=-1)  # (M, 2, 6)
    hw = problem.wts @ hx  # Wᵢ·Hᵢ
    cap = opts.sigma_px if opts.max_model_error_px is None else float(opts.max_model_error_px)
    dof = 2 * r.shape[0] + prior.n_equations - 6
    tau = model_error(r, base, dof, cap, opts.model_error_quantile) if opts.model_error else 0.0
    shared = common
    if opts.common_model_error and tau > 0:
        shared = (tau * tau) * np.eye(2) + (0.0 if common is None else common)
    rb = base + (tau * tau) * np.eye(2)
    a = np.einsum("mki,mkl,mlj->ij", hw, rb, hw)
    rows = None if patterns is None else np.asarray(patterns, dtype=np.float64)[used]
    modes = _error_modes(shared, rows, int(np.count_nonzero(used)), "fixed")
    if modes is not None:
        g = np.einsum("mik,mij->kj", modes, hw)  # (k, 6)
        a = a + g.T @ g
    jp = np.eye(6)  # the prior's share of N: Jₚᵀ·P₀⁻¹·Jₚ (as _Problem.normal)
    jp[3:, 3:] = so3_right_jacobian_inv(state.theta)
    n_prior = (jp.T * prior.info) @ jp
    p = cov_w @ (a + n_prior) @ cov_w
    return 0.5 * (p + p.T), float(tau), shared


def _common_covariance(common, mode):
    """The common error's 2×2 covariance checked (symmetric, finite, positive semi-definite), or None."""
    if common is None:
        return None
    c = np.asarray(common, dtype=np.float64)
    if c.shape != (2, 2) or not np.all(np.isfinite(c)):
        raise SpcUsageError(f"common_covariance must be a finite 2x2 matrix, got shape {c.shape}")
    c = 0.5 * (c + c.T)
    if np.linalg.eigvalsh(c)[0] < -1e-12 * max(1.0, float(np.abs(c).max())):
        raise SpcUsageError("common_covariance must be positive semi-definite")
    if mode != "fixed" and np.any(c != 0.0):
        raise SpcUsageError(f"common_covariance needs landmark_mode 'fixed', not {mode!r}")
    return c


def _error_modes(common, patterns, n, mode):
    """(N, 2, k) correlated error modes (:mod:`spctool.stages._pose_problem`): the common covariance's
    square root L (L·Lᵀ = C, every landmark alike) beside the given patterns; None without either."""
    parts = []
    if common is not None and np.any(common != 0.0):
        lam, vec = np.linalg.eigh(common)
        root = vec * np.sqrt(np.clip(lam, 0.0, None))
        parts.append(np.broadcast_to(root, (n, 2, 2)))
    if patterns is not None:
        u = np.asarray(patterns, dtype=np.float64)
        u = u[..., None] if u.ndim == 2 else u
        if u.ndim != 3 or u.shape[:2] != (n, 2):
            raise SpcUsageError(f"error_modes must have shape ({n}, 2, k), got {np.shape(patterns)}")
        if mode != "fixed":
            raise SpcUsageError(f"error_modes need landmark_mode 'fixed', not {mode!r}")
        parts.append(np.where(np.isfinite(u), u, 0.0))
    return np.concatenate(parts, axis=2) if parts else None
