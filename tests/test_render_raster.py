"""Raster visibility (issue 17: "render forward") against the grid march it replaces.

:func:`spctool.geometry._rasterkernels.terrain_cells` draws a patch's cells (two triangles each, with the
walls the march meets below the border and around missing nodes) into a depth buffer on the sub-ray
lattice, with the camera's *forward* model; the fused kernel then solves each sub-ray's crossing in the
cell drawn there, and marches only where the raster cannot vouch for it.  Checked here:

* the raster against brute force: every lattice point's nearest covering triangle, found by testing
  every triangle, is the cell the raster reports wherever it reports one; uncovered points beside
  covered ones and overlapping surfaces are handed to the march (−2);
* whole renders (the worlds of ``test_render_fast``: grazing and steep views, an OWEN distortion, low
  and high Sun, missing nodes, the patch partly outside the window, supersample 1–4, smooth and facet
  shading, shadows on and off) equal the march's to the last bit — coverage, shadow, surface and
  radiance;
* a template seen from the side shows the walls below the border (the march's hits there) and the
  raster hands those sub-rays to the march;
* registration: image-space measurements with raster templates equal the march's (issue 17: "must not
  move any measured pixel by more than 0.002 px" — they do not move at all).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import register_scene as rs
from test_render_fast import WORLDS, _world, assert_same_rendering

from spctool.errors import SpcUsageError
from spctool.geometry._rasterkernels import terrain_cells
from spctool.geometry.surfaces import PatchSet
from spctool.stages import render as rmod
from spctool.stages.register import RegisterOptions, register
from spctool.stages.render import RenderOptions, render


def _in_triangle(gx, gy, pts, eps):
    (x0, y0), (x1, y1), (x2, y2) = pts
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    b0 = ((x1 - gx) * (y2 - gy) - (x2 - gx) * (y1 - gy)) / area
    b1 = ((x2 - gx) * (y0 - gy) - (x0 - gx) * (y2 - gy)) / area
    return b0, b1, 1.0 - b0 - b1


def _brute_cells(xs, ys, depth, usable, nx, ny, eps=1e-9):
    """(best cell or −1, number of triangles strictly containing the point, points in the corners' hull
    of a cell whose projected quad is not convex) for every lattice point, by testing every triangle of
    every full cell (NumPy, no raster)."""
    n0, n1 = xs.shape
    gx, gy = np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float))
    best = np.full((ny, nx), -1)
    zbest = np.full((ny, nx), np.inf)
    inner = np.zeros((ny, nx), int)
    hull = np.zeros((ny, nx), bool)
    for i in range(n0 - 1):
        for j in range(n1 - 1):
            if not (usable[i, j] and usable[i + 1, j] and usable[i, j + 1] and usable[i + 1, j + 1]):
                continue
            for tri in (((i, j), (i + 1, j), (i + 1, j + 1)), ((i, j), (i, j + 1), (i + 1, j + 1))):
                b0, b1, b2 = _in_triangle(gx, gy, [(xs[a], ys[a]) for a in tri], eps)
                inside = (b0 >= -eps) & (b1 >= -eps) & (b2 >= -eps)
                inner += (b0 > eps) & (b1 > eps) & (b2 > eps)
                d = b0 * depth[tri[0]] + b1 * depth[tri[1]] + b2 * depth[tri[2]]
                take = inside & (d < zbest)
                zbest[take] = d[take]
                best[take] = i * (n1 - 1) + j
            quad = [(xs[a], ys[a]) for a in ((i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1))]
            turns = []
            for k in range(4):
                (ax, ay), (bx, by), (cx, cy) = quad[k], quad[(k + 1) % 4], quad[(k + 2) % 4]
                turns.append((bx - ax) * (cy - by) - (by - ay) * (cx - bx))
            if not (all(t > 0 for t in turns) or all(t < 0 for t in turns)):
                for tri in ((quad[0], quad[1], quad[3]), (quad[1], quad[2], quad[3])):
                    b0, b1, b2 = _in_triangle(gx, gy, tri, eps)
                    hull |= (b0 >= -eps) & (b1 >= -eps) & (b2 >= -eps)
    return best, inner, hull


def _near(mask):
    """Points within one lattice step (8-neighbourhood, itself included) of a True point."""
    pad = np.pad(mask, 1)
    out = np.zeros_like(mask)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            out |= pad[dy : dy + mask.shape[0], dx : dx + mask.shape[1]]
    return out


@pytest.mark.parametrize("seed", range(6))
def test_terrain_cells_against_brute_force(seed):
    rng = np.random.default_rng(seed)
    n = 9
    # a sheared, rotated, slightly perspective image of the grid with jittered nodes; for odd seeds the
    # rows i > 5 fold back over rows 2–4, nearer the camera: overlapping surfaces
    i, j = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    depth = 100.0 + i + 0.5 * j + rng.normal(0, 0.2, (n, n))
    if seed % 2:
        i = np.where(i > 5, 10.0 - i + 0.3, i)
        depth = np.where(i != np.floor(i), depth - 30.0, depth)
    if seed % 3 == 2:  # a few twisted cells (bow-tie quads): a corner pulled across its cell
        i[3, 3] += 1.6
        j[6, 2] -= 1.7
    th = rng.uniform(0, 2 * np.pi)
    sx = 2.0 * (np.cos(th) * i - np.sin(th) * j) + 0.4 * i * j / n + rng.normal(0, 0.25, (n, n)) + 18
    sy = 1.6 * (np.sin(th) * i + np.cos(th) * j) + rng.normal(0, 0.25, (n, n)) + 18
    usable = rng.uniform(size=(n, n)) > 0.08
    nx = ny = 36
    # walls of no height (every node its own foot): nothing drawn below the edges
    foot = np.arange(n * n).reshape(n, n)
    feet = np.column_stack([sx.ravel(), sy.ravel(), depth.ravel()])
    out = np.empty((ny, nx), np.int64)
    terrain_cells(sx, sy, depth, usable, foot, feet, out)
    best, inner, hull = _brute_cells(sx, sy, depth, usable, nx, ny)
    vouched = out >= 0
    assert vouched.sum() > (30 if seed % 2 else 60)
    np.testing.assert_array_equal(out[vouched], best[vouched])  # the nearest triangle's cell
    # a point the raster leaves as sky has no triangle on or next to it, and no twisted cell's hull
    sky = out == -1
    assert not np.any(sky & (_near(best >= 0) | hull))
    # overlaps (strictly inside two triangles), twisted cells' hulls, and their neighbours go to the march
    contested = _near((inner >= 2) | hull)
    assert np.all(out[contested] == -2)
    if seed % 2:
        assert contested.sum() > 10
    if seed % 3 == 2:
        assert hull.sum() > 3
    # nothing else is handed over: −2 only there, or uncovered beside a covered point
    assert np.all((out == -2) <= (contested | (_near(best >= 0) & (best < 0))))


CASES = WORLDS + [
    (7, 80.0, 20.0, 14, True, 2, "smooth", True),
    (8, 75.0, 30.0, 14, False, 4, "smooth", True),
    (9, 25.0, 45.0, 14, True, 2, "facet", False),
]


@pytest.mark.parametrize("seed, emission, sun_elev, q, holes, ss, shading, shadows", CASES)
def test_raster_render_equals_the_march(seed, emission, sun_elev, q, holes, ss, shading, shadows):
    patches, sun, cam = _world(seed, emission, sun_elev, q, holes)
    opts = RenderOptions(supersample=ss, shading=shading, shadows=shadows, ray_inverse="grid", threads=1)
    ref = render(cam, sun, None, patches[:1], opts)
    got = render(cam, sun, None, patches[:1], dataclasses.replace(opts, visibility="raster"))
    assert 0.1 < np.mean(ref.coverage > 0) < 0.95  # the patch fills part of the window
    assert_same_rendering(got, ref)
    # two patches: the raster applies to one-patch windows only, the march renders the rest
    both = render(cam, sun, None, patches, dataclasses.replace(opts, visibility="raster"))
    np.testing.assert_array_equal(both.radiance, render(cam, sun, None, patches, opts).radiance)


def _subrays(cam, p, ss):
    s0, s1, l0, l1 = rmod._window(cam, None)
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    sub_s = (np.arange(s0, s1 + 1.0)[:, None] + offs).reshape(-1)
    sub_l = (np.arange(l0, l1 + 1.0)[:, None] + offs).reshape(-1)
    dirs = cam.pixel_to_direction_lattice(sub_s, sub_l).reshape(-1, 3)
    return dirs, (s0, l0, s1 - s0 + 1, l1 - l0 + 1)


@pytest.mark.parametrize("seed, emission, holes", [(7, 80.0, False), (2, 65.0, True), (6, 60.0, True)])
def test_the_walls_the_march_meets_are_drawn(seed, emission, holes):
    """Seen far off the normal, rays pass below the grid's border (and through missing nodes) and the
    march stops where they enter a cell's column below its terrain.  The raster draws those walls (−2:
    march); drawn without them (walls of no height) it would vouch for cells behind them and the kernel
    would return other hits — so the walls are what makes the renders equal."""
    patches, sun, cam = _world(seed, emission, 20.0, 14, holes)
    p = patches[0]
    dirs, (s0, l0, width, height) = _subrays(cam, p, 2)
    cells = rmod._raster_cells(cam, p, s0, l0, width, height, 2).reshape(-1)
    # the same raster without walls
    n = p.heights.shape[0]
    smp, lin, _ = cam.project_with_mask(p.node_points.reshape(-1, 3))
    xs = ((smp - s0 + 0.5) * 2 - 0.5).reshape(n, n)
    ys = ((lin - l0 + 0.5) * 2 - 0.5).reshape(n, n)
    axis = (p.v - cam.position) / np.linalg.norm(p.v - cam.position)
    depth = (p.node_points.reshape(-1, 3) @ axis).reshape(n, n)
    bare = np.empty((height * 2, width * 2), np.int64)
    foot = np.arange(n * n).reshape(n, n)
    feet = np.column_stack([xs.ravel(), ys.ravel(), depth.ravel()])
    terrain_cells(xs, ys, depth, p.valid, foot, feet, bare)
    bare = bare.reshape(-1)
    sunn = sun / np.linalg.norm(sun)
    arrays = PatchSet([p]).fused_arrays(sunn)
    ok = np.ones(len(dirs), bool)

    def geom(cand):
        args = (cam.position, dirs, ok, sunn, sunn, False, 1e-3, arrays)
        return rmod._trace_fused(*args, threads=1, cand=cand)

    ref, walls, no_walls = geom(None), geom(cells), geom(bare)
    np.testing.assert_array_equal(walls[0], ref[0])
    np.testing.assert_array_equal(walls[1], ref[1])
    wrong = np.any(no_walls[1] != ref[1], axis=1) | (no_walls[0] != ref[0])
    assert wrong.sum() >= 3  # hits on the walls, taken for terrain behind them (or for sky)
    assert np.all(cells[wrong] == -2)


@pytest.mark.parametrize("seed, emission, sun_elev, q, holes, ss, shading, shadows", CASES)
def test_a_render_hinted_with_other_cells_equals_the_march(
    seed, emission, sun_elev, q, holes, ss, shading, shadows
):
    """``render(..., cells=)``: the cells an earlier render hit (at another sub-pixel phase, another
    supersampling repeated, or plain junk) only say where each sub-ray's search starts; the render is
    the march's to the last bit, and its own ``cells`` are the same whatever the hint."""
    patches, sun, cam = _world(seed, emission, sun_elev, q, holes)
    opts = RenderOptions(supersample=ss, shading=shading, shadows=shadows, ray_inverse="grid", threads=1)
    ref = render(cam, sun, None, patches[:1], opts, return_cells=True)
    n = patches[0].heights.shape[0]
    assert ref.cells.shape == (ref.radiance.shape[0] * ss, ref.radiance.shape[1] * ss)
    hit = ref.cells >= 0
    assert np.all(ref.cells[~hit] == -2) and np.all(ref.cells[hit] < (n - 1) ** 2)
    assert hit.mean() > 0.05  # the patch fills part of the window
    # the hit positions: NaN exactly where nothing was hit, on the grid, and in the cell reported
    pos = ref.positions
    assert pos.shape == ref.cells.shape + (2,)
    assert np.all(np.isnan(pos[~hit])) and np.all(np.isfinite(pos[hit]))
    assert np.all((pos[hit] >= 0.0) & (pos[hit] <= n - 1.0))
    cell_of = np.minimum(np.floor(pos[hit]).astype(int), n - 2)
    np.testing.assert_array_equal(cell_of[:, 0] * (n - 1) + cell_of[:, 1], ref.cells[hit])
    rng = np.random.default_rng(seed)
    other = render(cam.with_ctr(cam.ctr + [0.3, -0.2]), sun, None, patches[:1], opts, return_cells=True)
    hints = {
        "own": ref.cells,
        "another phase": other.cells,
        # its rays sat 0.3 px along the samples and −0.2 px along the lines from ref's: moved back
        "another phase, predicted": rmod.predicted_cells(other, [-0.3, 0.2], n),
        "junk": rng.integers(-5, (n - 1) ** 2 + 5, ref.cells.shape),
        "wrong shape (ignored)": ref.cells[1:],
    }
    for name, hint in hints.items():
        got = render(cam, sun, None, patches[:1], opts, cells=hint, return_cells=True)
        assert_same_rendering(got, ref)
        np.testing.assert_array_equal(got.cells, ref.cells, err_msg=name)
    # not asked for, or two patches: no cells (the hint is one patch's)
    assert render(cam, sun, None, patches[:1], opts).cells is None
    assert render(cam, sun, None, patches, opts, return_cells=True).cells is None


