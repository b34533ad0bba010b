"""One correlation step of one landmark, in maplet or image space (its options:
:mod:`spctool.stages.register_options`).

Specification: spc-algorithms.md §9 (Stage H), §7.3/§8.3 (the shift and its sign), §13 (defaults);
L15 §3.5.2 (Eq. 3.67); S16 "Template matching loop" (Eq. 11, 18–19) and "Future Retina development".
The drivers that run these steps over a schedule are :mod:`spctool.stages.register`.

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
estimate and template reuse cannot freeze it.  A re-render within :data:`_HINT_REACH` px of the last
one's phase starts each sub-ray at the terrain cell its predecessor hit (``render(..., cells=)``: the
same template to the last bit, about 20 % less time).  Templates take one thread each
(the rays of a pixel window, the distortion inverted on a coarse grid and interpolated bicubically,
one Newton step where that is not exact to 1e-7 px:
:meth:`spctool.geometry.camera.Camera.pixel_to_direction_lattice`);
:func:`spctool.stages.register.register` parallelises across landmarks instead (``threads``), with
results identical to one thread.  ``template_shading``:
``smooth`` (interpolated node slopes), ``facet`` (flat triangles, two per cell; albedo bilinear) or
``gouraud`` (the radiance shaded at the nodes, interpolated).
With ``image_shadows`` (default) the template's shadowed pixels are *used*, dark — the point of
ray-traced shadows; photo pixels then count when 0 < DN ≤ T2 (T1 is not applied; DN 0 is SPC's
missing data), template pixels where every sub-ray hit the maplet.  With ``photo_shadows="auto"``
(default) the photo's own shadows and their edges are then left out of a landmark's full-resolution
steps when its template shows them (:mod:`spctool.stages.image_shadows`: the maplet's smoothed heights
cannot place their edges).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import weakref
from dataclasses import dataclass

import numba
import numpy as np

from spctool.errors import SpcUsageError
from spctool.geometry import heightfield
from spctool.geometry.frames import unit_vector
from spctool.stages.correlate import (
    Correlation,
    correlate_maplet,
    correlate_valid,
    resampled_noise_footprint,
)
from spctool.stages.extract import (
    ZENITH_EPS,
    Extraction,
    _k_recentred,
    extract,
    shadow_extension,
    shadow_offsets,
)
from spctool.stages.image_shadows import dark_floor, dark_pixels
from spctool.stages.predict import predict, resolve_shadows
from spctool.stages.register_options import RegisterOptions

__all__ = ["LandmarkStep", "Registrar", "correlate_landmark"]

_NO_OFFSETS = np.zeros((0, 2), dtype=np.int64)  # the shadow enhancement's offsets when it does not run


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


def _check_search(options, shape, landmarks) -> None:
    """SpcUsageError for a search no photo can hold, before any array is made for it: a grid of more
    than ±(the photo's larger side) bins (``grid_half``: the correlation surface alone would be
    (2K + 1)² values), or a maplet extended beyond its edge (``acquire_reach``) past the largest
    half-size any stage accepts (:data:`spctool.formats.guard.MAX_QSZ`)."""
    from spctool.formats.guard import MAX_QSZ

    side = max(int(s) for s in shape)
    if int(options.grid_half) > side:
        raise SpcUsageError(
            f"a correlation grid of +-{options.grid_half} bins (--grid-half) is larger than the photo "
            f"({shape[1]} x {shape[0]} px): at most {side}"
        )
    reach = int(getattr(options, "acquire_reach", 0) or 0)
    q = max((int(lm.maplet.heights.shape[0] - 1) // 2 for lm in landmarks), default=0)
    if reach and q + reach > MAX_QSZ:
        raise SpcUsageError(
            f"an acquisition {reach} cells beyond the maplet's edge (--acquire-reach) would extend a maplet "
            f"of half-size {q} past {MAX_QSZ} cells, the largest any stage accepts: at most "
            f"{max(0, MAX_QSZ - q)}"
        )


@dataclass(frozen=True)
class _PaddedMaplet:
    """A maplet's frame with its grid extended beyond its edge (``acquire_reach``): heights continued
    from the edge, the outside nodes valid."""

    heights: np.ndarray
    valid: np.ndarray
    scale: float
    v: np.ndarray
    ux: np.ndarray
    uy: np.ndarray
    uz: np.ndarray

    @classmethod
    def around(cls, maplet, margin: int) -> _PaddedMaplet:
        valid = np.asarray(maplet.valid, dtype=bool)
        h = np.where(valid, np.asarray(maplet.heights, dtype=np.float64), 0.0)
        return cls(
            np.pad(h, margin, mode="edge"), np.pad(valid, margin, constant_values=True), float(maplet.scale),
            maplet.v, maplet.ux, maplet.uy, maplet.uz,
        )  # fmt: skip


class _Grid:
    """The grid a landmark's photo is resampled onto, with the extraction reused at other centres:
    the maplet's own (margin 0) or the maplet extended by ``margin`` cells per side."""

    __slots__ = ("maplet", "_slopes", "margin", "ext", "camera", "shadow")

    def __init__(self, maplet, slopes, margin: int = 0):
        """``slopes``: the grid's :func:`heightfield.slopes`, or a function giving them on first use."""
        self.maplet, self._slopes, self.margin = maplet, slopes, int(margin)
        self.ext = self.camera = self.shadow = None

    @property
    def slopes(self):
        if callable(self._slopes):
            self._slopes = self._slopes()
        return self._slopes


