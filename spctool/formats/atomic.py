"""Safe output: every file is written to a temporary name beside it and renamed.

Nothing is lost: an existing file is replaced only when the caller asks
(``overwrite=True``), and with ``backup=True`` the old content is kept as
``NAME.bak`` (``NAME.bak1``, ``NAME.bak2``… if that exists already).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from spctool.errors import SpcUsageError


def backup_path(path: Path) -> Path:
    """The first free backup name for ``path``: ``NAME.bak``, then ``NAME.bak1``…"""
    candidate = path.with_name(path.name + ".bak")
    n = 1
    while candidate.exists():
        candidate = path.with_name(f"{path.name}.bak{n}")
        n += 1
    return candidate


def write_bytes(path, data: bytes, *, overwrite: bool = True, backup: bool = False) -> Path | None:
    """Write ``data`` to ``path`` atomically; return the backup path if one was made."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise SpcUsageError(f"{path}: exists already (use --force or another name)")
    path.parent.mkdir(parents=True, exist_ok=True)
    kept = None
    if backup and path.exists():
        kept = backup_path(path)
        shutil.copy2(path, kept)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
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
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return kept


def write_text(path, text: str, *, overwrite: bool = True, backup: bool = False) -> Path | None:
    """Write ASCII/Latin-1 text atomically (SPC files are Latin-1, ``\\n`` line ends)."""
    return write_bytes(path, text.encode("latin-1"), overwrite=overwrite, backup=backup)


def read_text(path) -> str:
    """Read an SPC text file: Latin-1, ``\\r`` stripped."""
    data = Path(path).read_bytes()
    return data.decode("latin-1").replace("\r\n", "\n").replace("\r", "\n")