def test_registration_with_hinted_templates_equals_unhinted(scene, monkeypatch):
    """register's image-space templates start each sub-ray at the cell where the landmark's last render
    says it will hit (its hit positions moved by the change of phase, or a one-ray draft's cells within
    a quarter pixel): the measurements equal those without the hint, bit for bit, for one-ray drafts
    and 2 × 2 templates, and the hint is used."""
    from spctool.stages import registrar as regmod

    cam = rs.pointing_error(scene.camera, 6.0, -4.0)
    used = []
    real = regmod._cells_hint

    mode = {"hint": True}

    def spy(*args):
        out = real(*args) if mode["hint"] else None
        used.append(out is not None)
        return out

    monkeypatch.setattr(regmod, "_cells_hint", spy)
    got = {}
    for name in ("hinted", "plain"):
        mode["hint"] = name == "hinted"
        used.clear()
        opts = RegisterOptions(space="image", threads=1)
        got[name] = (register(scene.photo, cam, scene.sun, [scene.maplet], scene.thresholds, opts), any(used))
    (hinted, was_used), (plain, never) = got["hinted"], got["plain"]
    assert was_used and not never
    assert hinted.status == plain.status == ["ok"]
    np.testing.assert_array_equal(hinted.measured, plain.measured)
    np.testing.assert_array_equal(hinted.correlation, plain.correlation)


