#!/usr/bin/env python
"""Run spctool's benchmarks and print each figure beside its target.

Usage::

    python benchmarks/run.py              # every benchmark
    python benchmarks/run.py camera icq   # only those whose name contains a word
    python benchmarks/run.py --json       # machine-readable

Each ``benchmarks/bench_*.py`` module defines ``BENCHMARKS = [(name, target, fn), ...]``;
``fn()`` does its own setup, times only the measured work and returns
``(value, unit, passed)``.  Timings are kept out of the test suite on purpose.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent


def discover():
    for path in sorted(HERE.glob("bench_*.py")):
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        try:
            spec.loader.exec_module(module)
        except Exception as exc:  # a broken module is reported, never hidden
            yield path.stem, "(import failed)", exc
            continue
        yield from getattr(module, "BENCHMARKS", [])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("names", nargs="*", help="run only benchmarks whose name contains one of these words")
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    args = parser.parse_args(argv)
    rows = []
    failed = 0
    for name, target, fn in discover():
        if args.names and not any(word in name for word in args.names):
            continue
        if isinstance(fn, Exception):
            rows.append(
                {
                    "name": name,
                    "target": target,
                    "value": None,
                    "unit": "",
                    "passed": False,
                    "error": repr(fn),
                }
            )
            failed += 1
            continue
        try:
            value, unit, passed = fn()
            rows.append(
                {"name": name, "target": target, "value": float(value), "unit": unit, "passed": bool(passed)}
            )
        except Exception as exc:
            traceback.print_exc(file=sys.stderr)
            rows.append(
                {
                    "name": name,
                    "target": target,
                    "value": None,
                    "unit": "",
                    "passed": False,
                    "error": repr(exc),
                }
            )
        failed += not rows[-1]["passed"]
        if not args.json:
            r = rows[-1]
            shown = f"{r['value']:.4g} {r['unit']}" if r["value"] is not None else r.get("error", "error")
            mark = "ok  " if r["passed"] else "MISS"
            print(f"{mark} {r['name']:<58} {shown:>18}   target {r['target']}", flush=True)
    if args.json:
        print(json.dumps(rows, indent=2))
    else:
        print(f"{len(rows) - failed} of {len(rows)} benchmarks met their targets")
    return 0 if failed == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
