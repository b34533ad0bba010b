"""Tests of spctool.batch: the per-picture pipeline against truth and against the single-stage
commands, identical outputs whatever the parallelism (in-process, spawned processes, a real Dask
LocalCluster on loopback), failure isolation, and resuming an interrupted batch."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from batch_world import make_world, picture_name
from click.testing import CliRunner

from spctool import batch
from spctool.batch import BatchOptions, PictureSummary, SharedData, navigate_picture, output_paths, run_batch
from spctool.errors import SpcUsageError
from spctool.formats.landmark import read_lmk
from spctool.formats.sumfile import read_sum
from spctool.geometry.camera import Camera
from spctool.jsonsafe import json_safe
from spctool.stages.pose import PoseOptions

N_PICTURES = 4


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch") / "world"
    truth = make_world(root, n_pictures=N_PICTURES, n_landmarks=5)
    return root, truth


@pytest.fixture(scope="module")
def reference(world, tmp_path_factory):
    """One in-process run: the outputs every other run must reproduce byte for byte."""
    root, _ = world
    out = tmp_path_factory.mktemp("batch") / "ref"
    result = run_batch(root, out_dir=out, jobs=1)
    return out, result


def result_files(out: Path) -> dict[str, bytes]:
    """Every result file (SUMs and tables) by relative path; markers compared by their results."""
    files = {}
    for p in sorted(out.rglob("*")):
        if not p.is_file() or p.name.startswith("BATCH_SUMMARY"):
            continue
        rel = str(p.relative_to(out))
        if p.name.endswith(".done.json"):
            doc = json.loads(p.read_text())
            doc["summary"].pop("timings")
            doc["summary"].pop("resumed")
            files[rel] = json.dumps(doc, sort_keys=True).encode()
        else:
            files[rel] = p.read_bytes()
    return files


def results_of(result) -> list[dict]:
    return [p.result_dict() for p in result.pictures]


def copy_world(root: Path, dest: Path) -> Path:
    shutil.copytree(root, dest)
    return dest


# ------------------------------------------------------------------------------------------------
# one picture


def test_navigate_picture_recovers_true_pose(world):
    root, truth = world
    lmk = [read_lmk(root / "LMKFILES" / f"{n}.LMK").vlm for n in truth["landmarks"]]
    v = np.array(lmk)
    for pt in truth["pictures"]:
        out = navigate_picture(root, pt["name"])
        s = out.summary
        assert s.status == "ok", s.status
        assert (s.candidates, s.selected, s.found, s.used) == (5, 5, 5, 5)
        assert s.rms_after_px < 0.1 < s.rms_before_px
        # the updated SUM's camera puts every landmark within 0.05 px of where the true camera does
        # (a-priori: pixels off), an independent check of the whole chain against the world's truth
        from spctool.formats.sumfile import parse_sum

        new = Camera.from_picture(parse_sum(out.sum_text))
        old = Camera.from_picture(read_sum(root / "SUMFILES" / f"{pt['name']}.SUM"))
        true = old.with_pose(scobj=np.array(pt["scobj"]), rotation=np.array(pt["rotation"]))
        want = np.stack(true.project(v), -1)
        assert np.abs(np.stack(new.project(v), -1) - want).max() < 0.05
        assert np.abs(np.stack(old.project(v), -1) - want).max() > 0.5
        # the summary's pose change is the norm of the solve's change vectors
        assert s.dposition_km == pytest.approx(np.linalg.norm(out.pose.delta_position), rel=1e-12)
        assert s.dattitude_rad == pytest.approx(np.linalg.norm(out.pose.delta_attitude), rel=1e-12)


def test_demo_batch_recovers_the_true_poses(tmp_path):
    """The shipped demo (shape model with occlusion test, OWEN distortion, 768² photos in three
    formats): every picture ok, and the solved poses put the landmarks where the true poses do."""
    from spctool.errors import SpcUsageError
    from spctool.formats.lithos import read_lithos
    from spctool.sim.demo import copy_demo

    try:
        wd = copy_demo(tmp_path / "demo")
    except SpcUsageError:
        pytest.skip("the demo data are not generated yet")
    truth = json.loads((wd / "TRUTH.json").read_text())
    result = run_batch(wd, out_dir=tmp_path / "out")
    assert [p.status for p in result.pictures] == ["ok"] * len(truth["pictures"])
    settings = read_lithos(wd / "INIT_LITHOS.TXT")
    v = np.array([lm["vlm"] for lm in truth["landmarks"]])
    for pt in truth["pictures"]:
        before = Camera.from_picture(read_sum(wd / "SUMFILES" / f"{pt['name']}.SUM"), settings)
        after = Camera.from_picture(read_sum(tmp_path / "out" / "SUMFILES" / f"{pt['name']}.SUM"), settings)
        true = before.with_pose(
            scobj=np.array(pt["true"]["scobj"]), rotation=np.array(pt["true"]["rotation"])
        )
        want = np.stack(true.project(v), -1)
        assert np.abs(np.stack(before.project(v), -1) - want).max() > 1.0
        assert np.abs(np.stack(after.project(v), -1) - want).max() < 0.3


def test_sum_copy_changes_only_pose_and_landmark_lines(world, reference):
    root, _ = world
    out, _ = reference
    name = picture_name(0)
    old = (root / "SUMFILES" / f"{name}.SUM").read_text().split("\n")
    new = (out / "SUMFILES" / f"{name}.SUM").read_text().split("\n")
    start = old.index(next(x for x in old if x.startswith("LANDMARKS")))
    # lines 0..start-1: only SCOBJ, CX, CY, CZ, SIGMA_VSO, SIGMA_PTG may change
    changed = {old[i][60:].strip() for i in range(start) if old[i] != new[i]}
    assert changed == {"SCOBJ", "CX", "CY", "CZ", "SIGMA_VSO", "SIGMA_PTG"}
    pic = read_sum(out / "SUMFILES" / f"{name}.SUM")
    reg = (out / "TABLES" / f"{name}.register.txt").read_text().splitlines()
    rows = [r.split() for r in reg if r and not r.startswith("#")][1:]
    assert [lm.name for lm in pic.landmarks] == [r[0] for r in rows]
    for lm, r in zip(pic.landmarks, rows):
        # SUM LANDMARKS rows hold pixels to 2 decimals (spc-formats.md §2)
        assert lm.sample == pytest.approx(float(r[1]), abs=0.00501)
        assert lm.line == pytest.approx(float(r[2]), abs=0.00501)


def test_batch_equals_the_command_chain(world, reference, tmp_path):
    """lithos-select --json | navigate --output gives the (two-pass) batch's SUM byte for byte."""
    from spctool.cli.main import cli

    root, _ = world
    out, _ = reference
    wd = copy_world(root, tmp_path / "wd")
    name = picture_name(1)
    runner = CliRunner()

    def run(*args):
        res = runner.invoke(cli, ["-C", str(wd), *args], catch_exceptions=False)
        assert res.exit_code == 0, res.stderr
        return res

    run("lithos-select", name, "--json", "-o", str(tmp_path / "sel.json"))
    final = tmp_path / "final.SUM"
    run(
        "navigate", name, "--landmarks", str(tmp_path / "sel.json"), "--json", "-o",
        str(tmp_path / "nav.json"), "--output", str(final),
    )  # fmt: skip
    assert final.read_bytes() == (out / "SUMFILES" / f"{name}.SUM").read_bytes()


