"""Benchmark: reading many maplets (spctool.formats.maplet.read_maps).

10,000 q = 49 maplets (99×99 cells, 29,520 bytes each, ≈ 295 MB) are written once
into a temporary directory; only the reading is timed (best of 3).  Target ≤ 10 s.
The second figure also decodes every maplet's grids (float64 heights and albedo,
≈ 1.6 GB for 10,000 maplets), which ``read_maps`` otherwise defers to first use.
"""

from __future__ import annotations

import gc
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from spctool.formats.maplet import Maplet, format_map, read_maps

N_MAPS = 10_000
QSZ = 49
TARGET_S = 10.0


def _distinct_maplets(k: int) -> list[bytes]:
    rng = np.random.default_rng(2024)
    n = 2 * QSZ + 1
    out = []
    for _ in range(k):
        uz = rng.normal(size=3)
        uz /= np.linalg.norm(uz)
        uy = np.cross([0.0, 0.0, 1.0], uz)
        uy /= np.linalg.norm(uy)
        ux = np.cross(uy, uz)
        m = Maplet.new(
            0.0005, QSZ, uz * 2.0, ux, uy, uz,
            rng.normal(scale=3.0, size=(n, n)), rng.uniform(0.5, 1.5, (n, n)), rng.random((n, n)) > 0.05,
            sigma=(1e-3, 1e-3, 2e-3),
        )
        out.append(format_map(m))
    return out


def bench_read_maps(n_maps: int = N_MAPS, repeats: int = 3, decode: bool = False) -> tuple[float, str, bool]:
    """Best-of-``repeats`` seconds for ``read_maps`` of ``n_maps`` files; with ``decode`` the
    timed part also touches every maplet's heights, albedo and valid (decoded lazily)."""
    tmp = Path(tempfile.mkdtemp(prefix="spctool-bench-maps-"))
    try:
        blobs = _distinct_maplets(32)
        paths = []
        for i in range(n_maps):
            p = tmp / f"BM{i:04d}.MAP"
            p.write_bytes(blobs[i % len(blobs)])
            paths.append(p)
        best = float("inf")
        for _ in range(repeats):
            gc.collect()
            t0 = time.perf_counter()
            maps = read_maps(paths)
            if decode:
                for m in maps:
                    m.heights, m.albedo, m.valid  # noqa: B018 - force the lazy decode
            dt = time.perf_counter() - t0
            assert len(maps) == n_maps and maps[-1].size == 2 * QSZ + 1
            del maps
            best = min(best, dt)
        return best, "s", best <= TARGET_S
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def bench_read_maps_decoded() -> tuple[float, str, bool]:
    return bench_read_maps(decode=True)


BENCHMARKS = [
    ("read 10,000 q=49 maplets (read_maps)", "<= 10 s", bench_read_maps),
    ("read 10,000 q=49 maplets + decode every grid", "<= 10 s", bench_read_maps_decoded),
]


if __name__ == "__main__":
    for name, target, fn in BENCHMARKS:
        value, unit, ok = fn()
        print(f"{name}: {value:.3f} {unit} (target {target}) {'PASS' if ok else 'FAIL'}")
