"""``INIT_LITHOS.TXT`` <-> :class:`Settings`, including the ``DISTORT=`` camera-distortion entries.

Specification: ``shared/docs/spc-formats.md`` §6.1 (parsing rules), §6.2 (keys), §6.4 (``DISTORT=`` syntax and
the template rule), §8 items 15-16 (``BLEMISH=``/``BLEMISHES=``, last matching template wins) and §9.

Rules reproduced from SPC: records are ``(A80)`` so only columns 1-80 count; reading stops at the first line
whose columns 1-3 are ``END`` and that line is required; a key is recognised only when it starts in column 1,
upper case, immediately followed by ``=``; its value is read list-directed from the rest of the line (trailing
comment text ignored); a repeated scalar key takes its last value; ``PCK=``, ``DISTORT=`` and ``BLEMISH=``
repeat. ``DISTORT= 'TEMPLATE' 'MODEL' J`` is followed by J+1 coefficients that may wrap over several lines and
may use letterless exponents (``2.5000000-06``).

Writing is byte-exact for unchanged settings; a changed scalar key rewrites only its last occurrence; changed
repeatable lists are re-emitted where their first entry stood (unchanged entries keep their text); new keys
are inserted before ``END``.  The model equations themselves live in ``spctool.geometry`` (this layer only
decodes).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from spctool.errors import SpcFormatError
from spctool.formats import atomic
from spctool.formats.fortran import list_read, parse_number, read_internal
from spctool.formats.rows import join_lines, source_path, split_lines

__all__ = [
    "DistortModel",
    "Settings",
    "parse_lithos",
    "read_lithos",
    "format_lithos",
    "write_lithos",
]

_KEY = re.compile(r"^([A-Z][A-Z0-9_]*)=")
_INT = re.compile(r"^[+-]?\d+$")
_REPEAT = re.compile(r"^(\d+)\*(.+)$")
_GROUPS = ("pcks", "blemishes", "distortions")


# ----------------------------------------------------------------------------------------------------
# list-directed items with quoted strings


def _items(text: str) -> list[tuple[str, bool]]:
    """Split a list-directed record into (value, quoted) items; ``'...'`` / ``"..."`` strings are one item.

    A doubled quote inside a string stands for one quote; an unquoted ``/`` ends the record.
    Raises ``ValueError`` on an unterminated string.
    """
    out: list[tuple[str, bool]] = []
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c in " \t,":
            i += 1
            continue
        if c in "'\"":
            j = i + 1
            buf = []
            while True:
                if j >= n:
                    raise ValueError(f"unterminated string {text[i:]!r}")
                if text[j] == c:
                    if j + 1 < n and text[j + 1] == c:
                        buf.append(c)
                        j += 2
                        continue
                    break
                buf.append(text[j])
                j += 1
            out.append(("".join(buf), True))
            i = j + 1
            continue
        if c == "/":
            break
        j = i
        while j < n and text[j] not in " \t,":
            j += 1
        out.append((text[i:j], False))
        i = j
    return out


def _fortran_text(value) -> str:
    """A value in list-directed input form: logicals ``.TRUE.``, quoted strings, shortest exact reals."""
    if isinstance(value, (bool, np.bool_)):
        return ".TRUE." if value else ".FALSE."
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return _real_text(float(value))
    if isinstance(value, str):
        return "'" + value.replace("'", "''") + "'"
    if isinstance(value, (list, tuple, np.ndarray)):
        return ", ".join(_fortran_text(v) for v in value)
    raise TypeError(f"cannot write {type(value).__name__} as an INIT_LITHOS value")


def _real_text(value: float) -> str:
    """Shortest text that reads back to exactly ``value`` (``2.5e-06`` -> ``2.5D-06``)."""
    if not np.isfinite(value):
        raise ValueError(f"cannot write non-finite value {value!r}")
    text = repr(float(value))
    if "e" in text:
        mant, exp = text.split("e")
        text = f"{mant}D{exp}"
    return text


# ----------------------------------------------------------------------------------------------------
# DISTORT=


@dataclass(eq=False)
class DistortModel:
    """One ``DISTORT=`` entry (spc-formats.md §6.4): template, model name, order J and P0..PJ."""

    template: str
    model: str
    order: int
    coefficients: np.ndarray

    def __post_init__(self):
        self.template = str(self.template)[:12].ljust(12)
        # getmm: TYPE(KD) is CHARACTER*72 and is compared exactly (IF(TYPE(JD).EQ.'OWEN')): trailing blanks
        # do not count, case and leading blanks do ('owen' and ' OWEN' are no model to SPC)
        self.model = str(self.model)[:72].rstrip()
        self.order = int(self.order)
        self.coefficients = np.array(self.coefficients, dtype=float).ravel()
        if self.order < 0:
            raise ValueError(f"DISTORT order must be >= 0, got {self.order}")
        if self.coefficients.size != self.order + 1:
            raise ValueError(
                f"DISTORT {self.model} J={self.order} needs {self.order + 1} coefficients, "
                f"got {self.coefficients.size}"
            )

    def matches(self, picture_name: str) -> bool:
        """True when, at each of the 12 positions, the template has ``#``, a blank or the name's character."""
        name = str(picture_name)[:12].ljust(12)
        return all(t in "# " or t == c for t, c in zip(self.template, name))

    def __eq__(self, other):
        if not isinstance(other, DistortModel):
            return NotImplemented
        return self._key() == other._key()

    __hash__ = None  # type: ignore[assignment]

    def _key(self) -> tuple:
        return (self.template, self.model, self.order, tuple(float(c) for c in self.coefficients))

    def _lines(self) -> list[str]:
        lines = [f"DISTORT= '{self.template}' '{self.model}'  {self.order}"]
        cur = ""
        for c in self.coefficients:
            tok = _real_text(float(c))
            if cur and len(cur) + 2 + len(tok) > 80:
                lines.append(cur)
                cur = ""
            cur = f"{cur}  {tok}" if cur else tok
        lines.append(cur)
        return lines


