"""Tests of spctool.stages.pose (spc-algorithms.md §10, Stage I).

Independent checks used here:

* the normal equations (measurement rows, a-priori rows with J_r(θ)⁻¹, the pivot retraction, the
  landmark Schur complement) against central finite differences of the full whitened residual vector;
* J_r(θ)⁻¹ against finite differences of the exact composition log(Rot(−δθ)·Rot(−θ));
* Monte Carlo consistency: normalised estimation errors (NEES, 6 dof) against χ²₆ over 200 seeds;
* the real Rosetta 67P picture W48230079013 (3 landmarks, no prior: exactly determined) against
  scipy's Levenberg–Marquardt on a different parametrisation.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats
from scipy.optimize import least_squares

from spctool.errors import SpcResultError, SpcUsageError
from spctool.geometry.camera import Camera
from spctool.geometry.frames import apply_attitude_update, rot_from_rotvec, rotvec_from_rot
from spctool.stages.pose import (
    PoseError,
    PoseOptions,
    _Prior,
    _Problem,
    so3_right_jacobian_inv,
    solve_pose,
)

REAL = Path(__file__).resolve().parents[1] / "fixtures" / "real" / "rosetta-67p"
CHI2_99_6 = stats.chi2.ppf(0.99, 6)


# ------------------------------------------------------------------------------------------------
# synthetic scenes
# ------------------------------------------------------------------------------------------------


def make_camera(rng, range_km=5.0, model="OWEN"):
    """A 1024² camera (IFOV 2e-4 rad: 1 px = 1 m at 5 km) looking roughly at the body origin."""
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    pos = range_km * d
    cz = -d
    cx = np.cross([0.0, 0.0, 1.0], cz)
    cx /= np.linalg.norm(cx)
    cy = np.cross(cz, cx)
    rot = rot_from_rotvec(rng.normal(scale=0.05, size=3)) @ np.stack([cx, cy, cz])
    return Camera(
        mmfl=50.0,
        ctr=[512.5, 512.5],
        kmatrix=[[100.0, 0.2, 0.0], [0.1, -100.0, 0.0]],
        rotation=rot,
        scobj=-pos,
        npx=1024,
        nln=1024,
        model=model,
        coefficients=[0.0, 1e-5, 2e-5, 0.0, 0.0, 1e-5, -1e-5],
    )


def make_landmarks(rng, cam, n, depth=0.15):
    """n landmarks spread over the detector at ranges within ±depth of the camera range."""
    smp = rng.uniform(50, 975, n)
    lin = rng.uniform(50, 975, n)
    dirs = cam.pixel_to_direction(smp, lin)
    rng_km = np.linalg.norm(cam.position) * rng.uniform(1 - depth, 1 + depth, n)
    return cam.position + dirs * rng_km[:, None]


def observe(cam, pts, rng=None, sigma=0.0):
    s, ln = cam.project(pts)
    y = np.stack([s, ln], axis=-1)
    if rng is not None and sigma > 0:
        y = y + rng.normal(scale=sigma, size=y.shape)
    return y


def perturbed(cam, dp, dth):
    return cam.with_pose(position=cam.position + dp, rotation=apply_attitude_update(cam.rotation, dth))


def pose_error(truth, result):
    """Truth − estimate in the solution's local coordinates [Δp (km, body); θ (rad, camera)]."""
    ep = truth.position - result.position
    eth = -rotvec_from_rot(truth.rotation @ result.rotation.T)  # T_true = Rot(−e)·T_solved
    return np.concatenate([ep, eth])


def nees(truth, result):
    e = pose_error(truth, result)
    return float(e @ np.linalg.solve(result.covariance, e))


SIG_P = np.array([0.02, 0.02, 0.02])  # km
SIG_A = np.array([3e-4, 3e-4, 1e-3])  # rad


# ------------------------------------------------------------------------------------------------
# Jacobians and normal equations vs finite differences
# ------------------------------------------------------------------------------------------------


def test_so3_right_jacobian_inverse_matches_finite_differences():
    rng = np.random.default_rng(3)
    for theta in (rng.normal(scale=0.3, size=3), rng.normal(scale=1e-5, size=3), np.zeros(3)):
        jac = np.empty((3, 3))
        h = 1e-6
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            plus = -rotvec_from_rot(rot_from_rotvec(-e) @ rot_from_rotvec(-theta))
            minus = -rotvec_from_rot(rot_from_rotvec(e) @ rot_from_rotvec(-theta))
            jac[:, k] = (plus - minus) / (2 * h)
        np.testing.assert_allclose(so3_right_jacobian_inv(theta), jac, atol=2e-9)


def _whitened(problem, state):
    """Stacked whitened residual vector ρ with cost = ρᵀρ (independent of _Problem.normal)."""
    pts = problem.pts(state)
    s, ln = state.camera.project(pts)
    r = problem.meas - np.stack([s, ln], axis=-1)
    r = np.einsum("mji,mj->mi", np.linalg.cholesky(problem.wts), r)  # Lᵀr with W = LLᵀ: ρᵀρ = rᵀWr
    e = np.concatenate([state.dpos, state.theta]) * np.sqrt(problem.prior.info)
    parts = [r.reshape(-1), e]
    if state.dlmk is not None:
        parts.append((state.dlmk * np.sqrt(problem.lmk_info)).reshape(-1))
    return np.concatenate(parts)


