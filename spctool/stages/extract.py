"""Stages C, D and E — ``extract``: the photo resampled onto a maplet, filtered, and judged.

Implements L15 §3.3.2 ("Image extraction": §3.3.2.1 projection onto the maplet topography,
Eq. 3.46–3.51; §3.3.2.2 the extract filter, Eq. 3.52) and §3.4 ("Removing Maplets",
Eq. 3.53–3.56), and S16 "Landmark Extraction from Image" (Eq. 10–11), as corrected and specified in
``spc-algorithms.md`` §4 (Stage C), §5 (Stage D), §6 (Stage E), §11 (errata 19–23, 32) and §13.
Pure functions, no I/O; everything is vectorised over the maplet's nodes (numba kernels for the
sampler and the shadow enhancement, :mod:`spctool.geometry.heightfield` for the marches).

Stage C — resampling (:func:`extract`)
--------------------------------------
* Node (r, c) of the maplet, x = r − q along UX, y = c − q along UY, h = height (cells), sits at
  P = V + SCALE·(x·UX + y·UY + h·UZ).  Its pixel is found by
  - the **full camera model** (default, L15 Eq. 3.46: every node through distortion and K), or
  - ``linearized=True``: S16 Eq. 11, [s, l]_k = [s, l]_c + H·(P_k − V) with H = ∂(sample, line)/∂P
    at V — the camera's exact derivative where S16 uses finite differences (erratum 32: both are
    legitimate).
* **Re-centring** (``center_pixel``, used by ``register``): the landmark centre V is moved to the
  given pixel and every node moves with it — full model: [s, l]_k = proj(P_k) + (center_pixel −
  proj(V)); linearized: [s, l]_c = center_pixel in Eq. 11.  H, J_xy and the sub-sample offsets stay
  those of the a-priori geometry (S16 evaluates H at the a priori x*).
* J_xy = ∂(sample, line)/∂(x, y) at V in pixels per cell (the camera's exact derivative; L15
  Eq. 3.15 uses central differences of one cell), det J_xy its determinant (pixels per cell, an
  area ratio).
* **Sampling** with SPC's BRT0 (:func:`brt0`).  ``subsample="auto"``: when √|det J_xy| > 1 (more
  than one pixel per cell) each cell is the average of the non-zero samples of an m×m grid,
  m = ⌈√|det J_xy|⌉, at cell offsets ((k + ½)/m − ½), k = 0…m−1, along x and y; a cell with no
  non-zero sample is 0 (invalid).  An int forces m.  The sub-sample pixels are offset from the node's
  pixel to first order, on the node's tangent plane: Δ[s, l] = J₃·(a, b, h_x·a + h_y·b) with
  J₃ = ∂(sample, line)/∂(x, y, h) at V (px per cell) — exact to far below a pixel within one cell.
  How many samples SPC averages is not public [UNVERIFIED].
* Masks: ``covered`` = valid node, in front of the camera, with its pixel (with sub-sampling: any
  of its sub-sample pixels) inside the BRT0 domain 1 ≤ sample < NPX, 1 ≤ line < NLN; ``lit`` =
  covered and a non-zero value (a sample above T1, at most T2, no missing corner).  The extracted
  value is the photo DN (no normalisation: λ absorbs the scale).

Stage D — the extract filter (:func:`extract_filter`, every constant an option)
--------------------------------------------------------------------------------
Vectors in maplet-frame components ŝ_m = (ŝ·UX, ŝ·UY, ŝ·UZ), ê_m likewise; a step (dx, dy) moves dx
along axis 0 and dy along axis 1.  Rounding of offsets is Fortran NINT (half away from zero).

1. **Shadow enhancement** (L15 Eq. 3.52, footnote 35; spc-algorithms.md §5.3).  ŝ_xy = the unit
   projection of ŝ_m on the maplet plane, ŝ⊥ = (−ŝ_y, ŝ_x).  An *edge cell* p is non-zero while
   p + NINT(k·ŝ_xy) is 0 (zero or invalid) for k = 1…``edge_steps`` (3) — the anti-Sun end of a
   shadow; offsets falling outside the grid make p no edge.  From every edge cell (found on the
   image *before* any enhancement) zero the cells p + NINT(−k·ŝ_xy + j·ŝ⊥) for
   k = k₀…ds and j ∈ {−``lateral``…``lateral``} (``lateral_band=True``, default: L15's "within plus
   or minus two") or j ∈ {−lateral, 0, +lateral} (``lateral_band=False``, the ±2·ŝ⊥ offsets only).
   ds = ``ds_base`` + ⌊1/|det J_xy|⌋ (``ds_mode="seed"``, L15 Eq. 3.52) or ds_base + ⌊1/√|det J_xy|⌋
   (``"sqrt"``, erratum 19), capped at 2N.  k₀ = 0 (``shadow_include_edge=True``, default): the
   edge cell itself is zeroed too, so a shadow grows by ds + 1 cells along −ŝ_xy — L15's "each
   pixel … within a distance of ds".  spc-algorithms.md §5.3 lists k = 1…ds, which would leave the
   lit edge cell p standing between the old shadow and the zeroed cells;
   ``shadow_include_edge=False`` gives that literal reading.  ŝ⊥ is the perpendicular (−ŝ_y, ŝ_x),
   not the seed's swapped [y, x] (erratum 20).  Skipped when the Sun is at the maplet zenith.
2. **Emission cut**: zero cells with n̂·ê < ``cos_e_min`` (0.05), n̂ from the HGT2SLP slopes.
3. **Visibility march**: from every valid cell not cut in step 2, step one cell horizontally along
   ê_xy; the ray (lowered by ``vis_tol`` = 0.05 cell) must stay above the bilinear terrain
   (:func:`spctool.geometry.heightfield.march`, L15 footnote 36).  Steps 2 and 3 are evaluated for
   every valid cell (mask ``visible``); cells that were non-zero before them and are zeroed count as
   removed-invisible.
4. **Cast-shadow march** along ŝ, same rules with ``shadow_tol`` — off by default
   (``cast_shadow_trace=False``): SPC's code skips it with a GOTO (L15 footnote 37).

INV = NINT(1000·removed_invisible/(N² + 1)) (L15 Eq. 3.53 with its "+1"; the invisibility removals
only, not the shadow enhancement — SPC wiki "Eliminate pictures from landmark"; erratum 22).

Stage E — statistics and removal (:func:`statistics`, :class:`Criteria`)
-------------------------------------------------------------------------
* EMISS = arccos(ê·UZ) in degrees (L15 Eq. 3.54); COV = covered/N²; ILL = cells with a non-zero
  final (filtered) extracted value / N² (``ill_source="extracted"``, erratum 21; ``"predicted"`` uses
  the prediction's lit cells, L15 Eq. 3.55 read literally); RES = r_img/s_m = 1/√|det J_xy|
  (L15 Eq. 3.56 with erratum 9); INV as above.
* Removal (LITHOS "E. Eliminate pictures", spc-algorithms.md §6.3; errata 22, 23), first match wins,
  status ``removed-<criterion>``: INV > INVLIM (only when INVLIM > 0); EMISS ≥ SLIM; COV < CLIM;
  ILL < ILIM (LITHOS only; AUTOREGISTER has no ILIM); RES < RSMN; RES > RSMX.  Presets:
  ``lithos_standard`` = 0, 60, .25, .25, 0, 3 and ``autoregister`` = 0, 50, .25, 0, 5.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, fields
from typing import NamedTuple

import numba
import numpy as np

from spctool.errors import SpcUsageError
from spctool.geometry import heightfield
from spctool.geometry.frames import unit_vector
from spctool.geometry.heightfield import surface_cosines

__all__ = [
    "Criteria",
    "ExtractOptions",
    "Extraction",
    "FilterResult",
    "PRESETS",
    "Statistics",
    "brt0",
    "extract",
    "extract_filter",
    "filter",
    "nint",
    "shadow_extension",
    "shadow_offsets",
    "statistics",
    "subsample_count",
]

DS_MODES = ("seed", "sqrt")
ILL_SOURCES = ("extracted", "predicted")

#: |ŝ_xy| (of a unit ŝ) below this: the Sun is at the maplet zenith and no shadow direction exists.
ZENITH_EPS = 1e-9


# --------------------------------------------------------------------------------------------------
# Stage E criteria


@dataclass(frozen=True)
class Criteria:
    """LITHOS / AUTOREGISTER removal criteria (spc-algorithms.md §6.2–6.3).

    ``invlim`` ‰ (0 disables the test), ``slim`` degrees, ``clim`` and ``ilim`` fractions (``ilim``
    None: AUTOREGISTER's five-value form, no ILL test), ``rsmn``/``rsmx`` image pixel ÷ maplet scale.
    """

    invlim: float = 0.0
    slim: float = 60.0
    clim: float = 0.25
    ilim: float | None = 0.25
    rsmn: float = 0.0
    rsmx: float = 3.0

    @classmethod
    def parse(cls, value) -> Criteria:
        """A :class:`Criteria` from a preset name, a text ``"0,60,.25,.25,0,3"`` (commas and/or blanks;
        6 values = LITHOS INVLIM, SLIM, CLIM, ILIM, RSMN, RSMX; 5 values = AUTOREGISTER INVLIM, SLIM,
        CLIM, RSMN, RSMX), a sequence of 5 or 6 numbers, or a Criteria."""
        if isinstance(value, Criteria):
            return value
        if isinstance(value, str):
            key = value.strip().lower().replace("-", "_")
            if key in PRESETS:
                return PRESETS[key]
            parts = [p for p in re.split(r"[\s,]+", value.strip()) if p]
            try:
                nums = [float(p.replace("D", "E").replace("d", "e")) for p in parts]
            except ValueError:
                raise SpcUsageError(
                    f"removal criteria {value!r}: expected a preset ({', '.join(PRESETS)}) or 5/6 numbers "
                    "like '0,60,.25,.25,0,3'"
                ) from None
        else:
            try:
                nums = [float(x) for x in value]
            except (TypeError, ValueError):
                raise SpcUsageError(f"removal criteria must be 5 or 6 numbers, got {value!r}") from None
        if any(math.isnan(x) for x in nums):
            raise SpcUsageError(f"removal criteria must be numbers, got {value!r}")
        if len(nums) == 6:
            return cls(*nums)
        if len(nums) == 5:
            inv, slim, clim, rsmn, rsmx = nums
            return cls(inv, slim, clim, None, rsmn, rsmx)
        raise SpcUsageError(f"removal criteria need 6 (LITHOS) or 5 (AUTOREGISTER) values, got {len(nums)}")

    def as_tuple(self) -> tuple:
        if self.ilim is None:
            return (self.invlim, self.slim, self.clim, self.rsmn, self.rsmx)
        return (self.invlim, self.slim, self.clim, self.ilim, self.rsmn, self.rsmx)

    def text(self) -> str:
        return ",".join(f"{x:g}" for x in self.as_tuple())

    def status(self, emission_deg: float, cov: float, ill: float, res: float, inv: float) -> str:
        """``"ok"`` or ``"removed-<criterion>"`` for the first failed test, in the prompt's order."""
        if self.invlim > 0.0 and inv > self.invlim:
            return "removed-invlim"
        if emission_deg >= self.slim:
            return "removed-slim"
        if cov < self.clim:
            return "removed-clim"
        if self.ilim is not None and ill < self.ilim:
            return "removed-ilim"
        if res < self.rsmn:
            return "removed-rsmn"
        if res > self.rsmx:
            return "removed-rsmx"
        return "ok"


#: named criteria sets (spc-algorithms.md §6.3, §13)
PRESETS = {
    "lithos_standard": Criteria(0.0, 60.0, 0.25, 0.25, 0.0, 3.0),
    "autoregister": Criteria(0.0, 50.0, 0.25, None, 0.0, 5.0),
}


# --------------------------------------------------------------------------------------------------
# options and results


@dataclass
class ExtractOptions:
    """Every constant of Stages C–E (module docstring; spc-algorithms.md §13).

    ``criteria``: a :class:`Criteria`, a preset name (``"lithos_standard"`` default,
    ``"autoregister"``), a text like ``"0,60,.25,.25,0,3"`` or None (no removal test: status ``ok``).
    ``repair_floor``: the 1 of BRT0's max(1, b₁ + b₂ − b₃) repair.
    """

    linearized: bool = False
    subsample: str | int = "auto"
    apply_filter: bool = True
    ds_mode: str = "seed"
    ds_base: int = 3
    edge_steps: int = 3
    shadow_include_edge: bool = True
    lateral: int = 2
    lateral_band: bool = True
    emission_cut: bool = True
    cos_e_min: float = 0.05
    visibility_march: bool = True
    vis_tol: float = heightfield.VIS_TOL
    cast_shadow_trace: bool = False
    shadow_tol: float = heightfield.VIS_TOL
    criteria: Criteria | str | tuple | None = "lithos_standard"
    ill_source: str = "extracted"
    repair_floor: float = 1.0

    def __post_init__(self):
        def bad(msg):
            raise SpcUsageError(f"extraction option {msg}")

        if isinstance(self.subsample, str):
            if self.subsample.strip().lower() == "auto":
                self.subsample = "auto"
            else:
                try:
                    self.subsample = int(self.subsample)
                except ValueError:
                    bad(f"subsample must be 'auto' or an integer >= 1, got {self.subsample!r}")
        if self.subsample != "auto":
            self.subsample = int(self.subsample)
            if self.subsample < 1:
                bad(f"subsample must be 'auto' or an integer >= 1, got {self.subsample}")
        if self.ds_mode not in DS_MODES:
            bad(f"ds_mode must be one of {', '.join(DS_MODES)}, got {self.ds_mode!r}")
        if self.ill_source not in ILL_SOURCES:
            bad(f"ill_source must be one of {', '.join(ILL_SOURCES)}, got {self.ill_source!r}")
        for name in ("ds_base", "edge_steps", "lateral"):
            value = int(getattr(self, name))
            if value < 0:
                bad(f"{name} must be >= 0, got {value}")
            setattr(self, name, value)
        if self.edge_steps < 1:
            bad("edge_steps must be >= 1")
        for name in ("cos_e_min", "vis_tol", "shadow_tol", "repair_floor"):
            value = float(getattr(self, name))
            if math.isnan(value):
                bad(f"{name} must be a number, got NaN")
            setattr(self, name, value)
        if self.criteria is not None:
            self.criteria = Criteria.parse(self.criteria)

    def as_dict(self) -> dict:
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["criteria"] = None if self.criteria is None else self.criteria.text()
        return out


class FilterResult(NamedTuple):
    """Result of :func:`extract_filter` (arrays (N, N))."""

    image: np.ndarray  #: filtered image
    removed_shadow: np.ndarray  #: non-zero cells zeroed by the shadow enhancement (and the cast march)
    removed_invisible: np.ndarray  #: non-zero cells zeroed by the emission cut or the visibility march
    visible: np.ndarray  #: valid cells passing the emission cut and the visibility march
    emission_cut: np.ndarray  #: valid cells with n̂·ê < cos_e_min
    occluded: np.ndarray  #: valid cells whose line of sight is blocked (march)
    shadowed: np.ndarray  #: cells in cast shadow (cast_shadow_trace; else all False)
    edges: np.ndarray  #: shadow edge cells found
    ds: int  #: shadow extension used
    inv: int  #: NINT(1000·removed_invisible/(N² + 1))


class Statistics(NamedTuple):
    """Stage E values of one (maplet, picture) pair (spc-algorithms.md §6.3)."""

    emission_deg: float
    cov: float
    ill: float
    res: float
    inv: int


@dataclass
class Extraction:
    """Result of :func:`extract`.  Arrays are (N, N), axis 0 along UX, axis 1 along UY.

    ``image``: extracted (and, with ``apply_filter``, filtered) DN, 0 = no data.  ``valid`` =
    ``image > 0`` (the cells a correlator uses).  ``covered``, ``lit``: module docstring, Stage C.
    ``visible``: valid cells passing the emission cut and the march (all valid cells without the
    filter).  ``removed_shadow`` / ``removed_invisible``: cells the filter zeroed.  ``sample``,
    ``line``: the pixel of every node (after re-centring; NaN for invalid nodes and nodes behind the
    camera).  ``center_sample``/``center_line``: pixel of V used.  ``jxy``: J_xy (2, 2) px per cell
    at V (columns x along UX, y along UY); ``j3``: (2, 3) with the height column; ``det_j``.
    ``subsample``: m used; ``ds``: shadow extension used.  Statistics: ``emission_deg``, ``cov``,
    ``ill``, ``res``, ``inv`` (‰); ``status``: ``ok``, ``outside`` (V behind the camera) or
    ``removed-<criterion>``.
    """

    image: np.ndarray
    valid: np.ndarray
    covered: np.ndarray
    lit: np.ndarray
    visible: np.ndarray
    removed_shadow: np.ndarray
    removed_invisible: np.ndarray
    shadowed: np.ndarray
    sample: np.ndarray
    line: np.ndarray
    center_sample: float
    center_line: float
    jxy: np.ndarray
    j3: np.ndarray
    det_j: float
    subsample: int
    ds: int
    emission_deg: float
    cov: float
    ill: float
    res: float
    inv: int
    status: str
    emission_vector: np.ndarray
    sun_vector: np.ndarray
    options: ExtractOptions

    @property
    def statistics(self) -> Statistics:
        return Statistics(self.emission_deg, self.cov, self.ill, self.res, self.inv)


# --------------------------------------------------------------------------------------------------
# helpers


def nint(x) -> np.ndarray:
    """Fortran NINT: round half away from zero (arrays; returns int64)."""
    a = np.asarray(x, dtype=np.float64)
    return (np.sign(a) * np.floor(np.abs(a) + 0.5)).astype(np.int64)


def subsample_count(det_j: float, subsample="auto") -> int:
    """m (per axis): ⌈√|det J_xy|⌉ when √|det J_xy| > 1 and ``subsample="auto"``, else 1; an int forces m."""
    if subsample != "auto":
        return max(1, int(subsample))
    root = math.sqrt(abs(float(det_j)))
    if not math.isfinite(root) or root <= 1.0:
        return 1
    return int(math.ceil(root))


def shadow_extension(det_j: float, ds_mode: str = "seed", ds_base: int = 3, cap: int | None = None) -> int:
    """ds = ds_base + ⌊1/|det J_xy|⌋ (``"seed"``, L15 Eq. 3.52) or ds_base + ⌊1/√|det J_xy|⌋ (``"sqrt"``,
    erratum 19); the floor term is capped at ``cap`` (default: none) and is ``cap`` when det J = 0."""
    if ds_mode not in DS_MODES:
        raise SpcUsageError(f"ds_mode must be one of {', '.join(DS_MODES)}, got {ds_mode!r}")
    a = abs(float(det_j))
    if not a > 0.0:
        x = math.inf
    else:
        x = 1.0 / a if ds_mode == "seed" else 1.0 / math.sqrt(a)
    if cap is not None and not x <= cap:
        x = float(cap)
    if not math.isfinite(x):
        raise SpcUsageError("shadow extension is infinite (det J = 0); give a cap")
    return int(ds_base) + int(math.floor(x))


def shadow_offsets(sun_xy, ds: int, lateral: int = 2, band: bool = True, include_edge: bool = True,
                   edge_steps: int = 3):
    """The integer cell offsets of the shadow enhancement for a unit horizontal Sun direction ``sun_xy``
    (ŝ_x along axis 0, ŝ_y along axis 1).

    Returns ``(checks, zeros)``: ``checks`` (edge_steps, 2) = NINT(k·ŝ_xy), k = 1…edge_steps (the
    sunward cells that must be 0 for an edge cell); ``zeros`` (M, 2) = the distinct
    NINT(−k·ŝ_xy + j·ŝ⊥), k = k₀…ds, j in the lateral set (module docstring), ŝ⊥ = (−ŝ_y, ŝ_x), in
    ascending (row, column) order.  Computed without the GIL (:func:`_k_shadow_offsets`).
    """
    sx, sy = float(sun_xy[0]), float(sun_xy[1])
    return _k_shadow_offsets(sx, sy, int(ds), int(lateral), bool(band), bool(include_edge), int(edge_steps))


# --------------------------------------------------------------------------------------------------
# numba kernels

_JIT = dict(cache=True, nogil=True)


@numba.njit(forceinline=True, **_JIT)
def _corner(data, row, col, t_lo, t_hi):
    v = float(data[row, col])
    if v >= t_lo and v <= t_hi:  # NaN fails both
        return v
    return 0.0


@numba.njit(forceinline=True, **_JIT)
def _brt0_one(data, x, y, t_lo, t_hi, floor_value):
    """BRT0 at one point (1-based sample x, line y); 0 = invalid."""
    nln, npx = data.shape
    if not (x >= 1.0 and x < npx and y >= 1.0 and y < nln):  # NaN fails
        return 0.0
    i = int(x)  # floor (x >= 1)
    j = int(y)
    fx = x - i
    fy = y - j
    # corners (sample, line): b0 = (i, j), b1 = (i+1, j), b2 = (i, j+1), b3 = (i+1, j+1); 1-based
    b0 = _corner(data, j - 1, i - 1, t_lo, t_hi)
    b1 = _corner(data, j - 1, i, t_lo, t_hi)
    b2 = _corner(data, j, i - 1, t_lo, t_hi)
    b3 = _corner(data, j, i, t_lo, t_hi)
    nz = (b0 == 0.0) + (b1 == 0.0) + (b2 == 0.0) + (b3 == 0.0)
    if nz == 1:  # one missing corner: planar extrapolation from the other three
        if b0 == 0.0:
            b0 = max(floor_value, b1 + b2 - b3)
        elif b1 == 0.0:
            b1 = max(floor_value, b0 + b3 - b2)
        elif b2 == 0.0:
            b2 = max(floor_value, b0 + b3 - b1)
        else:
            b3 = max(floor_value, b1 + b2 - b0)
    elif nz > 1:
        return 0.0
    v = b0 + (b1 - b0) * fx + (b2 - b0) * fy + (b0 + b3 - b1 - b2) * fx * fy
    return v if v > 0.0 else 0.0


@numba.njit(forceinline=True, **_JIT)
def _nint1(a):
    """:func:`nint` of one float (sign(a)·⌊|a| + ½⌋, the same operations)."""
    sign = 1.0 if a > 0.0 else (-1.0 if a < 0.0 else a)
    return np.int64(sign * math.floor(abs(a) + 0.5))


@numba.njit(**_JIT)
def _k_shadow_offsets(sx, sy, ds, lateral, band, include_edge, edge_steps):  # pragma: no cover - compiled
    """:func:`shadow_offsets`: the products and sums of its NumPy form element by element (k along the
    outer loop, j the inner), NINT, and the distinct rows in ascending (row, column) order."""
    checks = np.empty((max(0, edge_steps), 2), dtype=np.int64)
    for k in range(1, edge_steps + 1):
        checks[k - 1, 0] = _nint1(k * sx)
        checks[k - 1, 1] = _nint1(k * sy)
    if band:
        js = np.empty(2 * lateral + 1 if lateral >= 0 else 0)
        for i in range(js.shape[0]):
            js[i] = float(i - lateral)
    else:  # the distinct values of (−lateral, 0, lateral), ascending (np.unique's, without its sort)
        hi = float(abs(lateral))
        js = np.zeros(1 if hi == 0.0 else 3)
        if hi != 0.0:
            js[0] = -hi
            js[2] = hi
    k0 = 0 if include_edge else 1
    nk = max(0, ds + 1 - k0)
    raw = np.empty((nk * js.shape[0], 2), dtype=np.int64)
    t = 0
    for a in range(nk):
        kk = float(k0 + a)
        for jj in js:
            raw[t, 0] = _nint1(-kk * sx - jj * sy)
            raw[t, 1] = _nint1(-kk * sy + jj * sx)
            t += 1
    if t == 0:
        return checks, np.empty((0, 2), dtype=np.int64)
    # the distinct (row, column) pairs in ascending row-major order: marked on their bounding grid and
    # read back row by row (no sort: numba's np.unique cost ~8 s to compile)
    r0, r1, c0, c1 = raw[0, 0], raw[0, 0], raw[0, 1], raw[0, 1]
    for i in range(1, t):
        r0, r1 = min(r0, raw[i, 0]), max(r1, raw[i, 0])
        c0, c1 = min(c0, raw[i, 1]), max(c1, raw[i, 1])
    seen = np.zeros((r1 - r0 + 1, c1 - c0 + 1), dtype=np.bool_)
    count = 0
    for i in range(t):
        if not seen[raw[i, 0] - r0, raw[i, 1] - c0]:
            seen[raw[i, 0] - r0, raw[i, 1] - c0] = True
            count += 1
    zeros = np.empty((count, 2), dtype=np.int64)
    r = 0
    for a in range(seen.shape[0]):
        for b in range(seen.shape[1]):
            if seen[a, b]:
                zeros[r, 0] = a + r0
                zeros[r, 1] = b + c0
                r += 1
    return checks, zeros


@numba.njit(**_JIT)
def _brt0_kernel(data, smp, lin, t_lo, t_hi, floor_value, out):
    for k in range(smp.shape[0]):
        out[k] = _brt0_one(data, smp[k], lin[k], t_lo, t_hi, floor_value)


@numba.njit(**_JIT)
def _subsample_kernel(data, smp, lin, ok, sx, sy, lx, ly, offs, t_lo, t_hi, floor_value, values, covered):
    """Average of the non-zero BRT0 samples at (smp + a·sx + b·sy, lin + a·lx + b·ly), a, b in offs."""
    nln, npx = data.shape
    m = offs.shape[0]
    for k in range(smp.shape[0]):
        values[k] = 0.0
        covered[k] = False
        if not ok[k]:
            continue
        total = 0.0
        count = 0
        inside = False
        for ia in range(m):
            a = offs[ia]
            for ib in range(m):
                b = offs[ib]
                x = smp[k] + a * sx[k] + b * sy[k]
                y = lin[k] + a * lx[k] + b * ly[k]
                if x >= 1.0 and x < npx and y >= 1.0 and y < nln:
                    inside = True
                    v = _brt0_one(data, x, y, t_lo, t_hi, floor_value)
                    if v > 0.0:
                        total += v
                        count += 1
        covered[k] = inside
        if count > 0:
            values[k] = total / count


@numba.njit(**_JIT)
def _enhance_kernel(nonzero, checks, zeros, out, edges):
    n0, n1 = nonzero.shape
    for r in range(n0):
        for c in range(n1):
            if not nonzero[r, c]:
                continue
            edge = True
            for k in range(checks.shape[0]):
                rr = r + checks[k, 0]
                cc = c + checks[k, 1]
                if rr < 0 or rr >= n0 or cc < 0 or cc >= n1 or nonzero[rr, cc]:
                    edge = False
                    break
            if not edge:
                continue
            edges[r, c] = True
            for k in range(zeros.shape[0]):
                rr = r + zeros[k, 0]
                cc = c + zeros[k, 1]
                if rr >= 0 and rr < n0 and cc >= 0 and cc < n1:
                    out[rr, cc] = True


@numba.njit(**_JIT)
def _k_recentred(data, sample0, line0, ds, dl, t_lo, t_hi, floor_value, enhance, checks, zeros,
                 filtered, visible, smp, lin, image, valid, covered, lit, removed_shadow):  # pragma: no cover
    """An extraction moved by (``ds``, ``dl``) px, in one pass without the GIL (the re-centred
    extraction of :meth:`spctool.stages.registrar.Registrar.extraction`, the same float operations
    as its NumPy form): node pixels ``sample0 + ds``, ``line0 + dl``; ``covered``; BRT0 at every
    finite node; ``lit``; with ``enhance`` the shadow enhancement (:func:`_enhance_kernel` with
    ``checks``, ``zeros``) zeroes and records ``removed_shadow``; with ``filtered`` cells not
    ``visible`` are zeroed; ``valid`` = image > 0.  Every output is (N, N) and overwritten."""
    n0, n1 = sample0.shape
    nln, npx = data.shape
    for r in range(n0):
        for c in range(n1):
            s = sample0[r, c] + ds
            ln = line0[r, c] + dl
            smp[r, c] = s
            lin[r, c] = ln
            ok = np.isfinite(sample0[r, c])
            covered[r, c] = ok and s >= 1.0 and s < npx and ln >= 1.0 and ln < nln
            v = _brt0_one(data, s, ln, t_lo, t_hi, floor_value) if ok else 0.0
            lit[r, c] = ok and v > 0.0
            image[r, c] = v if lit[r, c] else 0.0
            removed_shadow[r, c] = False
    if enhance:
        nonzero = np.empty((n0, n1), dtype=np.bool_)
        for r in range(n0):
            for c in range(n1):
                nonzero[r, c] = image[r, c] > 0.0
        zero = np.zeros((n0, n1), dtype=np.bool_)
        edges = np.zeros((n0, n1), dtype=np.bool_)
        _enhance_kernel(nonzero, checks, zeros, zero, edges)
        for r in range(n0):
            for c in range(n1):
                if zero[r, c]:
                    removed_shadow[r, c] = nonzero[r, c]
                    image[r, c] = 0.0
    for r in range(n0):
        for c in range(n1):
            if filtered and not visible[r, c]:
                image[r, c] = 0.0
            valid[r, c] = image[r, c] > 0.0


# --------------------------------------------------------------------------------------------------
# Stage C sampler


def _node_positions(x, y, h, scale, v, ux, uy, uz) -> np.ndarray:
    """P = V + SCALE·(x·UX + y·UY + h·UZ) (N, N, 3), component by component (the same formula as
    :func:`spctool.geometry.heightfield.node_positions`, ~20× faster than broadcasting over a length-3
    last axis for a 99×99 grid); ``x`` a column (N, 1) and ``y`` a row (1, N) of cell offsets."""
    out = np.empty(h.shape + (3,))
    for k in range(3):
        out[..., k] = v[k] + scale * ((x * ux[k] + y * uy[k]) + h * uz[k])
    return out


@numba.njit(**_JIT)
def _k_node_positions(h, q, scale, v, ux, uy, uz, out):  # pragma: no cover - compiled
    """:func:`_node_positions` with x = r − q, y = c − q at node (r, c), without the GIL (the same
    operations in the same order)."""
    for r in range(h.shape[0]):
        x = float(r) - q
        for c in range(h.shape[1]):
            y = float(c) - q
            for k in range(3):
                out[r, c, k] = v[k] + scale * ((x * ux[k] + y * uy[k]) + h[r, c] * uz[k])


@numba.njit(**_JIT)
def _k_sample_nodes(data, smp, lin, front, mvalid, front_v, moved, d_s, d_l, t_lo, t_hi, floor_value,
                    node_ok, covered, image, lit):  # pragma: no cover - compiled
    """:func:`extract`'s node sampling at one sample per cell, without the GIL: node pixels moved by
    (``d_s``, ``d_l``) when ``moved`` (in place), ``node_ok`` (valid, in front, finite, V in front),
    pixels of the other nodes set to NaN (in place), ``covered``, BRT0 values, ``lit`` and the image
    (the same operations as its NumPy form)."""
    nln, npx = data.shape
    for r in range(smp.shape[0]):
        for c in range(smp.shape[1]):
            s = smp[r, c]
            ln = lin[r, c]
            if moved:
                s = s + d_s
                ln = ln + d_l
            ok = mvalid[r, c] and front[r, c] and np.isfinite(s) and np.isfinite(ln) and front_v
            if not ok:
                s = np.nan
                ln = np.nan
            smp[r, c] = s
            lin[r, c] = ln
            node_ok[r, c] = ok
            covered[r, c] = ok and s >= 1.0 and s < npx and ln >= 1.0 and ln < nln
            v = _brt0_one(data, s, ln, t_lo, t_hi, floor_value)
            lit[r, c] = ok and v > 0.0
            image[r, c] = v if lit[r, c] else 0.0


def _thresholds(thresholds):
    if thresholds is None:
        return -math.inf, math.inf
    t = np.asarray(thresholds, dtype=np.float64).reshape(-1)
    if t.size != 2:
        raise SpcUsageError(f"thresholds must be (T1, T2), got {thresholds!r}")
    lo = -math.inf if math.isnan(t[0]) else float(t[0])
    hi = math.inf if math.isnan(t[1]) else float(t[1])
    return lo, hi


def _photo_array(photo) -> np.ndarray:
    data = photo.data if hasattr(photo, "data") else photo
    data = np.asarray(data)
    if data.ndim != 2:
        raise SpcUsageError(f"photo data must be 2-D (NLN, NPX), got shape {data.shape}")
    if data.dtype.kind not in "uif" or data.dtype.kind == "f" and data.dtype.itemsize < 4:
        data = data.astype(np.float64)
    return np.ascontiguousarray(data)


def brt0(photo_data, sample, line, t_lo=-math.inf, t_hi=math.inf, *, repair_floor: float = 1.0) -> np.ndarray:
    """SPC's BRT0 bilinear sampler (spc-algorithms.md §4.2, xBrt.f), vectorised over points.

    ``photo_data[line − 1, sample − 1]`` (a :class:`~spctool.formats.photo.Photo` works too);
    ``sample``, ``line`` 1-based SPC pixels (broadcast).  A point is sampled only if
    1 ≤ sample < NPX and 1 ≤ line < NLN; base pixel = floor; corners b₀ = (i, j), b₁ = (i+1, j),
    b₂ = (i, j+1), b₃ = (i+1, j+1).  DN outside [``t_lo``, ``t_hi``] (and NaN) count as 0 = missing;
    exactly one missing corner is rebuilt by planar extrapolation, b₀ ← max(1, b₁ + b₂ − b₃) (likewise
    b₁ ← max(1, b₀ + b₃ − b₂), b₂ ← max(1, b₀ + b₃ − b₁), b₃ ← max(1, b₁ + b₂ − b₀); the 1 is
    ``repair_floor``); two or more missing corners give 0.  The result is clipped at ≥ 0; 0 means
    invalid.  Returns float64 with the broadcast shape.
    """
    data = _photo_array(photo_data)
    s, ln = np.broadcast_arrays(np.asarray(sample, dtype=np.float64), np.asarray(line, dtype=np.float64))
    shape = s.shape
    sf = np.ascontiguousarray(s.reshape(-1))
    lf = np.ascontiguousarray(ln.reshape(-1))
    if not sf.flags.writeable:
        sf = sf.copy()
    if not lf.flags.writeable:
        lf = lf.copy()
    out = np.empty(sf.size)
    _brt0_kernel(data, sf, lf, float(t_lo), float(t_hi), float(repair_floor), out)
    return out.reshape(shape)


# --------------------------------------------------------------------------------------------------
# Stage D


def extract_filter(image, heights, valid, ux, uy, uz, sun, emission, det_j,
                   options: ExtractOptions | None = None, *,
                   slopes: heightfield.Slopes | None = None) -> FilterResult:
    """Stage D on an extracted image (module docstring, spc-algorithms.md §5.3).

    ``image`` (N, N) extracted values (0 = no data); ``heights``/``valid`` the maplet grid (heights in
    cells); ``ux``, ``uy``, ``uz`` the maplet axes; ``sun`` the body→Sun vector and ``emission`` the
    landmark→camera vector (body frame, normalised here); ``det_j`` = det J_xy (px per cell).
    ``slopes``: precomputed :func:`heightfield.slopes` (optional).  Returns a :class:`FilterResult`;
    the input image is not modified.
    """
    opts = options if options is not None else ExtractOptions()
    img = np.array(image, dtype=np.float64, copy=True)
    h = np.asarray(heights, dtype=np.float64)
    vmask = np.ones(h.shape, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if img.shape != h.shape or vmask.shape != h.shape or h.ndim != 2 or h.shape[0] != h.shape[1]:
        raise SpcUsageError("extract_filter: image, heights and valid must be square arrays of one shape")
    n = h.shape[0]
    s_m = heightfield.to_maplet_components(unit_vector(sun, "sun"), ux, uy, uz)
    e_m = heightfield.to_maplet_components(unit_vector(emission, "emission"), ux, uy, uz)

    # 1. shadow enhancement
    ds = shadow_extension(det_j, opts.ds_mode, opts.ds_base, cap=2 * n)
    zero = np.zeros(h.shape, dtype=bool)
    edges = np.zeros(h.shape, dtype=bool)
    nonzero = img > 0.0
    s_xy = math.hypot(s_m[0], s_m[1])
    if s_xy > ZENITH_EPS * float(np.linalg.norm(s_m)):
        checks, zeros = shadow_offsets(
            (s_m[0] / s_xy, s_m[1] / s_xy), ds, opts.lateral, opts.lateral_band, opts.shadow_include_edge,
            opts.edge_steps,
        )
        _enhance_kernel(nonzero, checks, zeros, zero, edges)
    removed_shadow = zero & nonzero
    img[zero] = 0.0

    # 2. emission cut and 3. visibility march, evaluated for every valid cell
    if opts.emission_cut or opts.visibility_march:
        hx, hy, _ = slopes if slopes is not None else heightfield.slopes(h, vmask)
    if opts.emission_cut:
        cut = vmask & (surface_cosines(hx, hy, e_m) < opts.cos_e_min)
    else:
        cut = np.zeros(h.shape, dtype=bool)
    if opts.visibility_march:
        occluded = heightfield.march(h, vmask, e_m, tol=opts.vis_tol, nodes=vmask & ~cut)
    else:
        occluded = np.zeros(h.shape, dtype=bool)
    invisible = cut | occluded
    removed_invisible = invisible & (img > 0.0)
    img[invisible] = 0.0

    # 4. cast-shadow march (SPC's dead code; off by default)
    if opts.cast_shadow_trace:
        shadowed = heightfield.march(h, vmask, s_m, tol=opts.shadow_tol, nodes=img > 0.0)
        removed_shadow = removed_shadow | shadowed
        img[shadowed] = 0.0
    else:
        shadowed = np.zeros(h.shape, dtype=bool)

    inv = int(nint(1000.0 * np.count_nonzero(removed_invisible) / (n * n + 1.0)))
    return FilterResult(img, removed_shadow, removed_invisible, vmask & ~invisible, cut, occluded, shadowed,
                        edges, ds, inv)


#: the name used by the stage map (``filter`` shadows the builtin only inside this module's namespace)
filter = extract_filter  # noqa: A001


# --------------------------------------------------------------------------------------------------
# Stage E


def statistics(emission_vector, uz, covered, image, removed_invisible, det_j, ill_mask=None) -> Statistics:
    """EMISS, COV, ILL, RES, INV of one (maplet, picture) pair (spc-algorithms.md §6.3).

    ``ill_mask``: the cells counted as illuminated (default ``image > 0``; pass the prediction's lit
    cells for ``ill_source="predicted"``).
    """
    e = unit_vector(emission_vector, "emission")
    z = unit_vector(uz, "uz")
    emission_deg = math.degrees(math.acos(min(1.0, max(-1.0, float(e @ z)))))
    total = np.asarray(image).size
    cov = np.count_nonzero(covered) / total
    lit = np.asarray(image) > 0.0 if ill_mask is None else np.asarray(ill_mask, dtype=bool)
    ill = np.count_nonzero(lit) / total
    a = abs(float(det_j))
    res = 1.0 / math.sqrt(a) if a > 0.0 else math.inf
    n = int(round(math.sqrt(total)))
    inv = int(nint(1000.0 * np.count_nonzero(removed_invisible) / (n * n + 1.0)))
    return Statistics(emission_deg, float(cov), float(ill), res, inv)


# --------------------------------------------------------------------------------------------------
# the stage


def extract(photo, maplet, camera, sun, thresholds=None, options: ExtractOptions | None = None,
            center_pixel=None, *, slopes: heightfield.Slopes | None = None, prediction=None) -> Extraction:
    """Stages C–E: resample ``photo`` onto ``maplet``, filter, and compute the removal statistics.

    ``photo``: :class:`~spctool.formats.photo.Photo` or array ``data[line − 1, sample − 1]``;
    ``maplet``: object with ``heights`` (cells), ``valid``, ``scale``, ``v``, ``ux``, ``uy``, ``uz``;
    ``camera``: :class:`~spctool.geometry.camera.Camera` of the picture; ``sun``: body→Sun vector;
    ``thresholds``: (T1, T2) = SUM THRSH (None or NaN: unbounded); ``center_pixel``: (sample, line)
    where V is placed (module docstring, "Re-centring"); ``slopes``: precomputed slopes;
    ``prediction``: a :class:`~spctool.stages.predict.Prediction` whose ``lit`` cells give ILL when
    ``ill_source="predicted"`` (computed from the slopes, without cast shadows, when omitted).
    """
    opts = options if options is not None else ExtractOptions()
    data = _photo_array(photo)
    nln, npx = data.shape
    t_lo, t_hi = _thresholds(thresholds)
    heights = np.asarray(maplet.heights, dtype=np.float64)
    mvalid = np.asarray(maplet.valid, dtype=bool)
    n = heights.shape[0]
    if heights.shape != (n, n) or mvalid.shape != heights.shape or n % 2 != 1:
        raise SpcUsageError("maplet heights and valid must be (2q+1)x(2q+1) arrays")
    q = (n - 1) // 2
    scale = float(maplet.scale)
    v = np.asarray(maplet.v, dtype=np.float64)
    ux, uy, uz = (np.asarray(u, dtype=np.float64) for u in (maplet.ux, maplet.uy, maplet.uz))
    s_hat = unit_vector(sun, "sun")
    e_hat = unit_vector(camera.position - v, "landmark-to-spacecraft vector")
    sl = slopes if slopes is not None else heightfield.slopes(heights, mvalid)

    # centre pixel and Jacobians at V
    pj = camera.project_with_jacobians(v[None, :])
    cs0, cl0 = float(pj.sample[0]), float(pj.line[0])
    front_v = bool(pj.camera_points[0, 2] > 0.0)
    j3 = pj.point[0] @ (scale * np.stack([ux, uy, uz], axis=1))  # (2, 3) px per cell along UX, UY, UZ
    jxy = j3[:, :2].copy()
    det_j = float(np.linalg.det(jxy))
    if center_pixel is not None:
        cs, cl = (float(x) for x in np.asarray(center_pixel, dtype=np.float64).reshape(2))
    else:
        cs, cl = cs0, cl0

    # node pixels
    m = subsample_count(det_j, opts.subsample)
    hz = np.where(mvalid, heights, 0.0)
    fused = not opts.linearized and m == 1
    if fused:
        # the node pixels and their BRT0 samples in two GIL-free kernels (the operations below)
        pos = np.empty(heights.shape + (3,))
        _k_node_positions(hz, float(q), scale, v, ux, uy, uz, pos)
        smp, lin, front = camera.project_with_mask(pos)
        node_ok, covered, lit = (np.empty(heights.shape, dtype=bool) for _ in range(3))
        image = np.empty(heights.shape)
        moved = center_pixel is not None
        _k_sample_nodes(
            data, smp, lin, front, mvalid, front_v, moved, cs - cs0, cl - cl0, t_lo, t_hi,
            float(opts.repair_floor), node_ok, covered, image, lit,
        )  # fmt: skip
    else:
        x = (np.arange(n, dtype=np.float64) - q)[:, None]
        y = (np.arange(n, dtype=np.float64) - q)[None, :]
        if opts.linearized:
            smp = cs + j3[0, 0] * x + j3[0, 1] * y + j3[0, 2] * hz
            lin = cl + j3[1, 0] * x + j3[1, 1] * y + j3[1, 2] * hz
            front = np.full(heights.shape, front_v)
        else:
            smp, lin, front = camera.project_with_mask(_node_positions(x, y, hz, scale, v, ux, uy, uz))
            if center_pixel is not None:
                smp = smp + (cs - cs0)
                lin = lin + (cl - cl0)
        node_ok = mvalid & front & np.isfinite(smp) & np.isfinite(lin) & front_v
        smp = np.where(node_ok, smp, np.nan)
        lin = np.where(node_ok, lin, np.nan)

    # sampling (BRT0), with sub-sample averaging when cells are larger than pixels
    if fused:
        pass  # sampled above
    elif m == 1:
        covered = node_ok & (smp >= 1.0) & (smp < npx) & (lin >= 1.0) & (lin < nln)  # NaN: False
        values = brt0(data, smp, lin, t_lo, t_hi, repair_floor=opts.repair_floor)
    else:
        off = (np.arange(m, dtype=np.float64) + 0.5) / m - 0.5  # cell offsets along x (UX) and y (UY)
        hx, hy, _ = sl

        def flat(a):
            return np.ascontiguousarray(np.broadcast_to(a, heights.shape), dtype=np.float64).reshape(-1)

        values = np.empty(n * n)
        cov_flat = np.empty(n * n, dtype=np.bool_)
        _subsample_kernel(
            data, flat(smp), flat(lin), np.ascontiguousarray(node_ok).reshape(-1),
            flat(j3[0, 0] + hx * j3[0, 2]), flat(j3[0, 1] + hy * j3[0, 2]),  # ∂sample/∂a, ∂sample/∂b
            flat(j3[1, 0] + hx * j3[1, 2]), flat(j3[1, 1] + hy * j3[1, 2]),  # ∂line/∂a, ∂line/∂b
            off, t_lo, t_hi, float(opts.repair_floor), values, cov_flat,
        )
        values = values.reshape(heights.shape)
        covered = cov_flat.reshape(heights.shape)
    if not fused:
        lit = node_ok & (values > 0.0)
        image = np.where(lit, values, 0.0)

    if opts.apply_filter and front_v:
        fr = extract_filter(image, heights, mvalid, ux, uy, uz, s_hat, e_hat, det_j, opts, slopes=sl)
        image, removed_shadow, removed_invisible, visible, shadowed, ds = (
            fr.image, fr.removed_shadow, fr.removed_invisible, fr.visible, fr.shadowed, fr.ds,
        )
    else:
        removed_shadow = np.zeros(heights.shape, dtype=bool)
        removed_invisible = np.zeros(heights.shape, dtype=bool)
        shadowed = np.zeros(heights.shape, dtype=bool)
        visible = mvalid.copy()
        ds = 0

    ill_mask = None
    if opts.ill_source == "predicted":
        if prediction is not None:
            ill_mask = np.asarray(prediction.lit, dtype=bool)
        else:
            hx, hy, usable = sl
            mu0 = surface_cosines(hx, hy, heightfield.to_maplet_components(s_hat, ux, uy, uz))
            mu = surface_cosines(hx, hy, heightfield.to_maplet_components(e_hat, ux, uy, uz))
            ill_mask = mvalid & usable & (mu0 > 0.0) & (mu > 0.0) & (mu0 + mu > 1e-12)
    st = statistics(e_hat, uz, covered, image, removed_invisible, det_j, ill_mask)

    if not front_v:
        status = "outside"
    elif opts.criteria is None:
        status = "ok"
    else:
        status = opts.criteria.status(st.emission_deg, st.cov, st.ill, st.res, st.inv)

    return Extraction(
        image=image,
        valid=image > 0.0,
        covered=covered,
        lit=lit,
        visible=visible,
        removed_shadow=removed_shadow,
        removed_invisible=removed_invisible,
        shadowed=shadowed,
        sample=smp,
        line=lin,
        center_sample=cs,
        center_line=cl,
        jxy=jxy,
        j3=j3,
        det_j=det_j,
        subsample=m,
        ds=ds,
        emission_deg=st.emission_deg,
        cov=st.cov,
        ill=st.ill,
        res=st.res,
        inv=st.inv,
        status=status,
        emission_vector=e_hat,
        sun_vector=s_hat,
        options=opts,
    )
