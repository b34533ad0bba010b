"""Tests of spctool.geometry.camera against independent computations.

* projection vs a plain per-point re-derivation of spc-formats.md §2.5 + §6.4 written below;
* every Jacobian vs central finite differences (attitude through frames.apply_attitude_update);
* inverse∘forward over the whole detector;
* peers.md §5 OWEN reference vectors (GIANT 2.0.0 output);
* real Rosetta 67P data (spc-formats.md §2.5 real-data check) and the §2.6 worked example.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from spctool.errors import SpcUsageError
from spctool.formats.landmark import read_lmk
from spctool.formats.lithos import parse_lithos
from spctool.formats.sumfile import parse_sum, read_sum
from spctool.geometry.camera import Camera
from spctool.geometry.frames import apply_attitude_update, maplet_to_body, orient_frame, rot_from_rotvec

REAL = Path(__file__).resolve().parents[1] / "fixtures" / "real" / "rosetta-67p"
seeds = st.integers(0, 2**32 - 1)
MODELS = ["NONE", "OWEN", "RADIAL", "CUBIC", "APOLLO", "HIRISE", "LINESCAN"]


# ------------------------------------------------------------------------------------------------
# independent re-derivation (plain Python, one point at a time, straight from the spec text)
# ------------------------------------------------------------------------------------------------


def reference_pixel(cam_args, p):
    """spc-formats.md §2.5 steps 1–5 with the §6.4 models, for one body-fixed point p."""
    scobj, rot = cam_args["scobj"], cam_args["rotation"]
    u = [scobj[i] + p[i] for i in range(3)]
    z = [sum(rot[k][i] * u[i] for i in range(3)) for k in range(3)]
    mmfl = cam_args["mmfl"]
    model = cam_args.get("model", "NONE")
    pc = list(cam_args.get("coefficients", [])) + [0.0] * 21
    if model == "NONE":
        x = mmfl * z[0] / z[2]
        y = mmfl * z[1] / z[2]
    else:
        x = (1 + pc[0]) * mmfl * z[0] / z[2]
        y = (1 + pc[0]) * mmfl * z[1] / z[2]
        r = math.sqrt(x * x + y * y)
        if model == "OWEN":
            x, y = (
                x
                - pc[1] * y * r
                + pc[2] * x * r**2
                - pc[3] * y * r**3
                + pc[4] * x * r**4
                + pc[5] * x * y
                + pc[6] * x**2,
                y
                + pc[1] * x * r
                + pc[2] * y * r**2
                + pc[3] * x * r**3
                + pc[4] * y * r**4
                + pc[5] * y**2
                + pc[6] * x * y,
            )
        elif model == "RADIAL":
            x, y = x * (1 + pc[1] * r**2 + pc[2] * r**4), y * (1 + pc[1] * r**2 + pc[2] * r**4)
        elif model == "CUBIC":
            m = [1, x, y, x * x, x * y, y * y, x**3, x * x * y, x * y * y, y**3]
            x, y = (
                sum(pc[k] * m[k - 1] for k in range(1, 11)),
                sum(pc[k + 10] * m[k - 1] for k in range(1, 11)),
            )
        elif model == "APOLLO":
            rho = r * r
            f = 1 + pc[1] * rho + pc[2] * rho**2 + pc[3] * rho**3
            x, y = x * f, y * f
            t = pc[4] * rho + pc[5] * rho**2
            x += t * math.sin(pc[6])
            y -= t * math.cos(pc[6])
        elif model == "HIRISE":
            x, y = x - pc[1], y - pc[2]
        elif model == "LINESCAN":
            y = mmfl * z[1] / z[2]
            big_r = math.sqrt(x * x + pc[1] ** 2)
            x = x * (1 + pc[2] * big_r**2 + pc[3] * big_r**3)
    d = cam_args.get("legacy_d", [0, 0, 0, 0])
    x, y = x * (1 + d[0]), y * (1 + d[0])
    if d[1] != 0 or d[2] != 0 or d[3] != 0:
        s = 1 + d[1] * (x * x + y * y) + d[2] * y + d[3] * x
        x, y = s * x, s * y
    k, c = cam_args["kmatrix"], cam_args["ctr"]
    return (
        c[0] + k[0][0] * x + k[0][1] * y + k[0][2] * x * y,
        c[1] + k[1][0] * x + k[1][1] * y + k[1][2] * x * y,
    )


# ------------------------------------------------------------------------------------------------
# random cameras and scenes
# ------------------------------------------------------------------------------------------------


def random_coefficients(rng, model):
    sgn = lambda: rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 1.5)  # noqa: E731
    if model == "NONE":
        return []
    if model == "OWEN":  # all seven non-zero, magnitudes like peers.md §5 (a few px of distortion)
        return [
            sgn() * 1e-3,
            sgn() * 3e-5,
            sgn() * 1e-4,
            sgn() * 2e-7,
            sgn() * 1e-6,
            sgn() * 1.5e-5,
            sgn() * 2e-5,
        ]
    if model == "RADIAL":
        return [sgn() * 1e-3, sgn() * 1e-4, sgn() * 1e-6]
    if model == "CUBIC":
        p = np.concatenate([[sgn() * 1e-3], sgn() * 1e-3 * rng.uniform(size=20) * rng.choice([-1, 1], 20)])
        p[1:11] *= [1e1, 1, 1, 1e-2, 1e-2, 1e-2, 1e-4, 1e-4, 1e-4, 1e-4]
        p[11:21] *= [1e1, 1, 1, 1e-2, 1e-2, 1e-2, 1e-4, 1e-4, 1e-4, 1e-4]
        p[2] += 1.0
        p[13] += 1.0
        return list(p)
    if model == "APOLLO":
        return [
            sgn() * 1e-3,
            sgn() * 1e-4,
            sgn() * 1e-6,
            sgn() * 1e-8,
            sgn() * 1e-4,
            sgn() * 1e-6,
            rng.uniform(0, 6.28),
        ]
    if model == "HIRISE":
        return [sgn() * 1e-3, sgn() * 0.05, sgn() * 0.05]
    if model == "LINESCAN":
        return [sgn() * 1e-3, sgn() * 2.0, sgn() * 1e-4, sgn() * 1e-5]
    raise AssertionError(model)


def random_camera_args(rng, model="OWEN"):
    """A camera with K cross terms, K x·y terms, legacy D1…D4 and the given distortion model."""
    kx = rng.uniform(60, 140)
    ky = rng.choice([-1.0, 1.0]) * rng.uniform(60, 140)
    rot = rot_from_rotvec(rng.normal(size=3))
    return dict(
        mmfl=rng.uniform(60, 150),
        ctr=[rng.uniform(480, 540), rng.uniform(480, 540)],
        kmatrix=[
            [kx, rng.uniform(-3, 3), rng.uniform(-0.3, 0.3)],
            [rng.uniform(-3, 3), ky, rng.uniform(-0.3, 0.3)],
        ],
        legacy_d=[
            rng.uniform(-1e-3, 1e-3),
            rng.uniform(-5e-5, 5e-5),
            rng.uniform(-2e-4, 2e-4),
            rng.uniform(-2e-4, 2e-4),
        ],
        model=model,
        coefficients=random_coefficients(rng, model),
        rotation=rot,
        scobj=rng.normal(size=3) * 5,
        npx=1024,
        nln=1024,
    )


def scene_points(rng, cam_args, n, fov_fraction=1.0):
    """Body-fixed points in front of the camera spread over ≈ the field of view."""
    half = 1024 / (2 * 140 * cam_args["mmfl"]) * fov_fraction
    xn = rng.uniform(-half, half, n)
    yn = rng.uniform(-half, half, n)
    depth = rng.uniform(2, 20, n)
    zc = np.stack([xn * depth, yn * depth, depth], axis=1)
    rot = np.asarray(cam_args["rotation"])
    return zc @ rot - np.asarray(cam_args["scobj"])


# ------------------------------------------------------------------------------------------------
# projection
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", MODELS)
@given(seed=seeds)
@settings(max_examples=15, deadline=None)
def test_projection_matches_independent_formula(model, seed):
    rng = np.random.default_rng(seed)
    args = random_camera_args(rng, model)
    cam = Camera(**args)
    pts = scene_points(rng, args, 40, fov_fraction=1.1)
    smp, lin = cam.project(pts)
    ref = np.array([reference_pixel(args, p) for p in pts])
    np.testing.assert_allclose(smp, ref[:, 0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(lin, ref[:, 1], rtol=0, atol=1e-9)
    # the camera-frame entry point agrees with the body-frame one
    s2, l2 = cam.project_camera_frame(cam.to_camera(pts))
    np.testing.assert_allclose(s2, smp, atol=1e-9)
    np.testing.assert_allclose(l2, lin, atol=1e-9)


def test_peers_owen_reference_vectors():
    # peers.md §5: GIANT 2.0.0 OwenModel output (+1 for SPC 1-based pixels)
    cam = Camera(
        mmfl=100.0,
        ctr=[512.5, 512.5],
        kmatrix=[[100, 0, 0], [0, 100, 0]],
        rotation=np.eye(3),
        scobj=np.zeros(3),
        npx=1024,
        nln=1024,
        model="OWEN",
        coefficients=[0, 3e-5, 1e-4, -2e-7, -1e-6, -1.5e-5, 2e-5],
    )
    # fmt: off
    rows = [  # x_C, y_C, z_C (km); undistorted x, y (mm); sample, line
        (-0.1018536534878839, 0.08586754111305335, 3.046024202204527, -3.343822857, 2.819003902,
         177.604684, 794.767415),
        (0.1995900756928282, -0.1163250301959087, 3.850825057387776, 5.183047080, -3.020782000,
         1032.117259, 209.751803),
        (-0.4232469471856701, 0.4063777084016465, 8.176289115994607, -5.176516402, 4.970197392,
         -6.422687, 1010.599478),
        (-0.09766365858396378, -0.1678580411667185, 4.519985955417181, -2.160707125, -3.713685016,
         296.143328, 140.543439),
        (-0.02801972788609037, -0.08006322092929616, 2.68060767043342, -1.045275226, -2.986756392,
         407.902254, 213.538837),
    ]
    # fmt: on
    rows = np.array(rows)
    zc = rows[:, :3]
    smp, lin = cam.project_camera_frame(zc)
    np.testing.assert_allclose(smp, rows[:, 5], atol=1e-6)
    np.testing.assert_allclose(lin, rows[:, 6], atol=1e-6)
    np.testing.assert_allclose(100 * zc[:, 0] / zc[:, 2], rows[:, 3], atol=1e-9)
    # body-frame entry with the identity pose gives the same
    s2, l2 = cam.project(zc)
    np.testing.assert_allclose(s2, rows[:, 5], atol=1e-6)
    assert not cam.in_image(smp, lin)[2]  # row 3 lies outside: no clipping
    assert cam.in_image(smp, lin)[[0, 3, 4]].all()
    # and the inverse returns the directions
    d = cam.pixel_to_camera_direction(rows[:, 5], rows[:, 6])
    np.testing.assert_allclose(d, zc / np.linalg.norm(zc, axis=1, keepdims=True), atol=1e-9)


def test_spec_worked_example():
    # spc-formats.md §2.6: AB0001 at (0.5, 0.1, 0.2) km -> (565.13, 407.24)
    cam = Camera(
        mmfl=50.0,
        ctr=[512.5, 512.5],
        kmatrix=[[100, 0, 0], [0, 100, 0]],
        rotation=[[0, 1, 0], [0, 0, -1], [-1, 0, 0]],
        scobj=[-10, 0, 0],
        npx=1024,
        nln=1024,
    )
    np.testing.assert_allclose(cam.to_camera([0.5, 0.1, 0.2]), [0.1, -0.2, 9.5], atol=1e-15)
    smp, lin = cam.project([0.5, 0.1, 0.2])
    assert smp == pytest.approx(565.13, abs=0.005)
    assert lin == pytest.approx(407.24, abs=0.005)
    assert cam.position.tolist() == [10, 0, 0]
    assert cam.ifov == pytest.approx(1 / 5000)
    np.testing.assert_allclose(cam.half_fov, (1024 / 10000, 1024 / 10000))
    np.testing.assert_array_equal(cam.boresight, [-1, 0, 0])
    assert cam.in_front([0.5, 0.1, 0.2]) and not cam.in_front([20.0, 0, 0])
    assert cam.resolution([0.0, 0, 0]) == pytest.approx(10 / 5000)
    assert cam.resolution([0.0, 0, 0], normals=[1.0, 1.0, 0]) == pytest.approx(10 / 5000 * np.sqrt(2))


def test_in_image_bounds():
    cam = Camera(
        mmfl=50.0,
        ctr=[512.5, 512.5],
        kmatrix=[[100, 0, 0], [0, 100, 0]],
        rotation=np.eye(3),
        scobj=np.zeros(3),
        npx=1024,
        nln=800,
    )
    s = np.array([1.0, 1024.0, 0.999, 1024.001, 500, 500, 500])
    ln = np.array([1.0, 800.0, 5, 5, 0.5, 800.5, 400])
    np.testing.assert_array_equal(cam.in_image(s, ln), [True, True, False, False, False, False, True])


# ------------------------------------------------------------------------------------------------
# Jacobians vs central finite differences
# ------------------------------------------------------------------------------------------------


def _check(analytic, numeric, rel=1e-6):
    analytic = np.asarray(analytic)
    numeric = np.asarray(numeric)
    scale = np.max(np.abs(numeric), axis=tuple(range(1, numeric.ndim)), keepdims=True)
    err = np.abs(analytic - numeric) / scale
    assert np.max(err) < rel, f"max relative error {np.max(err):.3g}"


def _fd(fun, x0, h):
    """Central differences of fun (-> (sample, line) arrays of N) wrt each of x0's k components: (N, 2, k)."""
    cols = []
    for k in range(x0.shape[-1]):
        e = np.zeros(x0.shape[-1])
        e[k] = h
        sp, lp = fun(x0 + e)
        sm, lm = fun(x0 - e)
        cols.append(np.stack([(sp - sm) / (2 * h), (lp - lm) / (2 * h)], axis=-1))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("model", MODELS)
