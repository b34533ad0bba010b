"""The GIL-free kernels of a maplet-space step (issue 39) against the NumPy code they replaced.

Each kernel fuses a few NumPy operations of :meth:`spctool.stages.registrar.Registrar.extraction` or
the correlator into one compiled pass that releases the GIL (so that threads can share the landmarks);
the references below are those NumPy operations, kept here verbatim, and the kernels must give the same
arrays to the bit on hand-made and random inputs.
"""

from __future__ import annotations

import numpy as np
import pytest

from spctool.stages.extract import _enhance_kernel, _k_recentred, brt0, shadow_offsets

# -- the re-centred extraction ---------------------------------------------------------------------


def _recentred_numpy(photo, sample0, line0, ds, dl, t_lo, t_hi, floor, shadow, filtered, visible):
    """Registrar.extraction's re-centring as NumPy did it before the kernel (``shadow``: (checks,
    zeros) or False)."""
    smp = sample0 + ds
    lin = line0 + dl
    nln, npx = photo.shape
    node_ok = np.isfinite(sample0)
    covered = node_ok & (smp >= 1.0) & (smp < npx) & (lin >= 1.0) & (lin < nln)
    values = brt0(
        photo, np.where(node_ok, smp, 0.0), np.where(node_ok, lin, 0.0), t_lo, t_hi, repair_floor=floor
    )
    lit = node_ok & (values > 0.0)
    image = np.where(lit, values, 0.0)
    removed_shadow = np.zeros(image.shape, dtype=bool)
    if filtered:
        if shadow is not False:
            checks, zeros = shadow
            zero = np.zeros(image.shape, dtype=bool)
            edges = np.zeros(image.shape, dtype=bool)
            nonzero = image > 0.0
            _enhance_kernel(nonzero, checks, zeros, zero, edges)
            removed_shadow = zero & nonzero
            image[zero] = 0.0
        image = np.where(visible, image, 0.0)
    return dict(
        sample=smp, line=lin, image=image, valid=image > 0.0, covered=covered, lit=lit,
        removed_shadow=removed_shadow,
    )  # fmt: skip


def _recentred_kernel(photo, sample0, line0, ds, dl, t_lo, t_hi, floor, shadow, filtered, visible):
    shape = sample0.shape
    out = dict(sample=np.empty(shape), line=np.empty(shape), image=np.empty(shape))
    out.update((k, np.empty(shape, dtype=bool)) for k in ("valid", "covered", "lit", "removed_shadow"))
    enhance = filtered and shadow is not False
    none = np.zeros((0, 2), dtype=np.int64)
    checks, zeros = shadow if enhance else (none, none)
    _k_recentred(
        photo, sample0, line0, float(ds), float(dl), float(t_lo), float(t_hi), float(floor), enhance, checks,
        zeros, filtered, visible, out["sample"], out["line"], out["image"], out["valid"], out["covered"],
        out["lit"], out["removed_shadow"],
    )  # fmt: skip
    return out


def _same(a: dict, b: dict):
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].tobytes() == b[k].tobytes(), k


def test_recentred_kernel_hand_made_case():
    """A 6×8 photo with a missing pixel (DN 0), one above T2 and one below T1; nodes inside, on the
    BRT0 border (sample = NPX is outside), NaN (behind the camera) and negative; a shadow whose edge
    is at a known cell."""
    photo = np.arange(1.0, 49.0).reshape(6, 8) * 10.0
    photo[2, 3] = 0.0  # missing: one corner repaired by planar extrapolation
    photo[4, 6] = 5000.0  # above T2
    photo[1, 1] = 15.0  # below T1
    sample0 = np.array([[1.0, 2.5, 4.2], [7.9, 8.0, np.nan], [-3.0, 3.5, 5.25]])
    line0 = np.array([[1.0, 1.5, 3.1], [2.0, 2.0, np.nan], [2.0, 4.5, 5.99]])
    visible = np.array([[True, True, False], [True, True, True], [True, True, True]])
    checks, zeros = np.array([[0, 1]], dtype=np.int64), np.array([[0, 0], [0, -1]], dtype=np.int64)
    for ds, dl in ((0.0, 0.0), (0.25, -0.5), (-1.0, 0.75)):
        for shadow in (False, (checks, zeros)):
            for filtered in (False, True):
                args = (photo, sample0, line0, ds, dl, 20.0, 400.0, 1.0, shadow, filtered, visible)
                ref = _recentred_numpy(*args)
                _same(ref, _recentred_kernel(*args))
    # the hand-made expectations themselves: node (0, 0) at pixel (1, 1) reads DN 10; the NaN node is
    # neither covered nor lit; sample 8.0 (= NPX) is outside the BRT0 domain
    ref = _recentred_numpy(photo, sample0, line0, 0.0, 0.0, -np.inf, np.inf, 1.0, False, False, visible)
    assert ref["image"][0, 0] == 10.0 and not ref["covered"][1, 2] and not ref["lit"][1, 2]
    assert ref["covered"][1, 0] and not ref["covered"][1, 1] and ref["image"][1, 1] == 0.0


