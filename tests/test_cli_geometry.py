"""``spctool geometry`` and ``batch --rounds`` on working directories with known truth: a biased map is
refined from the pictures (truth VLMs of tests/batch_world.py), the files are written as SPC's READ
statements read them, and a second round measures better than the first."""

from __future__ import annotations

import dataclasses
import json
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from batch_world import make_world

from spctool.formats.landmark import read_lmk, write_lmk
from spctool.formats.maplet import read_map, write_map

ERR_KM = 3e-5  # 3 cm: three maplet cells


def _world(root, n_pictures):
    make_world(root, n_pictures=n_pictures, n_landmarks=9)
    return root, {p.stem: read_lmk(p).vlm.copy() for p in sorted((root / "LMKFILES").glob("*.LMK"))}


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    return _world(tmp_path_factory.mktemp("geometry_world"), 8)


@pytest.fixture(scope="module")
def pristine20(tmp_path_factory):
    """Twenty pictures (the issue's simulated world for batch --rounds)."""
    return _world(tmp_path_factory.mktemp("geometry_world20"), 20)


def _biased(pristine, dest: Path) -> dict:
    """A copy whose LMK VLMs (and MAP V) are off by 3 cm (1σ per axis), SIGMA_LMK saying so."""
    root, truth = pristine
    shutil.copytree(root, dest)
    _move_landmarks(dest, sorted(truth), np.random.default_rng(5))
    return truth


def _move_landmarks(root: Path, names, rng, err_km: float = ERR_KM) -> None:
    """Each LMK VLM and its MAP's V moved by ``err_km`` (1σ per axis), the LMK's SIGMA_LMK saying so."""
    for name in names:
        p = root / "LMKFILES" / f"{name}.LMK"
        lmk = read_lmk(p)
        lmk = dataclasses.replace(
            lmk, vlm=lmk.vlm + rng.normal(size=3) * err_km, sigma_lmk=np.full(3, err_km)
        )
        write_lmk(p, lmk)
        m = read_map(root / "MAPFILES" / f"{name}.MAP")
        m.v = lmk.vlm
        write_map(root / "MAPFILES" / f"{name}.MAP", m)


def _fortran_d(text: str) -> float:
    return float(text.replace("D", "E").replace("d", "e"))


