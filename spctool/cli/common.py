"""Shared pieces of the command line: context, output, progress, messages, and reading a command's inputs.

The readers here are the one place where a command turns its input options into objects: the
picture (SUM, INIT_LITHOS, camera: :func:`load_picture`), its photo (:func:`load_photo`), the shape
(:func:`load_shape`) and the landmarks (:func:`resolve_landmarks`, :func:`picture_landmarks`).
The options themselves are declared in :mod:`spctool.cli.options`.
"""

from __future__ import annotations

import math
import sys
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import click

from spctool.cli.options import picture_thresholds
from spctool.errors import SpcFormatError, SpcUsageError
from spctool.formats import atomic, guard
from spctool.formats.workdir import WorkDir


@dataclass
class Context:
    workdir: str = "."
    settings_path: str | None = None
    verbosity: int = 0
    debug: bool = False
    explicit_workdir: bool = False  # -C DIR given (the process runs in DIR, like git -C)
    _said: set = field(default_factory=set)
    _later: list = field(default_factory=list)

    @property
    def wd(self) -> WorkDir:
        return WorkDir(Path(self.workdir))

    def settings(self):
        return self.wd.read_settings(self.settings_path)

    def info(self, message: str, level: int = 1) -> None:
        """A message on stderr when ``-v`` was given ``level`` times (never on stdout)."""
        if self.verbosity >= level:
            click.echo(f"spctool: {message}", err=True)

    def warn(self, message: str) -> None:
        """A warning on stderr (``spctool: warning: …``): a result that must not pass unnoticed."""
        if self.verbosity >= 0:
            click.echo(f"spctool: warning: {message}", err=True)

    def warn_later(self, message: str) -> None:
        """A warning about how an input was read, said once when the command has succeeded (a command
        that fails says only its one error line)."""
        if message not in self._later:
            self._later.append(message)

    def flush_later(self) -> None:
        for message in self._later:
            self.warn(message)
        self._later.clear()

    def note_once(self, message: str) -> None:
        """A one-time note on stderr (e.g. 'no shape: occlusion skipped'), silenced by -q."""
        if self.verbosity >= 0 and message not in self._said:
            self._said.add(message)
            click.echo(f"spctool: note: {message}", err=True)


pass_context = click.make_pass_decorator(Context, ensure=True)


def emit(text: str, output: str | None = None, *, overwrite: bool = True) -> None:
    """Write ``text`` to ``output`` atomically (an existing file is kept as ``.bak``), or to stdout when
    ``output`` is None or '-'.  An ``output`` that is a file this command read (by device and inode:
    a link or a second path to it too) is refused naming both (:func:`guard.refuse_read_input`)."""
    if output is None or output == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
    else:
        check_output(output)
        atomic.write_bytes(output, text.encode("utf-8"), overwrite=overwrite, backup=True)


def check_output(output: str | None) -> None:
    """Refuse an ``-o`` path that cannot take the output before a command writes any other file (a
    command that rewrites working-directory files and then prints its table must not fail at the
    table): a directory, a path under a file, or a file this command read (:func:`emit`'s checks)."""
    if output is None or output == "-":
        return
    path = Path(output)
    if path.is_dir():
        raise SpcUsageError(f"{path}: is a directory, cannot write a file there")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise SpcUsageError(f"{path}: {parent} is not a directory, cannot write a file there")
            break
    guard.refuse_read_input(output)


def emit_table(table, *, as_json: bool, output: str | None = None) -> None:
    emit(table.to_json() if as_json else table.to_text(), output)


#: the ``status(text)`` functions of the progress bars on screen, innermost last (what the first-use
#: kernel compilation writes into: :mod:`spctool.cli.jit`)
ACTIVE_BARS: list = []


