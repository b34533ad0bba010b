"""Thin click commands: read inputs, call one stage, write artifacts.

Importing the command line sets ``OPENBLAS_NUM_THREADS=1`` unless the environment already sets it (before
numpy loads OpenBLAS; the CLI imports numpy only inside a command): spctool parallelises over landmarks,
pictures and samples itself (numba kernels, worker processes), and its NumPy/SciPy linear algebra is on
matrices of a few rows, so OpenBLAS's thread pool had no work to share — its threads only spun after
start-up and after each call, about 0.3 s of CPU in every cold command (``spctool register`` of 16
landmarks: 1.82 → 1.50 s CPU, 8 A/B pairs) and, in ``montecarlo -j 2``, CPU taken from the other
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

It loads a cached kernel without numba's full registry refresh: numba's ``Cache.load_overload`` first
installs the typing and lowering registries of all of numba (imports of numba.np, numba.typed,
numba.experimental ..., ~0.22 s of CPU at the first kernel of every process, forked workers that load
a kernel of their own included), which only compiling needs — numba's compiler refreshes them itself
before it compiles.  A cached kernel is machine code linked against numba's runtime (NRT), so the
runtime is initialised and the kernel loaded; should the load fail, numba's own path (refresh, then
load) runs.  ``SPCTOOL_NUMBA_REFRESH=1`` keeps numba's refresh.  And while numba itself is imported it
finds neither SciPy (imported only to check its version, ~0.01-0.03 s) nor PyYAML (for a
``.numba_config.yaml``, ~0.015 s; left visible when the current folder has one): both import as usual
afterwards.  Nor does numba look for third-party extensions (``numba_extensions`` entry points: its
``importlib.metadata`` import, loaded lazily instead, and a scan of every installed distribution's
metadata at the first kernel, ~0.025 s); spctool's kernels use none.  ``SPCTOOL_NUMBA_EXTENSIONS=1``
loads them as numba does.  The garbage collector pauses during numba's import (whose objects all
live as long as the process) and then sets them, and everything imported before, aside for good
(``gc.freeze``): collections during a command's start cost 0.04-0.07 s of CPU, most of it visiting
those objects again.
"""

import gc
import importlib.abc
import importlib.machinery
import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
if os.environ.get("SPCTOOL_CFFI") != "1" and "cffi" not in sys.modules:
    sys.modules["cffi"] = None  # `import cffi` raises ImportError: numba's cffi support stays off


class _NumbaStartHooks(importlib.abc.MetaPathFinder):
    """Wraps the loading of three numba modules (each once; removes itself after the last): ``numba``
    (SciPy and PyYAML hidden while it executes), ``numba.core.caching`` (the light cache load) and
    ``numba.np.arraymath`` (the BLAS probe answering "no BLAS", no scipy.linalg import)."""

    def __init__(self, names):
        self.pending = set(names)

    def find_spec(self, name, path, target=None):
        if name not in self.pending:
            return None
        self.pending.discard(name)
        if not self.pending and self in sys.meta_path:
            sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        if spec is None or not hasattr(spec.loader, "exec_module"):
            return spec
        real_exec = spec.loader.exec_module
        wrap = {
            "numba": _exec_numba,
            "numba.core.caching": _exec_caching,
            "numba.np.arraymath": _exec_arraymath,
        }
        spec.loader.exec_module = lambda module: wrap[name](real_exec, module)
        return spec


def _exec_numba(real_exec, module):
    hidden = [n for n in ("scipy", "yaml") if n not in sys.modules]
    if "yaml" in hidden and os.path.exists(".numba_config.yaml"):  # numba reads it from here: keep yaml
        hidden.remove("yaml")
    extensions = os.environ.get("SPCTOOL_NUMBA_EXTENSIONS") == "1"
    if not extensions:
        _lazy_module("importlib.metadata")
    for n in hidden:
        sys.modules[n] = None  # `import n` raises ImportError inside numba's own import only
    collecting = gc.isenabled()
    gc.disable()  # numba's import makes ~50,000 long-lived objects and no garbage worth a collection
    try:
        real_exec(module)
    finally:
        for n in hidden:
            if n in sys.modules and sys.modules[n] is None:
                del sys.modules[n]
        if collecting:
            gc.freeze()  # what exists now lives as long as the process: later collections skip it
            gc.enable()
    entrypoints = sys.modules.get("numba.core.entrypoints")
    if not extensions and hasattr(entrypoints, "_already_initialized"):
        entrypoints._already_initialized = True  # no numba_extensions scan at the first kernel