@given(seed=seeds)
@settings(max_examples=12, deadline=None)
def test_jacobians_match_finite_differences(model, seed):
    rng = np.random.default_rng(seed)
    args = random_camera_args(rng, model)
    cam = Camera(**args)
    pts = scene_points(rng, args, 12, fov_fraction=1.05)

    # spacecraft position (body frame); SCOBJ = −position
    jpos = _fd(lambda q: cam.with_pose(position=q).project(pts), cam.position, 1e-4)
    _check(cam.jacobian_position(pts), jpos)

    # attitude: the same update function the pose solver uses, T+ = Rot(−δθ)·T
    jatt = _fd(
        lambda d: cam.with_pose(rotation=apply_attitude_update(cam.rotation, d)).project(pts),
        np.zeros(3),
        1e-6,
    )
    _check(cam.jacobian_attitude(pts), jatt)

    # landmark position, one point at a time
    jpt = np.stack([_fd(lambda q: cam.project(q[None]), p, 1e-4)[0] for p in pts])
    _check(cam.jacobian_point(pts), jpt)

    # camera-frame Jacobian
    zc = cam.to_camera(pts)
    jcam = np.stack([_fd(lambda q: cam.project_camera_frame(q[None]), z, 1e-5)[0] for z in zc])
    _check(cam.pixel_jacobian_camera(zc), jcam)

    # maplet offsets in cells: x along UX, y along UY
    ux, uy, uz = orient_frame(rng.normal(size=3))
    scale = 1e-3
    jm = _fd(lambda c: cam.project(maplet_to_body(c, pts, ux, uy, uz, scale)), np.zeros(3), 1e-2)[:, :, :2]
    _check(cam.jacobian_maplet(pts, ux, uy, scale), jm)

    # one-pass bundle agrees with the separate calls
    bundle = cam.project_with_jacobians(pts)
    np.testing.assert_allclose(bundle.position, cam.jacobian_position(pts), rtol=1e-14, atol=0)
    np.testing.assert_allclose(bundle.attitude, cam.jacobian_attitude(pts), rtol=1e-14, atol=0)
    np.testing.assert_allclose(
        np.stack([bundle.sample, bundle.line], -1), np.stack(cam.project(pts), -1), atol=1e-10
    )
    assert cam.jacobian_pose(pts).shape == (12, 2, 6)

    # focal-plane derivative
    xn, yn = zc[:, 0] / zc[:, 2], zc[:, 1] / zc[:, 2]
    _, _, jf = cam.focal_to_pixel(xn, yn, jacobian=True)
    jfd = _fd(lambda q: cam.focal_to_pixel(q[..., 0], q[..., 1]), np.stack([xn, yn], -1), 1e-7)
    _check(jf, jfd)


