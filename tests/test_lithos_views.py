"""The one builder of a maplet's picture views (:func:`spctool.batch.heights.landmark_views`, used by
``spctool lithos`` and ``batch --lithos``): PICTURES rows with their pixels, '*' rows left out, a
picture without photo or with a NaN pose skipped with a note, an LMK without PICTURES rows falling back
to the pictures of PICTLIST.TXT that see V."""

from __future__ import annotations

import numpy as np
import pytest
from heights_world import make_scene, write_workdir

from spctool.batch.heights import landmark_views
from spctool.formats.landmark import LandmarkPicture, read_lmk, write_lmk
from spctool.formats.workdir import WorkDir


@pytest.fixture(scope="module")
def scene():
    return make_scene(n_pictures=3, q=10, npx=96)


def test_rows_pixels_flags_and_notes(tmp_path, scene):
    start, _, views = scene
    names = write_workdir(tmp_path, start, views)
    wd = WorkDir(tmp_path)
    lmk = read_lmk(tmp_path / "LMKFILES" / "HW0001.LMK")
    lmk.pictures[1] = LandmarkPicture(names[1], 5.0, 6.0, "*")
    (tmp_path / "IMAGEFILES" / f"{names[2]}.DAT").unlink()
    notes = []
    got, skipped = landmark_views(wd, None, lmk, note=notes.append, thresholds=lambda pic: (3.0, 400.0))
    assert [v.name for v in got] == [names[0]] and skipped == [names[2]]
    assert got[0].pixel == pytest.approx(views[0].pixel, abs=1e-6)
    assert got[0].thresholds == (3.0, 400.0)
    np.testing.assert_allclose(got[0].photo.data, np.clip(views[0].photo, 0, 65535), atol=0.5)
    assert len(notes) == 1 and names[2] in notes[0] and "no photo" in notes[0]
    # a NaN pose is a picture left out, not a traceback
    path = tmp_path / "SUMFILES" / f"{names[0]}.SUM"
    text = path.read_text().splitlines()
    i = next(k for k, ln in enumerate(text) if ln.rstrip().endswith("SCOBJ"))
    text[i] = "    NaN    NaN    NaN    SCOBJ"
    path.write_text("\n".join(text) + "\n")
    got, skipped = landmark_views(wd, None, lmk, note=notes.append)
    assert got == [] and skipped == [names[0], names[2]]
    assert f"{path}" in notes[-2] and "NaN" in notes[-2]


def test_no_pictures_rows_falls_back_to_the_pictures_that_see_v(tmp_path, scene):
    start, _, views = scene
    names = write_workdir(tmp_path, start, views)
    lmk = read_lmk(tmp_path / "LMKFILES" / "HW0001.LMK")
    lmk.pictures = []
    write_lmk(tmp_path / "LMKFILES" / "HW0001.LMK", lmk)
    notes = []
    got, skipped = landmark_views(WorkDir(tmp_path), None, lmk, note=notes.append)
    assert [v.name for v in got] == names and skipped == []
    assert all(v.pixel is None for v in got)
    assert len(notes) == 1 and "no PICTURES rows" in notes[0] and "3 pictures" in notes[0]
