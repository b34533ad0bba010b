#!/usr/bin/env python
"""Run spctool's benchmarks and print each figure beside its target.

Usage::

    python benchmarks/run.py              # every benchmark
    python benchmarks/run.py camera icq   # only those whose name contains a word
    python benchmarks/run.py --json       # machine-readable

Each ``benchmarks/bench_*.py`` module defines ``BENCHMARKS = [(name, target, fn), ...]``;
``fn()`` does its own setup, times only the measured work and returns
``(value, unit, passed)``.  Every module runs in its own Python process, so settings one module
makes (numba thread counts, caches) never leak into another's figures.  Timings are kept out of
the test suite on purpose.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent


def run_module(path: Path, words: list[str]) -> list[dict]:
    """Import one benchmark module and run its (selected) benchmarks in this process."""
    rows = []
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # a broken module is reported, never hidden
        traceback.print_exc(file=sys.stderr)
        return [
            {
                "name": path.stem,
                "target": "(import failed)",
                "value": None,
                "unit": "",
                "passed": False,
                "error": repr(exc),
            }
        ]
    for name, target, fn in getattr(module, "BENCHMARKS", []):
        if words and not any(word in name for word in words):
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
    return rows


def _print_row(r: dict) -> None:
    shown = f"{r['value']:.4g} {r['unit']}" if r["value"] is not None else r.get("error", "error")
    mark = "ok  " if r["passed"] else "MISS"
    print(f"{mark} {r['name']:<58} {shown:>18}   target {r['target']}", flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("names", nargs="*", help="run only benchmarks whose name contains one of these words")
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    parser.add_argument("--module", help=argparse.SUPPRESS)  # internal: run one module, print JSON rows
    args = parser.parse_args(argv)
    if args.module:
        print(json.dumps(run_module(Path(args.module), args.names)))
        return 0
    rows: list[dict] = []
    for path in sorted(HERE.glob("bench_*.py")):
        proc = subprocess.run(
            [sys.executable, __file__, "--module", str(path), *args.names], stdout=subprocess.PIPE, text=True
        )
        try:
            found = json.loads(proc.stdout.strip().splitlines()[-1]) if proc.stdout.strip() else []
        except (json.JSONDecodeError, IndexError):
            found = [
                {
                    "name": path.stem,
                    "target": "(crashed)",
                    "value": None,
                    "unit": "",
                    "passed": False,
                    "error": f"exit code {proc.returncode}",
                }
            ]
        for r in found:
            rows.append(r)
            if not args.json:
                _print_row(r)
    failed = sum(not r["passed"] for r in rows)
    if args.json:
        print(json.dumps(rows, indent=2))
    else:
        print(f"{len(rows) - failed} of {len(rows)} benchmarks met their targets")
    return 0 if failed == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