def test_jacobian_shapes_and_pinwheel_at_principal_point():
    rng = np.random.default_rng(11)
    args = random_camera_args(rng, "OWEN")
    cam = Camera(**args)
    pts = scene_points(rng, args, 24).reshape(4, 6, 3)
    assert cam.jacobian_position(pts).shape == (4, 6, 2, 3)
    assert cam.jacobian_maplet(pts, [1, 0, 0], [0, 1, 0], 0.01).shape == (4, 6, 2, 2)
    assert cam.project(pts)[0].shape == (4, 6)
    # exactly on the optical axis r = 0: the r-pinwheel term has a finite derivative there
    j = cam.pixel_jacobian_camera([[0.0, 0.0, 5.0]])
    assert np.all(np.isfinite(j))
    jfd = _fd(lambda q: cam.project_camera_frame(q[None]), np.array([0.0, 0.0, 5.0]), 1e-7)
    # y·r and x·r are differentiable at r = 0 with zero derivative, so the check stays tight
    _check(j, jfd)
    # and a subnormal r does not overflow
    assert np.all(np.isfinite(cam.pixel_jacobian_camera([[1e-320, -1e-320, 1.0]])))


# ------------------------------------------------------------------------------------------------
# inverse
# ------------------------------------------------------------------------------------------------


