"""Tests of ``spctool correlate`` and ``spctool register`` (spctool.cli.register) on a working directory
built from a rendered scene with known truth (register_scene): SUM with an a-priori pointing error,
MAP and LMK files of the landmark, a second landmark without a MAP file, and the photo as FITS."""

from __future__ import annotations

import json

import numpy as np
import pytest
import register_scene as rs
from click.testing import CliRunner

from spctool.cli.main import cli
from spctool.formats.landmark import Landmark, write_lmk
from spctool.formats.maplet import Maplet, write_map
from spctool.formats.photo import Photo, read_photo, write_photo
from spctool.formats.sumfile import Picture, SumLandmark, read_sum, write_sum
from spctool.formats.table import LandmarkTable

PIC = "SYN0001"
LMK = "LMK001"


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    sc = rs.scene()
    root = tmp_path_factory.mktemp("wd")
    for d in ("SUMFILES", "MAPFILES", "LMKFILES", "IMAGEFILES"):
        (root / d).mkdir()
    m = sc.maplet
    maplet = Maplet.new(m.scale, m.qsz, m.v, m.ux, m.uy, m.uz, m.heights, m.albedo, name=LMK)
    write_map(root / "MAPFILES" / f"{LMK}.MAP", maplet)
    for name, v in ((LMK, maplet.v), ("NOMAP1", maplet.v + 1e-4 * maplet.ux)):
        write_lmk(
            root / "LMKFILES" / f"{name}.LMK",
            Landmark(
                name=name,
                hflag="T",
                bigmap_extra=None,
                qsz=m.qsz,
                scale=m.scale,
                horizon=(-1, -1, -1, -1),
                sigkm=0.5 * m.scale,
                rmslmk=0.0,
                vlm=v,
                ux=maplet.ux,
                uy=maplet.uy,
                uz=maplet.uz,
                sigma_lmk=np.zeros(3),
            ),
        )
    cam = rs.pointing_error(sc.camera, 5.0, -3.0)  # the SUM's a-priori pose
    pic = Picture(
        name=PIC,
        utc="2020 JAN 01 00:00:00.000",
        npx=cam.npx,
        nln=cam.nln,
        thrsh=np.array([1.0, 60000.0]),
        mmfl=cam.mmfl,
        ctr=cam.ctr,
        scobj=cam.scobj,
        cx=cam.rotation[0],
        cy=cam.rotation[1],
        cz=cam.rotation[2],
        sz=sc.sun,
        kmatrix=cam.kmatrix,
        sigma_vso=np.full(3, 1e-3),
        sigma_ptg=np.full(3, 1e-3),
        landmarks=[SumLandmark("OTHER1", 12.25, 30.5), SumLandmark(LMK, 1.0, 2.0, "*")],
    )
    write_sum(root / "SUMFILES" / f"{PIC}.SUM", pic)
    write_photo(root / "IMAGEFILES" / f"{PIC}.fits", Photo(sc.photo.astype(np.float32)))
    (root / "LMRKLIST.TXT").write_text(f"{LMK}\nEND\n")
    apriori = np.array(cam.project(maplet.v))
    return root, sc, apriori


def invoke(root, *args, stdin=None):
    return CliRunner().invoke(
        cli, ["-C", str(root), *[str(a) for a in args]], input=stdin, catch_exceptions=False
    )


def test_register_recovers_the_landmark(world):
    root, sc, apriori = world
    res = invoke(root, "register", PIC, LMK)
    assert res.exit_code == 0, res.output
    t = LandmarkTable.parse_text(res.stdout)
    assert t.command == "register" and t.picture == PIC and t.names == [LMK]
    assert list(t.columns) == [
        "name",
        "sample",
        "line",
        "apriori_sample",
        "apriori_line",
        "dsample",
        "dline",
        "correlation",
        "iterations",
        "spacing",
        "sigma_sample",
        "sigma_line",
        "rho_sl",
        "status",
    ]
    # S16's ten steps, then the converged full-resolution stage (at most --converge-max more)
    assert t["status"] == ["ok"] and 10 <= t["iterations"][0] <= 20 and t["spacing"][0] == 1
    assert 0.0 < t["sigma_sample"][0] < 0.2 and 0.0 < t["sigma_line"][0] < 0.2 and abs(t["rho_sl"][0]) < 1
    # the MAP file quantises heights and albedo (bytes/100): a few hundredths of a pixel
    assert abs(t["sample"][0] - sc.truth_pixel[0]) < 0.05 and abs(t["line"][0] - sc.truth_pixel[1]) < 0.05
    assert t["apriori_sample"][0] == pytest.approx(apriori[0], abs=1e-4)
    assert t["dsample"][0] == pytest.approx(t["sample"][0] - t["apriori_sample"][0], abs=2e-4)
    assert t["correlation"][0] > 0.9


