"""The shading model's error in a picture's landmark measurements, from its sensitivity (issue #39).

Why.  A landmark's registration covariance (the correlation peak's, :mod:`spctool.stages.correlate`
item 7) holds the photo's noise only.  The template's own error — the photometric law (spc-algorithms.md
§6, S16's lunar-Lambert), the template's shading — moves each measured pixel too, and it moves all the
landmarks of one picture in a related way: a law that brightens the slopes facing the Sun too much
shifts every landmark along the Sun's azimuth, by an amount that varies smoothly with the terrain and
the geometry.  The pose absorbs the shared part of such a pattern (a common shift is a pointing change),
so the pose residuals cannot reveal it and a covariance that treats the landmarks as independent is
too small (the independent worlds of :mod:`spctool.sim.independent`: a picture's common error of
0.002–0.01 px against 0.001–0.003 px of formal attitude σ; pose NEES 12–19 instead of 6, issue #39).

What the data can show is how far the measurements move when the model is changed to another one as
plausible.  Each landmark is registered once more from its measured pixel, at spacing 1 (the converged
stage, :func:`spctool.stages.register.register`), with the alternative photometric law — SPC's
lunar-Lambert ↔ Lambert (:data:`ALTERNATIVE_LAW`) —, with the maplets' heights smoothed once more (a
maplet is itself smoothed from finer data, S16; one more step of it shows how far that moves each
landmark: on the demo, whose maplets are smoothed from a 3× finer truth, this pattern takes the pose
NEES of the first picture from 22.7 to 3.5) and, in image space, the alternative template
shading (smooth ↔ facet) and the template without its cast shadows (a low Sun's shadows, cast by the
maplet's heights rather than the body's, shift every landmark along the Sun: 0.03 px of common error
at 70° incidence on the independent worlds).  The shifts δᵢ⁽ᵏ⁾ of the landmarks form one error
pattern per alternative k; each enters the measurement covariance of the pose solve as one mode with a
unit-variance coefficient,

    R = blkdiag(Cᵢ + τ²I) + U·τ²I·Uᵀ + Σₖ δ⁽ᵏ⁾ δ⁽ᵏ⁾ᵀ            (:mod:`spctool.stages._pose_problem`)

(τ the model error the pose residuals show beyond the patterns, U·τ²I·Uᵀ its part common to the
landmarks: :class:`spctool.stages.pose.PoseOptions` ``common_model_error``) — the model is taken to be
wrong by about as much as two plausible models differ, in the pattern their difference takes (its
common part along the Sun included).  Nothing is tuned to a scene: size and shape
are the picture's own.  Each landmark's marginal covariance is Cᵢ + τ²I + Σₖ δᵢ⁽ᵏ⁾δᵢ⁽ᵏ⁾ᵀ
(:meth:`Sensitivity.landmark_covariances`).  A landmark the alternative does not register (or moves by
more than ``max_shift_px``: it found other terrain) gets no shift in that pattern and is named.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "ALTERNATIVE_LAW",
    "SMOOTHED",
    "Sensitivity",
    "alternative_models",
    "shading_sensitivity",
    "smoothed_heights",
]

#: the photometric law each law is compared with (:data:`spctool.photometry` laws; Lambert ↔ SPC's)
ALTERNATIVE_LAW = {"spc": "lambert", "mcewen": "lambert", "fixed": "lambert", "lambert": "spc"}
#: image space: the template shading compared with (gouraud with facet, as smooth is: the model-error
#: term was calibrated on the smooth ↔ facet difference; gouraud and smooth differ far less, by the
#: concavity of the law between nodes)
ALTERNATIVE_SHADING = {"smooth": "facet", "facet": "smooth", "gouraud": "facet"}
#: the pattern of the maplets' heights smoothed once more (:func:`smoothed_heights`)
SMOOTHED = "heights smoothed"


@dataclass
class Sensitivity:
    """The shifts of a picture's landmark measurements under the alternative models (module docstring)."""

    labels: list[str]  # one per pattern, e.g. "photometry lambert", "template-shading facet"
    shifts: np.ndarray  # (N, 2, k) px: alternative − measured (0 where not available)
    available: np.ndarray  # (N, k) bool: the alternative registered the landmark within max_shift_px
    warnings: list[str] = field(default_factory=list)

    @property
    def modes(self) -> np.ndarray:
        """(N, 2, k) error modes for :func:`spctool.stages.pose.solve_pose` ``error_modes``."""
        return self.shifts

    def landmark_covariances(self, covariances) -> np.ndarray:
        """(N, 2, 2) each landmark's covariance plus its part of the patterns, Σₖ δᵢ⁽ᵏ⁾δᵢ⁽ᵏ⁾ᵀ."""
        return np.asarray(covariances, dtype=np.float64) + np.einsum("nik,njk->nij", self.shifts, self.shifts)

    def common(self) -> np.ndarray:
        """(2, k) each pattern's mean shift over the landmarks that have one (px)."""
        n = np.maximum(self.available.sum(axis=0), 1)
        return self.shifts.sum(axis=0) / n

    def as_dict(self) -> dict:
        rms = np.sqrt(np.mean(np.sum(self.shifts**2, axis=1), axis=0)) if self.shifts.size else []
        return {
            "patterns": list(self.labels),
            "rms_shift_px": [float(x) for x in rms],
            "common_shift_px": self.common().T.tolist(),
            "landmarks": [int(x) for x in self.available.sum(axis=0)],
        }


