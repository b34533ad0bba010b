"""Shell completion of picture and landmark names, and ``spctool man``.

Completion is click's (``_SPCTOOL_COMPLETE=bash_source spctool``, see the README); the callbacks here
make PICTURE arguments complete to the pictures of the working directory (``-C DIR``, else the current
directory: SUMFILES/*.SUM and PICTLIST.TXT) and LANDMARK arguments to its landmarks (LMKFILES/*.LMK,
MAPFILES/*.MAP and LMRKLIST.TXT).  They only list file names: no file is parsed beyond the two lists,
nothing heavy is imported, and a missing folder completes to nothing.

``spctool man NAME`` shows the man page of a command, generated from its ``--help``
(:mod:`spctool.cli.manpages`), so installed copies never drift from the code.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import click
from click.shell_completion import CompletionItem

from spctool.cli.common import Context, pass_context


def _workdir(ctx: click.Context) -> Path:
    root = ctx.find_root()
    return Path(root.params.get("workdir") or ".")


def _list_names(path: Path) -> list[str]:
    """Names in a PICTLIST.TXT / LMRKLIST.TXT (first word per line; 'END' and comments stop/skip)."""
    names = []
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return names
    for line in text.splitlines():
        word = line.strip().split()[0] if line.strip() else ""
        if word.upper() == "END":
            break
        word = word.lstrip("!#")  # flagged entries are still names
        if word:
            names.append(word)
    return names


def _stems(folder: Path, suffix: str) -> list[str]:
    try:
        return [p.stem for p in folder.iterdir() if p.suffix.upper() == suffix]
    except OSError:
        return []


def picture_names(workdir) -> list[str]:
    """Sorted picture names of a working directory (SUMFILES/*.SUM and PICTLIST.TXT)."""
    wd = Path(workdir)
    return sorted(set(_stems(wd / "SUMFILES", ".SUM")) | set(_list_names(wd / "PICTLIST.TXT")))


def landmark_names(workdir) -> list[str]:
    """Sorted landmark names of a working directory (LMKFILES/, MAPFILES/ and LMRKLIST.TXT)."""
    wd = Path(workdir)
    names = set(_stems(wd / "LMKFILES", ".LMK")) | set(_stems(wd / "MAPFILES", ".MAP"))
    return sorted(names | set(_list_names(wd / "LMRKLIST.TXT")))


def _matching(names, incomplete: str) -> list[CompletionItem]:
    low = incomplete.lower()
    return [CompletionItem(n) for n in names if n.lower().startswith(low)]


def complete_picture(ctx: click.Context, param, incomplete: str):
    """PICTURE: the working directory's pictures, else files (a .SUM path is a picture too)."""
    items = _matching(picture_names(_workdir(ctx)), incomplete)
    return items or [CompletionItem(incomplete, type="file")]


def complete_landmark(ctx: click.Context, param, incomplete: str):
    """LANDMARK: the working directory's landmarks (not those already on the line), else files."""
    given = set(ctx.params.get(param.name) or ())
    items = [i for i in _matching(landmark_names(_workdir(ctx)), incomplete) if i.value not in given]
    return items or [CompletionItem(incomplete, type="file")]


def complete_command(ctx: click.Context, param, incomplete: str):
    from spctool.cli.main import COMMANDS

    return [CompletionItem(n) for n in ["spctool", *COMMANDS] if n.startswith(incomplete)]


# ------------------------------------------------------------------------------------------------
# spctool man


@click.command("man")
@click.argument("name", required=False, default="spctool", shell_complete=complete_command)
@click.option(
    "--install",
    "install_dir",
    metavar="DIR",
    type=click.Path(file_okay=False),
    default=None,
    help="Write every page (spctool.1, spctool-COMMAND.1) to DIR instead, e.g. ~/.local/share/man/man1.",
)
@click.option("--raw", is_flag=True, help="Print the roff source instead of formatting it with man(1).")
@pass_context
def man_cmd(ctx: Context, name, install_dir, raw):
    """Show the man page of spctool or of one command, or install all of them.

    NAME is a command (register, solve-pose, ...) or 'spctool' (the default).  The pages are
    generated from the commands' --help, so they always match the installed version.  On a
    terminal the page is formatted by man(1) (through your pager); otherwise, or with --raw, the
    roff source is printed.  --install DIR writes every page to DIR: with DIR =
    ~/.local/share/man/man1 (or any man1 folder on your MANPATH), 'man spctool-register' works.
    Exit code 2 for an unknown NAME.

    Example:

    \b
      spctool man register
      spctool man --install mandir/man1 && man -M mandir spctool-register
      spctool man solve-pose --raw > spctool-solve-pose.1
    """
    from spctool.cli.manpages import all_pages
    from spctool.errors import SpcUsageError
    from spctool.formats import atomic

    pages = all_pages()
    if install_dir:
        folder = Path(install_dir).expanduser()
        folder.mkdir(parents=True, exist_ok=True)
        for page, text in pages.items():
            atomic.write_bytes(folder / page, text.encode("utf-8"))
        click.echo(f"wrote {len(pages)} man pages to {folder}")
        return
    page = "spctool.1" if name in ("spctool", "") else f"spctool-{name}.1"
    if page not in pages:
        known = ", ".join(sorted(p[8:-2] for p in pages if p != "spctool.1"))
        raise SpcUsageError(f"no man page for {name!r} (commands: {known})")
    text = pages[page]
    viewer = shutil.which("man")
    if raw or viewer is None or not sys.stdout.isatty():
        click.echo(text, nl=False)
        return
    with tempfile.TemporaryDirectory(prefix="spctool-man-") as tmp:
        path = Path(tmp) / page
        path.write_text(text)
        subprocess.run([viewer, "-l", str(path)], check=False, env=os.environ.copy())


def register(cli):
    cli.add_command(man_cmd)
