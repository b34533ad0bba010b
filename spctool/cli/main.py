"""The ``spctool`` command group: global options, error handling, subcommand registry."""

from __future__ import annotations

import click

from spctool import __version__


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="spctool")
def cli():
    """spctool — surface-feature optical navigation the SPC way."""
