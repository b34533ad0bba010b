"""Benchmark of Stage A (``lithos-select``): 10,000 candidate maplets against one picture with the
occlusion test on a q = 512 ICQ shape (1.57 M bilinear patches).

Target: <= 2 s for :func:`spctool.stages.select.select_maplets` once the shape is loaded; the shape's
hierarchy build and its (cached) largest diameter are timed separately and reported, not counted.
"""

from __future__ import annotations

import math
import time

import numpy as np

N_CANDIDATES = 10_000
Q = 512
TARGET_S = 2.0


def _bumpy_icq(q: int) -> np.ndarray:
    """(6, q+1, q+1, 3) ICQ vertices (spc-formats.md §5.2 faces): an elongated body (semi-axes 1.2, 0.8,
    0.6 km, like a small asteroid) with hills and a bowl."""
    t = -1.0 + 2.0 * np.arange(q + 1) / q
    a, b = np.meshgrid(t, t, indexing="xy")
    one = np.ones_like(a)
    faces = [(a, -b, one), (a, -one, -b), (-one, -a, -b), (-a, one, -b), (one, a, -b), (a, b, -one)]
    cube = np.stack([np.stack(f, axis=-1) for f in faces])
    d = cube / np.linalg.norm(cube, axis=-1, keepdims=True)
    r = 1.0 + 0.08 * np.sin(5 * d[..., 0]) * np.cos(4 * d[..., 1]) + 0.05 * np.sin(7 * d[..., 2])
    theta = np.arccos(np.clip(d[..., 2], -1, 1))
    r -= 0.3 * np.where(theta < 0.5, np.cos(np.pi / 2 * theta / 0.5) ** 2, 0.0)
    return d * r[..., None] * np.array([1.2, 0.8, 0.6])


def _scene(verts):
    from spctool.geometry.camera import Camera
    from spctool.geometry.frames import orient_frame

    rng = np.random.default_rng(1)
    cam_pos = np.array([3.0, 1.0, 2.0])
    # candidate landmarks: shape vertices (on the surface) facing the camera, so that nearly every candidate
    # reaches the occlusion test; normals from neighbouring vertices
    m = 6 * N_CANDIDATES
    f = rng.integers(0, 6, m)
    j = rng.integers(1, Q, m)
    i = rng.integers(1, Q, m)
    du = verts[f, j, i + 1] - verts[f, j, i - 1]
    dv = verts[f, j + 1, i] - verts[f, j - 1, i]
    normals = -np.cross(du, dv)  # ∂P/∂I × ∂P/∂J points inward (spc-formats.md §5.2)
    centres = verts[f, j, i]
    los = centres - cam_pos
    cos_e = -np.einsum("ij,ij->i", los, normals) / (
        np.linalg.norm(los, axis=1) * np.linalg.norm(normals, axis=1)
    )
    facing = cos_e > 0.2
    keep = np.flatnonzero(facing)[:N_CANDIDATES]
    centres, normals = centres[keep], normals[keep]
    ux, uy, uz = orient_frame(normals)
    scale = np.full(N_CANDIDATES, 0.002)
    qsz = np.full(N_CANDIDATES, 20)
    cz = -cam_pos / np.linalg.norm(cam_pos)
    cx = np.cross([0, 0, 1.0], cz)
    cx /= np.linalg.norm(cx)
    cy = np.cross(cz, cx)
    cam = Camera(
        mmfl=100.0,
        ctr=(512.5, 512.5),
        kmatrix=[[10.0, 0, 0], [0, 10.0, 0]],
        rotation=np.vstack([cx, cy, cz]),
        scobj=-cam_pos,
        npx=1024,
        nln=1024,
    )
    sun = cam_pos + np.array([0.5, -0.5, 0.3])  # near the camera: most facing candidates are lit
    return cam, sun, centres, ux, uy, uz, scale, qsz


def bench_select_10k_q512():
    from spctool.geometry.shape import PatchShape
    from spctool.stages.select import SelectOptions, select_maplets

    verts = _bumpy_icq(Q)
    t0 = time.perf_counter()
    shape = PatchShape(verts)
    build = time.perf_counter() - t0
    t0 = time.perf_counter()
    _ = shape.max_diameter  # cached statistic of the loaded shape (the occlusion tolerance is 1 % of it)
    dmax_time = time.perf_counter() - t0
    cam, sun, centres, ux, uy, uz, scale, qsz = _scene(verts)
    names = [f"L{k:05d}" for k in range(N_CANDIDATES)]
    opts = SelectOptions(numlm=10**9)  # no resolution screen: every visible candidate is kept
    # warm-up (numba kernels from cache / compile), then best of 3
    select_maplets(
        cam, sun, centres[:50], ux[:50], uy[:50], uz[:50], scale[:50], qsz[:50], names[:50], opts, shape=shape
    )
    best = math.inf
    result = None
    for _ in range(3):
        t0 = time.perf_counter()
        result = select_maplets(cam, sun, centres, ux, uy, uz, scale, qsz, names, opts, shape=shape)
        best = min(best, time.perf_counter() - t0)
    counts = result.status_counts()
    traced = int(result.occlusion_tested.sum())
    print(
        f"  q={Q} shape: BVH build {build:.2f} s, max_diameter {dmax_time:.2f} s (both excluded); "
        f"{N_CANDIDATES} candidates, {traced} occlusion rays; statuses {counts}"
    )
    return best, "s", best <= TARGET_S


BENCHMARKS = [
    (
        "select: 10k maplets, occlusion on q=512 ICQ",
        f"<= {TARGET_S:g} s (BVH build excluded)",
        bench_select_10k_q512,
    ),
]


if __name__ == "__main__":
    for name, target, fn in BENCHMARKS:
        value, unit, ok = fn()
        print(f"{name}: {value:.3f} {unit} (target {target}) {'PASS' if ok else 'FAIL'}")
