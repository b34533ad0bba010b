"""SPC picture summaries (``SUMFILES/<PICNM>.SUM``); their nominals (NOM) are :mod:`spctool.formats.nominal`.

Specification: ``shared/docs/spc-formats.md`` §0 (conventions, Fortran numbers, byte-exact round trip), §2
(SUM), §8 items 9-11 (DISTORTION line, foreign writers, tag column) and §9 (checklist).

Reading follows SPC: header lines by position, read list-directed (``D``/``E``/letterless exponents, trailing
tag text); the optional DISTORTION line, the SIGMA lines and the sections are found by name (tags at column 63
and 64 both occur).  Writing is byte-exact: every parsed line keeps its original text and is regenerated
(LITHOS formats, ``3D20.10`` with the tag at column 64, in the exponent letter and the 80-column padding style
of the line it replaces) only when its values differ from what was parsed.  New files use the canonical layout
of §2.6 / §3.

The row helpers it shares with the other text formats (``split_lines``, ``scan_numbers``, ``RowPool`` ...)
are :mod:`spctool.formats.rows`.
"""

from __future__ import annotations

import dataclasses
import os
import re
from dataclasses import dataclass, field

import numpy as np

from spctool.errors import SpcFormatError, SpcUsageError
from spctool.formats import atomic
from spctool.formats.fortran import (
    Records,
    parse_real,
    read_internal,
)
from spctool.formats.rows import (
    TOKEN,
    Slot,
    as_shaped,
    check_tag,
    d_fields,
    decimals_of,
    emit_rows,
    exponent_letter,
    fields_equal,
    fixed_field,
    float_tuple,
    int_field,
    is_integral,
    join_lines,
    majority_padded,
    pad80,
    read_section_row,
    row_text,
    source_path,
    split_lines,
    tag_line,
)

__all__ = [
    "LineScan",
    "SumLandmark",
    "LimbFit",
    "Picture",
    "parse_sum",
    "read_sum",
    "format_sum",
    "write_sum",
]


# ==================================================================================================
# list-directed reals and the DISTORTION line

_DIGIT = re.compile(r"\d")


def _is_real(token: str) -> bool:
    """A list-directed real or repeat item (``0.1D+01``, ``NaN``, ``3*0.0``)."""
    token = token.split("*", 1)[1] if re.match(r"^\d+\*", token) else token
    if token == "":
        return True
    try:
        parse_real(token)
    except ValueError:
        return False
    return True


def _d_like(line: str) -> bool:
    """The record after K-MATRIX that is a DISTORTION line: the tag at 64-73, or 4 untagged numbers."""
    if line[63:73] == "DISTORTION":
        return True
    toks = TOKEN.findall(line)
    return len(toks) == 4 and all(_is_real(t) for t in toks)


def _refuse_bom(line: str, path, what: str) -> None:
    """A UTF-8 byte-order mark is read by SPC as three characters of the record: refuse it."""
    if line.startswith(("\ufeff", "\xef\xbb\xbf")):
        raise SpcFormatError(
            path,
            1,
            f"expected {what} in column 1, found a UTF-8 byte-order mark (SPC reads it as text; remove it)",
        )


# ==================================================================================================
# SUM


@dataclass
class SumLandmark:
    """A measured landmark centre in a SUM ``LANDMARKS`` row (1-based sample/line, optional 1-char flag)."""

    name: str
    sample: float
    line: float
    flag: str = ""

    def __post_init__(self):
        self.flag = (self.flag or "").strip()
        if len(self.flag) > 1:
            raise ValueError(f"landmark flag must be '' or one character, got {self.flag!r}")

    def _key(self) -> tuple:
        return (self.name, float(self.sample), float(self.line), self.flag)


@dataclass
class LimbFit:
    """A ``LIMB FITS`` row: landmark name, sample, line and the third (undocumented) value."""

    name: str
    sample: float
    line: float
    value: float

    def _key(self) -> tuple:
        return (self.name, float(self.sample), float(self.line), float(self.value))


@dataclass
class _SumSource:
    """What a parsed SUM file looked like, for the byte-exact rewrite."""

    header: list[Slot]
    section_text: dict[str, str]  # 'landmarks' / 'limbs' / 'end' -> original header line
    landmark_rows: list[tuple[tuple, str]]
    limb_rows: list[tuple[tuple, str]]
    linescan: tuple[str, list[str]] | None  # (section it follows, lines)
    after_end: list[str]
    final_newline: bool
    pad_header: bool
    pad_body: bool
    name_line: str
    warnings: list = field(default_factory=list)
    linescan_data: LineScan | None = None


