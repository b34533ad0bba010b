"""``correlate`` and ``register``: where each landmark really is in a photo.

Thin commands over :mod:`spctool.stages.register` (Stage H) and :mod:`spctool.stages.correlate`
(Stages F–G).  Both load the picture (SUM), INIT_LITHOS (distortion model), the photo (IMAGEFILES/ or
``--photo``), each landmark's maplet (MAPFILES/<NAME>.MAP) and, when present, its LMK file (the VLM is
the landmark position of the AUTOREGISTER pose solve).

Landmarks come from positional names, ``--landmarks TABLE`` (its ``name`` column; its ``sample`` and
``line`` are the a-priori pixels unless ``--project``) or, with neither, from Stage A
(:func:`spctool.stages.select.select_maplets`) on LMRKLIST.TXT / LMKFILES/.  Without a table pixel the
a-priori pixel is the projection of V with the SUM camera.

``correlate`` runs one correlation at one spacing; ``--out-dir`` writes each surface as an image
(``<LANDMARK>_<PICTURE>_surface.<ext>``: PGM/PNG map ρ ∈ [−1, 1] to 0…255, NaN to 0; FITS keeps the
float values).  ``register`` runs a whole schedule; ``--write-sum`` rewrites only the SUM's LANDMARKS
section (atomic, ``.bak`` kept); ``--overlay`` draws a-priori and measured pixels on the photo.
"""

from __future__ import annotations

import math
from pathlib import Path

import click
import numpy as np

from spctool import __version__
from spctool.cli import options
from spctool.cli.common import Context, emit_table, load_stage_inputs, pass_context, progress
from spctool.errors import SpcFormatError, SpcResultError, SpcUsageError

# ------------------------------------------------------------------------------------------------
# options shared by both commands


_shared_options = options.option_group(
    options.picture_argument,
    options.landmark_names_argument,
    options.landmarks_table_option(
        "Landmarks and a-priori pixels from a landmark table ('-' = stdin), e.g. the output of "
        "lithos-select. Default: the named LANDMARKs, else run lithos-select on LMRKLIST.TXT / LMKFILES/."
    ),
    click.option(
        "--project",
        "project",
        is_flag=True,
        help="Start from the projection of each landmark with the SUM pose, not the table pixels.",
    ),
    options.sum_option,
    options.photo_option(),
    options.flip_rows_option,
    options.space_option,
    click.option(
        "--grid-half",
        type=click.IntRange(min=1),
        default=5,
        show_default=True,
        metavar="K",
        help="Correlation grid of (2K+1)^2 whole-cell offsets (search +-K x spacing).",
    ),
    click.option(
        "--min-valid",
        type=click.IntRange(min=2),
        default=25,
        show_default=True,
        metavar="N",
        help="Fewer (binned) pixels valid in both images leave an offset undefined.",
    ),
    options.corr_min_option,
    click.option(
        "--strict-8",
        "strict_8",
        is_flag=True,
        help="A peak needs all 8 neighbours lower (default: the 4 along the axes).",
    ),
    options.photometry_option,
    options.shadows_option,
    options.linearized_option,
    options.no_filter_option,
    options.criteria_option(
        "Removal criteria on the first extraction: lithos_standard, autoregister or "
        "'INVLIM,SLIM,CLIM,[ILIM,]RSMN,RSMX'; 'none' = no removal. Default: none for correlate "
        "and the S16 schedule, autoregister (0,50,.25,0,5) for the AUTOREGISTER schedule."
    ),
    options.thresholds_option,
    click.option(
        "--supersample",
        type=click.IntRange(1, 16),
        default=2,
        show_default=True,
        metavar="N",
        help="Image space: NxN rays per template pixel.",
    ),
    click.option(
        "--no-image-shadows",
        "no_image_shadows",
        is_flag=True,
        help="Image space: leave shadowed pixels out instead of correlating them as dark.",
    ),
    click.option(
        "--template-shading",
        type=click.Choice(["smooth", "facet"]),
        default="smooth",
        show_default=True,
        help="Image space: template normals from interpolated node slopes (smooth) or flat triangles, "
        "two per maplet cell (facet).",
    ),
    options.out_dir_option("Write each landmark's (last) correlation surface as an image to DIR."),
    options.image_format_option,
    options.json_option,
    options.output_option,
    pass_context,
)