@contextmanager
def progress(ctx: Context, description: str, total: int | None, *, threaded: bool = True):
    """A rich progress bar on a TTY; silent otherwise (and with -q).  Yields
    ``advance(n=1, description=None)`` (a new ``description`` replaces the bar's text).

    ``threaded=False``: no refresh thread (the bar is redrawn at each ``advance``), for commands that
    fork worker processes, which is safe only while this process runs a single thread.
    """
    if ctx.verbosity < 0 or not sys.stderr.isatty():
        yield lambda n=1, description=None: None
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        transient=True,
        auto_refresh=threaded,
        console=Console(stderr=True),  # stdout may be a pipe or file carrying the table
    ) as bar:
        task = bar.add_task(description, total=total)
        shown = {"description": description}

        def advance(n=1, description=None):
            if description is not None:
                shown["description"] = description
                bar.update(task, description=description)
            bar.advance(task, n)
            if not threaded:
                bar.refresh()

        def status(text: str | None) -> None:
            """A second part of the bar's text (None: none), e.g. the kernels being compiled."""
            bar.update(task, description=shown["description"] + (f" [dim]· {text}" if text else ""))
            bar.refresh()

        ACTIVE_BARS.append(status)
        try:
            yield advance
        finally:
            ACTIVE_BARS.remove(status)


def resolve_landmarks(ctx: Context, specs=(), table: str | None = None) -> list:
    """Landmarks (``Landmark`` from LMK files) named on the command line.

    ``specs`` may mix landmark names (resolved to ``LMKFILES/<NAME>.LMK``), LMK file paths and
    landmark-table files; ``table`` is a landmark table (``-`` = stdin) whose ``name`` column is used.
    With neither, every landmark of LMRKLIST.TXT (else LMKFILES/*.LMK) is taken.
    """
    from spctool.formats.table import read_table

    names: list[str] = []
    direct = []
    if table:
        names += read_table(table).names
    for spec in specs:
        p = Path(spec)
        if p.is_file() and p.suffix.upper() == ".LMK":
            direct.append(ctx.wd.read_landmark(str(p)))
        elif p.is_file():
            names += read_table(p).names
        else:
            names.append(spec)
    if not specs and not table:
        names = ctx.wd.landmark_names()
    return direct + [ctx.wd.read_landmark(n) for n in names]


# ------------------------------------------------------------------------------------------------
# inputs: picture, photo, shape, landmarks


class LoadedPicture(NamedTuple):
    """A picture ready for a stage: its SUM file, the SUM, the INIT_LITHOS settings, its camera."""

    path: Path
    pic: Any  # formats.sumfile.SumFile
    settings: Any  # formats.lithos settings, or None without INIT_LITHOS.TXT
    camera: Any  # geometry.camera.Camera


def sum_path_of(ctx: Context, picture: str, sum_path=None) -> Path:
    """The SUM file of PICTURE: ``--sum FILE``, else PICTURE itself when it is a .SUM file, else
    DIR/SUMFILES/PICTURE.SUM."""
    if sum_path:
        return Path(sum_path)
    p = Path(picture)
    if p.suffix.upper() == ".SUM" and p.exists():
        return p
    return ctx.wd.sum_path(picture)


def adopt_sum_workdir(ctx: Context, sum_path: Path) -> None:
    """The one rule for a picture named by its SUM path: without -C, a SUM in a folder named SUMFILES
    makes that folder's parent the working directory (INIT_LITHOS.TXT, SHAPEFILES/, IMAGEFILES/,
    LMKFILES/, MAPFILES/ are found there, as with ``-C``)."""
    if ctx.explicit_workdir:
        return
    parent = Path(sum_path).parent
    if parent.name.upper() == "SUMFILES":
        root = parent.parent
        if root.resolve() != Path(ctx.workdir).resolve():
            ctx.workdir = str(root) if str(root) else "."
            ctx.info(f"working directory {ctx.workdir} (the SUM file's SUMFILES/ parent)")


