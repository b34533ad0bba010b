"""Tests of spctool.sim.montecarlo: S16 Table 2 sampling, perturbations, the study driver, Table 3
statistics, report, figures and scene files (spc-algorithms.md §12)."""

from __future__ import annotations

import dataclasses
import json
import math
import multiprocessing as mp
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import norm

sys.path.insert(0, str(Path(__file__).resolve().parent))

import register_scene as rs  # noqa: E402

from spctool.errors import SpcUsageError  # noqa: E402
from spctool.geometry.frames import apply_attitude_update  # noqa: E402
from spctool.sim import montecarlo as mc  # noqa: E402
from spctool.sim import montecarlo_report as mcr  # noqa: E402
from spctool.sim import montecarlo_scene as mcs  # noqa: E402
from spctool.stages.register import RegisterOptions, register  # noqa: E402

# --------------------------------------------------------------------------------------------------
# a small rendered scene (S16 optics at 50 m, 1 cm maplet cells), shared by the module


@pytest.fixture(scope="module")
def scene():
    sc = rs.scene(q=24, q_truth=80, npx=120, nln=120)
    m = mcs.Knowledge.from_maplet(sc.maplet, "LMK001")
    return mcs.Scene(
        "P0001", sc.photo, sc.thresholds, sc.camera, sc.sun, [m], [sc.maplet.v], info={"test": 1}
    )


def _owen(x, y, p):
    """SPC OWEN distortion (spc-algorithms.md §1.3 step 4), written independently of the camera."""
    r = np.hypot(x, y)
    dx = -p[1] * y * r + p[2] * x * r**2 - p[3] * y * r**3 + p[4] * x * r**4 + p[5] * x * y + p[6] * x * x
    dy = p[1] * x * r + p[2] * y * r**2 + p[3] * x * r**3 + p[4] * y * r**4 + p[5] * y * y + p[6] * x * y
    return x + dx, y + dy


# --------------------------------------------------------------------------------------------------
# sampling


@settings(max_examples=40, deadline=None)
@given(n=st.integers(1, 300), d=st.integers(1, 25), seed=st.integers(0, 2**32 - 1))
def test_lhs_uses_every_stratum_once_per_dimension(n, d, seed):
    u = mc.lhs_uniform(n, d, np.random.default_rng(seed))
    assert u.shape == (n, d)
    assert np.all((u > 0) & (u < 1))
    strata = np.floor(u * n).astype(int)
    for k in range(d):
        assert np.array_equal(np.sort(strata[:, k]), np.arange(n))


@settings(max_examples=30, deadline=None)
@given(n=st.integers(1, 200), d=st.integers(1, 25), seed=st.integers(0, 2**32 - 1))
def test_lhs_is_scipys_latin_hypercube_value_for_value(n, d, seed):
    """The own LHS against the independent implementation it replaces: scipy's scrambled
    LatinHypercube given the same generator (scipy ≥ 1.15 spawns its child from it, as lhs_uniform
    does), then the normal inverse CDF of scipy.stats — equal to the last bit."""
    qmc = pytest.importorskip("scipy.stats.qmc")
    try:
        ref = qmc.LatinHypercube(d, rng=np.random.default_rng(seed)).random(n)
    except TypeError:  # pragma: no cover - scipy < 1.15 (no rng keyword, draws the generator itself)
        pytest.skip("scipy < 1.15: LatinHypercube draws differently")
    tiny = 1e-12 / n
    ref = np.clip(ref, tiny, 1.0 - tiny)
    got = mc.lhs_uniform(n, d, np.random.default_rng(seed))
    assert got.view(np.int64).tolist() == ref.view(np.int64).tolist()
    s = seed % 10**6
    z = mc.design(mc.MonteCarloConfig(samples=n, seed=s), 0)
    stream = np.random.SeedSequence([s, mc._SEED_TAG, mc._DESIGN, 0])
    u = qmc.LatinHypercube(z.shape[1], rng=np.random.default_rng(stream)).random(n)
    assert z.view(np.int64).tolist() == norm.ppf(np.clip(u, tiny, 1.0 - tiny)).view(np.int64).tolist()


@settings(max_examples=20, deadline=None)
@given(n=st.integers(2, 200), seed=st.integers(0, 10**6), landmark=st.integers(0, 20))
def test_design_is_lhs_through_the_normal_inverse_cdf(n, seed, landmark):
    cfg = mc.MonteCarloConfig(samples=n, seed=seed)
    z = mc.design(cfg, landmark)
    assert z.shape == (n, len(mc.design_dimensions(cfg)))
    assert np.all(np.isfinite(z))
    strata = np.floor(norm.cdf(z) * n).astype(int)
    for k in range(z.shape[1]):
        assert np.array_equal(np.sort(strata[:, k]), np.arange(n))
    # reproducible; landmarks get their own designs
    assert np.array_equal(z, mc.design(cfg, landmark))
    assert not np.array_equal(z, mc.design(cfg, landmark + 1))


def test_lhs_marginals_are_standard_normal():
    z = mc.design(mc.MonteCarloConfig(samples=2000, seed=3), 0)
    # stratified: the mean and the variance are far closer to 0 and 1 than random sampling gives
    assert np.all(np.abs(z.mean(axis=0)) < 0.01)
    assert np.all(np.abs(z.std(axis=0) - 1.0) < 0.02)
    zmc = mc.design(mc.MonteCarloConfig(samples=2000, seed=3, sampling="mc"), 0)
    assert np.all(np.abs(zmc.mean(axis=0)) < 5.0 / math.sqrt(2000))
    strata = np.floor(norm.cdf(zmc) * 2000).astype(int)
    assert any(len(np.unique(strata[:, k])) < 2000 for k in range(zmc.shape[1]))  # not stratified