@pytest.mark.parametrize("seed", range(6))
def test_recentred_kernel_random_inputs(seed):
    """Random photos (with missing DN and thresholds), random node pixels (some NaN, some outside) and
    the extract filter's own offsets for a random Sun azimuth."""
    rng = np.random.default_rng(seed)
    nln, npx = rng.integers(20, 60, size=2)
    photo = rng.uniform(0.0, 1000.0, size=(nln, npx))
    photo[rng.random(photo.shape) < 0.1] = 0.0
    n = int(rng.integers(5, 40))
    sample0 = rng.uniform(-3.0, npx + 3.0, size=(n, n))
    line0 = rng.uniform(-3.0, nln + 3.0, size=(n, n))
    gone = rng.random((n, n)) < 0.1
    sample0[gone] = np.nan
    line0[gone] = np.nan
    visible = rng.random((n, n)) < 0.8
    az = rng.uniform(0.0, 2 * np.pi)
    shadow = shadow_offsets((np.cos(az), np.sin(az)), int(rng.integers(1, 6)))
    for filtered in (False, True):
        for sh in (False, shadow):
            args = (photo, sample0, line0, *rng.normal(0.0, 2.0, 2), 50.0, 950.0, 1.0, sh, filtered, visible)
            _same(_recentred_numpy(*args), _recentred_kernel(*args))


# -- the correlation's front end -------------------------------------------------------------------


def _correlations_equal(a, b):
    for f in ("surface", "counts", "offset", "covariance", "hessian"):
        x, y = np.asarray(getattr(a, f)), np.asarray(getattr(b, f))
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), f
    for f in ("spacing", "status", "peak_index", "peak_fit"):
        assert getattr(a, f) == getattr(b, f), f
    assert np.asarray(a.peak).tobytes() == np.asarray(b.peak).tobytes()
    assert np.asarray(a.subpixel).tobytes() == np.asarray(b.subpixel).tobytes()


def _shaded(rng, n, shift=(0.0, 0.0)):
    """A smooth random texture of n×n cells, moved by ``shift`` cells."""
    i, j = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    out = np.full((n, n), 100.0)
    for _ in range(6):
        k = rng.uniform(0.1, 0.5, 2)
        phase = k[0] * (i - shift[0]) + k[1] * (j - shift[1]) + rng.uniform(0, 6)
        out += rng.uniform(5.0, 20.0) * np.sin(phase)
    return out


def test_correlate_maplet_is_correlate_hand_made_case():
    """A texture and itself moved by (1.3, −0.6) cells: the fused front end reads the same surface,
    peak and offset as :func:`correlate`, and the offset (least-squares alignment) is the move."""
    from spctool.stages.correlate import CorrelateOptions, correlate, correlate_maplet

    rng = np.random.default_rng(7)
    p = _shaded(rng, 41)
    e = _shaded(np.random.default_rng(7), 41, (1.3, -0.6))
    ok = np.ones(p.shape, dtype=bool)
    opts = CorrelateOptions(peak="gradient")
    ref = correlate(e, p, extracted_valid=ok, predicted_valid=ok, spacing=1, options=opts)
    got = correlate_maplet(e, ok, p, ok, 1, opts, (20, 20), (20, 20))
    _correlations_equal(ref, got)
    assert ref.status == "ok" and np.allclose(ref.offset, (1.3, -0.6), atol=0.1)


