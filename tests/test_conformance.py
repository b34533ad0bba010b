"""Legacy fidelity (issue #14): files read exactly as SPC's Fortran reads them.

Each case names the Fortran statement it follows (program, statement).  Where numbers are needed they were
taken from SPC's public Fortran (StereoPhotoClinometry/archivingTools, compiled with gfortran 12 as an
oracle) and are kept here as data; no Fortran is copied into spctool.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool.formats.lithos import parse_lithos

# the INIT_LITHOS of issue #14: seven OWEN coefficients on one record of 125 columns
ISSUE_LITHOS = (
    "DISTORT= 'HOLD########' 'OWEN' 6\n"
    "0.0000000000D+00 0.5000000000D-05 0.8000000000D-04 -0.1000000000D-06 -0.5000000000D-06 "
    "0.1000000000D-04 -0.1000000000D-04\n"
    "END\n"
)
ISSUE_P = [0.0, 0.5e-5, 0.8e-4, -0.1e-6, -0.5e-6, 0.1e-4, -0.1e-4]


def test_issue_lithos_loads_with_coefficients_past_column_80():
    # getmm (xCommon.f): READ(25,*) (PD(I,KD), I=0,J) -- list-directed from the unit, no column limit
    assert len(ISSUE_LITHOS.split("\n")[1]) == 121  # 125 columns with the issue's 4-blank code indent
    s = parse_lithos(ISSUE_LITHOS)
    (d,) = s.distortions
    assert d.template == "HOLD########" and d.model == "OWEN" and d.order == 6
    assert d.coefficients.tolist() == ISSUE_P
    assert any("past column 80" in w for _, w in s.warnings)


def _dvals(line: str, n: int) -> list[float]:
    return [float(t.replace("D", "E")) for t in line.split()[:n]]


def _owen_pixel(sum_text: str, vlm, p):
    """Independent SPC projection (spc-formats.md §2.5 + §6.4 OWEN), from the file text, not spctool."""
    lines = sum_text.split("\n")
    mmfl, c1, c2 = _dvals(lines[3], 3)
    scobj = np.array(_dvals(lines[4], 3))
    rot = np.array([_dvals(lines[k], 3) for k in (5, 6, 7)])
    k = np.array([float(t) for t in lines[9].split()[:6]]).reshape(2, 3)
    u = scobj + np.asarray(vlm)
    z1, z2, z3 = rot @ u
    x = (1 + p[0]) * mmfl * z1 / z3
    y = (1 + p[0]) * mmfl * z2 / z3
    r = np.hypot(x, y)
    xd = x - p[1] * y * r + p[2] * x * r**2 - p[3] * y * r**3 + p[4] * x * r**4 + p[5] * x * y + p[6] * x * x
    yd = y + p[1] * x * r + p[2] * y * r**2 + p[3] * x * r**3 + p[4] * y * r**4 + p[5] * y * y + p[6] * x * y
    # legacy DISTORTION line of this SUM is all zero: MMPX leaves (x, y) unchanged
    return (
        c1 + k[0, 0] * xd + k[0, 1] * yd + k[0, 2] * xd * yd,
        c2 + k[1, 0] * xd + k[1, 1] * yd + k[1, 2] * xd * yd,
    )


@pytest.fixture
def owen_workdir(real, tmp_path):
    (tmp_path / "SUMFILES").mkdir()
    (tmp_path / "LMKFILES").mkdir()
    shutil.copy(real / "rosetta-67p/W48230079013.SUM", tmp_path / "SUMFILES")
    for name in ("FA0115", "FC0098", "GD0036"):
        shutil.copy(real / f"rosetta-67p/{name}.LMK", tmp_path / "LMKFILES")
    return tmp_path


def _project(run_cli, workdir):
    r = run_cli("-C", workdir, "project", "W48230079013", "--json")
    assert r.exit_code == 0, r.stderr
    return {row["name"]: (row["sample"], row["line"]) for row in json.loads(r.stdout)["landmarks"]}


@pytest.mark.parametrize("template", ["HOLD########", "W###########"])
def test_issue_lithos_project_matches_independent_owen(run_cli, owen_workdir, real, template):
    # getmm: last matching template; TYPE 'OWEN' -> the OWEN model; 'HOLD####' matches nothing -> pinhole
    (owen_workdir / "INIT_LITHOS.TXT").write_text(ISSUE_LITHOS.replace("HOLD########", template))
    got = _project(run_cli, owen_workdir)
    sum_text = (real / "rosetta-67p/W48230079013.SUM").read_text()
    p = ISSUE_P if template.startswith("W") else [0.0] * 7
    for name, (s, ln) in got.items():
        vlm = _dvals((real / f"rosetta-67p/{name}.LMK").read_text().split("\n")[4], 3)
        es, el = _owen_pixel(sum_text, vlm, p)
        assert abs(s - es) < 1e-9 and abs(ln - el) < 1e-9, (name, s - es, ln - el)
    if template.startswith("W"):  # the model is not negligible: it moves the pixels
        base = _owen_pixel(
            sum_text, _dvals((real / "rosetta-67p/FA0115.LMK").read_text().split("\n")[4], 3), [0] * 7
        )
        assert abs(got["FA0115"][0] - base[0]) + abs(got["FA0115"][1] - base[1]) > 1e-3


@pytest.mark.parametrize("model", ["owen", " OWEN", "PINHOLE", "OPENCV"])
def test_unknown_or_miscased_model_is_the_plain_pinhole(run_cli, owen_workdir, real, model):
    # getmm: IF(TYPE(JD).EQ.'OWEN') is an exact compare; no branch taken -> z = MMFL*(z1/z3, z2/z3), no P0
    text = ISSUE_LITHOS.replace("HOLD########", "W###########").replace("'OWEN'", f"'{model}'")
    text = text.replace("0.0000000000D+00 0.5", "0.1000000000D+00 0.5")  # a P0 SPC must not apply either
    (owen_workdir / "INIT_LITHOS.TXT").write_text(text)
    got = _project(run_cli, owen_workdir)
    sum_text = (real / "rosetta-67p/W48230079013.SUM").read_text()
    for name, (s, ln) in got.items():
        vlm = _dvals((real / f"rosetta-67p/{name}.LMK").read_text().split("\n")[4], 3)
        es, el = _owen_pixel(sum_text, vlm, [0.0] * 7)
        assert abs(s - es) < 1e-9 and abs(ln - el) < 1e-9
    r = run_cli("validate", owen_workdir / "INIT_LITHOS.TXT")
    assert r.exit_code == 0
    assert "plain pinhole" in r.stderr and "INIT_LITHOS.TXT:1:" in r.stderr


# ---------------------------------------------------------------------------------------------------------
# photo search: FIND_PICFILE.f INQUIREs ./IMAGEFILES/<PIC>.DAT, then IMAGEFILES1..9; LITHOS adds ALTDIR=


def test_photo_search_follows_find_picfile(tmp_path):
    from spctool.formats.workdir import WorkDir

    for d in ("IMAGEFILES", "IMAGEFILES1", "IMAGEFILES3", "ALT"):
        (tmp_path / d).mkdir()
    wd = WorkDir(tmp_path)
    (tmp_path / "IMAGEFILES/P1.pgm").write_bytes(b"P5\n1 1\n255\n\0")
    (tmp_path / "IMAGEFILES3/P1.DAT").write_bytes(b"\0")
    # a stray PGM in IMAGEFILES/ must not win over the DAT SPC finds in IMAGEFILES3/
    assert wd.photo_path("P1") == tmp_path / "IMAGEFILES3/P1.DAT"
    (tmp_path / "IMAGEFILES1/P1.DAT").write_bytes(b"\0")
    assert wd.photo_path("P1") == tmp_path / "IMAGEFILES1/P1.DAT"
    # no DAT anywhere: spctool's extension takes the other formats, in the same folder order
    assert wd.photo_path("P2") is None
    (tmp_path / "IMAGEFILES3/P2.fits").write_bytes(b"")
    assert WorkDir(tmp_path).photo_path("P2") == tmp_path / "IMAGEFILES3/P2.fits"
    # ALTDIR= (LITHOS) is searched after IMAGEFILES9/ for a DAT
    (tmp_path / "ALT/P2.DAT").write_bytes(b"\0")
    (tmp_path / "INIT_LITHOS.TXT").write_text("ALTDIR= 'ALT'\nEND\n")
    assert WorkDir(tmp_path).photo_path("P2") == tmp_path / "ALT/P2.DAT"


# ---------------------------------------------------------------------------------------------------------
# fixtures/conformance/: files as SPC writes them and the legal variants its READs accept; each sidecar
# carries the numbers SPC's READ statements give (gfortran oracle) and cites those statements

from pathlib import Path  # noqa: E402

CORPUS = Path(__file__).resolve().parent.parent / "fixtures" / "conformance"
CASES = sorted(p for p in CORPUS.glob("*/*.json") if p.parent.name != "oracle")  # oracle/: programs, rows


def _same(got, want, rel=0.0):
    got = np.asarray(got, dtype=float).ravel()
    want = np.array([np.nan if w is None else w for w in np.asarray(want, dtype=object).ravel()], dtype=float)
    assert got.shape == want.shape
    nan = np.isnan(want)
    assert np.array_equal(np.isnan(got), nan)
    if rel:
        np.testing.assert_allclose(got[~nan], want[~nan], rtol=rel, atol=1e-30)
    else:
        assert np.array_equal(got[~nan], want[~nan])


def test_corpus_is_there_and_every_case_cites_its_fortran():
    assert len(CASES) >= 30
    kinds = {json.loads(p.read_text())["kind"] for p in CASES}
    assert kinds >= {"sum", "nom", "lmk", "lithos", "map", "icq", "pictlist", "lmrklist", "lmrklistx", "dat"}
    for p in CASES:
        doc = json.loads(p.read_text())
        assert doc["fortran"] and ("READ" in doc["fortran"] or "read" in doc["fortran"]), p.name
        assert Path(str(p)[: -len(".json")]).exists()


def _rows(items, fields):
    return [[getattr(it, f) for f in fields] for it in items]


def _same_rows(got, want):
    """Section rows: names and flags equal, numbers equal to the last bit."""
    assert [[x for x in r if isinstance(x, str)] for r in got] == [
        [x for x in r if isinstance(x, str)] for r in want
    ]
    _same(
        [[x for x in r if not isinstance(x, str)] for r in got],
        [[x for x in r if not isinstance(x, str)] for r in want],
    )


def _check_rows(obj, doc, mode, sections):
    """Section rows in both modes (issue #40): under --spc-columns LITHOS's numbers (``expect``); by default
    the writer's (``as_written``, where they differ), each differing row warned once."""
    from spctool.formats.rows import column_notes

    want = doc["expect"] if mode == "spc-columns" else {**doc["expect"], **doc.get("as_written", {})}
    for key, fields in sections.items():
        if key in want:
            _same_rows(_rows(getattr(obj, key), fields), want[key])
    warned = sorted(ln for ln, _ in column_notes(obj._source.warnings))
    assert warned == (doc.get("warned_lines", []) if mode == "default" else [])


SUM_ROWS = {"landmarks": ("name", "sample", "line", "flag"), "limb_fits": ("name", "sample", "line", "value")}
LMK_ROWS = {
    "pictures": ("name", "sample", "line", "flag"),
    "overlaps": ("name", "offset"),
    "limb_fits": ("name", "sample", "line", "value"),
}


@pytest.mark.parametrize("mode", ["default", "spc-columns"])
@pytest.mark.parametrize("case", CASES, ids=[f"{p.parent.name}/{p.name[:-5]}" for p in CASES])
def test_corpus_case(case, mode):
    """Every case read as SPC reads it, in both row modes (rows as written / --spc-columns)."""
    from spctool.errors import SpcFormatError
    from spctool.formats.rows import spc_columns_mode

    doc = json.loads(case.read_text())
    path = Path(str(case)[: -len(".json")])
    if mode == "spc-columns" and "spc_stops_at_line" in doc:  # LITHOS's READ stops: refused, naming the line
        with spc_columns_mode(), pytest.raises(SpcFormatError) as info:
            _read_case(doc, path)
        assert info.value.where == doc["spc_stops_at_line"] and "LITHOS's READ stops" in str(info.value)
        mode = "default"
    with spc_columns_mode(mode == "spc-columns"):
        _read_case(doc, path, mode)


def _read_case(doc, path, mode="default"):
    from spctool.errors import SpcFormatError

    if "refused" in doc:  # SPC would read nothing sensible: spctool refuses with one line naming the file
        with pytest.raises(SpcFormatError) as info:
            _read_case({k: v for k, v in doc.items() if k != "refused"}, path, mode)
        assert str(info.value).startswith(str(path)) and doc["refused"]["contains"] in str(info.value)
        assert "\n" not in str(info.value)
        return
    want = doc["expect"]
    kind = doc["kind"]
    if kind == "sum":
        from spctool.formats.sumfile import read_sum

        pic = read_sum(path)
        _check_rows(pic, doc, mode, SUM_ROWS)
        assert (pic.npx, pic.nln) == (want["npx"], want["nln"])
        _same(pic.thrsh, want["thrsh"])
        _same([pic.mmfl, *pic.ctr], [want["mmfl"], *want["ctr"]])
        for key in ("scobj", "cx", "cy", "cz", "sz", "kmatrix", "sigma_vso", "sigma_ptg"):
            if key in want:
                _same(getattr(pic, key), want[key])
        _same(np.zeros(4) if pic.distortion is None else pic.distortion, want["distortion"])
    elif kind == "lmk":
        from spctool.formats.landmark import read_lmk

        lmk = read_lmk(path)
        _check_rows(lmk, doc, mode, LMK_ROWS)
        if "spc_hflag" in doc:  # LITHOS's (A6,3X,A1) flag, where spctool reads the writer's and warns
            assert lmk.hflag in "TF" and lmk.hflag != doc["spc_hflag"]
            assert any(
                f"finds {'a blank' if not doc['spc_hflag'].strip() else repr(doc['spc_hflag'])}" in w
                for _, w in lmk._source.warnings
            )
        assert lmk.qsz == want["qsz"]
        _same(lmk.horizon, want["horizon"])
        _same([lmk.scale, lmk.sigkm, lmk.rmslmk], [want["scale"], want["sigkm"], want["rmslmk"]])
        for key in ("vlm", "ux", "uy", "uz", "sigma_lmk"):
            _same(getattr(lmk, key), want[key])
    elif kind == "nom":
        from spctool.formats.nominal import read_nom

        nom = read_nom(path)
        for key, value in want.items():
            _same(getattr(nom, key), value)
        assert [ln for ln, _ in nom._source.warnings] == doc.get("warned_lines", [])
    elif kind == "lithos":
        from spctool.formats.lithos import read_lithos

        got = read_lithos(path).distortions
        assert len(got) == len(want["distortions"])
        for d, w in zip(got, want["distortions"]):
            assert (d.template, d.model, d.order) == (w["template"], w["model"], w["order"])
            _same(d.coefficients, w["coefficients"])
    elif kind == "map":
        from spctool.formats.maplet import read_map

        m = read_map(path)
        assert m.qsz == want["qsz"]
        _same(
            [m.scale, *m.v, *m.ux, *m.uy, *m.uz],
            [want["scale"], *want["v"], *want["ux"], *want["uy"], *want["uz"]],
        )
        alb = np.array(want["albedo"])
        _same(m.albedo.ravel(), alb, rel=1e-7)  # ALB is REAL*4 in READ_MAP
        # heights: READ_MAP skips A = 0 cells in full records but decodes them in the last partial one;
        # spctool treats A = 0 as missing everywhere (spc-formats.md §8 item 3, a documented choice)
        ok = alb != 0
        _same(m.heights.ravel()[ok], np.array(want["height_times_scale_units"])[ok], rel=1e-7)
    elif kind == "icq":
        from spctool.formats.icq import read_icq

        shape = read_icq(path)
        assert shape.q == want["q"]
        _same(shape.flat_vertices(), want["vertices"])
        alb = shape.flat_albedo() if shape.albedo is not None else np.ones(len(want["albedo"]))
        _same(alb, want["albedo"])
    elif kind in ("pictlist", "lmrklist"):
        from spctool.formats.lists import read_lmrklist, read_pictlist

        lst = read_pictlist(path) if kind == "pictlist" else read_lmrklist(path)
        names = lst.active_names if kind == "pictlist" else lst.names
        assert names == want["active_names"]
    elif kind == "lmrklistx":
        from spctool.formats.lists import read_lmrklistx

        xlist = read_lmrklistx(path)
        got = [[e.name, e.qsz, e.npictures, *e.vlm, e.scale] for e in xlist]
        assert [g[:3] for g in got] == [w[:3] for w in want["entries"]]
        _same([g[3:] for g in got], [w[3:] for w in want["entries"]])
        assert sorted({ln for ln, _ in xlist._source.warnings}) == doc.get("warned_lines", [])
    elif kind == "dat":
        from spctool.formats.photo import read_photo

        photo = read_photo(path, npx=doc["npx"], nln=doc["nln"])
        assert photo.data.tolist() == want["dn"]
    else:  # pragma: no cover - a new kind needs its check here
        raise AssertionError(kind)
    if (
        "spc_differs_at_lines" in doc
    ):  # SPC reads these lines otherwise (or stops): spctool warns, one line each
        from spctool.cli.files import spc_warnings

        obj = {"lmk": locals().get("lmk"), "sum": locals().get("pic")}[kind]
        assert sorted({ln for ln, _ in spc_warnings(obj)}) == doc["spc_differs_at_lines"]


def test_spctool_writers_produce_files_spc_reads(tmp_path):
    """format_sum / format_lithos / format_map / format_icq / lists: written files read back to the same
    numbers through the same SPC READ rules (the corpus readers above)."""
    from spctool.formats.icq import format_icq, read_icq
    from spctool.formats.lists import format_lmrklist, format_pictlist, read_lmrklist, read_pictlist
    from spctool.formats.lithos import DistortModel, Settings, format_lithos
    from spctool.formats.maplet import format_map, read_map
    from spctool.formats.sumfile import _PICTURE_FIELDS, Picture, format_sum, parse_sum

    pic = parse_sum((CORPUS / "sum/CANONICAL.SUM").read_text())
    fresh = Picture(**{k: getattr(pic, k) for k in _PICTURE_FIELDS})  # every field a Picture is made of
    text = format_sum(fresh)
    lines = text.split("\n")
    assert lines[10][63:73] == "DISTORTION"  # the column globalStat tests
    assert all(len(ln) <= 80 for ln in lines)
    assert parse_sum(text) == pic
    s = Settings()
    s.distortions.append(DistortModel("X###########", "OWEN", 6, [0.0, 1e-5, -2.5e-6, 0, 3e-9, 0, 1.0 / 3]))
    out = format_lithos(s)
    assert all(len(ln) <= 80 for ln in out.split("\n"))  # the key record is (A80)
    back = parse_lithos(out).distortions[0]
    assert back == s.distortions[0]
    m = read_map(CORPUS / "map/LONGER.MAP")
    (tmp_path / "W.MAP").write_bytes(format_map(m))
    assert (tmp_path / "W.MAP").read_bytes() == (CORPUS / "map/EXACT.MAP").read_bytes()
    shape = read_icq(CORPUS / "icq/CUBE_TRAILING.TXT")
    (tmp_path / "S.TXT").write_text(format_icq(shape))
    assert np.array_equal(read_icq(tmp_path / "S.TXT").vertices, shape.vertices)
    plist = read_pictlist(CORPUS / "lists/PICTLIST.TXT")
    (tmp_path / "P.TXT").write_text(format_pictlist(plist))
    assert read_pictlist(tmp_path / "P.TXT").active_names == plist.active_names
    llist = read_lmrklist(CORPUS / "lists/LMRKLIST.TXT")
    (tmp_path / "L.TXT").write_text(format_lmrklist(llist))
    assert read_lmrklist(tmp_path / "L.TXT").names == llist.names


def test_validate_warns_where_spc_reads_differently_and_exits_0(run_cli, tmp_path):
    # DISTORTION tag at column 63: globalStat's LINE(64:73) test fails, D = 0 -- SPC accepts the file
    path = CORPUS / "sum/DISTORTION_COL63.SUM"
    r = run_cli("validate", path)
    assert r.exit_code == 0, r.stderr
    assert f"{path}:11: warning:" in r.stderr and "D = 0" in r.stderr
    r = run_cli("validate", CORPUS / "lithos/ISSUE14.TXT")
    assert r.exit_code == 0 and "ISSUE14.TXT:2: warning:" in r.stderr and "past column 80" in r.stderr
    r = run_cli("validate", CORPUS / "icq/CUBE_TRAILING.TXT")
    assert r.exit_code == 0 and "CUBE_TRAILING.TXT:26: warning:" in r.stderr
    r = run_cli("validate", CORPUS / "map/LONGER.MAP")
    assert r.exit_code == 0 and "LONGER.MAP:byte 216: warning:" in r.stderr
    # untagged files (read by position) are recognised
    r = run_cli("info", CORPUS / "sum/UNTAGGED.SUM", CORPUS / "lmk/UNTAGGED.LMK")
    assert r.exit_code == 0 and "UNTAGGED.SUM: sum" in r.stdout and "UNTAGGED.LMK: lmk" in r.stdout
    # a swapped header line is an error naming the line
    lines = (CORPUS / "sum/CANONICAL.SUM").read_text().split("\n")
    lines[5], lines[6] = lines[6], lines[5]
    bad = tmp_path / "SWAPPED.SUM"
    bad.write_text("\n".join(lines))
    r = run_cli("validate", bad)
    assert r.exit_code == 2 and "SWAPPED.SUM:6: expected the CX line" in r.stderr


# ---------------------------------------------------------------------------------------------------------
# line-scan (pushbroom) SUM: xV2IMGPL.f (column 14 'L' + LINE SCAN DATA)

LINESCAN_SUM = """X123456789A1 L
2021 MAR 04 12:34:56.789
  1024  2000   100  4095                                       NPX, NLN, THRSH
    0.5000000000D+02    0.5125000000D+03    0.1000500000D+04   MMFL, CTR
   -0.1000000000D+02    0.1000000000D+00    0.2000000000D+00   SCOBJ
    0.0000000000D+00    0.1000000000D+01    0.0000000000D+00   CX
    0.0000000000D+00    0.0000000000D+00   -0.1000000000D+01   CY
   -0.1000000000D+01    0.0000000000D+00    0.0000000000D+00   CZ
    0.8000000000D+00    0.6000000000D+00    0.0000000000D+00   SZ
 100.00000   0.00000   0.00000   0.00000 100.00000   0.00000   K-MATRIX
    0.00000D+00    0.00000D+00    0.00000D+00    0.00000D+00   DISTORTION
    0.1000000000D-01    0.1000000000D-01    0.1000000000D-01   SIGMA_VSO
    0.1000000000D-03    0.1000000000D-03    0.1000000000D-03   SIGMA_PTG
LANDMARKS
LIMB FITS
END FILE
LINE SCAN DATA
  9.0 9.0 9.0
  9.0  1.0D-5  2.0D-9
  0.0 0.0 1.0
  2.0D-6
  0.0 1.0 0.0
  2.0D-4 1.0D-9 0.0
  2
  1.0D-6 -2.0D-6 5.0D-7
  1.0D-10 0.0 -3.0D-10
"""


def _independent_linescan(pic_text: str, point):
    """SCOBJ / POINTING / ROT2MAT / VROTV rewritten with scipy rotations, the line found by brentq."""
    from scipy.optimize import brentq
    from scipy.spatial.transform import Rotation

    lines = pic_text.split("\n")
    mmfl, c1, c2 = _dvals(lines[3], 3)
    scobj = np.array(_dvals(lines[4], 3))
    cmat = np.array([_dvals(lines[k], 3) for k in (5, 6, 7)])
    k11 = float(lines[9].split()[0])
    blk = lines[lines.index("LINE SCAN DATA") + 1 :]
    r0 = _dvals(blk[1], 3)
    pol_axis, pol = np.array(_dvals(blk[2], 3)), _dvals(blk[3], 1)[0]
    trj_axis, trj = np.array(_dvals(blk[4], 3)), _dvals(blk[5], 3)
    cax = np.array([_dvals(blk[7 + k], 3) for k in range(int(blk[6]))])

    def rot(axis, ang):
        return Rotation.from_rotvec(np.asarray(axis) / np.linalg.norm(axis) * ang)

    def mm(ln):
        dl = ln - c2
        tau = trj[0] * dl + trj[1] * dl**2 + trj[2] * dl**3
        pos = rot(pol_axis, -pol * dl).apply(
            (np.linalg.norm(scobj) + r0[1] * dl + r0[2] * dl**2)
            * rot(trj_axis, tau).apply(scobj / np.linalg.norm(scobj))
        )
        turn = sum(cax[k] * dl ** (k + 1) for k in range(len(cax)))
        w = Rotation.from_rotvec(turn).as_matrix() @ cmat
        w = (rot(pol_axis, -pol * dl) * rot(trj_axis, tau)).apply(w)  # each row turned as a vector
        z = w @ (pos + point)
        return mmfl * z[0] / z[2], mmfl * z[1] / z[2]

    # xV2IMGPL's line search: three secant steps through the estimate -/+ 50 lines (not a converged root)
    z = c2
    for _ in range(3):
        x0, x1 = z - 50, z + 50
        y0, y1 = mm(x0)[1], mm(x1)[1]
        z = (x0 * y1 - x1 * y0) / (y1 - y0)
    root = brentq(lambda ln: mm(ln)[1], c2 - 1500, c2 + 1500, xtol=1e-13)
    return c1 + k11 * mm(z)[0], z, root


def test_linescan_sum_is_parsed_and_projected_as_xv2imgpl():
    from spctool.formats.sumfile import parse_sum
    from spctool.geometry.linescan import project_linescan

    pic = parse_sum(LINESCAN_SUM)
    assert pic.is_linescan and pic.linescan.cax.shape == (2, 3) and pic.linescan.pol == 2.0e-6
    pts = np.array([[0.5, 0.1, -0.15], [0.3, -0.8, -0.25], [-0.2, 0.4, -0.2]])
    s, ln, inside = project_linescan(pic, pts)
    for k, p in enumerate(pts):
        es, el, root = _independent_linescan(LINESCAN_SUM, p)
        assert abs(s[k] - es) < 1e-6 and abs(ln[k] - el) < 1e-6, (k, s[k] - es, ln[k] - el)
        assert abs(ln[k] - root) < 1.0  # SPC's three steps land within a line of the exact crossing
    assert inside.all()
    # the frame-camera formula would put these points elsewhere: the pushbroom model matters here
    from spctool.geometry.camera import Camera

    frame = pic.kmatrix[0, 0] * 50 * (pic.rotation @ (pic.scobj + pts[0]))
    assert abs(ln[0] - (pic.ctr[1] + frame[1] / (pic.rotation @ (pic.scobj + pts[0]))[2])) > 1.0
    with pytest.raises(Exception, match="line-scan"):
        Camera.from_picture(pic)  # the frame-camera stages refuse it with one clear line


def test_linescan_flag_without_block_is_refused():
    from spctool.errors import SpcFormatError
    from spctool.formats.sumfile import parse_sum

    with pytest.raises(SpcFormatError, match="LINE SCAN DATA"):
        parse_sum(LINESCAN_SUM.split("LINE SCAN DATA")[0])


def test_sum_writer_nan_reads_back():
    # spctool's writer emits NaN for an unknown sigma; NaN is legal list-directed input (gfortran reads
    # it); a non-finite pose (SCOBJ, CX, CY, CZ) is never written (issue #41)
    from spctool.errors import SpcUsageError
    from spctool.formats.sumfile import format_sum, parse_sum

    pic = parse_sum((CORPUS / "sum/CANONICAL.SUM").read_text())
    pic.sigma_vso = np.array([np.nan, 1.0, 2.0])
    back = parse_sum(format_sum(pic))
    _same(back.sigma_vso, [None, 1.0, 2.0])
    pic.scobj = np.array([np.nan, 0.0, 1.0])
    with pytest.raises(SpcUsageError, match="non-finite pose .SCOBJ"):
        format_sum(pic)


@pytest.mark.parametrize("kind", ["sum", "lithos", "pictlist"])
def test_utf8_bom_is_refused_naming_line_1(kind):
    # SPC reads the three BOM bytes as text: a SUM name 'ï»¿X123...', an INIT_LITHOS key it never
    # recognises, a PICTLIST flag 'ï' (in use) with a garbled name -- refused with one clear line
    from spctool.errors import SpcFormatError
    from spctool.formats.lists import parse_pictlist
    from spctool.formats.sumfile import parse_sum

    bom = "\xef\xbb\xbf"  # as decoded (Latin-1) by spctool's text reader
    cases = {
        "sum": (parse_sum, bom + (CORPUS / "sum/CANONICAL.SUM").read_text()),
        "lithos": (parse_lithos, bom + ISSUE_LITHOS),
        "pictlist": (parse_pictlist, bom + " X123456789A1\nEND\n"),
    }
    parse, text = cases[kind]
    with pytest.raises(SpcFormatError, match="byte-order mark") as e:
        parse(text, "F.TXT")
    assert str(e.value).startswith("F.TXT:1:")


def test_project_command_uses_the_pushbroom_model(run_cli, real, tmp_path):
    """`spctool project` on a line-scan picture: SPC's per-line pose (xV2IMGPL), not a frame camera."""
    import json

    (tmp_path / "SUMFILES").mkdir()
    (tmp_path / "LMKFILES").mkdir()
    (tmp_path / "SUMFILES" / "X123456789A1.SUM").write_text(LINESCAN_SUM)
    point = np.array([0.3, -0.8, -0.25])
    lines = (real / "rosetta-67p/FA0115.LMK").read_text().split("\n")
    tag = lines[4][lines[4].rstrip().rfind(" ") :] if "VLM" in lines[4] else ""
    lines[4] = "".join(f"{v:20.10E}".replace("E", "D") for v in point) + tag
    (tmp_path / "LMKFILES" / "FA0115.LMK").write_text("\n".join(lines))
    r = run_cli("-C", tmp_path, "project", "X123456789A1", "FA0115", "--json")
    assert r.exit_code == 0, r.stderr
    row = json.loads(r.stdout)["landmarks"][0]
    es, el, _ = _independent_linescan(LINESCAN_SUM, point)
    assert abs(row["sample"] - es) < 1e-6 and abs(row["line"] - el) < 1e-6
    assert row["status"] == "ok"
    r = run_cli("-C", tmp_path, "project", "X123456789A1", "--inverse", "500", "900")
    assert r.exit_code == 2 and "line-scan" in r.stderr


# ---------------------------------------------------------------------------------------------------------
# issue #40: a GIANT-written SUM (Summary.write layout) through info, validate, project and solve-pose, in
# both row modes; the numbers LITHOS reads from GIANT's 27-column rows are in sum/GIANT.SUM.json


@pytest.fixture
def giant_workdir(real, tmp_path):
    (tmp_path / "SUMFILES").mkdir()
    (tmp_path / "LMKFILES").mkdir()
    shutil.copy(CORPUS / "sum/GIANT.SUM", tmp_path / "SUMFILES/W48230079013.SUM")
    for name in ("FA0115", "FC0098", "GD0036"):
        shutil.copy(real / f"rosetta-67p/{name}.LMK", tmp_path / "LMKFILES")
    return tmp_path


def test_giant_sum_info_validate_project(run_cli, giant_workdir, real, tmp_path):
    path = giant_workdir / "SUMFILES/W48230079013.SUM"
    assert not path.read_bytes().endswith(b"\n")  # GIANT writes no newline after END FILE
    r = run_cli("info", path)
    assert r.exit_code == 0 and "3 landmarks, 1 limb fits" in r.stdout
    r = run_cli("validate", path)
    assert r.exit_code == 0 and "valid sum" in r.stdout
    warned = [ln for ln in r.stderr.splitlines() if "not in SPC's columns" in ln]
    assert [int(w.split(":")[1]) for w in warned] == [15, 16, 17, 19]
    assert "spctool reads 533.53, 475.22 as written; LITHOS reads 533.53, 475.2" in warned[0]
    assert "spctool reads 530.12, 470.87, 0 as written; LITHOS reads 530.12, 470.8, 0.07" in warned[3]
    # the header reads as the SPC-written original of the same picture: identical projections; project does
    # not use the LANDMARKS rows, so it says nothing of their columns
    r = run_cli("-C", giant_workdir, "project", "W48230079013", "--json")
    assert r.exit_code == 0 and "SPC's columns" not in r.stderr
    giant = _project(run_cli, giant_workdir)
    (tmp_path / "spc/SUMFILES").mkdir(parents=True)
    (tmp_path / "spc/LMKFILES").mkdir()
    shutil.copy(real / "rosetta-67p/W48230079013.SUM", tmp_path / "spc/SUMFILES")
    for name in ("FA0115", "FC0098", "GD0036"):
        shutil.copy(real / f"rosetta-67p/{name}.LMK", tmp_path / "spc/LMKFILES")
    assert giant == _project(run_cli, tmp_path / "spc")


@pytest.mark.parametrize("mode", ["default", "spc-columns"])
def test_giant_sum_solve_pose_uses_each_modes_rows(run_cli, giant_workdir, real, mode):
    from spctool.formats.landmark import read_lmk
    from spctool.formats.sumfile import read_sum
    from spctool.geometry.camera import Camera

    doc = json.loads((CORPUS / "sum/GIANT.SUM.json").read_text())
    rows = (doc["as_written"] if mode == "default" else doc["expect"])["landmarks"]
    flag = ["--spc-columns"] if mode == "spc-columns" else []
    out = giant_workdir / "new.SUM"
    r = run_cli(*flag, "-C", giant_workdir, "solve-pose", "W48230079013", "--no-prior", "--output", out)
    assert r.exit_code == 0, r.stderr
    notes = [ln for ln in r.stderr.splitlines() if "not in SPC's columns" in ln]
    assert len(notes) == (1 if mode == "default" else 0)  # the stage that uses the rows warns once per file
    if notes:
        assert "W48230079013.SUM:15:" in notes[0] and "(and 2 more rows)" in notes[0]  # its LANDMARKS rows
    # three landmarks, no prior: the solved pose reprojects the rows this mode read, exactly
    pic = read_sum(out)
    pts = np.array([read_lmk(real / f"rosetta-67p/{n}.LMK").vlm for n, *_ in rows])
    s, ln = Camera.from_picture(pic).project(pts)
    np.testing.assert_allclose(np.stack([s, ln], axis=-1), [r[1:3] for r in rows], atol=1e-3)
    assert out.read_text().endswith("END FILE")  # the rewrite keeps GIANT's missing final newline


# ---------------------------------------------------------------------------------------------------------
# issue #40: section rows as LITHOS reads them -- gfortran's formatted READ, and a writer whose rows it reads


def test_formatted_read_gives_gfortrans_numbers_on_600_random_rows():
    """fortran.formatted_read against gfortran 12 (oracle/rows_gfortran.json, oracle/rowread.f90): the
    same numbers to the last bit, the same flag, and the READ stops on the same rows."""
    from spctool.formats.fortran import FormattedReadError, formatted_read
    from spctool.formats.rows import read_section_row, spc_columns_mode

    doc = json.loads((CORPUS / "oracle/rows_gfortran.json").read_text())
    assert len(doc["cases"]) == 600 and 100 < sum(c.get("stops", False) for c in doc["cases"]) < 500
    for case in doc["cases"]:
        if case.get("stops"):
            with pytest.raises(FormattedReadError):
                formatted_read(case["row"], case["format"])
            continue
        got = formatted_read(case["row"], case["format"])
        nums = [v for v in got if isinstance(v, float)]
        want = [float(v) if isinstance(v, str) else v for v in case["values"]]  # 'nan' / 'inf' as text
        _same(nums, [None if w != w else w for w in want])
        if "flag" in case:
            assert got[-1] == case["flag"], case["row"]
        # --spc-columns: a section row read exactly so (rows.read_section_row, its fast path included)
        count, start = {
            "(A6,2F": (2, 6),
            "(A6,3F": (3, 6),
            "(A12,2": (2, 12),
            "(A6,2X": (3, 8),
            "(A12,3": (3, 12),
        }[case["format"][:6]]
        with spc_columns_mode():
            vals, rest, _ = read_section_row(
                case["row"], case["format"], count, start, path=None, lineno=1, what=""
            )
        _same(vals, [None if w != w else w for w in want])
        assert rest.strip() == case.get("flag", "").strip()


ROW_VALUES = st.one_of(
    st.floats(-1e4, 1e4, allow_nan=False),
    st.floats(-1e13, 1e13, allow_nan=False),
    st.sampled_from([-99999.995, -99999.994, 999999.995, 999999.994, 9999999.994, 9999999.995, -1e6, 1e300]),
)


@settings(max_examples=150, deadline=None)
@given(st.lists(ROW_VALUES, min_size=3, max_size=3), st.sampled_from(["", "*"]))
def test_row_writer_never_writes_a_row_lithos_misreads(values, flag):
    """Item 9: every SUM / LMK row spctool writes is read by LITHOS's formatted READ as the value written
    (F10.2 / F12.3 rounding; an E field where Fw.d would overflow) and by spctool identically, no warning."""
    from spctool.formats.fortran import formatted_read
    from spctool.formats.landmark import LandmarkLimb, LandmarkPicture, MapOverlap, _row
    from spctool.formats.rows import read_section_row, row_text

    rows = [
        ("(A6,2F10.2,1X,A1)", 2, 6, row_text("AB0001", 6, values[:2], (10, 2), flag), 2),
        ("(A12,2F10.2,1X,A1)", 2, 12, _row("pictures", LandmarkPicture("X1234567A1", *values[:2], flag)), 2),
        ("(A6,2X,3F12.3)", 3, 8, _row("overlaps", MapOverlap("AB0002", np.array(values))), 3),
        ("(A12,3F10.2)", 3, 12, _row("limbs", LandmarkLimb("X123456810A1", *values)), 2),
    ]
    for fmt, count, start, text, decimals in rows:
        width = 12 if "F12" in fmt else 10
        flagged = "1X,A1" in fmt
        assert len(text) == start + count * width + (2 if flag and flagged else 0)  # LITHOS's columns
        lithos = [v for v in formatted_read(text, fmt) if isinstance(v, float)]
        for got, v in zip(lithos, values):
            if abs(v) < 10 ** (width - 2 - decimals) - 1:  # fits Fw.d: gfortran's rounding of the value
                assert got == float(f"{v:.{decimals}f}"), (text, v)
            else:  # an E field: 4+ significant digits
                assert abs(got - v) <= 5e-4 * abs(v), (text, v)
        ours, rest, note = read_section_row(text, fmt, count, start, path=None, lineno=1, what="numbers")
        assert note is None and ours == lithos and rest.strip() == (flag if flagged else "")


def test_distort_model_chosen_by_the_picture_asked_for(run_cli, owen_workdir, real):
    """Issue #40 item 2: a copied picture (SUMFILES/H0LD00000001.SUM whose line 1 still says W48230079013)
    gets the DISTORT= model of the name SPC's getmm(PICNM) is called with -- H0LD00000001 -- and the
    line-1 mismatch is warned once."""
    (owen_workdir / "INIT_LITHOS.TXT").write_text(ISSUE_LITHOS.replace("HOLD########", "H0LD########"))
    shutil.copy(owen_workdir / "SUMFILES/W48230079013.SUM", owen_workdir / "SUMFILES/H0LD00000001.SUM")
    r = run_cli("-C", owen_workdir, "project", "H0LD00000001", "--json")
    assert r.exit_code == 0, r.stderr
    got = {row["name"]: (row["sample"], row["line"]) for row in json.loads(r.stdout)["landmarks"]}
    sum_text = (real / "rosetta-67p/W48230079013.SUM").read_text()
    for name, (s, ln) in got.items():
        vlm = _dvals((real / f"rosetta-67p/{name}.LMK").read_text().split("\n")[4], 3)
        es, el = _owen_pixel(sum_text, vlm, ISSUE_P)  # the OWEN model of H0LD########, not the pinhole
        assert abs(s - es) < 1e-9 and abs(ln - el) < 1e-9, (name, s - es, ln - el)
    warned = [ln for ln in r.stderr.splitlines() if "line 1 names picture" in ln]
    assert len(warned) == 1 and "'W48230079013'" in warned[0] and "'H0LD00000001'" in warned[0]
    # the original name: no such template, the plain pinhole, no warning
    r = run_cli("-C", owen_workdir, "project", "W48230079013", "--json")
    assert r.exit_code == 0 and "line 1 names" not in r.stderr
    assert _project(run_cli, owen_workdir) != got


def test_a_sum_file_outside_sumfiles_keeps_its_line1_name(run_cli, owen_workdir):
    """A SUM given by a path outside SUMFILES/ (named as its user likes) is not SPC's SUMFILES/<PICNM>.SUM:
    its line-1 name chooses the model, nothing is warned."""
    (owen_workdir / "INIT_LITHOS.TXT").write_text(ISSUE_LITHOS.replace("HOLD########", "W###########"))
    shutil.copy(owen_workdir / "SUMFILES/W48230079013.SUM", owen_workdir / "new.SUM")
    r = run_cli("-C", owen_workdir, "project", "new.SUM", "--json")
    assert r.exit_code == 0 and "line 1 names" not in r.stderr
    by_path = {row["name"]: (row["sample"], row["line"]) for row in json.loads(r.stdout)["landmarks"]}
    assert by_path == _project(run_cli, owen_workdir)  # the OWEN model of W###########, as for the original