def test_cells_hint_rules():
    """A hint comes from the last render of the same camera object and window: at its supersampling,
    its hit positions moved by the change of phase (any phase); a one-ray render's cells repeated for a
    finer supersampling within reach of its phase; a finer one's are not used for a coarser."""
    from spctool.stages.registrar import _HINT_REACH, _cells_hint

    cam, other = object(), object()
    n = 5  # nodes per side: cells i·4 + j
    # a 2 × 3 one-ray lattice whose rays hit (u, w) = (1.5 + column, 0.5 + 2·row): cells 4 + 4c + 2r
    u, w = np.meshgrid(1.5 + np.arange(3.0), 0.5 + 2.0 * np.arange(2.0))
    pos = np.stack([u, w], axis=-1)
    cells = (np.floor(u) * (n - 1) + np.floor(w)).astype(np.int64)
    prev = rmod.Rendering(*(np.zeros((2, 3)),) * 4, (1, 3, 1, 2), RenderOptions(), cells, pos)
    win = (1, 3, 1, 2)
    f0 = np.array([0.1, -0.1])
    hits = (cam, f0, 1, win, prev)
    np.testing.assert_array_equal(_cells_hint(hits, cam, f0, 1, win, n), cells)
    # cells 4 + 4c + 2r; the phase 0.6 px back along the samples: each ray where the earlier one 0.6 px
    # further on hit, u + 0.6 (the next cell along u), nothing known beyond the last column (march)
    moved = _cells_hint(hits, cam, f0 - [0.6, 0.0], 1, win, n)
    np.testing.assert_array_equal(moved, [[8, 12, -2], [10, 14, -2]])
    assert _cells_hint(None, cam, f0, 1, win, n) is None
    assert _cells_hint(hits, other, f0, 1, win, n) is None
    assert _cells_hint(hits, cam, f0, 1, (1, 3, 1, 3), n) is None
    # a finer supersampling: the one-ray positions read at its sub-rays, any phase (sub-ray c of 2 looks
    # through s0 + (c + ½)/2 − ½ − f: the one-ray lattice's c/2 − ¼ + (f0 − f))
    for df in ([0.9 * _HINT_REACH, 0.0], [-0.7, 0.4]):
        up = _cells_hint(hits, cam, f0 + df, 2, win, n)
        want = _predict_brute(pos, -0.25 - df[0], -0.25 - df[1], n, (4, 6), 0.5)
        np.testing.assert_array_equal(up, want)
        assert (up >= 0).sum() >= 6
    # without positions: its cells repeated over the sub-rays, within reach of its phase only
    bare = (cam, f0, 1, win, rmod.Rendering(*(np.zeros((2, 3)),) * 4, win, RenderOptions(), cells, None))
    near = f0 + [0.9 * _HINT_REACH, 0.0]
    up = _cells_hint(bare, cam, near, 2, win, n)
    np.testing.assert_array_equal(up, np.repeat(np.repeat(cells, 2, 0), 2, 1))
    assert _cells_hint(bare, cam, f0 + [1.1 * _HINT_REACH, 0.0], 2, win, n) is None
    fine = rmod.Rendering(*(np.zeros((2, 3)),) * 4, (1, 3, 1, 2), RenderOptions(supersample=2), up, None)
    assert _cells_hint((cam, near, 2, win, fine), cam, near, 1, win, n) is None


