"""INIT_LITHOS.TXT (spc-formats.md §6): parsing rules, DISTORT= entries, accessors, byte-exact rewrite."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool.errors import SpcFormatError
from spctool.formats.lithos import (
    DistortModel,
    Settings,
    format_lithos,
    parse_lithos,
    read_lithos,
    write_lithos,
)

EXAMPLE = """\
BODY='TARGET'
IDCODE=2000433
BFRAME='IAU_EROS'
PCK='DATA/naif0012.tls'
UNIT='METER'
MAPVERS=0
LMKLX=.TRUE.
DISTORT= 'X###########' 'OWEN'  6
0.0D0  0.0D0  1.2D-06  0.0D0  -3.0D-09  0.0D0  0.0D0
LMKWTS= 1, 1, 1, 0      WB, WO, WL, WR
PICWTS= 1, 1, 0, 1, 0   WB, WL, WC, WS, WT
LPCORLM= 0.2
ALCORLM= 0.3
CORRFLG= 3         0:LAP, 1:ALB, 2:GRD, 3:L+A
RESLM= 4
NUMLM=200
END
"""

# wiki-style sample: comments, a repeated key, wrapped letterless-exponent coefficients, several templates
WIKI = """\
# INIT_LITHOS for a test
USR='0'
BODY='RQ36'
PCK='DATA/naif0011.tls'
PCK='DATA/pck00010.tpc'
NEWLIM=.FALSE.
#REFLECT='VESTA'
 NUMLM=999
numlm=999
NEWLIM=.TRUE.
DISTORT= 'P###########' 'OWEN'  6
0.0D0  0.0D0  2.5000000-06
  0.0D0  0.0D0  1.0D-05  -4.0D-07
