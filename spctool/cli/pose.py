"""``solve-pose``: spacecraft position and attitude from measured landmark pixels (Stage I).

Loads the picture (SUM) and INIT_LITHOS (camera distortion), the measured landmark pixels (a landmark
table from ``register`` or the SUM's own LANDMARKS section) and the landmark positions (LMK VLM and
SIGMA_LMK), runs :func:`spctool.stages.pose.solve_pose` and writes the residual table of
cli-contract.md; ``--output``/``--in-place`` write the SUM with the solved SCOBJ, CX/CY/CZ and
SIGMA_VSO/SIGMA_PTG (every other line byte-identical); ``--plot`` draws the residuals before and after
(:func:`spctool.figures.pose_plot`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import click
import numpy as np

from spctool.cli import options
from spctool.cli.common import (
    Context,
    check_sum_picture,
    emit_table,
    load_picture,
    pass_context,
    warn_row_columns,
)
from spctool.errors import SpcFormatError, SpcResultError, SpcUsageError

# ------------------------------------------------------------------------------------------------
# inputs


@dataclasses.dataclass
class Measurements:
    """Measured landmark pixels (table rows or SUM LANDMARKS rows), with the status of each row."""

    names: list[str]
    sample: np.ndarray
    line: np.ndarray
    status: list[str]  # "ok" = to be used; anything else is passed through to the output
    covariance: np.ndarray | None = None  # (N, 2, 2) px² from sigma_sample, sigma_line, rho_sl


def measurements_from_table(path, picture: str | None = None, any_picture: bool = False) -> Measurements:
    """The rows of a landmark table; a table whose ``# picture:`` header names another picture than
    ``picture`` is refused (SpcUsageError) unless ``any_picture``."""
    from spctool.cli.common import refuse_other_picture
    from spctool.formats.table import read_table

    table = read_table(path)
    if picture:
        refuse_other_picture("table", path, table.picture, picture, any_picture)
    shown = "<stdin>" if str(path) == "-" else path
    made_by = (table.command or "").split(" ")[0]
    if made_by in _PREDICTING_COMMANDS:  # their pixels are the a-priori camera's: no measurement
        raise SpcFormatError(
            shown, None, f"measured pixels (a register, navigate or correlate table), found a {made_by} "
            "table, whose sample and line the SUM's own camera predicts"
        )
    # a correlate table's sample, line are the a-priori pixels; its measurement is measured_sample, _line
    columns = ("measured_sample", "measured_line") if "measured_sample" in table else ("sample", "line")
    missing = [c for c in ("name", *columns) if c not in table]
    if missing:
        raise SpcFormatError(
            shown, None, f"a landmark table with columns name, sample, line (missing: {', '.join(missing)})"
        )
    try:
        smp, lin = (np.asarray(table[c], dtype=np.float64) for c in columns)
    except (TypeError, ValueError):
        raise SpcFormatError(shown, None, f"numbers in the {' and '.join(columns)} columns") from None
    if "status" in table:
        status = ["ok" if str(s) == "ok" else str(s) for s in table["status"]]
    else:
        status = ["ok"] * len(table)
    cov = None
    if all(c in table for c in _COVARIANCE_COLUMNS):
        try:
            ss, sl, rho = (np.asarray(table[c], dtype=np.float64) for c in _COVARIANCE_COLUMNS)
        except (TypeError, ValueError):
            raise SpcFormatError(
                path, None, "expected numbers (or nan) in the sigma_sample, sigma_line and rho_sl columns"
            ) from None
        cov = np.empty((len(ss), 2, 2))
        cov[:, 0, 0], cov[:, 1, 1] = ss * ss, sl * sl
        cov[:, 0, 1] = cov[:, 1, 0] = rho * ss * sl
    return Measurements(table.names, smp, lin, status, cov)


#: commands whose tables hold predicted pixels, never measured ones (solve-pose refuses them)
_PREDICTING_COMMANDS = ("lithos-select", "predict", "extract", "project")

#: the measurement covariance columns of register/correlate tables
_COVARIANCE_COLUMNS = ("sigma_sample", "sigma_line", "rho_sl")


def measurements_from_sum(pic, path=None) -> Measurements:
    """The SUM's LANDMARKS rows (a row flagged ``*`` is passed through, not used); a landmark on two
    rows is refused (SpcFormatError naming ``path``), as a table's is: it would be counted twice."""
    from spctool.formats.guard import check_landmark_rows

    check_landmark_rows(pic, path)
    rows = pic.landmarks
    status = ["flagged" if lm.flag.strip() == "*" else "ok" for lm in rows]
    return Measurements(
        [lm.name for lm in rows],
        np.array([lm.sample for lm in rows], dtype=np.float64),
        np.array([lm.line for lm in rows], dtype=np.float64),
        status,
    )


