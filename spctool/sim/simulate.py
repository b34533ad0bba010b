"""``spctool simulate``: a complete SPC working directory of a synthetic world, with its truth.

What S16 did with Gaskell's synthetic-surface codes and the Geomod renderer ("Simulation
environment"; spc-algorithms.md §12.2), done with spctool's own parts:

1. **Terrain** (:mod:`spctool.sim.terrain`): one procedural function of position — power-law craters
   and boulders, fBm roughness, albedo — split at a diameter/wavelength ``split_cells`` × the shape's
   cell size into a *coarse* band (in the global shape) and a *fine* band (only under the maplets).
2. **Global shape**: an ICQ model (spc-formats.md §5) of Q = ``body.q`` over an ellipsoid (or a given
   shape), every vertex moved radially by the coarse terrain, with the coarse albedo as the 4th
   column.  The shape used for the truth is the one written (``3F12.5`` rounding included).
3. **Landmarks**: placed where every picture sees them (or at given latitudes/longitudes); frames by
   SPC's ORIENT at the shape's fitted normal (:mod:`spctool.sim.maplets`).
4. **Truth patches** (S16: 3 mm truth under 1 cm maplets): around each landmark a height field
   ``truth_factor`` times finer than the maplet and ``margin`` maplet cells wider on every side:
   the shape projected onto the maplet plane (GET_HEIGHTS, spc-algorithms.md §2.2; the creases of
   its bilinear cells rounded by a Gaussian of σ = min(shape cell/2, margin/4)) plus the fine
   terrain, the rounding and the fine terrain tapered to zero over the outer half of the margin so
   the patch meets the shape without a step.  V is moved onto the truth surface (the truth height at
   the landmark is 0).
5. **Maplets** (S16: "down-sampled and smoothed"): each truth patch smoothed by a Gaussian of
   σ = ``smoothing_cells`` maplet cells and sampled at the maplet nodes, written as MAP (2021 writer
   layout, spc-formats.md §1) + LMK (§4.3) + LMRKLIST.TXT (§7.2).
6. **Photos**: rendered by :func:`spctool.stages.render.render` with the *true* pose — ray tracing
   of shape + truth patches with cast shadows, the photometric law of spc-algorithms.md §3.2, the
   terrain albedo painted on the shape, ``supersample``² rays per pixel — through the camera
   exactly as a reader of the written SUM + INIT_LITHOS reconstructs it (K-matrix, CTR and the
   ``DISTORT= … 'OWEN'`` model of spc-formats.md §6.4); then a detector: DN = signal + Gaussian
   shot and read noise, clipped to [1, 2^bits − 1] on the body; DN 0 is reserved for "no data"
   (sky) as SPC's sampler expects (spc-formats.md §7.4).
7. **Files**: SUMFILES/*.SUM (canonical layout of spc-formats.md §2.6) and NOMINALS/*.NOM (§3) with
   the *a-priori* pose (true pose perturbed by seeded Gaussian errors), SHAPEFILES/SHAPE.TXT,
   MAPFILES/, LMKFILES/, IMAGEFILES/ (``.DAT`` big-endian 16-bit, ``.FITS``, ``.PGM``, ``.PNG``),
   INIT_LITHOS.TXT (§6, with the ``DISTORT=`` entry), PICTLIST.TXT, LMRKLIST.TXT and ``TRUTH.json``.
   SUM ``LANDMARKS`` sections and LMK ``PICTURES`` sections are left empty (registration fills them).

TRUTH.json (``"format": "spctool-truth/1"``):

* ``pictures[]``: ``name``, ``photo`` (path in the workdir), ``true`` {``scobj``, ``rotation`` (rows
  CX, CY, CZ), ``position`` (= −SCOBJ), ``sz``}, ``apriori`` {``scobj``, ``rotation``, ``sz``} (what the
  SUM holds), ``camera`` {``mmfl``, ``ctr``, ``kmatrix``, ``npx``, ``nln``, ``model``, ``coefficients``},
  ``exposure_dn`` (DN of radiance 1), ``utc``;
* ``landmarks[]``: ``name``, ``vlm`` (true, km), ``vlm_written`` (LMK/MAP, differs by the optional
  landmark error), ``ux``, ``uy``, ``uz``, ``scale_km``, ``qsz``, ``truth_scale_km``, ``truth_qsz``, and
  ``pixels`` {picture: {``sample``, ``line`` (projection of the true VLM with the true camera incl.
  distortion, SPC 1-based pixels), ``in_image``, ``visible`` (first truth surface on the line of sight),
  ``shadowed`` (cast shadow at V), ``emission_deg``, ``incidence_deg``, ``phase_deg``}};
* ``seed``, ``spec`` (the resolved specification), ``spctool_version``, ``body`` (shape facts and the
  coarse/fine split).

All randomness comes from ``seed``; the output is reproducible bit for bit.

SPEC keys (TOML; every key optional — the defaults make a small, registration-friendly world)
--------------------------------------------------------------------------------------------
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from spctool import __version__
from spctool.errors import SpcUsageError
from spctool.formats.atomic import write_text
from spctool.formats.icq import IcqShape, format_icq, icq_cube_grid, parse_icq
from spctool.formats.landmark import write_lmk
from spctool.formats.lists import LandmarkList, PictureList, PictureListEntry, write_lmrklist, write_pictlist
from spctool.formats.lithos import DistortModel, Settings, format_lithos, parse_lithos
from spctool.formats.maplet import Maplet, write_map
from spctool.formats.nominal import Nominal, write_nom
from spctool.formats.photo import Photo, write_photo
from spctool.formats.sumfile import Picture, format_sum, parse_sum
from spctool.geometry.camera import Camera
from spctool.geometry.frames import apply_attitude_update, look_rotation, rot_from_rotvec
from spctool.geometry.surfaces import HeightPatch, ShapeSurface
from spctool.photometry import phase_angle_deg
from spctool.sim.maplets import landmark_frames, landmark_names, new_landmark, project_heights, surface_points
from spctool.sim.spec import Spec, check_memory, load_spec
from spctool.sim.spec_keys import PHOTO_SUFFIX, spec_help
from spctool.sim.terrain import AlbedoField, Boulders, Craters, Roughness, Terrain
from spctool.stages.render import RenderOptions, render, shadowed, trace

__all__ = [
    "Detector",
    "expose",
    "World",
    "LandmarkTruth",
    "PictureTruth",
    "build_world",
    "landmark_geometry",
    "simulate",
    "SimulationResult",
]

# the SPEC keys (one table, spctool.sim.spec_keys; read by spctool.sim.spec) in the docstring and --help
__doc__ = (__doc__ or "") + "\n::\n\n" + "\n".join("    " + ln for ln in spec_help(96).splitlines()) + "\n"


# ------------------------------------------------------------------------------------------------
# detector
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Detector:
    """DN model: g = full_well/DN_max electrons per DN; signal S = exposure·radiance·g electrons; noise
    n ~ N(0, read² + S) (S only with ``shot_noise``); DN = round((S + n)/g) clipped to [1, DN_max] on the
    body; sky (coverage 0) is DN 0, SPC's "no data" (spc-formats.md §7.4)."""

    bits: int = 16
    exposure: float | str = "auto"
    auto_level: float = 0.8
    full_well_electrons: float = 40000.0
    read_noise_electrons: float = 20.0
    shot_noise: bool = True

    def __post_init__(self):
        if self.bits not in (8, 16):
            raise SpcUsageError("detector bits must be 8 or 16")
        if not self.full_well_electrons > 0 or self.read_noise_electrons < 0:
            raise SpcUsageError("detector needs full_well_electrons > 0 and read_noise_electrons >= 0")
        if self.exposure != "auto" and not float(self.exposure) > 0:
            raise SpcUsageError("detector exposure must be 'auto' or > 0")

    @property
    def dn_max(self) -> int:
        return (1 << int(self.bits)) - 1

    @property
    def gain(self) -> float:
        """Electrons per DN."""
        return self.full_well_electrons / self.dn_max

    def exposure_for(self, radiance, mask) -> float:
        """DN per unit radiance: the given number, or 'auto' (99.5th percentile → auto_level·DN_max)."""
        if self.exposure != "auto":
            return float(self.exposure)
        vals = np.asarray(radiance)[np.asarray(mask, bool)]
        ref = float(np.percentile(vals, 99.5)) if vals.size else 0.0
        if not ref > 0:
            return 1.0
        return self.auto_level * self.dn_max / ref