@pytest.mark.parametrize("mode", ["fixed", "estimate"])
def test_normal_equations_match_finite_differences(mode):
    rng = np.random.default_rng(11)
    cam = make_camera(rng)
    pts = make_landmarks(rng, cam, 6)
    y = observe(cam, pts, rng, 0.5)
    m = pts.shape[0]
    # full 2×2 weights (correlated axes, as --weights surface gives) checked against finite differences
    a = rng.normal(scale=0.2, size=(m, 2, 2))
    wts = np.linalg.inv(a @ np.swapaxes(a, 1, 2) + 0.05 * np.eye(2))
    lmk_info = 1.0 / np.full((m, 3), 2e-3) ** 2 if mode == "estimate" else None
    prior = _Prior(np.concatenate([1 / SIG_P**2, 1 / SIG_A**2]))
    start = perturbed(cam, [0.01, -0.02, 0.015], [2e-3, -1e-3, 3e-3])
    problem = _Problem(start, pts, y, wts, prior, mode, lmk_info, PoseOptions(landmark_mode=mode))
    s0 = problem.start()
    # move away from the a-priori pose so that θ ≠ 0 (J_r(θ)⁻¹ ≠ I) and the landmarks are offset
    s = problem.moved(
        s0,
        np.array([0.004, 0.003, -0.002, 0.02, -0.03, 0.05]),
        None if mode == "fixed" else rng.normal(scale=1e-3, size=(m, 3)),
        1.0,
    )
    n_red, g_red, extra = problem.normal(s)

    # full finite-difference Jacobian of ρ with respect to the step (δp, δθ[, δd])
    nx = 6 + (3 * m if mode == "estimate" else 0)
    rho0 = _whitened(problem, s)
    jac = np.empty((rho0.size, nx))
    for k in range(nx):
        h = 1e-6 if k < 3 else 1e-8 if k < 6 else 1e-7
        e = np.zeros(nx)
        e[k] = h
        dd_p = e[6:].reshape(m, 3) if mode == "estimate" else None
        dd_m = -e[6:].reshape(m, 3) if mode == "estimate" else None
        rp = _whitened(problem, problem.moved(s, e[:6], dd_p, 1.0))
        rm = _whitened(problem, problem.moved(s, -e[:6], dd_m, 1.0))
        jac[:, k] = (rp - rm) / (2 * h)
    n_full = jac.T @ jac
    g_full = -jac.T @ rho0
    if mode == "estimate":  # eliminate the landmark block (Schur complement), plain dense algebra
        a, b, d = n_full[:6, :6], n_full[:6, 6:], n_full[6:, 6:]
        n_fd = a - b @ np.linalg.solve(d, b.T)
        g_fd = g_full[:6] - b @ np.linalg.solve(d, g_full[6:])
    else:
        n_fd, g_fd = n_full, g_full
    scale = np.sqrt(np.diag(n_fd))
    np.testing.assert_allclose(n_red / np.outer(scale, scale), n_fd / np.outer(scale, scale), atol=1e-5)
    np.testing.assert_allclose(
        g_red / scale, g_fd / scale, atol=1e-4 * max(1.0, np.max(np.abs(g_fd / scale)))
    )

    # the measurement Jacobian H itself vs the full projection with the plain update (no retraction)
    hx = extra["hx"].reshape(-1, 6)
    pts_s = problem.pts(s)
    for k in range(6):
        h = 1e-6 if k < 3 else 1e-8
        e = np.zeros(6)
        e[k] = h

        def proj(sign, e=e):
            c = s.camera.with_pose(
                position=s.camera.position + sign * e[:3],
                rotation=apply_attitude_update(s.camera.rotation, sign * e[3:]),
            )
            return np.stack(c.project(pts_s), axis=-1).reshape(-1)

        fd = (proj(1) - proj(-1)) / (2 * h)
        np.testing.assert_allclose(hx[:, k], fd, rtol=1e-5, atol=1e-4 * np.max(np.abs(fd)))


def test_retraction_is_the_step_to_first_order():
    rng = np.random.default_rng(5)
    cam = make_camera(rng)
    pts = make_landmarks(rng, cam, 5)
    problem = _Problem(
        cam, pts, observe(cam, pts), np.ones((5, 2)), _Prior(np.zeros(6)), "fixed", None, PoseOptions()
    )
    dx = np.array([0.3, -0.2, 0.1, 0.01, 0.02, -0.03])
    for h in (1e-3, 1e-4):
        s = problem.moved(problem.start(), dx, None, h)
        err = np.concatenate([s.dpos, s.theta]) - h * dx
        assert np.max(np.abs(err)) < 50 * h * h * np.max(np.abs(dx))  # O(h²)
    s = problem.moved(problem.start(), dx, None, 1.0)
    np.testing.assert_allclose(s.camera.rotation @ s.camera.rotation.T, np.eye(3), atol=1e-14)
    # distance camera -> pivot is what the retraction keeps linear: |t + δt|
    t = cam.rotation @ (problem.pivot - cam.position)
    t_new = s.camera.rotation @ (problem.pivot - s.camera.position)
    np.testing.assert_allclose(t_new, t + np.cross(t, dx[3:]) - cam.rotation @ dx[:3], atol=1e-12)


