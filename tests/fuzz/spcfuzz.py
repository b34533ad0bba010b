"""A seeded mutation fuzzer over every input format and command of spctool (issue #19).

Seeds are real files: the demo working directory (``fixtures/demo``: SUM, NOM, LMK, MAP, ICQ shape,
INIT_LITHOS, PICTLIST, LMRKLIST, DAT/FITS/PGM photos, its SPEC ``fixtures/demo.toml``), mission files
from ``fixtures/real`` (Hayabusa SUM, Rosetta LMK), and files spctool derives from them (landmark
tables in text and JSON, a PNG photo, OBJ and VTK meshes).  Each mutant is one seed changed by one
or more seeded mutations (bit flips, interesting bytes and numbers — ``1D+400``, NaN, 2**31, 3.4e38 —
duplicated, swapped, dropped lines, a BOM, truncation, garbage after a number …), put in place of
the seed in a scratch copy of the working directory, and run through the commands that read that
kind of file (``info``, ``validate``, ``convert`` and the stages), in process through click.

Every run is classified:

* ``ok`` (exit 0), ``rejected`` (exit 2 / 3, or 1 for a result check, with ONE ``spctool: error:``
  line, or ``validate``'s one line per file);
* **failures**: ``internal`` (exit 1 "internal error"), ``traceback``, ``hang`` (over the time
  limit), ``blowup`` (MemoryError, or the address-space limit hit), ``noise`` (a warning or more
  than one line on stderr before the error).

Accepted mutants of *structural* mutations (those that should not give a valid file with the same
meaning: duplicated/swapped/dropped lines, garbage after a number, a BOM, an overflowing exponent)
whose ``info --json`` differs from the seed's are listed as silent-misread candidates for triage.

``python tests/fuzz/spcfuzz.py --mutants N --workers 2 --seed S`` runs it from the command line.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import re
import shutil
import signal
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "fixtures" / "demo"
REAL = ROOT / "fixtures" / "real"
PIC = "P000000001A1"
LMK = "B01536"
#: seconds one command may take before it counts as a hang
TIME_LIMIT_S = 60.0
#: address-space limit of a fuzz worker (a blow-up becomes a MemoryError, not the OOM killer)
MEMORY_LIMIT = 6 * 1024**3

FAILURES = ("internal", "traceback", "hang", "blowup", "noise")
STRUCTURAL = ("dup_line", "swap_lines", "drop_line", "bom", "garbage_after_number", "overflow_exponent")

INTERESTING_NUMBERS = [
    "0",
    "-0",
    "1",
    "-1",
    "2147483647",
    "2147483648",
    "-2147483649",
    "4294967296",
    "9" * 30,
    "1D+400",
    "1E+400",
    "-1D+400",
    "1e-400",
    "NaN",
    "nan",
    "Inf",
    "-Infinity",
    "3.4e38",
    "1.797e308",
    "1e9",
    "65536",
    "0.0",
    "1e-320",
    "12345678901234567890",
    "0x10",
    "1_000",
    "",
]
INTERESTING_BYTES = [0x00, 0xFF, 0x7F, 0x80, 0x0A, 0x0D, 0x20, 0x2E, 0x2D, 0x2B, 0x45, 0x44, 0x3A, 0xEF]
NUMBER = re.compile(rb"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eEdD][-+]?\d+)?")


# ------------------------------------------------------------------------------------------------
# seeds and the commands that read them


@dataclass
class Seed:
    name: str  # kind label
    rel: str  # path in the scratch working directory
    commands: list  # argument lists; "{F}" = the mutant, "{W}" = workdir, "{T}" = a scratch dir
    text: bool = True
    head_bias: int = 0  # binary: mutate mostly within the first head_bias bytes


def build_scratch(dest: Path) -> Path:
    """The scratch working directory: the demo plus derived seeds (tables, PNG, OBJ, VTK, SPEC)."""
    from click.testing import CliRunner

    from spctool.cli.main import cli

    wd = dest / "wd"
    shutil.copytree(DEMO, wd)
    seeds = wd / "SEEDS"
    seeds.mkdir()
    run = CliRunner()
    sel = run.invoke(cli, ["-C", str(wd), "lithos-select", PIC, "--no-occlusion"])
    (seeds / "sel.txt").write_text(sel.stdout)
    selj = run.invoke(cli, ["-C", str(wd), "lithos-select", PIC, "--no-occlusion", "--json"])
    (seeds / "sel.json").write_text(selj.stdout)
    reg = run.invoke(cli, ["-C", str(wd), "register", PIC, "--landmarks", str(seeds / "sel.txt")])
    (seeds / "reg.txt").write_text(reg.stdout)
    run.invoke(cli, ["convert", str(wd / "IMAGEFILES" / "P000000004A1.PGM"), str(seeds / "P4.PNG")])
    # a small closed mesh (an octahedron, subdivided once) as OBJ; VTK converted from it
    v = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]
    f = [(1, 3, 5), (3, 2, 5), (2, 4, 5), (4, 1, 5), (3, 1, 6), (2, 3, 6), (4, 2, 6), (1, 4, 6)]
    obj = "".join(f"v {x * 0.3:.6f} {y * 0.25:.6f} {z * 0.2:.6f}\n" for x, y, z in v)
    obj += "".join(f"f {a} {b} {c}\n" for a, b, c in f)
    (seeds / "tiny.obj").write_text(obj)
    run.invoke(cli, ["convert", str(seeds / "tiny.obj"), str(seeds / "tiny.vtk")])
    shutil.copy(ROOT / "fixtures" / "demo.toml", seeds / "spec.toml")
    shutil.copy(REAL / "hayabusa-itokawa" / "N2395699394.SUM", seeds / "N2395699394.SUM")
    shutil.copy(REAL / "rosetta-67p" / "FA0115.LMK", seeds / "FA0115.LMK")
    (seeds / "PICT1.TXT").write_text(f" {PIC}\nEND\n")
    return wd


def seeds() -> list[Seed]:
    info = [["info", "{F}"], ["validate", "{F}"], ["info", "--json", "{F}"]]
    stage_sel = ["-C", "{W}", "lithos-select", PIC, "--no-occlusion"]
    register = ["-C", "{W}", "register", PIC, "--landmarks", "{W}/SEEDS/sel.txt"]
    return [
        Seed("sum", f"SUMFILES/{PIC}.SUM", info + [stage_sel, register]),
        Seed("nom", f"NOMINALS/{PIC}.NOM", info),
        Seed("lmk", f"LMKFILES/{LMK}.LMK", info + [stage_sel]),
        Seed("map", f"MAPFILES/{LMK}.MAP", info + [register, ["-C", "{W}", "predict", PIC, LMK]], False, 72),
        Seed("icq", "SHAPEFILES/SHAPE.TXT", [["info", "{F}"], ["validate", "{F}"]]),
        Seed("lithos", "INIT_LITHOS.TXT", info + [stage_sel]),
        Seed("pictlist", "PICTLIST.TXT", info),
        Seed("pictlist-batch", "SEEDS/PICT1.TXT", [["-C", "{W}", "batch", "{F}", "--out-dir", "{T}/out"]]),
        Seed("lmrklist", "LMRKLIST.TXT", info + [stage_sel]),
        Seed(
            "dat",
            f"IMAGEFILES/{PIC}.DAT",
            [["validate", "--sum", f"{{W}}/SUMFILES/{PIC}.SUM", "{F}"], register],
            False,
            4096,
        ),
        Seed(
            "fits",
            "IMAGEFILES/P000000003A1.FITS",
            info + [["convert", "{F}", "{T}/x.PGM"], ["-C", "{W}", "register", "P000000003A1"]],
            False,
            2880,
        ),
        Seed("pgm", "IMAGEFILES/P000000004A1.PGM", info + [["convert", "{F}", "{T}/x.FITS"]], False, 64),
        Seed("png", "SEEDS/P4.PNG", info + [["convert", "{F}", "{T}/x.PGM"]], False, 256),
        Seed(
            "table",
            "SEEDS/reg.txt",
            info + [["-C", "{W}", "solve-pose", PIC, "--measurements", "{F}"]],
        ),
        Seed(
            "table-json",
            "SEEDS/sel.json",
            info + [["-C", "{W}", "register", PIC, "--landmarks", "{F}"]],
        ),
        Seed("table-sel", "SEEDS/sel.txt", [["-C", "{W}", "register", PIC, "--landmarks", "{F}"]]),
        Seed(
            "obj",
            "SEEDS/tiny.obj",
            info + [["convert", "{F}", "{T}/x.vtk"], [*stage_sel[:-1], "--occlusion", "--shape", "{F}"]],
        ),
        Seed("vtk", "SEEDS/tiny.vtk", info + [["convert", "{F}", "{T}/x.obj"]]),
        Seed("spec", "SEEDS/spec.toml", [["simulate", "{F}", "{T}/world", "--max-memory", "1K"]]),
        Seed("real-sum", "SEEDS/N2395699394.SUM", info),
        Seed("real-lmk", "SEEDS/FA0115.LMK", info),
    ]


# ------------------------------------------------------------------------------------------------
# mutations


def _lines(data: bytes) -> list[bytes]:
    return data.split(b"\n")


def mutate(data: bytes, rng: random.Random, seed: Seed) -> tuple[bytes, list[str]]:
    """One to three mutations of ``data``; returns the mutant and the names of the mutations."""
    names = []
    for _ in range(rng.choice((1, 1, 1, 2, 3))):
        ops = MUTATIONS_TEXT if seed.text else MUTATIONS_BINARY
        name, op = rng.choice(ops)
        data = op(data, rng, seed)
        names.append(name)
    return data, names


def _pos(data: bytes, rng: random.Random, seed: Seed) -> int:
    if not data:
        return 0
    if seed.head_bias and rng.random() < 0.7:
        return rng.randrange(min(len(data), seed.head_bias))
    return rng.randrange(len(data))


def m_bitflip(d, rng, seed):
    if not d:
        return d
    i = _pos(d, rng, seed)
    return d[:i] + bytes([d[i] ^ (1 << rng.randrange(8))]) + d[i + 1 :]


def m_byte(d, rng, seed):
    if not d:
        return bytes([rng.choice(INTERESTING_BYTES)])
    i = _pos(d, rng, seed)
    return d[:i] + bytes([rng.choice(INTERESTING_BYTES)]) + d[i + 1 :]


def m_insert(d, rng, seed):
    i = _pos(d, rng, seed)
    chunk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 16)))
    return d[:i] + chunk + d[i:]


def m_delete(d, rng, seed):
    if not d:
        return d
    i = _pos(d, rng, seed)
    return d[:i] + d[i + rng.randrange(1, 64) :]


def m_truncate(d, rng, seed):
    return d[: _pos(d, rng, seed)]


def m_append(d, rng, seed):
    return d + rng.choice([b"\x00" * 17, b"END\n", b"garbage\n", os.urandom(33), b"\n\n\n", b"1 2 3\n"])


def m_int32(d, rng, seed):  # binary header fields: a 2- or 4-byte integer at an aligned offset
    if len(d) < 4:
        return d
    i = _pos(d, rng, seed) & ~1
    i = min(i, len(d) - 4)
    value = rng.choice([0, 1, 0xFFFF, 0x7FFF, 0x8000, 0xFFFFFFFF, 0x7FFFFFFF, 0x10000])
    size = rng.choice((2, 4))
    order = rng.choice(("big", "little"))
    return d[:i] + (value & (256**size - 1)).to_bytes(size, order) + d[i + size :]


def m_float(d, rng, seed):  # binary: an IEEE float (big-endian real*4/real*8) at an aligned offset
    import struct

    if len(d) < 8:
        return d
    i = min(_pos(d, rng, seed) & ~3, len(d) - 8)
    value = rng.choice([float("nan"), float("inf"), -float("inf"), 3.4e38, -3.4e38, 1e300, 0.0, 1e-45])
    fmt = rng.choice((">f", ">d", "<f", "<d"))
    try:
        b = struct.pack(fmt, value)
    except OverflowError:
        b = struct.pack(fmt[0] + "f", float("inf"))
    return d[:i] + b + d[i + len(b) :]


def m_number(d, rng, seed):
    found = list(NUMBER.finditer(d))
    if not found:
        return m_byte(d, rng, seed)
    m = rng.choice(found)
    return d[: m.start()] + rng.choice(INTERESTING_NUMBERS).encode() + d[m.end() :]


def m_overflow_exponent(d, rng, seed):
    found = [m for m in NUMBER.finditer(d) if b"." in m.group()]
    if not found:
        return m_number(d, rng, seed)
    m = rng.choice(found)
    return d[: m.start()] + rng.choice([b"1D+400", b"-1.0D+999", b"1.0E+309", b"2.5E-999"]) + d[m.end() :]


def m_garbage_after_number(d, rng, seed):
    found = list(NUMBER.finditer(d))
    if not found:
        return m_insert(d, rng, seed)
    m = rng.choice(found)
    return d[: m.end()] + rng.choice([b",:Ba7", b"x", b"..", b"-", b"e", b"D+", b"#1"]) + d[m.end() :]


def m_dup_line(d, rng, seed):
    ls = _lines(d)
    i = rng.randrange(len(ls))
    return b"\n".join(ls[: i + 1] + [ls[i]] + ls[i + 1 :])


def m_drop_line(d, rng, seed):
    ls = _lines(d)
    if len(ls) < 2:
        return d
    i = rng.randrange(len(ls))
    return b"\n".join(ls[:i] + ls[i + 1 :])


def m_swap_lines(d, rng, seed):
    ls = _lines(d)
    if len(ls) < 3:
        return d
    i = rng.randrange(min(len(ls) - 1, 60))
    ls[i], ls[i + 1] = ls[i + 1], ls[i]
    return b"\n".join(ls)


def m_bom(d, rng, seed):
    return b"\xef\xbb\xbf" + d


def m_crlf(d, rng, seed):
    return d.replace(b"\n", b"\r\n")


def m_long_line(d, rng, seed):
    i = _pos(d, rng, seed)
    return d[:i] + b"9" * rng.choice((80, 5001, 100_000)) + d[i:]


def m_deep_json(d, rng, seed):
    if d.lstrip().startswith(b"{"):
        depth = rng.choice((1000, 100_000))
        return d.rstrip()[:-1] + b', "deep": ' + b"[" * depth + b"]" * depth + b"}"
    return m_long_line(d, rng, seed)


def m_empty(d, rng, seed):
    return b""


def m_name(d, rng, seed):  # a hostile name where a name stands
    hostile = rng.choice([b"../../x", b"/tmp/x", b"..", b"a/b", b"\x00", b"X" * 70])
    for name in (PIC.encode(), LMK.encode(), b"B0", b"P0"):
        k = d.find(name)
        if k >= 0:
            return d[:k] + hostile + d[k + len(name) :]
    return m_insert(d, rng, seed)


MUTATIONS_TEXT = [
    ("bitflip", m_bitflip),
    ("byte", m_byte),
    ("insert", m_insert),
    ("delete", m_delete),
    ("truncate", m_truncate),
    ("append", m_append),
    ("number", m_number),
    ("number", m_number),
    ("number", m_number),
    ("overflow_exponent", m_overflow_exponent),
    ("garbage_after_number", m_garbage_after_number),
    ("dup_line", m_dup_line),
    ("drop_line", m_drop_line),
    ("swap_lines", m_swap_lines),
    ("bom", m_bom),
    ("crlf", m_crlf),
    ("long_line", m_long_line),
    ("deep_json", m_deep_json),
    ("empty", m_empty),
    ("name", m_name),
]
MUTATIONS_BINARY = [
    ("bitflip", m_bitflip),
    ("bitflip", m_bitflip),
    ("byte", m_byte),
    ("insert", m_insert),
    ("delete", m_delete),
    ("truncate", m_truncate),
    ("append", m_append),
    ("int32", m_int32),
    ("int32", m_int32),
    ("float", m_float),
    ("float", m_float),
    ("number", m_number),
    ("empty", m_empty),
]


# ------------------------------------------------------------------------------------------------
# running


class _Timeout(BaseException):
    pass


def _alarm(signum, frame):
    raise _Timeout()


@dataclass
class Outcome:
    seed: str
    mutations: list
    args: list
    klass: str
    exit_code: int
    stderr: str = ""
    elapsed: float = 0.0


@dataclass
class Report:
    mutants: int = 0
    runs: int = 0
    counts: Counter = field(default_factory=Counter)
    by_seed: dict = field(default_factory=dict)
    failures: list = field(default_factory=list)
    misreads: list = field(default_factory=list)
    elapsed_s: float = 0.0

    def merge(self, other: Report) -> None:
        self.mutants += other.mutants
        self.runs += other.runs
        self.counts.update(other.counts)
        for k, v in other.by_seed.items():
            self.by_seed.setdefault(k, Counter()).update(v)
        self.failures += other.failures
        self.misreads += other.misreads

    @property
    def n_failures(self) -> int:
        return sum(self.counts[k] for k in FAILURES)

    def summary(self) -> str:
        c = self.counts
        lines = [
            f"{self.mutants} mutants, {self.runs} command runs in {self.elapsed_s:.0f} s: "
            f"{c['ok']} accepted, {c['rejected']} rejected cleanly; "
            + ", ".join(f"{k} {c[k]}" for k in FAILURES),
            "silent-misread candidates (structural mutation accepted with a changed reading): "
            f"{len(self.misreads)}",
        ]
        for name in sorted(self.by_seed):
            s = self.by_seed[name]
            shown = " ".join(f"{k}={s[k]}" for k in ("ok", "rejected", *FAILURES) if s[k])
            lines.append(f"  {name:15s} {shown}")
        for f in self.failures[:40]:
            cmd = " ".join(f.args)[:120]
            lines.append(f"  FAIL {f.klass}: {f.seed} {f.mutations} {cmd} -> {f.stderr[:300]!r}")
        return "\n".join(lines)


def _structural(kind: str) -> tuple[str, ...]:
    """The mutations that should not leave a file of ``kind`` valid with another meaning: in lists,
    tables and meshes a line dropped, doubled or swapped is just another valid file."""
    if kind.startswith(("pictlist", "lmrklist", "table", "obj", "vtk")):
        return ("bom", "garbage_after_number", "overflow_exponent")
    return STRUCTURAL


def classify(exit_code: int, stderr: str, args) -> str:
    text = stderr
    if "Traceback" in text:
        return "traceback"
    if "MemoryError" in text or "Unable to allocate" in text or "array is too big" in text:
        return "blowup"
    if "internal error" in text:
        return "internal"
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    if any("Warning" in ln for ln in lines):
        return "noise"
    if exit_code == 0:
        return "ok"
    per_file = "validate" in args or "batch" in args  # one line per file / per failed picture
    if not per_file and (len(lines) != 1 or not lines[0].startswith("spctool: ")):
        return "noise"
    return "rejected"


def _run(cli, args, limit: float):
    from click.testing import CliRunner

    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, limit)
    t0 = time.perf_counter()
    try:
        res = CliRunner().invoke(cli, args, catch_exceptions=True)
        code, err = res.exit_code, res.stderr
        if res.exception is not None and not isinstance(res.exception, SystemExit):
            import traceback

            err += "Traceback\n" + "".join(traceback.format_exception(res.exception))
        out = res.stdout
    except _Timeout:
        code, err, out = -1, "hang", ""
    except MemoryError:
        code, err, out = -1, "MemoryError", ""
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    return code, err, out, time.perf_counter() - t0


def _limit_memory() -> None:
    try:
        import resource

        soft, hard = resource.getrlimit(resource.RLIMIT_AS)
        want = MEMORY_LIMIT if hard == resource.RLIM_INFINITY else min(MEMORY_LIMIT, hard)
        resource.setrlimit(resource.RLIMIT_AS, (want, hard))
    except (ImportError, ValueError, OSError):  # pragma: no cover
        pass


def run_shard(args) -> Report:
    """Run mutants ``start, start + step, …`` below ``n`` of master seed ``master`` in a private
    scratch directory; returns their report."""
    master, start, step, n, time_limit = args
    import warnings

    warnings.simplefilter("default")  # what a user sees: warnings are printed, not raised
    from spctool.cli.main import cli

    report = Report()
    all_seeds = seeds()
    with tempfile.TemporaryDirectory(prefix="spcfuzz-") as tmp:
        tmp = Path(tmp)
        wd = build_scratch(tmp)
        originals = {s.rel: (wd / s.rel).read_bytes() for s in all_seeds}
        # warm up: every command once on the seeds (numba compiles its kernels, modules load), so
        # the time limit measures the mutant, not the first compilation
        for s in all_seeds:
            for cmd in s.commands:
                warm = tmp / "warm"
                argv = [
                    a.replace("{F}", str(wd / s.rel)).replace("{W}", str(wd)).replace("{T}", str(warm))
                    for a in cmd
                ]
                _run(cli, argv, 600.0)
                shutil.rmtree(tmp / "warm", ignore_errors=True)
        baseline: dict = {}
        for s in all_seeds:
            if ["info", "--json", "{F}"] in s.commands:
                code, _, out, _ = _run(cli, ["info", "--json", str(wd / s.rel)], time_limit)
                baseline[s.name] = out if code == 0 else None
        t0 = time.perf_counter()
        for k in range(start, n, step):
            rng = random.Random(f"{master}:{k}")
            seed = all_seeds[k % len(all_seeds)]
            target = wd / seed.rel
            mutant, names = mutate(originals[seed.rel], rng, seed)
            scratch = tmp / f"t{k}"
            scratch.mkdir()
            target.write_bytes(mutant)
            report.mutants += 1
            per_seed = report.by_seed.setdefault(seed.name, Counter())
            try:
                for cmd in seed.commands:
                    argv = [
                        a.replace("{F}", str(target)).replace("{W}", str(wd)).replace("{T}", str(scratch))
                        for a in cmd
                    ]
                    code, err, out, dt = _run(cli, argv, time_limit)
                    klass = "hang" if code == -1 and err == "hang" else classify(code, err, argv)
                    report.runs += 1
                    report.counts[klass] += 1
                    per_seed[klass] += 1
                    if klass in FAILURES:
                        report.failures.append(Outcome(seed.name, names, argv, klass, code, err.strip(), dt))
                    if (
                        klass == "ok"
                        and cmd == ["info", "--json", "{F}"]
                        and set(names) & set(_structural(seed.name))
                        and baseline.get(seed.name) is not None
                        and out != baseline[seed.name]
                    ):
                        report.misreads.append(Outcome(seed.name, names, argv, "misread", code, "", dt))
            finally:
                target.write_bytes(originals[seed.rel])
                shutil.rmtree(scratch, ignore_errors=True)
                for extra in (wd / "SUMFILES").glob("*.bak*"):
                    extra.unlink()
        report.elapsed_s = time.perf_counter() - t0
    return report


def run(n: int, workers: int = 2, master: int = 19, time_limit: float = TIME_LIMIT_S) -> Report:
    """Run ``n`` mutants on ``workers`` processes (each with an address-space limit)."""
    t0 = time.perf_counter()
    shards = [(master, w, workers, n, time_limit) for w in range(workers)]
    if workers == 1:
        _limit_memory()
        reports = [run_shard(shards[0])]
    else:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(workers, initializer=_limit_memory) as pool:
            reports = pool.map(run_shard, shards)
    total = Report()
    for r in reports:
        total.merge(r)
    total.elapsed_s = time.perf_counter() - t0
    return total


# ------------------------------------------------------------------------------------------------
# the silent-misread classes of issue #41, each attacked directly


#: the classes: a 16-bit DAT cut short, a FITS photo with bytes inserted or removed, a landmark table
#: (text or JSON) with a row given twice
MISREAD_CLASSES = ("dat-cut", "fits-shifted", "table-dup-row", "table-json-dup-row")


def misread_classes(n: int, master: int = 41) -> dict[str, tuple[int, int]]:
    """For each of :data:`MISREAD_CLASSES`, ``n`` seeded mutants read in this process: (mutants,
    accepted with a reading other than the seed's).  Every mutant must be refused (or read the same)."""
    import numpy as np

    from spctool.errors import SpcError
    from spctool.formats.photo import read_dat, read_photo
    from spctool.formats.table import LandmarkTable, read_table

    rng = random.Random(f"{master}:misread")
    out: dict[str, tuple[int, int]] = {}
    dat = (DEMO / "IMAGEFILES" / f"{PIC}.DAT").read_bytes()
    side = 768  # the demo photo: 768 x 768, 16-bit
    fits_path = DEMO / "IMAGEFILES" / "P000000003A1.FITS"
    fits = fits_path.read_bytes()
    fits_data = read_photo(fits_path).data
    names = sorted(p.stem for p in (DEMO / "LMKFILES").glob("*.LMK"))
    rows = [f"{n} {100 + 7 * k:.2f} {200 + 3 * k:.2f}" for k, n in enumerate(names)]

    def accepted(path, reader, same) -> bool:
        try:
            got = reader(path)
        except SpcError:
            return False
        return not same(got)

    with tempfile.TemporaryDirectory(prefix="spcmisread-") as tmp:
        path = Path(tmp) / "m"
        bad = 0
        for k in range(n):  # a cut anywhere from 30 % to just before the last line (then SPC pads it)
            cut = len(dat) // 2 if k == 0 else int(len(dat) * rng.uniform(0.3, 1 - 1.0 / side))
            path.write_bytes(dat[:cut])
            bad += accepted(path, lambda p: read_dat(p, side, side), lambda got: False)
        out["dat-cut"] = (n, bad)
        bad = 0
        for _ in range(n):
            pos = rng.randrange(len(fits) + 1)
            count = rng.choice([1, 2, 7, 80, 100, 2879, 2881])
            if rng.random() < 0.5:
                data = fits[:pos] + bytes(rng.randrange(256) for _ in range(count)) + fits[pos:]
            else:
                data = fits[:pos] + fits[pos + count :]
            path = Path(tmp) / "m.fits"
            path.write_bytes(data)
            bad += accepted(
                path,
                read_photo,
                lambda got: got.data.shape == fits_data.shape and np.array_equal(got.data, fits_data),
            )
        out["fits-shifted"] = (n, bad)
        for label, as_json in (("table-dup-row", False), ("table-json-dup-row", True)):
            bad = 0
            for _ in range(n):
                body = list(rows)
                body.insert(rng.randrange(len(body) + 1), body[rng.randrange(len(body))])
                if as_json:
                    parts = [r.split() for r in body]
                    table = LandmarkTable.from_rows(
                        [{"name": a, "sample": float(b), "line": float(c)} for a, b, c in parts]
                    )
                    text = table.to_json()
                else:
                    text = "name sample line\n" + "\n".join(body) + "\n"
                path = Path(tmp) / ("m.json" if as_json else "m.txt")
                path.write_text(text)
                bad += accepted(path, read_table, lambda got: False)
            out[label] = (n, bad)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mutants", type=int, default=2000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=19)
    ap.add_argument("--time-limit", type=float, default=TIME_LIMIT_S)
    ap.add_argument("--json", dest="json_out", default=None, help="write the failures and candidates here")
    a = ap.parse_args(argv)
    report = run(a.mutants, a.workers, a.seed, a.time_limit)
    print(report.summary())
    if a.json_out:
        doc = {
            "mutants": report.mutants,
            "runs": report.runs,
            "counts": dict(report.counts),
            "elapsed_s": report.elapsed_s,
            "failures": [vars(f) for f in report.failures],
            "misreads": [vars(f) for f in report.misreads],
        }
        Path(a.json_out).write_text(json.dumps(doc, indent=1, default=str))
    return 1 if report.n_failures else 0


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main())