_SUM_TAGS = {
    "npx": "NPX, NLN, THRSH",
    "mmfl": "MMFL, CTR",
    "scobj": "SCOBJ",
    "cx": "CX",
    "cy": "CY",
    "cz": "CZ",
    "sz": "SZ",
    "kmatrix": "K-MATRIX",
    "distortion": "DISTORTION",
    "vso": "SIGMA_VSO",
    "ptg": "SIGMA_PTG",
}
_SUM_ORDER = [
    "name",
    "utc",
    "npx",
    "mmfl",
    "scobj",
    "cx",
    "cy",
    "cz",
    "sz",
    "kmatrix",
    "distortion",
    "vso",
    "ptg",
]
_PICTURE_FIELDS = (
    "name",
    "utc",
    "npx",
    "nln",
    "thrsh",
    "mmfl",
    "ctr",
    "scobj",
    "cx",
    "cy",
    "cz",
    "sz",
    "kmatrix",
    "distortion",
    "sigma_vso",
    "sigma_ptg",
    "landmarks",
    "limb_fits",
)


@dataclass(eq=False)
class Picture:
    """One SUM file (spc-formats.md §2): camera constants, pose, sigmas and measured landmarks.

    ``cx``, ``cy``, ``cz`` are the ROWS of the body->camera rotation; ``scobj`` points from the spacecraft to
    the body centre (body frame, km); ``kmatrix`` is 2x3 px/mm with the third column multiplying x*y.
    """

    name: str
    utc: str
    npx: int
    nln: int
    thrsh: np.ndarray
    mmfl: float
    ctr: np.ndarray
    scobj: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    cz: np.ndarray
    sz: np.ndarray
    kmatrix: np.ndarray
    distortion: np.ndarray | None = field(default_factory=lambda: np.zeros(4))
    sigma_vso: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sigma_ptg: np.ndarray = field(default_factory=lambda: np.zeros(3))
    landmarks: list[SumLandmark] = field(default_factory=list)
    limb_fits: list[LimbFit] = field(default_factory=list)
    _source: _SumSource | None = field(default=None, repr=False)

    def __post_init__(self):
        self.npx = int(self.npx)
        self.nln = int(self.nln)
        self.mmfl = float(self.mmfl)
        self.thrsh = as_shaped(self.thrsh, (2,), "thrsh")
        self.ctr = as_shaped(self.ctr, (2,), "ctr")
        for name in ("scobj", "cx", "cy", "cz", "sz", "sigma_vso", "sigma_ptg"):
            setattr(self, name, as_shaped(getattr(self, name), (3,), name))
        self.kmatrix = as_shaped(self.kmatrix, (2, 3), "kmatrix")
        if self.distortion is not None:
            self.distortion = as_shaped(self.distortion, (4,), "distortion")
        self.landmarks = list(self.landmarks)
        self.limb_fits = list(self.limb_fits)

    def __eq__(self, other):
        if not isinstance(other, Picture):
            return NotImplemented
        return fields_equal(self, other, _PICTURE_FIELDS)

    __hash__ = None  # type: ignore[assignment]

    @property
    def rotation(self) -> np.ndarray:
        """Body -> camera rotation (rows CX, CY, CZ)."""
        return np.vstack([self.cx, self.cy, self.cz])

    @property
    def is_linescan(self) -> bool:
        """Column 14 of line 1 is ``L`` (spc-formats.md §2.4)."""
        line = self._source.name_line if self._source is not None else ""
        return len(line) >= 14 and line[13] == "L"

    @property
    def linescan(self) -> LineScan | None:
        """The parsed ``LINE SCAN DATA`` block of a line-scan picture, else None."""
        return self._source.linescan_data if self._source is not None else None


@dataclass(frozen=True, eq=False)
class LineScan:
    """The ``LINE SCAN DATA`` block of a line-scan SUM (spc-formats.md §2.4), as xV2IMGPL.f reads it.

    U0, R0, POL_AXIS, POL, TRJ_AXIS, TRJ and KMAX rows of CAX, each read with its own ``READ(32,*)``.
    (XV2IMGPL then replaces U0 and R0(1) by the direction and length of SCOBJ.)
    """

    u0: np.ndarray
    r0: np.ndarray
    pol_axis: np.ndarray
    pol: float
    trj_axis: np.ndarray
    trj: np.ndarray
    cax: np.ndarray  # (KMAX, 3)