def test_register_json_missing_maplet_and_require(world):
    root, sc, _ = world
    res = invoke(root, "register", PIC, LMK, "NOMAP1", "--json", "--steps", "4,2,1")
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["command"] == "register" and doc["schedule"] == "s16" and doc["space"] == "maplet"
    rows = {r["name"]: r for r in doc["landmarks"]}
    assert rows[LMK]["status"] == "ok" and 3 <= rows[LMK]["iterations"] <= 13
    assert rows[LMK]["sigma_sample"] > 0 and rows["NOMAP1"]["sigma_sample"] is None
    assert rows["NOMAP1"]["status"] == "no-maplet" and rows["NOMAP1"]["sample"] is None
    assert doc["registered"] == 1 and doc["options"]["steps"] == [["align", 4], ["align", 2], ["align", 1]]
    assert "no maplet" in res.stderr
    res = invoke(root, "register", PIC, LMK, "--steps", "1", "--require", "2")
    assert res.exit_code == 1 and "fewer than --require 2" in res.stderr


def test_register_from_a_lithos_select_table(world):
    root, sc, apriori = world
    sel = invoke(root, "lithos-select", PIC, "--no-occlusion")
    assert sel.exit_code == 0, sel.output
    assert LandmarkTable.parse_text(sel.stdout).names == [LMK]
    res = invoke(root, "register", PIC, "--landmarks", "-", stdin=sel.stdout)
    assert res.exit_code == 0, res.output
    t = LandmarkTable.parse_text(res.stdout)
    assert t["status"] == ["ok"] and abs(t["sample"][0] - sc.truth_pixel[0]) < 0.05
    assert t["apriori_sample"][0] == pytest.approx(apriori[0], abs=1e-3)
    # the chain continues: solve-pose reads the register table (its one ok row; a pose needs 3)
    pose = invoke(root, "solve-pose", PIC, "--measurements", "-", stdin=res.stdout)
    assert pose.exit_code == 1 and "1 usable" in pose.stderr


def test_register_by_selection_parses_each_lmk_once(world, monkeypatch):
    """Without named landmarks, register runs lithos-select, which reads each candidate's LMK; the
    registration then takes the VLM from the selection instead of parsing the file a second time."""
    import spctool.formats.landmark as landmark_format

    root, sc, apriori = world
    parsed = []
    read_lmk = landmark_format.read_lmk
    monkeypatch.setattr(landmark_format, "read_lmk", lambda path: parsed.append(path) or read_lmk(path))
    res = invoke(root, "register", PIC, "--json")
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["landmark_source"] == "selection" and [r["name"] for r in doc["landmarks"]] == [LMK]
    assert doc["landmarks"][0]["status"] == "ok"
    assert len(parsed) == 1 and parsed[0].name == f"{LMK}.LMK"
    # the same registration as with the landmark named (whose LMK register reads itself)
    named = json.loads(invoke(root, "register", PIC, LMK, "--json").stdout)["landmarks"][0]
    assert doc["landmarks"][0]["sample"] == pytest.approx(named["sample"], abs=1e-9)
    assert doc["landmarks"][0]["line"] == pytest.approx(named["line"], abs=1e-9)


def test_register_image_space_and_autoregister(world):
    root, sc, _ = world
    res = invoke(root, "register", PIC, LMK, "--space", "image", "--schedule", "autoregister", "--json")
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    row = doc["landmarks"][0]
    assert row["status"] == "ok" and doc["space"] == "image" and doc["schedule"] == "autoregister"
    assert abs(row["sample"] - sc.truth_pixel[0]) < 0.05 and abs(row["line"] - sc.truth_pixel[1]) < 0.05
    assert [p["spacing"] for p in doc["passes"]] == [2, 1, 1, 1]  # SPC's three, then the converged stage
    assert doc["passes"][-1]["converge"] and doc["passes"][-1]["ok"] == 1
    assert "pose not updated" in res.stderr  # one landmark cannot move the pose