def test_design_dimensions_follow_table_2():
    cell = mc.design_dimensions(mc.MonteCarloConfig())
    names = [n for n, _, _ in cell]
    # 3 position, 3 attitude, 3 landmark, skew, 2 centre, focal, 4 non-zero distortion, 2 sun
    assert len(cell) == 19 and "height" not in names and "albedo" not in names
    assert names.count("distortion") == 4
    bias = mc.design_dimensions(mc.MonteCarloConfig(fields="bias"))
    assert len(bias) == 21 and ("height", 0, 3.33e-6) in bias and ("albedo", 0, 0.047) in bias
    two = mc.design_dimensions(mc.MonteCarloConfig(parameters=("sun", "position"), sigma_scale=2.0))
    assert two == [("position", k, 2 * 1.667e-4) for k in range(3)] + [("sun", 0, 0.6), ("sun", 1, 0.6)]
    with pytest.raises(SpcUsageError):
        mc.MonteCarloConfig(parameters=("pose",))
    with pytest.raises(SpcUsageError):
        mc.MonteCarloConfig(sampling="sobol")
    with pytest.raises(SpcUsageError):
        mc.MonteCarloConfig(samples=0)


# --------------------------------------------------------------------------------------------------
# perturbations


def _row(cfg, **values):
    """A design row with the named (parameter, component) entries set (standard normals)."""
    dims = mc.design_dimensions(cfg)
    z = np.zeros(len(dims))
    for i, (n, k, _) in enumerate(dims):
        z[i] = values.get(f"{n}{k}", 0.0)
    return z


def test_zero_row_changes_nothing_but_cell_fields(scene):
    cfg = mc.MonteCarloConfig(fields="bias")
    p = mc.perturb(scene, 0, _row(cfg), 0, cfg)
    cam = scene.camera
    assert np.array_equal(p.camera.scobj, cam.scobj) and np.array_equal(p.camera.rotation, cam.rotation)
    assert np.array_equal(p.camera.ctr, cam.ctr) and p.camera.mmfl == cam.mmfl
    assert np.array_equal(p.sun, scene.sun)
    m0 = scene.maplets[0]
    assert np.array_equal(p.maplet.heights, m0.heights) and np.array_equal(p.maplet.albedo, m0.albedo)
    assert np.array_equal(p.maplet.v, m0.v)
    # a zero OWEN model projects exactly like no model
    pts = m0.v + 1e-4 * np.array([[1.0, 2.0, 0.5], [-3.0, 1.0, 0.0]])
    assert np.allclose(np.stack(p.camera.project(pts)), np.stack(cam.project(pts)), rtol=0, atol=1e-9)


def test_pose_and_landmark_perturbations(scene):
    cfg = mc.MonteCarloConfig()
    p = mc.perturb(scene, 0, _row(cfg, position0=1.0, position2=-2.0, attitude1=1.5, landmark2=-1.0), 0, cfg)
    assert np.allclose(
        p.camera.position - scene.camera.position, [1.667e-4, 0, -3.334e-4], rtol=0, atol=1e-15
    )
    expected = apply_attitude_update(scene.camera.rotation, np.radians([0.0, 0.075, 0.0]))
    assert np.array_equal(p.camera.rotation, expected)
    assert np.allclose(p.maplet.v - scene.maplets[0].v, [0, 0, -3.33e-5], rtol=0, atol=1e-15)
    assert np.allclose(p.values["attitude"], [0, 0.075, 0])


def test_camera_intrinsic_perturbations(scene):
    cam = scene.camera
    cfg = mc.MonteCarloConfig(parameters=("center", "focal", "skew", "distortion"))
    pts = scene.maplets[0].v + np.array([[0.0, 0.0, 0.0], [2e-4, -1e-4, 0.0], [-1e-4, 3e-4, 1e-5]])
    s0, l0 = cam.project(pts)
    # principal point: a pure shift of every pixel
    p = mc.perturb(scene, 0, _row(cfg, center0=1.0, center1=-2.0), 0, cfg)
    s1, l1 = p.camera.project(pts)
    assert np.allclose(s1 - s0, 0.1667, atol=1e-9) and np.allclose(l1 - l0, -0.3334, atol=1e-9)
    # focal length: (pixel − CTR) scales by f'/f (no distortion)
    p = mc.perturb(scene, 0, _row(cfg, focal0=2.0), 0, cfg)
    s1, l1 = p.camera.project(pts)
    ratio = (7.68 + 0.008) / 7.68
    assert np.allclose(s1 - cam.ctr[0], ratio * (s0 - cam.ctr[0]), atol=1e-9)
    assert np.allclose(l1 - cam.ctr[1], ratio * (l0 - cam.ctr[1]), atol=1e-9)
    # skew K21: line += δ·x (x in mm), sample unchanged
    p = mc.perturb(scene, 0, _row(cfg, skew0=1.0), 0, cfg)
    s1, l1 = p.camera.project(pts)
    x_mm = (s0 - cam.ctr[0]) / cam.kmatrix[0, 0]
    assert np.allclose(s1, s0, atol=1e-9) and np.allclose(l1 - l0, 1e-5 * x_mm, atol=1e-9)
    assert p.camera.kmatrix[1, 0] == pytest.approx(1e-5)
    # distortion: an independent OWEN evaluation
    p = mc.perturb(
        scene, 0, _row(cfg, distortion0=1.0, distortion1=-1.0, distortion2=2.0, distortion3=1.0), 0, cfg
    )
    assert p.camera.model == "OWEN"
    coef = np.array([0.0, 1e-5, -1e-7, 2e-5, 1e-5, 0.0, 0.0])
    assert np.allclose(p.camera.coefficients, coef, rtol=0, atol=1e-20)
    zc = scene.camera.to_camera(pts)
    xu, yu = 7.68 * zc[:, 0] / zc[:, 2], 7.68 * zc[:, 1] / zc[:, 2]
    xd, yd = _owen(xu, yu, coef)
    s1, l1 = p.camera.project(pts)
    k = cam.kmatrix
    assert np.allclose(s1, cam.ctr[0] + k[0, 0] * xd + k[0, 1] * yd, atol=1e-9)
    assert np.allclose(l1, cam.ctr[1] + k[1, 0] * xd + k[1, 1] * yd, atol=1e-9)


