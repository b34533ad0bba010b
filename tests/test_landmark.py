"""LMK files (spc-formats.md §4): real Rosetta files, the §4.3 example, byte-exact rewrites, errors."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool.errors import SpcFormatError
from spctool.formats.fortran import format_d, format_f, parse_number
from spctool.formats.landmark import (
    Landmark,
    LandmarkLimb,
    LandmarkPicture,
    MapOverlap,
    format_lmk,
    parse_lmk,
    read_lmk,
    write_lmk,
)

ROSETTA = Path(__file__).resolve().parent.parent / "fixtures" / "real" / "rosetta-67p"
NAMES = ["FA0115", "FC0098", "GD0036"]

EXAMPLE = """\
AB0001   T
      49   0.0005000                                           SIZE, SCALE(KM)··
        -1        -1        -1        -1                       HORIZON··········
    0.2500000000D-03    0.0000000000D+00                       SIGKM, RMSLMK····
    0.5000000000D+00    0.1000000000D+00    0.2000000000D+00   VLM··············
    0.3580574370D+00    0.7161148740D-01   -0.9309493363D+00   UX···············
   -0.1961161351D+00    0.9805806757D+00    0.0000000000D+00   UY···············
    0.9128709292D+00    0.1825741858D+00    0.3651483717D+00   UZ···············
    0.5000000000D-03    0.5000000000D-03    0.5000000000D-03   SIGMA_LMK········
