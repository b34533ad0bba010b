"""Tests of spctool.stages.model_error: the shading model's error patterns (issue #39).

Independent check: a scene rendered by spctool's renderer with the Lambert law (the truth), three perfect
maplets, registered with SPC's lunar-Lambert law (the default): the sensitivity — one spacing-1 step
from the measured pixels with the alternative law — must equal the difference between two complete,
separate registrations from the a-priori pixels with the two laws, and the shift to the right law must
take the measurements toward the truth where the law's error shows.  (That the patterns predict the
error on worlds spctool did not render: benchmarks/calibration.py.)
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import register_scene as rs

from spctool.stages.model_error import Sensitivity, alternative_models, shading_sensitivity
from spctool.stages.register import RegisterOptions, register
from spctool.stages.render import RenderOptions, render


@pytest.fixture(scope="module")
def lambert_scene():
    """The S16 scene re-rendered with the Lambert law, three maplets of its terrain (perfect models)."""
    sc = rs.scene(q_truth=150, sun_incidence=55.0)
    rend = render(sc.camera, sc.sun, None, [sc.truth], RenderOptions(supersample=2, photometry="lambert"))
    photo = np.where(rend.coverage > 0, 50.0 + 2000.0 * rend.radiance, 0.0)
    maplets = [
        rs.offset_maplet(sc, x, y, q=24, name=f"L{k}")
        for k, (x, y) in enumerate(((0, 0), (30, -20), (-25, 25)))
    ]
    truth = np.array([sc.camera.project(m.v) for m in maplets], dtype=float)
    return sc, photo, maplets, truth


def _options():
    return RegisterOptions(
        schedule="retina_s16", steps=(("align", 2), ("align", 1)), fail_fast=True, cap_spacing=False
    )


def test_the_alternative_models():
    labels = [lab for lab, _ in alternative_models(RegisterOptions())]
    assert labels == ["photometry lambert", "heights smoothed"]
    img = alternative_models(RegisterOptions(space="image"))
    assert [lab for lab, _ in img] == [
        "photometry lambert",
        "heights smoothed",
        "template-shading facet",
        "no cast shadows",
    ]
    assert (
        not img[3][1].image_shadows
        and img[2][1].image_shadows
        and img[1][1] == RegisterOptions(space="image")
    )
    plain = alternative_models(RegisterOptions(space="image", image_shadows=False))
    assert [lab for lab, _ in plain] == ["photometry lambert", "heights smoothed", "template-shading facet"]
    assert img[2][1].template_shading == "facet" and img[0][1].predict.photometry == "lambert"
    lam = RegisterOptions(predict=dataclasses.replace(RegisterOptions().predict, photometry="lambert"))
    assert alternative_models(lam)[0][1].predict.photometry == "spc"
    # every template shading is compared with another one (gouraud, like smooth, with facet)
    from spctool.stages.render_modes import SHADINGS

    for shading in SHADINGS:
        alt = alternative_models(RegisterOptions(space="image", template_shading=shading))[2][1]
        assert alt.template_shading in SHADINGS and alt.template_shading != shading
    gouraud = alternative_models(RegisterOptions(space="image", template_shading="gouraud"))
    assert gouraud[2][0] == "template-shading facet"


def test_smoothed_heights_by_hand():
    """One height of 16 at the centre of a 5×5 maplet: the binomial [1, 2, 1]/4 twice gives 4 at the
    centre, 2 beside it, 1 at the corners; an invalid node stays 0 and is not averaged in; the original
    maplet is left as it was."""
    from types import SimpleNamespace

    from spctool.stages.model_error import smoothed_heights

    h = np.zeros((5, 5))
    h[2, 2] = 16.0
    valid = np.ones((5, 5), bool)
    m = SimpleNamespace(heights=h.copy(), valid=valid, albedo=np.ones((5, 5)))
    s = smoothed_heights(m).heights
    np.testing.assert_allclose(s[1:4, 1:4], [[1, 2, 1], [2, 4, 2], [1, 2, 1]])
    assert s.sum() == pytest.approx(16.0) and np.array_equal(m.heights, h)
    valid[0, 0] = False
    m2 = SimpleNamespace(heights=np.where(valid, 3.0, 0.0), valid=valid, albedo=np.ones((5, 5)))
    s2 = smoothed_heights(m2).heights
    assert s2[0, 0] == 0.0 and np.allclose(s2[valid], 3.0)  # a constant stays constant, holes ignored


def test_the_sensitivity_is_the_difference_of_the_two_models(lambert_scene):
    """δ = (registration with Lambert) − (registration with SPC's law), each a complete registration from
    the a-priori pixels; the shift moves the landmark whose SPC-law error is largest toward its truth."""
    sc, photo, maplets, truth = lambert_scene
    opts = _options()
    reg = register(photo, sc.camera, sc.sun, maplets, sc.thresholds, opts, apriori=truth + 0.3)
    lam = dataclasses.replace(opts, predict=dataclasses.replace(opts.predict, photometry="lambert"))
    other = register(photo, sc.camera, sc.sun, maplets, sc.thresholds, lam, apriori=truth + 0.3)
    assert reg.ok.all() and other.ok.all()
    sens = shading_sensitivity(photo, sc.camera, sc.sun, maplets, sc.thresholds, opts, reg.measured, reg.ok)
    assert sens.labels == ["photometry lambert", "heights smoothed"] and not sens.warnings
    assert sens.available.all()
    d = sens.shifts[:, :, 0]
    np.testing.assert_allclose(d, other.measured - reg.measured, atol=0.002)
    err_spc = np.linalg.norm(reg.measured - truth, axis=1)
    err_lam = np.linalg.norm(other.measured - truth, axis=1)
    k = int(np.argmax(np.linalg.norm(d, axis=1)))
    assert np.linalg.norm(d[k]) > 0.005 and err_lam[k] < err_spc[k]
    # each landmark's marginal covariance holds its share of the pattern
    cov = np.broadcast_to(1e-6 * np.eye(2), (3, 2, 2))
    u = sens.shifts
    np.testing.assert_allclose(sens.landmark_covariances(cov), cov + np.einsum("nik,njk->nij", u, u))
    np.testing.assert_allclose(sens.common()[:, 0], d.mean(axis=0))
    assert sens.as_dict()["landmarks"] == [3, 3]


def test_a_landmark_the_alternative_does_not_find_gets_no_shift(lambert_scene):
    sc, photo, maplets, truth = lambert_scene
    meas = truth.copy()
    meas[1] = np.nan  # not measured: not registered again
    sens = shading_sensitivity(
        photo,
        sc.camera,
        sc.sun,
        maplets,
        sc.thresholds,
        _options(),
        meas,
        np.array([True, False, True]),
        max_shift_px=1e-9,  # every real shift is "too far": nothing is kept, each named
    )
    assert not sens.available.any() and np.all(sens.shifts == 0.0)
    assert len(sens.warnings) == 2 and "L0" in sens.warnings[0] and "L1" not in sens.warnings[0]
    empty = shading_sensitivity(
        photo, sc.camera, sc.sun, maplets, sc.thresholds, _options(), meas, np.zeros(3, bool)
    )
    assert isinstance(empty, Sensitivity) and empty.shifts.shape == (3, 2, 2) and not empty.warnings
    one = shading_sensitivity(
        photo, sc.camera, sc.sun, maplets, sc.thresholds, _options(), truth, np.ones(3, bool),
        only=("heights smoothed",),
    )  # fmt: skip
    assert one.labels == ["heights smoothed"] and one.shifts.shape == (3, 2, 1) and one.available.all()