def test_write_sum_rewrites_only_the_landmarks_section(world, tmp_path):
    root, sc, _ = world
    import shutil

    wd = tmp_path / "wd"
    shutil.copytree(root, wd)
    sum_path = wd / "SUMFILES" / f"{PIC}.SUM"
    before = sum_path.read_text().splitlines()
    res = invoke(wd, "register", PIC, LMK, "--write-sum")
    assert res.exit_code == 0, res.output
    after = sum_path.read_text().splitlines()
    assert (wd / "SUMFILES" / f"{PIC}.SUM.bak").read_text().splitlines() == before  # the input kept
    changed = [i for i, (a, b) in enumerate(zip(before, after)) if a != b]
    assert len(before) == len(after) and len(changed) == 1
    assert after[changed[0]].startswith(LMK)
    pic = read_sum(sum_path)
    lm = {x.name.strip(): x for x in pic.landmarks}
    assert lm["OTHER1"].sample == 12.25 and lm[LMK].flag == "*"
    t = LandmarkTable.parse_text(res.stdout)
    assert lm[LMK].sample == pytest.approx(t["sample"][0], abs=0.005)
    assert lm[LMK].line == pytest.approx(t["line"][0], abs=0.005)
    # a failed landmark is left alone, or removed with --drop-failed
    res = invoke(
        wd,
        "register",
        PIC,
        LMK,
        "--steps",
        "1",
        "--project",
        "--write-sum",
        "--drop-failed",
        "--corr-min",
        "0.9999",
    )
    assert res.exit_code == 0, res.output
    assert LandmarkTable.parse_text(res.stdout)["status"] != ["ok"]
    assert [x.name.strip() for x in read_sum(sum_path).landmarks] == ["OTHER1"]


def test_register_overlay(world, tmp_path):
    root, sc, _ = world
    out = tmp_path / "reg.png"
    res = invoke(root, "register", PIC, LMK, "--steps", "2,1", "--overlay", out, "--magnify", "10")
    assert res.exit_code == 0, res.output
    t = LandmarkTable.parse_text(res.stdout)
    assert t["status"] == ["ok"]
    from PIL import Image

    with Image.open(out) as img:
        # the photo enlarged by a whole factor under a title band
        z = img.size[0] // sc.camera.npx
        assert img.mode == "RGB" and img.size[0] == z * sc.camera.npx and img.size[1] > z * sc.camera.nln
        px = np.asarray(img)
    head = px.shape[0] - z * sc.camera.nln
    # the shift vector's tip sits at a-priori + 10 x (measured - a-priori), in the ok colour (green)
    x = (t["apriori_sample"][0] - 1 + 10 * t["dsample"][0]) * z + (z - 1) / 2
    y = head + (t["apriori_line"][0] - 1 + 10 * t["dline"][0]) * z + (z - 1) / 2
    tip = px[int(round(y)) - 1 : int(round(y)) + 2, int(round(x)) - 1 : int(round(x)) + 2].reshape(-1, 3)
    assert any(tuple(c) == (40, 230, 40) for c in tip)
    # the a-priori cross is yellow
    assert np.any((px[..., 0] > 200) & (px[..., 1] > 200) & (px[..., 2] < 50))


def test_correlate_one_pass_writes_surfaces(world, tmp_path):
    root, sc, apriori = world
    out = tmp_path / "surf"
    res = invoke(root, "correlate", PIC, LMK, "--spacing", "2", "--out-dir", out)
    assert res.exit_code == 0, res.output
    t = LandmarkTable.parse_text(res.stdout)
    assert t.command == "correlate" and t["status"] == ["ok"] and t["spacing"][0] == 2
    assert t["sample"][0] == pytest.approx(apriori[0], abs=1e-4)
    # one pass at spacing 2 from a 5.8-px a-priori error: within a few tenths of the truth
    assert abs(t["measured_sample"][0] - sc.truth_pixel[0]) < 0.5
    assert abs(t["measured_line"][0] - sc.truth_pixel[1]) < 0.5
    img = read_photo(out / f"{LMK}_{PIC}_surface.pgm")
    assert img.data.shape == (11, 11) and img.data.max() > 240
    res = invoke(
        root,
        "correlate",
        PIC,
        LMK,
        "--out-dir",
        out,
        "--image-format",
        "fits",
        "--grid-half",
        "7",
        "--spacing",
        "2",
        "--json",
    )
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["images_written"] == 1 and doc["spacing"] == 2
    from astropy.io import fits

    with fits.open(out / f"{LMK}_{PIC}_surface.fits") as hdul:
        hdr, data = hdul[0].header, hdul[0].data
    assert data.shape == (15, 15) and hdr["LANDMARK"] == LMK and hdr["SPACING"] == 2 and hdr["AXIS2"] == "UX"
    assert hdr["PEAK"] == pytest.approx(doc["landmarks"][0]["correlation"])
    assert np.nanmax(data) == pytest.approx(hdr["PEAK"], rel=1e-6)


