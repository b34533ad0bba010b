"""Benchmarks for spctool.geometry.shape: BVH build and ray throughput.

* q = 512 ICQ shape (1 572 864 bilinear cells): an ellipsoid of 0.30 × 0.25 × 0.20 km with a few
  metres of terrain noise, generated in memory on the ``spc-formats.md`` §5.2 cube-sphere grid.
  Targets from the geometry-core issue: face-quadtree build ≤ 5 s, ≥ 1 M first-hit line-of-sight
  queries per second (rays from a camera 1.7 km away toward random surface points; nearly all hit).
* Bennu49k triangle plate model (``fixtures/real/bennu-shapes/Bennu49k.obj``): 1024 × 1024 pinhole
  rays from 3.9 km, ≈ 78 % hitting, as in ``peers.md`` §6.5 (Embree 1.8–2.1 M rays/s there).

Timings exclude numba compilation (every kernel is warmed up first) and are the best of a few repeats.
"""

from __future__ import annotations

import time
from functools import lru_cache
from pathlib import Path

import numpy as np

from spctool.geometry.shape import PatchShape, TriangleShape, embree_available

ROOT = Path(__file__).resolve().parent.parent
BENNU_49K = ROOT / "fixtures" / "real" / "bennu-shapes" / "Bennu49k.obj"
Q = 512
N_RAYS = 2_000_000
REPEATS = 3

_FACES = [
    lambda a, b, one: (a, -b, one),
    lambda a, b, one: (a, -one, -b),
    lambda a, b, one: (-one, -a, -b),
    lambda a, b, one: (-a, one, -b),
    lambda a, b, one: (one, a, -b),
    lambda a, b, one: (a, b, -one),
]


def terrain_ellipsoid(q: int, axes=(0.30, 0.25, 0.20)) -> np.ndarray:
    """(6, q+1, q+1, 3) ICQ vertices: ellipsoid × (1 + smooth noise of the direction, ~±1.3 %)."""
    idx = np.arange(q + 1)
    a = np.broadcast_to(-1.0 + 2.0 * idx[None, :] / q, (q + 1, q + 1))
    b = np.broadcast_to(-1.0 + 2.0 * idx[:, None] / q, (q + 1, q + 1))
    one = np.ones((q + 1, q + 1))
    p = np.stack([np.stack(fn(a, b, one), axis=-1) for fn in _FACES])
    u = p / np.linalg.norm(p, axis=-1, keepdims=True)
    noise = (0.01 * np.sin(23 * u[..., 0] + 1) * np.sin(17 * u[..., 1] + 2) * np.sin(19 * u[..., 2] + 0.5)
             + 0.003 * np.sin(91 * u[..., 0] + 41 * u[..., 1] + 67 * u[..., 2]))
    r = 1.0 / np.sqrt(np.sum((u / np.asarray(axes)) ** 2, axis=-1))
    return u * (r * (1.0 + noise))[..., None]


def _best(fn, repeats=REPEATS):
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


@lru_cache(maxsize=1)
def _icq():
    PatchShape(terrain_ellipsoid(4))  # compile / load the numba cache outside the timing
    verts = terrain_ellipsoid(Q)
    shape = PatchShape(verts)
    rng = np.random.default_rng(2024)
    k = rng.integers(0, shape.n_cells, N_RAYS)
    targets = shape.surface_point(k, rng.random(N_RAYS), rng.random(N_RAYS))
    camera = np.array([1.5, 0.7, 0.4])
    directions = targets - camera
    shape.first_hit(camera, directions[:10_000])  # warm up both kernels
    shape.any_hit(camera, directions[:10_000])
    return verts, shape, camera, directions


def bench_icq_build():
    verts, *_ = _icq()
    dt = _best(lambda: PatchShape(verts))
    return dt, "s", dt <= 5.0


def bench_icq_first_hit():
    _, shape, camera, directions = _icq()
    hits = []
    dt = _best(lambda: hits.append(shape.first_hit(camera, directions).hit.mean()))
    if min(hits) < 0.99:
        raise AssertionError(f"expected ~all rays to hit, got {min(hits):.3f}")
    rate = N_RAYS / dt
    return rate, "rays/s", rate >= 1e6


def bench_icq_any_hit():
    _, shape, camera, directions = _icq()
    dt = _best(lambda: shape.any_hit(camera, directions))
    return N_RAYS / dt, "rays/s", True


def _read_obj(path):
    v, f = [], []
    with open(path, encoding="latin-1") as fh:
        for line in fh:
            if line.startswith("v "):
                v.append(line.split()[1:4])
            elif line.startswith("f "):
                f.append(line.split()[1:4])
    return np.array(v, dtype=float), np.array(f, dtype=np.int64) - 1


@lru_cache(maxsize=1)
def _bennu_rays():
    v, f = _read_obj(BENNU_49K)
    n = 1024
    camera = np.array([3.9, 0.0, 0.0])
    half = 0.0634  # tan of the half field of view: the body fills ≈ 78 % of the frame
    s = np.linspace(-half, half, n)
    sy, sz = np.meshgrid(s, s)
    d = np.stack([-np.ones(n * n), sy.ravel(), sz.ravel()], axis=1)
    return v, f, camera, d


def _bench_triangles(backend):
    v, f, camera, d = _bennu_rays()
    shape = TriangleShape(v, f, backend=backend)
    res = shape.first_hit(camera, d[:10_000])  # warm up
    frac = []
    dt = _best(lambda: frac.append(shape.first_hit(camera, d).hit.mean()))
    if not 0.7 < frac[0] < 0.85:
        raise AssertionError(f"expected ≈ 78 % of the rays to hit, got {frac[0]:.3f}")
    del res
    return len(d) / dt, "rays/s", True


def bench_bennu_numba():
    return _bench_triangles("numba")


def bench_bennu_embree():
    return _bench_triangles("embree")


BENCHMARKS = [
    ("shape: q=512 ICQ patch BVH build (1.57 M cells)", "<= 5 s", bench_icq_build),
    ("shape: q=512 ICQ first-hit line-of-sight queries", ">= 1e6 rays/s", bench_icq_first_hit),
    ("shape: q=512 ICQ any-hit (occlusion) queries", "report", bench_icq_any_hit),
    ("shape: Bennu49k triangles first-hit, numba BVH", "report (Embree 1.8-2.1e6 in peers §6.5)",
     bench_bennu_numba),
]
if embree_available():
    BENCHMARKS.append(("shape: Bennu49k triangles first-hit, Embree (+ float64 refine)", "report",
                       bench_bennu_embree))
