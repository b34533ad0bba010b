"""Guards at the boundary where outside data become paths or memory.

Hostile or corrupt input must neither escape the directories a user named nor exhaust the machine
(cli-contract.md "Errors"; issue #19):

* :func:`check_name` — a picture or landmark name read from a PICTLIST, LMRKLIST, a landmark table
  or a SPEC becomes a file name (``SUMFILES/<PIC>.SUM``); SPC's names are short plain identifiers
  (spc-formats.md §7: 12-character pictures, 6-character landmarks), so anything with a path
  separator, ``..``, an absolute path, a NUL or other control character is refused with one line;
* :func:`check_regular` / :func:`read_bytes` — inputs must be regular files: a FIFO would block a
  reader forever, ``/dev/zero`` would be read until memory runs out, a directory is not a file;
  the size is checked against a cap before a byte is read;
* :func:`check_allocation` — an array size computed from a header or a specification is checked
  against a cap before it is allocated;
* a file is read only for what it really holds: a large *sparse* file (a 432 MB MAP of 4 KB on disk,
  holes reading as zeros) is refused before a byte is read, and standard input is read with a size
  limit (:func:`read_stdin`);
* :func:`check_finite` — a pose, vector or camera value read from a text file must be finite (Fortran
  reads ``NaN`` and ``Infinity``; no stage can use them and no writer may pass them on);
* :func:`refuse_input_overwrite` — an output that is, by device and inode, one of the files a command
  read (or a directory of them) is refused, whatever path (symbolic link, bind mount) reaches it;
  inside an :func:`input_scope` (one command, one batch picture) every file read by
  :func:`read_bytes` is remembered, and :func:`refuse_read_input` refuses an output that is one of
  them (a command's ``-o FILE``, a batch picture's outputs; the explicit in-place updates —
  ``--in-place``, ``convert --force SRC SRC``, ``make-maplets`` adding to LMRKLIST.TXT — keep a
  ``.bak`` or are the command's purpose).

Operating-system refusals (permission denied, EIO) are re-raised as
:class:`~spctool.errors.SpcEnvironmentError` naming the user's path (exit 3).
"""

from __future__ import annotations

import contextlib
import os
import re
import stat
import threading
from pathlib import Path

from spctool.errors import SpcEnvironmentError, SpcFormatError, SpcUsageError

__all__ = [
    "MAX_INPUT_BYTES",
    "MAX_NAME_LENGTH",
    "MAX_STDIN_BYTES",
    "check_allocation",
    "check_finite",
    "check_finite_header",
    "check_landmark_rows",
    "check_sum_header",
    "duplicate_landmarks",
    "first_nonfinite",
    "check_name",
    "check_regular",
    "is_valid_name",
    "read_bytes",
    "read_stdin",
    "input_scope",
    "refuse_input_overwrite",
    "refuse_read_input",
    "same_file",
]

#: longest picture/landmark name accepted (SPC's are 12 and 6 characters; other missions' a few more)
MAX_NAME_LENGTH = 64
#: largest input file read whole (bytes): far above any SPC file (a Q = 1024 ICQ is ~230 MB)
MAX_INPUT_BYTES = int(os.environ.get("SPCTOOL_MAX_INPUT_BYTES", 8 * 1024**3))
#: largest standard input read (bytes): a landmark table or a list, never a photo
MAX_STDIN_BYTES = int(os.environ.get("SPCTOOL_MAX_STDIN_BYTES", 256 * 1024**2))
#: a file larger than this whose allocated blocks cover less than 1/SPARSE_RATIO of its size is refused
SPARSE_MIN_BYTES = 16 * 1024**2
SPARSE_RATIO = 8
#: plain identifier: letters, digits, ``_ - + .``; not starting with ``.`` or ``-``
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+\-]*\Z")


def is_valid_name(name: str) -> bool:
    """True when ``name`` is a plain SPC identifier that can safely become part of a file name."""
    return (
        isinstance(name, str)
        and 0 < len(name) <= MAX_NAME_LENGTH
        and _NAME.match(name) is not None
        and ".." not in name
    )