@pytest.mark.parametrize("seed", range(8))
def test_correlate_maplet_is_correlate_random_inputs(seed):
    """Random textures, masks (with NaN and non-positive pixels), spacings 1–5, anchors (the centre, or
    a larger search image's), every peak estimator, ``min_value`` None or 0 and a bin fraction."""
    from spctool.stages.correlate import PEAK_METHODS, CorrelateOptions, correlate, correlate_maplet

    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(15, 45))
    margin = int(rng.integers(0, 6)) if seed % 2 else 0
    p = _shaded(rng, n)
    e = _shaded(rng, n + 2 * margin, rng.normal(0.0, 2.0, 2))
    e[rng.random(e.shape) < 0.05] = 0.0
    e[rng.random(e.shape) < 0.01] = np.nan
    ve = rng.random(e.shape) < 0.9
    vp = rng.random(p.shape) < 0.9
    q = (n - 1) // 2
    anchors = dict(extracted_anchor=(q + margin, q + margin), predicted_anchor=(q, q))
    for peak in PEAK_METHODS:
        for spacing in (1, int(rng.integers(2, 6))):
            opts = CorrelateOptions(
                peak=peak, min_value=None if rng.random() < 0.3 else 0.0,
                bin_min_fraction=float(rng.choice([0.0, 0.5])), grid_half=int(rng.integers(2, 6)),
            )  # fmt: skip
            ref = correlate(
                e, p, extracted_valid=ve, predicted_valid=vp, spacing=spacing, options=opts, **anchors
            )
            got = correlate_maplet(e, ve, p, vp, spacing, opts, anchors["extracted_anchor"], (q, q))
            _correlations_equal(ref, got)


# -- the shadow enhancement's offsets --------------------------------------------------------------


def _shadow_offsets_numpy(sun_xy, ds, lateral=2, band=True, include_edge=True, edge_steps=3):
    """shadow_offsets as NumPy computed it before its kernel."""
    from spctool.stages.extract import nint

    sx, sy = float(sun_xy[0]), float(sun_xy[1])
    k = np.arange(1, edge_steps + 1, dtype=np.float64)
    checks = nint(np.stack([k * sx, k * sy], axis=-1)).reshape(-1, 2)
    ks = np.arange(0 if include_edge else 1, ds + 1, dtype=np.float64)
    js = np.arange(-lateral, lateral + 1, dtype=np.float64) if band else np.unique([-lateral, 0.0, lateral])
    kk, jj = np.meshgrid(ks, js, indexing="ij")
    off = np.stack([-kk * sx - jj * sy, -kk * sy + jj * sx], axis=-1).reshape(-1, 2)
    zeros = np.array(sorted(set(map(tuple, nint(off).tolist()))), dtype=np.int64).reshape(-1, 2)
    return np.ascontiguousarray(checks, dtype=np.int64), zeros


def test_shadow_offsets_kernel_hand_made_and_random():
    """The Sun along +x (ds 2, the band ±2): checks (1,0), (2,0), (3,0); zeros the 3×5 block
    k = 0…2 back along −x, j = −2…2 across; then random azimuths (half-way roundings included:
    azimuths of 45° and 30° put k·ŝ on .5 exactly), extensions, lateral sets and edge rules."""
    checks, zeros = shadow_offsets((1.0, 0.0), 2)
    assert checks.tolist() == [[1, 0], [2, 0], [3, 0]]
    assert zeros.tolist() == [[-k, j] for k in (2, 1, 0) for j in range(-2, 3)]
    rng = np.random.default_rng(3)
    azimuths = list(rng.uniform(0.0, 2 * np.pi, 40)) + [np.pi / 4, np.pi / 6, np.pi, 3 * np.pi / 2]
    for az in azimuths:
        sun = (np.cos(az), np.sin(az))
        for ds in (0, 1, int(rng.integers(2, 30))):
            other = (int(rng.integers(0, 4)), False, False, 2)
            for lateral, band, edge, steps in ((2, True, True, 3), other):
                ref = _shadow_offsets_numpy(sun, ds, lateral, band, edge, steps)
                got = shadow_offsets(sun, ds, lateral, band, edge, steps)
                for r, g in zip(ref, got):
                    assert r.dtype == g.dtype and r.shape == g.shape, (az, ds, lateral)
                    assert np.array_equal(r, g), (az, ds, lateral)


# -- a full extraction's node pixels and samples ---------------------------------------------------