class _KeptPatch:
    """A maplet's entry in :attr:`Registrar.patch_cache`: the maplet itself (the key is its id), its
    render-ready patch, and its last template window as (camera, window, template_margin) or None."""

    __slots__ = ("maplet", "patch", "window")

    def __init__(self, maplet, patch):
        self.maplet = maplet
        self.patch = patch
        self.window = None


class _Landmark:
    """Per-landmark state reused across steps: slopes (maplet space and predictions; computed on first
    use, which an image-space template never makes), prediction (per camera), template cache."""

    __slots__ = (
        "maplet",
        "name",
        "_slopes",
        "v",
        "pred",
        "pred_camera",
        "patch",
        "tmpl",
        "tmpl_key",
        "hits",
        "footprint",
        "grid",
        "padded",
        "shadow_mode",
        "cast",
        "dark_floor",
        "proj",
        "popts",
        "hbin",
        "__weakref__",
    )

    def __init__(self, maplet, name):
        self.maplet = maplet
        self.name = name
        self._slopes = None
        self.v = np.asarray(maplet.v, dtype=np.float64)
        self.pred = None
        self.pred_camera = None
        self.shadow_mode = None  # predict's shadows="auto", resolved on the first extraction
        self.cast = None  # the maplet's cast-shadow cells for the Registrar's Sun
        self.dark_floor = None  # image space, photo_shadows: DN left out (0: none), at the first L = 1 step
        self.patch = None
        self.tmpl = None
        self.tmpl_key = None
        self.hits = None  # (camera, frac, supersample, render window, Rendering) of the last render
        self.footprint = None
        self.grid = _Grid(maplet, self._lazy_slopes())  # the maplet's own grid
        self.padded = None  # the grid extended for acquire_reach
        self.proj = None  # (camera, V's pixel with it): image space projects V once per camera object
        self.popts = None  # (predict options, resolved shadow mode, the options with it)
        self.hbin = None  # (J_xy, √|det J_xy|): photo pixels per cell, once per extraction geometry

    def _lazy_slopes(self):
        """A function giving :attr:`slopes` on first use that holds this landmark weakly: a closure over
        the landmark itself would make landmark → grid → function → landmark a reference cycle, which
        keeps each landmark's arrays (~0.2 MB in the S16 pass) until the garbage collector runs."""
        ref = weakref.ref(self)
        return lambda: ref().slopes

    @property
    def slopes(self):
        """:func:`heightfield.slopes` of the maplet (hx, hy, usable)."""
        if self._slopes is None:
            self._slopes = heightfield.slopes(self.maplet.heights, self.maplet.valid)
        return self._slopes


@functools.lru_cache(maxsize=16)
def _border_nodes(q: int) -> np.ndarray:
    """(4·(2q + 1), 2) maplet-frame (x, y) of a maplet's border nodes, side by side: x = −q … q at
    y = −q, then at y = q, then y = −q … q at x = −q and at x = q (read-only: shared per q)."""
    t = np.arange(-q, q + 1, dtype=np.float64)
    edge = np.concatenate(
        [
            np.stack([t, np.full_like(t, -q)], 1),
            np.stack([t, np.full_like(t, q)], 1),
            np.stack([np.full_like(t, -q), t], 1),
            np.stack([np.full_like(t, q), t], 1),
        ]
    )
    edge.flags.writeable = False
    return edge


