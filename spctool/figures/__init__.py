"""Figures an analyst checks a registration or a pose with: PNG pictures drawn with Pillow.

SPC analysts judge a landmark registration by looking at the predicted and the extracted maplet
images side by side with the correlation surface, and a pose by its residuals over the photo.  This
package draws those pictures from the stages' results (it reads their result objects, it never runs a
stage).  Here the canvas and the pictures every command shares; beside them
:mod:`spctool.figures.register` (what ``register``/``correlate`` write: surfaces, panels, the overlay),
:mod:`spctool.figures.heights` (``lithos``) and :mod:`spctool.figures.refine` (``geometry --plot``):

* :func:`register_overlay` — the photo with each landmark's shift (measured − a-priori) drawn as a
  vector magnified by a stated factor, coloured by status, with legend, title and a reference vector;
* :func:`landmark_panel` — one landmark: predicted | extracted (maplet space) or template | photo
  window (image space) | correlation surface with the sub-pixel peak, upscaled nearest-neighbour, with
  a colour bar and the figures (ρ, shift, status);
* :func:`pose_plot` — solve-pose residuals before and after as a quiver over the photo plus a
  histogram of their lengths;
* :func:`batch_summary` — per picture of a batch: rms residual before/after, landmarks found vs selected;
* :func:`contact_sheet` — many small images (predict/extract/correlate) upscaled and labelled on one page;
* :func:`selection_overlay` — ``lithos-select --overlay``: the selected maplets' outlines on the photo.

Every function returns a :class:`Figure`: the Pillow image plus the mapping from SPC pixels (1-based,
centres at integers) to canvas coordinates, so a test can check that a vector or a marker sits where
the table says.  Colours: :data:`STATUS_COLOURS`; the colour map is viridis (perceptually uniform).
"""

from __future__ import annotations

import functools
import io
import math
from dataclasses import dataclass, field

import numpy as np
from PIL import Image, ImageDraw, ImageFont

# ------------------------------------------------------------------------------------------------
# colours

WHITE, BLACK, GREY = (255, 255, 255), (0, 0, 0), (128, 128, 128)
APRIORI = (255, 215, 0)  #: a-priori pixel marker (yellow)
BEFORE, AFTER = (255, 140, 0), (0, 200, 255)  #: pose residuals before / after the solve
PEAK = (255, 0, 0)  #: correlation peak marker (not in the colour map)
NO_DATA = (70, 30, 30)  #: cells without data in maplet images
#: vector / marker colour of each status (others: :data:`OTHER_STATUS`)
STATUS_COLOURS = {
    "ok": (40, 230, 40),
    "low-correlation": (255, 150, 0),
    "edge-peak": (255, 0, 255),
    "not-found": (255, 40, 40),
    "outside": (150, 150, 150),
    "no-maplet": (150, 150, 150),
    "rejected-outlier": (255, 40, 40),
}
OTHER_STATUS = (255, 90, 90)  #: removed-<criterion> and anything else

_VIRIDIS = np.array(
    [
        (68, 1, 84),
        (71, 44, 122),
        (59, 81, 139),
        (44, 113, 142),
        (33, 144, 141),
        (39, 173, 129),
        (92, 200, 99),
        (170, 220, 50),
        (253, 231, 37),
    ],
    dtype=np.float64,
)


def status_colour(status: str) -> tuple[int, int, int]:
    return STATUS_COLOURS.get(str(status), OTHER_STATUS)


def colormap(values, vmin: float, vmax: float, nan=GREY) -> np.ndarray:
    """(…, 3) uint8 viridis colours of ``values`` scaled from [vmin, vmax]; NaN → ``nan``."""
    v = np.asarray(values, dtype=np.float64)
    span = vmax - vmin if vmax > vmin else 1.0
    t = np.clip((np.nan_to_num(v, nan=vmin) - vmin) / span, 0.0, 1.0) * (len(_VIRIDIS) - 1)
    i = np.minimum(t.astype(np.int64), len(_VIRIDIS) - 2)
    f = (t - i)[..., None]
    rgb = _VIRIDIS[i] * (1.0 - f) + _VIRIDIS[i + 1] * f
    rgb = np.rint(rgb).astype(np.uint8)
    rgb[~np.isfinite(v)] = nan
    return rgb


# ------------------------------------------------------------------------------------------------
# basics


@functools.lru_cache(maxsize=16)
def font(size: int = 14):
    """Pillow's bundled scalable font (Pillow >= 10.1), else its fixed bitmap font (loaded once per size)."""
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # pragma: no cover - old Pillow
        return ImageFont.load_default()


def stretch(data, lo=None, hi=None, valid=None) -> np.ndarray:
    """8-bit grey of ``data`` scaled linearly from [lo, hi] (default: the 0.5 and 99.5 percentiles of
    the finite, ``valid`` values)."""
    d = np.asarray(data, dtype=np.float64)
    ok = np.isfinite(d) if valid is None else (np.asarray(valid, bool) & np.isfinite(d))
    if lo is None or hi is None or not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        if ok.any():
            lo, hi = (float(x) for x in np.percentile(d[ok], [0.5, 99.5]))
        else:
            lo, hi = 0.0, 1.0
        if not hi > lo:
            hi = lo + 1.0
    return np.clip(np.rint((np.nan_to_num(d, nan=lo) - lo) / (hi - lo) * 255.0), 0, 255).astype(np.uint8)


def grey_rgb(grey: np.ndarray) -> np.ndarray:
    return np.repeat(np.asarray(grey, np.uint8)[..., None], 3, axis=-1)


def upscale(rgb: np.ndarray, k: int) -> np.ndarray:
    """Nearest-neighbour enlargement by the integer factor ``k`` (each pixel becomes k × k)."""
    k = max(1, int(k))
    return np.repeat(np.repeat(rgb, k, axis=0), k, axis=1) if k > 1 else rgb


