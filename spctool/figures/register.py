"""Pictures a registration writes (``correlate`` and ``register``): each landmark's correlation surface
as an image, its panel, and the shift overlay on the photo.

The drawing primitives are :mod:`spctool.figures` (:func:`~spctool.figures.landmark_panel`,
:func:`~spctool.figures.register_overlay`); this room turns a registration's result into those pictures
and writes them, never replacing an analyst's file without a ``.bak``:

* :func:`write_surface` — ``<LANDMARK>_<PICTURE>_surface.<ext>``: PGM/PNG map ρ ∈ [−1, 1] to 0…255
  (:func:`surface_to_8bit`, NaN to 0); FITS keeps the float values with the step in its header;
* :func:`write_panel` / :func:`write_panels` — predicted | extracted | surface (maplet space, the
  prediction redrawn at the final pose: S16 Fig. 3, L15 §3.3) or template | photo window | surface
  (image space, S16 §2.2);
* :func:`overlay_png` — the photo with each landmark's magnified shift (measured − a-priori).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from spctool import __version__, figures
from spctool.formats.photo import write_photo
from spctool.stages.predict import predict


def surface_to_8bit(surface) -> np.ndarray:
    """ρ ∈ [−1, 1] → 0…255 (NaN → 0)."""
    s = np.asarray(surface, dtype=np.float64)
    return np.where(np.isfinite(s), np.clip(np.rint((np.nan_to_num(s) + 1.0) * 127.5), 0, 255), 0).astype(
        np.uint8
    )


def write_surface(out_dir: Path, fmt: str, name: str, picture: str, step, space: str, zoom: int = 1) -> Path:
    """OUT_DIR/<LANDMARK>_<PICTURE>_surface.<fmt> of a correlation step's surface (PGM/PNG enlarged by
    ``zoom``; FITS with the surface's figures in its header); an existing file is kept as ``.bak``."""
    path = out_dir / f"{name}_{picture}_surface.{fmt}"
    corr = step.correlation
    if fmt == "fits":
        hdr = {
            "LANDMARK": (name, "landmark (maplet) name"),
            "PICTURE": (picture, "SPC picture name"),
            "STAGE": ("correlate", "spctool stage of this image"),
            "SPCTVER": (__version__, "spctool version"),
            "SPACE": (space, "maplet or image space"),
            "SPACING": (int(corr.spacing), "cells (pixels) per bin"),
            "GRIDHALF": (int(corr.grid_half), "offsets -K..K per axis"),
            "AXIS1": ("UY" if space == "maplet" else "SAMPLE", "array axis 1 (NAXIS1) offset direction"),
            "AXIS2": ("UX" if space == "maplet" else "LINE", "array axis 0 (NAXIS2) offset direction"),
            "STATUS": (step.status, "peak status"),
        }
        if math.isfinite(corr.peak):
            hdr["PEAK"] = (float(corr.peak), "surface maximum")
        for k, v in (("OFFSET0", corr.offset[0]), ("OFFSET1", corr.offset[1])):
            if math.isfinite(float(v)):
                hdr[k] = (float(v), "offset along array axis 0/1, full-resolution cells or px")
        write_photo(path, np.asarray(corr.surface, dtype=np.float64), fmt="fits", header=hdr, backup=True)
    else:
        k = int(zoom)
        image = np.repeat(np.repeat(surface_to_8bit(corr.surface), k, axis=0), k, axis=1)
        write_photo(path, image, fmt=fmt, backup=True)
    return path


def overlay_png(
    photo_data, thrsh, names, apriori, measured, ok, *, status=None, picture="", subtitle="", magnify=None
) -> bytes:
    """PNG bytes of :func:`spctool.figures.register_overlay`: the photo with each landmark's shift drawn
    as a vector magnified by a stated factor, coloured by status, with legend, title and a reference
    vector (``status`` default: ok / not-found from ``ok``)."""
    if status is None:
        status = ["ok" if o else "not-found" for o in ok]
    fig = figures.register_overlay(
        photo_data,
        thrsh,
        names,
        apriori,
        measured,
        status,
        picture=picture,
        subtitle=subtitle,
        magnify=magnify,
    )
    return fig.png()


def write_panels(out_dir: Path, inp, result, opts) -> int:
    """One PNG per landmark with a last correlation step (:func:`write_panel`); returns the count."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = 0
    for i, st in enumerate(result.last_steps):
        shift = result.measured[i] - result.apriori[i]
        if st is not None and write_panel(out_dir, inp, i, st, result.camera, opts, result.status[i], shift):
            written += 1
    return written


def write_panel(out_dir: Path, inp, i, st, camera, opts, status, shift, suffix: str = "panel"):
    """DIR/LANDMARK_PICTURE_SUFFIX.png of landmark ``i``'s correlation step ``st`` (``correlate``'s
    suffix is its own, so that its panels never replace those of ``register`` in the same folder)
    (:func:`spctool.figures.landmark_panel`): predicted | extracted | surface (maplet space; the
    prediction is redrawn with ``camera``), or template | photo window at the template's placement |
    surface (image space).  ``shift``: the (dsample, dline) reported for the landmark."""

    name = inp.names[i]
    corr = st.correlation
    common = dict(
        peak_index=corr.peak_index,
        subpixel=corr.subpixel,
        spacing=int(corr.spacing),
        rho=float(corr.peak),
        status=status,
        shift=tuple(float(x) for x in shift),
    )
    if st.extraction is not None:
        pred = predict(inp.maplets[i], camera.position, inp.pic.sz, opts.predict, extracted=st.extraction)
        fig = figures.landmark_panel(
            name,
            inp.pic.name,
            pred.image,
            st.extraction.image,
            corr.surface,
            left_valid=pred.lit,
            middle_valid=st.extraction.valid,
            axes=("UY", "UX"),
            unit="cells",
            note="maplet space, North up; yellow + = landmark centre V; prediction at the final pose",
            **common,
        )
    elif st.template is not None:
        tmpl = st.template
        s0, s1, l0, l1 = tmpl.window
        c0 = np.asarray(camera.project(np.asarray(inp.maplets[i].v, float)[None, :]), float).reshape(2)
        ds, dl = (int(v) for v in np.rint(st.center - c0))
        win = photo_window(inp.photo.data, s0 + ds, s1 + ds, l0 + dl, l1 + dl)
        fig = figures.landmark_panel(
            name,
            inp.pic.name,
            tmpl.radiance,
            win,
            corr.surface,
            left_valid=tmpl.coverage >= 1.0 - 1e-12,
            middle_valid=np.isfinite(win),
            labels=("template (rendered)", "photo window"),
            axes=("sample", "line"),
            unit="px",
            note=f"image space; photo samples {s0 + ds}-{s1 + ds}, lines {l0 + dl}-{l1 + dl} "
            "(where the template sat for the last step)",
            mark_centre=False,
            **common,
        )
    else:
        return None
    path = out_dir / f"{name}_{inp.pic.name}_{suffix}.png"
    fig.save(path)  # a different picture already there is kept as .bak
    return path


def photo_window(data, s0, s1, l0, l1):
    """Photo DN over samples s0..s1, lines l0..l1 (1-based inclusive); NaN outside the photo."""
    out = np.full((l1 - l0 + 1, s1 - s0 + 1), np.nan)
    nln, npx = data.shape
    a, b = max(l0, 1), min(l1, nln)
    c, d = max(s0, 1), min(s1, npx)
    if a <= b and c <= d:
        out[a - l0 : b - l0 + 1, c - s0 : d - s0 + 1] = data[a - 1 : b, c - 1 : d]
    return out
