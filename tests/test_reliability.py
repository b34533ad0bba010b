"""Reliability, part 2 (issue #41): no input overwritten by any route, readers bounded by the file's
own content, no NaN pose read into a stage or written, ``--scheduler`` checked before any work, one
batch per ``--out-dir``, silent misreads of DAT, FITS and landmark tables, and the last internal errors.

Each test is one route the audit found broken; every one runs in well under a few seconds (a batch
that must not start is refused before its first picture).
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from spctool.cli.main import cli
from spctool.errors import SpcFormatError, SpcUsageError
from spctool.formats import guard

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "fixtures" / "demo"
PIC = "P000000001A1"


def invoke(*args, env=None):
    return CliRunner(env=env).invoke(cli, [str(a) for a in args], catch_exceptions=False)


def one_line(res, code):
    assert res.exit_code == code, (res.exit_code, res.stdout, res.stderr)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("spctool: error: "), res.stderr
    assert "internal error" not in res.stderr and "Traceback" not in res.stderr
    return lines[0]


def digests(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.fixture
def demo(tmp_path):
    wd = tmp_path / "wd"
    shutil.copytree(DEMO, wd)
    return wd


# ------------------------------------------------------------------------------------------------
# 1. no input overwritten, by any route


def test_symlinked_out_sumfiles_is_refused_naming_both_paths(demo, tmp_path):
    before = digests(demo / "SUMFILES")
    out = tmp_path / "out"
    out.mkdir()
    (out / "SUMFILES").symlink_to(demo / "SUMFILES")
    line = one_line(invoke("-C", demo, "batch", "--out-dir", out, "--no-figure"), 2)
    assert str(out / "SUMFILES") in line and str(demo / "SUMFILES") in line and "symbolic link" in line
    assert digests(demo / "SUMFILES") == before
    assert not list((demo / "SUMFILES").glob("*.bak"))


def test_out_dir_that_is_the_workdir_by_another_path_is_refused(demo, tmp_path):
    # a second path to the same directory (here a symbolic link; a bind mount below) is seen through
    alias = tmp_path / "alias"
    alias.symlink_to(demo)
    line = one_line(invoke("-C", demo, "batch", "--out-dir", alias, "--no-figure"), 2)
    assert "--out-dir must differ" in line or "same device and inode" in line


def _bind(src: Path, dst: Path) -> bool:
    if os.geteuid() != 0 or not shutil.which("mount"):
        return False
    res = subprocess.run(["mount", "--bind", str(src), str(dst)], capture_output=True)
    return res.returncode == 0


@pytest.mark.parametrize("what", ["out-dir", "SUMFILES"])
def test_bind_mounted_out_dir_or_sumfiles_is_refused_by_device_and_inode(demo, tmp_path, what):
    out = tmp_path / "out"
    target = out if what == "out-dir" else out / "SUMFILES"
    target.mkdir(parents=True)
    source = demo if what == "out-dir" else demo / "SUMFILES"
    if not _bind(source, target):
        pytest.skip("bind mounts need root and mount(8)")
    try:
        before = digests(demo / "SUMFILES")
        line = one_line(invoke("-C", demo, "batch", "--out-dir", out, "--no-figure"), 2)
        assert "same device and inode" in line and str(target) in line and str(source) in line
        assert digests(demo / "SUMFILES") == before
    finally:
        subprocess.run(["umount", str(target)], check=True)


def test_a_link_made_while_the_batch_runs_is_refused_per_picture_before_anything_is_removed(demo, tmp_path):
    from spctool.batch.picture import PictureOutcome, PictureSummary, write_outcome
    from spctool.formats.workdir import WorkDir

    before = digests(demo / "SUMFILES")
    out = tmp_path / "out"
    out.mkdir()
    (out / "SUMFILES").symlink_to(demo / "SUMFILES")  # after run_batch's own check
    outcome = PictureOutcome(PictureSummary(PIC, "ok"), sum_text="X\n", workdir=WorkDir(demo))
    with pytest.raises(SpcUsageError, match="symbolic link"):
        write_outcome(out, outcome, "f" * 64)
    assert digests(demo / "SUMFILES") == before
    os.unlink(out / "SUMFILES")
    (out / "SUMFILES").mkdir()
    os.rmdir(out / "SUMFILES")
    (out / "TABLES").symlink_to(demo)  # the markers' folder onto the working directory itself
    with pytest.raises(SpcUsageError):
        write_outcome(out, outcome, "f" * 64)


def test_a_picture_never_replaces_a_file_it_read_by_any_path(demo, tmp_path):
    from spctool.batch.picture import PictureOutcome, PictureSummary, write_outcome
    from spctool.formats.sumfile import read_sum
    from spctool.formats.workdir import WorkDir

    src = demo / "SUMFILES" / f"{PIC}.SUM"
    before = src.read_bytes()
    out = tmp_path / "out"
    (out / "SUMFILES").mkdir(parents=True)
    (out / "SUMFILES" / f"{PIC}.SUM").symlink_to(src)  # the output file itself a link to the input
    outcome = PictureOutcome(PictureSummary(PIC, "ok"), sum_text="X\n", workdir=WorkDir(demo))
    with guard.input_scope():  # as process_picture runs a picture
        read_sum(src)
        with pytest.raises(SpcUsageError, match=f"{PIC}.SUM: it is the input {src} .same device and inode"):
            write_outcome(out, outcome, "f" * 64)
    assert src.read_bytes() == before and (out / "SUMFILES" / f"{PIC}.SUM").is_symlink()
    hard = tmp_path / "hard.SUM"
    os.link(src, hard)
    with guard.input_scope():
        read_sum(hard)
        with pytest.raises(SpcUsageError, match="same device and inode"):
            guard.refuse_read_input(src)
    guard.refuse_read_input(src)  # outside a scope nothing is remembered


def test_output_option_onto_an_input_table_is_refused_naming_both(tmp_path):
    from spctool.cli.common import emit
    from spctool.formats.table import read_table

    table = tmp_path / "sel.txt"
    table.write_text("name\nB01536\nB01585\n")
    link = tmp_path / "sel-link.txt"
    link.symlink_to(table)
    before = table.read_bytes()
    with guard.input_scope():  # as every command runs (SpcGroup.main)
        read_table(table)  # a command's --landmarks TABLE
        with pytest.raises(SpcUsageError, match=f"{link}: it is the input {table} .same device and inode"):
            emit("name\nX\n", str(link))  # its -o FILE
    assert table.read_bytes() == before and not list(tmp_path.glob("*.bak"))


# ------------------------------------------------------------------------------------------------
# 2. readers bounded by the file's own content; linear checks


def _sparse_map(path: Path, q: int) -> None:
    import struct

    from spctool.formats.maplet import map_file_size

    header = bytearray(72)
    struct.pack_into(">f", header, 6, 0.001)
    header[10], header[11] = q % 256, q // 256
    struct.pack_into(">12f", header, 15, 0, 0, 1, 1, 0, 0, 0, 1, 0, 0, 0, 1)
    struct.pack_into(">f", header, 63, 1e-4)
    with open(path, "wb") as fh:
        fh.write(header)
        fh.truncate(map_file_size(q))  # a hole: nothing on disk


@pytest.mark.parametrize("command", ["info", "validate"])
def test_sparse_map_is_refused_before_it_is_read(tmp_path, command):
    path = tmp_path / "B00001.MAP"
    _sparse_map(path, 6000)  # 432 MB long, 4 KB on disk (the audit's case)
    if os.stat(path).st_blocks * 512 * guard.SPARSE_RATIO >= os.stat(path).st_size:
        pytest.skip("this file system does not make sparse files")
    t0 = time.monotonic()
    res = invoke(command, path)
    assert time.monotonic() - t0 < 5
    if command == "info":
        line = one_line(res, 2)
    else:
        assert res.exit_code == 2
        line = res.stderr
    assert "sparse file" in line and str(path) in line


def test_few_blocks_without_holes_is_no_sparse_file(tmp_path, monkeypatch):
    # a compressing file system (ZFS, btrfs) allocates few blocks for a full file: no holes, no refusal
    from types import SimpleNamespace

    monkeypatch.setattr(guard, "SPARSE_MIN_BYTES", 1024)
    full = tmp_path / "full.bin"
    full.write_bytes(bytes(256 * 1024))
    compressed = SimpleNamespace(st_size=256 * 1024, st_blocks=8)
    guard._refuse_sparse(full, compressed, "a file")  # SEEK_DATA finds every byte: accepted
    holes = tmp_path / "holes.bin"
    with open(holes, "wb") as fh:
        fh.truncate(256 * 1024)
    if guard._data_bytes(holes, 256 * 1024) == 256 * 1024:
        pytest.skip("this file system does not make sparse files")
    with pytest.raises(SpcFormatError, match="sparse file"):
        guard._refuse_sparse(holes, SimpleNamespace(st_size=256 * 1024, st_blocks=0), "a file")


def test_map_longer_than_its_largest_qsz_is_refused_before_allocating(tmp_path, monkeypatch):
    from spctool.formats.maplet import read_map

    monkeypatch.setattr(guard, "SPARSE_MIN_BYTES", 1 << 62)  # let the sparse file through to the cap
    path = tmp_path / "B00001.MAP"
    _sparse_map(path, 6000)
    reads = []
    real_open = open

    def watching_open(file, *a, **k):
        fh = real_open(file, *a, **k)
        reads.append(file)
        return fh

    monkeypatch.setattr("builtins.open", watching_open)
    with pytest.raises(SpcFormatError, match=r"QSZ <= 4096\) of at most"):
        read_map(path)
    assert not reads  # refused from its size, before a byte was read


def test_validate_of_a_100000_row_sum_is_linear(tmp_path):
    text = (DEMO / "SUMFILES" / f"{PIC}.SUM").read_text()
    head = text.split("LANDMARKS")[0]
    rows = "".join(f"L{i % 99999:05d}{100.0 + i % 500:10.2f}{200.0:10.2f}\n" for i in range(100_000))
    path = tmp_path / "BIG.SUM"
    path.write_text(head + "LANDMARKS\n" + rows + "LIMB FITS\nEND FILE\n")
    t0 = time.process_time()  # CPU time: other processes on a loaded machine do not count
    res = invoke("validate", path)
    elapsed = time.process_time() - t0
    assert res.exit_code == 2 and "duplicate landmark rows: L00000" in res.stderr
    assert elapsed < 2.0, elapsed


# ------------------------------------------------------------------------------------------------
# 3. non-finite values


@pytest.mark.parametrize(
    "folder, name, old, new, line, label",
    [
        ("SUMFILES", f"{PIC}.SUM", "   -0.1919302072D+01", "   NaN", 5, "SCOBJ"),
        ("SUMFILES", f"{PIC}.SUM", "    0.7680000000D+01", "    Infinity", 4, "MMFL, CTR"),
        ("NOMINALS", f"{PIC}.NOM", "   -0.1919302072D+01", "  -Inf", 3, "SCOBJ"),
        ("LMKFILES", "B01536.LMK", "    0.2777748334D+00", "    nan", 5, "VLM"),
    ],
)
def test_validate_refuses_non_finite_values_naming_file_and_line(demo, folder, name, old, new, line, label):
    path = demo / folder / name
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))
    res = invoke("validate", path)
    assert res.exit_code == 2
    assert f"{path}:{line}: expected finite numbers ({label})" in res.stderr
    assert "valid" not in res.stdout


def test_stages_and_batch_refuse_a_nan_pose_and_never_write_one(demo, tmp_path):
    from spctool.batch import run_batch

    path = demo / "SUMFILES" / f"{PIC}.SUM"
    path.write_text(path.read_text().replace("   -0.1919302072D+01", "   NaN", 1))
    line = one_line(invoke("-C", demo, "lithos-select", PIC), 2)
    assert f"{PIC}.SUM:5: expected finite numbers (SCOBJ)" in line
    out = tmp_path / "out"
    result = run_batch(demo, [PIC], out_dir=out, write_summary=False)
    assert result.pictures[0].failed and ":5: expected finite numbers (SCOBJ)" in result.pictures[0].status
    assert not (out / "SUMFILES" / f"{PIC}.SUM").exists()


@pytest.mark.parametrize("cx, found", [("0.9000000000D+00", "max |R R^T - I| = 0.69"), (None, "left-handed")])
def test_stages_and_geometry_refuse_a_skewed_camera_frame(demo, tmp_path, cx, found):
    """CX, CY, CZ not a rotation (a row edited; a row's sign flipped): every stage, the batch and
    geometry refuse the SUM naming its CX line (geometry once solved on it: chi2/dof 222, exit 0), while
    rounding far beyond SPC's D20.10 rows (1e-6) is accepted."""
    from spctool.batch import run_batch
    from spctool.formats import guard
    from spctool.formats.sumfile import read_sum

    path = demo / "SUMFILES" / f"{PIC}.SUM"
    text = path.read_text()
    row = "    0.3426042828D+00   -0.9394798049D+00    0.3974291037D-04   CX"
    assert row in text
    flipped = "   -0.3426042828D+00    0.9394798049D+00   -0.3974291037D-04   CX"  # -CX: det -1
    bad = row.replace("0.3426042828D+00", cx) if cx else flipped
    path.write_text(text.replace(row, bad))
    for command in ("lithos-select", "register", "geometry"):
        line = one_line(invoke("-C", demo, command, PIC), 2)
        assert f"{PIC}.SUM:6: expected CX, CY, CZ the rows of a rotation" in line and found in line, line
    result = run_batch(demo, [PIC], out_dir=tmp_path / "out", write_summary=False)
    assert result.pictures[0].failed and ":6: expected CX, CY, CZ" in result.pictures[0].status
    path.write_text(text.replace(row, row.replace("0.3426042828D+00", "0.3426052828D+00")))
    guard.check_sum_header(read_sum(path), path)  # 1e-6 off: accepted


@pytest.mark.parametrize(
    "old, new, line, words",
    [
        ("    0.7680000000D+01", "    0.0000000000D+00", 4, "a positive MMFL, found 0"),
        (" 454.54000   0.00000   0.00000   0.00000 -454.54000", "   0.00000   0.00000   0.00000   0.00000 "
         "   0.00000", 10, "a K-MATRIX whose 2 x 2 block is invertible"),
    ],
)
def test_a_sum_whose_camera_cannot_be_made_names_its_line(demo, old, new, line, words):
    """MMFL 0 or a zero K-MATRIX ended in a camera error naming no file ('the camera model cannot
    invert the photo's centre pixel'): the SUM's line is named, as for every other bad value."""
    path = demo / "SUMFILES" / f"{PIC}.SUM"
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))
    for command in ("lithos-select", "register"):
        got = one_line(invoke("-C", demo, command, PIC), 2)
        assert f"{PIC}.SUM:{line}: expected {words}" in got, got


