"""Long mutation-fuzz run (issue #19): >= 20,000 seeded mutants of every input format through every
command that reads it (tests/fuzz/spcfuzz.py), in chunks of 2,000 with their own master seeds, the
cumulative figures printed after each chunk:

    python benchmarks/fuzz_long.py [--mutants 20000] [--workers 2] [--json fuzz_long.json]

Target: 0 internal errors, 0 tracebacks, 0 hangs, 0 blow-ups, 0 stray warnings; the silent-misread
candidates are listed for triage.  Exit 1 when any failure was seen.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "fuzz"))

from spcfuzz import FAILURES, Report, misread_classes, run  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mutants", type=int, default=20000)
    ap.add_argument("--chunk", type=int, default=2000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", dest="json_out", default=None)
    ap.add_argument("--misread-mutants", type=int, default=500, help="per silent-misread class (issue #41)")
    a = ap.parse_args(argv)
    total = Report()
    t0 = time.perf_counter()
    done = 0
    k = 0
    while done < a.mutants:
        n = min(a.chunk, a.mutants - done)
        rep = run(n, a.workers, master=1000 + k)
        total.merge(rep)
        done += n
        k += 1
        total.elapsed_s = time.perf_counter() - t0
        c = total.counts
        print(
            f"[{done}/{a.mutants}] {total.runs} runs, {total.elapsed_s:.0f} s, "
            f"{done / total.elapsed_s:.1f} mutants/s: ok {c['ok']}, rejected {c['rejected']}, "
            + ", ".join(f"{f} {c[f]}" for f in FAILURES)
            + f"; misread candidates {len(total.misreads)}",
            flush=True,
        )
        if a.json_out:
            doc = {
                "mutants": total.mutants,
                "runs": total.runs,
                "counts": dict(total.counts),
                "elapsed_s": total.elapsed_s,
                "by_seed": {s: dict(v) for s, v in total.by_seed.items()},
                "failures": [vars(f) for f in total.failures],
                "misreads": [vars(f) for f in total.misreads],
            }
            Path(a.json_out).write_text(json.dumps(doc, indent=1, default=str))
    print(total.summary())
    classes = misread_classes(a.misread_mutants)
    print(
        "issue #41 silent-misread classes (mutants, accepted with another reading): "
        + ", ".join(f"{k} {n}/{bad}" for k, (n, bad) in classes.items()),
        flush=True,
    )
    if a.json_out:
        doc = json.loads(Path(a.json_out).read_text()) if Path(a.json_out).exists() else {}
        doc["misread_classes"] = classes
        Path(a.json_out).write_text(json.dumps(doc, indent=1, default=str))
    return 1 if total.n_failures or any(bad for _, bad in classes.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
