"""Two-pass navigation (spctool.stages.navigate): the acquisition schedule by hand and as a property,
option validation, and the passes on spctool's own S16-like scene (the independent world is in
test_independent_world.py)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool.errors import SpcUsageError
from spctool.stages.navigate import NavigateOptions, acquisition_steps


def test_acquisition_steps_by_hand():
    opts = NavigateOptions()
    # 49 cells: S16's L = 10 would leave 4 bins; L0 = 49 // 12 = 4, k0 = ceil(25 / 4) + 1 = 8
    assert acquisition_steps(49, 1.0, opts) == [(4, 8), (2, 5), (1, 5)]
    # 99 cells (S16's maplets), 1.43 cells per px at 50 m: reach 35.75 cells, L0 = 8, k0 = 6
    assert acquisition_steps(99, 1.43, opts) == [(8, 6), (4, 5), (2, 5), (1, 5)]
    # large maplets: S16's L = 10 with its +-5 bins reaches 50 cells >= 25 px at 1 cell/px
    assert acquisition_steps(301, 1.0, opts) == [(10, 5), (5, 5), (2, 5), (1, 5)]
    # tiny maplets: spacing 1 with a wide grid
    assert acquisition_steps(11, 1.0, opts) == [(1, 26)]


@settings(max_examples=200, deadline=None)
@given(
    size=st.integers(5, 401),
    per_px=st.floats(0.2, 5.0),
    reach=st.floats(1.0, 60.0),
)
def test_acquisition_reaches_and_keeps_bins(size, per_px, reach):
    opts = NavigateOptions(reach_px=reach)
    steps = acquisition_steps(size, per_px, opts)
    l0, k0 = steps[0]
    # the first step reaches the requested pixels plus a bin (a peak at the reach is not on the border)
    assert k0 * l0 >= reach * per_px + l0 - 1e-9
    assert l0 == 1 or size // l0 >= opts.min_bins
    assert l0 <= opts.max_spacing
    # each finer step reaches at least the previous spacing (the previous step's quantisation)
    for (a, _), (b, k) in zip(steps, steps[1:]):
        assert b < a and k * b >= a / 2
    assert steps[-1][0] == 1


@pytest.mark.parametrize(
    "kw",
    [
        {"passes": 3},
        {"reach_px": 0},
        {"reach_px": math.inf},
        {"refine_spacings": ()},
        {"refine_spacings": (2, 0)},
        {"min_landmarks": 0},
        {"min_bins": 2},
    ],
)
def test_bad_options_are_refused(kw):
    with pytest.raises(SpcUsageError):
        NavigateOptions(**kw)


def test_two_passes_on_the_s16_scene():
    """spctool's own rendered S16 scene (99x99 maplet, 50 m): a 12 px pointing error is acquired, and
    pass 2 (from the solved pose) lands within 0.1 px of the truth pixel."""
    import numpy as np
    import register_scene as rs

    from spctool.stages.navigate import navigate
    from spctool.stages.pose import PoseOptions

    sc = rs.scene()
    cam = rs.pointing_error(sc.camera, 9.0, -8.0)
    res = navigate(
        sc.photo,
        cam,
        sc.sun,
        [sc.maplet],
        sc.thresholds,
        NavigateOptions(min_landmarks=1, pose=PoseOptions(min_landmarks=1)),
        prior_sigma_position=np.full(3, 1e-6),
        prior_sigma_attitude=np.full(3, 1e-2),
    )
    assert res.status == "ok", res.status
    assert [p.found for p in res.passes] == [1, 1]
    err1 = np.linalg.norm(res.passes[0].register.measured[0] - sc.truth_pixel)
    err2 = np.linalg.norm(res.passes[1].register.measured[0] - sc.truth_pixel)
    assert err2 < 0.1, (err1, err2)


def test_an_implausible_pose_is_no_pose(monkeypatch):
    """A pose whose residuals are far above the measurement sigma (cost/dof > max_reduced_chi2) is not a
    navigation result: landmarks locked onto other terrain fit one (an independent world at 60 px
    a-priori error: cost/dof 1.4e4, benchmarks/bench_accuracy.py "beyond the reach")."""
    import types

    import numpy as np

    from spctool.stages import navigate as nav_mod
    from spctool.stages.register import RegisterResult

    bad = types.SimpleNamespace(converged=True, plausible=False, implausible="cost/dof 1.4e+04 > 100")
    good = types.SimpleNamespace(converged=True, plausible=True, implausible="")
    z = np.zeros((4, 2))
    reg = RegisterResult(list("ABCD"), z, z.copy(), np.zeros(4), np.zeros(4, int), np.zeros(4, int),
                         ["ok"] * 4, None)  # fmt: skip
    opts = NavigateOptions()
    for pose, err in ((bad, "implausible fit: cost/dof 1.4e+04 > 100"), (good, None)):
        monkeypatch.setattr(nav_mod, "solve_pose", lambda *a, _p=pose, **k: _p)
        got, why = nav_mod._solve(None, np.zeros((4, 3)), reg, opts, None, None)
        assert got is pose and why == err


def test_surface_weights_pass_the_registration_covariances(monkeypatch):
    """The final pass with weights="surface" hands each registered landmark's covariance
    and its shading-model error shifts to the pose solve (the rows used, in order); without the
    sensitivity (pass 1 of two, weights="uniform") none; "calibrated" (the default) fits uniformly with
    the covariances (no patterns) as the measurement covariance; anything else is refused."""
    import types

    import numpy as np

    from spctool.stages import navigate as nav_mod
    from spctool.stages.model_error import Sensitivity
    from spctool.stages.register import RegisterResult

    z = np.zeros((4, 2))
    cov = np.arange(16, dtype=float).reshape(4, 2, 2)
    reg = RegisterResult(list("ABCD"), z, z.copy(), np.zeros(4), np.zeros(4, int), np.zeros(4, int),
                         ["ok", "not-found", "ok", "ok"], None, covariance=cov)  # fmt: skip
    shifts = np.arange(8, dtype=float).reshape(4, 2, 1)
    sens = Sensitivity(["photometry lambert"], shifts, np.ones((4, 1), bool))
    seen = {}

    def fake(*a, **k):
        seen["cov"] = k.get("pixel_covariances")
        seen["modes"] = k.get("error_modes")
        seen["estimate"] = k.get("estimate_weights")
        return types.SimpleNamespace(converged=True, plausible=True, implausible="")

    monkeypatch.setattr(nav_mod, "solve_pose", fake)
    nav_mod._solve(None, np.zeros((4, 3)), reg, NavigateOptions(weights="surface"), None, None, sens)
    np.testing.assert_array_equal(seen["cov"], cov[[0, 2, 3]])
    np.testing.assert_array_equal(seen["modes"], shifts[[0, 2, 3]])
    assert seen["estimate"] == "covariance"
    nav_mod._solve(None, np.zeros((4, 3)), reg, NavigateOptions(), None, None)
    assert seen["estimate"] == "uniform" and NavigateOptions().weights == "calibrated"
    np.testing.assert_array_equal(seen["cov"], cov[[0, 2, 3]])
    assert seen["modes"] is None
    nav_mod._solve(None, np.zeros((4, 3)), reg, NavigateOptions(), None, None, final=False)  # pass 1 of 2
    assert seen["cov"] is None and seen["estimate"] == "covariance"
    nav_mod._solve(None, np.zeros((4, 3)), reg, NavigateOptions(weights="uniform"), None, None)
    assert seen["cov"] is None and seen["modes"] is None
    with pytest.raises(SpcUsageError):
        NavigateOptions(weights="inverse")