PICTURES
X123456789A1    565.13    407.24
X123456799A1    570.02    401.90 *
MAP OVERLAPS
AB0002         0.412      71.944      -0.318
LIMB FITS
X123456810A1     12.50    998.75      0.35
END FILE
""".replace("·", " ")


def example_landmark() -> Landmark:
    return Landmark(
        name="AB0001",
        hflag="T",
        bigmap_extra=None,
        qsz=49,
        scale=0.0005,
        horizon=(-1, -1, -1, -1),
        sigkm=0.00025,
        rmslmk=0.0,
        vlm=[0.5, 0.1, 0.2],
        ux=[0.3580574370, 0.07161148740, -0.9309493363],
        uy=[-0.1961161351, 0.9805806757, 0.0],
        uz=[0.9128709292, 0.1825741858, 0.3651483717],
        sigma_lmk=[0.0005] * 3,
        pictures=[
            LandmarkPicture("X123456789A1", 565.13, 407.24),
            LandmarkPicture("X123456799A1", 570.02, 401.90, "*"),
        ],
        overlaps=[MapOverlap("AB0002", [0.412, 71.944, -0.318])],
        limb_fits=[LandmarkLimb("X123456810A1", 12.50, 998.75, 0.35)],
    )


# ------------------------------------------------------------------------------------------------------------
# real Rosetta files


@pytest.mark.parametrize(
    "name, rmslmk, first_picture",
    [
        ("FA0115", 1.459, ("N46299874022", 204.85, 502.49)),
        ("FC0098", 1.373, ("N46037044523", 1253.92, 1832.63)),
        ("GD0036", 1.704, ("N46429973316", 970.68, 251.31)),
    ],
)
def test_rosetta_values(name, rmslmk, first_picture):
    lmk = read_lmk(ROSETTA / f"{name}.LMK")
    assert lmk.name == name and lmk.hflag == "T" and lmk.bigmap_extra is None
    assert lmk.qsz == 49 and lmk.scale == 0.01
    assert lmk.horizon == (-1, -1, -1, -1)
    assert lmk.sigkm == 0.005 == 0.5 * lmk.scale
    assert round(lmk.rmslmk, 3) == rmslmk
    assert len(lmk.pictures) == 3 and lmk.overlaps == [] and lmk.limb_fits == []
    assert lmk.pictures[0] == LandmarkPicture(*first_picture)
    assert all(p.name.startswith("N") for p in lmk.pictures)
    assert np.all(lmk.sigma_lmk > 0) and np.all(lmk.sigma_lmk < 0.001)


def test_rosetta_negative_picture_lines():
    lmk = read_lmk(ROSETTA / "FA0115.LMK")
    assert lmk.pictures[1] == LandmarkPicture("N46402766222", 655.45, -481.78)
    assert lmk.pictures[2] == LandmarkPicture("N46402769023", 668.43, -472.51)
    assert read_lmk(ROSETTA / "GD0036.LMK").pictures[2].line == -252.57


@pytest.mark.parametrize("name, cos_east", [("FA0115", 0.9975), ("FC0098", 1.0000), ("GD0036", 0.925)])
def test_rosetta_axes(name, cos_east):
    """README facts: orthonormal triad, det +1, UY ~ East (cosines 0.9975 / 1.0000 / 0.925), UX = UY x UZ."""
    lmk = read_lmk(ROSETTA / f"{name}.LMK")
    r = lmk.rotation_map_to_body
    np.testing.assert_array_equal(r[:, 0], lmk.ux)
    np.testing.assert_array_equal(r[:, 2], lmk.uz)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-7)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-7)
    east = np.cross([0.0, 0.0, 1.0], lmk.uz)
    east /= np.linalg.norm(east)
    assert float(lmk.uy @ east) == pytest.approx(cos_east, abs=5e-4)
    np.testing.assert_allclose(np.cross(lmk.uy, lmk.uz), lmk.ux, atol=1e-7)


@pytest.mark.parametrize("name", NAMES)
def test_rosetta_rewrite_byte_identical(name, tmp_path):
    src = ROSETTA / f"{name}.LMK"
    lmk = read_lmk(src)
    write_lmk(tmp_path / src.name, lmk)
    assert (tmp_path / src.name).read_bytes() == src.read_bytes()
    assert format_lmk(copy.deepcopy(lmk)).encode() == src.read_bytes()


def test_rosetta_edits_keep_trimmed_stripped_style():
    text = (ROSETTA / "FA0115.LMK").read_text()
    old = text.split("\n")
    lmk = parse_lmk(text)
    lmk.vlm = np.array([1.0, -2.0, 0.25])
    new = format_lmk(lmk).split("\n")
    assert [i for i, (a, b) in enumerate(zip(old, new)) if a != b] == [4]
    assert new[4] == "    0.1000000000D+01   -0.2000000000D+01    0.2500000000D+00   VLM"
    lmk.rmslmk = 0.5
    lmk.pictures[1].flag = "*"
    lmk.overlaps.append(MapOverlap("FA0116", [66.0, -1.5, 0.25]))
    out = format_lmk(lmk)
    new = out.split("\n")
    assert new[3] == "    0.5000000000D-02    0.5000000000D+00                       SIGKM, RMSLMK"
    assert new[9:] == [
        "PICTURES",
        "N46299874022    204.85    502.49",
        "N46402766222    655.45   -481.78 *",
        "N46402769023    668.43   -472.51",
        "MAP OVERLAPS",
        "FA0116        66.000      -1.500       0.250",
        "END FILE",
        "",
    ]
    assert parse_lmk(out) == lmk


# ------------------------------------------------------------------------------------------------------------
# §4.3 example


def test_example_written_byte_for_byte():
    assert format_lmk(example_landmark()) == EXAMPLE


def test_example_parses_and_axes_are_orient():
    lmk = parse_lmk(EXAMPLE)
    assert lmk == example_landmark()
    assert format_lmk(lmk) == EXAMPLE
    # ORIENT: UZ = normalised V, UY = normalise(z x UZ) (East), UX = UY x UZ (South)
    uz = lmk.vlm / np.linalg.norm(lmk.vlm)
    uy = np.cross([0, 0, 1.0], uz)
    uy /= np.linalg.norm(uy)
    np.testing.assert_allclose(lmk.uz, uz, atol=1e-10)
    np.testing.assert_allclose(lmk.uy, uy, atol=1e-10)
    np.testing.assert_allclose(lmk.ux, np.cross(uy, uz), atol=1e-10)


def test_example_edit_keeps_padding():
    lmk = parse_lmk(EXAMPLE)
    lmk.qsz = 99
    lmk.scale = 0.001
    lmk.horizon = (1, 2, 3, 4)
    new = format_lmk(lmk).split("\n")
    assert new[1] == "      99   0.0010000                                           SIZE, SCALE(KM)  "
    assert new[2] == "         1         2         3         4                       HORIZON          "
    assert new[3:] == EXAMPLE.split("\n")[3:]


def test_bigmap_line_one_variant():
    text = EXAMPLE.replace("AB0001   T\n", "AB0001   T      0.2500  0.0500\n", 1)
    lmk = parse_lmk(text)
    assert lmk.bigmap_extra == (0.25, 0.05)
    assert format_lmk(lmk) == text
    lmk.bigmap_extra = (0.5, 0.125)
    assert format_lmk(lmk).split("\n")[0] == "AB0001   T      0.5000  0.1250"
    lmk.bigmap_extra = None
    lmk.hflag = "F"
    assert format_lmk(lmk).split("\n")[0] == "AB0001   F"


def test_section_order_and_duplicates_preserved():
    lines = EXAMPLE.split("\n")
    # LIMB FITS before MAP OVERLAPS, a duplicate picture row and a trailing line after END FILE
    reordered = (
        lines[:9] + lines[9:12] + [lines[11]] + lines[14:16] + lines[12:14] + lines[16:17] + ["extra", ""]
    )
    text = "\n".join(reordered)
    lmk = parse_lmk(text)
    assert [p.name for p in lmk.pictures] == ["X123456789A1", "X123456799A1", "X123456799A1"]
    assert format_lmk(lmk) == text


# ------------------------------------------------------------------------------------------------------------
# errors


def err(text: str, path="LMKFILES/AB0001.LMK") -> str:
    with pytest.raises(SpcFormatError) as info:
        parse_lmk(text, path)
    return str(info.value)


def test_errors_name_file_and_line():
    lines = EXAMPLE.split("\n")
    bad = list(lines)
    bad[0] = "AB0001   Q"
    assert err("\n".join(bad)).startswith("LMKFILES/AB0001.LMK:1: expected HFLAG T or F")
    bad = list(lines)
    bad[4] = bad[4].replace("0.1000000000D+00", "0.10000x0000D+00")
    # header lines are list-directed READs: the bad item is named (gfortran "Bad real number in item 2")
    assert err("\n".join(bad)).startswith("LMKFILES/AB0001.LMK:5: expected 3 numbers (VLM): value 2 ")
    bad = list(lines)
    bad[5] = "    0.3580574370D+00    0.7161148740D-01   UX"
    assert err("\n".join(bad)).startswith("LMKFILES/AB0001.LMK:6: expected 3 numbers (UX): value 3 'UX'")
    bad = list(lines)
    bad[1] = "      49.5   0.0005000     SIZE, SCALE(KM)"
    assert err("\n".join(bad)).startswith(
        "LMKFILES/AB0001.LMK:2: expected 2 numbers (QSZ, SCALE): value 1 '49.5'"
    )
    bad = list(lines)
    bad[2] = "        -1        -1        -1       HORIZON"
    assert err("\n".join(bad)).startswith(
        "LMKFILES/AB0001.LMK:3: expected 4 numbers (HORIZON): value 4 'HORIZON'"
    )
    bad = list(lines)
    bad[10] = "X123456789A1    565.13    4O7.24"
    assert err("\n".join(bad)).startswith("LMKFILES/AB0001.LMK:11: expected 2 numbers (picture sample, line)")
    bad = list(lines)
    bad[13] = "AB0002         0.412      71.944"
    assert err("\n".join(bad)).startswith("LMKFILES/AB0001.LMK:14: expected 3 numbers (map overlap offset)")
    bad = list(lines)
    bad.insert(9, "X123456789A1    565.13    407.24")
    assert err("\n".join(bad)).startswith("LMKFILES/AB0001.LMK:10: expected PICTURES, MAP OVERLAPS")


def test_truncated_and_missing_end():
    lines = EXAMPLE.split("\n")
    assert (
        err("\n".join(lines[:5]) + "\n") == "LMKFILES/AB0001.LMK:5: expected UX on line 6, found end of file"
    )
    assert err("\n".join(lines[:16])) == "LMKFILES/AB0001.LMK:16: expected END FILE line, found end of file"
    assert err("") == "LMKFILES/AB0001.LMK:1: expected the landmark name and HFLAG, found an empty file"
    with pytest.raises(SpcFormatError) as info:
        read_lmk(ROSETTA / "NOPE.LMK")
    assert "NOPE.LMK" in str(info.value)


# ------------------------------------------------------------------------------------------------------------
# properties

D = st.floats(-1e6, 1e6, allow_nan=False).map(lambda v: parse_number(format_d(v)))
F2 = st.floats(-99999, 999999, allow_nan=False).map(lambda v: parse_number(format_f(v, 10, 2)))
F3 = st.floats(-9999, 99999, allow_nan=False).map(lambda v: parse_number(format_f(v, 12, 3)))
F4 = st.floats(-99, 999, allow_nan=False).map(lambda v: parse_number(format_f(v, 8, 4)))
SCALE = st.floats(0, 999, allow_nan=False).map(lambda v: parse_number(format_f(v, 12, 7)))
LM_NAME = st.from_regex(r"[A-Z][A-Z0-9]{0,5}", fullmatch=True)
# any 12-character name except one that starts with a section keyword (only PICTURES fits in 12 columns)
PIC_NAME = st.from_regex(r"[A-Z][A-Z0-9]{0,11}", fullmatch=True).filter(
    lambda n: not n.startswith("PICTURES")
)


def vec(n=3):
    return st.lists(D, min_size=n, max_size=n).map(np.array)


landmarks = st.builds(
    Landmark,
    name=LM_NAME,
    hflag=st.sampled_from(["T", "F"]),
    bigmap_extra=st.none() | st.tuples(F4, F4),
    qsz=st.integers(0, 9999999),
    scale=SCALE,
    horizon=st.tuples(*[st.integers(-999999999, 999999999)] * 4),
    sigkm=D,
    rmslmk=D,
    vlm=vec(),
    ux=vec(),
    uy=vec(),
    uz=vec(),
    sigma_lmk=vec(),
    pictures=st.lists(st.builds(LandmarkPicture, PIC_NAME, F2, F2, st.sampled_from(["", "*"])), max_size=4),
    overlaps=st.lists(st.builds(MapOverlap, LM_NAME, st.lists(F3, min_size=3, max_size=3)), max_size=3),
    limb_fits=st.lists(st.builds(LandmarkLimb, PIC_NAME, F2, F2, F2), max_size=3),
)


@settings(max_examples=60, deadline=None)
@given(landmarks)
def test_round_trip_property(lmk):
    text = format_lmk(lmk)
    back = parse_lmk(text)
    assert back == lmk
    assert format_lmk(back) == text


EDITS = {
    "vlm": (vec(), 4),
    "uz": (vec(), 7),
    "sigma_lmk": (vec(), 8),
    "sigkm": (D, 3),
    "scale": (SCALE, 1),
    "horizon": (st.tuples(*[st.integers(-99999, 99999)] * 4), 2),
}


@settings(max_examples=50, deadline=None)
@given(st.sampled_from(NAMES + ["example"]), st.sets(st.sampled_from(sorted(EDITS)), min_size=1), st.data())
def test_edit_property(which, chosen, data):
    text = EXAMPLE if which == "example" else (ROSETTA / f"{which}.LMK").read_text()
    lmk = parse_lmk(text)
    for name in chosen:
        setattr(lmk, name, data.draw(EDITS[name][0], label=name))
    out = format_lmk(lmk)
    assert parse_lmk(out) == lmk
    changed = {EDITS[name][1] for name in chosen}
    for i, (a, b) in enumerate(zip(text.split("\n"), out.split("\n"))):
        if i not in changed:
            assert a == b
        else:
            assert len(b) == len(a) or (len(a) != 80 and len(b) != 80)