def _detector_grid(npx, nln, n=41):
    s, ln = np.meshgrid(np.linspace(1, npx, n), np.linspace(1, nln, n), indexing="ij")
    return s.ravel(), ln.ravel()


def _no_preimage(cam, sample, line) -> bool:
    """True when no focal-plane point within the distortion's fold maps to (sample, line): scipy's
    least squares, started from the best of a coarse brute-force grid, stays > 1e-3 px away."""
    from scipy.optimize import least_squares

    half = max(cam.npx, cam.nln) / cam.mmfl / 40.0  # beyond any field of view the tests draw
    g = np.linspace(-half, half, 401)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    s, ln = cam.focal_to_pixel(x, y)
    i = np.nanargmin(np.hypot(s - sample, ln - line))

    def residual(p):
        ps, pl = cam.focal_to_pixel(np.array([p[0]]), np.array([p[1]]))
        return np.array([ps[0] - sample, pl[0] - line])

    fit = least_squares(residual, [x[i], y[i]], xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return bool(np.hypot(*fit.fun) > 1e-3)


def test_no_preimage_finds_a_pixel_that_has_one():
    cam = Camera(**random_camera_args(np.random.default_rng(79693), "APOLLO"))
    assert _no_preimage(cam, 1.0, 1024.0)  # past the fold: no preimage
    assert not _no_preimage(cam, 30.0, 1000.0)  # inside it: found


@pytest.mark.parametrize("model", MODELS)
@given(seed=seeds)
@settings(max_examples=10, deadline=None)
@example(seed=79693)
def test_inverse_round_trip_whole_detector(model, seed):
    rng = np.random.default_rng(seed)
    args = random_camera_args(rng, model)
    cam = Camera(**args)
    s, ln = _detector_grid(cam.npx, cam.nln)
    xn, yn, nit = cam.pixel_to_focal(s, ln, return_iterations=True)
    none = ~np.isfinite(xn)
    assert np.array_equal(none, ~np.isfinite(yn))
    # a strong random distortion can fold before a detector corner (APOLLO, seed 79693): a NaN is right
    # only where the forward model truly has no preimage, which an independent solver confirms
    for ps, pl in zip(s[none], ln[none]):
        assert _no_preimage(cam, ps, pl), (ps, pl)
    assert none.mean() <= 0.01
    s, ln, xn, yn = s[~none], ln[~none], xn[~none], yn[~none]
    assert nit[~none].max() <= 12
    s2, l2 = cam.focal_to_pixel(xn, yn)
    assert np.max(np.abs(s2 - s)) <= 1e-8 and np.max(np.abs(l2 - ln)) <= 1e-8
    # through the body frame: a point along the returned line of sight projects back to the pixel
    d = cam.pixel_to_direction(s, ln)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-15)
    s3, l3 = cam.project(cam.position + 7.0 * d)
    assert np.max(np.abs(s3 - s)) <= 1e-8 and np.max(np.abs(l3 - ln)) <= 1e-8
    dc = cam.pixel_to_camera_direction(s, ln)
    assert np.all(dc[:, 2] > 0)
    np.testing.assert_allclose(dc @ cam.rotation, d, atol=1e-15)


