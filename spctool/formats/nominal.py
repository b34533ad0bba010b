"""SPC nominals (``NOMINALS/<PICNM>.NOM``): a picture's a-priori pose from SPICE, before SPC's own
estimates went into its SUM file.

Specification: ``shared/docs/spc-formats.md`` §0 (conventions, Fortran numbers, byte-exact round trip) and
§3 (NOM).  Reading follows SPC: the name in columns 1–12, then seven lines by position, each a
list-directed READ of three numbers with its tag text after them (checked against the place); the
optional DYNAMICS lines up to END FILE are kept verbatim.  Writing is byte-exact as for SUM files
(:mod:`spctool.formats.sumfile`): a parsed line is reproduced unless its values changed, and then
regenerated in the exponent letter and padding of the line it replaces.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from spctool.errors import SpcFormatError, SpcUsageError
from spctool.formats import atomic
from spctool.formats.fortran import Records
from spctool.formats.rows import (
    Slot,
    as_shaped,
    check_tag,
    d_fields,
    exponent_letter,
    fields_equal,
    float_tuple,
    join_lines,
    majority_padded,
    pad80,
    source_path,
    split_lines,
    tag_line,
)

__all__ = ["Nominal", "parse_nom", "read_nom", "format_nom", "write_nom"]


@dataclass
class _NomSource:
    header: list[Slot]
    end_line: str | None  # None: the file has no END FILE line (kept so on rewrite)
    after_end: list[str]
    final_newline: bool
    pad: bool
    warnings: list = field(default_factory=list)


_NOM_ORDER = ["name", "frame", "scobj", "vso", "cx", "cy", "cz", "ptg"]
_NOM_TAGS = {"scobj": "SCOBJ", "vso": "SIGMA_VSO", "cx": "CX", "cy": "CY", "cz": "CZ", "ptg": "SIGMA_PTG"}
_NOMINAL_FIELDS = (
    "name",
    "frame_vector",
    "frame_tag",
    "scobj",
    "sigma_vso",
    "cx",
    "cy",
    "cz",
    "sigma_ptg",
    "extra_lines",
)


@dataclass(eq=False)
class Nominal:
    """A NOM file (spc-formats.md §3): the a-priori pose from SPICE.

    ``frame_vector`` is the unit vector of line 2 and ``frame_tag`` its frame name (``BOD_FRAME`` ...);
    ``extra_lines`` holds the optional DYNAMICS lines (between SIGMA_PTG and END FILE) verbatim.
    """

    name: str
    frame_vector: np.ndarray
    frame_tag: str
    scobj: np.ndarray
    sigma_vso: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    cz: np.ndarray
    sigma_ptg: np.ndarray
    extra_lines: list[str] = field(default_factory=list)
    _source: _NomSource | None = field(default=None, repr=False)

    def __post_init__(self):
        for name in ("frame_vector", "scobj", "sigma_vso", "cx", "cy", "cz", "sigma_ptg"):
            setattr(self, name, as_shaped(getattr(self, name), (3,), name))
        self.extra_lines = list(self.extra_lines)

    def __eq__(self, other):
        if not isinstance(other, Nominal):
            return NotImplemented
        return fields_equal(self, other, _NOMINAL_FIELDS)

    __hash__ = None  # type: ignore[assignment]

    @property
    def rotation(self) -> np.ndarray:
        """Body -> camera rotation (rows CX, CY, CZ)."""
        return np.vstack([self.cx, self.cy, self.cz])


def _nominal_values(nom: Nominal, key: str) -> tuple:
    if key == "name":
        return (nom.name,)
    if key == "frame":
        return float_tuple(nom.frame_vector) + (nom.frame_tag,)
    attr = {"vso": "sigma_vso", "ptg": "sigma_ptg"}.get(key, key)
    return float_tuple(getattr(nom, attr))


def parse_nom(text: str, path=None) -> Nominal:
    """Parse the text of a NOM file (spc-formats.md §3); lines are read by position."""
    path = source_path(path)
    lines, final = split_lines(text)
    n = len(lines)
    if n == 0:
        raise SpcFormatError(path, 1, "expected the picture name, found an empty file")
    header: list[Slot] = []
    name = lines[0][:12].strip()
    if not name:
        raise SpcFormatError(path, 1, "expected the picture name in columns 1-12")
    header.append(Slot("name", lines[0], (name,)))
    values: dict[str, list[float]] = {}
    frame_tag = ""
    whats = {"frame": "frame vector", **_NOM_TAGS}
    # lines 2-8 by position, each a list-directed READ (spc-formats.md §3); tags checked against places
    rec = Records(lines, path, 1)
    for key in _NOM_ORDER[1:]:
        if rec.at_end:
            raise SpcFormatError(path, n, f"expected {whats[key]} on line {rec.pos + 1}, found end of file")
        first = rec.pos
        res = rec.read_list("rrr", what=f"numbers ({whats[key]})")
        if res.nulls or res.slash:
            raise SpcFormatError(
                path, first + 1, f"expected 3 numbers ({whats[key]}), found a null item or '/'"
            )
        v = [float(x) for x in res.values]
        t = res.rest.strip()
        ln = "\n".join(lines[first : res.last + 1])
        values[key] = v
        if key == "frame":
            frame_tag = t
            header.append(Slot(key, ln, tuple(v) + (frame_tag,), frame_tag))
        else:
            check_tag(t, key, _NOM_TAGS, path, res.last + 1)
            header.append(Slot(key, ln, tuple(v), t))
    i = rec.pos
    extra: list[str] = []
    while i < n and not lines[i].startswith("END FILE"):
        extra.append(lines[i])
        i += 1
    notes = []
    if i >= n:
        # LITHOS reads the eight lines by position (READ(unit,*) each) and never looks for END FILE there:
        # the file reads the same without it (issue #40 item 8); the lines after SIGMA_PTG stay DYNAMICS
        notes.append(
            (
                n,
                "no END FILE line: SPC reads the NOM's 8 lines by position and is unaffected; a reader that "
                "scans for END FILE would run past the end of the file",
            )
        )
    source = _NomSource(
        header=header,
        end_line=lines[i] if i < n else None,
        after_end=lines[i + 1 :],
        final_newline=final,
        pad=majority_padded(lines[: i + 1], False),
        warnings=notes,
    )
    return Nominal(
        name=name,
        frame_vector=np.array(values["frame"]),
        frame_tag=frame_tag,
        scobj=np.array(values["scobj"]),
        sigma_vso=np.array(values["vso"]),
        cx=np.array(values["cx"]),
        cy=np.array(values["cy"]),
        cz=np.array(values["cz"]),
        sigma_ptg=np.array(values["ptg"]),
        extra_lines=extra,
        _source=source,
    )


def format_nom(nom: Nominal) -> str:
    """NOM file text; unchanged lines of a parsed file are reproduced byte for byte.  A non-finite
    pose (SCOBJ, CX, CY, CZ) is never written (SpcUsageError)."""
    for attr in ("scobj", "cx", "cy", "cz"):
        if not np.all(np.isfinite(np.asarray(getattr(nom, attr), dtype=np.float64))):
            raise SpcUsageError(
                f"NOM of picture {nom.name}: refusing to write a non-finite pose ({attr.upper()} holds "
                "NaN or Infinity)"
            )
    src = nom._source
    slots = src.header if src is not None else [Slot(k) for k in _NOM_ORDER]
    pad = src.pad if src is not None else False
    out: list[str] = []
    for slot in slots:
        if slot.text is not None and _nominal_values(nom, slot.key) == slot.values:
            out.append(slot.text)
            continue
        padded = slot.padded if slot.padded is not None else pad
        if slot.key == "name":
            out.append(pad80(nom.name, padded))
        elif slot.key == "frame":
            numbers = d_fields(nom.frame_vector, exponent_letter(slot.text))
            out.append(tag_line(numbers, nom.frame_tag, padded))
        else:
            vals = _nominal_values(nom, slot.key)
            numbers = d_fields(vals, exponent_letter(slot.text))
            out.append(tag_line(numbers, slot.tag or _NOM_TAGS[slot.key], padded))
    out.extend(nom.extra_lines)
    if src is None or src.end_line is not None:
        out.append(src.end_line if src is not None else "END FILE")
    if src is not None:
        out.extend(src.after_end)
    return join_lines(out, src.final_newline if src is not None else True)


def read_nom(path) -> Nominal:
    """Read ``NOMINALS/<PICNM>.NOM``."""
    text = atomic.read_spc_file(path, "NOM")
    return parse_nom(text, path)


def write_nom(path, nom: Nominal, *, overwrite: bool = True, backup: bool = False):
    """Write a NOM file atomically (returns the backup path if one was made)."""
    return atomic.write_text(path, format_nom(nom), overwrite=overwrite, backup=backup)
