"""Tests of ``spctool predict`` and ``spctool extract`` (spctool.cli.appearance) on a synthetic working
directory: a SUM written by spctool, a MAP file, an LMK file and a photo rendered by the independent
renderer of appearance_scene."""

from __future__ import annotations

import json
from pathlib import Path

import appearance_scene as sc
import numpy as np
import pytest
from click.testing import CliRunner

from spctool.cli.main import cli
from spctool.formats.landmark import Landmark, write_lmk
from spctool.formats.maplet import Maplet, read_map, write_map
from spctool.formats.photo import Photo, read_photo, write_photo
from spctool.formats.sumfile import Picture, write_sum
from spctool.formats.table import LandmarkTable
from spctool.geometry.camera import Camera
from spctool.stages.extract import extract
from spctool.stages.predict import predict

PIC = "SYN0001"
LMK = "SYN001"


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    root = tmp_path_factory.mktemp("wd")
    for d in ("SUMFILES", "MAPFILES", "LMKFILES", "IMAGEFILES"):
        (root / d).mkdir()
    syn = sc.make_maplet(q=24)
    maplet = Maplet.new(syn.scale, 24, syn.v, syn.ux, syn.uy, syn.uz, syn.heights, syn.albedo, name=LMK)
    write_map(root / "MAPFILES" / f"{LMK}.MAP", maplet)
    pos = syn.v + 0.5 * sc.direction(syn, 25.0, 200.0)
    cam = sc.look_at_camera(syn.v, pos)
    sun = sc.direction(syn, 40.0, 60.0)
    pic = Picture(name=PIC, utc="2020 JAN 01 00:00:00.000", npx=cam.npx, nln=cam.nln,
                  thrsh=np.array([5.0, 60000.0]), mmfl=cam.mmfl, ctr=cam.ctr, scobj=cam.scobj,
                  cx=cam.rotation[0], cy=cam.rotation[1], cz=cam.rotation[2], sz=sun, kmatrix=cam.kmatrix)
    write_sum(root / "SUMFILES" / f"{PIC}.SUM", pic)
    rendered = sc.render(cam, read_map(root / "MAPFILES" / f"{LMK}.MAP"), sun, offset=0.0)
    photo = np.clip(np.rint(rendered), 0, 65535)
    write_photo(root / "IMAGEFILES" / f"{PIC}.fits", Photo(photo.astype(np.uint16)))
    lmk = Landmark(name=LMK, hflag="T", bigmap_extra=None, qsz=24, scale=syn.scale, horizon=(-1, -1, -1, -1),
                   sigkm=0.5 * syn.scale, rmslmk=0.0, vlm=maplet.v, ux=maplet.ux, uy=maplet.uy, uz=maplet.uz,
                   sigma_lmk=np.zeros(3))
    write_lmk(root / "LMKFILES" / f"{LMK}.LMK", lmk)
    (root / "LMRKLIST.TXT").write_text(f"{LMK}\nEND\n")
    return root


def invoke(workdir, *args, stdin=None):
    return CliRunner().invoke(cli, ["-C", str(workdir), *args], input=stdin, catch_exceptions=False)


def _direct(workdir):
    """The stages called directly on the working directory's files (the CLI must agree)."""
    from spctool.formats.sumfile import read_sum

    pic = read_sum(workdir / "SUMFILES" / f"{PIC}.SUM")
    cam = Camera.from_picture(pic)
    m = read_map(workdir / "MAPFILES" / f"{LMK}.MAP")
    photo = read_photo(workdir / "IMAGEFILES" / f"{PIC}.fits")
    ex = extract(photo, m, cam, pic.sz, pic.thrsh)
    pr = predict(m, cam.position, pic.sz, extracted=ex)
    return ex, pr


