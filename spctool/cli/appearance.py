"""``predict`` and ``extract``: maplet appearance and the photo resampled onto the maplet.

Thin commands over :mod:`spctool.stages.predict` (Stage B) and :mod:`spctool.stages.extract`
(Stages C–E).  Both commands load the picture (SUM), INIT_LITHOS (distortion model), the photo
(IMAGEFILES/ or ``--photo``) and each landmark's maplet (MAPFILES/<NAME>.MAP), run extraction and
prediction for every landmark, print one landmark-table row per landmark (cli-contract.md) and, with
``--out-dir``, write the predicted (``predict``) or extracted (``extract``) maplet images.

Landmarks come from positional names, ``--landmarks TABLE`` (its ``name`` column) or, with neither,
from running Stage A (:func:`spctool.stages.select.select_maplets`) on LMRKLIST.TXT / LMKFILES/.

Image files are ``<OUT-DIR>/<LANDMARK>_<PICTURE>_predicted.<ext>`` / ``…_extracted.<ext>``; array
axis 0 (UX, ≈ South) runs down the image and axis 1 (UY, ≈ East) across, so North is up.  PGM and
PNG are 8-bit, linearly scaled so the image maximum is 255 (0 = no data / dark); FITS holds the
float64 values with the landmark, picture and stage parameters in the header.  ``--sheet FILE.png``
puts every landmark's image on one page, enlarged (:func:`spctool.figures.contact_sheet`).
"""

from __future__ import annotations

import math
from pathlib import Path

import click
import numpy as np

from spctool import __version__
from spctool.cli import options
from spctool.cli.common import Context, emit_table, load_stage_inputs, pass_context, progress
from spctool.errors import SpcFormatError

# ------------------------------------------------------------------------------------------------
# options of both commands


_common_options = options.option_group(
    options.picture_argument,
    options.landmark_names_argument,
    options.landmarks_table_option(
        "Landmarks from the 'name' column of a landmark table ('-' = stdin). Default: the named "
        "LANDMARKs, else run lithos-select on LMRKLIST.TXT / LMKFILES/."
    ),
    options.sum_option,
    options.any_picture_option,
    options.photo_option(),
    options.flip_rows_option,
    click.option(
        "--at-table-pixels",
        is_flag=True,
        help="Place each landmark centre at the table's sample/line (e.g. a register result) "
        "instead of its projection with the SUM pose.",
    ),
    options.out_dir_option("Write one image per landmark to DIR (created if needed). Default: no images."),
    options.image_format_option,
    options.image_zoom_option,
    click.option(
        "--sheet",
        "sheet",
        metavar="FILE.png",
        type=click.Path(dir_okay=False),
        default=None,
        help="Write every landmark's image on one page, enlarged (nearest neighbour) and captioned with "
        "its name, correlation and status (PNG; no-data cells dark red).",
    ),
    options.predict_options,
    options.extract_options,
    options.json_option,
    options.output_option,
    pass_context,
)


def _table_pixel(pix, source):
    """The landmark centre --at-table-pixels uses: a table row's finite sample/line, else None (the
    selection's predicted pixels are not table pixels)."""
    if source == "selection" or pix is None or not all(map(math.isfinite, pix)):
        return None
    return pix


# ------------------------------------------------------------------------------------------------
# images


def _to_8bit(image) -> np.ndarray:
    a = np.asarray(image, dtype=np.float64)
    top = float(np.max(a)) if a.size else 0.0
    if not top > 0.0:
        return np.zeros(a.shape, dtype=np.uint8)
    return np.clip(np.rint(np.where(a > 0.0, a, 0.0) * (255.0 / top)), 0, 255).astype(np.uint8)


