"""Shell completion of picture, landmark and command names.

Completion is click's (``_SPCTOOL_COMPLETE=bash_source spctool``, see the README); the callbacks here
make PICTURE arguments complete to the pictures of the working directory (``-C DIR``, else the current
directory: SUMFILES/*.SUM and PICTLIST.TXT) and LANDMARK arguments to its landmarks (LMKFILES/*.LMK,
MAPFILES/*.MAP and LMRKLIST.TXT).  They only list file names: no file is parsed beyond the two lists,
nothing heavy is imported, and a missing folder completes to nothing.  (``spctool man`` lives with the
pages it shows, in :mod:`spctool.cli.manpages`.)
"""

from __future__ import annotations

from pathlib import Path

import click
from click.shell_completion import CompletionItem


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
    from spctool.cli.commands import COMMANDS

    return [CompletionItem(n) for n in ["spctool", *COMMANDS] if n.startswith(incomplete)]
