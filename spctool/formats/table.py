"""The landmark table: the text (or JSON) file that chains the stages.

cli-contract.md "Landmark tables": a few ``#`` comment lines (tool version,
picture, command), one header line of column names, then one
whitespace-aligned row per landmark.  ``--json`` gives one document
``{"command", "picture", "spctool_version", "landmarks": [...], ...}`` with the
same column names as keys.  Pixel columns are SPC pixels (1-based sample/line).

The table is column-oriented: ``table["sample"]`` is a numpy array (or a list
for text columns), so stages read it without per-row loops.  Number formatting
lives here, never in the command line.
"""

from __future__ import annotations

import io
import json
import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spctool import __version__
from spctool.errors import SpcFormatError
from spctool.formats import guard

#: Decimal places used for well-known columns; other floats use ``%.6g``.
COLUMN_DECIMALS: dict[str, int] = {
    "sample": 4,
    "line": 4,
    "predicted_sample": 4,
    "predicted_line": 4,
    "apriori_sample": 4,
    "apriori_line": 4,
    "measured_sample": 4,
    "measured_line": 4,
    "dsample": 4,
    "dline": 4,
    "true_sample": 4,
    "true_line": 4,
    "error_sample": 4,
    "error_line": 4,
    "residual_sample_before": 4,
    "residual_line_before": 4,
    "residual_sample_after": 4,
    "residual_line_after": 4,
    "correlation": 4,
    "sigma_sample": 5,
    "sigma_line": 5,
    "rho_sl": 4,
    "emission": 3,
    "incidence": 3,
    "phase": 3,
    "range_km": 6,
    "fraction_in_photo": 4,
    "lambda": 5,
    "phi": 5,
}

_INT = re.compile(r"^[+-]?\d+$")


def _format_value(column: str, value) -> str:
    if value is None:
        return "nan"
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        text = f"{v:.{COLUMN_DECIMALS[column]}f}" if column in COLUMN_DECIMALS else f"{v:.6g}"
        if text.startswith("-") and float(text) == 0.0:
            text = text[1:]  # a value that rounds to zero prints without a sign
        return text
    text = str(value)
    if not text:
        return "-"
    return re.sub(r"\s+", "_", text)


def _parse_value(text: str):
    if _INT.match(text) and len(text) <= 20:  # longer: a number, not an int64 (nor 4300+ digits)
        return int(text)
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    try:
        return float(text)
    except ValueError:
        return text


def _json_value(value):
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return None if not math.isfinite(v) else v
    if value is None:
        return None
    return value


