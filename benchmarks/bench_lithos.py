"""Benchmarks of ``spctool lithos`` (LITHOS "Find heights", :mod:`spctool.stages.find_heights`).

The scene is ``tests/heights_world.py``: a band-limited truth rendered (ray traced, cast shadows) from
true cameras, the maplet under test the truth smoothed (coarse start, uniform albedo), 2 cm cells.

* one outer iteration of a 99×99 maplet with 10 pictures on one core (issue #38: ≤ 0.5 s): the
  re-registration (one spacing-1 step with its converged stage) and re-extraction of the 10 pictures
  on the current heights, then one pass (λ, per-cell solve, integration) — best CPU time of 3 after
  a warm-up, every library on one thread;
* the per-cell solve and the integration of that maplet alone (the numerics, without the pictures);
* 100 maplets (49×49, 4 pictures each, the default outer loop to convergence) mapped over local
  worker processes on every core, as ``batch --lithos`` maps :func:`find_heights` over maplets (the
  scene sent to each worker once); the line states the CPU seconds a maplet took and the load.
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core for the single-maplet lines (the pool's workers too)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

_SCENES: dict = {}


def _scene(q: int, n: int):
    key = (q, n)
    if key not in _SCENES:
        from heights_world import make_scene

        _SCENES[key] = make_scene(n_pictures=n, q=q, npx=256 if q > 30 else 160)
    return _SCENES[key]


def _best(fn, repeats: int = 3) -> float:
    """Best CPU time of ``fn`` (process time: one thread, so the seconds one core spends, whatever
    else the machine runs meanwhile)."""
    fn()
    best = math.inf
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def bench_outer_iteration():
    from spctool.stages import find_heights as fh
    from spctool.stages import photoclinometry as pc
    from spctool.stages import slope_integration as si

    start, _, views = _scene(49, 10)
    opts = fh.FindHeightsOptions()
    wm = fh.WorkingMaplet.of(start)
    cond = si.conditioning_cells(wm.valid, opts.condition_fraction, 0)

    def one():
        pixels = np.array([v.pixel for v in views], dtype=float)
        ob = fh._observe(wm, views, pixels, np.zeros(len(views)), opts, True)
        pc.heights_pass(wm.heights, wm.albedo, wm.valid, ob.pictures, wm.heights, cond,
                        opts.condition_weight, opts.keep_plane, None, opts.solve)

    t = _best(one)
    return t, "s", t <= 0.5


def bench_numerics():
    from spctool.stages import find_heights as fh
    from spctool.stages import photoclinometry as pc
    from spctool.stages import slope_integration as si

    start, _, views = _scene(49, 10)
    opts = fh.FindHeightsOptions()
    wm = fh.WorkingMaplet.of(start)
    pixels = np.array([v.pixel for v in views], dtype=float)
    ob = fh._observe(wm, views, pixels, np.zeros(len(views)), opts, False)
    cond = si.conditioning_cells(wm.valid, opts.condition_fraction, 0)

    def one():
        pc.heights_pass(wm.heights, wm.albedo, wm.valid, ob.pictures, wm.heights, cond,
                        opts.condition_weight, opts.keep_plane, None, opts.solve)

    t = _best(one, 5)
    return t * 1e3, "ms", t <= 0.15


def bench_parallel_100():
    import concurrent.futures as cf
    import multiprocessing as mp

    from heights_world import init_worker, solve_ok, solve_seeded

    from spctool.workers import start_method

    start, _, views = _scene(24, 4)
    solve_ok((start, views, 0))  # warm-up (numba kernels compiled in this process; forked workers inherit)
    workers = os.cpu_count() or 1
    ctx = mp.get_context(start_method())
    t0 = time.perf_counter()
    with cf.ProcessPoolExecutor(workers, mp_context=ctx, initializer=init_worker,
                                initargs=(start, views)) as pool:
        out = list(pool.map(solve_seeded, range(100), chunksize=5))
    t = time.perf_counter() - t0
    ok = [o for o, _ in out]
    cpu = sum(c for _, c in out)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    return t, (f"s ({workers} workers, {sum(ok)} of 100 solved, {cpu / 100:.2f} s CPU a maplet, "
               f"load {load:.1f})"), all(ok) and t <= 60.0


BENCHMARKS = [
    ("lithos: one outer iteration, 99x99 maplet, 10 pictures (1 core)", "<= 0.5 s", bench_outer_iteration),
    ("lithos: one pass of the numerics, 99x99, 10 pictures (1 core)", "<= 150 ms", bench_numerics),
    ("lithos: 100 maplets 49x49 x 4 pictures to convergence, all cores", "<= 60 s", bench_parallel_100),
]