def test_distortion_needs_owen(scene):
    other = dataclasses.replace(
        scene, camera=dataclasses.replace(scene.camera, model="RADIAL", coefficients=[0.0, 0.0, 0.0])
    )
    cfg = mc.MonteCarloConfig()
    with pytest.raises(SpcUsageError, match="OWEN"):
        mc.perturb(other, 0, _row(cfg, distortion0=1.0), 0, cfg)
    cfg = mc.MonteCarloConfig(parameters=("position",))
    assert mc.perturb(other, 0, _row(cfg, position0=1.0), 0, cfg).camera.model == "RADIAL"


def test_sun_right_ascension_and_declination(scene):
    cfg = mc.MonteCarloConfig(parameters=("sun",))
    p = mc.perturb(scene, 0, _row(cfg, sun0=1.0, sun1=-2.0), 0, cfg)
    s0, s1 = scene.sun, p.sun
    assert np.linalg.norm(s1) == pytest.approx(1.0)
    ra0, dec0 = math.atan2(s0[1], s0[0]), math.asin(s0[2])
    ra1, dec1 = math.atan2(s1[1], s1[0]), math.asin(s1[2])
    assert math.degrees(ra1 - ra0) == pytest.approx(0.3, abs=1e-9)
    assert math.degrees(dec1 - dec0) == pytest.approx(-0.6, abs=1e-9)


def test_terrain_errors_cell_and_bias(scene):
    m0 = scene.maplets[0]
    cfg = mc.MonteCarloConfig(fields="bias", parameters=("height", "albedo"))
    p = mc.perturb(scene, 0, _row(cfg, height0=1.0, albedo0=-1.0), 7, cfg)
    assert np.allclose(p.maplet.heights - m0.heights, 3.33e-6 / m0.scale, atol=1e-12)
    assert np.allclose(p.maplet.albedo - m0.albedo, -0.047, atol=1e-12)
    cfg = mc.MonteCarloConfig(fields="cell", parameters=("height", "albedo"), seed=5)
    a = mc.perturb(scene, 0, _row(cfg), 7, cfg)
    dh = (a.maplet.heights - m0.heights) * m0.scale
    da = a.maplet.albedo - m0.albedo
    n = dh.size
    assert abs(dh.std() / 3.33e-6 - 1) < 5 / math.sqrt(n) and abs(dh.mean()) < 5 * 3.33e-6 / math.sqrt(n)
    assert abs(da.std() / 0.047 - 1) < 5 / math.sqrt(n)
    assert abs(np.corrcoef(dh.ravel(), da.ravel())[0, 1]) < 5 / math.sqrt(n)
    # one stream per (seed, landmark, sample), the same whether or not the other field is on
    b = mc.perturb(scene, 0, _row(cfg), 7, cfg)
    assert np.array_equal(a.maplet.heights, b.maplet.heights)
    only_h = mc.MonteCarloConfig(fields="cell", parameters=("height",), seed=5)
    c = mc.perturb(scene, 0, _row(only_h), 7, only_h)
    assert np.array_equal(c.maplet.heights, a.maplet.heights) and np.array_equal(c.maplet.albedo, m0.albedo)
    d = mc.perturb(scene, 0, _row(cfg), 8, cfg)
    assert not np.array_equal(d.maplet.heights, a.maplet.heights)
    assert np.array_equal(a.maplet.valid, m0.valid)


# --------------------------------------------------------------------------------------------------
# the study


def _same(a, b):
    return np.array_equal(a, b, equal_nan=True)


def _cfg(**kw):
    """The S16 driver with L = 5 … 1: the test maplet has 49×49 cells (L = 10 bins would be too few)."""
    space = kw.pop("space", "maplet")
    plan = mc.default_plan(space, refine=kw.pop("refine", 0), s16_spacings=(5, 4, 3, 2, 1))
    return mc.MonteCarloConfig(space=space, plan=plan, **kw)


@pytest.mark.slow
def test_run_is_reproducible_whatever_jobs_and_chunks(scene):
    cfg = _cfg(samples=4, seed=11, sigma_scale=0.2)
    one = mc.run(scene, cfg, jobs=1)
    again = mc.run(scene, cfg, jobs=1, chunk=1)
    two = mc.run(scene, cfg, jobs=2, chunk=1)
    for r in (again, two):
        assert _same(r.measured, one.measured) and _same(r.apriori, one.apriori)
        assert _same(r.rho, one.rho) and np.array_equal(r.status, one.status)
        assert np.array_equal(r.iterations, one.iterations) and np.array_equal(r.z, one.z)
    assert one.ok.all()  # small perturbations of a good landmark
    assert np.all(np.abs(one.error) < 0.3)
    # another seed gives other samples
    other = mc.run(scene, _cfg(samples=4, seed=12, sigma_scale=0.2), jobs=1)
    assert not _same(other.apriori, one.apriori)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["fork", "spawn"])
def test_workers_started_either_way_give_the_same_samples(scene, monkeypatch, method):
    if method not in mp.get_all_start_methods():
        pytest.skip(f"no {method} here")
    cfg = _cfg(samples=2, seed=5, sigma_scale=0.2)
    one = mc.run(scene, cfg, jobs=1)
    monkeypatch.setenv("SPCTOOL_START_METHOD", method)
    two = mc.run(scene, cfg, jobs=2, chunk=1)
    assert two.timing["start_method"] == method and one.timing["start_method"] == "in-process"
    assert _same(two.measured, one.measured) and np.array_equal(two.status, one.status)