def test_inverse_reports_non_invertible_pixels():
    # CUBIC with x' = x² (P4 = 1), y' = y (P13 = 1): samples left of CTR1 (x' < 0) have no preimage
    coef = np.zeros(21)
    coef[4] = 1.0
    coef[13] = 1.0
    cam = Camera(
        mmfl=100.0,
        ctr=[512.5, 512.5],
        kmatrix=[[100, 0, 0], [0, 100, 0]],
        rotation=np.eye(3),
        scobj=np.zeros(3),
        npx=1024,
        nln=1024,
        model="CUBIC",
        coefficients=coef,
    )
    xn, yn = cam.pixel_to_focal([612.5, 412.5], [512.5, 600.0])
    assert xn[0] == pytest.approx(0.01, rel=1e-9) and yn[0] == pytest.approx(0.0, abs=1e-15)
    assert np.isnan(xn[1]) and np.isnan(yn[1])
    assert np.isnan(cam.pixel_to_direction(412.5, 600.0)).all()


def test_inverse_vectorised_shapes():
    cam = Camera(**random_camera_args(np.random.default_rng(2), "OWEN"))
    s = np.full((3, 4), 300.0)
    assert cam.pixel_to_direction(s, 700.0).shape == (3, 4, 3)
    assert cam.pixel_to_focal(300.0, 700.0)[0].shape == ()


# ------------------------------------------------------------------------------------------------
# construction
# ------------------------------------------------------------------------------------------------


def test_pose_copies_and_validation():
    args = random_camera_args(np.random.default_rng(4), "OWEN")
    cam = Camera(**args)
    moved = cam.with_pose(position=[1.0, 2.0, 3.0])
    np.testing.assert_array_equal(moved.scobj, [-1.0, -2.0, -3.0])
    np.testing.assert_array_equal(moved.rotation, cam.rotation)
    np.testing.assert_array_equal(cam.scobj, args["scobj"])  # original untouched
    up = cam.updated(dposition=[0.1, 0, 0], dtheta=[0, 0, 1e-3])
    np.testing.assert_allclose(up.position, cam.position + [0.1, 0, 0])
    np.testing.assert_allclose(up.rotation, apply_attitude_update(cam.rotation, [0, 0, 1e-3]))
    with pytest.raises(SpcUsageError):
        cam.with_pose(position=[0, 0, 0], scobj=[0, 0, 0])
    with pytest.raises(SpcUsageError):
        Camera(**{**args, "model": "USGS"})
    with pytest.raises(SpcUsageError):
        Camera(**{**args, "kmatrix": np.eye(2)})
    assert Camera(**{**args, "model": "owen"}).model == "OWEN"
    assert not cam.scobj.flags.writeable


