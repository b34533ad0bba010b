"""Tests of spctool.geometry.frames: rotations, attitude updates, ORIENT, maplet <-> body."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from spctool.geometry import frames as fr

REAL = Path(__file__).resolve().parents[1] / "fixtures" / "real" / "rosetta-67p"

vec = st.tuples(*[st.floats(-10, 10, allow_nan=False)] * 3).map(np.array)
seeds = st.integers(0, 2**32 - 1)


# ---------------------------------------------------------------- skew


@given(vec, vec)
@settings(max_examples=50, deadline=None)
def test_skew_is_cross_product(v, w):
    k = fr.skew(v)
    np.testing.assert_allclose(k @ w, np.cross(v, w), atol=1e-12)
    np.testing.assert_array_equal(k, -k.T)
    np.testing.assert_allclose(k @ v, 0.0, atol=1e-12)
    np.testing.assert_array_equal(fr.unskew(k), v)


def test_skew_vectorised():
    rng = np.random.default_rng(1)
    v = rng.normal(size=(4, 5, 3))
    w = rng.normal(size=(4, 5, 3))
    k = fr.skew(v)
    assert k.shape == (4, 5, 3, 3)
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", k, w), np.cross(v, w), atol=1e-14)


def test_skew_rejects_wrong_shape():
    with pytest.raises(ValueError):
        fr.skew(np.zeros((3, 2)))


# ---------------------------------------------------------------- rotations


def test_rot2mat_convention_hand_worked():
    r = fr.rot_from_axis_angle([0, 0, 1], np.pi / 2)
    np.testing.assert_allclose(r @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(r @ [0, 1, 0], [-1, 0, 0], atol=1e-15)
    # ROT2MAT written out for axis (1, 1, 1)/√3, θ = 0.3
    u = np.ones(3) / np.sqrt(3)
    th = 0.3
    k = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    expect = np.cos(th) * np.eye(3) + (1 - np.cos(th)) * np.outer(u, u) + np.sin(th) * k
    np.testing.assert_allclose(fr.rot_from_axis_angle([2, 2, 2], th), expect, atol=1e-15)


@given(seeds)
@settings(max_examples=50, deadline=None)
def test_rotvec_matches_scipy_and_axis_angle(seed):
    rng = np.random.default_rng(seed)
    phi = rng.normal(size=3) * rng.choice([1e-9, 1e-5, 1e-2, 1.0, 3.0])
    r = fr.rot_from_rotvec(phi)
    np.testing.assert_allclose(r, Rotation.from_rotvec(phi).as_matrix(), atol=2e-15)
    th = np.linalg.norm(phi)
    np.testing.assert_allclose(r, fr.rot_from_axis_angle(phi, th), atol=2e-15)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-14)
    np.testing.assert_allclose(r @ phi, phi, atol=1e-15 * max(th, 1.0))


@given(seeds)
@settings(max_examples=50, deadline=None)
def test_rotvec_round_trip(seed):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    th = rng.choice([1e-10, 1e-6, 1e-3, 0.5, 2.0, np.pi - 1e-4, np.pi - 1e-9])
    phi = th * u
    back = fr.rotvec_from_rot(fr.rot_from_rotvec(phi))
    # Compare rotations (near π the vector sign can legitimately flip when θ → π).
    np.testing.assert_allclose(fr.rot_from_rotvec(back), fr.rot_from_rotvec(phi), atol=1e-12)
    if th < 3.0:
        np.testing.assert_allclose(back, phi, atol=1e-12, rtol=1e-9)


def test_rotvec_vectorised_shapes():
    rng = np.random.default_rng(3)
    phi = rng.normal(size=(6, 2, 3))
    r = fr.rot_from_rotvec(phi)
    assert r.shape == (6, 2, 3, 3)
    np.testing.assert_allclose(fr.rot_from_rotvec(fr.rotvec_from_rot(r)), r, atol=1e-12)
    assert fr.rodrigues(phi[0, 0]).shape == (3, 3)


def test_orthonormalize():
    rng = np.random.default_rng(5)
    r = Rotation.random(4, random_state=7).as_matrix()
    np.testing.assert_allclose(fr.orthonormalize(r), r, atol=1e-14)
    noisy = r + 1e-6 * rng.normal(size=r.shape)
    o = fr.orthonormalize(noisy)
    np.testing.assert_allclose(o @ np.swapaxes(o, -1, -2), np.broadcast_to(np.eye(3), o.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(o), 1.0, atol=1e-14)
    np.testing.assert_allclose(o, r, atol=1e-5)
    # a reflection is turned into a proper rotation
    refl = np.diag([1.0, 1.0, -1.0]) @ r[0]
    assert np.linalg.det(fr.orthonormalize(refl)) == pytest.approx(1.0)


def test_single_rotation_paths_equal_the_stacked_ones_bit_for_bit():
    """One rotation vector / one matrix take a scalar path (the Monte Carlo perturbs the attitude of
    every sample); it must give the stacked path's values to the last bit, across the Taylor switch."""
    rng = np.random.default_rng(11)
    for scale in (0.0, 1e-9, 5e-5, 1e-4, 2e-4, 1e-3, 0.05, 1.0, 3.0):
        for _ in range(200):
            phi = rng.normal(size=3) * scale
            assert fr.rot_from_rotvec(phi).tobytes() == fr.rot_from_rotvec(phi[None])[0].tobytes()
            r = rng.normal(size=(3, 3))
            assert fr.orthonormalize(r).tobytes() == fr.orthonormalize(r[None])[0].tobytes()
    phi = np.array([1e-4, 0.0, 0.0])  # exactly at the switch
    assert fr.rot_from_rotvec(phi).tobytes() == fr.rot_from_rotvec(phi[None])[0].tobytes()
    assert np.isnan(fr.rot_from_rotvec(np.array([np.nan, 0.0, 0.0]))).all()