def test_single_pass_batch_equals_the_register_chain(world, tmp_path):
    """BatchOptions(two_pass=None): lithos-select --json | register --schedule autoregister --write-sum |
    solve-pose --output gives the batch's SUM byte for byte (JSON tables keep every digit)."""
    from spctool.cli.main import cli

    root, _ = world
    name = picture_name(1)
    out = tmp_path / "single"
    run_batch(root, [name], BatchOptions(two_pass=None), out_dir=out)
    wd = copy_world(root, tmp_path / "wd")
    runner = CliRunner()

    def run(*args):
        res = runner.invoke(cli, ["-C", str(wd), *args], catch_exceptions=False)
        assert res.exit_code == 0, res.stderr
        return res

    run("lithos-select", name, "--json", "-o", str(tmp_path / "sel.json"))
    run(
        "register", name, "--landmarks", str(tmp_path / "sel.json"), "--schedule", "autoregister",
        "--json", "-o", str(tmp_path / "reg.json"), "--write-sum",
    )  # fmt: skip
    final = tmp_path / "final.SUM"
    run("solve-pose", name, "--measurements", str(tmp_path / "reg.json"), "--output", str(final))
    assert final.read_bytes() == (out / "SUMFILES" / f"{name}.SUM").read_bytes()


# ------------------------------------------------------------------------------------------------
# parallelism