def nice_number(x: float) -> float:
    """The 1, 2 or 5 × 10^n nearest below ``x`` (> 0)."""
    if not (x > 0 and math.isfinite(x)):
        return 1.0
    e = math.floor(math.log10(x))
    for m in (5.0, 2.0, 1.0):
        if m * 10.0**e <= x:
            return m * 10.0**e
    return 10.0**e


def ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """About ``n`` round tick values covering [lo, hi]."""
    if not hi > lo:
        hi = lo + 1.0
    step = nice_number((hi - lo) / max(1, n - 1) * 1.5)
    start = math.ceil(lo / step - 1e-9) * step
    out = []
    v = start
    while v <= hi + 1e-9 * step:
        out.append(round(v, 12))
        v += step
    return out


def fmt(x: float, digits: int = 3) -> str:
    if not math.isfinite(x):
        return "nan"
    return f"{x:.{digits}g}" if abs(x) < 1e-3 or abs(x) >= 1e4 else f"{x:.{digits}f}".rstrip("0").rstrip(".")


@dataclass
class Figure:
    """A drawn figure: ``image`` (RGB), and where photo pixels land on it: the SPC pixel (sample,
    line) is drawn at canvas ``(x0 + (sample − 1)·zoom + (zoom − 1)/2, y0 + …)`` (:meth:`xy`)."""

    image: Image.Image
    x0: float = 0.0
    y0: float = 0.0
    zoom: float = 1.0
    magnify: float | None = None  #: vectors are drawn this many times their length
    extra: dict = field(default_factory=dict)  #: figure-specific positions (e.g. the peak marker)

    @property
    def size(self) -> tuple[int, int]:
        return self.image.size

    def xy(self, sample, line) -> tuple[float, float]:
        """Canvas position of SPC pixel (sample, line)."""
        h = (self.zoom - 1.0) / 2.0
        return self.x0 + (sample - 1.0) * self.zoom + h, self.y0 + (line - 1.0) * self.zoom + h

    def png(self) -> bytes:
        """PNG bytes; the figure's geometry (``x0``, ``y0``, ``zoom``, ``magnify`` and the scalar or
        short-tuple ``extra`` entries) is stored as JSON in a ``spctool`` text chunk."""
        import json

        from PIL.PngImagePlugin import PngInfo

        geometry = {"x0": self.x0, "y0": self.y0, "zoom": self.zoom, "magnify": self.magnify}
        for k, v in self.extra.items():
            if isinstance(v, (int, float, str)) or (
                isinstance(v, tuple) and len(v) <= 200 and all(isinstance(x, (int, float)) for x in v)
            ):
                geometry[k] = v
        info = PngInfo()
        info.add_text("Software", "spctool")
        info.add_text("spctool", json.dumps(geometry))
        buf = io.BytesIO()
        self.image.save(buf, format="PNG", compress_level=6, pnginfo=info)  # optimize=True: 4x slower
        return buf.getvalue()

    def save(self, path) -> None:
        """Write the PNG atomically (temporary file + rename); a different picture already at ``path``
        is kept as ``path.bak`` first (an analyst may keep the panels of an earlier run), the same
        picture is left as it is."""
        from pathlib import Path

        from spctool.formats import atomic

        data = self.png()
        path = Path(path)
        if path.is_file() and path.read_bytes() == data:
            return
        atomic.write_bytes(path, data, backup=True)


class _Canvas:
    def __init__(self, width: int, height: int, bg=WHITE):
        self.image = Image.new("RGB", (int(width), int(height)), bg)
        self.draw = ImageDraw.Draw(self.image)

    def text(self, xy, s, size=14, fill=BLACK, anchor="la"):
        self.draw.text((float(xy[0]), float(xy[1])), str(s), fill=fill, font=font(size), anchor=anchor)

    def text_width(self, s, size=14) -> float:
        box = self.draw.textbbox((0, 0), str(s), font=font(size))
        return float(box[2] - box[0])

    def paste(self, rgb: np.ndarray, xy) -> None:
        self.image.paste(
            Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8), "RGB"), (int(xy[0]), int(xy[1]))
        )

    def arrow(self, p, q, fill, width=2, head=7.0):
        """Line p → q with a filled head at q (no head when shorter than the head)."""
        (x0, y0), (x1, y1) = p, q
        self.draw.line([(x0, y0), (x1, y1)], fill=fill, width=width)
        length = math.hypot(x1 - x0, y1 - y0)
        if length > head:
            ux, uy = (x1 - x0) / length, (y1 - y0) / length
            bx, by = x1 - head * ux, y1 - head * uy
            w = head * 0.45
            self.draw.polygon([(x1, y1), (bx - w * uy, by + w * ux), (bx + w * uy, by - w * ux)], fill=fill)

    def cross(self, xy, r, fill, width=1, diagonal=False):
        x, y = xy
        if diagonal:
            self.draw.line([(x - r, y - r), (x + r, y + r)], fill=fill, width=width)
            self.draw.line([(x - r, y + r), (x + r, y - r)], fill=fill, width=width)
        else:
            self.draw.line([(x - r, y), (x + r, y)], fill=fill, width=width)
            self.draw.line([(x, y - r), (x, y + r)], fill=fill, width=width)

    def legend(self, xy, items, size=13, bg=(255, 255, 255), alpha_box=True):
        """Boxed legend at ``xy``: items (colour, label, kind) with kind 'line', 'cross' or 'box'."""
        x, y = xy
        w = max((self.text_width(lbl, size) for _, lbl, _ in items), default=0) + 34
        h = len(items) * (size + 6) + 8
        self.draw.rectangle([x, y, x + w, y + h], fill=bg, outline=BLACK)
        for k, (colour, label, kind) in enumerate(items):
            cy = y + 4 + k * (size + 6) + (size + 6) / 2
            if kind == "line":
                self.arrow((x + 6, cy), (x + 26, cy), colour, width=2, head=6)
            elif kind == "cross":
                self.cross((x + 16, cy), 5, colour, width=2)
            elif kind == "xmark":
                self.cross((x + 16, cy), 4, colour, width=2, diagonal=True)
            else:
                self.draw.rectangle([x + 9, cy - 5, x + 23, cy + 5], fill=colour, outline=BLACK)
            self.text((x + 30, cy), label, size, anchor="lm")
        return w, h

    def colour_bar(self, box, vmin, vmax, label="", size=12):
        """Vertical viridis bar in ``box`` (x0, y0, x1, y1), vmax at the top, with ticks."""
        x0, y0, x1, y1 = (int(v) for v in box)
        h = y1 - y0
        vals = np.linspace(vmax, vmin, h)[:, None] * np.ones((1, x1 - x0))
        self.paste(colormap(vals, vmin, vmax), (x0, y0))
        self.draw.rectangle([x0, y0, x1 - 1, y1 - 1], outline=BLACK)
        for t in ticks(vmin, vmax, 5):
            if vmin <= t <= vmax:
                ty = y0 + (vmax - t) / ((vmax - vmin) or 1.0) * (h - 1)
                self.draw.line([(x1, ty), (x1 + 4, ty)], fill=BLACK)
                self.text((x1 + 6, ty), fmt(t, 2), size, anchor="lm")
        if label:
            self.text(((x0 + x1) / 2, y1 + 4), label, size, anchor="ma")