@given(seeds)
@settings(max_examples=50, deadline=None)
def test_attitude_update_first_order_and_sign(seed):
    rng = np.random.default_rng(seed)
    t = Rotation.random(random_state=rng.integers(1 << 30)).as_matrix()
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    x_b = rng.normal(size=3)
    for eps in (1e-3, 1e-4):
        dth = eps * d
        tp = fr.apply_attitude_update(t, dth)
        np.testing.assert_allclose(tp @ tp.T, np.eye(3), atol=1e-14)
        first = (np.eye(3) - fr.skew(dth)) @ t  # L15 footnote 13
        assert np.max(np.abs(tp - first)) < eps**2
        # x_C+ − x_C ≈ x_C × δθ = [x_C×]δθ  (erratum 3)
        xc = t @ x_b
        np.testing.assert_allclose(tp @ x_b - xc, np.cross(xc, dth), atol=2 * eps**2 * np.linalg.norm(x_b))
    # exact exponential map: updating by δθ then by −δθ returns to T
    back = fr.apply_attitude_update(fr.apply_attitude_update(t, 0.3 * d), -0.3 * d)
    np.testing.assert_allclose(back, t, atol=1e-14)


# ---------------------------------------------------------------- ORIENT and maplet frame


def test_orient_frame_spec_example():
    # spc-formats.md §4.3: UZ = normalise(0.5, 0.1, 0.2)
    ux, uy, uz = fr.orient_frame([0.5, 0.1, 0.2])
    np.testing.assert_allclose(ux, [0.3580574370, 0.07161148740, -0.9309493363], atol=1e-10)
    np.testing.assert_allclose(uy, [-0.1961161351, 0.9805806757, 0.0], atol=1e-10)
    np.testing.assert_allclose(uz, [0.9128709292, 0.1825741858, 0.3651483717], atol=1e-10)
    np.testing.assert_allclose(np.cross(ux, uy), uz, atol=1e-15)