# ----------------------------------------------------------------------------------------------------
# Settings


@dataclass
class _Item:
    kind: str  # 'line' | 'key' | 'pcks' | 'blemishes' | 'distortions' | 'end' | 'after'
    lines: list[str]
    index: int  # 0-based line number of the first line
    key: str = ""
    value_start: int = 0


@dataclass
class _LithosSource:
    items: list[_Item]
    lines: list[str]
    key_raw: dict[str, str]
    key_last: dict[str, int]
    pcks: list[str]
    blemishes: list[str]
    distortions: list[DistortModel]
    final_newline: bool
    path: str | None
    warnings: list = field(default_factory=list)  # (1-based line, text): where SPC reads differently


@dataclass(eq=False)
class Settings:
    """The contents of ``INIT_LITHOS.TXT`` (spc-formats.md §6).

    ``keys`` maps each scalar key (without ``=``) to the raw value text of its LAST occurrence (columns
    after ``=`` up to column 80, stripped; trailing comments included).  ``pcks`` and ``blemishes`` hold the
    unquoted strings of every ``PCK=`` and ``BLEMISH=``/``BLEMISHES=`` line, ``distortions`` every
    ``DISTORT=`` entry in file order.  Use the typed accessors to read values the way SPC's list-directed READ
    does.
    """

    keys: dict[str, str] = field(default_factory=dict)
    distortions: list[DistortModel] = field(default_factory=list)
    pcks: list[str] = field(default_factory=list)
    blemishes: list[str] = field(default_factory=list)
    _source: _LithosSource | None = field(default=None, repr=False)

    def __eq__(self, other):
        if not isinstance(other, Settings):
            return NotImplemented
        return (
            self.keys == other.keys
            and self.distortions == other.distortions
            and self.pcks == other.pcks
            and self.blemishes == other.blemishes
        )

    __hash__ = None  # type: ignore[assignment]

    # -- round-trip views
    # -------------------------------------------------------------------------------------
    @property
    def lines(self) -> list[str]:
        """The original lines of the parsed file (empty for new settings)."""
        return list(self._source.lines) if self._source is not None else []

    @property
    def entries(self) -> list[tuple[int, str, str]]:
        """(1-based line, key, raw value) of every recognised scalar-key line, in file order."""
        if self._source is None:
            return []
        out = []
        for item in self._source.items:
            if item.kind == "key":
                out.append((item.index + 1, item.key, item.lines[0][:80][item.value_start :].strip()))
        return out

    # -- typed accessors
    # --------------------------------------------------------------------------------------
    def _raw(self, key: str) -> tuple[str | None, int | None]:
        key = key.rstrip("=")
        raw = self.keys.get(key)
        line = None
        src = self._source
        if raw is not None and src is not None and src.key_raw.get(key) == raw:
            line = src.key_last[key] + 1
        return raw, line

    def _error(self, line, expected: str) -> SpcFormatError:
        path = self._source.path if self._source is not None else None
        return SpcFormatError(path, line, expected)

    def _first(self, key: str) -> tuple[tuple[str, bool] | None, int | None]:
        raw, line = self._raw(key)
        if raw is None:
            return None, line
        try:
            items = _items(raw)
        except ValueError:
            raise self._error(line, f"expected a value for {key.rstrip('=')}=, found {raw!r}") from None
        lead = raw.lstrip(" \t")
        if lead.startswith((",", "/")):
            # READ(LINE(n:80),*) VALUE: a leading comma is a null item and '/' ends the READ -- the
            # variable keeps the program's default
            return None, line
        if not items:
            raise self._error(line, f"expected a value for {key.rstrip('=')}=, found nothing")
        text, quoted = items[0]
        m = None if quoted else _REPEAT.match(text)
        if m is not None:  # r*c: the first of r copies of c
            return (m.group(2), False), line
        if not quoted and re.fullmatch(r"\d+\*", text):  # r*: null values
            return None, line
        return items[0], line

    def get_str(self, key: str, default: str | None = None) -> str | None:
        """The value as a string (quotes removed), or ``default`` when the key is absent."""
        item, _ = self._first(key)
        return default if item is None else item[0]

    def get_float(self, key: str, default: float | None = None) -> float | None:
        """The first value as a real (``D``/letterless exponents accepted)."""
        item, line = self._first(key)
        if item is None:
            return default
        try:
            return parse_number(item[0])
        except ValueError:
            raise self._error(line, f"expected a number for {key.rstrip('=')}=, found {item[0]!r}") from None

    def get_int(self, key: str, default: int | None = None) -> int | None:
        """The first value as an integer (a real is refused, as by Fortran integer input)."""
        item, line = self._first(key)
        if item is None:
            return default
        if not _INT.match(item[0]):
            raise self._error(line, f"expected an integer for {key.rstrip('=')}=, found {item[0]!r}")
        return int(item[0])

    def get_bool(self, key: str, default: bool | None = None) -> bool | None:
        """A Fortran logical: ``.TRUE.``, ``.FALSE.``, ``T``, ``F`` (any case, rest ignored)."""
        item, line = self._first(key)
        if item is None:
            return default
        text = item[0].lstrip(".")[:1].upper()
        if text not in ("T", "F"):
            raise self._error(
                line, f"expected a logical (.TRUE./.FALSE.) for {key.rstrip('=')}=, found {item[0]!r}"
            )
        return text == "T"

    def get_floats(self, key: str, default: list[float] | None = None) -> list[float] | None:
        """All leading numeric values (e.g. ``LMKWTS= 1, 1, 1, 0   WB, WO, WL, WR`` -> [1, 1, 1, 0])."""
        raw, line = self._raw(key)
        if raw is None:
            return default
        try:
            items = _items(raw)
        except ValueError:
            raise self._error(line, f"expected numbers for {key.rstrip('=')}=, found {raw!r}") from None
        out = []
        for text, quoted in items:
            if quoted:
                break
            m = _REPEAT.match(text)  # list-directed r*c: r copies of c
            count, text = (int(m.group(1)), m.group(2)) if m else (1, text)
            try:
                out.extend([parse_number(text)] * count)
            except ValueError:
                break
        if not out:
            raise self._error(line, f"expected numbers for {key.rstrip('=')}=, found {raw!r}")
        return out

    def set(self, key: str, value) -> None:
        """Set a scalar key from a Python value (bool -> ``.TRUE.``, str -> quoted, float -> exact real)."""
        key = key.rstrip("=")
        if key in ("PCK", "DISTORT", "BLEMISH", "BLEMISHES"):
            raise ValueError(f"{key}= repeats: edit Settings.pcks / .distortions / .blemishes instead")
        if not _KEY.match(key + "="):
            raise ValueError(f"not an INIT_LITHOS key: {key!r}")
        self.keys[key] = _fortran_text(value)

    # -- SPC defaults where INIT_LITHOS is silent
    # --------------------------------------------------------------
    @property
    def numlm(self) -> int:
        return self.get_int("NUMLM", 200)

    @property
    def reslm(self) -> float:
        return self.get_float("RESLM", 4.0)

    @property
    def sizlm(self) -> float:
        return self.get_float("SIZLM", 1.5)

    @property
    def piclm(self) -> int:
        return self.get_int("PICLM", 2)

    @property
    def mapvers(self) -> int:
        return self.get_int("MAPVERS", 0)

    @property
    def warnings(self) -> list[tuple[int, str]]:
        """(1-based line, text) where SPC reads this file differently from a careless reader."""
        return list(self._source.warnings) if self._source is not None else []

    def distortion_for(self, picture_name: str) -> DistortModel | None:
        """The distortion model for a picture: the LAST ``DISTORT=`` entry whose template matches."""
        found = None
        for model in self.distortions:
            if model.matches(picture_name):
                found = model
        return found


