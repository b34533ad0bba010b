"""Stages F–G — ``correlate``: binning, the (2k+1)² NCC grid and the sub-pixel peak.

Specification: spc-algorithms.md §7 (Stage F) and §8 (Stage G), §13 (defaults); L15 §3.5–3.5.1;
S16 "Correlation and Peak Finding" (Eq. 18).

What it computes
----------------
Two images on the same grid (maplet space: the extracted photo E and the predicted image P, both
(2q+1)×(2q+1), NumPy axis 0 along UX, axis 1 along UY) or a template P placed over a larger search image
E (image space, :func:`correlate` with anchors).  With spacing n:

1. **Binning** (L15 Eq. 3.57 with erratum 24 — the inner sums run over the n cells (r_b−1)·n+1 … r_b·n,
   not to (r_b−1)·n): each image is averaged over n×n blocks, counting only valid pixels; a block with no
   valid pixel is invalid.  Both images are binned with **the same phase, anchored at the centre node**
   (spc-algorithms.md §7.3): for odd n the anchor is the centre of block 0; for even n block 0 covers
   anchor − n/2 … anchor + n/2 − 1 (a block of even width cannot be centred on a node; since E and P use
   the same phase, this shifts neither image relative to the other and so biases no offset).
2. **Grid** of whole-cell offsets (u, v) ∈ {−k…k}² in binned cells (k = ``grid_half``, default 5: 11×11),
   u along axis 0 (UX), v along axis 1 (UY).  **Sign convention** (spc-algorithms.md §7.3):

       C(u, v) = corr(E_b(m), P_b(m − (u, v)))

   so if E(m) = P(m − Δ) the peak is at Δ.  With a fixed bin phase this equals shifting the
   full-resolution prediction by n·(u, v) and then binning, as L15 describes.
3. **NCC** = Pearson's coefficient over the pixels valid in *both* binned images (L15 §3.5, S16 "near-zero
   threshold"):

       C = (N·Σpe − Σp·Σe) / √[(N·Σp² − (Σp)²)(N·Σe² − (Σe)²)]

   This departs from L15 Eq. 3.58, which has no square root (erratum 25; Eq. 3.59's σ normalisation
   and Eq. 3.60/3.61's sign are errata 26/27), and from S16 Eq. 18, whose numerator lacks the factor N
   (erratum 30).  Fewer than ``min_valid`` common pixels, or a constant image over the overlap, give NaN.
4. **Peak** (Stage G): (r₀, c₀) = argmax of the finite entries.  ``not-found`` if the surface has no
   finite value or its maximum is attained more than once (a flat surface); ``edge-peak`` if the peak
   lies on the border of the grid; ``not-found`` if a 4-neighbour (``strict_8``: any of the 8) is ≥ the
   peak or undefined — L15 footnote 43's "values decreasing around the peak";
   ``low-correlation`` if the peak is below ``corr_min``.
5. **Sub-pixel** (``peak``): by default (``"quadric"``) a least-squares quadric
   z = a + b·u + c·v + d·u² + e·u·v + f·v² fitted to the 3×3 neighbourhood of the peak (nine values,
   six unknowns; :func:`quadric_fit`), whose vertex is (δ_r, δ_c) = −H⁻¹·(b, c) with the Hessian
   H = [[2d, e], [e, 2f]].  The fit is rejected when H is not negative definite (not a maximum) or
   the vertex lies more than one cell from the grid peak; the peak, which passed the checks of item 4,
   then takes SPC's separable estimate below (``peak_fit = "parabola-fallback"``: it happens on peaks
   narrower than a bin, e.g. at coarse spacings, where the 3×3 quadric is a poor model).  The
   ``e·u·v`` term matters: correlation peaks of sun-shaded terrain are tilted ellipses (normalised
   cross term e/(2√(df)) ≈ 0.3–0.5), and a separable fit along the row and the column through the
   peak finds the *ridge* of the other axis, not the vertex: each axis estimate is pulled by −e/(2d)
   times the other axis's offset (for ρ = 0.5, about half of it; :func:`quadric_vertex`).  A quadratic
   surface is recovered exactly; a sampled Gaussian peak of width w keeps a "pixel-locking" bias that
   vanishes at zero and half-cell offsets (≤ 0.01 cell for w ≳ 6 cells at any offset, and for
   w ≳ 2 cells at offsets ≤ 0.1 cell, which the register loop reaches by re-extracting).
   ``peak="parabola"`` is SPC's: one parabola per axis through the peak and its two neighbours,

       δ = (y₊ − y₋) / (2·(2y₀ − y₊ − y₋))

   (L15 Eq. 3.65 has +2y₀ in the curvature: erratum 29 — with it the correction has the wrong sign;
   Eq. 3.64's d²x/dy² means (d²y/dx²)⁻¹, erratum 28).  For a strict local maximum |δ| ≤ ½.  Keep it
   for reproducing legacy runs.
   ``peak="gradient"`` reads no vertex: it aligns the two binned images at the grid peak by least
   squares (E ≈ a·P + b − a·δ·∇P, :func:`alignment.gradient_offset`; the quadric where that fit fails).  Any
   vertex of a sampled surface is biased where the surface is asymmetric about its maximum — and with
   masks and shading it is: a template identical to the photo still reads 0.03–0.05 px off with the
   quadric — while the alignment is exactly 0 there; the register loop's converged full-resolution
   stage uses it (``RegisterOptions.converge_peak``).  ``peak="gradient-photo"`` is the same
   alignment the other way round (P ≈ α·E + β + α·δ·∇E, :func:`alignment.gradient_offset_photo`): the
   regressors are the photo's, the prediction is the fitted side — for predictions noisier than the
   photo (maplets with per-node height errors), whose noise in the regressors biases the first form.
   ``peak="gradient-symmetric"`` chooses no side: the difference E − P' (P on E's scale) regressed on
   the mean of both images' gradients (:func:`alignment.gradient_offset_symmetric`), which halves a one-sided
   fit's attenuation by noise on either side; ``"gradient-weighted"`` mixes the two gradients by each
   image's estimated noise.  On the s16-50m Monte Carlo neither does what ``gradient-photo`` does for
   the per-landmark excess (docs/benchmarks.md): they are measured there, not adopted.
6. **Offset** in full-resolution cells: Δx (along UX) = n·((r₀ − k) + δ_r), Δy (along UY) =
   n·((c₀ − k) + δ_c).  The picture shift is δ = J_xy·Δ (Stage H, :mod:`spctool.stages.register`).

7. **Measurement covariance** (:func:`peak_covariance`): if E = S + noise and P matches S, the noise
   moves the surface gradient at the peak by ε with Cov(ε) = σ_n²·G/(N·σ_E·σ_S)² (G = Σ∇P∇Pᵀ) while
   the curvature is H = −G/(N·σ_E·σ_S), so the vertex −H⁻¹·ε has

       Cov(δ) = σ_n²·G⁻¹ = (1 − ρ²)/(ρ·N_eff) · (−H)⁻¹          (binned cells²; ρ = peak value)

   using σ_S/σ_E = ρ for the matched signal (everything that decorrelates the pair counts as noise,
   also model error).  N_eff = N / footprint: N binned pixels valid at the peak, footprint the number
   of binned cells per independent noise sample (1 for a photo correlated in its own pixels;
   :func:`resampled_noise_footprint` for a photo resampled bilinearly onto finer cells).  H is the
   least-squares quadric's Hessian whichever ``peak`` estimator gave the offset.  In full-resolution
   cells Cov(Δ) = n²·Cov(δ); Stage H maps it to pixels with J_xy.  Validated against the scatter of
   noise trials in tests/test_correlate.py.

Speed: the (2k+1)² masked Pearson sums run in one numba kernel (:func:`_k_ncc`): Σp·e is a dense
correlation with register tiling, and the masked sums (N, Σe, Σe², Σp, Σp²) come from row prefix sums
looked up at the ends of each run of valid pixels, so masks cost per run, not per pixel.  All sums are
float64 and agree with a brute-force Pearson to ≈ 1e-15; a 99×99 pair at spacing 1 takes ≈ 0.3 ms
(benchmarks/bench_register.py).  Images are centred on their valid mean before summing (Pearson is
invariant to that) to keep the one-pass sums well conditioned.  The rest of a call runs in small kernels
as well (the validity test, the binning, Stage G's grid checks, the alignment); at spacing 1 the images
go to them unbinned (no copy: no kernel reads an invalid pixel).  Wherever numba cannot prove an index
non-negative the kernels index with unsigned integers, which spares a wrap-around test per access
(twice as fast in the alignment and the binning).  None of this changes a result: every sum keeps its
operations and their order (tests/test_correlate.py compares the kernels bit for bit with NumPy).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np

from spctool.errors import SpcUsageError
from spctool.stages.alignment import _gradient_offset, _gradient_offset_photo, _gradient_offset_symmetric

__all__ = [
    "STATUSES",
    "CorrelateOptions",
    "Correlation",
    "bin_image",
    "correlate",
    "find_peak",
    "ncc_surface",
    "parabola_vertex",
    "PEAK_METHODS",
    "ALIGNMENTS",
    "peak_covariance",
    "quadric_fit",
    "quadric_vertex",
    "resampled_noise_footprint",
]

#: status words of a correlation (cli-contract.md "Landmark tables")
STATUSES = ("ok", "edge-peak", "not-found", "low-correlation")
#: sub-pixel peak estimators: 2-D least-squares quadric (default), SPC's separable parabolas, or the
#: least-squares image alignment at the grid peak (:func:`alignment.gradient_offset` and its variants)
PEAK_METHODS = (
    "quadric", "parabola", "gradient", "gradient-photo", "gradient-symmetric", "gradient-weighted",
)  # fmt: skip
#: the estimators that align the images at the grid peak (:func:`alignment.gradient_offset`,
#: :func:`alignment.gradient_offset_photo`, :func:`alignment.gradient_offset_symmetric` with w = ½
#: or w estimated)
ALIGNMENTS = ("gradient", "gradient-photo", "gradient-symmetric", "gradient-weighted")


@dataclass
class CorrelateOptions:
    """Settings of :func:`correlate` (defaults: spc-algorithms.md §13).

    * ``grid_half`` k — the grid is (2k+1)² offsets (5: L15/S16's 11×11).
    * ``min_valid`` — fewer binned pixels valid in both images gives C = NaN (25, [UNVERIFIED]).
    * ``min_value`` — a pixel is valid only if its value exceeds this (0.0: L15's "non-zero in both
      images", S16's near-zero threshold); ``None`` disables the value test (masks only).
    * ``corr_min`` — peaks below it are ``low-correlation`` (0.3: S16 and GIANT; 0.5 is AUTOREGISTER's
      removal cut, applied by the register driver).
    * ``strict_8`` — require all 8 neighbours (not only the 4 along the axes) below the peak.
    * ``bin_min_fraction`` — a bin is valid only if at least this fraction of its n² pixels is valid
      (0: any valid pixel, L15 Eq. 3.57; image space uses 1 so that a template's partial border bins,
      which average only the template's pixels, are not compared with full photo bins).
    * ``peak`` — sub-pixel estimator: ``"quadric"`` (2-D least squares on the 3×3 neighbourhood, with
      the cross term; default), ``"parabola"`` (SPC/L15: one parabola per axis, for legacy runs) or
      ``"gradient"`` (least-squares alignment of the two images at the grid peak,
      :func:`alignment.gradient_offset`; unbiased at zero offset, the register loop's converged stage uses it)
      or ``"gradient-photo"`` (the same with the photo's gradient as regressor:
      :func:`alignment.gradient_offset_photo`, for a prediction noisier than the photo), or
      ``"gradient-symmetric"`` / ``"gradient-weighted"`` (the difference on the mean of both images'
      gradients, or on their mix weighted by each image's estimated noise:
      :func:`alignment.gradient_offset_symmetric`).
    """

    grid_half: int = 5
    min_valid: int = 25
    min_value: float | None = 0.0
    corr_min: float = 0.3
    strict_8: bool = False
    bin_min_fraction: float = 0.0
    peak: str = "quadric"

    def __post_init__(self):
        if int(self.grid_half) != self.grid_half or self.grid_half < 1:
            raise SpcUsageError(f"grid_half must be an integer >= 1, got {self.grid_half!r}")
        self.grid_half = int(self.grid_half)
        if int(self.min_valid) != self.min_valid or self.min_valid < 2:
            raise SpcUsageError(f"min_valid must be an integer >= 2, got {self.min_valid!r}")
        self.min_valid = int(self.min_valid)
        if not (-1.0 <= float(self.corr_min) <= 1.0):
            raise SpcUsageError(f"corr_min must lie in [-1, 1], got {self.corr_min!r}")
        if not (0.0 <= float(self.bin_min_fraction) <= 1.0):
            raise SpcUsageError(f"bin_min_fraction must lie in [0, 1], got {self.bin_min_fraction!r}")
        if self.peak not in PEAK_METHODS:
            raise SpcUsageError(f"peak must be one of {', '.join(PEAK_METHODS)}, got {self.peak!r}")


@dataclass
class Correlation:
    """Result of :func:`correlate` for one image pair.

    ``offset`` is Δ = (Δx along UX / axis 0, Δy along UY / axis 1) in full-resolution cells (maplet space)
    or pixels of the search image (image space: (Δline, Δsample) order of the array axes).  It is NaN for
    ``not-found``; for ``edge-peak`` it is the whole-cell offset of the maximum (no sub-pixel part); for
    ``low-correlation`` it is the full estimate (informative only).
    """

    surface: np.ndarray  #: (2k+1, 2k+1) C(u, v), NaN where undefined
    counts: np.ndarray  #: (2k+1, 2k+1) binned pixels valid in both images
    spacing: int  #: n, cells per bin
    status: str  #: one of :data:`STATUSES`
    peak: float  #: surface maximum (NaN if none)
    peak_index: tuple[int, int] | None  #: (r₀, c₀) on the grid
    subpixel: tuple[float, float]  #: (δ_r, δ_c) in binned cells
    offset: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    #: (2, 2) Hessian of the least-squares quadric at the grid peak, per binned cell² (NaN if none)
    hessian: np.ndarray = field(default_factory=lambda: np.full((2, 2), np.nan))
    #: (2, 2) covariance of ``offset`` in full-resolution cells² (array axes; NaN if none)
    covariance: np.ndarray = field(default_factory=lambda: np.full((2, 2), np.nan))
    #: sub-pixel estimate used: "gradient", "gradient-photo", "quadric", "parabola" or
    #: "parabola-fallback" (quadric rejected); "" if none
    peak_fit: str = ""

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def grid_half(self) -> int:
        return (self.surface.shape[0] - 1) // 2


# --------------------------------------------------------------------------------------------------
# binning


def _block_range(size: int, anchor: int, n: int) -> tuple[int, int]:
    """First and last block index of a length-``size`` axis binned by n about ``anchor``."""
    h = n // 2
    return (0 - anchor + h) // n, (size - 1 - anchor + h) // n


@numba.njit(cache=True, nogil=True)
def _k_bin(v, m, n, s0, s1, need, out, ok):  # pragma: no cover - compiled
    """Block means of the valid pixels: pixel (i, j) belongs to block ((i − s0)//n, (j − s1)//n); a block
    is valid (``ok``) with at least one valid pixel and at least ``need`` of them.  ``out`` (zeros on
    entry) receives Σvalue/count of each valid block and stays 0 elsewhere.

    Each row is walked block by block (block b holds columns b·n + s1 … b·n + s1 + n − 1), so every
    block still sums its pixels in scan order, without a division per pixel; column indices are
    unsigned (np.uint64), which spares numba's negative-index test (see :func:`alignment._k_usable`)."""
    u = np.uint64
    cnts = np.zeros(out.shape)
    w = v.shape[1]
    for i_ in range(v.shape[0]):
        i = u(i_)
        bi = u((i_ - s0) // n)
        for b in range(u(out.shape[1])):
            lo = max(0, int(b) * n + s1)
            hi = min(w, int(b) * n + s1 + n)
            acc = out[bi, b]
            c = cnts[bi, b]
            for j in range(u(lo), u(hi)):
                if m[i, j]:
                    acc += v[i, j]
                    c += 1.0
            out[bi, b] = acc
            cnts[bi, b] = c
    for bi in range(out.shape[0]):
        for bj in range(out.shape[1]):
            c = cnts[bi, bj]
            good = (c > 0.0) & (c >= need)
            ok[bi, bj] = good
            out[bi, bj] = out[bi, bj] / c if good else 0.0


def bin_image(values, valid, n: int, anchor=None, min_fraction: float = 0.0):
    """Average ``values`` over n×n blocks of valid pixels (L15 Eq. 3.57, corrected bounds: erratum 24).

    Block (0, 0) is anchored at index ``anchor`` (default: the array centre ``(shape − 1)//2``): for odd n
    it is centred there; for even n it covers anchor − n/2 … anchor + n/2 − 1 along each axis.  Partial
    blocks at the borders average the valid pixels they hold; a block is valid when it holds at least
    one valid pixel and at least ``min_fraction``·n² of them.  Returns ``(binned, binned_valid,
    binned_anchor)`` where ``binned_anchor`` is the index of block (0, 0) in the binned arrays.  n = 1
    returns the values with invalid pixels set to 0.
    """
    v = np.asarray(values, dtype=np.float64)
    m = np.asarray(valid, dtype=bool)
    if v.ndim != 2 or m.shape != v.shape:
        raise SpcUsageError(f"bin_image needs 2-D values and a mask of one shape, got {v.shape}, {m.shape}")
    n = int(n)
    if n < 1:
        raise SpcUsageError(f"spacing must be >= 1, got {n}")
    if anchor is None:
        anchor = ((v.shape[0] - 1) // 2, (v.shape[1] - 1) // 2)
    a0, a1 = int(anchor[0]), int(anchor[1])
    if n == 1:
        return np.where(m, v, 0.0), m.copy(), (a0, a1)
    return _bin(np.ascontiguousarray(v), np.ascontiguousarray(m), n, a0, a1, min_fraction)


def _bin(v, m, n: int, a0: int, a1: int, min_fraction: float):
    """:func:`bin_image` for n ≥ 2 on a C-contiguous float64 image and bool mask (no checks)."""
    b0 = _block_range(v.shape[0], a0, n)
    b1 = _block_range(v.shape[1], a1, n)
    h = n // 2
    # input index of the first cell of the first block (≤ 0): block of pixel i = (i − s0)//n
    s0 = a0 - h + b0[0] * n
    s1 = a1 - h + b1[0] * n
    shape = (b0[1] - b0[0] + 1, b1[1] - b1[0] + 1)
    out = np.zeros(shape)
    ok = np.empty(shape, dtype=np.bool_)
    need = min_fraction * n * n - 1e-9
    _k_bin(v, m, n, s0, s1, need, out, ok)
    return out, ok, (-b0[0], -b1[0])


# --------------------------------------------------------------------------------------------------
# the NCC grid


_JIT = dict(cache=True, nogil=True)


@numba.njit(fastmath=True, **_JIT)
def _k_dense(ez, pz, g, out):  # pragma: no cover - compiled
    """out[a, b] += Σ_{i,j} pz[i, j]·ez[i + a, j + b] (ez is (Hp + g − 1, Wp + g − 1)).

    Four lags share each load of ``pz`` (register tiling); rows are contiguous so the loop vectorises.
    """
    hp, wp = pz.shape
    for a in range(g):
        for i in range(hp):
            pr = pz[i]
            er = ez[i + a]
            b = 0
            while b + 4 <= g:
                q0 = er[b : b + wp]
                q1 = er[b + 1 : b + 1 + wp]
                q2 = er[b + 2 : b + 2 + wp]
                q3 = er[b + 3 : b + 3 + wp]
                s0 = 0.0
                s1 = 0.0
                s2 = 0.0
                s3 = 0.0
                for j in range(wp):
                    p = pr[j]
                    s0 += p * q0[j]
                    s1 += p * q1[j]
                    s2 += p * q2[j]
                    s3 += p * q3[j]
                out[a, b] += s0
                out[a, b + 1] += s1
                out[a, b + 2] += s2
                out[a, b + 3] += s3
                b += 4
            while b < g:
                q0 = er[b : b + wp]
                s0 = 0.0
                for j in range(wp):
                    s0 += pr[j] * q0[j]
                out[a, b] += s0
                b += 1


@numba.njit(**_JIT)
def _k_runs(mask_row, lo, hi, out):  # pragma: no cover - compiled
    """Write the [start, stop) runs of True in mask_row[lo:hi] to out (k, 2); return k.  (0 ≤ lo:
    unsigned indices, see :func:`alignment._k_usable`.)"""
    one = np.uint64(1)
    end = np.uint64(hi)
    k = 0
    j = np.uint64(lo)
    while j < end:
        if mask_row[j]:
            s = j
            while j < end and mask_row[j]:
                j += one
            out[k, 0] = s
            out[k, 1] = j
            k += 1
        else:
            j += one
    return k


@numba.njit(**_JIT)
def _k_ncc(e, me, p, mp, o0, o1, half, min_valid, surf, cnts):  # pragma: no cover - compiled
    """C[a, b] (a = u + k, b = v + k) = Pearson over E[i, j] ↔ P[i − o0 − u, j − o1 − v], both valid.

    Work in P's frame: E' = E[i + o0 − k, j + o1 − k] is the (Hp + 2k)×(Wp + 2k) part of E that can
    pair with P at some offset, so pair (P[i, j], E'[i + a, j + b]).  The six Pearson sums split into

    * Σ p·e — a dense correlation (:func:`_k_dense`), values centred and zero where invalid;
    * N, Σe, Σe² (over P-valid pixels) and Σp, Σp² (over E-valid pixels) — masked box sums, taken from
      row prefix sums at the ends of each run of valid pixels (two look-ups per run and offset), so
      their cost depends on the number of runs, not on the number of pixels.

    All sums are float64; the result equals the brute-force Pearson to rounding (≈ 1e-15).  Indices
    that numba cannot prove non-negative are unsigned (see :func:`alignment._k_usable`); each prefix
    and box sum has its own array, so the look-ups of one offset row are contiguous loops that vectorise.
    """
    u = np.uint64
    one = u(1)
    he, we = e.shape
    hp, wp = p.shape
    g = 2 * half + 1
    h2 = hp + g - 1
    w2 = wp + g - 1
    # rows/columns of E' that are real E pixels
    r0 = max(0, half - o0)
    r1 = max(r0, min(h2, he + half - o0))
    c0 = max(0, half - o1)
    c1 = max(c0, min(w2, we + half - o1))
    nr = r1 - r0
    nc = c1 - c0
    er0 = u(r0 + o0 - half)  # E row and column of E' pixel (r0, c0), ≥ 0
    ec0 = u(c0 + o1 - half)
    # centring constants: Pearson is shift-invariant; centring keeps the one-pass sums well conditioned.
    # E's and P's sums are independent chains: one loop advances both, each in scan order
    ce = 0.0
    ne = 0
    cp = 0.0
    npv = 0
    for t_ in range(max(nr, hp)):
        t = u(t_)
        both = u(min(nc, wp) if (t_ < nr and t_ < hp) else 0)
        for j in range(both):
            if me[er0 + t, ec0 + j]:
                ce += e[er0 + t, ec0 + j]
                ne += 1
            if mp[t, j]:
                cp += p[t, j]
                npv += 1
        if t_ < nr:
            for j in range(both, u(nc)):
                if me[er0 + t, ec0 + j]:
                    ce += e[er0 + t, ec0 + j]
                    ne += 1
        if t_ < hp:
            for j in range(both, u(wp)):
                if mp[t, j]:
                    cp += p[t, j]
                    npv += 1
    ce = ce / ne if ne > 0 else 0.0
    cp = cp / npv if npv > 0 else 0.0
    # E': centred values and row prefixes of (valid, v, v²): en/es/es2[r, c] = Σ_{j<c} (0 outside E)
    ez = np.zeros((h2, w2))
    en = np.zeros((h2, w2 + 1))
    es = np.zeros((h2, w2 + 1))
    es2 = np.zeros((h2, w2 + 1))
    for r_ in range(r0, r1):
        r = u(r_)
        ei = er0 + u(r_ - r0)
        n_ = 0.0
        s_ = 0.0
        s2_ = 0.0
        for t in range(u(nc)):
            c = u(c0) + t
            if me[ei, ec0 + t]:
                v = e[ei, ec0 + t] - ce
                ez[r, c] = v
                n_ += 1.0
                s_ += v
                s2_ += v * v
            en[r, c + one] = n_
            es[r, c + one] = s_
            es2[r, c + one] = s2_
        for c in range(u(c1 + 1), u(w2 + 1)):
            en[r, c] = n_
            es[r, c] = s_
            es2[r, c] = s2_
    # P: centred values, row prefixes of (v, v²) for columns c = −pad … w2: pp/pp2[i, c + pad]
    pad = g - 1
    pz = np.zeros((hp, wp))
    wpp = w2 + pad + 1
    pp = np.zeros((hp, wpp))
    pp2 = np.zeros((hp, wpp))
    for i_ in range(hp):
        i = u(i_)
        s_ = 0.0
        s2_ = 0.0
        for j in range(u(wp)):
            if mp[i, j]:
                v = p[i, j] - cp
                pz[i, j] = v
                s_ += v
                s2_ += v * v
            pp[i, j + u(pad + 1)] = s_
            pp2[i, j + u(pad + 1)] = s2_
        for c in range(u(wp + pad + 1), u(wpp)):
            pp[i, c] = s_
            pp2[i, c] = s2_
    # the box sums N, Σe, Σe², Σp, Σp² per offset (a, b)
    an = np.zeros((g, g))
    ae = np.zeros((g, g))
    ae2 = np.zeros((g, g))
    ap = np.zeros((g, g))
    ap2 = np.zeros((g, g))
    runs = np.empty((max(w2, we) + 1, 2), np.int64)
    gu = u(g)
    for i in range(hp):  # runs of valid P pixels: sums of E' over them
        k = _k_runs(mp[i], 0, wp, runs)
        for q in range(k):
            s = u(runs[q, 0])
            t = u(runs[q, 1])
            for a in range(g):
                xn, xe, xe2 = an[a], ae[a], ae2[a]
                rn, rs, rs2 = en[i + a], es[i + a], es2[i + a]
                for b in range(gu):
                    xn[b] += rn[t + b] - rn[s + b]
                for b in range(gu):
                    xe[b] += rs[t + b] - rs[s + b]
                for b in range(gu):
                    xe2[b] += rs2[t + b] - rs2[s + b]
    # runs of valid E' pixels (found in E's mask): sums of P over them (P column = E' column − b)
    shift = c0 - int(ec0) + pad  # E column → E' column + pad
    for r in range(r0, r1):
        k = _k_runs(me[int(er0) + r - r0], int(ec0), int(ec0) + nc, runs)
        a_lo = max(0, r - hp + 1)
        a_hi = min(g, r + 1)
        for q in range(k):
            s = u(runs[q, 0] + shift)
            t = u(runs[q, 1] + shift)
            for a in range(a_lo, a_hi):
                xp, xp2 = ap[a], ap2[a]
                rs, rs2 = pp[r - a], pp2[r - a]
                for b in range(gu):
                    xp[b] += rs[t - b] - rs[s - b]
                for b in range(gu):
                    xp2[b] += rs2[t - b] - rs2[s - b]
    sep = np.zeros((g, g))
    _k_dense(ez, pz, g, sep)
    for a in range(g):
        for b in range(g):
            n = float(round(an[a, b]))
            se = ae[a, b]
            see = ae2[a, b]
            sp = ap[a, b]
            spp = ap2[a, b]
            cnts[a, b] = int(n)
            if n < min_valid:
                surf[a, b] = np.nan
                continue
            de = n * see - se * se
            dp = n * spp - sp * sp
            # a constant image over the overlap (zero variance up to rounding) has no correlation
            if de <= 1e-12 * n * see or dp <= 1e-12 * n * spp:
                surf[a, b] = np.nan
                continue
            c = (n * sep[a, b] - se * sp) / math.sqrt(de * dp)
            surf[a, b] = min(1.0, max(-1.0, c))


def ncc_surface(e, e_valid, p, p_valid, grid_half: int = 5, min_valid: int = 25, origin=(0, 0)):
    """Masked Pearson NCC on the (2k+1)² grid of whole-pixel offsets; returns ``(surface, counts)``.

    ``surface[u + k, v + k]`` correlates ``e[i, j]`` with ``p[i − origin[0] − u, j − origin[1] − v]`` over
    the pixels valid in both (``origin`` is the index in ``e`` of ``p``'s pixel (0, 0) at zero offset;
    (0, 0) for two images on the same grid).  NaN where fewer than ``min_valid`` pixels are common or an
    image is constant over the overlap.  No binning: see :func:`correlate`.
    """
    e = np.asarray(e, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    me = np.asarray(e_valid, dtype=bool)
    mp = np.asarray(p_valid, dtype=bool)
    if e.ndim != 2 or p.ndim != 2 or me.shape != e.shape or mp.shape != p.shape:
        raise SpcUsageError("ncc_surface needs 2-D images with masks of the same shapes")
    return _ncc(
        np.ascontiguousarray(e),
        np.ascontiguousarray(me),
        np.ascontiguousarray(p),
        np.ascontiguousarray(mp),
        int(grid_half),
        min_valid,
        (int(origin[0]), int(origin[1])),
    )


def _ncc(e, me, p, mp, half: int, min_valid, origin):
    """:func:`ncc_surface` on C-contiguous float64 images and bool masks (no checks)."""
    g = 2 * half + 1
    surf = np.empty((g, g))
    cnts = np.empty((g, g), dtype=np.int64)
    _k_ncc(e, me, p, mp, origin[0], origin[1], half, float(min_valid), surf, cnts)
    return surf, cnts


# --------------------------------------------------------------------------------------------------
# peak


def parabola_vertex(y_minus, y0, y_plus):
    """Vertex offset δ = (y₊ − y₋)/(2·(2y₀ − y₊ − y₋)) of the parabola through (−1, y₋), (0, y₀), (1, y₊).

    L15 Eq. 3.65 with erratum 29 (curvature y₊ + y₋ − 2y₀, not + 2y₀).  Vectorised; NaN where the
    curvature is zero.  Example: (0.5, 1.0, 0.8) → +0.2143 (the seed's formula gives −0.045).
    """
    ym = np.asarray(y_minus, dtype=np.float64)
    yz = np.asarray(y0, dtype=np.float64)
    yp = np.asarray(y_plus, dtype=np.float64)
    den = 2.0 * (2.0 * yz - yp - ym)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(den != 0.0, (yp - ym) / np.where(den != 0.0, den, 1.0), np.nan)
    return d if d.ndim else float(d)


def _vertex(ym: float, y0: float, yp: float) -> float:
    den = 2.0 * (2.0 * y0 - yp - ym)
    return (yp - ym) / den if den != 0.0 else math.nan


# the 3×3 neighbourhood: flat index 3·(u + 1) + (v + 1), u along axis 0, v along axis 1
_QU, _QV = (a.ravel().astype(np.float64) for a in np.meshgrid((-1, 0, 1), (-1, 0, 1), indexing="ij"))
#: design matrix of z = a + b·u + c·v + d·u² + e·u·v + f·v² on the nine nodes, and its pseudo-inverse
_QA = np.stack([np.ones(9), _QU, _QV, _QU * _QU, _QU * _QV, _QV * _QV], axis=1)
_QPINV = np.linalg.pinv(_QA)
_CROSS = np.array([1, 3, 4, 5, 7])  # centre and its four axis neighbours


def quadric_fit(z3) -> np.ndarray:
    """Least-squares quadric (a, b, c, d, e, f) of z = a + b·u + c·v + d·u² + e·u·v + f·v² on a 3×3
    neighbourhood (u = −1, 0, 1 along axis 0, v along axis 1).

    All nine values: the closed form ``_QPINV @ z``.  Undefined (NaN) diagonal values are left out of
    the fit; with no diagonal left the cross term is unknown and set to 0 (the fit is then SPC's two
    parabolas).  NaN coefficients if the centre or an axis neighbour is undefined.
    """
    z = np.asarray(z3, dtype=np.float64).reshape(9)
    ok = np.isfinite(z)
    if ok.all():
        return _QPINV @ z
    if not ok[_CROSS].all():
        return np.full(6, np.nan)
    # rank 6 with ≥ 1 diagonal; with none the e column is zero and lstsq's minimum norm gives e = 0
    coef, *_ = np.linalg.lstsq(_QA[ok], z[ok], rcond=None)
    return coef


def quadric_vertex(z3, max_move: float = 1.0):
    """Vertex of the least-squares quadric on a 3×3 neighbourhood: ``(δ_r, δ_c, H, ok)``.

    (δ_r, δ_c) = −H⁻¹·(b, c) with H = [[2d, e], [e, 2f]].  ``ok`` is False (and δ NaN) when H is not
    negative definite (the fit is no maximum) or the vertex lies more than ``max_move`` cells from the
    centre along either axis (outside the neighbourhood: an extrapolation).  H is returned in any case.

    Why the cross term: along the row u = 0 the quadric peaks at v = −(c + e·u)/(2f) evaluated at
    u = 0, i.e. at −c/(2f), while the vertex is at −c/(2f) − e·δ_r/(2f); a separable parabola is thus
    off by (e/2f)·δ_r along v (and by (e/2d)·δ_c along u).  For a peak with correlation ρ between the
    axes that is ρ·(σ_v/σ_u)·δ_r — half the other axis's offset at ρ = 0.5.
    """
    return _quadric_vertex(quadric_fit(z3).tolist(), max_move)


def _quadric_vertex(coef, max_move: float = 1.0):
    """:func:`quadric_vertex` from the fit's coefficients (a, b, c, d, e, f), as Python floats (the same
    IEEE operations as on NumPy scalars, without their overhead)."""
    _, b, c, d, e, f = coef
    h = np.array([[2.0 * d, e], [e, 2.0 * f]])
    det = 4.0 * d * f - e * e
    if not (d < 0.0 and det > 0.0):
        return math.nan, math.nan, h, False
    dr = -(2.0 * f * b - e * c) / det
    dc = -(2.0 * d * c - e * b) / det
    if not (abs(dr) <= max_move and abs(dc) <= max_move):
        return math.nan, math.nan, h, False
    return dr, dc, h, True


def resampled_noise_footprint(pixels_per_cell: float) -> float:
    """Cells per independent noise sample of a photo resampled bilinearly onto cells of
    ``pixels_per_cell`` pixels (linear; √|det J_xy| times the spacing n for binned maplet cells).

    Bilinear interpolation of white pixel noise, sampled every h pixels, has the autocorrelation sum
    Σₖ r(k·h) = 1.5/h per axis for h ≤ 1 (∫Λ² = 2/3 of the pixel variance at a node, ∫(Λ∗Λ) = 1);
    at h ≥ 1.5 neighbouring samples hardly share a pixel.  Returns max(1, 1.5/h)², the factor by which
    the number of valid cells overstates the independent samples (1 for a photo correlated in its
    own pixels: image space).
    """
    h = float(pixels_per_cell)
    if not (h > 0.0 and math.isfinite(h)):
        return math.nan
    return max(1.0, 1.5 / h) ** 2


def peak_covariance(hessian, rho: float, count: float, footprint: float = 1.0, times: int = 1) -> np.ndarray:
    """Covariance (2×2, binned cells²) of a correlation peak's vertex: (1 − ρ²)/(ρ·N_eff)·(−H)⁻¹.

    ``hessian`` H of the surface at the peak (per binned cell²; :func:`quadric_vertex`), ``rho`` the
    peak value, ``count`` N the binned pixels valid in both images there, ``footprint`` the binned
    cells per independent noise sample (N_eff = N/footprint).  Derivation in the module docstring
    (item 7).  NaN when H is not negative definite or ρ ∉ (0, 1].  ``times``: a factor applied to every
    element (``times · C``: n² for cells of spacing n, element by element as on the array).
    """
    h = np.asarray(hessian, dtype=np.float64)
    if h.shape != (2, 2):
        raise SpcUsageError(f"peak_covariance needs a 2×2 Hessian, got shape {h.shape}")
    (h00, h01), (h10, h11) = h.tolist()
    finite = math.isfinite(h00) and math.isfinite(h01) and math.isfinite(h10) and math.isfinite(h11)
    if not (finite and 0.0 < rho <= 1.0 and count > 0 and footprint > 0):
        return np.full((2, 2), np.nan)
    det = h00 * h11 - h01 * h10
    if not (h00 < 0.0 and det > 0.0):
        return np.full((2, 2), np.nan)
    # scale·(−H)⁻¹ and its symmetric part, element by element (the same operations as on the arrays)
    scale = (1.0 - rho * rho) / (rho * count / footprint)
    c00 = scale * (-h11 / det)
    c01 = scale * (h01 / det)
    c10 = scale * (h10 / det)
    c11 = scale * (-h00 / det)
    k = float(times)  # 1.0·x is x exactly: one expression for every factor
    return np.array(
        [
            [k * (0.5 * (c00 + c00)), k * (0.5 * (c01 + c10))],
            [k * (0.5 * (c10 + c01)), k * (0.5 * (c11 + c11))],
        ]
    )


@numba.njit(cache=True, nogil=True)
def _k_grid_peak(s, strict_8):  # pragma: no cover - compiled
    """Stage G's checks on the grid (:func:`_find_peak`): ``(code, r0, c0, all9)``.

    (r0, c0) is the first maximum of the finite entries in scan order (NumPy's argmax of the surface
    with −inf for the undefined ones); ``code`` 1: no finite entry, 2: the maximum is attained more
    than once, 3: it lies on the border, 4: a neighbour (the four along the axes, with ``strict_8`` all
    eight) is undefined or not below it, 0: a strict interior maximum; ``all9``: its 3×3 neighbourhood
    is finite."""
    g0, g1 = s.shape
    r0 = -1
    c0 = -1
    pk = -np.inf
    for i in range(g0):
        for j in range(g1):
            v = s[i, j]
            if math.isfinite(v) and (r0 < 0 or v > pk):
                pk = v
                r0 = i
                c0 = j
    if r0 < 0:
        return 1, 0, 0, False
    ties = 0
    for i in range(g0):
        for j in range(g1):
            ties += s[i, j] == pk
    if ties > 1:
        return 2, r0, c0, False
    if r0 == 0 or c0 == 0 or r0 == g0 - 1 or c0 == g1 - 1:
        return 3, r0, c0, False
    below = s[r0 - 1, c0] < pk and s[r0 + 1, c0] < pk and s[r0, c0 - 1] < pk and s[r0, c0 + 1] < pk
    if strict_8:
        below = (
            below
            and s[r0 - 1, c0 - 1] < pk
            and s[r0 - 1, c0 + 1] < pk
            and s[r0 + 1, c0 - 1] < pk
            and s[r0 + 1, c0 + 1] < pk
        )
    if not below:
        return 4, r0, c0, False
    all9 = True
    for i in range(r0 - 1, r0 + 2):
        for j in range(c0 - 1, c0 + 2):
            all9 = all9 and math.isfinite(s[i, j])
    return 0, r0, c0, all9


def _find_peak(s, corr_min, strict_8, peak, grid_peak=None):
    """find_peak plus the Hessian at the grid peak (NaN when there is no 3×3 neighbourhood) and the
    estimate used ("quadric", "parabola", "parabola-fallback" or "").  The Hessian is the quadric's,
    or, when the quadric is rejected, the separable one diag(y₊ + y₋ − 2y₀) of the two parabolas.
    ``s``: a C-contiguous float64 surface (the checks run in :func:`_k_grid_peak`, or ``grid_peak`` is
    its result already)."""
    code, r0, c0, all9 = _k_grid_peak(s, bool(strict_8)) if grid_peak is None else grid_peak
    if code == 1:
        return "not-found", math.nan, None, (math.nan, math.nan), np.full((2, 2), np.nan), ""
    pk = float(s[r0, c0])
    if code == 2:  # a flat surface or a tied maximum: no clearly defined peak
        return "not-found", pk, (r0, c0), (math.nan, math.nan), np.full((2, 2), np.nan), ""
    if code == 3:
        return "edge-peak", pk, (r0, c0), (0.0, 0.0), np.full((2, 2), np.nan), ""
    if code == 4:  # undefined (NaN) or non-decreasing neighbours: no clearly defined peak (L15 footnote 43)
        return "not-found", pk, (r0, c0), (math.nan, math.nan), np.full((2, 2), np.nan), ""
    z3 = s[r0 - 1 : r0 + 2, c0 - 1 : c0 + 2]
    # all nine values defined (the usual case): quadric_fit's closed form, without its checks
    coef = _QPINV @ z3.reshape(9) if all9 else quadric_fit(z3)
    qr, qc, h, q_ok = _quadric_vertex(coef.tolist())
    status = "ok" if pk >= corr_min else "low-correlation"
    if peak != "parabola" and q_ok:  # "gradient" refines it in correlate()
        return status, pk, (r0, c0), (qr, qc), h, "quadric"
    # SPC's two parabolas (|δ| ≤ ½ for the strict maximum checked above)
    up, down = float(s[r0 - 1, c0]), float(s[r0 + 1, c0])
    left, right = float(s[r0, c0 - 1]), float(s[r0, c0 + 1])
    dr = _vertex(up, pk, down)
    dc = _vertex(left, pk, right)
    if not q_ok:  # the quadric is no maximum: the curvature of the two parabolas
        h = np.diag([up + down - 2.0 * pk, left + right - 2.0 * pk])
    return status, pk, (r0, c0), (dr, dc), h, "parabola" if peak == "parabola" else "parabola-fallback"


def find_peak(surface, corr_min: float = 0.3, strict_8: bool = False, peak: str = "quadric"):
    """Stage G on one surface: ``(status, peak, (r₀, c₀) or None, (δ_r, δ_c))`` (spc-algorithms.md §8.3).

    ``peak``: ``"quadric"`` (default; :func:`quadric_vertex`; where that fit is rejected, the parabolas)
    or ``"parabola"`` (SPC's two 1-D parabolas, :func:`parabola_vertex`).
    """
    if peak not in PEAK_METHODS:
        raise SpcUsageError(f"peak must be one of {', '.join(PEAK_METHODS)}, got {peak!r}")
    s = np.ascontiguousarray(surface, dtype=np.float64)
    if s.ndim != 2:
        raise SpcUsageError(f"find_peak needs a 2-D surface, got shape {s.shape}")
    return _find_peak(s, corr_min, strict_8, peak)[:4]


# --------------------------------------------------------------------------------------------------
# the stage


@numba.njit(cache=True, nogil=True)
def _k_valid(v, vm, use_min, min_value, out):  # pragma: no cover - compiled
    """out = vm & finite(v) (& v > min_value when ``use_min``), in one pass (bitwise: no branches)."""
    for i in range(v.shape[0]):
        for j in range(v.shape[1]):
            x = v[i, j]
            out[i, j] = vm[i, j] & math.isfinite(x) & ((not use_min) | (x > min_value))


def _valid_mask(values, valid, min_value):
    """C-contiguous float64 values and their validity: finite, inside ``valid`` (if given) and above
    ``min_value`` (if not None)."""
    v = np.ascontiguousarray(values, dtype=np.float64)
    if valid is None:
        m = np.isfinite(v)
        if min_value is not None:
            with np.errstate(invalid="ignore"):
                m &= v > float(min_value)
        return v, m
    vm = np.ascontiguousarray(valid, dtype=np.bool_)
    if vm.shape != v.shape:
        raise SpcUsageError(f"mask shape {vm.shape} differs from image shape {v.shape}")
    if v.ndim != 2:
        raise SpcUsageError("correlate needs 2-D images")
    m = np.empty(v.shape, dtype=np.bool_)
    use_min = min_value is not None
    _k_valid(v, vm, use_min, float(min_value) if use_min else 0.0, m)
    return v, m


def correlate(
    extracted,
    predicted,
    *,
    extracted_valid=None,
    predicted_valid=None,
    spacing: int = 1,
    options: CorrelateOptions | None = None,
    extracted_anchor=None,
    predicted_anchor=None,
    noise_footprint: float = 1.0,
) -> Correlation:
    """Correlate a prediction with an extracted (or search) image; spc-algorithms.md §7–§8.

    ``extracted`` E and ``predicted`` P are 2-D arrays with optional validity masks (pixels must also be
    finite and exceed ``options.min_value``).  Maplet space: E and P share a grid and the anchors default
    to the centre node.  Image space: E is a larger search window and P a template; ``extracted_anchor``
    is the index in E where P's ``predicted_anchor`` sits at zero offset.  Both are binned by ``spacing``
    n with blocks anchored there (same phase), then C(u, v) = corr(E_b(m), P_b(m − (u, v))) on the
    (2k+1)² grid; the result's ``offset`` is in full-resolution cells: n·((r₀ − k) + δ_r, (c₀ − k) + δ_c).
    ``noise_footprint``: binned cells per independent noise sample, for the ``covariance`` of the offset
    (module docstring item 7; 1 for a photo correlated in its own pixels).
    """
    opts = options or CorrelateOptions()
    n = int(spacing)
    if n < 1 or n != spacing:
        raise SpcUsageError(f"spacing must be an integer >= 1, got {spacing!r}")
    e, me = _valid_mask(extracted, extracted_valid, opts.min_value)
    p, mp = _valid_mask(predicted, predicted_valid, opts.min_value)
    if e.ndim != 2 or p.ndim != 2:
        raise SpcUsageError("correlate needs 2-D images")
    if extracted_anchor is None and predicted_anchor is None and e.shape != p.shape:
        raise SpcUsageError(f"images differ in shape ({e.shape} vs {p.shape}); give the anchors")
    ea = ((e.shape[0] - 1) // 2, (e.shape[1] - 1) // 2) if extracted_anchor is None else extracted_anchor
    pa = ((p.shape[0] - 1) // 2, (p.shape[1] - 1) // 2) if predicted_anchor is None else predicted_anchor
    return correlate_valid(e, me, p, mp, n, opts, ea, pa, noise_footprint)


@numba.njit(**_JIT)
def _k_binned(v, m, n, a0, a1, need):  # pragma: no cover - compiled
    """:func:`_bin` of values ``v`` with validity ``m`` (n = 1: both as they are, as correlate_valid
    passes them): ``(binned, binned valid, binned anchor row, column)``."""
    if n == 1:
        return v, m, a0, a1
    h = n // 2
    b00 = (0 - a0 + h) // n
    b01 = (v.shape[0] - 1 - a0 + h) // n
    b10 = (0 - a1 + h) // n
    b11 = (v.shape[1] - 1 - a1 + h) // n
    out = np.zeros((b01 - b00 + 1, b11 - b10 + 1))
    ok = np.empty(out.shape, dtype=np.bool_)
    _k_bin(v, m, n, a0 - h + b00 * n, a1 - h + b10 * n, need, out, ok)
    return out, ok, -b00, -b10


@numba.njit(**_JIT)
def _k_front(e, ve, p, vp, use_min, min_value, n, ea0, ea1, pa0, pa1, need, half, min_valid, strict_8):
    """:func:`correlate`'s work up to the grid peak in one call without the GIL (maplet space, issue
    39): both validity masks (:func:`_k_valid`), both binnings (:func:`_k_bin`, as :func:`_bin`), the
    NCC surface (:func:`_k_ncc`) and the grid peak's checks (:func:`_k_grid_peak`) — the same kernels,
    called in the same order.  Returns (E_b, E_b valid, P_b, P_b valid, origin row, column, surface,
    counts, (code, r0, c0, all9))."""
    me = np.empty(e.shape, dtype=np.bool_)
    _k_valid(e, ve, use_min, min_value, me)
    mp = np.empty(p.shape, dtype=np.bool_)
    _k_valid(p, vp, use_min, min_value, mp)
    eb, meb, eab0, eab1 = _k_binned(e, me, n, ea0, ea1, need)
    pb, mpb, pab0, pab1 = _k_binned(p, mp, n, pa0, pa1, need)
    o0 = eab0 - pab0
    o1 = eab1 - pab1
    g = 2 * half + 1
    surf = np.empty((g, g))
    cnts = np.empty((g, g), dtype=np.int64)
    _k_ncc(eb, meb, pb, mpb, o0, o1, half, min_valid, surf, cnts)
    return eb, meb, pb, mpb, o0, o1, surf, cnts, _k_grid_peak(surf, strict_8)


def correlate_maplet(e, ve, p, vp, n: int, opts: CorrelateOptions, ea, pa, noise_footprint: float = 1.0):
    """:func:`correlate` of a maplet-space step (registrar's ``_maplet_step``): C-contiguous float64
    images of two dimensions with bool masks of their shapes (an extraction's image and ``valid``, a
    prediction's image and ``lit``), both anchors given — the same result to the bit, with the masks,
    binning, surface and grid peak in one GIL-free kernel (:func:`_k_front`) so that threads registering
    other landmarks run meanwhile."""
    use_min = opts.min_value is not None
    need = opts.bin_min_fraction * n * n - 1e-9
    f, b = np.float64, np.bool_
    e, ve = np.ascontiguousarray(e, dtype=f), np.ascontiguousarray(ve, dtype=b)
    p, vp = np.ascontiguousarray(p, dtype=f), np.ascontiguousarray(vp, dtype=b)
    eb, meb, pb, mpb, o0, o1, surf, cnts, grid_peak = _k_front(
        e, ve, p, vp, use_min, float(opts.min_value) if use_min else 0.0, int(n), int(ea[0]), int(ea[1]),
        int(pa[0]), int(pa[1]), need, int(opts.grid_half), float(opts.min_valid), bool(opts.strict_8),
    )  # fmt: skip
    return _from_surface(eb, meb, pb, mpb, n, opts, (o0, o1), surf, cnts, noise_footprint, grid_peak)


def correlate_valid(e, me, p, mp, n: int, opts: CorrelateOptions, ea, pa, noise_footprint: float = 1.0):
    """:func:`correlate` of images whose masks are already their valid pixels: C-contiguous float64 E and
    P, bool masks ``me``, ``mp`` true only where the pixel is finite (and above ``opts.min_value`` when
    that is set), spacing ``n`` ≥ 1 and both anchors given (no checks: image space's steps, whose
    photo window and template kernels make such masks)."""
    if n == 1:
        # bin_image would copy the images with their invalid pixels set to 0; no kernel reads those
        eb, meb, eab = e, me, (int(ea[0]), int(ea[1]))
        pb, mpb, pab = p, mp, (int(pa[0]), int(pa[1]))
    else:
        eb, meb, eab = _bin(e, me, n, int(ea[0]), int(ea[1]), opts.bin_min_fraction)
        pb, mpb, pab = _bin(p, mp, n, int(pa[0]), int(pa[1]), opts.bin_min_fraction)
    origin = (eab[0] - pab[0], eab[1] - pab[1])
    surf, cnts = _ncc(eb, meb, pb, mpb, opts.grid_half, opts.min_valid, origin)
    return _from_surface(eb, meb, pb, mpb, n, opts, origin, surf, cnts, noise_footprint)


def _from_surface(eb, meb, pb, mpb, n, opts, origin, surf, cnts, noise_footprint, grid_peak=None):
    """The rest of :func:`correlate_valid` from the binned images and their NCC surface: the peak, the
    alignment at it (``opts.peak``), the offset and its covariance."""
    k = opts.grid_half
    found = _find_peak(surf, opts.corr_min, opts.strict_8, opts.peak, grid_peak)
    status, peak, idx, (dr, dc), hess, fit = found
    if opts.peak in ALIGNMENTS and status in ("ok", "low-correlation"):
        o0, o1 = origin[0] + idx[0] - k, origin[1] + idx[1] - k
        if opts.peak == "gradient":
            g_r, g_c, g_ok = _gradient_offset(eb, meb, pb, mpb, o0, o1)
        elif opts.peak == "gradient-photo":
            g_r, g_c, g_ok = _gradient_offset_photo(eb, meb, pb, mpb, o0, o1)
        else:
            w = 0.5 if opts.peak == "gradient-symmetric" else None
            g_r, g_c, _, g_ok = _gradient_offset_symmetric(eb, meb, pb, mpb, o0, o1, w)
        if g_ok:
            dr, dc, fit = g_r, g_c, opts.peak
    if idx is None or status == "not-found":
        return Correlation(surf, cnts, n, status, peak, idx, (dr, dc), np.full(2, np.nan), hess, peak_fit=fit)
    off = np.array([n * ((idx[0] - k) + dr), n * ((idx[1] - k) + dc)])
    if status == "edge-peak":
        return Correlation(surf, cnts, n, status, peak, idx, (dr, dc), off, hess, peak_fit=fit)
    cov = peak_covariance(hess, peak, float(cnts[idx]), float(noise_footprint), n * n)
    return Correlation(surf, cnts, n, status, peak, idx, (dr, dc), off, hess, cov, fit)
