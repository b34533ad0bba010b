"""Monte Carlo characterisation of landmark registration: S16's study, reproduced and extended.

Specification: spc-algorithms.md §12 (the S16 reproduction checklist: camera §12.1, scene §12.2,
algorithm settings §12.3, Table 2 perturbations §12.4, Table 3 results §12.5) and §9 (the register
drivers); S16 "Performance characterization" (Table 2, Table 3, Fig. 8) and "Future Retina
development" (image-space correlation, Fig. 10).

The study (S16, checklist §12.4)
--------------------------------
One truth photo per epoch; only *knowledge* is perturbed per sample.  For every landmark and sample
the a-priori spacecraft pose, the landmark position, the maplet heights and albedo, the camera
intrinsics and the Sun direction are drawn from zero-mean Gaussians with S16's Table 2 sigmas
(:data:`PARAMETERS`), the landmark is registered in the unchanged photo
(:func:`spctool.stages.register.register` with the plan of :func:`default_plan`), and

    (s, l)_err = (s, l)_truth − (s, l)_measured

with (s, l)_truth the projection of the *true* landmark position with the *true* camera (S16 Eq. 2 at
the unperturbed (x, r_lm, c)).  A sample succeeds when register returns ``ok`` (peak found, not on the
edge, ρ ≥ 0.3); S16 Table 3's "not found" column counts the statuses ``not-found``, ``edge-peak``,
``outside`` and ``removed-*``, its "below threshold" column ``low-correlation``.  Error statistics are
over the successful samples; the mean of the maximum ρ is over all samples with a defined peak.

Registration plans (:func:`default_plan`).  Maplet space is S16's driver (``retina_s16``: L = 10 … 1,
±5L cells, no pose update, linearised extraction) followed by ``refine`` steps at L = 1 (``refine=0``
is S16 exactly); the extra steps re-extract at the current estimate so that the last correlation peak
sits at a near-zero offset, where the 3-point parabola is least biased.  Image space (S16's Retina
direction, for which S16 gives no schedule) searches at L = 4, 2, 1 over ±48 px with one rendered
template, then re-renders the template at the current estimate for each of ``refine`` steps at L = 1.

Sampling.  The scalar perturbations of one landmark form a design of N samples × d dimensions:
Latin Hypercube (``sampling="lhs"``, S16: :class:`scipy.stats.qmc.LatinHypercube`, each of the N
equal-probability strata of every dimension used exactly once) or plain Monte Carlo (``"mc"``), mapped
to standard normals by the inverse CDF (:func:`scipy.stats.norm.ppf`) and scaled by the sigmas.  The
checklist's ambiguity for z(x, y) and a(x, y) (§12.4: one field of i.i.d. per-node errors, or one bias
per maplet?) is the option ``fields``: ``"cell"`` — an i.i.d. N(0, σ) error on every node, drawn from
its own stream per (landmark, sample) (not part of the LHS design; with 9 801 nodes stratifying each
would change nothing), or ``"bias"`` — one N(0, σ) offset per maplet, a dimension of the design.
Per-cell errors (the default) degrade the prediction — the mean max ρ drops to about 0.5, close to
S16's 0.54–0.59, where one bias leaves it near 0.93 — but average out in position; one height bias
instead moves the terrain along the normal relative to V, a parallax error of σ·tan(off-nadir angle)
(≈ 0.08 px at the edge of the 50 m view).

Conventions of the perturbations (Table 2 → spctool):

* position — body-frame components of the spacecraft position (km);
* attitude — small rotation δθ about the camera axes, T⁺ = Rot(−δθ)·T
  (:func:`spctool.geometry.frames.apply_attitude_update`);
* landmark — body-frame components of V (the maplet moves rigidly);
* height — heights in km, divided by the maplet SCALE (heights are in cells); albedo — relative albedo;
* skew — the K-matrix element K21 (S16's K_yx, px/mm as printed); center — CTR (s₀, l₀) in px;
  focal — MMFL in mm; distortion — OWEN P1 … P6 (S16 Eq. 6 = SPC order, erratum 31), added to the
  camera's own coefficients (a camera without a model gets a zero OWEN model, which projects
  identically);
* sun — right ascension and declination of the body-frame Sun vector (degrees).

Reproducibility.  Every draw comes from :class:`numpy.random.SeedSequence` ``(seed, 0x5316, purpose,
landmark[, sample])``: the design of landmark i from ``(…, 1, i)``, the per-cell fields of sample j from
``(…, 2, i, j)``.  A sample's result therefore depends only on (seed, landmark, sample), never on the
order of evaluation or on the number of worker processes (``jobs``): runs are identical bit for bit.

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

Speed.  Everything that does not change per sample (the photo as float64, the truth pixels, the
designs) is computed once; samples run in chunks on ``jobs`` worker processes (``spawn``: the
renderer's OpenMP threads are not fork-safe), each capped at one numba thread.  Maplet space costs one
registration with 12 extraction/correlation steps per sample; image space about three template
renders (:mod:`spctool.stages.render`, ray-traced with cast shadows), which dominate its cost.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spctool import __version__
from spctool.errors import SpcUsageError
from spctool.geometry.frames import apply_attitude_update
from spctool.stages.register import RegisterOptions, register

__all__ = [
    "PARAMETERS",
    "PRESETS",
    "S16_LANDMARKS",
    "S16_TABLE3",
    "SAMPLINGS",
    "FIELD_MODES",
    "Parameter",
    "MonteCarloConfig",
    "Scene",
    "MonteCarloResult",
    "lhs_uniform",
    "design",
    "design_dimensions",
    "default_plan",
    "register_sample",
    "perturb",
    "run",
    "summarise",
    "format_report",
    "report_document",
    "write_figures",
    "write_samples_csv",
    "s16_spec",
    "s16_scene",
    "scene_from_workdir",
    "scene_window_half",
    "save_scene",
    "load_scene",
    "status_class",
]

#: the study's landmarks in S16 Fig. 6 / Table 3 order
S16_LANDMARKS = (
    "B01980", "B02176", "B02246", "B01585", "B01909", "B02235",
    "B02690", "B02631", "B02642", "B01926", "B01536", "B01595",
)  # fmt: skip

#: S16 Table 3 (50 m, 500 LHS samples each, maplet space): name → (s mean, l mean, s std, l std,
#: not found, below threshold, success rate, mean of max ρ); pixels (spc-algorithms.md §12.5)
S16_TABLE3 = {
    "B01980": (-0.136, 0.048, 0.062, 0.096, 42, 15, 0.89, 0.54),
    "B02176": (-0.163, 0.053, 0.028, 0.066, 23, 25, 0.90, 0.54),
    "B02246": (-0.111, -0.027, 0.041, 0.082, 31, 18, 0.90, 0.58),
    "B01585": (-0.041, 0.054, 0.033, 0.082, 36, 20, 0.89, 0.56),
    "B01909": (-0.049, 0.081, 0.043, 0.085, 36, 15, 0.90, 0.55),
    "B02235": (-0.139, 0.068, 0.025, 0.071, 39, 12, 0.90, 0.55),
    "B02690": (-0.052, -0.056, 0.043, 0.097, 52, 16, 0.86, 0.57),
    "B02631": (-0.107, -0.069, 0.038, 0.076, 37, 13, 0.90, 0.57),
    "B02642": (-0.117, 0.007, 0.058, 0.113, 46, 15, 0.88, 0.58),
    "B01926": (-0.193, 0.019, 0.032, 0.078, 49, 6, 0.89, 0.59),
    "B01536": (-0.208, 0.118, 0.037, 0.083, 35, 19, 0.89, 0.58),
    "B01595": (-0.114, 0.111, 0.041, 0.080, 33, 25, 0.88, 0.57),
}
S16_SAMPLES = 500

PRESETS = ("s16-50m",)
SAMPLINGS = ("lhs", "mc")
FIELD_MODES = ("cell", "bias")

_SEED_TAG = 0x5316  # second word of every SeedSequence of this module
_DESIGN, _FIELDS, _NOISE = 1, 2, 3


# --------------------------------------------------------------------------------------------------
# the perturbations (S16 Table 2)


@dataclass(frozen=True)
class Parameter:
    """One row of S16 Table 2: 1σ per component in ``unit`` (spctool's internal unit)."""

    name: str
    sigma: tuple
    unit: str
    label: str  #: Table 2 wording
    shown: str  #: the sigma as S16 prints it
    field: bool = False  #: height/albedo: per-cell field or bias (``MonteCarloConfig.fields``)

    @property
    def size(self) -> int:
        return len(self.sigma)


#: S16 Table 2 (spc-algorithms.md §12.4); internal units: km, degrees, px, mm, px/mm
PARAMETERS = (
    Parameter("position", (1.667e-4,) * 3, "km", "spacecraft position r_sc, each component", "0.1667 m"),
    Parameter(
        "attitude", (0.05,) * 3, "deg", "spacecraft attitude, each component (camera axes)", "0.05 deg"
    ),
    Parameter("landmark", (3.33e-5,) * 3, "km", "landmark position r_lm, each component", "3.33 cm"),
    Parameter("height", (3.33e-6,), "km", "maplet terrain height z(x, y)", "3.33 mm", field=True),
    Parameter("albedo", (0.047,), "", "maplet terrain albedo a(x, y)", "0.047", field=True),
    Parameter("skew", (1e-5,), "px/mm", "camera pixel skew K_yx (K21)", "1e-5"),
    Parameter("center", (0.1667, 0.1667), "px", "camera principal point (s0, l0)", "0.1667 px"),
    Parameter("focal", (0.004,), "mm", "camera focal length f", "0.004 mm"),
    Parameter(
        "distortion",
        (1e-5, 1e-7, 1e-5, 1e-5, 0.0, 0.0),
        "OWEN",
        "camera distortion eps1..eps6 (S16 = SPC OWEN order)",
        "(1e-5, 1e-7, 1e-5, 1e-5, 0, 0)",
    ),
    Parameter("sun", (0.3, 0.3), "deg", "Sun direction, right ascension and declination", "0.3 deg"),
)
_PARAM = {p.name: p for p in PARAMETERS}


@dataclass
class MonteCarloConfig:
    """Settings of one study (module docstring).

    * ``samples`` per landmark (S16: 500); ``seed``; ``sampling`` ``"lhs"`` | ``"mc"``;
    * ``fields`` — height/albedo errors ``"cell"`` (i.i.d. per node) or ``"bias"`` (one per maplet);
    * ``parameters`` — names of :data:`PARAMETERS` to perturb (default all); ``sigma_scale`` multiplies
      every sigma (success versus perturbation size);
    * ``space`` — ``"maplet"`` | ``"image"``; ``plan`` — the registration: one
      :class:`RegisterOptions` or a tuple of them run one after the other, each phase starting where
      the previous one ended (default: :func:`default_plan` for the space).
    """

    samples: int = S16_SAMPLES
    seed: int = 0
    sampling: str = "lhs"
    fields: str = "cell"
    parameters: tuple = tuple(p.name for p in PARAMETERS)
    sigma_scale: float = 1.0
    space: str = "maplet"
    plan: tuple | RegisterOptions | None = None

    def __post_init__(self):
        if int(self.samples) != self.samples or self.samples < 1:
            raise SpcUsageError(f"samples must be an integer >= 1, got {self.samples!r}")
        self.samples = int(self.samples)
        if int(self.seed) != self.seed or self.seed < 0:
            raise SpcUsageError(f"seed must be an integer >= 0, got {self.seed!r}")
        self.seed = int(self.seed)
        if self.sampling not in SAMPLINGS:
            raise SpcUsageError(f"sampling must be one of {', '.join(SAMPLINGS)}, got {self.sampling!r}")
        if self.fields not in FIELD_MODES:
            raise SpcUsageError(f"fields must be one of {', '.join(FIELD_MODES)}, got {self.fields!r}")
        names = tuple(str(p) for p in self.parameters)
        unknown = [p for p in names if p not in _PARAM]
        if unknown:
            raise SpcUsageError(f"unknown perturbation {', '.join(unknown)} (known: {', '.join(_PARAM)})")
        # keep Table 2 order whatever order they were given in
        self.parameters = tuple(p.name for p in PARAMETERS if p.name in names)
        if not (math.isfinite(float(self.sigma_scale)) and float(self.sigma_scale) >= 0.0):
            raise SpcUsageError(f"sigma_scale must be a finite number >= 0, got {self.sigma_scale!r}")
        self.sigma_scale = float(self.sigma_scale)
        if self.plan is None:
            self.plan = default_plan(self.space)
        elif isinstance(self.plan, RegisterOptions):
            self.plan = (self.plan,)
        self.plan = tuple(self.plan)
        if not self.plan or not all(isinstance(o, RegisterOptions) for o in self.plan):
            raise SpcUsageError("the registration plan must be one or more RegisterOptions")
        for o in self.plan:
            if o.space != self.space:
                raise SpcUsageError(f"register options are for space {o.space!r}, not {self.space!r}")
            if o.schedule != "retina_s16":
                raise SpcUsageError(
                    "montecarlo registers each landmark on its own: schedule must be retina_s16"
                )

    def as_dict(self) -> dict:
        return {
            "samples": self.samples,
            "seed": self.seed,
            "sampling": self.sampling,
            "fields": self.fields,
            "parameters": list(self.parameters),
            "sigma_scale": self.sigma_scale,
            "space": self.space,
            "plan": [o.as_dict() for o in self.plan],
        }

    @property
    def steps(self) -> list[int]:
        """The spacings of every align step of the plan, in order."""
        from spctool.stages.register import schedule_steps

        return [int(n) for o in self.plan for k, n in schedule_steps(o) if k == "align"]


def default_plan(space: str = "maplet", refine: int = 1, **changes) -> tuple[RegisterOptions, ...]:
    """The registration of one landmark in the study.

    * ``"maplet"`` — S16's driver (``retina_s16``: L = 10 … 1, ±5L cells, ρ ≥ 0.3, no pose update) with
      S16's linearised extraction (checklist §12.3, erratum 32), then ``refine`` extra steps at L = 1: each
      re-extracts at the current estimate, so the last correlation peak sits near zero offset where the
      3-point parabola is least biased ("pixel locking").  ``refine=0`` is S16's schedule exactly.
    * ``"image"`` — S16's image-space direction (Retina; S16 gives no schedule): a coarse search at
      L = 4, 2, 1 on a 25 × 25 grid (±48 px at L = 4: the search is not limited by the maplet) with the
      template rendered once (re-rendered only if its sub-pixel placement moves by more than half a bin),
      then ``refine`` steps at L = 1 that re-render the template at the current estimate every time,
      ending with register's converged stage (the coarse phase then runs its schedule only).

    ``changes`` are applied to every phase's :class:`RegisterOptions`.
    """
    from spctool.stages.extract import ExtractOptions

    if int(refine) != refine or refine < 0:
        raise SpcUsageError(f"refine must be an integer >= 0, got {refine!r}")
    refine = int(refine)
    if space == "maplet":
        opts = dict(
            schedule="retina_s16", space="maplet", extract=ExtractOptions(linearized=True, criteria=None)
        )
        opts.update(changes)
        spacings = tuple(opts.get("s16_spacings", RegisterOptions.s16_spacings))
        if refine and "steps" not in changes:
            opts["steps"] = tuple(("align", int(n)) for n in spacings) + (("align", 1),) * refine
        return (RegisterOptions(**opts),)
    if space == "image":
        coarse = dict(
            schedule="retina_s16",
            space="image",
            supersample=1,
            steps=(4, 2, 1),
            grid_half=12,
            rerender_tol=0.5,
        )
        if refine:  # the fine phase ends converged; the coarse one only acquires
            coarse["converge_max"] = 0
        coarse.update(changes)
        plan = [RegisterOptions(**coarse)]
        if refine:
            fine = dict(schedule="retina_s16", space="image", supersample=1, grid_half=5, rerender_tol=0.0)
            fine.update({k: v for k, v in changes.items() if k not in ("steps", "grid_half")})
            fine["steps"] = (1,) * refine
            plan.append(RegisterOptions(**fine))
        return tuple(plan)
    raise SpcUsageError(f"space must be maplet or image, got {space!r}")


def design_dimensions(config: MonteCarloConfig) -> list[tuple[str, int, float]]:
    """The design's dimensions: ``(parameter, component, sigma)`` for every enabled scalar component
    with σ > 0 (per-cell fields are not dimensions; bias fields are)."""
    out = []
    for p in PARAMETERS:
        if p.name not in config.parameters:
            continue
        if p.field and config.fields == "cell":
            continue
        for k, s in enumerate(p.sigma):
            if s > 0.0:
                out.append((p.name, k, float(s) * config.sigma_scale))
    return out


def lhs_uniform(n: int, d: int, rng: np.random.Generator) -> np.ndarray:
    """(n, d) Latin Hypercube in (0, 1): along every dimension each stratum [k/n, (k+1)/n) holds exactly
    one sample (:class:`scipy.stats.qmc.LatinHypercube`, scrambled).  Values are kept strictly inside
    (0, 1) so that the normal inverse CDF stays finite."""
    from scipy.stats import qmc

    if d == 0:
        return np.zeros((n, 0))
    u = qmc.LatinHypercube(d, rng=rng).random(n)
    tiny = 1e-12 / max(n, 1)
    return np.clip(u, tiny, 1.0 - tiny)


def design(config: MonteCarloConfig, landmark: int) -> np.ndarray:
    """(samples, d) standard-normal design of landmark number ``landmark`` (0-based): LHS or MC from the
    stream ``(seed, 0x5316, 1, landmark)``, mapped by the normal inverse CDF (LHS)."""
    from scipy.stats import norm

    d = len(design_dimensions(config))
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, _SEED_TAG, _DESIGN, int(landmark)]))
    if config.sampling == "lhs":
        return norm.ppf(lhs_uniform(config.samples, d, rng))
    return rng.standard_normal((config.samples, d))