def check_name(name: str, what: str = "name", source=None, where=None) -> str:
    """``name`` stripped, or SpcFormatError (``source`` given: the file it came from) / SpcUsageError
    naming it: a picture or landmark name must be a plain identifier (module docstring)."""
    text = name.strip() if isinstance(name, str) else name
    if is_valid_name(text):
        return text
    shown = repr(name)
    if len(shown) > 60:
        shown = shown[:57] + "..."
    expected = (
        f"a plain {what} (letters, digits, '_', '-', '+', '.'; at most {MAX_NAME_LENGTH} characters; "
        f"no path separators or '..'), got {shown}"
    )
    if source is not None:
        raise SpcFormatError(source, where, expected)
    raise SpcUsageError(f"expected {expected}")


def check_regular(path, what: str = "a file", max_bytes: int | None = None) -> int:
    """The size of ``path`` after checking it is a regular file (symbolic links followed) of at
    most ``max_bytes`` (default :data:`MAX_INPUT_BYTES`).  FIFOs, devices, sockets and directories
    are refused with one line (SpcFormatError); a missing file too."""
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise SpcFormatError(p, None, f"{what} (file not found)") from None
    except OSError as exc:
        raise SpcEnvironmentError.from_oserror(exc, p) from None
    mode = st.st_mode
    if not stat.S_ISREG(mode):
        kind = (
            "a directory"
            if stat.S_ISDIR(mode)
            else "a FIFO (named pipe)"
            if stat.S_ISFIFO(mode)
            else "a device"
            if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
            else "a socket"
            if stat.S_ISSOCK(mode)
            else "not a regular file"
        )
        raise SpcFormatError(p, None, f"{what} (a regular file), found {kind}")
    limit = MAX_INPUT_BYTES if max_bytes is None else int(max_bytes)
    if st.st_size > limit:
        raise SpcFormatError(
            p, None, f"{what} of at most {limit} bytes, found {st.st_size} bytes (SPCTOOL_MAX_INPUT_BYTES)"
        )
    _refuse_sparse(p, st, what)
    return st.st_size


def _refuse_sparse(p: Path, st, what: str) -> None:
    """A large file that is mostly holes (allocated blocks far below its size) holds zeros its header
    pretends are data: refused before it is read (the memory would be spent on nothing)."""
    blocks = getattr(st, "st_blocks", None)
    if blocks is None or st.st_size < SPARSE_MIN_BYTES:
        return
    on_disk = int(blocks) * 512
    if on_disk * SPARSE_RATIO < st.st_size:  # few blocks: holes, or a compressing file system
        on_disk = max(on_disk, _data_bytes(p, st.st_size))
    if on_disk * SPARSE_RATIO < st.st_size:
        raise SpcFormatError(
            p,
            None,
            f"{what} whose content is on disk: {st.st_size} bytes long but only {on_disk} bytes "
            "allocated (a sparse file: its holes are not data)",
        )


def _data_bytes(p: Path, size: int) -> int:
    """Bytes of ``p`` outside its holes (``SEEK_DATA`` / ``SEEK_HOLE``); ``size`` when the system
    cannot tell (then a compressing file system is not mistaken for holes)."""
    seek_data, seek_hole = getattr(os, "SEEK_DATA", None), getattr(os, "SEEK_HOLE", None)
    if seek_data is None or seek_hole is None:
        return size
    total, pos = 0, 0
    try:
        fd = os.open(p, os.O_RDONLY)
    except OSError:
        return size
    try:
        for _ in range(100_000):
            try:
                start = os.lseek(fd, pos, seek_data)
            except OSError:  # ENXIO: no data after pos
                break
            end = os.lseek(fd, start, seek_hole)
            total += end - start
            pos = end
            if pos >= size:
                break
        else:
            return size
    except OSError:
        return size
    finally:
        os.close(fd)
    return total


def read_stdin(what: str = "standard input", max_bytes: int | None = None, stream=None) -> bytes:
    """Standard input (``stream``: its binary buffer by default), at most ``max_bytes`` (default
    :data:`MAX_STDIN_BYTES`): read in chunks, refused with one line as soon as it is longer."""
    import sys

    limit = MAX_STDIN_BYTES if max_bytes is None else int(max_bytes)
    if stream is None:
        if sys.stdin is None:
            raise SpcUsageError(f"{what}: standard input is closed")
        stream = getattr(sys.stdin, "buffer", sys.stdin)
    chunks, total = [], 0
    while True:
        try:
            chunk = stream.read(min(1 << 20, limit + 1 - total))
        except OSError as exc:
            raise SpcEnvironmentError.from_oserror(exc, "<stdin>") from None
        if not chunk:
            break
        if isinstance(chunk, str):
            chunk = chunk.encode("utf-8", errors="surrogateescape")
        chunks.append(chunk)
        total += len(chunk)
        if total > limit:
            raise SpcFormatError(
                "<stdin>", None, f"{what} of at most {limit} bytes (SPCTOOL_MAX_STDIN_BYTES)"
            )
    return b"".join(chunks)


