"""Local worker processes: how they start (shared by :mod:`spctool.batch` and
:mod:`spctool.sim.montecarlo`), and the tasks of one call shared with forked children
(:func:`forked_map`: :func:`spctool.stages.register.register`'s maplet-space landmarks).

A forked worker starts in a few milliseconds with everything its parent loaded; a spawned one imports
spctool and loads its kernels again (about a second).  Forking is not always safe, so the choice is
made here once, by one rule, for every command that starts workers.
"""

from __future__ import annotations

import os
import sys
import threading

from spctool.errors import SpcUsageError

__all__ = ["can_fork_tasks", "children_cpu", "forked_map", "start_method"]


def start_method() -> str:
    """How local worker processes start (``spctool batch``'s pool, the Monte Carlo's workers): ``fork``
    where that is safe, else ``spawn``.

    A forked worker inherits this process's imports (numpy, scipy, numba, spctool: ~0.5 s a spawned
    worker spends before its first picture) and any shared data already loaded.  Fork is safe here
    only on Linux (macOS system libraries are not fork-safe), while this process runs a single thread
    (a lock held by another thread — a progress bar writing to stderr — would stay locked in the
    child) and before numba's threading layer has started (GNU OpenMP, numba's default on Linux,
    aborts a forked child that runs a parallel kernel).  ``SPCTOOL_START_METHOD=spawn|fork|forkserver``
    overrides the choice.
    """
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


# --------------------------------------------------------------------------------------------------
# tasks of one call shared with forked children (maplet-space registration over landmarks)


def can_fork_tasks() -> bool:
    """Whether :func:`forked_map` may fork: on Linux, while this process runs a single Python thread
    (a lock another thread holds — a progress bar's refresh thread writing to stderr — would stay
    locked in the child), unless ``SPCTOOL_START_METHOD`` asks for ``spawn`` or ``forkserver``.

    Unlike :func:`start_method`, numba's threading layer may have started here: the children of
    :func:`forked_map` run only the tasks they are given, which must call no parallel (``prange``)
    kernel (GNU OpenMP aborts a forked child that runs one; its threads in this process are not
    Python threads and are not inherited)."""
    forced = os.environ.get("SPCTOOL_START_METHOD", "").strip().lower()
    if forced in ("spawn", "forkserver"):
        return False
    return sys.platform.startswith("linux") and hasattr(os, "fork") and threading.active_count() == 1


