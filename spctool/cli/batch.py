"""``batch``: lithos-select → register → solve-pose over every picture of a PICTLIST.

A thin command over :func:`spctool.batch.run_batch` (the per-picture pipeline, the output layout, the
resume rule and the parallel back ends are documented there): parse the options, show a progress
bar, report each failed picture on stderr as it happens, print the summary table (or ``--json``), and
exit 1 when any picture failed.
"""

from __future__ import annotations

from pathlib import Path

import click

from spctool.cli import options
from spctool.cli.common import Context, emit, pass_context, progress
from spctool.errors import SpcResultError, SpcUsageError


@click.command("batch")
@click.argument(
    "pictlist", required=False, type=click.Path(dir_okay=False, exists=True), metavar="[PICTLIST]"
)
@click.option(
    "--out-dir",
    "out_dir",
    type=click.Path(file_okay=False),
    default=None,
    metavar="DIR",
    help="Output directory (SPC layout: DIR/SUMFILES/, DIR/TABLES/).  [default: WORKDIR/BATCH]",
)
@click.option(
    "-j",
    "--jobs",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    metavar="N",
    help="Local workers, one core each (1 = in this process).",
)
@click.option(
    "--scheduler",
    default=None,
    metavar="ADDRESS",
    help="Run on an existing Dask distributed cluster (e.g. tcp://scheduler-host:8786; needs "
    "'pip install spctool[dask]'; workers must see WORKDIR and --out-dir at the same paths). "
    "Overrides --jobs.",
)
@click.option("--force", is_flag=True, help="Redo pictures that are already done.")
@click.option(
    "--schedule",
    type=click.Choice(["two-pass", "autoregister", "s16"]),
    default="two-pass",
    show_default=True,
    help="two-pass: acquisition reaching +-25 px, pose, every landmark again from the solved pose, "
    "pose (see 'spctool navigate --help'); autoregister or s16: the old single pass of that "
    "register schedule.",
)
@options.reach_option(
    "two-pass: the acquisition's coarse search reaches at least +-PX pixels (default 25); set it "
    "beyond the pictures' a-priori error (a picture whose landmarks lie beyond it ends no-pose, see "
    "'spctool navigate --help').",
    default=None,
)
@options.space_option
@options.corr_min_option
@click.option(
    "--occlusion/--no-occlusion",
    "occlusion",
    default=None,
    help="Occlusion test of lithos-select.  [default: on when a shape model exists]",
)
@options.shape_option(" for the occlusion test", exists=True)
@options.sigma_px_option()
@options.weights_option("  Two-pass schedule only (the single-pass schedules solve with uniform weights).")
@options.no_prior_option
@options.prior_scale_option
@options.min_landmarks_option
@click.option(
    "--plots",
    is_flag=True,
    help="Also draw every picture's register overlay and solve-pose residual plot into DIR/PLOTS/.",
)
@click.option("--no-figure", "no_figure", is_flag=True, help="Do not write BATCH_SUMMARY.png.")
@click.option(
    "--lithos",
    is_flag=True,
    help="With --rounds: after each refinement of the landmarks and poses, also solve every refined "
    "maplet's heights and albedo (as 'spctool lithos', in parallel over maplets with --jobs) before the "
    "next round measures.",
)
@click.option(
    "--rounds",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    metavar="N",
    help="SPC's cycle: measure every picture, refine landmarks and poses from all of them (as 'spctool "
    "geometry'), measure again from the refined map; N rounds (DIR/ROUND1 ... DIR/ROUNDN, the refined "
    "maps DIR/MAP2 ...; the working directory is not written).",
)
@options.json_option
@options.output_option
@pass_context
def batch_cmd(
    ctx: Context,
    pictlist,
    out_dir,
    jobs,
    scheduler,
    force,
    schedule,
    reach_px,
    space,
    corr_min,
    occlusion,
    shape_path,
    sigma_px,
    weights,
    no_prior,
    prior_scale,
    min_landmarks,
    plots,
    no_figure,
    lithos,
    rounds,
    as_json,
    output,
):
    """Navigate every picture of a PICTLIST: lithos-select, register, solve-pose.

    PICTLIST is a PICTLIST.TXT-format file (default: the working directory's PICTLISTX.TXT or
    PICTLIST.TXT, else every SUMFILES/*.SUM); pictures flagged '!' or '#' are left out.  For each
    picture the maplets it can see are selected (LMRKLIST.TXT candidates, INIT_LITHOS options,
    occlusion with the shape model), registered in its photo and the spacecraft position and
    attitude solved from the registered pixels with the SUM's sigmas as prior, as the commands
    lithos-select and navigate (two-pass navigation, the default) do one by one; --schedule
    autoregister or s16 runs the old single pass (lithos-select, register with that schedule,
    solve-pose).

    Outputs, written atomically to --out-dir: SUMFILES/PIC.SUM (the input SUM with the registered
    LANDMARKS rows and, when the pose converged, the solved SCOBJ, CX, CY, CZ, SIGMA_VSO,
    SIGMA_PTG; every other line unchanged), TABLES/PIC.select.txt, TABLES/PIC.register.txt,
    TABLES/PIC.pose.txt (the stages' landmark tables), TABLES/PIC.done.json (written last) and
    BATCH_SUMMARY.txt / BATCH_SUMMARY.json, and the figure BATCH_SUMMARY.png (rms residual before
    and after and landmarks found vs selected per picture; --no-figure: none); --plots adds
    PLOTS/PIC.register.png and PLOTS/PIC.pose.png per picture.  A batch is resumable: a picture
    whose done-marker matches the options and its input SUM is skipped unless --force, so an
    interrupted batch continues where it stopped.  The results do not depend on --jobs or --scheduler.

    Summary columns (one row per picture, in list order): picture, candidates, selected (maplets
    selected), found (landmarks registered), used (in the pose solve), rms_before_px and
    rms_after_px (residual rms at the a-priori and the solved pose), dposition_km and
    dattitude_rad (size of the pose change), status: ok, inconsistent (solved and written, but
    chi2 of the fit above its 99.9 % quantile: the covariance is scaled by cost/dof and the worst
    landmarks are named after the table), prior-contradicted (solved and written, but the
    measurements contradict the SUM's SIGMA_VSO/SIGMA_PTG: rerun with --no-prior or --prior-scale
    auto), no-pose (the pose could not be solved:
    too few landmarks or no convergence; the SUM holds the registered landmarks only) or failed
    (the picture could not be processed; the reason follows the table as '# PIC failed: ...' and
    is printed on stderr at once).  --json writes the same rows with the full status text, the
    pose change vectors and per-stage timings.  A failed picture never stops the batch; the exit
    code is 1 when any picture failed, else 0.

    With --rounds N (SPC's cycle, S16 Fig. 3), round 1 is the batch above in DIR/ROUND1; then every
    landmark position and pose is refined from all its measurements (the 'spctool geometry' solve,
    weighed by the register tables' covariances) into a refined working directory DIR/MAP2 (its own
    SUMFILES/, LMKFILES/, MAPFILES/; links to everything else), and round 2 measures again on it, and
    so on.  The summary is the last round's; '# round' lines give each round's counts.

    Example:

    \b
      spctool -C demo batch --jobs 2
      spctool -C demo batch --rounds 2 --out-dir cycle
      spctool -C demo batch PICTLIST.TXT --out-dir run1 --json > run1.json
      spctool -C demo batch --reach 50 --out-dir run50  # a-priori errors up to ~50 px
      spctool -C demo batch --scheduler tcp://127.0.0.1:8786 --out-dir run1
    """
    from spctool.batch import BatchOptions, batch_pictures, run_batch
    from spctool.stages.navigate import NavigateOptions
    from spctool.stages.register import RegisterOptions

    workdir = Path(ctx.workdir)
    if lithos and rounds < 2:
        raise SpcUsageError("--lithos refines the map between rounds: give --rounds 2 or more")
    if not workdir.is_dir():
        raise SpcUsageError(f"{workdir}: no such working directory")
    if scheduler is not None:  # before any work: malformed exit 2 at once, unreachable within the timeout
        from spctool.batch.scheduler import check_scheduler

        check_scheduler(scheduler)
    target = Path(out_dir) if out_dir else workdir / "BATCH"
    from spctool.batch.driver import check_out_dir

    check_out_dir(workdir.resolve(), target.resolve())  # before any work: never an input folder
    if reach_px is not None and schedule != "two-pass":
        raise SpcUsageError(f"--reach applies to --schedule two-pass, not {schedule}")
    pose = options.pose_options(sigma_px, no_prior, min_landmarks, prior_scale)
    register = RegisterOptions(
        schedule="retina_s16" if schedule == "two-pass" else options.register_schedule(schedule),
        space=space,
        corr_min=corr_min,
        pose=pose,
    )
    batch_options = BatchOptions(
        occlusion=occlusion,
        register=register,
        pose=pose,
        two_pass=(
            NavigateOptions(reach_px=reach_px or 25.0, weights=weights) if schedule == "two-pass" else None
        ),
        settings_path=ctx.settings_path,
        shape_path=shape_path,
    )
    names = batch_pictures(workdir, pictlist)
    if not names:
        where = pictlist or f"{workdir}/PICTLIST.TXT (or SUMFILES/)"
        raise SpcUsageError(f"no pictures to process in {where}")
    ctx.info(f"{len(names)} pictures -> {target}")

    # no progress-bar thread: local workers are forked only from a single-threaded process
    with progress(ctx, "batch", len(names), threaded=False) as advance:

        def on_result(summary):
            for note in summary.notes:  # e.g. a corrupt MAP: the picture goes on without that landmark
                ctx.warn(f"{summary.picture}: {note}")
            if summary.failed:
                click.echo(f"spctool: {summary.picture} {summary.status}", err=True)
            elif summary.kind != "ok":
                ctx.info(f"{summary.picture} {summary.status}")
            advance()

        if rounds == 1:
            result = run_batch(
                workdir,
                names,
                batch_options,
                out_dir=target,
                jobs=jobs,
                scheduler=scheduler,
                force=force,
                on_result=on_result,
                on_note=ctx.note_once,
            )
            cycle = None
        else:
            from spctool.batch.rounds import run_rounds

            cycle = run_rounds(
                workdir,
                names,
                batch_options,
                out_dir=target,
                rounds=rounds,
                settings=ctx.settings(),
                refine_kw={"lithos": lithos, "jobs": jobs},
                jobs=jobs,
                scheduler=scheduler,
                force=force,
                on_result=on_result,
                on_note=ctx.note_once,
            )
            result = cycle.last
            target = result.out_dir

    if cycle is None:
        emit(result.to_json() if as_json else result.to_text(), output)
    else:
        emit(_rounds_text(cycle, as_json), output)
        for i, r in enumerate(cycle.refinements):  # a refinement not to be trusted is said (as geometry)
            if r.get("verdict", "ok") != "ok":
                ctx.warn(f"map {i + 2} (refined from round {i + 1}): {r.get('verdict_reason', r['verdict'])}")
    if not no_figure or plots:
        from spctool.cli import figures

        if not no_figure:
            ctx.info(f"wrote {figures.batch_summary_figure(result, target / 'BATCH_SUMMARY.png')}")
        if plots:
            ctx.info(
                f"wrote {figures.picture_plots(ctx, result, target, workdir)} plots to {target / 'PLOTS'}"
            )
    counts = result.counts()
    ctx.info(
        f"{len(result.pictures)} pictures in {result.elapsed_s:.1f} s ({result.mode}, {result.workers} "
        f"worker(s)): {result.counts_text()}, {counts['resumed']} done earlier"
    )
    failed = result.failed
    if failed:
        shown = ", ".join(p.picture for p in failed[:5]) + (", ..." if len(failed) > 5 else "")
        raise SpcResultError(f"{len(failed)} of {len(result.pictures)} pictures failed: {shown}")