def _group_of(key: str) -> str | None:
    if key == "PCK":
        return "pcks"
    if key in ("BLEMISH", "BLEMISHES"):
        return "blemishes"
    if key == "DISTORT":
        return "distortions"
    return None


def parse_lithos(text: str, path=None) -> Settings:
    # mirrors getmm (xCommon.f): READ(25,FMT='(A80)') LINE until LINE(1:3)='END'; keys LINE(1:n)='KEY='
    """Parse ``INIT_LITHOS.TXT`` text (spc-formats.md §6); a missing ``END`` line is an error."""
    path = source_path(path)
    lines, final = split_lines(text)
    n = len(lines)
    items: list[_Item] = []
    keys: dict[str, str] = {}
    key_last: dict[str, int] = {}
    lists: dict[str, list] = {g: [] for g in _GROUPS}
    i = 0
    end = None
    warnings: list = []
    if lines and lines[0].startswith(("\ufeff", "\xef\xbb\xbf")):
        bom = lines[0].lstrip("\ufeff\xef\xbb\xbf")
        m0 = _KEY.match(bom)
        if m0 is not None:
            raise SpcFormatError(
                path,
                1,
                f"expected the key {m0.group(1)}= in column 1, found a UTF-8 byte-order mark before it "
                "(SPC would not recognise the key; remove the mark)",
            )
    while i < n:
        line = lines[i]
        rec = line[:80]
        if len(line) > 80 and line[80:].strip() and _KEY.match(rec) and not rec.startswith("DISTORT="):
            warnings.append(
                (i + 1, f"text past column 80 is not read by SPC ((A80) record): {line[80:].strip()[:30]!r}")
            )
        if rec[:3] == "END":
            end = i
            break
        m = _KEY.match(rec)
        if m is None:
            items.append(_Item("line", [line], i))
            i += 1
            continue
        key = m.group(1)
        value = rec[m.end() :]
        group = _group_of(key)
        if group == "distortions":
            model, used = _parse_distort(lines, i, value, path, warnings)
            lists[group].append(model)
            items.append(_Item(group, lines[i : i + used], i, key))
            i += used
            continue
        if group is not None:
            try:
                vals = _items(value)
            except ValueError:
                raise SpcFormatError(path, i + 1, f"expected a quoted string after {key}=") from None
            if not vals:
                raise SpcFormatError(path, i + 1, f"expected a quoted string after {key}=")
            lists[group].append(vals[0][0])
            items.append(_Item(group, [line], i, key))
            i += 1
            continue
        start = m.end() + (len(value) - len(value.lstrip()))
        keys.pop(key, None)  # keep dict order = order of last occurrence
        keys[key] = value.strip()
        key_last[key] = i
        items.append(_Item("key", [line], i, key, start))
        i += 1
    if end is None:
        if n == 0:
            raise SpcFormatError(path, 1, "expected END line, found an empty file")
        raise SpcFormatError(path, n, "expected END line (columns 1-3), found end of file")
    items.append(_Item("end", [lines[end]], end))
    for j in range(end + 1, n):
        items.append(_Item("after", [lines[j]], j))
    source = _LithosSource(
        items=items,
        lines=list(lines),
        key_raw=dict(keys),
        key_last=key_last,
        pcks=list(lists["pcks"]),
        blemishes=list(lists["blemishes"]),
        distortions=[
            DistortModel(d.template, d.model, d.order, d.coefficients.copy()) for d in lists["distortions"]
        ],
        final_newline=final,
        path=path,
        warnings=warnings,
    )
    return Settings(
        keys=keys,
        distortions=lists["distortions"],
        pcks=lists["pcks"],
        blemishes=lists["blemishes"],
        _source=source,
    )