def _parse_linescan(lines: list[str], path) -> LineScan:
    """xV2IMGPL.f: READ(32,FMT='(A80)') LINE until LINE(1:14)='LINE SCAN DATA', then READ(32,*) U0; R0;
    POL_AXIS; POL; TRJ_AXIS; TRJ; KMAX; KMAX x CAX(K,1:3)."""
    start = next((k for k in range(1, len(lines)) if lines[k][:14] == "LINE SCAN DATA"), None)
    if start is None:
        raise SpcFormatError(
            path,
            1,
            "expected a LINE SCAN DATA line: column 14 of line 1 is 'L' (a line-scan picture), and xV2IMGPL "
            "reads the file up to that line",
        )
    rec = Records(lines, path, start + 1)

    def vec(kinds: str, what: str):
        if rec.at_end:
            raise SpcFormatError(
                path, len(lines), f"expected {what} in the LINE SCAN DATA block, found end of file"
            )
        res = rec.read_list(kinds, what=f"numbers ({what}, LINE SCAN DATA)")
        if res.nulls or res.slash:
            raise SpcFormatError(
                path, res.first + 1, f"expected {len(kinds)} numbers ({what}), found a null item"
            )
        return res.values

    u0, r0, pol_axis = vec("rrr", "U0"), vec("rrr", "R0"), vec("rrr", "POL_AXIS")
    pol = vec("r", "POL")[0]
    trj_axis, trj = vec("rrr", "TRJ_AXIS"), vec("rrr", "TRJ")
    kmax = vec("i", "KMAX")[0]
    if not 0 <= kmax <= 20:
        raise SpcFormatError(path, rec.pos, f"expected 0 <= KMAX <= 20 (CAX(20,3)), found {kmax}")
    cax = np.array([vec("rrr", f"CAX row {k + 1}") for k in range(kmax)], dtype=float).reshape(kmax, 3)
    arr = lambda v: np.array(v, dtype=float)  # noqa: E731
    return LineScan(arr(u0), arr(r0), arr(pol_axis), float(pol), arr(trj_axis), arr(trj), cax)


_UTC = re.compile(r"^\d{4}\s+[A-Za-z]{3}\s+\d{1,2}\s+\d{1,2}:\d{2}:\d{2}(\.\d*)?")


def _picture_values(pic: Picture, key: str) -> tuple | None:
    if key == "name":
        return (pic.name,)
    if key == "utc":
        return (pic.utc,)
    if key == "npx":
        return (pic.npx, pic.nln) + float_tuple(pic.thrsh)
    if key == "mmfl":
        return (float(pic.mmfl),) + float_tuple(pic.ctr)
    if key == "kmatrix":
        return float_tuple(pic.kmatrix)
    if key == "distortion":
        return None if pic.distortion is None else float_tuple(pic.distortion)
    attr = {"vso": "sigma_vso", "ptg": "sigma_ptg"}.get(key, key)
    return float_tuple(getattr(pic, attr))


def _section_kind(line: str) -> str | None:
    if line.startswith("LANDMARKS"):
        return "landmarks"
    if line.startswith("LIMB FITS"):
        return "limbs"
    if line.startswith("END FILE"):
        return "end"
    if line.startswith("LINE SCAN DATA"):
        return "linescan"
    return None


def _classify_tag(tag: str) -> str | None:
    t = tag.upper()
    if "DISTORTION" in t:
        return "distortion"
    if "VSO" in t:
        return "vso"
    if "PTG" in t:
        return "ptg"
    return None


def parse_sum(text: str, path=None) -> Picture:
    """Parse the text of a SUM file (spc-formats.md §2).  Bad input raises :class:`SpcFormatError`.

    Three parts, read as SPC's routines read them: the fixed header (:func:`_read_fixed_header`: name,
    UTC and the list-directed records to K-MATRIX), the rest of the header (:func:`_read_header_rest`:
    DISTORTION, SIGMA_VSO, SIGMA_PTG, other lines kept verbatim) and the sections
    (:func:`_read_sections`: LANDMARKS, LIMB FITS, LINE SCAN DATA, END FILE)."""
    path = source_path(path)
    lines, final = split_lines(text)
    header: list[Slot] = []
    warnings: list[tuple[int, str]] = []
    fixed, pos = _read_fixed_header(lines, path, header, warnings)
    distortion, sigma_vso, sigma_ptg, header_end = _read_header_rest(lines, pos, path, header, warnings)
    sec = _read_sections(lines, header_end, path, warnings)

    linescan_data = _parse_linescan(lines, path) if len(lines[0]) >= 14 and lines[0][13] == "L" else None
    source = _SumSource(
        linescan_data=linescan_data,
        warnings=warnings,
        header=header,
        section_text=sec.section_text,
        landmark_rows=sec.landmark_rows,
        limb_rows=sec.limb_rows,
        linescan=sec.linescan,
        after_end=lines[sec.end_index + 1 :],
        final_newline=final,
        pad_header=majority_padded(lines[:header_end], False),
        pad_body=majority_padded(lines[header_end : sec.end_index + 1], False),
        name_line=lines[0],
    )
    return Picture(
        **fixed,
        distortion=distortion,
        sigma_vso=sigma_vso,
        sigma_ptg=sigma_ptg,
        landmarks=sec.landmarks,
        limb_fits=sec.limbs,
        _source=source,
    )


