"""Tests of spctool.stages.pose_consistency and their use in solve_pose (issue 39): the χ² gate, the
prior–measurement test and the estimated prior scale.

Independent checks: the χ² quantile against scipy.stats; the normalised change q = dᵀ(P₀ − P)⁺d
against a brute-force linear-Gaussian computation (the measurement-only solution δ and Cov(δ) =
P₀ + P_m, q = δᵀ(P₀ + P_m)⁻¹δ, the same number by the information identity); and Monte Carlo over 100
seeds with the prior honest, understated ×10 and absent (NEES against χ²₆).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats
from test_pose import SIG_A, SIG_P, make_camera, make_landmarks, nees, observe, perturbed

from spctool.stages.pose import PoseOptions, solve_pose
from spctool.stages.pose_consistency import chi2_gate, chi2_quantile, prior_scale_step, prior_test


@pytest.mark.parametrize("dof", [0.5, 1, 1.5, 2, 3, 6, 17, 300, 5000, 1e5])
def test_chi2_quantile_matches_scipy(dof):
    """spctool's own quantile (no scipy.special import in navigate) against scipy's, both tails."""
    for p in (1e-12, 1e-6, 0.01, 0.3, 0.5, 0.7, 0.99, 0.999, 1 - 1e-8, 1 - 1e-12):
        assert chi2_quantile(dof, p) == pytest.approx(stats.chi2.ppf(p, dof), rel=1e-11), p
    assert math.isnan(chi2_quantile(0, 0.999))


def test_gate_names_the_worst_landmarks_with_their_share():
    rho2 = np.array([1.0, 50.0, 2.0, 20.0])
    g = chi2_gate(73.0, 2, rho2, ["A", "B", "C", "D"], 0.999)
    assert not g.consistent and [w[0] for w in g.worst] == ["B", "D", "C"]
    assert g.worst[0][2] == pytest.approx(50.0 / 73.0)
    assert "B (68 %)" in g.reason() and "13.8" in g.reason()  # χ²₂ 99.9 % = 13.82
    assert (
        chi2_gate(13.0, 2, rho2, list("ABCD")).consistent
        and not chi2_gate(13.0, 2, rho2, list("ABCD")).reason()
    )


def test_normalised_change_equals_the_measurement_only_innovation():
    """Linear-Gaussian case by hand: prior N(0, P₀) on 6 states, measurement information A = HᵀWH
    (full rank), measurement-only estimate δ.  The joint estimate is d = (A + P₀⁻¹)⁻¹Aδ with
    P = (A + P₀⁻¹)⁻¹, and dᵀ(P₀ − P)⁻¹d must equal δᵀ(P₀ + A⁻¹)⁻¹δ."""
    rng = np.random.default_rng(5)
    h = rng.normal(size=(20, 6))
    a = h.T @ h
    sig0 = np.array([0.5, 1.0, 2.0, 0.3, 0.7, 1.1])
    info = 1.0 / sig0**2
    p = np.linalg.inv(a + np.diag(info))
    delta = rng.normal(size=6) * 2.0
    d = p @ a @ delta
    expect = float(delta @ np.linalg.solve(np.diag(sig0**2) + np.linalg.inv(a), delta))
    t = prior_test(d, info, p, float(np.sum(info * d * d)), 10.0)
    assert t.dof == 6 and t.nis == pytest.approx(expect, rel=1e-9)
    np.testing.assert_allclose(t.change_sigma, d / sig0)
    # a component without prior carries no test; uninformed directions are left out
    info2 = info.copy()
    info2[2] = 0.0
    p2 = np.linalg.inv(a + np.diag(info2))
    d2 = p2 @ a @ delta
    t2 = prior_test(d2, info2, p2, 1.0, 10.0)
    assert t2.dof == 5 and math.isnan(t2.change_sigma[2])
    assert prior_test(np.zeros(6), np.zeros(6), p, 0.0, 1.0).dof == 0
    # measurements noisier than their weights (s = 4): Cov(d) = P(A P0 A + s A)P, by hand
    cov_d = p @ (a @ np.diag(sig0**2) @ a + 4.0 * a) @ p
    t4 = prior_test(d, info, p, 1.0, 10.0, noise_scale=4.0)
    assert t4.dof == 6 and t4.nis == pytest.approx(float(d @ np.linalg.solve(cov_d, d)), rel=1e-9)
    assert t4.nis < t.nis


def _scene(seed, factor, n=30):
    rng = np.random.default_rng(seed)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, n)
    start = perturbed(truth, rng.normal(size=3) * SIG_P * factor, rng.normal(size=3) * SIG_A * factor)
    return truth, pts, start, observe(truth, pts, rng, 0.1)


@pytest.mark.parametrize(
    "case, factor, use_prior, auto",
    [
        ("honest", 1.0, True, False),
        ("understated x10", 10.0, True, False),
        ("understated x10, scale estimated", 10.0, True, True),
        ("absent", 10.0, False, False),
    ],
)
def test_prior_honest_understated_and_absent_over_100_seeds(case, factor, use_prior, auto):
    """100 seeds: the honest prior and no prior are never contradicted and the NEES follows χ²₆; a
    prior whose sigmas are 10x too small is reported contradicted every time (the pose is not ok)
    and, with the scale estimated, widened ~10x with a NEES that follows χ²₆ again."""
    values, verdicts, scales = [], [], []
    for seed in range(100):
        truth, pts, start, y = _scene(seed, factor)
        opts = PoseOptions(sigma_px=0.1, use_prior=use_prior, estimate_prior_scale=auto)
        res = solve_pose(start, pts, y, opts, prior_sigma_position=SIG_P, prior_sigma_attitude=SIG_A)
        assert res.converged
        values.append(nees(truth, res))
        verdicts.append(res.verdict)
        scales.append(res.prior_scale)
    values = np.array(values)
    if case == "understated x10":
        assert verdicts == ["prior-contradicted"] * 100
        return
    assert verdicts.count("ok") >= 98, verdicts  # two 99.9 % tests: P(> 2 of 100 flagged) < 1e-3
    assert abs(values.mean() - 6.0) < 1.2, values.mean()
    assert stats.kstest(values, "chi2", args=(6,)).pvalue > 1e-3
    if auto:
        assert 5.0 < np.median(scales) < 20.0
    else:
        assert set(scales) == {1.0}


def test_contradicted_prior_is_one_line_with_figure_and_remedy():
    truth, pts, start, y = _scene(3, 10.0)
    res = solve_pose(start, pts, y, PoseOptions(), prior_sigma_position=SIG_P, prior_sigma_attitude=SIG_A)
    assert res.verdict == "prior-contradicted"
    line = res.prior_contradicted
    assert "\n" not in line and "--no-prior" in line and "--prior-scale auto" in line
    assert "understate" in line and "sigma" in line
    assert res.pose_dict()["verdict"] == "prior-contradicted"
    assert res.pose_dict()["prior_check"]["contradicted"] is True
    assert any(h.startswith("verdict: prior-contradicted") for h in res.header_lines())
    assert any(s.startswith("warning: prior contradicted") for s in res.summary_lines())
    # the factor to widen by is about the understatement
    assert 5.0 < prior_scale_step(res.prior_check) < 20.0
    # the scale estimated: the prior agrees, the pose is ok and the widening is said
    auto = solve_pose(
        start,
        pts,
        y,
        PoseOptions(estimate_prior_scale=True),
        prior_sigma_position=SIG_P,
        prior_sigma_attitude=SIG_A,
    )
    assert auto.verdict == "ok" and auto.prior_scale > 3.0
    assert any(w.startswith("prior widened x") for w in auto.warnings)
    # a given scale is applied as is
    given = solve_pose(
        start, pts, y, PoseOptions(prior_scale=10.0), prior_sigma_position=SIG_P, prior_sigma_attitude=SIG_A
    )
    assert given.prior_scale == 10.0 and given.verdict == "ok"


def test_biased_measurements_are_inconsistent_not_a_contradicted_prior():
    """Half the landmarks shifted by (1.5, −1.2) px pull the attitude ~10 sigma of a tight (honest)
    prior away; the measurements' own χ² says they are the problem: inconsistent, not
    prior-contradicted — without the noise scale in the prior test it would be (q ≈ 300)."""
    for seed in (1, 2):
        rng = np.random.default_rng(seed)
        truth = make_camera(rng)
        pts = make_landmarks(rng, truth, 30)
        sig_a = SIG_A / 10
        start = perturbed(truth, rng.normal(size=3) * SIG_P, rng.normal(size=3) * sig_a)
        bad = observe(truth, pts, rng, 0.1)
        bad[:15] += [1.5, -1.2]
        res = solve_pose(
            start,
            pts,
            bad,
            PoseOptions(reject_outliers=False),
            prior_sigma_position=SIG_P,
            prior_sigma_attitude=sig_a,
        )
        assert res.verdict == "inconsistent", (res.verdict, res.verdict_reason)
        assert not res.prior_check.contradicted
        e = np.concatenate([res.delta_position, res.delta_attitude])
        info = np.r_[1 / SIG_P**2, 1 / sig_a**2]
        assert prior_test(e, info, res.covariance_formal, 1.0, 1.0).contradicted  # noise scale 1


def test_inconsistent_fit_is_never_ok_and_names_the_worst_landmarks():
    """Three landmarks 1.5 px off (15 sigma, below the outlier test's robust limit when rejection is
    off) make χ² exceed its 99.9 % quantile: inconsistent, those three named, covariance scaled."""
    truth, pts, start, y = _scene(7, 1.0, n=20)
    bad = y.copy()
    bad[[2, 9, 15]] += 1.5
    res = solve_pose(
        start,
        pts,
        bad,
        PoseOptions(reject_outliers=False),
        prior_sigma_position=SIG_P,
        prior_sigma_attitude=SIG_A,
    )
    assert res.verdict == "inconsistent" and not res.consistent
    assert {w[0] for w in res.gate.worst} == {"#3", "#10", "#16"}
    assert res.covariance_scale == pytest.approx(res.cost / res.dof)
    assert "worst landmarks" in res.inconsistent and res.pose_dict()["consistency"]["consistent"] is False
    good = solve_pose(start, pts, y, PoseOptions(), prior_sigma_position=SIG_P, prior_sigma_attitude=SIG_A)
    assert good.verdict == "ok" and good.consistent and good.inconsistent == ""


# ------------------------------------------------------------------------------------------------
# model error estimated from the residuals (--weights surface)
# ------------------------------------------------------------------------------------------------


def _covs(rng, n, lo=0.005, hi=0.03):
    s = np.exp(rng.uniform(np.log(lo), np.log(hi), (n, 2)))
    rho = rng.uniform(-0.6, 0.6, n)
    c = np.empty((n, 2, 2))
    c[:, 0, 0], c[:, 1, 1] = s[:, 0] ** 2, s[:, 1] ** 2
    c[:, 0, 1] = c[:, 1, 0] = rho * s[:, 0] * s[:, 1]
    return c


def test_model_error_estimated_from_the_residuals_makes_the_pose_covariance_honest():
    """Pixel errors = the peaks' covariances Cᵢ (5–30 mpx) plus an isotropic 0.04 px model error that
    the covariances do not hold: weighted with Cᵢ alone the NEES is far above χ²₆; with the model
    error estimated (τ ≈ 0.04 px) it follows χ²₆ over 100 seeds.  With its common part too (the
    default, ``common_model_error``: a shift τ²I shared by the landmarks, which this world does not
    have) the covariance is larger, never smaller: NEES below χ²₆'s mean, not far below."""
    tau_true = 0.04
    est, with_tau, without, with_common = [], [], [], []
    for seed in range(100):
        rng = np.random.default_rng(500 + seed)
        truth = make_camera(rng)
        pts = make_landmarks(rng, truth, 25)
        cov = _covs(rng, 25)
        full = cov + tau_true**2 * np.eye(2)
        y = observe(truth, pts) + np.einsum("mij,mj->mi", np.linalg.cholesky(full), rng.normal(size=(25, 2)))
        start = perturbed(truth, rng.normal(size=3) * SIG_P, rng.normal(size=3) * SIG_A)
        kw = dict(pixel_covariances=cov, prior_sigma_position=SIG_P, prior_sigma_attitude=SIG_A)
        res = solve_pose(start, pts, y, PoseOptions(common_model_error=False), **kw)
        est.append(res.model_error_px)
        with_tau.append(nees(truth, res))
        with_common.append(nees(truth, solve_pose(start, pts, y, PoseOptions(), **kw)))
        if seed < 30:
            off = solve_pose(start, pts, y, PoseOptions(model_error=False, scale_covariance=False), **kw)
            without.append(nees(truth, off))
            assert off.model_error_px == 0.0
    est, with_tau = np.array(est), np.array(with_tau)
    assert np.median(est) == pytest.approx(tau_true, rel=0.15), np.median(est)
    assert abs(with_tau.mean() - 6.0) < 1.2, with_tau.mean()
    assert stats.kstest(with_tau, "chi2", args=(6,)).pvalue > 1e-3
    assert np.mean(without) > 15.0, np.mean(without)
    assert 3.0 < np.mean(with_common) < 6.0, np.mean(with_common)