def load_picture(ctx: Context, picture: str, sum_path=None, *, allow_linescan: bool = False) -> LoadedPicture:
    """Read PICTURE's SUM (:func:`sum_path_of`, :func:`adopt_sum_workdir`) and the settings, and build
    its camera (SUM pose and K-matrix with the INIT_LITHOS DISTORT= model; a note on stderr when the
    picture has no distortion model).  A line-scan (pushbroom) picture has no frame camera: with
    ``allow_linescan`` its camera is ``None`` (the caller projects with
    :func:`spctool.geometry.linescan.project_linescan`), else it is refused with one line."""
    from spctool.formats.sumfile import read_sum
    from spctool.geometry.camera import Camera

    path = sum_path_of(ctx, picture, sum_path)
    if not path.exists():
        raise SpcFormatError(path, None, f"expected the SUM file of picture {picture} (file not found)")
    adopt_sum_workdir(ctx, path)
    pic = read_sum(path)
    guard.check_sum_header(pic, path)  # SPC reads NaN or a skewed CX/CY/CZ; no stage can use them
    settings = ctx.settings()
    if allow_linescan and getattr(pic, "is_linescan", False):
        return LoadedPicture(path, pic, settings, None)
    # SPC chooses the DISTORT= model by the picture it was asked for (getmm(PICNM)), the SUM file
    # being SUMFILES/<PICNM>.SUM -- not by SUM line 1, which a renamed or copied picture leaves behind.
    # The picture asked for: PICTURE given as a name; a SUM file given as SUMFILES/<name>.SUM; else
    # (a SUM file elsewhere, named as its user likes) the name on its line 1.
    if picture and Path(picture).suffix.upper() != ".SUM":
        asked = picture
    elif Path(path).parent.name.upper() == "SUMFILES":
        asked = Path(path).stem
    else:
        asked = pic.name
    if asked.strip() != pic.name.strip() and ("line1", str(path)) not in ctx._said:
        ctx._said.add(("line1", str(path)))
        ctx.warn_later(
            f"{path}:1: line 1 names picture {pic.name.strip()!r} but it is the SUM of {asked.strip()!r}: "
            f"the DISTORT= model is chosen for {asked.strip()!r}, as SPC's getmm does"
        )
    try:
        camera = Camera.from_picture(pic, settings, picture_name=asked)
    except SpcUsageError as exc:  # a camera the SUM (MMFL, K-MATRIX) or INIT_LITHOS cannot make: name it
        raise SpcUsageError(f"{path}: {exc}") from None
    if camera.model.upper() == "NONE":
        where = (
            f"no INIT_LITHOS.TXT in {ctx.wd.root}"
            if settings is None and not ctx.settings_path
            else "no DISTORT= model for it in the INIT_LITHOS settings"
        )
        ctx.note_once(f"{pic.name}: projected without a distortion model ({where})")
    return LoadedPicture(path, pic, settings, camera)


def warn_row_columns(ctx: Context, path, obj, what: str = "") -> None:
    """One warning per file whose section rows are not in SPC's columns (issue #40), said by the stage that
    uses the rows: the first such row with both readings, and how many more there are (``validate`` lists
    every row); ``what`` keeps the rows of one section (``"landmark sample, line"``)."""
    from spctool.formats.rows import column_notes, spc_columns

    notes = column_notes(getattr(getattr(obj, "_source", None), "warnings", None))
    notes = [(line, text) for line, text in notes if what in text]
    key = ("columns", str(path))
    if not notes or key in ctx._said or spc_columns():
        return
    ctx._said.add(key)
    line, text = notes[0]
    more = f" (and {len(notes) - 1} more rows)" if len(notes) > 1 else ""
    ctx.warn_later(f"{path}:{line}: {text}{more}")


def load_photo(ctx: Context, pic, photo_path=None, *, flip_rows: bool = False, required: bool = True):
    """The photo of picture ``pic``: ``--photo FILE``, else its IMAGEFILES/ photo, checked against the
    SUM's size.  Without one: SpcUsageError when ``required``, else ``None``."""
    from spctool.formats.photo import read_photo

    if photo_path:
        photo = read_photo(photo_path, flip_rows=flip_rows, npx=pic.npx, nln=pic.nln)
    elif ctx.wd.photo_path(pic.name) is not None:
        photo = ctx.wd.read_photo(pic.name, npx=pic.npx, nln=pic.nln, flip_rows=flip_rows)
    elif required:
        raise SpcUsageError(
            f"no photo for picture {pic.name} (IMAGEFILES/{pic.name}.DAT not found; give --photo)"
        )
    else:
        return None
    if photo.data.shape != (pic.nln, pic.npx):
        where = photo_path or ctx.wd.photo_path(pic.name)
        raise SpcUsageError(
            f"{where}: the photo is {photo.npx} x {photo.nln} px but the SUM says {pic.npx} x {pic.nln}"
        )
    return photo