def test_node_positions_kernel_is_the_numpy_form():
    """P = V + SCALE·(x·UX + y·UY + h·UZ) node by node: a hand-made 3×3 maplet (V at the origin, unit
    axes: P = scale·(x, y, h)) and random frames, scales and heights, to the bit."""
    from spctool.stages.extract import _k_node_positions, _node_positions

    eye = np.eye(3)
    h = np.arange(9.0).reshape(3, 3)
    out = np.empty((3, 3, 3))
    _k_node_positions(h, 1.0, 2.0, np.zeros(3), eye[0], eye[1], eye[2], out)
    assert out[0, 2].tolist() == [-2.0, 2.0, 4.0] and out[1, 1].tolist() == [0.0, 0.0, 8.0]
    rng = np.random.default_rng(11)
    for _ in range(10):
        n = 2 * int(rng.integers(1, 30)) + 1
        q = (n - 1) // 2
        h = rng.normal(0.0, 3.0, (n, n))
        v, ux, uy, uz = (rng.normal(0.0, 1000.0, 3) for _ in range(4))
        scale = float(rng.uniform(0.01, 5.0))
        x = (np.arange(n, dtype=np.float64) - q)[:, None]
        y = (np.arange(n, dtype=np.float64) - q)[None, :]
        out = np.empty((n, n, 3))
        _k_node_positions(h, float(q), scale, v, ux, uy, uz, out)
        assert out.tobytes() == _node_positions(x, y, h, scale, v, ux, uy, uz).tobytes()


@pytest.mark.parametrize("seed", range(4))
def test_sample_nodes_kernel_is_the_numpy_form(seed):
    """Node pixels (some NaN, some behind the camera, some outside), moved or not, V in front or not:
    node_ok, the NaN'd pixels, covered, lit and the BRT0 image as extract's NumPy form gave them."""
    from spctool.stages.extract import _k_sample_nodes

    rng = np.random.default_rng(seed)
    nln, npx = rng.integers(20, 50, size=2)
    data = rng.uniform(0.0, 500.0, (nln, npx))
    data[rng.random(data.shape) < 0.1] = 0.0
    n = int(rng.integers(3, 30))
    smp0 = rng.uniform(-2.0, npx + 2.0, (n, n))
    lin0 = rng.uniform(-2.0, nln + 2.0, (n, n))
    smp0[rng.random((n, n)) < 0.05] = np.nan
    front = rng.random((n, n)) < 0.9
    mvalid = rng.random((n, n)) < 0.9
    for front_v in (True, False):
        for moved in (False, True):
            d_s, d_l = rng.normal(0.0, 3.0, 2)
            smp, lin = smp0.copy(), lin0.copy()
            if moved:
                smp, lin = smp + d_s, lin + d_l
            node_ok = mvalid & front & np.isfinite(smp) & np.isfinite(lin) & front_v
            smp = np.where(node_ok, smp, np.nan)
            lin = np.where(node_ok, lin, np.nan)
            covered = node_ok & (smp >= 1.0) & (smp < npx) & (lin >= 1.0) & (lin < nln)
            values = brt0(data, smp, lin, 10.0, 450.0, repair_floor=1.0)
            lit = node_ok & (values > 0.0)
            image = np.where(lit, values, 0.0)
            ks, kl = smp0.copy(), lin0.copy()
            got = [np.empty((n, n), dtype=bool) for _ in range(3)] + [np.empty((n, n))]
            _k_sample_nodes(data, ks, kl, front, mvalid, front_v, moved, d_s, d_l, 10.0, 450.0, 1.0,
                            got[0], got[1], got[3], got[2])  # fmt: skip
            for ref, g in zip((smp, lin, node_ok, covered, lit, image), (ks, kl, *got)):
                assert ref.dtype == g.dtype and ref.tobytes() == g.tobytes()


def test_surface_cosines_kernel_is_the_numpy_form():
    """n̂·d on a grid: a flat maplet gives d_z everywhere, a 45° slope along x gives (d_z − d_x)/√2;
    random slopes, directions and a given 1/|n| give the NumPy formula's values to the bit."""
    from spctool.geometry.heightfield import surface_cosines

    zero = np.zeros((3, 3))
    assert np.array_equal(surface_cosines(zero, zero, (0.6, 0.0, 0.8)), np.full((3, 3), 0.8))
    one = np.ones((2, 2))
    assert np.allclose(surface_cosines(one, 0.0 * one, (0.6, 0.0, 0.8)), (0.8 - 0.6) / np.sqrt(2.0))
    rng = np.random.default_rng(5)
    for _ in range(10):
        n = int(rng.integers(1, 40))
        hx, hy = rng.normal(0.0, 1.0, (2, n, n))
        hx[rng.random((n, n)) < 0.05] = np.nan
        d = rng.normal(0.0, 1.0, 3)
        inv = 1.0 / np.sqrt(1.0 + hx * hx + hy * hy)
        assert surface_cosines(hx, hy, d).tobytes() == ((d[2] - hx * d[0] - hy * d[1]) * inv).tobytes()
        assert surface_cosines(hx, hy, d, inv).tobytes() == ((d[2] - hx * d[0] - hy * d[1]) * inv).tobytes()