def forked_map(task, n: int, workers: int, on_result=None) -> list:
    """``[task(i) for i in range(n)]``, computed by this process and ``workers − 1`` children forked
    from it (:func:`can_fork_tasks` must hold).

    Each process claims the next index from a counter in shared memory (one task at a time: tasks of
    unequal cost stay balanced) and runs ``task(i)`` on its own copy of this process's memory; a child
    sends each result back through a pipe (pickled), so results must be picklable.  ``on_result(i,
    value)`` is called in this process as each result arrives here, own or a child's (progress).  The
    list is in index order whatever process computed what, so a deterministic ``task`` gives the same
    list for any ``workers``.  A task that raises in a child, or a child that dies, leaves its index
    to this process, which runs it again at the end (an error is then raised here, with its own
    traceback).  Children end with ``os._exit`` (no atexit handlers, no buffered output flushed twice).
    A child closes its pipe before it exits, so this process does not wait for the kernel to tear down
    the child's copy of its memory (~3 ms): a child not yet exited when this returns is reaped by the
    next call (or by the interpreter's exit); an exception here (^C) kills and reaps them first.
    :func:`children_cpu` counts the children's CPU as they reported it before exiting (their exit is not
    on this call's critical path).
    """
    import mmap
    import pickle
    import select
    import signal
    import struct

    _reap(block=False)
    results: list = [None] * n
    done = [False] * n

    def deliver(i, value):
        results[i], done[i] = value, True
        if on_result is not None:
            on_result(i, value)

    counter = mmap.mmap(-1, 8)  # shared (MAP_SHARED | MAP_ANONYMOUS): the next index to claim
    mutex_r, mutex_w = os.pipe()  # a one-byte token in this pipe is the counter's lock
    os.write(mutex_w, b"\0")

    def claim() -> int:
        os.read(mutex_r, 1)
        try:
            i = struct.unpack_from("<q", counter, 0)[0]
            struct.pack_into("<q", counter, 0, i + 1)
        finally:
            os.write(mutex_w, b"\0")
        return i

    children: dict = {}  # pid → read end of its result pipe
    try:
        for _ in range(max(0, min(int(workers), n) - 1)):
            r, w = os.pipe()
            try:  # room for a few results: a child rarely waits for this process to read
                import fcntl

                fcntl.fcntl(w, fcntl.F_SETPIPE_SZ, 1 << 20)
            except (ImportError, AttributeError, OSError):
                pass
            if not _ATEXIT:  # the last children are reaped (and counted) before the interpreter exits
                import atexit

                atexit.register(_reap, True)
                _ATEXIT.append(True)
            pid = os.fork()
            if pid == 0:  # the child: tasks until none is left, then exit without returning
                code = 1
                try:
                    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
                        signal.signal(signal.SIGINT, signal.SIG_DFL)  # ^C ends a child at once, silently
                    os.close(r)
                    for other in children.values():
                        os.close(other)
                    while True:
                        i = claim()
                        if i >= n:
                            break
                        frame = pickle.dumps((i, task(i)), protocol=pickle.HIGHEST_PROTOCOL)
                        _write_all(w, struct.pack("<Q", len(frame)) + frame)
                    import resource

                    use = resource.getrusage(resource.RUSAGE_SELF)
                    frame = pickle.dumps((-1, use.ru_utime + use.ru_stime))  # the end: this child's CPU
                    _write_all(w, struct.pack("<Q", len(frame)) + frame)
                    os.close(w)  # EOF now, not after the kernel has torn down this process
                    code = 0
                finally:
                    os._exit(code)
            os.close(w)
            children[pid] = r
        buffers = {r: bytearray() for r in children.values()}
        open_fds = set(buffers)

        def drain(timeout):
            """Read what the children sent (``timeout`` 0: what is there now; None: until one sends
            or ends), delivering complete results."""
            while open_fds:
                ready, _, _ = select.select(list(open_fds), [], [], timeout)
                if not ready:
                    return
                for fd in ready:
                    chunk = os.read(fd, 1 << 20)
                    if not chunk:
                        open_fds.discard(fd)
                        continue
                    buf = buffers[fd]
                    buf += chunk
                    while len(buf) >= 8:
                        size = struct.unpack_from("<Q", buf, 0)[0]
                        if len(buf) < 8 + size:
                            break
                        i, value = pickle.loads(bytes(buf[8 : 8 + size]))
                        del buf[: 8 + size]
                        if i < 0:
                            _CHILD_CPU[0] += value
                        else:
                            deliver(i, value)
                if timeout is None:
                    return

        while True:
            i = claim()
            if i >= n:
                break
            deliver(i, task(i))
            drain(0)
        while open_fds:
            drain(None)
    except BaseException:
        for pid in children:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        for r in children.values():
            os.close(r)
        _UNREAPED.extend(children)
        children.clear()
        _reap(block=True)
        raise
    finally:
        for r in children.values():
            os.close(r)
        _UNREAPED.extend(children)
        _reap(block=False)
        os.close(mutex_r)
        os.close(mutex_w)
        counter.close()
    for i in range(n):  # a child that failed or died: its task again, here
        if not done[i]:
            deliver(i, task(i))
    return results


_CHILD_CPU = [0.0]
_ATEXIT: list = []
#: children of earlier calls not yet reaped (exited or exiting)
_UNREAPED: list = []


def children_cpu() -> float:
    """CPU seconds (user + system) the children of every :func:`forked_map` call of this process
    reported before exiting (benchmarks: the children are not always reaped when a call returns)."""
    return _CHILD_CPU[0]


def _reap(block: bool) -> None:
    """Reap the children in :data:`_UNREAPED` that have exited (``block``: wait for all of them)."""
    for pid in list(_UNREAPED):
        try:
            done, _ = os.waitpid(pid, 0 if block else os.WNOHANG)
        except ChildProcessError:  # reaped elsewhere (a caller's os.wait())
            done = pid
        if done:
            _UNREAPED.remove(pid)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]