@pytest.mark.slow
def test_two_processes_give_identical_outputs(world, reference, tmp_path):
    root, _ = world
    ref_out, ref = reference
    result = run_batch(root, out_dir=tmp_path / "j2", jobs=2)
    assert result.mode == "processes"
    assert results_of(result) == results_of(ref)
    assert result_files(tmp_path / "j2") == result_files(ref_out)


_FRESH = """
import json, sys
from spctool.batch import run_batch
r = run_batch(sys.argv[1], out_dir=sys.argv[2], jobs=2)
print(json.dumps({"method": r.start_method, "mode": r.mode, "failed": len(r.failed)}))
"""


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fork is chosen on Linux only")
def test_forked_workers_of_a_fresh_process_give_identical_outputs(world, reference, tmp_path):
    # a fresh, single-threaded process that has not started numba's threading layer forks its
    # workers (they inherit its imports); the outputs are those of the in-process run
    root, _ = world
    ref_out, ref = reference
    env = {k: v for k, v in os.environ.items() if k != "SPCTOOL_START_METHOD"}
    run = subprocess.run(
        [sys.executable, "-c", _FRESH, str(root), str(tmp_path / "fork")],
        capture_output=True, text=True, env=env, timeout=600, check=True,
    )  # fmt: skip
    doc = json.loads(run.stdout.strip().splitlines()[-1])
    assert doc == {"method": "fork", "mode": "processes", "failed": 0}
    assert result_files(tmp_path / "fork") == result_files(ref_out)
    summary = json.loads((tmp_path / "fork" / "BATCH_SUMMARY.json").read_text())
    assert summary["start_method"] == "fork"


def test_start_method_forks_only_when_safe(monkeypatch):
    from numba.np.ufunc import parallel

    monkeypatch.delenv("SPCTOOL_START_METHOD", raising=False)
    stop = threading.Event()
    helper = threading.Thread(target=stop.wait)
    helper.start()
    try:
        assert batch.start_method() == "spawn"  # another thread alive: never fork
    finally:
        stop.set()
        helper.join()
    monkeypatch.setattr(threading, "active_count", lambda: 1)
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.setattr(parallel, "_is_initialized", True)
    monkeypatch.setattr(parallel, "_threading_layer", "omp")
    assert batch.start_method() == "spawn"  # GNU OpenMP started: a forked child would abort
    monkeypatch.setattr(parallel, "_threading_layer", "workqueue")
    assert batch.start_method() == "fork"  # numba's own layer is fork-safe
    monkeypatch.setattr(parallel, "_is_initialized", False)
    assert batch.start_method() == "fork"
    monkeypatch.setattr(sys, "platform", "darwin")
    assert batch.start_method() == "spawn"
    monkeypatch.setenv("SPCTOOL_START_METHOD", "forkserver")
    assert batch.start_method() == "forkserver"
    monkeypatch.setenv("SPCTOOL_START_METHOD", "threads")
    with pytest.raises(SpcUsageError, match="SPCTOOL_START_METHOD"):
        batch.start_method()


def test_dask_local_cluster_gives_identical_outputs(world, reference, tmp_path):
    pytest.importorskip("distributed")
    from distributed import Client, LocalCluster

    root, _ = world
    ref_out, ref = reference
    with LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=False,
        protocol="tcp",
        host="127.0.0.1",
        scheduler_port=0,
        dashboard_address=None,
    ) as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        result = run_batch(root, out_dir=tmp_path / "dask", scheduler=cluster.scheduler_address)
        assert result.mode == "dask" and result.workers == 2
        with Client(cluster, set_as_default=False) as client:  # an existing client works too
            again = run_batch(root, out_dir=tmp_path / "dask2", scheduler=client)
    assert results_of(result) == results_of(ref) == results_of(again)
    assert result_files(tmp_path / "dask") == result_files(ref_out) == result_files(tmp_path / "dask2")


