"""spctool.sim.simulate / spctool simulate, render and the demo world (spctool.sim.demo)."""

import filecmp
import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from spctool.errors import SpcUsageError
from spctool.formats.icq import read_icq
from spctool.formats.landmark import read_lmk
from spctool.formats.lists import read_lmrklist, read_pictlist
from spctool.formats.lithos import read_lithos
from spctool.formats.maplet import read_map
from spctool.formats.nominal import read_nom
from spctool.formats.photo import read_photo
from spctool.formats.sumfile import read_sum
from spctool.formats.table import LandmarkTable
from spctool.formats.workdir import WorkDir
from spctool.geometry.camera import Camera
from spctool.geometry.surfaces import HeightPatch
from spctool.sim.demo import copy_demo, demo_files, demo_path
from spctool.sim.simulate import Detector, expose, simulate
from spctool.sim.spec import load_spec, parse_spec
from spctool.stages.render import RenderOptions, render

ROOT = Path(__file__).resolve().parents[1]

SMALL = """
seed = 3
[body]
q = 16
[maplets]
count = 3
qsz = 6
margin = 4
[camera]
npx = 128
nln = 112
[detector]
supersample = 1
[perturbation]
position_sigma_km = 0.002
attitude_sigma_deg = 0.05
[[pictures]]
aim_lat_deg = 10.0
aim_lon_deg = 20.0
range_km = 5.0
[[pictures]]
aim_lat_deg = 10.0
aim_lon_deg = 20.0
view_lat_deg = 25.0
view_lon_deg = 35.0
range_km = 5.0
sun_lat_deg = 30.0
sun_lon_deg = 50.0
format = "fits"
[[pictures]]
name = "N0001"
aim_lat_deg = 10.0
aim_lon_deg = 20.0
view_lat_deg = 0.0
view_lon_deg = 10.0
range_km = 5.0
format = "pgm"
bits = 8
"""


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    base = tmp_path_factory.mktemp("sim")
    spec_path = base / "small.toml"
    spec_path.write_text(SMALL)
    result = simulate(spec_path, base / "world")
    return spec_path, result


# ------------------------------------------------------------------------------------------------
# the specification


def test_spec_defaults_and_errors():
    spec = parse_spec({})
    assert [p.name for p in spec.pictures] == [f"P00000000{k}A1" for k in range(1, 5)]
    assert spec.maplets.qsz == 24 and spec.camera.npx == 768 and spec.seed == 1
    assert spec.pictures[0].utc == "2024 JAN 01 00:00:00.000" and spec.pictures[3].bits == 8
    with pytest.raises(SpcUsageError, match="qsize"):
        parse_spec({"maplets": {"qsize": 3}})
    with pytest.raises(SpcUsageError, match="unknown section"):
        parse_spec({"lighting": {"sun": 1}})
    with pytest.raises(SpcUsageError, match="integer"):
        parse_spec({"body": {"q": 6.5}})
    with pytest.raises(SpcUsageError, match="power of 2"):
        parse_spec({"body": {"q": 48}})
    with pytest.raises(SpcUsageError, match="format"):
        parse_spec({"pictures": [{"format": "jpeg"}]})
    with pytest.raises(SpcUsageError, match="unique"):
        parse_spec({"pictures": [{"name": "A"}, {"name": "A"}]})
    with pytest.raises(SpcUsageError, match="zoom"):
        parse_spec({"pictures": [{"zoom": 2}]})


def test_example_spec_is_the_default(run_cli):
    r = run_cli("simulate", "--example")
    assert r.exit_code == 0
    assert parse_spec(tomllib.loads(r.stdout)).to_dict() == parse_spec({}).to_dict()
    help_text = run_cli("simulate", "--help").stdout
    for key in ("truth_factor", "coefficient", "full_well_electrons", "view_lat_deg", "write_truth"):
        assert key in help_text


# ------------------------------------------------------------------------------------------------
# the working directory


