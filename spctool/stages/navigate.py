"""Two-pass navigation of one picture: acquire, solve the pose, re-register from it, solve again.

Specification: issue #15 "Two-pass navigation"; S16 "Template matching loop" (the L = 10 … 1 coarse-to-
fine reach of ±5L cells) and "Future Retina development"; SPC's AUTOREGISTER (spc-algorithms.md §9.2–
9.3: align passes with a pose solve between them); L15 §2 (the pose solve, :mod:`spctool.stages.pose`).
GIANT's equivalent is a PnP pose fit followed by a second ±5 px pass.

Why two passes.  A landmark registered from an a-priori pose that is wrong by many pixels is measured
with the wrong extraction geometry (the maplet nodes are projected with the a-priori camera and only
translated onto the current pixel: a twist about the boresight or a wrong range is not removed), and a
coarse search that had to reach ±20 px leaves the peak on a coarse grid.  Solving the pose from the
first measurements and registering every landmark again *from the solved pose* with a small search
removes the a-priori viewpoint's share; the second pose solve uses those measurements.

Pass 1 (acquisition), for all landmarks at once (:func:`acquisition_steps`):

1. **coarse search** reaching ``reach_px`` (±25 px by default, S16's L = 10 reach) adapted to the
   maplet: spacing L₀ = the largest spacing ≤ ``max_spacing`` (10) that leaves ≥ ``min_bins`` binned
   cells across the maplet (a 49-cell maplet binned by 10 has 5 cells: S16's L = 10 step finds
   nothing there), and a grid of ±k₀ bins with k₀·L₀ cells ≥ the reach plus one bin (so a peak at the
   reach is not on the grid's border);
2. landmarks the coarse search did not find are re-centred by the **median shift** of those it found
   (the a-priori error of one picture is mostly a common pointing error);
3. the **fine steps**: spacings L₀/2, L₀/4, …, 1 with ±``grid_half`` bins
   (:func:`spctool.stages.register.register`, S16 driver — so its final full-resolution stage applies);
4. **pose solve** (:func:`spctool.stages.pose.solve_pose` from the a-priori pose with the SUM sigmas as
   prior, outlier rejection on); rejected landmarks are named.  A fit that does not converge, or is
   implausible (cost/dof above ``PoseOptions.max_reduced_chi2``, as ``solve-pose`` and ``batch`` judge
   it), is no pose.

Pass 2 (refinement): every landmark — also those pass 1 did not find or the pose solve rejected — is
registered again with the solved camera, starting at the projection of its position, with the
``refine_spacings`` (2, 1: ±10 cells), its converged stage starting from the secant Jacobian pass 1's
left (:attr:`RegisterResult.converge_jacobian`: the estimator's gain, ~1.5 on sharp image-space
templates, is not learned twice; the measurements move by no more than the stage's tolerance allows);
then the pose is solved again from the a-priori pose.  A
landmark is in the result when pass 2 measured it (``ok``); its pass-1 pixel is kept for the report.

Workers (``RegisterOptions.threads``; issue 39): in maplet space every register call of the passes
shares its landmarks with worker processes forked once, at the first (a
:class:`spctool.workers.ForkedPool` over the photo and maplets, which the passes do not modify): a later
pass sends them its camera, start pixels and options, not a new fork, and both processes' pages are
already their own (a fork costs ~3 ms and ~1300 copy-on-write faults per process in its first
landmark).  The result does not depend on the number of workers, to the last bit.

When pass 1 yields no pose (fewer than ``min_landmarks`` found, degenerate geometry), pass 2 is not run
and the result says why (``status`` ``no-pose``); when pass 2 cannot solve a pose although it
re-registered at least ``min_landmarks`` landmarks, the pass-1 pose and measurements stand (with a
warning); when pass 2 re-registered fewer, the pass-1 pose is not confirmed and the result is
``no-pose`` (a right pose puts its landmarks within pass 2's small search; one fitted to landmarks
locked onto other terrain does not — the silent wrong answer this rule removes).  Nothing is silently
dropped.

The coarse step (maplet space, L₀ ≥ 2) correlates on the photo resampled onto the maplet's grid
extended beyond its edge (``RegisterOptions.acquire_reach`` = k₀·L₀ cells), so every offset of its grid
compares the whole prediction: on the maplet's own grid an offset of j cells keeps (N − j)/N of the
overlap, and near ±N/2 partial-overlap maxima compete with the landmark.  ``passes=1`` stops after
pass 1 (the old single-pass path with the pose solve).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from spctool.errors import SpcUsageError
from spctool.stages.model_error import Sensitivity, shading_sensitivity
from spctool.stages.pose import PoseError, PoseOptions, PoseResult, solve_pose
from spctool.stages.register import RegisterOptions, RegisterResult, register

#: NavigateOptions.weights: the final pose solve's weights and covariance (NavigateOptions)
WEIGHTS = ("calibrated", "uniform", "surface")

__all__ = [
    "WEIGHTS",
    "NavigateOptions",
    "NavigateResult",
    "PassResult",
    "acquisition_steps",
    "navigate",
]


@dataclass
class NavigateOptions:
    """Settings of :func:`navigate` (module docstring).

    * ``passes`` — 2 (default) or 1 (acquisition and one pose solve only).
    * ``reach_px`` — the acquisition search must reach at least this far (25 px, S16's L = 10 reach).
    * ``max_spacing`` (10, S16) and ``min_bins`` (12 binned cells across the maplet) bound the coarse
      spacing; ``grid_half`` (5) is the ±bins of every finer step.
    * ``refine_spacings`` — pass 2's steps from the solved pose ((2, 1): search ±10 cells).
    * ``min_landmarks`` — landmarks needed for a pose (3; fewer is ``no-pose``).
    * ``register`` — the :class:`RegisterOptions` every step starts from (space, correlation
      thresholds, prediction/extraction options; schedule and steps are set here, and removal
      criteria apply only when given explicitly — ``criteria="default"`` means none).
    * ``pose`` — the :class:`PoseOptions` of both pose solves (outlier rejection on by default).
    * ``weights`` — the final pose solve (issue #39): ``"calibrated"`` (the default) fits with uniform
      weights (1/``sigma_px``² per axis: the most accurate pose on the independent worlds) and reports
      the covariance that fit has under the calibrated measurement covariance — each landmark's
      registration covariance, the model error τ the residuals show and as large a part common to
      the landmarks (:func:`spctool.stages.pose.solve_pose` ``estimate_weights="uniform"``; nothing is
      registered again); ``"surface"`` weights the fit by the registration covariances plus the
      shading model's error patterns (every landmark re-registered with the other photometric law and
      its maplet's heights smoothed once more, in image space also the other template shading and no
      cast shadows: :mod:`spctool.stages.model_error`) as errors shared by the picture's landmarks —
      honest but conservative (NEES 1.4–2.7), up to 2× less accurate in attitude at a low Sun and
      40–90 % more time; ``"uniform"`` is the old way (uniform weights and the formal covariance of
      ``sigma_px``: NEES 0.1–1.7 on the independent worlds).  Pass 1 of two passes solves with uniform
      weights either way (its pose only centres pass 2's search).
    """

    passes: int = 2
    reach_px: float = 25.0
    max_spacing: int = 10
    min_bins: int = 12
    grid_half: int = 5
    refine_spacings: tuple = (2, 1)
    min_landmarks: int = 3
    register: RegisterOptions = field(default_factory=RegisterOptions)
    pose: PoseOptions = field(default_factory=PoseOptions)
    weights: str = "calibrated"

    def __post_init__(self):
        if self.weights not in WEIGHTS:
            raise SpcUsageError(f"weights must be one of {', '.join(WEIGHTS)}, got {self.weights!r}")
        if int(self.passes) not in (1, 2):
            raise SpcUsageError(f"passes must be 1 or 2, got {self.passes}")
        self.passes = int(self.passes)
        if not (float(self.reach_px) > 0 and math.isfinite(float(self.reach_px))):
            raise SpcUsageError(f"reach must be a positive number of pixels, got {self.reach_px}")
        if int(self.max_spacing) < 1 or int(self.min_bins) < 3 or int(self.grid_half) < 1:
            raise SpcUsageError("max_spacing >= 1, min_bins >= 3 and grid_half >= 1 are needed")
        self.refine_spacings = tuple(int(n) for n in self.refine_spacings)
        if not self.refine_spacings or min(self.refine_spacings) < 1:
            raise SpcUsageError("refine spacings must be integers >= 1")
        if int(self.min_landmarks) < 1:
            raise SpcUsageError(f"min_landmarks must be >= 1, got {self.min_landmarks}")
        self.min_landmarks = int(self.min_landmarks)

    def as_dict(self) -> dict:
        out = {
            f.name: getattr(self, f.name)
            for f in dataclasses.fields(self)
            if f.name not in ("register", "pose")
        }
        out["refine_spacings"] = list(self.refine_spacings)
        out["register"] = self.register.as_dict()
        out["pose"] = dataclasses.asdict(self.pose)
        return out


def acquisition_steps(
    size_cells: int, cells_per_px: float, options: NavigateOptions
) -> list[tuple[int, int]]:
    """The pass-1 steps [(spacing, grid_half), …] for a maplet of ``size_cells`` across (module docstring).

    ``cells_per_px``: maplet cells per photo pixel on the ground.  The first step reaches
    ``reach_px``·cells_per_px cells plus one bin; the spacing halves down to 1 with ``grid_half``.
    """
    reach = float(options.reach_px) * float(cells_per_px)
    l0 = max(1, min(int(options.max_spacing), int(size_cells) // int(options.min_bins)))
    k0 = max(int(options.grid_half), int(math.ceil(reach / l0)) + 1)
    steps = [(l0, k0)]
    spacing = l0
    while spacing > 1:
        spacing = max(1, spacing // 2)
        steps.append((spacing, int(options.grid_half)))
    return steps


@dataclass
class PassResult:
    """One pass: the registration, its pose solve (None when it failed, ``pose_error`` says why)."""

    register: RegisterResult
    pose: PoseResult | None
    pose_error: str | None
    steps: list  #: [(spacing, grid_half), …] run
    seconds: float
    sensitivity: Sensitivity | None = None  #: the shading model's error patterns (``weights="surface"``)

    @property
    def found(self) -> int:
        return int(self.register.ok.sum())

    def as_dict(self) -> dict:
        p = self.pose
        return {
            "steps": [list(s) for s in self.steps],
            "found": self.found,
            "attempted": len(self.register),
            "status_counts": self.register.status_counts(),
            "pose_solved": p is not None,
            "pose_error": self.pose_error,
            "used": None if p is None else p.n_used,
            "rms_before_px": None if p is None else float(p.rms_before),
            "rms_after_px": None if p is None else float(p.rms_after),
            "converged": None if p is None else bool(p.converged),
            "rejected": [] if p is None else [r.as_dict() for r in p.rejected],
            "pose": None if p is None else p.pose_dict(),
            "seconds": self.seconds,
            "model_error": None if self.sensitivity is None else self.sensitivity.as_dict(),
        }


@dataclass
class NavigateResult:
    """Both passes of :func:`navigate`.  ``final`` is the last pass with a pose (else the last pass
    run); ``status``: ``ok`` (a converged pose: pass 2's, or pass 1's when pass 2 could not solve one,
    with a warning), ``no-pose: <reason>``."""

    names: list[str]
    passes: list[PassResult]
    status: str
    camera: object  #: the final camera (solved pose, else the a-priori one)
    warnings: list = field(default_factory=list)
    options: NavigateOptions | None = None

    @property
    def final(self) -> PassResult:
        solved = [p for p in self.passes if p.pose is not None]
        return solved[-1] if solved else self.passes[-1]

    @property
    def pose(self) -> PoseResult | None:
        return self.final.pose

    @property
    def ok(self) -> np.ndarray:
        return self.final.register.ok

    @property
    def measured(self) -> np.ndarray:
        return self.final.register.measured

    def to_table(self, picture=None, command="navigate", meta=None):
        """The final pass's landmark table (register columns) plus the pass-1 pixel and status
        (``sample_1``, ``line_1``, ``status_1``) and the residuals after the final pose solve."""
        from spctool.formats.table import LandmarkTable

        cols = dict(self.final.register.to_table().columns)
        first = self.passes[0].register
        n = len(self.names)
        ok1 = first.ok
        status = cols.pop("status")
        cols["sample_1"] = np.where(ok1, first.measured[:, 0], np.nan)
        cols["line_1"] = np.where(ok1, first.measured[:, 1], np.nan)
        cols["status_1"] = list(first.status)
        res = np.full((n, 2), np.nan)
        pstatus = ["-"] * n
        if self.pose is not None:
            idx = {nm: i for i, nm in enumerate(self.names)}
            for k, nm in enumerate(self.pose.names):
                res[idx[nm]] = self.pose.residuals_after[k]
                pstatus[idx[nm]] = self.pose.status[k]
        cols["residual_sample"] = res[:, 0]
        cols["residual_line"] = res[:, 1]
        cols["pose_status"] = pstatus
        cols["status"] = status
        return LandmarkTable(cols, picture=picture, command=command, meta=dict(meta or {}))


def _cells_per_px(camera, maplets) -> float:
    """Median maplet cells per photo pixel along the ground (foreshortening included)."""
    v = np.array([np.asarray(m.v, float) for m in maplets])
    uz = np.array([np.asarray(m.uz, float) for m in maplets])
    res = camera.resolution(v, normals=uz)
    scale = np.array([float(m.scale) for m in maplets])
    r = res / scale
    r = r[np.isfinite(r) & (r > 0)]
    return float(np.median(r)) if len(r) else 1.0


def _solve(
    camera, positions, reg: RegisterResult, options: NavigateOptions, sig_pos, sig_att, sens=None, final=True
):
    """The pose from the landmarks ``reg`` measured (:class:`NavigateOptions` ``weights``): the final
    pass ``calibrated`` fits uniformly with their registration covariances as the measurement
    covariance; ``sens`` given (``surface``) weights by them and the shading model's error patterns;
    otherwise (and pass 1 of two) uniform weights."""
    use = np.flatnonzero(reg.ok)
    calibrated = final and options.weights == "calibrated" and reg.covariance is not None
    covs = reg.covariance[use] if (calibrated or sens is not None) else None
    try:
        pose = solve_pose(
            camera,
            positions[use],
            reg.measured[use],
            options.pose,
            prior_sigma_position=sig_pos,
            prior_sigma_attitude=sig_att,
            names=[reg.names[i] for i in use],
            pixel_covariances=covs,
            error_modes=None if sens is None else sens.modes[use],
            estimate_weights="uniform" if calibrated else "covariance",
        )
    except PoseError as exc:
        return None, str(exc)
    if not pose.converged:
        return pose, f"pose did not converge in {options.pose.max_iter} iterations"
    if not pose.plausible:  # as batch and solve-pose: residuals far above the measurement sigma
        return pose, f"implausible fit: {pose.implausible}"
    return pose, None


def _sensitivity(photo, camera, sun, maplets, thresholds, base, opts, reg, kw, warnings) -> Sensitivity:
    """The shading model's error patterns of the landmarks ``reg`` measured with ``camera``
    (:func:`spctool.stages.model_error.shading_sensitivity`, spacing 1 with ±``grid_half``)."""
    sens = shading_sensitivity(
        photo,
        camera,
        sun,
        maplets,
        thresholds,
        dataclasses.replace(base, grid_half=opts.grid_half),
        reg.measured,
        reg.ok,
        names=kw["names"],
        positions=kw["positions"],
        converge_jacobian=reg.converge_jacobian,
        patch_cache=kw["patch_cache"],
    )
    warnings.extend(sens.warnings)
    return sens


def navigate(
    photo,
    camera,
    sun,
    maplets,
    thresholds=None,
    options: NavigateOptions | None = None,
    *,
    apriori=None,
    names=None,
    positions=None,
    prior_sigma_position=None,
    prior_sigma_attitude=None,
    progress=None,
) -> NavigateResult:
    """Two-pass navigation of one picture (module docstring).

    Arguments as :func:`spctool.stages.register.register`: ``apriori`` (N, 2) starting pixels (NaN rows
    or None: the projection of each position with ``camera``); ``positions`` (N, 3) landmark positions
    (LMK VLM; default each maplet's V) for the pose solves; ``prior_sigma_*`` the SUM's SIGMA_VSO (km)
    and SIGMA_PTG (rad).  ``progress(k)`` is called as landmark steps are done.
    """
    opts = options if options is not None else NavigateOptions()
    n = len(maplets)
    names = [getattr(m, "name", "") or f"#{i + 1}" for i, m in enumerate(maplets)] if names is None else names
    names = [str(x) for x in names]
    pos = (
        np.array([np.asarray(m.v, float) for m in maplets]).reshape(n, 3)
        if positions is None
        else np.asarray(positions, dtype=np.float64).reshape(n, 3)
    )
    tick = progress or (lambda k=1: None)
    # the photo as every pass's Registrar reads it (float64), converted once here, not once per pass
    photo = np.ascontiguousarray(getattr(photo, "data", photo), dtype=np.float64)
    side = max(photo.shape) if photo.ndim == 2 else 0
    if side and float(opts.reach_px) > side:  # a search wider than the photo: nothing there, and memory
        raise SpcUsageError(
            f"a reach of {opts.reach_px:g} px (--reach) is larger than the photo "
            f"({photo.shape[1]} x {photo.shape[0]} px): at most {side}"
        )
    # maplet space: the landmarks of every pass are shared with worker processes forked once, at the
    # first pass, over the photo and maplets as they are here (register's ``pool``)
    pool = _landmark_pool(photo, maplets, opts.register)
    try:
        return _navigate(
            photo, camera, sun, maplets, thresholds, opts, apriori, names, pos, prior_sigma_position,
            prior_sigma_attitude, tick, pool,
        )  # fmt: skip
    finally:
        if pool is not None:
            pool.close()


def _landmark_pool(photo, maplets, ropts):
    """A :class:`spctool.workers.ForkedPool` over ``(photo, maplets)`` for navigate's register calls,
    or None (image space: threads; one worker; forking not safe here)."""
    from spctool.stages.register import landmark_workers
    from spctool.workers import ForkedPool, can_fork_tasks

    if ropts.space != "maplet":
        return None
    cells = sum(int(np.size(m.heights)) for m in maplets)
    workers = landmark_workers(ropts, len(maplets), cells)
    if workers < 2 or not can_fork_tasks():
        return None
    return ForkedPool(workers, shared=(photo, maplets))


def _navigate(
    photo, camera, sun, maplets, thresholds, opts, apriori, names, pos, prior_sigma_position,
    prior_sigma_attitude, tick, pool,
) -> NavigateResult:  # fmt: skip
    """:func:`navigate`'s passes (``pool``: register's, or None)."""
    n = len(maplets)
    # the steps below are fitted to each maplet here (pass1_steps: at least min_bins bins across, the
    # coarse grid widened to reach_px), so register's generic K*L <= Q+1 cap must not shrink them again
    base = dataclasses.replace(
        opts.register, schedule="retina_s16", steps=None, fail_fast=True, cap_spacing=False
    )
    if isinstance(opts.register.criteria, str) and opts.register.criteria == "default":
        # the schedule here is S16's: no removal criteria unless asked for (an AUTOREGISTER schedule's
        # derived default 0,50,.25,0,5 does not carry over)
        base = dataclasses.replace(base, extract=dataclasses.replace(base.extract, criteria=None))
    kw = dict(names=names, positions=pos, prior_sigma_position=prior_sigma_position)
    kw["prior_sigma_attitude"] = prior_sigma_attitude
    kw["patch_cache"] = {}  # image space: each maplet's render-ready patch built once for all passes
    kw["pool"] = pool
    warnings: list[str] = []

    # start pixels: table pixels, else the projection of the landmark position
    s_, l_, front = camera.project_with_mask(pos) if n else (np.zeros(0), np.zeros(0), np.zeros(0, bool))
    start = np.where(front[:, None], np.stack([s_, l_], axis=-1), np.nan) if n else np.zeros((0, 2))
    if apriori is not None:
        ap = np.asarray(apriori, dtype=np.float64).reshape(n, 2)
        given = np.all(np.isfinite(ap), axis=1)
        start[given] = ap[given]

    # ---- pass 1: coarse acquisition, consensus re-centring, fine steps, pose -------------------------
    t0 = time.perf_counter()
    size = min((int(np.asarray(m.heights).shape[0]) for m in maplets), default=1)
    per_px = _cells_per_px(camera, maplets) if n else 1.0
    if base.space == "image":  # offsets and spacings in photo pixels: the template is size/per_px across
        size, per_px = max(1, int(size / per_px)), 1.0
    steps = acquisition_steps(size, per_px, opts)
    l0, k0 = steps[0]
    coarse_opts = dataclasses.replace(base, steps=(("align", l0),), grid_half=k0)
    if base.space == "maplet" and l0 >= 2:  # the whole prediction compared at every offset of the grid
        coarse_opts = dataclasses.replace(coarse_opts, acquire_reach=k0 * l0)
    coarse = register(photo, camera, sun, maplets, thresholds, coarse_opts, apriori=start, **kw)
    tick(n)
    found = coarse.ok
    centre = np.where(found[:, None], coarse.measured, start)
    if found.any() and (~found).any():
        common = np.median(coarse.measured[found] - coarse.apriori[found], axis=0)
        centre[~found] = start[~found] + common
    if len(steps) > 1:
        fine_opts = dataclasses.replace(
            base, steps=tuple(("align", s) for s, _ in steps[1:]), grid_half=steps[1][1]
        )
        fine = register(photo, camera, sun, maplets, thresholds, fine_opts, apriori=centre, **kw)
        tick(n)
        fine.apriori = start.copy()
        fine.iterations = fine.iterations + coarse.iterations
        reg1 = fine
    else:
        reg1 = coarse
    patterns = opts.weights == "surface"  # the shading model's error patterns (the final pass)
    sens1 = None
    if patterns and opts.passes == 1:
        sens1 = _sensitivity(photo, camera, sun, maplets, thresholds, base, opts, reg1, kw, warnings)
    one = opts.passes == 1
    pose1, err1 = _solve(camera, pos, reg1, opts, prior_sigma_position, prior_sigma_attitude, sens1, one)
    pass1 = PassResult(reg1, pose1 if err1 is None else None, err1, steps, time.perf_counter() - t0, sens1)
    passes = [pass1]
    if err1 is not None:
        warnings.append(f"pass 1: no pose ({err1})")
        return NavigateResult(names, passes, "no-pose: " + err1, camera, warnings, opts)
    cam1 = camera.with_pose(scobj=pose1.scobj, rotation=pose1.rotation)
    if opts.passes == 1:
        return NavigateResult(names, passes, "ok", cam1, warnings, opts)

    # ---- pass 2: every landmark again from the solved pose, small search, pose again -----------------
    t0 = time.perf_counter()
    s2, l2, front2 = cam1.project_with_mask(pos)
    start2 = np.where(front2[:, None], np.stack([s2, l2], axis=-1), np.nan)
    ref_steps = [(s, int(opts.grid_half)) for s in opts.refine_spacings]
    ref_opts = dataclasses.replace(
        base, steps=tuple(("align", s) for s, _ in ref_steps), grid_half=opts.grid_half
    )
    # the converged stage starts from the gain pass 1 measured for each landmark (its template and the
    # photo's sharpness are the same): no step spent learning it again
    kw["converge_jacobian"] = reg1.converge_jacobian
    reg2 = register(photo, cam1, sun, maplets, thresholds, ref_opts, apriori=start2, **kw)
    tick(n)
    reg2.apriori = start.copy()  # the table's a-priori pixel stays the input one
    sens2 = None
    if patterns:
        sens2 = _sensitivity(photo, cam1, sun, maplets, thresholds, base, opts, reg2, kw, warnings)
    pose2, err2 = _solve(camera, pos, reg2, opts, prior_sigma_position, prior_sigma_attitude, sens2)
    passes.append(
        PassResult(reg2, pose2 if err2 is None else None, err2, ref_steps, time.perf_counter() - t0, sens2)
    )
    if err2 is not None:
        again = int(reg2.ok.sum())
        if again < opts.min_landmarks:
            # a right pass-1 pose puts every landmark it measured within pass 2's small search: when
            # almost none is found there, pass 1 measured something else (a 45 px a-priori error beyond
            # the reach locks landmarks onto their neighbours' terrain, and they fit a pose of their own)
            why = (
                f"the pass-1 pose is not confirmed: pass 2 re-registered {again} of the "
                f"{pass1.found} landmarks pass 1 found, from that pose ({err2})"
            )
            warnings.append(why)
            return NavigateResult(names, passes, "no-pose: " + why, camera, warnings, opts)
        # never lose a picture pass 1 navigated and pass 2 confirmed (its pose solve failed)
        warnings.append(f"pass 2: no pose ({err2}); the pass-1 pose and measurements stand")
        return NavigateResult(names, passes, "ok", cam1, warnings, opts)
    cam2 = camera.with_pose(scobj=pose2.scobj, rotation=pose2.rotation)
    lost = [names[i] for i in np.flatnonzero(reg1.ok & ~reg2.ok)]
    if lost:
        warnings.append(
            f"pass 2 did not re-register {len(lost)} landmark(s) found in pass 1: {', '.join(lost)}"
        )
    return NavigateResult(names, passes, "ok", cam2, warnings, opts)