# ------------------------------------------------------------------------------------------------
# Monte Carlo consistency
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "use_prior, seeds, mean_tol, max_exceed",
    # mean of n χ²₆ draws: 6 ± √(12/n) (1σ: 0.24 for 200, 0.35 for 100);
    # P(≥ 7 of 200) = 0.5 %, P(≥ 5 of 100) = 0.3 % exceedances of the 99 % quantile
    [(True, 200, 0.9, 6), (False, 100, 1.2, 4)],
)
def test_nees_consistent_with_chi2_over_many_seeds(use_prior, seeds, mean_tol, max_exceed):
    values = []
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        truth = make_camera(rng)
        pts = make_landmarks(rng, truth, 30)
        # the a-priori pose is drawn from the prior about the truth (so the prior is honest)
        start = perturbed(truth, rng.normal(size=3) * SIG_P, rng.normal(size=3) * SIG_A)
        y = observe(truth, pts, rng, 0.1)
        res = solve_pose(
            start,
            pts,
            y,
            PoseOptions(sigma_px=0.1, use_prior=use_prior),
            prior_sigma_position=SIG_P,
            prior_sigma_attitude=SIG_A,
        )
        assert res.converged and res.n_used == 30
        values.append(nees(truth, res))
    values = np.array(values)
    exceed = int(np.count_nonzero(values > CHI2_99_6))
    assert abs(values.mean() - 6.0) < mean_tol, values.mean()
    assert exceed <= max_exceed, exceed
    assert stats.kstest(values, "chi2", args=(6,)).pvalue > 1e-3


def _random_covariances(rng, n):
    """Per-landmark measurement covariances like register's: 1σ 0.02–0.3 px, axes correlated |ρ| ≤ 0.8."""
    ss = np.exp(rng.uniform(np.log(0.02), np.log(0.3), n))
    sl = np.exp(rng.uniform(np.log(0.02), np.log(0.3), n))
    rho = rng.uniform(-0.8, 0.8, n)
    c = np.empty((n, 2, 2))
    c[:, 0, 0], c[:, 1, 1] = ss * ss, sl * sl
    c[:, 0, 1] = c[:, 1, 0] = rho * ss * sl
    return c


def test_nees_with_surface_weights_consistent_with_chi2():
    """--weights surface: measurements whose noise follows per-landmark full 2×2 covariances, weighted
    by exactly those (plus the 0.001 px floor): the NEES of 250 seeds is χ²₆ (mean, 99 % quantile
    exceedances, Kolmogorov–Smirnov).  The same data weighted uniformly (0.1 px) is not consistent.
    With the model error's common part (the default, ``common_model_error``: in the ~10 % of seeds where
    chance lifts χ² above its 90 % quantile, τ > 0 and a shift τ²I shared by the landmarks is assumed
    that this world does not have) the covariance is a little larger: NEES mean a little below 6."""
    seeds = 250
    values, uniform, common = [], [], []
    for seed in range(seeds):
        rng = np.random.default_rng(1000 + seed)
        truth = make_camera(rng)
        pts = make_landmarks(rng, truth, 20)
        cov = _random_covariances(rng, 20)
        y = observe(truth, pts) + np.einsum("mij,mj->mi", np.linalg.cholesky(cov), rng.normal(size=(20, 2)))
        start = perturbed(truth, rng.normal(size=3) * SIG_P, rng.normal(size=3) * SIG_A)
        opts = PoseOptions(use_prior=False, common_model_error=False)
        res = solve_pose(start, pts, y, opts, pixel_covariances=cov)
        assert res.converged and res.n_used == 20 and not res.warnings
        values.append(nees(truth, res))
        default = solve_pose(start, pts, y, PoseOptions(use_prior=False), pixel_covariances=cov)
        common.append(nees(truth, default))
        if seed < 60:
            # the formal covariance: no cost/dof scaling (that is a global, not per-landmark, fix)
            uniform.append(
                nees(
                    truth,
                    solve_pose(
                        start, pts, y, PoseOptions(use_prior=False, sigma_px=0.1, scale_covariance=False)
                    ),
                )
            )
    values = np.array(values)
    # mean of 250 χ²₆ draws: 6 ± 0.22 (1σ); P(≥ 8 of 250 above the 99 % quantile) ≈ 0.4 %
    assert 5.4 < values.mean() < 6.6, values.mean()
    assert np.count_nonzero(values > CHI2_99_6) <= 7
    assert stats.kstest(values, "chi2", args=(6,)).pvalue > 1e-3
    assert np.quantile(values, 0.5) == pytest.approx(stats.chi2.ppf(0.5, 6), rel=0.15)
    assert 4.8 < np.mean(common) <= values.mean() and np.count_nonzero(np.array(common) > CHI2_99_6) <= 7
    uniform = np.array(uniform)  # 0.1 px for all: too optimistic for half of them, too pessimistic for others
    assert uniform.mean() > 7.5 and stats.kstest(uniform, "chi2", args=(6,)).pvalue < 0.01, uniform.mean()


