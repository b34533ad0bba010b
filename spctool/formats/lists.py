"""SPC list files: ``PICTLIST.TXT``, ``LMRKLIST.TXT`` and ``LMRKLISTX.TXT`` <-> dataclasses.

Specification: ``shared/docs/spc-formats.md`` §7.1 (PICTLIST, ``(A13)``: column 1 flag, columns 2-13 name;
flags blank = in use, ``!`` = tucked out, ``#`` = skipped), §7.2 (LMRKLIST, ``(A6)``; ``#`` lines and names
starting with ``X`` are skipped), §7.3 (LMRKLISTX: name in columns 1-6, then list-directed QSZ, number of
pictures, VLM(3), SCALE), §0.2 (names) and §9.  Every list ends with an ``END`` line, which is required.

Byte-exact: lines whose entry is unchanged keep their text (comments, blank lines and text after the ``END``
line are preserved); changed or new entries are written in the layouts above.  The same variants
(``PICTLISTX.TXT``, ``USED_PICS.TXT``, ``LMRKLISTR.TXT`` ...) share these layouts.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from spctool.errors import SpcFormatError
from spctool.formats import atomic
from spctool.formats.fortran import format_d, is_number, read_internal
from spctool.formats.rows import (
    RowPool,
    as_shaped,
    float_tuple,
    join_lines,
    source_path,
    split_lines,
)

__all__ = [
    "PictureListEntry",
    "PictureList",
    "parse_pictlist",
    "read_pictlist",
    "format_pictlist",
    "write_pictlist",
    "LandmarkList",
    "parse_lmrklist",
    "read_lmrklist",
    "format_lmrklist",
    "write_lmrklist",
    "LandmarkListXEntry",
    "LandmarkListX",
    "parse_lmrklistx",
    "read_lmrklistx",
    "format_lmrklistx",
    "write_lmrklistx",
]

_PICT_FLAGS = ("", "!", "#")


@dataclass
class _ListSource:
    """Layout of a parsed list: ('entry', original key, text) or ('other', None, text) lines, END and
    after."""

    layout: list[tuple[str, tuple | None, str]]
    end_line: str
    after_end: list[str]
    final_newline: bool
    warnings: list = field(default_factory=list)


def _emit(layout_src: _ListSource | None, keys: list[tuple], make_text) -> str:
    """Emit a list: non-entry lines in place, entries in current order reusing unchanged original text."""
    out: list[str] = []
    if layout_src is None:
        out = [make_text(i) for i in range(len(keys))]
        out.append("END")
        return join_lines(out, True)
    original = [k for kind, k, _ in layout_src.layout if kind == "entry"]
    if original == keys:  # unchanged: the original lines
        out = [t for _, _, t in layout_src.layout]
        out.append(layout_src.end_line)
        out.extend(layout_src.after_end)
        return join_lines(out, layout_src.final_newline)
    pool = RowPool([(k, t) for kind, k, t in layout_src.layout if kind == "entry"])
    nxt = 0
    for kind, _, text in layout_src.layout:
        if kind == "other":
            out.append(text)
        elif nxt < len(keys):
            found = pool.take(keys[nxt])
            out.append(found if found is not None else make_text(nxt))
            nxt += 1
    for i in range(nxt, len(keys)):
        found = pool.take(keys[i])
        out.append(found if found is not None else make_text(i))
    out.append(layout_src.end_line)
    out.extend(layout_src.after_end)
    return join_lines(out, layout_src.final_newline)


def _missing_end(path, n: int) -> SpcFormatError:
    if n == 0:
        return SpcFormatError(path, 1, "expected END line, found an empty file")
    return SpcFormatError(path, n, "expected END line, found end of file")


# ==================================================================================================
# PICTLIST.TXT


@dataclass
class PictureListEntry:
    """One PICTLIST line: picture name and flag ('' in use, '!' tucked out, '#' skipped)."""

    name: str
    flag: str = ""

    def __post_init__(self):
        self.flag = (self.flag or "").strip()
        if self.flag not in _PICT_FLAGS:
            raise ValueError(f"PICTLIST flag must be '', '!' or '#', got {self.flag!r}")

    def _key(self) -> tuple:
        return (self.name, self.flag)


@dataclass
class PictureList:
    """``PICTLIST.TXT`` (and variants): entries in file order."""

    entries: list[PictureListEntry] = field(default_factory=list)
    _source: _ListSource | None = field(default=None, repr=False, compare=False)

    @property
    def active_names(self) -> list[str]:
        """Names of the pictures in use (blank flag)."""
        return [e.name for e in self.entries if e.flag == ""]

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.entries]


def parse_pictlist(text: str, path=None) -> PictureList:
    """Parse PICTLIST text: ``(A13)`` lines up to the required ``END`` line (columns 1-3)."""
    path = source_path(path)
    lines, final = split_lines(text)
    layout: list[tuple[str, tuple | None, str]] = []
    entries: list[PictureListEntry] = []
    warnings: list[tuple[int, str]] = []
    # globalStat: read(20,fmt='(a13)') xname; '!' or '#' in column 1 skips; IF(xname(1:3).ne.'END') the
    # picture xname(2:13) is in use -- whatever else column 1 holds
    for i, line in enumerate(lines):
        if line.startswith(("\ufeff", "\xef\xbb\xbf")):
            raise SpcFormatError(
                path,
                i + 1,
                "expected a flag in column 1, found a UTF-8 byte-order mark (SPC reads it as text)",
            )
        if line[:1] not in ("!", "#") and line[:3] == "END":
            src = _ListSource(layout, line, lines[i + 1 :], final)
            src.warnings = warnings
            return PictureList(entries, src)
        if not line.strip():
            warnings.append((i + 1, "blank line: SPC reads it as a picture with a blank name"))
            layout.append(("other", None, line))
            continue
        flag = line[0].strip()
        if flag not in _PICT_FLAGS:
            warnings.append(
                (
                    i + 1,
                    f"column 1 holds {flag!r}: SPC treats the picture as in use, named by columns 2-13 "
                    f"({line[1:13].strip()!r})",
                )
            )
            flag = ""
        name = line[1:13].strip()
        if not name:
            raise SpcFormatError(path, i + 1, "expected a picture name in columns 2-13")
        entry = PictureListEntry(name, flag)
        entries.append(entry)
        layout.append(("entry", entry._key(), line))
    raise _missing_end(path, len(lines))


def format_pictlist(plist: PictureList) -> str:
    entries = plist.entries
    for e in entries:
        if len(e.name) > 12:
            raise ValueError(f"picture name {e.name!r} is longer than 12 characters")

    def make(i: int) -> str:
        e = entries[i]
        return (e.flag or " ") + e.name

    return _emit(plist._source, [e._key() for e in entries], make)


def read_pictlist(path) -> PictureList:
    return parse_pictlist(atomic.read_spc_file(path, "PICTLIST"), path)


def write_pictlist(path, plist: PictureList, *, overwrite: bool = True, backup: bool = False):
    return atomic.write_text(path, format_pictlist(plist), overwrite=overwrite, backup=backup)


# ==================================================================================================
# LMRKLIST.TXT


@dataclass
class LandmarkList:
    """``LMRKLIST.TXT`` (and variants).

    ``names`` holds every landmark line in order, including ``X``-names; ``#`` comment lines and blank lines
    are kept for the round trip but are not names.  ``active_names`` drops names starting with ``X``
    (spc-formats.md §0.2, §7.2).
    """

    names: list[str] = field(default_factory=list)
    _source: _ListSource | None = field(default=None, repr=False, compare=False)

    @property
    def active_names(self) -> list[str]:
        return [n for n in self.names if not n.startswith("X")]

    @property
    def comments(self) -> list[str]:
        """The ``#`` lines of the parsed file."""
        if self._source is None:
            return []
        return [t for kind, _, t in self._source.layout if kind == "other" and t.startswith("#")]


