"""Stage H — ``register``: measure where each landmark really is in a photo.

Specification: spc-algorithms.md §9 (Stage H: both drivers), §7.3/§8.3 (the shift and its sign), §12
(S16 checklist), §13 (defaults); L15 §3.5.2 (Eq. 3.67); S16 "Template matching loop" (Eq. 9, 11,
18–19) and "Future Retina development".

The options of a registration and one correlation step of one landmark, in either space, are
:mod:`spctool.stages.registrar` (:class:`RegisterOptions`, :class:`Registrar`,
:func:`correlate_landmark`); this module drives the steps over a schedule.

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

The S16 driver's landmarks are independent and run on ``threads`` workers (:func:`landmark_workers`:
default numba's thread count, i.e. every core unless ``NUMBA_NUM_THREADS`` says otherwise, and one in
``batch``'s and the Monte Carlo's workers), one landmark per task, merged in landmark order: the result
is the one-thread driver's to the last bit.  Image space runs threads (its render and correlation
kernels release the GIL); maplet space forks worker processes (:func:`spctool.workers.forked_map`, or
the children of a caller's :class:`spctool.workers.ForkedPool`, forked once for several calls:
navigate's passes), since its steps are short kernels between Python and small NumPy operations that
hold the GIL (issue 39: in one thread ~70 % of its time is in kernels that release it — the re-centred
extraction and the correlation's front end are one kernel each —, so two threads could gain at most
1/(0.3 + 0.7/2) ≈ 1.5×; docs/benchmarks.md).

Both drivers end with a **converged full-resolution stage**
(:mod:`spctool.stages.register_converge`) when their last align step is at spacing 1: that step is
repeated (re-extracting or re-placing at the current estimate) until the estimate moves by less than
``converge_tol`` (0.005 px), at most ``converge_max`` extra steps (10; 0 = the schedule
exactly).  The coarse steps leave 0.3–1 px on tilted peaks and a single L = 1 step only removes part
of that.  The stage reads each step with ``converge_peak`` — by default the least-squares alignment
of prediction and photo at the grid peak (:func:`spctool.stages.alignment.gradient_offset`), which
is exactly zero where they agree, whereas a vertex of the correlation surface (quadric or parabola)
stays up to 0.05 px off on an asymmetric peak however often the step is repeated (independent world,
image space: 0.038 → 0.019 px rms) — and moves by secant (Broyden) steps, so an estimator that over-
or under-reads the shift converges in a few steps to the same zero.  A small cycle (the estimate
going round places < 20·``converge_tol`` apart, e.g. an image-space template re-rendered at each
sub-pixel placement) converges to the mean of those places.  A landmark that does not settle within
the cap gets the status ``not-converged`` (its last estimate is kept in
:attr:`RegisterResult.measured`, but it is not ``ok``).  AUTOREGISTER converges every landmark from
its last measurement with the final pose, then solves the pose once more from the converged pixels
(``pose_update``).

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

from spctool.stages.image_shadows import dark_floor_note
from spctool.stages.pose import PoseError, solve_pose
from spctool.stages.predict import cast_shadow_note
from spctool.stages.register_converge import _converge, _converges, _drafts, _record
from spctool.stages.register_options import SCHEDULES, SPACES, RegisterOptions, schedule_steps
from spctool.stages.registrar import LandmarkStep, Registrar, correlate_landmark

__all__ = [
    "SCHEDULES",
    "SPACES",
    "LandmarkStep",
    "RegisterOptions",
    "RegisterResult",
    "Registrar",
    "correlate_landmark",
    "landmark_workers",
    "register",
    "schedule_steps",
    "spacing_cap",
]


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
        k = reg.options.grid_half
        where = (
            f"a {n}x{n}-cell maplet holds a search of +-{k}L cells only up to L = {c}"
            if reg.options.space == "maplet"
            else "the template is too small in the photo for coarser bins"
        )
        text = f"{len(idx)} landmark(s): spacings above L = {c} skipped, one step at {c} instead ({where})"
        result.adapted.append(("spacing-cap", text))


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
    #: (kind, text) of what the run adapted to the data by design and needs no action: "spacing-cap"
    #: (the schedule's coarser steps fitted to the maplet) and "cast-shadows" (``shadows="auto"``
    #: predicted cast shadows the photo's THRSH T1 does not mark); the command line says them with -v
    adapted: list = field(default_factory=list)
    options: RegisterOptions | None = None
    #: (N, 2, 2) measurement covariance of ``measured`` in px² (sample, line); NaN unless ok
    covariance: np.ndarray | None = None
    #: (N, 2, 2) the converged stage's secant Jacobian of each landmark as its steps left it (its start:
    #: register's ``converge_jacobian``; NaN where the stage ran no step and had no start)
    converge_jacobian: np.ndarray | None = None

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
    patch_cache: dict | None = None,
    converge_jacobian=None,
    pool=None,
) -> RegisterResult:
    """Stage H: measure the landmarks of ``maplets`` in ``photo`` (module docstring).

    ``apriori`` (N, 2): starting pixels (e.g. the lithos-select table); rows with NaN — or no array —
    start at the projection of V with ``camera``.  ``positions`` (N, 3): body-fixed landmark positions
    for the pose solve (default: each maplet's V).  ``prior_sigma_*``: SUM SIGMA_VSO (km) and SIGMA_PTG
    (rad) for the pose solve.  ``progress(n)`` is called as landmarks are processed.  ``patch_cache``:
    a dict shared by several calls on the same maplets, not modified in between (navigate's passes),
    in which image space keeps each maplet's render-ready patch (:attr:`Registrar.patch_cache`), and every
    call the settings it makes from its ``options`` (an options object changed in place between two
    such calls would keep the first call's settings: pass a new one, e.g. ``dataclasses.replace``).
    ``converge_jacobian`` (N, 2, 2): where the converged stage's secant Jacobians start (a previous
    pass's :attr:`RegisterResult.converge_jacobian` on the same maplets; NaN rows or None: −I).  The
    stage's zero does not depend on it; the number of steps does, and so where within ``converge_tol``
    of the zero the stage stops (:func:`_converge`; navigate's pass 2 measured ≤ 0.0005 px apart on the
    independent worlds, ≤ 0.0025 px on the 16-landmark benchmark picture).  ``pool``: a
    :class:`spctool.workers.ForkedPool` whose ``shared`` is ``(photo, maplets)`` — these very objects —
    kept by the caller over several calls (navigate's passes): maplet space's workers are its children,
    forked once (another pool, or None: a fork per call).
    """
    reg, steps, start, result, caps, opts = _setup(
        photo, camera, sun, maplets, thresholds, options, apriori, names, patch_cache, converge_jacobian
    )
    n = len(reg)
    last = [None] * n
    tick = progress or (lambda k=1: None)
    if opts.schedule == "retina_s16":
        workers = landmark_workers(opts, n, sum(int(np.size(lm.maplet.heights)) for lm in reg.landmarks))
        if workers > 1:
            from spctool.workers import shares

            job = None  # what a child of the pool needs to make this call's task
            if not shares(pool, photo, maplets):
                pool = None
            else:
                job = (camera, sun, thresholds, options, apriori, names, converge_jacobian)
            _parallel_s16(reg, camera, steps, start, result, last, tick, workers, caps, pool, job)
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
    if opts.space == "maplet" and int(result.iterations.sum()) > 0:  # a step has run here (either driver)
        global _MAPLET_KERNELS_LOADED
        _MAPLET_KERNELS_LOADED = True
    result.last_steps = last
    bad = ~result.ok
    result.covariance[bad] = np.nan
    cast = reg.cast_shadow_landmarks()
    if cast:
        result.adapted.append(("cast-shadows", cast_shadow_note(cast, reg.thresholds[0])))
    floors = reg.dark_floor_landmarks()
    if floors:
        result.adapted.append(("photo-shadows", dark_floor_note(floors)))
    odd = disagreeing_shifts(result)
    if odd:
        result.warnings.append(odd)
    return result


def _setup(photo, camera, sun, maplets, thresholds, options, apriori, names, patch_cache, converge_jacobian):
    """What :func:`register` sets up before its driver runs (the Registrar, the schedule, the start
    pixels, the result to fill, each maplet's spacing cap and the options as adapted to the caps): a
    deterministic function of its arguments, made again in a :class:`spctool.workers.ForkedPool`'s
    child from the same arguments (:func:`_pool_task`)."""
    opts = options if options is not None else RegisterOptions()
    reg = Registrar(photo, sun, maplets, thresholds, opts, names, patch_cache=patch_cache)
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
        converge_jacobian=(
            np.full((n, 2, 2), np.nan)
            if converge_jacobian is None
            else np.array(converge_jacobian, dtype=np.float64).reshape(n, 2, 2)
        ),
    )
    top = max(int(v) for k, v in steps if k == "align")
    # a cap is at least 1: a schedule at spacing 1 only (a refinement phase) has nothing to cap
    capped = opts.cap_spacing and top > 1
    caps = np.array(
        [spacing_cap(lm.maplet, opts, camera) if capped else top for lm in reg.landmarks], dtype=np.int64
    )
    if capped:
        _cap_warnings(reg, caps, top, result)
        if (
            opts.schedule == "retina_s16"
            and opts.space == "maplet"
            and opts.capped_phases > opts.first_phases
            and np.any(caps < top)
        ):  # the capped step's border offsets overlap half the maplet: a denser first step (capped_phases)
            opts = dataclasses.replace(opts, first_phases=opts.capped_phases)
            reg.options = result.options = opts
    return reg, steps, start, result, caps, opts


#: a registered landmark whose shift from its a-priori pixel differs from the picture's median shift by
#: more than this many pixels, or this fraction of the median shift, moved unlike the others
DISAGREE_PX, DISAGREE_FRACTION = 3.0, 0.25


def disagreeing_shifts(result: RegisterResult) -> str | None:
    """A warning naming the registered landmarks that moved unlike the others, or None.

    A picture's a-priori error is mostly common to its landmarks (a pointing error; range and twist
    add a few pixels across a large photo), so right measurements share one shift to within a few
    pixels (the independent worlds of issue #15: within 0.1 px at 6–38 px).  A landmark searched
    beyond the reach of its schedule locks onto other terrain and reports ``ok`` with a shift of its own
    (S16's search on 49×49 maplets at 45 px: 27–98 px off, 3–51 px from the median shift).  Needs three
    registered landmarks; the status is not changed (solve-pose's outlier rejection and ``navigate``'s
    pose checks decide)."""
    if len(result.names) < 3:  # fewer than three landmarks: nothing to compare (no array work)
        return None
    ok = np.asarray(result.ok, dtype=bool) & np.all(np.isfinite(result.apriori), axis=1)
    if int(ok.sum()) < 3:
        return None
    shift = result.measured[ok] - result.apriori[ok]
    med = np.median(shift, axis=0)
    limit = max(DISAGREE_PX, DISAGREE_FRACTION * float(np.hypot(*med)))
    odd = np.hypot(*(shift - med).T) > limit
    if not odd.any():
        return None
    names = [str(n) for n, o in zip(np.asarray(result.names, dtype=object)[ok], odd) if o]
    return (
        f"{len(names)} of {int(ok.sum())} registered landmarks moved unlike the others (more than "
        f"{limit:.1f} px from the median shift ({med[0]:+.1f}, {med[1]:+.1f}) px): {', '.join(names)}; "
        "a search beyond its reach locks onto other terrain: check them with solve-pose (outlier "
        "rejection) or use navigate"
    )


#: maplet space, ``threads=None``: a worker process per this many landmarks at least (a forked worker
#: costs about ten milliseconds in all, a landmark's S16 schedule ten to fifteen)
MAPLET_LANDMARKS_PER_WORKER = 2
#: by default maplet space forks only for at least this many maplet cells in all (Σ (2q+1)²): a cold
#: ``register`` of a demo picture (12 maplets of 49², 29k cells) took 1.04× the wall of one thread with
#: a forked worker (20 A/B pairs of whole processes; 1.11× in another 10): the copy-on-write faults and the
#: child's start outweigh ~0.1 s of work; S16's 16 maplets of 99² (157k cells) take 1/1.63 of it
MAPLET_MIN_CELLS_TO_FORK = 100_000


def landmark_workers(opts: RegisterOptions, n: int, cells: int | None = None) -> int:
    """Workers over the ``n`` landmarks of an S16 run (:func:`_parallel_s16`): ``threads``, or with
    None numba's thread count (``NUMBA_NUM_THREADS``; all cores unless set; 1 in ``batch``'s and the
    Monte Carlo's workers, which are one core each), at most one per landmark; with None, maplet space
    also keeps :data:`MAPLET_LANDMARKS_PER_WORKER` landmarks per worker and stays in one process below
    :data:`MAPLET_MIN_CELLS_TO_FORK` maplet cells in all (``cells``, when given).  1: the one-thread
    driver."""
    if n < 2:
        return 1
    if opts.threads is None:
        from spctool.threads import numba_threads

        k = numba_threads()
        if opts.space == "maplet":
            k = min(k, n // MAPLET_LANDMARKS_PER_WORKER)
            if cells is not None and cells < MAPLET_MIN_CELLS_TO_FORK:
                k = 1
    else:
        k = int(opts.threads)
    return max(1, min(n, k))


@dataclass
class _Done:
    """What registering one landmark alone (:func:`_landmark_task`) adds to the result (small and
    picklable: it may come from a forked worker)."""

    measured: np.ndarray
    correlation: float
    iterations: int
    spacing: int
    status: str
    covariance: np.ndarray
    converge_jacobian: np.ndarray
    warnings: list
    adapted: list
    last: object  #: the landmark's last LandmarkStep (or None)
    shadow_mode: object  #: the landmark's resolved ``shadows="auto"`` (read by cast_shadow_landmarks)


def _landmark_task(reg: Registrar, camera, steps, start, result, caps):
    """``task(i)``: landmark ``i`` registered alone by :func:`_drive_s16` on a Registrar of that one
    landmark (sharing the photo and the settings) — exactly the one-thread driver's computation of it,
    which touches no other landmark's state — as a :class:`_Done`."""

    def task(i: int) -> _Done:
        sub = copy.copy(reg)  # shares the photo and caches; its own landmark list
        lm = reg.landmarks[i]
        sub.landmarks = [lm]
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
            converge_jacobian=result.converge_jacobian[i : i + 1].copy(),
        )
        sub_last = [None]
        _drive_s16(sub, camera, steps, start[i : i + 1], part, sub_last, lambda k=1: None, caps[i : i + 1])
        return _Done(
            part.measured[0], float(part.correlation[0]), int(part.iterations[0]), int(part.spacing[0]),
            part.status[0], part.covariance[0], part.converge_jacobian[0], part.warnings, part.adapted,
            sub_last[0], lm.shadow_mode,
        )  # fmt: skip

    return task


#: a maplet-space step has run in this process: its kernels are loaded (:func:`_parallel_s16` forks)
_MAPLET_KERNELS_LOADED = False


def _pool_task(shared, first: int, camera, sun, thresholds, options, apriori, names, converge_jacobian):
    """In a :class:`spctool.workers.ForkedPool`'s child: the task of :func:`_parallel_s16` (landmark
    ``first + k``) for a :func:`register` call with these arguments on the pool's ``shared`` photo and
    maplets, made by :func:`_setup` as the caller made it."""
    photo, maplets = shared
    reg, steps, start, result, caps, _ = _setup(
        photo, camera, sun, maplets, thresholds, options, apriori, names, None, converge_jacobian
    )
    task = _landmark_task(reg, camera, steps, start, result, caps)
    return lambda k: task(first + k)


def _parallel_s16(
    reg: Registrar, camera, steps, start, result, last, tick, workers: int, caps, pool=None, job=None
):
    """:func:`_drive_s16` with the landmarks spread over ``workers``, one landmark per task.

    Landmarks are independent (their own prediction, extraction or template, and state; the photo is
    only read) and every landmark runs exactly the computation of the one-thread driver
    (:func:`_landmark_task`); the results are merged in landmark order, so the result does not depend
    on ``workers`` (``tests/test_register.py``).

    Image space: threads (the render and correlation kernels release the GIL and hold most of the
    time).  Maplet space: processes forked from this one — a ``pool``'s children (forked by its first
    call; later calls send them ``job``, :func:`register`'s arguments but the photo and maplets, from
    which :func:`_pool_task` makes the same task there), or forked for this call
    (:func:`spctool.workers.forked_map`), since its steps are short kernels between small NumPy
    operations that hold the GIL (~70 % of a landmark's time is in kernels that release it: threads
    could gain at most ~1.5× on two cores).
    The first such call of a process registers landmarks alone until one has run a step, so that
    every kernel is loaded once, here, before the workers are forked with them.  Where forking is
    not safe (:func:`spctool.workers.can_fork_tasks`: another Python thread runs), maplet space uses
    threads.
    """
    import threading

    from spctool.workers import can_fork_tasks, forked_map

    task = _landmark_task(reg, camera, steps, start, result, caps)
    n = len(reg)
    done: list = [None] * n
    lock = threading.Lock()

    def ticked(i, rec):
        with lock:
            tick()

    if reg.options.space == "maplet" and ((pool is not None and pool.alive) or can_fork_tasks()):
        global _MAPLET_KERNELS_LOADED
        first = 0
        while first < n and not _MAPLET_KERNELS_LOADED:  # loaded here, once, before forking the workers
            done[first] = task(first)
            tick()
            first += 1
            _MAPLET_KERNELS_LOADED = done[first - 1].iterations > 0
        if pool is not None:
            job = (_pool_task, (first, *job))
            rest = pool.map(lambda k: task(first + k), n - first, on_result=ticked, job=job)
        else:
            rest = forked_map(lambda k: task(first + k), n - first, workers, on_result=ticked)
        done[first:] = rest
    else:
        from concurrent.futures import ThreadPoolExecutor

        def one(i):
            rec = task(i)
            ticked(i, rec)
            return rec

        with ThreadPoolExecutor(workers) as threads:
            done = list(threads.map(one, range(n)))
    for i, rec in enumerate(done):
        result.measured[i] = rec.measured
        result.correlation[i] = rec.correlation
        result.iterations[i] = rec.iterations
        result.spacing[i] = rec.spacing
        result.status[i] = rec.status
        result.covariance[i] = rec.covariance
        result.converge_jacobian[i] = rec.converge_jacobian
        result.warnings.extend(rec.warnings)
        result.adapted.extend(rec.adapted)
        last[i] = rec.last
        reg.landmarks[i].shadow_mode = rec.shadow_mode


def _phase_key(st: LandmarkStep):
    """Order of the phases of a first step: an ``ok`` peak, then an edge peak, then the highest ρ.

    An interior peak before a higher edge peak: in the s16-50m Monte Carlo (12 × 500) this loses no
    sample that started within 31.9 px (the reach is 35 px), where ranking by ρ alone lost six
    (5.7–23.6 px off) to small-overlap edge peaks while rescuing five beyond the reach."""
    peak = st.correlation.peak
    return (st.status == "ok", st.status == "edge-peak", peak if np.isfinite(peak) else -np.inf)


def _phased_first_step(reg: Registrar, i, camera, c, n: int, st0: LandmarkStep, result, last, search=()):
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
            st = reg.step(i, camera, c + move, n, apply_criteria=True, **dict(search))
            _record(result, last, i, st, opts.keep_images)
            if _phase_key(st) > _phase_key(best):
                best = st
    if best is not st0:  # the kept step is the landmark's last one
        _record(result, last, i, best, opts.keep_images)
        result.iterations[i] -= 1
    return best


def _acquisition(opts, spacing: int) -> dict:
    """``acquire_reach``'s search at the schedule's first spacing n, as keyword arguments of
    :meth:`Registrar.step`: ``{}`` when off, else the grid ``grid_half`` k = max(grid_half,
    ⌈reach / n⌉) and, in maplet space (n ≥ 2), the extraction's ``margin`` (k + 1)·n cells, so that
    every offset of the grid compares the whole prediction (image space crops the photo around the
    template by (k + 1)·n px itself)."""
    if opts.acquire_reach <= 0 or (opts.space == "maplet" and spacing < 2):
        return {}
    k = max(int(opts.grid_half), -(-int(opts.acquire_reach) // spacing))
    if opts.space == "image":
        return {"grid_half": k}
    return {"grid_half": k, "margin": (k + 1) * spacing}


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
        # acquire_reach: the steps at the schedule's first spacing search a full-overlap extraction
        first_n = int(plan[aligns[0]][1]) if aligns else 0
        wide = _acquisition(opts, first_n)
        for at, (kind, value) in enumerate(plan):
            final = at == final_at
            if kind == "drop":
                if state == "ok" and not result.correlation[i] >= value:
                    state = "low-correlation"
                    break
                continue
            draft = final and _drafts(opts)  # the converged stage's first step: a draft template
            search = wide if int(value) == first_n and not final else {}
            st = reg.step(i, camera, c, int(value), apply_criteria=first, final=final, draft=draft, **search)
            _record(result, last, i, st, opts.keep_images)
            if first and opts.first_phases > 1 and int(value) >= 2 and not final:
                st = _phased_first_step(reg, i, camera, c, int(value), st, result, last, search)
            first = False
            retries = 0
            while st.status == "edge-peak" and retries < opts.edge_retries and np.all(np.isfinite(st.shift)):
                # the maximum on the border of the grid: the peak lies beyond the search; go there
                c = st.center + st.shift
                st = reg.step(i, camera, c, int(value), final=final, draft=draft, **search)
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