def _parse_distort(lines: list[str], i: int, value: str, path, warnings: list) -> tuple[DistortModel, int]:
    """``DISTORT= 'TEMPLATE' 'MODEL' J`` then P0..PJ, as getmm reads them (xCommon.f getmm).

    getmm: ``READ(LINE(9:80),*) TMPL(KD), TYPE(KD), J`` on the ``(A80)`` key record, then
    ``READ(25,*) (PD(I,KD), I=0,J)`` straight from the file: list-directed, no column limit, over as many
    records as it needs; a ``/`` ends it and null items leave coefficients at their initial 0.
    """
    head = read_internal(
        value, "aai", ["", "", None], path=path, line=i + 1, what="values (DISTORT= 'TEMPLATE' 'MODEL' J)"
    )
    template, model, order = head.values
    if order is None:
        raise SpcFormatError(path, i + 1, "expected DISTORT= 'TEMPLATE' 'MODEL' J, found no J")
    if not 0 <= order <= 100:
        raise SpcFormatError(path, i + 1, f"expected 0 <= J <= 100 for DISTORT=, found {order}")
    need = order + 1
    if i + 1 >= len(lines):
        raise SpcFormatError(path, len(lines), f"expected {need} DISTORT= coefficients, found end of file")
    res = list_read(lines, i + 1, "r" * need, [0.0] * need, path=path, what="DISTORT= coefficients")
    for j in range(i + 1, res.last + 1):
        if len(lines[j]) > 80 and lines[j][80:].strip():
            warnings.append(
                (
                    j + 1,
                    "DISTORT= coefficients continue past column 80 "
                    "(SPC reads them: list-directed, no column limit)",
                )
            )
    if res.slash or res.nulls:
        how = "a '/' ends the list" if res.slash else "null items"
        kept = [k for k, ln in enumerate(res.lines) if ln is None]
        warnings.append(
            (i + 2, f"DISTORT= {how}: P{', P'.join(map(str, kept))} keep the value 0 (SPC getmm READ(25,*))")
        )
    dm = DistortModel(template, model, order, np.array(res.values, dtype=float))
    if dm.model not in _SPC_MODELS:
        known = ", ".join(_SPC_MODELS)
        warnings.append(
            (
                i + 1,
                f"DISTORT= model {dm.model!r} is not one SPC's getmm knows (exact, upper case: {known}); "
                "SPC projects these pictures with the plain pinhole",
            )
        )
    return dm, res.last + 1 - i