def _read_fixed_header(lines: list[str], path, header: list[Slot], warnings: list) -> tuple[dict, int]:
    """The picture name, the UTC and the list-directed records NPX … K-MATRIX (globalStat,
    map_coverage_p_low).  Appends a :class:`Slot` per record to ``header``; returns the
    :class:`Picture` fields read and the index of the first line after K-MATRIX."""
    n = len(lines)
    rec = Records(lines, path)

    def need(i: int, what: str) -> str:
        if i >= n:
            if n == 0:
                raise SpcFormatError(path, 1, f"expected {what}, found an empty file")
            raise SpcFormatError(path, n, f"expected {what} on line {i + 1}, found end of file")
        return lines[i]

    # line 1: globalStat READ(10,*) skips it; the name is columns 1-12, column 14 'L' marks a line-scan
    # picture (xV2IMGPL READ(32,FMT='(A80)') LINE; IF(LINE(14:14).EQ.'L'))
    line = need(0, "the picture name")
    _refuse_bom(line, path, "the picture name")
    rec.skip()
    name = line[:12].strip()
    if not name and path is not None:
        name = os.path.splitext(os.path.basename(path))[0][:12]
        warnings.append(
            (1, f"blank picture-name line (SPC skips it: READ(10,*)); name {name!r} taken from the file name")
        )
    header.append(Slot("name", line, (name,)))

    # line 2: the UTC, skipped by READ(10,*) (globalStat): any text, even blank, is accepted
    line = need(1, "the UTC line")
    rec.skip()
    utc = line.strip()
    header.append(Slot("utc", line, (utc,)))

    def field(key: str, kinds: str, what: str):
        """One header READ(10,*) (globalStat / map_coverage_p_low), its tag checked against its place."""
        if rec.at_end:
            raise SpcFormatError(path, n, f"expected {what} on line {rec.pos + 1}, found end of file")
        first = rec.pos
        res = rec.read_list(kinds, what=f"numbers ({what})")
        if res.nulls or res.slash:
            k = next(j for j, ln in enumerate(res.lines) if ln is None)
            raise SpcFormatError(
                path,
                first + 1,
                f"expected {len(kinds)} numbers ({what}), found a null item or '/' for value {k + 1} "
                "(SPC would keep the previous picture's value)",
            )
        tag = res.rest.strip()
        check_tag(tag, key, _SUM_TAGS, path, res.last + 1)
        more = tag.split(None, 1)[:1]
        if more and _is_real(more[0].rstrip(",")):
            warnings.append(
                (res.last + 1, f"{what}: values after the {len(kinds)} SPC reads are ignored ({more[0]!r})")
            )
        if res.last > first or res.first != first:
            warnings.append(
                (
                    first + 1,
                    f"{what} continues over lines {first + 1}-{res.last + 1} (SPC reads on: list-directed)",
                )
            )
        text = "\n".join(lines[first : res.last + 1])
        return res.values, text, tag

    # READ(10,*) NPX, NLN, T1, T2 (map_coverage_p_low; globalStat reads NPX, NLN only)
    vals, text, tag = field("npx", "iirr", "NPX, NLN, THRSH")
    if vals[0] < 1 or vals[1] < 1:
        raise SpcFormatError(path, 3, f"expected positive integers NPX, NLN, found {vals[0]!r}, {vals[1]!r}")
    npx, nln = int(vals[0]), int(vals[1])
    thrsh = np.array(vals[2:4], dtype=float)
    header.append(Slot("npx", text, (npx, nln, float(vals[2]), float(vals[3])), tag))

    def vec_line(key: str, count: int, what: str) -> list[float]:
        v, text, tag = field(key, "r" * count, what)
        header.append(Slot(key, text, tuple(float(x) for x in v), tag))
        return v

    v = vec_line("mmfl", 3, "MMFL, CTR")
    mmfl, ctr = v[0], np.array(v[1:3])
    scobj = np.array(vec_line("scobj", 3, "SCOBJ"))
    cx = np.array(vec_line("cx", 3, "CX"))
    cy = np.array(vec_line("cy", 3, "CY"))
    cz = np.array(vec_line("cz", 3, "CZ"))
    sz = np.array(vec_line("sz", 3, "SZ"))
    kmatrix = np.array(vec_line("kmatrix", 6, "K-MATRIX")).reshape(2, 3)
    fields = dict(
        name=name, utc=utc, npx=npx, nln=nln, thrsh=thrsh, mmfl=mmfl, ctr=ctr,
        scobj=scobj, cx=cx, cy=cy, cz=cz, sz=sz, kmatrix=kmatrix,
    )  # fmt: skip
    return fields, rec.pos