def test_correlate_image_space_and_edge_peak(world):
    root, sc, apriori = world
    res = invoke(root, "correlate", PIC, LMK, "--space", "image", "--spacing", "2")
    assert res.exit_code == 0, res.output
    t = LandmarkTable.parse_text(res.stdout)
    assert t["status"] == ["ok"]  # the (5, −3) px error is within ±10 px
    assert abs(t["dsample"][0] - (sc.truth_pixel[0] - apriori[0])) < 0.3
    res = invoke(root, "correlate", PIC, LMK)  # maplet space at spacing 1: ±5 cells < the 8-cell error
    t = LandmarkTable.parse_text(res.stdout)
    assert t["status"][0] in ("edge-peak", "not-found")


def test_usage_errors(world):
    root, _, _ = world
    res = invoke(root, "register", PIC, LMK, "--steps", "2,x")
    assert res.exit_code == 2 and "--steps" in res.stderr
    res = invoke(root, "register", PIC, LMK, "--thresholds", "1")
    assert res.exit_code == 2 and "T1,T2" in res.stderr
    res = invoke(root, "register", "NOPIC", LMK)
    assert res.exit_code == 2


def test_register_peak_and_convergence_options(world):
    root, sc, _ = world
    exact = invoke(root, "register", PIC, LMK, "--peak", "parabola", "--converge-max", "0", "--json")
    assert exact.exit_code == 0, exact.output
    doc = json.loads(exact.stdout)
    assert doc["options"]["peak"] == "parabola" and doc["options"]["converge_max"] == 0
    assert doc["landmarks"][0]["iterations"] == 10  # S16's schedule exactly
    capped = invoke(root, "register", PIC, LMK, "--converge-tol", "1e-9", "--converge-max", "1", "--json")
    row = json.loads(capped.stdout)["landmarks"][0]
    assert row["status"] == "not-converged" and row["iterations"] == 11
    assert invoke(root, "register", PIC, LMK, "--converge-tol", "0").exit_code == 2
    assert invoke(root, "register", PIC, LMK, "--peak", "spline").exit_code == 2


def test_register_then_solve_pose_with_surface_weights(world, tmp_path):
    """register's sigma columns feed solve-pose --weights surface; a table without them is refused
    with one line (exit 2)."""
    root, sc, _ = world
    reg = invoke(root, "register", PIC, LMK)
    assert reg.exit_code == 0, reg.output
    table = tmp_path / "reg.txt"
    table.write_text(reg.stdout)
    from spctool.cli.pose import measurements_from_table

    m = measurements_from_table(table)
    t = LandmarkTable.parse_text(reg.stdout)
    assert m.covariance[0, 0, 0] == pytest.approx(t["sigma_sample"][0] ** 2, rel=1e-3)
    assert m.covariance[0, 0, 1] == pytest.approx(
        t["rho_sl"][0] * t["sigma_sample"][0] * t["sigma_line"][0], rel=2e-3, abs=1e-9
    )
    bare = tmp_path / "bare.txt"
    bare.write_text(f"name sample line\n{LMK} 10.0 20.0\n")
    res = invoke(root, "solve-pose", PIC, "--measurements", bare, "--weights", "surface")
    assert res.exit_code == 2 and "--weights surface needs" in res.stderr
    assert len([ln for ln in res.stderr.strip().splitlines() if not ln.startswith("spctool: note:")]) == 1


@pytest.mark.parametrize("shading", ["facet", "gouraud"])
def test_register_image_space_template_shadings(world, shading):
    """``--template-shading`` reaches the templates: each shading registers the landmark within 0.05 px
    of its truth pixel, and the JSON's options echo the one asked for."""
    root, sc, _ = world
    res = invoke(root, "register", PIC, LMK, "--space", "image", "--template-shading", shading, "--json")
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    row = doc["landmarks"][0]
    assert row["status"] == "ok"
    assert abs(row["sample"] - sc.truth_pixel[0]) < 0.05 and abs(row["line"] - sc.truth_pixel[1]) < 0.05
    assert json.dumps(doc).count(f'"template_shading": "{shading}"') >= 1
