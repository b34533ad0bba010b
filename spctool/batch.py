"""Batch runs: many pictures × the navigation stages, in local processes or on a Dask cluster.

A mission measures thousands of pictures against thousands of landmarks.  For each picture of a
PICTLIST (spc-formats.md §7.1) :func:`navigate_picture` runs the stages the way the command chain of
cli-contract.md does::

    lithos-select PIC  →  register PIC --landmarks sel  →  solve-pose PIC --measurements reg

* **select** (Stage A, :func:`spctool.stages.select.select_maplets`): the candidates of LMRKLIST.TXT
  (else LMKFILES/*.LMK) at their LMK VLM (else the MAP's V), options from INIT_LITHOS
  (:meth:`SelectOptions.from_settings`), the occlusion test when the working directory has a shape;
* **register** (Stage H): the selected landmarks, starting at their selected pixels, with the MAPFILES/
  maplets.  By default **two-pass navigation** (:func:`spctool.stages.navigate.navigate`, issue #15:
  a coarse-to-fine acquisition reaching ±25 px, a pose solve, every landmark registered again from the
  solved pose, a second pose solve), because a single pass from the a-priori pose loses pictures whose
  a-priori error exceeds its first search (SPC's AUTOREGISTER seed searches ±10 cells at spacing 2 and
  lost a whole picture with a 14 px error on the independent world, :mod:`spctool.sim.independent`).
  ``BatchOptions(two_pass=None)`` runs the single pass of :func:`spctool.stages.register.register`
  with ``register.schedule`` (default SPC's AUTOREGISTER, spc-algorithms.md §9.2–9.3, what SPC's own
  batch seeds ``make_scriptA.seed`` run);
* **solve-pose** (Stage I, :func:`spctool.stages.pose.solve_pose`): the landmarks registered ``ok`` at
  their LMK VLM, from the SUM's a-priori pose with SIGMA_VSO / SIGMA_PTG as prior (spc-algorithms.md
  §10.3).

Outputs (under ``out_dir``, SPC layout; every file written atomically, see :mod:`spctool.formats.atomic`):

* ``SUMFILES/<PIC>.SUM`` — a copy of the input SUM with the registered landmarks in its LANDMARKS section
  (new pixels for ``ok`` landmarks, added when absent, other rows kept) and, when the pose solve
  converged, the solved SCOBJ, CX, CY, CZ, SIGMA_VSO and SIGMA_PTG; every other line is byte-identical
  (``formats.sumfile`` rewrites changed lines only);
* ``TABLES/<PIC>.select.txt``, ``TABLES/<PIC>.register.txt``, ``TABLES/<PIC>.pose.txt`` — the landmark
  tables of the three stages (cli-contract.md "Landmark tables");
* ``TABLES/<PIC>.done.json`` — the done-marker, written **last**: the picture's summary row, its timings,
  the options fingerprint, the spctool version and the SHA-256 of every input the result depends on
  (:func:`picture_inputs`): its SUM, its photo, the MAP of each maplet it selected (a missing one
  too), and the shared inputs — INIT_LITHOS, LMRKLIST.TXT, every candidate's LMK (or MAP), the shape
  model.  A picture counts as done only when its marker exists and every fingerprint matches, so a
  batch interrupted at any instant resumes safely and a new photo, a changed INIT_LITHOS, LMRKLIST or
  maplet redoes the pictures it affects: a picture is redone (its old outputs, its marker and any
  temporary file a killed rename left removed first) unless ``force`` is False and it is done with
  the same options and the same inputs.  Failed pictures get no marker (they are retried);
* ``BATCH_SUMMARY.txt`` / ``BATCH_SUMMARY.json`` — the summary of the last run, written by the driver.

Status of a picture (the summary's ``status`` column): ``ok`` (pose solved and converged, SUM updated);
``no-pose: <reason>`` (the stages ran but the pose could not be solved — too few landmarks registered,
degenerate geometry or no convergence; the SUM copy holds the registered landmarks, pose unchanged;
this is a result, not a failure); ``failed: <one line>`` (the picture could not be processed — a
missing or malformed file, an internal error; nothing is marked done).  A failure never stops the
batch.

Parallelism (:func:`run_batch`) never changes a result: each picture is computed from its own input
files by the same function with fixed options (no random draws), results are collected by picture
index and the summary is in picture order, and every picture runs its numba kernels on one thread
whatever the back end (one worker = one core: more cores are used by more workers), so ``jobs=1``,
``jobs=N`` (a :class:`~concurrent.futures.ProcessPoolExecutor` of forked or spawned workers,
:func:`start_method`), a :class:`WorkerPool` kept alive across batches and a Dask cluster
(``scheduler``; ``pip install 'spctool[dask]'``; the workers must see the working and output
directories at the same paths) write byte-identical files.

Data shared by every picture — the settings, the candidate landmark geometry, the shape model and a
bounded cache of maplets — is loaded once per worker process (:class:`SharedData`), not once per
picture, and a long-lived worker (a Dask worker, a :class:`WorkerPool`) keeps it from one batch to
the next while the files it was read from are unchanged (:func:`inputs_stamp`).  One process computes
one picture at a time (a process-wide lock: several threads of one Dask worker would otherwise launch
numba's parallel kernels concurrently), so give Dask workers one thread each.

Not done here: LMK ``PICTURES`` sections are not updated — several pictures would write the same LMK
file concurrently; SPC's own batch updates them in a separate serial step.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import os
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spctool import __version__
from spctool.errors import SpcError, SpcFormatError, SpcUsageError
from spctool.formats import atomic, guard
from spctool.formats.sumfile import with_measured_landmarks, with_pose
from spctool.formats.workdir import WorkDir
from spctool.geometry.shape import as_shape
from spctool.stages.navigate import NavigateOptions
from spctool.stages.pose import PoseError, PoseOptions
from spctool.stages.register import RegisterOptions

__all__ = [
    "BatchOptions",
    "BatchResult",
    "PictureOutcome",
    "PictureSummary",
    "SharedData",
    "WorkerPool",
    "batch_pictures",
    "inputs_stamp",
    "navigate_picture",
    "output_paths",
    "run_batch",
    "start_method",
]

MARKER_FORMAT = "spctool-batch-done/2"  # /2: input fingerprints cover every input (issue #19)
SUMMARY_FORMAT = "spctool-batch/1"
TABLES_DIR = "TABLES"
SUMMARY_STEM = "BATCH_SUMMARY"
#: status words of a picture; the text after ``": "`` is the one-line reason
STATUSES = ("ok", "no-pose", "failed")
#: how long a WorkerPool waits for its workers to warm up
WARM_TIMEOUT_S = 600.0


# --------------------------------------------------------------------------------------------------
# options


def _default_register() -> RegisterOptions:
    return RegisterOptions(schedule="autoregister")


@dataclass
class BatchOptions:
    """Everything that decides a picture's result (and so its resume fingerprint).

    * ``select`` — overrides of :class:`spctool.stages.select.SelectOptions` applied after INIT_LITHOS
      (``SelectOptions.from_settings(settings, **select)``; None values ignored).
    * ``occlusion`` — None: run the occlusion test when a shape model exists; True: require one;
      False: never.
    * ``register`` — :class:`RegisterOptions` (default: the AUTOREGISTER schedule in maplet space).
    * ``two_pass`` — :class:`NavigateOptions` of two-pass navigation (the default path,
      :func:`spctool.stages.navigate.navigate`: acquisition reaching ±25 px, pose, re-registration from
      the solved pose, pose; its ``register``/``pose`` are replaced by ``register`` (space, thresholds,
      stage options; the schedule is the navigation's) and ``pose``); None = the single pass of
      ``register.schedule``.
    * ``pose`` — :class:`PoseOptions` of the final solve (the AUTOREGISTER passes use ``register.pose``).
    * ``settings_path`` / ``shape_path`` — explicit INIT_LITHOS and shape files (default: the working
      directory's INIT_LITHOS.TXT and SHAPEFILES/SHAPE.TXT when present).
    * ``maplet_cache`` — maplets kept per worker process (least recently used dropped first).
    """

    select: dict = field(default_factory=dict)
    occlusion: bool | None = None
    register: RegisterOptions = field(default_factory=_default_register)
    pose: PoseOptions = field(default_factory=PoseOptions)
    two_pass: NavigateOptions | None = field(default_factory=NavigateOptions)
    settings_path: str | None = None
    shape_path: str | None = None
    maplet_cache: int = 4096

    def __post_init__(self):
        from spctool.stages.select import SelectOptions

        known = {f.name for f in dataclasses.fields(SelectOptions)}
        unknown = sorted(set(self.select) - known)
        if unknown:
            raise SpcUsageError(f"unknown selection option(s): {', '.join(unknown)}")
        if self.occlusion is not None:
            self.occlusion = bool(self.occlusion)
        self.maplet_cache = int(self.maplet_cache)
        if self.maplet_cache < 0:
            raise SpcUsageError(f"maplet_cache must be >= 0, got {self.maplet_cache}")
        for name in ("settings_path", "shape_path"):
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, str(Path(value).resolve()))

    def as_dict(self) -> dict:
        return {
            "select": {k: v for k, v in sorted(self.select.items()) if v is not None},
            "occlusion": self.occlusion,
            "register": self.register.as_dict(),
            "pose": dataclasses.asdict(self.pose),
            "two_pass": None
            if self.two_pass is None
            else {k: v for k, v in self.two_pass.as_dict().items() if k not in ("register", "pose")},
            "settings_path": self.settings_path,
            "shape_path": self.shape_path,
        }

    def fingerprint(self) -> str:
        """SHA-256 of the options that decide a result (``maplet_cache`` does not)."""
        text = json.dumps(_jsonable(self.as_dict()), sort_keys=True, allow_nan=True)
        return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _jsonable(v):
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return repr(v)
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    return repr(v)


# --------------------------------------------------------------------------------------------------
# data shared by the pictures of one worker


class SharedData:
    """Per-process data of a batch: settings, select options, candidate geometry, shape, maplets.

    Built once per (working directory, options, :func:`inputs_stamp`) in each worker process
    (:meth:`get`), so a long-lived process (a Dask worker, a Python session running several batches)
    reuses it for as long as the files it was read from are unchanged.  The maplet cache is bounded
    (``options.maplet_cache``), checks each MAP file's stat before reuse and holds read failures too,
    so a missing MAP is reported for every picture that selects it without being re-read.
    """

    _lock = threading.Lock()
    _instances: OrderedDict = OrderedDict()

    def __init__(self, workdir, options: BatchOptions):
        from spctool.stages.select import SelectOptions

        self.wd = WorkDir(Path(workdir))
        self.options = options
        self.inputs_sha256 = shared_inputs_sha256(workdir, options)  # before reading: never newer
        self.settings = self.wd.read_settings(options.settings_path)
        self.select_options = SelectOptions.from_settings(self.settings, **options.select)
        names = self.wd.landmark_names()
        if not names:
            raise SpcUsageError(
                f"{self.wd.root}: no candidate landmarks (no LMRKLIST.TXT, no LMKFILES/*.LMK)"
            )
        rows = [_candidate_row(self.wd, n) for n in names]
        self.names = [r[0] for r in rows]
        n = len(rows)

        def stack(k, width):
            return np.array([r[k] for r in rows], dtype=np.float64).reshape(n, width)

        self.centres = stack(1, 3)
        self.ux, self.uy, self.uz = stack(2, 3), stack(3, 3), stack(4, 3)
        self.scale = stack(5, 1).reshape(n)
        self.qsz = np.array([r[6] for r in rows], dtype=np.int64).reshape(n)
        self.index = {name: i for i, name in enumerate(self.names)}
        self.shape = None
        if options.occlusion is not False:
            path = options.shape_path
            if path or self.wd.shape_path.exists():
                self.shape = as_shape(self.wd.read_shape(path))
            if self.shape is None and options.occlusion:
                raise SpcUsageError(
                    f"the occlusion test needs a shape model ({self.wd.shape_path} not found)"
                )
            if self.shape is not None:
                self.shape.max_diameter  # noqa: B018  (build the cached hierarchy once, here)
        self._maplets: OrderedDict = OrderedDict()

    @classmethod
    def get(cls, workdir, options: BatchOptions, stamp: str | None = None) -> SharedData:
        """The instance for (``workdir``, ``options``, ``stamp``), built on first use.  ``stamp`` is
        the :func:`inputs_stamp` of the working directory (computed here when None): a batch passes
        the one it computed once, and an instance is reused only while its input files are unchanged.
        The last two instances are kept."""
        if stamp is None:
            stamp = inputs_stamp(workdir, options)
        key = (str(Path(workdir).resolve()), stamp)  # the stamp covers the options' fingerprint too
        with cls._lock:
            data = cls._instances.get(key)
            if data is None:
                data = cls(workdir, options)
                cls._instances[key] = data
                while len(cls._instances) > 2:
                    cls._instances.popitem(last=False)
            cls._instances.move_to_end(key)
            return data

    @classmethod
    def clear(cls) -> None:
        with cls._lock:
            cls._instances.clear()

    def maplet(self, name: str):
        """The maplet of ``name`` (MAPFILES/, then EXTFILES/), or the SpcFormatError reading it.
        A cached maplet is reused only while its file's (path, size, mtime, inode) are unchanged."""
        stat = _file_stat(self.wd.map_path(name))
        item = self._maplets.get(name)
        if item is not None and item[0] == stat:
            self._maplets.move_to_end(name)
            return item[1]
        try:
            value = self.wd.read_maplet(name)
        except SpcFormatError as exc:
            value = exc
        if self.options.maplet_cache:
            self._maplets[name] = (stat, value)
            self._maplets.move_to_end(name)
            while len(self._maplets) > self.options.maplet_cache:
                self._maplets.popitem(last=False)
        return value


def _file_stat(path: Path) -> tuple:
    """(path, size, mtime_ns, inode) of a file, or (path,) when it cannot be stat'ed: what decides
    whether data read from it earlier are still current (an in-place rewrite changes the size or
    mtime, an atomic replace the inode)."""
    try:
        st = os.stat(path)
    except OSError:
        return (str(path),)
    return (str(path), st.st_size, st.st_mtime_ns, st.st_ino)


def inputs_stamp(workdir, options: BatchOptions, fingerprint: str | None = None) -> str:
    """SHA-256 of the stat of every file :class:`SharedData` reads: INIT_LITHOS, LMRKLIST.TXT, each
    candidate's LMK (or MAP) and the shape model (:func:`_file_stat`).  Cheap (one ``stat`` per file,
    no reading), so a batch computes it once and a worker rebuilds its shared data only when it
    changed.  Unreadable lists are left to :class:`SharedData` to report.  ``fingerprint``: the
    options' :meth:`BatchOptions.fingerprint` when the caller has it already."""
    wd = WorkDir(Path(workdir).resolve())
    parts = [str(wd.root), fingerprint or options.fingerprint()]
    parts.append(_file_stat(Path(options.settings_path) if options.settings_path else wd.settings_path))
    parts.append(_file_stat(wd.lmrklist_path))
    try:
        names = wd.landmark_names()
    except SpcError as exc:
        names = []
        parts.append(str(exc))
    for name in names:
        stat = _file_stat(wd.lmk_path(name))
        parts.append(stat if len(stat) > 1 else _file_stat(wd.map_path(name)))
    if options.occlusion is not False:
        parts.append(_file_stat(Path(options.shape_path) if options.shape_path else wd.shape_path))
    return hashlib.sha256(repr(parts).encode("utf-8")).hexdigest()


#: SHA-256 of files by (path, size, mtime_ns, inode) — one hash per file version per process
_HASHES: OrderedDict = OrderedDict()
_HASHES_KEPT = 65536


def _file_sha256(path) -> str | None:
    """SHA-256 of a file's content, None when it does not exist or cannot be read (cached by
    :func:`_file_stat`, so the shared inputs are hashed once per process and batch)."""
    st = _file_stat(Path(path))
    if len(st) == 1:
        return None
    digest = _HASHES.get(st)
    if digest is None:
        try:
            digest = hashlib.sha256(guard.read_bytes(path)).hexdigest()
        except (OSError, SpcError):
            return None
        _HASHES[st] = digest
        while len(_HASHES) > _HASHES_KEPT:
            _HASHES.popitem(last=False)
    return digest


def _rel(wd: WorkDir, path: Path) -> str:
    try:
        return str(Path(path).resolve().relative_to(wd.root.resolve()))
    except ValueError:
        return str(Path(path).resolve())


def shared_inputs_sha256(workdir, options: BatchOptions) -> str:
    """SHA-256 over the content of every input shared by the pictures of a batch: INIT_LITHOS,
    LMRKLIST.TXT, each candidate landmark's LMK (else MAP), the shape model when the occlusion test
    may use it, the candidate names, the options' fingerprint and the spctool version."""
    wd = WorkDir(Path(workdir))
    files = [Path(options.settings_path) if options.settings_path else wd.settings_path, wd.lmrklist_path]
    try:
        names = wd.landmark_names()
    except SpcError as exc:
        names = [f"<unreadable: {exc}>"]
    for name in names:
        if not guard.is_valid_name(name):
            continue
        lmk = wd.lmk_path(name)
        files.append(lmk if lmk.exists() else wd.map_path(name))
    if options.occlusion is not False:
        files.append(Path(options.shape_path) if options.shape_path else wd.shape_path)
    parts = [__version__, options.fingerprint(), names]
    parts += [(_rel(wd, f), _file_sha256(f)) for f in files]
    return hashlib.sha256(repr(parts).encode("utf-8")).hexdigest()


def picture_inputs(wd: WorkDir, picture: str, photo_name: str | None, maplets: Sequence[str]) -> dict:
    """The per-picture inputs of a done-marker: ``{"sum": [path, sha], "photo": [name, path, sha],
    "maplets": {name: [path, sha]}}`` (paths relative to the working directory, sha None when the
    file is missing — a maplet that appears later changes the result too)."""
    sum_path = wd.sum_path(picture)
    doc: dict = {"sum": [_rel(wd, sum_path), _file_sha256(sum_path)]}
    if photo_name is not None:
        photo = wd.photo_path(photo_name)
        if photo is None:
            doc["photo"] = [photo_name, None, None]
        else:
            doc["photo"] = [photo_name, _rel(wd, photo), _file_sha256(photo)]
    doc["maplets"] = {}
    for name in maplets:
        path = wd.map_path(name)
        doc["maplets"][name] = [_rel(wd, path), _file_sha256(path)]
    return doc


def _same_inputs(wd: WorkDir, picture: str, stored) -> bool:
    """True when the per-picture inputs recorded in a marker are unchanged (:func:`picture_inputs`)."""
    if not isinstance(stored, dict) or not isinstance(stored.get("maplets"), dict):
        return False
    try:
        photo = stored.get("photo")
        photo_name = photo[0] if isinstance(photo, list) and photo else None
        now = picture_inputs(wd, picture, photo_name, list(stored["maplets"]))
    except (SpcError, OSError, TypeError):
        return False
    return _json_clean(now) == stored


def _candidate_row(wd: WorkDir, name: str):
    """(name, V, UX, UY, UZ, SCALE, QSZ) from LMKFILES/<name>.LMK (V = VLM), else from the MAP (V),
    as ``lithos-select`` and ``register`` take them."""
    if wd.lmk_path(name).exists():
        obj = wd.read_landmark(name)
        centre = obj.vlm
    elif wd.map_path(name).exists():
        obj = wd.read_maplet(name)
        centre = obj.v
    else:
        raise SpcFormatError(
            wd.lmk_path(name), None, f"the LMK (or MAP) file of landmark {name} (file not found)"
        )
    return (name, centre, obj.ux, obj.uy, obj.uz, float(obj.scale), int(obj.qsz))


# --------------------------------------------------------------------------------------------------
# one picture


@dataclass
class PictureSummary:
    """One row of the batch summary (small and picklable: what a worker sends back)."""

    picture: str
    status: str
    candidates: int = 0
    selected: int = 0
    found: int = 0
    used: int = 0
    rms_before_px: float = math.nan
    rms_after_px: float = math.nan
    dposition_km: float = math.nan
    dattitude_rad: float = math.nan
    converged: bool = False
    delta_position: list = field(default_factory=lambda: [math.nan] * 3)
    delta_attitude: list = field(default_factory=lambda: [math.nan] * 3)
    # fit quality and full covariance of the solved pose (6x6: km then rad; scaled by cost/dof > 1)
    reduced_chi2: float = math.nan
    covariance_scale: float = 1.0
    plausible: bool = True
    covariance: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    resumed: bool = False
    #: one line per problem that cost this picture landmarks without failing it (an unreadable MAP)
    notes: list = field(default_factory=list)

    @property
    def kind(self) -> str:
        """``ok``, ``no-pose`` or ``failed`` (the status without its reason)."""
        return self.status.split(":", 1)[0]

    @property
    def failed(self) -> bool:
        return self.kind == "failed"

    def result_dict(self) -> dict:
        """The deterministic part (no timings, no resume flag): equal whatever the parallelism."""
        d = dataclasses.asdict(self)
        d.pop("timings")
        d.pop("resumed")
        return d

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> PictureSummary:
        known = {f.name for f in dataclasses.fields(cls)}
        values = {k: v for k, v in d.items() if k in known}
        for k in ("rms_before_px", "rms_after_px", "dposition_km", "dattitude_rad", "reduced_chi2"):
            if values.get(k) is None:
                values[k] = math.nan
        for k in ("delta_position", "delta_attitude"):
            if k in values:
                values[k] = [math.nan if x is None else float(x) for x in values[k]]
        return cls(**values)


@dataclass
class PictureOutcome:
    """Everything :func:`navigate_picture` produced for one picture.

    ``select`` (SelectResult), ``register`` (RegisterResult), ``pose`` (PoseResult) are None for the
    stages that did not run; the ``*_table`` attributes are the landmark tables written to
    ``TABLES/``; ``sum_text`` the updated SUM (None when the picture failed before registering).
    """

    summary: PictureSummary
    select: object = None
    register: object = None
    pose: object = None
    select_table: object = None
    register_table: object = None
    pose_table: object = None
    sum_text: str | None = None
    input_sha256: str | None = None
    #: what the done-marker fingerprints (:func:`picture_inputs`): the shared inputs' SHA-256, the
    #: photo's picture name (from the SUM) and the maplets selected
    inputs_sha256: str | None = None
    photo_name: str | None = None
    maplets: list = field(default_factory=list)
    workdir: WorkDir | None = None

    @property
    def status(self) -> str:
        return self.summary.status


def _one_line(text: str, limit: int = 300) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _failure_text(exc: BaseException) -> str:
    if isinstance(exc, SpcError):
        return _one_line(str(exc))
    return _one_line(f"internal error: {type(exc).__name__}: {exc}")


#: one picture at a time per process (numba's default threading layer cannot run parallel kernels
#: from several threads at once; see the module docstring)
_COMPUTE_LOCK = threading.Lock()


def navigate_picture(
    workdir,
    picture: str,
    options: BatchOptions | None = None,
    *,
    shared: SharedData | None = None,
    stamp: str | None = None,
) -> PictureOutcome:
    """Run lithos-select → register → solve-pose for one picture of ``workdir`` (module docstring).

    Pure apart from reading the working directory: nothing is written (see :func:`write_outcome`).
    Never raises (interrupts apart): any problem — with this picture's files or with the shared data
    — is ``summary.status == "failed: <one line>"``.  ``shared``: the worker's :class:`SharedData`
    (default: ``SharedData.get(workdir, options, stamp)``).
    """
    options = options if options is not None else BatchOptions()
    with _COMPUTE_LOCK:
        return _navigate(workdir, picture, options, shared, stamp)


def _navigate(workdir, picture, options, shared, stamp) -> PictureOutcome:
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    summary = PictureSummary(picture=picture, status="failed: not run", timings=timings)
    out = PictureOutcome(summary, workdir=WorkDir(Path(workdir)))
    try:
        if shared is None:
            shared = SharedData.get(workdir, options, stamp)
        _run_stages(shared, picture, options, out, timings)
    except Exception as exc:  # noqa: BLE001 - a picture's failure (MemoryError too) never stops the batch
        summary.status = "failed: " + _failure_text(exc)
    timings["total_s"] = time.perf_counter() - t0
    return out


def _run_stages(shared: SharedData, picture: str, options: BatchOptions, out: PictureOutcome, timings):
    from spctool.formats.sumfile import parse_sum
    from spctool.geometry.camera import Camera
    from spctool.stages.pose import solve_pose
    from spctool.stages.register import register
    from spctool.stages.select import select_maplets

    summary = out.summary
    wd = shared.wd
    clock = time.perf_counter()

    # ---- inputs ----------------------------------------------------------------------------------
    sum_path = wd.sum_path(picture)
    if not sum_path.exists():
        raise SpcFormatError(sum_path, None, f"the SUM file of picture {picture} (file not found)")
    raw = guard.read_bytes(sum_path, f"the SUM file of picture {picture}")  # regular file, size checked
    out.input_sha256 = hashlib.sha256(raw).hexdigest()
    out.inputs_sha256 = shared.inputs_sha256
    pic = parse_sum(raw.decode("latin-1").replace("\r", ""), sum_path)
    out.photo_name = pic.name
    camera = Camera.from_picture(pic, shared.settings)
    photo = wd.read_photo(pic.name, npx=pic.npx, nln=pic.nln)
    if photo.data.shape != (pic.nln, pic.npx):
        raise SpcFormatError(
            wd.photo_path(pic.name),
            None,
            f"a {pic.npx} x {pic.nln} px photo as the SUM says (found {photo.npx} x {photo.nln})",
        )
    timings["read_s"] = time.perf_counter() - clock

    # ---- Stage A: lithos-select ------------------------------------------------------------------
    clock = time.perf_counter()
    sel = select_maplets(
        camera,
        pic.sz,
        shared.centres,
        shared.ux,
        shared.uy,
        shared.uz,
        shared.scale,
        shared.qsz,
        shared.names,
        shared.select_options,
        shape=shared.shape,
    )
    out.select = sel
    summary.candidates = len(sel)
    summary.selected = int(sel.n_selected)
    out.select_table = sel.to_table(
        picture=pic.name,
        command="lithos-select",
        meta={
            "candidates": len(sel),
            "selected": int(sel.n_selected),
            "occlusion": "checked" if sel.occlusion_checked else "skipped",
            "options": shared.select_options.as_dict(),
        },
    )
    out.select_table.comments.append(
        f"selected {sel.n_selected} of {len(sel)} candidate maplets; "
        f"occlusion {'checked' if sel.occlusion_checked else 'skipped'}"
    )
    timings["select_s"] = time.perf_counter() - clock

    # ---- Stage H: register -----------------------------------------------------------------------
    clock = time.perf_counter()
    chosen = np.flatnonzero(sel.selected)
    names, maplets, apriori, missing = [], [], [], []
    for i in chosen:  # file look-ups per selected landmark; the numerics are vectorised in the stages
        name = sel.names[i]
        m = shared.maplet(name)
        if isinstance(m, SpcFormatError):
            missing.append(name)
            summary.notes.append(f"landmark {name} left out (no-maplet): {m}")
            continue
        names.append(name)
        maplets.append(m)
        apriori.append((sel.sample[i], sel.line[i]))
    idx = np.array([shared.index[n] for n in names], dtype=np.int64)
    positions = shared.centres[idx] if len(idx) else np.zeros((0, 3))
    apriori = np.asarray(apriori, dtype=np.float64).reshape(-1, 2)
    ropts = options.register
    stage_kw = dict(
        apriori=apriori,
        names=names,
        positions=positions,
        prior_sigma_position=pic.sigma_vso,
        prior_sigma_attitude=pic.sigma_ptg,
    )
    thrsh = tuple(float(x) for x in pic.thrsh)
    nav = None
    if options.two_pass is not None:  # two-pass navigation (the final solve below repeats pass 2's)
        from spctool.stages.navigate import navigate

        nopts = dataclasses.replace(options.two_pass, register=ropts, pose=options.pose)
        nav = navigate(photo, camera, pic.sz, maplets, thrsh, nopts, **stage_kw)
        reg = nav.final.register
    else:
        reg = register(photo, camera, pic.sz, maplets, thrsh, ropts, **stage_kw)
    out.register = reg
    out.maplets = [sel.names[i] for i in chosen]
    ok = reg.ok
    summary.found = int(ok.sum())
    schedule = ropts.schedule if nav is None else f"two-pass ({len(nav.passes)} run)"
    meta = {
        "landmark_source": "selection",
        "schedule": schedule,
        "space": ropts.space,
        "thresholds": [float(x) for x in pic.thrsh],
        "status_counts": reg.status_counts(),
        "registered": summary.found,
        "passes": reg.passes if nav is None else [p.as_dict() for p in nav.passes],
        "options": ropts.as_dict(),
        "warnings": list(reg.warnings) + ([] if nav is None else list(nav.warnings)),
    }
    table = (
        reg.to_table(picture=pic.name, command="register", meta=meta)
        if nav is None
        else nav.to_table(picture=pic.name, command="register", meta=meta)
    )
    if missing:
        from spctool.formats.table import LandmarkTable

        rows = table.rows()
        for name in missing:
            row = {k: math.nan for k in table.columns}
            row.update(name=name, iterations=0, spacing=0, status="no-maplet")
            for c in ("status_1", "pose_status"):  # the two-pass table's word columns
                if c in row:
                    row[c] = "no-maplet" if c == "status_1" else "-"
            k = shared.index[name]
            row.update(sample=float(sel.sample[k]), line=float(sel.line[k]))
            row.update(apriori_sample=float(sel.sample[k]), apriori_line=float(sel.line[k]))
            rows.append(row)
        table = LandmarkTable.from_rows(rows, picture=pic.name, command="register", meta=meta)
    table.comments.append(
        f"registered {summary.found} of {len(reg) + len(missing)} landmarks "
        f"({schedule}, {ropts.space} space)"
    )
    out.register_table = table
    timings["register_s"] = time.perf_counter() - clock

    # ---- Stage I: solve-pose ---------------------------------------------------------------------
    clock = time.perf_counter()
    new_pic = with_measured_landmarks(pic, reg.names, reg.measured, reg.ok)
    use = np.flatnonzero(ok)
    try:
        pose = solve_pose(
            camera,
            positions[use],
            reg.measured[use],
            options.pose,
            prior_sigma_position=pic.sigma_vso,
            prior_sigma_attitude=pic.sigma_ptg,
            names=[names[i] for i in use],
        )
    except PoseError as exc:
        pose = None
        summary.status = "no-pose: " + _failure_text(exc)
    timings["pose_s"] = time.perf_counter() - clock
    if pose is not None:
        out.pose = pose
        summary.used = pose.n_used
        summary.rms_before_px = float(pose.rms_before)
        summary.rms_after_px = float(pose.rms_after)
        summary.converged = bool(pose.converged)
        summary.delta_position = [float(x) for x in pose.delta_position]
        summary.delta_attitude = [float(x) for x in pose.delta_attitude]
        summary.dposition_km = float(np.linalg.norm(pose.delta_position))
        summary.dattitude_rad = float(np.linalg.norm(pose.delta_attitude))
        summary.reduced_chi2 = float(pose.reduced_chi2)
        summary.covariance_scale = float(pose.covariance_scale)
        summary.plausible = pose.plausible
        summary.covariance = np.asarray(pose.covariance, dtype=float).tolist()
        out.pose_table = _pose_table(pic.name, pose, options.pose)
        if pose.converged and not pose.plausible:
            summary.status = f"no-pose: implausible fit: {pose.implausible}"
        elif pose.converged:
            new_pic = with_pose(new_pic, pose.scobj, pose.rotation, pose.sigma_position, pose.sigma_attitude)
            summary.status = "ok"
        else:
            summary.status = f"no-pose: did not converge in {options.pose.max_iter} iterations"
    from spctool.formats.sumfile import format_sum

    out.sum_text = format_sum(new_pic)


def _pose_table(picture: str, pose, popts: PoseOptions):
    """The solve-pose residual table (cli-contract.md; the columns of ``spctool solve-pose``)."""
    from spctool.formats.table import LandmarkTable

    cols = {
        "name": list(pose.names),
        "sample": pose.measured[:, 0],
        "line": pose.measured[:, 1],
        "apriori_sample": pose.predicted_before[:, 0],
        "apriori_line": pose.predicted_before[:, 1],
        "predicted_sample": pose.predicted_after[:, 0],
        "predicted_line": pose.predicted_after[:, 1],
        "residual_sample_before": pose.residuals_before[:, 0],
        "residual_line_before": pose.residuals_before[:, 1],
        "residual_sample_after": pose.residuals_after[:, 0],
        "residual_line_after": pose.residuals_after[:, 1],
        "status": list(pose.status),
    }
    meta = {"pose": pose.pose_dict(), "options": dataclasses.asdict(popts)}
    table = LandmarkTable(cols, picture=picture, command="solve-pose", meta=meta)
    table.comments.append(
        f"solved with {pose.n_used} landmarks, {pose.iterations} iterations, "
        f"{'converged' if pose.converged else 'NOT converged'}; residuals measured - predicted (px)"
    )
    table.comments.extend(pose.header_lines())
    return table


# --------------------------------------------------------------------------------------------------
# outputs and resume


def output_paths(out_dir, picture: str) -> dict[str, Path]:
    """The files of one picture under ``out_dir`` (``marker`` is written last)."""
    out = Path(out_dir)
    tables = out / TABLES_DIR
    picture = guard.check_name(picture, "picture name")  # never a path out of out_dir
    return {
        "sum": out / "SUMFILES" / f"{picture}.SUM",
        "select": tables / f"{picture}.select.txt",
        "register": tables / f"{picture}.register.txt",
        "pose": tables / f"{picture}.pose.txt",
        "marker": tables / f"{picture}.done.json",
    }


def clear_outputs(out_dir, picture: str) -> None:
    """Remove a picture's outputs, the marker first (so a crash in between leaves it 'not done')."""
    paths = output_paths(out_dir, picture)
    for key in ("marker", "sum", "select", "register", "pose"):
        try:
            paths[key].unlink()
        except FileNotFoundError:
            pass
        atomic.remove_stale_temps(paths[key])  # left by a run killed at the rename step


def write_outcome(out_dir, outcome: PictureOutcome, fingerprint: str) -> None:
    """Write a picture's outputs atomically, the done-marker last (only when it did not fail)."""
    paths = output_paths(out_dir, outcome.summary.picture)
    clear_outputs(out_dir, outcome.summary.picture)
    if outcome.sum_text is not None:
        atomic.write_text(paths["sum"], outcome.sum_text)
    for key, table in (
        ("select", outcome.select_table),
        ("register", outcome.register_table),
        ("pose", outcome.pose_table),
    ):
        if table is not None:
            atomic.write_bytes(paths[key], table.to_text().encode("utf-8"))
    if outcome.summary.failed:
        return
    marker = {
        "format": MARKER_FORMAT,
        "picture": outcome.summary.picture,
        "options_sha256": fingerprint,
        "input_sum_sha256": outcome.input_sha256,
        "spctool_version": __version__,
        "shared_inputs_sha256": outcome.inputs_sha256,
        "inputs": outcome_inputs(out_dir, outcome),
        "summary": _json_clean(outcome.summary.as_dict()),
    }
    atomic.write_bytes(paths["marker"], (json.dumps(marker, indent=1) + "\n").encode("utf-8"))


def outcome_inputs(out_dir, outcome: PictureOutcome) -> dict | None:
    """The per-picture input fingerprints of ``outcome`` for its marker (None when unknown)."""
    wd = outcome.workdir
    if wd is None:
        return None
    return _json_clean(picture_inputs(wd, outcome.summary.picture, outcome.photo_name, outcome.maplets))


def read_marker(out_dir, picture: str) -> dict | None:
    """The done-marker of ``picture`` (None when absent or unreadable)."""
    path = output_paths(out_dir, picture)["marker"]
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("format") != MARKER_FORMAT or doc.get("picture") != picture:
        return None
    return doc


def done_summary(
    workdir, out_dir, picture: str, fingerprint: str, options: BatchOptions | None = None,
    shared_sha256: str | None = None,
) -> PictureSummary | None:
    """The stored summary if ``picture`` is done with these options, this spctool version and the
    same inputs (its SUM, photo and maplets; with ``options`` or ``shared_sha256`` also the shared
    inputs, :func:`shared_inputs_sha256`), else None."""
    if not guard.is_valid_name(picture):
        return None
    doc = read_marker(out_dir, picture)
    if doc is None or doc.get("options_sha256") != fingerprint or doc.get("spctool_version") != __version__:
        return None
    wd = WorkDir(Path(workdir))
    try:
        raw = wd.sum_path(picture).read_bytes()
    except OSError:
        return None
    if doc.get("input_sum_sha256") != hashlib.sha256(raw).hexdigest():
        return None
    if not _same_inputs(wd, picture, doc.get("inputs")):
        return None
    if shared_sha256 is None and options is not None:
        shared_sha256 = shared_inputs_sha256(workdir, options)
    if shared_sha256 is not None and doc.get("shared_inputs_sha256") != shared_sha256:
        return None
    paths = output_paths(out_dir, picture)
    if not paths["sum"].exists():
        return None
    try:
        summary = PictureSummary.from_dict(doc["summary"])
    except (KeyError, TypeError, ValueError):
        return None
    summary.resumed = True
    return summary


@contextlib.contextmanager
def _one_numba_thread():
    """Run a picture's numba kernels on one thread (numba's setting is per thread; restored after).

    One worker = one core, whatever the back end: more cores are used by more workers, never by
    threads inside a picture, so a picture's result never depends on a thread count (a parallel
    reduction may round differently with another count) and two workers on two cores do not fight
    over them.
    """
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency
        yield
        return
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(before)


def process_picture(
    workdir, out_dir, picture: str, options: BatchOptions, fingerprint: str, stamp: str | None = None
) -> PictureSummary:
    """Worker task: navigate one picture and write its outputs; returns the summary row.

    A failure to write the outputs is reported as the picture's failure too.  ``timings["write_s"]``
    (writing, in the returned summary only: the marker is written before it is known).
    """
    with _one_numba_thread():
        outcome = navigate_picture(workdir, picture, options, stamp=stamp)
    clock = time.perf_counter()
    try:
        write_outcome(out_dir, outcome, fingerprint)
    except (OSError, SpcError) as exc:  # a full disk, a read-only out_dir: this picture fails
        outcome.summary.status = "failed: " + _one_line(f"cannot write the outputs: {exc}")
    outcome.summary.timings["write_s"] = time.perf_counter() - clock
    return outcome.summary


# --------------------------------------------------------------------------------------------------
# driver


@dataclass
class BatchResult:
    """The summaries of a batch in picture order, and where its outputs are."""

    pictures: list[PictureSummary]
    out_dir: Path
    fingerprint: str
    elapsed_s: float = math.nan
    mode: str = "local"
    #: how local worker processes started (``fork`` / ``spawn``; None in-process and on Dask)
    start_method: str | None = None
    workers: int = 1
    options: dict = field(default_factory=dict)

    @property
    def failed(self) -> list[PictureSummary]:
        return [p for p in self.pictures if p.failed]

    def counts(self) -> dict[str, int]:
        out = {k: 0 for k in STATUSES}
        for p in self.pictures:
            out[p.kind] = out.get(p.kind, 0) + 1
        out["resumed"] = sum(1 for p in self.pictures if p.resumed)
        return out

    def to_table(self):
        """The summary table: picture, candidates, selected, found, used, rms before/after (px),
        position change (km), attitude change (rad), status — one row per picture, in list order."""
        from spctool.formats.table import LandmarkTable

        ps = self.pictures

        def col(name, dtype=np.float64):
            return np.array([getattr(p, name) for p in ps], dtype=dtype)

        cols = {
            "picture": [p.picture for p in ps],
            "candidates": col("candidates", np.int64),
            "selected": col("selected", np.int64),
            "found": col("found", np.int64),
            "used": col("used", np.int64),
            "rms_before_px": col("rms_before_px"),
            "rms_after_px": col("rms_after_px"),
            "dposition_km": col("dposition_km"),
            "dattitude_rad": col("dattitude_rad"),
            "status": [p.kind for p in ps],
        }
        table = LandmarkTable(cols, command="batch", meta={})
        c = self.counts()
        table.comments.append(
            f"{len(ps)} pictures: {c['ok']} ok, {c['no-pose']} no-pose, {c['failed']} failed"
            + (f"; {c['resumed']} done earlier (skipped)" if c["resumed"] else "")
        )
        table.comments.append(f"outputs: {self.out_dir}")
        return table

    def to_text(self) -> str:
        """The summary table, then one ``# PICTURE status: reason`` line per picture not ok (the
        table's status column holds the word only, so the rows stay whitespace-separated)."""
        lines = [f"# {p.picture} {p.status}\n" for p in self.pictures if p.kind != "ok"]
        lines += [f"# {p.picture} note: {n}\n" for p in self.pictures for n in p.notes]
        return self.to_table().to_text() + "".join(lines)

    def to_json_dict(self) -> dict:
        return {
            "command": "batch",
            "format": SUMMARY_FORMAT,
            "spctool_version": __version__,
            "out_dir": str(self.out_dir),
            "mode": self.mode,
            "start_method": self.start_method,
            "workers": self.workers,
            "elapsed_s": self.elapsed_s,
            "options_sha256": self.fingerprint,
            "options": _jsonable(self.options),
            "counts": self.counts(),
            "pictures": [_json_clean(p.as_dict()) for p in self.pictures],
        }

    def to_json(self) -> str:
        return json.dumps(self.to_json_dict(), indent=2, allow_nan=False) + "\n"

    def write_summary(self) -> None:
        atomic.write_bytes(self.out_dir / f"{SUMMARY_STEM}.txt", self.to_text().encode("utf-8"))
        atomic.write_bytes(self.out_dir / f"{SUMMARY_STEM}.json", self.to_json().encode("utf-8"))


def _json_clean(v):
    """NaN/inf → None (JSON null), recursively."""
    if isinstance(v, dict):
        return {k: _json_clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_clean(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def batch_pictures(workdir, pictlist=None) -> list[str]:
    """The pictures to process: the active names of ``pictlist`` (a PICTLIST-format file), else of
    the working directory's PICTLIST (PICTLISTX.TXT preferred, else every SUMFILES/*.SUM); duplicates
    dropped, order kept."""
    if pictlist is not None:
        from spctool.formats.lists import read_pictlist

        names = read_pictlist(pictlist).active_names
    else:
        names = WorkDir(Path(workdir)).picture_names()
    where = pictlist if pictlist is not None else WorkDir(Path(workdir)).pictlist_path
    names = [guard.check_name(n, "picture name", where) for n in names if n.strip()]
    return list(dict.fromkeys(names))


def _check_usable(workdir, options: BatchOptions) -> None:
    """Fail early (SpcUsageError / SpcFormatError) when no picture could be processed: unreadable
    INIT_LITHOS or selection options, no candidate landmarks, a required shape model missing."""
    from spctool.stages.select import SelectOptions

    wd = WorkDir(Path(workdir))
    SelectOptions.from_settings(wd.read_settings(options.settings_path), **options.select)
    if not wd.landmark_names():
        raise SpcUsageError(f"{wd.root}: no candidate landmarks (no LMRKLIST.TXT, no LMKFILES/*.LMK)")
    if options.occlusion and not (options.shape_path or wd.shape_path.exists()):
        raise SpcUsageError(f"the occlusion test needs a shape model ({wd.shape_path} not found)")
    if options.shape_path and not Path(options.shape_path).exists():
        raise SpcUsageError(f"{options.shape_path}: shape model not found")


def _init_worker(workdir, options, stamp, warm: tuple = (), barrier=None) -> None:
    """Worker-process initializer: leave Ctrl-C to the parent (it stops the pool); load the shared
    data of ``workdir`` once; navigate the pictures ``warm`` (nothing written) so their code paths —
    numba kernels, the photo readers — are loaded before the first real picture; then meet the other
    workers at ``barrier`` (:class:`WorkerPool`)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        if workdir is not None:
            SharedData.get(workdir, options, stamp)
            for name in warm:
                with _one_numba_thread():
                    navigate_picture(workdir, name, options, stamp=stamp)
    except Exception:  # noqa: BLE001 - every picture will report the problem itself
        pass
    if barrier is not None:
        try:
            barrier.wait(timeout=WARM_TIMEOUT_S)
        except threading.BrokenBarrierError:
            pass


def run_batch(
    workdir,
    pictures: Sequence[str] | None = None,
    options: BatchOptions | None = None,
    *,
    out_dir,
    jobs: int = 1,
    scheduler=None,
    force: bool = False,
    on_result: Callable[[PictureSummary], None] | None = None,
    write_summary: bool = True,
    pool: WorkerPool | None = None,
) -> BatchResult:
    """Process ``pictures`` (default: the working directory's PICTLIST) and write their outputs.

    ``jobs``: 1 = in this process, N > 1 = N worker processes (forked where safe, else spawned:
    :func:`start_method`), each worker (this process too) computing on one core (numba limited to one
    thread); ``scheduler``: a Dask scheduler address (``tcp://host:port``) or a
    ``distributed.Client`` — then ``jobs`` is ignored;
    ``pool``: a :class:`WorkerPool` whose warm workers run the batch (``jobs`` ignored too).
    Pictures already done with the same options and input SUM are skipped unless ``force``.
    ``on_result(summary)`` is called in this process as each picture finishes (skipped ones first).
    Returns the summaries in picture order; raises only for bad usage (SpcUsageError) and interrupts.
    """
    options = options if options is not None else BatchOptions()
    workdir = Path(workdir).resolve()
    out_dir = Path(out_dir).resolve()
    if out_dir == workdir:
        raise SpcUsageError(
            f"--out-dir must differ from the working directory ({workdir}): the batch reads SUMFILES/ there"
        )
    if scheduler is not None and pool is not None:
        raise SpcUsageError("a batch runs on a Dask scheduler or on a worker pool, not both")
    if pool is not None:
        if pool.closed:
            raise SpcUsageError("the worker pool is closed")
        jobs = pool.jobs
    if int(jobs) < 1:
        raise SpcUsageError(f"--jobs must be at least 1, got {jobs}")
    if pictures is None:
        names = batch_pictures(workdir)  # checked names (they become output paths)
    else:  # checked (stripped) before de-duplication, so "A" and "A " are one picture
        names = list(dict.fromkeys(guard.check_name(n, "picture name") for n in pictures))
    fingerprint = options.fingerprint()
    stamp = inputs_stamp(workdir, options, fingerprint)  # workers reuse data of unchanged files
    out_dir.mkdir(parents=True, exist_ok=True)
    tick = on_result or (lambda s: None)
    t0 = time.perf_counter()

    results: list[PictureSummary | None] = [None] * len(names)
    todo: list[int] = []
    shared_sha = None if force else shared_inputs_sha256(workdir, options)
    for i, name in enumerate(names):
        done = None if force else done_summary(workdir, out_dir, name, fingerprint, shared_sha256=shared_sha)
        if done is not None:
            results[i] = done
            tick(done)
        else:
            todo.append(i)

    if todo and scheduler is None and pool is None and int(jobs) == 1:
        SharedData.get(workdir, options, stamp)  # settings, candidates, shape: fail here, once
    elif todo:
        _check_usable(workdir, options)  # the cheap part of that check; the workers load the rest

    def record(i: int, summary: PictureSummary) -> None:
        results[i] = summary
        tick(summary)

    mode, workers, method = "local", int(jobs), None
    if todo and scheduler is not None:
        mode = "dask"
        workers = _run_dask(scheduler, workdir, out_dir, names, todo, options, fingerprint, stamp, record)
    elif todo and (int(jobs) > 1 or pool is not None):
        mode = "processes"
        method = _run_processes(
            int(jobs), workdir, out_dir, names, todo, options, fingerprint, stamp, record, pool=pool
        )
    elif todo:
        for i in todo:
            record(i, process_picture(workdir, out_dir, names[i], options, fingerprint, stamp))

    result = BatchResult(
        [r for r in results if r is not None],
        out_dir,
        fingerprint,
        elapsed_s=time.perf_counter() - t0,
        mode=mode,
        workers=workers,
        start_method=method,
        options=options.as_dict(),
    )
    if write_summary:
        result.write_summary()
    return result


def _lost(picture: str, exc: BaseException) -> PictureSummary:
    reason = _one_line(f"worker lost: {type(exc).__name__}: {exc}")
    return PictureSummary(picture=picture, status="failed: " + reason)


def _run_processes(
    jobs, workdir, out_dir, names, todo, options, fingerprint, stamp, record, task=None, pool=None
) -> str | None:
    """Run ``task`` (default :func:`process_picture`) for the pictures ``todo`` in worker processes;
    returns how the (first) workers were started (:func:`start_method`).

    At most ``2 * jobs`` pictures are in flight — one computing and one queued per worker, so a worker
    that finishes a picture starts its next at once instead of idling while this process collects the
    result and submits more (this process needs a core for that round trip while the workers hold
    them all).  ``pool``: a :class:`WorkerPool` to run on first (it is not shut down here).  When a
    worker process dies (a crash in native code, the OOM killer)
    the suspects are those few: they are retried one at a time in a one-worker pool,
    which names the culprit ("failed: worker lost: …") and completes the innocent; the other
    pictures go on in a fresh pool.  A death never stops the batch.
    """
    from collections import deque
    from concurrent.futures import FIRST_COMPLETED, wait
    from concurrent.futures.process import BrokenProcessPool

    task = task or process_picture
    queue, suspects = deque(todo), deque()
    first_method = None
    while queue or suspects:
        solo = bool(suspects)
        source, width = (suspects, 1) if solo else (queue, jobs)
        depth = 1 if solo else 2 * width  # pictures in flight (docstring)
        given = pool is not None and not solo and not pool.closed
        if given:
            executor, method = pool.executor, pool.method
        else:
            method = start_method()
            executor = _new_pool(min(width, len(source)), method, (str(workdir), options, stamp))
        first_method = first_method or method
        inflight: dict = {}
        broken = False
        try:
            while (source or inflight) and not broken:
                while source and len(inflight) < depth:
                    i = source.popleft()
                    try:
                        fut = executor.submit(
                            task, str(workdir), str(out_dir), names[i], options, fingerprint, stamp
                        )
                    except (BrokenProcessPool, RuntimeError):  # a given pool broke between batches
                        if not given:
                            raise
                        source.appendleft(i)
                        broken = True
                        break
                    inflight[fut] = i
                if broken:
                    break
                done, _ = wait(inflight, return_when=FIRST_COMPLETED)
                for fut in done:
                    i = inflight.pop(fut)
                    try:
                        summary = fut.result()
                    except BrokenProcessPool as exc:
                        broken = True
                        if solo:
                            record(i, _lost(names[i], exc))
                        else:
                            suspects.append(i)
                        continue
                    except Exception as exc:  # noqa: BLE001 - e.g. a result that cannot be unpickled
                        summary = _lost(names[i], exc)
                    record(i, summary)
            suspects.extend(inflight.values())  # in flight when the pool broke
        except BaseException:
            pool.close(kill=True) if given else _stop_pool(executor)
            raise
        if given:
            if broken:
                pool.close(kill=True)  # a worker died: the caller's pool is unusable from here on
        elif broken:
            _stop_pool(executor)
        else:
            executor.shutdown(wait=True)
    return first_method


class WorkerPool:
    """Local worker processes kept alive from one batch to the next (``run_batch(..., pool=...)``).

    ``spctool batch`` starts its workers for one batch; a pipeline that runs batch after batch from
    Python — pictures navigated as they are downlinked, a study re-running a batch with other options
    — keeps them instead, so every batch after the first starts computing at once: each worker keeps
    its imports, numba's loaded kernels and the :class:`SharedData` of each working directory for as
    long as its files are unchanged (:func:`inputs_stamp`).  Results are those of any other back end.

    ``warm=(workdir, options)``: each worker, as it starts, loads that directory's shared data and
    navigates (without writing anything) one picture of each photo format the batch will read, so even
    the first batch finds its workers ready.  Workers start as :func:`start_method` says.  A pool
    whose worker died (a crash in native code) is closed; the batch that saw it completes in fresh
    processes.  Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, jobs: int, warm: tuple | None = None):
        jobs = int(jobs)
        if jobs < 1:
            raise SpcUsageError(f"a worker pool needs at least 1 worker, got {jobs}")
        self.jobs = jobs
        self.method = start_method()
        self.closed = False
        initargs: tuple = (None, None, None)
        if warm is not None:
            import multiprocessing

            workdir, options = warm
            workdir = Path(workdir).resolve()
            options = options if options is not None else BatchOptions()
            # the workers meet at a barrier once warm: no worker takes a task before all are ready
            barrier = multiprocessing.get_context(self.method).Barrier(jobs)
            stamp = inputs_stamp(workdir, options)
            initargs = (str(workdir), options, stamp, _one_per_format(workdir), barrier)
        self.executor = _new_pool(jobs, self.method, initargs)
        if warm is not None:
            # jobs tasks at once start every worker (spawned workers start on demand); the first
            # result means every worker is past the barrier, so warm
            from concurrent.futures import FIRST_COMPLETED, wait
            from concurrent.futures.process import BrokenProcessPool

            started = [self.executor.submit(os.getpid) for _ in range(jobs)]
            done, _ = wait(started, timeout=WARM_TIMEOUT_S + 60, return_when=FIRST_COMPLETED)
            try:
                for fut in done:
                    fut.result()
            except BrokenProcessPool as exc:
                self.close(kill=True)
                raise SpcUsageError(
                    f"the worker pool could not start: a worker died warming up ({_one_line(exc)})"
                ) from None

    def close(self, kill: bool = False) -> None:
        """End the workers (``kill``: now, cancelling what has not started)."""
        if self.closed:
            return
        self.closed = True
        if kill:
            _stop_pool(self.executor)
        else:
            self.executor.shutdown(wait=True)

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close(kill=exc[0] is not None)


def _one_per_format(workdir: Path) -> tuple[str, ...]:
    """The first picture of the working directory's PICTLIST for each photo file suffix."""
    wd = WorkDir(workdir)
    seen: dict[str, str] = {}
    for name in batch_pictures(workdir):
        path = wd.photo_path(name)
        if path is not None and wd.sum_path(name).exists():
            seen.setdefault(path.suffix.upper(), name)
    return tuple(seen.values())


def start_method() -> str:
    """How local worker processes start: ``fork`` where that is safe, else ``spawn``.

    A forked worker inherits this process's imports (numpy, scipy, numba, spctool: ~0.5 s a spawned
    worker spends before its first picture) and any shared data already loaded.  Fork is safe here
    only on Linux (macOS system libraries are not fork-safe), while this process runs a single thread
    (a lock held by another thread — a progress bar writing to stderr — would stay locked in the
    child) and before numba's threading layer has started (GNU OpenMP, numba's default on Linux,
    aborts a forked child that runs a parallel kernel).  ``SPCTOOL_START_METHOD=spawn|fork|forkserver``
    overrides the choice.
    """
    import sys

    forced = os.environ.get("SPCTOOL_START_METHOD", "").strip().lower()
    if forced:
        if forced not in ("spawn", "fork", "forkserver"):
            raise SpcUsageError(f"SPCTOOL_START_METHOD must be spawn, fork or forkserver, got {forced!r}")
        return forced
    if not sys.platform.startswith("linux") or threading.active_count() != 1:
        return "spawn"
    parallel = sys.modules.get("numba.np.ufunc.parallel")
    if parallel is not None and getattr(parallel, "_is_initialized", True):
        layer = getattr(parallel, "_threading_layer", None)
        if layer != "workqueue":  # numba's own layer is fork-safe; OpenMP and TBB here are not
            return "spawn"
    return "fork"


def _new_pool(workers: int, method: str, initargs: tuple):
    """Worker processes started by ``method``, each running :func:`_init_worker` with ``initargs``."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    # the workers end with this process (_watch_parent): PR_SET_PDEATHSIG is tied to the thread
    # that starts a worker, so it is asked for only when that is this process's main thread
    tied = threading.current_thread() is threading.main_thread()
    return ProcessPoolExecutor(
        max_workers=workers,
        mp_context=multiprocessing.get_context(method),
        initializer=_init_guarded_worker,
        initargs=(os.getpid(), tied, initargs),
    )


#: how often a worker checks that the process that started it is alive (seconds)
PARENT_POLL_S = 0.5


def _init_guarded_worker(parent_pid: int, tied: bool, initargs: tuple) -> None:
    _watch_parent(parent_pid, tied)
    _init_worker(*initargs)


def _watch_parent(parent_pid: int, tied: bool) -> None:
    """End this worker process when its parent dies (a killed ``spctool batch --jobs N`` must not
    leave its workers computing forever): on Linux the kernel sends SIGKILL at once
    (``prctl(PR_SET_PDEATHSIG)``, when ``tied``); everywhere a daemon thread checks every
    :data:`PARENT_POLL_S` whether the process was re-parented and exits if so."""
    import sys

    if tied and sys.platform.startswith("linux"):
        try:
            import ctypes
            import signal

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        except (OSError, AttributeError):  # pragma: no cover - no prctl: the thread below suffices
            pass
    if os.getppid() != parent_pid:  # the parent died before the guard was in place
        os._exit(1)

    def watch():
        while True:
            time.sleep(PARENT_POLL_S)
            if os.getppid() != parent_pid:
                os._exit(1)

    threading.Thread(target=watch, name="spctool-parent-watch", daemon=True).start()


def _stop_pool(pool) -> None:
    """Cancel what has not started and end the worker processes now (their pictures are not marked
    done, so the next run redoes them)."""
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        try:
            proc.terminate()
        except Exception:  # noqa: BLE001 - already gone
            pass


def _run_dask(scheduler, workdir, out_dir, names, todo, options, fingerprint, stamp, record) -> int:
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise SpcUsageError("--scheduler needs Dask distributed: pip install 'spctool[dask]'") from None
    own = not hasattr(scheduler, "submit")
    if own:
        try:
            client = Client(str(scheduler), timeout="30s", set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise SpcUsageError(
                f"cannot connect to the Dask scheduler {scheduler}: {_one_line(exc)}"
            ) from None
    else:
        client = scheduler
    futures = []
    try:
        workers = max(1, len(client.scheduler_info().get("workers", {})))
        run_id = uuid.uuid4().hex[:12]  # unique task keys: never shared with another batch
        keys = [f"spctool-batch-{names[i]}-{run_id}" for i in todo]
        futures = client.map(
            process_picture,
            [str(workdir)] * len(todo),
            [str(out_dir)] * len(todo),
            [names[i] for i in todo],
            [options] * len(todo),
            [fingerprint] * len(todo),
            [stamp] * len(todo),
            key=keys,
            pure=False,
        )
        index = {f.key: i for f, i in zip(futures, todo)}
        for fut in as_completed(futures, loop=client.loop):
            i = index[fut.key]
            try:
                summary = fut.result()
            except Exception as exc:  # noqa: BLE001 - lost worker, cancelled task
                summary = _lost(names[i], exc)
            record(i, summary)
            fut.release()
    except BaseException:
        if futures:
            try:
                client.cancel(futures)
            except Exception:  # noqa: BLE001
                pass
        raise
    finally:
        if own:
            client.close()
    return workers