def _read_header_rest(lines: list[str], start: int, path, header: list[Slot], warnings: list):
    """The header after K-MATRIX, up to the first section line: returns ``(distortion, sigma_vso,
    sigma_ptg, header_end)``."""
    n = len(lines)
    # the rest of the header.  DISTORTION: READ(10,FMT='(A80)') LINE; IF(LINE(64:73).EQ.'DISTORTION')
    # READ(LINE,*) (D(I),I=1,4), else D = 0 (globalStat, map_coverage_p_low); SIGMA_VSO / SIGMA_PTG (LITHOS)
    # by tag, untagged lines by position; other lines kept verbatim
    i = start
    d_line = i
    rest: list[tuple[int, str, str | None]] = []
    while i < n and _section_kind(lines[i]) is None:
        ln = lines[i]
        toks = TOKEN.findall(ln)
        k = 0
        while k < len(toks) and _is_real(toks[k]):
            k += 1
        tag_text = " ".join(toks[k:])
        # None = untagged (takes a SIGMA role by position below); "other" = an unknown tag such as SIGPXL
        rest.append((i, ln, (_classify_tag(tag_text) or "other") if tag_text else None))
        i += 1
    if i >= n:
        raise SpcFormatError(path, max(n, 1), "expected LANDMARKS, LIMB FITS or END FILE, found end of file")
    kinds = [r[2] for r in rest]
    # untagged lines take the SIGMA_VSO / SIGMA_PTG roles by position, as SPC reads them
    for role in ("vso", "ptg"):
        if role not in kinds:
            for j, kd in enumerate(kinds):
                if kd is None and not (rest[j][0] == d_line and _d_like(rest[j][1])):
                    kinds[j] = role
                    break
    distortion = None
    sigma_vso = sigma_ptg = None
    seen: set[str] = set()
    for (idx, ln, _), kind in zip(rest, kinds):
        if kind == "distortion" or (idx == d_line and ln[63:73] == "DISTORTION"):
            if idx == d_line and ln[63:73] == "DISTORTION" and "distortion" not in seen:
                res = read_internal(
                    ln[:80], "rrrr", [0.0] * 4, path=path, line=idx + 1, what="numbers (DISTORTION)"
                )
                v = [float(x) for x in res.values]
                header.append(Slot("distortion", ln, tuple(v), ln[63:].strip()))
                distortion = np.array(v)
                seen.add("distortion")
                if len(ln) > 80 and ln[80:].strip():
                    warnings.append(
                        (idx + 1, "text past column 80 of the DISTORTION record is not read by SPC")
                    )
                continue
            where = "is not the line after K-MATRIX" if idx != d_line else "is not in columns 64-73"
            warnings.append(
                (idx + 1, f"the DISTORTION tag {where}: SPC takes D = 0 (IF(LINE(64:73).EQ.'DISTORTION'))")
            )
            header.append(Slot("extra", ln))
            continue
        if kind is None and idx == d_line and _d_like(ln):
            warnings.append(
                (
                    idx + 1,
                    "untagged 4-number line after K-MATRIX: SPC tests LINE(64:73) for 'DISTORTION' "
                    "and takes D = 0",
                )
            )
        if kind in seen:
            kind = None  # a repeated role: keep verbatim
        if kind is None or kind == "other":
            header.append(Slot("extra", ln))
            continue
        seen.add(kind)
        res = read_internal(ln, "rrr", path=path, line=idx + 1, what=f"numbers ({_SUM_TAGS[kind]})")
        if res.nulls or res.slash:
            raise SpcFormatError(
                path, idx + 1, f"expected 3 numbers ({_SUM_TAGS[kind]}), found a null item or '/'"
            )
        v = [float(x) for x in res.values]
        header.append(Slot(kind, ln, tuple(v), res.rest.strip()))
        if kind == "vso":
            sigma_vso = np.array(v)
        else:
            sigma_ptg = np.array(v)
    if sigma_vso is None or sigma_ptg is None:
        missing = " and ".join(
            t for t, v in (("SIGMA_VSO", sigma_vso), ("SIGMA_PTG", sigma_ptg)) if v is None
        )
        warnings.append(
            (i + 1, f"the header ends without {missing} (SPC's readers stop after K-MATRIX); read as 0")
        )
        sigma_vso = np.zeros(3) if sigma_vso is None else sigma_vso
        sigma_ptg = np.zeros(3) if sigma_ptg is None else sigma_ptg
    return distortion, sigma_vso, sigma_ptg, i