def test_geometry_refines_a_biased_map_and_writes_what_spc_reads(pristine, run_cli, tmp_path):
    wd = tmp_path / "wd"
    truth = _biased(pristine, wd)
    before = {n: read_lmk(wd / "LMKFILES" / f"{n}.LMK").vlm for n in truth}
    out = tmp_path / "out"
    assert run_cli("-q", "-C", wd, "batch", "--out-dir", out).exit_code == 0  # no-pose pictures, not failed
    sums_before = {p.name: p.read_bytes() for p in (wd / "SUMFILES").glob("*.SUM")}
    res = run_cli("-C", wd, "geometry", "--from-batch", out, "--dry-run", "--json")
    assert res.exit_code == 0, res.stderr
    assert {p.name: p.read_bytes() for p in (wd / "SUMFILES").glob("*.SUM")} == sums_before  # nothing written
    assert not list((wd / "LMKFILES").glob("*.bak"))
    doc = json.loads(res.stdout)
    assert doc["n_landmarks_refined"] == 9 and doc["measurements"] == {"ok": 72}
    assert doc["rms_after_px"] < 0.05 < 1.0 < doc["rms_before_px"]
    res = run_cli("-C", wd, "geometry", "--from-batch", out, "--report-dir", "rep", "--plot", "geo.png")
    assert res.exit_code == 0, res.stderr
    after = {n: read_lmk(wd / "LMKFILES" / f"{n}.LMK") for n in truth}
    e0 = np.array([before[n] - truth[n] for n in truth])
    e1 = np.array([after[n].vlm - truth[n] for n in truth])
    rms0, rms1 = np.sqrt(np.mean(np.sum(e0**2, 1))), np.sqrt(np.mean(np.sum(e1**2, 1)))
    # the absolute error is bounded by the landmark priors (the gauge: their mean); the relative map is exact
    rel = e1 - e1.mean(axis=0)
    assert rms1 < 0.5 * rms0
    assert np.sqrt(np.mean(np.sum(rel**2, 1))) < 0.05 * rms0
    sig = np.array([after[n].sigma_lmk for n in truth])
    assert np.all(np.abs(e1) < 3 * sig)  # the posterior 1σ covers the error
    assert (wd / "rep" / "RESIDUALS.txt").exists() and (wd / "geo.png").stat().st_size > 10_000
    for n in truth:  # .bak kept; SPC's READ formats give back the numbers written
        assert (wd / "LMKFILES" / f"{n}.LMK.bak").exists()
        lines = (wd / "LMKFILES" / f"{n}.LMK").read_text().splitlines()
        # LITHOS: READ(10,'(3D20.10)') VLM on line 5; SIGMA_LMK on line 9; (2D20.10) SIGKM, RMSLMK on line 4
        vlm = [_fortran_d(lines[4][i : i + 20]) for i in (0, 20, 40)]
        assert np.allclose(vlm, after[n].vlm, rtol=1e-10, atol=0) and lines[4][63:66] == "VLM"
        assert np.allclose(
            [_fortran_d(lines[8][i : i + 20]) for i in (0, 20, 40)], after[n].sigma_lmk, rtol=1e-10
        )
        assert 0 < _fortran_d(lines[3][20:40]) < 0.05  # RMSLMK, pixels
        # PICTURES rows (A12,2F10.2): every picture, the measured pixel
        k = lines.index("PICTURES")
        rows = lines[k + 1 : k + 9]
        assert sorted(r[:12].strip() for r in rows) == sorted(p[:-4] for p in sums_before)
        assert all(abs(float(r[12:22])) > 0 and abs(float(r[22:32])) > 0 for r in rows)
        # MAP header V (real*4, big-endian, bytes 16-27): the VLM
        raw = (wd / "MAPFILES" / f"{n}.MAP").read_bytes()
        v = struct.unpack(">3f", raw[15:27])
        assert np.allclose(v, after[n].vlm, rtol=1e-6)
    # the SUMs: new pose lines (3D20.10) SCOBJ, the batch's LANDMARKS rows
    text = (wd / "SUMFILES" / "T000000001A1.SUM").read_text()
    assert "LANDMARKS" in text and text.count("\n") > 20


def test_batch_rounds_two_measures_better_than_one(pristine20, run_cli, tmp_path):
    wd = tmp_path / "wd"
    _biased(pristine20, wd)
    inputs = {p: p.read_bytes() for d in ("LMKFILES", "MAPFILES", "SUMFILES") for p in (wd / d).iterdir()}
    assert run_cli("-q", "-C", wd, "batch", "--rounds", "2", "--out-dir", tmp_path / "cycle").exit_code == 0
    truth = json.loads((wd / "TRUTH.json").read_text())
    true_pos = {p["name"]: -np.array(p["scobj"]) for p in truth["pictures"]}

    def round_stats(k):
        doc = json.loads((tmp_path / "cycle" / f"ROUND{k}" / "BATCH_SUMMARY.json").read_text())
        found = sum(p["found"] for p in doc["pictures"])
        ok = [p for p in doc["pictures"] if p["status"] == "ok"]
        err = []
        for name in true_pos:
            text = (tmp_path / "cycle" / f"ROUND{k}" / "SUMFILES" / f"{name}.SUM").read_text().splitlines()
            scobj = np.array([_fortran_d(text[4][i : i + 20]) for i in (0, 20, 40)])
            err.append(np.linalg.norm(-scobj - true_pos[name]))
        return found, len(ok), float(np.sqrt(np.mean(np.square(err))))

    f1, ok1, e1 = round_stats(1)
    f2, ok2, e2 = round_stats(2)
    print(
        f"round 1: {f1} found, {ok1} ok, pose error {1e5 * e1:.2f} cm; round 2: {f2}, {ok2}, {1e5 * e2:.2f}"
    )
    assert f2 >= f1 and ok2 >= ok1 and ok2 == 20
    assert e2 < e1
    # the working directory was not written (its files are hard-linked into the refined map, whose
    # writes replace the links); the refined map is a working directory of its own
    assert not list((wd / "LMKFILES").glob("*.bak"))
    assert inputs == {p: p.read_bytes() for p in inputs}
    assert (tmp_path / "cycle" / "MAP2" / "GEOMETRY.json").exists()
    assert (tmp_path / "cycle" / "MAP2" / "IMAGEFILES").is_symlink()
    # resuming the finished cycle changes nothing
    lmks = tmp_path / "cycle" / "MAP2" / "LMKFILES"
    stamp = {p: p.stat().st_mtime_ns for p in lmks.iterdir()}
    content = {p.name: p.read_bytes() for p in lmks.iterdir()}
    run_cli("-q", "-C", wd, "batch", "--rounds", "2", "--out-dir", tmp_path / "cycle")
    assert stamp == {p: p.stat().st_mtime_ns for p in lmks.iterdir()}
    # a run killed while the refined map was being built (a .partial folder, no round 2) resumes to the
    # same files, none lost or written twice
    (tmp_path / "cycle" / "MAP2").rename(tmp_path / "cycle" / "MAP2.partial")
    (tmp_path / "cycle" / "MAP2.partial" / "GEOMETRY.json").unlink()
    shutil.rmtree(tmp_path / "cycle" / "ROUND2")
    assert run_cli("-q", "-C", wd, "batch", "--rounds", "2", "--out-dir", tmp_path / "cycle").exit_code == 0
    assert not (tmp_path / "cycle" / "MAP2.partial").exists()
    assert content == {p.name: p.read_bytes() for p in lmks.iterdir()}
    assert round_stats(2) == (f2, ok2, e2)


