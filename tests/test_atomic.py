"""Outputs are written to a temporary file and renamed; backups are kept on request."""

import os

import pytest

from spctool.errors import SpcEnvironmentError, SpcUsageError
from spctool.formats import atomic


def test_write_replaces_and_keeps_backup(tmp_path):
    p = tmp_path / "A.SUM"
    p.write_text("old\n")
    kept = atomic.write_text(p, "new\n", backup=True)
    assert p.read_text() == "new\n"
    assert kept.name == "A.SUM.bak" and kept.read_text() == "old\n"
    kept2 = atomic.write_text(p, "newer\n", backup=True)
    assert kept2.name == "A.SUM.bak1" and kept2.read_text() == "new\n"
    assert not [f for f in os.listdir(tmp_path) if f.endswith(".tmp")]


def test_refuses_overwrite_when_asked(tmp_path):
    p = tmp_path / "x"
    p.write_text("keep")
    with pytest.raises(SpcUsageError, match="exists already"):
        atomic.write_text(p, "no", overwrite=False)
    assert p.read_text() == "keep"


def test_failed_write_leaves_original(tmp_path, monkeypatch):
    p = tmp_path / "x"
    p.write_text("keep")

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(atomic.os, "replace", boom)
    with pytest.raises(SpcEnvironmentError, match="disk full"):
        atomic.write_text(p, "lost")
    assert p.read_text() == "keep"
    assert sorted(os.listdir(tmp_path)) == ["x"]


def test_read_text_strips_cr(tmp_path):
    p = tmp_path / "c"
    p.write_bytes(b"a\r\nb\r\n")
    assert atomic.read_text(p) == "a\nb\n"


def test_new_files_get_umask_permissions(tmp_path):
    umask = os.umask(0o022)
    try:
        atomic.write_text(tmp_path / "new", "x")
        assert (tmp_path / "new").stat().st_mode & 0o777 == 0o644
        os.chmod(tmp_path / "new", 0o600)
        atomic.write_text(tmp_path / "new", "y")  # an existing file keeps its mode
        assert (tmp_path / "new").stat().st_mode & 0o777 == 0o600
    finally:
        os.umask(umask)