def _predict_brute(pos, ds, dl, n, shape=None, step=1.0):
    """:func:`predict_cells` by NumPy: bilinear positions where all four neighbours hit, else the
    nearest lattice point's, else −2 (``shape``: the output's, default ``pos``'s lattice; ``step``: the
    output's spacing on ``pos``'s lattice)."""
    nl, ns = pos.shape[:2]
    out = np.full(pos.shape[:2] if shape is None else shape, -2, np.int64)
    for r in range(out.shape[0]):
        for c in range(out.shape[1]):
            y, x = r * step + dl, c * step + ds
            b, a = min(int(np.floor(y)), nl - 2), min(int(np.floor(x)), ns - 2)
            uw = None
            if 0 <= b and 0 <= a and 0 <= y - b <= 1 and 0 <= x - a <= 1:
                quad = pos[b : b + 2, a : a + 2]
                if not np.isnan(quad).any():
                    fy, fx = y - b, x - a
                    g = np.array([[(1 - fx) * (1 - fy), fx * (1 - fy)], [(1 - fx) * fy, fx * fy]])
                    uw = np.einsum("ij,ijk->k", g, quad)
            if uw is None:
                rn, cn = int(np.floor(y + 0.5)), int(np.floor(x + 0.5))
                if 0 <= rn < nl and 0 <= cn < ns and not np.isnan(pos[rn, cn]).any():
                    uw = pos[rn, cn]
            if uw is not None:
                i, j = (min(max(int(np.floor(v)), 0), n - 2) for v in uw)
                out[r, c] = i * (n - 1) + j
    return out


