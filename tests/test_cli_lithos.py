"""``spctool lithos`` (LITHOS "Find heights") on a small rendered working directory with known truth
(tests/heights_world.py): MAP and LMK rewritten atomically with a .bak, the heights closer to the
truth; too few Sun azimuths: exit 1, one line, files unchanged."""

from __future__ import annotations

import json

import numpy as np
import pytest
from heights_world import make_scene, rms, write_workdir

from spctool.formats.landmark import read_lmk
from spctool.formats.maplet import read_map


@pytest.fixture(scope="module")
def scene():
    return make_scene(n_pictures=4)


def _centred(h, v):
    return h - h[v].mean()


def test_lithos_writes_refined_map_and_lmk(tmp_path, scene, run_cli):
    start, truth, views = scene
    write_workdir(tmp_path, start, views, truth)
    before_bytes = (tmp_path / "MAPFILES" / "HW0001.MAP").read_bytes()
    figs = tmp_path / "figs"
    res = run_cli("-C", tmp_path, "lithos", "HW0001", "--json", "--figures", figs)
    assert res.exit_code == 0, res.stderr
    doc = json.loads(res.stdout)
    m = doc["meta"]["maplets"][0] if "meta" in doc else doc["maplets"][0]
    assert m["status"] == "ok" and m["converged"]
    new = read_map(tmp_path / "MAPFILES" / "HW0001.MAP")
    assert (tmp_path / "MAPFILES" / "HW0001.MAP.bak").read_bytes() == before_bytes
    assert (tmp_path / "LMKFILES" / "HW0001.LMK.bak").exists()
    v = truth.valid
    e0 = rms(_centred(start.heights, v), _centred(truth.heights, v), v)
    e1 = rms(_centred(new.heights, v), _centred(truth.heights, v), v)
    assert 3.0 * e1 <= e0
    assert np.corrcoef(new.albedo[v], truth.albedo[v])[0, 1] >= 0.9
    lmk = read_lmk(tmp_path / "LMKFILES" / "HW0001.LMK")
    assert [p.flag for p in lmk.pictures] == [""] * 4
    assert np.array_equal(lmk.vlm, read_lmk(tmp_path / "LMKFILES" / "HW0001.LMK.bak").vlm)
    moved = [abs(p.sample - w.pixel[0]) + abs(p.line - w.pixel[1]) for p, w in zip(lmk.pictures, views)]
    assert max(moved) > 0.0 and max(moved) < 2.0  # re-registered, and close to the true centre
    assert (figs / "HW0001_heights.png").stat().st_size > 1000
    assert (figs / "HW0001_rerender.png").stat().st_size > 1000


def test_lithos_dry_run_writes_nothing(tmp_path, scene, run_cli):
    start, _, views = scene
    write_workdir(tmp_path, start, views)
    before = (tmp_path / "MAPFILES" / "HW0001.MAP").read_bytes()
    res = run_cli("-C", tmp_path, "lithos", "--dry-run", "--iterations", "1")
    assert res.exit_code == 0, res.stderr
    assert "HW0001" in res.stdout and "ok" in res.stdout
    assert (tmp_path / "MAPFILES" / "HW0001.MAP").read_bytes() == before
    assert not (tmp_path / "MAPFILES" / "HW0001.MAP.bak").exists()


def test_lithos_too_few_sun_azimuths_exit_1_unchanged(tmp_path, scene, run_cli):
    start, _, views = scene
    write_workdir(tmp_path, start, views[:2])
    before = (tmp_path / "MAPFILES" / "HW0001.MAP").read_bytes()
    lmk_before = (tmp_path / "LMKFILES" / "HW0001.LMK").read_bytes()
    res = run_cli("-C", tmp_path, "lithos", "HW0001")
    assert res.exit_code == 1
    lines = [ln for ln in res.stderr.splitlines() if "note:" not in ln]  # notes: no INIT_LITHOS
    assert len(lines) == 1 and "HW0001" in lines[0] and "Sun azimuth" in lines[0], res.stderr
    assert (tmp_path / "MAPFILES" / "HW0001.MAP").read_bytes() == before
    assert (tmp_path / "LMKFILES" / "HW0001.LMK").read_bytes() == lmk_before
    assert not (tmp_path / "MAPFILES" / "HW0001.MAP.bak").exists()


