"""A small in-memory scene with known truth for the photoclinometry tests (``find_heights``, ``lithos``).

The truth is :class:`Terrain` (smooth random plane waves in heights and albedo, wavelengths of at
least 5 maplet cells by default) on an ORIENT frame: a 181×181 height patch of 1 cm cells rendered
by :func:`spctool.stages.render.render` (ray traced, cast shadows) from true cameras.  The maplet
under test has 2 cm cells; its truth is the terrain sampled on the maplet grid, and the *starting*
maplet is that truth smoothed by a Gaussian of ``smooth`` maplet cells with a uniform albedo (far
coarser than the truth, as ``make-maplets`` from a shape model would give).  Seeded: the same
arguments give the same arrays.
"""

from __future__ import annotations

import math

import numpy as np
from batch_world import Q_TRUTH, _camera, _direction, _grid  # noqa: F401
from scipy.ndimage import gaussian_filter

from spctool.formats.maplet import Maplet
from spctool.geometry import frames
from spctool.geometry.surfaces import HeightPatch
from spctool.stages.find_heights import PictureView
from spctool.stages.render import RenderOptions, render

TRUTH_SCALE = 1e-5  # km per truth cell (1 cm)
FACTOR = 2  # truth cells per maplet cell
RANGE_KM = 0.04
#: (emission, azimuth, Sun incidence, Sun azimuth), degrees from UZ / from UX toward UY
VIEWS = [
    (25.0, 45.0, 45.0, 0.0),
    (25.0, 135.0, 45.0, 90.0),
    (25.0, 225.0, 45.0, 180.0),
    (25.0, 315.0, 45.0, 270.0),
    (10.0, 90.0, 30.0, 135.0),
    (15.0, 0.0, 55.0, 315.0),
    (20.0, 180.0, 40.0, 45.0),
    (20.0, 270.0, 40.0, 225.0),
    (30.0, 100.0, 50.0, 10.0),
    (12.0, 200.0, 35.0, 190.0),
]


class Terrain:
    """Sums of ``n`` random plane waves in heights (wavelengths ``lam`` truth cells, amplitude ∝
    wavelength, ``amp`` at the longest) and in albedo (wavelengths ``lam_albedo``, rms ``alb``) —
    :class:`batch_world.Terrain` with the albedo's band as a parameter, so that a test can keep the
    truth within what its maplet's grid can hold."""

    def __init__(self, seed=11, n=60, lam=(10.0, 80.0), amp=0.7, alb=0.2, lam_albedo=(10.0, 80.0)):
        rng = np.random.default_rng(seed)
        wl = np.exp(rng.uniform(np.log(lam[0]), np.log(lam[1]), n))
        th = rng.uniform(0.0, 2.0 * np.pi, n)
        self.k = np.stack([np.cos(th), np.sin(th)], 1) * (2.0 * np.pi / wl)[:, None]
        self.ph = rng.uniform(0.0, 2.0 * np.pi, n)
        self.a = amp * (wl / lam[1])
        wl2 = np.exp(rng.uniform(np.log(lam_albedo[0]), np.log(lam_albedo[1]), n))
        th2 = rng.uniform(0.0, 2.0 * np.pi, n)
        self.k2 = np.stack([np.cos(th2), np.sin(th2)], 1) * (2.0 * np.pi / wl2)[:, None]
        self.ph2 = rng.uniform(0.0, 2.0 * np.pi, n)
        self.alb = alb * math.sqrt(2.0 / n)

    def h(self, x, y):
        return (self.a * np.sin(x[..., None] * self.k[:, 0] + y[..., None] * self.k[:, 1] + self.ph)).sum(-1)

    def albedo(self, x, y):
        arg = x[..., None] * self.k2[:, 0] + y[..., None] * self.k2[:, 1] + self.ph2
        return 1.0 + self.alb * np.sin(arg).sum(-1)


def make_scene(n_pictures=4, q=20, smooth=4.0, seed=11, npx=160, views=None, amp=0.7, lam=(10.0, 80.0),
               lam_albedo=(10.0, 80.0)):
    """(start maplet, truth maplet, [PictureView]) — module docstring."""
    terr = Terrain(seed, lam=lam, amp=amp, lam_albedo=lam_albedo)
    ux, uy, uz = frames.orient_frame(frames.normalize(np.array([0.3, 0.2, 1.0])))
    v0 = 0.2 * uz
    xt, yt = _grid(max(Q_TRUTH, FACTOR * q + 10))
    truth_patch = HeightPatch(terr.h(xt, yt), TRUTH_SCALE, v0, ux, uy, uz, albedo=terr.albedo(xt, yt),
                              name="truth")
    x, y = _grid(q)
    h_true = terr.h(FACTOR * x, FACTOR * y) / FACTOR  # maplet cells
    a_true = terr.albedo(FACTOR * x, FACTOR * y)
    scale = FACTOR * TRUTH_SCALE
    truth = Maplet.new(scale, q, v0, ux, uy, uz, h_true, a_true, name="HW0001")
    h_start = gaussian_filter(h_true, smooth, mode="nearest")
    start = Maplet.new(scale, q, v0, ux, uy, uz, h_start, np.ones_like(h_start), name="HW0001")
    views = VIEWS if views is None else views
    out = []
    for k in range(n_pictures):
        emission, azimuth, inc, saz = views[k % len(views)]
        sun = _direction(ux, uy, uz, inc, saz)
        cam = _camera(v0, v0 + RANGE_KM * _direction(ux, uy, uz, emission, azimuth), npx, npx)
        rend = render(cam, sun, None, [truth_patch], RenderOptions(supersample=2, shadows=True))
        dn = np.where(rend.coverage > 0, np.clip(np.rint(20000.0 * rend.radiance), 0, 65535), 0)
        s, ln = cam.project(v0[None, :])
        out.append(PictureView(f"HP{k + 1:010d}", dn.astype(np.float64), cam, sun, (0.5, 65000.0),
                               (float(s[0]), float(ln[0]))))
    return start, truth, out


