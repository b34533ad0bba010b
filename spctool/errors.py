"""Error types shared by every layer.

Every problem with an input file is raised as :class:`SpcFormatError`, which
names the file, the place (1-based line, or 0-based byte offset for binary
files) and what was expected.  The command line turns it into the single stderr
line ``spctool: error: FILE:LINE: expected …`` and exit code 2.
"""

from __future__ import annotations

import os


class SpcError(Exception):
    """Base class of every error spctool reports to the user (exit code 2)."""

    exit_code = 2


class SpcFormatError(SpcError):
    """Malformed input: names the file, the line (or byte) and what was expected."""

    def __init__(self, path: str | os.PathLike | None, where: int | str | None, expected: str):
        self.path = os.fspath(path) if path is not None else "<input>"
        self.where = where
        self.expected = expected
        super().__init__(str(self))

    def __str__(self) -> str:
        if self.where is None:
            place = self.path
        elif isinstance(self.where, int):
            place = f"{self.path}:{self.where}"
        else:
            place = f"{self.path}:{self.where}"
        text = self.expected
        if not text.startswith(("expected", "unexpected")):
            text = "expected " + text
        return f"{place}: {text}"

    def at(self, path) -> SpcFormatError:
        """Return a copy that names ``path`` (for errors raised on in-memory text)."""
        return SpcFormatError(path, self.where, self.expected)


class SpcUsageError(SpcError):
    """Bad command-line usage that click itself cannot detect (exit code 2)."""


class SpcEnvironmentError(SpcError):
    """The machine refused: permissions, a full disk, an I/O error (exit code 3).

    Names the user's path (never a hidden temporary file) and what went wrong.
    """

    exit_code = 3

    def __init__(self, path: str | os.PathLike | None, reason: str):
        self.path = os.fspath(path) if path is not None else "<output>"
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")

    @classmethod
    def from_oserror(cls, exc: OSError, path: str | os.PathLike | None = None) -> SpcEnvironmentError:
        """Wrap ``exc``; ``path`` (the user's file) wins over the name the OS reported."""
        where = path if path is not None else (exc.filename if exc.filename is not None else None)
        if exc.strerror:
            reason = exc.strerror[:1].lower() + exc.strerror[1:]
        else:
            reason = str(exc) or type(exc).__name__
        return cls(where, reason)


#: documented exit codes of every command (cli --help, man EXIT STATUS, README)
EXIT_CODES = {
    0: "success",
    1: "the command ran but its result failed a requirement (e.g. nothing registered, implausible pose)",
    2: "bad usage or bad input (one line on stderr naming the file, the line and what was expected)",
    3: "environment: permission denied, disk full, I/O error (the line names your path)",
    130: "interrupted (Ctrl-C)",
}


def exit_codes_text() -> str:
    """The exit codes as ``CODE  meaning`` lines (top-level --help epilog, man EXIT STATUS, README)."""
    return "\n".join(f"{code:>3}  {text}" for code, text in EXIT_CODES.items())


class SpcResultError(SpcError):
    """The command ran but its result failed a requested check (exit code 1)."""

    exit_code = 1