def test_lithos_missing_landmark_exit_2(tmp_path, run_cli):
    res = run_cli("-C", tmp_path, "lithos", "NOPE01")
    assert res.exit_code == 2
    assert "NOPE01" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.parametrize("bad", ["name", "output"])
def test_lithos_bad_input_found_before_any_maplet_is_written(tmp_path, scene, run_cli, bad):
    """A landmark without an LMK named after a good one, or an -o that cannot take the table: exit 2
    with one line, and the good maplet unchanged (it was once solved and written first)."""
    start, _, views = scene
    write_workdir(tmp_path, start, views)
    before = (tmp_path / "MAPFILES" / "HW0001.MAP").read_bytes()
    (tmp_path / "out").mkdir()
    args = ["HW0001", "NOPE01"] if bad == "name" else ["HW0001", "-o", tmp_path / "out"]
    res = run_cli("-C", tmp_path, "lithos", *args, "--iterations", "1")
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.stderr.splitlines() if "note:" not in ln]
    assert len(lines) == 1 and ("NOPE01" in lines[0] if bad == "name" else "is a directory" in lines[0])
    assert (tmp_path / "MAPFILES" / "HW0001.MAP").read_bytes() == before
    assert not (tmp_path / "MAPFILES" / "HW0001.MAP.bak").exists()


def test_lithos_keeps_the_lmk_vlm_to_its_own_precision(tmp_path, run_cli):
    """Without --recentre the VLM is not moved: it was replaced by the MAP's V, which the MAP holds as
    real*4 (7 µm off on the demo's B01536); with --recentre it moves by V's move, from its own value."""
    import shutil
    from pathlib import Path

    demo = Path(__file__).resolve().parents[1] / "fixtures" / "demo"
    shutil.copytree(demo, tmp_path / "wd")
    wd = tmp_path / "wd"
    before = read_lmk(wd / "LMKFILES" / "B01536.LMK").vlm
    assert not np.array_equal(before, read_map(wd / "MAPFILES" / "B01536.MAP").v)  # real*4 there
    res = run_cli("-q", "-C", wd, "lithos", "B01536", "--force", "--iterations", "1")
    assert res.exit_code == 0, res.output
    assert np.array_equal(read_lmk(wd / "LMKFILES" / "B01536.LMK").vlm, before)


def test_lithos_warns_of_a_picture_whose_file_is_corrupt(tmp_path, run_cli):
    """A picture left out because its photo is cut short or its SUM is garbage is a warning naming the
    file (it was a note, and the maplet was rewritten from the others with exit 0, unnoticed); a picture
    simply without a photo stays a note.  batch --lithos (refine_maplet) records the same lines."""
    start, truth, views = make_scene(n_pictures=6)
    write_workdir(tmp_path, start, views, truth)
    dat = tmp_path / "IMAGEFILES" / "HP0000000002.DAT"
    dat.write_bytes(dat.read_bytes()[: dat.stat().st_size // 2])
    (tmp_path / "SUMFILES" / "HP0000000003.SUM").write_text("garbage\n")
    (tmp_path / "IMAGEFILES" / "HP0000000004.DAT").unlink()
    res = run_cli("-C", tmp_path, "lithos", "HW0001", "--dry-run", "--iterations", "1", "--json")
    assert res.exit_code == 0, res.stderr
    warned = [ln for ln in res.stderr.splitlines() if "warning:" in ln]
    assert len(warned) == 2
    assert "HP0000000002" in warned[0] and "HP0000000002.DAT" in warned[0] and "cut short" in warned[0]
    assert "HP0000000003" in warned[1] and "HP0000000003.SUM" in warned[1]
    noted = [ln for ln in res.stderr.splitlines() if "note:" in ln and "HP0000000004" in ln]
    assert len(noted) == 1 and "no photo" in noted[0]
    doc = json.loads(res.stdout)
    m = doc["meta"]["maplets"][0] if "meta" in doc else doc["maplets"][0]
    assert sorted(m["skipped_pictures"]) == ["HP0000000002", "HP0000000003", "HP0000000004"]
    from spctool.batch.heights import refine_maplet

    out = refine_maplet(tmp_path, "HW0001")
    assert len(out["warnings"]) == 2 and "HP0000000002.DAT" in out["warnings"][0]
