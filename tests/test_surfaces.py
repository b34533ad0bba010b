"""A height patch's render-ready set-up (:mod:`spctool.geometry.surfaces`) against its references.

:class:`HeightPatch` sanitises its grids in one pass (``_patchgrids.patch_maps``) and derives the
slopes, cell tops and both near-step reaches in one call (``patch_grids``); :class:`PatchSet` computes
the Sun's upwind maxima and horizon bounds in one sweep (``sun_bounds``).  Each is held to the last bit
to the separate reference computations it replaces (``np.where``/``np.isfinite`` sanitation,
:func:`heightfield.slopes`, ``cell_tops``, ``near_steps``, ``_upwind_max``, ``horizon_bound``) on random
grids with missing nodes, non-finite heights, odd sizes and reaches, and Sun directions along the axes,
the diagonals, at the zenith and below the horizon: the Monte Carlo's results are chaotic at the 0.01 px
level, so only bit-equal grids keep them.
"""

import math

import numpy as np
import pytest

from spctool.errors import SpcUsageError
from spctool.geometry import _heightkernels as hk
from spctool.geometry import _patchgrids as pg
from spctool.geometry import heightfield
from spctool.geometry.surfaces import LIT_CELLS, NEAR_CELLS, HeightPatch, PatchSet


def _same(a, b):
    """Bit-equal arrays (dtype, shape and every byte: −0 ≠ +0, nan = nan)."""
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _grid(rng, n0, n1, missing):
    """Heights with spikes, ties (a few nodes rounded to one decimal) and signed zeros, and a valid mask
    with ``missing`` of the nodes left out."""
    h = rng.normal(size=(n0, n1)) * rng.uniform(0.1, 3.0) + 8.0 * (rng.uniform(size=(n0, n1)) > 0.97)
    pick = rng.uniform(size=(n0, n1))
    h = np.where(pick < 0.1, np.round(h, 1), h)
    h = np.where(pick > 0.95, np.where(pick > 0.975, -0.0, 0.0), h)
    valid = rng.uniform(size=(n0, n1)) >= missing
    return np.where(valid, h, 0.0), valid


def _directions():
    """Unit Sun directions in the maplet frame: random, along ±axes, on the diagonals, at the zenith,
    grazing and below the horizon."""
    out = []
    for az_deg, el_deg in [(0, 30), (90, 20), (180, 5), (270, 60), (45, 10), (135, 40), (225, 1), (315, 80),
                           (20, -5), (200, 0), (33, 89.9), (0, 90)]:  # fmt: skip
        az, el = math.radians(az_deg), math.radians(el_deg)
        out.append((math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)))
    out += [(1.0, 0.0, 0.5), (0.0, -1.0, 0.5), (-1.0, 0.0, 0.2), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0),
            (0.0, 0.0, -1.0), (0.6, 0.6, 0.3), (-0.6, 0.6, 0.3), (-0.0, 0.0, 0.7)]  # fmt: skip
    return out


@pytest.mark.parametrize("seed", range(12))
def test_patch_grids_equal_the_reference_kernels(seed):
    rng = np.random.default_rng(seed)
    n0, n1 = (int(v) for v in rng.integers(3, 26, size=2))
    h, valid = _grid(rng, n0, n1, [0.0, 0.02, 0.3][seed % 3])
    albedo = rng.uniform(0.5, 1.5, size=h.shape)
    maps = np.empty((4, n0, n1))
    ok = np.empty((n0, n1), bool)
    zlo, zhi = pg.patch_maps(h, valid, albedo, maps, ok)
    assert _same(ok, valid) and _same(maps[0], h) and _same(maps[3], np.where(valid, albedo, 0.0))
    if valid.any():
        assert (zlo, zhi) == (h[valid].min(), h[valid].max())
    big = max(abs(zlo), abs(zhi)) if valid.any() else 0.0
    hx, hy, usable = np.empty(h.shape), np.empty(h.shape), np.empty(h.shape, bool)
    hk.slopes(h, valid, hx, hy, usable)
    tops = hk.cell_tops(h, valid)
    for ra, rb in [(4, 2), (2, 4), (3, 1), (0, 0), (5, 5), (7, 2), (0, 3), (1, 1)]:
        got_usable = np.empty(h.shape, bool)
        got_tops = np.empty((n0 - 1, n1 - 1))
        near = np.empty((n0 - 1, n1 - 1, 4))
        pg.patch_grids(maps, valid, big, ra, rb, got_usable, got_tops, near)
        assert _same(maps[1], hx) and _same(maps[2], hy) and _same(got_usable, usable)
        assert _same(got_tops, tops)
        for c, reach in ((0, ra), (2, rb)):
            want = np.empty((n0 - 1, n1 - 1, 2))
            hk.near_steps(h, valid, reach, want)
            assert _same(near[..., c : c + 2], want), (ra, rb, c)


