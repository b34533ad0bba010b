"""The bundle adjustment of ``spctool geometry`` (spctool.stages.bundle) against independent computations:
scipy's least_squares with a finite-difference Jacobian, truth worlds (1/√N, NEES over 100 seeds),
planted outliers, a perturbed camera, and the gauge."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.optimize import least_squares

from spctool.geometry.frames import rot_from_rotvec, rotvec_from_rot
from spctool.sim.bundle_world import bundle_world, demo_camera
from spctool.stages.bundle import BundleError, BundleOptions, BundleProblem, solve_bundle
from spctool.stages.pose import PoseOptions, solve_pose


def _exact_problem(world, **changes) -> BundleProblem:
    """The world's problem with the a-priori values at the truth and exact measurements."""
    p = world.problem
    cams = [
        c.with_pose(position=world.true_positions[j], rotation=world.true_rotations[j])
        for j, c in enumerate(p.cameras)
    ]
    return dataclasses.replace(
        p,
        cameras=cams,
        landmark_positions=world.true_landmarks.copy(),
        obs_pixel=world.true_pixels.copy(),
        **changes,
    )


def test_exact_measurements_leave_everything_unchanged():
    w = bundle_world(10, 60, seed=4)
    r = solve_bundle(_exact_problem(w))
    ok = np.array([s == "ok" for s in r.landmark_status])
    assert ok.sum() > 40
    assert np.max(np.abs(r.landmark_positions - w.true_landmarks)) < 1e-9
    assert np.max(np.abs(r.positions - w.true_positions)) < 1e-9
    assert np.max(np.abs(r.delta_attitude)) < 1e-10
    # nothing flagged: every measurement used (those of landmarks seen once only for the poses)
    assert set(r.counts()) <= {"ok", "undetermined"}
    assert sum(r.counts().values()) == w.problem.obs_picture.size
    assert np.max(r.rho_after[[s == "ok" for s in r.obs_status]]) < 1e-6


