"""A small SPC working directory with known truth, built in well under a second, for the batch tests
and benchmark (spctool.batch).

One smooth random terrain (sums of random plane waves in heights and albedo, wavelengths 5–80 cells)
on an ORIENT frame is the truth: a large height patch rendered by :func:`spctool.stages.render.render`
(ray traced, cast shadows) through S16's optics (f = 7.68 mm, K = ±454.54 px/mm) from several
viewpoints.  The landmarks are maplets of the same terrain (perfect models) at offsets from the
centre, written as MAPFILES/*.MAP and LMKFILES/*.LMK; the pictures' SUM files hold the true pose
turned by a few pixels of pointing error and moved by a few centimetres (the a-priori pose), photos
are IMAGEFILES/*.DAT (16-bit, big-endian), plus PICTLIST.TXT and LMRKLIST.TXT.  No shape model and
no INIT_LITHOS (defaults everywhere).  Everything is seeded: the same arguments give the same bytes.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from spctool.formats.landmark import write_lmk
from spctool.formats.lists import LandmarkList, PictureList, PictureListEntry, write_lmrklist, write_pictlist
from spctool.formats.maplet import Maplet, write_map
from spctool.formats.photo import write_photo
from spctool.formats.sumfile import Picture, write_sum
from spctool.geometry import frames
from spctool.geometry.camera import Camera
from spctool.geometry.surfaces import HeightPatch
from spctool.sim.maplets import new_landmark
from spctool.stages.render import RenderOptions, render

SCALE = 1e-5  # km per cell (1 cm)
Q = 24  # maplet QSZ
Q_TRUTH = 90
RANGE_KM = 0.05
OFFSETS = [(0, 0), (-32, -30), (30, -34), (-34, 32), (33, 31), (0, 36), (0, -38), (38, 0), (-38, 0)]
VIEWS = [  # (emission, azimuth, sun incidence, sun azimuth), degrees from UZ / UX toward UY
    (12.0, 200.0, 40.0, 30.0),
    (20.0, 60.0, 35.0, 120.0),
    (16.0, 300.0, 45.0, 250.0),
    (25.0, 150.0, 30.0, 200.0),
    (10.0, 20.0, 50.0, 330.0),
    (22.0, 250.0, 38.0, 80.0),
]


class Terrain:
    def __init__(self, seed=11, n=60, lam=(5.0, 80.0), amp=1.5, alb=0.35):
        rng = np.random.default_rng(seed)
        wl = np.exp(rng.uniform(np.log(lam[0]), np.log(lam[1]), n))
        th = rng.uniform(0.0, 2.0 * np.pi, n)
        self.k = np.stack([np.cos(th), np.sin(th)], 1) * (2.0 * np.pi / wl)[:, None]
        self.ph = rng.uniform(0.0, 2.0 * np.pi, n)
        self.a = amp * (wl / lam[1])
        wl2 = np.exp(rng.uniform(np.log(4.0), np.log(80.0), n))
        th2 = rng.uniform(0.0, 2.0 * np.pi, n)
        self.k2 = np.stack([np.cos(th2), np.sin(th2)], 1) * (2.0 * np.pi / wl2)[:, None]
        self.ph2 = rng.uniform(0.0, 2.0 * np.pi, n)
        self.alb = alb / math.sqrt(n)

    def h(self, x, y):
        return (self.a * np.sin(x[..., None] * self.k[:, 0] + y[..., None] * self.k[:, 1] + self.ph)).sum(-1)

    def albedo(self, x, y):
        arg = x[..., None] * self.k2[:, 0] + y[..., None] * self.k2[:, 1] + self.ph2
        return 1.0 + 2.0 * self.alb * np.sin(arg).sum(-1)


def _grid(q):
    n = 2 * q + 1
    x = (np.arange(n, dtype=float) - q)[:, None] * np.ones((1, n))
    return x, x.T.copy()


def _direction(ux, uy, uz, angle_deg, azimuth_deg):
    e, a = math.radians(angle_deg), math.radians(azimuth_deg)
    return math.sin(e) * math.cos(a) * ux + math.sin(e) * math.sin(a) * uy + math.cos(e) * uz


def _camera(target, position, npx, nln):
    cz = frames.normalize(np.asarray(target, float) - np.asarray(position, float))
    up = np.array([0.0, 0.0, 1.0]) if abs(cz[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    cx = frames.normalize(np.cross(up, cz))
    cy = np.cross(cz, cx)
    return Camera(
        mmfl=7.68,
        ctr=np.array([(npx + 1) / 2.0, (nln + 1) / 2.0]),
        kmatrix=np.array([[454.54, 0.0, 0.0], [0.0, -454.54, 0.0]]),
        rotation=np.vstack([cx, cy, cz]),
        scobj=-np.asarray(position, float),
        npx=npx,
        nln=nln,
    )


def picture_name(k: int) -> str:
    return f"T{k + 1:09d}A1"


def make_world(root, n_pictures=3, n_landmarks=5, npx=150, seed=11, pointing_px=1.5, position_km=3e-5):
    """Write the working directory to ``root`` (created); returns the truth as a dict (also written
    as ``root/TRUTH.json``): per picture the true SCOBJ and rotation, per landmark V."""
    root = Path(root)
    for d in ("SUMFILES", "IMAGEFILES", "MAPFILES", "LMKFILES"):
        (root / d).mkdir(parents=True, exist_ok=True)
    terr = Terrain(seed)
    ux, uy, uz = frames.orient_frame(frames.normalize(np.array([0.3, 0.2, 1.0])))
    v0 = 0.2 * uz
    xt, yt = _grid(Q_TRUTH)
    truth = HeightPatch(terr.h(xt, yt), SCALE, v0, ux, uy, uz, albedo=terr.albedo(xt, yt), name="truth")
    names = [f"BW{k:04d}" for k in range(n_landmarks)]
    x, y = _grid(Q)
    for name, (x0, y0) in zip(names, OFFSETS):
        h0 = float(terr.h(np.array(float(x0)), np.array(float(y0))))
        v = v0 + SCALE * (x0 * ux + y0 * uy + h0 * uz)
        m = Maplet.new(
            SCALE, Q, v, ux, uy, uz, terr.h(x + x0, y + y0) - h0, terr.albedo(x + x0, y + y0), name=name
        )
        write_map(root / "MAPFILES" / f"{name}.MAP", m)
        write_lmk(root / "LMKFILES" / f"{name}.LMK", new_landmark(name, SCALE, Q, m.v, m.ux, m.uy, m.uz))
    rng = np.random.default_rng(seed + 1)
    doc = {"pictures": [], "landmarks": names}
    pics = []
    for k in range(n_pictures):
        emission, azimuth, inc, saz = VIEWS[k % len(VIEWS)]
        azimuth += 7.0 * (k // len(VIEWS))
        sun = _direction(ux, uy, uz, inc, saz)
        cam = _camera(v0, v0 + RANGE_KM * _direction(ux, uy, uz, emission, azimuth), npx, npx)
        rend = render(cam, sun, None, [truth], RenderOptions(supersample=1, shadows=True))
        dn = np.where(rend.coverage > 0, np.clip(np.rint(200.0 + 20000.0 * rend.radiance), 1, 65535), 0)
        name = picture_name(k)
        write_photo(root / "IMAGEFILES" / f"{name}.DAT", dn.astype(np.uint16), fmt="dat")
        theta = rng.normal(0.0, 1.0, 3) * pointing_px * cam.ifov
        a_rot = frames.apply_attitude_update(cam.rotation, theta)
        a_scobj = cam.scobj + rng.normal(0.0, position_km, 3)
        pic = Picture(
            name=name,
            utc="2016 JAN 01 00:00:00.000",
            npx=npx,
            nln=npx,
            thrsh=np.array([1.0, 65000.0]),
            mmfl=cam.mmfl,
            ctr=cam.ctr,
            scobj=a_scobj,
            cx=a_rot[0],
            cy=a_rot[1],
            cz=a_rot[2],
            sz=sun,
            kmatrix=cam.kmatrix,
            sigma_vso=np.full(3, 1e-4),
            sigma_ptg=np.full(3, 2e-3),
        )
        write_sum(root / "SUMFILES" / f"{name}.SUM", pic)
        pics.append(name)
        doc["pictures"].append({"name": name, "scobj": cam.scobj.tolist(), "rotation": cam.rotation.tolist()})
    write_pictlist(root / "PICTLIST.TXT", PictureList([PictureListEntry(n) for n in pics]))
    write_lmrklist(root / "LMRKLIST.TXT", LandmarkList(names))
    (root / "TRUTH.json").write_text(json.dumps(doc, indent=1))
    return doc


def crash_task(workdir, out_dir, picture, options, fingerprint, token=None):
    """A batch task whose worker process dies (no exception, no clean-up) on pictures named *CRASH*;
    :func:`spctool.batch.process_picture` for the others."""
    import os

    from spctool.batch import process_picture

    if "CRASH" in picture:
        os._exit(3)
    return process_picture(workdir, out_dir, picture, options, fingerprint, token)
