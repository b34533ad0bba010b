"""Fortran numbers and records as SPC reads and writes them (spc-formats.md §0.3).

Reading follows gfortran's list-directed input (Fortran 2008 §10.10.3), checked against gfortran 12 as an
oracle: ``D``/``E``/``Q`` exponents in either case, letterless exponents (``0.123-06``,
``0.1000000000+101``), ``NaN``/``Inf``, blanks, tabs and commas as separators, ``r*c`` repeats and ``r*``
null repeats, null items (``1,,3``; a leading comma) that leave the variable unchanged, a ``/`` that ends
the READ (later items unchanged), values that continue over as many records as the READ needs (blank
records are skipped) and trailing text after the values.  :class:`Records` consumes a file the way a
sequence of ``READ(unit,*)`` and ``READ(unit,'(A80)')`` statements does: every READ starts on a new
record and discards the rest of the record it ends on.

One documented departure: a number whose exponent overflows double precision (``1D+400``) is refused,
where gfortran stores Infinity and SPC would carry it silently into the solution.

Writing reproduces gfortran's ``Dw.d``/``Ew.d`` (``0.ddddD±ee``), ``Fw.d`` (asterisks on overflow) and
``Iw`` edit descriptors byte for byte.

Formatted input (:func:`formatted_read`, :func:`read_f_field`): gfortran's ``READ(unit,'(A6,2F10.2,1X,A1)')``
of one record -- ``Aw``, ``Fw.d`` and ``nX`` -- as LITHOS reads section rows, checked against gfortran 12 on
tens of thousands of random rows (``fixtures/conformance/oracle/``).
"""

from __future__ import annotations

import math
import re

from spctool.errors import SpcFormatError

# ``\d+(?:\.\d*)?`` rather than ``\d+\.?\d*``: the same numbers, but a failed match of a long digit
# run backtracks in linear, not quadratic, time (a 100,000-digit token hung the reader)
_NUMBER = re.compile(r"^([+-]?(?:\d+(?:\.\d*)?|\.\d+))(?:[EDQedq]([+-]?\d+)|([+-]\d+))?$")
_SPECIAL = re.compile(r"^([+-]?)(inf|infinity|nan(?:\([0-9a-z_]*\))?)$", re.IGNORECASE)
_SPLIT = re.compile(r"[\s,]+")


def parse_number(token: str) -> float:
    """Parse one Fortran real (``0.1D+03``, ``1.5-06``, ``-2.E4``, ``7``) to a float.

    Raises ``ValueError`` when the token is not a Fortran number.
    """
    m = _NUMBER.match(token.strip())
    if m is None:
        raise ValueError(f"not a Fortran number: {token!r}")
    mant, exp1, exp2 = m.groups()
    exp = exp1 if exp1 is not None else exp2
    value = float(mant) if exp is None else float(f"{mant}e{exp}")
    if math.isinf(value):
        raise ValueError(f"Fortran number out of double-precision range: {token!r}")
    return value


def parse_real(token: str) -> float:
    """A list-directed real item: :func:`parse_number` forms plus ``NaN``, ``Inf``, ``Infinity`` (gfortran).

    Raises ``ValueError`` on anything else, and on a finite-looking number that overflows (``1D+400``).
    """
    m = _SPECIAL.match(token.strip())
    if m is not None:
        sign = -1.0 if m.group(1) == "-" else 1.0
        return sign * (math.nan if m.group(2).lower().startswith("nan") else math.inf)
    return parse_number(token)


def is_number(token: str) -> bool:
    return _NUMBER.match(token.strip()) is not None


# ---------------------------------------------------------------------------------------------
# list-directed READ over a record stream

#: one lexical element of a list-directed record: a comma, a slash, a quoted string or a bare token
_LEX = re.compile(r"""[ \t]*(?:(,)|(/)|'((?:[^']|'')*)'|"((?:[^"]|"")*)"|([^ \t,/'"]+))""")
_REPEAT_TOKEN = re.compile(r"^(\d+)\*(.*)$", re.S)
_LOGICAL = re.compile(r"^\.?([TtFf])")
_INTEGER = re.compile(r"^[+-]?\d+$")


class FortranEOF(Exception):
    """End of file inside a READ (SPC aborts with an end-of-file error)."""