def load_shape(ctx: Context, shape_path=None):
    """The geometry shape (``geometry.shape.as_shape``) of ``--shape FILE``, else of
    DIR/SHAPEFILES/SHAPE.TXT; ``None`` when there is none."""
    model = ctx.wd.read_shape(shape_path)
    if model is None:
        return None
    from spctool.geometry.shape import as_shape

    try:
        return as_shape(model)
    except TypeError as exc:
        raise SpcUsageError(str(exc)) from None


def _shown(path) -> str:
    return "<stdin>" if str(path) == "-" else str(path)


def refuse_other_picture(what: str, path, found: str | None, picture: str, any_picture: bool) -> None:
    """SpcUsageError (exit 2) when a file made for picture ``found`` is given for ``picture`` — a
    landmark table's ``# picture:`` header or a ``--sum`` file's picture name — unless ``any_picture``
    (``--any-picture``).  Nothing is checked when the file names no picture."""
    if any_picture or not found or not picture or found.strip() == picture.strip():
        return
    raise SpcUsageError(
        f"{_shown(path)}: the {what} is for picture {found.strip()}, not {picture.strip()} "
        "(--any-picture uses it anyway)"
    )


def picture_name_of(picture: str) -> str:
    """The picture name PICTURE stands for: the stem of a .SUM path, else PICTURE itself."""
    p = Path(picture)
    return p.stem if p.suffix.upper() == ".SUM" else str(picture)


def check_sum_picture(picture_arg: str, sum_path, loaded: LoadedPicture, any_picture: bool) -> None:
    """Refuse a ``--sum FILE`` whose picture name is not PICTURE's (:func:`refuse_other_picture`)."""
    if sum_path:
        refuse_other_picture("SUM file", sum_path, loaded.pic.name, picture_name_of(picture_arg), any_picture)


def table_pixels(
    path, picture: str | None = None, any_picture: bool = True
) -> list[tuple[str, tuple[float, float] | None]]:
    """(name, (sample, line)) of every row of a landmark table ('-' = stdin); the pixel is None when
    the table has no sample/line columns or the row holds no numbers there (NaN is kept).  With
    ``picture`` and not ``any_picture``, a table whose ``# picture:`` header names another picture is
    refused (:func:`refuse_other_picture`)."""
    from spctool.formats.table import read_table

    table = read_table(path)
    if picture:
        refuse_other_picture("table", path, table.picture, picture, any_picture)
    cols = table.pixel_columns("<stdin>" if str(path) == "-" else path)
    smp, lin = cols if cols is not None else (None, None)
    rows = []
    for i, name in enumerate(table.names):
        pix = None
        if cols is not None:
            try:
                pix = (float(smp[i]), float(lin[i]))
            except (TypeError, ValueError):
                pix = None
        rows.append((name, pix))
    return rows


