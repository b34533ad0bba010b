"""SPC landmark files (``LMKFILES/<NAME>.LMK``) <-> :class:`Landmark`.

Specification: ``shared/docs/spc-formats.md`` §4 (layout, notes, example), §0.3 (Fortran numbers, byte-exact
round trip), §8 items 6, 7, 17, 18 and §9 (checklist).

Lines 1-9 are read by position, list-directed; the sections (``PICTURES``, ``MAP OVERLAPS``, ``LIMB FITS``)
are found by their leading characters and may be missing (the real Rosetta files are trimmed to ``PICTURES`` +
``END FILE``).  Writing is byte-exact: a parsed line keeps its text unless its values change, and is then
regenerated with the LITHOS formats of §4.1 (tags at column 64) in the padding style of the line it replaces.
New files are written in the LITHOS layout of §4.3 (lines 2-9 blank-padded to 80 columns by the ``A20`` tags).

UX, UY, UZ are the COLUMNS of the maplet->body rotation (UY ~ East, UX ~ South; §8 item 6).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from spctool.errors import SpcFormatError
from spctool.formats import atomic
from spctool.formats.fortran import Records
from spctool.formats.rows import (
    Slot,
    as_shaped,
    check_tag,
    d_fields,
    emit_rows,
    exponent_letter,
    fields_equal,
    fixed_field,
    float_tuple,
    int_field,
    join_lines,
    majority_padded,
    pad80,
    read_section_row,
    row_text,
    scan_row,
    source_path,
    spc_columns,
    spc_field,
    split_lines,
    tag_line,
)
from spctool.formats.sumfile import parse_limb_row

__all__ = [
    "LandmarkPicture",
    "MapOverlap",
    "LandmarkLimb",
    "Landmark",
    "parse_lmk",
    "read_lmk",
    "format_lmk",
    "write_lmk",
]


@dataclass
class LandmarkPicture:
    """A ``PICTURES`` row: picture name, predicted/measured sample and line (may be negative), flag
    (``*``)."""

    name: str
    sample: float
    line: float
    flag: str = ""

    def __post_init__(self):
        self.flag = (self.flag or "").strip()
        if len(self.flag) > 1:
            raise ValueError(f"picture flag must be '' or one character, got {self.flag!r}")

    def _key(self) -> tuple:
        return (self.name, float(self.sample), float(self.line), self.flag)


@dataclass(eq=False)
class MapOverlap:
    """A ``MAP OVERLAPS`` row: neighbour name and its centre offset (UX, UY, UZ) in units of this SCALE."""

    name: str
    offset: np.ndarray

    def __post_init__(self):
        self.offset = as_shaped(self.offset, (3,), "offset")

    def __eq__(self, other):
        if not isinstance(other, MapOverlap):
            return NotImplemented
        return self.name == other.name and np.array_equal(self.offset, other.offset)

    __hash__ = None  # type: ignore[assignment]

    def _key(self) -> tuple:
        return (self.name,) + float_tuple(self.offset)


@dataclass
class LandmarkLimb:
    """A ``LIMB FITS`` row of an LMK: picture name, sample, line and the third (undocumented) value."""

    name: str
    sample: float
    line: float
    value: float

    def _key(self) -> tuple:
        return (self.name, float(self.sample), float(self.line), float(self.value))


@dataclass
class _LmkSource:
    header: list[Slot]
    section_order: list[str]
    section_text: dict[str, str]
    rows: dict[str, list[tuple[tuple, str]]]
    end_line: str
    after_end: list[str]
    final_newline: bool
    pad_header: bool
    pad_body: bool
    warnings: list = field(default_factory=list)


_LMK_TAGS = {
    "size": "SIZE, SCALE(KM)",
    "horizon": "HORIZON",
    "sig": "SIGKM, RMSLMK",
    "vlm": "VLM",
    "ux": "UX",
    "uy": "UY",
    "uz": "UZ",
    "sigma_lmk": "SIGMA_LMK",
}
#: what lines 2-9 hold, as error messages name them
_LMK_WHATS = {**_LMK_TAGS, "size": "QSZ, SCALE"}
_LMK_ORDER = ["name", "size", "horizon", "sig", "vlm", "ux", "uy", "uz", "sigma_lmk"]
_SECTIONS = {"pictures": "PICTURES", "overlaps": "MAP OVERLAPS", "limbs": "LIMB FITS"}
_LANDMARK_FIELDS = (
    "name",
    "hflag",
    "bigmap_extra",
    "qsz",
    "scale",
    "horizon",
    "sigkm",
    "rmslmk",
    "vlm",
    "ux",
    "uy",
    "uz",
    "sigma_lmk",
    "pictures",
    "overlaps",
    "limb_fits",
)


@dataclass(eq=False)
class Landmark:
    """One LMK file (spc-formats.md §4).

    ``vlm`` is the body-fixed maplet centre (km); ``ux``, ``uy``, ``uz`` the maplet axes in the body frame
    (columns of map->body); ``scale`` km per cell; ``sigkm`` the a-priori position sigma (0.5*SCALE by
    convention); ``bigmap_extra`` the two F8.4 numbers of the bigmap line-1 variant, or None.
    """

    name: str
    hflag: str
    bigmap_extra: tuple[float, float] | None
    qsz: int
    scale: float
    horizon: tuple[int, int, int, int]
    sigkm: float
    rmslmk: float
    vlm: np.ndarray
    ux: np.ndarray
    uy: np.ndarray
    uz: np.ndarray
    sigma_lmk: np.ndarray
    pictures: list[LandmarkPicture] = field(default_factory=list)
    overlaps: list[MapOverlap] = field(default_factory=list)
    limb_fits: list[LandmarkLimb] = field(default_factory=list)
    _source: _LmkSource | None = field(default=None, repr=False)

    def __post_init__(self):
        self.qsz = int(self.qsz)
        self.scale = float(self.scale)
        self.sigkm = float(self.sigkm)
        self.rmslmk = float(self.rmslmk)
        self.horizon = tuple(int(h) for h in self.horizon)
        if len(self.horizon) != 4:
            raise ValueError(f"horizon must have 4 integers, got {self.horizon!r}")
        if self.bigmap_extra is not None:
            a, b = self.bigmap_extra
            self.bigmap_extra = (float(a), float(b))
        for name in ("vlm", "ux", "uy", "uz", "sigma_lmk"):
            setattr(self, name, as_shaped(getattr(self, name), (3,), name))
        self.pictures = list(self.pictures)
        self.overlaps = list(self.overlaps)
        self.limb_fits = list(self.limb_fits)

    def __eq__(self, other):
        if not isinstance(other, Landmark):
            return NotImplemented
        return fields_equal(self, other, _LANDMARK_FIELDS)

    __hash__ = None  # type: ignore[assignment]

    @property
    def rotation_map_to_body(self) -> np.ndarray:
        """Maplet -> body rotation: UX, UY, UZ as columns."""
        return np.column_stack([self.ux, self.uy, self.uz])


def _landmark_values(lmk: Landmark, key: str) -> tuple:
    if key == "name":
        return (lmk.name, lmk.hflag, lmk.bigmap_extra)
    if key == "size":
        return (lmk.qsz, float(lmk.scale))
    if key == "horizon":
        return tuple(lmk.horizon)
    if key == "sig":
        return (float(lmk.sigkm), float(lmk.rmslmk))
    return float_tuple(getattr(lmk, key))


def _section_of(line: str) -> str | None:
    if line.startswith("PICTURES"):
        return "pictures"
    if line.startswith("MAP OVERLAPS"):
        return "overlaps"
    if line.startswith("LIMB FITS"):
        return "limbs"
    if line.startswith("END FILE"):
        return "end"
    return None


def parse_lmk(text: str, path=None) -> Landmark:
    """Parse the text of an LMK file (spc-formats.md §4).  Bad input raises :class:`SpcFormatError`.

    Read as LITHOS reads it: line 1 (:func:`_read_lmk_name`), lines 2-9 by position, each a
    list-directed READ(unit,*) (:func:`_read_lmk_header`), then the sections
    (:func:`_read_lmk_sections`)."""
    # mirrors: lines 2-9 READ(unit,*) by position (LITHOS); sections READ(27,FMT='(A80)') LINE with
    # LINE(1:8)='PICTURES', (1:12)='MAP OVERLAPS', (1:9)='LIMB FITS', (1:8)='END FILE' (KOUNT)
    path = source_path(path)
    lines, final = split_lines(text)
    header: list[Slot] = []
    name, hflag, bigmap_extra, line1_notes = _read_lmk_name(lines, path, header)
    values, pos = _read_lmk_header(lines, path, header)
    sec = _read_lmk_sections(lines, pos, path)
    i = sec.end_index
    section_text, rows, notes = sec.section_text, sec.rows, sec.notes
    section_order, pictures, overlaps, limbs = sec.section_order, sec.pictures, sec.overlaps, sec.limbs

    source = _LmkSource(
        header=header,
        section_order=section_order,
        section_text=section_text,
        rows=rows,
        end_line=lines[i],
        after_end=lines[i + 1 :],
        final_newline=final,
        pad_header=majority_padded(lines[1:9], True),
        pad_body=majority_padded([lines[0]] + lines[9 : i + 1], False),
    )
    source.warnings.extend(line1_notes + notes)
    missing = [_SECTIONS[k] for k in ("pictures", "overlaps", "limbs") if k not in section_text]
    if missing:
        # globalCoverage.f KOUNT: READ (A80) until PICTURES, then until MAP OVERLAPS, then LIMB FITS
        source.warnings.append(
            (
                i + 1,
                f"no {' / '.join(missing)} line before END FILE: globalCoverage.f KOUNT would read on "
                "past it "
                "(spctool accepts the trimmed file)",
            )
        )
    return Landmark(
        name=name,
        hflag=hflag,
        bigmap_extra=bigmap_extra,
        qsz=values["size"][0],
        scale=values["size"][1],
        horizon=tuple(values["horizon"]),
        sigkm=values["sig"][0],
        rmslmk=values["sig"][1],
        vlm=np.array(values["vlm"]),
        ux=np.array(values["ux"]),
        uy=np.array(values["uy"]),
        uz=np.array(values["uz"]),
        sigma_lmk=np.array(values["sigma_lmk"]),
        pictures=pictures,
        overlaps=overlaps,
        limb_fits=limbs,
        _source=source,
    )


def _read_lmk_name(lines: list[str], path, header: list[Slot]):
    """Line 1: (A6,3X,A1) or the bigmap variant (A6,3X,A1,4X,2F8.4); returns ``(name, hflag,
    bigmap_extra, notes)`` and appends its :class:`Slot` to ``header``."""
    if not lines:
        raise SpcFormatError(path, 1, "expected the landmark name and HFLAG, found an empty file")
    line = lines[0]
    name = line[:6].strip()
    if not name:
        raise SpcFormatError(path, 1, "expected the landmark name in columns 1-6")
    rest = line[6:].split()
    if not rest or rest[0] not in ("T", "F"):
        found = rest[0] if rest else "nothing"
        raise SpcFormatError(path, 1, f"expected HFLAG T or F after the name, found {found!r}")
    hflag = rest[0]
    line1_notes = []
    if line[9:10] != hflag:  # LITHOS reads line 1 (A6,3X,A1): the flag is column 10 (issue #40 item 8)
        col10 = repr(line[9:10]) if line[9:10].strip() else "a blank"
        line1_notes.append(
            (
                1,
                f"HFLAG {hflag!r} in column {line.index(hflag, 6) + 1}: LITHOS reads line 1 (A6,3X,A1) and "
                f"finds {col10} in column 10; spctool reads {hflag!r}",
            )
        )
    extra_text = line[6:].split(hflag, 1)[1]
    bigmap_extra = None
    if extra_text.strip():
        vals, _ = scan_row(extra_text, 2, 8, path=path, lineno=1, what="numbers (bigmap line-1 values)")
        bigmap_extra = (vals[0], vals[1])
    header.append(Slot("name", line, (name, hflag, bigmap_extra)))

    return name, hflag, bigmap_extra, line1_notes


def _read_lmk_header(lines: list[str], path, header: list[Slot]) -> tuple[dict[str, list[float]], int]:
    """Lines 2-9; returns their values by key and the index of the first line after them."""
    n = len(lines)
    whats = _LMK_WHATS
    # lines 2-9 by position, each a list-directed READ(unit,*) (LITHOS/bigmap write them with the LMK
    # formats of spc-formats.md §4.1); a tag that names another header line is a swapped/duplicated line
    values: dict[str, list[float]] = {}
    kinds = {"size": "ir", "horizon": "iiii", "sig": "rr"}
    rec = Records(lines, path, 1)
    for key in _LMK_ORDER[1:]:
        if rec.at_end:
            raise SpcFormatError(
                path, max(n, 1), f"expected {whats[key]} on line {rec.pos + 1}, found end of file"
            )
        first = rec.pos
        res = rec.read_list(kinds.get(key, "rrr"), what=f"numbers ({whats[key]})")
        if res.nulls or res.slash:
            raise SpcFormatError(
                path, first + 1, f"expected numbers ({whats[key]}), found a null item or '/'"
            )
        v = list(res.values)
        if key == "size" and v[0] < 0:
            raise SpcFormatError(path, first + 1, f"expected an integer QSZ >= 0, found {v[0]!r}")
        tag = res.rest.strip()
        check_tag(tag, key, _LMK_TAGS, path, res.last + 1)
        values[key] = v
        header.append(Slot(key, "\n".join(lines[first : res.last + 1]), tuple(v), tag))

    return values, rec.pos


@dataclass
class _LmkSections:
    """What :func:`_read_lmk_sections` read."""

    section_order: list[str]
    section_text: dict[str, str]
    rows: dict[str, list[tuple[tuple, str]]]
    pictures: list[LandmarkPicture]
    overlaps: list[MapOverlap]
    limbs: list[LandmarkLimb]
    notes: list[tuple[int, str]]
    end_index: int


def _read_lmk_sections(lines: list[str], i: int, path) -> _LmkSections:
    """PICTURES, MAP OVERLAPS, LIMB FITS to END FILE, from line index ``i`` (KOUNT's (A80) records)."""
    n = len(lines)
    section_order: list[str] = []
    section_text: dict[str, str] = {}
    rows: dict[str, list[tuple[tuple, str]]] = {"pictures": [], "overlaps": [], "limbs": []}
    pictures: list[LandmarkPicture] = []
    notes: list[tuple[int, str]] = []  # rows not in LITHOS's columns (rows.read_section_row)
    overlaps: list[MapOverlap] = []
    limbs: list[LandmarkLimb] = []
    state = None
    while i < n:
        ln = lines[i]
        kind = _section_of(ln)
        if kind == "end":
            break
        if kind is not None:
            if kind in section_text:
                raise SpcFormatError(path, i + 1, f"unexpected second {_SECTIONS[kind]} section")
            section_order.append(kind)
            section_text[kind] = ln
            state = kind
        elif state == "pictures":
            pname = ln[:12].strip()
            if not pname:
                raise SpcFormatError(path, i + 1, "expected a picture name in columns 1-12")
            v, r, note = read_section_row(
                ln,
                "(A12,2F10.2,1X,A1)",
                2,
                12,
                path=path,
                lineno=i + 1,
                what="numbers (picture sample, line)",
            )
            if note is not None:
                notes.append((i + 1, note))
            flag = r.strip()
            if len(flag) > 1:
                raise SpcFormatError(path, i + 1, f"expected at most a 1-character flag, found {flag!r}")
            pic = LandmarkPicture(pname, v[0], v[1], flag)
            pictures.append(pic)
            rows["pictures"].append((pic._key(), ln))
        elif state == "overlaps":
            oname = ln[:6].strip()
            if not oname:
                raise SpcFormatError(path, i + 1, "expected a landmark name in columns 1-6")
            v, r, note = read_section_row(
                ln, "(A6,2X,3F12.3)", 3, 8, path=path, lineno=i + 1, what="numbers (map overlap offset)"
            )
            if note is not None:
                notes.append((i + 1, note))
            if r.strip() or (ln[6:8].strip() and not spc_columns()):  # LITHOS's 2X skips columns 7-8
                raise SpcFormatError(path, i + 1, "expected a name and 3 numbers (map overlap)")
            ov = MapOverlap(oname, np.array(v))
            overlaps.append(ov)
            rows["overlaps"].append((ov._key(), ln))
        elif state == "limbs":
            lf = parse_limb_row(ln, path, i + 1, name_width=12, notes=notes)
            limb = LandmarkLimb(lf.name, lf.sample, lf.line, lf.value)
            limbs.append(limb)
            rows["limbs"].append((limb._key(), ln))
        else:
            raise SpcFormatError(path, i + 1, "expected PICTURES, MAP OVERLAPS, LIMB FITS or END FILE")
        i += 1
    if i >= n:
        raise SpcFormatError(path, max(n, 1), "expected END FILE line, found end of file")

    return _LmkSections(section_order, section_text, rows, pictures, overlaps, limbs, notes, i)


def _lmk_line(lmk: Landmark, slot: Slot, pad_header: bool, pad_body: bool) -> str:
    """Regenerate one of lines 1-9 with the LITHOS formats of spc-formats.md §4.1."""
    key = slot.key
    if key == "name":
        if len(lmk.name) > 6:
            raise ValueError(f"landmark name {lmk.name!r} is longer than 6 characters")
        if lmk.hflag not in ("T", "F"):
            raise ValueError(f"HFLAG must be 'T' or 'F', got {lmk.hflag!r}")
        text = lmk.name.ljust(6) + "   " + lmk.hflag
        if lmk.bigmap_extra is not None:
            text += "    " + "".join(fixed_field(v, 8, 4) for v in lmk.bigmap_extra)
        padded = slot.padded if slot.padded is not None else pad_body
        return pad80(text, padded)
    padded = slot.padded if slot.padded is not None else pad_header
    tag = slot.tag or _LMK_TAGS[key]
    letter = exponent_letter(slot.text)
    if key == "size":
        nums = int_field(lmk.qsz, 8) + fixed_field(lmk.scale, 12, 7)
    elif key == "horizon":
        nums = "".join(int_field(h, 10) for h in lmk.horizon)
    elif key == "sig":
        nums = d_fields([lmk.sigkm, lmk.rmslmk], letter)
    else:
        nums = d_fields(getattr(lmk, key), letter)
    return tag_line(nums, tag, padded)


def _row(kind: str, item) -> str:
    """A new section row: ``(A12,2F10.2[,1X,A1])``, ``(A6,2X,3F12.3)`` or ``(A12,3F10.2)``."""
    if kind == "pictures":
        return row_text(item.name, 12, (item.sample, item.line), (10, 2), item.flag)
    if kind == "overlaps":
        offsets = "".join(spc_field(v, 12, 3) for v in item.offset)
        return row_text(item.name, 6, (), (12, 3)) + "  " + offsets
    return row_text(item.name, 12, (item.sample, item.line, item.value), (10, 2))


def format_lmk(lmk: Landmark) -> str:
    """LMK file text; unchanged lines of a parsed file are reproduced byte for byte."""
    src = lmk._source
    if src is None:
        slots = [Slot(k) for k in _LMK_ORDER]
        pad_header, pad_body = True, False
        order = ["pictures", "overlaps", "limbs"]
        section_text: dict[str, str] = {}
        rows: dict[str, list] = {"pictures": [], "overlaps": [], "limbs": []}
    else:
        slots = src.header
        pad_header, pad_body = src.pad_header, src.pad_body
        order = list(src.section_order)
        section_text = src.section_text
        rows = src.rows
    out: list[str] = []
    for slot in slots:
        if slot.text is not None and _landmark_values(lmk, slot.key) == slot.values:
            out.append(slot.text)
        else:
            out.append(_lmk_line(lmk, slot, pad_header, pad_body))

    content = {"pictures": lmk.pictures, "overlaps": lmk.overlaps, "limbs": lmk.limb_fits}
    for kind in ("pictures", "overlaps", "limbs"):
        if kind not in order and content[kind]:
            order.append(kind)
    for kind in order:
        out.append(section_text.get(kind, pad80(_SECTIONS[kind], pad_body)))
        out.extend(
            emit_rows(rows[kind], content[kind], lambda item, kind=kind: pad80(_row(kind, item), pad_body))
        )
    if src is not None:
        out.append(src.end_line)
        out.extend(src.after_end)
    else:
        out.append("END FILE")
    return join_lines(out, src.final_newline if src is not None else True)


def read_lmk(path) -> Landmark:
    """Read ``LMKFILES/<NAME>.LMK``."""
    text = atomic.read_spc_file(path, "LMK")
    return parse_lmk(text, path)


def write_lmk(path, lmk: Landmark, *, overwrite: bool = True, backup: bool = False):
    """Write an LMK file atomically (returns the backup path if one was made)."""
    return atomic.write_text(path, format_lmk(lmk), overwrite=overwrite, backup=backup)