def test_surface_weights_bad_rows_fall_back_and_are_named():
    rng = np.random.default_rng(4)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, 8)
    cov = _random_covariances(rng, 8)
    cov[2] = np.nan
    cov[5] = [[0.01, 0.02], [0.02, 0.01]]  # not positive definite
    res = solve_pose(
        truth,
        pts,
        observe(truth, pts),
        PoseOptions(use_prior=False),
        pixel_covariances=cov,
        names=list("ABCDEFGH"),
    )
    assert res.converged and res.n_used == 8
    assert any("C, F" in w for w in res.warnings)
    with pytest.raises(SpcUsageError):
        solve_pose(truth, pts, observe(truth, pts), pixel_covariances=cov[:3])
    with pytest.raises(SpcUsageError):
        PoseOptions(sigma_floor_px=-1.0)
    # the floor: a zero covariance (a perfect correlation) is weighted by the floor, not infinitely
    zero = np.zeros((8, 2, 2))
    res = solve_pose(truth, pts, observe(truth, pts), PoseOptions(use_prior=False), pixel_covariances=zero)
    assert res.converged and not res.warnings


def test_truth_recovered_from_several_pixel_apriori_error():
    rng = np.random.default_rng(42)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, 30)
    y = observe(truth, pts, rng, 0.1)
    # 4 m of position and 1e-3 rad (5 px) of attitude at 5 km: 5–10 px a-priori residuals
    start = perturbed(truth, [0.004, -0.003, 0.002], [1.0e-3, -0.6e-3, 2e-3])
    res = solve_pose(start, pts, y, PoseOptions(use_prior=False))
    assert 5.0 <= res.rms_before <= 10.0, res.rms_before
    assert res.converged and res.iterations <= 5
    assert nees(truth, res) < stats.chi2.ppf(0.999, 6)
    assert 0.07 < res.rms_after < 0.16  # the 0.1 px noise remains
    np.testing.assert_allclose(res.position, truth.position, atol=5 * res.sigma_position.max())
    assert res.cost_history[0] > 1e4 > res.cost_history[-1]
    assert res.dof == 54 and abs(res.chi2 - res.cost) < 1e-9
    # 1σ, correlation and covariance agree
    np.testing.assert_allclose(res.correlation * np.outer(res.sigmas, res.sigmas), res.covariance)
    np.testing.assert_allclose(np.diag(res.correlation), 1.0)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), model=st.sampled_from(["NONE", "OWEN"]))
def test_noise_free_solution_is_exact(seed, model):
    rng = np.random.default_rng(seed)
    truth = make_camera(rng, range_km=rng.uniform(2, 200), model=model)
    pts = make_landmarks(rng, truth, int(rng.integers(4, 40)))
    rng_km = np.linalg.norm(truth.position)
    start = perturbed(truth, rng.normal(scale=1e-3 * rng_km, size=3), rng.normal(scale=1e-3, size=3))
    res = solve_pose(start, pts, observe(truth, pts), PoseOptions(use_prior=False))
    assert res.converged
    assert res.rms_after < 1e-7
    np.testing.assert_allclose(res.position, truth.position, atol=1e-7 * rng_km)
    np.testing.assert_allclose(res.rotation, truth.rotation, atol=1e-9)
    # delta_* describe the change from the a-priori pose
    np.testing.assert_allclose(res.position - start.position, res.delta_position, atol=1e-12 * rng_km)
    np.testing.assert_allclose(
        rot_from_rotvec(-res.delta_attitude) @ start.rotation, res.rotation, atol=1e-12
    )


def test_prior_pulls_towards_apriori_and_weak_prior_equals_no_prior():
    rng = np.random.default_rng(7)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, 10)
    y = observe(truth, pts, rng, 0.1)
    start = perturbed(truth, [0.01, 0.01, -0.01], [1e-3, 1e-3, -1e-3])
    free = solve_pose(start, pts, y, PoseOptions(use_prior=False))
    weak = solve_pose(
        start, pts, y, PoseOptions(), prior_sigma_position=[1e3] * 3, prior_sigma_attitude=[10.0] * 3
    )
    tight = solve_pose(  # the formal covariance (a prior this tight makes cost/dof >> 1)
        start,
        pts,
        y,
        PoseOptions(scale_covariance=False),
        prior_sigma_position=[1e-8] * 3,
        prior_sigma_attitude=[1e-11] * 3,
    )
    np.testing.assert_allclose(weak.position, free.position, atol=1e-9)
    assert np.linalg.norm(tight.delta_position) < 1e-7 and np.linalg.norm(tight.delta_attitude) < 1e-9
    assert tight.sigma_position.max() < 1e-8 and free.prior_used is False and weak.prior_used
    # covariance with the prior is never larger than without
    assert np.all(
        np.linalg.eigvalsh(free.covariance - weak.covariance) > -1e-12 * np.abs(free.covariance).max()
    )