def test_model_error_is_capped_and_the_rest_left_to_the_gate():
    """A misfit of 0.5 px against 0.1 px sigma_px: τ stops at sigma_px and the χ² gate fails; honest
    covariances (no model error) are left alone in most seeds."""
    rng = np.random.default_rng(77)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, 25)
    cov = _covs(rng, 25)
    y = observe(truth, pts) + rng.normal(scale=0.5, size=(25, 2))
    res = solve_pose(truth, pts, y, PoseOptions(), pixel_covariances=cov)
    assert res.model_error_px == pytest.approx(0.1) and res.verdict == "inconsistent"
    assert any("model error 0.1000 px" in s for s in res.summary_lines())
    zero = 0
    for seed in range(40):
        rng = np.random.default_rng(900 + seed)
        truth = make_camera(rng)
        pts = make_landmarks(rng, truth, 25)
        cov = _covs(rng, 25)
        y = observe(truth, pts) + np.einsum("mij,mj->mi", np.linalg.cholesky(cov), rng.normal(size=(25, 2)))
        zero += solve_pose(truth, pts, y, PoseOptions(), pixel_covariances=cov).model_error_px == 0.0
    assert zero >= 32  # 90 % quantile: ~36 of 40 expected; P(< 32) ≈ 1 %


def test_model_error_by_hand():
    """Cᵢ = σ²I: χ²(τ²) = Σ|rᵢ|²/(σ² + τ²), so τ² = Σ|rᵢ|²/dof − σ² exactly."""
    from spctool.stages.pose_consistency import model_error

    rng = np.random.default_rng(3)
    r = rng.normal(scale=0.05, size=(20, 2))
    c = np.broadcast_to(0.01**2 * np.eye(2), (20, 2, 2))
    dof = 34
    expect = math.sqrt(np.sum(r * r) / dof - 0.01**2)
    assert model_error(r, c, dof, cap=1.0) == pytest.approx(expect, rel=1e-5)
    assert model_error(r, c, dof, cap=0.02) == 0.02  # capped
    assert model_error(r * 0.1, c, dof, cap=1.0) == 0.0  # within the covariances
    assert model_error(r, c, 0, cap=1.0) == 0.0