@pytest.mark.parametrize("seed", range(4))
def test_predict_cells_against_numpy(seed):
    from spctool.geometry._patchkernels import predict_cells

    rng = np.random.default_rng(seed)
    n = 9
    pos = rng.uniform(-0.2, n - 0.8, (7, 6, 2)).clip(0.0, n - 1.0)
    pos[rng.random((7, 6)) < 0.2] = np.nan  # rays that hit nothing
    for ds, dl in ((0.0, 0.0), (0.37, -0.81), (-1.5, 2.25), (6.2, 0.1), (-0.5, 0.5), (0.0, 0.4)):
        out = np.empty((7, 6), np.int64)
        predict_cells(pos, ds, dl, n, out)
        np.testing.assert_array_equal(out, _predict_brute(pos, ds, dl, n), err_msg=f"{ds}, {dl}")
    # a lattice of another size (another window): the same rule, positions read where they exist
    for shape in ((5, 9), (9, 4)):
        out = np.empty(shape, np.int64)
        predict_cells(pos, 1.25, -0.5, n, out)
        np.testing.assert_array_equal(out, _predict_brute(pos, 1.25, -0.5, n, shape), err_msg=str(shape))
        assert np.all(out[:, 6:] == -2)  # more than half a lattice step beyond the earlier lattice
    # a finer lattice (half the spacing: 2 × 2 sub-rays after a one-ray render)
    out = np.empty((14, 12), np.int64)
    predict_cells(pos, -0.25 + 0.3, -0.25 - 0.2, n, out, 0.5)
    np.testing.assert_array_equal(out, _predict_brute(pos, 0.05, -0.45, n, (14, 12), 0.5))


