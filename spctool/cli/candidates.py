"""The candidate landmarks of a picture: the inputs of Stage A (lithos-select, L15 §2.2).

Their geometry (centre V, axes UX/UY/UZ, SCALE, QSZ) as arrays, read from LMK or MAP files, list
files, a landmark table or the working directory's LMRKLIST.TXT / LMKFILES/.  Used by
``lithos-select`` (:mod:`spctool.cli.select`) and by the per-picture stage commands when no
landmarks are given (:func:`spctool.cli.common.picture_landmarks`); kept apart from both so that
neither imports the other.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from spctool.errors import SpcFormatError, SpcUsageError
from spctool.formats import atomic


class Candidates:
    """Candidate maplet geometry as arrays (the stage's inputs)."""

    def __init__(self, names, centres, ux, uy, uz, scale, qsz):
        self.names = list(names)
        self.centres = np.asarray(centres, float).reshape(-1, 3)
        self.ux = np.asarray(ux, float).reshape(-1, 3)
        self.uy = np.asarray(uy, float).reshape(-1, 3)
        self.uz = np.asarray(uz, float).reshape(-1, 3)
        self.scale = np.asarray(scale, float).reshape(-1)
        self.qsz = np.asarray(qsz, np.int64).reshape(-1)

    def __len__(self):
        return len(self.names)

    def select(self, camera, sun, options, shape=None):
        """Stage A on these candidates (:func:`spctool.stages.select.select_maplets`)."""
        from spctool.stages.select import select_maplets

        return select_maplets(
            camera,
            sun,
            self.centres,
            self.ux,
            self.uy,
            self.uz,
            self.scale,
            self.qsz,
            self.names,
            options,
            shape=shape,
        )


def _geometry_of(obj, name=None):
    """(name, V, UX, UY, UZ, SCALE, QSZ) of a Landmark (LMK) or a Maplet (MAP)."""
    centre = getattr(obj, "vlm", None)
    if centre is None:
        centre = obj.v
    return (name or getattr(obj, "name", "") or "", centre, obj.ux, obj.uy, obj.uz, obj.scale, obj.qsz)


def _load_named(wd, name: str):
    """LMKFILES/<name>.LMK, else MAPFILES/<name>.MAP (EXTFILES/ too)."""
    if wd.lmk_path(name).exists():
        return _geometry_of(wd.read_landmark(name), name)
    if wd.map_path(name).exists():
        return _geometry_of(wd.read_maplet(name), name)
    raise SpcFormatError(
        wd.lmk_path(name), None, f"the LMK (or MAP) file of landmark {name} (file not found)"
    )


def _names_from_list_file(path: Path) -> list[str]:
    """Names from an LMRKLIST-style file (one name a line, ``END`` optional, ``#`` comments)."""
    names = []
    for raw in atomic.read_text(path).splitlines():
        token = raw[:6].strip() if raw.strip() else ""
        if not token or raw.startswith("#"):
            continue
        if token == "END":
            break
        names.append(token)
    return names


def load_candidates(ctx, maplets, landmarks_table) -> Candidates:
    """The candidate maplets of ``ctx``'s working directory (a :class:`spctool.cli.common.Context`):
    ``--maplets`` items (LMK or MAP files, list files, names), else the rows of ``--landmarks TABLE``,
    else LMRKLIST.TXT / LMKFILES/ (SpcUsageError when there are none)."""
    wd = ctx.wd
    rows = []
    if maplets:
        for item in maplets:
            p = Path(item)
            suffix = p.suffix.upper()
            if suffix == ".LMK" and p.exists():
                from spctool.formats.landmark import read_lmk

                rows.append(_geometry_of(read_lmk(p), None))
                if not rows[-1][0]:
                    rows[-1] = (p.stem,) + rows[-1][1:]
            elif suffix == ".MAP" and p.exists():
                from spctool.formats.maplet import read_map

                m = read_map(p)
                rows.append(_geometry_of(m, m.name or p.stem))
            elif p.is_file():
                rows.extend(_load_named(wd, n) for n in _names_from_list_file(p))
            else:
                rows.extend(_load_named(wd, n) for n in item.replace(",", " ").split())
    elif landmarks_table:
        from spctool.formats.table import read_table

        table = read_table(landmarks_table)
        rows = [_load_named(wd, n) for n in table.names]
    else:
        names = wd.landmark_names()
        if not names:
            raise SpcUsageError(
                f"{wd.root}: no candidate landmarks (no LMRKLIST.TXT, no LMKFILES/*.LMK); "
                "give --maplets or --landmarks"
            )
        rows = [_load_named(wd, n) for n in names]
    if not rows:
        return Candidates([], np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), [], [])
    cols = list(zip(*rows))
    return Candidates(
        cols[0],
        np.vstack(cols[1]),
        np.vstack(cols[2]),
        np.vstack(cols[3]),
        np.vstack(cols[4]),
        np.asarray(cols[5], float),
        np.asarray(cols[6], np.int64),
    )
