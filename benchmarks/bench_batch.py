"""Batch speed (spctool.batch): parallel speed-up and the per-picture cost of the Dask path.

Data: the demo working directory (``spctool.sim.demo``: 4 pictures of 768², 12 maplets, ICQ shape with
the occlusion test, OWEN distortion); when it is not installed yet, the small world of
``tests/batch_world.py`` (4 pictures, 9 maplets, no shape).  The "large" batches repeat those pictures
under new names (SUM copies with the new name, the same photo bytes), so every picture is a complete,
independent lithos-select → register (AUTOREGISTER) → solve-pose run with its outputs written.

* ``batch demo 2 workers vs 1`` — the issue's figure: the demo batch run by ``run_batch`` on warm
  workers — a :class:`spctool.batch.WorkerPool` of one and one of two worker processes, each worker
  warmed as it started (shared data loaded, one picture of each photo format navigated) and by
  ``WARM_UP`` batches, as a pipeline running batch after batch (or a Dask cluster) has them.  Time of
  the one-worker batch — the faster of the one-worker pool and the batch run in this process (no IPC
  at all) — divided by that of the two-worker batch; best of ``WARM_REPEATS`` interleaved runs
  (medians printed too).  Target ≥ 1.8×.  This 2-vCPU machine's own ceiling: two independent single-process
  batches side by side each run 5–10 % slower than one alone (about 1.8–1.9× together).
* ``batch demo --jobs 2 vs 1 (cold)`` — the same 4 pictures as ``spctool batch --jobs N`` runs them
  from a fresh Python process (spctool imported; worker start-up, numba's start, shared data inside
  the timing).  A cold process spends a fixed start-up ``S`` (≈ 0.9 s here: numba's first load, the
  shape hierarchy, astropy for the FITS picture) that every worker pays at the same time, so no number
  of workers can divide it: with ``T1`` the cold one-worker time and ``W`` the same batch warm,
  ``S = T1 − W`` and the best any 2-worker run can do is ``T1 / (S + W/2)`` (Amdahl).  Target: at least
  0.9 of that bound — what the parallel machinery itself loses (process start, scheduling, imbalance).
* ``batch N pictures 2 workers vs 1 (end to end, cold)`` — the cold measurement on N repeated
  pictures, where the start-up weighs less;
* ``batch 2 workers vs 1 (throughput)`` — pictures per second of a large batch on warm workers
  (``WorkerPool`` of one and of two, and this process; from the first to the last picture finished),
  the figure that matters for thousands of pictures: the median over interleaved rounds of each
  round's two-worker rate over its faster one-worker rate (best of each side printed too);
* ``batch dask per-picture overhead`` — a LocalCluster on loopback with one single-threaded worker
  *process* (warmed by a first batch), ``run_batch(scheduler=address)`` (client connection included)
  minus the same batch in this warm process, divided by the number of pictures.  Target ≤ 50 ms.

Best of a few repeats (the throughput line: the median of interleaved rounds' ratios).  On a 2-core
machine shared with other work the speed-ups are lower bounds.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

REPEATS = 3
WARM_UP = 3
WARM_REPEATS = 60
LARGE_N = 160  # pictures of the large end-to-end batch
THROUGHPUT_N = 64
THROUGHPUT_REPEATS = 6
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
cold = time.perf_counter() - t
warm = float("nan")
if jobs == 1 and len(sys.argv) > 5:  # the same batch again in this (now warm) process
    t = time.perf_counter()
    run_batch(wd, names, out_dir=out + "-warm", jobs=1, force=True)
    warm = time.perf_counter() - t
print(json.dumps({"seconds": cold, "warm": warm, "failed": len(r.failed), "n": len(r.pictures)}))
"""


def _cold_run(wd: Path, out: Path, jobs: int, plist: str = "", warm: bool = False) -> dict:
    env = dict(os.environ, NUMBA_NUM_THREADS=str(os.cpu_count() or 1))
    env.pop("SPCTOOL_START_METHOD", None)
    args = [sys.executable, "-c", _CHILD, str(wd), str(out), str(jobs), plist] + (["warm"] if warm else [])
    res = subprocess.run(args, capture_output=True, text=True, env=env, timeout=1800, check=True)
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    if doc["failed"]:
        raise RuntimeError(f"{doc['failed']} pictures failed in the benchmark batch")
    return doc