def test_world_files_follow_the_formats(small):
    _, res = small
    out, truth = res.outdir, res.truth
    wd = WorkDir(out)
    names = [p["name"] for p in truth["pictures"]]
    lms = [lm["name"] for lm in truth["landmarks"]]
    assert names == ["P000000001A1", "P000000002A1", "N0001"] and lms == ["SM0001", "SM0002", "SM0003"]
    assert list(read_pictlist(out / "PICTLIST.TXT").active_names) == names
    assert read_lmrklist(out / "LMRKLIST.TXT").names == lms
    settings = read_lithos(out / "INIT_LITHOS.TXT")
    dm = settings.distortion_for("P000000001A1")
    assert dm.model == "OWEN" and dm.coefficients.size == 7 and dm.coefficients[2] == 2e-3
    icq = read_icq(out / "SHAPEFILES" / "SHAPE.TXT")
    assert icq.q == 16 and icq.albedo is not None
    np.testing.assert_array_equal(icq.vertices, res.world.icq.vertices)
    for p in truth["pictures"]:
        pic = read_sum(wd.sum_path(p["name"]))
        nom = read_nom(wd.nom_path(p["name"]))
        assert pic.landmarks == [] and pic.npx == 128 and pic.nln == 112
        assert pic.thrsh.tolist() == [1, (1 << p["bits"]) - 1]
        np.testing.assert_array_equal(nom.scobj, pic.scobj)
        np.testing.assert_array_equal(nom.rotation, pic.rotation)
        # the a-priori pose is the truth plus errors of the SPEC's size
        dpos = np.linalg.norm(pic.scobj - np.array(p["true"]["scobj"]))
        rot = pic.rotation @ np.array(p["true"]["rotation"]).T
        dang = math.degrees(math.acos(np.clip((np.trace(rot) - 1) / 2, -1, 1)))
        assert 1e-5 < dpos < 6 * 0.002 * math.sqrt(3) and 1e-4 < dang < 6 * 0.05 * math.sqrt(3)
        np.testing.assert_allclose(pic.sigma_vso, 0.002)
        np.testing.assert_allclose(pic.sigma_ptg, math.radians(0.05))
        np.testing.assert_allclose(pic.sz, p["true"]["sz"], atol=1e-10)
    for lm in truth["landmarks"]:
        m = read_map(out / "MAPFILES" / f"{lm['name']}.MAP")
        lmk = read_lmk(out / "LMKFILES" / f"{lm['name']}.LMK")
        np.testing.assert_allclose(lmk.vlm, lm["vlm"], rtol=1e-9)  # D20.10 text
        np.testing.assert_allclose(m.v, lm["vlm"], rtol=1e-6)  # float32 header
        np.testing.assert_allclose(lmk.uz, lm["uz"], atol=1e-9)
        assert m.qsz == 6 and lmk.qsz == 6 and m.valid.all() and lmk.pictures == []


def test_truth_pixels_are_the_file_camera_projection(small):
    _, res = small
    wd = WorkDir(res.outdir)
    settings = read_lithos(res.outdir / "INIT_LITHOS.TXT")
    for p in res.truth["pictures"]:
        pic = read_sum(wd.sum_path(p["name"]))
        cam = Camera.from_picture(pic, settings).with_pose(
            scobj=p["true"]["scobj"], rotation=np.array(p["true"]["rotation"])
        )
        assert cam.model == "OWEN"
        for lm in res.truth["landmarks"]:
            s, ln = cam.project(np.array(lm["vlm"]))
            px = lm["pixels"][p["name"]]
            assert (float(s), float(ln)) == pytest.approx((px["sample"], px["line"]), abs=1e-9)
            assert px["in_image"] and px["visible"]


