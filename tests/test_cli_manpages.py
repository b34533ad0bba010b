"""Every command has a man page in man/ that matches its --help.

Regenerate with ``python -m spctool.cli.manpages man/``.
"""

from pathlib import Path

import click

from spctool.cli.main import cli
from spctool.cli.manpages import all_pages

MAN = Path(__file__).resolve().parents[1] / "man"


def test_man_pages_match_help():
    pages = all_pages()
    stale = [
        name for name, text in pages.items() if not (MAN / name).exists() or (MAN / name).read_text() != text
    ]
    extra = sorted(p.name for p in MAN.glob("spctool*.1") if p.name not in pages)
    assert not stale, f"man pages out of date: {stale}; run python -m spctool.cli.manpages man/"
    assert not extra, f"man pages for commands that do not exist: {extra}"


def test_every_command_has_an_example():
    ctx = click.Context(cli, info_name="spctool")
    for name in cli.list_commands(ctx):
        command = cli.get_command(ctx, name)
        assert "Example" in (command.help or ""), f"spctool {name} --help has no example"
        assert f"spctool-{name}.1" in all_pages()