def test_patch_maps_drops_non_finite_heights():
    h = np.arange(25.0).reshape(5, 5)
    h[1, 2], h[3, 3], h[4, 0] = np.nan, np.inf, -np.inf
    valid = np.ones((5, 5), bool)
    valid[0, 0] = False
    maps, ok = np.empty((4, 5, 5)), np.empty((5, 5), bool)
    zlo, zhi = pg.patch_maps(h, valid, np.full((5, 5), 2.0), maps, ok)
    want = valid & np.isfinite(h)
    assert _same(ok, want) and _same(maps[0], np.where(want, h, 0.0))
    assert _same(maps[3], np.where(want, 2.0, 0.0)) and (zlo, zhi) == (1.0, 24.0)
    assert pg.patch_maps(h, np.zeros((5, 5), bool), h, maps, ok) == (np.inf, -np.inf)


@pytest.mark.parametrize("seed", range(6))
def test_sun_bounds_equal_upwind_max_and_horizon_bound(seed):
    rng = np.random.default_rng(100 + seed)
    n0, n1 = (int(v) for v in rng.integers(3, 30, size=2))
    h, valid = _grid(rng, n0, n1, [0.0, 0.05, 0.3][seed % 3])
    tops = hk.cell_tops(h, valid)
    m0, m1 = tops.shape
    for au, aw, az in _directions():
        want_up, want_hor, want_ent = (np.empty((m0, m1)) for _ in range(3))
        hk._upwind_max(tops, au, aw, want_up)
        hk.horizon_bound(tops, au, aw, az, want_hor, want_ent)
        # into plane 1 of padded stacks: the rest untouched
        up, hor, ent = (np.full((3, m0 + 2, m1 + 1), 7.0) for _ in range(3))
        pg.sun_bounds(tops, au, aw, az, 1, up, hor, ent)
        for got, want in ((up, want_up), (hor, want_hor), (ent, want_ent)):
            assert _same(got[1, :m0, :m1], want), (au, aw, az)
            assert np.all(got[0] == 7.0) and np.all(got[2] == 7.0)
            assert np.all(got[1, m0:] == 7.0) and np.all(got[1, :, m1:] == 7.0)


def _reference_patch(patch_like):
    """What HeightPatch computed before its fused set-up: the sanitation and each grid on its own."""
    h = np.asarray(patch_like["heights"], dtype=np.float64)
    valid = np.asarray(patch_like["valid"], dtype=bool) & np.isfinite(h)
    heights = np.where(valid, h, 0.0)
    albedo = np.where(valid, np.asarray(patch_like["albedo"], dtype=np.float64), 0.0)
    hx, hy, usable = heightfield.slopes(heights, valid)
    n = h.shape[0]
    near = np.empty((n - 1, n - 1, 4))
    part = np.empty((n - 1, n - 1, 2))
    for c, reach in ((0, NEAR_CELLS), (2, LIT_CELLS)):
        hk.near_steps(heights, valid, reach, part)
        near[..., c : c + 2] = part
    return dict(
        heights=heights,
        valid=valid,
        albedo=albedo,
        hx=hx,
        hy=hy,
        usable=usable,
        tops=hk.cell_tops(heights, valid),
        near=near,
        maps=np.stack([heights, hx, hy, albedo]),
        range=(float(heights[valid].min()), float(heights[valid].max())),
    )


def _patch_kwargs(rng, q, missing):
    n = 2 * q + 1
    h, valid = _grid(rng, n, n, missing)
    h[rng.uniform(size=h.shape) < 0.02] = np.nan
    uz = np.array([0.2, -0.3, 1.0]) / math.sqrt(1.13)
    ux = np.cross([0.0, 1.0, 0.0], uz)
    ux /= np.linalg.norm(ux)
    uy = np.cross(uz, ux)
    return dict(
        heights=h,
        valid=valid,
        albedo=rng.uniform(0.5, 1.5, size=h.shape),
        scale=0.002,
        v=np.array([0.3, 0.1, 1.2]),
        ux=ux,
        uy=uy,
        uz=uz,
    )


