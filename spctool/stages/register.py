"""Stage H — ``register``: measure where each landmark really is in a photo.

Specification: spc-algorithms.md §9 (Stage H: both drivers), §7.3/§8.3 (the shift and its sign), §12
(S16 checklist), §13 (defaults); L15 §3.5.2 (Eq. 3.67); S16 "Template matching loop" (Eq. 9, 11,
18–19) and "Future Retina development".

One correlation step of one landmark (:func:`correlate_landmark`)
-----------------------------------------------------------------
``space="maplet"`` (SPC; S16's baseline): the prediction P (:func:`spctool.stages.predict.predict`,
one per landmark and pose) is correlated with the photo resampled onto the maplet with its centre V
placed at the current pixel c (:func:`spctool.stages.extract.extract` with ``center_pixel=c``).  The
correlator (:mod:`spctool.stages.correlate`) returns Δ in maplet cells (x along UX, y along UY) with
C(Δ) = corr(E(m), P(m − Δ)): the feature the prediction puts at cell m lies at cell m + Δ of the
extracted image, so V appears at extracted cell Δ and

    c_new = c + J_xy·Δ                 (L15 Eq. 3.67, S16 Eq. 19; spc-algorithms.md §7.3)

with J_xy = ∂(sample, line)/∂(x, y) at V in pixels per cell (the extraction's a-priori Jacobian, S16
evaluates H at x*).

``space="image"`` (S16 "Future Retina development"): the maplet is *rendered into the photo* with the
picture's camera, the Sun, per-pixel view directions and cast shadows
(:func:`spctool.stages.render.render` of the maplet as a height patch — the renderer of the synthetic
worlds, reused), over the pixels of its footprint; that template T is correlated with the photo itself
over a window that extends (k + 1)·n pixels beyond the footprint on every side, so the search is not
limited by the maplet's extent.  Offsets are whole photo pixels (binned by n); the shift is in pixels
directly.  A template placed at displacement d (pixels, relative to the projection c₀ of V) is rendered
with rays through p − d for its fractional part (the camera's CTR moved by frac(d)) and shifted by the
integer part.  A template is rendered once per landmark and pose and reused: a whole-pixel move of the
window never needs a new one, and the step's reference is where the template actually sat (its own
phase), so reuse never biases a shift.  Steps at spacing n ≥ 2 reuse it whatever its phase
(``rerender_tol_coarse``); a spacing-1 step re-renders it when the phase moved by more than
``rerender_tol`` (0.0005 px), so a converging L = 1 loop always ends on a template rendered at its own
estimate and template reuse cannot freeze it.  Templates take one thread each
(the rays of a pixel window, the distortion inverted on a coarse grid and interpolated bicubically,
one Newton step where that is not exact to 1e-7 px:
:meth:`spctool.geometry.camera.Camera.pixel_to_direction_lattice`); :func:`register` parallelises
across landmarks instead (``threads``), with results identical to one thread.  ``template_shading``:
``smooth`` (interpolated node slopes) or ``facet`` (flat triangles, two per cell; albedo bilinear).
With ``image_shadows`` (default) shadowed pixels are *used*, dark in both images — the point of
ray-traced shadows; photo pixels then count when 0 < DN ≤ T2 (T1 is not applied; DN 0 is SPC's
missing data), template pixels where every sub-ray hit the maplet.

Drivers (:func:`register`; spc-algorithms.md §9.3)
--------------------------------------------------
* ``schedule="retina_s16"`` — per landmark, no pose update: start at the a-priori pixel (S16 Eq. 9) and
  for L = 10, 9, …, 1 correlate at spacing L (search ±5L cells, S16) and move c by J_xy·Δ (S16
  Eq. 19).  A peak on the border of the grid (``edge-peak``: the true peak lies beyond the search)
  moves c to that border maximum and repeats the step, at most ``edge_retries`` (2) times, which
  triples the first step's reach (S16's maplet-space failures are mostly a-priori errors beyond ±5L;
  in the s16-50m Monte Carlo this takes success from 97 % to 99.3 %); 0 is S16's behaviour.  A
  failed peak check ends the landmark with its status (``fail_fast``, the default; S16 does not
  say) or, with ``fail_fast=False``, keeps c and goes on.  Acceptance needs ρ ≥ 0.3.
* ``schedule="autoregister"`` — SPC's AUTOREGISTER seed (``make_scriptA.seed``): removal criteria
  ``0,50,.25,0,5`` on the first pass; align at spacing 2, then 1, drop landmarks with ρ < 0.5, align at
  spacing 1.  Every align pass correlates all landmarks at the current pose, then (``pose_update``,
  default on) solves the spacecraft position and pointing from all accepted measurements
  (:func:`spctool.stages.pose.solve_pose`, with the SUM sigmas as prior) and re-predicts and
  re-extracts with the new pose in the next pass; ``halve_shift`` applies half of each shift (the
  "option 1" of Align landmarks).

Both drivers end with a **converged full-resolution stage** when their last align step is at
spacing 1: that step is repeated (re-extracting or re-placing at the current estimate) until the
estimate moves by less than ``converge_tol`` (0.005 px), at most ``converge_max`` extra steps (10;
0 = the schedule exactly).  The coarse steps leave 0.3–1 px on tilted peaks and a single L = 1 step
only removes part of that.  The stage reads each step with ``converge_peak`` — by default the
least-squares alignment of prediction and photo at the grid peak
(:func:`spctool.stages.correlate.gradient_offset`), which is exactly zero where they agree, whereas a
vertex of the correlation surface (quadric or parabola) stays up to 0.05 px off on an asymmetric peak
however often the step is repeated (independent world, image space: 0.038 → 0.019 px rms) — and
moves by secant (Broyden) steps, so an estimator that over- or under-reads the shift converges in a
few steps to the same zero.  A small cycle (the estimate going round places
< 20·``converge_tol`` apart, e.g. an image-space template re-rendered at each sub-pixel placement)
converges to the mean of those places.  A landmark that does not settle within the cap gets the
status ``not-converged`` (its last estimate is kept in :attr:`RegisterResult.measured`, but it is not
``ok``).  AUTOREGISTER converges every landmark from its last measurement with the final pose, then
solves the pose once more from the converged pixels (``pose_update``).

Every measured landmark also carries a **measurement covariance** (:attr:`RegisterResult.covariance`,
pixels², (sample, line)): the correlation peak's covariance (:mod:`spctool.stages.correlate` item 7)
mapped to pixels, J_xy·Σ_cells·J_xyᵀ in maplet space (with the bilinear-resampling noise footprint of
cells of √|det J_xy| px), the (line, sample) offsets swapped to (sample, line) in image space.

Every constant is a field of :class:`RegisterOptions`; a schedule is a list of steps ``("align", n)``
or ``("drop", ρ_min)`` (:func:`schedule_steps`).

The schedule fits the maplet (``cap_spacing``, default on; :func:`spacing_cap`): in maplet space a step at
spacing L searches ±K·L cells, and only while K·L ≤ Q + 1 (Q the maplet's half-width) does every offset of
the grid keep about half of the maplet (Q of its 2Q + 1 cells per axis) overlapping; beyond, the binned
images overlap in a few bins, the peak's neighbours are undefined and the step ends ``not-found`` (a
49×49 maplet binned by 10 has 5 bins for an 11×11 grid).  S16's own case is the limit: L = 10 with
N = 99 searches 50 = Q + 1 cells.  Steps above the cap are replaced by one step at the cap and the
result says so (:attr:`RegisterResult.warnings`).  In image space the search runs over the photo, so
the cap only keeps the binned template at least 2·√min_valid bins across (10 by default).

Status words (cli-contract.md): ``ok``; ``not-found`` (no clearly defined peak), ``edge-peak`` (peak on
the border of the search grid), ``low-correlation`` (peak below ``corr_min``, or dropped by the
AUTOREGISTER cut); ``outside`` (V behind the camera or projecting off the photo);
``removed-<criterion>`` (Stage E removal on the first extraction); ``not-converged`` (the final
full-resolution stage did not settle within ``converge_max`` steps).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from spctool.errors import SpcUsageError
from spctool.geometry import heightfield
from spctool.stages.correlate import (
    PEAK_METHODS,
    CorrelateOptions,
    Correlation,
    correlate,
    resampled_noise_footprint,
)
from spctool.stages.extract import (
    ZENITH_EPS,
    ExtractOptions,
    _enhance_kernel,
    brt0,
    extract,
    shadow_extension,
    shadow_offsets,
)
from spctool.stages.pose import PoseError, PoseOptions, solve_pose
from spctool.stages.predict import (
    PredictOptions,
    cast_shadow_note,
    predict,
    resolve_shadows,
    unit_vector,
)

__all__ = [
    "SCHEDULES",
    "SPACES",
    "LandmarkStep",
    "RegisterOptions",
    "RegisterResult",
    "Registrar",
    "correlate_landmark",
    "register",
    "schedule_steps",
    "spacing_cap",
]

SCHEDULES = ("retina_s16", "autoregister")
SPACES = ("maplet", "image")


# --------------------------------------------------------------------------------------------------
# options


@dataclass
class RegisterOptions:
    """Every constant of Stage H (spc-algorithms.md §9.3, §13).

    * ``schedule`` — ``"retina_s16"`` or ``"autoregister"``; ``space`` — ``"maplet"`` or ``"image"``.
    * ``s16_spacings`` — S16's L sequence (10 … 1); ``autoregister_steps`` — SPC's seed
      (align 2, align 1, drop ρ < 0.5, align 1).  ``steps`` overrides either with an explicit list of
      ``("align", n)`` / ``("drop", ρ)`` (or ints meaning align at that spacing).
    * ``corr_min`` — peak acceptance (0.3, S16/GIANT); ``grid_half`` (5 → 11×11, search ±5n);
      ``min_valid`` (25 binned pixels); ``strict_8`` (all 8 neighbours below the peak).
    * ``peak`` — sub-pixel peak estimator, ``"quadric"`` (2-D least squares with the cross term) or
      ``"parabola"`` (SPC's separable fit, for legacy runs).
    * ``converge_tol`` (px, 0.005) / ``converge_max`` (10) — the final full-resolution stage (module
      docstring): repeat the last spacing-1 step until the estimate moves by less than the tolerance,
      at most this many extra steps (0: the schedule exactly, as S16/SPC run it).
    * ``converge_peak`` — the sub-pixel estimator of that stage: ``"gradient"`` (default:
      least-squares alignment at the grid peak, exactly zero when prediction and photo agree, so the
      loop stops at the least-squares alignment; :func:`spctool.stages.correlate.gradient_offset`) or
      ``"quadric"`` / ``"parabola"`` (as ``peak``; a vertex read off an asymmetric correlation surface
      keeps a bias of up to 0.05 px that re-centring cannot remove).
    * ``fail_fast`` — S16 driver: stop a landmark at its first failed step (True).
    * ``edge_retries`` — S16 driver: a step whose peak is on the border of the grid (``edge-peak``)
      moves to that border maximum and is repeated, at most this many times per step (0: S16, which
      gives up; 2 extends the first step's reach from ±5L to ±15L cells).
    * ``first_phases`` — S16 driver: the first step of a landmark (at spacing L ≥ 2) is correlated at
      this many phases per axis, its centre moved by 0, L/p, 2L/p, … cells (p = ``first_phases``), and
      the best of the p² steps is kept (an ``ok`` peak before an edge peak, then the highest ρ).  1 (the
      default) is S16.  Why: the L-cell grid of the coarsest step reads a true peak that falls between
      two grid points at a fraction of its height (ρ ≈ 0.5 where it is 0.9 on the point; s16-50m
      Monte Carlo, L = 10), and an edge peak over a third of the overlap can beat it; 2 samples the
      surface at L/2 cells.  Costs p² − 1 more steps per landmark.
    * ``pose_update`` — AUTOREGISTER driver: pose solve after each align pass (True);
      ``halve_shift`` — apply ½ of every shift (False); ``min_pose_landmarks`` — accepted landmarks
      needed for a pose solve (3).
    * ``criteria`` — Stage E removal applied at the first extraction: ``"default"`` = ``None`` (no
      removal) for retina_s16 and ``"autoregister"`` (0,50,.25,0,5) for autoregister; or any
      :class:`spctool.stages.extract.Criteria` spec, or None.
    * image space: ``supersample`` (rays per pixel axis of the template, 2; ``supersample_coarse``,
      1, for the steps at spacing ≥ 2, whose bins average n² pixels), ``converge_draft`` (True: the
      converged stage's steps render at ``supersample_coarse``, a quarter of the rays, until one
      moves the estimate by less than 0.15 px (``_DRAFT_TOL``), then at ``supersample``; it only stops on a
      full template, so the result is that template's zero; the draft steps only bring it near
      first), ``image_shadows`` (use
      shadowed pixels, True), ``rerender_tol`` (px: a spacing-1 step re-renders the template when its
      sub-pixel phase moved by more than this, 0.0005), ``rerender_tol_coarse`` (px per unit spacing, the
      same for spacing ≥ 2 steps, 1.0: never, as phases differ by < 1 px), ``template_shading``
      (``"smooth"``, the default, | ``"facet"``; chosen on the two independent worlds of issue #15
      and the s16-50m Monte Carlo, two-pass image-space rms in px, smooth vs facet — tests' world
      (27 landmarks): 0.029 vs 0.024 (facet truth), 0.028 vs 0.024 (smooth truth); benchmark world
      (96): 0.019 vs 0.020 for both truths; but facet normals differentiate height noise, and with the
      Monte Carlo's 3.33 mm height errors on 1 cm cells 10 of 12 landmarks end low-correlation —
      README "Template shading"), ``threads`` (landmarks
      registered in parallel by :func:`register`: None = numba's thread count; results do not depend
      on it), ``template_margin`` (px
      added around the projected footprint, 1), ``image_bin_fraction`` (a binned template pixel needs
      this fraction of its n² pixels on the maplet, 0.5: border bins that average only a sliver of
      template are not compared with full photo bins).
    * ``cap_spacing`` — fit the schedule to each maplet (:func:`spacing_cap`, True).
    * ``keep_images`` — keep each landmark's last Extraction / template Rendering in
      :attr:`RegisterResult.last_steps` (False: only the correlation, to bound memory).
    * ``predict``, ``extract``, ``pose`` — options of the stages called (their own defaults).
    """

    schedule: str = "retina_s16"
    space: str = "maplet"
    s16_spacings: tuple = (10, 9, 8, 7, 6, 5, 4, 3, 2, 1)
    autoregister_steps: tuple = (("align", 2), ("align", 1), ("drop", 0.5), ("align", 1))
    steps: tuple | None = None
    corr_min: float = 0.3
    grid_half: int = 5
    min_valid: int = 25
    strict_8: bool = False
    peak: str = "quadric"
    converge_tol: float = 0.005
    converge_max: int = 10
    converge_peak: str = "gradient"
    fail_fast: bool = True
    edge_retries: int = 2
    first_phases: int = 1
    pose_update: bool = True
    halve_shift: bool = False
    min_pose_landmarks: int = 3
    criteria: object = "default"
    supersample: int = 2
    supersample_coarse: int = 1
    converge_draft: bool = True
    image_shadows: bool = True
    rerender_tol: float = 0.0005
    rerender_tol_coarse: float = 1.0
    template_shading: str = "smooth"
    threads: int | None = None
    template_margin: int = 1
    image_bin_fraction: float = 0.5
    keep_images: bool = False
    cap_spacing: bool = True
    predict: PredictOptions = field(default_factory=PredictOptions)
    extract: ExtractOptions | None = None
    pose: PoseOptions = field(default_factory=PoseOptions)

    def __post_init__(self):
        if self.schedule not in SCHEDULES:
            raise SpcUsageError(f"schedule must be one of {', '.join(SCHEDULES)}, got {self.schedule!r}")
        if self.space not in SPACES:
            raise SpcUsageError(f"space must be one of {', '.join(SPACES)}, got {self.space!r}")
        if not -1.0 <= float(self.corr_min) <= 1.0:
            raise SpcUsageError(f"corr_min must lie in [-1, 1], got {self.corr_min}")
        if int(self.supersample) < 1:
            raise SpcUsageError(f"supersample must be >= 1, got {self.supersample}")
        if int(self.supersample_coarse) < 1:
            raise SpcUsageError(f"supersample_coarse must be >= 1, got {self.supersample_coarse}")
        if not float(self.rerender_tol) >= 0.0:
            raise SpcUsageError(f"rerender_tol must be >= 0, got {self.rerender_tol}")
        if not float(self.rerender_tol_coarse) >= 0.0:
            raise SpcUsageError(f"rerender_tol_coarse must be >= 0, got {self.rerender_tol_coarse}")
        if self.converge_peak not in PEAK_METHODS:
            raise SpcUsageError(
                f"converge_peak must be one of {', '.join(PEAK_METHODS)}, got {self.converge_peak!r}"
            )
        if self.template_shading not in ("smooth", "facet"):
            raise SpcUsageError(f"template_shading must be smooth or facet, got {self.template_shading!r}")
        if self.threads is not None and int(self.threads) < 1:
            raise SpcUsageError(f"threads must be >= 1, got {self.threads}")
        if not 0.0 <= float(self.image_bin_fraction) <= 1.0:
            raise SpcUsageError(f"image_bin_fraction must lie in [0, 1], got {self.image_bin_fraction}")
        if int(self.edge_retries) != self.edge_retries or int(self.edge_retries) < 0:
            raise SpcUsageError(f"edge_retries must be an integer >= 0, got {self.edge_retries}")
        self.edge_retries = int(self.edge_retries)
        if int(self.first_phases) != self.first_phases or not 1 <= int(self.first_phases) <= 4:
            raise SpcUsageError(f"first_phases must be an integer from 1 to 4, got {self.first_phases}")
        self.first_phases = int(self.first_phases)
        if not float(self.converge_tol) > 0.0:
            raise SpcUsageError(f"converge_tol must be > 0 px, got {self.converge_tol}")
        if int(self.converge_max) != self.converge_max or int(self.converge_max) < 0:
            raise SpcUsageError(f"converge_max must be an integer >= 0, got {self.converge_max}")
        self.converge_max = int(self.converge_max)
        if int(self.template_margin) < 0:
            raise SpcUsageError(f"template_margin must be >= 0, got {self.template_margin}")
        self.s16_spacings = tuple(int(n) for n in self.s16_spacings)
        schedule_steps(self)  # validates the steps
        if self.extract is None:
            crit = self.criteria
            if isinstance(crit, str) and crit == "default":
                crit = "autoregister" if self.schedule == "autoregister" else None
            self.extract = ExtractOptions(criteria=crit)
        self.correlate_options  # validates grid_half / min_valid  # noqa: B018

    @property
    def correlate_options(self) -> CorrelateOptions:
        return CorrelateOptions(
            grid_half=self.grid_half,
            min_valid=self.min_valid,
            corr_min=self.corr_min,
            strict_8=self.strict_8,
            peak=self.peak,
        )

    def as_dict(self) -> dict:
        out = {
            f.name: getattr(self, f.name)
            for f in dataclasses.fields(self)
            if f.name not in ("predict", "extract", "pose")
        }
        out["steps"] = [list(s) for s in schedule_steps(self)]
        out["predict"] = self.predict.as_dict()
        out["extract"] = self.extract.as_dict()
        out["s16_spacings"] = list(self.s16_spacings)
        out["autoregister_steps"] = [list(s) for s in self.autoregister_steps]
        out["criteria"] = out["extract"]["criteria"]
        return out


def schedule_steps(options: RegisterOptions) -> list[tuple[str, float]]:
    """The driver's steps: ``[("align", n), …, ("drop", ρ), …]`` (validated)."""
    if options.steps is not None:
        raw = options.steps
    elif options.schedule == "retina_s16":
        raw = [("align", n) for n in options.s16_spacings]
    else:
        raw = options.autoregister_steps
    steps = []
    for s in raw:
        if isinstance(s, (int, np.integer)):
            s = ("align", int(s))
        if not (isinstance(s, (tuple, list)) and len(s) == 2 and s[0] in ("align", "drop")):
            raise SpcUsageError(f"schedule step must be ('align', n) or ('drop', rho), got {s!r}")
        kind, value = s
        if kind == "align":
            if int(value) != value or int(value) < 1:
                raise SpcUsageError(f"align spacing must be an integer >= 1, got {value!r}")
            steps.append(("align", int(value)))
        else:
            if not -1.0 <= float(value) <= 1.0:
                raise SpcUsageError(f"drop threshold must lie in [-1, 1], got {value!r}")
            steps.append(("drop", float(value)))
    if not any(k == "align" for k, _ in steps):
        raise SpcUsageError("a registration schedule needs at least one align step")
    return steps


def spacing_cap(maplet, options: RegisterOptions, camera=None) -> int:
    """The largest spacing L a correlation step of ``maplet`` can work at (module docstring).

    Maplet space: K·L ≤ Q + 1 (K = ``grid_half``, Q the maplet's half-width in cells).  Image space (needs
    ``camera``): the template footprint W (px, the smaller extent of the maplet's projected square)
    binned by L keeps at least 2·√min_valid bins across.  At least 1.
    """
    n = int(np.asarray(maplet.heights).shape[0])
    q = (n - 1) // 2
    if options.space == "maplet" or camera is None:
        return max(1, (q + 1) // int(options.grid_half))
    d = q * float(maplet.scale)
    ux, uy = np.asarray(maplet.ux, float), np.asarray(maplet.uy, float)
    v = np.asarray(maplet.v, dtype=np.float64)
    corners = np.stack([v + d * (a * ux + b * uy) for a, b in ((-1, -1), (-1, 1), (1, -1), (1, 1))])
    s, ln, front = camera.project_with_mask(corners)
    if not np.all(front) or not np.all(np.isfinite(s)) or not np.all(np.isfinite(ln)):
        return max(1, (q + 1) // int(options.grid_half))
    width = min(float(np.ptp(s)), float(np.ptp(ln)))
    return max(1, int(width // (2.0 * math.sqrt(options.min_valid))))


def capped_steps(steps, cap: int) -> list:
    """``steps`` with every align spacing above ``cap`` replaced by one align step at ``cap`` (the first
    step at the cap that follows it is then not repeated)."""
    out, state = [], 0  # 0: nothing capped yet; 1: the cap step emitted; 2: its own cap step skipped
    for kind, value in steps:
        if kind == "align" and int(value) > cap:
            if state == 0:
                out.append(("align", cap))
                state = 1
            continue
        if kind == "align" and state == 1 and int(value) == cap:
            state = 2  # the schedule's own step at the cap: already done
            continue
        out.append((kind, value))
    return out


def _cap_warnings(reg, caps, top, result):
    """One note per cap value that shortened the schedule (``top``: its largest spacing)."""
    by_cap = {}
    for i, c in enumerate(caps):
        if c < top and result.status[i] == "ok":
            by_cap.setdefault(int(c), []).append(i)
    for c, idx in sorted(by_cap.items()):
        n = int(np.asarray(reg.landmarks[idx[0]].maplet.heights).shape[0])
        where = (
            f"{n}x{n}-cell maplet: the search +-K*L cells must stay within its half-width + 1, {(n + 1) // 2}"
            if reg.options.space == "maplet"
            else "template too small in the photo for coarser bins"
        )
        result.warnings.append(
            f"{len(idx)} landmark(s): spacings above L = {c} skipped ({where}; K = {reg.options.grid_half})"
        )


# --------------------------------------------------------------------------------------------------
# one landmark, one step


@dataclass
class LandmarkStep:
    """One correlation step of one landmark (:func:`correlate_landmark`)."""

    center: np.ndarray  #: (2,) pixel (sample, line) where V was placed (maplet) / the template sat (image)
    shift: np.ndarray  #: (2,) px (dsample, dline) = J_xy·Δ (maplet) or the image offset; NaN if not-found
    correlation: Correlation  #: surface, peak, status, offset (cells or (line, sample) px)
    jxy: np.ndarray | None  #: (2, 2) px per cell (maplet space)
    status: str  #: correlation status, or the extraction's removed-*/outside
    extraction: object = None  #: the Extraction (maplet space)
    template: object = None  #: the template Rendering (image space)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def measured(self) -> np.ndarray:
        return self.center + self.shift

    @property
    def covariance(self) -> np.ndarray:
        """(2, 2) covariance of :attr:`measured` in px² (sample, line): J_xy·Σ·J_xyᵀ of the correlation
        offset's covariance Σ (maplet cells), or Σ with its (line, sample) axes swapped (image space)."""
        c = np.asarray(self.correlation.covariance, dtype=np.float64)
        if self.jxy is not None:
            return self.jxy @ c @ self.jxy.T
        return c[::-1, ::-1].copy()


class _Landmark:
    """Per-landmark state reused across steps: slopes, prediction (per camera), template cache."""

    __slots__ = (
        "maplet",
        "name",
        "slopes",
        "v",
        "pred",
        "pred_camera",
        "patch",
        "tmpl",
        "tmpl_key",
        "footprint",
        "ext",
        "ext_camera",
        "shadow",
        "shadow_mode",
        "cast",
    )

    def __init__(self, maplet, name):
        self.maplet = maplet
        self.name = name
        self.slopes = heightfield.slopes(maplet.heights, maplet.valid)
        self.v = np.asarray(maplet.v, dtype=np.float64)
        self.pred = None
        self.pred_camera = None
        self.shadow_mode = None  # predict's shadows="auto", resolved on the first extraction
        self.cast = None  # the maplet's cast-shadow cells for the Registrar's Sun
        self.patch = None
        self.tmpl = None
        self.tmpl_key = None
        self.footprint = None
        self.ext = None
        self.ext_camera = None
        self.shadow = None


class Registrar:
    """Correlation steps for the landmarks of one photo (shared by :func:`register` and the CLI).

    ``photo``: array ``data[line − 1, sample − 1]`` or a Photo; ``camera``: the picture's camera;
    ``sun``: body→Sun vector; ``maplets``: objects with heights, albedo, valid, scale, v, ux, uy, uz;
    ``thresholds``: (T1, T2).
    """

    def __init__(
        self, photo, sun, maplets, thresholds=None, options: RegisterOptions | None = None, names=None
    ):
        self.options = options if options is not None else RegisterOptions()
        data = getattr(photo, "data", photo)
        self.photo = np.ascontiguousarray(data, dtype=np.float64)
        if self.photo.ndim != 2:
            raise SpcUsageError("the photo must be a 2-D array")
        self.sun = unit_vector(sun, "sun")
        t = (-math.inf, math.inf) if thresholds is None else tuple(float(x) for x in thresholds)
        self.thresholds = tuple(-math.inf if math.isnan(x) else x for x in t[:1]) + tuple(
            math.inf if math.isnan(x) else x for x in t[1:2]
        )
        names = (
            [getattr(m, "name", "") or f"#{i + 1}" for i, m in enumerate(maplets)] if names is None else names
        )
        self.landmarks = [_Landmark(m, str(n)) for m, n in zip(maplets, names)]
        self._copts = self.options.correlate_options
        #: the converged stage's correlation settings (its sub-pixel estimator)
        self._copts_final = dataclasses.replace(self._copts, peak=self.options.converge_peak)

    def __len__(self):
        return len(self.landmarks)

    # -- geometry ------------------------------------------------------------------------------
    def release(self, i: int) -> None:
        """Drop landmark ``i``'s cached prediction, extraction and template (memory)."""
        lm = self.landmarks[i]
        lm.pred = lm.pred_camera = lm.ext = lm.ext_camera = lm.tmpl = lm.tmpl_key = lm.shadow = None
        lm.footprint = None

    def project(self, camera) -> tuple[np.ndarray, np.ndarray]:
        """(pixels (N, 2), usable (N,)): projection of every V; usable = in front and inside the photo."""
        if not self.landmarks:
            return np.zeros((0, 2)), np.zeros(0, bool)
        v = np.stack([lm.v for lm in self.landmarks])
        s, ln, front = camera.project_with_mask(v)
        nln, npx = self.photo.shape
        inside = front & (s >= 1.0) & (s <= npx) & (ln >= 1.0) & (ln <= nln)
        return np.stack([s, ln], axis=-1), inside

    def prediction(self, i: int, camera, extraction=None):
        """The prediction of landmark ``i`` for ``camera`` (cached per camera).  With
        ``predict.shadows="auto"`` the landmark's first ``extraction`` decides, once, whether its cast
        shadows are predicted (:func:`spctool.stages.predict.resolve_shadows`)."""
        lm = self.landmarks[i]
        popts = self.options.predict
        if popts.shadows != "spc" and lm.cast is None:  # the Sun is the Registrar's: once per landmark
            m = lm.maplet
            sun = self.sun / np.linalg.norm(self.sun)
            lm.cast = heightfield.cast_shadows(
                np.asarray(m.heights, dtype=np.float64), np.asarray(m.valid, dtype=bool), m.ux, m.uy, m.uz,
                sun, tol=popts.shadow_tol,
            )  # fmt: skip
        if popts.shadows == "auto":
            if lm.shadow_mode is None and extraction is not None:
                valid = np.asarray(lm.maplet.valid, dtype=bool) & lm.slopes[2]
                lm.shadow_mode = resolve_shadows(lm.cast & valid, extraction.image, valid)
                lm.pred = None
            popts = dataclasses.replace(popts, shadows=lm.shadow_mode or "spc")
        if lm.pred is None or lm.pred_camera is not camera:
            lm.pred = predict(
                lm.maplet, camera.position, self.sun, popts, slopes=lm.slopes, cast_shadows=lm.cast
            )
            lm.pred_camera = camera
        return lm.pred

    def cast_shadow_landmarks(self) -> list[str]:
        """The landmarks whose prediction ``shadows="auto"`` switched to cast shadows."""
        return [lm.name for lm in self.landmarks if lm.shadow_mode == "cast"]

    # -- one step ------------------------------------------------------------------------------
    def step(
        self,
        i: int,
        camera,
        center,
        spacing: int,
        *,
        apply_criteria: bool = False,
        final: bool = False,
        draft: bool = False,
    ) -> LandmarkStep:
        """Correlate landmark ``i`` with V placed at pixel ``center`` (sample, line), spacing n
        (``final``: a step of the converged stage, with ``converge_peak``'s estimator; ``draft``: image
        space, its template rendered at ``supersample_coarse``)."""
        copts = self._copts_final if final else self._copts
        if self.options.space == "image":
            return self._image_step(i, camera, np.asarray(center, dtype=np.float64), spacing, copts, draft)
        return self._maplet_step(
            i, camera, np.asarray(center, dtype=np.float64), spacing, apply_criteria, copts
        )

    def _maplet_step(self, i, camera, center, spacing, apply_criteria, copts):
        lm = self.landmarks[i]
        ext = self.extraction(i, camera, center, apply_criteria)
        pred = self.prediction(i, camera, ext)
        # photo pixels per binned cell: the bilinear resampling shares noise between finer cells
        h_bin = spacing * math.sqrt(abs(float(np.linalg.det(ext.jxy)))) if ext.jxy is not None else 1.0
        corr = correlate(
            ext.image,
            pred.image,
            extracted_valid=ext.valid,
            predicted_valid=pred.lit,
            spacing=spacing,
            options=copts,
            noise_footprint=resampled_noise_footprint(h_bin) if h_bin > 0 else 1.0,
        )
        status = corr.status if ext.status == "ok" else ext.status
        shift = ext.jxy @ corr.offset
        del lm
        return LandmarkStep(center, shift, corr, ext.jxy, status, extraction=ext)

    def extraction(self, i: int, camera, center, apply_criteria: bool = False):
        """The photo resampled onto landmark ``i`` with V at pixel ``center`` (Stage C–E).

        The first extraction per camera is :func:`spctool.stages.extract.extract`.  Later ones at other
        centres (the S16 loop) reuse its geometry: re-centring moves every node pixel by the same
        amount (extract's own rule: proj(P_k) + (centre − proj(V)), or Eq. 11 with a new [s, l]_c), and
        the emission cut and the visibility march depend on the geometry only; so only the BRT0
        sampling and the shadow enhancement (which depends on the image) are redone.  The result is the
        same Extraction that ``extract`` would return (the removal statistics are those of the first
        extraction).  Sub-sampled cells (m > 1), the cast-shadow march and requested removal criteria
        run the full ``extract``.
        """
        lm = self.landmarks[i]
        eopts = self.options.extract
        if not apply_criteria and eopts.criteria is not None:
            eopts = dataclasses.replace(eopts, criteria=None)
        base = lm.ext
        if (
            base is None
            or lm.ext_camera is not camera
            or base.subsample != 1
            or eopts.cast_shadow_trace
            or base.status == "outside"
            or eopts.criteria is not None
        ):
            ext = extract(
                self.photo,
                lm.maplet,
                camera,
                self.sun,
                self.thresholds,
                eopts,
                center_pixel=center,
                slopes=lm.slopes,
            )
            lm.ext, lm.ext_camera = ext, camera
            lm.shadow = None
            return ext
        ds, dl = float(center[0]) - base.center_sample, float(center[1]) - base.center_line
        smp = base.sample + ds
        lin = base.line + dl
        nln, npx = self.photo.shape
        node_ok = np.isfinite(base.sample)
        covered = node_ok & (smp >= 1.0) & (smp < npx) & (lin >= 1.0) & (lin < nln)
        values = brt0(
            self.photo,
            np.where(node_ok, smp, 0.0),
            np.where(node_ok, lin, 0.0),
            self.thresholds[0],
            self.thresholds[1],
            repair_floor=eopts.repair_floor,
        )
        lit = node_ok & (values > 0.0)
        image = np.where(lit, values, 0.0)
        removed_shadow = np.zeros(image.shape, dtype=bool)
        if eopts.apply_filter:
            # the extract filter's step 1 (shadow enhancement: extract_filter's own offsets and kernel,
            # computed once per landmark and camera), then steps 2–3 from the first extraction's mask
            if lm.shadow is None:
                lm.shadow = self._shadow_offsets(lm, base)
            if lm.shadow is not False:
                checks, zeros = lm.shadow
                zero = np.zeros(image.shape, dtype=bool)
                edges = np.zeros(image.shape, dtype=bool)
                nonzero = image > 0.0
                _enhance_kernel(nonzero, checks, zeros, zero, edges)
                removed_shadow = zero & nonzero
                image[zero] = 0.0
            image = np.where(base.visible, image, 0.0)
        return dataclasses.replace(
            base,
            image=image,
            valid=image > 0.0,
            covered=covered,
            lit=lit,
            removed_shadow=removed_shadow,
            sample=smp,
            line=lin,
            center_sample=float(center[0]),
            center_line=float(center[1]),
            status="ok",  # criteria were not requested (else the full path ran); "outside" never gets here
        )

    def _shadow_offsets(self, lm: _Landmark, base):
        """(checks, zeros) of the shadow enhancement for this landmark and camera, or False when the Sun
        is at the maplet zenith — exactly as :func:`spctool.stages.extract.extract_filter` computes them."""
        eopts = self.options.extract
        m = lm.maplet
        s_m = heightfield.to_maplet_components(self.sun, m.ux, m.uy, m.uz)
        s_xy = math.hypot(s_m[0], s_m[1])
        if not s_xy > ZENITH_EPS * float(np.linalg.norm(s_m)):
            return False
        n = np.asarray(m.heights).shape[0]
        ds = shadow_extension(base.det_j, eopts.ds_mode, eopts.ds_base, cap=2 * n)
        return shadow_offsets(
            (s_m[0] / s_xy, s_m[1] / s_xy),
            ds,
            eopts.lateral,
            eopts.lateral_band,
            eopts.shadow_include_edge,
            eopts.edge_steps,
        )

    def _template(self, lm: _Landmark, camera, frac, spacing: int = 1, draft: bool = False):
        """Rendering of the maplet for a placement whose fractional part is ``frac`` (sample, line).

        Returns ``(rendering or None, fractional offset rendered, window (s0, s1, l0, l1))``; the cached
        template is reused while the camera is the same and ``frac`` moved by ≤ ``rerender_tol`` (spacing
        1) or ≤ ``rerender_tol_coarse``·n (spacing n ≥ 2: the correlation bins n pixels, and the shift is
        measured from where the template sat, so its phase only matters for the final steps).
        """
        from spctool.stages.render import HeightPatch, Rendering, RenderOptions, _PatchSet, render

        if lm.patch is None:
            m = lm.maplet
            patch = HeightPatch(
                m.heights, m.scale, m.v, m.ux, m.uy, m.uz, albedo=m.albedo, valid=m.valid, name=lm.name
            )
            lm.patch = _PatchSet([patch])  # packed once per landmark, reused by every render
        patch = lm.patch.patches[0]
        tol = self.options.rerender_tol if spacing <= 1 else self.options.rerender_tol_coarse * spacing
        # coarse steps bin n pixels: their template needs fewer rays per pixel (supersample_coarse)
        nss = int(self.options.supersample if spacing <= 1 and not draft else self.options.supersample_coarse)
        if (
            lm.tmpl is not None
            and lm.tmpl_key[0] is camera
            and np.max(np.abs(lm.tmpl_key[1] - frac)) <= tol
            and lm.tmpl.options.supersample >= nss
        ):
            return lm.tmpl, lm.tmpl_key[1], lm.tmpl_key[2]
        if lm.footprint is None or lm.footprint[0] is not camera:
            lm.footprint = (camera, self._footprint(patch, camera))
        if lm.footprint[1] is None:
            return None, frac, None
        s0, s1, l0, l1 = lm.footprint[1]
        # rays through p − frac: the same camera with its CTR moved by frac
        shifted = camera.with_ctr(camera.ctr + frac)
        ropts = RenderOptions(
            photometry=self.options.predict.photometry,
            supersample=nss,
            shadows=bool(self.options.image_shadows),
            shading=self.options.template_shading,
            ray_inverse="grid",
            threads=1,
        )
        shp = (l1 - l0 + 1, s1 - s0 + 1)
        rad = np.zeros(shp)
        cov = np.zeros(shp)
        cs0, cl0 = max(s0, 1), max(l0, 1)  # render() windows are 1-based; pixels left of/above 1 stay sky
        if cs0 <= s1 and cl0 <= l1:
            part = render(shifted, self.sun, None, lm.patch, ropts, window=(cs0, s1, cl0, l1))
            rad[cl0 - l0 :, cs0 - s0 :] = part.radiance
            cov[cl0 - l0 :, cs0 - s0 :] = part.coverage
        rend = Rendering(rad, cov, np.zeros(shp), np.zeros(shp, np.int16), (s0, s1, l0, l1), ropts)
        lm.tmpl, lm.tmpl_key = rend, (camera, frac.copy(), (s0, s1, l0, l1))
        return rend, frac.copy(), (s0, s1, l0, l1)

    def _footprint(self, patch, camera):
        """The template window (s0, s1, l0, l1): the projection of the maplet's border nodes, plus
        ``template_margin``; None when a border node is behind the camera."""
        q = patch.qsz
        t = np.arange(-q, q + 1, dtype=np.float64)
        edge = np.concatenate(
            [
                np.stack([t, np.full_like(t, -q)], 1),
                np.stack([t, np.full_like(t, q)], 1),
                np.stack([np.full_like(t, -q), t], 1),
                np.stack([np.full_like(t, q), t], 1),
            ]
        )
        h = patch.interpolate(edge[:, 0], edge[:, 1])[0]
        s, ln, front = camera.project_with_mask(patch.to_body(np.column_stack([edge, h])))
        if not np.all(front):
            return None
        mg = int(self.options.template_margin)
        s0, s1 = int(math.floor(s.min())) - mg, int(math.ceil(s.max())) + mg
        l0, l1 = int(math.floor(ln.min())) - mg, int(math.ceil(ln.max())) + mg
        return s0, s1, l0, l1

    def _image_step(self, i, camera, center, spacing, copts, draft=False):
        lm = self.landmarks[i]
        c0 = np.asarray(camera.project(lm.v[None, :]), dtype=np.float64).reshape(2)
        disp = center - c0
        frac = disp - np.round(disp)
        rend, f_t, window = self._template(lm, camera, frac, spacing, draft)
        g = 2 * self._copts.grid_half + 1
        if rend is None:
            corr = Correlation(
                np.full((g, g), np.nan),
                np.zeros((g, g), np.int64),
                spacing,
                "not-found",
                math.nan,
                None,
                (math.nan, math.nan),
            )
            return LandmarkStep(center, np.full(2, np.nan), corr, None, "outside")
        placement_int = np.round(disp - f_t)
        placement = placement_int + f_t
        s0, s1, l0, l1 = window
        di_s, di_l = int(placement_int[0]), int(placement_int[1])
        tmpl = rend.radiance
        tvalid = rend.coverage >= 1.0 - 1e-12
        if not self.options.image_shadows:
            tvalid &= tmpl > 0.0
        # photo crop: the template window moved by the integer placement, plus the search margin
        marg = (self._copts.grid_half + 1) * int(spacing)
        cl_lo, cl_hi = l0 + di_l - marg, l1 + di_l + marg
        cs_lo, cs_hi = s0 + di_s - marg, s1 + di_s + marg
        crop = np.zeros((cl_hi - cl_lo + 1, cs_hi - cs_lo + 1))
        nln, npx = self.photo.shape
        a_lo, a_hi = max(cl_lo, 1), min(cl_hi, nln)
        b_lo, b_hi = max(cs_lo, 1), min(cs_hi, npx)
        inside = np.zeros(crop.shape, bool)
        if a_lo <= a_hi and b_lo <= b_hi:
            crop[a_lo - cl_lo : a_hi - cl_lo + 1, b_lo - cs_lo : b_hi - cs_lo + 1] = self.photo[
                a_lo - 1 : a_hi, b_lo - 1 : b_hi
            ]
            inside[a_lo - cl_lo : a_hi - cl_lo + 1, b_lo - cs_lo : b_hi - cs_lo + 1] = True
        t1, t2 = self.thresholds
        cvalid = inside & np.isfinite(crop) & (crop > 0.0) & (crop <= t2)  # DN 0 = no data (SPC)
        if not self.options.image_shadows:
            cvalid &= crop >= t1
        # anchors: the template pixel nearest to V's rendered position, and where it sits in the crop
        a_s = int(np.clip(round(c0[0] + f_t[0]), s0, s1))
        a_l = int(np.clip(round(c0[1] + f_t[1]), l0, l1))
        p_anchor = (a_l - l0, a_s - s0)
        e_anchor = (a_l + di_l - cl_lo, a_s + di_s - cs_lo)
        copts = dataclasses.replace(
            copts, min_value=None, bin_min_fraction=self.options.image_bin_fraction
        )
        corr = correlate(
            crop,
            tmpl,
            extracted_valid=cvalid,
            predicted_valid=tvalid,
            spacing=spacing,
            options=copts,
            extracted_anchor=e_anchor,
            predicted_anchor=p_anchor,
        )
        shift = np.array([corr.offset[1], corr.offset[0]])  # (line, sample) axes → (dsample, dline)
        # the step's reference is where the template actually sat
        return LandmarkStep(c0 + placement, shift, corr, None, corr.status, template=rend)


def correlate_landmark(
    photo,
    camera,
    sun,
    maplet,
    center=None,
    spacing: int = 1,
    thresholds=None,
    options: RegisterOptions | None = None,
) -> LandmarkStep:
    """One correlation step of one landmark at pixel ``center`` (default: projection of V)."""
    reg = Registrar(photo, sun, [maplet], thresholds, options)
    if center is None:
        center = reg.project(camera)[0][0]
    return reg.step(0, camera, center, spacing)


# --------------------------------------------------------------------------------------------------
# drivers


@dataclass
class RegisterResult:
    """Per-landmark outcome of :func:`register` (arrays (N, …), pixels (sample, line), SPC 1-based)."""

    names: list[str]
    apriori: np.ndarray  #: (N, 2) a-priori pixel (table pixel or projection with the input pose)
    measured: np.ndarray  #: (N, 2) measured pixel; NaN unless status is ok
    correlation: np.ndarray  #: (N,) peak ρ of the last correlation (NaN if none)
    iterations: np.ndarray  #: (N,) correlation steps run
    spacing: np.ndarray  #: (N,) spacing of the last step
    status: list[str]
    camera: object  #: final camera (pose updated by the AUTOREGISTER driver)
    pose: object = None  #: last PoseResult (AUTOREGISTER with pose_update), else None
    passes: list = field(default_factory=list)  #: per align pass: dict(spacing, ok, pose_solved, …)
    last_steps: list = field(default_factory=list)  #: the last LandmarkStep of every landmark (or None)
    warnings: list = field(default_factory=list)
    options: RegisterOptions | None = None
    #: (N, 2, 2) measurement covariance of ``measured`` in px² (sample, line); NaN unless ok
    covariance: np.ndarray | None = None

    def __len__(self):
        return len(self.names)

    def sigmas(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(sigma_sample, sigma_line, rho_sl) of :attr:`covariance` (px, px, correlation; NaN if none)."""
        n = len(self)
        c = self.covariance if self.covariance is not None else np.full((n, 2, 2), np.nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            ss = np.sqrt(c[:, 0, 0])
            sl = np.sqrt(c[:, 1, 1])
            rho = c[:, 0, 1] / (ss * sl)
        return ss, sl, rho

    @property
    def ok(self) -> np.ndarray:
        return np.array([s == "ok" for s in self.status], dtype=bool)

    @property
    def shift(self) -> np.ndarray:
        """(N, 2) measured − a-priori (NaN unless ok)."""
        return self.measured - self.apriori

    def status_counts(self) -> dict:
        out: dict[str, int] = {}
        for s in self.status:
            out[s] = out.get(s, 0) + 1
        return out

    def to_table(self, picture=None, command="register", meta=None):
        """The landmark table (cli-contract.md): sample/line = measured pixel when ok, else the
        a-priori pixel; apriori_sample/line; dsample/dline = measured − a-priori; correlation;
        iterations; spacing (last); sigma_sample, sigma_line, rho_sl (the measurement covariance:
        1σ in px and the correlation of the two axes, NaN unless ok); status."""
        from spctool.formats.table import LandmarkTable

        ok = self.ok
        best = np.where(ok[:, None], self.measured, self.apriori) if len(self) else np.zeros((0, 2))
        d = self.shift
        cols = {
            "name": list(self.names),
            "sample": best[:, 0],
            "line": best[:, 1],
            "apriori_sample": self.apriori[:, 0].copy(),
            "apriori_line": self.apriori[:, 1].copy(),
            "dsample": d[:, 0],
            "dline": d[:, 1],
            "correlation": self.correlation.astype(np.float64),
            "iterations": self.iterations.astype(np.int64),
            "spacing": self.spacing.astype(np.int64),
        }
        cols["sigma_sample"], cols["sigma_line"], cols["rho_sl"] = self.sigmas()
        cols["status"] = list(self.status)
        return LandmarkTable(cols, picture=picture, command=command, meta=dict(meta or {}))


def register(
    photo,
    camera,
    sun,
    maplets,
    thresholds=None,
    options: RegisterOptions | None = None,
    *,
    apriori=None,
    names=None,
    positions=None,
    prior_sigma_position=None,
    prior_sigma_attitude=None,
    progress=None,
) -> RegisterResult:
    """Stage H: measure the landmarks of ``maplets`` in ``photo`` (module docstring).

    ``apriori`` (N, 2): starting pixels (e.g. the lithos-select table); rows with NaN — or no array —
    start at the projection of V with ``camera``.  ``positions`` (N, 3): body-fixed landmark positions
    for the pose solve (default: each maplet's V).  ``prior_sigma_*``: SUM SIGMA_VSO (km) and SIGMA_PTG
    (rad) for the pose solve.  ``progress(n)`` is called as landmarks are processed.
    """
    opts = options if options is not None else RegisterOptions()
    reg = Registrar(photo, sun, maplets, thresholds, opts, names)
    n = len(reg)
    steps = schedule_steps(opts)
    proj, usable = reg.project(camera)
    start = proj.copy()
    if apriori is not None:
        ap = np.asarray(apriori, dtype=np.float64).reshape(n, 2)
        given = np.all(np.isfinite(ap), axis=1)
        start[given] = ap[given]
    apri = start.copy()
    measured = np.full((n, 2), np.nan)
    corr = np.full(n, np.nan)
    iters = np.zeros(n, np.int64)
    spac = np.zeros(n, np.int64)
    status = ["ok" if u else "outside" for u in usable]
    last = [None] * n
    tick = progress or (lambda k=1: None)
    result = RegisterResult(
        [lm.name for lm in reg.landmarks],
        apri,
        measured,
        corr,
        iters,
        spac,
        status,
        camera,
        options=opts,
        covariance=np.full((n, 2, 2), np.nan),
    )
    top = max(int(v) for k, v in steps if k == "align")
    caps = np.array(
        [spacing_cap(lm.maplet, opts, camera) if opts.cap_spacing else top for lm in reg.landmarks],
        dtype=np.int64,
    )
    _cap_warnings(reg, caps, top, result)
    if opts.schedule == "retina_s16":
        workers = _image_workers(opts, n)
        if workers > 1:
            _parallel_s16(reg, camera, steps, start, result, last, tick, workers, caps)
        else:
            _drive_s16(reg, camera, steps, start, result, last, tick, caps)
    else:
        pos = (
            (np.stack([lm.v for lm in reg.landmarks]) if n else np.zeros((0, 3)))
            if positions is None
            else np.asarray(positions, dtype=np.float64).reshape(n, 3)
        )
        _drive_autoregister(
            reg,
            camera,
            steps,
            start,
            result,
            last,
            pos,
            prior_sigma_position,
            prior_sigma_attitude,
            tick,
            caps,
        )
    result.last_steps = last
    bad = ~result.ok
    result.covariance[bad] = np.nan
    cast = reg.cast_shadow_landmarks()
    if cast:
        result.warnings.append(cast_shadow_note(cast, reg.thresholds[0]))
    return result


def _image_workers(opts: RegisterOptions, n: int) -> int:
    """Threads for the landmarks of an image-space S16 run (maplet space stays on one thread: its small
    numpy steps hold the GIL)."""
    if opts.space != "image" or n < 2:
        return 1
    if opts.threads is None:
        import numba

        return min(n, int(numba.get_num_threads()))
    return min(n, int(opts.threads))


def _parallel_s16(reg: Registrar, camera, steps, start, result, last, tick, workers: int, caps):
    """:func:`_drive_s16` with the landmarks spread over ``workers`` threads, one landmark per task.

    Landmarks are independent (their own template, crop and state; the photo is only read), and the
    render and correlation kernels release the GIL; every landmark runs exactly the computation of the
    one-thread driver, so the result does not depend on ``workers`` (``tests/test_register.py``).
    """
    import threading
    from concurrent.futures import ThreadPoolExecutor

    lock = threading.Lock()

    def locked_tick(k=1):
        with lock:
            tick(k)

    def one(i):
        sub = copy.copy(reg)  # shares the photo and caches; its own landmark list
        sub.landmarks = [reg.landmarks[i]]
        part = RegisterResult(
            [result.names[i]],
            result.apriori[i : i + 1],
            result.measured[i : i + 1].copy(),
            result.correlation[i : i + 1].copy(),
            result.iterations[i : i + 1].copy(),
            result.spacing[i : i + 1].copy(),
            [result.status[i]],
            camera,
            options=result.options,
            covariance=result.covariance[i : i + 1].copy(),
        )
        sub_last = [None]
        _drive_s16(sub, camera, steps, start[i : i + 1], part, sub_last, locked_tick, caps[i : i + 1])
        return i, part, sub_last[0]

    with ThreadPoolExecutor(workers) as pool:
        for i, part, st in pool.map(one, range(len(reg))):
            result.measured[i] = part.measured[0]
            result.correlation[i] = part.correlation[0]
            result.iterations[i] = part.iterations[0]
            result.spacing[i] = part.spacing[0]
            result.status[i] = part.status[0]
            result.covariance[i] = part.covariance[0]
            result.warnings.extend(part.warnings)
            last[i] = st


def _record(result, last, i, st: LandmarkStep, keep_images: bool):
    last[i] = st if keep_images else dataclasses.replace(st, extraction=None, template=None)
    result.iterations[i] += 1
    result.spacing[i] = st.correlation.spacing
    result.correlation[i] = st.correlation.peak


def _converges(steps, opts) -> bool:
    """The final full-resolution stage runs when the last align step is at spacing 1."""
    last_align = [v for k, v in steps if k == "align"][-1]
    return opts.converge_max > 0 and int(last_align) == 1


#: a cycle of the final stage (the estimate returns to where it was some steps before) whose
#: diameter is below this many converge_tol (0.1 px at the default 0.005 px: about the 1σ of an image-space
#: measurement) is resolved to the mean of its places
_CYCLE_FACTOR = 20.0


def _broyden_step(jac, f, dc, df):
    """The secant (Broyden) update of the final stage's Jacobian estimate ``jac`` of F(c) = (where the
    step says V is) − c, given the last move ``dc`` and the change ``df`` of F; then the step −jac⁻¹·F.
    Falls back to the plain step F (jac = −I) when the update leaves the Jacobian far from −I (a gain
    outside 0.2–5 on an axis, a turn, or a singular matrix): the secant then measured noise, not gain."""
    minus_i = -np.eye(2)
    if dc is not None:
        den = float(dc @ dc)
        if den > 0.0:
            jac = jac + np.outer(df - jac @ dc, dc) / den
    g = -jac
    eig = np.linalg.eigvals(g)
    if not (np.all(np.isfinite(eig)) and np.all(np.abs(eig.imag) <= 0.5 * np.abs(eig.real))):
        return minus_i, f.copy()
    if not (np.all(eig.real >= 0.2) and np.all(eig.real <= 5.0)):
        return minus_i, f.copy()
    return jac, np.linalg.solve(g, f)


#: the converged stage's draft steps (``converge_draft``) end with the first that moves by less than this
_DRAFT_TOL = 0.15


def _drafts(opts) -> bool:
    """The converged stage starts with draft steps: image space, whose coarse templates have fewer rays."""
    return (
        bool(opts.converge_draft)
        and opts.space == "image"
        and int(opts.supersample_coarse) < int(opts.supersample)
    )


def _converge(reg: Registrar, i, camera, c, moved, result, last, factor, seed=None, draft=False):
    """Repeat the spacing-1 step of landmark ``i`` from pixel ``c`` until the estimate moves by less
    than ``converge_tol`` (``moved``: the move of the step that produced ``c``; the stage runs at least
    once when its estimator ``converge_peak`` is not the schedule's ``peak``, unless ``seed`` = (c, F)
    says the schedule's last step was already read with it).  Returns
    ``(status, c, step)``: ``"ok"``; a failed step's status; or ``"not-converged"`` after
    ``converge_max`` extra steps (``c`` is then the last estimate).  ``step`` is the last ok step.

    The moves are secant (Broyden) steps on F(c) = (where the step puts V) − c, whose zero is the
    converged estimate: the first is the plain step F (or, with a ``seed``, already a secant step),
    later ones divide by the gain the previous
    steps measured (a least-squares alignment whose central-difference gradients underestimate a sharp
    template's slope overshoots by up to 1.7×, which plain steps would turn into a slow oscillation).
    The zero, and so the result, does not depend on the steps taken; ``halve_shift`` keeps plain
    half steps.

    A cycle — the estimate goes round two, three or four places, as an image-space template
    re-rendered at each sub-pixel placement can make it (0.01–0.09 px in the s16-50m Monte Carlo) —
    is detected when a step returns within ``converge_tol`` of an estimate two or more steps before;
    if the places of the cycle are less than ``_CYCLE_FACTOR``·``converge_tol`` apart, their mean is
    the converged estimate (``ok``).

    ``draft`` (``converge_draft``, image space): the steps render their templates at
    ``supersample_coarse`` until one moves by less than ``_DRAFT_TOL``; from then on at
    ``supersample``, with the secant Jacobian kept but no secant across the change of template (a
    draft and a full template read slightly different zeros).  ``draft`` says whether ``seed`` came
    from a draft step.  The stage ends only on a full step."""
    opts = reg.options
    tol = opts.converge_tol
    if opts.converge_peak != opts.peak and seed is None:
        moved = math.inf  # at least one step reads the estimate with the stage's own estimator
    st_ok = None
    hist = [np.asarray(c, dtype=np.float64)]
    jac = -np.eye(2)
    prev = seed  # (c, F) of the previous step (``seed``: the schedule's last step, read the same way)
    if draft and moved < _DRAFT_TOL:  # the seed's draft already came close: full templates now
        draft, prev, moved = False, None, math.inf
    k = 0
    while not moved < tol:
        if k >= opts.converge_max:
            return "not-converged", c, st_ok
        st = reg.step(i, camera, c, 1, final=True, draft=draft)
        _record(result, last, i, st, opts.keep_images)
        k += 1
        if not st.ok:
            return st.status, c, st_ok
        f = st.center + st.shift - c
        if factor != 1.0:
            move = factor * f
        else:
            dc, df = (None, None) if prev is None else (c - prev[0], f - prev[1])
            jac, move = _broyden_step(jac, f, dc, df)
            scale = float(np.hypot(*move))
            if scale > 1.0:  # never more than a pixel per step (the linear range of the estimator)
                move = move / scale
        prev = (c, f)
        new = c + move
        moved = float(np.hypot(*(new - c)))
        if draft:
            if moved < _DRAFT_TOL:  # close: the next steps read full templates, from here
                draft, prev, moved = False, None, math.inf
                hist = []
            c = new
            hist.append(c)
            continue
        st_ok = st
        back = [j for j in range(len(hist) - 1) if np.hypot(*(new - hist[j])) < tol]
        if back and moved >= tol:
            cycle = np.array(hist[back[-1] :])
            span = np.max(np.hypot(*(cycle[:, None, :] - cycle[None, :, :]).transpose(2, 0, 1)))
            if span < _CYCLE_FACTOR * tol:
                return "ok", cycle.mean(axis=0), st_ok
        c = new
        hist.append(c)
    return "ok", c, st_ok


def _phase_key(st: LandmarkStep):
    """Order of the phases of a first step: an ``ok`` peak, then an edge peak, then the highest ρ.

    An interior peak before a higher edge peak: in the s16-50m Monte Carlo (12 × 500) this loses no
    sample that started within 31.9 px (the reach is 35 px), where ranking by ρ alone lost six
    (5.7–23.6 px off) to small-overlap edge peaks while rescuing five beyond the reach."""
    peak = st.correlation.peak
    return (st.status == "ok", st.status == "edge-peak", peak if np.isfinite(peak) else -np.inf)


def _phased_first_step(reg: Registrar, i, camera, c, n: int, st0: LandmarkStep, result, last):
    """The first step of landmark ``i`` at spacing ``n`` repeated with its centre moved by k·n/p cells
    per axis (k = 0 … p − 1, p = ``first_phases``; image space: pixels); the best step by
    :func:`_phase_key` (``st0``, the step at ``c`` itself, on ties)."""
    opts = reg.options
    p = opts.first_phases
    to_px = st0.jxy if st0.jxy is not None else np.eye(2)  # cells → pixels (maplet space)
    if st0.status.startswith("removed-") or st0.status == "outside" or not np.all(np.isfinite(to_px)):
        return st0  # a landmark its criteria removed, or off the photo, stays so
    best = st0
    for a in range(p):
        for b in range(p):
            if a == 0 and b == 0:
                continue
            move = to_px @ (np.array([a, b], dtype=np.float64) * (n / p))
            st = reg.step(i, camera, c + move, n, apply_criteria=True)
            _record(result, last, i, st, opts.keep_images)
            if _phase_key(st) > _phase_key(best):
                best = st
    if best is not st0:  # the kept step is the landmark's last one
        _record(result, last, i, best, opts.keep_images)
        result.iterations[i] -= 1
    return best


def _drive_s16(reg: Registrar, camera, steps, start, result, last, tick, caps):
    opts = reg.options
    factor = 0.5 if opts.halve_shift else 1.0
    converge = _converges(steps, opts)
    for i in range(len(reg)):
        if result.status[i] != "ok":
            tick()
            continue
        c = start[i].copy()
        state = None
        first = True
        moved = math.inf
        st_ok = None
        plan = list(capped_steps(steps, int(caps[i])))
        aligns = [k for k, (kind, _) in enumerate(plan) if kind == "align"]
        # the schedule's last step at spacing 1 is the converged stage's first: read it with its estimator
        final_at = aligns[-1] if converge and aligns and int(plan[aligns[-1]][1]) == 1 else -1
        seed = None  # (c, F) of the schedule's last step when the converged stage's estimator read it
        for at, (kind, value) in enumerate(plan):
            final = at == final_at
            if kind == "drop":
                if state == "ok" and not result.correlation[i] >= value:
                    state = "low-correlation"
                    break
                continue
            draft = final and _drafts(opts)  # the converged stage's first step: a draft template
            st = reg.step(i, camera, c, int(value), apply_criteria=first, final=final, draft=draft)
            _record(result, last, i, st, opts.keep_images)
            if first and opts.first_phases > 1 and int(value) >= 2 and not final:
                st = _phased_first_step(reg, i, camera, c, int(value), st, result, last)
            first = False
            retries = 0
            while st.status == "edge-peak" and retries < opts.edge_retries and np.all(np.isfinite(st.shift)):
                # the maximum on the border of the grid: the peak lies beyond the search; go there
                c = st.center + st.shift
                st = reg.step(i, camera, c, int(value), final=final, draft=draft)
                _record(result, last, i, st, opts.keep_images)
                retries += 1
            if st.status.startswith("removed-") or st.status == "outside":
                state = st.status
                break
            if st.ok:
                new = st.center + factor * st.shift
                moved = float(np.hypot(*(new - c)))
                seed = (c, st.center + st.shift - c) if final else None
                c = new
                state = "ok"
                st_ok = st
            else:
                state = st.status
                moved = math.inf
                if opts.fail_fast:
                    break
        if state == "ok" and converge and int(st_ok.correlation.spacing) == 1:
            state, c, st_c = _converge(
                reg, i, camera, c, moved, result, last, factor, seed, draft=final_at >= 0 and _drafts(opts)
            )
            st_ok = st_c or st_ok
        result.status[i] = state or "not-found"
        if result.status[i] in ("ok", "not-converged"):
            result.measured[i] = c
            result.covariance[i] = st_ok.covariance
        reg.release(i)
        tick()


def _drive_autoregister(
    reg: Registrar, camera, steps, start, result, last, positions, sig_pos, sig_att, tick, caps
):
    opts = reg.options
    factor = 0.5 if opts.halve_shift else 1.0
    n = len(reg)
    active = np.array([s == "ok" for s in result.status], dtype=bool)
    centre = start.copy()
    first = True
    cam = camera
    for kind, value in steps:
        if kind == "drop":
            low = active & ~(result.correlation >= value)
            for i in np.flatnonzero(low):
                result.status[i] = "low-correlation"
                result.measured[i] = np.nan
            active &= ~low
            continue
        spacing = int(value)
        ok_pass = np.zeros(n, bool)
        for i in np.flatnonzero(active):
            st = reg.step(i, cam, centre[i], min(spacing, int(caps[i])), apply_criteria=first)
            _record(result, last, i, st, opts.keep_images)
            result.status[i] = st.status
            if st.status.startswith("removed-") or st.status == "outside":
                active[i] = False
                result.measured[i] = np.nan
            elif st.ok:
                ok_pass[i] = True
                result.measured[i] = st.center + factor * st.shift
                result.covariance[i] = st.covariance
            else:
                result.measured[i] = np.nan
            if opts.pose_update:  # the next pass has a new camera: nothing cached is reused
                reg.release(i)
            tick()
        first = False
        info = {
            "spacing": spacing,
            "ok": int(ok_pass.sum()),
            "attempted": int(active.sum()),
            "pose_solved": False,
        }
        if opts.pose_update and ok_pass.sum() >= max(1, int(opts.min_pose_landmarks)):
            meas = np.where(ok_pass[:, None], result.measured, np.nan)
            try:
                pr = solve_pose(cam, positions, meas, opts.pose, sig_pos, sig_att, names=result.names)
            except PoseError as exc:
                result.warnings.append(f"pass at spacing {spacing}: pose not updated ({exc})")
            else:
                cam = cam.with_pose(scobj=pr.scobj, rotation=pr.rotation)
                result.pose = pr
                info["pose_solved"] = True
                info["rms_after_px"] = float(pr.rms_after)
                proj, inside = reg.project(cam)
                centre = np.where(np.isfinite(proj), proj, centre)
        elif opts.pose_update:
            result.warnings.append(
                f"pass at spacing {spacing}: {int(ok_pass.sum())} landmarks accepted, "
                f"fewer than {opts.min_pose_landmarks}: pose not updated"
            )
        if not info["pose_solved"]:
            # without a pose update each landmark carries its own measurement into the next pass
            centre = np.where(ok_pass[:, None], result.measured, centre)
        result.passes.append(info)
    if _converges(steps, opts):
        cam = _autoregister_converge(reg, cam, result, last, positions, sig_pos, sig_att, factor)
    result.camera = cam


def _autoregister_converge(reg: Registrar, cam, result, last, positions, sig_pos, sig_att, factor):
    """AUTOREGISTER's final full-resolution stage: every ok landmark is converged from its last
    measurement with the final pose (:func:`_converge`), then (``pose_update``) the pose is solved once
    more from the converged pixels.  Recorded as a pass with ``"converge": True``."""
    opts = reg.options
    ok_idx = [i for i in range(len(reg)) if result.status[i] == "ok"]
    steps_run = 0
    not_conv = 0
    for i in ok_idx:
        moved = float(np.hypot(*(factor * last[i].shift))) if last[i] is not None else math.inf
        before = int(result.iterations[i])
        status, c, st = _converge(reg, i, cam, result.measured[i].copy(), moved, result, last, factor)
        steps_run += int(result.iterations[i]) - before
        result.status[i] = status
        if status in ("ok", "not-converged"):
            result.measured[i] = c
            if st is not None:
                result.covariance[i] = st.covariance
            not_conv += status == "not-converged"
        else:
            result.measured[i] = np.nan
        reg.release(i)
    ok_now = np.array([s == "ok" for s in result.status], dtype=bool)
    info = {
        "spacing": 1,
        "converge": True,
        "ok": int(ok_now.sum()),
        "attempted": len(ok_idx),
        "steps": steps_run,
        "not_converged": not_conv,
        "pose_solved": False,
    }
    if opts.pose_update and steps_run and ok_now.sum() >= max(1, int(opts.min_pose_landmarks)):
        meas = np.where(ok_now[:, None], result.measured, np.nan)
        try:
            pr = solve_pose(cam, positions, meas, opts.pose, sig_pos, sig_att, names=result.names)
        except PoseError as exc:
            result.warnings.append(f"converged pass: pose not updated ({exc})")
        else:
            cam = cam.with_pose(scobj=pr.scobj, rotation=pr.rotation)
            result.pose = pr
            info["pose_solved"] = True
            info["rms_after_px"] = float(pr.rms_after)
    result.passes.append(info)
    return cam