def check_finite(values, path, where, what: str) -> None:
    """SpcFormatError naming ``path`` and ``where`` (a line) when a value of ``values`` is NaN or
    infinite: ``what`` (e.g. "SCOBJ") must be finite numbers."""
    import math

    for k, v in enumerate(values):
        try:
            ok = math.isfinite(float(v))
        except (TypeError, ValueError, OverflowError):
            continue  # not a number: the parser's own checks speak for it
        if not ok:
            raise SpcFormatError(path, where, f"finite numbers ({what}), found {v!r} for value {k + 1}")


#: the header keys whose values a stage uses as pose, vector or camera (per format: SUM, NOM, LMK)
FINITE_KEYS = {
    "sum": ("npx", "mmfl", "scobj", "cx", "cy", "cz", "sz", "kmatrix", "distortion", "vso", "ptg"),
    "nom": ("frame", "scobj", "vso", "cx", "cy", "cz", "ptg"),
    "lmk": ("size", "vlm", "ux", "uy", "uz"),
}
_ATTRS = {"vso": "sigma_vso", "ptg": "sigma_ptg", "frame": "frame_vector"}


def _header_lines(obj):
    """(line, slot) of each header slot of a parsed SUM, NOM or LMK (``obj._source.header``, in file
    order; nothing for an object built in memory)."""
    line = 1
    for slot in getattr(getattr(obj, "_source", None), "header", None) or []:
        yield line, slot
        line += 0 if slot.text is None else slot.text.count("\n") + 1


def _line_of(obj, key: str) -> int | None:
    """The line of header ``key`` of a parsed file (None when unknown)."""
    return next((line for line, slot in _header_lines(obj) if slot.key == key), None)


def first_nonfinite(obj, keys) -> tuple[int | None, str] | None:
    """(line, label) of the first header value of a parsed SUM, NOM or LMK (``obj._source.header``,
    its slots in file order) among ``keys`` that is NaN or infinite — the values a stage would use —
    or None.  Values changed since parsing (or an object built in memory) are checked on the object
    itself (line None)."""
    import math

    import numpy as np

    for line, slot in _header_lines(obj):
        if slot.key in keys and slot.values is not None:
            for v in slot.values:
                if isinstance(v, float) and not math.isfinite(v):
                    return line, (slot.tag or slot.key.upper())
    for key in keys:
        value = getattr(obj, _ATTRS.get(key, key), None)
        if value is None or isinstance(value, str):
            continue
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            continue
        if not np.all(np.isfinite(arr)):
            return None, key.upper()
    return None


def check_finite_header(obj, path, kind: str) -> None:
    """SpcFormatError naming ``path`` and the line when a pose, vector or camera value of ``obj`` (a
    parsed SUM, NOM or LMK: ``kind``) is NaN or infinite (:func:`first_nonfinite`).  SPC's Fortran
    reads such a file (list-directed READ takes ``NaN``), so the readers do too; a stage refuses it."""
    found = first_nonfinite(obj, FINITE_KEYS[kind])
    if found is not None:
        line, label = found
        raise SpcFormatError(path, line, f"finite numbers ({label}), found NaN or Infinity")


#: how far a SUM's CX, CY, CZ may be from orthonormal before a stage refuses it (max |R Rᵀ − I|; SPC's
#: D20.10 rows are orthonormal to ~1e-10, the real files here to 1.3e-10; ``validate`` warns from 1e-5)
ROTATION_TOL = 1e-3