@pytest.mark.parametrize("shift", [0.05, 0.25, 0.5])
def test_predicted_cells_find_most_hits_at_another_phase(shift):
    """The point of the prediction: at another phase of the same camera most rays are expected in the
    cell they hit (the earlier render's own cells, the shift rounded, find about half at a quarter
    pixel), so most re-rendered rays solve one cell instead of marching."""
    patches, sun, cam = _world(*WORLDS[0][:5])
    opts = RenderOptions(supersample=1, ray_inverse="grid", threads=1)
    n = patches[0].heights.shape[0]
    prev = render(cam, sun, None, patches[:1], opts, return_cells=True)
    f = np.array([shift, -0.6 * shift])
    now = render(cam.with_ctr(cam.ctr + f), sun, None, patches[:1], opts, return_cells=True)
    pred = rmod.predicted_cells(prev, -f, n)
    hit = now.cells >= 0
    assert np.mean(pred[hit] == now.cells[hit]) > 0.85
    assert np.mean(pred[hit] == now.cells[hit]) > np.mean(prev.cells[hit] == now.cells[hit]) - 1e-9


@pytest.mark.parametrize("shift", [0.0, 0.2, 0.45])
def test_one_ray_positions_predict_a_finer_render(shift):
    """A 2 × 2 template after a one-ray render of the same camera (the converged stage's first full
    template after its drafts): the one-ray hit positions read at each sub-ray
    (``predicted_cells(..., supersample=2)``) find the cell of nearly every hit, where the one-ray
    cells repeated over each pixel's sub-rays miss a quarter of them; the render is the same either way."""
    patches, sun, cam = _world(*WORLDS[0][:5])
    n = patches[0].heights.shape[0]
    one = RenderOptions(supersample=1, ray_inverse="grid", threads=1)
    two = dataclasses.replace(one, supersample=2)
    prev = render(cam, sun, None, patches[:1], one, return_cells=True)
    f = np.array([shift, -0.6 * shift])
    now = render(cam.with_ctr(cam.ctr + f), sun, None, patches[:1], two, return_cells=True)
    pred = rmod.predicted_cells(prev, -f, n, now.cells.shape, supersample=2)
    hit = now.cells >= 0
    assert np.mean(pred[hit] == now.cells[hit]) > 0.9
    if shift == 0.0:  # what the repeated cells find, for comparison
        rep = np.repeat(np.repeat(prev.cells, 2, 0), 2, 1)
        assert np.mean(pred[hit] == now.cells[hit]) > np.mean(rep[hit] == now.cells[hit]) + 0.05
    got = render(cam.with_ctr(cam.ctr + f), sun, None, patches[:1], two, cells=pred, return_cells=True)
    assert_same_rendering(got, now)
    with pytest.raises(ValueError, match="shape"):
        rmod.predicted_cells(prev, -f, n, supersample=2)