def _lex(record: str) -> list[tuple[str, str, int]]:
    """Elements of one record: ``(',', '')``, ``('/', '')``, ``('q', text)`` (quoted), ``('v', text)``,
    each with the offset just after it."""
    out: list[tuple[str, str, int]] = []
    pos, n = 0, len(record)
    while pos < n:
        m = _LEX.match(record, pos)
        if m is None:  # only blanks left, or an unterminated quote: the rest is one bare token
            rest = record[pos:].strip(" \t")
            if rest:
                out.append(("v", rest, n))
            break
        if m.end() == pos:
            break
        pos = m.end()
        if m.group(1) is not None:
            out.append((",", "", pos))
        elif m.group(2) is not None:
            out.append(("/", "", pos))
        elif m.group(3) is not None:
            out.append(("q", m.group(3).replace("''", "'"), pos))
        elif m.group(4) is not None:
            out.append(("q", m.group(4).replace('""', '"'), pos))
        else:
            out.append(("v", m.group(5), pos))
    return out


_KIND_NAMES = {"r": "real", "i": "integer", "a": "character", "l": "logical"}


def _convert(kind: str, text: str, quoted: bool):
    """One list-directed item of type ``kind`` ('r', 'i', 'a', 'l'); ValueError when it is not one."""
    if kind == "a":
        return text
    if quoted:
        raise ValueError(text)
    if kind == "r":
        return parse_real(text)
    if kind == "i":
        if not _INTEGER.match(text):
            raise ValueError(text)
        return int(text)
    m = _LOGICAL.match(text)
    if m is None:
        raise ValueError(text)
    return m.group(1).upper() == "T"


class ListRead:
    """The outcome of one list-directed READ: the values, and where they came from.

    ``values[k]`` is the item's new value, or its ``defaults[k]`` when a null item or a ``/`` left it
    unchanged; ``lines[k]`` is the 1-based line it was read from (None when unchanged); ``first`` and
    ``last`` are the 0-based indices of the records the READ consumed; ``slash`` says a ``/`` ended it;
    ``rest`` is the unread text of the last record.
    """

    __slots__ = ("values", "lines", "first", "last", "slash", "nulls", "rest")

    def __init__(self, values, lines, first, last, slash, nulls, rest):
        self.values = values
        self.lines = lines
        self.first = first
        self.last = last
        self.slash = slash
        self.nulls = nulls
        self.rest = rest


def list_read(
    records,
    start: int,
    kinds: str,
    defaults=None,
    *,
    path=None,
    what: str = "values",
    base: int = 1,
    internal: bool = False,
) -> ListRead:
    """``READ(unit,*) v1, …, vn`` starting at record ``records[start]`` (list-directed, Fortran §10.10.3).

    ``kinds`` has one letter per item: ``r`` real, ``i`` integer, ``a`` character, ``l`` logical.
    Records are consumed until every item has a value, a ``/`` is met, or (``internal=True``: an internal
    READ of one character variable, ``READ(LINE,*)``) the single record ends.  Errors name
    ``path`` and the 1-based line (``base`` = line number of ``records[0]``):
    :class:`SpcFormatError` for a bad item, and for end of file before the list is satisfied.
    """
    n = len(kinds)
    values = list(defaults) if defaults is not None else [None] * n
    lines: list[int | None] = [None] * n
    k = 0
    first_elem = True
    after_comma = False
    nulls = 0
    j = start
    nrec = len(records)
    while True:
        if j >= nrec:
            if internal:
                where = base + start
            else:
                where = base + max(nrec - 1, 0) if nrec else base
            found = f"found {k}" if k else "found none"
            unit = "record" if internal else "file"
            raise SpcFormatError(path, where, f"expected {n} {what}, {found} before the end of the {unit}")
        record = records[j]
        elems = _lex(record)
        for idx, (typ, text, _end) in enumerate(elems):
            if typ == ",":
                if after_comma or first_elem:
                    k += 1
                    nulls += 1
                after_comma = True
                first_elem = False
            elif typ == "/":
                return ListRead(values, lines, start, j, True, nulls, _rest_of(record, elems, idx + 1))
            else:
                count, body, quoted = 1, text, typ == "q"
                m = None if quoted else _REPEAT_TOKEN.match(text)
                if m is not None:
                    count, body = int(m.group(1)), m.group(2)
                    if count == 0:
                        raise SpcFormatError(
                            path, base + j, f"expected {n} {what}: zero repeat count {text!r}"
                        )
                    if body == "":  # r* : r null values, the items keep their values
                        k += count
                        nulls += count
                        after_comma = first_elem = False
                        if k >= n:
                            rest = _rest_of(record, elems, idx + 1)
                            return ListRead(values, lines, start, j, False, nulls, rest)
                        continue
                for _ in range(count):
                    if k >= n:
                        break
                    try:
                        values[k] = _convert(kinds[k], body, quoted)
                    except ValueError:
                        detail = (
                            "out of range"
                            if kinds[k] == "r" and _NUMBER.match(body)
                            else f"not a Fortran {_KIND_NAMES[kinds[k]]}"
                        )
                        raise SpcFormatError(
                            path, base + j, f"expected {n} {what}: value {k + 1} {text!r} is {detail}"
                        ) from None
                    lines[k] = base + j
                    k += 1
                after_comma = False
                first_elem = False
            if k >= n:
                return ListRead(values, lines, start, j, False, nulls, _rest_of(record, elems, idx + 1))
        if internal:
            j = nrec  # an internal READ has one record
            continue
        j += 1