@dataclass
class LandmarkTable:
    """Columns of equal length; ``name`` first by convention."""

    columns: dict[str, object] = field(default_factory=dict)
    picture: str | None = None
    command: str | None = None
    comments: list[str] = field(default_factory=list)
    meta: dict = field(default_factory=dict)

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def from_rows(cls, rows: Iterable[Mapping], **kw) -> LandmarkTable:
        rows = list(rows)
        names: list[str] = []
        for r in rows:
            for k in r:
                if k not in names:
                    names.append(k)
        cols = {k: _column([r.get(k) for r in rows]) for k in names}
        return cls(columns=cols, **kw)

    def __post_init__(self):
        self.columns = {k: _column(v) for k, v in self.columns.items()}
        lengths = {len(v) for v in self.columns.values()}
        if len(lengths) > 1:
            raise ValueError(f"table columns differ in length: {lengths}")

    # -- access -------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(next(iter(self.columns.values()))) if self.columns else 0

    def __contains__(self, name: str) -> bool:
        return name in self.columns

    def __getitem__(self, name: str):
        return self.columns[name]

    def __setitem__(self, name: str, values) -> None:
        values = _column(values)
        if self.columns and len(values) != len(self):
            raise ValueError(f"column {name!r} has {len(values)} values, table has {len(self)} rows")
        self.columns[name] = values

    def get(self, name: str, default=None):
        return self.columns.get(name, default)

    @property
    def names(self) -> list[str]:
        return [str(n) for n in self.columns.get("name", [])]

    def rows(self) -> list[dict]:
        keys = list(self.columns)
        return [{k: _scalar(self.columns[k][i]) for k in keys} for i in range(len(self))]

    def select(self, mask) -> LandmarkTable:
        mask = np.asarray(mask, bool)
        cols = {}
        for k, v in self.columns.items():
            cols[k] = v[mask] if isinstance(v, np.ndarray) else [x for x, m in zip(v, mask) if m]
        return LandmarkTable(cols, self.picture, self.command, list(self.comments), dict(self.meta))

    # -- text ---------------------------------------------------------------------------------
    def to_text(self) -> str:
        out = io.StringIO()
        out.write(f"# spctool {__version__}\n")
        if self.picture:
            out.write(f"# picture: {self.picture}\n")
        if self.command:
            out.write(f"# command: {self.command}\n")
        for c in self.comments:
            out.write(f"# {c}\n")
        keys = list(self.columns)
        if not keys:
            return out.getvalue()
        cells = [[_format_value(k, self.columns[k][i]) for k in keys] for i in range(len(self))]
        widths = [max([len(k)] + [len(r[j]) for r in cells]) for j, k in enumerate(keys)]
        numeric = [
            isinstance(self.columns[k], np.ndarray) and self.columns[k].dtype.kind in "fiu" for k in keys
        ]

        def fmt(items):
            parts = []
            for j, text in enumerate(items):
                parts.append(text.rjust(widths[j]) if numeric[j] else text.ljust(widths[j]))
            return "  ".join(parts).rstrip()

        out.write(fmt(keys) + "\n")
        for r in cells:
            out.write(fmt(r) + "\n")
        return out.getvalue()

    def pixel_columns(self, path=None):
        """(sample, line) columns, or None when the table has neither; one without the other is a
        SpcFormatError naming the missing column."""
        smp, lin = self.get("sample"), self.get("line")
        if (smp is None) != (lin is None):
            have, miss = ("sample", "line") if lin is None else ("line", "sample")
            raise SpcFormatError(
                path, None, f"expected a '{miss}' column beside '{have}' (columns: {', '.join(self.columns)})"
            )
        return None if smp is None else (smp, lin)

    @classmethod
    def parse_text(cls, text: str, path=None) -> LandmarkTable:
        """The text form: whitespace-aligned columns, or comma-separated (CSV) when the header line
        has commas; ``#`` lines are comments (``# picture:``, ``# command:``)."""
        picture = command = None
        comments: list[str] = []
        header: list[str] | None = None
        delimited = False
        rows: list[list[str]] = []
        linenos: list[tuple[int, None]] = []
        for lineno, raw in enumerate(text.splitlines(), start=1):
            line = raw.strip()
            if not line:
                continue
            if line.startswith("#"):
                body = line[1:].strip()
                if body.startswith("picture:"):
                    picture = body.split(":", 1)[1].strip()
                elif body.startswith("command:"):
                    command = body.split(":", 1)[1].strip()
                elif not body.startswith("spctool "):
                    comments.append(body)
                continue
            if header is None:
                delimited = "," in line  # a CSV table (e.g. from a spreadsheet): comma-separated
            parts = _split_csv(line, path, lineno) if delimited else line.split()
            if header is None:
                header = [p.lower() if p.lower() in _KNOWN_LOWER else p for p in parts]
                if "name" not in header:
                    raise SpcFormatError(
                        path, lineno, "expected a header line of column names including 'name'"
                    )
                continue
            if len(parts) != len(header):
                raise SpcFormatError(path, lineno, f"expected {len(header)} columns, found {len(parts)}")
            rows.append(parts)
            linenos.append((lineno, None))
        if header is None:
            raise SpcFormatError(path, None, "expected a landmark table (header line with a 'name' column)")
        cols = {}
        for j, key in enumerate(header):
            values = [_parse_value(r[j]) for r in rows]
            if key in _PIXEL_COLUMNS:  # stages read these as numbers: a word is bad input (nan is not)
                for v, (lineno, _) in zip(values, linenos):
                    if isinstance(v, str):
                        raise SpcFormatError(
                            path, lineno, f"a number (or nan) in column '{key}', found {v!r}"
                        )
            if key == "name":
                values = [str(r[j]) for r in rows]
                # one row per landmark — per landmark and picture in a table with a picture column
                # (simulate's truth rows, geometry's residuals)
                pic = header.index("picture") if "picture" in header else None
                keys = (
                    values
                    if pic is None
                    else [f"{v.strip()} in picture {r[pic]}" for v, r in zip(values, rows)]
                )
                _refuse_duplicates(keys, [n for n, _ in linenos], path, "line")
            cols[key] = values
        return cls(cols, picture, command, comments)

    # -- json ---------------------------------------------------------------------------------
    def to_json_dict(self) -> dict:
        doc = {
            "command": self.command,
            "picture": self.picture,
            "spctool_version": __version__,
        }
        doc.update({k: _jsonify(v) for k, v in self.meta.items()})
        doc["landmarks"] = [{k: _json_value(v) for k, v in r.items()} for r in self.rows()]
        return doc

    def to_json(self) -> str:
        return json.dumps(self.to_json_dict(), indent=2, allow_nan=False) + "\n"

    @classmethod
    def from_json(cls, text: str, path=None) -> LandmarkTable:
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise SpcFormatError(path, exc.lineno, f"expected JSON ({exc.msg})") from None
        except RecursionError:
            raise SpcFormatError(
                path, None, "expected JSON nested at most a few hundred levels deep"
            ) from None
        except ValueError:  # json.loads refuses integers of more than 4300 digits
            raise SpcFormatError(path, None, "expected JSON numbers of at most 4300 digits") from None
        if not isinstance(doc, dict) or not isinstance(doc.get("landmarks"), list):
            raise SpcFormatError(path, None, "expected a JSON object with a 'landmarks' list")
        if not all(isinstance(r, dict) for r in doc["landmarks"]):
            raise SpcFormatError(path, None, "expected a JSON object per row of the 'landmarks' list")
        rows = [{k: (math.nan if v is None else v) for k, v in r.items()} for r in doc["landmarks"]]
        if all("name" in r for r in rows):
            names = [str(r["name"]) for r in rows]
            if all("picture" in r for r in rows):
                names = [f"{n.strip()} in picture {r['picture']}" for n, r in zip(names, rows)]
            _refuse_duplicates(names, range(1, len(rows) + 1), path, "row")
        meta = {
            k: v for k, v in doc.items() if k not in ("command", "picture", "spctool_version", "landmarks")
        }
        return cls.from_rows(rows, picture=doc.get("picture"), command=doc.get("command"), meta=meta)