class _Pic:
    """Duck-typed stand-in with the Picture fields Camera.from_picture reads."""

    def __init__(self, args, distortion):
        self.name = "N1234567890A"
        self.npx, self.nln = args["npx"], args["nln"]
        self.mmfl, self.ctr, self.kmatrix = args["mmfl"], np.array(args["ctr"]), np.array(args["kmatrix"])
        self.scobj = np.array(args["scobj"])
        self.cx, self.cy, self.cz = np.asarray(args["rotation"])
        self.distortion = distortion

    @property
    def rotation(self):
        return np.vstack([self.cx, self.cy, self.cz])


class _Dm:
    def __init__(self, model, coefficients):
        self.model, self.order, self.coefficients = model, len(coefficients) - 1, np.array(coefficients)


class _Settings:
    def __init__(self, dm):
        self.dm = dm

    def distortion_for(self, name):
        return self.dm if name.startswith("N") else None


def test_from_picture_duck_typed():
    args = random_camera_args(np.random.default_rng(9), "OWEN")
    pic = _Pic(args, np.array(args["legacy_d"]))
    cam = Camera.from_picture(pic, _Settings(_Dm("OWEN", args["coefficients"])))
    pts = scene_points(np.random.default_rng(1), args, 10)
    np.testing.assert_allclose(
        np.stack(cam.project(pts), -1), np.stack(Camera(**args).project(pts), -1), atol=1e-12
    )
    plain = Camera.from_picture(_Pic(args, None))
    assert plain.model == "NONE" and not plain.legacy_d.any()


# ------------------------------------------------------------------------------------------------
# real data: Rosetta 67P (spc-formats.md §2.5 real-data check)
# ------------------------------------------------------------------------------------------------


def _read_real():
    """Picture (via formats.sumfile) and the landmark VLMs (via formats.landmark)."""
    pic = read_sum(REAL / "W48230079013.SUM")
    cam = Camera.from_picture(pic)
    meas = {m.name: (m.sample, m.line) for m in pic.landmarks}
    vlm = {n: np.asarray(read_lmk(REAL / f"{n}.LMK").vlm) for n in ("FA0115", "FC0098", "GD0036")}
    return cam, meas, vlm


def test_rosetta_landmarks_project_near_measured_pixels():
    cam, meas, vlm = _read_real()
    expected = {"FA0115": (0.83, 1.11), "FC0098": (0.04, 0.45), "GD0036": (-0.79, 0.17)}
    names = list(expected)
    smp, lin = cam.project(np.stack([vlm[n] for n in names]))
    for i, n in enumerate(names):
        ds, dl = smp[i] - meas[n][0], lin[i] - meas[n][1]
        assert abs(ds) < 1.5 and abs(dl) < 1.5
        assert ds == pytest.approx(expected[n][0], abs=0.006)
        assert dl == pytest.approx(expected[n][1], abs=0.006)
    assert cam.in_front(np.stack([vlm[n] for n in names])).all()
    # inverse: the measured pixel's line of sight passes within a pixel footprint of the VLM
    d = cam.pixel_to_direction([meas[n][0] for n in names], [meas[n][1] for n in names])
    for i, n in enumerate(names):
        los = vlm[n] - cam.position
        miss = np.linalg.norm(np.cross(los, d[i]))
        assert miss < 1.5 * np.linalg.norm(los) * cam.ifov * 1.01


