"""Navigation on a world spctool did not render (issue #15): trimesh + Embree ray casting of a triangle
mesh finer than the maplets, Lambert shading, cast shadows, noise, a-priori errors of 6, 14 and ~20 px
(:mod:`spctool.sim.independent`), for a faceted and a smooth truth.

Thresholds asserted are the issue's targets where the merged code meets them, tight so that a
regression fails (measured on this world, pooled over 3 pictures x 9 landmarks, 100 % found in both
passes and both spaces; ``pytest -s`` prints them):

======  ========================  ========================  ==========================
truth   maplet one pass rms       maplet two-pass rms/max   image two-pass rms/max
======  ========================  ========================  ==========================
facet   0.0248 px                 0.0250 / 0.071 px         0.0293 / 0.069 px
smooth  0.0238 px                 0.0239 / 0.064 px         0.0287 / 0.066 px
======  ========================  ========================  ==========================

Both spaces meet the issue (two-pass <= 0.03 px, one pass <= 0.05 px, max <= 0.1 px).  Image space
met only the max until the converged stage read its steps by least-squares alignment instead of the
correlation surface's vertex (``RegisterOptions.converge_peak``): 0.0510 / 0.097 and 0.0502 / 0.099 px
with the vertex (benchmarks/bench_accuracy.py's bigger world: 0.038 → 0.019 px).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("trimesh")
from spctool.geometry.shape import embree_available  # noqa: E402
from spctool.sim.independent import load_picture, navigate_picture  # noqa: E402

# the worlds take a minute or two to ray-trace: slow (CI runs them, tests/conftest.py)
pytestmark = [pytest.mark.skipif(not embree_available(), reason="embreex not installed"), pytest.mark.slow]

ISSUE_TWO_PASS_RMS, ISSUE_ONE_PASS_RMS, ISSUE_MAX = 0.03, 0.05, 0.1


@pytest.fixture(scope="session")
def worlds(tmp_path_factory):
    """Both truths, built once per test session."""
    from spctool.sim.independent import IndependentSpec, build_world

    out = {}
    for truth in ("facet", "smooth"):
        root = tmp_path_factory.mktemp(f"independent_{truth}")
        out[truth] = (root, build_world(root, IndependentSpec(truth=truth)))
    return out



def _navigate(root, pic_doc, space="maplet", passes=2, **register):
    from spctool.stages.navigate import NavigateOptions
    from spctool.stages.register import RegisterOptions

    loaded = load_picture(root, pic_doc)
    opts = NavigateOptions(passes=passes, register=RegisterOptions(space=space, **register))
    return navigate_picture(loaded, opts), loaded[5]


def _errors(reg, truth):
    return np.linalg.norm(reg.measured - truth, axis=1)


# ------------------------------------------------------------------------------------------------
# the world itself


def test_independent_pinhole_agrees_with_spctool_camera(worlds):
    """Truth pixels come from the world's own pinhole; spctool's Camera (SUM + INIT_LITHOS) with the
    true pose projects the landmarks to the same pixels."""
    from spctool.formats.workdir import WorkDir
    from spctool.geometry.camera import Camera

    root, doc = worlds["facet"]
    wd = WorkDir(root)
    for p in doc["pictures"]:
        cam = Camera.from_picture(wd.read_picture(p["name"]), wd.read_settings()).with_pose(
            scobj=np.array(p["scobj"]), rotation=np.array(p["rotation"])
        )
        names = sorted(p["pixels"])
        v = np.array([doc["landmarks"][n] for n in names])
        got = np.stack(cam.project(v), axis=-1)
        assert np.max(np.abs(got - np.array([p["pixels"][n] for n in names]))) < 1e-8


def test_world_is_an_spc_working_directory_with_the_apriori_errors(worlds):
    from spctool.formats.lists import read_lmrklist, read_pictlist

    for truth, (root, doc) in worlds.items():
        assert json.loads((root / "TRUTH.json").read_text())["spec"]["truth"] == truth
        pics = [e.name for e in read_pictlist(root / "PICTLIST.TXT").entries]
        assert pics == [p["name"] for p in doc["pictures"]]
        assert len(read_lmrklist(root / "LMRKLIST.TXT").names) == 9
        errs = []
        for p in doc["pictures"]:
            _, cam, photo, names, maplets, true_px = load_picture(root, p)
            apri = np.stack(cam.project(np.array([m.v for m in maplets])), axis=-1)
            errs.append(np.max(np.linalg.norm(apri - true_px, axis=1)))
            data = np.asarray(photo.data, float)
            inner = data[40:-40, 40:-40]
            assert np.all(inner > 0)  # the mesh covers the landmarks' neighbourhood
            # cast shadows: some of the scene is at the dark level (bias + noise; measured 0.1-0.8 %)
            assert np.mean(data[data > 0] < 200 + 4 * 20) > 5e-4
        assert errs[0] == pytest.approx(6.0, abs=0.5)
        assert errs[1] == pytest.approx(14.0, abs=0.5)
        assert 19.0 <= errs[2] <= 20.5


def test_facet_and_smooth_photos_differ(worlds):
    """The two truths are different renders of the same terrain (not the same photo twice)."""
    a = np.asarray(load_picture(*[worlds["facet"][0], worlds["facet"][1]["pictures"][0]])[2].data, float)
    b = np.asarray(load_picture(*[worlds["smooth"][0], worlds["smooth"][1]["pictures"][0]])[2].data, float)
    diff = np.abs(a - b)[40:-40, 40:-40]
    assert diff.mean() > 5.0 and np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.9


# ------------------------------------------------------------------------------------------------
# navigation


@pytest.mark.parametrize("truth", ["facet", "smooth"])
def test_two_pass_navigation_maplet_space(worlds, truth):
    root, doc = worlds[truth]
    rows, all1, all2 = [], [], []
    for p in doc["pictures"]:
        res, true_px = _navigate(root, p)
        assert res.status == "ok"
        e1 = _errors(res.passes[0].register, true_px)
        e2 = _errors(res.passes[1].register, true_px)
        assert res.passes[0].register.ok.all() and res.passes[1].register.ok.all()  # 100 % found
        all1.append(e1)
        all2.append(e2)
        rms1, rms2 = float(np.sqrt(np.mean(e1**2))), float(np.sqrt(np.mean(e2**2)))
        rows.append((p["name"], p["apriori_px"], rms1, e1.max(), rms2, e2.max()))
        # per picture (measured: facet 0.021 / 0.030 / 0.024, smooth 0.020 / 0.029 / 0.023 px)
        assert rms2 <= 0.035
        # the second pass (from the solved pose) is never worse than the first by more than noise
        assert rms2 <= rms1 + 0.005
        assert res.pose is not None and res.pose.converged
    e1, e2 = np.concatenate(all1), np.concatenate(all2)
    rms1, rms2 = float(np.sqrt(np.mean(e1**2))), float(np.sqrt(np.mean(e2**2)))
    print(f"\n{truth} truth, maplet space (issue: two-pass <= {ISSUE_TWO_PASS_RMS}, one pass <= "
          f"{ISSUE_ONE_PASS_RMS}, max <= {ISSUE_MAX} px)")  # fmt: skip
    for r in rows:
        name, apri, r1, m1, r2, m2 = r
        print(f"  {name} a-priori {apri:5.1f} px: one pass rms {r1:.3f} max {m1:.3f} | "
              f"two-pass rms {r2:.3f} max {m2:.3f}")  # fmt: skip
    print(f"  pooled: one pass rms {rms1:.4f} | two-pass rms {rms2:.4f} max {e2.max():.4f}")
    # the issue's targets (measured pooled: facet 0.025 / 0.025, max 0.072; smooth 0.025 / 0.025, 0.065)
    # the issue's two-pass rms; max and one-pass bounds tighter than the issue's (0.1, 0.05 px)
    assert rms2 <= ISSUE_TWO_PASS_RMS and e2.max() <= 0.08
    assert rms1 <= 0.03


@pytest.mark.parametrize("truth", ["facet", "smooth"])
def test_two_pass_navigation_image_space(worlds, truth):
    root, doc = worlds[truth]
    all2 = []
    for p in doc["pictures"]:
        res, true_px = _navigate(root, p, space="image")
        assert res.status == "ok"
        assert res.passes[0].register.ok.all() and res.passes[1].register.ok.all()  # 100 % found
        all2.append(_errors(res.passes[1].register, true_px))
    e2 = np.concatenate(all2)
    rms2 = float(np.sqrt(np.mean(e2**2)))
    print(f"\n{truth} truth, image space: two-pass rms {rms2:.4f} max {e2.max():.4f} px")
    # the issue's two-pass rms (measured 0.0293 / 0.0287; 0.0286 / 0.0281 with --photo-shadows use) and a
    # max tighter than its 0.1 px (0.069 / 0.066; 0.060 / 0.065)
    assert rms2 <= ISSUE_TWO_PASS_RMS and e2.max() <= 0.08


@pytest.mark.parametrize("truth", ["facet", "smooth"])
def test_raster_templates_measure_what_the_march_measures(worlds, truth):
    """Issue 17: rendering the templates forward must not move a measured pixel by more than 0.002 px on
    the test worlds.  On photos ray-traced by another renderer, two-pass image-space navigation with
    raster templates (the default) and with the grid march measures the same pixels, both passes."""
    root, doc = worlds[truth]
    p = doc["pictures"][-1]  # the largest a-priori error, ~20 px
    raster, true_px = _navigate(root, p, space="image", threads=1)
    march, _ = _navigate(root, p, space="image", threads=1, template_visibility="march")
    assert raster.status == march.status == "ok"
    for a, b in zip(raster.passes, march.passes):
        assert a.register.ok.all() and list(a.register.status) == list(b.register.status)
        np.testing.assert_array_equal(a.register.measured, b.register.measured)
    assert np.max(_errors(raster.passes[1].register, true_px)) <= 0.08


@pytest.mark.parametrize("truth", ["facet", "smooth"])
def test_pass_2_started_from_pass_1_jacobians_measures_the_same(worlds, truth, monkeypatch):
    """navigate's pass 2 starts its converged stages from the secant Jacobians pass 1 learned (the
    estimator's gain): no more steps than from −I, and the same pixels within issue 17's 0.002 px
    (measured ≤ 0.0005 px here; the stage's zero does not depend on its start)."""
    import spctool.stages.navigate as nav_mod

    root, doc = worlds[truth]
    p = doc["pictures"][-1]
    seeded, _ = _navigate(root, p, space="image", threads=1)
    plain_register = nav_mod.register

    def without_start(*args, **kw):
        kw.pop("converge_jacobian", None)
        return plain_register(*args, **kw)

    monkeypatch.setattr(nav_mod, "register", without_start)
    plain, _ = _navigate(root, p, space="image", threads=1)
    a, b = seeded.passes[1].register, plain.passes[1].register
    assert a.ok.all() and b.ok.all()
    assert np.max(np.abs(a.measured - b.measured)) <= 0.002
    assert a.iterations.sum() <= b.iterations.sum()
    assert np.all(np.isfinite(seeded.passes[0].register.converge_jacobian))


def test_single_pass_autoregister_loses_the_14px_picture_two_pass_keeps_it(worlds):
    """The issue's batch lost a picture with a 14 px a-priori error (AUTOREGISTER starts at spacing 2,
    ±10 cells); two-pass navigation measures every landmark of it."""
    from spctool.stages.register import RegisterOptions, register

    root, doc = worlds["facet"]
    p = doc["pictures"][1]
    assert 13.5 <= p["apriori_px"] <= 14.5
    pic, cam, photo, names, maplets, _ = load_picture(root, p)
    old = register(
        photo, cam, pic.sz, maplets, tuple(pic.thrsh), RegisterOptions(schedule="autoregister"), names=names
    )
    assert old.ok.sum() < 3  # no pose possible: the picture is lost
    res, _ = _navigate(root, p)
    assert res.status == "ok" and res.ok.all()


def test_batch_default_navigates_every_picture(worlds, tmp_path):
    from spctool.batch import BatchOptions, run_batch

    root, doc = worlds["facet"]
    result = run_batch(root, options=BatchOptions(), out_dir=tmp_path / "out")
    assert [s.status for s in result.pictures] == ["ok"] * len(doc["pictures"])
    assert [s.found for s in result.pictures] == [9] * len(doc["pictures"])
    old = run_batch(root, options=BatchOptions(two_pass=None), out_dir=tmp_path / "old")
    assert old.pictures[1].status.startswith("no-pose")  # the single AUTOREGISTER pass loses it


def test_navigate_cli_on_the_independent_world(worlds, run_cli, tmp_path):
    root, doc = worlds["smooth"]
    p = doc["pictures"][2]
    out = tmp_path / "new.SUM"
    res = run_cli("-C", root, "navigate", p["name"], "--json", "--output", out)
    assert res.exit_code == 0, res.stderr
    d = json.loads(res.stdout)
    assert [x["found"] for x in d["passes"]] == [9, 9]
    # both passes end converged at full resolution: the second is no worse than the first beyond noise
    assert d["passes"][1]["rms_after_px"] <= d["passes"][0]["rms_after_px"] + 0.005
    from spctool.formats.sumfile import read_sum

    new = read_sum(out)
    assert len(new.landmarks) == 9
    # the solved pointing: the truth pixels are reproduced to a small fraction of a pixel
    from spctool.geometry.camera import Camera

    cam = Camera.from_picture(new)
    names = sorted(p["pixels"])
    v = np.array([doc["landmarks"][n] for n in names])
    err = np.stack(cam.project(v), axis=-1) - np.array([p["pixels"][n] for n in names])
    assert np.max(np.linalg.norm(err, axis=1)) < 0.1
    # fewer landmarks than required: exit 1, one line
    bad = run_cli("-C", root, "navigate", p["name"], "--single-pass", "--require", "10")
    assert bad.exit_code == 1 and "fewer than --require 10" in bad.stderr
    assert "Traceback" not in bad.stderr


def test_pass_2_without_a_pose_keeps_pass_1(worlds, monkeypatch):
    """A pass-2 pose failure does not lose the picture: pass 1's pose and pixels stand, with a warning."""
    from spctool.stages import navigate as nav_mod

    real = nav_mod._solve
    calls = []

    def second_fails(*a, **k):
        calls.append(1)
        return (None, "simulated failure") if len(calls) == 2 else real(*a, **k)

    monkeypatch.setattr(nav_mod, "_solve", second_fails)
    root, doc = worlds["facet"]
    res, true_px = _navigate(root, doc["pictures"][0])
    assert res.status == "ok" and len(res.passes) == 2
    assert res.final is res.passes[0] and res.pose is res.passes[0].pose
    assert any("simulated failure" in w for w in res.warnings)


def test_batch_cli_default_is_two_pass(worlds, run_cli, tmp_path):
    import json as _json

    root, doc = worlds["smooth"]
    res = run_cli("-C", root, "batch", "--out-dir", tmp_path / "two", "--json")
    assert res.exit_code == 0, res.stderr
    rows = _json.loads(res.stdout)["pictures"]
    assert [r["status"] for r in rows] == ["ok"] * 3 and [r["found"] for r in rows] == [9] * 3
    old = run_cli("-C", root, "batch", "--out-dir", tmp_path / "one", "--schedule", "autoregister", "--json")
    assert old.exit_code == 0  # a no-pose picture is a result, not a failure
    rows = _json.loads(old.stdout)["pictures"]
    assert rows[1]["status"].startswith("no-pose")


# ------------------------------------------------------------------------------------------------
# an a-priori error beyond the acquisition's reach (45 px, the photo 160 px across)


@pytest.fixture(scope="session")
def far_world(tmp_path_factory):
    """One picture whose landmarks start 45 px from their truth pixels (faceted truth)."""
    from spctool.sim.independent import IndependentSpec, build_world

    root = tmp_path_factory.mktemp("independent_far")
    doc = build_world(root, IndependentSpec(truth="facet", apriori_px=(45.0,)))
    return root, doc


def _far_navigate(far_world, space, **nav):
    from spctool.stages.navigate import NavigateOptions, navigate
    from spctool.stages.register import RegisterOptions

    root, doc = far_world
    pic, cam, photo, names, maplets, truth = load_picture(root, doc["pictures"][0])
    assert 44.0 <= doc["pictures"][0]["apriori_px"] <= 46.0
    opts = NavigateOptions(register=RegisterOptions(space=space), **nav)
    res = navigate(
        photo, cam, pic.sz, maplets, tuple(pic.thrsh), opts, names=names,
        prior_sigma_position=pic.sigma_vso, prior_sigma_attitude=pic.sigma_ptg,
    )  # fmt: skip
    return res, truth


@pytest.mark.parametrize("space", ["maplet", "image"])
def test_navigate_beyond_its_reach_says_so(far_world, space):
    """45 px beyond the ±25 px reach: landmarks lock onto other terrain.  The release before this
    check returned ``ok`` with a pose fitted to 7 wrong landmarks (maplet space; pass 2 re-registered 1);
    now the picture is ``no-pose``, or every landmark it keeps is right."""
    res, truth = _far_navigate(far_world, space)
    if res.status == "ok":
        assert np.all(_errors(res.final.register, truth)[res.ok] < 0.1)
    else:
        assert res.status.startswith("no-pose")


@pytest.mark.parametrize("space", ["maplet", "image"])
def test_navigate_with_a_reach_beyond_the_apriori_error(far_world, space):
    """``--reach 50``: every landmark of the 45 px picture, at the issue's accuracy."""
    res, truth = _far_navigate(far_world, space, reach_px=50.0)
    assert res.status == "ok" and res.ok.all()
    err = _errors(res.final.register, truth)
    assert np.sqrt(np.mean(err**2)) <= ISSUE_TWO_PASS_RMS + 0.01 and np.max(err) <= ISSUE_MAX


def test_register_acquire_reach_on_the_independent_world(far_world):
    """S16's search within the 49-cell maplets cannot reach 45 px (52 cells); the first step on the
    extended extraction (``acquire_reach``) measures every landmark."""
    from spctool.stages.register import RegisterOptions, register

    root, doc = far_world
    pic, cam, photo, names, maplets, truth = load_picture(root, doc["pictures"][0])
    args = (photo, cam, pic.sz, maplets, tuple(pic.thrsh))
    s16 = register(*args, RegisterOptions(), names=names)
    err = _errors(s16, truth)
    # S16's reach: landmarks lost, and 'ok' ones locked onto other terrain (27-98 px off, rho 0.4-0.5)
    assert np.sum(s16.ok & (err < 0.1)) < 3
    # and says so: the wrong ones moved unlike the others
    odd = [w for w in s16.warnings if "moved unlike the others" in w]
    assert len(odd) == 1
    assert all(nm in odd[0] for nm, e, ok in zip(names, err, s16.ok) if ok and e > 5.0)
    wide = register(*args, RegisterOptions(acquire_reach=70), names=names)
    assert not any("moved unlike the others" in w for w in wide.warnings)
    err = _errors(wide, truth)
    # every landmark whose a-priori pixel is on the photo (one is off it: 'outside')
    on = np.array([s != "outside" for s in wide.status])
    assert on.sum() >= 8 and wide.ok[on].all() and np.max(err[on]) <= ISSUE_MAX


def test_pass_2_finding_nothing_does_not_confirm_pass_1(worlds, monkeypatch, tmp_path):
    """Pass 2 starts from pass 1's pose with a ±10-cell search: when it re-registers fewer landmarks than
    a pose needs, pass 1's pose is not confirmed — ``no-pose`` (navigate and batch), not ``ok``."""
    from spctool.stages import navigate as nav_mod

    real = nav_mod.register
    calls = []

    def pass_2_finds_nothing(*a, **k):
        calls.append(1)
        r = real(*a, **k)
        if len(calls) == 3:  # coarse, fine, then pass 2
            r.status = ["not-found"] * len(r.status)
            r.measured[:] = np.nan
        return r

    monkeypatch.setattr(nav_mod, "register", pass_2_finds_nothing)
    root, doc = worlds["facet"]
    res, _ = _navigate(root, doc["pictures"][0])
    assert res.status.startswith("no-pose: the pass-1 pose is not confirmed")
    assert "re-registered 0 of the 9" in res.status
    from spctool.batch import BatchOptions, run_batch

    calls.clear()
    out = run_batch(root, [doc["pictures"][0]["name"]], BatchOptions(), out_dir=tmp_path / "out")
    assert out.pictures[0].status.startswith("no-pose: the pass-1 pose is not confirmed")


def test_batch_cli_reach(far_world, run_cli, tmp_path):
    """``batch`` at the default reach: the 45 px picture is no-pose (not a wrong ok); ``--reach 50``
    navigates it; ``--reach`` with a single-pass schedule is refused."""
    import json as _json

    root, doc = far_world
    res = run_cli("-C", root, "batch", "--out-dir", tmp_path / "r25", "--json")
    assert res.exit_code == 0, res.stderr
    (row,) = _json.loads(res.stdout)["pictures"]
    assert row["status"].startswith("no-pose")
    res = run_cli("-C", root, "batch", "--reach", "50", "--out-dir", tmp_path / "r50", "--json")
    assert res.exit_code == 0, res.stderr
    (row,) = _json.loads(res.stdout)["pictures"]
    assert row["status"] == "ok" and row["found"] >= 8
    bad = run_cli("-C", root, "batch", "--schedule", "s16", "--reach", "50", "--out-dir", tmp_path / "x")
    assert bad.exit_code == 2 and "--reach applies to --schedule two-pass" in bad.stderr