# ------------------------------------------------------------------------------------------------
# an error common to the picture's landmarks (Woodbury)


def _dense_problem(problem, state):
    """HᵀR⁻¹H, HᵀR⁻¹r and rᵀR⁻¹r with R = blkdiag(Wᵢ⁻¹) + U·Uᵀ inverted as a dense 2M × 2M matrix (U the
    problem's error modes stacked, 2M × k; a common C: U = [L; …; L] written out here from C)."""
    j = state.camera.project_with_jacobians(problem.pts(state))
    r = (problem.meas - np.stack([j.sample, j.line], axis=-1)).reshape(-1)
    h = np.concatenate([j.position, j.attitude], axis=-1).reshape(-1, 6)
    m = problem.meas.shape[0]
    big = np.zeros((2 * m, 2 * m))
    for i in range(m):
        big[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = np.linalg.inv(problem.wts[i])
    if problem.common_dense is not None:
        u = np.tile(np.eye(2), (m, 1))
        extra = u @ problem.common_dense @ u.T
    else:
        u = problem.modes.reshape(2 * m, -1)
        extra = u @ u.T
    rinv = np.linalg.inv(big + extra)
    return h.T @ rinv @ h, h.T @ rinv @ r, float(r @ rinv @ r)


@pytest.mark.parametrize("common", ["full", "rank one", "patterns"])
def test_common_error_woodbury_equals_the_dense_inverse(common):
    """The normal matrix, gradient and χ² with the common term (Woodbury, O(M)) equal those of the
    dense 2M × 2M measurement covariance, for a full and a rank-one (Sun-aligned) C, and for three
    arbitrary error patterns over the landmarks (with a common C)."""
    from spctool.stages._pose_problem import _Prior, _Problem

    rng = np.random.default_rng(11)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, 12)
    cov = _covs(rng, 12)
    y = observe(truth, pts) + rng.normal(scale=0.02, size=(12, 2))
    sun = np.array([math.cos(0.7), math.sin(0.7)])
    c = np.array([[3e-3, 1e-3], [1e-3, 2e-3]]) if common == "full" else 0.05**2 * np.outer(sun, sun)
    start = perturbed(truth, rng.normal(size=3) * SIG_P, rng.normal(size=3) * SIG_A)
    from spctool.stages.pose import _error_modes

    patterns = rng.normal(scale=0.03, size=(12, 2, 3)) if common == "patterns" else None
    modes = _error_modes(c, patterns, 12, "fixed")
    prob = _Problem(
        start, pts, y, np.linalg.inv(cov), _Prior(np.zeros(6)), "fixed", None, PoseOptions(), modes
    )
    prob.common_dense = None if common == "patterns" else c
    s = prob.start()
    n, g, _ = prob.normal(s)
    nd, gd, chi2d = _dense_problem(prob, s)
    np.testing.assert_allclose(n, nd, rtol=1e-9, atol=1e-9 * np.abs(nd).max())
    np.testing.assert_allclose(g, gd, rtol=1e-9, atol=1e-9 * np.abs(gd).max())
    assert prob.cost(s)[1] == pytest.approx(chi2d, rel=1e-10)
    # C = 0 is the independent problem exactly
    plain = _Problem(start, pts, y, np.linalg.inv(cov), _Prior(np.zeros(6)), "fixed", None, PoseOptions())
    zero = _Problem(
        start,
        pts,
        y,
        np.linalg.inv(cov),
        _Prior(np.zeros(6)),
        "fixed",
        None,
        PoseOptions(),
        np.zeros((12, 2, 1)),
    )
    assert np.array_equal(plain.normal(s)[0], zero.normal(s)[0])