def _photo_zoom(shape, target: int = 600) -> int:
    """Integer enlargement making the photo's longer side at least ``target`` px (small photos)."""
    return max(1, int(math.ceil(target / max(1, max(shape)))))


def photo_rgb(data, thrsh=None) -> np.ndarray:
    """The photo as 8-bit RGB, stretched between the SUM THRSH values (else the 0.5–99.5 percentiles)."""
    lo, hi = (None, None) if thrsh is None else (float(thrsh[0]), float(thrsh[1]))
    return grey_rgb(stretch(data, lo, hi))


def auto_magnify(vectors, target_px: float = 40.0) -> float:
    """A round magnification drawing the median vector about ``target_px`` long (1 when none)."""
    v = np.asarray(vectors, dtype=np.float64).reshape(-1, 2)
    n = np.hypot(v[:, 0], v[:, 1])
    n = n[np.isfinite(n) & (n > 0)]
    if not n.size:
        return 1.0
    return max(1.0, nice_number(target_px / float(np.median(n))))


# ------------------------------------------------------------------------------------------------
# register overlay


def register_overlay(
    photo,
    thrsh,
    names,
    apriori,
    measured,
    status,
    *,
    picture: str = "",
    subtitle: str = "",
    magnify: float | None = None,
    label: bool | None = None,
) -> Figure:
    """The photo with every landmark's registration drawn on it.

    A-priori pixels are yellow crosses; a landmark measured (status ok, or any row with a finite
    measured pixel) gets a vector from its a-priori pixel to a-priori + ``magnify`` × (measured −
    a-priori), coloured by status; landmarks without a measurement get an × in their status colour.
    Names are written next to each landmark when ``label`` (default: up to 80 landmarks).
    ``magnify`` (default :func:`auto_magnify`: the median shift drawn ≈ 40 px) is stated in the title
    and by a reference vector under the legend.  ``Figure.extra['tips']`` holds each vector's canvas tip.
    """
    data = np.asarray(getattr(photo, "data", photo), dtype=np.float64)
    apriori = np.asarray(apriori, np.float64).reshape(-1, 2)
    measured = np.asarray(measured, np.float64).reshape(-1, 2)
    status = [str(s) for s in status]
    shift = measured - apriori
    has = np.all(np.isfinite(shift), axis=1) & np.all(np.isfinite(apriori), axis=1)
    mag = float(magnify) if magnify else auto_magnify(shift[has])
    z = _photo_zoom(data.shape)
    rgb = upscale(photo_rgb(data, thrsh), z)
    head = 52
    cv = _Canvas(rgb.shape[1], rgb.shape[0] + head)
    cv.paste(rgb, (0, head))
    fig = Figure(cv.image, 0.0, float(head), float(z), mag)

    counts: dict[str, int] = {}
    for s in status:
        counts[s] = counts.get(s, 0) + 1
    tips = np.full((len(status), 2), np.nan)
    if label is None:
        label = len(status) <= 80
    # marks and names first, vectors on top (PIL draws one primitive at a time)
    shown = [k for k in range(len(status)) if np.all(np.isfinite(apriori[k]))]
    for k in shown:
        a = fig.xy(*apriori[k])
        if label:
            cv.text((a[0] + 7, a[1] + 4), names[k], 11, fill=status_colour(status[k]))
        cv.cross(a, 5, APRIORI, width=1)
        if not has[k]:
            cv.cross(a, 4, status_colour(status[k]), width=2, diagonal=True)
    for k in shown:
        if has[k]:
            a = fig.xy(*apriori[k])
            tips[k] = (a[0] + mag * z * shift[k, 0], a[1] + mag * z * shift[k, 1])
            cv.arrow(a, tuple(tips[k]), status_colour(status[k]), width=2, head=7)
    fig.extra["tips"] = tips

    n = len(status)
    summary = ", ".join(f"{c} {s}" for s, c in sorted(counts.items(), key=lambda kv: (kv[0] != "ok", kv[0])))
    cv.text((8, 6), f"{picture}  register: {counts.get('ok', 0)} of {n} landmarks ok", 17)
    cv.text((8, 30), f"{summary or 'no landmarks'}   {subtitle}   vectors x{fmt(mag)}", 13)
    with_vectors = {status[k] for k in shown if has[k]}
    _overlay_legend(cv, counts, with_vectors, mag, z, rgb.shape[1], head)
    return fig