@dataclass
class _Sections:
    """What :func:`_read_sections` read."""

    section_text: dict[str, str]
    landmarks: list[SumLandmark]
    limbs: list[LimbFit]
    landmark_rows: list[tuple[tuple, str]]
    limb_rows: list[tuple[tuple, str]]
    linescan: tuple[str, list[str]] | None
    end_index: int


def _read_sections(lines: list[str], i: int, path, warnings: list) -> _Sections:
    """LANDMARKS, LIMB FITS, a LINE SCAN DATA block and END FILE, from line index ``i`` (LMCOUNT's
    (A80) records)."""
    n = len(lines)
    section_text: dict[str, str] = {}
    landmarks: list[SumLandmark] = []
    limbs: list[LimbFit] = []
    landmark_rows: list[tuple[tuple, str]] = []
    limb_rows: list[tuple[tuple, str]] = []
    linescan: tuple[str, list[str]] | None = None
    state = None
    end_index = None
    while i < n:
        ln = lines[i]
        kind = _section_kind(ln)
        if kind == "end":
            section_text["end"] = ln
            end_index = i
            if "limbs" not in section_text:
                warnings.append(
                    (
                        i + 1,
                        "END FILE before a LIMB FITS line: SPC's LMCOUNT reads (A80) records until LIMB FITS "
                        "and would run past it",
                    )
                )
            break
        if state == "linescan" and kind not in ("landmarks", "limbs"):
            linescan[1].append(ln)  # type: ignore[index]
            i += 1
            continue
        if kind == "linescan":
            if linescan is not None:
                raise SpcFormatError(path, i + 1, "unexpected second LINE SCAN DATA block")
            linescan = (state or "header", [ln])
            state = "linescan"
        elif kind in ("landmarks", "limbs"):
            if kind in section_text:
                raise SpcFormatError(path, i + 1, f"unexpected second {ln[:9]} section")
            section_text[kind] = ln
            state = kind
        elif state == "landmarks":
            if _DIGIT.search(ln, 6) is None and ln.strip():
                raise SpcFormatError(
                    path,
                    i + 1,
                    f"expected a landmark row or LIMB FITS in columns 1-9 (LMCOUNT), "
                    f"found {ln.strip()[:20]!r}",
                )
            lm = _parse_sum_landmark(ln, path, i + 1, warnings)
            landmarks.append(lm)
            landmark_rows.append((lm._key(), ln))
        elif state == "limbs":
            if _DIGIT.search(ln, 6) is None and ln.strip():
                raise SpcFormatError(
                    path,
                    i + 1,
                    f"expected a limb row or END FILE in columns 1-8 (LMCOUNT), found {ln.strip()[:20]!r}",
                )
            lf = parse_limb_row(ln, path, i + 1, name_width=6, notes=warnings)
            limbs.append(lf)
            limb_rows.append((lf._key(), ln))
        else:  # pragma: no cover - header loop stops only at a section line
            raise SpcFormatError(path, i + 1, "expected LANDMARKS, LIMB FITS or END FILE")
        i += 1
    if end_index is None:
        raise SpcFormatError(path, n, "expected END FILE line, found end of file")
    return _Sections(section_text, landmarks, limbs, landmark_rows, limb_rows, linescan, end_index)