def test_batch_rounds_rebuild_a_refined_map_whose_inputs_changed(pristine, run_cli, tmp_path):
    """A refined map is reused on resume only while what it was built from is unchanged: a landmark
    moved in the working directory after the run, ``--lithos`` added, or ``--force``, build it again
    (a stale map once stayed, and round 2 measured on it); an output folder inside the working
    directory is not linked into the map."""
    wd = tmp_path / "wd"
    _biased(pristine, wd)
    cycle = wd / "cycle"  # inside the working directory

    def rounds(*extra):
        res = run_cli("-q", "-C", wd, "batch", "--rounds", "2", "--out-dir", cycle, *extra)
        assert res.exit_code == 0, res.output
        return json.loads((cycle / "MAP2" / "GEOMETRY.json").read_text())

    first = rounds()
    assert len(first["inputs"]) == 64 and not (cycle / "MAP2" / "cycle").exists()
    summary = cycle / "MAP2" / "GEOMETRY.json"
    lmk = cycle / "MAP2" / "LMKFILES" / "BW0001.LMK"
    refined, built = read_lmk(lmk).vlm, summary.stat().st_mtime_ns
    assert rounds()["inputs"] == first["inputs"] and summary.stat().st_mtime_ns == built  # unchanged: kept
    # the working directory's landmark moved by 4 cm: the map is built again from it
    src = read_lmk(wd / "LMKFILES" / "BW0001.LMK")
    write_lmk(wd / "LMKFILES" / "BW0001.LMK", dataclasses.replace(src, vlm=src.vlm + [4e-5, 0.0, 0.0]))
    second = rounds()
    assert second["inputs"] != first["inputs"] and summary.stat().st_mtime_ns != built
    assert np.linalg.norm(read_lmk(lmk).vlm - refined) > 1e-7  # refined again, from the moved landmark
    built = summary.stat().st_mtime_ns
    assert rounds("--force")["inputs"] == second["inputs"] and summary.stat().st_mtime_ns != built


def test_geometry_reports_the_residuals_of_what_it_writes_when_no_landmark_is_refined(
    pristine, run_cli, tmp_path
):
    """Every landmark undetermined (--min-parallax 90): the VLMs keep their prior and the poses are fitted
    to them, so the rms reported after the solve is the rms of the files written, as a dry run on them
    measures it (the poses were once fitted to VLMs moved in the solve, then put back: 0.0529 -> 0.0391
    px reported on the demo, 0.0561 px in the files)."""
    root, _ = pristine
    wd = tmp_path / "wd"
    shutil.copytree(root, wd)
    out = tmp_path / "out"
    assert run_cli("-q", "-C", wd, "batch", "--out-dir", out).exit_code == 0
    res = run_cli("-C", wd, "geometry", "--from-batch", out, "--min-parallax", "90", "--json")
    assert res.exit_code == 0, res.stderr
    solved = json.loads(res.stdout)
    assert solved["n_landmarks_refined"] == 0 and solved["written"]
    res = run_cli("-C", wd, "geometry", "--tables", out, "--dry-run", "--json")
    assert res.exit_code == 0, res.stderr
    again = json.loads(res.stdout)
    assert again["n_pictures"] == solved["n_pictures"] and again["measurements"] == {"ok": 72}
    assert again["rms_before_px"] == pytest.approx(solved["rms_after_px"], rel=1e-6)
    assert solved["rms_after_px"] <= solved["rms_before_px"]