# --------------------------------------------------------------------------------------------------
# the scene: one photo with its truth and the onboard maplets


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
    """The SPEC (:func:`spctool.sim.simulate.parse_spec` mapping) of the ``s16-50m`` world.

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
    from spctool.sim.simulate import build_world, expose, parse_spec

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


# --------------------------------------------------------------------------------------------------
# one sample


@dataclass
class Perturbed:
    """The knowledge of one sample: camera, Sun, maplet (and the a-priori pixel of V)."""

    camera: object
    sun: np.ndarray
    maplet: Knowledge
    values: dict  #: parameter → applied perturbation (internal units)


def _sun_radec(sun, dra_deg: float, ddec_deg: float) -> np.ndarray:
    ra = math.atan2(sun[1], sun[0]) + math.radians(dra_deg)
    dec = math.asin(max(-1.0, min(1.0, float(sun[2])))) + math.radians(ddec_deg)
    return np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])


def _owen_camera(cam):
    """The camera with an OWEN model (a camera without a model gets zero coefficients: same projection)."""
    if cam.model == "OWEN":
        coef = np.zeros(max(7, cam.coefficients.size))
        coef[: cam.coefficients.size] = cam.coefficients
        return cam.model, coef
    if cam.model == "NONE":
        return "OWEN", np.zeros(7)
    raise SpcUsageError(
        f"the camera's distortion model is {cam.model}; the distortion perturbation (S16 Eq. 6) needs OWEN "
        "or none (leave out 'distortion')"
    )


def perturb(scene: Scene, landmark: int, z_row, sample: int, config: MonteCarloConfig) -> Perturbed:
    """Knowledge of sample ``sample`` of landmark ``landmark`` from its design row ``z_row`` (standard
    normals, :func:`design`) and, for per-cell fields, the stream ``(seed, 0x5316, 2, landmark, sample)``."""
    dims = design_dimensions(config)
    z = np.asarray(z_row, dtype=np.float64).reshape(-1)
    if z.size != len(dims):
        raise SpcUsageError(f"design row has {z.size} values, the configuration {len(dims)} dimensions")
    delta: dict[str, np.ndarray] = {p.name: np.zeros(p.size) for p in PARAMETERS}
    for (name, k, sigma), zk in zip(dims, z):
        delta[name][k] = sigma * zk
    cam = scene.camera
    m0 = scene.maplets[landmark]
    changes = {}
    if np.any(delta["position"]) or np.any(delta["attitude"]):
        changes["scobj"] = cam.scobj - delta["position"]
        changes["rotation"] = apply_attitude_update(cam.rotation, np.radians(delta["attitude"]))
    if delta["skew"][0] != 0.0:
        k = cam.kmatrix.copy()
        k[1, 0] += delta["skew"][0]
        changes["kmatrix"] = k
    if np.any(delta["center"]):
        changes["ctr"] = cam.ctr + delta["center"]
    if delta["focal"][0] != 0.0:
        changes["mmfl"] = cam.mmfl + delta["focal"][0]
    if "distortion" in config.parameters and any(s > 0 for s in _PARAM["distortion"].sigma):
        model, coef = _owen_camera(cam)
        coef = coef.copy()
        coef[1:7] += delta["distortion"]
        changes["model"], changes["coefficients"] = model, coef
    pcam = dataclasses.replace(cam, **changes) if changes else cam
    sun = _sun_radec(scene.sun, *delta["sun"]) if np.any(delta["sun"]) else scene.sun
    heights, albedo = m0.heights, m0.albedo
    fields_on = [n for n in ("height", "albedo") if n in config.parameters]
    if fields_on and config.fields == "cell":
        rng = np.random.default_rng(
            np.random.SeedSequence([config.seed, _SEED_TAG, _FIELDS, int(landmark), int(sample)])
        )
        noise = rng.standard_normal((2,) + m0.heights.shape)  # both drawn always: streams independent
        if "height" in fields_on:
            heights = heights + noise[0] * (_PARAM["height"].sigma[0] * config.sigma_scale / m0.scale)
        if "albedo" in fields_on:
            albedo = albedo + noise[1] * (_PARAM["albedo"].sigma[0] * config.sigma_scale)
    elif fields_on:
        if delta["height"][0] != 0.0:
            heights = heights + delta["height"][0] / m0.scale
        if delta["albedo"][0] != 0.0:
            albedo = albedo + delta["albedo"][0]
    maplet = dataclasses.replace(m0, heights=heights, albedo=albedo, v=m0.v + delta["landmark"])
    return Perturbed(pcam, sun, maplet, delta)


# --------------------------------------------------------------------------------------------------
# running the study


#: status → S16 Table 3 class
def status_class(status: str) -> str:
    """``"ok"``, ``"below"`` (low-correlation: Table 3 column 7) or ``"not-found"`` (column 6: not-found,
    edge-peak, outside, removed-*)."""
    if status == "ok":
        return "ok"
    if status == "low-correlation":
        return "below"
    return "not-found"


@dataclass
class MonteCarloResult:
    """Per-sample outcomes, arrays (landmarks, samples, …); pixels are SPC (sample, line)."""

    scene_info: dict
    picture: str
    names: list
    truth: np.ndarray  #: (L, 2) truth pixels
    config: MonteCarloConfig
    dimensions: list  #: design_dimensions(config)
    z: np.ndarray  #: (L, N, d) design (standard normals)
    apriori: np.ndarray  #: (L, N, 2) a-priori pixel of each sample (perturbed V, perturbed camera)
    measured: np.ndarray  #: (L, N, 2) NaN unless ok
    status: np.ndarray  #: (L, N) str
    rho: np.ndarray  #: (L, N) peak ρ of the last correlation (NaN if none)
    iterations: np.ndarray  #: (L, N) correlation steps run
    timing: dict = field(default_factory=dict)

    @property
    def error(self) -> np.ndarray:
        """(L, N, 2) truth − measured (S16's (s, l)_err); NaN unless ok."""
        return self.truth[:, None, :] - self.measured

    @property
    def apriori_error(self) -> np.ndarray:
        """(L, N, 2) truth − a-priori pixel: the perturbation's size in the photo."""
        return self.truth[:, None, :] - self.apriori

    @property
    def ok(self) -> np.ndarray:
        return self.status == "ok"


def register_sample(scene: Scene, p: Perturbed, plan) -> object:
    """Register one perturbed landmark with every phase of ``plan``; each phase after the first starts
    at the previous phase's measurement and runs only if that one succeeded.  Returns the
    :class:`spctool.stages.register.RegisterResult` of the last phase run, with the first phase's
    a-priori pixel and the iterations of all phases."""
    res = register(scene.photo, p.camera, p.sun, [p.maplet], scene.thresholds, plan[0])
    apriori, iters = res.apriori.copy(), res.iterations.copy()
    for opts in plan[1:]:
        if res.status[0] != "ok":
            break
        res = register(scene.photo, p.camera, p.sun, [p.maplet], scene.thresholds, opts, apriori=res.measured)
        iters += res.iterations
    res.apriori, res.iterations = apriori, iters
    return res


_WORKER: dict = {}


def _worker_init(scene, config, designs, threads):
    _WORKER.clear()
    _WORKER.update(scene=scene, config=config, designs=designs)
    if threads:
        try:
            import numba

            numba.set_num_threads(int(threads))
        except Exception:  # noqa: BLE001 - a thread cap is an optimisation only
            pass


def _run_chunk(landmark: int, start: int, stop: int):
    scene, config, designs = _WORKER["scene"], _WORKER["config"], _WORKER["designs"]
    cpu0 = time.process_time()
    n = stop - start
    apriori = np.full((n, 2), np.nan)
    measured = np.full((n, 2), np.nan)
    rho = np.full(n, np.nan)
    iters = np.zeros(n, np.int64)
    status = []
    for k, j in enumerate(range(start, stop)):
        p = perturb(scene, landmark, designs[landmark][j], j, config)
        res = register_sample(scene, p, config.plan)
        apriori[k], measured[k], rho[k], iters[k] = (
            res.apriori[0],
            res.measured[0],
            res.correlation[0],
            res.iterations[0],
        )
        status.append(res.status[0])
    return landmark, start, apriori, measured, rho, iters, status, time.process_time() - cpu0


def _chunks(n_landmarks: int, samples: int, size: int):
    for i in range(n_landmarks):
        for a in range(0, samples, size):
            yield i, a, min(samples, a + size)


def run(
    scene: Scene, config: MonteCarloConfig, *, jobs: int = 1, progress=None, chunk: int | None = None
) -> MonteCarloResult:
    """Run the study: every landmark of ``scene`` × ``config.samples`` samples (module docstring).

    ``jobs`` worker processes (1: in this process); ``progress(n)`` is called as samples finish.
    Results do not depend on ``jobs`` or ``chunk`` (bit for bit).
    """
    if int(jobs) < 1:
        raise SpcUsageError(f"jobs must be >= 1, got {jobs}")
    jobs = int(jobs)
    n_lm, n = len(scene), config.samples
    dims = design_dimensions(config)
    designs = [design(config, i) for i in range(n_lm)]
    apriori = np.full((n_lm, n, 2), np.nan)
    measured = np.full((n_lm, n, 2), np.nan)
    rho = np.full((n_lm, n), np.nan)
    iters = np.zeros((n_lm, n), np.int64)
    status = np.empty((n_lm, n), dtype=object)
    tick = progress or (lambda k=1: None)
    if chunk is None:
        chunk = max(1, min(25, math.ceil(n / 4)))
    t0 = time.perf_counter()

    cpu = [0.0]

    def store(out):
        i, a, ap, me, rh, it, st, cpu_s = out
        cpu[0] += cpu_s
        b = a + len(st)
        apriori[i, a:b], measured[i, a:b], rho[i, a:b], iters[i, a:b] = ap, me, rh, it
        status[i, a:b] = st
        tick(len(st))

    work = list(_chunks(n_lm, n, int(chunk)))
    if jobs == 1 or len(work) == 1:
        _worker_init(scene, config, designs, 0)
        try:
            for w in work:
                store(_run_chunk(*w))
        finally:
            _WORKER.clear()
    else:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor, as_completed

        ctx = mp.get_context("spawn")
        with ProcessPoolExecutor(
            max_workers=min(jobs, len(work)),
            mp_context=ctx,
            initializer=_worker_init,
            initargs=(scene, config, designs, 1),
        ) as pool:
            futures = [pool.submit(_run_chunk, *w) for w in work]
            for f in as_completed(futures):
                store(f.result())
    elapsed = time.perf_counter() - t0
    total = n_lm * n
    return MonteCarloResult(
        scene_info=dict(scene.info),
        picture=scene.picture,
        names=scene.names,
        truth=scene.truth.copy(),
        config=config,
        dimensions=dims,
        z=np.stack(designs) if designs else np.zeros((0, n, len(dims))),
        apriori=apriori,
        measured=measured,
        status=status.astype(str) if total else np.zeros((n_lm, n), dtype=str),
        rho=rho,
        iterations=iters,
        timing={
            "run_s": elapsed,
            "per_sample_ms": 1e3 * elapsed / max(total, 1),
            "cpu_s": cpu[0],
            "cpu_per_sample_ms": 1e3 * cpu[0] / max(total, 1),
            "jobs": jobs,
            "samples": total,
        },
    )


# --------------------------------------------------------------------------------------------------
# statistics (S16 Table 3 layout)


def _stats(err: np.ndarray) -> tuple[float, float, float, float]:
    if err.shape[0] == 0:
        return (math.nan,) * 4
    mean = err.mean(axis=0)
    std = err.std(axis=0, ddof=1) if err.shape[0] > 1 else np.full(2, math.nan)
    return float(mean[0]), float(mean[1]), float(std[0]), float(std[1])


def _row(name, status, err, rho) -> dict:
    cls = np.array([status_class(s) for s in status])
    ok = cls == "ok"
    e = err[ok]
    sm, lm, ss, ls = _stats(e)
    counts: dict[str, int] = {}
    for s in status:
        counts[str(s)] = counts.get(str(s), 0) + 1
    finite = np.isfinite(rho)
    return {
        "name": name,
        "samples": int(len(status)),
        "ok": int(ok.sum()),
        "sample_mean": sm,
        "line_mean": lm,
        "sample_std": ss,
        "line_std": ls,
        "not_found": int((cls == "not-found").sum()),
        "below_threshold": int((cls == "below").sum()),
        "success_rate": float(ok.mean()) if len(status) else math.nan,
        "mean_max_rho": float(rho[finite].mean()) if finite.any() else math.nan,
        "rho_defined": int(finite.sum()),
        "status_counts": dict(sorted(counts.items())),
    }


def _s16_aggregate() -> dict:
    t = np.array([v for v in S16_TABLE3.values()], float)
    n = S16_SAMPLES * len(S16_TABLE3)
    succ = S16_SAMPLES * len(S16_TABLE3) - t[:, 4].sum() - t[:, 5].sum()
    return {
        "success_rate": float(succ / n),
        "min_success_rate": float(t[:, 6].min()),
        "max_abs_sample_mean": float(np.abs(t[:, 0]).max()),
        "max_abs_line_mean": float(np.abs(t[:, 1]).max()),
        "max_sample_std": float(t[:, 2].max()),
        "max_line_std": float(t[:, 3].max()),
        "median_abs_sample_mean": float(np.median(np.abs(t[:, 0]))),
        "median_abs_line_mean": float(np.median(np.abs(t[:, 1]))),
        "median_sample_std": float(np.median(t[:, 2])),
        "median_line_std": float(np.median(t[:, 3])),
        "mean_max_rho": float(t[:, 7].mean()),
    }


#: targets of the issue: image space (success, |mean|, 1σ per axis)
IMAGE_TARGETS = {"success_rate": 0.995, "abs_mean_px": 0.05, "std_px": 0.08}


def sensitivity(result: MonteCarloResult) -> list[dict]:
    """Linear sensitivity of the errors to each design dimension over the successful samples (pooled):
    least-squares coefficients of (s_err, l_err) on the standard-normal design, i.e. px per 1σ of that
    perturbation (the checklist's "dominant error sources", §12.5).  Per-cell fields are not dimensions."""
    ok = result.ok.reshape(-1)
    d = len(result.dimensions)
    if d == 0 or ok.sum() <= d + 1:
        return []
    z = result.z.reshape(-1, d)[ok]
    e = result.error.reshape(-1, 2)[ok]
    # per-landmark means removed (each landmark has its own bias)
    lm = np.repeat(np.arange(len(result.names)), result.config.samples)[ok]
    for i in np.unique(lm):
        sel = lm == i
        e[sel] -= e[sel].mean(axis=0)
        z[sel] -= z[sel].mean(axis=0)
    coef, *_ = np.linalg.lstsq(z, e, rcond=None)
    out = []
    for (name, k, sigma), c in zip(result.dimensions, coef):
        out.append(
            {
                "parameter": name,
                "component": int(k),
                "sigma": sigma,
                "sample_px_per_sigma": float(c[0]),
                "line_px_per_sigma": float(c[1]),
            }
        )
    return out


def summarise(result: MonteCarloResult) -> dict:
    """Table 3 rows per landmark, the pooled ("all") row, the S16 comparison and the target checks."""
    err = result.error
    rows = [_row(n, result.status[i], err[i], result.rho[i]) for i, n in enumerate(result.names)]
    overall = _row("all", result.status.reshape(-1), err.reshape(-1, 2), result.rho.reshape(-1))
    if rows:
        overall["min_success_rate"] = min(r["success_rate"] for r in rows)
        for key in ("sample_mean", "line_mean"):
            vals = [abs(r[key]) for r in rows if math.isfinite(r[key])]
            overall[f"max_abs_{key}"] = max(vals) if vals else math.nan
        for key in ("sample_std", "line_std"):
            vals = [r[key] for r in rows if math.isfinite(r[key])]
            overall[f"max_{key}"] = max(vals) if vals else math.nan
    s16 = _s16_aggregate()
    ours = overall
    checks = {}
    if rows:
        # S16 Table 3 (maplet space): at least as good on success and on the worst landmark per axis
        checks["s16_table3"] = {
            "success_rate": ours["success_rate"] >= s16["success_rate"],
            "max_abs_sample_mean": ours["max_abs_sample_mean"] <= s16["max_abs_sample_mean"],
            "max_abs_line_mean": ours["max_abs_line_mean"] <= s16["max_abs_line_mean"],
            "max_sample_std": ours["max_sample_std"] <= s16["max_sample_std"],
            "max_line_std": ours["max_line_std"] <= s16["max_line_std"],
        }
        t = IMAGE_TARGETS
        checks["image_targets"] = {
            "success_rate": ours["success_rate"] >= t["success_rate"],
            "abs_sample_mean": abs(ours["sample_mean"]) <= t["abs_mean_px"],
            "abs_line_mean": abs(ours["line_mean"]) <= t["abs_mean_px"],
            "sample_std": ours["sample_std"] <= t["std_px"],
            "line_std": ours["line_std"] <= t["std_px"],
        }
        # the same limits for every landmark on its own (informative: not part of --check)
        checks["image_targets_per_landmark"] = {
            "min_success_rate": ours["min_success_rate"] >= t["success_rate"],
            "max_abs_sample_mean": ours["max_abs_sample_mean"] <= t["abs_mean_px"],
            "max_abs_line_mean": ours["max_abs_line_mean"] <= t["abs_mean_px"],
            "max_sample_std": ours["max_sample_std"] <= t["std_px"],
            "max_line_std": ours["max_line_std"] <= t["std_px"],
        }
        for v in checks.values():
            for k in v:
                v[k] = bool(v[k])
    return {"landmarks": rows, "overall": overall, "s16": s16, "checks": checks}


def _f(x, fmt="{:+.3f}") -> str:
    return "nan" if x is None or not math.isfinite(x) else fmt.format(x)


def format_report(result: MonteCarloResult, summary: dict | None = None) -> str:
    """The text report: settings, Table 3 layout (ours, then S16's), comparison and target checks."""
    summary = summary or summarise(result)
    c = result.config
    out = []
    src = result.scene_info.get("preset") or result.scene_info.get("workdir") or "scene"
    out.append(f"# spctool {__version__} montecarlo: {src}, picture {result.picture}")
    out.append(
        f"# space {c.space}, steps L = {', '.join(str(n) for n in c.steps)}, "
        f"{c.samples} {c.sampling.upper()} samples per landmark, seed {c.seed}, "
        f"terrain errors {'per cell' if c.fields == 'cell' else 'as one bias'}, "
        f"sigma scale {c.sigma_scale:g}"
    )
    out.append("# perturbations (1 sigma, S16 Table 2):")
    for p in PARAMETERS:
        on = p.name in c.parameters
        mode = ""
        if p.field:
            mode = " per cell" if c.fields == "cell" else " bias"
        out.append(f"#   {p.name:10s} {p.shown:>32s}{mode:9s} {'' if on else '(off) '}{p.label}")
    out.append("")
    head = (
        f"{'L-map':8s} {'s mean':>8s} {'l mean':>8s} {'s std':>7s} {'l std':>7s} {'not found':>9s} "
        f"{'below 0.3':>9s} {'success':>8s} {'mean max rho':>12s}"
    )
    out.append("Table 3 layout (pixels; errors = truth - measured, over successful samples)")
    out.append(head)
    for r in summary["landmarks"] + [summary["overall"]]:
        out.append(
            f"{r['name']:8s} {_f(r['sample_mean']):>8s} {_f(r['line_mean']):>8s} "
            f"{_f(r['sample_std'], '{:.3f}'):>7s} {_f(r['line_std'], '{:.3f}'):>7s} "
            f"{r['not_found']:9d} {r['below_threshold']:9d} "
            f"{_f(r['success_rate'], '{:.3f}'):>8s} {_f(r['mean_max_rho'], '{:.2f}'):>12s}"
        )
    ov = summary["overall"]
    if summary["landmarks"]:
        out.append(
            f"worst landmark: |s mean| {_f(ov['max_abs_sample_mean'], '{:.3f}')}, |l mean| "
            f"{_f(ov['max_abs_line_mean'], '{:.3f}')}, s std {_f(ov['max_sample_std'], '{:.3f}')}, l std "
            f"{_f(ov['max_line_std'], '{:.3f}')}, success {_f(ov['min_success_rate'], '{:.3f}')}"
        )
    out.append("")
    out.append("S16 Table 3 (maplet space, 50 m, 500 LHS samples each; different terrain, same names)")
    out.append(head)
    for name, t in S16_TABLE3.items():
        out.append(
            f"{name:8s} {t[0]:+8.3f} {t[1]:+8.3f} {t[2]:7.3f} {t[3]:7.3f} {t[4]:9d} {t[5]:9d} "
            f"{t[6]:8.2f} {t[7]:12.2f}"
        )
    s = summary["s16"]
    out.append(
        f"worst landmark: |s mean| {s['max_abs_sample_mean']:.3f}, |l mean| {s['max_abs_line_mean']:.3f}, "
        f"s std {s['max_sample_std']:.3f}, l std {s['max_line_std']:.3f}, "
        f"success {s['min_success_rate']:.2f}; "
        f"overall success {s['success_rate']:.3f}"
    )
    out.append("")
    for group, checks in summary["checks"].items():
        title = {
            "s16_table3": "at least as good as S16 Table 3 (overall success, worst landmark per axis)",
            "image_targets": "image-space targets, all samples (success >= 99.5 %, |mean| <= 0.05 px, "
            "1 sigma <= 0.08 px per axis)",
            "image_targets_per_landmark": "the same for the worst landmark (informative)",
        }[group]
        marks = ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in checks.items())
        out.append(f"{title}: {marks}")
    sens = sensitivity(result)
    if sens:
        out.append("")
        out.append(
            "error sensitivity (px per 1 sigma; least squares over successful samples, "
            "landmark means removed)"
        )
        groups: dict[str, list] = {}
        for r in sens:
            groups.setdefault(r["parameter"], []).append(r)
        ranked = sorted(
            groups.items(),
            key=lambda kv: (
                -math.sqrt(sum(r["sample_px_per_sigma"] ** 2 + r["line_px_per_sigma"] ** 2 for r in kv[1]))
            ),
        )
        for name, rs in ranked:
            tot = math.sqrt(sum(r["sample_px_per_sigma"] ** 2 + r["line_px_per_sigma"] ** 2 for r in rs))
            comps = " ".join(f"({r['sample_px_per_sigma']:+.4f}, {r['line_px_per_sigma']:+.4f})" for r in rs)
            out.append(f"  {name:10s} {tot:.4f}  {comps}")
    tm = result.timing
    if tm:
        out.append("")
        out.append(
            f"time: {tm.get('run_s', math.nan):.1f} s for {tm.get('samples', 0)} registrations "
            f"({tm.get('per_sample_ms', math.nan):.1f} ms each, {tm.get('jobs', 1)} job(s); "
            f"{tm.get('cpu_per_sample_ms', math.nan):.1f} ms of CPU per registration)"
            + (f"; scene {tm['scene_s']:.1f} s" if "scene_s" in tm else "")
        )
    return "\n".join(out) + "\n"


