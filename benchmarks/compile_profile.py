"""What a command compiles on first use (issue 42): run one ``spctool`` command in this process with a
listener on numba's ``numba:compile`` event and print, per kernel, the CPU seconds of its compilations
(exclusive of the kernels it calls, and inclusive), the order in which the top-level ones finished, and
the command's whole wall and CPU time.  Give it an empty cache to see a first run:

    NUMBA_CACHE_DIR=$(mktemp -d) SPCTOOL_CACHE_DIR=$(mktemp -d) python benchmarks/compile_profile.py demo

(the command's own output goes to stdout, the profile to stderr).  docs/benchmarks.md "First use"
quotes its figures before and after.
"""

from __future__ import annotations

import sys
import time
from collections import defaultdict


def main(argv: list[str]) -> None:
    from numba.core import event

    start = time.perf_counter()
    records = []  # (kernel, signature, inclusive CPU s, exclusive CPU s, depth, end s)
    stack = []

    def name_of(data) -> str:
        func = getattr((data or {}).get("dispatcher"), "py_func", None)
        return f"{getattr(func, '__module__', '?')}.{getattr(func, '__name__', '?')}"

    class Listener(event.Listener):
        def on_start(self, ev) -> None:
            stack.append([name_of(ev.data), str((ev.data or {}).get("args")), time.process_time(), 0.0])

        def on_end(self, ev) -> None:
            name, sig, c0, inner = stack.pop()
            incl = time.process_time() - c0
            records.append((name, sig, incl, incl - inner, len(stack), time.perf_counter() - start))
            if stack:
                stack[-1][3] += incl

    event.register("numba:compile", Listener())
    cpu0 = time.process_time()
    from spctool.cli.main import cli

    try:
        cli.main(args=argv, prog_name="spctool", standalone_mode=False)
    except SystemExit:
        pass
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu0
    err = sys.stderr
    print("top-level kernels in the order they finished (s since start, inclusive CPU s):", file=err)
    for name, _, incl, _, depth, end in records:
        if depth == 0:
            print(f"  {end:6.1f} {incl:5.2f}  {name}", file=err)
    per = defaultdict(lambda: [0, 0.0, 0.0])
    for name, _, incl, excl, _, _ in records:
        per[name][0] += 1
        per[name][1] += incl
        per[name][2] += excl
    total = sum(r[3] for r in records)
    print(
        f"wall {wall:.1f} s, CPU {cpu:.1f} s; {len(records)} compilations, {total:.1f} s of CPU in all",
        file=err,
    )
    for name, (k, incl, excl) in sorted(per.items(), key=lambda kv: -kv[1][2]):
        print(f"  {excl:6.2f} exclusive {incl:6.2f} inclusive  x{k}  {name}", file=err)


if __name__ == "__main__":
    main(sys.argv[1:])