def _measured(pristine, run_cli, tmp_path):
    """(working directory, batch output) of a copy of the pristine world measured by one batch, with an
    empty folder ``no-tables`` in it (``--tables no-tables``: the SUM rows weighed by --sigma-px)."""
    wd = tmp_path / "wd"
    shutil.copytree(pristine[0], wd)
    out = tmp_path / "out"
    assert run_cli("-q", "-C", wd, "batch", "--out-dir", out).exit_code == 0
    (wd / "no-tables").mkdir()
    return wd, out


def test_geometry_reports_the_sigmas_it_writes_when_chi2_per_dof_exceeds_one(pristine, run_cli, tmp_path):
    """chi2/dof above 1 (SUM rows weighed at 0.002 px): SIGMA_LMK is written scaled by sqrt(chi2/dof), and
    the table's sigmas and the formal best-80 % figure are those written (they were the unscaled ones:
    0.144 m reported for B01536 on the demo with --sigma-floor-px 0, sqrt(1.755) times that written)."""
    _, truth = pristine
    wd, out = _measured(pristine, run_cli, tmp_path)
    args = ["--from-batch", out, "--tables", "no-tables", "--sigma-px", "0.002", "--json"]
    res = run_cli("-q", "-C", wd, "geometry", *args)
    assert res.exit_code == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["reduced_chi2"] > 1.5
    rows = [r for r in doc["landmarks"] if r["status"] == "ok"]
    assert len(rows) == len(truth)
    written = np.array([read_lmk(wd / "LMKFILES" / f"{r['name']}.LMK").sigma_lmk for r in rows])
    reported = np.array([[r["sigma_x_m"], r["sigma_y_m"], r["sigma_z_m"]] for r in rows]) / 1000.0
    assert np.allclose(reported, written, rtol=1e-8, atol=0)
    each = np.sort(np.sqrt(np.sum(written**2, axis=1))) * 1000.0
    best = each[: int(np.ceil(0.8 * each.size))]
    f = doc["formal_uncertainty"]
    assert f["best80_rms_m"] == pytest.approx(float(np.sqrt(np.mean(best**2))), rel=1e-8)
    assert f["best80_max_m"] == pytest.approx(float(best.max()), rel=1e-8)
    assert doc["covariance_scale"] == doc["reduced_chi2"]


def test_geometry_says_an_inconsistent_fit_and_refuses_an_implausible_one(pristine, run_cli, tmp_path):
    """solve-pose's chi-square gate: a normal run says nothing; SUM rows weighed at 0.002 px (chi2/dof
    ~4.5) are an inconsistent fit: one warning with the figures and the remedy, the JSON says so, the
    files are written; at 0.0002 px (cost/dof ~450) implausible: exit 1 with one line, nothing written,
    unless --force (the demo at --sigma-px 0.001 once gave chi2/dof 1320 with no word and exit 0)."""
    wd, out = _measured(pristine, run_cli, tmp_path)

    def files():
        return {p: p.read_bytes() for d in ("LMKFILES", "MAPFILES", "SUMFILES") for p in (wd / d).iterdir()}

    def geometry(*extra):
        res = run_cli("-C", wd, "geometry", "--from-batch", out, "--json", *extra)
        warned = [ln for ln in res.stderr.splitlines() if "note:" not in ln]
        return res, warned

    res, warned = geometry("--dry-run")
    assert res.exit_code == 0 and warned == []
    # the register tables weigh every measurement here: --sigma-px weighs nothing, and says so
    res, _ = geometry("--dry-run", "--sigma-px", "0.0002")
    assert res.exit_code == 0 and "note: --sigma-px weighs SUM LANDMARKS rows only" in res.stderr
    res, _ = geometry("--dry-run", "--tables", "no-tables", "--sigma-floor-px", "0.1")
    assert res.exit_code == 0 and "note: --sigma-floor-px applies to register tables only" in res.stderr
    before = files()
    res, warned = geometry("--tables", "no-tables", "--sigma-px", "0.002")
    assert res.exit_code == 0, res.stderr
    assert len(warned) == 1 and "warning: inconsistent fit" in warned[0] and "--sigma-px" in warned[0]
    doc = json.loads(res.stdout)
    assert doc["verdict"] == "inconsistent" and not doc["consistency"]["consistent"]
    assert doc["consistency"]["cost"] > doc["consistency"]["limit"]
    assert files() != before  # written, sigmas scaled
    before = files()
    res, warned = geometry("--tables", "no-tables", "--sigma-px", "0.0002")
    assert res.exit_code == 1
    assert json.loads(res.stdout)["verdict"] == "implausible"
    assert len(warned) == 1 and "error: implausible fit" in warned[0]
    assert "no LMK, MAP or SUM written (--force writes them)" in warned[0]
    assert files() == before
    res, warned = geometry("--tables", "no-tables", "--sigma-px", "0.0002", "--force")
    assert res.exit_code == 0, res.stderr
    assert len(warned) == 1 and "implausible fit" in warned[0] and "because of --force" in warned[0]
    assert files() != before


