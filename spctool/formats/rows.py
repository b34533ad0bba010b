"""Text rows of SPC's line-oriented files: the machinery SUM, NOM, LMK, INIT_LITHOS and the lists share.

Specification: ``shared/docs/spc-formats.md`` §0 (conventions: Fortran numbers, 80-column records, the
byte-exact round trip) and §8 items 9–11 (tag columns, foreign writers).  SPC reads these files
list-directed, line by line; spctool reads them the same way and rewrites them byte for byte, regenerating
only the lines whose values changed.  What that takes, for every format module:

* lines: :func:`split_lines` / :func:`join_lines` (CR, LF or CRLF; whether the file ended with a newline),
  80-column blank padding (:func:`is_padded`, :func:`majority_padded`, :func:`pad80`), the tag at column 64
  (:func:`tag_line`, :func:`check_tag`: a tag naming another header line is a swapped line);
* numbers: list-directed reads of a row (:func:`scan_numbers`; :func:`scan_row` with the fixed-width
  fallback for fields that abut), the exponent letter and decimals of the line being replaced
  (:func:`exponent_letter`, :func:`decimals_of`), gfortran ``Iw`` / ``Fw.d`` / ``Dw.d`` fields that stay
  separable (:func:`int_field`, :func:`fixed_field`, :func:`d_fields`, :func:`row_text`);
* rewriting: :class:`Slot` (one parsed header line), :class:`RowPool` and :func:`emit_rows` (a section row
  whose values are unchanged keeps its original text), :func:`fields_equal`;
* section rows in LITHOS's fixed columns (issue #40): :func:`read_section_row` reads a row both ways --
  list-directed (what its writer meant) and with LITHOS's formatted READ (:func:`fortran.formatted_read`)
  -- and says when they differ; :func:`spc_columns` / :func:`spc_columns_mode` (``--spc-columns``) take
  LITHOS's reading; :func:`spc_field` writes a field LITHOS reads back (``row_text``).
"""

from __future__ import annotations

import os
import re
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

import numpy as np

from spctool.errors import SpcFormatError
from spctool.formats.fortran import (
    FormattedReadError,
    format_d,
    format_f,
    format_i,
    formatted_read,
    is_number,
    parse_format,
    parse_number,
)

__all__ = [
    "TOKEN",
    "RowPool",
    "Slot",
    "as_shaped",
    "COLUMNS_NOTE",
    "check_tag",
    "column_notes",
    "d_fields",
    "decimals_of",
    "emit_rows",
    "exponent_letter",
    "fields_equal",
    "fixed_field",
    "float_tuple",
    "int_field",
    "is_integral",
    "is_padded",
    "join_lines",
    "majority_padded",
    "pad80",
    "row_text",
    "same_value",
    "scan_fixed_fields",
    "scan_numbers",
    "read_section_row",
    "scan_row",
    "spc_columns",
    "spc_columns_mode",
    "spc_field",
    "use_spc_columns",
    "source_path",
    "split_lines",
    "tag_line",
]


TOKEN = re.compile(r"[^\s,]+")


_FIXED = re.compile(r"^[+-]?\d*\.\d*$")


_EXP_LETTER = re.compile(r"\d([EeDdQq])[+-]?\d")


def check_tag(tag: str, key: str, tags: dict, path, lineno: int) -> None:
    """A tag naming another header line: the line is swapped or duplicated (SPC reads by position)."""
    if not tag:
        return
    t = " ".join(tag.upper().split())
    for other, name in tags.items():
        if other != key and t == name:
            raise SpcFormatError(
                path,
                lineno,
                f"expected the {tags[key]} line here (SPC reads this line by position as {tags[key]}), "
                f"found the tag {name}: a swapped or duplicated line",
            )


def split_lines(text: str) -> tuple[list[str], bool]:
    """Split file text into lines (no terminators) and whether the last line ended with a newline."""
    text = text.replace("\r\n", "\n").replace("\r", "\n")
    if text == "":
        return [], False
    final = text.endswith("\n")
    body = text[:-1] if final else text
    return body.split("\n"), final


