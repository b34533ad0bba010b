"""Tests of spctool.geometry.heightfield (maplet grids as geometry).

Every expectation is computed independently: analytic derivatives of quadratics, the spc-formats.md §1.3
node formula written with SPC's (I, J) loops, a hand-worked node of the §4.3 LMK frame, hand-computed
bilinear samples and ray crossings, shadow lengths H/tan(elevation), and pure-Python brute-force
references for the HGT2SLP table and the horizon march.
"""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool.geometry import frames
from spctool.geometry import heightfield as hf

# §4.3 example frame (ORIENT frame of V = (0.5, 0.1, 0.2)), spc-formats.md
LMK_V = np.array([0.5, 0.1, 0.2])
LMK_UX = np.array([0.3580574370, 0.7161148740e-01, -0.9309493363])
LMK_UY = np.array([-0.1961161351, 0.9805806757, 0.0])
LMK_UZ = np.array([0.9128709292, 0.1825741858, 0.3651483717])


def random_frame(rng):
    """A random right-handed orthonormal triad (UX, UY, UZ)."""
    a = rng.normal(size=(3, 3))
    qm, _ = np.linalg.qr(a)
    if np.linalg.det(qm) < 0:
        qm[:, 0] = -qm[:, 0]
    return qm[:, 0], qm[:, 1], qm[:, 2]


def quadratic(coef, x, y):
    a, b, c, d, e, f = coef
    return a + b * x + c * y + d * x * x + e * x * y + f * y * y


def quadratic_dx(coef, x, y):
    _, b, _, d, e, _ = coef
    return b + 2 * d * x + e * y


def quadratic_dy(coef, x, y):
    _, _, c, _, e, f = coef
    return c + e * x + 2 * f * y


def grid_xy(q):
    x = np.arange(-q, q + 1, dtype=float)
    return np.meshgrid(x, x, indexing="ij")  # X along axis 0 (UX), Y along axis 1 (UY)


# ------------------------------------------------------------------------------------------------
# node positions


def test_node_offsets_layout():
    h = np.arange(25, dtype=float).reshape(5, 5)
    off = hf.node_offsets(h)
    assert off.shape == (5, 5, 3)
    # r = J + q along UX (x), c = I + q along UY (y)
    assert off[0, 4].tolist() == [-2.0, 2.0, 4.0]
    assert off[3, 1].tolist() == [1.0, -1.0, 16.0]
    assert off[2, 2].tolist() == [0.0, 0.0, 12.0]


def test_node_positions_against_spc_formula():
    rng = np.random.default_rng(3)
    q = 3
    scale = 0.0123
    v = rng.normal(size=3)
    ux, uy, uz = random_frame(rng)
    h = rng.normal(size=(2 * q + 1, 2 * q + 1))
    got = hf.node_positions(h, scale, v, ux, uy, uz)
    # spc-formats.md §1.3, written with SPC's indices: P(I, J) = V + SCALE (J UX + I UY + h(I, J) UZ),
    # the file stores J outer, I inner -> array [J + q, I + q].
    for J in range(-q, q + 1):
        for I in range(-q, q + 1):
            hij = h[J + q, I + q]
            expected = [v[k] + scale * (J * ux[k] + I * uy[k] + hij * uz[k]) for k in range(3)]
            np.testing.assert_allclose(got[J + q, I + q], expected, rtol=0, atol=1e-15)


def test_node_positions_hand_example_lmk_frame():
    # §4.3 frame, SCALE 0.0005 km, q = 1.  Hand-worked with the printed 10-digit axes:
    #   node J = -1, I = +1, h = 2:  -UX + UY + 2 UZ = (1.2715682863, 1.2741175599, 1.6612460797)
    #   P = V + 0.0005 * that = (0.50063578414315, 0.10063705877995, 0.20083062303985)
    #   node J = +1, I = 0, h = -0.5: UX - 0.5 UZ = (-0.0983780276, -0.0196756055, -1.11352352215)
    #   P = (0.4999508109862, 0.09999016219725, 0.199443238238925)
    h = np.zeros((3, 3))
    h[0, 2] = 2.0
    h[2, 1] = -0.5
    p = hf.node_positions(h, 0.0005, LMK_V, LMK_UX, LMK_UY, LMK_UZ)
    np.testing.assert_allclose(p[0, 2], [0.50063578414315, 0.10063705877995, 0.20083062303985], atol=1e-15)
    np.testing.assert_allclose(p[2, 1], [0.4999508109862, 0.09999016219725, 0.199443238238925], atol=1e-15)
    np.testing.assert_array_equal(p[1, 1], LMK_V)


REAL = Path(__file__).resolve().parent.parent / "fixtures" / "real" / "rosetta-67p"


def read_lmk_frame(path):
    """SCALE, VLM, UX, UY, UZ from an LMK file (lines 2, 5-8; Fortran D exponents)."""
    lines = path.read_text().splitlines()

    def vec(line):
        return np.array([float(t.replace("D", "E")) for t in line[:60].split()])

    scale = float(lines[1].split()[1])
    return scale, vec(lines[4]), vec(lines[5]), vec(lines[6]), vec(lines[7])