def _speedup(wd: Path, plist: str = "") -> tuple[float, float, float, float]:
    """(T1 / T2, T1, T2, W): cold one- and two-worker times (best of REPEATS, interleaved) and the
    one-worker batch run again warm in the same process."""
    one, two = [], []
    for _ in range(REPEATS):
        one.append(_cold_run(wd, wd.parent / "o1", 1, plist, warm=True))
        two.append(_cold_run(wd, wd.parent / "o2", 2, plist))
    t1 = min(d["seconds"] for d in one)
    t2 = min(d["seconds"] for d in two)
    w = min(d["warm"] for d in one)
    return t1 / t2, t1, t2, w


def bench_demo_speedup():
    from spctool.batch import WorkerPool, batch_pictures, run_batch

    with tempfile.TemporaryDirectory() as tmp:
        wd, what = _demo(Path(tmp) / "wd")
        names = batch_pictures(wd)
        times = {1: [], 2: []}
        with WorkerPool(1, warm=(wd, None)) as one, WorkerPool(2, warm=(wd, None)) as two:
            pools = ((1, one), (2, two))
            for _ in range(WARM_UP):  # let the workers' allocators and caches settle
                for n, pool in pools:
                    run_batch(wd, names, out_dir=wd.parent / f"w{n}", pool=pool, force=True)
            for _ in range(WARM_REPEATS):  # interleaved, so a slow spell of the machine hits both
                for n, pool in pools:
                    t = time.perf_counter()
                    r = run_batch(wd, names, out_dir=wd.parent / f"w{n}", pool=pool, force=True)
                    times[n].append(time.perf_counter() - t)
                    assert not r.failed and r.workers == n
        inproc = []
        for _ in range(WARM_UP + WARM_REPEATS // 2):  # for reference: one worker = this process
            t = time.perf_counter()
            run_batch(wd, names, out_dir=wd.parent / "w0", jobs=1, force=True)
            inproc.append(time.perf_counter() - t)
    # one worker: the faster of a one-worker pool and this process itself (no IPC at all)
    t1, t2 = min(min(times[1]), min(inproc)), min(times[2])
    med1, med2 = statistics.median(times[1]), statistics.median(times[2])
    print(
        f"    {what}, {len(names)} pictures, warm workers (WorkerPool): 1 worker {t1 * 1e3:.0f} ms, "
        f"2 workers {t2 * 1e3:.0f} ms, best of {WARM_REPEATS}; "
        f"medians {med1 * 1e3:.0f} / {med2 * 1e3:.0f} ms "
        f"({med1 / med2:.2f}x); one worker in this process {min(inproc) * 1e3:.0f} ms; the faster "
        f"one-worker time is the reference",
        file=sys.stderr,
    )
    return t1 / t2, "x", t1 / t2 >= 1.8


def _cluster(n: int):
    from distributed import LocalCluster

    return LocalCluster(
        n_workers=n,
        threads_per_worker=1,
        processes=True,
        protocol="tcp",
        host="127.0.0.1",
        scheduler_port=0,
        dashboard_address=None,
    )


def bench_demo_cold_speedup():
    with tempfile.TemporaryDirectory() as tmp:
        wd, what = _demo(Path(tmp) / "wd")
        s, t1, t2, w = _speedup(wd)
    startup = t1 - w
    bound = t1 / (startup + w / 2)
    print(
        f"    {what}: jobs=1 {t1:.2f} s, jobs=2 {t2:.2f} s; the same batch warm {w:.2f} s, so a fixed "
        f"start-up of {startup:.2f} s and an Amdahl bound of {bound:.2f}x; measured {s / bound:.0%} of it",
        file=sys.stderr,
    )
    return s, "x", s >= 0.9 * bound


def bench_large_speedup():
    with tempfile.TemporaryDirectory() as tmp:
        wd, what = _demo(Path(tmp) / "wd")
        _replicate(wd, LARGE_N)
        s, t1, t2, w = _speedup(wd, str(wd / "LARGE.TXT"))
    bound = t1 / ((t1 - w) + w / 2)
    print(
        f"    {LARGE_N} pictures of {what}: jobs=1 {t1:.2f} s, jobs=2 {t2:.2f} s "
        f"(warm {w:.2f} s; Amdahl bound {bound:.2f}x)",
        file=sys.stderr,
    )
    return s, "x", s >= 1.8


def _throughput(wd, names, pool) -> float:
    """Pictures per second from the first to the last finished (``pool`` None: in this process)."""
    from spctool.batch import run_batch

    stamps = []
    run_batch(
        wd,
        names,
        out_dir=wd.parent / f"t{pool.jobs if pool else 0}",
        pool=pool,
        force=True,
        on_result=lambda s: stamps.append(time.perf_counter()),
    )
    stamps.sort()
    return (len(stamps) - 1) / (stamps[-1] - stamps[0])


def bench_throughput_speedup():
    """Throughput of two warm workers over one, in rounds of three interleaved batches (a one-worker
    pool, a two-worker pool, this process): each round's ratio is the two-worker rate over the faster
    one-worker rate of the same round, and the verdict reads the median of the rounds' ratios — as
    the maplet-space two-worker lines do (``bench_register._maplet_split``), so that a calm spell of
    the machine, which a one-core batch meets more often than a two-core one, does not set one side
    of the ratio alone.  The best of each side is printed too."""
    from spctool.batch import WorkerPool, batch_pictures, run_batch

    with tempfile.TemporaryDirectory() as tmp:
        wd, what = _demo(Path(tmp) / "wd")
        _replicate(wd, THROUGHPUT_N)
        names = batch_pictures(wd, wd / "LARGE.TXT")
        rates = {0: [], 1: [], 2: []}
        run_batch(wd, names[:4], out_dir=wd.parent / "warm", jobs=1)  # warm this process
        with WorkerPool(1, warm=(wd, None)) as one, WorkerPool(2, warm=(wd, None)) as two:
            for _ in range(THROUGHPUT_REPEATS):  # interleaved: a slow spell of the machine hits all three
                for pool in (one, two, None):
                    rates[pool.jobs if pool else 0].append(_throughput(wd, names, pool))
    # one worker: the faster of a one-worker pool and this process itself (no IPC at all)
    ratios = [r2 / max(r1, r0) for r0, r1, r2 in zip(rates[0], rates[1], rates[2])]
    ratio = statistics.median(ratios)
    b1, b2 = max(max(rates[1]), max(rates[0])), max(rates[2])
    print(
        f"    {THROUGHPUT_N} pictures of {what}, warm workers (WorkerPool), {THROUGHPUT_REPEATS} rounds: "
        f"rounds' ratios {', '.join(f'{r:.2f}' for r in ratios)}; best {b1:.1f} / s with 1 worker "
        f"(pool {max(rates[1]):.1f}, this process {max(rates[0]):.1f}), {b2:.1f} / s with 2 "
        f"(best over best {b2 / b1:.2f}x); medians {statistics.median(rates[1]):.1f}, "
        f"{statistics.median(rates[0]):.1f} and {statistics.median(rates[2]):.1f} / s",
        file=sys.stderr,
    )
    return ratio, "x", ratio >= 1.8


def bench_dask_overhead():
    try:
        import distributed  # noqa: F401
    except ImportError:
        return float("nan"), "ms", False
    from spctool.batch import batch_pictures, run_batch

    with tempfile.TemporaryDirectory() as tmp:
        wd, what = _demo(Path(tmp) / "wd")
        _replicate(wd, DASK_N)
        names = batch_pictures(wd, wd / "LARGE.TXT")
        with _cluster(1) as cluster:
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
    ("batch demo 2 workers vs 1", ">= 1.8x (warm workers)", bench_demo_speedup),
    ("batch demo --jobs 2 vs 1 (cold)", ">= 0.9 x Amdahl bound", bench_demo_cold_speedup),
    (f"batch {LARGE_N} pictures 2 workers vs 1", ">= 1.8x (end to end, cold)", bench_large_speedup),
    ("batch 2 workers vs 1 (throughput)", ">= 1.8x", bench_throughput_speedup),
    ("batch dask per-picture overhead", "<= 50 ms", bench_dask_overhead),
]


if __name__ == "__main__":  # pragma: no cover
    for name, target, fn in BENCHMARKS:
        value, unit, ok = fn()
        print(f"{name:40s} {value:8.3f} {unit:3s} target {target}  {'ok' if ok else 'MISSED'}")
