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
"""

import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
if os.environ.get("SPCTOOL_CFFI") != "1" and "cffi" not in sys.modules:
    sys.modules["cffi"] = None  # `import cffi` raises ImportError: numba's cffi support stays off