@pytest.mark.skipif(not (REAL / "FA0115.LMK").exists(), reason="real fixtures not present")
def test_node_positions_real_rosetta_frame():
    # FA0115: QSZ 49, SCALE 0.01 km; UY points East with cos 0.9975 (fixtures/real/README.md)
    scale, v, ux, uy, uz = read_lmk_frame(REAL / "FA0115.LMK")
    q = 49
    h = np.zeros((2 * q + 1, 2 * q + 1))
    h[q + 3, q - 7] = 2.5
    p = hf.node_positions(h, scale, v, ux, uy, uz)
    np.testing.assert_allclose(p[q, q], v, atol=1e-15)
    # flat nodes lie in the plane through VLM normal to UZ, the raised node 2.5 cells above it (up to
    # the triad's 1e-7 non-orthogonality times the 0.7 km half-diagonal)
    np.testing.assert_allclose((p - v) @ uz - scale * h, 0.0, atol=1e-7 * 0.7)
    assert (p[q + 3, q - 7] - v) @ uz == pytest.approx(0.025, abs=1e-7)
    # corner to corner: 2q cells along UX and along UY
    assert np.linalg.norm(p[-1, q] - p[0, q]) == pytest.approx(2 * q * scale, rel=1e-7)
    assert np.linalg.norm(p[q, -1] - p[q, 0]) == pytest.approx(2 * q * scale, rel=1e-7)
    # stepping along axis 1 (I, along UY) goes East
    east = np.cross([0.0, 0.0, 1.0], uz)
    east /= np.linalg.norm(east)
    step = p[q, q + 1] - p[q, q]
    assert step @ east / np.linalg.norm(step) == pytest.approx(0.9975, abs=5e-5)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), scale=st.floats(1e-5, 10.0), q=st.integers(1, 6))
def test_node_positions_invert_to_node_offsets(seed, scale, q):
    rng = np.random.default_rng(seed)
    ux, uy, uz = random_frame(rng)
    v = rng.normal(size=3) * 100
    h = rng.normal(size=(2 * q + 1, 2 * q + 1)) * 5
    body = hf.node_positions(h, scale, v, ux, uy, uz)
    back = frames.body_to_maplet(body, v, ux, uy, uz, scale)
    np.testing.assert_allclose(back, hf.node_offsets(h), atol=1e-12 * (1 + 100 / scale))


# ------------------------------------------------------------------------------------------------
# slopes: HGT2SLP


def ref_stencil(vals, oks):
    """Pure-Python HGT2SLP row for offsets -2..2 (dicts keyed by offset)."""
    o = oks
    hv = vals
    if o[-1] and o[1]:
        return (hv[1] - hv[-1]) / 2.0, True, 1
    if o[0] and o[-1] and o[2]:
        return (hv[2] + 3.0 * hv[0] - 4.0 * hv[-1]) / 6.0, True, 2
    if o[0] and o[1] and o[-2]:
        return (4.0 * hv[1] - 3.0 * hv[0] - hv[-2]) / 6.0, True, 3
    if o[0] and o[-1] and o[-2]:
        return (3.0 * hv[0] - 4.0 * hv[-1] + hv[-2]) / 2.0, True, 4
    if o[0] and o[1] and o[2]:
        return (-3.0 * hv[0] + 4.0 * hv[1] - hv[2]) / 2.0, True, 5
    if o[0] and o[-1]:
        return hv[0] - hv[-1], True, 6
    if o[0] and o[1]:
        return hv[1] - hv[0], True, 7
    return 0.0, False, 0


def ref_slopes(h, valid):
    n = h.shape[0]
    hx = np.zeros_like(h)
    hy = np.zeros_like(h)
    usable = np.zeros(h.shape, bool)
    for r in range(n):
        for c in range(n):
            res = []
            for axis in (0, 1):
                vals, oks = {}, {}
                for k in range(-2, 3):
                    rr, cc = (r + k, c) if axis == 0 else (r, c + k)
                    inside = 0 <= rr < n and 0 <= cc < n
                    oks[k] = inside and bool(valid[rr, cc])
                    vals[k] = h[rr, cc] if oks[k] else 0.0
                res.append(ref_stencil(vals, oks))
            if res[0][1] and res[1][1]:
                hx[r, c], hy[r, c], usable[r, c] = res[0][0], res[1][0], True
    return hx, hy, usable


# Masks (offsets along one direction that are MISSING) forcing each stencil row at the test node,
# with the analytic value each row must reproduce for a quadratic: rows 1-5 are exact derivatives at
# the node; the 2-point rows 6 and 7 are exact for quadratics only at the midpoint x0 -+ 1/2.
STENCIL_CASES = [
    (1, [], 0.0),
    (2, [+1], 0.0),
    (3, [-1], 0.0),
    (4, [+1, +2], 0.0),
    (5, [-1, -2], 0.0),
    (6, [+1, +2, -2], -0.5),
    (7, [-1, -2, +2], +0.5),
]


@pytest.mark.parametrize("row, missing, shift", STENCIL_CASES)
@pytest.mark.parametrize("axis", [0, 1])
def test_slopes_each_stencil_exact_on_quadratic(row, missing, shift, axis):
    q = 5
    coef = (0.3, 0.7, -1.1, 0.45, -0.35, 0.8)
    X, Y = grid_xy(q)
    h = quadratic(coef, X, Y)
    valid = np.ones_like(h, bool)
    r0, c0 = q + 1, q - 1  # test node at x = 1, y = -1
    for k in missing:
        if axis == 0:
            valid[r0 + k, c0] = False
        else:
            valid[r0, c0 + k] = False
    h_file = np.where(valid, h, 0.0)  # SPC files hold 0 at missing cells
    hx, hy, usable = hf.slopes(h_file, valid)
    x0, y0 = X[r0, c0], Y[r0, c0]
    assert usable[r0, c0]
    # the stencil the reference picks is the one the case was built for
    _, _, ref_row = ref_stencil(
        {k: 0.0 for k in range(-2, 3)},
        {
            k: bool(valid[r0 + k, c0] if axis == 0 else valid[r0, c0 + k]) if 0 <= q + k + 1 else False
            for k in range(-2, 3)
        },
    )
    assert ref_row == row
    if axis == 0:
        assert hx[r0, c0] == pytest.approx(quadratic_dx(coef, x0 + shift, y0), abs=1e-12)
        assert hy[r0, c0] == pytest.approx(quadratic_dy(coef, x0, y0), abs=1e-12)  # central, exact
    else:
        assert hy[r0, c0] == pytest.approx(quadratic_dy(coef, x0, y0 + shift), abs=1e-12)
        assert hx[r0, c0] == pytest.approx(quadratic_dx(coef, x0, y0), abs=1e-12)