def parse_lmrklist(text: str, path=None) -> LandmarkList:
    """Parse LMRKLIST text: one ``(A6)`` name a line up to the required ``END`` line."""
    path = source_path(path)
    lines, final = split_lines(text)
    layout: list[tuple[str, tuple | None, str]] = []
    names: list[str] = []
    # globalCoverage: read(15,fmt='(A6)') NAME; '#' in column 1 skips; NAME(1:3).ne.'END' is a landmark
    for i, line in enumerate(lines):
        name = line[:6].strip()
        if line[:1] != "#" and line[:3] == "END":
            return LandmarkList(names, _ListSource(layout, line, lines[i + 1 :], final))
        if line.startswith("#") or not line.strip():
            layout.append(("other", None, line))
            continue
        if not name:
            raise SpcFormatError(path, i + 1, "expected a landmark name in columns 1-6")
        names.append(name)
        layout.append(("entry", (name,), line))
    raise _missing_end(path, len(lines))


def format_lmrklist(llist: LandmarkList) -> str:
    names = llist.names
    for name in names:
        if len(name) > 6 or not name.strip():
            raise ValueError(f"landmark name {name!r} must have 1 to 6 characters")
    return _emit(llist._source, [(n,) for n in names], lambda i: names[i])


def read_lmrklist(path) -> LandmarkList:
    return parse_lmrklist(atomic.read_spc_file(path, "LMRKLIST"), path)


def write_lmrklist(path, llist: LandmarkList, *, overwrite: bool = True, backup: bool = False):
    return atomic.write_text(path, format_lmrklist(llist), overwrite=overwrite, backup=backup)


# ==================================================================================================
# LMRKLISTX.TXT