def test_from_picture_with_real_readers_and_distort_template():
    # spc-formats.md §2.6 example SUM + an INIT_LITHOS DISTORT= entry matching its name ('X#…', §6.5)
    sum_text = """X123456789A1
2021 MAR 04 12:34:56.789
  1024  1024   100  4095                                       NPX, NLN, THRSH
    0.5000000000D+02    0.5125000000D+03    0.5125000000D+03   MMFL, CTR
   -0.1000000000D+02    0.0000000000D+00    0.0000000000D+00   SCOBJ
    0.0000000000D+00    0.1000000000D+01    0.0000000000D+00   CX
    0.0000000000D+00    0.0000000000D+00   -0.1000000000D+01   CY
   -0.1000000000D+01    0.0000000000D+00    0.0000000000D+00   CZ
    0.8000000000D+00    0.6000000000D+00    0.0000000000D+00   SZ
 100.00000   0.00000   0.00000   0.00000 100.00000   0.00000   K-MATRIX
    0.00000D+00    0.00000D+00    0.00000D+00    0.00000D+00   DISTORTION
    0.1000000000D-01    0.1000000000D-01    0.1000000000D-01   SIGMA_VSO
    0.1000000000D-03    0.1000000000D-03    0.1000000000D-03   SIGMA_PTG
LANDMARKS
AB0001    565.13    407.24
AB0002    601.77    388.02
LIMB FITS
END FILE
"""
    lithos_text = """BODY='TARGET'
DISTORT= 'Y###########' 'RADIAL'  2
0.0D0  1.0D-03  0.0D0
DISTORT= 'X###########' 'OWEN'  6
0.0D0  0.0D0  1.2D-03  0.0D0  -3.0D-09  0.0D0  0.0D0
END
"""
    pic = parse_sum(sum_text)
    plain = Camera.from_picture(pic)
    cam = Camera.from_picture(pic, parse_lithos(lithos_text))
    assert plain.model == "NONE" and cam.model == "OWEN"
    np.testing.assert_allclose(cam.coefficients, [0, 0, 1.2e-3, 0, -3e-9, 0, 0])
    p = np.array([0.5, 0.1, 0.2])
    smp, lin = plain.project(p)
    assert (float(smp), float(lin)) == pytest.approx((565.13, 407.24), abs=0.005)
    args = dict(
        mmfl=50.0,
        ctr=[512.5, 512.5],
        kmatrix=[[100, 0, 0], [0, 100, 0]],
        rotation=pic.rotation,
        scobj=pic.scobj,
        model="OWEN",
        coefficients=[0, 0, 1.2e-3, 0, -3e-9, 0, 0],
    )
    np.testing.assert_allclose(cam.project(p), reference_pixel(args, p), atol=1e-9)
    assert abs(float(cam.project(p)[1]) - float(lin)) > 0.1  # the model is really applied


@pytest.mark.parametrize(
    "model, coef",
    [
        ("NONE", []),
        ("OWEN", [0.01, 1e-4, 2e-3, 1e-5, 1e-4, 1e-5, 1e-5]),
        ("RADIAL", [0.0, -3e-3, 1e-5]),
        ("CUBIC", [0, 0, 1.0, 0, 1e-4, 0, 0, 1e-6, 0, 0, 0, 0, 0, 1.0, 0, 2e-4, 0, 0, 0, 1e-6, 0]),
        ("OWEN", [0.0, 3e-3, 5e-2, 1e-3, 1e-3, 1e-3, 1e-3]),  # strongly distorted (~25 px at the corners)
        ("LITHOS", [0, 0, 1.2e-3, 0, -3e-9, 0, 0]),  # the INIT_LITHOS OWEN entry of the test above
    ],
)
@pytest.mark.slow
def test_grid_seeded_inverse_equals_newton(model, coef):
    """pixel_to_direction_grid (exact inverses on a coarse grid; bicubic interpolation where it checks
    exact to 1e-7 px, else one Newton step per point) gives pixel_to_direction's rays within 1e-6 px
    (the Newton-only path to 1e-12), on template-sized windows (one across the optical axis, where
    OWEN's odd terms are not smooth) and across a whole photo; so does pixel_to_direction_lattice on a
    window's sub-ray lattice, also from its kept grid after a CTR shift."""
    if model == "LITHOS":
        args = dict(mmfl=50.0, kmatrix=[[100, 0, 0], [0, 100, 0]], model="OWEN")
    else:
        args = dict(mmfl=7.68, kmatrix=[[454.54, 0, 0.1], [0.3, -454.54, 0]], model=model)
    cam = Camera(
        ctr=[512.5, 512.5],
        rotation=np.eye(3),
        scobj=np.zeros(3),
        npx=1024,
        nln=1024,
        coefficients=np.asarray(coef, float),
        **args,
    )

    def pixel_error(dirs, s, ln):
        smp, lin = cam.focal_to_pixel(dirs[:, 0] / dirs[:, 2], dirs[:, 1] / dirs[:, 2])
        return np.max(np.maximum(np.abs(smp - s), np.abs(lin - ln)))

    rng = np.random.default_rng(3)
    for lo, hi in ((300.0, 420.0), (470.0, 551.0), (-20.0, 1045.0)):
        s = rng.uniform(lo, hi, 5000)
        ln = rng.uniform(lo, hi, 5000)
        want = cam.pixel_to_direction(s, ln)
        got = cam.pixel_to_direction_grid(s, ln)
        assert pixel_error(want, s, ln) < 1e-9
        assert pixel_error(got, s, ln) < 1e-6
        newton = cam.pixel_to_direction_grid(s, ln, interp_tol=-1.0)
        np.testing.assert_allclose(newton, want, rtol=0, atol=1e-12)
        # a template window's sub-ray lattice (supersample 2)
        subs = lo + 0.25 + 0.5 * np.arange(int(2 * (hi - lo)))
        subl = lo + 3.75 + 0.5 * np.arange(int(2 * (hi - lo)) - 7)
        ss, ll = np.broadcast_arrays(subs[None, :], subl[:, None])
        lat = cam.pixel_to_direction_lattice(subs, subl)
        assert lat.shape == ss.shape + (3,)
        assert pixel_error(lat.reshape(-1, 3), ss.reshape(-1), ll.reshape(-1)) < 1e-6
        np.testing.assert_array_equal(cam.pixel_to_direction_lattice(subs, subl), lat)  # kept grid
        # the kept grid serves a camera with CTR moved by a fraction of a pixel (register's templates)
        moved = cam.with_ctr(cam.ctr + np.array([0.31, -0.27]))
        lat2 = moved.pixel_to_direction_lattice(subs, subl).reshape(-1, 3)
        smp, lin = moved.focal_to_pixel(lat2[:, 0] / lat2[:, 2], lat2[:, 1] / lat2[:, 2])
        assert np.max(np.maximum(np.abs(smp - ss.reshape(-1)), np.abs(lin - ll.reshape(-1)))) < 1e-6
    assert cam.pixel_to_direction_grid([], []).shape == (0, 3)
    assert cam.pixel_to_direction_lattice([], [1.0, 2.0]).shape == (2, 0, 3)
    # a sample or line that is not finite (the lattice reads it off the extremes): NaN there, the other
    # points as without it (the general grid path, mesh for mesh)
    for smp, lin in (([10.0, np.nan, 12.0], [5.0, 6.0]), ([10.0, 11.0], [np.inf, 6.0]), ([np.nan], [1.0])):
        ss, ll = np.meshgrid(np.array(smp), np.array(lin))
        lat = cam.pixel_to_direction_lattice(np.array(smp), np.array(lin))
        np.testing.assert_array_equal(lat, cam.pixel_to_direction_grid(ss, ll))
        bad = ~(np.isfinite(ss) & np.isfinite(ll))
        assert np.all(np.isnan(lat[bad]))
        if (~bad).any():
            np.testing.assert_array_equal(lat[~bad], cam.pixel_to_direction_grid(ss[~bad], ll[~bad]))


