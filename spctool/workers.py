"""Local worker processes: how they start (shared by :mod:`spctool.batch` and
:mod:`spctool.sim.montecarlo`).

A forked worker starts in a few milliseconds with everything its parent loaded; a spawned one imports
spctool and loads its kernels again (about a second).  Forking is not always safe, so the choice is
made here once, by one rule, for every command that starts workers.
"""

from __future__ import annotations

import os
import sys
import threading

from spctool.errors import SpcUsageError

__all__ = ["start_method"]


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