def test_zero_or_infinite_prior_sigmas_mean_no_constraint():
    rng = np.random.default_rng(8)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, 10)
    y = observe(truth, pts, rng, 0.1)
    free = solve_pose(truth, pts, y, PoseOptions(use_prior=False))
    res = solve_pose(
        truth,
        pts,
        y,
        PoseOptions(),
        prior_sigma_position=[0.0, 0.0, 0.0],
        prior_sigma_attitude=[np.inf, np.nan, 0.0],
    )
    assert not res.prior_used and len(res.warnings) == 2
    np.testing.assert_allclose(res.position, free.position, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# landmark modes
# ------------------------------------------------------------------------------------------------


def test_estimate_and_consider_modes_are_consistent_fixed_is_not():
    """Landmarks off by σ_lmk = 0.5 m (≈ 0.5 px): fixed mode is overconfident, the others are not."""
    sig_l = 5e-4
    out = {"fixed": [], "estimate": [], "consider": [], "lmk": []}
    for seed in range(60):
        rng = np.random.default_rng(1000 + seed)
        truth = make_camera(rng)
        pts_true = make_landmarks(rng, truth, 20)
        pts_cat = pts_true + rng.normal(scale=sig_l, size=pts_true.shape)  # catalogue positions
        y = observe(truth, pts_true, rng, 0.1)
        start = perturbed(truth, rng.normal(size=3) * SIG_P, rng.normal(size=3) * SIG_A)
        kw = dict(
            prior_sigma_position=SIG_P, prior_sigma_attitude=SIG_A, landmark_sigmas=np.full((20, 3), sig_l)
        )
        for mode in ("fixed", "estimate", "consider"):
            res = solve_pose(start, pts_cat, y, PoseOptions(landmark_mode=mode, reject_outliers=False), **kw)
            if mode == "fixed":  # the formal covariance; scaled by cost/dof it is far less overconfident
                formal = dataclasses.replace(res, covariance=res.covariance_formal)
                out["fixed"].append(nees(truth, formal))
                out.setdefault("fixed_scaled", []).append(nees(truth, res))
                continue
            out[mode].append(nees(truth, res))
            if mode == "estimate":
                err = pts_true - (pts_cat + res.landmark_corrections)
                out["lmk"].extend(
                    np.einsum("ni,nij,nj->n", err, np.linalg.inv(res.landmark_covariances), err)
                )
            if mode == "consider":
                assert np.all(np.diag(res.covariance) >= np.diag(res.covariance_no_consider))
    mean = {k: float(np.mean(v)) for k, v in out.items()}
    # standard errors of the means here: ≈ 0.4 (pose, 60 draws) and ≈ 0.07 (1200 landmark draws)
    assert mean["fixed"] > 20.0, mean  # clearly inconsistent (≈ 170)
    assert mean["fixed_scaled"] < 0.1 * mean["fixed"], mean  # cost/dof scaling absorbs most of it
    assert abs(mean["estimate"] - 6.0) < 1.5, mean
    assert abs(mean["consider"] - 6.0) < 1.5, mean
    assert abs(mean["lmk"] - 3.0) < 0.3, mean


def test_landmark_modes_need_sigmas_and_valid_names():
    with pytest.raises(SpcUsageError):
        PoseOptions(landmark_mode="wobble")
    with pytest.raises(SpcUsageError):
        PoseOptions(estimate_landmarks=True, landmark_mode="consider")
    assert PoseOptions(estimate_landmarks=True).landmark_mode == "estimate"
    with pytest.raises(SpcUsageError):
        PoseOptions(sigma_px=0)
    rng = np.random.default_rng(1)
    cam = make_camera(rng)
    pts = make_landmarks(rng, cam, 5)
    with pytest.raises(SpcUsageError, match="landmark sigmas"):
        solve_pose(cam, pts, observe(cam, pts), PoseOptions(landmark_mode="estimate"))
    with pytest.raises(SpcUsageError):
        solve_pose(cam, pts, observe(cam, pts)[:4])


# ------------------------------------------------------------------------------------------------
# outliers, too few landmarks, degenerate geometry
# ------------------------------------------------------------------------------------------------


def _outlier_scene(seed, n=30, bad=(3, 11, 25), size=20.0):
    rng = np.random.default_rng(seed)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, n)
    y = observe(truth, pts, rng, 0.1)
    ang = rng.uniform(0, 2 * np.pi, len(bad))
    y[list(bad)] += size * np.stack([np.cos(ang), np.sin(ang)], axis=-1)
    start = perturbed(truth, [0.003, 0.002, -0.002], [5e-4, -5e-4, 1e-3])
    names = [f"LM{i:04d}" for i in range(n)]
    return truth, start, pts, y, names


