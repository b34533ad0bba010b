"""PICTLIST / LMRKLIST / LMRKLISTX (spc-formats.md §7.1-7.3): layouts, flags, END rule, byte-exact rewrite."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool.errors import SpcFormatError
from spctool.formats.fortran import format_d, parse_number
from spctool.formats.lists import (
    LandmarkList,
    LandmarkListX,
    LandmarkListXEntry,
    PictureList,
    PictureListEntry,
    format_lmrklist,
    format_lmrklistx,
    format_pictlist,
    parse_lmrklist,
    parse_lmrklistx,
    parse_pictlist,
    read_lmrklist,
    read_lmrklistx,
    read_pictlist,
    write_lmrklist,
    write_lmrklistx,
    write_pictlist,
)

PICTLIST = """\
 X123456789A1
!X123456799A1
 X123456810A1
END
"""

LMRKLIST = """\
AB0001
# a comment
XB0002
AB0003
END
"""

LMRKLISTX = """\
AB0001 49 212 0.500000D+00 0.100000D+00 0.200000D+00 0.500000D-03
AB0002   99   3   -1.25  2.5E-01  0.0   1.0D-03
END
"""


def err(parse, text: str, path="LIST.TXT") -> str:
    with pytest.raises(SpcFormatError) as info:
        parse(text, path)
    return str(info.value)


# ------------------------------------------------------------------------------------------------------------
# PICTLIST


def test_pictlist_example(tmp_path):
    plist = parse_pictlist(PICTLIST)
    assert plist.entries == [
        PictureListEntry("X123456789A1"),
        PictureListEntry("X123456799A1", "!"),
        PictureListEntry("X123456810A1"),
    ]
    assert plist.active_names == ["X123456789A1", "X123456810A1"]
    assert format_pictlist(plist) == PICTLIST
    write_pictlist(tmp_path / "PICTLIST.TXT", plist)
    assert read_pictlist(tmp_path / "PICTLIST.TXT") == plist
    assert (tmp_path / "PICTLIST.TXT").read_text() == PICTLIST


def test_pictlist_layout_details():
    text = " N2395699394\n#X123456789A1 skipped for now\n\n X123456810A1trailing\nEND\nafter\n"
    plist = parse_pictlist(text)
    assert [(e.name, e.flag) for e in plist.entries] == [
        ("N2395699394", ""),  # 11-character name
        ("X123456789A1", "#"),
        ("X123456810A1", ""),  # only columns 2-13 are the name
    ]
    assert plist.active_names == ["N2395699394", "X123456810A1"]
    assert format_pictlist(plist) == text


def test_pictlist_tuck_changes_only_that_line():
    plist = parse_pictlist(PICTLIST)
    plist.entries[0].flag = "!"
    plist.entries[1].flag = ""
    plist.entries.append(PictureListEntry("N2395699394"))
    assert format_pictlist(plist) == "!X123456789A1\n X123456799A1\n X123456810A1\n N2395699394\nEND\n"
    assert format_pictlist(PictureList([PictureListEntry("A1_05", "#")])) == "#A1_05\nEND\n"


def test_pictlist_errors():
    assert (
        err(parse_pictlist, " X123456789A1\n X123456799A1\n")
        == "LIST.TXT:2: expected END line, found end of file"
    )
    # globalStat reads (a13): a column-1 flag other than blank/!/# means "in use", name = columns 2-13
    # (the leading blank was lost: SPC reads '123456799A1'); a warning names the line
    text = " X123456789A1\nX123456799A1\nEND\n"
    plist = parse_pictlist(text)
    assert plist.active_names == ["X123456789A1", "123456799A1"]
    assert plist._source.warnings[0][0] == 2
    assert format_pictlist(plist) == text
    # the end test is columns 1-3 = END: 'END OF LIST' and 'ENDX' end a list too
    assert parse_pictlist(" A\nEND OF LIST\n B\n").names == ["A"]
    assert parse_lmrklist("AB0001\nENDX\nCD0002\n").names == ["AB0001"]
    assert err(parse_pictlist, "!\nEND\n") == "LIST.TXT:1: expected a picture name in columns 2-13"
    assert err(parse_pictlist, "") == "LIST.TXT:1: expected END line, found an empty file"
    with pytest.raises(ValueError):
        PictureListEntry("X", "?")
    with pytest.raises(ValueError):
        format_pictlist(PictureList([PictureListEntry("X123456789A12")]))


# ------------------------------------------------------------------------------------------------------------
# LMRKLIST


def test_lmrklist_example(tmp_path):
    llist = parse_lmrklist(LMRKLIST)
    assert llist.names == ["AB0001", "XB0002", "AB0003"]
    assert llist.active_names == ["AB0001", "AB0003"]
    assert llist.comments == ["# a comment"]
    assert format_lmrklist(llist) == LMRKLIST
    write_lmrklist(tmp_path / "LMRKLIST.TXT", llist)
    assert (tmp_path / "LMRKLIST.TXT").read_text() == LMRKLIST
    assert read_lmrklist(tmp_path / "LMRKLIST.TXT").names == llist.names


def test_lmrklist_edit_and_new():
    llist = parse_lmrklist(LMRKLIST)
    llist.names.remove("XB0002")
    llist.names.append("EN0001")  # 'EN' region code is not the END line
    assert format_lmrklist(llist) == "AB0001\n# a comment\nAB0003\nEN0001\nEND\n"
    assert parse_lmrklist("EN0001\nEND   \n").names == ["EN0001"]
    assert format_lmrklist(LandmarkList(["AB0001"])) == "AB0001\nEND\n"


def test_lmrklist_errors():
    assert err(parse_lmrklist, "AB0001\nAB0002") == "LIST.TXT:2: expected END line, found end of file"
    assert (
        err(parse_lmrklist, "AB0001\n      x\nEND\n") == "LIST.TXT:2: expected a landmark name in columns 1-6"
    )
    with pytest.raises(ValueError):
        format_lmrklist(LandmarkList(["TOOLONG"]))


# ------------------------------------------------------------------------------------------------------------
# LMRKLISTX


def test_lmrklistx_example(tmp_path):
    xlist = parse_lmrklistx(LMRKLISTX)
    assert len(xlist) == 2 and xlist.names == ["AB0001", "AB0002"]
    a, b = xlist
    assert (a.name, a.qsz, a.npictures, a.scale) == ("AB0001", 49, 212, 0.0005)
    np.testing.assert_array_equal(a.vlm, [0.5, 0.1, 0.2])
    assert (b.qsz, b.npictures, b.scale) == (99, 3, 0.001)
    np.testing.assert_array_equal(xlist[1].vlm, [-1.25, 0.25, 0.0])
    assert format_lmrklistx(xlist) == LMRKLISTX
    write_lmrklistx(tmp_path / "LMRKLISTX.TXT", xlist)
    assert (tmp_path / "LMRKLISTX.TXT").read_text() == LMRKLISTX
    assert list(read_lmrklistx(tmp_path / "LMRKLISTX.TXT")) == list(xlist)


def test_lmrklistx_new_entries_in_wiki_layout():
    xlist = LandmarkListX([LandmarkListXEntry("AB0001", 49, 212, [0.5, 0.1, 0.2], 0.0005)])
    assert (
        format_lmrklistx(xlist) == "AB0001 49 212 0.500000D+00 0.100000D+00 0.200000D+00 0.500000D-03\nEND\n"
    )
    parsed = parse_lmrklistx(LMRKLISTX)
    parsed.entries[1].npictures = 4
    lines = format_lmrklistx(parsed).split("\n")
    assert lines[0] == LMRKLISTX.split("\n")[0]
    assert lines[1] == "AB0002 99 4 -0.125000D+01 0.250000D+00 0.000000D+00 0.100000D-02"


def test_lmrklistx_errors():
    assert err(parse_lmrklistx, "AB0001 49 212 0.5 0.1 0.2\nEND\n").startswith(
        "LIST.TXT:1: expected 6 numbers (QSZ, pictures, VLM(3), SCALE), found 5"
    )
    assert err(parse_lmrklistx, "AB0001 49.5 212 0.5 0.1 0.2 0.1\nEND\n").startswith(
        "LIST.TXT:1: expected 6 numbers (QSZ, pictures, VLM(3), SCALE): value 1 '49.5' is not a Fortran "
        "integer"
    )
    assert (
        err(parse_lmrklistx, "AB0001 49 212 0.5 0.1 0.2 0.1\n")
        == "LIST.TXT:1: expected END line, found end of file"
    )
    assert err(parse_lmrklistx, "AB0001 49 212 0.5 O.1 0.2 0.1\nEND\n").startswith(
        "LIST.TXT:1: expected 6 numbers (QSZ, pictures, VLM(3), SCALE): value 4 'O.1' is not a Fortran real"
    )


# ------------------------------------------------------------------------------------------------------------
# properties

PIC = st.from_regex(r"[A-Z][A-Z0-9_]{0,11}", fullmatch=True)
LMK = st.from_regex(r"[A-DF-Z][A-Z0-9]{0,5}", fullmatch=True)
D6 = st.floats(-1e6, 1e6, allow_nan=False).map(lambda v: parse_number(format_d(v, 12, 6)))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.builds(PictureListEntry, PIC, st.sampled_from(["", "!", "#"])), max_size=8))
def test_pictlist_property(entries):
    plist = PictureList(entries)
    text = format_pictlist(plist)
    back = parse_pictlist(text)
    assert back.entries == entries
    assert format_pictlist(back) == text
    assert back.active_names == [e.name for e in entries if e.flag == ""]


@settings(max_examples=60, deadline=None)
@given(st.lists(LMK, max_size=8))
def test_lmrklist_property(names):
    text = format_lmrklist(LandmarkList(names))
    back = parse_lmrklist(text)
    assert back.names == names
    assert format_lmrklist(back) == text
    assert back.active_names == [n for n in names if not n.startswith("X")]


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.builds(
            LandmarkListXEntry,
            LMK,
            st.integers(0, 10**6),
            st.integers(0, 10**6),
            st.lists(D6, min_size=3, max_size=3),
            D6,
        ),
        max_size=6,
    ),
    st.data(),
)
def test_lmrklistx_property(entries, data):
    text = format_lmrklistx(LandmarkListX(entries))
    assert all(len(line) <= 80 for line in text.split("\n"))  # bigmap reads LINE (A80)
    back = parse_lmrklistx(text)
    assert list(back) == entries
    assert format_lmrklistx(back) == text
    if entries:  # editing one entry changes only its line
        k = data.draw(st.integers(0, len(entries) - 1))
        back.entries[k].qsz += 1
        old, new = text.split("\n"), format_lmrklistx(back).split("\n")
        assert [i for i, (a, b) in enumerate(zip(old, new)) if a != b] == [k]