def _clean(x):
    """JSON-safe: NaN/inf → None, numpy scalars → Python."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def report_document(result: MonteCarloResult, summary: dict | None = None) -> dict:
    """The JSON document (cli-contract.md shape): per-landmark Table 3 rows and success rates, the
    overall row, S16's table, checks, sensitivity, settings, timing."""
    summary = summary or summarise(result)
    rows = []
    for i, r in enumerate(summary["landmarks"]):
        r = dict(r)
        r["truth_sample"], r["truth_line"] = (float(v) for v in result.truth[i])
        if r["name"] in S16_TABLE3:
            r["s16"] = dict(
                zip(
                    (
                        "sample_mean",
                        "line_mean",
                        "sample_std",
                        "line_std",
                        "not_found",
                        "below_threshold",
                        "success_rate",
                        "mean_max_rho",
                    ),
                    S16_TABLE3[r["name"]],
                )
            )
        rows.append(r)
    info = {k: v for k, v in result.scene_info.items() if k != "spec"}
    doc = {
        "command": "montecarlo",
        "picture": result.picture,
        "spctool_version": __version__,
        "scene": info,
        "config": result.config.as_dict(),
        "perturbations": [
            {
                "name": p.name,
                "sigma": list(p.sigma),
                "unit": p.unit,
                "label": p.label,
                "s16": p.shown,
                "enabled": p.name in result.config.parameters,
                "mode": (result.config.fields if p.field else "design"),
            }
            for p in PARAMETERS
        ],
        "dimensions": [{"parameter": n, "component": k, "sigma": s} for n, k, s in result.dimensions],
        "landmarks": rows,
        "overall": summary["overall"],
        "s16_table3": {"landmarks": {k: list(v) for k, v in S16_TABLE3.items()}, "aggregate": summary["s16"]},
        "checks": summary["checks"],
        "sensitivity": sensitivity(result),
        "timing": result.timing,
    }
    return _clean(doc)