def test_error_is_truth_minus_register(scene):
    cfg = _cfg(samples=2, seed=2, sigma_scale=0.3)
    res = mc.run(scene, cfg)
    z = mc.design(cfg, 0)
    for j in range(2):
        p = mc.perturb(scene, 0, z[j], j, cfg)
        r = register(scene.photo, p.camera, p.sun, [p.maplet], scene.thresholds, cfg.plan[0])
        assert _same(res.measured[0, j], r.measured[0]) and res.status[0, j] == r.status[0]
        assert _same(res.error[0, j], scene.truth[0] - r.measured[0])
        assert _same(res.apriori[0, j], np.array(p.camera.project(p.maplet.v[None]), float).reshape(2))
    assert np.allclose(scene.truth[0], np.array(scene.camera.project(scene.true_v), float).reshape(2))


def test_default_plans():
    (o,) = mc.default_plan("maplet")
    assert [n for _, n in o.steps] == [10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 1]  # refine = 1, then converged
    # the prediction (noisy maplets) is the fitted side of the converged stage's alignment
    assert o.converge_max > 0 and o.converge_peak == mc.MAPLET_CONVERGE_PEAK == "gradient-photo"
    assert mc.default_plan("maplet", converge_peak="gradient")[0].converge_peak == "gradient"
    for other in ("gradient-symmetric", "gradient-weighted"):  # measured in docs/benchmarks.md
        assert mc.default_plan("maplet", converge_peak=other)[0].converge_peak == other
    assert o.extract.linearized and o.extract.criteria is None and o.schedule == "retina_s16"
    assert o.acquire_reach == mc.S16_ACQUIRE_REACH and o.first_phases == 1  # 4 sigma, full overlap
    (s16,) = mc.default_plan("maplet", refine=0, acquire_reach=0)
    assert s16.steps is None and s16.s16_spacings == (10, 9, 8, 7, 6, 5, 4, 3, 2, 1)
    assert s16.acquire_reach == 0 and s16.first_phases == 1
    # the reach follows the perturbation's size; none without perturbation
    assert mc.MonteCarloConfig(sigma_scale=0.5).plan[0].acquire_reach == mc.S16_ACQUIRE_REACH // 2
    assert mc.MonteCarloConfig(sigma_scale=0.0).plan[0].acquire_reach == 0
    with pytest.raises(SpcUsageError):
        mc.default_plan("maplet", acquire_reach=-3)
    coarse, fine = mc.default_plan("image", refine=3)
    assert coarse.space == fine.space == "image" and fine.rerender_tol == 0.0
    assert mc.MonteCarloConfig(space="image", plan=(coarse, fine)).steps == [4, 2, 1, 1, 1, 1]
    assert coarse.converge_max == 0 and fine.converge_max > 0  # the fine phase ends converged
    # image space (issue 39): the template fitted on the photo, 2 × 2 rays, no cast shadows (the study's
    # noisy heights cast shadows the terrain lacks); register keeps "gradient", shadows, and 2 rays
    assert coarse.converge_peak == fine.converge_peak == mc.IMAGE_CONVERGE_PEAK == "gradient-photo"
    assert coarse.image_shadows is fine.image_shadows is mc.IMAGE_TEMPLATE_SHADOWS is False
    assert fine.supersample == mc.IMAGE_SUPERSAMPLE == 2
    assert coarse.supersample == 1  # the coarse phase only acquires: one ray per pixel
    assert all(o.supersample == 2 for o in mc.default_plan("image", supersample=2))  # as asked
    # SPC's node slopes (the fourth-order ones lower the floor but amplify the height noise)
    assert coarse.template_slopes == fine.template_slopes == mc.IMAGE_TEMPLATE_SLOPES == "spc"
    assert all(o.template_slopes == "fourth" for o in mc.default_plan("image", template_slopes="fourth"))
    # the radiance interpolated from the nodes (maplet space's prediction), not the slopes (register's)
    assert coarse.template_shading == fine.template_shading == mc.IMAGE_TEMPLATE_SHADING == "gouraud"
    assert all(o.template_shading == "smooth" for o in mc.default_plan("image", template_shading="smooth"))
    reg = RegisterOptions()
    assert reg.image_shadows and reg.converge_peak == "gradient" and reg.template_slopes == "spc"
    assert reg.template_shading == "smooth"
    before = dict(supersample=1, image_shadows=True, converge_peak="gradient", template_slopes="spc")
    before["template_shading"] = "smooth"
    old = mc.default_plan("image", **before)
    assert all(all(getattr(o, k) == v for k, v in before.items()) for o in old)
    # ±48 px at L = 4 (25 × 25 bins), then ±3 bins: the estimate is within a bin or two by then
    assert coarse.acquire_reach == mc.IMAGE_ACQUIRE_REACH == 48 and coarse.steps[0] == 4
    assert coarse.grid_half == fine.grid_half == mc.IMAGE_GRID_HALF == 3
    # image space converges to 0.01 px (every step re-renders); maplet space keeps register's 0.005
    assert coarse.converge_tol == fine.converge_tol == mc.IMAGE_CONVERGE_TOL == 0.01
    assert o.converge_tol == RegisterOptions().converge_tol == 0.005
    assert mc.default_plan("image", converge_tol=0.005)[1].converge_tol == 0.005
    assert len(mc.default_plan("image", refine=0)) == 1
    # the converged stage's cost (issue 39): drafts to 0.05 px (at most 3), then the first 2 × 2
    # template ends it below 0.03 px; register keeps 0.15 px, no cap, every full step verified
    assert (fine.converge_draft_tol, fine.converge_draft_max, fine.converge_accept) == (
        mc.IMAGE_DRAFT_TOL, mc.IMAGE_DRAFT_MAX, mc.IMAGE_CONVERGE_ACCEPT) == (0.05, 3, 0.03)  # fmt: skip
    assert (reg.converge_draft_tol, reg.converge_draft_max, reg.converge_accept) == (0.15, 0, 0.0)
    assert mc.default_plan("image", converge_accept=0.0)[1].converge_accept == 0.0
    with pytest.raises(SpcUsageError):
        mc.default_plan("pixel")
    with pytest.raises(SpcUsageError):
        mc.MonteCarloConfig(space="maplet", plan=coarse)