def load_landmarks(ctx: Context, names, lmk_dir):
    """(positions (N, 3), sigmas (N, 3), found (N,)) from LMK files; missing files give NaN rows."""
    from spctool.formats.guard import check_landmark_geometry
    from spctool.formats.landmark import read_lmk

    n = len(names)
    pos = np.full((n, 3), np.nan)
    sig = np.full((n, 3), np.nan)
    found = np.zeros(n, dtype=bool)
    cache: dict[str, tuple] = {}
    for i, name in enumerate(names):  # file I/O per landmark; the numerics are vectorised
        key = name.strip()
        if key not in cache:
            path = Path(lmk_dir) / f"{key}.LMK" if lmk_dir else ctx.wd.lmk_path(key)
            if path.exists():  # a NaN VLM or a broken frame is bad input, as in every stage (exit 2)
                lmk = check_landmark_geometry(read_lmk(path), path)
                cache[key] = (lmk.vlm, lmk.sigma_lmk)
            else:
                cache[key] = None
        if cache[key] is not None:
            pos[i], sig[i] = cache[key]
            found[i] = True
    return pos, sig, found


# ------------------------------------------------------------------------------------------------
# command


@click.command("solve-pose")
@options.picture_argument
@options.sum_option
@click.option(
    "--measurements",
    "measurements",
    metavar="TABLE",
    type=click.Path(dir_okay=False, allow_dash=True),
    help="Landmark table with name, sample, line (and optionally status: only 'ok' rows are used); "
    "'-' = stdin.  Default: the SUM's own LANDMARKS section.",
)
@click.option(
    "--lmk-dir",
    "lmk_dir",
    metavar="DIR",
    type=click.Path(file_okay=False),
    help="Folder of the LMK files giving landmark positions (VLM) and sigmas (SIGMA_LMK).  "
    "[default: DIR/LMKFILES]",
)
@options.sigma_px_option()
@click.option(
    "--weights",
    type=click.Choice(["uniform", "surface"]),
    default="uniform",
    show_default=True,
    help="uniform: every landmark 1/sigma_px^2 per axis; surface: each landmark by the inverse of its "
    "measurement covariance (the table's sigma_sample, sigma_line, rho_sl from register/correlate; full "
    "2x2), so a weak, smeared correlation peak counts less than a sharp one.",
)
@options.no_prior_option
@options.prior_scale_option
@click.option(
    "--estimate-landmarks",
    is_flag=True,
    help="Also estimate landmark positions, with the LMK SIGMA_LMK as a-priori sigmas.",
)
@click.option(
    "--consider-landmarks",
    is_flag=True,
    help="Keep landmark positions fixed but inflate the covariance by their SIGMA_LMK (consider parameters).",
)
@click.option(
    "--max-iter",
    type=click.IntRange(min=1),
    default=10,
    show_default=True,
    metavar="N",
    help="Maximum Gauss-Newton iterations.",
)
@click.option(
    "--tol",
    type=options.FINITE_FLOAT,
    default=1e-8,
    show_default=True,
    metavar="F",
    help="Convergence: step below F x its 1-sigma, or relative cost change below F.",
)
@click.option(
    "--reject-sigma",
    type=options.FINITE_FLOAT,
    default=5.0,
    show_default=True,
    metavar="K",
    help="Reject a landmark whose normalised residual exceeds K (times the robust residual scale), "
    "worst first, then refit.",
)
@click.option(
    "--reject-px",
    type=options.FINITE_FLOAT,
    default=None,
    metavar="PX",
    help="Reject on an absolute pixel residual above PX instead of --reject-sigma.",
)
@click.option("--no-reject", is_flag=True, help="No outlier rejection.")
@options.min_landmarks_option
@click.option(
    "--output",
    "sum_output",
    metavar="FILE.SUM",
    type=click.Path(dir_okay=False),
    help="Write a SUM with the solved SCOBJ, CX, CY, CZ, SIGMA_VSO, SIGMA_PTG (all other lines unchanged).",
)
@click.option(
    "--in-place", is_flag=True, help="Rewrite the picture's SUM file itself, keeping the old one as FILE.bak."
)
@options.any_picture_option
@click.option(
    "--force",
    "force",
    is_flag=True,
    help="Write the SUM and exit 0 even when the fit is implausible (cost/dof > 100: residuals ~10x "
    "--sigma-px).",
)
@click.option(
    "-o",
    "--table-output",
    "table_output",
    metavar="FILE",
    help="Write the residual table to FILE instead of stdout ('-' = stdout).",
)
@click.option(
    "--plot",
    "plot",
    metavar="FILE.png",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write the residuals before (orange) and after (blue) the solve as vectors over the photo, "
    "magnified by a stated factor, beside a histogram of their lengths (PNG).",
)
@options.photo_option(" for --plot")
@options.flip_rows_option
@options.json_option
@pass_context
def solve_pose_cmd(
    ctx: Context,
    picture,
    sum_path,
    measurements,
    lmk_dir,
    sigma_px,
    weights,
    no_prior,
    prior_scale,
    estimate_landmarks,
    consider_landmarks,
    max_iter,
    tol,
    reject_sigma,
    reject_px,
    no_reject,
    min_landmarks,
    sum_output,
    in_place,
    any_picture,
    force,
    table_output,
    plot,
    photo_path,
    flip_rows,
    as_json,
):
    """Solve the spacecraft position and camera attitude from measured landmark pixels.

    Minimises the weighted pixel residuals (1/sigma_px^2, or with --weights surface each landmark's
    inverse measurement covariance, floored at 0.001 px) of the landmarks' LMK positions
    projected with the picture's camera (SUM + INIT_LITHOS distortion), plus the a-priori term
    from the SUM's SIGMA_VSO (km, body axes) and SIGMA_PTG (rad, camera axes), by Gauss-Newton
    with step halving.  The attitude change is the rotation vector
    theta with [CX;CY;CZ]_new = Rot(-theta) [CX;CY;CZ]_old, in camera axes.  Outliers are
    rejected worst first and named on stderr, in the status column and in the JSON.

    Columns: name, sample and line (measured), apriori_sample/apriori_line (predicted with the
    SUM's pose), predicted_sample/predicted_line (with the solved pose),
    residual_sample_before/residual_line_before and residual_sample_after/residual_line_after
    (measured - predicted, px), and status: ok, rejected-outlier, no-lmk (no LMK file),
    behind-camera, no-measurement, flagged ('*' in the SUM), or the status of the input row.
    With --estimate-landmarks also dx_km, dy_km, dz_km (landmark corrections, body axes).

    --json adds a top-level "pose" object: position, scobj, rotation, delta_position,
    delta_attitude, covariance (6x6, km then rad), sigma_position, sigma_attitude, correlation,
    condition_number, iterations, converged, rejected, chi2, dof, rms before/after,
    covariance_scale, covariance_formal, position_attitude_correlation, plausible.  The text table's
    header block gives the solved position, its 1-sigma, chi2/dof and the largest
    position-attitude correlation; a summary goes to stderr (with --json only with -v).

    Checks: a --measurements table whose '# picture:' header names another picture, or a --sum file of
    another picture, is refused (exit 2; --any-picture). When the residuals exceed --sigma-px (cost/dof
    > 1) the covariance is scaled by cost/dof (both reported). A fit with cost/dof > 100 (residuals ~10x
    --sigma-px: wrong measurements or another picture's table) is implausible: the table is written, no
    SUM, exit 1 (--force writes it). Too few landmarks, degenerate geometry or no convergence: exit 1
    (no SUM is written). --output writes SIGMA_VSO/SIGMA_PTG as the solved 1-sigma values and keeps an
    existing FILE as FILE.bak (also when FILE is the input SUM).

    Example:

    \b
      spctool -C demo solve-pose P000000001A1 --measurements reg.txt --output new.SUM
      cd demo && spctool register P000000001A1 | spctool solve-pose P000000001A1 --measurements - --in-place
      spctool -C fixtures/real/rosetta-67p solve-pose W48230079013.SUM --lmk-dir . --no-prior --json
      spctool -C demo solve-pose P000000001A1 --measurements reg.txt --weights surface
    """
    from spctool.stages.pose import solve_pose

    if estimate_landmarks and consider_landmarks:
        raise SpcUsageError("give --estimate-landmarks or --consider-landmarks, not both")
    if in_place and sum_output:
        raise SpcUsageError("give --output FILE.SUM or --in-place, not both")
    mode = "estimate" if estimate_landmarks else "consider" if consider_landmarks else "fixed"
    pose_options = options.pose_options(
        sigma_px,
        no_prior,
        min_landmarks,
        prior_scale,
        max_iter=max_iter,
        tol=tol,
        landmark_mode=mode,
        reject_outliers=not no_reject,
        reject_sigma=reject_sigma,
        reject_px=reject_px,
    )

    loaded = load_picture(ctx, picture, sum_path)
    check_sum_picture(picture, sum_path, loaded, any_picture)
    src_path, pic, _, camera = loaded
    if measurements:
        meas = measurements_from_table(measurements, pic.name, any_picture)
    else:  # the SUM's LANDMARKS rows are the measurements: rows off SPC's columns are said (issue #40)
        warn_row_columns(ctx, src_path, pic, "(landmark sample, line)")
        meas = measurements_from_sum(pic, src_path)
    if weights == "surface" and meas.covariance is None:
        raise SpcUsageError(
            "--weights surface needs a landmark table with sigma_sample, sigma_line and rho_sl columns "
            "(from register or correlate): give it with --measurements"
        )
    pos, lsig, found = load_landmarks(ctx, meas.names, lmk_dir)
    use = np.array([s == "ok" for s in meas.status], dtype=bool) & found
    missing = [n for n, s, f in zip(meas.names, meas.status, found) if s == "ok" and not f]
    if missing:
        where = lmk_dir or ctx.wd.root / "LMKFILES"
        ctx.note_once(f"no LMK file in {where} for {len(missing)} landmark(s): {', '.join(missing)}")
    ctx.info(f"picture {pic.name}: {int(use.sum())} measured landmarks with positions, landmarks {mode}")

    idx = np.flatnonzero(use)
    y = np.stack([meas.sample[idx], meas.line[idx]], axis=-1)
    result = solve_pose(
        camera,
        pos[idx],
        y,
        pose_options,
        prior_sigma_position=pic.sigma_vso,
        prior_sigma_attitude=pic.sigma_ptg,
        landmark_sigmas=lsig[idx] if mode != "fixed" else None,
        names=[meas.names[i] for i in idx],
        pixel_covariances=meas.covariance[idx] if weights == "surface" else None,
    )

    cols, res0, res1, status = _residual_columns(camera, result, meas, pos, found, idx)

    from spctool.formats.table import LandmarkTable

    wrote = None
    write_target = src_path if in_place else Path(sum_output) if sum_output else None
    if write_target is not None and result.converged and (result.plausible or force):
        from spctool.formats.sumfile import with_pose, write_sum

        new_pic = with_pose(pic, result.scobj, result.rotation, result.sigma_position, result.sigma_attitude)
        backup = write_sum(write_target, new_pic, overwrite=True, backup=True)  # an existing file: .bak
        wrote = str(write_target)
        ctx.info(f"wrote {write_target}" + (f" (old file kept as {backup})" if backup else ""))

    meta = {
        "pose": result.pose_dict(),
        "sum_written": wrote,
        "options": {k: v for k, v in dataclasses.asdict(pose_options).items()},
    }
    table = LandmarkTable(cols, picture=pic.name, command="solve-pose", meta=meta)
    table.comments.append(
        f"solved with {result.n_used} landmarks, {result.iterations} iterations, "
        f"{'converged' if result.converged else 'NOT converged'}; residuals measured - predicted (px)"
    )
    table.comments.extend(result.header_lines())
    emit_table(table, as_json=as_json, output=table_output)
    if plot:
        _plot(ctx, plot, pic, photo_path, flip_rows, meas, res0, res1, status, result)

    if ctx.verbosity >= (1 if as_json else 0):
        for line in result.summary_lines():
            click.echo(f"spctool: {line}", err=True)
    elif result.verdict in ("inconsistent", "prior-contradicted", "unchecked"):  # the summary says it too
        ctx.warn(f"{pic.name}: {result.verdict}: {result.verdict_reason}")
    if not result.converged:
        raise SpcResultError(
            f"{pic.name}: pose did not converge in {pose_options.max_iter} iterations"
            + ("; no SUM written" if write_target is not None else "")
        )
    if not result.plausible:
        if not force:
            raise SpcResultError(
                f"{pic.name}: implausible fit: {result.implausible}"
                + ("; no SUM written (--force writes it)" if write_target is not None else "")
            )
        ctx.warn(f"{pic.name}: implausible fit (written because of --force): {result.implausible}")