def write_samples_csv(result: MonteCarloResult, path) -> Path:
    """One row per sample: landmark, sample, status, rho, iterations, a-priori, measured, error, design."""
    from spctool.formats.atomic import write_text

    dims = [f"z_{n}{k}" for n, k, _ in result.dimensions]
    head = [
        "landmark",
        "sample",
        "status",
        "rho",
        "iterations",
        "apriori_sample",
        "apriori_line",
        "measured_sample",
        "measured_line",
        "err_sample",
        "err_line",
    ] + dims
    lines = [",".join(head)]
    err = result.error
    for i, name in enumerate(result.names):
        for j in range(result.config.samples):
            vals = [
                name,
                str(j),
                str(result.status[i, j]),
                repr(float(result.rho[i, j])),
                str(int(result.iterations[i, j])),
            ]
            vals += [repr(float(x)) for x in (*result.apriori[i, j], *result.measured[i, j], *err[i, j])]
            vals += [repr(float(x)) for x in result.z[i, j]]
            lines.append(",".join(vals))
    path = Path(path)
    write_text(path, "\n".join(lines) + "\n")
    return path


# --------------------------------------------------------------------------------------------------
# figures (pillow; no plotting library needed)


def _nice_step(span: float, target: int = 5) -> float:
    if not span > 0:
        return 1.0
    raw = span / target
    mag = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if raw <= m * mag:
            return m * mag
    return 10.0 * mag