@pytest.mark.parametrize("mode", ["fixed", "estimate", "consider"])
def test_outliers_at_20px_are_rejected_and_named(mode):
    for seed in range(5 if mode == "fixed" else 2):
        truth, start, pts, y, names = _outlier_scene(seed)
        # landmark σ 0.1 m (0.1 px): a 20 px error cannot hide in a landmark correction
        res = solve_pose(
            start,
            pts,
            y,
            PoseOptions(landmark_mode=mode),
            names=names,
            landmark_sigmas=np.full(pts.shape, 1e-4),
        )
        assert sorted(r.name for r in res.rejected) == ["LM0003", "LM0011", "LM0025"]
        # at rejection time an estimated landmark has absorbed about half of its 20 px (σ_lmk ≈ σ_px)
        least = 15 if mode != "estimate" else 7
        assert all(r.reason == "outlier" and "px" in r.detail and r.residual_px > least for r in res.rejected)
        assert [res.status[i] for i in (3, 11, 25)] == ["rejected-outlier"] * 3
        assert res.n_used == 27 and not res.used[[3, 11, 25]].any()
        assert nees(truth, res) < stats.chi2.ppf(0.999, 6)
        # residuals of the rejected landmarks are still reported (≈ 20 px), the others are ≈ noise
        assert np.all(np.linalg.norm(res.residuals_after[[3, 11, 25]], axis=1) > 15)
        assert res.rms_after < 0.2
        assert "rejected LM0003" in "\n".join(res.summary_lines())
        assert res.pose_dict()["rejected"][0]["reason"] == "outlier"


def test_absolute_pixel_threshold_and_rejection_off():
    truth, start, pts, y, names = _outlier_scene(9, bad=(4,), size=3.0)
    res = solve_pose(start, pts, y, PoseOptions(reject_px=2.0), names=names)
    assert [r.name for r in res.rejected] == ["LM0004"] and "> 2 px" in res.rejected[0].detail
    res = solve_pose(start, pts, y, PoseOptions(reject_px=5.0), names=names)
    assert res.rejected == []
    res = solve_pose(start, pts, y, PoseOptions(reject_outliers=False), names=names)
    assert res.rejected == [] and res.n_used == 30


def test_robust_scale_keeps_all_when_sigma_px_is_too_optimistic():
    rng = np.random.default_rng(21)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, 30)
    y = observe(truth, pts, rng, 1.0)  # real noise 1 px, assumed 0.1 px
    res = solve_pose(truth, pts, y, PoseOptions(sigma_px=0.1))
    assert res.rejected == [] and res.reduced_chi2 > 50
    strict = solve_pose(truth, pts, y, PoseOptions(sigma_px=0.1, robust_scale=False))
    assert len(strict.rejected) == 15  # max_reject_fraction 0.5 caps it, and says so
    assert any("no more landmarks may be rejected" in w for w in strict.warnings)


def test_too_few_landmarks_is_a_pose_error():
    rng = np.random.default_rng(2)
    cam = make_camera(rng)
    pts = make_landmarks(rng, cam, 2)
    with pytest.raises(PoseError, match="too few landmarks: 2 usable, at least 3"):
        solve_pose(cam, pts, observe(cam, pts), PoseOptions(use_prior=False))
    assert issubclass(PoseError, SpcResultError) and PoseError.exit_code == 1
    # with a prior, one landmark is enough when the user allows it
    res = solve_pose(
        cam,
        pts[:1],
        observe(cam, pts[:1]) + 0.5,
        PoseOptions(min_landmarks=1),
        prior_sigma_position=SIG_P,
        prior_sigma_attitude=SIG_A,
    )
    assert res.converged and res.dof == 2
    # NaN measurements and landmarks behind the camera do not count
    y = observe(cam, pts)
    y[0] = np.nan
    with pytest.raises(PoseError, match="1 usable"):
        solve_pose(cam, pts, y, PoseOptions(), prior_sigma_position=SIG_P)


def test_collinear_landmarks_are_degenerate():
    rng = np.random.default_rng(4)
    cam = make_camera(rng)
    a, b = make_landmarks(rng, cam, 2)
    pts = a + np.linspace(0, 1, 8)[:, None] * (b - a)
    with pytest.raises(PoseError, match="degenerate geometry"):
        solve_pose(
            perturbed(cam, [1e-3, 0, 0], [0, 1e-4, 0]), pts, observe(cam, pts), PoseOptions(use_prior=False)
        )
    # a prior removes the degeneracy
    res = solve_pose(
        cam, pts, observe(cam, pts), PoseOptions(), prior_sigma_position=SIG_P, prior_sigma_attitude=SIG_A
    )
    assert res.converged and res.condition_number > 1e3