def test_photos_sky_is_zero_and_the_body_is_lit(small):
    _, res = small
    wd = WorkDir(res.outdir)
    for k, p in enumerate(res.truth["pictures"]):
        pic = read_sum(wd.sum_path(p["name"]))
        photo = wd.read_photo(p["name"], npx=pic.npx, nln=pic.nln)
        assert photo.data.shape == (112, 128)
        assert photo.data.dtype == (np.uint8 if p["bits"] == 8 else np.uint16)
        assert Path(wd.photo_path(p["name"])).suffix == {0: ".DAT", 1: ".FITS", 2: ".PGM"}[k]
        r = res.world.render(k)
        np.testing.assert_array_equal(photo.data > 0, r.coverage > 0)
        for lm in res.truth["landmarks"]:
            px = lm["pixels"][p["name"]]
            assert photo.dn(round(px["sample"]), round(px["line"])) > 0


def test_maplets_are_the_smoothed_truth(small):
    spec_path, res = small
    spec = load_spec(spec_path)
    m_spec = spec.maplets
    k = m_spec.truth_factor
    for lm in res.world.landmarks:
        t = lm.truth
        assert t.qsz == k * (m_spec.qsz + m_spec.margin) and t.scale == pytest.approx(m_spec.scale_km / k)
        assert t.heights[t.qsz, t.qsz] == 0.0  # V is on the truth surface
        np.testing.assert_allclose(lm.v, t.v)
        sm = gaussian_filter(t.heights, m_spec.smoothing_cells * k, mode="nearest")
        nodes = sm[k * m_spec.margin :: k, k * m_spec.margin :: k][: 2 * m_spec.qsz + 1, : 2 * m_spec.qsz + 1]
        m = read_map(res.outdir / "MAPFILES" / f"{lm.name}.MAP")
        hscale = float(m.hscale)
        np.testing.assert_allclose(m.heights, nodes / k, atol=0.51 * hscale + 1e-9)


@pytest.mark.slow
def test_reproducible_bit_for_bit(small, tmp_path):
    spec_path, res = small
    again = simulate(spec_path, tmp_path / "again")
    a = sorted(p.relative_to(res.outdir) for p in res.outdir.rglob("*") if p.is_file())
    b = sorted(p.relative_to(again.outdir) for p in again.outdir.rglob("*") if p.is_file())
    assert a == b and len(a) == 20
    _, mismatch, errors = filecmp.cmpfiles(res.outdir, again.outdir, [str(p) for p in a], shallow=False)
    assert mismatch == [] and errors == []
    with pytest.raises(SpcUsageError, match="not empty"):
        simulate(spec_path, tmp_path / "again")
    # another process with another hash seed writes the same bytes (no set/dict-order dependence)
    import os
    import subprocess
    import sys

    env = dict(os.environ, PYTHONHASHSEED="12345")
    subprocess.run(
        [sys.executable, "-m", "spctool.cli.main", "-q", "simulate", str(spec_path), str(tmp_path / "p")],
        check=True,
        env=env,
        capture_output=True,
    )
    _, mismatch, errors = filecmp.cmpfiles(res.outdir, tmp_path / "p", [str(p) for p in a], shallow=False)
    assert mismatch == [] and errors == []


def test_expose_noise_statistics():
    det = Detector(bits=16, exposure=30000.0, full_well_electrons=40000.0, read_noise_electrons=20.0)
    rad = np.full((200, 200), 1.0)
    cov = np.ones_like(rad)
    cov[:10] = 0
    clean, expo = expose(rad, cov, det)
    assert expo == 30000.0 and np.all(clean[10:] == 30000) and np.all(clean[:10] == 0)
    noisy, _ = expose(rad, cov, det, np.random.default_rng(0))
    g = 40000.0 / 65535.0
    sigma_dn = math.sqrt(20.0**2 + 30000.0 * g) / g
    assert noisy[10:].std() == pytest.approx(sigma_dn, rel=0.05)
    assert abs(noisy[10:].mean() - 30000.0) < 3 * sigma_dn / 190
    dark, _ = expose(np.zeros_like(rad), cov, Detector(bits=8), np.random.default_rng(1))
    assert dark.dtype == np.uint8 and dark[10:].min() >= 1 and np.all(dark[:10] == 0)
    auto, e = expose(rad * np.linspace(0, 2, 200)[None, :], cov, Detector(bits=16))
    assert auto[10:].max() == pytest.approx(0.8 * 65535 / 0.995, rel=0.01)


