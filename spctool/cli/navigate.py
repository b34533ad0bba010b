"""``navigate``: two-pass navigation of one picture (acquire, pose, re-register from it, pose).

A thin command over :func:`spctool.stages.navigate.navigate`; the inputs are those of ``register``
(:class:`spctool.cli.register._Inputs`: SUM, INIT_LITHOS, photo, MAPFILES/ maplets, LMK positions,
landmarks from names, ``--landmarks`` or lithos-select).  ``--output`` writes the SUM as ``batch``
does: the registered landmarks in LANDMARKS and, when the pose converged, the solved SCOBJ, CX, CY,
CZ, SIGMA_VSO and SIGMA_PTG (every other line unchanged).
"""

from __future__ import annotations

from pathlib import Path

import click

from spctool.cli import options
from spctool.cli.common import Context, emit_table, pass_context, progress
from spctool.errors import SpcResultError, SpcUsageError


def _spacings(text: str) -> tuple:
    try:
        out = tuple(int(t) for t in text.replace(" ", ",").split(",") if t)
    except ValueError:
        out = ()
    if not out or min(out) < 1:
        raise SpcUsageError(f"--refine-spacings expects spacings like 2,1, got {text!r}")
    return out


@click.command("navigate")
@options.picture_argument
@options.landmark_names_argument
@options.landmarks_table_option(
    "Landmarks and a-priori pixels from a landmark table ('-' = stdin), e.g. the output of "
    "lithos-select. Default: the named LANDMARKs, else run lithos-select on LMRKLIST.TXT / LMKFILES/."
)
@click.option(
    "--project",
    "project",
    is_flag=True,
    help="Start from the projection of each landmark with the SUM pose, not the table pixels.",
)
@options.sum_option
@options.any_picture_option
@options.photo_option()
@options.flip_rows_option
@options.space_option
@options.template_shading_option
@options.photo_shadows_option
@options.corr_min_option
@options.photometry_option
@options.thresholds_option
@options.reach_option(
    "Pass 1's coarse search reaches at least +-PX pixels (S16's L = 10 reach), with the spacing "
    "adapted to the maplet size.",
    default=25.0,
)
@click.option(
    "--refine-spacings",
    default="2,1",
    show_default=True,
    metavar="LIST",
    help="Pass 2's spacings from the solved pose (each searches +-5 x spacing cells).",
)
@click.option(
    "--single-pass",
    is_flag=True,
    help="Stop after pass 1 (acquisition and one pose solve).",
)
@options.sigma_px_option()
@options.weights_option()
@options.no_prior_option
@options.prior_scale_option
@options.min_landmarks_option
@click.option(
    "--output",
    "sum_output",
    metavar="FILE.SUM",
    type=click.Path(dir_okay=False),
    help="Write the SUM with the registered LANDMARKS rows and the solved pose (only when it converged).",
)
@click.option(
    "-o",
    "--table-output",
    "table_output",
    metavar="FILE",
    help="Write the landmark table to FILE instead of stdout ('-' = stdout).",
)
@options.threads_option
@options.require_option("Exit 1 when fewer than N landmarks are registered in the final pass.")
@options.json_option
@pass_context
def navigate_cmd(ctx: Context, **kw):
    """Two-pass navigation of a picture: acquire, solve the pose, re-register from it, solve again.

    Pass 1: every landmark is searched from its a-priori pixel by a coarse correlation that reaches
    at least --reach pixels (the spacing adapted so the maplet keeps >= 12 binned cells across; a
    landmark the coarse search misses is moved by the median shift of those it found), refined at
    halving spacings down to 1, and the pose is solved (SUM sigmas as prior, outliers rejected).
    Pass 2: every landmark is registered again from the solved pose with a small search
    (--refine-spacings) and the pose solved again.  Both passes are reported.

    Columns: those of register for the final pass (name, sample, line, apriori_sample,
    apriori_line, dsample, dline, correlation, iterations, spacing), then sample_1, line_1 and
    status_1 (pass 1), residual_sample and residual_line (measured minus predicted with the final
    pose), pose_status (ok, rejected-outlier, ...) and status.  --json adds "passes" (per pass:
    steps, found, rms_before_px, rms_after_px, used, rejected, pose) and "pose" (the final one).
    Exit 1 when no pose could be solved or fewer than --require landmarks were registered.  A pose
    whose chi2 exceeds its 99.9 % quantile (inconsistent: the worst landmarks named, covariance scaled
    by cost/dof) or whose measurements contradict the SUM's SIGMA_VSO/SIGMA_PTG (prior-contradicted:
    --no-prior or --prior-scale auto) is reported in one warning line and in the JSON's pose
    "verdict".

    Example:

    \b
      spctool -C demo navigate P000000001A1
      spctool -C demo navigate P000000001A1 --json -o nav.json --output new.SUM
      spctool -C demo navigate P000000002A1 --single-pass --space image
      spctool -C demo navigate P000000003A1 --weights surface --prior-scale auto
    """
    from spctool.cli.register import _Inputs, _register_options
    from spctool.stages.navigate import NavigateOptions, navigate
    from spctool.stages.register import RegisterOptions

    # register's settings navigate does not expose: RegisterOptions' own defaults, never copies
    kw.update(
        _command="navigate",
        grid_half=RegisterOptions.grid_half,
        min_valid=RegisterOptions.min_valid,
        strict_8=RegisterOptions.strict_8,
        supersample=RegisterOptions.supersample,
        no_image_shadows=not RegisterOptions.image_shadows,
        criteria=None,
    )
    pose = options.pose_options(kw["sigma_px"], kw["no_prior"], kw["min_landmarks"], kw["prior_scale"])
    ropts = _register_options(kw, "retina_s16", pose=pose)
    nopts = NavigateOptions(
        passes=1 if kw["single_pass"] else 2,
        reach_px=kw["reach_px"],
        refine_spacings=_spacings(kw["refine_spacings"]),
        min_landmarks=max(1, kw["min_landmarks"]),
        register=ropts,
        pose=pose,
        weights=kw["weights"],
    )
    inp = _Inputs(ctx, kw)
    if not inp.names:
        raise SpcResultError(f"{inp.pic.name}: no landmark with a maplet to navigate with")
    # maplet space forks its workers: only while this process runs one thread (no refresh thread)
    steps = len(inp.names) * (3 if nopts.passes == 2 else 2)
    with progress(ctx, f"navigate {inp.pic.name}", steps, threaded=ropts.space == "image") as adv:
        result = inp.run(navigate, nopts, adv)
    for w in result.warnings:
        ctx.note_once(w)
    for name in inp.missing:
        ctx.note_once(f"{name}: no maplet, left out")

    wrote = None
    pose = result.pose
    if kw["sum_output"] and pose is not None and result.status == "ok":
        from spctool.formats.sumfile import read_sum, with_measured_landmarks, with_pose, write_sum

        reg = result.final.register
        pic = with_measured_landmarks(read_sum(inp.sum_path), reg.names, reg.measured, reg.ok)
        pic = with_pose(pic, pose.scobj, pose.rotation, pose.sigma_position, pose.sigma_attitude)
        write_sum(Path(kw["sum_output"]), pic, overwrite=True, backup=True)  # a replaced file kept as .bak
        wrote = str(kw["sum_output"])
        ctx.info(f"wrote {wrote}")
    meta = {
        "landmark_source": inp.source,
        "space": ropts.space,
        # a navigated pose that fails its consistency checks is not plain ok (its SUM is still written)
        "status": (
            f"{pose.verdict}: {pose.verdict_reason}"
            if result.status == "ok" and pose is not None and pose.verdict != "ok"
            else result.status
        ),
        "registered": int(result.ok.sum()),
        "passes": [p.as_dict() for p in result.passes],
        "sum_written": wrote,
        "options": nopts.as_dict(),
        "warnings": list(result.warnings),
        "missing": list(inp.missing),
    }
    if pose is not None:
        meta["pose"] = pose.pose_dict()
    table = result.to_table(picture=inp.pic.name, command="navigate", meta=meta)
    for k, p in enumerate(result.passes, 1):
        rms = (
            "-" if p.pose is None else f"{p.pose.rms_after:.4f} px rms after the solve, {p.pose.n_used} used"
        )
        table.comments.append(
            f"pass {k}: {p.found} of {len(p.register)} landmarks registered (steps "
            f"{', '.join(f'{s}x+-{g}' for s, g in p.steps)}); {rms}"
            + (f"; no pose: {p.pose_error}" if p.pose_error else "")
        )
    emit_table(table, as_json=kw["as_json"], output=kw["table_output"])
    if ctx.verbosity >= (1 if kw["as_json"] else 0) and pose is not None:
        for line in pose.summary_lines():
            click.echo(f"spctool: {line}", err=True)
    elif pose is not None and pose.verdict in ("inconsistent", "prior-contradicted", "unchecked"):
        ctx.warn(f"{inp.pic.name}: {pose.verdict}: {pose.verdict_reason}")
    if result.status != "ok":
        raise SpcResultError(f"{inp.pic.name}: {result.status}")
    options.check_require(inp.pic.name, int(result.ok.sum()), kw["require"], "landmarks registered")


def register(cli):
    cli.add_command(navigate_cmd)
