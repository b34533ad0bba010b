"""SUM and NOM files (spc-formats.md §2, §3, §0.3): real data, canonical examples, byte-exact rewrites."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from spctool.errors import SpcFormatError, SpcUsageError
from spctool.formats.fortran import format_d, format_f, parse_number
from spctool.formats.landmark import read_lmk
from spctool.formats.nominal import Nominal, format_nom, parse_nom, read_nom, write_nom
from spctool.formats.sumfile import (
    LimbFit,
    Picture,
    SumLandmark,
    format_sum,
    parse_sum,
    read_sum,
    write_sum,
)

REAL = Path(__file__).resolve().parent.parent / "fixtures" / "real"
ROSETTA = REAL / "rosetta-67p" / "W48230079013.SUM"
ITOKAWA = REAL / "hayabusa-itokawa" / "N2395699394.SUM"

CANONICAL_SUM = """\
X123456789A1
2021 MAR 04 12:34:56.789
  1024  1024   100  4095                                       NPX, NLN, THRSH
    0.5000000000D+02    0.5125000000D+03    0.5125000000D+03   MMFL, CTR
   -0.1000000000D+02    0.0000000000D+00    0.0000000000D+00   SCOBJ
    0.0000000000D+00    0.1000000000D+01    0.0000000000D+00   CX
    0.0000000000D+00    0.0000000000D+00   -0.1000000000D+01   CY
   -0.1000000000D+01    0.0000000000D+00    0.0000000000D+00   CZ
    0.8000000000D+00    0.6000000000D+00    0.0000000000D+00   SZ
 100.00000   0.00000   0.00000   0.00000 100.00000   0.00000   K-MATRIX
    0.00000D+00    0.00000D+00    0.00000D+00    0.00000D+00   DISTORTION
    0.1000000000D-01    0.1000000000D-01    0.1000000000D-01   SIGMA_VSO
    0.1000000000D-03    0.1000000000D-03    0.1000000000D-03   SIGMA_PTG
LANDMARKS
AB0001    565.13    407.24
AB0002    601.77    388.02
LIMB FITS
END FILE
"""

CANONICAL_NOM = """\
X123456789A1
    0.0000000000D+00    0.1000000000D+01    0.0000000000D+00   BOD_FRAME
   -0.1000000000D+02    0.0000000000D+00    0.0000000000D+00   SCOBJ
    0.1000000000D+01    0.1000000000D+01    0.1000000000D+01   SIGMA_VSO
    0.0000000000D+00    0.1000000000D+01    0.0000000000D+00   CX
    0.0000000000D+00    0.0000000000D+00   -0.1000000000D+01   CY
   -0.1000000000D+01    0.0000000000D+00    0.0000000000D+00   CZ
    0.1000000000D-02    0.1000000000D-02    0.1000000000D-02   SIGMA_PTG
