"""Figures of a "Find heights" run (``spctool lithos``): what changed in the maplet, and how its
re-rendering now matches each photo.

Drawn with :mod:`spctool.figures` (Pillow; grey tiles stretched to their 1–99 % range, cells without
data in :data:`spctool.figures.NO_DATA`) from a :class:`spctool.stages.find_heights.FindHeightsResult`
(it never runs a stage):

* :func:`maplet_sheet` — heights before | after | change, albedo before | after, flagged cells, then per
  picture the residual (extraction − re-rendered maplet, divided by λ) before and after;
* :func:`rerender_sheet` — per picture, the photo's extraction beside the re-rendered maplet, before and
  after, each with its NCC (Pearson ρ, map-refinement.md §2 "Known limits and metrics": comparing
  the re-rendered maplet with the photos is an accepted quality metric).
"""

from __future__ import annotations

import numpy as np

from spctool import figures
from spctool.figures import fmt

__all__ = ["maplet_sheet", "rerender_sheet"]


def _used_names(result, which: str) -> list[str]:
    used = result.images.get(which, {}).get("used")
    if used is None:
        return []
    return [p.name for p, u in zip(result.pictures, used) if u]


def _residuals(block):
    obs, pred = block["observed"], block["predicted"]
    ok = (obs > 0) & (pred > 0)
    scale = np.array([np.median(p[o]) if np.any(o) else 1.0 for p, o in zip(pred, ok)])
    return (obs - pred) / scale[:, None, None], ok


def _tile(values, valid, lo, hi) -> np.ndarray:
    """RGB of ``values`` stretched on the fixed range [lo, hi], no-data cells in NO_DATA."""
    ok = np.asarray(valid, bool) & np.isfinite(values)
    rgb = figures.grey_rgb(figures.stretch(values, lo, hi, valid=ok))
    rgb[~ok] = figures.NO_DATA
    return rgb


def maplet_sheet(result, title: str = "") -> figures.Figure:
    """Heights, albedo and per-picture residual maps before and after (module docstring).  Heights
    before/after share one grey scale, as do albedo before/after and each picture's two residual
    maps (±the 99th percentile of |residual| before), so what flattens is seen to flatten."""
    v = result.valid
    h0, h1 = result.start_heights, result.heights
    hlo, hhi = (float(np.min(np.r_[h0[v], h1[v]])), float(np.max(np.r_[h0[v], h1[v]]))) if v.any() else (0, 1)
    a0, a1 = result.start_albedo, result.albedo
    alo, ahi = (float(np.min(np.r_[a0[v], a1[v]])), float(np.max(np.r_[a0[v], a1[v]]))) if v.any() else (0, 2)
    if not ahi > alo:
        alo, ahi = alo - 0.1, ahi + 0.1
    tiles = [
        ("heights before", _tile(h0, v, hlo, hhi)),
        ("heights after", _tile(h1, v, hlo, hhi)),
        (f"change, rms {fmt(result.summary()['height_change_rms_cells'])}", h1 - h0, v),
        ("albedo before", _tile(a0, v, alo, ahi)),
        ("albedo after", _tile(a1, v, alo, ahi)),
        (f"flagged: {int(result.flagged.sum())} cells", _tile(result.flagged.astype(float), v, 0.0, 1.0)),
    ]
    before, after = result.images.get("before"), result.images.get("after")
    if before is not None and after is not None:
        rb, okb = _residuals(before)
        ra, oka = _residuals(after)
        names_b, names_a = _used_names(result, "before"), _used_names(result, "after")
        for name in dict.fromkeys(names_b + names_a):
            kb = names_b.index(name) if name in names_b else None
            ka = names_a.index(name) if name in names_a else None
            ref = rb[kb][okb[kb]] if kb is not None and okb[kb].any() else np.zeros(1)
            r = float(np.percentile(np.abs(ref), 99)) or 1.0
            for k, res, ok, when in ((kb, rb, okb, "before"), (ka, ra, oka, "after")):
                if k is not None:
                    rms = float(np.sqrt(np.mean(res[k][ok[k]] ** 2))) if ok[k].any() else float("nan")
                    tiles.append((f"{name[-6:]} {when} {fmt(rms, 2)}", _tile(res[k], ok[k], -r, r)))
    head = title or (f"{result.name}: {result.status}, {result.iterations} iteration(s); heights "
                     f"{fmt(hlo)}..{fmt(hhi)} cells; residuals (photo - maplet)/median, rms")
    return figures.contact_sheet(tiles, title=head, columns=6)


def rerender_sheet(result, title: str = "") -> figures.Figure:
    """Each picture's extraction beside the re-rendered maplet, before and after, with the NCC."""
    tiles = []
    by_name = {p.name: p for p in result.pictures}
    for which in ("before", "after"):
        block = result.images.get(which)
        if block is None:
            continue
        for k, name in enumerate(_used_names(result, which)):
            p = by_name[name]
            ncc = p.ncc_before if which == "before" else p.ncc_after
            obs, pred = block["observed"][k], block["predicted"][k]
            tiles.append((f"{name[-6:]} photo, {which}", obs, obs > 0))
            tiles.append((f"maplet {which}: NCC {fmt(ncc)}", pred, pred > 0))
    head = title or f"{result.name}: extraction | re-rendered maplet"
    return figures.contact_sheet(tiles, title=head, columns=4)