def test_extract_writes_images_and_table(workdir, tmp_path):
    out = tmp_path / "ext"
    res = invoke(workdir, "extract", PIC, LMK, "--out-dir", str(out))
    assert res.exit_code == 0, res.output
    table = LandmarkTable.parse_text(res.stdout)
    assert table.names == [LMK] and table.command == "extract" and table.picture == PIC
    for col in ("sample", "line", "lambda", "phi", "cov", "ill", "res", "inv", "emission", "status"):
        assert col in table.columns
    ex, pr = _direct(workdir)
    assert table["status"] == ["ok"]
    assert table["cov"][0] == pytest.approx(ex.cov, abs=1e-6)
    assert table["ill"][0] == pytest.approx(ex.ill, abs=1e-6)
    assert table["lambda"][0] == pytest.approx(pr.lam, rel=1e-4)
    assert table["correlation"][0] > 0.99
    img = read_photo(out / f"{LMK}_{PIC}_extracted.pgm")
    assert img.data.shape == (49, 49) and img.data.dtype == np.uint8 and img.data.max() == 255
    np.testing.assert_array_equal(img.data > 0, ex.image > 0.5 * ex.image.max() / 255)


def test_predict_fits_images_carry_the_parameters(workdir, tmp_path):
    out = tmp_path / "pred"
    res = invoke(workdir, "predict", PIC, LMK, "--out-dir", str(out), "--image-format", "fits", "--json",
                 "--shadows", "cast")
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["command"] == "predict" and doc["images_written"] == 1
    assert doc["predict_options"]["shadows"] == "cast"
    row = doc["landmarks"][0]
    from astropy.io import fits

    with fits.open(out / f"{LMK}_{PIC}_predicted.fits") as hdul:
        hdr = hdul[0].header
        data = hdul[0].data
    assert hdr["LANDMARK"] == LMK and hdr["PICTURE"] == PIC and hdr["STAGE"] == "predicted"
    assert hdr["SHADOWS"] == "cast" and hdr["PHOTOMET"] == "spc"
    assert hdr["LAMBDA"] == pytest.approx(row["lambda"], rel=1e-9) and hdr["STATUS"] == row["status"]
    assert hdr["SAMPLE"] == pytest.approx(row["sample"]) and hdr["QSZ"] == 24 and hdr["AXIS1"] == "UY"
    assert data.shape == (49, 49) and data.dtype.kind == "f"
    assert data.max() == pytest.approx(row["lambda"] * data.max() / row["lambda"])  # finite, scaled by lambda
    assert np.count_nonzero(data) > 0.8 * data.size


def test_default_landmarks_come_from_selection(workdir):
    res = invoke(workdir, "extract", PIC)
    assert res.exit_code == 0, res.output
    table = LandmarkTable.parse_text(res.stdout)
    assert table.names == [LMK]


def test_table_pixels_and_recentring(workdir, tmp_path):
    first = invoke(workdir, "extract", PIC, LMK)
    table = LandmarkTable.parse_text(first.stdout)
    s0, l0 = table["sample"][0], table["line"][0]
    moved = LandmarkTable.from_rows([{"name": LMK, "sample": s0 + 2.5, "line": l0, "status": "ok"}]).to_text()
    path = tmp_path / "moved.txt"
    path.write_text(moved)
    res = invoke(workdir, "extract", PIC, "--landmarks", str(path), "--at-table-pixels")
    t2 = LandmarkTable.parse_text(res.stdout)
    assert t2["sample"][0] == pytest.approx(s0 + 2.5, abs=1e-4)
    assert t2["line"][0] == pytest.approx(l0, abs=1e-4)
    assert t2["predicted_sample"][0] == pytest.approx(s0, abs=1e-4)
    assert t2["correlation"][0] < table["correlation"][0]  # a 2.5 px error decorrelates
    res = invoke(workdir, "extract", PIC, "--landmarks", "-", stdin=moved)
    assert LandmarkTable.parse_text(res.stdout)["sample"][0] == pytest.approx(s0, abs=1e-4)


