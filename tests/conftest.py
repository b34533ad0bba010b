"""Shared test fixtures: paths to the real mission files and a CLI runner."""

from pathlib import Path

import pytest
from click.testing import CliRunner

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / "fixtures" / "real"


@pytest.fixture
def real():
    return REAL


@pytest.fixture
def run_cli():
    """Run ``spctool ARGS``; returns click's Result with separate .stdout / .stderr."""
    from spctool.cli.main import cli

    def _run(*args, input=None):
        return CliRunner().invoke(cli, [str(a) for a in args], input=input, catch_exceptions=False)

    return _run