def check_sum_header(pic, path) -> None:
    """What every stage needs of a parsed SUM: :func:`check_finite_header`, CX, CY, CZ the rows of a
    proper rotation (orthonormal to :data:`ROTATION_TOL`, right-handed), MMFL positive and the
    K-MATRIX's 2 × 2 block invertible — SpcFormatError naming ``path`` and the line otherwise: a camera
    of a skewed frame would project every landmark wrong and a solve would report its misfit as the
    pose's; a zero focal length or K-matrix ended in a camera error that named no file."""
    import numpy as np

    check_finite_header(pic, path, "sum")
    m = np.asarray(pic.rotation, dtype=np.float64)
    err = float(np.abs(m @ m.T - np.eye(3)).max())
    if err > ROTATION_TOL or np.linalg.det(m) < 0.0:
        found = f"max |R R^T - I| = {err:.2g}" if err > ROTATION_TOL else "a left-handed frame"
        raise SpcFormatError(path, _line_of(pic, "cx"), f"CX, CY, CZ the rows of a rotation (orthonormal, "
                             f"right-handed), found {found}")
    if not float(pic.mmfl) > 0.0:
        raise SpcFormatError(path, _line_of(pic, "mmfl"), f"a positive MMFL, found {float(pic.mmfl):g}")
    k = np.asarray(pic.kmatrix, dtype=np.float64)
    if abs(np.linalg.det(k[:, :2])) < 1e-12:
        raise SpcFormatError(
            path, _line_of(pic, "kmatrix"), "a K-MATRIX whose 2 x 2 block is invertible (px/mm)"
        )


def duplicate_landmarks(pic) -> list[str]:
    """The landmark names on more than one of a SUM's LANDMARKS rows, sorted (linear: 100,000 rows in
    milliseconds)."""
    from collections import Counter

    return sorted(n for n, c in Counter(lm.name.strip() for lm in pic.landmarks).items() if c > 1)


def check_landmark_rows(pic, path) -> None:
    """SpcFormatError naming ``path`` when a landmark is on two LANDMARKS rows of a SUM a stage takes as
    measurements: it would be counted twice (a table's duplicate rows are refused the same way)."""
    twice = duplicate_landmarks(pic)
    if twice:
        shown = ", ".join(twice[:5]) + (f", ... ({len(twice)} landmarks)" if len(twice) > 5 else "")
        raise SpcFormatError(path, None, f"one LANDMARKS row per landmark, found {shown} on more than one")


def _identity(path) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return (st.st_dev, st.st_ino)


def same_file(a, b) -> bool:
    """True when ``a`` and ``b`` are the same file or directory (device and inode, links followed)."""
    ia = _identity(a)
    return ia is not None and ia == _identity(b)


def refuse_input_overwrite(output, inputs, what: str = "output") -> None:
    """SpcUsageError naming both paths when ``output`` (a file or a directory) is, by device and inode,
    one of ``inputs`` (files or directories: a symbolic link or a bind mount leading to them is seen
    through).  A path that does not exist yet is no input."""
    out_id = _identity(output)
    if out_id is None:
        return
    for src in inputs:
        if src is not None and _identity(src) == out_id:
            raise SpcUsageError(
                f"{what} {output} is the input {src} (same device and inode): refusing to overwrite "
                "what was read; choose another path"
            )


def read_bytes(path, what: str = "a file", max_bytes: int | None = None) -> bytes:
    """The content of a regular file (:func:`check_regular`), never more than its checked size."""
    p = Path(path)
    size = check_regular(p, what, max_bytes)
    try:
        with open(p, "rb") as fh:
            data = fh.read(size + 1)
            _note_input(p, os.fstat(fh.fileno()))
    except IsADirectoryError:
        raise SpcFormatError(p, None, f"{what}, found a directory") from None
    except OSError as exc:
        raise SpcEnvironmentError.from_oserror(exc, p) from None
    if len(data) > size:  # grew between stat and read: read what the cap allows, no more
        limit = MAX_INPUT_BYTES if max_bytes is None else int(max_bytes)
        if len(data) > limit:
            raise SpcFormatError(p, None, f"{what} of at most {limit} bytes (the file is growing)")
        with open(p, "rb") as fh:
            data = fh.read(limit + 1)
        if len(data) > limit:
            raise SpcFormatError(p, None, f"{what} of at most {limit} bytes (the file is growing)")
    return data