def expose(radiance, coverage, detector: Detector, rng: np.random.Generator | None = None, exposure=None):
    """DN image (uint8/uint16) of a rendering and the exposure used (DN per unit radiance).

    ``rng`` None: no noise.  Pixels with ``coverage`` 0 are 0; every other pixel is ≥ 1.
    """
    radiance = np.asarray(radiance, float)
    mask = np.asarray(coverage) > 0
    expo = detector.exposure_for(radiance, mask) if exposure is None else float(exposure)
    g = detector.gain
    signal = radiance * expo * g  # electrons
    if rng is not None:
        var = detector.read_noise_electrons**2 + (np.maximum(signal, 0.0) if detector.shot_noise else 0.0)
        signal = signal + rng.standard_normal(signal.shape) * np.sqrt(var)
    dn = np.where(mask, np.clip(np.rint(signal / g), 1, detector.dn_max), 0)
    return dn.astype(np.uint8 if detector.bits == 8 else np.uint16), expo


# ------------------------------------------------------------------------------------------------
# geometry helpers
# ------------------------------------------------------------------------------------------------


def _latlon_dir(lat_deg, lon_deg) -> np.ndarray:
    lat = np.radians(np.asarray(lat_deg, float))
    lon = np.radians(np.asarray(lon_deg, float))
    return np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=-1)