def _common_error_world(seed):
    """One seed of the common-error world: 25 landmarks whose pixel errors are the peaks' covariances Cᵢ
    (5–30 mpx) plus one shift shared by all, 0.03 px along a random 'Sun' (and 0.005 px isotropic).
    Returns (true camera, points, Cᵢ, the common covariance C, observed pixels, a-priori camera)."""
    rng = np.random.default_rng(1300 + seed)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, 25)
    cov = _covs(rng, 25)
    a = rng.uniform(0.0, 2.0 * math.pi)
    sun = np.array([math.cos(a), math.sin(a)])
    c = 0.03**2 * np.outer(sun, sun) + 0.005**2 * np.eye(2)
    shift = np.linalg.cholesky(c) @ rng.normal(size=2)
    noise = np.einsum("mij,mj->mi", np.linalg.cholesky(cov), rng.normal(size=(25, 2)))
    y = observe(truth, pts) + noise + shift
    start = perturbed(truth, rng.normal(size=3) * SIG_P, rng.normal(size=3) * SIG_A)
    return truth, pts, cov, c, y, start


def test_common_error_makes_the_pose_covariance_honest_over_100_seeds():
    """Pixel errors = the peaks' covariances Cᵢ (5–30 mpx) plus one 0.03 px shift common to all 25
    landmarks along a random 'Sun' direction: weighted with Cᵢ the NEES is far above χ²₆ (the residuals
    cannot show the shift: the attitude absorbs it, τ stays ~0); with the common term C in the
    measurement covariance it follows χ²₆ over 100 seeds."""
    with_c, without = [], []
    for seed in range(100):
        truth, pts, cov, c, y, start = _common_error_world(seed)
        kw = dict(pixel_covariances=cov, prior_sigma_position=SIG_P, prior_sigma_attitude=SIG_A)
        res = solve_pose(start, pts, y, PoseOptions(), common_covariance=c, **kw)
        assert res.converged and res.common_covariance is not None
        with_c.append(nees(truth, res))
        if seed < 30:
            without.append(nees(truth, solve_pose(start, pts, y, PoseOptions(), **kw)))
    with_c = np.array(with_c)
    assert abs(with_c.mean() - 6.0) < 1.2, with_c.mean()
    assert stats.kstest(with_c, "chi2", args=(6,)).pvalue > 1e-3
    assert np.mean(without) > 20.0, np.mean(without)


