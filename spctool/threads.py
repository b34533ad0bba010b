"""numba's thread count without starting its thread pool (issue 42: every command starts fast).

``numba.get_num_threads()`` first launches numba's threading layer (loads the OpenMP/TBB/workqueue
library and sets up its pool, ~0.01 s of CPU in a cold process) even when the caller only wants the
number to decide whether to split small work at all: register's landmark workers and the renderer's
window split ask it in every command, and neither runs a ``prange`` kernel.  Until the pool is launched
no one can have changed the count (``numba.set_num_threads`` launches it first), so the count is then
numba's configured default, ``NUMBA_NUM_THREADS``; once launched, numba's own (thread-local) answer.
"""

from __future__ import annotations


def numba_threads() -> int:
    """What ``numba.get_num_threads()`` returns, without launching numba's thread pool to say it."""
    import numba
    from numba.np.ufunc import parallel

    if not getattr(parallel, "_is_initialized", True):
        return int(numba.config.NUMBA_NUM_THREADS)
    return int(numba.get_num_threads())