def test_phases_chain_from_the_previous_measurement(scene):
    """A two-phase plan equals running the second phase from the first phase's measurement."""
    cfg = _cfg(samples=1, seed=4, sigma_scale=0.3)
    second = mc.default_plan("maplet", refine=0, steps=(1, 1))[0]
    two = mc.MonteCarloConfig(samples=1, seed=4, sigma_scale=0.3, plan=(cfg.plan[0], second))
    p = mc.perturb(scene, 0, mc.design(cfg, 0)[0], 0, cfg)
    first = register(scene.photo, p.camera, p.sun, [p.maplet], scene.thresholds, cfg.plan[0])
    then = register(
        scene.photo, p.camera, p.sun, [p.maplet], scene.thresholds, second, apriori=first.measured
    )
    both = mc.register_sample(scene, p, two.plan)
    assert first.status == ["ok"] and both.status == then.status
    assert _same(both.measured, then.measured) and _same(both.apriori, first.apriori)
    assert both.iterations[0] == first.iterations[0] + then.iterations[0]
    assert np.abs(both.measured - first.measured).max() < 0.2


@pytest.mark.parametrize("study_plan", [False, True])
def test_a_sample_carries_its_templates_to_the_next(scene, monkeypatch, study_plan):
    """Image space: each sample hands its last template (where its rays hit) to the landmark's next
    sample, whose first template starts each ray in the cell predicted from it
    (:meth:`Registrar._carried_hint`); the measurements are those without the carry, bit for bit,
    and the hint is used and mostly right.  The carried template has the first one's rays per pixel:
    a one-ray plan's last, or, for the study's plan (a one-ray coarse phase, then 2 × 2), the last
    one-ray template of the previous sample's, kept beside its last (2 × 2) one."""
    from spctool.stages import registrar as regmod
    from spctool.stages import render as rmod

    if study_plan:
        plan = mc.default_plan("image", s16_spacings=(5, 4, 3, 2, 1))
        assert [o.supersample for o in plan] == [1, 2]
    else:
        plan = mc.default_plan("image", refine=0, s16_spacings=(5, 4, 3, 2, 1), supersample=1)
    cfg = mc.MonteCarloConfig(samples=3, seed=5, sigma_scale=0.3, space="image", plan=plan)
    real_hint, real_render = regmod.Registrar._carried_hint, rmod.render
    carried, agree = [], []

    def hint(self, *args):
        out = real_hint(self, *args)
        carried.append(out)
        return out

    def render(*args, **kw):
        out = real_render(*args, **kw)
        if carried and carried[-1] is not None and kw.get("cells") is carried[-1]:
            hit = out.cells >= 0
            agree.append(np.mean(carried[-1][hit] == out.cells[hit]))
        return out

    monkeypatch.setattr(regmod.Registrar, "_carried_hint", hint)
    monkeypatch.setattr(rmod, "render", render)
    carry: dict = {}
    for j in range(3):
        p = mc.perturb(scene, 0, mc.design(cfg, 0)[j], j, cfg)
        n_hints = len(carried)
        with_carry = mc.register_sample(scene, p, cfg.plan, carry)
        if j > 0:  # the sample's first template was hinted from the previous sample's
            assert carried[n_hints] is not None
        # the templates (the last, and the last per rays per pixel) and the settings made from each
        # phase's options, not the sample's patch
        assert sorted(k[0] for k in carry) == ["options"] * len(cfg.plan) + ["template"] * (2 + study_plan)
        keys = sorted((k for k in carry if k[0] == "template"), key=len)
        per_rays = [("template", "LMK001", k) for k in (1, 2)[: 1 + study_plan]]
        assert keys == [("template", "LMK001")] + per_rays
        plain = mc.register_sample(scene, p, cfg.plan)
        assert with_carry.status == plain.status == ["ok"]
        assert _same(with_carry.measured, plain.measured)
        assert _same(with_carry.correlation, plain.correlation)
    if not study_plan:
        assert sum(h is not None for h in carried) == 2  # the first template of samples 1 and 2
    assert len(agree) >= 2 and min(agree) > 0.5


# --------------------------------------------------------------------------------------------------
# statistics and report


def _fake_result(statuses, errors, rho, names=("A", "B")):
    n = len(statuses[0])
    cfg = mc.MonteCarloConfig(samples=n, parameters=("position",))
    truth = np.array([[100.0, 200.0], [300.0, 400.0]])[: len(names)]
    st_ = np.array(statuses, dtype=object).astype(str)
    meas = truth[:, None, :] - np.asarray(errors, float)
    meas[st_ != "ok"] = np.nan
    z = np.random.default_rng(0).standard_normal((len(names), n, 3))
    return mc.MonteCarloResult(
        {"preset": "test"},
        "P1",
        list(names),
        truth,
        cfg,
        mc.design_dimensions(cfg),
        z,
        truth[:, None, :] + z[..., :2],
        meas,
        st_,
        np.asarray(rho, float),
        np.full((len(names), n), 10),
    )