def test_geometry_refuses_a_picture_named_twice_and_uses_a_pictlist_duplicate_once(
    pristine, run_cli, tmp_path
):
    """A picture given twice on the command line was counted twice (its measurements doubled, its SUM
    written twice): exit 2, one line, nothing written.  One listed twice in PICTLIST is used once, said."""
    root, _ = pristine
    wd = tmp_path / "wd"
    shutil.copytree(root, wd)
    names = sorted(p.stem for p in (wd / "SUMFILES").glob("*.SUM"))
    out = tmp_path / "out"
    assert run_cli("-q", "-C", wd, "batch", "--out-dir", out).exit_code == 0
    before = {p: p.read_bytes() for d in ("LMKFILES", "SUMFILES") for p in (wd / d).iterdir()}
    res = run_cli("-C", wd, "geometry", "--from-batch", out, names[0], names[1], names[0])
    assert res.exit_code == 2
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and "more than once" in lines[0] and names[0] in lines[0]
    assert {p: p.read_bytes() for d in ("LMKFILES", "SUMFILES") for p in (wd / d).iterdir()} == before
    res = run_cli("-C", wd, "geometry", "--from-batch", out, "--dry-run", "--json")
    once = json.loads(res.stdout)
    pictlist = wd / "PICTLIST.TXT"
    text = pictlist.read_text().splitlines()
    pictlist.write_text("\n".join([text[0], *text]) + "\n")
    res = run_cli("-C", wd, "geometry", "--from-batch", out, "--dry-run", "--json")
    assert res.exit_code == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["n_pictures"] == once["n_pictures"] == len(names)
    assert doc["measurements"] == once["measurements"]
    assert "more than once" in res.stderr and text[0].strip() in res.stderr


def test_geometry_checks_its_output_before_writing_and_writes_strict_json(pristine, run_cli, tmp_path):
    """An -o that is a directory is refused before any LMK, MAP or SUM is rewritten (they once were,
    and then the table was lost); --json with no landmark refined is strict JSON (null, not NaN)."""
    wd = tmp_path / "wd"
    _biased(pristine, wd)
    out = tmp_path / "out"
    run_cli("-q", "-C", wd, "batch", "--out-dir", out)
    def files():
        return {p: p.read_bytes() for d in ("LMKFILES", "MAPFILES", "SUMFILES") for p in (wd / d).iterdir()}

    before = files()
    (tmp_path / "table").mkdir()
    res = run_cli("-C", wd, "geometry", "--from-batch", out, "-o", tmp_path / "table")
    assert res.exit_code == 2 and "is a directory" in res.stderr
    assert files() == before
    res = run_cli("-C", wd, "geometry", "--from-batch", out, "--min-pictures", "99", "--json", "--dry-run")
    assert res.exit_code == 0, res.output

    def no_nan(name):
        raise AssertionError(f"{name} in the JSON")

    doc = json.loads(res.stdout, parse_constant=no_nan)
    assert doc["n_landmarks_refined"] == 0 and doc["vlm_correction_rms_m"] is None


