"""Shared pieces of the command line: context, output, progress, messages, and reading a command's inputs.

The readers here are the one place where a command turns its input options into objects: the
picture (SUM, INIT_LITHOS, camera: :func:`load_picture`), its photo (:func:`load_photo`), the shape
(:func:`load_shape`) and the landmarks (:func:`resolve_landmarks`, :func:`picture_landmarks`).
The options themselves are declared in :mod:`spctool.cli.options`.
"""

from __future__ import annotations

import sys
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import click

from spctool.cli.options import picture_thresholds
from spctool.errors import SpcFormatError, SpcUsageError
from spctool.formats import atomic
from spctool.formats.workdir import WorkDir


@dataclass
class Context:
    workdir: str = "."
    settings_path: str | None = None
    verbosity: int = 0
    debug: bool = False
    explicit_workdir: bool = False  # -C DIR given (the process runs in DIR, like git -C)
    _said: set = field(default_factory=set)

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

    def note_once(self, message: str) -> None:
        """A one-time note on stderr (e.g. 'no shape: occlusion skipped'), silenced by -q."""
        if self.verbosity >= 0 and message not in self._said:
            self._said.add(message)
            click.echo(f"spctool: note: {message}", err=True)


pass_context = click.make_pass_decorator(Context, ensure=True)


def emit(text: str, output: str | None = None, *, overwrite: bool = True) -> None:
    """Write ``text`` to ``output`` atomically (an existing file is kept as ``.bak``), or to stdout when
    ``output`` is None or '-'."""
    if output is None or output == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
    else:
        atomic.write_bytes(output, text.encode("utf-8"), overwrite=overwrite, backup=True)


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
    settings = ctx.settings()
    if allow_linescan and getattr(pic, "is_linescan", False):
        return LoadedPicture(path, pic, settings, None)
    camera = Camera.from_picture(pic, settings)
    if camera.model.upper() == "NONE":
        where = (
            f"no INIT_LITHOS.TXT in {ctx.wd.root}"
            if settings is None and not ctx.settings_path
            else "no DISTORT= model for it in the INIT_LITHOS settings"
        )
        ctx.note_once(f"{pic.name}: projected without a distortion model ({where})")
    return LoadedPicture(path, pic, settings, camera)


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
        raise SpcUsageError(
            f"the photo is {photo.npx} x {photo.nln} px but the SUM says {pic.npx} x {pic.nln}"
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


def table_pixels(path) -> list[tuple[str, tuple[float, float] | None]]:
    """(name, (sample, line)) of every row of a landmark table ('-' = stdin); the pixel is None when
    the table has no sample/line columns or the row holds no numbers there (NaN is kept)."""
    from spctool.formats.table import read_table

    table = read_table(path)
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


def picture_landmarks(ctx: Context, names, table_path, picture: LoadedPicture):
    """The landmarks a per-picture stage works on, as ([(name, pixel or None)], source).

    Given landmarks (source ``"given"``): the rows of ``--landmarks TABLE`` with their table pixels
    (:func:`table_pixels`), then the named ``names`` (no pixel; a name with neither MAP nor LMK file
    is an error, exit 2, as in every command — table rows without a maplet become no-maplet rows).
    With neither, lithos-select (:func:`spctool.stages.select.select_maplets`, INIT_LITHOS options,
    occlusion by the shape as ``lithos-select`` checks it) on the
    LMRKLIST.TXT / LMKFILES/ candidates gives the selected maplets with their predicted pixels
    (source ``"selection"``).
    """
    rows = table_pixels(table_path) if table_path else []
    for n in names:  # a landmark named on the command line must exist (exit 2, as in every command)
        if not (Path(n).is_file() or ctx.wd.map_path(n).exists() or ctx.wd.lmk_path(n).exists()):
            raise SpcFormatError(
                ctx.wd.map_path(n), None, f"expected the MAP (or LMK) file of landmark {n} (file not found)"
            )
    rows += [(n, None) for n in names]
    if rows:
        return rows, "given"
    from spctool.cli.candidates import load_candidates
    from spctool.stages.select import SelectOptions

    cand = load_candidates(ctx, (), None)
    if not len(cand):
        return [], "selection"
    shape = load_shape(ctx)  # occlusion checked as lithos-select checks it (when there is a shape)
    if shape is None:
        ctx.note_once("no shape model (SHAPEFILES/SHAPE.TXT): occlusion check skipped")
    sel_opts = SelectOptions.from_settings(picture.settings)
    res = cand.select(picture.camera, picture.pic.sz, sel_opts, shape=shape)
    ctx.info(
        f"lithos-select: {res.n_selected} of {len(res)} candidate maplets "
        f"(occlusion {'checked' if res.occlusion_checked else 'skipped'})"
    )
    selected = zip(res.names, res.sample, res.line, res.selected)
    return [(n, (float(s), float(ln))) for n, s, ln, sel in selected if sel], "selection"


class StageInputs(NamedTuple):
    """What a per-landmark stage command reads before its loop (see :func:`load_stage_inputs`)."""

    picture: LoadedPicture
    thresholds: tuple[float, float]
    photo: Any  # formats.photo.Photo, or None when not required and there is none
    landmarks: list  # [(name, pixel or None)] of picture_landmarks
    source: str  # "given" or "selection"


def load_stage_inputs(ctx: Context, kw: dict, *, photo_required: bool = True) -> StageInputs:
    """The inputs of predict, extract, correlate and register, from their parsed options (``kw``:
    PICTURE, [LANDMARK]..., --landmarks, --sum, --photo, --flip-rows, --thresholds of
    :mod:`spctool.cli.options`): the picture and camera, the DN range, the photo and the landmarks."""
    picture = load_picture(ctx, kw["picture"], kw["sum_path"])
    thresholds = picture_thresholds(kw["thresholds"], picture.pic)
    photo = load_photo(ctx, picture.pic, kw["photo_path"], flip_rows=kw["flip_rows"], required=photo_required)
    landmarks, source = picture_landmarks(ctx, kw["names"], kw["landmarks_table"], picture)
    return StageInputs(picture, thresholds, photo, landmarks, source)