def test_stages_refuse_a_nan_landmark_naming_its_line(demo):
    path = demo / "LMKFILES" / "B01536.LMK"
    path.write_text(path.read_text().replace("    0.2777748334D+00", "    NaN", 1))
    line = one_line(invoke("-C", demo, "lithos-select", PIC), 2)
    assert "B01536.LMK:5: expected finite numbers (VLM)" in line


def test_writers_refuse_a_non_finite_pose():
    from spctool.formats.nominal import format_nom, read_nom
    from spctool.formats.sumfile import format_sum, read_sum

    pic = read_sum(DEMO / "SUMFILES" / f"{PIC}.SUM")
    pic.cz = np.array([0.0, np.inf, 1.0])
    with pytest.raises(SpcUsageError, match=r"non-finite pose \(CZ"):
        format_sum(pic)
    nom = read_nom(DEMO / "NOMINALS" / f"{PIC}.NOM")
    nom.scobj = np.array([np.nan, 0.0, 1.0])
    with pytest.raises(SpcUsageError, match=r"non-finite pose \(SCOBJ"):
        format_nom(nom)


@pytest.mark.parametrize(
    "args, named",
    [
        (["geometry", PIC, "--sigma-floor-px", "nan", "--dry-run"], "--sigma-floor-px"),
        (["geometry", PIC, "--estimate-camera", "focal", "--camera-sigma", "nan"], "--camera-sigma"),
        (["geometry", PIC, "--min-parallax", "inf", "--dry-run"], "--min-parallax"),
        (["register", PIC, "--corr-min", "nan"], "--corr-min"),
        (["lithos", "B01536", "--seed", "-5", "--dry-run"], "--seed"),
        (["lithos", "B01536", "--thresholds", "200,10", "--dry-run"], "--thresholds"),
        (["lithos", "B01536", "--thresholds", "nan,nan", "--dry-run"], "--thresholds"),
    ],
)
def test_non_finite_or_out_of_range_option_values_are_bad_input(demo, args, named):
    """NaN passes every comparison of a range check: such values once reached the solvers (an internal
    error, exit 1) or ran silently; now exit 2 with one line naming the option."""
    res = invoke("-C", demo, *args)
    assert res.exit_code == 2, res.output
    assert named in one_line(res, 2)


