"""``lithos``: SPC's LITHOS "Find heights" — maplet heights and albedo solved from registered pictures.

A thin command over :func:`spctool.stages.find_heights.find_heights` (the outer loop) and
:mod:`spctool.stages.photoclinometry` / :mod:`spctool.stages.slope_integration` (the numerics).  For
each LANDMARK it reads ``MAPFILES/<NAME>.MAP`` and ``LMKFILES/<NAME>.LMK``; the pictures are the LMK
PICTURES rows not flagged ``*`` (their pixels are the a-priori centres), each with its SUM (pose,
Sun, THRSH), INIT_LITHOS (distortion) and photo.  A picture whose SUM or photo is missing is left
out with a note; one whose SUM or photo is there but cannot be used (corrupt, truncated, unreadable)
is left out with a warning naming the file.

Writes (unless ``--dry-run``), atomically with a ``.bak`` of the file replaced: the MAP (heights
re-quantised with HSCALE = max|h|/30000, SPC's 2021 WRITE_MAP rule, which keeps int16 precision;
albedo bytes NINT(100·a)) and the LMK (PICTURES: each picture used gets its last registered centre
and no flag, a picture the extraction removed gets ``*``; VLM only with ``--recentre``).  A maplet
that cannot be solved is left unchanged and named on stderr with the reason; exit 1.
"""

from __future__ import annotations

import math
from pathlib import Path

import click
import numpy as np

from spctool.cli import options
from spctool.cli.common import Context, check_output, emit_table, pass_context
from spctool.errors import SpcResultError, SpcUsageError


def _row(name, result, n_pictures, wrote):
    s = result.summary() if result is not None else {}
    used = [p for p in (result.pictures if result is not None else []) if p.used]

    def mean(attr):
        vals = [getattr(p, attr) for p in used if math.isfinite(getattr(p, attr))]
        return float(np.mean(vals)) if vals else math.nan

    return {
        "name": name,
        "pictures": n_pictures,
        "used": len(used),
        "iterations": s.get("iterations", 0),
        "converged": "yes" if s.get("converged") else "no",
        "change_rms": s.get("change_rms_cells", math.nan),
        "height_change_rms": s.get("height_change_rms_cells", math.nan),
        "solved": s.get("solved_cells", 0),
        "flagged": s.get("flagged_cells", 0),
        "ncc_before": mean("ncc_before"),
        "ncc_after": mean("ncc_after"),
        "written": "yes" if wrote else "no",
        "status": "worse" if result is not None and result.worse else s.get("status", "unsolvable"),
    }


@click.command("lithos")
@click.argument("landmarks", nargs=-1, metavar="[LANDMARK]...")
@click.option("--iterations", type=click.IntRange(min=1), default=10, show_default=True, metavar="N",
              help="Outer iterations at most (heights -> slopes -> predict -> re-register -> solve).")
@click.option("--tolerance", type=options.FiniteFloatRange(min=0.0), default=0.005, show_default=True,
              metavar="CELLS",
              help="Stop when the rms height change of an iteration is below this (maplet cells).")
@click.option("--weight", type=options.FiniteFloatRange(min=0.0, min_open=True), default=0.025,
              show_default=True, metavar="W",
              help="Weight of the conditioning heights (SPC: 'always use .025').")
@click.option("--condition-fraction", type=options.FiniteFloatRange(0.0, 1.0), default=0.02,
              show_default=True, metavar="F",
              help="Fraction of the cells pulled toward the starting heights.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, metavar="N",
              help="Seed of the conditioning cells' draw.")
@click.option("--free-plane", is_flag=True,
              help="Let the best-fit plane move (default: keep the starting map's offset and tilt).")
@click.option("--fixed-lambda", is_flag=True,
              help="Fit each picture's brightness scale on the starting map only, not every iteration.")
@click.option("--no-register", is_flag=True,
              help="Extract at the LMK PICTURES pixels; do not re-register on the updated heights.")
@click.option("--first-pixels", type=click.Choice(["auto", "apriori", "register"]), default="auto",
              show_default=True,
              help="Where the pictures sit in the first pass: at their a-priori pixels (LMK PICTURES, "
                   "else the projection of V: navigated pictures), registered on the starting maplet "
                   "(poses not navigated, a start close to the truth), or auto: both tried, the one the "
                   "pictures agree on best kept.")
