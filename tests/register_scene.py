"""Rendered scenes with known truth for the correlate/register tests and benchmarks.

A world is one smooth random terrain (a sum of random plane waves in heights and albedo, red spectrum,
wavelengths 4–80 cells) on an ORIENT maplet frame.  The *truth* is a large height patch of that terrain
(q_truth cells around V) rendered by :func:`spctool.stages.render.render` (ray-traced, per-pixel view
directions, optional cast shadows) through a camera with S16's optics (f = 7.68 mm, K = ±454.54 px/mm:
2.865e-4 rad/px, the line axis flipped) at ``range_km`` from V; the *maplet* is the same terrain sampled
on its (2q+1)² nodes — a perfect model, so any registration error comes from the algorithms.  At 50 m
and 1 cm cells a pixel is 1.43 cells (S16 §12.1).  The true pixel of the landmark is the projection of
V with the true camera.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from spctool.geometry import frames
from spctool.geometry.camera import Camera
from spctool.geometry.surfaces import HeightPatch
from spctool.stages.render import RenderOptions, render


class Terrain:
    """h(x, y) and albedo(x, y) (x along UX, y along UY, in cells): sums of random plane waves."""

    def __init__(self, seed=7, n=60, lam=(5.0, 80.0), amp=1.5, alb=0.35):
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
        arg = x[..., None] * self.k[:, 0] + y[..., None] * self.k[:, 1] + self.ph
        return (self.a * np.sin(arg)).sum(-1)

    def albedo(self, x, y):
        arg = x[..., None] * self.k2[:, 0] + y[..., None] * self.k2[:, 1] + self.ph2
        return 1.0 + 2.0 * self.alb * np.sin(arg).sum(-1)


def grid(q):
    n = 2 * q + 1
    x = (np.arange(n, dtype=float) - q)[:, None] * np.ones((1, n))
    y = (np.arange(n, dtype=float) - q)[None, :] * np.ones((n, 1))
    return x, y


def direction(ux, uy, uz, angle_deg, azimuth_deg):
    """Unit vector ``angle_deg`` from UZ, azimuth from UX toward UY."""
    e, a = math.radians(angle_deg), math.radians(azimuth_deg)
    return math.sin(e) * math.cos(a) * ux + math.sin(e) * math.sin(a) * uy + math.cos(e) * uz


def s16_camera(target, position, npx=200, nln=200):
    """S16's optics looking from ``position`` at ``target`` (body km)."""
    cz = frames.normalize(np.asarray(target, float) - np.asarray(position, float))
    up = np.array([0.0, 0.0, 1.0]) if abs(cz[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    cx = frames.normalize(np.cross(up, cz))
    cy = np.cross(cz, cx)
    k = np.array([[454.54, 0.0, 0.0], [0.0, -454.54, 0.0]])
    return Camera(
        mmfl=7.68,
        ctr=np.array([(npx + 1) / 2.0, (nln + 1) / 2.0]),
        kmatrix=k,
        rotation=np.vstack([cx, cy, cz]),
        scobj=-np.asarray(position, float),
        npx=npx,
        nln=nln,
    )


def scene(
    q=49,
    q_truth=140,
    scale=1e-5,
    range_km=0.05,
    emission=15.0,
    azimuth=200.0,
    sun_incidence=40.0,
    sun_azimuth=30.0,
    npx=200,
    nln=200,
    shadows=True,
    supersample=2,
    seed=7,
    gain=2000.0,
    offset=50.0,
    name="LMK001",
):
    """A rendered scene: maplet, truth patch, Sun, true camera, photo (data[line − 1, sample − 1]) and
    the true pixel of V."""
    terr = Terrain(seed)
    ux, uy, uz = frames.orient_frame(frames.normalize(np.array([0.3, 0.2, 1.0])))
    v = 0.2 * uz  # on a 200 m "body", any point works
    x, y = grid(q)
    maplet = SimpleNamespace(
        heights=terr.h(x, y),
        albedo=terr.albedo(x, y),
        valid=np.ones(x.shape, bool),
        scale=scale,
        qsz=q,
        v=v,
        ux=ux,
        uy=uy,
        uz=uz,
        name=name,
    )
    xt, yt = grid(q_truth)
    truth = HeightPatch(terr.h(xt, yt), scale, v, ux, uy, uz, albedo=terr.albedo(xt, yt), name="truth")
    sun = direction(ux, uy, uz, sun_incidence, sun_azimuth)
    camera = s16_camera(v, v + range_km * direction(ux, uy, uz, emission, azimuth), npx, nln)
    rend = render(camera, sun, None, [truth], RenderOptions(supersample=supersample, shadows=shadows))
    photo = np.where(rend.coverage > 0, offset + gain * rend.radiance, 0.0)
    truth_pixel = np.array(camera.project(v), dtype=float)
    return SimpleNamespace(
        terrain=terr,
        maplet=maplet,
        truth=truth,
        sun=sun,
        camera=camera,
        photo=photo,
        rendering=rend,
        truth_pixel=truth_pixel,
        thresholds=(1.0, 1e9),
    )


def pointing_error(camera, dsample, dline):
    """The camera turned so that the scene moves by about (dsample, dline) pixels at the boresight."""
    ifov = camera.ifov
    # a rotation about camera y moves x_C (sample via K11 > 0) ; about camera x moves y_C (line via K22)
    k11, k22 = camera.kmatrix[0, 0], camera.kmatrix[1, 1]
    theta = np.array([dline * ifov * np.sign(k22), -dsample * ifov * np.sign(k11), 0.0])
    return camera.updated(dtheta=theta)


def offset_maplet(sc, x0, y0, q=24, name="LMK002"):
    """A maplet of the scene's terrain centred on the node (x0, y0) cells of the main maplet's frame."""
    t, m = sc.terrain, sc.maplet
    x, y = grid(q)
    h0 = float(t.h(np.array(float(x0)), np.array(float(y0))))
    v = m.v + m.scale * (x0 * m.ux + y0 * m.uy + h0 * m.uz)
    return SimpleNamespace(
        heights=t.h(x + x0, y + y0) - h0,
        albedo=t.albedo(x + x0, y + y0),
        valid=np.ones(x.shape, bool),
        scale=m.scale,
        qsz=q,
        v=v,
        ux=m.ux,
        uy=m.uy,
        uz=m.uz,
        name=name,
    )
