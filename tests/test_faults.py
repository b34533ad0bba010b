"""Fault injection: hostile names, stale resume, kills, full disks, read-only and refused files.

Issue #19.  Each case is one the mutation/fault study found broken; the test shows the fixed
behaviour: paths confined to the directories named, resume fingerprints over every input, atomic
backups, no stale temporary files, no orphan workers, environment errors as one line with exit 3.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from spctool import batch
from spctool.batch import output_paths, run_batch
from spctool.cli.main import cli
from spctool.errors import SpcEnvironmentError, SpcFormatError, SpcUsageError
from spctool.formats import atomic, guard
from spctool.formats.workdir import WorkDir

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "fixtures" / "demo"
PIC = "P000000001A1"


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def one_line_error(res, code, prefix="spctool: error: "):
    assert res.exit_code == code, (res.exit_code, res.stdout, res.stderr)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(prefix), res.stderr
    assert "internal error" not in res.stderr and "Traceback" not in res.stderr
    return lines[0]


def tree(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


@pytest.fixture
def demo(tmp_path):
    """A private copy of the demo working directory, inside a sandbox directory whose other
    content must never change."""
    box = tmp_path / "box"
    wd = box / "a" / "b" / "wd"
    shutil.copytree(DEMO, wd)
    return wd


# ------------------------------------------------------------------------------------------------
# names never become paths out of the directories named


@pytest.mark.parametrize("bad", ["../../x", "/tmp/x", "..", "a/b", "a\x00b", ".hidden", "-rf", "x" * 65])
def test_check_name_refuses_path_like_names(bad):
    assert not guard.is_valid_name(bad)
    with pytest.raises(SpcUsageError, match="plain picture name"):
        guard.check_name(bad, "picture name")
    with pytest.raises(SpcFormatError, match="LIST.TXT"):
        guard.check_name(bad, "picture name", "LIST.TXT")


@pytest.mark.parametrize(
    "good", ["P000000001A1", "B01536", "N2395699394", "W48230079013", "EN1000_01", "A.B+1-c"]
)
def test_check_name_accepts_spc_names(good):
    assert guard.check_name(" " + good + " ") == good


@pytest.mark.parametrize("name", ["../../x", "/tmp/x"])
def test_pictlist_name_cannot_escape_the_out_dir(demo, name):
    before = tree(demo.parents[2])
    (demo / "PICTLIST.TXT").write_text(f" {PIC}\n {name}\nEND\n")
    res = invoke("-C", demo, "batch", "--out-dir", demo / "OUT")
    line = one_line_error(res, 2)
    assert "PICTLIST.TXT" in line and "plain picture name" in line
    assert tree(demo.parents[2]) == before  # nothing written, nothing deleted
    # an explicit PICTLIST argument too
    (demo.parent / "LIST.TXT").write_text(f" {name}\nEND\n")
    res = invoke("-C", demo, "batch", demo.parent / "LIST.TXT", "--out-dir", demo / "OUT")
    assert "LIST.TXT" in one_line_error(res, 2)


def test_absolute_picture_name_never_replaces_an_input(demo, tmp_path):
    victim = demo / "SUMFILES" / f"{PIC}.SUM"
    before = victim.read_bytes()
    with pytest.raises(SpcUsageError, match="plain picture name"):
        run_batch(demo, [str(victim.with_suffix(""))], out_dir=tmp_path / "out")
    assert victim.read_bytes() == before
    assert not list(victim.parent.glob("*.bak*"))
    with pytest.raises(SpcUsageError):
        output_paths(tmp_path / "out", str(victim.with_suffix("")))


def test_lmrklist_and_table_names_cannot_escape(demo):
    (demo / "LMRKLIST.TXT").write_text("B01536\n../../../etc/passwd\nEND\n")
    res = invoke("-C", demo, "lithos-select", PIC)
    assert "LMRKLIST.TXT" in one_line_error(res, 2)
    table = demo / "sel.txt"
    table.write_text("name sample line\n../../x 10 10\n")
    res = invoke("-C", demo, "register", PIC, "--landmarks", table)
    assert "plain landmark name" in one_line_error(res, 2)


def test_sum_picture_name_cannot_point_the_photo_elsewhere(demo):
    path = demo / "SUMFILES" / f"{PIC}.SUM"
    text = path.read_text()
    path.write_text(text.replace(PIC, "../../../../" + PIC[:0] + "x", 1))
    res = invoke("-C", demo, "register", PIC)
    assert res.exit_code == 2 and "internal error" not in res.stderr


@pytest.mark.parametrize("name", ["../../../ESC", "/tmp/ESC"])
def test_simulate_picture_name_cannot_escape_outdir(tmp_path, name):
    spec = tmp_path / "a" / "b" / "spec.toml"
    spec.parent.mkdir(parents=True)
    spec.write_text(f"[[pictures]]\nname = '{name}'\n")
    before = tree(tmp_path)
    res = invoke("simulate", spec, tmp_path / "a" / "b" / "OUT")
    assert "plain name" in one_line_error(res, 2)
    assert tree(tmp_path) == before
    spec.write_text("[maplets]\nnames = ['../x']\n")
    assert "plain name" in one_line_error(invoke("simulate", spec, tmp_path / "a" / "b" / "OUT"), 2)
    spec.write_text("[maplets]\nprefix = '/'\n")
    assert "plain name" in one_line_error(invoke("simulate", spec, tmp_path / "a" / "b" / "OUT"), 2)


# ------------------------------------------------------------------------------------------------
# resume fingerprints cover every input


def _resumed(wd, out):
    return {p.picture: p.resumed for p in run_batch(wd, [PIC], out_dir=out).pictures}[PIC]


def test_resume_redoes_a_picture_when_any_input_changes(demo, tmp_path):
    out = tmp_path / "out"
    first = run_batch(demo, [PIC], out_dir=out)
    assert first.pictures[0].kind == "ok" and not first.pictures[0].resumed
    marker = json.loads(output_paths(out, PIC)["marker"].read_text())
    assert set(marker["inputs"]) == {"sum", "photo", "maplets"} and marker["inputs"]["maplets"]
    assert marker["shared_inputs_sha256"] and marker["spctool_version"]
    assert _resumed(demo, out)

    def changed(path: Path, edit) -> bool:
        data = path.read_bytes()
        path.write_bytes(edit(data))
        redone = not _resumed(demo, out)
        assert _resumed(demo, out)  # done again with the new input
        return redone

    # a new photo (same size, one DN changed)
    photo = demo / "IMAGEFILES" / f"{PIC}.DAT"
    assert changed(photo, lambda d: d[:1000] + bytes([d[1000] ^ 1]) + d[1001:])
    # a changed INIT_LITHOS
    assert changed(demo / "INIT_LITHOS.TXT", lambda d: d.replace(b"END", b"OVERLAP=  0.5\nEND", 1))
    # a changed LMRKLIST (one landmark fewer)
    lmrk = demo / "LMRKLIST.TXT"
    assert changed(lmrk, lambda d: b"\n".join(d.split(b"\n")[1:]))
    # a changed maplet used by the picture
    marker = json.loads(output_paths(out, PIC)["marker"].read_text())
    used = next(iter(marker["inputs"]["maplets"]))
    assert changed(demo / "MAPFILES" / f"{used}.MAP", lambda d: d[:300] + bytes([d[300] ^ 1]) + d[301:])
    # a photo of higher precedence appearing in IMAGEFILES/ instead of IMAGEFILES1/
    moved = demo / "IMAGEFILES1"
    moved.mkdir()
    shutil.move(str(photo), moved / photo.name)
    assert not _resumed(demo, out)
    # a changed spctool version
    doc = json.loads(output_paths(out, PIC)["marker"].read_text())
    doc["spctool_version"] = "0.0.0-old"
    output_paths(out, PIC)["marker"].write_text(json.dumps(doc))
    assert not _resumed(demo, out)


def test_old_markers_are_not_trusted(demo, tmp_path):
    out = tmp_path / "out"
    run_batch(demo, [PIC], out_dir=out)
    path = output_paths(out, PIC)["marker"]
    doc = json.loads(path.read_text())
    doc["format"] = "spctool-batch-done/1"
    path.write_text(json.dumps(doc))
    assert not _resumed(demo, out)


# ------------------------------------------------------------------------------------------------
# atomic backups and temporary files


def test_backup_is_never_partial_on_a_full_disk(tmp_path, monkeypatch):
    p = tmp_path / "A.SUM"
    p.write_bytes(b"original\n" * 1000)

    def full(src, dst, length=0):
        dst.write(src.read(10))
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(atomic.shutil, "copyfileobj", full)
    with pytest.raises(SpcEnvironmentError) as err:
        atomic.write_text(p, "new\n", backup=True)
    assert str(err.value) == f"{p}: no space left on device"
    assert sorted(os.listdir(tmp_path)) == ["A.SUM"]  # no .bak, no .tmp
    assert p.read_bytes() == b"original\n" * 1000


def test_backup_survives_sigkill_at_any_instant(tmp_path):
    """Kill a process writing a 20 MB file with backup=True at many instants: whatever is left,
    every .bak is a complete copy of the original (never empty or truncated)."""
    original = os.urandom(1 << 16) * 320
    code = (
        "import sys; from spctool.formats import atomic\n"
        "atomic.write_bytes(sys.argv[1], b'new' * 7000000, backup=True)\n"
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    for k in range(8):
        d = tmp_path / f"t{k}"
        d.mkdir()
        target = d / "BIG.MAP"
        target.write_bytes(original)
        proc = subprocess.Popen([sys.executable, "-c", code, str(target)], env=env)
        time.sleep(0.15 + 0.05 * k)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        for bak in d.glob("BIG.MAP.bak*"):
            assert bak.read_bytes() == original
        assert target.read_bytes() in (original, b"new" * 7000000)
        atomic.remove_stale_temps(target)
        assert not list(d.glob(".*.tmp"))


def test_resume_removes_temporary_files_of_a_killed_rename(demo, tmp_path):
    out = tmp_path / "out"
    run_batch(demo, [PIC], out_dir=out)
    paths = output_paths(out, PIC)
    paths["marker"].unlink()  # killed before the marker's rename: not done
    stale = [paths[k].with_name(f".{paths[k].name}.a1b2c3d4.tmp") for k in ("sum", "marker", "register")]
    for s in stale:
        s.write_text("half")
    keep = paths["sum"].with_name("notes.tmp")  # not ours: kept
    keep.write_text("mine")
    res = run_batch(demo, [PIC], out_dir=out)
    assert not res.pictures[0].resumed and res.pictures[0].kind == "ok"
    assert not any(s.exists() for s in stale) and keep.exists()


def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(x) for x in text.split()]


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("method", ["fork", "spawn"])
def test_killing_the_batch_kills_its_workers(demo, tmp_path, method):
    cmd = [sys.executable, "-c", "from spctool.cli.main import cli; cli()"]
    cmd += ["-C", str(demo), "batch", "--jobs", "2", "--out-dir", str(tmp_path / "out")]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path), SPCTOOL_START_METHOD=method)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            workers = [c for c in _children(proc.pid) if _alive(c)]
            if len(workers) >= 2:
                break
            time.sleep(0.02)
        if proc.poll() is not None:
            pytest.skip("the batch finished before its workers were seen")
        assert len(workers) >= 2
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(_alive(w) for w in workers):
            time.sleep(0.05)
        alive = [w for w in workers if _alive(w)]
    finally:
        for w in workers:
            try:
                os.kill(w, signal.SIGKILL)
            except OSError:
                pass
        if proc.poll() is None:
            proc.kill()
    assert alive == [], "workers outlived the killed batch"


# ------------------------------------------------------------------------------------------------
# environment errors: one line naming the user's path, exit 3


@pytest.mark.parametrize(
    "code, words",
    [
        (errno.ENOSPC, "no space left on device"),
        (errno.EROFS, "read-only file system"),
        (errno.EACCES, "permission denied"),
        (errno.EIO, "input/output error"),
        (errno.EMFILE, "too many open files"),
    ],
)
def test_write_refusals_are_exit_3_naming_the_users_file(demo, tmp_path, monkeypatch, code, words):
    target = tmp_path / "new.SUM"

    def refuse(*a, **k):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(atomic.tempfile, "mkstemp", refuse)
    res = invoke("-C", demo, "convert", demo / "SUMFILES" / f"{PIC}.SUM", target)
    line = one_line_error(res, 3)
    assert str(target) in line and words in line.lower() and ".tmp" not in line


def test_disk_full_at_the_rename_names_the_user_file(tmp_path, monkeypatch):
    target = tmp_path / "x.txt"

    def full(*a, **k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/hidden/.x.txt.abcdefgh.tmp")

    monkeypatch.setattr(atomic.os, "replace", full)
    with pytest.raises(SpcEnvironmentError) as err:
        atomic.write_text(target, "data")
    assert str(err.value).startswith(str(target)) and ".tmp" not in str(err.value)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("code", [errno.EACCES, errno.EIO, errno.EMFILE])
def test_read_refusals_are_exit_3_naming_the_file(demo, monkeypatch, code):
    real_open = open
    victim = str(demo / "SUMFILES" / f"{PIC}.SUM")

    def refusing_open(file, *a, **k):
        if isinstance(file, (str, os.PathLike)) and os.path.abspath(os.fspath(file)) == victim:
            raise OSError(code, os.strerror(code), os.fspath(file))
        return real_open(file, *a, **k)

    monkeypatch.setattr("builtins.open", refusing_open)
    for args in (("info", victim), ("validate", victim), ("-C", demo, "lithos-select", PIC)):
        line = one_line_error(invoke(*args), 3)
        # the user's path: as given, or relative to -C DIR (which works like git -C)
        named = victim in line or f"SUMFILES/{PIC}.SUM" in line
        assert named and os.strerror(code).lower() in line.lower(), line


def test_batch_out_dir_refused_is_one_line(demo, tmp_path, monkeypatch):
    def refuse(*a, **k):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(atomic.tempfile, "mkstemp", refuse)
    res = invoke("-C", demo, "batch", "--out-dir", tmp_path / "out")
    assert res.exit_code in (1, 3), res.stderr
    assert "internal error" not in res.stderr and "Traceback" not in res.stderr
    assert "read-only file system" in res.stderr.lower()


# ------------------------------------------------------------------------------------------------
# non-regular and oversized inputs


@pytest.fixture
def fifo(tmp_path):
    path = tmp_path / "B00001.MAP"
    os.mkfifo(path)
    return path


@pytest.mark.parametrize("command", ["info", "validate"])
def test_fifo_input_is_refused_not_waited_for(fifo, command):
    t0 = time.monotonic()
    line = one_line_error(invoke(command, fifo), 2, "" if command == "validate" else "spctool: error: ")
    assert "FIFO" in line and str(fifo) in line
    assert time.monotonic() - t0 < 10


def test_fifo_convert_and_devices_are_refused(fifo, tmp_path):
    assert "FIFO" in one_line_error(invoke("convert", fifo, tmp_path / "x.MAP"), 2)
    link = tmp_path / "ZERO.MAP"
    link.symlink_to("/dev/zero")
    assert "device" in one_line_error(invoke("info", link), 2)
    assert "directory" in one_line_error(invoke("info", tmp_path), 2)


def test_non_regular_files_in_a_workdir_are_refused(demo):
    name = "B01536"
    (demo / "MAPFILES" / f"{name}.MAP").unlink()
    (demo / "MAPFILES" / f"{name}.MAP").symlink_to("/dev/zero")
    (demo / "LMKFILES" / f"{name}.LMK").unlink()
    os.mkfifo(demo / "LMKFILES" / f"{name}.LMK")
    res = invoke("-C", demo, "lithos-select", PIC)
    assert "FIFO" in one_line_error(res, 2)


def test_input_size_cap(tmp_path, monkeypatch):
    p = tmp_path / "big.txt"
    p.write_bytes(b"x" * 1000)
    with pytest.raises(SpcFormatError, match="at most 100 bytes"):
        guard.read_bytes(p, max_bytes=100)
    assert guard.read_bytes(p, max_bytes=1000) == b"x" * 1000


def test_spec_size_and_encoding(tmp_path):
    spec = tmp_path / "spec.toml"
    spec.write_bytes(b"seed = 1\n# caf\xe9\n")
    line = one_line_error(invoke("simulate", spec, tmp_path / "o"), 2)
    assert "UTF-8" in line and str(spec) in line
    spec.write_bytes(b"# " + b"x" * (2 << 20) + b"\n")
    assert "at most" in one_line_error(invoke("simulate", spec, tmp_path / "o"), 2)
    os.mkfifo(tmp_path / "fifo.toml")
    assert "FIFO" in one_line_error(invoke("simulate", tmp_path / "fifo.toml", tmp_path / "o"), 2)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "body, words",
    [
        ("[maplets]\ntruth_factor = 1000\n", "truth patches"),
        ("[body]\nq = 2147483648\n", "[body] q"),
        ("[camera]\nnpx = 1e9\n", "photos"),
    ],
)
def test_simulate_refuses_worlds_too_big_before_allocating(tmp_path, body, words):
    import resource

    spec = tmp_path / "spec.toml"
    spec.write_text(body)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    line = one_line_error(invoke("simulate", spec, tmp_path / "o"), 2)
    assert words in line and "--max-memory" in line
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200_000  # KiB
    assert not (tmp_path / "o").exists()


def test_max_memory_option(tmp_path):
    from spctool.sim.spec import memory_estimate, parse_spec

    spec = tmp_path / "spec.toml"
    spec.write_text("[maplets]\ncount = 2\n")
    need = memory_estimate(parse_spec({"maplets": {"count": 2}}))["total"]
    line = one_line_error(invoke("simulate", spec, tmp_path / "o", "--max-memory", "100M"), 2)
    assert "100.0 MiB" in line
    assert need > 100 * 1024**2
    assert "expected a size" in one_line_error(
        invoke("simulate", spec, tmp_path / "o", "--max-memory", "lots"), 2
    )


def test_workdir_paths_refuse_bad_names(tmp_path):
    wd = WorkDir(tmp_path)
    for method in (wd.sum_path, wd.nom_path, wd.map_path, wd.lmk_path, wd.photo_path):
        with pytest.raises(SpcUsageError):
            method("../x")
    assert batch.done_summary(tmp_path, tmp_path / "o", "../x", "f") is None


# ------------------------------------------------------------------------------------------------
# internal errors from file content are one line, exit 2; validate is as strict as the stages


def _map_with_ux(demo, value) -> Path:
    import struct

    import numpy as np

    from spctool.formats.maplet import read_map

    path = demo / "MAPFILES" / "B01536.MAP"
    data = bytearray(path.read_bytes())
    at = data.find(struct.pack(">f", np.float32(read_map(path).ux[0])))
    assert at > 0
    data[at : at + 4] = struct.pack(">f", value)
    path.write_bytes(bytes(data))
    return path


def test_map_with_absurd_frame_fails_validate_and_only_its_landmark(demo, tmp_path):
    path = _map_with_ux(demo, 3.4e38)
    res = invoke("validate", path)
    assert res.exit_code == 2 and "orthonormal" in res.stderr and "Warning" not in res.stderr
    res = invoke("-C", demo, "register", PIC, "B01536", "B01585")
    assert res.exit_code == 0 and "internal error" not in res.stderr
    assert "no-maplet" in res.stdout
    out = run_batch(demo, [PIC], out_dir=tmp_path / "out")
    assert out.pictures[0].kind == "ok"
    # the batch says so: a note in the summary (and its text) and a warning on stderr
    assert any("B01536" in n and "no-maplet" in n for n in out.pictures[0].notes)
    assert f"# {PIC} note: landmark B01536 left out" in out.to_text()
    res = invoke("-C", demo, "batch", "--out-dir", tmp_path / "out2", "--no-figure")
    assert res.exit_code == 0 and "warning" in res.stderr and "B01536" in res.stderr


@pytest.mark.parametrize(
    "name, text, words",
    [
        ("pts.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n", "faces"),
        ("big.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999999\n", "vertex index"),
        ("far.obj", "v 0 0 0\nv 1 0 0\nv 0 1e300 0\nf 1 2 3\n", "coordinates"),
        ("deep.json", '{"landmarks": [], "x": ' + "[" * 100000 + "]" * 100000 + "}", "nested"),
        ("huge.json", '{"landmarks": [{"name": "A", "sample": ' + "9" * 5001 + "}]}", "JSON"),
    ],
)
def test_content_that_crashed_is_one_line_exit_2(tmp_path, name, text, words):
    path = tmp_path / name
    path.write_text(text)
    for command in ("info", "validate"):
        res = invoke(command, path)
        assert res.exit_code == 2 and words in res.stderr, res.stderr
        assert "internal error" not in res.stderr and "Traceback" not in res.stderr


def test_json_table_with_int64_overflow_reads_as_numbers(tmp_path):
    from spctool.formats.table import read_table

    path = tmp_path / "t.json"
    path.write_text('{"landmarks": [{"name": "A", "sample": 123456789012345678901234567890, "line": 1}]}')
    t = read_table(path)
    assert t["sample"][0] == pytest.approx(1.2345678901234568e29)


def test_fits_with_zero_width_or_truncated_data_is_rejected(tmp_path):
    import numpy as np

    from spctool.formats.photo import format_fits

    good = format_fits(np.arange(64, dtype=np.uint16).reshape(8, 8))
    zero = good.replace(b"NAXIS1  =                    8", b"NAXIS1  =                    0", 1)
    (tmp_path / "zero.fits").write_bytes(zero)
    for command in ("info", "validate"):
        assert invoke(command, tmp_path / "zero.fits").exit_code == 2
    assert invoke("convert", tmp_path / "zero.fits", tmp_path / "z.pgm").exit_code == 2
    big = good.replace(b"NAXIS1  =                    8", b"NAXIS1  =                80000", 1)
    (tmp_path / "big.fits").write_bytes(big)
    res = invoke("info", tmp_path / "big.fits")
    assert res.exit_code == 2 and "data bytes" in res.stderr


def test_pgm_with_trailing_bytes_is_rejected(tmp_path):
    path = tmp_path / "x.pgm"
    path.write_bytes(b"P5\n4 2\n255\n" + bytes(8) + b"\n")  # trailing newline: fine
    assert invoke("info", path).exit_code == 0
    path.write_bytes(b"P5\n4 2\n255\n" + bytes(12))  # a wrong width hidden by extra bytes
    res = invoke("info", path)
    assert res.exit_code == 2 and "width or height" in res.stderr


def test_runtime_warnings_are_not_printed_before_the_error(demo):
    path = _map_with_ux(demo, 3.4e38)
    res = invoke("validate", path)
    assert "RuntimeWarning" not in res.stderr and len(res.stderr.strip().splitlines()) == 1


def test_an_input_replaced_in_place_keeps_a_bak(demo):
    src = demo / "SUMFILES" / f"{PIC}.SUM"
    before = src.read_bytes()
    res = invoke("convert", "--force", src, src)
    assert res.exit_code == 0, res.stderr
    assert (demo / "SUMFILES" / f"{PIC}.SUM.bak").read_bytes() == before


@pytest.mark.parametrize(
    "name, content",
    [
        ("q.txt", "9" * 5001 + "\n"),  # detected as ICQ by its lone integer, Q of 5001 digits
        ("spec.toml", "seed = " + "9" * 5001 + "\n"),
        ("x.NOM", (DEMO / "NOMINALS" / f"{PIC}.NOM").read_text().replace("BOD_FRAME", "9" * 100000 + "x", 1)),
        ("x.SUM", (DEMO / "SUMFILES" / f"{PIC}.SUM").read_text().replace("\n", "\n" + "9" * 100000, 40)),
    ],
)
def test_huge_digit_runs_are_one_line_and_fast(tmp_path, name, content):
    path = tmp_path / name
    path.write_text(content)
    t0 = time.monotonic()
    res = invoke("simulate", path, tmp_path / "o") if name.endswith(".toml") else invoke("info", path)
    assert "internal error" not in res.stderr and "Traceback" not in res.stderr
    assert time.monotonic() - t0 < 10


def test_map_linked_to_dev_zero_is_refused_by_the_stages(demo):
    path = demo / "MAPFILES" / "B01536.MAP"
    path.unlink()
    path.symlink_to("/dev/zero")
    t0 = time.monotonic()
    res = invoke("-C", demo, "register", PIC, "B01536", "B01585")
    assert res.exit_code == 0 and "device" in res.stderr and "no-maplet" in res.stdout
    assert time.monotonic() - t0 < 30


def test_direct_map_and_icq_readers_refuse_non_regular_files(tmp_path):
    """read_map / read_icq called from Python (not only through the commands) go through the guard:
    a FIFO is refused at once instead of blocking, a directory is named."""
    from spctool.errors import SpcFormatError
    from spctool.formats.icq import read_icq
    from spctool.formats.maplet import read_map

    fifo = tmp_path / "X.MAP"
    os.mkfifo(fifo)
    for reader in (read_map, read_icq):
        with pytest.raises(SpcFormatError, match="FIFO"):
            reader(fifo)
        with pytest.raises(SpcFormatError, match="directory"):
            reader(tmp_path)