def join_lines(lines: list[str], final_newline: bool) -> str:
    if not lines:
        return ""
    return "\n".join(lines) + ("\n" if final_newline else "")


def is_padded(line: str) -> bool:
    """True for a line blank-padded to exactly 80 columns (the Hayabusa / ``A20`` style)."""
    return len(line) == 80 and line.endswith(" ")


def majority_padded(lines: list[str], default: bool) -> bool:
    lines = [ln for ln in lines if ln.strip()]
    if not lines:
        return default
    return 2 * sum(is_padded(ln) for ln in lines) > len(lines)


def pad80(text: str, padded: bool) -> str:
    return text.ljust(80) if padded else text


def exponent_letter(line: str | None, default: str = "D") -> str:
    """Exponent letter (``D`` or ``E``) used by the numbers of an original line."""
    if not line:
        return default
    m = _EXP_LETTER.search(line)
    if m is None:
        return default
    letter = m.group(1).upper()
    return "E" if letter == "E" else "D"


def scan_numbers(
    text: str,
    count: int,
    *,
    path,
    lineno: int,
    what: str,
    strict: bool = True,
) -> tuple[list[float], str]:
    """List-directed read of ``count`` numbers from ``text``; return them and the raw text after them.

    With ``strict`` a further number after the ``count`` values is an error (a wrong number count), which
    SPC's own reader would silently accept; trailing non-numeric text (the tag) is returned.
    """
    values: list[float] = []
    end = 0
    for m in TOKEN.finditer(text):
        tok = m.group()
        if len(values) == count:
            if strict and is_number(tok):
                raise SpcFormatError(
                    path, lineno, f"expected {count} {what}, found more than {count} numbers"
                )
            break
        try:
            values.append(parse_number(tok))
        except ValueError:
            found = f"found {len(values)} then {tok!r}" if values else f"found {tok!r}"
            raise SpcFormatError(path, lineno, f"expected {count} {what}, {found}") from None
        end = m.end()
    if len(values) < count:
        raise SpcFormatError(path, lineno, f"expected {count} {what}, found {len(values)}")
    return values, text[end:]


def scan_fixed_fields(text: str, count: int, width: int) -> tuple[list[float], str] | None:
    """Fixed-width fallback (``countFwidth.d``) for fields that abut (e.g. ``-100000.00-100000.00``)."""
    if len(text) < count * width:
        return None
    values = []
    for k in range(count):
        field_text = text[k * width : (k + 1) * width]
        try:
            values.append(parse_number(field_text))
        except ValueError:
            return None
    return values, text[count * width :]


_PLAIN = r"([+-]?(?:\d+(?:\.\d*)?|\.\d+))"  # unambiguous: no quadratic backtracking on long digit runs


_FAST_ROW = {n: re.compile(r"\s*" + r"\s+".join([_PLAIN] * n) + r"(?=\s|\Z)(.*)\Z", re.S) for n in (2, 3)}


def scan_row(text: str, count: int, width: int, *, path, lineno: int, what: str) -> tuple[list[float], str]:
    """Numbers of a section row: list-directed, falling back to fixed ``Fwidth`` columns."""
    fast = _FAST_ROW.get(count)
    if fast is not None:  # plain blank-separated decimals (every SPC-written row): one regex, no tokenising
        m = fast.match(text)
        if m is not None:
            rest = m.group(count + 1)
            first = rest.split(None, 1)
            if not first or not is_number(first[0]):
                return [float(m.group(k)) for k in range(1, count + 1)], rest
    try:
        return scan_numbers(text, count, path=path, lineno=lineno, what=what)
    except SpcFormatError:
        fixed = scan_fixed_fields(text, count, width)
        if fixed is None:
            raise
        return fixed


def is_integral(value: float) -> bool:
    return float(value).is_integer()