class Registrar:
    """Correlation steps for the landmarks of one photo (shared by
    :func:`spctool.stages.register.register` and the CLI).

    ``photo``: array ``data[line − 1, sample − 1]`` or a Photo; ``camera``: the picture's camera;
    ``sun``: body→Sun vector; ``maplets``: objects with heights, albedo, valid, scale, v, ux, uy, uz;
    ``thresholds``: (T1, T2).
    """

    def __init__(
        self,
        photo,
        sun,
        maplets,
        thresholds=None,
        options: RegisterOptions | None = None,
        names=None,
        patch_cache: dict | None = None,
    ):
        self.options = options if options is not None else RegisterOptions()
        #: image space: each maplet's render-ready patch (packed maps, slope bounds, Sun tables) and its
        #: last template window, kept in this dict under id(maplet) as a :class:`_KeptPatch`, so that
        #: Registrars of later passes over the same maplets (not modified in between) build none again
        #: (navigate, the Monte Carlo's phases; the Sun tables are kept per Sun direction, the window per
        #: camera object); under ("template", name) each landmark's last template with V's pixel, whose
        #: hit positions place the rays of the first template of a later call (the Monte Carlo's next
        #: phase and next sample, navigate's next pass: :meth:`_carried_hint`; a hint only, so a name
        #: shared by two maplets costs marches, never a different template); None: per Registrar
        self.patch_cache = patch_cache
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
        _check_search(self.options, self.photo.shape, self.landmarks)
        # the settings derived from the options, made once per options object: per Registrar, or, with a
        # patch_cache, once for every call with the same options (the Monte Carlo's phases and samples)
        key = ("options", id(self.options))
        made = None if patch_cache is None else patch_cache.get(key)
        if made is None or made[0] is not self.options:
            copts = self.options.correlate_options
            made = (
                self.options,
                copts,
                #: the converged stage's correlation settings (its sub-pixel estimator)
                dataclasses.replace(copts, peak=self.options.converge_peak),
                {},  # id(copts) → (copts, its image-space form): made once, not per step
                #: (final, grid_half) → the step's correlation settings with that search: one object per
                #: search width, so that the image-space forms stay one per setting, not one per step
                {},
                {},  # rays per pixel → the templates' RenderOptions (the same for every render)
            )
            if patch_cache is not None:
                patch_cache[key] = made
        _, self._copts, self._copts_final, self._image_copts, self._copts_half, self._ropts = made

    def __len__(self):
        return len(self.landmarks)

    # -- geometry ------------------------------------------------------------------------------
    def release(self, i: int) -> None:
        """Drop landmark ``i``'s cached prediction, extraction and template (memory)."""
        lm = self.landmarks[i]
        lm.pred = lm.pred_camera = lm.tmpl = lm.tmpl_key = lm.hits = lm.footprint = lm.padded = lm.proj = None
        lm.grid = _Grid(lm.maplet, lm._lazy_slopes())

    def project(self, camera) -> tuple[np.ndarray, np.ndarray]:
        """(pixels (N, 2), usable (N,)): projection of every V; usable = in front and inside the photo."""
        if not self.landmarks:
            return np.zeros((0, 2)), np.zeros(0, bool)
        v = np.array([lm.v for lm in self.landmarks], dtype=np.float64)
        s, ln, front = camera.project_with_mask(v)
        nln, npx = self.photo.shape
        inside = front & (s >= 1.0) & (s <= npx) & (ln >= 1.0) & (ln <= nln)
        pixels = np.empty((s.shape[0], 2))
        pixels[:, 0] = s
        pixels[:, 1] = ln
        for lm, px in zip(self.landmarks, pixels):  # V's pixel with this camera (image space places by it)
            lm.proj = (camera, px.copy())
        return pixels, inside

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
            mode = lm.shadow_mode or "spc"
            if lm.popts is None or lm.popts[0] is not popts or lm.popts[1] != mode:
                lm.popts = (popts, mode, dataclasses.replace(popts, shadows=mode))  # once, not every step
            popts = lm.popts[2]
        if lm.pred is None or lm.pred_camera is not camera:
            lm.pred = predict(
                lm.maplet, camera.position, self.sun, popts, slopes=lm.slopes, cast_shadows=lm.cast
            )
            lm.pred_camera = camera
        return lm.pred

    def dark_floor_landmarks(self) -> dict:
        """Image space: name → the DN at or below which ``photo_shadows="auto"`` left the photo out."""
        return {lm.name: lm.dark_floor for lm in self.landmarks if lm.dark_floor}

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
        margin: int = 0,
        grid_half: int | None = None,
    ) -> LandmarkStep:
        """Correlate landmark ``i`` with V placed at pixel ``center`` (sample, line), spacing n
        (``final``: a step of the converged stage, with ``converge_peak``'s estimator; ``draft``: image
        space, its template rendered at ``supersample_coarse``; ``margin``: maplet space, the extraction
        extended by this many cells per side, and ``grid_half`` the search, ``acquire_reach``)."""
        copts = self._copts_final if final else self._copts
        if grid_half is not None and grid_half != copts.grid_half:
            key = (bool(final), int(grid_half))
            made = self._copts_half.get(key)
            if made is None:
                made = self._copts_half[key] = dataclasses.replace(copts, grid_half=int(grid_half))
            copts = made
        if self.options.space == "image":
            return self._image_step(i, camera, np.asarray(center, dtype=np.float64), spacing, copts, draft)
        return self._maplet_step(
            i, camera, np.asarray(center, dtype=np.float64), spacing, apply_criteria, copts, int(margin)
        )

    def _maplet_step(self, i, camera, center, spacing, apply_criteria, copts, margin=0):
        lm = self.landmarks[i]
        ext = self.extraction(i, camera, center, apply_criteria)
        pred = self.prediction(i, camera, ext)
        q0, q1 = (pred.image.shape[0] - 1) // 2, (pred.image.shape[1] - 1) // 2
        anchors = ((q0, q1), (q0, q1))  # correlate's default: the centre node of the shared grid
        if margin > 0 and ext.status == "ok":
            # the search image: the same resampling on the grid extended by ``margin`` cells
            q = q0
            anchors = ((q + margin, q + margin), (q, q))
            ext = self.extraction(i, camera, center, margin=margin)
        # photo pixels per binned cell: the bilinear resampling shares noise between finer cells
        if ext.jxy is None:
            h_bin = 1.0
        else:
            if lm.hbin is None or lm.hbin[0] is not ext.jxy:  # re-centred extractions share their J_xy
                lm.hbin = (ext.jxy, math.sqrt(abs(float(np.linalg.det(ext.jxy)))))
            h_bin = spacing * lm.hbin[1]
        corr = correlate_maplet(  # correlate(), its masks, binning, surface and grid peak in one kernel
            ext.image,
            ext.valid,
            pred.image,
            pred.lit,
            spacing,
            copts,
            *anchors,
            noise_footprint=resampled_noise_footprint(h_bin) if h_bin > 0 else 1.0,
        )
        status = corr.status if ext.status == "ok" else ext.status
        shift = ext.jxy @ corr.offset
        del lm
        return LandmarkStep(center, shift, corr, ext.jxy, status, extraction=ext)

    def extraction(self, i: int, camera, center, apply_criteria: bool = False, margin: int = 0):
        """The photo resampled onto landmark ``i`` with V at pixel ``center`` (Stage C–E); ``margin`` > 0:
        onto the maplet's grid extended by that many cells per side (``acquire_reach``: heights continued
        from the maplet's edge, no removal criteria; node (q + margin, q + margin) is V).

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
        if (margin > 0 or not apply_criteria) and eopts.criteria is not None:
            eopts = dataclasses.replace(eopts, criteria=None)
        if margin > 0:
            if lm.padded is None or lm.padded.margin != margin:
                grid = _PaddedMaplet.around(lm.maplet, margin)
                lm.padded = _Grid(grid, heightfield.slopes(grid.heights, grid.valid), margin)
            grid = lm.padded
        else:
            grid = lm.grid
        base = grid.ext
        if (
            base is None
            or grid.camera is not camera
            or base.subsample != 1
            or eopts.cast_shadow_trace
            or base.status == "outside"
            or eopts.criteria is not None
        ):
            ext = extract(
                self.photo,
                grid.maplet,
                camera,
                self.sun,
                self.thresholds,
                eopts,
                center_pixel=center,
                slopes=grid.slopes,
            )
            grid.ext, grid.camera, grid.shadow = ext, camera, None
            return ext
        ds, dl = float(center[0]) - base.center_sample, float(center[1]) - base.center_line
        # re-sampled, enhanced and filtered in one GIL-free kernel (the extract filter's step 1 with
        # its own offsets and kernel, computed once per landmark and camera; steps 2–3 from the first
        # extraction's mask)
        if eopts.apply_filter and grid.shadow is None:
            grid.shadow = self._shadow_offsets(grid.maplet, base)
        enhance = bool(eopts.apply_filter) and grid.shadow is not False
        checks, zeros = grid.shadow if enhance else (_NO_OFFSETS, _NO_OFFSETS)
        shape = base.sample.shape
        smp, lin, image = np.empty(shape), np.empty(shape), np.empty(shape)
        valid, covered, lit, removed_shadow = (np.empty(shape, dtype=bool) for _ in range(4))
        _k_recentred(
            self.photo, base.sample, base.line, ds, dl, self.thresholds[0], self.thresholds[1],
            float(eopts.repair_floor), enhance, checks, zeros, bool(eopts.apply_filter), base.visible,
            smp, lin, image, valid, covered, lit, removed_shadow,
        )  # fmt: skip
        ext = object.__new__(Extraction)  # dataclasses.replace without its per-field keyword pass
        ext.__dict__.update(base.__dict__)
        ext.__dict__.update(
            image=image,
            valid=valid,
            covered=covered,
            lit=lit,
            removed_shadow=removed_shadow,
            sample=smp,
            line=lin,
            center_sample=float(center[0]),
            center_line=float(center[1]),
            status="ok",  # criteria were not requested (else the full path ran); "outside" never gets here
        )
        return ext

    def _shadow_offsets(self, m, base):
        """(checks, zeros) of the shadow enhancement for grid ``m`` and this camera, or False when the Sun
        is at the maplet zenith — exactly as :func:`spctool.stages.extract.extract_filter` computes them."""
        eopts = self.options.extract
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
        from spctool.geometry.surfaces import HeightPatch, PatchSet
        from spctool.stages.render import Rendering, RenderOptions, render

        mg = int(self.options.template_margin)
        if lm.patch is None:
            kept = self._kept(lm.maplet)
            if kept is not None and kept.patch.patches[0].node_slopes != self.options.template_slopes:
                kept = None  # another phase's slopes: a patch of this one's own
            if kept is not None:
                lm.patch = kept.patch
                if lm.footprint is None and kept.window is not None and kept.window[2] == mg:
                    lm.footprint = kept.window[:2]
            else:
                # packed once per landmark, reused by every render
                slopes = self.options.template_slopes
                lm.patch = PatchSet([HeightPatch.from_maplet(lm.maplet, name=lm.name, node_slopes=slopes)])
                if self.patch_cache is not None:
                    self.patch_cache[id(lm.maplet)] = _KeptPatch(lm.maplet, lm.patch)
        patch = lm.patch.patches[0]
        tol = self.options.rerender_tol if spacing <= 1 else self.options.rerender_tol_coarse * spacing
        # coarse steps bin n pixels: their template needs fewer rays per pixel (supersample_coarse)
        nss = int(self.options.supersample if spacing <= 1 and not draft else self.options.supersample_coarse)
        if (
            lm.tmpl is not None
            and lm.tmpl_key[0] is camera
            and _phase_moved(lm.tmpl_key[1], frac) <= tol
            and lm.tmpl.options.supersample >= nss
        ):
            return lm.tmpl, lm.tmpl_key[1], lm.tmpl_key[2]
        if lm.footprint is None or lm.footprint[0] is not camera:
            lm.footprint = (camera, self._footprint(patch, camera))
            kept = self._kept(lm.maplet)
            if kept is not None:
                kept.window = (*lm.footprint, mg)
        if lm.footprint[1] is None:
            return None, frac, None
        s0, s1, l0, l1 = lm.footprint[1]
        # rays through p − frac: the same camera with its CTR moved by frac
        shifted = camera.with_ctr(camera.ctr + frac)
        ropts = self._ropts.get(nss)
        if ropts is None:
            ropts = self._ropts[nss] = RenderOptions(
                photometry=self.options.predict.photometry,
                supersample=nss,
                shadows=bool(self.options.image_shadows),
                shading=self.options.template_shading,
                visibility=self.options.template_visibility if nss >= 2 else "march",
                ray_inverse="grid",
                threads=1,
            )
        shp = (l1 - l0 + 1, s1 - s0 + 1)
        cs0, cl0 = max(s0, 1), max(l0, 1)  # render() windows are 1-based; pixels left of/above 1 stay sky
        part = None
        if cs0 <= s1 and cl0 <= l1:
            win = (cs0, s1, cl0, l1)
            n = patch.heights.shape[0]
            hint = _cells_hint(lm.hits, camera, frac, nss, win, n)
            if hint is None:
                hint = self._carried_hint(lm, camera, frac, nss, win, n)
            part = render(shifted, self.sun, None, lm.patch, ropts, window=win, cells=hint, return_cells=True)
            lm.hits = (camera, frac.copy(), nss, win, part)
            if self.patch_cache is not None and lm.proj is not None and lm.proj[0] is camera:
                # the last render, and the last at this supersampling (a later call's first template
                # under another camera is hinted only by one with its own rays: _carried_hint)
                self.patch_cache[("template", lm.name)] = self.patch_cache[("template", lm.name, nss)] = (
                    lm.proj[1],
                    lm.hits,
                )
        if part is not None and (cs0, cl0) == (s0, l0):
            rend = part  # the whole window in the photo: the render is the template
        else:  # sky (radiance and coverage 0) left of / above the photo
            rad, cov = np.zeros(shp), np.zeros(shp)
            if part is not None:
                rad[cl0 - l0 :, cs0 - s0 :] = part.radiance
                cov[cl0 - l0 :, cs0 - s0 :] = part.coverage
            shd = np.zeros(shp)
            if part is not None:
                shd[cl0 - l0 :, cs0 - s0 :] = part.shadow
            rend = Rendering(rad, cov, shd, np.zeros(shp, np.int16), (s0, s1, l0, l1), ropts)
        lm.tmpl, lm.tmpl_key = rend, (camera, frac.copy(), (s0, s1, l0, l1))
        return rend, frac.copy(), (s0, s1, l0, l1)

    def _carried_hint(self, lm: _Landmark, camera, frac, nss: int, window, n: int):
        """The cells a first template of ``lm`` is expected to hit, from the last template of a landmark
        of the same name kept in :attr:`patch_cache` by an earlier call, or None.  With the same camera
        object (the Monte Carlo's second phase): :func:`_cells_hint`'s rules.  With another (its
        knowledge perturbed: the Monte Carlo's previous sample; navigate's next pass): the same terrain
        appears at the same offset from V's pixel, so this template's pixel p (phase ``frac``) sits
        where the earlier one's p − P + P' − f + f' sat (P, P': V's pixels, f, f': the phases, windows
        apart by their origins); the maplet frame moves with V, so the hit positions carry over (a
        hint: a miss costs a march, never a different template)."""
        if self.patch_cache is None or lm.proj is None or lm.proj[0] is not camera:
            return None
        carried = self.patch_cache.get(("template", lm.name))
        if carried is None:
            return None
        v_old, hits = carried
        cam_old, f_old, k, win_old, prev = hits
        if cam_old is camera:
            return _cells_hint(hits, camera, frac, nss, window, n)
        if k != nss:  # another camera: the last template with this one's rays (the image plan's coarse
            # phase renders one ray per pixel, its fine phase ends on 2 × 2)
            carried = self.patch_cache.get(("template", lm.name, nss))
            if carried is None:
                return None
            v_old, hits = carried
            cam_old, f_old, k, win_old, prev = hits
            if cam_old is camera:
                return None
        from spctool.stages.render import predicted_cells

        v_new = lm.proj[1]
        shift = (
            window[0] - win_old[0] + v_old[0] - v_new[0] + f_old[0] - frac[0],
            window[2] - win_old[2] + v_old[1] - v_new[1] + f_old[1] - frac[1],
        )
        shape = ((window[3] - window[2] + 1) * nss, (window[1] - window[0] + 1) * nss)
        return predicted_cells(prev, shift, n, shape)

    def _kept(self, maplet) -> _KeptPatch | None:
        """This maplet's entry in :attr:`patch_cache` (None: no cache, or none for this very object)."""
        kept = None if self.patch_cache is None else self.patch_cache.get(id(maplet))
        return kept if kept is not None and kept.maplet is maplet else None

    def _footprint(self, patch, camera):
        """The template window (s0, s1, l0, l1): the projection of the maplet's border nodes, plus
        ``template_margin``; None when a border node is behind the camera."""
        q = patch.qsz
        edge = _border_nodes(q)
        hts = patch.heights  # the border nodes' own heights (the bilinear surface there, exactly)
        local = np.empty((edge.shape[0], 3))
        local[:, :2] = edge
        m = 2 * q + 1
        local[:m, 2] = hts[:, 0]
        local[m : 2 * m, 2] = hts[:, -1]
        local[2 * m : 3 * m, 2] = hts[0, :]
        local[3 * m :, 2] = hts[-1, :]
        s, ln, front = camera.project_with_mask(patch.to_body(local))
        if not np.all(front):
            return None
        mg = int(self.options.template_margin)
        s0, s1 = int(math.floor(s.min())) - mg, int(math.ceil(s.max())) + mg
        l0, l1 = int(math.floor(ln.min())) - mg, int(math.ceil(ln.max())) + mg
        return s0, s1, l0, l1

    def _image_step(self, i, camera, center, spacing, copts, draft=False):
        lm = self.landmarks[i]
        if lm.proj is None or lm.proj[0] is not camera:
            lm.proj = (camera, np.asarray(camera.project(lm.v[None, :]), dtype=np.float64).reshape(2))
        c0 = lm.proj[1]
        # the placement's arithmetic on Python floats: the same IEEE operations as on the 2-vectors
        (c0s, c0l), (cs, cl) = c0.tolist(), center.tolist()
        disp_s, disp_l = cs - c0s, cl - c0l
        frac = np.array([disp_s - _rint(disp_s), disp_l - _rint(disp_l)])
        rend, f_t, window = self._template(lm, camera, frac, spacing, draft)
        g = 2 * copts.grid_half + 1
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
        fs, fl = f_t.tolist()
        pi_s, pi_l = _rint(disp_s - fs), _rint(disp_l - fl)  # the integer placement
        di_s, di_l = int(pi_s), int(pi_l)
        s0, s1, l0, l1 = window
        tmpl = rend.radiance
        tvalid = np.empty(tmpl.shape, dtype=np.bool_)
        _k_template_valid(rend.coverage, tmpl, 1.0 - 1e-12, not self.options.image_shadows, tvalid)
        # photo crop: the template window moved by the integer placement, plus the search margin; DN 0 =
        # no data (SPC), and the crop beyond the photo is 0, so "> 0" also keeps it out
        marg = (copts.grid_half + 1) * int(spacing)
        cl_lo, cl_hi = l0 + di_l - marg, l1 + di_l + marg
        cs_lo, cs_hi = s0 + di_s - marg, s1 + di_s + marg
        crop = np.empty((cl_hi - cl_lo + 1, cs_hi - cs_lo + 1))
        cvalid = np.empty(crop.shape, dtype=np.bool_)
        t1, t2 = self.thresholds
        use_t1 = not self.options.image_shadows
        _k_photo_window(self.photo, cl_lo - 1, cs_lo - 1, t1, t2, use_t1, crop, cvalid)
        if lm.dark_floor is None and not use_t1 and int(spacing) == 1:
            # photo_shadows="auto": read once, at the first full-resolution step (image_shadows module)
            lm.dark_floor = 0.0
            if self.options.photo_shadows == "auto":
                h, w = tmpl.shape
                under = (slice(marg, marg + h), slice(marg, marg + w))  # the photo under the template
                lm.dark_floor = dark_floor(tmpl, tvalid, crop[under], cvalid[under])
        if lm.dark_floor:  # the photo's shadows and their edges out of this landmark's correlation
            cvalid &= ~dark_pixels(crop, lm.dark_floor)
        # anchors: the template pixel nearest to V's rendered position, and where it sits in the crop
        a_s = min(max(round(c0s + fs), s0), s1)
        a_l = min(max(round(c0l + fl), l0), l1)
        p_anchor = (a_l - l0, a_s - s0)
        e_anchor = (a_l + di_l - cl_lo, a_s + di_s - cs_lo)
        made = self._image_copts.get(id(copts))
        if made is None or made[0] is not copts:
            frac_min = self.options.image_bin_fraction
            made = (copts, dataclasses.replace(copts, min_value=None, bin_min_fraction=frac_min))
            self._image_copts[id(copts)] = made
        # the masks are the valid pixels already (finite; image space sets no min_value)
        corr = correlate_valid(crop, cvalid, tmpl, tvalid, int(spacing), made[1], e_anchor, p_anchor)
        (o_l, o_s) = corr.offset.tolist()
        shift = np.array([o_s, o_l])  # (line, sample) axes → (dsample, dline)
        # the step's reference is where the template actually sat: c0 + the integer placement + f_t
        return LandmarkStep(
            np.array([c0s + (pi_s + fs), c0l + (pi_l + fl)]), shift, corr, None, corr.status, template=rend
        )