def test_unusable_landmarks_are_reported_not_dropped():
    rng = np.random.default_rng(6)
    cam = make_camera(rng)
    pts = make_landmarks(rng, cam, 8)
    behind = cam.position - (pts[0] - cam.position)
    pts = np.vstack([pts, behind, [np.nan] * 3])
    y = np.vstack([observe(cam, pts[:8]), [[500.0, 500.0], [1.0, 2.0]]])
    y[1] = [np.nan, 3.0]
    res = solve_pose(cam, pts, y, PoseOptions(use_prior=False), names=list("ABCDEFGHIJ"))
    assert (
        res.status[1] == "no-measurement"
        and res.status[8] == "behind-camera"
        and res.status[9] == "no-position"
    )
    assert {r.name: r.reason for r in res.rejected} == {
        "B": "no-measurement",
        "I": "behind-camera",
        "J": "no-position",
    }
    assert res.n_used == 7 and np.isnan(res.residuals_after[9]).all()


def test_not_converged_is_reported():
    rng = np.random.default_rng(12)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, 20)
    start = perturbed(truth, [0.05, -0.05, 0.05], [0.01, 0.01, -0.01])
    res = solve_pose(start, pts, observe(truth, pts, rng, 0.1), PoseOptions(max_iter=1, use_prior=False))
    assert not res.converged and res.iterations == 1 and "did not converge" in res.warnings[-1]


# ------------------------------------------------------------------------------------------------
# real data: Rosetta 67P, W48230079013 with FA0115, FC0098, GD0036
# ------------------------------------------------------------------------------------------------


def _rosetta():
    from spctool.formats.landmark import read_lmk
    from spctool.formats.sumfile import read_sum

    pic = read_sum(REAL / "W48230079013.SUM")
    names = [lm.name for lm in pic.landmarks]
    lmks = [read_lmk(REAL / f"{n}.LMK") for n in names]
    pts = np.array([lk.vlm for lk in lmks])
    y = np.array([[lm.sample, lm.line] for lm in pic.landmarks])
    return pic, Camera.from_picture(pic), names, pts, y, np.array([lk.sigma_lmk for lk in lmks])


def test_rosetta_three_landmarks_no_prior_exact_solution():
    pic, cam, names, pts, y, _ = _rosetta()
    res = solve_pose(cam, pts, y, PoseOptions(use_prior=False), names=names)
    centroid = pts.mean(axis=0)
    rng0 = np.linalg.norm(centroid - cam.position)
    rng1 = np.linalg.norm(centroid - res.position)
    solved = cam.with_pose(scobj=res.scobj, rotation=res.rotation)
    shift = np.hypot(*(np.array(solved.project(centroid)) - np.array(cam.project(centroid))))
    dp = np.linalg.norm(res.delta_position)
    dt = np.linalg.norm(res.delta_attitude)
    worst = np.abs(res.residuals_after).max()
    print(
        f"\nRosetta no prior: {res.iterations} iterations, residual max {worst:.2e} px,"
        f" |dp| = {dp:.3f} km, |dtheta| = {dt:.3e} rad, range {rng0:.3f} -> {rng1:.3f} km,"
        f" centroid shift {shift:.3f} px, cond {res.condition_number:.3g}"
    )
    # 6 equations, 6 unknowns: residuals vanish
    assert res.converged and res.dof == 0 and res.n_used == 3
    np.testing.assert_allclose(
        res.residuals_before, [[-0.83, -1.11], [-0.04, -0.45], [0.79, -0.17]], atol=0.02
    )
    assert np.abs(res.residuals_after).max() < 1e-6
    # the apparent pointing at the landmarks moves by about the ~1 px residuals …
    assert shift < 1.5
    # … while the pattern's ~1.7 % scale and shape misfit needs a viewpoint change of a few % of the range;
    # attitude and position move together (the camera orbits the landmarks)
    assert 1.0 < rng1 / rng0 < 1.08
    assert np.linalg.norm(res.delta_position) < 0.1 * rng0
    los0 = (centroid - cam.position) / rng0
    los1 = (centroid - res.position) / rng1
    orbit = math.acos(np.clip(los0 @ los1, -1, 1))
    assert abs(np.linalg.norm(res.delta_attitude) - orbit) < 0.02 and orbit < 0.1
    # the nearly degenerate geometry shows in the condition number and the σ
    assert 1e5 < res.condition_number < 1e9
    # independent check: scipy Levenberg–Marquardt on (Δp, rotation vector φ with T = Rot(φ)·T₀)

    def f(x):
        c = cam.with_pose(position=cam.position + x[:3], rotation=rot_from_rotvec(x[3:]) @ cam.rotation)
        return (np.stack(c.project(pts), axis=-1) - y).ravel()

    sol = least_squares(
        f, np.zeros(6), method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, x_scale=[1, 1, 1, 1e-2, 1e-2, 1e-2]
    )
    np.testing.assert_allclose(cam.position + sol.x[:3], res.position, atol=1e-6)
    np.testing.assert_allclose(rot_from_rotvec(sol.x[3:]) @ cam.rotation, res.rotation, atol=1e-8)


