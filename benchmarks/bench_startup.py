"""How fast every command starts (issue 42): one picture per command in a new process, beside the
same command run again inside one process (its work without the start-up).

The working directory is bench_register's 16-landmark world (a q = 64 ICQ shape, 16 maplets of
99×99, 1024² pictures; built once by ``spctool simulate`` and kept in the temporary folder).  Each
``cold`` figure is the best wall (and CPU) time of three new ``spctool`` processes after one that warms the
caches (numba's kernels, the shape's diameter: what a second command after ``spctool warmup`` finds);
``in-process`` is the best of three runs of the same command line through ``cli.main`` in this
process after one warm-up run (one numba thread: bench_register's setting).  Targets (the issue's,
on wall time): one picture costs at most 1.0 s wall in maplet space and 1.2 s in image space
(``register``, ``navigate``, ``lithos-select``).

What the CPU lines measure: the user + system seconds of the whole command, its threads and every
process it forked and waited for (maplet space forks a worker for 16 maplets of 99×99) — what the
command costs the machine, the figure a shared machine disturbs least.  It is not the wall time: with
work split over two cores it is larger than the wall by design (in-process, the work alone, it is the
calling process's time only, its threads included, its forked worker not).  So the CPU lines carry
no pass/fail: only the wall lines are held to the targets.

    python benchmarks/run.py startup
"""

from __future__ import annotations

import importlib.util
import os
import time
from pathlib import Path

_HERE = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("_bench_register_world", _HERE / "bench_register.py")
_br = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_br)

_WARMED: dict = {}


def _args(command: str, space: str | None) -> list[str]:
    root = str(_br._world16())
    args = ["-q", "-C", root, command, _br.PICTURE16, "-o", os.devnull]
    return args + (["--space", space] if space else [])


def _child_cpu() -> float:
    import resource

    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


_COLD: dict = {}


def _cold(command: str, space: str | None) -> tuple[float, float]:
    """(best wall s, best CPU s) of three new processes (after one that warms the caches); CPU is the
    user + system time of the process and of every child it waited for (its forked worker)."""
    key = (command, space)
    if key in _COLD:
        return _COLD[key]
    if not _WARMED.get("warmup"):
        _br._spctool("-q", "warmup")
        _WARMED["warmup"] = True
    args = _args(command, space)
    _br._spctool(*args)
    wall = cpu = float("inf")
    for _ in range(3):
        t, c = time.perf_counter(), _child_cpu()
        _br._spctool(*args)
        wall, cpu = min(wall, time.perf_counter() - t), min(cpu, _child_cpu() - c)
    _COLD[key] = (wall, cpu)
    return _COLD[key]


_WARM: dict = {}


def _in_process(command: str, space: str | None) -> tuple[float, float]:
    """(best wall s, best CPU s) of the same command line run inside this process (after one warm-up
    run)."""
    key = (command, space)
    if key in _WARM:
        return _WARM[key]
    from spctool.cli.main import cli

    args = _args(command, space)

    def once():
        try:
            cli.main(args=list(args), prog_name="spctool", standalone_mode=False)
        except SystemExit as exc:  # a command's exit code 0
            if exc.code not in (0, None):
                raise

    once()
    wall = cpu = float("inf")
    for _ in range(3):
        t, c = time.perf_counter(), time.process_time()
        once()
        wall, cpu = min(wall, time.perf_counter() - t), min(cpu, time.process_time() - c)
    _WARM[key] = (wall, cpu)
    return _WARM[key]


def _line(command, space, kind, which, limit=None):
    def fn():
        wall, cpu = _cold(command, space) if kind == "cold" else _in_process(command, space)
        t = wall if which == "wall" else cpu
        return t, "s", True if limit is None else t <= limit

    return fn


BENCHMARKS = []
for _command, _space, _limit in (
    ("register", "maplet", 1.0),
    ("register", "image", 1.2),
    ("navigate", "maplet", 1.0),
    ("navigate", "image", 1.2),
    ("lithos-select", None, 1.0),
):
    _label = f"startup {_command}" + (f", {_space} space" if _space else "")
    BENCHMARKS += [
        (f"{_label}: cold process, wall", f"<= {_limit} s", _line(_command, _space, "cold", "wall", _limit)),
        (f"{_label}: cold process, CPU", "(all its processes)", _line(_command, _space, "cold", "cpu")),
        (f"{_label}: in-process, wall", "(the work alone)", _line(_command, _space, "warm", "wall")),
        (f"{_label}: in-process, CPU", "(the work alone)", _line(_command, _space, "warm", "cpu")),
    ]
