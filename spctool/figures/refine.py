"""The picture of a landmark refinement (``spctool geometry --plot``), drawn with Pillow.

Two panels, from a :class:`spctool.stages.bundle.BundleResult` (it never runs a stage):

* **landmark corrections** — every landmark at its longitude/latitude (degrees, from the refined VLM),
  its correction (new − old VLM) projected on the local east/north plane drawn as a vector magnified by
  a stated factor, and its 1σ error ellipse (the posterior covariance projected on the same plane, at
  the same magnification) around the vector's tip; landmarks that kept their prior are grey crosses;
* **residuals per picture** — the rms residual (px, log axis) of each picture's measurements at the
  a-priori values and after the refinement, with the outliers flagged in that picture counted.

Conventions and helpers are those of :mod:`spctool.figures` (:class:`~spctool.figures.Figure`, colours,
axes).  ``extra['landmarks']``: {name: (x, y)} canvas position of each landmark, for tests.
"""

from __future__ import annotations

import math

import numpy as np

from spctool.figures import AFTER, BEFORE, BLACK, GREY, Figure, _Axes, _Canvas, fmt, nice_number

__all__ = ["refinement_plot"]

_OK = (0, 120, 220)
_ELLIPSE = (220, 60, 60)


def _east_north(v) -> tuple[np.ndarray, np.ndarray]:
    """Unit east and north vectors (L, 3) at body-fixed points ``v``."""
    z = np.array([0.0, 0.0, 1.0])
    up = v / np.linalg.norm(v, axis=1, keepdims=True)
    east = np.cross(z, up)
    n = np.linalg.norm(east, axis=1, keepdims=True)
    east = np.where(n > 1e-12, east / np.where(n > 1e-12, n, 1.0), np.array([0.0, 1.0, 0.0]))
    north = np.cross(up, east)
    return east, north