def test_shared_data_are_loaded_once_per_batch(world, tmp_path, monkeypatch):
    root = Path(shutil.copytree(world[0], tmp_path / "wd"))
    made = []
    original = SharedData.__init__

    def counting(self, *a, **k):
        made.append(1)
        original(self, *a, **k)

    monkeypatch.setattr(SharedData, "__init__", counting)
    result = run_batch(root, out_dir=tmp_path / "o", jobs=1)
    assert len(result.pictures) == N_PICTURES and len(made) == 1
    # the next batch on unchanged files reuses them (a long-lived worker keeps its shared data) ...
    again = run_batch(root, out_dir=tmp_path / "o2", jobs=1)
    assert len(made) == 1 and results_of(again) == results_of(result)
    # ... and reads them again as soon as one of them changed: an LMK rewritten in place, ...
    lmk = sorted((root / "LMKFILES").glob("*.LMK"))[0]
    text = lmk.read_bytes()
    lmk.write_bytes(text + b"\n")
    run_batch(root, out_dir=tmp_path / "o3", jobs=1, force=True)
    assert len(made) == 2
    # ... or replaced by another file (new inode), even of the same size and time
    st = lmk.stat()
    lmk.with_suffix(".new").write_bytes(lmk.read_bytes())
    os.replace(lmk.with_suffix(".new"), lmk)
    os.utime(lmk, ns=(st.st_atime_ns, st.st_mtime_ns))
    run_batch(root, out_dir=tmp_path / "o4", jobs=1, force=True)
    assert len(made) == 3
    # direct calls share one instance per (working directory, options, unchanged inputs)
    SharedData.clear()
    for k in range(2):
        navigate_picture(root, picture_name(k))
    assert len(made) == 4


def test_cached_maplet_is_reread_when_its_file_changes(world, tmp_path):
    root = Path(shutil.copytree(world[0], tmp_path / "wd"))
    SharedData.clear()
    shared = SharedData.get(root, BatchOptions())
    name = shared.names[0]
    first = shared.maplet(name)
    assert shared.maplet(name) is first  # cached
    path = root / "MAPFILES" / f"{name}.MAP"
    raw = path.read_bytes()
    path.write_bytes(raw[:-1] + bytes([raw[-1] ^ 0x01]))  # same size, one albedo bit flipped
    os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 1_000_000))
    second = shared.maplet(name)
    assert second is not first
    assert shared.maplet(name) is second
    path.unlink()
    missing = shared.maplet(name)
    assert "MAP" in str(missing) and not hasattr(missing, "heights")


# ------------------------------------------------------------------------------------------------
# failures


def corrupt(wd: Path) -> tuple[str, str, str]:
    """Truncate one photo, garble one SUM, list a picture that does not exist."""
    bad_photo, bad_sum = picture_name(1), picture_name(2)
    photo = wd / "IMAGEFILES" / f"{bad_photo}.DAT"
    photo.write_bytes(photo.read_bytes()[:1000])
    sum_path = wd / "SUMFILES" / f"{bad_sum}.SUM"
    lines = sum_path.read_text().split("\n")
    lines[4] = "  this is not a number   -0.1D+01   0.3D+00                     SCOBJ"
    sum_path.write_text("\n".join(lines))
    text = (wd / "PICTLIST.TXT").read_text().replace("END", " NOSUCHPIC01\nEND")
    (wd / "PICTLIST.TXT").write_text(text)
    return bad_photo, bad_sum, "NOSUCHPIC01"