def test_slopes_full_grid_exact_including_edges():
    # all valid: central inside, forward (row 5) on the first line, backward (row 4) on the last
    q = 4
    coef = (1.0, -0.4, 0.25, -0.3, 0.55, 0.15)
    X, Y = grid_xy(q)
    hx, hy, usable = hf.slopes(quadratic(coef, X, Y), np.ones(X.shape, bool))
    assert usable.all()
    np.testing.assert_allclose(hx, quadratic_dx(coef, X, Y), atol=1e-12)
    np.testing.assert_allclose(hy, quadratic_dy(coef, X, Y), atol=1e-12)


def test_slopes_sign_is_true_derivative():
    # h rises along UX (axis 0) by 2 per cell and falls along UY by 0.5: SPC would store (-2, +0.5)
    X, Y = grid_xy(3)
    hx, hy, _ = hf.slopes(2 * X - 0.5 * Y, None)
    np.testing.assert_allclose(hx, 2.0, atol=1e-14)
    np.testing.assert_allclose(hy, -0.5, atol=1e-14)


def usable_at_centre(missing_axis0, missing_axis1, centre_valid=True):
    q = 3
    valid = np.ones((2 * q + 1, 2 * q + 1), bool)
    valid[q, q] = centre_valid
    for k in missing_axis0:
        valid[q + k, q] = False
    for k in missing_axis1:
        valid[q, q + k] = False
    X, Y = grid_xy(q)
    hx, hy, usable = hf.slopes(np.where(valid, X * 1.5 - Y, 0.0), valid)
    return bool(usable[q, q]), hx[q, q], hy[q, q]


@pytest.mark.parametrize(
    "missing0, missing1, centre_valid, expected",
    [
        ([], [], True, True),
        ([-1, +1], [], True, False),  # axis 0: only {-2, 0, +2}: no pair (-1,+1), (-1,0), (0,+1)
        ([-1], [+1], True, True),  # (0,+1) along axis 0, (-1,0) along axis 1
        ([], [], False, True),  # own height missing but central pairs valid
        ([-1], [], False, False),  # no own height and -1 missing: (-1,+1) broken, others need 0
        ([+1, +2], [-1, -2], True, True),  # (-1,0) and (0,+1)
        ([], [-1, +1], True, False),
        ([-1, +1], [-1, +1], True, False),
    ],
)
def test_slopes_usability_rule(missing0, missing1, centre_valid, expected):
    usable, hx, hy = usable_at_centre(missing0, missing1, centre_valid)
    assert usable is expected
    if expected:
        assert (hx, hy) == pytest.approx((1.5, -1.0), abs=1e-13)
    else:
        assert (hx, hy) == (0.0, 0.0)


def test_slopes_match_bruteforce_reference_on_random_masks():
    rng = np.random.default_rng(11)
    for _ in range(20):
        n = 2 * int(rng.integers(1, 7)) + 1
        h = rng.normal(size=(n, n)) * 3
        valid = rng.random((n, n)) > rng.uniform(0.05, 0.7)
        got = hf.slopes(np.where(valid, h, 0.0), valid)
        ref = ref_slopes(h, valid)
        np.testing.assert_array_equal(got.usable, ref[2])
        np.testing.assert_allclose(got.hx, ref[0], atol=1e-12)
        np.testing.assert_allclose(got.hy, ref[1], atol=1e-12)


def test_slopes_ignore_garbage_at_missing_cells():
    rng = np.random.default_rng(5)
    h = rng.normal(size=(9, 9))
    valid = rng.random((9, 9)) > 0.3
    a = hf.slopes(np.where(valid, h, 0.0), valid)
    b = hf.slopes(np.where(valid, h, np.nan), valid)
    for u, w in zip(a, b):
        np.testing.assert_array_equal(u, w)


# ------------------------------------------------------------------------------------------------
# normals


def test_normals_tilted_plane_both_frames():
    rng = np.random.default_rng(2)
    a, b = 0.7, -0.3
    X, Y = grid_xy(4)
    h = a * X + b * Y + 2.0
    hx, hy, usable = hf.slopes(h, None)
    assert usable.all()
    nm = hf.normals_maplet(hx, hy)
    expected_m = np.array([-a, -b, 1.0]) / math.sqrt(1 + a * a + b * b)
    np.testing.assert_allclose(nm, np.broadcast_to(expected_m, nm.shape), atol=1e-14)
    for ux, uy, uz in [(LMK_UX, LMK_UY, LMK_UZ), random_frame(rng)]:
        nb = hf.normals_body(hx, hy, ux, uy, uz)
        # independent: normal of the plane through the body-frame node positions
        p = hf.node_positions(h, 0.01, LMK_V, ux, uy, uz)
        t0 = p[1, 0] - p[0, 0]  # step along UX
        t1 = p[0, 1] - p[0, 0]  # step along UY
        cross = np.cross(t0, t1)
        cross /= np.linalg.norm(cross)
        np.testing.assert_allclose(nb, np.broadcast_to(cross, nb.shape), atol=2e-9)  # 10-digit axes
        np.testing.assert_allclose(np.linalg.norm(nb, axis=-1), 1.0, atol=1e-15)


