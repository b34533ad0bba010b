"""The batch driver: every picture of a PICTLIST in this process, in local worker processes (a new
pool or a kept :class:`WorkerPool`) or on a Dask cluster, with the same files written whatever the back
end, and the batch's summary.

Specification: the package docstring (:mod:`spctool.batch`, "Parallelism").
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spctool import __version__
from spctool.batch.inputs import (
    STATUSES,
    SUMMARY_FORMAT,
    SUMMARY_STEM,
    WARM_TIMEOUT_S,
    BatchOptions,
    SharedData,
    _jsonable,
    inputs_stamp,
    shared_inputs_sha256,
)
from spctool.batch.lock import out_dir_lock
from spctool.batch.picture import (
    PictureSummary,
    _one_line,
    _one_numba_thread,
    done_summary,
    navigate_picture,
    process_picture,
)
from spctool.errors import SpcUsageError
from spctool.formats import atomic, guard
from spctool.formats.rows import spc_columns, use_spc_columns
from spctool.formats.workdir import WorkDir
from spctool.jsonsafe import json_safe
from spctool.workers import start_method

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
        """Pictures per status word (:data:`STATUSES`) and ``resumed``."""
        out = {k: 0 for k in STATUSES}
        for p in self.pictures:
            out[p.kind] = out.get(p.kind, 0) + 1
        out["resumed"] = sum(1 for p in self.pictures if p.resumed)
        return out

    def counts_text(self) -> str:
        """'3 ok, 1 inconsistent, 0 no-pose, 0 failed' (inconsistent and prior-contradicted only when
        some are)."""
        c = self.counts()
        words = [k for k in STATUSES if c.get(k) or k in ("ok", "no-pose", "failed")]
        return ", ".join(f"{c.get(k, 0)} {k}" for k in words)

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
            f"{len(ps)} pictures: {self.counts_text()}"
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
            "pictures": [json_safe(p.as_dict()) for p in self.pictures],
        }

    def to_json(self) -> str:
        return json.dumps(self.to_json_dict(), indent=2, allow_nan=False) + "\n"

    def write_summary(self) -> None:
        atomic.write_bytes(self.out_dir / f"{SUMMARY_STEM}.txt", self.to_text().encode("utf-8"))
        atomic.write_bytes(self.out_dir / f"{SUMMARY_STEM}.json", self.to_json().encode("utf-8"))


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
    on_note: Callable[[str], None] | None = None,
) -> BatchResult:
    """Process ``pictures`` (default: the working directory's PICTLIST) and write their outputs.

    ``jobs``: 1 = in this process, N > 1 = N worker processes (forked where safe, else spawned:
    :func:`start_method`), each worker (this process too) computing on one core (numba limited to one
    thread); ``scheduler``: a Dask scheduler address (``tcp://host:port``) or a
    ``distributed.Client`` — then ``jobs`` is ignored;
    ``pool``: a :class:`WorkerPool` whose warm workers run the batch (``jobs`` ignored too).
    Pictures already done with the same options and input SUM are skipped unless ``force``.
    ``on_result(summary)`` is called in this process as each picture finishes (skipped ones first).
    ``on_note(text)``: told of what the user should know that is no failure (a stale batch lock of
    ``out_dir`` taken over).
    One batch at a time writes ``out_dir`` (:mod:`spctool.batch.lock`); ``out_dir`` and its
    ``SUMFILES/``, ``TABLES/``, ``PLOTS/`` may be neither the working directory nor one of its SPC
    folders, by any path, nor symbolic links (:func:`check_out_dir`).
    Returns the summaries in picture order; raises only for bad usage (SpcUsageError) and interrupts.
    """
    with contextlib.ExitStack() as locks:  # the out_dir lock, taken once the checks passed
        return _run_batch(
            workdir,
            pictures,
            options,
            out_dir=out_dir,
            jobs=jobs,
            scheduler=scheduler,
            force=force,
            on_result=on_result,
            write_summary=write_summary,
            pool=pool,
            locks=(locks, on_note),
        )


def _run_batch(
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
    locks: tuple = (None, None),
) -> BatchResult:
    """:func:`run_batch`; ``locks``: (an ExitStack that holds the out_dir lock, the note callback)."""
    options = options if options is not None else BatchOptions()
    workdir = Path(workdir).resolve()
    out_dir = Path(out_dir).resolve()
    if out_dir == workdir:
        raise SpcUsageError(
            f"--out-dir must differ from the working directory ({workdir}): the batch reads SUMFILES/ there"
        )
    check_out_dir(workdir, out_dir)
    if scheduler is not None and pool is not None:
        raise SpcUsageError("a batch runs on a Dask scheduler or on a worker pool, not both")
    if isinstance(scheduler, str):  # checked before any work: form, reachability, a Dask handshake
        from spctool.batch.scheduler import check_scheduler

        scheduler = str(check_scheduler(scheduler))
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
    check_out_dir(workdir, out_dir)  # again: the directory may have been made just now
    if locks[0] is not None:
        locks[0].enter_context(out_dir_lock(out_dir, locks[1]))
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


#: the working directory's folders a batch reads (never written: :func:`check_out_dir`)
SPC_FOLDERS = ("SUMFILES", "IMAGEFILES", "LMKFILES", "MAPFILES", "SHAPEFILES", "NOMINALS")
#: the folders a batch writes under out_dir (never followed when they are symbolic links)
OUT_FOLDERS = ("SUMFILES", "TABLES", "PLOTS")


def check_out_dir(workdir: Path, out_dir: Path) -> None:
    """SpcUsageError (one line naming both paths) when writing the batch's outputs under ``out_dir``
    could replace an input: ``out_dir`` is the working directory or one of its SPC folders by device
    and inode (a bind mount, a second path), or ``out_dir/SUMFILES`` (``TABLES``, ``PLOTS``) is a
    symbolic link (never followed) or one of the working directory's folders; also a name that is not
    valid UTF-8 (the summary records it)."""
    try:
        str(out_dir).encode("utf-8")
    except UnicodeEncodeError:
        shown = os.fsencode(out_dir).decode("utf-8", errors="backslashreplace")
        raise SpcUsageError(
            f"--out-dir {shown}: the name is not valid UTF-8 (the batch summary records it); choose another"
        ) from None
    if guard.same_file(out_dir, workdir):
        raise SpcUsageError(
            f"--out-dir {out_dir} must differ from the working directory {workdir} (same device and "
            "inode): the batch reads SUMFILES/ there"
        )
    inputs = [workdir] + [workdir / d for d in SPC_FOLDERS]
    guard.refuse_input_overwrite(out_dir, inputs, "--out-dir")
    for sub in OUT_FOLDERS:
        path = out_dir / sub
        if path.is_symlink():
            raise SpcUsageError(
                f"{path} is a symbolic link to {path.resolve()}: the batch does not follow links in "
                "its output tree; remove it or choose another --out-dir"
            )
        guard.refuse_input_overwrite(path, inputs, "output folder")


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

            try:
                # a worker that dies at once breaks the pool while the tasks are still being submitted
                started = [self.executor.submit(os.getpid) for _ in range(jobs)]
                done, _ = wait(started, timeout=WARM_TIMEOUT_S + 60, return_when=FIRST_COMPLETED)
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
        initargs=(os.getpid(), tied, initargs, spc_columns()),  # --spc-columns reaches spawned workers
    )


#: how often a worker checks that the process that started it is alive (seconds)
PARENT_POLL_S = 0.5


def _init_guarded_worker(parent_pid: int, tied: bool, initargs: tuple, columns: bool = False) -> None:
    _watch_parent(parent_pid, tied)
    use_spc_columns(columns)  # the worker reads section rows as its parent does (--spc-columns)
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
        from spctool.batch.scheduler import CONNECT_TIMEOUT_S

        # run_batch checked that a Dask scheduler answers there (check_scheduler): this connection only
        # waits longer than that check for a scheduler that is busy registering
        try:
            client = Client(str(scheduler), timeout=f"{max(CONNECT_TIMEOUT_S, 30.0)}s", set_as_default=False)
        except Exception as exc:  # noqa: BLE001 - any refusal (TLS, handshake, timeout) is one line
            raise SpcUsageError(
                f"cannot connect to the Dask scheduler {scheduler}: {type(exc).__name__}: {_one_line(exc)}"
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

