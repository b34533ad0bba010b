"""Stage H's options: every constant of one landmark's registration in maplet or image space
(:class:`RegisterOptions`, spc-algorithms.md §9.3 and §13; S16 "Template matching loop" and "Future
Retina development") and the schedule of correlation steps they give (:func:`schedule_steps`).

The steps themselves are :mod:`spctool.stages.registrar`; the drivers over a schedule
:mod:`spctool.stages.register`, which re-exports these names.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from spctool.errors import SpcUsageError
from spctool.stages.correlate import PEAK_METHODS, CorrelateOptions
from spctool.stages.extract import ExtractOptions
from spctool.stages.image_shadows import PHOTO_SHADOW_MODES
from spctool.stages.pose import PoseOptions
from spctool.stages.predict import PredictOptions

__all__ = ["SCHEDULES", "SPACES", "RegisterOptions", "schedule_steps"]

SCHEDULES = ("retina_s16", "autoregister")
SPACES = ("maplet", "image")


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
      loop stops at the least-squares alignment; :func:`spctool.stages.alignment.gradient_offset`) or
      ``"quadric"`` / ``"parabola"`` (as ``peak``; a vertex read off an asymmetric correlation surface
      keeps a bias of up to 0.05 px that re-centring cannot remove), or ``"gradient-photo"`` (the same
      alignment with the prediction as the fitted side, for predictions noisier than the photo:
      :func:`spctool.stages.alignment.gradient_offset_photo`; the Monte Carlo's maplet plan), or
      ``"gradient-symmetric"`` / ``"gradient-weighted"`` (the difference regressed on both images'
      gradients, mean or noise-weighted: :func:`spctool.stages.alignment.gradient_offset_symmetric`).
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
    * ``capped_phases`` — S16 driver, maplet space: when the maplet's size capped the schedule (one
      step at the cap replaces the coarser ones, :func:`spctool.stages.register.spacing_cap`), the
      first step is taken at max(``first_phases``, this) phases (2).  At the cap the grid's border
      offsets keep about half of the maplet per axis, the case above: on the shipped demo (49×49
      maplets, cap L = 5, a-priori errors of 2–5 px) landmark B02631 of P000000002A1 read its peak
      between two grid points and ended ``edge-peak`` at one phase; 1 runs the capped step as given.
    * ``acquire_reach`` — S16 driver, maplet space (cells): the steps at the schedule's first spacing
      L ≥ 2 (its phases and edge retries) search ±k·L cells, k = max(``grid_half``, ⌈reach / L⌉), on
      the photo resampled onto the maplet's grid extended by (k + 1)·L cells per side (heights continued
      from the maplet's edge), so that the prediction lies wholly on the extraction at every offset.
      0 (the default) is S16/SPC: the extraction is the maplet's own grid, an offset of j cells keeps
      (N − j)/N of the overlap per axis, and the reach ends near N/2 cells (an N = 99 maplet at L = 10:
      ±50 cells, where partial-overlap maxima on the grid's border compete with the landmark).  Set it
      from the a-priori uncertainty (the Monte Carlo: 4σ of the a-priori pixel, in cells).  Image
      space (px): the steps at the first spacing L search ±k·L px (the photo is cropped around the
      template for any grid), so a wide acquisition need not make every later step as wide.
    * ``pose_update`` — AUTOREGISTER driver: pose solve after each align pass (True);
      ``halve_shift`` — apply ½ of every shift (False); ``min_pose_landmarks`` — accepted landmarks
      needed for a pose solve (3).
    * ``criteria`` — Stage E removal applied at the first extraction: ``"default"`` = ``None`` (no
      removal) for retina_s16 and ``"autoregister"`` (0,50,.25,0,5) for autoregister; or any
      :class:`spctool.stages.extract.Criteria` spec, or None.
    * image space: ``supersample`` (rays per pixel axis of the template, 2; ``supersample_coarse``,
      1, for the steps at spacing ≥ 2, whose bins average n² pixels), ``converge_draft`` (True: the
      converged stage's steps render at ``supersample_coarse``, a quarter of the rays, until one
      moves the estimate by less than ``converge_draft_tol`` (0.15 px) or ``converge_draft_max`` of
      them have run (0: no cap but ``converge_max``), then at ``supersample``; it only stops on a full
      template, so the result is that template's zero; the draft steps only bring it near first),
      ``converge_accept`` (px, 0 = off: the stage also ends at its first full-template step when that
      step moves the estimate by less than this — the step's secant move taken, not verified by
      another template, as a step below ``converge_tol`` is; the Monte Carlo's image plan, whose
      drafts leave the first full step a few hundredths of a pixel to go: its error, a fraction of
      that move, averages out of the study's means), ``image_shadows`` (use
      shadowed pixels, True), ``rerender_tol`` (px: a spacing-1 step re-renders the template when its
      sub-pixel phase moved by more than this, 0.0005), ``rerender_tol_coarse`` (px per unit spacing, the
      same for spacing ≥ 2 steps, 1.0: never, as phases differ by < 1 px), ``template_shading``
      (``"smooth"``, the default, | ``"facet"``; chosen on the four independent benchmark worlds of
      issue #39 — both truths, the views' Sun and 70° —, two-pass image-space rms in px, smooth vs
      facet: 0.0184 vs 0.0187, 0.0181 vs 0.0186 (views' Sun), 0.0247 vs 0.0278, 0.0237 vs 0.0268
      (70°); the tests' smaller world (27 landmarks) prefers facet at the views' Sun, 0.029 vs 0.024;
      facet normals differentiate height noise, and with the s16-50m Monte Carlo's 3.33 mm height
      errors on 1 cm cells 10 of 12 landmarks end low-correlation — docs/benchmarks.md "Template
      shading"; ``"gouraud"``: the radiance shaded at the nodes and interpolated, as maplet space
      predicts it, the s16-50m Monte Carlo's image plan: docs/benchmarks.md "The image floor"),
      ``template_slopes`` (the node slopes the smooth shading interpolates: ``"spc"``, the
      default, SPC's HGT2SLP table, | ``"fourth"``, the fourth-order central difference where five
      nodes are valid: :func:`spctool.geometry.heightfield.fourth_order_slopes`; the s16-50m Monte
      Carlo's image plan), ``template_visibility`` (``"raster"``, the default: supersampled
      templates find each sub-ray's terrain cell by rasterising the maplet with the camera's forward
      model, then solve the crossing there — the same template as ``"march"``, the grid march of
      every sub-ray, to the last bit, 10–30 % less time per ss2 template: :class:`RenderOptions`
      ``visibility``; single-ray templates march, where the raster costs as much as it saves),
      ``photo_shadows`` (``"auto"``, the default: a landmark's photo pixels at the photo's dark level,
      read once under its template's own shadows, and those within 3 px of one are left out of its
      full-resolution steps — independent worlds at a low Sun, two-pass 0.045 → 0.024–0.025 px rms;
      ``"use"``: correlated as dark; :mod:`spctool.stages.image_shadows`), ``template_margin`` (px
      added around the projected footprint, 1), ``image_bin_fraction`` (a binned template pixel needs
      this fraction of its n² pixels on the maplet, 0.5: border bins that average only a sliver of
      template are not compared with full photo bins).
    * ``threads`` — workers over the landmarks of an S16 run (:func:`spctool.stages.register.register`:
      image space threads, maplet space processes forked from this one; 1 = one thread): None = numba's
      thread count (maplet space: at most one worker per two landmarks).  The result does not depend
      on it, to the last bit.
    * ``cap_spacing`` — fit the schedule to each maplet (:func:`spctool.stages.register.spacing_cap`, True).
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
    capped_phases: int = 2
    acquire_reach: int = 0
    pose_update: bool = True
    halve_shift: bool = False
    min_pose_landmarks: int = 3
    criteria: object = "default"
    supersample: int = 2
    supersample_coarse: int = 1
    converge_draft: bool = True
    converge_draft_tol: float = 0.15
    converge_draft_max: int = 0
    converge_accept: float = 0.0
    image_shadows: bool = True
    rerender_tol: float = 0.0005
    rerender_tol_coarse: float = 1.0
    template_shading: str = "smooth"
    template_slopes: str = "spc"
    template_visibility: str = "raster"
    threads: int | None = None
    template_margin: int = 1
    image_bin_fraction: float = 0.5
    photo_shadows: str = "auto"
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
        from spctool.stages.render_modes import NODE_SLOPES, SHADINGS, VISIBILITIES  # the renderer's lists

        for name, allowed in (
            ("template_shading", SHADINGS),
            ("template_visibility", VISIBILITIES),
            ("template_slopes", NODE_SLOPES),
        ):
            if getattr(self, name) not in allowed:
                raise SpcUsageError(
                    f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}"
                )
        if self.photo_shadows not in PHOTO_SHADOW_MODES:
            raise SpcUsageError(
                f"photo_shadows must be one of {', '.join(PHOTO_SHADOW_MODES)}, got {self.photo_shadows!r}"
            )
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
        if int(self.capped_phases) != self.capped_phases or not 1 <= int(self.capped_phases) <= 4:
            raise SpcUsageError(f"capped_phases must be an integer from 1 to 4, got {self.capped_phases}")
        self.capped_phases = int(self.capped_phases)
        if int(self.acquire_reach) != self.acquire_reach or int(self.acquire_reach) < 0:
            raise SpcUsageError(
                f"acquire_reach must be an integer >= 0 (cells; px in image space), got {self.acquire_reach}"
            )
        self.acquire_reach = int(self.acquire_reach)
        if not float(self.converge_tol) > 0.0:
            raise SpcUsageError(f"converge_tol must be > 0 px, got {self.converge_tol}")
        if not float(self.converge_draft_tol) > 0.0:
            raise SpcUsageError(f"converge_draft_tol must be > 0 px, got {self.converge_draft_tol}")
        if int(self.converge_draft_max) != self.converge_draft_max or int(self.converge_draft_max) < 0:
            raise SpcUsageError(f"converge_draft_max must be an integer >= 0, got {self.converge_draft_max}")
        self.converge_draft_max = int(self.converge_draft_max)
        if not float(self.converge_accept) >= 0.0:
            raise SpcUsageError(f"converge_accept must be >= 0 px, got {self.converge_accept}")
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
