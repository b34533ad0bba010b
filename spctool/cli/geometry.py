"""``geometry``: refine every landmark position (VLM) and picture pose from all registered pictures.

SPC's GEOMETRY step (map-refinement.md §1): the working directory's measurements
(:func:`spctool.batch.refine.gather`) → :func:`spctool.stages.bundle.solve_bundle` → the LMK, MAP and SUM
files rewritten (:func:`spctool.batch.refine.updated_files`, atomic, ``.bak`` kept) and the reports.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import click
import numpy as np

from spctool.cli import options
from spctool.cli.common import Context, check_output, emit, pass_context, warn_row_columns
from spctool.errors import SpcResultError


@click.command("geometry")
@click.argument("pictures", nargs=-1, shell_complete=options.complete_picture)
@click.option(
    "--tables",
    "tables",
    metavar="DIR",
    type=click.Path(file_okay=False, exists=True),
    help="Folder of register tables (<PIC>.register.txt; a batch --out-dir is accepted): each measurement "
    "weighed by its own covariance (sigma_sample, sigma_line, rho_sl).  Default: the SUM LANDMARKS rows, "
    "weighed 1/sigma_px^2.",
)
@click.option(
    "--from-batch",
    "from_batch",
    metavar="OUT",
    type=click.Path(file_okay=False, exists=True),
    help="Take the pictures, their SUMs (solved poses, measured LANDMARKS rows) and register tables from a "
    "batch --out-dir OUT; the refined files are written to the working directory as usual.",
)
@options.sigma_px_option(
    default=0.25,
    help="1-sigma pixel noise of a SUM LANDMARKS measurement (per axis).",
)
@click.option(
    "--sigma-floor-px",
    type=options.FiniteFloatRange(min=0.0),
    default=0.05,
    show_default=True,
    metavar="PX",
    help="Added in quadrature to each register table covariance (--tables).",
)
@click.option(
    "--mode",
    type=click.Choice(["joint", "alternate"]),
    default="joint",
    show_default=True,
    help="joint: one sparse bundle adjustment of every VLM and pose; alternate: SPC's alternation "
    "(landmarks with poses fixed, then poses with landmarks fixed, repeated) for reproducing legacy runs.",
)
@click.option(
    "--reject-sigma",
    type=options.FiniteFloatRange(min=0.0, min_open=True),
    default=5.0,
    show_default=True,
    metavar="K",
    help="Flag a measurement whose normalised residual exceeds K times the robust residual scale "
    "(the worst of each landmark per round), then refit.",
)
@click.option("--no-reject", is_flag=True, help="No outlier flagging.")
@click.option(
    "--min-pictures",
    type=click.IntRange(min=1),
    default=2,
    show_default=True,
    metavar="N",
    help="A landmark needs N usable pictures to be refined; fewer: its VLM keeps its prior.",
)
@click.option(
    "--min-parallax",
    "min_parallax",
    type=options.FiniteFloatRange(min=0.0),
    default=1.0,
    show_default=True,
    metavar="DEG",
    help="A landmark needs lines of sight spread by DEG degrees to be refined.",
)
@click.option(
    "--ignore-in-vlm",
    "ignore_in_vlm",
    multiple=True,
    metavar="PIC",
    help="A picture whose measurements do not constrain any VLM (SPC's 'ignore image in Vlm'); its pose "
    "is solved against the refined landmarks.  Repeatable.",
)
@click.option(
    "--estimate-camera",
    "estimate_camera",
    metavar="TERMS",
    default="",
    help="Also solve camera terms, comma-separated among focal, ctr, ky, kyx, owen (K_x and K_xy stay "
    "fixed: L15 1.1.1).",
)
@click.option(
    "--camera-sigma",
    type=options.FiniteFloatRange(min=0.0, min_open=True),
    default=None,
    metavar="F",
    help="A-priori 1-sigma of the camera terms (relative for focal/ky/kyx, px for ctr).  Default: none.",
)
@click.option(
    "--covariance",
    type=click.Choice(["auto", "full", "conditional"]),
    default="auto",
    show_default=True,
    help="full: joint covariances (dense inverse of the reduced system); conditional: landmark and pose "
    "covariances with the others held (large problems); auto: full up to 4,000 pose unknowns.",
)
@click.option("--dry-run", is_flag=True, help="Solve and report; write no SUM, LMK or MAP file.")
@click.option(
    "--force",
    is_flag=True,
    help="Write the files even when the fit is implausible (cost/dof above 100; otherwise exit 1, nothing "
    "written).",
)
@click.option(
    "--report-dir",
    "report_dir",
    metavar="DIR",
    type=click.Path(file_okay=False),
    help="Also write RESIDUALS.txt (per measurement), LANDMARKS.txt (per landmark), LMKVECS.TXT and "
    "geometry.json here.",
)
@click.option(
    "--plot",
    metavar="FILE.png",
    type=click.Path(dir_okay=False),
    help="Landmark corrections with their 1-sigma ellipses, and the rms residual per picture (PNG).",
)
@options.output_option
@options.json_option
@pass_context
def geometry_cmd(
    ctx: Context,
    pictures,
    tables,
    from_batch,
    sigma_px,
    sigma_floor_px,
    mode,
    reject_sigma,
    no_reject,
    min_pictures,
    min_parallax,
    ignore_in_vlm,
    estimate_camera,
    camera_sigma,
    covariance,
    dry_run,
    force,
    report_dir,
    plot,
    output,
    as_json,
):
    """Refine landmark positions (VLM) and picture poses from every registered picture (SPC's GEOMETRY).

    Reads the pictures (PICTURES, default: PICTLIST's active ones), their measured landmarks (the SUM
    LANDMARKS rows written by register --write-sum, navigate or batch; a '*' row is not used; or the
    register tables of --tables) and the landmarks' LMK files, and solves all VLMs and poses jointly:
    a sparse bundle adjustment with each landmark eliminated as a 3x3 block, priors from SIGMA_VSO and
    SIGMA_PTG (pictures) and SIGMA_LMK or SIGKM (landmarks), INIT_LITHOS PICWTS=/LMKWTS= applied.
    The common translation, rotation and scale of the solution are fixed by the priors only: if they
    leave one free, the command refuses (exit 1) instead of returning an arbitrary solution.

    Outliers are flagged robustly and refitted; a landmark with fewer than --min-pictures usable
    pictures or less parallax than --min-parallax keeps its VLM (status undetermined).

    Writes (unless --dry-run; atomic, each replaced file kept as FILE.bak): LMK VLM, SIGMA_LMK
    (posterior 1-sigma, km, scaled by chi2/dof when above 1), RMSLMK (rms post-fit
    residual in pixels) and the PICTURES rows (measured sample/line, '*' = not used); the MAP header V =
    VLM; the SUM's SCOBJ, CX/CY/CZ, SIGMA_VSO/SIGMA_PTG and a '*' on outlier LANDMARKS rows.

    Output: one row per landmark (vlm_x/y/z km, dx/dy/dz_m correction, sigma_x/y/z_m, pictures used,
    parallax_deg, rms_px, status) and a summary in the header; --json adds pictures, formal
    uncertainty (best 80 % of landmarks, as SPC's get80), gauge and counts.  Every sigma reported is
    the one written: the formal one scaled by chi2/dof when above 1 (covariance_scale).

    --mode alternate runs SPC's alternation for up to 30 rounds and reports where it stopped beside the
    joint minimum of the same cost (a warning with both costs); it is not an error for it to stop short.

    Consistency (solve-pose's chi-square gate): the minimised cost (chi2 + priors) above the 99.9 %
    quantile of chi-square with the solve's degrees of freedom is an inconsistent fit: a warning with
    the figures, the landmarks with the largest shares and the remedy; the files are written, their
    sigmas scaled.  Above 100 per degree of freedom it is implausible: exit 1 and nothing written
    (--force writes it).  The JSON says which (verdict, consistency).

    Exit codes: 0 solved; 1 not solvable as asked (free gauge, no measurements), the joint solve did
    not converge, or an implausible fit; 2 bad input.

    Examples:

    \b
      spctool -q -C demo batch --out-dir geo-out
      spctool -C demo geometry --from-batch geo-out --dry-run
      spctool -C demo geometry --from-batch geo-out --mode alternate --dry-run --json
      spctool -C demo geometry --from-batch geo-out --report-dir geo-report --plot geometry.png
    """
    from spctool.batch import refine
    from spctool.stages.bundle import BundleOptions, group_rms, solve_bundle

    terms = tuple(t.strip() for t in estimate_camera.split(",") if t.strip())
    opts = BundleOptions(
        mode=mode,
        reject_outliers=not no_reject,
        reject_sigma=reject_sigma,
        min_pictures=min_pictures,
        min_parallax_deg=min_parallax,
        estimate_camera=terms,
        camera_sigma=camera_sigma,
        covariance=covariance,
    )
    wd = ctx.wd
    inputs = refine.gather(
        wd,
        ctx.settings(),
        pictures=pictures,
        tables=tables,
        sigma_px=sigma_px,
        sigma_floor_px=sigma_floor_px,
        ignore_in_vlm=ignore_in_vlm,
        from_batch=from_batch,
    )
    for note in inputs.notes:
        ctx.note_once(note)
    _say_unused_sigma(ctx, inputs)
    for src, pic in inputs.row_sources:  # SUM LANDMARKS rows off SPC's columns are said (issue #40)
        warn_row_columns(ctx, src, pic, "(landmark sample, line)")
    check_output(output)  # before any file is rewritten: a bad -o must not end a run whose files are written
    prob = inputs.problem
    ctx.info(
        f"{len(prob.picture_names)} pictures, {len(prob.landmark_names)} landmarks, "
        f"{int(prob.obs_use.sum())} usable measurements ({inputs.source})"
    )
    result = solve_bundle(prob, opts)
    refused = result.verdict == "implausible" and not force  # solve-pose's rule: nothing written
    for w in result.warnings:
        if w == result.verdict_reason and refused:
            continue  # the error line below says it
        ctx.warn(w + (" (written because of --force)" if w == result.verdict_reason and force else ""))
    table = refine.summary_table(result, prob)
    summary = _summary(result, prob, inputs, opts)
    table.meta.update(summary)
    table.comments.extend(_summary_lines(summary))
    files = {} if dry_run or refused else refine.updated_files(inputs, result, wd)
    written = refine.write_back(files) if files else []
    summary["written"] = [str(p) for p in written]
    if written:
        ctx.info(f"wrote {len(written)} file(s) (each replaced one kept as .bak)")
    if report_dir:
        _reports(Path(report_dir), result, prob, inputs, summary)
    if plot:
        from spctool.figures.refine import refinement_plot

        used = np.array([s in ("ok", "undetermined", "ignored-in-vlm") for s in result.obs_status])
        rb = group_rms(result.residual_before, prob.obs_picture, used, len(prob.picture_names))
        ra = group_rms(result.residual_after, prob.obs_picture, used, len(prob.picture_names))
        nout = np.bincount(
            prob.obs_picture[np.array([s == "outlier" for s in result.obs_status], dtype=bool)],
            minlength=len(prob.picture_names),
        )
        # the ellipses at the sigmas written (scaled as SIGMA_LMK)
        shown = replace(result, landmark_covariance=result.landmark_covariance * result.covariance_scale)
        refinement_plot(shown, rb, ra, nout).save(plot)
    if as_json:  # JSON has no NaN: an undefined figure (no landmark refined) is null
        from spctool.jsonsafe import json_safe

        emit(json.dumps(json_safe(_json_doc(table, summary)), indent=1) + "\n", output)
    else:
        emit(table.to_text(), output)
    if not result.converged and mode == "joint":  # the alternation's stop is SPC's, and said above
        raise SpcResultError(f"the refinement did not converge in {opts.max_iter} iterations")
    if refused:
        raise SpcResultError(
            result.verdict_reason + ("" if dry_run else "; no LMK, MAP or SUM written (--force writes them)")
        )


def _say_unused_sigma(ctx, inputs) -> None:
    """A note when --sigma-px or --sigma-floor-px was given but weighs nothing: --sigma-px weighs only SUM
    LANDMARKS rows (every picture had a register table here), --sigma-floor-px only register tables."""
    given = click.get_current_context()

    def on_line(name):
        return given.get_parameter_source(name) is click.core.ParameterSource.COMMANDLINE

    from_rows = len(inputs.row_sources)
    if on_line("sigma_px") and from_rows == 0:
        ctx.note_once(
            "--sigma-px weighs SUM LANDMARKS rows only: every picture has a register table, whose "
            "covariances (+ --sigma-floor-px) weigh its measurements"
        )
    if on_line("sigma_floor_px") and from_rows == len(inputs.problem.picture_names):
        ctx.note_once("--sigma-floor-px applies to register tables only: no picture has one (--sigma-px)")


def _summary(result, prob, inputs, opts) -> dict:
    from spctool.batch.refine import formal_summary

    ok_l = np.array([s == "ok" for s in result.landmark_status])
    d = np.linalg.norm(result.landmark_positions - result.landmark_positions0, axis=1) * 1000.0
    used = np.array([s in ("ok", "undetermined", "ignored-in-vlm") for s in result.obs_status])
    rms_b = float(np.sqrt(np.mean(result.residual_before[used] ** 2))) if used.any() else math.nan
    rms_a = float(np.sqrt(np.mean(result.residual_after[used] ** 2))) if used.any() else math.nan
    dp = np.linalg.norm(result.delta_position, axis=1) * 1000.0
    return {
        "mode": result.mode,
        "source": inputs.source,
        "n_pictures": len(prob.picture_names),
        "n_landmarks": len(prob.landmark_names),
        "n_landmarks_refined": int(ok_l.sum()),
        "measurements": result.counts(),
        "iterations": result.iterations,
        "converged": result.converged,
        "chi2": result.chi2,
        "dof": result.dof,
        "reduced_chi2": result.reduced_chi2,
        "verdict": result.verdict,
        "consistency": {
            "consistent": result.verdict == "ok",
            "cost": result.cost,
            "chi2": result.chi2,
            "prior_cost": result.prior_cost,
            "dof": result.dof,
            "quantile": result.consistency_quantile,
            "limit": result.consistency_limit,
            "max_reduced_chi2": result.max_reduced_chi2,
            "reason": result.verdict_reason,
        },
        "rms_before_px": rms_b,
        "rms_after_px": rms_a,
        "vlm_correction_rms_m": float(np.sqrt(np.mean(d[ok_l] ** 2))) if ok_l.any() else math.nan,
        "position_change_rms_m": float(np.sqrt(np.mean(dp**2))) if dp.size else math.nan,
        "covariance_scale": result.covariance_scale,
        "formal_uncertainty": formal_summary(result),
        "gauge_sigma": result.gauge_sigma,
        "covariance": result.covariance_kind,
        "camera_terms": {
            k: {t: [v[0], v[1], v[2] * math.sqrt(result.covariance_scale)] for t, v in d2.items()}
            for k, d2 in result.camera_terms.items()
        },
        "weights": inputs.weights,
        "outlier_rounds": result.outlier_rounds,
        "warnings": list(result.warnings),
        "options": opts.as_dict(),
        "time_s": result.timing.get("total_s", math.nan),
    }


def _summary_lines(s: dict) -> list[str]:
    counts = s["measurements"]
    f = s["formal_uncertainty"]
    c = s["consistency"]
    return [
        f"geometry ({s['mode']}): {s['n_pictures']} pictures, {s['n_landmarks']} landmarks "
        f"({s['n_landmarks_refined']} refined), measurements "
        + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())),
        f"{s['iterations']} iterations, {'converged' if s['converged'] else 'NOT converged'}; "
        f"chi2/dof {s['reduced_chi2']:.3g}; rms residual {s['rms_before_px']:.4g} -> "
        f"{s['rms_after_px']:.4g} px",
        f"consistency: {s['verdict'].upper() if s['verdict'] != 'ok' else 'ok'} (cost {c['cost']:.4g} = "
        f"chi2 + priors, {c['dof']} dof, {100 * c['quantile']:g} % limit {c['limit']:.4g})",
        f"VLM corrections rms {s['vlm_correction_rms_m']:.4g} m; pose position changes rms "
        f"{s['position_change_rms_m']:.4g} m",
        f"formal 1-sigma of the best 80% of landmarks: rms {f['best80_rms_m']:.4g} m, max "
        f"{f['best80_max_m']:.4g} m ({s['covariance']} covariance)",
        "every sigma here and in the files written is the formal one"
        + (
            f" x sqrt(chi2/dof) = x {math.sqrt(s['covariance_scale']):.4g}"
            if s["covariance_scale"] > 1.0
            else " (chi2/dof <= 1: not scaled)"
        ),
    ]


def _json_doc(table, summary) -> dict:
    doc = table.to_json_dict()
    doc.update(summary)
    return doc


def _reports(folder: Path, result, prob, inputs, summary) -> None:
    from spctool.batch import refine
    from spctool.formats import atomic

    res = refine.residuals_table(result, prob)
    atomic.write_bytes(folder / "RESIDUALS.txt", res.to_text().encode("utf-8"), backup=True)
    lm = refine.summary_table(result, prob)
    atomic.write_bytes(folder / "LANDMARKS.txt", lm.to_text().encode("utf-8"), backup=True)
    atomic.write_bytes(
        folder / "LMKVECS.TXT", refine.lmkvecs_text(result, inputs.landmarks).encode("latin-1"), backup=True
    )
    from spctool.jsonsafe import json_safe

    atomic.write_bytes(
        folder / "geometry.json",
        (json.dumps(json_safe(summary), indent=1) + "\n").encode("utf-8"),
        backup=True,
    )


def register(cli):
    cli.add_command(geometry_cmd)


__all__ = ["geometry_cmd", "register"]
