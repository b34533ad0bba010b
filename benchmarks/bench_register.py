"""Correlation and registration speed (spctool.stages.correlate / register, spc-algorithms.md §7–§9).

* ``correlate 99x99 11x11`` — one :func:`spctool.stages.correlate.correlate` of a 99×99 extracted image
  against a 99×99 prediction at spacing 1 (121 masked Pearson sums, sub-pixel peak), both taken from the
  rendered S16-like scene of ``tests/register_scene.py`` with the extract filter's shadow cells and the
  prediction's dark cells masked.  Target ≤ 0.5 ms.
* ``register 99x99 S16 schedule`` — one complete :func:`spctool.stages.register.register` of one 99×99
  maplet with the S16 schedule (prediction, 10 extractions at L = 10 … 1, 10 correlations, peak checks),
  from an a-priori pointing error of (5, −3) px.  Target ≤ 10 ms on one core; peers.md §6.4: GIANT's
  surface-feature navigation spends ≈ 70 ms per feature per pass (rendering + correlation).

Best of several repeats (wall clock, warm numba caches).
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import numpy as np  # noqa: E402
import register_scene as rs  # noqa: E402

from spctool.stages.correlate import correlate  # noqa: E402
from spctool.stages.extract import extract  # noqa: E402
from spctool.stages.predict import predict  # noqa: E402
from spctool.stages.register import RegisterOptions, register  # noqa: E402

_SCENE = None


def _scene():
    global _SCENE
    if _SCENE is None:
        _SCENE = rs.scene()
    return _SCENE


def _best(fn, repeats, inner=1):
    fn()
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        for _ in range(inner):
            fn()
        best = min(best, (time.perf_counter() - t) / inner)
    return best


def bench_correlate():
    sc = _scene()
    cam = rs.pointing_error(sc.camera, 1.3, -0.8)
    ext = extract(sc.photo, sc.maplet, cam, sc.sun, sc.thresholds)
    pred = predict(sc.maplet, cam.position, sc.sun)
    res = correlate(ext.image, pred.image, extracted_valid=ext.valid, predicted_valid=pred.lit)
    assert res.ok and ext.image.shape == (99, 99)
    t = _best(
        lambda: correlate(ext.image, pred.image, extracted_valid=ext.valid, predicted_valid=pred.lit),
        repeats=30,
        inner=20,
    )
    ms = t * 1e3
    return ms, "ms", ms <= 0.5


def bench_register_s16():
    sc = _scene()
    cam = rs.pointing_error(sc.camera, 5.0, -3.0)
    opts = RegisterOptions()

    def run():
        return register(sc.photo, cam, sc.sun, [sc.maplet], sc.thresholds, opts)

    r = run()
    assert r.status == ["ok"] and r.iterations[0] == 10
    assert np.all(np.abs(r.measured[0] - sc.truth_pixel) < 0.05)
    ms = _best(run, repeats=20) * 1e3
    return ms, "ms", ms <= 10.0


BENCHMARKS = [
    ("correlate 99x99 11x11", "<= 0.5 ms", bench_correlate),
    ("register 99x99 S16 schedule", "<= 10 ms (GIANT SFN ~70 ms/feature/pass)", bench_register_s16),
]


if __name__ == "__main__":  # pragma: no cover
    for name, target, fn in BENCHMARKS:
        value, unit, ok = fn()
        print(f"{name:32s} {value:8.3f} {unit:3s} target {target}  {'ok' if ok else 'MISSED'}")