def _rounds_text(cycle, as_json: bool) -> str:
    """The last round's summary with one line per round (text), or every round's document (JSON)."""
    import json

    if as_json:
        doc = cycle.last.to_json_dict()
        doc["rounds"] = [
            {
                "out_dir": str(b.out_dir),
                "counts": b.counts(),
                "refinement": cycle.refinements[i - 1] if i else None,
            }
            for i, b in enumerate(cycle.batches)
        ]
        from spctool.jsonsafe import json_safe

        return json.dumps(json_safe(doc), indent=1) + "\n"
    lines = []
    for i, b in enumerate(cycle.batches):
        found = sum(p.found or 0 for p in b.pictures)
        c = b.counts()
        text = (
            f"# round {i + 1} ({b.out_dir}): {c['ok']} ok, {c['no-pose']} no-pose, {c['failed']} failed; "
            f"{found} landmarks found"
        )
        if i:
            r = cycle.refinements[i - 1]
            text += (
                f"; map refined from round {i}: {r['landmarks_refined']} of {r['landmarks']} landmarks, "
                f"chi2/dof {r['reduced_chi2']:.3g}"
            )
            if "heights" in r:
                wrote = sum(h["written"] for h in r["heights"])
                text += f"; heights solved and written for {wrote} of {len(r['heights'])} maplets"
        lines.append(text)
    return "\n".join(lines) + "\n" + cycle.last.to_text()


def register(cli):
    cli.add_command(batch_cmd)