class _Axes:
    """A minimal plot panel drawn with PIL.ImageDraw: data → pixel mapping, frame, ticks, labels."""

    def __init__(self, draw, box, xlim, ylim, *, title="", xlabel="", ylabel="", font=None, small=None):
        self.d = draw
        self.x0, self.y0, self.x1, self.y1 = box
        self.xlim, self.ylim = xlim, ylim
        self.font, self.small = font, small
        self._frame(title, xlabel, ylabel)

    def X(self, x):
        a, b = self.xlim
        return self.x0 + (np.asarray(x, float) - a) / (b - a) * (self.x1 - self.x0)

    def Y(self, y):
        a, b = self.ylim
        return self.y1 - (np.asarray(y, float) - a) / (b - a) * (self.y1 - self.y0)

    def _frame(self, title, xlabel, ylabel):
        d = self.d
        d.rectangle((self.x0, self.y0, self.x1, self.y1), outline=(0, 0, 0))
        for lim, axis in ((self.xlim, "x"), (self.ylim, "y")):
            step = _nice_step(lim[1] - lim[0])
            t = math.ceil(lim[0] / step - 1e-9) * step
            while t <= lim[1] + 1e-9 * step:
                label = f"{t:.10g}" if abs(t) > 1e-12 * step else "0"
                if axis == "x":
                    px = float(self.X(t))
                    d.line((px, self.y1, px, self.y1 + 4), fill=(0, 0, 0))
                    d.line((px, self.y0, px, self.y1), fill=(232, 232, 232))
                    d.text((px, self.y1 + 6), label, fill=(0, 0, 0), font=self.small, anchor="ma")
                else:
                    py = float(self.Y(t))
                    d.line((self.x0 - 4, py, self.x0, py), fill=(0, 0, 0))
                    d.line((self.x0, py, self.x1, py), fill=(232, 232, 232))
                    d.text((self.x0 - 6, py), label, fill=(0, 0, 0), font=self.small, anchor="rm")
                t += step
        d.rectangle((self.x0, self.y0, self.x1, self.y1), outline=(0, 0, 0))
        if title:
            d.text(((self.x0 + self.x1) / 2, self.y0 - 6), title, fill=(0, 0, 0), font=self.font, anchor="md")
        if xlabel:
            d.text(
                ((self.x0 + self.x1) / 2, self.y1 + 22), xlabel, fill=(0, 0, 0), font=self.small, anchor="ma"
            )
        if ylabel:
            d.text(
                (self.x0 - 44, (self.y0 + self.y1) / 2), ylabel, fill=(0, 0, 0), font=self.small, anchor="rm"
            )

    def inside(self, x, y):
        x, y = np.asarray(x, float), np.asarray(y, float)
        return (x >= self.xlim[0]) & (x <= self.xlim[1]) & (y >= self.ylim[0]) & (y <= self.ylim[1])

    def points(self, x, y, color, r=1.5):
        keep = self.inside(x, y)
        for px, py in zip(self.X(np.asarray(x)[keep]), self.Y(np.asarray(y)[keep])):
            self.d.ellipse((px - r, py - r, px + r, py + r), fill=color)
        return int((~keep).sum())

    def polyline(self, x, y, color, width=2):
        pts = [
            (float(a), float(b))
            for a, b in zip(self.X(x), self.Y(y))
            if math.isfinite(a) and math.isfinite(b)
        ]
        if len(pts) > 1:
            self.d.line(pts, fill=color, width=width)

    def bars(self, edges, heights, color):
        for a, b, h in zip(edges[:-1], edges[1:], heights):
            if h > 0:
                self.d.rectangle(
                    (float(self.X(a)), float(self.Y(h)), float(self.X(b)), float(self.Y(0))),
                    fill=color,
                    outline=(80, 80, 80),
                )

    def vline(self, x, color=(0, 0, 0)):
        self.d.line((float(self.X(x)), self.y0, float(self.X(x)), self.y1), fill=color)

    def hline(self, y, color=(0, 0, 0)):
        self.d.line((self.x0, float(self.Y(y)), self.x1, float(self.Y(y))), fill=color)