def test_a_landmark_table_is_read_as_given(demo):
    """A table given with no row registers nothing (it once fell back to a lithos-select of every
    landmark), with a warning; a word in its sample or line column is exit 2 naming the line (it was
    replaced by the projection silently); a nan there is the projection, with a note."""
    sel = invoke("-C", demo, "lithos-select", PIC)
    assert sel.exit_code == 0
    lines = sel.stdout.splitlines()
    head = [ln for ln in lines if ln.startswith("#")] + [next(ln for ln in lines if ln.startswith("name"))]
    rows = [ln for ln in lines if not ln.startswith(("#", "name"))]
    (demo / "empty.txt").write_text("\n".join(head) + "\n")
    res = invoke("-C", demo, "register", PIC, "--landmarks", demo / "empty.txt", "--json")
    assert res.exit_code == 0 and json.loads(res.stdout)["landmarks"] == []
    assert "registered 0 of 0 landmarks: the table given has no landmark row" in res.stderr
    first = rows[0].split()
    worded = " ".join([first[0], "4x5.5", *first[2:]])
    (demo / "word.txt").write_text("\n".join([*head, worded, *rows[1:]]) + "\n")
    line = one_line(invoke("-C", demo, "register", PIC, "--landmarks", demo / "word.txt"), 2)
    assert f"word.txt:{len(head) + 1}: expected a number (or nan) in column 'sample', found '4x5.5'" in line
    nan_row = " ".join([first[0], "nan", *first[2:]])
    (demo / "nan.txt").write_text("\n".join([*head, nan_row, *rows[1:]]) + "\n")
    res = invoke("-C", demo, "register", PIC, "--landmarks", demo / "nan.txt", "--steps", "4,2,1")
    assert res.exit_code == 0 and f"no pixel (nan) for {first[0]}" in res.stderr