def _lazy_module(name):
    """Put a lazily executed ``name`` in sys.modules (executed at its first attribute access)."""
    import importlib.util

    if name in sys.modules:
        return
    try:
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            return
        spec.loader = importlib.util.LazyLoader(spec.loader)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        parent, _, child = name.rpartition(".")
        if parent in sys.modules:
            setattr(sys.modules[parent], child, module)
    except Exception:  # left to the ordinary import
        sys.modules.pop(name, None)


def _exec_caching(real_exec, module):
    real_exec(module)
    cache = getattr(module, "Cache", None)
    real_load = getattr(cache, "load_overload", None)
    if real_load is None or not all(
        hasattr(cache, a) for a in ("_load_overload", "_guard_against_spurious_io_errors")
    ):  # another numba: its own loading, untouched
        return

    def load_overload(self, sig, target_context):
        """numba's ``Cache.load_overload`` without the registry refresh (see spctool.cli)."""
        try:
            from numba.core.runtime import rtsys

            rtsys.initialize(target_context)  # what a cached kernel links against
            with self._guard_against_spurious_io_errors():
                loaded = self._load_overload(sig, target_context)
            if loaded is not None:
                return loaded
        except Exception:  # numba's own path below: refresh, then load (or compile)
            pass
        return real_load(self, sig, target_context)

    load_overload.__wrapped__ = real_load
    cache.load_overload = load_overload
    _light_environments()


def _light_environments():
    """A cached kernel's environments rebuilt without importing numba's own modules they name.

    Each function in a cached kernel keeps an ``Environment`` (globals and constants for the few
    operations that need Python objects); unpickling one imports the module it names to take its
    globals.  For numba's array constructors that is ``numba.np.arrayobj``, whose import (with
    ``numba.cpython.unicode``, ``charseq``, ``hashing``) was 0.04-0.07 s of CPU at the first kernel of
    every command.  Compiled nopython code reads only an environment's constants; its globals are read
    by object mode alone, which spctool's kernels never use.  So an environment of a numba module not
    yet imported gets a globals dict holding the module's name only (what numba checks and pickles
    again); any other, and everything when ``SPCTOOL_NUMBA_REFRESH=1``, numba's own rebuild.
    """
    import numba.core.environment as environment

    real = getattr(environment, "_rebuild_env", None)
    env_class = getattr(environment, "Environment", None)
    if real is None or env_class is None or not hasattr(env_class, "_memo"):
        return  # another numba: its own rebuild, untouched

    def _rebuild_env(modname, consts, env_name):
        if not (isinstance(modname, str) and modname.startswith("numba.")) or modname in sys.modules:
            return real(modname, consts, env_name)
        env = environment.lookup_environment(env_name)
        if env is not None:
            return env
        env = env_class({"__name__": modname})
        env.consts[:] = consts
        env.env_name = env_name
        env_class._memo[env_name] = env
        return env

    _rebuild_env.__wrapped__ = real
    environment._rebuild_env = _rebuild_env


def _exec_arraymath(real_exec, module):
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


_hooked = [
    name
    for name, off in (
        ("numba", "numba" in sys.modules),
        ("numba.core.caching", os.environ.get("SPCTOOL_NUMBA_REFRESH") == "1"),
        ("numba.np.arraymath", os.environ.get("SPCTOOL_BLAS_PROBE") == "1"),
    )
    if not off and name not in sys.modules
]
if _hooked:
    sys.meta_path.insert(0, _NumbaStartHooks(_hooked))
