"""Batch speed (spctool.batch): parallel speed-up and the per-picture cost of the Dask path.

Data: the demo working directory (``spctool.sim.demo``: 4 pictures of 768², 12 maplets, ICQ shape with
the occlusion test, OWEN distortion); when it is not installed yet, the small world of
``tests/batch_world.py`` (4 pictures, 9 maplets, no shape).  The "large" batches repeat those pictures
under new names (SUM copies with the new name, the same photo bytes), so every picture is a complete,
independent lithos-select → register (AUTOREGISTER) → solve-pose run with its outputs written.

* ``batch demo 2 workers vs 1`` — end-to-end wall time of ``run_batch`` (as ``spctool batch`` runs it:
  a fresh Python process, spctool imported, everything else — shared data, numba caches, worker
  start-up — inside the timing) with ``jobs=1`` divided by the time with ``jobs=2``.  Target ≥ 1.8×.
  Four pictures of ~0.1 s cannot show it: spawning and warming a worker (import, numba start, shape
  hierarchy) costs more than the whole batch, so the same figure is measured on a large batch too:
* ``batch 2 workers vs 1 (N pictures, end to end)`` — the same measurement on N repeated pictures;
* ``batch 2 workers vs 1 (throughput)`` — pictures per second once the workers run (from the first to
  the last picture finished), the figure that matters for thousands of pictures;
* ``batch dask per-picture overhead`` — a LocalCluster on loopback with one single-threaded worker
  *process* (warmed by a first batch), ``run_batch(scheduler=address)`` (client connection included)
  minus the same batch in this warm process, divided by the number of pictures.  Target ≤ 50 ms.

Best of a few repeats.  On a 2-core machine shared with other work the speed-ups are lower bounds.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

REPEATS = 3
LARGE_N = 160  # pictures of the large end-to-end batch
THROUGHPUT_N = 64
DASK_N = 48


def _demo(dest: Path) -> tuple[Path, str]:
    """A writable working directory: the demo if installed, else tests/batch_world.py."""
    try:
        from spctool.sim.demo import copy_demo

        return copy_demo(dest), "demo"
    except Exception:  # noqa: BLE001 - the demo data are not generated yet
        pass
    fixture = HERE.parent / "fixtures" / "demo"
    if (fixture / "PICTLIST.TXT").is_file():
        shutil.copytree(fixture, dest)
        return dest, "demo"
    from batch_world import make_world

    make_world(dest, n_pictures=4, n_landmarks=9, npx=200)
    return dest, "tests/batch_world (demo not installed)"


def _replicate(wd: Path, n: int) -> list[str]:
    """n pictures cycling over the working directory's pictures, under new 12-character names."""
    from spctool.formats.lists import PictureList, PictureListEntry, write_pictlist
    from spctool.formats.workdir import WorkDir

    w = WorkDir(wd)
    base = w.picture_names()
    names = []
    for k in range(n):
        src = base[k % len(base)]
        name = f"R{k:07d}{src[-4:]}"[:12] if len(src) >= 4 else f"R{k:011d}"
        text = w.sum_path(src).read_text(encoding="latin-1")
        first, rest = text.split("\n", 1)
        (wd / "SUMFILES" / f"{name}.SUM").write_text(
            first.replace(src, name, 1) + "\n" + rest, encoding="latin-1"
        )
        photo = w.photo_path(src)
        target = photo.with_name(name + photo.suffix)
        if not target.exists():
            os.link(photo, target)
        names.append(name)
    write_pictlist(wd / "LARGE.TXT", PictureList([PictureListEntry(x) for x in names]))
    return names


_CHILD = """
import json, sys, time
from spctool.batch import batch_pictures, run_batch
wd, out, jobs, plist = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4] or None
names = batch_pictures(wd, plist)
t = time.perf_counter()
r = run_batch(wd, names, out_dir=out, jobs=jobs, force=True)
print(json.dumps({"seconds": time.perf_counter() - t, "failed": len(r.failed), "n": len(r.pictures)}))
"""


def _cold_run(wd: Path, out: Path, jobs: int, plist: str = "") -> float:
    env = dict(os.environ, NUMBA_NUM_THREADS=str(os.cpu_count() or 1))
    res = subprocess.run(
        [sys.executable, "-c", _CHILD, str(wd), str(out), str(jobs), plist],
        capture_output=True,
        text=True,
        env=env,
        timeout=1800,
        check=True,
    )
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    if doc["failed"]:
        raise RuntimeError(f"{doc['failed']} pictures failed in the benchmark batch")
    return doc["seconds"]