def test_batch_rounds_warns_of_a_refinement_not_to_be_trusted(pristine, run_cli, tmp_path, monkeypatch):
    """A refined map whose solve fails the chi-square gate is said on stderr (geometry's line), and
    GEOMETRY.json records the verdict; the verdict forced here, the gate itself is geometry's test."""
    from spctool.stages.bundle import BundleResult

    monkeypatch.setattr(BundleResult, "verdict", property(lambda self: "inconsistent"))
    monkeypatch.setattr(BundleResult, "verdict_reason", property(lambda self: "inconsistent fit: forced"))
    wd = tmp_path / "wd"
    _biased(pristine, wd)
    res = run_cli("-C", wd, "batch", "--rounds", "2", "--out-dir", tmp_path / "c")
    assert res.exit_code == 0, res.output
    assert "warning: map 2 (refined from round 1): inconsistent fit: forced" in res.stderr
    doc = json.loads((tmp_path / "c" / "MAP2" / "GEOMETRY.json").read_text())
    assert doc["verdict"] == "inconsistent"


def test_geometry_says_a_picture_the_batch_left_out_and_refuses_a_doubled_row(pristine, run_cli, tmp_path):
    """--from-batch: a picture without a batch SUM (failed, not run) was dropped silently, now a note
    names it; SUM LANDMARKS rows naming one landmark twice are refused (counted twice before), as
    solve-pose refuses them."""
    wd = tmp_path / "wd"
    _biased(pristine, wd)
    out = tmp_path / "out"
    run_cli("-q", "-C", wd, "batch", "--out-dir", out)
    gone, path = sorted((out / "SUMFILES").glob("*.SUM"))[:2]
    gone.unlink()
    res = run_cli("-C", wd, "geometry", "--from-batch", out, "--dry-run")
    assert res.exit_code == 0, res.output
    assert f"no SUM for {gone.stem}: left out of the refinement" in res.stderr
    lines = path.read_text().split("\n")
    k = lines.index("LANDMARKS")
    lines.insert(k + 1, lines[k + 1])  # the first measured landmark twice
    path.write_text("\n".join(lines))
    (wd / "no-tables").mkdir()
    res = run_cli("-C", wd, "geometry", "--from-batch", out, "--tables", "no-tables", "--dry-run")
    assert res.exit_code == 2 and path.name in res.stderr and "one LANDMARKS row per landmark" in res.stderr


def test_batch_rounds_stop_at_an_implausible_refinement(pristine, run_cli, tmp_path, monkeypatch):
    """An implausible refinement (geometry's rule: exit 1, nothing written) is not written and no round
    measures on it: it once was, and round 2 measured on the map; the verdict forced here."""
    from spctool.stages.bundle import BundleResult

    monkeypatch.setattr(BundleResult, "verdict", property(lambda self: "implausible"))
    monkeypatch.setattr(BundleResult, "verdict_reason", property(lambda self: "implausible fit: forced"))
    wd = tmp_path / "wd"
    _biased(pristine, wd)
    res = run_cli("-C", wd, "batch", "--rounds", "2", "--out-dir", tmp_path / "c")
    assert res.exit_code == 1
    err = [ln for ln in res.stderr.splitlines() if "error:" in ln]
    said = "MAP2 (refined from ROUND1): implausible fit: forced; not written, the cycle stops here"
    assert err == [f"spctool: error: {said}"]
    assert (tmp_path / "c" / "ROUND1" / "BATCH_SUMMARY.json").exists()
    assert not any((tmp_path / "c" / d).exists() for d in ("MAP2", "MAP2.partial", "ROUND2"))


def test_geometry_refuses_a_free_gauge_with_one_line(pristine, run_cli, tmp_path):
    from spctool.formats.sumfile import read_sum, write_sum

    wd = tmp_path / "wd"
    _biased(pristine, wd)
    out = tmp_path / "out"
    run_cli("-q", "-C", wd, "batch", "--out-dir", out)
    for p in (out / "SUMFILES").glob("*.SUM"):
        pic = read_sum(p)
        write_sum(p, dataclasses.replace(pic, sigma_vso=np.zeros(3), sigma_ptg=np.zeros(3)))
    for p in (wd / "LMKFILES").glob("*.LMK"):
        write_lmk(p, dataclasses.replace(read_lmk(p), sigma_lmk=np.zeros(3), sigkm=0.0))
    res = run_cli("-C", wd, "geometry", "--from-batch", out)
    assert res.exit_code == 1
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and "gauge is not fixed" in err[0]


