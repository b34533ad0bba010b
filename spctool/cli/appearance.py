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
float64 values with the landmark, picture and stage parameters in the header.
"""

from __future__ import annotations

import math
from pathlib import Path

import click
import numpy as np

from spctool import __version__
from spctool.cli.common import Context, emit_table, json_option, output_option, pass_context, progress
from spctool.errors import SpcFormatError, SpcUsageError

IMAGE_FORMATS = ("pgm", "png", "fits")


# ------------------------------------------------------------------------------------------------
# option groups


def _common_options(f):
    decorators = [
        click.argument("picture"),
        click.argument("names", nargs=-1, metavar="[LANDMARK]..."),
        click.option("--landmarks", "landmarks_table", metavar="TABLE",
                     type=click.Path(dir_okay=False, allow_dash=True),
                     help="Landmarks from the 'name' column of a landmark table ('-' = stdin). Default: the "
                          "named LANDMARKs, else run lithos-select on LMRKLIST.TXT / LMKFILES/."),
        click.option("--sum", "sum_path", metavar="FILE", type=click.Path(dir_okay=False),
                     help="The picture's SUM file (default: DIR/SUMFILES/PIC.SUM)."),
        click.option("--photo", "photo_path", metavar="FILE", type=click.Path(dir_okay=False, exists=True),
                     help="The photo (FITS, PGM, PNG or .DAT). Default: the picture's IMAGEFILES/ photo."),
        click.option("--flip-rows", is_flag=True,
                     help="The photo's rows are stored bottom-up: read line 1 from the last stored row."),
        click.option("--at-table-pixels", is_flag=True,
                     help="Place each landmark centre at the table's sample/line (e.g. a register result) "
                          "instead of its projection with the SUM pose."),
        click.option("--out-dir", type=click.Path(file_okay=False), default=None, metavar="DIR",
                     help="Write one image per landmark to DIR (created if needed). Default: no images."),
        click.option("--image-format", type=click.Choice(IMAGE_FORMATS), default="pgm", show_default=True,
                     help="Format of the --out-dir images (FITS keeps float values and a header)."),
        # Stage B
        click.option("--photometry", type=click.Choice(["spc", "mcewen", "fixed", "lambert"]), default="spc",
                     show_default=True,
                     help="Illumination law: SPC lunar-Lambert (no factor 2), McEwen, SPC form with fixed "
                          "beta, Lambert."),
        click.option("--beta", type=float, default=0.65, show_default=True, metavar="B",
                     help="Constant beta of --photometry fixed."),
        click.option("--alpha0", type=float, default=60.0, show_default=True, metavar="DEG",
                     help="beta = exp(-phase/alpha0)."),
        click.option("--shadows", type=click.Choice(["spc", "cast"]), default="spc", show_default=True,
                     help="spc: dark only where the incidence exceeds 90 deg; cast: also ray-marched cast "
                          "shadows over the maplet."),
        click.option("--bg-corr-min", type=float, default=1.0, show_default=True, metavar="RHO",
                     help="Fit the background phi when the zero-offset correlation exceeds RHO "
                          "(>= 1: never)."),
        # Stages C-E
        click.option("--linearized", is_flag=True,
                     help="Project nodes with the S16 linearisation about the landmark "
                          "(default: the full camera model)."),
        click.option("--subsample", default="auto", show_default=True, metavar="auto|M",
                     help="Average MxM samples per cell (auto: ceil(sqrt|det J|) when cells exceed pixels)."),
        click.option("--no-filter", "no_filter", is_flag=True,
                     help="Skip the extract filter (shadow enhancement, emission cut, visibility march)."),
        click.option("--ds-mode", type=click.Choice(["seed", "sqrt"]), default="seed", show_default=True,
                     help="Shadow extension ds = base + floor(1/|det J|) (seed) or floor(1/sqrt|det J|)."),
        click.option("--ds-base", type=click.IntRange(min=0), default=3, show_default=True, metavar="N",
                     help="Base shadow extension in cells."),
        click.option("--lateral", type=click.IntRange(min=0), default=2, show_default=True, metavar="N",
                     help="Lateral widening of the shadow extension in cells."),
        click.option("--cos-e-min", type=float, default=0.05, show_default=True, metavar="C",
                     help="Zero cells whose normal makes cos(emission) < C."),
        click.option("--vis-tol", type=float, default=0.05, show_default=True, metavar="CELLS",
                     help="Lowering of the visibility ray march."),
        click.option("--cast-shadow-trace", is_flag=True,
                     help="Also zero cells in cast shadow by a march toward the Sun (SPC skips it)."),
        click.option("--criteria", default="lithos_standard", show_default=True, metavar="SPEC",
                     help="Removal criteria: lithos_standard, autoregister, or "
                          "'INVLIM,SLIM,CLIM,ILIM,RSMN,RSMX' (5 values: AUTOREGISTER's form without ILIM)."),
        click.option("--no-removal", is_flag=True,
                     help="Report the statistics but never a removed-* status."),
        click.option("--ill-source", type=click.Choice(["extracted", "predicted"]), default="extracted",
                     show_default=True,
                     help="ILL counts non-zero cells of the extracted or predicted image."),
        click.option("--thresholds", default=None, metavar="T1,T2",
                     help="DN range used from the photo (default: the SUM THRSH)."),
        json_option,
        output_option,
        pass_context,
    ]
    for d in reversed(decorators):
        f = d(f)
    return f


def _thresholds(text, pic):
    if text is None:
        return tuple(float(x) for x in pic.thrsh)
    parts = [p for p in text.replace(",", " ").split() if p]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 2:
        raise SpcUsageError(f"--thresholds expects two numbers T1,T2, got {text!r}")
    return values


def _options(kw):
    from spctool.stages.extract import ExtractOptions
    from spctool.stages.predict import PredictOptions

    popts = PredictOptions(photometry=kw["photometry"], beta=kw["beta"], alpha0_deg=kw["alpha0"],
                           shadows=kw["shadows"], bg_corr_min=kw["bg_corr_min"])
    eopts = ExtractOptions(
        linearized=kw["linearized"], subsample=kw["subsample"], apply_filter=not kw["no_filter"],
        ds_mode=kw["ds_mode"], ds_base=kw["ds_base"], lateral=kw["lateral"], cos_e_min=kw["cos_e_min"],
        vis_tol=kw["vis_tol"], cast_shadow_trace=kw["cast_shadow_trace"],
        criteria=None if kw["no_removal"] else kw["criteria"], ill_source=kw["ill_source"],
    )
    return popts, eopts


# ------------------------------------------------------------------------------------------------
# landmarks


def _landmark_list(ctx: Context, names, table_path, camera, pic, settings):
    """[(name, table_pixel or None)] and a note about where they came from."""
    rows = []
    if table_path:
        from spctool.formats.table import read_table

        table = read_table(table_path)
        smp = table.get("sample")
        lin = table.get("line")
        for i, n in enumerate(table.names):
            pix = None
            if smp is not None and lin is not None:
                try:
                    pix = (float(smp[i]), float(lin[i]))
                except (TypeError, ValueError):
                    pix = None
                if pix is not None and not all(math.isfinite(x) for x in pix):
                    pix = None
            rows.append((n, pix))
    for n in names:
        rows.append((n, None))
    if rows:
        return rows, "given"
    from spctool.cli.select import load_candidates
    from spctool.stages.select import SelectOptions, select_maplets

    cand = load_candidates(ctx, (), None)
    if not len(cand):
        return [], "selection"
    result = select_maplets(camera, pic.sz, cand.centres, cand.ux, cand.uy, cand.uz, cand.scale, cand.qsz,
                            cand.names, SelectOptions.from_settings(settings), shape=None)
    ctx.info(f"lithos-select: {result.n_selected} of {len(result)} candidate maplets (occlusion not checked)")
    return [(n, None) for n, sel in zip(result.names, result.selected) if sel], "selection"


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
        "LINEARIZ": (bool(eopts.linearized), "S16 linearised projection"),
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


def _write_image(out_dir: Path, fmt: str, stage: str, row: dict, image, maplet, popts, eopts, thresholds):
    from spctool.formats.photo import write_photo

    path = out_dir / f"{row['name']}_{row['picture']}_{stage}.{fmt}"
    if fmt == "fits":
        write_photo(path, np.asarray(image, dtype=np.float64), fmt="fits",
                    header=_fits_header(row, stage, maplet, popts, eopts, thresholds))
    else:
        write_photo(path, _to_8bit(image), fmt=fmt)
    return path


# ------------------------------------------------------------------------------------------------
# the shared driver


_NAN_COLUMNS = ("lambda", "phi", "correlation", "emission", "incidence", "phase", "cov", "ill", "res",
                "det_j")


def _run(ctx: Context, stage: str, kw: dict):
    from spctool.formats.photo import read_photo
    from spctool.formats.table import LandmarkTable
    from spctool.geometry import heightfield
    from spctool.geometry.camera import Camera
    from spctool.stages.extract import extract
    from spctool.stages.predict import predict, unit_vector

    wd = ctx.wd
    pic = wd.read_picture(kw["sum_path"] if kw["sum_path"] else kw["picture"])
    settings = ctx.settings()
    camera = Camera.from_picture(pic, settings)
    popts, eopts = _options(kw)
    thresholds = _thresholds(kw["thresholds"], pic)

    photo = None
    if kw["photo_path"]:
        photo = read_photo(kw["photo_path"], flip_rows=kw["flip_rows"], npx=pic.npx, nln=pic.nln)
    elif wd.photo_path(pic.name) is not None:
        photo = wd.read_photo(pic.name, npx=pic.npx, nln=pic.nln, flip_rows=kw["flip_rows"])
    if photo is None:
        if stage == "extracted":
            raise SpcUsageError(f"no photo for picture {pic.name} (IMAGEFILES/{pic.name}.DAT not found; "
                                "give --photo)")
        ctx.note_once("no photo: brightness fit skipped (lambda = 1, phi = 0)")
    elif photo.data.shape != (pic.nln, pic.npx):
        raise SpcUsageError(f"the photo is {photo.npx} x {photo.nln} px but the SUM says "
                            f"{pic.npx} x {pic.nln}")

    landmarks, source = _landmark_list(ctx, kw["names"], kw["landmarks_table"], camera, pic, settings)
    out_dir = Path(kw["out_dir"]) if kw["out_dir"] else None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
    sun = unit_vector(pic.sz, "SUM SZ")

    rows = []
    written = 0
    command = "predict" if stage == "predicted" else "extract"
    with progress(ctx, f"{command} {pic.name}", len(landmarks)) as advance:
        for name, table_pixel in landmarks:
            row = {"name": name, "picture": pic.name}
            try:
                maplet = wd.read_maplet(name)
            except SpcFormatError as exc:
                ctx.note_once(f"{name}: no maplet ({exc})")
                row.update({"sample": math.nan, "line": math.nan, "predicted_sample": math.nan,
                            "predicted_line": math.nan, **dict.fromkeys(_NAN_COLUMNS, math.nan),
                            "inv": -1, "ds": -1, "subsample": -1, "status": "no-maplet"})
                rows.append(row)
                advance()
                continue
            center = table_pixel if kw["at_table_pixels"] else None
            sl = heightfield.slopes(maplet.heights, maplet.valid)
            pred0 = None
            if eopts.ill_source == "predicted":
                pred0 = predict(maplet, camera.position, sun, popts, slopes=sl)
            ext = None
            if photo is not None:
                ext = extract(photo, maplet, camera, sun, thresholds, eopts, center, slopes=sl,
                              prediction=pred0)
            pred = predict(maplet, camera.position, sun, popts, extracted=ext, slopes=sl)
            ps, pl = camera.project(np.asarray(maplet.v, float))
            uz = unit_vector(maplet.uz, "UZ")
            emission = math.degrees(math.acos(min(1.0, max(-1.0, float(pred.emission_vector @ uz)))))
            incidence = math.degrees(math.acos(min(1.0, max(-1.0, float(sun @ uz)))))
            front = bool(camera.in_front(np.asarray(maplet.v, float)))
            cs = ext.center_sample if ext is not None else (center[0] if center else float(ps))
            cl = ext.center_line if ext is not None else (center[1] if center else float(pl))
            row.update({
                "sample": cs, "line": cl, "predicted_sample": float(ps), "predicted_line": float(pl),
                "lambda": pred.lam, "phi": pred.phi, "correlation": pred.correlation,
                "emission": emission, "incidence": incidence, "phase": pred.alpha_deg,
            })
            if ext is not None:
                row.update({"cov": ext.cov, "ill": ext.ill, "res": ext.res, "inv": int(ext.inv),
                            "det_j": ext.det_j, "ds": int(ext.ds), "subsample": int(ext.subsample),
                            "status": ext.status})
            else:
                det_j = float(np.linalg.det(camera.jacobian_maplet(np.asarray(maplet.v, float), maplet.ux,
                                                                   maplet.uy, maplet.scale)))
                row.update({"cov": math.nan, "ill": pred.lit_fraction, "res": 1.0 / math.sqrt(abs(det_j))
                            if det_j else math.inf, "inv": -1, "det_j": det_j, "ds": -1, "subsample": -1,
                            "status": "ok" if front else "outside"})
            if not front:
                row["status"] = "outside"
            rows.append(row)
            if out_dir is not None and front:
                image = pred.image if stage == "predicted" else ext.image
                _write_image(out_dir, kw["image_format"], stage, row, image, maplet, popts, eopts, thresholds)
                written += 1
            advance()

    columns = ["name", "sample", "line", "predicted_sample", "predicted_line", "emission", "incidence",
               "phase", "lambda", "phi", "correlation", "cov", "ill", "res", "inv", "det_j", "ds",
               "subsample", "status"]
    meta = {"landmark_source": source, "thresholds": list(thresholds), "predict_options": popts.as_dict(),
            "extract_options": eopts.as_dict(), "images_written": written,
            "out_dir": None if out_dir is None else str(out_dir)}
    table = LandmarkTable.from_rows([{c: r[c] for c in columns} for r in rows], picture=pic.name,
                                    command=command, meta=meta)
    if not rows:
        table = LandmarkTable(columns={c: [] for c in columns}, picture=pic.name, command=table.command,
                              meta=table.meta)
    if out_dir is not None:
        table.comments.append(f"{written} {stage} images written to {out_dir}")
    emit_table(table, as_json=kw["as_json"], output=kw["output"])


# ------------------------------------------------------------------------------------------------
# commands


@click.command("predict")
@_common_options
def predict_cmd(ctx: Context, **kw):
    """Illuminated maplet images of a picture's landmarks, with the brightness fit.

    For each landmark the maplet is illuminated with one landmark-to-camera vector and the Sun
    vector of the SUM (L15 3.3.1, S16 Eq. 12-17): normals from SPC's slope hierarchy, the chosen
    illumination law, dark only where the incidence exceeds 90 deg (--shadows cast adds ray-marched
    cast shadows).  When the photo is available it is extracted too (see 'spctool extract') and the
    brightness scale lambda = mean(extracted)/mean(predicted) is fitted over cells non-zero in both;
    phi (background) is fitted by least squares only when the zero-offset correlation exceeds
    --bg-corr-min.  Without a photo lambda = 1 and phi = 0.

    Columns: name, sample and line (pixel of the landmark centre used), predicted_sample and
    predicted_line (its projection with the SUM pose), emission, incidence, phase (degrees),
    lambda, phi, correlation (zero offset), cov, ill, res, inv (per mille), det_j (pixels per
    cell), ds (shadow extension), subsample, status (ok, outside, no-maplet, removed-<criterion>).

    With --out-dir DIR the predicted images are written as DIR/LANDMARK_PICTURE_predicted.pgm
    (or .png, .fits); North (-UX) is up and East (UY) to the right.

    Example:

    \b
      spctool -C WORKDIR predict P600127001 --landmarks sel.txt --out-dir pred/
      spctool -C WORKDIR predict P600127001 FC0098 --shadows cast --image-format fits --out-dir pred/
    """
    _run(ctx, "predicted", kw)


@click.command("extract")
@_common_options
def extract_cmd(ctx: Context, **kw):
    """The photo resampled onto each landmark's maplet, filtered and judged.

    Every maplet node is projected with the full camera model (--linearized: S16's linearisation
    about the landmark), the photo is sampled with SPC's BRT0 bilinear rule (DN outside the SUM
    THRSH are missing; one missing corner is repaired), averaging MxM samples per cell when cells
    are larger than pixels.  The extract filter then extends shadows away from the Sun by
    ds = 3 + floor(1/|det J|) cells (and 2 cells sideways), zeroes cells seen at cos(emission)
    < 0.05 and cells hidden by the terrain (ray march toward the camera).  COV, ILL, RES and INV
    are computed and the removal criteria (LITHOS 'INVLIM,SLIM,CLIM,ILIM,RSMN,RSMX', default
    0,60,.25,.25,0,3) give the status.

    Columns: as for 'spctool predict'.  With --out-dir DIR the extracted images are written as
    DIR/LANDMARK_PICTURE_extracted.pgm (or .png, .fits).

    Example:

    \b
      spctool -C WORKDIR extract P600127001 --landmarks sel.txt --out-dir ext/ --image-format fits
      spctool -C WORKDIR extract P600127001 --criteria autoregister --json
      spctool extract PIC --sum PIC.SUM --photo PIC.fits FC0098 --criteria 0,50,.25,0,5
    """
    _run(ctx, "extracted", kw)


def register(cli):
    cli.add_command(predict_cmd)
    cli.add_command(extract_cmd)