def _fonts():
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=15), ImageFont.load_default(size=12)
    except TypeError:  # very old Pillow: bitmap font only
        f = ImageFont.load_default()
        return f, f


def _symmetric_limit(values, floor=0.1) -> float:
    v = np.abs(np.asarray(values, float))
    v = v[np.isfinite(v)]
    if v.size == 0:
        return floor
    lim = 1.15 * float(np.percentile(v, 99.5))
    step = _nice_step(lim, 4)
    return max(floor, math.ceil(lim / step) * step)


_OK, _NF, _LOW = (30, 90, 200), (210, 40, 40), (240, 150, 0)


def figure_scatter(result: MonteCarloResult, path) -> Path:
    """S16 Fig. 8: (s, l)_err of the successful samples, one panel per landmark, common axes."""
    from PIL import Image, ImageDraw

    n = len(result.names)
    ncol = min(4, max(n, 1))
    nrow = max(1, math.ceil(n / ncol))
    pw, ph = 300, 300
    W, H = 80 + ncol * (pw + 80), 60 + nrow * (ph + 90)
    im = Image.new("RGB", (W, H), "white")
    d = ImageDraw.Draw(im)
    font, small = _fonts()
    err = result.error
    lim = _symmetric_limit(err[result.ok])
    c = result.config
    d.text(
        (W / 2, 12),
        f"(s, l) error = truth - measured [px]: {c.space} space, {c.samples} {c.sampling.upper()} "
        f"samples per landmark",
        fill=(0, 0, 0),
        font=font,
        anchor="ma",
    )
    for i, name in enumerate(result.names):
        r, q = divmod(i, ncol)
        x0, y0 = 90 + q * (pw + 80), 60 + r * (ph + 90)
        ok = result.ok[i]
        ax = _Axes(
            d,
            (x0, y0, x0 + pw, y0 + ph),
            (-lim, lim),
            (-lim, lim),
            title=f"{name}: {int(ok.sum())}/{c.samples} ok",
            xlabel="sample error [px]",
            ylabel="line",
            font=font,
            small=small,
        )
        ax.hline(0.0, (150, 150, 150))
        ax.vline(0.0, (150, 150, 150))
        outside = ax.points(err[i, ok, 0], err[i, ok, 1], _OK, r=1.6)
        if ok.any():
            m = err[i, ok].mean(axis=0)
            ax.points([m[0]], [m[1]], (220, 0, 0), r=4)
        if outside:
            d.text((x0 + pw - 4, y0 + 4), f"{outside} off axes", fill=(200, 0, 0), font=small, anchor="ra")
    path = Path(path)
    im.save(path)
    return path


