"""spctool.sim.maplets (make-maplets): SPC's GET_HEIGHTS projection of a shape onto maplet planes."""

import numpy as np
import pytest

from spctool.errors import SpcUsageError
from spctool.formats.icq import IcqShape, icq_cube_grid, write_icq
from spctool.formats.landmark import read_lmk
from spctool.formats.lists import read_lmrklist
from spctool.formats.maplet import read_map
from spctool.geometry.frames import orient_frame
from spctool.geometry.heightfield import maplet_node_positions
from spctool.sim.maplets import (
    landmark_names,
    make_maplets,
    project_heights,
    surface_points,
    tile_count,
    tile_directions,
)

R = 1.0


@pytest.fixture(scope="module")
def sphere():
    q = 128
    g = icq_cube_grid(q)
    v = R * g / np.linalg.norm(g, axis=-1, keepdims=True)
    return IcqShape(q, v, albedo=1.0 + 0.5 * v[..., 2])


def test_heights_on_a_sphere_are_within_one_percent_of_a_cell(sphere):
    scale, qsz = 0.01, 16
    dirs = np.vstack([tile_directions(6), [[0.0, 0.0, 1.0]], [[0.577, 0.577, 0.577]]])
    made = make_maplets(
        sphere, [f"S{k:05d}" for k in range(len(dirs))], surface_points(sphere, dirs), scale, qsz
    )
    for m, lmk in made:
        assert m.valid.all()
        p = maplet_node_positions(m)
        # every node lies on the sphere: |P| − R within 1 % of a cell (the ICQ's own bilinear cells
        # depart from the sphere by < 0.7 % of a 10 m cell at Q = 128)
        assert np.abs(np.linalg.norm(p, axis=-1) - R).max() < 0.01 * scale
        # ORIENT at the normal: UZ radial, UY East (no z component), UX = UY x UZ (South)
        v = np.asarray(lmk.vlm)
        np.testing.assert_allclose(lmk.uz, v / np.linalg.norm(v), atol=2e-4)
        assert abs(lmk.uy[2]) < 1e-12 or abs(lmk.uz[2]) > 0.9998
        np.testing.assert_allclose(np.cross(lmk.uy, lmk.uz), lmk.ux, atol=1e-12)
        assert abs(np.linalg.norm(v) - R) < 1e-4  # V on the surface ...
        assert abs(m.heights[qsz, qsz]) < 1e-3  # ... so the centre height is 0
        assert lmk.scale == scale and lmk.qsz == qsz and lmk.sigkm == 0.5 * scale and lmk.hflag == "T"
        # the albedo comes from the ICQ 4th column (1 + z/2 here), stored to 0.01
        np.testing.assert_allclose(m.albedo, 1.0 + 0.5 * p[..., 2], atol=0.006)


def test_get_heights_keeps_the_maximum_height(sphere):
    # a plane through the centre: every node's vertical crosses the sphere twice; the top wins
    ux, uy, uz = orient_frame(np.array([0.0, 0.0, 1.0]))
    scale, qsz = 0.05, 10
    ph = project_heights(sphere, [0.0, 0.0, 0.0], ux, uy, uz, scale, qsz)
    x = np.arange(-qsz, qsz + 1) * scale
    r2 = x[:, None] ** 2 + x[None, :] ** 2
    want = np.sqrt(R**2 - r2) / scale
    assert ph.valid.all()
    np.testing.assert_allclose(ph.heights[0], want, atol=0.01)
    # nodes outside the body's outline are missing
    ph2 = project_heights(sphere, [0.0, 0.0, 0.0], ux, uy, uz, 0.1, 12)
    outside = (np.arange(-12, 13)[:, None] ** 2 + np.arange(-12, 13)[None, :] ** 2) * 0.01 > 1.0001
    assert not ph2.valid[0][outside].any() and ph2.valid[0][~outside].all()


def test_keep_frame_keeps_v_and_axes(sphere):
    ux, uy, uz = orient_frame(np.array([[0.2, 0.3, 1.0]]))
    tilt_uz = uz + 0.1 * ux
    ux2, uy2, uz2 = orient_frame(tilt_uz)
    v = surface_points(sphere, uz)[0]
    ((m, lmk),) = make_maplets(sphere, ["KEEP01"], v[None], 0.01, 8, frames=(ux2, uy2, uz2))
    np.testing.assert_array_equal(lmk.vlm, v)
    np.testing.assert_array_equal(lmk.uz, uz2[0])
    assert np.abs(np.linalg.norm(maplet_node_positions(m), axis=-1) - R).max() < 0.01 * 0.01 + 1e-6


def test_tiling_and_names(sphere):
    d = tile_directions(500)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    assert abs(d.mean(axis=0)).max() < 0.01  # spread evenly
    assert abs(tile_count(sphere, 0.5) - 4 * np.pi * R**2 / 0.25) < 1.0  # area / spacing²
    assert landmark_names("TL", 3) == ["TL0001", "TL0002", "TL0003"]
    with pytest.raises(SpcUsageError):
        landmark_names("ABCDEF", 1)
    with pytest.raises(SpcUsageError):
        make_maplets(sphere, ["TOOLONGNAME"], [[0, 0, 1.0]], 0.01, 4)


def test_make_maplets_command(run_cli, tmp_path, sphere):
    (tmp_path / "SHAPEFILES").mkdir()
    small = IcqShape(32, sphere.vertices[:, ::4, ::4], sphere.albedo[:, ::4, ::4])
    write_icq(tmp_path / "SHAPEFILES" / "SHAPE.TXT", small)
    r = run_cli(
        "-C",
        tmp_path,
        "make-maplets",
        "--at",
        "AA0001",
        "0",
        "0",
        "1.2",
        "--at",
        "AA0002",
        "1",
        "0",
        "0",
        "--scale",
        "0.01",
        "--qsz",
        "8",
    )
    assert r.exit_code == 0, r.stderr
    assert "AA0001" in r.stdout and "AA0002" in r.stdout
    m = read_map(tmp_path / "MAPFILES" / "AA0001.MAP")
    lmk = read_lmk(tmp_path / "LMKFILES" / "AA0001.LMK")
    assert m.qsz == 8 and abs(m.scale - 0.01) < 1e-9 and m.valid.all()
    assert abs(np.linalg.norm(lmk.vlm) - 1.0) < 2e-3  # moved onto the (Q = 32) sphere
    assert read_lmrklist(tmp_path / "LMRKLIST.TXT").names == ["AA0001", "AA0002"]
    # refuses to overwrite, then re-frames an existing landmark with --overwrite
    r = run_cli(
        "-C", tmp_path, "make-maplets", "--at", "AA0001", "0", "0", "1", "--scale", "0.01", "--qsz", "8"
    )
    assert r.exit_code == 2 and "overwrite" in r.stderr
    r = run_cli(
        "-C", tmp_path, "make-maplets", "AA0002", "--keep-frame", "--overwrite", "--qsz", "4", "--json"
    )
    assert r.exit_code == 0, r.stderr
    assert read_map(tmp_path / "MAPFILES" / "AA0002.MAP").qsz == 4
    assert read_lmk(tmp_path / "LMKFILES" / "AA0002.LMK").qsz == 4
    r = run_cli(
        "-C", tmp_path, "make-maplets", "--tile", "0.6", "--scale", "0.01", "--qsz", "4", "--prefix", "TT"
    )
    assert r.exit_code == 0, r.stderr
    names = read_lmrklist(tmp_path / "LMRKLIST.TXT").names
    assert names[:2] == ["AA0001", "AA0002"] and sum(n.startswith("TT") for n in names) == tile_count(
        small, 0.6
    )
