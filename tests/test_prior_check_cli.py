"""The prior–measurement test from the command line (issue 39): the demo picture with its SUM's
SIGMA_VSO / SIGMA_PTG divided by 10 (the a-priori pose unchanged, so the prior now understates its
error ~10x).  navigate says so in one line with the figure and the remedy and calls the pose
prior-contradicted; --prior-scale auto widens the prior and the pose is ok; batch counts it."""

from __future__ import annotations

import json

import numpy as np
import pytest

PIC = "P000000001A1"


@pytest.fixture(scope="module")
def understated(tmp_path_factory):
    from click.testing import CliRunner

    from spctool.cli.main import cli
    from spctool.formats.sumfile import read_sum, with_pose, write_sum

    def run(*args):
        return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)

    demo = tmp_path_factory.mktemp("prior") / "demo"
    assert run("demo", "--copy-to", demo).exit_code == 0
    path = demo / "SUMFILES" / f"{PIC}.SUM"
    pic = read_sum(path)
    rot = np.stack([pic.cx, pic.cy, pic.cz])
    write_sum(path, with_pose(pic, pic.scobj, rot, pic.sigma_vso / 10, pic.sigma_ptg / 10), overwrite=True)
    (demo / "ONE.TXT").write_text(f" {PIC}\nEND\n")
    return run, demo


def test_navigate_reports_a_contradicted_prior_and_widens_it_on_request(understated):
    run, demo = understated
    res = run("-C", demo, "navigate", PIC, "--json")
    assert res.exit_code == 0, res.stderr
    doc = json.loads(res.stdout)
    pose = doc["pose"]
    assert pose["verdict"] == "prior-contradicted" and pose["prior_check"]["contradicted"] is True
    assert doc["status"].startswith("prior-contradicted: the measurements contradict the a-priori pose")
    assert pose["prior_check"]["understatement"] > 4.0
    warn = [ln for ln in res.stderr.splitlines() if "warning" in ln]
    assert len(warn) == 1 and warn[0].startswith(f"spctool: warning: {PIC}: prior-contradicted: ")
    assert "--no-prior or --prior-scale auto" in warn[0] and "understate" in warn[0]
    res = run("-C", demo, "navigate", PIC, "--json", "--prior-scale", "auto")
    assert res.exit_code == 0, res.stderr
    doc = json.loads(res.stdout)
    pose = doc["pose"]
    assert pose["verdict"] == "ok" and pose["prior_scale"] > 3.0 and doc["status"] == "ok"
    assert any(w.startswith("prior widened x") for w in pose["warnings"])
    res = run("-C", demo, "navigate", PIC, "--prior-scale", "-2")
    assert res.exit_code == 2 and "--prior-scale" in res.stderr


def test_batch_counts_the_contradicted_prior(understated):
    run, demo = understated
    res = run("-C", demo, "batch", demo / "ONE.TXT", "--out-dir", demo / "B", "--json", "--no-figure")
    assert res.exit_code == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["counts"]["prior-contradicted"] == 1 and doc["counts"]["ok"] == 0
    assert doc["pictures"][0]["status"].startswith("prior-contradicted: the measurements contradict")
    text = (demo / "B" / "BATCH_SUMMARY.txt").read_text()
    assert "1 prior-contradicted" in text and f"# {PIC} prior-contradicted: " in text