def check_allocation(nbytes: float, what: str, limit: int, where: str | None = None, hint: str = "") -> None:
    """SpcUsageError (or SpcFormatError when ``where`` names a file) when ``nbytes`` exceed ``limit``."""
    if nbytes <= limit:
        return
    text = f"{what} would need {_human(nbytes)}, more than the {_human(limit)} allowed{hint}"
    if where is not None:
        raise SpcFormatError(where, None, "expected sizes that fit in memory: " + text)
    raise SpcUsageError(text)


#: largest maplet half-size accepted by the stages ((2 QSZ + 1)^2 cells; SPC's are at most a few hundred)
MAX_QSZ = 4096


def landmark_geometry_problem(obj) -> str | None:
    """Why a landmark's (LMK) or maplet's (MAP) geometry cannot be used by a stage, or None: V/VLM
    finite, UX/UY/UZ a finite orthonormal frame, SCALE finite and positive, QSZ in 1 … MAX_QSZ.
    (A MAP with UX = 3.4e38 is a valid record but no maplet: every stage would overflow on it.)"""
    import numpy as np

    centre = getattr(obj, "vlm", None)
    if centre is None:
        centre = getattr(obj, "v", None)
    with np.errstate(all="ignore"):
        if centre is not None and not np.all(np.isfinite(np.asarray(centre, float))):
            return "a finite landmark position V"
        m = np.vstack([np.asarray(obj.ux, float), np.asarray(obj.uy, float), np.asarray(obj.uz, float)])
        if not np.all(np.isfinite(m)) or np.abs(m @ m.T - np.eye(3)).max() > 1e-3:
            return "an orthonormal frame UX, UY, UZ"
        scale = float(obj.scale)
        if not (np.isfinite(scale) and 0 < scale < 1e6):
            return f"a finite positive SCALE (km), found {scale:g}"
        if not 1 <= int(obj.qsz) <= MAX_QSZ:
            return f"QSZ in 1 ... {MAX_QSZ}, found {int(obj.qsz)}"
    return None


def check_landmark_geometry(obj, path):
    """``obj`` when :func:`landmark_geometry_problem` finds nothing, else SpcFormatError naming ``path``
    (and, for a NaN or Infinity in a parsed LMK header, its line: :func:`check_finite_header`)."""
    if getattr(getattr(obj, "_source", None), "header", None):
        check_finite_header(obj, path, "lmk")
    problem = landmark_geometry_problem(obj)
    if problem is not None:
        raise SpcFormatError(path, None, problem)
    return obj


def _human(nbytes: float) -> str:
    value = float(nbytes)
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if value < 1024 or unit == "PiB":
            return f"{value:.0f} {unit}" if unit == "bytes" else f"{value:.1f} {unit}"
        value /= 1024
    return f"{value:.1f} EiB"  # pragma: no cover


# ------------------------------------------------------------------------------------------------
# the files read by one command (or one batch picture): never replaced without a backup

_READ: dict[tuple[int, int], str] = {}
_SCOPE = {"depth": 0}
_SCOPE_LOCK = threading.Lock()
#: most files remembered in one scope (a batch picture reads a few dozen)
_MAX_REMEMBERED = 200_000


@contextlib.contextmanager
def input_scope():
    """Remember the files :func:`read_bytes` reads inside the ``with`` body (nested scopes share one
    record, cleared when the outermost ends)."""
    with _SCOPE_LOCK:
        if _SCOPE["depth"] == 0:
            _READ.clear()
        _SCOPE["depth"] += 1
    try:
        yield
    finally:
        with _SCOPE_LOCK:
            _SCOPE["depth"] -= 1
            if _SCOPE["depth"] == 0:
                _READ.clear()


def _note_input(path, st) -> None:
    if _SCOPE["depth"] and len(_READ) < _MAX_REMEMBERED:
        _READ[(st.st_dev, st.st_ino)] = os.fspath(path)


def refuse_read_input(output) -> None:
    """SpcUsageError naming both paths when ``output`` is, by device and inode, a file read in the
    current :func:`input_scope` (and the path it was read by still leads to it: an inode number
    reused by a new file is no match)."""
    if not _READ:
        return
    ident = _identity(output)
    if ident is None:
        return
    src = _READ.get(ident)
    if src is not None and _identity(src) == ident:
        raise SpcUsageError(
            f"refusing to replace {output}: it is the input {src} (same device and inode), read by this "
            "command; choose an output path that is not an input"
        )