def _rest_of(record: str, elems, idx: int) -> str:
    """The raw text of ``record`` after element ``idx - 1`` (what the READ left unread)."""
    return record[elems[idx - 1][2] :] if idx > 0 else record


class Records:
    """A text file as a stream of records, consumed as a sequence of SPC READ statements.

    ``lines`` are the records without terminators (CR already stripped); ``pos`` is the 0-based index of
    the next record.  :meth:`read_list` is ``READ(unit,*)``; :meth:`read_a` is ``READ(unit,'(A80)')``;
    :meth:`skip` is ``READ(unit,*)`` with an empty list (one record, whatever it holds).
    """

    def __init__(self, lines: list[str], path=None, pos: int = 0):
        self.lines = lines
        self.path = path
        self.pos = pos

    @property
    def at_end(self) -> bool:
        return self.pos >= len(self.lines)

    def read_list(self, kinds: str, defaults=None, *, what: str = "values") -> ListRead:
        result = list_read(self.lines, self.pos, kinds, defaults, path=self.path, what=what)
        self.pos = result.last + 1
        return result

    def read_a(self, width: int = 80, *, what: str = "a record") -> str:
        """The next record cut to ``width`` columns and blank-padded to it (``PAD='YES'``)."""
        if self.pos >= len(self.lines):
            raise SpcFormatError(self.path, max(len(self.lines), 1), f"expected {what}, found end of file")
        text = self.lines[self.pos][:width].ljust(width)
        self.pos += 1
        return text

    def skip(self, *, what: str = "a record") -> str:
        """``READ(unit,*)`` with no items: consumes one record; returns its text."""
        if self.pos >= len(self.lines):
            raise SpcFormatError(self.path, max(len(self.lines), 1), f"expected {what}, found end of file")
        text = self.lines[self.pos]
        self.pos += 1
        return text


def read_internal(
    text: str, kinds: str, defaults=None, *, path=None, line=None, what: str = "values"
) -> ListRead:
    """``READ(LINE,*) …``: a list-directed READ of one character variable (one record)."""
    return list_read([text], 0, kinds, defaults, path=path, what=what, base=line or 1, internal=True)


def tokens(text: str) -> list[str]:
    """Split a list-directed record into tokens (blanks and commas separate)."""
    text = text.strip().strip(",")
    if not text:
        return []
    return [t for t in _SPLIT.split(text) if t]


def read_reals(
    text: str, count: int, *, path=None, line: int | None = None, what: str = "numbers"
) -> list[float]:
    """List-directed ``READ(LINE,*) A(1:count)``: the first ``count`` values, rest ignored.

    Raises :class:`SpcFormatError` naming ``path``/``line`` when fewer than
    ``count`` numbers start the record.
    """
    toks = tokens(text)
    out: list[float] = []
    for tok in toks:
        if len(out) == count:
            break
        try:
            out.append(parse_number(tok))
        except ValueError:
            raise SpcFormatError(
                path, line, f"expected {count} {what}, found {tok!r} at value {len(out) + 1}"
            ) from None
    if len(out) < count:
        raise SpcFormatError(path, line, f"expected {count} {what}, found {len(out)}")
    return out


def read_ints(
    text: str, count: int, *, path=None, line: int | None = None, what: str = "integers"
) -> list[int]:
    """List-directed read of ``count`` integers (a real with an integral value is refused)."""
    toks = tokens(text)
    out: list[int] = []
    for tok in toks:
        if len(out) == count:
            break
        if not re.fullmatch(r"[+-]?\d+", tok):
            raise SpcFormatError(
                path, line, f"expected {count} {what}, found {tok!r} at value {len(out) + 1}"
            )
        out.append(int(tok))
    if len(out) < count:
        raise SpcFormatError(path, line, f"expected {count} {what}, found {len(out)}")
    return out


# ---------------------------------------------------------------------------------------------
# writing


