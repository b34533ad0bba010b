"""Benchmarks of Stage B–E (spctool.stages.predict / extract) on one 99×99 maplet (q = 49).

Target: predict + extract + filter for one 99×99 maplet <= 3 ms on one core.  The scene follows S16
(spc-algorithms.md §12): 1 cm cells, the ARRM camera (2592 × 1944 px, f = 7.68 mm, 454.54 px/mm) at
50 m, emission 20°, incidence 50°, a terrain of gentle undulations with ~40 boulders (so the shadow
enhancement and the visibility march have work to do).  The photo is rendered once by the
independent ray-cast renderer of ``tests/appearance_scene.py`` into a crop around the landmark and
pasted into a full-size 16-bit frame.  The measured call computes the slopes once, extracts (BRT0
sampling, filter, statistics) and predicts (illumination, λ fit) — everything a registration step
needs per maplet and picture.  numba is limited to one thread; timings are the best of many repeats
after a warm-up (which also compiles the numba kernels).
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import appearance_scene as sc  # noqa: E402

from spctool.geometry import heightfield as hf  # noqa: E402
from spctool.stages.extract import ExtractOptions, extract  # noqa: E402
from spctool.stages.predict import PredictOptions, predict  # noqa: E402

Q = 49
_RNG = np.random.default_rng(5)
_BOULDERS = [(a, b, hgt, r) for a, b, hgt, r in zip(_RNG.uniform(-Q, Q, 40), _RNG.uniform(-Q, Q, 40),
                                                     _RNG.uniform(1.0, 4.0, 40), _RNG.uniform(1.5, 3.5, 40))]


def _terrain(x, y):
    """Undulations plus Gaussian boulders (heights in cells) with exact derivatives."""
    h = 1.5 * np.sin(x / 13.0) * np.cos(y / 17.0)
    hx = 1.5 / 13.0 * np.cos(x / 13.0) * np.cos(y / 17.0)
    hy = -1.5 / 17.0 * np.sin(x / 13.0) * np.sin(y / 17.0)
    for a, b, hgt, r in _BOULDERS:
        g = hgt * np.exp(-((x - a) ** 2 + (y - b) ** 2) / (2.0 * r * r))
        h = h + g
        hx = hx - g * (x - a) / (r * r)
        hy = hy - g * (y - b) / (r * r)
    return h, hx, hy


def _scene(kpx=454.54, emission_deg=20.0, sun_deg=50.0):
    m = sc.make_maplet(q=Q, scale=1e-5, v=(0.0, 0.0, 0.2), terrain_fn=_terrain)
    pos = m.v + 0.05 * sc.direction(m, emission_deg, 200.0)  # 50 m
    big = sc.look_at_camera(m.v, pos, mmfl=7.68, kpx=kpx, npx=2592, nln=1944)
    s0, l0 = (float(v) for v in big.project(m.v))
    px_per_cell = math.sqrt(abs(np.linalg.det(big.jacobian_maplet(m.v, m.ux, m.uy, m.scale))))
    w = int(2.2 * (2 * Q + 1) * px_per_cell) + 8
    c0 = (int(s0) - w // 2, int(l0) - w // 2)
    crop_cam = sc.look_at_camera(m.v, pos, mmfl=7.68, kpx=kpx, npx=w, nln=w,
                                 ctr=(big.ctr[0] - c0[0] + 1, big.ctr[1] - c0[1] + 1))
    sun = sc.direction(m, sun_deg, 60.0)
    crop = sc.render(crop_cam, m, sun, offset=0.0, terrain_fn=_terrain, cast_shadows=True)
    photo = np.zeros((1944, 2592), dtype=np.uint16)
    photo[c0[1] - 1:c0[1] - 1 + w, c0[0] - 1:c0[0] - 1 + w] = np.clip(np.rint(crop), 0, 65535)
    return m, big, sun, photo


def _best(fn, repeats: int = 60) -> float:
    fn()
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _bench(kpx: float, popts: PredictOptions | None = None, eopts: ExtractOptions | None = None,
           target_ms: float = 3.0):
    def bench():
        numba.set_num_threads(1)
        m, cam, sun, photo = _scene(kpx)
        thr = (1.0, 65535.0)

        def run():
            sl = hf.slopes(m.heights, m.valid)
            ex = extract(photo, m, cam, sun, thr, eopts, slopes=sl)
            return predict(m, cam.position, sun, popts, extracted=ex, slopes=sl), ex

        pr, ex = run()
        if not pr.correlation > 0.9:  # a wrong scene would time the wrong work
            raise RuntimeError(f"benchmark scene broken: zero-offset correlation {pr.correlation:.3f}")
        ms = _best(run) * 1e3
        return ms, f"ms (m={ex.subsample}, rho={pr.correlation:.3f})", ms <= target_ms

    return bench


BENCHMARKS = [
    ("appearance: predict + extract + filter, 99x99 maplet, S16 camera at 50 m (1.43 cm px, 1 cm cells)",
     "<= 3 ms", _bench(454.54)),
    ("appearance: same, cells larger than pixels (2.3 px per cell, 3x3 sub-samples)",
     "<= 3 ms", _bench(1500.0)),
    ("appearance: same as the first, cast shadows in prediction and filter",
     "<= 4 ms", _bench(454.54, PredictOptions(shadows="cast"), ExtractOptions(cast_shadow_trace=True), 4.0)),
]


if __name__ == "__main__":
    for name, target, fn in BENCHMARKS:
        value, unit, passed = fn()
        print(f"{name:100s} {value:8.3f} {unit:26s} target {target:8s} {'ok' if passed else 'MISSED'}")
