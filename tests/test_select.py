"""Tests of spctool.stages.select (Stage A, L15 §3.2/§3.2.1, spc-algorithms.md §2).

* one synthetic scene per check in which exactly that check rejects (and the option that relaxes it
  makes the maplet pass);
* the NUMLM/RESLM rule at its thresholds, both modes;
* hand-worked geometry (resolution, angles, half-diagonal field of view, cone boundary);
* occlusion on an ICQ sphere with a deep bowl against an independent brute-force intersection of
  every cell written here (both quadratic roots, least-squares γ);
* properties: the cone never rejects what the fine test keeps;
* real data: the three Rosetta 67P landmarks of W48230079013 (spc-formats.md §2.5 check).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.distance import pdist

from spctool.errors import SpcUsageError
from spctool.geometry.camera import Camera
from spctool.geometry.frames import orient_frame
from spctool.stages.select import CHECKS, SelectOptions, field_of_view, select_maplets

REAL = Path(__file__).resolve().parents[1] / "fixtures" / "real" / "rosetta-67p"

# ------------------------------------------------------------------------------------------------
# scenes
# ------------------------------------------------------------------------------------------------

H = 10.0  # camera height above the plane z = 0 (km)
F_PX = 1000.0  # focal length in pixels
NPX = NLN = 100


def nadir_camera(height=H, f_px=F_PX, npx=NPX, nln=NLN):
    """Pinhole camera at (0, 0, height) looking down −z: sample = c + f·x/h, line = c − f·y/h."""
    mmfl = 100.0
    k = f_px / mmfl
    rot = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    return Camera(
        mmfl=mmfl,
        ctr=((npx + 1) / 2, (nln + 1) / 2),
        kmatrix=[[k, 0, 0], [0, k, 0]],
        rotation=rot,
        scobj=[0.0, 0.0, -height],
        npx=npx,
        nln=nln,
    )


def flat(xy, scale=0.005, qsz=10):
    """Maplets on the plane z = 0 facing up (Ux = +x, Uy = +y, Uz = +z)."""
    xy = np.atleast_2d(np.asarray(xy, float))
    n = xy.shape[0]
    centres = np.column_stack([xy, np.zeros(n)])
    ux = np.tile([1.0, 0, 0], (n, 1))
    uy = np.tile([0, 1.0, 0], (n, 1))
    uz = np.tile([0, 0, 1.0], (n, 1))
    return dict(
        centres=centres, ux=ux, uy=uy, uz=uz, scale=np.full(n, float(scale)), qsz=np.full(n, int(qsz))
    )


def tilted(x, angle_deg, scale=0.005, qsz=10):
    """A maplet at (x, 0, 0) rotated by angle about +y (Uz tilts toward +x)."""
    a = math.radians(angle_deg)
    uz = np.array([[math.sin(a), 0, math.cos(a)]])
    ux = np.array([[math.cos(a), 0, -math.sin(a)]])
    uy = np.array([[0, 1.0, 0]])
    return dict(
        centres=np.array([[x, 0, 0.0]]), ux=ux, uy=uy, uz=uz, scale=np.array([scale]), qsz=np.array([qsz])
    )


def concat(*scenes):
    return {k: np.concatenate([s[k] for s in scenes]) for k in scenes[0]}


def run(scene, sun=(0, 0, 1.0), camera=None, shape=None, **opts):
    cam = camera if camera is not None else nadir_camera()
    return select_maplets(
        cam,
        np.asarray(sun, float),
        scene["centres"],
        scene["ux"],
        scene["uy"],
        scene["uz"],
        scene["scale"],
        scene["qsz"],
        options=SelectOptions(**opts),
        shape=shape,
    )


def failed(result, i=0):
    return {name for name in CHECKS if not result.checks[name][i]}


# ------------------------------------------------------------------------------------------------
# one scene per check
# ------------------------------------------------------------------------------------------------


def test_baseline_maplet_passes_every_check():
    r = run(flat([0.0, 0.0]))
    assert failed(r) == set()
    assert r.status.tolist() == ["ok"] and r.selected.tolist() == [True]
    assert r.fraction_in_photo[0] == 1.0


def test_outside_cone():
    r = run(flat([5.0, 0.0]))  # 26.6° off the boresight, half-diagonal FOV ≈ 4°
    assert failed(r) == {"cone", "in_photo"}
    assert r.status[0] == "outside" and not r.selected[0]


def test_outside_fine_test_but_inside_cone():
    # right edge of the photo at x = 0.495 km; the cone reaches the half-diagonal (0.7 km) off-axis
    r = run(flat([0.6, 0.0]))
    assert failed(r) == {"in_photo"}
    assert r.status[0] == "outside"
    assert r.fraction_in_photo[0] == 0.0


def test_box_partly_in_photo_is_kept():
    # centre at x = 0.53 km (sample 103.5, outside); the box offset w·d_m = 0.0525 km puts 3 points
    # at sample 98.25
    r = run(flat([0.53, 0.0]))
    assert not (1 <= r.sample[0] <= NPX)
    assert failed(r) == set() and r.selected[0]
    assert r.fraction_in_photo[0] == pytest.approx(3 / 9)
    # reading (b): offset w·d_m/2 = 0.02625 km -> sample 100.875: every point outside
    rb = run(flat([0.53, 0.0]), fw_scale="half")
    assert rb.status[0] == "outside" and rb.fraction_in_photo[0] == 0.0
    # w = 0 tests the centre only
    r0 = run(flat([0.53, 0.0]), fractional_width=0.0)
    assert r0.status[0] == "outside"


def test_box_fully_outside_is_rejected_on_every_side():
    r = run(flat([[0.6, 0.0], [-0.6, 0.0], [0.0, 0.6], [0.0, -0.6], [0.0, 0.0]]))
    assert r.status.tolist() == ["outside"] * 4 + ["ok"]
    assert r.checks["cone"].all()


def test_backfacing():
    r = run(tilted(0.0, 88.0), reslm=1e6)  # cos e = cos 88° = 0.035 < 0.05
    assert failed(r) == {"facing"}
    assert r.status[0] == "backfacing"
    assert r.emission[0] == pytest.approx(88.0, abs=1e-9)
    assert run(tilted(0.0, 88.0), reslm=1e6, facing_cos_min=0.03).status[0] == "ok"


def test_too_oblique_only_with_max_emission():
    sc = tilted(0.0, 60.0)
    assert run(sc).status[0] == "ok"
    r = run(sc, max_emission=55.0)
    assert failed(r) == {"emission"} and r.status[0] == "too-oblique"
    assert run(sc, max_emission=65.0).status[0] == "ok"


def test_unlit():
    sun = (1.0, 0.0, -0.1)  # 5.7° below the maplet plane
    r = run(flat([0.0, 0.0]), sun=sun)
    assert failed(r) == {"sunlit"} and r.status[0] == "unlit"
    assert r.incidence[0] > 90
    assert run(flat([0.0, 0.0]), sun=(1.0, 0.0, 0.1)).status[0] == "ok"


def test_too_coarse():
    # pixel footprint 0.01 km; maplet scale 0.002 km: 0.01 >= 4 * 0.002 fails the RESLM test
    sc = concat(flat([0.0, 0.0], scale=0.002), flat([[0.1, 0.1], [-0.1, 0.1]]))
    r = run(sc, numlm=2)
    assert failed(r) == {"resolution"} and r.status[0] == "too-coarse"
    assert r.status.tolist() == ["too-coarse", "ok", "ok"]
    assert r.resolution_applied.all()
    assert run(sc, numlm=2, reslm=6.0).status[0] == "ok"


def test_too_big():
    # photo side at the landmark = 100 px * 0.01 km = 1 km; maplet side (2*60+1)*0.01 = 1.21 km
    r = run(flat([0.0, 0.0], scale=0.01, qsz=60), numlm=0)
    assert failed(r) == {"size"} and r.status[0] == "too-big"
    assert run(flat([0.0, 0.0], scale=0.01, qsz=60), size_factor=1.5).status[0] == "ok"
    # just below the limit: 99 cells of 0.01 km
    assert run(flat([0.0, 0.0], scale=0.01, qsz=49)).status[0] == "ok"


def test_status_is_the_first_failed_check_in_l15_order():
    # outside the cone, backfacing, unlit and too coarse at once: 'outside' wins
    sc = tilted(5.0, 100.0, scale=0.001)
    r = run(sc, sun=(-1.0, 0, -1.0), numlm=0)
    assert {"cone", "facing", "sunlit"} <= failed(r)
    assert r.status[0] == "outside"
    # backfacing and unlit: 'backfacing' wins
    r = run(tilted(0.0, 100.0), sun=(-1.0, 0, -0.2))
    assert {"facing", "sunlit"} <= failed(r) and r.status[0] == "backfacing"


# ------------------------------------------------------------------------------------------------
# NUMLM / RESLM rule
# ------------------------------------------------------------------------------------------------


def numlm_scene(n_good, fine_at=0, n_backfacing=0):
    """n_good maplets that pass every check plus one fine-scale maplet (too fine for RESLM = 4)
    inserted at index ``fine_at``; optional backfacing maplets first (they never count)."""
    xs = np.linspace(-0.3, 0.3, max(n_good, 1))[:n_good]
    good = flat(np.column_stack([xs, np.zeros(n_good)]))
    fine = flat([0.0, 0.2], scale=0.002)
    parts = [good[k] for k in good]
    sc = {k: np.insert(good[k], fine_at, fine[k], axis=0) for k in good}
    del parts
    if n_backfacing:
        back = tilted(0.0, 120.0)
        back = {k: np.repeat(back[k], n_backfacing, axis=0) for k in back}
        sc = concat(back, sc)
    return sc


@pytest.mark.parametrize("n_total, applied", [(4, False), (5, False), (6, True)])
def test_numlm_deterministic_counts_around_threshold(n_total, applied):
    numlm = 5
    sc = numlm_scene(n_total - 1, fine_at=0)
    r = run(sc, numlm=numlm)
    assert r.resolution_applied.all() == applied and (~r.resolution_applied).all() == (not applied)
    assert r.status[0] == ("too-coarse" if applied else "ok")
    assert r.n_selected == n_total - applied


def test_numlm_counts_only_candidates_passing_other_checks():
    sc = numlm_scene(4, fine_at=0, n_backfacing=3)  # 8 candidates, 5 pass the other checks
    r = run(sc, numlm=5)
    assert not r.resolution_applied.any()
    assert r.status.tolist() == ["backfacing"] * 3 + ["ok"] * 5
    assert run(sc, numlm=4).status[3] == "too-coarse"


@pytest.mark.parametrize("fine_at, expected", [(0, "ok"), (4, "ok"), (5, "too-coarse"), (6, "too-coarse")])
def test_numlm_spc_sequential_is_order_dependent(fine_at, expected):
    numlm = 5
    sc = numlm_scene(6, fine_at=fine_at)  # 7 candidates
    r = run(sc, numlm=numlm, numlm_mode="spc_sequential")
    assert r.status[fine_at] == expected
    assert r.resolution_applied.tolist() == [i >= numlm for i in range(7)]
    # the deterministic rule rejects it wherever it is
    assert run(sc, numlm=numlm).status[fine_at] == "too-coarse"


def test_spc_sequential_matches_a_literal_loop():
    rng = np.random.default_rng(3)
    n = 40
    xs = rng.uniform(-0.45, 0.45, n)
    ys = rng.uniform(-0.45, 0.45, n)
    scale = rng.choice([0.002, 0.005], n)
    sc = flat(np.column_stack([xs, ys]))
    sc["scale"] = scale
    back = rng.random(n) < 0.3
    sc["uz"][back] = [0, 0, -1.0]
    numlm = 7
    r = run(sc, numlm=numlm, numlm_mode="spc_sequential")
    found = 0
    for i in range(n):  # SPC's loop: the resolution test once NUMLM maplets have been found
        ok = not back[i]
        if ok and found >= numlm:
            ok = r.resolution_km_px[i] < 4.0 * scale[i]
        found += ok
        assert r.selected[i] == ok, i


def test_reslm_exactly_at_threshold_is_rejected():
    sc = flat([0.0, 0.0], scale=0.002)
    r = run(sc)
    r_img, s = r.resolution_km_px[0], 0.002
    assert r_img == pytest.approx(H / F_PX, rel=1e-12)
    reslm = r_img / s
    while reslm * s < r_img:
        reslm = np.nextafter(reslm, np.inf)
    while reslm * s > r_img:
        reslm = np.nextafter(reslm, -np.inf)
    assert reslm * s == r_img
    assert run(sc, numlm=0, reslm=reslm).status[0] == "too-coarse"
    assert run(sc, numlm=0, reslm=reslm * (1 + 1e-12)).status[0] == "ok"


def test_numlm_zero_and_reslm_inf():
    sc = flat([0.0, 0.0], scale=0.002)
    assert run(sc, numlm=0).status[0] == "too-coarse"
    assert run(sc, numlm=0, reslm=math.inf).status[0] == "ok"


# ------------------------------------------------------------------------------------------------
# hand-worked geometry
# ------------------------------------------------------------------------------------------------


def test_resolution_and_angles_hand_worked():
    # flat maplet at nadir: exact pixel footprint H/f; sun 30° from the zenith toward +x
    sun = (math.sin(math.radians(30)), 0, math.cos(math.radians(30)))
    r = run(flat([0.0, 0.0]), sun=sun)
    assert r.resolution_km_px[0] == pytest.approx(H / F_PX, rel=1e-12)
    assert r.range_km[0] == pytest.approx(H)
    assert r.emission[0] == pytest.approx(0.0, abs=1e-6)
    assert r.incidence[0] == pytest.approx(30.0, abs=1e-9)
    assert r.phase[0] == pytest.approx(30.0, abs=1e-9)
    assert (r.sample[0], r.line[0]) == (pytest.approx(50.5), pytest.approx(50.5))
    # J_xy: +x -> +sample, +y -> −line, 0.5 px per 0.005 km cell
    np.testing.assert_allclose(r.jacobian[0], [[0.5, 0], [0, -0.5]], atol=1e-12)


def test_resolution_of_a_tilted_maplet_and_jacobian_modes():
    sc = tilted(0.2, 50.0)
    rc = run(sc)
    ra = run(sc, jacobian="analytic")
    # exact ∂(sample, line)/∂(x, y) from the camera vs the one-cell central difference
    np.testing.assert_allclose(rc.jacobian[0], ra.jacobian[0], rtol=1e-5)
    # independent: a patch dA at range ρ, emission e, angle β off the optical axis covers
    # f²·dA·cos e/(ρ²·cos³β) pixels, so r_img = ρ·cos^1.5 β/(f·√cos e)
    rho = rc.range_km[0]
    cos_e = math.cos(math.radians(rc.emission[0]))
    cos_beta = H / rho
    expected = rho * cos_beta**1.5 / (F_PX * math.sqrt(cos_e))
    assert ra.resolution_km_px[0] == pytest.approx(expected, rel=1e-9)
    assert rc.resolution_km_px[0] == pytest.approx(expected, rel=1e-5)


def test_field_of_view_of_a_pinhole():
    cam = nadir_camera(npx=120, nln=80)
    b, lam = field_of_view(cam)
    np.testing.assert_allclose(b, [0, 0, -1.0], atol=1e-12)
    assert lam == pytest.approx(math.atan(math.hypot(119 / 2, 79 / 2) / F_PX), rel=1e-12)


def test_cone_boundary():
    cam = nadir_camera()
    _, lam_c = field_of_view(cam)
    scale, qsz = 0.005, 10
    d_m = (2 * qsz + 1) * scale
    rho = d_m / math.sqrt(2)

    def at_angle(theta):
        # a maplet facing the camera at angle theta from the boresight, range 10 km
        d = np.array([math.sin(theta), 0, -math.cos(theta)])
        centre = np.array([0, 0, H]) + 10.0 * d
        ux, uy, uz = orient_frame(-d)
        sc = dict(
            centres=centre[None],
            ux=ux[None],
            uy=uy[None],
            uz=uz[None],
            scale=np.array([scale]),
            qsz=np.array([qsz]),
        )
        return run(sc, sun=-d)

    lam_m = math.asin(rho / 10.0)
    assert at_angle(lam_c + lam_m - 1e-9).checks["cone"][0]
    assert not at_angle(lam_c + lam_m + 1e-9).checks["cone"][0]
    # with the half-side radius the cone is narrower
    lam_m2 = math.asin(d_m / 2 / 10.0)
    assert lam_m2 < lam_m


def test_behind_the_camera():
    sc = flat([0.0, 0.0])
    sc["centres"][0, 2] = 20.0  # above the camera
    sc["uz"][0] = [0, 0, -1.0]
    r = run(sc, sun=(0, 0, -1.0))
    assert r.status[0] == "outside" and np.isnan(r.sample[0]) and np.isnan(r.resolution_km_px[0])


def test_empty_candidate_list():
    sc = flat(np.zeros((0, 2)))
    r = run(sc)
    assert len(r) == 0 and r.n_selected == 0
    assert len(r.to_table(include_rejected=True)) == 0


def test_bad_inputs():
    with pytest.raises(SpcUsageError):
        SelectOptions(numlm_mode="sometimes")
    with pytest.raises(SpcUsageError):
        SelectOptions(reslm=0)
    with pytest.raises(SpcUsageError):
        run(flat([0.0, 0.0]), occlusion=True)  # no shape
    sc = flat([0.0, 0.0])
    with pytest.raises(SpcUsageError):
        select_maplets(
            nadir_camera(),
            (0, 0, 1.0),
            sc["centres"],
            sc["ux"][:0],
            sc["uy"],
            sc["uz"],
            sc["scale"],
            sc["qsz"],
        )


def test_options_from_settings():
    from spctool.formats.lithos import parse_lithos

    s = parse_lithos("NUMLM=   50\nRESLM= 2.5D0\nEND\n")
    o = SelectOptions.from_settings(s)
    assert (o.numlm, o.reslm, o.size_factor) == (50, 2.5, 1.0)  # SIZLM absent: spctool's default
    o = SelectOptions.from_settings(parse_lithos("SIZLM= 1.5\nEND\n"), numlm=7, reslm=None)
    assert (o.numlm, o.reslm, o.size_factor) == (7, 4.0, 1.5)
    assert SelectOptions.from_settings(None) == SelectOptions()
    with pytest.raises(SpcUsageError):
        SelectOptions.from_settings(None, nonsense=1)


# ------------------------------------------------------------------------------------------------
# properties
# ------------------------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.sampled_from(["half-diagonal", "half-side"]),
    st.sampled_from(["side", "half"]),
    st.floats(0.0, 1.2),
)
def test_cone_never_rejects_what_the_fine_test_keeps(seed, cone_rho, fw_scale, w):
    rng = np.random.default_rng(seed)
    n = 200
    # maplets scattered around the field edge, at random ranges and orientations, large and small
    xy = rng.uniform(-1.5, 1.5, (n, 2)) * rng.uniform(0.2, 1.0)
    z = rng.uniform(-3.0, 8.0, n)
    normals = rng.normal(size=(n, 3))
    ux, uy, uz = orient_frame(normals)
    sc = dict(
        centres=np.column_stack([xy, z]),
        ux=ux,
        uy=uy,
        uz=uz,
        scale=rng.uniform(0.001, 0.05, n),
        qsz=rng.integers(1, 40, n),
    )
    r = run(sc, cone_rho=cone_rho, fw_scale=fw_scale, fractional_width=w)
    assert not np.any(r.checks["in_photo"] & ~r.checks["cone"])
    assert np.array_equal(r.fraction_in_photo > 0, r.checks["in_photo"])
    # selection is exactly "every effective check passes"
    assert np.array_equal(r.selected, r.status == "ok")


# ------------------------------------------------------------------------------------------------
# occlusion: ICQ sphere with a deep bowl vs brute force
# ------------------------------------------------------------------------------------------------

BOWL_AXIS = np.array([0.0, 0.0, 1.0])
BOWL_HALF_ANGLE = math.radians(35.0)
BOWL_DEPTH = 0.6


def bowl_radius(dirs):
    theta = np.arccos(np.clip(dirs @ BOWL_AXIS, -1, 1))
    dip = np.where(theta < BOWL_HALF_ANGLE, np.cos(np.pi / 2 * theta / BOWL_HALF_ANGLE) ** 2, 0.0)
    return 1.0 - BOWL_DEPTH * dip


def icq_vertices(q, radius_fn):
    """(6, q+1, q+1, 3) ICQ vertices [F−1, J, I] on the cube faces of spc-formats.md §5.2."""
    t = -1.0 + 2.0 * np.arange(q + 1) / q
    a, b = np.meshgrid(t, t, indexing="xy")  # a along I (axis 1), b along J (axis 0)
    one = np.ones_like(a)
    faces = [(a, -b, one), (a, -one, -b), (-one, -a, -b), (-a, one, -b), (one, a, -b), (a, b, -one)]
    cube = np.stack([np.stack(f, axis=-1) for f in faces])
    dirs = cube / np.linalg.norm(cube, axis=-1, keepdims=True)
    return dirs * radius_fn(dirs)[..., None]


def brute_first_hit(verts, origin, dirs, eps=0.01):
    """Nearest bilinear-patch hit by testing every cell: both roots of the quadratic in u, γ by least
    squares over both equations, parameters accepted in [−eps, 1 + eps] (independent of the kernels)."""
    v = verts
    c0 = v[:, :-1, :-1].reshape(-1, 3)
    c1 = v[:, :-1, 1:].reshape(-1, 3)
    c2 = v[:, 1:, :-1].reshape(-1, 3)
    c3 = v[:, 1:, 1:].reshape(-1, 3)
    t_best = np.full(len(dirs), np.inf)
    p_best = np.full((len(dirs), 3), np.nan)
    for r, d in enumerate(dirs):
        d = d / np.linalg.norm(d)
        e1 = np.cross(d, [1.0, 0, 0] if abs(d[0]) < 0.9 else [0, 1.0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(d, e1)
        X = [(c - origin) @ e1 for c in (c0, c1, c2, c3)]
        Y = [(c - origin) @ e2 for c in (c0, c1, c2, c3)]
        x0, xa, xb, xc = X[0], X[1] - X[0], X[2] - X[0], X[0] - X[1] - X[2] + X[3]
        y0, ya, yb, yc = Y[0], Y[1] - Y[0], Y[2] - Y[0], Y[0] - Y[1] - Y[2] + Y[3]
        qa = xa * yc - ya * xc
        qb = x0 * yc + xa * yb - y0 * xc - ya * xb
        qc = x0 * yb - y0 * xb
        disc = qb * qb - 4 * qa * qc
        ok = disc >= 0
        sq = np.sqrt(np.where(ok, disc, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            roots = [
                np.where(np.abs(qa) > 1e-14, (-qb + sq) / (2 * qa), -qc / qb),
                np.where(np.abs(qa) > 1e-14, (-qb - sq) / (2 * qa), np.nan),
            ]
        for u in roots:
            gx, gy = xb + xc * u, yb + yc * u
            with np.errstate(divide="ignore", invalid="ignore"):
                g = -((x0 + xa * u) * gx + (y0 + ya * u) * gy) / (gx * gx + gy * gy)
            good = (
                ok
                & np.isfinite(u)
                & np.isfinite(g)
                & (u >= -eps)
                & (u <= 1 + eps)
                & (g >= -eps)
                & (g <= 1 + eps)
            )
            uu, gg = u[:, None], g[:, None]
            p = (1 - uu) * (1 - gg) * c0 + uu * (1 - gg) * c1 + (1 - uu) * gg * c2 + uu * gg * c3
            resid = np.abs((p - origin) @ e1) + np.abs((p - origin) @ e2)
            t = (p - origin) @ d
            good &= (resid < 1e-9) & (t >= 0)
            if good.any():
                k = np.flatnonzero(good)[np.argmin(t[good])]
                if t[k] < t_best[r]:
                    t_best[r] = t[k]
                    p_best[r] = p[k]
    return t_best, p_best


def fibonacci_dirs(n):
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = i * math.pi * (3 - math.sqrt(5))
    rr = np.sqrt(1 - z * z)
    return np.column_stack([rr * np.cos(phi), rr * np.sin(phi), z])


def look_at_camera(position, f_px=400.0, npx=200, nln=200):
    cz = -position / np.linalg.norm(position)
    cx = np.cross([0, 0, 1.0], cz)
    cx /= np.linalg.norm(cx)
    cy = np.cross(cz, cx)
    k = f_px / 100.0
    return Camera(
        mmfl=100.0,
        ctr=((npx + 1) / 2, (nln + 1) / 2),
        kmatrix=[[k, 0, 0], [0, k, 0]],
        rotation=np.vstack([cx, cy, cz]),
        scobj=-position,
        npx=npx,
        nln=nln,
    )


@pytest.fixture(scope="module")
def bowl():
    from spctool.geometry.shape import PatchShape

    verts = icq_vertices(16, bowl_radius)
    return verts, PatchShape(verts)


def test_occlusion_matches_brute_force_on_a_bowl(bowl):
    verts, shape = bowl
    el = math.radians(75.0)  # camera 75° off the bowl axis: the rim hides the near side of the floor
    cam_pos = 5.0 * np.array([math.sin(el), 0.0, math.cos(el)])
    cam = look_at_camera(cam_pos)
    # landmarks on the surface: all over the body, plus a dense patch in the bowl
    dirs = np.vstack([fibonacci_dirs(150), fibonacci_dirs(2000)[fibonacci_dirs(2000)[:, 2] > 0.85]])
    pts = dirs * bowl_radius(dirs)[:, None]
    to_cam = cam_pos - pts
    to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
    ux, uy, uz = orient_frame(to_cam)  # every maplet faces the camera and is lit: only occlusion decides
    n = len(pts)
    sc = dict(centres=pts, ux=ux, uy=uy, uz=uz, scale=np.full(n, 0.002), qsz=np.full(n, 2))
    sun = cam_pos / np.linalg.norm(cam_pos)
    r = select_maplets(
        cam,
        sun,
        pts,
        ux,
        uy,
        uz,
        sc["scale"],
        sc["qsz"],
        options=SelectOptions(numlm=10**6, facing_cos_min=-1.0),
        shape=shape,
    )
    assert r.occlusion_checked and r.occlusion_tested.all()

    d_max = pdist(verts.reshape(-1, 3)).max()
    assert shape.max_diameter == pytest.approx(d_max, rel=1e-12)
    tol = 0.01 * d_max
    t_hit, p_hit = brute_first_hit(verts, cam_pos, pts - cam_pos)
    brute_visible = np.isfinite(t_hit) & (np.linalg.norm(p_hit - pts, axis=1) <= tol)
    assert np.array_equal(r.checks["visible"], brute_visible)
    assert np.array_equal(r.status == "occluded", ~brute_visible)
    # the scene exercises both outcomes, inside the bowl too (near floor hidden by the rim)
    in_bowl = dirs[:, 2] > math.cos(BOWL_HALF_ANGLE)
    assert (in_bowl & brute_visible).sum() > 5 and (in_bowl & ~brute_visible).sum() > 5
    assert (~in_bowl & brute_visible).sum() > 5 and (~in_bowl & ~brute_visible).sum() > 5

    # the switch: occlusion=False (or no shape) keeps them all
    r_off = select_maplets(
        cam,
        sun,
        pts,
        ux,
        uy,
        uz,
        sc["scale"],
        sc["qsz"],
        options=SelectOptions(numlm=10**6, facing_cos_min=-1.0, occlusion=False),
        shape=shape,
    )
    assert not r_off.occlusion_checked and r_off.selected.all()


def test_occlusion_scene_where_only_occlusion_rejects(bowl):
    _, shape = bowl
    el = math.radians(75.0)
    cam_pos = 5.0 * np.array([math.sin(el), 0.0, math.cos(el)])
    cam = look_at_camera(cam_pos)
    # the bowl floor on the camera side (facing up, hidden by the rim) and a point of the sphere outside the
    # bowl facing the camera (visible)
    dirs = np.array([[math.sin(math.radians(a)), 0.0, math.cos(math.radians(a))] for a in (15.0, 75.0)])
    pts = dirs * bowl_radius(dirs)[:, None]
    ux, uy, uz = orient_frame(np.array([[0, 0, 1.0], dirs[1]]))
    sun = cam_pos / np.linalg.norm(cam_pos)
    r = select_maplets(
        cam,
        sun,
        pts,
        ux,
        uy,
        uz,
        np.full(2, 0.01),
        np.full(2, 2),
        options=SelectOptions(numlm=10**6),
        shape=shape,
    )
    assert failed(r, 0) == {"visible"} and r.status[0] == "occluded"
    assert failed(r, 1) == set() and r.status[1] == "ok"
    # a generous tolerance (the whole body) lets the hidden one through
    r2 = select_maplets(
        cam,
        sun,
        pts,
        ux,
        uy,
        uz,
        np.full(2, 0.01),
        np.full(2, 2),
        options=SelectOptions(numlm=10**6, occlusion_tol=1.0),
        shape=shape,
    )
    assert r2.status.tolist() == ["ok", "ok"]


def test_no_shape_skips_occlusion():
    r = run(flat([0.0, 0.0]))
    assert not r.occlusion_checked and not r.occlusion_tested.any() and r.checks["visible"].all()


# ------------------------------------------------------------------------------------------------
# real data
# ------------------------------------------------------------------------------------------------


def test_rosetta_landmarks_are_selected_within_1p5_px():
    from spctool.formats.landmark import read_lmk
    from spctool.formats.sumfile import read_sum

    pic = read_sum(REAL / "W48230079013.SUM")
    lmks = [read_lmk(REAL / f"{n}.LMK") for n in ("FA0115", "FC0098", "GD0036")]
    cam = Camera.from_picture(pic)
    r = select_maplets(
        cam,
        pic.sz,
        np.array([m.vlm for m in lmks]),
        np.array([m.ux for m in lmks]),
        np.array([m.uy for m in lmks]),
        np.array([m.uz for m in lmks]),
        np.array([m.scale for m in lmks]),
        np.array([m.qsz for m in lmks]),
        [m.name for m in lmks],
    )
    assert r.status.tolist() == ["ok"] * 3 and not r.occlusion_checked
    measured = {lm.name: (lm.sample, lm.line) for lm in pic.landmarks}
    for i, name in enumerate(r.names):
        ds = r.sample[i] - measured[name][0]
        dl = r.line[i] - measured[name][1]
        assert math.hypot(ds, dl) < 1.5, (name, ds, dl)
    # spc-formats.md §2.5 table: FC0098 predicted (513.59, 501.83)
    assert (r.sample[1], r.line[1]) == (pytest.approx(513.59, abs=0.01), pytest.approx(501.83, abs=0.01))
    # ground resolution vs the SUM-derived formula range·IFOV/cos(emission), to the foreshortening model
    ifov = cam.ifov
    approx = r.range_km * ifov / np.sqrt(np.cos(np.radians(r.emission)))
    np.testing.assert_allclose(r.resolution_km_px, approx, rtol=0.02)
