"""Pictures an analyst may keep are never replaced silently (issue 42): register's and correlate's
panels have distinct names, and a different picture already at an output path is kept as FILE.bak."""

from spctool.sim.demo import copy_demo

PIC, LMK = "P000000001A1", "B01980"


def test_panels_of_register_and_correlate_are_both_kept(run_cli, tmp_path):
    demo = copy_demo(tmp_path / "demo")
    r = run_cli("-C", demo, "register", PIC, LMK, "--panels", "panels", "-o", "reg.txt")
    assert r.exit_code == 0, r.stderr
    reg_panel = demo / "panels" / f"{LMK}_{PIC}_panel.png"
    first = reg_panel.read_bytes()
    r = run_cli("-C", demo, "correlate", PIC, LMK, "--spacing", "2", "--panels", "panels", "--sheet", "s.png")
    assert r.exit_code == 0, r.stderr
    assert (demo / "panels" / f"{LMK}_{PIC}_correlate-panel.png").is_file()
    assert reg_panel.read_bytes() == first and not (demo / "panels" / f"{LMK}_{PIC}_panel.png.bak").exists()
    # the same command again draws the same pictures: nothing to keep
    r = run_cli("-C", demo, "register", PIC, LMK, "--panels", "panels", "-o", "reg.txt")
    assert reg_panel.read_bytes() == first and not reg_panel.with_name(reg_panel.name + ".bak").exists()
    # another run that draws something else keeps the earlier picture as .bak
    r = run_cli("-C", demo, "register", PIC, LMK, "--steps", "3,1", "--panels", "panels", "-o", "reg.txt")
    assert r.exit_code == 0, r.stderr
    assert reg_panel.with_name(reg_panel.name + ".bak").read_bytes() == first
    assert reg_panel.read_bytes() != first
    sheet = demo / "s.png"
    before = sheet.read_bytes()
    r = run_cli("-C", demo, "correlate", PIC, LMK, "--spacing", "3", "--sheet", "s.png")
    assert r.exit_code == 0, r.stderr
    assert (demo / "s.png.bak").read_bytes() == before
