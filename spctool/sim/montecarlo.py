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
±5L cells, no pose update, linearised extraction) followed by ``refine`` steps at L = 1; the extra
steps re-extract at the current estimate so that the last correlation peak sits at a near-zero offset,
where the 3-point parabola is least biased; the converged stage fits the prediction on the photo
(:data:`MAPLET_CONVERGE_PEAK`), since the study's noisy maplets make the prediction the noisier image.
Its first step (L = 10) searches ±80 cells on the photo
resampled onto the maplet's grid extended beyond its edge (``acquire_reach``, 4σ of the a-priori pixel):
S16's search within the maplet's own 99 cells ends near ±50 cells (35 px = 2.8σ), and lost 1.1 % of
one landmark's samples beyond it (0.8 % within it to edge peaks of a third of the overlap, which the
full-overlap search does not have).  ``refine=0, acquire_reach=0`` is S16 exactly.  Image space (S16's Retina
direction, for which S16 gives no schedule) searches at L = 4, 2, 1 over ±48 px with one rendered
template, then re-renders the template at the current estimate for each of ``refine`` steps at L = 1
and for every step of the converged stage, which it stops at 0.01 px (:data:`IMAGE_CONVERGE_TOL`);
its templates have 2 × 2 rays per pixel and no cast shadows, and its converged stage fits the template on
the photo (:data:`IMAGE_TEMPLATE_SHADOWS`: the study's noisy heights cast spurious shadows); its node
slopes are SPC's (:data:`IMAGE_TEMPLATE_SLOPES`).

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

Floor.  Each landmark is also registered once with every perturbation at zero
(:func:`zero_floor`, :attr:`MonteCarloResult.floor`): its error is the model-error floor of the scene
(the onboard maplets are smoothed from a finer truth, as S16 prescribes), which the per-landmark means
are read against (report: the excess |mean − floor| per axis, with the mean's σ/√n, and a PASS/MISS per
landmark against :data:`spctool.sim.montecarlo_report.LANDMARK_TARGETS`).

Scenes and report.  The study's input — one photo with its truth and the onboard maplets, the
``s16-50m`` preset among them — is :mod:`spctool.sim.montecarlo_scene`; its output in S16 Table 3's
layout (statistics, text, JSON, CSV and figures) is :mod:`spctool.sim.montecarlo_report`.

Speed.  Everything that does not change per sample (the photo as float64, the truth pixels, the
designs) is computed once; samples run in chunks on ``jobs`` worker processes (forked where
:func:`spctool.workers.start_method` finds it safe: they start with the scene and the loaded modules,
no import, no 40 MB pickle of the photo; else spawned), each capped at one numba thread.  Maplet
space costs one registration with 12 extraction/correlation steps per sample; image space about three
template renders (:mod:`spctool.stages.render`), which dominate its cost: the coarse phase acquires
with one one-ray template of the sample's own perturbed maplet, the fine phase renders one-ray drafts
(1.6 per sample) and 2 × 2 templates (1.4; issue 39: the first one ends the stage when its move is
below :data:`IMAGE_CONVERGE_ACCEPT`).  Each sample hands its last
templates, the last per rays per pixel, to the landmark's next one (``register_sample``'s ``carry``),
whose first template of each kind starts most rays in the cell they hit (a hint only: the same
results).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np

from spctool.errors import SpcUsageError
from spctool.geometry.frames import apply_attitude_update
from spctool.stages.register import RegisterOptions, register
from spctool.workers import start_method

