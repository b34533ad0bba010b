"""Thin click commands: read inputs, call one stage, write artifacts.

Importing the command line sets ``OPENBLAS_NUM_THREADS=1`` unless the environment already sets it (before
numpy loads OpenBLAS; the CLI imports numpy only inside a command): spctool parallelises over landmarks,
pictures and samples itself (numba kernels, worker processes), and its NumPy/SciPy linear algebra is on
matrices of a few rows, so OpenBLAS's thread pool had no work to share — its threads only spun after
start-up and after each call, about 0.3 s of CPU in every cold command (``spctool register`` of 16
landmarks: 1.82 → 1.50 s CPU, ``farm-bench -n 8``) and, in ``montecarlo -j 2``, CPU taken from the other
worker.  Worker processes inherit the setting; set the variable to use more BLAS threads.

It also keeps numba from loading cffi, which spctool never uses: numba's typing imports ``cffi`` when it
is installed and builds a C parser (pycparser's lexer tables) at once, 0.06-0.24 s of every command's
start on this machine.  ``SPCTOOL_CFFI=1`` leaves it importable (a plugin of your own that needs it).

And it spares numba's first kernel its BLAS probe: when ``numba.np.arraymath`` loads (at the first
kernel a process compiles or loads from the cache) it imports ``scipy.linalg`` only to know whether
``np.correlate``/``np.convolve`` inside kernels may call BLAS; spctool's kernels use neither, and that
import (scipy.linalg, scipy's array-API layer, numpy.f2py) was 0.3-0.4 s of every command that runs a
kernel.  The probe answers "no BLAS" (those two functions would use numba's own loop, same results);
``SPCTOOL_BLAS_PROBE=1`` runs numba's probe.
"""

import importlib.abc
import importlib.machinery
import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
if os.environ.get("SPCTOOL_CFFI") != "1" and "cffi" not in sys.modules:
    sys.modules["cffi"] = None  # `import cffi` raises ImportError: numba's cffi support stays off


class _SkipBlasProbe(importlib.abc.MetaPathFinder):
    """Loads ``numba.np.arraymath`` with numba's BLAS probe answering "no BLAS" (no scipy.linalg import);
    removes itself at once."""

    def find_spec(self, name, path, target=None):
        if name != "numba.np.arraymath":
            return None
        if self in sys.meta_path:
            sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        if spec is None or not hasattr(spec.loader, "exec_module"):
            return spec
        real_exec = spec.loader.exec_module

        def exec_module(module):
            import numba.np.linalg as linalg

            probe = getattr(linalg, "ensure_blas", None)
            if probe is None:  # another numba: its own import, untouched
                real_exec(module)
                return

            def no_probe():
                raise ImportError("numba's BLAS probe skipped by spctool (SPCTOOL_BLAS_PROBE=1 runs it)")

            linalg.ensure_blas = no_probe
            try:
                real_exec(module)
            finally:
                linalg.ensure_blas = probe
                if getattr(module, "ensure_blas", None) is no_probe:
                    module.ensure_blas = probe

        spec.loader.exec_module = exec_module
        return spec


if os.environ.get("SPCTOOL_BLAS_PROBE") != "1" and "numba.np.arraymath" not in sys.modules:
    sys.meta_path.insert(0, _SkipBlasProbe())
