"""``project``: landmark -> pixel, and pixel -> line of sight, with a picture's SPC camera (L15 §1)."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

import click
import numpy as np

from spctool import __version__
from spctool.cli import options
from spctool.cli.common import (
    Context,
    emit,
    emit_table,
    load_picture,
    load_shape,
    pass_context,
    resolve_landmarks,
)
from spctool.errors import SpcUsageError
from spctool.formats.table import LandmarkTable

if TYPE_CHECKING:
    from spctool.geometry.camera import Camera


def project_table(camera: Camera, landmarks, picture_name: str) -> LandmarkTable:
    """Predicted pixels of landmarks (their LMK VLM) as a landmark table."""
    names = [lm.name for lm in landmarks]
    if not landmarks:
        return LandmarkTable.from_rows([], picture=picture_name)
    vlm = np.array([lm.vlm for lm in landmarks], dtype=np.float64)
    sample, line, front = camera.project_with_mask(vlm)
    inside = camera.in_image(sample, line)
    rng = np.linalg.norm(vlm - camera.position, axis=1)
    status = np.where(~front, "behind", np.where(inside, "ok", "outside"))
    return LandmarkTable(
        {"name": names, "sample": sample, "line": line, "range_km": rng, "status": list(status)},
        picture=picture_name,
    )


def linescan_table(pic, settings, landmarks) -> LandmarkTable:
    """Predicted pixels of landmarks in a line-scan picture (SPC's pushbroom projection, xV2IMGPL)."""
    from spctool.geometry.linescan import linescan_position, project_linescan

    names = [lm.name for lm in landmarks]
    if not landmarks:
        return LandmarkTable.from_rows([], picture=pic.name)
    vlm = np.array([lm.vlm for lm in landmarks], dtype=np.float64)
    sample, line, inside = project_linescan(pic, vlm, settings)
    finite = np.isfinite(sample) & np.isfinite(line)
    # the spacecraft position at each landmark's own line (SCOBJ points spacecraft -> body centre)
    at = np.where(finite, line, pic.ctr[1])
    rng = np.linalg.norm(vlm + linescan_position(pic, at), axis=1)
    status = np.where(~finite, "behind", np.where(inside, "ok", "outside"))
    return LandmarkTable(
        {"name": names, "sample": sample, "line": line, "range_km": rng, "status": list(status)},
        picture=pic.name,
    )


@click.command("project")
@options.picture_argument
@click.argument("landmarks", nargs=-1, shell_complete=options.complete_landmark)
@options.landmarks_table_option("Take landmark names from a landmark table ('-' = stdin).")
@click.option(
    "--inverse",
    nargs=2,
    type=options.FINITE_FLOAT,
    metavar="SAMPLE LINE",
    help="Instead: the line of sight of pixel (SAMPLE, LINE) and, with a shape, the surface point hit.",
)
@options.shape_option(" for --inverse")
@options.json_option
@options.output_option
@pass_context
def project_cmd(ctx: Context, picture, landmarks, landmarks_table, inverse, shape_path, as_json, output):
    """Project landmarks into PICTURE, or a pixel back onto the body.

    LANDMARKS are names (LMKFILES/NAME.LMK), LMK files or landmark tables; default: every
    landmark of LMRKLIST.TXT (else LMKFILES/). The camera is the SUM's pose and K-matrix with the
    INIT_LITHOS DISTORT= model matching the picture; a line-scan (pushbroom) picture is projected
    with its per-line pose (the SUM's LINE SCAN DATA), as SPC does.

    Columns: name, sample and line (the predicted SPC pixel, 1-based), range_km (spacecraft to
    landmark), status (ok, outside the photo, behind the camera).  --inverse prints the line of
    sight of one pixel instead: in_image, spacecraft_position (km, body frame), direction_body and
    direction_camera (unit vectors) and, with a shape, the surface_point, range_km, latitude_deg,
    longitude_deg and radius_km where it meets the body.

    Example:

    \b
      spctool -C demo project P000000001A1
      spctool project demo/SUMFILES/P000000001A1.SUM demo/LMKFILES/B01980.LMK --json
      spctool -C demo project P000000001A1 --inverse 384.5 384.5
    """
    _, pic, settings, camera = load_picture(ctx, picture, allow_linescan=True)
    command = "project " + picture
    if camera is None:  # a line-scan (pushbroom) picture: each line has its own pose
        if inverse:
            raise SpcUsageError(
                f"picture {pic.name} is a line-scan picture: --inverse needs a frame camera "
                "(landmark -> pixel works)"
            )
        lms = resolve_landmarks(ctx, landmarks, landmarks_table)
        t = linescan_table(pic, settings, lms)
        t.command = command
        emit_table(t, as_json=as_json, output=output)
        return
    if inverse:
        if landmarks or landmarks_table:
            raise SpcUsageError("--inverse takes a pixel, not landmarks")
        sample, line = inverse
        direction = camera.pixel_to_direction(np.array([sample]), np.array([line]))[0]
        doc = {
            "command": command,
            "picture": pic.name,
            "spctool_version": __version__,
            "sample": sample,
            "line": line,
            "in_image": bool(camera.in_image(np.array([sample]), np.array([line]))[0]),
            "spacecraft_position": camera.position.tolist(),
            "direction_body": direction.tolist(),
            "direction_camera": (camera.rotation @ direction).tolist(),
        }
        shape = load_shape(ctx, shape_path)
        if shape is None:
            ctx.note_once(
                "no shape model: the surface point is not computed (give --shape or SHAPEFILES/SHAPE.TXT)"
            )
        else:
            hit = shape.first_hit(camera.position[None, :], direction[None, :])
            if bool(hit.hit[0]):
                point = hit.point[0]
                r = float(np.linalg.norm(point))
                doc["surface_point"] = point.tolist()
                doc["range_km"] = float(hit.t[0])
                doc["latitude_deg"] = float(np.degrees(np.arcsin(point[2] / r)))
                doc["longitude_deg"] = float(np.degrees(np.arctan2(point[1], point[0])) % 360.0)
                doc["radius_km"] = r
            else:
                doc["surface_point"] = None
        if as_json:
            emit(json.dumps(doc, indent=2) + "\n", output)
        else:
            lines = [f"# spctool {__version__}", f"# picture: {pic.name}", f"# command: {command}"]
            for key, value in doc.items():
                if key in ("command", "picture", "spctool_version"):
                    continue
                if isinstance(value, list):
                    value = " ".join(f"{v:.10g}" for v in value)
                lines.append(f"{key:<20} {value}")
            emit("\n".join(lines) + "\n", output)
        return
    lms = resolve_landmarks(ctx, landmarks, landmarks_table)
    t = project_table(camera, lms, pic.name)
    t.command = command
    emit_table(t, as_json=as_json, output=output)


def register(cli):
    cli.add_command(project_cmd)
