"""One batch at a time per output directory: an advisory lock file holding its holder's PID and host.

Two batches writing one ``--out-dir`` at once would clear and rewrite each other's pictures (issue #41:
one of eight trials failed a picture spuriously).  :func:`out_dir_lock` takes ``OUT/.spctool-batch.lock``
with ``flock`` (advisory, exclusive, never waiting): a second batch is refused at once with one line
naming the holder ("PID 1234 on host …, since …").  The kernel releases the lock when its holder ends
in any way (SIGKILL, a crash), so a lock left by a dead process is taken over; its file still names
that holder, and the batch reports the take-over in a note.  The file is removed when the batch ends.

Where ``flock`` is not available the file itself is the lock (created exclusively); a lock file whose
holder is on this host and no longer runs is then taken over the same way.
"""

from __future__ import annotations

import contextlib
import datetime
import os
import socket
from collections.abc import Callable, Iterator
from pathlib import Path

from spctool.errors import SpcEnvironmentError, SpcUsageError

__all__ = ["LOCK_NAME", "out_dir_lock"]

#: the lock file in the output directory
LOCK_NAME = ".spctool-batch.lock"


def _holder_text() -> str:
    now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    return f"pid {os.getpid()}\nhost {socket.gethostname()}\nsince {now}\n"


def _parse(text: str) -> dict[str, str]:
    out = {}
    for line in text.splitlines():
        key, _, value = line.partition(" ")
        if key in ("pid", "host", "since"):
            out[key] = value.strip()
    return out


def _describe(info: dict[str, str]) -> str:
    if not info:
        return "an unknown process"
    text = f"PID {info.get('pid', '?')} on host {info.get('host', '?')}"
    return text + (f", since {info['since']}" if info.get("since") else "")


def _alive_here(info: dict[str, str]) -> bool:
    """True unless the holder is a process of this host that no longer exists."""
    if info.get("host") != socket.gethostname():
        return True  # cannot tell: assume it runs
    try:
        os.kill(int(info.get("pid", "")), 0)
    except (ValueError, ProcessLookupError):
        return False
    except PermissionError:
        return True
    return True


def _read(fd: int) -> str:
    os.lseek(fd, 0, os.SEEK_SET)
    return os.read(fd, 4096).decode("utf-8", errors="replace")


def _write(fd: int) -> None:
    os.lseek(fd, 0, os.SEEK_SET)
    os.ftruncate(fd, 0)
    os.write(fd, _holder_text().encode("utf-8"))
    os.fsync(fd)


@contextlib.contextmanager
def out_dir_lock(out_dir, note: Callable[[str], None] | None = None) -> Iterator[Path]:
    """Hold the batch lock of ``out_dir`` (an existing directory) for the ``with`` body (module
    docstring); ``note(text)`` is told when a stale lock was taken over."""
    path = Path(out_dir) / LOCK_NAME
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        fcntl = None
    if fcntl is None:  # pragma: no cover
        yield from _exclusive_file(path, note)
        return
    for _attempt in range(10):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as exc:
            raise SpcEnvironmentError.from_oserror(exc, path) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            info = _parse(_read(fd))
            os.close(fd)
            raise SpcUsageError(
                f"{out_dir}: another batch is writing there ({_describe(info)}; lock file {path}): "
                "wait for it to end or choose another --out-dir"
            ) from None
        except OSError:  # no flock on this file system: the file itself is the lock
            os.close(fd)
            yield from _exclusive_file(path, note)
            return
        # the file may have been removed by the holder that just ended: lock the file that is there
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path, follow_symlinks=False))
        except OSError:
            same = False
        if not same:
            os.close(fd)
            continue
        break
    else:  # pragma: no cover - ten holders ended in ten attempts
        raise SpcUsageError(f"{out_dir}: could not take the batch lock {path} (it changes hands constantly)")
    try:
        previous = _parse(_read(fd))
        if previous and note is not None:
            note(f"took over the lock of a batch that did not end ({_describe(previous)}): {path}")
        _write(fd)
        yield path
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)
        os.close(fd)


def _exclusive_file(path: Path, note) -> Iterator[Path]:
    """The lock as a file created exclusively (no ``flock``); a dead holder of this host is replaced."""
    for _attempt in range(3):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
            break
        except FileExistsError:
            try:
                info = _parse(path.read_text(encoding="utf-8", errors="replace"))
            except OSError:
                info = {}
            if _alive_here(info):
                raise SpcUsageError(
                    f"{path.parent}: another batch is writing there ({_describe(info)}; lock file {path}): "
                    "wait for it to end or choose another --out-dir"
                ) from None
            if note is not None:
                note(f"took over the lock of a batch that did not end ({_describe(info)}): {path}")
            with contextlib.suppress(OSError):
                path.unlink()
        except OSError as exc:
            raise SpcEnvironmentError.from_oserror(exc, path) from None
    else:
        raise SpcUsageError(f"{path.parent}: could not take the batch lock {path}")
    try:
        _write(fd)
        yield path
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)
        os.close(fd)