def test_predict_and_extract_refuse_another_pictures_table_and_navigate_keeps_a_bak(demo, tmp_path):
    other = invoke("-C", demo, "lithos-select", "P000000002A1")
    (demo / "other.txt").write_text(other.stdout)
    for command in ("predict", "extract"):
        line = one_line(invoke("-C", demo, command, PIC, "--landmarks", demo / "other.txt"), 2)
        assert "P000000002A1" in line and "--any-picture" in line
        res = invoke("-C", demo, command, PIC, "--landmarks", demo / "other.txt", "--any-picture")
        assert res.exit_code == 0, res.output
    target = demo / "SUMFILES" / f"{PIC}.SUM"
    before = target.read_bytes()
    res = invoke("-C", demo, "navigate", PIC, "--output", target)
    assert res.exit_code == 0, res.output
    assert (demo / "SUMFILES" / f"{PIC}.SUM.bak").read_bytes() == before and target.read_bytes() != before


@pytest.mark.parametrize(
    "args, named",
    [
        (["navigate", PIC, "--reach", "1e6"], "--reach"),
        (["register", PIC, "--acquire-reach", "100000"], "--acquire-reach"),
        (["correlate", PIC, "B01980", "--grid-half", "100000"], "--grid-half"),
        (["register", PIC, "--space", "image", "--grid-half", "5000"], "--grid-half"),
    ],
)
def test_a_search_larger_than_the_photo_is_refused_before_any_array(demo, args, named):
    """Searches no photo can hold ended in MemoryError (34.7 TiB for --reach 1e6) or ran the machine
    out of memory: exit 2 with one line naming the option and the most it can be."""
    line = one_line(invoke("-C", demo, *args), 2)
    assert named in line and "at most" in line


