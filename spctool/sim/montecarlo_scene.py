"""The Monte Carlo study's scenes: one photo with its truth pixels and the onboard maplets.

Specification: spc-algorithms.md §12.2 (the S16 reproduction's scene); S16 "Performance
characterization".  A scene is what :func:`spctool.sim.montecarlo.run` perturbs and registers: the
``s16-50m`` preset (:func:`s16_scene`), a picture of an SPC working directory
(:func:`scene_from_workdir`) or a saved scene (:func:`save_scene`, :func:`load_scene`).

The ``s16-50m`` preset (:func:`s16_scene`)
------------------------------------------
S16's camera (Table 1: 2592 × 1944 px of 2.2 µm, f = 7.68 mm, K = ±454.54 px/mm, principal point
(1296.5, 972.5), a zero OWEN model), one picture at 50 m range looking down at a ~0.4 km body (2008 EV5
is ~0.4 km), twelve landmarks named as in S16 Fig. 6 on a jittered 4 × 3 grid over the field of view,
99 × 99 maplets of 1 cm derived (Gaussian σ = 0.5 cell, down-sampled) from 3.33 mm truth patches, terrain
of power-law boulders and craters (2 cm … 0.3 m) with cm-scale roughness and albedo in truth patches
reaching 40 cells beyond each maplet (beyond them the surface is the smooth shape with the albedo field
only: a simulate world carries sub-shape-cell relief only in its truth patches).  The world is built
by :func:`spctool.sim.simulate.build_world` (:func:`s16_spec` is its SPEC) and rendered by the same
renderer with cast shadows and detector noise — but only in a window around each landmark that is
large enough for every search (:func:`scene_window_half`): pixels outside are DN 0, SPC's "no data".
The onboard maplets are the MAP files exactly as written (heights quantised by the MAP encoding).
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spctool import __version__
from spctool.errors import SpcUsageError
from spctool.sim.montecarlo import _NOISE, _PARAM, _SEED_TAG, S16_LANDMARKS

__all__ = [
    "Knowledge",
    "Scene",
    "S16_PICTURE",
    "S16_POSITIONS",
    "s16_spec",
    "s16_scene",
    "scene_from_workdir",
    "scene_window_half",
    "save_scene",
    "load_scene",
]



@dataclass
class Knowledge:
    """A maplet as the registration knows it (any object with these fields is accepted by register)."""

    name: str
    heights: np.ndarray  #: (2q+1)² in cells (SCALE units), axis 0 along UX
    albedo: np.ndarray
    valid: np.ndarray
    scale: float  #: km per cell
    v: np.ndarray
    ux: np.ndarray
    uy: np.ndarray
    uz: np.ndarray

    @property
    def qsz(self) -> int:
        return (self.heights.shape[0] - 1) // 2

    @classmethod
    def from_maplet(cls, m, name: str | None = None) -> Knowledge:
        return cls(
            name=str(name if name is not None else getattr(m, "name", "")),
            heights=np.array(m.heights, dtype=np.float64),
            albedo=np.array(m.albedo, dtype=np.float64),
            valid=np.array(m.valid, dtype=bool),
            scale=float(m.scale),
            v=np.array(m.v, dtype=np.float64),
            ux=np.array(m.ux, dtype=np.float64),
            uy=np.array(m.uy, dtype=np.float64),
            uz=np.array(m.uz, dtype=np.float64),
        )


@dataclass
class Scene:
    """One epoch of the study: the truth photo, the true camera and Sun, the onboard maplets and the
    true landmark positions.  ``truth`` (N, 2) is the projection of ``true_v`` with ``camera``."""

    picture: str
    photo: np.ndarray  #: float64 DN, data[line − 1, sample − 1]; 0 = no data
    thresholds: tuple
    camera: object  #: the true camera (spctool.geometry.camera.Camera)
    sun: np.ndarray  #: true body→Sun unit vector
    maplets: list  #: Knowledge per landmark (the unperturbed onboard maplets)
    true_v: np.ndarray  #: (N, 3) true landmark positions (km)
    info: dict = field(default_factory=dict)
    truth: np.ndarray = field(init=False)

    def __post_init__(self):
        self.photo = np.ascontiguousarray(self.photo, dtype=np.float64)
        self.sun = np.asarray(self.sun, dtype=np.float64) / float(np.linalg.norm(self.sun))
        self.true_v = np.asarray(self.true_v, dtype=np.float64).reshape(-1, 3)
        if len(self.maplets) != self.true_v.shape[0]:
            raise SpcUsageError("a scene needs one true position per maplet")
        self.thresholds = tuple(float(t) for t in self.thresholds)
        s, ln = self.camera.project(self.true_v)
        self.truth = np.stack([np.asarray(s, float), np.asarray(ln, float)], axis=-1).reshape(-1, 2)

    @property
    def names(self) -> list[str]:
        return [m.name for m in self.maplets]

    def __len__(self):
        return len(self.maplets)

    def subset(self, names) -> Scene:
        """The scene restricted to the named landmarks (in the order given)."""
        index = {n: i for i, n in enumerate(self.names)}
        missing = [n for n in names if n not in index]
        if missing:
            raise SpcUsageError(
                f"landmark(s) not in the scene: {', '.join(missing)} (have {', '.join(index)})"
            )
        sel = [index[n] for n in names]
        out = dataclasses.replace(self, maplets=[self.maplets[i] for i in sel], true_v=self.true_v[sel])
        return out


# -- the s16-50m preset ------------------------------------------------------------------------

#: landmark sites of the preset (planetocentric lat, lon in degrees): a jittered 4 × 3 grid of pixels
#: over the 50 m view (rows of S16 Fig. 6's spread), fixed once so the world never moves
S16_POSITIONS = (
    (12.8428, 24.0297), (12.4642, 21.3772), (12.2721, 18.9513), (12.2383, 16.1446),
    (9.8743, 23.8755), (10.2122, 21.6131), (10.0647, 18.474), (10.1171, 15.8963),
    (7.1145, 24.1939), (7.5941, 21.0907), (7.4466, 18.9292), (7.5158, 16.0501),
)  # fmt: skip

S16_PICTURE = "S16A0050M001"


def s16_spec(seed: int = 16, *, exact_maplets: bool = False) -> dict:
    """The SPEC (:func:`spctool.sim.spec.parse_spec` mapping) of the ``s16-50m`` world.

    Camera: S16 Table 1 with a zero OWEN model (nominal ε = 0, checklist §12.1).  Body: a 0.42 × 0.40 ×
    0.37 km ellipsoid (2008 EV5's size), ICQ Q = 64.  Terrain at the maplet scale (the fine band, only
    in the truth patches; the shape stays smooth): boulders 2 cm … 0.3 m (N(>D) ∝ D^−2.5), craters
    4 cm … 0.3 m (∝ D^−2), fBm roughness and albedo from 1 cm to 0.3 m.  Maplets: 99 × 99 of 1 cm
    (QSZ 49) from 3.33 mm truth (truth_factor 3) with a 40-cell margin of truth around each, so that
    extractions far off the maplet still see real terrain.  One picture at 50 m along the local
    vertical of (10°, 20°), Sun 45° from the vertical.  No a-priori errors in the SUM: the study
    perturbs its own knowledge.

    ``exact_maplets``: the control world — truth at the maplet's own 1 cm (truth_factor 1, no smoothing),
    so the onboard maplets are the surface that rendered the photo (up to the MAP encoding's
    quantisation).  Whatever error remains at zero perturbation there belongs to the registration, not
    to the preset's 3.33 mm → 1 cm loss of detail.
    """
    truth_factor, smoothing = (1, 0.0) if exact_maplets else (3, 0.5)
    return {
        "seed": int(seed),
        "body": {"name": "EV5SYNTH", "radii_km": [0.21, 0.2, 0.185], "q": 64},
        "terrain": {
            "split_cells": 4.0,
            "craters": {
                "coefficient": 0.05,
                "slope": 2.0,
                "min_diameter_km": 4e-5,
                "max_diameter_km": 3e-4,
                "depth_ratio": 0.2,
                "rim_ratio": 0.04,
                "albedo": 0.06,
            },
            "boulders": {
                "coefficient": 5e-5,
                "slope": 2.5,
                "min_diameter_km": 2e-5,
                "max_diameter_km": 3e-4,
                "height_ratio": 0.5,
                "albedo_spread": 0.15,
            },
            "roughness": {
                "amplitude_km": 1.5e-5,
                "hurst": 0.8,
                "min_wavelength_km": 1e-5,
                "max_wavelength_km": 3e-4,
            },
            "albedo": {
                "contrast": 0.1,
                "hurst": 0.5,
                "min_wavelength_km": 1e-5,
                "max_wavelength_km": 3e-4,
                "min": 0.05,
                "max": 1.95,
            },
        },
        "maplets": {
            "names": list(S16_LANDMARKS),
            "positions": [list(p) for p in S16_POSITIONS],
            "scale_km": 1e-5,
            "qsz": 49,
            "truth_factor": truth_factor,
            "margin": 40,
            "smoothing_cells": smoothing,
        },
        "camera": {
            "npx": 2592,
            "nln": 1944,
            "mmfl": 7.68,
            "kmatrix": [[454.54, 0.0, 0.0], [0.0, -454.54, 0.0]],
            "distortion": "OWEN",
            "coefficients": [0.0] * 7,
        },
        "detector": {"bits": 16, "supersample": 2, "shadows": True, "photometry": "spc"},
        "perturbation": {"position_sigma_km": 0.0, "attitude_sigma_deg": 0.0, "sun_sigma_deg": 0.0},
        "pictures": [
            {
                "name": S16_PICTURE,
                "aim_lat_deg": 10.0,
                "aim_lon_deg": 20.0,
                "range_km": 0.05,
                "sun_lat_deg": 45.0,
                "sun_lon_deg": 45.0,
                "format": "dat",
            }
        ],
    }


def scene_window_half(
    camera, maplet, sigma_scale: float = 1.0, grid_half: int = 5, max_spacing: int = 10
) -> int:
    """Half side (px) of the photo window rendered around a landmark: the maplet's projected half
    diagonal, plus 5σ of the a-priori pixel error from Table 2's pose sigmas, plus the largest search
    ((k + 1)·L_max pixels or cells, whichever is larger in pixels)."""
    v = np.asarray(maplet.v, float)
    rng_km = float(np.linalg.norm(camera.position - v))
    px_km = rng_km * camera.ifov  # km per pixel at the landmark
    half_diag = math.sqrt(2.0) * (maplet.qsz + 0.5) * maplet.scale / px_km
    sig_pos = _PARAM["position"].sigma[0] / px_km
    sig_att = math.radians(_PARAM["attitude"].sigma[0]) / camera.ifov
    apriori = 5.0 * math.hypot(sig_pos, sig_att) * max(sigma_scale, 1.0)
    search = (grid_half + 1) * max_spacing * max(1.0, maplet.scale / px_km)
    return int(math.ceil(half_diag + apriori + search))


def s16_scene(
    seed: int = 16, *, window_half: int | None = None, progress=None, exact_maplets: bool = False
) -> Scene:
    """Build the ``s16-50m`` scene (module docstring): world of :func:`s16_spec`, truth photo rendered in
    a window of ``window_half`` px (default :func:`scene_window_half`) around every landmark, detector
    noise from the world's seed, onboard maplets as written to MAP files (``exact_maplets``: the
    control world of :func:`s16_spec`)."""
    from spctool.formats.maplet import format_map, parse_map
    from spctool.sim.simulate import build_world, expose
    from spctool.sim.spec import parse_spec

    say = progress or (lambda msg: None)
    spec = parse_spec(s16_spec(seed, exact_maplets=exact_maplets), where="preset s16-50m")
    world = build_world(spec, say)
    pic = world.pictures[0]
    cam = pic.camera
    maplets = []
    for lm in world.landmarks:
        written = parse_map(format_map(lm.maplet), f"MAPFILES/{lm.name}.MAP", name=lm.name)
        maplets.append(Knowledge.from_maplet(written, lm.name))
    true_v = np.array([lm.v for lm in world.landmarks])
    radiance = np.zeros((cam.nln, cam.npx))
    coverage = np.zeros((cam.nln, cam.npx))
    s, ln = cam.project(true_v)
    for i, lm in enumerate(world.landmarks):
        say(f"render {lm.name}")
        h = window_half if window_half is not None else scene_window_half(cam, maplets[i])
        s0, s1 = max(1, int(round(s[i])) - h), min(cam.npx, int(round(s[i])) + h)
        l0, l1 = max(1, int(round(ln[i])) - h), min(cam.nln, int(round(ln[i])) + h)
        if s0 > s1 or l0 > l1:
            continue
        r = world.render(0, window=(s0, s1, l0, l1))
        radiance[l0 - 1 : l1, s0 - 1 : s1] = r.radiance
        coverage[l0 - 1 : l1, s0 - 1 : s1] = r.coverage
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _SEED_TAG, _NOISE, 0]))
    dn, exposure = expose(radiance, coverage, pic.detector, rng)
    info = {
        "preset": "s16-50m",
        "world_seed": int(seed),
        "exact_maplets": bool(exact_maplets),
        "spec": spec.to_dict(),
        "exposure_dn": float(exposure),
        "window_half_px": window_half,
        "range_km": float(np.linalg.norm(cam.position - true_v.mean(axis=0))),
    }
    return Scene(
        picture=pic.spec.name,
        photo=dn.astype(np.float64),
        thresholds=tuple(float(t) for t in pic.picture.thrsh),
        camera=cam,
        sun=pic.sun,
        maplets=maplets,
        true_v=true_v,
        info=info,
    )


def scene_from_workdir(workdir, picture: str | None = None, names=None) -> Scene:
    """A scene from a working directory written by ``spctool simulate`` (it needs TRUTH.json).

    The true camera is the SUM's camera (intrinsics and INIT_LITHOS distortion as SPC reads them) with
    the true pose of TRUTH.json; the Sun is the true one; the maplets are MAPFILES/ as written; the
    landmarks default to those TRUTH.json marks as in the photo and visible.
    """
    from spctool.formats.workdir import WorkDir
    from spctool.geometry.camera import Camera

    wd = WorkDir(Path(workdir))
    tpath = Path(workdir) / "TRUTH.json"
    try:
        truth = json.loads(tpath.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SpcUsageError(
            f"{tpath}: not found (montecarlo needs a world made by 'spctool simulate')"
        ) from None
    except json.JSONDecodeError as exc:
        raise SpcUsageError(f"{tpath}: not valid JSON ({exc})") from None
    pics = {p["name"]: p for p in truth.get("pictures", [])}
    if not pics:
        raise SpcUsageError(f"{tpath}: no pictures")
    name = picture if picture is not None else next(iter(pics))
    if name not in pics:
        raise SpcUsageError(f"{tpath}: no picture {name!r} (have {', '.join(pics)})")
    tp = pics[name]
    sumpic = wd.read_picture(name)
    settings = wd.read_settings()
    cam = Camera.from_picture(sumpic, settings).with_pose(
        scobj=np.array(tp["true"]["scobj"], float), rotation=np.array(tp["true"]["rotation"], float)
    )
    photo = wd.read_photo(name, sumpic.npx, sumpic.nln)
    lms = {lm["name"]: lm for lm in truth.get("landmarks", [])}
    if names is None:
        names = [
            n
            for n, lm in lms.items()
            if lm.get("pixels", {}).get(name, {}).get("in_image") and lm["pixels"][name].get("visible")
        ]
    missing = [n for n in names if n not in lms]
    if missing:
        raise SpcUsageError(f"{tpath}: no landmark(s) {', '.join(missing)}")
    if not names:
        raise SpcUsageError(f"{tpath}: no landmark is in picture {name} and visible")
    maplets = [Knowledge.from_maplet(wd.read_maplet(n), n) for n in names]
    true_v = np.array([lms[n]["vlm"] for n in names], float)
    return Scene(
        picture=name,
        photo=getattr(photo, "data", photo),
        thresholds=tuple(sumpic.thrsh),
        camera=cam,
        sun=np.array(tp["true"]["sz"], float),
        maplets=maplets,
        true_v=true_v,
        info={"workdir": str(workdir), "truth_seed": truth.get("seed")},
    )


def save_scene(scene: Scene, path) -> Path:
    """Write a scene to one ``.npz`` file (the photo, maplets, truth and camera) for reuse."""
    from spctool.formats.atomic import write_bytes

    cam = scene.camera
    meta = {
        "format": "spctool-montecarlo-scene/1",
        "spctool_version": __version__,
        "picture": scene.picture,
        "thresholds": list(scene.thresholds),
        "names": scene.names,
        "scales": [m.scale for m in scene.maplets],
        "camera": {
            "mmfl": cam.mmfl,
            "ctr": cam.ctr.tolist(),
            "kmatrix": cam.kmatrix.tolist(),
            "rotation": cam.rotation.tolist(),
            "scobj": cam.scobj.tolist(),
            "npx": cam.npx,
            "nln": cam.nln,
            "legacy_d": cam.legacy_d.tolist(),
            "model": cam.model,
            "coefficients": cam.coefficients.tolist(),
            "name": cam.name,
        },
        "info": scene.info,
    }
    arrays = {
        "meta": np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8),
        "sun": scene.sun,
        "true_v": scene.true_v,
    }
    photo = scene.photo
    if np.all(photo == np.rint(photo)) and photo.min() >= 0 and photo.max() <= 65535:
        arrays["photo_u16"] = photo.astype(np.uint16)
    else:
        arrays["photo"] = photo
    for i, m in enumerate(scene.maplets):
        for key in ("heights", "albedo", "valid", "v", "ux", "uy", "uz"):
            arrays[f"m{i}_{key}"] = getattr(m, key)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    path = Path(path)
    write_bytes(path, buf.getvalue())
    return path


def load_scene(path) -> Scene:
    """Read a scene written by :func:`save_scene`."""
    from spctool.geometry.camera import Camera

    path = Path(path)
    try:
        with np.load(path) as z:
            meta = json.loads(bytes(z["meta"]).decode("utf-8"))
            if meta.get("format") != "spctool-montecarlo-scene/1":
                raise SpcUsageError(f"{path}: not a montecarlo scene file")
            photo = z["photo_u16"].astype(np.float64) if "photo_u16" in z else z["photo"]
            maplets = []
            for i, n in enumerate(meta["names"]):
                g = {k: z[f"m{i}_{k}"] for k in ("heights", "albedo", "valid", "v", "ux", "uy", "uz")}
                maplets.append(Knowledge(name=n, scale=float(meta["scales"][i]), **g))
            sun, true_v = z["sun"], z["true_v"]
    except (OSError, ValueError, KeyError) as exc:
        raise SpcUsageError(f"{path}: cannot read the scene ({exc})") from None
    c = meta["camera"]
    cam = Camera(**{k: (np.array(v) if isinstance(v, list) else v) for k, v in c.items()})
    return Scene(meta["picture"], photo, tuple(meta["thresholds"]), cam, sun, maplets, true_v, meta["info"])