def _overlay_legend(cv: _Canvas, counts, with_vectors, mag, z, width, head):
    items = [(APRIORI, "a-priori pixel", "cross")]
    for s in sorted(counts, key=lambda s: (s != "ok", s)):
        kind = "line" if s in with_vectors else "xmark"
        items.append((status_colour(s), f"{s} ({counts[s]})", kind))
    # measure first, then draw at the top right
    w = max(cv.text_width(lbl, 13) for _, lbl, _ in items) + 34
    x = width - w - 8
    lw, lh = cv.legend((x, head + 8), items)
    # reference vector: a round shift drawn at the same magnification
    ref = nice_number(max(60.0, lw - 20) / (mag * z))
    y = head + 8 + lh + 6
    length = ref * mag * z
    cv.draw.rectangle([x, y, x + max(lw, length + 12), y + 34], fill=WHITE, outline=BLACK)
    cv.arrow((x + 6, y + 10), (x + 6 + length, y + 10), BLACK, width=2, head=6)
    cv.text((x + 6, y + 18), f"{fmt(ref)} px shift (x{fmt(mag)})", 12)


def titled(image, title: str, subtitle: str = "", head: int = 52) -> Figure:
    """``image`` (a Pillow image or PNG bytes) under a white title band (``Figure.y0`` = band height)."""
    if isinstance(image, (bytes, bytearray)):
        image = Image.open(io.BytesIO(image)).convert("RGB")
    cv = _Canvas(image.size[0], image.size[1] + head)
    cv.image.paste(image, (0, head))
    cv.text((8, 6), title, 17)
    if subtitle:
        cv.text((8, 30), subtitle, 13)
    return Figure(cv.image, 0.0, float(head))


# ------------------------------------------------------------------------------------------------
# lithos-select: the selected maplets' outlines on the photo


SELECTION_PALETTE = [
    (255, 64, 64),
    (64, 220, 64),
    (80, 160, 255),
    (255, 200, 0),
    (255, 80, 255),
    (0, 230, 230),
    (255, 140, 0),
    (180, 120, 255),
]


def stretch_8bit(data, thrsh) -> np.ndarray:
    """DN -> 0..255 linearly between the SUM THRSH values (min/max of the photo if THRSH is empty)."""
    d = np.asarray(data, dtype=np.float64)
    lo, hi = (float(thrsh[0]), float(thrsh[1])) if thrsh is not None else (math.nan, math.nan)
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        lo, hi = float(np.nanmin(d)), float(np.nanmax(d))
        if not hi > lo:
            hi = lo + 1.0
    return np.clip(np.round((d - lo) / (hi - lo) * 255.0), 0, 255).astype(np.uint8)


def outline_pixels(camera, centres, ux, uy, half_side, per_edge: int = 8):
    """(sample, line, in_front) of the square outlines V + a·Ux + b·Uy, |a|, |b| = half_side, as
    (N, 4·per_edge + 1) arrays walking the boundary (closed)."""
    t = np.linspace(-1.0, 1.0, per_edge + 1)[:-1]
    one = np.ones_like(t)
    a = np.concatenate([t, one, -t, -one, [-1.0]])
    b = np.concatenate([-one, t, one, -t, [-1.0]])
    h = np.asarray(half_side, float)[:, None, None]
    pts = centres[:, None, :] + h * (a[None, :, None] * ux[:, None, :] + b[None, :, None] * uy[:, None, :])
    s, ln, front = camera.project_with_mask(pts.reshape(-1, 3))
    shape = pts.shape[:2]
    return s.reshape(shape), ln.reshape(shape), front.reshape(shape)


def selection_overlay(photo_data, thrsh, camera, names, centres, ux, uy, half_side, selected, sample, line):
    """The photo stretched to 8 bits (:func:`stretch_8bit`) with each selected maplet's square outline
    (half side ``half_side`` km, projected with ``camera``), its name and a cross at its (sample, line);
    a Pillow image (one colour per selected maplet, cycling :data:`SELECTION_PALETTE`)."""
    gray = stretch_8bit(photo_data, thrsh)
    img = Image.fromarray(np.repeat(gray[:, :, None], 3, axis=2), mode="RGB")
    draw = ImageDraw.Draw(img)
    sel = np.flatnonzero(np.asarray(selected, bool))
    if sel.size:
        centres, ux, uy = (np.asarray(a, float)[sel] for a in (centres, ux, uy))
        s, ln, front = outline_pixels(camera, centres, ux, uy, np.asarray(half_side, float)[sel])
        for k, idx in enumerate(sel):  # drawing is per polygon in PIL; the geometry above is vectorised
            if not front[k].all():
                continue
            colour = SELECTION_PALETTE[k % len(SELECTION_PALETTE)]
            xy = list(zip((s[k] - 1.0).tolist(), (ln[k] - 1.0).tolist()))  # SPC 1-based -> PIL 0-based
            draw.line(xy, fill=colour, width=1)
            cs, cl = float(sample[idx]) - 1.0, float(line[idx]) - 1.0
            if math.isfinite(cs) and math.isfinite(cl):
                draw.line([(cs - 2, cl), (cs + 2, cl)], fill=colour)
                draw.line([(cs, cl - 2), (cs, cl + 2)], fill=colour)
            draw.text((float(np.min(s[k])) - 1.0, float(np.min(ln[k])) - 12.0), names[idx], fill=colour)
    return img


# ------------------------------------------------------------------------------------------------
# one landmark: predicted | extracted | correlation surface


