"""Synthetic maplet + camera + independent ray-cast renderer shared by the appearance tests
(test_predict.py, test_extract.py, test_cli_appearance.py, benchmarks/bench_appearance.py).

The renderer shares no code with spctool.stages.extract / predict: for every photo pixel it casts
the camera ray (Camera.pixel_to_direction), finds the first crossing with the maplet's bilinear
terrain (heightfield.intersect_rays), and shades the hit with the *analytic* normal and albedo of
the terrain function and the per-pixel view direction.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from spctool import photometry
from spctool.geometry import frames, heightfield
from spctool.geometry.camera import Camera


def terrain(x, y):
    """Heights (cells), ∂h/∂x, ∂h/∂y of a smooth analytic terrain (x along UX, y along UY, in cells)."""
    a1, a2 = 1.6, 2.5
    h = a1 * np.sin(x / 7.0 + 0.3) * np.cos(y / 9.0) + a2 * np.exp(-((x - 5.0) ** 2 + (y + 3.0) ** 2) / 72.0)
    g = a2 * np.exp(-((x - 5.0) ** 2 + (y + 3.0) ** 2) / 72.0)
    hx = a1 / 7.0 * np.cos(x / 7.0 + 0.3) * np.cos(y / 9.0) - g * (x - 5.0) / 36.0
    hy = -a1 / 9.0 * np.sin(x / 7.0 + 0.3) * np.sin(y / 9.0) - g * (y + 3.0) / 36.0
    return h, hx, hy


def albedo(x, y):
    return 1.0 + 0.3 * np.sin(x / 3.0 + 0.5) * np.sin(y / 4.0) + 0.1 * np.cos((x + 2.0 * y) / 5.0)


def make_maplet(q=24, scale=0.001, v=(0.2, -0.1, 1.0), uz=(0.3, 0.2, 1.0), terrain_fn=terrain,
                albedo_fn=albedo, name="SYN001"):
    """A duck-typed maplet (heights exact, no file quantisation) on an ORIENT frame."""
    uz = frames.normalize(np.asarray(uz, float))
    ux, uy, uz = frames.orient_frame(uz)
    n = 2 * q + 1
    x = (np.arange(n, dtype=float) - q)[:, None] * np.ones((1, n))
    y = (np.arange(n, dtype=float) - q)[None, :] * np.ones((n, 1))
    h = terrain_fn(x, y)[0]
    return SimpleNamespace(heights=h, albedo=albedo_fn(x, y), valid=np.ones((n, n), bool), scale=scale, qsz=q,
                           v=np.asarray(v, float), ux=ux, uy=uy, uz=uz, name=name)


def direction(maplet, emission_deg, azimuth_deg):
    """Unit body-frame vector at ``emission_deg`` from UZ, azimuth measured from UX toward UY."""
    e, a = math.radians(emission_deg), math.radians(azimuth_deg)
    return (math.sin(e) * math.cos(a) * maplet.ux + math.sin(e) * math.sin(a) * maplet.uy
            + math.cos(e) * maplet.uz)


def look_at_camera(target, position, *, mmfl=100.0, kpx=10.0, npx=200, nln=200, ctr=None, roll_deg=0.0):
    """A pinhole Camera at ``position`` whose boresight passes through ``target`` (body frame, km)."""
    cz = frames.normalize(np.asarray(target, float) - np.asarray(position, float))
    up = np.array([0.0, 0.0, 1.0]) if abs(cz[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    cx = frames.normalize(np.cross(up, cz))
    cy = np.cross(cz, cx)
    rot = np.vstack([cx, cy, cz])
    if roll_deg:
        rot = frames.rot_from_axis_angle(np.array([0.0, 0.0, 1.0]), math.radians(roll_deg)) @ rot
    if ctr is None:
        ctr = ((npx + 1) / 2.0, (nln + 1) / 2.0)
    k = np.array([[kpx, 0.0, 0.0], [0.0, kpx, 0.0]])
    return Camera(mmfl=mmfl, ctr=np.asarray(ctr, float), kmatrix=k, rotation=rot,
                  scobj=-np.asarray(position, float), npx=npx, nln=nln)


def render(camera, maplet, sun, *, model="spc", gain=2000.0, offset=50.0, terrain_fn=terrain,
           albedo_fn=albedo, cast_shadows=False, supersample=1):
    """Photo data[line-1, sample-1] (float64) of the maplet terrain; 0 where no ray hits it.

    DN = offset + gain·a·R(μ0, μ, α) at the ray's first terrain hit, with the analytic normal and
    albedo; μ and α from the per-pixel view direction.  ``cast_shadows`` traces a second ray from the
    hit toward the Sun.  ``supersample`` k averages the k×k rays per pixel that hit the terrain (box filter).
    """
    s_hat = frames.normalize(np.asarray(sun, float))
    k = int(supersample)
    off = (np.arange(k) + 0.5) / k - 0.5
    ss, ll = np.meshgrid(np.arange(1, camera.npx + 1, dtype=float), np.arange(1, camera.nln + 1, dtype=float))
    ss = ss[..., None, None] + off[None, None, :, None] + 0.0 * off[None, None, None, :]
    ll = ll[..., None, None] + 0.0 * off[None, None, :, None] + off[None, None, None, :]
    d = camera.pixel_to_direction(ss, ll)
    o_m = frames.body_to_maplet(camera.position, maplet.v, maplet.ux, maplet.uy, maplet.uz, maplet.scale)
    d_m = heightfield.to_maplet_components(d, maplet.ux, maplet.uy, maplet.uz) / maplet.scale
    t = heightfield.intersect_rays(maplet.heights, maplet.valid, o_m, d_m)
    hit = np.isfinite(t)
    p = o_m + np.where(hit, t, 0.0)[..., None] * d_m
    _, hx, hy = terrain_fn(p[..., 0], p[..., 1])
    nrm = np.stack([-hx, -hy, np.ones_like(hx)], axis=-1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    s_m = heightfield.to_maplet_components(s_hat, maplet.ux, maplet.uy, maplet.uz)
    view = -d_m / np.linalg.norm(d_m, axis=-1, keepdims=True)
    mu0 = nrm @ s_m
    mu = np.sum(nrm * view, axis=-1)
    alpha = np.degrees(np.arccos(np.clip(view @ s_m, -1.0, 1.0)))
    r = photometry.reflectance(mu0, mu, alpha, model)
    if cast_shadows:
        start = p + 1e-6 * np.asarray(s_m)
        ts = heightfield.intersect_rays(maplet.heights, maplet.valid, start, np.broadcast_to(s_m, p.shape),
                                        t_min=1e-3)
        r = np.where(np.isfinite(ts), 0.0, r)
    dn = np.where(hit, offset + gain * albedo_fn(p[..., 0], p[..., 1]) * r, 0.0)
    # average over the rays that hit the maplet (a pixel straddling its border sees terrain only)
    nhit = np.count_nonzero(hit, axis=(-2, -1))
    return np.where(nhit > 0, dn.sum(axis=(-2, -1)) / np.maximum(nhit, 1), 0.0)