@given(seeds)
@settings(max_examples=50, deadline=None)
def test_orient_frame_properties(seed):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(20, 3))
    v[:3] = [[1e-5, 2e-5, 1.0], [0.0, 0.0, -3.0], [0.01, -0.015, -1.0]]  # polar branch
    ux, uy, uz = fr.orient_frame(v)
    m = fr.map_to_body_matrix(ux, uy, uz)
    np.testing.assert_allclose(np.swapaxes(m, -1, -2) @ m, np.broadcast_to(np.eye(3), m.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(m), 1.0, atol=1e-14)
    np.testing.assert_allclose(uz, v / np.linalg.norm(v, axis=1, keepdims=True), atol=1e-15)
    pole = np.abs(uz[:, 2]) > fr.POLE_LIMIT
    assert pole[:3].all()
    # away from the poles UY ⟂ ẑ and points East (+ẑ × UZ); UX points South (UX·ẑ ≤ 0)
    assert np.allclose(uy[~pole, 2], 0.0, atol=1e-15)
    east = np.cross([0, 0, 1.0], uz[~pole])
    assert np.all(np.sum(uy[~pole] * east, axis=1) > 0)
    assert np.all(ux[~pole, 2] <= 1e-15)
    # at the poles UY is (0, 1, 0) orthogonalised: in the plane of ŷ and UZ, with positive ŷ component
    assert np.all(uy[pole, 1] > 0)
    np.testing.assert_allclose(np.sum(np.cross(uy[pole], [0, 1.0, 0]) * uz[pole], axis=1), 0.0, atol=1e-15)


def _lmk_axes(path):
    vals = {}
    for line in path.read_text().splitlines()[4:8]:
        tag = line[60:].strip()
        vals[tag] = np.array([float(t.replace("D", "E")) for t in line[:60].split()])
    return vals["VLM"], vals["UX"], vals["UY"], vals["UZ"]


def test_orient_frame_against_real_rosetta_lmk():
    # spc-formats.md §1.2: cos(UY_file, normalise(ẑ × UZ)) = 0.9975, 1.0000, 0.925
    for name, expect in (("FA0115", 0.9975), ("FC0098", 1.0000), ("GD0036", 0.925)):
        _, ux, uy, uz = _lmk_axes(REAL / f"{name}.LMK")
        oux, ouy, ouz = fr.orient_frame(uz)
        assert float(uy @ ouy) == pytest.approx(expect, abs=6e-4)
        assert float(ux @ oux) == pytest.approx(expect, abs=6e-4)  # same rotation about UZ
        np.testing.assert_allclose(np.cross(ux, uy), uz, atol=1e-7)


@given(seeds)
@settings(max_examples=50, deadline=None)
def test_maplet_body_round_trip(seed):
    rng = np.random.default_rng(seed)
    ux, uy, uz = fr.orient_frame(rng.normal(size=3))
    v = rng.normal(size=3) * 2
    scale = 10 ** rng.uniform(-5, -1)
    cells = rng.uniform(-49, 49, size=(7, 3))
    p = fr.maplet_to_body(cells, v, ux, uy, uz, scale)
    # written out per point
    for c, pk in zip(cells, p):
        np.testing.assert_allclose(
            pk, v + scale * (c[0] * ux + c[1] * uy + c[2] * uz), rtol=1e-15, atol=1e-15
        )
    np.testing.assert_allclose(fr.body_to_maplet(p, v, ux, uy, uz, scale), cells, atol=1e-9)
    # the map→body matrix has the axes as columns
    m = fr.map_to_body_matrix(ux, uy, uz)
    np.testing.assert_allclose(v + scale * (cells @ m.T), p, atol=1e-15)


def test_maplet_grid_layout():
    # axis 0 = J steps along UX; axis 1 = I steps along UY (spc-formats.md §1.3 NumPy recipe)
    ux, uy, uz = fr.orient_frame([0.5, 0.1, 0.2])
    q = 2
    j, i = np.meshgrid(np.arange(-q, q + 1), np.arange(-q, q + 1), indexing="ij")
    h = np.zeros_like(j, dtype=float)
    p = fr.maplet_to_body(np.stack([j, i, h], axis=-1), np.zeros(3), ux, uy, uz, 0.01)
    np.testing.assert_allclose(p[q + 1, q] - p[q, q], 0.01 * ux, atol=1e-16)
    np.testing.assert_allclose(p[q, q + 1] - p[q, q], 0.01 * uy, atol=1e-16)


# ---------------------------------------------------------------- angle helpers


def test_angle_between_and_illumination():
    assert fr.angle_between([1, 0, 0], [0, 1, 0]) == pytest.approx(np.pi / 2)
    assert fr.angle_between([1, 0, 0], [1, 1e-12, 0]) == pytest.approx(1e-12, rel=1e-9)
    assert fr.angle_between([1, 0, 0], [-1, 1e-12, 0]) == pytest.approx(np.pi - 1e-12, rel=1e-15)
    # surface point at the origin, normal +z, Sun at 60° incidence, spacecraft overhead at 10 km
    mu0, mu, cph = fr.illumination_cosines(
        [0, 0, 0], [0, 0, 2.0], [np.sin(np.pi / 3), 0, np.cos(np.pi / 3)], [0, 0, 10.0]
    )
    assert mu0 == pytest.approx(0.5)
    assert mu == pytest.approx(1.0)
    assert cph == pytest.approx(0.5)
