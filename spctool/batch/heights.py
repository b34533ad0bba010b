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

from spctool.errors import SpcError, SpcFormatError

__all__ = ["landmark_views", "refine_maplet", "refine_heights"]


def _sees(camera, pic, lmk) -> bool:
    """V in front of the camera, inside the photo, facing it and lit (both above the maplet plane)."""
    import numpy as np

    v = np.asarray(lmk.vlm, dtype=np.float64)
    uz = np.asarray(lmk.uz, dtype=np.float64)
    s, ln, front = camera.project_with_mask(v[None, :])
    e = np.asarray(camera.position, dtype=np.float64) - v
    return bool(front[0] and 1.0 <= s[0] < pic.npx and 1.0 <= ln[0] < pic.nln and e @ uz > 0.0
                and np.asarray(pic.sz, float) @ uz > 0.0)


def landmark_views(wd, settings, lmk, *, thresholds=None, note=None, warn=None):
    """(views, skipped names): a :class:`~spctool.stages.find_heights.PictureView` per PICTURES row of
    the LMK not flagged ``*`` (its pixel the a-priori centre), with the picture's SUM (finite pose
    checked), camera (the INIT_LITHOS ``settings``' DISTORT= model of that picture name) and photo
    (checked against the SUM's size).  An LMK without any PICTURES row tries every picture of
    PICTLIST.TXT (else SUMFILES/) whose camera sees V lit and facing it, pixel None (the projection).

    ``thresholds(pic)``: the (T1, T2) of a picture (default its SUM THRSH).  A picture left out is
    skipped, not an error: ``note(message)`` is told of one simply without a SUM or photo file,
    ``warn(message)`` (default: ``note``) of one whose SUM or photo exists but cannot be used (corrupt,
    truncated, unreadable, the wrong size), naming the file — the maplet is then solved without a
    picture it was meant to have, which must not pass unnoticed.
    The one builder of a maplet's views for ``spctool lithos`` and ``batch --lithos``.
    """
    from spctool.formats import guard
    from spctool.geometry.camera import Camera
    from spctool.stages.find_heights import PictureView

    say = note if note is not None else (lambda message: None)
    complain = warn if warn is not None else say
    explicit = bool(lmk.pictures)
    rows = [(r.name, (float(r.sample), float(r.line))) for r in lmk.pictures if r.flag != "*"]
    if not explicit:
        names = wd.picture_names()
        say(f"{lmk.name}: no PICTURES rows in its LMK: trying the {len(names)} pictures of PICTLIST.TXT "
            "that see it")
        rows = [(n, None) for n in names]
    views, skipped = [], []
    for name, pixel in rows:  # file reads per picture
        if not wd.sum_path(name).exists():
            say(f"{lmk.name}: picture {name} left out (no SUM file {wd.sum_path(name).name} in SUMFILES/)")
            skipped.append(name)
            continue
        try:
            pic = wd.read_picture(name)
            guard.check_sum_header(pic, wd.sum_path(name))
            camera = Camera.from_picture(pic, settings, picture_name=name)
            if not explicit and not _sees(camera, pic, lmk):
                continue
            if wd.photo_path(pic.name) is None:
                say(f"{lmk.name}: picture {name} left out (no photo in IMAGEFILES/)")
                skipped.append(name)
                continue
            photo = wd.read_photo(pic.name, npx=pic.npx, nln=pic.nln)
            if photo.data.shape != (pic.nln, pic.npx):
                raise SpcFormatError(wd.photo_path(pic.name), None, f"{pic.npx} x {pic.nln} px (the SUM's "
                                     f"size), found {photo.npx} x {photo.nln}")
            thr = tuple(float(x) for x in (pic.thrsh if thresholds is None else thresholds(pic)))
        except (SpcError, OSError) as exc:  # the file is there but cannot be used: a warning
            complain(f"{lmk.name}: picture {name} left out: its file cannot be used ({exc})")
            skipped.append(name)
            continue
        if pixel is not None and not all(math.isfinite(x) for x in pixel):
            pixel = None
        views.append(PictureView(name, photo, camera, pic.sz, thr, pixel))
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
        bad_files: list[str] = []
        views, skipped = landmark_views(wd, settings, lmk, warn=bad_files.append)
        result = find_heights(maplet, views, FindHeightsOptions())
    except SpcError as exc:
        out["reason"] = str(exc)
        return out
    out["warnings"] = bad_files  # pictures left out because their SUM or photo cannot be used
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