def refinement_plot(result, residual_rms_before, residual_rms_after, outliers_per_picture, *, title=""):
    """The two panels of the module docstring; ``residual_rms_*`` and ``outliers_per_picture`` per
    picture in the result's order."""
    v = np.asarray(result.landmark_positions, dtype=np.float64)
    n_l = v.shape[0]
    lon = np.degrees(np.arctan2(v[:, 1], v[:, 0])) if n_l else np.zeros(0)
    lat = np.degrees(np.arcsin(np.clip(v[:, 2] / np.linalg.norm(v, axis=1), -1, 1))) if n_l else np.zeros(0)
    east, north = _east_north(v) if n_l else (np.zeros((0, 3)), np.zeros((0, 3)))
    d = (v - np.asarray(result.landmark_positions0)) * 1000.0  # m
    de = np.sum(d * east, axis=1)
    dn = np.sum(d * north, axis=1)
    basis = np.stack([east, north], axis=2)  # (L, 3, 2)
    cov2 = np.einsum("lia,lij,ljb->lab", basis, np.asarray(result.landmark_covariance), basis) * 1e6
    ok = np.array([s == "ok" for s in result.landmark_status], dtype=bool)
    width, pad = 1100, 20
    cv = _Canvas(width, 900)
    cv.text((pad, 8), title or f"geometry: {n_l} landmarks, {len(result.picture_names)} pictures", 17)
    # ---- panel 1: corrections
    box = (70, 60, 760, 500)
    if n_l:
        xl = (float(lon.min()), float(lon.max()))
        yl = (float(lat.min()), float(lat.max()))
    else:
        xl = yl = (0.0, 1.0)
    mx = max(xl[1] - xl[0], 1e-6) * 0.08
    my = max(yl[1] - yl[0], 1e-6) * 0.08
    ax = _Axes(
        cv, box, (xl[0] - mx, xl[1] + mx), (yl[0] - my, yl[1] + my), "longitude (deg)", "latitude (deg)"
    )
    lengths = np.hypot(de[ok], dn[ok])
    semi = np.sqrt(np.maximum(np.linalg.eigvalsh(cov2[ok]).max(axis=1), 0.0)) if ok.any() else np.zeros(0)
    span_px = min(box[2] - box[0], box[3] - box[1])
    sizes = np.maximum(lengths, np.where(np.isfinite(semi), semi, 0.0))
    typical = float(np.median(sizes)) if sizes.size and np.median(sizes) > 0 else 1.0
    mag_px = nice_number(
        0.06 * span_px / typical
    )  # canvas px per metre: the larger of vector and ellipse fits
    # vectors and ellipses are drawn on the panel's own layer, so nothing spills out of the axes
    layer = _Canvas(box[2] - box[0] - 1, box[3] - box[1] - 1)
    layer.image.paste(cv.image.crop((box[0] + 1, box[1] + 1, box[2], box[3])))
    ox, oy = box[0] + 1, box[1] + 1
    positions = {}
    for i in range(n_l):  # one vector and ellipse per landmark (drawing)
        x, y = ax.x(lon[i]), ax.y(lat[i])
        positions[result.landmark_names[i]] = (x, y)
        if not ok[i]:
            layer.cross((x - ox, y - oy), 4, GREY, width=2, diagonal=True)
            continue
        tip = (x - ox + de[i] * mag_px, y - oy - dn[i] * mag_px)
        layer.arrow((x - ox, y - oy), tip, _OK, width=2, head=6)
        c = cov2[i]
        if np.all(np.isfinite(c)):
            w, vec = np.linalg.eigh(0.5 * (c + c.T))
            t = np.linspace(0, 2 * np.pi, 40)
            pts = (vec @ (np.sqrt(np.maximum(w, 0))[:, None] * np.stack([np.cos(t), np.sin(t)]))) * mag_px
            ring = [(tip[0] + a, tip[1] - b) for a, b in zip(pts[0], pts[1])]
            layer.draw.line(ring + ring[:1], fill=_ELLIPSE, width=1)
    cv.image.paste(layer.image, (ox, oy))
    # reference vector
    ref = nice_number(typical)
    rx, ry = box[0] + 12, box[3] - 14
    cv.arrow((rx, ry), (rx + ref * mag_px, ry), BLACK, width=2, head=6)
    cv.text((rx + ref * mag_px + 6, ry), f"{fmt(ref, 3)} m", 12, anchor="lm")
    cv.legend(
        (box[2] + 14, box[1]),
        [
            (_OK, "VLM correction (east/north)", "line"),
            (_ELLIPSE, "1-sigma posterior ellipse", "box"),
            (GREY, "kept its prior", "xmark"),
        ],
    )
    cv.text(
        (box[2] + 14, box[1] + 84),
        f"vectors and ellipses: {fmt(mag_px, 3)} canvas px per metre",
        12,
    )
    # ---- panel 2: residuals per picture
    rb = np.asarray(residual_rms_before, dtype=np.float64)
    ra = np.asarray(residual_rms_after, dtype=np.float64)
    nout = np.asarray(outliers_per_picture)
    n_p = rb.size
    fin = np.concatenate([rb[np.isfinite(rb) & (rb > 0)], ra[np.isfinite(ra) & (ra > 0)]])
    lo = 10.0 ** math.floor(math.log10(fin.min())) if fin.size else 0.01
    hi = 10.0 ** math.ceil(math.log10(fin.max() * 1.3)) if fin.size else 10.0
    box2 = (70, 580, 1060 - 180, 840)
    a2 = _Axes(
        cv,
        box2,
        (0.0, float(max(1, n_p))),
        (lo, hi),
        "",
        "rms residual per picture (px, log)",
        xticks=False,
        ylog=True,
    )
    bars = {}
    for k in range(n_p):  # one pair of bars per picture (drawing)
        mid = k + 0.5
        for key, val, colour, xa, xb in (
            ("before", rb[k], BEFORE, k + 0.08, mid),
            ("after", ra[k], AFTER, mid, k + 0.92),
        ):
            top = a2.bar(xa, xb, val, colour) if math.isfinite(val) else None
            if top is not None:
                bars[(k, key)] = ((a2.x(xa) + a2.x(xb)) / 2, top)
        if nout[k]:
            cv.text((a2.x(mid), box2[1] + 4), str(int(nout[k])), 10, fill=(220, 0, 0), anchor="ma")
    cv.text((box2[0], box2[3] + 6), f"pictures 1 .. {n_p} in list order; red numbers: outliers flagged", 12)
    cv.legend(
        (box2[2] + 14, box2[1]),
        [(BEFORE, "a-priori map and poses", "box"), (AFTER, "refined", "box")],
    )
    return Figure(cv.image, extra={"landmarks": positions, "bars": bars, "magnify_px_per_m": mag_px})
