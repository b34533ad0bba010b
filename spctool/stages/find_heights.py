"""Stage ``find_heights`` — SPC's LITHOS "Find heights" outer loop for one maplet: re-register, re-extract,
solve slopes and albedo, integrate, until the heights stop changing.

Specification: ``map-refinement.md`` §2 ("Outer loop", "Pitfalls") and §3; S16 Introduction ¶4 and
Fig. 3; L15 §3 first paragraph.  Pure function, no I/O: :func:`find_heights` takes one maplet, the
pictures that see it (:class:`PictureView`: photo, camera, Sun, thresholds, a-priori pixel) and a
:class:`FindHeightsOptions`, and returns a :class:`FindHeightsResult`; ``batch`` can map it over
maplets.

**First pass** (``first_pixels``).  Where the pictures sit before any heights are solved decides what
the loop converges to.  ``"apriori"``: at their a-priori pixels (the LMK PICTURES rows, else the
projection of V with the SUM pose) — right for navigated pictures (SPC runs LITHOS after navigation and
GEOMETRY), whereas a coarse starting maplet registers several pixels off (simulated world of
``benchmarks/validate_lithos.py``: 2–6 px, correlations 0.4–0.8).  ``"register"``: registered on the
starting maplet (``acquire`` from the projection, ``register`` from a given pixel) — right when the
poses are not navigated but the start is close to the truth.  ``"auto"`` (default) makes both first
passes, solves one heights pass on each, and keeps the one whose pictures agree best with each other
(lower rms misfit: pictures extracted at wrong pixels disagree whatever heights are solved).  The
first pass's pixels are the **reference** of the later ones.

One outer iteration, on the current heights H and albedo a:

1. **Re-register** each picture on the current maplet (:func:`spctool.stages.register.register`, the
   ``register_steps`` schedule, by default one full-resolution step and its converged stage) from its
   last pixel; a picture that fails keeps its last pixel.  ``reregister=False`` keeps the given pixels.
   With ``anchor`` (default) the one move of V (cells along UX, UY, UZ) that best explains the
   pictures' offsets from their reference pixels is removed from every picture's pixel (least squares
   through each picture's ∂pixel/∂V): a move common to the pictures is a move of the landmark —
   GEOMETRY's business; lithos keeps V — while the pictures' offsets from each other are the
   co-registration the albedo needs.  Without it the heights and the registrations drift together
   (the maplet's translation is otherwise held only by the weak conditioning heights: 0.03–0.07 px a
   pass, unbounded).  The move is reported per iteration (``v_move_cells``, ``v_move_px``).
2. **Re-extract** the photo onto the grid at that pixel, on the current heights (the first extraction
   sits on wrong heights: parallax; :func:`spctool.stages.extract.extract` with its filters and the
   LITHOS removal criteria).  Pictures the criteria remove take no part.  The brightness model has
   no cast shadows, so cells in the cast shadow of the current heights — or of an earlier pass's: a
   cell let in and out as the heights move makes the loop cycle — and cells darker than
   ``dark_fraction`` of the picture's median are left out of that picture's equations.
3. **λ fit, per-cell solve** (:mod:`spctool.stages.photoclinometry`), starting from the HGT2SLP
   slopes of H (:func:`spctool.geometry.heightfield.slopes`) and a; albedo normalised to mean 1.
4. **Integration** (:mod:`spctool.stages.slope_integration`) with conditioning cells (a seeded random
   ``condition_fraction`` of the valid cells) pulled toward the *starting* heights with weight
   ``condition_weight`` (0.025); cells that cannot be solved (fewer than three Sun azimuths) are fixed
   at their starting heights and flagged.  ``keep_plane`` (default) restores the starting map's
   best-fit plane, which pins the tilt the λ ratios leave free (map-refinement.md §2, "Pitfalls").
5. The rms height change over the valid cells; the loop stops when it is below ``tolerance`` (cells)
   or after ``iterations``.

**Known limit** (measured on the simulated world of ``benchmarks/validate_lithos.py``, 2026-11-28).
The anchor stops the common drift, not the pictures' drift relative to each other: run far past
convergence (tolerance 0.002, up to 20 iterations) the re-registrations keep moving the pictures apart by
0.03–0.08 px a pass and the heights wander (SM0003: 3.1× closer to the truth at the default tolerance
of 0.005 cells, reached in 3 iterations; 2.4× after 15).  Registering each picture on a maplet solved
without it (leave one out) drifts as much, so this is a bias of the registration on a maplet whose
model cannot hold the photo's sub-cell detail, not the maplet following its own picture; the default
tolerance stops the loop before it matters (3–6 iterations on both validation worlds), and
``reregister=False`` (``--no-register``) for navigated pictures does not drift at all.

A last registration and extraction on the final heights gives the "after" figures: per picture the
residual rms (reflectance units) and the NCC (Pearson ρ) between the re-rendered maplet and the
extraction, beside the same figures on the starting maplet ("before").

A maplet **cannot be solved** (``status = "unsolvable"``, ``reason`` one line, heights unchanged) when
fewer than ``min_azimuths`` usable pictures with distinct Sun azimuths remain, or when fewer than
``min_solved_fraction`` of its valid cells are solvable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np

from spctool.errors import SpcUsageError
from spctool.geometry import heightfield
from spctool.geometry.frames import unit_vector
from spctool.photometry import phase_angle_deg
from spctool.stages import photoclinometry as pc
from spctool.stages import slope_integration as si
from spctool.stages.extract import ExtractOptions, extract
from spctool.stages.predict import pearson
from spctool.stages.register import register
from spctool.stages.register_options import RegisterOptions

__all__ = [
    "FindHeightsOptions",
    "FindHeightsResult",
    "PictureOutcome",
    "PictureView",
    "WorkingMaplet",
    "find_heights",
    "landmark_with",
    "maplet_with",
]


@dataclass
class PictureView:
    """One picture of a maplet: ``name``, ``photo`` (Photo or array ``data[line − 1, sample − 1]``),
    ``camera`` (:class:`~spctool.geometry.camera.Camera`), ``sun`` (body → Sun), ``thresholds``
    (T1, T2) or None, ``pixel`` (sample, line) a-priori (e.g. the LMK PICTURES row) or None (the
    projection of V)."""

    name: str
    photo: object
    camera: object
    sun: object
    thresholds: tuple | None = None
    pixel: tuple | None = None


@dataclass
class WorkingMaplet:
    """The maplet attributes the stages read (heights in cells, albedo, valid, scale, v, axes)."""

    heights: np.ndarray
    albedo: np.ndarray
    valid: np.ndarray
    scale: float
    v: np.ndarray
    ux: np.ndarray
    uy: np.ndarray
    uz: np.ndarray
    name: str = ""

    @property
    def qsz(self) -> int:
        return (self.heights.shape[0] - 1) // 2

    @classmethod
    def of(cls, maplet, heights=None, albedo=None) -> WorkingMaplet:
        return cls(
            np.array(maplet.heights if heights is None else heights, dtype=np.float64),
            np.array(maplet.albedo if albedo is None else albedo, dtype=np.float64),
            np.array(maplet.valid, dtype=bool),
            float(maplet.scale),
            np.array(maplet.v, dtype=np.float64),
            np.array(maplet.ux, dtype=np.float64),
            np.array(maplet.uy, dtype=np.float64),
            np.array(maplet.uz, dtype=np.float64),
            str(getattr(maplet, "name", "") or ""),
        )


def _default_register() -> RegisterOptions:
    # one full-resolution step and its converged stage, to 0.02 px (the maplet changes between passes,
    # so register's 0.005 px would be spent on a target that moves)
    return RegisterOptions(steps=(("align", 1),), converge_tol=0.02, converge_max=4)


def _default_acquire() -> RegisterOptions:
    # coarser spacings (4, 2, 1) lock a coarse starting maplet onto wrong peaks several pixels away
    # (simulated world of benchmarks/validate_lithos.py: height rms 0.25 instead of 0.11 cells)
    return _default_register()


#: where the pictures sit in the first pass (module docstring, "First pass")
FIRST_PIXELS = ("auto", "apriori", "register")


def _default_extract() -> ExtractOptions:
    return ExtractOptions(criteria="lithos_standard")


@dataclass
class FindHeightsOptions:
    """Every constant of the outer loop (module docstring).

    ``iterations`` (10: Palmer et al. find the first ~10 matter) and ``tolerance`` (rms height change,
    cells); ``condition_weight`` (0.025, SPC's "always use .025") and ``condition_fraction`` (0.02 of
    the valid cells, map-refinement.md §2 "Pitfalls"), ``seed`` of their draw; ``keep_plane``;
    ``refit_lambda`` (λ refitted every pass; False: fitted on the starting map only);
    ``first_pixels`` (``"auto"``, ``"apriori"``, ``"register"``) and ``anchor`` (module docstring);
    ``reregister`` and ``register`` (the registration options; default one spacing-1 step with the
    converged stage, maplet space), ``acquire`` (those of a picture without an a-priori pixel, from
    the projection of V: by default the same); ``extract`` (extraction options; default LITHOS
    removal criteria);
    ``solve`` (:class:`~spctool.stages.photoclinometry.SolveOptions`); ``min_solved_fraction``;
    ``recentre`` (move V along UZ by the mean height and subtract it: off unless asked);
    ``cast_shadows`` (leave out of the solve the cells the current heights shadow in a picture) and
    ``dark_fraction`` (and the cells darker than this fraction of the picture's median on the maplet:
    shadows a THRSH T1 of 1 DN lets through with the read noise).
    """

    iterations: int = 10
    tolerance: float = 0.005
    condition_weight: float = 0.025
    condition_fraction: float = 0.02
    seed: int = 0
    keep_plane: bool = True
    refit_lambda: bool = True
    reregister: bool = True
    min_solved_fraction: float = 0.25
    recentre: bool = False
    cast_shadows: bool = True
    dark_fraction: float = 0.1
    first_pixels: str = "auto"
    anchor: bool = True
    register: RegisterOptions = field(default_factory=_default_register)
    acquire: RegisterOptions = field(default_factory=_default_acquire)
    extract: ExtractOptions = field(default_factory=_default_extract)
    solve: pc.SolveOptions = field(default_factory=pc.SolveOptions)

    def __post_init__(self):
        if int(self.iterations) < 1:
            raise SpcUsageError(f"iterations must be >= 1, got {self.iterations}")
        self.iterations = int(self.iterations)
        for name in ("tolerance", "condition_weight", "condition_fraction", "min_solved_fraction",
                     "dark_fraction"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value >= 0.0):
                raise SpcUsageError(f"{name} must be a finite number >= 0, got {value}")
            setattr(self, name, value)
        if not self.condition_weight > 0.0:
            raise SpcUsageError("condition_weight must be > 0")
        if self.first_pixels not in FIRST_PIXELS:
            choices = ", ".join(FIRST_PIXELS)
            raise SpcUsageError(f"first_pixels must be one of {choices}, got {self.first_pixels!r}")
        if self.condition_fraction > 1.0 or self.min_solved_fraction > 1.0:
            raise SpcUsageError("condition_fraction and min_solved_fraction must lie in [0, 1]")

    def as_dict(self) -> dict:
        nested = ("register", "acquire", "extract", "solve")
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in nested}
        out["register"] = self.register.as_dict()
        out["acquire"] = self.acquire.as_dict()
        out["extract"] = self.extract.as_dict()
        out["solve"] = self.solve.as_dict()
        return out


@dataclass
class PictureOutcome:
    """One picture's part (:class:`FindHeightsResult`): ``used`` in the last pass; ``status`` (``ok``,
    the extraction's ``removed-…``/``outside``, or ``register-<status>`` when the last registration
    failed and the previous pixel was kept); ``pixel`` (sample, line) of V last used; ``lam``;
    ``ncc_before``/``ncc_after`` and ``rms_before``/``rms_after`` (reflectance units)."""

    name: str
    used: bool
    status: str
    pixel: tuple
    lam: float = math.nan
    ncc_before: float = math.nan
    ncc_after: float = math.nan
    rms_before: float = math.nan
    rms_after: float = math.nan
    registration_correlation: float = math.nan


@dataclass
class FindHeightsResult:
    """Result of :func:`find_heights`.  Arrays (N, N), heights in cells.

    ``status``: ``"ok"`` or ``"unsolvable"`` (``reason`` says why; heights and albedo are then the
    starting ones).  ``heights``, ``albedo``: the refined maplet (prior on flagged cells); ``v``: the
    (possibly re-centred) centre; ``flagged``: valid cells kept at their prior; ``solved``;
    ``azimuths``: distinct Sun-azimuth groups per cell; ``history``: per iteration dict(iteration,
    change_rms, residual_rms, solved, pictures); ``converged``; ``pictures``: one
    :class:`PictureOutcome` per view; ``before``/``after``: the last extractions (K, N, N) and the
    re-rendered maplet on them, for figures (``images`` dict).
    """

    name: str
    status: str
    reason: str
    heights: np.ndarray
    albedo: np.ndarray
    valid: np.ndarray
    v: np.ndarray
    flagged: np.ndarray
    solved: np.ndarray
    azimuths: np.ndarray
    history: list
    converged: bool
    pictures: list
    start_heights: np.ndarray
    start_albedo: np.ndarray
    images: dict = field(default_factory=dict)
    options: FindHeightsOptions | None = None
    start_v: np.ndarray | None = None  #: the maplet's V at the start (``v`` moves from it only by recentre)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def iterations(self) -> int:
        return len(self.history)

    @property
    def change_rms(self) -> float:
        return float(self.history[-1]["change_rms"]) if self.history else math.nan

    def mean_ncc(self) -> tuple[float, float]:
        """Mean NCC of the re-rendered maplet with the extractions, (before, after), over the pictures
        used in both (NaN when none)."""
        both = [p for p in self.pictures if math.isfinite(p.ncc_before) and math.isfinite(p.ncc_after)]
        if not both:
            return math.nan, math.nan
        return (float(np.mean([p.ncc_before for p in both])), float(np.mean([p.ncc_after for p in both])))

    @property
    def worse(self) -> bool:
        """True when the refined maplet matches the photos worse than the starting one (mean NCC fell
        by more than 0.005): a result not to be written unasked (map-refinement.md §2, "Known limits
        and metrics")."""
        before, after = self.mean_ncc()
        return bool(self.ok and math.isfinite(before) and math.isfinite(after) and after < before - 0.005)

    @property
    def used_pictures(self) -> list[str]:
        return [p.name for p in self.pictures if p.used]

    def summary(self) -> dict:
        """A JSON-ready summary (no arrays)."""
        v = self.valid
        return {
            "name": self.name,
            "status": self.status,
            "reason": self.reason,
            "iterations": self.iterations,
            "converged": bool(self.converged),
            "change_rms_cells": self.change_rms,
            "solved_cells": int(np.count_nonzero(self.solved)),
            "flagged_cells": int(np.count_nonzero(self.flagged)),
            "valid_cells": int(np.count_nonzero(v)),
            "height_change_rms_cells": float(np.sqrt(np.mean((self.heights - self.start_heights)[v] ** 2)))
            if np.any(v) else math.nan,
            "ncc_before": self.mean_ncc()[0],
            "ncc_after": self.mean_ncc()[1],
            "worse": self.worse,
            "history": list(self.history),
            "pictures": [dict(p.__dict__) for p in self.pictures],
        }


# --------------------------------------------------------------------------------------------------
# one pass over the pictures


@dataclass
class _Observed:
    pictures: pc.Pictures | None
    used: np.ndarray  # (K,) bool
    status: list
    extractions: list
    move: np.ndarray = field(default_factory=lambda: np.zeros(3))
    shadowed: np.ndarray | None = None  # (K, N, N) cells cast-shadowed in any pass so far


def _observe(wm: WorkingMaplet, views, pixels, reg_corr, opts: FindHeightsOptions,
             do_register: bool, reference=None, jac=None, trusted=None, shadowed=None) -> _Observed:
    """Register (optionally) and extract every view on ``wm``; ``pixels`` (K, 2) updated in place.
    With ``reference`` and ``jac`` (:func:`_v_jacobians`) the registered pixels' common move from
    ``reference`` is removed before the extraction (:func:`_remove_common_move`), fitted on the
    ``trusted`` pictures (default all).  ``shadowed`` (K, N, N): the cells cast-shadowed in a
    picture in the earlier passes, which stay out of its equations (a cell let in and out as the
    heights move makes the loop cycle instead of converging: simulated world, SM0002)."""
    k = len(views)
    n = wm.heights.shape[0]
    obs = np.zeros((k, n, n))
    val = np.zeros((k, n, n), dtype=bool)
    suns = np.zeros((k, 3))
    ems = np.zeros((k, 3))
    alpha = np.zeros(k)
    used = np.zeros(k, dtype=bool)
    status = []
    exts = []
    slopes = heightfield.slopes(wm.heights, wm.valid)
    st_reg = ["ok"] * k
    move = np.zeros(3)
    memory = np.zeros((k, n, n), dtype=bool) if shadowed is None else shadowed.copy()
    for i, view in enumerate(views) if do_register else ():
        known = bool(np.all(np.isfinite(pixels[i])))
        # no pixel yet: from the projection of V with the SUM pose (``acquire``)
        ropts = opts.register if known else opts.acquire
        res = register(view.photo, view.camera, view.sun, [wm], view.thresholds, ropts,
                       apriori=pixels[i:i + 1] if known else None, names=[wm.name or "maplet"])
        if res.status[0] == "ok":
            pixels[i] = res.measured[0]
            reg_corr[i] = float(res.correlation[0])
        else:
            st_reg[i] = f"register-{res.status[0]}"
    if do_register and reference is not None and jac is not None:
        mask = np.ones(k, dtype=bool) if trusted is None else trusted
        pixels[:], move = _remove_common_move(pixels, reference, jac, mask)
    for i, view in enumerate(views):
        center = pixels[i] if np.all(np.isfinite(pixels[i])) else None
        ext = extract(view.photo, wm, view.camera, view.sun, view.thresholds, opts.extract,
                      center_pixel=center, slopes=slopes)
        if center is None:
            pixels[i] = (ext.center_sample, ext.center_line)
        exts.append(ext)
        s_hat = unit_vector(view.sun, "sun")
        e_hat = np.asarray(ext.emission_vector, dtype=np.float64)
        suns[i] = heightfield.to_maplet_components(s_hat, wm.ux, wm.uy, wm.uz)
        ems[i] = heightfield.to_maplet_components(e_hat, wm.ux, wm.uy, wm.uz)
        alpha[i] = float(phase_angle_deg(s_hat, e_hat))
        # a failed re-registration keeps the previous pixel; the picture is still used
        status.append(ext.status if ext.status != "ok" else st_reg[i])
        ok = ext.status == "ok"
        used[i] = ok and bool(np.any(ext.valid))
        obs[i] = ext.image
        val[i] = ext.valid & wm.valid
        if opts.cast_shadows:  # cells the heights shadow carry no slope (the model has no shadows)
            memory[i] |= heightfield.cast_shadows(wm.heights, wm.valid, wm.ux, wm.uy, wm.uz, s_hat)
            val[i] &= ~memory[i]
        if opts.dark_fraction > 0.0 and np.any(val[i]):  # shadows above THRSH T1 (noise, a dark offset)
            val[i] &= obs[i] > opts.dark_fraction * float(np.median(obs[i][val[i]]))
    if not np.any(used):
        return _Observed(None, used, status, exts, move, memory)
    pics = pc.Pictures(obs[used], val[used], suns[used], ems[used], alpha[used])
    return _Observed(pics, used, status, exts, move, memory)


def _figures_of(t1, t2, albedo, pics: pc.Pictures, lam, valid, sopts):
    """(per-picture NCC, per-picture residual rms, predicted images (K', N, N))."""
    pred, lit = pc.brightness(t1, t2, albedo, pics, lam, sopts)
    rms = pc.residual_rms(t1, t2, albedo, pics, lam, valid, sopts)
    ncc = np.array([
        pearson(pred[k], pics.observed[k], pics.valid[k] & lit[k] & valid) for k in range(len(pics))
    ])
    return ncc, rms, np.where(lit & valid[None], pred, 0.0)


def _v_jacobians(wm: WorkingMaplet, views) -> np.ndarray:
    """(K, 2, 3): pixels per cell that V's image moves in each picture when V moves by one cell along
    UX, UY and UZ (central differences of the camera projection; NaN where it cannot be projected)."""
    out = np.full((len(views), 2, 3), np.nan)
    step = wm.scale
    pts = np.stack([wm.v + sgn * step * u for u in (wm.ux, wm.uy, wm.uz) for sgn in (1.0, -1.0)])
    for i, view in enumerate(views):
        s, ln, front = view.camera.project_with_mask(pts)
        if np.all(front):
            out[i, 0] = 0.5 * (s[0::2] - s[1::2])
            out[i, 1] = 0.5 * (ln[0::2] - ln[1::2])
    return out


def _remove_common_move(pixels, reference, jac, mask) -> tuple[np.ndarray, np.ndarray]:
    """``pixels`` (K, 2) less the pixel motion J_k·δ of the one move δ (cells along UX, UY, UZ) of the
    landmark that best explains (least squares) the pictures' offsets from ``reference`` over ``mask``:
    what is common to the pictures is a move of V (GEOMETRY's), not a co-registration.  The move is
    fitted on the pictures of ``mask`` (those whose reference pixel is trusted) and removed from all."""
    movable = np.all(np.isfinite(pixels), axis=1) & np.all(np.isfinite(jac), axis=(1, 2))
    ok = mask & movable & np.all(np.isfinite(reference), axis=1)
    if np.count_nonzero(ok) < 2:
        return pixels, np.zeros(3)
    a = jac[ok].reshape(-1, 3)
    b = (pixels[ok] - reference[ok]).reshape(-1)
    delta, *_ = np.linalg.lstsq(a, b, rcond=1e-6)
    out = pixels.copy()
    out[movable] -= jac[movable] @ delta  # the landmark's move shows in every picture
    return out, delta


def _first_pass(wm: WorkingMaplet, views, pixels, opts: FindHeightsOptions, cond, cache):
    """The first pass's observations (module docstring, "First pass"): (observed, pixels, registration
    correlations, trusted (K,) pictures whose first pixel anchors the common move, the choice made,
    the heights pass already solved on them or None)."""
    k = len(views)
    if not opts.reregister:
        modes = ["apriori"]
    else:
        modes = ["apriori", "register"] if opts.first_pixels == "auto" else [opts.first_pixels]
    trials = []
    for mode in modes:
        px = pixels.copy()
        rc = np.full(k, np.nan)
        ob = _observe(wm, views, px, rc, opts, mode == "register")
        trusted = np.array([not st.startswith("register-") for st in ob.status]) if mode == "register" \
            else np.ones(k, dtype=bool)
        trials.append([ob, px, rc, trusted, mode, None])
    if len(trials) == 1:
        return tuple(trials[0])
    scores = []
    for trial in trials:
        trial[5], misfit = _first_solve(trial[0], wm, cond, opts, cache)
        scores.append(misfit)
    best = int(np.nanargmin(scores)) if np.any(np.isfinite(scores)) else 0
    return tuple(trials[best])


def _first_solve(ob: _Observed, wm: WorkingMaplet, cond, opts: FindHeightsOptions, cache):
    """(heights pass, rms misfit in reflectance units over the pictures) of one heights pass on these
    observations: pictures extracted at wrong pixels disagree with each other, whatever heights are
    solved."""
    if ob.pictures is None:
        return None, math.nan
    step = pc.heights_pass(wm.heights, wm.albedo, wm.valid, ob.pictures, wm.heights, cond,
                           opts.condition_weight, opts.keep_plane, None, opts.solve, cache)
    res = pc.residual_rms(step.cells.t1, step.cells.t2, step.albedo, ob.pictures, step.lam, wm.valid,
                          opts.solve)
    return step, (float(np.sqrt(np.nanmean(res * res))) if np.any(np.isfinite(res)) else math.nan)


def _move_px(jac, history, move, used) -> float:
    """rms over the used pictures of the pixel motion of the landmark's summed common move (cells)"""
    if jac is None:
        return 0.0
    total = np.sum([h["v_move_cells"] for h in history] + [move], axis=0)
    px = np.einsum("kij,j->ki", jac[used], total)
    return float(np.sqrt(np.nanmean(np.sum(px * px, axis=1)))) if px.size else 0.0


def _scatter(values, used, fill=math.nan):
    out = np.full(used.shape[0], fill, dtype=np.float64)
    out[used] = values
    return out


# --------------------------------------------------------------------------------------------------
# the stage


def find_heights(maplet, views, options: FindHeightsOptions | None = None) -> FindHeightsResult:
    """LITHOS "Find heights" on one maplet from the pictures ``views`` (module docstring).

    ``maplet``: a :class:`~spctool.formats.maplet.Maplet` (or any object with heights in cells,
    albedo, valid, scale, v, ux, uy, uz, name); ``views``: a sequence of :class:`PictureView`.
    Returns a :class:`FindHeightsResult`; the maplet itself is not modified.
    """
    opts = options if options is not None else FindHeightsOptions()
    sopts = opts.solve
    start = WorkingMaplet.of(maplet)
    valid = start.valid
    h0 = np.where(valid, start.heights, 0.0)
    a0 = np.where(valid, start.albedo, 1.0)
    views = list(views)
    k = len(views)
    pixels = np.array([v.pixel if v.pixel is not None else (np.nan, np.nan) for v in views],
                      dtype=np.float64).reshape(k, 2)
    reg_corr = np.full(k, np.nan)
    name = start.name

    def result(status, reason, heights, albedo, flagged, solved, azimuths, history, converged, outcomes,
               images=None, v=None):
        return FindHeightsResult(name, status, reason, heights, albedo, valid.copy(),
                                 start.v.copy() if v is None else v, flagged, solved, azimuths, history,
                                 converged, outcomes, h0.copy(), start.albedo.copy(), images or {}, opts,
                                 np.array(start.v, dtype=np.float64))

    def outcomes_of(ob: _Observed):
        out = []
        for i, view in enumerate(views):
            out.append(PictureOutcome(view.name, bool(ob.used[i]), ob.status[i],
                                      (float(pixels[i, 0]), float(pixels[i, 1])),
                                      registration_correlation=float(reg_corr[i])))
        return out

    zeros = np.zeros(valid.shape, dtype=bool)
    if k == 0 or not np.any(valid):
        why = "no pictures" if k == 0 else "no valid cells"
        return result("unsolvable", f"{why}: nothing to solve", h0.copy(), start.albedo.copy(), valid.copy(),
                      zeros, np.zeros(valid.shape, np.int64), [], False, [])

    wm = WorkingMaplet.of(start, h0, a0)
    cond = si.conditioning_cells(valid, opts.condition_fraction, opts.seed)
    cache: dict = {}  # the integration's factorization, kept across the passes
    ob, pixels, reg_corr, trusted, first, first_step = _first_pass(wm, views, pixels, opts, cond, cache)
    reference = pixels.copy()
    jac = _v_jacobians(wm, views) if opts.anchor else None
    outcomes = outcomes_of(ob)
    groups_needed = sopts.min_azimuths
    if ob.pictures is not None:
        n_groups = int(np.unique(pc.azimuth_groups(ob.pictures.sun, sopts.azimuth_separation_deg)).size)
    else:
        n_groups = 0
    if n_groups < groups_needed:
        return result(
            "unsolvable",
            f"{int(ob.used.sum())} usable picture(s) of {k} with {n_groups} distinct Sun azimuth(s) "
            f"(at least {groups_needed}, {sopts.azimuth_separation_deg:g} deg apart, are needed)",
            h0.copy(), start.albedo.copy(), valid.copy(), zeros, np.zeros(valid.shape, np.int64), [], False,
            outcomes,
        )

    t1, t2, _ = heightfield.slopes(h0, valid)
    lam = pc.fit_lambda(t1, t2, a0, ob.pictures, valid, sopts)
    ncc0, rms0, pred0 = _figures_of(t1, t2, a0, ob.pictures, lam, valid, sopts)
    before = {"observed": ob.pictures.observed.copy(), "predicted": pred0, "used": ob.used.copy()}
    ncc_before, rms_before = _scatter(ncc0, ob.used), _scatter(rms0, ob.used)

    n_az = pc.solvable_cells(ob.pictures.valid & valid[None], ob.pictures.sun, sopts)
    solvable = valid & (n_az >= groups_needed)
    frac = float(np.count_nonzero(solvable)) / float(np.count_nonzero(valid))
    if frac < opts.min_solved_fraction:
        return result(
            "unsolvable",
            f"only {100.0 * frac:.1f}% of the valid cells are seen by {groups_needed} pictures with distinct "
            f"Sun azimuths (at least {100.0 * opts.min_solved_fraction:g}% are needed)",
            h0.copy(), start.albedo.copy(), valid.copy(), zeros, n_az, [], False, outcomes,
        )

    heights, albedo = h0.copy(), a0.copy()
    history = []
    converged = False
    sol = None
    lam_by_view = np.full(k, np.nan)
    for it in range(opts.iterations):
        if it > 0:
            wm = WorkingMaplet.of(start, heights, albedo)
            ob = _observe(wm, views, pixels, reg_corr, opts, opts.reregister, reference, jac, trusted,
                          ob.shadowed)
            if ob.pictures is None:
                break
        lam = None
        if not opts.refit_lambda and it > 0 and np.all(np.isfinite(lam_by_view[ob.used])):
            lam = lam_by_view[ob.used]  # the first pass's scales
        if it == 0 and first_step is not None:
            step = first_step  # the same pass, already solved to choose the first pixels
        else:
            step = pc.heights_pass(heights, albedo, valid, ob.pictures, h0, cond, opts.condition_weight,
                                   opts.keep_plane, lam, sopts, cache)
        if it == 0:
            lam_by_view[ob.used] = step.lam
        sol, lam, new_heights, new_albedo = step.cells, step.lam, step.heights, step.albedo
        change = step.change_rms
        res = pc.residual_rms(sol.t1, sol.t2, new_albedo, ob.pictures, lam, valid, sopts)
        history.append({
            "iteration": it + 1,
            "change_rms": change,
            "residual_rms": float(np.sqrt(np.nanmean(res * res))) if np.any(np.isfinite(res)) else math.nan,
            "solved": int(np.count_nonzero(sol.solved)),
            "pictures": int(ob.used.sum()),
            "v_move_cells": [float(x) for x in ob.move],
            "v_move_px": _move_px(jac, history, ob.move, ob.used),
            "first_pixels": first,
        })
        heights, albedo = new_heights, new_albedo
        if change < opts.tolerance:
            converged = True
            break

    # the "after" figures: register and extract once more on the final map
    wm = WorkingMaplet.of(start, heights, albedo)
    ob_after = _observe(wm, views, pixels, reg_corr, opts, opts.reregister, reference, jac, trusted,
                        ob.shadowed)
    outcomes = outcomes_of(ob_after)
    images = {"before": before}
    if ob_after.pictures is not None:
        t1, t2, _ = heightfield.slopes(heights, valid)
        lam_a = pc.fit_lambda(t1, t2, albedo, ob_after.pictures, valid, sopts)
        ncc1, rms1, pred1 = _figures_of(t1, t2, albedo, ob_after.pictures, lam_a, valid, sopts)
        images["after"] = {"observed": ob_after.pictures.observed.copy(), "predicted": pred1,
                           "used": ob_after.used.copy()}
        lam_all, ncc_after, rms_after = (_scatter(x, ob_after.used) for x in (lam_a, ncc1, rms1))
    else:
        lam_all = ncc_after = rms_after = np.full(k, np.nan)
    for i, o in enumerate(outcomes):
        o.lam, o.ncc_before, o.ncc_after = float(lam_all[i]), float(ncc_before[i]), float(ncc_after[i])
        o.rms_before, o.rms_after = float(rms_before[i]), float(rms_after[i])

    v = start.v.copy()
    if opts.recentre:
        mean_h = float(np.mean(heights[valid]))
        v = v + mean_h * start.scale * start.uz
        heights = np.where(valid, heights - mean_h, 0.0)
    images["start_heights"] = h0
    return result("ok", "", heights, albedo, sol.flagged.copy(), sol.solved.copy(), sol.azimuths.copy(),
                  history, converged, outcomes, images, v)


def maplet_with(maplet, result: FindHeightsResult):
    """A copy of ``maplet`` (a :class:`~spctool.formats.maplet.Maplet`) holding the result's heights,
    albedo and centre (the MAP writer re-quantises: HSCALE from the largest height, albedo bytes)."""
    from copy import copy

    m = copy(maplet)
    m.heights = np.asarray(result.heights, dtype=np.float64).copy()
    m.albedo = np.asarray(result.albedo, dtype=np.float64).copy()
    m.valid = np.asarray(result.valid, dtype=bool).copy()
    if not np.array_equal(np.asarray(m.v, dtype=np.float64), result.v):
        m.v = np.asarray(result.v, dtype=np.float64).copy()
    return m


def landmark_with(lmk, result: FindHeightsResult):
    """A copy of the landmark ``lmk`` (:class:`~spctool.formats.landmark.Landmark`) with its PICTURES
    updated from ``result``: a picture used gets its last registered centre and no flag, a picture
    the extraction removed keeps its row flagged ``*`` (SPC: picture excluded), a picture not in
    PICTURES is added; the VLM follows the result's centre (moved only by ``recentre``)."""
    from copy import copy

    from spctool.formats.landmark import LandmarkPicture

    out = copy(lmk)
    by_name = {p.name: p for p in result.pictures}
    rows = []
    for row in lmk.pictures:
        p = by_name.get(row.name)
        if p is None:
            rows.append(row)
        elif p.used:
            rows.append(LandmarkPicture(row.name, p.pixel[0], p.pixel[1], ""))
        else:
            rows.append(LandmarkPicture(row.name, row.sample, row.line, "*"))
    listed = {row.name for row in lmk.pictures}
    rows += [LandmarkPicture(p.name, p.pixel[0], p.pixel[1], "" if p.used else "*")
             for p in result.pictures if p.name not in listed]
    out.pictures = rows
    if result.start_v is not None:  # the VLM moves as V moved (recentre), keeping its own precision: the
        shift = np.asarray(result.v, float) - np.asarray(result.start_v, float)  # MAP's V is real*4
        if np.any(shift != 0.0):
            out.vlm = np.asarray(lmk.vlm, dtype=np.float64) + shift
    elif not np.array_equal(np.asarray(result.v, float), np.asarray(lmk.vlm, float)):
        out.vlm = np.asarray(result.v, dtype=np.float64)
    return out