def test_table3_statistics():
    statuses = [
        ["ok", "ok", "ok", "not-found", "low-correlation"],
        ["ok", "edge-peak", "outside", "ok", "ok"],
    ]
    errors = np.zeros((2, 5, 2))
    errors[0, :3] = [[0.1, -0.2], [0.3, 0.0], [-0.1, 0.1]]
    errors[1, [0, 3, 4]] = [[0.05, 0.0], [0.05, 0.1], [0.2, -0.1]]
    rho = [[0.6, 0.7, 0.5, np.nan, 0.2], [0.9, 0.8, np.nan, 0.7, 0.6]]
    s = mcr.summarise(_fake_result(statuses, errors, rho))
    a, b = s["landmarks"]
    assert a["sample_mean"] == pytest.approx(0.1) and a["line_mean"] == pytest.approx(-1 / 30)
    assert a["sample_std"] == pytest.approx(np.std([0.1, 0.3, -0.1], ddof=1))
    assert a["line_std"] == pytest.approx(np.std([-0.2, 0.0, 0.1], ddof=1))
    assert (a["not_found"], a["below_threshold"], a["ok"]) == (1, 1, 3)
    assert a["success_rate"] == pytest.approx(0.6)
    assert a["mean_max_rho"] == pytest.approx(np.mean([0.6, 0.7, 0.5, 0.2])) and a["rho_defined"] == 4
    assert (b["not_found"], b["below_threshold"]) == (2, 0)
    assert b["status_counts"] == {"edge-peak": 1, "ok": 3, "outside": 1}
    o = s["overall"]
    assert o["samples"] == 10 and o["ok"] == 6 and o["success_rate"] == pytest.approx(0.6)
    ok_err = np.concatenate([errors[0, :3], errors[1, [0, 3, 4]]])
    assert o["sample_mean"] == pytest.approx(ok_err[:, 0].mean())
    assert o["line_std"] == pytest.approx(ok_err[:, 1].std(ddof=1))
    assert o["max_abs_sample_mean"] == pytest.approx(0.1) and o["min_success_rate"] == pytest.approx(0.6)
    assert s["checks"]["image_targets"]["success_rate"] is False
    assert s["checks"]["image_targets"]["abs_sample_mean"] is False  # pooled mean 0.1 > 0.05
    assert s["checks"]["image_targets_per_landmark"]["max_abs_sample_mean"] is False
    assert s["checks"]["image_targets_per_landmark"]["max_line_std"] is False  # std of −0.2, 0, 0.1
    assert s["checks"]["s16_table3"]["success_rate"] is False
    assert [mc.status_class(x) for x in ("ok", "low-correlation", "edge-peak", "removed-cov", "outside")] == [
        "ok",
        "below",
        "not-found",
        "not-found",
        "not-found",
    ]


def test_s16_table3_transcription_is_consistent():
    # success = (500 − not found − below threshold)/500 for every row (spc-algorithms.md §8.2)
    for name, row in mc.S16_TABLE3.items():
        assert round((500 - row[4] - row[5]) / 500, 2) == pytest.approx(row[6], abs=0.0051), name
    agg = mcr._s16_aggregate()
    assert agg["success_rate"] == pytest.approx(1 - (sum(r[4] + r[5] for r in mc.S16_TABLE3.values())) / 6000)
    assert agg["max_abs_sample_mean"] == 0.208 and agg["max_line_std"] == 0.113
    assert list(mc.S16_TABLE3) == list(mc.S16_LANDMARKS)


def test_report_json_and_figures(tmp_path):
    rng = np.random.default_rng(4)
    n = 60
    statuses = [["ok"] * 55 + ["not-found"] * 3 + ["low-correlation"] * 2, ["ok"] * 60]
    errors = rng.normal(0.0, 0.05, (2, n, 2))
    rho = rng.uniform(0.4, 0.9, (2, n))
    res = _fake_result(statuses, errors, rho)
    res.timing = {"run_s": 1.0, "per_sample_ms": 8.3, "jobs": 1, "samples": 120}
    text = mcr.format_report(res)
    assert "s mean" in text and "S16 Table 3" in text and "B01980" in text
    table3 = text.split("per-landmark targets")[0]
    lines = [ln for ln in table3.splitlines() if ln.startswith(("A ", "B ", "all "))]
    assert len(lines) == 3 and lines[0].split()[5:7] == ["3", "2"]
    doc = mcr.report_document(res)
    json.dumps(doc, allow_nan=False)
    assert doc["command"] == "montecarlo" and len(doc["landmarks"]) == 2
    assert doc["landmarks"][0]["success_rate"] == pytest.approx(55 / 60)
    assert doc["overall"]["success_rate"] == pytest.approx(115 / 120)
    assert doc["sensitivity"] and doc["dimensions"][0]["parameter"] == "position"
    paths = mcr.write_figures(res, tmp_path / "figs")
    from PIL import Image

    for p in paths:
        im = Image.open(p)
        assert im.format == "PNG" and im.size[0] > 500
        assert len(np.unique(np.asarray(im.convert("L")))) > 5  # something was drawn
    csv = mcr.write_samples_csv(res, tmp_path / "s.csv").read_text().splitlines()
    assert len(csv) == 1 + 120 and csv[0].startswith("landmark,sample,status")
    assert csv[56].split(",")[2] == "not-found"


def test_sensitivity_recovers_a_linear_model():
    rng = np.random.default_rng(9)
    n = 400
    res = _fake_result([["ok"] * n, ["ok"] * n], np.zeros((2, n, 2)), np.full((2, n), 0.8))
    noise = rng.normal(0, 0.001, (2, n, 2))
    err = (
        0.02 * res.z[..., [0]] * np.array([1.0, -0.5]) + 0.01 * res.z[..., [2]] * np.array([0.0, 1.0]) + noise
    )
    res.measured = res.truth[:, None, :] - (
        err + np.array([[[0.1, -0.2]], [[0.0, 0.3]]])
    )  # per-landmark biases
    sens = mcr.sensitivity(res)
    assert [r["parameter"] for r in sens] == ["position"] * 3
    assert sens[0]["sample_px_per_sigma"] == pytest.approx(0.02, abs=5e-4)
    assert sens[0]["line_px_per_sigma"] == pytest.approx(-0.01, abs=5e-4)
    assert sens[2]["line_px_per_sigma"] == pytest.approx(0.01, abs=5e-4)
    assert abs(sens[1]["sample_px_per_sigma"]) < 5e-4


# --------------------------------------------------------------------------------------------------
# scenes