def figure_histograms(result: MonteCarloResult, path) -> Path:
    """Histograms of the sample and line errors (successful samples, all landmarks) with the normal
    density of the same mean and standard deviation."""
    from PIL import Image, ImageDraw

    im = Image.new("RGB", (1000, 430), "white")
    d = ImageDraw.Draw(im)
    font, small = _fonts()
    e = result.error[result.ok]
    lim = _symmetric_limit(e)
    edges = np.linspace(-lim, lim, 41)
    for k, axis in enumerate(("sample", "line")):
        v = e[:, k] if e.size else np.zeros(0)
        h, _ = np.histogram(v, edges)
        dens = h / max(v.size, 1) / (edges[1] - edges[0])
        top = max(float(dens.max()) if dens.size else 1.0, 1e-9)
        mu, sd = (float(v.mean()), float(v.std(ddof=1))) if v.size > 1 else (0.0, math.nan)
        if math.isfinite(sd) and sd > 0:
            top = max(top, 1.0 / (sd * math.sqrt(2 * math.pi)))
        x0 = 90 + k * 480
        ax = _Axes(
            d,
            (x0, 50, x0 + 380, 360),
            (-lim, lim),
            (0.0, 1.1 * top),
            title=f"{axis} error: mean {mu:+.3f}, std {sd:.3f} px (n = {v.size})",
            xlabel=f"{axis} error = truth - measured [px]",
            ylabel="density",
            font=font,
            small=small,
        )
        ax.bars(edges, dens, (150, 180, 230))
        if math.isfinite(sd) and sd > 0:
            xs = np.linspace(-lim, lim, 200)
            ax.polyline(xs, np.exp(-0.5 * ((xs - mu) / sd) ** 2) / (sd * math.sqrt(2 * math.pi)), (200, 0, 0))
        ax.vline(0.0, (120, 120, 120))
    path = Path(path)
    im.save(path)
    return path


