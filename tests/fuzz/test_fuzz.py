"""CI-sized mutation fuzz (issue #19): >= 2,000 seeded mutants of every input format through every
command that reads it, on 2 processes; no internal error, traceback, hang, blow-up or stray warning.

The long run (>= 20,000 mutants) is ``python benchmarks/fuzz_long.py``.
"""

import os

import pytest
from spcfuzz import FAILURES, MISREAD_CLASSES, misread_classes, mutate, run, seeds

N_MUTANTS = int(os.environ.get("SPCTOOL_FUZZ_MUTANTS", "2000"))


def test_mutations_are_seeded_and_reproducible():
    import random

    for s in seeds():
        data = b"P000000001A1 1.0 2.5D+00\nEND\n" if s.text else bytes(range(256)) * 4
        a = mutate(data, random.Random(f"1:{s.name}"), s)
        b = mutate(data, random.Random(f"1:{s.name}"), s)
        assert a == b


@pytest.mark.slow
def test_ci_fuzz_has_no_failures():
    report = run(N_MUTANTS, workers=2, master=19)
    print(report.summary())
    assert report.mutants == N_MUTANTS
    assert report.runs >= 2 * N_MUTANTS
    assert {k: report.counts[k] for k in FAILURES} == dict.fromkeys(FAILURES, 0), report.summary()


def test_issue_41_misread_classes_are_all_refused():
    # a 16-bit DAT cut short, a FITS with bytes inserted or removed, a landmark table row given twice
    found = misread_classes(40)
    assert set(found) == set(MISREAD_CLASSES)
    assert {k: v[1] for k, v in found.items()} == dict.fromkeys(MISREAD_CLASSES, 0), found