def picture_landmarks(ctx: Context, names, table_path, picture: LoadedPicture, any_picture: bool = True):
    """The landmarks a per-picture stage works on, as ([(name, pixel or None)], source, centres).

    Given landmarks (source ``"given"``): the rows of ``--landmarks TABLE`` with their table pixels
    (:func:`table_pixels`), then the named ``names`` (no pixel; a name with neither MAP nor LMK file
    is an error, exit 2, as in every command — table rows without a maplet become no-maplet rows).
    With neither, lithos-select (:func:`spctool.stages.select.select_maplets`, INIT_LITHOS options,
    occlusion by the shape as ``lithos-select`` checks it) on the
    LMRKLIST.TXT / LMKFILES/ candidates gives the selected maplets with their predicted pixels
    (source ``"selection"``) and each selected one's centre as the selection read it (``centres``,
    name → V: the LMK's VLM, else the MAP's V; empty for given landmarks), so that a command need not
    read those files again.  A table made for another picture is refused unless ``any_picture``.
    """
    rows = table_pixels(table_path, picture.pic.name, any_picture) if table_path else []
    unplaced = [n for n, pix in rows if pix is not None and not all(math.isfinite(x) for x in pix)]
    if unplaced:
        shown = ", ".join(unplaced[:8]) + (f", ... ({len(unplaced)})" if len(unplaced) > 8 else "")
        ctx.note_once(f"{table_path}: no pixel (nan) for {shown}: a-priori pixel from the SUM camera")
    for n in names:  # a landmark named on the command line must exist (exit 2, as in every command)
        if not (Path(n).is_file() or ctx.wd.map_path(n).exists() or ctx.wd.lmk_path(n).exists()):
            raise SpcFormatError(
                ctx.wd.map_path(n), None, f"expected the MAP (or LMK) file of landmark {n} (file not found)"
            )
    rows += [(n, None) for n in names]
    if rows or table_path:  # a table given is the landmarks, even with no row (never a selection)
        return rows, "given", {}
    from spctool.cli.candidates import load_candidates
    from spctool.stages.select import SelectOptions

    cand = load_candidates(ctx, (), None)
    if not len(cand):
        return [], "selection", {}
    shape = load_shape(ctx)  # occlusion checked as lithos-select checks it (when there is a shape)
    if shape is None:
        ctx.note_once("no shape model (SHAPEFILES/SHAPE.TXT): occlusion check skipped")
    sel_opts = SelectOptions.from_settings(picture.settings)
    res = cand.select(picture.camera, picture.pic.sz, sel_opts, shape=shape)
    ctx.info(
        f"lithos-select: {res.n_selected} of {len(res)} candidate maplets "
        f"(occlusion {'checked' if res.occlusion_checked else 'skipped'})"
    )
    chosen = [k for k, sel in enumerate(res.selected) if sel]
    rows = [(res.names[k], (float(res.sample[k]), float(res.line[k]))) for k in chosen]
    centre_of = dict(zip(cand.names, cand.centres))
    return rows, "selection", {res.names[k]: centre_of[res.names[k]] for k in chosen}


class StageInputs(NamedTuple):
    """What a per-landmark stage command reads before its loop (see :func:`load_stage_inputs`)."""

    picture: LoadedPicture
    thresholds: tuple[float, float]
    photo: Any  # formats.photo.Photo, or None when not required and there is none
    landmarks: list  # [(name, pixel or None)] of picture_landmarks
    source: str  # "given" or "selection"
    centres: dict  # name → V of the selected landmarks as the selection read them (picture_landmarks)


def load_stage_inputs(ctx: Context, kw: dict, *, photo_required: bool = True) -> StageInputs:
    """The inputs of predict, extract, correlate and register, from their parsed options (``kw``:
    PICTURE, [LANDMARK]..., --landmarks, --sum, --photo, --flip-rows, --thresholds of
    :mod:`spctool.cli.options`): the picture and camera, the DN range, the photo and the landmarks.
    Commands with ``--any-picture`` (``kw["any_picture"]``) refuse a ``--landmarks`` table or a
    ``--sum`` made for another picture unless it is given."""
    picture = load_picture(ctx, kw["picture"], kw["sum_path"])
    checked = "any_picture" in kw
    any_picture = bool(kw.get("any_picture")) or not checked
    check_sum_picture(kw["picture"], kw["sum_path"], picture, any_picture)
    thresholds = picture_thresholds(kw["thresholds"], picture.pic)
    photo = load_photo(ctx, picture.pic, kw["photo_path"], flip_rows=kw["flip_rows"], required=photo_required)
    landmarks, source, centres = picture_landmarks(
        ctx, kw["names"], kw["landmarks_table"], picture, any_picture
    )
    return StageInputs(picture, thresholds, photo, landmarks, source, centres)
