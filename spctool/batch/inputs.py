"""Batch inputs: the options of a batch, the data a worker shares between its pictures, and the
fingerprints of every input a picture's result depends on (what makes a batch resumable).

Specification: the package docstring (:mod:`spctool.batch`), spc-formats.md §7.1 (PICTLIST) and
cli-contract.md "batch".
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spctool import __version__
from spctool.batch import layout
from spctool.errors import SpcError, SpcFormatError, SpcUsageError
from spctool.formats import guard
from spctool.formats.workdir import WorkDir
from spctool.geometry.shape import as_shape
from spctool.jsonsafe import json_safe
from spctool.stages.navigate import NavigateOptions
from spctool.stages.pose import PoseOptions
from spctool.stages.register import RegisterOptions

MARKER_FORMAT = "spctool-batch-done/2"  # /2: input fingerprints cover every input (issue #19)
SUMMARY_FORMAT = "spctool-batch/1"
TABLES_DIR = layout.TABLES_DIR
SUMMARY_STEM = "BATCH_SUMMARY"
#: status words of a picture; the text after ``": "`` is the one-line reason.  ``inconsistent`` (χ² of
#: the fit above its 99.9 % quantile) and ``prior-contradicted`` (the measurements contradict the SUM's
#: SIGMA_VSO/SIGMA_PTG) are solved poses that are not plain ``ok`` (:attr:`PoseResult.verdict`)
STATUSES = ("ok", "inconsistent", "prior-contradicted", "no-pose", "failed")
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
    """The options as JSON for their fingerprint: unlike :func:`spctool.jsonsafe.json_safe`, a NaN or
    an unknown object keeps its ``repr`` (two options that differ must never print alike)."""
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
    return json_safe(now) == stored


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