def _criteria(text, default):
    if text is None:
        return default
    if text.strip().lower() == "none":
        return None
    return text


def _parse_steps(text):
    """'10,9,8' or '2,1,drop:0.5,1' → [('align', 10), …, ('drop', 0.5), …]."""
    steps = []
    for tok in [t for t in text.replace(" ", ",").split(",") if t]:
        low = tok.lower()
        try:
            if low.startswith("drop"):
                value = low[4:].lstrip(":=")
                steps.append(("drop", float(value)))
            else:
                steps.append(("align", int(tok)))
        except ValueError:
            raise SpcUsageError(
                f"--steps: cannot read {tok!r} (use spacings like 10,9,1 and drop:RHO)"
            ) from None
    if not steps:
        raise SpcUsageError("--steps is empty")
    return tuple(steps)


def _register_options(kw, schedule, **extra):
    from spctool.stages.register import RegisterOptions

    default_criteria = (
        "autoregister" if schedule == "autoregister" and kw.get("_command") == "register" else None
    )
    popts, eopts = options.predict_extract_options(kw, criteria=_criteria(kw["criteria"], default_criteria))
    return RegisterOptions(
        schedule=schedule,
        space=kw["space"],
        corr_min=kw["corr_min"],
        grid_half=kw["grid_half"],
        min_valid=kw["min_valid"],
        strict_8=kw["strict_8"],
        supersample=kw["supersample"],
        image_shadows=not kw["no_image_shadows"],
        template_shading=kw["template_shading"],
        predict=popts,
        extract=eopts,
        **extra,
    )


# ------------------------------------------------------------------------------------------------
# inputs


class _Inputs:
    """Picture, camera, photo and the landmarks (maplets, positions, a-priori pixels) of one run."""

    def __init__(self, ctx: Context, kw):
        wd = ctx.wd
        inputs = load_stage_inputs(ctx, kw)
        self.sum_path, self.pic, self.camera = inputs.picture.path, inputs.picture.pic, inputs.picture.camera
        self.thresholds, self.photo, self.source = inputs.thresholds, inputs.photo, inputs.source
        self.names, self.maplets, self.positions, self.apriori, self.missing = [], [], [], [], []
        for name, pix in inputs.landmarks:
            try:
                maplet = wd.read_maplet(name)
            except SpcFormatError as exc:
                ctx.note_once(f"{name}: no maplet ({exc})")
                self.missing.append(name)
                continue
            pos = np.asarray(maplet.v, dtype=np.float64)
            has_lmk = wd.lmk_path(name).exists()
            if has_lmk:
                pos = np.asarray(wd.read_landmark(name).vlm, dtype=np.float64)
            self.names.append(name)
            self.maplets.append(maplet)
            self.positions.append(pos)
            if pix is not None and not kw["project"]:
                self.apriori.append(pix)
            elif has_lmk and bool(self.camera.in_front(pos)):
                # the LMK VLM projected with the SUM camera (without an LMK: the MAP's V, in the stage)
                self.apriori.append(tuple(float(x) for x in self.camera.project(pos)))
            else:
                self.apriori.append((math.nan, math.nan))
        self.apriori = np.asarray(self.apriori, dtype=np.float64).reshape(-1, 2)
        self.positions = np.asarray(self.positions, dtype=np.float64).reshape(-1, 3)


# ------------------------------------------------------------------------------------------------
# images