@pytest.mark.parametrize("command", ["register", "predict", "navigate"])
def test_a_truncated_maplet_is_a_warning_a_missing_one_a_note(demo, command):
    """A MAP file there but unreadable fails only its landmark (tests/test_faults.py), but it was said
    as a note, which -q silences and a reader takes for a landmark without a maplet: it is a warning
    naming the file and byte.  A landmark with no MAP file at all stays a note."""
    path = demo / "MAPFILES" / "B01980.MAP"
    path.write_bytes(path.read_bytes()[:1000])
    res = invoke("-C", demo, command, PIC)
    assert res.exit_code in (0, 1), res.output
    assert "warning: B01980: no maplet: its MAP file is unreadable" in res.stderr
    assert "B01980.MAP:byte 1000" in res.stderr
    path.unlink()
    res = invoke("-C", demo, command, PIC)
    assert res.exit_code in (0, 1) and "note: B01980: no maplet" in res.stderr, res.output


# ------------------------------------------------------------------------------------------------
# 4. --scheduler checked before any work


@pytest.mark.parametrize(
    "address, words",
    [
        ("garbage", "no port"),
        ("", "empty address"),
        ("inproc://127.0.0.1/1/1", "inproc://"),
        ("tls://127.0.0.1:8786", "certificates"),
        ("tcp://127.0.0.1:0", "outside 1-65535"),
        ("tcp://127.0.0.1:x", "not a number"),
        ("ws://127.0.0.1:8786", "not supported"),
        ("tcp://a b:1", "spaces"),
    ],
)
def test_malformed_scheduler_is_exit_2_at_once(demo, tmp_path, address, words):
    t0 = time.monotonic()
    line = one_line(invoke("-C", demo, "batch", "--scheduler", address, "--out-dir", tmp_path / "o"), 2)
    assert time.monotonic() - t0 < 2 and words in line
    assert not (tmp_path / "o").exists()  # nothing done


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Server:
    """A loopback TCP server of ours that behaves as ``mode`` says (never a Dask scheduler)."""

    def __init__(self, mode: str):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(4)
        self.port = self.sock.getsockname()[1]
        self.mode = mode
        self.conns = []
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        try:
            while True:
                conn, _ = self.sock.accept()
                self.conns.append(conn)
                if self.mode == "close":
                    conn.close()
                elif self.mode == "banner":
                    conn.sendall(b"SSH-2.0-OpenSSH_9.6\r\n")
                # "silent": an HTTP server waiting for a request
        except OSError:
            pass

    def close(self):
        self.sock.close()
        for c in self.conns:
            c.close()


