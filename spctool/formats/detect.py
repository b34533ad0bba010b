"""Recognise an SPC file or photo from its content (name only breaks ties).

Used by ``info``, ``validate`` and ``convert``.  Kinds: ``sum``, ``nom``,
``lmk``, ``map``, ``icq``, ``obj``, ``vtk``, ``lithos``, ``pictlist``,
``lmrklist``, ``lmrklistx``, ``table``, ``fits``, ``pgm``, ``png``, ``dat``.
"""

from __future__ import annotations

import re
from pathlib import Path

from spctool.errors import SpcFormatError

PHOTO_KINDS = ("fits", "pgm", "png", "dat")
SHAPE_KINDS = ("icq", "obj", "vtk")


def _map_size_ok(size: int, head: bytes) -> bool:
    if size < 72 or size % 72 or len(head) < 12:
        return False
    for q in (head[10] + 256 * head[11], head[11] + 256 * head[10]):
        n = (2 * q + 1) ** 2
        if size == 72 * (1 + -(-n // 24)):
            return True
    return False


def _numeric_line(line: str, count: int) -> bool:
    from spctool.formats.fortran import is_number

    toks = line.replace(",", " ").split()
    return len(toks) >= count and all(is_number(t) or t.lower() == "nan" for t in toks[:count])


def _untagged_kind(lines: list[str]) -> str | None:
    """SUM / NOM / LMK files without tags: SPC reads them by position, so recognise them by shape."""
    heads = {ln[:9] for ln in lines}
    if len(lines) > 10 and ("LANDMARKS" in heads or "LIMB FITS" in heads):
        if _numeric_line(lines[2], 4) and all(_numeric_line(lines[k], 3) for k in range(3, 9)):
            if _numeric_line(lines[9], 6):
                return "sum"
    if (
        len(lines) > 9
        and re.match(r"^.{1,6}\s+[TF]\b", lines[0])
        and any(ln[:8] == "PICTURES" for ln in lines)
    ):
        if (
            _numeric_line(lines[1], 2)
            and _numeric_line(lines[2], 4)
            and all(_numeric_line(lines[k], 3) for k in range(4, 9))
        ):
            return "lmk"
    if 8 < len(lines) < 200 and any(ln[:8] == "END FILE" for ln in lines) and "LANDMARKS" not in heads:
        if all(_numeric_line(lines[k], 3) for k in range(1, 8)) and lines[0][:12].strip():
            return "nom"
    return None


def detect_kind(path) -> str:
    """The kind of file at ``path`` (see module docstring); SpcFormatError if unknown."""
    from spctool.errors import SpcEnvironmentError
    from spctool.formats.guard import check_regular

    p = Path(path)
    if not p.exists() and not p.is_symlink():
        raise SpcFormatError(p, None, "expected an existing file (not found)")
    # a FIFO would block the read below forever, /dev/zero never end: regular files only
    size = check_regular(p, "an SPC file or photo")
    try:
        with open(p, "rb") as fh:
            head = fh.read(4096)
    except OSError as exc:
        raise SpcEnvironmentError.from_oserror(exc, p) from None
    suffix = p.suffix.lower()
    upper = p.name.upper()
    if head.startswith(b"SIMPLE  ="):
        return "fits"
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    if head[:2] in (b"P5", b"P2") and len(head) > 2 and head[2:3].isspace():
        return "pgm"
    if head.startswith(b"# vtk DataFile"):
        return "vtk"
    if suffix == ".map" or (b"\n" not in head[:72] and _map_size_ok(size, head)):
        if _map_size_ok(size, head) or suffix == ".map":
            return "map"
    if suffix == ".dat":
        return "dat"
    try:
        text = head.decode("latin-1")
    except UnicodeDecodeError:  # pragma: no cover - latin-1 decodes everything
        text = ""
    if "\x00" in text:
        raise SpcFormatError(p, None, "expected an SPC file or photo (unrecognised binary content)")
    lines = text.replace("\r", "").split("\n")
    first = lines[0].strip() if lines else ""
    if upper.startswith("INIT_LITHOS") or any(re.match(r"^[A-Z][A-Z0-9_]*=", ln) for ln in lines[:40]):
        if any(ln[:3] == "END" for ln in lines) or upper.startswith("INIT_LITHOS") or size > len(head):
            if not any("SCOBJ" in ln for ln in lines[:12]):
                return "lithos"
    if first.startswith("# spctool") or first.startswith("{"):
        return "table"
    if len(lines) > 2 and "SIZE, SCALE" in lines[1]:
        return "lmk"
    if any("MMFL" in ln for ln in lines[:6]) and any("SCOBJ" in ln for ln in lines[:8]):
        return "sum"
    if len(lines) > 3 and "SCOBJ" in lines[2] and any("SIGMA_VSO" in ln for ln in lines[:6]):
        return "nom"
    untagged = _untagged_kind(lines)
    if untagged is not None:
        return untagged
    if re.fullmatch(r"[+-]?\d{1,9}", first):  # ICQ's Q; a longer number is no ICQ header
        return "icq"
    if any(ln.startswith(("v ", "f ")) for ln in lines[:2000]) and any(ln.startswith("v ") for ln in lines):
        return "obj"
    if upper.startswith("LMRKLISTX"):
        return "lmrklistx"
    if upper.startswith(("PICTLIST", "USED_PICS")):
        return "pictlist"
    if upper.startswith(("LMRKLIST", "BIGLIST", "USED_MAPS", "INSIDE")):
        return "lmrklist"
    if any(ln.strip() == "END" for ln in lines):
        body = [ln for ln in lines if ln.strip() and ln.strip() != "END"]
        if body and all(len(ln.split()) >= 7 for ln in body[:5]):
            return "lmrklistx"
        if body and all(ln[:1] in (" ", "!", "#") for ln in body):
            return "pictlist"
        return "lmrklist"
    if any(ln.split()[:1] == ["name"] for ln in lines[:20] if ln.strip()):
        return "table"
    raise SpcFormatError(
        p, 1, "expected an SPC file (SUM, NOM, LMK, MAP, ICQ, OBJ, VTK, INIT_LITHOS, list) or a photo"
    )