def _mantissa_exponent(value: float, digits: int) -> tuple[str, int]:
    """Digits of |value| rounded to ``digits`` significant figures and the exponent of 0.ddd form."""
    if value == 0.0:
        return "0" * digits, 0
    s = f"{abs(value):.{digits - 1}e}"
    mant, exp = s.split("e")
    return mant.replace(".", ""), int(exp) + 1


def format_d(value: float, width: int = 20, decimals: int = 10, letter: str = "D") -> str:
    """gfortran ``Dw.d`` (or ``Ew.d`` with ``letter='E'``): ``  0.1356800000D+03``.

    A two-digit exponent carries the letter; |exponent| > 99 drops it
    (``0.1000000000+101``) as gfortran does.  Overflow of the width gives
    asterisks.
    """
    value = float(value)
    if not math.isfinite(value):
        text = "NaN" if math.isnan(value) else ("-Infinity" if value < 0 else "Infinity")
        return text.rjust(width)[-width:] if len(text) <= width else "*" * width
    digits, exp = _mantissa_exponent(value, decimals)
    sign = "-" if (value < 0 or (value == 0.0 and math.copysign(1.0, value) < 0 and False)) else ""
    if abs(exp) <= 99:
        exp_text = f"{letter}{'-' if exp < 0 else '+'}{abs(exp):02d}"
    elif abs(exp) <= 999:
        exp_text = f"{'-' if exp < 0 else '+'}{abs(exp):03d}"
    else:
        return "*" * width
    text = f"{sign}0.{digits}{exp_text}"
    if len(text) > width:
        # gfortran drops the optional leading zero before giving up
        text = f"{sign}.{digits}{exp_text}"
        if len(text) > width:
            return "*" * width
    return text.rjust(width)


def format_e(value: float, width: int = 20, decimals: int = 10) -> str:
    """gfortran ``Ew.d``."""
    return format_d(value, width, decimals, letter="E")


def format_f(value: float, width: int, decimals: int) -> str:
    """gfortran ``Fw.d``: fixed point, right-justified, ``*`` × w on overflow."""
    value = float(value)
    if not math.isfinite(value):
        return "*" * width
    text = f"{value:.{decimals}f}"
    if text.startswith("-") and float(text) == 0.0:
        text = text  # gfortran keeps the minus sign of a negative value rounded to zero
    if len(text) > width:
        if text.startswith("0.") and len(text) - 1 <= width:
            text = text[1:]
        elif text.startswith("-0.") and len(text) - 1 <= width:
            text = "-" + text[2:]
        else:
            return "*" * width
    return text.rjust(width)


def format_i(value: int, width: int) -> str:
    """gfortran ``Iw``."""
    text = str(int(value))
    if len(text) > width:
        return "*" * width
    return text.rjust(width)


def pad_tag(numbers: str, tag: str, column: int = 64, pad_to: int | None = None) -> str:
    """Place ``tag`` so that it starts at 1-based ``column`` after ``numbers``.

    ``pad_to=80`` pads with blanks to 80 columns (the ``A20`` tag style).
    """
    gap = column - 1 - len(numbers)
    line = numbers + " " * max(gap, 1) + tag
    if pad_to is not None and len(line) < pad_to:
        line = line.ljust(pad_to)
    return line


# ---------------------------------------------------------------------------------------------
# formatted READ of one record (``READ(unit,'(A6,2F10.2,1X,A1)')``): how LITHOS reads a section row

_FORMAT_ITEM = re.compile(r"^(\d*)([AFX])(\d*)(?:\.(\d+))?$", re.IGNORECASE)
_F_SPECIAL = re.compile(r"^([+-]?)(inf|infinity|nan(?:\([0-9a-z_]*\))?)$", re.IGNORECASE)


class FormattedReadError(ValueError):
    """A formatted READ stops (gfortran: "Bad value during floating point read"); ``column`` is 1-based."""

    def __init__(self, column: int, field: str, message: str):
        super().__init__(message)
        self.column = column
        self.field = field


def parse_format(fmt: str) -> tuple[tuple[str, int, int], ...]:
    """``'(A6,2F10.2,1X,A1)'`` -> ``(('A', 6, 0), ('F', 10, 2), ('F', 10, 2), ('X', 1, 0), ('A', 1, 0))``.

    Only the edit descriptors of SPC's section rows: ``Aw``, ``[r]Fw.d`` and ``nX``.
    """
    items: list[tuple[str, int, int]] = []
    for part in fmt.strip().strip("()").split(","):
        m = _FORMAT_ITEM.match(part.strip())
        if m is None:
            raise ValueError(f"unsupported edit descriptor {part!r} in {fmt!r}")
        rep, kind, width, dec = m.groups()
        kind = kind.upper()
        if kind == "X":  # nX: the number before X is the width
            items.append(("X", int(rep or 1), 0))
            continue
        if not width:
            raise ValueError(f"{kind} needs a width here: {part!r}")
        if kind == "F" and dec is None:
            raise ValueError(f"Fw.d needs its decimals: {part!r}")
        items.extend([(kind, int(width), int(dec or 0))] * (int(rep) if rep else 1))
    return tuple(items)