@pytest.mark.parametrize("mode", ["silent", "close", "banner"])
def test_non_dask_endpoint_is_one_line_within_the_timeout(demo, tmp_path, monkeypatch, mode):
    from spctool.batch import scheduler

    monkeypatch.setattr(scheduler, "CONNECT_TIMEOUT_S", 1.0)
    server = _Server(mode)
    try:
        t0 = time.monotonic()
        address = f"tcp://127.0.0.1:{server.port}"
        res = invoke("-C", demo, "batch", "--scheduler", address, "--out-dir", tmp_path / "o")
        elapsed = time.monotonic() - t0
    finally:
        server.close()
    line = one_line(res, 2)
    assert "not a Dask scheduler" in line and elapsed < 1.0 + 1.5
    assert not (tmp_path / "o").exists()


def test_unreachable_scheduler_is_exit_3_at_once(demo, tmp_path):
    port = _free_port()  # opened and closed by us: nothing listens there
    t0 = time.monotonic()
    res = invoke("-C", demo, "batch", "--scheduler", f"127.0.0.1:{port}", "--out-dir", tmp_path / "o")
    line = one_line(res, 3)
    assert "cannot reach a Dask scheduler" in line and time.monotonic() - t0 < 5.0


def test_a_real_scheduler_passes_the_check():
    from distributed import LocalCluster

    from spctool.batch.scheduler import check_scheduler

    kw = dict(n_workers=0, processes=False, protocol="tcp", host="127.0.0.1", dashboard_address=None)
    with LocalCluster(scheduler_port=0, **kw) as cluster:
        assert str(check_scheduler(cluster.scheduler_address)) == cluster.scheduler_address