#: model names getmm compares TYPE against (xCommon.f getmm), exactly
_SPC_MODELS = ("CUBIC", "RADIAL", "OWEN", "LINESCAN", "APOLLO", "HIRISE")


def format_lithos(settings: Settings) -> str:
    """``INIT_LITHOS.TXT`` text; an unchanged parsed file is reproduced byte for byte."""
    src = settings._source
    current = {"pcks": settings.pcks, "blemishes": settings.blemishes, "distortions": settings.distortions}
    for key, raw in settings.keys.items():
        if not isinstance(raw, str):
            raise TypeError(f"Settings.keys[{key!r}] must be the raw value text (use Settings.set)")

    def entry_lines(group: str, value, pool) -> list[str]:
        if pool is not None:
            k = value._key() if group == "distortions" else value
            found = pool.get(k)
            if found:
                return found.pop(0)
        if group == "distortions":
            return value._lines()
        key = "PCK" if group == "pcks" else "BLEMISH"
        return [f"{key}= {_fortran_text(str(value))}"]

    def emit_group(group: str, pool) -> list[str]:
        out = []
        for value in current[group]:
            out.extend(entry_lines(group, value, pool))
        return out

    if src is None:
        out = [f"{key}= {raw}" for key, raw in settings.keys.items()]
        for group in _GROUPS:
            out.extend(emit_group(group, None))
        out.append("END")
        return join_lines(out, True)

    original = {"pcks": src.pcks, "blemishes": src.blemishes, "distortions": src.distortions}
    changed = {g: list(current[g]) != list(original[g]) for g in _GROUPS}
    pools: dict[str, dict] = {g: {} for g in _GROUPS}
    counters = {g: 0 for g in _GROUPS}
    for item in src.items:
        if item.kind in _GROUPS:
            value = original[item.kind][counters[item.kind]]
            counters[item.kind] += 1
            k = value._key() if item.kind == "distortions" else value
            pools[item.kind].setdefault(k, []).append(item.lines)
    emitted: set[str] = set()
    out: list[str] = []
    for item in src.items:
        kind = item.kind
        if kind in ("line", "after"):
            out.extend(item.lines)
        elif kind == "key":
            key = item.key
            if key not in settings.keys:
                continue
            raw = settings.keys[key]
            if item.index == src.key_last[key] and raw != src.key_raw[key]:
                out.append(item.lines[0][: item.value_start] + raw)
            else:
                out.extend(item.lines)
        elif kind in _GROUPS:
            if not changed[kind]:
                out.extend(item.lines)
            elif kind not in emitted:
                out.extend(emit_group(kind, pools[kind]))
                emitted.add(kind)
        elif kind == "end":
            for key, raw in settings.keys.items():
                if key not in src.key_raw:
                    out.append(f"{key}= {raw}")
            for group in _GROUPS:
                if changed[group] and group not in emitted:
                    out.extend(emit_group(group, pools[group]))
                    emitted.add(group)
            out.extend(item.lines)
    return join_lines(out, src.final_newline)


def read_lithos(path) -> Settings:
    """Read ``INIT_LITHOS.TXT``."""
    text = atomic.read_spc_file(path, "INIT_LITHOS")
    return parse_lithos(text, path)


def write_lithos(path, settings: Settings, *, overwrite: bool = True, backup: bool = False):
    """Write ``INIT_LITHOS.TXT`` atomically (returns the backup path if one was made)."""
    return atomic.write_text(path, format_lithos(settings), overwrite=overwrite, backup=backup)