def read_f_field(text: str, decimals: int) -> float:
    """gfortran ``Fw.d`` input of one field's characters (``BLANK='NULL'``: blanks are ignored).

    ``text`` holds the characters of the field that lie inside the record (shorter than ``w`` when the
    record ends inside the field).  Rules checked against gfortran 12 on random fields: an all-blank field
    is 0; without a decimal point the digits carry ``d`` implied decimals (``565`` in ``F10.2`` is 5.65);
    an exponent is a letter ``E D Q`` (either case) and/or a sign, blanks inside it are ignored, a letter
    needs a sign or digit after it in the field and a sign needs one more character; ``Inf``/``NaN``
    are read.  Anything else (a tab, a comma, a letter, a second point) stops the READ: ``ValueError``.
    """
    s = text
    if not s.strip(" "):
        return 0.0
    special = _F_SPECIAL.match(s.strip(" "))
    if special is not None:
        sign = -1.0 if special.group(1) == "-" else 1.0
        return sign * (math.nan if special.group(2).lower().startswith("nan") else math.inf)
    n = len(s)
    i = 0
    while i < n and s[i] == " ":
        i += 1
    sign = ""
    if s[i] in "+-":
        sign = "-" if s[i] == "-" else ""
        i += 1
    digits = []
    point = None
    while i < n:
        c = s[i]
        if c == " ":
            i += 1
        elif "0" <= c <= "9":
            digits.append(c)
            i += 1
        elif c == ".":
            if point is not None:
                raise ValueError(f"second decimal point in {text!r}")
            point = len(digits)
            i += 1
        else:
            break
    exponent = 0
    if i < n:
        c = s[i]
        if c in "EeDdQq":
            i += 1
            while i < n and s[i] == " ":
                i += 1
            if i >= n:
                raise ValueError(f"exponent letter without digits in {text!r}")
            c = s[i]
            if c not in "+-0123456789":
                raise ValueError(f"bad exponent in {text!r}")
        if c in "+-":
            neg = c == "-"
            i += 1
            if i >= n:
                raise ValueError(f"exponent sign at the end of the field {text!r}")
        else:
            neg = False
        if not ("0" <= s[i] <= "9" or s[i] == " "):
            raise ValueError(f"bad character {s[i]!r} in {text!r}")
        exp_digits = []
        while i < n:
            c = s[i]
            if c == " ":
                pass
            elif "0" <= c <= "9":
                exp_digits.append(c)
            else:
                raise ValueError(f"bad character {c!r} in the exponent of {text!r}")
            i += 1
        exponent = int("".join(exp_digits) or "0") * (-1 if neg else 1)
    if abs(exponent - (decimals if point is None else 0)) > 9999:  # gfortran: "Bad value" past 10^±9999
        raise ValueError(f"exponent out of range in {text!r}")
    if not digits:
        return 0.0 if not sign else -0.0
    mantissa = "".join(digits)
    if point is None:
        exponent -= decimals
        point = len(digits)
    return float(f"{sign}{mantissa[:point] or '0'}.{mantissa[point:] or '0'}e{exponent}")


def formatted_read(record: str, fmt) -> list:
    """``READ(unit, fmt)`` of one record, as gfortran does it for a sequential formatted file.

    ``fmt`` is a format string or :func:`parse_format`'s tuple.  ``A`` items are strings (blank-padded
    past the record's end, ``PAD='YES'``), ``F`` items floats; ``X`` skips.  Raises
    :class:`FormattedReadError` (with the field's 1-based column) where the READ would stop.
    """
    items = parse_format(fmt) if isinstance(fmt, str) else fmt
    out: list = []
    pos = 0
    for kind, width, dec in items:
        field = record[pos : pos + width]
        if kind == "A":
            out.append(field.ljust(width))
        elif kind == "F":
            step = width
            comma = field.find(",")
            if comma >= 0:  # a comma ends a numeric field early; the next field starts after it
                field, step = field[:comma], comma + 1
            try:
                out.append(read_f_field(field, dec))
            except ValueError as exc:
                raise FormattedReadError(pos + 1, field, str(exc)) from None
            pos += step
            continue
        pos += width
    return out
