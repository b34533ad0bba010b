"""``lithos-select``: the maplets a picture can see (Stage A, :mod:`spctool.stages.select`).

Loads the picture (SUM), the candidate landmarks (LMRKLIST.TXT, LMKFILES/, ``--maplets`` or
``--landmarks``), INIT_LITHOS (distortion model, NUMLM/RESLM/SIZLM) and the shape, runs
:func:`spctool.stages.select.select_maplets` and writes the landmark table of cli-contract.md.
``--overlay`` draws the selected maplets' outlines on the photo.
"""

from __future__ import annotations

import click

from spctool.cli import options
from spctool.cli.candidates import load_candidates
from spctool.cli.common import Context, emit_table, load_photo, load_picture, load_shape, pass_context
from spctool.errors import SpcUsageError
from spctool.formats import atomic

# ------------------------------------------------------------------------------------------------
# command


@click.command("lithos-select")
@options.picture_argument
@options.sum_option
@click.option(
    "--maplets",
    "maplets",
    metavar="NAME|FILE",
    multiple=True,
    help="Candidate landmarks: names (LMKFILES/NAME.LMK, else MAPFILES/NAME.MAP), .LMK or .MAP "
    "files, or a list file of names. Repeatable. Default: LMRKLIST.TXT, else LMKFILES/*.LMK.",
)
@options.landmarks_table_option(
    "Candidate landmarks from the 'name' column of a landmark table ('-' = stdin)."
)
@options.shape_option(" for the occlusion test")
@click.option(
    "--occlusion/--no-occlusion",
    "occlusion",
    default=None,
    help="Run the occlusion test (Liounis 2015 sec. 3.2.1). Default: on when a shape model is available.",
)
@click.option(
    "--occlusion-tol",
    type=options.FINITE_FLOAT,
    default=None,
    metavar="F",
    help="Occlusion tolerance as a fraction of the body's largest diameter.  [default: 0.01]",
)
@click.option(
    "--numlm",
    type=click.IntRange(min=0),
    default=None,
    metavar="N",
    help="Maplet count above which the resolution screen applies.  [default: INIT_LITHOS NUMLM, else 200]",
)
@click.option(
    "--reslm",
    type=options.FINITE_FLOAT,
    default=None,
    metavar="F",
    help="Keep maplets whose pixel footprint < F x maplet scale.  [default: INIT_LITHOS RESLM, else 4]",
)
@click.option(
    "--numlm-mode",
    type=click.Choice(["deterministic", "spc_sequential"]),
    default=None,
    help="deterministic: screen all candidates when more than NUMLM pass; spc_sequential: screen "
    "those met after NUMLM selections, in list order.  [default: deterministic]",
)
@click.option(
    "--size-factor",
    type=options.FINITE_FLOAT,
    default=None,
    metavar="F",
    help="Maplet side must be < F x photo side at the landmark.  [default: INIT_LITHOS SIZLM, else 1]",
)
@click.option(
    "--facing-cos-min",
    type=options.FINITE_FLOAT,
    default=None,
    metavar="F",
    help="Minimum cosine between the maplet normal and the direction to the camera.  [default: 0.05]",
)
@click.option(
    "--max-emission",
    type=options.FINITE_FLOAT,
    default=None,
    metavar="DEG",
    help="Reject maplets seen at emission >= DEG (LITHOS uses 75 for PICTLIST candidates).",
)
@click.option(
    "--fractional-width",
    type=options.FINITE_FLOAT,
    default=None,
    metavar="W",
    help="Offset of the 3x3 in-photo test points (LITHOS 'fractional width').  [default: 0.5]",
)
@click.option(
    "--fw-scale",
    type=click.Choice(["side", "half"]),
    default=None,
    help="The offset is W x maplet side (side) or W x half side (half).  [default: side]",
)
@click.option(
    "--cone-rho",
    type=click.Choice(["half-diagonal", "half-side"]),
    default=None,
    help="Maplet radius used by the field-of-view cone.  [default: half-diagonal]",
)
@click.option(
    "--jacobian",
    type=click.Choice(["central", "analytic"]),
    default=None,
    help="Pixel/maplet-cell Jacobian for the resolution: one-cell central differences (as in Liounis "
    "2015) or exact. "
    " [default: central]",
)
@click.option(
    "--all",
    "show_all",
    is_flag=True,
    help="Also list rejected maplets, with the first failed check as status.",
)
@options.require_option("Exit 1 when fewer than N maplets are selected.")
@options.overlay_option("Write the photo with the selected maplets' outlines and names drawn on it (PNG).")
@options.photo_option(" for --overlay")
@options.json_option
@options.output_option
@pass_context
def select_cmd(
    ctx: Context,
    picture,
    sum_path,
    maplets,
    landmarks_table,
    shape_path,
    occlusion,
    occlusion_tol,
    numlm,
    reslm,
    numlm_mode,
    size_factor,
    facing_cos_min,
    max_emission,
    fractional_width,
    fw_scale,
    cone_rho,
    jacobian,
    show_all,
    require,
    overlay,
    photo_path,
    as_json,
    output,
):
    """Select the maplets a picture can see, with predicted pixels and geometry.

    The checks follow Liounis 2015 sec. 3.2 in order; a rejected maplet's status is the first one it fails:
    outside (field-of-view cone), backfacing (maplet faces away from the camera), too-oblique
    (only with --max-emission), unlit (Sun below the maplet plane), too-coarse (pixel footprint
    >= RESLM x scale, applied when more than NUMLM maplets pass), too-big (maplet larger than the
    photo at that range), outside (none of the 3x3 box points in the photo), occluded (the shape
    hides the landmark).  The occlusion test needs a shape model; without one it is skipped with
    a note on stderr.

    Columns: name, sample and line (predicted SPC pixel of the landmark), range_km (spacecraft to
    landmark), resolution_km_px (photo pixel footprint at the landmark), emission, incidence and phase
    (degrees), fraction_in_photo (fraction of the 3x3 box points inside the photo) and status (ok =
    selected, else the name of the first check failed, as above).  An empty selection is a valid result
    (exit 0) unless --require N asks for more.

    Example:

    \b
      spctool -C demo lithos-select P000000001A1 -o sel.txt
      spctool -C demo lithos-select P000000001A1 --all --json
      spctool lithos-select demo/SUMFILES/P000000001A1.SUM --maplets B01980 --maplets B02176
      spctool -C demo lithos-select P000000001A1 --numlm 5 --overlay sel.png
    """
    from spctool.stages.select import SelectOptions

    _, pic, settings, camera = load_picture(ctx, picture, sum_path)
    select_options = SelectOptions.from_settings(
        settings,
        numlm=numlm,
        reslm=reslm,
        numlm_mode=numlm_mode,
        size_factor=size_factor,
        facing_cos_min=facing_cos_min,
        max_emission=max_emission,
        fractional_width=fractional_width,
        fw_scale=fw_scale,
        cone_rho=cone_rho,
        jacobian=jacobian,
        occlusion=occlusion,
        occlusion_tol=occlusion_tol,
    )
    cand = load_candidates(ctx, maplets, landmarks_table)
    ctx.info(f"{len(cand)} candidate maplets for picture {pic.name}")

    shape = None
    if occlusion is not False:
        shape = load_shape(ctx, shape_path)
        if shape is None:
            if occlusion:
                raise SpcUsageError(
                    f"--occlusion needs a shape model ({ctx.wd.shape_path} not found; give --shape)"
                )
            ctx.note_once("no shape model (SHAPEFILES/SHAPE.TXT or --shape): occlusion check skipped")

    result = cand.select(camera, pic.sz, select_options, shape=shape)
    counts = result.status_counts()
    meta = {
        "candidates": len(result),
        "selected": result.n_selected,
        "status_counts": counts,
        "occlusion": "checked" if result.occlusion_checked else "skipped",
        "half_fov_deg": result.half_fov_deg,
        "options": select_options.as_dict(),
    }
    table = result.to_table(include_rejected=show_all, picture=pic.name, command="lithos-select", meta=meta)
    table.comments.append(
        f"selected {result.n_selected} of {len(result)} candidate maplets; occlusion {meta['occlusion']}"
    )
    emit_table(table, as_json=as_json, output=output)

    if overlay:
        photo = load_photo(ctx, pic, photo_path)
        from spctool import figures

        others = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()) if s != "ok")
        fig = figures.titled(
            figures.selection_overlay(
                photo.data,
                pic.thrsh,
                camera,
                cand.names,
                cand.centres,
                cand.ux,
                cand.uy,
                (2.0 * cand.qsz + 1.0) * cand.scale / 2.0,
                result.selected,
                result.sample,
                result.line,
            ),
            f"{pic.name}  lithos-select: {result.n_selected} of {len(result)} candidate maplets selected",
            f"outlines: selected maplets at the SUM pose; occlusion {meta['occlusion']}"
            + (f"; rejected: {others}" if others else ""),
        )
        atomic.write_bytes(overlay, fig.png(), backup=True)
        ctx.info(f"wrote {overlay}")

    options.check_require(pic.name, result.n_selected, require, "maplets selected")


def register(cli):
    cli.add_command(select_cmd)
