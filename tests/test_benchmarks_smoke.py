"""The benchmark suite stays runnable (``python benchmarks/run.py``): every ``benchmarks/bench_*.py``
defines its lines as ``(name, target, fn)``, and the shims that stand in for a library function keep
that function's signature — the general-path template line once raised a TypeError when ``render``
gained keywords, and printed as a MISS nobody read.  Timings stay out of the tests.

The modules run in a child process, as ``run.py`` runs them: importing them sets process-wide
settings (``NUMBA_NUM_THREADS=1``) that must not reach the other tests of a worker."""

import inspect
import json
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"

_CHILD = r"""
import importlib.util, json, sys
from pathlib import Path
out = {}
for path in sorted(Path(sys.argv[1]).glob("bench_*.py")):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    lines = module.BENCHMARKS
    out[path.stem] = [[isinstance(n, str), isinstance(t, str), callable(f), n] for n, t, f in lines]
    if path.stem == "bench_render":
        out["general"] = list(module._template_bench(fused=False)())
print(json.dumps(out))
"""


@pytest.mark.slow
def test_benchmark_modules_declare_their_lines_and_the_general_path_line_runs():
    import spctool.stages.render as rmod

    done = subprocess.run(
        [sys.executable, "-c", _CHILD, str(BENCH)], capture_output=True, text=True, timeout=600, check=False
    )
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    modules = sorted(p.stem for p in BENCH.glob("bench_*.py"))
    assert sorted(k for k in out if k.startswith("bench_")) == modules
    for stem in modules:
        lines = out[stem]
        assert lines and all(a and b and c for a, b, c, _ in lines), stem
        assert len({name for *_, name in lines}) == len(lines), stem
    # the render benchmark's general-path line: its stand-in for render accepts render's keywords
    ms, unit, ok = out["general"]
    assert unit == "ms" and ms > 0 and ok
    keywords = {
        name for name, p in inspect.signature(rmod.render).parameters.items() if p.kind == p.KEYWORD_ONLY
    }
    assert keywords == {"window", "albedo_fn", "progress", "cells", "return_cells"}