#: column names read case-insensitively (a spreadsheet's "Name, Sample, Line")
_KNOWN_LOWER = {"name", "sample", "line", "status"}

#: pixel columns a stage reads as numbers (a table's a-priori or measured pixels)
_PIXEL_COLUMNS = ("sample", "line", "measured_sample", "measured_line")


def _refuse_duplicates(names, places, path, unit: str) -> None:
    """SpcFormatError naming both places (``unit`` "line" or "row") of the first name given twice: a
    landmark measured twice in one table is ambiguous (which pixel?), never resolved silently."""
    first: dict[str, int] = {}
    for name, place in zip(names, places):
        key = name.strip()
        if key in first:
            raise SpcFormatError(
                path,
                place if unit == "line" else None,
                f"one row per landmark: {key!r} is on {unit}s {first[key]} and {place}",
            )
        first[key] = place


def _split_csv(line: str, path, lineno: int) -> list[str]:
    """One comma-separated line (quotes allowed), fields stripped; a field may not be empty."""
    import csv

    fields = [f.strip() for f in next(csv.reader([line], skipinitialspace=True))]
    if any(f == "" for f in fields):
        raise SpcFormatError(path, lineno, "expected a value in every comma-separated field (use nan)")
    return fields


def _jsonify(v):
    if isinstance(v, np.ndarray):
        return _jsonify(v.tolist())
    if isinstance(v, dict):
        return {k: _jsonify(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonify(x) for x in v]
    return _json_value(v)


def _scalar(v):
    if isinstance(v, np.generic):
        return v.item()
    return v


def _as_float(v) -> float:
    try:
        return float(v)
    except OverflowError:  # an integer beyond float's range (copysign would convert it too)
        return math.inf if v > 0 else -math.inf


def _column(values):
    if isinstance(values, np.ndarray):
        return values
    values = list(values)
    if values and all(isinstance(v, (bool, np.bool_)) for v in values):
        return np.asarray(values, bool)
    if values and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in values):
        if all(-(2**63) <= v < 2**63 for v in values):
            return np.asarray(values, np.int64)
        return np.asarray([_as_float(v) for v in values], np.float64)  # beyond int64: as numbers
    if values and all(
        (isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)) or v is None
        for v in values
    ):  # an integer beyond float's range (JSON 1e400 written out) is infinite, not an OverflowError
        return np.asarray([math.nan if v is None else _as_float(v) for v in values], np.float64)
    return ["" if v is None else str(v) if not isinstance(v, str) else v for v in values]


def read_table(path) -> LandmarkTable:
    """Read a landmark table (text or JSON) from ``path``; ``-`` is stdin."""
    if str(path) == "-":
        text = guard.read_stdin("a landmark table on standard input").decode("utf-8", errors="replace")
        name = "<stdin>"
    else:
        p = Path(path)
        if not p.exists():
            raise SpcFormatError(path, None, "expected a landmark table file (not found)")
        text = guard.read_bytes(p, "a landmark table").decode("utf-8", errors="replace")
        name = str(path)
    if text.lstrip().startswith("{"):
        return LandmarkTable.from_json(text, name)
    return LandmarkTable.parse_text(text, name)