def test_grid_seeded_inverse_keeps_non_invertible_pixels_nan():
    coef = np.zeros(21)
    coef[4] = 1.0
    coef[13] = 1.0
    cam = Camera(
        mmfl=100.0, ctr=[512.5, 512.5], kmatrix=[[100, 0, 0], [0, 100, 0]], rotation=np.eye(3),
        scobj=np.zeros(3), npx=1024, nln=1024, model="CUBIC", coefficients=coef,
    )  # fmt: skip
    s = np.array([612.5, 412.5, 700.0])
    ln = np.array([512.5, 600.0, 400.0])
    got = cam.pixel_to_direction_grid(s, ln)
    want = cam.pixel_to_direction(s, ln)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got[[0, 2]], want[[0, 2]], rtol=0, atol=1e-12)


def test_with_ctr_equals_replace():
    """with_ctr (register's shifted template camera) is dataclasses.replace(ctr=…) without re-packing."""
    import dataclasses

    cam = Camera(
        mmfl=7.68, ctr=[512.5, 500.25], kmatrix=[[454.54, 0, 0.1], [0.3, -454.54, 0]], rotation=np.eye(3),
        scobj=np.array([1.0, 2.0, -30.0]), npx=1024, nln=1024, model="OWEN",
        coefficients=[0.01, 1e-4, 2e-3, 1e-5, 1e-4, 1e-5, 1e-5], legacy_d=[1e-3, 1e-6, 0, 0],
    )  # fmt: skip
    new = cam.ctr + np.array([0.137, -0.42])
    a = cam.with_ctr(new)
    b = dataclasses.replace(cam, ctr=new)
    for f in dataclasses.fields(Camera):
        np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name))
    assert a._q == b._q and a._guess == b._guess and a._code == b._code
    assert not a.ctr.flags.writeable and np.array_equal(cam.ctr, [512.5, 500.25])
    s, ln = np.array([100.3, 700.9]), np.array([40.2, 999.1])
    np.testing.assert_array_equal(a.pixel_to_direction(s, ln), b.pixel_to_direction(s, ln))
    p = np.array([[0.1, 0.2, 0.3]])
    np.testing.assert_array_equal(a.project(p), b.project(p))