@click.option("--acquire-spacings", default="1", show_default=True, metavar="LIST",
              help="Spacings (e.g. 4,2,1) of the first registration of a picture without a PICTURES pixel "
                   "(from the projection of V with the SUM pose); 1 suits navigated pictures.")
@click.option("--min-azimuths", type=click.IntRange(min=1), default=3, show_default=True, metavar="N",
              help="A cell needs pictures with at least N distinct Sun azimuths.")
@click.option("--azimuth-separation", type=options.FiniteFloatRange(min=0.0), default=20.0, show_default=True,
              metavar="DEG", help="Sun azimuths closer than this count as one.")
@click.option("--damping", type=options.FiniteFloatRange(min=0.0), default=5e-3, show_default=True,
              metavar="D",
              help="Levenberg-Marquardt damping of the per-cell solve toward the current values.")
@options.photometry_option
@options.thresholds_option
@click.option("--recentre", is_flag=True,
              help="Move V along UZ by the mean height (MAP and LMK VLM) and subtract it.")
@click.option("--dry-run", is_flag=True, help="Solve and report; write nothing.")
@click.option("--force", is_flag=True,
              help="Write a refined maplet even when it matches the photos worse (lower mean NCC).")
@click.option("--figures", "figures_dir", metavar="DIR", type=click.Path(file_okay=False),
              help="Write <LANDMARK>_heights.png and <LANDMARK>_rerender.png to DIR.")
