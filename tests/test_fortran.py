"""Fortran number reading and writing (spc-formats.md §0.3)."""

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool.errors import SpcFormatError
from spctool.formats.fortran import format_d, format_e, format_f, format_i, pad_tag, parse_number, read_reals


@pytest.mark.parametrize(
    "token, value",
    [
        ("0.1356800000D+03", 135.68),
        ("0.1356800000d+03", 135.68),
        ("-0.2626299087D-01", -0.02626299087),
        ("0.5000000000E-05", 5e-6),
        ("1.5Q2", 150.0),
        ("0.0000000-06", 0.0),
        ("1.5-06", 1.5e-6),
        ("2.5000000-06", 2.5e-6),
        ("0.1000000000+101", 1e100),
        (".5", 0.5),
        ("7", 7.0),
        ("-3.", -3.0),
        ("+4.25E+1", 42.5),
    ],
)
def test_parse_number_forms(token, value):
    assert parse_number(token) == pytest.approx(value, rel=1e-15, abs=0)


@pytest.mark.parametrize("token", ["", "abc", "1.2.3", "D+03", "1.5--6", "1,5"])
def test_parse_number_rejects(token):
    with pytest.raises(ValueError):
        parse_number(token)


def test_read_reals_commas_and_trailing_text():
    assert read_reals("1, 1, 1, 0      WB, WO, WL, WR", 4) == [1, 1, 1, 0]
    assert read_reals(" 3   0:LAP, 1:ALB", 1) == [3]


def test_read_reals_names_place():
    with pytest.raises(SpcFormatError) as e:
        read_reals("1.0 x 3.0", 3, path="F.SUM", line=5, what="SCOBJ components")
    assert str(e.value).startswith("F.SUM:5: expected 3 SCOBJ components")
    with pytest.raises(SpcFormatError, match="found 2"):
        read_reals("1.0 2.0", 3, path="F.SUM", line=5)


def test_format_d_matches_gfortran_examples():
    # values printed in spc-formats.md §0.3 and the real Rosetta SUM
    assert format_d(135.68) == "    0.1356800000D+03"
    assert format_d(-0.02626299087) == "   -0.2626299087D-01"
    assert format_d(0.0) == "    0.0000000000D+00"
    assert format_d(5e-6) == "    0.5000000000D-05"
    assert format_d(1e100) == "    0.1000000000+101"
    assert format_d(-1.5e-120) == "   -0.1500000000-119"
    assert format_d(0.5, 15, 5) == "    0.50000D+00"
    assert format_e(120.4711641) == "    0.1204711641E+03"


def test_format_f_and_i():
    assert format_f(37.0371, 10, 4) == "   37.0371"
    assert format_f(-481.78, 10, 2) == "   -481.78"
    assert format_f(83.333333, 10, 5) == "  83.33333"
    assert format_f(1e9, 10, 2) == "**********"
    assert format_i(1024, 6) == "  1024"
    assert format_i(1234567, 6) == "******"


def test_pad_tag_column_64():
    line = pad_tag(format_d(1.0) * 3, "SCOBJ")
    assert line.index("SCOBJ") == 63
    assert len(pad_tag("x", "TAG", pad_to=80)) == 80


@settings(max_examples=300, deadline=None)
@given(st.floats(allow_nan=False, allow_infinity=False, min_value=-1e99, max_value=1e99))
def test_d_format_round_trips_to_ten_digits(x):
    text = format_d(x)
    assert len(text) == 20
    back = parse_number(text)
    if x == 0:
        assert back == 0
    else:
        assert math.isclose(back, x, rel_tol=5.1e-10)
        # a second write is identical (the text is a fixed point)
        assert format_d(back) == text