END FILE
"""


def project(pic: Picture, v) -> tuple[float, float]:
    """spc-formats.md §2.5 steps 1-5 written out independently (no distortion)."""
    u = pic.scobj + np.asarray(v, float)
    z = np.array([pic.cx @ u, pic.cy @ u, pic.cz @ u])
    x, y = pic.mmfl * z[0] / z[2], pic.mmfl * z[1] / z[2]
    k = pic.kmatrix
    return (
        pic.ctr[0] + k[0, 0] * x + k[0, 1] * y + k[0, 2] * x * y,
        pic.ctr[1] + k[1, 0] * x + k[1, 1] * y + k[1, 2] * x * y,
    )


# ------------------------------------------------------------------------------------------------------------
# real Rosetta file


def test_rosetta_values():
    pic = read_sum(ROSETTA)
    assert pic.name == "W48230079013"
    assert pic.utc == "2015 APR 14 16:26:27.974"
    assert (pic.npx, pic.nln) == (1024, 1024)
    np.testing.assert_array_equal(pic.thrsh, [500, 65535])
    assert pic.mmfl == 135.68
    np.testing.assert_array_equal(pic.ctr, [511.7, 510.6])
    np.testing.assert_array_equal(pic.kmatrix, [[37.0371, 0.1240, 0], [-0.1240, 37.0371, 0]])
    np.testing.assert_array_equal(pic.distortion, np.zeros(4))
    assert np.linalg.norm(pic.scobj) == pytest.approx(170.69, abs=0.01)
    np.testing.assert_array_equal(pic.scobj, [-0.1430589240e03, -0.3893115914e02, 0.8458863431e02])
    assert np.all((pic.sigma_vso > 0.036) & (pic.sigma_vso < 0.040))
    np.testing.assert_allclose(pic.sigma_ptg, [2.2e-4, 2.2e-4, 5.5e-4], rtol=0.02)
    assert pic.landmarks == [
        SumLandmark("FA0115", 533.53, 475.22),
        SumLandmark("FC0098", 513.55, 501.38),
        SumLandmark("GD0036", 493.55, 498.21),
    ]
    assert pic.limb_fits == []
    assert not pic.is_linescan
    np.testing.assert_array_equal(pic.rotation, np.vstack([pic.cx, pic.cy, pic.cz]))
    # CX, CY, CZ rows form a rotation
    np.testing.assert_allclose(pic.rotation @ pic.rotation.T, np.eye(3), atol=1e-8)
    assert np.linalg.det(pic.rotation) == pytest.approx(1.0, abs=1e-8)


def test_rosetta_projection_matches_verified_facts():
    """README verified facts: LMK VLMs through the SUM pose land (+0.83,+1.11), (+0.04,+0.45), (-0.79,+0.17)
    px from the measured pixels -- fails by tens of pixels on any sign or transpose error."""
    pic = read_sum(ROSETTA)
    expected = {"FA0115": (0.83, 1.11), "FC0098": (0.04, 0.45), "GD0036": (-0.79, 0.17)}
    measured = {lm.name: (lm.sample, lm.line) for lm in pic.landmarks}
    for name, (ds, dl) in expected.items():
        lmk = read_lmk(REAL / "rosetta-67p" / f"{name}.LMK")
        s, l = project(pic, lmk.vlm)
        assert s - measured[name][0] == pytest.approx(ds, abs=0.01)
        assert l - measured[name][1] == pytest.approx(dl, abs=0.01)


def test_rosetta_rewrite_byte_identical(tmp_path):
    pic = read_sum(ROSETTA)
    out = tmp_path / "W48230079013.SUM"
    write_sum(out, pic)
    assert out.read_bytes() == ROSETTA.read_bytes()
    # a deep copy still knows its original text
    assert format_sum(copy.deepcopy(pic)).encode() == ROSETTA.read_bytes()


def test_rosetta_changing_scobj_regenerates_only_that_line():
    text = ROSETTA.read_text()
    pic = parse_sum(text)
    pic.scobj = np.array([-10.0, 0.0, 0.0])
    new = format_sum(pic).split("\n")
    old = text.split("\n")
    diff = [i for i, (a, b) in enumerate(zip(old, new)) if a != b]
    assert diff == [4] and len(new) == len(old)
    assert new[4] == "   -0.1000000000D+02    0.0000000000D+00    0.0000000000D+00   SCOBJ"
    assert new[4].index("SCOBJ") == 63  # column 64
    # in-place mutation is detected too
    pic = parse_sum(text)
    pic.cz[2] = 0.5
    new = format_sum(pic).split("\n")
    assert [i for i, (a, b) in enumerate(zip(old, new)) if a != b] == [7]
    assert parse_sum(format_sum(pic)).cz[2] == 0.5


def test_rosetta_landmark_block_update():
    text = ROSETTA.read_text()
    pic = parse_sum(text)
    del pic.landmarks[1]
    pic.landmarks.append(SumLandmark("AB0001", -12.5, 1033.25, "*"))
    pic.limb_fits.append(LimbFit("FA0115", 1.0, 2.0, 0.05))
    out = format_sum(pic)
    lines = out.split("\n")
    i = lines.index("LANDMARKS")
    assert lines[i : i + 6] == [
        "LANDMARKS",
        "FA0115    533.53    475.22",
        "GD0036    493.55    498.21",
        "AB0001    -12.50   1033.25 *",
        "LIMB FITS",
        "FA0115      1.00      2.00      0.05",
    ]
    again = parse_sum(out)
    assert again.landmarks == pic.landmarks and again.limb_fits == pic.limb_fits


# ------------------------------------------------------------------------------------------------------------
# real Hayabusa file


def test_itokawa_values_and_rewrite(tmp_path):
    raw = ITOKAWA.read_bytes()
    text = raw.decode("latin-1")
    assert all(len(ln) == 80 for ln in text.split("\n")[:-1])
    pic = read_sum(ITOKAWA)
    assert pic.name == "N2395699394"
    assert pic.utc == "2005 SEP 21 10:44:07.352"
    np.testing.assert_array_equal(pic.thrsh, [10, 255])
    assert pic.mmfl == 120.4711641
    np.testing.assert_array_equal(pic.ctr, [512.5, 512.5])
    np.testing.assert_array_equal(pic.kmatrix, [[83.33333, 0, 0], [0, 83.33333, 0]])
    np.testing.assert_array_equal(pic.distortion, np.zeros(4))
    assert np.linalg.norm(pic.scobj) == pytest.approx(18.45, abs=0.01)
    assert len(pic.landmarks) == 14 and len(pic.limb_fits) == 68
    assert pic.landmarks[0] == SumLandmark("DN0001", 534.39, 458.93)
    assert pic.limb_fits[0] == LimbFit("BB0001", 571.13, 533.56, 0.03)
    values = np.array([lf.value for lf in pic.limb_fits])
    # the README says "0.01-0.08"; the file itself holds 65 values in 0.01-0.08 plus 0.09, 0.11 and 0.18
    assert values.min() == 0.01 and values.max() == 0.18
    assert np.count_nonzero(values <= 0.08) == 65 and sorted(values[values > 0.08]) == [0.09, 0.11, 0.18]
    np.testing.assert_array_equal(pic.sz, [0.8318773078, -0.5541012100, 0.3085439849e-01])
    out = tmp_path / "N2395699394.SUM"
    write_sum(out, pic)
    assert out.read_bytes() == raw


def test_itokawa_regenerated_lines_keep_letter_and_padding():
    text = ITOKAWA.read_text()
    old = text.split("\n")
    pic = parse_sum(text)
    pic.sz = np.array([0.6, -0.8, 0.0])  # an E-style line
    pic.scobj = pic.scobj * 2  # a D-style line
    pic.ctr = np.array([512.0, 511.0])  # E-style MMFL/CTR line
    new = format_sum(pic).split("\n")
    diff = [i for i, (a, b) in enumerate(zip(old, new)) if a != b]
    assert diff == [3, 4, 8]
    assert new[8] == ("    0.6000000000E+00   -0.8000000000E+00    0.0000000000E+00   SZ").ljust(80)
    assert new[3] == ("    0.1204711641E+03    0.5120000000E+03    0.5110000000E+03   MMFL, CTR").ljust(80)
    assert "D+02" in new[4] and len(new[4]) == 80 and new[4].index("SCOBJ") == 63
    # added rows follow the file's padded style
    pic.landmarks.append(SumLandmark("ZZ0001", 1.0, 2.0))
    lines = format_sum(pic).split("\n")
    assert lines[lines.index("LIMB FITS".ljust(80)) - 1] == "ZZ0001      1.00      2.00".ljust(80)


# ------------------------------------------------------------------------------------------------------------
# canonical layout (§2.6)


def canonical_picture(**changes) -> Picture:
    fields = dict(
        name="X123456789A1",
        utc="2021 MAR 04 12:34:56.789",
        npx=1024,
        nln=1024,
        thrsh=[100, 4095],
        mmfl=50.0,
        ctr=[512.5, 512.5],
        scobj=[-10.0, 0, 0],
        cx=[0, 1.0, 0],
        cy=[0, 0, -1.0],
        cz=[-1.0, 0, 0],
        sz=[0.8, 0.6, 0],
        kmatrix=[[100, 0, 0], [0, 100, 0]],
        distortion=np.zeros(4),
        sigma_vso=[0.01] * 3,
        sigma_ptg=[1e-4] * 3,
        landmarks=[SumLandmark("AB0001", 565.13, 407.24), SumLandmark("AB0002", 601.77, 388.02)],
    )
    fields.update(changes)
    return Picture(**fields)


def test_canonical_example_written_byte_for_byte():
    assert format_sum(canonical_picture()) == CANONICAL_SUM


def test_canonical_example_parses_and_projects():
    pic = parse_sum(CANONICAL_SUM)
    assert pic == canonical_picture()
    # self-consistency stated in §2.6: AB0001 at (0.5, 0.1, 0.2) km projects to (565.13, 407.24)
    s, l = project(pic, [0.5, 0.1, 0.2])
    assert (round(s, 2), round(l, 2)) == (565.13, 407.24)
    assert format_sum(pic) == CANONICAL_SUM


def test_dataclass_replace_and_equality():
    pic = parse_sum(CANONICAL_SUM)
    other = dataclasses.replace(pic, mmfl=51.0)
    assert other != pic and other.mmfl == 51.0
    assert (
        format_sum(other).split("\n")[3]
        == "    0.5100000000D+02    0.5125000000D+03    0.5125000000D+03   MMFL, CTR"
    )


# ------------------------------------------------------------------------------------------------------------
# layout variants


def rosetta_lines() -> list[str]:
    return ROSETTA.read_text().split("\n")


def test_missing_distortion_line_and_insertion():
    lines = rosetta_lines()
    del lines[10]
    text = "\n".join(lines)
    pic = parse_sum(text)
    assert pic.distortion is None
    assert pic.sigma_vso[0] == 0.3907025850e-01 and pic.sigma_ptg[2] == 0.5515340338e-03
    assert format_sum(pic) == text
    pic.distortion = np.array([0.0, 1e-5, 0, 0])
    new = format_sum(pic).split("\n")
    assert new[10] == "    0.00000D+00    0.10000D-04    0.00000D+00    0.00000D+00   DISTORTION"
    assert new[11:] == lines[10:]
    # and removing it again drops the line
    full = parse_sum(ROSETTA.read_text())
    full.distortion = None
    assert format_sum(full) == text


def test_tags_at_column_63_and_foreign_tags():
    lines = rosetta_lines()
    for i in (2, 3, 8, 9, 10, 11, 12):
        lines[i] = lines[i].replace("   ", "  ", 1) if i == 2 else lines[i][:60] + "  " + lines[i][63:]
    lines[11] = lines[11].replace("SIGMA_VSO", "SIG_VSO")
    lines[12] = lines[12].replace("SIGMA_PTG", "SIG_PTG")
    text = "\n".join(lines)
    pic = parse_sum(text)
    ref = read_sum(ROSETTA)
    # globalStat: IF(LINE(64:73).EQ.'DISTORTION') -- a tag at column 63 is not seen, D = 0 (no D line)
    assert pic.distortion is None
    assert any("columns 64-73" in w for _, w in pic._source.warnings)
    ref.distortion = None
    assert pic == ref
    assert format_sum(pic) == text
    pic.sigma_vso = np.array([1.0, 2.0, 3.0])
    assert format_sum(pic).split("\n")[11].endswith("   SIG_VSO")


def test_untagged_sigma_lines_and_sigpxl_preserved():
    lines = rosetta_lines()
    untagged = lines[:10] + [lines[11][:60], lines[12][:60]] + lines[13:]
    pic = parse_sum("\n".join(untagged))
    assert pic.distortion is None and pic.sigma_vso[1] == 0.3696649938e-01
    sig = lines[:11] + ["    0.1000000000D+01                                           SIGPXL"] + lines[11:]
    text = "\n".join(sig)
    pic = parse_sum(text)
    assert pic == read_sum(ROSETTA)
    assert format_sum(pic) == text


def test_flags_duplicates_and_blank_flag():
    lines = rosetta_lines()
    i = lines.index("LANDMARKS")
    lines[i + 1] = "FA0115    533.53    475.22 *"
    lines[i + 2] = "FA0115    533.53    475.22  "  # (…,1X,A1) with a blank flag: two trailing blanks
    lines.insert(i + 3, "FA0115    533.53    475.22  ")  # duplicate row
    text = "\n".join(lines)
    pic = parse_sum(text)
    assert [lm.flag for lm in pic.landmarks] == ["*", "", "", ""]
    assert [lm.name for lm in pic.landmarks] == ["FA0115", "FA0115", "FA0115", "GD0036"]
    assert format_sum(pic) == text


def test_linescan_trailer_preserved():
    lines = rosetta_lines()
    lines[0] = "W48230079013 L"
    end = lines.index("END FILE")
    # a complete block as xV2IMGPL reads it: U0; R0; POL_AXIS; POL; TRJ_AXIS; TRJ; KMAX; KMAX rows of CAX
    block = ["LINE SCAN DATA", " 1.0 2.0 3.0", " 0.1 0.2 0.3", " 0 0 1", " 1D-6", " 0 1 0", " 1D-5 0 0", " 2"]
    block += [" 1D-7 2D-7 3D-7", " 4D-9 5D-9 6D-9"]
    text = "\n".join(lines[:end] + block + lines[end:])
    pic = parse_sum(text)
    assert pic.is_linescan and pic.name == "W48230079013"
    assert pic.linescan.cax.tolist() == [[1e-7, 2e-7, 3e-7], [4e-9, 5e-9, 6e-9]]
    assert format_sum(pic) == text
    pic.name = "W48230079099"
    assert format_sum(pic).split("\n")[0] == "W48230079099 L"
    # also after END FILE and with no final newline
    text2 = "\n".join(lines).rstrip("\n") + "\n" + "\n".join(block)
    pic2 = parse_sum(text2)
    assert format_sum(pic2) == text2


def test_missing_sections_tolerated():
    lines = rosetta_lines()
    text = "\n".join(lines[:13] + ["END FILE", ""])
    pic = parse_sum(text)
    assert pic.landmarks == [] and pic.limb_fits == []
    assert format_sum(pic) == text
    pic.landmarks.append(SumLandmark("AB0001", 1, 2))
    assert format_sum(pic).split("\n")[13:16] == ["LANDMARKS", "AB0001      1.00      2.00", "END FILE"]


def test_crlf_input_is_read():
    pic = parse_sum(ROSETTA.read_text().replace("\n", "\r\n"))
    assert pic == read_sum(ROSETTA)


# ------------------------------------------------------------------------------------------------------------
# errors


def err(text: str, path="SUMFILES/X.SUM") -> str:
    with pytest.raises(SpcFormatError) as info:
        parse_sum(text, path)
    return str(info.value)


def test_garbage_number_names_file_and_line():
    lines = rosetta_lines()
    lines[4] = lines[4].replace("0.1430589240D+03", "0.14305X9240D+03")
    msg = err("\n".join(lines))
    assert msg.startswith("SUMFILES/X.SUM:5: expected 3 numbers (SCOBJ)")


def test_wrong_number_count():
    # SPC reads each header line with READ(10,*) (globalStat): a short line runs into its tag, which is
    # not a number; extra numbers after the list are never read (a validate warning, not an error)
    lines = rosetta_lines()
    lines[5] = "    0.5399383659D+00   -0.2193934560D+00   CX"
    assert err("\n".join(lines)).startswith("SUMFILES/X.SUM:6: expected 3 numbers (CX): value 3 'CX'")
    lines = rosetta_lines()
    lines[5] = lines[5].replace("   CX", "  0.1D+00   CX")
    pic = parse_sum("\n".join(lines))
    assert pic.cx[2] == pytest.approx(0.8126088065) and any(ln == 6 for ln, _ in pic._source.warnings)
    lines = rosetta_lines()
    lines[9] = lines[9].replace("0.0000   K-MATRIX", "K-MATRIX")
    assert err("\n".join(lines)).startswith("SUMFILES/X.SUM:10: expected 6 numbers (K-MATRIX)")
    lines = rosetta_lines()
    lines[10] = "    0.00000D+00    0.00000D+00    0.00000D+00   DISTORTION"
    # the tag now sits at column 49: LINE(64:73) is not 'DISTORTION', so SPC takes D = 0
    pic = parse_sum("\n".join(lines))
    assert pic.distortion is None and any(ln == 11 for ln, _ in pic._source.warnings)
    lines[10] = "    0.00000D+00    0.00000D+00    0.00000D+00                  DISTORTION"
    assert lines[10][63:73] == "DISTORTION"
    # READ(LINE,*) (D(I),I=1,4) then meets the tag as the 4th value
    assert err("\n".join(lines)).startswith("SUMFILES/X.SUM:11: expected 4 numbers (DISTORTION)")


def test_missing_end_file():
    lines = rosetta_lines()
    text = "\n".join(lines[:-2])  # drop END FILE and the empty tail
    assert err(text) == "SUMFILES/X.SUM:18: expected END FILE line, found end of file"


def test_truncated_files():
    lines = rosetta_lines()
    msg = err("\n".join(lines[:7]) + "\n")
    assert msg == "SUMFILES/X.SUM:7: expected CZ on line 8, found end of file"
    # cut in the middle of line 5
    msg = err("\n".join(lines[:4]) + "\n" + lines[4][:30])
    assert msg.startswith("SUMFILES/X.SUM:5: expected 3 numbers (SCOBJ), found 2")
    assert err("") == "SUMFILES/X.SUM:1: expected the picture name, found an empty file"
    # header complete but no section/END
    msg = err("\n".join(lines[:13]))
    assert msg.startswith("SUMFILES/X.SUM:13: expected LANDMARKS, LIMB FITS or END FILE")


def test_bad_header_values():
    # line 2 is skipped by READ(10,*) (globalStat): any UTC text is accepted
    lines = rosetta_lines()
    lines[1] = "  1024  1024   500 65535"
    assert parse_sum("\n".join(lines)).utc == "1024  1024   500 65535"
    # READ(10,*) NPX, NLN, T1, T2 into INTEGERs (map_coverage_p_low): 1024.5 is not an integer
    lines = rosetta_lines()
    lines[2] = "  1024.5  1024   500 65535   NPX, NLN, THRSH"
    assert "value 1 '1024.5' is not a Fortran integer" in err("\n".join(lines))
    # a header that ends after K-MATRIX is read (SPC's readers stop there); sigmas 0 with a warning
    lines = rosetta_lines()
    del lines[11:13]
    pic = parse_sum("\n".join(lines))
    assert not pic.sigma_vso.any() and any("SIGMA_VSO" in w for _, w in pic._source.warnings)


def test_bad_rows():
    lines = rosetta_lines()
    i = lines.index("LANDMARKS")
    lines[i + 2] = "FC0098    513.55    5O1.38"
    assert err("\n".join(lines)).startswith(
        f"SUMFILES/X.SUM:{i + 3}: expected 2 numbers (landmark sample, line)"
    )
    lines = rosetta_lines()
    lines[i + 1] = "FA0115    533.53    475.22 ab"
    assert err("\n".join(lines)).startswith(f"SUMFILES/X.SUM:{i + 2}: expected at most a 1-character flag")
    lines = rosetta_lines()
    j = lines.index("LIMB FITS")
    lines.insert(j + 1, "BB0001    571.13    533.56")
    # two numbers in SPC's columns (GIANT writes no third): LITHOS's (A6,3F10.2) reads the blank field as 0
    pic = parse_sum("\n".join(lines))
    assert pic.limb_fits[0]._key() == ("BB0001", 571.13, 533.56, 0.0) and not pic._source.warnings
    lines[j + 1] = "BB0001    571.13"
    assert err("\n".join(lines)).startswith(f"SUMFILES/X.SUM:{j + 2}: expected 3 numbers (limb fit), found 1")
    lines = rosetta_lines()
    lines.insert(i + 1, "LANDMARKS")
    assert err("\n".join(lines)).startswith(f"SUMFILES/X.SUM:{i + 2}: unexpected second LANDMARKS")


def test_read_missing_file_and_write_options(tmp_path):
    with pytest.raises(SpcFormatError) as info:
        read_sum(tmp_path / "NOPE.SUM")
    assert str(info.value).startswith(str(tmp_path / "NOPE.SUM"))
    out = tmp_path / "A.SUM"
    write_sum(out, canonical_picture())
    with pytest.raises(SpcUsageError):
        write_sum(out, canonical_picture(), overwrite=False)
    kept = write_sum(out, canonical_picture(mmfl=60.0), backup=True)
    assert kept is not None and kept.read_text() == CANONICAL_SUM
    assert read_sum(out).mmfl == 60.0


def test_writer_rejects_bad_values():
    with pytest.raises(ValueError):
        Picture(**{**dataclasses.asdict(canonical_picture()), "scobj": [1.0, 2.0]})
    with pytest.raises(ValueError):
        SumLandmark("AB0001", 1.0, 2.0, "**")
    pic = canonical_picture(landmarks=[SumLandmark("TOOLONG7", 1.0, 2.0)])
    with pytest.raises(ValueError):
        format_sum(pic)


# ------------------------------------------------------------------------------------------------------------
# property tests

D = st.floats(-1e7, 1e7, allow_nan=False).map(lambda v: parse_number(format_d(v)))
F2 = st.floats(-99999, 999999, allow_nan=False).map(lambda v: parse_number(format_f(v, 10, 2)))
K5 = st.floats(-999, 999, allow_nan=False).map(lambda v: parse_number(format_f(v, 10, 5)))
K4 = st.floats(-999, 999, allow_nan=False).map(lambda v: parse_number(format_f(v, 10, 4)))
D5 = st.floats(-1e3, 1e3, allow_nan=False).map(lambda v: parse_number(format_d(v, 15, 5)))
LM_NAME = st.from_regex(r"[A-Z][A-Z0-9]{0,5}", fullmatch=True)
PIC_NAME = st.from_regex(r"[A-Z][A-Z0-9_]{0,11}", fullmatch=True)
MONTHS = ["JAN", "FEB", "MAR", "APR", "MAY", "JUN", "JUL", "AUG", "SEP", "OCT", "NOV", "DEC"]
UTC = st.builds(
    lambda y, mo, d, h, mi, s, ms: f"{y:04d} {mo} {d:02d} {h:02d}:{mi:02d}:{s:02d}.{ms:03d}",
    st.integers(1990, 2100),
    st.sampled_from(MONTHS),
    st.integers(1, 28),
    st.integers(0, 23),
    st.integers(0, 59),
    st.integers(0, 59),
    st.integers(0, 999),
)


def vec(elements, n):
    return st.lists(elements, min_size=n, max_size=n).map(np.array)


pictures = st.builds(
    Picture,
    name=PIC_NAME,
    utc=UTC,
    npx=st.integers(1, 10**7),
    nln=st.integers(1, 10**7),
    thrsh=vec(st.integers(-(10**7), 10**7).map(float), 2),
    mmfl=D,
    ctr=vec(D, 2),
    scobj=vec(D, 3),
    cx=vec(D, 3),
    cy=vec(D, 3),
    cz=vec(D, 3),
    sz=vec(D, 3),
    kmatrix=vec(K5, 6),
    distortion=st.none() | vec(D5, 4),
    sigma_vso=vec(D, 3),
    sigma_ptg=vec(D, 3),
    landmarks=st.lists(st.builds(SumLandmark, LM_NAME, F2, F2, st.sampled_from(["", "*", "!"])), max_size=5),
    limb_fits=st.lists(st.builds(LimbFit, LM_NAME, F2, F2, F2), max_size=5),
)


@settings(max_examples=60, deadline=None)
@given(pictures)
def test_sum_round_trip_property(pic):
    text = format_sum(pic)
    back = parse_sum(text)
    assert back == pic
    assert format_sum(back) == text
    assert all(len(ln) <= 80 for ln in text.split("\n"))


FIELD_VALUES = {
    "scobj": vec(D, 3),
    "cx": vec(D, 3),
    "sz": vec(D, 3),
    "sigma_ptg": vec(D, 3),
    "ctr": vec(D, 2),
    "kmatrix": vec(K4, 6).map(lambda a: a.reshape(2, 3)),
    "distortion": vec(D5, 4),
    "utc": UTC,
    "npx": st.integers(1, 99999),
}
LINE_OF = {
    "scobj": 4,
    "cx": 5,
    "sz": 8,
    "sigma_ptg": 12,
    "ctr": 3,
    "kmatrix": 9,
    "distortion": 10,
    "utc": 1,
    "npx": 2,
}


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.sampled_from([ROSETTA, ITOKAWA]),
    st.dictionaries(st.sampled_from(sorted(FIELD_VALUES)), st.just(None), min_size=1, max_size=4),
    st.data(),
)
def test_real_file_edit_property(path, chosen, data):
    """Edit random header fields of a real file: only those lines change, in the original style."""
    text = path.read_text()
    pic = parse_sum(text)
    for name in chosen:
        setattr(pic, name, data.draw(FIELD_VALUES[name], label=name))
    out = format_sum(pic)
    back = parse_sum(out)
    assert back == pic
    old, new = text.split("\n"), out.split("\n")
    assert len(old) == len(new)
    changed_lines = {LINE_OF[name] for name in chosen}
    for i, (a, b) in enumerate(zip(old, new)):
        if i not in changed_lines:
            assert a == b
        else:
            assert (len(b) == 80) == (len(a) == 80)
    assert format_sum(back) == out


# ------------------------------------------------------------------------------------------------------------
# NOM


def canonical_nominal(**changes) -> Nominal:
    fields = dict(
        name="X123456789A1",
        frame_vector=[0, 1.0, 0],
        frame_tag="BOD_FRAME",
        scobj=[-10.0, 0, 0],
        sigma_vso=[1.0, 1.0, 1.0],
        cx=[0, 1.0, 0],
        cy=[0, 0, -1.0],
        cz=[-1.0, 0, 0],
        sigma_ptg=[1e-3] * 3,
    )
    fields.update(changes)
    return Nominal(**fields)


def test_nom_canonical_example():
    assert format_nom(canonical_nominal()) == CANONICAL_NOM
    nom = parse_nom(CANONICAL_NOM)
    assert nom == canonical_nominal()
    assert nom.frame_tag == "BOD_FRAME"
    np.testing.assert_array_equal(nom.rotation, [[0, 1, 0], [0, 0, -1], [-1, 0, 0]])
    assert format_nom(nom) == CANONICAL_NOM


def test_nom_dynamics_and_edit(tmp_path):
    lines = CANONICAL_NOM.split("\n")
    dyn = ["DYNAMICS", "  X123456788A1   0.1D+00 0.2D+00 0.3D+00", "  X123456790A1   -0.1 -0.2 -0.3"]
    text = "\n".join(lines[:8] + dyn + lines[8:]).replace("\n", " \n").ljust(0)
    nom = parse_nom(text, "NOMINALS/X.NOM")
    assert nom.extra_lines == [d + " " for d in dyn]
    assert format_nom(nom) == text
    nom.scobj = np.array([1.0, 2.0, 3.0])
    nom.frame_tag = "dxR_FRAME"
    new = format_nom(nom).split("\n")
    assert new[1] == "    0.0000000000D+00    0.1000000000D+01    0.0000000000D+00   dxR_FRAME"
    assert new[2] == "    0.1000000000D+01    0.2000000000D+01    0.3000000000D+01   SCOBJ"
    assert new[3:] == text.split("\n")[3:]
    out = tmp_path / "X.NOM"
    write_nom(out, nom)
    assert read_nom(out) == nom


def test_nom_errors():
    lines = CANONICAL_NOM.split("\n")
    # no END FILE: LITHOS reads the 8 lines by position -- read alike, warned, rewritten without one
    short = "\n".join(lines[:-2])
    nom = parse_nom(short, "N.NOM")
    assert nom == parse_nom(CANONICAL_NOM) and [ln for ln, _ in nom._source.warnings] == [8]
    assert format_nom(nom) == short
    with pytest.raises(SpcFormatError) as info:
        parse_nom("\n".join(lines[:5]), "N.NOM")
    assert str(info.value) == "N.NOM:5: expected CY on line 6, found end of file"
    bad = list(lines)
    bad[5] = "    0.0000000000D+00    0.0000000000D+00   CY"
    with pytest.raises(SpcFormatError) as info:
        parse_nom("\n".join(bad), "N.NOM")
    assert str(info.value).startswith("N.NOM:6: expected 3 numbers (CY): value 3 'CY'")
    with pytest.raises(SpcFormatError) as info:
        parse_nom("\n".join(lines[:4]), "N.NOM")
    assert str(info.value) == "N.NOM:4: expected CX on line 5, found end of file"


noms = st.builds(
    Nominal,
    name=PIC_NAME,
    frame_vector=vec(D, 3),
    frame_tag=st.sampled_from(["BOD_FRAME", "dxR_FRAME", "Dxr_FRAME", "VELOCITY"]),
    scobj=vec(D, 3),
    sigma_vso=vec(D, 3),
    cx=vec(D, 3),
    cy=vec(D, 3),
    cz=vec(D, 3),
    sigma_ptg=vec(D, 3),
    extra_lines=st.lists(st.from_regex(r"[A-DF-Z0-9 .+-]{0,40}", fullmatch=True), max_size=3),
)


@settings(max_examples=50, deadline=None)
@given(noms)
def test_nom_round_trip_property(nom):
    text = format_nom(nom)
    back = parse_nom(text)
    assert back == nom
    assert format_nom(back) == text


def test_with_measured_landmarks_and_with_pose_touch_only_their_lines():
    from spctool.formats.sumfile import format_sum, parse_sum, with_measured_landmarks, with_pose

    text = (REAL / "rosetta-67p/W48230079013.SUM").read_text()
    pic = parse_sum(text)
    new = with_measured_landmarks(
        pic, ["FC0098", "ZZ0001", "GD0036"], [(1.5, 2.5), (3.0, 4.0), (9, 9)], [True, True, False]
    )
    out = format_sum(new).splitlines()
    old = text.splitlines()
    k = old.index("LANDMARKS")
    # FC0098 gets its new pixel, GD0036 (not ok) is left alone, ZZ0001 is appended; nothing else moves
    rows = ["FC0098      1.50      2.50", old[k + 3], "ZZ0001      3.00      4.00"]
    assert out == old[: k + 2] + rows + old[k + 4 :]
    dropped = with_measured_landmarks(pic, ["GD0036"], [(0, 0)], [False], drop_failed=True)
    assert [lm.name for lm in dropped.landmarks] == ["FA0115", "FC0098"]
    rot = pic.rotation[[1, 2, 0]]
    posed = format_sum(with_pose(pic, pic.scobj + 0.001, rot, [1e-3] * 3, [1e-4] * 3)).splitlines()
    changed = {posed[i][63:].strip() for i, (a, b) in enumerate(zip(old, posed)) if a != b}
    assert changed == {"SCOBJ", "CX", "CY", "CZ", "SIGMA_VSO", "SIGMA_PTG"}
    assert pic.landmarks[1].sample == 513.55  # the input is not modified