# ------------------------------------------------------------------------------------------------
# commands


def test_simulate_and_render_commands(run_cli, small, tmp_path):
    spec_path, res = small
    r = run_cli("simulate", spec_path, tmp_path / "w", "--seed", "4")
    assert r.exit_code == 0, r.stderr
    table = LandmarkTable.parse_text(r.stdout)
    assert len(table) == 9 and set(table["picture"]) == {"P000000001A1", "P000000002A1", "N0001"}
    truth = json.loads((tmp_path / "w" / "TRUTH.json").read_text())
    assert truth["seed"] == 4 and truth["landmarks"][0]["vlm"] != res.truth["landmarks"][0]["vlm"]
    # render: the shape and maplets of the workdir at the SUM pose
    out = tmp_path / "r.fits"
    r = run_cli("-C", res.outdir, "render", "P000000001A1", "-o", out, "--float", "--supersample", "1")
    assert r.exit_code == 0, r.stderr
    img = read_photo(out).data
    assert img.shape == (112, 128) and img.dtype == np.float32 and img.max() > 0
    r = run_cli(
        "-C", res.outdir, "render", "N0001", "SM0001", "--no-shape", "-o", tmp_path / "m.pgm", "--bits", "8"
    )
    assert r.exit_code == 0, r.stderr
    m = read_photo(tmp_path / "m.pgm").data
    assert m.dtype == np.uint8 and 0 < np.count_nonzero(m) < 200
    r = run_cli("-C", res.outdir, "render", "N0001", "-o", tmp_path / "x.png", "--float")
    assert r.exit_code == 2 and "FITS" in r.stderr


# ------------------------------------------------------------------------------------------------
# the demo


def test_demo_copies_are_identical_and_come_from_the_spec():
    pkg = ROOT / "spctool" / "data" / "demo"
    fix = ROOT / "fixtures" / "demo"
    assert demo_path() == pkg.resolve() or demo_path().samefile(pkg)
    files = demo_files(pkg)
    assert files == demo_files(fix)
    _, mismatch, errors = filecmp.cmpfiles(pkg, fix, [str(p) for p in files], shallow=False)
    assert mismatch == [] and errors == []
    truth = json.loads((pkg / "TRUTH.json").read_text())
    assert truth["spec"] == load_spec(ROOT / "fixtures" / "demo.toml").to_dict()
    size = sum((pkg / p).stat().st_size for p in files)
    assert size <= 10e6
    assert len(truth["landmarks"]) == 12 and len(truth["pictures"]) == 4
    assert (pkg / "PICTLIST.TXT").is_file() and (pkg / "LMRKLIST.TXT").is_file()


def test_copy_demo(tmp_path):
    dest = copy_demo(tmp_path / "demo")
    assert demo_files(dest) == demo_files()
    with pytest.raises(SpcUsageError, match="not empty"):
        copy_demo(dest)
    copy_demo(dest, overwrite=True)


