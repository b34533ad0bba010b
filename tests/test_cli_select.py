"""Tests of ``spctool lithos-select`` (spctool.cli.select) on a working directory built from the real
Rosetta 67P files (fixtures/real/rosetta-67p) plus synthetic landmarks that fail one check each."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from spctool.cli.main import cli
from spctool.formats.landmark import read_lmk, write_lmk
from spctool.formats.photo import Photo, write_photo
from spctool.formats.sumfile import read_sum
from spctool.geometry.frames import orient_frame

REAL = Path(__file__).resolve().parents[1] / "fixtures" / "real" / "rosetta-67p"
PIC = "W48230079013"
REAL_NAMES = ["FA0115", "FC0098", "GD0036"]
NOTE = "occlusion check skipped"


def _variant(src, name, **changes):
    lmk = read_lmk(src)
    lmk.name = name
    for k, v in changes.items():
        setattr(lmk, k, np.asarray(v, float) if k in ("vlm", "ux", "uy", "uz") else v)
    return lmk


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    root = tmp_path_factory.mktemp("wd")
    (root / "SUMFILES").mkdir()
    (root / "LMKFILES").mkdir()
    (root / "IMAGEFILES").mkdir()
    shutil.copy(REAL / f"{PIC}.SUM", root / "SUMFILES")
    for n in REAL_NAMES:
        shutil.copy(REAL / f"{n}.LMK", root / "LMKFILES")
    pic = read_sum(REAL / f"{PIC}.SUM")
    base = REAL / "FC0098.LMK"
    ref = read_lmk(base)
    to_cam = -(ref.vlm + pic.scobj)
    to_cam /= np.linalg.norm(to_cam)
    sun = pic.sz / np.linalg.norm(pic.sz)
    # facing the camera but with the Sun below the plane: Uz = a − 1.2 (a·s) s
    unlit_uz = to_cam - 1.2 * (to_cam @ sun) * sun
    ux, uy, uz = orient_frame(unlit_uz)
    variants = [
        _variant(base, "BACK01", ux=ref.ux, uy=-ref.uy, uz=-ref.uz),
        _variant(base, "OUT001", vlm=ref.vlm + 40.0 * ref.ux),
        _variant(base, "BIG001", scale=1.0),
        _variant(base, "UNLIT1", ux=ux, uy=uy, uz=uz),
    ]
    for lmk in variants:
        write_lmk(root / "LMKFILES" / f"{lmk.name}.LMK", lmk)
    names = REAL_NAMES + [v.name for v in variants]
    (root / "LMRKLIST.TXT").write_text("".join(f"{n}\n" for n in names) + "END\n")
    # a synthetic 16-bit photo: a smooth ramp inside THRSH
    s, ln = np.meshgrid(np.arange(pic.npx), np.arange(pic.nln))
    data = (1000 + 20 * s + 10 * ln).astype(np.uint16)
    write_photo(root / "IMAGEFILES" / f"{PIC}.DAT", Photo(data, name=PIC))
    return root


def invoke(workdir, *args):
    runner = CliRunner()
    return runner.invoke(cli, ["-C", str(workdir), "lithos-select", PIC, *args], catch_exceptions=False)


def parse(text):
    from spctool.formats.table import LandmarkTable

    return LandmarkTable.parse_text(text)


def test_default_table_lists_selected_maplets(workdir):
    res = invoke(workdir)
    assert res.exit_code == 0, res.stderr
    table = parse(res.stdout)
    assert table.names == REAL_NAMES
    assert list(table.columns) == [
        "name",
        "sample",
        "line",
        "range_km",
        "resolution_km_px",
        "emission",
        "incidence",
        "phase",
        "fraction_in_photo",
        "status",
    ]
    assert set(table["status"]) == {"ok"}
    assert table.picture == PIC and table.command == "lithos-select"
    # no shape: said once on stderr
    assert res.stderr.count(NOTE) == 1
    # predicted pixels close to the SUM's measured ones (spc-formats.md §2.5)
    pic = read_sum(REAL / f"{PIC}.SUM")
    measured = {lm.name: (lm.sample, lm.line) for lm in pic.landmarks}
    for n, s, ln in zip(table.names, table["sample"], table["line"]):
        assert np.hypot(s - measured[n][0], ln - measured[n][1]) < 1.5


def test_all_lists_rejected_with_first_failed_check(workdir):
    res = invoke(workdir, "--all")
    assert res.exit_code == 0, res.stderr
    table = parse(res.stdout)
    status = dict(zip(table.names, table["status"]))
    assert status == {
        "FA0115": "ok",
        "FC0098": "ok",
        "GD0036": "ok",
        "BACK01": "backfacing",
        "OUT001": "outside",
        "BIG001": "too-big",
        "UNLIT1": "unlit",
    }
    # rows keep the LMRKLIST order
    assert table.names == REAL_NAMES + ["BACK01", "OUT001", "BIG001", "UNLIT1"]


def test_resolution_options_and_settings(workdir, tmp_path):
    res = invoke(workdir, "--all", "--numlm", "0", "--reslm", "1")
    status = dict(zip(parse(res.stdout).names, parse(res.stdout)["status"]))
    # r_img ≈ 0.035 km/px >= 1 x 0.01 km: too coarse (checked before the size test)
    assert [status[n] for n in REAL_NAMES] == ["too-coarse"] * 3
    assert status["BIG001"] == "too-big" and status["BACK01"] == "backfacing"
    # INIT_LITHOS keys, and the command line overriding them
    settings = tmp_path / "INIT_LITHOS.TXT"
    settings.write_text("NUMLM= 0\nRESLM= 1.0\nEND\n")
    runner = CliRunner()
    args = ["-C", str(workdir), "--settings", str(settings), "lithos-select", PIC]
    out = runner.invoke(cli, args)
    assert out.exit_code == 0 and len(parse(out.stdout)) == 0
    out = runner.invoke(cli, args + ["--reslm", "10"])
    assert parse(out.stdout).names == REAL_NAMES


def test_json_fields(workdir):
    res = invoke(workdir, "--json", "--all")
    assert res.exit_code == 0, res.stderr
    doc = json.loads(res.stdout)
    for key in (
        "command",
        "picture",
        "spctool_version",
        "landmarks",
        "candidates",
        "selected",
        "status_counts",
        "occlusion",
        "options",
    ):
        assert key in doc
    assert doc["command"] == "lithos-select" and doc["picture"] == PIC
    assert doc["candidates"] == 7 and doc["selected"] == 3 and doc["occlusion"] == "skipped"
    assert doc["status_counts"] == {"ok": 3, "backfacing": 1, "outside": 1, "too-big": 1, "unlit": 1}
    assert doc["options"]["numlm"] == 200 and doc["options"]["fw_scale"] == "side"
    row = doc["landmarks"][0]
    assert set(row) == {
        "name",
        "sample",
        "line",
        "range_km",
        "resolution_km_px",
        "emission",
        "incidence",
        "phase",
        "fraction_in_photo",
        "status",
    }
    assert row["name"] == "FA0115" and row["sample"] == pytest.approx(534.36, abs=0.01)
    # behind-the-camera / NaN values would be null; this one is finite everywhere
    assert all(v is not None for v in row.values())


def test_explicit_candidates_and_chaining(workdir, tmp_path):
    res = invoke(workdir, "--maplets", str(REAL / "GD0036.LMK"), "--maplets", "FA0115 BACK01")
    assert res.exit_code == 0, res.stderr
    assert parse(res.stdout).names == ["GD0036", "FA0115"]
    # a table from an earlier run feeds --landmarks (stdin too)
    first = invoke(workdir, "--all")
    path = tmp_path / "sel.txt"
    path.write_text(first.stdout)
    again = invoke(workdir, "--landmarks", str(path))
    assert parse(again.stdout).names == REAL_NAMES
    piped = CliRunner().invoke(
        cli, ["-C", str(workdir), "lithos-select", PIC, "--landmarks", "-"], input=first.stdout
    )
    assert parse(piped.stdout).names == REAL_NAMES
    # -o writes the table to a file
    out = tmp_path / "out.txt"
    res = invoke(workdir, "-o", str(out))
    assert res.stdout == "" and parse(out.read_text()).names == REAL_NAMES


def test_require_and_empty_selection(workdir):
    assert invoke(workdir, "--require", "3").exit_code == 0
    res = invoke(workdir, "--require", "4")
    assert res.exit_code == 1 and "fewer than --require 4" in res.stderr
    # an empty selection is a valid result
    res = invoke(workdir, "--maplets", "BACK01")
    assert res.exit_code == 0 and len(parse(res.stdout)) == 0


def test_missing_landmark_is_one_line_error(workdir):
    res = invoke(workdir, "--maplets", "NOSUCH")
    assert res.exit_code == 2
    errors = [ln for ln in res.stderr.strip().splitlines() if ": note:" not in ln]  # (no INIT_LITHOS)
    assert len(errors) == 1 and "NOSUCH" in errors[0]


def test_overlay_png(workdir, tmp_path):
    from PIL import Image

    from spctool.figures import stretch_8bit

    png = tmp_path / "sel.png"
    res = invoke(workdir, "--overlay", str(png))
    assert res.exit_code == 0, res.stderr
    img = np.asarray(Image.open(io.BytesIO(png.read_bytes())).convert("RGB"))
    head = img.shape[0] - 1024  # the title band above the photo
    assert head > 0 and img.shape[1:] == (1024, 3) and np.all(img[:head] == 255, axis=-1).mean() > 0.5
    img = img[head:]
    pic = read_sum(REAL / f"{PIC}.SUM")
    s, ln = np.meshgrid(np.arange(pic.npx), np.arange(pic.nln))
    gray = stretch_8bit((1000 + 20 * s + 10 * ln).astype(np.uint16), pic.thrsh)
    differs = np.any(img != gray[:, :, None], axis=2)
    coloured = (img[:, :, 0] != img[:, :, 1]) | (img[:, :, 1] != img[:, :, 2])
    assert np.array_equal(differs, coloured)  # everything drawn is colour on a gray photo
    # outlines around each selected maplet: a ~28 px square (0.99 km at 0.035 km/px) near its pixel
    table = parse(res.stdout)
    for sm, lm in zip(table["sample"], table["line"]):
        r, c = int(round(lm - 1)), int(round(sm - 1))
        window = differs[r - 25 : r + 26, c - 25 : c + 26]
        assert window.sum() > 40
    far = differs.copy()
    far[430:560, 440:590] = False
    assert far.sum() == 0
    # outside THRSH the stretch saturates
    assert stretch_8bit(np.array([0, 500, 65535, 70000]), (500, 65535)).tolist() == [0, 0, 255, 255]


@pytest.fixture(scope="module")
def sphere_icq(tmp_path_factory):
    """A q = 16 ICQ sphere through FA0115: FC0098 and GD0036 lie 0.5–0.7 km below its surface."""
    from spctool.formats.icq import IcqShape, icq_cube_grid, write_icq

    radius = float(np.linalg.norm(read_lmk(REAL / "FA0115.LMK").vlm))
    grid = icq_cube_grid(16)
    verts = grid / np.linalg.norm(grid, axis=-1, keepdims=True) * radius
    path = tmp_path_factory.mktemp("shape") / "SPHERE.TXT"
    write_icq(path, IcqShape(q=16, vertices=verts), style="exact")
    return path


def test_occlusion_with_a_shape(workdir, sphere_icq, tmp_path):
    res = invoke(workdir, "--all", "--json", "--shape", str(sphere_icq))
    assert res.exit_code == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["occlusion"] == "checked" and NOTE not in res.stderr
    status = {row["name"]: row["status"] for row in doc["landmarks"]}
    assert [status[n] for n in REAL_NAMES] == ["ok", "occluded", "occluded"]
    # --no-occlusion does not even read the shape
    res = invoke(workdir, "--no-occlusion", "--shape", str(tmp_path / "missing.TXT"))
    assert res.exit_code == 0 and parse(res.stdout).names == REAL_NAMES and NOTE not in res.stderr
    # SHAPEFILES/SHAPE.TXT is the default shape
    wd2 = tmp_path / "wd2"
    shutil.copytree(workdir, wd2)
    (wd2 / "SHAPEFILES").mkdir()
    shutil.copy(sphere_icq, wd2 / "SHAPEFILES" / "SHAPE.TXT")
    assert parse(invoke(wd2).stdout).names == ["FA0115"]
    # a generous tolerance (a whole body diameter) keeps the buried ones
    assert parse(invoke(wd2, "--occlusion-tol", "1").stdout).names == REAL_NAMES


def test_occlusion_required_without_shape(workdir):
    res = invoke(workdir, "--occlusion")
    assert res.exit_code == 2 and "needs a shape model" in res.stderr