def _rng(seed: int, purpose: int, index: int = 0) -> np.random.Generator:
    """Independent, reproducible streams per purpose (0 placement, 1 pose, 2 noise, 3 landmark, 4 sun)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(purpose), int(index)]))


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


# ------------------------------------------------------------------------------------------------
# the world
# ------------------------------------------------------------------------------------------------


@dataclass
class LandmarkTruth:
    """One landmark of a world: true frame, its truth patch and the maplet/LMK as written."""

    name: str
    v: np.ndarray
    ux: np.ndarray
    uy: np.ndarray
    uz: np.ndarray
    truth: HeightPatch
    maplet: Maplet
    landmark: object  # formats.landmark.Landmark (as written)


@dataclass
class PictureTruth:
    """One picture: the SUM/NOM as written (a-priori pose) and the true camera and Sun."""

    spec: SimpleNamespace
    picture: Picture  # a-priori, as parsed back from the written text
    nominal: Nominal
    camera: Camera  # true pose, intrinsics exactly as read back
    sun: np.ndarray  # true body→Sun unit vector
    detector: Detector


@dataclass
class World:
    """Everything :func:`simulate` writes, in memory (see :func:`build_world`)."""

    spec: Spec
    terrain: Terrain
    icq: IcqShape  # as written (and read back)
    surface: ShapeSurface
    shape_cell_km: float
    split_km: float
    settings: Settings
    pictures: list[PictureTruth]
    landmarks: list[LandmarkTruth]

    def albedo_fn(self, points):
        """The albedo painted on the shape where no truth patch is: every albedo-field wavelength, but only
        the features (craters, boulders) that the shape itself carries."""
        return self.terrain.albedo_at(points, (self.split_km, math.inf), fbm_band=(0.0, math.inf))

    @property
    def truth_patches(self) -> list[HeightPatch]:
        return [lm.truth for lm in self.landmarks]

    def render(self, k: int, *, window=None, options: RenderOptions | None = None):
        """The truth rendering of picture ``k`` (radiance, before the detector)."""
        p = self.pictures[k]
        d = self.spec.detector
        options = options or RenderOptions(
            photometry=d.photometry, supersample=d.supersample, shadows=d.shadows
        )
        return render(
            p.camera,
            p.sun,
            self.surface,
            self.truth_patches,
            options,
            window=window,
            albedo_fn=self.albedo_fn,
        )


def _terrain(spec: Spec) -> Terrain:
    return Terrain(
        seed=spec.seed,
        craters=Craters(**vars(spec.sections["terrain.craters"])),
        boulders=Boulders(**vars(spec.sections["terrain.boulders"])),
        roughness=Roughness(**vars(spec.sections["terrain.roughness"])),
        albedo=AlbedoField(**vars(spec.sections["terrain.albedo"])),
    )


def _reference_vertices(spec: Spec) -> np.ndarray:
    """(6, q+1, q+1, 3) reference surface at the ICQ directions: the ellipsoid or the given shape."""
    q = spec.body.q
    g = icq_cube_grid(q)
    d = g / np.linalg.norm(g, axis=-1, keepdims=True)
    if spec.body.shape:
        from spctool.formats.mesh import read_shape

        path = Path(spec.body.shape)
        if not path.is_absolute():
            path = spec.base / path
        if not path.is_file():
            raise SpcUsageError(f"{path}: reference shape file not found ([body] shape)")
        model = read_shape(path)
        pts = surface_points(model, d.reshape(-1, 3))
        if not np.all(np.isfinite(pts)):
            raise SpcUsageError(
                f"{path}: the reference shape is not star-shaped around the origin "
                "(some radial lines miss it)"
            )
        return pts.reshape(d.shape)
    a, b, c = spec.body.radii_km
    r = 1.0 / np.sqrt((d[..., 0] / a) ** 2 + (d[..., 1] / b) ** 2 + (d[..., 2] / c) ** 2)
    return d * r[..., None]


def _global_shape(spec: Spec, terrain: Terrain):
    ref = _reference_vertices(spec)
    radial = ref / np.linalg.norm(ref, axis=-1, keepdims=True)
    cell = float(np.mean(np.linalg.norm(ref[:, :, 1:] - ref[:, :, :-1], axis=-1)))
    split = spec.terrain.split_cells * cell
    h, _ = terrain.evaluate(ref, (split, math.inf), albedo=False)
    verts = ref + h[..., None] * radial
    _, alb = terrain.evaluate(verts, (split, math.inf), heights=False)
    text = format_icq(IcqShape(spec.body.q, verts, alb), style="spc")
    icq = parse_icq(text, "SHAPEFILES/SHAPE.TXT")  # exactly what a reader of the file gets
    return icq, text, cell, split


def _camera_constants(spec: Spec):
    c = spec.camera
    ctr = c.ctr if c.ctr else [(c.npx + 1) / 2.0, (c.nln + 1) / 2.0]
    return ctr


def _settings(spec: Spec) -> tuple[Settings, str]:
    c = spec.camera
    s = Settings()
    s.set("BODY", spec.body.name)
    s.set("MAPVERS", spec.maplets.mapvers)
    dist = c.distortion.strip().upper()
    if dist and dist != "NONE":
        coef = list(c.coefficients)
        template = c.template or "#" * 12
        s.distortions.append(DistortModel(template, dist, len(coef) - 1, coef))
    text = format_lithos(s)
    return parse_lithos(text, "INIT_LITHOS.TXT"), text


def _sum_text(pspec, spec: Spec, scobj, rot, sz, bits) -> Picture:
    c = spec.camera
    pert = spec.perturbation
    pic = Picture(
        name=pspec.name,
        utc=pspec.utc,
        npx=c.npx,
        nln=c.nln,
        thrsh=[1, (1 << bits) - 1],
        mmfl=c.mmfl,
        ctr=_camera_constants(spec),
        scobj=scobj,
        cx=rot[0],
        cy=rot[1],
        cz=rot[2],
        sz=sz,
        kmatrix=c.kmatrix,
        sigma_vso=np.full(3, max(pert.position_sigma_km, 0.0)),
        sigma_ptg=np.full(3, math.radians(max(pert.attitude_sigma_deg, 0.0))),
    )
    return parse_sum(format_sum(pic), f"SUMFILES/{pspec.name}.SUM")


def _place_landmarks(spec: Spec, surface: ShapeSurface, cams, suns, names_needed: int, rng) -> np.ndarray:
    """Automatic placement: surface points seen well by every picture, at least min_separation apart."""
    m = spec.maplets
    ncand = 6000
    from spctool.sim.maplets import tile_directions

    d = tile_directions(ncand)
    lo, hi = surface.shape.bounding_box
    far = 2.0 * float(np.max(np.abs(np.concatenate([lo, hi])))) + 1.0
    res = surface.shape.first_hit(d * far, -d, t_max=2 * far)
    ok = res.hit.copy()
    pts = np.where(ok[:, None], res.point, 0.0)
    nrm = np.zeros_like(pts)
    nrm[ok] = surface.normals(res.index[ok], res.u[ok], res.v[ok])
    half_diag = math.sqrt(2.0) * (m.qsz + 0.5) * m.scale_km
    cos_e = math.cos(math.radians(m.max_emission_deg))
    cos_i = math.cos(math.radians(m.max_incidence_deg))
    for cam, sun in zip(cams, suns):
        smp, lin, front = cam.project_with_mask(pts)
        res_km = cam.resolution(pts)
        margin = m.edge_margin_px + half_diag / np.where(res_km > 0, res_km, np.inf)
        inside = (
            front
            & (smp >= 1 + margin)
            & (smp <= cam.npx - margin)
            & (lin >= 1 + margin)
            & (lin <= cam.nln - margin)
        )
        los = cam.position - pts
        los /= np.linalg.norm(los, axis=1, keepdims=True)
        ok &= inside & (np.sum(nrm * los, axis=1) >= cos_e) & (nrm @ sun >= cos_i)
        idx = np.flatnonzero(ok)
        if idx.size:
            vis = surface.shape.visible_from(cam.position, pts[idx], tol_km=2.0 * m.scale_km * m.qsz)
            ok[idx[~vis]] = False
    cand = np.flatnonzero(ok)
    order = cand[rng.permutation(cand.size)]
    sep = m.min_separation_km or 2.0 * (m.qsz + m.margin) * m.scale_km
    chosen: list[int] = []
    for k in order:
        if all(np.linalg.norm(pts[k] - pts[j]) >= sep for j in chosen):
            chosen.append(int(k))
            if len(chosen) == names_needed:
                break
    if len(chosen) < names_needed:
        raise SpcUsageError(
            f"automatic landmark placement found room for {len(chosen)} of {names_needed} landmarks seen by "
            "every picture; lower [maplets] count or min_separation_km, relax max_emission_deg / "
            "max_incidence_deg, or give positions"
        )
    return pts[chosen]


def _truth_and_maplets(
    spec: Spec, terrain: Terrain, surface: ShapeSurface, split: float, shape_cell: float, names, centres, rng
):
    m = spec.maplets
    k = m.truth_factor
    st = m.scale_km / k
    qt = k * (m.qsz + m.margin)
    v0, ux, uy, uz = landmark_frames(surface, centres, m.scale_km, m.qsz)
    n = 2 * qt + 1
    # the coarse part: the shape projected onto the patch plane (GET_HEIGHTS), with the creases of its
    # bilinear cells rounded by a Gaussian of sigma = min(shape cell / 2, margin / 4) inside the patch
    # (projected over a grid padded by 3 sigma, so the filter sees real shape at the patch edges)
    sig_t = min(0.5 * shape_cell, 0.25 * m.margin * m.scale_km) / st
    pad = int(math.ceil(3.0 * sig_t))
    ph = project_heights(surface, v0, ux, uy, uz, st, qt + pad, points=False)
    if not ph.valid.all():
        bad = [names[i] for i in range(len(names)) if not ph.valid[i].all()]
        raise SpcUsageError(f"the shape does not lie under the whole truth patch of {', '.join(bad)}")
    from scipy.ndimage import gaussian_filter

    xm = (np.arange(n) - qt) / k  # node offsets in maplet cells
    rho = np.maximum(np.abs(xm)[:, None], np.abs(xm)[None, :])
    inner = m.qsz + 0.5 * m.margin
    outer = m.qsz + m.margin
    # taper: 1 up to qsz + margin/2 maplet cells, 0 at the patch edge (where the patch meets the shape)
    w = 1.0 - _smoothstep((rho - inner) / max(outer - inner, 1e-12)) if outer > inner else np.ones((n, n))
    inside = slice(pad, pad + n)
    coarse = np.empty((len(names), n, n))
    for i in range(len(names)):
        raw = ph.heights[i][inside, inside]
        smooth = gaussian_filter(ph.heights[i], sig_t, mode="nearest")[inside, inside] if sig_t > 0 else raw
        coarse[i] = raw + w * (smooth - raw)
    off = (np.arange(n) - qt) * st
    pts = (
        v0[:, None, None, :]
        + off[None, :, None, None] * ux[:, None, None, :]
        + off[None, None, :, None] * uy[:, None, None, :]
        + (coarse * st)[..., None] * uz[:, None, None, :]
    )
    pts = pts.reshape(-1, 3)
    fine, _ = terrain.evaluate(pts, (0.0, split), albedo=False)
    alb_full = terrain.albedo_at(pts).reshape(-1, n, n)
    alb_shape = terrain.albedo_at(pts, (split, math.inf), fbm_band=(0.0, math.inf)).reshape(-1, n, n)
    fine = fine.reshape(-1, n, n)
    # the albedo of the fine features fades out with the same taper (the shape around carries none)
    alb = alb_shape + w * (alb_full - alb_shape)
    out = []
    for i, name in enumerate(names):
        ht = coarse[i] + w * fine[i] / st
        c = ht[qt, qt]
        v = v0[i] + c * st * uz[i]
        ht = ht - c
        truth = HeightPatch(ht, st, v, ux[i], uy[i], uz[i], albedo=alb[i], name=name)
        sig = m.smoothing_cells * k
        hs = gaussian_filter(ht, sig, mode="nearest") if sig > 0 else ht
        as_ = gaussian_filter(alb[i], sig, mode="nearest") if sig > 0 else alb[i]
        sl = slice(k * m.margin, k * m.margin + k * (2 * m.qsz) + 1, k)
        hm = hs[sl, sl] * (st / m.scale_km)
        am = as_[sl, sl]
        vw = v.copy()
        if m.landmark_sigma_km > 0:
            vw = v + rng.standard_normal(3) * m.landmark_sigma_km
        maplet = Maplet.new(
            m.scale_km,
            m.qsz,
            vw,
            ux[i],
            uy[i],
            uz[i],
            hm,
            am,
            np.ones_like(hm, bool),
            mapvers=m.mapvers,
            sigma=np.full(3, m.scale_km),
            name=name,
        )
        lmk = new_landmark(name, m.scale_km, m.qsz, vw, ux[i], uy[i], uz[i])
        out.append(LandmarkTruth(name, v, ux[i].copy(), uy[i].copy(), uz[i].copy(), truth, maplet, lmk))
    return out


def build_world(spec: Spec, progress=None, max_memory: int | None = None) -> World:
    """Build a world in memory (no files): shape, cameras, landmarks, truth patches, maplets.
    Refused before anything is allocated when :func:`spctool.sim.spec.memory_estimate` exceeds ``max_memory``
    (default: half the physical memory)."""
    check_memory(spec, max_memory)
    say = progress or (lambda msg: None)
    terrain = _terrain(spec)
    say("global shape")
    icq, _, cell, split = _global_shape(spec, terrain)
    surface = ShapeSurface.from_model(icq)
    settings, _ = _settings(spec)
    pert = spec.perturbation
    # true poses and Sun
    aims = surface_points(
        surface, _latlon_dir([p.aim_lat_deg for p in spec.pictures], [p.aim_lon_deg for p in spec.pictures])
    )
    if not np.all(np.isfinite(aims)):
        raise SpcUsageError("a picture's aim point is not on the shape")
    pictures = []
    cams_true = []
    suns = []
    for i, ps in enumerate(spec.pictures):
        pos = aims[i] + ps.range_km * _latlon_dir(ps.view_lat_deg, ps.view_lon_deg)
        rot = look_rotation(pos, aims[i], ps.roll_deg)
        sun = _latlon_dir(ps.sun_lat_deg, ps.sun_lon_deg)
        rng = _rng(spec.seed, 1, i)
        pos_ap = pos + rng.standard_normal(3) * pert.position_sigma_km
        rot_ap = apply_attitude_update(rot, rng.standard_normal(3) * math.radians(pert.attitude_sigma_deg))
        sun_ap = sun
        if pert.sun_sigma_deg > 0:
            sun_ap = (
                rot_from_rotvec(_rng(spec.seed, 4, i).standard_normal(3) * math.radians(pert.sun_sigma_deg))
                @ sun
            )
        pic = _sum_text(ps, spec, -pos_ap, rot_ap, sun_ap, ps.bits)
        cam = Camera.from_picture(pic, settings).with_pose(scobj=-pos, rotation=rot)
        nom = Nominal(
            name=ps.name,
            frame_vector=[0.0, 0.0, 1.0],
            frame_tag="BOD_FRAME",
            scobj=pic.scobj,
            sigma_vso=pic.sigma_vso,
            cx=pic.cx,
            cy=pic.cy,
            cz=pic.cz,
            sigma_ptg=pic.sigma_ptg,
        )
        d = spec.detector
        det = Detector(
            bits=ps.bits,
            exposure=d.exposure,
            auto_level=d.auto_level,
            full_well_electrons=d.full_well_electrons,
            read_noise_electrons=d.read_noise_electrons,
            shot_noise=d.shot_noise,
        )
        pictures.append(PictureTruth(ps, pic, nom, cam, sun, det))
        cams_true.append(cam)
        suns.append(sun)
    # landmarks
    m = spec.maplets
    count = spec.landmark_count
    names = list(m.names) if m.names else landmark_names(m.prefix, count)
    if len(names) != count:
        raise SpcUsageError(f"[maplets] names gives {len(names)} names for {count} landmarks")
    if count == 0:  # a world without landmarks: just the shape and the photos
        return World(spec, terrain, icq, surface, cell, split, settings, pictures, [])
    say("landmarks")
    if m.positions:
        centres = surface_points(
            surface, _latlon_dir([a for a, _ in m.positions], [b for _, b in m.positions])
        )
        if not np.all(np.isfinite(centres)):
            raise SpcUsageError("a landmark position is not on the shape")
    else:
        centres = _place_landmarks(spec, surface, cams_true, suns, count, _rng(spec.seed, 0))
    say("truth patches and maplets")
    landmarks = _truth_and_maplets(spec, terrain, surface, split, cell, names, centres, _rng(spec.seed, 3))
    return World(spec, terrain, icq, surface, cell, split, settings, pictures, landmarks)


# ------------------------------------------------------------------------------------------------
# writing a working directory
# ------------------------------------------------------------------------------------------------


@dataclass
class SimulationResult:
    """What :func:`simulate` wrote: the working directory, its files and the truth document."""

    outdir: Path
    files: list[Path]
    truth: dict
    world: World


def _vec(a) -> list[float]:
    return [float(x) for x in np.asarray(a, float).reshape(-1)]


def landmark_geometry(world: World, k: int) -> dict:
    """Truth pixels and geometry of every landmark in picture ``k`` (the TRUTH.json ``pixels`` rows)."""
    p = world.pictures[k]
    cam = p.camera
    if not world.landmarks:
        return {}
    v = np.array([lm.v for lm in world.landmarks])
    uz = np.array([lm.uz for lm in world.landmarks])
    smp, lin, front = cam.project_with_mask(v)
    inside = front & cam.in_image(smp, lin)
    e = cam.position - v
    rng_km = np.linalg.norm(e, axis=1)
    e /= rng_km[:, None]
    # visibility: the first truth surface on the camera→V line of sight is V itself
    dirs = -e
    hits = trace(np.broadcast_to(cam.position, v.shape), dirs, world.surface, world.truth_patches)
    tol = 0.5 * world.spec.maplets.scale_km
    visible = hits.hit & (np.abs(hits.t - rng_km) <= tol)
    # cast shadow at V: a hit record located at V on its own patch
    from spctool.stages.render import SurfaceHits

    local = np.zeros((v.shape[0], 3))
    sh_hits = SurfaceHits(np.arange(v.shape[0], dtype=np.int32), rng_km, v, uz, np.ones(v.shape[0]), local)
    shadow = shadowed(sh_hits, p.sun, world.surface, world.truth_patches)
    out = {}
    for i, lm in enumerate(world.landmarks):
        out[lm.name] = {
            "sample": float(smp[i]),
            "line": float(lin[i]),
            "in_image": bool(inside[i]),
            "visible": bool(visible[i]),
            "shadowed": bool(shadow[i]),
            "emission_deg": float(np.degrees(np.arccos(np.clip(uz[i] @ e[i], -1, 1)))),
            "incidence_deg": float(np.degrees(np.arccos(np.clip(uz[i] @ p.sun, -1, 1)))),
            "phase_deg": float(phase_angle_deg(p.sun, e[i])),
        }
    return out


def _truth_document(world: World, exposures: list[float], photo_paths: list[str]) -> dict:
    spec = world.spec
    pics = []
    for k, p in enumerate(world.pictures):
        cam = p.camera
        pics.append(
            {
                "name": p.spec.name,
                "photo": photo_paths[k],
                "utc": p.spec.utc,
                "true": {
                    "scobj": _vec(cam.scobj),
                    "rotation": [_vec(r) for r in cam.rotation],
                    "position": _vec(cam.position),
                    "sz": _vec(p.sun),
                },
                "apriori": {
                    "scobj": _vec(p.picture.scobj),
                    "rotation": [_vec(r) for r in p.picture.rotation],
                    "sz": _vec(p.picture.sz),
                },
                "camera": {
                    "mmfl": cam.mmfl,
                    "ctr": _vec(cam.ctr),
                    "kmatrix": [_vec(r) for r in cam.kmatrix],
                    "npx": cam.npx,
                    "nln": cam.nln,
                    "model": cam.model,
                    "coefficients": _vec(cam.coefficients),
                },
                "exposure_dn": float(exposures[k]),
                "bits": p.detector.bits,
            }
        )
    geo = [landmark_geometry(world, k) for k in range(len(world.pictures))]
    lms = []
    for lm in world.landmarks:
        lms.append(
            {
                "name": lm.name,
                "vlm": _vec(lm.v),
                "vlm_written": _vec(lm.landmark.vlm),
                "ux": _vec(lm.ux),
                "uy": _vec(lm.uy),
                "uz": _vec(lm.uz),
                "scale_km": spec.maplets.scale_km,
                "qsz": spec.maplets.qsz,
                "truth_scale_km": lm.truth.scale,
                "truth_qsz": lm.truth.qsz,
                "pixels": {p.spec.name: geo[k][lm.name] for k, p in enumerate(world.pictures)},
            }
        )
    return {
        "format": "spctool-truth/1",
        "spctool_version": __version__,
        "seed": spec.seed,
        "body": {
            "shape": "SHAPEFILES/SHAPE.TXT",
            "q": spec.body.q,
            "shape_cell_km": world.shape_cell_km,
            "split_km": world.split_km,
        },
        "pictures": pics,
        "landmarks": lms,
        "spec": spec.to_dict(),
    }


def simulate(
    spec: Spec | str | Path, outdir, *, overwrite: bool = False, progress=None, max_memory: int | None = None
) -> SimulationResult:
    """Build the world of ``spec`` and write the SPC working directory ``outdir`` (module docstring).

    Refuses a non-empty ``outdir`` unless ``overwrite``, and a world whose
    :func:`spctool.sim.spec.memory_estimate` exceeds ``max_memory`` bytes (default: half the physical
    memory) before allocating anything.
    """
    if not isinstance(spec, Spec):
        spec = load_spec(spec)
    say = progress or (lambda msg: None)
    out = Path(outdir)
    if out.exists() and not out.is_dir():
        raise SpcUsageError(f"{out}: exists and is not a directory")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise SpcUsageError(f"{out}: directory is not empty (use --overwrite to replace its files)")
    world = build_world(spec, say, max_memory=max_memory)
    files: list[Path] = []

    def put_text(rel, text):
        path = out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        write_text(path, text)
        files.append(path)

    out.mkdir(parents=True, exist_ok=True)
    put_text("SHAPEFILES/SHAPE.TXT", format_icq(world.icq, style="spc"))
    put_text("INIT_LITHOS.TXT", format_lithos(world.settings))
    for lm in world.landmarks:
        for folder in ("MAPFILES", "LMKFILES"):
            (out / folder).mkdir(parents=True, exist_ok=True)
        write_map(out / "MAPFILES" / f"{lm.name}.MAP", lm.maplet)
        write_lmk(out / "LMKFILES" / f"{lm.name}.LMK", lm.landmark)
        files += [out / "MAPFILES" / f"{lm.name}.MAP", out / "LMKFILES" / f"{lm.name}.LMK"]
        if spec.maplets.write_truth:
            (out / "TRUTHFILES").mkdir(parents=True, exist_ok=True)
            t = lm.truth
            tm = Maplet.new(
                t.scale,
                t.qsz,
                t.v,
                t.ux,
                t.uy,
                t.uz,
                t.heights,
                t.albedo,
                t.valid,
                sigma=np.full(3, t.scale),
                name=lm.name,
            )
            write_map(out / "TRUTHFILES" / f"{lm.name}.MAP", tm)
            files.append(out / "TRUTHFILES" / f"{lm.name}.MAP")
    (out / "LMRKLIST.TXT").parent.mkdir(parents=True, exist_ok=True)
    write_lmrklist(out / "LMRKLIST.TXT", LandmarkList([lm.name for lm in world.landmarks]))
    files.append(out / "LMRKLIST.TXT")
    exposures = []
    photo_paths = []
    for k, p in enumerate(world.pictures):
        say(f"render {p.spec.name}")
        put_text(f"SUMFILES/{p.spec.name}.SUM", format_sum(p.picture))
        (out / "NOMINALS").mkdir(parents=True, exist_ok=True)
        write_nom(out / "NOMINALS" / f"{p.spec.name}.NOM", p.nominal)
        files.append(out / "NOMINALS" / f"{p.spec.name}.NOM")
        rendering = world.render(k)
        dn, expo = expose(rendering.radiance, rendering.coverage, p.detector, _rng(spec.seed, 2, k))
        exposures.append(expo)
        rel = f"IMAGEFILES/{p.spec.name}{PHOTO_SUFFIX[p.spec.format]}"
        photo_paths.append(rel)
        header = None
        if p.spec.format == "fits":
            header = {
                "PICTURE": (p.spec.name, "SPC picture name"),
                "ORIGIN": ("spctool simulate", "synthetic"),
            }
        (out / "IMAGEFILES").mkdir(parents=True, exist_ok=True)
        write_photo(out / rel, Photo(dn, name=p.spec.name), fmt=p.spec.format, header=header)
        files.append(out / rel)
    write_pictlist(out / "PICTLIST.TXT", PictureList([PictureListEntry(p.spec.name) for p in world.pictures]))
    files.append(out / "PICTLIST.TXT")
    say("truth")
    truth = _truth_document(world, exposures, photo_paths)
    put_text("TRUTH.json", json.dumps(truth, indent=1) + "\n")
    return SimulationResult(out, files, truth, world)
