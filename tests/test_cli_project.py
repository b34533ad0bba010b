"""spctool project: landmark -> pixel and pixel -> line of sight on real Rosetta data."""

import json
import shutil

import numpy as np
import pytest

from spctool.formats.sumfile import read_sum
from spctool.formats.table import LandmarkTable

EXPECTED = {"FA0115": (0.83, 1.11), "FC0098": (0.04, 0.45), "GD0036": (-0.79, 0.17)}


@pytest.fixture
def rosetta_workdir(real, tmp_path):
    (tmp_path / "SUMFILES").mkdir()
    (tmp_path / "LMKFILES").mkdir()
    shutil.copy(real / "rosetta-67p/W48230079013.SUM", tmp_path / "SUMFILES")
    for name in EXPECTED:
        shutil.copy(real / f"rosetta-67p/{name}.LMK", tmp_path / "LMKFILES")
    return tmp_path


def test_project_every_landmark_of_the_workdir(run_cli, rosetta_workdir):
    r = run_cli("-C", rosetta_workdir, "project", "W48230079013")
    assert r.exit_code == 0, r.stderr
    table = LandmarkTable.parse_text(r.stdout)
    measured = {
        lm.name: (lm.sample, lm.line)
        for lm in read_sum(rosetta_workdir / "SUMFILES/W48230079013.SUM").landmarks
    }
    assert sorted(table.names) == sorted(EXPECTED)
    for name, s, ln, status in zip(table.names, table["sample"], table["line"], table["status"]):
        ds, dl = s - measured[name][0], ln - measured[name][1]
        assert np.hypot(ds, dl) < 1.5 and status == "ok"
        assert (ds, dl) == pytest.approx(EXPECTED[name], abs=0.01)


def test_project_json_and_explicit_lmk(run_cli, real):
    r = run_cli("project", real / "rosetta-67p/W48230079013.SUM", real / "rosetta-67p/FA0115.LMK", "--json")
    assert r.exit_code == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["picture"] == "W48230079013" and doc["landmarks"][0]["name"] == "FA0115"
    assert doc["landmarks"][0]["sample"] == pytest.approx(534.36, abs=0.01)


def test_inverse_line_of_sight_round_trip(run_cli, rosetta_workdir):
    r = run_cli("-C", rosetta_workdir, "project", "W48230079013", "--inverse", "534.36", "476.33", "--json")
    assert r.exit_code == 0, r.stderr
    doc = json.loads(r.stdout)
    d = np.array(doc["direction_body"])
    assert np.linalg.norm(d) == pytest.approx(1.0)
    # the ray passes close to FA0115's VLM (that pixel is its projection)
    from spctool.formats.landmark import read_lmk

    v = read_lmk(rosetta_workdir / "LMKFILES/FA0115.LMK").vlm
    p = np.array(doc["spacecraft_position"])
    off = (v - p) - ((v - p) @ d) * d
    assert np.linalg.norm(off) < 0.01  # km, i.e. well under a pixel at 170 km
    assert "no shape model" in r.stderr


def test_inverse_with_a_shape_hits_the_surface(run_cli, rosetta_workdir, tmp_path):
    # a sphere of radius 2.2 km around the origin stands in for the comet
    from spctool.formats.icq import IcqShape, icq_cube_grid, write_icq

    q = 16
    cube = icq_cube_grid(q)
    verts = 2.2 * cube / np.linalg.norm(cube, axis=-1, keepdims=True)
    (rosetta_workdir / "SHAPEFILES").mkdir()
    write_icq(
        rosetta_workdir / "SHAPEFILES/SHAPE.TXT",
        IcqShape(q=q, vertices=verts, albedo=None),
        style="exact",
        seams="unify",
    )
    r = run_cli("-C", rosetta_workdir, "project", "W48230079013", "--inverse", "512", "512", "--json")
    assert r.exit_code == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["surface_point"] is not None
    assert doc["radius_km"] == pytest.approx(2.2, rel=0.01)
