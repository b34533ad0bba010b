"""Shared pieces of the command line: context, output, progress, messages."""

from __future__ import annotations

import sys
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import click

from spctool.formats import atomic
from spctool.formats.workdir import WorkDir


@dataclass
class Context:
    workdir: str = "."
    settings_path: str | None = None
    verbosity: int = 0
    debug: bool = False
    _said: set = field(default_factory=set)

    @property
    def wd(self) -> WorkDir:
        return WorkDir(Path(self.workdir))

    def settings(self):
        return self.wd.read_settings(self.settings_path)

    def info(self, message: str, level: int = 1) -> None:
        """A message on stderr when ``-v`` was given ``level`` times (never on stdout)."""
        if self.verbosity >= level:
            click.echo(f"spctool: {message}", err=True)

    def note_once(self, message: str) -> None:
        """A one-time note on stderr (e.g. 'no shape: occlusion skipped'), silenced by -q."""
        if self.verbosity >= 0 and message not in self._said:
            self._said.add(message)
            click.echo(f"spctool: note: {message}", err=True)


pass_context = click.make_pass_decorator(Context, ensure=True)


def emit(text: str, output: str | None = None, *, overwrite: bool = True) -> None:
    """Write ``text`` to ``output`` atomically, or to stdout when ``output`` is None or '-'."""
    if output is None or output == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
    else:
        atomic.write_bytes(output, text.encode("utf-8"), overwrite=overwrite)


def emit_table(table, *, as_json: bool, output: str | None = None) -> None:
    emit(table.to_json() if as_json else table.to_text(), output)


def json_option(f):
    return click.option("--json", "as_json", is_flag=True, help="Write one JSON document instead of text.")(f)


def output_option(f):
    return click.option(
        "-o",
        "--output",
        "output",
        metavar="FILE",
        default=None,
        help="Write the table to FILE instead of stdout ('-' = stdout).",
    )(f)


@contextmanager
def progress(ctx: Context, description: str, total: int | None):
    """A rich progress bar on a TTY; silent otherwise (and with -q).  Yields ``advance(n=1)``."""
    if ctx.verbosity < 0 or not sys.stderr.isatty():
        yield lambda n=1: None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        transient=True,
    ) as bar:
        task = bar.add_task(description, total=total)
        yield lambda n=1: bar.advance(task, n)


def resolve_landmarks(ctx: Context, specs=(), table: str | None = None) -> list:
    """Landmarks (``Landmark`` from LMK files) named on the command line.

    ``specs`` may mix landmark names (resolved to ``LMKFILES/<NAME>.LMK``), LMK file paths and
    landmark-table files; ``table`` is a landmark table (``-`` = stdin) whose ``name`` column is used.
    With neither, every landmark of LMRKLIST.TXT (else LMKFILES/*.LMK) is taken.
    """
    from spctool.formats.table import read_table

    names: list[str] = []
    direct = []
    if table:
        names += read_table(table).names
    for spec in specs:
        p = Path(spec)
        if p.is_file() and p.suffix.upper() == ".LMK":
            direct.append(ctx.wd.read_landmark(str(p)))
        elif p.is_file():
            names += read_table(p).names
        else:
            names.append(spec)
    if not specs and not table:
        names = ctx.wd.landmark_names()
    return direct + [ctx.wd.read_landmark(n) for n in names]