def surface_to_8bit(surface) -> np.ndarray:
    """ρ ∈ [−1, 1] → 0…255 (NaN → 0)."""
    s = np.asarray(surface, dtype=np.float64)
    return np.where(np.isfinite(s), np.clip(np.rint((np.nan_to_num(s) + 1.0) * 127.5), 0, 255), 0).astype(
        np.uint8
    )


def _write_surface(out_dir: Path, fmt: str, name: str, picture: str, step, space: str) -> Path:
    from spctool.formats.photo import write_photo

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
        write_photo(path, np.asarray(corr.surface, dtype=np.float64), fmt="fits", header=hdr)
    else:
        write_photo(path, surface_to_8bit(corr.surface), fmt=fmt)
    return path


def render_overlay(photo_data, thrsh, names, apriori, measured, ok) -> bytes:
    """PNG bytes: the photo stretched to 8 bits, a-priori pixels as yellow crosses, measured ones as green
    crosses joined to them (red X where registration failed), with the landmark names."""
    import io

    from PIL import Image, ImageDraw

    from spctool.cli.select import stretch_8bit

    gray = stretch_8bit(photo_data, thrsh)
    img = Image.fromarray(np.repeat(gray[:, :, None], 3, axis=2), mode="RGB")
    draw = ImageDraw.Draw(img)
    yellow, green, red = (255, 210, 0), (60, 230, 60), (255, 60, 60)
    for k, name in enumerate(names):  # PIL draws one primitive at a time
        a = apriori[k] - 1.0  # SPC 1-based → PIL 0-based
        if not np.all(np.isfinite(a)):
            continue
        draw.line([(a[0] - 4, a[1]), (a[0] + 4, a[1])], fill=yellow)
        draw.line([(a[0], a[1] - 4), (a[0], a[1] + 4)], fill=yellow)
        if ok[k] and np.all(np.isfinite(measured[k])):
            m = measured[k] - 1.0
            draw.line([(a[0], a[1]), (m[0], m[1])], fill=green)
            draw.line([(m[0] - 4, m[1]), (m[0] + 4, m[1])], fill=green)
            draw.line([(m[0], m[1] - 4), (m[0], m[1] + 4)], fill=green)
            colour = green
        else:
            draw.line([(a[0] - 3, a[1] - 3), (a[0] + 3, a[1] + 3)], fill=red)
            draw.line([(a[0] - 3, a[1] + 3), (a[0] + 3, a[1] - 3)], fill=red)
            colour = red
        draw.text((float(a[0]) + 5.0, float(a[1]) - 12.0), name, fill=colour)
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()


def _missing_rows(names, columns):
    rows = []
    for n in names:
        row = {c: math.nan for c in columns}
        row.update({"name": n, "status": "no-maplet"})
        for c in ("iterations", "spacing"):
            if c in row:
                row[c] = 0
        rows.append(row)
    return rows


# ------------------------------------------------------------------------------------------------
# correlate