def _fits_header(row: dict, stage: str, maplet, popts, eopts, thresholds) -> dict:
    hdr = {
        "LANDMARK": (row["name"], "landmark (maplet) name"),
        "PICTURE": (row["picture"], "SPC picture name"),
        "STAGE": (stage, "spctool stage of this image"),
        "SPCTVER": (__version__, "spctool version"),
        "AXIS1": ("UY", "array axis 1 (FITS NAXIS1) runs along maplet UY (I, ~East)"),
        "AXIS2": ("UX", "array axis 0 (FITS NAXIS2) runs along maplet UX (J, ~South)"),
        "SCALE": (float(maplet.scale), "maplet scale, km per cell"),
        "QSZ": (int((np.asarray(maplet.heights).shape[0] - 1) // 2), "maplet half-size, cells"),
        "SAMPLE": (row["sample"], "pixel of the landmark centre used (SPC, 1-based)"),
        "LINE": (row["line"], "pixel of the landmark centre used (SPC, 1-based)"),
        "PHOTOMET": (popts.photometry, "illumination law"),
        "SHADOWS": (popts.shadows, "prediction shadow model"),
        "ALPHA0": (popts.alpha0_deg, "beta = exp(-phase/alpha0), degrees"),
        "BGCORMIN": (popts.bg_corr_min, "background fit threshold"),
        "LAMBDA": (row["lambda"], "brightness scale"),
        "PHI": (row["phi"], "brightness background"),
        "CORR": (row["correlation"], "zero-offset correlation"),
        "EMISSION": (row["emission"], "deg, landmark-to-camera vs UZ"),
        "INCIDENC": (row["incidence"], "deg, Sun vs UZ"),
        "PHASE": (row["phase"], "deg"),
        "THRSH1": (float(thresholds[0]), "lowest DN used"),
        "THRSH2": (float(thresholds[1]), "highest DN used"),
        "LINEARIZ": (bool(eopts.linearized), "linearised projection about V"),
        "FILTER": (bool(eopts.apply_filter), "extract filter applied"),
        "DSMODE": (eopts.ds_mode, "shadow extension formula"),
        "COV": (row["cov"], "fraction of nodes covered by the photo"),
        "ILL": (row["ill"], f"fraction of nodes lit ({eopts.ill_source})"),
        "RES": (row["res"], "image pixel / maplet scale"),
        "INV": (row["inv"], "invisible removals, per mille"),
        "DETJ": (row["det_j"], "det of d(sample,line)/d(x,y), px per cell"),
        "DS": (row["ds"], "shadow extension, cells"),
        "SUBSAMP": (row["subsample"], "samples per cell axis"),
        "CRITERIA": ("none" if eopts.criteria is None else eopts.criteria.text(), "removal criteria"),
        "STATUS": (row["status"], "ok or removed-<criterion>"),
    }
    out = {}
    for k, (v, comment) in hdr.items():
        if isinstance(v, (float, np.floating)):
            if not math.isfinite(float(v)):
                continue
            v = float(v)
        elif isinstance(v, (np.integer,)):
            v = int(v)
        out[k] = (v, comment)
    return out


def _write_image(
    out_dir: Path, fmt: str, stage: str, row: dict, image, maplet, popts, eopts, thresholds, zoom: int = 1
):
    from spctool.formats.photo import write_photo

    path = out_dir / f"{row['name']}_{row['picture']}_{stage}.{fmt}"
    if fmt == "fits":
        write_photo(
            path,
            np.asarray(image, dtype=np.float64),
            fmt="fits",
            header=_fits_header(row, stage, maplet, popts, eopts, thresholds),
            backup=True,  # an image already there is kept as .bak
        )
    else:
        k = int(zoom)
        write_photo(path, np.repeat(np.repeat(_to_8bit(image), k, axis=0), k, axis=1), fmt=fmt, backup=True)
    return path


# ------------------------------------------------------------------------------------------------
# the shared driver


_NAN_COLUMNS = (
    "lambda",
    "phi",
    "correlation",
    "emission",
    "incidence",
    "phase",
    "cov",
    "ill",
    "res",
    "det_j",
)


def _appearance(row: dict, maplet, camera, sun, photo, thresholds, popts, eopts, center):
    """One landmark's prediction and (with a photo) extraction, its table columns put in ``row``:
    the pixels, the brightness fit, the angles and the extraction's figures (or, without a photo,
    the prediction's lit fraction and the resolution from the camera's Jacobian).  Returns
    ``(prediction, extraction or None, in front of the camera)``."""
    from spctool.geometry import heightfield
    from spctool.geometry.frames import unit_vector
    from spctool.stages.extract import extract
    from spctool.stages.predict import predict

    sl = heightfield.slopes(maplet.heights, maplet.valid)
    pred0 = None
    if eopts.ill_source == "predicted":
        pred0 = predict(maplet, camera.position, sun, popts, slopes=sl)
    ext = None
    if photo is not None:
        ext = extract(photo, maplet, camera, sun, thresholds, eopts, center, slopes=sl, prediction=pred0)
    pred = predict(maplet, camera.position, sun, popts, extracted=ext, slopes=sl)
    ps, pl = camera.project(np.asarray(maplet.v, float))
    uz = unit_vector(maplet.uz, "UZ")
    emission = math.degrees(math.acos(min(1.0, max(-1.0, float(pred.emission_vector @ uz)))))
    incidence = math.degrees(math.acos(min(1.0, max(-1.0, float(sun @ uz)))))
    front = bool(camera.in_front(np.asarray(maplet.v, float)))
    cs = ext.center_sample if ext is not None else (center[0] if center else float(ps))
    cl = ext.center_line if ext is not None else (center[1] if center else float(pl))
    row.update(
        {
            "sample": cs,
            "line": cl,
            "predicted_sample": float(ps),
            "predicted_line": float(pl),
            "lambda": pred.lam,
            "phi": pred.phi,
            "correlation": pred.correlation,
            "emission": emission,
            "incidence": incidence,
            "phase": pred.alpha_deg,
        }
    )
    if ext is not None:
        row.update(
            {
                "cov": ext.cov,
                "ill": ext.ill,
                "res": ext.res,
                "inv": int(ext.inv),
                "det_j": ext.det_j,
                "ds": int(ext.ds),
                "subsample": int(ext.subsample),
                "status": ext.status,
            }
        )
    else:
        det_j = float(
            np.linalg.det(
                camera.jacobian_maplet(np.asarray(maplet.v, float), maplet.ux, maplet.uy, maplet.scale)
            )
        )
        row.update(
            {
                "cov": math.nan,
                "ill": pred.lit_fraction,
                "res": 1.0 / math.sqrt(abs(det_j)) if det_j else math.inf,
                "inv": -1,
                "det_j": det_j,
                "ds": -1,
                "subsample": -1,
                "status": "ok" if front else "outside",
            }
        )
    return pred, ext, front


def _run(ctx: Context, stage: str, kw: dict):
    from spctool.formats.table import LandmarkTable
    from spctool.geometry.frames import unit_vector
    from spctool.stages.predict import cast_shadow_note

    wd = ctx.wd
    inputs = load_stage_inputs(ctx, kw, photo_required=stage == "extracted")
    pic, camera = inputs.picture.pic, inputs.picture.camera
    photo, thresholds = inputs.photo, inputs.thresholds
    if photo is None:
        ctx.note_once("no photo: brightness fit skipped (lambda = 1, phi = 0)")
    popts, eopts = options.predict_extract_options(kw, criteria=None if kw["no_removal"] else kw["criteria"])
    out_dir = Path(kw["out_dir"]) if kw["out_dir"] else None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
    sun = unit_vector(pic.sz, "SUM SZ")

    rows = []
    written = 0
    tiles = []  # --sheet: (caption, image, valid)
    command = "predict" if stage == "predicted" else "extract"
    cast = []  # landmarks whose shadows="auto" became "cast"
    with progress(ctx, f"{command} {pic.name}", len(inputs.landmarks)) as advance:
        for name, pixel in inputs.landmarks:
            row = {"name": name, "picture": pic.name}
            try:
                maplet = wd.read_maplet(name)
            except SpcFormatError as exc:
                # a MAP there but unreadable fails only its landmark, said as a warning, not a note
                if wd.map_path(name).exists():
                    ctx.warn(f"{name}: no maplet: its MAP file is unreadable ({exc})")
                else:
                    ctx.note_once(f"{name}: no maplet ({exc})")
                row.update(
                    {
                        "sample": math.nan,
                        "line": math.nan,
                        "predicted_sample": math.nan,
                        "predicted_line": math.nan,
                        **dict.fromkeys(_NAN_COLUMNS, math.nan),
                        "inv": -1,
                        "ds": -1,
                        "subsample": -1,
                        "status": "no-maplet",
                    }
                )
                rows.append(row)
                advance()
                continue
            center = _table_pixel(pixel, inputs.source) if kw["at_table_pixels"] else None
            pred, ext, front = _appearance(row, maplet, camera, sun, photo, thresholds, popts, eopts, center)
            if not front:
                row["status"] = "outside"
            rows.append(row)
            if out_dir is not None and front:
                image = pred.image if stage == "predicted" else ext.image
                _write_image(
                    out_dir,
                    kw["image_format"],
                    stage,
                    row,
                    image,
                    maplet,
                    popts,
                    eopts,
                    thresholds,
                    kw["zoom"],
                )
                written += 1
            if kw["sheet"] and front:
                image, valid = (pred.image, pred.lit) if stage == "predicted" else (ext.image, ext.valid)
                tiles.append((f"{name} rho {row['correlation']:.2f} {row['status']}", image, valid))
            if popts.shadows == "auto" and pred.options.shadows == "cast":
                cast.append(name)
            advance()
    if cast:
        ctx.info(cast_shadow_note(cast, thresholds[0]))  # the default adapting to the photo: -v

    columns = [
        "name",
        "sample",
        "line",
        "predicted_sample",
        "predicted_line",
        "emission",
        "incidence",
        "phase",
        "lambda",
        "phi",
        "correlation",
        "cov",
        "ill",
        "res",
        "inv",
        "det_j",
        "ds",
        "subsample",
        "status",
    ]
    meta = {
        "landmark_source": inputs.source,
        "thresholds": list(thresholds),
        "predict_options": popts.as_dict(),
        "extract_options": eopts.as_dict(),
        "images_written": written,
        "out_dir": None if out_dir is None else str(out_dir),
    }
    table = LandmarkTable.from_rows(
        [{c: r[c] for c in columns} for r in rows], picture=pic.name, command=command, meta=meta
    )
    if not rows:
        table = LandmarkTable(
            columns={c: [] for c in columns}, picture=pic.name, command=table.command, meta=table.meta
        )
    if out_dir is not None:
        table.comments.append(f"{written} {stage} image{'' if written == 1 else 's'} written to {out_dir}")
    if kw["sheet"]:
        from spctool import figures

        title = f"{pic.name}  {stage} maplet images ({len(tiles)}), North up"
        dark = "not lit" if stage == "predicted" else "no data (off the photo, or below THRSH T1)"
        key = (
            "caption: landmark, rho = correlation of prediction and extraction at zero offset "
            f"(1: identical up to brightness), status; dark red: {dark}"
        )
        figures.contact_sheet(tiles, title=title, key=key).save(kw["sheet"])
        ctx.info(f"wrote {kw['sheet']}")
    emit_table(table, as_json=kw["as_json"], output=kw["output"])


# ------------------------------------------------------------------------------------------------
# commands


@click.command("predict")
@_common_options
def predict_cmd(ctx: Context, **kw):
    """Illuminated maplet images of a picture's landmarks, with the brightness fit.

    For each landmark the maplet is illuminated with one landmark-to-camera vector and the Sun vector of
    the SUM (Liounis 2015 sec. 3.3.1; Shoemaker et al. 2016 Eq. 12-17): normals from SPC's slope
    hierarchy, the chosen illumination law, dark only where the incidence exceeds 90 deg (--shadows cast
    adds ray-marched cast shadows).  When the photo is available it is extracted too (see 'spctool
    extract') and the brightness scale lambda = mean(extracted)/mean(predicted) is fitted over cells
    non-zero in both; phi (background) is fitted by least squares only when the zero-offset correlation
    exceeds --bg-corr-min.  Without a photo lambda = 1 and phi = 0.

    Columns: name, sample and line (pixel of the landmark centre used), predicted_sample and
    predicted_line (its projection with the SUM pose), emission, incidence, phase (degrees),
    lambda (brightness scale), phi (background), correlation (zero-offset rho between prediction
    and extraction), cov (fraction of maplet nodes inside the photo), ill (fraction of nodes lit),
    res (photo pixel size / maplet scale), inv (per mille of nodes removed as hidden or seen too
    obliquely), det_j (determinant of d(sample, line)/d(x, y), pixels per cell), ds (shadow
    extension, cells), subsample (samples per cell axis), status (ok, outside, no-maplet,
    removed-<criterion>); -1 or nan where a value needs the photo.

    With --out-dir DIR the predicted images are written as DIR/LANDMARK_PICTURE_predicted.pgm
    (or .png, .fits); North (-UX) is up and East (UY) to the right.

    Example:

    \b
      spctool -C demo predict P000000001A1 --landmarks sel.txt --out-dir pred/
      spctool -C demo predict P000000001A1 B01980 --shadows cast --image-format fits --out-dir pred/
    """
    _run(ctx, "predicted", kw)


@click.command("extract")
@_common_options
def extract_cmd(ctx: Context, **kw):
    """The photo resampled onto each landmark's maplet, filtered and judged.

    Every maplet node is projected with the full camera model (--linearized: the linearisation about the
    landmark of Shoemaker et al. 2016), the photo is sampled with SPC's BRT0 bilinear rule (DN outside
    the SUM THRSH are missing; one missing corner is repaired), averaging MxM samples per cell when
    cells are larger than pixels.  The extract filter then extends shadows away from the Sun by ds = 3 +
    floor(1/|det J|) cells (and 2 cells sideways), zeroes cells seen at cos(emission) < 0.05 and cells
    hidden by the terrain (ray march toward the camera).  COV, ILL, RES and INV are computed and the
    removal criteria (LITHOS 'INVLIM,SLIM,CLIM,ILIM,RSMN,RSMX', default 0,60,.25,.25,0,3) give the
    status.

    Columns: as for 'spctool predict'.  With --out-dir DIR the extracted images are written as
    DIR/LANDMARK_PICTURE_extracted.pgm (or .png, .fits).

    Example:

    \b
      spctool -C demo extract P000000001A1 --landmarks sel.txt --out-dir ext/ --image-format fits
      spctool -C demo extract P000000001A1 --criteria autoregister --json
      spctool -C demo extract P000000003A1 --photo IMAGEFILES/P000000003A1.FITS B01980 --criteria 0,50,.25,0,5
    """
    _run(ctx, "extracted", kw)


def register(cli):
    cli.add_command(predict_cmd)
    cli.add_command(extract_cmd)