def figure_success(result: MonteCarloResult, path) -> Path:
    """Success versus perturbation size: (left) the success, not-found and below-threshold fractions in
    bins of the a-priori pixel error |truth − a-priori|; (right) every sample at its a-priori error,
    coloured by outcome."""
    from PIL import Image, ImageDraw

    im = Image.new("RGB", (1040, 470), "white")
    d = ImageDraw.Draw(im)
    font, small = _fonts()
    ae = result.apriori_error.reshape(-1, 2)
    size = np.hypot(ae[:, 0], ae[:, 1])
    cls = np.array([status_class(s) for s in result.status.reshape(-1)])
    fin = np.isfinite(size)
    top = float(np.percentile(size[fin], 99.5)) if fin.any() else 1.0
    step = _nice_step(top, 12)
    xmax = max(step, math.ceil(top / step) * step)
    edges = np.arange(0.0, xmax + 0.5 * step, step)
    ax = _Axes(
        d,
        (90, 50, 470, 390),
        (0.0, float(edges[-1])),
        (0.0, 1.05),
        title="outcome versus a-priori pixel error",
        xlabel="|truth - a priori| [px]",
        ylabel="fraction",
        font=font,
        small=small,
    )
    idx = np.clip(np.digitize(size, edges) - 1, 0, len(edges) - 2)
    mids = 0.5 * (edges[:-1] + edges[1:])
    for label, color in (("ok", _OK), ("not-found", _NF), ("below", _LOW)):
        frac = np.full(len(mids), np.nan)
        for b in range(len(mids)):
            sel = fin & (idx == b)
            if sel.sum() >= 3:
                frac[b] = float(np.mean(cls[sel] == label))
        ax.polyline(mids, frac, color, width=2)
        ax.points(mids[np.isfinite(frac)], frac[np.isfinite(frac)], color, r=3)
    for k, (label, color) in enumerate((("success", _OK), ("not found", _NF), ("below 0.3", _LOW))):
        d.text((110 + 130 * k, 440), label, fill=color, font=font)
    lim = max(step, math.ceil(1.02 * float(np.abs(ae[fin]).max()) / step) * step) if fin.any() else 1.0
    ax2 = _Axes(
        d,
        (600, 50, 940, 390),
        (-lim, lim),
        (-lim, lim),
        title="samples at their a-priori pixel error",
        xlabel="sample: truth - a priori [px]",
        ylabel="line",
        font=font,
        small=small,
    )
    for label, color in (("ok", _OK), ("below", _LOW), ("not-found", _NF)):
        sel = fin & (cls == label)
        ax2.points(ae[sel, 0], ae[sel, 1], color, r=1.4)
    path = Path(path)
    im.save(path)
    return path


def write_figures(result: MonteCarloResult, outdir, prefix: str = "montecarlo") -> list[Path]:
    """The PNG figures: ``<prefix>_scatter.png`` (S16 Fig. 8), ``<prefix>_histograms.png``,
    ``<prefix>_success.png`` (success versus perturbation size)."""
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    return [
        figure_scatter(result, out / f"{prefix}_scatter.png"),
        figure_histograms(result, out / f"{prefix}_histograms.png"),
        figure_success(result, out / f"{prefix}_success.png"),
    ]


def default_jobs() -> int:
    """Worker processes to use by default: the CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)