def alternative_models(options) -> list[tuple[str, object]]:
    """[(label, RegisterOptions)] of the alternative models for ``options`` (module docstring): the
    other photometric law; the maplets' heights smoothed once more (:data:`SMOOTHED`, same options);
    in image space also the other template shading and (when the templates have them) no cast
    shadows."""
    law = options.predict.photometry
    alt = ALTERNATIVE_LAW.get(law, "lambert")
    predict = dataclasses.replace(options.predict, photometry=alt)
    out = [(f"photometry {alt}", dataclasses.replace(options, predict=predict)), (SMOOTHED, options)]
    if options.space == "image":
        shading = ALTERNATIVE_SHADING[options.template_shading]
        out.append((f"template-shading {shading}", dataclasses.replace(options, template_shading=shading)))
        if options.image_shadows:  # the template's cast shadows (the maplet's heights, not the body's)
            out.append(("no cast shadows", dataclasses.replace(options, image_shadows=False)))
    return out


def smoothed_heights(maplet):
    """A copy of ``maplet`` whose heights are smoothed once more: the binomial kernel [1, 2, 1]/4 along
    each axis over its valid nodes (the valid nodes only; edges repeat)."""
    import copy

    h = np.asarray(maplet.heights, dtype=np.float64)
    valid = np.asarray(maplet.valid, dtype=bool)
    _ = maplet.albedo  # decoded before the copy: the copy shares it

    def blur(a):
        p = np.pad(a, 1, mode="edge")
        a = 0.25 * p[:-2, 1:-1] + 0.5 * p[1:-1, 1:-1] + 0.25 * p[2:, 1:-1]
        p = np.pad(a, 1, mode="edge")
        return 0.25 * p[1:-1, :-2] + 0.5 * p[1:-1, 1:-1] + 0.25 * p[1:-1, 2:]

    weight = blur(valid.astype(np.float64))
    out = copy.copy(maplet)
    out.heights = np.where(valid, blur(np.where(valid, h, 0.0)) / np.maximum(weight, 1e-12), 0.0)
    return out


def shading_sensitivity(
    photo,
    camera,
    sun,
    maplets,
    thresholds,
    options,
    measured,
    ok,
    *,
    names=None,
    positions=None,
    converge_jacobian=None,
    patch_cache=None,
    max_shift_px: float = 1.0,
    only=None,
) -> Sensitivity:
    """Register every landmark ``ok`` once more from ``measured`` (N, 2) with each alternative model of
    ``options`` (a :class:`spctool.stages.register.RegisterOptions` of the S16 driver, as navigate's)
    at spacing 1, and return the shifts (module docstring).  ``positions``, ``converge_jacobian`` (N, …)
    and ``patch_cache`` go to :func:`spctool.stages.register.register`; ``only``: the labels of the
    alternatives to run (None: all of :func:`alternative_models`)."""
    from spctool.stages.register import register

    meas = np.asarray(measured, dtype=np.float64)
    ok = np.asarray(ok, dtype=bool) & np.all(np.isfinite(meas), axis=1)
    n = meas.shape[0]
    models = [(lab, o) for lab, o in alternative_models(options) if only is None or lab in only]
    shifts = np.zeros((n, 2, len(models)))
    avail = np.zeros((n, len(models)), dtype=bool)
    warnings: list[str] = []
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return Sensitivity([lab for lab, _ in models], shifts, avail, warnings)
    if names is None:
        names = [getattr(m, "name", "") or f"#{i + 1}" for i, m in enumerate(maplets)]
    sub_names = [str(names[i]) for i in idx]
    kw = {"patch_cache": patch_cache}
    if positions is not None:
        kw["positions"] = np.asarray(positions, dtype=np.float64)[idx]
    if converge_jacobian is not None:
        kw["converge_jacobian"] = np.asarray(converge_jacobian, dtype=np.float64)[idx]
    for k, (label, opts) in enumerate(models):
        step = dataclasses.replace(opts, steps=(("align", 1),))
        sub = [maplets[i] for i in idx]
        kw_k = kw
        if label == SMOOTHED:  # new maplet objects: never in the shared patch cache (keyed by object)
            sub, kw_k = [smoothed_heights(m) for m in sub], {**kw, "patch_cache": None}
        alt = register(photo, camera, sun, sub, thresholds, step, apriori=meas[idx], names=sub_names, **kw_k)
        d = alt.measured - meas[idx]
        good = alt.ok & np.all(np.isfinite(d), axis=1) & (np.hypot(d[:, 0], d[:, 1]) <= max_shift_px)
        shifts[idx[good], :, k] = d[good]
        avail[idx[good], k] = True
        lost = [sub_names[j] for j in np.flatnonzero(~good)]
        if lost:
            warnings.append(
                f"model error ({label}): {len(lost)} landmark(s) not re-registered within {max_shift_px:g} px"
                f" ({', '.join(lost[:5])}{', ...' if len(lost) > 5 else ''}): no shift in that pattern"
            )
    return Sensitivity([lab for lab, _ in models], shifts, avail, warnings)