def _phase_moved(a, b) -> float:
    """max |a − b| over the two axes of two phases (2-vectors), as Python floats: the value of
    ``np.max(np.abs(a − b))`` (NaN where either difference is NaN) without its NumPy calls."""
    (a0, a1), (b0, b1) = a.tolist(), b.tolist()
    d0, d1 = abs(a0 - b0), abs(a1 - b1)
    if d0 != d0 or d1 != d1:
        return math.nan
    return d0 if d0 >= d1 else d1


def _rint(x: float) -> float:
    """``np.rint`` of one Python float (half to even, the sign of a zero kept, non-finite unchanged)."""
    if not math.isfinite(x):
        return x
    r = float(round(x))
    return r if r != 0.0 else math.copysign(0.0, x)


@numba.njit(cache=True, nogil=True)
def _k_template_valid(coverage, radiance, full, positive, out):  # pragma: no cover - compiled
    """An image-space template's valid pixels: fully covered (coverage ≥ ``full``), of finite radiance and,
    with ``positive`` (no image shadows), of positive radiance."""
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            x = radiance[i, j]
            out[i, j] = (coverage[i, j] >= full) & math.isfinite(x) & ((not positive) | (x > 0.0))


@numba.njit(cache=True, nogil=True)
def _k_photo_window(photo, i0, j0, t1, t2, use_t1, crop, valid):  # pragma: no cover - compiled
    """crop[i, j] = photo[i0 + i, j0 + j] (0-based; 0 outside the photo) and its validity: positive
    (DN 0 = no data), finite, ≤ ``t2`` and, with ``use_t1``, ≥ ``t1`` — in one pass."""
    nl, ns = photo.shape
    for i in range(crop.shape[0]):
        r = i0 + i
        for j in range(crop.shape[1]):
            c = j0 + j
            x = photo[r, c] if (r >= 0) & (r < nl) & (c >= 0) & (c < ns) else 0.0
            crop[i, j] = x
            valid[i, j] = (x > 0.0) & (x <= t2) & math.isfinite(x) & ((not use_t1) | (x >= t1))


