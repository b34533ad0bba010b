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


class SpcResultError(SpcError):
    """The command ran but its result failed a requested check (exit code 1)."""

    exit_code = 1