def test_corrupt_pictures_are_reported_and_the_others_complete(world, reference, tmp_path):
    root, _ = world
    ref_out, ref = reference
    wd = copy_world(root, tmp_path / "wd")
    bad_photo, bad_sum, missing = corrupt(wd)
    seen = []
    result = run_batch(wd, out_dir=tmp_path / "out", on_result=seen.append)
    status = {p.picture: p.status for p in result.pictures}
    assert [p.picture for p in result.pictures] == [picture_name(k) for k in range(N_PICTURES)] + [missing]
    assert sorted(s.picture for s in seen) == sorted(status)
    assert status[bad_photo].startswith("failed: ") and f"{bad_photo}.DAT" in status[bad_photo]
    assert status[bad_sum].startswith("failed: ") and f"{bad_sum}.SUM:5:" in status[bad_sum]
    assert status[missing].startswith("failed: ") and "NOSUCHPIC01.SUM" in status[missing]
    assert all("\n" not in s for s in status.values())
    assert [p.picture for p in result.failed] == [bad_photo, bad_sum, missing]
    # the good pictures are exactly what the clean run gave; failed ones have no done-marker
    good = {picture_name(0), picture_name(3)}
    ref_rows = {p.picture: p.result_dict() for p in ref.pictures}
    for p in result.pictures:
        if p.picture in good:
            assert p.result_dict() == ref_rows[p.picture]
    files, ref_files = result_files(tmp_path / "out"), result_files(ref_out)
    for rel, data in files.items():
        assert any(g in rel for g in good), rel
        assert data == ref_files[rel]
    for bad in (bad_photo, bad_sum, missing):
        assert not output_paths(tmp_path / "out", bad)["marker"].exists()
    # the summary lists each failure with its reason after the table
    text = result.to_text()
    assert f"# {bad_sum} failed: " in text and result.counts()["failed"] == 3
    doc = json.loads((tmp_path / "out" / "BATCH_SUMMARY.json").read_text())
    assert [p["status"] for p in doc["pictures"]] == [p.status for p in result.pictures]
    # failed pictures are retried by the next run, done ones are not
    again = run_batch(wd, out_dir=tmp_path / "out")
    assert {p.picture for p in again.pictures if p.resumed} == good


def test_unsolvable_pose_is_a_result_not_a_failure(world, tmp_path):
    root, _ = world
    wd = copy_world(root, tmp_path / "wd")
    opts = BatchOptions(pose=PoseOptions(min_landmarks=6))  # 5 landmarks: never enough
    result = run_batch(wd, out_dir=tmp_path / "out", options=opts, pictures=[picture_name(0)])
    (p,) = result.pictures
    assert p.kind == "no-pose" and "too few landmarks" in p.status and not result.failed
    assert p.found == 5 and np.isnan(p.rms_after_px)
    paths = output_paths(tmp_path / "out", picture_name(0))
    assert paths["marker"].exists() and not paths["pose"].exists()
    old = read_sum(wd / "SUMFILES" / f"{picture_name(0)}.SUM")
    new = read_sum(paths["sum"])
    assert np.array_equal(old.scobj, new.scobj) and np.array_equal(old.rotation, new.rotation)
    assert len(new.landmarks) == 5  # the registered landmarks are kept


# ------------------------------------------------------------------------------------------------
# resume


class Stop(KeyboardInterrupt):
    pass


def test_interrupted_batch_resumes_to_the_same_outputs(world, reference, tmp_path):
    root, _ = world
    ref_out, ref = reference
    out = tmp_path / "out"
    count = []

    def interrupt_after_two(summary):
        count.append(summary.picture)
        if len(count) == 2:
            raise Stop

    with pytest.raises(Stop):
        run_batch(root, out_dir=out, on_result=interrupt_after_two)
    done = sorted(p.name for p in (out / "TABLES").glob("*.done.json"))
    assert done == [f"{picture_name(k)}.done.json" for k in range(2)]
    # a picture caught half-written (outputs there, marker not yet) is redone, not trusted
    output_paths(out, picture_name(1))["marker"].unlink()
    (out / "SUMFILES" / f"{picture_name(2)}.SUM").write_text("half a SUM")
    resumed = run_batch(root, out_dir=out)
    assert [p.resumed for p in resumed.pictures] == [True, False, False, False]
    assert results_of(resumed) == results_of(ref)
    assert result_files(out) == result_files(ref_out)


