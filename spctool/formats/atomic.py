"""Safe output: every file is written to a temporary name beside it and renamed.

Nothing is lost: an existing file is replaced only when the caller asks
(``overwrite=True``), and with ``backup=True`` the old content is kept as
``NAME.bak`` (``NAME.bak1``, ``NAME.bak2``… if that exists already).  The backup
is itself written atomically — copied to a temporary file, flushed, then renamed —
so a kill or a full disk never leaves a truncated or empty ``.bak`` standing in for
the original.  A temporary file left by a process killed between writing and
renaming (``.NAME.XXXXXXXX.tmp``) is removed by :func:`remove_stale_temps` (a
resumed batch calls it).

Every refusal of the operating system (permission denied, read-only file system,
disk full, I/O error, too many open files) is raised as
:class:`~spctool.errors.SpcEnvironmentError` naming the user's file — never the
hidden temporary one — so the command line reports it on one line with exit 3.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from spctool.errors import SpcEnvironmentError, SpcFormatError, SpcUsageError

#: suffix of the temporary files written beside their target
TMP_SUFFIX = ".tmp"


def backup_path(path: Path) -> Path:
    """The first free backup name for ``path``: ``NAME.bak``, then ``NAME.bak1``…"""
    candidate = path.with_name(path.name + ".bak")
    n = 1
    while candidate.exists():
        candidate = path.with_name(f"{path.name}.bak{n}")
        n += 1
    return candidate


def _temp_beside(path: Path) -> tuple[int, str]:
    return tempfile.mkstemp(prefix=f".{path.name}.", suffix=TMP_SUFFIX, dir=path.parent)


def _unlink_quietly(name) -> None:
    try:
        os.unlink(name)
    except OSError:
        pass


def _copy_backup(path: Path) -> Path:
    """Copy ``path`` to its backup name atomically (temporary copy, fsync, rename); the backup
    name is claimed with ``os.link`` so two writers never share one."""
    fd, tmp = _temp_beside(path)
    try:
        with os.fdopen(fd, "wb") as dst, open(path, "rb") as src:
            shutil.copyfileobj(src, dst, 1 << 20)
            dst.flush()
            os.fsync(dst.fileno())
        shutil.copystat(path, tmp)
        while True:
            kept = backup_path(path)
            try:
                os.link(tmp, kept)  # fails if another process took the name meanwhile
                break
            except FileExistsError:
                continue
            except OSError:  # no hard links here (some network file systems): plain rename
                if kept.exists():
                    continue
                os.replace(tmp, kept)
                return kept
        os.unlink(tmp)
        return kept
    except BaseException:
        _unlink_quietly(tmp)
        raise


def write_bytes(path, data: bytes, *, overwrite: bool = True, backup: bool = False) -> Path | None:
    """Write ``data`` to ``path`` atomically; return the backup path if one was made."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise SpcUsageError(f"{path}: exists already (use --force or another name)")
    if path.is_dir():
        raise SpcUsageError(f"{path}: is a directory, cannot write a file there")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        kept = _copy_backup(path) if backup and path.exists() else None
        fd, tmp = _temp_beside(path)
    except OSError as exc:
        raise SpcEnvironmentError.from_oserror(exc, path) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        if path.exists():
            shutil.copymode(path, tmp)
        else:  # mkstemp creates 0600; a new file gets the usual 0666 less the umask
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException as exc:
        _unlink_quietly(tmp)
        if isinstance(exc, OSError):
            raise SpcEnvironmentError.from_oserror(exc, path) from None
        raise
    return kept


def write_text(path, text: str, *, overwrite: bool = True, backup: bool = False) -> Path | None:
    """Write ASCII/Latin-1 text atomically (SPC files are Latin-1, ``\\n`` line ends)."""
    return write_bytes(path, text.encode("latin-1"), overwrite=overwrite, backup=backup)


def remove_stale_temps(path) -> list[Path]:
    """Remove the temporary files of ``path`` (``.NAME.XXXXXXXX.tmp`` beside it) that a process
    killed between writing and renaming left behind; returns those removed.  Call it only when no
    other process is writing ``path``."""
    path = Path(path)
    removed = []
    try:
        candidates = list(path.parent.glob(f".{_glob_escape(path.name)}.*{TMP_SUFFIX}"))
    except OSError:
        return removed
    for p in candidates:
        middle = p.name[len(path.name) + 2 : -len(TMP_SUFFIX)]
        if len(middle) == 8 and "." not in middle:  # mkstemp's 8 random characters, nothing else
            try:
                p.unlink()
                removed.append(p)
            except OSError:
                pass
    return removed


def _glob_escape(name: str) -> str:
    return "".join(f"[{c}]" if c in "*?[]" else c for c in name)


def read_text(path) -> str:
    """Read an SPC text file: Latin-1, ``\\r`` stripped.  Only regular files are read (a FIFO or
    ``/dev/zero`` is refused with one line, :func:`spctool.formats.guard.read_bytes`)."""
    from spctool.formats.guard import read_bytes

    data = read_bytes(path)
    return data.decode("latin-1").replace("\r\n", "\n").replace("\r", "\n")


def read_spc_file(path, what: str) -> str:
    """:func:`read_text` of an SPC file of kind ``what`` (``"SUM"``, ``"LMK"`` ...); an unreadable file is
    one :class:`~spctool.errors.SpcFormatError` naming the path: "expected a readable <what> file"."""
    try:
        return read_text(path)
    except OSError as exc:
        raise SpcFormatError(path, None, f"expected a readable {what} file ({exc.strerror})") from None