def test_scene_file_round_trip(scene, tmp_path):
    path = mcs.save_scene(scene, tmp_path / "scene.npz")
    back = mcs.load_scene(path)
    assert np.array_equal(back.photo, scene.photo) and np.array_equal(back.truth, scene.truth)
    assert (
        np.array_equal(back.camera.rotation, scene.camera.rotation)
        and back.camera.model == scene.camera.model
    )
    assert back.names == scene.names and back.thresholds == scene.thresholds and back.info == scene.info
    for a, b in zip(back.maplets, scene.maplets):
        for key in ("heights", "albedo", "valid", "v", "ux", "uy", "uz"):
            assert np.array_equal(getattr(a, key), getattr(b, key))
        assert a.scale == b.scale
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(SpcUsageError):
        mcs.load_scene(tmp_path / "bad.npz")
    with pytest.raises(SpcUsageError):
        scene.subset(["NOPE"])


@pytest.mark.parametrize("exact", [True, False])
def test_s16_exact_maplets_control_world_is_the_photo_surface(exact):
    """``exact_maplets``: the onboard maplet is the surface that renders the photo (to the MAP encoding's
    quantisation); the preset's own maplets differ from it by the 3.33 mm → 1 cm smoothing."""
    from spctool.formats.maplet import format_map, parse_map
    from spctool.sim.simulate import build_world
    from spctool.sim.spec import parse_spec

    d = mcs.s16_spec(16, exact_maplets=exact)
    for key in ("names", "positions"):  # one landmark is enough
        d["maplets"][key] = d["maplets"][key][:1]
    lm = build_world(parse_spec(d), lambda msg: None).landmarks[0]
    m = parse_map(format_map(lm.maplet), "X.MAP", name="X")
    truth = lm.truth
    k = 1 if exact else 3  # truth nodes per maplet cell
    margin = d["maplets"]["margin"] * k
    nodes = slice(margin, margin + 99 * k, k)
    at_nodes = truth.heights[nodes, nodes] * truth.scale / m.scale
    assert np.linalg.norm(np.asarray(m.v) - np.asarray(truth.v)) < 1e-8  # same V (km)
    diff = np.abs(m.heights - at_nodes).max()
    if exact:
        assert diff < 1e-3  # cells: the MAP encoding's quantisation
        assert np.allclose(m.albedo, truth.albedo[nodes, nodes], atol=0.0051)  # MAP albedo: 0.01 steps
    else:
        assert diff > 0.1  # cells: the smoothing of the preset's 3.33 mm truth


def test_s16_spec_camera_and_scene_window():
    from spctool.sim.spec import parse_spec

    spec = parse_spec(mcs.s16_spec(16))
    c = spec.camera
    assert (c.npx, c.nln, c.mmfl) == (2592, 1944, 7.68)
    assert c.kmatrix == [[454.54, 0.0, 0.0], [0.0, -454.54, 0.0]]
    # S16 Table 1: FOV 40.7 x 31.1 deg from 2.2 um pixels
    assert math.degrees(2 * math.atan(2592 / 2 / 454.54 / 7.68)) == pytest.approx(40.7, abs=0.05)
    assert math.degrees(2 * math.atan(1944 / 2 / 454.54 / 7.68)) == pytest.approx(31.1, abs=0.05)
    assert spec.maplets.names == list(mc.S16_LANDMARKS) and spec.maplets.qsz == 49
    assert spec.maplets.scale_km == 1e-5 and spec.pictures[0].range_km == 0.05
    # window: half diagonal + 5 sigma of the a-priori error + the L = 10 search, in pixels at 50 m
    cam = rs.s16_camera(np.zeros(3), np.array([0.0, 0.0, 0.05]), npx=2592, nln=1944)
    m = mcs.Knowledge(
        "X",
        np.zeros((99, 99)),
        np.ones((99, 99)),
        np.ones((99, 99), bool),
        1e-5,
        np.zeros(3),
        np.eye(3)[0],
        np.eye(3)[1],
        np.eye(3)[2],
    )
    px = 0.05 * cam.ifov
    expected = math.sqrt(2) * 49.5e-5 / px + 5 * math.hypot(1.667e-4 / px, math.radians(0.05) / cam.ifov) + 60
    assert mcs.scene_window_half(cam, m) == math.ceil(expected)


def test_zero_perturbation_floor_is_registered_without_the_accepted_step(scene, monkeypatch):
    """The image plan's samples may end on an unverified full step (``converge_accept``), whose error
    averages out of their means but not out of the floor's one registration: the floor runs the plan
    with it off, and otherwise the same phases."""
    plan = mc.default_plan("image", s16_spacings=(5, 4, 3, 2, 1))
    assert plan[1].converge_accept > 0
    cfg = mc.MonteCarloConfig(samples=1, space="image", plan=plan)
    seen = []
    real = mc.register_sample

    def spy(scene_, p, plan_, carry=None):
        seen.append(plan_)
        return real(scene_, p, plan_, carry)

    monkeypatch.setattr(mc, "register_sample", spy)
    floor = mc.zero_floor(scene, cfg)
    (used,) = seen
    assert [o.converge_accept for o in used] == [0.0, 0.0]
    assert [dataclasses.replace(o, converge_accept=a) for o, a in zip(used, (0.0, 0.03))] == list(plan)
    zero = {q.name: np.zeros(q.size) for q in mc.PARAMETERS}
    ref = real(scene, mc.Perturbed(scene.camera, scene.sun, scene.maplets[0], zero), used)
    assert _same(floor[0], scene.truth[0] - ref.measured[0])