def _parse_sum_landmark(line: str, path, lineno: int, notes: list | None = None) -> SumLandmark:
    """``(A6,2F10.2)`` or ``(A6,2F10.2,1X,A1)`` (:func:`~spctool.formats.rows.read_section_row`; a row not in
    those columns appends ``(lineno, warning)`` to ``notes``)."""
    name = line[:6].strip()
    if not name:
        raise SpcFormatError(path, lineno, "expected a landmark name in columns 1-6")
    vals, rest, note = read_section_row(
        line, SUM_LANDMARK_FORMAT, 2, 6, path=path, lineno=lineno, what="numbers (landmark sample, line)"
    )
    flag = rest.strip()
    if len(flag) > 1:
        raise SpcFormatError(
            path, lineno, f"expected at most a 1-character flag after sample, line; found {flag!r}"
        )
    if note is not None and notes is not None:
        notes.append((lineno, note))
    return SumLandmark(name, vals[0], vals[1], flag)


#: LITHOS's READ formats of the SUM section rows [BIN]
SUM_LANDMARK_FORMAT = "(A6,2F10.2,1X,A1)"
SUM_LIMB_FORMAT = "(A6,3F10.2)"


def parse_limb_row(line: str, path, lineno: int, name_width: int, notes: list | None = None):
    """``(A6,3F10.2)`` (SUM) or ``(A12,3F10.2)`` (LMK): name, sample, line, value.  A row of two numbers
    (GIANT writes no third) reads as LITHOS's formatted READ does, the third 0 as written."""
    name = line[:name_width].strip()
    if not name:
        raise SpcFormatError(path, lineno, f"expected a name in columns 1-{name_width}")
    vals, rest, note = read_section_row(
        line,
        f"(A{name_width},3F10.2)",
        3,
        name_width,
        path=path,
        lineno=lineno,
        what="numbers (limb fit)",
        short_ok=True,
    )
    if rest.strip():
        raise SpcFormatError(path, lineno, f"expected 3 numbers (limb fit), found trailing {rest.strip()!r}")
    if note is not None and notes is not None:
        notes.append((lineno, note))
    return LimbFit(name, vals[0], vals[1], vals[2])


def _int_or_repr(value: float, width: int) -> str:
    if is_integral(value):
        return int_field(int(value), width)
    return " " + repr(float(value))


def _k_text(values, decimals: int) -> str:
    """``6F10.d`` K-matrix numbers (d = 5 canonical, or the decimals of the line being replaced)."""
    return "".join(fixed_field(v, 10, decimals) for v in values)


def _sum_line(pic: Picture, slot: Slot, padded: bool) -> str:
    """Regenerate one SUM header line (spc-formats.md §2.3 canonical / LITHOS formats)."""
    key = slot.key
    if key == "name":
        rest = slot.text[12:] if slot.text else ""
        text = pic.name.ljust(12) + rest if rest.strip() else pic.name
        return pad80(text, padded)
    if key == "utc":
        return pad80(pic.utc, padded)
    tag = slot.tag or _SUM_TAGS[key]
    letter = exponent_letter(slot.text)
    if key == "npx":
        nums = "".join(_int_or_repr(v, 6) for v in (pic.npx, pic.nln, *pic.thrsh))
    elif key == "mmfl":
        nums = d_fields([pic.mmfl, *pic.ctr], letter)
    elif key == "kmatrix":
        nums = _k_text(float_tuple(pic.kmatrix), decimals_of(slot.text, 5))
    elif key == "distortion":
        nums = d_fields(pic.distortion, letter, 15, 5)
    else:
        nums = d_fields(_picture_values(pic, key), letter)
    return tag_line(nums, tag, padded)