def _speedup(wd: Path, plist: str = "") -> tuple[float, float, float]:
    t1 = min(_cold_run(wd, wd.parent / "o1", 1, plist) for _ in range(REPEATS))
    t2 = min(_cold_run(wd, wd.parent / "o2", 2, plist) for _ in range(REPEATS))
    return t1 / t2, t1, t2


def bench_demo_speedup():
    with tempfile.TemporaryDirectory() as tmp:
        wd, what = _demo(Path(tmp) / "wd")
        s, t1, t2 = _speedup(wd)
    print(f"    {what}: jobs=1 {t1:.2f} s, jobs=2 {t2:.2f} s", file=sys.stderr)
    return s, "x", s >= 1.8


def bench_large_speedup():
    with tempfile.TemporaryDirectory() as tmp:
        wd, what = _demo(Path(tmp) / "wd")
        _replicate(wd, LARGE_N)
        s, t1, t2 = _speedup(wd, str(wd / "LARGE.TXT"))
    print(f"    {LARGE_N} pictures of {what}: jobs=1 {t1:.2f} s, jobs=2 {t2:.2f} s", file=sys.stderr)
    return s, "x", s >= 1.8


def _throughput(wd, names, jobs) -> float:
    from spctool.batch import run_batch

    stamps = []
    run_batch(
        wd,
        names,
        out_dir=wd.parent / f"t{jobs}",
        jobs=jobs,
        force=True,
        on_result=lambda s: stamps.append(time.perf_counter()),
    )
    stamps.sort()
    return (len(stamps) - 1) / (stamps[-1] - stamps[0])


def bench_throughput_speedup():
    from spctool.batch import batch_pictures, run_batch

    with tempfile.TemporaryDirectory() as tmp:
        wd, what = _demo(Path(tmp) / "wd")
        _replicate(wd, THROUGHPUT_N)
        names = batch_pictures(wd, wd / "LARGE.TXT")
        run_batch(wd, names[:2], out_dir=wd.parent / "warm", jobs=1)  # warm this process (jobs=1 runs here)
        r1 = max(_throughput(wd, names, 1) for _ in range(REPEATS))
        r2 = max(_throughput(wd, names, 2) for _ in range(REPEATS))
    print(
        f"    {THROUGHPUT_N} pictures of {what}: {r1:.1f} / s with 1 worker, {r2:.1f} / s with 2",
        file=sys.stderr,
    )
    return r2 / r1, "x", r2 / r1 >= 1.8


def bench_dask_overhead():
    try:
        from distributed import LocalCluster
    except ImportError:
        return float("nan"), "ms", False
    from spctool.batch import batch_pictures, run_batch

    with tempfile.TemporaryDirectory() as tmp:
        wd, what = _demo(Path(tmp) / "wd")
        _replicate(wd, DASK_N)
        names = batch_pictures(wd, wd / "LARGE.TXT")
        with LocalCluster(
            n_workers=1,
            threads_per_worker=1,
            processes=True,
            protocol="tcp",
            host="127.0.0.1",
            scheduler_port=0,
            dashboard_address=None,
        ) as cluster:
            address = cluster.scheduler_address
            run_batch(wd, names[:4], out_dir=wd.parent / "warm", scheduler=address)  # warm the worker
            best = float("inf")
            for _ in range(REPEATS):
                t = time.perf_counter()
                r = run_batch(wd, names, out_dir=wd.parent / "dask", scheduler=address, force=True)
                wall = time.perf_counter() - t
                assert not r.failed
                # the one single-threaded worker ran the pictures one after another: whatever the wall
                # time has on top of the work it timed (navigate + write) is the Dask path's cost
                work = sum(p.timings["total_s"] + p.timings["write_s"] for p in r.pictures)
                best = min(best, (wall - work) / len(names))
    ms = best * 1e3
    print(f"    {DASK_N} pictures of {what}, one worker process; client connection included", file=sys.stderr)
    return ms, "ms", ms <= 50.0


BENCHMARKS = [
    ("batch demo 2 workers vs 1", ">= 1.8x", bench_demo_speedup),
    (f"batch {LARGE_N} pictures 2 workers vs 1", ">= 1.8x (end to end)", bench_large_speedup),
    ("batch 2 workers vs 1 (throughput)", ">= 1.8x", bench_throughput_speedup),
    ("batch dask per-picture overhead", "<= 50 ms", bench_dask_overhead),
]


if __name__ == "__main__":  # pragma: no cover
    for name, target, fn in BENCHMARKS:
        value, unit, ok = fn()
        print(f"{name:40s} {value:8.3f} {unit:3s} target {target}  {'ok' if ok else 'MISSED'}")