def rms(a, b, mask=None) -> float:
    d = np.asarray(a, float) - np.asarray(b, float)
    if mask is not None:
        d = d[np.asarray(mask, bool)]
    return float(math.sqrt(np.mean(d * d)))


def write_workdir(root, start, views, truth=None) -> list[str]:
    """An SPC working directory of the scene: MAPFILES/ and LMKFILES/ (PICTURES: every view at its
    a-priori pixel), SUMFILES/ (true poses, THRSH of the views), IMAGEFILES/ (16-bit DAT),
    LMRKLIST.TXT, PICTLIST.TXT and, with ``truth``, TRUTHFILES/<NAME>.MAP.  Returns the picture names."""
    from pathlib import Path

    from spctool.formats.landmark import LandmarkPicture, write_lmk
    from spctool.formats.lists import (
        LandmarkList,
        PictureList,
        PictureListEntry,
        write_lmrklist,
        write_pictlist,
    )
    from spctool.formats.maplet import write_map
    from spctool.formats.photo import write_photo
    from spctool.formats.sumfile import Picture, write_sum
    from spctool.sim.maplets import new_landmark

    root = Path(root)
    for d in ("SUMFILES", "IMAGEFILES", "MAPFILES", "LMKFILES", "TRUTHFILES"):
        (root / d).mkdir(parents=True, exist_ok=True)
    name = start.name
    write_map(root / "MAPFILES" / f"{name}.MAP", start)
    if truth is not None:
        write_map(root / "TRUTHFILES" / f"{name}.MAP", truth)
    lmk = new_landmark(name, start.scale, start.qsz, start.v, start.ux, start.uy, start.uz)
    lmk.pictures = [LandmarkPicture(v.name, v.pixel[0], v.pixel[1]) for v in views]
    write_lmk(root / "LMKFILES" / f"{name}.LMK", lmk)
    for v in views:
        cam = v.camera
        npx = v.photo.shape[1]
        dn = np.clip(v.photo, 0, 65535).astype(np.uint16)
        write_photo(root / "IMAGEFILES" / f"{v.name}.DAT", dn, fmt="dat")
        rot = np.asarray(cam.rotation)
        pic = Picture(name=v.name, utc="2016 JAN 01 00:00:00.000", npx=npx, nln=v.photo.shape[0],
                      thrsh=np.array(v.thresholds, dtype=float), mmfl=cam.mmfl, ctr=cam.ctr, scobj=cam.scobj,
                      cx=rot[0], cy=rot[1], cz=rot[2], sz=np.asarray(v.sun, float), kmatrix=cam.kmatrix,
                      sigma_vso=np.full(3, 1e-4), sigma_ptg=np.full(3, 2e-3))
        write_sum(root / "SUMFILES" / f"{v.name}.SUM", pic)
    write_pictlist(root / "PICTLIST.TXT", PictureList([PictureListEntry(v.name) for v in views]))
    write_lmrklist(root / "LMRKLIST.TXT", LandmarkList([name]))
    return [v.name for v in views]


def solve_ok(args) -> bool:
    """``find_heights`` of (maplet, views, seed) → solved?  (a picklable task for worker processes)"""
    from spctool.stages.find_heights import FindHeightsOptions, find_heights

    start, views, seed = args
    return find_heights(start, views, FindHeightsOptions(seed=seed)).ok


_WORKER_SCENE: tuple = ()


def init_worker(start, views) -> None:
    """A worker process's scene, received once (``ProcessPoolExecutor(initializer=...)``)."""
    global _WORKER_SCENE
    _WORKER_SCENE = (start, views)


def solve_seeded(seed: int):
    """(solved?, CPU seconds) of ``find_heights`` on the worker's scene (:func:`init_worker`) with the
    conditioning cells drawn by ``seed``."""
    import time

    from spctool.stages.find_heights import FindHeightsOptions, find_heights

    t0 = time.process_time()
    ok = find_heights(_WORKER_SCENE[0], _WORKER_SCENE[1], FindHeightsOptions(seed=seed)).ok
    return ok, time.process_time() - t0