@click.command("correlate")
@_shared_options
@click.option(
    "--spacing",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    metavar="N",
    help="Bin both images by NxN and correlate over +-K bins (search +-K x N cells).",
)
def correlate_cmd(ctx: Context, **kw):
    """One correlation of each landmark: offset, peak and peak quality.

    Maplet space (default): the prediction (SPC illumination, one view vector, dark only where the
    incidence exceeds 90 deg) is correlated with the photo resampled onto the maplet with the landmark
    at its a-priori pixel.  Both images are binned by --spacing N (same phase, anchored at the centre
    node); the normalised cross-correlation (Pearson, with the square root L15 Eq. 3.58 lacks) is taken
    over the (2K+1)^2 grid of whole-bin offsets, counting only cells valid in both images.  The peak is
    refined by one parabola per axis (the corrected L15 Eq. 3.65) and checked: edge-peak (on the grid
    border), not-found (a neighbour not lower, or no defined value), low-correlation (below
    --corr-min).  Image space: the maplet rendered into the photo (cast shadows) is correlated with the
    photo itself, offsets in pixels.

    Columns: name, sample and line (the a-priori pixel used), offset_x and offset_y (maplet cells along
    UX and UY; image space: pixels along line and sample), dsample and dline (the implied pixel shift,
    J_xy times the offset in maplet space), measured_sample, measured_line, correlation (peak), spacing,
    status (ok, not-found, edge-peak, low-correlation, outside, removed-<criterion>, no-maplet).

    Example:

    \b
      spctool -C WORKDIR correlate P600127001 --landmarks sel.txt --spacing 2
      spctool -C WORKDIR correlate P600127001 FC0098 --out-dir surf/ --image-format fits --json
    """
    from spctool.formats.table import LandmarkTable
    from spctool.stages.register import Registrar

    kw["_command"] = "correlate"
    inp = _Inputs(ctx, kw)
    opts = _register_options(kw, "retina_s16", steps=(("align", kw["spacing"]),))
    reg = Registrar(inp.photo, inp.pic.sz, inp.maplets, inp.thresholds, opts, inp.names)
    proj, usable = reg.project(inp.camera)
    start = np.where(np.isfinite(inp.apriori), inp.apriori, proj) if len(inp.names) else proj
    out_dir = Path(kw["out_dir"]) if kw["out_dir"] else None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
    columns = [
        "name",
        "sample",
        "line",
        "offset_x",
        "offset_y",
        "dsample",
        "dline",
        "measured_sample",
        "measured_line",
        "correlation",
        "spacing",
        "status",
    ]
    rows, written = [], 0
    with progress(ctx, f"correlate {inp.pic.name}", len(reg)) as advance:
        for i, name in enumerate(inp.names):
            row = {
                "name": name,
                "sample": float(start[i, 0]),
                "line": float(start[i, 1]),
                "spacing": int(kw["spacing"]),
            }
            if not usable[i] and not np.all(np.isfinite(inp.apriori[i])):
                row.update(
                    {
                        "offset_x": math.nan,
                        "offset_y": math.nan,
                        "dsample": math.nan,
                        "dline": math.nan,
                        "measured_sample": math.nan,
                        "measured_line": math.nan,
                        "correlation": math.nan,
                        "status": "outside",
                    }
                )
                rows.append(row)
                advance()
                continue
            st = reg.step(i, inp.camera, start[i], int(kw["spacing"]), apply_criteria=True)
            reg.release(i)
            shift = st.shift if st.status in ("ok", "low-correlation", "edge-peak") else np.full(2, np.nan)
            row.update(
                {
                    "offset_x": float(st.correlation.offset[0]),
                    "offset_y": float(st.correlation.offset[1]),
                    "dsample": float(shift[0]),
                    "dline": float(shift[1]),
                    "measured_sample": float(st.center[0] + shift[0]),
                    "measured_line": float(st.center[1] + shift[1]),
                    "correlation": float(st.correlation.peak),
                    "status": st.status,
                }
            )
            rows.append(row)
            if out_dir is not None:
                _write_surface(out_dir, kw["image_format"], name, inp.pic.name, st, opts.space)
                written += 1
            advance()
    rows += _missing_rows(inp.missing, columns)
    meta = {
        "landmark_source": inp.source,
        "space": opts.space,
        "spacing": int(kw["spacing"]),
        "thresholds": list(inp.thresholds),
        "options": opts.as_dict(),
        "images_written": written,
        "out_dir": None if out_dir is None else str(out_dir),
    }
    table = (
        LandmarkTable.from_rows(
            [{c: r[c] for c in columns} for r in rows], picture=inp.pic.name, command="correlate", meta=meta
        )
        if rows
        else LandmarkTable({c: [] for c in columns}, picture=inp.pic.name, command="correlate", meta=meta)
    )
    if out_dir is not None:
        table.comments.append(f"{written} correlation surfaces written to {out_dir}")
    emit_table(table, as_json=kw["as_json"], output=kw["output"])


# ------------------------------------------------------------------------------------------------
# register


