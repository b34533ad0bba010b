"""ICQ shape files at SPC's production size: read and write Q = 512 (1 579 014 vertex lines).

The shape is a triaxial ellipsoid (0.6 × 0.5 × 0.4 km, Bennu-sized) with terrain noise, built once
per run in a temporary directory; seam duplicates are made identical through the merge map
(spc-formats.md §5.2).  Timed: ``write_icq`` and ``read_icq`` in SPC style (3F12.5, as SHAPE.TXT) and in
the lossless "exact" style.  Target: each ≤ 3 s.  Best of 3, after an untimed first pass.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from spctool.formats import icq

Q = 512
TARGET_S = 3.0


def _shape(q: int = Q) -> icq.IcqShape:
    grid = icq.icq_cube_grid(q)
    unit = grid / np.sqrt(grid[..., 0] ** 2 + grid[..., 1] ** 2 + grid[..., 2] ** 2)[..., None]
    rng = np.random.default_rng(512)
    # terrain: a few random low-order waves plus fine noise, in km
    k = rng.normal(size=(8, 3)) * 6.0
    ph = rng.uniform(0, 2 * np.pi, 8)
    waves = np.sin(unit @ k.T + ph).sum(axis=-1) * 0.004
    noise = rng.normal(scale=0.0005, size=unit.shape[:-1])
    radius = 1.0 + waves + noise
    v = unit * np.array([0.6, 0.5, 0.4]) * radius[..., None]
    rep = icq.icq_merge_map(q)
    n = q + 1
    v = v.reshape(-1, 3)[rep].reshape(6, n, n, 3)
    return icq.IcqShape(q, v)


def _best(fn, repeats: int = 3) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _bench(style: str, what: str):
    def run():
        shape = _shape()
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "SHAPE.TXT"
            icq.write_icq(path, shape, style=style)  # untimed first pass: loads the numba kernels
            icq.read_icq(path)
            if what == "write":
                t = _best(lambda: icq.write_icq(path, shape, style=style))
            else:
                t = _best(lambda: icq.read_icq(path))
                back = icq.read_icq(path)
                tol = 0.0 if style == "exact" else 5.000001e-6
                assert np.max(np.abs(back.vertices - shape.vertices)) <= tol
        return t, "s", t <= TARGET_S

    return run


BENCHMARKS = [
    ("icq write q=512 (spc 3F12.5)", f"<= {TARGET_S:g} s", _bench("spc", "write")),
    ("icq read q=512 (spc 3F12.5)", f"<= {TARGET_S:g} s", _bench("spc", "read")),
    ("icq write q=512 (exact ES24.16)", f"<= {TARGET_S:g} s", _bench("exact", "write")),
    ("icq read q=512 (exact ES24.16)", f"<= {TARGET_S:g} s", _bench("exact", "read")),
]


if __name__ == "__main__":
    for name, target, fn in BENCHMARKS:
        value, unit, ok = fn()
        print(f"{name:36s} {value:8.3f} {unit}   target {target}   {'ok' if ok else 'FAIL'}")
