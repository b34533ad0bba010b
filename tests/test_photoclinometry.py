"""Stereophotoclinometry numerics (spctool.stages.photoclinometry, spctool.stages.slope_integration):
the analytic Jacobian against finite differences, the per-cell solve and the whole pass on analytic
surfaces (a plane, a Gaussian bump; uniform albedo, noise-free, Sun from N, E, S, W), the
integration against a dense brute-force least squares, the three-azimuth rule."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool import photometry as phot
from spctool.errors import SpcUsageError
from spctool.stages import photoclinometry as pc
from spctool.stages import slope_integration as si

N = 41
Q = 20


def _dir(inc, az):
    i, a = math.radians(inc), math.radians(az)
    return np.array([math.sin(i) * math.cos(a), math.sin(i) * math.sin(a), math.cos(i)])


def _geometry(sun_az=(0.0, 90.0, 180.0, 270.0), inc=45.0, emission=30.0):
    suns = np.array([_dir(inc, az) for az in sun_az])
    ems = np.array([_dir(emission, az + 45.0) for az in sun_az])
    alpha = np.degrees(np.arccos(np.clip(np.sum(suns * ems, axis=1), -1, 1)))
    return suns, ems, alpha


def _observe(t1, t2, albedo, lam, geometry=None, options=None):
    suns, ems, alpha = geometry if geometry is not None else _geometry()
    k = len(suns)
    blank = pc.Pictures(np.zeros((k,) + t1.shape), np.ones((k,) + t1.shape, bool), suns, ems, alpha)
    p, lit = pc.brightness(t1, t2, albedo, blank, lam, options)
    return pc.Pictures(p, lit & (p > 0), suns, ems, alpha)


def _surface(kind):
    x = np.arange(N, dtype=float) - Q
    xx, yy = np.meshgrid(x, x, indexing="ij")
    if kind == "plane":
        return 0.12 * xx - 0.07 * yy, np.full_like(xx, 0.12), np.full_like(xx, -0.07)
    amp, sig = 3.0, 8.0
    h = amp * np.exp(-(xx**2 + yy**2) / (2 * sig * sig))
    return h + 0.05 * xx, -xx / sig**2 * h + 0.05, -yy / sig**2 * h


# --------------------------------------------------------------------------------------------------
# model and Jacobian


@pytest.mark.parametrize("model", phot.MODELS)
def test_jacobian_matches_finite_differences(model):
    rng = np.random.default_rng(3)
    opts = pc.SolveOptions(photometry=model)
    t1 = rng.uniform(-0.4, 0.4, 200)
    t2 = rng.uniform(-0.4, 0.4, 200)
    a = rng.uniform(0.6, 1.4, 200)
    pics = _observe(np.zeros((1, 1)), np.zeros((1, 1)), np.ones((1, 1)), np.ones(4))
    lam = np.array([1.0, 2.0, 0.5, 1.3])
    p, jac, lit = pc.jacobian(t1, t2, a, pics, lam, opts)
    p_ref, lit_ref = pc.brightness(t1, t2, a, pics, lam, opts)
    np.testing.assert_allclose(p, p_ref, rtol=0, atol=1e-15)
    assert np.array_equal(lit, lit_ref)
    eps = 1e-6
    for i, (d1, d2, da) in enumerate(((eps, 0, 0), (0, eps, 0), (0, 0, eps))):
        hi, _ = pc.brightness(t1 + d1, t2 + d2, a + da, pics, lam, opts)
        lo, _ = pc.brightness(t1 - d1, t2 - d2, a - da, pics, lam, opts)
        fd = (hi - lo) / (2 * eps)
        np.testing.assert_allclose(np.where(lit, jac[..., i], 0), np.where(lit, fd, 0), rtol=0, atol=2e-8)


def test_brightness_is_predict_model():
    """P/(λa) is spctool.photometry's reflectance of the same cosines (SPC's lunar-Lambert)."""
    suns, ems, alpha = _geometry()
    t1 = np.array([0.1, -0.3, 0.0])
    t2 = np.array([0.2, 0.05, 0.0])
    pics = _observe(np.zeros((1, 1)), np.zeros((1, 1)), np.ones((1, 1)), np.ones(4))
    p, _ = pc.brightness(t1, t2, np.ones(3), pics, np.ones(4))
    n = np.stack([-t1, -t2, np.ones(3)], axis=1)
    n /= np.linalg.norm(n, axis=1)[:, None]
    for k in range(4):
        r = phot.reflectance(n @ suns[k], n @ ems[k], alpha[k], "spc")
        np.testing.assert_allclose(p[k], r, rtol=1e-14)


# --------------------------------------------------------------------------------------------------
# per-cell solve and the pass


@pytest.mark.parametrize("kind", ["plane", "bump"])
def test_cells_recover_analytic_slopes(kind):
    _, t1, t2 = _surface(kind)
    lam = np.array([100.0, 120.0, 90.0, 110.0])
    pics = _observe(t1, t2, np.ones_like(t1), lam)
    sol = pc.solve_cells(np.zeros_like(t1), np.zeros_like(t1), np.ones_like(t1), pics, lam)
    assert sol.solved.all() and not sol.flagged.any()
    assert np.max(np.abs(sol.t1 - t1)) <= 1e-3
    assert np.max(np.abs(sol.t2 - t2)) <= 1e-3
    assert np.max(np.abs(sol.albedo - 1.0)) <= 1e-3


@pytest.mark.parametrize("kind", ["plane", "bump"])
def test_pass_recovers_heights_from_flat_start(kind):
    """λ unknown, flat start; conditioning heights (2 %) from the truth, as a starting map gives them."""
    h, t1, t2 = _surface(kind)
    lam = np.array([100.0, 120.0, 90.0, 110.0])
    pics = _observe(t1, t2, np.ones_like(t1), lam)
    valid = np.ones(h.shape, bool)
    cond = si.conditioning_cells(valid, 0.02, seed=1)
    heights, albedo = np.zeros_like(h), np.ones_like(h)
    for _ in range(8):
        step = pc.heights_pass(heights, albedo, valid, pics, h, cond, 0.025, keep_plane=True)
        heights, albedo = step.heights, step.albedo
    err = heights - h
    assert math.sqrt(np.mean(err**2)) <= 0.01
    assert np.max(np.abs(step.cells.t1 - t1)) <= 1e-3
    assert np.max(np.abs(step.cells.t2 - t2)) <= 1e-3
    np.testing.assert_allclose(step.lam / step.lam.mean(), lam / lam.mean(), rtol=1e-4)
    assert step.change_rms < 1e-4


def test_albedo_recovered_with_slopes():
    h, t1, t2 = _surface("bump")
    x = np.arange(N, dtype=float) - Q
    alb = 1.0 + 0.2 * np.sin(x[:, None] / 4.0) * np.cos(x[None, :] / 5.0)
    lam = np.ones(4)
    pics = _observe(t1, t2, alb, lam)
    sol = pc.solve_cells(np.zeros_like(t1), np.zeros_like(t1), np.ones_like(t1), pics, lam)
    np.testing.assert_allclose(sol.albedo, alb, atol=1e-6)
    np.testing.assert_allclose(sol.t1, t1, atol=1e-6)


def test_fit_lambda_and_normalisation():
    _, t1, t2 = _surface("bump")
    lam = np.array([3.0, 5.0, 7.0, 11.0])
    pics = _observe(t1, t2, np.full_like(t1, 0.5), lam)
    fitted = pc.fit_lambda(t1, t2, np.full_like(t1, 0.5), pics)
    np.testing.assert_allclose(fitted, lam, rtol=1e-13)
    a, lam2 = pc.normalise_albedo(np.full_like(t1, 0.5), fitted, np.ones(t1.shape, bool))
    np.testing.assert_allclose(a, 1.0)
    np.testing.assert_allclose(lam2, lam * 0.5)
    # predictions unchanged
    p1, _ = pc.brightness(t1, t2, np.full_like(t1, 0.5), pics, fitted)
    p2, _ = pc.brightness(t1, t2, a, pics, lam2)
    np.testing.assert_allclose(p1, p2, rtol=1e-14)


# --------------------------------------------------------------------------------------------------
# the three-azimuth rule


def test_azimuth_groups():
    suns, _, _ = _geometry(sun_az=(0.0, 5.0, 90.0, 358.0, 180.0))
    g = pc.azimuth_groups(suns, 20.0)
    assert g[0] == g[1] == g[3] and len({g[0], g[2], g[4]}) == 3
    assert np.unique(pc.azimuth_groups(suns, 1.0)).size == 5
    zenith = np.array([[0, 0, 1.0], [1, 0, 1.0]])
    assert np.unique(pc.azimuth_groups(zenith, 20.0)).size == 2


def test_cells_with_too_few_azimuths_keep_prior_and_are_flagged():
    _, t1, t2 = _surface("bump")
    geo = _geometry(sun_az=(0.0, 10.0, 180.0, 90.0))
    lam = np.ones(4)
    pics = _observe(t1, t2, np.ones_like(t1), lam, geo)
    # the 90° picture sees only the left half: the right half has two azimuth groups (0/10, 180)
    pics.valid[3, :, Q:] = False
    prior1, prior2, prior_a = np.full_like(t1, 0.3), np.full_like(t1, -0.2), np.full_like(t1, 0.8)
    sol = pc.solve_cells(prior1, prior2, prior_a, pics, lam)
    right = np.zeros(t1.shape, bool)
    right[:, Q:] = True
    assert np.array_equal(sol.flagged, right)
    assert np.array_equal(sol.azimuths, np.where(right, 2, 3))
    assert np.array_equal(sol.t1[right], prior1[right]) and np.array_equal(sol.albedo[right], prior_a[right])
    assert np.max(np.abs(sol.t1[~right] - t1[~right])) <= 1e-3


def test_solve3_matches_numpy():
    rng = np.random.default_rng(9)
    m = rng.normal(size=(50, 3, 3))
    a = m @ m.transpose(0, 2, 1) + 0.1 * np.eye(3)
    b = rng.normal(size=(50, 3))
    got = pc._solve3(a[:, 0, 0], a[:, 0, 1], a[:, 0, 2], a[:, 1, 1], a[:, 1, 2], a[:, 2, 2], *b.T)
    np.testing.assert_allclose(got, np.linalg.solve(a, b[..., None])[..., 0], rtol=1e-9, atol=1e-12)
    assert np.isnan(pc._solve3(*np.zeros((9, 1)))).all()


def test_options_refuse_bad_values():
    with pytest.raises(SpcUsageError):
        pc.SolveOptions(photometry="hapke")
    with pytest.raises(SpcUsageError):
        pc.SolveOptions(damping=-1.0)
    with pytest.raises(SpcUsageError):
        pc.SolveOptions(iterations=0)


# --------------------------------------------------------------------------------------------------
# integration


def _dense_solution(t1, t2, valid, cond, targets, weight, fixed):
    """Brute force: every equation of the module docstring written out one by one, dense lstsq."""
    n0, n1 = valid.shape
    free = [(r, c) for r in range(n0) for c in range(n1) if valid[r, c] and not fixed[r, c]]
    col = {rc: i for i, rc in enumerate(free)}
    rows, rhs = [], []

    def height_term(rc, sign, row):
        if rc in col:
            row[col[rc]] += sign
            return 0.0
        return -sign * targets[rc]  # known height moves to the right side

    for r in range(n0):
        for c in range(n1):
            for dr, dc, t in ((1, 0, t1), (0, 1, t2)):
                a, b = (r, c), (r + dr, c + dc)
                if b[0] >= n0 or b[1] >= n1 or not (valid[a] and valid[b]):
                    continue
                if a not in col and b not in col:
                    continue
                row = np.zeros(len(free))
                k = height_term(b, 1.0, row) + height_term(a, -1.0, row)
                rows.append(row)
                rhs.append(0.5 * (t[a] + t[b]) + k)
    for rc in free:
        if cond[rc]:
            row = np.zeros(len(free))
            row[col[rc]] = math.sqrt(weight)
            rows.append(row)
            rhs.append(math.sqrt(weight) * targets[rc])
    sol, *_ = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)
    out = np.where(valid, targets, 0.0)
    for rc, i in col.items():
        out[rc] = sol[i]
    return out


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_integration_matches_dense_least_squares(seed):
    rng = np.random.default_rng(seed)
    n = 9
    valid = rng.random((n, n)) > 0.15
    t1 = rng.normal(0, 0.3, (n, n))
    t2 = rng.normal(0, 0.3, (n, n))
    targets = rng.normal(0, 2.0, (n, n))
    fixed = valid & (rng.random((n, n)) < 0.1)
    # every island of free cells needs an anchor for the brute force (no ridge there): condition many
    cond = valid & (rng.random((n, n)) < 0.5)
    weight = float(rng.uniform(0.01, 1.0))
    # islands without an anchor are singular without the ridge: compare when the system is full rank
    g, _, _ = si.normal_system(t1, t2, valid, cond, targets, weight, fixed, ridge=0.0)
    if g.shape[1] and np.linalg.matrix_rank(g.toarray()) < g.shape[1]:
        return
    got = si.integrate_slopes(t1, t2, valid, cond, targets, weight, fixed=fixed, ridge=0.0)
    ref = _dense_solution(t1, t2, valid, cond, targets, weight, fixed)
    np.testing.assert_allclose(got, ref, atol=1e-9)
    assert np.array_equal(got[fixed], targets[fixed])


def test_integration_of_exact_differences_is_exact():
    """Slopes whose edge means are the height differences of a linear field give it back exactly."""
    h, t1, t2 = _surface("plane")
    valid = np.ones(h.shape, bool)
    cond = si.conditioning_cells(valid, 0.005, seed=2)
    got = si.integrate_slopes(t1, t2, valid, cond, h, 0.025)
    np.testing.assert_allclose(got, h, atol=1e-8)


def test_conditioning_cells_and_keep_plane():
    valid = np.ones((20, 20), bool)
    valid[:5] = False
    c = si.conditioning_cells(valid, 0.02, seed=4)
    assert c.sum() == math.ceil(0.02 * 300) and not (c & ~valid).any()
    assert np.array_equal(c, si.conditioning_cells(valid, 0.02, seed=4))
    with pytest.raises(SpcUsageError):
        si.conditioning_cells(valid, 1.5)
    r, cc = np.indices((20, 20))
    ref = 0.3 * r - 0.1 * cc + 2.0
    bump = np.exp(-((r - 10.0) ** 2 + (cc - 10.0) ** 2) / 8.0)
    got = si.keep_plane(bump + 0.5 * r + 7.0, ref, valid)
    fit = si.keep_plane(got, ref, valid)
    np.testing.assert_allclose(fit, got, atol=1e-12)  # already has ref's plane
    np.testing.assert_allclose(si.keep_plane(ref + 0.0, ref, valid), ref, atol=1e-12)


@pytest.mark.parametrize("model", ["spc", "lambert"])
def test_compiled_gauss_newton_matches_the_numpy_steps(model):
    """The compiled per-cell iterations (_k_gauss_newton) against the same steps written with numpy
    over all cells (_gauss_newton_numpy): a noisy, partly invalid problem with an albedo field, six
    pictures (one with no usable scale), a far start and a step cap that bites."""
    rng = np.random.default_rng(3)
    opts = pc.SolveOptions(photometry=model, iterations=6, max_step=0.2)
    m = 400
    t1, t2 = rng.normal(0.0, 0.3, (20, 20)), rng.normal(0.0, 0.3, (20, 20))
    albedo = rng.uniform(0.6, 1.4, (20, 20))
    geom = _geometry(sun_az=(0.0, 60.0, 130.0, 200.0, 270.0, 320.0), inc=50.0)
    lam = np.array([900.0, 1100.0, 1000.0, 950.0, np.nan, 1050.0])
    pics = _observe(t1, t2, albedo, np.nan_to_num(lam, nan=1000.0), geom, opts)
    obs = pics.observed.reshape(6, m) + rng.normal(0.0, 5.0, (6, m))
    ov = pics.valid.reshape(6, m) & (rng.random((6, m)) > 0.15) & np.isfinite(lam)[:, None]
    x0 = np.stack([t1.ravel() + rng.normal(0, 0.4, m), t2.ravel() + rng.normal(0, 0.4, m), np.ones(m)], 1)
    ref = pc._gauss_newton_numpy(obs, ov, pics, lam, x0.copy(), opts)
    good = np.isfinite(lam) & (lam > 0)
    safe = np.where(good, lam, 1.0)
    c1, c2 = pc.photometric_constants(pics.alpha_deg, opts)
    x = x0.copy()
    pc._k_gauss_newton(obs, ov, pics.sun, pics.emission, c1, c2, safe, np.where(good, 1 / safe**2, 0.0), x,
                       opts.damping, opts.max_step, opts.albedo_min, opts.albedo_max, opts.iterations)
    assert np.max(np.abs(x - x0)) > 0.1  # the iterations moved the cells
    np.testing.assert_allclose(x, ref, rtol=0, atol=1e-7)