@pytest.mark.parametrize(
    "seed, q, missing", [(0, 1, 0.0), (1, 5, 0.0), (2, 12, 0.05), (3, 20, 0.3), (4, 49, 0.0)]
)
def test_height_patch_grids_equal_the_separate_computations(seed, q, missing):
    kw = _patch_kwargs(np.random.default_rng(seed), q, missing)
    ref = _reference_patch(kw)
    p = HeightPatch(**kw)
    assert (
        _same(p.heights, ref["heights"]) and _same(p.valid, ref["valid"]) and _same(p.albedo, ref["albedo"])
    )
    assert p.height_range == ref["range"]
    hx, hy, usable = p.slopes
    assert _same(hx, ref["hx"]) and _same(hy, ref["hy"]) and _same(usable, ref["usable"])
    assert isinstance(p.slopes, heightfield.Slopes)
    assert _same(p.cell_tops, ref["tops"]) and _same(p.near_steps, ref["near"])
    maps, valid = p.stacked_maps
    assert _same(maps, ref["maps"]) and _same(valid, ref["valid"])
    # the properties keep returning the same arrays
    assert p.cell_tops is p.cell_tops and p.near_steps is p.near_steps and p.stacked_maps[0] is maps
    # in any order of first use
    p2 = HeightPatch(**kw)
    assert _same(p2.near_steps, ref["near"]) and _same(p2.stacked_maps[0], ref["maps"])


def test_height_patch_range_keeps_numpy_signed_zeros():
    h = np.zeros((5, 5))
    h[1, 1] = -0.0
    h[2, 2] = -1.0
    p = HeightPatch(
        h, 0.001, np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0])
    )
    assert _same(np.array(p.height_range), np.array((float(h.min()), float(h.max()))))
    with pytest.raises(SpcUsageError, match="no valid node"):
        HeightPatch(np.full((3, 3), np.nan), 0.001, np.zeros(3), [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0])


def test_patch_set_bounds_equal_the_reference_kernels():
    rng = np.random.default_rng(7)
    patches = [HeightPatch(**_patch_kwargs(rng, q, 0.05)) for q in (6, 9, 6)]
    for sun in _directions()[:8] + [(0.3, -0.4, 0.866)]:
        sun = np.asarray(sun) / np.linalg.norm(sun)
        for group in (patches[1:2], patches):
            pset = PatchSet(group)
            _, _, maps, _, tops, _, up, hor, ent, near, _ = pset.fused_arrays(sun)
            nmax = max(p.heights.shape[0] for p in group)
            for k, p in enumerate(group):
                m = p.heights.shape[0] - 1
                su, sw, sz = sun @ p.rotation
                want_up, want_hor, want_ent = (np.empty((m, m)) for _ in range(3))
                hk._upwind_max(p.cell_tops, float(su), float(sw), want_up)
                hk.horizon_bound(p.cell_tops, float(su), float(sw), float(sz), want_hor, want_ent)
                for got, want in ((up, want_up), (hor, want_hor), (ent, want_ent)):
                    assert _same(got[k, :m, :m], want)
                    assert np.all(got[k, m:] == np.inf) and np.all(got[k, :, m:] == np.inf)
                assert _same(maps[k, :, : m + 1, : m + 1], p.stacked_maps[0])
                assert _same(tops[k, :m, :m], p.cell_tops) and _same(near[k, :m, :m], p.near_steps)
            assert up.shape == (len(group), nmax - 1, nmax - 1)
    # no Sun: no bound
    up, hor, ent = PatchSet(patches).fused_arrays(None)[6:9]
    assert np.all(up == np.inf) and np.all(hor == np.inf) and np.all(ent == np.inf)
    assert not PatchSet(patches).fused_arrays(None)[10].any()


@pytest.mark.parametrize("seed, q, missing", [(5, 6, 0.0), (6, 20, 0.1)])
def test_height_patch_fourth_order_node_slopes(seed, q, missing):
    """``node_slopes="fourth"``: the slope planes are :func:`heightfield.fourth_order_slopes` of the
    patch's heights over SPC's; the geometry's grids are the SPC patch's, to the bit."""
    kw = _patch_kwargs(np.random.default_rng(seed), q, missing)
    spc, four = HeightPatch(**kw), HeightPatch(**kw, node_slopes="fourth")
    hx, hy = heightfield.fourth_order_slopes(spc.heights, spc.valid, spc.slopes.hx, spc.slopes.hy)
    assert (
        _same(four.slopes.hx, hx)
        and _same(four.slopes.hy, hy)
        and _same(four.slopes.usable, spc.slopes.usable)
    )
    assert not _same(four.slopes.hx, spc.slopes.hx)
    assert _same(four.cell_tops, spc.cell_tops) and _same(four.near_steps, spc.near_steps)
    maps, _ = four.stacked_maps
    assert _same(maps[1], hx) and _same(maps[2], hy) and _same(maps[0], spc.stacked_maps[0][0])
    with pytest.raises(SpcUsageError, match="node_slopes"):
        HeightPatch(**kw, node_slopes="central")


def test_node_slope_names_agree_with_the_options_check():
    from spctool.stages.register_options import RegisterOptions
    from spctool.stages.render_modes import NODE_SLOPES

    assert NODE_SLOPES == heightfield.NODE_SLOPES
    assert RegisterOptions().template_slopes == "spc"
    with pytest.raises(SpcUsageError, match="template_slopes"):
        RegisterOptions(template_slopes="central")