def test_zero_perturbation_floor_is_reported_beside_the_bias(scene):
    """run() registers every landmark once with its knowledge unperturbed: the floor equals truth −
    register() on the scene's own camera, Sun and maplet (every plan phase chained by hand), and the
    report gives |mean − floor| per axis beside it."""
    cfg = _cfg(samples=2, seed=2, sigma_scale=0.3)
    res = mc.run(scene, cfg)
    r = None
    for k, opts in enumerate(cfg.plan):
        apriori = None if r is None else r.measured
        r = register(scene.photo, scene.camera, scene.sun, [scene.maplets[0]], scene.thresholds, opts,
                     apriori=apriori)  # fmt: skip
        assert r.status[0] == "ok", (k, r.status)
    assert res.floor.shape == (1, 2) and _same(res.floor[0], scene.truth[0] - r.measured[0])
    s = mcr.summarise(res)
    row = s["landmarks"][0]
    assert row["sample_floor"] == res.floor[0, 0] and row["line_floor"] == res.floor[0, 1]
    assert row["sample_excess"] == pytest.approx(abs(row["sample_mean"] - res.floor[0, 0]))
    assert s["overall"]["max_line_excess"] == row["line_excess"]
    text = mcr.format_report(res, s)
    assert "floor = the landmark registered with every Table 2 sigma at zero" in text
    assert "worst landmark per target" in text
    # a result without a floor (an older run) reports none and judges no excess
    fake = _fake_result([["ok", "ok"], ["ok", "ok"]], np.zeros((2, 2, 2)), [[0.9, 0.9], [0.9, 0.9]])
    text = mcr.format_report(fake)
    assert fake.floor is None and "no zero-perturbation floor in this result: excess not judged" in text
    fs = mcr.summarise(fake)
    assert math.isnan(fs["landmarks"][0]["sample_floor"]) and "excess" not in fs["landmarks"][0]["targets"]
    assert set(fs["checks"]["landmark_targets"]) == {"max_std", "min_success_rate"}


def _excess_world():
    """Two landmarks, 400 samples each, hand-made errors: A's mean on its floor, B's sample mean on the
    other side of its floor (mean −0.04, floor +0.04: |mean| − |floor| = 0, the shift is 0.08 px)."""
    rng = np.random.default_rng(5)
    e = rng.normal(0.0, 0.03, (2, 400, 2))
    e -= e.mean(axis=1, keepdims=True)  # exact means below
    e[0] += [0.045, -0.02]
    e[1] += [-0.04, 0.01]
    res = _fake_result([["ok"] * 400] * 2, e, np.full((2, 400), 0.9))
    res.floor = np.array([[0.045, -0.02], [0.04, 0.013]])
    return res, e


def test_excess_is_the_shift_from_the_floor_with_its_sampling_error():
    res, e = _excess_world()
    s = mcr.summarise(res)
    a, b = s["landmarks"]
    assert a["sample_excess"] == pytest.approx(0.0, abs=1e-12) and a["line_excess"] == pytest.approx(
        0.0, abs=1e-12
    )
    # opposite signs: |mean| − |floor| would read 0; the perturbations moved B's mean by 0.08 px
    assert b["sample_excess"] == pytest.approx(0.08) and b["line_excess"] == pytest.approx(0.003)
    assert b["excess"] == pytest.approx(0.08) and b["excess_se"] == pytest.approx(e[1, :, 0].std(ddof=1) / 20)
    assert b["line_mean_se"] == pytest.approx(e[1, :, 1].std(ddof=1) / math.sqrt(400))
    assert b["excess_z"] == pytest.approx(0.08 / b["excess_se"])
    assert (
        a["verdict"] == "PASS"
        and b["verdict"] == "MISS"
        and b["targets"]
        == {
            "excess": False,
            "std": True,
            "success": True,
        }
    )
    w = s["overall"]["worst_landmarks"]
    assert (w["excess"]["name"], w["excess"]["pass"]) == ("B", False)
    assert s["overall"]["max_excess"] == pytest.approx(0.08)
    assert s["checks"]["landmark_targets"] == {"max_excess": False, "max_std": True, "min_success_rate": True}
    text = mcr.format_report(res, s)
    assert "excess <= 0.01 px: B 0.0800 MISS" in text and "landmarks meeting every target: 1 of 2" in text
    row_b = next(ln for ln in text.splitlines() if ln.startswith("B ") and ln.rstrip().endswith("MISS"))
    assert "0.0800 +-0.0015" in row_b


def test_landmark_verdicts_on_spread_success_and_a_lost_floor():
    res, e = _excess_world()
    res.floor = np.array([[0.045, -0.02], [-0.04, 0.01]])  # B now on its floor too
    assert mcr.summarise(res)["checks"]["landmark_targets"] == dict.fromkeys(
        ("max_excess", "max_std", "min_success_rate"), True
    )
    # a 1σ of 0.05 px on A's line axis; 3 of 400 of B's samples lost (99.25 %)
    e2 = e.copy()
    e2[0, :, 1] = (e2[0, :, 1] - e2[0, :, 1].mean()) * (0.05 / e2[0, :, 1].std(ddof=1)) - 0.02
    st_ = [["ok"] * 400, ["ok"] * 397 + ["not-found"] * 3]
    res2 = _fake_result(st_, e2, np.full((2, 400), 0.9))
    res2.floor = np.array([[0.045, -0.02], [np.nan, np.nan]])  # B's floor registration failed
    s = mcr.summarise(res2)
    a, b = s["landmarks"]
    assert a["targets"] == {"excess": True, "std": False, "success": True}
    assert b["targets"] == {"excess": False, "std": True, "success": False}  # a lost floor is a miss
    w = s["overall"]["worst_landmarks"]
    assert (w["std"]["name"], w["std"]["value"]) == ("A", pytest.approx(0.05))
    assert (w["success"]["name"], w["success"]["value"]) == ("B", pytest.approx(0.9925))
    assert w["excess"]["name"] == "B" and math.isnan(w["excess"]["value"])
    doc = mcr.report_document(res2, s)
    assert doc["landmarks"][1]["verdict"] == "MISS" and doc["landmarks"][1]["excess"] is None
