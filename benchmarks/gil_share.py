"""How much of a maplet-space S16 pass holds the GIL (issue 39): the share that bounds two threads.

    python benchmarks/gil_share.py [PASSES] [--functions N]

On bench_register's 16-landmark picture, one thread, warm: every compiled kernel of spctool is wrapped
by a timer of thread CPU, and the share of the pass spent inside kernels compiled with ``nogil=True``
is printed (the rest — Python, NumPy, the wrappers' own few microseconds a call — holds the GIL; two
threads then gain at most 1/(g + (1 − g)/2) for a GIL-held share g).  With ``--functions N`` every
spctool function is wrapped too, and the N largest own thread-CPU times are listed (a function's own
time excludes the wrapped functions and kernels it calls): where the GIL-held time is.  The wrappers
cost time of their own; compare figures of this script with each other, not with bench_register's.
"""

from __future__ import annotations

import collections
import os
import sys
import time
import types
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_register as br  # noqa: E402
from numba.core.registry import CPUDispatcher  # noqa: E402

from spctool.stages.register import RegisterOptions, register  # noqa: E402

_MODULES = (
    "spctool.stages.register", "spctool.stages.register_converge", "spctool.stages.registrar",
    "spctool.stages.extract", "spctool.stages.predict",
    "spctool.stages.correlate", "spctool.stages.alignment", "spctool.geometry.heightfield",
    "spctool.geometry._heightkernels", "spctool.geometry.camera", "spctool.geometry._camerakernels",
    "spctool.geometry.frames",
    "spctool.photometry",
)  # fmt: skip


def _wrap_all(functions: bool):
    """Wrap the kernels (and with ``functions`` the Python functions and methods) of :data:`_MODULES`
    everywhere spctool refers to them; returns (own time by name, calls by name, kind by name, stack)."""
    own, calls, kind, stack = collections.defaultdict(float), collections.Counter(), {}, []
    clock = time.thread_time

    def wrap(f, key, k):
        kind[key] = k

        def wrapper(*a, **kw):
            t0 = clock()
            stack.append(0.0)
            try:
                return f(*a, **kw)
            finally:
                inc = clock() - t0
                child = stack.pop()
                own[key] += inc - child
                calls[key] += 1
                if stack:
                    stack[-1] += inc

        return wrapper

    done = {}
    for name in _MODULES:
        mod = sys.modules[name]
        short = name.rsplit(".", 1)[-1]
        for attr, v in list(vars(mod).items()):
            if isinstance(v, CPUDispatcher):
                k = "nogil" if v.targetoptions.get("nogil") else "GIL"
            elif functions and isinstance(v, types.FunctionType) and v.__module__ == name:
                k = "py"
            else:
                continue
            if id(v) not in done:
                done[id(v)] = wrap(v, f"{short}.{attr}", k)
        if functions:
            for cname, c in list(vars(mod).items()):
                if isinstance(c, type) and c.__module__ == name:
                    for attr, v in list(vars(c).items()):
                        if isinstance(v, types.FunctionType) and not attr.startswith("__"):
                            setattr(c, attr, wrap(v, f"{short}.{cname}.{attr}", "py"))
    for name, mod in list(sys.modules.items()):  # every module's reference to a wrapped object
        if name.startswith("spctool") and mod is not None:
            for attr, v in list(vars(mod).items()):
                if id(v) in done:
                    setattr(mod, attr, done[id(v)])
    return own, calls, kind, stack


def main(argv):
    passes = int(argv[0]) if argv and argv[0].isdigit() else 7
    top = int(argv[argv.index("--functions") + 1]) if "--functions" in argv else 0
    w = br._load16()
    opts = RegisterOptions(space="maplet", threads=1)

    def run():
        photo, camera, sun, maplets, t12 = (w[k] for k in ("photo", "camera", "sun", "maplets", "thresholds"))
        return register(photo, camera, sun, maplets, t12, opts, names=w["names"])

    run(), run()
    own, calls, kind, stack = _wrap_all(functions=top > 0)
    t = time.thread_time()
    stack.append(0.0)
    for _ in range(passes):
        run()
    stack.pop()
    total = time.thread_time() - t
    free = sum(v for k, v in own.items() if kind[k] == "nogil")
    g = 1.0 - free / total
    bound = 1 / (g + (1 - g) / 2)
    print(
        f"one-thread S16 pass {total / passes * 1e3:.1f} ms (wrapped; load {os.getloadavg()[0]:.1f}): "
        f"GIL-free kernels {free / total:.1%}, GIL held {g:.1%}; two threads at most {bound:.2f}x"
    )
    for k, v in sorted(own.items(), key=lambda kv: -kv[1])[:top]:
        print(f"  {k:50s} {kind[k]:5s} calls/pass {calls[k] / passes:6.0f}  own {v / passes * 1e3:6.2f} ms")


if __name__ == "__main__":  # pragma: no cover
    main(sys.argv[1:])