@pytest.mark.slow
def test_rounds_on_the_independent_world_refine_the_map(run_cli, tmp_path):
    """Photos ray-traced by the third-party renderer (trimesh + Embree) of a faceted truth surface, eight
    pictures, the maplets' V off by 3 cm: round 1 cannot solve a pose consistent with the map (every
    picture no-pose); the refined map halves the VLM error and round 2 solves every picture."""
    from spctool.formats.sumfile import read_sum, write_sum
    from spctool.geometry.shape import embree_available
    from spctool.sim.independent import IndependentSpec, build_world

    if not embree_available():
        pytest.skip("embreex not installed")
    root = tmp_path / "iw"
    doc = build_world(root, IndependentSpec(apriori_px=(6.0, 8.0, 6.0, 10.0, 7.0, 9.0, 6.0, 8.0)))
    truth = {n: np.array(v) for n, v in doc["landmarks"].items()}
    _move_landmarks(root, sorted(truth), np.random.default_rng(7))
    for p in (root / "SUMFILES").glob("*.SUM"):  # the a-priori position error is 2 cm: say so
        write_sum(p, dataclasses.replace(read_sum(p), sigma_vso=np.full(3, doc["spec"]["position_km"])))
    e0 = np.array([read_lmk(root / "LMKFILES" / f"{n}.LMK").vlm - v for n, v in truth.items()])
    out = tmp_path / "cycle"
    assert run_cli("-q", "-C", root, "batch", "--rounds", "2", "--out-dir", out).exit_code == 0
    e1 = np.array([read_lmk(out / "MAP2" / "LMKFILES" / f"{n}.LMK").vlm - v for n, v in truth.items()])
    rms = lambda e: float(np.sqrt(np.mean(np.sum(e**2, axis=1))))  # noqa: E731
    assert rms(e1) < 0.6 * rms(e0)
    assert rms(e1 - e1.mean(axis=0)) < 0.2 * rms(e0)  # the map's shape; its place is the priors' (gauge)
    counts = [json.loads((out / f"ROUND{k}" / "BATCH_SUMMARY.json").read_text()) for k in (1, 2)]
    ok = [sum(p["status"] == "ok" for p in c["pictures"]) for c in counts]
    found = [sum(p["found"] for p in c["pictures"]) for c in counts]
    assert ok[1] == 8 and ok[1] > ok[0] and found[1] >= found[0]
    err = []
    for k in (1, 2):
        e = [
            np.linalg.norm(read_sum(out / f"ROUND{k}" / "SUMFILES" / f"{p['name']}.SUM").scobj - p["scobj"])
            for p in doc["pictures"]
        ]
        err.append(float(np.sqrt(np.mean(np.square(e)))))
    assert err[1] < err[0]


def test_geometry_on_the_real_rosetta_picture_keeps_single_picture_landmarks(real, run_cli, tmp_path):
    """One real picture (Rosetta OSIRIS, three LMKs): nothing can be triangulated, every VLM keeps its
    prior (said once), the pose is solved against them; the LMK files are rewritten with .bak."""
    src = real / "rosetta-67p"
    for folder, pattern in (("SUMFILES", "*.SUM"), ("LMKFILES", "*.LMK")):
        (tmp_path / folder).mkdir()
        for f in src.glob(pattern):
            shutil.copy(f, tmp_path / folder / f.name)
    before = {f.name: read_lmk(f).vlm for f in (tmp_path / "LMKFILES").glob("*.LMK")}
    res = run_cli("-C", tmp_path, "geometry", "--json")
    assert res.exit_code == 0, res.stderr
    doc = json.loads(res.stdout)
    assert [r["status"] for r in doc["landmarks"]] == ["undetermined"] * 3
    # said once; and the real residuals (0.54 px rms) against the default --sigma-px 0.25 are an
    # inconsistent fit (chi2/dof 4.7 > its 99.9 % quantile), said too
    lines = res.stderr.splitlines()
    assert len(lines) == 2 and "undetermined" in lines[0] and "inconsistent fit" in lines[1]
    assert doc["verdict"] == "inconsistent"
    for f in (tmp_path / "LMKFILES").glob("*.LMK"):
        assert np.array_equal(read_lmk(f).vlm, before[f.name])
    assert doc["rms_after_px"] < doc["rms_before_px"]