def test_rosetta_with_sum_prior_and_landmark_sigmas():
    pic, cam, names, pts, y, sig_l = _rosetta()
    res = solve_pose(
        cam,
        pts,
        y,
        PoseOptions(),
        prior_sigma_position=pic.sigma_vso,
        prior_sigma_attitude=pic.sigma_ptg,
        names=names,
    )
    print(
        f"\nRosetta with SUM prior: dp = {res.delta_position} km, dtheta = {res.delta_attitude} rad,"
        f" rms {res.rms_before:.3f} -> {res.rms_after:.3f} px"
    )
    assert res.converged and res.prior_used and res.dof == 6 and res.rejected == []
    assert res.rms_after < res.rms_before
    # the change stays within 3σ of the SUM's a-priori sigmas, and the sigmas shrink
    assert np.all(np.abs(res.delta_position) < 3 * pic.sigma_vso)
    assert np.all(np.abs(res.delta_attitude) < 3 * pic.sigma_ptg)
    # (formal sigmas: 0.75 px residuals against sigma_px 0.1 scale the reported ones by sqrt(cost/dof))
    formal = np.sqrt(np.diag(res.covariance_formal))
    assert np.all(formal[:3] <= pic.sigma_vso) and np.all(formal[3:] <= pic.sigma_ptg)
    assert res.covariance_scale == pytest.approx(res.reduced_chi2) and res.plausible
    np.testing.assert_allclose(res.covariance, res.covariance_formal * res.reduced_chi2)
    est = solve_pose(
        cam,
        pts,
        y,
        PoseOptions(landmark_mode="estimate"),
        prior_sigma_position=pic.sigma_vso,
        prior_sigma_attitude=pic.sigma_ptg,
        landmark_sigmas=sig_l,
        names=names,
    )
    assert est.converged and est.rms_after < res.rms_after
    assert np.all(np.abs(est.landmark_corrections) < 3 * sig_l)


# ------------------------------------------------------------------------------------------------
# fit quality: covariance scaled by cost/dof, implausible fits flagged (issue 16 gap 2)
# ------------------------------------------------------------------------------------------------


def test_covariance_scaled_by_cost_per_dof_only_above_one():
    rng = np.random.default_rng(21)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, 15)
    noisy = observe(truth, pts, rng, 0.3)  # 3x the assumed 0.1 px: cost/dof ~ 9
    res = solve_pose(truth, pts, noisy, PoseOptions(use_prior=False))
    assert 4.0 < res.reduced_chi2 < 20.0 and res.plausible
    assert res.covariance_scale == pytest.approx(res.cost / res.dof)
    np.testing.assert_allclose(res.covariance, res.covariance_formal * res.covariance_scale, rtol=1e-12)
    np.testing.assert_allclose(res.sigmas, np.sqrt(np.diag(res.covariance)))
    # the correlation does not change with a scalar factor
    d = np.sqrt(np.diag(res.covariance_formal))
    np.testing.assert_allclose(res.correlation, res.covariance_formal / np.outer(d, d), atol=1e-12)
    quiet = observe(truth, pts, np.random.default_rng(22), 0.05)  # cost/dof ~ 0.25: left alone
    res2 = solve_pose(truth, pts, quiet, PoseOptions(use_prior=False))
    assert res2.reduced_chi2 < 1.0 and res2.covariance_scale == 1.0 and res2.covariance_formal is None
    off = solve_pose(truth, pts, noisy, PoseOptions(use_prior=False, scale_covariance=False))
    np.testing.assert_allclose(off.covariance, res.covariance_formal)


def test_measurements_of_another_picture_are_implausible():
    """Pixels assigned to the wrong landmarks (as in another picture's table): flagged, with why."""
    rng = np.random.default_rng(23)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, 12)
    y = observe(truth, pts, rng, 0.1)
    wrong = y[rng.permutation(len(y))]
    res = solve_pose(truth, pts, wrong, PoseOptions(use_prior=False, reject_outliers=False))
    assert not res.plausible and "cost/dof" in res.implausible and "sigma_px" in res.implausible
    assert res.pose_dict()["plausible"] is False
    ok = solve_pose(truth, pts, y, PoseOptions(use_prior=False))
    assert ok.plausible and ok.pose_dict()["implausible"] is None
    assert 0.0 <= ok.position_attitude_correlation <= 1.0


@pytest.mark.parametrize("value", [1e300, -1e250, 1e154])
def test_absurd_but_finite_pixels_are_a_pose_error_not_a_crash(value):
    """A landmark table with a pixel of 1e300 (found by the fuzzer): numpy's LinAlgError from the
    normal equations becomes a PoseError (one line, exit 1), never an internal error."""
    from spctool.stages.pose import PoseError

    rng = np.random.default_rng(5)
    cam = make_camera(rng)
    pts = make_landmarks(rng, cam, 8)
    y = observe(cam, pts)
    y[3, 0] = value
    try:
        with np.errstate(all="ignore"):  # overflow on the way is expected (the command line hides it)
            res = solve_pose(cam, pts, y, PoseOptions(use_prior=False))
    except PoseError as exc:  # one line, exit 1 on the command line
        assert str(exc) and "\n" not in str(exc)
    else:  # the absurd row may instead be rejected as an outlier: then the pose must still be right
        assert res.converged and res.status[3] != "ok"
        np.testing.assert_allclose(res.scobj, cam.scobj, atol=1e-6)
