"""The bundle adjustment's model (private; used by :mod:`spctool.stages.bundle`): the state, the projection
of every measurement with its Jacobians, the normal equations with the priors, the camera terms, the
gauge and determinacy checks, the two solvers (joint Levenberg–Marquardt, SPC's alternation) and the
covariance at the solution.

Conventions, equations and sources: :mod:`spctool.stages.bundle` (map-refinement.md §1;
spc-algorithms.md §10–§11).  The reduced pose system and the pair sums are
:mod:`spctool.stages._bundle_linalg`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.sparse as sp

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

#: information given to an undetermined landmark's V (held at its prior), relative to its data
_HOLD = 1e12


class BundleError(SpcResultError):
    """The bundle adjustment cannot be solved as asked (free gauge, nothing to solve): exit code 1."""


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
    def __init__(self, prob, opts):
        """``prob`` a :class:`spctool.stages.bundle.BundleProblem`, ``opts`` its :class:`BundleOptions`."""
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
        #: the measurements' weights in the solve: W, or for a held landmark's (:meth:`hold_landmarks`)
        #: (W⁻¹ + J_V Σ_V J_Vᵀ)⁻¹
        self.eff_weight = prob.obs_weight

    def hold_landmarks(self, s, hold) -> None:
        """Weights for landmarks ``hold`` held at their prior VLM: a measurement of one with a prior on
        every axis gets the prior's uncertainty projected into the picture, (W⁻¹ + J_V Σ_V J_Vᵀ)⁻¹ with
        J_V = ∂h/∂V at ``s`` (so a VLM known to 1 m does not pin a pose as if it were exact; to first
        order the poses of the solve with V free under its prior, V eliminated); one without is exact.
        Written as W − W J (Σ_V⁻¹ + Jᵀ W J)⁻¹ Jᵀ W (Woodbury), which needs no W⁻¹."""
        prob = self.prob
        w = prob.obs_weight.copy()
        full = hold & np.all(self.info_lmk > 0, axis=1)
        k = np.flatnonzero(full[prob.obs_landmark] & prob.obs_use)
        if k.size:
            _, _, jc, rot, _, _ = self.project(s, k, True)
            jv = jc @ rot  # (K, 2, 3)
            wk = prob.obs_weight[k]
            wj = wk @ jv  # (K, 2, 3)
            m = np.einsum("kai,kaj->kij", jv, wj)
            m[:, np.arange(3), np.arange(3)] += self.info_lmk[prob.obs_landmark[k]]
            w[k] = wk - wj @ np.linalg.solve(m, np.swapaxes(wj, 1, 2))
            w[k] = 0.5 * (w[k] + np.swapaxes(w[k], 1, 2))
        self.eff_weight = w

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
        return self.eff_weight[k_idx] * self.robust[k_idx, None, None]

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
        gk = np.einsum("kij,kj->ki", b, np.einsum("kjl,kl->kj", dinv[lv], gd[lv]))  # G_k g_V = B_k (D⁻¹ g_V)
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
    import scipy.sparse.linalg as spla  # camera terms only: not paid by the plain bundle

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
            dv[hold] = 0.0  # a held landmark stays exactly where it is (its large weight leaves ~1e-12)
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
