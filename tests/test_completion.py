"""Shell completion of picture and landmark names from the working directory, and ``spctool man``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from click.testing import CliRunner

import spctool
from spctool.cli import completion
from spctool.cli.main import cli
from spctool.sim.demo import demo_path


def _complete(words, cwd=None):
    """What bash completion offers for the last word of ``words`` (click's bash protocol)."""
    env = dict(os.environ, COMP_WORDS=" ".join(words), COMP_CWORD=str(len(words) - 1))
    env["_SPCTOOL_COMPLETE"] = "bash_complete"
    here = str(Path(spctool.__file__).resolve().parents[1])  # this checkout, also from another cwd
    env["PYTHONPATH"] = os.pathsep.join(p for p in (here, env.get("PYTHONPATH")) if p)
    r = subprocess.run(
        [sys.executable, "-c", "from spctool.cli.main import cli; cli()"],
        env=env,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=60,
    )
    return [line.split(",", 1) for line in r.stdout.splitlines() if line]


def test_names_from_a_working_directory(tmp_path):
    for d in ("SUMFILES", "LMKFILES", "MAPFILES"):
        (tmp_path / d).mkdir()
    (tmp_path / "SUMFILES" / "P1.SUM").write_text("")
    (tmp_path / "LMKFILES" / "AA0001.LMK").write_text("")
    (tmp_path / "MAPFILES" / "AA0002.MAP").write_text("")
    (tmp_path / "PICTLIST.TXT").write_text(" P2\n!P3\nEND\n P9\n")
    (tmp_path / "LMRKLIST.TXT").write_text("AB0001\nEND\n")
    assert completion.picture_names(tmp_path) == ["P1", "P2", "P3"]
    assert completion.landmark_names(tmp_path) == ["AA0001", "AA0002", "AB0001"]
    assert completion.picture_names(tmp_path / "nowhere") == []


def test_bash_completion_offers_demo_pictures_and_landmarks():
    root = demo_path()
    pics = sorted(p.stem for p in (root / "SUMFILES").glob("*.SUM"))
    got = _complete(["spctool", "-C", str(root), "register", "P"])
    assert [v for _, v in got] == sorted(set(pics) | {"P000000004A1"}) and all(t == "plain" for t, _ in got)
    lmks = sorted(p.stem for p in (root / "LMKFILES").glob("*.LMK"))
    got = _complete(["spctool", "-C", str(root), "register", pics[0], lmks[0], lmks[0][:3]])
    assert lmks[0] not in [v for _, v in got] and set(v for _, v in got) == {
        n for n in lmks[1:] if n[:3] == lmks[0][:3]
    }
    # from inside the working directory, without -C; solve-pose takes a picture too
    got = _complete(["spctool", "solve-pose", "P00000000"], cwd=root)
    assert len(got) == 4
    # nothing known: fall back to file names
    assert _complete(["spctool", "-C", "/nonexistent", "register", "x"]) == [["file", "x"]]


def test_man_prints_and_installs_pages(tmp_path):
    r = CliRunner().invoke(cli, ["man", "register"])
    assert (
        r.exit_code == 0
        and r.output.startswith(".TH")
        and "spctool-register" in r.output.splitlines()[0].lower()
    )
    r = CliRunner().invoke(cli, ["man", "--install", str(tmp_path / "man1")])
    assert r.exit_code == 0
    pages = sorted(p.name for p in (tmp_path / "man1").iterdir())
    assert "spctool.1" in pages and "spctool-register.1" in pages and "spctool-man.1" in pages
    r = CliRunner().invoke(cli, ["man", "nosuch"])
    assert r.exit_code == 2 and "no man page" in r.output