def test_normals_flat_and_unusable_are_uz():
    valid = np.zeros((5, 5), bool)
    valid[2, 2] = True
    hx, hy, usable = hf.slopes(np.ones((5, 5)), valid)
    assert not usable.any()
    nb = hf.normals_body(hx, hy, LMK_UX, LMK_UY, LMK_UZ)
    np.testing.assert_allclose(nb, np.broadcast_to(LMK_UZ / np.linalg.norm(LMK_UZ), nb.shape), atol=1e-15)


# ------------------------------------------------------------------------------------------------
# sampling


def test_sample_heights_hand_case_and_missing_rules():
    h = np.array([[0.0, 2.0, 0.0], [4.0, 8.0, 0.0], [0.0, 0.0, 1.0]])
    valid = np.ones((3, 3), bool)
    # x = -0.5 -> index 0.5 (axis 0), y = -0.25 -> index 0.75 (axis 1): corners 0, 4 (axis 0), 2, 8
    # 0.25 * (0.5*0 + 0.5*4) + 0.75 * (0.5*2 + 0.5*8) = 0.5 + 3.75
    val, ok = hf.sample_heights(h, valid, -0.5, -0.25)
    assert ok and val == pytest.approx(4.25, abs=1e-15)
    # the last node is reachable, outside is not
    val, ok = hf.sample_heights(h, valid, [1.0, 1.0000001, -1.0], [1.0, 0.0, -1.0000001])
    assert ok.tolist() == [True, False, False] and val[0] == 1.0
    # a missing corner invalidates fractional samples using it ...
    valid[1, 1] = False
    val, ok = hf.sample_heights(h, valid, -0.5, -0.25)
    assert not ok and val == 0.0
    # ... but not samples that give it zero weight (on the node (0, 0) = index (1, 0))
    valid2 = np.ones((3, 3), bool)
    valid2[1, 1] = False
    val, ok = hf.sample_heights(h, valid2, [0.0, 0.0, -0.5], [-1.0, -0.5, -1.0])
    assert ok.tolist() == [True, False, True]
    assert val.tolist() == [4.0, 0.0, 2.0]
    # BRT0-style one-corner repair: h11 <- h10 + h01 - h00 = 4 + 2 - 0 = 6
    val, ok = hf.sample_heights(h, valid, -0.5, -0.25, repair_one_corner=True)
    assert ok and val == pytest.approx(0.25 * 2.0 + 0.75 * (0.5 * 2 + 0.5 * 6), abs=1e-15)
    valid[0, 0] = False  # two corners missing: no repair
    val, ok = hf.sample_heights(h, valid, -0.5, -0.25, repair_one_corner=True)
    assert not ok


@settings(max_examples=50, deadline=None)
@given(a=st.floats(-5, 5), b=st.floats(-5, 5), c=st.floats(-5, 5), seed=st.integers(0, 2**32 - 1))
def test_sample_heights_reproduces_planes(a, b, c, seed):
    q = 6
    X, Y = grid_xy(q)
    h = a * X + b * Y + c
    rng = np.random.default_rng(seed)
    x = rng.uniform(-q, q, 200)
    y = rng.uniform(-q, q, 200)
    val, ok = hf.sample_heights(h, None, x, y)
    assert ok.all()
    np.testing.assert_allclose(val, a * x + b * y + c, atol=1e-12)
    # a plane's one missing corner is rebuilt exactly by planar extrapolation
    valid = np.ones(h.shape, bool)
    valid[q, q] = False
    xs = rng.uniform(-0.99, 0.99, 50)
    ys = rng.uniform(-0.99, 0.99, 50)
    val, ok = hf.sample_heights(np.where(valid, h, 0.0), valid, xs, ys, repair_one_corner=True)
    assert ok.all()
    np.testing.assert_allclose(val, a * xs + b * ys + c, atol=1e-12)


def test_bilinear_kernel_agrees_with_sample_heights():
    from spctool.geometry._heightkernels import bilinear_index

    rng = np.random.default_rng(7)
    n, q = 9, 4
    h = rng.normal(size=(n, n))
    valid = rng.random((n, n)) > 0.2
    h = np.where(valid, h, 0.0)
    x = np.concatenate([rng.uniform(-q - 0.5, q + 0.5, 300), rng.integers(-q, q + 1, 50).astype(float)])
    y = np.concatenate([rng.uniform(-q - 0.5, q + 0.5, 300), rng.uniform(-q, q, 50)])
    val, ok = hf.sample_heights(h, valid, x, y)
    for xi, yi, vi, oi in zip(x, y, val, ok):
        kv, ko = bilinear_index(h, valid, xi + q, yi + q)
        assert ko == oi
        if oi:
            assert kv == pytest.approx(vi, abs=1e-14)


# ------------------------------------------------------------------------------------------------
# horizon march


