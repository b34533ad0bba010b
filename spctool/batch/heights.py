"""SPC's LITHOS "Find heights" over the maplets of a working directory, in parallel over maplets.

The cycle's second reduction (map-refinement.md §2 "Outer loop"; S16 Fig. 3): after the landmarks and
poses are refined (:mod:`spctool.batch.refine`), each maplet's heights and albedo are solved from the
pictures that measured it (:func:`spctool.stages.find_heights.find_heights`).  Maplets are independent,
so they go to local worker processes (``jobs``; started as :func:`spctool.workers.start_method` says),
one maplet a task; each task reads its own files and writes its own MAP and LMK.

A maplet is written only when it was solved and its re-rendering matches the photos at least as well
as the starting one (``find_heights``'s ``worse`` test, as ``spctool lithos`` without ``--force``);
every maplet's outcome is returned (status, mean NCC before/after, reason).
"""

from __future__ import annotations

import math
from pathlib import Path

from spctool.errors import SpcError

__all__ = ["landmark_views", "refine_maplet", "refine_heights"]


def landmark_views(wd, settings, lmk):
    """(views, skipped names): a :class:`~spctool.stages.find_heights.PictureView` per PICTURES row of
    the LMK not flagged ``*`` (its pixel the a-priori centre), with the picture's SUM, camera and photo."""
    from spctool.geometry.camera import Camera
    from spctool.stages.find_heights import PictureView

    views, skipped = [], []
    for row in lmk.pictures:  # file reads per picture
        if row.flag == "*":
            continue
        try:
            pic = wd.read_picture(row.name)
            photo = wd.read_photo(pic.name, npx=pic.npx, nln=pic.nln)
            camera = Camera.from_picture(pic, settings)
        except (SpcError, OSError):
            skipped.append(row.name)
            continue
        pixel = (float(row.sample), float(row.line))
        if not all(math.isfinite(x) for x in pixel):
            pixel = None
        views.append(PictureView(row.name, photo, camera, pic.sz, tuple(float(x) for x in pic.thrsh), pixel))
    return views, skipped


def refine_maplet(root, name: str) -> dict:
    """Solve one maplet of the working directory ``root`` and write it when better (module docstring)."""
    from spctool.formats.landmark import write_lmk
    from spctool.formats.maplet import write_map
    from spctool.formats.workdir import WorkDir
    from spctool.stages.find_heights import FindHeightsOptions, find_heights, landmark_with, maplet_with

    wd = WorkDir(Path(root))
    out = {"name": name, "status": "failed", "written": False, "reason": ""}
    try:
        settings = wd.read_settings()
        lmk = wd.read_landmark(name)
        maplet = wd.read_maplet(lmk.name)
        views, skipped = landmark_views(wd, settings, lmk)
        result = find_heights(maplet, views, FindHeightsOptions())
    except SpcError as exc:
        out["reason"] = str(exc)
        return out
    before, after = result.mean_ncc() if result.ok else (math.nan, math.nan)
    out.update(status=result.status, reason=result.reason or "", ncc_before=before, ncc_after=after)
    out["skipped_pictures"] = skipped
    if result.ok and result.worse:
        out["status"] = "worse"
    elif result.ok:
        write_map(wd.map_path(lmk.name), maplet_with(maplet, result))
        write_lmk(wd.lmk_path(lmk.name), landmark_with(lmk, result))
        out["written"] = True
    return out


def refine_heights(root, names, *, jobs: int = 1) -> list[dict]:
    """:func:`refine_maplet` for every landmark of ``names`` (in order), on ``jobs`` local processes."""
    names = list(names)
    if jobs <= 1 or len(names) <= 1:
        return [refine_maplet(root, n) for n in names]
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from spctool.workers import start_method

    ctx = multiprocessing.get_context(start_method())
    with ProcessPoolExecutor(max_workers=int(jobs), mp_context=ctx) as pool:
        return list(pool.map(refine_maplet, [str(root)] * len(names), names))