def test_visibility_option_is_checked():
    with pytest.raises(SpcUsageError, match="visibility"):
        RenderOptions(visibility="zbuffer")
    with pytest.raises(SpcUsageError, match="template_visibility"):
        RegisterOptions(template_visibility="zbuffer")


@pytest.fixture(scope="module")
def scene():
    return rs.scene()


def test_image_space_registration_with_raster_templates_equals_the_march(scene):
    cam = rs.pointing_error(scene.camera, 6.0, -4.0)
    got = {}
    for vis in ("raster", "march"):
        opts = RegisterOptions(space="image", threads=1, template_visibility=vis)
        got[vis] = register(scene.photo, cam, scene.sun, [scene.maplet], scene.thresholds, opts)
    assert got["raster"].status == got["march"].status == ["ok"]
    np.testing.assert_array_equal(got["raster"].measured, got["march"].measured)
    assert np.all(np.abs(got["raster"].measured[0] - scene.truth_pixel) < 0.05)


@pytest.mark.parametrize("seed, reach", [(0, 0), (1, 2), (2, 4), (3, 7), (4, 1), (5, 30)])
def test_near_steps_against_brute_force(seed, reach):
    from spctool.geometry._heightkernels import near_steps

    rng = np.random.default_rng(seed)
    n0, n1 = 15, 11
    h = rng.normal(size=(n0, n1)) * rng.uniform(0.1, 3.0)
    valid = rng.uniform(size=h.shape) > 0.04
    h = np.where(valid, h, 0.0)
    out = np.empty((n0 - 1, n1 - 1, 2))
    near_steps(h, valid, reach, out)
    for i in range(n0 - 1):
        for j in range(n1 - 1):
            want = [0.0, 0.0]
            for a in range(max(i - reach, 0), min(i + reach, n0 - 2) + 1):
                for b in range(max(j - reach, 0), min(j + reach, n1 - 2) + 1):
                    if not valid[a : a + 2, b : b + 2].all():
                        want = [np.inf, np.inf]
                        break
                    want[0] = max(want[0], np.abs(h[a + 1, b : b + 2] - h[a, b : b + 2]).max())
                    want[1] = max(want[1], np.abs(h[a : a + 2, b + 1] - h[a : a + 2, b]).max())
                else:
                    continue
                break
            np.testing.assert_array_equal(out[i, j], want)
    # the bound holds: |∂h/∂u|, |∂h/∂w| of the bilinear terrain at random points of full cells
    for _ in range(200):
        i, j = rng.integers(0, n0 - 1), rng.integers(0, n1 - 1)
        if not valid[i : i + 2, j : j + 2].all():
            continue
        fu, fw = rng.uniform(size=2)
        du = (1 - fw) * (h[i + 1, j] - h[i, j]) + fw * (h[i + 1, j + 1] - h[i, j + 1])
        dw = (1 - fu) * (h[i, j + 1] - h[i, j]) + fu * (h[i + 1, j + 1] - h[i + 1, j])
        assert abs(du) <= out[i, j, 0] + 1e-12 and abs(dw) <= out[i, j, 1] + 1e-12


