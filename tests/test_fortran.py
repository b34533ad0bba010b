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


# ---------------------------------------------------------------------------------------------------------
# list-directed READ over records (Fortran 2008 §10.10.3).  Expected values are gfortran 12's, from
# ``double precision a(4); a = -7; read(10,*) a`` on each record (oracle run, numbers kept here as data).

from spctool.formats.fortran import Records, list_read, parse_real, read_internal  # noqa: E402

NAN = float("nan")
GFORTRAN_LIST_READ = [
    ("1,,3,4", [1, -7, 3, 4]),  # null item leaves the value unchanged
    ("2*5 2*", [5, 5, -7, -7]),  # r*c repeat, r* null repeat
    ("1 2 / 9", [1, 2, -7, -7]),  # slash ends the READ
    ("1.5-06 NaN inf 4", [1.5e-6, NAN, float("inf"), 4]),
    ("1e-400 2 3 4", [0, 2, 3, 4]),  # underflow reads as 0
    ("\t1\t2,\t3 , 4  ", [1, 2, 3, 4]),  # tabs, commas with blanks, trailing blanks
    (",2,3,4", [-7, 2, 3, 4]),  # a leading comma is a null item
    ("1 2 3 4 :garbage", [1, 2, 3, 4]),  # text after the list is never read
    ("1 2 3 4*", [1, 2, 3, -7]),
    ("3*1.0 .5E1", [1, 1, 1, 5]),
    ("+.5 -.5e-1 1. -0", [0.5, -0.05, 1, -0.0]),
    ("1.5q2 2d0 3D+00 4e0", [150, 2, 3, 4]),
]


@pytest.mark.parametrize("record, expected", GFORTRAN_LIST_READ)
def test_list_read_matches_gfortran(record, expected):
    got = list_read([record], 0, "rrrr", [-7.0] * 4).values
    assert len(got) == 4
    for g, e in zip(got, expected):
        if math.isnan(e):
            assert math.isnan(g)
        else:
            assert g == e and math.copysign(1, g) == math.copysign(1, e)


@pytest.mark.parametrize(
    "record, item",
    [("1 2 3 4abc", 4), ("1.5q2 1d 3 4", 2), ("-0.9150303,:Ba758D+00 1 1 1", 2), ("1D+400 2 3 4", 1)],
)
def test_list_read_rejects_bad_items(record, item):
    # gfortran: "Bad real number in item N of list input"; 1D+400 gfortran reads as Infinity, spctool refuses
    with pytest.raises(SpcFormatError, match=f"value {item} "):
        list_read([record], 0, "rrrr", path="X.SUM")


def test_list_read_continues_across_records_and_skips_blank_ones():
    recs = ["", "1", "   ", "2 3", "4 5 6", "7"]
    r = list_read(recs, 0, "rrrr")
    assert r.values == [1, 2, 3, 4] and r.first == 0 and r.last == 4 and r.lines == [2, 4, 4, 5]
    # the next READ starts on the next record: the 5 6 after the list are discarded
    rr = Records(recs)
    rr.read_list("rrrr")
    assert rr.read_list("r").values == [7]


def test_list_read_end_of_file_names_the_file():
    with pytest.raises(SpcFormatError, match=r"F\.TXT:2: expected 3 numbers, found 2"):
        list_read(["1", "2"], 0, "rrr", path="F.TXT", what="numbers")


def test_list_read_kinds():
    r = list_read(["'HOLD########' 'OWEN' 6 .true. f"], 0, "aailL".lower())
    assert r.values == ["HOLD########", "OWEN", 6, True, False]
    with pytest.raises(SpcFormatError, match="not a Fortran integer"):
        list_read(["1.5"], 0, "i")
    assert read_internal(" 'it''s' 3", "ai").values == ["it's", 3]
    with pytest.raises(SpcFormatError, match="end of the record"):
        read_internal("1 2", "rrr")


def test_parse_real_specials_and_overflow():
    assert math.isnan(parse_real("NaN")) and parse_real("-Infinity") == float("-inf")
    with pytest.raises(ValueError):
        parse_real("1D+400")
    with pytest.raises(ValueError):
        parse_number("0.1+401")


_fmt = st.sampled_from(["D", "E", "d", "e", "", "Q"])


@st.composite
def _written(draw):
    values = draw(
        st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64), min_size=1, max_size=12)
    )
    toks = []
    for v in values:
        letter = draw(_fmt)
        if letter == "":  # letterless exponent: mantissa then a signed exponent
            m, e = f"{v:.17e}".split("e")
            toks.append(f"{m}{int(e):+03d}")
        else:
            toks.append(f"{v:.17e}".replace("e", letter))
    seps = [draw(st.sampled_from([" ", "  ", ",", " , ", "\t", "\n", "\n\n", ", \n"])) for _ in toks]
    text = "".join(t + s for t, s in zip(toks, seps))
    if draw(st.booleans()):
        text = text.replace("\n", "\r\n")
    return values, text


@settings(max_examples=200, deadline=None)
@given(_written())
def test_list_read_round_trip(case):
    values, text = case
    lines = text.replace("\r\n", "\n").split("\n")
    r = list_read(lines, 0, "r" * len(values))
    assert r.values == values


@st.composite
def _encoded(draw):
    """Items as runs: ('v', x, r) -> r values x (written r*x or x), ('n', r) -> r nulls (r* or commas)."""
    runs = draw(
        st.lists(
            st.one_of(
                st.tuples(st.just("v"), st.floats(-1e6, 1e6, allow_nan=False), st.integers(1, 4)),
                st.tuples(st.just("n"), st.just(0.0), st.integers(1, 3)),
            ),
            min_size=1,
            max_size=8,
        )
    )
    expected, parts = [], []
    for kind, x, r in runs:
        if kind == "v":
            expected += [x] * r
            parts.append(f"{r}*{x!r}" if r > 1 or draw(st.booleans()) else repr(x))
        else:
            expected += [None] * r
            parts.append(f"{r}*")
    return runs, expected, parts


@settings(max_examples=200, deadline=None)
@given(_encoded(), st.integers(0, 3))
def test_list_read_repeats_and_nulls_model(case, tail_nulls):
    # Fortran 2008 §10.10.3.2: r*c is r copies of c, r* is r null values; a null leaves the item unchanged
    runs, expected, parts = case
    n = len(expected) + tail_nulls  # items after the list are left by a '/'
    defaults = [-7.0] * n
    text = ", ".join(parts) + " /"
    got = list_read([text], 0, "r" * n, defaults).values
    want = [-7.0 if e is None else e for e in expected] + [-7.0] * tail_nulls
    assert got == want