def _image_tile(values, valid, size: int, title: str, lo=None, hi=None):
    """An image upscaled nearest-neighbour to about ``size`` px, no-data cells in :data:`NO_DATA`."""
    v = np.asarray(values, dtype=np.float64)
    ok = np.isfinite(v) if valid is None else (np.asarray(valid, bool) & np.isfinite(v))
    rgb = grey_rgb(stretch(v, lo, hi, valid=ok))
    rgb[~ok] = NO_DATA
    k = max(1, size // max(v.shape))
    return upscale(rgb, k), k, title


def landmark_panel(
    name: str,
    picture: str,
    left,
    middle,
    surface,
    *,
    left_valid=None,
    middle_valid=None,
    labels=("predicted", "extracted"),
    peak_index=None,
    subpixel=(0.0, 0.0),
    spacing: int = 1,
    rho: float = math.nan,
    shift=(math.nan, math.nan),
    status: str = "",
    axes=("UY", "UX"),
    unit: str = "cells",
    tile: int = 240,
    note: str = "",
    mark_centre: bool = True,
) -> Figure:
    """Three tiles side by side: ``left`` | ``middle`` (e.g. predicted | extracted maplet images, axis 0
    down, no-data cells dark red) | the correlation ``surface`` (viridis over its finite range, NaN
    grey; zero offset marked by a small black +, the sub-pixel peak ``peak_index + subpixel`` by a red
    cross and circle), each upscaled nearest-neighbour to about ``tile`` px, a colour bar for ρ and the
    figures underneath.  ``axes``: names of the surface's column and row offset directions.
    ``mark_centre``: a yellow + on the centre cell of both images (the landmark centre V of maplet
    images).  ``Figure.extra['peak']`` = canvas (x, y) of the peak marker, ``extra['surface_origin']`` =
    canvas (x, y) of the surface's cell (0, 0) centre and ``extra['cell']`` = canvas px per surface
    cell.
    """
    pad, head, foot = 14, 44, 64
    t1, k1, _ = _image_tile(left, left_valid, tile, labels[0])
    t2, k2, _ = _image_tile(middle, middle_valid, tile, labels[1])
    s = np.asarray(surface, dtype=np.float64)
    fin = s[np.isfinite(s)]
    vmin, vmax = (float(fin.min()), float(fin.max())) if fin.size else (-1.0, 1.0)
    if not vmax > vmin:
        vmin, vmax = vmin - 0.05, vmax + 0.05
    ks = max(1, tile // max(s.shape))
    t3 = upscale(colormap(s, vmin, vmax), ks)
    th = max(t1.shape[0], t2.shape[0], t3.shape[0])
    bar_w = 16
    # the figures under the tiles (measured first: they set the width when the tiles are narrow)
    ok = "ok" if status == "ok" else status or "?"
    g0 = (s.shape[0] - 1) // 2
    if peak_index is not None:
        dr, dc = (float(v) if math.isfinite(float(v)) else 0.0 for v in subpixel)
        off = (spacing * (peak_index[0] - g0 + dr), spacing * (peak_index[1] - g0 + dc))
        last = f"last step: peak at ({fmt(off[1], 3)}, {fmt(off[0], 3)}) {unit} along ({axes[0]}, {axes[1]})"
    else:
        last = "last step: no peak"
    lines = [
        (
            f"rho = {fmt(rho, 4)}    measured - a-priori = ({fmt(shift[0], 3)}, {fmt(shift[1], 3)}) px "
            f"(sample, line)    status: {ok}",
            15,
            status_colour(status) if status not in ("ok", "") else BLACK,
        ),
        (f"{last};  surface: {s.shape[0]}x{s.shape[1]} offsets of {spacing} {unit}", 12, (60, 60, 60)),
        (
            f"surface columns: offset along {axes[0]}, rows: along {axes[1]} (down); black + = zero offset, "
            "red = sub-pixel peak; dark red = no data",
            12,
            (60, 60, 60),
        ),
    ]
    text_w = max(font(size).getlength(t) for t, size, _ in lines)
    width = int(max(pad * 4 + t1.shape[1] + t2.shape[1] + t3.shape[1] + bar_w + 56, text_w + 2 * pad))
    cv = _Canvas(width, head + 20 + th + 28 + foot + 18)
    cv.text((pad, 8), f"{name}  in  {picture}", 18)
    if note:
        cv.text((pad, 30), note, 12, fill=(60, 60, 60))
    x = pad
    y = head + 20
    xs = []
    for t, lbl in ((t1, labels[0]), (t2, labels[1]), (t3, f"correlation, spacing {spacing}")):
        cv.text((x + t.shape[1] / 2, head + 2), lbl, 14, anchor="ma")
        cv.paste(t, (x, y))
        cv.draw.rectangle([x - 1, y - 1, x + t.shape[1], y + t.shape[0]], outline=BLACK)
        xs.append(x)
        x += t.shape[1] + pad
    if mark_centre:  # maplet-image centres (V) on the two image tiles
        for xt, t, k in ((xs[0], t1, k1), (xs[1], t2, k2)):
            c = ((t.shape[1] // k - 1) // 2) * k + (k - 1) / 2
            r = ((t.shape[0] // k - 1) // 2) * k + (k - 1) / 2
            cv.cross((xt + c, y + r), max(4, k), APRIORI, width=1)
    # surface: zero offset and the peak
    ox, oy = xs[2] + (ks - 1) / 2, y + (ks - 1) / 2
    cv.cross((ox + g0 * ks, oy + g0 * ks), max(3, ks // 3), BLACK, width=1)
    peak_xy = None
    if peak_index is not None:
        px, py = ox + (peak_index[1] + dc) * ks, oy + (peak_index[0] + dr) * ks
        r = max(5, ks // 2)
        cv.draw.ellipse([px - r, py - r, px + r, py + r], outline=PEAK, width=2)
        cv.cross((px, py), r + 3, PEAK, width=2)
        peak_xy = (float(px), float(py))
    bx = xs[2] + t3.shape[1] + 10
    cv.colour_bar((bx, y, bx + bar_w, y + t3.shape[0]), vmin, vmax, "rho")
    cv.text((xs[2] + t3.shape[1] / 2, y + t3.shape[0] + 4), f"offset {axes[0]} ->", 12, anchor="ma")
    fy = y + th + 26
    for k, (text, size, colour) in enumerate(lines):
        cv.text((pad, fy + (0 if k == 0 else 6 + 16 * k)), text, size, fill=colour)
    return Figure(
        cv.image,
        extra={
            "peak": peak_xy,
            "surface_origin": (ox, oy),
            "cell": float(ks),
            "range": (vmin, vmax),
            "tiles_x": xs,
            "tiles_y": y,
        },
    )


# ------------------------------------------------------------------------------------------------
# a page of small images


def contact_sheet(
    tiles, *, title: str = "", columns: int | None = None, tile: int = 160, key: str = ""
) -> Figure:
    """``tiles``: (caption, values, valid or None) — or (caption, rgb uint8 (h, w, 3)) — each upscaled
    nearest-neighbour to about ``tile`` px and captioned, in a grid under ``title``; ``key`` (a line
    under the title) explains what the captions and colours show."""
    tiles = list(tiles)
    n = max(1, len(tiles))
    cols = columns or max(1, min(n, int(math.ceil(math.sqrt(n * 1.3)))))
    rows = int(math.ceil(n / cols))
    pad, cap, head = 10, 18, (30 if title else 6) + (20 if key else 0)
    cv = _Canvas(pad + cols * (tile + pad), head + rows * (tile + cap + pad) + pad)
    if key:  # as wide as it needs: a sheet of a few tiles is widened to show it whole
        need = int(cv.text_width(key, 12)) + 2 * pad
        if need > cv.image.width:
            cv = _Canvas(need, cv.image.height)
    if title:
        cv.text((pad, 6), title, 16)
    if key:
        cv.text((pad, 30), key, 12)
    for k, t in enumerate(tiles):
        r, c = divmod(k, cols)
        x, y = pad + c * (tile + pad), head + r * (tile + cap + pad)
        if len(t) == 2:
            caption, rgb = t
            kk = max(1, tile // max(rgb.shape[:2]))
            img = upscale(np.asarray(rgb, np.uint8), kk)
        else:
            caption, values, valid = t
            img, _, _ = _image_tile(values, valid, tile, caption)
        cv.paste(img[:tile, :tile], (x + (tile - min(tile, img.shape[1])) // 2, y + cap))
        cv.text((x, y + 2), caption, 12)
    return Figure(cv.image)


def surface_tile(corr) -> np.ndarray:
    """A correlation surface (a stage ``Correlation``) as RGB, upscaled, with its peak marked in red."""
    s = np.asarray(corr.surface, dtype=np.float64)
    fin = s[np.isfinite(s)]
    vmin, vmax = (float(fin.min()), float(fin.max())) if fin.size else (-1.0, 1.0)
    k = max(1, 150 // max(s.shape))
    rgb = upscale(colormap(s, vmin, vmax if vmax > vmin else vmin + 0.1), k)
    if corr.peak_index is not None:
        img = Image.fromarray(rgb, "RGB")
        d = ImageDraw.Draw(img)
        dr, dc = (float(v) if math.isfinite(float(v)) else 0.0 for v in corr.subpixel)
        px, py = (corr.peak_index[1] + dc) * k + (k - 1) / 2, (corr.peak_index[0] + dr) * k + (k - 1) / 2
        d.line([(px - k, py), (px + k, py)], fill=PEAK, width=2)
        d.line([(px, py - k), (px, py + k)], fill=PEAK, width=2)
        rgb = np.asarray(img)
    return rgb


# ------------------------------------------------------------------------------------------------
# plots with axes


class _Axes:
    """A plotting box mapping data (x, y) to canvas pixels, with ticks and labels.  ``ylog``: the y
    axis is logarithmic (ylim > 0; bars start at ylim[0]); ``yint``: integer y ticks only."""

    def __init__(
        self, cv: _Canvas, box, xlim, ylim, xlabel="", ylabel="", xticks=True, ylog=False, yint=False
    ):
        self.cv, self.box = cv, [float(v) for v in box]
        self.xlim, self.ylim, self.ylog = xlim, ylim, ylog
        x0, y0, x1, y1 = self.box
        cv.draw.rectangle([x0, y0, x1, y1], outline=BLACK)
        if ylog:
            lo, hi = math.floor(math.log10(ylim[0])), math.ceil(math.log10(ylim[1]))
            yt = [m * 10.0**e for e in range(lo, hi + 1) for m in (1, 2, 5)]
        else:
            yt = [t for t in ticks(*ylim, 5) if not yint or t == round(t)]
        for t in yt:
            if ylim[0] <= t <= ylim[1]:
                ty = self.y(t)
                cv.draw.line([(x0 - 4, ty), (x0, ty)], fill=BLACK)
                cv.draw.line([(x0 + 1, ty), (x1 - 1, ty)], fill=(225, 225, 225))
                cv.text((x0 - 6, ty), fmt(t, 3), 11, anchor="rm")
        if xticks:
            for t in ticks(*xlim, 6):
                if xlim[0] <= t <= xlim[1]:
                    tx = self.x(t)
                    cv.draw.line([(tx, y1), (tx, y1 + 4)], fill=BLACK)
                    cv.text((tx, y1 + 6), fmt(t, 3), 11, anchor="ma")
        if xlabel:
            cv.text(((x0 + x1) / 2, y1 + 22), xlabel, 12, anchor="ma")
        if ylabel:
            cv.text((x0, y0 - 6), ylabel, 12, anchor="ld")

    def x(self, v):
        x0, _, x1, _ = self.box
        return x0 + (v - self.xlim[0]) / ((self.xlim[1] - self.xlim[0]) or 1.0) * (x1 - x0)

    def y(self, v):
        _, y0, _, y1 = self.box
        lo, hi = self.ylim
        if self.ylog:
            v, lo, hi = (math.log10(max(float(x), 1e-300)) for x in (v, lo, hi))
        return y1 - (v - lo) / ((hi - lo) or 1.0) * (y1 - y0)

    def bar(self, xa, xb, h, fill):
        """A bar from the axis bottom to ``h`` (clipped to the box); returns its top's canvas y."""
        if not h > 0:
            return None
        base = self.ylim[0]
        top = self.y(min(max(h, base), self.ylim[1]))
        self.cv.draw.rectangle([self.x(xa), top, self.x(xb), self.y(base)], fill=fill)
        return top


def histogram_counts(values, edges) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64)
    return np.histogram(v[np.isfinite(v)], bins=edges)[0]


def pose_plot(
    photo,
    thrsh,
    names,
    measured,
    residual_before,
    residual_after,
    status,
    *,
    picture: str = "",
    rms_before: float = math.nan,
    rms_after: float = math.nan,
    magnify: float | None = None,
    magnify_after: float | None = None,
    shape=None,
    label: bool | None = None,
) -> Figure:
    """solve-pose residuals (measured − predicted, px) before (orange) and after (blue) the solve,
    drawn from each measured pixel toward the predicted one, over the photo (``photo`` None: a grey
    frame of ``shape`` (lines, samples)), with one histogram of the residual lengths before and one
    after.  The two sets have their own magnification (default: each median drawn ≈ 40 px, after at
    least as magnified as before), both stated in the title and legend.  Rows whose status is not ok
    are marked by an × in their status colour.  Landmark names are written beside their pixels when
    ``label`` (default: up to 80 landmarks); a legend in the overlay's style explains every mark, and
    one reference vector per magnification gives the scale (``extra['reference_before']``,
    ``extra['reference_after']``: residual px, drawn length, start x, y).
    ``extra['tips_before']`` / ``extra['tips_after']``:
    canvas tips of the vectors; ``extra['hist']``: ((edges, counts) before, (edges, counts) after);
    ``extra['magnify_after']``."""
    if photo is not None:
        rgb = photo_rgb(getattr(photo, "data", photo), thrsh)
    else:
        rgb = np.full(tuple(shape) + (3,), 60, np.uint8)
    m = np.asarray(measured, np.float64).reshape(-1, 2)
    rb = np.asarray(residual_before, np.float64).reshape(-1, 2)
    ra = np.asarray(residual_after, np.float64).reshape(-1, 2)
    status = [str(s) for s in status]
    ok = np.array([s == "ok" for s in status], bool)
    mag = float(magnify) if magnify else auto_magnify(rb[ok])
    mag_a = float(magnify_after) if magnify_after else max(mag, auto_magnify(ra[ok]))
    z = _photo_zoom(rgb.shape[:2], 560)
    step = max(1, int(math.ceil(max(rgb.shape[:2]) / 1000)))  # very large photos: drawn reduced
    rgb = upscale(rgb, z)[::step, ::step]
    zoom = z / step
    head, side, pad = 56, 360, 20
    n_marks = len(set(str(s) for s in status) - {"ok"})
    cv = _Canvas(rgb.shape[1] + side + 2 * pad, max(rgb.shape[0], 660 + 19 * n_marks) + head + 10)
    cv.paste(rgb, (0, head))
    fig = Figure(cv.image, 0.0, float(head), zoom, mag, extra={"magnify_after": mag_a})
    tips_b = np.full(m.shape, np.nan)
    tips_a = np.full(m.shape, np.nan)
    shown = [k for k in range(len(status)) if np.all(np.isfinite(m[k]))]
    if label is None:
        label = len(status) <= 80
    for k in shown:  # marks and names first, then the vectors on top (PIL draws one primitive at a time)
        p = fig.xy(*m[k])
        if label:
            colour = WHITE if ok[k] else status_colour(status[k])
            cv.text((p[0] + 7, p[1] + 4), str(names[k]), 11, fill=colour)
        cv.cross(p, *((3, WHITE, 1) if ok[k] else (4, status_colour(status[k]), 2)), diagonal=not ok[k])
    for res, colour, tips, f in ((rb, BEFORE, tips_b, mag), (ra, AFTER, tips_a, mag_a)):
        for k in shown:
            if ok[k] and np.all(np.isfinite(res[k])):
                # from the measured pixel toward the predicted one (− residual)
                p = fig.xy(*m[k])
                tips[k] = (p[0] - f * zoom * res[k, 0], p[1] - f * zoom * res[k, 1])
                cv.arrow(p, tuple(tips[k]), colour, width=2, head=7)
    fig.extra["tips_before"], fig.extra["tips_after"] = tips_b, tips_a
    n_ok = int(ok.sum())
    cv.text((8, 6), f"{picture}  solve-pose: {n_ok} of {len(status)} landmarks used", 17)
    cv.text(
        (8, 30),
        f"rms residual {fmt(rms_before, 3)} px before -> {fmt(rms_after, 3)} px after;  vectors from the "
        f"measured pixel toward the predicted one, before x{fmt(mag)}, after x{fmt(mag_a)}",
        13,
    )
    x = rgb.shape[1] + pad + 40
    hb = _residual_histogram(cv, rb[ok], x, head + 30, side - 50, BEFORE, "before the solve")
    ha = _residual_histogram(cv, ra[ok], x, head + 250, side - 50, AFTER, "after the solve")
    fig.extra["hist"] = (hb, ha)
    items = [
        (WHITE, "measured pixel (landmark name beside it)", "cross"),
        (BEFORE, f"residual before (a-priori pose) x{fmt(mag)}", "line"),
        (AFTER, f"residual after (solved pose) x{fmt(mag_a)}", "line"),
    ]
    items += [(status_colour(s), f"{s} (not used)", "xmark") for s in sorted(set(status) - {"ok"})]
    lx, ly = x - 30, head + 470
    lw, lh = cv.legend((lx, ly), items, bg=(200, 200, 200))  # grey: the white mark shows
    # reference vectors, one per magnification: a round residual drawn as the plot draws it
    y = ly + lh + 6
    room = side - 40
    for colour, f, when in ((BEFORE, mag, "before"), (AFTER, mag_a, "after")):
        ref = nice_number(min(80.0, room) / (f * zoom))
        while ref * f * zoom > room:  # nice_number may round up past the room
            ref = nice_number(ref / 2.0)
        length = ref * f * zoom
        cv.draw.rectangle([lx, y, lx + max(lw, length + 12), y + 34], fill=WHITE, outline=BLACK)
        cv.arrow((lx + 6, y + 10), (lx + 6 + length, y + 10), colour, width=2, head=6)
        cv.text((lx + 6, y + 18), f"{fmt(ref)} px residual {when} (x{fmt(f)})", 12)
        # (residual in px, drawn length, the arrow's start x, y) in canvas px
        fig.extra[f"reference_{when}"] = (float(ref), float(length), float(lx + 6), float(y + 10))
        y += 40
    return fig


def _residual_histogram(cv, res, x, y, w, colour, title):
    """Histogram of the residual lengths |res| (px) in a box at (x, y); returns (edges, counts)."""
    n = np.hypot(res[:, 0], res[:, 1])
    n = n[np.isfinite(n)]
    top = float(n.max()) if n.size else 1.0
    step = nice_number((top if top > 0 else 1.0) / 8.0)
    edges = np.arange(0.0, top + step * 1.0001, step)
    if len(edges) < 2:
        edges = np.array([0.0, step])
    counts = histogram_counts(n, edges)
    ymax = max(1, int(counts.max(initial=0)))
    ax = _Axes(cv, (x, y + 16, x + w, y + 166), (0.0, float(edges[-1])), (0.0, ymax * 1.1), yint=True)
    cv.text((x, y), f"{title}: residual length (px), landmarks per bin", 12)
    for k in range(len(edges) - 1):
        ax.bar(edges[k] + 0.05 * step, edges[k + 1] - 0.05 * step, counts[k], colour)
    return edges, counts


# ------------------------------------------------------------------------------------------------
# batch summary


def batch_summary(pictures, rms_before, rms_after, selected, found, status, *, title: str = "") -> Figure:
    """Two panels over the pictures of a batch (in list order): rms residual before / after the pose
    solve (px, logarithmic axis), and landmarks found (registered) beside selected; pictures whose
    status is not ok are marked by an × on the axis (red: failed, orange: no pose).  With room, each
    bar carries its value.  ``extra['bars']``: {(picture index, key): (x_centre, y_top)} with key in
    rms_before, rms_after, selected, found; ``extra['axes']``: the two axes boxes."""
    n = len(pictures)
    rb = np.asarray(rms_before, np.float64)
    ra = np.asarray(rms_after, np.float64)
    sel = np.asarray(selected, np.float64)
    fnd = np.asarray(found, np.float64)
    slot = max(4, min(110, 1100 // max(1, n)))
    left, pad = 70, 20
    label_names = slot >= 14
    values_on_bars = slot >= 60
    plot_w = slot * max(1, n)
    width = max(left + plot_w + 200, 560)
    h1 = h2 = 220
    cv = _Canvas(width, 56 + h1 + 56 + h2 + (96 if label_names else 40))
    cv.text((pad, 8), title or f"batch: {n} pictures", 17)
    fin = np.concatenate([rb[np.isfinite(rb) & (rb > 0)], ra[np.isfinite(ra) & (ra > 0)]])
    lo = 10.0 ** math.floor(math.log10(fin.min())) if fin.size else 0.01
    hi = 10.0 ** math.ceil(math.log10(fin.max() * 1.3)) if fin.size else 10.0
    a1 = _Axes(
        cv,
        (left, 56, left + plot_w, 56 + h1),
        (0.0, float(max(1, n))),
        (lo, hi),
        "",
        "rms residual (px, log scale)",
        xticks=False,
        ylog=True,
    )
    ctop = float(np.nanmax(np.concatenate([sel, fnd, [1.0]]))) * 1.15
    y2 = 56 + h1 + 56
    a2 = _Axes(
        cv,
        (left, y2, left + plot_w, y2 + h2),
        (0.0, float(max(1, n))),
        (0.0, ctop),
        "",
        "landmarks",
        xticks=False,
        yint=True,
    )
    bars = {}
    for k in range(n):
        a, b, mid = k + 0.08, k + 0.92, k + 0.5
        for ax, pair in (
            (a1, (("rms_before", rb[k], BEFORE), ("rms_after", ra[k], AFTER))),
            (a2, (("selected", sel[k], (150, 150, 220)), ("found", fnd[k], (40, 170, 40)))),
        ):
            for (key, v, colour), (xa, xb) in zip(pair, ((a, mid), (mid, b))):
                top = ax.bar(xa, xb, v, colour) if math.isfinite(v) else None
                if top is not None:
                    bars[(k, key)] = ((ax.x(xa) + ax.x(xb)) / 2, top)
                    if values_on_bars:
                        text = fmt(v, 2) if key.startswith("rms") else str(int(v))
                        cv.text(((ax.x(xa) + ax.x(xb)) / 2, top - 2), text, 10, anchor="md")
        if str(status[k]) != "ok":
            colour = (220, 0, 0) if str(status[k]).startswith("failed") else (255, 140, 0)
            for ax in (a1, a2):
                cv.cross((ax.x(mid), ax.box[3] - 7), 5, colour, width=2, diagonal=True)
        if label_names:
            mask = Image.new("L", (100, 14), 0)
            ImageDraw.Draw(mask).text((0, 0), str(pictures[k])[-14:], fill=255, font=font(11))
            mask = mask.rotate(60, expand=True)
            cv.image.paste(BLACK, (int(a2.x(mid) - mask.size[0] + 6), int(y2 + h2 + 4)), mask)
    lx = left + plot_w + 16
    cv.legend((lx, 56), [(BEFORE, "a-priori pose", "box"), (AFTER, "solved pose", "box")])
    cv.legend(
        (lx, y2),
        [
            ((150, 150, 220), "selected", "box"),
            ((40, 170, 40), "found", "box"),
            ((220, 0, 0), "failed", "xmark"),
            ((255, 140, 0), "no pose", "xmark"),
        ],
    )
    if not label_names:
        cv.text((left, y2 + h2 + 6), f"pictures 1 .. {n} in list order", 12)
    return Figure(
        cv.image,
        extra={
            "bars": bars,
            "axes": (a1.box, a2.box),
            "rms_box": tuple(a1.box),
            "rms_ylim": (float(lo), float(hi)),
            "count_box": tuple(a2.box),
            "count_ylim": (0.0, float(ctop)),
            "slot_x": tuple(float(a1.x(k + 0.5)) for k in range(n)) if n <= 200 else (),
        },
    )