@click.command("register")
@_shared_options
@click.option(
    "--schedule",
    type=click.Choice(["s16", "retina_s16", "autoregister"]),
    default="s16",
    show_default=True,
    help="s16: per landmark, spacings 10..1, no pose update (S16); autoregister: all landmarks at "
    "spacing 2, then 1, drop below 0.5, then 1, with a pose solve after each pass (SPC).",
)
@click.option(
    "--steps",
    default=None,
    metavar="LIST",
    help="Replace the schedule's steps, e.g. '10,8,6,4,2,1' or '2,1,drop:0.5,1'.",
)
@click.option(
    "--drop-corr",
    type=float,
    default=None,
    metavar="RHO",
    help="AUTOREGISTER's removal cut between the passes.  [default: 0.5]",
)
@click.option(
    "--no-fail-fast",
    "no_fail_fast",
    is_flag=True,
    help="S16 schedule: keep going after a failed step (default: stop the landmark).",
)
@click.option(
    "--no-pose-update",
    "no_pose_update",
    is_flag=True,
    help="AUTOREGISTER schedule: no pose solve between passes (each landmark carries its own shift).",
)
@click.option(
    "--halve-shift", is_flag=True, help="Apply half of every measured shift (Align landmarks option 1)."
)
@click.option(
    "--write-sum",
    "write_sum_flag",
    is_flag=True,
    help="Rewrite the SUM's LANDMARKS section with the registered pixels (atomic, SUM.bak kept); "
    "other lines are left byte for byte.",
)
@click.option(
    "--drop-failed",
    is_flag=True,
    help="With --write-sum: also remove the LANDMARKS rows of landmarks that failed.",
)
@options.overlay_option("Write the photo with a-priori (yellow) and measured (green) landmark pixels (PNG).")
@options.require_option("Exit 1 when fewer than N landmarks are registered.")
def register_cmd(ctx: Context, **kw):
    """Measure the landmarks of a picture: iterated predict, extract and correlate.

    Schedule s16 (default; S16's template-matching loop): for each landmark, starting at its a-priori
    pixel, correlate at spacing L = 10, 9, ..., 1 (search +-5L cells, acceptance rho >= 0.3) and move
    the pixel by J_xy times the offset (L15 Eq. 3.67, S16 Eq. 19) after each step; the pose is not
    changed.  Schedule autoregister (SPC's AUTOREGISTER seed): removal criteria 0,50,.25,0,5 on the
    first pass, then all landmarks at spacing 2, a pose solve, spacing 1, a pose solve, landmarks with
    rho < 0.5 dropped, spacing 1 and a last pose solve; each pass re-predicts and re-extracts with the
    updated pose.  --space image correlates the maplet rendered into the photo (with cast shadows)
    against the photo itself, so the search is not limited by the maplet's extent (S16 Retina).

    Columns: name, sample and line (the measured pixel when ok, else the a-priori pixel),
    apriori_sample, apriori_line, dsample and dline (measured minus a-priori), correlation (last
    peak), iterations (correlations run), spacing (of the last one), status (ok, not-found, edge-peak,
    low-correlation, outside, removed-<criterion>, no-maplet).  The table feeds solve-pose directly
    (only ok rows are used).  With --write-sum the ok landmarks are written to the SUM's LANDMARKS
    section (rows of other landmarks are kept unless --drop-failed).

    Example:

    \b
      spctool -C WORKDIR lithos-select P600127001 > sel.txt
      spctool -C WORKDIR register P600127001 --landmarks sel.txt > reg.txt
      spctool -C WORKDIR register P600127001 --schedule autoregister --write-sum --overlay reg.png
      spctool -C WORKDIR register P600127001 FC0098 --space image --json
    """
    from spctool.stages.register import RegisterOptions
    from spctool.stages.register import register as run_register

    kw["_command"] = "register"
    schedule = options.register_schedule(kw["schedule"])
    extra = {
        "fail_fast": not kw["no_fail_fast"],
        "pose_update": not kw["no_pose_update"],
        "halve_shift": kw["halve_shift"],
    }
    if kw["steps"]:
        extra["steps"] = _parse_steps(kw["steps"])
    if kw["drop_corr"] is not None:
        seed = RegisterOptions.__dataclass_fields__["autoregister_steps"].default
        extra["autoregister_steps"] = tuple(
            ("drop", kw["drop_corr"]) if k == "drop" else (k, v) for k, v in seed
        )
    opts = _register_options(kw, schedule, **extra)
    inp = _Inputs(ctx, kw)
    with progress(
        ctx, f"register {inp.pic.name}", None if schedule == "autoregister" else len(inp.names)
    ) as adv:
        result = run_register(
            inp.photo,
            inp.camera,
            inp.pic.sz,
            inp.maplets,
            inp.thresholds,
            opts,
            apriori=inp.apriori,
            names=inp.names,
            positions=inp.positions,
            prior_sigma_position=inp.pic.sigma_vso,
            prior_sigma_attitude=inp.pic.sigma_ptg,
            progress=adv,
        )
    for w in result.warnings:
        ctx.note_once(w)

    out_dir = Path(kw["out_dir"]) if kw["out_dir"] else None
    written = 0
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        for name, st in zip(result.names, result.last_steps):
            if st is not None:
                _write_surface(out_dir, kw["image_format"], name, inp.pic.name, st, opts.space)
                written += 1
    meta = {
        "landmark_source": inp.source,
        "schedule": schedule,
        "space": opts.space,
        "thresholds": list(inp.thresholds),
        "status_counts": result.status_counts(),
        "registered": int(result.ok.sum()),
        "passes": result.passes,
        "options": opts.as_dict(),
        "warnings": list(result.warnings),
    }
    if result.pose is not None:
        meta["pose"] = result.pose.pose_dict()
    table = result.to_table(picture=inp.pic.name, command="register", meta=meta)
    if inp.missing:
        from spctool.formats.table import LandmarkTable

        rows = table.rows() + _missing_rows(inp.missing, list(table.columns))
        table = (
            LandmarkTable.from_rows(rows, picture=inp.pic.name, command="register", meta=meta)
            if rows
            else table
        )
    table.comments.append(
        f"registered {int(result.ok.sum())} of {len(result) + len(inp.missing)} landmarks "
        f"({schedule}, {opts.space} space)"
    )
    emit_table(table, as_json=kw["as_json"], output=kw["output"])

    if kw["write_sum_flag"]:
        path = _write_sum(kw, inp, result)
        ctx.info(f"rewrote the LANDMARKS section of {path}")
    if kw["overlay"]:
        from spctool.formats import atomic

        atomic.write_bytes(
            kw["overlay"],
            render_overlay(
                inp.photo.data, inp.pic.thrsh, result.names, result.apriori, result.measured, result.ok
            ),
        )
        ctx.info(f"wrote {kw['overlay']}")
    if kw["require"] is not None and int(result.ok.sum()) < kw["require"]:
        raise SpcResultError(
            f"{inp.pic.name}: {int(result.ok.sum())} landmarks registered, fewer than "
            f"--require {kw['require']}"
        )


def _write_sum(kw, inp, result):
    """Update the SUM's LANDMARKS rows (new pixels for ok landmarks, added when absent); write atomically
    with a backup.  Only LANDMARKS lines change (formats.sumfile rewrites changed lines only)."""
    from spctool.formats.sumfile import read_sum, with_measured_landmarks, write_sum

    path = inp.sum_path
    pic = with_measured_landmarks(
        read_sum(path), result.names, result.measured, result.ok, drop_failed=kw["drop_failed"]
    )
    write_sum(path, pic, overwrite=True, backup=True)
    return path


def register(cli):
    cli.add_command(correlate_cmd)
    cli.add_command(register_cmd)
