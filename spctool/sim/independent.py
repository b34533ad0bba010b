"""An independent validation world: photos ray-traced by a third-party renderer (trimesh + Embree).

Why (issue #15, GUIDE "validate against what we did not write"): spctool's own Monte Carlo worlds are
rendered by :mod:`spctool.stages.render`, the same code that makes the image-space templates, so they
cannot reveal errors that code shares with the correlator.  Here the photo comes from a different ray
tracer on a different surface representation:

* **Truth surface**: an analytic terrain h(x, y) (random Fourier modes with a red spectrum plus a few
  bowl craters with raised rims, see :class:`TruthTerrain`) on a local frame (UX, UY, UZ) at V₀ = R·UZ,
  meshed as a triangle mesh **finer than the maplets** — ``facet``: facets of ``facet_cells`` maplet
  cells, flat-shaded (face normals); ``smooth``: the mesh subdivided to ``smooth_cells`` (far below a
  pixel) and shaded with the vertex normals interpolated barycentrically, so no facet is visible.
* **Photo**: every pixel is ``supersample``² rays of an independent pinhole model (spc-formats.md §2.5:
  sample = CTR1 + K11·x + K12·y, line = CTR2 + K21·x + K22·y, (x, y) = MMFL·(X/Z, Y/Z); written here
  from the formula, not from :class:`spctool.geometry.camera.Camera`), cast with
  ``trimesh.ray.ray_pyembree`` (Embree).  Radiance is Lambert, albedo·max(0, n·s), zero where a shadow
  ray from the hit toward the Sun hits the mesh (cast shadows).  DN = ``dn_bias`` + ``dn_gain``·radiance
  + Gaussian noise (``noise_dn``), 16-bit, 0 where a ray missed the mesh (SPC's no-data value).
* **Maplets** are generated from the truth mesh the way SPC's GET_HEIGHTS does
  (:func:`spctool.sim.maplets.make_maplets`: ORIENT frame at the fitted normal, highest surface point
  on each node's vertical); their albedo is the truth albedo at the nodes.
* **A-priori poses**: the true pointing turned (and the position moved by ``position_km``) so that the
  largest landmark error of picture k is ``apriori_px[k]`` pixels — 6, 14 and 20 px by default, the
  14 px case being the picture the issue's batch lost.
* **Truth pixels**: the projection of every landmark's V with the true pose by the independent pinhole
  (``TRUTH.json``).

Everything is written as a legacy SPC working directory with spctool's writers (:mod:`spctool.formats`):
SUMFILES/, IMAGEFILES/ (.DAT, 16-bit big-endian), MAPFILES/, LMKFILES/, INIT_LITHOS.TXT, PICTLIST.TXT,
LMRKLIST.TXT and TRUTH.json.  Seeded: the same spec gives the same files.  ``pip install trimesh`` (and
embreex) is needed to *build* a world; nothing else in spctool imports trimesh.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spctool.errors import SpcEnvironmentError, SpcUsageError

__all__ = [
    "IndependentSpec",
    "TruthTerrain",
    "build_world",
    "load_picture",
    "pinhole_project",
    "pinhole_rays",
    "TRUTHS",
]

TRUTHS = ("facet", "smooth")
#: S16's optics (f = 7.68 mm, K = ±454.54 px/mm, line axis flipped): 2.865e-4 rad/px
MMFL = 7.68
KMAT = np.array([[454.54, 0.0, 0.0], [0.0, -454.54, 0.0]])
#: (emission, azimuth, sun incidence, sun azimuth) in degrees from UZ / from UX toward UY, per picture
VIEWS = (
    (14.0, 200.0, 48.0, 30.0),
    (22.0, 70.0, 42.0, 130.0),
    (18.0, 310.0, 55.0, 250.0),
    (26.0, 150.0, 38.0, 200.0),
    (10.0, 20.0, 60.0, 330.0),
    (20.0, 250.0, 45.0, 80.0),
    (24.0, 110.0, 50.0, 300.0),
    (12.0, 340.0, 40.0, 170.0),
)


@dataclass
class IndependentSpec:
    """Size and truth of an independent world (defaults: the CI world, built in a few seconds).

    * ``truth`` — ``"facet"`` or ``"smooth"``; ``facet_cells`` / ``smooth_cells``: mesh spacing in maplet
      cells of the two truths.
    * ``n_side`` landmarks per side of a square grid ``spacing_cells`` apart; maplets (2·``qsz``+1)² at
      ``scale_km`` per cell.
    * ``range_km`` camera distance (40 m: 1.15 cm per pixel, 0.87 px per 1 cm cell); photos ``npx``².
    * ``apriori_px`` — the largest a-priori landmark error of each picture (one picture per entry);
      ``position_km`` a-priori position error (1σ per axis); ``sigma_vso_km``/``sigma_ptg_rad`` the SUM
      sigmas written.
    * ``supersample`` rays per pixel axis; ``noise_dn`` Gaussian noise (1σ DN) on ``dn_bias`` +
      ``dn_gain``·radiance.
    * ``sun_incidence_deg`` — the Sun's angle from UZ in every picture (None: each view's own, 38–60°
      of :data:`VIEWS`; e.g. 70 for a low Sun and long shadows, as the issue's second scene).
    """

    truth: str = "facet"
    seed: int = 15
    n_side: int = 3
    qsz: int = 24
    scale_km: float = 1e-5
    spacing_cells: float = 34.0
    range_km: float = 0.04
    npx: int = 160
    apriori_px: tuple = (6.0, 14.0, 20.0)
    position_km: float = 2e-5
    sigma_vso_km: float = 2e-4
    sigma_ptg_rad: float = 1e-2
    facet_cells: float = 0.5
    smooth_cells: float = 1.0 / 3.0
    supersample: int = 3
    noise_dn: float = 20.0
    dn_bias: float = 200.0
    dn_gain: float = 20000.0
    body_radius_km: float = 0.2
    sun_incidence_deg: float | None = None

    def __post_init__(self):
        if self.truth not in TRUTHS:
            raise SpcUsageError(f"truth must be one of {', '.join(TRUTHS)}, got {self.truth!r}")
        self.apriori_px = tuple(float(x) for x in self.apriori_px)
        if not self.apriori_px:
            raise SpcUsageError("an independent world needs at least one picture")
        if int(self.n_side) < 2 or int(self.qsz) < 4 or int(self.supersample) < 1:
            raise SpcUsageError("n_side >= 2, qsz >= 4 and supersample >= 1 are needed")
        if len(self.apriori_px) > len(VIEWS):
            raise SpcUsageError(f"at most {len(VIEWS)} pictures")
        if self.sun_incidence_deg is not None and not (0.0 <= float(self.sun_incidence_deg) < 90.0):
            raise SpcUsageError(f"sun_incidence_deg must be in [0, 90), got {self.sun_incidence_deg}")

    @property
    def mesh_cells(self) -> float:
        return float(self.facet_cells if self.truth == "facet" else self.smooth_cells)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


class TruthTerrain:
    """h(x, y) (cells, x along UX, y along UY) and albedo(x, y): Fourier modes + craters, seeded.

    Wavelengths 6–90 cells with amplitude ∝ wavelength (slopes of tens of degrees at the short end),
    plus craters of radius 6–18 cells (parabolic bowl, depth 0.25·radius, a raised rim that decays
    outside).  Albedo: 1 ± ~12 % from its own modes.
    """

    def __init__(self, seed: int, extent: float, n_modes: int = 48, n_craters: int = 10):
        rng = np.random.default_rng(seed)
        wl = np.exp(rng.uniform(np.log(6.0), np.log(90.0), n_modes))
        th = rng.uniform(0.0, 2.0 * np.pi, n_modes)
        self.k = np.stack([np.cos(th), np.sin(th)], 1) * (2.0 * np.pi / wl)[:, None]
        self.ph = rng.uniform(0.0, 2.0 * np.pi, n_modes)
        self.amp = 1.3 * wl / 90.0
        wl2 = np.exp(rng.uniform(np.log(5.0), np.log(60.0), n_modes))
        th2 = rng.uniform(0.0, 2.0 * np.pi, n_modes)
        self.k2 = np.stack([np.cos(th2), np.sin(th2)], 1) * (2.0 * np.pi / wl2)[:, None]
        self.ph2 = rng.uniform(0.0, 2.0 * np.pi, n_modes)
        self.alb = 0.12 * math.sqrt(2.0 / n_modes)
        self.crater_xy = rng.uniform(-extent, extent, (n_craters, 2))
        self.crater_r = rng.uniform(6.0, 18.0, n_craters)

    def height(self, x, y):
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        h = np.zeros(np.broadcast(x, y).shape)
        for kx, ky, p, a in zip(self.k[:, 0], self.k[:, 1], self.ph, self.amp):  # few modes, big arrays
            h += a * np.sin(kx * x + ky * y + p)
        for (cx, cy), r in zip(self.crater_xy, self.crater_r):
            d = np.hypot(x - cx, y - cy) / r
            bowl = np.where(d < 1.0, 0.25 * r * (d * d - 1.0), 0.0)
            rim = 0.06 * r * np.where(d < 1.0, d**4, np.exp(-(((d - 1.0) / 0.35) ** 2)))
            h += bowl + rim
        return h

    def albedo(self, x, y):
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        a = np.ones(np.broadcast(x, y).shape)
        for kx, ky, p in zip(self.k2[:, 0], self.k2[:, 1], self.ph2):
            a += self.alb * np.sin(kx * x + ky * y + p)
        return a


# --------------------------------------------------------------------------------------------------
# the independent pinhole (spc-formats.md §2.5, no distortion)


def pinhole_project(points, scobj, rotation, ctr, mmfl=MMFL, kmatrix=KMAT):
    """(N, 2) SPC pixels (sample, line) of body points (N, 3): x_C = T·(P + SCOBJ), (x, y) = f·x_C/z_C."""
    pc = (np.asarray(points, float) + np.asarray(scobj, float)) @ np.asarray(rotation, float).T
    x = mmfl * pc[:, 0] / pc[:, 2]
    y = mmfl * pc[:, 1] / pc[:, 2]
    k = np.asarray(kmatrix, float)
    return np.stack([ctr[0] + k[0, 0] * x + k[0, 1] * y, ctr[1] + k[1, 0] * x + k[1, 1] * y], axis=-1)


def pinhole_rays(sample, line, rotation, ctr, mmfl=MMFL, kmatrix=KMAT):
    """Unit body-frame directions (N, 3) of the rays through pixels (sample, line) (the inverse above)."""
    k2 = np.asarray(kmatrix, float)[:, :2]
    xy = np.linalg.solve(k2, np.stack([np.ravel(sample) - ctr[0], np.ravel(line) - ctr[1]]))
    d = np.column_stack([xy[0], xy[1], np.full(xy.shape[1], mmfl)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d @ np.asarray(rotation, float)


# --------------------------------------------------------------------------------------------------
# mesh and rendering


def _grid_mesh(terrain: TruthTerrain, half: float, step: float):
    """Vertices (local cells: x, y, h) and faces of the terrain on a square grid, alternating diagonals."""
    n = int(math.ceil(2.0 * half / step)) + 1
    t = -half + step * np.arange(n)
    x, y = np.meshgrid(t, t, indexing="ij")
    verts = np.column_stack([x.ravel(), y.ravel(), terrain.height(x, y).ravel()])
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    b, c, d = a + n, a + 1, a + n + 1
    flip = ((i + j) % 2 == 0).ravel()
    f1 = np.where(flip[:, None], np.column_stack([a, b, d]), np.column_stack([a, b, c]))
    f2 = np.where(flip[:, None], np.column_stack([a, d, c]), np.column_stack([c, b, d]))
    faces = np.concatenate([f1, f2])
    # counter-clockwise seen from +UZ (outward)
    e1 = verts[faces[:, 1]] - verts[faces[:, 0]]
    e2 = verts[faces[:, 2]] - verts[faces[:, 0]]
    down = np.cross(e1, e2)[:, 2] < 0.0
    faces[down] = faces[down][:, ::-1]
    return verts, faces


class _Tracer:
    """trimesh + Embree ray casting of the truth mesh in a local metric frame (metres about V₀)."""

    def __init__(self, verts_m, faces, vertex_albedo, smooth: bool):
        try:
            import trimesh
            from trimesh.ray.ray_pyembree import RayMeshIntersector
        except ImportError as exc:  # pragma: no cover - environment
            raise SpcEnvironmentError(
                f"the independent world needs trimesh and embreex (pip install trimesh embreex): {exc}"
            ) from None
        self.mesh = trimesh.Trimesh(vertices=verts_m, faces=faces, process=False)
        self.ray = RayMeshIntersector(self.mesh)
        self.albedo = np.asarray(vertex_albedo, float)
        self.smooth = smooth
        # plain arrays: trimesh re-hashes its tracked arrays on every access
        self.verts = np.array(self.mesh.vertices, dtype=np.float64)
        self.faces = np.array(self.mesh.faces, dtype=np.int64)
        self.face_normals = np.array(self.mesh.face_normals, dtype=np.float64)
        self.vertex_normals = np.array(self.mesh.vertex_normals, dtype=np.float64) if smooth else None

    def shade(self, origins, dirs, sun):
        """Lambert radiance per ray (NaN where the ray misses) with cast shadows."""
        import trimesh

        loc, iray, itri = self.ray.intersects_location(origins, dirs, multiple_hits=False)
        out = np.full(len(origins), np.nan)
        if len(iray) == 0:
            return out
        fidx = self.faces[itri]
        bary = trimesh.triangles.points_to_barycentric(self.verts[fidx], loc)
        alb = np.einsum("ij,ij->i", bary, self.albedo[fidx])
        if self.smooth:
            nrm = np.einsum("ij,ijk->ik", bary, self.vertex_normals[fidx])
            nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        else:
            nrm = self.face_normals[itri]
        cos_i = nrm @ sun
        lit = cos_i > 0.0
        # shadow rays from just above the hit (1e-5 m along the face normal) toward the Sun
        k = np.flatnonzero(lit)
        if len(k):
            o = loc[k] + 1e-5 * self.face_normals[itri[k]]
            blocked = self.ray.intersects_any(o, np.broadcast_to(sun, (len(k), 3)).copy())
            lit[k[blocked]] = False
        out[iray] = np.where(lit, alb * np.clip(cos_i, 0.0, None), 0.0)
        return out


def _direction(ux, uy, uz, angle_deg, azimuth_deg):
    e, a = math.radians(angle_deg), math.radians(azimuth_deg)
    return math.sin(e) * math.cos(a) * ux + math.sin(e) * math.sin(a) * uy + math.cos(e) * uz


def _look_at(target, position):
    cz = target - position
    cz = cz / np.linalg.norm(cz)
    up = np.array([0.0, 0.0, 1.0]) if abs(cz[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    cx = np.cross(up, cz)
    cx /= np.linalg.norm(cx)
    return np.vstack([cx, np.cross(cz, cx), cz])


def _photo(tracer: _Tracer, v0, rotation, position_km, sun, spec: IndependentSpec, ctr):
    """(nln, npx) radiance (NaN where any ray of the pixel missed) rendered by the tracer."""
    ss = int(spec.supersample)
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    n = int(spec.npx)
    pix = np.arange(1, n + 1, dtype=np.float64)
    rad = np.zeros((n, n))
    origin = (np.asarray(position_km) - v0) * 1e3
    for dl in sub:
        for ds in sub:
            smp, lin = np.meshgrid(pix + ds, pix + dl)  # (line, sample)
            dirs = pinhole_rays(smp.ravel(), lin.ravel(), rotation, ctr)
            rad += tracer.shade(np.broadcast_to(origin, dirs.shape).copy(), dirs, sun).reshape(n, n)
    return rad / (ss * ss)


# --------------------------------------------------------------------------------------------------
# the world


def _apriori_rotation(rotation, scobj, a_scobj, points, ctr, target_px, ifov, rng):
    """Rotation turned so that the largest pixel error of ``points`` seen from ``a_scobj`` is
    ``target_px`` (a turn in a random direction plus a twist about the boresight)."""
    from spctool.geometry.frames import apply_attitude_update

    true_px = pinhole_project(points, scobj, rotation, ctr)
    ang = rng.uniform(0.0, 2.0 * np.pi)
    theta = np.array([math.sin(ang), math.cos(ang), 0.15 * rng.normal()]) * ifov
    for _ in range(12):  # the error is nearly linear in θ to first order: rescale until exact
        rot = apply_attitude_update(rotation, theta)
        err = np.max(np.linalg.norm(pinhole_project(points, a_scobj, rot, ctr) - true_px, axis=1))
        theta = theta * (target_px / err)
    return apply_attitude_update(rotation, theta)


def build_world(root, spec: IndependentSpec | None = None) -> dict:
    """Write the independent world to ``root`` (created) and return its truth (also ``TRUTH.json``).

    The truth document: ``spec``; ``pictures``: name, true ``scobj``/``rotation``, ``apriori_px`` (the
    largest a-priori landmark error) and ``pixels`` {landmark: [sample, line]} (true pixels, the
    independent pinhole); ``landmarks``: names and V (km).
    """
    from spctool.formats.landmark import write_lmk
    from spctool.formats.lists import (
        LandmarkList,
        PictureList,
        PictureListEntry,
        write_lmrklist,
        write_pictlist,
    )
    from spctool.formats.lithos import parse_lithos, write_lithos
    from spctool.formats.maplet import Maplet, write_map
    from spctool.formats.mesh import TriangleMesh
    from spctool.formats.photo import write_photo
    from spctool.formats.sumfile import Picture, write_sum
    from spctool.geometry.surfaces import ShapeSurface
    from spctool.sim.maplets import make_maplets

    spec = spec if spec is not None else IndependentSpec()
    root = Path(root)
    for d in ("SUMFILES", "IMAGEFILES", "MAPFILES", "LMKFILES"):
        (root / d).mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(spec.seed)
    s = float(spec.scale_km)
    from spctool.geometry.frames import orient_frame

    ux, uy, uz = orient_frame(np.array([0.35, -0.2, 1.0]))  # SPC ORIENT
    v0 = spec.body_radius_km * uz
    ifov = 1.0 / (MMFL * math.sqrt(abs(KMAT[0, 0] * KMAT[1, 1])))
    # the mesh covers the photo footprint of the most oblique view (cells)
    half = 0.5 * spec.npx * spec.range_km * ifov / s / math.cos(math.radians(30.0)) + 10.0
    reach = 0.5 * (spec.n_side - 1) * spec.spacing_cells + spec.qsz + 30.0 * spec.range_km * ifov / s + 20.0
    half = min(half, reach)
    terrain = TruthTerrain(spec.seed, extent=half)
    loc, faces = _grid_mesh(terrain, half, spec.mesh_cells)
    body = v0 + s * (loc[:, :1] * ux + loc[:, 1:2] * uy + loc[:, 2:3] * uz)
    tracer = _Tracer((body - v0) * 1e3, faces, terrain.albedo(loc[:, 0], loc[:, 1]), spec.truth == "smooth")

    # ---- maplets from the truth mesh (GET_HEIGHTS) ---------------------------------------------------
    k = int(spec.n_side)
    offs = (np.arange(k) - (k - 1) / 2.0) * spec.spacing_cells
    gx, gy = np.meshgrid(offs, offs, indexing="ij")
    gx, gy = gx.ravel(), gy.ravel()
    centres = v0 + s * (gx[:, None] * ux + gy[:, None] * uy + terrain.height(gx, gy)[:, None] * uz)
    names = [f"IW{i:04d}" for i in range(len(gx))]
    surface = ShapeSurface.from_model(TriangleMesh(body, faces))  # spctool's own ray caster (GET_HEIGHTS)
    pairs = make_maplets(surface, names, centres, s, int(spec.qsz))
    n = 2 * int(spec.qsz) + 1
    t = np.arange(n, dtype=np.float64) - spec.qsz
    vs = []
    for (m, lmk), name in zip(pairs, names):
        node = m.v + s * (
            t[:, None, None] * m.ux + t[None, :, None] * m.uy + np.asarray(m.heights)[:, :, None] * m.uz
        )
        rel = (node - v0) / s
        alb = terrain.albedo(rel @ ux, rel @ uy)
        m2 = Maplet.new(s, int(spec.qsz), m.v, m.ux, m.uy, m.uz, m.heights, alb, m.valid, name=name)
        write_map(root / "MAPFILES" / f"{name}.MAP", m2)
        write_lmk(root / "LMKFILES" / f"{name}.LMK", lmk)
        vs.append(np.asarray(m.v, float))
    vs = np.array(vs)

    # ---- pictures ----------------------------------------------------------------------------------
    ctr = np.array([(spec.npx + 1) / 2.0, (spec.npx + 1) / 2.0])
    doc = {
        "format": "spctool-independent-world/1",
        "spec": spec.as_dict(),
        "renderer": "trimesh + embree ray casting (Lambert, cast shadows)",
        "landmarks": {nm: v.tolist() for nm, v in zip(names, vs)},
        "pictures": [],
    }
    pics = []
    for j, target in enumerate(spec.apriori_px):
        emission, azimuth, inc, saz = VIEWS[j]
        inc = inc if spec.sun_incidence_deg is None else float(spec.sun_incidence_deg)
        sun = _direction(ux, uy, uz, inc, saz)
        position = v0 + spec.range_km * _direction(ux, uy, uz, emission, azimuth)
        rot = _look_at(v0, position)
        scobj = -position
        rad = _photo(tracer, v0, rot, position, sun, spec, ctr)
        dn = spec.dn_bias + spec.dn_gain * rad + rng.normal(0.0, spec.noise_dn, rad.shape)
        dn = np.where(np.isfinite(rad), np.clip(np.rint(dn), 1, 65535), 0).astype(np.uint16)
        name = f"I{j + 1:09d}A1"
        write_photo(root / "IMAGEFILES" / f"{name}.DAT", dn, fmt="dat")
        a_scobj = scobj + rng.normal(0.0, spec.position_km, 3)
        a_rot = _apriori_rotation(rot, scobj, a_scobj, vs, ctr, target, ifov, rng)
        pic = Picture(
            name=name,
            utc="2026 NOV 25 12:00:00.000",
            npx=spec.npx,
            nln=spec.npx,
            thrsh=np.array([1.0, 65000.0]),
            mmfl=MMFL,
            ctr=ctr,
            scobj=a_scobj,
            cx=a_rot[0],
            cy=a_rot[1],
            cz=a_rot[2],
            sz=sun,
            kmatrix=KMAT,
            sigma_vso=np.full(3, spec.sigma_vso_km),
            sigma_ptg=np.full(3, spec.sigma_ptg_rad),
        )
        write_sum(root / "SUMFILES" / f"{name}.SUM", pic)
        pics.append(name)
        true_px = pinhole_project(vs, scobj, rot, ctr)
        apri_px = pinhole_project(vs, a_scobj, a_rot, ctr)
        doc["pictures"].append(
            {
                "name": name,
                "scobj": scobj.tolist(),
                "rotation": rot.tolist(),
                "sun": sun.tolist(),
                "apriori_px": float(np.max(np.linalg.norm(apri_px - true_px, axis=1))),
                "pixels": {nm: p.tolist() for nm, p in zip(names, true_px)},
            }
        )
    write_lithos(root / "INIT_LITHOS.TXT", parse_lithos("BODY= 'INDEP'\nMAPVERS= 0\nEND\n"))
    write_pictlist(root / "PICTLIST.TXT", PictureList([PictureListEntry(p) for p in pics]))
    write_lmrklist(root / "LMRKLIST.TXT", LandmarkList(names))
    (root / "TRUTH.json").write_text(json.dumps(doc, indent=1))
    return doc


def load_picture(root, pic_doc: dict):
    """One picture of a built world, read back through spctool's readers as a user's run would:
    ``(picture, camera, photo, landmark names, maplets, true pixels (N, 2))``; ``pic_doc`` is the
    picture's entry of TRUTH.json (``build_world``'s return value)."""
    from spctool.formats.workdir import WorkDir
    from spctool.geometry.camera import Camera

    wd = WorkDir(root)
    pic = wd.read_picture(pic_doc["name"])
    names = sorted(pic_doc["pixels"])
    return (
        pic,
        Camera.from_picture(pic, wd.read_settings()),
        wd.read_photo(pic.name, npx=pic.npx, nln=pic.nln),
        names,
        [wd.read_maplet(n) for n in names],
        np.array([pic_doc["pixels"][n] for n in names]),
    )


def navigate_picture(loaded, options):
    """Two-pass ``navigate`` of one picture read by :func:`load_picture` (``loaded``, its tuple) with
    ``options`` (:class:`~spctool.stages.navigate.NavigateOptions`) and the SUM's SIGMA_VSO/SIGMA_PTG
    as the prior, as ``spctool navigate`` runs it."""
    from spctool.stages.navigate import navigate

    pic, cam, photo, names, maplets, _ = loaded
    return navigate(
        photo,
        cam,
        pic.sz,
        maplets,
        tuple(pic.thrsh),
        options,
        names=names,
        prior_sigma_position=pic.sigma_vso,
        prior_sigma_attitude=pic.sigma_ptg,
    )