def test_demo_is_a_registration_target():
    """At the true pixel the photo matches the maplet rendered with the true camera (NCC peak at zero
    shift for at least 90 % of the landmarks, within one pixel for all: the smoothed maplet's shadows
    differ from the truth's), and the a-priori SUM pose is a few pixels off."""
    root = demo_path()
    wd = WorkDir(root)
    truth = json.loads((root / "TRUTH.json").read_text())
    settings = read_lithos(root / "INIT_LITHOS.TXT")
    hw = 14
    for p in truth["pictures"]:
        pic = read_sum(wd.sum_path(p["name"]))
        apriori = Camera.from_picture(pic, settings)
        cam = apriori.with_pose(scobj=p["true"]["scobj"], rotation=np.array(p["true"]["rotation"]))
        photo = wd.read_photo(p["name"], npx=pic.npx, nln=pic.nln).data.astype(float)
        offsets = []
        exact = []
        for lm in truth["landmarks"]:
            px = lm["pixels"][p["name"]]
            assert px["in_image"]  # (the centre itself may hide behind a boulder: "visible" is the truth's)
            s, ln = int(round(px["sample"])), int(round(px["line"]))
            assert hw + 4 < s < pic.npx - hw - 4 and hw + 4 < ln < pic.nln - hw - 4
            patch = HeightPatch.from_maplet(wd.read_maplet(lm["name"]))
            pred = render(
                cam,
                p["true"]["sz"],
                None,
                [patch],
                RenderOptions(supersample=2),
                window=(s - hw, s + hw, ln - hw, ln + hw),
            )
            mask = pred.coverage == 1
            scores = {}
            for ds in range(-2, 3):
                for dl in range(-2, 3):
                    obs = photo[ln - hw - 1 + dl : ln + hw + dl, s - hw - 1 + ds : s + hw + ds]
                    scores[ds, dl] = np.corrcoef(pred.radiance[mask], obs[mask])[0, 1]
            best = max(scores, key=scores.get)
            assert max(abs(best[0]), abs(best[1])) <= 1, (p["name"], lm["name"], scores)
            exact.append(best == (0, 0))
            assert scores[0, 0] > 0.6
            a_s, a_l = apriori.project(np.array(lm["vlm"]))
            offsets.append(math.hypot(a_s - px["sample"], a_l - px["line"]))
        assert np.mean(exact) >= 0.9  # the peak is at the true pixel (a grazing Sun may shift it by 1 px)
        assert 0.3 < np.median(offsets) < 10.0


def test_a_given_reference_shape(tmp_path):
    from spctool.formats.icq import IcqShape, icq_cube_grid, write_icq

    g = icq_cube_grid(8)
    write_icq(tmp_path / "ref.txt", IcqShape(8, 0.25 * g / np.linalg.norm(g, axis=-1, keepdims=True)))
    spec = parse_spec(
        {
            "body": {"shape": "ref.txt", "q": 16},
            "maplets": {"count": 1, "qsz": 4, "margin": 2},
            "camera": {"npx": 64, "nln": 64},
            "detector": {"supersample": 1},
            "pictures": [{"range_km": 6.0}],
        },
        base=tmp_path,
    )
    res = simulate(spec, tmp_path / "w")
    r = np.linalg.norm(res.world.icq.vertices, axis=-1)
    # the Q = 8 sphere's bilinear cells (sagging < 1.5 % between its vertices) plus the coarse terrain
    assert abs(np.median(r) - 0.25) < 0.003 and 0.2 < r.min() and r.max() < 0.27 and res.world.icq.q == 16
    with pytest.raises(SpcUsageError, match="not found"):
        simulate(parse_spec({"body": {"shape": "missing.txt"}}, base=tmp_path), tmp_path / "w2")


def test_a_world_without_landmarks(tmp_path, run_cli):
    spec = tmp_path / "bare.toml"
    spec.write_text(
        "[maplets]\ncount = 0\n[camera]\nnpx = 48\nnln = 40\n[detector]\nsupersample = 1\n"
        '[[pictures]]\nrange_km = 6.0\nformat = "png"\n'
    )
    r = run_cli("simulate", spec, tmp_path / "w")
    assert r.exit_code == 0, r.stderr
    truth = json.loads((tmp_path / "w" / "TRUTH.json").read_text())
    assert truth["landmarks"] == [] and read_lmrklist(tmp_path / "w" / "LMRKLIST.TXT").names == []
    assert read_photo(tmp_path / "w" / "IMAGEFILES" / "P000000001A1.PNG").data.shape == (40, 48)