def test_resume_rules(world, reference, tmp_path):
    root, _ = world
    wd = copy_world(root, tmp_path / "wd")
    out = tmp_path / "out"
    first = run_batch(wd, out_dir=out)
    assert not any(p.resumed for p in first.pictures)
    assert all(p.resumed for p in run_batch(wd, out_dir=out).pictures)
    assert not any(p.resumed for p in run_batch(wd, out_dir=out, force=True).pictures)
    # other options: redone
    other = BatchOptions(pose=PoseOptions(sigma_px=0.2))
    assert not any(p.resumed for p in run_batch(wd, out_dir=out, options=other).pictures)
    # a changed input SUM: that picture is redone
    path = wd / "SUMFILES" / f"{picture_name(3)}.SUM"
    path.write_bytes(path.read_bytes().replace(b"SIGMA_VSO", b"SIGMA_VSO", 1) + b"\n")
    again = run_batch(wd, out_dir=out, options=other)
    assert [p.resumed for p in again.pictures] == [True, True, True, False]
    # a marker from another picture or a damaged one is not trusted
    marker = output_paths(out, picture_name(0))["marker"]
    marker.write_text("{not json")
    assert batch.done_summary(wd, out, picture_name(0), other.fingerprint()) is None


# ------------------------------------------------------------------------------------------------
# pieces


def test_options_fingerprint_and_summary_round_trip():
    a, b = BatchOptions(), BatchOptions()
    assert a.fingerprint() == b.fingerprint()
    assert BatchOptions(maplet_cache=3).fingerprint() == a.fingerprint()
    assert BatchOptions(select={"reslm": 2.0}).fingerprint() != a.fingerprint()
    assert BatchOptions(occlusion=False).fingerprint() != a.fingerprint()
    with pytest.raises(Exception, match="unknown selection option"):
        BatchOptions(select={"no_such": 1})
    s = PictureSummary(
        "P1", "ok", 3, 3, 2, 2, 1.5, 0.1, 2e-3, 1e-4, True, [1.0, 2.0, 3.0], [0.1, 0.2, 0.3], reduced_chi2=1.2
    )
    doc = json.loads(json.dumps(batch.inputs._jsonable(s.as_dict())))
    assert PictureSummary.from_dict(doc) == s
    nan = PictureSummary("P2", "failed: x")
    back = PictureSummary.from_dict(json.loads(json.dumps(json_safe(nan.as_dict()))))
    assert back.kind == "failed" and np.isnan(back.rms_after_px) and np.isnan(back.delta_position).all()


def test_usage_errors(world, tmp_path):
    root, _ = world
    with pytest.raises(Exception, match="must differ from the working directory"):
        run_batch(root, out_dir=root)
    with pytest.raises(Exception, match="at least 1"):
        run_batch(root, out_dir=tmp_path / "o", jobs=0)
    with pytest.raises(Exception, match="needs a shape model"):
        run_batch(root, out_dir=tmp_path / "o", options=BatchOptions(occlusion=True))
    with pytest.raises(Exception, match="needs a shape model"):
        run_batch(root, out_dir=tmp_path / "o", jobs=2, options=BatchOptions(occlusion=True))
    empty = tmp_path / "empty"
    (empty / "SUMFILES").mkdir(parents=True)
    assert run_batch(empty, out_dir=tmp_path / "o3").pictures == []


def _crash_on_p3(workdir, out_dir, picture, options, fingerprint, token):
    """A worker task (module level: spawn-started workers import it) that kills its process on P3."""
    import os
    import time

    if picture == "P3":
        os._exit(3)
    time.sleep(0.05)  # keep several pictures in flight when P3's worker dies
    return PictureSummary(picture=picture, status="ok")


@pytest.mark.slow
def test_worker_death_names_the_culprit_and_completes_the_rest(tmp_path):
    # up to 2 * jobs pictures are in flight: every suspect of a death is retried alone, so only the
    # picture that kills its worker is reported lost and all the others complete exactly once
    names = [f"P{k}" for k in range(9)]
    got: dict[int, PictureSummary] = {}

    def record(i, s):
        assert i not in got
        got[i] = s

    opts = BatchOptions()
    batch.driver._run_processes(
        2, tmp_path, tmp_path / "out", names, list(range(len(names))), opts, opts.fingerprint(), "t",
        record, task=_crash_on_p3,
    )
    assert sorted(got) == list(range(len(names)))
    for i, s in got.items():
        assert s.picture == names[i]
        if names[i] == "P3":
            assert s.status.startswith("failed: worker lost")
        else:
            assert s.status == "ok"