def test_criteria_and_options(workdir):
    res = invoke(workdir, "extract", PIC, LMK, "--criteria", "0,60,.25,.25,0,0.1")
    assert LandmarkTable.parse_text(res.stdout)["status"] == ["removed-rsmx"]
    res = invoke(workdir, "extract", PIC, LMK, "--criteria", "0,60,.25,.25,0,0.1", "--no-removal")
    assert LandmarkTable.parse_text(res.stdout)["status"] == ["ok"]
    res = invoke(workdir, "extract", PIC, LMK, "--no-filter", "--subsample", "1", "--linearized", "--json")
    doc = json.loads(res.stdout)
    assert doc["extract_options"]["apply_filter"] is False and doc["landmarks"][0]["subsample"] == 1
    res = invoke(workdir, "extract", PIC, LMK, "--criteria", "1,2")
    assert res.exit_code == 2 and "criteria" in res.stderr
    res = invoke(workdir, "extract", PIC, LMK, "--thresholds", "1e9,2e9")  # every DN rejected
    t = LandmarkTable.parse_text(res.stdout)
    assert t["ill"][0] == 0.0 and t["status"] == ["removed-ilim"]


def test_missing_photo_and_maplet(workdir, tmp_path):
    bare = tmp_path / "bare"
    (bare / "SUMFILES").mkdir(parents=True)
    (bare / "MAPFILES").mkdir()
    for f in ("SUMFILES", "MAPFILES"):
        for p in (workdir / f).iterdir():
            (bare / f / p.name).write_bytes(p.read_bytes())
    res = invoke(bare, "extract", PIC, LMK)
    assert res.exit_code == 2 and "no photo" in res.stderr
    res = invoke(bare, "predict", PIC, LMK, "NOPE01")  # a named unknown landmark: exit 2 (every command)
    assert res.exit_code == 2 and "landmark NOPE01 (file not found)" in res.stderr
    table = tmp_path / "two.txt"  # a table row without a maplet: a no-maplet row
    table.write_text(f"name sample line\n{LMK} nan nan\nNOPE01 nan nan\n")
    res = invoke(bare, "predict", PIC, "--landmarks", str(table))
    assert res.exit_code == 0
    t = LandmarkTable.parse_text(res.stdout)
    assert t["lambda"][0] == 1.0 and t["status"] == ["ok", "no-maplet"]
    assert "no photo" in res.stderr
    # --photo and --flip-rows: a bottom-up copy of the photo read with --flip-rows gives the same result
    src = read_photo(workdir / "IMAGEFILES" / f"{PIC}.fits")
    flipped = tmp_path / "flipped.fits"
    write_photo(flipped, Photo(np.ascontiguousarray(src.data[::-1])))
    a = LandmarkTable.parse_text(invoke(workdir, "extract", PIC, LMK).stdout)
    b = invoke(bare, "extract", PIC, LMK, "--photo", str(flipped), "--flip-rows")
    b = LandmarkTable.parse_text(b.stdout)
    assert a["correlation"][0] == pytest.approx(b["correlation"][0], abs=1e-9)
    assert Path(flipped).exists()


def test_auto_shadows_are_said_on_stderr(tmp_path, run_cli):
    """The shipped demo's photos carry their cast shadows above THRSH T1 = 1 DN: with the default
    ``--shadows auto`` the landmarks whose maplets cast enough shadow are predicted with them, and -v
    says so in one line naming them and T1 (the default adapting: no note without -v);
    ``--shadows spc`` keeps SPC's rule and says nothing."""
    from spctool.sim.demo import copy_demo

    root = copy_demo(tmp_path / "demo")
    pic = sorted(p.stem for p in (root / "SUMFILES").glob("*.SUM"))[0]
    for command in ("predict", "extract"):
        plain = run_cli("-C", root, command, pic)
        assert plain.exit_code == 0 and "cast shadows" not in plain.stderr
        res = run_cli("-v", "-C", root, command, pic)
        assert res.exit_code == 0
        notes = [ln for ln in res.stderr.splitlines() if "predicted with their cast shadows" in ln]
        assert len(notes) == 1 and "B02176" in notes[0] and "T1 = 1 DN" in notes[0], res.stderr
        quiet = run_cli("-v", "-C", root, command, pic, "--shadows", "spc")
        assert quiet.exit_code == 0 and "cast shadows" not in quiet.stderr