DISTORT= 'P#########F2' 'radial'  2   trailing words
1.5-03 7.5E-06 -2.0D-09 ignored after the count
DISTORT= 'P##########3' 'CUBIC'  20
21*0.0
BLEMISHES='FC2#########'
BLEMISH= 'FC3#########'
TPARS= 1.D0 1.5 .05 1 2 6 0 0 0 0
SEED=1.3827453
END
text after END is kept
"""


# ------------------------------------------------------------------------------------------------------------
# parsing


def test_example_values_and_round_trip(tmp_path):
    s = parse_lithos(EXAMPLE, "INIT_LITHOS.TXT")
    assert s.get_str("BODY") == "TARGET" and s.get_int("IDCODE") == 2000433
    assert s.pcks == ["DATA/naif0012.tls"] and s.blemishes == []
    assert s.get_bool("LMKLX") is True
    assert s.get_floats("LMKWTS") == [1, 1, 1, 0]
    assert s.get_floats("PICWTS") == [1, 1, 0, 1, 0]
    assert s.get_int("CORRFLG") == 3  # trailing comment ignored
    assert s.get_float("LPCORLM") == 0.2
    assert (s.numlm, s.reslm, s.mapvers) == (200, 4.0, 0)
    assert (s.sizlm, s.piclm) == (1.5, 2)  # defaults
    assert s.keys["CORRFLG"] == "3         0:LAP, 1:ALB, 2:GRD, 3:L+A"
    (d,) = s.distortions
    assert (d.template, d.model, d.order) == ("X###########", "OWEN", 6)
    np.testing.assert_array_equal(d.coefficients, [0, 0, 1.2e-6, 0, -3.0e-9, 0, 0])
    assert format_lithos(s) == EXAMPLE
    write_lithos(tmp_path / "INIT_LITHOS.TXT", s)
    assert (tmp_path / "INIT_LITHOS.TXT").read_text() == EXAMPLE
    assert read_lithos(tmp_path / "INIT_LITHOS.TXT") == s


def test_wiki_sample_rules():
    s = parse_lithos(WIKI)
    assert format_lithos(s) == WIKI
    assert s.pcks == ["DATA/naif0011.tls", "DATA/pck00010.tpc"]
    assert s.blemishes == ["FC2#########", "FC3#########"]  # BLEMISHES= and BLEMISH= both accepted
    assert s.get_bool("NEWLIM") is True  # last value of a repeated key wins
    assert "REFLECT" not in s.keys  # '#' comment
    assert s.numlm == 200  # ' NUMLM=' (not column 1) and 'numlm=' (lower case) are not keys
    assert s.get_floats("TPARS") == [1, 1.5, 0.05, 1, 2, 6, 0, 0, 0, 0]
    assert s.get_float("SEED") == 1.3827453
    owen, radial, cubic = s.distortions
    np.testing.assert_array_equal(owen.coefficients, [0, 0, 2.5e-6, 0, 0, 1.0e-5, -4.0e-7])
    # getmm compares TYPE exactly (IF(TYPE(JD).EQ.'RADIAL')): 'radial' is kept as written, and is no model
    assert radial.model == "radial" and radial.template == "P#########F2"
    np.testing.assert_array_equal(radial.coefficients, [1.5e-3, 7.5e-6, -2.0e-9])
    assert cubic.order == 20 and np.array_equal(cubic.coefficients, np.zeros(21))
    assert s.entries[0] == (2, "USR", "'0'")


def test_only_columns_1_to_80_count():
    text = "RESLM= 4" + " " * 72 + "9\nNUMLM=" + " " * 74 + "300\nEND   and more\n"
    s = parse_lithos(text)
    assert s.reslm == 4.0
    assert s.keys["NUMLM"] == ""
    with pytest.raises(SpcFormatError, match="expected a value for NUMLM="):
        _ = s.numlm
    assert format_lithos(s) == text


def test_typed_accessor_errors_name_the_line():
    s = parse_lithos("NUMLM=200.5\nLMKLX=maybe\nBODY='open\nEND\n", "INIT_LITHOS.TXT")
    with pytest.raises(SpcFormatError) as info:
        _ = s.numlm
    assert str(info.value) == "INIT_LITHOS.TXT:1: expected an integer for NUMLM=, found '200.5'"
    with pytest.raises(SpcFormatError) as info:
        s.get_bool("LMKLX")
    assert str(info.value).startswith("INIT_LITHOS.TXT:2: expected a logical")
    with pytest.raises(SpcFormatError) as info:
        s.get_str("BODY")
    assert str(info.value).startswith("INIT_LITHOS.TXT:3: expected a value for BODY=")
    assert s.get_float("ABSENT", 7.5) == 7.5 and s.get_str("ABSENT") is None


@pytest.mark.parametrize(
    "text, value",
    [
        (".TRUE.", True),
        (".FALSE.", False),
        ("T", True),
        ("F", False),
        (".true.", True),
        ("f", False),
        (".T.", True),
    ],
)
def test_fortran_logicals(text, value):
    assert parse_lithos(f"NEWLIM={text}\nEND\n").get_bool("NEWLIM") is value


def test_missing_end_line():
    with pytest.raises(SpcFormatError) as info:
        parse_lithos("BODY='X'\nNUMLM=200\n", "INIT_LITHOS.TXT")
    assert str(info.value) == "INIT_LITHOS.TXT:2: expected END line (columns 1-3), found end of file"
    with pytest.raises(SpcFormatError) as info:
        parse_lithos(" END\n", "INIT_LITHOS.TXT")
    assert str(info.value).startswith("INIT_LITHOS.TXT:1: expected END line")
    with pytest.raises(SpcFormatError) as info:
        parse_lithos("", "INIT_LITHOS.TXT")
    assert str(info.value) == "INIT_LITHOS.TXT:1: expected END line, found an empty file"


def test_distort_errors():
    with pytest.raises(SpcFormatError) as info:
        parse_lithos("DISTORT= 'P###' 'OWEN'  6\n0.0 0.0 0.0\n0.0\nEND\n", "L.TXT")
    # getmm READ(25,*) (PD(I,KD), I=0,J) reads on into the END record (gfortran: bad real in item 5)
    assert str(info.value) == "L.TXT:4: expected 7 DISTORT= coefficients: value 5 'END' is not a Fortran real"
    with pytest.raises(SpcFormatError) as info:
        parse_lithos("DISTORT= 'P###' 'OWEN'  six\n0.0\nEND\n", "L.TXT")
    assert str(info.value).startswith(
        "L.TXT:1: expected 3 values (DISTORT= 'TEMPLATE' 'MODEL' J): value 3 'six'"
    )
    with pytest.raises(SpcFormatError) as info:
        parse_lithos("DISTORT= 'P###' 'OWEN'  2\n0.0 0.0x 0.0\nEND\n", "L.TXT")
    assert (
        str(info.value) == "L.TXT:2: expected 3 DISTORT= coefficients: value 2 '0.0x' is not a Fortran real"
    )
    with pytest.raises(SpcFormatError) as info:
        parse_lithos("DISTORT= 'P###' 'OWEN'\nEND\n", "L.TXT")
    assert str(info.value).startswith("L.TXT:1: expected 3 values (DISTORT= 'TEMPLATE' 'MODEL' J), found 2")
    with pytest.raises(SpcFormatError) as info:
        parse_lithos("DISTORT= 'P###' 'OWEN' 1\n0.0\n", "L.TXT")
    assert str(info.value) == "L.TXT:2: expected 2 DISTORT= coefficients, found 1 before the end of the file"


# ------------------------------------------------------------------------------------------------------------
# templates


def model(template, name="OWEN"):
    return DistortModel(template, name, 0, [0.0])


def test_template_matching():
    m = model("P###########")
    assert m.matches("P601296494J3") and not m.matches("Q601296494J3")
    assert model("P#########J3").matches("P601296494J3")
    assert not model("P#########J3").matches("P601296494J4")
    assert model("N2395699394 ").matches("N2395699394")  # blank template char matches anything
    assert model("N###").matches("N2395699394")  # short template is blank-padded to 12
    assert model("############").matches("")
    assert not model("p###########").matches("P601296494J3")  # case-sensitive, as in Fortran
    assert model("P###########").template == "P###########" and len(model("P#").template) == 12


def test_last_matching_template_wins():
    s = parse_lithos(WIKI)
    assert s.distortion_for("P601296494F2").model == "radial"  # matches OWEN and radial: radial is later
    assert s.distortion_for("P601296494J3").model == "CUBIC"
    assert s.distortion_for("P601296494J1").model == "OWEN"
    assert s.distortion_for("X601296494J1") is None
    # brute force: the answer is the last entry whose every character matches
    for name in ["P601296494F2", "P601296494J3", "P60129649403", "PXXXXXXXXXF3", "Q60"]:
        expected = None
        for d in s.distortions:
            t, n = d.template, name.ljust(12)
            if all(t[k] in "# " or t[k] == n[k] for k in range(12)):
                expected = d
        assert s.distortion_for(name) is expected


def test_distort_model_validation():
    with pytest.raises(ValueError):
        DistortModel("P###", "OWEN", 6, [0.0] * 6)
    with pytest.raises(ValueError):
        DistortModel("P###", "OWEN", -1, [])


# ------------------------------------------------------------------------------------------------------------
# editing


def test_set_key_rewrites_only_its_last_line():
    s = parse_lithos(WIKI)
    s.set("NEWLIM", False)
    s.set("SEED", 2.5e-7)
    out = format_lithos(s)
    old, new = WIKI.split("\n"), out.split("\n")
    diff = [i for i, (a, b) in enumerate(zip(old, new)) if a != b]
    assert diff == [9, 20]
    assert new[9] == "NEWLIM=.FALSE." and new[20] == "SEED=2.5D-07"
    back = parse_lithos(out)
    assert back.get_bool("NEWLIM") is False and back.get_float("SEED") == 2.5e-7


def test_delete_and_add_keys_and_lists():
    s = parse_lithos(EXAMPLE)
    del s.keys["UNIT"]
    s.set("SIZLM", 2.0)
    s.set("REFLECT", "LOMMEL-SEELIGER")
    s.pcks.append("DATA/x.tpc")
    s.blemishes.append("X###########")
    s.distortions.append(DistortModel("X#########AB", "RADIAL", 2, [0.0, 1.25e-5, -3.5e-9]))
    out = format_lithos(s)
    lines = out.split("\n")
    assert "UNIT='METER'" not in lines
    assert lines[3:5] == ["PCK='DATA/naif0012.tls'", "PCK= 'DATA/x.tpc'"]
    i = lines.index("DISTORT= 'X#########AB' 'RADIAL'  2")
    assert lines[i - 2 : i] == EXAMPLE.split("\n")[7:9] and lines[i + 1] == "0.0  1.25D-05  -3.5D-09"
    assert lines[-5:] == ["SIZLM= 2.0", "REFLECT= 'LOMMEL-SEELIGER'", "BLEMISH= 'X###########'", "END", ""]
    back = parse_lithos(out)
    assert back == s
    assert back.sizlm == 2.0 and back.get_str("REFLECT") == "LOMMEL-SEELIGER"
    assert back.distortion_for("X123456789AB").model == "RADIAL"
    assert back.distortion_for("X123456789AC").model == "OWEN"


def test_new_settings_and_long_coefficient_lists():
    s = Settings()
    s.set("BODY", "EROS")
    s.set("LMKLX", True)
    s.set("LMKWTS", [1, 1, 1, 0])
    coefs = np.linspace(-1e-3, 1e-3, 21) * np.pi
    s.distortions.append(DistortModel("P###########", "CUBIC", 20, coefs))
    out = format_lithos(s)
    assert out.startswith(
        "BODY= 'EROS'\nLMKLX= .TRUE.\nLMKWTS= 1, 1, 1, 0\nDISTORT= 'P###########' 'CUBIC'  20\n"
    )
    assert out.endswith("\nEND\n")
    assert all(len(line) <= 80 for line in out.split("\n"))
    back = parse_lithos(out)
    assert back == s
    np.testing.assert_array_equal(back.distortions[0].coefficients, coefs)  # exact
    with pytest.raises(ValueError):
        s.set("PCK", "x")


# ------------------------------------------------------------------------------------------------------------
# properties

KEY = st.from_regex(r"[A-CF-Z][A-Z0-9_]{0,8}", fullmatch=True).filter(
    lambda k: k not in ("PCK", "DISTORT", "BLEMISH", "BLEMISHES")
)
VALUE = st.one_of(
    st.booleans(),
    st.integers(-(10**9), 10**9),
    st.floats(allow_nan=False, allow_infinity=False),
    st.from_regex(r"[A-Za-z0-9_./ #'-]{0,20}", fullmatch=True),
)
COEF = st.floats(allow_nan=False, allow_infinity=False)
TEMPLATE = st.from_regex(r"[A-Z0-9#]{12}", fullmatch=True)
STRING = st.from_regex(r"[A-Za-z0-9_./#-]{1,30}", fullmatch=True)


@st.composite
def settings_strategy(draw):
    s = Settings()
    for key, value in draw(st.dictionaries(KEY, VALUE, max_size=6)).items():
        s.set(key, value)
    s.pcks = draw(st.lists(STRING, max_size=3))
    s.blemishes = draw(st.lists(TEMPLATE, max_size=2))
    for _ in range(draw(st.integers(0, 3))):
        order = draw(st.integers(0, 25))
        coefs = draw(st.lists(COEF, min_size=order + 1, max_size=order + 1))
        s.distortions.append(
            DistortModel(draw(TEMPLATE), draw(st.sampled_from(["OWEN", "RADIAL"])), order, coefs)
        )
    return s


@settings(max_examples=60, deadline=None)
@given(settings_strategy())
def test_round_trip_property(s):
    text = format_lithos(s)
    back = parse_lithos(text)
    assert back == s
    assert format_lithos(back) == text
    for key, raw in s.keys.items():
        assert back.keys[key] == raw


@settings(max_examples=60, deadline=None)
@given(st.lists(STRING, max_size=3), st.integers(0, 3), st.dictionaries(KEY, st.integers(0, 999), max_size=3))
def test_edit_property(pcks, n_distort, new_keys):
    """Edits to a parsed file round-trip; untouched lines stay byte-identical."""
    s = parse_lithos(WIKI)
    s.pcks = pcks
    del s.distortions[n_distort:]
    for key, value in new_keys.items():
        s.set(key, value)
    out = format_lithos(s)
    back = parse_lithos(out)
    assert back == s
    kept = [ln for ln in WIKI.split("\n") if not ln.startswith(("PCK=", "DISTORT=")) and ln[:1] not in "0 12"]
    out_lines = out.split("\n")
    for ln in kept:
        key = ln.split("=")[0]
        if key not in new_keys:
            assert ln in out_lines


def test_get_floats_expands_repeat_counts():
    # list-directed input: r*c is r copies of c (Fortran 2008 §10.10.3)
    s = parse_lithos("LMKWTS= 3*1, 0   WB, WO, WL, WR\nTPARS= 1.D0 1.5 .05 1 2 6 4*0\nEND\n")
    assert s.get_floats("LMKWTS") == [1, 1, 1, 0]
    assert s.get_floats("TPARS") == [1, 1.5, 0.05, 1, 2, 6, 0, 0, 0, 0]


def test_scalar_keys_null_slash_and_repeat():
    # READ(LINE(n:80),*) VALUE: a leading comma (null) or '/' leaves the program's default; r*c gives c
    s = parse_lithos("CHI0= , 2.0\nNUMLM= 2*150\nRESLM= 3*\nSIZLM= / 9\nSEED= 1.5\nEND\n")
    assert s.get_float("CHI0", 1.0) == 1.0 and s.numlm == 150 and s.reslm == 4.0 and s.sizlm == 1.5
    assert s.get_float("SEED") == 1.5
