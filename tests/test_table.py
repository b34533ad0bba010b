"""The landmark table that chains the stages (cli-contract.md)."""

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spctool.errors import SpcFormatError
from spctool.formats.table import LandmarkTable, read_table

names = st.text(alphabet="ABCDEFGHJKLMNPQRSTUVWXYZ0123456789", min_size=6, max_size=6)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(
            names,
            st.floats(-1e4, 1e4),
            st.floats(-1e4, 1e4),
            st.integers(0, 50),
            st.sampled_from(["ok", "outside", "edge-peak"]),
        ),
        min_size=1,
        max_size=12,
        unique_by=lambda r: r[0],  # one row per landmark (a name twice is refused when read)
    )
)
def test_text_and_json_round_trip(rows):
    t = LandmarkTable.from_rows(
        [{"name": n, "sample": s, "line": ln, "iterations": k, "status": st_} for n, s, ln, k, st_ in rows],
        picture="P0001",
        command="register P0001",
    )
    back = LandmarkTable.parse_text(t.to_text())
    assert back.picture == "P0001" and back.command == "register P0001"
    assert back.names == [r[0] for r in rows]
    np.testing.assert_allclose(back["sample"], [r[1] for r in rows], atol=5e-5)
    assert list(back["iterations"]) == [r[3] for r in rows]
    assert back["status"] == [r[4] for r in rows]
    j = LandmarkTable.from_json(t.to_json())
    np.testing.assert_array_equal(j["sample"], t["sample"])


def test_nan_is_null_in_json_and_nan_in_text():
    t = LandmarkTable.from_rows([{"name": "AB0001", "sample": math.nan, "line": 1.0, "status": "not-found"}])
    doc = json.loads(t.to_json())
    assert doc["landmarks"][0]["sample"] is None
    assert "nan" in t.to_text()
    assert math.isnan(LandmarkTable.parse_text(t.to_text())["sample"][0])


def test_json_has_contract_keys_and_meta():
    t = LandmarkTable.from_rows(
        [{"name": "AB0001", "sample": 1.0, "line": 2.0}],
        picture="P",
        command="c",
        meta={"pose": {"position": np.array([1.0, 2.0, 3.0])}},
    )
    doc = json.loads(t.to_json())
    assert set(doc) >= {"command", "picture", "spctool_version", "landmarks", "pose"}
    assert doc["pose"]["position"] == [1.0, 2.0, 3.0]


def test_bad_tables_name_the_line(tmp_path):
    p = tmp_path / "t.txt"
    p.write_text("# spctool 0.1\nname sample line\nAB0001 1.0\n")
    with pytest.raises(SpcFormatError, match=r"t.txt:3: expected 3 columns"):
        read_table(p)
    p.write_text("sample line\n1 2\n")
    with pytest.raises(SpcFormatError, match="'name'"):
        read_table(p)
    with pytest.raises(SpcFormatError, match="not found"):
        read_table(tmp_path / "missing.txt")


def test_select_and_set_column():
    t = LandmarkTable.from_rows([{"name": f"AB000{i}", "sample": float(i)} for i in range(4)])
    t["status"] = ["ok", "x", "ok", "x"]
    s = t.select(np.array(t["status"]) == "ok")
    assert s.names == ["AB0000", "AB0002"]
    with pytest.raises(ValueError):
        t["bad"] = [1, 2]


def test_tiny_negative_values_print_without_sign():
    t = LandmarkTable.from_rows([{"name": "AB0001", "residual_sample_after": -1e-9, "x": -1e-30}])
    row = t.to_text().splitlines()[-1].split()
    assert row[1] == "0.0000" and row[2] == "-1e-30"


# ------------------------------------------------------------------------------------------------
# CSV tables and missing columns (issue 16 gap 6)


def test_csv_table_is_read_like_the_aligned_text():
    text = (
        "# picture: P1\nName, Sample, Line, status\n"
        'B01980, 449.43, 435.58, ok\n"B02176",343.5,475.5,not-found\n'
    )
    t = LandmarkTable.parse_text(text, "t.csv")
    assert (
        t.picture == "P1"
        and t.names == ["B01980", "B02176"]
        and list(t.columns)
        == [
            "name",
            "sample",
            "line",
            "status",
        ]
    )
    np.testing.assert_array_equal(t["sample"], [449.43, 343.5])
    assert t["status"] == ["ok", "not-found"]
    same = LandmarkTable.parse_text(
        "name sample line status\nB01980 449.43 435.58 ok\nB02176 343.5 475.5 not-found\n"
    )
    assert same.rows() == t.rows()


def test_csv_empty_field_and_sample_without_line_name_the_problem():
    with pytest.raises(SpcFormatError, match=r"t.csv:2: expected a value in every comma-separated field"):
        LandmarkTable.parse_text("name,sample,line\nB1,,3\n", "t.csv")
    t = LandmarkTable.parse_text("name sample\nB1 3.5\n", "s.txt")
    with pytest.raises(SpcFormatError, match=r"s.txt: expected a 'line' column beside 'sample'"):
        t.pixel_columns("s.txt")
    assert LandmarkTable.parse_text("name\nB1\n").pixel_columns() is None


def test_duplicate_landmark_rows_are_refused_naming_both_lines_or_rows(tmp_path):
    # issue #41: the last of two rows of one landmark used to win silently
    text = "# picture: P1\nname sample line\nAB0001 1.0 2.0\nAB0002 3.0 4.0\n\nAB0001 5.0 6.0\n"
    expected = r"T\.txt:6: expected one row per landmark: 'AB0001' is on lines 3 and 6"
    with pytest.raises(SpcFormatError, match=expected):
        LandmarkTable.parse_text(text, "T.txt")
    doc = {"landmarks": [{"name": n, "sample": k} for k, n in enumerate(["A1", "B2", "A1"])]}
    with pytest.raises(SpcFormatError, match="'A1' is on rows 1 and 3"):
        LandmarkTable.from_json(json.dumps(doc), "T.json")


def test_json_integer_beyond_float_range_is_read_as_infinite(tmp_path):
    # issue #41: an integer above ~1e308 beside floats was an internal OverflowError
    big = "1" + "0" * 400
    path = tmp_path / "big.json"
    path.write_text('{"landmarks": [{"name": "A", "sample": 1.5}, {"name": "B", "sample": -' + big + "}]}")
    t = read_table(path)
    assert t["sample"][0] == 1.5 and t["sample"][1] == -math.inf


def test_stdin_table_has_a_size_limit(monkeypatch):
    import io

    from spctool.formats import guard

    monkeypatch.setattr(guard, "MAX_STDIN_BYTES", 1000)
    stream = io.BytesIO(b"name sample line\n" + b"AB0001 1.0 2.0\n" * 200)
    monkeypatch.setattr("sys.stdin", io.TextIOWrapper(stream))
    with pytest.raises(SpcFormatError, match="<stdin>: expected a landmark table on standard input of at"):
        read_table("-")
    assert stream.tell() == 1001  # stopped one byte past the limit, not at the end of the stream