@pytest.mark.slow
def test_worker_pool_death_closes_the_pool_and_the_batch_completes(tmp_path):
    names = [f"P{k}" for k in range(7)]
    got: dict[int, PictureSummary] = {}
    opts = BatchOptions()
    with batch.WorkerPool(2) as pool:
        batch.driver._run_processes(
            2, tmp_path, tmp_path / "out", names, list(range(len(names))), opts, opts.fingerprint(), "t",
            lambda i, s: got.__setitem__(i, s), task=_crash_on_p3, pool=pool,
        )  # fmt: skip
        assert pool.closed  # a worker died: the caller's pool is not used again
    assert sorted(got) == list(range(len(names)))
    assert [got[i].status.startswith("failed: worker lost") for i in range(7)] == [k == 3 for k in range(7)]


# ------------------------------------------------------------------------------------------------
# a worker pool kept alive across batches


def _pids(pool) -> set[int]:
    return {p.pid for p in pool.executor._processes.values()}


@pytest.mark.slow
def test_worker_pool_runs_batch_after_batch_with_the_same_warm_workers(world, reference, tmp_path):
    root, _ = world
    ref_out, ref = reference
    with batch.WorkerPool(2, warm=(root, None)) as pool:
        assert pool.jobs == 2 and pool.method in ("fork", "spawn")
        workers = _pids(pool)
        assert len(workers) == 2  # both started and warmed before the constructor returned
        first = run_batch(root, out_dir=tmp_path / "a", pool=pool)
        second = run_batch(root, out_dir=tmp_path / "b", pool=pool, force=True)
        assert _pids(pool) == workers  # the same processes ran both batches
        assert first.mode == second.mode == "processes" and first.workers == 2
        assert first.start_method == pool.method
    assert pool.closed
    for result, out in ((first, "a"), (second, "b")):
        assert results_of(result) == results_of(ref)
        assert result_files(tmp_path / out) == result_files(ref_out)
    with pytest.raises(SpcUsageError, match="closed"):
        run_batch(root, out_dir=tmp_path / "c", pool=pool)


@pytest.mark.slow
def test_worker_pool_usage_errors(world, tmp_path):
    root, _ = world
    with pytest.raises(SpcUsageError, match="at least 1"):
        batch.WorkerPool(0)
    with batch.WorkerPool(1) as pool:
        with pytest.raises(SpcUsageError, match="not both"):
            run_batch(root, out_dir=tmp_path / "x", pool=pool, scheduler="tcp://127.0.0.1:1")
        one = run_batch(root, out_dir=tmp_path / "one", pool=pool, jobs=5)  # jobs follows the pool
        assert one.workers == 1 and not one.failed


@pytest.mark.slow
def test_worker_pool_whose_worker_died_between_batches_is_replaced(world, reference, tmp_path):
    import signal

    root, _ = world
    ref_out, ref = reference
    with batch.WorkerPool(2, warm=(root, None)) as pool:
        os.kill(next(iter(_pids(pool))), signal.SIGKILL)  # e.g. the OOM killer, while the pool is idle
        for _ in range(100):  # the executor notices the death
            if pool.executor._broken:
                break
            time.sleep(0.05)
        result = run_batch(root, out_dir=tmp_path / "after", pool=pool)
        assert pool.closed
    assert results_of(result) == results_of(ref)
    assert result_files(tmp_path / "after") == result_files(ref_out)


def _die(*args, **kwargs):
    os._exit(3)


def test_worker_pool_that_cannot_warm_up_is_an_error(world, monkeypatch):
    root, _ = world
    monkeypatch.setenv("SPCTOOL_START_METHOD", "fork")  # the forked workers inherit the patch below
    monkeypatch.setattr(batch.driver, "navigate_picture", _die)
    with pytest.raises(SpcUsageError, match="could not start"):
        batch.WorkerPool(2, warm=(root, None))
