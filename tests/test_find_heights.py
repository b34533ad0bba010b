"""The "Find heights" outer loop (spctool.stages.find_heights) on a rendered scene with known truth
(tests/heights_world.py): from a coarse starting maplet the heights come ≥ 3× closer to the truth
and the albedo correlates ≥ 0.9 with it; too few Sun azimuths leave the maplet unchanged, with a
reason."""

from __future__ import annotations

import numpy as np
import pytest
from heights_world import make_scene, rms

from spctool.formats.maplet import format_map, parse_map
from spctool.stages.find_heights import FindHeightsOptions, find_heights, maplet_with


@pytest.fixture(scope="module")
def scene():
    return make_scene(n_pictures=4)


def _centred(h, valid):
    return h - h[valid].mean()


def test_heights_and_albedo_approach_the_truth(scene):
    start, truth, views = scene
    res = find_heights(start, views, FindHeightsOptions())
    assert res.ok and res.reason == ""
    v = truth.valid
    before = rms(_centred(start.heights, v), _centred(truth.heights, v), v)
    after = rms(_centred(res.heights, v), _centred(truth.heights, v), v)
    corr = float(np.corrcoef(res.albedo[v], truth.albedo[v])[0, 1])
    # measured: 0.376 -> 0.066 cells (5.7x), albedo correlation 0.996, converged in 3 iterations
    assert after * 3.0 <= before, (before, after)
    assert corr >= 0.9
    assert res.converged and res.history[-1]["change_rms"] < 0.01
    assert [p.used for p in res.pictures] == [True] * 4
    for p in res.pictures:
        assert p.ncc_after > p.ncc_before and p.ncc_after > 0.95
        assert p.rms_after < p.rms_before
    assert res.flagged.sum() < 0.05 * v.sum()
    # the input maplet is not modified
    assert np.array_equal(start.heights, scene[0].heights)
    # the MAP writer keeps the solved heights to int16 precision
    m = parse_map(format_map(maplet_with(start, res)))
    assert np.max(np.abs(m.heights - res.heights)) <= m.hscale
    assert np.max(np.abs(m.albedo - res.albedo)) <= 0.006


def test_too_few_sun_azimuths_leave_the_maplet_unchanged(scene):
    start, _, views = scene
    res = find_heights(start, views[:2], FindHeightsOptions())
    assert res.status == "unsolvable"
    assert "2 distinct Sun azimuth" in res.reason and "\n" not in res.reason
    assert np.array_equal(res.heights, start.heights) and np.array_equal(res.albedo, start.albedo)
    assert res.flagged.sum() == start.valid.sum()


def test_no_pictures():
    start, _, _ = make_scene(n_pictures=0)
    res = find_heights(start, [], FindHeightsOptions())
    assert res.status == "unsolvable" and "no pictures" in res.reason


def test_recentre_moves_v_by_the_mean_height(scene):
    start, _, views = scene
    res = find_heights(start, views, FindHeightsOptions(recentre=True, iterations=2))
    v = res.valid
    assert abs(float(res.heights[v].mean())) < 1e-9
    plain = find_heights(start, views, FindHeightsOptions(iterations=2))
    mean_h = float(plain.heights[v].mean())
    moved = np.asarray(start.v) + mean_h * start.scale * np.asarray(start.uz)
    np.testing.assert_allclose(res.v, moved, atol=1e-12)
    np.testing.assert_allclose(res.heights[v], plain.heights[v] - mean_h, atol=1e-9)


def test_worse_when_the_mean_ncc_falls(scene):
    from dataclasses import replace

    start, _, views = scene
    res = find_heights(start, views, FindHeightsOptions(iterations=1))
    assert not res.worse
    b, a = res.mean_ncc()
    assert a > b
    res.pictures = [replace(p, ncc_after=p.ncc_before - 0.01) for p in res.pictures]
    assert res.worse and res.summary()["worse"]