# ------------------------------------------------------------------------------------------------
# 5. one batch per --out-dir


def test_second_batch_on_one_out_dir_is_refused_naming_the_holder(demo, tmp_path):
    from spctool.batch.lock import out_dir_lock

    out = tmp_path / "out"
    out.mkdir()
    with out_dir_lock(out):
        line = one_line(invoke("-C", demo, "batch", "--out-dir", out, "--no-figure"), 2)
    assert f"PID {os.getpid()} on host {socket.gethostname()}" in line and "another batch" in line
    assert not (out / ".spctool-batch.lock").exists()  # released and removed


def test_stale_lock_of_a_dead_process_is_taken_over_with_a_note(tmp_path):
    from spctool.batch.lock import LOCK_NAME, out_dir_lock

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    lock = tmp_path / LOCK_NAME
    lock.write_text(f"pid {dead.pid}\nhost {socket.gethostname()}\nsince 2026-01-01T00:00:00Z\n")
    notes = []
    with out_dir_lock(tmp_path, notes.append):
        assert f"pid {os.getpid()}\n" in lock.read_text()
    assert len(notes) == 1 and f"PID {dead.pid}" in notes[0] and "took over" in notes[0]
    assert not lock.exists()


# ------------------------------------------------------------------------------------------------
# 6. silent misreads: DAT, FITS


def test_dat_cut_to_half_is_refused_and_a_true_8_bit_dat_is_read(tmp_path):
    from spctool.formats.photo import read_dat

    data = (DEMO / "IMAGEFILES" / f"{PIC}.DAT").read_bytes()  # 768 x 768, 16-bit
    cut = tmp_path / "cut.DAT"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(SpcFormatError, match="16-bit photo cut short"):
        read_dat(cut, 768, 768)
    res = invoke("info", cut, "--npx", 768, "--nln", 768)
    assert "16-bit photo cut short" in one_line(res, 2)
    eight = read_dat(DEMO / "IMAGEFILES" / f"{PIC}.DAT", 768, 768).data >> 8
    path = tmp_path / "eight.DAT"
    path.write_bytes(eight.astype(np.uint8).tobytes() + bytes(100))  # with bytes SPC never reads
    assert read_dat(path, 768, 768).data.dtype == np.uint8


def test_fits_structure_is_checked(tmp_path):
    from spctool.formats.photo import format_fits, read_photo

    img = np.random.default_rng(0).integers(0, 4000, (100, 120)).astype(np.uint16)
    good = format_fits(img)
    (tmp_path / "padded.fits").write_bytes(good + bytes(2880))  # zero blocks after the last HDU
    assert np.array_equal(read_photo(tmp_path / "padded.fits").data, img)
    cases = {
        "inserted.fits": good[:5000] + b"1234567" + good[5000:],
        "appended.fits": good + b"x" * 2880,
        "noend.fits": good.replace(b"END" + b" " * 77, b"XND" + b" " * 77, 1),
    }
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        line = one_line(invoke("info", tmp_path / name), 2)
        assert name in line and ("2880-byte blocks" in line or "END card" in line), line


# ------------------------------------------------------------------------------------------------
# 7. the last internal errors


def test_closed_stdout_is_exit_3_one_line(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    code = "from spctool.cli.main import cli; cli()"
    res = subprocess.run(
        [sys.executable, "-c", code, "info", str(DEMO / "SUMFILES" / f"{PIC}.SUM")],
        preexec_fn=lambda: os.close(1),
        stderr=subprocess.PIPE,
        env=env,
        timeout=60,
    )
    lines = res.stderr.decode().strip().splitlines()
    assert res.returncode == 3 and lines == [
        "spctool: error: <stdout>: standard output is closed (redirect it to a file or use -o)"
    ]


def test_out_dir_name_not_valid_utf8_is_exit_2_one_line(demo, tmp_path):
    name = os.fsdecode(bytes(tmp_path) + b"/out\xff")
    line = one_line(invoke("-C", demo, "batch", "--out-dir", name, "--no-figure"), 2)
    assert "not valid UTF-8" in line and "out\\xff" in line
    assert not os.path.exists(os.fsencode(name))