@dataclass(eq=False)
class LandmarkListXEntry:
    """One LMRKLISTX line: name, QSZ, number of pictures, VLM (km, body frame), SCALE (km)."""

    name: str
    qsz: int
    npictures: int
    vlm: np.ndarray
    scale: float

    def __post_init__(self):
        self.qsz = int(self.qsz)
        self.npictures = int(self.npictures)
        self.vlm = as_shaped(self.vlm, (3,), "vlm")
        self.scale = float(self.scale)

    def __eq__(self, other):
        if not isinstance(other, LandmarkListXEntry):
            return NotImplemented
        return self._key() == other._key()

    __hash__ = None  # type: ignore[assignment]

    def _key(self) -> tuple:
        return (self.name, self.qsz, self.npictures) + float_tuple(self.vlm) + (float(self.scale),)


@dataclass
class LandmarkListX:
    """``LMRKLISTX.TXT``: entries in file order (iterable and indexable like a list)."""

    entries: list[LandmarkListXEntry] = field(default_factory=list)
    _source: _ListSource | None = field(default=None, repr=False, compare=False)

    def __iter__(self):
        return iter(self.entries)

    def __len__(self) -> int:
        return len(self.entries)

    def __getitem__(self, index):
        return self.entries[index]

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.entries]


def parse_lmrklistx(text: str, path=None) -> LandmarkListX:
    """Parse LMRKLISTX text up to the required ``END`` line, as bigmap (``LMKLX=.TRUE.``) reads it:
    ``READ(69,FMT='(A80)') LINE``; ``IF(LINE(1:3).EQ.'END')`` ends the list;
    ``READ(LINE(7:80),*) K0,J,(V1(K),K=1,3),S1``; ``NAME=LINE(1:6)``.

    So: text past column 80 is not read (a warning when it holds something); the six values are read
    list-directed, with ``r*c`` repeats, ``NaN`` and text after them (a warning when that text is a
    number); a null item or ``/`` keeps the previous line's value (bigmap's variable, warned; refused on
    the first line, where it is undefined).  Where bigmap stops -- a blank line, a ``#`` line, a QSZ or
    picture count that is not an integer -- the line is refused.
    """
    path = source_path(path)
    lines, final = split_lines(text)
    layout: list[tuple[str, tuple | None, str]] = []
    entries: list[LandmarkListXEntry] = []
    warnings: list[tuple[int, str]] = []
    what = "numbers (QSZ, pictures, VLM(3), SCALE)"
    previous = None
    for i, line in enumerate(lines):
        record = line[:80]  # CHARACTER*80 LINE
        if record[:3] == "END":
            src = _ListSource(layout, line, lines[i + 1 :], final)
            src.warnings = warnings
            return LandmarkListX(entries, src)
        if not record.strip() or record.startswith("#"):
            found = "a blank line" if not record.strip() else "a '#' line"
            raise SpcFormatError(
                path,
                i + 1,
                f"expected a maplet line or END, found {found}: bigmap reads every line up to END as "
                "NAME + READ(LINE(7:80),*) QSZ, pictures, VLM(3), SCALE and stops here",
            )
        name = record[:6].strip()
        if not name:
            raise SpcFormatError(path, i + 1, "expected a landmark name in columns 1-6")
        res = read_internal(record[6:], "iirrrr", previous, path=path, line=i + 1, what=what)
        if any(v is None for v in res.values):
            raise SpcFormatError(
                path, i + 1, f"expected 6 {what}: a null item or '/' on line 1 leaves a value undefined"
            )
        if res.nulls or res.slash:
            warnings.append((i + 1, "a null item or '/': bigmap keeps the previous line's value there"))
        if any(is_number(t) for t in res.rest.replace(",", " ").split()[:1]):
            warnings.append((i + 1, f"text after the 6 values is not read by bigmap ({res.rest.strip()!r})"))
        if line[80:].strip():
            warnings.append((i + 1, f"text past column 80 is not read by bigmap ({line[80:].strip()!r})"))
        vals = res.values
        if any(v != v for v in vals[2:]):
            warnings.append((i + 1, "NaN in VLM or SCALE: bigmap's distance test never skips this maplet"))
        previous = list(vals)
        entry = LandmarkListXEntry(name, int(vals[0]), int(vals[1]), np.array(vals[2:5]), vals[5])
        entries.append(entry)
        layout.append(("entry", entry._key(), line))
    raise _missing_end(path, len(lines))


def format_lmrklistx(xlist: LandmarkListX) -> str:
    entries = list(xlist.entries)
    for e in entries:
        if len(e.name) > 6:
            raise ValueError(f"landmark name {e.name!r} is longer than 6 characters")

    def make(i: int) -> str:
        e = entries[i]
        numbers = " ".join(format_d(v, 13, 6).strip() for v in (*e.vlm, e.scale))
        return f"{e.name.ljust(6)} {e.qsz} {e.npictures} {numbers}"

    return _emit(xlist._source, [e._key() for e in entries], make)


def read_lmrklistx(path) -> LandmarkListX:
    return parse_lmrklistx(atomic.read_spc_file(path, "LMRKLISTX"), path)


def write_lmrklistx(path, xlist: LandmarkListX, *, overwrite: bool = True, backup: bool = False):
    return atomic.write_text(path, format_lmrklistx(xlist), overwrite=overwrite, backup=backup)