def test_common_error_is_checked():
    from spctool.errors import SpcUsageError

    rng = np.random.default_rng(5)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, 6)
    y = observe(truth, pts)
    for bad in (np.eye(3), -np.eye(2), np.full((2, 2), np.nan)):
        with pytest.raises(SpcUsageError):
            solve_pose(truth, pts, y, common_covariance=bad)
    with pytest.raises(SpcUsageError, match="fixed"):
        solve_pose(
            truth,
            pts,
            y,
            PoseOptions(landmark_mode="consider"),
            landmark_sigmas=np.full((6, 3), 1e-4),
            common_covariance=np.eye(2) * 1e-3,
        )


# ------------------------------------------------------------------------------------------------
# uniform weights, calibrated covariance (the sandwich)


def test_uniform_fit_under_the_calibrated_covariance_equals_the_dense_sandwich():
    """estimate_weights="uniform": the pose is the uniform fit's (the same numbers), and its covariance
    is N⁻¹(HᵀW·R·WH + P₀⁻¹)N⁻¹ with R = blkdiag(Cᵢ + floor²I) + U·Uᵀ written out densely (2M × 2M),
    N = HᵀWH + P₀⁻¹, at the solution."""
    from spctool.stages.pose import _error_modes

    rng = np.random.default_rng(21)
    truth = make_camera(rng)
    pts = make_landmarks(rng, truth, 10)
    cov = _covs(rng, 10)
    y = observe(truth, pts) + rng.normal(scale=0.02, size=(10, 2))
    start = perturbed(truth, rng.normal(size=3) * SIG_P, rng.normal(size=3) * SIG_A)
    patterns = rng.normal(scale=0.02, size=(10, 2, 2))
    c = np.array([[4e-4, 1e-4], [1e-4, 2e-4]])
    opts = PoseOptions(model_error=False)
    kw = dict(prior_sigma_position=SIG_P, prior_sigma_attitude=SIG_A)
    uni = solve_pose(start, pts, y, opts, **kw)
    res = solve_pose(
        start, pts, y, opts, pixel_covariances=cov, common_covariance=c, error_modes=patterns,
        estimate_weights="uniform", **kw,
    )  # fmt: skip
    np.testing.assert_array_equal(res.position, uni.position)
    assert res.verdict == uni.verdict and res.prior_check.nis == pytest.approx(uni.prior_check.nis, rel=1e-12)
    cam = start.with_pose(scobj=res.scobj, rotation=res.rotation)
    j = cam.project_with_jacobians(pts)
    h = np.concatenate([j.position, j.attitude], axis=-1).reshape(-1, 6)
    w = np.eye(20) / 0.1**2
    big = np.zeros((20, 20))
    for i in range(10):
        big[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = cov[i] + 0.001**2 * np.eye(2)
    u = _error_modes(c, patterns, 10, "fixed").reshape(20, -1)
    r_dense = big + u @ u.T
    from spctool.stages.pose import so3_right_jacobian_inv

    jp = np.eye(6)
    jp[3:, 3:] = so3_right_jacobian_inv(res.delta_attitude)
    info = np.concatenate([np.full(3, 1.0 / SIG_P**2), np.full(3, 1.0 / SIG_A**2)])
    n_prior = (jp.T * info) @ jp
    n = h.T @ w @ h + n_prior
    ninv = np.linalg.inv(n)
    expect = ninv @ (h.T @ w @ r_dense @ w @ h + n_prior) @ ninv
    np.testing.assert_allclose(res.covariance, expect, rtol=1e-6, atol=1e-6 * np.abs(expect).max())
    with pytest.raises(Exception, match="estimate_weights"):
        solve_pose(start, pts, y, opts, estimate_weights="inverse")


def test_uniform_fit_with_the_calibrated_covariance_is_honest_over_100_seeds():
    """The world of the common-error test (peaks' covariances Cᵢ plus one 0.03 px shift along a random
    'Sun' shared by the 25 landmarks): fitted with uniform 0.1 px weights, the formal covariance is
    too large (NEES mean 2.5); under the calibrated covariance (Cᵢ and the common C) the NEES of the same
    poses follows χ²₆."""
    values, formal = [], []
    for seed in range(100):
        truth, pts, cov, c, y, start = _common_error_world(seed)
        kw = dict(prior_sigma_position=SIG_P, prior_sigma_attitude=SIG_A)
        opts = PoseOptions(model_error=False)
        res = solve_pose(
            start, pts, y, opts, pixel_covariances=cov, common_covariance=c, estimate_weights="uniform", **kw
        )
        values.append(nees(truth, res))
        if seed < 20:
            formal.append(nees(truth, solve_pose(start, pts, y, opts, **kw)))
    values = np.array(values)
    assert abs(values.mean() - 6.0) < 1.2, values.mean()
    assert stats.kstest(values, "chi2", args=(6,)).pvalue > 1e-3
    assert np.mean(formal) < 4.0, np.mean(formal)  # 0.1 px: too large for most seeds (2.5 here)
