"""Image space: the photo's shadowed pixels, left out of the correlation where they carry no signal.

Specification: S16 "Future Retina development" (templates rendered into the photo with cast shadows;
spc-algorithms.md §9) and issue #39 (image space as accurate as maplet space at a low Sun).  The
maplet-space counterpart is ``predict``'s ``shadows="auto"`` (:func:`spctool.stages.predict.resolve_shadows`).

An image-space template is rendered from the maplet's heights, which cannot hold the truth's sub-cell
relief: the edges of its cast shadows sit where the *smoothed* heights put them.  The photo's own
shadows are darker than the template's lit terrain wherever the truth casts further (its sharper
relief), and these pixels, dark in the photo and lit in the template, pull the alignment along the
Sun, as do the shadow's edge pixels (partly dark, where the truth puts the edge).  On the independent
low-Sun worlds (issue #39; truth ray-traced by trimesh + Embree, Sun 70° from the zenith; two-pass
image-space rms, facet truth, 96 landmarks; docs/benchmarks.md "The photo's shadows at a low Sun"):
no cast shadows in the template 0.198 px; the template's shadows left out (0/1/2 px margins)
0.041/0.046/0.053 px; Lambert instead of SPC's law 0.047 px; facet shading 0.045 px; 3 × 3 rays per
template pixel 0.044 px; as is 0.045 px; **the photo's pixels at its dark level left out 0.028 px**
(floors 2σ…10σ above the dark level alike), and with every pixel within 1/2/3 px of them 0.024/0.024/
0.025 px, the error common to a picture's landmarks along the Sun −0.027 → −0.019 → −0.009/−0.005/
−0.002 px.  The 3 px margin (:data:`AUTO_DARK_MARGIN_PX`) is the one whose remaining common error
the calibrated covariance covers (95 % ellipse: 0.82 → 0.85 at 2 px, 0.96 at 3 px).

So ``photo_shadows="auto"`` (:class:`spctool.stages.register_options.RegisterOptions`, the default) leaves out
of every full-resolution correlation of a landmark the photo pixels at or below a *dark floor* it
reads, once, from the photo under the landmark's own template (:func:`dark_floor`), and those within
:data:`AUTO_DARK_MARGIN_PX` of one (:func:`dark_pixels`):

* the template's dark pixels (radiance 0: cast or attached shadow, every sub-ray) must number at least
  :data:`AUTO_DARK_MIN_PIXELS` and :data:`AUTO_DARK_MIN_FRACTION` of the pixels compared, else the
  floor is 0 (nothing left out: a high Sun, or a landmark without shadows);
* the photo's dark level d and noise σ are the median and the scaled median absolute deviation
  (1.4826·MAD) of the photo under those pixels, its lit level ℓ the median under the template's lit
  pixels; the floor is d + clip(:data:`AUTO_DARK_SIGMAS`·σ, 5 %, 50 % of ℓ − d).  When ℓ − d is not
  above :data:`AUTO_DARK_CONTRAST_SIGMAS`·σ the photo shows no shadows there and the floor is 0.

``photo_shadows="use"`` correlates the photo's shadowed pixels (the previous behaviour).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "AUTO_DARK_CONTRAST_SIGMAS",
    "AUTO_DARK_MIN_FRACTION",
    "AUTO_DARK_MIN_PIXELS",
    "AUTO_DARK_SIGMAS",
    "PHOTO_SHADOW_MODES",
    "AUTO_DARK_MARGIN_PX",
    "dark_floor",
    "dark_floor_note",
    "dark_pixels",
]

PHOTO_SHADOW_MODES = ("auto", "use")

#: the template's dark pixels needed before a landmark's photo shadows are left out: this many …
AUTO_DARK_MIN_PIXELS = 20
#: … and this fraction of the pixels valid in both images (maplet space's rule: 1 % of the cells)
AUTO_DARK_MIN_FRACTION = 0.01
#: the floor lies this many noise σ above the photo's dark level (measured insensitive from 2 to 10)
AUTO_DARK_SIGMAS = 5.0
#: the photo shows shadows only if its lit level is this many σ above its dark level
AUTO_DARK_CONTRAST_SIGMAS = 10.0
#: pixels within this many px (square neighbourhood) of a dark one are left out too: the shadow's edge
AUTO_DARK_MARGIN_PX = 3


def dark_floor(template, template_valid, photo, photo_valid) -> float:
    """The DN at or below which the photo's pixels are left out of a landmark's correlation (0: none).

    ``template`` (H, W) radiance of the landmark's template and ``template_valid`` its valid pixels;
    ``photo`` (H, W) the photo under the template at its current placement, ``photo_valid`` its valid
    pixels.  Module docstring for the rule.  Pure; O(H·W).
    """
    t = np.asarray(template, dtype=np.float64)
    p = np.asarray(photo, dtype=np.float64)
    both = np.asarray(template_valid, dtype=bool) & np.asarray(photo_valid, dtype=bool)
    dark = both & (t <= 0.0)
    lit = both & (t > 0.0)
    n_dark, n_lit = int(np.count_nonzero(dark)), int(np.count_nonzero(lit))
    enough = max(AUTO_DARK_MIN_PIXELS, AUTO_DARK_MIN_FRACTION * (n_dark + n_lit))
    if n_dark < enough or n_lit < AUTO_DARK_MIN_PIXELS:
        return 0.0
    pd = p[dark]
    d = float(np.median(pd))
    sigma = 1.4826 * float(np.median(np.abs(pd - d)))
    contrast = float(np.median(p[lit])) - d
    if not contrast > AUTO_DARK_CONTRAST_SIGMAS * sigma or not contrast > 0.0:
        return 0.0
    return d + min(max(AUTO_DARK_SIGMAS * sigma, 0.05 * contrast), 0.5 * contrast)


def dark_floor_note(floors: dict) -> str:
    """The one line that says which landmarks' photo shadows were left out (``floors``: name → DN)."""
    names = sorted(floors)
    listed = ", ".join(names[:8]) + (f" and {len(names) - 8} more" if len(names) > 8 else "")
    lo, hi = min(floors.values()), max(floors.values())
    dn = f"{lo:.0f} DN" if round(lo) == round(hi) else f"{lo:.0f}-{hi:.0f} DN"
    return (
        f"{len(names)} landmark(s) correlated without the photo's shadowed pixels ({listed}; at or below "
        f"{dn}): the maplet's smoothed heights cannot place those shadows' edges "
        "(--photo-shadows use keeps them)"
    )


def dark_pixels(photo, floor: float, margin: int = AUTO_DARK_MARGIN_PX) -> np.ndarray:
    """The photo pixels left out with a dark floor: 0 < DN ≤ ``floor`` (DN 0 is no data, left out anyway)
    and every pixel within ``margin`` px of one (a square neighbourhood: the shadow's edge, partly dark,
    whose DN depends on where the truth puts that edge).  Separable dilation, O(margin·H·W)."""
    p = np.asarray(photo)
    dark = (p > 0.0) & (p <= floor)
    for axis in (0, 1):
        grown = dark.copy()
        n = dark.shape[axis]
        for k in range(1, min(int(margin), n - 1) + 1):
            lo = [slice(None)] * 2
            hi = [slice(None)] * 2
            lo[axis], hi[axis] = slice(k, None), slice(None, n - k)
            grown[tuple(lo)] |= dark[tuple(hi)]
            grown[tuple(hi)] |= dark[tuple(lo)]
        dark = grown
    return dark