@options.output_option
@options.json_option
@pass_context
def lithos_cmd(ctx: Context, landmarks, **kw):
    """LITHOS "Find heights": solve maplet heights and albedo from the registered pictures.

    Stereophotoclinometry (S16; map-refinement.md section 2).  For each LANDMARK (default: every
    landmark of LMRKLIST.TXT, else LMKFILES/) the pictures of its LMK PICTURES section are
    re-registered on the maplet and extracted onto its grid; each picture's brightness scale is
    fitted; every cell's two slopes and relative albedo are solved by damped least squares from
    all pictures at once; the slopes are integrated to heights with a few conditioning heights
    pulled toward the starting map (--weight, --condition-fraction); and the loop repeats on the
    new heights until they change by less than --tolerance cells rms.  Later registrations only
    co-register the pictures: the move of V they share is removed (moving V is GEOMETRY's job).

    Cells seen by pictures with fewer than --min-azimuths distinct Sun azimuths keep their heights
    and albedo and are counted as flagged.  A maplet with fewer such pictures, or with fewer than
    a quarter of its cells solvable, cannot be solved: it is left unchanged and named on stderr.

    A refined maplet whose re-rendering matches the extractions worse than the starting one (mean
    NCC lower by more than 0.005) is not written unless --force: a warning says so and its status
    is "worse".

    Writes MAPFILES/<NAME>.MAP (heights, albedo; HSCALE = max|h|/30000) and LMKFILES/<NAME>.LMK
    (PICTURES: centres of the pictures used, '*' on those the extraction removed), each atomically
    with a .bak of the old file.  Columns: name, pictures, used, iterations, converged, change_rms
    (last iteration, cells), height_change_rms (against the start, cells), solved, flagged,
    ncc_before, ncc_after (mean NCC of the re-rendered maplet with the extractions), written,
    status.  --json adds each maplet's history and per-picture figures.

    Exit codes: 0 every maplet solved; 1 a maplet could not be solved (unchanged); 2 bad input.

    Example:

    \b
      spctool -C demo lithos B01536 --dry-run
      spctool -C demo lithos B01536 B01595 --iterations 3 --figures lithos-figures
      spctool -C demo lithos B01980 --json -o lithos.json
    """
    from spctool.batch.heights import landmark_views
    from spctool.cli.options import picture_thresholds
    from spctool.formats.landmark import write_lmk
    from spctool.formats.maplet import write_map
    from spctool.stages.find_heights import FindHeightsOptions, find_heights, landmark_with, maplet_with
    from spctool.stages.photoclinometry import SolveOptions
    from spctool.stages.register_options import RegisterOptions

    try:
        spacings = tuple(int(t) for t in kw["acquire_spacings"].replace(" ", ",").split(",") if t)
    except ValueError:
        spacings = ()
    if not spacings or min(spacings) < 1:
        raise SpcUsageError(f"--acquire-spacings expects spacings like 4,2,1, got {kw['acquire_spacings']!r}")
    acquire = RegisterOptions(steps=tuple(("align", n) for n in spacings), converge_tol=0.02, converge_max=4)
    opts = FindHeightsOptions(
        acquire=acquire,
        iterations=kw["iterations"],
        tolerance=kw["tolerance"],
        condition_weight=kw["weight"],
        condition_fraction=kw["condition_fraction"],
        seed=kw["seed"],
        keep_plane=not kw["free_plane"],
        refit_lambda=not kw["fixed_lambda"],
        reregister=not kw["no_register"],
        first_pixels=kw["first_pixels"],
        recentre=kw["recentre"],
        solve=SolveOptions(photometry=kw["photometry"], damping=kw["damping"],
                           min_azimuths=kw["min_azimuths"], azimuth_separation_deg=kw["azimuth_separation"]),
    )
    if kw["thresholds"] is not None:  # a bad --thresholds is bad input (exit 2), not every picture left out
        picture_thresholds(kw["thresholds"], None)
    names = list(landmarks) or ctx.wd.landmark_names()
    if not names:
        raise SpcResultError("no landmark to solve (none named, no LMRKLIST.TXT, no LMKFILES/)")
    # every named landmark's LMK and MAP read before any maplet is solved or written (a MAP again when
    # its turn comes, not kept: a map of many maplets): a missing or bad file is exit 2 with nothing
    # written; so is an -o that cannot take the table
    lmks = [ctx.wd.read_landmark(n) for n in names]
    for lmk in lmks:
        ctx.wd.read_maplet(lmk.name)
    check_output(kw["output"])
    rows, docs, failed = [], [], []
    for lmk in lmks:
        maplet = ctx.wd.read_maplet(lmk.name)
        views, skipped = landmark_views(ctx.wd, ctx.settings(), lmk, note=ctx.note_once, warn=ctx.warn,
                                        thresholds=lambda pic: picture_thresholds(kw["thresholds"], pic))
        result = find_heights(maplet, views, opts)
        wrote = False
        if not result.ok:
            failed.append(f"{lmk.name}: cannot solve the heights: {result.reason}; MAP and LMK unchanged")
        elif result.worse and not kw["force"]:
            b, a = result.mean_ncc()
            ctx.warn(f"{lmk.name}: the refined maplet matches the photos worse than the starting one "
                     f"(mean NCC {b:.3f} -> {a:.3f}): not written (--force writes it)")
        elif not kw["dry_run"]:
            map_path = ctx.wd.map_path(lmk.name)
            write_map(map_path, maplet_with(maplet, result), backup=True)
            write_lmk(ctx.wd.lmk_path(lmk.name), landmark_with(lmk, result), backup=True)
            wrote = True
            ctx.info(f"wrote {map_path} and {ctx.wd.lmk_path(lmk.name)}")
        if kw["figures_dir"] and result.ok:
            from spctool.figures.heights import maplet_sheet, rerender_sheet

            out = Path(kw["figures_dir"])
            out.mkdir(parents=True, exist_ok=True)
            maplet_sheet(result).save(out / f"{lmk.name}_heights.png")
            rerender_sheet(result).save(out / f"{lmk.name}_rerender.png")
        rows.append(_row(lmk.name, result, len(views) + len(skipped), wrote))
        doc = result.summary()
        doc["skipped_pictures"] = skipped
        docs.append(doc)
    from spctool.formats.table import LandmarkTable

    meta = {"maplets": docs, "options": opts.as_dict(), "dry_run": kw["dry_run"]}
    table = LandmarkTable.from_rows(rows, command="lithos", meta=meta)
    for doc in docs:
        hist = ", ".join(f"{h['change_rms']:.3g}" for h in doc["history"])
        table.comments.append(f"{doc['name']}: {doc['status']}; height change per iteration (cells rms): "
                              f"{hist or '-'}")
    emit_table(table, as_json=kw["as_json"], output=kw["output"])
    if failed:
        for line in failed[:-1]:
            ctx.warn(line)
        raise SpcResultError(failed[-1] if len(failed) == 1 else
                             f"{failed[-1]} ({len(failed)} maplets could not be solved)")


def register(cli):
    cli.add_command(lithos_cmd)