def ref_march(h, valid, direction, tol, nodes=None):
    """Pure-Python brute force of spc-algorithms.md §5.3: every step to the edge, no shortcuts."""
    n = h.shape[0]
    dx, dy, dz = direction
    dxy = math.hypot(dx, dy)
    out = np.zeros((n, n), bool)
    if dxy <= 1e-9 * math.sqrt(dx * dx + dy * dy + dz * dz):
        return out
    su, sw, rise = dx / dxy, dy / dxy, dz / dxy
    for r in range(n):
        for c in range(n):
            if not valid[r, c] or (nodes is not None and not nodes[r, c]):
                continue
            k = 1
            while True:
                u = r + k * su
                w = c + k * sw
                if not (0.0 <= u <= n - 1 and 0.0 <= w <= n - 1):
                    break
                i = min(math.floor(u), n - 2)
                j = min(math.floor(w), n - 2)
                fu, fw = u - i, w - j
                corners = [
                    (i, j, (1 - fu) != 0 and (1 - fw) != 0),
                    (i + 1, j, fu != 0 and (1 - fw) != 0),
                    (i, j + 1, (1 - fu) != 0 and fw != 0),
                    (i + 1, j + 1, fu != 0 and fw != 0),
                ]
                if all(valid[a, b] for a, b, needed in corners if needed):
                    terrain = (1 - fw) * ((1 - fu) * h[i, j] + fu * h[i + 1, j]) + fw * (
                        (1 - fu) * h[i, j + 1] + fu * h[i + 1, j + 1]
                    )
                    if terrain > h[r, c] + k * rise - tol:
                        out[r, c] = True
                        break
                k += 1
    return out


