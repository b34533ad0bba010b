"""Speed of the SPC text-file readers/writers (spctool.formats.sumfile / landmark / lithos / lists).

No published peer figure exists for these parsers (peers.md §6 lists none); the targets are budgets that keep
file I/O negligible next to registration: a LITHOS-sized SUM (2000 landmark rows) or LMK (2000 picture rows)
parsed and re-formatted byte-exactly in well under 50 ms.
"""

from __future__ import annotations

import time

from spctool.formats.landmark import format_lmk, parse_lmk
from spctool.formats.lists import format_pictlist, parse_pictlist
from spctool.formats.sumfile import format_sum, parse_sum

_SUM_HEAD = """\
X123456789A1
2021 MAR 04 12:34:56.789
  1024  1024   100  4095                                       NPX, NLN, THRSH
    0.5000000000D+02    0.5125000000D+03    0.5125000000D+03   MMFL, CTR
   -0.1000000000D+02    0.0000000000D+00    0.0000000000D+00   SCOBJ
    0.0000000000D+00    0.1000000000D+01    0.0000000000D+00   CX
    0.0000000000D+00    0.0000000000D+00   -0.1000000000D+01   CY
   -0.1000000000D+01    0.0000000000D+00    0.0000000000D+00   CZ
    0.8000000000D+00    0.6000000000D+00    0.0000000000D+00   SZ
 100.00000   0.00000   0.00000   0.00000 100.00000   0.00000   K-MATRIX
    0.00000D+00    0.00000D+00    0.00000D+00    0.00000D+00   DISTORTION
    0.1000000000D-01    0.1000000000D-01    0.1000000000D-01   SIGMA_VSO
    0.1000000000D-03    0.1000000000D-03    0.1000000000D-03   SIGMA_PTG
"""

_LMK_HEAD = """\
AB0001   T
      49   0.0005000                                           SIZE, SCALE(KM)
        -1        -1        -1        -1                       HORIZON
    0.2500000000D-03    0.0000000000D+00                       SIGKM, RMSLMK
    0.5000000000D+00    0.1000000000D+00    0.2000000000D+00   VLM
    0.3580574370D+00    0.7161148740D-01   -0.9309493363D+00   UX
   -0.1961161351D+00    0.9805806757D+00    0.0000000000D+00   UY
    0.9128709292D+00    0.1825741858D+00    0.3651483717D+00   UZ
    0.5000000000D-03    0.5000000000D-03    0.5000000000D-03   SIGMA_LMK
"""


def _sum_text(rows: int) -> str:
    body = ["LANDMARKS"]
    body += [
        f"{'A' + format(i, '05d'):6s}{(i % 1000) + 0.25:10.2f}{(i * 7 % 1000) + 0.5:10.2f}"
        for i in range(rows)
    ]
    body += ["LIMB FITS"] + [
        f"B{i:05d}{i % 900 + 0.5:10.2f}{i % 800 + 0.25:10.2f}{0.03:10.2f}" for i in range(200)
    ]
    return _SUM_HEAD + "\n".join(body + ["END FILE"]) + "\n"


def _lmk_text(rows: int) -> str:
    body = ["PICTURES"] + [
        f"P{i:011d}{(i % 1000) - 99.5:10.2f}{(i * 3 % 1000) + 0.75:10.2f}" for i in range(rows)
    ]
    body += ["MAP OVERLAPS", "LIMB FITS", "END FILE"]
    return _LMK_HEAD + "\n".join(body) + "\n"


def _best(fn, repeats: int = 7) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench_sum_round_trip():
    text = _sum_text(2000)

    def work():
        pic = parse_sum(text)
        pic.scobj = pic.scobj * 1.0001  # one regenerated line, as LITHOS does
        pic.landmarks[10].sample += 0.5
        assert format_sum(pic) != text

    ms = _best(work) * 1e3
    return ms, "ms", ms < 50.0


def bench_lmk_round_trip():
    text = _lmk_text(2000)

    def work():
        lmk = parse_lmk(text)
        assert format_lmk(lmk) == text

    ms = _best(work) * 1e3
    return ms, "ms", ms < 50.0


def bench_pictlist_round_trip():
    text = "".join(f" P{i:011d}\n" for i in range(20000)) + "END\n"

    def work():
        plist = parse_pictlist(text)
        assert format_pictlist(plist) == text

    ms = _best(work, 3) * 1e3
    return ms, "ms", ms < 200.0


BENCHMARKS = [
    ("sumfile parse+format, 2000 landmark rows", "< 50 ms", bench_sum_round_trip),
    ("landmark parse+format, 2000 picture rows", "< 50 ms", bench_lmk_round_trip),
    ("pictlist parse+format, 20000 pictures", "< 200 ms", bench_pictlist_round_trip),
]