def decimals_of(line: str | None, default: int) -> int:
    """Number of decimals of the first fixed-point token of a line (``37.0371`` -> 4)."""
    if not line:
        return default
    for tok in TOKEN.findall(line):
        if _FIXED.match(tok):
            return len(tok.split(".", 1)[1])
    return default


def tag_line(numbers: str, tag: str, padded: bool) -> str:
    """``numbers`` (60 columns) + 3 blanks + tag at column 64, optionally padded to 80 columns."""
    return pad80(numbers.ljust(60) + "   " + tag, padded)


def d_fields(values, letter: str = "D", width: int = 20, decimals: int = 10) -> str:
    return "".join(format_d(float(v), width, decimals, letter) for v in values)


def float_tuple(values) -> tuple[float, ...]:
    return tuple(float(v) for v in np.asarray(values, dtype=float).ravel())


def as_shaped(value, shape: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.array(value, dtype=float)
    if arr.size != int(np.prod(shape)):
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    return arr.reshape(shape)


def same_value(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if a is None or b is None:
            return False
        return np.array_equal(np.asarray(a), np.asarray(b))
    return a == b


def fields_equal(a, b, names: tuple[str, ...]) -> bool:
    return all(same_value(getattr(a, n), getattr(b, n)) for n in names)


def emit_rows(rows: list[tuple[tuple, str]], items, make) -> list[str]:
    """Texts for section rows: the original texts when nothing changed, else unchanged rows keep theirs."""
    keys = [item._key() for item in items]
    if len(keys) == len(rows) and all(k == r[0] for k, r in zip(keys, rows)):
        return [r[1] for r in rows]
    pool = RowPool(rows)
    out = []
    for item, key in zip(items, keys):
        text = pool.take(key)
        out.append(text if text is not None else make(item))
    return out


class RowPool:
    """Original row texts keyed by their parsed values; a row whose values are unchanged reuses its text."""

    def __init__(self, rows: list[tuple[tuple, str]]):
        self._pool: dict[tuple, list[str]] = {}
        for key, text in rows:
            self._pool.setdefault(key, []).append(text)

    def take(self, key: tuple) -> str | None:
        texts = self._pool.get(key)
        if texts:
            return texts.pop(0)
        return None


@dataclass
class Slot:
    """One parsed header line: its key, original text and the values parsed from it."""

    key: str
    text: str | None = None
    values: tuple | None = None
    tag: str = ""

    @property
    def padded(self) -> bool | None:
        return None if self.text is None else is_padded(self.text)


def source_path(path):
    return os.fspath(path) if path is not None else None


def row_text(name: str, width: int, values, decimals_width: tuple[int, int], flag: str = "") -> str:
    if len(name) > width:
        raise ValueError(f"name {name!r} is longer than {width} characters")
    w, d = decimals_width
    text = name.ljust(width) + "".join(spc_field(v, w, d) for v in values)  # LITHOS's columns (#40)
    if flag:
        text += " " + flag
    return text


def int_field(value: int, width: int) -> str:
    """gfortran ``Iw``, one column wider when the number would fill (abut) or overflow the field."""
    text = format_i(int(value), width)
    if not text.startswith(" "):
        text = " " + str(int(value))
    return text


def fixed_field(value: float, width: int, decimals: int) -> str:
    """gfortran ``Fw.d``, except that a value filling all ``w`` columns (it would abut the previous field, or
    overflow into asterisks) is written one column wider, so that a list-directed read still separates it."""
    text = format_f(float(value), width, decimals)
    if not text.startswith(" "):
        text = " " + f"{float(value):.{decimals}f}"
    return text


# ---------------------------------------------------------------------------------------------------------
# section rows in SPC's columns (issue #40): LITHOS reads a LANDMARKS / PICTURES / MAP OVERLAPS / LIMB FITS
# row with a formatted READ -- (A6,2F10.2,1X,A1), (A6,3F10.2), (A12,2F10.2,1X,A1), (A6,2X,3F12.3),
# (A12,3F10.2) [BIN] -- not list-directed.  A row whose numbers sit in those columns reads the same both
# ways; a row that does not (single blanks, no decimal point, tabs, GIANT's 27-column rows) is read by
# spctool as its writer meant, with a warning giving LITHOS's reading, unless --spc-columns asks for
# LITHOS's reading itself.

_SPC_COLUMNS: ContextVar[bool] = ContextVar("spc_columns", default=False)

#: the phrase every row-column warning carries (a stage finds its warnings by it)
COLUMNS_NOTE = "not in SPC's columns"


def spc_columns() -> bool:
    """True while section rows are read exactly as LITHOS reads them (``--spc-columns``)."""
    return _SPC_COLUMNS.get()


@contextmanager
def spc_columns_mode(on: bool = True):
    """Read section rows in SPC's fixed columns (``on``) or as their writer meant, inside the block."""
    token = _SPC_COLUMNS.set(bool(on))
    try:
        yield
    finally:
        _SPC_COLUMNS.reset(token)


def use_spc_columns(on: bool) -> None:
    """Read section rows in SPC's columns (``on``) from now on in this context (a batch worker process)."""
    _SPC_COLUMNS.set(bool(on))


def column_notes(warnings) -> list[tuple[int | None, str]]:
    """The row-column warnings among a parsed file's ``(line, text)`` warnings."""
    return [(ln, text) for ln, text in warnings or () if COLUMNS_NOTE in text]


def _show(values, flag: str | None) -> str:
    text = ", ".join(f"{v:.10g}" for v in values)
    return text + ("" if flag is None else f" flag {flag!r}" if flag else " no flag")


_CANONICAL_FIELD = re.compile(r" +[+-]?\d+\.\d+\Z")
_FORMATS: dict[str, tuple] = {}


def _parsed_format(fmt: str) -> tuple:
    items = _FORMATS.get(fmt)
    if items is None:
        items = _FORMATS[fmt] = parse_format(fmt)
    return items


def _canonical_row(line: str, items, has_flag: bool):
    """``(values, rest, None)`` for a row exactly as gfortran writes it (each ``F`` field a blank-led
    ``ddd.dd`` filling its columns, then nothing or `` X``), where list-directed and formatted READs agree
    without being run; else None."""
    pos, values = 0, []
    for kind, width, _ in items[:-2] if has_flag else items:
        if kind == "F":
            text = line[pos : pos + width]
            if len(text) != width or _CANONICAL_FIELD.match(text) is None:
                return None
            values.append(float(text))
        pos += width
    rest = line[pos:]
    if rest.strip() and not (has_flag and rest[0] == " " and len(rest.rstrip()) == 2):
        return None
    return values, rest, None


def read_section_row(
    line: str,
    fmt: str,
    count: int,
    start: int,
    *,
    path,
    lineno: int,
    what: str,
    short_ok: bool = False,
) -> tuple[list[float], str, str | None]:
    """Numbers of one section row: ``(values, rest, note)``.

    ``fmt`` is LITHOS's READ format of the row, ``count`` its number of ``F`` items and ``start`` the
    column (0-based) where they begin.  The writer's reading is list-directed from ``start`` (``rest`` is
    the text after the numbers: the flag); ``short_ok`` lets a row hold ``count - 1`` numbers, the last
    then 0 (GIANT's two-number LIMB FITS rows).  LITHOS's reading is :func:`formatted_read` of ``fmt``.
    Both equal: no note.  They differ: the writer's numbers, and ``note`` gives both readings.  Only
    LITHOS's succeeds: its numbers when every field holds a number with its point (fields that abut, as
    gfortran writes a full field), else the list-directed error naming LITHOS's reading.  Under
    :func:`spc_columns` LITHOS's reading is returned (``rest`` is the ``A1`` flag) and a row where its
    READ stops is an error.
    """
    items = _parsed_format(fmt)
    f_items = [k for k, _, _ in items if k == "F"]
    has_flag = items[-1][0] == "A" and len(items) > 1 and items[-2][0] == "X"
    canonical = _canonical_row(line, items, has_flag)
    if canonical is not None:  # every field blank-led 'ddd.dd' in its columns: both readings are these
        return canonical
    try:
        fixed = formatted_read(line, items)
        lith_vals = [v for (k, _, _), v in zip([it for it in items if it[0] != "X"], fixed) if k == "F"]
        lith_flag = fixed[-1].strip() if has_flag else ""
        stop = None
    except FormattedReadError as exc:
        lith_vals, lith_flag, stop = None, "", exc
    if spc_columns():
        if stop is not None:
            raise SpcFormatError(
                path,
                lineno,
                f"expected {what} in SPC's columns {fmt} (--spc-columns): LITHOS's READ stops at column "
                f"{stop.column} ({stop.field!r})",
            )
        return lith_vals, (" " + lith_flag if lith_flag else ""), None
    assert len(f_items) == count
    try:
        meant, rest = scan_numbers(line[start:], count, path=path, lineno=lineno, what=what)
    except SpcFormatError as exc:
        meant = None
        error = exc
        if short_ok:
            try:
                part, rest = scan_numbers(line[start:], count - 1, path=path, lineno=lineno, what=what)
            except SpcFormatError:
                part = None
            if part is not None and not rest.strip():
                meant = part + [0.0]
    if meant is not None:
        flag = rest.strip() if has_flag else None
        same = lith_vals is not None and lith_vals == meant and (not has_flag or flag == lith_flag)
        if same:
            return meant, rest, None
        flags = has_flag and flag != lith_flag
        lithos = (
            f"LITHOS reads {_show(lith_vals, lith_flag if flags else None)}"
            if stop is None
            else f"LITHOS's READ stops at column {stop.column} ({stop.field!r})"
        )
        note = (
            f"{what} {COLUMNS_NOTE} {fmt}: spctool reads {_show(meant, flag if flags else None)} as written; "
            f"{lithos} "
            "(--spc-columns reads as LITHOS)"
        )
        return meant, rest, note
    if lith_vals is None:
        raise error
    pos, filled = 0, True
    for kind, width, _ in items:
        if kind == "F":
            text = line[pos : pos + width]
            filled = filled and len(text) == width and "." in text and bool(text.strip())
        pos += width
    end = sum(w for k, w, _ in (items[:-2] if has_flag else items))
    if not filled:  # a missing or unpointed field: the writer's numbers are unknown -- refused, as before
        raise SpcFormatError(
            path,
            lineno,
            f"{error.expected} (LITHOS's READ {fmt} gives {_show(lith_vals, None)}; "
            "--spc-columns reads it so)",
        )
    return lith_vals, line[end:], None


def spc_field(value: float, width: int, decimals: int) -> str:
    """A ``Fw.d`` field exactly ``width`` columns wide that LITHOS's formatted READ reads back.

    gfortran's ``Fw.d`` when it fits (a value filling all ``w`` columns abuts the previous field: a
    formatted READ still separates it; spctool reads such rows in SPC's columns too); NaN and Infinity as
    gfortran writes them; a value too large for ``Fw.d`` (gfortran would write asterisks) in the
    ``E`` form with as many digits as fit after a blank (``F`` input accepts an exponent; ``-1.6208E7``).
    """
    value = float(value)
    if value != value:
        return "NaN".rjust(width)
    if value in (float("inf"), float("-inf")):
        word = ("-" if value < 0 else "") + ("Infinity" if width >= 8 + (value < 0) else "Inf")
        return word.rjust(width)
    text = format_f(value, width, decimals)
    if not text.startswith("*"):
        return text
    for digits in range(max(width - 4, 0), -1, -1):
        mantissa, exponent = f"{value:.{digits}E}".split("E")
        text = f"{mantissa}E{int(exponent)}"  # the shortest exponent F input reads: E7, E-7, E300
        if len(text) <= width - 1:
            return text.rjust(width)
    raise ValueError(f"{value!r} does not fit a {width}-column field")
