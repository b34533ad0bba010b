"""Fortran numbers as SPC reads and writes them (spc-formats.md §0.3).

Reading follows gfortran's list-directed input: ``D``/``E``/``Q`` exponents in
either case, letterless exponents (``0.123-06``, ``0.1000000000+101``), commas
as separators and trailing text after the values.  Writing reproduces gfortran's
``Dw.d``/``Ew.d`` (``0.ddddD±ee``), ``Fw.d`` (asterisks on overflow) and ``Iw``
edit descriptors byte for byte.
"""

from __future__ import annotations

import math
import re

from spctool.errors import SpcFormatError

# ``\d+(?:\.\d*)?`` rather than ``\d+\.?\d*``: the same numbers, but a failed match of a long digit
# run backtracks in linear, not quadratic, time (a 100,000-digit token hung the reader)
_NUMBER = re.compile(r"^([+-]?(?:\d+(?:\.\d*)?|\.\d+))(?:[EDQedq]([+-]?\d+)|([+-]\d+))?$")
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
    if exp is None:
        return float(mant)
    return float(f"{mant}e{exp}")


def is_number(token: str) -> bool:
    return _NUMBER.match(token.strip()) is not None


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
