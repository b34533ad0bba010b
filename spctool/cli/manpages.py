"""Man pages generated from the click commands, so that ``man/`` never drifts from ``--help``; and
``spctool man NAME``, which shows one of them (or installs all), so installed copies never drift either.

``python -m spctool.cli.manpages man/`` rewrites ``man/spctool.1`` and one
``man/spctool-COMMAND.1`` per command; ``tests/test_cli_manpages.py`` fails
when a committed page differs from what the current ``--help`` text gives.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import click

from spctool import __version__
from spctool.cli.common import Context, pass_context
from spctool.cli.completion import complete_command
from spctool.errors import SpcUsageError


def _escape(text: str) -> str:
    out = []
    for line in text.splitlines():
        line = line.replace("\\", "\\e")
        if line.startswith((".", "'")):
            line = "\\&" + line
        out.append(line)
    return "\n".join(out)


def _paragraphs(help_text: str) -> str:
    """click help text -> troff: blank lines become .PP, \\b blocks become .nf/.fi."""
    lines = help_text.strip("\n").splitlines()
    out: list[str] = []
    verbatim = False
    for line in lines:
        stripped = line.strip()
        if stripped == "\b":
            out.append(".nf")
            verbatim = True
            continue
        if not stripped:
            if verbatim:
                out.append(".fi")
                verbatim = False
            out.append(".PP")
            continue
        out.append(_escape(line if verbatim else stripped))
    if verbatim:
        out.append(".fi")
    return "\n".join(out)


def render(command: click.Command, path: list[str]) -> str:
    name = "-".join(path)
    ctx = click.Context(command, info_name=" ".join(path), help_option_names=["-h", "--help"])
    summary = command.get_short_help_str(limit=120)
    usage = " ".join(command.collect_usage_pieces(ctx))
    parts = [
        f'.TH {name.upper()} 1 "" "spctool {__version__}" "spctool manual"',
        ".SH NAME",
        f"{_escape(name)} \\- {_escape(summary)}",
        ".SH SYNOPSIS",
        f".B {_escape(' '.join(path))}",
        _escape(usage),
        ".SH DESCRIPTION",
        _paragraphs(command.help or ""),
    ]
    params = [p for p in command.get_params(ctx) if isinstance(p, click.Option) and not p.hidden]
    if params:
        parts.append(".SH OPTIONS")
        for p in params:
            record = p.get_help_record(ctx)
            if record is None:
                continue
            opts, text = record
            parts.append(".TP")
            parts.append(f".B {_escape(opts)}")
            parts.append(_escape(text or ""))
    if isinstance(command, click.Group):
        parts.append(".SH COMMANDS")
        for sub in command.list_commands(ctx):
            c = command.get_command(ctx, sub)
            parts.append(".TP")
            parts.append(f".B {sub}")
            parts.append(_escape(c.get_short_help_str(limit=120)))
            parts.append(f"See \\fB{name}-{sub}\\fR(1).")
    parts += _common_sections()
    parts.append(".SH SEE ALSO")
    parts.append("\\fBspctool\\fR(1)" if len(path) > 1 else "spctool-COMMAND(1) for each command")
    return "\n".join(parts) + "\n"


#: files every command finds in the working directory (cli-contract.md "Invocation")
FILES = (
    (
        "SUMFILES/PIC.SUM",
        "picture: pose, camera, LANDMARKS (a PICTURE given as DIR/SUMFILES/PIC.SUM makes "
        "DIR the working directory)",
    ),
    ("NOMINALS/PIC.NOM", "nominal pose"),
    ("IMAGEFILES[1-9]/PIC.DAT", "photo (also .FITS, .PGM, .PNG with the same stem)"),
    ("MAPFILES/LMK.MAP", "maplet (then EXTFILES/)"),
    ("LMKFILES/LMK.LMK", "landmark position and sigmas"),
    ("SHAPEFILES/SHAPE.TXT", "global shape (ICQ; OBJ/VTK with --shape)"),
    (
        "INIT_LITHOS.TXT",
        "settings, camera DISTORT= model (without one a picture is projected without "
        "distortion, with a note)",
    ),
    ("PICTLIST.TXT, LMRKLIST.TXT", "pictures and landmarks in use (PICTLISTX.TXT preferred)"),
    ("FILE.bak", "the previous content of every file spctool replaces (outputs and inputs alike)"),
)

#: environment variables spctool reads
ENVIRONMENT = (
    (
        "SPCTOOL_START_METHOD",
        "batch, montecarlo: force how local workers start (fork, spawn, forkserver); spawn or "
        "forkserver: register and navigate in maplet space fork no workers (threads instead)",
    ),
    (
        "NUMBA_NUM_THREADS",
        "threads of the compiled kernels (one per batch worker); register's and navigate's "
        "default --threads",
    ),
    ("NUMBA_CACHE_DIR", "where numba caches its compiled kernels"),
    (
        "OPENBLAS_NUM_THREADS",
        "threads of NumPy/SciPy's OpenBLAS: 1 unless set (spctool parallelises its own work)",
    ),
)


def _common_sections() -> list[str]:
    """EXIT STATUS, FILES and ENVIRONMENT: the same for every page."""
    from spctool.errors import EXIT_CODES

    parts = [".SH EXIT STATUS"]
    for code, text in EXIT_CODES.items():
        parts += [".TP", f".B {code}", _escape(text)]
    parts.append(".SH FILES")
    parts.append(
        "Paths are relative to the working directory, \\fB-C\\fR DIR (like git \\fB-C\\fR: relative paths "
        "on the command line are relative to DIR too), else the current directory."
    )
    for name, text in FILES:
        parts += [".TP", f".I {_escape(name)}", _escape(text)]
    parts.append(".SH ENVIRONMENT")
    for name, text in ENVIRONMENT:
        parts += [".TP", f".B {name}", _escape(text)]
    return parts


def all_pages() -> dict[str, str]:
    from spctool.cli.main import cli

    pages = {"spctool.1": render(cli, ["spctool"])}
    ctx = click.Context(cli, info_name="spctool", help_option_names=["-h", "--help"])
    for sub in cli.list_commands(ctx):
        command = cli.get_command(ctx, sub)
        pages[f"spctool-{sub}.1"] = render(command, ["spctool", sub])
    return pages


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


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    folder = Path(argv[0] if argv else "man")
    folder.mkdir(parents=True, exist_ok=True)
    pages = all_pages()
    for old in folder.glob("spctool*.1"):
        if old.name not in pages:
            old.unlink()
    for name, text in pages.items():
        (folder / name).write_text(text)
    print(f"wrote {len(pages)} man pages to {folder}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