def test_geometry_says_once_when_landmark_rows_are_off_spc_columns(real, run_cli, tmp_path):
    """A LANDMARKS row written with single blanks is read as its writer meant, and geometry (a stage
    using the rows) says so once for the file (issue #40's rule)."""
    src = real / "rosetta-67p"
    for folder, pattern in (("SUMFILES", "*.SUM"), ("LMKFILES", "*.LMK")):
        (tmp_path / folder).mkdir()
        for f in src.glob(pattern):
            shutil.copy(f, tmp_path / folder / f.name)
    sum_path = tmp_path / "SUMFILES" / "W48230079013.SUM"
    text = sum_path.read_text().replace("FA0115    533.53    475.22", "FA0115 533.53 475.22")
    text = text.replace("FC0098    513.55    501.38", "FC0098 513.55 501.38")
    sum_path.write_text(text)
    res = run_cli("-C", tmp_path, "geometry", "--dry-run")
    assert res.exit_code == 0, res.stderr
    said = [ln for ln in res.stderr.splitlines() if "W48230079013.SUM" in ln]
    assert len(said) == 1 and "1 more" in said[0]


def test_batch_cycle_chains_geometry_and_lithos(pristine, run_cli, tmp_path):
    """measure → geometry → lithos (every refined maplet, two worker processes) → measure: the refined
    maplets' re-renderings match the photos better, and the second round solves every picture."""
    wd = tmp_path / "wd"
    _biased(pristine, wd)
    assert run_cli("-C", wd, "batch", "--lithos", "--out-dir", tmp_path / "x").exit_code == 2
    res = run_cli(
        "-q", "-C", wd, "batch", "--rounds", "2", "--lithos", "-j", "2", "--out-dir", tmp_path / "c"
    )
    assert res.exit_code == 0, res.stderr
    doc = json.loads((tmp_path / "c" / "MAP2" / "GEOMETRY.json").read_text())
    heights = doc["heights"]
    assert [h["name"] for h in heights] == sorted(pristine[1])
    assert all(h["status"] in ("ok", "worse", "unsolvable") for h in heights)
    written = [h for h in heights if h["written"]]
    assert written and all(h["ncc_after"] >= h["ncc_before"] for h in written)
    assert "heights solved and written" in res.stdout.splitlines()[1]
    summary = json.loads((tmp_path / "c" / "ROUND2" / "BATCH_SUMMARY.json").read_text())
    assert all(p["status"] == "ok" for p in summary["pictures"])


@pytest.mark.slow
def test_batch_rounds_on_the_demo_with_a_biased_map(run_cli, tmp_path):
    """The shipped demo with its maplets' V moved by 1 m (two cells, SIGMA_LMK saying so): round 1 cannot
    confirm a pose, round 2 on the refined map solves all four, closer to the truth.  (On the demo as
    shipped the map is exact: the refinement then has nothing to gain, and round 2's poses stay within
    their reported sigmas of round 1's.)"""
    from spctool.formats.sumfile import read_sum

    wd = tmp_path / "demo"
    assert run_cli("demo", "--copy-to", wd).exit_code == 0
    names = sorted(p.stem for p in (wd / "LMKFILES").glob("*.LMK"))
    _move_landmarks(wd, names, np.random.default_rng(3), err_km=1e-3)
    assert run_cli("-q", "-C", wd, "batch", "--rounds", "2", "--out-dir", tmp_path / "c").exit_code == 0
    truth = json.loads((wd / "TRUTH.json").read_text())
    stats = []
    for k in (1, 2):
        doc = json.loads((tmp_path / "c" / f"ROUND{k}" / "BATCH_SUMMARY.json").read_text())
        err = [
            np.linalg.norm(
                read_sum(tmp_path / "c" / f"ROUND{k}" / "SUMFILES" / f"{p['name']}.SUM").scobj
                - p["true"]["scobj"]
            )
            for p in truth["pictures"]
        ]
        ok = sum(p["status"] == "ok" for p in doc["pictures"])
        stats.append((sum(p["found"] for p in doc["pictures"]), ok, float(np.sqrt(np.mean(np.square(err))))))
    (f1, ok1, e1), (f2, ok2, e2) = stats
    assert f2 >= f1 and ok2 == 4 > ok1 and e2 < e1
