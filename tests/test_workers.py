"""spctool.workers.forked_map: tasks of one call shared by this process and forked children."""

from __future__ import annotations

import os
import sys
import time

import pytest

from spctool import workers

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forks on Linux only")


def _slow_pid(i):
    time.sleep(0.01)  # long enough that the child claims some of the tasks
    return (i, i * i, os.getpid())


def test_forked_map_returns_every_result_in_order_from_several_processes():
    seen = []
    out = workers.forked_map(_slow_pid, 12, 2, on_result=lambda i, v: seen.append(i))
    assert [(i, sq) for i, sq, _ in out] == [(i, i * i) for i in range(12)]
    assert sorted(seen) == list(range(12))  # each result reported once, in this process
    pids = {pid for _, _, pid in out}
    assert os.getpid() in pids and len(pids) == 2  # this process and one child shared the work
    assert workers.forked_map(_slow_pid, 0, 2) == []


def test_forked_map_runs_a_failed_or_lost_task_again_here():
    """A task that raises in a child, or whose child dies, is run again by this process: its exception
    is raised here; a task that succeeds here gives its value."""
    parent = os.getpid()

    def dies_in_child(i):
        time.sleep(0.01)
        if os.getpid() != parent:
            os._exit(3)  # the child dies without a word
        return i

    out = workers.forked_map(dies_in_child, 6, 2)
    assert out == list(range(6))

    def raises(i):
        time.sleep(0.01)
        if i == 5:
            raise ValueError(f"task {i} fails in process {os.getpid()}")
        return i

    with pytest.raises(ValueError, match=f"task 5 fails in process {parent}"):
        workers.forked_map(raises, 8, 2)


def test_can_fork_tasks_only_with_one_thread(monkeypatch):
    monkeypatch.delenv("SPCTOOL_START_METHOD", raising=False)
    monkeypatch.setattr(workers.threading, "active_count", lambda: 1)
    assert workers.can_fork_tasks()
    monkeypatch.setattr(workers.threading, "active_count", lambda: 2)
    assert not workers.can_fork_tasks()  # another thread alive (a progress bar's): never fork
    monkeypatch.setattr(workers.threading, "active_count", lambda: 1)
    for method, ok in (("spawn", False), ("forkserver", False), ("fork", True)):
        monkeypatch.setenv("SPCTOOL_START_METHOD", method)
        assert workers.can_fork_tasks() is ok


def _big(i):
    time.sleep(0.01)
    return bytes([i]) * (3 << 20)  # larger than a pipe's buffer: read in several pieces


def test_forked_map_large_results():
    out = workers.forked_map(_big, 4, 2)
    assert [len(v) for v in out] == [3 << 20] * 4 and [v[-1] for v in out] == [0, 1, 2, 3]


def _busy(i):
    end = time.thread_time() + 0.01
    while time.thread_time() < end:
        pass
    return i


def test_forked_map_children_are_reaped_and_counted():
    """A child closes its pipe before it exits: the call does not wait for its teardown, the next call
    (or the interpreter's exit) reaps it; its CPU, as it reported it, is counted."""
    before = workers.children_cpu()
    workers.forked_map(_busy, 6, 2)
    workers.forked_map(_busy, 6, 2)  # reaps the first call's child, if it had not exited then
    assert len(workers._UNREAPED) <= 1
    workers._reap(block=True)
    assert workers._UNREAPED == []
    assert workers.children_cpu() > before


def _pid_of(shared, offset):
    """A later job's task in a ForkedPool's child: what the child holds of ``shared`` (a copy made at
    the fork), the index plus ``offset``, and the process."""
    def task(i):
        time.sleep(0.01)
        return shared[0]["tag"], i + offset, os.getpid()

    return task


def test_forked_pool_forks_once_and_serves_later_calls_from_their_job():
    """A ForkedPool forks at its first map; later maps send their children the job, which makes the task
    there from the objects held since the fork (a change made here since then is not seen there: the
    shared objects must not change while the pool lives); results in index order, each once."""
    real_fork, forks = os.fork, []

    def counting_fork():
        pid = real_fork()
        if pid:
            forks.append(pid)
        return pid

    state = {"tag": "at-fork"}
    os.fork = counting_fork
    try:
        with workers.ForkedPool(2, shared=(state,)) as pool:
            first = pool.map(_slow_pid, 8)
            assert pool.alive and len(forks) == 1
            state["tag"] = "changed-here"
            seen = []
            for offset in (100, 200):
                here = _pid_of((state,), offset)
                out = pool.map(here, 10, on_result=lambda i, v: seen.append(i), job=(_pid_of, (offset,)))
                assert [v[1] for v in out] == [i + offset for i in range(10)]
                tags = {v[0] for v in out if v[2] != os.getpid()}
                assert tags == {"at-fork"}  # the child's copy, as it was at the fork
                assert len({v[2] for v in out}) == 2
            assert sorted(seen) == sorted(list(range(10)) * 2)
            assert {v[2] for v in pool.map(_slow_pid, 6)} == {os.getpid()}  # no job: every task here
            unpicklable = (lambda shared: _slow_pid, ())  # a lambda: not sent, every task here
            assert {v[2] for v in pool.map(_slow_pid, 4, job=unpicklable)} == {os.getpid()} and pool.alive
            assert len(forks) == 1
        assert not pool.alive
        assert [v[:2] for v in first] == [(i, i * i) for i in range(8)]
        with pytest.raises(RuntimeError, match="closed"):
            pool.map(_slow_pid, 2)
    finally:
        os.fork = real_fork
    workers._reap(block=True)
    assert workers._UNREAPED == []


def _dies(shared):
    def task(i):
        time.sleep(0.01)
        os._exit(5)

    return task


def test_forked_pool_a_child_that_dies_leaves_its_tasks_here():
    with workers.ForkedPool(2, shared=()) as pool:
        pool.map(_slow_pid, 4)
        out = pool.map(lambda i: time.sleep(0.01) or i * 3, 6, job=(_dies, ()))
        assert out == [i * 3 for i in range(6)] and not pool.alive
        assert pool.map(lambda i: -i, 3, job=(_dies, ())) == [0, -1, -2]  # no child left: all here
    workers._reap(block=True)


def test_shares_compares_by_identity():
    a, b = object(), object()
    pool = workers.ForkedPool(2, shared=(a, [a, b]))
    assert workers.shares(pool, a, [a, b]) and workers.shares(pool, a, (a, b))  # a list: its elements
    assert not workers.shares(pool, b, [a, b]) and not workers.shares(pool, a, [a, object()])
    assert not workers.shares(pool, a, [a]) and not workers.shares(None, a, [a, b])
    pool.close()
    assert not workers.shares(pool, a, [a, b])