def test_solution_and_covariance_equal_a_brute_force_least_squares():
    """scipy's least_squares on the same cost, written independently (per-measurement projection through
    Camera.project, finite-difference Jacobian), gives the same minimum; its (JᵀJ)⁻¹ the same covariance.
    Every landmark is solved (one picture is enough: --min-pictures 1); with the default 2, the landmarks
    seen once keep their prior VLM, held, their prior's uncertainty added to their measurements' (to first
    order the same poses: within 0.1 sigma)."""
    w = bundle_world(6, 30, seed=3)
    p = w.problem
    r = solve_bundle(p, BundleOptions(reject_outliers=False, min_parallax_deg=0.0, min_pictures=1))
    held = solve_bundle(p, BundleOptions(reject_outliers=False, min_parallax_deg=0.0))
    n_p, n_l = len(p.cameras), len(p.landmark_names)
    p0 = np.array([c.position for c in p.cameras])
    t0 = np.array([c.rotation for c in p.cameras])
    chol = np.linalg.cholesky(p.obs_weight)

    def resid(x):
        dp, th, v = (
            x[: 3 * n_p].reshape(-1, 3),
            x[3 * n_p : 6 * n_p].reshape(-1, 3),
            x[6 * n_p :].reshape(-1, 3),
        )
        out = np.empty((p.obs_picture.size, 2))
        for j in range(n_p):  # projection per picture, the bundle's own vectorised path not used
            k = np.flatnonzero(p.obs_picture == j)
            cam = p.cameras[j].with_pose(position=p0[j] + dp[j], rotation=rot_from_rotvec(-th[j]) @ t0[j])
            s, li = cam.project(v[p.obs_landmark[k]])
            out[k] = p.obs_pixel[k] - np.stack([s, li], axis=1)
        white = np.einsum("kji,kj->ki", chol, out)  # Lᵀ r with W = L Lᵀ
        prior = [(dp / p.sigma_position).ravel(), (th / p.sigma_attitude).ravel()]
        prior.append(((v - p.landmark_positions) / p.landmark_sigmas).ravel())
        return np.concatenate([white.ravel()] + prior)

    x0 = np.concatenate([np.zeros(6 * n_p), p.landmark_positions.ravel()])
    sol = least_squares(resid, x0, x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    dp, th, v = (
        sol.x[: 3 * n_p].reshape(-1, 3),
        sol.x[3 * n_p : 6 * n_p].reshape(-1, 3),
        sol.x[6 * n_p :].reshape(-1, 3),
    )
    ok = np.array([s == "ok" for s in r.landmark_status])
    assert ok.sum() >= 15
    tol_v = 1e-9
    assert np.max(np.abs(v[ok] - r.landmark_positions[ok])) < tol_v
    assert np.max(np.abs(p0 + dp - r.positions)) < tol_v
    assert np.max(np.abs(th - r.delta_attitude)) < tol_v
    cov = np.linalg.inv(sol.jac.T @ sol.jac)
    idx = lambda j: np.r_[3 * j : 3 * j + 3, 3 * n_p + 3 * j : 3 * n_p + 3 * j + 3]  # noqa: E731
    pose = np.stack([cov[np.ix_(idx(j), idx(j))] for j in range(n_p)])
    lm = np.stack(
        [
            cov[6 * n_p + 3 * i : 6 * n_p + 3 * i + 3, 6 * n_p + 3 * i : 6 * n_p + 3 * i + 3]
            for i in range(n_l)
        ]
    )
    assert np.max(np.abs(pose - r.pose_covariance)) < 1e-4 * np.max(np.abs(pose))
    assert np.max(np.abs(lm[ok] - r.landmark_covariance[ok])) < 1e-6 * np.max(np.abs(lm[ok]))
    kept = np.array([s == "undetermined" for s in held.landmark_status])
    assert kept.any() and np.array_equal(held.landmark_positions[kept], p.landmark_positions[kept])
    solved = ~kept
    assert np.all(np.abs(held.landmark_positions[solved] - v[solved]) < 0.1 * held.landmark_sigmas[solved])
    assert np.all(np.abs(held.positions - (p0 + dp)) < 0.1 * held.pose_sigmas[:, :3])
    assert np.all(np.abs(held.delta_attitude - th) < 0.1 * held.pose_sigmas[:, 3:])


def test_vlm_error_falls_as_one_over_root_n_pictures():
    """Landmark errors of several maplet cells (1 m a priori, 0.5 m cells) shrink as 1/√N with the
    pictures (spacecraft positions known to 0.2 m, as radio tracking gives them); the curve is printed
    (pytest -s) and its log-log slope is −½ within 0.2."""
    counts = (8, 16, 32, 64)
    rms = []
    for n in counts:
        errs = []
        for seed in range(10):
            w = bundle_world(
                n,
                40,
                seed=100 + seed,
                sigma_landmark_km=0.001,
                cap_deg=25.0,
                sigma_px=0.3,
                sigma_position_km=2e-4,
            )
            r = solve_bundle(w.problem)
            ok = np.array([s == "ok" for s in r.landmark_status])
            errs.append(np.sum((r.landmark_positions[ok] - w.true_landmarks[ok]) ** 2, axis=1))
        rms.append(np.sqrt(np.mean(np.concatenate(errs))))
    slope = np.polyfit(np.log(counts), np.log(rms), 1)[0]
    print("pictures  VLM rms error (m):", ", ".join(f"{n}: {1000 * e:.4f}" for n, e in zip(counts, rms)))
    assert rms[-1] < 0.15 * 1.0e-3  # far below the 1 m a-priori error
    assert -0.7 < slope < -0.3, slope


def test_nees_consistent_with_chi2_over_100_seeds():
    """One landmark and one picture per seed (independent draws): mean NEES within the 99 % band of
    χ²₃/100 and χ²₆/100."""
    nees_l, nees_p = [], []
    for seed in range(100):
        w = bundle_world(8, 30, seed=seed)
        r = solve_bundle(w.problem)
        ok = np.flatnonzero([s == "ok" for s in r.landmark_status])
        i = ok[0]
        d = r.landmark_positions[i] - w.true_landmarks[i]
        nees_l.append(d @ np.linalg.solve(r.landmark_covariance[i], d))
        th = -rotvec_from_rot(r.rotations[0] @ w.true_rotations[0].T)
        e = np.concatenate([r.positions[0] - w.true_positions[0], th])
        nees_p.append(e @ np.linalg.solve(r.pose_covariance[0], e))
    # mean of 100 χ²_k: k ± 2.58·√(2k/100)
    assert abs(np.mean(nees_l) - 3) < 2.58 * np.sqrt(6 / 100), np.mean(nees_l)
    assert abs(np.mean(nees_p) - 6) < 2.58 * np.sqrt(12 / 100), np.mean(nees_p)


def test_poses_beat_single_picture_solves_on_the_biased_map():
    """The joint solve's poses are closer to the truth than each picture solved alone (solve-pose, the
    landmarks fixed at their biased a-priori VLMs)."""
    w = bundle_world(12, 60, seed=7, sigma_landmark_km=0.002)
    p = w.problem
    r = solve_bundle(p)
    alone = []
    for j, cam in enumerate(p.cameras):
        k = np.flatnonzero(p.obs_picture == j)
        res = solve_pose(
            cam,
            p.landmark_positions[p.obs_landmark[k]],
            p.obs_pixel[k],
            PoseOptions(sigma_px=0.1),
            prior_sigma_position=p.sigma_position[j],
            prior_sigma_attitude=p.sigma_attitude[j],
        )
        alone.append(np.linalg.norm(res.position - w.true_positions[j]))
    joint = np.linalg.norm(r.positions - w.true_positions, axis=1)
    print(
        f"position error rms: single-picture {1000 * np.sqrt(np.mean(np.square(alone))):.2f} m, joint "
        f"{1000 * np.sqrt(np.mean(joint**2)):.2f} m"
    )
    assert np.sqrt(np.mean(joint**2)) < 0.5 * np.sqrt(np.mean(np.square(alone)))


def test_planted_outliers_are_all_flagged_and_no_clean_one():
    """20 px errors on 15 measurements of landmarks seen at least three times (so that the odd one out
    can be told): exactly those are flagged; the clean data alone get no flag at all."""
    w = bundle_world(12, 80, seed=11)
    p = w.problem
    assert not any(s == "outlier" for s in solve_bundle(p).obs_status)
    rng = np.random.default_rng(0)
    counts = np.bincount(p.obs_landmark)
    eligible = np.flatnonzero(counts[p.obs_landmark] >= 3)
    bad = rng.choice(eligible, 15, replace=False)
    ang = rng.uniform(0, 2 * np.pi, bad.size)
    pix = p.obs_pixel.copy()
    pix[bad] += 20.0 * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    r = solve_bundle(dataclasses.replace(p, obs_pixel=pix))
    flagged = np.flatnonzero([s == "outlier" for s in r.obs_status])
    assert set(flagged) == set(bad)
    ok = np.array([s == "ok" for s in r.landmark_status])
    assert np.sqrt(np.mean((r.landmark_positions[ok] - w.true_landmarks[ok]) ** 2)) < 2e-4


def test_an_outlier_among_two_measurements_flags_both_and_keeps_the_prior():
    """Two measurements that disagree cannot say which is wrong: both are flagged, V keeps its prior."""
    w = bundle_world(12, 80, seed=11)
    p = w.problem
    counts = np.bincount(p.obs_landmark)
    k = int(np.flatnonzero(counts[p.obs_landmark] == 2)[0])
    lm = p.obs_landmark[k]
    pix = p.obs_pixel.copy()
    pix[k] += (14.0, -14.0)
    r = solve_bundle(dataclasses.replace(p, obs_pixel=pix))
    both = np.flatnonzero(p.obs_landmark == lm)
    assert all(r.obs_status[i] == "outlier" for i in both)
    assert r.landmark_status[lm] == "undetermined"
    assert np.array_equal(r.landmark_positions[lm], p.landmark_positions[lm])
    assert sum(s == "outlier" for s in r.obs_status) == 2


def test_camera_focal_length_and_centre_recovered_within_three_sigma():
    true_cam = demo_camera(fov_deg=20.0)
    w = bundle_world(16, 120, seed=5, camera=true_cam, sigma_px=0.1)
    p = w.problem
    wrong = dataclasses.replace(
        true_cam, mmfl=true_cam.mmfl * 1.002, ctr=true_cam.ctr + np.array([0.8, -0.6])
    )
    cams = [wrong.with_pose(position=c.position, rotation=c.rotation) for c in p.cameras]
    r = solve_bundle(dataclasses.replace(p, cameras=cams), BundleOptions(estimate_camera=("focal", "ctr")))
    (terms,) = r.camera_terms.values()
    for label, truth in (
        ("focal", true_cam.mmfl),
        ("ctr_sample", true_cam.ctr[0]),
        ("ctr_line", true_cam.ctr[1]),
    ):
        before, after, sigma = terms[label]
        assert abs(after - truth) < 3 * sigma, (label, before, after, sigma)
        assert abs(after - truth) < abs(before - truth)


def test_kx_and_kxy_are_refused():
    with pytest.raises(Exception, match="L15"):
        BundleOptions(estimate_camera=("kxy",))


def test_a_free_gauge_is_refused():
    w = bundle_world(6, 30, seed=2)
    p = w.problem
    free = dataclasses.replace(
        p,
        sigma_position=np.zeros_like(p.sigma_position),
        sigma_attitude=np.zeros_like(p.sigma_attitude),
        landmark_sigmas=np.zeros_like(p.landmark_sigmas),
    )
    with pytest.raises(BundleError, match="gauge is not fixed"):
        solve_bundle(free)
    # attitude priors alone fix rotation but not translation nor scale
    with pytest.raises(BundleError, match="translation"):
        solve_bundle(dataclasses.replace(free, sigma_attitude=p.sigma_attitude))


def test_undetermined_landmark_keeps_its_prior_and_flags_are_honoured():
    w = bundle_world(8, 40, seed=9)
    p = w.problem
    counts = np.bincount(p.obs_landmark, minlength=40)
    lm = int(np.flatnonzero(counts >= 3)[0])
    k = np.flatnonzero(p.obs_landmark == lm)
    use = p.obs_use.copy()
    use[k[1:]] = False  # only one usable measurement left
    r = solve_bundle(dataclasses.replace(p, obs_use=use))
    assert r.landmark_status[lm] == "undetermined"
    assert np.array_equal(r.landmark_positions[lm], p.landmark_positions[lm])
    assert all(r.obs_status[i] == "flagged" for i in k[1:])


def test_a_picture_ignored_in_vlm_does_not_move_any_landmark():
    w = bundle_world(10, 50, seed=12)
    p = w.problem
    vlm = np.ones(10, bool)
    vlm[3] = False
    r = solve_bundle(dataclasses.replace(p, vlm_pictures=vlm))
    keep = p.obs_picture != 3
    cams = [c for j, c in enumerate(p.cameras) if j != 3]
    remap = np.cumsum(np.arange(10) != 3) - 1
    alone = solve_bundle(
        dataclasses.replace(
            p,
            cameras=cams,
            picture_names=[n for j, n in enumerate(p.picture_names) if j != 3],
            sigma_position=p.sigma_position[np.arange(10) != 3],
            sigma_attitude=p.sigma_attitude[np.arange(10) != 3],
            obs_picture=remap[p.obs_picture[keep]],
            obs_landmark=p.obs_landmark[keep],
            obs_pixel=p.obs_pixel[keep],
            obs_weight=p.obs_weight[keep],
            obs_use=p.obs_use[keep],
            vlm_pictures=None,
        )
    )
    assert np.max(np.abs(r.landmark_positions - alone.landmark_positions)) < 1e-12
    assert all(s == "ignored-in-vlm" for s, j in zip(r.obs_status, p.obs_picture) if j == 3)
    assert np.linalg.norm(r.positions[3] - w.true_positions[3]) < np.linalg.norm(
        r.positions0[3] - w.true_positions[3]
    )


def test_spc_alternation_descends_toward_the_joint_minimum_far_more_slowly():
    """SPC's alternation (landmarks with poses fixed, then poses with landmarks fixed) lowers the same
    cost at every round but crawls along the directions that move landmarks and cameras together: after
    200 rounds it is still above the minimum the joint solve reaches in a few iterations."""
    w = bundle_world(6, 30, seed=3)
    opts = dict(reject_outliers=False, min_parallax_deg=0.0)
    joint = solve_bundle(w.problem, BundleOptions(**opts))
    alt = solve_bundle(w.problem, BundleOptions(mode="alternate", max_iter=200, tol=0.0, **opts))
    hist = np.array(alt.cost_history)
    assert np.all(np.diff(hist) <= 1e-9 * hist[:-1])  # never up
    assert hist[-1] >= joint.cost_history[-1] * (1 - 1e-9)  # never below the minimum
    assert hist[-1] > 1.2 * joint.cost_history[-1]
    assert joint.iterations <= 10 and joint.converged
    said = [w_ for w_ in alt.warnings if "alternation stopped after 200 rounds" in w_]
    assert len(said) == 1 and f"{joint.cost_history[-1]:.6g}" in said[0]


def test_banded_and_dense_reduced_systems_agree():
    """The reverse Cuthill–McKee banded factorisation and the dense one give the same step."""
    from spctool.stages import _bundle_linalg as bl

    w = bundle_world(60, 600, seed=3, cap_deg=180.0, camera=demo_camera(fov_deg=25.0))
    r1 = solve_bundle(w.problem, BundleOptions(reject_outliers=False))
    old = bl.ReducedSystem.assemble.__func__

    def dense(cls, *a, **k):
        k["dense_limit_band"] = 0.0
        return old(cls, *a, **k)

    try:
        bl.ReducedSystem.assemble = classmethod(dense)
        r2 = solve_bundle(w.problem, BundleOptions(reject_outliers=False))
    finally:
        bl.ReducedSystem.assemble = classmethod(old)
    assert np.max(np.abs(r1.landmark_positions - r2.landmark_positions)) < 1e-10
    assert np.max(np.abs(r1.pose_covariance - r2.pose_covariance)) < 1e-8 * np.max(np.abs(r1.pose_covariance))


def test_pose_of_a_rotated_attitude_prior_uses_the_exact_right_jacobian():
    """so3_right_jacobian_inv_batch equals the single-vector version of stages.pose."""
    from spctool.stages.bundle import so3_right_jacobian_inv_batch
    from spctool.stages.pose import so3_right_jacobian_inv

    th = np.random.default_rng(1).normal(size=(50, 3)) * np.logspace(-7, 0.3, 50)[:, None]
    batch = so3_right_jacobian_inv_batch(th)
    for t, b in zip(th, batch):
        assert np.allclose(b, so3_right_jacobian_inv(t), atol=1e-14)


def _pose_alone(p, j, covariances):
    """Picture j solved alone by solve-pose against the a-priori VLMs (no model error, no floor)."""
    k = np.flatnonzero(p.obs_picture == j)
    return solve_pose(
        p.cameras[j],
        p.landmark_positions[p.obs_landmark[k]],
        p.obs_pixel[k],
        PoseOptions(reject_outliers=False, model_error=False, sigma_floor_px=0.0, min_landmarks=1),
        prior_sigma_position=p.sigma_position[j],
        prior_sigma_attitude=p.sigma_attitude[j],
        pixel_covariances=covariances[k],
    )


def test_undetermined_landmarks_are_held_and_the_residuals_are_those_of_the_result():
    """A landmark that is not refined keeps its prior VLM, and the poses are fitted to that VLM, held (they
    were once fitted to a VLM moved in the solve and then put back: the residuals, χ² and rms reported
    were not those of the VLMs and poses written).  Every landmark undetermined (parallax 90°): the
    residuals are those of the returned poses and VLMs, and each pose is the picture's solve-pose
    against the a-priori VLMs, the measurements' covariance C + J_V Σ_V J_Vᵀ (the VLM's own uncertainty
    projected; J_V by finite differences here); without landmark priors, exactly the plain solve-pose."""
    w = bundle_world(8, 40, seed=9)
    p = w.problem
    opts = BundleOptions(reject_outliers=False, min_parallax_deg=90.0)
    r = solve_bundle(p, opts)
    assert set(r.landmark_status) <= {"undetermined", "unobserved"}
    assert np.array_equal(r.landmark_positions, p.landmark_positions)
    cov = np.linalg.inv(p.obs_weight)
    for j in range(len(p.cameras)):
        k = np.flatnonzero(p.obs_picture == j)
        s, li = r.cameras[j].project(r.landmark_positions[p.obs_landmark[k]])
        assert np.max(np.abs(r.residual_after[k] - (p.obs_pixel[k] - np.stack([s, li], axis=1)))) < 1e-9
        jv = np.empty((k.size, 2, 3))
        for a in range(3):  # ∂(sample, line)/∂V by central differences (1 cm)
            dv = np.zeros(3)
            dv[a] = 1e-5
            sp_, lp = p.cameras[j].project(p.landmark_positions[p.obs_landmark[k]] + dv)
            sm, lm = p.cameras[j].project(p.landmark_positions[p.obs_landmark[k]] - dv)
            jv[:, :, a] = np.stack([sp_ - sm, lp - lm], axis=1) / 2e-5
        inflated = cov.copy()
        inflated[k] += np.einsum("kai,ki,kbi->kab", jv, p.landmark_sigmas[p.obs_landmark[k]] ** 2, jv)
        alone = _pose_alone(p, j, inflated)
        assert np.all(np.abs(r.positions[j] - alone.position) < 0.01 * r.pose_sigmas[j, :3])
    used = np.array([s == "undetermined" for s in r.obs_status])
    assert used.all()
    assert r.chi2 == pytest.approx(float(np.sum(r.rho_after[used] ** 2)), rel=1e-12)
    # no landmark unknown: the degrees of freedom are those of the poses alone
    n_prior = int(np.count_nonzero(p.sigma_position > 0) + np.count_nonzero(p.sigma_attitude > 0))
    assert r.dof == 2 * p.obs_picture.size - 6 * len(p.cameras) + n_prior
    exact = dataclasses.replace(p, landmark_sigmas=np.zeros_like(p.landmark_sigmas))
    r0 = solve_bundle(exact, opts)
    for j in range(len(p.cameras)):
        plain = _pose_alone(p, j, cov).position
        assert np.all(np.abs(r0.positions[j] - plain) < 1e-4 * r0.pose_sigmas[j, :3])


def test_a_fit_whose_chi2_exceeds_its_quantile_is_inconsistent_and_far_above_implausible():
    """solve-pose's χ² gate on the whole solve: honest weights pass (ok, no warning); weights claiming
    half the true noise (cost/dof ≈ 2.4, the priors unchanged) are inconsistent, said once with the
    figures and the remedy; a hundredth implausible (cost/dof above 100)."""
    w = bundle_world(10, 60, seed=4)
    p = w.problem
    ok = solve_bundle(p)
    assert ok.verdict == "ok" and ok.verdict_reason == "" and ok.reduced_chi2 < 1.5
    assert ok.cost == pytest.approx(ok.chi2 + ok.prior_cost) and ok.prior_cost > 0
    assert ok.cost < ok.consistency_limit
    assert not [x for x in ok.warnings if "fit" in x]
    bad = solve_bundle(dataclasses.replace(p, obs_weight=p.obs_weight * 4.0))
    assert bad.verdict == "inconsistent" and 2.0 < bad.cost / bad.dof < 100
    assert bad.cost > bad.consistency_limit
    said = [x for x in bad.warnings if x.startswith("inconsistent fit")]
    assert len(said) == 1 and f"{bad.consistency_limit:.4g}" in said[0] and "--sigma-px" in said[0]
    assert bad.covariance_scale == pytest.approx(bad.reduced_chi2)
    worse = solve_bundle(dataclasses.replace(p, obs_weight=p.obs_weight * 1e4))
    assert worse.verdict == "implausible" and worse.reduced_chi2 > 100
    assert any(x.startswith("implausible fit") for x in worse.warnings)


def test_scaled_covariance_covers_the_truth_when_the_weights_claim_too_much():
    """Measurement weights 4× too large (sigmas claimed half the noise), the priors honest: the
    covariances scaled by covariance_scale (χ²/dof above 1) still cover the true errors — mean NEES
    over 100 truth worlds within the 99 % band of χ²₃ (landmark) and χ²₆ (pose).  Scaling by the cost
    per dof (χ² + the priors' part) read 1.81 / 4.06: too wide; unscaled, the pose reads 6.6."""
    nees_l, nees_p, scales = [], [], []
    for seed in range(100):
        w = bundle_world(8, 30, seed=seed)
        r = solve_bundle(dataclasses.replace(w.problem, obs_weight=w.problem.obs_weight * 4.0))
        s = r.covariance_scale
        scales.append(s)
        i = np.flatnonzero([st == "ok" for st in r.landmark_status])[0]
        d = r.landmark_positions[i] - w.true_landmarks[i]
        nees_l.append(d @ np.linalg.solve(s * r.landmark_covariance[i], d))
        th = -rotvec_from_rot(r.rotations[0] @ w.true_rotations[0].T)
        e = np.concatenate([r.positions[0] - w.true_positions[0], th])
        nees_p.append(e @ np.linalg.solve(s * r.pose_covariance[0], e))
    assert np.mean(np.array(scales) > 1.0) > 0.5, scales  # the case is exercised: most fits are scaled
    assert abs(np.mean(nees_l) - 3) < 2.58 * np.sqrt(6 / 100), np.mean(nees_l)
    assert abs(np.mean(nees_p) - 6) < 2.58 * np.sqrt(12 / 100), np.mean(nees_p)
