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
section (atomic, ``.bak`` kept).  Figures (:mod:`spctool.figures`): ``register --overlay`` draws each
landmark's magnified shift on the photo; ``--panels DIR`` (both commands) writes predicted | extracted |
correlation surface per landmark; ``correlate --sheet`` puts every surface on one page.
"""

from __future__ import annotations

import math
from pathlib import Path

import click
import numpy as np

from spctool.cli import options
from spctool.cli.common import Context, emit_table, load_stage_inputs, pass_context, progress
from spctool.errors import SpcFormatError, SpcUsageError

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
    options.any_picture_option,
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
    click.option(
        "--peak",
        type=click.Choice(["quadric", "parabola", "gradient"]),
        default="quadric",
        show_default=True,
        help="Sub-pixel peak: least-squares 2-D quadric on the 3x3 neighbourhood (with the cross term), "
        "SPC's two 1-D parabolas (legacy runs; biased on tilted peaks) or gradient (least-squares "
        "alignment of the two images at the grid peak: exactly 0 when they agree).",
    ),
    options.photometry_option,
    options.shadows_option,
    options.linearized_option,
    options.no_filter_option,
    options.criteria_option(
        "Removal criteria on the first extraction: lithos_standard, autoregister or "
        "'INVLIM,SLIM,CLIM,[ILIM,]RSMN,RSMX'; 'none' = no removal. Default: none for correlate "
        "and the s16 schedule, autoregister (0,50,.25,0,5) for the AUTOREGISTER schedule."
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
    options.template_shading_option,
    options.photo_shadows_option,
    options.out_dir_option("Write each landmark's (last) correlation surface as an image to DIR."),
    options.image_format_option,
    options.image_zoom_option,
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
        peak=kw.get("peak", "quadric"),  # commands that reuse these options without --peak
        supersample=kw["supersample"],
        image_shadows=not kw["no_image_shadows"],
        template_shading=kw["template_shading"],
        photo_shadows=kw.get("photo_shadows", RegisterOptions.photo_shadows),
        threads=kw.get("threads"),  # commands without --threads: numba's thread count
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
                # a MAP there but unreadable fails only its landmark, said as a warning, not a note
                if wd.map_path(name).exists():
                    ctx.warn(f"{name}: no maplet: its MAP file is unreadable ({exc})")
                else:
                    ctx.note_once(f"{name}: no maplet ({exc})")
                self.missing.append(name)
                continue
            has_lmk = wd.lmk_path(name).exists()
            if name in inputs.centres:  # the selection read the LMK's VLM (else the MAP's V) already
                pos = np.asarray(inputs.centres[name], dtype=np.float64)
            elif has_lmk:
                pos = np.asarray(wd.read_landmark(name).vlm, dtype=np.float64)
            else:
                pos = np.asarray(maplet.v, dtype=np.float64)
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

    def run(self, stage, options, progress=None):
        """``stage(photo, camera, sz, maplets, thresholds, options, ...)`` — register or navigate — on
        these inputs, with the SUM's sigmas as the pose prior."""
        return stage(
            self.photo,
            self.camera,
            self.pic.sz,
            self.maplets,
            self.thresholds,
            options,
            apriori=self.apriori,
            names=self.names,
            positions=self.positions,
            prior_sigma_position=self.pic.sigma_vso,
            prior_sigma_attitude=self.pic.sigma_ptg,
            progress=progress,
        )


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
@click.option(
    "--sheet",
    "sheet",
    metavar="FILE.png",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write every landmark's correlation surface on one page, enlarged, peak marked in red (PNG).",
)
@options.panels_option
def correlate_cmd(ctx: Context, **kw):
    """One correlation of each landmark: offset, peak and peak quality.

    Maplet space (default): the prediction (SPC illumination, one view vector, dark only where the
    incidence exceeds 90 deg) is correlated with the photo resampled onto the maplet with the landmark
    at its a-priori pixel.  Both images are binned by --spacing N (same phase, anchored at the centre
    node); the normalised cross-correlation (Pearson, with the square root that Liounis 2015 Eq. 3.58
    lacks) is taken
    over the (2K+1)^2 grid of whole-bin offsets, counting only cells valid in both images.  The peak is
    checked -- edge-peak (on the grid border), not-found (a neighbour not lower, or no defined value),
    low-correlation (below --corr-min) -- and refined by a least-squares 2-D quadric on its 3x3
    neighbourhood (--peak quadric; where that fit is no maximum, and with --peak parabola, by one
    parabola per axis, the corrected Liounis 2015 Eq. 3.65, which is biased on tilted peaks).  Image
    space: the maplet rendered into the photo (cast shadows) is correlated with the photo itself,
    offsets in pixels.

    Columns: name, sample and line (the a-priori pixel used), offset_x and offset_y (maplet cells along
    UX and UY; image space: pixels along line and sample), dsample and dline (the implied pixel shift,
    J_xy times the offset in maplet space), measured_sample, measured_line, correlation (peak), spacing,
    sigma_sample, sigma_line and rho_sl (the measurement covariance in px from the peak's curvature and
    (1 - rho^2) noise, ok rows only), status (ok, not-found, edge-peak, low-correlation, outside,
    removed-<criterion>, no-maplet).

    Example:

    \b
      spctool -C demo correlate P000000001A1 --landmarks sel.txt --spacing 2
      spctool -C demo correlate P000000001A1 B01980 --out-dir surf/ --image-format fits --json
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
        "sigma_sample",
        "sigma_line",
        "rho_sl",
        "status",
    ]
    rows, written, tiles = [], 0, []
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
                        "sigma_sample": math.nan,
                        "sigma_line": math.nan,
                        "rho_sl": math.nan,
                        "status": "outside",
                    }
                )
                rows.append(row)
                advance()
                continue
            st = reg.step(i, inp.camera, start[i], int(kw["spacing"]), apply_criteria=True)
            reg.release(i)
            shift = st.shift if st.status in ("ok", "low-correlation", "edge-peak") else np.full(2, np.nan)
            cov = st.covariance if st.ok else np.full((2, 2), np.nan)
            sig = np.sqrt(np.diag(cov))
            row.update(
                {
                    "offset_x": float(st.correlation.offset[0]),
                    "offset_y": float(st.correlation.offset[1]),
                    "dsample": float(shift[0]),
                    "dline": float(shift[1]),
                    "measured_sample": float(st.center[0] + shift[0]),
                    "measured_line": float(st.center[1] + shift[1]),
                    "correlation": float(st.correlation.peak),
                    "sigma_sample": float(sig[0]),
                    "sigma_line": float(sig[1]),
                    "rho_sl": float(cov[0, 1] / (sig[0] * sig[1])) if st.ok and sig.prod() > 0 else math.nan,
                    "status": st.status,
                }
            )
            rows.append(row)
            if out_dir is not None:
                from spctool.figures import register as figures_register

                figures_register.write_surface(
                    out_dir, kw["image_format"], name, inp.pic.name, st, opts.space, kw["zoom"]
                )
                written += 1
            if kw["panels"]:
                from spctool.figures import register as figures_register

                Path(kw["panels"]).mkdir(parents=True, exist_ok=True)
                figures_register.write_panel(
                    Path(kw["panels"]), inp, i, st, inp.camera, opts, st.status, shift, "correlate-panel"
                )
            if kw["sheet"]:
                from spctool.figures import surface_tile

                tiles.append(
                    (f"{name} rho {st.correlation.peak:.2f} {st.status}", surface_tile(st.correlation))
                )
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
    if kw["sheet"]:
        from spctool.figures import contact_sheet

        title = (
            f"{inp.pic.name}  correlation surfaces, spacing {kw['spacing']} (viridis per tile; red = peak)"
        )
        key = (
            "caption: landmark, rho = the surface's peak correlation (1: identical up to brightness), "
            "status"
        )
        contact_sheet(tiles, title=title, key=key).save(kw["sheet"])
        ctx.info(f"wrote {kw['sheet']}")
    emit_table(table, as_json=kw["as_json"], output=kw["output"])


def _say_adapted(ctx, adapted) -> None:
    """What the run adapted to the data by design (:attr:`RegisterResult.adapted`): said with -v, since
    nothing needs doing; a schedule the user named that had to be shortened is a note with the way out."""
    named = any(
        click.get_current_context().get_parameter_source(p) is click.core.ParameterSource.COMMANDLINE
        for p in ("schedule", "steps")
    )
    for kind, text in adapted:
        if kind == "spacing-cap" and named:
            ctx.note_once(f"{text}; --no-spacing-cap runs them as given")
        else:
            ctx.info(text)


# ------------------------------------------------------------------------------------------------
# register


@click.command("register")
@_shared_options
@click.option(
    "--schedule",
    type=click.Choice(["s16", "retina_s16", "autoregister"]),
    default="s16",
    show_default=True,
    help="s16: per landmark, spacings 10..1, no pose update (Shoemaker et al. 2016); autoregister: all "
    "landmarks at spacing 2, then 1, drop below 0.5, then 1, with a pose solve after each pass (SPC).",
)
@click.option(
    "--steps",
    default=None,
    metavar="LIST",
    help="Replace the schedule's steps, e.g. '10,8,6,4,2,1' or '2,1,drop:0.5,1'.",
)
@click.option(
    "--drop-corr",
    type=options.FINITE_FLOAT,
    default=None,
    metavar="RHO",
    help="AUTOREGISTER's removal cut between the passes.  [default: 0.5]",
)
@click.option(
    "--converge-tol",
    type=options.FiniteFloatRange(min=0.0, min_open=True),
    default=0.005,
    show_default=True,
    metavar="PX",
    help="Final stage: repeat the last spacing-1 step until the estimate moves by less than PX.",
)
@click.option(
    "--converge-peak",
    type=click.Choice(["gradient", "quadric", "parabola"]),
    default="gradient",
    show_default=True,
    help="Final stage's sub-pixel estimate: gradient (least-squares alignment, zero when prediction "
    "and photo agree) or a vertex of the correlation surface (biased up to 0.05 px where the surface "
    "is asymmetric).",
)
@click.option(
    "--converge-max",
    type=click.IntRange(min=0),
    default=10,
    show_default=True,
    metavar="N",
    help="At most N extra spacing-1 steps (0 = the schedule exactly, as S16/SPC run it); a landmark "
    "that has not settled is 'not-converged'.",
)
@click.option(
    "--no-converge-draft",
    "no_converge_draft",
    is_flag=True,
    help="Image space: render every final-stage template with --supersample rays (default: the first "
    "steps use one ray per pixel until a step moves by less than 0.15 px; the stage still ends on full "
    "templates).",
)
@click.option(
    "--edge-retries",
    type=click.IntRange(min=0),
    default=2,
    show_default=True,
    metavar="N",
    help="S16 schedule: a peak on the border of the search grid moves there and repeats the step, "
    "at most N times (0 = S16, which gives up).",
)
@options.first_phases_option(
    "S16 schedule: correlate each landmark's first step (spacing L >= 2) at P x P phases, its "
    "centre moved by L/P cells, and keep the best (1 = S16). 2 samples the coarsest search at L/2 "
    "cells: a peak between two L-cell grid points is no longer read at half its height.",
    default=1,
)
@click.option(
    "--capped-phases",
    "capped_phases",
    type=click.IntRange(1, 4),
    default=2,
    show_default=True,
    metavar="P",
    help="S16 schedule, maplet space: when the maplet's size capped the schedule (one step at the cap "
    "instead of the coarser ones, said with -v), the first step runs at max(P, --first-phases) phases: "
    "at the cap the grid's border offsets overlap half the maplet and can beat a peak read between grid "
    "points (1 = the capped step as given).",
)
@options.acquire_reach_option(
    "S16 schedule, maplet space: the first step (spacing L >= 2) searches +-CELLS on the photo "
    "resampled onto the maplet's grid extended beyond its edge, so every offset compares the whole "
    "prediction (0 = S16: within the maplet's own grid, which reaches about half the maplet's width). "
    "Image space: pixels; the steps at the first spacing search +-max(K, CELLS/L) bins, the later ones "
    "keep --grid-half K.",
    default=0,
)
@click.option(
    "--no-fail-fast",
    "no_fail_fast",
    is_flag=True,
    help="s16 schedule: keep going after a failed step (default: stop the landmark).",
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
    "--no-spacing-cap",
    "no_spacing_cap",
    is_flag=True,
    help="Run every step as given even where the maplet is too small for it (default: spacings with "
    "K x L > Q + 1, Q the maplet's half-width, are replaced by one step at the largest L that fits; a "
    "note says so).",
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
@options.overlay_option(
    "Write the photo with each landmark's shift (measured - a-priori) as a vector magnified by "
    "--magnify, coloured by status, with legend and title (PNG)."
)
@click.option(
    "--magnify",
    type=options.FiniteFloatRange(min=0, min_open=True),
    default=None,
    metavar="F",
    help="--overlay: draw shift vectors F times their length.  [default: the median shift drawn ~40 px]",
)
@options.panels_option
@options.threads_option
@options.require_option(
    "Exit 1 when fewer than N landmarks are registered (the table is still written). Without it a run "
    "that registers nothing exits 0 with a warning on stderr."
)
def register_cmd(ctx: Context, **kw):
    """Measure the landmarks of a picture: iterated predict, extract and correlate.

    Schedule s16 (default; the template-matching loop of Shoemaker et al. 2016): for each landmark,
    starting at its a-priori pixel, correlate at spacing L = 10, 9, ..., 1 (search +-5L cells,
    acceptance rho >= 0.3) and move the pixel by J_xy times the offset (Liounis 2015 Eq. 3.67, Shoemaker
    et al. 2016 Eq. 19) after each step; the pose is not changed.  Schedule autoregister (SPC's
    AUTOREGISTER seed): removal criteria 0,50,.25,0,5 on the first pass, then all landmarks at spacing
    2, a pose solve, spacing 1, a pose solve, landmarks with rho < 0.5 dropped, spacing 1 and a last
    pose solve; each pass re-predicts and re-extracts with the updated pose.  Both end with a
    converged full-resolution stage: the last spacing-1 step is repeated until the estimate moves by
    less than --converge-tol (at most --converge-max times; else the status is not-converged), then
    AUTOREGISTER solves the pose once more.  That stage reads each step by least-squares alignment
    of prediction and photo (--converge-peak gradient: exactly zero when they agree, where a vertex of
    the correlation surface keeps up to 0.05 px of bias) and moves by secant steps.  A schedule is fitted to
    each maplet: a step at spacing L searches +-K*L cells and works only while K*L <= Q + 1, Q the
    maplet's half-width (Shoemaker et al. 2016: L = 10 for 99x99 maplets; a 49x49 maplet: L <= 5), so
    coarser steps are replaced by one step at the largest L that fits (said with -v, or in a note when
    you named --schedule or --steps; --no-spacing-cap runs them as given).  --space image correlates
    the maplet rendered into the photo (with cast shadows) against the photo itself, so the search is
    not limited by the maplet's extent (as in the Retina system, Wright et al. 2016).

    Columns: name, sample and line (the measured pixel when ok, else the a-priori pixel),
    apriori_sample, apriori_line, dsample and dline (measured minus a-priori), correlation (last
    peak), iterations (correlations run), spacing (of the last one), sigma_sample, sigma_line and
    rho_sl (measurement covariance, px: 1-sigma per axis and their correlation, from the last peak's
    curvature and (1 - rho^2) noise; an upper bound where model error rather than noise lowers rho),
    status (ok, not-found, edge-peak, low-correlation, not-converged, outside, removed-<criterion>,
    no-maplet).  The table feeds solve-pose directly (only ok rows are used; --weights surface uses
    the covariance).  With --write-sum the ok landmarks are written to the SUM's LANDMARKS
    section (rows of other landmarks are kept unless --drop-failed).

    A --landmarks table whose '# picture:' header names another picture, or a --sum file of
    another picture, is refused (exit 2; --any-picture uses it anyway).
    A run that registers no landmark prints a warning naming the most common failure on stderr;
    --require N turns fewer than N registered into exit code 1.

    Example:

    \b
      spctool -C demo lithos-select P000000001A1 -o sel.txt
      spctool -C demo register P000000001A1 --landmarks sel.txt --require 12 -o reg.txt
      spctool -C demo register P000000001A1 --schedule autoregister --write-sum --overlay reg.png
      spctool -C demo register P000000001A1 B01980 --space image --json
      spctool -C demo register P000000001A1 --peak parabola --converge-max 0 --edge-retries 0  # S16
      spctool -C demo register P000000001A1 --first-phases 2  # a denser first search
      spctool -C demo register P000000001A1 --acquire-reach 80  # search +-80 cells beyond the maplet
      spctool -C demo register P000000001A1 --converge-peak quadric  # the previous release's final stage
    """
    from spctool.stages.register import RegisterOptions, schedule_steps
    from spctool.stages.register import register as run_register

    kw["_command"] = "register"
    schedule = options.register_schedule(kw["schedule"])
    extra = {
        "fail_fast": not kw["no_fail_fast"],
        "pose_update": not kw["no_pose_update"],
        "halve_shift": kw["halve_shift"],
        "cap_spacing": not kw["no_spacing_cap"],
        "converge_tol": kw["converge_tol"],
        "edge_retries": kw["edge_retries"],
        "first_phases": kw["first_phases"],
        "capped_phases": kw["capped_phases"],
        "acquire_reach": kw["acquire_reach"],
        "converge_max": kw["converge_max"],
        "converge_peak": kw["converge_peak"],
        "converge_draft": not kw["no_converge_draft"],
    }
    if kw["steps"]:
        extra["steps"] = _parse_steps(kw["steps"])
    if kw["panels"]:
        extra["keep_images"] = True  # the last extraction / template of every landmark, for the panels
    if kw["drop_corr"] is not None:
        seed = RegisterOptions.__dataclass_fields__["autoregister_steps"].default
        extra["autoregister_steps"] = tuple(
            ("drop", kw["drop_corr"]) if k == "drop" else (k, v) for k, v in seed
        )
    opts = _register_options(kw, schedule, **extra)
    inp = _Inputs(ctx, kw)
    # AUTOREGISTER visits every active landmark once per align pass (fewer after a drop)
    passes = sum(k == "align" for k, _ in schedule_steps(opts)) if schedule == "autoregister" else 1
    # maplet space forks its workers: only while this process runs one thread (no refresh thread)
    bar = progress(ctx, f"register {inp.pic.name}", passes * len(inp.names), threaded=opts.space == "image")
    with bar as adv:
        result = inp.run(run_register, opts, adv)
    for w in result.warnings:
        ctx.note_once(w)
    _say_adapted(ctx, result.adapted)

    out_dir = Path(kw["out_dir"]) if kw["out_dir"] else None
    written = 0
    if out_dir is not None:
        from spctool.figures import register as figures_register

        out_dir.mkdir(parents=True, exist_ok=True)
        for name, st in zip(result.names, result.last_steps):
            if st is not None:
                figures_register.write_surface(
                    out_dir, kw["image_format"], name, inp.pic.name, st, opts.space, kw["zoom"]
                )
                written += 1
    meta = {
        "landmark_source": inp.source,
        "schedule": "s16" if schedule == "retina_s16" else schedule,  # the --schedule word
        "space": opts.space,
        "thresholds": list(inp.thresholds),
        "status_counts": result.status_counts(),
        "registered": int(result.ok.sum()),
        "passes": result.passes,
        "options": result.options.as_dict(),  # as run (capped_phases may have raised first_phases)
        "warnings": list(result.warnings),
        "adapted": [text for _, text in result.adapted],
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
        f"({'s16' if schedule == 'retina_s16' else schedule}, {opts.space} space)"
    )
    emit_table(table, as_json=kw["as_json"], output=kw["output"])
    n_all = len(result) + len(inp.missing)
    if n_all and not int(result.ok.sum()):
        ctx.warn(f"{inp.pic.name}: registered 0 of {n_all} landmarks: {_why(result, inp)}")
    elif not n_all:  # nothing to register: a camera pointed away, a table without rows
        where = "the table given has no landmark row" if inp.source == "given" else (
            "lithos-select finds no maplet this picture sees (its pose and Sun, the maplets' sizes)")
        ctx.warn(f"{inp.pic.name}: registered 0 of 0 landmarks: {where}")

    if kw["write_sum_flag"]:
        path = _write_sum(kw, inp, result)
        ctx.info(f"rewrote the LANDMARKS section of {path}")
    if kw["overlay"]:
        from spctool.figures import register as figures_register
        from spctool.formats import atomic

        atomic.write_bytes(
            kw["overlay"],
            figures_register.overlay_png(
                inp.photo.data,
                inp.pic.thrsh,
                result.names,
                result.apriori,
                result.measured,
                result.ok,
                status=result.status,
                picture=inp.pic.name,
                subtitle=f"({'s16' if schedule == 'retina_s16' else schedule}, {opts.space} space)",
                magnify=kw["magnify"],
            ),
            backup=True,
        )
        ctx.info(f"wrote {kw['overlay']}")
    if kw["panels"]:
        from spctool.figures import register as figures_register

        n = figures_register.write_panels(Path(kw["panels"]), inp, result, opts)
        ctx.info(f"wrote {n} panels to {kw['panels']}")
    options.check_require(inp.pic.name, int(result.ok.sum()), kw["require"], "landmarks registered")


def _why(result, inp) -> str:
    """The reason a run registered nothing: its status counts, most common first, with the spacing."""
    counts = dict(result.status_counts())
    if inp.missing:
        counts["no-maplet"] = counts.get("no-maplet", 0) + len(inp.missing)
    parts = [f"{n} {word}" for word, n in sorted(counts.items(), key=lambda kv: -kv[1])]
    top = max(counts, key=counts.get)
    at = [int(s) for s, st in zip(result.spacing, result.status) if st == top and s > 0]
    if at:
        parts[0] += f" at spacing {max(set(at), key=at.count)}"
    return ", ".join(parts)


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