def _residual_columns(camera, result, meas, pos, found, idx):
    """The residual table's columns for every input row (rows left out of the solve keep their
    reason and, where their LMK exists, get predictions with both poses); returns ``(columns,
    residuals before (N, 2), residuals after (N, 2), status words)``."""
    n = len(meas.names)
    cols = {"name": list(meas.names), "sample": meas.sample, "line": meas.line}
    # rows left out of the solve (e.g. 'not-found' in a register table) still get predictions when
    # their LMK exists; solved rows take the stage's values (with landmark corrections, if estimated)
    pred0 = np.full((n, 2), np.nan)
    pred1 = np.full((n, 2), np.nan)
    solved = camera.with_pose(scobj=result.scobj, rotation=result.rotation)
    for cam_, pred in ((camera, pred0), (solved, pred1)):
        s_, l_, front = cam_.project_with_mask(pos[found])
        pred[found] = np.where(front[:, None], np.stack([s_, l_], axis=-1), np.nan)
    pred0[idx], pred1[idx] = result.predicted_before, result.predicted_after
    y_all = np.stack([meas.sample, meas.line], axis=-1)
    res0, res1 = y_all - pred0, y_all - pred1
    cols.update(
        apriori_sample=pred0[:, 0],
        apriori_line=pred0[:, 1],
        predicted_sample=pred1[:, 0],
        predicted_line=pred1[:, 1],
        residual_sample_before=res0[:, 0],
        residual_line_before=res0[:, 1],
        residual_sample_after=res1[:, 0],
        residual_line_after=res1[:, 1],
    )
    status = list(meas.status)
    for i in range(n):  # status words only (no numerics)
        if status[i] == "ok" and not found[i]:
            status[i] = "no-lmk"
    for k, i in enumerate(idx):
        status[i] = result.status[k]
    if result.landmark_corrections is not None:
        corr = np.full((n, 3), np.nan)
        corr[idx] = result.landmark_corrections
        cols.update(dx_km=corr[:, 0], dy_km=corr[:, 1], dz_km=corr[:, 2])
    cols["status"] = status
    return cols, res0, res1, status


def _plot(ctx, path, pic, photo_path, flip_rows, meas, res0, res1, status, result):
    from spctool import figures
    from spctool.cli.common import load_photo

    photo = load_photo(ctx, pic, photo_path, flip_rows=flip_rows, required=False)
    if photo is None:
        ctx.note_once(f"no photo for picture {pic.name}: --plot draws on a blank frame")
    fig = figures.pose_plot(
        None if photo is None else photo.data,
        pic.thrsh,
        meas.names,
        np.stack([meas.sample, meas.line], axis=-1),
        res0,
        res1,
        status,
        picture=pic.name,
        rms_before=result.rms_before,
        rms_after=result.rms_after,
        shape=(pic.nln, pic.npx),
    )
    fig.save(path)
    ctx.info(f"wrote {path}")


def register(cli):
    cli.add_command(solve_pose_cmd)
