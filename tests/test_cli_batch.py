"""Tests of ``spctool batch`` (spctool.cli.batch): summary table and JSON, the same outputs with
--jobs 1, --jobs 2 and --scheduler (a Dask LocalCluster on loopback), failed pictures reported with
exit code 1, and a batch killed mid-run that resumes to the same outputs."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from batch_world import make_world, picture_name
from click.testing import CliRunner

from spctool.cli.main import cli

N_PICTURES = 6


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("clibatch") / "world"
    make_world(root, n_pictures=N_PICTURES, n_landmarks=5)
    return root


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def outputs(out: Path) -> dict[str, bytes]:
    """SUMs and tables (markers and summaries hold timings and paths)."""
    return {
        str(p.relative_to(out)): p.read_bytes()
        for p in sorted(out.rglob("*"))
        if p.is_file() and not p.name.endswith(".done.json") and not p.name.startswith("BATCH_SUMMARY")
    }


def rows(text: str) -> list[list[str]]:
    lines = [ln.split() for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
    return lines[1:]


@pytest.fixture(scope="module")
def reference(world, tmp_path_factory):
    out = tmp_path_factory.mktemp("clibatch") / "ref"
    res = invoke("-C", world, "batch", "--out-dir", out)
    assert res.exit_code == 0, res.stderr
    return out, res.stdout


def test_summary_table_and_default_out_dir(world, reference, tmp_path):
    out, text = reference
    header = [ln for ln in text.splitlines() if ln.startswith("picture")][0].split()
    assert header == [
        "picture", "candidates", "selected", "found", "used", "rms_before_px", "rms_after_px",
        "dposition_km", "dattitude_rad", "status",
    ]  # fmt: skip
    table = rows(text)
    assert [r[0] for r in table] == [picture_name(k) for k in range(N_PICTURES)]
    assert all(r[-1] == "ok" and r[3] == "5" for r in table)
    assert all(float(r[6]) < 0.1 < float(r[5]) for r in table)
    assert (out / "BATCH_SUMMARY.txt").read_text() == text
    for k in range(N_PICTURES):
        for suffix in ("select.txt", "register.txt", "pose.txt", "done.json"):
            assert (out / "TABLES" / f"{picture_name(k)}.{suffix}").is_file()
        assert (out / "SUMFILES" / f"{picture_name(k)}.SUM").is_file()
    # default --out-dir: WORKDIR/BATCH; a PICTLIST argument picks the pictures (flags respected)
    wd = tmp_path / "wd"
    shutil.copytree(world, wd)
    plist = tmp_path / "LIST.TXT"
    plist.write_text(f" {picture_name(2)}\n!{picture_name(0)}\n {picture_name(4)}\nEND\n")
    res = invoke("-C", wd, "batch", plist)
    assert res.exit_code == 0, res.stderr
    assert [r[0] for r in rows(res.stdout)] == [picture_name(2), picture_name(4)]
    assert sorted(p.name for p in (wd / "BATCH" / "SUMFILES").iterdir()) == [
        f"{picture_name(2)}.SUM",
        f"{picture_name(4)}.SUM",
    ]
    assert outputs(wd / "BATCH") == {
        k: v for k, v in outputs(out).items() if picture_name(2) in k or picture_name(4) in k
    }


def test_json_summary(world, reference, tmp_path):
    out, text = reference
    res = invoke("-C", world, "batch", "--out-dir", out, "--json")  # everything done: resumed
    assert res.exit_code == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["command"] == "batch" and doc["format"] == "spctool-batch/1"
    assert doc["counts"] == {
        "ok": N_PICTURES, "inconsistent": 0, "prior-contradicted": 0, "no-pose": 0, "failed": 0,
        "resumed": N_PICTURES,
    }
    table = rows(text)
    for row, p in zip(table, doc["pictures"]):
        assert p["picture"] == row[0] and p["status"] == "ok" and p["resumed"] is True
        assert p["rms_after_px"] == pytest.approx(float(row[6]), rel=1e-5)
        assert sum(x * x for x in p["delta_position"]) ** 0.5 == pytest.approx(p["dposition_km"], rel=1e-12)
        assert set(p["timings"]) >= {"select_s", "register_s", "pose_s", "total_s"}


def test_jobs_and_scheduler_give_the_same_outputs(world, reference, tmp_path):
    pytest.importorskip("distributed")
    from distributed import LocalCluster

    out, text = reference
    res = invoke("-C", world, "batch", "--out-dir", tmp_path / "j2", "--jobs", "2")
    assert res.exit_code == 0, res.stderr
    assert rows(res.stdout) == rows(text)
    assert outputs(tmp_path / "j2") == outputs(out)
    with LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=False,
        protocol="tcp",
        host="127.0.0.1",
        scheduler_port=0,
        dashboard_address=None,
    ) as cluster:
        res = invoke(
            "-C",
            world,
            "-v",
            "batch",
            "--out-dir",
            tmp_path / "dask",
            "--scheduler",
            cluster.scheduler_address,
        )
    assert res.exit_code == 0, res.stderr
    assert "(dask, 2 worker(s))" in res.stderr
    assert rows(res.stdout) == rows(text)
    assert outputs(tmp_path / "dask") == outputs(out)


def test_failed_pictures_exit_1_and_the_rest_complete(world, reference, tmp_path):
    out, _ = reference
    wd = tmp_path / "wd"
    shutil.copytree(world, wd)
    bad = picture_name(3)
    (wd / "IMAGEFILES" / f"{bad}.DAT").write_bytes(b"\0" * 10)
    res = invoke("-C", wd, "batch", "--out-dir", tmp_path / "o")
    assert res.exit_code == 1
    err = res.stderr.splitlines()
    assert any(ln.startswith(f"spctool: {bad} failed: ") and f"{bad}.DAT" in ln for ln in err)
    assert err[-1] == f"spctool: error: 1 of {N_PICTURES} pictures failed: {bad}"
    table = rows(res.stdout)
    assert [r[-1] for r in table] == ["failed" if r[0] == bad else "ok" for r in table]
    assert f"# {bad} failed: " in res.stdout
    good = {k: v for k, v in outputs(out).items() if bad not in k}
    assert outputs(tmp_path / "o") == good


def test_usage_errors(world, tmp_path):
    res = invoke("-C", tmp_path / "nowhere", "batch")
    assert res.exit_code == 2 and "no such working directory" in res.stderr
    (tmp_path / "empty").mkdir()
    res = invoke("-C", tmp_path / "empty", "batch")
    assert res.exit_code == 2 and "no pictures" in res.stderr
    res = invoke("-C", world, "batch", "--out-dir", world)
    assert res.exit_code == 2 and "must differ" in res.stderr
    res = invoke("-C", world, "batch", "--jobs", "0")
    assert res.exit_code == 2


def test_killed_batch_resumes(world, reference, tmp_path):
    """A batch killed (SIGKILL: no clean-up at all) after its first picture resumes where it stopped
    and ends with the outputs of an uninterrupted run."""
    out, text = reference
    target = tmp_path / "o"
    code = "from spctool.cli.main import cli; cli()"
    cmd = [sys.executable, "-c", code, "-C", str(world), "batch", "--out-dir", str(target)]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    deadline = time.monotonic() + 60
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            if any((target / "TABLES").glob("*.done.json")):
                proc.send_signal(signal.SIGKILL)
                break
            time.sleep(0.002)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=30)
    done = len(list((target / "TABLES").glob("*.done.json")))
    if proc.returncode == 0 or done == N_PICTURES:
        pytest.skip("the batch finished before it could be killed")
    assert 1 <= done < N_PICTURES
    res = invoke("-C", world, "-v", "batch", "--out-dir", target)
    assert res.exit_code == 0, res.stderr
    assert f"{done} done earlier" in res.stderr
    assert rows(res.stdout) == rows(text)
    assert outputs(target) == outputs(out)


def test_a_dying_worker_process_costs_only_its_picture(world, reference, tmp_path):
    """A picture that kills its worker process (as a crash in native code would) is reported; the
    pictures in flight with it are retried alone and complete, the rest go on in a fresh pool."""
    from batch_world import crash_task

    from spctool import batch

    out, _ = reference
    names = ["CRASHPIC0001", picture_name(0), picture_name(1)]
    got = {}
    opts = batch.BatchOptions()
    batch.driver._run_processes(
        2, world, tmp_path / "o", names, [0, 1, 2], opts, opts.fingerprint(), "t",
        lambda i, s: got.setdefault(names[i], s), task=crash_task,
    )  # fmt: skip
    assert sorted(got) == sorted(names)
    assert got["CRASHPIC0001"].status.startswith("failed: worker lost: BrokenProcessPool")
    assert [got[n].status for n in names[1:]] == ["ok", "ok"]
    assert outputs(tmp_path / "o") == {
        k: v for k, v in outputs(out).items() if picture_name(0) in k or picture_name(1) in k
    }
