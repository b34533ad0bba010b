"""One picture of a batch: select → register (two-pass navigation by default) → solve-pose, its
outputs in SPC's layout and its done-marker, written last.

Specification: the package docstring (:mod:`spctool.batch`); L15 §2 (the stages) and issue #15
(two-pass navigation).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spctool import __version__
from spctool.batch.inputs import (
    MARKER_FORMAT,
    TABLES_DIR,
    BatchOptions,
    SharedData,
    _same_inputs,
    picture_inputs,
    shared_inputs_sha256,
)
from spctool.errors import SpcError, SpcFormatError, SpcUsageError
from spctool.formats import atomic, guard
from spctool.formats.sumfile import with_measured_landmarks, with_pose
from spctool.formats.workdir import WorkDir
from spctool.jsonsafe import json_safe
from spctool.stages.pose import PoseError, PoseOptions

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
    """One picture through SPC's stages (reading, A lithos-select, H register, I solve-pose), each
    timed into ``timings``; results and the new SUM text go into ``out``."""
    pic, camera, photo = _read_inputs(shared, picture, out, timings)
    sel = _select_stage(shared, pic, camera, out, timings)
    reg, nav, names, positions = _register_stage(shared, pic, camera, photo, sel, options, out, timings)
    _pose_stage(pic, camera, reg, nav, names, positions, options, out, timings)


def _read_inputs(shared: SharedData, picture: str, out: PictureOutcome, timings):
    """The SUM (hashed, parsed, checked finite), its camera and its photo (size checked)."""
    from spctool.formats.sumfile import parse_sum
    from spctool.geometry.camera import Camera

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
    guard.check_sum_header(pic, sum_path)  # a NaN pose or a skewed frame in, never a wrong pose out
    out.photo_name = pic.name
    camera = Camera.from_picture(pic, shared.settings, picture_name=picture)  # getmm(PICNM)
    photo = wd.read_photo(pic.name, npx=pic.npx, nln=pic.nln)
    if photo.data.shape != (pic.nln, pic.npx):
        raise SpcFormatError(
            wd.photo_path(pic.name),
            None,
            f"a {pic.npx} x {pic.nln} px photo as the SUM says (found {photo.npx} x {photo.nln})",
        )
    timings["read_s"] = time.perf_counter() - clock

    return pic, camera, photo


def _select_stage(shared: SharedData, pic, camera, out: PictureOutcome, timings):
    """Stage A: the maplets the picture sees, with their a-priori pixels."""
    from spctool.stages.select import select_maplets

    summary = out.summary
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

    return sel


def _register_stage(shared: SharedData, pic, camera, photo, sel, options: BatchOptions, out, timings):
    """Stage H: the selected landmarks registered (two-pass navigation when asked); a landmark whose
    maplet cannot be read is a ``no-maplet`` row."""
    from spctool.stages.register import register

    summary = out.summary
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
        f"registered {summary.found} of {len(reg) + len(missing)} landmarks ({schedule}, {ropts.space} space)"
    )
    out.register_table = table
    timings["register_s"] = time.perf_counter() - clock

    return reg, nav, names, positions


def _pose_stage(pic, camera, reg, nav, names, positions, options: BatchOptions, out, timings):
    """Stage I: the pose from the registered landmarks, the status it earns and the new SUM text."""
    from spctool.stages.pose import solve_pose

    summary = out.summary
    ok = reg.ok
    # ---- Stage I: solve-pose ---------------------------------------------------------------------
    clock = time.perf_counter()
    new_pic = with_measured_landmarks(pic, reg.names, reg.measured, reg.ok)
    use = np.flatnonzero(ok)
    # two-pass navigation's final weights and covariance (issue #39, NavigateOptions.weights: calibrated,
    # surface with the shading model's error patterns, or uniform) — the same solve as its final pass
    sens = None if nav is None else nav.final.sensitivity
    calibrated = nav is not None and nav.options.weights == "calibrated"
    try:
        pose = solve_pose(
            camera,
            positions[use],
            reg.measured[use],
            options.pose,
            prior_sigma_position=pic.sigma_vso,
            prior_sigma_attitude=pic.sigma_ptg,
            names=[names[i] for i in use],
            pixel_covariances=reg.covariance[use] if (calibrated or sens is not None) else None,
            error_modes=None if sens is None else sens.modes[use],
            estimate_weights="uniform" if calibrated else "covariance",
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
        if nav is not None and nav.status != "ok":  # navigation could not confirm a pose
            summary.status = nav.status
        elif pose.converged and not pose.plausible:
            summary.status = f"no-pose: implausible fit: {pose.implausible}"
        elif pose.converged:
            # written also when inconsistent (its covariance scaled by cost/dof) or prior-contradicted:
            # the status says which, with the one line behind it
            new_pic = with_pose(new_pic, pose.scobj, pose.rotation, pose.sigma_position, pose.sigma_attitude)
            summary.status = "ok" if pose.verdict == "ok" else f"{pose.verdict}: {pose.verdict_reason}"
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


def _refuse_input_folder(paths: dict[str, Path], wd: WorkDir | None) -> None:
    """SpcUsageError naming both paths when a picture's output folder is a symbolic link (the output
    tree's links are never followed) or, by device and inode, the working directory's SUMFILES/ or
    TABLES/ (checked again per picture: a link made while the batch runs is caught too)."""
    inputs = [] if wd is None else [wd.root / "SUMFILES", wd.root / "IMAGEFILES", wd.root]
    for key in ("sum", "marker"):
        folder = paths[key].parent
        if folder.is_symlink():
            raise SpcUsageError(
                f"{folder} is a symbolic link: the batch does not follow links in its output tree"
            )
        guard.refuse_input_overwrite(folder, inputs, "output folder")


def write_outcome(out_dir, outcome: PictureOutcome, fingerprint: str) -> None:
    """Write a picture's outputs atomically, the done-marker last (only when it did not fail)."""
    paths = output_paths(out_dir, outcome.summary.picture)
    _refuse_input_folder(paths, outcome.workdir)  # before anything is removed (clear_outputs)
    for path in paths.values():  # none is a file this picture read, by any path (guard.input_scope)
        guard.refuse_read_input(path)
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
        "summary": json_safe(outcome.summary.as_dict()),
    }
    atomic.write_bytes(paths["marker"], (json.dumps(marker, indent=1) + "\n").encode("utf-8"))


def outcome_inputs(out_dir, outcome: PictureOutcome) -> dict | None:
    """The per-picture input fingerprints of ``outcome`` for its marker (None when unknown)."""
    wd = outcome.workdir
    if wd is None:
        return None
    return json_safe(picture_inputs(wd, outcome.summary.picture, outcome.photo_name, outcome.maplets))


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
    workdir,
    out_dir,
    picture: str,
    fingerprint: str,
    options: BatchOptions | None = None,
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
    with guard.input_scope():  # the picture's inputs are never replaced by its outputs
        with _one_numba_thread():
            outcome = navigate_picture(workdir, picture, options, stamp=stamp)
        clock = time.perf_counter()
        try:
            write_outcome(out_dir, outcome, fingerprint)
        except (OSError, SpcError) as exc:  # a full disk, a read-only out_dir: this picture fails
            outcome.summary.status = "failed: " + _one_line(f"cannot write the outputs: {exc}")
        outcome.summary.timings["write_s"] = time.perf_counter() - clock
    return outcome.summary