__all__ = [
    "PARAMETERS",
    "PRESETS",
    "S16_LANDMARKS",
    "S16_TABLE3",
    "SAMPLINGS",
    "FIELD_MODES",
    "Parameter",
    "MonteCarloConfig",
    "MonteCarloResult",
    "lhs_uniform",
    "design",
    "design_dimensions",
    "default_plan",
    "register_sample",
    "perturb",
    "run",
    "status_class",
    "default_jobs",
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

_SEED_TAG = 0x5316  # second word of every SeedSequence of the study (and its scenes' noise)
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
            self.plan = default_plan(self.space, acquire_reach=acquire_reach_for(self.sigma_scale))
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


#: the maplet plan's first-step reach (cells): 4σ of the s16-50m a-priori pixel (12.6 px = 18 cells per
#: axis at 0.70 px per cell, Table 2's sigmas), scaled by ``sigma_scale``
S16_ACQUIRE_REACH = 72


#: the image plan's search: ±IMAGE_ACQUIRE_REACH px at its first spacing (L = 4: a 25 × 25 grid, 3.8σ
#: of the a-priori pixel), then ±IMAGE_GRID_HALF bins at L = 2 and 1 and in the fine phase, where the
#: estimate is already within a bin or two (the same measurements as ±12 throughout on the s16-50m
#: preset, to 1e-13 px, for a tenth of the correlations' cost)
IMAGE_ACQUIRE_REACH = 48
IMAGE_GRID_HALF = 3

#: the image plan's converged stage stops when a step moves the estimate by less than this (px; register's
#: own default is 0.005).  Its templates are re-rendered at every step, so the last steps toward 0.005
#: cost a render each for moves far below the study's noise: on the s16-50m preset (12 × 500) the same
#: success, worst |mean| and worst 1σ as 0.005 (0.0917 / 0.0493 px against 0.0917 / 0.0492), every sample
#: within 0.013 px of its 0.005 measurement in 99 % of cases (median 0.0007 px; between 0.005 and 0.004
#: the path alone moves samples as far), 0.7 fewer renders per sample: 47 → 40 s on 2 jobs
IMAGE_CONVERGE_TOL = 0.01

#: the image plan's converged stage (issue 39, the plan's cost): its one-ray drafts run until a move is
#: below IMAGE_DRAFT_TOL px (register's 0.15; at most IMAGE_DRAFT_MAX of them), and its first 2 × 2
#: template ends it when that step moves the estimate by less than IMAGE_CONVERGE_ACCEPT px (its secant
#: move taken: :attr:`RegisterOptions.converge_accept`).  Where the drafts stopped at 0.15 px, a
#: sample's first full step moved 0.028 px (median) and a second full template followed in 90 % of the
#: samples, a third in 20 %: 2.1 of them per sample at four times a draft's rays.  Now 1.35 full templates
#: and 1.7 drafts.  The accepted move's error (a fraction of it: the secant's gain error) is a noise that
#: averages out of the means: s16-50m, 12 × 100 against the stage converged to 0.001 px, per-sample rms
#: 0.0025 px, every landmark's mean within 0.0007 px (docs/benchmarks.md "image plan's cost").  Not out
#: of one registration, so the zero-perturbation floor is registered without it (:func:`zero_floor`)
IMAGE_DRAFT_TOL = 0.05
IMAGE_DRAFT_MAX = 3
IMAGE_CONVERGE_ACCEPT = 0.03


#: the maplet plan's converged-stage estimator: the least-squares alignment with the photo's gradient as
#: regressor (:func:`spctool.stages.alignment.gradient_offset_photo`).  The study's maplets carry an
#: i.i.d. height error on every node (a third of a cell), so the prediction shaded from their slopes is
#: far noisier than the photo; with the prediction's gradient as regressor (register's ``"gradient"``)
#: that noise moved the landmarks' mean errors by up to 0.044 px from their zero-perturbation
#: registration (s16-50m, 12 × 500; docs/benchmarks.md).  The fits that choose no side
#: (``"gradient-symmetric"``, ``"gradient-weighted"``) leave 0.038 and 0.019 px of that excess
#: (measured there, not adopted)
MAPLET_CONVERGE_PEAK = "gradient-photo"

#: the image plan's templates (issue 39; s16-50m, seed 0; docs/benchmarks.md "Per-landmark targets").
#: Runs with one perturbation at a time (12 × 100) put image space's excess over the floor and its 1σ
#: on the per-node height errors (heights alone: worst excess 0.046 px, 1σ 0.045; albedo alone and all
#: the rest: ≤ 0.01 / 0.02).  Split further (heights only, the template fitted on the photo): template
#: normals from the clean maplet with the noisy one's geometry leave the excess (0.021 px) and cut the
#: 1σ (0.027); clean geometry with noisy normals removes the excess (0.008) and leaves the 1σ (0.040);
#: the noisy geometry's part is its cast shadows (templates without them: 0.011 px).  Presumably a node
#: raised by a third of a cell shades its down-Sun neighbours: a bias of the template's mean, not a noise
#: that averages out.  So the plan: the template fitted on the photo (:data:`IMAGE_CONVERGE_PEAK`, as in
#: maplet space), templates without cast shadows (:data:`IMAGE_TEMPLATE_SHADOWS`; the preset's floor is
#: the same without them, 0.072 px worst) and 2 × 2 rays per pixel at L = 1 (:data:`IMAGE_SUPERSAMPLE`:
#: the normals' noise averaged over four rays; 1σ 0.041 → 0.039 px on 12 × 100).  12 × 500: worst
#: excess 0.047 → 0.007 px, 1σ 0.049 → 0.037, 1 → 12 of 12 PASS (seed 1: 11, B02631's 1σ 0.041), for
#: twice the CPU (the coarse phase, which only acquires, renders one ray per pixel: the same verdicts,
#: worst excess 0.0067 px and 1σ 0.037, in 46 s instead of 60 s on 2 quiet cores).  It costs the
#: exact-maplet control's zero-perturbation error (0.005 → 0.059 px at
#: 2 × 2 rays: there the maplet's own 1 cm relief casts the photo's shadows), which is why register keeps
#: shadowed templates
IMAGE_CONVERGE_PEAK = "gradient-photo"
IMAGE_TEMPLATE_SHADOWS = False
IMAGE_SUPERSAMPLE = 2

#: the image plan's node slopes (issue 39): SPC's (register's).  The fourth-order central difference
#: (``"fourth"``, :func:`spctool.geometry.heightfield.fourth_order_slopes`) keeps more of the 1 cm maplets'
#: cell-scale relief in the template's shading, whose damping is most of the image floor's part common
#: to the landmarks (s16-50m zero perturbation, worst landmark 0.072 → 0.064 px, mean line floor
#: +0.021 → +0.013), but it amplifies the per-node height noise 1.34 times: 12 × 500, seed 0, worst 1σ
#: 0.037 → 0.0395 px (12 of 12 PASS); seed 1, 0.043 px and 9 of 12 PASS.  Measured, not adopted
IMAGE_TEMPLATE_SLOPES = "spc"

#: the image plan's template shading (issue 39, the image floor; docs/benchmarks.md "The image floor"):
#: ``"gouraud"``, the radiance computed at the maplet's nodes and interpolated
#: (:func:`spctool.stages.render.node_radiance`), as maplet space predicts the brightness at the nodes,
#: instead of register's ``"smooth"`` (the node slopes interpolated, then shaded).  Crossing the two
#: spaces' images at zero perturbation put the part of the floor common to the landmarks (along the
#: Sun) on the template's brightness, not on the pixel grid or the estimator; the photo averages the
#: photometric law over relief finer than the maplet, and the law is concave in the slope, so shading
#: the interpolated slopes is brighter (99 % of template pixels) than interpolating the shaded nodes.
#: s16-50m, zero perturbation: worst landmark 0.072 → 0.064 px, mean line floor +0.021 → +0.012 (maplet
#: space: +0.006, or +0.011 with the exact extraction); 12 × 500: seed 0 12 of 12 PASS (worst excess
#: 0.0067 → 0.0061 px, 1σ 0.037 → 0.038), seed 1 11 of 12 as before (B02631's 1σ 0.0410 → 0.0413); the
#: same CPU per registration (pairs' median ratio 1.03).  It costs the exact-maplet control (0.059 →
#: 0.071 px), whose photo spctool's own smooth shading rendered from the maplet's surface
IMAGE_TEMPLATE_SHADING = "gouraud"


def acquire_reach_for(sigma_scale: float) -> int:
    """The maplet plan's first-step reach (cells) for Table 2's sigmas multiplied by ``sigma_scale``."""
    return round(S16_ACQUIRE_REACH * float(sigma_scale))


def default_plan(
    space: str = "maplet",
    refine: int = 1,
    first_phases: int | None = None,
    acquire_reach: int | None = None,
    **changes,
) -> tuple[RegisterOptions, ...]:
    """The registration of one landmark in the study.

    * ``"maplet"`` — S16's driver (``retina_s16``: L = 10 … 1, ±5L cells, ρ ≥ 0.3, no pose update) with
      S16's linearised extraction (checklist §12.3, erratum 32), then ``refine`` extra steps at L = 1: each
      re-extracts at the current estimate, so the last correlation peak sits near zero offset where the
      3-point parabola is least biased ("pixel locking").  ``acquire_reach`` (cells, default
      :data:`S16_ACQUIRE_REACH`): the first step searches that far on a full-overlap extraction
      (:class:`RegisterOptions`; s16-50m 12 × 500, worst landmark's success 96.4 % with S16's search,
      99.0 % with 2 × 2 phases, 99.8 % with the reach).  ``first_phases`` (default 1): the first step
      at p × p phases.  The converged stage reads each step with :data:`MAPLET_CONVERGE_PEAK` (the
      prediction fitted on the photo; ``converge_peak="gradient"`` is register's default).
      ``refine=0, acquire_reach=0, first_phases=1, converge_peak="gradient"`` is S16's schedule
      followed by register's converged stage.
    * ``"image"`` — S16's image-space direction (Retina; S16 gives no schedule): a coarse search at
      L = 4, 2, 1, ±48 px at L = 4 (a 25 × 25 grid: the search is not limited by the maplet; the
      image-space ``acquire_reach``), then ±3 bins (:data:`IMAGE_GRID_HALF`), with the template
      rendered once (re-rendered only if its sub-pixel placement moves by more than half a bin),
      then ``refine`` steps at L = 1 that re-render the template at the current estimate every time,
      ending with register's converged stage (the coarse phase then runs its schedule only), stopped
      at moves below :data:`IMAGE_CONVERGE_TOL` (0.01 px, where register's default is 0.005), or at
      its first full template's move below :data:`IMAGE_CONVERGE_ACCEPT` (0.03 px) after one-ray drafts
      to :data:`IMAGE_DRAFT_TOL` (0.05 px; ``converge_accept=0, converge_draft_tol=0.15,
      converge_draft_max=0`` is the stage before).  Its
      templates have no cast shadows and, in the fine phase, 2 × 2 rays per pixel at L = 1 (the coarse
      phase, which only acquires, one ray), and the converged stage fits the
      template on the photo (:data:`IMAGE_SUPERSAMPLE`, :data:`IMAGE_TEMPLATE_SHADOWS`,
      :data:`IMAGE_CONVERGE_PEAK`: the study's per-node height errors cast spurious shadows and make the
      template the noisier image); its templates interpolate the radiance shaded at the nodes
      (:data:`IMAGE_TEMPLATE_SHADING`, ``"gouraud"``: the lower zero-perturbation floor);
      ``supersample=1, image_shadows=True, converge_peak="gradient", template_shading="smooth"`` is
      the plan before issue 39.

    ``changes`` are applied to every phase's :class:`RegisterOptions`.
    """
    from spctool.stages.extract import ExtractOptions

    if int(refine) != refine or refine < 0:
        raise SpcUsageError(f"refine must be an integer >= 0, got {refine!r}")
    refine = int(refine)
    if first_phases is None:
        first_phases = 1
    changes = {"first_phases": first_phases, **changes}
    if space == "maplet":
        reach = S16_ACQUIRE_REACH if acquire_reach is None else acquire_reach
        if int(reach) != reach or reach < 0:
            raise SpcUsageError(f"acquire_reach must be an integer >= 0 (cells), got {reach!r}")
        changes = {"acquire_reach": int(reach), **changes}
        opts = dict(
            schedule="retina_s16",
            space="maplet",
            extract=ExtractOptions(linearized=True, criteria=None),
            converge_peak=MAPLET_CONVERGE_PEAK,
        )
        opts.update(changes)
        spacings = tuple(opts.get("s16_spacings", RegisterOptions.s16_spacings))
        if refine and "steps" not in changes:
            opts["steps"] = tuple(("align", int(n)) for n in spacings) + (("align", 1),) * refine
        return (RegisterOptions(**opts),)
    if space == "image":
        templates = dict(
            template_shading=IMAGE_TEMPLATE_SHADING,
            supersample=IMAGE_SUPERSAMPLE,
            image_shadows=IMAGE_TEMPLATE_SHADOWS,
            converge_peak=IMAGE_CONVERGE_PEAK,
            template_slopes=IMAGE_TEMPLATE_SLOPES,
        )
        coarse = dict(
            schedule="retina_s16",
            space="image",
            **dict(templates, supersample=1),  # acquisition only: one ray per pixel suffices
            steps=(4, 2, 1),
            grid_half=IMAGE_GRID_HALF,
            acquire_reach=IMAGE_ACQUIRE_REACH,
            rerender_tol=0.5,
            converge_tol=IMAGE_CONVERGE_TOL,
        )
        if refine:  # the fine phase ends converged; the coarse one only acquires
            coarse["converge_max"] = 0
        coarse.update(changes)
        plan = [RegisterOptions(**coarse)]
        if refine:
            fine = dict(
                schedule="retina_s16",
                space="image",
                **templates,
                grid_half=IMAGE_GRID_HALF,
                rerender_tol=0.0,
                converge_tol=IMAGE_CONVERGE_TOL,
                converge_draft_tol=IMAGE_DRAFT_TOL,
                converge_draft_max=IMAGE_DRAFT_MAX,
                converge_accept=IMAGE_CONVERGE_ACCEPT,
            )
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
    one sample.  Scrambled LHS (McKay et al. 1979) drawn from the first child of ``rng``'s seed sequence
    (``rng.spawn(1)[0]``): one uniform per cell of the (n, d) array, then, per dimension, the strata
    1 … n shuffled, and ``(stratum − uniform) / n`` — the draws and the arithmetic of
    :class:`scipy.stats.qmc.LatinHypercube` (``scramble=True``, ``strength=1``) given ``rng``, value for
    value (a test holds them equal), without importing ``scipy.stats`` (0.4 s of every study's start).
    Values are kept strictly inside (0, 1) so that the normal inverse CDF stays finite."""
    if d == 0:
        return np.zeros((n, 0))
    rng = rng.spawn(1)[0]
    u = rng.uniform(size=(n, d))
    strata = np.tile(np.arange(1, n + 1), (d, 1))
    for k in range(d):
        rng.shuffle(strata[k, :])
    out = (strata.T - u) / n
    tiny = 1e-12 / max(n, 1)
    return np.clip(out, tiny, 1.0 - tiny)


def design(config: MonteCarloConfig, landmark: int) -> np.ndarray:
    """(samples, d) standard-normal design of landmark number ``landmark`` (0-based): LHS or MC from the
    stream ``(seed, 0x5316, 1, landmark)``, mapped by the normal inverse CDF (LHS; ``scipy.special.ndtri``,
    what ``scipy.stats.norm.ppf`` evaluates)."""
    from scipy.special import ndtri

    d = len(design_dimensions(config))
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, _SEED_TAG, _DESIGN, int(landmark)]))
    if config.sampling == "lhs":
        return ndtri(lhs_uniform(config.samples, d, rng))
    return rng.standard_normal((config.samples, d))


# --------------------------------------------------------------------------------------------------
# one sample


@dataclass
class Perturbed:
    """The knowledge of one sample: camera, Sun, maplet (and the a-priori pixel of V)."""

    camera: object
    sun: np.ndarray
    maplet: object  #: :class:`spctool.sim.montecarlo_scene.Knowledge` with the sample's errors
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


def perturb(scene, landmark: int, z_row, sample: int, config: MonteCarloConfig) -> Perturbed:
    """Knowledge of sample ``sample`` of landmark ``landmark`` of ``scene`` (a
    :class:`spctool.sim.montecarlo_scene.Scene`) from its design row ``z_row`` (standard normals,
    :func:`design`) and, for per-cell fields, the stream ``(seed, 0x5316, 2, landmark, sample)``."""
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
    if delta["position"].any() or delta["attitude"].any():
        changes["scobj"] = cam.scobj - delta["position"]
        changes["rotation"] = apply_attitude_update(cam.rotation, np.radians(delta["attitude"]))
    if delta["skew"][0] != 0.0:
        k = cam.kmatrix.copy()
        k[1, 0] += delta["skew"][0]
        changes["kmatrix"] = k
    if delta["center"].any():
        changes["ctr"] = cam.ctr + delta["center"]
    if delta["focal"][0] != 0.0:
        changes["mmfl"] = cam.mmfl + delta["focal"][0]
    if "distortion" in config.parameters and any(s > 0 for s in _PARAM["distortion"].sigma):
        model, coef = _owen_camera(cam)
        coef = coef.copy()
        coef[1:7] += delta["distortion"]
        changes["model"], changes["coefficients"] = model, coef
    pcam = dataclasses.replace(cam, **changes) if changes else cam
    sun = _sun_radec(scene.sun, *delta["sun"]) if delta["sun"].any() else scene.sun
    heights, albedo = m0.heights, m0.albedo
    fields_on = [n for n in ("height", "albedo") if n in config.parameters]
    if fields_on and config.fields == "cell":
        rng = np.random.default_rng(
            np.random.SeedSequence([config.seed, _SEED_TAG, _FIELDS, int(landmark), int(sample)])
        )
        noise = rng.standard_normal((2,) + m0.heights.shape)  # both drawn always: streams independent
        # the fields in place of their noise (no temporaries): noise·σ, then + the onboard grid (the sum
        # is commutative: the values of grid + noise·σ)
        if "height" in fields_on:
            heights = np.multiply(
                noise[0], _PARAM["height"].sigma[0] * config.sigma_scale / m0.scale, out=noise[0]
            )
            heights += m0.heights
        if "albedo" in fields_on:
            albedo = np.multiply(noise[1], _PARAM["albedo"].sigma[0] * config.sigma_scale, out=noise[1])
            albedo += m0.albedo
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
    #: (L, 2) truth − measured with every perturbation at zero (the model-error floor: the onboard
    #: maplet against the photo of the finer truth); NaN where that registration failed; None: not run
    floor: np.ndarray | None = None

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


def register_sample(scene, p: Perturbed, plan, carry: dict | None = None) -> object:
    """Register one perturbed landmark with every phase of ``plan``; each phase after the first starts
    at the previous phase's measurement and runs only if that one succeeded.  Returns the
    :class:`spctool.stages.register.RegisterResult` of the last phase run, with the first phase's
    a-priori pixel and the iterations of all phases.  ``carry``: a dict kept by the caller across the
    samples of a landmark, through which image space hands each sample's last template to the next
    one's first (:meth:`spctool.stages.registrar.Registrar._carried_hint`: where its rays hit; the
    results do not depend on it)."""
    # image space: the perturbed maplet's render-ready patch, built once for all phases, and the templates
    cache: dict = {} if carry is None else dict(carry)
    res = register(scene.photo, p.camera, p.sun, [p.maplet], scene.thresholds, plan[0], patch_cache=cache)
    apriori, iters = res.apriori.copy(), res.iterations.copy()
    for opts in plan[1:]:
        if res.status[0] != "ok":
            break
        res = register(
            scene.photo, p.camera, p.sun, [p.maplet], scene.thresholds, opts, apriori=res.measured,
            patch_cache=cache,
        )  # fmt: skip
        iters += res.iterations
    res.apriori, res.iterations = apriori, iters
    if carry is not None:  # templates and the settings made from the options (the patches are this sample's)
        carry.clear()
        carry.update((k, v) for k, v in cache.items() if isinstance(k, tuple))
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
    carry: dict = {}
    for k, j in enumerate(range(start, stop)):
        p = perturb(scene, landmark, designs[landmark][j], j, config)
        res = register_sample(scene, p, config.plan, carry)
        apriori[k], measured[k], rho[k], iters[k] = (
            res.apriori[0],
            res.measured[0],
            res.correlation[0],
            res.iterations[0],
        )
        status.append(res.status[0])
    return landmark, start, apriori, measured, rho, iters, status, time.process_time() - cpu0


def zero_floor(scene, config: MonteCarloConfig) -> np.ndarray:
    """(L, 2) truth − measured of every landmark registered with its knowledge unperturbed (the
    a-priori pose, maplet, camera and Sun of ``scene``, ``config.plan``): the bias the study would
    show with every Table 2 sigma at zero — the floor its per-landmark means are to be read against.
    Each converged stage ends on a verified step (``converge_accept`` off: the samples' shortcut
    leaves an error that averages out of their means, not out of one registration)."""
    out = np.full((len(scene), 2), np.nan)
    zero = {p.name: np.zeros(p.size) for p in PARAMETERS}
    plan = tuple(dataclasses.replace(o, converge_accept=0.0) if o.converge_accept else o for o in config.plan)
    for i in range(len(scene)):
        p = Perturbed(scene.camera, scene.sun, scene.maplets[i], zero)
        res = register_sample(scene, p, plan)
        if res.status[0] == "ok":
            out[i] = scene.truth[i] - res.measured[0]
    return out


def _chunks(n_landmarks: int, samples: int, size: int):
    for i in range(n_landmarks):
        for a in range(0, samples, size):
            yield i, a, min(samples, a + size)


def run(
    scene, config: MonteCarloConfig, *, jobs: int = 1, progress=None, chunk: int | None = None
) -> MonteCarloResult:
    """Run the study: every landmark of ``scene`` (a :class:`spctool.sim.montecarlo_scene.Scene`) ×
    ``config.samples`` samples (module docstring).

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
    method = "in-process"
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

        method = start_method()
        ctx = mp.get_context(method)
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
    t1 = time.perf_counter()
    floor = zero_floor(scene, config) if n_lm else np.zeros((0, 2))
    floor_s = time.perf_counter() - t1
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
            "start_method": method,
            "samples": total,
            "floor_s": floor_s,
        },
        floor=floor,
    )


def default_jobs() -> int:
    """Worker processes to use by default: the CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)
