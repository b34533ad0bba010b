"""Benchmarks of spctool.geometry.heightfield on a 99x99 maplet (q = 49).

Budget context: predict + extract + filter for one 99x99 maplet should take <= 3 ms on one core, so the
height-grid kernels (slopes, normals, the visibility march) must be a fraction of that.  The terrain is a
synthetic boulder field on gentle undulations (relief of a few cells, like S16's 1 cm maplets with
rocks), identical on every run.  Each function times only the measured call (best of several repeats,
after a warm-up that also triggers numba compilation).
"""

from __future__ import annotations

import math
import time

import numpy as np

from spctool.geometry import heightfield as hf

Q = 49


def _terrain(seed: int = 0):
    rng = np.random.default_rng(seed)
    x = np.arange(-Q, Q + 1, dtype=float)
    X, Y = np.meshgrid(x, x, indexing="ij")
    h = 1.5 * np.sin(X / 13.0) * np.cos(Y / 17.0) + rng.normal(0.0, 0.1, X.shape)
    for _ in range(60):
        a, b = rng.uniform(-Q, Q, 2)
        height, radius = rng.uniform(1.0, 5.0), rng.uniform(1.5, 4.0)
        h = np.maximum(h, height * np.exp(-((X - a) ** 2 + (Y - b) ** 2) / (2 * radius * radius)))
    valid = np.ones(h.shape, bool)
    valid[:3, :7] = False  # a few missing cells, as in real maplets
    return np.where(valid, h, 0.0), valid


def _best(fn, repeats: int = 50) -> float:
    fn()
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _frame():
    # ORIENT-style frame of the spc-formats.md §4.3 example
    ux = np.array([0.3580574370, 0.7161148740e-01, -0.9309493363])
    uy = np.array([-0.1961161351, 0.9805806757, 0.0])
    uz = np.array([0.9128709292, 0.1825741858, 0.3651483717])
    return ux, uy, uz


def _emission(emission_deg: float, azimuth_deg: float = 30.0):
    ux, uy, uz = _frame()
    e, a = math.radians(emission_deg), math.radians(azimuth_deg)
    return math.sin(e) * math.cos(a) * ux + math.sin(e) * math.sin(a) * uy + math.cos(e) * uz


def bench_slopes_normals():
    h, valid = _terrain()
    ux, uy, uz = _frame()

    def run():
        hx, hy, _ = hf.slopes(h, valid)
        hf.normals_body(hx, hy, ux, uy, uz)

    ms = _best(run) * 1e3
    return ms, "ms", ms <= 0.25


def _bench_march(emission_deg: float, target_ms: float):
    h, valid = _terrain()
    ux, uy, uz = _frame()
    e_hat = _emission(emission_deg)

    def bench():
        ms = _best(lambda: hf.visibility(h, valid, ux, uy, uz, e_hat)) * 1e3
        return ms, "ms", ms <= target_ms

    return bench


def bench_slopes_normals_march45():
    h, valid = _terrain()
    ux, uy, uz = _frame()
    e_hat = _emission(45.0)

    def run():
        hx, hy, _ = hf.slopes(h, valid)
        hf.normals_body(hx, hy, ux, uy, uz)
        hf.visibility(h, valid, ux, uy, uz, e_hat)

    ms = _best(run) * 1e3
    return ms, "ms", ms <= 1.0


def bench_intersect_rays():
    """Primary rays, 2x2 per cell over the maplet, from a camera 45 degrees off the normal."""
    h, valid = _terrain()
    s = (np.arange(2 * (2 * Q + 1)) + 0.25) / 2.0 - Q - 0.25
    gx, gy = np.meshgrid(s, s, indexing="ij")
    d = np.array([math.sin(math.radians(45.0)), 0.0, math.cos(math.radians(45.0))])
    origins = np.stack([gx, gy, np.full(gx.shape, 20.0)], axis=-1) + 30.0 * d  # 30 cells up-ray
    directions = -d
    ms = _best(lambda: hf.intersect_rays(h, valid, origins, directions), repeats=25) * 1e3
    return ms, f"ms / {gx.size} rays", ms <= 20.0


BENCHMARKS = [
    ("heightfield slopes + body normals, 99x99", "<= 0.25 ms", bench_slopes_normals),
    ("heightfield visibility march, 99x99, emission 45 deg", "<= 0.6 ms", _bench_march(45.0, 0.6)),
    ("heightfield visibility march, 99x99, emission 60 deg", "<= 1.0 ms", _bench_march(60.0, 1.0)),
    ("heightfield slopes + normals + march(45 deg), 99x99", "<= 1.0 ms", bench_slopes_normals_march45),
    (
        "heightfield intersect_rays, 2x2 rays per cell of 99x99 (Embree ~ 2 M rays/s)",
        "<= 20 ms",
        bench_intersect_rays,
    ),
]


if __name__ == "__main__":
    for name, target, fn in BENCHMARKS:
        value, unit, passed = fn()
        print(f"{name:75s} {value:8.3f} {unit:16s} target {target:12s} {'ok' if passed else 'MISSED'}")