def format_sum(pic: Picture) -> str:
    """SUM file text.  Unchanged lines of a parsed file are reproduced byte for byte.  A non-finite
    pose (SCOBJ, CX, CY, CZ) is never written (SpcUsageError)."""
    _refuse_nonfinite_pose(pic, "SUM", ("scobj", "cx", "cy", "cz"))
    src = pic._source
    if src is None:
        slots = [Slot(k) for k in _SUM_ORDER]
        pad_header = pad_body = False
    else:
        slots = list(src.header)
        pad_header, pad_body = src.pad_header, src.pad_body
        if pic.distortion is not None and not any(s.key == "distortion" for s in slots):
            at = next(j for j, s in enumerate(slots) if s.key == "kmatrix") + 1
            slots.insert(at, Slot("distortion"))
    out: list[str] = []
    for slot in slots:
        if slot.key == "extra":
            out.append(slot.text)
            continue
        if slot.key == "distortion" and pic.distortion is None:
            continue
        if slot.text is not None and _picture_values(pic, slot.key) == slot.values:
            out.append(slot.text)
        else:
            padded = slot.padded if slot.padded is not None else pad_header
            out.append(_sum_line(pic, slot, padded))

    sections = src.section_text if src is not None else {}
    linescan = src.linescan if src is not None else None

    def header_line(kind: str, text: str) -> str:
        return sections.get(kind, pad80(text, pad_body))

    if linescan is not None and linescan[0] == "header":
        out.extend(linescan[1])
    if src is None or "landmarks" in sections or pic.landmarks:
        out.append(header_line("landmarks", "LANDMARKS"))
    out.extend(
        emit_rows(
            src.landmark_rows if src is not None else [],
            pic.landmarks,
            lambda lm: pad80(row_text(lm.name, 6, (lm.sample, lm.line), (10, 2), lm.flag), pad_body),
        )
    )
    if linescan is not None and linescan[0] == "landmarks":
        out.extend(linescan[1])
    if src is None or "limbs" in sections or pic.limb_fits:
        out.append(header_line("limbs", "LIMB FITS"))
    out.extend(
        emit_rows(
            src.limb_rows if src is not None else [],
            pic.limb_fits,
            lambda lf: pad80(row_text(lf.name, 6, (lf.sample, lf.line, lf.value), (10, 2)), pad_body),
        )
    )
    if linescan is not None and linescan[0] == "limbs":
        out.extend(linescan[1])
    out.append(header_line("end", "END FILE"))
    if src is not None:
        out.extend(src.after_end)
    return join_lines(out, src.final_newline if src is not None else True)


def _refuse_nonfinite_pose(obj, kind: str, attrs) -> None:
    """SpcUsageError when a pose value of ``obj`` to be written is NaN or infinite."""
    for attr in attrs:
        if not np.all(np.isfinite(np.asarray(getattr(obj, attr), dtype=np.float64))):
            raise SpcUsageError(
                f"{kind} of picture {obj.name}: refusing to write a non-finite pose ({attr.upper()} "
                "holds NaN or Infinity)"
            )


def read_sum(path) -> Picture:
    """Read ``SUMFILES/<PICNM>.SUM``."""
    text = atomic.read_spc_file(path, "SUM")
    return parse_sum(text, path)


def write_sum(path, pic: Picture, *, overwrite: bool = True, backup: bool = False):
    """Write a SUM file atomically (returns the backup path if one was made)."""
    return atomic.write_text(path, format_sum(pic), overwrite=overwrite, backup=backup)


# ------------------------------------------------------------------------------------------------
# updates that stages make to a picture (only the changed lines are regenerated on write)


def with_pose(pic: Picture, scobj, rotation, sigma_vso=None, sigma_ptg=None) -> Picture:
    """A copy of ``pic`` with a new SCOBJ, CX/CY/CZ (rows of ``rotation``, body→camera) and, when
    given, SIGMA_VSO / SIGMA_PTG — the lines LITHOS rewrites after a geometry solve (§0.3)."""
    rotation = np.asarray(rotation, dtype=np.float64)
    changes = {
        "scobj": np.asarray(scobj, dtype=np.float64),
        "cx": rotation[0],
        "cy": rotation[1],
        "cz": rotation[2],
    }
    if sigma_vso is not None:
        changes["sigma_vso"] = np.asarray(sigma_vso, dtype=np.float64)
    if sigma_ptg is not None:
        changes["sigma_ptg"] = np.asarray(sigma_ptg, dtype=np.float64)
    return dataclasses.replace(pic, **changes)


def with_measured_landmarks(pic: Picture, names, pixels, ok, *, drop_failed: bool = False) -> Picture:
    """A copy of ``pic`` whose LANDMARKS rows carry new measured pixels, as ``register --write-sum``.

    For every ``ok`` landmark its row gets ``pixels`` (sample, line) — the row's flag is kept — or a
    row is appended when the SUM has none.  Rows of landmarks that were not measured stay as they are,
    unless ``drop_failed`` removes the rows of the names given with ``ok`` false.
    """
    rows = list(pic.landmarks)
    index = {lm.name.strip(): k for k, lm in enumerate(rows)}
    failed = set()
    for name, good, (sample, line) in zip(names, ok, pixels):
        name = name.strip()
        if not good:
            failed.add(name)
            continue
        if name in index:
            old = rows[index[name]]
            rows[index[name]] = SumLandmark(old.name, float(sample), float(line), old.flag)
        else:
            rows.append(SumLandmark(name, float(sample), float(line)))
            index[name] = len(rows) - 1
    if drop_failed:
        rows = [lm for lm in rows if lm.name.strip() not in failed]
    return dataclasses.replace(pic, landmarks=rows)
