"""The analyst workflow on the shipped demo (issue 16): defaults that work, no silent wrong answers.

Every test runs spctool as a user would (the click command, stdout and stderr apart) on a copy of the
demo working directory (``spctool demo --copy-to``).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from spctool.formats.table import LandmarkTable

PIC1, PIC2 = "P000000001A1", "P000000002A1"


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """The README session with default options: lithos-select -> register on PIC1 (run once)."""
    from click.testing import CliRunner

    from spctool.cli.main import cli

    def run(*args, input=None):
        return CliRunner().invoke(cli, [str(a) for a in args], input=input, catch_exceptions=False)

    root = tmp_path_factory.mktemp("wf")
    demo = root / "demo"
    assert run("demo", "--copy-to", demo).exit_code == 0
    sel = run("-C", demo, "lithos-select", PIC1)
    assert sel.exit_code == 0, sel.stderr
    (root / "sel.txt").write_text(sel.stdout)
    reg = run("-C", demo, "register", PIC1, "--landmarks", root / "sel.txt")
    (root / "reg.txt").write_text(reg.stdout)
    return run, root, demo, sel, reg


def test_readme_session_registers_every_demo_landmark(session):
    run, root, demo, sel, reg = session
    assert reg.exit_code == 0, reg.stderr
    t = LandmarkTable.parse_text(reg.stdout)
    assert len(t) == 12 and t["status"] == ["ok"] * 12
    # the 49x49 maplets cannot take S16's L = 10: the default schedule is fitted to them, silently
    # (said with -v; tests/test_demo.py), so a newcomer's first register prints no note
    assert "note:" not in reg.stderr and "spacings above" not in reg.stderr
    pose = run(
        "-C", demo, "solve-pose", PIC1, "--measurements", root / "reg.txt", "--output", root / "new.SUM"
    )
    assert pose.exit_code == 0, pose.stderr
    head = [c for c in LandmarkTable.parse_text(pose.stdout).comments]
    assert any(c.startswith("position_km") and "sigma_km" in c for c in head)
    assert any("cost/dof" in c and "dof" in c for c in head)
    assert any("position-attitude correlation" in c for c in head)
    assert "fit: plausible" in head


def test_nothing_registered_is_a_warning_and_require_exit_1(session):
    run, root, demo, sel, reg = session
    r = run("-C", demo, "register", PIC1, "B01980", "--no-spacing-cap")
    assert r.exit_code == 0 and LandmarkTable.parse_text(r.stdout)["status"] == ["not-found"]
    warn = [ln for ln in r.stderr.splitlines() if "warning" in ln]
    assert warn == [f"spctool: warning: {PIC1}: registered 0 of 1 landmarks: 1 not-found at spacing 10"]
    r = run("-C", demo, "register", PIC1, "B01980", "--no-spacing-cap", "--require", "1")
    assert r.exit_code == 1 and "fewer than --require 1" in r.stderr


def test_solve_pose_refuses_another_pictures_table(session):
    run, root, demo, sel, reg = session
    r = run("-C", demo, "solve-pose", PIC2, "--measurements", root / "reg.txt", "--output", root / "x.SUM")
    assert r.exit_code == 2
    assert r.stderr.strip().splitlines() == [
        f"spctool: error: {root / 'reg.txt'}: the table is for picture {PIC1}, not {PIC2} "
        "(--any-picture uses it anyway)"
    ]
    # forced past the header check, the fit itself is implausible: table written, no SUM, exit 1
    r = run(
        "-C",
        demo,
        "solve-pose",
        PIC2,
        "--measurements",
        root / "reg.txt",
        "--any-picture",
        "--output",
        root / "x.SUM",
    )
    assert r.exit_code == 1 and not (root / "x.SUM").exists()
    assert "implausible fit" in r.stderr.splitlines()[-1] and "no SUM written" in r.stderr
    assert "fit: IMPLAUSIBLE" in r.stdout
    r = run(
        "-C",
        demo,
        "solve-pose",
        PIC2,
        "--measurements",
        root / "reg.txt",
        "--any-picture",
        "--output",
        root / "x.SUM",
        "--force",
    )
    assert r.exit_code == 0 and (root / "x.SUM").exists() and "warning: " in r.stderr


def test_register_refuses_another_pictures_table_or_sum(session):
    """register (as solve-pose) refuses a landmark table or a --sum made for another picture, with
    one line naming the file; --any-picture runs it anyway (issue 39)."""
    run, root, demo, sel, reg = session
    r = run("-C", demo, "register", PIC2, "--landmarks", root / "sel.txt")
    assert r.exit_code == 2
    assert r.stderr.strip().splitlines() == [
        f"spctool: error: {root / 'sel.txt'}: the table is for picture {PIC1}, not {PIC2} "
        "(--any-picture uses it anyway)"
    ]
    sum1 = demo / "SUMFILES" / f"{PIC1}.SUM"
    r = run("-C", demo, "register", PIC2, "B01980", "--sum", sum1)
    assert r.exit_code == 2
    assert r.stderr.strip().splitlines() == [
        f"spctool: error: {sum1}: the SUM file is for picture {PIC1}, not {PIC2} "
        "(--any-picture uses it anyway)"
    ]
    r = run("-C", demo, "solve-pose", PIC2, "--sum", sum1, "--measurements", root / "reg.txt")
    assert r.exit_code == 2 and "the SUM file is for picture" in r.stderr
    # the picture's own SUM given with --sum, and another picture's with --any-picture, are used
    r = run("-C", demo, "register", PIC1, "B01980", "--sum", sum1)
    assert r.exit_code == 0, r.stderr
    r = run("-C", demo, "register", PIC2, "B01980", "--sum", sum1, "--any-picture")
    assert r.exit_code == 0, r.stderr
    r = run("-C", demo, "navigate", PIC2, "--landmarks", root / "sel.txt")
    assert r.exit_code == 2 and "the table is for picture" in r.stderr


def test_solve_pose_output_onto_its_input_keeps_a_backup(session, tmp_path):
    run, root, demo, sel, reg = session
    wd = tmp_path / "d"
    shutil.copytree(demo, wd)
    target = wd / "SUMFILES" / f"{PIC1}.SUM"
    before = target.read_bytes()
    r = run("-C", wd, "solve-pose", PIC1, "--measurements", root / "reg.txt", "--output", target)
    assert r.exit_code == 0, r.stderr
    assert (wd / "SUMFILES" / f"{PIC1}.SUM.bak").read_bytes() == before and target.read_bytes() != before


def test_batch_like_json_keeps_full_covariance(session):
    run, root, demo, sel, reg = session
    import json

    r = run("-C", demo, "solve-pose", PIC1, "--measurements", root / "reg.txt", "--json")
    pose = json.loads(r.stdout)["pose"]
    cov = np.array(pose["covariance"])
    assert cov.shape == (6, 6) and np.array(pose["covariance_formal"]).shape == (6, 6)
    np.testing.assert_allclose(cov, np.array(pose["covariance_formal"]) * pose["covariance_scale"])
    assert pose["plausible"] is True and 0 <= pose["position_attitude_correlation"] <= 1


# ------------------------------------------------------------------------------------------------
# one rule for the working directory: -C like git -C, a SUM path's SUMFILES/ parent (gap 3, 4)


def test_sum_path_and_dash_c_give_identical_pixels(session, monkeypatch):
    run, root, demo, sel, reg = session
    monkeypatch.chdir(root)
    by_c = run("-C", "demo", "project", PIC1)  # relative -C
    by_path = run("project", f"demo/SUMFILES/{PIC1}.SUM", "demo/LMKFILES/B01980.LMK")
    inside = run("-C", "demo", "project", f"SUMFILES/{PIC1}.SUM", "LMKFILES/B01980.LMK")  # git -C
    assert by_c.exit_code == by_path.exit_code == inside.exit_code == 0, by_path.stderr + inside.stderr
    t_c, t_p, t_i = (LandmarkTable.parse_text(r.stdout) for r in (by_c, by_path, inside))
    k = t_c.names.index("B01980")
    assert (t_p["sample"][0], t_p["line"][0]) == (t_c["sample"][k], t_c["line"][k])
    assert (t_i["sample"][0], t_i["line"][0]) == (t_c["sample"][k], t_c["line"][k])
    assert "distortion" not in by_path.stderr
    # selection and pose by SUM path use the same INIT_LITHOS, shape and LMK files
    a = run("-C", "demo", "lithos-select", PIC1)
    b = run("lithos-select", f"demo/SUMFILES/{PIC1}.SUM")
    assert a.stdout.split("\n", 3)[3] == b.stdout.split("\n", 3)[3]
    a = run("-C", "demo", "solve-pose", PIC1, "--measurements", "../reg.txt", "--json")
    b = run("solve-pose", f"demo/SUMFILES/{PIC1}.SUM", "--measurements", "reg.txt", "--json")
    import json

    pa, pb = json.loads(a.stdout)["pose"], json.loads(b.stdout)["pose"]
    assert pa["position"] == pb["position"] and pa["covariance"] == pb["covariance"]


def test_a_picture_without_distortion_model_says_so(session, tmp_path, monkeypatch):
    run, root, demo, sel, reg = session
    shutil.copy(demo / "SUMFILES" / f"{PIC1}.SUM", tmp_path / "lone.SUM")
    monkeypatch.chdir(tmp_path)
    r = run("project", "lone.SUM", str(demo / "LMKFILES" / "B01980.LMK"))
    assert r.exit_code == 0
    assert (
        f"spctool: note: {PIC1}: projected without a distortion model (no INIT_LITHOS.TXT in .)" in r.stderr
    )
    inside = run("-C", demo, "project", PIC1, "B01980")
    s0 = LandmarkTable.parse_text(r.stdout)["sample"][0]
    assert abs(s0 - LandmarkTable.parse_text(inside.stdout)["sample"][0]) > 1e-3  # OWEN distortion
    assert run("-q", "project", "lone.SUM", str(demo / "LMKFILES" / "B01980.LMK")).stderr == ""


def test_dash_c_errors_and_leaves_the_callers_directory(session, tmp_path, monkeypatch):
    import os

    run, root, demo, sel, reg = session
    monkeypatch.chdir(tmp_path)
    r = run("-C", "nowhere", "info", "x")
    assert r.exit_code == 2 and r.stderr.strip() == "spctool: error: -C nowhere: no such working directory"
    run("-C", demo, "info", f"SUMFILES/{PIC1}.SUM")
    assert os.getcwd() == str(tmp_path)


# ------------------------------------------------------------------------------------------------
# exit codes documented, unknown landmark the same everywhere, register selects like lithos-select


def test_exit_codes_in_help_and_every_man_page():
    from click.testing import CliRunner

    from spctool.cli.main import cli
    from spctool.cli.manpages import all_pages
    from spctool.errors import EXIT_CODES

    top = CliRunner().invoke(cli, ["--help"]).stdout
    assert "Exit codes" in top and all(f"{c:>3}  {t}" in top for c, t in EXIT_CODES.items())
    for name, page in all_pages().items():
        for section in (".SH EXIT STATUS", ".SH FILES", ".SH ENVIRONMENT"):
            assert section in page, (name, section)
        assert all(f".B {c}\n" in page for c in EXIT_CODES), name


@pytest.mark.parametrize(
    "args",
    [
        ("lithos-select", PIC1, "--maplets", "NOSUCH"),
        ("predict", PIC1, "NOSUCH"),
        ("extract", PIC1, "NOSUCH"),
        ("correlate", PIC1, "NOSUCH"),
        ("register", PIC1, "NOSUCH"),
        ("project", PIC1, "NOSUCH"),
    ],
)
def test_unknown_landmark_is_exit_2_in_every_command(session, args):
    run, root, demo, sel, reg = session
    r = run("-C", demo, *args)
    assert r.exit_code == 2 and r.stdout == ""
    errors = [ln for ln in r.stderr.splitlines() if ": note:" not in ln]
    assert len(errors) == 1 and "NOSUCH" in errors[0] and "file not found" in errors[0]


def test_register_without_landmarks_checks_occlusion_like_lithos_select(session):
    run, root, demo, sel, reg = session
    r = run("-v", "-C", demo, "register", PIC1, "--steps", "1")
    assert "12 of 12 candidate maplets (occlusion checked)" in r.stderr
    assert LandmarkTable.parse_text(r.stdout).names == LandmarkTable.parse_text(sel.stdout).names


def test_every_replaced_file_keeps_a_backup(session, tmp_path):
    run, root, demo, sel, reg = session
    out = tmp_path / "sel.txt"
    out.write_text("old table\n")
    assert run("-C", demo, "lithos-select", PIC1, "-o", out).exit_code == 0
    assert (tmp_path / "sel.txt.bak").read_text() == "old table\n" and out.read_text() == sel.stdout
    dst = tmp_path / "s.SUM"
    dst.write_text("old\n")
    assert run("convert", demo / "SUMFILES" / f"{PIC1}.SUM", dst, "--force").exit_code == 0
    assert (tmp_path / "s.SUM.bak").read_text() == "old\n"