@pytest.mark.parametrize("q, ss, chunk", [(1, 2, 1 << 18), (14, 3, 997), (14, 8, 5000)])
def test_raster_small_patches_chunks_and_fine_supersampling(q, ss, chunk):
    """A 3×3 patch, windows split into many chunks (the raster's rows sliced to match), 8×8 sub-rays
    (the NumPy bins): still the march's picture."""
    patches, sun, cam = _world(11, 35.0, 25.0, q, q > 1)
    opts = RenderOptions(supersample=ss, ray_inverse="grid", threads=1, chunk=chunk)
    ref = render(cam, sun, None, patches[:1], opts)
    got = render(cam, sun, None, patches[:1], dataclasses.replace(opts, visibility="raster"))
    assert np.count_nonzero(ref.coverage) > (0 if q == 1 else 500)
    assert_same_rendering(got, ref)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(3))
def test_a_hinted_cell_never_moves_a_hit_at_nodes_edges_and_grid_lines(seed):
    """Rays aimed at the grid's nodes and edges (and along its lines, du = 0), each hinted with the cell
    of its hit and the eight around it: wherever ``_cell_hit`` takes the hint, its crossing is the
    march's to the last bit (a crossing two cells' formulas share, a ray lying in two columns: the
    march decides)."""
    import math

    from spctool.geometry._heightkernels import _march
    from spctool.geometry._patchkernels import _cell_hit
    from spctool.geometry.surfaces import NEAR_CELLS, HeightPatch

    rng = np.random.default_rng(seed)
    n, taken = 9, 0
    for _ in range(40):
        h = rng.normal(size=(n, n)) * rng.choice([0.05, 0.3, 1.0])
        if rng.random() < 0.3:
            h = np.round(h, 1)  # ties and flat cells
        p = HeightPatch(h, 0.001, np.zeros(3), [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0])
        hts, valids, tops, near = p.heights[None], p.valid[None], p.cell_tops[None], p.near_steps[None]
        hmin, hmax = p.height_range
        for _ in range(60):
            u = float(rng.integers(1, n - 1)) if rng.random() < 0.7 else rng.uniform(1, n - 2)
            w = float(rng.integers(1, n - 1)) if rng.random() < 0.7 else rng.uniform(1, n - 2)
            i, j = min(int(u), n - 2), min(int(w), n - 2)
            fu, fw = u - i, w - j
            z = (1 - fu) * (1 - fw) * h[i, j] + fu * (1 - fw) * h[i + 1, j]
            z += (1 - fu) * fw * h[i, j + 1] + fu * fw * h[i + 1, j + 1]
            d = np.array([rng.normal() * 0.3, rng.normal() * 0.3, -1.0])
            if rng.random() < 0.3:
                d[1] = d[0] * rng.choice([1, -1])  # a diagonal through the corners
            if rng.random() < 0.15:
                d[0] = 0.0  # along a grid line
            t0 = rng.uniform(5, 20)
            u0, w0, z0 = u - t0 * d[0], w - t0 * d[1], z - t0 * d[2]
            args = (u0, w0, z0, d[0], d[1], d[2], 0.0, 1e9)
            ref = _march(hts, valids, tops, 0, n, n, hmin, hmax, *args, tops, False)
            if not math.isfinite(ref):
                continue
            ci = min(max(int(math.floor(u0 + ref * d[0])), 0), n - 2)
            cj = min(max(int(math.floor(w0 + ref * d[1])), 0), n - 2)
            for a in range(max(ci - 1, 0), min(ci + 1, n - 2) + 1):
                for b in range(max(cj - 1, 0), min(cj + 1, n - 2) + 1):
                    got = _cell_hit(hts, near, 0, n, a, b, *args, hmax, float(NEAR_CELLS))
                    if not math.isnan(got):
                        taken += 1
                        assert np.float64(got).tobytes() == np.float64(ref).tobytes(), (a, b, got, ref)
    assert taken > 100  # the hint is taken for most rays off the nodes
