"""Figures of a finished batch, drawn from its output files (:mod:`spctool.figures` does the drawing).

``batch`` writes ``BATCH_SUMMARY.png`` (rms residual before/after and landmarks found vs selected per
picture) and, with ``--plots``, ``PLOTS/<PIC>.register.png`` (the register overlay) and
``PLOTS/<PIC>.pose.png`` (the solve-pose residual plot) of every picture from its
``TABLES/<PIC>.register.txt`` / ``TABLES/<PIC>.pose.txt`` and its photo in the working directory.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

PLOTS_DIR = "PLOTS"


def batch_summary_figure(result, path) -> Path:
    """Write the summary figure of a :class:`spctool.batch.BatchResult` to ``path``."""
    from spctool import figures

    pics = result.pictures
    title = f"batch: {len(pics)} pictures: {result.counts_text()}"
    fig = figures.batch_summary(
        [p.picture for p in pics],
        [p.rms_before_px for p in pics],
        [p.rms_after_px for p in pics],
        [p.selected for p in pics],
        [p.found for p in pics],
        [p.kind for p in pics],
        title=title,
    )
    fig.save(path)
    return Path(path)


def _column(table, name):
    return np.asarray(table[name], dtype=np.float64) if name in table else None


def picture_plots(ctx, result, out_dir, workdir) -> int:
    """Write ``PLOTS/<PIC>.register.png`` and ``PLOTS/<PIC>.pose.png`` for every picture whose tables
    exist; returns the number of files written.  A picture without a photo is drawn on a blank frame."""
    from spctool import figures
    from spctool.batch import output_paths
    from spctool.errors import SpcError
    from spctool.formats.sumfile import read_sum
    from spctool.formats.table import read_table
    from spctool.formats.workdir import WorkDir

    wd = WorkDir(Path(workdir))
    plots = Path(out_dir) / PLOTS_DIR
    plots.mkdir(parents=True, exist_ok=True)
    written = 0
    for summary in result.pictures:
        paths = output_paths(out_dir, summary.picture)
        try:
            pic = read_sum(wd.sum_path(summary.picture))
            photo = None
            if wd.photo_path(pic.name) is not None:
                photo = wd.read_photo(pic.name, npx=pic.npx, nln=pic.nln).data
        except (SpcError, OSError) as exc:
            ctx.note_once(f"{summary.picture}: no plots ({exc})")
            continue
        data = photo if photo is not None else np.zeros((pic.nln, pic.npx))
        if paths["register"].exists():
            t = read_table(paths["register"])
            apri = np.stack([_column(t, "apriori_sample"), _column(t, "apriori_line")], axis=-1)
            status = [str(s) for s in t["status"]]
            ok = np.array([s == "ok" for s in status])
            meas = np.where(
                ok[:, None], np.stack([_column(t, "sample"), _column(t, "line")], axis=-1), math.nan
            )
            fig = figures.register_overlay(data, pic.thrsh, t.names, apri, meas, status, picture=pic.name)
            fig.save(plots / f"{pic.name}.register.png")
            written += 1
        if paths["pose"].exists():
            t = read_table(paths["pose"])
            meas = np.stack([_column(t, "sample"), _column(t, "line")], axis=-1)
            rb = np.stack([_column(t, "residual_sample_before"), _column(t, "residual_line_before")], axis=-1)
            ra = np.stack([_column(t, "residual_sample_after"), _column(t, "residual_line_after")], axis=-1)
            status = [str(s) for s in t["status"]]
            fig = figures.pose_plot(
                photo,
                pic.thrsh,
                t.names,
                meas,
                rb,
                ra,
                status,
                picture=pic.name,
                rms_before=summary.rms_before_px,
                rms_after=summary.rms_after_px,
                shape=(pic.nln, pic.npx),
            )
            fig.save(plots / f"{pic.name}.pose.png")
            written += 1
    return written