#: a template re-rendered at a finer supersampling within this many pixels (per axis) of the phase of
#: the landmark's last one-ray render starts each sub-ray's search in the cell its predecessor hit
#: (:func:`spctool.stages.render.render`'s ``cells``; the same template to the last bit): most rays hit
#: the same cell there, where at 0.45 px the misses cost more than the hits save
_HINT_REACH = 0.25


def _cells_hint(hits, camera, frac, nss: int, window, n: int):
    """The cells a template at phase ``frac`` is expected to hit, from the landmark's last render (same
    camera object and window), or None: at the same supersampling its hit positions moved by the
    change of phase (:func:`spctool.stages.render.predicted_cells`: any phase; on the s16-50m maplets
    a re-render costs 0.4 ms where a march costs 0.7); from a one-ray render at a finer supersampling,
    its hit positions read at the finer sub-rays (any phase), or, where it kept none, its cells
    repeated over the sub-rays of each pixel when the phase is within :data:`_HINT_REACH`.  ``n``: the
    patch's nodes per side."""
    if hits is None:
        return None
    cam, f, k, win, prev = hits
    if prev.cells is None or cam is not camera or win != window:
        return None
    if k == nss:
        from spctool.stages.render import predicted_cells

        return predicted_cells(prev, f - frac, n)
    if k == 1 and prev.positions is not None:
        # a one-ray render's hit positions read at the finer sub-rays (any phase): on the s16-50m Monte
        # Carlo's 2 × 2 templates after a one-ray draft, 27 % of the repeated cells below miss (a march
        # each) and the template costs 13 % more than with its own cells
        from spctool.stages.render import predicted_cells

        shape = (prev.cells.shape[0] * nss, prev.cells.shape[1] * nss)
        return predicted_cells(prev, f - frac, n, shape, supersample=nss)
    if k == 1 and np.max(np.abs(f - frac)) <= _HINT_REACH:
        return np.repeat(np.repeat(prev.cells, nss, axis=0), nss, axis=1)
    return None


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
