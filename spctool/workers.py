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

__all__ = ["ForkedPool", "can_fork_tasks", "children_cpu", "forked_map", "shares", "start_method"]


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
    from it (:func:`can_fork_tasks` must hold): a :class:`ForkedPool` used for one call and closed.

    ``on_result(i, value)`` is called in this process as each result arrives here (progress).  The list
    is in index order whatever process computed what, so a deterministic ``task`` gives the same list
    for any ``workers``.  A task that raises in a child, or a child that dies, leaves its index to this
    process, which runs it again at the end (an error is then raised here, with its own traceback).
    The children are not waited for: a child closes its pipe before it exits, so this process does not
    wait for the kernel to tear down the child's copy of its memory (~3 ms); it is reaped by the next
    call (or by the interpreter's exit).  :func:`children_cpu` counts the children's CPU as they
    reported it.
    """
    pool = ForkedPool(workers)
    pool._one_call = True  # its children exit after their last result: their teardown overlaps this call
    try:
        return pool.map(task, n, on_result)
    finally:
        pool.close()


class ForkedPool:
    """Worker processes forked from this one at its first :meth:`map` and given the tasks of every later
    call too (one command's several passes over the same landmarks: ``spctool navigate``).

    ``workers − 1`` children are forked at the first :meth:`map` (:func:`can_fork_tasks` must hold
    then) and keep a copy of this process's memory as it was at that moment: the objects named in
    ``shared`` are what later calls may rely on there (:attr:`shared` is that copy in a child); they
    must not be modified while the pool lives.  A later call gives its children ``job = (build, args)``,
    pickled to them: each child makes its task as ``build(shared, *args)``.  Forking once saves each
    later call the fork (~3 ms here) and the copy-on-write faults of both processes' first task
    (~1300 pages each: the pages every process writes after a fork are copied on first write, then
    stay private).

    Each process claims the next index from a counter in shared memory (one task at a time: tasks of
    unequal cost stay balanced) and runs it on its own memory; a child sends each result back through
    a pipe (pickled, so results must be picklable).  Children end with ``os._exit`` (no atexit
    handlers, no buffered output flushed twice) when :meth:`close` (or the interpreter's exit) closes
    their job pipes; an exception here (^C) kills them.  A child that dies is dropped, its tasks run
    here.
    """

    def __init__(self, workers: int, shared=None):
        self.workers = max(1, int(workers))
        self.shared = shared
        self._children: dict = {}  # pid → [job pipe's write end, result pipe's read end, CPU reported]
        self._counter = None  # mmap: the next index to claim
        self._mutex = None  # (r, w): a one-byte token in this pipe is the counter's lock
        self._forked = False
        self._closed = False
        self._one_call = False  # children exit after the first call's tasks (:func:`forked_map`)

    @property
    def alive(self) -> bool:
        """Whether this pool's children were forked and still serve (a later call needs no fork)."""
        return self._forked and not self._closed and bool(self._children)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _claim(self) -> int:
        import struct

        r, w = self._mutex
        os.read(r, 1)
        try:
            i = struct.unpack_from("<q", self._counter, 0)[0]
            struct.pack_into("<q", self._counter, 0, i + 1)
        finally:
            os.write(w, b"\0")
        return i

    def _fork(self, task, n: int) -> None:
        import mmap
        import signal

        self._forked = True
        self._counter = mmap.mmap(-1, 8)  # shared (MAP_SHARED | MAP_ANONYMOUS)
        self._mutex = os.pipe()
        os.write(self._mutex[1], b"\0")
        if not _ATEXIT:  # open pools closed, the last children reaped, before the interpreter exits
            import atexit

            atexit.register(_at_exit)
            _ATEXIT.append(True)
        _POOLS.append(self)
        for _ in range(max(0, min(self.workers, n) - 1)):
            jr, jw = os.pipe()
            rr, rw = os.pipe()
            try:  # room for a few results: a child rarely waits for this process to read
                import fcntl

                fcntl.fcntl(rw, fcntl.F_SETPIPE_SZ, 1 << 20)
            except (ImportError, AttributeError, OSError):
                pass
            pid = os.fork()
            if pid == 0:  # the child: serves jobs until its job pipe closes, then exits without returning
                code = 1
                try:
                    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
                        signal.signal(signal.SIGINT, signal.SIG_DFL)  # ^C ends a child at once, silently
                    os.close(jw)
                    os.close(rr)
                    for other in self._children.values():  # an earlier child's pipes: its EOF is not ours
                        os.close(other[0])
                        os.close(other[1])
                    for pool in _POOLS:
                        if pool is not self:
                            pool._abandon()
                    self._serve(task, n, jr, rw)
                    code = 0
                finally:
                    os._exit(code)
            os.close(jr)
            os.close(rw)
            self._children[pid] = [jw, rr, 0.0]

    def _abandon(self) -> None:
        """In a child: this other pool's pipes are its parent's, not ours (closed, children forgotten)."""
        for jw, rr, _ in self._children.values():
            for fd in (jw, rr):
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._children = {}
        self._closed = True

    def _serve(self, task, n: int, jr: int, rw: int) -> None:
        """A child's life: the first job's tasks (``task`` inherited), then each job read from ``jr``."""
        import pickle
        import resource
        import struct

        while True:
            while True:
                i = self._claim()
                if i >= n:
                    break
                frame = pickle.dumps((i, task(i)), protocol=pickle.HIGHEST_PROTOCOL)
                _write_all(rw, struct.pack("<Q", len(frame)) + frame)
            use = resource.getrusage(resource.RUSAGE_SELF)
            frame = pickle.dumps((-1, use.ru_utime + use.ru_stime))  # the job's end: this child's CPU
            _write_all(rw, struct.pack("<Q", len(frame)) + frame)
            head = None if self._one_call else _read_exactly(jr, 8)
            if head is None:  # the pool was closed (or serves one call)
                os.close(rw)  # EOF now, not after the kernel has torn down this process
                return
            build, args, n = pickle.loads(_read_exactly(jr, struct.unpack("<Q", head)[0]))
            task = build(self.shared, *args)

    def map(self, task, n: int, on_result=None, job=None) -> list:
        """``[task(i) for i in range(n)]`` over this process and the pool's children (as
        :func:`forked_map`).  The first call forks them (``task`` is theirs then); a later call sends its
        children ``job = (build, args)`` (:class:`ForkedPool`), or without one runs every task here."""
        import pickle
        import select
        import struct

        if self._closed:
            raise RuntimeError("this ForkedPool is closed")
        _reap(block=False)
        results: list = [None] * n
        done = [False] * n

        def deliver(i, value):
            results[i], done[i] = value, True
            if on_result is not None:
                on_result(i, value)

        if not self._forked and n < 2:  # nothing to share: no fork (yet)
            for i in range(n):
                deliver(i, task(i))
            return results
        sent = not self._forked  # the children take part: forked now, or sent this call's job
        try:
            if not self._forked:
                self._fork(task, n)
            else:
                struct.pack_into("<q", self._counter, 0, 0)  # every child is idle: its last job ended
                frame = None
                if job is not None and self._children:
                    build, args = job
                    try:
                        frame = pickle.dumps((build, args, n), protocol=pickle.HIGHEST_PROTOCOL)
                    except (pickle.PicklingError, TypeError, AttributeError):  # not picklable: all here
                        frame = None
                if frame is not None:
                    for pid, child in list(self._children.items()):
                        try:
                            _write_all(child[0], struct.pack("<Q", len(frame)) + frame)
                        except OSError:  # it died: dropped, its tasks claimed by the others
                            self._drop(pid)
                    sent = True
            serving = {child[1]: pid for pid, child in self._children.items()} if sent else {}
            buffers = {r: bytearray() for r in serving}

            def drain(timeout):
                """Read what the children sent (``timeout`` 0: what is there now; None: until one sends
                or ends), delivering complete results; a child's end-of-job frame or EOF ends it."""
                while serving:
                    ready, _, _ = select.select(list(serving), [], [], timeout)
                    if not ready:
                        return
                    for fd in ready:
                        chunk = os.read(fd, 1 << 20)
                        if not chunk:  # it died
                            self._drop(serving.pop(fd))
                            continue
                        buf = buffers[fd]
                        buf += chunk
                        while len(buf) >= 8 and fd in serving:
                            size = struct.unpack_from("<Q", buf, 0)[0]
                            if len(buf) < 8 + size:
                                break
                            i, value = pickle.loads(bytes(buf[8 : 8 + size]))
                            del buf[: 8 + size]
                            if i >= 0:
                                deliver(i, value)
                                continue
                            child = self._children[serving.pop(fd)]
                            _CHILD_CPU[0] += value - child[2]
                            child[2] = value
                    if timeout is None:
                        return

            while True:
                i = self._claim()
                if i >= n:
                    break
                deliver(i, task(i))
                drain(0)
            while serving:
                drain(None)
        except BaseException:
            self._kill()
            raise
        for i in range(n):  # a child that failed or died: its task again, here
            if not done[i]:
                deliver(i, task(i))
        return results

    def _drop(self, pid) -> None:
        """Forget a child that died (reaped later)."""
        child = self._children.pop(pid, None)
        if child is not None:
            for fd in child[:2]:
                try:
                    os.close(fd)
                except OSError:
                    pass
            _UNREAPED.append(pid)

    def _kill(self) -> None:
        import signal

        for pid in self._children:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        self.close()
        _reap(block=True)

    def close(self) -> None:
        """End the children (their job pipes closed: each exits at once) without waiting for them: they
        are reaped by a later call or at the interpreter's exit."""
        if self._closed:
            return
        self._closed = True
        for pid in list(self._children):
            self._drop(pid)
        if self._mutex is not None:
            for fd in self._mutex:
                os.close(fd)
            self._counter.close()
            self._mutex = self._counter = None
        if self in _POOLS:
            _POOLS.remove(self)
        _reap(block=False)

    def __del__(self):
        try:
            self.close()
        except Exception:  # pragma: no cover - interpreter teardown
            pass


def shares(pool, *objects) -> bool:
    """Whether ``pool`` (a :class:`ForkedPool`, or None) can serve a call on ``objects``: alive (or not
    yet forked) and holding these very objects in :attr:`ForkedPool.shared` (compared by identity,
    element by element for lists and tuples)."""
    if pool is None or pool._closed or pool.shared is None or len(pool.shared) != len(objects):
        return False
    for held, given in zip(pool.shared, objects):
        if isinstance(held, (list, tuple)):
            if not isinstance(given, (list, tuple)) or len(held) != len(given):
                return False
            if any(a is not b for a, b in zip(held, given)):
                return False
        elif held is not given:
            return False
    return True


_CHILD_CPU = [0.0]
_ATEXIT: list = []
#: pools with children (closed at the interpreter's exit before the children are reaped)
_POOLS: list = []
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


def _at_exit() -> None:
    for pool in list(_POOLS):
        pool.close()
    _reap(block=True)


def _read_exactly(fd: int, size: int) -> bytes | None:
    """``size`` bytes from ``fd`` (None: end of file first)."""
    out = bytearray()
    while len(out) < size:
        chunk = os.read(fd, size - len(out))
        if not chunk:
            return None
        out += chunk
    return bytes(out)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]
