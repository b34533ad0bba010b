"""Shared test fixtures: paths to the real mission files and a CLI runner; the slow tests' switch.

Tests marked ``slow`` (a few minutes between them) are skipped by a plain ``pytest``, which then takes
about the README's time on two cores; CI (``.ci/run``) sets ``SPCTOOL_SLOW_TESTS=1`` and runs them all,
and so does any explicit ``-m`` selection (``pytest -m slow``: only those).
"""

import os
import tempfile
from pathlib import Path

import pytest
from click.testing import CliRunner

# the cache of derived values (spctool.formats.derived) of the tests' processes and of the commands
# they start: one folder per test run's machine user, never the user's own ~/.cache/spctool
_CACHE = Path(tempfile.gettempdir()) / f"spctool-test-cache-{os.getuid()}"
os.environ.setdefault("SPCTOOL_CACHE_DIR", str(_CACHE))

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


def pytest_collection_modifyitems(config, items):
    """Skip the tests marked slow unless SPCTOOL_SLOW_TESTS=1 or a -m selection is given."""
    if os.environ.get("SPCTOOL_SLOW_TESTS") == "1" or config.getoption("markexpr", ""):
        return
    skip = pytest.mark.skip(reason="slow: CI runs it (SPCTOOL_SLOW_TESTS=1 pytest, or pytest -m slow)")
    for item in items:
        if item.get_closest_marker("slow") is not None:
            item.add_marker(skip)