def direction_from(azimuth_deg, elevation_deg):
    """Maplet-frame unit vector: azimuth from +UX toward +UY, elevation above the maplet plane."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


@pytest.mark.parametrize("elevation", [10.0, 20.0, 35.0, 55.0])
@pytest.mark.parametrize("height", [2.0, 5.0])
def test_march_wall_shadow_length_axis_aligned(elevation, height):
    q = 20
    n = 2 * q + 1
    h = np.zeros((n, n))
    wall = slice(30, 33)  # rows (axis 0) 30..32 all columns: a wall across the Sun's path
    h[wall, :] = height
    sun = direction_from(0.0, elevation)  # toward +UX, i.e. increasing axis-0 index
    shadow = hf.march(h, None, sun, tol=0.0)
    expected_len = height / math.tan(math.radians(elevation))
    for c in range(n):
        col = shadow[:, c]
        assert not col[30:].any()  # on and behind the wall (seen from the Sun) nothing is shadowed
        run = 0
        while run < 30 and col[29 - run]:
            run += 1
        assert not col[: 30 - run].any()  # a single contiguous shadow at the wall's foot
        assert abs(run - expected_len) <= 1.0


@pytest.mark.parametrize("azimuth", [20.0, 35.0, -40.0])
def test_march_wall_shadow_length_oblique(azimuth):
    q = 25
    n = 2 * q + 1
    h = np.zeros((n, n))
    h[36:40, :] = 4.0
    elevation = 25.0
    sun = direction_from(azimuth, elevation)
    shadow = hf.march(h, None, sun, tol=0.0)
    # shadow length L = H / tan(el) along the Sun's azimuth, i.e. L cos(az) perpendicular to the wall
    # (along axis 0).  The march samples once per cell *along the ray*, so the first sample on the
    # wall top is up to one step (cos(az) perpendicular) past the wall edge, and nodes are one cell
    # apart: the run of shadowed nodes lies in [L cos(az) - cos(az) - 1, L cos(az) + 1].
    cos_az = math.cos(math.radians(azimuth))
    expected_len = 4.0 * cos_az / math.tan(math.radians(elevation))
    for c in range(12, n - 12):  # away from the side edges where the march leaves the grid early
        col = shadow[:, c]
        run = 0
        while run < 36 and col[35 - run]:
            run += 1
        assert not col[: 36 - run].any()
        assert expected_len - cos_az - 1.0 <= run <= expected_len + 1.0


def test_march_hill_back_slope_blocked_front_not():
    q = 20
    X, Y = grid_xy(q)
    h = 10.0 * np.exp(-(X**2 + Y**2) / (2 * 5.0**2))
    view = direction_from(0.0, 30.0)  # camera toward +UX, 60 degrees emission
    blocked = hf.march(h, None, view, tol=0.05)
    front = X > 0
    assert not blocked[front].any()
    assert blocked[q - 5, q]  # back slope, x = -5: the summit at x = 0 rises 3.9 > 5 tan 30
    assert blocked[X < -1].sum() > 30
    # from the other side the roles swap
    blocked2 = hf.march(h, None, direction_from(180.0, 30.0), tol=0.05)
    assert not blocked2[X < 0].any() and blocked2[q + 5, q]


def test_march_nadir_and_flat_tolerance():
    rng = np.random.default_rng(1)
    h = rng.normal(size=(15, 15)) * 5
    assert not hf.march(h, None, [0.0, 0.0, 1.0]).any()
    assert not hf.march(h, None, [1e-12, -1e-12, 1.0]).any()
    assert not hf.march(h, None, [0.0, 0.0, -1.0]).any()
    # flat terrain: the ray lowered by tol is blocked at k = 1 when the rise per cell is below tol
    flat = np.zeros((9, 9))
    low = direction_from(0.0, math.degrees(math.atan(0.04)))
    high = direction_from(0.0, math.degrees(math.atan(0.06)))
    blocked_low = hf.march(flat, None, low, tol=0.05)
    assert blocked_low[:-1].all() and not blocked_low[-1].any()  # last line has no step inside
    assert not hf.march(flat, None, high, tol=0.05).any()


def test_march_matches_bruteforce_on_random_terrain():
    rng = np.random.default_rng(1234)
    directions = [direction_from(az, el) for az, el in [(0, 20), (90, 15), (180, 30), (270, 8), (45, 25)]]
    directions.append(np.array([0.3, -0.2, -0.05]))  # descending ray, not unit
    for trial in range(12):
        n = 2 * int(rng.integers(3, 9)) + 1
        h = np.cumsum(np.cumsum(rng.normal(size=(n, n)), axis=0), axis=1) * 0.3  # rough terrain
        valid = rng.random((n, n)) > (0.15 if trial % 2 else 0.0)
        nodes = rng.random((n, n)) > 0.3 if trial % 3 == 0 else None
        h = np.where(valid, h, 0.0)
        dirs = directions + [direction_from(rng.uniform(0, 360), rng.uniform(3, 60))]
        for d in dirs:
            tol = float(rng.choice([0.0, 0.05, 0.3]))
            got = hf.march(h, valid, d, tol=tol, nodes=nodes)
            ref = ref_march(h, valid, d, tol, nodes)
            np.testing.assert_array_equal(got, ref)


def test_visibility_and_cast_shadow_wrappers_use_maplet_components():
    rng = np.random.default_rng(9)
    X, Y = grid_xy(8)
    h = 6.0 * np.exp(-(X**2 + Y**2) / 8.0) + 0.2 * rng.normal(size=X.shape)
    valid = np.ones(h.shape, bool)
    d_m = direction_from(130.0, 22.0)
    # body-frame vector with these maplet components in the §4.3 frame
    d_body = d_m[0] * LMK_UX + d_m[1] * LMK_UY + d_m[2] * LMK_UZ
    d_check = np.array([d_body @ LMK_UX, d_body @ LMK_UY, d_body @ LMK_UZ])
    np.testing.assert_allclose(d_check, d_m, atol=1e-9)
    expected = ref_march(h, valid, d_check, 0.05)
    np.testing.assert_array_equal(hf.visibility(h, valid, LMK_UX, LMK_UY, LMK_UZ, d_body), expected)
    np.testing.assert_array_equal(hf.cast_shadows(h, valid, LMK_UX, LMK_UY, LMK_UZ, d_body), expected)
    assert expected.any() and not expected.all()
    m = SimpleNamespace(heights=h, valid=valid, scale=0.001, v=LMK_V, ux=LMK_UX, uy=LMK_UY, uz=LMK_UZ)
    np.testing.assert_array_equal(hf.maplet_visibility(m, d_body), expected)
    np.testing.assert_array_equal(hf.maplet_cast_shadows(m, d_body, tol=0.05), expected)


def test_maplet_wrappers():
    rng = np.random.default_rng(4)
    h = rng.normal(size=(7, 7))
    valid = rng.random((7, 7)) > 0.2
    m = SimpleNamespace(heights=h, valid=valid, scale=0.002, v=LMK_V, ux=LMK_UX, uy=LMK_UY, uz=LMK_UZ)
    np.testing.assert_array_equal(
        hf.maplet_node_positions(m), hf.node_positions(h, 0.002, LMK_V, LMK_UX, LMK_UY, LMK_UZ)
    )
    sl = hf.maplet_slopes(m)
    ref = ref_slopes(np.where(valid, h, 0.0), valid)
    np.testing.assert_allclose(sl.hx, ref[0], atol=1e-12)
    normals, usable = hf.maplet_normals(m)
    np.testing.assert_array_equal(usable, ref[2])
    np.testing.assert_allclose(normals, hf.normals_body(ref[0], ref[1], LMK_UX, LMK_UY, LMK_UZ), atol=1e-14)


def test_bad_shapes_rejected():
    with pytest.raises(ValueError):
        hf.slopes(np.zeros((4, 4)), None)
    with pytest.raises(ValueError):
        hf.slopes(np.zeros((5, 5)), np.ones((3, 3), bool))
    with pytest.raises(ValueError):
        hf.march(np.zeros((5, 5)), None, [1.0, 0.0])
    with pytest.raises(ValueError):
        hf.march(np.zeros((5, 5)), None, [1.0, 0.0, 1.0], nodes=np.ones((4, 4), bool))
    with pytest.raises(ValueError):
        hf.sample_heights(np.zeros((1, 1)), None, 0.0, 0.0)


# ------------------------------------------------------------------------------------------------
# general rays


def test_intersect_rays_hand_cases():
    # tent: one node of height 1 at the centre of a flat 5x5 grid (q = 2)
    h = np.zeros((5, 5))
    h[2, 2] = 1.0
    # along the node line y = 0 the terrain is 1 - |x|: a ray at z = 0.5 from x = -2 hits at x = -0.5
    # off the node line at y = 0.3 it is 0.7 (1 - |x|): crossing at |x| = 2/7
    t = hf.intersect_rays(h, None, [[-2.0, 0.0, 0.5], [-2.0, 0.3, 0.5]], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(t, [1.5, 2.0 - 2.0 / 7.0], atol=1e-12)
    # diagonal through cell (0,0)-(1,1) from node (1, 1) toward the peak: height (1 - s)^2, z = 0.25
    t = hf.intersect_rays(h, None, [1.0, 1.0, 0.25], [-1.0, -1.0, 0.0])
    assert t == pytest.approx(0.5, abs=1e-12)
    # a crossing strictly inside one cell with both cell-edge samples above the terrain:
    # cell with h11 = 1 only; along fu = s, fw = 1 - s the height is s (1 - s) (max 1/4);
    # a level ray at z = 0.21 first meets it at s = 0.3
    g = np.zeros((5, 5))
    g[3, 3] = 1.0
    t = hf.intersect_rays(g, None, [0.0, 1.0, 0.21], [1.0, -1.0, 0.0])
    assert t == pytest.approx(0.3, abs=1e-12)
    t = hf.intersect_rays(g, None, [0.0, 1.0, 0.26], [1.0, -1.0, 0.0])
    assert math.isnan(t)
    # vertical ray onto a plane; hole cells let the ray through
    plane = np.full((5, 5), 2.0)
    assert hf.intersect_rays(plane, None, [0.5, 0.5, 10.0], [0.0, 0.0, -2.0]) == pytest.approx(4.0, abs=1e-12)
    valid = np.ones((5, 5), bool)
    valid[2, 2] = False  # the four cells around the centre become holes
    assert math.isnan(hf.intersect_rays(plane, valid, [0.5, 0.5, 10.0], [0.0, 0.0, -1.0]))
    assert hf.intersect_rays(plane, valid, [1.5, 0.5, 10.0], [0.0, 0.0, -1.0]) == pytest.approx(8.0)
    # start below the surface: hit at t_min; above the highest node going up: miss; t_max respected
    assert hf.intersect_rays(plane, None, [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]) == 0.0
    assert math.isnan(hf.intersect_rays(plane, None, [0.0, 0.0, 3.0], [0.1, 0.0, 1.0]))
    assert math.isnan(hf.intersect_rays(plane, None, [0.5, 0.5, 10.0], [0.0, 0.0, -1.0], t_max=7.9))
    assert hf.intersect_rays(plane, None, [0.5, 0.5, 1.0], [0.0, 0.0, -1.0], t_min=0.5) == 0.5


def test_intersect_rays_body_frame_ray_conversion():
    # a body-frame ray O + t D (km) against a flat maplet 1.5 cells above V in the §4.3 frame:
    # origin 10 m above V along UZ (+ an offset in the plane), D = -UZ tilted:
    # hit at t = (0.01 - 1.5 s) / (D . -UZ)
    scale = 0.0005
    h = np.full((7, 7), 1.5)
    o_body = LMK_V + 0.01 * LMK_UZ + 0.0004 * LMK_UX
    d_body = -LMK_UZ + 0.05 * LMK_UY
    o_m = frames.body_to_maplet(o_body, LMK_V, LMK_UX, LMK_UY, LMK_UZ, scale)
    d_m = hf.to_maplet_components(d_body, LMK_UX, LMK_UY, LMK_UZ) / scale
    t = hf.intersect_rays(h, None, o_m, d_m)
    down = -(d_body @ LMK_UZ)
    assert t == pytest.approx((0.01 - 1.5 * scale) / down, rel=1e-8)


def test_intersect_rays_bruteforce_random_terrain():
    rng = np.random.default_rng(21)
    q = 6
    X, Y = grid_xy(q)
    h = 1.5 * np.sin(X / 1.7) * np.cos(Y / 2.3) + 0.4 * rng.normal(size=X.shape)
    valid = rng.random(h.shape) > 0.1
    h = np.where(valid, h, 0.0)
    m = 250
    origins = np.c_[rng.uniform(-q - 2, q + 2, (m, 2)), rng.uniform(2.0, 6.0, m)]
    dirs = np.c_[rng.normal(size=(m, 2)), -rng.uniform(0.05, 1.5, m)]
    t = hf.intersect_rays(h, valid, origins, dirs)
    assert 40 < np.isfinite(t).sum() < m
    # brute force: 20000 dense samples up to where the ray leaves the grid square; terrain by
    # sample_heights (inside a cell it needs all four corners, as the ray march does)
    hits_wall = 0
    for k in range(m):
        with np.errstate(divide="ignore"):
            t_exit = np.max(np.abs((q + np.abs(origins[k, :2])) / dirs[k, :2]))
        ts = np.linspace(0.0, t_exit, 20001)
        step = ts[1]
        p = origins[k] + ts[:, None] * dirs[k]
        terrain, ok = hf.sample_heights(h, valid, p[:, 0], p[:, 1])
        below = ok & (p[:, 2] < terrain)
        if math.isnan(t[k]):
            assert not below.any()
            continue
        assert below.any()
        first = ts[np.argmax(below)]
        assert first - step - 1e-9 <= t[k] <= first + 1e-9
        hit = origins[k] + t[k] * dirs[k]
        zt, okt = hf.sample_heights(h, valid, hit[0], hit[1])
        pre = hit - 1e-7 * dirs[k]
        zp, okp = hf.sample_heights(h, valid, pre[0], pre[1])
        if okp:  # came from above the surface: the hit is on the surface
            assert okt and pre[2] >= zp - 1e-12
            assert hit[2] == pytest.approx(float(zt), abs=1e-9)
        else:  # came out of a hole or in through the grid's side: a wall hit, below the surface
            hits_wall += 1
            assert hit[2] < float(zt) + 1e-9
    assert hits_wall > 0


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), z0=st.floats(-3.0, 8.0), speed=st.floats(0.01, 100.0))
def test_vertical_rays_hit_the_sampled_height(seed, z0, speed):
    rng = np.random.default_rng(seed)
    q = 4
    h = rng.normal(size=(2 * q + 1, 2 * q + 1))
    valid = rng.random(h.shape) > 0.15
    x = rng.uniform(-q, q, 40)
    y = rng.uniform(-q, q, 40)
    t = hf.intersect_rays(h, valid, np.c_[x, y, np.full(40, z0)], [0.0, 0.0, -speed])
    hv = np.where(valid, h, 0.0)
    zs, ok = hf.sample_heights(hv, valid, x, y)
    full = np.zeros(40, bool)  # the cell (not only the nonzero-weight corners) must be complete
    for k in range(40):
        i = min(int(np.floor(x[k] + q)), 2 * q - 1)
        j = min(int(np.floor(y[k] + q)), 2 * q - 1)
        full[k] = valid[i : i + 2, j : j + 2].all()
    assert np.array_equal(np.isfinite(t), full)
    expected = np.maximum(z0 - zs, 0.0) / speed  # a start below the surface hits at t = 0
    np.testing.assert_allclose(t[full], expected[full], atol=1e-12 * (1 + 1 / speed), rtol=1e-12)


def test_intersect_rays_broadcasting():
    X, Y = grid_xy(3)
    h = 0.2 * X + 0.1 * Y
    origins = np.zeros((2, 4, 3))
    origins[..., 2] = 5.0
    origins[..., 0] = np.linspace(-2, 2, 4)
    t = hf.intersect_rays(h, None, origins, [0.0, 0.0, -1.0])
    assert t.shape == (2, 4)
    np.testing.assert_allclose(t, 5.0 - 0.2 * origins[..., 0], atol=1e-12)


def test_kernel_array_passes_fit_arrays_through_and_copies_the_rest():
    from spctool.geometry.heightfield import kernel_array

    a = np.zeros((3, 4))
    assert kernel_array(a) is a  # already C-contiguous, writeable float64: no copy
    b = np.zeros((4, 3)).T  # Fortran order
    got = kernel_array(b)
    assert got is not b and got.flags.c_contiguous and np.array_equal(got, b)
    r = np.arange(4.0)
    r.flags.writeable = False
    got = kernel_array(r)
    assert got is not r and got.flags.writeable and np.array_equal(got, r)
    f = np.arange(4, dtype=np.float32)
    assert kernel_array(f).dtype == np.float64
    m = np.ones(3, bool)
    assert kernel_array(m, np.bool_) is m
    assert kernel_array([1.0, 2.0]).dtype == np.float64  # a list becomes an array


# ------------------------------------------------------------------------------------------------
# fourth-order node slopes (issue 39: the Monte Carlo's image templates)


def test_fourth_order_slopes_exact_on_quartic_and_spc_where_five_nodes_are_missing():
    q = 6
    X, Y = grid_xy(q)
    h = 0.3 * X**4 - 0.2 * X**3 * Y + 0.1 * X * Y**3 + 0.05 * Y**4 - X**2 + 0.7 * Y  # a quartic
    dx = 1.2 * X**3 - 0.6 * X**2 * Y + 0.1 * Y**3 - 2.0 * X
    dy = -0.2 * X**3 + 0.3 * X * Y**2 + 0.2 * Y**3 + 0.7
    valid = np.ones(h.shape, bool)
    valid[7, 9] = False  # nodes one or two from it along an axis fall back to SPC's slopes (not the
    # node itself: the stencil, like SPC's central difference, does not read the centre)
    spc = hf.slopes(h, valid)
    hx, hy = hf.fourth_order_slopes(h, valid, spc.hx, spc.hy)
    n = h.shape[0]
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    five_x = (i >= 2) & (i <= n - 3) & ~((j == 9) & np.isin(np.abs(i - 7), (1, 2)))
    five_y = (j >= 2) & (j <= n - 3) & ~((i == 7) & np.isin(np.abs(j - 9), (1, 2)))
    np.testing.assert_allclose(hx[five_x], dx[five_x], atol=1e-9)  # exact for quartics
    np.testing.assert_allclose(hy[five_y], dy[five_y], atol=1e-9)
    assert np.array_equal(hx[~five_x], spc.hx[~five_x]) and np.array_equal(hy[~five_y], spc.hy[~five_y])
    # SPC's central difference is not exact there (a quartic): the two differ inside
    assert np.abs(spc.hx[five_x] - dx[five_x]).max() > 0.1
    # the inputs are not modified
    assert not np.shares_memory(hx, spc.hx) and np.array_equal(spc.hx, hf.slopes(h, valid).hx)


def test_fourth_order_slopes_damp_a_wave_as_the_stencil_says():
    # h = sin(k x): the stencil returns (8 sin k − sin 2k)/6 · cos(k x), the central difference
    # sin k · cos(k x); both against the true derivative k cos(k x), worked by hand from the stencils
    q, k = 8, 2.0
    X, Y = grid_xy(q)
    h = np.sin(k * X)
    spc = hf.slopes(h)
    hx, hy = hf.fourth_order_slopes(h, None, spc.hx, spc.hy)
    inner = (slice(2, -2), slice(None))
    np.testing.assert_allclose(
        hx[inner], ((8 * np.sin(k) - np.sin(2 * k)) / 6 * np.cos(k * X))[inner], atol=1e-12
    )
    np.testing.assert_allclose(spc.hx[inner], (np.sin(k) * np.cos(k * X))[inner], atol=1e-12)
    np.testing.assert_allclose(hy, 0.0, atol=1e-12)
    assert (8 * np.sin(k) - np.sin(2 * k)) / 6 / k > np.sin(k) / k  # keeps more of the wave
